//! Solver benches: subdomain solves (single vs batched right-hand sides),
//! DD set-up and iterations, the direct solver, and the "pay only for what
//! is called" check.
//!
//! Sizes: double-layer grids `grid(nx = ny = n)` have about `6 n²` free
//! dofs: n = 37 → 8.2k, n = 41 → 10.1k, n = 52 → 16.2k (the subdomain size
//! of the 1e6-dof plate with 64 subdomains), n = 130 → 101k.
//!
//! Groups (ids are `case/parameter`):
//! - `subdomain_solve`: one subdomain's factor (the whole grid as one
//!   subdomain, `SubdomainOperator::new`), `k = 1` column through
//!   `solve_in_place` (the per-iteration path) and `k = 9, 27` columns
//!   through `solve_columns` (the set-up path). Throughput is in elements =
//!   columns, so criterion's elem/s is columns per second. Each twice:
//!   repeated on a cache-warm factor (`<n>dofs`), and after writing 64 MiB
//!   so the factor comes from memory (`<n>dofs-cold`), as in the solver,
//!   which streams every other subdomain's factor between two uses of one.
//! - `dd_coarse`: `DdSolver::new` (factorizations, macro space, coarse
//!   factorization, automatic `d`) with 16 subdomains (with 64 it takes
//!   seconds: its one measured set-up time is printed, not benched), and
//!   solves with 16 and 64 subdomains stopped after 1 and 11 iterations,
//!   and `CoarseProblem::solve` alone on each solver's own coarse problem.
//! - `dd_iteration`: `DdSolver::solve` with `set_stopping(0.0, k)`, `k = 1`
//!   and `k = 11`, so per-iteration time = (t(k=11) − t(k=1)) / 10; the
//!   k = 1 time is the fixed cost of a solve (initial global step, final
//!   assembly) plus one iteration. Linear (`unilateral = false`, `t0 = 0`)
//!   and nonsmooth (`unilateral = true`, `t0 = 0.1`) grids, 4 and 16
//!   subdomains, multilevel.
//! - `direct`: `DirectSolver::new` (assembly + factorization, once per size:
//!   `K` is the same for the linear and nonsmooth grids), `solve` on a
//!   set-up solver (warm active-set cache, as for a second load case; the
//!   first, cold solve is timed once and printed) and, on the small grid,
//!   `new` + first `solve` (a one-shot nonsmooth solve).
//! - `pay_only`: a grid whose elements are all bars, multilevel with 4
//!   subdomains, with `effects.unilateral_cables` false and declared true;
//!   the two must cost the same.
//!
//! Run: `cargo bench --bench solver` (or a filter, e.g.
//! `cargo bench --bench solver -- dd_iteration`).

use std::hint::black_box;
use std::time::{Duration, Instant};

use criterion::{criterion_group, criterion_main, BatchSize, BenchmarkId, Criterion, SamplingMode, Throughput};
use nsdd::dd::{DdOptions, DdSolver};
use nsdd::direct::DirectSolver;
use nsdd::generate::{grid, GridParams};
use nsdd::model::Model;
use nsdd::scene::{ElementKind, Scene, SearchDirection};
use nsdd::solve::decompose;
use nsdd::subdomain::SubdomainOperator;

/// Grid of ~1e4 dofs.
const SMALL: usize = 41;
/// Grid of ~1e5 dofs.
const LARGE: usize = 130;

fn grid_scene(n: usize, nonsmooth: bool) -> Scene {
    grid(&GridParams {
        nx: n,
        ny: n,
        t0: if nonsmooth { 0.1 } else { 0.0 },
        unilateral: nonsmooth,
        ..Default::default()
    })
}

fn case_name(nonsmooth: bool) -> &'static str {
    if nonsmooth {
        "nonsmooth"
    } else {
        "linear"
    }
}

fn multilevel(max_iterations: usize) -> DdOptions {
    DdOptions {
        coarse: true,
        tolerance: 0.0,
        max_iterations,
        search_direction: SearchDirection::Auto,
        krylov: false,
        preconditioner: Default::default(),
        interface_scaling: Default::default(),
        adaptive_threshold: nsdd::settings::AdaptiveThreshold::OFF,
        adaptive_edges: nsdd::settings::AdaptiveEdges::Off,
        macro_degree: Default::default(),
        ordering: Default::default(),
    }
}

/// Deterministic right-hand sides in [-1, 1).
fn pseudo_random(n: usize) -> Vec<f64> {
    let mut s: u64 = 0x2545_f491_4f6c_dd1d;
    (0..n)
        .map(|_| {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        })
        .collect()
}

/// Bytes written before a cold solve: twice the 32 MiB L3 of the machine
/// the figures in BENCHMARKS.md come from.
const EVICT_BYTES: usize = 64 << 20;

fn solve_k(op: &mut SubdomainOperator, x: &mut [f64], k: usize) {
    if k == 1 {
        op.solve_in_place(black_box(x));
    } else {
        op.solve_columns(black_box(x), k);
    }
}

