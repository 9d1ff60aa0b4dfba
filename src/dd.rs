//! The seed's multilevel domain decomposition iteration (docs/design.md §5, the
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
//! This module is the set-up ([`DdSolver`]); the operations of an
//! iteration are the interface operator's ([`crate::operator`]), and the
//! ones that cross subdomains go through [`crate::comm`]. Everything per
//! subdomain runs in parallel with rayon; reductions are summed serially
//! in subdomain or interface order, so results do not depend on the number
//! of threads. Scratch is allocated at set-up: the iteration loop does not
//! allocate.

use crate::adaptive;
use crate::coarse::{CoarseContribution, CoarseProblem, MacroBasis};
use crate::comm::{Communicator, Placement, Seam};
use crate::decomposition::Decomposition;
use crate::error::{Error, Result};
use crate::factor::OrderingKind;
use crate::kernels::{self, Run};
use crate::method::cg::{BlockSource, CgWorkspace, DeluxeLayout, Preconditioning};
pub use crate::method::stopping::{stalled, stopping_factor, CONTRACTION_CAP, CONTRACTION_WINDOW};
use crate::method::{on_workers, Progress};
use crate::model::{Model, FIXED};
use crate::operator::InterfaceOperator;
use crate::outcome::{Outcome, Refinement, Status};
use crate::scaling::{Edges, InterfaceEntries, InterfaceScaling};
use crate::settings::{
    AdaptiveEdges, AdaptiveThreshold, MacroDegree, MethodConfig, OrderingChoice, Preconditioner, SearchDirection,
    SolverSettings,
};
use crate::subdomain::{InteriorProblem, SubdomainOperator};
use faer::Mat;
use rayon::prelude::*;
use std::collections::HashMap;
use std::time::Instant;

/// Settings of the iterative methods: [`SolverSettings`] with the method
/// already turned into its configuration ([`DdOptions::from_settings`]).
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
    /// Weights of the CG preconditioner's scaled jump operator
    /// ([`crate::scaling`]; ignored by the stationary iteration).
    pub interface_scaling: InterfaceScaling,
    /// Eigenvalue threshold of the adaptive macro columns
    /// ([`crate::adaptive`]); `Auto` is resolved from the model's element
    /// stiffnesses at set-up (off for an algebraic problem).
    pub adaptive_threshold: AdaptiveThreshold,
    /// Adaptive constraints on the edges too ([`crate::adaptive`]); `Auto`
    /// is resolved from the model's element stiffnesses at set-up (off for
    /// an algebraic problem).
    pub adaptive_edges: AdaptiveEdges,
    /// Degree of the polynomial fields of each interface's macro basis;
    /// `Auto` is resolved at set-up from the dof points' flatness and
    /// whether the adaptive space is on ([`MacroDegree`]).
    pub macro_degree: MacroDegree,
    /// Fill-reducing ordering of the subdomain and interior factors.
    pub ordering: OrderingChoice,
}

impl DdOptions {
    /// The options of a domain-decomposition method from the settings
    /// (validated here); the direct method is refused.
    pub fn from_settings(s: &SolverSettings) -> Result<DdOptions> {
        s.validate()?;
        let MethodConfig { coarse, krylov } = s.method.config().ok_or_else(|| {
            Error::MethodNotApplicable(format!(
                "domain decomposition runs monolevel, multilevel or cg, not {}",
                s.method.name()
            ))
        })?;
        Ok(DdOptions {
            coarse,
            krylov,
            tolerance: s.tolerance,
            max_iterations: s.max_iterations,
            search_direction: s.search_direction,
            preconditioner: s.preconditioner,
            interface_scaling: s.interface_scaling,
            adaptive_threshold: s.adaptive_threshold,
            adaptive_edges: s.adaptive_edges,
            macro_degree: s.macro_degree,
            ordering: s.ordering,
        })
    }
}

/// Fraction of the stability limit `2 / λ_max` used by the automatic `d`.
pub const AUTO_D_FACTOR: f64 = 0.6;

