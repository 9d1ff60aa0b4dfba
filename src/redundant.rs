//! Macro directions that repeat others around cross points.
//!
//! The coarse problem's macro forces act on the subdomains through
//! `W = Σ_E W_E` (`W_E` puts `±P_Γ` on the subdomain's dofs of each of its
//! interfaces `Γ`). Where the bases of the interfaces around an edge or a
//! vertex overlap (one-node and edge-only interfaces, short faces, the
//! constraints on the edges), combinations `z` of macro columns leave no
//! force on any subdomain (`W z = 0`), or almost none. The exact ones are
//! null directions of the coarse problem, which its regularised factor
//! and refinement must absorb; the near ones are worse: the coarse
//! solution has a large component along them, known only to the coarse
//! solve's backward error over their tiny eigenvalue, and that component
//! moves the subdomains. On the 4³ contrast tower cut in 8 with the edges'
//! constraints (one combination with `‖W z‖² = 1.2e-12`) two evaluations
//! of the same CG operator differed by up to 60 % of the jump, and CG took
//! 345 iterations where it now takes 14.
//!
//! A combination with `W z ≈ 0` must vanish on every face dof (a dof of
//! two subdomains has one interface only), so it lives in the directions
//! `S_Γ` of each basis that vanish on its face ([`cross_directions`]). On
//! those, the Gram matrix `M = Sᵀ WᵀW S` is sparse; one `LDLᵀ` of it names
//! candidate unknowns, their kernel columns span the (near-)null space, a
//! Rayleigh–Ritz step on them picks the combinations below
//! [`NULL_EIGENVALUE`], and a column-pivoted QR of those picks one
//! direction per combination to drop: the directions they lean on most,
//! so that what remains is well conditioned ([`redundant_directions`]; on
//! the 130² plate with 64 subdomains, 71 of 1 959 go and the smallest
//! eigenvalue of the rest's Gram matrix is 0.036, where dropping the
//! unknowns of the `LDLᵀ`'s own small pivots left 5.7e-10 and CG stalled).
//!
//! The dropped directions leave the macro space altogether: the coarse
//! problem, the preconditioner's projection and the macro-part monitor
//! all use the reduced bases. (Projecting the exactly null ones out of
//! CG's space all the same kept the 20³ tower with 64 subdomains at 28
//! iterations where the reduced bases once took 41, but stalled the 30³
//! tower with 64 subdomains and the nonsmooth 12³ one with 16, both with
//! the edges' constraints, on a floor of the preconditioned jump: 1e-5
//! and 8e-5 of the loads.)

use crate::adaptive::find_root;
use faer::Mat;

/// Squared size on its face (of a unit direction of an interface basis)
/// below which the direction counts as living on the cross points:
/// `‖P_Γ c‖_face ≤ 1e-3`.
const FACE_NORM2: f64 = 1e-6;

/// Eigenvalue of the restricted Gram matrix (`WᵀW`, whose diagonal is 2)
/// below which a combination counts as leaving no force: `‖W z‖ ≤ 1e-3`
/// for a unit `z`. At 1e-8 (`‖W z‖ ≤ 1e-4`) the 30³ contrast tower cut in
/// 64 with the edges' constraints kept three combinations between the two
/// (495 of 17 914 directions dropped, 498 now): CG met `pᵀAp < 0` along the
/// preconditioned residual itself at an indicator of 2e-2, with every
/// coarse solve at a backward error of 7e-15, and broke down; now it
/// converges in 84 iterations. Twenty-six other plates and towers cut in
/// 4 to 64 lost no other direction but one, with the same iterations
/// (BENCHMARKS.md, "Near-null macro combinations up to ‖W z‖ = 1e-3").
pub const NULL_EIGENVALUE: f64 = 1e-6;

