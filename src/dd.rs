//! The seed's multilevel domain decomposition iteration (DESIGN.md §5, the
//! paper's eqs. 20–23), linear and nonsmooth.
//!
//! One iteration:
//! 1. local stage: `F ← F + (X^D)^{-1} J V` on every interface, and per
//!    cable `λ ← max(0, −(e + e0))`;
//! 2. global step: `y_E = K_E⁺ r_E` with `r_E = b_E − C_Eᵀ B_E F − H_c k_c λ`
//!    (the one sparse solve per subdomain);
//! 3. coarse step: solve `[L −G; −Gᵀ 0]` for `(f, α)` with the right-hand side
//!    `Pᵀ J y` (reusing the solve of step 2) and `Rᵀ r`, then
//!    `V_E = y_E − Z_E f_E + R_E α_E`.
//!
//! Everything per subdomain runs in parallel with rayon; reductions are
//! summed serially in subdomain order, so results do not depend on the
//! number of threads. Scratch is allocated at set-up: the iteration loop
//! does not allocate.

use crate::cg_stopping::{self, CgStopping};
use crate::coarse::{CoarseContribution, CoarseProblem, MacroBasis};
use crate::decomposition::Decomposition;
use crate::error::{Error, Result};
use crate::kernels::{self, Run, Side};
use crate::model::{Model, FIXED};
use crate::result::HistoryEntry;
use crate::scaling::{self, EntryWeights, InterfaceScaling};
use crate::scene::{Preconditioner, SearchDirection};
use crate::subdomain::{InteriorProblem, SubdomainOperator};
use faer::Mat;
use rayon::prelude::*;
use std::time::Instant;

/// Settings of the iterative methods.
#[derive(Debug, Clone)]
pub struct DdOptions {
    /// With the macro space and coarse problem (multilevel) or without.
    pub coarse: bool,
    pub tolerance: f64,
    pub max_iterations: usize,
    pub search_direction: SearchDirection,
    /// Conjugate gradient on the interface problem instead of the seed's
    /// stationary iteration (linear case only; needs the coarse step).
    pub krylov: bool,
    /// Preconditioner of the CG (ignored by the stationary iteration).
    pub preconditioner: Preconditioner,
}

/// Fraction of the stability limit `2 / λ_max` used by the automatic `d`.
pub const AUTO_D_FACTOR: f64 = 0.6;

/// Power iterations used to estimate `λ_max` for the automatic `d`.
const POWER_ITERATIONS: usize = 30;

/// Indicator growth over the best value seen that counts as divergence.
const DIVERGENCE_GROWTH: f64 = 1e6;

/// Interface CG restarts (from the true residual) when its indicator grows
/// this much above the best since the last restart...
const CG_RESTART_GROWTH: f64 = 4.0;
/// ...at most this often in one solve.
const CG_MAX_RESTARTS: usize = 10;

/// Restarts with a halved automatic `d` before divergence is reported.
const MAX_D_RESTARTS: usize = 3;

/// Iterations over which the contraction factor `ρ` of the indicator is
/// measured for the stopping test.
pub const CONTRACTION_WINDOW: usize = 10;

/// Largest `ρ` used in the stopping test (caps the safety factor
/// `1 / (1 − ρ)` at 100).
pub const CONTRACTION_CAP: f64 = 0.99;

/// Safety factor `1 / (1 − ρ)` of the stopping test. The indicator of a
/// stationary iteration measures the last step (an interface residual, a
/// change of `λ`), not the distance to the solution; for a linear
/// contraction with factor `ρ` that distance is up to `1 / (1 − ρ)` times
/// larger. Stopping on `indicator` alone left slowly converging runs 10-35×
/// the tolerance away from the direct solution (docs/robustness.md).
/// `history` holds the indicators so far, the current one last; `ρ` is the
/// geometric mean ratio over the last [`CONTRACTION_WINDOW`] iterations
/// (fewer at the start; 0.5 with a single value), clamped to
/// `[0, CONTRACTION_CAP]`.
pub fn stopping_factor(history: &[HistoryEntry]) -> f64 {
    let n = history.len();
    let rho = if n < 2 {
        0.5
    } else {
        let w = (n - 1).min(CONTRACTION_WINDOW);
        let (now, then) = (history[n - 1].indicator, history[n - 1 - w].indicator);
        if then > 0.0 && now >= 0.0 {
            (now / then).powf(1.0 / w as f64)
        } else {
            CONTRACTION_CAP
        }
    };
    1.0 / (1.0 - rho.clamp(0.0, CONTRACTION_CAP))
}

/// Whether the indicator made no net progress over the last
/// [`CONTRACTION_WINDOW`] iterations: it sits on the floor that round-off
/// allows, so an indicator already below the tolerance is accepted there.
pub fn stalled(history: &[HistoryEntry]) -> bool {
    let n = history.len();
    n > CONTRACTION_WINDOW && history[n - 1].indicator >= history[n - 1 - CONTRACTION_WINDOW].indicator
}

/// A unilateral cable seen from its subdomain: the column `h_c` of `H`
/// (at most 6 entries, local dofs; unused slots hold [`NO_DOF`]), its
/// stiffness `k_c` and prestrain `e0_c`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CableColumn {
    /// Global cable index (position in the solution's `lambda`).
    pub cable: usize,
    pub dofs: [u32; 6],
    pub coef: [f64; 6],
    pub k: f64,
    pub e0: f64,
}

/// Unused slot of a [`CableColumn`].
pub const NO_DOF: u32 = u32::MAX;

impl CableColumn {
    /// Elongation `h_cᵀ v`.
    #[inline]
    fn elongation(&self, v: &[f64]) -> f64 {
        let mut x = 0.0;
        for (&i, &c) in self.dofs.iter().zip(&self.coef) {
            if i != NO_DOF {
                x += c * v[i as usize];
            }
        }
        x
    }

    /// `out += h_c · coef`.
    #[inline]
    fn add_to(&self, coef: f64, out: &mut [f64]) {
        for (&i, &c) in self.dofs.iter().zip(&self.coef) {
            if i != NO_DOF {
                out[i as usize] += c * coef;
            }
        }
    }
}

/// What the iteration needs of one subdomain besides its operator: the
/// constant part of its right-hand side and its unilateral cables.
#[derive(Debug, Clone, Default)]
pub struct SubdomainLoad {
    /// Constant local load (prestrain load `−Σ H k e0` of its elements).
    pub constant: Vec<f64>,
    pub cables: Vec<CableColumn>,
}

/// A DD problem in algebraic form: factored subdomain operators, their
/// global dof ids (through the decomposition), the point and component of
/// every global dof (for the macro modes), and the cable columns.
pub struct DdProblem<'a> {
    pub decomposition: &'a Decomposition,
    pub operators: Vec<SubdomainOperator>,
    pub loads: Vec<SubdomainLoad>,
    /// Point and component (0..3) of each global dof.
    pub dof_points: Vec<([f64; 3], usize)>,
    pub n_cables: usize,
}

