//! The one-call API: scene in, [`SolveResult`] out, with the pipeline
//! composed from the scene's effects and the chosen method.
//!
//! ```
//! use nsdd::scene::{Scene, Method};
//! use nsdd::solve::{solve, SolveOptions};
//! let text = r#"
//! [nodes]
//! x = [0.0, 1.0]
//! y = [0.0, 0.0]
//! z = [0.0, 0.0]
//! [elements]
//! a = [0]
//! b = [1]
//! kind = ["bar"]
//! ea = [100.0]
//! [supports]
//! node = [0, 1]
//! dofs = ["xyz", "yz"]
//! [loads]
//! node = [1]
//! fx = [2.0]
//! "#;
//! let scene = Scene::from_toml_str(text).unwrap();
//! let result = solve(&scene, &SolveOptions::from_scene(&scene)).unwrap();
//! // u = F L / EA = 2 * 1 / 100
//! assert!((result.displacements[1][0] - 0.02).abs() < 1e-14);
//! assert!((result.tensions[0] - 2.0).abs() < 1e-12);
//! ```

use crate::comm::Placement;
use crate::dd::{DdOptions, DdSolver, Refined};
use crate::decomposition::Decomposition;
use crate::direct::DirectSolver;
use crate::error::{Error, Result};
use crate::factor::OrderingKind;
use crate::merging::{merged_all_for, merged_for, merges_indefinite, past_merging};
use crate::model::Model;
use crate::nonsmooth::{NonsmoothCg, NonsmoothOptions};
use crate::outcome::{Outcome, Status};
use crate::partition::{resolve_subdomains, Partition};
use crate::result::{CaseResult, FactorSizes, HistoryEntry, SetupPhases, SolveResult, Timings};
use crate::scene::{Method, Partitioner, Scene};
pub use crate::settings::SolverSettings;
use std::time::Instant;

/// Solver settings (the scene's `[solver]`, possibly overridden): the one
/// settings type of the crate, [`SolverSettings`], under its historical name.
pub type SolveOptions = SolverSettings;

pub use crate::method::Progress;

/// A set-up solver of either kind, reusable over load cases.
pub enum Prepared {
    Direct(Box<DirectSolver>),
    Dd(Box<DdSolver>, Decomposition),
    /// `cg` on a model with unilateral cables: active set around the
    /// interface CG ([`crate::nonsmooth`]).
    NonsmoothCg(Box<NonsmoothCg>),
}

/// Builds the decomposition of `scene` into `subdomains` (0: automatic)
/// with the scene's partitioner (user partition first).
pub fn decompose(model: &Model, scene: &Scene, subdomains: usize) -> Result<Decomposition> {
    decompose_with(model, scene, subdomains, scene.solver.partitioner)
}

/// Builds the decomposition the options ask for (user partition first;
/// `subdomains = 0` is resolved by [`auto_subdomains`]).
pub fn decompose_with(
    model: &Model,
    scene: &Scene,
    subdomains: usize,
    partitioner: Partitioner,
) -> Result<Decomposition> {
    let partition = if !scene.elements.subdomain.is_empty() {
        Partition::from_user(model, &scene.elements.subdomain)?
    } else {
        let n = if subdomains == 0 {
            auto_subdomains(model)
        } else {
            subdomains
        };
        Partition::automatic(model, n, partitioner)?
    };
    Ok(Decomposition::new(model, partition))
}

/// The automatic subdomain count of `model` on this machine
/// ([`resolve_subdomains`] with the model's size and rayon's thread count).
pub fn auto_subdomains(model: &Model) -> usize {
    resolve_subdomains(0, model.n_free, model.elements.len(), rayon::current_num_threads())
}

/// Share of the free dofs on an interface above which the result warns:
/// the iteration then works on (nearly) the whole problem, with tiny
/// subdomains, and is far slower than fewer subdomains.
pub const INTERFACE_WARNING_FRACTION: f64 = 0.5;

/// Notes that start with this are warnings (the CLI prints them to stderr).
pub const WARNING_PREFIX: &str = "warning: ";

/// Free dofs on at least one interface.
fn interface_dofs(dec: &Decomposition, n_free: usize) -> usize {
    let mut on = vec![false; n_free];
    for &d in &dec.entry_dof {
        on[d] = true;
    }
    on.iter().filter(|&&b| b).count()
}

