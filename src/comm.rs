//! The communication seam: every operation of the iteration that crosses
//! subdomains goes through [`Communicator`], so the methods
//! ([`crate::method`]) and the interface operator ([`crate::operator`])
//! never read another subdomain's vectors themselves.
//!
//! The operations (docs/design.md §8):
//! - **neighbour traces** ([`Communicator::neighbour_traces`]): an
//!   interface combines the traces of its two subdomains (a jump, a force
//!   update, the preconditioner's scaled jump). Interface vectors (forces,
//!   jumps, CG directions) are held by both sides, so a subdomain reads its
//!   interfaces' vectors without communication.
//! - **global sums** ([`Communicator::sum_interfaces`],
//!   [`Communicator::sum_subdomains`]): norms and dot products, summed in
//!   interface or subdomain order whatever the threads (or ranks), so results
//!   are deterministic.
//! - **the coarse step** ([`Communicator::coarse_solve`]): the coarse
//!   right-hand side is assembled from each interface's and subdomain's part,
//!   solved, and its solution made readable to every subdomain.
//! - **global vectors** ([`Communicator::assemble`]): the summed load and
//!   the averaged displacement, once per solve.
//!
//! [`Threads`] implements it for subdomains that all live in this process
//! (rayon): the neighbour's vector is read in place, nothing is copied. An
//! MPI rank owning a block of subdomains would keep ghost buffers for the
//! neighbour subdomains it does not own, fill their interface entries by
//! point-to-point messages with the rank sharing the interface before
//! calling the closure, compute only the interfaces (and sums) it owns, and
//! reduce the per-interface/per-subdomain parts in global order.

use crate::coarse::CoarseProblem;
use rayon::prelude::*;

/// The cross-subdomain operations of the iteration (see the module
/// documentation). Indices are positions in this process's vectors:
/// `subs[s]` its subdomains, `items[i]` its interfaces (for [`Threads`],
/// all of them, in the decomposition's numbering); the implementation knows
/// which subdomains each interface joins, and where a neighbour it does
/// not hold lives.
pub trait Communicator: Send + Sync {
    /// For every interface `i` computed here, `f(i, &mut items[i], lo, hi)`
    /// with `lo`, `hi` the vectors `trace(&subs[·])` of its two subdomains
    /// (local numbering; only the interface entries of a neighbour's are
    /// read). In parallel over the interfaces.
    fn neighbour_traces<S, T, R, F>(&self, subs: &[S], trace: R, items: &mut [T], f: F)
    where
        S: Sync,
        T: Send,
        R: Fn(&S) -> &[f64] + Sync,
        F: Fn(usize, &mut T, &[f64], &[f64]) + Sync;

    /// `Σ_i f(i)` over all interfaces, in interface order (each interface
    /// counted once), `N` sums at a time; from `-0.0` as `Iterator::sum`, so
    /// a serial `.sum()` it replaces gives the same bits.
    fn sum_interfaces<const N: usize>(&self, f: impl Fn(usize) -> [f64; N]) -> [f64; N];

    /// `Σ_s f(s)` over all subdomains, in subdomain order, `N` sums at a time.
    fn sum_subdomains<const N: usize>(&self, f: impl Fn(usize) -> [f64; N]) -> [f64; N];