/// The directions `S_Γ` (`p × s`, orthonormal) of the basis `p` (orthonormal
/// columns) that (almost) vanish on its face: `cross` are the rows of its
/// entries on dofs of three or more subdomains. From `P_crossᵀ P_cross =
/// I − P_faceᵀ P_face`, whose eigenvalues near 1 mark them. Empty when the
/// interface has no cross entries.
pub fn cross_directions(p: &Mat<f64>, cross: &[usize]) -> Mat<f64> {
    let m = p.ncols();
    if cross.is_empty() || m == 0 {
        return Mat::zeros(m, 0);
    }
    if cross.len() == p.nrows() {
        return Mat::identity(m, m);
    }
    let c = Mat::from_fn(m, m, |a, b| cross.iter().map(|&r| p[(r, a)] * p[(r, b)]).sum::<f64>());
    let Ok(evd) = c.self_adjoint_eigen(faer::Side::Lower) else {
        return Mat::zeros(m, 0);
    };
    let (u, mu) = (evd.U(), evd.S().column_vector());
    let keep: Vec<usize> = (0..m).filter(|&q| mu[q] >= 1.0 - FACE_NORM2).collect();
    Mat::from_fn(m, keep.len(), |a, j| u[(a, keep[j])])
}

/// Pivot (relative to the largest diagonal entry, about 2) below which the
/// `LDLᵀ` scan of the restricted Gram matrix takes an unknown as a
/// candidate. Looser than [`NULL_EIGENVALUE`]: a near-null combination
/// can show as a pivot far above its eigenvalue when it leans little on
/// the unknown eliminated last (the 4³ tower's `1.2e-12` did), and the
/// candidates' kernel columns then span it to `λ ‖M_EE⁻¹‖` with the rest's
/// pivots above this.
const CANDIDATE_PIVOT: f64 = 1e-4;

/// Shift of the rest `M_EE` for its factor: a null combination the scan's
/// candidates do not cover leaves `M_EE` singular (on the 30³ tower with 64
/// subdomains and the edges' constraints its factor met a zero pivot, in
/// the scan's own order); shifted, the combination enters the kernel
/// columns amplified `1/μ`, and the Rayleigh–Ritz step finds it there.
const KERNEL_SHIFT: f64 = 1e-10;

/// Largest `k² n` (a group's kernel columns squared times its directions)
/// the selection may cost; beyond it the group keeps every direction.
const MAX_QR_WORK: f64 = 2e10;

