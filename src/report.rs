//! Part of the `nsdd` binary (a module of `main.rs`, not of the library:
//! it needs plotters, which the library and its C users do not): the human
//! summary of a solve, exit codes, the partition report, the accuracy study
//! (error against time to accuracy, against the direct solution) and the
//! scaling study, with their CSV and SVG output.
//!
//! Every study runs through the public facade ([`nsdd::solve`]), so the
//! times it reports are what a user of `nsdd solve` gets: setup (model,
//! partition, factorizations, coarse problem) plus solve.

use std::collections::BTreeMap;
use std::fmt::Write as _;

use plotters::prelude::*;
use serde::Serialize;

use nsdd::decomposition::QualityReport;
use nsdd::error::{Error, Result};
use nsdd::model::Model;
use nsdd::result::SolveResult;
use nsdd::scene::{ElementKind, Method, Preconditioner, Scene, SearchDirection};
use nsdd::solve::{auto_subdomains, decompose, solve_with_progress, SolveOptions, WARNING_PREFIX};
use nsdd::subdomain::SubdomainOperator;

// ---------------------------------------------------------------------------
// Exit codes and summary
// ---------------------------------------------------------------------------

/// Exit status of the command line for an error: 2 bad input (parse, I/O,
/// invalid field), 3 a structure or decomposition the method cannot solve,
/// 4 divergence or numerical failure.
pub fn exit_code(e: &Error) -> i32 {
    match e {
        Error::InvalidInput { .. } | Error::Parse(_) | Error::Io(_) => 2,
        Error::Mechanism(_) | Error::IndefiniteSubdomain { .. } | Error::MethodNotApplicable(_) => 3,
        Error::Diverged { .. } | Error::Numerical(_) => 4,
    }
}

/// Exit status of a solve that ran but did not reach its tolerance.
pub const EXIT_NOT_CONVERGED: i32 = 5;

/// Largest displacement magnitude and its node (None without nodes).
pub fn max_displacement(displacements: &[[f64; 3]]) -> Option<(usize, f64)> {
    displacements
        .iter()
        .map(|d| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt())
        .enumerate()
        .fold(None, |best, (i, m)| match best {
            Some((_, b)) if b >= m => best,
            _ => Some((i, m)),
        })
}

/// The short human summary `nsdd solve` prints.
pub fn summary(scene: &Scene, r: &SolveResult) -> String {
    let mut s = String::new();
    let n_cables = scene.elements.kind.iter().filter(|k| **k == ElementKind::Cable).count();
    let n_slack = r.slack.iter().filter(|&&b| b).count();
    let _ = writeln!(
        s,
        "scene       {}",
        if r.scene.is_empty() { "(unnamed)" } else { &r.scene }
    );
    let mut method = r.method.clone();
    if r.method != "direct" {
        let _ = write!(
            method,
            " ({} subdomain{}",
            r.subdomains,
            if r.subdomains == 1 { "" } else { "s" }
        );
        if let Some(d) = r.search_direction {
            let _ = write!(method, ", d = {d:.3e}");
        }
        method.push(')');
    }
    let _ = writeln!(s, "method      {method}");
    let _ = writeln!(
        s,
        "effects     {}",
        if r.effects.is_empty() {
            "none".into()
        } else {
            r.effects.join(", ")
        }
    );
    let _ = writeln!(s, "stages      {}", r.stages.join(", "));
    let last = r.history.last().map(|h| h.indicator);
    let _ = write!(
        s,
        "converged   {} ({} iteration{}",
        if r.converged {
            "yes".to_string()
        } else {
            format!("NO, {}", r.status.describe())
        },
        r.iterations,
        if r.iterations == 1 { "" } else { "s" }
    );
    if let (Some(ind), true) = (last, r.method != "direct") {
        let _ = write!(s, ", final indicator {ind:.3e}");
    }
    let _ = writeln!(s, ")");
    if let Some(e) = r.equilibrium_residual {
        let _ = write!(s, "equilibrium tensions off the loads by {e:.3e} of their norm");
        if let Some(rf) = r.equilibrium_refinement {
            let _ = write!(
                s,
                " ({:.1e} before {} correction{}, {} of the iterations)",
                rf.residual_before,
                rf.corrections,
                if rf.corrections == 1 { "" } else { "s" },
                rf.iterations
            );
        }
        let _ = writeln!(s);
    }
    let _ = writeln!(
        s,
        "time        setup {:.4} s, solve {:.4} s, total {:.4} s",
        r.timings_s.setup,
        r.timings_s.solve,
        r.timings_s.setup + r.timings_s.solve
    );
    if let Some(p) = &r.timings_s.setup_phases {
        let _ = writeln!(
            s,
            "setup       factor {:.4} s, interior {:.4} s, scaling {:.4} s, coarse {:.4} s, d {:.4} s",
            p.factor, p.interior, p.scaling, p.coarse, p.search_direction
        );
        if p.adaptive > 0.0 {
            let _ = writeln!(s, "            adaptive macro columns {:.4} s", p.adaptive);
        }
    }
    if let Some(f) = &r.factors {
        let _ = writeln!(
            s,
            "factors     nnz(L) {:.3e} in {} factor{} (nested dissection {}, amd {})",
            f.nnz_l as f64,
            f.nested_dissection + f.amd,
            if f.nested_dissection + f.amd == 1 { "" } else { "s" },
            f.nested_dissection,
            f.amd
        );
    }
    match max_displacement(&r.displacements) {
        Some((n, m)) => {
            let _ = writeln!(s, "max |u|     {m:.6e} (node {n})");
        }
        None => {
            let _ = writeln!(s, "max |u|     -");
        }
    }
    let _ = writeln!(
        s,
        "slack       {n_slack} of {n_cables} cable{}",
        if n_cables == 1 { "" } else { "s" }
    );
    if !r.steps.is_empty() {
        let _ = writeln!(
            s,
            "load path   {} steps, all converged: {}",
            r.steps.len(),
            r.steps.iter().all(|c| c.converged)
        );
    }
    if !r.load_cases.is_empty() {
        let _ = writeln!(
            s,
            "load cases  {} more, all converged: {}",
            r.load_cases.len(),
            r.load_cases.iter().all(|c| c.converged)
        );
    }
    // Warnings go to stderr (`nsdd solve`), not into the summary.
    for n in r.notes.iter().filter(|n| !n.starts_with(WARNING_PREFIX)) {
        let _ = writeln!(s, "note        {n}");
    }
    s
}

// ---------------------------------------------------------------------------
// Errors against a reference
// ---------------------------------------------------------------------------

/// `‖a − b‖ / ‖b‖` (the absolute norm when `b` is zero).
pub fn rel_err(a: &[f64], b: &[f64]) -> f64 {
    let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>().sqrt();
    let den: f64 = b.iter().map(|y| y * y).sum::<f64>().sqrt();
    if den > 0.0 {
        num / den
    } else {
        num
    }
}

/// True error of a solution against a reference.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Errors {
    /// Relative 2-norm error of the displacements.
    pub error_u: f64,
    /// Relative 2-norm error of the tensions.
    pub error_t: f64,
    /// Elements whose slack flag differs.
    pub slack_mismatch: usize,
}

fn flat(v: &[[f64; 3]]) -> Vec<f64> {
    v.iter().flatten().copied().collect()
}

/// Errors of `r` against `reference` (both top-level states).
pub fn compare(r: &SolveResult, reference: &SolveResult) -> Errors {
    Errors {
        error_u: rel_err(&flat(&r.displacements), &flat(&reference.displacements)),
        error_t: rel_err(&r.tensions, &reference.tensions),
        slack_mismatch: r.slack.iter().zip(&reference.slack).filter(|(a, b)| a != b).count()
            + r.slack.len().abs_diff(reference.slack.len()),
    }
}

// ---------------------------------------------------------------------------
// Progress of the studies
// ---------------------------------------------------------------------------

