//! The MPI backend (`--features mpi`): `mpirun -np 1/2/3 nsdd solve` must
//! give the threaded solver's result (in this process, through the same
//! `solve` API) for every DD method, on linear and nonsmooth grids, 3D
//! towers with singular subdomains, load paths and load cases; and an
//! error on one rank must end every rank with the same status, at once.
//!
//! Run with `cargo test --release --features mpi --test mpi` on a machine
//! with `mpirun` (OpenMPI: `openmpi-bin libopenmpi-dev`). `NSDD_MPIRUN`
//! overrides the launcher (default `mpirun --allow-run-as-root
//! --oversubscribe`: CI runs as root on two cores).
#![cfg(feature = "mpi")]

use nsdd::generate::{grid, tensegrity, GridParams, TensegrityParams};
use nsdd::result::SolveResult;
use nsdd::scene::{LoadCase, LoadPath, Method, Scene};
use nsdd::solve::{solve, SolveOptions};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::time::{Duration, Instant};

/// Where the scenes and results of these tests go: under the target
/// directory, as the CLI tests' files (a directory per process under the
/// system's temporary one was never removed, and every run left one).
/// Each result file is removed before the run that writes it.
fn dir() -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("mpi");
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn write_scene(scene: &Scene, name: &str) -> PathBuf {
    let p = dir().join(format!("{name}.toml"));
    std::fs::write(&p, scene.to_toml_string().unwrap()).unwrap();
    p
}

fn mpirun(np: usize, args: &[&str]) -> Output {
    let launcher = std::env::var("NSDD_MPIRUN").unwrap_or_else(|_| "mpirun --allow-run-as-root --oversubscribe".into());
    let mut parts = launcher.split_whitespace();
    let mut cmd = Command::new(parts.next().unwrap());
    cmd.args(parts)
        .args(["-np", &np.to_string(), env!("CARGO_BIN_EXE_nsdd")])
        .args(args)
        // One rayon thread per rank: ranks share the machine's cores.
        .env("RAYON_NUM_THREADS", "1");
    cmd.output().expect("mpirun runs (is OpenMPI installed?)")
}

fn opts(scene: &Scene, method: Method, n: usize) -> SolveOptions {
    let mut o = SolveOptions::from_scene(scene);
    o.method = method;
    o.subdomains = n;
    o.tolerance = 1e-8;
    o.max_iterations = 20_000;
    o
}

fn rel(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    let scale = a.iter().flatten().fold(0.0f64, |m, x| m.max(x.abs())).max(1e-300);
    a.iter()
        .flatten()
        .zip(b.iter().flatten())
        .fold(0.0f64, |m, (x, y)| m.max((x - y).abs()))
        / scale
}

fn rel_t(a: &[f64], b: &[f64]) -> f64 {
    let scale = a.iter().fold(0.0f64, |m, x| m.max(x.abs())).max(1e-300);
    a.iter().zip(b).fold(0.0f64, |m, (x, y)| m.max((x - y).abs())) / scale
}

