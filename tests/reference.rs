//! Cross-check against the independent reference solutions in
//! `tests/data/reference/` (dense active set, checked with Siconos' Lemke;
//! see the README there).

use nsdd::direct::DirectSolver;
use nsdd::model::Model;
use nsdd::scene::Scene;
use std::path::PathBuf;

fn data() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/data/reference")
}

struct Ref {
    displacements: Vec<[f64; 3]>,
    tensions: Vec<f64>,
    slack: Vec<bool>,
}

fn load_ref(name: &str) -> (Scene, Ref) {
    let scene = Scene::load(&data().join(format!("{name}.toml"))).unwrap();
    let text = std::fs::read_to_string(data().join(format!("{name}.ref.json"))).unwrap();
    let v: serde_json::Value = serde_json::from_str(&text).unwrap();
    let displacements = v["displacements"]
        .as_array()
        .unwrap()
        .iter()
        .map(|d| {
            let a = d.as_array().unwrap();
            [a[0].as_f64().unwrap(), a[1].as_f64().unwrap(), a[2].as_f64().unwrap()]
        })
        .collect();
    let tensions = v["tensions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_f64().unwrap())
        .collect();
    let slack = v["slack"]
        .as_array()
        .unwrap()
        .iter()
        .map(|t| t.as_bool().unwrap())
        .collect();
    (
        scene,
        Ref {
            displacements,
            tensions,
            slack,
        },
    )
}

fn rel_err(a: &[f64], b: &[f64]) -> f64 {
    let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>().sqrt();
    let den: f64 = b.iter().map(|y| y * y).sum::<f64>().sqrt();
    num / den.max(f64::MIN_POSITIVE)
}

fn check_direct(name: &str) {
    let (scene, r) = load_ref(name);
    let model = Model::from_scene(&scene).unwrap();
    let mut solver = DirectSolver::new(&model).unwrap();
    let b = model.rhs(&model.load_cases[0]);
    let eq = solver.solve(&model, &b).unwrap();
    let u = model.node_displacements(&eq.u);
    let t = model.tensions(&eq.u, &eq.lambda);
    let flat = |v: &[[f64; 3]]| v.iter().flatten().copied().collect::<Vec<f64>>();
    let eu = rel_err(&flat(&u), &flat(&r.displacements));
    let et = rel_err(&t, &r.tensions);
    let mut slack = vec![false; model.elements.len()];
    for (c, &e) in model.cables.iter().enumerate() {
        slack[e] = eq.lambda[c] > 0.0;
    }
    assert!(eu < 1e-9, "{name}: displacement error {eu}");
    assert!(et < 1e-9, "{name}: tension error {et}");
    assert_eq!(slack, r.slack, "{name}: slack set differs");
}

#[test]
fn direct_matches_reference_grid4_slack() {
    check_direct("grid4-slack");
}

#[test]
fn direct_matches_reference_tower_small() {
    check_direct("tower-small");
}

fn check_dd(name: &str, method: nsdd::scene::Method, subdomains: usize, tol: f64) -> usize {
    use nsdd::solve::{solve, SolveOptions};
    let (scene, r) = load_ref(name);
    let mut opts = SolveOptions::from_scene(&scene);
    opts.method = method;
    opts.subdomains = subdomains;
    opts.tolerance = tol;
    opts.max_iterations = 200_000;
    let res = solve(&scene, &opts).unwrap_or_else(|e| panic!("{name} {subdomains}: {e}"));
    assert!(
        res.converged,
        "{name} with {subdomains} subdomains did not converge in {}",
        res.iterations
    );
    let flat = |v: &[[f64; 3]]| v.iter().flatten().copied().collect::<Vec<f64>>();
    let eu = rel_err(&flat(&res.displacements), &flat(&r.displacements));
    let et = rel_err(&res.tensions, &r.tensions);
    eprintln!(
        "{name} {method:?} {subdomains}: {} iterations, eu {eu:.2e} et {et:.2e} d {:?}",
        res.iterations, res.search_direction
    );
    assert!(eu < 10.0 * tol, "{name} {subdomains}: displacement error {eu}");
    assert!(et < 10.0 * tol, "{name} {subdomains}: tension error {et}");
    assert_eq!(res.slack, r.slack, "{name} {subdomains}: slack set differs");
    res.iterations
}

#[test]
fn multilevel_matches_reference() {
    for n in [1, 2, 4, 8] {
        check_dd("grid4-slack", nsdd::scene::Method::Multilevel, n, 1e-8);
        check_dd("tower-small", nsdd::scene::Method::Multilevel, n, 1e-8);
    }
}
