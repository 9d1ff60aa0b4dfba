//! The `nsdd` command line: solve a scene, generate scenes, inspect a
//! partition, and run the accuracy and scaling studies. The studies and
//! reports live in `report` (a module of this binary, with plotters); this
//! file parses arguments, draws progress bars (only when stderr is a
//! terminal) and writes files. Needs the `cli` feature (default).

mod report;

use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::{Args, Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};

use nsdd::comm::Placement;
use nsdd::error::{Error, Result};
use nsdd::generate;
use nsdd::model::Model;
use nsdd::scene::{
    AdaptiveEdges, AdaptiveThreshold, InterfaceScaling, MacroDegree, Method, OrderingChoice, Partitioner,
    Preconditioner, Scene, SearchDirection,
};
use nsdd::solve::{solve_in, SolveOptions};
use nsdd::vtk;
use report::{AccuracyOptions, Event, ScalingOptions};

#[derive(Parser)]
#[command(
    name = "nsdd",
    version,
    about = "Static equilibrium of trusses and tensegrity grids with slack cables: direct and multilevel domain decomposition solvers",
    after_help = "Exit status: 0 success; 2 bad input (parse, i/o, invalid field); 3 structure or decomposition the method cannot solve (mechanism, indefinite subdomain, method not applicable); 4 divergence or numerical failure; 5 solved but not converged to the tolerance; 1 other."
)]
struct Cli {
    /// Number of worker threads (rayon global pool; default: all cores)
    #[arg(long, global = true, value_name = "N", value_parser = parse_count, allow_hyphen_values = true)]
    threads: Option<usize>,
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Solve a scene (TOML or JSON); flags override the scene's [solver]
    Solve(SolveArgs),
    /// Generate a scene: nsdd gen KIND key=value ... --out scene.toml
    #[command(after_help = gen_help())]
    Gen(GenArgs),
    /// Partition report: interface quality and singular subdomains
    Partition(PartitionArgs),
    /// Error against time to accuracy of every method, against the direct solution
    Accuracy(AccuracyArgs),
    /// Iterations and time against subdomains (strong) and size (weak)
    Scaling(ScalingArgs),
    /// Cost profiles: direct solver phases and memory, DD iteration vs substitution bound
    Bench(BenchArgs),
}

#[derive(Clone, Copy, ValueEnum)]
enum MethodArg {
    Direct,
    Monolevel,
    Multilevel,
    /// Interface conjugate gradient with the coarse step (with unilateral cables: active set around it)
    Cg,
}

impl From<MethodArg> for Method {
    fn from(m: MethodArg) -> Method {
        match m {
            MethodArg::Direct => Method::Direct,
            MethodArg::Monolevel => Method::Monolevel,
            MethodArg::Multilevel => Method::Multilevel,
            MethodArg::Cg => Method::Cg,
        }
    }
}

/// The iterative methods, for `accuracy --methods`.
#[derive(Clone, Copy, ValueEnum)]
enum IterativeArg {
    Monolevel,
    Multilevel,
    Cg,
}

impl From<IterativeArg> for Method {
    fn from(m: IterativeArg) -> Method {
        match m {
            IterativeArg::Monolevel => Method::Monolevel,
            IterativeArg::Multilevel => Method::Multilevel,
            IterativeArg::Cg => Method::Cg,
        }
    }
}

fn parse_preconditioner(s: &str) -> std::result::Result<Preconditioner, String> {
    s.parse()
}

fn parse_interface_scaling(s: &str) -> std::result::Result<InterfaceScaling, String> {
    s.parse()
}

/// Parsed only: the range is checked with the other settings, whose error
/// names `solver.adaptive_threshold`.
fn parse_adaptive(s: &str) -> std::result::Result<AdaptiveThreshold, String> {
    s.parse()
}

fn parse_adaptive_edges(s: &str) -> std::result::Result<AdaptiveEdges, String> {
    s.parse()
}

fn parse_macro_degree(s: &str) -> std::result::Result<MacroDegree, String> {
    s.parse()
}

fn parse_d(s: &str) -> std::result::Result<SearchDirection, String> {
    let d: SearchDirection = s.parse()?;
    match d {
        SearchDirection::Value(v) if !(v > 0.0 && v.is_finite()) => {
            Err(format!("must be a positive number or \"auto\", got {s}"))
        }
        _ => Ok(d),
    }
}

// Numeric flags take `allow_hyphen_values` so that `--tolerance -1e-6`
// reaches these checks (clap would otherwise read `-1e-6` as a flag), and
// the message names the flag.

/// A positive finite number (tolerances).
fn parse_positive(s: &str) -> std::result::Result<f64, String> {
    match s.parse::<f64>() {
        Ok(v) if v > 0.0 && v.is_finite() => Ok(v),
        _ => Err(format!("must be a positive number, got {s}")),
    }
}

/// A whole number of at least 1 (counts, sizes, limits).
fn parse_count(s: &str) -> std::result::Result<usize, String> {
    match s.parse::<usize>() {
        Ok(v) if v >= 1 => Ok(v),
        _ => Err(format!("must be a whole number of at least 1, got {s}")),
    }
}

