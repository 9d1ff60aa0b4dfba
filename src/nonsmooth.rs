//! Nonsmooth interface CG (issue #17, design 2): a primal–dual active set
//! on the cable slacks around the linear interface CG.
//!
//! Each outer step takes the structure with its current slack cables
//! removed (zero axial stiffness, so zero tension) and solves it by the
//! linear DD CG; the set is then updated by the rule of the direct solver
//! (`src/direct.rs`): a slack cable whose slack `λ = −(e + e0)` is negative
//! becomes taut, a taut cable whose strain `e + e0` is negative goes slack;
//! a revisited set switches to Murty's least-index rule. A set whose
//! structure is a mechanism is stepped through with its slack cables
//! softened to [`SOFT`] of their stiffness (a guide step, as the direct
//! solver does); a final set that is one is a named [`Error::Mechanism`].
//! Such a set's set-up stops at the first partition that finds the
//! mechanism (it is the structure's, so every partition has it); a set
//! that settles on its softened step is tried on all of them before it
//! is named.
//!
//! The inner solves are inexact: their tolerance follows the size of the
//! last complementarity violation (loose while the set moves, tighter
//! once a step flips at most [`ENDGAME_FLIPS`] of the cables, the set's
//! tolerance once the set has settled and from the first solve at that
//! tolerance on; the set's tolerance is the requested one, or
//! [`SET_TOLERANCE`] where that is looser), and each starts from the
//! interface forces of the previous one: CG's iterate `F` while the set
//! moves, and in the tail the forces the interfaces carried, `F + P f`
//! with the coarse step's macro forces (one more application of the last
//! operator), which a new set whose kernels moved with its flips would
//! otherwise recompute from nothing. A loose solve stops on its indicator
//! alone; the set is accepted only after a certified solve at the set's
//! tolerance leaves it unchanged, or leaves no violation above the
//! requested tolerance where that is looser. A set that stops settling
//! ([`UNSETTLED_STEPS`] steps without cutting the fewest flips by a tenth)
//! ends the solve unconverged, with a message that says so.
//!
//! Each new slack set gets a new [`DdSolver`] (macro space and coarse
//! problem rebuilt), but only the subdomains whose elements or local dof
//! layout changed are refactored: the others take their operator over from
//! the previous set-up (see [`NonsmoothOutcome::reused`]), and, where their
//! interface dofs are unchanged too, their interior (Dirichlet) factor and
//! the deluxe face blocks of their unchanged faces; and, where their macro
//! columns are unchanged too, their coarse blocks. The last set-up is
//! kept, so load steps and load cases whose set does not change cost no
//! set-up.
//!
//! Every step keeps a slack cable's geometric stiffness `t0 / L` (the
//! prestress's `K_G` does not change as cables go slack, docs/design.md
//! §1, and both paths of the direct solver keep it too); an exact step
//! drops the axial stiffness, and the cable itself where it has no
//! geometric stiffness.
//!
//! `NSDD_NS_DEBUG=1` prints one line per outer step (set size, inner
//! tolerance and iterations, set-up and CG time, coarse sizes) to stderr,
//! and why an exact set-up gave way to a softened one.
//!
//! Not done yet: low-rank updates instead of refactoring, and reusing the
//! factorization of the coarse problem itself.

use crate::comm::Placement;
use crate::dd::{DdOptions, DdSolver, PooledSubdomain, Refined};
use crate::decomposition::Decomposition;
use crate::direct::Equilibrium;
use crate::error::{Error, Result};
use crate::method::{on_workers, Progress};
use crate::model::Model;
use crate::model::FIXED;
use crate::outcome::{Refinement, Status};
use crate::partition::Partition;
use crate::result::HistoryEntry;
use crate::scaling::InterfaceScaling;
use crate::scene::{OrderingChoice, Preconditioner, SearchDirection};
use crate::settings::{AdaptiveEdges, AdaptiveThreshold, MacroDegree};
use std::collections::{HashMap, HashSet};

/// Stiffness fraction kept by slack cables in a step whose slack set alone
/// would be a mechanism. Larger than the direct solver's 1e-6: subdomain
/// factorizations take pivots below 1e-9 of the diagonal for mechanisms
/// (and below 1e-6 for suspects), and with a bar/cable contrast of 1e4 a
/// 1e-6 cable falls below that.
pub const SOFT: f64 = 1e-3;

/// Least softened stiffness, as a fraction of the stiffest element: keeps
/// the softened pivots above the subdomain's suspect ratio (1e-6) whatever
/// the contrast (the README's tower: bars 1e4 × the cables).
pub const SOFT_FLOOR: f64 = 1e-4;

/// Loosest inner tolerance (the first step, and steps after large
/// violations): a set from a solve this accurate is close enough to guide
/// the next one. An outer step costs a DD set-up, worth 15-25 inner
/// iterations on the grids (the 130² grid with 16 subdomains: 0.4-0.9 s
/// against 0.03 s), so the tolerances are chosen for fewer steps rather
/// than fewer iterations. With this and [`INNER_TOL_FACTOR`] at 1e-2 and
/// 0.1 (before session 38), the strains of the loose steps were too
/// inexact to decide the last few hundred cables: the 130² grid took 24 /
/// 22 steps (16 / 64 subdomains) where the direct solver takes 16; at
/// 1e-3 and 0.03 it takes 18 / 18 (BENCHMARKS.md, "Fewer active-set
/// steps"). The early steps are capped anyway ([`EARLY_STOP_ITERATIONS`]),
/// so their tighter tolerance costs few iterations.
pub const INNER_TOL_MAX: f64 = 1e-3;

/// Inner tolerance as a fraction of the last relative violation (see
/// [`INNER_TOL_MAX`]; 0.01 took the same steps with 3-10 % more
/// iterations).
pub const INNER_TOL_FACTOR: f64 = 0.03;

/// Loosest tolerance a cable set is decided at, whatever the requested
/// one: the schedule's solves go down to it and violations above it flip
/// cables. A looser request only lets a set be accepted earlier (below).
/// At the requested tolerance 1e-3 the tail's solves, the flips and the
/// confirmations all ran at 1e-3: only the violations above 1e-3 of the
/// strain scale flipped, the smaller ones the flips move about were never
/// settled, and the 130² grid cut in 16 took 27 set-ups and 21–25 s where
/// 1e-8 takes 17 and 15 s (BENCHMARKS.md, "Cable sets decided at 1e-6 at
/// most").
pub const SET_TOLERANCE: f64 = 1e-6;

/// Flips, as a fraction of the cables, at or below which the next set is
/// solved at the set's tolerance ([`SET_TOLERANCE`]) and the ones after it at
/// [`ENDGAME_TOL_FACTOR`] of their violation. The active set then
/// is in the tail the direct solver has too (halving the flips at each
/// step); with the loose steps' strains the cables near zero strain were
/// decided again and again: the nonsmooth 410² grid (1e6 dofs) with 64
/// subdomains took 60 steps where the direct solver takes 29, 40 with the
/// tail at the requested tolerance and 15 % less time; the 32² to 200²
/// grids one to seven steps fewer (BENCHMARKS.md, "exact steps in the
/// active set's tail").
pub const ENDGAME_FLIPS: f64 = 1e-3;

/// Inner tolerance of the tail's steps ([`ENDGAME_FLIPS`]) after its first
/// set, as a fraction of the last relative violation: a thirtieth of the
/// loose steps' [`INNER_TOL_FACTOR`]. The set they settle on is then
/// confirmed at the set's tolerance, from where they left it. Solving
/// every tail set to the requested tolerance took the same set-ups and
/// 13 % more iterations on the 130² grid cut in 16 (145 against 128); the
/// tail's first set stays at the tolerance, because few flips after a
/// loose step can hide many small violations (the nonsmooth 30³ tower: 8
/// flips, then 3 998; taken loosely, 8 set-ups instead of 4).
/// BENCHMARKS.md, "The active set's tail at a tolerance tied to its
/// violation".
pub const ENDGAME_TOL_FACTOR: f64 = 1e-3;

