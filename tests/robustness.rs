//! Hard cases stay numerically stable (robustness suite).
//!
//! Every case is checked against the direct solver or an analytic value, and
//! every result is checked for NaN/Inf. The direct solver itself is checked
//! independently through the KKT conditions of the convex QP of docs/design.md §1:
//! nodal equilibrium `Σ_e H_e t_e = f` at the free dofs, `t ≥ 0` on cables,
//! and `t = 0`, `e + e0 ≤ 0` on slack ones. What was found by experiment
//! (iteration counts, where the DD iteration stops converging) is recorded in
//! docs/robustness.md.

#![allow(clippy::needless_range_loop)]

mod common;

use common::*;
use nsdd::dd::{DdOptions, DdSolver};
use nsdd::error::Error;
use nsdd::generate::{grid, tensegrity, GridParams, TensegrityParams};
use nsdd::model::Model;
use nsdd::outcome::Status;
use nsdd::result::SolveResult;
use nsdd::scene::{Effects, Method, Scene, SceneBuilder, SearchDirection};
use nsdd::solve::{decompose, solve, SolveOptions};

// ---------------------------------------------------------------- helpers

/// Every displacement, tension and history indicator is finite.
fn assert_finite(r: &SolveResult, what: &str) {
    for v in r.displacements.iter().flatten().chain(&r.tensions) {
        assert!(v.is_finite(), "{what}: non-finite value in the result");
    }
    for h in &r.history {
        assert!(
            h.indicator.is_finite(),
            "{what}: non-finite indicator at iteration {}",
            h.iteration
        );
    }
}

/// Free-dof displacement vector of a result.
fn free_u(model: &Model, disp: &[[f64; 3]]) -> Vec<f64> {
    (0..model.n_free)
        .map(|d| {
            let (node, c) = model.dof_owner(d);
            disp[node][c]
        })
        .collect()
}

/// Independent KKT check of a result: returns `(equilibrium, complementarity)`
/// where `equilibrium = ‖Σ_e H_e t_e − f‖ / (‖f‖ + ‖t‖)` over the free dofs
/// and `complementarity` is the largest violation, relative to the largest
/// element strain, of `t ≥ 0` (cables), `t = 0 ∧ e + e0 ≤ 0` (slack cables)
/// and `t = k (e + e0)` (bars and taut cables).
fn kkt(scene: &Scene, r: &SolveResult) -> (f64, f64) {
    let model = Model::from_scene(scene).unwrap();
    let f = &model.load_cases[0];
    let mut internal = vec![0.0; model.n_free];
    for (e, &t) in r.tensions.iter().enumerate() {
        model.add_h(e, t, &mut internal);
    }
    let res: f64 = internal
        .iter()
        .zip(f)
        .map(|(a, b)| (a - b) * (a - b))
        .sum::<f64>()
        .sqrt();
    let fnorm = f.iter().map(|v| v * v).sum::<f64>().sqrt();
    let tnorm = r.tensions.iter().map(|v| v * v).sum::<f64>().sqrt();
    let eq = res / (fnorm + tnorm).max(f64::MIN_POSITIVE);

    let u = free_u(&model, &r.displacements);
    let strain: Vec<f64> = (0..model.elements.len())
        .map(|e| model.elongation(e, &u) + model.elements[e].e0)
        .collect();
    let scale = strain.iter().fold(0.0f64, |m, v| m.max(v.abs())).max(f64::MIN_POSITIVE);
    let mut worst = 0.0f64;
    for (e, el) in model.elements.iter().enumerate() {
        let t = r.tensions[e];
        let s = strain[e];
        if el.unilateral {
            worst = worst.max(-t / (el.k * scale));
            if r.slack[e] {
                worst = worst.max(t.abs() / (el.k * scale)).max(s / scale);
            } else {
                worst = worst
                    .max((-s / scale).max(0.0))
                    .max((t - el.k * s.max(0.0)).abs() / (el.k * scale));
            }
        } else {
            assert!(!r.slack[e], "a bilateral element is reported slack");
            worst = worst.max((t - el.k * s).abs() / (el.k * scale));
        }
    }
    (eq, worst)
}

/// Cables whose slack flag differs between `r` and the reference `d` must be
/// degenerate: zero strain `e + e0` (relative to the largest strain) in the
/// reference, where either state is an exact solution. Returns their number.
fn assert_same_slack(scene: &Scene, r: &SolveResult, d: &SolveResult, what: &str) -> usize {
    let model = Model::from_scene(scene).unwrap();
    let u = free_u(&model, &d.displacements);
    let strain: Vec<f64> = (0..model.elements.len())
        .map(|e| model.elongation(e, &u) + model.elements[e].e0)
        .collect();
    let scale = strain.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let mut n = 0;
    for e in 0..strain.len() {
        if r.slack[e] != d.slack[e] {
            assert!(
                strain[e].abs() <= 1e-9 * scale,
                "{what}: element {e} slack {} vs {} at strain {:.2e} (scale {scale:.2e})",
                r.slack[e],
                d.slack[e],
                strain[e]
            );
            n += 1;
        }
    }
    n
}

/// Like `assert_matches_direct`, but cables at zero strain may differ in
/// their slack flag (see [`assert_same_slack`]).
fn matches_direct(scene: &Scene, method: Method, n: usize, tol: f64) -> usize {
    let d = direct(scene);
    let r =
        solve(scene, &opts(method, n, tol)).unwrap_or_else(|e| panic!("{} with {n} subdomains: {e}", scene.scene.name));
    assert_finite(&r, "dd");
    assert!(
        r.converged,
        "{} with {n} subdomains: not converged after {}",
        scene.scene.name, r.iterations
    );
    let eu = rel_err(&flat(&r.displacements), &flat(&d.displacements));
    let et = rel_err(&r.tensions, &d.tensions);
    assert!(
        eu <= 10.0 * tol && et <= 10.0 * tol,
        "{} {n}: errors {eu:.2e} {et:.2e}",
        scene.scene.name
    );
    let deg = assert_same_slack(scene, &r, &d, &scene.scene.name);
    if deg > 0 {
        eprintln!(
            "{} {n} subdomains: {deg} zero-strain cables flagged differently",
            scene.scene.name
        );
    }
    r.iterations
}

fn direct(scene: &Scene) -> SolveResult {
    let r = solve(scene, &opts(Method::Direct, 1, 1e-10)).unwrap_or_else(|e| panic!("direct: {e}"));
    assert_finite(&r, "direct");
    r
}

fn with_iters(mut o: SolveOptions, max_iterations: usize) -> SolveOptions {
    o.max_iterations = max_iterations;
    o
}

fn grid_scene(n: usize, unilateral: bool, t0: f64) -> Scene {
    grid(&GridParams {
        nx: n,
        ny: n,
        t0,
        unilateral,
        ..Default::default()
    })
}

fn scale_coords(scene: &Scene, s: f64) -> Scene {
    let mut sc = scene.clone();
    for v in sc
        .nodes
        .x
        .iter_mut()
        .chain(sc.nodes.y.iter_mut())
        .chain(sc.nodes.z.iter_mut())
    {
        *v *= s;
    }
    sc
}

fn scale_loads(scene: &Scene, s: f64) -> Scene {
    let mut sc = scene.clone();
    for v in sc
        .loads
        .fx
        .iter_mut()
        .chain(sc.loads.fy.iter_mut())
        .chain(sc.loads.fz.iter_mut())
    {
        *v *= s;
    }
    sc
}

fn scaled(v: &[f64], s: f64) -> Vec<f64> {
    v.iter().map(|x| x * s).collect()
}

// ---------------------------------------------------------------- stiffness contrast

