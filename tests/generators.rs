//! Scene generators: element counts, stiffness positive definiteness (no
//! mechanism), agreement with the reference scenes, self-stress of the
//! tensegrity grid, speed on large grids, the command-line helper and the
//! bundled scenes in `scenes/`.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use faer::Mat;
use nsdd::generate::{self, GridParams, TensegrityParams, TowerParams};
use nsdd::model::Model;
use nsdd::scene::{ElementKind, Scene};
use nsdd::Error;

fn reference(name: &str) -> Scene {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/reference")
        .join(name);
    Scene::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn scenes_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes")
}

/// Dense `K` (+ `K_G` when the model simulates it) on the free dofs.
fn dense_k(model: &Model) -> Mat<f64> {
    let n = model.n_free;
    let all: Vec<usize> = (0..model.elements.len()).collect();
    let mut k = Mat::<f64>::zeros(n, n);
    for (r, c, v) in model.stiffness_triplets(&all, Some) {
        k[(r, c)] += v;
        if r != c {
            k[(c, r)] += v;
        }
    }
    k
}

/// Asserts that the scene's stiffness is positive definite (dense LLT) and
/// returns the number of free dofs.
fn assert_spd(scene: &Scene) -> usize {
    let model = Model::from_scene(scene).unwrap_or_else(|e| panic!("{}: {e}", scene.scene.name));
    let k = dense_k(&model);
    assert!(
        k.llt(faer::Side::Lower).is_ok(),
        "{}: K is not positive definite ({} free dofs)",
        scene.scene.name,
        model.n_free
    );
    model.n_free
}

/// Whether the smallest eigenvalue of the dense K exceeds `bound` (LLT of
/// `K − bound·I`).
fn min_eig_above(scene: &Scene, bound: f64) -> bool {
    let model = Model::from_scene(scene).unwrap();
    let mut k = dense_k(&model);
    for i in 0..model.n_free {
        k[(i, i)] -= bound;
    }
    k.llt(faer::Side::Lower).is_ok()
}

fn count(scene: &Scene, kind: ElementKind) -> usize {
    scene.elements.kind.iter().filter(|&&k| k == kind).count()
}

/// Nodal resultant of the element prestress `Σ H t0`, over all dofs
/// (supported ones too), i.e. what a self-stress must make vanish.
fn prestress_resultant(scene: &Scene) -> Vec<[f64; 3]> {
    let n = &scene.nodes;
    let el = &scene.elements;
    let mut r = vec![[0.0; 3]; n.x.len()];
    for e in 0..el.a.len() {
        let (a, b) = (el.a[e], el.b[e]);
        let d = [n.x[b] - n.x[a], n.y[b] - n.y[a], n.z[b] - n.z[a]];
        let l = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
        for c in 0..3 {
            let f = el.t0[e] * d[c] / l;
            r[a][c] += f;
            r[b][c] -= f;
        }
    }
    r
}

// ---------------------------------------------------------------- grid

#[test]
fn grid_counts_and_positive_definite() {
    for (nx, ny) in [(1, 1), (2, 2), (3, 3), (4, 4), (3, 2), (1, 4)] {
        let p = GridParams {
            nx,
            ny,
            ..GridParams::default()
        };
        let s = generate::grid(&p);
        s.validate().unwrap();
        let top = (nx + 1) * (ny + 1);
        let bottom = nx * ny;
        assert_eq!(s.nodes.x.len(), top + bottom);
        assert_eq!(p.n_nodes(), top + bottom);
        let top_chords = nx * (ny + 1) + (nx + 1) * ny;
        let bottom_chords = (nx - 1) * ny + nx * (ny - 1);
        let diagonals = nx * ny + (nx - 1) * (ny - 1);
        let webs = 4 * nx * ny;
        assert_eq!(count(&s, ElementKind::Bar), webs);
        assert_eq!(count(&s, ElementKind::Cable), top_chords + bottom_chords + diagonals);
        assert_eq!(s.elements.a.len(), p.n_elements());
        let boundary = 2 * (nx + 1) + 2 * (ny + 1) - 4;
        assert_eq!(s.supports.node.len(), boundary);
        assert_eq!(s.loads.node.len(), (nx - 1) * (ny - 1));
        assert!(s.loads.fz.iter().all(|&f| f == -1.0));
        assert!(s.elements.t0.is_empty());
        let free = assert_spd(&s);
        assert_eq!(free, 3 * (top + bottom - boundary));
    }
}

