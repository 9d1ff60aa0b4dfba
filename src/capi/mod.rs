//! The C ABI (`include/nsdd.h`, generated from this directory by `build.rs`
//! with cbindgen), split by concern: the status codes and handle types here,
//! the boundary (errors to status codes, the panic guard, pointer helpers)
//! in `boundary.rs`, the scene level in `scene.rs`, the algebraic level in
//! `algebraic.rs`.
//!
//! Conventions, for every exported function:
//! - names start with `nsdd_`; objects are opaque handles created by a
//!   `*_new` / `*_from_*` function and released by the matching `*_destroy`
//!   (which accepts NULL);
//! - a function that can fail returns an [`NsddStatus`]; on failure the
//!   thread's last-error message ([`nsdd_last_error_message`]) says what went
//!   wrong, naming the argument, field and index;
//! - no panic crosses the boundary: every body runs inside one guard
//!   ([`ffi_guard`]) that turns a panic into [`NsddStatus::Panic`];
//! - null pointers, wrong lengths and out-of-range indices are reported as
//!   status codes; a pointer paired with a length of 0 may be NULL;
//! - output arrays are owned by the caller, and their required length is
//!   part of each function's documentation; outputs are written only on
//!   success (except `*out` handles, which are set to NULL first).

use crate::algebraic::{AlgebraicProblem, AlgebraicSolver};
use crate::dd::DdOptions;
use crate::error::Error;
use crate::outcome::Status;
use crate::result::SolveResult;
use crate::scene::{
    ElementKind, InterfaceScaling, Method, Nodes, Preconditioner, Scene, SearchDirection, SolverSettings,
};
use crate::solve::{solve, SolveOptions};
use std::cell::RefCell;
use std::ffi::{c_char, CStr, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};

/// Status code returned by every fallible function of the C ABI.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NsddStatus {
    /// Success.
    Ok = 0,
    /// A required pointer argument was NULL.
    NullPointer = 1,
    /// An argument is out of range or an array has the wrong length.
    InvalidArgument = 2,
    /// The scene (or algebraic problem) failed validation; the message names
    /// the field and index.
    InvalidInput = 3,
    /// The scene text could not be parsed (TOML or JSON).
    ParseError = 4,
    /// A file could not be read or written.
    IoError = 5,
    /// The structure has no unique equilibrium (unsupported or a mechanism).
    Mechanism = 6,
    /// A subdomain matrix is indefinite or too badly conditioned.
    IndefiniteSubdomain = 7,
    /// The method cannot run on this problem (e.g. monolevel with a floating
    /// subdomain, or `direct` at the algebraic level).
    MethodNotApplicable = 8,
    /// The iteration diverged.
    Diverged = 9,
    /// An unexpected numerical failure.
    Numerical = 10,
    /// The handle is not in the state the call needs (e.g. `nsdd_alg_solve`
    /// before `nsdd_alg_setup`).
    NotSolved = 11,
    /// An internal error (a Rust panic) was caught at the boundary.
    Panic = 12,
}

/// Solution method (values for `nsdd_options_set_method`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NsddMethod {
    /// One sparse Cholesky of the whole structure (scene level only).
    Direct = 0,
    /// Domain decomposition without the coarse (macro) space.
    Monolevel = 1,
    /// Domain decomposition with the kernel-enriched macro space.
    Multilevel = 2,
    /// Conjugate gradient on the interface problem with the same coarse
    /// step; with unilateral cables, an active set around it.
    Cg = 3,
}

/// Preconditioner of the interface CG (values for
/// `nsdd_options_set_preconditioner`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NsddPreconditioner {
    /// Schur complement of each subdomain on its interface (default): one
    /// interior solve per subdomain and iteration, fewer iterations.
    Dirichlet = 0,
    /// The subdomain stiffness on its interface dofs; no extra factorization.
    Lumped = 1,
}

/// Automatic partitioner (values for `nsdd_options_set_partitioner`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NsddPartitioner {
    /// Recursive coordinate bisection of element midpoints (default).
    Bisection = 0,
    /// METIS k-way partition of the node graph.
    Metis = 1,
}

