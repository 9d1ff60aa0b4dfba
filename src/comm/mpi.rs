//! The seam over MPI (`mpi` feature): each rank owns a contiguous block of
//! subdomains ([`super::block`]), with their factorizations, kernels and
//! macro columns; the decomposition itself (which subdomain holds which dof)
//! is known to every rank.
//!
//! - Neighbour traces: for every other rank it shares an interface with, a
//!   rank packs the interface entries of its own subdomains' traces into
//!   one buffer (interfaces in increasing order), posts every receive and
//!   send at once, and unpacks what it receives into ghost buffers of the
//!   neighbour subdomains. Interfaces with no subdomain here are skipped;
//!   the others are computed on both ranks that touch them, from the same
//!   numbers, so both hold the same interface vectors.
//! - Sums: each rank writes the parts it owns (an interface belongs to the
//!   rank of its `lo` subdomain) at their global position in a zeroed
//!   buffer; an `MPI_Allreduce` of that buffer adds each part to zeros
//!   only, which is exact, and every rank then sums the parts in global
//!   order: the bits of [`super::Threads`] whatever the rank count.
//! - The coarse step: the right-hand side is gathered the same way and the
//!   coarse problem, assembled once from every rank's contributions at
//!   set-up, is solved on every rank (replicated: a broadcast from one rank
//!   would cost as much as the reduction and add a step of latency).
//! - Global vectors (once per solve): rank 0 adds its subdomains' parts,
//!   passes the vector to rank 1, which adds its own, and so on; the last
//!   rank broadcasts the sum. Same order as the threads, same bits.
//!
//! The per-iteration paths call MPI through `mpi::ffi` on buffers allocated
//! at set-up, so they allocate nothing. MPI is called only from the thread
//! that drives the solve, never from rayon's workers: initialise it with
//! `MPI_THREAD_FUNNELED` (the command line does) or better.

use super::{block, owner_of, CoarseRhsPart, Communicator};
use crate::coarse::CoarseProblem;
use crate::decomposition::Decomposition;
use crate::error::{Error, Result};
use mpi::ffi;
use mpi::raw::FromRaw;
use mpi::topology::SimpleCommunicator;
use mpi::traits::{AsRaw, Communicator as _, CommunicatorCollectives, Destination, Root, Source};
use rayon::prelude::*;
use std::ops::Range;
use std::os::raw::c_int;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// Message tag of the per-iteration trace exchanges.
const TRACE_TAG: c_int = 0x6e73;
/// Message tag of the set-up exchanges (payload sizes, then payloads).
const SETUP_TAG: c_int = 0x6e74;

struct Handle(SimpleCommunicator);

// SAFETY: an MPI communicator handle is an opaque id; nsdd calls MPI on it
// only from the thread that drives a set-up or a solve (the seam's methods
// are never called from rayon's workers), which `MPI_THREAD_FUNNELED`
// allows; the handle itself is never mutated after creation.
unsafe impl Send for Handle {}
unsafe impl Sync for Handle {}

/// A communicator nsdd works on: its own duplicate of the caller's, so its
/// messages never match the caller's (freed when the last clone goes).
#[derive(Clone)]
pub struct MpiComm(Arc<Handle>);

impl MpiComm {
    /// A duplicate of `MPI_COMM_WORLD`. MPI must be initialised (with
    /// `mpi::initialize_with_threading` and at least `Funneled`).
    pub fn world() -> MpiComm {
        MpiComm(Arc::new(Handle(SimpleCommunicator::world().duplicate())))
    }

