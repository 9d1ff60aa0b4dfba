//! Adaptive enrichment of the macro space (docs/design.md §4): per face,
//! the jumps the preconditioner cannot bound, found by a small generalized
//! eigenproblem on the face, become extra macro columns of its interface.
//!
//! For the face `E` of the interface of subdomains `k` and `l` (its
//! entries no third subdomain shares), let `S_k` be the
//! principal block on `E` of subdomain `k`'s Schur complement on its whole
//! interface (the other interface dofs held: what the deluxe weights use)
//! and `S̃_k` the Schur complement of `K_k` on `E` alone (everything else
//! free). With deluxe weights the local bound of the preconditioned
//! operator is the largest `λ` of
//!
//! ```text
//!     (S_k : S_l) z = λ (S̃_k : S̃_l) z,      z ⟂ P_Γ,
//! ```
//!
//! `A : B = A (A + B)⁺ B` the parallel sum (Pechstein & Dohrmann's unified
//! adaptive BDDC; λ ≥ 1, about `(1 + log H/h)²` on a uniform structure and of
//! the order of the stiffness contrast where stiff parts hang on soft ones).
//! Each `z` with `λ > θ` adds the constraint `(S̃_k : S̃_l) z` on the jump.
//!
//! Edges (dofs shared by the same three or more subdomains, a node where
//! several cuts meet included) get constraints too, or a bar/cable contrast
//! leaves the spectrum there unbounded: the 16³ tower at contrast 1e4 with
//! 64 subdomains took 424 iterations with constraints on its faces alone
//! (largest Lanczos eigenvalue estimate ~200-350 on the 12³ one) and 39 with
//! them on its edges too. Every pair of an edge's subdomains solves the
//! eigenproblem above on the edge's dofs; the union `C_E` of their
//! constraints is imposed on the pairs of a spanning tree of the edge's
//! subdomains (`edge_trees`), which gives it on every pair by
//! transitivity (`Cᵀ(u_a − u_b) = Cᵀ(u_a − u_c) + Cᵀ(u_c − u_b)`) and on no
//! cycle of pairs: a constraint repeated around a cycle is a circulation of
//! the redundant pair forces, which the coarse problem cannot resolve (cg
//! broke down when each pair took its own). The edge problems take no
//! macro columns out first: those are spread over whole interfaces, not
//! local to the edge.

use crate::coarse::MACRO_RANK_RTOL;
use crate::dd::FaceBlock;
use crate::decomposition::Decomposition;
use crate::error::{Error, Result};
use crate::model::Model;
use crate::scaling::Edges;
use crate::settings::{AdaptiveEdges, AdaptiveThreshold};
use crate::subdomain::{orthonormal_columns, subtract_gram_of, InteriorProblem, SubdomainOperator};
use faer::linalg::solvers::DenseSolveCore;
use faer::Mat;
use rayon::prelude::*;

/// `threshold` with `"auto"` decided for `model` (from its elements'
/// axial stiffnesses `EA/L`, [`AdaptiveThreshold::resolve`]): what a set-up
/// uses.
pub fn threshold_for(threshold: AdaptiveThreshold, model: &Model) -> AdaptiveThreshold {
    AdaptiveThreshold::Value(threshold.resolve(model.elements.iter().map(|e| e.k)))
}

/// `edges` with `"auto"` decided for `model` ([`AdaptiveEdges::resolve`]).
pub fn edges_for(edges: AdaptiveEdges, model: &Model) -> AdaptiveEdges {
    edges.resolve(model.elements.iter().map(|e| e.k)).into()
}

/// What one side brings to the eigenproblem of a face: the principal block
/// `S_k` and the Neumann block `S̃_k` on the face's entries.
pub struct FaceSide {
    pub principal: Mat<f64>,
    pub neumann: Mat<f64>,
}

impl FaceSide {
    /// Both blocks as one message: the order, then each block column-major.
    pub fn pack(&self) -> Vec<f64> {
        let n = self.principal.nrows();
        let mut out = Vec::with_capacity(1 + 2 * n * n);
        out.push(n as f64);
        for m in [&self.principal, &self.neumann] {
            for j in 0..n {
                out.extend((0..n).map(|i| m[(i, j)]));
            }
        }
        out
    }

    /// The side [`FaceSide::pack`] sent; `None` for an empty message (no
    /// side there).
    pub fn unpack(msg: &[f64]) -> Option<FaceSide> {
        let n = *msg.first()? as usize;
        if msg.len() != 1 + 2 * n * n {
            return None;
        }
        let block = |k: usize| Mat::from_fn(n, n, |i, j| msg[1 + k * n * n + j * n + i]);
        Some(FaceSide {
            principal: block(0),
            neumann: block(1),
        })
    }
}

/// The face of every interface: its entries no third subdomain shares
/// (multiplicity 2), in entry order.
pub fn face_entries(dec: &Decomposition) -> Vec<Vec<usize>> {
    dec.interfaces
        .iter()
        .map(|it| {
            let m = &dec.subdomains[it.lo].multiplicity;
            (it.start..it.end)
                .filter(|&e| m[dec.entry_lo_local[e] as usize] == 2)
                .map(|e| e - it.start)
                .collect()
        })
        .collect()
}

/// One subdomain's adaptive work, kept for a later set-up that takes its
/// operator over (the nonsmooth cg's active-set steps, where most
/// subdomains keep their cables from one step to the next): a Neumann
/// block depends only on the operator and its rows, and a face's
/// constraints only on its two sides, its macro columns and the
/// threshold. On the nonsmooth 30³ tower cut in 16 the face and edge
/// blocks and the face eigenproblems were half of each step's set-up.
#[derive(Default)]
pub(crate) struct SideCache {
    /// Neumann blocks of the faces by local rows (a failed block is not kept).
    faces: Vec<(Vec<u32>, Mat<f64>)>,
    /// The same for the edges.
    edges: Vec<(Vec<u32>, Mat<f64>)>,
    /// Normalised constraints of the faces this subdomain is the `lo` side
    /// of, by [`constraint_key`].
    constraints: Vec<(u64, Mat<f64>)>,
}