/// A subdomain count: a whole number, or `auto` (= 0: chosen from the size
/// and the thread count).
fn parse_subdomains(s: &str) -> std::result::Result<usize, String> {
    if s == "auto" {
        return Ok(0);
    }
    s.parse::<usize>()
        .map_err(|_| format!("must be a whole number (0 = automatic) or \"auto\", got {s}"))
}

/// A whole number of at least 0.
fn parse_non_negative(s: &str) -> std::result::Result<usize, String> {
    s.parse::<usize>()
        .map_err(|_| format!("must be a whole number of at least 0, got {s}"))
}

#[derive(Args)]
struct SolveArgs {
    /// Scene file (.toml, or .json)
    scene: PathBuf,
    /// Solution method
    #[arg(long, value_enum)]
    method: Option<MethodArg>,
    /// Number of subdomains (iterative methods); auto or 0: chosen from the size and the threads (the default unless the scene sets it)
    #[arg(long, value_name = "N|auto", value_parser = parse_subdomains, allow_hyphen_values = true)]
    subdomains: Option<usize>,
    /// Automatic partitioner: bisection or metis (default: the scene's [solver] partitioner)
    #[arg(long, value_name = "P")]
    partitioner: Option<Partitioner>,
    /// Fill-reducing ordering of the sparse factorizations: auto (AMD, and nested dissection where AMD fills much), amd or nested_dissection (default: the scene's [solver] ordering)
    #[arg(long, value_name = "O")]
    ordering: Option<OrderingChoice>,
    /// Relative tolerance on the convergence indicator
    #[arg(long, value_name = "T", value_parser = parse_positive, allow_hyphen_values = true)]
    tolerance: Option<f64>,
    /// Iteration limit
    #[arg(long, value_name = "K", value_parser = parse_count, allow_hyphen_values = true)]
    max_iterations: Option<usize>,
    /// Search direction d of the local stage: a positive number or "auto"
    #[arg(long, value_name = "D|auto", value_parser = parse_d, allow_hyphen_values = true)]
    search_direction: Option<SearchDirection>,
    /// Preconditioner of cg: dirichlet (default: interior solves, fewer iterations) or lumped
    #[arg(long, value_name = "P", value_parser = parse_preconditioner)]
    preconditioner: Option<Preconditioner>,
    /// Weights of cg's preconditioner across interfaces: economic_deluxe (default: deluxe, the blocks of large faces from the interior near them), deluxe (every block exact), contrast, multiplicity, stiffness or none
    #[arg(long, value_name = "S", value_parser = parse_interface_scaling)]
    interface_scaling: Option<InterfaceScaling>,
    /// Adaptive macro space of cg: eigenvalue threshold above which a face's jump modes become macro columns; 0: none; auto (the default): 5 where the elements' EA/L span 100x or more (stiff bars on soft cables), else none
    #[arg(long, value_name = "THETA|auto", value_parser = parse_adaptive, allow_hyphen_values = true)]
    adaptive_threshold: Option<AdaptiveThreshold>,
    /// With the adaptive macro space, constraints on the edges too (dofs shared by three or more subdomains): 2-11x fewer cg iterations on 3D towers with stiff bars on soft cables; auto (the default): on where the elements' EA/L span 100x or more, as the adaptive space itself. `--adaptive-edges` alone means true
    #[arg(long, value_name = "true|false|auto", num_args = 0..=1, default_missing_value = "true", value_parser = parse_adaptive_edges)]
    adaptive_edges: Option<AdaptiveEdges>,
    /// Degree of the polynomial fields in each interface's macro basis (multilevel and cg): 1 (rigid motions and in-plane extensions) to 6 (2 to 6 add the quadratic, cubic, ... fields per component: 8-16 cg iterations instead of 15-33 on plates); auto (the default): for cg on a flat structure (plates, double-layer grids) without the adaptive space, 5 on the interfaces of 80 nodes or more, 3 on those of 20 to 79 and 2 on those of 16 to 19, else 1
    #[arg(long, value_name = "1-6|auto", value_parser = parse_macro_degree)]
    macro_degree: Option<MacroDegree>,
    /// Write the result JSON here (also when not converged: its `status` says why; not after an error or divergence)
    #[arg(long, value_name = "FILE")]
    out: Option<PathBuf>,
    /// Write a ParaView .vtu here (with a load path: also one .vtu per step and a .pvd series)
    #[arg(long, value_name = "FILE")]
    vtk: Option<PathBuf>,
}

#[derive(Args)]
struct GenArgs {
    /// Generator kind (see below)
    kind: String,
    /// Parameters as key=value
    #[arg(value_name = "KEY=VALUE")]
    params: Vec<String>,
    /// Output scene file: .json writes JSON, anything else TOML (default: TOML on stdout)
    #[arg(long, value_name = "FILE")]
    out: Option<PathBuf>,
}

#[derive(Args)]
struct PartitionArgs {
    /// Scene file
    scene: PathBuf,
    /// Number of subdomains, or auto (default: the scene's [solver] subdomains, automatic when unset)
    #[arg(long, value_name = "N|auto", value_parser = parse_subdomains, allow_hyphen_values = true)]
    subdomains: Option<usize>,
    /// Automatic partitioner: bisection or metis (default: the scene's [solver] partitioner)
    #[arg(long, value_name = "P")]
    partitioner: Option<Partitioner>,
    /// Print the report as JSON
    #[arg(long)]
    json: bool,
}

