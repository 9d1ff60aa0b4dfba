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

use crate::dd::{DdOptions, DdSolver};
use crate::decomposition::Decomposition;
use crate::direct::{DirectSolver, Equilibrium};
use crate::error::Result;
use crate::model::Model;
use crate::nonsmooth::{NonsmoothCg, NonsmoothOptions};
use crate::partition::Partition;
use crate::result::{CaseResult, HistoryEntry, SolveResult, Timings};
use crate::scene::{Method, Preconditioner, Scene, SearchDirection};
use std::time::Instant;

/// Solver settings (the scene's `[solver]`, possibly overridden).
#[derive(Debug, Clone)]
pub struct SolveOptions {
    pub method: Method,
    pub subdomains: usize,
    pub tolerance: f64,
    pub max_iterations: usize,
    pub search_direction: SearchDirection,
    /// Preconditioner of `cg` (ignored by the other methods).
    pub preconditioner: Preconditioner,
}

impl SolveOptions {
    /// Checks the settings like the scene's `[solver]` section is checked.
    pub fn validate(&self) -> Result<()> {
        crate::scene::check_solver_values(
            self.tolerance,
            self.subdomains,
            self.max_iterations,
            self.search_direction,
        )
    }

    /// The scene's own `[solver]` settings.
    pub fn from_scene(scene: &Scene) -> SolveOptions {
        let s = &scene.solver;
        SolveOptions {
            method: s.method,
            subdomains: s.subdomains,
            tolerance: s.tolerance,
            max_iterations: s.max_iterations,
            search_direction: s.search_direction,
            preconditioner: s.preconditioner,
        }
    }
}

/// A callback told `(iteration, indicator)` after every iteration.
pub type Progress<'a> = Option<&'a mut dyn FnMut(usize, f64)>;

/// A set-up solver of either kind, reusable over load cases.
pub enum Prepared {
    Direct(Box<DirectSolver>),
    Dd(Box<DdSolver>, Decomposition),
    /// `cg` on a model with unilateral cables: active set around the
    /// interface CG ([`crate::nonsmooth`]).
    NonsmoothCg(Box<NonsmoothCg>),
}

/// Builds the decomposition the options ask for (user partition first).
pub fn decompose(model: &Model, scene: &Scene, subdomains: usize) -> Result<Decomposition> {
    let partition = if !scene.elements.subdomain.is_empty() {
        Partition::from_user(model, &scene.elements.subdomain)?
    } else {
        Partition::bisection(model, subdomains)?
    };
    Ok(Decomposition::new(model, partition))
}

/// Sets up the solver for `model` (factorizations, coarse problem).
pub fn prepare(model: &Model, scene: &Scene, opts: &SolveOptions) -> Result<Prepared> {
    Ok(match opts.method {
        Method::Direct => Prepared::Direct(Box::new(DirectSolver::new(model)?)),
        Method::Cg if !model.cables.is_empty() => {
            let dec = decompose(model, scene, opts.subdomains)?;
            Prepared::NonsmoothCg(Box::new(NonsmoothCg::new(
                model,
                dec,
                NonsmoothOptions {
                    tolerance: opts.tolerance,
                    max_iterations: opts.max_iterations,
                    preconditioner: opts.preconditioner,
                },
            )?))
        }
        Method::Monolevel | Method::Multilevel | Method::Cg => {
            let dec = decompose(model, scene, opts.subdomains)?;
            let dd = DdSolver::new(
                model,
                &dec,
                DdOptions {
                    coarse: opts.method != Method::Monolevel,
                    krylov: opts.method == Method::Cg,
                    preconditioner: opts.preconditioner,
                    tolerance: opts.tolerance,
                    max_iterations: opts.max_iterations,
                    search_direction: opts.search_direction,
                },
            )?;
            Prepared::Dd(Box::new(dd), dec)
        }
    })
}

/// One solved state.
pub struct State {
    pub equilibrium: Equilibrium,
    pub converged: bool,
    pub history: Vec<HistoryEntry>,
    /// Outer active-set steps and DD set-ups of the nonsmooth CG.
    pub outer_steps: Option<(usize, usize)>,
}