/// Grid with `k_bar / k_cable = contrast` (k_bar = 1e3 fixed).
fn contrast_grid(n: usize, contrast: f64) -> Scene {
    grid(&GridParams {
        nx: n,
        ny: n,
        ea_bar: 1e3,
        ea_cable: 1e3 / contrast,
        t0: 0.1 / contrast.sqrt(),
        unilateral: true,
        ..Default::default()
    })
}

#[test]
fn stiffness_contrast_direct_satisfies_kkt() {
    for contrast in [1.0, 1e2, 1e4, 1e6, 1e8] {
        let scene = contrast_grid(4, contrast);
        let r = direct(&scene);
        let (eq, comp) = kkt(&scene, &r);
        eprintln!("contrast {contrast:e}: equilibrium {eq:.1e} complementarity {comp:.1e}");
        // Round-off in K u grows with the condition number, i.e. the contrast.
        let bound = 1e-13 * contrast.max(1.0);
        assert!(eq < bound, "contrast {contrast:e}: equilibrium residual {eq:.2e}");
        assert!(
            comp < bound,
            "contrast {contrast:e}: complementarity violation {comp:.2e}"
        );
        assert!(
            r.slack.iter().any(|&s| s),
            "contrast {contrast:e}: expected some slack cables"
        );
    }
}

#[test]
fn stiffness_contrast_multilevel() {
    // Up to 1e4 the multilevel iteration reaches the direct answer; beyond,
    // it either does or stops unconverged / with a named error: never NaN and
    // never a wrong answer flagged converged.
    for (contrast, must_converge) in [(1.0, true), (1e2, true), (1e4, true), (1e6, false), (1e8, false)] {
        let scene = contrast_grid(4, contrast);
        let d = direct(&scene);
        let tol = 1e-8;
        match solve(&scene, &with_iters(opts(Method::Multilevel, 4, tol), 20_000)).and_then(|r| match r.divergence() {
            Some(e) => Err(e),
            None => Ok(r),
        }) {
            Ok(r) => {
                assert_finite(&r, "multilevel");
                let eu = rel_err(&flat(&r.displacements), &flat(&d.displacements));
                let et = rel_err(&r.tensions, &d.tensions);
                eprintln!(
                    "contrast {contrast:e}: converged={} iterations={} eu={eu:.1e} et={et:.1e}",
                    r.converged, r.iterations
                );
                if r.converged {
                    assert!(
                        eu <= 10.0 * tol,
                        "contrast {contrast:e}: converged but displacement error {eu:.2e}"
                    );
                    assert!(
                        et <= 10.0 * tol,
                        "contrast {contrast:e}: converged but tension error {et:.2e}"
                    );
                    assert_eq!(r.slack, d.slack, "contrast {contrast:e}: slack sets differ");
                } else {
                    assert!(
                        !must_converge,
                        "contrast {contrast:e}: not converged after {}",
                        r.iterations
                    );
                }
            }
            Err(e) => {
                eprintln!("contrast {contrast:e}: {e}");
                assert!(!must_converge, "contrast {contrast:e}: {e}");
                assert!(
                    matches!(e, Error::Diverged { .. } | Error::IndefiniteSubdomain { .. }),
                    "{e}"
                );
            }
        }
    }
}

// ---------------------------------------------------------------- coordinate scaling

fn scaled_case(s: f64) -> (Scene, Scene) {
    let scene = grid_scene(4, true, 0.1);
    let sc = scale_coords(&scene, s);
    (scene, sc)
}

#[test]
fn coordinate_scaling_direct() {
    for s in [1e-6, 1e6] {
        let (scene, sc) = scaled_case(s);
        let base = direct(&scene);
        let d = direct(&sc);
        assert!(
            rel_err(&flat(&d.displacements), &scaled(&flat(&base.displacements), s)) < 1e-9,
            "direct s={s:e}"
        );
        assert!(rel_err(&d.tensions, &base.tensions) < 1e-9, "direct s={s:e}");
        assert_same_slack(&sc, &d, &base, "direct, scaled coordinates");
    }
}

/// Multilevel on scaled coordinates against the unscaled multilevel solve.
fn multilevel_scaled(s: f64, n: usize, tol: f64, max_iterations: usize) -> (SolveResult, f64, f64) {
    let (scene, sc) = scaled_case(s);
    let base = solve(&scene, &opts(Method::Multilevel, n, tol)).unwrap();
    assert!(base.converged);
    let m = solve(&sc, &with_iters(opts(Method::Multilevel, n, tol), max_iterations))
        .unwrap_or_else(|e| panic!("s={s:e}: {e}"));
    assert_finite(&m, "multilevel");
    let eu = rel_err(&flat(&m.displacements), &scaled(&flat(&base.displacements), s));
    let et = rel_err(&m.tensions, &base.tensions);
    eprintln!(
        "scale {s:e}, {n} subdomains: converged={} iterations {} (unscaled {}), eu={eu:.1e} et={et:.1e}",
        m.converged, m.iterations, base.iterations
    );
    (m, eu, et)
}

#[test]
fn coordinate_scaling_multilevel() {
    // Large and small coordinates: results scaled to round-off.
    for (s, n) in [(1e6, 4), (1e6, 2), (1e-6, 2)] {
        let (m, eu, et) = multilevel_scaled(s, n, 1e-12, 20_000);
        assert!(m.converged, "s={s:e} n={n}");
        assert!(eu < 1e-9 && et < 1e-9, "s={s:e} n={n}: eu={eu:.1e} et={et:.1e}");
    }
}

#[test]
fn coordinate_scaling_multilevel_small_coordinates_4_subdomains() {
    let (m, eu, et) = multilevel_scaled(1e-6, 4, 1e-12, 20_000);
    assert!(m.converged);
    assert!(eu < 1e-9 && et < 1e-9, "eu={eu:.1e} et={et:.1e}");
}

// ---------------------------------------------------------------- cable states

/// A stable planar bar frame (planar_grid 3×3) with a cable along every
/// horizontal bar, all cables prestressed with `t0`.
fn frame_with_cables(t0: f64) -> Scene {
    let mut s = planar_grid(3, None);
    let n = 3;
    let id = |i: usize, j: usize| i * (n + 1) + j;
    let first = s.elements.a.len();
    for i in 0..n {
        for j in 0..=n {
            s.elements.a.push(id(i, j));
            s.elements.b.push(id(i + 1, j));
            s.elements.kind.push(nsdd::scene::ElementKind::Cable);
            s.elements.ea.push(50.0);
        }
    }
    let m = s.elements.a.len();
    s.elements.t0 = (0..m).map(|e| if e >= first { t0 } else { 0.0 }).collect();
    s.effects = Effects {
        unilateral_cables: true,
        prestress: true,
        ..Default::default()
    };
    s
}

fn cable_ids(s: &Scene) -> Vec<usize> {
    (0..s.elements.kind.len())
        .filter(|&e| s.elements.kind[e] == nsdd::scene::ElementKind::Cable)
        .collect()
}

#[test]
fn all_cables_slack_equals_the_bars_alone() {
    let scene = frame_with_cables(-1e3);
    let cables = cable_ids(&scene);
    let r = direct(&scene);
    assert!(cables.iter().all(|&e| r.slack[e] && r.tensions[e] == 0.0));
    let (eq, comp) = kkt(&scene, &r);
    assert!(eq < 1e-12 && comp < 1e-12, "{eq:.1e} {comp:.1e}");
    // Reference: the same frame without the cables.
    let bars = planar_grid(3, None);
    let b = direct(&bars);
    let nb = bars.elements.a.len();
    assert!(rel_err(&flat(&r.displacements), &flat(&b.displacements)) < 1e-12);
    assert!(rel_err(&r.tensions[..nb], &b.tensions) < 1e-12);
    for n in [2, 4] {
        matches_direct(&scene, Method::Multilevel, n, 1e-9);
    }
}