/// The directions to drop, per interface (`p_i × t_i`, orthonormal, in the
/// coefficients of its basis; `p_i × 0` for none). `offset[i]`, `s[i]` are
/// interface `i`'s first macro column and cross directions (`p_i × s_i`,
/// [`cross_directions`]); `gram` holds lower-triangle triplets `(row >
/// col)` of `WᵀW` off its diagonal (duplicates summed), the diagonal
/// being `2 I`. Deterministic.
///
/// The restricted Gram matrix `M = Sᵀ WᵀW S` is sparse (directions couple
/// at shared cross dofs only). The unknowns of its small `LDLᵀ` pivots
/// (`CANDIDATE_PIVOT`) are fixed, the rest factored, and the kernel
/// columns `e_f − M_EE⁻¹ M_Ef` span the (near-)null space; grouped by
/// shared support, a Rayleigh–Ritz step on each group's columns keeps
/// the combinations below [`NULL_EIGENVALUE`], and a column-pivoted QR of
/// those picks the directions they lean on most. A group whose QR would
/// cost more than `MAX_QR_WORK` keeps its directions.
pub fn redundant_directions(offset: &[usize], s: &[Mat<f64>], gram: &[(usize, usize, f64)]) -> Vec<Mat<f64>> {
    let ni = s.len();
    let none = || s.iter().map(|si| Mat::zeros(si.nrows(), 0)).collect::<Vec<_>>();
    let n_macro = offset.last().copied().unwrap_or(0) + s.last().map_or(0, |x| x.nrows());
    // Interface of each macro column, and each interface's first direction.
    let mut owner = vec![usize::MAX; n_macro];
    let mut d_off = Vec::with_capacity(ni + 1);
    let mut nd = 0;
    for i in 0..ni {
        owner[offset[i]..offset[i] + s[i].nrows()].fill(i);
        d_off.push(nd);
        nd += s[i].ncols();
    }
    d_off.push(nd);
    if nd == 0 {
        return none();
    }
    // Blocks of WᵀW between interfaces that both have cross directions.
    let mut blocks: std::collections::BTreeMap<(usize, usize), Mat<f64>> = Default::default();
    for &(r, c, v) in gram {
        let (a, b) = (owner[r], owner[c]);
        if a == usize::MAX || b == usize::MAX || a == b || s[a].ncols() == 0 || s[b].ncols() == 0 {
            continue;
        }
        let blk = blocks
            .entry((a, b))
            .or_insert_with(|| Mat::zeros(s[a].nrows(), s[b].nrows()));
        blk[(r - offset[a], c - offset[b])] += v;
    }
    // M's lower triangle: 2 on the diagonal (S_Γ orthonormal), S_aᵀ A_ab S_b
    // below it (a after b).
    let mut m: Vec<(usize, usize, f64)> = (0..nd).map(|k| (k, k, 2.0)).collect();
    for (&(a, b), blk) in &blocks {
        let t = s[a].transpose() * blk * &s[b];
        for q in 0..t.nrows() {
            for r in 0..t.ncols() {
                if t[(q, r)] != 0.0 {
                    m.push((d_off[a] + q, d_off[b] + r, t[(q, r)]));
                }
            }
        }
    }
    drop(blocks);
    let Ok(lower) = crate::factor::lower_csc(nd, &m) else {
        return none();
    };
    // One elimination order for the scan and the factor of the rest: which
    // unknowns look null depends on it.
    let identity: Vec<usize> = (0..nd).collect();
    let Ok(order) = crate::factor::EliminationOrder::amd_in_reference(&lower, &identity) else {
        return none();
    };
    let Ok(scan) = crate::factor::scan_pivots(&lower, Some(&order), CANDIDATE_PIVOT) else {
        return none();
    };
    // Kernel columns: fix the scan's unknowns `F`, factor the rest
    // (`M_EE`), and `z_f = e_f − M_EE⁻¹ M_Ef` for each `f` in `F` spans the
    // null space (each is local: the combination through `f`).
    let mut fixed = scan.negligible;
    fixed.extend(scan.negative.iter().map(|&(k, _)| k));
    fixed.sort_unstable();
    fixed.dedup();
    let k = fixed.len();
    if k == 0 {
        return none();
    }
    let mut pos = vec![usize::MAX; nd];
    for (q, &f) in fixed.iter().enumerate() {
        pos[f] = q;
    }
    let mut ee = Vec::with_capacity(m.len());
    let mut rhs_cols: Vec<Vec<(usize, f64)>> = vec![Vec::new(); k];
    for &(i, j, v) in &m {
        match (pos[i], pos[j]) {
            (usize::MAX, usize::MAX) => ee.push((i, j, if i == j { v + KERNEL_SHIFT } else { v })),
            (usize::MAX, qj) => rhs_cols[qj].push((i, v)),
            (qi, usize::MAX) => rhs_cols[qi].push((j, v)),
            _ => {}
        }
    }
    ee.extend(fixed.iter().map(|&f| (f, f, 2.0)));
    drop(m);
    let Ok(ee) = crate::factor::lower_csc(nd, &ee) else {
        return none();
    };
    let Ok(mut factor) = crate::factor::SparseCholesky::factor_ordered(&ee, Some(&order), 32, 1e-14) else {
        return none();
    };
    drop(ee);
    let mut z = vec![0.0; nd * k];
    for (q, col) in rhs_cols.iter().enumerate() {
        for &(i, v) in col {
            z[q * nd + i] -= v;
        }
    }
    factor.solve_columns(&mut z, k);
    for (q, &f) in fixed.iter().enumerate() {
        for &g in &fixed {
            z[q * nd + g] = 0.0;
        }
        z[q * nd + f] = 1.0;
    }
    // Groups of directions the null vectors share (entries above round-off
    // of each vector's largest); a pivoted QR of each group's vectors picks
    // as many directions as it has vectors, those they lean on most.
    let mut root: Vec<usize> = (0..nd).collect();
    let support: Vec<Vec<usize>> = (0..k)
        .map(|q| {
            let col = &z[q * nd..(q + 1) * nd];
            let big = col.iter().fold(0.0f64, |a, v| a.max(v.abs()));
            (0..nd).filter(|&i| col[i].abs() > 1e-10 * big).collect()
        })
        .collect();
    for sup in &support {
        for w in sup.windows(2) {
            let (ra, rb) = (find_root(&mut root, w[0]), find_root(&mut root, w[1]));
            if ra != rb {
                root[ra.max(rb)] = ra.min(rb);
            }
        }
    }
    let mut groups: std::collections::BTreeMap<usize, Vec<usize>> = Default::default();
    for (q, sup) in support.iter().enumerate() {
        let r = find_root(&mut root, sup[0]);
        groups.entry(r).or_default().push(q);
    }
    // Per group, Rayleigh–Ritz on the span of its kernel columns: the
    // combinations below NULL_EIGENVALUE are the (near-)null ones.
    let mut mz = vec![0.0; nd * k];
    crate::factor::sym_matmat(&lower, &z, &mut mz, k);
    let mut picked = Vec::with_capacity(k);
    for vectors in groups.values() {
        let mut dirs: Vec<usize> = vectors.iter().flat_map(|&q| support[q].iter().copied()).collect();
        dirs.sort_unstable();
        dirs.dedup();
        let kg = vectors.len();
        if (kg * kg) as f64 * dirs.len() as f64 > MAX_QR_WORK {
            continue;
        }
        let zg = Mat::from_fn(dirs.len(), kg, |i, a| z[vectors[a] * nd + dirs[i]]);
        let mzg = Mat::from_fn(dirs.len(), kg, |i, a| mz[vectors[a] * nd + dirs[i]]);
        // The two products side by side (each on one thread: the same
        // bits with one thread or two); on the 20³ and 30³ towers cut in
        // 64 with slack cables, one group holds every one of 300–480
        // kernel columns over ~3 300 directions.
        let (gram_z, h) = rayon::join(|| zg.transpose() * &zg, || zg.transpose() * &mzg);
        // An orthonormal basis of their span through B's eigendecomposition
        // (a null direction the scan missed appears in every kernel column
        // it touches, amplified by the shift: B is then nearly singular).
        let Ok(be) = gram_z.self_adjoint_eigen(faer::Side::Lower) else {
            continue;
        };
        let (bu, bl) = (be.U(), be.S().column_vector());
        let bmax = bl.iter().fold(0.0f64, |a, &v| a.max(v));
        let span: Vec<usize> = (0..kg).filter(|&j| bl[j] > 1e-12 * bmax).collect();
        let r = span.len();
        let w = Mat::from_fn(kg, r, |i, j| bu[(i, span[j])] / bl[span[j]].sqrt());
        let c = w.transpose() * &h * &w;
        let c = Mat::from_fn(r, r, |i, j| 0.5 * (c[(i, j)] + c[(j, i)]));
        let Ok(ce) = c.self_adjoint_eigen(faer::Side::Lower) else {
            continue;
        };
        let (cu, theta) = (ce.U(), ce.S().column_vector());
        let coef = &w * cu;
        let null: Vec<usize> = (0..r).filter(|&j| theta[j] < NULL_EIGENVALUE).collect();
        if null.is_empty() {
            continue;
        }
        let nz = &zg * Mat::from_fn(kg, null.len(), |a, j| coef[(a, null[j])]);
        let qr = nz.transpose().to_owned().col_piv_qr();
        let fwd = qr.P().arrays().0;
        picked.extend(fwd[..null.len().min(dirs.len())].iter().map(|&c| dirs[c]));
    }
    let mut per: Vec<Vec<usize>> = vec![Vec::new(); ni];
    for &d in &picked {
        let i = d_off.partition_point(|&o| o <= d) - 1;
        per[i].push(d - d_off[i]);
    }
    per.iter()
        .enumerate()
        .map(|(i, js)| {
            let mut js = js.clone();
            js.sort_unstable();
            Mat::from_fn(s[i].nrows(), js.len(), |a, c| s[i][(a, js[c])])
        })
        .collect()
}

