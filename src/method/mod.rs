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

/// A callback told `(iteration, indicator)` after every iteration. It runs
/// on one of the solver's worker threads (see `on_workers`), hence `Send`.
pub type Progress<'a> = Option<&'a mut (dyn FnMut(usize, f64) + Send)>;

/// Runs `f` on a worker thread of the current rayon pool (at once if this
/// thread is one already) when `in_process`, else on this thread. The
/// solves and set-ups start here (`solve::solve_in`, `DdSolver`'s set-ups
/// and `solve`, the nonsmooth cg's active set). Under
/// MPI the thread that drives a solve is the one that calls MPI, which is
/// initialised with `MPI_THREAD_FUNNELED`.
///
/// Why: a parallel loop started from outside the pool hands its work to
/// the pool and sleeps until it is done (futex calls and a thread wake-up
/// each time); an iteration runs about ten such loops, so on small
/// structures the hand-overs cost far more than the work (the bundled 8×8
/// grid's `monolevel` solve: 2.3 s, 3.5 s of CPU of it in the kernel,
/// against 0.18 s from a worker). Started from a worker, the loops split
/// their work in place, with the same bits.
pub(crate) fn on_workers<R: Send>(in_process: bool, f: impl FnOnce() -> R + Send) -> R {
    if in_process {
        rayon::scope(|_| f())
    } else {
        f()
    }
}
