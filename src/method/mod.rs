//! The methods, each a loop over the set-up solver ([`crate::dd::DdSolver`])
//! with its own workspace, sharing the stopping tests of [`stopping`]. A
//! method touches the set-up only through the interface operator
//! ([`crate::operator::InterfaceOperator`]: apply, force stage,
//! preconditioner, sums), never another subdomain's vectors: those cross
//! the communication seam ([`crate::comm`]). A new method is a new module
//! here; it does not touch the others.

pub mod cg;
pub mod stationary;
pub mod stopping;
