//! The direct reference solver: one sparse Cholesky of the whole truss
//! stiffness `K`, and an exact primal–dual active set on the cable slacks.
//!
//! `K` never changes when cables go slack (docs/design.md §1), so the active set
//! works on the Schur complement of the slack set and keeps the single
//! factorization: with `S` the slack set and `μ = K_S^{1/2} λ_S`,
//!
//! ```text
//! (I − K_S^{1/2} H_Sᵀ K⁻¹ H_S K_S^{1/2}) μ = −K_S^{1/2} g_S,   g = Hᵀ K⁻¹ b + e0
//! ```
//!
//! whose matrix has its spectrum in `[0, 1]`: a zero pivot there means the
//! structure becomes a mechanism once those cables are slack. Columns
//! `K⁻¹ h_c` are computed in batches only for cables that ever enter `S`,
//! and their Schur entries are cached as `S` changes.
//!
//! When the slack set grows beyond `SCHUR_MAX` cables, the dense Schur
//! complement costs more than a factorization, and each step instead
//! factors `K` without the slack cables' axial stiffness (a mechanism
//! there is reported); their geometric stiffness stays, as in `K`.
//!
//! The set update is the primal–dual active set (semismooth Newton) rule;
//! if it revisits a set, it switches to Murty's least-index rule, which
//! terminates for the positive definite Schur matrices met here.

use crate::error::{Error, Result};
use crate::factor::{lower_csc, FactorError, OrderingChoice, OrderingKind, SparseCholesky, PIVOT_RATIO};
use crate::method::on_workers;
use crate::model::{Model, StiffnessScatter};
use faer::linalg::solvers::Solve;
use faer::sparse::SparseColMat;
use faer::Mat;
use std::collections::HashSet;

/// Width of the column blocks solved at once when building Schur columns.
const BATCH: usize = 32;

/// Largest slack set handled through the dense Schur complement. Beyond it,
/// `|S|` solves and an `O(|S|³)` dense factorization per active-set step
/// cost far more than one factorization of `K` without the slack cables.
const SCHUR_MAX: usize = 400;

/// Stiffness fraction kept by slack cables in a step whose slack set alone
/// would be a mechanism.
const SOFT: f64 = 1e-6;

/// Iterative refinement of a direct solve: at most this many corrections,
/// fewer once a correction is below `REFINED` times the displacement.
const MAX_REFINEMENTS: usize = 3;
const REFINED: f64 = 1e-14;

/// ...or once the residual is below this fraction of the element forces it
/// sums (before solving the next correction).
const RESIDUAL_DONE: f64 = 1e-15;

/// The equilibrium found by a solver, in free-dof numbering.
#[derive(Debug, Clone, PartialEq)]
pub struct Equilibrium {
    /// Displacements on free dofs.
    pub u: Vec<f64>,
    /// Cable slacks `λ ≥ 0`, indexed like `Model::cables`.
    pub lambda: Vec<f64>,
    /// Active-set iterations (direct) or solver iterations (DD).
    pub iterations: usize,
    /// Element elongations summed over the iterative refinement's
    /// corrections (more accurate than those of `u`, which rounds each
    /// correction to `ε ‖u‖`); `None` where not refined.
    pub elongations: Option<Vec<f64>>,
}

/// Timings and sizes of the direct factorization, for reports.
#[derive(Debug, Clone, Default)]
pub struct DirectStats {
    pub n: usize,
    pub nnz_k: usize,
    pub nnz_l: usize,
    pub assembly_s: f64,
    /// Symbolic analysis (AMD ordering, elimination tree, supernodes).
    pub ordering_s: f64,
    /// Numeric factorization.
    pub factor_s: f64,
    pub supernodal: bool,
    /// Fill-reducing ordering chosen (smaller predicted `nnz(L)`).
    pub ordering: Option<OrderingKind>,
    /// Threads of the numeric factorization.
    pub threads: usize,
    /// Iterative refinement: corrections solved, and their time (residuals
    /// and substitutions), over every solve so far.
    pub refinements: usize,
    pub refinement_s: f64,
}

/// Maps a factorization pivot failure on the whole structure to a message
/// naming the node and component.
pub(crate) fn mechanism_error(model: &Model, dof: usize, what: &str) -> Error {
    let (node, c) = model.dof_owner(dof);
    let comp = ["x", "y", "z"][c];
    Error::Mechanism(format!(
        "{what} has no stiffness at node {node} component {comp}: it is not supported well enough or is a mechanism"
    ))
}

