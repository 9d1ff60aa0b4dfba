//! Effects (issue 8): each against an analytic or direct result, and the
//! pipeline runs only the stages a scene calls for.

mod common;

use common::*;
use nsdd::error::Error;
use nsdd::generate::{grid, GridParams};
use nsdd::scene::{Effects, LoadCase, LoadPath, Method, Scene, SceneBuilder};
use nsdd::solve::solve;

fn effects(unilateral: bool, prestress: bool, geometric: bool, self_weight: bool) -> Effects {
    Effects {
        unilateral_cables: unilateral,
        prestress,
        geometric_stiffness: geometric,
        self_weight,
    }
}

#[test]
fn prestress_alone_shortens_a_free_bar_end() {
    // Bar 0–1 (L = 2, EA = 100, k = 50), node 1 free along x only, t0 = 5:
    // no load, so t = 0 and u = −e0 = −t0/k = −0.1.
    let mut b = SceneBuilder::new("prestress");
    b.node(0.0, 0.0, 0.0);
    b.node(2.0, 0.0, 0.0);
    let e = b.bar(0, 1, 100.0);
    b.prestress(e, 5.0).support(0, "xyz").support(1, "yz");
    b.effects(effects(false, true, false, false));
    let scene = b.build();
    for method in [Method::Direct, Method::Multilevel] {
        let r = solve(&scene, &opts(method, 1, 1e-10)).unwrap();
        assert!((r.displacements[1][0] + 0.1).abs() < 1e-14, "{method:?}");
        assert!(r.tensions[0].abs() < 1e-12);
        assert_eq!(r.effects, vec!["prestress"]);
    }
    // Without the effect, t0 is ignored.
    let mut s = scene.clone();
    s.effects.prestress = false;
    let r = solve(&s, &opts(Method::Direct, 1, 1e-10)).unwrap();
    assert_eq!(r.displacements[1][0], 0.0);
    assert!(r.effects.is_empty());
}

#[test]
fn self_weight_hangs_a_bar() {
    // Vertical bar from (0,0,0) down to (0,0,−3), EA = 300 (k = 100),
    // mass 2 per length: node 1 carries m L / 2 · g = 2·3/2·9.81 = 29.43.
    let mut b = SceneBuilder::new("hanging");
    b.node(0.0, 0.0, 0.0);
    b.node(0.0, 0.0, -3.0);
    b.bar(0, 1, 300.0);
    b.support(0, "xyz").support(1, "xy");
    b.effects(effects(false, false, false, true));
    let mut scene = b.build();
    scene.elements.mass_per_length = vec![2.0];
    scene.scene.gravity = Some([0.0, 0.0, -9.81]);
    let r = solve(&scene, &opts(Method::Direct, 1, 1e-10)).unwrap();
    assert!((r.tensions[0] - 29.43).abs() < 1e-12);
    assert!((r.displacements[1][2] + 0.2943).abs() < 1e-14);
    assert_eq!(r.effects, vec!["self_weight"]);
    // Without mass_per_length the effect is a named input error.
    scene.elements.mass_per_length.clear();
    match solve(&scene, &opts(Method::Direct, 1, 1e-10)) {
        Err(Error::InvalidInput { field, .. }) => assert_eq!(field, "elements.mass_per_length"),
        other => panic!("expected an input error, got {other:?}"),
    }
}

fn string_scene(geometric: bool) -> Scene {
    // A prestressed string of two cables (each a = 1) between fixed ends;
    // the middle node is loaded transversally by P = 0.2. Its only lateral
    // stiffness is geometric: 2 t0 / a, so w = P a / (2 t0) = 0.01 (t0 = 10).
    let mut b = SceneBuilder::new("string");
    b.node(0.0, 0.0, 0.0);
    b.node(1.0, 0.0, 0.0);
    b.node(2.0, 0.0, 0.0);
    let c0 = b.cable(0, 1, 1000.0);
    let c1 = b.cable(1, 2, 1000.0);
    b.prestress(c0, 10.0).prestress(c1, 10.0);
    b.support(0, "xyz").support(2, "xyz").support(1, "x");
    b.load(1, [0.0, 0.0, -0.2]);
    b.effects(effects(true, true, geometric, false));
    b.build()
}

#[test]
fn geometric_stiffness_carries_a_transverse_load_on_a_string() {
    let scene = string_scene(true);
    for (method, n) in [(Method::Direct, 1), (Method::Multilevel, 1), (Method::Multilevel, 2)] {
        let r = solve(&scene, &opts(method, n, 1e-12)).unwrap();
        assert!(
            (r.displacements[1][2] + 0.01).abs() < 1e-12,
            "{method:?} {n}: {:?}",
            r.displacements[1]
        );
        assert_eq!(r.slack, vec![false, false]);
    }
    // Without K_G the string is a mechanism transversally.
    match solve(&string_scene(false), &opts(Method::Direct, 1, 1e-12)) {
        Err(Error::Mechanism(m)) => assert!(m.contains("node 1"), "{m}"),
        other => panic!("expected a mechanism, got {other:?}"),
    }
}

