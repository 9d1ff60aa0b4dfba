//! Dense symmetric helpers of the set-up: a Cholesky factorization taken
//! only when the matrix is clearly positive definite, so that callers can
//! keep an eigendecomposition (about 15 n³ flops against n³/3) for the
//! rare matrices near singularity, where they need its directions.

use faer::linalg::solvers::{Llt, Solve};
use faer::Mat;

/// The Cholesky factor of the symmetric `a` when it is clearly positive
/// definite: every pivot above `pivot_ratio` times the largest, and the
/// smallest eigenvalue, estimated by `steps` inverse iterations from a
/// fixed pseudo-random start, above `eigen_ratio` times the trace. `None`
/// otherwise (or when the factorization fails).
///
/// Pivots bound the smallest eigenvalue only from above; each inverse
/// iteration (2n² flops) multiplies the weight of the smallest eigenvector
/// in the iterate by the gap ratio, so a direction below the threshold is
/// found unless the start misses it by many orders of magnitude. The start
/// is fixed: the same matrix always takes the same path.
pub(crate) fn clearly_positive_definite(
    a: &Mat<f64>,
    pivot_ratio: f64,
    eigen_ratio: f64,
    steps: usize,
) -> Option<Llt<f64>> {
    let n = a.nrows();
    let llt = a.llt(faer::Side::Lower).ok()?;
    let l = llt.L();
    let pivots = (0..n).map(|k| l[(k, k)] * l[(k, k)]);
    let (lo, hi) = pivots.fold((f64::INFINITY, 0.0f64), |(a, b), p| (a.min(p), b.max(p)));
    if !(lo > pivot_ratio * hi) {
        return None;
    }
    let trace: f64 = (0..n).map(|k| a[(k, k)]).sum();
    let x = iterate(n, steps, |x| llt.solve(x))?;
    let rayleigh = (x.transpose() * a * &x)[(0, 0)];
    (rayleigh > eigen_ratio * trace).then_some(llt)
}

/// `steps` applications of `op` to the normalised iterate, from the fixed
/// start of [`inverse_iteration_start`]; the last iterate normalised, or
/// `None` once one vanishes or overflows.
fn iterate(n: usize, steps: usize, op: impl Fn(Mat<f64>) -> Mat<f64>) -> Option<Mat<f64>> {
    let start = inverse_iteration_start(n);
    let normalised = |x: &Mat<f64>| {
        let norm = x.norm_l2();
        (norm > 0.0 && norm.is_finite()).then(|| x * faer::Scale(1.0 / norm))
    };
    let mut x = Mat::<f64>::from_fn(n, 1, |i, _| start[i]);
    for _ in 0..steps {
        x = op(normalised(&x)?);
    }
    normalised(&x)
}

/// Estimates of the largest eigenvalue of the symmetric positive
/// semidefinite `a` and of its smallest eigenpair, without an
/// eigendecomposition (about 15 n³ flops: 3 s for n = 2 645, twice in one
/// active-set step of the 130² nonsmooth grid with 64 subdomains, where
/// one Bunch–Kaufman factorization takes n³/3).
///
/// The largest eigenvalue is the Rayleigh quotient of `steps` power
/// iterations, at least the largest diagonal entry (a lower bound, within
/// a small factor of it: callers compare it with orders of magnitude).
/// The smallest pair is the Rayleigh quotient and direction of `steps`
/// inverse iterations with `a + shift·λ_max·I`, factored by
/// Bunch–Kaufman, so that an exactly singular `a` (a zero column) still
/// factors; the quotient is taken on `a` itself, an upper bound of its
/// smallest eigenvalue. Both start from the fixed start of
/// [`inverse_iteration_start`]: the same matrix takes the same path.
pub(crate) fn extreme_eigen_estimates(a: &Mat<f64>, shift: f64, steps: usize) -> (f64, f64, Vec<f64>) {
    let n = a.nrows();
    let rayleigh = |x: &Mat<f64>| (x.transpose() * a * x)[(0, 0)];
    let diag_max = (0..n).map(|k| a[(k, k)]).fold(0.0f64, f64::max);
    let lmax = iterate(n, steps, |x| a * x).map_or(diag_max, |x| rayleigh(&x).max(diag_max));
    let sigma = shift * lmax;
    let shifted = Mat::<f64>::from_fn(n, n, |i, j| a[(i, j)] + if i == j { sigma } else { 0.0 });
    let lblt = shifted.lblt(faer::Side::Lower);
    match iterate(n, steps, |y| lblt.solve(y)) {
        Some(y) => (lmax, rayleigh(&y).max(0.0), (0..n).map(|i| y[(i, 0)]).collect()),
        None => (lmax, 0.0, inverse_iteration_start(n)),
    }
}

