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
//!   right-hand side is summed from each subdomain's part,
//!   solved, and its solution made readable to every subdomain.
//! - **global vectors** ([`Communicator::assemble`]): the summed load and
//!   the averaged displacement, once per solve.
//! - **set-up** ([`Communicator::exchange`], [`Communicator::gather`],
//!   [`Communicator::agree`]): what a subdomain needs of its neighbours
//!   once (kernel traces, stiffness diagonals, Schur face blocks), the
//!   coarse contributions of every subdomain, and errors that end every
//!   process alike.
//!
//! [`Threads`] implements it for subdomains that all live in this process
//! (rayon): the neighbour's vector is read in place, nothing is copied.
//! With the `mpi` feature, `mpi::MpiSeam` implements it for a rank that
//! owns a contiguous block of subdomains: it keeps ghost buffers for the
//! neighbour subdomains it does not own, fills their interface entries by
//! point-to-point messages with the ranks sharing an interface, computes
//! only the interfaces (and sums) it touches, and reduces in global order,
//! so every rank count gives the bits of [`Threads`]. [`Placement`] says
//! which of the two a set-up uses.

use crate::coarse::CoarseProblem;
use crate::decomposition::Decomposition;
use crate::error::Result;
use rayon::prelude::*;
use std::ops::Range;

#[cfg(feature = "mpi")]
pub mod mpi;

/// Where the subdomains of a set-up live: all in this process (the
/// default, rayon threads) or spread over the ranks of an MPI communicator
/// (`mpi` feature), each rank owning a contiguous block
/// ([`Placement::owned`]).
#[derive(Clone, Default)]
pub enum Placement {
    /// Every subdomain in this process.
    #[default]
    Process,
    /// Rank `r` of `p` owns subdomains `⌊r n/p⌋ .. ⌊(r+1) n/p⌋`.
    #[cfg(feature = "mpi")]
    Mpi(mpi::MpiComm),
}

impl std::fmt::Debug for Placement {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Placement({} of {})", self.rank(), self.ranks())
    }
}

impl Placement {
    /// This process's rank (0 for [`Placement::Process`]).
    pub fn rank(&self) -> usize {
        match self {
            Placement::Process => 0,
            #[cfg(feature = "mpi")]
            Placement::Mpi(c) => c.rank(),
        }
    }

    /// Number of ranks (1 for [`Placement::Process`]).
    pub fn ranks(&self) -> usize {
        match self {
            Placement::Process => 1,
            #[cfg(feature = "mpi")]
            Placement::Mpi(c) => c.size(),
        }
    }

    /// Whether no MPI is involved: the solve may then run on any thread
    /// (see `crate::method::on_workers`).
    pub fn in_process(&self) -> bool {
        matches!(self, Placement::Process)
    }

    /// Whether this process writes results and prints progress (rank 0).
    pub fn is_root(&self) -> bool {
        self.rank() == 0
    }

    /// The subdomains this process owns among `n_subdomains`.
    pub fn owned(&self, n_subdomains: usize) -> Range<usize> {
        block(n_subdomains, self.rank(), self.ranks())
    }

    /// The rank that owns subdomain `s` of `n_subdomains`.
    pub fn owner(&self, s: usize, n_subdomains: usize) -> usize {
        owner_of(s, n_subdomains, self.ranks())
    }

    /// `r` if it is `Ok` on every process, else the error of the lowest
    /// process that failed, on every process: a failure on one rank ends
    /// them all alike, never a hang.
    pub fn agree<T>(&self, r: Result<T>) -> Result<T> {
        match self {
            Placement::Process => r,
            #[cfg(feature = "mpi")]
            Placement::Mpi(c) => c.agree(r),
        }
    }

    /// [`Self::agree`] for any error type, sent between processes as
    /// `encode` writes it and `decode` reads it back.
    pub fn agree_by<T, E>(
        &self,
        r: std::result::Result<T, E>,
        encode: impl FnOnce(&E) -> Vec<u8>,
        decode: impl FnOnce(&[u8]) -> E,
    ) -> std::result::Result<T, E> {
        match self {
            Placement::Process => {
                let _ = (encode, decode);
                r
            }
            #[cfg(feature = "mpi")]
            Placement::Mpi(c) => c.agree_by(r, encode, decode),
        }
    }

    /// Every process's `local`, concatenated in rank order (set-up only).
    pub fn gather(&self, local: &[f64]) -> Vec<f64> {
        match self {
            Placement::Process => local.to_vec(),
            #[cfg(feature = "mpi")]
            Placement::Mpi(c) => c.gather(local),
        }
    }