/// The lower triangle of the whole structure's `K` (every element, CSC).
pub(crate) fn assemble(model: &Model) -> Result<SparseColMat<usize, f64>> {
    let all: Vec<usize> = (0..model.elements.len()).collect();
    let trip = model.stiffness_triplets(&all, Some);
    lower_csc(model.n_free, &trip).map_err(|e| Error::Numerical(format!("{e:?}")))
}

/// Factorization of the whole structure plus the cable active-set cache.
pub struct DirectSolver {
    chol: SparseCholesky,
    stats: DirectStats,
    /// Cables that have entered a slack set so far (cache order).
    cached: Vec<usize>,
    /// Position of each cable in `cached`, or `usize::MAX`.
    cache_pos: Vec<usize>,
    /// Dense symmetric `K_c^{1/2} h_cᵀ K⁻¹ h_d K_d^{1/2}` over `cached`.
    schur: Mat<f64>,
    schur_max: usize,
    /// Factor of `K` with the slack cables removed or softened, sharing the
    /// symbolic analysis of `chol`: the assembly keeps every element's
    /// entries (zero for a removed cable), so the pattern never changes
    /// and each active-set step is one numeric refactorization.
    without_slack: Option<SparseCholesky>,
    /// The matrix `without_slack` factors (the pattern of `K`, values
    /// rewritten in place at each step) and where each element's entries
    /// go in it: assembling from triplets at each step spent a third of a
    /// 130² grid's run on the triplets, their sort and the page faults of
    /// their fresh buffers.
    slack_stiffness: Option<(SparseColMat<usize, f64>, StiffnessScatter)>,
    /// Numeric refactorizations done by the active set (for tests/reports).
    refactorizations: usize,
}

impl DirectSolver {
    /// Assembles `K` and factors it once ([`OrderingChoice::Auto`]).
    pub fn new(model: &Model) -> Result<DirectSolver> {
        Self::with_ordering(model, OrderingChoice::Auto)
    }

    /// [`DirectSolver::new`] in the fill-reducing ordering `ordering` asks for.
    pub fn with_ordering(model: &Model, ordering: OrderingChoice) -> Result<DirectSolver> {
        // faer's parallel factorization started from a worker (`on_workers`;
        // no MPI here: every rank that solves directly solves alone).
        on_workers(true, || Self::factor_here(model, ordering))
    }

    /// [`Self::with_ordering`] on the thread that runs it.
    fn factor_here(model: &Model, ordering: OrderingChoice) -> Result<DirectSolver> {
        let t = std::time::Instant::now();
        let k = assemble(model)?;
        let assembly_s = t.elapsed().as_secs_f64();
        if model.n_free == 0 {
            return Err(Error::Mechanism("every dof is blocked: nothing to solve".into()));
        }
        let par = crate::factor::pool_par();
        let chol = SparseCholesky::factor_choosing(&k, ordering, BATCH, PIVOT_RATIO, par).map_err(|e| match e {
            FactorError::Pivot { dof, negative: true, .. } if model.effects.geometric_stiffness => Error::Mechanism(format!(
                "the stiffness with geometric stiffness is not positive definite (negative pivot at node {} component {})",
                model.dof_owner(dof).0,
                ["x", "y", "z"][model.dof_owner(dof).1]
            )),
            FactorError::Pivot { dof, .. } => mechanism_error(model, dof, "the structure"),
            FactorError::Internal(m) => Error::Numerical(m),
        })?;
        let stats = DirectStats {
            n: model.n_free,
            nnz_k: k.compute_nnz(),
            nnz_l: chol.nnz_l(),
            assembly_s,
            ordering_s: chol.timings.symbolic_s,
            factor_s: chol.timings.numeric_s,
            supernodal: chol.is_supernodal(),
            ordering: Some(chol.ordering()),
            threads: par.degree(),
            refinements: 0,
            refinement_s: 0.0,
        };
        Ok(DirectSolver {
            chol,
            stats,
            cached: Vec::new(),
            cache_pos: vec![usize::MAX; model.cables.len()],
            schur: Mat::zeros(0, 0),
            schur_max: SCHUR_MAX,
            without_slack: None,
            slack_stiffness: None,
            refactorizations: 0,
        })
    }