/// Flips at or below which the tail's next set is solved at the set's
/// tolerance rather than at [`ENDGAME_TOL_FACTOR`] of its violation: it is
/// then most likely the last set, and a looser solve would need a
/// confirmation at the tolerance after it.
pub const ENDGAME_LAST_FLIPS: usize = 4;

/// Backward error of the coarse solves as a fraction of the inner
/// tolerance (the coarse problem clamps it at round-off, its default).
/// The coarse problems of the structures without their slack cables are
/// ill-conditioned enough that the default 1e-15 is at their round-off
/// floor: its GMRES refinement then ran 15-30 iterations per coarse solve
/// (7 096 in the 290 CG iterations of the 32² grid, 16 subdomains, 60 % of
/// the solve time); a millionth of the inner tolerance took 37 in all, for
/// the same error against direct (7e-12) and 296 CG iterations. But a
/// loose coarse solve can stall the loose inner solves of ill-conditioned
/// sets (their indicator falls for ~10 iterations and grows back, restart
/// after restart): at 1e-10 instead of 1e-6 the nonsmooth 130² grid takes
/// 365 / 325 iterations with 16 / 64 subdomains instead of 689 / 463, the
/// 32² grid with 64 subdomains 83 instead of 147, in less time; 1e-12 and
/// the round-off default cost up to 1.8× more time on the 65² grid for no
/// fewer iterations (BENCHMARKS.md, "Cheaper set-up"). Those figures are
/// of the normwise backward error; since it is measured on the
/// Jacobi-scaled macro block (stricter on all but the softest rows), 1e-10
/// made each coarse solve of the 30³ nonsmooth tower's loose steps refine
/// with 7 solves instead of 1 (inner CG 4-9 s per step instead of 1.5 s),
/// and 1e-8 gives back the earlier costs: the grids above take 189 / 194
/// (65²) and 379 / 326 (130²) iterations with 16 / 64 subdomains, against
/// 188 / 194 and 365 / 325 before the change of measure.
pub const COARSE_TARGET_FACTOR: f64 = 1e-8;

/// Inner iterations allowed to a step whose set is clearly wrong (last
/// relative violation at least [`EARLY_STOP_VIOLATION`]; the first step
/// counts as one). On the 32² grid to 1e-8 (`nsdd solve g32.toml --method
/// cg --subdomains 16`): no cap 296 iterations in 11 steps, 15 → 200 in
/// 11, 10 → 263 in 14, 5 → 207 in 16; with 5 and a threshold of 0.01 the
/// set no longer settled within a minute. Softened (mechanism) steps are
/// never stopped early: doing so led the tower of
/// `slack_set_with_a_mechanism_is_named_like_direct` to another set.
pub const EARLY_STOP_ITERATIONS: usize = 15;

/// See [`EARLY_STOP_ITERATIONS`].
pub const EARLY_STOP_VIOLATION: f64 = 0.1;

/// Indicator above which a step stopped at [`EARLY_STOP_ITERATIONS`] shows
/// the cap is far too short for this structure: no later step is capped.
/// The cap assumes a few iterations bring a step near its loose tolerance
/// (the grids' capped steps end at 0.02-1.1 for 1e-2). On the nonsmooth
/// cubic towers (`gen tower nx=n ny=n nz=n`: bars 1e4 × the cables, whose
/// linear solve takes hundreds of iterations) the first capped step ends
/// at 5e2-8e3 (12³: from 1e4 to 4e3 at 4 subdomains): their sets were
/// noise, and the set never settled (34 steps, tensions 120 % off), where
/// full inner solves settle it in 5 steps.
pub const EARLY_STOP_LIFT: f64 = 10.0;

/// Outer steps a solve may go without cutting its fewest flips so far by
/// a tenth before it ends as `stalled`: the cable set is
/// not settling. On the nonsmooth 30³ tower with 64 subdomains the set
/// flipped 4 000-11 000 cables per step for 62 steps (15 minutes, still
/// going) without settling; the grids cut their flips by a third or more
/// per step, and Murty's least-index rule, one flip per step, removes a
/// tenth of a few violations within a few steps.
pub const UNSETTLED_STEPS: usize = 30;

/// Whether the cable set is still settling (see [`UNSETTLED_STEPS`]).
#[derive(Debug, Clone)]
struct Settling {
    fewest: usize,
    at: usize,
    window: usize,
}

impl Settling {
    /// A solve that may go `window` outer steps without progress.
    fn new(window: usize) -> Settling {
        Settling {
            fewest: usize::MAX,
            at: 0,
            window,
        }
    }

    /// Records the flips (violations) found after outer step `step`;
    /// `false` once `window` steps have passed without a count below
    /// 0.9 × the fewest before.
    fn record(&mut self, step: usize, flips: usize) -> bool {
        if (flips as f64) < 0.9 * self.fewest as f64 {
            self.fewest = flips;
            self.at = step;
        }
        step - self.at < self.window
    }

    /// The fewest flips of a step so far.
    fn fewest(&self) -> usize {
        self.fewest
    }
}

/// Settings of the nonsmooth CG.
#[derive(Debug, Clone)]
pub struct NonsmoothOptions {
    pub tolerance: f64,
    /// Budget of interface-operator applications over all outer steps.
    pub max_iterations: usize,
    pub preconditioner: Preconditioner,
    pub interface_scaling: InterfaceScaling,
    /// See [`crate::settings::SolverSettings::adaptive_threshold`].
    pub adaptive_threshold: AdaptiveThreshold,
    /// See [`crate::settings::SolverSettings::adaptive_edges`].
    pub adaptive_edges: AdaptiveEdges,
    /// See [`crate::settings::SolverSettings::macro_degree`].
    pub macro_degree: MacroDegree,
    /// Fill-reducing ordering of the subdomain and interior factors.
    pub ordering: OrderingChoice,
}

/// One solved state of the nonsmooth CG.
#[derive(Debug, Clone)]
pub struct NonsmoothOutcome {
    pub equilibrium: Equilibrium,
    pub converged: bool,
    /// Every inner CG iteration, numbered over the whole solve; the last
    /// entry of each outer step carries the relative violation of the set
    /// it found as `cable_change`.
    pub history: Vec<HistoryEntry>,
    /// Outer (active-set) steps, each one inner CG solve.
    pub outer_steps: usize,
    /// Outer steps that needed a new DD set-up (factorizations).
    pub setups: usize,
    /// Subdomain factorizations over those set-ups (failed attempts
    /// included)...
    pub factored: usize,
    /// ...and subdomain operators taken over from the previous set-up
    /// instead (same elements and dof layout: no slack cable of theirs
    /// changed).
    pub reused: usize,
    /// Of the reused subdomains, those whose interface dofs did not change
    /// either kept their interior (Dirichlet) factor too...
    pub interiors_reused: usize,
    /// ...and their deluxe face blocks on the faces that did not change.
    pub face_blocks_reused: usize,
    /// Of the reused subdomains, those whose macro columns did not change
    /// either (no neighbour's kernel changed): their coarse blocks and
    /// `K⁺ W` were taken over, without a multi-RHS solve.
    pub coarse_blocks_reused: usize,
    /// Element elongations, each measured in its own subdomain's copy
    /// (slack cables, outside the last set-up's structure, from the
    /// assembled displacement): see [`crate::outcome::Outcome::elongations`].
    pub elongations: Option<Vec<f64>>,
    /// Why the solve stopped short, if it did: the last inner solve's
    /// reason, or a cable set that did not settle ([`UNSETTLED_STEPS`]).
    pub message: Option<String>,
    /// The iterative refinement of the settled set's solve, if it needed
    /// one (see [`crate::outcome::Outcome::refinement`]).
    pub refinement: Option<Refinement>,
}