/// The fixed pseudo-random start of the inverse iterations that vouch for
/// a positive definite matrix (here and in the coarse rank check): the
/// same matrix always takes the same path.
pub(crate) fn inverse_iteration_start(n: usize) -> Vec<f64> {
    let mut seed = 0x9e37_79b9_7f4a_7c15u64;
    (0..n)
        .map(|_| {
            seed = seed
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 - 0.5
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Dense `Q diag(λ) Qᵀ` (`Q` a product of Givens rotations) with
    /// eigenvalues `1, 2, …, n`, the one in the middle replaced by `mid`.
    fn rotated(n: usize, mid: f64) -> Mat<f64> {
        let mut q = Mat::<f64>::identity(n, n);
        for k in 0..n - 1 {
            let (c, s) = ((0.3 + k as f64).cos(), (0.3 + k as f64).sin());
            for i in 0..n {
                let (a, b) = (q[(i, k)], q[(i, k + 1)]);
                q[(i, k)] = c * a - s * b;
                q[(i, k + 1)] = s * a + c * b;
            }
        }
        let d = Mat::<f64>::from_fn(n, n, |i, j| match (i == j, i == n / 2) {
            (false, _) => 0.0,
            (true, true) => mid,
            (true, false) => 1.0 + i as f64,
        });
        &q * d * q.transpose()
    }

    /// The estimate is the smallest eigenvalue: it sits between 0.9 and
    /// 1.1 times it on a well-conditioned matrix, and a nearly singular one
    /// is refused.
    #[test]
    fn the_estimate_is_the_smallest_eigenvalue() {
        let n = 40;
        let a = rotated(n, 1.5);
        let trace: f64 = (0..n).map(|k| a[(k, k)]).sum();
        assert!(clearly_positive_definite(&a, 1e-8, 0.9 / trace, 8).is_some());
        assert!(clearly_positive_definite(&a, 1e-8, 1.1 / trace, 8).is_none());
        assert!(clearly_positive_definite(&rotated(n, 1e-13), 1e-8, 1e-10, 8).is_none());
    }

    /// The estimates bracket what the eigendecomposition gives: the largest
    /// eigenvalue within a few per cent, the smallest one at round-off for a
    /// singular matrix (a zero row and column included) with its direction,
    /// and to a few per cent for a regular one.
    #[test]
    fn extreme_estimates_find_the_null_direction() {
        let n = 60;
        for mid in [0.0, 1e-9, 0.5] {
            let a = rotated(n, mid);
            let eig = a.self_adjoint_eigen(faer::Side::Lower).unwrap();
            let (lmax, lmin, v) = extreme_eigen_estimates(&a, 1e-13, 12);
            let (s, u) = (eig.S(), eig.U());
            assert!(
                lmax <= s[n - 1] * (1.0 + 1e-12) && lmax >= 0.95 * s[n - 1],
                "{lmax} against {}",
                s[n - 1]
            );
            assert!(
                lmin >= s[0] - 1e-12 && lmin <= s[0] * 1.05 + 1e-12 * lmax,
                "{lmin} against {}",
                s[0]
            );
            let dot: f64 = (0..n).map(|i| v[i] * u[(i, 0)]).sum();
            assert!(dot.abs() > 1.0 - 1e-6, "direction off by {}", 1.0 - dot.abs());
        }
        // An exactly zero row and column: the shift keeps the factorization
        // finite, and the direction is that row's unit vector.
        let mut a = rotated(n, 1.0);
        for k in 0..n {
            a[(7, k)] = 0.0;
            a[(k, 7)] = 0.0;
        }
        let (lmax, lmin, v) = extreme_eigen_estimates(&a, 1e-13, 12);
        assert!(lmin <= 1e-13 * lmax, "{lmin}");
        assert!(v[7].abs() > 1.0 - 1e-9, "{}", v[7]);
    }
}