/// The notes on the subdomain count: how an automatic count was chosen,
/// and a warning when most free dofs are on interfaces.
fn subdomain_notes(model: &Model, scene: &Scene, opts: &SolveOptions, dec: &Decomposition) -> Vec<String> {
    let mut notes = Vec::new();
    let n = dec.len();
    if !dec.merged.is_empty() {
        let k = dec.merged.len();
        let pairs: Vec<String> = dec
            .merged
            .iter()
            .take(8)
            .map(|m| format!("{} into {}", m.subdomain, m.into))
            .collect();
        // Down to one subdomain the method ran as a slower direct solve.
        let (warning, whole) = if n == 1 {
            (
                WARNING_PREFIX,
                ": one subdomain is left, the whole structure, and `direct` solves it faster",
            )
        } else {
            ("", "")
        };
        notes.push(format!(
            "{warning}subdomains: {n}, not the {} partitioned: {k} merge{} ({}{}; ids of the partition each \
             round of merges was made on) of a subdomain indefinite on its own (compressed struts cut off from the \
             cables that hold them) into its neighbour{whole}",
            n + k,
            if k == 1 { "" } else { "s" },
            pairs.join(", "),
            if k > 8 { ", ..." } else { "" }
        ));
    }
    if opts.subdomains == 0 && scene.elements.subdomain.is_empty() {
        notes.push(format!(
            "subdomains: {n}, chosen automatically from {} free dofs, {} elements and {} threads",
            model.n_free,
            model.elements.len(),
            rayon::current_num_threads()
        ));
    }
    let on = interface_dofs(dec, model.n_free);
    let fraction = on as f64 / model.n_free.max(1) as f64;
    if fraction > INTERFACE_WARNING_FRACTION {
        notes.push(format!(
            "{WARNING_PREFIX}{:.0}% of the free dofs ({on} of {}) are on interfaces with {n} subdomains: \
             the iteration will be slow; fewer subdomains (the automatic count here is {}) are faster",
            100.0 * fraction,
            model.n_free,
            auto_subdomains(model)
        ));
    }
    notes
}

/// Sets up the solver for `model` (factorizations, coarse problem).
pub fn prepare(model: &Model, scene: &Scene, opts: &SolveOptions) -> Result<Prepared> {
    prepare_in(model, scene, opts, Placement::Process)
}

/// [`prepare`] with the subdomains placed as `placement` says: under MPI,
/// every rank calls it and sets up its block of subdomains (the direct
/// method runs whole on every rank).
pub fn prepare_in(model: &Model, scene: &Scene, opts: &SolveOptions, placement: Placement) -> Result<Prepared> {
    Ok(match opts.method {
        Method::Direct => Prepared::Direct(Box::new(DirectSolver::with_ordering(model, opts.ordering)?)),
        Method::Cg if !model.cables.is_empty() => {
            opts.validate()?;
            let dec = decompose_with(model, scene, opts.subdomains, opts.partitioner)?;
            let mut ns = NonsmoothCg::new_in(
                model,
                dec,
                NonsmoothOptions {
                    tolerance: opts.tolerance,
                    max_iterations: opts.max_iterations,
                    preconditioner: opts.preconditioner,
                    interface_scaling: opts.interface_scaling,
                    adaptive_threshold: opts.adaptive_threshold,
                    adaptive_edges: opts.adaptive_edges,
                    macro_degree: opts.macro_degree,
                    ordering: opts.ordering,
                },
                placement,
            )?;
            ns.set_merging(merges_indefinite(model, scene));
            Prepared::NonsmoothCg(Box::new(ns))
        }
        Method::Monolevel | Method::Multilevel | Method::Cg => {
            let mut dec = decompose_with(model, scene, opts.subdomains, opts.partitioner)?;
            let merging = merges_indefinite(model, scene);
            loop {
                match DdSolver::new_in(model, &dec, DdOptions::from_settings(opts)?, placement.clone()) {
                    Ok(dd) => break Prepared::Dd(Box::new(dd), dec),
                    Err(e) => {
                        let merged = if placement.in_process() {
                            merged_all_for(merging, model, &dec, &e, None, opts.ordering)
                        } else {
                            merged_for(merging, model, &dec, &e, placement.ranks())
                        };
                        match merged {
                            Some(m) => dec = m,
                            None => return Err(past_merging(merging, &dec, e)),
                        }
                    }
                }
            }
        }
    })
}