/// The set-up of the nonsmooth CG: the decomposition, and the DD solver of
/// the last slack set with its interface forces (warm start of the next
/// solve).
pub struct NonsmoothCg {
    dec: Decomposition,
    opts: NonsmoothOptions,
    /// The DD solver of the last outer step.
    current: Option<Step>,
    /// Last set a solve settled on (initial set of the next solve).
    settled: Option<Vec<bool>>,
    pool: Pool,
    /// Outer steps without progress before a solve stops ([`UNSETTLED_STEPS`]).
    unsettled_steps: usize,
    /// Whether a set whose structure is a mechanism on one partition is
    /// tried on the others too: only for a set that settled on a softened
    /// step (see [`is_structural_mechanism`]).
    retry_mechanisms: bool,
    /// Whether a subdomain indefinite on its own is merged into a
    /// neighbour and the set tried again ([`NonsmoothCg::set_merging`]).
    merging: bool,
}

/// Operators of the previous set-up by [`OpKey`] while the next one is
/// built (empty otherwise), and the factorizations and reuses since the
/// last `solve` began.
#[derive(Default)]
struct Pool {
    /// Where the subdomains of every set-up live.
    placement: Placement,
    ops: HashMap<OpKey, PooledSubdomain>,
    factored: usize,
    reused: usize,
    interiors_reused: usize,
    face_blocks_reused: usize,
    coarse_blocks_reused: usize,
}

impl Pool {
    /// One DD set-up of `lin` on `dec` (`original`: index in the model of
    /// each element of `lin`, `None` for the same numbering), with the
    /// pooled operators of unchanged subdomains.
    fn setup(
        &mut self,
        lin: &Model,
        dec: &Decomposition,
        original: Option<&[usize]>,
        opts: &DdOptions,
    ) -> Result<(DdSolver, Vec<OpKey>)> {
        // Keys of the subdomains held here (all, or an MPI rank's block).
        let keys = op_keys(lin, dec, original, self.placement.owned(dec.len()));
        let reused: Vec<Option<PooledSubdomain>> = keys.iter().map(|k| self.ops.remove(k)).collect();
        // The rest would only raise the peak memory of this set-up (a retry
        // on another partition of the same set refactors instead).
        self.ops.clear();
        let hits = reused.iter().filter(|o| o.is_some()).count();
        self.reused += hits;
        self.factored += keys.len() - hits;
        let dd = DdSolver::new_pooled(lin, dec, opts.clone(), reused, self.placement.clone())?;
        self.interiors_reused += dd.stats().interiors_reused;
        self.face_blocks_reused += dd.stats().face_blocks_reused;
        self.coarse_blocks_reused += dd.stats().coarse_blocks_reused;
        Ok((dd, keys))
    }
}

/// What a subdomain operator is a function of: its elements (original
/// index, axial stiffness bits) in assembly order and its local dofs.
/// Geometry is fixed, so equal keys mean equal `K_E` and layout.
type OpKey = (Vec<(usize, u64)>, Vec<usize>);

fn op_keys(lin: &Model, dec: &Decomposition, original: Option<&[usize]>, held: std::ops::Range<usize>) -> Vec<OpKey> {
    dec.subdomains[held]
        .iter()
        .map(|sd| {
            let els = sd
                .elements
                .iter()
                .map(|&e| (original.map_or(e, |o| o[e]), lin.elements[e].k.to_bits()))
                .collect();
            (els, sd.dofs.clone())
        })
        .collect()
}

/// One outer step's linear problem, set up.
struct Step {
    slack: Vec<bool>,
    soft: bool,
    dd: Box<DdSolver>,
    /// Decomposition of the structure without its slack cables (`None`:
    /// the solver's own, for a softened step).
    dec: Option<Decomposition>,
    /// Key of each subdomain operator of `dd` (the subdomains held here).
    keys: Vec<OpKey>,
    /// Element of the full model behind each element of `dec`'s structure
    /// (`None`: the same numbering).
    elements: Option<Vec<usize>>,
}

/// Interface forces keyed by `(lo, hi, global dof)`: decompositions of
/// different slack sets share most of their interface entries, and a warm
/// start carries the forces of the shared ones over.
type Forces = HashMap<(usize, usize, usize), f64>;

fn keyed_forces(dec: &Decomposition, forces: &[f64]) -> Forces {
    let mut m = HashMap::with_capacity(forces.len());
    for it in &dec.interfaces {
        for j in it.start..it.end {
            m.insert((it.lo, it.hi, dec.entry_dof[j]), forces[j]);
        }
    }
    m
}

fn forces_on(dec: &Decomposition, forces: &Forces) -> Vec<f64> {
    let mut v = vec![0.0; dec.entry_dof.len()];
    for it in &dec.interfaces {
        for j in it.start..it.end {
            v[j] = forces.get(&(it.lo, it.hi, dec.entry_dof[j])).copied().unwrap_or(0.0);
        }
    }
    v
}

/// The structure of `model` with the given slack cables at `soft` times
/// their axial stiffness (0: removed) and every cable bilateral: the
/// linear problem of one outer step.
fn linear_model(model: &Model, slack: &[bool], soft: f64) -> Model {
    let mut m = model.clone();
    let k_max = model.elements.iter().fold(0.0f64, |a, e| a.max(e.k));
    for (c, &e) in model.cables.iter().enumerate() {
        let el = &mut m.elements[e];
        el.unilateral = false;
        if slack[c] {
            // k e0 scales with k: a removed cable carries no prestrain load.
            el.k = if soft > 0.0 {
                (soft * el.k).max(SOFT_FLOOR * k_max)
            } else {
                0.0
            };
        }
    }
    m.cables.clear();
    m.effects.unilateral_cables = false;
    m
}

/// Names a slack set that leaves a mechanism, as the direct solver does.
fn mechanism_message(model: &Model, slack: &[bool]) -> String {
    let set: Vec<usize> = (0..slack.len()).filter(|&c| slack[c]).collect();
    let names: Vec<String> = set.iter().take(8).map(|&c| model.cables[c].to_string()).collect();
    format!(
        "the structure becomes a mechanism when its {} slack cables are removed (elements {}{})",
        set.len(),
        names.join(", "),
        if set.len() > 8 { ", ..." } else { "" }
    )
}

/// The error of a slack set whose exact set-up failed with `e`: a
/// mechanism of the structure without those cables (a subdomain's
/// "indefinite" is then round-off on it), unless the structure has
/// compressed elements with geometric stiffness, which can make a
/// subdomain indefinite on its own where the whole structure is stable:
/// then the subdomain's error, with the set it was met on.
fn set_failure(model: &Model, slack: &[bool], e: Error) -> Error {
    match e {
        Error::IndefiniteSubdomain { subdomain, message } if model.has_struts() => Error::IndefiniteSubdomain {
            subdomain,
            message: format!(
                "{message}, in the structure without its {} slack cables: compressed elements with \
                     geometric stiffness can make a subdomain indefinite where the whole structure is not \
                     (`multilevel`, whose subdomains keep their slack cables' stiffness, `direct`, fewer \
                     subdomains or nsdd's own partition, which merges such a subdomain into a neighbour, may \
                     solve it)",
                slack.iter().filter(|&&s| s).count()
            ),
        },
        e => Error::Mechanism(format!("{} ({e})", mechanism_message(model, slack))),
    }
}

