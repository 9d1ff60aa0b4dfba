//! Interface scaling of the interface CG's Dirichlet (or lumped)
//! preconditioner.
//!
//! The unknowns of the interface problem are pair forces (one entry per
//! pair of subdomains sharing a dof, redundant at cross points), so the
//! FETI theory of the Dirichlet preconditioner applies: `M = B_D S B_Dᵀ`
//! with `B_D` the *scaled* jump operator. On the entry of the pair
//! `(lo, hi)` at dof `x`, the lo side is weighted by `δ_hi(x)` and the hi
//! side by `δ_lo(x)`, with `δ_k(x) = ρ_k(x) / Σ_{l ∋ x} ρ_l(x)`: each side
//! takes the *other* side's share of the stiffness. With `ρ = 1` this is
//! the multiplicity scaling (`1/m` at a dof shared by `m` subdomains); with
//! `ρ_k(x) = K_k(x, x)` (the diagonal of the subdomain's stiffness) it is the
//! diagonal-stiffness ("ρ-") scaling, which keeps the preconditioner
//! spectrally equivalent across a bar/cable contrast: a soft side is not
//! asked to hold the stiff side's displacement jump.
//!
//! Without scaling, `M = B S Bᵀ` overweights cross points (a dof in `m`
//! subdomains appears in `m(m−1)/2` pairs) and, across a contrast, applies
//! the stiff side's Schur complement to the whole jump: the README's tower
//! (bars 1e4 × the cables, 4 subdomains) did not converge in 851 CG
//! iterations. Pointwise stiffness weights everywhere converge there (596
//! iterations) but they oscillate along an interface where the element sets
//! of a node differ, which costs iterations on homogeneous plates (130²
//! grid, 16 subdomains: 393 iterations against 120 with multiplicity). The
//! default, [`InterfaceScaling::Contrast`], uses the stiffness weights only
//! at dofs whose sides differ by more than [`CONTRAST_THRESHOLD`] and the
//! multiplicity elsewhere: 563 iterations on the tower, 120 on that grid.
//!
//! The default, [`InterfaceScaling::Deluxe`], replaces the pointwise
//! weights by the dense ones of [`DeluxeBlock`], built from the Schur
//! complements of the subdomains sharing a set of dofs: on each
//! interface's face (dofs of two subdomains), and on each edge (dofs
//! shared by the same three or more subdomains, [`Edges`]): 60 iterations
//! on that tower, 16/23/16 on the 24² grid with 4/16/64 subdomains
//! (52/55/37 with contrast; 20/29/18 when the cross points kept the
//! contrast weights), 22/22 on a uniform 30³ tower with 16/64 subdomains
//! (44/82 with deluxe on the faces only). The contrast weights remain
//! where a block's weights cannot be formed.

use crate::kernels::{Run, Side};
use faer::{Mat, MatRef};

/// Weights of the scaled jump operator `B_D` (`[solver] interface_scaling`
/// of a scene, `--interface-scaling`, `nsdd_options_set_interface_scaling`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum InterfaceScaling {
    /// `B_D = B`: the unscaled `Σ_E B_E S_E B_Eᵀ`.
    None,
    /// `δ_k = 1/m`: multiplicity of the dof.
    Multiplicity,
    /// `δ_k = K_k(x,x) / Σ_l K_l(x,x)`: diagonal stiffness of each side.
    Stiffness,
    /// Stiffness weights at dofs whose sides' diagonals differ by more
    /// than [`CONTRAST_THRESHOLD`], multiplicity elsewhere.
    Contrast,
    /// Deluxe: on the face dofs of each interface (those shared by its two
    /// subdomains only) the dense weights `D_hi = (S_lo + S_hi)⁻¹ S_hi` and
    /// `D_lo = I − D_hi` of the face blocks of the subdomains' Schur
    /// complements, and on each edge `E` (dofs shared by the same `m ≥ 3`
    /// subdomains) `D_j = (Σ_i S_i^E)⁻¹ S_j^E` ([`DeluxeBlock`]); the
    /// [`InterfaceScaling::Contrast`] weights where a block cannot be
    /// formed. Every block is the exact principal block of the Schur
    /// complement.
    Deluxe,
    /// [`InterfaceScaling::Deluxe`] with the blocks whose exact
    /// computation would cost more than about
    /// [`crate::subdomain::NEAR_MIN_WORK`] multiply-adds (large 3D faces)
    /// computed from the interior dofs near them only, the farther ones
    /// held ("economic deluxe",
    /// [`crate::subdomain::InteriorProblem::schur_block_near`]): the same
    /// weights on small subdomains; on the 30³ tower with 4 and 16
    /// subdomains the blocks 2–4× cheaper and the whole set-up 1.4–2×, for
    /// the same iteration counts (8 % more on a tower with stiffness
    /// contrast 1e4, BENCHMARKS.md). The default.
    #[default]
    #[serde(rename = "economic_deluxe")]
    EconomicDeluxe,
}

/// Ratio of the largest to the smallest side diagonal at a dof above which
/// [`InterfaceScaling::Contrast`] uses the stiffness weights there (a side
/// with a zero diagonal, which holds the dof by a mechanism only, keeps the
/// multiplicity weights: taken as contrast it cost the 130² grid 173
/// iterations against 120 with 16 subdomains).
pub const CONTRAST_THRESHOLD: f64 = 1000.0;

impl InterfaceScaling {
    pub(crate) fn is_default(&self) -> bool {
        *self == InterfaceScaling::default()
    }

