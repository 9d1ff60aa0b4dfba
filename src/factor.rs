//! Cached sparse Cholesky factorization (faer 0.24 low-level API).
//!
//! Symbolic analysis (AMD ordering, supernodal when it pays) and the numeric
//! `LLᵀ` are done once; solves then run on preallocated scratch and make no
//! heap allocation (`Par::Seq`: parallelism goes over subdomains instead).
//!
//! faer's LLT only reports *non-positive* pivots; a singular matrix factored
//! in floating point usually gives a tiny positive pivot instead. We therefore
//! check every pivot against the matrix diagonal and report the first one
//! whose relative size is below [`PIVOT_RATIO`], with its dof in the caller's
//! numbering. Dynamic regularization is never used (faer 0.24.4 stores the
//! regularised supernodal pivots wrongly: solves then leave residuals ~1e10).

use faer::dyn_stack::{MemBuffer, MemStack};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::reborrow::{Reborrow, ReborrowMut};
use faer::sparse::linalg::cholesky::supernodal::{SupernodalLltRef, SymbolicSupernodalCholesky};
use faer::sparse::linalg::cholesky::{
    factorize_symbolic_cholesky, CholeskySymbolicParams, SymbolicCholesky, SymbolicCholeskyRaw, SymmetricOrdering,
};
use faer::sparse::SparseColMat;
use faer::{Conj, MatMut, Par, Side, Spec};
use std::sync::Arc;

/// A pivot `L_jj²` smaller than this fraction of `A_jj` means the matrix is
/// numerically singular (a mechanism). Stiffness contrasts of 1e8 give
/// ratios around 1e-8, so this leaves a wide margin on both sides.
pub const PIVOT_RATIO: f64 = 1e-12;

/// Why a factorization failed.
#[derive(Debug, Clone, PartialEq)]
pub enum FactorError {
    /// Pivot at matrix row `dof` (caller numbering) is non-positive or
    /// negligible: the matrix is singular or indefinite there.
    Pivot { dof: usize, ratio: f64, negative: bool },
    /// Out of memory or another internal failure.
    Internal(String),
}

/// Symmetric positive definite sparse matrix, factored once.
pub struct SparseCholesky {
    n: usize,
    /// Shared by refactorizations of the same pattern.
    symbolic: std::sync::Arc<SymbolicCholesky<usize>>,
    /// Pattern (column pointers, row indices) the analysis was done for.
    pattern: std::sync::Arc<(Vec<usize>, Vec<usize>)>,
    l_values: Vec<f64>,
    scratch: MemBuffer,
    scratch_cols: usize,
    /// The permuted right-hand sides of the solves (`n × scratch_cols`),
    /// then for a supernodal factor the products of its supernodes'
    /// off-diagonal blocks in the forward substitution ([`perm_buffer`]).
    perm_buf: Vec<f64>,
    ordering: OrderingKind,
    /// The numeric factorization's workspace, kept between
    /// refactorizations once [`SparseCholesky::keep_numeric_workspace`]
    /// asks for it (a fresh one costs its page faults at every step).
    numeric_workspace: Option<MemBuffer>,
    keep_numeric_workspace: bool,
    /// Parallelism of the numeric factorization (solves stay sequential).
    par: Par,
    /// Seconds spent in the symbolic analysis (with the AMD ordering unless
    /// an [`EliminationOrder`] was given) and the numeric LLT.
    pub timings: FactorTimings,
}

/// Which fill-reducing ordering a factorization used.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum OrderingKind {
    /// Approximate minimum degree (faer's AMD).
    Amd,
    /// METIS nested dissection.
    NestedDissection,
}

impl OrderingKind {
    /// Short name for reports (`"amd"`, `"nested_dissection"`).
    pub fn name(self) -> &'static str {
        match self {
            OrderingKind::Amd => "amd",
            OrderingKind::NestedDissection => "nested_dissection",
        }
    }
}

/// Which orderings [`EliminationOrder::best_in_reference`] may return
/// (the `[solver] ordering` setting).
pub use crate::settings::OrderingChoice;

/// Where the factorization time went.
#[derive(Debug, Clone, Copy, Default)]
pub struct FactorTimings {
    pub symbolic_s: f64,
    pub numeric_s: f64,
}

impl std::fmt::Debug for SparseCholesky {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("SparseCholesky")
            .field("n", &self.n)
            .field("nnz_l", &self.nnz_l())
            .field("ordering", &self.ordering)
            .finish()
    }
}

pub(crate) fn pattern_of(lower: &SparseColMat<usize, f64>) -> (Vec<usize>, Vec<usize>) {
    let a = lower.symbolic();
    let n = a.ncols();
    let mut col_ptr = Vec::with_capacity(n + 1);
    let mut row_idx = Vec::with_capacity(lower.compute_nnz());
    col_ptr.push(0);
    for j in 0..n {
        row_idx.extend(a.row_idx_of_col(j));
        col_ptr.push(row_idx.len());
    }
    (col_ptr, row_idx)
}

fn same_pattern(lower: &SparseColMat<usize, f64>, pattern: &(Vec<usize>, Vec<usize>)) -> bool {
    let a = lower.symbolic();
    let (cp, ri) = pattern;
    a.ncols() + 1 == cp.len() && (0..a.ncols()).all(|j| a.row_idx_of_col(j).eq(ri[cp[j]..cp[j + 1]].iter().copied()))
}

/// Builds a lower-triangular CSC matrix from triplets, summing duplicates.
/// Groups the `(key, value)` pairs by key (keys below `n`), each group in
/// the order the pairs come: returns the offsets (`n + 1`) and the values,
/// key `k`'s at `values[ptr[k]..ptr[k + 1]]`. A counting sort: `pairs` is
/// called twice, to count and to fill.
pub(crate) fn group_by_key<T: Copy + Default, I: Iterator<Item = (usize, T)>>(
    n: usize,
    pairs: impl Fn() -> I,
) -> (Vec<usize>, Vec<T>) {
    let mut ptr = vec![0usize; n + 1];
    for (k, _) in pairs() {
        ptr[k + 1] += 1;
    }
    for k in 0..n {
        ptr[k + 1] += ptr[k];
    }
    let mut next = ptr.clone();
    let mut values = vec![T::default(); ptr[n]];
    for (k, v) in pairs() {
        values[next[k]] = v;
        next[k] += 1;
    }
    (ptr, values)
}

/// A counting sort by column, then a short sort per column: element
/// assembly produces ~21 triplets per element and a few dozen per column,
/// so this is several times faster than a general triplet conversion.
pub fn lower_csc(n: usize, triplets: &[(usize, usize, f64)]) -> Result<SparseColMat<usize, f64>, FactorError> {
    use faer::sparse::SymbolicSparseColMat;
    if let Some(&(r, c, _)) = triplets.iter().find(|&&(r, c, _)| r >= n || c >= n) {
        return Err(FactorError::Internal(format!(
            "entry ({r}, {c}) outside a {n}x{n} matrix"
        )));
    }
    let (count, mut bucket) = group_by_key(n, || triplets.iter().map(|&(r, c, v)| (c, (r, v))));
    let mut col_ptr = Vec::with_capacity(n + 1);
    let mut row_idx = Vec::with_capacity(triplets.len() / 2);
    let mut values = Vec::with_capacity(triplets.len() / 2);
    col_ptr.push(0);
    for j in 0..n {
        let col = &mut bucket[count[j]..count[j + 1]];
        col.sort_unstable_by_key(|&(r, _)| r);
        for &(r, v) in col.iter() {
            if row_idx.len() > col_ptr[j] && *row_idx.last().expect("non-empty") == r {
                *values.last_mut().expect("non-empty") += v;
            } else {
                row_idx.push(r);
                values.push(v);
            }
        }
        col_ptr.push(row_idx.len());
    }
    let symbolic = SymbolicSparseColMat::new_checked(n, n, col_ptr, None, row_idx);
    Ok(SparseColMat::new(symbolic, values))
}

/// faer's parallelism over every thread of the current rayon pool
/// (`Par::Seq` on one thread): for a factorization that runs alone (the
/// whole structure's and its active-set refactorizations, the coarse
/// problem's), not inside the per-subdomain loops. faer's supernodal LLT
/// splits its work without changing any sum, so the factor has the same
/// bits on any thread count (`tests/cli.rs` compares whole runs at 1 and
/// 2 threads).
pub(crate) fn pool_par() -> Par {
    let t = rayon::current_num_threads().max(1);
    if t > 1 {
        Par::rayon(t)
    } else {
        Par::Seq
    }
}

impl SparseCholesky {
    /// Factors the SPD matrix whose lower triangle is `lower`.
    /// Scratch is sized for solves of up to `max_rhs` columns at once.
    pub fn factor(lower: &SparseColMat<usize, f64>, max_rhs: usize) -> Result<Self, FactorError> {
        Self::factor_checked(lower, max_rhs, PIVOT_RATIO)
    }

    /// [`SparseCholesky::factor`] with a caller-chosen pivot ratio threshold.
    pub fn factor_checked(
        lower: &SparseColMat<usize, f64>,
        max_rhs: usize,
        pivot_ratio: f64,
    ) -> Result<Self, FactorError> {
        Self::factor_ordered(lower, None, max_rhs, pivot_ratio)
    }

    /// [`SparseCholesky::factor_checked`] with a precomputed elimination
    /// order (`None`: AMD or nested dissection, as [`OrderingChoice::Auto`] decides, on
    /// `lower` as numbered, see [`OrderingChoice::Auto`]).
    pub fn factor_ordered(
        lower: &SparseColMat<usize, f64>,
        order: Option<&EliminationOrder>,
        max_rhs: usize,
        pivot_ratio: f64,
    ) -> Result<Self, FactorError> {
        Self::factor_with(lower, order, max_rhs, pivot_ratio, Par::Seq)
    }

    /// [`SparseCholesky::factor_ordered`] with the numeric factorization
    /// (and later [`SparseCholesky::refactor`]s) run with `par` (the whole
    /// structure uses both cores; subdomains stay `Par::Seq` inside and
    /// run in parallel with each other). Solves stay sequential.
    pub fn factor_with(
        lower: &SparseColMat<usize, f64>,
        order: Option<&EliminationOrder>,
        max_rhs: usize,
        pivot_ratio: f64,
        par: Par,
    ) -> Result<Self, FactorError> {
        Self::build(lower, order, OrderingChoice::Auto, max_rhs, pivot_ratio, par)
    }

    /// [`SparseCholesky::factor_with`] in the ordering `choice` asks for,
    /// chosen here on `lower` as numbered.
    pub fn factor_choosing(
        lower: &SparseColMat<usize, f64>,
        choice: OrderingChoice,
        max_rhs: usize,
        pivot_ratio: f64,
        par: Par,
    ) -> Result<Self, FactorError> {
        Self::build(lower, None, choice, max_rhs, pivot_ratio, par)
    }

