//! How a solve ended: one [`Outcome`] for every method and every ending,
//! with the reason it stopped ([`Status`]) and the whole history. A
//! diverged or broken-down run is an outcome, not an error: its history is
//! kept, and the callers that must fail on it (the command line's exit
//! status, the C ABI's status code) turn it into [`crate::Error::Diverged`]
//! themselves ([`Outcome::divergence`]).

use crate::error::Error;
use crate::result::HistoryEntry;
use serde::{Deserialize, Serialize};

/// Why an iteration stopped. `#[non_exhaustive]`: methods still to come
/// (the nonsmooth CG) may add their own reasons.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
#[non_exhaustive]
pub enum Status {
    /// The stopping test passed (the direct solver always ends here).
    #[default]
    Converged,
    /// `max_iterations` ran out before the stopping test passed.
    IterationLimit,
    /// The method gave up before the limit: the indicator no longer
    /// decreases (CG: its restarts from the true residual are used up).
    Stalled,
    /// The iterate grew without bound or became NaN/Inf.
    Diverged,
    /// The method cannot continue (CG: `pᵀAp <= 0`, the direction lies in
    /// the operator's null space) short of the tolerance.
    Breakdown,
}

impl Status {
    /// The name used in the result JSON (`status`) and the messages.
    pub fn name(&self) -> &'static str {
        match self {
            Status::Converged => "converged",
            Status::IterationLimit => "iteration_limit",
            Status::Stalled => "stalled",
            Status::Diverged => "diverged",
            Status::Breakdown => "breakdown",
        }
    }

    /// Words for a sentence: "stalled", "reached the iteration limit", ...
    pub fn describe(&self) -> &'static str {
        match self {
            Status::Converged => "converged",
            Status::IterationLimit => "iteration limit reached",
            Status::Stalled => "stalled",
            Status::Diverged => "diverged",
            Status::Breakdown => "broke down",
        }
    }

    pub fn is_converged(&self) -> bool {
        *self == Status::Converged
    }
}

/// The result of one solve of a set-up solver (one load case or step).
#[derive(Debug, Clone)]
pub struct Outcome {
    /// Displacement of the free dofs.
    pub u: Vec<f64>,
    /// Cable slacks.
    pub lambda: Vec<f64>,
    pub status: Status,
    pub iterations: usize,
    /// One entry per iteration, kept whatever the ending.
    pub history: Vec<HistoryEntry>,
    /// What went wrong, for a diverged or broken-down run.
    pub message: Option<String>,
    /// The step length `d` this solve ended with (the stationary iteration
    /// only; a halved automatic `d` stays local to the solve).
    pub search_direction: Option<f64>,
    /// The nonsmooth cg's active-set steps and DD set-ups (`None` for the
    /// other methods); `iterations` counts its inner CG iterations in all.
    pub outer_steps: Option<(usize, usize)>,
    /// Element elongations measured in each element's own subdomain copy
    /// (the DD methods on a truss model; `None` otherwise). Tensions from
    /// them are in equilibrium with the interface forces; the assembled
    /// `u` averages the copies across interfaces, so with a large
    /// stiffness contrast a round-off jump of 1e-13 ‖u‖ there becomes a
    /// tension error of 1e-4 in the stiff bars beside it.
    pub elongations: Option<Vec<f64>>,
    /// The iterative refinement a linear DD solve took to bring its
    /// tensions into equilibrium with the loads (`None`: none was needed or
    /// the method has none).
    pub refinement: Option<Refinement>,
}

/// Iterative refinement of a linear DD solve: corrections solved for the
/// loads the tensions left unbalanced, on the same set-up. In the result
/// JSON as `equilibrium_refinement`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Refinement {
    /// Corrections solved.
    pub corrections: usize,
    /// Iterations the corrections took (included in the outcome's).
    pub iterations: usize,
    /// The equilibrium residual before the first correction
    /// (see [`crate::model::Model::equilibrium_residual`]).
    pub residual_before: f64,
}

impl Outcome {
    pub fn converged(&self) -> bool {
        self.status.is_converged()
    }

    /// The error a caller that cannot return a diverged state reports.
    pub fn divergence(&self) -> Option<Error> {
        (self.status == Status::Diverged).then(|| Error::Diverged {
            iteration: self.iterations,
            message: self.message.clone().unwrap_or_default(),
        })
    }
}
