//! Conjugate gradient on the interface problem (linear case), over the
//! set-up solver's interface operator, with its own workspace
//! (`CgWorkspace`): the direction, residual and iterate live here, not
//! in the solver's state, so the operator is applied to them directly.

use crate::cg_stopping::{self, CgStopping};
use crate::comm::Communicator;
use crate::dd::{DdSolver, FaceBlock, IfaceState, SubState};
use crate::error::Result;
use crate::method::stopping::{finish, stalled};
use crate::method::Progress;
use crate::outcome::{Outcome, Status};
use crate::result::HistoryEntry;
use crate::scaling::{self, DeluxeBlock, EntryWeights, InterfaceScaling};
use crate::subdomain::{InteriorProblem, SubdomainOperator};
use faer::Mat;
use rayon::prelude::*;
use std::time::Instant;

/// Interface CG restarts (from the true residual) when its restart monitor
/// (`DdSolver::cg_jump`) grows this much above the best since the last
/// restart...
const CG_RESTART_GROWTH: f64 = 4.0;
/// ...at most this often in one solve.
const CG_MAX_RESTARTS: usize = 10;
/// ...or when its monitor has not fallen below `CG_PROGRESS` × its best
/// for this many iterations: the recursive residual has converged while
/// the true jump stays put (seen at stiffness contrast 1e8, where the
/// recurrences drift by more than the tolerance and CG takes zero steps).
const CG_STAGNATION_WINDOW: usize = 50;
const CG_PROGRESS: f64 = 0.5;
/// Restart when the macro part `‖Pᵀ r‖` of the residual (zero in exact
/// arithmetic) exceeds this fraction of `‖r‖`.
const CG_DRIFT: f64 = 0.5;
/// Iterations between two restarts on the macro part: at the round-off
/// floor the residual is noise and its macro part is half of it as often as
/// not; a restart every iteration would only burn the restart budget.
const CG_DRIFT_SPACING: usize = 10;
/// A jump below this fraction of the displacement is round-off (a few
/// hundred ε): where the iteration stalls there, the message says so.
const ROUNDOFF_JUMP: f64 = 1e-12;

/// Scratch of the interface CG, allocated at set-up (the iteration
/// allocates nothing).
pub(crate) struct CgWorkspace {
    /// Per interface: residual (the jump), preconditioned residual and
    /// search direction.
    r: Vec<Vec<f64>>,
    z: Vec<Vec<f64>>,
    p: Vec<Vec<f64>>,
    /// Per subdomain: displacement of the current forces (the iterate).
    v: Vec<Vec<f64>>,
    /// Per interface: weights of the preconditioner's scaled jump operator
    /// `B_D` ([`crate::scaling`], set by [`DdSolver::set_interface_scaling`]).
    pub(crate) w: Vec<EntryWeights>,
    /// Per interface: the deluxe weights of its face (empty face unless the
    /// scaling is deluxe, exact or economic); they replace `w` there.
    pub(crate) deluxe: Vec<Vec<DeluxeBlock>>,
    /// Per interface: `B_D,loᵀ r` and `B_D,hiᵀ r` (entry order), the
    /// preconditioner's scaled residual on either side.
    sl: Vec<Vec<f64>>,
    sh: Vec<Vec<f64>>,
    /// Per interface: the true jump `J V` and its preconditioned value,
    /// for the force part of the indicator where the stopping test looks
    /// at it (the recursive residual `r` drifts from `J V` at round-off).
    jt: Vec<Vec<f64>>,
    zt: Vec<Vec<f64>>,
    /// Per subdomain: its parts of the stopping energies
    /// ([`DdSolver::cg_energies`]).
    energy: Vec<(f64, f64)>,
}

impl CgWorkspace {
    /// Zeroed vectors of the interface and subdomain sizes.
    pub(crate) fn new(
        interface_sizes: impl Iterator<Item = usize> + Clone,
        subdomain_sizes: impl Iterator<Item = usize>,
    ) -> CgWorkspace {
        let zeros = |s: usize| vec![0.0; s];
        let v: Vec<Vec<f64>> = subdomain_sizes.map(zeros).collect();
        CgWorkspace {
            r: interface_sizes.clone().map(zeros).collect(),
            z: interface_sizes.clone().map(zeros).collect(),
            p: interface_sizes.clone().map(zeros).collect(),
            sl: interface_sizes.clone().map(zeros).collect(),
            sh: interface_sizes.clone().map(zeros).collect(),
            jt: interface_sizes.clone().map(zeros).collect(),
            zt: interface_sizes.clone().map(zeros).collect(),
            deluxe: interface_sizes.clone().map(|_| Vec::new()).collect(),
            w: interface_sizes.map(|_| EntryWeights::default()).collect(),
            energy: vec![(0.0, 0.0); v.len()],
            v,
        }
    }
}

/// The indicator from its two parts (NaN when the jump is not finite).
fn indicator_of(jump: f64, force: f64) -> f64 {
    if jump.is_finite() {
        jump.max(force)
    } else {
        f64::NAN
    }
}

/// A CG history entry: the indicator is the jump's (no cable stage).
fn cg_entry(iteration: usize, t0: Instant, indicator: f64) -> HistoryEntry {
    HistoryEntry {
        iteration,
        time_s: t0.elapsed().as_secs_f64(),
        indicator,
        jump: Some(indicator),
        cable_change: None,
    }
}

impl DdSolver {
    /// Conjugate gradient on the interface problem (docs/design.md §6, the
    /// paper's outlook), linear case. With `S(F) = F + P f(F)` the forces
    /// after the coarse step, the operator `A F = −J V_hom(F)` satisfies
    /// `⟨F₂, A F₁⟩ = S₂ᵀ 𝔽 S₁` (`𝔽 = Σ B K⁺ Bᵀ`, `Gᵀ S = 0`), so it is
    /// symmetric positive semi-definite and CG applies; the preconditioner
    /// is `Σ_E B_E S_E B_Eᵀ` (Dirichlet) or `Σ_E B_E K_E B_Eᵀ` (lumped), see
    /// [`crate::operator::InterfaceOperator::precondition`]. One homogeneous global step (one solve per
    /// subdomain and one coarse solve) per iteration, plus one interior
    /// solve per subdomain with the Dirichlet choice; the displacement is updated by linearity, so
    /// no solve is added at the end. No allocation per iteration.
    pub(crate) fn iterate_cg(&mut self, warm: bool, progress: Progress<'_>) -> Result<Outcome> {
        // The workspace is taken out for the solve (no allocation) so that
        // the operator (`&mut self`) and the CG vectors are borrowed apart.
        let mut ws = self.cg.take().expect("the CG workspace exists when the method is cg");
        let out = self.cg_loop(&mut ws, warm, progress);
        self.cg = Some(ws);
        out
    }