#[derive(Args)]
struct AccuracyArgs {
    /// Scene file
    scene: PathBuf,
    /// Output directory (accuracy.csv, accuracy.svg, history-<method>.csv/.svg)
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
    /// Subdomains of the iterative methods, or auto (default: the scene's, automatic when unset, 4 when it asks for 1)
    #[arg(long, value_name = "N|auto", value_parser = parse_subdomains, allow_hyphen_values = true)]
    subdomains: Option<usize>,
    /// Tolerances to sweep, comma separated
    #[arg(
        long,
        value_name = "T,...",
        value_delimiter = ',',
        default_value = "1e-2,1e-3,1e-4,1e-5,1e-6,1e-7,1e-8,1e-9,1e-10",
        value_parser = parse_positive,
        allow_hyphen_values = true
    )]
    tolerances: Vec<f64>,
    /// Iterative methods to run, comma separated (default: all; the direct
    /// solve always runs as the reference)
    #[arg(long, value_name = "M,...", value_delimiter = ',')]
    methods: Vec<IterativeArg>,
    /// Iteration limit (default: the scene's)
    #[arg(long, value_name = "K", value_parser = parse_count, allow_hyphen_values = true)]
    max_iterations: Option<usize>,
    /// Search direction d: a positive number or "auto" (default: the scene's)
    #[arg(long, value_name = "D|auto", value_parser = parse_d, allow_hyphen_values = true)]
    search_direction: Option<SearchDirection>,
    /// Number of true-error samples along each convergence history (0: none).
    /// Each sample re-runs setup + the first k iterations (k geometric).
    #[arg(long, value_name = "N", default_value_t = 24, value_parser = parse_non_negative, allow_hyphen_values = true)]
    samples: usize,
}

#[derive(Args)]
struct BenchArgs {
    /// What to profile: `direct` (assembly, ordering, factorization, solve,
    /// nnz(L), peak memory) or `iteration` (DD per-iteration time against one
    /// substitution with every subdomain factor)
    #[arg(value_parser = ["direct", "iteration"])]
    what: String,
    /// Scene file to profile (any scene) instead of the generated grids of
    /// --sizes (size is then shown as 0)
    scene: Option<PathBuf>,
    /// Print the direct profile of SCENE as one JSON object (nnz(L), the
    /// ordering, phase timings, peak memory) instead of the table
    #[arg(long)]
    json: bool,
    /// With `direct SCENE`: stop after the ordering and symbolic analysis
    /// and report nnz(L) and the memory the factor needs, without factoring
    /// (for structures whose factor may not fit)
    #[arg(long)]
    analyse: bool,
    /// Grid sizes (nx = ny) of the generated double-layer grids, increasing
    #[arg(long, value_delimiter = ',', default_value = "40,130", value_parser = parse_count, allow_hyphen_values = true)]
    sizes: Vec<usize>,
    /// Subdomain counts (iteration profile)
    #[arg(long, value_delimiter = ',', default_value = "4,16", value_parser = parse_count, allow_hyphen_values = true)]
    subdomains: Vec<usize>,
    /// Iterations timed per measurement (iteration profile); fewer when the
    /// solve reaches round-off first, as the last column ("timed its") shows
    #[arg(long, default_value_t = 20, value_parser = parse_count, allow_hyphen_values = true)]
    iterations: usize,
    /// Automatic partitioner of the iteration profile: bisection or metis
    #[arg(long, value_name = "P")]
    partitioner: Option<Partitioner>,
    /// Fill-reducing ordering of every factorization: auto, amd or nested_dissection (default: the scene's [solver] ordering)
    #[arg(long, value_name = "O")]
    ordering: Option<OrderingChoice>,
    /// Unilateral cables (nonsmooth) instead of the linear grid
    #[arg(long)]
    nonsmooth: bool,
    /// Method of the iteration profile: multilevel (the stationary
    /// iteration; bound: one substitution with every subdomain factor) or
    /// cg (the interface CG with the scene's preconditioner; bound: one
    /// substitution with every subdomain factor and every interior factor)
    #[arg(long, value_enum, default_value = "multilevel")]
    method: IterativeArg,
    /// Write the rows as JSON lines to this file as well
    #[arg(long)]
    out: Option<PathBuf>,
}

#[derive(Args)]
struct ScalingArgs {
    /// Generator kind of the scenes
    #[arg(long, default_value = "grid")]
    kind: String,
    /// Sizes (nx = ny = size; nz for a tower), comma separated
    #[arg(long, value_name = "N,...", value_delimiter = ',', default_value = "8,16,32", value_parser = parse_count, allow_hyphen_values = true)]
    sizes: Vec<usize>,
    /// Subdomain counts, comma separated; the weak study pairs sizes[i] with subdomains[i]
    #[arg(long, value_name = "N,...", value_delimiter = ',', default_value = "4,16,64", value_parser = parse_count, allow_hyphen_values = true)]
    subdomains: Vec<usize>,
    /// Size of the strong-scaling study (default: the largest size)
    #[arg(long, value_name = "SIZE", value_parser = parse_count, allow_hyphen_values = true)]
    strong_size: Option<usize>,
    /// Tolerance of the iterative methods
    #[arg(long, value_name = "T", default_value = "1e-6", value_parser = parse_positive, allow_hyphen_values = true)]
    tolerance: f64,
    /// Iteration limit
    #[arg(long, value_name = "K", default_value_t = 20000, value_parser = parse_count, allow_hyphen_values = true)]
    max_iterations: usize,
    /// Search direction d: a positive number or "auto"
    #[arg(long, value_name = "D|auto", value_parser = parse_d, default_value = "auto", allow_hyphen_values = true)]
    search_direction: SearchDirection,
    /// Extra generator parameter key=value (repeatable)
    #[arg(long = "param", value_name = "KEY=VALUE")]
    params: Vec<String>,
    /// Output directory (scaling.csv, scaling.svg)
    #[arg(long, value_name = "DIR")]
    out: PathBuf,
}