/// Power iterations used to estimate `λ_max` for the automatic `d`.
const POWER_ITERATIONS: usize = 30;

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
    pub(crate) fn elongation(&self, v: &[f64]) -> f64 {
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
    pub(crate) fn add_to(&self, coef: f64, out: &mut [f64]) {
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
///
/// `operators` and `loads` are those of the subdomains this process owns
/// (`placement.owned(decomposition.len())`, in order): all of them with
/// [`Placement::Process`], a rank's block under MPI.
pub struct DdProblem<'a> {
    pub decomposition: &'a Decomposition,
    pub operators: Vec<SubdomainOperator>,
    pub loads: Vec<SubdomainLoad>,
    /// Where the subdomains live.
    pub placement: Placement,
    /// Point and component (0..3) of each global dof.
    pub dof_points: Vec<([f64; 3], usize)>,
    pub n_cables: usize,
}

impl<'a> DdProblem<'a> {
    /// Builds the algebraic problem of a truss model (factors every
    /// subdomain in parallel).
    pub fn from_model(model: &Model, dec: &'a Decomposition) -> Result<DdProblem<'a>> {
        Self::from_model_reusing(model, dec, Vec::new(), Placement::Process, OrderingChoice::Auto)
    }

    /// [`Self::from_model`], taking `reused[s]` (when `Some`) as subdomain
    /// `s`'s operator instead of factoring it: an operator of an earlier
    /// set-up whose subdomain had the same elements (same stiffness) and
    /// the same local dof layout, which the caller vouches for (the
    /// nonsmooth CG refactors only the subdomains whose slack cables
    /// changed). Missing entries are factored. Only the subdomains
    /// `placement` gives this process are factored (`reused` is indexed by
    /// their position in that block); a failure on any process is returned
    /// on every process. `ordering` is the factors' fill-reducing ordering.
    pub fn from_model_reusing(
        model: &Model,
        dec: &'a Decomposition,
        mut reused: Vec<Option<SubdomainOperator>>,
        placement: Placement,
        ordering: OrderingChoice,
    ) -> Result<DdProblem<'a>> {
        let owned = placement.owned(dec.len());
        reused.resize_with(owned.len(), || None);
        let ops: Vec<Result<SubdomainOperator>> = dec.subdomains[owned.clone()]
            .par_iter()
            .zip(reused.into_par_iter())
            .enumerate()
            .map(|(k, (sd, op))| {
                let i = owned.start + k;
                match op {
                    Some(mut op) if op.n() == sd.dofs.len() => {
                        op.id = i;
                        Ok(op)
                    }
                    _ => SubdomainOperator::new(i, model, sd, 64, ordering),
                }
            })
            .collect();
        let operators = placement.agree(ops.into_iter().collect::<Result<Vec<_>>>())?;
        let loads = dec.subdomains[owned]
            .par_iter()
            .map(|sd| {
                let n = sd.dofs.len();
                let mut constant = vec![0.0; n];
                let mut cables = Vec::new();
                sd.with_numbering(model.n_free, |numbering| {
                    let local = |d: usize| {
                        if d == FIXED {
                            NO_DOF
                        } else {
                            numbering.get(d).map_or(NO_DOF, |l| l as u32)
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
                });
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
            placement,
            dof_points,
            n_cables: model.cables.len(),
        })
    }
}

pub(crate) struct SubState {
    pub(crate) op: SubdomainOperator,
    /// `(interface, is_lo)` for every interface of this subdomain.
    pub(crate) ifaces: Vec<(usize, bool)>,
    pub(crate) inv_mult: Vec<f64>,
    /// Constant local load (prestrain).
    pub(crate) prestrain: Vec<f64>,
    pub(crate) b: Vec<f64>,
    pub(crate) r: Vec<f64>,
    pub(crate) y: Vec<f64>,
    pub(crate) v: Vec<f64>,
    pub(crate) g: Vec<f64>,
    /// Interface dofs of this subdomain (local, unique, increasing).
    pub(crate) iface_dofs: Vec<u32>,
    /// Search-direction weight per local dof: 1 for a scalar `d`, the
    /// diagonal of `K_E` for the lumped choice.
    pub(crate) weight: Vec<f64>,
    /// `Z_E = K_E⁺ W_E` (`n × m_E`) and the global macro index of each column.
    pub(crate) z: MacroResponses,
    pub(crate) macro_cols: Vec<usize>,
    /// The rows of `Z_E` at `iface_dofs`, and the non-zeros of `W_E`
    /// (which is zero off those dofs): the coarse right-hand side and the
    /// macro forces of a homogeneous global step
    /// ([`crate::operator::InterfaceOperator`]).
    pub(crate) z_iface: Mat<f64>,
    pub(crate) w_cols: SparseColumns,
    /// Scratch of `iface_dofs`' length, and this subdomain's part of the
    /// macro right-hand side (one entry per macro column).
    pub(crate) rb: Vec<f64>,
    pub(crate) zt_r: Vec<f64>,
    pub(crate) fm: Vec<f64>,
    pub(crate) alpha_off: usize,
    pub(crate) alpha: Vec<f64>,
    pub(crate) rt_r: Vec<f64>,
    pub(crate) cables: Vec<CableColumn>,
    pub(crate) lambda: Vec<f64>,
    pub(crate) elong: Vec<f64>,
    pub(crate) e0: Vec<f64>,
    // per-iteration reductions
    pub(crate) v_norm2: f64,
    pub(crate) dlambda2: f64,
    pub(crate) dforce2: f64,
    /// Stiffness of each cable.
    pub(crate) kc: Vec<f64>,
    /// Factored interior problem for the Dirichlet preconditioner of CG.
    pub(crate) interior: Option<InteriorProblem>,
    /// Schur-complement face blocks of the deluxe weights by face rows,
    /// kept for a later set-up that takes this subdomain over
    /// ([`DdSolver::new_pooled`]); `None`: not kept.
    pub(crate) face_blocks: Option<Vec<FaceBlock>>,
    /// The adaptive blocks and face constraints, kept the same way.
    pub(crate) side_cache: Option<adaptive::SideCache>,
    /// What `z` and this subdomain's coarse contribution were computed
    /// from, kept for a later set-up; `None`: not kept.
    pub(crate) coarse_kept: Option<CoarseBlocks>,
}

/// The non-zeros of a matrix with few per column, by column: `W_E`, whose
/// column for a macro unknown of interface `i` lives on that interface's
/// dofs only (a dense `|interface dofs of E| × m_E` block multiplied
/// mostly zeros: 7 % of the solve of the 30³ tower at contrast 1e4 with 16
/// subdomains, where `m_E` is in the hundreds).
#[derive(Debug, Clone, Default)]
pub(crate) struct SparseColumns {
    start: Vec<usize>,
    row: Vec<u32>,
    value: Vec<f64>,
}

impl SparseColumns {
    /// The non-zeros of `dense`, whose row `i` is local dof `rows[i]`.
    pub(crate) fn from_dense(rows: &[u32], dense: &Mat<f64>) -> SparseColumns {
        let mut out = SparseColumns {
            start: Vec::with_capacity(dense.ncols() + 1),
            ..SparseColumns::default()
        };
        out.start.push(0);
        for j in 0..dense.ncols() {
            for (&l, &v) in rows.iter().zip(dense.col(j).iter()) {
                if v != 0.0 {
                    out.row.push(l);
                    out.value.push(v);
                }
            }
            out.start.push(out.row.len());
        }
        out
    }

    /// Column `k` as (local dof, value), rows increasing.
    #[inline]
    pub(crate) fn col(&self, k: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        let range = self.start[k]..self.start[k + 1];
        self.row[range.clone()]
            .iter()
            .zip(&self.value[range])
            .map(|(&l, &v)| (l as usize, v))
    }
}

/// A subdomain's coarse block `L_E = W_Eᵀ Z_E` and the
/// columns `W_E` it came from, on its interface dofs `rows` (`W_E` is zero
/// elsewhere). A later set-up of the same operator whose `W_E` is equal
/// takes it, and `Z_E`, over instead of solving again: in the nonsmooth
/// CG's last steps most subdomains keep their operator, and their
/// neighbours' kernels, and so their macro columns.
pub(crate) struct CoarseBlocks {
    rows: Vec<u32>,
    w: Mat<f64>,
    l: Mat<f64>,
}

/// Copies into `z` (column-major, `n` rows per column) the column of
/// `z_old` kept for each column of `w` equal bit for bit to a column of
/// `w_old` (the interface rows of `W_E`, same rows), and returns the
/// columns left to solve, in increasing order. Set-up only (allocates).
fn take_unchanged_columns(w_old: &Mat<f64>, z_old: &MacroResponses, w: &Mat<f64>, z: &mut [f64]) -> Vec<usize> {
    let n = z_old.nrows();
    let bits = |m: &Mat<f64>, j: usize| -> Vec<u64> { m.col(j).iter().map(|v| v.to_bits()).collect() };
    let old: HashMap<Vec<u64>, usize> = (0..w_old.ncols()).map(|j| (bits(w_old, j), j)).collect();
    let mut fresh = Vec::new();
    for j in 0..w.ncols() {
        match old.get(&bits(w, j)) {
            Some(&o) => z[j * n..(j + 1) * n].copy_from_slice(z_old.col(o)),
            None => fresh.push(j),
        }
    }
    fresh
}

/// `Z_E = K_E⁺ W_E` of a subdomain: column-major, `nrows` entries per
/// column, in the array the batched solve wrote (no padded copy).
#[derive(Debug, Clone, Default)]
pub(crate) struct MacroResponses {
    data: Vec<f64>,
    rows: usize,
}

impl MacroResponses {
    fn new(data: Vec<f64>, rows: usize) -> MacroResponses {
        debug_assert!(if rows == 0 {
            data.is_empty()
        } else {
            data.len() % rows == 0
        });
        MacroResponses { data, rows }
    }

    pub(crate) fn nrows(&self) -> usize {
        self.rows
    }

    pub(crate) fn ncols(&self) -> usize {
        self.data.len().checked_div(self.rows).unwrap_or(0)
    }

    /// Column `k`.
    pub(crate) fn col(&self, k: usize) -> &[f64] {
        &self.data[k * self.rows..(k + 1) * self.rows]
    }

    /// The rows `rows` of every column (`Z_I`, the interface rows).
    fn rows(&self, rows: &[u32]) -> Mat<f64> {
        Mat::from_fn(rows.len(), self.ncols(), |i, j| self.col(j)[rows[i] as usize])
    }
}

/// `K_E⁺` applied to the columns `cols` of `z` (column-major, `n` rows per
/// column), the others left as they are; one batched solve.
fn solve_some_columns(op: &mut SubdomainOperator, z: &mut [f64], n: usize, cols: &[usize]) {
    let m = z.len() / n.max(1);
    if cols.len() == m {
        op.solve_columns(z, m);
        return;
    }
    if cols.is_empty() {
        return;
    }
    let mut block = vec![0.0; n * cols.len()];
    for (c, &j) in cols.iter().enumerate() {
        block[c * n..(c + 1) * n].copy_from_slice(&z[j * n..(j + 1) * n]);
    }
    op.solve_columns(&mut block, cols.len());
    for (c, &j) in cols.iter().enumerate() {
        z[j * n..(j + 1) * n].copy_from_slice(&block[c * n..(c + 1) * n]);
    }
}

/// A Schur-complement face block `S_E[rows, rows]` and its rows.
pub(crate) type FaceBlock = (Vec<u32>, Mat<f64>);

/// Per subdomain held: the interior factor, face blocks and adaptive
/// blocks taken over.
type PooledBlocks = Vec<(Option<InteriorProblem>, Vec<FaceBlock>, adaptive::SideCache)>;
/// Per subdomain held: `Z_E` and the coarse blocks taken over.
type PooledCoarse = Vec<Option<(MacroResponses, CoarseBlocks)>>;

/// What a set-up of a changed structure can take over from an earlier
/// one for a subdomain whose elements and dof layout did not change
/// (the nonsmooth CG's active-set steps): its factored operator, and,
/// where its interface dofs are also the same, the interior factor of
/// the Dirichlet preconditioner and the Schur face blocks of the deluxe
/// weights.
pub(crate) struct PooledSubdomain {
    pub(crate) op: SubdomainOperator,
    interior: Option<InteriorProblem>,
    face_blocks: Vec<FaceBlock>,
    /// The adaptive macro space's blocks and face constraints.
    adaptive: adaptive::SideCache,
    /// `Z_E` and the blocks it gave, see [`CoarseBlocks`].
    coarse: Option<(MacroResponses, CoarseBlocks)>,
}

pub(crate) struct IfaceState {
    pub(crate) lo: usize,
    pub(crate) hi: usize,
    pub(crate) lo_idx: Vec<u32>,
    pub(crate) hi_idx: Vec<u32>,
    /// `lo_idx`, `hi_idx` as runs of consecutive local dofs: what the
    /// per-iteration kernels use (vectorised slice loops).
    pub(crate) runs: Vec<Run>,
    pub(crate) jump: Vec<f64>,
    /// The jump of the solve an equilibrium correction continues, added to
    /// every jump of an iterate (empty: none; see
    /// [`DdSolver::refine_equilibrium`]).
    pub(crate) base_jump: Vec<f64>,
    /// `P_Γ` (`entries × m_Γ`), empty without coarse space; without the
    /// directions that repeat others around cross points ([`crate::redundant`]).
    pub(crate) p: Mat<f64>,
    pub(crate) macro_off: usize,
    pub(crate) jump_norm2: f64,
    /// Lumped interface stiffness `diag(K_lo) + diag(K_hi)` per entry: turns
    /// a jump into the force it leaves unbalanced.
    pub(crate) stiffness: Vec<f64>,
    pub(crate) force_norm2: f64,
}

/// Result of one DD solve: the crate's one [`Outcome`].
pub type DdOutcome = Outcome;

/// Sizes of the set-up, for reports.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct DdStats {
    pub subdomains: usize,
    pub kernel_dims: Vec<usize>,
    pub macro_unknowns: usize,
    /// Macro columns the adaptive macro space added (included in
    /// `macro_unknowns`), on faces and edges.
    pub adaptive_columns: usize,
    /// Of [`Self::adaptive_columns`], those on edges (dofs shared by three
    /// or more subdomains).
    pub adaptive_edge_columns: usize,
    /// Macro columns dropped because combinations through them leave (almost)
    /// no force on any subdomain ([`crate::redundant`]).
    pub redundant_macro_columns: usize,
    /// The threshold of the adaptive macro space used (0: off; `"auto"`
    /// resolved).
    pub adaptive_threshold: f64,
    /// The highest degree of the interfaces' polynomial macro fields used
    /// ([`MacroDegree`] resolved; 0 without geometric modes).
    pub macro_degree: u8,
    /// Interfaces whose macro fields go above degree 1 (of
    /// [`Self::interfaces`]; under MPI, of those this process holds).
    pub polynomial_interfaces: usize,
    /// Interfaces of the decomposition.
    pub interfaces: usize,
    pub kernel_unknowns: usize,
    pub interface_entries: usize,
    /// Values stored in the subdomain factors...
    pub nnz_l: usize,
    /// ...and in the Dirichlet interiors' factors (`cg`).
    pub interior_nnz_l: usize,
    /// Subdomain and interior factors ordered by nested dissection (the
    /// others by AMD).
    pub nested_dissection_factors: usize,
    /// Subdomain and interior factors.
    pub factors: usize,
    pub search_direction: f64,
    /// Whole set-up (operators, macro space, coarse problem, `d`).
    pub setup_s: f64,
    /// Subdomain assembly and factorizations (with kernels).
    pub factor_s: f64,
    /// Interior (Dirichlet preconditioner) factorizations of `cg`.
    pub interior_s: f64,
    /// Interior factors and deluxe face blocks taken over from an earlier
    /// set-up instead of being computed (the nonsmooth CG's active-set
    /// steps; see `NonsmoothOutcome::reused`).
    pub interiors_reused: usize,
    pub face_blocks_reused: usize,
    /// Neumann blocks of the adaptive macro space (faces and edges) and
    /// face constraints taken over from an earlier set-up (the nonsmooth
    /// CG's active-set steps).
    pub neumann_blocks_reused: usize,
    pub face_constraints_reused: usize,
    /// Subdomains whose coarse blocks (`Z_E`, `L_E`) were taken over
    /// from the previous set-up: same operator and same macro columns on
    /// their interfaces, so no multi-RHS solve.
    pub coarse_blocks_reused: usize,
    /// Columns of `Z_E = K_E⁺ W_E` taken over in the other subdomains with
    /// the same operator: their column of `W_E` did not change (a
    /// neighbour's new kernel changes only the columns they share).
    pub coarse_columns_reused: usize,
    /// Deluxe blocks (a face's, or one edge's) computed from the interior
    /// near them only (the default `economic_deluxe` scaling, on large
    /// faces); the others are exact.
    pub near_blocks: usize,
    /// Macro basis, batched solves for `L` and `G`, coarse factorization.
    pub coarse_s: f64,
    /// The adaptive macro columns: interior factors, face blocks and face
    /// eigenproblems (0 without them).
    pub adaptive_s: f64,
    /// Choice of `d` (power iteration on the interface operator).
    pub search_direction_s: f64,
    /// Weights of the CG preconditioner (the deluxe blocks: one Schur
    /// complement application per face dof).
    pub scaling_s: f64,
    /// Largest over smallest positive diagonal entry of the subdomain
    /// stiffnesses (about 10× the largest over the smallest `EA/L` of a
    /// truss): which force part cg's indicator takes
    /// ([`crate::cg_stopping::LUMPED_FORCE_SPREAD`]).
    pub stiffness_spread: f64,
}

/// The set-up DD solver: factorizations, macro space and coarse problem,
/// reusable for any number of load cases.
pub struct DdSolver {
    /// Subdomain operators, interfaces, coarse problem and the
    /// communication seam: what the methods apply.
    pub(crate) op: InterfaceOperator<Seam>,
    /// Interface forces `F` (per interface) of the last solve: where a
    /// `warm` solve starts.
    pub(crate) forces: Vec<Vec<f64>>,
    /// The set-up's step length (a solve never changes it).
    pub(crate) d: f64,
    pub(crate) opts: DdOptions,
    n_free: usize,
    pub(crate) n_cables: usize,
    /// Global dof of each local dof, for every subdomain (held here or not).
    pub(crate) dof_maps: Vec<Vec<usize>>,
    /// Multiplicity of each local dof, for every subdomain.
    pub(crate) multiplicity: Vec<Vec<u32>>,
    pub(crate) stats: DdStats,
    /// The CG method's workspace (`None` unless the method is cg).
    pub(crate) cg: Option<CgWorkspace>,
    /// Whether cg must certify its tolerance (energy estimate from its
    /// coefficients) or may stop on the indicator alone: the nonsmooth
    /// CG's loose solves of cable sets that are still moving, whose
    /// result only guides the next set (the settled set is solved at the
    /// tolerance with the certificate).
    pub(crate) certify: bool,
    /// Least force and displacement scales of the indicators
    /// ([`Self::force_scale`], [`Self::displacement_scale`]): zero, except
    /// during an equilibrium correction, which is measured against the
    /// solve it corrects.
    scale_floors: (f64, f64),
}

/// The global dof that moves most in the mode `Σ_E R_E α_E`, given per
/// subdomain as (kernel basis `R_E`, global dof of each local dof, `α_E`):
/// where a mechanism message points the user. On an interface the
/// subdomains' motions differ (the mode is not restrained there); the
/// largest one is taken.
fn largest_motion(modes: &[(&Mat<f64>, &[usize], &[f64])]) -> Option<usize> {
    let mut best: Option<(f64, usize)> = None;
    for &(r, dofs, alpha) in modes {
        for (l, &d) in dofs.iter().enumerate().take(r.nrows()) {
            let v: f64 = alpha.iter().enumerate().map(|(j, a)| r[(l, j)] * a).sum::<f64>().abs();
            if best.is_none_or(|(b, _)| v > b) {
                best = Some((v, d));
            }
        }
    }
    best.filter(|&(v, _)| v > 0.0).map(|(_, d)| d)
}

/// Lower-triangle entries `(i, j, v)`, `i > j`, of the macro forces' Gram
/// matrix `WᵀW = Σ_E W_EᵀW_E` off its diagonal, from the subdomains in
/// `owned`, flattened for a gather. `W_E` puts `±P_Γ` on the subdomain's
/// dofs of each interface `Γ`; the bases are orthonormal, so the diagonal
/// blocks are the identity on either side (`2 I` in all, added by the
/// caller) and only dofs on two or more of a subdomain's interfaces (cross
/// points) couple columns.
fn macro_gram(dec: &Decomposition, ifaces: &[IfaceState], owned: std::ops::Range<usize>) -> Vec<f64> {
    let per_subdomain: Vec<Vec<f64>> = owned
        .into_par_iter()
        .map(|s| {
            // (local dof, interface, entry, sign) of every entry of s.
            let mut at: Vec<(u32, usize, usize, f64)> = Vec::new();
            for &i in &dec.subdomains[s].interfaces {
                let it = &ifaces[i];
                let (idx, sign) = if it.lo == s {
                    (&it.lo_idx, 1.0)
                } else {
                    (&it.hi_idx, -1.0)
                };
                at.extend(idx.iter().enumerate().map(|(e, &l)| (l, i, e, sign)));
            }
            at.sort_unstable_by_key(|&(l, i, _, _)| (l, i));
            let mut block: std::collections::BTreeMap<(usize, usize), Mat<f64>> = Default::default();
            for group in at.chunk_by(|a, b| a.0 == b.0).filter(|g| g.len() > 1) {
                for &(_, a, ea, sa) in group {
                    for &(_, b, eb, sb) in group {
                        if ifaces[a].macro_off <= ifaces[b].macro_off || a == b {
                            continue;
                        }
                        let (pa, pb) = (&ifaces[a].p, &ifaces[b].p);
                        let m = block
                            .entry((a, b))
                            .or_insert_with(|| Mat::zeros(pa.ncols(), pb.ncols()));
                        for r in 0..pb.ncols() {
                            let v = sa * sb * pb[(eb, r)];
                            for q in 0..pa.ncols() {
                                m[(q, r)] += pa[(ea, q)] * v;
                            }
                        }
                    }
                }
            }
            let mut out = Vec::new();
            for ((a, b), m) in block {
                let (oa, ob) = (ifaces[a].macro_off, ifaces[b].macro_off);
                for r in 0..m.ncols() {
                    for q in 0..m.nrows() {
                        if m[(q, r)] != 0.0 {
                            out.extend([(oa + q) as f64, (ob + r) as f64, m[(q, r)]]);
                        }
                    }
                }
            }
            out
        })
        .collect();
    per_subdomain.concat()
}

/// The cross-point directions ([`crate::redundant::cross_directions`]) of
/// the bases of the interfaces whose `lo` subdomain is `held` here,
/// flattened for a gather: per interface with any, `i, p, s`, then the
/// `p × s` directions column by column.
fn packed_cross_directions(dec: &Decomposition, ifaces: &[IfaceState], held: impl Fn(usize) -> bool) -> Vec<f64> {
    let mut packed = Vec::new();
    for (i, st) in ifaces.iter().enumerate() {
        if !held(st.lo) || st.p.ncols() == 0 {
            continue;
        }
        let mult = &dec.subdomains[st.lo].multiplicity;
        let cross: Vec<usize> = (0..st.lo_idx.len())
            .filter(|&e| mult[st.lo_idx[e] as usize] > 2)
            .collect();
        let sd = crate::redundant::cross_directions(&st.p, &cross);
        if sd.ncols() > 0 {
            packed.extend([i as f64, sd.nrows() as f64, sd.ncols() as f64]);
            for j in 0..sd.ncols() {
                packed.extend(sd.col(j).iter());
            }
        }
    }
    packed
}

/// Each subdomain's `(alpha_off, cols, G_E)` as one vector of numbers, to
/// gather them from every process (in subdomain order): per subdomain
/// `alpha_off, m, r`, the `m` columns, then `G_E` column by column.
/// Indices are below 2⁵³, exact in an f64.
fn pack_kernel_parts<'a>(parts: impl Iterator<Item = (usize, &'a [usize], &'a Mat<f64>)>) -> Vec<f64> {
    let mut v = Vec::new();
    for (alpha_off, cols, g) in parts {
        v.extend([alpha_off as f64, cols.len() as f64, g.ncols() as f64]);
        v.extend(cols.iter().map(|&c| c as f64));
        for j in 0..g.ncols() {
            v.extend(g.col(j).iter());
        }
    }
    v
}

/// The inverse of [`pack_kernel_parts`]: `(cols, G_E, alpha_off)`.
fn unpack_kernel_parts(v: &[f64]) -> Vec<(Vec<usize>, Mat<f64>, usize)> {
    let mut out = Vec::new();
    let mut k = 0;
    while k < v.len() {
        let (alpha_off, m, r) = (v[k] as usize, v[k + 1] as usize, v[k + 2] as usize);
        k += 3;
        let cols = v[k..k + m].iter().map(|&c| c as usize).collect();
        k += m;
        let g = Mat::from_fn(m, r, |i, j| v[k + j * m + i]);
        k += m * r;
        out.push((cols, g, alpha_off));
    }
    out
}

/// Each subdomain's square block `L_E` as one vector of `f64` (order, then
/// the values by columns), in subdomain order.
fn pack_macro_blocks(blocks: &[Mat<f64>]) -> Vec<f64> {
    let mut v = Vec::new();
    for l in blocks {
        v.push(l.nrows() as f64);
        for j in 0..l.ncols() {
            v.extend(l.col(j).iter());
        }
    }
    v
}

/// The inverse of [`pack_macro_blocks`].
fn unpack_macro_blocks(v: &[f64]) -> Vec<Mat<f64>> {
    let mut out = Vec::new();
    let mut k = 0;
    while k < v.len() {
        let m = v[k] as usize;
        k += 1;
        out.push(Mat::from_fn(m, m, |i, j| v[k + j * m + i]));
        k += m * m;
    }
    out
}

impl DdSolver {
    /// Sets up a truss model: factors every subdomain, builds the macro
    /// basis and the coarse problem (multilevel), and picks `d`.
    pub fn new(model: &Model, dec: &Decomposition, opts: DdOptions) -> Result<DdSolver> {
        Self::new_reusing(model, dec, opts, Vec::new(), Placement::Process)
    }

    /// [`Self::new`] with the subdomains placed as `placement` says (under
    /// MPI each rank sets up its own block; every rank calls this).
    pub fn new_in(model: &Model, dec: &Decomposition, opts: DdOptions, placement: Placement) -> Result<DdSolver> {
        Self::new_reusing(model, dec, opts, Vec::new(), placement)
    }

    /// [`Self::new`] with some subdomain operators taken from an earlier
    /// set-up ([`DdProblem::from_model_reusing`], [`Self::into_operators`]);
    /// the macro space and the coarse problem are rebuilt.
    pub fn new_reusing(
        model: &Model,
        dec: &Decomposition,
        opts: DdOptions,
        reused: Vec<Option<SubdomainOperator>>,
        placement: Placement,
    ) -> Result<DdSolver> {
        Self::set_up_reusing(model, dec, opts, reused, None, placement)
    }

    /// [`Self::new_reusing`] with the interior factors and face blocks of
    /// the taken-over subdomains too; the set-up keeps its own face blocks
    /// for the next one ([`Self::into_pooled`]).
    pub(crate) fn new_pooled(
        model: &Model,
        dec: &Decomposition,
        opts: DdOptions,
        reused: Vec<Option<PooledSubdomain>>,
        placement: Placement,
    ) -> Result<DdSolver> {
        let mut coarse = Vec::with_capacity(reused.len());
        let (ops, parts): (Vec<_>, Vec<_>) = reused
            .into_iter()
            .map(|p| match p {
                Some(p) => {
                    coarse.push(p.coarse);
                    (Some(p.op), (p.interior, p.face_blocks, p.adaptive))
                }
                None => {
                    coarse.push(None);
                    (None, Default::default())
                }
            })
            .unzip();
        Self::set_up_reusing(model, dec, opts, ops, Some((parts, coarse)), placement)
    }

    fn set_up_reusing(
        model: &Model,
        dec: &Decomposition,
        opts: DdOptions,
        reused: Vec<Option<SubdomainOperator>>,
        pooled: Option<(PooledBlocks, PooledCoarse)>,
        placement: Placement,
    ) -> Result<DdSolver> {
        on_workers(placement.in_process(), || {
            let t0 = Instant::now();
            let mut opts = opts;
            opts.adaptive_threshold = adaptive::threshold_for(opts.adaptive_threshold, model);
            opts.adaptive_edges = adaptive::edges_for(opts.adaptive_edges, model);
            let problem = DdProblem::from_model_reusing(model, dec, reused, placement, opts.ordering)?;
            let factor_s = t0.elapsed().as_secs_f64();
            let name_dof = |d: usize| {
                let (node, c) = model.dof_owner(d);
                format!("node {node}, component {}", ["x", "y", "z"][c])
            };
            let mut solver = DdSolver::from_problem_named(problem, opts, &name_dof, pooled)?;
            solver.stats.setup_s = t0.elapsed().as_secs_f64();
            solver.stats.factor_s = factor_s;
            Ok(solver)
        })
    }

    /// Sets up an algebraic problem (already factored operators).
    pub fn from_problem(problem: DdProblem<'_>, opts: DdOptions) -> Result<DdSolver> {
        on_workers(problem.placement.in_process(), || {
            Self::from_problem_named(problem, opts, &|d| format!("global dof {d}"), None)
        })
    }

    /// [`DdSolver::from_problem`]; a mechanism message names the dof that
    /// moves most with `name_dof` (a node and component for a truss).
    /// `pooled`: the interior factors and face blocks taken over, one per
    /// subdomain held (see [`Self::new_pooled`]), and the coarse blocks.
    fn from_problem_named(
        problem: DdProblem<'_>,
        opts: DdOptions,
        name_dof: &(dyn Fn(usize) -> String + Sync),
        pooled: Option<(PooledBlocks, PooledCoarse)>,
    ) -> Result<DdSolver> {
        let t0 = Instant::now();
        // Whether the caller keeps the Schur blocks for a later set-up (the
        // adaptive macro space hands its blocks to the cg set-up the same way).
        let retain_blocks = pooled.is_some();
        let (mut pooled, kept_coarse) = match pooled {
            Some((p, c)) => (Some(p), c),
            None => (None, Vec::new()),
        };
        let mut kept_coarse = kept_coarse.into_iter();
        let DdProblem {
            decomposition: dec,
            mut operators,
            loads,
            placement,
            dof_points,
            n_cables,
        } = problem;
        let ns = dec.len();
        let n_free = dof_points.len();
        let seam = placement.seam(dec);
        let owned = seam.owned();
        let first = owned.start;
        if operators.len() != owned.len() || loads.len() != owned.len() {
            return seam.agree(Err(Error::input(
                "operators",
                None,
                format!(
                    "{} operators and {} loads given for the {} subdomains {}..{} of this process",
                    operators.len(),
                    loads.len(),
                    owned.len(),
                    owned.start,
                    owned.end
                ),
            )));
        }
        seam.agree(Ok(()))?;
        // One pool entry per subdomain held (a short pool, as from
        // `new_pooled` with nothing to take over, would leave the adaptive
        // face sides, zipped with it, out).
        if let Some(p) = pooled.as_mut() {
            p.resize_with(owned.len(), Default::default);
        }
        // Kernel dimensions of every subdomain (each process factored its own).
        let local_dims: Vec<f64> = operators.iter().map(|o| o.kernel_dim() as f64).collect();
        let kernel_dims: Vec<usize> = seam.gather(&local_dims).into_iter().map(|d| d as usize).collect();
        let singular = kernel_dims.iter().any(|&r| r > 0);
        if singular && ns == 1 {
            // One subdomain: rank 0 holds it, and every process fails
            // with its message (the lowest failing rank's).
            let at = operators.first().map_or(String::new(), |op| {
                let r = op.kernel();
                let e0: Vec<f64> = (0..r.ncols()).map(|j| if j == 0 { 1.0 } else { 0.0 }).collect();
                largest_motion(&[(r, &dec.subdomains[0].dofs, &e0)])
                    .map(|d| format!(" (a free motion, largest at {})", name_dof(d)))
                    .unwrap_or_default()
            });
            return seam.agree(Err(Error::Mechanism(format!(
                "the structure is not supported well enough: its stiffness is singular{at}"
            ))));
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
        // Monolevel keeps only the coarse problem its singular subdomains
        // need (FETI's natural coarse space: the interface traces of their
        // kernels, no geometric macro modes); with regular subdomains it
        // has none. Multilevel adds the macro space.
        let natural_only = !opts.coarse;
        let use_coarse = (opts.coarse || singular) && !dec.interfaces.is_empty();
        let t_coarse = Instant::now();
        let local = |s: usize| owned.contains(&s).then(|| s - first);
        // Interfaces and their macro bases (every interface is listed; only
        // the ones with a subdomain here are filled in).
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
                jump: vec![0.0; it.len()],
                base_jump: Vec::new(),
                p: Mat::zeros(0, 0),
                macro_off: 0,
                jump_norm2: 0.0,
                stiffness: Vec::new(),
                force_norm2: 0.0,
            })
            .collect();
        let touched = |it: &IfaceState| local(it.lo).is_some() || local(it.hi).is_some();
        let mut n_macro = 0;
        let mut adaptive_columns = 0;
        let mut adaptive_edge_columns = 0;
        let mut redundant_macro_columns = 0;
        let mut macro_degree = 0;
        let mut polynomial_interfaces = 0;
        // Already resolved from the model where there is one; off for an
        // algebraic problem, which has no element stiffnesses to judge by.
        let adaptive_threshold = opts.adaptive_threshold.resolve(std::iter::empty());
        let mut adaptive_s = 0.0;
        let (mut neumann_blocks_reused, mut face_constraints_reused) = (0, 0);
        if use_coarse {
            // Each side's kernel on the interface entries (column-major).
            let traces = seam.exchange(|i, is_lo| {
                let it = &ifaces[i];
                let (s, idx) = if is_lo {
                    (it.lo, &it.lo_idx)
                } else {
                    (it.hi, &it.hi_idx)
                };
                let r = operators[s - first].macro_trace_kernel();
                (0..r.ncols())
                    .flat_map(|q| idx.iter().map(move |&l| r[(l as usize, q)]))
                    .collect()
            });
            // The adaptive macro space: each held subdomain's principal and
            // Neumann blocks on its faces, then one eigenproblem per face.
            let adaptive_on = adaptive_threshold > 0.0 && opts.krylov && !natural_only;
            // Flatness is only asked where "auto" can pick by it (cg).
            let flat = opts.macro_degree.is_default() && opts.krylov && {
                let points: Vec<[f64; 3]> = dof_points.iter().map(|(p, _)| *p).collect();
                crate::coarse::is_flat(&points)
            };
            let degree = opts.macro_degree.resolve(flat, adaptive_on, opts.krylov);
            let t_adaptive = Instant::now();
            let neumann_reused = std::sync::atomic::AtomicUsize::new(0);
            let constraints_reused = std::sync::atomic::AtomicUsize::new(0);
            // Only a set-up whose blocks a later one takes over keeps copies.
            let keeping = adaptive::Keeping {
                keep: retain_blocks,
                reused: &neumann_reused,
            };
            let (face_entries, face_sides) = if adaptive_on {
                let entries = adaptive::face_entries(dec);
                let pool = pooled.get_or_insert_with(|| (0..owned.len()).map(|_| Default::default()).collect());
                let held = seam.agree(adaptive::face_sides(
                    dec,
                    first,
                    &mut operators,
                    pool,
                    &entries,
                    &keeping,
                ))?;
                // Each face's two sides where either is held (from the
                // neighbour's process under MPI; copies in one process).
                let sides = seam.exchange(|i, is_lo| {
                    held[i][usize::from(!is_lo)]
                        .as_ref()
                        .map_or_else(Vec::new, adaptive::FaceSide::pack)
                });
                drop(held);
                let sides = sides
                    .iter()
                    .map(|[lo, hi]| [adaptive::FaceSide::unpack(lo), adaptive::FaceSide::unpack(hi)])
                    .collect();
                (entries, sides)
            } else {
                (Vec::new(), Vec::new())
            };
            // Then the edges: every subdomain's blocks on its edges, to
            // every process (each edge's problems need all its subdomains),
            // and one set of constraints per edge, on the interfaces of a
            // spanning tree of its pairs (docs/design.md §4).
            let edge_columns: Vec<Vec<(Vec<u32>, Mat<f64>)>> =
                if adaptive_on && opts.adaptive_edges.resolve(std::iter::empty()) {
                    let entries: Vec<InterfaceEntries<'_>> = dec
                        .interfaces
                        .iter()
                        .map(|it| InterfaceEntries {
                            lo: it.lo,
                            hi: it.hi,
                            lo_idx: &dec.entry_lo_local[it.start..it.end],
                            hi_idx: &dec.entry_hi_local[it.start..it.end],
                        })
                        .collect();
                    let dofs: Vec<Vec<usize>> = dec.subdomains.iter().map(|sd| sd.dofs.clone()).collect();
                    let mult: Vec<Vec<u32>> = dec.subdomains.iter().map(|sd| sd.multiplicity.clone()).collect();
                    let edges = Edges::new(&entries, &dofs, &mult);
                    drop((entries, dofs, mult));
                    let pool = pooled.as_mut().expect("the face sides set it");
                    let held = seam.agree(adaptive::edge_sides(&edges, first, &mut operators, pool, &keeping))?;
                    let constraints = adaptive::edge_constraints(&edges, &seam.gather(&held), adaptive_threshold);
                    let ends: Vec<(usize, usize)> = dec.interfaces.iter().map(|it| (it.lo, it.hi)).collect();
                    let has_face: Vec<bool> = face_entries.iter().map(|f| !f.is_empty()).collect();
                    let mut per_interface: Vec<Vec<(Vec<u32>, Mat<f64>)>> = vec![Vec::new(); ends.len()];
                    for (tree, c) in adaptive::edge_trees(&edges, &ends, &has_face)
                        .into_iter()
                        .zip(constraints)
                    {
                        if let Some(c) = c {
                            for (i, entries) in tree {
                                per_interface[i].push((entries, c.clone()));
                            }
                        }
                    }
                    per_interface
                } else {
                    Vec::new()
                };
            let n_adaptive = std::sync::atomic::AtomicUsize::new(0);
            let n_edge = std::sync::atomic::AtomicUsize::new(0);
            let highest_degree = std::sync::atomic::AtomicU8::new(0);
            let n_polynomial = std::sync::atomic::AtomicUsize::new(0);
            // Each block, and each held face's constraints for the next set-up
            // (`lo` subdomain here, key, constraints).
            type Kept = Option<(usize, u64, Mat<f64>)>;
            let (blocks, kept_constraints): (Vec<Option<Mat<f64>>>, Vec<Kept>) = dec
                .interfaces
                .par_iter()
                .zip(ifaces.par_iter())
                .zip(traces.par_iter())
                .enumerate()
                .map(|(i, ((it, st), [tl, th]))| {
                    if !touched(st) {
                        return (None, None);
                    }
                    let mut kept = None;
                    let n = it.len();
                    let tlo = Mat::from_fn(n, kernel_dims[it.lo], |j, q| tl[q * n + j]);
                    let thi = Mat::from_fn(n, kernel_dims[it.hi], |j, q| th[q * n + j]);
                    let block = if natural_only {
                        // No geometric modes: no dof points needed (the
                        // algebraic level may not have them).
                        MacroBasis::kernel_block(&tlo, &thi)
                    } else {
                        let dofs = &dec.entry_dof[it.start..it.end];
                        let (points, comp): (Vec<[f64; 3]>, Vec<usize>) = dofs.iter().map(|&d| dof_points[d]).unzip();
                        let degree = opts
                            .macro_degree
                            .on_interface(degree, || crate::coarse::distinct_points(&points));
                        highest_degree.fetch_max(degree, std::sync::atomic::Ordering::Relaxed);
                        if degree > 1 {
                            n_polynomial.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                        }
                        // The kernel traces' deviations are kept down to
                        // round-off, but not beside an adaptive space, whose
                        // columns they would nearly repeat (SOFT_TRACE_RTOL).
                        let rtol = if adaptive_on {
                            crate::coarse::MACRO_RANK_RTOL
                        } else {
                            crate::coarse::SOFT_TRACE_RTOL
                        };
                        let p = MacroBasis::interface_block(&points, &comp, &tlo, &thi, degree, rtol);
                        let p = match face_sides.get(i) {
                            Some([Some(lo), Some(hi)]) => {
                                let face = &face_entries[i];
                                let pf = adaptive::face_rows(&p, face);
                                let earlier = local(it.lo).and_then(|k| pooled.as_ref()?.get(k)).map(|(_, _, c)| c);
                                let (key, extra) = adaptive::face_constraints_kept(
                                    &pf,
                                    lo,
                                    hi,
                                    adaptive_threshold,
                                    earlier,
                                    &constraints_reused,
                                );
                                let (p, added) = adaptive::enrich_with(p, face, &extra);
                                n_adaptive.fetch_add(added, std::sync::atomic::Ordering::Relaxed);
                                kept = local(it.lo).filter(|_| retain_blocks).map(|k| (k, key, extra));
                                p
                            }
                            _ => p,
                        };
                        match edge_columns.get(i) {
                            Some(extra) if !extra.is_empty() => {
                                let extra: Vec<(&[u32], &Mat<f64>)> =
                                    extra.iter().map(|(e, c)| (e.as_slice(), c)).collect();
                                let (p, added) = adaptive::with_columns(p, &extra);
                                n_edge.fetch_add(added, std::sync::atomic::Ordering::Relaxed);
                                p
                            }
                            _ => p,
                        }
                    };
                    (Some(block), kept)
                })
                .unzip();
            drop((traces, edge_columns));
            // The faces' constraints for a later set-up that takes their
            // `lo` subdomain over (the others go).
            if let Some(pool) = pooled.as_mut() {
                let mut found: Vec<Vec<(u64, Mat<f64>)>> = vec![Vec::new(); pool.len()];
                for (k, key, c) in kept_constraints.into_iter().flatten() {
                    found[k].push((key, c));
                }
                for ((_, _, cache), f) in pool.iter_mut().zip(found) {
                    cache.set_constraints(f);
                }
            }
            neumann_blocks_reused = neumann_reused.into_inner();
            face_constraints_reused = constraints_reused.into_inner();
            adaptive_edge_columns = n_edge.into_inner();
            macro_degree = highest_degree.into_inner();
            polynomial_interfaces = n_polynomial.into_inner();
            adaptive_columns = n_adaptive.into_inner() + adaptive_edge_columns;
            if adaptive_on {
                adaptive_s = t_adaptive.elapsed().as_secs_f64();
            }
            // Macro offsets need every interface's width: the process of
            // its `lo` subdomain tells.
            let widths: Vec<f64> = blocks
                .iter()
                .zip(&ifaces)
                .enumerate()
                .filter(|(_, (_, st))| local(st.lo).is_some())
                .flat_map(|(i, (b, _))| [i as f64, b.as_ref().map_or(0, |b| b.ncols()) as f64])
                .collect();
            let mut width = vec![0usize; ifaces.len()];
            for pair in seam.gather(&widths).chunks_exact(2) {
                width[pair[0] as usize] = pair[1] as usize;
            }
            let mut off = 0;
            for ((st, b), w) in ifaces.iter_mut().zip(blocks).zip(&width) {
                st.macro_off = off;
                off += w;
                if let Some(p) = b {
                    st.p = p;
                }
            }
            n_macro = off;
            // Columns that repeat others around cross points
            // (`crate::redundant`) leave every basis before the coarse
            // problem is built from them; every process finds the same
            // ones from the same gathered bases' cross directions and Gram
            // matrix.
            let mut cross_dirs: Vec<Mat<f64>> = width.iter().map(|&w| Mat::zeros(w, 0)).collect();
            let all = seam.gather(&packed_cross_directions(dec, &ifaces, |s| local(s).is_some()));
            let mut k = 0;
            while k < all.len() {
                let (i, m, c) = (all[k] as usize, all[k + 1] as usize, all[k + 2] as usize);
                k += 3;
                cross_dirs[i] = Mat::from_fn(m, c, |a, b| all[k + b * m + a]);
                k += m * c;
            }
            let offsets: Vec<usize> = ifaces.iter().map(|st| st.macro_off).collect();
            // Without a cross-point direction anywhere nothing can repeat:
            // no Gram matrix to gather (every process sees the same gather).
            let gram: Vec<(usize, usize, f64)> = if cross_dirs.iter().any(|d| d.ncols() > 0) {
                seam.gather(&macro_gram(dec, &ifaces, owned.clone()))
                    .chunks_exact(3)
                    .map(|t| (t[0] as usize, t[1] as usize, t[2]))
                    .collect()
            } else {
                Vec::new()
            };
            let dropped = crate::redundant::redundant_directions(&offsets, &cross_dirs, &gram);
            drop((gram, cross_dirs));
            let n_dropped: usize = dropped.iter().map(|d| d.ncols()).sum();
            if n_dropped > 0 {
                redundant_macro_columns = n_dropped;
                let mut off = 0;
                for ((st, d), &w) in ifaces.iter_mut().zip(&dropped).zip(&width) {
                    if d.ncols() > 0 && st.p.ncols() == w {
                        st.p = crate::redundant::without_directions(&st.p, d);
                    }
                    st.macro_off = off;
                    off += w - d.ncols();
                }
                n_macro = off;
            }
        }

        // Per-subdomain state, for the subdomains held here.
        let mut alpha_offsets = Vec::with_capacity(ns);
        let mut alpha_off = 0;
        for &r in &kernel_dims {
            alpha_offsets.push(alpha_off);
            alpha_off += r;
        }
        let mut subs: Vec<SubState> = Vec::with_capacity(owned.len());
        let keep = pooled.is_some();
        let mut pooled = pooled.unwrap_or_default().into_iter();
        for (k, (op, load)) in operators.into_iter().zip(loads).enumerate() {
            let (interior, face_blocks, side_cache) = pooled.next().unwrap_or_default();
            let (z, coarse_kept) = match kept_coarse.next().flatten().filter(|_| use_coarse) {
                Some((z, b)) => (z, Some(b)),
                None => (MacroResponses::default(), None),
            };
            let s = first + k;
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
                z,
                coarse_kept,
                macro_cols: Vec::new(),
                z_iface: Mat::zeros(0, 0),
                w_cols: SparseColumns::default(),
                rb: Vec::new(),
                zt_r: Vec::new(),
                fm: Vec::new(),
                alpha_off: alpha_offsets[s],
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
                interior,
                face_blocks: keep.then_some(face_blocks),
                side_cache: keep.then_some(side_cache),
                op,
            });
        }

        let diags: Vec<Vec<f64>> = subs.iter().map(|s| s.op.diagonal()).collect();
        // Largest over smallest positive stiffness diagonal, over every
        // subdomain: cg's choice of the indicator's force part.
        let (dmin, dmax) = diags
            .iter()
            .flatten()
            .filter(|&&d| d > 0.0)
            .fold((f64::INFINITY, 0.0f64), |(lo, hi), &d| (lo.min(d), hi.max(d)));
        let ends = seam.gather(&[dmax, -dmin]);
        let dmax = ends.iter().step_by(2).fold(0.0f64, |a, &b| a.max(b));
        let dmin = -ends.iter().skip(1).step_by(2).fold(f64::NEG_INFINITY, |a, &b| a.max(b));
        let stiffness_spread = if dmin.is_finite() && dmin > 0.0 {
            dmax / dmin
        } else {
            1.0
        };
        let sides = seam.exchange(|i, is_lo| {
            let it = &ifaces[i];
            let (s, idx) = if is_lo {
                (it.lo, &it.lo_idx)
            } else {
                (it.hi, &it.hi_idx)
            };
            idx.iter().map(|&l| diags[s - first][l as usize]).collect()
        });
        for (it, [lo, hi]) in ifaces.iter_mut().zip(sides) {
            it.stiffness = lo.iter().zip(&hi).map(|(a, b)| a + b).collect();
        }
        let lumped = matches!(opts.search_direction, SearchDirection::Auto);
        for (k, st) in subs.iter_mut().enumerate() {
            let mut dofs: Vec<u32> = Vec::new();
            for &(i, is_lo) in &st.ifaces {
                dofs.extend(if is_lo { &ifaces[i].lo_idx } else { &ifaces[i].hi_idx });
            }
            dofs.sort_unstable();
            dofs.dedup();
            st.iface_dofs = dofs;
            if lumped {
                st.weight = diags[k].clone();
            }
        }
        drop(diags);

        // cg's preconditioner: which interior factors a pooled set-up hands
        // over stay (where the interface is the same; they serve the
        // Dirichlet preconditioner only, the lumped deluxe blocks being of
        // `K_E`), and where its deluxe blocks sit. The interiors and blocks
        // themselves are computed beside the coarse problem below.
        let dof_maps: Vec<Vec<usize>> = dec.subdomains.iter().map(|s| s.dofs.clone()).collect();
        let multiplicity: Vec<Vec<u32>> = dec.subdomains.iter().map(|s| s.multiplicity.clone()).collect();
        let dirichlet = opts.krylov && opts.preconditioner == Preconditioner::Dirichlet;
        let mut interiors_reused = 0;
        let layout = opts.krylov.then(|| {
            for st in subs.iter_mut() {
                let n = st.op.n();
                if !(dirichlet && st.interior.as_ref().is_some_and(|ip| ip.fits(n, &st.iface_dofs))) {
                    st.interior = None;
                    if let Some(b) = st.face_blocks.as_mut() {
                        b.clear();
                    }
                }
            }
            interiors_reused = subs.iter().filter(|st| st.interior.is_some()).count();
            DeluxeLayout::new(&ifaces, &dof_maps, &multiplicity, owned.clone(), opts.interface_scaling)
        });

        // Coarse operator from one batched multi-RHS solve per subdomain.
        let mut coarse = None;
        let mut coarse_parts = None;
        let reused_blocks = std::sync::atomic::AtomicUsize::new(0);
        let reused_columns = std::sync::atomic::AtomicUsize::new(0);
        if use_coarse {
            // `W_E` on the interface rows and `G_E = W_Iᵀ R_I` first, and
            // the rank of `G` checked from them: a structure that is a
            // mechanism (a nonsmooth step's set that leaves one) fails here,
            // before the solves of `Z_E` and the preconditioner's interiors
            // and blocks (about 7 of the 10 s a failed exact step cost on the
            // nonsmooth 410² grid cut in 64).
            let early: Vec<(Vec<usize>, Mat<f64>, Mat<f64>)> = subs
                .par_iter()
                .map(|st| {
                    let n = st.op.n();
                    let mut cols = Vec::new();
                    for &(i, _) in &st.ifaces {
                        let it = &ifaces[i];
                        cols.extend((0..it.p.ncols()).map(|q| it.macro_off + q));
                    }
                    let m = cols.len();
                    // W_E is zero off the interface dofs: it is built on
                    // those rows only (L_E = W_Iᵀ Z_I, G_E = W_Iᵀ R_I), and
                    // the n × m array of the solves is allocated only when
                    // columns are solved, then kept as `Z_E` without a copy
                    // (fresh pages fault slowly: with three such arrays
                    // per subdomain, their allocations and copies took as
                    // many samples as the solves on the 30³ tower with 64
                    // subdomains).
                    let rows = &st.iface_dofs;
                    let mut at = vec![u32::MAX; n];
                    for (i, &l) in rows.iter().enumerate() {
                        at[l as usize] = i as u32;
                    }
                    let mut wi = Mat::<f64>::zeros(rows.len(), m);
                    let mut c = 0;
                    for &(i, is_lo) in &st.ifaces {
                        let it = &ifaces[i];
                        let idx = if is_lo { &it.lo_idx } else { &it.hi_idx };
                        let sign = if is_lo { 1.0 } else { -1.0 };
                        for q in 0..it.p.ncols() {
                            for (j, &l) in idx.iter().enumerate() {
                                wi[(at[l as usize] as usize, c)] += sign * it.p[(j, q)];
                            }
                            c += 1;
                        }
                    }
                    drop(at);
                    let kernel = st.op.kernel();
                    let ri = Mat::from_fn(rows.len(), kernel.ncols(), |i, j| kernel[(rows[i] as usize, j)]);
                    let g_e = wi.transpose() * &ri;
                    (cols, wi, g_e)
                })
                .collect();
            // Every process checks and then assembles the whole coarse
            // problem from every subdomain's contribution (in subdomain order).
            let g_parts = unpack_kernel_parts(
                &seam.gather(&pack_kernel_parts(
                    subs.iter()
                        .zip(&early)
                        .map(|(st, (cols, _, g_e))| (st.alpha_off, &cols[..], g_e)),
                )),
            );
            let n_alpha = alpha_off;
            let mut owner = vec![0usize; n_alpha];
            for (s, (_, g, off)) in g_parts.iter().enumerate() {
                owner[*off..*off + g.ncols()].fill(s);
            }
            let describe = |alpha: &[f64]| {
                // The subdomains held here (rank 0's message is the one shown).
                let modes: Vec<_> = subs
                    .iter()
                    .zip(&dec.subdomains[owned.clone()])
                    .map(|(st, sd)| {
                        (
                            st.op.kernel(),
                            &sd.dofs[..],
                            &alpha[st.alpha_off..st.alpha_off + st.alpha.len()],
                        )
                    })
                    .collect();
                largest_motion(&modes)
                    .map(|d| format!(" (largest motion at {})", name_dof(d)))
                    .unwrap_or_default()
            };
            let views: Vec<(&[usize], &Mat<f64>, usize)> =
                g_parts.iter().map(|(c, g, off)| (&c[..], g, *off)).collect();
            let g = seam.agree(CoarseProblem::check_restrained(
                n_macro, n_alpha, &views, &owner, &describe,
            ))?;
            let local_blocks: Vec<Mat<f64>> = subs
                .par_iter_mut()
                .zip(early.into_par_iter())
                .map(|(st, (cols, wi, _))| {
                    let n = st.op.n();
                    let m = cols.len();
                    let rows = &st.iface_dofs;
                    let l_e = match st.coarse_kept.take() {
                        // (faer's `==` asserts equal shapes: compare them first.)
                        Some(b)
                            if b.rows == *rows
                                && b.w.ncols() == m
                                && st.z.nrows() == n
                                && st.z.ncols() == m
                                && b.w == wi =>
                        {
                            reused_blocks.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                            st.z_iface = st.z.rows(rows);
                            b.l
                        }
                        kept => {
                            let mut z = vec![0.0; n * m];
                            for (j, col) in z.chunks_exact_mut(n.max(1)).enumerate().take(m) {
                                for (i, &l) in rows.iter().enumerate() {
                                    col[l as usize] = wi[(i, j)];
                                }
                            }
                            // The same operator (the blocks are pooled with
                            // it) and rows: a column of `W_E` kept bit for
                            // bit keeps its column of `Z_E = K_E⁺ W_E`. A
                            // neighbour's new kernel changes the columns of
                            // the interface they share, not the others.
                            let old =
                                kept.filter(|b| b.rows == *rows && st.z.nrows() == n && st.z.ncols() == b.w.ncols());
                            let fresh = match old {
                                Some(b) => {
                                    let taken = take_unchanged_columns(&b.w, &st.z, &wi, &mut z);
                                    reused_columns.fetch_add(m - taken.len(), std::sync::atomic::Ordering::Relaxed);
                                    taken
                                }
                                None => (0..m).collect(),
                            };
                            solve_some_columns(&mut st.op, &mut z, n, &fresh);
                            st.z = MacroResponses::new(z, n);
                            st.z_iface = st.z.rows(rows);
                            wi.transpose() * &st.z_iface
                        }
                    };
                    if retain_blocks {
                        st.coarse_kept = Some(CoarseBlocks {
                            rows: rows.clone(),
                            w: wi.clone(),
                            l: l_e.clone(),
                        });
                    }
                    st.w_cols = SparseColumns::from_dense(rows, &wi);
                    st.rb = vec![0.0; rows.len()];
                    st.zt_r = vec![0.0; m];
                    st.fm = vec![0.0; m];
                    st.macro_cols = cols;
                    l_e
                })
                .collect();
            let blocks = unpack_macro_blocks(&seam.gather(&pack_macro_blocks(&local_blocks)));
            drop(local_blocks);
            let parts: Vec<CoarseContribution> = g_parts
                .into_iter()
                .zip(blocks)
                .map(|((cols, g, alpha_off), l)| CoarseContribution { cols, l, g, alpha_off })
                .collect();
            coarse_parts = Some((parts, g));
        }
        // The coarse problem's factorizations have serial stretches; cg's
        // interior factors and deluxe blocks (the subdomains' own work, no
        // communication) fill them. The operators are only read from here
        // on: the interiors are factored from them.
        let mut sources = Vec::with_capacity(subs.len());
        for st in subs.iter_mut() {
            let SubState {
                op,
                ifaces: sides,
                iface_dofs,
                interior,
                face_blocks,
                ..
            } = st;
            sources.push(BlockSource {
                op,
                ifaces: sides,
                iface_dofs,
                interior,
                face_blocks,
            });
        }
        let build_coarse = move || {
            coarse_parts.map(|(parts, g)| {
                let t = Instant::now();
                let built = CoarseProblem::new_checked(n_macro, &parts, g);
                (built, t.elapsed().as_secs_f64())
            })
        };
        let prepare = || match &layout {
            Some(layout) => Preconditioning::prepare(sources, &ifaces, layout, opts.interface_scaling, dirichlet),
            None => Preconditioning::default(),
        };
        let coarse_start = t_coarse.elapsed().as_secs_f64();
        let (built, prepared) = rayon::join(build_coarse, prepare);
        let mut coarse_own_s = coarse_start;
        if let Some((built, s)) = built {
            coarse_own_s += s;
            coarse = Some(seam.agree(built)?);
        }

        let nd = |k: OrderingKind| (k == OrderingKind::NestedDissection) as usize as f64;
        let op_sizes = seam.gather(&[
            subs.iter().map(|s| s.op.nnz_l() as f64).sum::<f64>(),
            subs.iter().map(|s| nd(s.op.ordering())).sum::<f64>(),
        ]);
        let total = |v: &[f64], k: usize| v.iter().skip(k).step_by(2).sum::<f64>() as usize;
        let stats = DdStats {
            subdomains: ns,
            kernel_dims: kernel_dims.clone(),
            macro_unknowns: n_macro,
            adaptive_columns,
            adaptive_edge_columns,
            redundant_macro_columns,
            adaptive_threshold,
            macro_degree,
            polynomial_interfaces,
            interfaces: dec.interfaces.len(),
            adaptive_s,
            kernel_unknowns: alpha_off,
            interface_entries: dec.n_entries(),
            stiffness_spread,
            nnz_l: total(&op_sizes, 0),
            interior_nnz_l: 0,
            nested_dissection_factors: total(&op_sizes, 1),
            factors: ns,
            search_direction: 0.0,
            setup_s: 0.0,
            factor_s: 0.0,
            interior_s: 0.0,
            interiors_reused: 0,
            face_blocks_reused: 0,
            neumann_blocks_reused,
            face_constraints_reused,
            coarse_blocks_reused: reused_blocks.into_inner(),
            coarse_columns_reused: reused_columns.into_inner(),
            near_blocks: 0,
            coarse_s: if use_coarse { coarse_own_s - adaptive_s } else { 0.0 },
            search_direction_s: 0.0,
            scaling_s: 0.0,
        };
        let forces = ifaces.iter().map(|it| vec![0.0; it.lo_idx.len()]).collect();
        let entry_inv_mult = dec
            .interfaces
            .iter()
            .zip(&ifaces)
            .map(|(it, st)| {
                let m = &dec.subdomains[it.lo].multiplicity;
                st.lo_idx.iter().map(|&a| 1.0 / m[a as usize] as f64).collect()
            })
            .collect();
        let mut solver = DdSolver {
            op: InterfaceOperator::with_seam(subs, ifaces, coarse, seam, entry_inv_mult),
            forces,
            d: 0.0,
            opts,
            n_free,
            n_cables,
            dof_maps,
            multiplicity,
            stats,
            cg: None,
            certify: true,
            scale_floors: (0.0, 0.0),
        };
        if let Some(layout) = layout {
            solver.cg = Some(CgWorkspace::new(
                solver.op.interface_sizes(),
                solver.op.subs.iter().map(|s| s.v.len()),
            ));
            let Preconditioning {
                interiors,
                interior_s,
                blocks,
                blocks_s,
            } = prepared;
            if dirichlet {
                solver.stats.interiors_reused = interiors_reused;
                solver.op.comm.agree(interiors)?;
                let interiors: Vec<_> = solver.op.subs.iter().filter_map(|st| st.interior.as_ref()).collect();
                let sizes = solver.op.comm.gather(&[
                    interiors.iter().map(|ip| ip.nnz_l() as f64).sum::<f64>(),
                    interiors.iter().filter(|ip| ip.ordering().is_some()).count() as f64,
                    interiors
                        .iter()
                        .filter(|ip| ip.ordering() == Some(OrderingKind::NestedDissection))
                        .count() as f64,
                ]);
                let total = |k: usize| sizes.iter().skip(k).step_by(3).sum::<f64>() as usize;
                solver.stats.interior_nnz_l = total(0);
                solver.stats.factors += total(1);
                solver.stats.nested_dissection_factors += total(2);
                solver.stats.interior_s = interior_s;
            }
            // The weights and every interface's deluxe blocks from the
            // subdomains' blocks.
            let t = Instant::now();
            solver.finish_interface_scaling(solver.opts.interface_scaling, layout, blocks);
            if !retain_blocks {
                for st in solver.op.subs.iter_mut() {
                    st.face_blocks = None;
                }
            }
            solver.stats.scaling_s = blocks_s + t.elapsed().as_secs_f64();
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
            self.op.subs.par_iter_mut().for_each(|s| {
                s.y.copy_from_slice(&s.b);
                s.op.solve_in_place(&mut s.y);
            });
        }
        t.elapsed().as_secs_f64() / reps as f64
    }

    /// Like [`Self::substitution_time`], with every interior factor of
    /// the Dirichlet preconditioner (`cg`) and a right-hand side of ones
    /// (0 without interior factors).
    pub fn interior_substitution_time(&mut self, reps: usize) -> f64 {
        let reps = reps.max(1);
        let t = Instant::now();
        for _ in 0..reps {
            self.op.subs.par_iter_mut().for_each(|s| {
                if let Some(ip) = s.interior.as_mut() {
                    ip.substitute_ones();
                }
            });
        }
        t.elapsed().as_secs_f64() / reps as f64
    }

    /// Changes the stopping rule for later solves (the set-up is unchanged).
    pub fn set_stopping(&mut self, tolerance: f64, max_iterations: usize) {
        self.opts.tolerance = tolerance;
        self.opts.max_iterations = max_iterations;
    }

    /// See [`DdSolver::certify`]: `false` lets cg stop as soon as its
    /// indicator meets the tolerance.
    pub(crate) fn set_certified_stop(&mut self, certify: bool) {
        self.certify = certify;
    }

    /// The interface forces of the last solve, interfaces one after the
    /// other (the layout of the decomposition's interface vector).
    pub fn interface_forces(&self) -> Vec<f64> {
        self.forces.iter().flat_map(|f| f.iter().copied()).collect()
    }

    /// The forces the interfaces carry with the current interface forces
    /// `F` (as [`Self::interface_forces`] lays them out): `F + P f`, with
    /// `f` the coarse step's macro forces of a loaded application of the
    /// operator (one solve per subdomain and one coarse solve; the
    /// subdomains' state is left with that application's). Where the next
    /// set-up's macro space differs, they warm-start it better than `F`,
    /// whose macro part only this set-up's coarse step completes.
    pub(crate) fn total_interface_forces(&mut self) -> Vec<f64> {
        self.op.apply(&self.forces, false, true);
        let macro_f = self.op.coarse.as_ref().map(|c| c.macro_forces());
        let mut out = Vec::new();
        for (force, it) in self.forces.iter().zip(&self.op.ifaces) {
            let start = out.len();
            out.extend_from_slice(force);
            if let Some(f) = macro_f {
                for q in 0..it.p.ncols() {
                    let c = f[it.macro_off + q];
                    if c != 0.0 {
                        for j in 0..it.p.nrows() {
                            out[start + j] += it.p[(j, q)] * c;
                        }
                    }
                }
            }
        }
        out
    }

    /// Sets the interface forces a `warm` solve starts from: another
    /// solver's [`Self::interface_forces`] on the same decomposition (the
    /// nonsmooth CG warm-starts each active-set step from the last one).
    pub fn set_interface_forces(&mut self, forces: &[f64]) -> Result<()> {
        let n: usize = self.forces.iter().map(|f| f.len()).sum();
        if forces.len() != n {
            return Err(Error::input(
                "interface forces",
                None,
                format!("has {} entries, expected {n}", forces.len()),
            ));
        }
        let mut off = 0;
        for f in self.forces.iter_mut() {
            let m = f.len();
            f.copy_from_slice(&forces[off..off + m]);
            off += m;
        }
        Ok(())
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
        self.op.ifaces.iter().map(|i| &i.p).collect()
    }

    /// The assembled coarse operator `L` (macro block of the saddle system),
    /// as a dense matrix: for tests on small cases.
    pub fn coarse_operator(&self) -> Option<Mat<f64>> {
        self.op.coarse.as_ref().map(|c| c.operator())
    }

    /// Worst relative residual of the coarse solves since set-up
    /// ([`CoarseProblem::worst_residual`]), if there is a coarse step.
    pub fn coarse_residual(&self) -> Option<f64> {
        self.op.coarse.as_ref().map(|c| c.worst_residual())
    }

    /// The factored coarse problem (multilevel only), e.g. to time its solve.
    pub fn coarse_problem_mut(&mut self) -> Option<&mut CoarseProblem> {
        self.op.coarse.as_mut()
    }

    /// The factored operator of the `s`-th subdomain held here (subdomain
    /// `s` itself unless the set-up is spread over MPI ranks:
    /// [`Self::owned`]).
    pub fn operator(&self, s: usize) -> &SubdomainOperator {
        &self.op.subs[s].op
    }

    /// Mutable access to the operator of the `s`-th subdomain held here
    /// (for solves in tests and tools; the iteration does not depend on its
    /// scratch state).
    pub fn operator_mut(&mut self, s: usize) -> &mut SubdomainOperator {
        &mut self.op.subs[s].op
    }

    /// The factored operators of the subdomains held here, for a later
    /// set-up that reuses them ([`Self::new_reusing`]).
    pub fn into_operators(self) -> Vec<SubdomainOperator> {
        self.op.subs.into_iter().map(|s| s.op).collect()
    }

    /// The subdomains held here, for a later [`Self::new_pooled`].
    pub(crate) fn into_pooled(self) -> Vec<PooledSubdomain> {
        self.op
            .subs
            .into_iter()
            .map(|s| PooledSubdomain {
                op: s.op,
                interior: s.interior,
                face_blocks: s.face_blocks.unwrap_or_default(),
                adaptive: s.side_cache.unwrap_or_default(),
                coarse: s.coarse_kept.map(|b| (s.z, b)),
            })
            .collect()
    }

    /// Number of subdomains (on every process).
    pub fn n_subdomains(&self) -> usize {
        self.dof_maps.len()
    }

    /// The subdomains whose operators this process holds: all of them,
    /// or an MPI rank's block.
    pub fn owned(&self) -> std::ops::Range<usize> {
        self.op.comm.owned()
    }

    /// The set-up's communication seam (its traffic, under MPI).
    pub fn seam(&self) -> &Seam {
        &self.op.comm
    }

    /// Whether this solver runs a coarse step.
    pub fn has_coarse(&self) -> bool {
        self.op.coarse.is_some()
    }

    /// Whether any interface exists (more than one subdomain).
    pub fn has_interfaces(&self) -> bool {
        !self.op.ifaces.is_empty()
    }

    /// Elongation of every element of `model`, each measured in the
    /// displacement copy of the subdomain that owns it (`dec` is the
    /// decomposition this solver was set up on): consistent with the
    /// interface forces, where the assembled displacement averages the
    /// copies across interfaces. Allocates (once per solve).
    pub fn element_elongations(&self, model: &Model, dec: &Decomposition) -> Vec<f64> {
        let mut out = vec![0.0; model.elements.len()];
        self.write_element_elongations(model, dec, None, &mut out);
        out
    }

    /// [`Self::element_elongations`] into `out` (indexed by `model`'s
    /// elements), for a decomposition of a structure whose element `i` is
    /// `model`'s element `ids[i]` (`None`: the same numbering; nodes and
    /// dofs are shared either way). Elements no subdomain holds keep their
    /// value.
    pub(crate) fn write_element_elongations(
        &self,
        model: &Model,
        dec: &Decomposition,
        ids: Option<&[usize]>,
        out: &mut [f64],
    ) {
        let held = &dec.subdomains[self.owned()];
        if self.owned().len() == dec.len() {
            for (sd, st) in held.iter().zip(&self.op.subs) {
                sd.with_numbering(model.n_free, |local| {
                    for &e in &sd.elements {
                        let e = ids.map_or(e, |ids| ids[e]);
                        out[e] = model.elongation_by(e, |d| local.get(d).map_or(0.0, |l| st.v[l]));
                    }
                });
            }
            return;
        }
        // Spread over processes: each element's value comes from the one
        // holding its subdomain, placed in a vector of zeros (exact sum).
        let mut all = vec![0.0; dec.partition.part_of.len()];
        self.op.comm.assemble(&mut all, |s, o| {
            let (sd, st) = (&held[s], &self.op.subs[s]);
            sd.with_numbering(model.n_free, |local| {
                for &e in &sd.elements {
                    o[e] = model.elongation_by(ids.map_or(e, |ids| ids[e]), |d| local.get(d).map_or(0.0, |l| st.v[l]));
                }
            });
        });
        for sd in &dec.subdomains {
            for &e in &sd.elements {
                out[ids.map_or(e, |ids| ids[e])] = all[e];
            }
        }
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
        if self.op.ifaces.is_empty() {
            return Ok(1.0);
        }
        for s in self.op.subs.iter_mut() {
            s.b.iter_mut().for_each(|v| *v = 0.0);
            s.lambda.iter_mut().for_each(|v| *v = 0.0);
        }
        // Deterministic, non-degenerate start vector.
        for (force, it) in self.forces.iter_mut().zip(&self.op.ifaces) {
            for (j, f) in force.iter_mut().enumerate() {
                *f = 1.0 + ((j * 7 + it.lo * 3 + it.hi) % 11) as f64 / 11.0;
            }
        }
        let mut lambda_max = 0.0;
        for _ in 0..POWER_ITERATIONS {
            let norm = self.op.norm2(&self.forces).sqrt();
            if !(norm > 0.0) {
                break;
            }
            for force in self.forces.iter_mut() {
                force.iter_mut().for_each(|f| *f /= norm);
            }
            self.op.apply(&self.forces, false, true);
            // T x = −M J V(x): the force increment for d = −1, from zero.
            for force in self.forces.iter_mut() {
                force.iter_mut().for_each(|f| *f = 0.0);
            }
            self.op.force_stage(&mut self.forces, -1.0);
            lambda_max = self.op.norm2(&self.forces).sqrt();
        }
        for force in self.forces.iter_mut() {
            force.iter_mut().for_each(|f| *f = 0.0);
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
    pub fn solve(&mut self, f_ext: &[f64], warm: bool, progress: Progress<'_>) -> Result<DdOutcome> {
        if f_ext.len() != self.n_free {
            return Err(Error::input(
                "rhs",
                None,
                format!("has {} entries, expected {}", f_ext.len(), self.n_free),
            ));
        }
        self.set_loads(f_ext, true);
        self.iterate(warm, progress)
    }

    /// Each subdomain's right-hand side from the nodal forces `f` (global
    /// dofs; a force on a dof shared by `m` subdomains split equally),
    /// plus its prestrain if `prestrain`.
    fn set_loads(&mut self, f: &[f64], prestrain: bool) {
        let subs_dofs = &self.dof_maps[self.op.comm.owned()];
        self.op
            .subs
            .par_iter_mut()
            .zip(subs_dofs.par_iter())
            .for_each(|(s, dofs)| {
                for (l, &d) in dofs.iter().enumerate() {
                    s.b[l] = f[d] * s.inv_mult[l] + if prestrain { s.prestrain[l] } else { 0.0 };
                }
            });
    }

    /// Solves for right-hand sides given per subdomain in local numbering
    /// (the algebraic level: each subdomain's share of the load).
    pub fn solve_local(&mut self, rhs: &[&[f64]], warm: bool, progress: Progress<'_>) -> Result<DdOutcome> {
        if rhs.len() != self.op.subs.len() {
            return Err(Error::input(
                "rhs",
                None,
                format!("{} subdomain vectors given, expected {}", rhs.len(), self.op.subs.len()),
            ));
        }
        for (i, (s, r)) in self.op.subs.iter().zip(rhs).enumerate() {
            if r.len() != s.b.len() {
                return Err(Error::input(
                    "rhs",
                    Some(i),
                    format!("has {} entries, subdomain {i} has {} dofs", r.len(), s.b.len()),
                ));
            }
        }
        self.op.subs.par_iter_mut().zip(rhs.par_iter()).for_each(|(s, r)| {
            for ((b, &x), &p) in s.b.iter_mut().zip(r.iter()).zip(&s.prestrain) {
                *b = x + p;
            }
        });
        self.iterate(warm, progress)
    }

    /// Iterative refinement of a linear solve that converged, or stalled
    /// (broke down) on a round-off floor, on the subdomain factorizations
    /// and coarse problem already set up ([`Self::correction`]): until it
    /// converges with its tensions leaving the loads unbalanced by less
    /// than `REFINE_ABOVE` times the tolerance, at most `MAX_CORRECTIONS`
    /// corrections, a stalled one followed by another only if it got the
    /// indicator `CORRECTION_PROGRESS` lower. The floor a DD solve reaches (its subdomains'
    /// round-off times the rigid-body amplitudes of floating subdomains)
    /// is relative to what the subdomains solve for, and a correction
    /// solves for the unbalanced loads only, 1e-8 of the solution: the 410²
    /// plate on 64 subdomains went from a residual of 1.7e-8 (tensions
    /// 1.25e-8 off the direct solve's) to 4e-15 (2.8e-10 off).
    /// `tension(e, elongation)` is element `e`'s tension in the solved
    /// (linear) structure, 0 for an element it does not hold; `ids` as in
    /// [`Self::write_element_elongations`]. The corrections are added to
    /// `solve`'s displacements and elongations, their iterations and
    /// history entries to its own.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn refine_equilibrium(
        &mut self,
        model: &Model,
        dec: &Decomposition,
        ids: Option<&[usize]>,
        f_ext: &[f64],
        tension: &dyn Fn(usize, f64) -> f64,
        solve: Refined<'_>,
    ) -> Result<Option<Refinement>> {
        let tolerance = self.opts.tolerance;
        let mut refinement: Option<Refinement> = None;
        let mut indicator = solve.history.last().map_or(f64::INFINITY, |h| h.indicator);
        for k in 0..MAX_CORRECTIONS {
            let converged = *solve.status == Status::Converged;
            if !converged && !matches!(*solve.status, Status::Stalled | Status::Breakdown) {
                break;
            }
            let tensions: Vec<f64> = solve
                .elongations
                .iter()
                .enumerate()
                .map(|(e, &x)| tension(e, x))
                .collect();
            let Some((unbalanced, r)) = model.unbalanced_forces(f_ext, &tensions, solve.u) else {
                break;
            };
            if converged && r <= REFINE_ABOVE * tolerance {
                break;
            }
            let corr = self.correction(model, dec, ids, &unbalanced)?;
            let Some(de) = corr.elongations else {
                break;
            };
            solve.elongations.iter_mut().zip(&de).for_each(|(e, d)| *e += d);
            solve.u.iter_mut().zip(&corr.u).for_each(|(u, d)| *u += d);
            let rf = refinement.get_or_insert(Refinement {
                corrections: 0,
                iterations: 0,
                residual_before: r,
            });
            rf.corrections = k + 1;
            rf.iterations += corr.iterations;
            let done = *solve.iterations;
            let t_done = solve.history.last().map_or(0.0, |h| h.time_s);
            *solve.iterations += corr.iterations;
            solve.history.extend(corr.history.into_iter().map(|mut h| {
                h.iteration += done;
                h.time_s += t_done;
                h
            }));
            if corr.status == Status::Converged {
                (*solve.status, *solve.message) = (Status::Converged, None);
                continue;
            }
            // A correction that stopped on its own floor, far below the
            // one it started from, is followed by another from there.
            let reached = solve.history.last().map_or(f64::INFINITY, |h| h.indicator);
            let progress = reached < CORRECTION_PROGRESS * indicator;
            indicator = reached;
            let why = corr.message.map(|m| format!(": {m}")).unwrap_or_default();
            if converged {
                *solve.status = corr.status;
                *solve.message = Some(format!(
                    "the correction for the loads its tensions left unbalanced ({r:.1e} of their norm) {}{why}",
                    corr.status.describe()
                ));
            } else if progress && corr.status == Status::Stalled {
                continue;
            } else if let Some(m) = solve.message.as_mut() {
                m.push_str(&format!(
                    "; {} correction{} from that state, on the loads its tensions left unbalanced, took the \
                     indicator to {reached:.1e} and {} too{why}",
                    k + 1,
                    if k == 0 { "" } else { "s" },
                    corr.status.describe()
                ));
            }
            break;
        }
        Ok(refinement)
    }

    /// One equilibrium correction of a linear solve (no unilateral
    /// cables): the method is run again from zero interface forces on the
    /// loads `unbalanced` that the solve's tensions leave (see
    /// [`Model::unbalanced_forces`]), with the solve's interface jump added
    /// to every jump of its iterates. The subdomains then solve for the
    /// unbalanced loads alone, and what the method measures, and drives
    /// below the tolerance, is the sum's jump, against the solve's force
    /// and displacement scales ([`Self::force_scale`],
    /// [`Self::displacement_scale`]), without the certificate of a
    /// relative error (the correction's own error matters only against the
    /// sum). Returns the correction: `u`, and `elongations` indexed like
    /// `model`'s elements (from `u` for those no subdomain holds), for the
    /// caller to add; the solver's state (interface forces, displacements)
    /// becomes the sum, so a warm start goes on from it. A correction that
    /// does not end finite leaves the solve as it was (`elongations`
    /// `None`).
    fn correction(
        &mut self,
        model: &Model,
        dec: &Decomposition,
        ids: Option<&[usize]>,
        unbalanced: &[f64],
    ) -> Result<Outcome> {
        debug_assert_eq!(self.n_cables, 0, "a correction superposes: linear solves only");
        let floors = (self.force_scale(self.load_norm()), self.subdomain_v_norm());
        let forces = self.forces.clone();
        let saved: Vec<(Vec<f64>, Vec<f64>)> = self.op.subs.iter().map(|s| (s.v.clone(), s.b.clone())).collect();
        self.op.jumps(None);
        for it in self.op.ifaces.iter_mut() {
            it.base_jump = it.jump.clone();
        }
        self.set_loads(unbalanced, false);
        let certify = std::mem::replace(&mut self.certify, false);
        self.scale_floors = floors;
        let out = self.iterate(false, None);
        self.scale_floors = (0.0, 0.0);
        self.certify = certify;
        for it in self.op.ifaces.iter_mut() {
            it.base_jump = Vec::new();
        }
        // The solve's state comes back whatever the correction's ending, an
        // error included.
        let mut out = out;
        let finite = matches!(&out, Ok(o) if o.u.iter().all(|x| x.is_finite()));
        if let (true, Ok(o)) = (finite, out.as_mut()) {
            let mut e: Vec<f64> = (0..model.elements.len()).map(|e| model.elongation(e, &o.u)).collect();
            self.write_element_elongations(model, dec, ids, &mut e);
            o.elongations = Some(e);
        }
        for (s, (v0, b0)) in self.op.subs.iter_mut().zip(saved) {
            if finite {
                s.v.iter_mut().zip(&v0).for_each(|(x, x0)| *x += x0);
            } else {
                s.v = v0;
            }
            s.b = b0;
        }
        for (f, f0) in self.forces.iter_mut().zip(&forces) {
            if finite {
                f.iter_mut().zip(f0).for_each(|(x, x0)| *x += x0);
            } else {
                f.copy_from_slice(f0);
            }
        }
        // The jumps of the sum, for what reads them next.
        self.op.jumps(None);
        out
    }

    /// `‖V‖` over the subdomains' current displacements.
    fn subdomain_v_norm(&self) -> f64 {
        self.op.comm.sum_subdomains(|s| [kernels::norm2(&self.op.subs[s].v)])[0].sqrt()
    }

    /// Runs the configured method (a module of [`crate::method`]).
    fn iterate(&mut self, warm: bool, progress: Progress<'_>) -> Result<Outcome> {
        on_workers(self.op.comm.in_process(), || {
            if self.opts.krylov {
                self.iterate_cg(warm, progress)
            } else {
                self.iterate_stationary(warm, progress)
            }
        })
    }

    /// Zero interface forces and cable slacks: a cold start.
    pub(crate) fn reset_unknowns(&mut self) {
        self.op.reset_slacks();
        for force in self.forces.iter_mut() {
            force.iter_mut().for_each(|f| *f = 0.0);
        }
    }

    /// The force scale of the indicators: the larger of the load norm and
    /// the norm of the interface forces. The unbalanced force a jump leaves
    /// (`k ∘ J V`) is an error in the tensions of the elements at the cut,
    /// so it is measured against the forces the structure carries there;
    /// on large soft plates those are 10³–10⁴ × the load, and against the
    /// load alone the indicator stalled at 3e-4 on its round-off floor while
    /// the true error was 1e-8 (300 × 300 grid, 64 subdomains).
    pub(crate) fn force_scale(&self, b_norm: f64) -> f64 {
        let f2 = self.op.norm2(&self.forces);
        b_norm.max(f2.sqrt()).max(self.scale_floors.0).max(f64::MIN_POSITIVE)
    }

    /// The displacement scale of the jump indicator: `‖V‖`, or the solve's
    /// own during an equilibrium correction ([`Self::correction`]).
    pub(crate) fn displacement_scale(&self, v_norm: f64) -> f64 {
        v_norm.max(self.scale_floors.1).max(f64::MIN_POSITIVE)
    }

    /// Norm of the assembled right-hand side (loads and prestrain).
    pub(crate) fn load_norm(&self) -> f64 {
        self.op.load_norm(&self.dof_maps[self.op.comm.owned()], self.n_free)
    }

    /// Global displacement (average of the subdomain copies) and slacks.
    pub(crate) fn assemble(&self) -> (Vec<f64>, Vec<f64>) {
        self.op
            .assemble(&self.dof_maps[self.op.comm.owned()], self.n_free, self.n_cables)
    }
}