#[test]
fn all_cables_taut_equals_bilateral_cables() {
    let scene = frame_with_cables(1e3);
    let cables = cable_ids(&scene);
    let r = direct(&scene);
    assert!(cables.iter().all(|&e| !r.slack[e] && r.tensions[e] > 0.0));
    let mut bilateral = scene.clone();
    bilateral.effects.unilateral_cables = false;
    let b = direct(&bilateral);
    assert!(rel_err(&flat(&r.displacements), &flat(&b.displacements)) < 1e-12);
    assert!(rel_err(&r.tensions, &b.tensions) < 1e-12);
    for n in [2, 4] {
        matches_direct(&scene, Method::Multilevel, n, 1e-9);
    }
}

/// Node 1 at (1,0,0) held in x by a cable to node 0 and a bar to node 3, in
/// y by a bar to node 2, loaded in y only. The cable strain is exactly
/// `e + e0 = e0 k_b / (k_c + k_b)`: zero for zero prestress, and of the
/// sign of `e0` otherwise.
fn strain_probe(e0: f64) -> (Scene, f64, f64) {
    let mut b = SceneBuilder::new("strain-probe");
    let n0 = b.node(0.0, 0.0, 0.0);
    let n1 = b.node(1.0, 0.0, 0.0);
    let n2 = b.node(1.0, -1.0, 0.0);
    let n3 = b.node(2.0, 0.0, 0.0);
    let (kc, kb) = (100.0, 300.0);
    let c = b.cable(n0, n1, kc);
    b.bar(n2, n1, 1000.0);
    b.bar(n1, n3, kb);
    b.prestress(c, e0 * kc);
    b.support(n0, "xyz")
        .support(n2, "xyz")
        .support(n3, "xyz")
        .support(n1, "z");
    b.load(n1, [0.0, -1.0, 0.0]);
    b.effects(Effects {
        unilateral_cables: true,
        prestress: true,
        ..Default::default()
    });
    let s = b.build();
    let t = if e0 > 0.0 { kc * kb * e0 / (kc + kb) } else { 0.0 };
    let ux = if e0 > 0.0 { -kc * e0 / (kc + kb) } else { 0.0 };
    (s, t, ux)
}

#[test]
fn cables_at_exactly_zero_strain_and_at_plus_minus_1e_14() {
    for e0 in [0.0, 1e-14, -1e-14] {
        let (scene, t, ux) = strain_probe(e0);
        let r = direct(&scene);
        assert_eq!(r.slack[0], e0 < 0.0, "e0 = {e0:e}");
        assert!(
            (r.tensions[0] - t).abs() <= 1e-12 * t.abs().max(1e-300),
            "e0 = {e0:e}: t = {:e}, expected {t:e}",
            r.tensions[0]
        );
        assert!(
            (r.displacements[1][0] - ux).abs() <= 1e-12 * ux.abs() + 1e-25,
            "e0 = {e0:e}: ux = {:e}",
            r.displacements[1][0]
        );
        assert!((r.displacements[1][1] + 1e-3).abs() < 1e-15, "e0 = {e0:e}");
        let m = solve(&scene, &opts(Method::Multilevel, 2, 1e-10)).unwrap();
        assert_finite(&m, "multilevel");
        assert!(m.converged);
        // The prestress is 1e-14 of the load: below the tolerance, so only
        // the sign convention and finiteness are checked.
        assert!(
            m.tensions[0] >= 0.0 && m.tensions[0] < 1e-9,
            "e0 = {e0:e}: t = {:e}",
            m.tensions[0]
        );
        assert!((m.displacements[1][1] + 1e-3).abs() < 1e-11);
    }
}

#[test]
fn zero_load_zero_prestress_gives_zero_without_nan() {
    let mut scene = grid_scene(4, true, 0.0);
    scene.loads = Default::default();
    let r = direct(&scene);
    assert!(r.displacements.iter().flatten().all(|&v| v == 0.0));
    assert!(r.tensions.iter().all(|&v| v == 0.0));
    for n in [1, 4] {
        let m = solve(&scene, &opts(Method::Multilevel, n, 1e-8)).unwrap();
        assert_finite(&m, "multilevel");
        assert!(m.converged, "{n} subdomains: not converged on a zero load");
        assert!(m.displacements.iter().flatten().all(|&v| v == 0.0));
    }
}

#[test]
fn zero_prestress_nonsmooth_grid() {
    let scene = grid_scene(6, true, 0.0);
    let r = direct(&scene);
    let (eq, comp) = kkt(&scene, &r);
    assert!(eq < 1e-12 && comp < 1e-12, "{eq:.1e} {comp:.1e}");
    assert!(r.slack.iter().any(|&s| s));
    for n in [2, 4, 9] {
        matches_direct(&scene, Method::Multilevel, n, 1e-8);
    }
}

#[test]
fn very_small_and_very_large_loads_scale_linearly() {
    // Without prestress the problem is positively homogeneous: u(s f) = s u(f)
    // for every s > 0 (no cable changes state).
    let scene = grid_scene(4, true, 0.0);
    let d = direct(&scene);
    let m = solve(&scene, &opts(Method::Multilevel, 4, 1e-10)).unwrap();
    for s in [1e-12, 1e12] {
        let sc = scale_loads(&scene, s);
        let ds = direct(&sc);
        assert!(
            rel_err(&flat(&ds.displacements), &scaled(&flat(&d.displacements), s)) < 1e-12,
            "s={s:e}"
        );
        assert!(rel_err(&ds.tensions, &scaled(&d.tensions, s)) < 1e-12);
        assert_same_slack(&sc, &ds, &d, "direct, scaled loads");
        let ms = solve(&sc, &opts(Method::Multilevel, 4, 1e-10)).unwrap();
        assert_finite(&ms, "multilevel");
        assert!(ms.converged);
        assert!(
            rel_err(&flat(&ms.displacements), &scaled(&flat(&m.displacements), s)) < 1e-9,
            "s={s:e}"
        );
        assert!(
            rel_err(&flat(&ms.displacements), &scaled(&flat(&d.displacements), s)) < 1e-9,
            "s={s:e}"
        );
        assert_same_slack(&sc, &ms, &ds, "multilevel, scaled loads");
    }
}

// ---------------------------------------------------------------- near mechanisms

/// Two bars from (−1, 0) and (1, 0) to the apex (0, δ), load P in −y at the apex.
fn shallow_truss(delta: f64, p: f64) -> Scene {
    let mut b = SceneBuilder::new("shallow-truss");
    let a = b.node(-1.0, 0.0, 0.0);
    let c = b.node(0.0, delta, 0.0);
    let d = b.node(1.0, 0.0, 0.0);
    b.bar(a, c, 1e3);
    b.bar(c, d, 1e3);
    b.support(a, "xyz").support(d, "xyz").support(c, "z");
    b.load(c, [0.0, -p, 0.0]);
    b.build()
}