    /// A duplicate of the communicator whose Fortran handle is `fcomm`
    /// (`MPI_Comm_c2f` of a C communicator): what the C ABI takes, so the
    /// header does not depend on one MPI's `MPI_Comm` type.
    ///
    /// # Safety
    /// MPI must be initialised and `fcomm` must be a live intra-communicator.
    pub unsafe fn from_fortran(fcomm: c_int) -> Result<MpiComm> {
        if !mpi::environment::is_initialized() {
            return Err(Error::input("comm", None, "MPI is not initialised"));
        }
        let c = ffi::RSMPI_Comm_f2c(fcomm);
        if c == ffi::RSMPI_COMM_NULL {
            return Err(Error::input("comm", None, "is MPI_COMM_NULL"));
        }
        let mut dup = ffi::RSMPI_COMM_NULL;
        if ffi::MPI_Comm_dup(c, &mut dup) != 0 || dup == ffi::RSMPI_COMM_NULL {
            return Err(Error::input(
                "comm",
                None,
                "could not be duplicated (not a communicator?)",
            ));
        }
        Ok(MpiComm(Arc::new(Handle(SimpleCommunicator::from_raw(dup)))))
    }

    fn comm(&self) -> &SimpleCommunicator {
        &self.0 .0
    }

    fn raw(&self) -> ffi::MPI_Comm {
        self.comm().as_raw()
    }

    /// This process's rank.
    pub fn rank(&self) -> usize {
        self.comm().rank() as usize
    }

    /// Number of ranks.
    pub fn size(&self) -> usize {
        self.comm().size() as usize
    }

    /// See [`super::Placement::agree`]: the error of the lowest failing
    /// rank, sent to all as JSON.
    pub(crate) fn agree<T>(&self, r: Result<T>) -> Result<T> {
        self.agree_by(
            r,
            |e| serde_json::to_vec(e).unwrap_or_default(),
            |b| {
                serde_json::from_slice(b)
                    .unwrap_or_else(|_| Error::Numerical("another rank failed (its error could not be read)".into()))
            },
        )
    }

    /// [`Self::agree`] for any error type, encoded as the caller says.
    pub(crate) fn agree_by<T, E>(
        &self,
        r: std::result::Result<T, E>,
        encode: impl FnOnce(&E) -> Vec<u8>,
        decode: impl FnOnce(&[u8]) -> E,
    ) -> std::result::Result<T, E> {
        let c = self.comm();
        let failed = c_int::from(r.is_err());
        let mut all = vec![0 as c_int; self.size()];
        c.all_gather_into(&failed, &mut all[..]);
        let Some(root) = all.iter().position(|&x| x != 0) else {
            return r;
        };
        let mut bytes = match &r {
            Err(e) if root == self.rank() => encode(e),
            _ => Vec::new(),
        };
        let mut len = bytes.len() as u64;
        let at = c.process_at_rank(root as c_int);
        at.broadcast_into(&mut len);
        bytes.resize(len as usize, 0);
        at.broadcast_into(&mut bytes[..]);
        match r {
            Err(e) if root == self.rank() => Err(e),
            _ => Err(decode(&bytes)),
        }
    }

    /// Every rank's `local`, concatenated in rank order.
    pub(crate) fn gather(&self, local: &[f64]) -> Vec<f64> {
        let c = self.comm();
        let n = local.len() as c_int;
        let mut counts = vec![0 as c_int; self.size()];
        c.all_gather_into(&n, &mut counts[..]);
        let displs: Vec<c_int> = counts
            .iter()
            .scan(0, |acc, &x| {
                let d = *acc;
                *acc += x;
                Some(d)
            })
            .collect();
        let total: c_int = counts.iter().sum();
        let mut out = vec![0.0; total as usize];
        {
            let mut part = mpi::datatype::PartitionMut::new(&mut out[..], counts, &displs[..]);
            c.all_gather_varcount_into(local, &mut part);
        }
        out
    }
}

/// One interface between a subdomain here and one on another rank.
struct Crossing {
    /// The interface.
    iface: usize,
    /// Whether the subdomain here is the interface's `lo` side.
    own_is_lo: bool,
    /// Local position of the subdomain here.
    own: usize,
    /// Its local dofs of the interface entries.
    own_idx: Vec<u32>,
    /// Ghost buffer of the other side, and its local dofs of the entries.
    ghost: usize,
    ghost_idx: Vec<u32>,
}

/// The interfaces shared with one other rank, with the message buffers.
struct Link {
    rank: c_int,
    crossings: Vec<Crossing>,
    send: Vec<f64>,
    recv: Vec<f64>,
}