#[test]
fn grid_uniform_stiffness_gives_equal_k() {
    let s = generate::grid(&GridParams {
        nx: 3,
        ny: 2,
        cell: 2.0,
        depth: 0.7,
        ..GridParams::default()
    });
    let m = Model::from_scene(&s).unwrap();
    for el in &m.elements {
        let k = if el.kind == ElementKind::Bar {
            1e3 / 2.0
        } else {
            1e2 / 2.0
        };
        assert!((el.k - k).abs() <= 1e-12 * k, "k = {} expected {k}", el.k);
    }
    let s = generate::grid(&GridParams {
        uniform_stiffness: false,
        ..GridParams::default()
    });
    assert!(s.elements.ea.iter().all(|&ea| ea == 1e3 || ea == 1e2));
}

#[test]
fn grid_prestress_and_effects() {
    let s = generate::grid(&GridParams {
        t0: 0.25,
        unilateral: false,
        ..GridParams::default()
    });
    assert!(s.effects.prestress && !s.effects.unilateral_cables);
    assert_eq!(s.elements.t0.len(), s.elements.a.len());
    for (k, t) in s.elements.kind.iter().zip(&s.elements.t0) {
        assert_eq!(*t, if *k == ElementKind::Cable { 0.25 } else { 0.0 });
    }
}

#[test]
fn grid_matches_reference_grid4_slack() {
    let r = reference("grid4-slack.toml");
    let g = generate::grid(&GridParams {
        nx: 4,
        ny: 4,
        t0: 0.1,
        load: 4.0,
        ..GridParams::default()
    });
    assert_eq!(g.nodes, r.nodes);
    assert_eq!(g.elements.a, r.elements.a);
    assert_eq!(g.elements.b, r.elements.b);
    assert_eq!(g.elements.kind, r.elements.kind);
    for (e, (x, y)) in g.elements.ea.iter().zip(&r.elements.ea).enumerate() {
        assert!((x - y).abs() <= 1e-13 * y, "ea[{e}]: {x} vs {y}");
    }
    assert_eq!(g.elements.t0, r.elements.t0);
    assert_eq!(g.supports, r.supports);
    assert_eq!(g.loads, r.loads);
    assert_eq!(g.effects, r.effects);
}

#[test]
fn grid_600x600_is_fast() {
    let t = Instant::now();
    let p = GridParams {
        nx: 600,
        ny: 600,
        t0: 0.1,
        ..GridParams::default()
    };
    let s = generate::grid(&p);
    let dt = t.elapsed().as_secs_f64();
    assert_eq!(s.elements.a.len(), p.n_elements());
    assert_eq!(s.nodes.x.len(), p.n_nodes());
    assert!(3 * s.nodes.x.len() > 1_000_000);
    eprintln!(
        "600x600 grid: {} nodes, {} elements in {dt:.3} s",
        s.nodes.x.len(),
        s.elements.a.len()
    );
    assert!(dt < 2.0, "600x600 grid took {dt} s");
}

// ---------------------------------------------------------------- tensegrity

