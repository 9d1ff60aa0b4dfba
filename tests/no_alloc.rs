//! The iteration loop allocates nothing: extra iterations add no heap
//! allocation (counted with a counting global allocator).

use nsdd::dd::{DdOptions, DdSolver};
use nsdd::generate::{grid, GridParams};
use nsdd::model::Model;
use nsdd::scene::{Preconditioner, SearchDirection};
use nsdd::solve::decompose;
use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

struct Counting;
static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        unsafe { System.alloc(layout) }
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        unsafe { System.dealloc(ptr, layout) }
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// The counter is process-wide: the tests of this file take turns.
static SERIAL: std::sync::Mutex<()> = std::sync::Mutex::new(());

#[test]
fn extra_iterations_allocate_nothing() {
    let _turn = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    // The stationary iteration, linear and nonsmooth, and the interface CG;
    // with a huge tolerance CG also runs its energy stopping test (one
    // product with K_E per subdomain, src/cg_stopping.rs) every iteration
    // until it certifies.
    for (unilateral, krylov, preconditioner, tolerance) in [
        (false, false, Preconditioner::Dirichlet, 0.0),
        (true, false, Preconditioner::Dirichlet, 0.0),
        (false, true, Preconditioner::Dirichlet, 0.0),
        (false, true, Preconditioner::Lumped, 0.0),
        (false, true, Preconditioner::Dirichlet, 1e300),
    ] {
        let scene = grid(&GridParams {
            nx: 8,
            ny: 8,
            unilateral,
            t0: if unilateral { 0.1 } else { 0.0 },
            ..Default::default()
        });
        let model = Model::from_scene(&scene).unwrap();
        let dec = decompose(&model, &scene, 4).unwrap();
        let opts = DdOptions {
            coarse: true,
            tolerance: 0.0,
            max_iterations: 1,
            search_direction: SearchDirection::Auto,
            krylov,
            preconditioner,
            interface_scaling: Default::default(),
            adaptive_threshold: nsdd::settings::AdaptiveThreshold::OFF,
            adaptive_edges: nsdd::settings::AdaptiveEdges::Off,
            // Degree 1: at the plate's default the solves end before the
            // extra iterations this test counts.
            macro_degree: nsdd::settings::MacroDegree::Fixed(1),
            ordering: Default::default(),
        };
        let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
        pool.install(|| {
            let mut dd = DdSolver::new(&model, &dec, opts.clone()).unwrap();
            let f = model.load_cases[0].clone();
            let count = |dd: &mut DdSolver, k: usize| {
                dd.set_stopping(tolerance, k);
                let before = ALLOCATIONS.load(Ordering::SeqCst);
                let out = dd.solve(&f, false, None).unwrap();
                let n = ALLOCATIONS.load(Ordering::SeqCst) - before;
                drop(out);
                n
            };
            count(&mut dd, 1); // warm-up of the thread pool
                               // The thread pool itself allocates now and then when work is
                               // stolen (seen: 2 allocations in ~1 of 6 runs, in either
                               // count); the solver's own allocations repeat in every run, so
                               // the minimum over a few runs is what the iterations cost.
            let one = (0..5).map(|_| count(&mut dd, 1)).min().unwrap();
            let many = (0..5).map(|_| count(&mut dd, 41)).min().unwrap();
            assert_eq!(
                many,
                one,
                "unilateral {unilateral}, krylov {krylov}, {preconditioner:?}: 40 extra iterations made {} allocations",
                many as i64 - one as i64
            );
        });
    }
}

/// The nonsmooth cg's inner iterations allocate nothing either. Once a
/// first solve has settled the cable set, a second solve from that set
/// runs on the kept set-up (no new one): a loose step (tolerance 1e-2),
/// then the confirming one, which with tolerance 0 spends the rest of the
/// budget. A budget of 15 against 3 is 12 more inner iterations in the
/// same outer steps: the same count of allocations (the outer steps' own
/// bookkeeping is per step).
#[test]
fn nonsmooth_cg_iterations_allocate_nothing() {
    use nsdd::nonsmooth::{NonsmoothCg, NonsmoothOptions, EARLY_STOP_ITERATIONS};
    let _turn = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let scene = grid(&GridParams {
        nx: 8,
        ny: 8,
        ..Default::default()
    });
    let model = Model::from_scene(&scene).unwrap();
    let dec = decompose(&model, &scene, 4).unwrap();
    let opts = NonsmoothOptions {
        tolerance: 1e-10,
        max_iterations: 10_000,
        preconditioner: Preconditioner::Dirichlet,
        interface_scaling: Default::default(),
        adaptive_threshold: nsdd::settings::AdaptiveThreshold::OFF,
        adaptive_edges: nsdd::settings::AdaptiveEdges::Off,
        // Degree 1: at the plate's default the solves end before the
        // extra iterations this test counts.
        macro_degree: nsdd::settings::MacroDegree::Fixed(1),
        ordering: Default::default(),
    };
    let pool = rayon::ThreadPoolBuilder::new().num_threads(2).build().unwrap();
    pool.install(|| {
        let mut ns = NonsmoothCg::new(&model, dec, opts).unwrap();
        let f = model.load_cases[0].clone();
        let first = ns.solve(&model, &f, None).unwrap();
        assert!(first.converged && first.equilibrium.lambda.iter().any(|&l| l > 0.0));
        let count = |ns: &mut NonsmoothCg, k: usize| {
            ns.set_stopping(0.0, k);
            let before = ALLOCATIONS.load(Ordering::SeqCst);
            let out = ns.solve(&model, &f, None).unwrap();
            let n = ALLOCATIONS.load(Ordering::SeqCst) - before;
            assert_eq!((out.setups, out.equilibrium.iterations), (0, k));
            let steps = out.outer_steps;
            drop(out);
            (n, steps)
        };
        let (short, long) = (3, EARLY_STOP_ITERATIONS);
        count(&mut ns, short);
        let few = (0..5).map(|_| count(&mut ns, short)).min().unwrap();
        let many = (0..5).map(|_| count(&mut ns, long)).min().unwrap();
        assert_eq!(many.1, few.1, "outer steps");
        assert_eq!(
            many.0,
            few.0,
            "12 extra nonsmooth inner iterations made {} allocations",
            many.0 as i64 - few.0 as i64
        );
    });
}
