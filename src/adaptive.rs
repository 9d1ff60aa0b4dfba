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

use crate::coarse::MACRO_RANK_RTOL;
use crate::dd::FaceBlock;
use crate::decomposition::Decomposition;
use crate::error::{Error, Result};
use crate::model::Model;
use crate::settings::AdaptiveThreshold;
use crate::subdomain::{orthonormal_columns, InteriorProblem, SubdomainOperator};
use faer::Mat;
use rayon::prelude::*;

/// `threshold` with `"auto"` decided for `model` (from its elements'
/// axial stiffnesses `EA/L`, [`AdaptiveThreshold::resolve`]): what a set-up
/// uses.
pub fn threshold_for(threshold: AdaptiveThreshold, model: &Model) -> AdaptiveThreshold {
    AdaptiveThreshold::Value(threshold.resolve(model.elements.iter().map(|e| e.k)))
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

/// Both sides of every face whose subdomains are held here (`operators`
/// and `pool` from subdomain `first` on), in parallel over subdomains. Each
/// subdomain's interior problem and principal face blocks go into its
/// `pool` entry (taken over if they are there already), where the cg
/// set-up takes them over for its deluxe weights: same rows, same order.
/// A face whose Neumann block fails (an eigensolve) gets no side there.
pub(crate) fn face_sides(
    dec: &Decomposition,
    first: usize,
    operators: &mut [SubdomainOperator],
    pool: &mut [(Option<InteriorProblem>, Vec<FaceBlock>)],
    faces: &[Vec<usize>],
) -> Result<Vec<[Option<FaceSide>; 2]>> {
    let sides = operators
        .par_iter_mut()
        .zip(pool.par_iter_mut())
        .enumerate()
        .map(|(k, (op, (interior, kept)))| -> Result<Vec<(usize, FaceSide)>> {
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
                if let Some(neumann) = neumann_block(op, &rows, &mut scratch)? {
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
    let n = a.nrows();
    if let Ok(llt) = a.llt(faer::Side::Lower) {
        let l = llt.L();
        let pivots = (0..n).map(|k| l[(k, k)] * l[(k, k)]);
        let (lo, hi) = pivots.fold((f64::INFINITY, 0.0f64), |(lo, hi), p| (lo.min(p), hi.max(p)));
        if lo > rtol * hi && hi.is_finite() {
            let mut x = Mat::<f64>::identity(n, n);
            faer::linalg::triangular_solve::solve_lower_triangular_in_place(l, x.as_mut(), faer::Par::Seq);
            return Some(x.transpose().to_owned());
        }
    }
    let evd = a.self_adjoint_eigen(faer::Side::Lower).ok()?;
    let (u, s) = (evd.U(), evd.S().column_vector());
    let smax = (0..n).map(|k| s[k].abs()).fold(0.0f64, f64::max);
    let keep: Vec<usize> = (0..n).filter(|&k| s[k] > rtol * smax).collect();
    Some(Mat::from_fn(n, keep.len(), |i, j| u[(i, keep[j])] / s[keep[j]].sqrt()))
}

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
    let t = inverse_root(&symmetrize(&(a + b)), PINV_RTOL)?;
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
    let c = if kernel.ncols() == 0 {
        Mat::<f64>::identity(m, m)
    } else {
        complement(&Mat::from_fn(m, kernel.ncols(), |a, q| kernel[(rows[a] as usize, q)]))
    };
    let fc = symmetrize(&(c.transpose() * &f * &c));
    let Some(root) = inverse_root(&fc, FLEXIBILITY_RTOL) else {
        return Ok(None);
    };
    let cr = &c * &root;
    Ok(Some(&cr * cr.transpose()))
}

/// Eigenvalues of a face flexibility (kernel traces removed) below this
/// times the largest are round-off: the face is rigid there.
const FLEXIBILITY_RTOL: f64 = 1e-15;

/// The principal block `S_k` of `op`'s Schur complement on `rows`, through
/// its interior problem (the other interface dofs held).
pub fn principal_block(ip: &mut InteriorProblem, op: &SubdomainOperator, rows: &[u32]) -> Result<Mat<f64>> {
    Ok(symmetrize(&ip.schur_block(op, rows)?))
}

/// The macro block `p` (orthonormal, `entries × m`) of an interface,
/// enriched with the constraints of [`face_modes`] on its face (`face`:
/// the entries no third subdomain shares): returns the new orthonormal
/// block and the number of columns added. Constraints on the faces alone
/// keep the blocks of different interfaces on disjoint entries, so that
/// they cannot repeat each other at cross points (on the edges they do,
/// and cg broke down when they were allowed there).
pub fn enrich(p: Mat<f64>, face: &[usize], lo: &FaceSide, hi: &FaceSide, theta: f64) -> (Mat<f64>, usize) {
    let n = p.nrows();
    let pf = Mat::from_fn(face.len(), p.ncols(), |i, j| p[(face[i], j)]);
    // A failed eigensolve leaves the face without adaptive columns.
    let extra = match face_modes(lo, hi, &pf, theta) {
        Ok(extra) if extra.ncols() > 0 => extra,
        _ => return (p, 0),
    };
    // The constraints are orthogonal to `p` on the face already; their own
    // basis drops near-repeats, which add nothing but conditioning trouble
    // to the coarse problem.
    let extra = orthonormal_columns(&extra, EXTRA_RANK_RTOL);
    let m = p.ncols();
    let mut all = Mat::<f64>::zeros(n, m + extra.ncols());
    all.as_mut().submatrix_mut(0, 0, n, m).copy_from(p.as_ref());
    for (k, &i) in face.iter().enumerate() {
        for j in 0..extra.ncols() {
            all[(i, m + j)] = extra[(k, j)];
        }
    }
    let all = orthonormal_columns(&all, MACRO_RANK_RTOL);
    let added = all.ncols().saturating_sub(m);
    (all, added)
}

/// The constraints (`face × k`, orthogonal to the columns of `p`, not
/// normalised) of one face whose macro columns restricted to it are `p`:
/// `(S̃_lo : S̃_hi) z` for the eigenvectors `z ⟂ p` of `(S_lo : S_hi) z = λ
/// (S̃_lo : S̃_hi) z` whose eigenvalue exceeds `theta`.
pub fn face_modes(lo: &FaceSide, hi: &FaceSide, p: &Mat<f64>, theta: f64) -> Result<Mat<f64>> {
    let n = p.nrows();
    let fail = || Error::Numerical("adaptive macro space: a face eigensolve failed".into());
    if n == 0 {
        return Ok(Mat::zeros(0, 0));
    }
    let a = parallel_sum(&lo.principal, &hi.principal).ok_or_else(fail)?;
    let b = parallel_sum(&lo.neumann, &hi.neumann).ok_or_else(fail)?;
    // Q: orthonormal complement of the span of p.
    let q = complement(p);
    let aq = symmetrize(&(q.transpose() * &a * &q));
    let bq = symmetrize(&(q.transpose() * &b * &q));
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

#[cfg(test)]
mod tests {
    use super::*;

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