#[test]
fn nearly_collinear_two_bar_truss_matches_analytic() {
    let p = 1.0;
    for delta in [1e-1, 1e-2, 1e-3, 1e-4, 1e-6] {
        let scene = shallow_truss(delta, p);
        let l = (1.0 + delta * delta).sqrt();
        let sin = delta / l;
        let k = 1e3 / l;
        // Linear theory: each bar carries t = −P / (2 sinθ) (compression),
        // the apex moves v = −P / (2 k sin²θ).
        let t = -p / (2.0 * sin);
        let v = -p / (2.0 * k * sin * sin);
        let r = direct(&scene);
        assert!(
            (r.tensions[0] - t).abs() <= 1e-9 * t.abs(),
            "δ={delta:e}: t={} expected {t}",
            r.tensions[0]
        );
        assert!((r.tensions[1] - t).abs() <= 1e-9 * t.abs());
        assert!(
            (r.displacements[1][1] - v).abs() <= 1e-9 * v.abs(),
            "δ={delta:e}: v={} expected {v}",
            r.displacements[1][1]
        );
        assert!(r.displacements[1][0].abs() <= 1e-9 * v.abs());
        // DD with one bar per subdomain: each subdomain is singular (the
        // apex hangs on one bar), the kernel modes are nearly parallel.
        let mut split = scene.clone();
        split.elements.subdomain = vec![0, 1];
        match solve(&split, &opts(Method::Multilevel, 2, 1e-10)) {
            Ok(m) => {
                assert_finite(&m, "multilevel");
                let eu = rel_err(&flat(&m.displacements), &flat(&r.displacements));
                eprintln!(
                    "shallow δ={delta:e}: converged={} it={} eu={eu:.1e}",
                    m.converged, m.iterations
                );
                assert!(!m.converged || eu < 1e-8, "δ={delta:e}: converged with error {eu:.1e}");
            }
            Err(e) => {
                eprintln!("shallow δ={delta:e}: {e}");
                panic!("δ={delta:e}: {e}");
            }
        }
    }
    // Exactly collinear: an infinitesimal mechanism at the apex.
    let scene = shallow_truss(0.0, p);
    match solve(&scene, &opts(Method::Direct, 1, 1e-10)) {
        Err(Error::Mechanism(m)) => assert!(m.contains("node 1") && m.contains("component y"), "{m}"),
        other => panic!("collinear truss: expected a mechanism, got {other:?}"),
    }
    let mut split = scene.clone();
    split.elements.subdomain = vec![0, 1];
    match solve(&split, &opts(Method::Multilevel, 2, 1e-10)) {
        Err(Error::Mechanism(_)) => {}
        other => panic!("collinear truss, multilevel: expected a mechanism, got {other:?}"),
    }
}

/// A unit square panel, base nodes 0 (0,0) and 1 (1,0) fixed, top nodes
/// 2 (1,1) and 3 (0,1), bars of EA `eas`; brace 0–2 of EA `eab` (none if 0);
/// horizontal load P at node 3. Statically determinate: t_top = −P,
/// t_brace = √2 P, t_right = −P, t_left = 0.
fn braced_panel(eas: f64, eab: f64, p: f64) -> Scene {
    let mut b = SceneBuilder::new("braced-panel");
    let n0 = b.node(0.0, 0.0, 0.0);
    let n1 = b.node(1.0, 0.0, 0.0);
    let n2 = b.node(1.0, 1.0, 0.0);
    let n3 = b.node(0.0, 1.0, 0.0);
    b.bar(n1, n2, eas);
    b.bar(n0, n3, eas);
    b.bar(n2, n3, eas);
    if eab > 0.0 {
        b.bar(n0, n2, eab);
    }
    b.support(n0, "xyz")
        .support(n1, "xyz")
        .support(n2, "z")
        .support(n3, "z");
    b.load(n3, [p, 0.0, 0.0]);
    b.build()
}

#[test]
fn tiny_stiffness_brace_matches_analytic() {
    let (eas, p) = (1e3, 1.0);
    for ratio in [1e-2, 1e-4, 1e-6, 1e-8, 1e-10] {
        let eab = eas * ratio;
        let scene = braced_panel(eas, eab, p);
        let ks = eas;
        let kb = eab / 2f64.sqrt();
        let y2 = -p / ks;
        let x2 = 2.0 * p / kb + p / ks;
        let x3 = x2 + p / ks;
        let r = direct(&scene);
        let t = [-p, 0.0, -p, 2f64.sqrt() * p];
        // Tensions of the stiff bars come from displacement differences of
        // size P/k_s on top of the sway 2P/k_b: round-off ~ eps / ratio.
        let tt = 1e-12 + 1e-14 / ratio;
        for e in 0..4 {
            assert!(
                (r.tensions[e] - t[e]).abs() <= tt * p,
                "ratio {ratio:e}: t[{e}]={} expected {}",
                r.tensions[e],
                t[e]
            );
        }
        let u = [
            r.displacements[2][0],
            r.displacements[2][1],
            r.displacements[3][0],
            r.displacements[3][1],
        ];
        let expect = [x2, y2, x3, 0.0];
        for (i, (a, b)) in u.iter().zip(&expect).enumerate() {
            assert!(
                (a - b).abs() <= tt * x2.abs(),
                "ratio {ratio:e}: u[{i}]={a} expected {b}"
            );
        }
        // DD: brace in its own subdomain.
        let mut split = scene.clone();
        split.elements.subdomain = vec![0, 0, 1, 1];
        for method in [Method::Multilevel, Method::Cg] {
            match solve(&split, &with_iters(opts(method, 2, 1e-10), 20_000)).and_then(|r| match r.divergence() {
                Some(e) => Err(e),
                None => Ok(r),
            }) {
                Ok(m) => {
                    assert_finite(&m, "multilevel");
                    // Against the analytic values, not the direct solve: at
                    // ratio 1e-8 the direct sway is 3.2e-8 off them (the
                    // round-off allowed above), while cg, with the brace
                    // alone in its subdomain, is exact to 1e-15 and says so.
                    let mu = [
                        m.displacements[2][0],
                        m.displacements[2][1],
                        m.displacements[3][0],
                        m.displacements[3][1],
                    ];
                    let eu = rel_err(&mu, &expect);
                    eprintln!(
                        "{method:?} brace {ratio:e}: converged={} it={} eu={eu:.1e}",
                        m.converged, m.iterations
                    );
                    assert!(
                        !m.converged || eu < 1e-8,
                        "ratio {ratio:e}: converged with error {eu:.1e}"
                    );
                    assert!(m.converged || ratio < 1e-4, "ratio {ratio:e}: not converged");
                }
                Err(e) => {
                    eprintln!("{method:?} brace {ratio:e}: {e}");
                    assert!(
                        ratio < 1e-4
                            && matches!(
                                e,
                                Error::Diverged { .. } | Error::IndefiniteSubdomain { .. } | Error::Mechanism(_)
                            ),
                        "{e}"
                    );
                }
            }
        }
    }
    // Below the pivot threshold the brace is no longer seen: a mechanism.
    let scene = braced_panel(eas, eas * 1e-14, p);
    match solve(&scene, &opts(Method::Direct, 1, 1e-10)) {
        Err(Error::Mechanism(_)) => {}
        other => panic!("brace 1e-14: expected a mechanism, got {other:?}"),
    }
    // Without the brace: an exact mechanism.
    let scene = braced_panel(eas, 0.0, p);
    for (method, n) in [(Method::Direct, 1), (Method::Multilevel, 1), (Method::Multilevel, 2)] {
        match solve(&scene, &opts(method, n, 1e-10)) {
            Err(Error::Mechanism(m)) => assert!(!m.is_empty()),
            other => panic!("unbraced panel, {method:?} {n}: expected a mechanism, got {other:?}"),
        }
    }
}

// ---------------------------------------------------------------- hard decompositions

/// Kernel dimension of every subdomain of the multilevel set-up of `scene`
/// decomposed into `subdomains` parts.
fn kernel_dims(scene: &Scene, subdomains: usize) -> Vec<usize> {
    let model = Model::from_scene(scene).unwrap();
    let dec = decompose(&model, scene, subdomains).unwrap();
    let dd = DdSolver::new(
        &model,
        &dec,
        DdOptions {
            coarse: true,
            tolerance: 1e-8,
            max_iterations: 10,
            search_direction: SearchDirection::Auto,
            krylov: false,
            preconditioner: Default::default(),
            interface_scaling: Default::default(),
            adaptive_threshold: nsdd::settings::AdaptiveThreshold::OFF,
            adaptive_edges: nsdd::settings::AdaptiveEdges::Off,
            macro_degree: Default::default(),
            ordering: Default::default(),
        },
    )
    .unwrap();
    dd.stats().kernel_dims.clone()
}