    /// Largest slack set solved through the Schur complement of the single
    /// factorization (default 400); larger sets refactor `K` without them.
    pub fn set_schur_limit(&mut self, max_slack: usize) {
        self.schur_max = max_slack;
    }

    /// Numeric refactorizations of `K` without slack cables done so far
    /// (large slack sets, see [`DirectSolver::set_schur_limit`]).
    pub fn refactorizations(&self) -> usize {
        self.refactorizations
    }

    /// Iterative-refinement corrections added to the solves so far.
    pub fn refinements(&self) -> usize {
        self.stats.refinements
    }

    /// Solves `(K − (1−s) H_S K_S H_Sᵀ) u = b + (1−s) H_S K_S e0_S`: the
    /// structure with its slack cables removed (`s = 0`, their tension is
    /// zero) or softened to `s` times their stiffness, by a numeric
    /// refactorization on the symbolic analysis of `K`.
    fn solve_without_slack(
        &mut self,
        model: &Model,
        b: &[f64],
        slack: &[bool],
        soft: f64,
        u: &mut [f64],
    ) -> Result<()> {
        let mut is_slack = vec![false; model.elements.len()];
        for (c, &e) in model.cables.iter().enumerate() {
            is_slack[e] = slack[c];
        }
        let (k, scatter) = match &mut self.slack_stiffness {
            Some(m) => m,
            slot => {
                let k = assemble(model)?;
                let scatter = model.stiffness_scatter(&k);
                slot.insert((k, scatter))
            }
        };
        // Slack cables lose their axial stiffness (soft = 0: they stay in
        // the pattern as explicit zeros) and keep their geometric one, as
        // on the Schur path: `K_G` does not depend on the slack set. Scaling
        // the whole block instead made the two paths differ by 46 % of `u`
        // on a 10×10 tensegrity grid with 284 slack cables.
        model.stiffness_values_into(scatter, |e| if is_slack[e] { soft } else { 1.0 }, k.val_mut());
        let k = &*k;
        let chol = match &mut self.without_slack {
            Some(f) => f,
            slot => {
                let mut f = self
                    .chol
                    .sharing_symbolic(1)
                    .map_err(|e| Error::Numerical(format!("{e:?}")))?;
                f.keep_numeric_workspace();
                slot.insert(f)
            }
        };
        self.refactorizations += 1;
        chol.refactor(k, PIVOT_RATIO).map_err(|e| match e {
            FactorError::Pivot { dof, .. } => {
                let (node, c) = model.dof_owner(dof);
                Error::Mechanism(format!(
                    "the structure becomes a mechanism when its slack cables are removed (no stiffness at node {node} component {})",
                    ["x", "y", "z"][c]
                ))
            }
            FactorError::Internal(m) => Error::Numerical(m),
        })?;
        u.copy_from_slice(b);
        for (c, &e) in model.cables.iter().enumerate() {
            if slack[c] {
                let el = &model.elements[e];
                model.add_h(e, (1.0 - soft) * el.k * el.e0, u);
            }
        }
        chol.solve_in_place(u);
        Ok(())
    }

    /// Sizes and timings of the factorization.
    pub fn stats(&self) -> &DirectStats {
        &self.stats
    }

    /// Solves `K x = rhs` in place with the cached factor.
    pub fn solve_linear(&mut self, rhs: &mut [f64]) {
        self.chol.solve_in_place(rhs);
    }

    /// Solves the equilibrium for the right-hand side `b = f − H k e0`
    /// (see [`Model::rhs`]), with exact cable complementarity.
    pub fn solve(&mut self, model: &Model, b: &[f64]) -> Result<Equilibrium> {
        on_workers(true, || self.active_set(model, b))
    }