/// How [`reduced_problem`] names a free node whose elements are all slack.
const HELD_BY_SLACK_CABLES: &str = "is held by slack cables only";

/// Whether the set-up error `e` says that the structure without its slack
/// cables is a mechanism whatever its partition: a free node held by slack
/// cables only, or a kernel mode no interface restrains.
fn is_structural_mechanism(e: &Error) -> bool {
    crate::coarse::is_unrestrained_mode(e) || matches!(e, Error::Mechanism(m) if m.contains(HELD_BY_SLACK_CABLES))
}

/// The structure without its slack cables and its decomposition: the
/// partition restricted to the remaining elements, weak nodes repaired.
/// A node left without any element, or a subdomain left empty, is reported
/// as a mechanism (the caller then takes the softened step).
fn reduced_problem(
    model: &Model,
    dec: &Decomposition,
    slack: &[bool],
    repair: bool,
) -> Result<(Model, Decomposition, Vec<usize>)> {
    let mut is_slack = vec![false; model.elements.len()];
    for (c, &e) in model.cables.iter().enumerate() {
        is_slack[e] = slack[c];
    }
    // The exact step's structure (slack cables at zero axial stiffness),
    // without the slack cables that then contribute nothing. One with
    // geometric stiffness stays, with that stiffness alone: `K_G` is part
    // of the `K` that never changes (docs/design.md §1), as on the direct
    // solver's paths.
    let keep: Vec<usize> = (0..model.elements.len())
        .filter(|&e| !is_slack[e] || model.elements[e].geo != 0.0)
        .collect();
    let mut m = linear_model(model, slack, 0.0);
    let elements = keep.iter().map(|&e| m.elements[e].clone()).collect();
    m.elements = elements;
    let mut used = vec![false; model.coords.len()];
    for el in &m.elements {
        used[el.a] = true;
        used[el.b] = true;
    }
    if let Some(n) = (0..used.len()).find(|&n| !used[n] && m.node_dofs[n].iter().any(|&d| d != FIXED)) {
        return Err(Error::Mechanism(format!("node {n} {HELD_BY_SLACK_CABLES}")));
    }
    let part: Vec<usize> = keep.iter().map(|&e| dec.partition.part_of[e]).collect();
    let mut partition =
        Partition::from_user(&m, &part).map_err(|_| Error::Mechanism("a subdomain has slack cables only".into()))?;
    if repair {
        partition.repair_weak_nodes(&m);
    }
    let d = Decomposition::new(&m, partition);
    Ok((m, d, keep))
}

/// The inner tolerance of each outer step: loose while the set moves
/// ([`INNER_TOL_FACTOR`] of the last relative violation, at most
/// [`INNER_TOL_MAX`]); the set's tolerance (the requested one, at most
/// [`SET_TOLERANCE`]) from the first solve at it on (the few flips left
/// are solved at it rather than loosely and then again to confirm them).
/// In the active set's tail ([`ENDGAME_FLIPS`]) by
/// the flips instead: its first set at the tolerance (few flips after a
/// loose step may hide many small violations: the nonsmooth 30³ tower's 8
/// flips were followed by 3 998), then [`ENDGAME_TOL_FACTOR`] of the
/// violation, and the tolerance again after at most
/// [`ENDGAME_LAST_FLIPS`] flips.
#[derive(Debug, Clone, Copy)]
struct InnerTolerance {
    tol: f64,
    /// The next solve is at the tolerance.
    exact: bool,
    /// In the active set's tail, for good.
    endgame: bool,
}

impl InnerTolerance {
    fn new(tol: f64) -> InnerTolerance {
        InnerTolerance {
            tol,
            exact: false,
            endgame: false,
        }
    }

    /// The tolerance of the next solve, after a last relative violation
    /// `violation` (infinite before the first solve, 0 to confirm a set).
    fn next(&mut self, violation: f64) -> f64 {
        let factor = if self.endgame {
            ENDGAME_TOL_FACTOR
        } else {
            INNER_TOL_FACTOR
        };
        let t = if self.exact {
            self.tol
        } else {
            (factor * violation).clamp(self.tol, INNER_TOL_MAX.max(self.tol))
        };
        // Outside the tail a solve at the tolerance keeps the next ones
        // there; in it the flips decide (`flipped`).
        self.exact = !self.endgame && !(t > self.tol);
        t
    }

    /// A solve flipped `flips` of `cables` cables (`soft`: a softened guide
    /// step, whose flips say little about the tail).
    fn flipped(&mut self, flips: usize, cables: usize, soft: bool) {
        if soft {
            return;
        }
        if !self.endgame {
            if flips as f64 <= ENDGAME_FLIPS * cables as f64 {
                self.endgame = true;
                self.exact = true;
            }
        } else if flips <= ENDGAME_LAST_FLIPS {
            // A set this close to the last is most likely it: solved at
            // the tolerance, it is its own confirmation.
            self.exact = true;
        }
    }
}

impl NonsmoothCg {
    /// Keeps the decomposition; nothing is factored before the first solve.
    pub fn new(model: &Model, dec: Decomposition, opts: NonsmoothOptions) -> Result<NonsmoothCg> {
        Self::new_in(model, dec, opts, Placement::Process)
    }

    /// [`Self::new`] with the subdomains of every set-up placed as
    /// `placement` says (under MPI, every rank calls it).
    pub fn new_in(
        model: &Model,
        dec: Decomposition,
        opts: NonsmoothOptions,
        placement: Placement,
    ) -> Result<NonsmoothCg> {
        if !(opts.tolerance > 0.0) {
            return Err(Error::input("solver.tolerance", None, "must be positive"));
        }
        if dec.partition.part_of.len() != model.elements.len() {
            return Err(Error::input(
                "elements.subdomain",
                None,
                "the decomposition does not belong to this model",
            ));
        }
        // `"auto"` judged once, on every element: the steps' structures
        // lose their slack cables, and the choice should not move with them.
        let mut opts = opts;
        opts.adaptive_threshold = crate::adaptive::threshold_for(opts.adaptive_threshold, model);
        opts.adaptive_edges = crate::adaptive::edges_for(opts.adaptive_edges, model);
        Ok(NonsmoothCg {
            dec,
            opts,
            current: None,
            settled: None,
            pool: Pool {
                placement,
                ..Pool::default()
            },
            unsettled_steps: UNSETTLED_STEPS,
            retry_mechanisms: false,
            merging: false,
        })
    }

    /// With `on`, a set-up that meets a subdomain indefinite on its own
    /// merges it into a neighbour ([`Decomposition::merge_target`]; in one
    /// process with every other subdomain the set leaves indefinite) and
    /// tries the set again, on the merged decomposition from then on: at
    /// the first set (every cable taut), and for a later set once its
    /// softened guide step fails too or it is the one the solve settles on
    /// (until then the softened step guides it, as without merging). Off by
    /// default: the decomposition is the caller's. [`crate::solve::solve`]
    /// turns it on for a structure with compressed struts on nsdd's own
    /// partition.
    pub fn set_merging(&mut self, on: bool) {
        self.merging = on;
    }