fn subdomain_solve(c: &mut Criterion) {
    let mut g = c.benchmark_group("subdomain_solve");
    g.sampling_mode(SamplingMode::Flat);
    for n in [37, 52, LARGE] {
        let scene = grid_scene(n, false);
        let model = Model::from_scene(&scene).unwrap();
        let dec = decompose(&model, &scene, 1).unwrap();
        let mut op = SubdomainOperator::new(0, &model, &dec.subdomains[0], 64, Default::default()).unwrap();
        let dofs = op.n();
        eprintln!("subdomain_solve: n={n}: {dofs} dofs, nnz(L) = {}", op.nnz_l());
        let mut evict = vec![0.0f64; EVICT_BYTES / 8];
        for k in [1usize, 9, 27] {
            let rhs = pseudo_random(dofs * k);
            let mut x = rhs.clone();
            g.throughput(Throughput::Elements(k as u64));
            g.bench_function(BenchmarkId::new(format!("{dofs}dofs"), format!("k{k}")), |b| {
                b.iter(|| {
                    // Reset the right-hand side (an n·k copy, small against
                    // the solve) so repeated solves stay in range.
                    x.copy_from_slice(&rhs);
                    solve_k(&mut op, &mut x, k);
                })
            });
            // The same solve on a factor evicted from the caches, as in the
            // solver, which streams every other subdomain's factor between
            // two uses of one (the set-up is not timed).
            g.bench_function(BenchmarkId::new(format!("{dofs}dofs-cold"), format!("k{k}")), |b| {
                b.iter_batched_ref(
                    || {
                        evict.iter_mut().for_each(|v| *v += 1.0);
                        black_box(&evict);
                        rhs.clone()
                    },
                    |x| solve_k(&mut op, x, k),
                    BatchSize::PerIteration,
                )
            });
        }
    }
    g.finish();
}

type Group<'a> = criterion::BenchmarkGroup<'a, criterion::measurement::WallTime>;

/// Benches `solve` stopped after 1 and after 11 iterations. The solver is
/// built by `make` on first use, so a filtered-out case costs no set-up.
fn bench_iterations(g: &mut Group<'_>, case: &str, make: impl FnOnce() -> DdSolver, f: &[f64]) -> Option<DdSolver> {
    let mut make = Some(make);
    let mut slot: Option<DdSolver> = None;
    for k in [1usize, 11] {
        g.bench_function(BenchmarkId::new(case, format!("k{k}")), |b| {
            let dd = slot.get_or_insert_with(|| make.take().expect("built once")());
            dd.set_stopping(0.0, k);
            b.iter(|| {
                let out = dd.solve(black_box(f), false, None).unwrap();
                assert_eq!(out.iterations, k, "the solve must run exactly {k} iterations");
                black_box(out)
            })
        });
    }
    slot
}

fn report_dd(what: &str, dd: &DdSolver, setup_s: f64) {
    let st = dd.stats();
    eprintln!(
        "{what}: set-up {setup_s:.3}s, coarse {} macro + {} kernel unknowns, {} interface entries, \
         max kernel dim {}, nnz(L) {}, d = {:.3e}",
        st.macro_unknowns,
        st.kernel_unknowns,
        st.interface_entries,
        st.kernel_dims.iter().max().copied().unwrap_or(0),
        st.nnz_l,
        st.search_direction
    );
}

/// Builds a multilevel solver and reports its sizes and set-up time.
fn build_dd(what: &str, model: &Model, scene: &Scene, subs: usize) -> DdSolver {
    let dec = decompose(model, scene, subs).unwrap();
    let t = Instant::now();
    let dd = DdSolver::new(model, &dec, multilevel(1)).unwrap();
    report_dd(what, &dd, t.elapsed().as_secs_f64());
    dd
}

fn dd_coarse(c: &mut Criterion) {
    let mut g = c.benchmark_group("dd_coarse");
    g.sampling_mode(SamplingMode::Flat);
    let scene = grid_scene(SMALL, false);
    let model = Model::from_scene(&scene).unwrap();
    let f = model.load_cases[0].clone();
    let dofs = model.n_free;
    // Set-up is benched with 16 subdomains only: with 64 it takes several
    // seconds, so ten samples would not fit the time budget; its single
    // measured time is printed by `build_dd` instead.
    let dec = decompose(&model, &scene, 16).unwrap();
    g.bench_function(BenchmarkId::new("setup", format!("{dofs}dofs/16sd")), |b| {
        b.iter(|| black_box(DdSolver::new(&model, &dec, multilevel(1)).unwrap()))
    });
    for subs in [16, 64] {
        let case = format!("solve/{dofs}dofs/{subs}sd");
        let what = format!("dd_coarse linear {dofs} dofs {subs} subdomains");
        let mut built = bench_iterations(&mut g, &case, || build_dd(&what, &model, &scene, subs), &f);
        // The coarse solve alone, on the solver's own coarse problem.
        let mut dd: Option<DdSolver> = None;
        g.bench_function(BenchmarkId::new("coarse_solve", format!("{dofs}dofs/{subs}sd")), |b| {
            let dd = dd.get_or_insert_with(|| built.take().unwrap_or_else(|| build_dd(&what, &model, &scene, subs)));
            let cp = dd.coarse_problem_mut().expect("multilevel solver has a coarse problem");
            b.iter(|| {
                cp.rhs
                    .iter_mut()
                    .enumerate()
                    .for_each(|(i, r)| *r = 1.0 + (i % 7) as f64);
                cp.solve();
                black_box(&cp.solution);
            })
        });
    }
    g.finish();
}

