//! The macro space and the coarse problem (docs/design.md §4).
//!
//! [`MacroBasis`]: on each interface, 3 translations, 3 rotations about the
//! centroid and 3 extensions in the average plane (two stretches along the
//! principal axes and the in-plane shear), enriched with the traces of the
//! kernel modes of both neighbours, then orthonormalised with a rank-revealing
//! SVD so that `PᵀP = I` even for one-node, collinear and coplanar interfaces.
//!
//! [`CoarseProblem`]: the saddle point system `L f − G α = Pᵀ J K⁺ r`,
//! `Gᵀ f = Rᵀ r`, assembled from per-subdomain [`CoarseContribution`]s and
//! solved through a sparse Cholesky factorization of the augmented macro
//! block and a small dense Schur complement on `α`. `L` can be nearly
//! singular (redundant multipliers at cross points that the set-up did not
//! drop, soft modes): the block is then regularised, and iterative
//! refinement against the exact system makes the relevant components exact
//! to round-off.

use crate::error::{Error, Result};
use crate::factor::{group_by_key, lower_csc, lower_diagonal, sym_matvec, FactorError, SparseCholesky};
use crate::subdomain::orthonormal_columns;
use faer::sparse::SparseColMat;
use faer::Mat;

/// Orthonormal macro basis of every interface.
#[derive(Debug, Clone)]
pub struct MacroBasis {
    /// `P_Γ` of each interface (`entries × columns`).
    pub blocks: Vec<Mat<f64>>,
    /// Offset of each interface's macro unknowns in the global macro vector.
    pub offset: Vec<usize>,
    /// Total number of macro unknowns.
    pub len: usize,
}

/// Geometric macro modes at points `x` for entries of component `comp`:
/// returns an `entries × m` matrix. The first 9 columns are the
/// translations, the rotations about the centroid and the extensions in
/// the average plane (degree 1); `degree` 2 and 3 add, per component, the
/// monomials `s1^i s2^j` of that total degree in the in-plane coordinates
/// `(s1, s2)` along the principal axes, scaled by the points' largest
/// spread (`m = 9 + 9` for 2, `9 + 9 + 12` for 3). Columns the points do
/// not span (`s2` on a line) are left for the orthonormalisation to drop.
pub fn geometric_modes(points: &[[f64; 3]], comp: &[usize], degree: u8) -> Mat<f64> {
    let n = points.len();
    // Principal axes of the interface's points (average plane).
    let (c, cov) = centred_scatter(points);
    let (a1, a2) = match cov.self_adjoint_eigen(faer::Side::Lower) {
        Ok(eig) => {
            let u = eig.U();
            // Eigenvalues ascend: the last two span the average plane.
            ([u[(0, 2)], u[(1, 2)], u[(2, 2)]], [u[(0, 1)], u[(1, 1)], u[(2, 1)]])
        }
        Err(_) => ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
    };
    // (i, j) of every monomial s1^i s2^j of total degree 2..=degree.
    let monomials: Vec<(i32, i32)> = (2..=degree as i32)
        .flat_map(|t| (0..=t).rev().map(move |i| (i, t - i)))
        .collect();
    let spread = points
        .iter()
        .flat_map(|p| (0..3).map(move |d| (p[d] - c[d]).abs()))
        .fold(0.0f64, f64::max);
    let spread = if spread > 0.0 { spread } else { 1.0 };
    Mat::from_fn(n, 9 + 3 * monomials.len(), |j, q| {
        let d = comp[j];
        let x = [points[j][0] - c[0], points[j][1] - c[1], points[j][2] - c[2]];
        let s1 = a1[0] * x[0] + a1[1] * x[1] + a1[2] * x[2];
        let s2 = a2[0] * x[0] + a2[1] * x[1] + a2[2] * x[2];
        match q {
            0..=2 => (d == q) as u8 as f64,
            3..=5 => {
                // ω = e_{q-3}; (ω × x)_d
                let w = q - 3;
                let mut om = [0.0; 3];
                om[w] = 1.0;
                let cr = [
                    om[1] * x[2] - om[2] * x[1],
                    om[2] * x[0] - om[0] * x[2],
                    om[0] * x[1] - om[1] * x[0],
                ];
                cr[d]
            }
            6 => s1 * a1[d],
            7 => s2 * a2[d],
            8 => s2 * a1[d] + s1 * a2[d],
            _ => {
                let (component, k) = ((q - 9) / monomials.len(), (q - 9) % monomials.len());
                if component != d {
                    return 0.0;
                }
                let (i, e) = monomials[k];
                (s1 / spread).powi(i) * (s2 / spread).powi(e)
            }
        }
    })
}

/// Number of distinct points among `points` (the nodes of an interface's
/// entries: up to three entries share one).
pub fn distinct_points(points: &[[f64; 3]]) -> usize {
    let mut bits: Vec<[u64; 3]> = points.iter().map(|p| p.map(f64::to_bits)).collect();
    bits.sort_unstable();
    bits.dedup();
    bits.len()
}

/// Centroid of `points` and the sum of the outer products of their
/// offsets from it (the scatter matrix, whose eigenvectors are the
/// principal axes).
fn centred_scatter(points: &[[f64; 3]]) -> ([f64; 3], Mat<f64>) {
    let n = points.len();
    let mut c = [0.0; 3];
    for p in points {
        for d in 0..3 {
            c[d] += p[d] / n as f64;
        }
    }
    let mut scatter = Mat::<f64>::zeros(3, 3);
    for p in points {
        for i in 0..3 {
            for j in 0..3 {
                scatter[(i, j)] += (p[i] - c[i]) * (p[j] - c[j]);
            }
        }
    }
    (c, scatter)
}

/// Whether `points` make a flat structure: the smallest principal spread
/// at most [`crate::settings::FLAT_SPREAD_RATIO`] of the middle one
/// (what [`crate::settings::MacroDegree::Auto`] asks).
pub fn is_flat(points: &[[f64; 3]]) -> bool {
    if points.is_empty() {
        return false;
    }
    match centred_scatter(points).1.self_adjoint_eigen(faer::Side::Lower) {
        Ok(eig) => {
            // Ascending: the smallest and the middle variance.
            let s = eig.S();
            let (small, middle) = (s[0].max(0.0).sqrt(), s[1].max(0.0).sqrt());
            middle > 0.0 && small <= crate::settings::FLAT_SPREAD_RATIO * middle
        }
        Err(_) => false,
    }
}

impl MacroBasis {
    /// Builds the basis of one interface from its geometric modes up to
    /// `degree` ([`geometric_modes`]) and the kernel traces of its two
    /// subdomains (`trace_lo`, `trace_hi`: `entries × r` each), ranked at
    /// `rtol` ([`MACRO_RANK_RTOL`] or [`SOFT_TRACE_RTOL`]).
    pub fn interface_block(
        points: &[[f64; 3]],
        comp: &[usize],
        trace_lo: &Mat<f64>,
        trace_hi: &Mat<f64>,
        degree: u8,
        rtol: f64,
    ) -> Mat<f64> {
        let g = geometric_modes(points, comp, degree);
        let ng = g.ncols();
        let n = points.len();
        let m = ng + trace_lo.ncols() + trace_hi.ncols();
        let all = Mat::from_fn(n, m, |i, j| {
            if j < ng {
                g[(i, j)]
            } else if j < ng + trace_lo.ncols() {
                trace_lo[(i, j - ng)]
            } else {
                trace_hi[(i, j - ng - trace_lo.ncols())]
            }
        });
        orthonormal_columns(&all, rtol)
    }

    /// The basis of one interface from the kernel traces of its two
    /// subdomains alone (FETI's natural coarse space, what `monolevel`
    /// keeps): no columns between two regular subdomains.
    pub fn kernel_block(trace_lo: &Mat<f64>, trace_hi: &Mat<f64>) -> Mat<f64> {
        let n = trace_lo.nrows();
        let (a, b) = (trace_lo.ncols(), trace_hi.ncols());
        if a + b == 0 {
            return Mat::zeros(n, 0);
        }
        let all = Mat::from_fn(
            n,
            a + b,
            |i, j| if j < a { trace_lo[(i, j)] } else { trace_hi[(i, j - a)] },
        );
        orthonormal_columns(&all, MACRO_RANK_RTOL)
    }

    /// Assembles the per-interface blocks.
    pub fn from_blocks(blocks: Vec<Mat<f64>>) -> MacroBasis {
        let mut offset = Vec::with_capacity(blocks.len());
        let mut len = 0;
        for b in &blocks {
            offset.push(len);
            len += b.ncols();
        }
        MacroBasis { blocks, offset, len }
    }
}

/// One subdomain's share of the coarse problem: its block of `L`
/// (`W_Eᵀ K_E⁺ W_E`) and of `G` (`W_Eᵀ R_E`) on its macro columns.
#[derive(Debug, Clone)]
pub struct CoarseContribution {
    /// Global macro index of each local macro column.
    pub cols: Vec<usize>,
    /// `m_E × m_E` block of `L` (symmetric up to round-off).
    pub l: Mat<f64>,
    /// `m_E × r_E` block of `G`.
    pub g: Mat<f64>,
    /// Offset of this subdomain's kernel amplitudes in `α`.
    pub alpha_off: usize,
}