    fn cg_loop(&mut self, ws: &mut CgWorkspace, warm: bool, mut progress: Progress<'_>) -> Result<Outcome> {
        let t0 = Instant::now();
        if !warm {
            self.reset_unknowns();
        }
        let b_norm = self.load_norm().max(f64::MIN_POSITIVE);
        let mut history = Vec::with_capacity(self.opts.max_iterations.min(100_000));
        let mut rz = self.cg_start(ws);
        let mut converged = !self.op.has_interfaces() || self.cg_true_indicator(ws, b_norm) == 0.0;
        if converged {
            history.push(HistoryEntry {
                iteration: 0,
                time_s: t0.elapsed().as_secs_f64(),
                indicator: 0.0,
                jump: None,
                cable_change: None,
            });
        }
        let mut iterations = 0;
        let (mut best, mut restarts, mut restart_at) = (f64::INFINITY, 0, 0);
        // Best indicator at the last clear progress, and when.
        let (mut milestone, mut milestone_at) = (f64::INFINITY, 0);
        let mut energy_terms = CgStopping::default();
        // Whether the iterate's macro part is still corrected where the
        // test would stop (see below).
        let mut correct_macro = true;
        // How the loop ended when not by the stopping test or the limit.
        let mut ended: Option<(Status, String)> = None;
        while !converged && iterations < self.opts.max_iterations {
            if rz == 0.0 {
                // The preconditioned residual vanished exactly (`z = 0`,
                // e.g. a residual at round-off that the coarse projection
                // removes whole): there is no direction left, and the next
                // `β = rz_new / rz` would be 0/0. The true indicator decides.
                (converged, ended) = self.cg_without_direction(ws, b_norm, &mut history, t0, iterations, |ind| {
                    format!(
                        "the preconditioned residual is exactly zero with the indicator at {ind:.1e}: the \
                         residual lies where the preconditioner sees nothing"
                    )
                });
                break;
            }
            iterations += 1;
            // q = A p = −J V_hom(p): the homogeneous global step with F = p
            // (V_hom(p) is left in the subdomains' `v`, `jump` = J V_hom(p)).
            self.op.apply(&ws.p, false, false);
            let pq = -self.op.dot_jump(&ws.p);
            if !(pq > 0.0) || !rz.is_finite() {
                // The operator is positive semi-definite by construction
                // (indefinite subdomains are refused at set-up), so pᵀAp ≤ 0
                // is round-off: the direction lies in its null space and CG
                // cannot reduce the residual further (e.g. the macro space
                // covers the whole interface). Stop, with the indicator
                // re-measured on the iterate deciding `converged`; only a
                // non-finite value is divergence.
                if !rz.is_finite() || !pq.is_finite() {
                    ended = Some((Status::Diverged, "the iterate is no longer finite (NaN or Inf)".into()));
                    break;
                }
                (converged, ended) = self.cg_without_direction(ws, b_norm, &mut history, t0, iterations, |_| {
                    format!("pᵀAp = {pq:.3e} <= 0: the search direction lies in the operator's null space")
                });
                // This iteration counts (its operator application was made):
                // the callback sees it like any other.
                if let (Some(p), Some(h)) = (progress.as_mut(), history.last()) {
                    p(iterations, h.indicator);
                }
                break;
            }
            let a = rz / pq;
            energy_terms.push(a * rz);
            // F += a p, r −= a q (q = −jump), V += a V_hom.
            self.forces
                .par_iter_mut()
                .zip(self.op.ifaces.par_iter())
                .zip(ws.r.par_iter_mut().zip(ws.p.par_iter()))
                .for_each(|((force, it), (cr, cp))| {
                    for ((f, r), (&p, &j)) in force.iter_mut().zip(cr.iter_mut()).zip(cp.iter().zip(&it.jump)) {
                        *f += a * p;
                        *r += a * j;
                    }
                });
            ws.v.par_iter_mut().zip(self.op.subs.par_iter()).for_each(|(cv, s)| {
                for (v, &h) in cv.iter_mut().zip(&s.v) {
                    *v += a * h;
                }
            });
            // The indicator: the true jump of the iterate, and as a force the
            // preconditioned residual, which the next direction needs anyway.
            let (jump, monitor) = self.cg_jump(ws, b_norm);
            self.op
                .precondition(&ws.r, &ws.w, &mut ws.deluxe, &mut ws.sl, &mut ws.sh, &mut ws.z);
            let lumped = self.lumped_force();
            let mut indicator = if lumped {
                monitor
            } else {
                indicator_of(jump, self.cg_force(&ws.z, b_norm))
            };
            history.push(cg_entry(iterations, t0, indicator));
            if !indicator.is_finite() {
                ended = Some((Status::Diverged, "the iterate is no longer finite (NaN or Inf)".into()));
                break;
            }
            // Where the test would stop, its force part is measured on the
            // true jump (one more application of the preconditioner): the
            // recursive residual may have drifted below it.
            let since_restart = history.len() - (iterations - restart_at);
            converged = self.cg_stops(ws, indicator, &energy_terms, restarts, &history[since_restart..]);
            if converged && !lumped {
                let (off_macro, macro_part) = self.cg_true_force_parts(ws, b_norm);
                indicator = indicator_of(jump, off_macro.hypot(macro_part));
                converged = self.cg_stops(ws, indicator, &energy_terms, restarts, &history[since_restart..]);
                if !converged && macro_part > off_macro && correct_macro {
                    // What stands between the recursive residual and the true
                    // one is the macro part that `V` carries (the coarse
                    // solves' round-off, accumulated from the first
                    // iterations): one more coarse step on the iterate
                    // removes it, and the residual is replaced by the true
                    // jump (reliable updating), rather than restarting.
                    // Where the coarse problem is so ill-conditioned that
                    // its solves' round-off is the macro part measured (the
                    // 30³ contrast tower cut in 64 with the edges'
                    // constraints: 1e-7 to 5e-5 of the loads, correction or
                    // not), corrections only cost: the first that does not
                    // halve it is the last of the solve.
                    self.cg_correct_macro_part(ws);
                    let (jump, _) = self.cg_jump(ws, b_norm);
                    let (off_after, macro_after) = self.cg_true_force_parts(ws, b_norm);
                    correct_macro = macro_after < 0.5 * macro_part;
                    indicator = indicator_of(jump, off_after.hypot(macro_after));
                    converged = self.cg_stops(ws, indicator, &energy_terms, restarts, &history[since_restart..]);
                }
                if let Some(last) = history.last_mut() {
                    last.indicator = indicator;
                    last.jump = Some(indicator);
                }
            }
            if let Some(p) = progress.as_mut() {
                p(iterations, indicator);
            }
            if converged {
                break;
            }
            if monitor < CG_PROGRESS * milestone {
                (milestone, milestone_at) = (monitor, iterations);
            }
            let grew = monitor > CG_RESTART_GROWTH * best;
            let stagnant = iterations - milestone_at > CG_STAGNATION_WINDOW;
            // A macro part of the residual (the coarse solve's round-off,
            // once large against a residual that has since fallen by orders)
            // is invisible to the preconditioner, which projects it out: CG
            // cannot reduce it and stagnates on it. Restart as soon as it
            // dominates instead of waiting for the stagnation window.
            let (m2, r2) = self.op.macro_part2(&ws.r);
            let drifted = m2.sqrt() > CG_DRIFT * r2.sqrt() && iterations - restart_at >= CG_DRIFT_SPACING;
            if grew || stagnant || drifted {
                if restarts == CG_MAX_RESTARTS {
                    let force = if lumped {
                        monitor
                    } else {
                        self.cg_true_force(ws, b_norm)
                    };
                    let floor = if jump < ROUNDOFF_JUMP && force > jump {
                        let measure = if lumped {
                            "the jump times the interface stiffness"
                        } else {
                            "the preconditioned jump"
                        };
                        format!(
                            ": the jump is at round-off ({jump:.1e} of the displacement) but the interface force \
                             error it stands for ({measure}) is {force:.1e} of the loads, a floor set by the \
                             stiffness contrast and the subdomain solves' round-off"
                        )
                    } else {
                        String::new()
                    };
                    let why = if grew {
                        format!(
                            "the residual grew again after {CG_MAX_RESTARTS} restarts from the true residual{floor}"
                        )
                    } else if drifted {
                        format!(
                            "the residual's macro part, which the preconditioner cannot reduce (round-off of the \
                             coarse solve), dominated it again after {CG_MAX_RESTARTS} restarts from the true \
                             residual{floor}"
                        )
                    } else {
                        format!(
                            "no progress over {CG_STAGNATION_WINDOW} iterations after {CG_MAX_RESTARTS} restarts \
                             from the true residual{floor}"
                        )
                    };
                    ended = Some((Status::Stalled, why));
                    break;
                }
                milestone_at = iterations;
                // The recurrences have drifted from the true operator (the
                // coarse solve is exact only to round-off, and the residual
                // fell by many orders): recompute V(F) and the residual from
                // the forces and restart from the steepest direction.
                restarts += 1;
                restart_at = iterations;
                energy_terms.reset();
                rz = self.cg_start(ws);
                best = f64::INFINITY;
                continue;
            }
            best = best.min(monitor);
            let rz_new = self.op.dot(&ws.r, &ws.z);
            let beta = rz_new / rz;
            rz = rz_new;
            ws.p.par_iter_mut().zip(ws.z.par_iter()).for_each(|(cp, cz)| {
                for (p, &z) in cp.iter_mut().zip(cz) {
                    *p = z + beta * *p;
                }
            });
        }
        for (s, cv) in self.op.subs.iter_mut().zip(&ws.v) {
            s.v.copy_from_slice(cv);
        }
        Ok(finish(self, converged, ended, iterations, history, None))
    }