/// What a study tells its observer (the command line draws a bar from it).
#[derive(Debug, Clone, Copy)]
pub enum Event<'a> {
    /// Run `run` of `runs` starts; `label` says which.
    Start { label: &'a str, run: usize, runs: usize },
    /// An iteration of the current run finished.
    Iteration { iteration: usize, indicator: f64 },
}

/// Optional observer of a study.
pub type Observer<'a> = Option<&'a mut (dyn FnMut(Event<'_>) + Send)>;

fn run_solve(scene: &Scene, opts: &SolveOptions, obs: &mut Observer<'_>) -> Result<SolveResult> {
    match obs.as_deref_mut() {
        Some(o) => {
            let mut cb = |iteration: usize, indicator: f64| o(Event::Iteration { iteration, indicator });
            solve_with_progress(scene, opts, Some(&mut cb))
        }
        None => solve_with_progress(scene, opts, None),
    }
}

fn start(obs: &mut Observer<'_>, label: &str, run: usize, runs: usize) {
    if let Some(o) = obs.as_deref_mut() {
        o(Event::Start { label, run, runs });
    }
}

// ---------------------------------------------------------------------------
// Partition report
// ---------------------------------------------------------------------------

/// One subdomain of the partition report.
#[derive(Debug, Clone, Serialize)]
pub struct SubdomainInfo {
    pub id: usize,
    pub elements: usize,
    pub dofs: usize,
    /// Dimension of the kernel of `K_E` (0 for a regular subdomain); None
    /// when the subdomain could not be factored (see `error`).
    pub kernel_dim: Option<usize>,
    /// Of those, the modes that are not rigid motions of the subdomain:
    /// local mechanisms (`nsdd::subdomain::local_mechanisms`).
    pub mechanisms: Option<usize>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Whether the error is an indefinite matrix.
    #[serde(skip)]
    pub indefinite: bool,
}

/// What `nsdd partition` prints.
#[derive(Debug, Clone, Serialize)]
pub struct PartitionReport {
    pub scene: String,
    pub quality: QualityReport,
    pub subdomains: Vec<SubdomainInfo>,
    /// `(subdomain, kernel dimension)` of every singular subdomain.
    pub singular: Vec<(usize, usize)>,
    /// Whether `monolevel` applies (no singular subdomain, more than one).
    pub monolevel_applies: bool,
    /// Where subdomains are indefinite on their own and a solve would
    /// merge them into neighbours (compressed struts on nsdd's own
    /// partition): the subdomains it would start from.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub subdomains_after_merging: Option<usize>,
}

/// Partitions the scene into `subdomains` parts (or the user partition of
/// the scene), reports the interface quality, and factors every subdomain
/// matrix to find its kernel dimension.
pub fn partition_report(scene: &Scene, subdomains: usize) -> Result<PartitionReport> {
    let model = Model::from_scene(scene)?;
    let dec = decompose(&model, scene, subdomains)?;
    let quality = dec.quality(&model);
    let infos: Vec<SubdomainInfo> = dec
        .subdomains
        .iter()
        .enumerate()
        .map(|(id, sd)| {
            let (kernel_dim, mechanisms, error) = match SubdomainOperator::new(id, &model, sd, 1, scene.solver.ordering)
            {
                Ok(op) => (
                    Some(op.kernel_dim()),
                    nsdd::subdomain::local_mechanisms(&op, &model, sd),
                    None,
                ),
                Err(e) => (None, None, Some(e)),
            };
            SubdomainInfo {
                id,
                elements: sd.elements.len(),
                dofs: sd.dofs.len(),
                kernel_dim,
                mechanisms,
                indefinite: matches!(error, Some(Error::IndefiniteSubdomain { .. })),
                error: error.map(|e| e.to_string()),
            }
        })
        .collect();
    let singular: Vec<(usize, usize)> = infos
        .iter()
        .filter_map(|i| i.kernel_dim.filter(|&k| k > 0).map(|k| (i.id, k)))
        .collect();
    let monolevel_applies = dec.len() > 1 && infos.iter().all(|i| i.kernel_dim == Some(0));
    let indefinite = infos.iter().any(|i| i.indefinite);
    let subdomains_after_merging = (indefinite && nsdd::merging::merges_indefinite(&model, scene))
        .then(|| nsdd::merging::merge_indefinite_subdomains(&model, &dec, scene.solver.ordering).len());
    Ok(PartitionReport {
        scene: model.name.clone(),
        quality,
        subdomains: infos,
        singular,
        monolevel_applies,
        subdomains_after_merging,
    })
}

impl PartitionReport {
    /// Human-readable text.
    pub fn text(&self) -> String {
        let q = &self.quality;
        let mut s = String::new();
        let _ = writeln!(s, "scene               {}", self.scene);
        let _ = writeln!(s, "subdomains          {}", q.subdomains);
        let _ = writeln!(s, "interfaces          {}", q.interfaces);
        let _ = writeln!(
            s,
            "interface dofs      {} ({} pair entries)",
            q.interface_dofs, q.interface_entries
        );
        let _ = writeln!(
            s,
            "cross points        {} (max {} subdomains at a node)",
            q.cross_points, q.max_node_multiplicity
        );
        let _ = writeln!(s, "element imbalance   {:.3} (max / mean)", q.element_imbalance);
        let _ = writeln!(s, "subdomain  elements  dofs  kernel  mechanisms");
        for i in &self.subdomains {
            let k = match (&i.kernel_dim, &i.error) {
                (Some(k), _) => format!("{k:>6}  {:>10}", i.mechanisms.map_or("-".into(), |m| m.to_string())),
                (None, Some(e)) => format!("error: {e}"),
                (None, None) => "-".into(),
            };
            let _ = writeln!(s, "{:>9}  {:>8}  {:>4}  {}", i.id, i.elements, i.dofs, k);
        }
        let mech: Vec<usize> = self.subdomains.iter().filter_map(|i| i.mechanisms).collect();
        let with = mech.iter().filter(|&&m| m > 0).count();
        // A factored subdomain whose kernel could not be split from its
        // rigid motions (an SVD failure) is named, not counted as zero.
        let uncounted = self
            .subdomains
            .iter()
            .filter(|i| i.kernel_dim.is_some() && i.mechanisms.is_none())
            .count();
        let plural = |n: usize| if n > 1 { "s" } else { "" };
        if with > 0 || uncounted > 0 {
            let _ = writeln!(
                s,
                "local mechanisms    {} in {with} subdomain{} (kernel modes that are not rigid motions, each a coarse unknown){}",
                mech.iter().sum::<usize>(),
                plural(with),
                if uncounted > 0 {
                    format!("; not counted in {uncounted} subdomain{} (\"-\" above)", plural(uncounted))
                } else {
                    String::new()
                }
            );
        }
        if self.singular.is_empty() {
            let _ = writeln!(s, "singular subdomains none");
        } else {
            let list: Vec<String> = self.singular.iter().map(|(i, k)| format!("{i} (kernel {k})")).collect();
            let _ = writeln!(s, "singular subdomains {}", list.join(", "));
        }
        let failed: Vec<String> = self
            .subdomains
            .iter()
            .filter(|i| i.error.is_some())
            .map(|i| i.id.to_string())
            .collect();
        if let (false, Some(n)) = (failed.is_empty(), self.subdomains_after_merging) {
            let _ = writeln!(
                s,
                "factorization       failed for subdomain{} {}: a solve merges the ones indefinite on their own \
                 (compressed struts cut off from the cables that hold them) into neighbours and starts from {n} \
                 subdomain{} (a nonsmooth cg may merge more at later slack sets)",
                if failed.len() > 1 { "s" } else { "" },
                failed.join(", "),
                if n > 1 { "s" } else { "" }
            );
        } else if !failed.is_empty() {
            let _ = writeln!(
                s,
                "factorization       failed for subdomain{} {}: no DD method can use this partition",
                if failed.len() > 1 { "s" } else { "" },
                failed.join(", ")
            );
        } else {
            let _ = writeln!(
                s,
                "monolevel           {}",
                if self.monolevel_applies {
                    "applies"
                } else {
                    "does not apply (needs regular subdomains); use multilevel"
                }
            );
        }
        s
    }
}

// ---------------------------------------------------------------------------
// Accuracy study
// ---------------------------------------------------------------------------

/// Settings of [`accuracy`].
#[derive(Debug, Clone)]
pub struct AccuracyOptions {
    /// Number of subdomains of the iterative methods.
    pub subdomains: usize,
    /// Tolerances to sweep, any order (run from loose to tight).
    pub tolerances: Vec<f64>,
    /// Iterative methods to run (the direct solve always runs: it is the
    /// reference). Default: all of them.
    pub methods: Vec<Method>,
    pub max_iterations: usize,
    pub search_direction: SearchDirection,
    /// Preconditioner of `cg` (the scene's).
    pub preconditioner: Preconditioner,
    /// Also sample the true error along the iterations of the tightest run
    /// (costs one extra setup + partial solve per sample).
    pub history: bool,
    /// At most this many true-error samples per history.
    pub history_samples: usize,
}

impl AccuracyOptions {
    /// The scene's settings (an automatic count stays 0, resolved where the
    /// decomposition is made), 4 subdomains when the scene asks for one, and
    /// the decades 1e-2 … 1e-10.
    pub fn from_scene(scene: &Scene) -> AccuracyOptions {
        AccuracyOptions {
            subdomains: if scene.solver.subdomains == 1 {
                4
            } else {
                scene.solver.subdomains
            },
            tolerances: default_tolerances(),
            methods: ITERATIVE_METHODS.to_vec(),
            max_iterations: scene.solver.max_iterations,
            search_direction: scene.solver.search_direction,
            preconditioner: scene.solver.preconditioner,
            history: true,
            history_samples: 24,
        }
    }
}

/// Every iterative method, in the order the studies run them.
pub const ITERATIVE_METHODS: [Method; 3] = [Method::Monolevel, Method::Multilevel, Method::Cg];

/// 1e-2, 1e-3, …, 1e-10.
pub fn default_tolerances() -> Vec<f64> {
    (2..=10).map(|k| 10f64.powi(-k)).collect()
}

/// One run of the accuracy study (a row of `accuracy.csv`).
#[derive(Debug, Clone, Serialize)]
pub struct AccuracyRow {
    pub method: String,
    /// None for the direct reference.
    pub tolerance: Option<f64>,
    pub error_u: f64,
    pub error_t: f64,
    pub slack_mismatch: usize,
    pub iterations: usize,
    /// Wall time, setup + solve.
    pub seconds: f64,
    pub setup_s: f64,
    pub solve_s: f64,
    pub converged: bool,
}

/// One iteration of a convergence history with, at sampled iterations, the
/// true error against the direct solution.
#[derive(Debug, Clone, Serialize)]
pub struct HistoryPoint {
    pub iteration: usize,
    pub time_s: f64,
    pub indicator: f64,
    pub error_u: Option<f64>,
    pub error_t: Option<f64>,
}

/// Convergence history of one method at one tolerance.
#[derive(Debug, Clone, Serialize)]
pub struct MethodHistory {
    pub method: String,
    pub tolerance: f64,
    pub points: Vec<HistoryPoint>,
}

/// The whole accuracy study.
#[derive(Debug, Clone, Serialize)]
pub struct AccuracyReport {
    pub scene: String,
    pub subdomains: usize,
    pub rows: Vec<AccuracyRow>,
    pub histories: Vec<MethodHistory>,
    /// Skipped methods and failed runs, with the reason.
    pub notes: Vec<String>,
}

/// Header of `accuracy.csv`: the first seven columns are fixed; later ones
/// may be added at the end.
pub const ACCURACY_HEADER: &str =
    "method,tolerance,error_u,error_t,slack_mismatch,iterations,seconds,setup_s,solve_s,converged";

/// Header of `history-<method>.csv` (`error_u` and later columns are empty
/// on iterations where the true error was not sampled).
pub const HISTORY_HEADER: &str = "iteration,time_s,indicator,error_u,error_t";

/// Iteration counts `1 = k_0 < k_1 < … < k_m = n`, geometric, at most
/// `max_samples` of them (fewer when `n` is small).
pub fn geometric_samples(n: usize, max_samples: usize) -> Vec<usize> {
    if n == 0 || max_samples == 0 {
        return Vec::new();
    }
    let m = max_samples.max(2) - 1;
    let ratio = (n as f64).powf(1.0 / m as f64).max(1.0 + 1e-12);
    let mut out = vec![1usize];
    let mut x = 1.0f64;
    while *out.last().unwrap() < n {
        x *= ratio;
        let k = (x.round() as usize).clamp(out.last().unwrap() + 1, n);
        out.push(k);
    }
    out
}

fn method_options(
    method: Method,
    subdomains: usize,
    tolerance: f64,
    max_iterations: usize,
    d: SearchDirection,
    preconditioner: Preconditioner,
    scene: &SolveOptions,
) -> SolveOptions {
    // The scene's partition and factorizations; the rest is the study's.
    SolveOptions {
        method,
        subdomains,
        tolerance,
        max_iterations,
        search_direction: d,
        preconditioner,
        interface_scaling: Default::default(),
        adaptive_threshold: Default::default(),
        adaptive_edges: Default::default(),
        macro_degree: Default::default(),
        partitioner: scene.partitioner,
        ordering: scene.ordering,
    }
}

fn refuses(e: &Error) -> bool {
    matches!(
        e,
        Error::MethodNotApplicable(_) | Error::Mechanism(_) | Error::IndefiniteSubdomain { .. }
    )
}

/// Runs the direct method (the reference), then monolevel (when it applies)
/// and multilevel at every tolerance, each with a fresh setup so that
/// `seconds` is the honest time to that accuracy. Errors are true errors
/// against the direct solution. With `opts.history`, the tightest run of each
/// iterative method also gets its convergence history with the true error
/// at a geometric sample of iteration counts, measured by re-running the
/// same (deterministic) iteration with `max_iterations = k`.
///
/// A method that refuses the decomposition (monolevel with a singular
/// subdomain) or fails at one tolerance (divergence) is recorded in `notes`
/// and skipped; only a failing direct reference is an error.
pub fn accuracy(scene: &Scene, opts: &AccuracyOptions, mut obs: Observer<'_>) -> Result<AccuracyReport> {
    let mut tols: Vec<f64> = opts.tolerances.clone();
    if let Some(t) = tols.iter().find(|t| !(t.is_finite() && **t > 0.0)) {
        return Err(Error::input(
            "tolerances",
            None,
            format!("must be positive numbers, got {t}"),
        ));
    }
    if tols.is_empty() {
        return Err(Error::input("tolerances", None, "at least one tolerance is needed"));
    }
    tols.sort_by(|a, b| b.partial_cmp(a).unwrap());
    tols.dedup();
    let iterative: Vec<Method> = ITERATIVE_METHODS
        .into_iter()
        .filter(|m| opts.methods.contains(m))
        .collect();
    if let Some(m) = opts.methods.iter().find(|m| !ITERATIVE_METHODS.contains(m)) {
        return Err(Error::input(
            "methods",
            None,
            format!(
                "{} is not an iterative method (the direct solve always runs as the reference)",
                m.name()
            ),
        ));
    }
    let runs = 1 + iterative.len() * tols.len();
    start(&mut obs, "direct", 0, runs);
    let dopts = method_options(
        Method::Direct,
        1,
        tols[tols.len() - 1],
        opts.max_iterations,
        opts.search_direction,
        opts.preconditioner,
        &scene.solver,
    );
    let reference = run_solve(scene, &dopts, &mut obs)?;
    let mut rows = vec![AccuracyRow {
        method: "direct".into(),
        tolerance: None,
        error_u: 0.0,
        error_t: 0.0,
        slack_mismatch: 0,
        iterations: reference.iterations,
        seconds: reference.timings_s.setup + reference.timings_s.solve,
        setup_s: reference.timings_s.setup,
        solve_s: reference.timings_s.solve,
        converged: reference.converged,
    }];
    let mut notes = Vec::new();
    let mut histories = Vec::new();

    for (mi, method) in iterative.into_iter().enumerate() {
        let name = method.name();
        let mut tightest: Option<(f64, SolveResult)> = None;
        for (ti, &tol) in tols.iter().enumerate() {
            let label = format!("{name} tol {tol:e}");
            start(&mut obs, &label, 1 + mi * tols.len() + ti, runs);
            let o = method_options(
                method,
                opts.subdomains,
                tol,
                opts.max_iterations,
                opts.search_direction,
                opts.preconditioner,
                &scene.solver,
            );
            match run_solve(scene, &o, &mut obs) {
                Ok(r) => {
                    let e = compare(&r, &reference);
                    rows.push(AccuracyRow {
                        method: name.into(),
                        tolerance: Some(tol),
                        error_u: e.error_u,
                        error_t: e.error_t,
                        slack_mismatch: e.slack_mismatch,
                        iterations: r.iterations,
                        seconds: r.timings_s.setup + r.timings_s.solve,
                        setup_s: r.timings_s.setup,
                        solve_s: r.timings_s.solve,
                        converged: r.converged,
                    });
                    if !r.converged {
                        notes.push(format!(
                            "{name} at tolerance {tol:e}: not converged after {} iterations",
                            r.iterations
                        ));
                    }
                    tightest = Some((tol, r));
                }
                Err(e) if refuses(&e) => {
                    notes.push(format!("{name} skipped: {e}"));
                    break;
                }
                Err(e) => notes.push(format!("{name} at tolerance {tol:e} failed: {e}")),
            }
        }
        if let (true, Some((tol, r))) = (opts.history, tightest) {
            histories.push(history_with_errors(scene, opts, method, tol, &r, &reference, &mut obs)?);
        }
    }
    // The count the runs used (decompose resolves an automatic 0 the same way).
    let subdomains = if opts.subdomains == 0 && scene.elements.subdomain.is_empty() {
        auto_subdomains(&Model::from_scene(scene)?)
    } else {
        opts.subdomains
    };
    Ok(AccuracyReport {
        scene: reference.scene.clone(),
        subdomains,
        rows,
        histories,
        notes,
    })
}

fn history_with_errors(
    scene: &Scene,
    opts: &AccuracyOptions,
    method: Method,
    tol: f64,
    r: &SolveResult,
    reference: &SolveResult,
    obs: &mut Observer<'_>,
) -> Result<MethodHistory> {
    let mut points: Vec<HistoryPoint> = r
        .history
        .iter()
        .map(|h| HistoryPoint {
            iteration: h.iteration,
            time_s: h.time_s,
            indicator: h.indicator,
            error_u: None,
            error_t: None,
        })
        .collect();
    // Load paths and load cases solve several times: the history is the
    // last solve's, which re-running with fewer iterations would not match.
    let sample = scene.load_path.is_none() && r.load_cases.is_empty();
    if sample {
        let n = r.iterations;
        let samples = geometric_samples(n, opts.history_samples);
        for (i, &k) in samples.iter().enumerate() {
            let e = if k == n {
                compare(r, reference)
            } else {
                let label = format!("{} history {}/{}", method.name(), i + 1, samples.len());
                start(obs, &label, 0, 0);
                let o = method_options(
                    method,
                    opts.subdomains,
                    tol,
                    k,
                    opts.search_direction,
                    opts.preconditioner,
                    &scene.solver,
                );
                match run_solve(scene, &o, obs) {
                    Ok(rk) => compare(&rk, reference),
                    Err(_) => continue,
                }
            };
            if let Some(p) = points.iter_mut().find(|p| p.iteration == k) {
                p.error_u = Some(e.error_u);
                p.error_t = Some(e.error_t);
            }
        }
    }
    Ok(MethodHistory {
        method: method.name().into(),
        tolerance: tol,
        points,
    })
}

fn opt_num(v: Option<f64>) -> String {
    v.map(|x| format!("{x:.6e}")).unwrap_or_default()
}

impl AccuracyReport {
    /// `accuracy.csv`: [`ACCURACY_HEADER`], then one row per run (the direct
    /// reference has an empty tolerance and zero error by definition).
    pub fn csv(&self) -> String {
        let mut s = String::from(ACCURACY_HEADER);
        s.push('\n');
        for r in &self.rows {
            let _ = writeln!(
                s,
                "{},{},{:.6e},{:.6e},{},{},{:.6e},{:.6e},{:.6e},{}",
                r.method,
                r.tolerance.map(|t| format!("{t:e}")).unwrap_or_default(),
                r.error_u,
                r.error_t,
                r.slack_mismatch,
                r.iterations,
                r.seconds,
                r.setup_s,
                r.solve_s,
                r.converged
            );
        }
        s
    }

    /// The study as text: the notes, then one line per run.
    pub fn text(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "scene {} ({} subdomains for the iterative methods)",
            self.scene, self.subdomains
        );
        let _ = writeln!(
            s,
            "{:<11} {:>9} {:>12} {:>12} {:>6} {:>7} {:>10}",
            "method", "tolerance", "error_u", "error_t", "slack", "iters", "seconds"
        );
        for r in &self.rows {
            let _ = writeln!(
                s,
                "{:<11} {:>9} {:>12.3e} {:>12.3e} {:>6} {:>7} {:>10.4}{}",
                r.method,
                r.tolerance.map(|t| format!("{t:e}")).unwrap_or_else(|| "-".into()),
                r.error_u,
                r.error_t,
                r.slack_mismatch,
                r.iterations,
                r.seconds,
                if r.converged { "" } else { "  (not converged)" }
            );
        }
        for n in &self.notes {
            let _ = writeln!(s, "note: {n}");
        }
        s
    }
}

impl MethodHistory {
    /// `history-<method>.csv`: [`HISTORY_HEADER`], one row per iteration.
    pub fn csv(&self) -> String {
        let mut s = String::from(HISTORY_HEADER);
        s.push('\n');
        for p in &self.points {
            let _ = writeln!(
                s,
                "{},{:.6e},{:.6e},{},{}",
                p.iteration,
                p.time_s,
                p.indicator,
                opt_num(p.error_u),
                opt_num(p.error_t)
            );
        }
        s
    }
}

// ---------------------------------------------------------------------------
// Scaling study
// ---------------------------------------------------------------------------

/// Settings of [`scaling`].
#[derive(Debug, Clone)]
pub struct ScalingOptions {
    /// Generator kind (`generate::KINDS`).
    pub kind: String,
    /// Scene sizes: `nx = ny = size` (grid, tensegrity) or `nz = size` (tower).
    pub sizes: Vec<usize>,
    /// Subdomain counts.
    pub subdomains: Vec<usize>,
    pub tolerance: f64,
    pub max_iterations: usize,
    pub search_direction: SearchDirection,
    /// Size of the strong-scaling study (default: the largest of `sizes`).
    pub strong_size: Option<usize>,
    /// Extra generator parameters (`key=value`).
    pub params: BTreeMap<String, String>,
}

/// One row of `scaling.csv`.
#[derive(Debug, Clone, Serialize)]
pub struct ScalingRow {
    /// `strong` (fixed size, more subdomains) or `weak` (size grows with the
    /// number of subdomains).
    pub study: String,
    pub size: usize,
    pub subdomains: usize,
    pub method: String,
    pub dofs: usize,
    pub elements: usize,
    /// None for a skipped run.
    pub iterations: Option<usize>,
    pub converged: bool,
    pub setup_s: f64,
    pub solve_s: f64,
    /// Displacement error against the direct solution of the same scene.
    pub error_u: Option<f64>,
    /// Why the run was skipped (empty otherwise).
    pub skipped: String,
}

/// The scaling study.
#[derive(Debug, Clone, Serialize)]
pub struct ScalingReport {
    pub kind: String,
    pub tolerance: f64,
    pub rows: Vec<ScalingRow>,
    pub notes: Vec<String>,
}

/// Header of `scaling.csv`.
pub const SCALING_HEADER: &str =
    "study,size,subdomains,method,dofs,elements,iterations,converged,setup_s,solve_s,seconds,error_u,skipped";

fn scaling_scene(opts: &ScalingOptions, size: usize) -> Result<Scene> {
    let mut args = opts.params.clone();
    if opts.kind == "tower" {
        args.insert("nz".into(), size.to_string());
    } else {
        args.insert("nx".into(), size.to_string());
        args.insert("ny".into(), size.to_string());
    }
    nsdd::generate::by_name(&opts.kind, &args)
}

/// Strong scaling (the strong size with every subdomain count) and weak
/// scaling (`sizes[i]` with `subdomains[i]`), each with monolevel (no coarse
/// step) and multilevel, plus one direct row per size as the time reference.
/// A refused or failed run becomes a row with `skipped` set.
pub fn scaling(opts: &ScalingOptions, mut obs: Observer<'_>) -> Result<ScalingReport> {
    if opts.sizes.is_empty() || opts.subdomains.is_empty() {
        return Err(Error::input(
            "sizes",
            None,
            "at least one size and one subdomain count are needed",
        ));
    }
    if !(opts.tolerance.is_finite() && opts.tolerance > 0.0) {
        return Err(Error::input(
            "tolerance",
            None,
            format!("must be a positive number, got {}", opts.tolerance),
        ));
    }
    let strong = opts.strong_size.unwrap_or_else(|| *opts.sizes.iter().max().unwrap());
    let mut notes = Vec::new();
    if opts.sizes.len() != opts.subdomains.len() {
        notes.push(format!(
            "weak scaling pairs sizes with subdomain counts: {} sizes and {} counts given, {} pairs used",
            opts.sizes.len(),
            opts.subdomains.len(),
            opts.sizes.len().min(opts.subdomains.len())
        ));
    }
    let mut plan: Vec<(&str, usize, usize)> = opts.subdomains.iter().map(|&n| ("strong", strong, n)).collect();
    plan.extend(opts.sizes.iter().zip(&opts.subdomains).map(|(&s, &n)| ("weak", s, n)));
    let methods = ITERATIVE_METHODS;
    let runs = plan.len() * methods.len();
    let mut cache: BTreeMap<usize, (Scene, SolveResult, usize, usize)> = BTreeMap::new();
    let mut rows = Vec::new();
    let mut run = 0;
    for (study, size, nsub) in plan {
        if let std::collections::btree_map::Entry::Vacant(slot) = cache.entry(size) {
            let scene = scaling_scene(opts, size)?;
            let model = Model::from_scene(&scene)?;
            start(&mut obs, &format!("direct size {size}"), run, runs);
            let dopts = method_options(
                Method::Direct,
                1,
                opts.tolerance,
                opts.max_iterations,
                opts.search_direction,
                scene.solver.preconditioner,
                &scene.solver,
            );
            let reference = run_solve(&scene, &dopts, &mut obs)?;
            slot.insert((scene, reference, model.n_free, model.elements.len()));
        }
        let (scene, reference, dofs, elements) = &cache[&size];
        if !rows
            .iter()
            .any(|r: &ScalingRow| r.method == "direct" && r.study == study && r.size == size)
        {
            rows.push(ScalingRow {
                study: study.into(),
                size,
                subdomains: 1,
                method: "direct".into(),
                dofs: *dofs,
                elements: *elements,
                iterations: Some(reference.iterations),
                converged: reference.converged,
                setup_s: reference.timings_s.setup,
                solve_s: reference.timings_s.solve,
                error_u: Some(0.0),
                skipped: String::new(),
            });
        }
        for method in methods {
            start(
                &mut obs,
                &format!("{study} size {size} {} {nsub} subdomains", method.name()),
                run,
                runs,
            );
            run += 1;
            // The same run in the other study (the strong size with its
            // subdomain count in the weak list): reuse it.
            if let Some(prev) = rows
                .iter()
                .find(|r| r.size == size && r.subdomains == nsub && r.method == method.name())
                .cloned()
            {
                rows.push(ScalingRow {
                    study: study.into(),
                    ..prev
                });
                continue;
            }
            // The generated scene's own preconditioner (its `[solver]`).
            let o = method_options(
                method,
                nsub,
                opts.tolerance,
                opts.max_iterations,
                opts.search_direction,
                scene.solver.preconditioner,
                &scene.solver,
            );
            let mut row = ScalingRow {
                study: study.into(),
                size,
                subdomains: nsub,
                method: method.name().into(),
                dofs: *dofs,
                elements: *elements,
                iterations: None,
                converged: false,
                setup_s: 0.0,
                solve_s: 0.0,
                error_u: None,
                skipped: String::new(),
            };
            match run_solve(scene, &o, &mut obs) {
                Ok(r) => {
                    row.iterations = Some(r.iterations);
                    row.converged = r.converged;
                    row.setup_s = r.timings_s.setup;
                    row.solve_s = r.timings_s.solve;
                    row.error_u = Some(compare(&r, reference).error_u);
                    if !r.converged {
                        row.skipped = format!("not converged after {} iterations", r.iterations);
                    }
                }
                Err(e) => row.skipped = e.to_string(),
            }
            rows.push(row);
        }
    }
    Ok(ScalingReport {
        kind: opts.kind.clone(),
        tolerance: opts.tolerance,
        rows,
        notes,
    })
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

impl ScalingReport {
    /// `scaling.csv`: [`SCALING_HEADER`], one row per run.
    pub fn csv(&self) -> String {
        let mut s = String::from(SCALING_HEADER);
        s.push('\n');
        for r in &self.rows {
            let _ = writeln!(
                s,
                "{},{},{},{},{},{},{},{},{:.6e},{:.6e},{:.6e},{},{}",
                r.study,
                r.size,
                r.subdomains,
                r.method,
                r.dofs,
                r.elements,
                r.iterations.map(|i| i.to_string()).unwrap_or_default(),
                r.converged,
                r.setup_s,
                r.solve_s,
                r.setup_s + r.solve_s,
                opt_num(r.error_u),
                csv_field(&r.skipped)
            );
        }
        s
    }

    /// The study as text.
    pub fn text(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(s, "{} scenes, tolerance {:e}", self.kind, self.tolerance);
        let _ = writeln!(
            s,
            "{:<6} {:>5} {:>5} {:<10} {:>8} {:>7} {:>10} {:>10}",
            "study", "size", "subs", "method", "dofs", "iters", "seconds", "error_u"
        );
        for r in &self.rows {
            let _ = write!(
                s,
                "{:<6} {:>5} {:>5} {:<10} {:>8} ",
                r.study, r.size, r.subdomains, r.method, r.dofs
            );
            match r.iterations {
                Some(i) => {
                    let _ = write!(
                        s,
                        "{:>7} {:>10.4} {:>10.2e}",
                        i,
                        r.setup_s + r.solve_s,
                        r.error_u.unwrap_or(f64::NAN)
                    );
                }
                None => {
                    let _ = write!(s, "{:>7} {:>10} {:>10}", "-", "-", "-");
                }
            }
            if !r.skipped.is_empty() {
                let _ = write!(s, "  {}", r.skipped);
            }
            s.push('\n');
        }
        for n in &self.notes {
            let _ = writeln!(s, "note: {n}");
        }
        s
    }
}

// ---------------------------------------------------------------------------
// Plots (SVG)
// ---------------------------------------------------------------------------

const COLORS: [RGBColor; 5] = [
    RGBColor(31, 119, 180),
    RGBColor(214, 39, 40),
    RGBColor(44, 160, 44),
    RGBColor(148, 103, 189),
    RGBColor(255, 127, 14),
];

/// Smallest error drawn on a log axis (a zero error is drawn there).
pub const ERROR_FLOOR: f64 = 1e-17;

fn plot_err<E: std::fmt::Display>(e: E) -> Error {
    Error::Io(format!("cannot draw the plot: {e}"))
}

/// A log-axis range covering `values` (positive ones), padded.
fn log_range(values: impl Iterator<Item = f64>) -> std::ops::Range<f64> {
    let (lo, hi) = values
        .filter(|v| v.is_finite() && *v > 0.0)
        .fold((f64::INFINITY, 0.0f64), |(lo, hi), v| (lo.min(v), hi.max(v)));
    if !(lo.is_finite() && hi > 0.0) {
        return 1e-3..1.0;
    }
    let (lo, hi) = if hi / lo < 10.0 {
        (lo / 3.0, hi * 3.0)
    } else {
        (lo / 1.5, hi * 1.5)
    };
    lo..hi
}

/// `accuracy.svg`: error `max(error_u, error_t)` against wall time (setup +
/// solve), log-log, one curve per iterative method (a point per tolerance,
/// joined loose to tight, each labelled with its tolerance), the direct solve
/// as one marked point (a decade below the smallest other error, its own
/// error being zero by definition). The legend sits beside the plot, never
/// on the data.
pub fn accuracy_svg(report: &AccuracyReport) -> Result<String> {
    let mut buf = String::new();
    {
        let root = SVGBackend::with_string(&mut buf, (1000, 600)).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        let titled = root
            .titled(
                &format!("{}: error against time to accuracy", report.scene),
                ("sans-serif", 22),
            )
            .map_err(plot_err)?;
        let (plot_area, legend_area) = titled.split_horizontally(780);
        // The direct reference has error 0 by definition: draw it a decade
        // below the smallest error of the other runs.
        let floor = report
            .rows
            .iter()
            .map(|r| r.error_u.max(r.error_t))
            .filter(|e| *e > 0.0)
            .fold(f64::INFINITY, f64::min);
        let floor = if floor.is_finite() {
            (floor / 10.0).max(ERROR_FLOOR)
        } else {
            ERROR_FLOOR
        };
        let err = |r: &AccuracyRow| {
            if r.method == "direct" {
                floor
            } else {
                r.error_u.max(r.error_t).max(ERROR_FLOOR)
            }
        };
        let xr = log_range(report.rows.iter().map(|r| r.seconds));
        let yr = log_range(report.rows.iter().map(err));
        let mut chart = ChartBuilder::on(&plot_area)
            .margin(15)
            .x_label_area_size(45)
            .y_label_area_size(80)
            .build_cartesian_2d(xr.log_scale(), yr.log_scale())
            .map_err(plot_err)?;
        chart
            .configure_mesh()
            .light_line_style(RGBColor(238, 238, 238))
            .x_desc("wall time, setup + solve [s]")
            .y_desc("relative error (max of u, t) against direct")
            .x_label_formatter(&sparse_log_label)
            .y_label_formatter(&|y| format!("{y:.0e}"))
            .draw()
            .map_err(plot_err)?;
        let mut methods: Vec<&str> = Vec::new();
        for r in &report.rows {
            if r.method != "direct" && !methods.contains(&r.method.as_str()) {
                methods.push(&r.method);
            }
        }
        // Points of every curve, in tolerance order (loose to tight, as the
        // rows are), with their tolerance labels.
        let curves: Vec<(RGBColor, Vec<LabelledPoint>)> = methods
            .iter()
            .enumerate()
            .map(|(i, m)| {
                let pts = report
                    .rows
                    .iter()
                    .filter(|r| r.method == *m)
                    .map(|r| {
                        let label = r.tolerance.map(|t| format!("{t:e}")).unwrap_or_default();
                        ((r.seconds.max(1e-9), err(r)), label)
                    })
                    .collect();
                (COLORS[i % COLORS.len()], pts)
            })
            .collect();
        for (color, pts) in &curves {
            let xy: Vec<(f64, f64)> = pts.iter().map(|(p, _)| *p).collect();
            chart
                .draw_series(LineSeries::new(xy.clone(), color.stroke_width(2)))
                .map_err(plot_err)?;
            chart
                .draw_series(xy.iter().map(|&p| Circle::new(p, 4, color.filled())))
                .map_err(plot_err)?;
        }
        let direct = report.rows.iter().find(|r| r.method == "direct");
        if let Some(d) = direct {
            chart
                .draw_series(std::iter::once(Cross::new(
                    (d.seconds.max(1e-9), err(d)),
                    8,
                    BLACK.stroke_width(3),
                )))
                .map_err(plot_err)?;
        }

        // Tolerance labels, placed in pixels where they cover no dot, no
        // curve and no other label (a label that fits nowhere is left out;
        // accuracy.csv has every value).
        let (px_range, py_range) = chart.plotting_area().get_pixel_range();
        let mut taken: Vec<LabelBox> = Vec::new();
        for (_, pts) in &curves {
            let px: Vec<(i32, i32)> = pts.iter().map(|(p, _)| chart.backend_coord(p)).collect();
            for &(x, y) in &px {
                taken.push(LabelBox::around(x, y, 5));
            }
            // The joining segments, sampled every few pixels.
            for w in px.windows(2) {
                let (a, b) = (w[0], w[1]);
                let n = ((b.0 - a.0).abs().max((b.1 - a.1).abs()) / 3).max(1);
                for k in 1..n {
                    let x = a.0 + (b.0 - a.0) * k / n;
                    let y = a.1 + (b.1 - a.1) * k / n;
                    taken.push(LabelBox::around(x, y, 1));
                }
            }
        }
        if let Some(d) = direct {
            let (x, y) = chart.backend_coord(&(d.seconds.max(1e-9), err(d)));
            taken.push(LabelBox::around(x, y, 9));
        }
        const LABEL_H: i32 = 11;
        for (color, pts) in &curves {
            let style = ("sans-serif", LABEL_H).into_font().color(color);
            for (p, label) in pts {
                if label.is_empty() {
                    continue;
                }
                let (x, y) = chart.backend_coord(p);
                // A rough width of sans-serif digits at this size.
                let w = 6 * label.len() as i32 + 2;
                let h = LABEL_H;
                // Right, left, then the four diagonals, then above and below;
                // 7 px clears the dot's radius and its own box.
                let candidates = [
                    (x + 8, y - h / 2),
                    (x - 8 - w, y - h / 2),
                    (x + 7, y - h - 7),
                    (x + 7, y + 7),
                    (x - 7 - w, y - h - 7),
                    (x - 7 - w, y + 7),
                    (x - w / 2, y - h - 8),
                    (x - w / 2, y + 8),
                ];
                let fits = candidates
                    .iter()
                    .map(|&(lx, ly)| LabelBox {
                        x0: lx,
                        y0: ly,
                        x1: lx + w,
                        y1: ly + h,
                    })
                    .find(|b| {
                        b.x0 >= px_range.start
                            && b.x1 < px_range.end
                            && b.y0 >= py_range.start
                            && b.y1 < py_range.end
                            && !taken.iter().any(|t| t.overlaps(b))
                    });
                if let Some(b) = fits {
                    root.draw(&Text::new(label.clone(), (b.x0, b.y0), style.clone()))
                        .map_err(plot_err)?;
                    taken.push(b);
                }
            }
        }

        // Legend, beside the plot.
        let font = ("sans-serif", 14).into_font();
        let mut y = 40;
        for ((color, _), m) in curves.iter().zip(&methods) {
            legend_area
                .draw(&PathElement::new(vec![(4, y), (30, y)], color.stroke_width(2)))
                .map_err(plot_err)?;
            legend_area
                .draw(&Circle::new((17, y), 4, color.filled()))
                .map_err(plot_err)?;
            legend_area
                .draw(&Text::new(m.to_string(), (38, y - 7), font.clone()))
                .map_err(plot_err)?;
            y += 24;
        }
        if direct.is_some() {
            legend_area
                .draw(&Cross::new((17, y), 6, BLACK.stroke_width(2)))
                .map_err(plot_err)?;
            legend_area
                .draw(&Text::new("direct (reference)", (38, y - 7), font.clone()))
                .map_err(plot_err)?;
            let small = ("sans-serif", 12).into_font().color(&RGBColor(90, 90, 90));
            for (k, line) in ["error 0, drawn at the", "bottom"].iter().enumerate() {
                legend_area
                    .draw(&Text::new(
                        line.to_string(),
                        (38, y + 10 + 15 * k as i32),
                        small.clone(),
                    ))
                    .map_err(plot_err)?;
            }
            y += 50;
        }
        let small = ("sans-serif", 12).into_font().color(&RGBColor(90, 90, 90));
        for (k, line) in ["Each dot is one run, labelled", "with its tolerance."]
            .iter()
            .enumerate()
        {
            legend_area
                .draw(&Text::new(line.to_string(), (4, y + 10 + 15 * k as i32), small.clone()))
                .map_err(plot_err)?;
        }
        root.present().map_err(plot_err)?;
    }
    Ok(buf)
}

/// A log-axis tick label at mantissas 1, 2 and 5 only: plotters puts a
/// tick at every mantissa near the end of a decade, where the labels
/// `7e-2 8e-2 9e-2 1e-1` ran into each other.
fn sparse_log_label(x: &f64) -> String {
    let label = format!("{x:.0e}");
    if label.starts_with(['1', '2', '5']) {
        label
    } else {
        String::new()
    }
}

/// A point of the accuracy plot and its tolerance label.
type LabelledPoint = ((f64, f64), String);

/// A label's pixel rectangle (half-open), for placing labels apart.
#[derive(Debug, Clone, Copy)]
struct LabelBox {
    x0: i32,
    y0: i32,
    x1: i32,
    y1: i32,
}

impl LabelBox {
    fn around(x: i32, y: i32, r: i32) -> LabelBox {
        LabelBox {
            x0: x - r,
            y0: y - r,
            x1: x + r + 1,
            y1: y + r + 1,
        }
    }

    fn overlaps(&self, o: &LabelBox) -> bool {
        self.x0 < o.x1 && o.x0 < self.x1 && self.y0 < o.y1 && o.y0 < self.y1
    }
}

/// `history-<method>.svg`: the convergence indicator at every iteration and
/// the sampled true error, against solve time, log y.
pub fn history_svg(h: &MethodHistory) -> Result<String> {
    let mut buf = String::new();
    {
        let root = SVGBackend::with_string(&mut buf, (900, 600)).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        let ind: Vec<(f64, f64)> = h
            .points
            .iter()
            .filter(|p| p.indicator > 0.0 && p.indicator.is_finite())
            .map(|p| (p.time_s, p.indicator))
            .collect();
        let err: Vec<(f64, f64)> = h
            .points
            .iter()
            .filter_map(|p| p.error_u.map(|e| (p.time_s, e.max(ERROR_FLOOR))))
            .collect();
        let tmax = h.points.iter().map(|p| p.time_s).fold(0.0f64, f64::max).max(1e-6) * 1.05;
        let yr = log_range(ind.iter().chain(&err).map(|p| p.1));
        let mut chart = ChartBuilder::on(&root)
            .caption(
                format!("{} convergence (tolerance {:e})", h.method, h.tolerance),
                ("sans-serif", 22),
            )
            .margin(15)
            .x_label_area_size(45)
            .y_label_area_size(80)
            .build_cartesian_2d(0.0..tmax, yr.log_scale())
            .map_err(plot_err)?;
        chart
            .configure_mesh()
            .light_line_style(RGBColor(238, 238, 238))
            .x_desc("solve time [s]")
            .y_desc("indicator / relative error of u")
            .y_label_formatter(&|y| format!("{y:.0e}"))
            .draw()
            .map_err(plot_err)?;
        let c0 = COLORS[0];
        chart
            .draw_series(LineSeries::new(ind, c0.stroke_width(2)))
            .map_err(plot_err)?
            .label("indicator")
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c0.stroke_width(2)));
        let c1 = COLORS[1];
        chart
            .draw_series(LineSeries::new(err.clone(), c1.stroke_width(2)))
            .map_err(plot_err)?
            .label("true error of u (against direct)")
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], c1.stroke_width(2)));
        chart
            .draw_series(err.iter().map(|&p| Circle::new(p, 4, c1.filled())))
            .map_err(plot_err)?;
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(BLACK)
            .draw()
            .map_err(plot_err)?;
        root.present().map_err(plot_err)?;
    }
    Ok(buf)
}