    /// Name (`none`, `multiplicity`, `stiffness`, `contrast`, `deluxe`,
    /// `economic_deluxe`).
    pub fn as_str(self) -> &'static str {
        match self {
            InterfaceScaling::None => "none",
            InterfaceScaling::Multiplicity => "multiplicity",
            InterfaceScaling::Stiffness => "stiffness",
            InterfaceScaling::Contrast => "contrast",
            InterfaceScaling::Deluxe => "deluxe",
            InterfaceScaling::EconomicDeluxe => "economic_deluxe",
        }
    }

    /// Whether the weights are deluxe blocks (exact or economic).
    pub fn is_deluxe(self) -> bool {
        matches!(self, InterfaceScaling::Deluxe | InterfaceScaling::EconomicDeluxe)
    }
}

impl std::str::FromStr for InterfaceScaling {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "none" => Ok(InterfaceScaling::None),
            "multiplicity" => Ok(InterfaceScaling::Multiplicity),
            "stiffness" => Ok(InterfaceScaling::Stiffness),
            "contrast" => Ok(InterfaceScaling::Contrast),
            "deluxe" => Ok(InterfaceScaling::Deluxe),
            "economic_deluxe" => Ok(InterfaceScaling::EconomicDeluxe),
            _ => Err(format!(
                "unknown interface scaling '{s}' (expected none, multiplicity, stiffness, contrast, deluxe or economic_deluxe)"
            )),
        }
    }
}

/// Per-entry weights of one interface: `lo[j]` multiplies the lo side's
/// value of entry `j` (it is `δ_hi`), `hi[j]` the hi side's (`δ_lo`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EntryWeights {
    pub lo: Vec<f64>,
    pub hi: Vec<f64>,
}

/// One interface as the weights see it: its subdomains and the local dof
/// of each entry on either side.
#[derive(Debug, Clone, Copy)]
pub struct InterfaceEntries<'a> {
    pub lo: usize,
    pub hi: usize,
    pub lo_idx: &'a [u32],
    pub hi_idx: &'a [u32],
}