    /// `out = A p = −J V_hom(p)`, the CG operator on the interface vector
    /// (interfaces one after the other): for tests of its symmetry.
    #[doc(hidden)]
    pub fn apply_interface_operator(&mut self, p: &[f64], out: &mut [f64]) {
        let mut off = 0;
        let mut forces = Vec::with_capacity(self.forces.len());
        for n in self.op.interface_sizes() {
            forces.push(p[off..off + n].to_vec());
            off += n;
        }
        self.op.apply(&forces, false, false);
        let mut off = 0;
        for it in &self.op.ifaces {
            let n = it.jump.len();
            for (o, j) in out[off..off + n].iter_mut().zip(&it.jump) {
                *o = -j;
            }
            off += n;
        }
    }

    /// (Re)starts CG from the current forces: `V = V(F)` by a global step
    /// and a coarse correction
    /// ([`InterfaceOperator::correct_macro_part`](crate::operator::InterfaceOperator::correct_macro_part)),
    /// `r = J V`, `z = M r`, `p = z`. Returns `⟨r, z⟩`.
    fn cg_start(&mut self, ws: &mut CgWorkspace) -> f64 {
        self.op.apply(&self.forces, false, true);
        // The loaded step's macro part is round-off of the whole load's
        // macro forces, out of CG's reach: one more coarse step removes it.
        self.cg_take_corrected(ws);
        for (cp, cz) in ws.p.iter_mut().zip(&ws.z) {
            cp.copy_from_slice(cz);
        }
        self.op.dot(&ws.r, &ws.z)
    }

