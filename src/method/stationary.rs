//! The stationary iteration of the seed (the paper's eqs. 20–23) over the
//! set-up solver: local stage `F ← F + d D J V` and the cable projection,
//! then the global step with the coarse step. It restarts with a halved
//! automatic `d` when the iteration blows up; that `d` stays local to the
//! solve.

use crate::dd::DdSolver;
use crate::error::Result;
use crate::method::stopping::{finish, stalled, stopping_factor, DIVERGENCE_GROWTH};
use crate::method::Progress;
use crate::outcome::{Outcome, Status};
use crate::result::HistoryEntry;
use crate::settings::SearchDirection;
use std::time::Instant;

/// Restarts with a halved automatic `d` before divergence is reported.
const MAX_D_RESTARTS: usize = 3;

impl DdSolver {
    /// The seed's stationary iteration (local stage, global step, coarse
    /// step), linear and nonsmooth.
    pub(crate) fn iterate_stationary(&mut self, warm: bool, mut progress: Progress<'_>) -> Result<Outcome> {
        let t0 = Instant::now();
        if !warm {
            self.reset_unknowns();
        }
        let has_cables = self.n_cables > 0;
        let b_norm = self.load_norm();
        let mut history = Vec::with_capacity(self.opts.max_iterations.min(100_000));
        self.op.apply(&self.forces, has_cables, true);
        let mut best = f64::INFINITY;
        let mut converged = false;
        let mut iterations = 0;
        let auto_d = matches!(self.opts.search_direction, SearchDirection::Auto);
        // The step length of this solve: a halved automatic d stays here,
        // the set-up's d is the same for every solve.
        let mut d = self.d;
        let mut ended: Option<(Status, String)> = None;
        let mut restarts = 0;
        // Iteration count at the last restart (history entries after it count).
        let mut restart_at = 0;
        // One subdomain without cables: the first global step is exact.
        if !self.op.has_interfaces() && !has_cables {
            converged = true;
            history.push(HistoryEntry {
                iteration: 0,
                time_s: t0.elapsed().as_secs_f64(),
                indicator: 0.0,
                jump: None,
                cable_change: None,
            });
        }
        while !converged && iterations < self.opts.max_iterations {
            iterations += 1;
            // Local stage.
            self.op.force_stage(&mut self.forces, d);
            if has_cables {
                self.op.cable_stage();
            }
            // Global step and coarse step.
            self.op.apply(&self.forces, has_cables, true);
            let v2 = self.op.v_norm2();
            let vn = self.displacement_scale(v2.sqrt());
            let (jump2, force2) = self.op.jump_norms2();
            let jump = jump2.sqrt() / vn;
            let force_scale = self.force_scale(b_norm);
            let force = force2.sqrt() / force_scale;
            let jump = jump.max(force);
            let cable = if has_cables {
                let (dlambda2, dforce2) = self.op.cable_change2();
                let length = dlambda2.sqrt() / vn;
                let force = dforce2.sqrt() / force_scale;
                Some(length.max(force))
            } else {
                None
            };
            let indicator = jump.max(cable.unwrap_or(0.0));
            history.push(HistoryEntry {
                iteration: iterations,
                time_s: t0.elapsed().as_secs_f64(),
                indicator,
                jump: if self.op.has_interfaces() { Some(jump) } else { None },
                cable_change: cable,
            });
            if let Some(p) = progress.as_mut() {
                p(iterations, indicator);
            }
            let blew_up = !indicator.is_finite()
                || !v2.is_finite()
                || (indicator > DIVERGENCE_GROWTH * best && iterations > restart_at + 10);
            if blew_up && auto_d && restarts < MAX_D_RESTARTS {
                // The automatic d rests on an estimate of λ_max from below;
                // when it proves too large, halve it and start again.
                restarts += 1;
                d *= 0.5;
                self.reset_unknowns();
                self.op.apply(&self.forces, has_cables, true);
                best = f64::INFINITY;
                restart_at = iterations;
                continue;
            }
            if !indicator.is_finite() || !v2.is_finite() {
                ended = Some((
                    Status::Diverged,
                    "the iterate is no longer finite (NaN or Inf); lower the search direction d".into(),
                ));
                break;
            }
            if indicator > DIVERGENCE_GROWTH * best && iterations > restart_at + 10 {
                ended = Some((
                    Status::Diverged,
                    format!(
                        "the indicator grew from {best:.3e} to {indicator:.3e}; the search direction d = {d:.3e} is too large"
                    ),
                ));
                break;
            }
            best = best.min(indicator);
            let recent = &history[history.len() - (iterations - restart_at)..];
            converged = indicator <= self.opts.tolerance
                && (indicator * stopping_factor(recent) <= self.opts.tolerance || stalled(recent));
        }
        Ok(finish(self, converged, ended, iterations, history, Some(d)))
    }
}