impl SideCache {
    /// Keeps `found` as the constraints of this set-up's faces (the
    /// earlier ones go).
    pub(crate) fn set_constraints(&mut self, found: Vec<(u64, Mat<f64>)>) {
        self.constraints = found;
    }
}

/// The key of a face's constraints: a hash of every bit they are computed
/// from (the threshold, the macro columns on the face, both sides' blocks).
/// Equal inputs give equal constraints; a collision, improbable at 64 bits,
/// would only hand a face another face's constraints, which changes the
/// iteration count, not the answer (the macro space is a coarse space).
fn constraint_key(theta: f64, pf: &Mat<f64>, lo: &FaceSide, hi: &FaceSide) -> u64 {
    use std::hash::Hasher;
    let mut h = std::collections::hash_map::DefaultHasher::new();
    h.write_u64(theta.to_bits());
    for m in [pf, &lo.principal, &lo.neumann, &hi.principal, &hi.neumann] {
        h.write_usize(m.nrows());
        h.write_usize(m.ncols());
        for j in 0..m.ncols() {
            for &v in m.col_as_slice(j) {
                h.write_u64(v.to_bits());
            }
        }
    }
    h.finish()
}

/// Whether a set-up keeps its adaptive blocks for a later one, and how
/// many it took over from an earlier one.
pub(crate) struct Keeping<'a> {
    pub(crate) keep: bool,
    pub(crate) reused: &'a std::sync::atomic::AtomicUsize,
}

/// The Neumann block of `op` on `rows` from `earlier` (taken out) if it is
/// there, else computed; kept in `now` where `keeping` says (a failed one
/// is not).
fn neumann_kept(
    op: &mut SubdomainOperator,
    rows: &[u32],
    earlier: &mut Vec<(Vec<u32>, Mat<f64>)>,
    now: &mut Vec<(Vec<u32>, Mat<f64>)>,
    scratch: &mut Vec<f64>,
    keeping: &Keeping<'_>,
) -> Result<Option<Mat<f64>>> {
    if let Some(k) = earlier.iter().position(|(r, _)| r == rows) {
        let (r, b) = earlier.swap_remove(k);
        keeping.reused.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        if keeping.keep {
            now.push((r, b.clone()));
        }
        return Ok(Some(b));
    }
    let b = neumann_block(op, rows, scratch)?;
    if let (Some(b), true) = (&b, keeping.keep) {
        now.push((rows.to_vec(), b.clone()));
    }
    Ok(b)
}

/// Both sides of every face whose subdomains are held here (`operators`
/// and `pool` from subdomain `first` on), in parallel over subdomains. Each
/// subdomain's interior problem and principal face blocks go into its
/// `pool` entry (taken over if they are there already), where the cg
/// set-up takes them over for its deluxe weights: same rows, same order.
/// A face whose Neumann block fails (an eigensolve) gets no side there.
/// Neumann blocks come from the subdomain's [`SideCache`] where they are
/// there, and go there where `keeping` says.
pub(crate) fn face_sides(
    dec: &Decomposition,
    first: usize,
    operators: &mut [SubdomainOperator],
    pool: &mut [(Option<InteriorProblem>, Vec<FaceBlock>, SideCache)],
    faces: &[Vec<usize>],
    keeping: &Keeping<'_>,
) -> Result<Vec<[Option<FaceSide>; 2]>> {
    let sides = operators
        .par_iter_mut()
        .zip(pool.par_iter_mut())
        .enumerate()
        .map(|(k, (op, (interior, kept, cache)))| -> Result<Vec<(usize, FaceSide)>> {
            let s = first + k;
            let sd = &dec.subdomains[s];
            let boundary: Vec<u32> = (0..sd.multiplicity.len() as u32)
                .filter(|&l| sd.multiplicity[l as usize] > 1)
                .collect();
            if !interior.as_ref().is_some_and(|ip| ip.fits(op.n(), &boundary)) {
                *interior = Some(InteriorProblem::new(op, &boundary)?);
                kept.clear();
            }
            let ip = interior.as_mut().expect("set above");
            let mut out = Vec::with_capacity(sd.interfaces.len());
            let mut scratch = Vec::new();
            let mut earlier = std::mem::take(&mut cache.faces);
            for &i in &sd.interfaces {
                let it = &dec.interfaces[i];
                let local = if it.lo == s {
                    &dec.entry_lo_local[it.start..it.end]
                } else {
                    &dec.entry_hi_local[it.start..it.end]
                };
                let rows: Vec<u32> = faces[i].iter().map(|&j| local[j]).collect();
                if rows.is_empty() {
                    continue;
                }
                let principal = match kept.iter().find(|(r, _)| *r == rows) {
                    Some((_, b)) => b.clone(),
                    None => {
                        let b = principal_block(ip, op, &rows)?;
                        kept.push((rows.clone(), b.clone()));
                        b
                    }
                };
                if let Some(neumann) = neumann_kept(op, &rows, &mut earlier, &mut cache.faces, &mut scratch, keeping)? {
                    out.push((i, FaceSide { principal, neumann }));
                }
            }
            ip.release_face_scratch();
            Ok(out)
        })
        .collect::<Result<Vec<_>>>()?;
    let mut by_face: Vec<[Option<FaceSide>; 2]> = (0..dec.interfaces.len()).map(|_| [None, None]).collect();
    for (k, list) in sides.into_iter().enumerate() {
        for (i, side) in list {
            let at = usize::from(dec.interfaces[i].lo != first + k);
            by_face[i][at] = Some(side);
        }
    }
    Ok(by_face)
}