impl Prepared {
    /// Solves for external forces `f_ext` (free dofs). `warm` starts a DD
    /// iteration from the previous state (load paths). Every ending is an
    /// [`Outcome`] (a diverged run too, with its history); errors are
    /// reserved for input the solver cannot take.
    pub fn solve(&mut self, model: &Model, f_ext: &[f64], warm: bool, progress: Progress<'_>) -> Result<Outcome> {
        match self {
            Prepared::Direct(d) => {
                let t = Instant::now();
                let b = model.rhs(f_ext);
                let eq = d.solve(model, &b)?;
                let history = vec![HistoryEntry {
                    iteration: eq.iterations,
                    time_s: t.elapsed().as_secs_f64(),
                    indicator: 0.0,
                    jump: None,
                    cable_change: None,
                }];
                Ok(Outcome {
                    u: eq.u,
                    lambda: eq.lambda,
                    status: Status::Converged,
                    iterations: eq.iterations,
                    history,
                    message: None,
                    search_direction: None,
                    outer_steps: None,
                    elongations: eq.elongations,
                    refinement: None,
                })
            }
            Prepared::Dd(dd, dec) => {
                let mut out = dd.solve(f_ext, warm, progress)?;
                out.elongations = Some(dd.element_elongations(model, dec));
                if model.cables.is_empty() {
                    let (u, history) = (&mut out.u, &mut out.history);
                    if let Some(elongations) = out.elongations.as_mut() {
                        let tension = |e: usize, x: f64| model.elements[e].tension(x);
                        out.refinement = dd.refine_equilibrium(
                            model,
                            dec,
                            None,
                            f_ext,
                            &tension,
                            Refined {
                                u,
                                elongations,
                                history,
                                iterations: &mut out.iterations,
                                status: &mut out.status,
                                message: &mut out.message,
                            },
                        )?;
                    }
                }
                check_equilibrium(model, f_ext, &mut out, dd.opts.tolerance);
                Ok(out)
            }
            Prepared::NonsmoothCg(ns) => {
                let (max_iterations, tolerance) = (ns.max_iterations(), ns.tolerance());
                let out = ns.solve(model, f_ext, progress)?;
                let status = if out.converged {
                    Status::Converged
                } else if out.equilibrium.iterations >= max_iterations {
                    Status::IterationLimit
                } else {
                    Status::Stalled
                };
                let mut out = Outcome {
                    u: out.equilibrium.u,
                    lambda: out.equilibrium.lambda,
                    status,
                    iterations: out.equilibrium.iterations,
                    history: out.history,
                    message: out.message.filter(|_| status != Status::Converged),
                    search_direction: None,
                    outer_steps: Some((out.outer_steps, out.setups)),
                    elongations: out.elongations,
                    refinement: out.refinement,
                };
                check_equilibrium(model, f_ext, &mut out, tolerance);
                Ok(out)
            }
        }
    }

    /// The solver stages that run, named as in SCENE.md.
    pub fn stages(&self, model: &Model) -> Vec<String> {
        let mut v = Vec::new();
        match self {
            Prepared::Direct(_) => v.push("direct"),
            Prepared::NonsmoothCg(ns) => {
                if !ns.decomposition().interfaces.is_empty() {
                    v.push("interface");
                }
                v.push("cables");
                v.push("coarse");
                if ns.last_solver().is_some_and(|dd| dd.has_kernels()) {
                    v.push("kernel");
                }
            }
            Prepared::Dd(dd, _) => {
                if dd.has_interfaces() {
                    v.push("interface");
                }
                if !model.cables.is_empty() {
                    v.push("cables");
                }
                if dd.has_coarse() {
                    v.push("coarse");
                }
                if dd.has_kernels() {
                    v.push("kernel");
                }
            }
        }
        if matches!(self, Prepared::Direct(_)) && !model.cables.is_empty() {
            v.push("cables");
        }
        v.into_iter().map(String::from).collect()
    }
}