/// The threaded result and `mpirun -np np`'s agree to 1e-12: displacements,
/// tensions, slack sets, iteration counts, for the top level, every load
/// path step and every load case.
fn agree(scene_path: &Path, threaded: &SolveResult, method: Method, n: usize, np: usize, tol: f64) {
    let out = dir().join(format!(
        "{}-{}-{n}-{np}.json",
        scene_path.file_stem().unwrap().to_str().unwrap(),
        method.name()
    ));
    // A result left by an earlier run must not stand in for this one's.
    let _ = std::fs::remove_file(&out);
    let o = mpirun(
        np,
        &[
            "solve",
            scene_path.to_str().unwrap(),
            "--method",
            method.name(),
            "--subdomains",
            &n.to_string(),
            "--tolerance",
            &tol.to_string(),
            "--max-iterations",
            "20000",
            "--out",
            out.to_str().unwrap(),
        ],
    );
    let what = format!("{} {} n={n} np={np}", scene_path.display(), method.name());
    assert!(
        o.status.success(),
        "{what}: {}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    // Rank 0 alone prints the summary.
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert_eq!(stdout.matches("converged   ").count(), 1, "{what}: {stdout}");
    let r: SolveResult = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert!(r.converged, "{what}");
    assert_eq!(r.iterations, threaded.iterations, "{what}");
    assert_eq!(r.equilibrium_refinement, threaded.equilibrium_refinement, "{what}");
    // `n`, unless the set-up merged indefinite subdomains: alike then.
    assert_eq!(r.subdomains, threaded.subdomains, "{what}");
    assert_eq!(r.element_subdomain, threaded.element_subdomain, "{what}");
    let tops = std::iter::once((&r.displacements, &r.tensions, &r.slack)).chain(
        r.steps
            .iter()
            .chain(&r.load_cases)
            .map(|c| (&c.displacements, &c.tensions, &c.slack)),
    );
    let refs = std::iter::once((&threaded.displacements, &threaded.tensions, &threaded.slack)).chain(
        threaded
            .steps
            .iter()
            .chain(&threaded.load_cases)
            .map(|c| (&c.displacements, &c.tensions, &c.slack)),
    );
    assert_eq!(r.steps.len(), threaded.steps.len(), "{what}");
    assert_eq!(r.load_cases.len(), threaded.load_cases.len(), "{what}");
    for ((u, t, s), (u0, t0, s0)) in tops.zip(refs) {
        let (du, dt) = (rel(u0, u), rel_t(t0, t));
        assert!(
            du < 1e-12 && dt < 1e-12,
            "{what}: displacements {du:.1e}, tensions {dt:.1e}"
        );
        assert_eq!(s, s0, "{what}: slack sets");
    }
}

fn check_all(scene: &Scene, name: &str, cases: &[(Method, usize)], ranks: &[usize]) -> Vec<SolveResult> {
    check_all_at(scene, name, cases, ranks, 1e-8)
}

fn check_all_at(scene: &Scene, name: &str, cases: &[(Method, usize)], ranks: &[usize], tol: f64) -> Vec<SolveResult> {
    let mut results = Vec::new();
    let path = write_scene(scene, name);
    for &(method, n) in cases {
        // One thread, as each rank runs (faer's dense kernels split work by
        // thread count, which moves round-off).
        let threaded = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap()
            .install(|| {
                let o = SolveOptions {
                    tolerance: tol,
                    ..opts(scene, method, n)
                };
                solve(scene, &o).unwrap()
            });
        assert!(
            threaded.converged,
            "{name} {}: {:?} after {} iterations",
            method.name(),
            threaded.status,
            threaded.iterations
        );
        for &np in ranks {
            agree(&path, &threaded, method, n, np, tol);
        }
        results.push(threaded);
    }
    results
}

/// Equilibrium corrections (iterative refinement on the same set-up) run
/// under MPI as on threads: a linear plate and the README's tower with
/// its unilateral cables, asked for tolerances below the floor of their
/// subdomain solves.
#[test]
fn equilibrium_corrections_on_2_ranks() {
    let plate = grid(&GridParams {
        nx: 32,
        ny: 32,
        unilateral: false,
        t0: 0.0,
        ..Default::default()
    });
    let tower = nsdd::generate::tower(&nsdd::generate::TowerParams {
        nx: 2,
        ny: 2,
        nz: 10,
        ..Default::default()
    });
    for (scene, name, n, tol) in [
        (&plate, "plate-refined", 16, 1e-12),
        (&tower, "tower-refined", 4, 1e-11),
    ] {
        let r = check_all_at(scene, name, &[(Method::Cg, n)], &[2], tol);
        assert!(
            r[0].equilibrium_refinement.is_some(),
            "{name}: no correction was needed"
        );
    }
}

#[test]
fn linear_grid_every_dd_method_on_1_2_3_ranks() {
    let scene = grid(&GridParams {
        nx: 16,
        ny: 16,
        unilateral: false,
        t0: 0.0,
        ..Default::default()
    });
    check_all(
        &scene,
        "grid-linear",
        &[(Method::Cg, 6), (Method::Multilevel, 6), (Method::Monolevel, 6)],
        &[1, 2, 3],
    );
}

#[test]
fn nonsmooth_grid_cg_and_multilevel_on_2_3_ranks() {
    let scene = grid(&GridParams {
        nx: 10,
        ny: 10,
        ..Default::default()
    });
    let direct = solve(&scene, &opts(&scene, Method::Direct, 1)).unwrap();
    assert!(direct.slack.iter().any(|&s| s), "the scene has slack cables");
    check_all(
        &scene,
        "grid-nonsmooth",
        &[(Method::Cg, 6), (Method::Multilevel, 4)],
        &[2, 3],
    );
}

#[test]
fn tower_with_floating_subdomains_on_2_3_ranks() {
    let scene = Scene::load(Path::new(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/scenes/tower-2x2x6.toml"
    )))
    .unwrap();
    check_all(&scene, "tower", &[(Method::Cg, 5)], &[2, 3]);
}