#[test]
fn floating_subdomains_match_direct() {
    // Bands along x: only the first touches the supports.
    let scene = planar_grid(6, Some(&|i, _| i / 2));
    let dims = &kernel_dims(&scene, 1);
    assert_eq!(dims[0], 0);
    assert!(dims[1] > 0 && dims[2] > 0, "kernel dims {dims:?}");
    matches_direct(&scene, Method::Multilevel, 3, 1e-8);
    // Monolevel solves them too, with their kernel modes as its only
    // coarse unknowns.
    matches_direct(&scene, Method::Monolevel, 3, 1e-8);
}

#[test]
fn checkerboard_local_mechanisms_and_one_node_interfaces() {
    // Cells alternate between two subdomains: neighbours along a diagonal
    // share a single node, and corner nodes hang on one diagonal bar.
    let scene = planar_grid(6, Some(&|i, j| (i + j) % 2));
    matches_direct(&scene, Method::Multilevel, 2, 1e-8);
    // One subdomain per cell: 36 subdomains, every cut a local mechanism.
    let scene = planar_grid(6, Some(&|i, j| i * 6 + j));
    matches_direct(&scene, Method::Multilevel, 36, 1e-8);
}

#[test]
fn collinear_interfaces_in_3d() {
    // Quadrants in (i, j) of a 2×2×2 lattice: diagonal quadrants touch only
    // along the vertical centre line.
    for unilateral in [false, true] {
        let scene = cube_lattice(2, unilateral, Some(&|i, j, _| i + 2 * j));
        matches_direct(&scene, Method::Multilevel, 4, 1e-8);
    }
}

#[test]
fn cross_point_shared_by_8_subdomains() {
    for unilateral in [false, true] {
        let scene = cube_lattice(2, unilateral, Some(&|i, j, k| i + 2 * j + 4 * k));
        let model = Model::from_scene(&scene).unwrap();
        let dec = decompose(&model, &scene, 1).unwrap();
        assert_eq!(dec.len(), 8);
        // The centre node (1,1,1) is used by all 8 cells.
        let centre = (3 + 1) * 3 + 1;
        let dof = model.node_dofs[centre][0];
        let owners = dec.subdomains.iter().filter(|s| s.local(dof).is_some()).count();
        assert_eq!(owners, 8);
        matches_direct(&scene, Method::Multilevel, 8, 1e-8);
    }
    // And a 3×3×3 lattice, one subdomain per cell (27).
    let scene = cube_lattice(3, true, Some(&|i, j, k| i + 3 * j + 9 * k));
    matches_direct(&scene, Method::Multilevel, 27, 1e-8);
}

#[test]
fn one_to_256_subdomains() {
    let scene = grid_scene(8, true, 0.1);
    for n in [1, 2, 3, 5, 7, 16, 32] {
        matches_direct(&scene, Method::Multilevel, n, 1e-8);
    }
    // 256 subdomains: one per cell of a 16×16 planar grid (set-up ~6 s; the
    // double-layer 16×16 grid cut into 256 by bisection takes ~130 s to set
    // up because the coarse problem is factored densely).
    let scene = planar_grid(16, Some(&|i, j| i * 16 + j));
    let it = matches_direct(&scene, Method::Multilevel, 256, 1e-8);
    eprintln!("16x16 planar grid, 256 subdomains: {it} iterations");
}

// ---------------------------------------------------------------- re-solves

#[test]
fn resolving_reuses_factorizations_bit_identically() {
    let scene = grid_scene(6, true, 0.1);
    let model = Model::from_scene(&scene).unwrap();
    let dec = decompose(&model, &scene, 4).unwrap();
    let o = DdOptions {
        coarse: true,
        tolerance: 1e-9,
        max_iterations: 100_000,
        search_direction: SearchDirection::Auto,
        krylov: false,
        preconditioner: Default::default(),
        interface_scaling: Default::default(),
        adaptive_threshold: nsdd::settings::AdaptiveThreshold::OFF,
        adaptive_edges: nsdd::settings::AdaptiveEdges::Off,
        macro_degree: Default::default(),
        ordering: Default::default(),
    };
    let mut dd = DdSolver::new(&model, &dec, o.clone()).unwrap();
    let f = model.load_cases[0].clone();
    let first = dd.solve(&f, false, None).unwrap();
    assert!(first.converged());
    for factor in [-2.0, 0.0, 5.0] {
        let g: Vec<f64> = f
            .iter()
            .enumerate()
            .map(|(i, v)| v * factor + 0.01 * (i % 3) as f64)
            .collect();
        let out = dd.solve(&g, false, None).unwrap();
        assert!(out.u.iter().all(|v| v.is_finite()));
    }
    let again = dd.solve(&f, false, None).unwrap();
    assert_eq!(again.u, first.u);
    assert_eq!(again.lambda, first.lambda);
    assert_eq!(again.iterations, first.iterations);
    let mut fresh = DdSolver::new(&model, &dec, o).unwrap();
    let new = fresh.solve(&f, false, None).unwrap();
    assert_eq!(new.u, first.u);
    assert_eq!(new.lambda, first.lambda);
    assert_eq!(new.iterations, first.iterations);
    assert_eq!(fresh.search_direction(), dd.search_direction());
}

// ---------------------------------------------------------------- unsolvable structures

#[test]
fn unsupported_structure_is_a_mechanism() {
    let mut scene = grid_scene(4, false, 0.0);
    scene.supports = Default::default();
    for (method, n) in [
        (Method::Direct, 1),
        (Method::Multilevel, 1),
        (Method::Multilevel, 4),
        (Method::Monolevel, 1),
    ] {
        match solve(&scene, &opts(method, n, 1e-8)) {
            Err(Error::Mechanism(m)) => assert!(m.contains("supported") || m.contains("mechanism"), "{m}"),
            Err(Error::MethodNotApplicable(m)) if method == Method::Monolevel => {
                assert!(m.contains("subdomain"), "{m}")
            }
            other => panic!("{method:?} {n}: expected a mechanism, got {other:?}"),
        }
    }
}

#[test]
fn mechanism_is_reported_by_every_method() {
    // The planar grid without its diagonals is a mechanism (square cells).
    let mut b = SceneBuilder::new("squares");
    let n = 4;
    let id = |i: usize, j: usize| i * (n + 1) + j;
    for i in 0..=n {
        for j in 0..=n {
            b.node(i as f64, j as f64, 0.0);
        }
    }
    for i in 0..=n {
        for j in 0..=n {
            if i < n {
                b.bar(id(i, j), id(i + 1, j), 100.0);
            }
            if j < n {
                b.bar(id(i, j), id(i, j + 1), 100.0);
            }
            b.support(id(i, j), if i == 0 && j == 0 { "xyz" } else { "z" });
        }
    }
    b.support(id(0, 1), "x");
    b.load(id(n, n), [1.0, 0.0, 0.0]);
    let scene = b.build();
    for (method, k) in [
        (Method::Direct, 1),
        (Method::Multilevel, 1),
        (Method::Multilevel, 2),
        (Method::Multilevel, 4),
    ] {
        match solve(&scene, &opts(method, k, 1e-8)) {
            Err(Error::Mechanism(m)) => assert!(!m.is_empty()),
            other => panic!("{method:?} {k}: expected a mechanism, got {other:?}"),
        }
    }
}