/// Worst backward error of the coarse solves above which the result
/// carries a note: far above round-off (1e-16), the coarse step is not
/// what the method assumes.
const COARSE_RESIDUAL_NOTE: f64 = 1e-10;

/// A DD solve claims its tolerance only if the tensions it reports (from
/// each element's own subdomain copy) are in equilibrium with the loads to
/// that tolerance, relative to their norm
/// ([`Model::equilibrium_residual`]). The interface forces cancel in that
/// sum, so it sees what the jump-based indicator cannot: the subdomains'
/// own round-off, their solves and kernel bases times the rigid-body
/// amplitudes of floating subdomains (the 30³ contrast tower on 16
/// subdomains claimed 1e-8 with tensions 2.7e-8 off and this residual at
/// 1.5e-8; the direct solve's is 4e-11). No iteration of the solve
/// reduces it; its equilibrium corrections
/// ([`DdSolver::refine_equilibrium`], run before this check) do, down to
/// the round-off of the tensions themselves. Above the tolerance after
/// them (or without them: the nonsmooth cg's unsettled sets), the solve
/// ends `Stalled`, its answer kept.
fn check_equilibrium(model: &Model, f_ext: &[f64], out: &mut Outcome, tolerance: f64) {
    if out.status != Status::Converged {
        return;
    }
    let Some(elongations) = &out.elongations else {
        return;
    };
    let slack = model.slack_flags(&out.u, &out.lambda, iterative_slack_threshold(tolerance));
    let tensions = model.tensions_from_elongations(elongations, &slack);
    let Some(r) = model.equilibrium_residual(f_ext, &tensions, &out.u) else {
        return;
    };
    if !(r <= tolerance) {
        let indicator = out.history.last().map_or(f64::NAN, |h| h.indicator);
        out.status = Status::Stalled;
        let why = match out.refinement {
            Some(rf) => format!(
                "after {} equilibrium correction{} (from {:.1e}): the round-off of the tensions themselves",
                rf.corrections,
                if rf.corrections == 1 { "" } else { "s" },
                rf.residual_before
            ),
            None => "a floor set by the subdomains' own round-off (their solves and kernel bases, times the \
                     rigid-body amplitudes of floating subdomains)"
                .into(),
        };
        out.message = Some(format!(
            "the indicator reached {indicator:.1e}, but the tensions miss equilibrium with the loads by {r:.1e} \
             of their norm, above the tolerance, {why}"
        ));
    }
}

/// Relative slack threshold of a method: round-off for the direct solver,
/// ten times the tolerance for the iterative ones.
fn slack_threshold(opts: &SolveOptions) -> f64 {
    match opts.method {
        Method::Direct => 1e-12,
        _ => iterative_slack_threshold(opts.tolerance),
    }
}

/// [`slack_threshold`] of an iterative method asked for `tolerance`.
fn iterative_slack_threshold(tolerance: f64) -> f64 {
    10.0 * tolerance
}

fn case_result(model: &Model, name: &str, load_factor: f64, st: &Outcome, slack_rel: f64) -> CaseResult {
    let slack = model.slack_flags(&st.u, &st.lambda, slack_rel);
    CaseResult {
        name: name.to_string(),
        load_factor,
        converged: st.converged(),
        status: st.status,
        iterations: st.iterations,
        displacements: model.node_displacements(&st.u),
        tensions: match &st.elongations {
            Some(el) => model.tensions_from_elongations(el, &slack),
            None => model.tensions_with_slack(&st.u, &slack),
        },
        slack,
    }
}

/// Validates the scene, builds the model, sets up the method and solves
/// every load case (and load-path step) the scene asks for.
pub fn solve(scene: &Scene, opts: &SolveOptions) -> Result<SolveResult> {
    solve_with_progress(scene, opts, None)
}

/// [`solve`] with a progress callback.
pub fn solve_with_progress(scene: &Scene, opts: &SolveOptions, progress: Progress<'_>) -> Result<SolveResult> {
    solve_in(scene, opts, progress, Placement::Process)
}