/// The factored coarse saddle-point system
/// `L f − G α = a`, `Gᵀ f = b` (docs/design.md §4).
///
/// `L` and `G` are block sparse (a subdomain couples only the macro
/// unknowns of its own interfaces), so the system is solved by a Schur
/// complement on `α` over a *sparse* Cholesky factorization of the
/// augmented macro block `L_γ = L + γ G Gᵀ + ε I`:
/// - the augmentation `γ G Gᵀ` (with `γ` = median diag `L`, `G` being
///   dimensionless) makes `L_γ` definite on directions that only `G`
///   restrains, without changing the solution (`Gᵀ f = b` is imposed);
/// - `ε = 1e-10 · max(L_ii, φ γ)` per entry covers the redundant
///   multipliers at cross points, which act on nothing; GMRES on the exact
///   system, preconditioned by this factorization, removes the
///   perturbation (one cycle of a few iterations in practice);
/// - `S = Gᵀ L_γ⁻¹ G` is small (one row per kernel mode) and kept as its
///   dense Cholesky factor. It is formed as `Bᵀ B` from `B = L⁻¹ P G`
///   (`L_γ = Pᵀ L Lᵀ P`): forward substitutions only, whose columns stay
///   sparse, and `B` is kept for the solves.
///
/// Every solve is allocation free.
pub struct CoarseProblem {
    /// Number of macro unknowns `f`.
    pub n_macro: usize,
    /// Number of kernel unknowns `α`.
    pub n_kernel: usize,
    /// Exact `L` (lower triangle), for the refinement residuals.
    l_lower: SparseColMat<usize, f64>,
    /// `G` by columns.
    g: KernelCoupling,
    gamma: f64,
    factor: SparseCholesky,
    /// Cholesky factor of `S = Gᵀ L_γ⁻¹ G` (lower triangle, `n_kernel` square).
    s_factor: Mat<f64>,
    /// `B = L⁻¹ P G` (forward-substituted kernel columns, sparse), kept
    /// from the set-up where it fits ([`MAX_KERNEL_COLUMN_VALUES`]): an
    /// inner solve is then one forward and one backward substitution and
    /// two products with `B`, instead of two solves.
    kernel_columns: Option<KernelColumns>,
    /// Right-hand side `[a; b]`, written by the caller before [`CoarseProblem::solve`].
    pub rhs: Vec<f64>,
    /// Solution `[f; α]` after [`CoarseProblem::solve`].
    pub solution: Vec<f64>,
    residual: Vec<f64>,
    correction: Vec<f64>,
    /// GMRES workspace: Arnoldi basis `V` (`KRYLOV_DIM + 1` columns),
    /// preconditioned directions `Z`, Hessenberg matrix, rotations.
    krylov: Krylov,
    work_f: Vec<f64>,
    work_f2: Vec<f64>,
    work_a: Vec<f64>,
    /// Seconds spent assembling and factoring.
    pub setup_s: f64,
    last_residual: f64,
    worst_residual: f64,
    /// Solves with the regularised factorization since set-up.
    inner_solves: usize,
    /// Backward error the refinement stops at ([`BACKWARD_ERROR_TARGET`]
    /// unless a caller relaxes it: [`Self::set_refinement_target`]).
    target: f64,
    /// `1/√L_ii` per macro row: the backward error of the macro block is
    /// measured on the Jacobi-scaled system (see [`Self::last_residual`]).
    row_scale: Vec<f64>,
}

impl std::fmt::Debug for CoarseProblem {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CoarseProblem")
            .field("n_macro", &self.n_macro)
            .field("n_kernel", &self.n_kernel)
            .field("nnz_factor", &self.factor.nnz_l())
            .finish()
    }
}

/// Krylov dimension of the refinement (GMRES, restarted); most cycles.
/// Relative singular value below which a column of an interface's macro
/// basis counts as dependent on the others. The kernel traces that repeat
/// a geometric mode carry the kernel vectors' round-off (up to ~5e-11 of
/// the largest on the 130² grid); at 1e-10 that noise decided the rank
/// (371 or 372 columns on the 130² grid: 82 or 69 cg iterations; on its
/// nonsmooth twin with 64 subdomains the smaller bases left cg stalled at
/// 6e-3 after 752 iterations, and at 1e-12 it converges in 463). Below the
/// noise, a kept column is an orthonormal direction more, which costs a
/// coarse unknown and never an answer.
pub const MACRO_RANK_RTOL: f64 = 1e-12;

/// [`MACRO_RANK_RTOL`] for a macro space without the adaptive columns: the
/// kernel traces' deviations from the geometric modes are kept down to
/// round-off. They point along the subdomains' softest modes, the only
/// such enrichment such a space has, and at 1e-12 the threshold cut
/// through them (relative singular values spread from 1e-9 to 1e-16 on the
/// 410² plate cut in 64): one column more or less moved its cg count
/// between 20 and 28 with round-off alone; at 1e-14 it is 19 whatever the
/// factorization's round-off. With the adaptive space (stiffness
/// contrast) they duplicate its columns: there the 12³ contrast tower cut
/// in 64 stalled at 1e-14 (BENCHMARKS.md, session 45).
pub const SOFT_TRACE_RTOL: f64 = 1e-14;

const KRYLOV_DIM: usize = 30;
const MAX_CYCLES: usize = 3;
/// GMRES iterations between looks at the corrected solution's true
/// backward error.
const TRUE_ERROR_EVERY: usize = 4;
/// Backward error (see [`CoarseProblem::last_residual`]) at which the coarse
/// solve stops: a few tens of units of round-off, what the Jacobi-scaled
/// macro block of thousands of unknowns leaves (its floor was 2e-15 to
/// 4e-15 on the 1e6-dof plate and the 30³ tower, reached in two GMRES
/// iterations; at 1e-15 each cycle then ran its 30 iterations without
/// gaining). (A relative residual target cannot be met when `x` is large
/// along a soft mode: the round-off of `A x` alone is `ε ‖A‖ ‖x‖`.)
const BACKWARD_ERROR_TARGET: f64 = 1e-14;
/// Regularisation of the macro block, relative to each diagonal entry: a
/// shift relative to the largest entry would swamp the stiff macro modes
/// (the diagonal of `L` spans 7 decades on a 2.4e5-dof plate with 64
/// subdomains) and leave refinement stalled at 10% residual. Only the
/// redundant cross-point directions need it (their exact eigenvalue is 0),
/// and every other direction pays for it: where soft modes (cables
/// without their slack neighbours, 1e8 contrast) bring eigenvalues near
/// 1e-10 of their diagonal, 1e-10 left the regularised factor a poor
/// preconditioner and each coarse solve took 25–31 GMRES iterations (the
/// nonsmooth 12³ tower on 64 subdomains: 90 % of the run); at 1e-13, 9.
/// Where the pivots then fail, the floors below raise it.
const MACRO_REGULARIZATION: f64 = 1e-13;
/// Smallest pivot, relative to its diagonal entry, for which the macro
/// block is factored as it is, without [`MACRO_REGULARIZATION`]. The shift
/// leaves each solve a backward error of about its own size (5e-14 to
/// 1e-13 on the 30³ tower and the 130² plate with 64 subdomains, above the
/// [`BACKWARD_ERROR_TARGET`]), so every coarse solve took a refinement
/// step, a second solve with the factor; unshifted, one solve meets the
/// target (2e-15 to 4e-15). But where soft directions bring pivots near
/// the shift (ratios 4e-11 on a nonsmooth 12³ tower's slack set, 2e-13 on
/// the 10³ contrast tower cut in 64 with the edges' constraints) the
/// unshifted factor's round-off along them took cg 2× the iterations; the
/// regular cases seen had ratios of 1e-4 to 8e-9.
const EXACT_MIN_PIVOT: f64 = 1e-8;
/// Floors `φ` of the diagonal entries the regularisation is relative to, as
/// fractions of the median entry, tried in turn: they keep the redundant
/// (null) directions at cross points clear of round-off when their
/// diagonal entries are tiny. (Scaled by the largest entry, the 1e6-dof
/// plate with 16 subdomains needed 1e-4.) The last floor is a uniform
/// shift; GMRES then does the rest.
const REGULARIZATION_FLOORS: &[f64] = &[1e-8, 1e-6, 1e-4, 1e-2, 1.0];
/// Columns per batched solve when forming `B = L⁻¹ P G` (or `L_γ⁻¹ G`).
const SCHUR_BATCH: usize = 32;

/// `G` assembled from the subdomains' `G_E` and found of full column rank
/// by [`CoarseProblem::check_restrained`]: what
/// [`CoarseProblem::new_checked`] builds the coarse problem on.
pub(crate) struct RestrainedCoupling(KernelCoupling);

impl CoarseProblem {
    /// Assembles and factors the coarse system from the subdomain
    /// contributions. `G` must have full column rank, otherwise a kernel
    /// mode of some subdomain is not restrained by the interfaces and the
    /// structure is a mechanism (`kernel_owner` names the subdomain of each
    /// column of `G`).
    pub fn new(
        n_macro: usize,
        n_kernel: usize,
        parts: &[CoarseContribution],
        kernel_owner: &[usize],
    ) -> Result<CoarseProblem> {
        Self::new_described(n_macro, n_kernel, parts, kernel_owner, &|_| String::new())
    }

    /// [`CoarseProblem::new`] whose mechanism message ends with
    /// `describe(α)`, `α` the kernel coefficients of the unrestrained mode
    /// (the caller knows the kernel bases and can say where it moves).
    pub fn new_described(
        n_macro: usize,
        n_kernel: usize,
        parts: &[CoarseContribution],
        kernel_owner: &[usize],
        describe: &dyn Fn(&[f64]) -> String,
    ) -> Result<CoarseProblem> {
        let views: Vec<(&[usize], &Mat<f64>, usize)> = parts.iter().map(|p| (&p.cols[..], &p.g, p.alpha_off)).collect();
        let g = Self::check_restrained(n_macro, n_kernel, &views, kernel_owner, describe)?;
        Self::new_checked(n_macro, parts, g)
    }

    /// Fails as [`CoarseProblem::new_described`] does when `G` is rank
    /// deficient (the structure is a mechanism), from `G` alone: each
    /// subdomain's `(cols, G_E, alpha_off)`. A set-up checks this before
    /// the solves `L` needs, which a mechanism would waste (the nonsmooth
    /// cg's exact steps on sets that leave one), and then builds the
    /// problem with [`CoarseProblem::new_checked`].
    pub(crate) fn check_restrained(
        n_macro: usize,
        n_kernel: usize,
        parts: &[(&[usize], &Mat<f64>, usize)],
        kernel_owner: &[usize],
        describe: &dyn Fn(&[f64]) -> String,
    ) -> Result<RestrainedCoupling> {
        let g = kernel_coupling(n_macro, n_kernel, parts.iter().copied())?;
        if n_kernel > 0 {
            check_full_rank(&g, kernel_owner, describe)?;
        }
        Ok(RestrainedCoupling(g))
    }