/// Request handles of one exchange.
struct Requests(Vec<ffi::MPI_Request>);

// SAFETY: the handles are only used between posting and waiting, inside
// one call, on the thread that makes it (they are null otherwise).
unsafe impl Send for Requests {}

/// Buffers of the per-iteration calls, allocated at set-up.
struct Buffers {
    links: Vec<Link>,
    /// Ghost copies of the neighbour subdomains' traces (full local
    /// length; only interface entries are ever written or read).
    ghosts: Vec<Vec<f64>>,
    requests: Requests,
    parts: Vec<f64>,
    summed: Vec<f64>,
}

/// The seam of one MPI rank (see the module documentation).
pub struct MpiSeam {
    comm: MpiComm,
    rank: usize,
    owned: Range<usize>,
    /// `(lo, hi)` of every interface.
    ends: Vec<(usize, usize)>,
    /// Per interface: whether a subdomain here is on it.
    touched: Vec<bool>,
    /// Per subdomain: its ghost buffer, if it neighbours this rank.
    ghost_of: Vec<usize>,
    buffers: Mutex<Buffers>,
    /// Trace messages sent and their bytes, reductions and their bytes
    /// (for the benchmarks).
    messages: AtomicU64,
    bytes: AtomicU64,
    reductions: AtomicU64,
    reduced_bytes: AtomicU64,
}

/// What one rank sent since its set-up: trace messages to neighbour ranks
/// and all-reductions (sums, coarse right-hand sides), with their payload.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct Traffic {
    pub trace_messages: u64,
    pub trace_bytes: u64,
    pub reductions: u64,
    pub reduction_bytes: u64,
}

impl MpiSeam {
    /// The seam of this rank for a set-up on `dec` (every rank calls it).
    pub(crate) fn new(comm: MpiComm, dec: &Decomposition) -> MpiSeam {
        let (rank, size, ns) = (comm.rank(), comm.size(), dec.len());
        let owned = block(ns, rank, size);
        let ends: Vec<(usize, usize)> = dec.interfaces.iter().map(|it| (it.lo, it.hi)).collect();
        let touched: Vec<bool> = ends
            .iter()
            .map(|&(lo, hi)| owned.contains(&lo) || owned.contains(&hi))
            .collect();
        let mut ghost_of = vec![usize::MAX; ns];
        let mut ghosts: Vec<Vec<f64>> = Vec::new();
        let mut links: Vec<Link> = Vec::new();
        for (i, it) in dec.interfaces.iter().enumerate() {
            let (lo_here, hi_here) = (owned.contains(&it.lo), owned.contains(&it.hi));
            if lo_here == hi_here {
                continue;
            }
            let (own, other) = if lo_here { (it.lo, it.hi) } else { (it.hi, it.lo) };
            if ghost_of[other] == usize::MAX {
                ghost_of[other] = ghosts.len();
                ghosts.push(vec![0.0; dec.subdomains[other].dofs.len()]);
            }
            let lo_idx = dec.entry_lo_local[it.start..it.end].to_vec();
            let hi_idx = dec.entry_hi_local[it.start..it.end].to_vec();
            let (own_idx, ghost_idx) = if lo_here { (lo_idx, hi_idx) } else { (hi_idx, lo_idx) };
            let r = owner_of(other, ns, size) as c_int;
            let k = match links.iter().position(|l| l.rank == r) {
                Some(k) => k,
                None => {
                    links.push(Link {
                        rank: r,
                        crossings: Vec::new(),
                        send: Vec::new(),
                        recv: Vec::new(),
                    });
                    links.len() - 1
                }
            };
            links[k].crossings.push(Crossing {
                iface: i,
                own_is_lo: lo_here,
                own: own - owned.start,
                own_idx,
                ghost: ghost_of[other],
                ghost_idx,
            });
        }
        links.sort_by_key(|l| l.rank);
        for l in links.iter_mut() {
            let n: usize = l.crossings.iter().map(|c| c.own_idx.len()).sum();
            l.send = vec![0.0; n];
            l.recv = vec![0.0; n];
        }
        let requests = Requests(vec![unsafe { ffi::RSMPI_REQUEST_NULL }; 2 * links.len()]);
        MpiSeam {
            comm,
            rank,
            owned,
            ends,
            touched,
            ghost_of,
            buffers: Mutex::new(Buffers {
                links,
                ghosts,
                requests,
                parts: Vec::new(),
                summed: Vec::new(),
            }),
            messages: AtomicU64::new(0),
            bytes: AtomicU64::new(0),
            reductions: AtomicU64::new(0),
            reduced_bytes: AtomicU64::new(0),
        }
    }