impl Prepared {
    /// Solves for external forces `f_ext` (free dofs). `warm` starts a DD
    /// iteration from the previous state (load paths).
    pub fn solve(&mut self, model: &Model, f_ext: &[f64], warm: bool, progress: Progress<'_>) -> Result<State> {
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
                Ok(State {
                    equilibrium: eq,
                    converged: true,
                    history,
                    outer_steps: None,
                })
            }
            Prepared::Dd(dd, _) => {
                let out = dd.solve(f_ext, warm, progress)?;
                Ok(State {
                    equilibrium: Equilibrium {
                        u: out.u,
                        lambda: out.lambda,
                        iterations: out.iterations,
                    },
                    converged: out.converged,
                    history: out.history,
                    outer_steps: None,
                })
            }
            Prepared::NonsmoothCg(ns) => {
                let out = ns.solve(model, f_ext, progress)?;
                Ok(State {
                    equilibrium: out.equilibrium,
                    converged: out.converged,
                    history: out.history,
                    outer_steps: Some((out.outer_steps, out.setups)),
                })
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

/// Relative slack threshold of a method: round-off for the direct solver,
/// ten times the tolerance for the iterative ones.
fn slack_threshold(opts: &SolveOptions) -> f64 {
    match opts.method {
        Method::Direct => 1e-12,
        _ => 10.0 * opts.tolerance,
    }
}

fn case_result(model: &Model, name: &str, load_factor: f64, st: &State, slack_rel: f64) -> CaseResult {
    let eq = &st.equilibrium;
    let slack = model.slack_flags(&eq.u, &eq.lambda, slack_rel);
    CaseResult {
        name: name.to_string(),
        load_factor,
        converged: st.converged,
        iterations: eq.iterations,
        displacements: model.node_displacements(&eq.u),
        tensions: model.tensions_with_slack(&eq.u, &slack),
        slack,
    }
}

/// Validates the scene, builds the model, sets up the method and solves
/// every load case (and load-path step) the scene asks for.
pub fn solve(scene: &Scene, opts: &SolveOptions) -> Result<SolveResult> {
    solve_with_progress(scene, opts, None)
}

/// [`solve`] with a progress callback.
pub fn solve_with_progress(scene: &Scene, opts: &SolveOptions, mut progress: Progress<'_>) -> Result<SolveResult> {
    let t_setup = Instant::now();
    opts.validate()?;
    let model = Model::from_scene(scene)?;
    let mut prepared = prepare(&model, scene, opts)?;
    let setup = t_setup.elapsed().as_secs_f64();
    let t_solve = Instant::now();

    let mut steps = Vec::new();
    let mut top: Option<State> = None;
    if let Some(path) = &scene.load_path {
        for k in 1..=path.steps {
            let factor = path.final_factor * k as f64 / path.steps as f64;
            let f: Vec<f64> = model.load_cases[0].iter().map(|v| v * factor).collect();
            let st = prepared.solve(
                &model,
                &f,
                k > 1,
                progress.as_deref_mut().map(|p| p as &mut dyn FnMut(usize, f64)),
            )?;
            steps.push(case_result(
                &model,
                &format!("step {k}"),
                factor,
                &st,
                slack_threshold(opts),
            ));
            top = Some(st);
        }
    } else {
        top = Some(prepared.solve(&model, &model.load_cases[0], false, progress)?);
    }
    let mut load_cases = Vec::new();
    for c in 1..model.load_cases.len() {
        let st = prepared.solve(&model, &model.load_cases[c], false, None)?;
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
    let (n_sub, element_subdomain, d) = match &prepared {
        Prepared::Direct(_) => (1, Vec::new(), None),
        // CG has no step length `d`: only the stationary iteration reports one.
        Prepared::Dd(dd, dec) => (
            dec.len(),
            dec.partition.part_of.clone(),
            (opts.method != Method::Cg).then(|| dd.search_direction()),
        ),
        Prepared::NonsmoothCg(ns) => (
            ns.decomposition().len(),
            ns.decomposition().partition.part_of.clone(),
            None,
        ),
    };
    let mut notes = model.notes.clone();
    if let Some((outer, setups)) = top.outer_steps {
        notes.push(format!(
            "nonsmooth cg: {outer} active-set steps ({setups} DD set-ups), {} interface CG iterations in all",
            top.equilibrium.iterations
        ));
    }
    let last_dd = match &prepared {
        Prepared::Dd(dd, _) => Some(&**dd),
        Prepared::NonsmoothCg(ns) => ns.last_solver(),
        Prepared::Direct(_) => None,
    };
    if let Some(dd) = last_dd {
        if let Some(r) = dd.coarse_residual().filter(|r| !(*r <= COARSE_RESIDUAL_NOTE)) {
            notes.push(format!(
                "the coarse problem was solved to a backward error of only {r:.1e} (badly conditioned \
                 macro space): the result may be less accurate than its indicator says"
            ));
        }
    }
    Ok(SolveResult {
        scene: model.name.clone(),
        method: opts.method.name().to_string(),
        effects: model.effects.names().into_iter().map(String::from).collect(),
        stages: prepared.stages(&model),
        converged: top.converged && steps.iter().all(|s| s.converged) && load_cases.iter().all(|s| s.converged),
        iterations: top.equilibrium.iterations,
        subdomains: n_sub,
        displacements: main.displacements,
        tensions: main.tensions,
        slack: main.slack,
        history: top.history,
        timings_s: Timings {
            setup,
            solve: t_solve.elapsed().as_secs_f64(),
        },
        search_direction: d,
        notes,
        load_cases,
        steps,
        element_subdomain,
    })
}
