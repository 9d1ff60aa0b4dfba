//! The macro space and the coarse problem (DESIGN.md §4).
//!
//! [`MacroBasis`]: on each interface, 3 translations, 3 rotations about the
//! centroid and 3 extensions in the average plane (two stretches along the
//! principal axes and the in-plane shear), enriched with the traces of the
//! kernel modes of both neighbours, then orthonormalised with a rank-revealing
//! SVD so that `PᵀP = I` even for one-node, collinear and coplanar interfaces.
//!
//! [`CoarseProblem`]: the saddle point system
//! `[L −G; −Gᵀ 0] [f; α] = [Pᵀ J K⁺ r; −Rᵀ r]` (symmetric form). `L` is only
//! positive semi-definite because of the redundant multipliers at cross
//! points, so the system is solved through the inverse of a slightly
//! regularised matrix followed by iterative refinement against the exact
//! one: the null directions of `L` act on nothing, and the refinement makes
//! the relevant components exact to round-off.

use crate::error::{Error, Result};
use crate::subdomain::orthonormal_columns;
use faer::linalg::solvers::DenseSolveCore;
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
/// returns an `entries × 9` matrix (translations, rotations, extensions).
pub fn geometric_modes(points: &[[f64; 3]], comp: &[usize]) -> Mat<f64> {
    let n = points.len();
    let mut c = [0.0; 3];
    for p in points {
        for d in 0..3 {
            c[d] += p[d] / n as f64;
        }
    }
    // Principal axes of the interface's points (average plane).
    let mut cov = Mat::<f64>::zeros(3, 3);
    for p in points {
        for i in 0..3 {
            for j in 0..3 {
                cov[(i, j)] += (p[i] - c[i]) * (p[j] - c[j]);
            }
        }
    }
    let (a1, a2) = match cov.self_adjoint_eigen(faer::Side::Lower) {
        Ok(eig) => {
            let u = eig.U();
            // Eigenvalues ascend: the last two span the average plane.
            ([u[(0, 2)], u[(1, 2)], u[(2, 2)]], [u[(0, 1)], u[(1, 1)], u[(2, 1)]])
        }
        Err(_) => ([1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
    };
    Mat::from_fn(n, 9, |j, q| {
        let d = comp[j];
        let x = [points[j][0] - c[0], points[j][1] - c[1], points[j][2] - c[2]];
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
            6 => (a1[0] * x[0] + a1[1] * x[1] + a1[2] * x[2]) * a1[d],
            7 => (a2[0] * x[0] + a2[1] * x[1] + a2[2] * x[2]) * a2[d],
            _ => {
                let s1 = a1[0] * x[0] + a1[1] * x[1] + a1[2] * x[2];
                let s2 = a2[0] * x[0] + a2[1] * x[1] + a2[2] * x[2];
                s2 * a1[d] + s1 * a2[d]
            }
        }
    })
}

impl MacroBasis {
    /// Builds the basis of one interface from its geometric modes and the
    /// kernel traces of its two subdomains (`trace_lo`, `trace_hi`:
    /// `entries × r` each).
    pub fn interface_block(points: &[[f64; 3]], comp: &[usize], trace_lo: &Mat<f64>, trace_hi: &Mat<f64>) -> Mat<f64> {
        let g = geometric_modes(points, comp);
        let n = points.len();
        let m = 9 + trace_lo.ncols() + trace_hi.ncols();
        let all = Mat::from_fn(n, m, |i, j| {
            if j < 9 {
                g[(i, j)]
            } else if j < 9 + trace_lo.ncols() {
                trace_lo[(i, j - 9)]
            } else {
                trace_hi[(i, j - 9 - trace_lo.ncols())]
            }
        });
        orthonormal_columns(&all, 1e-10)
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

/// The factored coarse saddle-point system.
#[derive(Debug)]
pub struct CoarseProblem {
    /// Number of macro unknowns `f`.
    pub n_macro: usize,
    /// Number of kernel unknowns `α`.
    pub n_kernel: usize,
    matrix: Mat<f64>,
    inverse: Mat<f64>,
    /// Right-hand side, written by the caller before [`CoarseProblem::solve`].
    pub rhs: Vec<f64>,
    /// Solution `[f; α]` after [`CoarseProblem::solve`].
    pub solution: Vec<f64>,
    residual: Vec<f64>,
    correction: Vec<f64>,
    /// `α = alpha_scale · α̃`: balances the dimensionless `G` against `L`.
    alpha_scale: f64,
}

/// Refinement passes per coarse solve.
const REFINEMENTS: usize = 2;

impl CoarseProblem {
    /// Factors `[L −G; −Gᵀ 0]`. `G` must have full column rank, otherwise a
    /// kernel mode of some subdomain is not restrained by the interfaces and
    /// the structure is a mechanism (`kernel_owner` names the subdomain of
    /// each column of `G`).
    pub fn new(l: Mat<f64>, g: Mat<f64>, kernel_owner: &[usize]) -> Result<CoarseProblem> {
        let nf = l.nrows();
        let na = g.ncols();
        let n = nf + na;
        if na > 0 {
            check_full_rank(&g, kernel_owner)?;
        }
        let mut matrix = Mat::<f64>::zeros(n, n);
        let lscale = (0..nf)
            .map(|i| l[(i, i)].abs())
            .fold(0.0f64, f64::max)
            .max(f64::MIN_POSITIVE);
        for j in 0..nf {
            for i in 0..nf {
                // Symmetrise: L is assembled from W_Eᵀ Z_E, symmetric up to round-off.
                matrix[(i, j)] = 0.5 * (l[(i, j)] + l[(j, i)]);
            }
        }
        // Balance the α block with L: G is dimensionless, so its block is
        // scaled by the size of L (the square root left a 1/s imbalance
        // when coordinates are scaled by s).
        let gs = lscale;
        for j in 0..na {
            for i in 0..nf {
                matrix[(i, nf + j)] = -g[(i, j)] * gs;
                matrix[(nf + j, i)] = -g[(i, j)] * gs;
            }
        }
        let mut reg = matrix.clone();
        for i in 0..nf {
            reg[(i, i)] += 1e-10 * lscale;
        }
        let lblt = reg.lblt(faer::Side::Lower);
        let inverse = lblt.inverse();
        if inverse.col_iter().any(|c| c.iter().any(|v| !v.is_finite())) {
            return Err(Error::Numerical("coarse problem could not be factored".into()));
        }
        Ok(CoarseProblem {
            n_macro: nf,
            n_kernel: na,
            matrix,
            inverse,
            rhs: vec![0.0; n],
            solution: vec![0.0; n],
            residual: vec![0.0; n],
            correction: vec![0.0; n],
            alpha_scale: gs,
        })
    }

    /// Solves for `rhs = [Pᵀ J K⁺ r; Rᵀ r]` (unscaled, in the DESIGN.md sign
    /// convention); the solution is `[f; α]`. No allocation.
    pub fn solve(&mut self) {
        let nf = self.n_macro;
        let n = nf + self.n_kernel;
        // Symmetric form: the second block row is negated and, like the
        // α columns, scaled by gs (α = gs·α̃).
        for i in nf..n {
            self.rhs[i] = -self.rhs[i] * self.alpha_scale;
        }
        gemv(&self.inverse, &self.rhs, &mut self.solution);
        for _ in 0..REFINEMENTS {
            gemv(&self.matrix, &self.solution, &mut self.residual);
            for i in 0..n {
                self.residual[i] = self.rhs[i] - self.residual[i];
            }
            gemv(&self.inverse, &self.residual, &mut self.correction);
            for i in 0..n {
                self.solution[i] += self.correction[i];
            }
        }
        for i in nf..n {
            self.solution[i] *= self.alpha_scale;
        }
    }

    /// The operator `L` (copy of the macro block).
    pub fn operator(&self) -> Mat<f64> {
        let nf = self.n_macro;
        Mat::from_fn(nf, nf, |i, j| self.matrix[(i, j)])
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

/// `y = A x` for a dense column-major matrix, written as column axpys so it
/// vectorises.
fn gemv(a: &Mat<f64>, x: &[f64], y: &mut [f64]) {
    y.iter_mut().for_each(|v| *v = 0.0);
    for (j, &xj) in x.iter().enumerate() {
        if xj == 0.0 {
            continue;
        }
        let col = a.col(j);
        for (yi, ai) in y.iter_mut().zip(col.iter()) {
            *yi += ai * xj;
        }
    }
}

/// Fails with a named subdomain when `G` has a (numerically) dependent column.
fn check_full_rank(g: &Mat<f64>, owner: &[usize]) -> Result<()> {
    let gtg = g.transpose() * g;
    let eig = gtg
        .self_adjoint_eigen(faer::Side::Lower)
        .map_err(|_| Error::Numerical("coarse kernel check failed".into()))?;
    let s = eig.S();
    let na = g.ncols();
    let smax = (0..na).map(|i| s[i]).fold(0.0f64, f64::max);
    if na > 0 && s[0] <= 1e-12 * smax.max(f64::MIN_POSITIVE) || smax == 0.0 {
        let u = eig.U();
        let worst = (0..na).fold(0, |b, i| if u[(i, 0)].abs() > u[(b, 0)].abs() { i } else { b });
        return Err(Error::Mechanism(format!(
            "a rigid-body or mechanism mode of subdomain {} is not restrained by its interfaces: the structure is not supported well enough or is a mechanism",
            owner.get(worst).copied().unwrap_or(0)
        )));
    }
    Ok(())
}