    /// The jump part of the indicator: `‖J V‖` of the CG iterate
    /// (`ws.v`) relative to the displacement (NaN once it is not finite),
    /// and the monitor of the restarts: the larger of that and the jump
    /// times the lumped interface stiffness relative to the loads. The
    /// monitor is measured on the true jump, so it sees the recurrences
    /// drift, and it varies smoothly enough to judge progress by; as an
    /// error estimate it is 30–1 000× too large (see [`Self::cg_force`]).
    /// Leaves `jump` = `J V`.
    fn cg_jump(&mut self, ws: &CgWorkspace, b_norm: f64) -> (f64, f64) {
        self.op.jumps(Some(&ws.v));
        let v2 = self.op.norm2_subdomains(&ws.v);
        let (jump2, force2) = self.op.jump_norms2();
        if v2.is_finite() {
            let jump = jump2.sqrt() / self.displacement_scale(v2.sqrt());
            (jump, jump.max(force2.sqrt() / self.force_scale(b_norm)))
        } else {
            (f64::NAN, f64::NAN)
        }
    }

    /// The force part of the indicator from a preconditioned jump `z`:
    /// `‖z‖` relative to the forces the structure carries
    /// ([`Self::force_scale`]). The preconditioner approximates the
    /// inverse of the CG operator, so `z` estimates the error of the
    /// interface forces, which is what the tensions at the cut carry. It
    /// replaced the jump times the lumped interface stiffness, which is
    /// right for a jump that varies from dof to dof but 30–1 000× too
    /// large for the smooth jumps CG leaves and for the subdomain solves'
    /// round-off, on which it set a floor (docs/robustness.md).
    fn cg_force(&self, z: &[Vec<f64>], b_norm: f64) -> f64 {
        self.op.norm2(z).sqrt() / self.force_scale(b_norm)
    }

    /// The force part on the true jump `J V` (as [`Self::cg_jump`] leaves
    /// it): the preconditioned jump off the macro space (one application
    /// of the preconditioner) and the forces its macro part stands for,
    /// through the coarse problem (one coarse solve,
    /// [`InterfaceOperator::macro_force_error`](crate::operator::InterfaceOperator::macro_force_error)).
    /// CG leaves no macro part in the error in exact arithmetic, but where
    /// the macro space covers most of the interface the error is the
    /// coarse solve's round-off and the rest of the jump is round-off
    /// noise: dropped, that part let the README's tower at contrast 1e8 on
    /// 16 subdomains claim 1e-8 with tensions 1.4e-6 off. The
    /// preconditioner is no measure of it: on the adaptive macro columns it
    /// overstates the stiffness by their eigenvalues (the 270² plate with
    /// the adaptive space sat on a floor of 1.5e-8 that way, with its
    /// tensions as close to the direct solves as those are to each other).
    fn cg_true_force(&mut self, ws: &mut CgWorkspace, b_norm: f64) -> f64 {
        let (off_macro, macro_part) = self.cg_true_force_parts(ws, b_norm);
        off_macro.hypot(macro_part)
    }

    /// [`Self::cg_true_force`]'s two parts: the preconditioned jump off the
    /// macro space and the forces of its macro part, each relative to the
    /// forces the structure carries.
    fn cg_true_force_parts(&mut self, ws: &mut CgWorkspace, b_norm: f64) -> (f64, f64) {
        for (cj, it) in ws.jt.iter_mut().zip(&self.op.ifaces) {
            cj.copy_from_slice(&it.jump);
        }
        self.op
            .precondition(&ws.jt, &ws.w, &mut ws.deluxe, &mut ws.sl, &mut ws.sh, &mut ws.zt);
        let fm = self.op.macro_force_error();
        let scale = self.force_scale(b_norm);
        (self.op.norm2(&ws.zt).sqrt() / scale, fm / scale)
    }

    /// Residual replacement on the macro part: one more coarse step on the
    /// iterate `V` ([`InterfaceOperator::correct_macro_part`](crate::operator::InterfaceOperator::correct_macro_part)),
    /// then the residual is its true jump and the preconditioned residual
    /// is taken again (the search direction is kept). One coarse solve,
    /// one solve per subdomain and one application of the preconditioner.
    fn cg_correct_macro_part(&mut self, ws: &mut CgWorkspace) {
        for (s, cv) in self.op.subs.iter_mut().zip(&ws.v) {
            s.v.copy_from_slice(cv);
        }
        self.op.jumps(None);
        self.cg_take_corrected(ws);
    }

    /// One more coarse step on the subdomains' `V` and its jumps
    /// ([`InterfaceOperator::correct_macro_part`](crate::operator::InterfaceOperator::correct_macro_part)),
    /// taken as the iterate: `ws.v = V`, `r = J V`, `z = M r`.
    fn cg_take_corrected(&mut self, ws: &mut CgWorkspace) {
        self.op.correct_macro_part();
        for (cv, s) in ws.v.iter_mut().zip(&self.op.subs) {
            cv.copy_from_slice(&s.v);
        }
        for (cr, it) in ws.r.iter_mut().zip(&self.op.ifaces) {
            cr.copy_from_slice(&it.jump);
        }
        self.op
            .precondition(&ws.r, &ws.w, &mut ws.deluxe, &mut ws.sl, &mut ws.sh, &mut ws.z);
    }

    /// The end of a CG run with no search direction left (`rz = 0`, or
    /// `pᵀAp ≤ 0`): the indicator re-measured on the iterate decides
    /// `converged`; otherwise a breakdown, `why(indicator)`.
    fn cg_without_direction(
        &mut self,
        ws: &mut CgWorkspace,
        b_norm: f64,
        history: &mut Vec<HistoryEntry>,
        t0: Instant,
        iterations: usize,
        why: impl FnOnce(f64) -> String,
    ) -> (bool, Option<(Status, String)>) {
        let indicator = self.cg_true_indicator(ws, b_norm);
        history.push(cg_entry(iterations, t0, indicator));
        if indicator <= self.opts.tolerance {
            (true, None)
        } else {
            (false, Some((Status::Breakdown, why(indicator))))
        }
    }