/// The weights of every interface (in the order given). `dofs[s]` maps
/// subdomain `s`'s local dofs to global ones, `multiplicity[s]` gives the
/// number of subdomains sharing each local dof, `diag[s]` is the diagonal
/// of its stiffness (used by [`InterfaceScaling::Stiffness`] only). With
/// [`InterfaceScaling::None`] every weight is 1. A dof whose stiffness sum
/// is not positive falls back to the multiplicity weights. Set-up only
/// (allocates).
pub fn interface_weights(
    ifaces: &[InterfaceEntries<'_>],
    dofs: &[Vec<usize>],
    multiplicity: &[Vec<u32>],
    diag: &[Vec<f64>],
    kind: InterfaceScaling,
) -> Vec<EntryWeights> {
    if kind == InterfaceScaling::None {
        return ifaces
            .iter()
            .map(|it| EntryWeights {
                lo: vec![1.0; it.lo_idx.len()],
                hi: vec![1.0; it.hi_idx.len()],
            })
            .collect();
    }
    let n_global = dofs.iter().flat_map(|d| d.iter()).max().map_or(0, |&d| d + 1);
    // Contrast: which dofs see sides differing by more than the threshold.
    let mut contrast = vec![false; n_global];
    if matches!(kind, InterfaceScaling::Contrast | InterfaceScaling::Deluxe) {
        let (mut lo, mut hi) = (vec![f64::INFINITY; n_global], vec![0.0f64; n_global]);
        for (s, (sd, ms)) in dofs.iter().zip(multiplicity).enumerate() {
            for (l, (&d, &m)) in sd.iter().zip(ms).enumerate() {
                if m > 1 {
                    lo[d] = lo[d].min(diag[s][l].max(0.0));
                    hi[d] = hi[d].max(diag[s][l]);
                }
            }
        }
        for d in 0..n_global {
            contrast[d] = lo[d] > 0.0 && hi[d] > CONTRAST_THRESHOLD * lo[d];
        }
    }
    let rho = |s: usize, l: u32| -> f64 {
        match kind {
            InterfaceScaling::Stiffness => diag[s][l as usize].max(0.0),
            InterfaceScaling::Contrast | InterfaceScaling::Deluxe if contrast[dofs[s][l as usize]] => {
                diag[s][l as usize].max(0.0)
            }
            _ => 1.0,
        }
    };
    // Σ_l ρ_l(x) over the subdomains sharing each interface dof x, and
    // their number m(x).
    let mut sum = vec![0.0; n_global];
    let mut mult = vec![0u32; n_global];
    for (s, (sd, ms)) in dofs.iter().zip(multiplicity).enumerate() {
        for (l, (&d, &m)) in sd.iter().zip(ms).enumerate() {
            if m > 1 {
                sum[d] += rho(s, l as u32);
                mult[d] = m;
            }
        }
    }
    ifaces
        .iter()
        .map(|it| {
            let n = it.lo_idx.len();
            let (mut lo, mut hi) = (Vec::with_capacity(n), Vec::with_capacity(n));
            for (&a, &b) in it.lo_idx.iter().zip(it.hi_idx) {
                let d = dofs[it.lo][a as usize];
                let total = sum[d];
                if total > 0.0 && total.is_finite() {
                    lo.push(rho(it.hi, b) / total);
                    hi.push(rho(it.lo, a) / total);
                } else {
                    let m = mult[d].max(2) as f64;
                    lo.push(1.0 / m);
                    hi.push(1.0 / m);
                }
            }
            EntryWeights { lo, hi }
        })
        .collect()
}

/// Scaled scatter-add over runs: `r[idx[j]] += coef · w[j] · f[j]` with the
/// `side` map (`B_Dᵀ` on one side of an interface).
#[inline]
pub fn scatter_add_scaled_runs(r: &mut [f64], side: Side, runs: &[Run], f: &[f64], w: &[f64], coef: f64) {
    for run in runs {
        let (e, a, n) = (run.entry as usize, run.start(side), run.len as usize);
        for ((x, &fj), &wj) in r[a..a + n].iter_mut().zip(&f[e..e + n]).zip(&w[e..e + n]) {
            *x += coef * wj * fj;
        }
    }
}

/// Scaled jump over runs: `out[j] = w_lo[j] lo[lo_idx[j]] − w_hi[j] hi[hi_idx[j]]`
/// (`B_D` on an interface).
#[inline]
pub fn scaled_jump_runs(out: &mut [f64], lo: &[f64], w_lo: &[f64], hi: &[f64], w_hi: &[f64], runs: &[Run]) {
    for r in runs {
        let (e, a, b, n) = (r.entry as usize, r.lo as usize, r.hi as usize, r.len as usize);
        let (o, x, y, wx, wy) = (
            &mut out[e..e + n],
            &lo[a..a + n],
            &hi[b..b + n],
            &w_lo[e..e + n],
            &w_hi[e..e + n],
        );
        for ((o, (&x, &wx)), (&y, &wy)) in o.iter_mut().zip(x.iter().zip(wx)).zip(y.iter().zip(wy)) {
            *o = wx * x - wy * y;
        }
    }
}

/// Deluxe weights of one block of an interface's entries.
///
/// **Faces.** The entries whose dof is shared by the interface's two
/// subdomains only. With `S_lo`, `S_hi` the face blocks of the two
/// subdomains' Schur complements (the force each side needs to hold a
/// displacement of the face, the rest of its interface fixed), the average
/// of the two sides' displacements is `ū = (S_lo + S_hi)⁻¹ (S_lo u_lo + S_hi
/// u_hi)`, so `u_lo − ū = D_hi (u_lo − u_hi)` with `D_hi = (S_lo + S_hi)⁻¹
/// S_hi`: the scaled jump operator is `B_D,lo = D_hiᵀ` and `B_D,hi = D_loᵀ =
/// (I − D_hi)ᵀ` on the face. Unlike a pointwise weight, it accounts for how a
/// soft cable side and a stiff bar side resist a displacement *mode* of the
/// face (a shear of the bar frame), not a dof.
///
/// **Edges.** A set `E` of dofs shared by the same `m ≥ 3` subdomains (an
/// edge or a vertex of the partition) appears on each of their `m(m−1)/2`
/// pair interfaces. The average is `ū = Σ_j D_j u_j` with `D_j = (Σ_i
/// S_i^E)⁻¹ S_j^E`, and `u_k − ū = Σ_{l≠k} D_l (u_k − u_l)` (the `D_j` sum to
/// `I`): on the pair `(k, l)` the lo side `k` takes `D_l` and the hi side `l`
/// takes `D_k`, which need not add up to `I` ([`DeluxeBlock::edge_weights`]).
/// Each pair needs only its own two traces, like a face.
#[derive(Debug, Clone, Default)]
pub struct DeluxeBlock {
    /// Entry indices (in the interface) of the block.
    pub entries: Vec<u32>,
    /// `D_hi`, `entries.len()²`, column-major.
    pub d: Vec<f64>,
    /// `D_lo`, column-major; empty on a face, where `D_lo = I − D_hi`.
    pub d_lo: Vec<f64>,
    /// Scratch of the applications (no allocation per iteration).
    x: Vec<f64>,
    x2: Vec<f64>,
    y: Vec<f64>,
}

/// Relative eigenvalue of `Σ S_j` below which a block direction is taken
/// as held by no side (mechanisms on all): it is split evenly.
const DELUXE_PINV_RTOL: f64 = 1e-12;

/// Smallest Cholesky pivot of `Σ S_j`, relative to the largest, for which
/// the weights take the Cholesky path; below it the eigendecomposition
/// sorts out the directions no side holds.
const DELUXE_CHOLESKY_PIVOT_RATIO: f64 = 1e-8;

/// Smallest eigenvalue of `Σ S_j` (estimated), relative to its trace, for
/// which the weights take the Cholesky path: a margin of 100 over
/// [`DELUXE_PINV_RTOL`] for the estimate.
const DELUXE_CHOLESKY_EIGEN_RATIO: f64 = 1e-10;

/// Blocks of at least this many dofs take the Cholesky path.
const DELUXE_CHOLESKY_MIN_DOFS: usize = 96;

/// Inverse-iteration steps of that estimate.
const DELUXE_INVERSE_ITERATIONS: usize = 8;

/// The entries of `d`, column-major, if all are finite.
fn finite_column_major(d: &Mat<f64>) -> Option<Vec<f64>> {
    let data: Vec<f64> = (0..d.ncols())
        .flat_map(|j| (0..d.nrows()).map(move |i| d[(i, j)]))
        .collect();
    data.iter().all(|v| v.is_finite()).then_some(data)
}

/// `(Σ S_j)⁺ rhs + share · N Nᵀ` on each square block of `rhs`, column-major
/// (`N` the null space of `sum`), by Cholesky on large well-conditioned sums
/// and by eigendecomposition otherwise. Any finite result keeps the
/// preconditioner symmetric positive, so round-off here costs iterations
/// at worst, never correctness.
fn deluxe_solve(sum: &Mat<f64>, rhs: MatRef<'_, f64>, share: f64) -> Option<Vec<f64>> {
    // The usual large case: the sum is positive definite and a Cholesky
    // factorization gives the weights in about 2.3 n³ flops a block, against
    // about 15 n³ for the eigendecomposition and its products (3D faces of
    // 1 000+ dofs spent a sixth of the 30³ tower's set-up there). Small
    // blocks keep the eigendecomposition, whose cost is negligible there
    // (and whose rounding the results of small scenes were measured with).
    let fast = if sum.nrows() >= DELUXE_CHOLESKY_MIN_DOFS {
        by_cholesky(sum, rhs)
    } else {
        None
    };
    fast.or_else(|| by_eigen(sum, rhs, share))
}

/// `sum⁻¹ rhs` by Cholesky, column-major; `None` when the sum is not
/// clearly positive definite (a pivot below [`DELUXE_CHOLESKY_PIVOT_RATIO`]
/// of the largest).
fn by_cholesky(sum: &Mat<f64>, rhs: MatRef<'_, f64>) -> Option<Vec<f64>> {
    use faer::linalg::solvers::Solve;
    // A sum with directions the eigendecomposition would split evenly
    // (below DELUXE_PINV_RTOL) goes that way instead of being inverted.
    let llt = crate::dense::clearly_positive_definite(
        sum,
        DELUXE_CHOLESKY_PIVOT_RATIO,
        DELUXE_CHOLESKY_EIGEN_RATIO,
        DELUXE_INVERSE_ITERATIONS,
    )?;
    finite_column_major(&llt.solve(rhs))
}

/// `sum⁺ rhs + share · N Nᵀ` (on each square block of `rhs`) by
/// eigendecomposition, column-major.
fn by_eigen(sum: &Mat<f64>, rhs: MatRef<'_, f64>, share: f64) -> Option<Vec<f64>> {
    let n = sum.nrows();
    let evd = sum.self_adjoint_eigen(faer::Side::Lower).ok()?;
    let (u, s) = (evd.U(), evd.S().column_vector());
    let smax = (0..n).map(|k| s[k].abs()).fold(0.0f64, f64::max);
    let cut = DELUXE_PINV_RTOL * smax;
    // sum⁺ rhs = U Λ⁺ Uᵀ rhs, plus share · U₀ U₀ᵀ.
    let ut_rhs = u.transpose() * rhs;
    // The null part is the same for every block: formed once.
    let null = Mat::<f64>::from_fn(n, n, |k, j| if s[k] > cut { 0.0 } else { share * u[(j, k)] });
    let u_null = u * &null;
    let mut scaled = Mat::<f64>::zeros(n, n);
    let blocks = rhs.ncols() / n.max(1);
    let mut out = Vec::with_capacity(n * rhs.ncols());
    for b in 0..blocks {
        for k in (0..n).filter(|&k| s[k] > cut) {
            for j in 0..n {
                scaled[(k, j)] = ut_rhs[(k, b * n + j)] / s[k];
            }
        }
        out.extend(finite_column_major(&(u * &scaled + &u_null))?);
    }
    Some(out)
}

impl DeluxeBlock {
    /// The face `entries` (entry indices) with the face blocks `s_lo`,
    /// `s_hi` (symmetric, `entries.len()` square). `D_hi = (S_lo + S_hi)⁺
    /// S_hi + ½ N Nᵀ` with `N` the null space of the sum: directions neither
    /// side resists get the multiplicity weights. `None` if the eigensolver
    /// fails.
    pub fn face(entries: Vec<u32>, s_lo: MatRef<'_, f64>, s_hi: MatRef<'_, f64>) -> Option<DeluxeBlock> {
        let n = entries.len();
        let sum = Mat::from_fn(n, n, |i, j| {
            0.5 * (s_lo[(i, j)] + s_lo[(j, i)] + s_hi[(i, j)] + s_hi[(j, i)])
        });
        let d = deluxe_solve(&sum, s_hi, 0.5)?;
        Some(DeluxeBlock::new(entries, Vec::new(), d))
    }

    /// The block of `entries` with `D_lo = d_lo` (empty: `I − D_hi`) and
    /// `D_hi = d_hi`, column-major.
    pub fn new(entries: Vec<u32>, d_lo: Vec<f64>, d_hi: Vec<f64>) -> DeluxeBlock {
        let n = entries.len();
        DeluxeBlock {
            entries,
            d: d_hi,
            d_lo,
            x: vec![0.0; n],
            x2: vec![0.0; n],
            y: vec![0.0; n],
        }
    }

    /// The weights `D_j = (Σ_i S_i)⁺ S_j + N Nᵀ / m` of an edge shared by the
    /// `m = sides.len()` subdomains with the Schur blocks `sides` (square,
    /// symmetric, all of one size), column-major in the order given: they
    /// sum to `I`, and directions no side resists get the multiplicity
    /// weights. `None` if a block is missing, of the wrong size, or the
    /// eigensolver fails.
    pub fn edge_weights(sides: &[MatRef<'_, f64>]) -> Option<Vec<Vec<f64>>> {
        let n = sides.first()?.nrows();
        if sides.iter().any(|s| s.nrows() != n || s.ncols() != n) || n == 0 {
            return None;
        }
        let m = sides.len();
        let sum = Mat::from_fn(n, n, |i, j| {
            0.5 * sides.iter().map(|s| s[(i, j)] + s[(j, i)]).sum::<f64>()
        });
        let rhs = Mat::from_fn(n, n * m, |i, c| sides[c / n][(i, c % n)]);
        let all = deluxe_solve(&sum, rhs.as_ref(), 1.0 / m as f64)?;
        Some(all.chunks_exact(n * n).map(<[f64]>::to_vec).collect())
    }

    /// `y = D x` with `D` column-major (`x.len()` square).
    fn apply(d: &[f64], x: &[f64], y: &mut [f64]) {
        y.iter_mut().for_each(|y| *y = 0.0);
        for (col, &xj) in d.chunks_exact(x.len()).zip(x) {
            for (y, &a) in y.iter_mut().zip(col) {
                *y += a * xj;
            }
        }
    }

    /// `B_D,loᵀ r` and `B_D,hiᵀ r` on the block: `lo[f] = (D_hi r_F)`, `hi[f]
    /// = D_lo r_F` (the other entries are left alone). No allocation.
    pub fn scale(&mut self, r: &[f64], lo: &mut [f64], hi: &mut [f64]) {
        for (x, &f) in self.x.iter_mut().zip(&self.entries) {
            *x = r[f as usize];
        }
        Self::apply(&self.d, &self.x, &mut self.y);
        if self.d_lo.is_empty() {
            for ((&f, &x), &y) in self.entries.iter().zip(&self.x).zip(&self.y) {
                lo[f as usize] = y;
                hi[f as usize] = x - y;
            }
        } else {
            Self::apply(&self.d_lo, &self.x, &mut self.x2);
            for ((&f, &y), &y2) in self.entries.iter().zip(&self.y).zip(&self.x2) {
                lo[f as usize] = y;
                hi[f as usize] = y2;
            }
        }
    }

    /// `z_F = D_hiᵀ y_lo − D_loᵀ y_hi` on the block, with `y_lo[lo_idx[f]]`,
    /// `y_hi[hi_idx[f]]` the two sides' values of entry `f`. No allocation.
    pub fn jump(&mut self, z: &mut [f64], y_lo: &[f64], lo_idx: &[u32], y_hi: &[f64], hi_idx: &[u32]) {
        self.face_jump(y_lo, lo_idx, y_hi, hi_idx);
        self.write_face(z);
    }

    /// [`DeluxeBlock::jump`] in two halves, for callers that see the two
    /// sides' values and the interface vector `z` at different times (the
    /// communication seam hands out the traces per interface): this one
    /// computes the block's values from the traces into its scratch...
    pub fn face_jump(&mut self, y_lo: &[f64], lo_idx: &[u32], y_hi: &[f64], hi_idx: &[u32]) {
        let n = self.entries.len();
        if self.d_lo.is_empty() {
            // D_hiᵀ y_lo − (I − D_hi)ᵀ y_hi = D_hiᵀ (y_lo + y_hi) − y_hi.
            for (x, &f) in self.x.iter_mut().zip(&self.entries) {
                let f = f as usize;
                *x = y_lo[lo_idx[f] as usize] + y_hi[hi_idx[f] as usize];
            }
            for ((yk, col), &f) in self.y.iter_mut().zip(self.d.chunks_exact(n)).zip(&self.entries) {
                let dot = crate::kernels::dot(col, &self.x);
                *yk = dot - y_hi[hi_idx[f as usize] as usize];
            }
        } else {
            for ((x, x2), &f) in self.x.iter_mut().zip(self.x2.iter_mut()).zip(&self.entries) {
                let f = f as usize;
                *x = y_lo[lo_idx[f] as usize];
                *x2 = y_hi[hi_idx[f] as usize];
            }
            let cols = self.d.chunks_exact(n).zip(self.d_lo.chunks_exact(n));
            for (yk, (c_hi, c_lo)) in self.y.iter_mut().zip(cols) {
                let a = crate::kernels::dot(c_hi, &self.x);
                let b = crate::kernels::dot(c_lo, &self.x2);
                *yk = a - b;
            }
        }
    }

    /// ...and this one writes them into the block's entries of `z`.
    pub fn write_face(&self, z: &mut [f64]) {
        for (&f, &y) in self.entries.iter().zip(&self.y) {
            z[f as usize] = y;
        }
    }
}

/// One set of interface dofs shared by the same three or more subdomains
/// (an edge or a vertex of the partition): the unit of the deluxe weights
/// at cross points.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Edge {
    /// Its subdomains, increasing.
    pub subdomains: Vec<usize>,
    /// Per subdomain (in that order): the local dof of each of the edge's
    /// dofs, in increasing global order.
    pub rows: Vec<Vec<u32>>,
}

/// The edges of a decomposition ([`Edge`]), and where they lie on its
/// pair interfaces.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Edges {
    pub edges: Vec<Edge>,
    /// Per interface: its edges, increasing, each with the interface's
    /// entries of the edge's dofs (in the edge's order).
    pub of_interface: Vec<Vec<(usize, Vec<u32>)>>,
    /// Per subdomain: its edges, increasing.
    pub of_subdomain: Vec<Vec<usize>>,
}