fn grid_with_cases() -> Scene {
    let mut scene = grid(&GridParams {
        nx: 6,
        ny: 6,
        t0: 0.1,
        ..Default::default()
    });
    let node = scene.loads.node.clone();
    scene.load_cases.push(LoadCase {
        name: "uplift".into(),
        fz: vec![0.5; node.len()],
        fx: vec![0.2; node.len()],
        node,
        ..Default::default()
    });
    scene
}

#[test]
fn load_cases_are_solved_on_one_setup_and_equal_separate_solves() {
    let scene = grid_with_cases();
    for (method, n) in [(Method::Direct, 1), (Method::Multilevel, 4)] {
        let r = solve(&scene, &opts(method, n, 1e-9)).unwrap();
        assert_eq!(r.load_cases.len(), 1);
        let case = &r.load_cases[0];
        assert_eq!(case.name, "uplift");
        let mut alone = scene.clone();
        let lc = alone.load_cases.remove(0);
        alone.loads = nsdd::scene::Loads {
            node: lc.node,
            fx: lc.fx,
            fy: lc.fy,
            fz: lc.fz,
        };
        let reference = solve(&alone, &opts(Method::Direct, 1, 1e-9)).unwrap();
        assert!(rel_err(&flat(&case.displacements), &flat(&reference.displacements)) < 1e-8);
        assert_eq!(case.slack, reference.slack);
    }
}

#[test]
fn load_path_steps_match_direct_solves_at_each_factor() {
    let mut scene = grid(&GridParams {
        nx: 6,
        ny: 6,
        t0: 0.1,
        load: 3.0,
        ..Default::default()
    });
    scene.load_path = Some(LoadPath {
        steps: 4,
        final_factor: 1.0,
    });
    for (method, n) in [(Method::Direct, 1), (Method::Multilevel, 4)] {
        let r = solve(&scene, &opts(method, n, 1e-9)).unwrap();
        assert_eq!(r.steps.len(), 4);
        for (k, step) in r.steps.iter().enumerate() {
            let factor = (k + 1) as f64 / 4.0;
            assert!((step.load_factor - factor).abs() < 1e-15);
            let mut s = scene.clone();
            s.load_path = None;
            for v in s
                .loads
                .fx
                .iter_mut()
                .chain(s.loads.fy.iter_mut())
                .chain(s.loads.fz.iter_mut())
            {
                *v *= factor;
            }
            let reference = solve(&s, &opts(Method::Direct, 1, 1e-9)).unwrap();
            assert!(
                rel_err(&flat(&step.displacements), &flat(&reference.displacements)) < 1e-8,
                "step {k}"
            );
            assert_eq!(step.slack, reference.slack, "step {k}");
        }
        // The top level holds the last step.
        assert_eq!(r.displacements, r.steps[3].displacements);
    }
}

#[test]
fn declared_but_unusable_effects_are_not_run_and_are_reported() {
    // Unilateral cables declared on a structure without cables.
    let mut scene = planar_grid(3, None);
    scene.effects = effects(true, true, false, false);
    let r = solve(&scene, &opts(Method::Multilevel, 2, 1e-9)).unwrap();
    assert!(r.effects.is_empty(), "{:?}", r.effects);
    assert!(!r.stages.contains(&"cables".to_string()), "{:?}", r.stages);
    assert!(r.notes.iter().any(|n| n.contains("unilateral_cables")), "{:?}", r.notes);
    assert!(r.notes.iter().any(|n| n.contains("prestress")), "{:?}", r.notes);
    // Identical numbers to the scene that never declared them.
    let mut plain = scene.clone();
    plain.effects = Effects::default();
    let q = solve(&plain, &opts(Method::Multilevel, 2, 1e-9)).unwrap();
    assert_eq!(r.displacements, q.displacements);
    assert_eq!(r.iterations, q.iterations);
}

#[test]
fn stages_follow_the_scene_and_the_decomposition() {
    let nonsmooth = grid(&GridParams {
        nx: 4,
        ny: 4,
        t0: 0.1,
        ..Default::default()
    });
    let linear = grid(&GridParams {
        nx: 4,
        ny: 4,
        unilateral: false,
        ..Default::default()
    });
    let stages = |s: &Scene, m, n| solve(s, &opts(m, n, 1e-8)).unwrap().stages;
    assert_eq!(stages(&linear, Method::Direct, 1), vec!["direct"]);
    assert_eq!(stages(&nonsmooth, Method::Direct, 1), vec!["direct", "cables"]);
    // One subdomain: no interface, no coarse step.
    assert_eq!(stages(&linear, Method::Multilevel, 1), Vec::<String>::new());
    assert_eq!(stages(&nonsmooth, Method::Multilevel, 1), vec!["cables"]);
    assert_eq!(
        stages(&linear, Method::Multilevel, 4),
        vec!["interface", "coarse", "kernel"]
    );
    assert_eq!(
        stages(&nonsmooth, Method::Multilevel, 4),
        vec!["interface", "cables", "coarse", "kernel"]
    );
    // Regular subdomains: no kernel machinery.
    let halves = planar_grid(6, Some(&|_, j| (j >= 3) as usize));
    assert_eq!(stages(&halves, Method::Multilevel, 2), vec!["interface", "coarse"]);
    assert_eq!(stages(&halves, Method::Monolevel, 2), vec!["interface"]);
}