/// The adaptive macro space: each face's two sides meet across ranks (the
/// README's contrast tower, 4 subdomains on 2 and 3 ranks).
#[test]
fn adaptive_macro_space_on_2_3_ranks() {
    let mut scene = nsdd::generate::tower(&nsdd::generate::TowerParams {
        nx: 2,
        ny: 2,
        nz: 10,
        unilateral: false,
        ..Default::default()
    });
    scene.solver.adaptive_threshold = nsdd::scene::AdaptiveThreshold::Value(5.0);
    check_all(&scene, "adaptive", &[(Method::Cg, 4)], &[2, 3]);
    // A 3D contrast tower cut in 8: edges shared by 3-4 subdomains held on
    // different ranks, whose sides every rank gathers.
    let mut scene = nsdd::generate::tower(&nsdd::generate::TowerParams {
        nx: 6,
        ny: 6,
        nz: 6,
        unilateral: false,
        ..Default::default()
    });
    scene.solver.adaptive_edges = nsdd::settings::AdaptiveEdges::On;
    let r = check_all(&scene, "adaptive-edges", &[(Method::Cg, 8)], &[2, 3]);
    assert!(
        r.iter().all(|r| r
            .notes
            .iter()
            .any(|n| n.contains("adaptive") && !n.contains(" and 0 on the edges"))),
        "the tower's edges get constraints"
    );
}

#[test]
fn load_path_and_load_cases_on_2_ranks() {
    let mut scene = grid(&GridParams {
        nx: 8,
        ny: 8,
        t0: 0.1,
        load: 2.0,
        ..Default::default()
    });
    scene.load_path = Some(LoadPath {
        steps: 3,
        final_factor: 1.0,
    });
    scene.load_cases.push(LoadCase {
        name: "corner".into(),
        node: vec![10, 20],
        fx: vec![0.5, 0.0],
        fy: vec![0.0, -0.3],
        fz: vec![-2.0, 1.0],
    });
    check_all(&scene, "grid-path", &[(Method::Cg, 4), (Method::Multilevel, 4)], &[2]);

    // VTK: rank 0 alone writes the series, byte for byte what one process
    // with one thread writes.
    let path = dir().join("grid-path.toml");
    let vtk = |sub: &str, np: usize| -> Vec<(String, Vec<u8>)> {
        let d = dir().join(sub);
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        let out = d.join("r.vtu");
        let args = [
            "solve",
            path.to_str().unwrap(),
            "--method",
            "cg",
            "--subdomains",
            "4",
            "--vtk",
            out.to_str().unwrap(),
        ];
        let o = if np == 0 {
            Command::new(env!("CARGO_BIN_EXE_nsdd"))
                .args(args)
                .env("RAYON_NUM_THREADS", "1")
                .output()
                .unwrap()
        } else {
            mpirun(np, &args)
        };
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let mut files: Vec<(String, Vec<u8>)> = std::fs::read_dir(&d)
            .unwrap()
            .map(|e| {
                let e = e.unwrap();
                (
                    e.file_name().to_string_lossy().into_owned(),
                    std::fs::read(e.path()).unwrap(),
                )
            })
            .collect();
        files.sort();
        files
    };
    let (one, two) = (vtk("vtk-process", 0), vtk("vtk-mpi", 2));
    assert_eq!(
        one.len(),
        5,
        "3 steps, the series and the top level: {:?}",
        one.iter().map(|f| &f.0).collect::<Vec<_>>()
    );
    assert!(one == two, "the VTK files of 2 ranks differ from one process's");
}