fn gen_help() -> String {
    let mut s = String::from("Kinds and parameters (defaults in parentheses; every kind also takes name=...):\n");
    for kind in generate::KINDS {
        let defaults = match *kind {
            "grid" => serde_json::to_value(generate::GridParams::default()),
            "tensegrity" => serde_json::to_value(generate::TensegrityParams::default()),
            _ => serde_json::to_value(generate::TowerParams::default()),
        }
        .unwrap_or_default();
        let keys = generate::parameters(kind).unwrap_or(&[]);
        let list: Vec<String> = keys
            .iter()
            .map(|k| match defaults.get(*k) {
                Some(v) => format!("{k} ({v})"),
                None => k.to_string(),
            })
            .collect();
        s.push_str(&format!("  {kind}: {}\n", list.join(", ")));
    }
    s.push_str("\nExample: nsdd gen grid nx=8 ny=8 t0=0.1 --out grid.toml");
    s
}

/// Under `mpirun` (an MPI launcher's environment) with the `mpi` feature:
/// MPI started with `MPI_THREAD_FUNNELED` (only this thread calls MPI) and
/// the placement over `MPI_COMM_WORLD`; otherwise every subdomain in this
/// process. The universe finalises MPI when dropped, at the end of `main`.
#[cfg(feature = "mpi")]
fn start_placement() -> std::result::Result<(Placement, Option<mpi::environment::Universe>), String> {
    if !launched_by_mpi() {
        return Ok((Placement::Process, None));
    }
    let (universe, level) = mpi::initialize_with_threading(mpi::Threading::Funneled)
        .ok_or_else(|| "MPI was already initialised".to_string())?;
    if level < mpi::Threading::Funneled {
        return Err(format!("MPI offers only {level:?} threading; nsdd needs Funneled"));
    }
    Ok((Placement::Mpi(nsdd::comm::mpi::MpiComm::world()), Some(universe)))
}

/// Whether an MPI launcher (OpenMPI, MPICH/Hydra, PMIx) started this process.
fn launched_by_mpi() -> bool {
    ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK", "MPI_LOCALNRANKS"]
        .iter()
        .any(|v| std::env::var_os(v).is_some())
}

/// Without the `mpi` feature, several ranks would each solve the whole
/// problem and write the same files: refused with the way out.
#[cfg(not(feature = "mpi"))]
fn start_placement() -> std::result::Result<(Placement, Option<()>), String> {
    let ranks = ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE"]
        .iter()
        .find_map(|v| std::env::var(v).ok()?.parse::<usize>().ok());
    if launched_by_mpi() && ranks.is_some_and(|n| n > 1) {
        return Err(
            "this nsdd was built without MPI: under mpirun every rank would solve the whole \
                    problem and write the same files; rebuild with `cargo build --release --features mpi`"
                .into(),
        );
    }
    Ok((Placement::Process, None))
}

/// Whether this process prints (rank 0, or the only process).
static ROOT: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(true);

fn is_root() -> bool {
    ROOT.load(std::sync::atomic::Ordering::Relaxed)
}

fn main() -> ExitCode {
    // A reader that goes away early (`nsdd gen ... | head`) ends the
    // process quietly, as it does other command-line tools, instead of a
    // panic on the failed write. Not under an MPI launcher, whose
    // transports may count on SIGPIPE being ignored.
    #[cfg(unix)]
    if !launched_by_mpi() {
        // SAFETY: restores one signal's default disposition at start-up,
        // before any other thread exists.
        unsafe {
            libc::signal(libc::SIGPIPE, libc::SIG_DFL);
        }
    }
    let cli = Cli::parse();
    // faer's dense kernels (the coarse operator's products, the macro
    // bases' and deluxe faces' eigensolves) split their work by the number
    // of threads by default, and so round differently with 1 and 2
    // threads; CG amplifies that (72 against 82 iterations on the 130²
    // plate). They run inside the per-subdomain parallel loops anyway, so
    // the command line keeps them sequential: its results do not depend on
    // the thread count, at the same speed (BENCHMARKS.md). The direct
    // solver passes its own parallelism to its factorization.
    faer::set_global_parallelism(faer::Par::Seq);
    let (placement, _universe) = match start_placement() {
        Ok(p) => p,
        Err(e) => {
            eprintln!("error: {e}");
            return ExitCode::from(1);
        }
    };
    ROOT.store(placement.is_root(), std::sync::atomic::Ordering::Relaxed);
    if let Some(n) = cli.threads {
        if let Err(e) = rayon::ThreadPoolBuilder::new().num_threads(n).build_global() {
            eprintln!("error: cannot start {n} threads: {e}");
            return ExitCode::from(1);
        }
    }
    let outcome = match cli.command {
        Command::Solve(a) => cmd_solve(a, placement),
        Command::Gen(a) => cmd_gen(a),
        Command::Partition(a) => cmd_partition(a),
        Command::Accuracy(a) => cmd_accuracy(a),
        Command::Scaling(a) => cmd_scaling(a),
        Command::Bench(a) => cmd_bench(a),
    };
    match outcome {
        Ok(code) => ExitCode::from(code as u8),
        Err(e) => {
            if is_root() {
                eprintln!("error: {e}");
            }
            ExitCode::from(report::exit_code(&e) as u8)
        }
    }
}