    /// [`Self::solve`] on the thread that runs it.
    fn active_set(&mut self, model: &Model, b: &[f64]) -> Result<Equilibrium> {
        let nc = model.cables.len();
        let mut u0 = b.to_vec();
        self.chol.solve_in_place(&mut u0);
        if nc == 0 {
            let elongations = self.refine(model, b, &[], true, &mut u0, &mut []);
            return Ok(Equilibrium {
                u: u0,
                lambda: Vec::new(),
                iterations: 0,
                elongations,
            });
        }
        // g_c = e_c(u0) + e0_c: cable strain with every cable taut.
        let g0: Vec<f64> = model
            .cables
            .iter()
            .map(|&e| model.elongation(e, &u0) + model.elements[e].e0)
            .collect();
        let strain_scale = g0.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(f64::MIN_POSITIVE);
        let tol = 1e-13 * strain_scale;

        let mut slack: Vec<bool> = g0.iter().map(|&g| g < -tol).collect();
        let mut seen: HashSet<Vec<bool>> = HashSet::new();
        let mut murty = false;
        let max_iter = 20 * nc + 100;
        let mut u = u0.clone();
        let mut lambda = vec![0.0; nc];
        let mut softened;
        for it in 1..=max_iter {
            let mut mechanism: Option<String> = None;
            let set: Vec<usize> = (0..nc).filter(|&c| slack[c]).collect();
            lambda.iter_mut().for_each(|l| *l = 0.0);
            // An intermediate set may leave a node with only slack cables: a
            // mechanism that the final set does not have. Such a step is
            // taken with the slack cables kept at SOFT times their stiffness
            // (a guide for the next set); a set the iteration settles on must
            // solve exactly.
            softened = false;
            let mut schur_ok = false;
            if set.len() <= self.schur_max {
                if set.is_empty() {
                    schur_ok = true;
                } else {
                    self.extend_cache(model, &set);
                    match self.solve_schur(model, &set, &g0) {
                        Ok(mu) => {
                            for (i, &c) in set.iter().enumerate() {
                                lambda[c] = mu[i] / model.elements[model.cables[c]].k.sqrt();
                            }
                            schur_ok = true;
                        }
                        Err(Error::Mechanism(m)) => mechanism = Some(m),
                        Err(e) => return Err(e),
                    }
                }
            }
            if schur_ok {
                // u = K⁻¹ (b − Σ h_c k_c λ_c)
                u.copy_from_slice(b);
                for &c in &set {
                    let e = model.cables[c];
                    model.add_h(e, -model.elements[e].k * lambda[c], &mut u);
                }
                self.chol.solve_in_place(&mut u);
            } else {
                if mechanism.is_none() {
                    match self.solve_without_slack(model, b, &slack, 0.0, &mut u) {
                        Ok(()) => {}
                        Err(Error::Mechanism(m)) => mechanism = Some(m),
                        Err(e) => return Err(e),
                    }
                }
                if mechanism.is_some() {
                    self.solve_without_slack(model, b, &slack, SOFT, &mut u)?;
                    softened = true;
                }
                for &c in &set {
                    let e = model.cables[c];
                    lambda[c] = -(model.elongation(e, &u) + model.elements[e].e0);
                }
            }
            if u.iter().any(|v| !v.is_finite()) {
                return Err(Error::Numerical(
                    "direct solve produced a non-finite displacement".into(),
                ));
            }

            // Violations: slack cables with λ < 0, taut cables with g < 0.
            let mut changed = false;
            let mut first_violation = None;
            let mut next = slack.clone();
            for c in 0..nc {
                let e = model.cables[c];
                let viol = if slack[c] {
                    lambda[c] < -tol
                } else {
                    model.elongation(e, &u) + model.elements[e].e0 < -tol
                };
                if viol {
                    if first_violation.is_none() {
                        first_violation = Some(c);
                    }
                    next[c] = !slack[c];
                    changed = true;
                }
            }
            if !changed {
                if softened {
                    return Err(Error::Mechanism(mechanism.unwrap_or_default()));
                }
                let elongations = self.refine(model, b, &set, schur_ok, &mut u, &mut lambda);
                for l in lambda.iter_mut() {
                    *l = l.max(0.0);
                }
                return Ok(Equilibrium {
                    u,
                    lambda,
                    iterations: it,
                    elongations,
                });
            }
            if !murty && !seen.insert(slack.clone()) {
                murty = true;
            }
            if murty {
                let c = first_violation.unwrap_or(0);
                slack[c] = !slack[c];
            } else {
                slack = next;
            }
        }
        Err(Error::Numerical(format!(
            "cable active set did not settle in {max_iter} iterations"
        )))
    }