    /// What this rank has sent since its set-up.
    pub fn traffic(&self) -> Traffic {
        let l = |a: &AtomicU64| a.load(Ordering::Relaxed);
        Traffic {
            trace_messages: l(&self.messages),
            trace_bytes: l(&self.bytes),
            reductions: l(&self.reductions),
            reduction_bytes: l(&self.reduced_bytes),
        }
    }

    fn count_reduction(&self, n: usize) {
        self.reductions.fetch_add(1, Ordering::Relaxed);
        self.reduced_bytes.fetch_add(8 * n as u64, Ordering::Relaxed);
    }

    /// Sends every link's `send` buffer and receives its `recv` buffer.
    fn swap(&self, links: &mut [Link], requests: &mut [ffi::MPI_Request]) {
        let comm = self.comm.raw();
        let mut k = 0;
        // SAFETY: the buffers outlive the requests (waited for below) and
        // are not touched until then; counts match the allocations.
        unsafe {
            for l in links.iter_mut() {
                ffi::MPI_Irecv(
                    l.recv.as_mut_ptr().cast(),
                    l.recv.len() as c_int,
                    ffi::RSMPI_DOUBLE,
                    l.rank,
                    TRACE_TAG,
                    comm,
                    &mut requests[k],
                );
                k += 1;
            }
            for l in links.iter() {
                ffi::MPI_Isend(
                    l.send.as_ptr().cast(),
                    l.send.len() as c_int,
                    ffi::RSMPI_DOUBLE,
                    l.rank,
                    TRACE_TAG,
                    comm,
                    &mut requests[k],
                );
                k += 1;
                self.messages.fetch_add(1, Ordering::Relaxed);
                self.bytes.fetch_add(8 * l.send.len() as u64, Ordering::Relaxed);
            }
            ffi::MPI_Waitall(k as c_int, requests.as_mut_ptr(), ffi::RSMPI_STATUSES_IGNORE);
        }
    }

    /// `Σ` of the parts written by `fill` at their global positions
    /// (`len` parts of `N`), in global order.
    fn sum_parts<const N: usize>(&self, len: usize, fill: impl FnOnce(&mut [f64])) -> [f64; N] {
        let mut b = self.buffers.lock().expect("seam buffers");
        let Buffers { parts, summed, .. } = &mut *b;
        let n = len * N;
        // First use of this size (set-up): grow once.
        if parts.len() < n {
            parts.resize(n, 0.0);
        }
        if summed.len() < n {
            summed.resize(n, 0.0);
        }
        parts[..n].iter_mut().for_each(|x| *x = 0.0);
        fill(&mut parts[..n]);
        self.count_reduction(n);
        // SAFETY: both buffers hold `n` doubles.
        unsafe {
            ffi::MPI_Allreduce(
                parts.as_ptr().cast(),
                summed.as_mut_ptr().cast(),
                n as c_int,
                ffi::RSMPI_DOUBLE,
                ffi::RSMPI_SUM,
                self.comm.raw(),
            );
        }
        let mut acc = [-0.0; N];
        for part in summed[..n].chunks_exact(N) {
            for (a, x) in acc.iter_mut().zip(part) {
                *a += x;
            }
        }
        acc
    }