// ---------------------------------------------------------------------------
// Progress (only on a terminal)
// ---------------------------------------------------------------------------

fn on_terminal() -> bool {
    std::io::stderr().is_terminal()
}

/// Fraction of the way from indicator 1 down to `tol` (log scale).
fn progress_fraction(indicator: f64, tol: f64) -> f64 {
    if indicator.is_nan() || indicator <= 0.0 {
        return 1.0;
    }
    if indicator >= 1.0 || !(tol > 0.0 && tol < 1.0) {
        return 0.0;
    }
    (indicator.ln() / tol.ln()).clamp(0.0, 1.0)
}

/// Progress bar of one solve: how far the indicator is towards the tolerance.
struct SolveBar {
    bar: ProgressBar,
    tol: f64,
    last: Instant,
}

impl SolveBar {
    fn new(tol: f64) -> Option<SolveBar> {
        if !on_terminal() {
            return None;
        }
        let bar = ProgressBar::new(1000);
        bar.set_style(
            ProgressStyle::with_template("{spinner} {elapsed:>4} {bar:25} {msg}")
                .expect("valid template")
                .progress_chars("=> "),
        );
        bar.set_message("setting up");
        bar.enable_steady_tick(Duration::from_millis(100));
        Some(SolveBar {
            bar,
            tol,
            last: Instant::now() - Duration::from_secs(1),
        })
    }

    fn update(&mut self, iteration: usize, indicator: f64) {
        if self.last.elapsed() < Duration::from_millis(50) {
            return;
        }
        self.last = Instant::now();
        self.bar
            .set_position((progress_fraction(indicator, self.tol) * 1000.0) as u64);
        self.bar.set_message(format!(
            "iter {iteration}  indicator {indicator:.2e} -> {:.0e}",
            self.tol
        ));
    }
}

/// Progress bar of a study: runs done, and the current run's iteration.
struct StudyBar {
    bar: ProgressBar,
    label: String,
    last: Instant,
}

impl StudyBar {
    fn new() -> Option<StudyBar> {
        if !on_terminal() {
            return None;
        }
        let bar = ProgressBar::new(1);
        bar.set_style(
            ProgressStyle::with_template("{spinner} {elapsed:>4} {bar:20} {pos}/{len} {msg}")
                .expect("valid template")
                .progress_chars("=> "),
        );
        bar.enable_steady_tick(Duration::from_millis(100));
        Some(StudyBar {
            bar,
            label: String::new(),
            last: Instant::now() - Duration::from_secs(1),
        })
    }

    fn event(&mut self, e: Event<'_>) {
        match e {
            Event::Start { label, run, runs } => {
                self.label = label.to_string();
                if runs > 0 {
                    self.bar.set_length(runs as u64);
                    self.bar.set_position(run as u64);
                }
                self.bar.set_message(self.label.clone());
            }
            Event::Iteration { iteration, indicator } => {
                if self.last.elapsed() < Duration::from_millis(50) {
                    return;
                }
                self.last = Instant::now();
                self.bar
                    .set_message(format!("{}: iter {iteration}, ind {indicator:.1e}", self.label));
            }
        }
    }
}

// ---------------------------------------------------------------------------
// Commands
// ---------------------------------------------------------------------------

fn write_file(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).map_err(|e| Error::Io(format!("{}: {e}", path.display())))
}

fn create_dir(dir: &Path) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::Io(format!("{}: {e}", dir.display())))
}

