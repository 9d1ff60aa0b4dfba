//! Measurements behind `nsdd bench` and BENCHMARKS.md: where the direct
//! solver's time and memory go, and what one DD iteration costs against its
//! lower bound (one forward and backward substitution with every subdomain
//! factor). Figures are meant to be read as ratios within one run.

use crate::dd::{DdOptions, DdSolver};
use crate::direct::DirectSolver;
use crate::error::{Error, Result};
use crate::model::Model;
use crate::scene::{Method, Scene, SearchDirection, SolverSettings};
use crate::solve::decompose;
use serde::Serialize;
use std::time::Instant;

/// Peak resident memory of this process so far (Linux `VmHWM`), in bytes.
pub fn peak_memory_bytes() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kb * 1024)
}

/// Direct solver profile of one scene.
#[derive(Debug, Clone, Serialize)]
pub struct DirectProfile {
    pub dofs: usize,
    pub nnz_k: usize,
    pub nnz_l: usize,
    pub assembly_s: f64,
    pub ordering_s: f64,
    pub factor_s: f64,
    /// The solve, its iterative refinement included...
    pub solve_s: f64,
    /// ...which took this long, in this many corrections.
    pub refinement_s: f64,
    pub refinements: usize,
    pub active_set_steps: usize,
    /// `(assembly + ordering + solve) / factor`: the overhead outside the
    /// numeric factorization.
    pub overhead_ratio: f64,
    /// Bytes of `K` (lower CSC) plus `L` values.
    pub matrix_and_factor_bytes: u64,
    pub peak_bytes: Option<u64>,
    /// Fill-reducing ordering used (`"amd"` or `"nested_dissection"`).
    pub ordering: String,
    /// Threads of the numeric factorization.
    pub factor_threads: usize,
}

/// Bytes of `K` (lower CSC: values and row indices, column pointers) plus
/// the values of `L`, for `n` dofs.
fn matrix_and_factor_bytes(n: usize, nnz_k: usize, nnz_l: usize) -> u64 {
    (nnz_k * 16 + (n + 1) * 8 + nnz_l * 8) as u64
}

/// Factors and solves `scene` with the direct solver, timing each phase.
pub fn direct_profile(scene: &Scene) -> Result<DirectProfile> {
    let model = Model::from_scene(scene)?;
    let mut solver = DirectSolver::with_ordering(&model, scene.solver.ordering)?;
    let b = model.rhs(&model.load_cases[0]);
    let t = Instant::now();
    let eq = solver.solve(&model, &b)?;
    let solve_s = t.elapsed().as_secs_f64();
    let st = solver.stats().clone();
    let bytes = matrix_and_factor_bytes(st.n, st.nnz_k, st.nnz_l);
    Ok(DirectProfile {
        dofs: st.n,
        nnz_k: st.nnz_k,
        nnz_l: st.nnz_l,
        assembly_s: st.assembly_s,
        ordering_s: st.ordering_s,
        factor_s: st.factor_s,
        solve_s,
        refinement_s: st.refinement_s,
        refinements: st.refinements,
        active_set_steps: eq.iterations,
        overhead_ratio: (st.assembly_s + st.ordering_s + solve_s) / st.factor_s.max(1e-12),
        matrix_and_factor_bytes: bytes,
        peak_bytes: peak_memory_bytes(),
        ordering: st.ordering.map_or("none", |o| o.name()).to_string(),
        factor_threads: st.threads,
    })
}

/// What the direct solver would need for one scene, from its ordering and
/// symbolic analysis alone: `nnz(L)` is known before any numeric work, so
/// a structure whose factor does not fit in memory is reported without
/// trying to factor it.
#[derive(Debug, Clone, Serialize)]
pub struct DirectAnalysis {
    pub dofs: usize,
    pub nnz_k: usize,
    pub nnz_l: usize,
    /// Fill-reducing ordering the direct solver would use (`"amd"` or
    /// `"nested_dissection"`: with the scene's `ordering = "auto"`, as
    /// [`crate::factor::EliminationOrder::best_in_reference`] decides).
    pub ordering: String,
    /// Assembly of `K`.
    pub assembly_s: f64,
    /// Ordering choice and symbolic analysis.
    pub analysis_s: f64,
    /// Bytes of `K` (lower CSC) plus `L` values: a lower bound on what the
    /// factorization needs (its dense update blocks come on top).
    pub matrix_and_factor_bytes: u64,
    /// Peak resident memory of this process (the analysis only).
    pub peak_bytes: Option<u64>,
}