/// Both blocks of every held subdomain on every edge it shares
/// ([`Edges`]), for [`edge_constraints`], packed as one message: per
/// (edge, subdomain) pair, `[edge, position of the subdomain in the edge,
/// FaceSide::pack()...]`, subdomains in order, each subdomain's edges in
/// order. Uses the interior problems [`face_sides`] left in `pool`. A side
/// whose Neumann block fails (an eigensolve) is left out, and its edge
/// gets no constraints. Neumann blocks are kept as in [`face_sides`].
pub(crate) fn edge_sides(
    edges: &Edges,
    first: usize,
    operators: &mut [SubdomainOperator],
    pool: &mut [(Option<InteriorProblem>, Vec<FaceBlock>, SideCache)],
    keeping: &Keeping<'_>,
) -> Result<Vec<f64>> {
    let parts = operators
        .par_iter_mut()
        .zip(pool.par_iter_mut())
        .enumerate()
        .map(|(k, (op, (interior, _, cache)))| -> Result<Vec<f64>> {
            let s = first + k;
            let mut out = Vec::new();
            let mut scratch = Vec::new();
            let mut earlier = std::mem::take(&mut cache.edges);
            for &e in &edges.of_subdomain[s] {
                let edge = &edges.edges[e];
                let m = edge.subdomains.binary_search(&s).expect("an edge lists its subdomains");
                let rows = &edge.rows[m];
                let Some(ip) = interior.as_mut() else {
                    continue;
                };
                let principal = principal_block(ip, op, rows)?;
                if let Some(neumann) = neumann_kept(op, rows, &mut earlier, &mut cache.edges, &mut scratch, keeping)? {
                    out.extend([e as f64, m as f64]);
                    out.extend(FaceSide { principal, neumann }.pack());
                }
            }
            if let Some(ip) = interior.as_mut() {
                ip.release_face_scratch();
            }
            Ok(out)
        })
        .collect::<Result<Vec<_>>>()?;
    Ok(parts.concat())
}

/// The constraints `C_E` (`edge dofs × c`, orthonormal, in the edge's dof
/// order) of every edge from the sides of all its subdomains (`packed`:
/// every process's [`edge_sides`], in any order), `None` where a side is
/// missing or no pair has an eigenvalue above `theta`. The same on every
/// process.
pub(crate) fn edge_constraints(edges: &Edges, packed: &[f64], theta: f64) -> Vec<Option<Mat<f64>>> {
    let mut sides: Vec<Vec<Option<FaceSide>>> = edges
        .edges
        .iter()
        .map(|e| (0..e.subdomains.len()).map(|_| None).collect())
        .collect();
    let mut at = 0;
    while at + 3 <= packed.len() {
        let (e, m, n) = (packed[at] as usize, packed[at + 1] as usize, packed[at + 2] as usize);
        let len = 1 + 2 * n * n;
        let Some(msg) = packed.get(at + 2..at + 2 + len) else {
            break;
        };
        if let Some(slot) = sides.get_mut(e).and_then(|v| v.get_mut(m)) {
            *slot = FaceSide::unpack(msg);
        }
        at += 2 + len;
    }
    sides
        .into_par_iter()
        .map(|sides| {
            let sides: Vec<FaceSide> = sides.into_iter().collect::<Option<_>>()?;
            let n = sides.first()?.principal.nrows();
            let none = Mat::<f64>::zeros(n, 0);
            let mut found: Vec<Mat<f64>> = Vec::new();
            for a in 0..sides.len() {
                for b in a + 1..sides.len() {
                    // A failed eigensolve leaves that pair without constraints.
                    if let Ok(c) = face_modes(&sides[a], &sides[b], &none, theta) {
                        if c.ncols() > 0 {
                            found.push(c);
                        }
                    }
                }
            }
            let total: usize = found.iter().map(|c| c.ncols()).sum();
            if total == 0 {
                return None;
            }
            let mut all = Mat::<f64>::zeros(n, total);
            let mut q = 0;
            for c in &found {
                all.as_mut().submatrix_mut(0, q, n, c.ncols()).copy_from(c.as_ref());
                q += c.ncols();
            }
            let basis = orthonormal_columns(&all, EXTRA_RANK_RTOL);
            (basis.ncols() > 0).then_some(basis)
        })
        .collect()
}

/// The root of `a` in a disjoint-set forest (`root[x] == x` at a root),
/// halving the path on the way.
pub(crate) fn find_root(root: &mut [usize], mut a: usize) -> usize {
    while root[a] != a {
        root[a] = root[root[a]];
        a = root[a];
    }
    a
}

/// The interfaces that carry each edge's constraints ([`edge_constraints`]):
/// a spanning tree of the pairs of its subdomains, as `(interface, its
/// entries of the edge's dofs in the edge's order)` per edge; empty for an
/// edge whose pairs with an interface holding all its dofs do not connect
/// its subdomains (it gets no constraints). A tree, so that the
/// constraints go around no cycle of pairs; and one that takes the
/// interfaces without a face (`has_face[i]` false: subdomains that touch
/// along edges only) first, because their macro columns live on edges
/// alone: the same vectors on such a pair and on a path of tree pairs
/// around it would be a circulation (the 4³ contrast tower cut in 8 broke
/// down with a star of pairs from the first subdomain). Kruskal's order:
/// faceless pairs, then by subdomains.
pub(crate) fn edge_trees(edges: &Edges, ends: &[(usize, usize)], has_face: &[bool]) -> Vec<Vec<(usize, Vec<u32>)>> {
    let mut pairs: Vec<Vec<(usize, &Vec<u32>)>> = vec![Vec::new(); edges.edges.len()];
    for (i, list) in edges.of_interface.iter().enumerate() {
        for (e, entries) in list {
            pairs[*e].push((i, entries));
        }
    }
    pairs
        .into_iter()
        .zip(&edges.edges)
        .map(|(mut cand, edge)| {
            cand.sort_by_key(|&(i, _)| (has_face[i], ends[i]));
            let subs = &edge.subdomains;
            let mut root: Vec<usize> = (0..subs.len()).collect();
            let mut tree = Vec::with_capacity(subs.len().saturating_sub(1));
            for (i, entries) in cand {
                let (Ok(a), Ok(b)) = (subs.binary_search(&ends[i].0), subs.binary_search(&ends[i].1)) else {
                    continue;
                };
                let (ra, rb) = (find_root(&mut root, a), find_root(&mut root, b));
                if ra != rb {
                    root[ra] = rb;
                    tree.push((i, entries.clone()));
                }
            }
            if tree.len() + 1 != subs.len() {
                tree.clear();
            }
            tree
        })
        .collect()
}