/// `nsdd solve`; under MPI every rank solves its block of subdomains and
/// rank 0 alone shows progress and writes the result.
fn cmd_solve(a: SolveArgs, placement: Placement) -> Result<i32> {
    let mut scene = Scene::load(&a.scene)?;
    if let Some(p) = a.partitioner {
        scene.solver.partitioner = p;
    }
    if let Some(o) = a.ordering {
        scene.solver.ordering = o;
    }
    let mut opts = SolveOptions::from_scene(&scene);
    if let Some(m) = a.method {
        opts.method = m.into();
    }
    if let Some(n) = a.subdomains {
        opts.subdomains = n;
    }
    if let Some(t) = a.tolerance {
        if !(t > 0.0 && t.is_finite()) {
            return Err(Error::input(
                "--tolerance",
                None,
                format!("must be a positive number, got {t}"),
            ));
        }
        opts.tolerance = t;
    }
    if let Some(k) = a.max_iterations {
        opts.max_iterations = k;
    }
    if let Some(d) = a.search_direction {
        opts.search_direction = d;
    }
    if let Some(p) = a.preconditioner {
        opts.preconditioner = p;
    }
    if let Some(s) = a.interface_scaling {
        opts.interface_scaling = s;
    }
    if let Some(t) = a.adaptive_threshold {
        opts.adaptive_threshold = t;
    }
    if let Some(e) = a.adaptive_edges {
        opts.adaptive_edges = e;
    }
    if let Some(m) = a.macro_degree {
        opts.macro_degree = m;
    }

    let root = placement.is_root();
    let mut bar = if opts.method == Method::Direct || !root {
        None
    } else {
        SolveBar::new(opts.tolerance)
    };
    let result = match bar.as_mut() {
        Some(b) => {
            let mut cb = |it: usize, ind: f64| b.update(it, ind);
            solve_in(&scene, &opts, Some(&mut cb), placement)
        }
        None => solve_in(&scene, &opts, None, placement),
    };
    if let Some(b) = bar {
        b.bar.finish_and_clear();
    }
    let result = result?;
    // Divergence keeps its exit status and writes nothing, as before the
    // result carried the diverged state.
    if let Some(e) = result.divergence() {
        return Err(e);
    }
    if !root {
        return Ok(if result.converged {
            0
        } else {
            report::EXIT_NOT_CONVERGED
        });
    }

    let mut wrote = Vec::new();
    if let Some(path) = &a.vtk {
        let model = Model::from_scene(&scene)?;
        let sub = (!result.element_subdomain.is_empty()).then_some(result.element_subdomain.as_slice());
        if !result.steps.is_empty() {
            let dir = path.parent().unwrap_or(Path::new(""));
            let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("result");
            let mut series = Vec::new();
            for (k, st) in result.steps.iter().enumerate() {
                let name = format!("{stem}-step{:03}.vtu", k + 1);
                vtk::write_vtu(dir.join(&name), &model, &st.displacements, &st.tensions, &st.slack, sub)?;
                series.push((st.load_factor, name));
            }
            let pvd = path.with_extension("pvd");
            vtk::write_pvd_series(&pvd, &series)?;
            wrote.push(format!("{} ({} steps)", pvd.display(), series.len()));
        }
        vtk::write_vtu(
            path,
            &model,
            &result.displacements,
            &result.tensions,
            &result.slack,
            sub,
        )?;
        wrote.push(path.display().to_string());
    }
    if let Some(path) = &a.out {
        write_file(path, &result.to_json())?;
        wrote.push(path.display().to_string());
    }
    print!("{}", report::summary(&scene, &result));
    for w in result
        .notes
        .iter()
        .filter(|n| n.starts_with(nsdd::solve::WARNING_PREFIX))
    {
        eprintln!("{w}");
    }
    for w in wrote {
        println!("wrote       {w}");
    }
    if !result.converged {
        eprintln!(
            "error: not converged: {}, tolerance {:e}{}{}",
            result.stop_summary(),
            opts.tolerance,
            result
                .stop_message
                .as_deref()
                .map(|m| format!(": {m}"))
                .unwrap_or_default(),
            if a.out.is_some() || a.vtk.is_some() {
                " (result written anyway)"
            } else {
                ""
            }
        );
        return Ok(report::EXIT_NOT_CONVERGED);
    }
    Ok(0)
}

fn cmd_gen(a: GenArgs) -> Result<i32> {
    let mut args = BTreeMap::new();
    for p in &a.params {
        let Some((k, v)) = p.split_once('=') else {
            return Err(Error::input(p.as_str(), None, "expected key=value"));
        };
        if args.insert(k.trim().to_string(), v.trim().to_string()).is_some() {
            return Err(Error::input(k.trim(), None, "given twice"));
        }
    }
    let scene = generate::by_name(&a.kind, &args)?;
    match &a.out {
        Some(path) => {
            let text = if path.extension().and_then(|e| e.to_str()) == Some("json") {
                scene.to_json_string()?
            } else {
                scene.to_toml_string()?
            };
            write_file(path, &text)?;
            println!(
                "wrote {} ({} nodes, {} elements)",
                path.display(),
                scene.nodes.x.len(),
                scene.elements.a.len()
            );
        }
        None => print!("{}", scene.to_toml_string()?),
    }
    Ok(0)
}

fn cmd_partition(a: PartitionArgs) -> Result<i32> {
    let mut scene = Scene::load(&a.scene)?;
    if let Some(p) = a.partitioner {
        scene.solver.partitioner = p;
    }
    let n = a.subdomains.unwrap_or(scene.solver.subdomains);
    let r = report::partition_report(&scene, n)?;
    if a.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&r).map_err(|e| Error::Io(e.to_string()))?
        );
    } else {
        print!("{}", r.text());
    }
    Ok(0)
}