impl<'a> DdProblem<'a> {
    /// Builds the algebraic problem of a truss model (factors every
    /// subdomain in parallel).
    pub fn from_model(model: &Model, dec: &'a Decomposition) -> Result<DdProblem<'a>> {
        let ops: Vec<Result<SubdomainOperator>> = dec
            .subdomains
            .par_iter()
            .enumerate()
            .map(|(i, sd)| SubdomainOperator::new(i, model, sd, 64))
            .collect();
        let mut operators = Vec::with_capacity(ops.len());
        for op in ops {
            operators.push(op?);
        }
        let loads = dec
            .subdomains
            .iter()
            .map(|sd| {
                let n = sd.dofs.len();
                let mut constant = vec![0.0; n];
                let mut cables = Vec::new();
                let local = |d: usize| {
                    if d == FIXED {
                        NO_DOF
                    } else {
                        sd.local(d).map_or(NO_DOF, |l| l as u32)
                    }
                };
                for &e in &sd.elements {
                    let el = &model.elements[e];
                    let dofs = model.element_dofs(e).map(local);
                    let n = el.dir;
                    let col = CableColumn {
                        cable: usize::MAX,
                        dofs,
                        coef: [-n[0], -n[1], -n[2], n[0], n[1], n[2]],
                        k: el.k,
                        e0: el.e0,
                    };
                    if el.e0 != 0.0 {
                        col.add_to(-el.k * el.e0, &mut constant);
                    }
                    if el.unilateral {
                        let cable = model.cables.binary_search(&e).expect("unilateral element is a cable");
                        cables.push(CableColumn { cable, ..col });
                    }
                }
                SubdomainLoad { constant, cables }
            })
            .collect();
        let dof_points = (0..model.n_free)
            .map(|d| {
                let (node, c) = model.dof_owner(d);
                (model.coords[node], c)
            })
            .collect();
        Ok(DdProblem {
            decomposition: dec,
            operators,
            loads,
            dof_points,
            n_cables: model.cables.len(),
        })
    }
}

struct SubState {
    op: SubdomainOperator,
    /// `(interface, is_lo)` for every interface of this subdomain.
    ifaces: Vec<(usize, bool)>,
    inv_mult: Vec<f64>,
    /// Constant local load (prestrain).
    prestrain: Vec<f64>,
    b: Vec<f64>,
    r: Vec<f64>,
    y: Vec<f64>,
    v: Vec<f64>,
    g: Vec<f64>,
    /// Interface dofs of this subdomain (local, unique, increasing).
    iface_dofs: Vec<u32>,
    /// Search-direction weight per local dof: 1 for a scalar `d`, the
    /// diagonal of `K_E` for the lumped choice.
    weight: Vec<f64>,
    /// `Z_E = K_E⁺ W_E` (`n × m_E`) and the global macro index of each column.
    z: Mat<f64>,
    macro_cols: Vec<usize>,
    fm: Vec<f64>,
    alpha_off: usize,
    alpha: Vec<f64>,
    rt_r: Vec<f64>,
    cables: Vec<CableColumn>,
    lambda: Vec<f64>,
    elong: Vec<f64>,
    e0: Vec<f64>,
    // per-iteration reductions
    v_norm2: f64,
    dlambda2: f64,
    dforce2: f64,
    /// Stiffness of each cable.
    kc: Vec<f64>,
    /// Interface CG: the displacement of the current forces (empty unless
    /// the solver uses CG).
    cg_v: Vec<f64>,
    /// Factored interior problem for the Dirichlet preconditioner of CG.
    interior: Option<InteriorProblem>,
    /// Interface CG: this subdomain's parts of the stopping energies
    /// (`cg_energies`).
    cg_energy: (f64, f64),
}

struct IfaceState {
    lo: usize,
    hi: usize,
    lo_idx: Vec<u32>,
    hi_idx: Vec<u32>,
    /// `lo_idx`, `hi_idx` as runs of consecutive local dofs: what the
    /// per-iteration kernels use (vectorised slice loops).
    runs: Vec<Run>,
    force: Vec<f64>,
    jump: Vec<f64>,
    /// `P_Γ` (`entries × m_Γ`), empty without coarse space.
    p: Mat<f64>,
    macro_off: usize,
    pt: Vec<f64>,
    jump_norm2: f64,
    /// Lumped interface stiffness `diag(K_lo) + diag(K_hi)` per entry: turns
    /// a jump into the force it leaves unbalanced.
    stiffness: Vec<f64>,
    force_norm2: f64,
    /// Interface CG: residual (jump), preconditioned residual, direction
    /// (empty unless the solver uses CG).
    cg_r: Vec<f64>,
    cg_z: Vec<f64>,
    cg_p: Vec<f64>,
    /// Interface CG: weights of the scaled jump operator `B_D` of the
    /// preconditioner ([`crate::scaling`]; empty unless the solver uses CG).
    w: EntryWeights,
}

/// Result of one DD solve.
#[derive(Debug, Clone)]
pub struct DdOutcome {
    pub u: Vec<f64>,
    pub lambda: Vec<f64>,
    pub converged: bool,
    pub iterations: usize,
    pub history: Vec<HistoryEntry>,
}

/// Sizes of the set-up, for reports.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct DdStats {
    pub subdomains: usize,
    pub kernel_dims: Vec<usize>,
    pub macro_unknowns: usize,
    pub kernel_unknowns: usize,
    pub interface_entries: usize,
    pub nnz_l: usize,
    pub search_direction: f64,
    /// Whole set-up (operators, macro space, coarse problem, `d`).
    pub setup_s: f64,
    /// Subdomain assembly and factorizations (with kernels).
    pub factor_s: f64,
    /// Macro basis, batched solves for `L` and `G`, coarse factorization.
    pub coarse_s: f64,
    /// Choice of `d` (power iteration on the interface operator).
    pub search_direction_s: f64,
}

/// The set-up DD solver: factorizations, macro space and coarse problem,
/// reusable for any number of load cases.
pub struct DdSolver {
    subs: Vec<SubState>,
    ifaces: Vec<IfaceState>,
    coarse: Option<CoarseProblem>,
    d: f64,
    opts: DdOptions,
    n_free: usize,
    n_cables: usize,
    dof_maps: Vec<Vec<usize>>,
    stats: DdStats,
}

impl DdSolver {
    /// Sets up a truss model: factors every subdomain, builds the macro
    /// basis and the coarse problem (multilevel), and picks `d`.
    pub fn new(model: &Model, dec: &Decomposition, opts: DdOptions) -> Result<DdSolver> {
        let t0 = Instant::now();
        let problem = DdProblem::from_model(model, dec)?;
        let factor_s = t0.elapsed().as_secs_f64();
        let mut solver = DdSolver::from_problem(problem, opts)?;
        solver.stats.setup_s = t0.elapsed().as_secs_f64();
        solver.stats.factor_s = factor_s;
        Ok(solver)
    }