    /// The coarse step: `coarse.rhs` gets `iface_part(i)` of every interface
    /// at its macro offset and `sub_part(s)` of every subdomain at its
    /// kernel offset (after the `n_macro` macro unknowns); the problem is
    /// solved and its solution is readable by every subdomain afterwards
    /// (`macro_forces`, `kernel_amplitudes`).
    fn coarse_solve<'a>(
        &self,
        coarse: &mut CoarseProblem,
        iface_part: impl Fn(usize) -> (usize, &'a [f64]),
        sub_part: impl Fn(usize) -> (usize, &'a [f64]),
    );

    /// A global vector summed from the subdomains' contributions, in
    /// subdomain order: `add(s, out)` adds subdomain `s`'s part into `out`
    /// (zero on entry). Once per solve (loads, the displacement).
    fn assemble(&self, out: &mut [f64], add: impl Fn(usize, &mut [f64]));
}

/// Every subdomain in this process, the per-subdomain and per-interface
/// work on rayon's threads: the neighbours' vectors are read in place.
#[derive(Debug, Clone, Default)]
pub struct Threads {
    /// `(lo, hi)` subdomains of every interface.
    ends: Vec<(usize, usize)>,
    n_subdomains: usize,
}

impl Threads {
    /// The seam for `n_subdomains` subdomains joined by interfaces with
    /// the given `(lo, hi)` ends.
    pub fn new(n_subdomains: usize, ends: Vec<(usize, usize)>) -> Threads {
        Threads { ends, n_subdomains }
    }
}

#[inline]
fn add_into<const N: usize>(acc: &mut [f64; N], x: [f64; N]) {
    for (a, x) in acc.iter_mut().zip(x) {
        *a += x;
    }
}

impl Communicator for Threads {
    #[inline]
    fn neighbour_traces<S, T, R, F>(&self, subs: &[S], trace: R, items: &mut [T], f: F)
    where
        S: Sync,
        T: Send,
        R: Fn(&S) -> &[f64] + Sync,
        F: Fn(usize, &mut T, &[f64], &[f64]) + Sync,
    {
        let ends = &self.ends;
        items.par_iter_mut().enumerate().for_each(|(i, t)| {
            let (lo, hi) = ends[i];
            f(i, t, trace(&subs[lo]), trace(&subs[hi]));
        });
    }

    #[inline]
    fn sum_interfaces<const N: usize>(&self, f: impl Fn(usize) -> [f64; N]) -> [f64; N] {
        let mut acc = [-0.0; N];
        for i in 0..self.ends.len() {
            add_into(&mut acc, f(i));
        }
        acc
    }

    #[inline]
    fn sum_subdomains<const N: usize>(&self, f: impl Fn(usize) -> [f64; N]) -> [f64; N] {
        let mut acc = [-0.0; N];
        for s in 0..self.n_subdomains {
            add_into(&mut acc, f(s));
        }
        acc
    }

    fn coarse_solve<'a>(
        &self,
        coarse: &mut CoarseProblem,
        iface_part: impl Fn(usize) -> (usize, &'a [f64]),
        sub_part: impl Fn(usize) -> (usize, &'a [f64]),
    ) {
        for i in 0..self.ends.len() {
            let (off, x) = iface_part(i);
            coarse.rhs[off..off + x.len()].copy_from_slice(x);
        }
        let nf = coarse.n_macro;
        for s in 0..self.n_subdomains {
            let (off, x) = sub_part(s);
            coarse.rhs[nf + off..nf + off + x.len()].copy_from_slice(x);
        }
        coarse.solve();
    }

    fn assemble(&self, out: &mut [f64], add: impl Fn(usize, &mut [f64])) {
        for s in 0..self.n_subdomains {
            add(s, out);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn traces_pair_each_interface_with_its_two_subdomains() {
        let c = Threads::new(3, vec![(0, 1), (1, 2), (0, 2)]);
        let subs = vec![vec![1.0], vec![10.0], vec![100.0]];
        let mut out = vec![0.0; 3];
        c.neighbour_traces(&subs, |v| &v[..], &mut out, |_, o, lo, hi| *o = lo[0] - hi[0]);
        assert_eq!(out, vec![-9.0, -90.0, -99.0]);
        assert_eq!(c.sum_interfaces(|i| [out[i], 1.0]), [-198.0, 3.0]);
        assert_eq!(c.sum_subdomains(|s| [subs[s][0]]), [111.0]);
        let mut g = vec![0.0; 2];
        c.assemble(&mut g, |s, o| o[s % 2] += subs[s][0]);
        assert_eq!(g, vec![101.0, 10.0]);
    }
}