/// The macro block `p` (orthonormal, `entries × m`) with the columns of
/// `extra` (`(entries of the interface, columns on them)`) added:
/// returns the new orthonormal block and the number of columns added.
pub fn with_columns(p: Mat<f64>, extra: &[(&[u32], &Mat<f64>)]) -> (Mat<f64>, usize) {
    let (n, m) = (p.nrows(), p.ncols());
    let k: usize = extra.iter().map(|(_, c)| c.ncols()).sum();
    if k == 0 {
        return (p, 0);
    }
    let mut all = Mat::<f64>::zeros(n, m + k);
    all.as_mut().submatrix_mut(0, 0, n, m).copy_from(p.as_ref());
    let mut q = m;
    for (entries, c) in extra {
        for (r, &j) in entries.iter().enumerate() {
            for t in 0..c.ncols() {
                all[(j as usize, q + t)] = c[(r, t)];
            }
        }
        q += c.ncols();
    }
    let all = orthonormal_columns(&all, MACRO_RANK_RTOL);
    let added = all.ncols().saturating_sub(m);
    (all, added)
}

/// Relative cut of the pseudo-inverses below.
const PINV_RTOL: f64 = 1e-10;

/// Rank cut of the added constraints among themselves.
const EXTRA_RANK_RTOL: f64 = 1e-8;

fn symmetrize(a: &Mat<f64>) -> Mat<f64> {
    Mat::from_fn(a.nrows(), a.ncols(), |i, j| 0.5 * (a[(i, j)] + a[(j, i)]))
}

/// A factor `T` with `T Tᵀ = A⁺` of a symmetric positive semi-definite
/// `A`, on its eigenvalues above `rtol` times the largest: `L⁻ᵀ` of a
/// Cholesky factorization when every pivot is above that cut (`n³/3`
/// flops), else the scaled eigenvectors (an eigendecomposition, ten times
/// dearer, only where `A` is singular or nearly so).
fn inverse_root(a: &Mat<f64>, rtol: f64) -> Option<Mat<f64>> {
    if let Some(llt) = clear_cholesky(a, rtol) {
        let mut x = Mat::<f64>::identity(a.nrows(), a.nrows());
        lower_solve(&llt, &mut x);
        return Some(x.transpose().to_owned());
    }
    eigen_inverse_root(a, rtol)
}

/// [`inverse_root`] by an eigendecomposition.
fn eigen_inverse_root(a: &Mat<f64>, rtol: f64) -> Option<Mat<f64>> {
    let n = a.nrows();
    let evd = a.self_adjoint_eigen(faer::Side::Lower).ok()?;
    let (u, s) = (evd.U(), evd.S().column_vector());
    let smax = (0..n).map(|k| s[k].abs()).fold(0.0f64, f64::max);
    let keep: Vec<usize> = (0..n).filter(|&k| s[k] > rtol * smax).collect();
    Some(Mat::from_fn(n, keep.len(), |i, j| u[(i, keep[j])] / s[keep[j]].sqrt()))
}

/// The Cholesky factorization of the symmetric `a` when every pivot is
/// above `rtol` times the largest, else `None` (singular or nearly so).
fn clear_cholesky(a: &Mat<f64>, rtol: f64) -> Option<faer::linalg::solvers::Llt<f64>> {
    let llt = a.llt(faer::Side::Lower).ok()?;
    let l = llt.L();
    let pivots = (0..a.nrows()).map(|k| l[(k, k)] * l[(k, k)]);
    let (lo, hi) = pivots.fold((f64::INFINITY, 0.0f64), |(lo, hi), p| (lo.min(p), hi.max(p)));
    (lo > rtol * hi && hi.is_finite()).then_some(llt)
}

/// `x ← L⁻¹ x` for the factor `L` of `llt`.
fn lower_solve(llt: &faer::linalg::solvers::Llt<f64>, x: &mut Mat<f64>) {
    faer::linalg::triangular_solve::solve_lower_triangular_in_place(llt.L(), x.as_mut(), faer::Par::Seq);
}

/// `a − xᵀ x` for symmetric `a` (the lower triangle by a triangular
/// product, then mirrored).
fn minus_gram(a: &Mat<f64>, x: &Mat<f64>) -> Mat<f64> {
    let mut out = a.clone();
    subtract_gram_of(&mut out, x.as_ref());
    out
}

/// `Π a Π` for the projector `Π = I − k kᵀ` off the orthonormal columns
/// `k` (`n × r`): `a − k (kᵀa) − (a k) kᵀ + k (kᵀ a k) kᵀ`, in `O(n² r)`
/// flops where the product with a complement basis takes `O(n³)`.
fn project_off(a: &Mat<f64>, k: &Mat<f64>) -> Mat<f64> {
    if k.ncols() == 0 {
        return a.clone();
    }
    let ak = a * k;
    let kak = k.transpose() * &ak;
    // Π a Π = a − ak kᵀ − k akᵀ + k kak kᵀ = a − (ak − ½ k kak) kᵀ − k (ak − ½ k kak)ᵀ.
    let w = &ak - k * &kak * 0.5;
    let mut out = a - &w * k.transpose();
    out -= k * w.transpose();
    out
}

/// The shift `σ` of a projection `Π a Π` of `a`: its largest diagonal
/// entry; `None` where that is not clearly above `a`'s round-off (the
/// projection leaves nothing, as on a face whose macro columns span it:
/// shifted and factored, its round-off took constraints where the
/// complement route finds none), so that the complement route decides.
fn projected_scale(a: &Mat<f64>, projected: &Mat<f64>) -> Option<f64> {
    let largest = |m: &Mat<f64>| (0..m.nrows()).map(|i| m[(i, i)]).fold(0.0f64, f64::max);
    let sigma = largest(projected);
    (sigma.is_finite() && sigma > PROJECTED_RTOL * largest(a)).then_some(sigma)
}

/// Smallest largest diagonal entry of a projection, relative to the
/// matrix's own, for the shifted routes ([`projected_scale`]).
const PROJECTED_RTOL: f64 = 1e-8;