    /// Sets up an algebraic problem (already factored operators).
    pub fn from_problem(problem: DdProblem<'_>, opts: DdOptions) -> Result<DdSolver> {
        let t0 = Instant::now();
        let DdProblem {
            decomposition: dec,
            operators,
            loads,
            dof_points,
            n_cables,
        } = problem;
        let ns = dec.len();
        let n_free = dof_points.len();
        let singular: Vec<usize> = operators.iter().filter(|o| o.kernel_dim() > 0).map(|o| o.id).collect();
        if !singular.is_empty() && (!opts.coarse || ns == 1) {
            let what = if ns == 1 {
                "the structure is not supported well enough: its stiffness is singular".to_string()
            } else {
                format!(
                    "monolevel needs every subdomain matrix to be regular, but subdomain{} {} {} singular (floating or with a mechanism at the cut); use multilevel",
                    if singular.len() > 1 { "s" } else { "" },
                    singular.iter().map(|s| s.to_string()).collect::<Vec<_>>().join(", "),
                    if singular.len() > 1 { "are" } else { "is" }
                )
            };
            return Err(if ns == 1 {
                Error::Mechanism(what)
            } else {
                Error::MethodNotApplicable(what)
            });
        }

        if opts.krylov && n_cables > 0 {
            return Err(Error::MethodNotApplicable(format!(
                "the interface conjugate gradient solves the linear case, but the model has {n_cables} unilateral cables; use multilevel"
            )));
        }
        if opts.krylov && !opts.coarse {
            return Err(Error::MethodNotApplicable(
                "the interface conjugate gradient needs the coarse step".into(),
            ));
        }
        let use_coarse = opts.coarse && !dec.interfaces.is_empty();
        let t_coarse = Instant::now();
        // Interfaces and their macro bases.
        let mut ifaces: Vec<IfaceState> = dec
            .interfaces
            .iter()
            .map(|it| IfaceState {
                lo: it.lo,
                hi: it.hi,
                lo_idx: dec.entry_lo_local[it.start..it.end].to_vec(),
                hi_idx: dec.entry_hi_local[it.start..it.end].to_vec(),
                runs: kernels::runs(
                    &dec.entry_lo_local[it.start..it.end],
                    &dec.entry_hi_local[it.start..it.end],
                ),
                force: vec![0.0; it.len()],
                jump: vec![0.0; it.len()],
                p: Mat::zeros(0, 0),
                macro_off: 0,
                pt: Vec::new(),
                jump_norm2: 0.0,
                stiffness: Vec::new(),
                force_norm2: 0.0,
                cg_r: Vec::new(),
                cg_z: Vec::new(),
                cg_p: Vec::new(),
                w: EntryWeights::default(),
            })
            .collect();
        if use_coarse {
            let blocks: Vec<Mat<f64>> = dec
                .interfaces
                .par_iter()
                .zip(ifaces.par_iter())
                .map(|(it, st)| {
                    let dofs = &dec.entry_dof[it.start..it.end];
                    let (points, comp): (Vec<[f64; 3]>, Vec<usize>) = dofs.iter().map(|&d| dof_points[d]).unzip();
                    let rlo = operators[it.lo].kernel();
                    let rhi = operators[it.hi].kernel();
                    let tlo = Mat::from_fn(it.len(), rlo.ncols(), |j, q| rlo[(st.lo_idx[j] as usize, q)]);
                    let thi = Mat::from_fn(it.len(), rhi.ncols(), |j, q| rhi[(st.hi_idx[j] as usize, q)]);
                    MacroBasis::interface_block(&points, &comp, &tlo, &thi)
                })
                .collect();
            let basis = MacroBasis::from_blocks(blocks);
            for (i, st) in ifaces.iter_mut().enumerate() {
                st.macro_off = basis.offset[i];
                st.pt = vec![0.0; basis.blocks[i].ncols()];
            }
            for (st, p) in ifaces.iter_mut().zip(basis.blocks) {
                st.p = p;
            }
        }

        // Per-subdomain state.
        let mut alpha_off = 0;
        let mut subs: Vec<SubState> = Vec::with_capacity(ns);
        for (s, (op, load)) in operators.into_iter().zip(loads).enumerate() {
            let sd = &dec.subdomains[s];
            let n = op.n();
            let ifs: Vec<(usize, bool)> = sd.interfaces.iter().map(|&i| (i, dec.interfaces[i].lo == s)).collect();
            let SubdomainLoad {
                constant: prestrain,
                cables,
            } = load;
            let r = op.kernel_dim();
            let nc = cables.len();
            subs.push(SubState {
                ifaces: ifs,
                inv_mult: sd.multiplicity.iter().map(|&m| 1.0 / m as f64).collect(),
                prestrain,
                b: vec![0.0; n],
                r: vec![0.0; n],
                y: vec![0.0; n],
                v: vec![0.0; n],
                g: vec![0.0; n],
                iface_dofs: Vec::new(),
                weight: vec![1.0; n],
                z: Mat::zeros(0, 0),
                macro_cols: Vec::new(),
                fm: Vec::new(),
                alpha_off,
                alpha: vec![0.0; r],
                rt_r: vec![0.0; r],
                e0: cables.iter().map(|c| c.e0).collect(),
                kc: cables.iter().map(|c| c.k).collect(),
                cables,
                lambda: vec![0.0; nc],
                elong: vec![0.0; nc],
                v_norm2: 0.0,
                dlambda2: 0.0,
                dforce2: 0.0,
                cg_v: Vec::new(),
                interior: None,
                cg_energy: (0.0, 0.0),
                op,
            });
            alpha_off += r;
        }

        let diags: Vec<Vec<f64>> = subs.iter().map(|s| s.op.diagonal()).collect();
        for it in ifaces.iter_mut() {
            it.stiffness = it
                .lo_idx
                .iter()
                .zip(&it.hi_idx)
                .map(|(&a, &b)| diags[it.lo][a as usize] + diags[it.hi][b as usize])
                .collect();
        }
        let lumped = matches!(opts.search_direction, SearchDirection::Auto);
        for (s, st) in subs.iter_mut().enumerate() {
            let mut dofs: Vec<u32> = Vec::new();
            for &(i, is_lo) in &st.ifaces {
                dofs.extend(if is_lo { &ifaces[i].lo_idx } else { &ifaces[i].hi_idx });
            }
            dofs.sort_unstable();
            dofs.dedup();
            st.iface_dofs = dofs;
            if lumped {
                st.weight = diags[s].clone();
            }
        }
        drop(diags);

        // Coarse operator from one batched multi-RHS solve per subdomain.
        let mut coarse = None;
        let mut n_macro = 0;
        if use_coarse {
            n_macro = ifaces.iter().map(|i| i.p.ncols()).sum();
            let parts: Vec<CoarseContribution> = subs
                .par_iter_mut()
                .map(|st| {
                    let n = st.op.n();
                    let mut cols = Vec::new();
                    for &(i, _) in &st.ifaces {
                        let it = &ifaces[i];
                        cols.extend((0..it.p.ncols()).map(|q| it.macro_off + q));
                    }
                    let m = cols.len();
                    let mut w = vec![0.0; n * m];
                    let mut c = 0;
                    for &(i, is_lo) in &st.ifaces {
                        let it = &ifaces[i];
                        let idx = if is_lo { &it.lo_idx } else { &it.hi_idx };
                        let sign = if is_lo { 1.0 } else { -1.0 };
                        for q in 0..it.p.ncols() {
                            for (j, &l) in idx.iter().enumerate() {
                                w[c * n + l as usize] += sign * it.p[(j, q)];
                            }
                            c += 1;
                        }
                    }
                    let mut z = w.clone();
                    st.op.solve_columns(&mut z, m);
                    // W_E is zero off the interface dofs: L_E = W_Iᵀ Z_I and
                    // G_E = W_Iᵀ R_I on those rows only.
                    let rows = &st.iface_dofs;
                    let wi = Mat::from_fn(rows.len(), m, |i, j| w[j * n + rows[i] as usize]);
                    let zi = Mat::from_fn(rows.len(), m, |i, j| z[j * n + rows[i] as usize]);
                    let kernel = st.op.kernel();
                    let ri = Mat::from_fn(rows.len(), kernel.ncols(), |i, j| kernel[(rows[i] as usize, j)]);
                    let l_e = wi.transpose() * &zi;
                    let g_e = wi.transpose() * &ri;
                    drop(w);
                    st.z = Mat::from_fn(n, m, |i, j| z[j * n + i]);
                    st.fm = vec![0.0; m];
                    st.macro_cols = cols.clone();
                    CoarseContribution {
                        cols,
                        l: l_e,
                        g: g_e,
                        alpha_off: st.alpha_off,
                    }
                })
                .collect();
            let n_alpha = alpha_off;
            let mut owner = vec![0usize; n_alpha];
            for (s, p) in parts.iter().enumerate() {
                owner[p.alpha_off..p.alpha_off + p.g.ncols()].fill(s);
            }
            coarse = Some(CoarseProblem::new(n_macro, n_alpha, &parts, &owner)?);
        }

        let stats = DdStats {
            subdomains: ns,
            kernel_dims: subs.iter().map(|s| s.op.kernel_dim()).collect(),
            macro_unknowns: n_macro,
            kernel_unknowns: alpha_off,
            interface_entries: dec.n_entries(),
            nnz_l: subs.iter().map(|s| s.op.nnz_l()).sum(),
            search_direction: 0.0,
            setup_s: 0.0,
            factor_s: 0.0,
            coarse_s: if use_coarse {
                t_coarse.elapsed().as_secs_f64()
            } else {
                0.0
            },
            search_direction_s: 0.0,
        };
        let mut solver = DdSolver {
            subs,
            ifaces,
            coarse,
            d: 0.0,
            opts,
            n_free,
            n_cables,
            dof_maps: dec.subdomains.iter().map(|s| s.dofs.clone()).collect(),
            stats,
        };
        if solver.opts.krylov {
            solver.set_interface_scaling(InterfaceScaling::default());
            for it in solver.ifaces.iter_mut() {
                let n = it.force.len();
                (it.cg_r, it.cg_z, it.cg_p) = (vec![0.0; n], vec![0.0; n], vec![0.0; n]);
            }
            for st in solver.subs.iter_mut() {
                st.cg_v = vec![0.0; st.v.len()];
            }
            if solver.opts.preconditioner == Preconditioner::Dirichlet {
                let t = Instant::now();
                solver.subs.par_iter_mut().try_for_each(|st| -> Result<()> {
                    st.interior = Some(InteriorProblem::new(&st.op, &st.iface_dofs)?);
                    Ok(())
                })?;
                solver.stats.factor_s += t.elapsed().as_secs_f64();
            }
        }
        let t_d = Instant::now();
        solver.d = match solver.opts.search_direction {
            SearchDirection::Value(d) => d,
            // CG needs no step length: only the lumped weights.
            SearchDirection::Auto if solver.opts.krylov => 0.0,
            SearchDirection::Auto => solver.auto_search_direction()?,
        };
        solver.stats.search_direction_s = t_d.elapsed().as_secs_f64();
        solver.stats.search_direction = solver.d;
        solver.stats.setup_s = t0.elapsed().as_secs_f64();
        Ok(solver)
    }