/// [`solve_with_progress`] with the subdomains placed as `placement` says.
/// Under MPI every rank calls it with the same scene and options, and
/// every rank returns the same result (or the same error).
pub fn solve_in(
    scene: &Scene,
    opts: &SolveOptions,
    progress: Progress<'_>,
    placement: Placement,
) -> Result<SolveResult> {
    // The set-up's parallel loops too (see `on_workers`).
    crate::method::on_workers(placement.in_process(), || solve_here(scene, opts, progress, placement))
        .map_err(|e| with_strut_hint(scene, e))
}

/// An indefinite subdomain of a structure with compressed struts (geometric
/// stiffness) on the user's partition (nsdd's own merges it away,
/// `crate::merging`) is most likely a partition that separates struts
/// from the cables that stabilise them, not an indefinite structure: the
/// error says what may solve it, unless it already does (a nonsmooth
/// step's message).
fn with_strut_hint(scene: &Scene, e: Error) -> Error {
    match e {
        Error::IndefiniteSubdomain { subdomain, message }
            if !message.contains("`direct`")
                && !scene.elements.subdomain.is_empty()
                && Model::from_scene(scene).is_ok_and(|m| m.has_struts()) =>
        {
            Error::IndefiniteSubdomain {
                subdomain,
                message: format!(
                    "{message}; with compressed struts a subdomain can be indefinite where the structure is not: \
                     `direct`, fewer subdomains or nsdd's own partition (without `elements.subdomain`: it merges \
                     such a subdomain into a neighbour) may solve it"
                ),
            }
        }
        e => e,
    }
}

