//! nsdd: multilevel domain decomposition for nonsmooth discrete structures.
//!
//! See the README for the method, the command line and the C ABI.
// Index loops mirror the formulas of docs/design.md in the numerical code, and
// `!(x > 0.0)` is the deliberate NaN-catching form of a positivity check.
#![allow(clippy::needless_range_loop, clippy::neg_cmp_op_on_partial_ord)]
pub mod adaptive;
pub mod algebraic;
pub mod bench;
pub mod capi;
pub mod cg_stopping;
pub mod coarse;
pub mod comm;
pub mod dd;
pub mod decomposition;
pub(crate) mod dense;
pub mod direct;
pub mod error;
pub mod factor;
pub mod generate;
pub mod kernels;
pub mod merging;
pub mod method;
pub mod model;
pub mod nonsmooth;
pub mod operator;
pub mod ordering;
pub mod outcome;
pub mod partition;
pub mod redundant;
pub mod result;
pub mod scaling;
pub mod scene;
pub mod settings;
pub mod solve;
pub mod subdomain;
pub mod vtk;

pub use error::{Error, Result};

// The README's Rust example runs as a doc-test, so it stays pasteable.
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