impl Edges {
    /// The edges of the interfaces `ifaces`, with `dofs` and `multiplicity`
    /// as in [`interface_weights`]. Every pair of an edge's subdomains has
    /// an interface holding all its dofs (a dof shared by two subdomains is
    /// an entry of their interface); an interface that does not is left
    /// out of that edge. The same on every process. Set-up only.
    pub fn new(ifaces: &[InterfaceEntries<'_>], dofs: &[Vec<usize>], multiplicity: &[Vec<u32>]) -> Edges {
        use std::collections::BTreeMap;
        // Per global dof of multiplicity ≥ 3: its (subdomain, local dof)
        // pairs and its (interface, entry) pairs.
        type At = (Vec<(usize, u32)>, Vec<(usize, u32)>);
        let mut at: BTreeMap<usize, At> = BTreeMap::new();
        for (i, it) in ifaces.iter().enumerate() {
            for (j, (&a, &b)) in it.lo_idx.iter().zip(it.hi_idx).enumerate() {
                if multiplicity[it.lo][a as usize] < 3 {
                    continue;
                }
                let e = at.entry(dofs[it.lo][a as usize]).or_default();
                e.0.extend([(it.lo, a), (it.hi, b)]);
                e.1.push((i, j as u32));
            }
        }
        let mut by_set: BTreeMap<Vec<usize>, Vec<usize>> = BTreeMap::new();
        for (&g, (subs, _)) in at.iter_mut() {
            subs.sort_unstable();
            subs.dedup();
            by_set
                .entry(subs.iter().map(|&(s, _)| s).collect())
                .or_default()
                .push(g);
        }
        let mut out = Edges {
            edges: Vec::with_capacity(by_set.len()),
            of_interface: vec![Vec::new(); ifaces.len()],
            of_subdomain: vec![Vec::new(); dofs.len()],
        };
        for (e, (subdomains, globals)) in by_set.into_iter().enumerate() {
            let rows = subdomains
                .iter()
                .map(|&s| {
                    // `s` is in the set because a pair listed it with `g`.
                    let local = |g: &usize| at[g].0.iter().find(|&&(t, _)| t == s).expect("listed with the dof").1;
                    globals.iter().map(local).collect()
                })
                .collect();
            let mut pairs: BTreeMap<usize, Vec<u32>> = BTreeMap::new();
            for g in &globals {
                for &(i, j) in &at[g].1 {
                    pairs.entry(i).or_default().push(j);
                }
            }
            for (i, entries) in pairs {
                if entries.len() == globals.len() {
                    out.of_interface[i].push((e, entries));
                }
            }
            for &s in &subdomains {
                out.of_subdomain[s].push(e);
            }
            out.edges.push(Edge { subdomains, rows });
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two subdomains share dofs 0 and 1, three share dof 2 (a cross point).
    fn weights(kind: InterfaceScaling) -> Vec<EntryWeights> {
        // Local numbering: subdomain s holds global dof d at local d.
        let dofs = vec![vec![0, 1, 2], vec![0, 1, 2], vec![0, 1, 2]];
        let mult = vec![vec![2, 2, 3], vec![2, 2, 3], vec![1, 1, 3]];
        let diag = vec![vec![1.0, 3.0, 1.0], vec![1.0, 1.0, 2.0], vec![0.0, 0.0, 5.0]];
        let (a, b, c) = ([0u32, 1, 2], [0u32, 1, 2], [2u32]);
        let ifaces = [
            InterfaceEntries {
                lo: 0,
                hi: 1,
                lo_idx: &a,
                hi_idx: &b,
            },
            InterfaceEntries {
                lo: 0,
                hi: 2,
                lo_idx: &c,
                hi_idx: &c,
            },
            InterfaceEntries {
                lo: 1,
                hi: 2,
                lo_idx: &c,
                hi_idx: &c,
            },
        ];
        interface_weights(&ifaces, &dofs, &mult, &diag, kind)
    }

    #[test]
    fn each_side_takes_the_other_sides_share() {
        let none = weights(InterfaceScaling::None);
        assert!(none.iter().all(|w| w.lo.iter().chain(&w.hi).all(|&x| x == 1.0)));
        let m = weights(InterfaceScaling::Multiplicity);
        assert_eq!(m[0].lo, vec![0.5, 0.5, 1.0 / 3.0]);
        assert_eq!(m[1].hi, vec![1.0 / 3.0]);
        // No side ratio here exceeds CONTRAST_THRESHOLD: Contrast is the
        // multiplicity scaling.
        assert_eq!(weights(InterfaceScaling::Contrast), m);
        let k = weights(InterfaceScaling::Stiffness);
        // dof 1: K_0 = 3, K_1 = 1, so the lo side (0) gets the hi side's
        // share 1/4 and the hi side the lo side's 3/4.
        assert_eq!((k[0].lo[1], k[0].hi[1]), (0.25, 0.75));
        // Cross point (sum 8): pair (0, 2) weights 5/8 on 0 and 1/8 on 2.
        assert_eq!((k[1].lo[0], k[1].hi[0]), (5.0 / 8.0, 1.0 / 8.0));
        assert_eq!((k[2].lo[0], k[2].hi[0]), (5.0 / 8.0, 2.0 / 8.0));
    }

    #[test]
    fn contrast_weights_only_where_the_sides_differ() {
        // dof 0: diagonals 1 and 1e4 (contrast), dof 1: 1 and 2, dof 2: 0
        // and 1e4 (a mechanism side: no contrast).
        let dofs = vec![vec![0, 1, 2], vec![0, 1, 2]];
        let mult = vec![vec![2, 2, 2], vec![2, 2, 2]];
        let diag = vec![vec![1.0, 1.0, 0.0], vec![1e4, 2.0, 1e4]];
        let idx = [0u32, 1, 2];
        let ifaces = [InterfaceEntries {
            lo: 0,
            hi: 1,
            lo_idx: &idx,
            hi_idx: &idx,
        }];
        let w = interface_weights(&ifaces, &dofs, &mult, &diag, InterfaceScaling::Contrast);
        assert_eq!(w[0].lo, vec![1e4 / 10001.0, 0.5, 0.5]);
        assert_eq!(w[0].hi, vec![1.0 / 10001.0, 0.5, 0.5]);
    }

    #[test]
    fn deluxe_face_weights() {
        // 1×1 faces: the stiffness ratio of the two sides (lo side 3, hi 1:
        // D_hi = 1/4); a face neither side holds is split evenly.
        let d = DeluxeBlock::face(
            vec![0],
            Mat::from_fn(1, 1, |_, _| 3.0).as_ref(),
            Mat::from_fn(1, 1, |_, _| 1.0).as_ref(),
        )
        .unwrap();
        assert!((d.d[0] - 0.25).abs() < 1e-15);
        let z = Mat::<f64>::zeros(1, 1);
        assert_eq!(DeluxeBlock::face(vec![0], z.as_ref(), z.as_ref()).unwrap().d, vec![0.5]);
        // 2×2 with coupling: (S_lo + S_hi) D_hi = S_hi.
        let s_lo = Mat::from_fn(2, 2, |i, j| [[4.0, 1.0], [1.0, 3.0]][i][j]);
        let s_hi = Mat::from_fn(2, 2, |i, j| [[1.0, -0.5], [-0.5, 2.0]][i][j]);
        let mut f = DeluxeBlock::face(vec![0, 2], s_lo.as_ref(), s_hi.as_ref()).unwrap();
        let dm = Mat::from_fn(2, 2, |i, j| f.d[j * 2 + i]);
        let res = (&s_lo + &s_hi) * &dm - &s_hi;
        assert!(res.norm_max() < 1e-14, "{res:?}");
        // scale: lo = D r_F, hi = r_F − D r_F on the face entries only.
        let r = [1.0, 7.0, -2.0];
        let (mut lo, mut hi) = ([9.0; 3], [9.0; 3]);
        f.scale(&r, &mut lo, &mut hi);
        let dr = [dm[(0, 0)] - 2.0 * dm[(0, 1)], dm[(1, 0)] - 2.0 * dm[(1, 1)]];
        assert!((lo[0] - dr[0]).abs() < 1e-15 && (lo[2] - dr[1]).abs() < 1e-15 && lo[1] == 9.0);
        assert!((hi[0] - (1.0 - dr[0])).abs() < 1e-15 && (hi[2] - (-2.0 - dr[1])).abs() < 1e-15);
        // jump: z_F = D_hiᵀ y_lo − (I − D_hi)ᵀ y_hi, sides indexed apart.
        let (ylo, yhi) = ([0.0, 1.0, 0.0, 2.0], [3.0, 0.0, -1.0]);
        let mut z = [5.0; 3];
        f.jump(&mut z, &ylo, &[1, 0, 3], &yhi, &[0, 0, 2]);
        let want = |k: usize| {
            let (a, b) = ([1.0, 2.0], [3.0, -1.0]);
            (0..2).map(|i| dm[(i, k)] * (a[i] + b[i])).sum::<f64>() - b[k]
        };
        assert!((z[0] - want(0)).abs() < 1e-14 && (z[2] - want(1)).abs() < 1e-14 && z[1] == 5.0);
    }

    /// The Cholesky path and the eigendecomposition give the same `D_hi`
    /// on a positive definite sum (a 40×40 face with a 1e4 stiffness
    /// contrast between the sides); a singular sum (a direction neither
    /// side holds) is left to the eigendecomposition, which splits it
    /// evenly.
    #[test]
    fn deluxe_cholesky_path_agrees_with_the_eigendecomposition() {
        let n = 40;
        let spd = |scale: f64, seed: usize| {
            let b = Mat::from_fn(n, n, |i, j| (((i * 31 + j * 17 + seed) % 23) as f64 - 11.0) / 11.0);
            Mat::from_fn(n, n, |i, j| {
                let g: f64 = (0..n).map(|k| b[(i, k)] * b[(j, k)]).sum();
                scale * (g + if i == j { 0.5 } else { 0.0 })
            })
        };
        let (s_lo, s_hi) = (spd(1e4, 3), spd(1.0, 7));
        let sum = &s_lo + &s_hi;
        let chol = by_cholesky(&sum, s_hi.as_ref()).expect("positive definite");
        let eig = by_eigen(&sum, s_hi.as_ref(), 0.5).unwrap();
        let err = chol.iter().zip(&eig).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
        assert!(err < 1e-10, "{err}");
        // Singular sum: zero row and column 0 on both sides.
        let cut = |m: &Mat<f64>| Mat::from_fn(n, n, |i, j| if i == 0 || j == 0 { 0.0 } else { m[(i, j)] });
        let (z_lo, z_hi) = (cut(&s_lo), cut(&s_hi));
        assert!(by_cholesky(&(&z_lo + &z_hi), z_hi.as_ref()).is_none());
        let f = DeluxeBlock::face((0..n as u32).collect(), z_lo.as_ref(), z_hi.as_ref()).unwrap();
        assert!((f.d[0] - 0.5).abs() < 1e-12, "{}", f.d[0]);
    }

    #[test]
    fn scaled_kernels_match_the_plain_formula() {
        let runs = crate::kernels::runs(&[0, 1, 3], &[2, 3, 0]);
        let (f, w) = ([1.0, 2.0, 3.0], [0.5, 0.25, 2.0]);
        let mut r = [0.0; 4];
        scatter_add_scaled_runs(&mut r, Side::Hi, &runs, &f, &w, -1.0);
        assert_eq!(r, [-6.0, 0.0, -0.5, -0.5]);
        let (lo, hi) = ([1.0, 2.0, 3.0, 4.0], [10.0, 20.0, 30.0, 40.0]);
        let mut out = [0.0; 3];
        scaled_jump_runs(&mut out, &lo, &w, &hi, &[1.0, 0.5, 0.25], &runs);
        assert_eq!(out, [0.5 - 30.0, 0.5 - 20.0, 8.0 - 2.5]);
    }

    /// Edge weights: `D_j = (Σ S_i)⁻¹ S_j` sum to `I` and solve their
    /// defining equation; a direction no side holds is split in `1/m`.
    #[test]
    fn deluxe_edge_weights_sum_to_the_identity() {
        let n = 3;
        let spd = |seed: usize, scale: f64| {
            let b = Mat::from_fn(n, n, |i, j| (((i * 7 + j * 5 + seed) % 11) as f64 - 5.0) / 5.0);
            Mat::from_fn(n, n, |i, j| {
                scale * ((0..n).map(|k| b[(i, k)] * b[(j, k)]).sum::<f64>() + if i == j { 0.3 } else { 0.0 })
            })
        };
        let s = [spd(1, 1.0), spd(2, 1e3), spd(3, 0.1)];
        let refs: Vec<MatRef<'_, f64>> = s.iter().map(|m| m.as_ref()).collect();
        let w = DeluxeBlock::edge_weights(&refs).unwrap();
        let sum = &s[0] + &s[1] + &s[2];
        let mut total = Mat::<f64>::zeros(n, n);
        for (d, sj) in w.iter().zip(&s) {
            let dm = Mat::from_fn(n, n, |i, j| d[j * n + i]);
            assert!((&sum * &dm - sj).norm_max() < 1e-11 * sum.norm_max());
            total += &dm;
        }
        assert!((total - Mat::<f64>::identity(n, n)).norm_max() < 1e-12);
        // No side holds anything: the multiplicity weights.
        let z = Mat::<f64>::zeros(2, 2);
        let w = DeluxeBlock::edge_weights(&[z.as_ref(), z.as_ref(), z.as_ref(), z.as_ref()]).unwrap();
        assert!(w.iter().all(|d| d == &[0.25, 0.0, 0.0, 0.25]), "{w:?}");
        // Sides of different sizes are refused.
        let one = Mat::<f64>::identity(1, 1);
        assert!(DeluxeBlock::edge_weights(&[one.as_ref(), z.as_ref(), z.as_ref()]).is_none());
    }

    /// With separate `D_lo` and `D_hi` the jump is the transpose of the
    /// scaling: `⟨r, z⟩ = ⟨B_D,loᵀ r, y_lo⟩ − ⟨B_D,hiᵀ r, y_hi⟩`, which keeps
    /// the preconditioner symmetric.
    #[test]
    fn deluxe_edge_block_jump_is_the_transpose_of_its_scaling() {
        let d_lo = vec![0.2, 0.1, -0.05, 0.3];
        let d_hi = vec![0.5, -0.2, 0.1, 0.4];
        let mut b = DeluxeBlock::new(vec![0, 2], d_lo.clone(), d_hi.clone());
        let r = [1.0, 9.0, -2.0];
        let (mut lo, mut hi) = ([0.0; 3], [0.0; 3]);
        b.scale(&r, &mut lo, &mut hi);
        // lo = D_hi r_F, hi = D_lo r_F on the block's entries.
        assert!((lo[0] - (0.5 * 1.0 + 0.1 * -2.0)).abs() < 1e-15 && lo[1] == 0.0);
        assert!((hi[2] - (0.1 * 1.0 + 0.3 * -2.0)).abs() < 1e-15);
        let (y_lo, y_hi) = ([0.7, 0.0, -1.3], [2.0, 0.0, 0.4]);
        let idx = [0u32, 1, 2];
        let mut z = [0.0; 3];
        b.jump(&mut z, &y_lo, &idx, &y_hi, &idx);
        let lhs: f64 = r.iter().zip(&z).map(|(a, b)| a * b).sum();
        let rhs: f64 = (0..3).map(|k| lo[k] * y_lo[k] - hi[k] * y_hi[k]).sum();
        assert!((lhs - rhs).abs() < 1e-14, "{lhs} vs {rhs}");
    }

    /// Three subdomains around dofs 4 and 5 (an edge), four around dof 6 (a
    /// vertex); dofs 0..3 lie on faces.
    #[test]
    fn edges_group_the_dofs_of_each_subdomain_set() {
        // Subdomain s holds global dof g at local g (s = 0, 1, 2) and at
        // local g − 3 (s = 3, which holds 3..7).
        let dofs = vec![
            (0..7).collect::<Vec<usize>>(),
            (0..7).collect(),
            (0..7).collect(),
            (3..7).collect(),
        ];
        let m = |g: usize| [2, 2, 2, 2, 3, 3, 4][g];
        let multiplicity: Vec<Vec<u32>> = dofs.iter().map(|d| d.iter().map(|&g| m(g)).collect()).collect();
        let local = |s: usize, g: usize| (if s == 3 { g - 3 } else { g }) as u32;
        let pairs = [
            (0, 1, vec![0, 4, 5, 6]),
            (0, 2, vec![1, 4, 5, 6]),
            (1, 2, vec![2, 4, 5, 6]),
            (0, 3, vec![6]),
            (1, 3, vec![3, 6]),
            (2, 3, vec![6]),
        ];
        let idx: Vec<(Vec<u32>, Vec<u32>)> = pairs
            .iter()
            .map(|(a, b, gs)| {
                (
                    gs.iter().map(|&g| local(*a, g)).collect(),
                    gs.iter().map(|&g| local(*b, g)).collect(),
                )
            })
            .collect();
        let ifaces: Vec<InterfaceEntries<'_>> = pairs
            .iter()
            .zip(&idx)
            .map(|((a, b, _), (l, h))| InterfaceEntries {
                lo: *a,
                hi: *b,
                lo_idx: l,
                hi_idx: h,
            })
            .collect();
        let e = Edges::new(&ifaces, &dofs, &multiplicity);
        assert_eq!(e.edges.len(), 2);
        assert_eq!(e.edges[0].subdomains, vec![0, 1, 2]);
        assert_eq!(e.edges[0].rows, vec![vec![4, 5]; 3]);
        assert_eq!(e.edges[1].subdomains, vec![0, 1, 2, 3]);
        assert_eq!(e.edges[1].rows, vec![vec![6], vec![6], vec![6], vec![3]]);
        // Interface (0, 1) holds the edge at entries 1, 2 and the vertex at 3.
        assert_eq!(e.of_interface[0], vec![(0, vec![1, 2]), (1, vec![3])]);
        assert_eq!(e.of_interface[4], vec![(1, vec![1])]);
        assert_eq!(e.of_subdomain, vec![vec![0, 1], vec![0, 1], vec![0, 1], vec![1]]);
    }
}