    /// [`CoarseProblem::new_described`] for contributions whose `G` passed
    /// [`CoarseProblem::check_restrained`] (`g`, assembled there from the
    /// same `G_E`, is not assembled again).
    pub(crate) fn new_checked(
        n_macro: usize,
        parts: &[CoarseContribution],
        g: RestrainedCoupling,
    ) -> Result<CoarseProblem> {
        let t0 = std::time::Instant::now();
        let nf = n_macro;
        let g = g.0;
        let na = g.ncols();

        // Exact L (symmetrised) and the augmented, regularised L_γ, on one
        // pattern.
        let blocks = MacroBlocks::assemble(nf, parts);
        let l_lower = blocks.matrix(blocks.exact.clone());
        let ldiag = lower_diagonal(&l_lower);
        if ldiag.iter().any(|v| !v.is_finite()) {
            return Err(Error::Numerical("the coarse operator is not finite".into()));
        }
        let lscale = typical_scale(&ldiag);
        // A diagonal entry below 1e-12 of the typical one (or not positive)
        // is floored there, so that its row is not weighted without bound.
        let row_scale: Vec<f64> = ldiag
            .iter()
            .map(|&d| 1.0 / d.max(1e-12 * lscale).max(f64::MIN_POSITIVE).sqrt())
            .collect();
        let gamma = lscale;
        // γ G_E G_Eᵀ on each subdomain's own columns: the pattern of L.
        let aug = blocks.augmented(gamma);
        // First the macro block unshifted: kept where it is clearly definite
        // (see [`EXACT_MIN_PIVOT`]). Otherwise the regularised block, with
        // the smallest floor first (most accurate) and a larger one when
        // round-off on the redundant directions still gives a non-positive
        // pivot.
        let shifted_lower = |reg: f64, floor: f64| -> Result<SparseColMat<usize, f64>> {
            let mut shifted = aug.clone();
            if reg > 0.0 {
                for (j, &d) in ldiag.iter().enumerate() {
                    // The diagonal is each column's first entry.
                    shifted[blocks.col_ptr[j]] += reg * d.max(floor * lscale);
                }
            }
            Ok(blocks.matrix(shifted))
        };
        let unshifted = shifted_lower(0.0, 1.0)?;
        // Any factor of the unshifted block, clearly definite or not, holds
        // the symbolic analysis the shifted blocks (same pattern) reuse.
        // The coarse problem is factored alone, between the subdomain
        // loops: on every thread.
        let par = crate::factor::pool_par();
        let mut analysed = SparseCholesky::factor_with(&unshifted, None, SCHUR_BATCH, 0.0, par).ok();
        let exact = analysed
            .as_ref()
            .is_some_and(|f| f.min_pivot_ratio(&unshifted) >= EXACT_MIN_PIVOT);
        drop(unshifted);
        let mut factor = if exact { analysed.take() } else { None };
        if factor.is_none() {
            for &floor in REGULARIZATION_FLOORS {
                let lower = shifted_lower(MACRO_REGULARIZATION, floor)?;
                let pivot_ratio = 0.01 * MACRO_REGULARIZATION * floor;
                let attempt = match analysed.take() {
                    Some(mut f) => match f.refactor(&lower, pivot_ratio) {
                        Ok(()) => Ok(f),
                        Err(e @ FactorError::Pivot { .. }) => {
                            analysed = Some(f);
                            Err(e)
                        }
                        // Another pattern after all: analysed afresh.
                        Err(FactorError::Internal(_)) => {
                            SparseCholesky::factor_with(&lower, None, SCHUR_BATCH, pivot_ratio, par)
                        }
                    },
                    None => SparseCholesky::factor_with(&lower, None, SCHUR_BATCH, pivot_ratio, par),
                };
                match attempt {
                    Ok(f) => {
                        factor = Some(f);
                        break;
                    }
                    Err(FactorError::Pivot { .. }) => continue,
                    Err(e) => {
                        return Err(Error::Numerical(format!(
                            "the coarse problem could not be factored: {e:?}"
                        )))
                    }
                }
            }
        }
        drop(aug);
        drop(blocks);
        let mut factor = factor.ok_or_else(|| {
            Error::Numerical("the coarse problem could not be factored even with the largest regularisation".into())
        })?;

        // S = Gᵀ L_γ⁻¹ G = Bᵀ B with B = L⁻¹ P G: forward substitutions
        // only, which keep G's sparsity (a column is nonzero only where the
        // elimination tree reaches from its rows), and B is kept for the
        // inner solves. Where B would not fit, S from full solves instead.
        let kernel_columns = if na > 0 {
            KernelColumns::forward(&mut factor, &g, MAX_KERNEL_COLUMN_VALUES)
        } else {
            None
        };
        let s = match &kernel_columns {
            Some(b) => b.gram(na),
            None => schur_by_solves(&mut factor, &g),
        };
        // S's Cholesky factor, kept for two triangular solves per inner
        // solve: as many multiply-adds as a product with S⁻¹, without the
        // inverse's n³ (0.03-0.12 s per set-up with 1 000 kernel modes).
        let s_factor = if na > 0 {
            let sym = Mat::from_fn(na, na, |i, j| 0.5 * (s[(i, j)] + s[(j, i)]));
            let llt = sym
                .llt(faer::Side::Lower)
                .map_err(|_| Error::Numerical("the coarse kernel block is not positive definite".into()))?;
            llt.L().to_owned()
        } else {
            Mat::zeros(0, 0)
        };
        if s_factor.col_iter().any(|c| c.iter().any(|v| !v.is_finite())) {
            return Err(Error::Numerical("coarse problem could not be factored".into()));
        }
        let n = nf + na;
        Ok(CoarseProblem {
            n_macro: nf,
            n_kernel: na,
            l_lower,
            g,
            gamma,
            factor,
            s_factor,
            kernel_columns,
            rhs: vec![0.0; n],
            solution: vec![0.0; n],
            residual: vec![0.0; n],
            correction: vec![0.0; n],
            krylov: Krylov::new(n),
            work_f: vec![0.0; nf],
            work_f2: vec![0.0; nf],
            work_a: vec![0.0; na],
            last_residual: 0.0,
            worst_residual: 0.0,
            inner_solves: 0,
            target: BACKWARD_ERROR_TARGET,
            row_scale,
            setup_s: t0.elapsed().as_secs_f64(),
        })
    }

    /// A coarse problem from dense `L` (`nf × nf`) and `G` (`nf × na`), for
    /// tests and benchmarks.
    pub fn from_dense(l: &Mat<f64>, g: &Mat<f64>, kernel_owner: &[usize]) -> Result<CoarseProblem> {
        let part = CoarseContribution {
            cols: (0..l.nrows()).collect(),
            l: l.clone(),
            g: g.clone(),
            alpha_off: 0,
        };
        CoarseProblem::new(l.nrows(), g.ncols(), &[part], kernel_owner)
    }

    /// Solves for `rhs = [a; b] = [Pᵀ J K⁺ r; Rᵀ r]` (the sign
    /// convention of docs/design.md §4); the solution is `[f; α]`. No allocation.
    ///
    /// The factorization is exact where the macro block is clearly definite,
    /// and exact up to its shift otherwise, so one solve is usually within
    /// round-off or one refinement step of it; where `L` has eigenvalues below the shift
    /// (large, ill-conditioned plates) it is used as the preconditioner of a
    /// restarted GMRES on the exact saddle system, which resolves those few
    /// directions in a few iterations where plain refinement would contract
    /// them by 0.1 % per pass on the 1e6-dof plate.
    pub fn solve(&mut self) {
        let nf = self.n_macro;
        let n = nf + self.n_kernel;
        let rhs = std::mem::take(&mut self.rhs);
        let mut sol = std::mem::take(&mut self.solution);
        let mut res = std::mem::take(&mut self.residual);
        let mut cor = std::mem::take(&mut self.correction);
        let mut kr = std::mem::take(&mut self.krylov);
        let row_scale = std::mem::take(&mut self.row_scale);
        self.inner_solve(&rhs, &mut sol);
        let mut error = 0.0;
        for cycle in 0..=MAX_CYCLES {
            let prev = error;
            let (e, scale_f, scale_a) = self.backward_error(&rhs, &sol, &mut res, &row_scale);
            error = e;
            // Stop at round-off, when a cycle no longer halves the true
            // residual (its floor), or out of cycles.
            if !(error > self.target) || (cycle > 0 && !(error < 0.5 * prev)) || cycle == MAX_CYCLES {
                break;
            }
            // Right-preconditioned GMRES from the current solution, on the
            // system whose two blocks of rows are divided by their own
            // scales: the residual it minimises is then the backward error
            // of both blocks at once. (On the unscaled residual, a target on
            // the smaller scale lay below the other block's round-off, so
            // every cycle ran all its iterations: 31 inner solves per coarse
            // solve, 39 % of a 3D tower's run, where 2 or 3 suffice; a target
            // on the larger scale left the kernel block inexact and CG
            // stalled at a 5e-6 tension error on the 1e6-dof plate.)
            let weight_of = |s: f64| if s > 0.0 { 1.0 / s } else { 1.0 };
            let (weight_f, weight_a) = (weight_of(scale_f), weight_of(scale_a));
            let weight = |i: usize| if i < nf { row_scale[i] * weight_f } else { weight_a };
            for (i, (v, &r)) in kr.v[..n].iter_mut().zip(&res).enumerate() {
                *v = r * weight(i);
            }
            let beta = kr.v[..n].iter().map(|x| x * x).sum::<f64>().sqrt();
            kr.v[..n].iter_mut().for_each(|v| *v /= beta);
            let target = 0.5 * self.target;
            kr.g.iter_mut().for_each(|x| *x = 0.0);
            kr.g[0] = beta;
            let mut k = 0;
            while k < KRYLOV_DIM {
                let (vk, rest) = kr.v[k * n..].split_at_mut(n);
                let zk = &mut kr.z[k * n..(k + 1) * n];
                // z = M⁻¹ W⁻¹ v and w = W A z, `W` the row weights (`cor`
                // is free until the update below).
                for (i, (c, &v)) in cor.iter_mut().zip(vk.iter()).enumerate() {
                    *c = v / weight(i);
                }
                self.inner_solve(&cor, zk);
                let w = &mut rest[..n];
                self.apply(zk, w);
                for (i, wi) in w.iter_mut().enumerate() {
                    *wi *= weight(i);
                }
                // Modified Gram–Schmidt against v_0 … v_k.
                let (basis, w) = kr.v.split_at_mut((k + 1) * n);
                let w = &mut w[..n];
                let h = &mut kr.h[k * (KRYLOV_DIM + 1)..(k + 1) * (KRYLOV_DIM + 1)];
                for i in 0..=k {
                    let vi = &basis[i * n..(i + 1) * n];
                    let hik: f64 = vi.iter().zip(w.iter()).map(|(a, b)| a * b).sum();
                    h[i] = hik;
                    for (wj, &vj) in w.iter_mut().zip(vi) {
                        *wj -= hik * vj;
                    }
                }
                let hnext = w.iter().map(|v| v * v).sum::<f64>().sqrt();
                h[k + 1] = hnext;
                if hnext > 0.0 {
                    w.iter_mut().for_each(|v| *v /= hnext);
                }
                // Previous rotations, then a new one that zeroes h[k+1].
                for i in 0..k {
                    let (c, s) = (kr.cs[i], kr.sn[i]);
                    let (a, b) = (h[i], h[i + 1]);
                    h[i] = c * a + s * b;
                    h[i + 1] = -s * a + c * b;
                }
                let r = h[k].hypot(h[k + 1]);
                let (c, s) = if r > 0.0 { (h[k] / r, h[k + 1] / r) } else { (1.0, 0.0) };
                kr.cs[k] = c;
                kr.sn[k] = s;
                h[k] = r;
                h[k + 1] = 0.0;
                kr.g[k + 1] = -s * kr.g[k];
                kr.g[k] *= c;
                k += 1;
                if !(kr.g[k].abs() > target) || !(hnext > 0.0) || !(r > 0.0) {
                    break;
                }
                // GMRES's estimate is weighted by the scales of the cycle's
                // start; where the correction is large along soft modes, the
                // backward error of the corrected solution (its own scales)
                // is met long before the estimate says so: look every few
                // iterations (one product with the system, no solve).
                if k % TRUE_ERROR_EVERY == 0 && k < KRYLOV_DIM {
                    kr.correction(k, n, &mut cor);
                    for (c, &x) in cor.iter_mut().zip(&sol) {
                        *c += x;
                    }
                    let (e, _, _) = self.backward_error(&rhs, &cor, &mut res, &row_scale);
                    if !(e > self.target) {
                        break;
                    }
                }
            }
            kr.correction(k, n, &mut cor);
            for (x, &c) in sol.iter_mut().zip(&cor) {
                *x += c;
            }
        }
        self.last_residual = error;
        if !(error <= self.worst_residual) {
            self.worst_residual = error;
        }
        self.rhs = rhs;
        self.solution = sol;
        self.residual = res;
        self.correction = cor;
        self.krylov = kr;
        self.row_scale = row_scale;
    }

