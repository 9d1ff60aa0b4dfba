//! The result format of SCENE.md (`--out result.json`). Field names are a
//! public contract: add, never rename.

use crate::error::Error;
use crate::outcome::Status;
use serde::{Deserialize, Serialize};

/// One entry of the convergence history.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct HistoryEntry {
    pub iteration: usize,
    pub time_s: f64,
    /// The stopping indicator (max of the individual indicators below).
    pub indicator: f64,
    /// Relative interface jump `‖Σ B_Eᵀ C_E V_E‖ / ‖V‖`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub jump: Option<f64>,
    /// Relative change of the cable slacks `‖Δλ‖ / ‖e‖`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cable_change: Option<f64>,
}

/// Wall-clock timings in seconds.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct Timings {
    pub setup: f64,
    pub solve: f64,
    /// Where a DD set-up went (nsdd addition; absent for `direct`, and for
    /// nonsmooth cg, whose set-ups repeat per cable set).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub setup_phases: Option<SetupPhases>,
}

/// Phases of one DD set-up, in seconds; `setup` less their sum is the
/// model, the partition and the interfaces. cg's `interior` and `scaling`
/// run beside the coarse problem's factorization (part of `coarse`), so
/// with them the phases can add up to more than `setup`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SetupPhases {
    /// Subdomain assembly and factorizations, kernels included.
    pub factor: f64,
    /// cg's interior (Dirichlet) factorizations.
    pub interior: f64,
    /// cg's interface weights (the deluxe Schur blocks).
    pub scaling: f64,
    /// Macro basis, coarse operator and its factorization.
    pub coarse: f64,
    /// cg's adaptive macro columns (their interior factors and face
    /// blocks, which the deluxe weights then take over, included).
    #[serde(default)]
    pub adaptive: f64,
    /// The stationary methods' choice of `d`.
    pub search_direction: f64,
}

/// State of one load case or load step (nsdd addition).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CaseResult {
    pub name: String,
    /// Load factor for a load-path step; 1 for a load case.
    pub load_factor: f64,
    pub converged: bool,
    /// Why this solve stopped (`converged` is `status == "converged"`).
    #[serde(default)]
    pub status: Status,
    pub iterations: usize,
    pub displacements: Vec<[f64; 3]>,
    pub tensions: Vec<f64>,
    pub slack: Vec<bool>,
}

/// The whole result of `nsdd solve`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SolveResult {
    pub scene: String,
    pub method: String,
    pub effects: Vec<String>,
    pub stages: Vec<String>,
    pub converged: bool,
    /// Why the run stopped: `converged`, `iteration_limit`, `stalled`,
    /// `diverged` or `breakdown`, from the first solve (load-path steps,
    /// the top level, the load cases) that did not converge.
    #[serde(default)]
    pub status: Status,
    /// What went wrong, for a diverged or broken-down (or stalled) run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub stop_message: Option<String>,
    pub iterations: usize,
    pub subdomains: usize,
    pub displacements: Vec<[f64; 3]>,
    pub tensions: Vec<f64>,
    pub slack: Vec<bool>,
    pub history: Vec<HistoryEntry>,
    pub timings_s: Timings,
    /// The search direction `d` used by the iterative methods.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub search_direction: Option<f64>,
    /// Declared effects that were not applied, and other remarks.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
    /// Extra load cases (`[[load_cases]]`), after case 0 which is the top level.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub load_cases: Vec<CaseResult>,
    /// Load-path steps (`[load_path]`); the top level holds the last step.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub steps: Vec<CaseResult>,
    /// Subdomain id of each element (empty for the direct method).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub element_subdomain: Vec<usize>,
    /// Sizes and orderings of the sparse factors (nsdd addition; absent
    /// for nonsmooth cg, whose set-ups repeat per cable set).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub factors: Option<FactorSizes>,
    /// How far the top-level tensions miss equilibrium with its loads,
    /// `‖f − Σ_e H_e t_e − K_G u‖ / ‖t‖` at the free dofs (`K_G u`: the
    /// forces of the geometric stiffness, where simulated; nsdd addition;
    /// absent without load). A DD solve is
    /// `converged` only with this at or below its tolerance.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub equilibrium_residual: Option<f64>,
    /// The corrections a DD solve of the top level took to bring its
    /// tensions into equilibrium (nsdd addition; absent when none were
    /// needed): `corrections`, their `iterations` (included in
    /// `iterations`) and the `residual_before` them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub equilibrium_refinement: Option<crate::outcome::Refinement>,
}

/// The sparse Cholesky factors of a solve: the whole structure's (direct),
/// or every subdomain's and every Dirichlet interior's (DD), with the
/// fill-reducing ordering each got (`[solver] ordering`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct FactorSizes {
    /// Values stored in `L`, summed over the factors.
    pub nnz_l: usize,
    /// Factors ordered by nested dissection...
    pub nested_dissection: usize,
    /// ...and by AMD.
    pub amd: usize,
}

impl SolveResult {
    /// The error of a diverged run, for callers that fail on it (the
    /// command line's exit status, the C ABI's status code).
    pub fn divergence(&self) -> Option<Error> {
        (self.status == Status::Diverged).then(|| Error::Diverged {
            iteration: self.history.last().map_or(self.iterations, |h| h.iteration),
            message: self.stop_message.clone().unwrap_or_default(),
        })
    }

    /// One line on why an unconverged run stopped, e.g. "stalled after 851
    /// iterations (indicator 2.4e-5)".
    pub fn stop_summary(&self) -> String {
        let last = self.history.last().map_or(f64::NAN, |h| h.indicator);
        format!(
            "{} after {} iteration{} (indicator {last:.1e})",
            self.status.describe(),
            self.iterations,
            if self.iterations == 1 { "" } else { "s" }
        )
    }

    /// Pretty JSON text.
    pub fn to_json(&self) -> String {
        serde_json::to_string_pretty(self).expect("result serialization cannot fail")
    }
}