    /// The indicator of the CG iterate measured on its true jump.
    fn cg_true_indicator(&mut self, ws: &mut CgWorkspace, b_norm: f64) -> f64 {
        let (jump, monitor) = self.cg_jump(ws, b_norm);
        if self.lumped_force() {
            monitor
        } else {
            indicator_of(jump, self.cg_true_force(ws, b_norm))
        }
    }

    /// Whether the indicator's force part is the lumped force `k ∘ J V`
    /// (stiffness spread from [`cg_stopping::LUMPED_FORCE_SPREAD`] on)
    /// rather than the preconditioned jump.
    pub(crate) fn lumped_force(&self) -> bool {
        self.stats.stiffness_spread >= cg_stopping::LUMPED_FORCE_SPREAD
    }

    /// The stopping test (Status::Converged either way): the energy error
    /// estimate from the CG coefficients is certified
    /// ([`crate::cg_stopping`], computed only once the indicator is
    /// close); or, with the indicator itself below the tolerance, restarts
    /// or a stall (`since_restart`, the history since the last restart)
    /// show the residual is on the floor that round-off allows. A loose
    /// solve (`certify` off) stops on the indicator alone. Needs `jump` =
    /// `J V`.
    fn cg_stops(
        &mut self,
        ws: &mut CgWorkspace,
        indicator: f64,
        energy_terms: &CgStopping,
        restarts: usize,
        since_restart: &[HistoryEntry],
    ) -> bool {
        let tol = self.opts.tolerance;
        (!self.certify && indicator <= tol)
            || cg_stopping::indicator_allows(indicator, tol) && {
                let (jump_energy, load_energy) = self.cg_energies(ws);
                energy_terms.tail().is_some_and(|tail| {
                    cg_stopping::certified(cg_stopping::relative_energy_error(jump_energy, tail, load_energy), tol)
                })
            }
            || (indicator <= tol && (restarts >= 2 || stalled(since_restart)))
    }

    /// Weights of the CG preconditioner's scaled jump operator `B_D`
    /// ([`crate::scaling`]; the settings' `interface_scaling`, default
    /// [`InterfaceScaling::default`]). For comparisons; later solves use
    /// them. Set-up cost only (allocates); the deluxe blocks take one
    /// application of the subdomain's Schur complement (of `K_E` with the
    /// lumped preconditioner) per face dof, so the Dirichlet interior
    /// problems must be factored first. Without the CG workspace (another
    /// method) there is nothing to set.
    pub fn set_interface_scaling(&mut self, kind: InterfaceScaling) {
        if self.cg.is_none() {
            return;
        }
        let layout = DeluxeLayout::new(
            &self.op.ifaces,
            &self.dof_maps,
            &self.multiplicity,
            self.op.comm.owned(),
            kind,
        );
        let blocks = subdomain_blocks(
            self.op.subs.iter_mut().map(BlockSource::of).collect(),
            &self.op.ifaces,
            &layout,
            kind,
        );
        self.finish_interface_scaling(kind, layout, blocks);
    }