    /// `res = rhs − A x` and the backward error of `x`, block by block (`L`
    /// and `G` carry different units), with the scales it is measured
    /// against (macro rows, kernel rows): each residual against what
    /// round-off in `A x` and `rhs` can leave there. The macro block is
    /// measured on the Jacobi-scaled system `D^-½ L D^-½` (unit diagonal,
    /// norm ~1): the diagonal of `L` spans ten decades on the 1e6-dof
    /// plate, so against the largest entry the ordinary rows would be left
    /// 1e10 times above their own round-off.
    fn backward_error(&mut self, rhs: &[f64], x: &[f64], res: &mut [f64], row_scale: &[f64]) -> (f64, f64, f64) {
        let nf = self.n_macro;
        self.residual_into(rhs, x, res);
        // After `residual_into`, `work_f` holds `G α`.
        let norm = |v: &[f64]| v.iter().map(|x| x * x).sum::<f64>().sqrt();
        let scaled_norm = |v: &[f64], up: bool| {
            v.iter()
                .zip(row_scale)
                .map(|(x, s)| if up { x / s } else { x * s })
                .map(|x| x * x)
                .sum::<f64>()
                .sqrt()
        };
        let scale_f = scaled_norm(&x[..nf], true) + scaled_norm(&self.work_f, false) + scaled_norm(&rhs[..nf], false);
        let scale_a = norm(&x[..nf]) + norm(&rhs[nf..]);
        let part = |r: f64, s: f64| {
            if s > 0.0 {
                r / s
            } else if r > 0.0 {
                f64::INFINITY
            } else {
                0.0
            }
        };
        let error = part(scaled_norm(&res[..nf], false), scale_f).max(part(norm(&res[nf..]), scale_a));
        (error, scale_f, scale_a)
    }

    /// `y = [L f − G α; Gᵀ f]` for `x = [f; α]`.
    fn apply(&mut self, x: &[f64], y: &mut [f64]) {
        let nf = self.n_macro;
        let (yf, ya) = y.split_at_mut(nf);
        sym_matvec(&self.l_lower, &x[..nf], yf);
        self.g.mul_into(&x[nf..], &mut self.work_f);
        for (a, &b) in yf.iter_mut().zip(&self.work_f) {
            *a -= b;
        }
        self.g.t_mul_into(&x[..nf], ya);
    }

    /// `res = rhs − A x`.
    fn residual_into(&mut self, rhs: &[f64], x: &[f64], res: &mut [f64]) {
        self.apply(x, res);
        for (r, &b) in res.iter_mut().zip(rhs) {
            *r = b - *r;
        }
    }

    /// One solve of the augmented, regularised system (see the type docs).
    fn inner_solve(&mut self, rhs: &[f64], out: &mut [f64]) {
        self.inner_solves += 1;
        let nf = self.n_macro;
        let (a, b) = rhs.split_at(nf);
        let (f, alpha) = out.split_at_mut(nf);
        // c = a + γ G b
        self.g.mul_into(b, &mut self.work_f);
        for i in 0..nf {
            f[i] = a[i] + self.gamma * self.work_f[i];
        }
        // With L_γ = Pᵀ L Lᵀ P: y = L_γ⁻¹ c, α = S⁻¹ (b − Gᵀ y), f = y +
        // L_γ⁻¹ G α. With B = L⁻¹ P G kept: w = L⁻¹ P c, Gᵀ y = Bᵀ w, f =
        // Pᵀ L⁻ᵀ (w + B α).
        if let Some(bc) = &self.kernel_columns {
            self.factor.forward_columns(f, 1);
            bc.transpose_mul(f, &mut self.work_a);
            for (w, &bi) in self.work_a.iter_mut().zip(b) {
                *w = bi - *w;
            }
            alpha.copy_from_slice(&self.work_a);
            cholesky_solve(&self.s_factor, alpha);
            bc.mul_add(alpha, f);
            self.factor.backward_columns(f, 1);
            return;
        }
        self.factor.solve_in_place(f);
        self.g.t_mul_into(f, &mut self.work_a);
        for (w, &bi) in self.work_a.iter_mut().zip(b) {
            *w = bi - *w;
        }
        alpha.copy_from_slice(&self.work_a);
        cholesky_solve(&self.s_factor, alpha);
        self.g.mul_into(alpha, &mut self.work_f2);
        self.factor.solve_in_place(&mut self.work_f2);
        for (fi, &w) in f.iter_mut().zip(&self.work_f2) {
            *fi += w;
        }
    }

    /// Drops the kept `B = L⁻¹ P G`, so that inner solves take two solves
    /// with the factor (tests compare the two routes).
    #[doc(hidden)]
    pub fn forget_kernel_solves(&mut self) {
        self.kernel_columns = None;
    }

    /// Whether the set-up kept `B = L⁻¹ P G` (see [`MAX_KERNEL_COLUMN_VALUES`]).
    pub fn kernel_solves_kept(&self) -> bool {
        self.kernel_columns.is_some()
    }

    /// The operator `L` as a dense matrix (for tests on small cases).
    pub fn operator(&self) -> Mat<f64> {
        let nf = self.n_macro;
        let mut m = Mat::<f64>::zeros(nf, nf);
        let a = self.l_lower.as_ref();
        for j in 0..nf {
            for (i, &v) in a.row_idx_of_col(j).zip(a.val_of_col(j)) {
                m[(i, j)] = v;
                m[(j, i)] = v;
            }
        }
        m
    }

    /// Backward error of the last solve on the exact coarse system, the
    /// larger of the two blocks: `‖D^-½ (a − L f + G α)‖ / (‖D^½ f‖ +
    /// ‖D^-½ G α‖ + ‖D^-½ a‖)` with `D` the diagonal of `L` (the
    /// Jacobi-scaled system, norm ~1), and `‖b − Gᵀ f‖ / (‖f‖ + ‖b‖)`
    /// (`‖G‖` ~ 1). Round-off (≈ 1e-16) means `x` is exact for a system
    /// within round-off of the true one, row by row of `L` up to its scale.
    pub fn last_residual(&self) -> f64 {
        self.last_residual
    }

    /// Solves with the factorization since set-up: one per coarse solve,
    /// plus one per GMRES iteration of the refinement.
    pub fn inner_solves(&self) -> usize {
        self.inner_solves
    }

    /// Largest [`last_residual`](Self::last_residual) since set-up (NaN if
    /// any solve produced NaN): how far from exact the coarse step has been.
    pub fn worst_residual(&self) -> f64 {
        self.worst_residual
    }

    /// Sets the backward error the refinement of later solves stops at
    /// (never below round-off, `BACKWARD_ERROR_TARGET`): a caller that
    /// solves only loosely (the nonsmooth CG's early active-set steps) need
    /// not pay for round-off accuracy of each coarse solve.
    pub fn set_refinement_target(&mut self, target: f64) {
        self.target = target.max(BACKWARD_ERROR_TARGET);
    }

    /// The backward error the refinement stops at.
    pub fn refinement_target(&self) -> f64 {
        self.target
    }

    /// Stored entries of the coarse factor.
    pub fn nnz_factor(&self) -> usize {
        self.factor.nnz_l()
    }

    /// Macro forces `f` of the last solve.
    pub fn macro_forces(&self) -> &[f64] {
        &self.solution[..self.n_macro]
    }

    /// Kernel amplitudes `α` of the last solve.
    pub fn kernel_amplitudes(&self) -> &[f64] {
        &self.solution[self.n_macro..]
    }
}

/// Workspace of the restarted GMRES in [`CoarseProblem::solve`].
#[derive(Default)]
struct Krylov {
    v: Vec<f64>,
    z: Vec<f64>,
    /// Column `k` of the Hessenberg matrix at `h[k (m + 1)..]`.
    h: Vec<f64>,
    cs: Vec<f64>,
    sn: Vec<f64>,
    g: Vec<f64>,
    y: Vec<f64>,
}

impl Krylov {
    /// `cor = Z y` with `y = H⁻¹ g` (upper triangular `k × k`): the
    /// correction of the cycle's first `k` iterations.
    fn correction(&mut self, k: usize, n: usize, cor: &mut [f64]) {
        for i in (0..k).rev() {
            let mut yi = self.g[i];
            for j in i + 1..k {
                yi -= self.h[j * (KRYLOV_DIM + 1) + i] * self.y[j];
            }
            let hii = self.h[i * (KRYLOV_DIM + 1) + i];
            self.y[i] = if hii != 0.0 { yi / hii } else { 0.0 };
        }
        cor.iter_mut().for_each(|c| *c = 0.0);
        for j in 0..k {
            let yj = self.y[j];
            for (c, &z) in cor.iter_mut().zip(&self.z[j * n..(j + 1) * n]) {
                *c += yj * z;
            }
        }
    }

    fn new(n: usize) -> Krylov {
        let m = KRYLOV_DIM;
        Krylov {
            v: vec![0.0; (m + 1) * n],
            z: vec![0.0; m * n],
            h: vec![0.0; m * (m + 1)],
            cs: vec![0.0; m],
            sn: vec![0.0; m],
            g: vec![0.0; m + 1],
            y: vec![0.0; m],
        }
    }
}

/// The pattern of the macro block `L = Σ_E L_E` (lower triangle, by
/// columns, rows increasing) with the values of `L` and of `Σ_E G_E G_Eᵀ`
/// on it (the augmentation has the pattern of `L`). A macro column belongs
/// to one interface, so to two subdomains' blocks: its rows are the union
/// of their columns, found with a stamp per row and no sort of triplets.
/// Summed in the subdomains' order.
struct MacroBlocks {
    n: usize,
    col_ptr: Vec<usize>,
    row_idx: Vec<usize>,
    exact: Vec<f64>,
    gram: Vec<f64>,
}