    /// Merges the subdomain `e` names, if merging is on and `e` is an
    /// indefinite subdomain with a neighbour, and in one process every
    /// other subdomain the set `slack`'s exact structure leaves indefinite
    /// ([`crate::merging`]); the next set-up starts over.
    fn merge_for(&mut self, model: &Model, slack: &[bool], e: &Error) -> bool {
        let merged = if !self.merging {
            None
        } else if self.pool.placement.in_process() {
            // The structure the exact set-up failed on: without the slack
            // cables, on the restricted partition with its weak nodes
            // repaired (the first one `build_step` tries); its subdomains
            // are numbered as `self.dec`'s.
            let reduced = match slack.contains(&true) {
                true => reduced_problem(model, &self.dec, slack, true).ok(),
                false => None,
            };
            let failed = reduced.as_ref().map(|(lin, dec, _)| (lin, dec));
            crate::merging::merged_all_for(true, model, &self.dec, e, failed, self.opts.ordering)
        } else {
            crate::merging::merged_for(true, model, &self.dec, e, self.pool.placement.ranks())
        };
        let Some(dec) = merged else { return false };
        if std::env::var_os("NSDD_NS_DEBUG").is_some() {
            eprintln!("   merging: {e}; {} subdomains now", dec.len());
        }
        self.dec = dec;
        self.current = None;
        true
    }

    /// Sets the outer steps a solve may make without progress (default
    /// [`UNSETTLED_STEPS`]); tests use 0 to reach that ending on a small
    /// structure.
    #[doc(hidden)]
    pub fn set_unsettled_steps(&mut self, steps: usize) {
        self.unsettled_steps = steps;
    }

    fn keyed(&self, st: &Step) -> Forces {
        keyed_forces(st.dec.as_ref().unwrap_or(&self.dec), &st.dd.interface_forces())
    }

    /// The budget of interface-operator applications of one solve.
    pub fn max_iterations(&self) -> usize {
        self.opts.max_iterations
    }

    /// The tolerance the solve is asked for.
    pub fn tolerance(&self) -> f64 {
        self.opts.tolerance
    }

    /// The decomposition every slack set is solved on.
    pub fn decomposition(&self) -> &Decomposition {
        &self.dec
    }

    /// Element elongations of the last outer step's solve, each from the
    /// copy of the subdomain that holds it; elements outside that step's
    /// structure (slack cables) from the assembled `u`.
    fn local_elongations(&self, model: &Model, u: &[f64]) -> Option<Vec<f64>> {
        let step = self.current.as_ref()?;
        let mut out: Vec<f64> = (0..model.elements.len()).map(|e| model.elongation(e, u)).collect();
        let dec = step.dec.as_ref().unwrap_or(&self.dec);
        step.dd
            .write_element_elongations(model, dec, step.elements.as_deref(), &mut out);
        Some(out)
    }

    /// The DD solver of the last outer step, if any (for its coarse
    /// residual and stages).
    pub fn last_solver(&self) -> Option<&DdSolver> {
        self.current.as_ref().map(|c| &*c.dd)
    }

    /// Changes the stopping rule for later solves.
    pub fn set_stopping(&mut self, tolerance: f64, max_iterations: usize) {
        self.opts.tolerance = tolerance;
        self.opts.max_iterations = max_iterations;
    }

    /// Makes `current` the DD solver of `(slack, soft)`, setting one up if
    /// the kept one is for another set. Returns whether it set one up.
    ///
    /// Exact steps drop the slack cables from the structure and from the
    /// partition, whose weak nodes are then repaired: a node at the cut
    /// held in one subdomain by slack cables only would otherwise be a local
    /// mechanism there, and hundreds of them (a 32² grid, 16 subdomains)
    /// make the coarse problem large and its solve 10-40× slower.
    fn ensure_solver(&mut self, model: &Model, slack: &[bool], soft: bool) -> Result<bool> {
        if let Some(st) = &self.current {
            if st.slack == slack && st.soft == soft {
                return Ok(false);
            }
        }
        // The previous set-up's operators go to the pool: a subdomain whose
        // elements and dof layout did not change takes its operator back
        // instead of being refactored (a set change touches the subdomains
        // owning the flipped cables, and their neighbours only where a node
        // at the cut appears or disappears).
        if let Some(old) = self.current.take() {
            for (key, op) in old.keys.into_iter().zip(old.dd.into_pooled()) {
                self.pool.ops.insert(key, op);
            }
        }
        let out = self.build_step(model, slack, soft);
        self.pool.ops.clear();
        self.current = Some(out?);
        Ok(true)
    }

    fn build_step(&mut self, model: &Model, slack: &[bool], soft: bool) -> Result<Step> {
        let opts = DdOptions {
            coarse: true,
            krylov: true,
            preconditioner: self.opts.preconditioner,
            interface_scaling: self.opts.interface_scaling,
            adaptive_threshold: self.opts.adaptive_threshold,
            adaptive_edges: self.opts.adaptive_edges,
            macro_degree: self.opts.macro_degree,
            tolerance: self.opts.tolerance,
            max_iterations: self.opts.max_iterations,
            search_direction: SearchDirection::Auto,
            ordering: self.opts.ordering,
        };
        let (own, pool) = (&self.dec, &mut self.pool);
        let step = if soft || !slack.iter().any(|&s| s) {
            let lin = linear_model(model, slack, if soft { SOFT } else { 0.0 });
            let (dd, keys) = pool.setup(&lin, own, None, &opts)?;
            Step {
                slack: slack.to_vec(),
                soft,
                dd: Box::new(dd),
                dec: None,
                keys,
                elements: None,
            }
        } else {
            // A local mechanism at the cut can leave a round-off pivot that
            // the subdomain takes for indefinite (bar/cable contrast 1e4):
            // the set is tried on the restricted partition with its weak
            // nodes repaired, then as it is, then with the slack cables
            // kept at zero stiffness, before it counts as a mechanism.
            let mut first_err = None;
            let mut found = None;
            for repair in [true, false] {
                let rr = reduced_problem(model, own, slack, repair).and_then(|(lin, dec, keep)| {
                    let (dd, keys) = pool.setup(&lin, &dec, Some(&keep), &opts)?;
                    Ok((dd, dec, keys, keep))
                });
                match rr {
                    Ok((dd, dec, keys, keep)) => {
                        found = Some((dd, Some(dec), keys, Some(keep)));
                        break;
                    }
                    Err(e) => {
                        if std::env::var_os("NSDD_NS_DEBUG").is_some() {
                            eprintln!(
                                "   the set-up on the {} partition failed: {e}",
                                if repair { "repaired" } else { "plainly restricted" }
                            );
                        }
                        // The structure itself is a mechanism: the other
                        // partitions would fail the same way after factoring
                        // every subdomain again (4.5 s of a 6.6 s step of the
                        // 130² grid with 64 subdomains). A set that settles
                        // there is set up with every attempt before it is
                        // called a mechanism (`retry_mechanisms`).
                        if !self.retry_mechanisms && is_structural_mechanism(&e) {
                            return Err(e);
                        }
                        first_err.get_or_insert(e);
                    }
                }
            }
            if found.is_none() {
                let lin = linear_model(model, slack, 0.0);
                match pool.setup(&lin, own, None, &opts) {
                    Ok((dd, keys)) => found = Some((dd, None, keys, None)),
                    Err(e) => return Err(first_err.unwrap_or(e)),
                }
            }
            let (dd, dec, keys, elements) = found.expect("set above");
            Step {
                slack: slack.to_vec(),
                soft,
                dd: Box::new(dd),
                dec,
                keys,
                elements,
            }
        };
        Ok(step)
    }

    /// Solves for the external forces `f_ext` (free dofs) with exact cable
    /// complementarity up to the tolerance. The first set is the last
    /// settled one (load steps and load cases), else every cable taut.
    pub fn solve(&mut self, model: &Model, f_ext: &[f64], progress: Progress<'_>) -> Result<NonsmoothOutcome> {
        on_workers(self.pool.placement.in_process(), || {
            self.active_set(model, f_ext, progress)
        })
    }