#[test]
fn tensegrity_counts_self_stress_and_positive_definite() {
    for (nx, ny) in [(1, 1), (2, 2), (3, 2), (1, 3)] {
        let p = TensegrityParams {
            nx,
            ny,
            ..TensegrityParams::default()
        };
        let s = generate::tensegrity(&p);
        s.validate().unwrap();
        assert_eq!(s.nodes.x.len(), p.n_nodes());
        assert_eq!(s.elements.a.len(), p.n_elements());
        assert_eq!(count(&s, ElementKind::Bar), 4 * nx * ny);
        assert!(s.effects.prestress && s.effects.geometric_stiffness && s.effects.unilateral_cables);
        // Cables in tension, struts in compression, and a self-stress.
        for (k, t) in s.elements.kind.iter().zip(&s.elements.t0) {
            match k {
                ElementKind::Cable => assert!(*t > 0.0),
                ElementKind::Bar => assert!(*t < 0.0),
            }
        }
        let worst = prestress_resultant(&s)
            .iter()
            .flatten()
            .fold(0.0f64, |m, v| m.max(v.abs()));
        assert!(worst < 1e-12, "{nx}x{ny}: prestress resultant {worst}");
        let m = Model::from_scene(&s).unwrap();
        assert!(m.effects.geometric_stiffness);
        assert_spd(&s);
        assert!(min_eig_above(&s, 1e-3), "{nx}x{ny}: K + K_G nearly singular");
    }
}

#[test]
fn tensegrity_module_needs_its_geometric_stiffness() {
    // One 4-strut module on its blocked bottom square keeps a mechanism that
    // only the geometric stiffness of the self-stress removes.
    let mut s = generate::tensegrity(&TensegrityParams {
        nx: 1,
        ny: 1,
        ..TensegrityParams::default()
    });
    assert!(min_eig_above(&s, 1.0));
    s.effects.geometric_stiffness = false;
    assert!(!min_eig_above(&s, 1e-9));
    // The assembled grid is braced by node sharing (see the generator docs).
    let mut s = generate::tensegrity(&TensegrityParams {
        nx: 2,
        ny: 2,
        ..TensegrityParams::default()
    });
    s.effects.geometric_stiffness = false;
    assert!(min_eig_above(&s, 1.0));
}

#[test]
fn tensegrity_geometry_is_as_documented() {
    let c = 2.0;
    let h = 0.5;
    let t0 = 3.0;
    let s = generate::tensegrity(&TensegrityParams {
        nx: 1,
        ny: 1,
        cell: c,
        depth: h,
        t0,
        ..Default::default()
    });
    let len = |e: usize| {
        let (a, b) = (s.elements.a[e], s.elements.b[e]);
        let n = &s.nodes;
        ((n.x[b] - n.x[a]).powi(2) + (n.y[b] - n.y[a]).powi(2) + (n.z[b] - n.z[a]).powi(2)).sqrt()
    };
    // 4 boundary bottom cables, then 4 top, 4 vertical cables, 4 struts.
    for e in 0..4 {
        assert!((s.elements.t0[e] - t0 / 2.0).abs() < 1e-12);
        assert!((len(e) - c).abs() < 1e-12);
    }
    for e in 4..8 {
        assert!((s.elements.t0[e] - t0 / 2f64.sqrt()).abs() < 1e-12);
    }
    let lv = (c * c / 4.0 + h * h).sqrt();
    let ls = (1.25 * c * c + h * h).sqrt();
    for e in 8..12 {
        assert!((len(e) - lv).abs() < 1e-12);
        assert!((s.elements.t0[e] - t0 * lv / c).abs() < 1e-12);
    }
    for e in 12..16 {
        assert_eq!(s.elements.kind[e], ElementKind::Bar);
        assert!((len(e) - ls).abs() < 1e-12);
        assert!((s.elements.t0[e] + t0 * ls / c).abs() < 1e-12);
    }
}

// ---------------------------------------------------------------- tower