fn cmd_accuracy(a: AccuracyArgs) -> Result<i32> {
    let scene = Scene::load(&a.scene)?;
    let mut opts = AccuracyOptions::from_scene(&scene);
    if let Some(n) = a.subdomains {
        opts.subdomains = n;
    }
    opts.tolerances = a.tolerances.clone();
    if !a.methods.is_empty() {
        opts.methods = a.methods.iter().map(|&m| m.into()).collect();
    }
    if let Some(k) = a.max_iterations {
        opts.max_iterations = k;
    }
    if let Some(d) = a.search_direction {
        opts.search_direction = d;
    }
    opts.history = a.samples > 0;
    opts.history_samples = a.samples;
    create_dir(&a.out)?;

    let mut bar = StudyBar::new();
    let rep = match bar.as_mut() {
        Some(b) => {
            let mut cb = |e: Event<'_>| b.event(e);
            report::accuracy(&scene, &opts, Some(&mut cb))
        }
        None => report::accuracy(&scene, &opts, None),
    };
    if let Some(b) = bar {
        b.bar.finish_and_clear();
    }
    let rep = rep?;
    let mut files = vec![a.out.join("accuracy.csv"), a.out.join("accuracy.svg")];
    write_file(&files[0], &rep.csv())?;
    write_file(&files[1], &report::accuracy_svg(&rep)?)?;
    for h in &rep.histories {
        let csv = a.out.join(format!("history-{}.csv", h.method));
        let svg = a.out.join(format!("history-{}.svg", h.method));
        write_file(&csv, &h.csv())?;
        write_file(&svg, &report::history_svg(h)?)?;
        files.extend([csv, svg]);
    }
    print!("{}", rep.text());
    for f in files {
        println!("wrote {}", f.display());
    }
    Ok(0)
}

fn cmd_scaling(a: ScalingArgs) -> Result<i32> {
    let mut params = BTreeMap::new();
    for p in &a.params {
        let Some((k, v)) = p.split_once('=') else {
            return Err(Error::input("--param", None, format!("expected key=value, got '{p}'")));
        };
        params.insert(k.trim().to_string(), v.trim().to_string());
    }
    let opts = ScalingOptions {
        kind: a.kind,
        sizes: a.sizes,
        subdomains: a.subdomains,
        tolerance: a.tolerance,
        max_iterations: a.max_iterations,
        search_direction: a.search_direction,
        strong_size: a.strong_size,
        params,
    };
    create_dir(&a.out)?;
    let mut bar = StudyBar::new();
    let rep = match bar.as_mut() {
        Some(b) => {
            let mut cb = |e: Event<'_>| b.event(e);
            report::scaling(&opts, Some(&mut cb))
        }
        None => report::scaling(&opts, None),
    };
    if let Some(b) = bar {
        b.bar.finish_and_clear();
    }
    let rep = rep?;
    let csv = a.out.join("scaling.csv");
    let svg = a.out.join("scaling.svg");
    write_file(&csv, &rep.csv())?;
    write_file(&svg, &report::scaling_svg(&rep)?)?;
    print!("{}", rep.text());
    println!("wrote {}", csv.display());
    println!("wrote {}", svg.display());
    Ok(0)
}

/// `nsdd bench direct SCENE [--json]`: the direct profile of one scene.
fn bench_direct_scene(a: &BenchArgs) -> Result<i32> {
    let path = a.scene.as_ref().expect("checked by the caller");
    let mut scene = Scene::load(path)?;
    if let Some(o) = a.ordering {
        scene.solver.ordering = o;
    }
    if a.analyse {
        return bench_direct_analysis(a, path, &scene);
    }
    let p = nsdd::bench::direct_profile(&scene)?;
    emit_profile(a, &serde_json::to_string(&p).expect("serializable"), || {
        let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
        println!("scene      {}", path.display());
        println!("dofs       {}", p.dofs);
        println!("nnz(K)     {}", p.nnz_k);
        println!("nnz(L)     {}", p.nnz_l);
        println!("ordering   {}", p.ordering);
        println!("assembly   {:.3} s", p.assembly_s);
        println!(
            "ordering   {:.3} s (ordering choice and symbolic analysis)",
            p.ordering_s
        );
        println!("factor     {:.3} s ({} threads)", p.factor_s, p.factor_threads);
        println!(
            "solve      {:.3} s ({} active-set steps; iterative refinement {:.3} s in {} corrections)",
            p.solve_s, p.active_set_steps, p.refinement_s, p.refinements
        );
        println!("K+L        {:.1} MiB", mib(p.matrix_and_factor_bytes));
        println!("peak       {:.1} MiB", p.peak_bytes.map_or(f64::NAN, mib));
    })
}

/// Prints a profile of one scene: its JSON with `--json`, else `table`;
/// the JSON goes to `--out` too.
fn emit_profile(a: &BenchArgs, json: &str, table: impl FnOnce()) -> Result<i32> {
    if a.json {
        println!("{json}");
    } else {
        table();
    }
    if let Some(out) = &a.out {
        std::fs::write(out, format!("{json}\n")).map_err(|e| Error::Io(format!("{}: {e}", out.display())))?;
    }
    Ok(0)
}