/// Iterative refinement of a linear DD solve: at most this many
/// corrections.
const MAX_CORRECTIONS: usize = 3;

/// A correction that stalls with its indicator below this fraction of the
/// one it started from is followed by another.
const CORRECTION_PROGRESS: f64 = 0.1;

/// A converged linear DD solve whose tensions leave more than this fraction
/// of the tolerance unbalanced is refined. The true tension error has been
/// measured at 0.6–1.8 × that residual on towers and small plates, but at
/// 2.4 × and 17 × on the 1e6-dof plate cut in 16 and 4 (subdomains of 63k
/// and 250k dofs, whose solves' forward error the residual hardly shows):
/// 1.1e-8 and 3.1e-8 for a tolerance of 1e-8, where 0.5 left them alone.
/// One correction takes them to 3e-11 and 6e-11; below 0.05 the plates and towers
/// cut in 4–64 would pay a correction's 3 iterations for nothing.
const REFINE_ABOVE: f64 = 0.05;

/// The parts of a solve's outcome that [`DdSolver::refine_equilibrium`]
/// adds its corrections to.
pub(crate) struct Refined<'a> {
    /// Displacements of the free dofs.
    pub u: &'a mut [f64],
    /// Element elongations, indexed like the model's elements.
    pub elongations: &'a mut [f64],
    pub history: &'a mut Vec<crate::result::HistoryEntry>,
    pub iterations: &'a mut usize,
    /// How the solve ended, and why if not converged: a solve stalled (or
    /// broken down) on a round-off floor is continued by a correction too.
    pub status: &'a mut Status,
    pub message: &'a mut Option<String>,
}