fn dd_iteration(c: &mut Criterion) {
    let mut g = c.benchmark_group("dd_iteration");
    g.sampling_mode(SamplingMode::Flat);
    for n in [SMALL, LARGE] {
        for nonsmooth in [false, true] {
            let scene = grid_scene(n, nonsmooth);
            let model = Model::from_scene(&scene).unwrap();
            let f = model.load_cases[0].clone();
            for subs in [4, 16] {
                let case = format!("{}/{}dofs/{subs}sd", case_name(nonsmooth), model.n_free);
                let what = format!("dd_iteration {case}");
                bench_iterations(&mut g, &case, || build_dd(&what, &model, &scene, subs), &f);
            }
        }
    }
    g.finish();
}

/// Factors and runs a first (cold) solve, outside the timing: it fills the
/// active-set cache as a first load case would. `None` when it fails.
fn first_direct_solve(case: &str, model: &Model, rhs: &[f64]) -> Option<DirectSolver> {
    let mut s = DirectSolver::new(model).unwrap();
    let t = Instant::now();
    match s.solve(model, rhs) {
        Ok(eq) => {
            eprintln!(
                "direct {case}: factor {:.3}s, nnz(L) {}, {} cables, {} slack, {} active-set steps, first solve {:.3}s",
                s.stats().factor_s,
                s.stats().nnz_l,
                model.cables.len(),
                eq.lambda.iter().filter(|&&l| l > 0.0).count(),
                eq.iterations,
                t.elapsed().as_secs_f64()
            );
            Some(s)
        }
        Err(e) => {
            eprintln!(
                "direct {case}: solve FAILED after {:.3}s: {e}",
                t.elapsed().as_secs_f64()
            );
            None
        }
    }
}

fn direct(c: &mut Criterion) {
    let mut g = c.benchmark_group("direct");
    g.sampling_mode(SamplingMode::Flat);
    for n in [SMALL, LARGE] {
        for nonsmooth in [false, true] {
            let scene = grid_scene(n, nonsmooth);
            let model = Model::from_scene(&scene).unwrap();
            let rhs = model.rhs(&model.load_cases[0]);
            let case = format!("{}/{}dofs", case_name(nonsmooth), model.n_free);
            // K does not depend on the cables' unilateral flag: one
            // factorization bench per size.
            if !nonsmooth {
                g.bench_function(BenchmarkId::new("factor", &case), |b| {
                    b.iter(|| black_box(DirectSolver::new(&model).unwrap()))
                });
            }
            let mut solver: Option<Option<DirectSolver>> = None;
            g.bench_function(BenchmarkId::new("solve", &case), |b| {
                match solver.get_or_insert_with(|| first_direct_solve(&case, &model, &rhs)) {
                    Some(s) => b.iter(|| black_box(s.solve(&model, black_box(&rhs)).unwrap())),
                    // The failure is reported; nothing to time.
                    None => b.iter(|| ()),
                }
            });
            if nonsmooth && n == SMALL {
                g.bench_function(BenchmarkId::new("factor+first_solve", &case), |b| {
                    b.iter(|| {
                        let mut s = DirectSolver::new(&model).unwrap();
                        black_box(s.solve(&model, &rhs).unwrap())
                    })
                });
            }
        }
    }
    g.finish();
}

fn pay_only(c: &mut Criterion) {
    let mut g = c.benchmark_group("pay_only");
    g.sampling_mode(SamplingMode::Flat);
    for declared in [false, true] {
        let mut scene = grid_scene(SMALL, false);
        scene.elements.kind.iter_mut().for_each(|k| *k = ElementKind::Bar);
        scene.effects.unilateral_cables = declared;
        let model = Model::from_scene(&scene).unwrap();
        assert!(model.cables.is_empty());
        let f = model.load_cases[0].clone();
        let case = format!("bars_{}dofs_4sd/unilateral_{declared}", model.n_free);
        eprintln!("pay_only {case}: notes {:?}", model.notes);
        let what = format!("pay_only {case}");
        bench_iterations(&mut g, &case, || build_dd(&what, &model, &scene, 4), &f);
    }
    g.finish();
}

fn config() -> Criterion {
    Criterion::default()
        .sample_size(10)
        .warm_up_time(Duration::from_millis(300))
        .measurement_time(Duration::from_secs(1))
}

criterion_group! {
    name = benches;
    config = config();
    targets = subdomain_solve, dd_coarse, dd_iteration, direct, pay_only
}
criterion_main!(benches);