    /// The seam of a set-up on `dec` for this placement.
    pub(crate) fn seam(&self, dec: &Decomposition) -> Seam {
        let ends = dec.interfaces.iter().map(|it| (it.lo, it.hi)).collect();
        match self {
            Placement::Process => Seam::Threads(Threads::new(dec.len(), ends)),
            #[cfg(feature = "mpi")]
            Placement::Mpi(c) => Seam::Mpi(Box::new(mpi::MpiSeam::new(c.clone(), dec))),
        }
    }
}

/// Subdomains `⌊r n/p⌋ .. ⌊(r+1) n/p⌋`: rank `r`'s block.
pub(crate) fn block(n: usize, r: usize, p: usize) -> Range<usize> {
    n * r / p..n * (r + 1) / p
}

/// The rank whose [`block`] holds `s`.
pub(crate) fn owner_of(s: usize, n: usize, p: usize) -> usize {
    // The last r with ⌊r n/p⌋ ≤ s.
    let mut r = ((s * p) / n.max(1)).min(p - 1);
    while r > 0 && n * r / p > s {
        r -= 1;
    }
    while r + 1 < p && n * (r + 1) / p <= s {
        r += 1;
    }
    r
}

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

    /// The coarse step: `coarse.rhs` is the sum over the subdomains of
    /// their parts `part(s)` ([`CoarseRhsPart`]: macro values added at
    /// their columns, the kernel part placed at its offset after the
    /// `n_macro` macro unknowns); the problem is solved and its solution is
    /// readable by every subdomain afterwards (`macro_forces`,
    /// `kernel_amplitudes`). A macro column belongs to one interface, so it
    /// gets two terms, whose sum has the same bits in any order.
    fn coarse_solve<'a>(&self, coarse: &mut CoarseProblem, part: impl Fn(usize) -> CoarseRhsPart<'a>);

    /// A global vector summed from the subdomains' contributions, in
    /// subdomain order: `add(s, out)` adds subdomain `s`'s part into `out`
    /// (zero on entry). Once per solve (loads, the displacement).
    fn assemble(&self, out: &mut [f64], add: impl Fn(usize, &mut [f64]));

    /// The subdomains held here, a contiguous block of the decomposition's
    /// numbering: local position `s` is subdomain `owned().start + s`.
    fn owned(&self) -> Range<usize>;

    /// Set-up only (allocates). For every interface `i` with a subdomain
    /// held here, the payloads `[lo, hi]` its two sides computed with
    /// `payload(i, is_lo)` (called here for the sides held here; the others
    /// come from the rank that holds them). Interfaces without a subdomain
    /// here get two empty vectors.
    fn exchange(&self, payload: impl Fn(usize, bool) -> Vec<f64> + Sync) -> Vec<[Vec<f64>; 2]>;

    /// Set-up only: every process's `local`, concatenated in rank order.
    fn gather(&self, local: &[f64]) -> Vec<f64>;

    /// `r` if it is `Ok` everywhere, else the same error on every process
    /// (see [`Placement::agree`]).
    fn agree<T>(&self, r: Result<T>) -> Result<T>;
}

/// The seam of a set-up: [`Threads`], or an MPI rank's.
pub enum Seam {
    Threads(Threads),
    #[cfg(feature = "mpi")]
    Mpi(Box<mpi::MpiSeam>),
}

impl Seam {
    /// Whether every subdomain is in this process (no MPI).
    pub fn in_process(&self) -> bool {
        matches!(self, Seam::Threads(_))
    }

    /// Under MPI, every rank's traffic since the set-up as `[trace
    /// messages, trace bytes, reductions, reduction bytes]` per rank, in
    /// rank order (collective: every rank calls it); `None` in one process.
    pub fn traffic_by_rank(&self) -> Option<Vec<[u64; 4]>> {
        match self {
            Seam::Threads(_) => None,
            #[cfg(feature = "mpi")]
            Seam::Mpi(c) => {
                let t = c.traffic();
                let mine = [t.trace_messages, t.trace_bytes, t.reductions, t.reduction_bytes].map(|x| x as f64);
                Some(
                    c.gather(&mine)
                        .chunks_exact(4)
                        .map(|p| [p[0] as u64, p[1] as u64, p[2] as u64, p[3] as u64])
                        .collect(),
                )
            }
        }
    }
}