/// An orthonormal basis of the complement of the span of `a` (`n × k`,
/// any rank): the trailing columns of the full `Q` of a QR factorization
/// of an orthonormal basis of that span.
fn complement(a: &Mat<f64>) -> Mat<f64> {
    let n = a.nrows();
    let basis = orthonormal_columns(a, SPAN_RTOL);
    let r = basis.ncols();
    if r == 0 {
        return Mat::identity(n, n);
    }
    let q = basis.qr().compute_Q();
    q.subcols(r, n - r).to_owned()
}

/// Rank cut of the spans whose complements [`complement`] takes.
const SPAN_RTOL: f64 = 1e-8;

/// `A : B = A − A (A + B)⁺ A` for symmetric positive semi-definite `A`, `B`.
fn parallel_sum(a: &Mat<f64>, b: &Mat<f64>) -> Option<Mat<f64>> {
    let sum = symmetrize(&(a + b));
    if let Some(llt) = clear_cholesky(&sum, PINV_RTOL) {
        // (A + B)⁻¹ = L⁻ᵀ L⁻¹: A (A + B)⁻¹ A = Xᵀ X with X = L⁻¹ A.
        let mut x = a.clone();
        lower_solve(&llt, &mut x);
        return Some(minus_gram(a, &x));
    }
    let t = eigen_inverse_root(&sum, PINV_RTOL)?;
    let ta = t.transpose() * a;
    Some(symmetrize(&(a - ta.transpose() * &ta)))
}

/// The Neumann block `S̃` of `op` on its local dofs `rows` (`None` if an
/// eigensolve failed): the Schur
/// complement of `K` on them with every other dof free, from the
/// flexibility `F = R K⁺ Rᵀ` (forward substitutions with the subdomain's
/// own factor and a product, no new factorization). Loads balanced against the kernel `N`
/// have `S̃ F λ = λ`, and `S̃` vanishes on the kernel's traces, so `S̃ = (Π
/// F Π)⁺` with `Π` the projector off those traces (inverted on its range).
pub fn neumann_block(op: &mut SubdomainOperator, rows: &[u32], scratch: &mut Vec<f64>) -> Result<Option<Mat<f64>>> {
    let m = rows.len();
    let f = op.flexibility_block(rows, scratch)?;
    // Inverted on the complement of the kernel traces only: a relative cut
    // there would take the stiffest directions (the smallest flexibilities,
    // 1e-10 of the largest behind a 1e4 contrast) for null ones.
    let kernel = op.kernel();
    let traces = Mat::from_fn(m, kernel.ncols(), |a, q| kernel[(rows[a] as usize, q)]);
    Ok(neumann_from_projected(&f, &traces).or_else(|| neumann_by_complement(&f, &traces)))
}

/// [`neumann_block`] through an orthonormal basis `C` of the complement of
/// the kernel traces: `C (Cᵀ F C)⁺ Cᵀ`, the pseudo-inverse by an
/// eigendecomposition where `Cᵀ F C` is singular or nearly so.
fn neumann_by_complement(f: &Mat<f64>, traces: &Mat<f64>) -> Option<Mat<f64>> {
    let m = f.nrows();
    let c = if traces.ncols() == 0 {
        Mat::<f64>::identity(m, m)
    } else {
        complement(traces)
    };
    let fc = symmetrize(&(c.transpose() * f * &c));
    let root = inverse_root(&fc, FLEXIBILITY_RTOL)?;
    let cr = &c * &root;
    Some(&cr * cr.transpose())
}

/// [`neumann_block`] where the flexibility is clearly definite off the
/// kernel traces (`None` otherwise): with `K` an orthonormal basis of the
/// traces, `Π = I − K Kᵀ` and `σ` the largest diagonal entry of `Π F Π`,
/// `(Π F Π + σ K Kᵀ)⁻¹ = (Π F Π)⁺ + K Kᵀ / σ`. One Cholesky factorization
/// and its inverse (about `4n³/3` flops) where the complement basis took
/// about `10 n³`: on the 30³ contrast tower cut in 16 the face blocks of
/// ~700 dofs made this a third of the adaptive set-up.
fn neumann_from_projected(f: &Mat<f64>, traces: &Mat<f64>) -> Option<Mat<f64>> {
    let k = orthonormal_columns(traces, SPAN_RTOL);
    let mut m = symmetrize(&project_off(f, &k));
    let sigma = projected_scale(f, &m)?;
    m += &k * k.transpose() * sigma;
    let llt = clear_cholesky(&m, FLEXIBILITY_RTOL)?;
    let mut s = llt.inverse();
    s -= &k * k.transpose() * (1.0 / sigma);
    Some(symmetrize(&s))
}

/// Eigenvalues of a face flexibility (kernel traces removed) below this
/// times the largest are round-off: the face is rigid there.
const FLEXIBILITY_RTOL: f64 = 1e-15;

/// The principal block `S_k` of `op`'s Schur complement on `rows`, through
/// its interior problem (the other interface dofs held).
pub fn principal_block(ip: &mut InteriorProblem, op: &SubdomainOperator, rows: &[u32]) -> Result<Mat<f64>> {
    Ok(symmetrize(&ip.schur_block(op, rows)?))
}

/// `p`'s rows on the face (`face`: entries of the interface).
pub fn face_rows(p: &Mat<f64>, face: &[usize]) -> Mat<f64> {
    Mat::from_fn(face.len(), p.ncols(), |i, j| p[(face[i], j)])
}

/// The constraints of [`face_modes`] on a face whose macro columns are
/// `pf` there, orthonormal (`face × k`, `k` = 0 where none or the
/// eigensolve failed): the adaptive columns [`enrich_with`] adds.
pub fn face_constraints(pf: &Mat<f64>, lo: &FaceSide, hi: &FaceSide, theta: f64) -> Mat<f64> {
    // A failed eigensolve leaves the face without adaptive columns.
    match face_modes(lo, hi, pf, theta) {
        // The constraints are orthogonal to `p` on the face already; their
        // own basis drops near-repeats, which add nothing but conditioning
        // trouble to the coarse problem.
        Ok(extra) if extra.ncols() > 0 => orthonormal_columns(&extra, EXTRA_RANK_RTOL),
        _ => Mat::zeros(pf.nrows(), 0),
    }
}

