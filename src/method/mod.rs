//! The methods, each a loop over the set-up solver ([`crate::dd::DdSolver`]:
//! subdomain operators, coarse problem, interface operator) with its own
//! workspace, sharing the stopping tests of [`stopping`]. A new method is a
//! new module here; it does not touch the others.

pub mod cg;
pub mod stationary;
pub mod stopping;