    /// [`Self::set_interface_scaling`] from the subdomains' blocks, computed
    /// by [`subdomain_blocks`] on `layout` (the set-up computes them beside
    /// the coarse problem): the weights, the neighbours' blocks where they
    /// live on another process, and the deluxe blocks of every interface.
    pub(crate) fn finish_interface_scaling(
        &mut self,
        kind: InterfaceScaling,
        layout: DeluxeLayout,
        blocks: SubdomainBlocks,
    ) {
        let Some(ws) = self.cg.as_mut() else {
            return;
        };
        let entries = interface_entries(&self.op.ifaces);
        let mult = &self.multiplicity;
        let held = self.op.comm.owned();
        let first = held.start;
        let diag: Vec<Vec<f64>> = match kind {
            InterfaceScaling::Stiffness
            | InterfaceScaling::Contrast
            | InterfaceScaling::Deluxe
            | InterfaceScaling::EconomicDeluxe => {
                let own: Vec<Vec<f64>> = self.op.subs.iter().map(|s| s.op.diagonal()).collect();
                if held.len() == self.dof_maps.len() {
                    own
                } else {
                    // Spread over processes: the neighbours' diagonals on
                    // the shared entries are all the weights read of them
                    // (every subdomain sharing a dof with one held here
                    // has an interface with it); the rest stays unknown.
                    let ifaces = &self.op.ifaces;
                    let sides = self.op.comm.exchange(|i, is_lo| {
                        let it = &ifaces[i];
                        let (s, idx) = if is_lo {
                            (it.lo, &it.lo_idx)
                        } else {
                            (it.hi, &it.hi_idx)
                        };
                        idx.iter().map(|&l| own[s - first][l as usize]).collect()
                    });
                    let mut full: Vec<Vec<f64>> = self.dof_maps.iter().map(|d| vec![f64::NAN; d.len()]).collect();
                    for (it, [lo, hi]) in ifaces.iter().zip(&sides) {
                        for (j, &v) in lo.iter().enumerate() {
                            full[it.lo][it.lo_idx[j] as usize] = v;
                        }
                        for (j, &v) in hi.iter().enumerate() {
                            full[it.hi][it.hi_idx[j] as usize] = v;
                        }
                    }
                    for (k, d) in own.into_iter().enumerate() {
                        full[first + k] = d;
                    }
                    full
                }
            }
            _ => Vec::new(),
        };
        ws.w = scaling::interface_weights(&entries, &self.dof_maps, mult, &diag, kind);
        drop(entries);
        self.stats.near_blocks = 0;
        let DeluxeLayout { faces, edges, .. } = layout;
        let Some(edges) = edges.filter(|_| kind.is_deluxe()) else {
            ws.deluxe.iter_mut().for_each(Vec::clear);
            return;
        };
        let SubdomainBlocks {
            blocks,
            taken_over,
            near,
        } = blocks;
        self.stats.face_blocks_reused = taken_over;
        self.stats.near_blocks = near;
        let ifaces = &self.op.ifaces;
        let mut side: Vec<[Option<&Mat<f64>>; 2]> = vec![[None, None]; self.op.ifaces.len()];
        for (s, (b, _)) in self.op.subs.iter().zip(&blocks) {
            for (&(i, is_lo), (_, m)) in s.ifaces.iter().zip(b) {
                if m.nrows() > 0 {
                    side[i][usize::from(!is_lo)] = Some(m);
                }
            }
        }
        // Each edge's blocks, by its subdomains: the diagonal blocks of the
        // held subdomains' edge blocks.
        let mut edge_side: Vec<Vec<Option<Mat<f64>>>> =
            edges.edges.iter().map(|e| vec![None; e.subdomains.len()]).collect();
        for (k, (_, (_, b))) in blocks.iter().enumerate() {
            if b.nrows() == 0 {
                continue;
            }
            let mut at = 0;
            for &e in &edges.of_subdomain[first + k] {
                let edge = &edges.edges[e];
                let n = edge.rows[0].len();
                let m = edge
                    .subdomains
                    .binary_search(&(first + k))
                    .expect("an edge lists its subdomains");
                edge_side[e][m] = Some(b.submatrix(at, at, n, n).to_owned());
                at += n;
            }
        }
        // The neighbours' blocks where they live on another process.
        let remote_faces: Vec<[Mat<f64>; 2]> = if held.len() == self.dof_maps.len() {
            Vec::new()
        } else {
            exchange_deluxe_blocks(&self.op.comm, ifaces, &edges, &side, &mut edge_side)
        };
        for (i, [lo, hi]) in remote_faces.iter().enumerate() {
            for (k, m) in [(0, lo), (1, hi)] {
                if side[i][k].is_none() && m.nrows() > 0 {
                    side[i][k] = Some(m);
                }
            }
        }
        // Each edge's weights `D_j`, in the order of its subdomains, where a
        // subdomain of it is held here and every block is known.
        let edge_weights: Vec<Option<Vec<Vec<f64>>>> = edges
            .edges
            .par_iter()
            .zip(edge_side.par_iter())
            .map(|(edge, blocks)| {
                let here = edge.subdomains.iter().any(|s| held.contains(s));
                let sides: Option<Vec<_>> = blocks.iter().map(|b| b.as_ref().map(Mat::as_ref)).collect();
                // A failed eigensolve leaves the pointwise weights there.
                sides.filter(|_| here).and_then(|s| DeluxeBlock::edge_weights(&s))
            })
            .collect();
        ws.deluxe = faces
            .into_par_iter()
            .zip(side.par_iter())
            .enumerate()
            .map(|(i, (face, [lo, hi]))| {
                let mut out = Vec::new();
                if let (Some(lo), Some(hi)) = (lo, hi) {
                    if !face.is_empty() && lo.nrows() == face.len() && hi.nrows() == face.len() {
                        // A failed eigensolve leaves the pointwise weights there.
                        out.extend(DeluxeBlock::face(face, lo.as_ref(), hi.as_ref()));
                    }
                }
                let it = &ifaces[i];
                for (e, entries) in &edges.of_interface[i] {
                    let subs = &edges.edges[*e].subdomains;
                    if let (Some(w), Ok(a), Ok(b)) = (
                        &edge_weights[*e],
                        subs.binary_search(&it.lo),
                        subs.binary_search(&it.hi),
                    ) {
                        // The lo side takes the hi subdomain's share, and the
                        // hi side the lo one's.
                        out.push(DeluxeBlock::new(entries.clone(), w[a].clone(), w[b].clone()));
                    }
                }
                out
            })
            .collect();
        // A set-up that keeps its Schur blocks for the next one
        // (`DdSolver::new_pooled`) takes them over here, without a copy.
        for (s, (b, e)) in self.op.subs.iter_mut().zip(blocks) {
            if let (Some(kept), true) = (s.face_blocks.as_mut(), s.interior.is_some()) {
                kept.extend(b.into_iter().chain([e]).filter(|(_, m)| m.nrows() > 0));
            }
        }
    }

    /// The energies of the CG stopping test ([`crate::cg_stopping`]) for
    /// the iterate `ws.v`, with `jump` = `J ws.v` (as [`Self::cg_jump`]
    /// leaves it): `J = Σ_E (ū_E − v_E)ᵀ K_E (ū_E − v_E)`, the strain energy
    /// that averaging the copies adds (`ū − v_E` at a dof of multiplicity
    /// `m` is `1/m` of the signed sum of its pair jumps), and `E = Σ_E b_Eᵀ
    /// v_E`, the work of the loads (`‖u*‖_K²` at convergence). One product
    /// with `K_E` per subdomain; no allocation.
    fn cg_energies(&mut self, ws: &mut CgWorkspace) -> (f64, f64) {
        self.op.jump_energies(&ws.v, &mut ws.energy)
    }
}

/// Each interface's subdomains and entries, as [`crate::scaling`] reads them.
fn interface_entries(ifaces: &[IfaceState]) -> Vec<scaling::InterfaceEntries<'_>> {
    ifaces
        .iter()
        .map(|it| scaling::InterfaceEntries {
            lo: it.lo,
            hi: it.hi,
            lo_idx: &it.lo_idx,
            hi_idx: &it.hi_idx,
        })
        .collect()
}

/// Where the deluxe blocks sit: each interface's face entries (dofs shared
/// by its two sides only), the edges (dofs shared by three or more
/// subdomains) and, per held subdomain, the rows of its edges' dofs, edge
/// after edge, with each edge's length. Cheap; computed before the blocks.
pub(crate) struct DeluxeLayout {
    faces: Vec<Vec<u32>>,
    /// `None` without deluxe scaling.
    edges: Option<scaling::Edges>,
    edge_rows: Vec<(Vec<u32>, Vec<usize>)>,
}