    /// Factors in `order`, or without one in the ordering `choice` asks for.
    fn build(
        lower: &SparseColMat<usize, f64>,
        order: Option<&EliminationOrder>,
        choice: OrderingChoice,
        max_rhs: usize,
        pivot_ratio: f64,
        par: Par,
    ) -> Result<Self, FactorError> {
        let t = std::time::Instant::now();
        let (symbolic, ordering) = match order {
            Some(o) => (symbolic_cholesky(lower, Some(o))?, o.kind),
            None => {
                let (o, sym) = EliminationOrder::choose(lower, None, choice)?;
                (sym, o.kind)
            }
        };
        let symbolic_s = t.elapsed().as_secs_f64();
        let mut this = Self::unfactored(lower, order, symbolic, ordering, max_rhs, par, symbolic_s)?;
        this.refactor(lower, pivot_ratio)?;
        Ok(this)
    }

    /// Storage for a factor of `lower` with the analysis `symbolic`, not
    /// yet factored.
    fn unfactored(
        lower: &SparseColMat<usize, f64>,
        order: Option<&EliminationOrder>,
        symbolic: Arc<SymbolicCholesky<usize>>,
        ordering: OrderingKind,
        max_rhs: usize,
        par: Par,
        symbolic_s: f64,
    ) -> Result<Self, FactorError> {
        let max_rhs = max_rhs.max(1);
        let req = symbolic.solve_in_place_scratch::<f64>(max_rhs, Par::Seq);
        let scratch = MemBuffer::try_new(req).map_err(|_| FactorError::Internal("out of memory".into()))?;
        Ok(SparseCholesky {
            n: lower.nrows(),
            l_values: vec![0.0f64; symbolic.len_val()],
            pattern: match order.and_then(|o| o.analysis.as_ref()) {
                Some(a) if Arc::ptr_eq(&a.symbolic, &symbolic) => a.pattern.clone(),
                _ => Arc::new(pattern_of(lower)),
            },
            perm_buf: perm_buffer(&symbolic, max_rhs),
            symbolic,
            scratch,
            scratch_cols: max_rhs,
            ordering,
            numeric_workspace: None,
            keep_numeric_workspace: false,
            par,
            timings: FactorTimings {
                symbolic_s,
                numeric_s: 0.0,
            },
        })
    }

    /// The pivots of the singular or indefinite matrix `lower` in `order`
    /// (as [`scan_pivots`]: negligible below `ratio` times the largest
    /// diagonal entry) and, when none is negative, the factor of `lower`
    /// with the negligible ones decoupled, from the same pass.
    ///
    /// The `LDLᵀ` replaces a negligible pivot by [`DECOUPLING_PIVOT`] times
    /// the largest diagonal entry: its column below becomes `1e-120` of its
    /// size and so do its updates of the rows after it, so the factor is
    /// that of `lower` with the rows and columns of those dofs decoupled,
    /// to round-off (the column below is then set to zero). Scaled to
    /// `LLᵀ`, it is what a second factorization of the decoupled matrix
    /// gave before (a singular subdomain's set-up took both). With a
    /// right-hand side zero at the decoupled dofs, the solution there is
    /// `1e-60` of the rest or less. faer's `LLᵀ` cannot do this itself: its
    /// dynamic regularization is wrong in the supernodal kernels (0.24).
    pub(crate) fn factor_decoupling_small_pivots(
        lower: &SparseColMat<usize, f64>,
        order: &EliminationOrder,
        max_rhs: usize,
        ratio: f64,
    ) -> Result<(PivotScan, Option<SparseCholesky>), FactorError> {
        let t = std::time::Instant::now();
        let symbolic = symbolic_cholesky(lower, Some(order))?;
        let symbolic_s = t.elapsed().as_secs_f64();
        let mut this = Self::unfactored(lower, Some(order), symbolic, order.kind, max_rhs, Par::Seq, symbolic_s)?;
        let t = std::time::Instant::now();
        let (scan, delta) = regularised_ldlt(&this.symbolic, &mut this.l_values, lower, ratio, DECOUPLING_PIVOT)?;
        if !scan.negative.is_empty() {
            return Ok((scan, None));
        }
        ldlt_to_llt(&this.symbolic, &mut this.l_values, delta);
        this.timings.numeric_s = t.elapsed().as_secs_f64();
        Ok((scan, Some(this)))
    }

    /// Numeric factorization of a new matrix with *the same pattern* as the
    /// one this factor was built from (explicit zeros included), reusing
    /// the symbolic analysis and the factor's storage. On a pivot failure
    /// the factor is invalid until the next successful refactorization.
    pub fn refactor(&mut self, lower: &SparseColMat<usize, f64>, pivot_ratio: f64) -> Result<(), FactorError> {
        if !same_pattern(lower, &self.pattern) {
            return Err(FactorError::Internal(
                "refactorization with a pattern other than the analysed one".into(),
            ));
        }
        let n = self.n;
        let t = std::time::Instant::now();
        let symbolic = &*self.symbolic;
        let mut fbuf = match self.numeric_workspace.take() {
            Some(b) => b,
            None => {
                let fact_req = symbolic.factorize_numeric_llt_scratch::<f64>(self.par, Spec::default());
                MemBuffer::try_new(fact_req).map_err(|_| FactorError::Internal("out of memory".into()))?
            }
        };
        let res = symbolic.factorize_numeric_llt(
            &mut self.l_values,
            lower.as_ref(),
            Side::Lower,
            LltRegularization::default(),
            self.par,
            MemStack::new(&mut fbuf),
            Spec::default(),
        );
        if self.keep_numeric_workspace {
            self.numeric_workspace = Some(fbuf);
        }
        self.timings.numeric_s = t.elapsed().as_secs_f64();
        let perm_fwd = forward_perm(symbolic);
        if let Err(faer::linalg::cholesky::llt::factor::LltError::NonPositivePivot { index }) = res {
            // faer 0.24.4 reports the failing pivot one-based from its
            // simplicial kernel (`k + 1`) but zero-based from its supernodal
            // one (`j + s_start`); taken as is, a mechanism was named at the
            // dof after the free one (x-free printed "y").
            let p = match symbolic.raw() {
                SymbolicCholeskyRaw::Simplicial(_) => index.saturating_sub(1),
                SymbolicCholeskyRaw::Supernodal(_) => index,
            };
            return Err(FactorError::Pivot {
                dof: perm_fwd[p.min(n - 1)],
                ratio: 0.0,
                negative: true,
            });
        }
        self.check_pivots(lower, &perm_fwd, pivot_ratio)
    }

    /// A second factor sharing this one's symbolic analysis, of a matrix
    /// with the same pattern (see [`SparseCholesky::refactor`]).
    pub fn factor_same_pattern(
        &self,
        lower: &SparseColMat<usize, f64>,
        max_rhs: usize,
        pivot_ratio: f64,
    ) -> Result<SparseCholesky, FactorError> {
        let mut other = self.sharing_symbolic(max_rhs)?;
        other.refactor(lower, pivot_ratio)?;
        Ok(other)
    }

    /// Storage for a factor with this one's symbolic analysis, *not yet
    /// factored*: [`SparseCholesky::refactor`] it before solving.
    pub(crate) fn sharing_symbolic(&self, max_rhs: usize) -> Result<SparseCholesky, FactorError> {
        let max_rhs = max_rhs.max(1);
        let req = self.symbolic.solve_in_place_scratch::<f64>(max_rhs, Par::Seq);
        let scratch = MemBuffer::try_new(req).map_err(|_| FactorError::Internal("out of memory".into()))?;
        Ok(SparseCholesky {
            n: self.n,
            symbolic: self.symbolic.clone(),
            pattern: self.pattern.clone(),
            l_values: vec![0.0; self.l_values.len()],
            scratch,
            scratch_cols: max_rhs,
            perm_buf: perm_buffer(&self.symbolic, max_rhs),
            ordering: self.ordering,
            numeric_workspace: None,
            keep_numeric_workspace: false,
            par: self.par,
            timings: FactorTimings::default(),
        })
    }

    /// Keeps the numeric factorization's workspace between
    /// [`SparseCholesky::refactor`]s of this factor (the direct active
    /// set's steps) instead of allocating it afresh each time.
    pub(crate) fn keep_numeric_workspace(&mut self) {
        self.keep_numeric_workspace = true;
    }

    /// The fill-reducing ordering this factor was computed with.
    pub fn ordering(&self) -> OrderingKind {
        self.ordering
    }

    /// Compares each pivot `L_jj²` with `A_jj` (both in permuted order).
    fn check_pivots(
        &self,
        lower: &SparseColMat<usize, f64>,
        perm_fwd: &[usize],
        pivot_ratio: f64,
    ) -> Result<(), FactorError> {
        let adiag = lower_diagonal(lower);
        let scale = adiag.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let ldiag = l_diagonal(&self.symbolic, &self.l_values);
        for (orig, ratio) in pivot_ratios(&ldiag, &adiag, perm_fwd) {
            // Relative to the row's own diagonal, and absolutely to the
            // largest one: an all-zero row is a mechanism too.
            if !(ratio >= pivot_ratio) || adiag[orig] <= pivot_ratio * scale * 1e-4 {
                return Err(FactorError::Pivot {
                    dof: orig,
                    ratio,
                    negative: false,
                });
            }
        }
        Ok(())
    }

    /// The smallest pivot relative to its diagonal entry, `l_jj² / a_jj`
    /// over the rows of `lower` (the matrix this factor was computed from).
    pub(crate) fn min_pivot_ratio(&self, lower: &SparseColMat<usize, f64>) -> f64 {
        let ldiag = l_diagonal(&self.symbolic, &self.l_values);
        pivot_ratios(&ldiag, &lower_diagonal(lower), &forward_perm(&self.symbolic))
            .map(|(_, ratio)| ratio)
            .fold(f64::INFINITY, f64::min)
    }

    /// Matrix dimension.
    pub fn n(&self) -> usize {
        self.n
    }

    /// Number of stored entries of `L`.
    pub fn nnz_l(&self) -> usize {
        self.l_values.len()
    }

    /// True when faer chose the supernodal kernel.
    pub fn is_supernodal(&self) -> bool {
        matches!(self.symbolic.raw(), SymbolicCholeskyRaw::Supernodal(_))
    }

    /// Solves `A x = rhs` in place for one right-hand side. Allocation free.
    pub fn solve_in_place(&mut self, rhs: &mut [f64]) {
        debug_assert_eq!(rhs.len(), self.n);
        let n = self.n;
        let mat = MatMut::from_column_major_slice_mut(rhs, n, 1);
        self.solve_block(mat);
    }