/// [`face_constraints`] of a face, taken from `earlier` (the `lo`
/// subdomain's cache, where it is held here) when they were computed from
/// the same bits ([`constraint_key`]; counted in `reused`). Returns their
/// key, for the cache of the next set-up, and the constraints.
pub(crate) fn face_constraints_kept(
    pf: &Mat<f64>,
    lo: &FaceSide,
    hi: &FaceSide,
    theta: f64,
    earlier: Option<&SideCache>,
    reused: &std::sync::atomic::AtomicUsize,
) -> (u64, Mat<f64>) {
    let key = constraint_key(theta, pf, lo, hi);
    let kept = earlier.and_then(|c| c.constraints.iter().find(|(k, _)| *k == key));
    match kept {
        Some((_, c)) => {
            reused.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            (key, c.clone())
        }
        None => (key, face_constraints(pf, lo, hi, theta)),
    }
}

/// The macro block `p` (orthonormal, `entries × m`) of an interface with
/// the constraints `extra` of its face ([`face_constraints`]; `face`: the
/// entries no third subdomain shares) as new columns: returns the new
/// orthonormal block and the number of columns added. Constraints on the
/// faces alone keep the blocks of different interfaces on disjoint
/// entries, so that they cannot repeat each other at cross points (on the
/// edges they do, and cg broke down when they were allowed there).
pub fn enrich_with(p: Mat<f64>, face: &[usize], extra: &Mat<f64>) -> (Mat<f64>, usize) {
    if extra.ncols() == 0 {
        return (p, 0);
    }
    let entries: Vec<u32> = face.iter().map(|&i| i as u32).collect();
    with_columns(p, &[(&entries, extra)])
}

/// The constraints (`face × k`, orthogonal to the columns of `p`, not
/// normalised) of one face whose macro columns restricted to it are `p`:
/// `(S̃_lo : S̃_hi) z` for the eigenvectors `z ⟂ p` of `(S_lo : S_hi) z = λ
/// (S̃_lo : S̃_hi) z` whose eigenvalue exceeds `theta`.
pub fn face_modes(lo: &FaceSide, hi: &FaceSide, p: &Mat<f64>, theta: f64) -> Result<Mat<f64>> {
    let n = p.nrows();
    let fail = face_eigensolve_failed;
    if n == 0 {
        return Ok(Mat::zeros(0, 0));
    }
    let a = parallel_sum(&lo.principal, &hi.principal).ok_or_else(fail)?;
    let b = parallel_sum(&lo.neumann, &hi.neumann).ok_or_else(fail)?;
    face_modes_projected(&a, &b, p, theta).unwrap_or_else(|| face_modes_by_complement(&a, &b, p, theta))
}

/// The error of a face whose eigenproblem could not be solved.
fn face_eigensolve_failed() -> Error {
    Error::Numerical("adaptive macro space: a face eigensolve failed".into())
}

/// [`face_modes`] from the parallel sums `a` and `b` through an orthonormal
/// basis `Q` of the complement of `p`'s span, the inverse root of `Qᵀ b Q`
/// by an eigendecomposition where it is singular or nearly so.
fn face_modes_by_complement(a: &Mat<f64>, b: &Mat<f64>, p: &Mat<f64>, theta: f64) -> Result<Mat<f64>> {
    let fail = face_eigensolve_failed;
    // Q: orthonormal complement of the span of p.
    let q = complement(p);
    let aq = symmetrize(&(q.transpose() * a * &q));
    let bq = symmetrize(&(q.transpose() * b * &q));
    // Bq = T⁻ᵀ T⁻¹ on its range: the eigenproblem becomes Tᵀ Aq T y = λ y.
    let t = inverse_root(&bq, PINV_RTOL).ok_or_else(fail)?;
    let c = symmetrize(&(t.transpose() * &aq * &t));
    let evd = c.self_adjoint_eigen(faer::Side::Lower).map_err(|_| fail())?;
    let (v, lam) = (evd.U(), evd.S().column_vector());
    let k = t.ncols();
    let picked: Vec<usize> = (0..k).filter(|&j| lam[j] > theta).collect();
    let y = &t * Mat::from_fn(k, picked.len(), |i, j| v[(i, picked[j])]);
    Ok(&q * (&bq * &y))
}