#[test]
fn tower_counts_and_positive_definite() {
    for (nx, ny, nz) in [(1, 1, 1), (1, 1, 4), (2, 2, 3), (3, 1, 2)] {
        let p = TowerParams {
            nx,
            ny,
            nz,
            ..TowerParams::default()
        };
        let s = generate::tower(&p);
        s.validate().unwrap();
        assert_eq!(s.nodes.x.len(), (nx + 1) * (ny + 1) * (nz + 1));
        assert_eq!(s.elements.a.len(), p.n_elements());
        let edges = nx * (ny + 1) * (nz + 1) + (nx + 1) * ny * (nz + 1) + (nx + 1) * (ny + 1) * nz;
        assert_eq!(count(&s, ElementKind::Bar), edges + nx * ny * nz);
        assert_eq!(s.supports.node.len(), (nx + 1) * (ny + 1));
        assert_eq!(s.loads.node.len(), (nx + 1) * (ny + 1));
        assert!(s.loads.fx.iter().all(|&f| f == 0.1));
        assert_spd(&s);
    }
}

#[test]
fn tower_matches_reference_topology() {
    let r = reference("tower-small.toml");
    let g = generate::tower(&TowerParams {
        nx: 1,
        ny: 1,
        nz: 4,
        load: 0.1,
        load_z: -0.05,
        ..Default::default()
    });
    assert_eq!(g.nodes, r.nodes);
    assert_eq!(g.elements.a, r.elements.a);
    assert_eq!(g.elements.b, r.elements.b);
    assert_eq!(g.elements.kind, r.elements.kind);
    assert_eq!(g.supports, r.supports);
    assert_eq!(g.loads, r.loads);
    // The reference draws ea per element around the same contrast.
    for (k, ea) in r.elements.kind.iter().zip(&r.elements.ea) {
        let nominal = if *k == ElementKind::Bar { 1e4 } else { 1.0 };
        assert!(*ea > nominal / 4.0 && *ea < nominal * 4.0);
    }
}

#[test]
fn tower_prestress_on_cables_only() {
    let s = generate::tower(&TowerParams {
        t0: 0.01,
        ..Default::default()
    });
    assert!(s.effects.prestress);
    for (k, t) in s.elements.kind.iter().zip(&s.elements.t0) {
        assert_eq!(*t, if *k == ElementKind::Cable { 0.01 } else { 0.0 });
    }
    assert!(!generate::tower(&TowerParams::default()).effects.prestress);
}

#[test]
fn large_generators_are_linear_time() {
    let t = Instant::now();
    let s = generate::tower(&TowerParams {
        nx: 30,
        ny: 30,
        nz: 100,
        ..Default::default()
    });
    let s2 = generate::tensegrity(&TensegrityParams {
        nx: 400,
        ny: 400,
        ..Default::default()
    });
    let dt = t.elapsed().as_secs_f64();
    assert!(3 * s.nodes.x.len() > 250_000 && 3 * s2.nodes.x.len() > 1_000_000);
    assert!(dt < 3.0, "large tower + tensegrity took {dt} s");
}

// ---------------------------------------------------------------- by_name

fn args(kv: &[(&str, &str)]) -> BTreeMap<String, String> {
    kv.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect()
}

fn bad_field(r: nsdd::Result<Scene>) -> String {
    match r {
        Err(Error::InvalidInput { field, .. }) => field,
        other => panic!("expected InvalidInput, got {other:?}"),
    }
}

#[test]
fn by_name_builds_each_kind() {
    let s = generate::by_name(
        "grid",
        &args(&[("nx", "3"), ("ny", "2"), ("t0", "0.5"), ("unilateral", "false")]),
    )
    .unwrap();
    assert_eq!(
        s,
        generate::grid(&GridParams {
            nx: 3,
            ny: 2,
            t0: 0.5,
            unilateral: false,
            ..Default::default()
        })
    );
    let s = generate::by_name(
        "tower",
        &args(&[("nz", "2"), ("height", "2"), ("load_z", "-1"), ("name", "t")]),
    )
    .unwrap();
    let mut e = generate::tower(&TowerParams {
        nz: 2,
        height: 2.0,
        load_z: -1.0,
        ..Default::default()
    });
    e.scene.name = "t".into();
    assert_eq!(s, e);
    let s = generate::by_name("tensegrity", &BTreeMap::new()).unwrap();
    assert_eq!(s, generate::tensegrity(&TensegrityParams::default()));
    for k in generate::KINDS {
        assert!(generate::parameters(k).is_some());
    }
}