    /// Solves `A X = B` in place for a block of columns (column major),
    /// in chunks of at most the scratch width. Allocation free.
    ///
    /// The forward substitution skips the columns (simplicial) or
    /// supernodes (supernodal) of `L` where the right-hand sides are zero
    /// (`forward_skipping_zeros`): the set-up's solves have right-hand
    /// sides on one face or the interface only. Otherwise faer's
    /// arithmetic in faer's order: the same bits.
    pub fn solve_block(&mut self, mut rhs: MatMut<'_, f64>) {
        let k = rhs.ncols();
        let mut j = 0;
        while j < k {
            let w = (k - j).min(self.scratch_cols);
            let mut block = rhs.rb_mut().subcols_mut(j, w);
            self.forward(block.rb(), w);
            self.backward_in_perm_buf(w);
            self.unpermute(w, |i, c, v| block[(i, c)] = v);
            j += w;
        }
    }

    /// `L⁻ᵀ` (faer's backward substitution) on the first `w` columns of
    /// `perm_buf`, which hold forward-substituted values in the permuted
    /// order.
    fn backward_in_perm_buf(&mut self, w: usize) {
        let n = self.n;
        if let (1, SymbolicCholeskyRaw::Supernodal(sym)) = (w, self.symbolic.raw()) {
            let (x, tmp) = self.perm_buf.split_at_mut(n * self.scratch_cols);
            supernodal_backward_one(sym, &self.l_values, &mut x[..n], tmp);
            return;
        }
        let xm = MatMut::from_column_major_slice_mut(&mut self.perm_buf[..n * w], n, w);
        match self.symbolic.raw() {
            SymbolicCholeskyRaw::Simplicial(sym) => {
                let l = faer::sparse::SparseColMatRef::<'_, usize, f64>::new(sym.factor(), &self.l_values);
                faer::sparse::linalg::triangular_solve::solve_lower_triangular_transpose_in_place(
                    l,
                    Conj::Yes,
                    xm,
                    Par::Seq,
                );
            }
            SymbolicCholeskyRaw::Supernodal(sym) => {
                let l = SupernodalLltRef::<'_, usize, f64>::new(sym, &self.l_values);
                l.l_transpose_solve_with_conj(Conj::No, xm, Par::Seq, MemStack::new(&mut self.scratch));
            }
        }
    }

    /// Finishes solves begun by [`SparseCholesky::forward_columns`]: `data`
    /// holds `W = L⁻¹ P B` (`k` columns, column-major) and is replaced by
    /// `A⁻¹ B = Pᵀ L⁻ᵀ W`, the same bits as [`SparseCholesky::solve_columns`]
    /// on `B`. No allocation.
    pub fn backward_columns(&mut self, data: &mut [f64], k: usize) {
        let n = self.n;
        self.by_blocks(data, k, |this, block, w| {
            this.perm_buf[..n * w].copy_from_slice(block);
            this.backward_in_perm_buf(w);
            this.unpermute(w, |i, c, v| block[c * n + i] = v);
        });
    }

    /// Hands out the first `w` columns of `perm_buf` in the original row
    /// order: `put(row, column, value)`.
    fn unpermute(&self, w: usize, mut put: impl FnMut(usize, usize, f64)) {
        let n = self.n;
        let perm = self.symbolic.perm().map(|p| p.arrays());
        for (c, xc) in self.perm_buf[..n * w].chunks(n.max(1)).enumerate() {
            match perm {
                Some((_, inv)) => inv.iter().enumerate().for_each(|(i, &v)| put(i, c, xc[v])),
                None => xc.iter().enumerate().for_each(|(i, &v)| put(i, c, v)),
            }
        }
    }

    /// Runs `step` on the column-major `data` (`k` columns) in blocks of at
    /// most `scratch_cols` columns: the block and its width.
    fn by_blocks(&mut self, data: &mut [f64], k: usize, mut step: impl FnMut(&mut Self, &mut [f64], usize)) {
        let n = self.n;
        debug_assert_eq!(data.len(), n * k);
        let mut j = 0;
        while j < k {
            let w = (k - j).min(self.scratch_cols);
            step(self, &mut data[j * n..(j + w) * n], w);
            j += w;
        }
    }

    /// `P B` for a block of `w ≤ scratch_cols` columns into the head of
    /// `perm_buf`, then `L⁻¹` applied to it there, skipping the zero rows
    /// ([`forward_skipping_zeros`], [`supernodal_forward_skipping_zeros`]).
    /// No allocation.
    fn forward(&mut self, block: faer::MatRef<'_, f64>, w: usize) {
        let n = self.n;
        let (x, tmp) = self.perm_buf.split_at_mut(n * self.scratch_cols);
        let x = &mut x[..n * w];
        let perm = self.symbolic.perm().map(|p| p.arrays());
        for c in 0..w {
            let xc = &mut x[c * n..(c + 1) * n];
            let col = block.col(c);
            match (perm, col.try_as_col_major()) {
                (Some((fwd, _)), Some(bc)) => {
                    let bc = bc.as_slice();
                    xc.iter_mut().zip(fwd).for_each(|(d, &f)| *d = bc[f]);
                }
                (None, Some(bc)) => xc.copy_from_slice(bc.as_slice()),
                (Some((fwd, _)), None) => xc.iter_mut().zip(fwd).for_each(|(d, &f)| *d = col[f]),
                (None, None) => xc.iter_mut().enumerate().for_each(|(i, d)| *d = col[i]),
            }
        }
        match self.symbolic.raw() {
            SymbolicCholeskyRaw::Simplicial(sym) => {
                let f = sym.factor();
                forward_skipping_zeros(f.col_ptr(), f.row_idx(), &self.l_values, x, n);
            }
            SymbolicCholeskyRaw::Supernodal(sym) => {
                supernodal_forward_skipping_zeros(sym, &self.l_values, x, n, w, tmp);
            }
        }
    }

    /// Forward substitution alone: replaces a column-major block `B` of
    /// `k` columns (`n * k` values) by `W = L⁻¹ P B`, where `A = Pᵀ L Lᵀ P`.
    /// Then `Bᵀ A⁻¹ B = Wᵀ W`: a Schur complement for half the triangular
    /// work of full solves. No allocation.
    pub fn forward_columns(&mut self, data: &mut [f64], k: usize) {
        let n = self.n;
        self.by_blocks(data, k, |this, block, w| {
            this.forward(faer::MatRef::from_column_major_slice(block, n, w), w);
            block.copy_from_slice(&this.perm_buf[..n * w]);
        });
    }

    /// Columns per block of the batched solves (see [`Self::set_max_rhs`]).
    pub fn max_rhs(&self) -> usize {
        self.scratch_cols
    }

    /// Resizes the solve scratch for blocks of `k` columns (set-up only:
    /// batched solves, then back to the iteration's width).
    pub fn set_max_rhs(&mut self, k: usize) -> Result<(), FactorError> {
        let k = k.max(1);
        if k != self.scratch_cols {
            let req = self.symbolic.solve_in_place_scratch::<f64>(k, Par::Seq);
            self.scratch = MemBuffer::try_new(req).map_err(|_| FactorError::Internal("out of memory".into()))?;
            self.scratch_cols = k;
            self.perm_buf = perm_buffer(&self.symbolic, k);
        }
        Ok(())
    }

    /// A second solver of the same factor (its values copied, its own
    /// scratch), for solves on another thread. Same bits as this one.
    pub fn solver_copy(&self) -> Result<Self, FactorError> {
        let req = self.symbolic.solve_in_place_scratch::<f64>(self.scratch_cols, Par::Seq);
        Ok(SparseCholesky {
            n: self.n,
            symbolic: self.symbolic.clone(),
            pattern: self.pattern.clone(),
            l_values: self.l_values.clone(),
            scratch: MemBuffer::try_new(req).map_err(|_| FactorError::Internal("out of memory".into()))?,
            scratch_cols: self.scratch_cols,
            perm_buf: perm_buffer(&self.symbolic, self.scratch_cols),
            ordering: self.ordering,
            numeric_workspace: None,
            keep_numeric_workspace: false,
            par: self.par,
            timings: self.timings,
        })
    }

    /// Solves for a column-major block stored in a slice of `n * k` values.
    pub fn solve_columns(&mut self, data: &mut [f64], k: usize) {
        let n = self.n;
        self.solve_block(MatMut::from_column_major_slice_mut(data, n, k));
    }

    /// Bytes held by the factor and its scratch (for memory reports).
    pub fn bytes(&self) -> usize {
        self.l_values.len() * 8 + self.n * 16
    }
}

/// A fill-reducing elimination order for one sparsity pattern, computed
/// once and shared by every factorization of matrices with that pattern (a
/// singular subdomain is factored up to four times: its pivot scan, and
/// again where soft suspects are released).
///
/// [`EliminationOrder::amd_in_reference`] makes the order a function of a
/// *reference* numbering of the dofs rather than of the matrix's own: the
/// decomposition lays each subdomain's dofs out interface by interface (so
/// the gather/scatter kernels see long contiguous runs), while its
/// factorization keeps the elimination order AMD gives in increasing global
/// dof order. AMD breaks ties by input order, and which round-off pivots
/// appear at a cut depends on the order, so the layout must not change it.
#[derive(Debug, Clone)]
pub struct EliminationOrder {
    fwd: Vec<usize>,
    inv: Vec<usize>,
    kind: OrderingKind,
    /// Multiple of faer's supernodal test the analyses in this order use:
    /// [`SET_UP_SUPERNODAL_THRESHOLD`] for the subdomain factors of the DD
    /// set-up, faer's own (1) otherwise.
    supernodal: f64,
    /// The symbolic analysis the choice was made with, and the pattern it
    /// is for: every factorization of that pattern in this order (a
    /// singular subdomain's pivot scan and refactorizations) shares it
    /// instead of repeating the analysis.
    analysis: Option<Analysis>,
}

#[derive(Debug, Clone)]
struct Analysis {
    symbolic: Arc<SymbolicCholesky<usize>>,
    pattern: Arc<(Vec<usize>, Vec<usize>)>,
}

/// Nested dissection is tried only from this many rows on: below it AMD's
/// fill is never large in absolute terms and METIS costs more than it saves.
pub const ND_MIN_ROWS: usize = 200;

/// Nested dissection is tried only when AMD gives `nnz(L) ≥ 8 nnz(A)`.
/// CHOLMOD's default (`cholmod_analyze`) tries it from 5 nnz(A) (or 500
/// flops per entry of `L`); on the subdomains of 2D grids (AMD's fill
/// 5–7 nnz(A) with 1.6k–6.6k rows) METIS then lost or won by 1–4 %, and
/// its trial cost more than that saved (the 130² grid with 16 subdomains:
/// cg 2.06 → 1.77 s, its nonsmooth twin 24.1 → 21.4 s, BENCHMARKS.md),
/// while the 3D subdomains it pays on fill 8–15 nnz(A) with AMD.
pub const ND_FILL_RATIO: f64 = 8.0;

/// Nested dissection is chosen only when its `nnz(L)` is at most this
/// fraction of AMD's: a smaller gain does not pay for what the choice
/// costs beyond the factor itself (the Dirichlet interior takes its
/// subdomain's kind, so METIS runs again there).
pub const ND_MARGIN: f64 = 0.95;