/// A small linear grid on 6 subdomains and `cg` options (Dirichlet,
/// deluxe) for the unit tests of the set-up and the operator.
#[cfg(test)]
pub(crate) fn cg_test_problem() -> (Model, Decomposition, DdOptions) {
    use crate::generate::{grid, GridParams};
    let scene = grid(&GridParams {
        nx: 8,
        ny: 6,
        unilateral: false,
        ..Default::default()
    });
    cg_test_problem_on(&scene, 6)
}

/// [`cg_test_problem`]'s options on `scene` cut into `subdomains`.
#[cfg(test)]
pub(crate) fn cg_test_problem_on(scene: &crate::scene::Scene, subdomains: usize) -> (Model, Decomposition, DdOptions) {
    let model = Model::from_scene(scene).unwrap();
    let dec = crate::solve::decompose(&model, scene, subdomains).unwrap();
    let opts = DdOptions {
        coarse: true,
        tolerance: 1e-8,
        max_iterations: 10,
        search_direction: SearchDirection::Auto,
        krylov: true,
        preconditioner: Preconditioner::Dirichlet,
        interface_scaling: InterfaceScaling::Deluxe,
        adaptive_threshold: AdaptiveThreshold::OFF,
        adaptive_edges: AdaptiveEdges::Off,
        macro_degree: MacroDegree::Fixed(1),
        ordering: Default::default(),
    };
    (model, dec, opts)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::outcome::Status;

    /// A set-up that takes every subdomain over from an earlier one of the
    /// same structure (operators, interior factors, deluxe face blocks,
    /// coarse blocks)
    /// solves with the same bits as a fresh one: what it takes over is
    /// what it would have computed. A stale interior factor or face block
    /// (of another interface) would change the preconditioner, and with it
    /// the iterates.
    #[test]
    fn a_pooled_set_up_solves_with_the_bits_of_a_fresh_one() {
        let (model, dec, mut opts) = cg_test_problem();
        (opts.tolerance, opts.max_iterations) = (1e-10, 200);
        let f = model.load_cases[0].clone();
        let mut fresh = DdSolver::new_pooled(&model, &dec, opts.clone(), Vec::new(), Placement::Process).unwrap();
        assert_eq!(fresh.stats.interiors_reused, 0);
        assert_eq!(fresh.stats.face_blocks_reused, 0);
        let a = fresh.solve(&f, false, None).unwrap();
        assert_eq!(a.status, Status::Converged);
        let pooled: Vec<Option<PooledSubdomain>> = fresh.into_pooled().into_iter().map(Some).collect();
        let faces: usize = pooled.iter().flatten().map(|p| p.face_blocks.len()).sum();
        assert!(faces >= dec.interfaces.len(), "{faces} face blocks kept");
        let mut again = DdSolver::new_pooled(&model, &dec, opts, pooled, Placement::Process).unwrap();
        assert_eq!(again.stats.interiors_reused, dec.len());
        assert_eq!(again.stats.face_blocks_reused, faces);
        assert_eq!(again.stats.coarse_blocks_reused, dec.len());
        let b = again.solve(&f, false, None).unwrap();
        assert_eq!(a.iterations, b.iterations);
        assert!(a.u.iter().zip(&b.u).all(|(x, y)| x.to_bits() == y.to_bits()));
    }

    /// The set-up computes the interior factors and deluxe blocks beside
    /// the coarse problem, on a layout made before it; weights set again
    /// afterwards, the plain way (`set_interface_scaling`), give the same
    /// preconditioner: the same iterates, bit for bit. A block of the wrong
    /// subdomain or rows would change them.
    #[test]
    fn deluxe_blocks_made_beside_the_coarse_problem_are_the_plain_ones() {
        let (model, dec, mut opts) = cg_test_problem();
        (opts.tolerance, opts.max_iterations) = (1e-10, 200);
        let f = model.load_cases[0].clone();
        for kind in [InterfaceScaling::Deluxe, InterfaceScaling::EconomicDeluxe] {
            opts.interface_scaling = kind;
            let mut dd = DdSolver::new(&model, &dec, opts.clone()).unwrap();
            let a = dd.solve(&f, false, None).unwrap();
            assert_eq!(a.status, Status::Converged, "{kind:?}");
            dd.set_interface_scaling(kind);
            let b = dd.solve(&f, false, None).unwrap();
            assert_eq!(a.iterations, b.iterations, "{kind:?}");
            assert!(
                a.u.iter().zip(&b.u).all(|(x, y)| x.to_bits() == y.to_bits()),
                "{kind:?}"
            );
            // Without scaling the iterates differ: the test can tell.
            dd.set_interface_scaling(InterfaceScaling::Multiplicity);
            let c = dd.solve(&f, false, None).unwrap();
            assert!(
                a.u.iter().zip(&c.u).any(|(x, y)| x.to_bits() != y.to_bits()),
                "{kind:?}"
            );
        }
    }

    /// The forces the interfaces carry (`F + P f`) warm-start a set-up
    /// with another macro space; CG's iterate `F` alone does not: its
    /// macro part was the old coarse step's. Solved with quadratic macro
    /// fields, the same structure set up with linear ones starts from `F`
    /// far from the solution, from `F + P f` at it.
    #[test]
    fn carried_forces_warm_start_another_macro_space() {
        let (model, dec, mut opts) = cg_test_problem();
        (opts.tolerance, opts.max_iterations) = (1e-10, 200);
        let f = model.load_cases[0].clone();
        opts.macro_degree = MacroDegree::Fixed(2);
        let mut quadratic = DdSolver::new(&model, &dec, opts.clone()).unwrap();
        let solved = quadratic.solve(&f, false, None).unwrap();
        assert_eq!(solved.status, Status::Converged);
        let iterate = quadratic.interface_forces();
        let carried = quadratic.total_interface_forces();
        opts.macro_degree = MacroDegree::Fixed(1);
        let mut linear = DdSolver::new(&model, &dec, opts).unwrap();
        let mut start = |forces: &[f64]| {
            linear.set_interface_forces(forces).unwrap();
            let out = linear.solve(&f, true, None).unwrap();
            assert_eq!(out.status, Status::Converged);
            let e = solved
                .u
                .iter()
                .zip(&out.u)
                .map(|(a, b)| (a - b).powi(2))
                .sum::<f64>()
                .sqrt()
                / solved.u.iter().map(|a| a * a).sum::<f64>().sqrt();
            assert!(e < 1e-8, "{e:.1e}");
            (out.history[0].indicator, out.iterations)
        };
        let (from_carried, its_carried) = start(&carried);
        let (from_iterate, its_iterate) = start(&iterate);
        assert!(from_carried < 1e-8, "{from_carried:.1e}");
        assert!(from_iterate > 1e-4, "{from_iterate:.1e}");
        assert!(its_carried < its_iterate, "{its_carried} against {its_iterate}");
    }

    /// The README's tower, taut (bars 1e4 × the cables), on 4 subdomains,
    /// with cg's options to 1e-8.
    fn readme_tower_problem() -> (Model, Decomposition, DdOptions) {
        let scene = crate::generate::tower(&crate::generate::TowerParams {
            nx: 2,
            ny: 2,
            nz: 10,
            unilateral: false,
            ..Default::default()
        });
        let (model, dec, mut opts) = cg_test_problem_on(&scene, 4);
        (opts.tolerance, opts.max_iterations) = (1e-8, 500);
        (model, dec, opts)
    }

    /// An adaptive set-up taken over keeps its Neumann blocks (same
    /// operator, same rows) and its face constraints (same sides, macro
    /// columns and threshold), and solves with the bits of a fresh one; a
    /// new threshold keeps the blocks but solves every face eigenproblem
    /// again.
    #[test]
    fn adaptive_blocks_are_taken_over_with_their_operator() {
        let (model, dec, mut opts) = readme_tower_problem();
        opts.adaptive_threshold = AdaptiveThreshold::Value(10.0);
        let f = model.load_cases[0].clone();
        let mut fresh = DdSolver::new_pooled(&model, &dec, opts.clone(), Vec::new(), Placement::Process).unwrap();
        assert!(fresh.stats.adaptive_columns > 0, "the threshold adds columns");
        assert_eq!(
            (fresh.stats.neumann_blocks_reused, fresh.stats.face_constraints_reused),
            (0, 0)
        );
        let a = fresh.solve(&f, false, None).unwrap();
        assert_eq!(a.status, Status::Converged);
        let pooled: Vec<Option<PooledSubdomain>> = fresh.into_pooled().into_iter().map(Some).collect();
        let faces = crate::adaptive::face_entries(&dec)
            .iter()
            .filter(|f| !f.is_empty())
            .count();
        let mut again = DdSolver::new_pooled(&model, &dec, opts.clone(), pooled, Placement::Process).unwrap();
        // Two sides per face.
        assert_eq!(again.stats.neumann_blocks_reused, 2 * faces);
        assert_eq!(again.stats.face_constraints_reused, faces);
        let b = again.solve(&f, false, None).unwrap();
        assert_eq!(a.iterations, b.iterations);
        assert!(a.u.iter().zip(&b.u).all(|(x, y)| x.to_bits() == y.to_bits()));
        // Another threshold: other constraints, from the same blocks.
        opts.adaptive_threshold = AdaptiveThreshold::Value(3.0);
        let pooled: Vec<Option<PooledSubdomain>> = again.into_pooled().into_iter().map(Some).collect();
        let mut third = DdSolver::new_pooled(&model, &dec, opts.clone(), pooled, Placement::Process).unwrap();
        assert_eq!(third.stats.neumann_blocks_reused, 2 * faces);
        assert_eq!(third.stats.face_constraints_reused, 0);
        let mut own = DdSolver::new_pooled(&model, &dec, opts, Vec::new(), Placement::Process).unwrap();
        assert_eq!(third.stats.adaptive_columns, own.stats.adaptive_columns);
        let c = third.solve(&f, false, None).unwrap();
        let d = own.solve(&f, false, None).unwrap();
        assert_eq!(c.iterations, d.iterations);
        assert!(c.u.iter().zip(&d.u).all(|(x, y)| x.to_bits() == y.to_bits()));
    }

    /// Coarse blocks are taken over only where the macro columns are the
    /// same: a set-up whose macro space grew (adaptive columns) from a
    /// pool of one without them solves with the bits of a fresh set-up of
    /// its own, its enriched subdomains solved again. Taking `Z_E`, `L_E`
    /// over by the operator alone would pair them with the wrong columns
    /// (or panic on their sizes).
    #[test]
    fn coarse_blocks_are_taken_over_only_for_the_same_macro_columns() {
        let (model, dec, mut opts) = readme_tower_problem();
        let f = model.load_cases[0].clone();
        let plain = DdSolver::new_pooled(&model, &dec, opts.clone(), Vec::new(), Placement::Process).unwrap();
        // Operators and coarse blocks only: the adaptive set-up takes kept
        // face blocks over as its principal blocks, which have other bits.
        let strip = |p: PooledSubdomain| {
            Some(PooledSubdomain {
                interior: None,
                face_blocks: Vec::new(),
                adaptive: Default::default(),
                ..p
            })
        };
        let pooled: Vec<Option<PooledSubdomain>> = plain.into_pooled().into_iter().map(strip).collect();
        opts.adaptive_threshold = AdaptiveThreshold::Value(10.0);
        let mut fresh = DdSolver::new_pooled(&model, &dec, opts.clone(), Vec::new(), Placement::Process).unwrap();
        assert!(fresh.stats.adaptive_columns > 0, "the threshold adds columns");
        let mut again = DdSolver::new_pooled(&model, &dec, opts.clone(), pooled, Placement::Process).unwrap();
        let kept = again.stats.coarse_blocks_reused;
        assert!(kept < dec.len(), "{kept} of {} subdomains kept stale blocks", dec.len());
        // The enriched subdomains keep `K⁺ W` for the columns that did not
        // change and solve for the others.
        assert!(again.stats.coarse_columns_reused > 0);
        let a = fresh.solve(&f, false, None).unwrap();
        let b = again.solve(&f, false, None).unwrap();
        assert_eq!(a.status, Status::Converged);
        assert_eq!(a.iterations, b.iterations);
        assert!(a.u.iter().zip(&b.u).all(|(x, y)| x.to_bits() == y.to_bits()));
        // Blocks kept for other columns of the same shape (here: the
        // columns negated, the blocks zeroed) are not taken over either.
        let pooled: Vec<Option<PooledSubdomain>> = again
            .into_pooled()
            .into_iter()
            .map(|mut p| {
                if let Some((z, b)) = p.coarse.as_mut() {
                    b.w = -&b.w;
                    b.l.fill(0.0);
                    z.data.fill(0.0);
                }
                strip(p)
            })
            .collect();
        let mut third = DdSolver::new_pooled(&model, &dec, opts, pooled, Placement::Process).unwrap();
        assert_eq!(third.stats.coarse_blocks_reused, 0);
        assert_eq!(third.stats.coarse_columns_reused, 0);
        let c = third.solve(&f, false, None).unwrap();
        assert!(a.u.iter().zip(&c.u).all(|(x, y)| x.to_bits() == y.to_bits()));
    }

    /// Only columns equal bit for bit keep their `Z` column, wherever they
    /// moved; a column that differs in one entry (or only in the sign of
    /// zero) is left to solve.
    #[test]
    fn unchanged_columns_keep_their_solution_wherever_they_moved() {
        let w_old = Mat::from_fn(3, 3, |i, j| (i + 3 * j) as f64 + 1.0);
        let z_old = MacroResponses::new((0..15).map(|k| 100.0 * (k / 5) as f64 + (k % 5) as f64).collect(), 5);
        // New columns: old 2, old 0 changed in one entry, old 1, and zeros.
        let mut w = Mat::zeros(3, 4);
        w.col_mut(0).copy_from(w_old.col(2));
        w.col_mut(1).copy_from(w_old.col(0));
        w[(1, 1)] += 1e-15;
        w.col_mut(2).copy_from(w_old.col(1));
        let mut z = vec![-1.0; 5 * 4];
        let fresh = take_unchanged_columns(&w_old, &z_old, &w, &mut z);
        assert_eq!(fresh, vec![1, 3]);
        assert_eq!(&z[0..5], &[200.0, 201.0, 202.0, 203.0, 204.0]);
        assert_eq!(&z[10..15], &[100.0, 101.0, 102.0, 103.0, 104.0]);
        assert!(z[5..10].iter().chain(&z[15..20]).all(|&v| v == -1.0));
        let zero = Mat::<f64>::zeros(3, 1);
        let neg = Mat::from_fn(3, 1, |_, _| -0.0);
        let mut z1 = vec![0.0; 5];
        assert_eq!(
            take_unchanged_columns(&zero, &MacroResponses::new(vec![0.0; 5], 5), &neg, &mut z1),
            vec![0]
        );
    }
}