impl MacroBlocks {
    fn assemble(n: usize, parts: &[CoarseContribution]) -> MacroBlocks {
        use rayon::prelude::*;
        let grams: Vec<Mat<f64>> = parts.par_iter().map(|p| &p.g * p.g.transpose()).collect();
        // The subdomains holding each column, with its local index there.
        let mut holders: Vec<Vec<(usize, usize)>> = vec![Vec::new(); n];
        for (p, part) in parts.iter().enumerate() {
            for (a, &c) in part.cols.iter().enumerate() {
                holders[c].push((p, a));
            }
        }
        let mut stamp = vec![usize::MAX; n];
        let mut pos = vec![0usize; n];
        let mut col_ptr = Vec::with_capacity(n + 1);
        let mut row_idx = Vec::new();
        let (mut exact, mut gram) = (Vec::new(), Vec::new());
        let mut rows = Vec::new();
        col_ptr.push(0);
        for j in 0..n {
            // The diagonal even for a column no subdomain holds (zero).
            rows.clear();
            rows.push(j);
            stamp[j] = j;
            for &(p, _) in &holders[j] {
                for &r in &parts[p].cols {
                    if r >= j && stamp[r] != j {
                        stamp[r] = j;
                        rows.push(r);
                    }
                }
            }
            rows.sort_unstable();
            let start = row_idx.len();
            for (k, &r) in rows.iter().enumerate() {
                pos[r] = start + k;
            }
            row_idx.extend_from_slice(&rows);
            exact.resize(row_idx.len(), 0.0);
            gram.resize(row_idx.len(), 0.0);
            for &(p, b) in &holders[j] {
                let (part, gg) = (&parts[p], &grams[p]);
                for (a, &r) in part.cols.iter().enumerate() {
                    if r >= j {
                        exact[pos[r]] += 0.5 * (part.l[(a, b)] + part.l[(b, a)]);
                        gram[pos[r]] += gg[(a, b)];
                    }
                }
            }
            col_ptr.push(row_idx.len());
        }
        MacroBlocks {
            n,
            col_ptr,
            row_idx,
            exact,
            gram,
        }
    }

    /// The values of `L + γ Σ_E G_E G_Eᵀ`.
    fn augmented(&self, gamma: f64) -> Vec<f64> {
        self.exact.iter().zip(&self.gram).map(|(l, g)| l + gamma * g).collect()
    }

    /// The lower triangle with `values` on this pattern.
    fn matrix(&self, values: Vec<f64>) -> SparseColMat<usize, f64> {
        let symbolic = faer::sparse::SymbolicSparseColMat::new_checked(
            self.n,
            self.n,
            self.col_ptr.clone(),
            None,
            self.row_idx.clone(),
        );
        SparseColMat::new(symbolic, values)
    }
}

/// The median of the positive diagonal entries: the scale of `L`. Not the
/// largest: one soft subdomain mode (compliance 1e10 × the median on the
/// 1e6-dof plate) would make `γ G Gᵀ` and the floors swamp everything else.
fn typical_scale(diag: &[f64]) -> f64 {
    let mut d: Vec<f64> = diag.iter().copied().filter(|&v| v > 0.0).collect();
    if d.is_empty() {
        return 1.0;
    }
    let mid = d.len() / 2;
    *d.select_nth_unstable_by(mid, f64::total_cmp).1
}

/// `G` (`n_macro × n_kernel`): the macro traces of the kernel modes, by
/// columns (one per kernel mode), rows sorted and unique in each.
struct KernelCoupling {
    nrows: usize,
    ptr: Vec<usize>,
    row: Vec<usize>,
    val: Vec<f64>,
}

impl KernelCoupling {
    /// From the entries of each column in any order, repeated rows summed.
    fn from_columns(nrows: usize, mut cols: Vec<Vec<(usize, f64)>>) -> KernelCoupling {
        let mut g = KernelCoupling {
            nrows,
            ptr: Vec::with_capacity(cols.len() + 1),
            row: Vec::new(),
            val: Vec::new(),
        };
        g.ptr.push(0);
        for col in &mut cols {
            col.sort_unstable_by_key(|&(r, _)| r);
            let start = g.row.len();
            for &(r, v) in col.iter() {
                if g.row.len() > start && g.row.last() == Some(&r) {
                    *g.val.last_mut().expect("an entry of this column") += v;
                } else {
                    g.row.push(r);
                    g.val.push(v);
                }
            }
            g.ptr.push(g.row.len());
        }
        g
    }

    fn ncols(&self) -> usize {
        self.ptr.len() - 1
    }

    /// The entries `(row, value)` of column `j`.
    fn col(&self, j: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        let k = self.ptr[j]..self.ptr[j + 1];
        self.row[k.clone()].iter().copied().zip(self.val[k].iter().copied())
    }

    /// `y = G x`.
    fn mul_into(&self, x: &[f64], y: &mut [f64]) {
        y.iter_mut().for_each(|v| *v = 0.0);
        for (j, &xj) in x.iter().enumerate() {
            for (r, v) in self.col(j) {
                y[r] += v * xj;
            }
        }
    }

    /// `y = Gᵀ x`.
    fn t_mul_into(&self, x: &[f64], y: &mut [f64]) {
        for (j, yj) in y.iter_mut().enumerate() {
            *yj = self.col(j).map(|(r, v)| v * x[r]).sum();
        }
    }

    /// The first column of each batch of [`SCHUR_BATCH`] columns.
    fn batch_starts(&self) -> Vec<usize> {
        (0..self.ncols()).step_by(SCHUR_BATCH).collect()
    }

    /// `each(block, w)` for the batches of columns from `starts`
    /// ([`Self::batch_starts`]), each scattered into a column-major block
    /// (`nrows × w`, `w` up to [`SCHUR_BATCH`]); stops at the first `false`
    /// (returned then, `true` otherwise).
    fn for_each_batch(&self, starts: &[usize], mut each: impl FnMut(&mut [f64], usize) -> bool) -> bool {
        let nf = self.nrows;
        let mut block = vec![0.0; nf * SCHUR_BATCH];
        for &j0 in starts {
            let w = (self.ncols() - j0).min(SCHUR_BATCH);
            let blk = &mut block[..nf * w];
            self.columns_into(blk, j0);
            if !each(blk, w) {
                return false;
            }
        }
        true
    }

    /// Columns `j0..j0 + w` into the column-major block `blk` (`nrows`
    /// rows, `w` columns), zero elsewhere.
    fn columns_into(&self, blk: &mut [f64], j0: usize) {
        blk.iter_mut().for_each(|v| *v = 0.0);
        for (c, col) in blk.chunks_mut(self.nrows.max(1)).enumerate() {
            for (r, v) in self.col(j0 + c) {
                col[r] = v;
            }
        }
    }
}

/// Most stored values of `B = L⁻¹ P G` a coarse problem keeps (16 M, about
/// 200 MB with their row indices; twice that for a moment at set-up).
/// Beyond it `S` comes from full solves (`schur_by_solves`) and each
/// inner solve takes two solves with the factor.
pub const MAX_KERNEL_COLUMN_VALUES: usize = 1 << 24;

/// Rows per dense block of the product `Bᵀ B` ([`KernelColumns::gram`]):
/// at least this many...
const GRAM_ROWS: usize = 32;

/// ...and more while the block has fewer than one row per this many of its
/// columns, up to [`GRAM_MAX_ROWS`]. Each block's product is an update of
/// an `m × m` block by `g` rows; near the root, where a row holds nearly
/// all of the 1 700-1 900 kernel columns of the nonsmooth 30³ tower cut in
/// 64, 32 rows made it a rank-32 update whose time went to moving the
/// `m × m` block, not to the multiply-adds.
const GRAM_COLUMNS_PER_ROW: usize = 8;

/// Largest row count of a dense block of `Bᵀ B`.
const GRAM_MAX_ROWS: usize = 512;

/// `B = L⁻¹ P G` by columns, rows in the factor's (permuted) order, exact
/// zeros dropped. Where `L_γ = Pᵀ L Lᵀ P`, `S = Gᵀ L_γ⁻¹ G = Bᵀ B`: half
/// the triangular work of full solves, on right-hand sides that stay
/// sparse (a kernel column reaches the rows of its elimination-tree
/// paths: a quarter to a half of `n_macro` on the grids and towers with
/// 16 and 64 subdomains, where `L_γ⁻¹ G` is dense).
///
/// Each column is stored as runs of consecutive rows (`(first row,
/// length)`, values contiguous, gaps of up to [`RUN_GAP`] zeros kept
/// inside a run): a column's rows are its elimination-tree paths, mostly
/// whole supernodes, so the products of the iteration's coarse solves run
/// over contiguous slices instead of gathering row by row.
struct KernelColumns {
    /// Column `j`'s runs at `runs[ptr[j]..ptr[j + 1]]`.
    ptr: Vec<usize>,
    runs: Vec<(u32, u32)>,
    /// The runs' values, run after run, column after column.
    val: Vec<f64>,
}

/// Zeros between two nonzeros of a column of `B` kept inside one run
/// rather than starting another ([`KernelColumns`]).
const RUN_GAP: usize = 4;

impl KernelColumns {
    /// Forward substitutions of the columns of `G`, in batches split
    /// between the factor and a copy of it on the rayon pool (every column
    /// is solved as it would be alone: the same bits whatever the split).
    /// `None` where `B` would hold more than `cap` values (a half's share
    /// each, where the columns are split).
    fn forward(factor: &mut SparseCholesky, g: &KernelCoupling, cap: usize) -> Option<KernelColumns> {
        let nf = g.nrows;
        let starts = g.batch_starts();
        let columns = |solver: &mut SparseCholesky, starts: &[usize], parts: usize| -> Option<KernelColumns> {
            let mut out = KernelColumns {
                ptr: Vec::with_capacity(starts.len() * SCHUR_BATCH + 1),
                runs: Vec::new(),
                val: Vec::new(),
            };
            out.ptr.push(0);
            let fits = g.for_each_batch(starts, |blk, w| {
                solver.forward_columns(blk, w);
                for col in blk.chunks(nf.max(1)).take(w) {
                    out.push_column(col);
                    if out.val.len() > cap / parts {
                        return false;
                    }
                }
                true
            });
            fits.then_some(out)
        };
        let (a, b) = on_two_solvers(factor, &starts, columns);
        let mut a = a?;
        if let Some(b) = b {
            let b = b?;
            let base = a.runs.len();
            a.ptr.extend(b.ptr[1..].iter().map(|&p| p + base));
            a.runs.extend_from_slice(&b.runs);
            a.val.extend_from_slice(&b.val);
        }
        Some(a)
    }