impl EliminationOrder {
    /// AMD on the pattern of `lower`, with the rows and columns renumbered
    /// by `rank` first (`rank[i]` is the reference number of row `i`, a
    /// permutation of `0..n`). With the identity it is faer's own AMD.
    pub fn amd_in_reference(lower: &SparseColMat<usize, f64>, rank: &[usize]) -> Result<Self, FactorError> {
        Self::amd(lower, Some(rank))
    }

    /// METIS nested dissection on the pattern of `lower` renumbered by
    /// `rank` (as [`EliminationOrder::amd_in_reference`]).
    pub fn nd_in_reference(lower: &SparseColMat<usize, f64>, rank: &[usize]) -> Result<Self, FactorError> {
        Self::nd(lower, Some(rank))
    }

    /// The ordering `choice` asks for in the reference numbering `rank`;
    /// with [`OrderingChoice::Auto`], AMD unless nested dissection, tried
    /// when AMD fills [`ND_FILL_RATIO`] or more, saves at least
    /// 1 − [`ND_MARGIN`] of its `nnz(L)` (faer's symbolic analysis).
    pub fn best_in_reference(
        lower: &SparseColMat<usize, f64>,
        rank: &[usize],
        choice: OrderingChoice,
    ) -> Result<Self, FactorError> {
        Ok(Self::choose(lower, Some(rank), choice)?.0)
    }

    /// [`EliminationOrder::best_in_reference`] for a subdomain factor of the
    /// DD set-up (`rank = None`: as numbered): its analyses take the
    /// supernodal layout from [`SET_UP_SUPERNODAL_THRESHOLD`] on.
    pub fn for_set_up(
        lower: &SparseColMat<usize, f64>,
        rank: Option<&[usize]>,
        choice: OrderingChoice,
    ) -> Result<Self, FactorError> {
        Ok(Self::choose_with(lower, rank, choice, SET_UP_SUPERNODAL_THRESHOLD)?.0)
    }

    /// The ordering used for the factorization.
    pub fn kind(&self) -> OrderingKind {
        self.kind
    }

    /// [`EliminationOrder::best_in_reference`] (`rank = None`: as
    /// numbered), with the winner's symbolic analysis.
    pub(crate) fn choose(
        lower: &SparseColMat<usize, f64>,
        rank: Option<&[usize]>,
        choice: OrderingChoice,
    ) -> Result<(Self, Arc<SymbolicCholesky<usize>>), FactorError> {
        Self::choose_with(lower, rank, choice, 1.0)
    }

    fn choose_with(
        lower: &SparseColMat<usize, f64>,
        rank: Option<&[usize]>,
        choice: OrderingChoice,
        supernodal: f64,
    ) -> Result<(Self, Arc<SymbolicCholesky<usize>>), FactorError> {
        let n = lower.nrows();
        let with = |o: Self| Self { supernodal, ..o };
        if choice == OrderingChoice::NestedDissection {
            let nd = with(Self::nd(lower, rank)?);
            let sym = symbolic_cholesky(lower, Some(&nd))?;
            return Ok(nd.with_analysis(lower, sym));
        }
        let amd = with(Self::amd(lower, rank)?);
        let amd_sym = symbolic_cholesky(lower, Some(&amd))?;
        let nnz_a = lower.compute_nnz();
        if choice == OrderingChoice::Amd || n < ND_MIN_ROWS || (amd_sym.len_val() as f64) < ND_FILL_RATIO * nnz_a as f64
        {
            return Ok(amd.with_analysis(lower, amd_sym));
        }
        let nd = with(Self::nd(lower, rank)?);
        let nd_sym = symbolic_cholesky(lower, Some(&nd))?;
        if (nd_sym.len_val() as f64) <= ND_MARGIN * amd_sym.len_val() as f64 {
            Ok(nd.with_analysis(lower, nd_sym))
        } else {
            Ok(amd.with_analysis(lower, amd_sym))
        }
    }

    /// Keeps `symbolic` (the analysis of `lower` in this order) for reuse.
    fn with_analysis(
        mut self,
        lower: &SparseColMat<usize, f64>,
        symbolic: Arc<SymbolicCholesky<usize>>,
    ) -> (Self, Arc<SymbolicCholesky<usize>>) {
        self.analysis = Some(Analysis {
            symbolic: symbolic.clone(),
            pattern: Arc::new(pattern_of(lower)),
        });
        (self, symbolic)
    }

    fn check_rank(n: usize, rank: Option<&[usize]>) -> Result<Vec<usize>, FactorError> {
        let Some(rank) = rank else {
            return Ok((0..n).collect());
        };
        if rank.len() != n {
            return Err(FactorError::Internal(format!(
                "reference numbering has {} entries for a {n}x{n} matrix",
                rank.len()
            )));
        }
        let mut member = vec![usize::MAX; n];
        for (i, &r) in rank.iter().enumerate() {
            if r >= n || member[r] != usize::MAX {
                return Err(FactorError::Internal(format!(
                    "reference numbering is not a permutation (rank {r} of row {i})"
                )));
            }
            member[r] = i;
        }
        Ok(member)
    }

    /// Maps an order of reference numbers back to rows.
    fn from_reference(ref_fwd: &[usize], member: &[usize], kind: OrderingKind) -> Self {
        // Step k eliminates reference dof ref_fwd[k], i.e. row member[..].
        let fwd: Vec<usize> = ref_fwd.iter().map(|&r| member[r]).collect();
        let mut inv = vec![0usize; fwd.len()];
        for (k, &i) in fwd.iter().enumerate() {
            inv[i] = k;
        }
        EliminationOrder {
            fwd,
            inv,
            kind,
            supernodal: 1.0,
            analysis: None,
        }
    }

    fn amd(lower: &SparseColMat<usize, f64>, rank: Option<&[usize]>) -> Result<Self, FactorError> {
        use faer::sparse::linalg::amd;
        let n = lower.nrows();
        let member = Self::check_rank(n, rank)?;
        let renumbered;
        let reference = match rank {
            None => lower,
            Some(rank) => {
                let a = lower.as_ref();
                let mut triplets = Vec::with_capacity(a.compute_nnz());
                for j in 0..n {
                    for i in a.row_idx_of_col(j) {
                        let (ri, rj) = (rank[i], rank[j]);
                        triplets.push((ri.max(rj), ri.min(rj), 0.0));
                    }
                }
                renumbered = lower_csc(n, &triplets)?;
                &renumbered
            }
        };
        let mut ref_fwd = vec![0usize; n];
        let mut ref_inv = vec![0usize; n];
        let control = CholeskySymbolicParams::default().amd_params;
        let req = amd::order_maybe_unsorted_scratch::<usize>(n, reference.compute_nnz());
        let mut buf = MemBuffer::try_new(req).map_err(|_| FactorError::Internal("out of memory".into()))?;
        amd::order_maybe_unsorted(
            &mut ref_fwd,
            &mut ref_inv,
            reference.symbolic(),
            control,
            MemStack::new(&mut buf),
        )
        .map_err(|e| FactorError::Internal(format!("AMD ordering: {e:?}")))?;
        Ok(Self::from_reference(&ref_fwd, &member, OrderingKind::Amd))
    }

    fn nd(lower: &SparseColMat<usize, f64>, rank: Option<&[usize]>) -> Result<Self, FactorError> {
        let n = lower.nrows();
        let member = Self::check_rank(n, rank)?;
        let (cp, ri) = pattern_of(lower);
        let graph = crate::ordering::Graph::from_symmetric_pattern(n, &cp, &ri, rank);
        let ref_fwd = crate::ordering::nested_dissection(&graph).map_err(FactorError::Internal)?;
        Ok(Self::from_reference(&ref_fwd, &member, OrderingKind::NestedDissection))
    }

    /// Row eliminated at each step.
    pub fn forward(&self) -> &[usize] {
        &self.fwd
    }
}

/// `nnz(L)` and the ordering a factorization of `lower` in the ordering
/// `choice` asks for would use, from the symbolic analysis alone.
pub fn analyse(lower: &SparseColMat<usize, f64>, choice: OrderingChoice) -> Result<(usize, OrderingKind), FactorError> {
    let (order, symbolic) = EliminationOrder::choose(lower, None, choice)?;
    Ok((symbolic.len_val(), order.kind))
}

/// Multiple of faer's flops-per-entry test (supernodal when the
/// factorization costs more than 40 flops per entry of `L`) from which a
/// subdomain factor of the DD set-up ([`EliminationOrder::for_set_up`]) is
/// supernodal. faer's default (1), which the whole-structure factor keeps,
/// is tuned for one factorization and a few solves; a subdomain's factor
/// serves hundreds of multi-column set-up solves and refactorizations, for
/// which the supernodal kernels are faster from about 8 flops per entry on
/// (the 2D subdomains of 0.4–2k dofs this moves: 65² nonsmooth grid with
/// 16 subdomains 4.3 → 2.3 s, 32² with 4 0.60 → 0.27 s; per-iteration time
/// and the 3D towers unchanged; BENCHMARKS.md).
pub const SET_UP_SUPERNODAL_THRESHOLD: f64 = 0.2;

/// Symbolic analysis of `lower` in `order` (`None`: faer's AMD).
/// Supernodal or simplicial by faer's test, scaled by the order's threshold.
fn symbolic_cholesky(
    lower: &SparseColMat<usize, f64>,
    order: Option<&EliminationOrder>,
) -> Result<Arc<SymbolicCholesky<usize>>, FactorError> {
    if let Some(a) = order.and_then(|o| o.analysis.as_ref()) {
        if same_pattern(lower, &a.pattern) {
            return Ok(a.symbolic.clone());
        }
    }
    let n = lower.nrows();
    let ordering = match order {
        None => SymmetricOrdering::Amd,
        Some(o) if o.fwd.len() == n => SymmetricOrdering::Custom(faer::perm::PermRef::new_checked(&o.fwd, &o.inv, n)),
        Some(o) => {
            return Err(FactorError::Internal(format!(
                "elimination order of length {} for a {n}x{n} matrix",
                o.fwd.len()
            )))
        }
    };
    factorize_symbolic_cholesky(
        lower.symbolic(),
        Side::Lower,
        ordering,
        CholeskySymbolicParams {
            supernodal_flop_ratio_threshold: faer::sparse::linalg::SupernodalThreshold(
                order.map_or(1.0, |o| o.supernodal),
            ),
            ..CholeskySymbolicParams::default()
        },
    )
    .map(Arc::new)
    .map_err(|e| FactorError::Internal(format!("symbolic analysis: {e:?}")))
}