#[test]
fn more_ranks_than_subdomains() {
    let scene = grid(&GridParams {
        nx: 6,
        ny: 6,
        unilateral: false,
        t0: 0.0,
        ..Default::default()
    });
    check_all(&scene, "grid-small", &[(Method::Cg, 2)], &[3]);
}

/// nsdd's own partition of the tensegrity grid cut in 8 leaves subdomains
/// indefinite on their own (struts cut off from their cables). Each one's
/// error is agreed on every rank before it is merged into a neighbour, so
/// every rank merges alike, down to the threaded run's subdomains (3, more
/// than the 2 ranks), and the answers agree.
#[test]
fn indefinite_subdomains_are_merged_alike_on_every_rank() {
    let scene = tensegrity(&TensegrityParams {
        nx: 3,
        ny: 3,
        unilateral: true,
        ..Default::default()
    });
    let results = check_all(
        &scene,
        "tensegrity-merging",
        &[(Method::Cg, 8), (Method::Multilevel, 8)],
        &[2],
    );
    for r in &results {
        assert!((2..8).contains(&r.subdomains), "{} {}", r.method, r.subdomains);
        assert!(
            r.notes.iter().any(|n| n.contains("not the 8 partitioned")),
            "{:?}",
            r.notes
        );
    }
}

#[test]
fn an_error_on_one_rank_ends_every_rank_alike() {
    // Compressed struts make subdomain 1 of 4 indefinite (its geometric
    // stiffness); with 3 ranks it belongs to rank 1 alone. The partition
    // is the user's: nsdd's own would merge the subdomain away.
    let mut scene = tensegrity(&TensegrityParams {
        nx: 3,
        ny: 3,
        unilateral: true,
        ..Default::default()
    });
    let model = nsdd::model::Model::from_scene(&scene).unwrap();
    scene.elements.subdomain = nsdd::partition::Partition::bisection(&model, 4).unwrap().part_of;
    let expected = match solve(&scene, &opts(&scene, Method::Multilevel, 4)) {
        Err(e) => e,
        Ok(_) => panic!("the threaded set-up should fail"),
    };
    assert!(
        matches!(expected, nsdd::error::Error::IndefiniteSubdomain { subdomain: 1, .. }),
        "{expected}"
    );
    let path = write_scene(&scene, "tensegrity");
    ends_every_rank_alike(&path, Method::Multilevel, 4, 3, &expected);
}

/// `mpirun -np np nsdd solve path` with `method` on `n` subdomains ends
/// without hanging, every rank with the status of the threaded error
/// `expected` (mpirun reports the first non-zero one: 3 for a mechanism or
/// an indefinite subdomain, docs: CLI exit codes), and rank 0 alone prints
/// the message, the threaded one.
fn ends_every_rank_alike(path: &Path, method: Method, n: usize, np: usize, expected: &nsdd::error::Error) {
    let t = Instant::now();
    let o = mpirun(
        np,
        &[
            "solve",
            path.to_str().unwrap(),
            "--method",
            method.name(),
            "--subdomains",
            &n.to_string(),
        ],
    );
    assert!(t.elapsed() < Duration::from_secs(60), "no hang");
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(3), "{stderr}");
    assert_eq!(stderr.matches("error: ").count(), 1, "{stderr}");
    assert!(stderr.contains(&format!("error: {expected}")), "{stderr}");
}

/// A structure that is a mechanism is refused by the rank check of the
/// coarse problem's `G`, which runs before the coarse solves: on 2 ranks
/// (one subdomain each) every rank stops there with the threaded status
/// and rank 0 alone prints the mechanism.
#[test]
fn a_mechanism_found_by_the_coarse_rank_check_ends_every_rank_alike() {
    // Two bars in a vee, both ends held: node 1 is free to move along y.
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/vee-mechanism.toml");
    let scene = Scene::load(&path).unwrap();
    let expected = match solve(&scene, &opts(&scene, Method::Cg, 2)) {
        Err(e) => e,
        Ok(_) => panic!("the threaded set-up should fail"),
    };
    assert!(
        expected.to_string().contains("is not restrained by its interfaces"),
        "{expected}"
    );
    ends_every_rank_alike(&path, Method::Cg, 2, 2, &expected);
}