    /// Sends variable-size payloads to the linked ranks and receives
    /// theirs (set-up only).
    fn swap_payloads(&self, links: &[Link], out: Vec<Vec<f64>>) -> Vec<Vec<f64>> {
        let c = self.comm.comm();
        let sizes: Vec<u64> = out.iter().map(|p| p.len() as u64).collect();
        let mut their = vec![0u64; links.len()];
        mpi::request::scope(|scope| {
            let mut reqs = Vec::new();
            for (l, n) in links.iter().zip(their.iter_mut()) {
                reqs.push(
                    c.process_at_rank(l.rank)
                        .immediate_receive_into_with_tag(scope, n, SETUP_TAG),
                );
            }
            for (l, n) in links.iter().zip(&sizes) {
                reqs.push(c.process_at_rank(l.rank).immediate_send_with_tag(scope, n, SETUP_TAG));
            }
            for r in reqs {
                r.wait();
            }
        });
        let mut back: Vec<Vec<f64>> = their.iter().map(|&n| vec![0.0; n as usize]).collect();
        mpi::request::scope(|scope| {
            let mut reqs = Vec::new();
            for (l, b) in links.iter().zip(back.iter_mut()) {
                reqs.push(
                    c.process_at_rank(l.rank)
                        .immediate_receive_into_with_tag(scope, &mut b[..], SETUP_TAG),
                );
            }
            for (l, p) in links.iter().zip(&out) {
                reqs.push(
                    c.process_at_rank(l.rank)
                        .immediate_send_with_tag(scope, &p[..], SETUP_TAG),
                );
            }
            for r in reqs {
                r.wait();
            }
        });
        back
    }
}

impl Communicator for MpiSeam {
    fn neighbour_traces<S, T, R, F>(&self, subs: &[S], trace: R, items: &mut [T], f: F)
    where
        S: Sync,
        T: Send,
        R: Fn(&S) -> &[f64] + Sync,
        F: Fn(usize, &mut T, &[f64], &[f64]) + Sync,
    {
        let mut b = self.buffers.lock().expect("seam buffers");
        let Buffers {
            links,
            ghosts,
            requests,
            ..
        } = &mut *b;
        for l in links.iter_mut() {
            let mut pos = 0;
            for c in &l.crossings {
                let t = trace(&subs[c.own]);
                for &a in &c.own_idx {
                    l.send[pos] = t[a as usize];
                    pos += 1;
                }
            }
        }
        self.swap(links, &mut requests.0);
        for l in links.iter() {
            let mut pos = 0;
            for c in &l.crossings {
                let g = &mut ghosts[c.ghost];
                for &a in &c.ghost_idx {
                    g[a as usize] = l.recv[pos];
                    pos += 1;
                }
            }
        }
        let ghosts = &*ghosts;
        let first = self.owned.start;
        let side = |s: usize| -> &[f64] {
            if self.owned.contains(&s) {
                trace(&subs[s - first])
            } else {
                &ghosts[self.ghost_of[s]]
            }
        };
        items
            .par_iter_mut()
            .enumerate()
            .filter(|(i, _)| self.touched[*i])
            .for_each(|(i, t)| {
                let (lo, hi) = self.ends[i];
                f(i, t, side(lo), side(hi));
            });
    }

    fn sum_interfaces<const N: usize>(&self, f: impl Fn(usize) -> [f64; N]) -> [f64; N] {
        self.sum_parts(self.ends.len(), |parts| {
            for (i, &(lo, _)) in self.ends.iter().enumerate() {
                if self.owned.contains(&lo) {
                    parts[i * N..(i + 1) * N].copy_from_slice(&f(i));
                }
            }
        })
    }

    fn sum_subdomains<const N: usize>(&self, f: impl Fn(usize) -> [f64; N]) -> [f64; N] {
        let ns = self.ghost_of.len();
        let first = self.owned.start;
        self.sum_parts(ns, |parts| {
            for s in 0..self.owned.len() {
                let g = first + s;
                parts[g * N..(g + 1) * N].copy_from_slice(&f(s));
            }
        })
    }