/// [`SparseCholesky::perm_buf`] for `k` columns: the permuted right-hand
/// sides, and for a supernodal factor the products of its supernodes'
/// off-diagonal blocks.
fn perm_buffer(symbolic: &SymbolicCholesky<usize>, k: usize) -> Vec<f64> {
    let k = k.max(1);
    let extra = match symbolic.raw() {
        SymbolicCholeskyRaw::Simplicial(_) => 0,
        SymbolicCholeskyRaw::Supernodal(sym) => {
            (0..sym.n_supernodes())
                .map(|s| sym.supernode(s).pattern().len())
                .max()
                .unwrap_or(0)
                * k
        }
    };
    vec![0.0; symbolic.nrows() * k + extra]
}

/// `X ← L⁻¹ X` for a supernodal factor, on column-major `x` (`n × w`),
/// as faer's `l_solve_with_conj` does it (same operations, same bits) but
/// skipping the supernodes whose rows of `X` are all zero, which leave `X`
/// unchanged: see [`forward_skipping_zeros`]. One column (`w = 1`) takes
/// [`supernode_sweep_one`] instead: faer's answer to round-off, not its
/// bits. `tmp` holds the largest supernode pattern times `w`. No
/// allocation.
fn supernodal_forward_skipping_zeros(
    sym: &SymbolicSupernodalCholesky<usize>,
    values: &[f64],
    x: &mut [f64],
    n: usize,
    w: usize,
    tmp: &mut [f64],
) {
    let l = SupernodalLltRef::<'_, usize, f64>::new(sym, values);
    for s in 0..sym.n_supernodes() {
        let sn = l.supernode(s);
        let ls = sn.val();
        let (size, start) = (ls.ncols(), sn.start());
        if (0..w).all(|c| x[c * n + start..c * n + start + size].iter().all(|&v| v == 0.0)) {
            continue;
        }
        let pattern = sn.pattern();
        let np = pattern.len();
        if w == 1 {
            // One right-hand side (every solve of an iteration): the rows
            // below the diagonal block gathered, and one column sweep over
            // the whole supernode. faer's recursive kernel did the diagonal
            // block at a quarter of the speed of its transposed (backward)
            // one, and its product with the rows below cost a call and a
            // pass over a temporary per supernode.
            let below = &mut tmp[..np];
            gather_rows(x, pattern, below);
            supernode_sweep_one(ls, &mut x[start..start + size], below);
            for (&g, &i) in below.iter().zip(pattern) {
                // SAFETY: as above.
                unsafe { *x.get_unchecked_mut(i) = g };
            }
            continue;
        }
        let (top, bot) = ls.split_at_row(size);
        let mut t = MatMut::from_column_major_slice_mut(&mut tmp[..np * w], np, w);
        {
            let mut xm = MatMut::from_column_major_slice_mut(&mut *x, n, w);
            let mut x_top = xm.rb_mut().subrows_mut(start, size);
            faer::linalg::triangular_solve::solve_lower_triangular_in_place_with_conj(
                top,
                Conj::No,
                x_top.rb_mut(),
                Par::Seq,
            );
            faer::linalg::matmul::matmul_with_conj(
                t.rb_mut(),
                faer::Accum::Replace,
                bot,
                Conj::No,
                x_top.rb(),
                Conj::No,
                1.0,
                Par::Seq,
            );
        }
        if np == 0 {
            continue;
        }
        for (xc, tc) in x.chunks_mut(n).zip(tmp[..np * w].chunks(np)) {
            for (&i, &v) in pattern.iter().zip(tc) {
                // SAFETY: supernode patterns hold row indices below n
                // (faer's symbolic invariant) and xc has n values.
                unsafe { *xc.get_unchecked_mut(i) -= v };
            }
        }
    }
}

/// `x ← L_s⁻¹ x` through one supernode `ls` (column major, `size` columns
/// of `size + below.len()` rows: the diagonal block, then the rows of its
/// pattern): `top` holds the supernode's own rows of `x` and is solved in
/// place, `below` the pattern's rows (gathered) and takes their updates.
/// A column sweep, four columns per pass over the rows: each entry takes
/// its updates in column order, one subtraction at a time (no fused
/// multiply-add, no reassociation), so the AVX2 path gives the bits of
/// the plain one. Not faer's bits; single right-hand sides only.
fn supernode_sweep_one(ls: faer::MatRef<'_, f64>, top: &mut [f64], below: &mut [f64]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just above).
        unsafe { supernode_sweep_avx2(ls, top, below) };
        return;
    }
    supernode_sweep(ls, top, below);
}

/// The sweep of [`supernode_sweep_one`].
#[inline(always)]
fn supernode_sweep(ls: faer::MatRef<'_, f64>, top: &mut [f64], below: &mut [f64]) {
    let size = top.len();
    let col = |j: usize| ls.col(j).try_as_col_major().expect("column-major supernode").as_slice();
    let mut j = 0;
    while j + 4 <= size {
        let (c0, c1, c2, c3) = (col(j), col(j + 1), col(j + 2), col(j + 3));
        // The 4 × 4 diagonal triangle, in the order of a single sweep.
        let a = top[j] / c0[j];
        let b = (top[j + 1] - c0[j + 1] * a) / c1[j + 1];
        let c = ((top[j + 2] - c0[j + 2] * a) - c1[j + 2] * b) / c2[j + 2];
        let d = (((top[j + 3] - c0[j + 3] * a) - c1[j + 3] * b) - c2[j + 3] * c) / c3[j + 3];
        top[j..j + 4].copy_from_slice(&[a, b, c, d]);
        if a != 0.0 || b != 0.0 || c != 0.0 || d != 0.0 {
            let (r, m) = (j + 4, size);
            sweep_rows4(
                &mut top[r..],
                [&c0[r..m], &c1[r..m], &c2[r..m], &c3[r..m]],
                [a, b, c, d],
            );
            sweep_rows4(below, [&c0[m..], &c1[m..], &c2[m..], &c3[m..]], [a, b, c, d]);
        }
        j += 4;
    }
    while j < size {
        let c0 = col(j);
        let a = top[j] / c0[j];
        top[j] = a;
        if a != 0.0 {
            for (v, &l) in top[j + 1..].iter_mut().zip(&c0[j + 1..size]) {
                *v -= l * a;
            }
            for (v, &l) in below.iter_mut().zip(&c0[size..]) {
                *v -= l * a;
            }
        }
        j += 1;
    }
}

/// `v_i ← (((v_i − l0_i a) − l1_i b) − l2_i c) − l3_i d` over the rows.
#[inline(always)]
fn sweep_rows4(v: &mut [f64], l: [&[f64]; 4], x: [f64; 4]) {
    let n = v.len();
    let (l0, l1, l2, l3) = (&l[0][..n], &l[1][..n], &l[2][..n], &l[3][..n]);
    for i in 0..n {
        v[i] = (((v[i] - l0[i] * x[0]) - l1[i] * x[1]) - l2[i] * x[2]) - l3[i] * x[3];
    }
}

/// [`supernode_sweep`] compiled for AVX2 (4 lanes instead of SSE2's 2).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn supernode_sweep_avx2(ls: faer::MatRef<'_, f64>, top: &mut [f64], below: &mut [f64]) {
    supernode_sweep(ls, top, below)
}

/// `x ← L⁻ᵀ x` for a supernodal factor and one right-hand side, supernodes
/// last to first: each gathers its pattern's rows of `x` (already solved)
/// into `tmp` and solves its own rows by [`supernode_back_sweep`]. Faer's
/// answer to round-off, not its bits; its kernel spent more than half of
/// this in a product call and a temporary per supernode. No allocation.
fn supernodal_backward_one(sym: &SymbolicSupernodalCholesky<usize>, values: &[f64], x: &mut [f64], tmp: &mut [f64]) {
    let l = SupernodalLltRef::<'_, usize, f64>::new(sym, values);
    for s in (0..sym.n_supernodes()).rev() {
        let sn = l.supernode(s);
        let ls = sn.val();
        let (size, start) = (ls.ncols(), sn.start());
        let pattern = sn.pattern();
        let below = &mut tmp[..pattern.len()];
        gather_rows(x, pattern, below);
        supernode_back_sweep_one(ls, &mut x[start..start + size], below);
    }
}

/// [`supernode_back_sweep`] on AVX2 where the CPU has it (the same bits).
fn supernode_back_sweep_one(ls: faer::MatRef<'_, f64>, top: &mut [f64], below: &[f64]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU has AVX2 (checked just above).
        unsafe { supernode_back_sweep_avx2(ls, top, below) };
        return;
    }
    supernode_back_sweep(ls, top, below);
}

/// `below[k] = x[pattern[k]]`: a supernode's pattern rows of `x`.
#[inline(always)]
fn gather_rows(x: &[f64], pattern: &[usize], below: &mut [f64]) {
    for (g, &i) in below.iter_mut().zip(pattern) {
        // SAFETY: supernode patterns hold row indices below n (faer's
        // symbolic invariant) and x has n values.
        *g = unsafe { *x.get_unchecked(i) };
    }
}

/// `top ← L_s⁻ᵀ (top − L_belowᵀ below)` through one supernode `ls` (as in
/// [`supernode_sweep_one`]), columns last to first, four per pass: their
/// dot products with the solved rows share each load of those rows, in
/// four lanes each, summed in a fixed order (the AVX2 and plain paths give
/// the same bits); the last `size % 4` columns take [`crate::kernels::dot`]
/// one by one.
#[inline(always)]
fn supernode_back_sweep(ls: faer::MatRef<'_, f64>, top: &mut [f64], below: &[f64]) {
    let size = top.len();
    let col = |j: usize| ls.col(j).try_as_col_major().expect("column-major supernode").as_slice();
    // The last size % 4 columns one by one, then groups of four.
    let mut j = size;
    while j % 4 != 0 {
        j -= 1;
        let c = col(j);
        let d = crate::kernels::dot(&c[j + 1..size], &top[j + 1..]) + crate::kernels::dot(&c[size..], below);
        top[j] = (top[j] - d) / c[j];
    }
    while j > 0 {
        j -= 4;
        let (c0, c1, c2, c3) = (col(j), col(j + 1), col(j + 2), col(j + 3));
        let r = j + 4;
        let a = dots4([&c0[r..size], &c1[r..size], &c2[r..size], &c3[r..size]], &top[r..]);
        let b = dots4([&c0[size..], &c1[size..], &c2[size..], &c3[size..]], below);
        let x3 = (top[j + 3] - (a[3] + b[3])) / c3[j + 3];
        let x2 = (top[j + 2] - (a[2] + b[2]) - c2[j + 3] * x3) / c2[j + 2];
        let x1 = ((top[j + 1] - (a[1] + b[1]) - c1[j + 3] * x3) - c1[j + 2] * x2) / c1[j + 1];
        let x0 = (((top[j] - (a[0] + b[0]) - c0[j + 3] * x3) - c0[j + 2] * x2) - c0[j + 1] * x1) / c0[j];
        top[j..j + 4].copy_from_slice(&[x0, x1, x2, x3]);
    }
}