/// Assembles `K` and runs the direct solver's ordering choice and symbolic
/// analysis only (no numeric factorization).
pub fn direct_analysis(scene: &Scene) -> Result<DirectAnalysis> {
    let model = Model::from_scene(scene)?;
    let t = Instant::now();
    let k = crate::direct::assemble(&model)?;
    let assembly_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let (nnz_l, kind) = crate::factor::analyse(&k, scene.solver.ordering)
        .map_err(|e| crate::error::Error::Numerical(format!("{e:?}")))?;
    let analysis_s = t.elapsed().as_secs_f64();
    let nnz_k = k.compute_nnz();
    Ok(DirectAnalysis {
        dofs: model.n_free,
        nnz_k,
        nnz_l,
        ordering: kind.name().to_string(),
        assembly_s,
        analysis_s,
        matrix_and_factor_bytes: matrix_and_factor_bytes(model.n_free, nnz_k, nnz_l),
        peak_bytes: peak_memory_bytes(),
    })
}

/// Runs of each length [`dd_profile`]'s timing keeps the best of.
const TIMING_REPEATS: usize = 3;

/// Cost of the DD iteration on one scene and decomposition.
#[derive(Debug, Clone, Serialize)]
pub struct DdProfile {
    pub dofs: usize,
    pub subdomains: usize,
    pub threads: usize,
    pub macro_unknowns: usize,
    pub kernel_unknowns: usize,
    /// Partition and decomposition.
    pub partition_s: f64,
    /// Subdomain assembly and factorizations.
    pub factor_s: f64,
    /// Macro space and coarse problem.
    pub coarse_s: f64,
    /// Automatic `d` (30 power-iteration steps).
    pub search_direction_s: f64,
    /// Whole set-up: partition + factorizations + coarse problem + `d`.
    pub setup_s: f64,
    /// Time of one iteration (difference of two runs, divided by the
    /// iterations between them).
    pub iteration_s: f64,
    /// Iterations between the two timed runs: fewer than asked for when the
    /// longer run stopped early (at round-off).
    pub iterations_timed: usize,
    /// The method timed: `multilevel` or `cg`.
    pub method: &'static str,
    /// One forward and backward substitution with every subdomain factor,
    /// and for `cg` with every interior factor too (its preconditioner
    /// solves with them once per iteration), in parallel over subdomains
    /// as in the iteration.
    pub substitution_s: f64,
    /// The interior factors' part of `substitution_s` (0 for `multilevel`).
    pub interior_substitution_s: f64,
    /// `iteration_s / substitution_s` (target ≤ 1.5).
    pub ratio: f64,
    /// One solve of the coarse problem (on the right-hand side of the last
    /// iteration's), sequential as in the iteration: part of
    /// `iteration_s`. 0 without a coarse problem.
    pub coarse_solve_s: f64,
}

