//! The stopping tests and the ending of a method's loop, shared by every
//! method (the stationary iteration, CG, and the ones to come).

use crate::dd::DdSolver;
use crate::outcome::{Outcome, Status};
use crate::result::HistoryEntry;

/// Indicator growth over the best value seen that counts as divergence.
pub const DIVERGENCE_GROWTH: f64 = 1e6;

/// Iterations over which the contraction factor `ρ` of the indicator is
/// measured for the stopping test.
pub const CONTRACTION_WINDOW: usize = 10;

/// Largest `ρ` used in the stopping test (caps the safety factor
/// `1 / (1 − ρ)` at 100).
pub const CONTRACTION_CAP: f64 = 0.99;

/// Safety factor `1 / (1 − ρ)` of the stopping test. The indicator of a
/// stationary iteration measures the last step (an interface residual, a
/// change of `λ`), not the distance to the solution; for a linear
/// contraction with factor `ρ` that distance is up to `1 / (1 − ρ)` times
/// larger. Stopping on `indicator` alone left slowly converging runs 10-35×
/// the tolerance away from the direct solution (docs/robustness.md).
/// `history` holds the indicators so far, the current one last; `ρ` is the
/// geometric mean ratio over the last [`CONTRACTION_WINDOW`] iterations
/// (fewer at the start; 0.5 with a single value), clamped to
/// `[0, CONTRACTION_CAP]`.
pub fn stopping_factor(history: &[HistoryEntry]) -> f64 {
    let n = history.len();
    let rho = if n < 2 {
        0.5
    } else {
        let w = (n - 1).min(CONTRACTION_WINDOW);
        let (now, then) = (history[n - 1].indicator, history[n - 1 - w].indicator);
        if then > 0.0 && now >= 0.0 {
            (now / then).powf(1.0 / w as f64)
        } else {
            CONTRACTION_CAP
        }
    };
    1.0 / (1.0 - rho.clamp(0.0, CONTRACTION_CAP))
}

/// Whether the indicator made no net progress over the last
/// [`CONTRACTION_WINDOW`] iterations: it sits on the floor that round-off
/// allows, so an indicator already below the tolerance is accepted there.
pub fn stalled(history: &[HistoryEntry]) -> bool {
    let n = history.len();
    n > CONTRACTION_WINDOW && history[n - 1].indicator >= history[n - 1 - CONTRACTION_WINDOW].indicator
}

/// The outcome of a finished loop over the set-up solver: the assembled
/// displacement and slacks, with the status from `converged` and the reason
/// the loop broke off (`ended`; none: the iteration limit).
pub fn finish(
    solver: &DdSolver,
    converged: bool,
    ended: Option<(Status, String)>,
    iterations: usize,
    history: Vec<HistoryEntry>,
    search_direction: Option<f64>,
) -> Outcome {
    let (u, lambda) = solver.assemble();
    let (status, message) = match (converged, ended) {
        (true, _) => (Status::Converged, None),
        (false, Some((status, message))) => (status, Some(message)),
        (false, None) => (Status::IterationLimit, None),
    };
    Outcome {
        u,
        lambda,
        status,
        iterations,
        history,
        message,
        search_direction,
        outer_steps: None,
        elongations: None,
        refinement: None,
    }
}