    /// Seconds for one forward and backward substitution with every
    /// subdomain factor, in parallel as in the iteration (average of
    /// `reps`): the lower bound of an iteration's cost. Uses the solver's
    /// own scratch, so it allocates nothing.
    pub fn substitution_time(&mut self, reps: usize) -> f64 {
        let reps = reps.max(1);
        let t = Instant::now();
        for _ in 0..reps {
            self.subs.par_iter_mut().for_each(|s| {
                s.y.copy_from_slice(&s.b);
                s.op.solve_in_place(&mut s.y);
            });
        }
        t.elapsed().as_secs_f64() / reps as f64
    }

    /// Weights of the CG preconditioner's scaled jump operator `B_D`
    /// ([`crate::scaling`]; default [`InterfaceScaling::Contrast`]). For
    /// comparisons; later solves use them. Set-up cost only (allocates).
    pub fn set_interface_scaling(&mut self, kind: InterfaceScaling) {
        let entries: Vec<scaling::InterfaceEntries<'_>> = self
            .ifaces
            .iter()
            .map(|it| scaling::InterfaceEntries {
                lo: it.lo,
                hi: it.hi,
                lo_idx: &it.lo_idx,
                hi_idx: &it.hi_idx,
            })
            .collect();
        let mult: Vec<Vec<u32>> = self
            .subs
            .iter()
            .map(|s| s.inv_mult.iter().map(|&w| (1.0 / w).round() as u32).collect())
            .collect();
        let diag: Vec<Vec<f64>> = match kind {
            InterfaceScaling::Stiffness | InterfaceScaling::Contrast => {
                self.subs.iter().map(|s| s.op.diagonal()).collect()
            }
            _ => Vec::new(),
        };
        let weights = scaling::interface_weights(&entries, &self.dof_maps, &mult, &diag, kind);
        for (it, w) in self.ifaces.iter_mut().zip(weights) {
            it.w = w;
        }
    }

    /// Changes the stopping rule for later solves (the set-up is unchanged).
    pub fn set_stopping(&mut self, tolerance: f64, max_iterations: usize) {
        self.opts.tolerance = tolerance;
        self.opts.max_iterations = max_iterations;
    }

    /// Set-up sizes and the chosen `d`.
    pub fn stats(&self) -> &DdStats {
        &self.stats
    }

    /// The search direction `d` in use.
    pub fn search_direction(&self) -> f64 {
        self.d
    }

    /// The macro basis `P_Γ` of each interface (empty without coarse step).
    pub fn macro_blocks(&self) -> Vec<&Mat<f64>> {
        self.ifaces.iter().map(|i| &i.p).collect()
    }

    /// The assembled coarse operator `L` (macro block of the saddle system),
    /// as a dense matrix: for tests on small cases.
    pub fn coarse_operator(&self) -> Option<Mat<f64>> {
        self.coarse.as_ref().map(|c| c.operator())
    }

    /// Worst relative residual of the coarse solves since set-up
    /// ([`CoarseProblem::worst_residual`]), if there is a coarse step.
    pub fn coarse_residual(&self) -> Option<f64> {
        self.coarse.as_ref().map(|c| c.worst_residual())
    }

    /// The factored coarse problem (multilevel only), e.g. to time its solve.
    pub fn coarse_problem_mut(&mut self) -> Option<&mut CoarseProblem> {
        self.coarse.as_mut()
    }

    /// The factored operator of subdomain `s`.
    pub fn operator(&self, s: usize) -> &SubdomainOperator {
        &self.subs[s].op
    }

    /// Mutable access to the operator of subdomain `s` (for solves in tests
    /// and tools; the iteration does not depend on its scratch state).
    pub fn operator_mut(&mut self, s: usize) -> &mut SubdomainOperator {
        &mut self.subs[s].op
    }

    /// Number of subdomains.
    pub fn n_subdomains(&self) -> usize {
        self.subs.len()
    }

    /// Whether this solver runs a coarse step.
    pub fn has_coarse(&self) -> bool {
        self.coarse.is_some()
    }

    /// Whether any interface exists (more than one subdomain).
    pub fn has_interfaces(&self) -> bool {
        !self.ifaces.is_empty()
    }

    /// Whether any subdomain needed a generalised inverse.
    pub fn has_kernels(&self) -> bool {
        self.stats.kernel_unknowns > 0
    }