/// Measures per-iteration time of `method` (multilevel or cg) against the
/// triangular-solve bound.
pub fn dd_profile(scene: &Scene, subdomains: usize, iterations: usize, method: Method) -> Result<DdProfile> {
    if !matches!(method, Method::Multilevel | Method::Cg) {
        return Err(Error::input(
            "method",
            None,
            format!("the iteration profile times multilevel or cg, not {}", method.name()),
        ));
    }
    let model = Model::from_scene(scene)?;
    let t = Instant::now();
    let dec = decompose(&model, scene, subdomains)?;
    let partition_s = t.elapsed().as_secs_f64();
    let settings = SolverSettings {
        method,
        max_iterations: 1,
        search_direction: SearchDirection::Auto,
        ordering: scene.solver.ordering,
        interface_scaling: scene.solver.interface_scaling,
        adaptive_threshold: scene.solver.adaptive_threshold,
        ..SolverSettings::default()
    };
    let mut dd = DdSolver::new(&model, &dec, DdOptions::from_settings(&settings)?)?;
    let setup_s = t.elapsed().as_secs_f64();
    let f = model.load_cases[0].clone();
    let iterations = iterations.max(2);
    // The iterations a run did: CG may stop before `k` (at a tolerance of 0
    // it stalls at round-off), and dividing by the count asked for then
    // reported a fraction of the true cost (8.5 ms against 24.4 ms on the 130²
    // plate with 64 subdomains and `--iterations 300`).
    let run = |dd: &mut DdSolver, k: usize| -> Result<(f64, usize)> {
        dd.set_stopping(0.0, k);
        let t = Instant::now();
        let out = dd.solve(&f, false, None)?;
        Ok((t.elapsed().as_secs_f64(), out.iterations))
    };
    run(&mut dd, 1)?; // warm-up
                      // Best of a few runs each: the difference of two single runs of a small
                      // problem drowned in a busy machine's noise (it came out negative, and
                      // was reported as 0).
    let mut best = |k: usize| -> Result<(f64, usize)> {
        let (mut t, mut done) = (f64::INFINITY, 0);
        for _ in 0..TIMING_REPEATS {
            let (tr, d) = run(&mut dd, k)?;
            t = t.min(tr);
            done = d;
        }
        Ok((t, done))
    };
    let (t1, done1) = best(1)?;
    let (tk, donek) = best(1 + iterations)?;
    let iterations_timed = donek.saturating_sub(done1);
    if iterations_timed == 0 {
        return Err(Error::Numerical(format!(
            "the iteration profile timed no iteration: the solve stopped after {donek} of {} iterations",
            1 + iterations
        )));
    }
    let iteration_s = ((tk - t1) / iterations_timed as f64).max(0.0);
    // On a worker thread, as the iteration runs (`DdSolver::solve`): timed
    // from the caller's thread, the bound would carry the hand-over of its
    // work to the pool, which the iteration no longer pays.
    // Best of a few measurements too, as the iteration: a single one took
    // 11.5 to 29 ms on the 130² plate with 64 subdomains in three runs on
    // a shared machine, and the ratio with it.
    let (interior_substitution_s, substitution_s) = rayon::scope(|_| {
        let (mut interior, mut own) = (f64::INFINITY, f64::INFINITY);
        for _ in 0..TIMING_REPEATS {
            if method == Method::Cg {
                interior = interior.min(dd.interior_substitution_time(10));
            }
            own = own.min(dd.substitution_time(10));
        }
        let interior = if method == Method::Cg { interior } else { 0.0 };
        (interior, own + interior)
    });
    let coarse_solve_s = match dd.coarse_problem_mut() {
        Some(cp) => {
            let mut best = f64::INFINITY;
            for _ in 0..TIMING_REPEATS {
                let t = Instant::now();
                for _ in 0..10 {
                    cp.solve();
                }
                best = best.min(t.elapsed().as_secs_f64() / 10.0);
            }
            best
        }
        None => 0.0,
    };
    let ns = dd.n_subdomains();
    let stats = dd.stats();
    Ok(DdProfile {
        dofs: model.n_free,
        subdomains: ns,
        threads: rayon::current_num_threads(),
        macro_unknowns: stats.macro_unknowns,
        kernel_unknowns: stats.kernel_unknowns,
        partition_s,
        factor_s: stats.factor_s,
        coarse_s: stats.coarse_s,
        search_direction_s: stats.search_direction_s,
        setup_s,
        iteration_s,
        iterations_timed,
        method: method.name(),
        substitution_s,
        interior_substitution_s,
        ratio: iteration_s / substitution_s.max(1e-12),
        coarse_solve_s,
    })
}