/// `scaling.svg`: iterations against the number of subdomains (strong
/// scaling, left) and against the size (weak scaling, right), one curve per
/// iterative method; skipped runs are left out.
pub fn scaling_svg(report: &ScalingReport) -> Result<String> {
    let mut buf = String::new();
    {
        let root = SVGBackend::with_string(&mut buf, (1200, 550)).into_drawing_area();
        root.fill(&WHITE).map_err(plot_err)?;
        let panels = root.split_evenly((1, 2));
        for (panel, study) in panels.iter().zip(["strong", "weak"]) {
            let rows: Vec<&ScalingRow> = report
                .rows
                .iter()
                .filter(|r| r.study == study && r.method != "direct" && r.iterations.is_some())
                .collect();
            // log2 of the subdomain count or size on a linear axis, labelled
            // with the value at powers of two.
            let xval = |r: &ScalingRow| (if study == "strong" { r.subdomains } else { r.size }).max(1) as f64;
            let xval = |r: &ScalingRow| xval(r).log2();
            let all: Vec<&ScalingRow> = report
                .rows
                .iter()
                .filter(|r| r.study == study && r.method != "direct")
                .collect();
            let (x0, x1) = all
                .iter()
                .map(|r| xval(r))
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), x| (a.min(x), b.max(x)));
            let xr = if x0.is_finite() {
                (x0.floor() - 0.5)..(x1.ceil() + 0.5)
            } else {
                0.0..1.0
            };
            let n_labels = (xr.end - xr.start).round() as usize + 1;
            let ymax = rows.iter().filter_map(|r| r.iterations).max().unwrap_or(1).max(1) as f64 * 1.15;
            let title = if study == "strong" {
                let size = all.first().map(|r| r.size).unwrap_or(0);
                format!("strong: size {size}, iterations vs subdomains")
            } else {
                "weak: size grows with subdomains".to_string()
            };
            let mut chart = ChartBuilder::on(panel)
                .caption(title, ("sans-serif", 20))
                .margin(15)
                .x_label_area_size(45)
                .y_label_area_size(60)
                .build_cartesian_2d(xr, 0.0..ymax)
                .map_err(plot_err)?;
            chart
                .configure_mesh()
                .light_line_style(RGBColor(238, 238, 238))
                .x_labels(n_labels)
                .x_desc(if study == "strong" {
                    "subdomains (log scale)"
                } else {
                    "size (log scale)"
                })
                .y_desc("iterations")
                .x_label_formatter(&|x| {
                    if (x - x.round()).abs() < 1e-6 {
                        format!("{:.0}", 2f64.powf(x.round()))
                    } else {
                        String::new()
                    }
                })
                .y_label_formatter(&|y| format!("{y:.0}"))
                .draw()
                .map_err(plot_err)?;
            let mut methods: Vec<&str> = Vec::new();
            for r in &all {
                if !methods.contains(&r.method.as_str()) {
                    methods.push(&r.method);
                }
            }
            for (i, m) in methods.iter().enumerate() {
                let color = COLORS[i % COLORS.len()];
                let mut pts: Vec<(f64, f64)> = rows
                    .iter()
                    .filter(|r| r.method == *m)
                    .map(|r| (xval(r), r.iterations.unwrap_or(0) as f64))
                    .collect();
                pts.sort_by(|a, b| a.0.partial_cmp(&b.0).unwrap());
                let label = if pts.is_empty() {
                    format!("{m} (every run skipped)")
                } else {
                    m.to_string()
                };
                chart
                    .draw_series(LineSeries::new(pts.clone(), color.stroke_width(2)))
                    .map_err(plot_err)?
                    .label(label)
                    .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2)));
                chart
                    .draw_series(pts.iter().map(|&p| Circle::new(p, 4, color.filled())))
                    .map_err(plot_err)?;
            }
            chart
                .configure_series_labels()
                .position(SeriesLabelPosition::UpperLeft)
                .background_style(WHITE.mix(0.85))
                .border_style(BLACK)
                .draw()
                .map_err(plot_err)?;
        }
        root.present().map_err(plot_err)?;
    }
    Ok(buf)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The partition text sums the local mechanisms it could count and
    /// names the subdomains it could not, rather than counting them as 0.
    #[test]
    fn partition_text_names_uncounted_mechanisms() {
        let params = nsdd::generate::TowerParams {
            nx: 6,
            ny: 6,
            nz: 6,
            ea_cable: 1e4,
            unilateral: false,
            ..Default::default()
        };
        let scene = nsdd::generate::tower(&params);
        let mut report = partition_report(&scene, 16).unwrap();
        let counted: usize = report.subdomains.iter().filter_map(|i| i.mechanisms).sum();
        assert!(counted > 0, "a 6³ tower cut in 16 has local mechanisms");
        let text = report.text();
        assert!(text.contains(&format!("local mechanisms    {counted} in ")), "{text}");
        assert!(!text.contains("not counted"), "{text}");
        // One subdomain whose count failed.
        let lost = report
            .subdomains
            .iter()
            .position(|i| i.mechanisms.is_some_and(|m| m > 0))
            .unwrap();
        let m = report.subdomains[lost].mechanisms.take().unwrap();
        let text = report.text();
        assert!(
            text.contains(&format!("local mechanisms    {} in ", counted - m)),
            "{text}"
        );
        assert!(text.contains("not counted in 1 subdomain"), "{text}");
    }

    #[test]
    fn samples_are_geometric_and_end_at_n() {
        assert_eq!(geometric_samples(0, 10), Vec::<usize>::new());
        assert_eq!(geometric_samples(1, 10), vec![1]);
        assert_eq!(geometric_samples(5, 24), vec![1, 2, 3, 4, 5]);
        let s = geometric_samples(10_000, 24);
        assert!(s.len() <= 24, "{s:?}");
        assert_eq!(*s.last().unwrap(), 10_000);
        assert!(s.windows(2).all(|w| w[0] < w[1]));
    }

    /// `(x, y, font size, text, fill)` of every `<text>` of a plotters SVG.
    fn svg_texts(svg: &str) -> Vec<(f64, f64, f64, String, String)> {
        let attr = |tag: &str, name: &str| -> String {
            let key = format!(" {name}=\"");
            tag.find(&key)
                .map(|i| {
                    let rest = &tag[i + key.len()..];
                    rest[..rest.find('"').unwrap()].to_string()
                })
                .unwrap_or_default()
        };
        svg.split("<text")
            .skip(1)
            .map(|t| {
                let (tag, rest) = t.split_once('>').unwrap();
                let body = rest.split("</text>").next().unwrap().trim().to_string();
                let num = |n: &str| attr(tag, n).parse::<f64>().unwrap_or(f64::NAN);
                (num("x"), num("y"), num("font-size"), body, attr(tag, "fill"))
            })
            .collect()
    }

    fn circles(svg: &str) -> Vec<(f64, f64)> {
        svg.split("<circle")
            .skip(1)
            .map(|c| {
                let get = |n: &str| {
                    let key = format!(" {n}=\"");
                    let i = c.find(&key).unwrap() + key.len();
                    c[i..i + c[i..].find('"').unwrap()].parse::<f64>().unwrap()
                };
                (get("cx"), get("cy"))
            })
            .collect()
    }

    fn row(method: &str, tolerance: Option<f64>, err: f64, seconds: f64) -> AccuracyRow {
        AccuracyRow {
            method: method.into(),
            tolerance,
            error_u: err,
            error_t: err,
            slack_mismatch: 0,
            iterations: 1,
            seconds,
            setup_s: 0.0,
            solve_s: seconds,
            converged: true,
        }
    }

    /// Issue #20 item 8: the legend box covered the loosest point of the
    /// slower curve (top right). The legend is now beside the plot, every
    /// dot is labelled with its tolerance when there is room, and no label
    /// covers a dot or another label - also where runs crowd together.
    #[test]
    fn accuracy_plot_labels_tolerances_and_keeps_the_legend_off_the_data() {
        let tols = [1e-2, 1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10];
        let mut rows = vec![row("direct", None, 0.0, 0.05)];
        for (k, &t) in tols.iter().enumerate() {
            // multilevel: slow, its loosest run at the top right.
            rows.push(row("multilevel", Some(t), t * 1e-1, 3.0 + 0.3 * k as f64));
        }
        for (k, &t) in tols.iter().enumerate() {
            // cg: the last four runs nearly on top of each other.
            let s = if k < 5 {
                0.2 + 0.02 * k as f64
            } else {
                0.3 + 0.001 * k as f64
            };
            let e = if k < 5 {
                t * 1e-2
            } else {
                1e-11 * (1.0 + 0.01 * k as f64)
            };
            rows.push(row("cg", Some(t), e, s));
        }
        let report = AccuracyReport {
            scene: "synthetic".into(),
            subdomains: 4,
            rows,
            histories: Vec::new(),
            notes: Vec::new(),
        };
        let svg = accuracy_svg(&report).unwrap();
        let texts = svg_texts(&svg);
        // The legend entries are right of the 780-px plot column.
        for name in ["multilevel", "cg", "direct (reference)"] {
            let t = texts
                .iter()
                .find(|t| t.3 == name)
                .unwrap_or_else(|| panic!("no legend entry {name}"));
            assert!(t.0 > 780.0, "legend entry {name} at x = {}", t.0);
        }
        // Tolerance labels: coloured like their curve, one per well-spaced
        // dot (every multilevel run and the first five cg runs).
        let labels: Vec<_> = texts
            .iter()
            .filter(|t| t.3.starts_with("1e-") && t.4 != "#000000")
            .collect();
        for t in &tols {
            let l = format!("{t:e}");
            let n = labels.iter().filter(|x| x.3 == l).count();
            let want = if *t >= 1e-6 { 2 } else { 1 };
            assert!(n >= want, "label {l}: {n} of {want}");
        }
        // Boxes of the labels (text drawn from its top left; width at most
        // 0.6 em per character) against each other and against the dots.
        let boxes: Vec<[f64; 4]> = labels
            .iter()
            .map(|t| [t.0, t.1, t.0 + 0.6 * t.2 * t.3.len() as f64, t.1 + t.2])
            .collect();
        for (i, a) in boxes.iter().enumerate() {
            for b in &boxes[i + 1..] {
                let overlap = a[0] < b[2] && b[0] < a[2] && a[1] < b[3] && b[1] < a[3];
                assert!(!overlap, "labels overlap: {a:?} {b:?}");
            }
            for &(cx, cy) in &circles(&svg) {
                let inside = cx + 4.0 > a[0] && cx - 4.0 < a[2] && cy + 4.0 > a[1] && cy - 4.0 < a[3];
                assert!(!inside, "label {a:?} covers the dot at ({cx}, {cy})");
            }
        }
    }

    #[test]
    fn rel_err_of_zero_reference_is_absolute() {
        assert_eq!(rel_err(&[3.0, 4.0], &[0.0, 0.0]), 5.0);
        assert!((rel_err(&[1.0, 1.0], &[1.0, 0.0]) - 1.0).abs() < 1e-15);
    }
}