/// One subdomain's part of the coarse right-hand side: `macro_values[k]`
/// adds to the macro unknown `macro_cols[k]` (`Z_Eᵀ r_E` or `W_Eᵀ y_E` on
/// the macro columns of its interfaces), and `kernel` is its kernel block
/// (`R_Eᵀ r_E`) at `kernel_off` among the kernel unknowns.
#[derive(Clone, Copy)]
pub struct CoarseRhsPart<'a> {
    pub macro_cols: &'a [usize],
    pub macro_values: &'a [f64],
    pub kernel_off: usize,
    pub kernel: &'a [f64],
}

impl CoarseRhsPart<'_> {
    /// Adds the macro part into `rhs` and places the kernel part after its
    /// `n_macro` macro unknowns.
    pub(crate) fn add_to(&self, rhs: &mut [f64], n_macro: usize) {
        for (&c, &x) in self.macro_cols.iter().zip(self.macro_values) {
            rhs[c] += x;
        }
        let off = n_macro + self.kernel_off;
        rhs[off..off + self.kernel.len()].copy_from_slice(self.kernel);
    }
}

macro_rules! dispatch {
    ($self:ident, $c:ident => $e:expr) => {
        match $self {
            Seam::Threads($c) => $e,
            #[cfg(feature = "mpi")]
            Seam::Mpi($c) => $e,
        }
    };
}

impl Communicator for Seam {
    #[inline]
    fn neighbour_traces<S, T, R, F>(&self, subs: &[S], trace: R, items: &mut [T], f: F)
    where
        S: Sync,
        T: Send,
        R: Fn(&S) -> &[f64] + Sync,
        F: Fn(usize, &mut T, &[f64], &[f64]) + Sync,
    {
        dispatch!(self, c => c.neighbour_traces(subs, trace, items, f))
    }

    #[inline]
    fn sum_interfaces<const N: usize>(&self, f: impl Fn(usize) -> [f64; N]) -> [f64; N] {
        dispatch!(self, c => c.sum_interfaces(f))
    }

    #[inline]
    fn sum_subdomains<const N: usize>(&self, f: impl Fn(usize) -> [f64; N]) -> [f64; N] {
        dispatch!(self, c => c.sum_subdomains(f))
    }

    fn coarse_solve<'a>(&self, coarse: &mut CoarseProblem, part: impl Fn(usize) -> CoarseRhsPart<'a>) {
        dispatch!(self, c => c.coarse_solve(coarse, part))
    }

    fn assemble(&self, out: &mut [f64], add: impl Fn(usize, &mut [f64])) {
        dispatch!(self, c => c.assemble(out, add))
    }

    fn owned(&self) -> Range<usize> {
        dispatch!(self, c => c.owned())
    }

    fn exchange(&self, payload: impl Fn(usize, bool) -> Vec<f64> + Sync) -> Vec<[Vec<f64>; 2]> {
        dispatch!(self, c => c.exchange(payload))
    }

    fn gather(&self, local: &[f64]) -> Vec<f64> {
        dispatch!(self, c => c.gather(local))
    }

    fn agree<T>(&self, r: Result<T>) -> Result<T> {
        dispatch!(self, c => c.agree(r))
    }
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

    fn coarse_solve<'a>(&self, coarse: &mut CoarseProblem, part: impl Fn(usize) -> CoarseRhsPart<'a>) {
        coarse.rhs.iter_mut().for_each(|x| *x = 0.0);
        for s in 0..self.n_subdomains {
            part(s).add_to(&mut coarse.rhs, coarse.n_macro);
        }
        coarse.solve();
    }

    fn assemble(&self, out: &mut [f64], add: impl Fn(usize, &mut [f64])) {
        for s in 0..self.n_subdomains {
            add(s, out);
        }
    }

    fn owned(&self) -> Range<usize> {
        0..self.n_subdomains
    }

    fn exchange(&self, payload: impl Fn(usize, bool) -> Vec<f64> + Sync) -> Vec<[Vec<f64>; 2]> {
        (0..self.ends.len())
            .into_par_iter()
            .map(|i| [payload(i, true), payload(i, false)])
            .collect()
    }

    fn gather(&self, local: &[f64]) -> Vec<f64> {
        local.to_vec()
    }

    fn agree<T>(&self, r: Result<T>) -> Result<T> {
        r
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

    #[test]
    fn blocks_cover_every_subdomain_once_in_rank_order() {
        for n in [0, 1, 2, 3, 7, 16] {
            for p in 1..6 {
                let mut next = 0;
                for r in 0..p {
                    let b = block(n, r, p);
                    assert_eq!(b.start, next);
                    next = b.end;
                    for s in b {
                        assert_eq!(owner_of(s, n, p), r, "n {n} p {p} s {s}");
                    }
                }
                assert_eq!(next, n);
            }
        }
    }
}