    /// The automatic search direction is the paper's lumped choice
    /// `(X^D)⁻¹ = θ Σ_E B_Eᵀ diag(K_E) B_E`: each interface dof gets the
    /// stiffness of its own elements, so soft cables and stiff bars are each
    /// iterated at their own scale (a single scalar `d` must fit the softest
    /// direction and then crawls on the stiff ones). `θ = AUTO_D_FACTOR ·
    /// 2 / λ_max(M X_P)`, with `M = Σ B_Eᵀ diag(K_E) B_E` and `X_P` the
    /// interface operator with the coarse step inside, is a fixed fraction
    /// of the stability limit; `λ_max` comes from a power iteration on the
    /// same kernels as the solve.
    fn auto_search_direction(&mut self) -> Result<f64> {
        if self.ifaces.is_empty() {
            return Ok(1.0);
        }
        for s in self.subs.iter_mut() {
            s.b.iter_mut().for_each(|v| *v = 0.0);
            s.lambda.iter_mut().for_each(|v| *v = 0.0);
        }
        // Deterministic, non-degenerate start vector.
        for it in self.ifaces.iter_mut() {
            for (j, f) in it.force.iter_mut().enumerate() {
                *f = 1.0 + ((j * 7 + it.lo * 3 + it.hi) % 11) as f64 / 11.0;
            }
        }
        let mut lambda_max = 0.0;
        for _ in 0..POWER_ITERATIONS {
            let norm = self.ifaces.iter().map(|i| kernels::norm2(&i.force)).sum::<f64>().sqrt();
            if !(norm > 0.0) {
                break;
            }
            for it in self.ifaces.iter_mut() {
                it.force.iter_mut().for_each(|f| *f /= norm);
            }
            self.global_step(false);
            self.compute_jumps();
            // T x = −M J V(x): the force increment for d = −1, from zero.
            for it in self.ifaces.iter_mut() {
                it.force.iter_mut().for_each(|f| *f = 0.0);
            }
            self.force_stage(-1.0);
            lambda_max = self.ifaces.iter().map(|i| kernels::norm2(&i.force)).sum::<f64>().sqrt();
        }
        for it in self.ifaces.iter_mut() {
            it.force.iter_mut().for_each(|f| *f = 0.0);
        }
        if !lambda_max.is_finite() {
            return Err(Error::Numerical(
                "could not estimate the interface operator's spectrum for d".into(),
            ));
        }
        // When the macro space covers (nearly) all of the interface, the
        // projected operator vanishes and only round-off is left to iterate
        // on: cap d by the lumped interface stiffness, the scale of X⁻¹.
        let cap = 0.5;
        let d = if lambda_max > 0.0 {
            AUTO_D_FACTOR * 2.0 / lambda_max
        } else {
            cap
        };
        Ok(d.min(cap))
    }

    /// Solves for the external nodal forces `f_ext` (global dofs); a force
    /// on a dof shared by `m` subdomains is split equally between them. With
    /// `warm`, starts from the interface forces and slacks of the previous
    /// solve (load paths).
    pub fn solve(
        &mut self,
        f_ext: &[f64],
        warm: bool,
        progress: Option<&mut dyn FnMut(usize, f64)>,
    ) -> Result<DdOutcome> {
        if f_ext.len() != self.n_free {
            return Err(Error::input(
                "rhs",
                None,
                format!("has {} entries, expected {}", f_ext.len(), self.n_free),
            ));
        }
        let subs_dofs = &self.dof_maps;
        self.subs
            .par_iter_mut()
            .zip(subs_dofs.par_iter())
            .for_each(|(s, dofs)| {
                for (l, &d) in dofs.iter().enumerate() {
                    s.b[l] = f_ext[d] * s.inv_mult[l] + s.prestrain[l];
                }
            });
        self.iterate(warm, progress)
    }

    /// Solves for right-hand sides given per subdomain in local numbering
    /// (the algebraic level: each subdomain's share of the load).
    pub fn solve_local(
        &mut self,
        rhs: &[&[f64]],
        warm: bool,
        progress: Option<&mut dyn FnMut(usize, f64)>,
    ) -> Result<DdOutcome> {
        if rhs.len() != self.subs.len() {
            return Err(Error::input(
                "rhs",
                None,
                format!("{} subdomain vectors given, expected {}", rhs.len(), self.subs.len()),
            ));
        }
        for (i, (s, r)) in self.subs.iter().zip(rhs).enumerate() {
            if r.len() != s.b.len() {
                return Err(Error::input(
                    "rhs",
                    Some(i),
                    format!("has {} entries, subdomain {i} has {} dofs", r.len(), s.b.len()),
                ));
            }
        }
        self.subs.par_iter_mut().zip(rhs.par_iter()).for_each(|(s, r)| {
            for ((b, &x), &p) in s.b.iter_mut().zip(r.iter()).zip(&s.prestrain) {
                *b = x + p;
            }
        });
        self.iterate(warm, progress)
    }

    fn iterate(&mut self, warm: bool, mut progress: Option<&mut dyn FnMut(usize, f64)>) -> Result<DdOutcome> {
        if self.opts.krylov {
            return self.iterate_cg(warm, progress);
        }
        let t0 = Instant::now();
        if !warm {
            self.reset_unknowns();
        }
        let has_cables = self.n_cables > 0;
        let b_norm = self.load_norm();
        let mut history = Vec::with_capacity(self.opts.max_iterations.min(100_000));
        self.global_step(has_cables);
        self.compute_jumps();
        let mut best = f64::INFINITY;
        let mut converged = false;
        let mut iterations = 0;
        let auto_d = matches!(self.opts.search_direction, SearchDirection::Auto);
        let mut restarts = 0;
        // Iteration count at the last restart (history entries after it count).
        let mut restart_at = 0;
        // One subdomain without cables: the first global step is exact.
        if self.ifaces.is_empty() && !has_cables {
            converged = true;
            history.push(HistoryEntry {
                iteration: 0,
                time_s: t0.elapsed().as_secs_f64(),
                indicator: 0.0,
                jump: None,
                cable_change: None,
            });
        }
        while !converged && iterations < self.opts.max_iterations {
            iterations += 1;
            // Local stage.
            self.force_stage(self.d);
            if has_cables {
                self.subs.par_iter_mut().for_each(|s| {
                    cable_elongations(s);
                    (s.dlambda2, s.dforce2) = kernels::cable_projection(&mut s.lambda, &s.elong, &s.e0, &s.kc);
                });
            }
            // Global step and coarse step.
            self.global_step(has_cables);
            self.compute_jumps();
            let v2: f64 = self.subs.iter().map(|s| s.v_norm2).sum();
            let vn = v2.sqrt().max(f64::MIN_POSITIVE);
            let jump = self.ifaces.iter().map(|i| i.jump_norm2).sum::<f64>().sqrt() / vn;
            let force_scale = self.force_scale(b_norm);
            let force = self.ifaces.iter().map(|i| i.force_norm2).sum::<f64>().sqrt() / force_scale;
            let jump = jump.max(force);
            let cable = if has_cables {
                let length = self.subs.iter().map(|s| s.dlambda2).sum::<f64>().sqrt() / vn;
                let force = self.subs.iter().map(|s| s.dforce2).sum::<f64>().sqrt() / force_scale;
                Some(length.max(force))
            } else {
                None
            };
            let indicator = jump.max(cable.unwrap_or(0.0));
            history.push(HistoryEntry {
                iteration: iterations,
                time_s: t0.elapsed().as_secs_f64(),
                indicator,
                jump: if self.ifaces.is_empty() { None } else { Some(jump) },
                cable_change: cable,
            });
            if let Some(p) = progress.as_mut() {
                p(iterations, indicator);
            }
            let blew_up = !indicator.is_finite()
                || !v2.is_finite()
                || (indicator > DIVERGENCE_GROWTH * best && iterations > restart_at + 10);
            if blew_up && auto_d && restarts < MAX_D_RESTARTS {
                // The automatic d rests on an estimate of λ_max from below;
                // when it proves too large, halve it and start again.
                restarts += 1;
                self.d *= 0.5;
                self.stats.search_direction = self.d;
                self.reset_unknowns();
                self.global_step(has_cables);
                self.compute_jumps();
                best = f64::INFINITY;
                restart_at = iterations;
                continue;
            }
            if !indicator.is_finite() || !v2.is_finite() {
                return Err(Error::Diverged {
                    iteration: iterations,
                    message: "the iterate is no longer finite (NaN or Inf); lower the search direction d".into(),
                });
            }
            if indicator > DIVERGENCE_GROWTH * best && iterations > restart_at + 10 {
                return Err(Error::Diverged {
                    iteration: iterations,
                    message: format!(
                        "the indicator grew from {best:.3e} to {indicator:.3e}; the search direction d = {:.3e} is too large",
                        self.d
                    ),
                });
            }
            best = best.min(indicator);
            let recent = &history[history.len() - (iterations - restart_at)..];
            converged = indicator <= self.opts.tolerance
                && (indicator * stopping_factor(recent) <= self.opts.tolerance || stalled(recent));
        }
        let (u, lambda) = self.assemble();
        Ok(DdOutcome {
            u,
            lambda,
            converged,
            iterations,
            history,
        })
    }