    /// Iterative refinement of the settled solve (slack set `set`): the
    /// forces `b − K u` are recomputed element by element from the
    /// elongations, which are differences of displacements and so exact to
    /// round-off of themselves, where the assembled `K u` loses
    /// `ε ‖K‖ ‖u‖`; a correction is solved on the same factors and added.
    /// On the 130² plate the AMD and nested-dissection solutions differed
    /// by 5e-10 before and by 6e-17 after; on a 20×20 tensegrity grid with
    /// struts 1e5 × its cables (geometric stiffness: `K_G u` enters the
    /// forces from `u`), 3.6e-8 and 9.5e-15. `schur`: the set was solved on
    /// the factor of `K` with the cached Schur complement (slack cables
    /// kept, their tension cancelled by `λ`); otherwise on the
    /// refactorization without them.
    fn refine(
        &mut self,
        model: &Model,
        b: &[f64],
        set: &[usize],
        schur: bool,
        u: &mut [f64],
        lambda: &mut [f64],
    ) -> Option<Vec<f64>> {
        // The elongations of `u` and of each correction, summed apart: the
        // sum `u` rounds each correction to `ε ‖u‖`, which at a stiffness
        // contrast of 1e8 is 1e-8 of the stiff bars' elongations.
        let started = std::time::Instant::now();
        let mut elongations: Vec<f64> = (0..model.elements.len()).map(|e| model.elongation(e, u)).collect();
        // The cable index of each slack element.
        let mut slack_cable = vec![None; model.elements.len()];
        for &c in set {
            slack_cable[model.cables[c]] = Some(c);
        }
        let u_norm = u.iter().map(|x| x * x).sum::<f64>().sqrt();
        // `K_G u`, the forces of the geometric stiffness, where simulated:
        // from `u` itself (they are not a function of the elongations).
        let geometric = model.elements.iter().any(|el| el.geo != 0.0);
        let mut kg = vec![0.0; if geometric { u.len() } else { 0 }];
        for _ in 0..MAX_REFINEMENTS {
            // r = b − Σ_e H_e k_e e_e(u) − K_G u, over the elements in the
            // solved system: slack cables with `λ` (Schur), or not at all
            // (their geometric stiffness stays in `K_G`).
            let mut r = b.to_vec();
            let mut forces2 = 0.0;
            for (e, el) in model.elements.iter().enumerate() {
                let t = match slack_cable[e] {
                    None => el.k * elongations[e],
                    Some(c) if schur => el.k * (elongations[e] + lambda[c]),
                    Some(_) => -el.k * el.e0,
                };
                forces2 += t * t;
                model.add_h(e, -t, &mut r);
            }
            if geometric {
                kg.iter_mut().for_each(|x| *x = 0.0);
                model.add_geometric_forces(u, 1.0, &mut kg);
                for (r, g) in r.iter_mut().zip(&kg) {
                    *r -= g;
                    forces2 += g * g;
                }
            }
            // Done when the residual is at the round-off of the forces it
            // sums (and, on the Schur path, the slack cables' tension too):
            // on a well-conditioned structure before any correction, on
            // the 1e6-dof plate after one (a second cost 0.35 s of 12).
            let r_norm = r.iter().map(|x| x * x).sum::<f64>().sqrt();
            let strain = elongations.iter().fold(0.0f64, |m, x| m.max(x.abs()));
            let cancelled = !schur
                || set.iter().all(|&c| {
                    let e = model.cables[c];
                    (elongations[e] + model.elements[e].e0 + lambda[c]).abs() <= RESIDUAL_DONE * strain
                });
            if r_norm <= RESIDUAL_DONE * forces2.sqrt() && cancelled {
                break;
            }
            if schur {
                self.chol.solve_in_place(&mut r);
                if !set.is_empty() {
                    // The slack cables' tension must stay cancelled:
                    // g_c = e_c(δu0) + (e_c(u) + e0_c + λ_c).
                    let mut g = vec![0.0; model.cables.len()];
                    for &c in set {
                        let e = model.cables[c];
                        g[c] = model.elongation(e, &r) + elongations[e] + model.elements[e].e0 + lambda[c];
                    }
                    let Ok(mu) = self.solve_schur(model, set, &g) else {
                        break;
                    };
                    let mut q = vec![0.0; r.len()];
                    for (i, &c) in set.iter().enumerate() {
                        let e = model.cables[c];
                        let dl = mu[i] / model.elements[e].k.sqrt();
                        lambda[c] += dl;
                        model.add_h(e, -model.elements[e].k * dl, &mut q);
                    }
                    self.chol.solve_in_place(&mut q);
                    r.iter_mut().zip(&q).for_each(|(x, y)| *x += y);
                }
            } else {
                let Some(chol) = self.without_slack.as_mut() else {
                    break;
                };
                chol.solve_in_place(&mut r);
            }
            if !r.iter().all(|x| x.is_finite()) {
                break;
            }
            u.iter_mut().zip(&r).for_each(|(x, d)| *x += d);
            elongations
                .iter_mut()
                .enumerate()
                .for_each(|(e, x)| *x += model.elongation(e, &r));
            if !schur {
                for &c in set {
                    let e = model.cables[c];
                    lambda[c] = -(elongations[e] + model.elements[e].e0);
                }
            }
            self.stats.refinements += 1;
            let d_norm = r.iter().map(|x| x * x).sum::<f64>().sqrt();
            if d_norm <= REFINED * u_norm {
                break;
            }
        }
        self.stats.refinement_s += started.elapsed().as_secs_f64();
        Some(elongations)
    }