    /// `S = Bᵀ B` (`na × na`, symmetric): the rows of `B` in blocks of
    /// [`GRAM_ROWS`] consecutive rows (rows of one supernode share their
    /// columns), each block dense on the union of its columns and
    /// multiplied by faer, then added into `S`. The blocks are split in two
    /// fixed halves summed in a fixed order: the same bits on any number of
    /// threads.
    fn gram(&self, na: usize) -> Mat<f64> {
        let nrows = self.runs.iter().map(|&(r, n)| (r + n) as usize).max().unwrap_or(0);
        // Rows of B (by rows: column index and value).
        let (rptr, entries) = group_by_key(nrows, || {
            (0..self.ptr.len() - 1)
                .flat_map(|j| self.runs[self.ptr[j]..self.ptr[j + 1]].iter().map(move |&run| (j, run)))
                .scan(0usize, |off, (j, (r, n))| {
                    let start = *off;
                    *off += n as usize;
                    Some((j, r as usize, start..*off))
                })
                .flat_map(|(j, r, vals)| (r..).zip(&self.val[vals]).map(move |(i, &v)| (i, (j as u32, v))))
        });
        let gram_of = |rows: std::ops::Range<usize>| -> Mat<f64> {
            let mut s = Mat::<f64>::zeros(na, na);
            let mut slot = vec![usize::MAX; na];
            let mut cols: Vec<usize> = Vec::with_capacity(na);
            let mut dense: Vec<f64> = Vec::new();
            let mut prod = Mat::<f64>::zeros(0, 0);
            let mut r0 = rows.start;
            while r0 < rows.end {
                // Rows join the block up to GRAM_ROWS, and on while the
                // block has fewer than 1/GRAM_COLUMNS_PER_ROW of its
                // columns' count in rows (up to GRAM_MAX_ROWS).
                cols.clear();
                let mut r1 = r0;
                while r1 < rows.end
                    && (r1 - r0 < GRAM_ROWS
                        || ((r1 - r0) * GRAM_COLUMNS_PER_ROW < cols.len() && r1 - r0 < GRAM_MAX_ROWS))
                {
                    for &(c, _) in &entries[rptr[r1]..rptr[r1 + 1]] {
                        let c = c as usize;
                        if slot[c] == usize::MAX {
                            slot[c] = cols.len();
                            cols.push(c);
                        }
                    }
                    r1 += 1;
                }
                let (g, m) = (r1 - r0, cols.len());
                if m > 0 {
                    // D: g × m, column-major.
                    dense.clear();
                    dense.resize(g * m, 0.0);
                    for r in r0..r1 {
                        for &(c, v) in &entries[rptr[r]..rptr[r + 1]] {
                            dense[slot[c as usize] * g + (r - r0)] = v;
                        }
                    }
                    let d = faer::MatRef::from_column_major_slice(&dense, g, m);
                    if prod.nrows() < m {
                        prod = Mat::zeros(m, m);
                    }
                    // The lower triangle of DᵀD (half the flops), added
                    // into the lower triangle of S.
                    faer::linalg::matmul::triangular::matmul(
                        prod.as_mut().submatrix_mut(0, 0, m, m),
                        faer::linalg::matmul::triangular::BlockStructure::TriangularLower,
                        faer::Accum::Replace,
                        d.transpose(),
                        faer::linalg::matmul::triangular::BlockStructure::Rectangular,
                        d,
                        faer::linalg::matmul::triangular::BlockStructure::Rectangular,
                        1.0,
                        faer::Par::Seq,
                    );
                    for (b, &cb) in cols.iter().enumerate() {
                        for (a, &ca) in cols.iter().enumerate().skip(b) {
                            s[(ca.max(cb), ca.min(cb))] += prod[(a, b)];
                        }
                    }
                }
                for &c in &cols {
                    slot[c] = usize::MAX;
                }
                r0 = r1;
            }
            s
        };
        // The halves split the work (a row with `c` entries costs `c²`),
        // not the rows: the rows near the factor's root hold nearly every
        // column, and split by rows the second half did 96-98 % of the work
        // on the nonsmooth 30³ tower cut in 64 (0.01-0.03 against 0.34-0.45 s).
        let cost = |r: usize| ((rptr[r + 1] - rptr[r]) as f64).powi(2);
        let total: f64 = (0..nrows).map(cost).sum();
        let mut mid = nrows;
        let mut acc = 0.0;
        for r in 0..nrows {
            acc += cost(r);
            if acc >= 0.5 * total {
                mid = r + 1;
                break;
            }
        }
        let (mut lo, hi) = rayon::join(|| gram_of(0..mid), || gram_of(mid..nrows));
        lo += &hi;
        for j in 0..na {
            for i in 0..j {
                lo[(i, j)] = lo[(j, i)];
            }
        }
        lo
    }

    /// Appends a column of `B` from its dense values (exact zeros
    /// dropped, short gaps kept inside runs: see [`RUN_GAP`]).
    fn push_column(&mut self, col: &[f64]) {
        let n = col.len();
        let mut i = 0;
        while i < n {
            if col[i] == 0.0 {
                i += 1;
                continue;
            }
            // A run from i to the last nonzero followed by more than
            // RUN_GAP zeros (or the end).
            let mut end = i + 1;
            let mut k = end;
            while k < n && k - end <= RUN_GAP {
                if col[k] != 0.0 {
                    end = k + 1;
                }
                k += 1;
            }
            self.runs.push((i as u32, (end - i) as u32));
            self.val.extend_from_slice(&col[i..end]);
            i = end;
        }
        self.ptr.push(self.runs.len());
    }

    /// `y = Bᵀ x`.
    fn transpose_mul(&self, x: &[f64], y: &mut [f64]) {
        let mut off = 0;
        for (j, yj) in y.iter_mut().enumerate() {
            let mut acc = 0.0;
            for &(r, n) in &self.runs[self.ptr[j]..self.ptr[j + 1]] {
                let (r, n) = (r as usize, n as usize);
                acc += crate::kernels::dot(&self.val[off..off + n], &x[r..r + n]);
                off += n;
            }
            *yj = acc;
        }
    }

    /// `y += B x`.
    fn mul_add(&self, x: &[f64], y: &mut [f64]) {
        let mut off = 0;
        for (j, &xj) in x.iter().enumerate() {
            for &(r, n) in &self.runs[self.ptr[j]..self.ptr[j + 1]] {
                let (r, n) = (r as usize, n as usize);
                if xj != 0.0 {
                    for (yi, &v) in y[r..r + n].iter_mut().zip(&self.val[off..off + n]) {
                        *yi += v * xj;
                    }
                }
                off += n;
            }
        }
    }
}

/// `work(solver, batches, parts)` on the batches `starts` of columns of
/// `G`, split in two halves between `factor` and a copy of it on the
/// rayon pool (`parts` = 2; 1 with a single batch or no copy): the halves'
/// results in order. Every batch is solved as it would be alone, so the
/// results have the same bits whatever the split.
fn on_two_solvers<T: Send>(
    factor: &mut SparseCholesky,
    starts: &[usize],
    work: impl Fn(&mut SparseCholesky, &[usize], usize) -> T + Sync,
) -> (T, Option<T>) {
    let half = starts.len() / 2;
    let mut twin = if half > 0 { factor.solver_copy().ok() } else { None };
    match twin.as_mut() {
        Some(twin) => {
            let (a, b) = rayon::join(|| work(factor, &starts[..half], 2), || work(twin, &starts[half..], 2));
            (a, Some(b))
        }
        None => (work(factor, starts, 1), None),
    }
}

/// `S = Gᵀ L_γ⁻¹ G` from full solves in batches of columns, the batches
/// split between the factor and a copy of it on the rayon pool: where `B`
/// does not fit ([`MAX_KERNEL_COLUMN_VALUES`]). The same bits whatever the
/// split.
fn schur_by_solves(factor: &mut SparseCholesky, g: &KernelCoupling) -> Mat<f64> {
    let (nf, na) = (g.nrows, g.ncols());
    let starts = g.batch_starts();
    let schur_columns = |solver: &mut SparseCholesky, starts: &[usize], _parts: usize| -> Vec<f64> {
        let mut cols = Vec::with_capacity(starts.len() * SCHUR_BATCH * na);
        g.for_each_batch(starts, |blk, w| {
            solver.solve_columns(blk, w);
            for y in blk.chunks(nf.max(1)).take(w) {
                let at = cols.len();
                cols.resize(at + na, 0.0);
                g.t_mul_into(y, &mut cols[at..]);
            }
            true
        });
        cols
    };
    let (mut cols, rest) = on_two_solvers(factor, &starts, schur_columns);
    cols.extend(rest.unwrap_or_default());
    Mat::from_fn(na, na, |i, j| cols[j * na + i])
}

/// `x ← (L Lᵀ)⁻¹ x` for the dense lower-triangular `l` (column major): a
/// forward sweep by column axpys and a backward one by column dots, both
/// over contiguous slices. No allocation.
fn cholesky_solve(l: &Mat<f64>, x: &mut [f64]) {
    let n = x.len();
    for j in 0..n {
        let col = l.col(j).try_as_col_major().expect("owned matrix").as_slice();
        let xj = x[j] / col[j];
        x[j] = xj;
        if xj != 0.0 {
            for (xi, &lij) in x[j + 1..].iter_mut().zip(&col[j + 1..]) {
                *xi -= lij * xj;
            }
        }
    }
    for j in (0..n).rev() {
        let col = l.col(j).try_as_col_major().expect("owned matrix").as_slice();
        let dot: f64 = x[j + 1..].iter().zip(&col[j + 1..]).map(|(a, b)| a * b).sum();
        x[j] = (x[j] - dot) / col[j];
    }
}

/// Smallest eigenvalue of `GᵀG`, relative to the largest, below which a
/// kernel mode counts as unrestrained. At 1e-12 the shallow two-bar truss
/// with a rise of 1e-6 (ratio exactly 1e-12, solved by the direct solver)
/// passed or failed by its kernels' round-off; an exactly collinear one
/// gives ~1e-32.
const RANK_RTOL: f64 = 1e-13;

/// Cholesky pivot ratio and estimated smallest eigenvalue (relative to the
/// trace, a margin of 1000 over [`RANK_RTOL`]) from which `GᵀG` is taken as
/// full rank without its eigendecomposition; the inverse-iteration steps of
/// that estimate.
const RANK_PIVOT_RATIO: f64 = 1e-8;
const RANK_EIGEN_RATIO: f64 = 1e-10;
const RANK_INVERSE_ITERATIONS: usize = 8;

/// Power and inverse iterations of the estimate that decides the rank
/// without an eigendecomposition where the tests above could not vouch
/// for it, and the factor over [`RANK_RTOL`] above which its smallest
/// eigenvalue (an upper bound) says full rank: between the two the
/// eigendecomposition decides, as before.
const RANK_ESTIMATE_ITERATIONS: usize = 12;
const RANK_ESTIMATE_MARGIN: f64 = 1e3;

/// What an unrestrained kernel mode is called in [`Error::Mechanism`].
const UNRESTRAINED: &str = "is not restrained by its interfaces";