impl DeluxeLayout {
    /// The layout of `kind` on `ifaces`, for the subdomains `held`, with
    /// every subdomain's dofs and multiplicities.
    pub(crate) fn new(
        ifaces: &[IfaceState],
        dof_maps: &[Vec<usize>],
        mult: &[Vec<u32>],
        held: std::ops::Range<usize>,
        kind: InterfaceScaling,
    ) -> DeluxeLayout {
        let faces: Vec<Vec<u32>> = ifaces
            .iter()
            .map(|it| {
                let m = &mult[it.lo];
                (0..it.lo_idx.len() as u32)
                    .filter(|&j| kind.is_deluxe() && m[it.lo_idx[j as usize] as usize] == 2)
                    .collect()
            })
            .collect();
        if !kind.is_deluxe() {
            return DeluxeLayout {
                faces,
                edges: None,
                edge_rows: Vec::new(),
            };
        }
        let edges = scaling::Edges::new(&interface_entries(ifaces), dof_maps, mult);
        let edge_rows = held
            .map(|s| {
                let mut rows = Vec::new();
                let mut lens = Vec::new();
                for &e in &edges.of_subdomain[s] {
                    let edge = &edges.edges[e];
                    let m = edge.subdomains.binary_search(&s).expect("an edge lists its subdomains");
                    rows.extend_from_slice(&edge.rows[m]);
                    lens.push(edge.rows[m].len());
                }
                (rows, lens)
            })
            .collect();
        DeluxeLayout {
            faces,
            edges: Some(edges),
            edge_rows,
        }
    }
}

/// What a held subdomain's deluxe blocks are computed from, borrowed apart
/// from the rest of its state, so that the set-up can compute them beside
/// the coarse problem (which reads the operators too).
pub(crate) struct BlockSource<'a> {
    pub(crate) op: &'a SubdomainOperator,
    pub(crate) ifaces: &'a [(usize, bool)],
    /// Its interface dofs (local, increasing).
    pub(crate) iface_dofs: &'a [u32],
    /// The Dirichlet interior problem (`None`: lumped blocks of `K_E`).
    pub(crate) interior: &'a mut Option<InteriorProblem>,
    /// Blocks a pooled set-up kept (`None`: none kept).
    pub(crate) face_blocks: &'a mut Option<Vec<FaceBlock>>,
}