    /// `r = b − C Bᵀ F − H k λ`, `y = K⁺ r`, coarse step, `V = y − Z f + R α`.
    fn global_step(&mut self, with_cables: bool) {
        self.global_step_with(with_cables, true);
    }

    /// The global step; without `load`, for the interface forces alone
    /// (`b = 0`: the homogeneous problem of the CG operator).
    fn global_step_with(&mut self, with_cables: bool, load: bool) {
        let ifaces = &self.ifaces;
        self.subs.par_iter_mut().for_each(|s| {
            if load {
                s.r.copy_from_slice(&s.b);
            } else {
                s.r.iter_mut().for_each(|v| *v = 0.0);
            }
            for &(i, is_lo) in &s.ifaces {
                let it = &ifaces[i];
                let (side, coef) = if is_lo { (Side::Lo, -1.0) } else { (Side::Hi, 1.0) };
                kernels::scatter_add_runs(&mut s.r, side, &it.runs, &it.force, coef);
            }
            if with_cables {
                for (c, &lam) in s.cables.iter().zip(&s.lambda) {
                    if lam != 0.0 {
                        c.add_to(-c.k * lam, &mut s.r);
                    }
                }
            }
            s.y.copy_from_slice(&s.r);
            s.op.solve_in_place(&mut s.y);
        });
        if let Some(coarse) = self.coarse.as_mut() {
            let subs = &self.subs;
            self.ifaces.par_iter_mut().for_each(|it| {
                kernels::jump_runs(&mut it.jump, &subs[it.lo].y, &subs[it.hi].y, &it.runs);
                let m = it.p.ncols();
                for q in 0..m {
                    let col = it.p.col(q);
                    it.pt[q] = col.iter().zip(&it.jump).map(|(a, b)| a * b).sum();
                }
            });
            for it in &self.ifaces {
                coarse.rhs[it.macro_off..it.macro_off + it.pt.len()].copy_from_slice(&it.pt);
            }
            self.subs.par_iter_mut().for_each(|s| {
                let r = s.op.kernel();
                for q in 0..r.ncols() {
                    s.rt_r[q] = r.col(q).iter().zip(&s.r).map(|(a, b)| a * b).sum();
                }
            });
            let nf = coarse.n_macro;
            for s in &self.subs {
                coarse.rhs[nf + s.alpha_off..nf + s.alpha_off + s.rt_r.len()].copy_from_slice(&s.rt_r);
            }
            coarse.solve();
            let coarse = &*coarse;
            self.subs.par_iter_mut().for_each(|s| {
                let f = coarse.macro_forces();
                for (k, &c) in s.macro_cols.iter().enumerate() {
                    s.fm[k] = f[c];
                }
                let na = s.alpha.len();
                s.alpha
                    .copy_from_slice(&coarse.kernel_amplitudes()[s.alpha_off..s.alpha_off + na]);
                s.v.copy_from_slice(&s.y);
                for (k, &fk) in s.fm.iter().enumerate() {
                    if fk != 0.0 {
                        for (v, z) in s.v.iter_mut().zip(s.z.col(k).iter()) {
                            *v -= z * fk;
                        }
                    }
                }
                let r = s.op.kernel();
                for (q, &a) in s.alpha.iter().enumerate() {
                    for (v, rq) in s.v.iter_mut().zip(r.col(q).iter()) {
                        *v += rq * a;
                    }
                }
                s.v_norm2 = kernels::norm2(&s.v);
            });
        } else {
            self.subs.par_iter_mut().for_each(|s| {
                s.v.copy_from_slice(&s.y);
                s.v_norm2 = kernels::norm2(&s.v);
            });
        }
    }

    /// Zero interface forces and cable slacks: a cold start.
    fn reset_unknowns(&mut self) {
        for s in self.subs.iter_mut() {
            s.lambda.iter_mut().for_each(|v| *v = 0.0);
        }
        for it in self.ifaces.iter_mut() {
            it.force.iter_mut().for_each(|f| *f = 0.0);
        }
    }

    /// The force scale of the indicators: the larger of the load norm and
    /// the norm of the interface forces. The unbalanced force a jump leaves
    /// (`k ∘ J V`) is an error in the tensions of the elements at the cut,
    /// so it is measured against the forces the structure carries there;
    /// on large soft plates those are 10³–10⁴ × the load, and against the
    /// load alone the indicator stalled at 3e-4 on its round-off floor while
    /// the true error was 1e-8 (300 × 300 grid, 64 subdomains).
    fn force_scale(&self, b_norm: f64) -> f64 {
        let f2: f64 = self.ifaces.iter().map(|it| kernels::norm2(&it.force)).sum();
        b_norm.max(f2.sqrt()).max(f64::MIN_POSITIVE)
    }

    /// Norm of the assembled right-hand side (loads and prestrain).
    fn load_norm(&self) -> f64 {
        let mut b_global = vec![0.0; self.n_free];
        for (s, dofs) in self.subs.iter().zip(&self.dof_maps) {
            for (l, &d) in dofs.iter().enumerate() {
                b_global[d] += s.b[l];
            }
        }
        kernels::norm2(&b_global).sqrt()
    }