/// `nsdd bench direct SCENE --analyse [--json]`: what the direct solver
/// would need, from its symbolic analysis.
fn bench_direct_analysis(a: &BenchArgs, path: &std::path::Path, scene: &Scene) -> Result<i32> {
    let p = nsdd::bench::direct_analysis(scene)?;
    emit_profile(a, &serde_json::to_string(&p).expect("serializable"), || {
        let gib = |b: u64| b as f64 / (1024.0 * 1024.0 * 1024.0);
        println!("scene      {}", path.display());
        println!("dofs       {}", p.dofs);
        println!("nnz(K)     {}", p.nnz_k);
        println!("nnz(L)     {} (symbolic analysis, not factored)", p.nnz_l);
        println!("ordering   {}", p.ordering);
        println!("assembly   {:.3} s", p.assembly_s);
        println!(
            "analysis   {:.3} s (ordering choice and symbolic analysis)",
            p.analysis_s
        );
        println!(
            "K+L        {:.2} GiB (at least, for the factorization)",
            gib(p.matrix_and_factor_bytes)
        );
        println!(
            "peak       {:.2} GiB (this analysis)",
            p.peak_bytes.map_or(f64::NAN, gib)
        );
    })
}

fn cmd_bench(a: BenchArgs) -> Result<i32> {
    let mut rows: Vec<String> = Vec::new();
    let scene_of = |n: usize| {
        let mut scene = generate::grid(&generate::GridParams {
            nx: n,
            ny: n,
            unilateral: a.nonsmooth,
            t0: if a.nonsmooth { 0.1 } else { 0.0 },
            ..Default::default()
        });
        if let Some(o) = a.ordering {
            scene.solver.ordering = o;
        }
        scene
    };
    if a.what == "direct" && a.scene.is_some() {
        return bench_direct_scene(&a);
    }
    if a.analyse {
        return Err(Error::input(
            "--analyse",
            None,
            "applies to `nsdd bench direct SCENE` only".to_string(),
        ));
    }
    if a.what == "direct" {
        println!(
            "{:>6} {:>9} {:>11} {:>11} {:>9} {:>9} {:>9} {:>9} {:>6} {:>9} {:>10} {:>10}",
            "size",
            "dofs",
            "nnz(K)",
            "nnz(L)",
            "assembly",
            "ordering",
            "factor",
            "solve",
            "steps",
            "overhead",
            "K+L MiB",
            "peak MiB"
        );
        for &n in &a.sizes {
            let p = nsdd::bench::direct_profile(&scene_of(n))?;
            let mib = |b: u64| b as f64 / (1024.0 * 1024.0);
            println!(
                "{:>6} {:>9} {:>11} {:>11} {:>9.3} {:>9.3} {:>9.3} {:>9.3} {:>6} {:>8.1}% {:>10.1} {:>10.1}",
                n,
                p.dofs,
                p.nnz_k,
                p.nnz_l,
                p.assembly_s,
                p.ordering_s,
                p.factor_s,
                p.solve_s,
                p.active_set_steps,
                100.0 * p.overhead_ratio,
                mib(p.matrix_and_factor_bytes),
                p.peak_bytes.map_or(f64::NAN, mib)
            );
            rows.push(serde_json::to_string(&p).expect("serializable"));
        }
    } else {
        println!(
            "{:>6} {:>9} {:>5} {:>7} {:>7} {:>7} {:>8} {:>8} {:>8} {:>8} {:>8} {:>8} {:>7} {:>10} {:>11} {:>6} {:>9} {:>9}",
            "size",
            "dofs",
            "subs",
            "threads",
            "macro",
            "kernel",
            "part. s",
            "factor s",
            "coarse s",
            "d s",
            "setup s",
            "direct s",
            "setup/d",
            "iter ms",
            "substit. ms",
            "ratio",
            "coarse ms",
            "timed its"
        );
        let scenes: Vec<(usize, Scene)> = match &a.scene {
            Some(path) => vec![(0, Scene::load(path)?)],
            None => a.sizes.iter().map(|&n| (n, scene_of(n))).collect(),
        };
        for (n, mut scene) in scenes {
            if let Some(p) = a.partitioner {
                scene.solver.partitioner = p;
            }
            if let Some(o) = a.ordering {
                scene.solver.ordering = o;
            }
            // The direct solver's set-up on the same structure (assembly,
            // ordering, factorization), for the set-up ratio.
            let direct = nsdd::bench::direct_profile(&scene)?;
            let direct_s = direct.assembly_s + direct.ordering_s + direct.factor_s;
            for &s in &a.subdomains {
                let p = nsdd::bench::dd_profile(&scene, s, a.iterations, a.method.into())?;
                println!(
                    "{:>6} {:>9} {:>5} {:>7} {:>7} {:>7} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>8.3} {:>7.2} {:>10.3} {:>11.3} {:>6.2} {:>9.3} {:>9}",
                    n,
                    p.dofs,
                    p.subdomains,
                    p.threads,
                    p.macro_unknowns,
                    p.kernel_unknowns,
                    p.partition_s,
                    p.factor_s,
                    p.coarse_s,
                    p.search_direction_s,
                    p.setup_s,
                    direct_s,
                    p.setup_s / direct_s.max(1e-12),
                    1e3 * p.iteration_s,
                    1e3 * p.substitution_s,
                    p.ratio,
                    1e3 * p.coarse_solve_s,
                    p.iterations_timed
                );
                let mut row = serde_json::to_value(&p).expect("serializable");
                row["direct_setup_s"] = serde_json::json!(direct_s);
                rows.push(row.to_string());
            }
        }
    }
    if let Some(path) = &a.out {
        let mut text = rows.join("\n");
        text.push('\n');
        std::fs::write(path, text).map_err(|e| Error::Io(format!("{}: {e}", path.display())))?;
    }
    Ok(0)
}