/// [`solve_in`], on the thread that runs it.
fn solve_here(
    scene: &Scene,
    opts: &SolveOptions,
    mut progress: Progress<'_>,
    placement: Placement,
) -> Result<SolveResult> {
    let t_setup = Instant::now();
    opts.validate()?;
    let model = Model::from_scene(scene)?;
    let mut prepared = prepare_in(&model, scene, opts, placement)?;
    let setup = t_setup.elapsed().as_secs_f64();
    let t_solve = Instant::now();

    let mut steps = Vec::new();
    let mut top: Option<Outcome> = None;
    // A diverged solve ends the run: later steps and cases are not tried,
    // and the result carries the diverged state with its history.
    let mut diverged = false;
    let mut step_status = Vec::new();
    // The load factor of the top-level solve (the last load-path step run).
    let mut top_factor = 1.0;
    if let Some(path) = &scene.load_path {
        for k in 1..=path.steps {
            let factor = path.final_factor * k as f64 / path.steps as f64;
            let f: Vec<f64> = model.load_cases[0].iter().map(|v| v * factor).collect();
            let st = prepared.solve(
                &model,
                &f,
                k > 1,
                progress
                    .as_deref_mut()
                    .map(|p| p as &mut (dyn FnMut(usize, f64) + Send)),
            )?;
            steps.push(case_result(
                &model,
                &format!("step {k}"),
                factor,
                &st,
                slack_threshold(opts),
            ));
            diverged = st.status == Status::Diverged;
            step_status.push((st.status, st.message.clone()));
            top = Some(st);
            top_factor = factor;
            if diverged {
                break;
            }
        }
    } else {
        let st = prepared.solve(&model, &model.load_cases[0], false, progress)?;
        diverged = st.status == Status::Diverged;
        top = Some(st);
    }
    let mut load_cases = Vec::new();
    let mut case_status = Vec::new();
    for c in 1..model.load_cases.len() {
        if diverged {
            break;
        }
        let st = prepared.solve(&model, &model.load_cases[c], false, None)?;
        diverged = st.status == Status::Diverged;
        case_status.push((st.status, st.message.clone(), st.iterations));
        load_cases.push(case_result(
            &model,
            &model.load_case_names[c],
            1.0,
            &st,
            slack_threshold(opts),
        ));
    }
    let top = top.expect("at least one solve");
    let main = case_result(&model, "loads", 1.0, &top, slack_threshold(opts));
    let f_top: Vec<f64> = model.load_cases[0].iter().map(|v| v * top_factor).collect();
    let equilibrium_residual = model.equilibrium_residual(&f_top, &main.tensions, &top.u);
    let (n_sub, element_subdomain) = match &prepared {
        Prepared::Direct(_) => (1, Vec::new()),
        Prepared::Dd(_, dec) => (dec.len(), dec.partition.part_of.clone()),
        Prepared::NonsmoothCg(ns) => (ns.decomposition().len(), ns.decomposition().partition.part_of.clone()),
    };
    // The `d` the top solve ended with (a halved automatic d included); CG
    // has no step length: only the stationary iteration reports one.
    let d = top.search_direction;
    // Why the run stopped: the first solve, in order (steps, the top
    // level, the load cases), that did not converge.
    let (status, stop_message) = step_status
        .into_iter()
        .chain(std::iter::once((top.status, top.message.clone())))
        .chain(case_status.into_iter().map(|(s, m, _)| (s, m)))
        .find(|(s, _)| !s.is_converged())
        .unwrap_or((Status::Converged, None));
    let mut notes = model.notes.clone();
    if let Some((outer, setups)) = top.outer_steps {
        notes.push(format!(
            "nonsmooth cg: {outer} active-set steps ({setups} DD set-ups), {} interface CG iterations in all",
            top.iterations
        ));
    }
    match &prepared {
        Prepared::Dd(_, dec) => notes.extend(subdomain_notes(&model, scene, opts, dec)),
        Prepared::NonsmoothCg(ns) => notes.extend(subdomain_notes(&model, scene, opts, ns.decomposition())),
        Prepared::Direct(_) => {}
    }
    let last_dd = match &prepared {
        Prepared::Dd(dd, _) => Some(&**dd),
        Prepared::NonsmoothCg(ns) => ns.last_solver(),
        Prepared::Direct(_) => None,
    };
    if let Some(dd) = last_dd {
        let st = dd.stats();
        if st.adaptive_threshold > 0.0 {
            let why = if opts.adaptive_threshold.is_auto() {
                " (\"auto\": the elements' EA/L span 100x or more)"
            } else {
                ""
            };
            notes.push(format!(
                "adaptive macro space (threshold {}): {} columns added on the faces and {} on the edges, {} macro \
                 unknowns in all{why}",
                st.adaptive_threshold,
                st.adaptive_columns - st.adaptive_edge_columns,
                st.adaptive_edge_columns,
                st.macro_unknowns
            ));
        }
        if st.macro_degree > 1 {
            let why = if opts.macro_degree.is_default() {
                format!(
                    " (\"auto\": cg on a flat structure without the adaptive space, degree {} on the interfaces of {} \
                     nodes or more, 3 on those of {} or more, 2 on those of {} or more; macro_degree = 1 keeps the \
                     rigid motions and extensions alone)",
                    crate::settings::MacroDegree::AUTO_MAX,
                    crate::settings::QUINTIC_FACE_NODES,
                    crate::settings::POLYNOMIAL_FACE_NODES,
                    crate::settings::QUADRATIC_FACE_NODES
                )
            } else {
                String::new()
            };
            notes.push(format!(
                "macro space: polynomial fields up to degree {} on {} of {} interfaces, {} macro unknowns{why}",
                st.macro_degree, st.polynomial_interfaces, st.interfaces, st.macro_unknowns
            ));
        }
        if st.redundant_macro_columns > 0 {
            notes.push(format!(
                "macro space: dropped {} of {} columns that repeat others at cross points (combinations that \
                 leave no force on any subdomain)",
                st.redundant_macro_columns,
                st.macro_unknowns + st.redundant_macro_columns
            ));
        }
        if let Some(t) = dd.seam().traffic_by_rank() {
            let col = |k: usize| t.iter().map(|r| r[k].to_string()).collect::<Vec<_>>().join(", ");
            notes.push(format!(
                "mpi: {} ranks; per rank since the last set-up: trace messages [{}], trace bytes [{}], \
                 reductions [{}], reduction bytes [{}]",
                t.len(),
                col(0),
                col(1),
                col(2),
                col(3)
            ));
        }
        let spread = dd.stats().stiffness_spread;
        if opts.method == Method::Cg && dd.lumped_force() {
            notes.push(format!(
                "cg: the stiffness spread is {spread:.1e} (largest over smallest stiffness diagonal): the \
                 indicator measures the force error by the stiffness-weighted jump, which is pessimistic \
                 and may stall above a tight tolerance, because the preconditioned jump let wrong answers \
                 pass at this contrast"
            ));
        }
        if let Some(r) = dd.coarse_residual().filter(|r| !(*r <= COARSE_RESIDUAL_NOTE)) {
            notes.push(format!(
                "the coarse problem was solved to a backward error of only {r:.1e} (badly conditioned \
                 macro space): the result may be less accurate than its indicator says"
            ));
        }
    }
    let factors = match &prepared {
        Prepared::Direct(d) => {
            let st = d.stats();
            let nd = st.ordering == Some(OrderingKind::NestedDissection);
            Some(FactorSizes {
                nnz_l: st.nnz_l,
                nested_dissection: nd as usize,
                amd: (!nd) as usize,
            })
        }
        Prepared::Dd(dd, _) => {
            let st = dd.stats();
            Some(FactorSizes {
                nnz_l: st.nnz_l + st.interior_nnz_l,
                nested_dissection: st.nested_dissection_factors,
                amd: st.factors - st.nested_dissection_factors,
            })
        }
        Prepared::NonsmoothCg(_) => None,
    };
    let setup_phases = match &prepared {
        Prepared::Dd(dd, _) => {
            let st = dd.stats();
            Some(SetupPhases {
                factor: st.factor_s,
                interior: st.interior_s,
                scaling: st.scaling_s,
                coarse: st.coarse_s,
                adaptive: st.adaptive_s,
                search_direction: st.search_direction_s,
            })
        }
        _ => None,
    };
    Ok(SolveResult {
        factors,
        equilibrium_residual,
        equilibrium_refinement: top.refinement,
        scene: model.name.clone(),
        method: opts.method.name().to_string(),
        effects: model.effects.names().into_iter().map(String::from).collect(),
        stages: prepared.stages(&model),
        converged: status.is_converged(),
        status,
        stop_message,
        iterations: top.iterations,
        subdomains: n_sub,
        displacements: main.displacements,
        tensions: main.tensions,
        slack: main.slack,
        history: top.history,
        timings_s: Timings {
            setup,
            solve: t_solve.elapsed().as_secs_f64(),
            setup_phases,
        },
        search_direction: d,
        notes,
        load_cases,
        steps,
        element_subdomain,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::generate::{tower, TowerParams};

    /// The direct solve's tensions pass the equilibrium check at 1e-10 (6e-12);
    /// one bar's elongation off by 1e-6 of itself (tensions 1e-7 off
    /// relative to their norm at most) turns a converged outcome into a
    /// stalled one that says why, and keeps its answer.
    #[test]
    fn a_claim_needs_tensions_in_equilibrium_with_the_loads() {
        let scene = tower(&TowerParams {
            nx: 2,
            ny: 2,
            nz: 4,
            unilateral: false,
            ..Default::default()
        });
        let model = Model::from_scene(&scene).unwrap();
        let opts = SolveOptions {
            method: Method::Direct,
            ..Default::default()
        };
        let mut prepared = prepare_in(&model, &scene, &opts, Placement::Process).unwrap();
        let f = model.load_cases[0].clone();
        let mut out = prepared.solve(&model, &f, false, None).unwrap();
        let elongations: Vec<f64> = (0..model.elements.len()).map(|e| model.elongation(e, &out.u)).collect();
        let tensions = model.tensions_from_elongations(&elongations, &vec![false; elongations.len()]);
        let exact = model.equilibrium_residual(&f, &tensions, &out.u).unwrap();
        assert!(exact < 1e-10, "direct: {exact:e}");
        out.elongations = Some(elongations.clone());
        check_equilibrium(&model, &f, &mut out, 1e-10);
        assert_eq!(out.status, Status::Converged);
        // The stiffest loaded element, off by 1e-6 of its elongation.
        let e = (0..tensions.len())
            .max_by(|&a, &b| tensions[a].abs().total_cmp(&tensions[b].abs()))
            .unwrap();
        let mut off = elongations;
        off[e] *= 1.0 + 1e-6;
        let u = out.u.clone();
        out.elongations = Some(off);
        check_equilibrium(&model, &f, &mut out, 1e-10);
        assert_eq!(out.status, Status::Stalled);
        assert!(
            out.message.as_deref().is_some_and(|m| m.contains("miss equilibrium")),
            "{:?}",
            out.message
        );
        assert_eq!(out.u, u);
    }
}