#[test]
fn slack_cables_leaving_a_mechanism_are_reported() {
    // A node held only by cables that all go slack.
    let mut b = SceneBuilder::new("slack-mechanism");
    let n0 = b.node(0.0, 0.0, 0.0);
    let n1 = b.node(1.0, 0.0, 0.0);
    let n2 = b.node(2.0, 0.0, 0.0);
    b.cable(n0, n1, 100.0);
    b.cable(n1, n2, 100.0);
    b.support(n0, "xyz").support(n2, "xyz").support(n1, "yz");
    b.prestress(0, -1.0);
    b.prestress(1, -1.0);
    b.effects(Effects {
        unilateral_cables: true,
        prestress: true,
        ..Default::default()
    });
    let scene = b.build();
    match solve(&scene, &opts(Method::Direct, 1, 1e-8)) {
        Err(Error::Mechanism(m)) => assert!(m.contains("slack"), "{m}"),
        other => panic!("expected a mechanism, got {other:?}"),
    }
    match solve(&scene, &with_iters(opts(Method::Multilevel, 2, 1e-8), 2000)) {
        Ok(r) => {
            eprintln!(
                "slack mechanism multilevel: converged={} it={}",
                r.converged, r.iterations
            );
            assert_finite(&r, "multilevel");
            // Any state with u_x in a band is an equilibrium: if converged,
            // it must at least satisfy the KKT conditions.
            if r.converged {
                let (eq, comp) = kkt(&scene, &r);
                assert!(eq < 1e-6 && comp < 1e-6, "{eq:.1e} {comp:.1e}");
            }
        }
        Err(e) => eprintln!("slack mechanism multilevel: {e}"),
    }
}

/// Compressed struts cut off from the cables that stabilise them make a
/// subdomain indefinite where the structure is not. On the user's
/// partition (`elements.subdomain`) that is a named error; nsdd's own
/// partition merges such a subdomain into a neighbour and solves the
/// structure as the direct solver does, whatever the subdomain count.
#[test]
fn indefinite_subdomain_is_named_or_merged() {
    let scene = tensegrity(&TensegrityParams {
        nx: 3,
        ny: 3,
        unilateral: true,
        ..Default::default()
    });
    assert!(scene.effects.geometric_stiffness);
    let mut found = 0;
    for n in [2, 4, 8, 16] {
        let users = with_user_partition(&scene, n);
        match solve(&users, &opts(Method::Multilevel, n, 1e-8)) {
            Err(Error::IndefiniteSubdomain { subdomain, message }) => {
                assert!(subdomain < n);
                assert!(
                    message.contains("indefinite") || message.contains("positive definite"),
                    "{message}"
                );
                assert!(Error::IndefiniteSubdomain {
                    subdomain,
                    message: message.clone()
                }
                .to_string()
                .contains(&format!("subdomain {subdomain}")));
                found += 1;
            }
            Err(e) => panic!("{n}: unexpected error {e}"),
            Ok(r) => {
                assert_finite(&r, "multilevel");
                matches_direct(&users, Method::Multilevel, n, 1e-8);
            }
        }
        for method in [Method::Multilevel, Method::Cg] {
            matches_direct(&scene, method, n, 1e-8);
        }
    }
    eprintln!("tensegrity 3x3: {found} of 4 partitions have an indefinite subdomain");
    assert!(found > 0, "no partition produced an indefinite subdomain");
}

#[test]
fn globally_indefinite_geometric_stiffness_is_reported() {
    // Node 1 held transversally by a spring bar of k = 10; the compressed bar
    // 0–1 adds t0/L = −1e3 of transverse stiffness: K is indefinite.
    let mut b = SceneBuilder::new("buckled");
    let n0 = b.node(0.0, 0.0, 0.0);
    let n1 = b.node(1.0, 0.0, 0.0);
    let n2 = b.node(1.0, 1.0, 0.0);
    let n3 = b.node(2.0, 0.0, 0.0);
    b.bar(n0, n1, 1e5);
    b.bar(n1, n2, 10.0);
    b.bar(n1, n3, 1e5);
    b.prestress(0, -1e3);
    b.support(n0, "xyz")
        .support(n2, "xyz")
        .support(n3, "xyz")
        .support(n1, "z");
    b.load(n1, [0.0, 1.0, 0.0]);
    b.effects(Effects {
        prestress: true,
        geometric_stiffness: true,
        ..Default::default()
    });
    let scene = b.build();
    let mut past_merging = 0;
    for (method, n) in [
        (Method::Direct, 1),
        (Method::Multilevel, 1),
        (Method::Multilevel, 3),
        (Method::Cg, 3),
    ] {
        match solve(&scene, &opts(method, n, 1e-8)) {
            Err(Error::Mechanism(m)) => assert!(m.contains("positive definite") || m.contains("mechanism"), "{m}"),
            Err(Error::IndefiniteSubdomain { subdomain, message }) => {
                assert!(subdomain < n);
                // nsdd's own partition merged the indefinite subdomain into
                // its neighbours in vain: the error says the structure is.
                if n > 1 {
                    assert!(message.contains("down to one, the whole structure"), "{message}");
                    past_merging += 1;
                }
            }
            other => panic!("{method:?} {n}: expected an indefinite-stiffness error, got {other:?}"),
        }
    }
    assert_eq!(past_merging, 2, "multilevel and cg on 3 merged in vain");
}

#[test]
fn divergence_is_reported_not_looped() {
    for scene in [grid_scene(8, true, 0.1), cube_lattice(4, true, None)] {
        let mut o = opts(Method::Multilevel, 8, 1e-10);
        o.search_direction = SearchDirection::Value(1e6);
        match solve(&scene, &o) {
            Ok(r) if r.status == Status::Diverged => {
                let Some(Error::Diverged { iteration, message }) = r.divergence() else {
                    panic!("a diverged result names its divergence")
                };
                assert!((1..1000).contains(&iteration), "{iteration}");
                assert!(message.contains('d'), "{message}");
                assert_eq!(r.history.len(), iteration, "the history is kept");
            }
            other => panic!("expected divergence, got {other:?}"),
        }
    }
}

// ---------------------------------------------------------------- bad input through solve()

const BASE: &str = r#"
[nodes]
x = [0.0, 1.0, 0.0, 1.0]
y = [0.0, 0.0, 1.0, 1.0]
z = [0.0, 0.0, 0.0, 1.0]
[elements]
a = [0, 1, 2]
b = [3, 3, 3]
kind = ["bar", "bar", "cable"]
ea = [1000.0, 1000.0, 100.0]
t0 = [0.0, 0.0, 1.0]
[supports]
node = [0, 1, 2]
dofs = ["xyz", "xyz", "xyz"]
[loads]
node = [3]
fx = [0.0]
fy = [0.0]
fz = [-1.0]
"#;

fn all_methods() -> [SolveOptions; 3] {
    [
        opts(Method::Direct, 1, 1e-8),
        opts(Method::Monolevel, 1, 1e-8),
        opts(Method::Multilevel, 2, 1e-8),
    ]
}

fn expect_invalid(text: &str, field: &str, index: Option<usize>) {
    let scene = Scene::from_toml_str(text).unwrap_or_else(|e| panic!("{e}"));
    for o in all_methods() {
        match solve(&scene, &o) {
            Err(Error::InvalidInput { field: f, index: i, .. }) => {
                assert_eq!((f.as_str(), i), (field, index), "{:?}", o.method)
            }
            other => panic!("{:?}: expected invalid {field}, got {other:?}", o.method),
        }
    }
}