    fn coarse_solve<'a>(&self, coarse: &mut CoarseProblem, part_of: impl Fn(usize) -> CoarseRhsPart<'a>) {
        let nf = coarse.n_macro;
        let n = coarse.rhs.len();
        {
            let mut b = self.buffers.lock().expect("seam buffers");
            let Buffers { parts, .. } = &mut *b;
            if parts.len() < n {
                parts.resize(n, 0.0);
            }
            let part = &mut parts[..n];
            part.iter_mut().for_each(|x| *x = 0.0);
            // Each macro column has two terms (its interface's sides), so
            // the reduction gives the bits of `Threads` whichever ranks hold
            // them.
            for s in 0..self.owned.len() {
                part_of(s).add_to(part, nf);
            }
            self.count_reduction(n);
            // SAFETY: `part` and `coarse.rhs` hold `n` doubles each.
            unsafe {
                ffi::MPI_Allreduce(
                    part.as_ptr().cast(),
                    coarse.rhs.as_mut_ptr().cast(),
                    n as c_int,
                    ffi::RSMPI_DOUBLE,
                    ffi::RSMPI_SUM,
                    self.comm.raw(),
                );
            }
        }
        coarse.solve();
    }

    fn assemble(&self, out: &mut [f64], add: impl Fn(usize, &mut [f64])) {
        let (comm, size) = (self.comm.raw(), self.comm.size() as c_int);
        let rank = self.rank as c_int;
        // SAFETY: `out` holds `out.len()` doubles on every rank.
        unsafe {
            if rank > 0 {
                ffi::MPI_Recv(
                    out.as_mut_ptr().cast(),
                    out.len() as c_int,
                    ffi::RSMPI_DOUBLE,
                    rank - 1,
                    TRACE_TAG,
                    comm,
                    ffi::RSMPI_STATUS_IGNORE,
                );
            }
            for s in 0..self.owned.len() {
                add(s, out);
            }
            if rank + 1 < size {
                ffi::MPI_Send(
                    out.as_ptr().cast(),
                    out.len() as c_int,
                    ffi::RSMPI_DOUBLE,
                    rank + 1,
                    TRACE_TAG,
                    comm,
                );
            }
            ffi::MPI_Bcast(
                out.as_mut_ptr().cast(),
                out.len() as c_int,
                ffi::RSMPI_DOUBLE,
                size - 1,
                comm,
            );
        }
    }

    fn owned(&self) -> Range<usize> {
        self.owned.clone()
    }

    fn exchange(&self, payload: impl Fn(usize, bool) -> Vec<f64> + Sync) -> Vec<[Vec<f64>; 2]> {
        let b = self.buffers.lock().expect("seam buffers");
        let links = &b.links;
        // What each link's other rank needs: our side of every crossing,
        // length-prefixed, in the crossings' order.
        let out: Vec<Vec<f64>> = links
            .par_iter()
            .map(|l| {
                let mut buf = Vec::new();
                for c in &l.crossings {
                    let p = payload(c.iface, c.own_is_lo);
                    buf.push(p.len() as f64);
                    buf.extend_from_slice(&p);
                }
                buf
            })
            .collect();
        let back = self.swap_payloads(links, out);
        let mut res: Vec<[Vec<f64>; 2]> = (0..self.ends.len())
            .into_par_iter()
            .map(|i| {
                let (lo, hi) = self.ends[i];
                let side = |s: usize, is_lo: bool| {
                    if self.owned.contains(&s) {
                        payload(i, is_lo)
                    } else {
                        Vec::new()
                    }
                };
                if self.touched[i] {
                    [side(lo, true), side(hi, false)]
                } else {
                    [Vec::new(), Vec::new()]
                }
            })
            .collect();
        for (l, buf) in links.iter().zip(back) {
            let mut pos = 0;
            for c in &l.crossings {
                let n = buf[pos] as usize;
                let p = buf[pos + 1..pos + 1 + n].to_vec();
                pos += 1 + n;
                res[c.iface][usize::from(c.own_is_lo)] = p;
            }
        }
        res
    }

    fn gather(&self, local: &[f64]) -> Vec<f64> {
        self.comm.gather(local)
    }

    fn agree<T>(&self, r: Result<T>) -> Result<T> {
        self.comm.agree(r)
    }
}