    /// Conjugate gradient on the interface problem (DESIGN.md §5, the
    /// paper's outlook), linear case. With `S(F) = F + P f(F)` the forces
    /// after the coarse step, the operator `A F = −J V_hom(F)` satisfies
    /// `⟨F₂, A F₁⟩ = S₂ᵀ 𝔽 S₁` (`𝔽 = Σ B K⁺ Bᵀ`, `Gᵀ S = 0`), so it is
    /// symmetric positive semi-definite and CG applies; the preconditioner
    /// is `Σ_E B_E S_E B_Eᵀ` (Dirichlet) or `Σ_E B_E K_E B_Eᵀ` (lumped), see
    /// [`Self::precondition`]. One homogeneous global step (one solve per
    /// subdomain and one coarse solve) per iteration, plus one interior
    /// solve per subdomain with the Dirichlet choice; the displacement is updated by linearity, so
    /// no solve is added at the end. No allocation per iteration.
    fn iterate_cg(&mut self, warm: bool, mut progress: Option<&mut dyn FnMut(usize, f64)>) -> Result<DdOutcome> {
        let t0 = Instant::now();
        if !warm {
            self.reset_unknowns();
        }
        let b_norm = self.load_norm().max(f64::MIN_POSITIVE);
        let mut history = Vec::with_capacity(self.opts.max_iterations.min(100_000));
        let mut rz = self.cg_start();
        let mut converged = self.ifaces.is_empty() || self.cg_indicator(b_norm) == 0.0;
        if converged {
            history.push(HistoryEntry {
                iteration: 0,
                time_s: t0.elapsed().as_secs_f64(),
                indicator: 0.0,
                jump: None,
                cable_change: None,
            });
        }
        let mut iterations = 0;
        let (mut best, mut restarts, mut restart_at) = (f64::INFINITY, 0, 0);
        let mut energy_terms = CgStopping::default();
        while !converged && iterations < self.opts.max_iterations {
            iterations += 1;
            // q = A p = −J V_hom(p): the homogeneous global step with F = p.
            for it in self.ifaces.iter_mut() {
                std::mem::swap(&mut it.force, &mut it.cg_p);
            }
            self.global_step_with(false, false);
            self.compute_jumps();
            for it in self.ifaces.iter_mut() {
                std::mem::swap(&mut it.force, &mut it.cg_p);
            }
            let pq = -self.iface_dot(|it| (&it.cg_p, &it.jump));
            if !(pq > 0.0) || !rz.is_finite() {
                // The operator is positive semi-definite by construction
                // (indefinite subdomains are refused at set-up), so pᵀAp ≤ 0
                // is round-off: the direction lies in its null space and CG
                // cannot reduce the residual further (e.g. the macro space
                // covers the whole interface). Stop, with the indicator
                // re-measured on the iterate deciding `converged`; only a
                // non-finite value is an error.
                if !rz.is_finite() || !pq.is_finite() {
                    return Err(Error::Diverged {
                        iteration: iterations,
                        message: "the iterate is no longer finite (NaN or Inf)".into(),
                    });
                }
                let indicator = self.cg_indicator(b_norm);
                history.push(HistoryEntry {
                    iteration: iterations,
                    time_s: t0.elapsed().as_secs_f64(),
                    indicator,
                    jump: Some(indicator),
                    cable_change: None,
                });
                converged = indicator <= self.opts.tolerance;
                break;
            }
            let a = rz / pq;
            energy_terms.push(a * rz);
            // F += a p, r −= a q (q = −jump), V += a V_hom.
            self.ifaces.par_iter_mut().for_each(|it| {
                for ((f, r), (&p, &j)) in it
                    .force
                    .iter_mut()
                    .zip(it.cg_r.iter_mut())
                    .zip(it.cg_p.iter().zip(&it.jump))
                {
                    *f += a * p;
                    *r += a * j;
                }
            });
            self.subs.par_iter_mut().for_each(|s| {
                for (v, &h) in s.cg_v.iter_mut().zip(&s.v) {
                    *v += a * h;
                }
            });
            let indicator = self.cg_indicator(b_norm);
            history.push(HistoryEntry {
                iteration: iterations,
                time_s: t0.elapsed().as_secs_f64(),
                indicator,
                jump: Some(indicator),
                cable_change: None,
            });
            if let Some(p) = progress.as_mut() {
                p(iterations, indicator);
            }
            if !indicator.is_finite() {
                return Err(Error::Diverged {
                    iteration: iterations,
                    message: "the iterate is no longer finite (NaN or Inf)".into(),
                });
            }
            // Stop when the energy error estimate from the CG coefficients
            // is certified (crate::cg_stopping, computed only once the
            // indicator is close); or, with the indicator itself below the
            // tolerance, once restarts or a stall show the residual is on
            // the floor that round-off allows (it cannot fall further).
            let tol = self.opts.tolerance;
            converged = cg_stopping::indicator_allows(indicator, tol) && {
                let (jump_energy, load_energy) = self.cg_energies();
                energy_terms.tail().is_some_and(|tail| {
                    cg_stopping::certified(cg_stopping::relative_energy_error(jump_energy, tail, load_energy), tol)
                })
            };
            converged = converged
                || (indicator <= tol
                    && (restarts >= 2 || stalled(&history[history.len() - (iterations - restart_at)..])));
            if converged {
                break;
            }
            if indicator > CG_RESTART_GROWTH * best {
                if restarts == CG_MAX_RESTARTS {
                    break;
                }
                // The recurrences have drifted from the true operator (the
                // coarse solve is exact only to round-off, and the residual
                // fell by many orders): recompute V(F) and the residual from
                // the forces and restart from the steepest direction.
                restarts += 1;
                restart_at = iterations;
                energy_terms.reset();
                rz = self.cg_start();
                best = f64::INFINITY;
                continue;
            }
            best = best.min(indicator);
            self.precondition();
            let rz_new = self.iface_dot(|it| (&it.cg_r, &it.cg_z));
            let beta = rz_new / rz;
            rz = rz_new;
            self.ifaces.par_iter_mut().for_each(|it| {
                for (p, &z) in it.cg_p.iter_mut().zip(&it.cg_z) {
                    *p = z + beta * *p;
                }
            });
        }
        for s in self.subs.iter_mut() {
            s.v.copy_from_slice(&s.cg_v);
        }
        let (u, lambda) = self.assemble();
        Ok(DdOutcome {
            u,
            lambda,
            converged,
            iterations,
            history,
        })
    }

    /// `out = A p = −J V_hom(p)`, the CG operator on the interface vector
    /// (interfaces one after the other): for tests of its symmetry.
    #[doc(hidden)]
    pub fn apply_interface_operator(&mut self, p: &[f64], out: &mut [f64]) {
        let mut off = 0;
        for it in self.ifaces.iter_mut() {
            let n = it.force.len();
            std::mem::swap(&mut it.force, &mut it.cg_p);
            it.force.clear();
            it.force.extend_from_slice(&p[off..off + n]);
            off += n;
        }
        self.global_step_with(false, false);
        self.compute_jumps();
        let mut off = 0;
        for it in self.ifaces.iter_mut() {
            let n = it.force.len();
            for (o, j) in out[off..off + n].iter_mut().zip(&it.jump) {
                *o = -j;
            }
            off += n;
            std::mem::swap(&mut it.force, &mut it.cg_p);
        }
    }

    /// (Re)starts CG from the current forces: `V = V(F)` by a global step,
    /// `r = J V`, `z = M r`, `p = z`. Returns `⟨r, z⟩`.
    fn cg_start(&mut self) -> f64 {
        self.global_step(false);
        self.compute_jumps();
        for s in self.subs.iter_mut() {
            s.cg_v.copy_from_slice(&s.v);
        }
        for it in self.ifaces.iter_mut() {
            it.cg_r.copy_from_slice(&it.jump);
        }
        self.precondition();
        for it in self.ifaces.iter_mut() {
            it.cg_p.copy_from_slice(&it.cg_z);
        }
        self.iface_dot(|it| (&it.cg_r, &it.cg_z))
    }

    /// The indicator of the CG iterate (`cg_v`): the true jump `J V`, as a
    /// length and as a force (see `iterate`). Leaves `jump` = `J V`.
    fn cg_indicator(&mut self, b_norm: f64) -> f64 {
        for s in self.subs.iter_mut() {
            std::mem::swap(&mut s.v, &mut s.cg_v);
        }
        self.compute_jumps();
        let v2: f64 = self.subs.iter().map(|s| kernels::norm2(&s.v)).sum();
        for s in self.subs.iter_mut() {
            std::mem::swap(&mut s.v, &mut s.cg_v);
        }
        let vn = v2.sqrt().max(f64::MIN_POSITIVE);
        let jump = self.ifaces.iter().map(|i| i.jump_norm2).sum::<f64>().sqrt() / vn;
        let force = self.ifaces.iter().map(|i| i.force_norm2).sum::<f64>().sqrt() / self.force_scale(b_norm);
        if v2.is_finite() {
            jump.max(force)
        } else {
            f64::NAN
        }
    }