impl<'a> BlockSource<'a> {
    pub(crate) fn of(s: &'a mut SubState) -> BlockSource<'a> {
        BlockSource {
            op: &s.op,
            ifaces: &s.ifaces,
            iface_dofs: &s.iface_dofs,
            interior: &mut s.interior,
            face_blocks: &mut s.face_blocks,
        }
    }
}

/// What cg's preconditioner needs of each held subdomain, computed before
/// the solver is assembled (beside the coarse problem): its Dirichlet
/// interior factor, then its deluxe blocks.
pub(crate) struct Preconditioning {
    /// Whether every interior factor was made (the first failure).
    pub(crate) interiors: Result<()>,
    pub(crate) interior_s: f64,
    pub(crate) blocks: SubdomainBlocks,
    pub(crate) blocks_s: f64,
}

impl Default for Preconditioning {
    fn default() -> Preconditioning {
        Preconditioning {
            interiors: Ok(()),
            interior_s: 0.0,
            blocks: SubdomainBlocks::default(),
            blocks_s: 0.0,
        }
    }
}

impl Preconditioning {
    /// Factors the interiors the subdomains lack (with `dirichlet`), then
    /// computes their blocks on `layout`. No communication: the caller
    /// agrees on `interiors` with the other processes.
    pub(crate) fn prepare(
        mut sources: Vec<BlockSource<'_>>,
        ifaces: &[IfaceState],
        layout: &DeluxeLayout,
        kind: InterfaceScaling,
        dirichlet: bool,
    ) -> Preconditioning {
        let t = Instant::now();
        let interiors = if dirichlet {
            sources.par_iter_mut().try_for_each(|s| -> Result<()> {
                if s.interior.is_none() {
                    *s.interior = Some(InteriorProblem::new(s.op, s.iface_dofs)?);
                }
                Ok(())
            })
        } else {
            Ok(())
        };
        let interior_s = t.elapsed().as_secs_f64();
        if interiors.is_err() {
            return Preconditioning {
                interiors,
                interior_s,
                ..Preconditioning::default()
            };
        }
        let t = Instant::now();
        let blocks = subdomain_blocks(sources, ifaces, layout, kind);
        Preconditioning {
            interiors,
            interior_s,
            blocks,
            blocks_s: t.elapsed().as_secs_f64(),
        }
    }
}

/// Each held subdomain's face blocks (one per interface, in its order) and
/// edge block, with how many were taken over from a pooled set-up and how
/// many were computed from the interior near them only.
#[derive(Default)]
pub(crate) struct SubdomainBlocks {
    blocks: Vec<(Vec<FaceBlock>, FaceBlock)>,
    taken_over: usize,
    near: usize,
}

/// The subdomains' blocks of their Schur complements on the deluxe layout,
/// one column per face dof: `S_E e_l` restricted to the face; then the
/// block of all its edge dofs, whose diagonal blocks are the edges'. In
/// parallel over the subdomains, no communication; nothing without deluxe
/// scaling.
pub(crate) fn subdomain_blocks(
    sources: Vec<BlockSource<'_>>,
    ifaces: &[IfaceState],
    layout: &DeluxeLayout,
    kind: InterfaceScaling,
) -> SubdomainBlocks {
    if layout.edges.is_none() || !kind.is_deluxe() {
        return SubdomainBlocks::default();
    }
    let faces = &layout.faces;
    let taken_over = std::sync::atomic::AtomicUsize::new(0);
    let near = std::sync::atomic::AtomicUsize::new(0);
    let economic = kind == InterfaceScaling::EconomicDeluxe;
    let blocks = sources
        .into_par_iter()
        .zip(layout.edge_rows.par_iter())
        .map(|(s, erows)| {
            // Kept blocks of faces this set-up no longer has are dropped.
            let mut earlier = s.face_blocks.as_mut().map(std::mem::take).unwrap_or_default();
            let interior = s.interior;
            // `parts`: the lengths of the pieces of `rows` whose blocks
            // are wanted (the edges of the edge block); the blocks
            // between pieces are not used.
            let mut block_of = |rows: Vec<u32>, parts: &[usize]| -> FaceBlock {
                if rows.is_empty() {
                    return (rows, Mat::zeros(0, 0));
                }
                let Some(ip) = interior.as_mut() else {
                    // Lumped: the block of K_E.
                    return (Vec::new(), s.op.principal_block(&rows));
                };
                // A set-up that took this subdomain over may hold the
                // block already.
                let b = match earlier.iter().position(|(r, _)| *r == rows) {
                    Some(k) => {
                        taken_over.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        earlier.swap_remove(k).1
                    }
                    // A failure (out of memory) leaves these dofs
                    // without deluxe weights.
                    None if economic => near_blocks(ip, s.op, &rows, parts, &near).unwrap_or_else(|_| Mat::zeros(0, 0)),
                    None => ip.schur_block(s.op, &rows).unwrap_or_else(|_| Mat::zeros(0, 0)),
                };
                (rows, b)
            };
            let face_blocks = s
                .ifaces
                .iter()
                .map(|&(i, is_lo)| {
                    let it = &ifaces[i];
                    let idx = if is_lo { &it.lo_idx } else { &it.hi_idx };
                    let rows: Vec<u32> = faces[i].iter().map(|&f| idx[f as usize]).collect();
                    let len = rows.len();
                    block_of(rows, &[len])
                })
                .collect();
            let edge_block = block_of(erows.0.clone(), &erows.1);
            if let Some(ip) = interior.as_mut() {
                ip.release_face_scratch();
            }
            (face_blocks, edge_block)
        })
        .collect();
    SubdomainBlocks {
        blocks,
        taken_over: taken_over.into_inner(),
        near: near.into_inner(),
    }
}

/// The deluxe blocks of the neighbours held by another process: each side
/// sends its face block, then its blocks of the interface's edges (every
/// subdomain of an edge has an interface with every other), each as its
/// order and its entries (order 0: none). Returns each interface's two face
/// blocks as received and fills in the edge blocks missing from
/// `edge_side`. Set-up only (allocates).
fn exchange_deluxe_blocks(
    comm: &impl Communicator,
    ifaces: &[IfaceState],
    edges: &scaling::Edges,
    side: &[[Option<&Mat<f64>>; 2]],
    edge_side: &mut [Vec<Option<Mat<f64>>>],
) -> Vec<[Mat<f64>; 2]> {
    let put = |out: &mut Vec<f64>, m: Option<&Mat<f64>>| match m {
        Some(m) => {
            out.push(m.nrows() as f64);
            out.extend((0..m.ncols()).flat_map(|j| m.col(j).iter().copied()));
        }
        None => out.push(0.0),
    };
    let sides = comm.exchange(|i, is_lo| {
        let it = &ifaces[i];
        let s = if is_lo { it.lo } else { it.hi };
        let mut out = Vec::new();
        put(&mut out, side[i][usize::from(!is_lo)]);
        for &(e, _) in &edges.of_interface[i] {
            let m = edges.edges[e]
                .subdomains
                .binary_search(&s)
                .expect("an edge lists its subdomains");
            put(&mut out, edge_side[e][m].as_ref());
        }
        out
    });
    // Blocks in the order sent, until the payload ends (an empty
    // payload: an interface without a subdomain here).
    let take = |p: &[f64], at: &mut usize| -> Option<Mat<f64>> {
        let n = *p.get(*at)? as usize;
        *at += 1;
        let data = p.get(*at..*at + n * n)?;
        *at += n * n;
        (n > 0).then(|| Mat::from_fn(n, n, |a, b| data[b * n + a]))
    };
    let mut faces_in = Vec::with_capacity(sides.len());
    for (i, ps) in sides.iter().enumerate() {
        let it = &ifaces[i];
        let mut two: [Mat<f64>; 2] = [Mat::zeros(0, 0), Mat::zeros(0, 0)];
        for (k, (p, s)) in ps.iter().zip([it.lo, it.hi]).enumerate() {
            let mut at = 0;
            if let Some(m) = take(p, &mut at) {
                two[k] = m;
            }
            for &(e, _) in &edges.of_interface[i] {
                let m = edges.edges[e]
                    .subdomains
                    .binary_search(&s)
                    .expect("an edge lists its subdomains");
                if let Some(b) = take(p, &mut at) {
                    edge_side[e][m].get_or_insert(b);
                }
            }
        }
        faces_in.push(two);
    }
    faces_in
}

/// The block of `rows` (local) of a subdomain's Schur complement, for the
/// pieces of `rows` (`parts`: their lengths; the blocks between pieces are
/// not used): each piece's by [`InteriorProblem::schur_block_near`] where
/// that pays (counted in `near`), the other pieces' together by one exact
/// [`InteriorProblem::schur_block`], as the exact deluxe weights do, so
/// that where no piece pays the block is theirs to the bit.
///
/// [`InteriorProblem::schur_block_near`]: crate::subdomain::InteriorProblem::schur_block_near
/// [`InteriorProblem::schur_block`]: crate::subdomain::InteriorProblem::schur_block
fn near_blocks(
    ip: &mut crate::subdomain::InteriorProblem,
    op: &crate::subdomain::SubdomainOperator,
    rows: &[u32],
    parts: &[usize],
    near: &std::sync::atomic::AtomicUsize,
) -> Result<Mat<f64>> {
    let mut b = Mat::<f64>::zeros(rows.len(), rows.len());
    // The pieces left to the exact block: (offset in `rows`, length).
    let mut exact = Vec::new();
    let mut at = 0;
    for &len in parts {
        match ip.schur_block_near(op, &rows[at..at + len])? {
            Some(block) => {
                near.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                b.submatrix_mut(at, at, len, len).copy_from(&block);
            }
            None => exact.push((at, len)),
        }
        at += len;
    }
    if exact.len() == parts.len() {
        return ip.schur_block(op, rows);
    }
    let exact_rows: Vec<u32> = exact
        .iter()
        .flat_map(|&(at, len)| rows[at..at + len].iter().copied())
        .collect();
    let e = ip.schur_block(op, &exact_rows)?;
    let mut from = 0;
    for (at, len) in exact {
        b.submatrix_mut(at, at, len, len)
            .copy_from(e.submatrix(from, from, len, len));
        from += len;
    }
    Ok(b)
}