/// The four dot products `l_d · v`, each in four lanes over blocks of four
/// rows, the lanes summed pairwise and the remaining rows added in order.
#[inline(always)]
fn dots4(l: [&[f64]; 4], v: &[f64]) -> [f64; 4] {
    let n = v.len();
    let (l0, l1, l2, l3) = (&l[0][..n], &l[1][..n], &l[2][..n], &l[3][..n]);
    let mut acc = [[0.0f64; 4]; 4];
    let blocks = n / 4;
    for b in 0..blocks {
        let i = 4 * b;
        for k in 0..4 {
            let vk = v[i + k];
            acc[0][k] += l0[i + k] * vk;
            acc[1][k] += l1[i + k] * vk;
            acc[2][k] += l2[i + k] * vk;
            acc[3][k] += l3[i + k] * vk;
        }
    }
    let mut out = [0.0; 4];
    for (d, (o, a)) in out.iter_mut().zip(&acc).enumerate() {
        let mut t = (a[0] + a[1]) + (a[2] + a[3]);
        for i in 4 * blocks..n {
            t += l[d][i] * v[i];
        }
        *o = t;
    }
    out
}

/// [`supernode_back_sweep`] compiled for AVX2.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn supernode_back_sweep_avx2(ls: faer::MatRef<'_, f64>, top: &mut [f64], below: &[f64]) {
    supernode_back_sweep(ls, top, below)
}

/// `X ← L⁻¹ X` for a simplicial factor in CSC (diagonal first in each
/// column), on column-major `x` with `n` rows, four columns at a time,
/// skipping the columns of `L` where the four are zero. A Schur
/// complement's right-hand sides are the couplings of a face to the
/// interior: sparse, and `L⁻¹ b` is nonzero only on the rows the
/// elimination tree reaches from them, which faer's dense-block kernel does
/// not exploit.
fn forward_skipping_zeros(col_ptr: &[usize], row_idx: &[usize], values: &[f64], x: &mut [f64], n: usize) {
    if n == 0 {
        return;
    }
    for group in x.chunks_mut(4 * n) {
        let g = group.len() / n;
        if g == 4 {
            let (x0, rest) = group.split_at_mut(n);
            let (x1, rest) = rest.split_at_mut(n);
            let (x2, x3) = rest.split_at_mut(n);
            for j in 0..n {
                if x0[j] == 0.0 && x1[j] == 0.0 && x2[j] == 0.0 && x3[j] == 0.0 {
                    continue;
                }
                let (p0, p1) = (col_ptr[j], col_ptr[j + 1]);
                let d = values[p0].recip();
                let (a, b, c, e) = (x0[j] * d, x1[j] * d, x2[j] * d, x3[j] * d);
                x0[j] = a;
                x1[j] = b;
                x2[j] = c;
                x3[j] = e;
                for (&i, &l) in row_idx[p0 + 1..p1].iter().zip(&values[p0 + 1..p1]) {
                    x0[i] -= l * a;
                    x1[i] -= l * b;
                    x2[i] -= l * c;
                    x3[i] -= l * e;
                }
            }
        } else {
            for col in group.chunks_mut(n) {
                for j in 0..n {
                    if col[j] == 0.0 {
                        continue;
                    }
                    let (p0, p1) = (col_ptr[j], col_ptr[j + 1]);
                    let a = col[j] * values[p0].recip();
                    col[j] = a;
                    for (&i, &l) in row_idx[p0 + 1..p1].iter().zip(&values[p0 + 1..p1]) {
                        col[i] -= l * a;
                    }
                }
            }
        }
    }
}

/// Diagonal of the stored factor (of `L` for LLT, of `D` for LDLT), in the
/// permuted order.
fn l_diagonal(symbolic: &SymbolicCholesky<usize>, values: &[f64]) -> Vec<f64> {
    let mut d = vec![0.0; symbolic.nrows()];
    for_each_factor_column(symbolic, |j, diag, _| d[j] = values[diag]);
    d
}

/// Walks the columns of a factor stored in `symbolic`'s layout, in the
/// permuted order: `f(column, index of its diagonal entry, indices of the
/// entries below it)`, indices into the factor's values.
fn for_each_factor_column(
    symbolic: &SymbolicCholesky<usize>,
    mut f: impl FnMut(usize, usize, &mut dyn Iterator<Item = usize>),
) {
    match symbolic.raw() {
        SymbolicCholeskyRaw::Simplicial(s) => {
            let cp = s.col_ptr();
            let ri = s.row_idx();
            for j in 0..symbolic.nrows() {
                if let Some(diag) = (cp[j]..cp[j + 1]).find(|&p| ri[p] == j) {
                    f(j, diag, &mut (cp[j]..cp[j + 1]).filter(|&p| ri[p] != j));
                }
            }
        }
        SymbolicCholeskyRaw::Supernodal(s) => {
            let begin = s.supernode_begin();
            let end = s.supernode_end();
            let cpv = s.col_ptr_for_val();
            for sn in 0..s.n_supernodes() {
                let ncols = end[sn] - begin[sn];
                let nrows = (cpv[sn + 1] - cpv[sn]) / ncols.max(1);
                for j in 0..ncols {
                    let col = cpv[sn] + j * nrows;
                    f(begin[sn] + j, col + j, &mut (col + j + 1..col + nrows));
                }
            }
        }
    }
}

/// Pivots of a symmetric matrix that is singular or indefinite, found by
/// one regularised `LDLᵀ` (faer's dynamic regularization replaces every
/// pivot with `|d| ≤ eps` by `delta`, so the factorization runs to the end).
#[derive(Debug, Clone, Default)]
pub struct PivotScan {
    /// Rows (caller numbering) whose pivot was negligible: fixing dofs.
    pub negligible: Vec<usize>,
    /// Rows whose pivot is clearly negative, with `d / A_jj`.
    pub negative: Vec<(usize, f64)>,
}

/// The factor's forward permutation (position in the factor → row of the
/// matrix as numbered).
fn forward_perm(symbolic: &SymbolicCholesky<usize>) -> Vec<usize> {
    match symbolic.perm() {
        Some(p) => p.arrays().0.to_vec(),
        None => (0..symbolic.nrows()).collect(),
    }
}

/// `(row, l_jj² / a_jj)` of every pivot in factor order: `ldiag` the
/// factor's diagonal, `adiag` the matrix's, `perm_fwd` the factor's
/// forward permutation.
fn pivot_ratios<'a>(
    ldiag: &'a [f64],
    adiag: &'a [f64],
    perm_fwd: &'a [usize],
) -> impl Iterator<Item = (usize, f64)> + 'a {
    ldiag
        .iter()
        .zip(perm_fwd)
        .map(move |(&l, &orig)| (orig, (l * l) / adiag[orig].max(f64::MIN_POSITIVE)))
}

/// Scans the pivots of the matrix whose lower triangle is `lower`, eliminated
/// in `order` (`None`: AMD). A pivot is negligible below `ratio` times the
/// largest diagonal entry.
pub fn scan_pivots(
    lower: &SparseColMat<usize, f64>,
    order: Option<&EliminationOrder>,
    ratio: f64,
) -> Result<PivotScan, FactorError> {
    let symbolic = symbolic_cholesky(lower, order)?;
    let mut values = vec![0.0f64; symbolic.len_val()];
    // A distinctive value, so regularised pivots can be recognised exactly.
    Ok(regularised_ldlt(&symbolic, &mut values, lower, ratio, 1.0 + 1.0 / 1024.0)?.0)
}

/// `LDLᵀ` of `lower` in `symbolic`'s order into `values`, with faer's
/// dynamic regularization: a pivot with `|d| ≤ ratio × max diag` becomes
/// `delta = pivot × max diag` (returned). The scan: the rows whose pivot
/// was so replaced (sorted), and those with a negative pivot.
fn regularised_ldlt(
    symbolic: &SymbolicCholesky<usize>,
    values: &mut [f64],
    lower: &SparseColMat<usize, f64>,
    ratio: f64,
    pivot: f64,
) -> Result<(PivotScan, f64), FactorError> {
    use faer::linalg::cholesky::ldlt::factor::LdltRegularization;
    let adiag = lower_diagonal(lower);
    let scale = adiag.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(f64::MIN_POSITIVE);
    let delta = scale * pivot;
    let req = symbolic.factorize_numeric_ldlt_scratch::<f64>(Par::Seq, Spec::default());
    let mut buf = MemBuffer::try_new(req).map_err(|_| FactorError::Internal("out of memory".into()))?;
    symbolic
        .factorize_numeric_ldlt(
            values,
            lower.as_ref(),
            Side::Lower,
            LdltRegularization {
                dynamic_regularization_signs: None,
                dynamic_regularization_delta: delta,
                dynamic_regularization_epsilon: ratio * scale,
            },
            Par::Seq,
            MemStack::new(&mut buf),
            Spec::default(),
        )
        .map_err(|e| FactorError::Internal(format!("LDLT: {e:?}")))?;
    let fwd = forward_perm(symbolic);
    let mut scan = PivotScan::default();
    for (p, &dp) in l_diagonal(symbolic, values).iter().enumerate() {
        let orig = fwd[p];
        if dp.abs() == delta {
            scan.negligible.push(orig);
        } else if dp < 0.0 {
            scan.negative
                .push((orig, dp / adiag[orig].abs().max(f64::MIN_POSITIVE)));
        }
    }
    scan.negligible.sort_unstable();
    Ok((scan, delta))
}

/// Pivot given to a negligible pivot by
/// `SparseCholesky::factor_decoupling_small_pivots`, as a multiple of the
/// largest diagonal entry: large enough that the row's couplings vanish
/// (`1e-60`), small enough that no product of the factor overflows.
pub const DECOUPLING_PIVOT: f64 = 1e120;

/// `L D Lᵀ` (unit `L`, `D > 0` but for `±decoupled`) stored by faer,
/// turned in place into the `L Lᵀ` factor (`L D^½`). The entries below a
/// pivot of size `decoupled` are set to zero: they are `1e-60` of their
/// size, and exactly what the factor of the decoupled matrix has there.
fn ldlt_to_llt(symbolic: &SymbolicCholesky<usize>, values: &mut [f64], decoupled: f64) {
    for_each_factor_column(symbolic, |_, diag, below| {
        let d = values[diag].abs();
        let scale = if d == decoupled { 0.0 } else { d.sqrt() };
        values[diag] = d.sqrt();
        below.for_each(|p| values[p] *= scale);
    });
}

/// Diagonal of the matrix whose lower triangle (CSC) is `lower`
/// (duplicate entries summed).
pub fn lower_diagonal(lower: &SparseColMat<usize, f64>) -> Vec<f64> {
    let a = lower.as_ref();
    let mut d = vec![0.0; a.ncols()];
    for (j, dj) in d.iter_mut().enumerate() {
        for (i, v) in a.row_idx_of_col(j).zip(a.val_of_col(j)) {
            if i == j {
                *dj += *v;
            }
        }
    }
    d
}