#[test]
fn base_scene_solves_with_every_method() {
    let scene = Scene::from_toml_str(BASE).unwrap();
    for o in all_methods() {
        let r = solve(&scene, &o).unwrap();
        assert_finite(&r, o.method.name());
    }
}

#[test]
fn bad_scenes_are_rejected_by_solve_naming_the_field() {
    let cases: &[(&str, &str, &str, Option<usize>)] = &[
        ("y = [0.0, 0.0, 1.0, 1.0]", "y = [0.0, 0.0, 1.0]", "nodes.y", None),
        ("b = [3, 3, 3]", "b = [3, 3]", "elements.b", None),
        (
            r#"kind = ["bar", "bar", "cable"]"#,
            r#"kind = ["bar"]"#,
            "elements.kind",
            None,
        ),
        ("ea = [1000.0, 1000.0, 100.0]", "ea = [1000.0]", "elements.ea", None),
        ("t0 = [0.0, 0.0, 1.0]", "t0 = [0.0]", "elements.t0", None),
        (
            r#"dofs = ["xyz", "xyz", "xyz"]"#,
            r#"dofs = ["xyz"]"#,
            "supports.dofs",
            None,
        ),
        ("fz = [-1.0]", "fz = [-1.0, 0.0]", "loads.fz", None),
        ("a = [0, 1, 2]", "a = [0, 7, 2]", "elements.a", Some(1)),
        ("node = [0, 1, 2]", "node = [0, 1, 9]", "supports.node", Some(2)),
        ("node = [3]", "node = [4]", "loads.node", Some(0)),
        ("b = [3, 3, 3]", "b = [3, 3, 2]", "elements", Some(2)),
        (
            "x = [0.0, 1.0, 0.0, 1.0]",
            "x = [0.0, nan, 0.0, 1.0]",
            "nodes.x",
            Some(1),
        ),
        (
            "ea = [1000.0, 1000.0, 100.0]",
            "ea = [1000.0, inf, 100.0]",
            "elements.ea",
            Some(1),
        ),
        ("t0 = [0.0, 0.0, 1.0]", "t0 = [0.0, -inf, 1.0]", "elements.t0", Some(1)),
        ("fx = [0.0]", "fx = [nan]", "loads.fx", Some(0)),
        (
            "ea = [1000.0, 1000.0, 100.0]",
            "ea = [1000.0, 0.0, 100.0]",
            "elements.ea",
            Some(1),
        ),
        (
            "ea = [1000.0, 1000.0, 100.0]",
            "ea = [-5.0, 1000.0, 100.0]",
            "elements.ea",
            Some(0),
        ),
        (
            r#"dofs = ["xyz", "xyz", "xyz"]"#,
            r#"dofs = ["xyz", "xyq", "xyz"]"#,
            "supports.dofs",
            Some(1),
        ),
    ];
    for (old, new, field, index) in cases {
        let text = BASE.replacen(old, new, 1);
        assert_ne!(text, BASE, "{old}");
        expect_invalid(&text, field, *index);
    }
    // Elements with coinciding nodes at different indices.
    let text = BASE
        .replacen("x = [0.0, 1.0, 0.0, 1.0]", "x = [0.0, 1.0, 0.0, 0.0]", 1)
        .replacen("z = [0.0, 0.0, 0.0, 1.0]", "z = [0.0, 0.0, 0.0, 0.0]", 1);
    expect_invalid(&text, "elements", Some(2));
    // Solver settings and the nsdd additions, read from the scene.
    for (section, field) in [
        ("[solver]\ntolerance = 0.0", "solver.tolerance"),
        ("[solver]\ntolerance = nan", "solver.tolerance"),
        // 0 means "automatic" (issue #20); more parts than elements is wrong.
        ("[solver]\nmethod = \"multilevel\"\nsubdomains = 4", "solver.subdomains"),
        ("[solver]\nmax_iterations = 0", "solver.max_iterations"),
        ("[solver]\nsearch_direction = -1.0", "solver.search_direction"),
        ("[solver]\nsearch_direction = inf", "solver.search_direction"),
        ("[load_path]\nsteps = 0", "load_path.steps"),
        ("[load_path]\nsteps = 2\nfinal_factor = inf", "load_path.final_factor"),
        ("[effects]\nself_weight = true", "elements.mass_per_length"),
    ] {
        let text = format!("{section}\n{BASE}");
        let scene = Scene::from_toml_str(&text).unwrap_or_else(|e| panic!("{section}: {e}"));
        match solve(&scene, &SolveOptions::from_scene(&scene)) {
            Err(Error::InvalidInput { field: f, .. }) => assert_eq!(f, field, "{section}"),
            other => panic!("{section}: expected invalid {field}, got {other:?}"),
        }
    }
    // Unknown kinds, effects and fields are parse errors naming the word.
    for (old, new, word) in [
        (r#""cable"]"#, r#""rope"]"#, "rope"),
        ("[nodes]", "[effects]\nthermal = true\n[nodes]", "thermal"),
        ("[nodes]", "[solver]\nmethod = \"magic\"\n[nodes]", "magic"),
        ("t0 = [", "tzero = [", "tzero"),
    ] {
        match Scene::from_toml_str(&BASE.replacen(old, new, 1)) {
            Err(Error::Parse(m)) => assert!(m.contains(word), "{m}"),
            other => panic!("{word}: expected a parse error, got {other:?}"),
        }
    }
    // A user partition with a gap in the subdomain ids.
    let text = BASE.replacen("t0 = [", "subdomain = [0, 2, 2]\nt0 = [", 1);
    let scene = Scene::from_toml_str(&text).unwrap();
    match solve(&scene, &opts(Method::Multilevel, 2, 1e-8)) {
        Err(Error::InvalidInput { field, .. }) => assert_eq!(field, "elements.subdomain"),
        other => panic!("{other:?}"),
    }
    let text = BASE.replacen("t0 = [", "subdomain = [0, 1]\nt0 = [", 1);
    let scene = Scene::from_toml_str(&text).unwrap();
    match solve(&scene, &opts(Method::Multilevel, 2, 1e-8)) {
        Err(Error::InvalidInput { field, .. }) => assert_eq!(field, "elements.subdomain"),
        other => panic!("{other:?}"),
    }
    // More subdomains than elements.
    let scene = Scene::from_toml_str(BASE).unwrap();
    match solve(&scene, &opts(Method::Multilevel, 4, 1e-8)) {
        Err(Error::InvalidInput { field, .. }) => assert_eq!(field, "solver.subdomains"),
        other => panic!("{other:?}"),
    }
}

#[test]
fn bad_solve_options_never_give_nan_or_a_hang() {
    // SolveOptions given directly (not through the scene's [solver]).
    let scene = grid_scene(4, true, 0.1);
    let base = with_iters(opts(Method::Multilevel, 4, 1e-8), 500);
    let mut cases: Vec<(String, SolveOptions)> = Vec::new();
    for d in [-1.0, 0.0, f64::NAN, f64::INFINITY] {
        let mut o = base.clone();
        o.search_direction = SearchDirection::Value(d);
        cases.push((format!("search_direction {d}"), o));
    }
    for t in [0.0, -1.0, f64::NAN] {
        let mut o = base.clone();
        o.tolerance = t;
        cases.push((format!("tolerance {t}"), o));
    }
    let mut o = base.clone();
    o.subdomains = 0;
    cases.push(("subdomains 0".into(), o));
    let mut o = base.clone();
    o.max_iterations = 0;
    cases.push(("max_iterations 0".into(), o));
    for (what, o) in cases {
        match solve(&scene, &o) {
            Ok(r) => {
                eprintln!("{what}: converged={} iterations={}", r.converged, r.iterations);
                assert_finite(&r, &what);
                if r.converged {
                    // Only acceptable if it is the right answer.
                    let d = direct(&scene);
                    assert!(
                        rel_err(&flat(&r.displacements), &flat(&d.displacements)) < 1e-7,
                        "{what}"
                    );
                }
            }
            Err(e) => eprintln!("{what}: {e}"),
        }
    }
}

// ---------------------------------------------------------------- fuzz corpus replay

#[test]
fn fuzz_corpus_replays_without_panic() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("fuzz/corpus/scene_parser");
    let mut n = 0;
    if let Ok(entries) = std::fs::read_dir(&dir) {
        for entry in entries.flatten() {
            let bytes = std::fs::read(entry.path()).unwrap();
            let text = String::from_utf8_lossy(&bytes);
            for scene in [Scene::from_toml_str(&text), Scene::from_json_str(&text)]
                .into_iter()
                .flatten()
            {
                {
                    if scene.validate().is_ok() {
                        let _ = Model::from_scene(&scene);
                    }
                }
            }
            n += 1;
        }
    }
    assert!(n > 0, "no corpus in {}", dir.display());
}