/// [`face_modes`] on the whole face, where `Π b Π + σ P Pᵀ` is clearly
/// definite (`None` otherwise): with `P` an orthonormal basis of `p`'s
/// span, `Π = I − P Pᵀ` and `σ` the largest diagonal entry of `Π b Π`, the
/// pencil `(Π a Π, Π b Π + σ P Pᵀ)` has the eigenpairs of `(Qᵀ a Q, Qᵀ b
/// Q)` (as `z = Q y`) and the eigenvalue 0 on `P`. That takes the
/// projections in `O(n² k)` and the reduction by two triangular solves
/// with one Cholesky factor, about half the flops of the complement basis
/// with its products and inverse root.
fn face_modes_projected(a: &Mat<f64>, b: &Mat<f64>, p: &Mat<f64>, theta: f64) -> Option<Result<Mat<f64>>> {
    let basis = orthonormal_columns(p, SPAN_RTOL);
    let ap = symmetrize(&project_off(a, &basis));
    let bp = symmetrize(&project_off(b, &basis));
    let sigma = projected_scale(b, &bp)?;
    let shifted = &bp + &basis * basis.transpose() * sigma;
    let llt = clear_cholesky(&shifted, PINV_RTOL)?;
    // C = L⁻¹ (Π a Π) L⁻ᵀ.
    let mut x = ap;
    lower_solve(&llt, &mut x);
    let mut c = x.transpose().to_owned();
    lower_solve(&llt, &mut c);
    let c = symmetrize(&c);
    let Ok(evd) = c.self_adjoint_eigen(faer::Side::Lower) else {
        return Some(Err(face_eigensolve_failed()));
    };
    let (v, lam) = (evd.U(), evd.S().column_vector());
    let picked: Vec<usize> = (0..c.nrows()).filter(|&j| lam[j] > theta).collect();
    // z = L⁻ᵀ v, and the constraint Π b Π z.
    let mut z = Mat::from_fn(c.nrows(), picked.len(), |i, j| v[(i, picked[j])]);
    faer::linalg::triangular_solve::solve_upper_triangular_in_place(llt.L().transpose(), z.as_mut(), faer::Par::Seq);
    Some(Ok(&bp * &z))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scaling::Edge;

    /// A symmetric positive semi-definite `n × n` matrix of rank `rank`
    /// with eigenvalues spread over `spread` decades, from a fixed seed.
    fn spd(n: usize, rank: usize, spread: f64, seed: u64) -> Mat<f64> {
        let mut state = seed;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((state >> 11) as f64 / (1u64 << 53) as f64) - 0.5
        };
        let g = Mat::from_fn(n, n, |_, _| next());
        let q = g.qr().compute_Q();
        let d = Mat::from_fn(n, n, |i, j| {
            if i == j && i < rank {
                10f64.powf(-spread * i as f64 / n as f64)
            } else {
                0.0
            }
        });
        symmetrize(&(&q * d * q.transpose()))
    }

    fn max_abs(a: &Mat<f64>) -> f64 {
        (0..a.nrows())
            .flat_map(|i| (0..a.ncols()).map(move |j| (i, j)))
            .fold(0.0f64, |m, (i, j)| m.max(a[(i, j)].abs()))
    }

    /// The parallel sum through one Cholesky factor agrees with the
    /// eigendecomposition route (and with `A (A + B)⁻¹ B`).
    #[test]
    fn parallel_sum_by_cholesky_matches_the_eigen_route() {
        let (a, b) = (spd(40, 40, 3.0, 1), spd(40, 40, 5.0, 2));
        let fast = parallel_sum(&a, &b).unwrap();
        let t = eigen_inverse_root(&symmetrize(&(&a + &b)), PINV_RTOL).unwrap();
        let ta = t.transpose() * &a;
        let slow = symmetrize(&(&a - ta.transpose() * &ta));
        let direct = &a * (&a + &b).llt(faer::Side::Lower).unwrap().inverse() * &b;
        assert!(max_abs(&(&fast - &slow)) <= 1e-12 * max_abs(&slow));
        assert!(max_abs(&(&fast - &direct)) <= 1e-10 * max_abs(&slow));
    }

    /// The Neumann block from the shifted projection agrees with the
    /// complement route: with kernel traces (the flexibility singular on
    /// none of them, as `K⁺` leaves it), without, and it declines a
    /// flexibility singular off the traces, which the complement route's
    /// pseudo-inverse takes.
    #[test]
    fn neumann_block_by_projection_matches_the_complement_route() {
        let n = 30;
        let f = spd(n, n, 4.0, 3);
        let traces = Mat::from_fn(n, 3, |i, q| ((i + 1) as f64).powi(q as i32) / (n as f64).powi(q as i32));
        for t in [traces.clone(), Mat::zeros(n, 0)] {
            let fast = neumann_from_projected(&f, &t).unwrap();
            let slow = neumann_by_complement(&f, &t).unwrap();
            assert!(
                max_abs(&(&fast - &slow)) <= 1e-9 * max_abs(&slow),
                "{} traces: {:.2e} of {:.2e}",
                t.ncols(),
                max_abs(&(&fast - &slow)),
                max_abs(&slow)
            );
            // S̃ vanishes on the traces.
            assert!(max_abs(&(&fast * &t)) <= 1e-9 * max_abs(&slow) * max_abs(&t));
        }
        let singular = spd(n, n - 2, 2.0, 4);
        assert!(neumann_from_projected(&singular, &Mat::zeros(n, 0)).is_none());
        assert!(neumann_by_complement(&singular, &Mat::zeros(n, 0)).is_some());
    }

    /// The face modes from the shifted pencil span what the complement
    /// route gives: the same number above the threshold, the same columns
    /// up to round-off (both are `Π b Π z` for `b`-normalised eigenvectors
    /// `z`, equal up to sign where the eigenvalues are simple), and
    /// orthogonal to `p`.
    #[test]
    fn face_modes_by_projection_match_the_complement_route() {
        let n = 36;
        let (a, b) = (spd(n, n, 1.0, 5), spd(n, n, 3.0, 6));
        let p = Mat::from_fn(n, 4, |i, q| ((i as f64) * 0.37 + q as f64).sin());
        let theta = {
            let q = complement(&p);
            let (aq, bq) = (q.transpose() * &a * &q, q.transpose() * &b * &q);
            // The generalized eigenvalues, through the complement route's
            // own reduction: a threshold between the 5th and 6th.
            let t = inverse_root(&symmetrize(&bq), PINV_RTOL).unwrap();
            let c = symmetrize(&(t.transpose() * &aq * &t));
            let evd = c.self_adjoint_eigen(faer::Side::Lower).unwrap();
            let mut lam: Vec<f64> = evd.S().column_vector().iter().copied().collect();
            lam.sort_by(|x, y| y.partial_cmp(x).unwrap());
            0.5 * (lam[4] + lam[5])
        };
        let fast = face_modes_projected(&a, &b, &p, theta).unwrap().unwrap();
        let slow = face_modes_by_complement(&a, &b, &p, theta).unwrap();
        assert_eq!((fast.ncols(), slow.ncols()), (5, 5));
        for j in 0..5 {
            let (x, y) = (fast.col(j), slow.col(j));
            let sign = if x.transpose() * y >= 0.0 { 1.0 } else { -1.0 };
            let diff = (0..n).map(|i| (x[i] - sign * y[i]).abs()).fold(0.0f64, f64::max);
            let size = (0..n).map(|i| y[i].abs()).fold(0.0f64, f64::max);
            assert!(diff <= 1e-8 * size, "column {j}: {diff:.2e} of {size:.2e}");
        }
        assert!(max_abs(&(p.transpose() * &fast)) <= 1e-10 * max_abs(&fast) * max_abs(&p));
    }

    /// One edge of two dofs shared by subdomains 1, 3 and 5, on the
    /// interfaces (1,3), (1,5) and (3,5), and one of subdomains 0, 2, 4 on
    /// (0,2) and (2,4) ((0,4) holds no interface).
    fn two_edges() -> (Edges, Vec<(usize, usize)>) {
        let edge = |subdomains: Vec<usize>| Edge {
            rows: subdomains.iter().map(|_| vec![0, 1]).collect(),
            subdomains,
        };
        let ends = vec![(1, 3), (1, 5), (3, 5), (0, 2), (2, 4)];
        let mut of_interface = vec![Vec::new(); ends.len()];
        for i in 0..3 {
            of_interface[i].push((0, vec![4, 7]));
        }
        for i in 3..5 {
            of_interface[i].push((1, vec![2, 3]));
        }
        let edges = Edges {
            edges: vec![edge(vec![1, 3, 5]), edge(vec![0, 2, 4])],
            of_interface,
            of_subdomain: vec![vec![1], vec![0], vec![1], vec![0], vec![1], vec![0]],
        };
        (edges, ends)
    }

    /// An edge's constraints go on a spanning tree of its pairs, never
    /// around a cycle, the pairs without a face first; an edge whose pairs
    /// do not connect its subdomains gets none.
    #[test]
    fn edge_constraints_go_on_a_spanning_tree_of_pairs() {
        let (edges, ends) = two_edges();
        let trees = edge_trees(&edges, &ends, &[true; 5]);
        assert_eq!(trees[0], vec![(0, vec![4, 7]), (1, vec![4, 7])]);
        assert_eq!(trees[1], vec![(3, vec![2, 3]), (4, vec![2, 3])]);
        // (3,5) touches along the edge only: it is in the tree.
        let trees = edge_trees(&edges, &ends, &[true, true, false, true, true]);
        assert_eq!(trees[0], vec![(2, vec![4, 7]), (0, vec![4, 7])]);
        // Without (0,2), subdomain 0 is cut off from 2 and 4.
        let mut cut = edges.clone();
        cut.of_interface[3].clear();
        assert!(edge_trees(&cut, &ends, &[true; 5])[1].is_empty());
    }

    /// Each edge's constraints come from every pair of its subdomains, and
    /// do not depend on the order the sides arrive in (ranks gather them in
    /// rank order); an edge with a side missing gets none.
    #[test]
    fn edge_constraints_take_every_pair_in_any_order() {
        let (edges, _) = two_edges();
        let stiff = Mat::from_fn(2, 2, |i, j| if i == j { 2.0 } else { 0.0 });
        // Subdomain 5's Neumann block is soft along (1, 1): the pairs (1,5)
        // and (3,5) see it, (1,3) does not.
        let soft = Mat::from_fn(2, 2, |i, j| if i == j { 1.0005 } else { -0.9995 });
        let side = |neumann: &Mat<f64>| FaceSide {
            principal: stiff.clone(),
            neumann: neumann.clone(),
        };
        let message = |e: usize, m: usize, s: FaceSide| {
            let mut v = vec![e as f64, m as f64];
            v.extend(s.pack());
            v
        };
        let parts = [
            message(0, 0, side(&stiff)),
            message(0, 1, side(&stiff)),
            message(0, 2, side(&soft)),
            message(1, 0, side(&stiff)),
            message(1, 1, side(&stiff)),
        ];
        let forward = edge_constraints(&edges, &parts.concat(), 5.0);
        let backward: Vec<f64> = parts.iter().rev().flatten().copied().collect();
        let backward = edge_constraints(&edges, &backward, 5.0);
        let c = forward[0].as_ref().expect("the soft direction is constrained");
        assert_eq!(c.ncols(), 1);
        assert!((c[(0, 0)] - c[(1, 0)]).abs() < 1e-12 * c[(0, 0)].abs());
        assert_eq!(backward[0].as_ref().map(|b| b == c), Some(true));
        // Edge 1 lacks subdomain 4's side.
        assert!(forward[1].is_none() && backward[1].is_none());
    }

    #[test]
    fn parallel_sum_of_diagonals_is_the_harmonic_half() {
        let a = Mat::from_fn(3, 3, |i, j| if i == j { [1.0, 2.0, 4.0][i] } else { 0.0 });
        let b = Mat::from_fn(3, 3, |i, j| if i == j { [1.0, 6.0, 0.0][i] } else { 0.0 });
        let c = parallel_sum(&a, &b).unwrap();
        for (i, want) in [0.5, 1.5, 0.0].into_iter().enumerate() {
            assert!((c[(i, i)] - want).abs() < 1e-14, "{i}: {}", c[(i, i)]);
        }
    }

    /// Two sides equal: `A : A = A/2`, so the eigenvalues are those of
    /// `S z = λ S̃ z`; a Neumann block soft in one direction gives one large
    /// eigenvalue there, and its constraint is orthogonal to `p`.
    #[test]
    fn a_soft_neumann_direction_becomes_one_constraint() {
        let n = 4;
        let principal = Mat::from_fn(n, n, |i, j| if i == j { 2.0 } else { 0.0 });
        let mut neumann = principal.clone();
        // Soft along (e2 - e3)/√2: S̃ = 2 I − 1.999 v vᵀ.
        let v = [0.0, 0.0, 1.0 / 2f64.sqrt(), -1.0 / 2f64.sqrt()];
        for i in 0..n {
            for j in 0..n {
                neumann[(i, j)] -= 1.999 * v[i] * v[j];
            }
        }
        let side = FaceSide { principal, neumann };
        let p = Mat::from_fn(n, 1, |i, _| if i == 0 { 1.0 } else { 0.0 });
        let c = face_modes(&side, &side, &p, 10.0).unwrap();
        assert_eq!(c.ncols(), 1);
        assert!(c[(0, 0)].abs() < 1e-14);
        // Parallel to v.
        let dot: f64 = (0..n).map(|i| c[(i, 0)] * v[i]).sum();
        let norm: f64 = (0..n).map(|i| c[(i, 0)] * c[(i, 0)]).sum::<f64>().sqrt();
        assert!((dot.abs() / norm - 1.0).abs() < 1e-10);
        // Below the threshold: nothing.
        assert_eq!(face_modes(&side, &side, &p, 3000.0).unwrap().ncols(), 0);
    }
}