    /// The energies of the CG stopping test ([`crate::cg_stopping`]) for
    /// the iterate `cg_v`, with `jump` = `J cg_v` (as [`Self::cg_indicator`]
    /// leaves it): `J = Σ_E (ū_E − v_E)ᵀ K_E (ū_E − v_E)`, the strain energy
    /// that averaging the copies adds (`ū − v_E` at a dof of multiplicity
    /// `m` is `1/m` of the signed sum of its pair jumps), and `E = Σ_E b_Eᵀ
    /// v_E`, the work of the loads (`‖u*‖_K²` at convergence). One product
    /// with `K_E` per subdomain; no allocation.
    fn cg_energies(&mut self) -> (f64, f64) {
        let ifaces = &self.ifaces;
        self.subs.par_iter_mut().for_each(|s| {
            for &(i, is_lo) in &s.ifaces {
                let it = &ifaces[i];
                let (side, coef) = if is_lo { (Side::Lo, -1.0) } else { (Side::Hi, 1.0) };
                kernels::scatter_add_runs(&mut s.g, side, &it.runs, &it.jump, coef);
            }
            for &l in &s.iface_dofs {
                s.g[l as usize] *= s.inv_mult[l as usize];
            }
            s.op.apply(&s.g, &mut s.r);
            let j: f64 = s.iface_dofs.iter().map(|&l| s.g[l as usize] * s.r[l as usize]).sum();
            for &l in &s.iface_dofs {
                s.g[l as usize] = 0.0;
            }
            let e: f64 = s.b.iter().zip(&s.cg_v).map(|(b, v)| b * v).sum();
            s.cg_energy = (j, e);
        });
        // Summed serially in subdomain order (thread-count independent).
        let (j, e) = self
            .subs
            .iter()
            .fold((0.0, 0.0), |(a, b), s| (a + s.cg_energy.0, b + s.cg_energy.1));
        (j, e)
    }

    /// `z = (I − P Pᵀ) Σ_E B_E S_E B_Eᵀ r` with `S_E` the Schur complement
    /// of the subdomain on its interface (Dirichlet: the interface force
    /// that holds the displacement `Bᵀr` with the interior free), or `K_E`
    /// itself on the interface dofs (lumped: interior held at zero), then
    /// the macro part removed. `range(P)` is in the null space of the CG operator (the
    /// coarse step absorbs it); leaving it in `z` lets round-off grow there
    /// and break the iteration on long runs.
    fn precondition(&mut self) {
        let ifaces = &self.ifaces;
        self.subs.par_iter_mut().for_each(|s| {
            for &(i, is_lo) in &s.ifaces {
                let it = &ifaces[i];
                let (side, coef, w) = if is_lo {
                    (Side::Lo, 1.0, &it.w.lo)
                } else {
                    (Side::Hi, -1.0, &it.w.hi)
                };
                scaling::scatter_add_scaled_runs(&mut s.g, side, &it.runs, &it.cg_r, w, coef);
            }
            // s.r is free between global steps: K_E B_Eᵀ r (lumped) or
            // S_E B_Eᵀ r (Dirichlet) goes there.
            match s.interior.as_mut() {
                Some(ip) => ip.apply_schur(&s.op, &mut s.g, &mut s.r),
                None => s.op.apply(&s.g, &mut s.r),
            }
            for &l in &s.iface_dofs {
                s.g[l as usize] = 0.0;
            }
        });
        let subs = &self.subs;
        self.ifaces.par_iter_mut().for_each(|it| {
            scaling::scaled_jump_runs(
                &mut it.cg_z,
                &subs[it.lo].r,
                &it.w.lo,
                &subs[it.hi].r,
                &it.w.hi,
                &it.runs,
            );
        });
        // Circulations of the redundant pair forces at cross points (zero
        // net force on every subdomain) are null directions too: project z
        // onto the differences of subdomain forces, `z ← (B_lo z − B_hi z)/m`
        // per dof of multiplicity m (the identity where m = 2).
        let ifaces = &self.ifaces;
        self.subs.par_iter_mut().for_each(|s| {
            for &(i, is_lo) in &s.ifaces {
                let it = &ifaces[i];
                let (side, coef) = if is_lo { (Side::Lo, 1.0) } else { (Side::Hi, -1.0) };
                kernels::scatter_add_runs(&mut s.g, side, &it.runs, &it.cg_z, coef);
            }
        });
        let subs = &self.subs;
        self.ifaces.par_iter_mut().for_each(|it| {
            let (lo, hi) = (&subs[it.lo], &subs[it.hi]);
            for ((z, &a), &b) in it.cg_z.iter_mut().zip(&it.lo_idx).zip(&it.hi_idx) {
                *z = (lo.g[a as usize] - hi.g[b as usize]) * lo.inv_mult[a as usize];
            }
            for q in 0..it.p.ncols() {
                let col = it.p.col(q);
                let c: f64 = col.iter().zip(&it.cg_z).map(|(a, b)| a * b).sum();
                for (z, a) in it.cg_z.iter_mut().zip(col.iter()) {
                    *z -= c * a;
                }
            }
        });
        self.subs.par_iter_mut().for_each(|s| {
            for &l in &s.iface_dofs {
                s.g[l as usize] = 0.0;
            }
        });
    }

    /// `Σ_Γ ⟨x_Γ, y_Γ⟩` over the interfaces, summed in interface order.
    fn iface_dot(&self, pick: impl Fn(&IfaceState) -> (&Vec<f64>, &Vec<f64>)) -> f64 {
        self.ifaces
            .iter()
            .map(|it| {
                let (x, y) = pick(it);
                x.iter().zip(y).map(|(a, b)| a * b).sum::<f64>()
            })
            .sum()
    }

    /// `jump = J V` on every interface.
    fn compute_jumps(&mut self) {
        let subs = &self.subs;
        self.ifaces.par_iter_mut().for_each(|it| {
            kernels::jump_runs(&mut it.jump, &subs[it.lo].v, &subs[it.hi].v, &it.runs);
            it.jump_norm2 = kernels::norm2(&it.jump);
            it.force_norm2 = it.jump.iter().zip(&it.stiffness).map(|(j, k)| (j * k) * (j * k)).sum();
        });
    }

    /// `F += d Σ_E B_Eᵀ D_E B_E jump` (cross points couple their pair
    /// entries); `D_E` is the identity for a scalar `d` and `diag(K_E)` for
    /// the lumped search direction (the paper's "lumped" `X^D`).
    fn force_stage(&mut self, d: f64) {
        let ifaces = &self.ifaces;
        self.subs.par_iter_mut().for_each(|s| {
            for &(i, is_lo) in &s.ifaces {
                let it = &ifaces[i];
                let (side, coef) = if is_lo { (Side::Lo, 1.0) } else { (Side::Hi, -1.0) };
                kernels::scatter_add_runs(&mut s.g, side, &it.runs, &it.jump, coef);
            }
            for &l in &s.iface_dofs {
                s.g[l as usize] *= s.weight[l as usize];
            }
        });
        let subs = &self.subs;
        self.ifaces.par_iter_mut().for_each(|it| {
            kernels::force_update_runs(&mut it.force, d, &subs[it.lo].g, &subs[it.hi].g, &it.runs);
        });
        self.subs.par_iter_mut().for_each(|s| {
            for &l in &s.iface_dofs {
                s.g[l as usize] = 0.0;
            }
        });
    }

    /// Global displacement (average of the subdomain copies) and slacks.
    fn assemble(&self) -> (Vec<f64>, Vec<f64>) {
        let mut u = vec![0.0; self.n_free];
        let mut lambda = vec![0.0; self.n_cables];
        for (s, dofs) in self.subs.iter().zip(&self.dof_maps) {
            for (l, &d) in dofs.iter().enumerate() {
                u[d] += s.v[l] * s.inv_mult[l];
            }
            for (c, &lam) in s.cables.iter().zip(&s.lambda) {
                lambda[c.cable] = lam;
            }
        }
        (u, lambda)
    }
}

fn cable_elongations(s: &mut SubState) {
    for (c, e) in s.cables.iter().zip(s.elong.iter_mut()) {
        *e = c.elongation(&s.v);
    }
}