#[test]
fn large_user_subdomain_ids_are_rejected() {
    let text = BASE.replacen("t0 = [", "subdomain = [0, 1, 1000000]\nt0 = [", 1);
    let scene = Scene::from_toml_str(&text).unwrap();
    match solve(&scene, &opts(Method::Multilevel, 2, 1e-8)) {
        Err(Error::InvalidInput { field, .. }) => assert_eq!(field, "elements.subdomain"),
        other => panic!("{other:?}"),
    }
}

#[test]
fn huge_user_subdomain_id_is_an_input_error() {
    let text = BASE.replacen("t0 = [", "subdomain = [0, 1, 18446744073709551615]\nt0 = [", 1);
    let scene = Scene::from_toml_str(&text).unwrap();
    match solve(&scene, &opts(Method::Multilevel, 2, 1e-8)) {
        Err(Error::InvalidInput { field, .. }) => assert_eq!(field, "elements.subdomain"),
        other => panic!("{other:?}"),
    }
}

#[test]
fn solve_options_given_in_rust_are_checked_like_the_scene() {
    let scene = Scene::from_toml_str(BASE).unwrap();
    let bad = [
        (f64::NAN, 1, 10, SearchDirection::Auto, "solver.tolerance"),
        (0.0, 1, 10, SearchDirection::Auto, "solver.tolerance"),
        // 0 is the automatic count (issue #20); 4 parts of 3 elements are not.
        (1e-8, 4, 10, SearchDirection::Auto, "solver.subdomains"),
        (1e-8, 1, 0, SearchDirection::Auto, "solver.max_iterations"),
        (
            1e-8,
            2,
            10,
            SearchDirection::Value(f64::INFINITY),
            "solver.search_direction",
        ),
        (1e-8, 2, 10, SearchDirection::Value(-1.0), "solver.search_direction"),
    ];
    for (tolerance, subdomains, max_iterations, search_direction, name) in bad {
        let o = nsdd::solve::SolveOptions {
            method: Method::Multilevel,
            subdomains,
            tolerance,
            max_iterations,
            search_direction,
            preconditioner: Default::default(),
            interface_scaling: Default::default(),
            adaptive_threshold: nsdd::settings::AdaptiveThreshold::OFF,
            adaptive_edges: nsdd::settings::AdaptiveEdges::Off,
            macro_degree: Default::default(),
            partitioner: Default::default(),
            ordering: Default::default(),
        };
        match solve(&scene, &o) {
            Err(Error::InvalidInput { field, .. }) => assert_eq!(field, name),
            other => panic!("{name}: {other:?}"),
        }
    }
}

/// The kernel of a linear truss stiffness `Σ EA_e b_e b_eᵀ` is the
/// intersection of the `ker b_eᵀ`: it does not depend on the (positive)
/// axial rigidities. So every subdomain must find the same kernel dimension
/// whatever the bar/cable contrast. Before the kernel detection looked at
/// the span of the suspect pivots, contrast 1e8 hid two mechanisms of the
/// README tower's top subdomain (round-off pivots as large as the soft
/// cables' ones) and one was factored as a soft pivot.
#[test]
fn subdomain_kernels_do_not_depend_on_stiffness_contrast() {
    let dims = |ea_cable: f64| kernel_dims(&taut_tower(ea_cable), 4);
    let reference = dims(1.0);
    assert!(
        reference.iter().any(|&k| k > 6),
        "a subdomain with mechanisms: {reference:?}"
    );
    for ea_cable in [1e-2, 1e-4] {
        assert_eq!(dims(ea_cable), reference, "contrast {:.0e}", 1e4 / ea_cable);
    }
}

/// A random truss of the property test (`tests/proptest_dd.rs`, one case in
/// about a hundred): two subdomains, one interface of 9 dofs, and after the
/// coarse step a residual at round-off that the deluxe-weighted
/// preconditioner maps to exactly zero. CG then had `rz = 0`, and the next
/// `β = rz_new / rz` was 0/0: reported "diverged: the iterate is no longer
/// finite". It is converged, like direct.
#[test]
fn cg_stops_cleanly_when_the_preconditioned_residual_vanishes() {
    const SCENE: &str = r#"[scene]
name = "random-truss"

[effects]
unilateral_cables = false
prestress = true
geometric_stiffness = false
self_weight = false

[nodes]
x = [-2.0, 2.0, 0.0, 0.5896131325040812, 0.18421453995559048, -0.5400793385310666, 0.001136606715858569]
y = [-2.0, -2.0, 2.0, 0.3192458404341767, 0.8613146248021678, 0.8265856746243166, -0.5516764199130298]
z = [-2.0, -2.0, -2.0, -0.7739364098743496, -0.536343410898097, -0.006839284958555618, 0.27035346304939645]

[elements]
a = [0, 1, 2, 1, 2, 3, 1, 2, 3, 2, 3, 5, 3, 3, 5, 0]
b = [3, 3, 3, 4, 4, 4, 5, 5, 5, 6, 6, 6, 2, 2, 0, 3]
kind = ["bar", "bar", "bar", "bar", "bar", "bar", "bar", "bar", "bar", "bar", "bar", "bar", "cable", "cable", "cable", "bar"]
ea = [312.0288976632578, 441.0973429675756, 559.2013847902166, 979.3319324503575, 944.9864180719136, 530.3739466507534, 794.1504376303143, 279.5099180688879, 682.796143578362, 36.041425162435424, 977.5992884927934, 40.11501508934773, 298.82406443617276, 275.4468650905629, 654.6005054988647, 859.8289024658375]
t0 = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.41066939605089103, -0.199372281047934, 0.3428048913479598, 0.0]
subdomain = [0, 0, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 0, 0, 1]

[supports]
node = [0, 1, 2]
dofs = ["xyz", "xyz", "xyz"]

[loads]
node = [3, 4, 5, 6]
fx = [-0.6010438691157483, -0.45888064081798663, 0.4507730069323179, 0.7623531773356412]
fy = [-0.7930969773929554, 0.22786952749125058, -0.6693240338384591, 0.21397970503136482]
fz = [0.04277394651130627, 0.7681847261921938, 0.8825852328626768, -0.5855433489552333]
"#;
    let scene = Scene::from_toml_str(SCENE).unwrap();
    let r = solve(&scene, &opts(Method::Cg, 0, 1e-8)).expect("cg solve");
    assert!(r.converged, "{:?}: {:?}", r.status, r.stop_message);
    let d = solve(&scene, &opts(Method::Direct, 1, 1e-8)).unwrap();
    let eu = rel_err(&flat(&r.displacements), &flat(&d.displacements));
    assert!(eu < 1e-10, "{eu:e}");
}