/// Fill-reducing ordering of the sparse factorizations (values for
/// `nsdd_options_set_ordering`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NsddOrdering {
    /// Per matrix: AMD, and nested dissection where AMD fills 8 nnz(K) or
    /// more and nested dissection saves 5 % of that (default).
    Auto = 0,
    /// Approximate minimum degree everywhere.
    Amd = 1,
    /// METIS nested dissection everywhere (interiors under 200 rows keep
    /// AMD): no AMD trial, for structures known to be 3D.
    NestedDissection = 2,
}

/// Weights of the interface CG's preconditioner across interfaces (values
/// for `nsdd_options_set_interface_scaling`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NsddInterfaceScaling {
    /// Dense weights from the subdomains' Schur complements on each
    /// interface face and on each set of dofs shared by three or more
    /// subdomains, every block exact: fewest iterations, across stiffness
    /// contrasts too; one Schur complement application per interface dof
    /// at set-up.
    Deluxe = 0,
    /// Multiplicity weights, diagonal-stiffness weights where the sides
    /// differ by more than 1000×.
    Contrast = 1,
    /// `1/m` at a dof shared by `m` subdomains.
    Multiplicity = 2,
    /// Diagonal-stiffness weights everywhere.
    Stiffness = 3,
    /// Unscaled.
    None = 4,
    /// Deluxe, with the blocks of large faces (whose exact block would
    /// cost more than about 1e8 multiply-adds) taken from the interior
    /// near the face only (default): the same weights on small
    /// subdomains, deluxe blocks 2–4× cheaper on large 3D ones.
    EconomicDeluxe = 5,
}

/// Why a solve stopped (`nsdd_result_stop_reason`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NsddStopReason {
    /// The stopping test passed (always, for the direct method).
    Converged = 0,
    /// The iteration limit ran out first.
    IterationLimit = 1,
    /// The method gave up before the limit: the indicator no longer
    /// decreases (CG's restarts used up).
    Stalled = 2,
    /// The iterate grew without bound (`nsdd_solve` returns DIVERGED
    /// instead of a result, so a result handle does not hold this value).
    Diverged = 3,
    /// The method could not continue (CG: a direction in the operator's
    /// null space) short of the tolerance.
    Breakdown = 4,
}

impl From<Status> for NsddStopReason {
    fn from(s: Status) -> NsddStopReason {
        match s {
            Status::Converged => NsddStopReason::Converged,
            Status::IterationLimit => NsddStopReason::IterationLimit,
            Status::Stalled => NsddStopReason::Stalled,
            Status::Diverged => NsddStopReason::Diverged,
            Status::Breakdown => NsddStopReason::Breakdown,
        }
    }
}

/// Element kind (values of the `kind` array of `nsdd_scene_set_elements`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NsddElementKind {
    /// Carries tension and compression.
    Bar = 0,
    /// Goes slack instead of pushing when the unilateral effect is on.
    Cable = 1,
}

/// Support mask bit: the x component is blocked.
pub const NSDD_SUPPORT_X: u8 = 1;
/// Support mask bit: the y component is blocked.
pub const NSDD_SUPPORT_Y: u8 = 2;
/// Support mask bit: the z component is blocked.
pub const NSDD_SUPPORT_Z: u8 = 4;
/// Largest number of entries of one cable column (`nsdd_alg_add_cable`).
pub const NSDD_MAX_CABLE_ENTRIES: usize = 6;

/// A scene (nodes, elements, supports, loads, effects, solver settings).
pub struct NsddScene {
    scene: Scene,
}

/// Solver settings for `nsdd_solve` and `nsdd_alg_setup`.
pub struct NsddOptions {
    opts: SolveOptions,
}

/// The result of `nsdd_solve`.
pub struct NsddResult {
    result: SolveResult,
}

/// An algebraic domain-decomposition problem assembled by the caller
/// (subdomain matrices in CSR, local-to-global maps, cables), set up once
/// and solved for any number of right-hand sides.
pub struct NsddAlgebraic {
    problem: AlgebraicProblem,
    /// Discarded by any change to the problem.
    setup: Option<AlgebraicSolver>,
}

// In this order: it is the order of the header (cbindgen follows the
// declarations).
mod boundary;

mod scene;

mod algebraic;

pub use algebraic::*;
pub use boundary::*;
pub use scene::*;