/// The error of a kernel mode of `subdomain` that no interface restrains
/// (`where_` describes its largest motion): a mechanism of the whole
/// structure, whatever the partition.
pub(crate) fn unrestrained_mode(subdomain: usize, where_: &str) -> Error {
    Error::Mechanism(format!(
        "a rigid-body or mechanism mode of subdomain {subdomain} {UNRESTRAINED}{where_}: the structure is not supported well enough or is a mechanism"
    ))
}

/// Whether `e` is the coarse set-up's [`unrestrained_mode`]: the structure
/// itself is a mechanism, so another partition of it fails the same way.
pub(crate) fn is_unrestrained_mode(e: &Error) -> bool {
    matches!(e, Error::Mechanism(m) if m.contains(UNRESTRAINED))
}

/// `G` by columns (each kernel column belongs to one subdomain) from each
/// subdomain's `(cols, G_E, alpha_off)`.
fn kernel_coupling<'a>(
    nf: usize,
    na: usize,
    parts: impl Iterator<Item = (&'a [usize], &'a Mat<f64>, usize)>,
) -> Result<KernelCoupling> {
    let mut g_cols: Vec<Vec<(usize, f64)>> = vec![Vec::new(); na];
    for (cols, g, alpha_off) in parts {
        if cols.iter().any(|&c| c >= nf) || alpha_off + g.ncols() > na || g.nrows() != cols.len() {
            return Err(Error::Numerical("coarse contribution outside the coarse system".into()));
        }
        for q in 0..g.ncols() {
            let col = &mut g_cols[alpha_off + q];
            for (a, &ca) in cols.iter().enumerate() {
                let v = g[(a, q)];
                if v != 0.0 {
                    col.push((ca, v));
                }
            }
        }
    }
    Ok(KernelCoupling::from_columns(nf, g_cols))
}

/// Fails with a named subdomain when `G` has a (numerically) dependent
/// column. `GᵀG` is formed row by row of `G`: a row holds the kernel modes
/// of the two subdomains of one interface only.
fn check_full_rank(g: &KernelCoupling, owner: &[usize], describe: &dyn Fn(&[f64]) -> String) -> Result<()> {
    let na = g.ncols();
    let mut rows: Vec<Vec<(usize, f64)>> = vec![Vec::new(); g.nrows];
    for j in 0..na {
        for (r, v) in g.col(j) {
            rows[r].push((j, v));
        }
    }
    // The usual case, full rank, on the sparse GᵀG (it couples only the
    // kernel modes of neighbouring subdomains): its dense Cholesky took
    // 1.4 s of each coarse set-up with 4 704 kernel modes (the 130²
    // nonsmooth grid with 256 subdomains).
    if sparse_clearly_positive_definite(na, &rows) {
        return Ok(());
    }
    let mut gtg = Mat::<f64>::zeros(na, na);
    for r in &rows {
        for &(a, va) in r {
            for &(b, vb) in r {
                gtg[(a, b)] += va * vb;
            }
        }
    }
    // Else by dense Cholesky and inverse iteration (the eigendecomposition
    // of a 1 838-mode GᵀG took 1.4 s of the 30³ tower's set-up with 216
    // subdomains).
    if crate::dense::clearly_positive_definite(&gtg, RANK_PIVOT_RATIO, RANK_EIGEN_RATIO, RANK_INVERSE_ITERATIONS)
        .is_some()
    {
        return Ok(());
    }
    // The mode `alpha` (kernel coefficients) named by its largest entry.
    let unrestrained = |alpha: &[f64]| {
        let worst = (0..na).fold(0, |b, i| if alpha[i].abs() > alpha[b].abs() { i } else { b });
        unrestrained_mode(owner.get(worst).copied().unwrap_or(0), &describe(alpha))
    };
    // Else the smallest eigenpair by inverse iteration; the
    // eigendecomposition only where that estimate sits near the threshold.
    let (lmax, lmin, v) = crate::dense::extreme_eigen_estimates(&gtg, RANK_RTOL, RANK_ESTIMATE_ITERATIONS);
    if lmax == 0.0 || lmin <= RANK_RTOL * lmax {
        return Err(unrestrained(&v));
    }
    if lmin > RANK_ESTIMATE_MARGIN * RANK_RTOL * lmax {
        return Ok(());
    }
    let eig = gtg
        .self_adjoint_eigen(faer::Side::Lower)
        .map_err(|_| Error::Numerical("coarse kernel check failed".into()))?;
    let s = eig.S();
    let smax = (0..na).map(|i| s[i]).fold(0.0f64, f64::max);
    if s[0] <= RANK_RTOL * smax.max(f64::MIN_POSITIVE) || smax == 0.0 {
        let u = eig.U();
        let alpha: Vec<f64> = (0..na).map(|i| u[(i, 0)]).collect();
        return Err(unrestrained(&alpha));
    }
    Ok(())
}

