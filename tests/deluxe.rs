//! The deluxe interface scaling of the interface CG (issue 18): on the
//! README's contrast tower (bars 1e4 × the cables) it converges where the
//! pointwise weights need ~10× the iterations, and every scaling agrees with
//! the direct solver. The setting is validated with an error naming it.

use nsdd::generate::{grid, tower, GridParams, TowerParams};
use nsdd::result::SolveResult;
use nsdd::scene::{InterfaceScaling, Method, Scene};
use nsdd::solve::{solve, SolveOptions};

fn rel(a: impl Iterator<Item = f64> + Clone, b: impl Iterator<Item = f64> + Clone) -> f64 {
    let d: f64 = a.clone().zip(b.clone()).map(|(x, y)| (x - y) * (x - y)).sum();
    let n: f64 = b.map(|y| y * y).sum();
    (d / n.max(f64::MIN_POSITIVE)).sqrt()
}

/// Relative 2-norm errors of displacements and tensions against `direct`.
fn errors(r: &SolveResult, direct: &SolveResult) -> (f64, f64) {
    let flat = |s: &SolveResult| s.displacements.iter().flatten().copied().collect::<Vec<f64>>();
    let (u, ud) = (flat(r), flat(direct));
    (
        rel(u.iter().copied(), ud.iter().copied()),
        rel(r.tensions.iter().copied(), direct.tensions.iter().copied()),
    )
}

fn cg(scene: &Scene, subdomains: usize, scaling: InterfaceScaling) -> SolveResult {
    let opts = SolveOptions {
        method: Method::Cg,
        subdomains,
        tolerance: 1e-8,
        max_iterations: 2000,
        interface_scaling: scaling,
        ..Default::default()
    };
    solve(scene, &opts).unwrap()
}

fn direct(scene: &Scene) -> SolveResult {
    solve(scene, &SolveOptions::default()).unwrap()
}

/// The README's tower (`gen tower nx=2 ny=2 nz=10 unilateral=false`, 4
/// subdomains): 60 iterations with the default (deluxe), 563 with the
/// contrast weights; both agree with the direct solve.
#[test]
fn deluxe_converges_on_the_contrast_tower() {
    let scene = tower(&TowerParams {
        nx: 2,
        ny: 2,
        nz: 10,
        unilateral: false,
        ..Default::default()
    });
    let d = direct(&scene);
    assert_eq!(InterfaceScaling::default(), InterfaceScaling::Deluxe);
    let r = cg(&scene, 4, InterfaceScaling::default());
    assert!(r.converged, "{:?}", r.status);
    assert!(r.iterations <= 100, "deluxe took {} iterations", r.iterations);
    let (eu, et) = errors(&r, &d);
    assert!(eu < 1e-8 && et < 1e-7, "errors {eu:.2e} {et:.2e}");
    let c = cg(&scene, 4, InterfaceScaling::Contrast);
    assert!(c.converged);
    assert!(
        c.iterations > 3 * r.iterations,
        "contrast {} vs deluxe {}",
        c.iterations,
        r.iterations
    );
}

/// Every scaling, Dirichlet and lumped, agrees with the direct solve on a
/// grid with cross points (16 subdomains), deluxe in the fewest iterations.
#[test]
fn every_scaling_agrees_with_direct() {
    let scene = grid(&GridParams {
        nx: 12,
        ny: 12,
        unilateral: false,
        t0: 0.0,
        ..Default::default()
    });
    let d = direct(&scene);
    let mut its = Vec::new();
    for k in [
        InterfaceScaling::Deluxe,
        InterfaceScaling::Contrast,
        InterfaceScaling::Multiplicity,
        InterfaceScaling::Stiffness,
        InterfaceScaling::None,
    ] {
        let r = cg(&scene, 16, k);
        assert!(r.converged, "{k:?}: {:?}", r.status);
        let (eu, et) = errors(&r, &d);
        assert!(eu < 1e-8 && et < 1e-7, "{k:?}: errors {eu:.2e} {et:.2e}");
        its.push(r.iterations);
    }
    assert!(its[1..].iter().all(|&i| its[0] < i), "iterations {its:?}");
    let mut opts = SolveOptions {
        method: Method::Cg,
        subdomains: 4,
        preconditioner: nsdd::scene::Preconditioner::Lumped,
        ..Default::default()
    };
    let r = solve(&scene, &opts).unwrap();
    let (eu, _) = errors(&r, &d);
    assert!(r.converged && eu < 1e-8, "lumped deluxe: {eu:.2e}");
    opts.interface_scaling = InterfaceScaling::Contrast;
    let c = solve(&scene, &opts).unwrap();
    assert!(
        c.converged && r.iterations < c.iterations,
        "lumped: {} vs {}",
        r.iterations,
        c.iterations
    );
}

/// `[solver] interface_scaling` is read from a scene, written back when
/// not the default, and a bad value is an error naming the field and the
/// choices.
#[test]
fn scene_setting_is_validated() {
    let mut scene = grid(&GridParams {
        nx: 2,
        ny: 2,
        ..Default::default()
    });
    scene.solver.interface_scaling = InterfaceScaling::Contrast;
    let text = scene.to_toml_string().unwrap();
    assert!(text.contains("interface_scaling = \"contrast\""), "{text}");
    let back = Scene::from_toml_str(&text).unwrap();
    assert_eq!(back.solver.interface_scaling, InterfaceScaling::Contrast);
    scene.solver.interface_scaling = InterfaceScaling::Deluxe;
    assert!(!scene.to_toml_string().unwrap().contains("interface_scaling"));
    let bad = text.replace("interface_scaling = \"contrast\"", "interface_scaling = \"rho\"");
    let err = Scene::from_toml_str(&bad).unwrap_err().to_string();
    assert!(err.contains("interface_scaling") && err.contains("deluxe"), "{err}");
}