    /// [`Self::solve`], on a worker thread.
    fn active_set(&mut self, model: &Model, f_ext: &[f64], mut progress: Progress<'_>) -> Result<NonsmoothOutcome> {
        if f_ext.len() != model.n_free {
            return Err(Error::input(
                "rhs",
                None,
                format!("has {} entries, expected {}", f_ext.len(), model.n_free),
            ));
        }
        let nc = model.cables.len();
        let tol = self.opts.tolerance;
        self.retry_mechanisms = false;
        let mut slack = match &self.settled {
            Some(s) if s.len() == nc => s.clone(),
            _ => vec![false; nc],
        };
        let mut forces: Option<Forces> = self.current.as_ref().map(|c| self.keyed(c));
        // Sized like the inner solvers' own histories: no growth per iteration.
        let mut history: Vec<HistoryEntry> = Vec::with_capacity(self.opts.max_iterations.min(100_000));
        let mut total = 0usize;
        let mut outer = 0usize;
        let mut setups = 0usize;
        self.pool.factored = 0;
        self.pool.reused = 0;
        self.pool.interiors_reused = 0;
        self.pool.face_blocks_reused = 0;
        self.pool.coarse_blocks_reused = 0;
        let mut seen: HashSet<Vec<bool>> = HashSet::new();
        let mut murty = false;
        // Relative size of the last violation; none measured yet.
        let mut violation = f64::INFINITY;
        // The tolerance the set is decided at; a certified solve at it
        // may accept a set whose violations are all below the requested
        // one.
        let tol_set = tol.min(SET_TOLERANCE);
        let mut schedule = InnerTolerance::new(tol_set);
        let mut settling = Settling::new(self.unsettled_steps);
        // Set for good once a capped step ends far from its tolerance.
        let mut cap_lifted = false;
        let max_outer = 20 * nc + 100;
        let mut g = vec![0.0; nc];
        loop {
            outer += 1;
            if outer > max_outer {
                return Err(Error::Numerical(format!(
                    "cable active set did not settle in {max_outer} outer steps"
                )));
            }
            let inner_tol = schedule.next(violation);
            // A set that leaves a mechanism is taken softened (a guide
            // step); the error it stands for, if the set turns out final.
            let mut failure: Option<Error> = None;
            let t_setup = std::time::Instant::now();
            let soft = match self.ensure_solver(model, &slack, false) {
                Ok(new) => {
                    setups += new as usize;
                    false
                }
                // Every cable taut: the structure is the one the user gave,
                // so a subdomain indefinite on its own is the partition's.
                Err(e) if !slack.contains(&true) && self.merge_for(model, &slack, &e) => {
                    outer -= 1;
                    continue;
                }
                Err(e) if !slack.contains(&true) => {
                    return Err(crate::merging::past_merging(self.merging, &self.dec, e));
                }
                // Removing cables can leave a subdomain with a mechanism
                // whose round-off pivot reads as indefinite: both are what
                // the softened step is for. If the softened set-up fails
                // too, that error is the structure's own; so is it at once
                // when no cable is slack (softening would change nothing).
                Err(e @ (Error::Mechanism(_) | Error::IndefiniteSubdomain { .. })) if slack.contains(&true) => {
                    if std::env::var_os("NSDD_NS_DEBUG").is_some() {
                        eprintln!("outer {outer}: the exact set-up failed ({e}); taking the softened step");
                    }
                    failure = Some(set_failure(model, &slack, e));
                    match self.ensure_solver(model, &slack, true) {
                        Ok(new) => setups += new as usize,
                        Err(Error::Mechanism(_) | Error::IndefiniteSubdomain { .. }) => {
                            let failure = failure.take().expect("set above");
                            if self.merge_for(model, &slack, &failure) {
                                outer -= 1;
                                continue;
                            }
                            return Err(crate::merging::past_merging(self.merging, &self.dec, failure));
                        }
                        Err(e) => return Err(e),
                    }
                    true
                }
                Err(e) => return Err(e),
            };
            let left = self.opts.max_iterations.saturating_sub(total).max(1);
            // While the set is clearly wrong, a loose solve to the end buys
            // nothing the next set keeps: stop it early.
            let capped = !soft && !cap_lifted && violation >= EARLY_STOP_VIOLATION && EARLY_STOP_ITERATIONS < left;
            let budget = if capped { EARLY_STOP_ITERATIONS } else { left };
            let step = self.current.as_mut().expect("set up above");
            let dec = step.dec.as_ref().unwrap_or(&self.dec);
            let dd = &mut step.dd;
            dd.set_stopping(inner_tol, budget);
            // Certified (at least 2 × WINDOW CG terms) at the set's
            // tolerance only, whatever the requested one: a set that
            // settles on a looser solve is confirmed at it. When every
            // solve that met the requested tolerance was certified, the
            // loose steps at 1e-3 took 8 iterations each on the 65² grid
            // cut in 16 instead of 5, and the tail's steps at 1e-4 on the
            // 130² grid 8 instead of 2.
            let certified = !(inner_tol > tol_set);
            dd.set_certified_stop(certified);
            if let Some(c) = dd.coarse_problem_mut() {
                c.set_refinement_target(COARSE_TARGET_FACTOR * inner_tol);
            }
            let warm = match forces.as_ref() {
                Some(f) => dd.set_interface_forces(&forces_on(dec, f)).is_ok(),
                None => false,
            };
            let base = total;
            let setup_s = t_setup.elapsed().as_secs_f64();
            let t_inner = std::time::Instant::now();
            let out = {
                let mut shifted = progress.as_deref_mut().map(|p| move |i: usize, v: f64| p(base + i, v));
                dd.solve(
                    f_ext,
                    warm,
                    shifted.as_mut().map(|p| p as &mut (dyn FnMut(usize, f64) + Send)),
                )?
            };
            // A diverged inner solve ends the nonsmooth one as an error, as
            // before the DD outcome kept its history.
            if let Some(e) = out.divergence() {
                return Err(e);
            }
            let inner_converged = out.converged();
            let inner_status = out.status;
            let inner_indicator = out.history.last().map_or(f64::NAN, |h| h.indicator);
            if capped && !inner_converged && !(inner_indicator <= EARLY_STOP_LIFT) {
                cap_lifted = true;
            }
            forces = Some(keyed_forces(dec, &dd.interface_forces()));
            total += out.iterations;
            history.extend(out.history.into_iter().map(|h| HistoryEntry {
                iteration: base + h.iteration,
                ..h
            }));
            // A stalled solve is a step like the others: its strains update
            // the set, and a settled set's stall is continued by an
            // equilibrium correction (below). A stall on the repaired
            // partition used to send every later set to the plain
            // restriction, for the README's tower, which no longer stalls;
            // on the nonsmooth 12³ tower cut in 64 that restriction's
            // subdomains held 1 156 kernel modes and every later solve broke
            // down, where the stalled step (2.4e-7 at 1e-8, no flips) and its
            // correction converge (BENCHMARKS.md, session 46).
            // Strains and violations on the original cables.
            let u = out.u;
            let inner_message = out
                .message
                .map(|m| format!("the cg solve of the last cable set stopped: {m}"));
            let scale = cable_strains(model, |e| model.elongation(e, &u), &mut g);
            // Strain errors of an inexact solve are about its tolerance
            // times the strain scale, but the CG's stopping test leaves it
            // closer than that: violations down to a tenth of the inner
            // tolerance are acted on (the set then settles before the
            // solve at the tolerance: 963 → 817 iterations on 65², 16
            // subdomains), never below the set's tolerance (cables at zero
            // strain must not flip).
            let thr = (0.1 * inner_tol).max(tol_set) * scale;
            let mut next = slack.clone();
            let mut first = None;
            let mut worst = 0.0f64;
            for (c, v) in violations(&g, &slack, thr) {
                first.get_or_insert(c);
                next[c] = !slack[c];
                worst = worst.max(v);
            }
            violation = worst / scale;
            // No violation above the requested tolerance (looser than the
            // set's): the set is accurate enough as it is, if its solve was.
            let within_request = !soft && tol_set < tol && violation <= tol;
            let flips = next.iter().zip(&slack).filter(|(a, b)| a != b).count();
            let settles = flips == 0 || settling.record(outer, flips);
            schedule.flipped(flips, nc, soft);
            if flips > 0 && !within_request && schedule.endgame && total < self.opts.max_iterations {
                // In the tail the next set differs from this one by a few
                // cables, but its coarse space moves with the kernels they
                // change, and from CG's iterate `F` alone the next solve
                // would rebuild the macro forces `P f` from nothing: it
                // started at an indicator of 1e-2 after one flip on the
                // nonsmooth 12³ tower, against 2e-9 for the same set set up
                // again. The forces the interfaces carried, `F + P f`, cost
                // one application of this step's operator (counted, and
                // only within the budget) and cut the iterations by 14–19 %
                // on the 130² grid cut in 16 and the 30³ tower cut in 64.
                // Taken while the set still moves, the loose solves stop
                // closer to their start and the set cycled (the 20³ tower
                // cut in 64: 37 steps unconverged, against 9).
                let own = &self.dec;
                let step = self.current.as_mut().expect("set up above");
                let dec = step.dec.as_ref().unwrap_or(own);
                forces = Some(keyed_forces(dec, &step.dd.total_interface_forces()));
                total += 1;
            }
            if std::env::var_os("NSDD_NS_DEBUG").is_some() {
                eprintln!(
                    "outer {outer}: {} slack, soft {soft}, inner tol {inner_tol:.1e}, {} its (conv {}, {:?}, indicator {:.1e}), setup {setup_s:.3}s, cg {:.3}s, {} flips, violation {violation:.2e}",
                    slack.iter().filter(|&&s| s).count(),
                    out.iterations,
                    inner_converged,
                    inner_status,
                    inner_indicator,
                    t_inner.elapsed().as_secs_f64(),
                    flips
                );
                let st = self.current.as_ref().unwrap().dd.stats();
                eprintln!(
                    "   kernel {} macro {} nnz_l {} factor {:.3}s adaptive {:.3}s coarse {:.3}s interior {:.3}s scaling {:.3}s; subdomains factored {} reused {} (interiors {}, face blocks {}, coarse blocks {}) so far; this set-up kept {} coarse columns, {} adaptive Neumann blocks, {} face constraints",
                    st.kernel_unknowns,
                    st.macro_unknowns,
                    st.nnz_l,
                    st.factor_s,
                    st.adaptive_s,
                    st.coarse_s,
                    st.interior_s,
                    st.scaling_s,
                    self.pool.factored,
                    self.pool.reused,
                    self.pool.interiors_reused,
                    self.pool.face_blocks_reused,
                    self.pool.coarse_blocks_reused,
                    st.coarse_columns_reused,
                    st.neumann_blocks_reused,
                    st.face_constraints_reused
                );
                // How the flips spread over the subdomains (of the user's
                // partition): what a low-rank update of each factor would
                // have to absorb instead of a refactorization.
                let mut per = vec![0usize; self.dec.len()];
                for c in (0..nc).filter(|&c| next[c] != slack[c]) {
                    per[self.dec.partition.part_of[model.cables[c]]] += 1;
                }
                let touched = per.iter().filter(|&&k| k > 0).count();
                eprintln!(
                    "   flips in {touched} of {} subdomains, at most {} in one",
                    per.len(),
                    per.iter().max().copied().unwrap_or(0)
                );
            }
            if let Some(h) = history.last_mut() {
                h.cable_change = Some(violation);
            }
            if first.is_none() || within_request {
                if capped && !inner_converged {
                    // Stopped early on a set that then looked right: solve
                    // it properly before trusting it.
                    violation = 0.0;
                    continue;
                }
                if !certified {
                    // Settled on a loose solve, converged to its loose
                    // tolerance or stalled above it: confirm at the
                    // tolerance. A stalled loose solve used to be accepted
                    // as it was, and its equilibrium corrections then ran
                    // at the loose tolerance too: the nonsmooth 2×2×5
                    // tower on 3 subdomains with stiffness scaling claimed
                    // 1e-8 with its indicator at 9e-3 and its tensions
                    // 3e-3 off.
                    violation = 0.0;
                    continue;
                }
                if soft {
                    if !self.retry_mechanisms && failure.as_ref().is_some_and(is_structural_mechanism) {
                        // Its exact set-up stopped at the first partition
                        // that found a mechanism: try them all before
                        // calling the final set one.
                        self.retry_mechanisms = true;
                        self.current = None;
                        violation = 0.0;
                        continue;
                    }
                    let failure = failure.take().expect("a softened step follows a failed set-up");
                    if self.merge_for(model, &slack, &failure) {
                        violation = 0.0;
                        continue;
                    }
                    return Err(crate::merging::past_merging(self.merging, &self.dec, failure));
                }
                let mut elongations = self.local_elongations(model, &u);
                let mut u = u;
                let mut refinement = None;
                let (mut status, mut message) = (inner_status, inner_message);
                // A certified solve of the settled set is refined if its
                // tensions miss equilibrium; one stalled (or broken down)
                // on a round-off floor is continued by a correction, and
                // its set checked again on the corrected strains.
                let refinable = matches!(inner_status, Status::Converged | Status::Stalled | Status::Breakdown);
                if refinable {
                    if let (Some(el), Some(step)) = (elongations.as_mut(), self.current.as_mut()) {
                        // The settled set's structure is linear: refine it
                        // as a linear solve (its slack cables carry nothing).
                        let mut slack_element = vec![false; model.elements.len()];
                        for (c, &e) in model.cables.iter().enumerate() {
                            slack_element[e] = slack[c];
                        }
                        let tension = |e: usize, x: f64| {
                            if slack_element[e] {
                                0.0
                            } else {
                                model.elements[e].tension(x)
                            }
                        };
                        let dec = step.dec.as_ref().unwrap_or(&self.dec);
                        refinement = step.dd.refine_equilibrium(
                            model,
                            dec,
                            step.elements.as_deref(),
                            f_ext,
                            &tension,
                            Refined {
                                u: &mut u,
                                elongations: el,
                                history: &mut history,
                                iterations: &mut total,
                                status: &mut status,
                                message: &mut message,
                            },
                        )?;
                        if refinement.is_some() {
                            let scale = cable_strains(model, |e| el[e], &mut g);
                            let (mut flips, mut worst) = (0usize, 0.0f64);
                            for (_, v) in violations(&g, &slack, tol * scale) {
                                flips += 1;
                                worst = worst.max(v / scale);
                            }
                            if flips > 0 && status == Status::Converged {
                                status = Status::Stalled;
                                message = Some(format!(
                                    "the solve of the last cable set converged after an equilibrium correction, \
                                     but {flips} cables then violate complementarity (by up to {worst:.1e} of the \
                                     strain scale): the set is not certified"
                                ));
                            }
                        }
                    }
                }
                let lambda = (0..nc).map(|c| if slack[c] { (-g[c]).max(0.0) } else { 0.0 }).collect();
                self.settled = Some(slack);
                return Ok(NonsmoothOutcome {
                    equilibrium: Equilibrium {
                        u,
                        lambda,
                        iterations: total,
                        elongations: None,
                    },
                    converged: status == Status::Converged,
                    history,
                    outer_steps: outer,
                    setups,
                    factored: self.pool.factored,
                    reused: self.pool.reused,
                    interiors_reused: self.pool.interiors_reused,
                    face_blocks_reused: self.pool.face_blocks_reused,
                    coarse_blocks_reused: self.pool.coarse_blocks_reused,
                    elongations,
                    message,
                    refinement,
                });
            }
            let budget_spent = !inner_converged && total >= self.opts.max_iterations;
            if budget_spent || !settles {
                // Budget spent with the set still moving, or a set that does
                // not settle: report the state.
                let message = if settles {
                    inner_message
                } else {
                    Some(format!(
                        "the cable set did not settle: {flips} cables would flip after step {outer}, and no step \
                         of the last {} cut the fewest flips so far ({}) by a tenth",
                        self.unsettled_steps,
                        settling.fewest()
                    ))
                };
                let lambda = (0..nc).map(|c| if slack[c] { (-g[c]).max(0.0) } else { 0.0 }).collect();
                let elongations = self.local_elongations(model, &u);
                return Ok(NonsmoothOutcome {
                    equilibrium: Equilibrium {
                        u,
                        lambda,
                        iterations: total,
                        elongations: None,
                    },
                    converged: false,
                    history,
                    outer_steps: outer,
                    setups,
                    factored: self.pool.factored,
                    reused: self.pool.reused,
                    interiors_reused: self.pool.interiors_reused,
                    face_blocks_reused: self.pool.face_blocks_reused,
                    coarse_blocks_reused: self.pool.coarse_blocks_reused,
                    elongations,
                    message,
                    refinement: None,
                });
            }
            if !murty && !seen.insert(slack.clone()) {
                murty = true;
            }
            if murty {
                let c = first.expect("a violation");
                slack[c] = !slack[c];
            } else {
                slack = next;
            }
        }
    }
}