/// `y = A x` for the symmetric matrix whose lower triangle is `lower`.
///
/// Each column is read once: its off-diagonal entries scatter `A_ij x_j`
/// into `y_i` and gather `A_ij x_i` into a register for `y_j`, so `y_j` is
/// not a memory dependency chain (the preconditioner's `K_bb x` and the
/// kernel tests run this).
pub fn sym_matvec(lower: &SparseColMat<usize, f64>, x: &[f64], y: &mut [f64]) {
    let a = lower.as_ref();
    let n = a.ncols();
    assert!(
        x.len() >= n && y.len() >= n,
        "sym_matvec: vectors shorter than the matrix"
    );
    y[..n].iter_mut().for_each(|v| *v = 0.0);
    for j in 0..n {
        let xj = x[j];
        let mut acc = 0.0;
        for (&i, &v) in a.row_idx_of_col_raw(j).iter().zip(a.val_of_col(j)) {
            if i == j {
                acc += v * xj;
                continue;
            }
            // SAFETY: a SparseColMat's row indices are below nrows() = n
            // (faer's invariant), and x, y hold at least n values.
            unsafe {
                *y.get_unchecked_mut(i) += v * xj;
                acc += v * *x.get_unchecked(i);
            }
        }
        y[j] += acc;
    }
}

/// `Y = A X` for `k` columns stored column-major (`n × k`) in `x` and `y`,
/// four columns per pass over the matrix (the set-up's kernel tests apply
/// the stiffness to tens of columns at once).
pub fn sym_matmat(lower: &SparseColMat<usize, f64>, x: &[f64], y: &mut [f64], k: usize) {
    let a = lower.as_ref();
    let n = a.ncols();
    assert!(
        x.len() >= n * k && y.len() >= n * k,
        "sym_matmat: blocks shorter than n × k"
    );
    let mut c = 0;
    while c + 4 <= k {
        let xs = &x[c * n..(c + 4) * n];
        let (x0, rest) = xs.split_at(n);
        let (x1, rest) = rest.split_at(n);
        let (x2, x3) = rest.split_at(n);
        let ys = &mut y[c * n..(c + 4) * n];
        ys.iter_mut().for_each(|v| *v = 0.0);
        let (y0, rest) = ys.split_at_mut(n);
        let (y1, rest) = rest.split_at_mut(n);
        let (y2, y3) = rest.split_at_mut(n);
        for j in 0..n {
            let (xj0, xj1, xj2, xj3) = (x0[j], x1[j], x2[j], x3[j]);
            let (mut a0, mut a1, mut a2, mut a3) = (0.0, 0.0, 0.0, 0.0);
            for (&i, &v) in a.row_idx_of_col_raw(j).iter().zip(a.val_of_col(j)) {
                if i == j {
                    a0 += v * xj0;
                    a1 += v * xj1;
                    a2 += v * xj2;
                    a3 += v * xj3;
                    continue;
                }
                // SAFETY: row indices are below n (faer's invariant) and
                // every column slice holds n values.
                unsafe {
                    *y0.get_unchecked_mut(i) += v * xj0;
                    *y1.get_unchecked_mut(i) += v * xj1;
                    *y2.get_unchecked_mut(i) += v * xj2;
                    *y3.get_unchecked_mut(i) += v * xj3;
                    a0 += v * *x0.get_unchecked(i);
                    a1 += v * *x1.get_unchecked(i);
                    a2 += v * *x2.get_unchecked(i);
                    a3 += v * *x3.get_unchecked(i);
                }
            }
            y0[j] += a0;
            y1[j] += a1;
            y2[j] += a2;
            y3[j] += a3;
        }
        c += 4;
    }
    for c in c..k {
        sym_matvec(lower, &x[c * n..(c + 1) * n], &mut y[c * n..(c + 1) * n]);
    }
}