/// The sparse test of [`crate::dense::clearly_positive_definite`] on `GᵀG`
/// given by the rows of `G` (each `(kernel column, value)`): a sparse
/// Cholesky factorization (every pivot above [`RANK_PIVOT_RATIO`] of its
/// row's diagonal) and the smallest eigenvalue, estimated by
/// [`RANK_INVERSE_ITERATIONS`] inverse iterations from the same fixed
/// start, above [`RANK_EIGEN_RATIO`] times the trace. `false` says only
/// that this test cannot vouch for full rank (the dense test decides).
fn sparse_clearly_positive_definite(na: usize, rows: &[Vec<(usize, f64)>]) -> bool {
    // Column by column into one dense accumulator (Gustavson): one triplet
    // per entry of GᵀG. A triplet per product (2 million for 65 000
    // entries, the 130² nonsmooth grid with 64 subdomains) made the sort
    // cost 50-190 ms of each coarse set-up.
    let mut cols: Vec<Vec<(usize, f64)>> = vec![Vec::new(); na];
    for (r, row) in rows.iter().enumerate() {
        for &(a, v) in row {
            cols[a].push((r, v));
        }
    }
    let mut acc = vec![0.0; na];
    let mut mark = vec![usize::MAX; na];
    let mut hit = Vec::new();
    let mut triplets = Vec::new();
    for (a, col) in cols.iter().enumerate() {
        for &(r, va) in col {
            for &(b, vb) in &rows[r] {
                if b >= a {
                    if mark[b] != a {
                        mark[b] = a;
                        acc[b] = 0.0;
                        hit.push(b);
                    }
                    acc[b] += va * vb;
                }
            }
        }
        triplets.extend(hit.drain(..).map(|b| (b, a, acc[b])));
    }
    drop(cols);
    let Ok(lower) = lower_csc(na, &triplets) else {
        return false;
    };
    drop(triplets);
    let Ok(mut chol) = SparseCholesky::factor_checked(&lower, 1, RANK_PIVOT_RATIO) else {
        return false;
    };
    let trace: f64 = lower_diagonal(&lower).iter().sum();
    let mut x = crate::dense::inverse_iteration_start(na);
    let norm = |x: &[f64]| x.iter().map(|v| v * v).sum::<f64>().sqrt();
    for _ in 0..RANK_INVERSE_ITERATIONS {
        let n = norm(&x);
        if !(n > 0.0) || !n.is_finite() {
            return false;
        }
        x.iter_mut().for_each(|v| *v /= n);
        chol.solve_in_place(&mut x);
    }
    let n = norm(&x);
    if !(n > 0.0) || !n.is_finite() {
        return false;
    }
    x.iter_mut().for_each(|v| *v /= n);
    let mut ax = vec![0.0; na];
    sym_matvec(&lower, &x, &mut ax);
    let rayleigh: f64 = x.iter().zip(&ax).map(|(a, b)| a * b).sum();
    rayleigh > RANK_EIGEN_RATIO * trace
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A kernel trace that repeats a geometric mode up to a deviation of
    /// 1e-13 (what a computed kernel's round-off leaves) is a column of
    /// its own at [`SOFT_TRACE_RTOL`] and dropped at [`MACRO_RANK_RTOL`].
    #[test]
    fn soft_trace_deviations_are_kept_below_the_macro_cut() {
        // A straight line of 12 points along x, x components only: the
        // degree-1 fields there are a translation and an extension.
        let points: Vec<[f64; 3]> = (0..12).map(|i| [i as f64, 0.0, 0.0]).collect();
        let comp = vec![0; 12];
        let base = MacroBasis::interface_block(
            &points,
            &comp,
            &Mat::zeros(12, 0),
            &Mat::zeros(12, 0),
            1,
            MACRO_RANK_RTOL,
        );
        // A translation, off by a rough (non-polynomial) 1e-13 field.
        let trace = Mat::from_fn(12, 1, |i, _| 1.0 + 1e-13 * (((i * 7) % 5) as f64 - 2.0));
        let none = Mat::zeros(12, 0);
        let cut = MacroBasis::interface_block(&points, &comp, &trace, &none, 1, MACRO_RANK_RTOL);
        let kept = MacroBasis::interface_block(&points, &comp, &trace, &none, 1, SOFT_TRACE_RTOL);
        assert_eq!(cut.ncols(), base.ncols());
        assert_eq!(kept.ncols(), base.ncols() + 1);
        // An exact repeat stays out at either cut.
        let exact = Mat::from_fn(12, 1, |_, _| 1.0);
        let soft = MacroBasis::interface_block(&points, &comp, &exact, &none, 1, SOFT_TRACE_RTOL);
        assert_eq!(soft.ncols(), base.ncols());
    }

    /// The size `m²` and the factor of a shifted 5-point Laplacian on an
    /// `m × m` grid (`diag` on the diagonal, -1 to each neighbour).
    fn grid_laplacian_factor(m: usize, diag: f64) -> (usize, SparseCholesky) {
        let nf = m * m;
        let mut t = Vec::new();
        for i in 0..m {
            for j in 0..m {
                let k = i * m + j;
                t.push((k, k, diag));
                if i + 1 < m {
                    t.push((k + m, k, -1.0));
                }
                if j + 1 < m {
                    t.push((k + 1, k, -1.0));
                }
            }
        }
        let lower = lower_csc(nf, &t).unwrap();
        (nf, SparseCholesky::factor(&lower, SCHUR_BATCH).unwrap())
    }

    /// `S = Bᵀ B` where the rows near the root hold hundreds of columns (its
    /// blocks grow past [`GRAM_ROWS`] rows there, and its two halves split
    /// the work, not the rows): the Schur complement of full solves, with
    /// the same bits on one thread as on two.
    #[test]
    fn kernel_columns_gram_with_dense_rows_near_the_root() {
        let (nf, mut factor) = grid_laplacian_factor(24, 4.2);
        let na = 400;
        let cols: Vec<Vec<(usize, f64)>> = (0..na)
            .map(|q| {
                let r0 = (q * 131) % (nf - 2);
                (r0..r0 + 2)
                    .map(|r| (r, 1.0 + ((q * 7 + r) % 10) as f64 / 10.0))
                    .collect()
            })
            .collect();
        let g = KernelCoupling::from_columns(nf, cols);
        let b = KernelColumns::forward(&mut factor, &g, usize::MAX).unwrap();
        let widest = {
            let mut per_row = vec![0usize; nf];
            for j in 0..na {
                for &(r, n) in &b.runs[b.ptr[j]..b.ptr[j + 1]] {
                    per_row[r as usize..(r + n) as usize].iter_mut().for_each(|c| *c += 1);
                }
            }
            per_row.into_iter().max().unwrap()
        };
        assert!(
            widest > GRAM_ROWS * GRAM_COLUMNS_PER_ROW,
            "rows near the root hold {widest} columns"
        );
        let in_pool = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| b.gram(na))
        };
        let (s1, s2) = (in_pool(1), in_pool(2));
        let s_ref = schur_by_solves(&mut factor, &g);
        let scale = (0..na).map(|i| s_ref[(i, i)]).fold(0.0, f64::max);
        for i in 0..na {
            for j in 0..na {
                assert_eq!(
                    s1[(i, j)].to_bits(),
                    s2[(i, j)].to_bits(),
                    "S[{i},{j}] on 1 and 2 threads"
                );
                assert!((s1[(i, j)] - s_ref[(i, j)]).abs() <= 1e-13 * scale, "S[{i},{j}]");
            }
        }
    }

    /// `S = Bᵀ B` from the forward-substituted kernel columns against `S`
    /// from full solves, and the kept columns' inner-solve route
    /// (`Pᵀ L⁻ᵀ (L⁻¹ P c + B α)`) against `L_γ⁻¹ (c + G α)`: on a 2D
    /// Laplacian with local kernel columns (70 of them: both halves of the
    /// batched forward substitutions), whose `B` is sparse. With too small
    /// a cap the columns are not kept.
    #[test]
    fn kernel_columns_give_the_schur_complement_of_full_solves() {
        let (nf, mut factor) = grid_laplacian_factor(15, 4.1);
        let na = 70;
        let cols: Vec<Vec<(usize, f64)>> = (0..na)
            .map(|q| {
                let r0 = (q * 37) % (nf - 3);
                (r0..r0 + 3).map(|r| (r, 1.0 + 0.1 * (q + r) as f64 % 1.0)).collect()
            })
            .collect();
        let g = KernelCoupling::from_columns(nf, cols);
        let b = KernelColumns::forward(&mut factor, &g, usize::MAX).unwrap();
        assert!(
            b.val.len() < nf * na / 2,
            "B is sparse here: {} of {}",
            b.val.len(),
            nf * na
        );
        let s = b.gram(na);
        let s_ref = schur_by_solves(&mut factor, &g);
        let scale = (0..na).map(|i| s_ref[(i, i)]).fold(0.0, f64::max);
        for i in 0..na {
            for j in 0..na {
                assert!((s[(i, j)] - s_ref[(i, j)]).abs() <= 1e-13 * scale, "S[{i},{j}]");
            }
        }
        // f = Pᵀ L⁻ᵀ (L⁻¹ P c + B α) against L_γ⁻¹ (c + G α).
        let c: Vec<f64> = (0..nf).map(|i| ((i * 7) % 11) as f64 - 5.0).collect();
        let alpha: Vec<f64> = (0..na).map(|q| ((q * 3) % 5) as f64 - 2.0).collect();
        let mut f = c.clone();
        factor.forward_columns(&mut f, 1);
        b.mul_add(&alpha, &mut f);
        factor.backward_columns(&mut f, 1);
        let mut f_ref = vec![0.0; nf];
        g.mul_into(&alpha, &mut f_ref);
        f_ref.iter_mut().zip(&c).for_each(|(x, &ci)| *x += ci);
        factor.solve_in_place(&mut f_ref);
        let fmax = f_ref.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        for (x, y) in f.iter().zip(&f_ref) {
            assert!((x - y).abs() <= 1e-13 * fmax);
        }
        // Bᵀ (L⁻¹ P c) = Gᵀ L_γ⁻¹ c.
        let mut w = c.clone();
        factor.forward_columns(&mut w, 1);
        let mut bt = vec![0.0; na];
        b.transpose_mul(&w, &mut bt);
        let mut y = c.clone();
        factor.solve_in_place(&mut y);
        let mut gt = vec![0.0; na];
        g.t_mul_into(&y, &mut gt);
        let gmax = gt.iter().fold(0.0f64, |a, v| a.max(v.abs()));
        for (x, y) in bt.iter().zip(&gt) {
            assert!((x - y).abs() <= 1e-13 * gmax);
        }
        assert!(KernelColumns::forward(&mut factor, &g, 100).is_none());
    }

    /// `G` from unsorted columns with repeated rows: sorted, the repeats
    /// summed, and its products and column blocks those of the dense `G`.
    #[test]
    fn kernel_coupling_sums_repeated_rows() {
        let g = KernelCoupling::from_columns(4, vec![vec![(3, 1.0), (0, 2.0), (3, 0.5)], vec![], vec![(1, -1.0)]]);
        assert_eq!(g.ncols(), 3);
        assert_eq!(g.col(0).collect::<Vec<_>>(), vec![(0, 2.0), (3, 1.5)]);
        let mut y = [9.0; 4];
        g.mul_into(&[1.0, 5.0, 2.0], &mut y);
        assert_eq!(y, [2.0, -2.0, 0.0, 1.5]);
        let mut z = [9.0; 3];
        g.t_mul_into(&[1.0, 1.0, 0.0, 2.0], &mut z);
        assert_eq!(z, [5.0, 0.0, -1.0]);
        let mut blk = [7.0; 8];
        g.columns_into(&mut blk, 1);
        assert_eq!(blk, [0.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0]);
    }

    /// The assembled `L` and `L_γ` are the sums of the subdomains' blocks
    /// scattered to their columns (unsorted), lower triangle by columns
    /// with the diagonal first, including a column no subdomain holds.
    #[test]
    fn macro_blocks_are_the_scattered_sums_of_the_subdomains_blocks() {
        let n = 7;
        let block = |m: usize, s: f64| Mat::from_fn(m, m, |i, j| s * (1.0 + i as f64) + 0.25 * (i * j) as f64);
        let parts = vec![
            CoarseContribution {
                cols: vec![4, 0, 2],
                l: block(3, 1.0),
                g: Mat::from_fn(3, 2, |i, j| (i + 2 * j) as f64 - 1.5),
                alpha_off: 0,
            },
            CoarseContribution {
                cols: vec![2, 5, 4, 1],
                l: block(4, 3.0),
                g: Mat::from_fn(4, 1, |i, _| 0.5 * i as f64),
                alpha_off: 2,
            },
        ];
        let gamma = 2.0;
        let (mut l, mut aug) = (Mat::<f64>::zeros(n, n), Mat::<f64>::zeros(n, n));
        for p in &parts {
            let gg = &p.g * p.g.transpose();
            for (a, &ca) in p.cols.iter().enumerate() {
                for (b, &cb) in p.cols.iter().enumerate() {
                    l[(ca, cb)] += 0.5 * (p.l[(a, b)] + p.l[(b, a)]);
                    aug[(ca, cb)] += 0.5 * (p.l[(a, b)] + p.l[(b, a)]) + gamma * gg[(a, b)];
                }
            }
        }
        let blocks = MacroBlocks::assemble(n, &parts);
        let got_l = blocks.matrix(blocks.exact.clone());
        let got_aug = blocks.matrix(blocks.augmented(gamma));
        for (got, want) in [(&got_l, &l), (&got_aug, &aug)] {
            let a = got.as_ref();
            let mut seen = 0;
            for j in 0..n {
                let rows: Vec<usize> = a.row_idx_of_col(j).collect();
                assert_eq!(rows[0], j, "column {j} starts at its diagonal");
                assert!(rows.windows(2).all(|w| w[0] < w[1]), "column {j}: {rows:?}");
                for (i, &v) in a.row_idx_of_col(j).zip(a.val_of_col(j)) {
                    assert!((v - want[(i, j)]).abs() <= 1e-14 * want.norm_max(), "({i}, {j})");
                    seen += 1;
                }
            }
            // Columns 3 and 6 (no subdomain) have their zero diagonal and
            // nothing else; the pairs of columns no block shares (0 and 5,
            // 0 and 1) are absent.
            assert_eq!(a.row_idx_of_col(3).collect::<Vec<_>>(), vec![3]);
            assert!(!a.row_idx_of_col(0).any(|i| i == 5 || i == 1));
            assert_eq!(a.row_idx_of_col(6).collect::<Vec<_>>(), vec![6]);
            assert_eq!(seen, 6 + 10 - 3 + 2);
        }
    }

    /// Rows of `G` for a chain of `k` subdomains with 3 kernel modes each,
    /// every interface holding 4 macro rows on the modes of its two sides.
    fn chain_rows(k: usize) -> (usize, Vec<Vec<(usize, f64)>>) {
        let mut seed = 11u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        };
        let mut rows = Vec::new();
        for s in 0..k - 1 {
            for _ in 0..4 {
                let row: Vec<(usize, f64)> = (3 * s..3 * s + 6).map(|c| (c, next())).collect();
                rows.push(row);
            }
        }
        // The first subdomain is also held by a support (its own rows).
        for q in 0..3 {
            rows.push(vec![(q, 1.0)]);
        }
        (3 * k, rows)
    }

    /// The sparse test vouches for a full-rank `G` and refuses one with a
    /// dependent or nearly dependent column (the dense test decides then).
    #[test]
    fn sparse_rank_test_vouches_only_for_clear_full_rank() {
        let (na, rows) = chain_rows(20);
        assert!(sparse_clearly_positive_definite(na, &rows));
        // Column 7 a copy of column 6 wherever 6 appears (and nothing else).
        let dependent: Vec<Vec<(usize, f64)>> = rows
            .iter()
            .map(|r| {
                let v6 = r.iter().find(|&&(c, _)| c == 6).map(|&(_, v)| v);
                r.iter()
                    .map(|&(c, v)| if c == 7 { (c, v6.unwrap_or(0.0)) } else { (c, v) })
                    .chain(v6.filter(|_| !r.iter().any(|&(c, _)| c == 7)).map(|v| (7, v)))
                    .collect()
            })
            .collect();
        assert!(!sparse_clearly_positive_definite(na, &dependent));
        // Nearly dependent: one entry of the copy 1e-7 off, an eigenvalue
        // ~1e-16 of the trace.
        let mut near = dependent.clone();
        let (r, k) = (0..near.len())
            .find_map(|r| near[r].iter().position(|&(c, _)| c == 7).map(|k| (r, k)))
            .expect("column 7 appears");
        near[r][k].1 *= 1.0 + 1e-7;
        assert!(!sparse_clearly_positive_definite(na, &near));
        // A mode no row touches.
        assert!(!sparse_clearly_positive_definite(na + 1, &rows));
    }
}