/// Each cable's strain `g = e + e0` into `g`, from the elongation of its
/// element; returns the largest `|g|` (the strain scale, positive).
fn cable_strains(model: &Model, elongation: impl Fn(usize) -> f64, g: &mut [f64]) -> f64 {
    let mut scale = 0.0f64;
    for (c, &e) in model.cables.iter().enumerate() {
        g[c] = elongation(e) + model.elements[e].e0;
        scale = scale.max(g[c].abs());
    }
    scale.max(f64::MIN_POSITIVE)
}

/// The cables that violate complementarity by more than `thr`, with by how
/// much: a slack cable with `λ = −g < −thr`, a taut one with `g < −thr`.
fn violations<'a>(g: &'a [f64], slack: &'a [bool], thr: f64) -> impl Iterator<Item = (usize, f64)> + 'a {
    g.iter().zip(slack).enumerate().filter_map(move |(c, (&g, &s))| {
        let v = if s { g } else { -g };
        (v > thr).then_some((c, v))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The errors that stop a set's set-up at its first partition are the
    /// structure's own mechanisms, also once wrapped as the step's failure;
    /// an indefinite subdomain (which another partition may avoid) is not.
    #[test]
    fn structural_mechanisms_are_told_from_indefinite_subdomains() {
        let coarse = crate::coarse::unrestrained_mode(3, " (largest motion at node 7, component x)");
        let node = Error::Mechanism(format!("node 12 {HELD_BY_SLACK_CABLES}"));
        let indefinite = Error::IndefiniteSubdomain {
            subdomain: 2,
            message: "stiffness matrix is indefinite".into(),
        };
        let other = Error::Mechanism("a subdomain has slack cables only".into());
        assert!(is_structural_mechanism(&coarse));
        assert!(is_structural_mechanism(&node));
        assert!(!is_structural_mechanism(&indefinite));
        assert!(!is_structural_mechanism(&other));
        // As `set_failure` words the step's failure.
        let scene = crate::generate::grid(&crate::generate::GridParams::default());
        let model = Model::from_scene(&scene).unwrap();
        let slack = vec![true; model.cables.len()];
        assert!(is_structural_mechanism(&set_failure(&model, &slack, coarse)));
        assert!(!is_structural_mechanism(&set_failure(&model, &slack, indefinite)));
    }

    /// Progress is a new fewest count below 0.9 × the last one; the solve
    /// ends `window` steps after the last progress, however the counts
    /// wander in between.
    #[test]
    fn settling_ends_a_window_after_the_last_tenth_cut() {
        let mut s = Settling::new(3);
        // 100 at step 1; 95 is no tenth cut, 89 is.
        assert!(s.record(1, 100));
        assert!(s.record(2, 95));
        assert!(s.record(3, 89));
        assert_eq!(s.fewest(), 89);
        // Wandering above 0.9 × 89 for three steps ends it.
        assert!(s.record(4, 120));
        assert!(s.record(5, 81));
        assert!(!s.record(6, 85));
        // A grid-like sequence (each step a third fewer) never ends.
        let mut g = Settling::new(3);
        let (mut flips, mut step) = (35_000usize, 1);
        while flips > 0 {
            assert!(g.record(step, flips), "step {step}");
            flips = flips * 2 / 3;
            step += 1;
        }
        // Window 0 ends at the first count.
        assert!(!Settling::new(0).record(1, 5));
    }

    /// The schedule: loose steps at 0.03 of the violation, at most 1e-3;
    /// after a step of at most 1e-3 of the cables (101 141 here, the 130²
    /// grid's) the next set at the tolerance, then `ENDGAME_TOL_FACTOR` of
    /// the violation, the tolerance after at most 4 flips; a settled loose
    /// set is confirmed at the tolerance.
    #[test]
    fn inner_tolerance_follows_the_violation_and_the_tails_flips() {
        let tol = 1e-8;
        let nc = 101_141;
        let close = |a: f64, b: f64| (a - b).abs() <= 1e-12 * b;
        let mut t = InnerTolerance::new(tol);
        assert_eq!(t.next(f64::INFINITY), INNER_TOL_MAX);
        t.flipped(35_488, nc, false);
        assert!(close(t.next(0.0197), INNER_TOL_FACTOR * 0.0197));
        // A softened step's few flips do not start the tail.
        t.flipped(70, nc, true);
        assert!(close(t.next(0.0035), INNER_TOL_FACTOR * 0.0035));
        // The tail: its first set at the tolerance, whatever the violation.
        t.flipped(70, nc, false);
        assert_eq!(t.next(0.0035), tol);
        // Then by the violation, however many flips.
        t.flipped(3_998, nc, false);
        assert!(close(t.next(1e-4), ENDGAME_TOL_FACTOR * 1e-4));
        t.flipped(57, nc, false);
        assert!(close(t.next(2.7e-3), ENDGAME_TOL_FACTOR * 2.7e-3));
        // Never below the tolerance.
        t.flipped(7, nc, false);
        assert_eq!(t.next(1e-9), tol);
        // At most 4 flips: the next set at the tolerance; more, by the
        // violation again.
        t.flipped(4, nc, false);
        assert_eq!(t.next(6e-4), tol);
        t.flipped(9, nc, false);
        assert!(close(t.next(5e-4), ENDGAME_TOL_FACTOR * 5e-4));
        // Outside the tail a solve at the tolerance keeps the next ones there.
        let mut t = InnerTolerance::new(tol);
        t.next(f64::INFINITY);
        t.flipped(2_000, nc, false);
        assert_eq!(t.next(0.0), tol);
        t.flipped(500, nc, false);
        assert_eq!(t.next(0.01), tol);
    }
}