/// Lower-triangle triplets of a lattice Laplacian (`m × m × depth` points,
/// 6.5 on the diagonal, −1 to each lattice neighbour): SPD; in 3D enough
/// fill for faer to go supernodal. Point `(i, j, l)` is row `(l m + i) m + j`.
#[cfg(test)]
pub(crate) fn lattice_triplets(m: usize, depth: usize) -> Vec<(usize, usize, f64)> {
    let idx = |i: usize, j: usize, l: usize| (l * m + i) * m + j;
    let mut trip = Vec::new();
    for l in 0..depth {
        for i in 0..m {
            for j in 0..m {
                trip.push((idx(i, j, l), idx(i, j, l), 6.5));
                for (di, dj, dl) in [(1, 0, 0), (0, 1, 0), (0, 0, 1)] {
                    if i + di < m && j + dj < m && l + dl < depth {
                        trip.push((idx(i + di, j + dj, l + dl), idx(i, j, l), -1.0));
                    }
                }
            }
        }
    }
    trip
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::sparse::linalg::cholesky::LltRef;

    fn tridiagonal(n: usize, coupled: bool) -> SparseColMat<usize, f64> {
        let mut trip: Vec<(usize, usize, f64)> = (0..n).map(|i| (i, i, 4.0)).collect();
        if coupled {
            trip.extend((1..n).map(|i| (i, i - 1, -1.0)));
        }
        lower_csc(n, &trip).unwrap()
    }

    /// Two disconnected copies of a lattice's graph Laplacian: singular,
    /// with a kernel of dimension two (a constant on each copy).
    fn floating_pair(m: usize, depth: usize) -> SparseColMat<usize, f64> {
        let half = m * m * depth;
        let mut trip = Vec::new();
        for copy in 0..2 {
            let mut degree = vec![0.0; half];
            for (i, j, v) in lattice_triplets(m, depth) {
                if i != j {
                    trip.push((i + copy * half, j + copy * half, v));
                    degree[i] -= v;
                    degree[j] -= v;
                }
            }
            trip.extend(
                degree
                    .iter()
                    .enumerate()
                    .map(|(i, &d)| (i + copy * half, i + copy * half, d)),
            );
        }
        lower_csc(2 * half, &trip).unwrap()
    }

    fn norm(v: &[f64]) -> f64 {
        crate::kernels::norm2(v).sqrt()
    }

    /// The pivot scan's own factor is the factor of the matrix with its
    /// negligible pivots decoupled (what a second factorization gave),
    /// in both layouts, and a generalised inverse.
    #[test]
    fn decoupling_scan_is_the_factor_of_the_decoupled_matrix() {
        for (m, depth, supernodal) in [(3, 2, false), (12, 12, true)] {
            let a = floating_pair(m, depth);
            let n = a.nrows();
            let order = EliminationOrder::for_set_up(&a, None, OrderingChoice::Auto).unwrap();
            let (scan, ours) = SparseCholesky::factor_decoupling_small_pivots(&a, &order, 1, 1e-6).unwrap();
            assert_eq!(scan.negligible.len(), 2, "one fixing dof per copy");
            assert!(scan.negative.is_empty());
            let mut ours = ours.expect("no negative pivot");
            assert_eq!(ours.is_supernodal(), supernodal);
            let fixing = &scan.negligible;
            let scale = lower_diagonal(&a).iter().fold(0.0f64, |m, &v| m.max(v));
            let mut trip = Vec::new();
            for j in 0..n {
                for (i, &v) in a.as_ref().row_idx_of_col(j).zip(a.as_ref().val_of_col(j)) {
                    let touches = fixing.contains(&i) || fixing.contains(&j);
                    trip.push((
                        i,
                        j,
                        if !touches {
                            v
                        } else if i == j {
                            scale
                        } else {
                            0.0
                        },
                    ));
                }
            }
            let decoupled = lower_csc(n, &trip).unwrap();
            let mut before = SparseCholesky::factor_ordered(&decoupled, Some(&order), 1, PIVOT_RATIO).unwrap();
            // Balanced on each copy (orthogonal to the kernel); solved with
            // its entries at F zeroed, as the subdomain does.
            let mut b: Vec<f64> = (0..n).map(|i| ((i * 7919) % 13) as f64 - 6.0).collect();
            for copy in b.chunks_mut(n / 2) {
                let mean = copy.iter().sum::<f64>() / copy.len() as f64;
                copy.iter_mut().for_each(|v| *v -= mean);
            }
            let mut x = b.clone();
            for f in fixing {
                x[*f] = 0.0;
            }
            let mut y = x.clone();
            ours.solve_in_place(&mut x);
            before.solve_in_place(&mut y);
            let diff: Vec<f64> = x.iter().zip(&y).map(|(p, q)| p - q).collect();
            assert!(norm(&diff) <= 1e-12 * norm(&y), "{:e}", norm(&diff) / norm(&y));
            for f in fixing {
                assert!(x[*f].abs() <= 1e-50 * norm(&y), "x_F = {:e}", x[*f]);
            }
            // x solves A x = b (b is orthogonal to the kernel).
            let mut ax = vec![0.0; n];
            sym_matvec(&a, &x, &mut ax);
            let res: Vec<f64> = ax.iter().zip(&b).map(|(p, q)| p - q).collect();
            assert!(norm(&res) <= 1e-10 * norm(&b));
        }
    }

    /// A single right-hand side takes the supernode sweeps (forward and
    /// transposed): faer's solution to round-off, and the same bits on the
    /// AVX2 path as on the plain one.
    #[test]
    fn one_column_solve_matches_faer() {
        let a = lower_csc(14 * 14 * 14, &lattice_triplets(14, 14)).unwrap();
        let n = a.nrows();
        let mut chol = SparseCholesky::factor_ordered(&a, None, 1, PIVOT_RATIO).unwrap();
        assert!(chol.is_supernodal());
        let b: Vec<f64> = (0..n).map(|i| ((i * 7919) % 13) as f64 - 6.0).collect();
        let mut ours = b.clone();
        chol.solve_in_place(&mut ours);
        let mut faers = b.clone();
        let llt = LltRef::<'_, usize, f64>::new(&chol.symbolic, &chol.l_values);
        let mut buf = MemBuffer::new(chol.symbolic.solve_in_place_scratch::<f64>(1, Par::Seq));
        llt.solve_in_place_with_conj(
            Conj::No,
            MatMut::from_column_major_slice_mut(&mut faers, n, 1),
            Par::Seq,
            MemStack::new(&mut buf),
        );
        let size = faers.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let diff = ours.iter().zip(&faers).fold(0.0f64, |m, (x, y)| m.max((x - y).abs()));
        assert!(diff <= 1e-13 * size, "{diff:e} against {size:e}");
        // The sweep on a dense supernode (a 37-column diagonal block over
        // 11 rows below it, so both the four-column passes and the last
        // single columns run), both paths: the same bits, and the solution
        // of the block with the rows below updated as a product would.
        let (m, below_rows) = (37, 11);
        let t = faer::Mat::<f64>::from_fn(m + below_rows, m, |i, j| {
            if i == j {
                2.0 + i as f64
            } else if i > j {
                1.0 / (1 + i + j) as f64
            } else {
                0.0
            }
        });
        let top0: Vec<f64> = (0..m).map(|i| (i as f64).sin()).collect();
        let below0: Vec<f64> = (0..below_rows).map(|i| (i as f64).cos()).collect();
        let (mut top, mut below) = (top0.clone(), below0.clone());
        supernode_sweep(t.as_ref(), &mut top, &mut below);
        let diag = t.as_ref().subrows(0, m);
        let back: Vec<f64> = (0..m)
            .map(|i| (0..=i).map(|j| diag[(i, j)] * top[j]).sum::<f64>())
            .collect();
        let err = back.iter().zip(&top0).fold(0.0f64, |e, (x, y)| e.max((x - y).abs()));
        assert!(err < 1e-14, "triangle: {err:e}");
        for r in 0..below_rows {
            let want = below0[r] - (0..m).map(|j| t[(m + r, j)] * top[j]).sum::<f64>();
            assert!(
                (below[r] - want).abs() < 1e-14,
                "row {r} below: {} against {want}",
                below[r]
            );
        }
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            let (mut wide_top, mut wide_below) = (top0.clone(), below0.clone());
            // SAFETY: AVX2 checked.
            unsafe { supernode_sweep_avx2(t.as_ref(), &mut wide_top, &mut wide_below) };
            let same = |a: &[f64], b: &[f64]| a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits());
            assert!(same(&top, &wide_top) && same(&below, &wide_below));
        }
        // The transposed sweep: `top ← T⁻ᵀ (top − Bᵀ below)` for the same
        // block, against the dense product, both paths the same bits.
        let mut back = top0.clone();
        supernode_back_sweep(t.as_ref(), &mut back, &below0);
        for j in 0..m {
            let lhs: f64 = (j..m).map(|i| t[(i, j)] * back[i]).sum::<f64>()
                + (0..below_rows).map(|r| t[(m + r, j)] * below0[r]).sum::<f64>();
            assert!((lhs - top0[j]).abs() < 1e-13, "column {j}: {lhs} against {}", top0[j]);
        }
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            let mut wide = top0.clone();
            // SAFETY: AVX2 checked.
            unsafe { supernode_back_sweep_avx2(t.as_ref(), &mut wide, &below0) };
            assert!(back.iter().zip(&wide).all(|(x, y)| x.to_bits() == y.to_bits()));
        }
    }

    /// The analysis made while choosing the order is the one the
    /// factorizations of that pattern use (no second analysis); another
    /// pattern with the same order gets its own.
    #[test]
    fn factorizations_share_the_analysis_of_their_order() {
        let k = tridiagonal(300, true);
        let (order, sym) = EliminationOrder::choose(&k, None, OrderingChoice::Auto).unwrap();
        let a = SparseCholesky::factor_ordered(&k, Some(&order), 1, PIVOT_RATIO).unwrap();
        let b = SparseCholesky::factor_ordered(&k, Some(&order), 1, PIVOT_RATIO).unwrap();
        assert!(Arc::ptr_eq(&a.symbolic, &sym) && Arc::ptr_eq(&b.symbolic, &sym));
        assert!(Arc::ptr_eq(&a.pattern, &b.pattern));
        let d = tridiagonal(300, false);
        let mut c = SparseCholesky::factor_ordered(&d, Some(&order), 1, PIVOT_RATIO).unwrap();
        assert!(!Arc::ptr_eq(&c.symbolic, &sym));
        let mut x = vec![4.0; 300];
        c.solve_in_place(&mut x);
        assert!(x.iter().all(|&v| (v - 1.0).abs() < 1e-14));
    }

    /// `Wᵀ W` from the forward substitution alone equals `Bᵀ A⁻¹ B` from
    /// full solves, on a simplicial (tridiagonal) and a supernodal (dense
    /// block) factor, with a block wider than the solve scratch.
    #[test]
    fn forward_substitution_gives_the_schur_product() {
        let dense = |m: usize| {
            let mut trip = Vec::new();
            for j in 0..m {
                trip.push((j, j, 2.0 * m as f64));
                for i in j + 1..m {
                    trip.push((i, j, 1.0 / (1 + i + j) as f64));
                }
            }
            lower_csc(m, &trip).unwrap()
        };
        for (a, want_supernodal) in [(tridiagonal(300, true), false), (dense(120), true)] {
            let n = a.nrows();
            let mut chol = SparseCholesky::factor_ordered(&a, None, 1, PIVOT_RATIO).unwrap();
            assert_eq!(chol.is_supernodal(), want_supernodal);
            chol.set_max_rhs(3).unwrap();
            let k = 7;
            let b: Vec<f64> = (0..n * k).map(|i| ((i * 37 % 101) as f64 - 50.0) / 17.0).collect();
            let mut x = b.clone();
            chol.solve_columns(&mut x, k);
            let mut w = b.clone();
            chol.forward_columns(&mut w, k);
            for p in 0..k {
                for q in 0..k {
                    let full: f64 = (0..n).map(|i| b[p * n + i] * x[q * n + i]).sum();
                    let fwd: f64 = (0..n).map(|i| w[p * n + i] * w[q * n + i]).sum();
                    assert!(
                        (full - fwd).abs() <= 1e-12 * full.abs().max(1.0),
                        "{p},{q}: {full} vs {fwd}"
                    );
                }
            }
        }
    }

    /// The solves that skip zero right-hand-side rows give faer's bits, on
    /// a simplicial and a supernodal factor, with right-hand sides that
    /// are zero but for a few rows (as on the interface) and dense ones,
    /// in blocks wider than 4 and than the scratch; an empty matrix too.
    #[test]
    fn skipping_zeros_gives_faers_bits() {
        let lattice = |m: usize, dims: usize| {
            let depth = if dims == 3 { m } else { 1 };
            lower_csc(m * m * depth, &lattice_triplets(m, depth)).unwrap()
        };
        for (a, supernodal) in [(lattice(8, 2), false), (lattice(14, 3), true)] {
            let n = a.nrows();
            let mut chol = SparseCholesky::factor_ordered(&a, None, 1, PIVOT_RATIO).unwrap();
            assert_eq!(chol.is_supernodal(), supernodal);
            chol.set_max_rhs(6).unwrap();
            let k = 9;
            let mut b = vec![0.0; n * k];
            for c in 0..k {
                for r in [c, n / 2 + c, n - 1 - c] {
                    b[c * n + r] = 1.0 + c as f64;
                }
            }
            b[8 * n..]
                .iter_mut()
                .enumerate()
                .for_each(|(i, v)| *v = (i % 7) as f64 - 3.0);
            let mut ours = b.clone();
            chol.solve_columns(&mut ours, k);
            // faer's solve in the same blocks of columns (its dense kernels
            // round differently with the block width).
            let mut faers = b.clone();
            let llt = LltRef::<'_, usize, f64>::new(&chol.symbolic, &chol.l_values);
            let req = chol.symbolic.solve_in_place_scratch::<f64>(6, Par::Seq);
            let mut buf = MemBuffer::new(req);
            for (c0, w) in [(0, 6), (6, 3)] {
                llt.solve_in_place_with_conj(
                    Conj::No,
                    MatMut::from_column_major_slice_mut(&mut faers[c0 * n..(c0 + w) * n], n, w),
                    Par::Seq,
                    MemStack::new(&mut buf),
                );
            }
            assert!(
                ours.iter().zip(&faers).all(|(x, y)| x.to_bits() == y.to_bits()),
                "supernodal {supernodal}"
            );
            // Forward, then backward on the kept result: the same bits.
            let mut split = b.clone();
            chol.forward_columns(&mut split, k);
            chol.backward_columns(&mut split, k);
            assert!(
                split.iter().zip(&ours).all(|(x, y)| x.to_bits() == y.to_bits()),
                "split solve, supernodal {supernodal}"
            );
            // The symmetric products against a dense product.
            let dense = faer::Mat::from_fn(n, n, |i, j| {
                let (r, c) = (i.max(j), i.min(j));
                a.as_ref()
                    .row_idx_of_col(c)
                    .zip(a.as_ref().val_of_col(c))
                    .filter(|&(row, _)| row == r)
                    .map(|(_, &v)| v)
                    .sum::<f64>()
            });
            let mut y = vec![0.0; n * k];
            sym_matmat(&a, &b, &mut y, k);
            let mut yv = vec![0.0; n];
            for c in 0..k {
                sym_matvec(&a, &b[c * n..(c + 1) * n], &mut yv);
                for i in 0..n {
                    let want: f64 = (0..n).map(|j| dense[(i, j)] * b[c * n + j]).sum();
                    assert!(
                        (y[c * n + i] - want).abs() <= 1e-12 * want.abs().max(1.0),
                        "sym_matmat ({i}, {c})"
                    );
                    assert!(
                        (yv[i] - want).abs() <= 1e-12 * want.abs().max(1.0),
                        "sym_matvec ({i}, {c})"
                    );
                }
            }
        }
        let empty = lower_csc(0, &[]).unwrap();
        let mut chol = SparseCholesky::factor_ordered(&empty, None, 4, PIVOT_RATIO).unwrap();
        chol.solve_columns(&mut [], 3);
        chol.forward_columns(&mut [], 3);
    }

    /// A dense SPD block of order `m` (diagonally dominant) with one extra
    /// row `zero` that has an explicit zero diagonal and no coupling: the
    /// factorization must fail at that row, whichever kernel faer picks.
    fn block_with_zero_row(m: usize, zero: usize) -> (SparseColMat<usize, f64>, SparseColMat<usize, f64>) {
        let n = m + 1;
        let idx = |i: usize| if i >= zero { i + 1 } else { i };
        let mut trip = Vec::new();
        for j in 0..m {
            trip.push((idx(j), idx(j), 2.0 * m as f64));
            for i in j + 1..m {
                trip.push((idx(i), idx(j), 1.0));
            }
        }
        let mut regular = trip.clone();
        trip.push((zero, zero, 0.0));
        regular.push((zero, zero, 1.0));
        (lower_csc(n, &trip).unwrap(), lower_csc(n, &regular).unwrap())
    }

    #[test]
    fn non_positive_pivot_names_its_own_row_in_both_kernels() {
        for (m, supernodal) in [(5, false), (400, true)] {
            for zero in [0, 2, m / 2, m] {
                let (singular, regular) = block_with_zero_row(m, zero);
                // The same pattern factored without the zero shows which
                // kernel faer chose (the failure path cannot tell).
                let ok = SparseCholesky::factor(&regular, 1).unwrap();
                assert_eq!(ok.is_supernodal(), supernodal, "m = {m}");
                match SparseCholesky::factor(&singular, 1) {
                    Err(FactorError::Pivot { dof, .. }) => assert_eq!(dof, zero, "m = {m}"),
                    other => panic!("m = {m}, zero row {zero}: expected a pivot failure, got {other:?}"),
                }
            }
        }
    }
}