    /// Adds Schur columns for cables of `set` not yet cached.
    fn extend_cache(&mut self, model: &Model, set: &[usize]) {
        let new: Vec<usize> = set
            .iter()
            .copied()
            .filter(|&c| self.cache_pos[c] == usize::MAX)
            .collect();
        if new.is_empty() {
            return;
        }
        let n = model.n_free;
        let old = self.cached.len();
        for &c in &new {
            self.cache_pos[c] = self.cached.len();
            self.cached.push(c);
        }
        let m = self.cached.len();
        let mut schur = Mat::<f64>::zeros(m, m);
        for j in 0..old {
            for i in 0..old {
                schur[(i, j)] = self.schur[(i, j)];
            }
        }
        let mut block = vec![0.0; n * BATCH];
        for chunk in new.chunks(BATCH) {
            let w = chunk.len();
            block[..n * w].iter_mut().for_each(|v| *v = 0.0);
            for (j, &c) in chunk.iter().enumerate() {
                let e = model.cables[c];
                model.add_h(e, model.elements[e].k.sqrt(), &mut block[j * n..(j + 1) * n]);
            }
            self.chol.solve_columns(&mut block[..n * w], w);
            for (j, &c) in chunk.iter().enumerate() {
                let col = &block[j * n..(j + 1) * n];
                let pj = self.cache_pos[c];
                for (pi, &d) in self.cached.iter().enumerate() {
                    let e = model.cables[d];
                    let v = model.elongation(e, col) * model.elements[e].k.sqrt();
                    schur[(pi, pj)] = v;
                    schur[(pj, pi)] = v;
                }
            }
        }
        self.schur = schur;
    }

    /// Solves `(I − S_SS) μ = −K^{1/2} g_S` for the slack set.
    fn solve_schur(&self, model: &Model, set: &[usize], g0: &[f64]) -> Result<Vec<f64>> {
        let m = set.len();
        let mut a = Mat::<f64>::zeros(m, m);
        for (j, &cj) in set.iter().enumerate() {
            for (i, &ci) in set.iter().enumerate() {
                let s = self.schur[(self.cache_pos[ci], self.cache_pos[cj])];
                a[(i, j)] = if i == j { 1.0 - s } else { -s };
            }
        }
        let mut rhs = Mat::<f64>::zeros(m, 1);
        for (i, &c) in set.iter().enumerate() {
            rhs[(i, 0)] = -model.elements[model.cables[c]].k.sqrt() * g0[c];
        }
        // Spectrum in [0, 1]: a pivot below 1e-10 is a mechanism, not noise.
        let min_diag = (0..m).map(|i| a[(i, i)]).fold(f64::INFINITY, f64::min);
        let llt = a.llt(faer::Side::Lower);
        let ok = match &llt {
            Ok(l) => {
                let lm = l.L();
                (0..m).all(|i| lm[(i, i)] * lm[(i, i)] > 1e-10)
            }
            Err(_) => false,
        };
        if !ok || min_diag <= 1e-10 {
            let names: Vec<String> = set.iter().take(8).map(|&c| model.cables[c].to_string()).collect();
            return Err(Error::Mechanism(format!(
                "the structure becomes a mechanism when its {m} slack cables are removed (elements {}{})",
                names.join(", "),
                if m > 8 { ", ..." } else { "" }
            )));
        }
        let x = llt.expect("checked above").solve(&rhs);
        Ok((0..m).map(|i| x[(i, 0)]).collect())
    }
}