#[test]
fn by_name_names_the_bad_parameter() {
    assert_eq!(bad_field(generate::by_name("dome", &BTreeMap::new())), "kind");
    assert_eq!(bad_field(generate::by_name("grid", &args(&[("nz", "3")]))), "nz");
    assert_eq!(bad_field(generate::by_name("grid", &args(&[("nx", "0")]))), "nx");
    assert_eq!(bad_field(generate::by_name("grid", &args(&[("ny", "two")]))), "ny");
    assert_eq!(bad_field(generate::by_name("grid", &args(&[("cell", "-1")]))), "cell");
    assert_eq!(
        bad_field(generate::by_name("grid", &args(&[("ea_bar", "nan")]))),
        "ea_bar"
    );
    assert_eq!(bad_field(generate::by_name("grid", &args(&[("load", "inf")]))), "load");
    assert_eq!(bad_field(generate::by_name("grid", &args(&[("t0", "-0.1")]))), "t0");
    assert_eq!(
        bad_field(generate::by_name("grid", &args(&[("unilateral", "maybe")]))),
        "unilateral"
    );
    assert_eq!(bad_field(generate::by_name("tensegrity", &args(&[("t0", "0")]))), "t0");
    assert_eq!(bad_field(generate::by_name("tower", &args(&[("depth", "1")]))), "depth");
    assert_eq!(
        bad_field(generate::by_name(
            "grid",
            &args(&[("nx", "100000000"), ("ny", "100000000")])
        )),
        "nx"
    );
    assert_eq!(
        bad_field(generate::by_name(
            "grid",
            &args(&[("nx", "18446744073709551615"), ("ny", "2")])
        )),
        "nx"
    );
}

// ---------------------------------------------------------------- bundled scenes

#[test]
fn bundled_scenes_match_the_generators() {
    for (file, expected) in generate::bundled() {
        let path = scenes_dir().join(file);
        let parsed = Scene::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert_eq!(parsed, expected, "{file} differs from the generator: regenerate with `cargo test --release --test generators -- --ignored write_bundled_scenes`");
        let free = assert_spd(&parsed);
        eprintln!(
            "{file}: {} nodes, {} elements, {free} free dofs",
            parsed.nodes.x.len(),
            parsed.elements.a.len()
        );
    }
}

#[test]
fn bundled_grid_8x8_settings() {
    let s = Scene::load(&scenes_dir().join("grid-8x8.toml")).unwrap();
    assert_eq!(s.solver.method, nsdd::scene::Method::Multilevel);
    assert_eq!(s.solver.subdomains, 4);
    assert_eq!(s.solver.tolerance, 1e-8);
    assert!(s.effects.unilateral_cables && s.effects.prestress);
    let s = Scene::load(&scenes_dir().join("grid-4x4-linear.toml")).unwrap();
    assert!(!s.effects.unilateral_cables);
}

/// Rewrites `scenes/*.toml` from [`generate::bundled`].
#[test]
#[ignore]
fn write_bundled_scenes() {
    std::fs::create_dir_all(scenes_dir()).unwrap();
    for (file, scene) in generate::bundled() {
        let text = format!(
            "# {}: generated by nsdd::generate::bundled(); do not edit by hand.\n\
             # Regenerate with: cargo test --release --test generators -- --ignored write_bundled_scenes\n\n{}",
            file,
            scene.to_toml_string().unwrap()
        );
        std::fs::write(scenes_dir().join(file), text).unwrap();
    }
}