/// `p` without the directions `d` (orthonormal, in its coefficients): `p`
/// times an orthonormal basis of the complement of `d`.
pub fn without_directions(p: &Mat<f64>, d: &Mat<f64>) -> Mat<f64> {
    let m = p.ncols();
    if d.ncols() == 0 {
        return p.clone();
    }
    let proj = Mat::from_fn(m, m, |a, b| {
        let dd: f64 = (0..d.ncols()).map(|j| d[(a, j)] * d[(b, j)]).sum();
        if a == b {
            1.0 - dd
        } else {
            -dd
        }
    });
    let Ok(evd) = proj.self_adjoint_eigen(faer::Side::Lower) else {
        return p.clone();
    };
    let (u, mu) = (evd.U(), evd.S().column_vector());
    let keep: Vec<usize> = (0..m).filter(|&q| mu[q] > 0.5).collect();
    p * Mat::from_fn(m, keep.len(), |a, j| u[(a, keep[j])])
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Three one-column interfaces around a node, `W z = 0` for `z = (1,
    /// 1, 1)` (a circulation): one column goes, the other two stay.
    #[test]
    fn a_circulation_loses_one_column() {
        let s: Vec<Mat<f64>> = (0..3).map(|_| Mat::identity(1, 1)).collect();
        // WᵀW = 2 I − (J − I) for a circulation among three pair forces:
        // off-diagonal −1 (each subdomain sees two of them with opposite
        // signs), eigenvalues 0, 3, 3.
        let gram = vec![(1, 0, -1.0), (2, 0, -1.0), (2, 1, -1.0)];
        let dropped = redundant_directions(&[0, 1, 2], &s, &gram);
        assert_eq!(dropped.iter().map(|d| d.ncols()).sum::<usize>(), 1);
    }

    /// A combination that leaves almost no force (`‖W z‖² ~ 1e-9`, or
    /// `1e-7`, which the threshold of 1e-8 kept) goes too; one that leaves
    /// a little (`1e-5`) stays.
    #[test]
    fn a_near_circulation_goes_and_a_weak_one_stays() {
        let s: Vec<Mat<f64>> = (0..3).map(|_| Mat::identity(1, 1)).collect();
        for (delta, gone) in [(1e-9, 1), (1e-7, 1), (1e-5, 0)] {
            let gram = vec![(1, 0, -1.0), (2, 0, -1.0), (2, 1, -(1.0 - delta))];
            let dropped = redundant_directions(&[0, 1, 2], &s, &gram);
            assert_eq!(dropped.iter().map(|d| d.ncols()).sum::<usize>(), gone, "δ = {delta:e}");
        }
    }

    /// Dropping a direction leaves an orthonormal basis of the rest.
    #[test]
    fn without_directions_keeps_the_rest_orthonormal() {
        let p = Mat::from_fn(4, 3, |i, j| if i == j { 1.0 } else { 0.0 });
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let d = Mat::from_fn(3, 1, |i, _| if i < 2 { h } else { 0.0 });
        let q = without_directions(&p, &d);
        assert_eq!(q.ncols(), 2);
        let qtq = q.transpose() * &q;
        let pd = &p * &d;
        for a in 0..2 {
            for b in 0..2 {
                assert!((qtq[(a, b)] - if a == b { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
            let along: f64 = (0..4).map(|i| q[(i, a)] * pd[(i, 0)]).sum();
            assert!(along.abs() < 1e-12);
        }
    }

    /// Directions of a basis that vanish on the face are found, the others not.
    #[test]
    fn cross_directions_vanish_on_the_face() {
        // Rows 0, 1 face, row 2 cross: column 0 on the face, column 1 on
        // the cross row only.
        let p = Mat::from_fn(3, 2, |i, j| match (i, j) {
            (0, 0) => 1.0,
            (2, 1) => 1.0,
            _ => 0.0,
        });
        let s = cross_directions(&p, &[2]);
        assert_eq!(s.ncols(), 1);
        assert!((s[(1, 0)].abs() - 1.0).abs() < 1e-12 && s[(0, 0)].abs() < 1e-12);
    }
}
