//! Scene input/output: TOML ↔ JSON ↔ builder round trips, every bad-input
//! case of SCENE.md (error naming the field and index), the reference scenes,
//! and mechanisms the model detects by itself.

use std::path::Path;

use nsdd::generate::{self, GridParams, TensegrityParams, TowerParams};
use nsdd::model::Model;
use nsdd::scene::{Effects, ElementKind, Method, Scene, SceneBuilder, SearchDirection, SolverSettings};
use nsdd::Error;

/// The example of SCENE.md, verbatim apart from the comments.
const EXAMPLE: &str = r#"
[scene]
name = "grid-6x6"

[effects]
unilateral_cables = true
prestress = true
geometric_stiffness = false
self_weight = false

[solver]
method = "multilevel"
subdomains = 4
tolerance = 1e-8
max_iterations = 20000
search_direction = "auto"

[nodes]
x = [0.0, 1.0]
y = [0.0, 0.0]
z = [0.0, 0.0]

[elements]
a = [0]
b = [1]
kind = ["cable"]
ea = [1000.0]
t0 = [10.0]

[supports]
node = [0, 1]
dofs = ["xyz", "yz"]

[loads]
node = [1]
fx = [0.0]
fy = [0.0]
fz = [-1.0]
"#;

/// A small valid scene (a triangle of two bars and a cable on a square
/// base) used as the starting point of the bad-input cases.
const BASE: &str = r#"
[scene]
name = "base"

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

fn toml(text: &str) -> Scene {
    Scene::from_toml_str(text).unwrap_or_else(|e| panic!("{e}\n{text}"))
}

/// `BASE` with one line replaced (the line must exist).
fn base_with(old: &str, new: &str) -> String {
    assert!(BASE.contains(old), "BASE has no '{old}'");
    BASE.replacen(old, new, 1)
}

/// Asserts that validation fails on `field` at `index`.
fn assert_invalid(scene: &Scene, field: &str, index: Option<usize>) {
    match scene.validate() {
        Err(Error::InvalidInput {
            field: f,
            index: i,
            message,
        }) => {
            assert_eq!((f.as_str(), i), (field, index), "message: {message}");
            assert!(!message.is_empty());
        }
        other => panic!("expected InvalidInput on {field}[{index:?}], got {other:?}"),
    }
    // The model refuses the same scene with the same error.
    assert!(matches!(Model::from_scene(scene), Err(Error::InvalidInput { .. })));
}

fn assert_invalid_toml(text: &str, field: &str, index: Option<usize>) {
    assert_invalid(&toml(text), field, index);
}

fn parse_error(r: nsdd::Result<Scene>) -> String {
    match r {
        Err(Error::Parse(m)) => m,
        other => panic!("expected a parse error, got {other:?}"),
    }
}

fn builder_scene() -> Scene {
    let mut b = SceneBuilder::new("built");
    let n: Vec<usize> = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.3, 0.4, 1.0]]
        .iter()
        .map(|p| b.node(p[0], p[1], p[2]))
        .collect();
    b.bar(n[0], n[3], 1e3);
    let c = b.cable(n[1], n[3], 1e2);
    b.bar(n[2], n[3], 1e3);
    b.prestress(c, 0.1 + 0.2); // not exactly representable in decimal
    b.support(n[0], "xyz").support(n[1], "xyz").support(n[2], "xyz");
    b.load(n[3], [1.0 / 3.0, 0.0, -2.5e-7]);
    b.effects(Effects {
        unilateral_cables: true,
        prestress: true,
        ..Effects::default()
    });
    b.solver(SolverSettings {
        method: Method::Monolevel,
        subdomains: 2,
        tolerance: 1e-9,
        max_iterations: 77,
        search_direction: SearchDirection::Value(12.5),
        preconditioner: nsdd::scene::Preconditioner::Lumped,
        interface_scaling: nsdd::scene::InterfaceScaling::Contrast,
        adaptive_threshold: nsdd::scene::AdaptiveThreshold::Value(12.0),
        adaptive_edges: nsdd::settings::AdaptiveEdges::On,
        macro_degree: Default::default(),
        partitioner: nsdd::scene::Partitioner::Metis,
        ordering: Default::default(),
    });
    b.build_validated().unwrap()
}

// ---------------------------------------------------------------- round trips

/// Whether two scenes are equal up to `ulps` units in the last place in
/// every number (compared through their JSON values).
fn same_up_to_ulps(a: &Scene, b: &Scene, ulps: u64) -> bool {
    fn eq(x: &serde_json::Value, y: &serde_json::Value, ulps: u64) -> bool {
        use serde_json::Value as V;
        match (x, y) {
            (V::Number(p), V::Number(q)) => match (p.as_f64(), q.as_f64()) {
                (Some(p), Some(q)) if p.is_finite() && q.is_finite() && p.signum() == q.signum() => {
                    p.to_bits().abs_diff(q.to_bits()) <= ulps
                }
                _ => p == q,
            },
            (V::Array(p), V::Array(q)) => p.len() == q.len() && p.iter().zip(q).all(|(p, q)| eq(p, q, ulps)),
            (V::Object(p), V::Object(q)) => {
                p.len() == q.len() && p.iter().all(|(k, v)| q.get(k).is_some_and(|w| eq(v, w, ulps)))
            }
            _ => x == y,
        }
    }
    eq(
        &serde_json::to_value(a).unwrap(),
        &serde_json::to_value(b).unwrap(),
        ulps,
    )
}

/// TOML round trips are exact. JSON ones are checked to 1 ulp: serde_json
/// without its `float_roundtrip` feature (not enabled in Cargo.toml) reads
/// some 17-digit numbers 1 ulp off (seen on the reference tower's `ea`).
fn assert_round_trips(s: &Scene) {
    let t = s.to_toml_string().unwrap();
    assert_eq!(&Scene::from_toml_str(&t).unwrap(), s, "TOML round trip\n{t}");
    let j = s.to_json_string().unwrap();
    assert!(
        same_up_to_ulps(&Scene::from_json_str(&j).unwrap(), s, 1),
        "JSON round trip\n{j}"
    );
    // TOML → JSON → TOML.
    let via = Scene::from_json_str(&Scene::from_toml_str(&t).unwrap().to_json_string().unwrap()).unwrap();
    assert!(same_up_to_ulps(
        &Scene::from_toml_str(&via.to_toml_string().unwrap()).unwrap(),
        s,
        1
    ));
}

#[test]
fn scene_md_example_parses_validates_and_round_trips() {
    let s = toml(EXAMPLE);
    s.validate().unwrap();
    assert_eq!(s.scene.name, "grid-6x6");
    assert!(s.effects.unilateral_cables && s.effects.prestress);
    assert_eq!(s.solver.method, Method::Multilevel);
    assert_eq!(s.solver.subdomains, 4);
    assert_eq!(s.elements.kind, vec![ElementKind::Cable]);
    assert_eq!(s.supports.dofs, vec!["xyz", "yz"]);
    assert_round_trips(&s);
}

#[test]
fn builder_toml_json_round_trips() {
    let s = builder_scene();
    assert_eq!(s.elements.t0, vec![0.0, 0.1 + 0.2, 0.0]);
    assert_eq!(s.loads.fx, vec![1.0 / 3.0]);
    assert_round_trips(&s);
    // The builder gives the same scene as the equivalent file.
    let from_text = Scene::from_toml_str(&s.to_toml_string().unwrap()).unwrap();
    assert_eq!(from_text, s);
}

#[test]
fn builder_keeps_columns_consistent() {
    let mut b = SceneBuilder::new("cols");
    let a = b.node(0.0, 0.0, 0.0);
    let c = b.node(1.0, 0.0, 0.0);
    b.bar(a, c, 1.0);
    assert!(b.clone().build().elements.t0.is_empty(), "t0 stays empty until used");
    b.prestress(0, 2.0);
    b.cable(a, c, 1.0);
    b.bar(c, a, 1.0);
    let s = b.build();
    assert_eq!(s.elements.t0, vec![2.0, 0.0, 0.0]);
    assert_eq!(s.elements.a.len(), s.elements.kind.len());
}

#[test]
fn builder_reports_bad_indices_through_validation() {
    let mut b = SceneBuilder::new("bad");
    let a = b.node(0.0, 0.0, 0.0);
    let c = b.node(1.0, 0.0, 0.0);
    b.bar(a, c, 1.0);
    b.prestress(5, 1.0).prestress(usize::MAX, 2.0);
    assert!(b.clone().build().validate().is_err());
    match b.build_validated() {
        Err(Error::InvalidInput { field, index, .. }) => assert_eq!((field.as_str(), index), ("elements.t0", Some(5))),
        other => panic!("{other:?}"),
    }
    let mut b = SceneBuilder::new("bad");
    let a = b.node(0.0, 0.0, 0.0);
    b.bar(a, 7, 1.0);
    match b.build_validated() {
        Err(Error::InvalidInput { field, index, .. }) => assert_eq!((field.as_str(), index), ("elements.b", Some(0))),
        other => panic!("{other:?}"),
    }
}

#[test]
fn generated_scenes_round_trip() {
    for s in [
        generate::grid(&GridParams {
            nx: 3,
            ny: 2,
            t0: 0.1,
            ..Default::default()
        }),
        generate::tensegrity(&TensegrityParams {
            nx: 2,
            ny: 1,
            ..Default::default()
        }),
        generate::tower(&TowerParams {
            nx: 2,
            ny: 1,
            nz: 2,
            t0: 0.003,
            load_z: -0.1,
            ..Default::default()
        }),
    ] {
        s.validate().unwrap();
        assert_round_trips(&s);
    }
}

#[test]
fn optional_sections_default() {
    // Only nodes and elements are required; everything else defaults.
    let s = toml(
        r#"
[nodes]
x = [0.0, 1.0]
y = [0.0, 0.0]
z = [0.0, 0.0]
[elements]
a = [0]
b = [1]
kind = ["bar"]
ea = [1.0]
"#,
    );
    s.validate().unwrap();
    assert_eq!(s.effects, Effects::default());
    assert_eq!(s.solver, SolverSettings::default());
    assert!(s.elements.t0.is_empty() && s.supports.node.is_empty() && s.loads.node.is_empty());
}

// ---------------------------------------------------------------- bad input

#[test]
fn base_is_valid() {
    let s = toml(BASE);
    s.validate().unwrap();
    Model::from_scene(&s).unwrap();
}

#[test]
fn arrays_of_different_lengths() {
    assert_invalid_toml(
        &base_with("y = [0.0, 0.0, 1.0, 1.0]", "y = [0.0, 0.0, 1.0]"),
        "nodes.y",
        None,
    );
    assert_invalid_toml(
        &base_with("z = [0.0, 0.0, 0.0, 1.0]", "z = [0.0, 0.0, 0.0, 1.0, 2.0]"),
        "nodes.z",
        None,
    );
    assert_invalid_toml(&base_with("b = [3, 3, 3]", "b = [3, 3]"), "elements.b", None);
    assert_invalid_toml(
        &base_with(r#"kind = ["bar", "bar", "cable"]"#, r#"kind = ["bar", "bar"]"#),
        "elements.kind",
        None,
    );
    assert_invalid_toml(
        &base_with("ea = [1000.0, 1000.0, 100.0]", "ea = [1000.0]"),
        "elements.ea",
        None,
    );
    assert_invalid_toml(
        &base_with("t0 = [0.0, 0.0, 1.0]", "t0 = [0.0, 0.0, 1.0, 0.0]"),
        "elements.t0",
        None,
    );
    assert_invalid_toml(
        &base_with(r#"dofs = ["xyz", "xyz", "xyz"]"#, r#"dofs = ["xyz", "xyz"]"#),
        "supports.dofs",
        None,
    );
    assert_invalid_toml(&base_with("fz = [-1.0]", "fz = [-1.0, 2.0]"), "loads.fz", None);
    assert_invalid_toml(&base_with("fx = [0.0]", "fx = [0.0, 1.0]"), "loads.fx", None);
}

#[test]
fn node_indices_out_of_range() {
    assert_invalid_toml(&base_with("a = [0, 1, 2]", "a = [0, 4, 2]"), "elements.a", Some(1));
    assert_invalid_toml(&base_with("b = [3, 3, 3]", "b = [3, 3, 99]"), "elements.b", Some(2));
    assert_invalid_toml(
        &base_with("node = [0, 1, 2]", "node = [0, 1, 4]"),
        "supports.node",
        Some(2),
    );
    assert_invalid_toml(&base_with("node = [3]", "node = [4]"), "loads.node", Some(0));
}

#[test]
fn zero_length_element() {
    // Same node at both ends, and two distinct nodes at the same place.
    assert_invalid_toml(&base_with("b = [3, 3, 3]", "b = [3, 1, 3]"), "elements", Some(1));
    let coincide = base_with("y = [0.0, 0.0, 1.0, 1.0]", "y = [0.0, 0.0, 1.0, 0.0]").replacen(
        "z = [0.0, 0.0, 0.0, 1.0]",
        "z = [0.0, 0.0, 0.0, 0.0]",
        1,
    );
    assert_invalid_toml(&coincide, "elements", Some(1));
}

#[test]
fn non_finite_numbers_in_toml() {
    // TOML has nan and inf float literals: they parse and must be rejected.
    assert_invalid_toml(
        &base_with("x = [0.0, 1.0, 0.0, 1.0]", "x = [0.0, 1.0, nan, 1.0]"),
        "nodes.x",
        Some(2),
    );
    assert_invalid_toml(
        &base_with("y = [0.0, 0.0, 1.0, 1.0]", "y = [0.0, 0.0, 1.0, -inf]"),
        "nodes.y",
        Some(3),
    );
    assert_invalid_toml(
        &base_with("z = [0.0, 0.0, 0.0, 1.0]", "z = [+inf, 0.0, 0.0, 1.0]"),
        "nodes.z",
        Some(0),
    );
    assert_invalid_toml(
        &base_with("ea = [1000.0, 1000.0, 100.0]", "ea = [1000.0, inf, 100.0]"),
        "elements.ea",
        Some(1),
    );
    assert_invalid_toml(
        &base_with("t0 = [0.0, 0.0, 1.0]", "t0 = [0.0, 0.0, nan]"),
        "elements.t0",
        Some(2),
    );
    assert_invalid_toml(&base_with("fx = [0.0]", "fx = [-nan]"), "loads.fx", Some(0));
    assert_invalid_toml(&base_with("fz = [-1.0]", "fz = [inf]"), "loads.fz", Some(0));
}

#[test]
fn non_finite_numbers_from_builder_and_json() {
    let mut s = builder_scene();
    s.nodes.y[1] = f64::NAN;
    assert_invalid(&s, "nodes.y", Some(1));
    let mut s = builder_scene();
    s.loads.fy[0] = f64::INFINITY;
    assert_invalid(&s, "loads.fy", Some(0));
    let mut b = SceneBuilder::new("nan");
    let a = b.node(0.0, 0.0, 0.0);
    let c = b.node(1.0, 0.0, 0.0);
    b.cable(a, c, 1.0);
    b.prestress(0, f64::NEG_INFINITY);
    match b.build_validated() {
        Err(Error::InvalidInput { field, index, .. }) => assert_eq!((field.as_str(), index), ("elements.t0", Some(0))),
        other => panic!("{other:?}"),
    }
    // JSON has no literal for them: a scene that tries is a parse error, and
    // an overflowing number is one too (never a silent infinity).
    let j = builder_scene().to_json_string().unwrap();
    let bad = j.replacen("\"x\": [\n      0.0", "\"x\": [\n      NaN", 1);
    assert_ne!(bad, j);
    parse_error(Scene::from_json_str(&bad));
    let big = j.replacen("\"x\": [\n      0.0", "\"x\": [\n      1e999", 1);
    match Scene::from_json_str(&big) {
        Err(Error::Parse(_)) => {}
        Ok(s) => assert_invalid(&s, "nodes.x", Some(0)),
        Err(e) => panic!("{e:?}"),
    }
}

#[test]
fn negative_or_zero_ea() {
    assert_invalid_toml(
        &base_with("ea = [1000.0, 1000.0, 100.0]", "ea = [1000.0, 1000.0, 0.0]"),
        "elements.ea",
        Some(2),
    );
    assert_invalid_toml(
        &base_with("ea = [1000.0, 1000.0, 100.0]", "ea = [1000.0, -1.0, 100.0]"),
        "elements.ea",
        Some(1),
    );
    assert_invalid_toml(
        &base_with("ea = [1000.0, 1000.0, 100.0]", "ea = [-0.0, 1.0, 100.0]"),
        "elements.ea",
        Some(0),
    );
}

#[test]
fn unknown_kind_effect_and_fields_are_parse_errors() {
    let m = parse_error(Scene::from_toml_str(&base_with(
        r#""bar", "bar", "cable""#,
        r#""bar", "rope", "cable""#,
    )));
    assert!(m.contains("rope"), "{m}");
    let m = parse_error(Scene::from_toml_str(&base_with(
        "[nodes]",
        "[effects]\nthermal = true\n\n[nodes]",
    )));
    assert!(m.contains("thermal"), "{m}");
    let m = parse_error(Scene::from_toml_str(&base_with(
        "[nodes]",
        "[solver]\nmethod = \"magic\"\n\n[nodes]",
    )));
    assert!(m.contains("magic"), "{m}");
    // Same in JSON.
    let j = builder_scene().to_json_string().unwrap();
    let m = parse_error(Scene::from_json_str(&j.replacen("\"cable\"", "\"chain\"", 1)));
    assert!(m.contains("chain"), "{m}");
    let m = parse_error(Scene::from_json_str(&j.replacen("\"prestress\"", "\"creep\"", 1)));
    assert!(m.contains("creep"), "{m}");
}

#[test]
fn unknown_dof_letter() {
    assert_invalid_toml(
        &base_with(r#"dofs = ["xyz", "xyz", "xyz"]"#, r#"dofs = ["xyz", "xw", "xyz"]"#),
        "supports.dofs",
        Some(1),
    );
    assert_invalid_toml(
        &base_with(r#"dofs = ["xyz", "xyz", "xyz"]"#, r#"dofs = ["xyz", "xyz", "X"]"#),
        "supports.dofs",
        Some(2),
    );
    assert_invalid_toml(
        &base_with(r#"dofs = ["xyz", "xyz", "xyz"]"#, r#"dofs = ["", "xyz", "xyz"]"#),
        "supports.dofs",
        Some(0),
    );
}

#[test]
fn errors_are_reported_without_touching_anything() {
    // Validation is read-only: the scene is unchanged after an error.
    let s = toml(&base_with("ea = [1000.0, 1000.0, 100.0]", "ea = [1000.0, 1000.0, 0.0]"));
    let before = s.clone();
    assert!(s.validate().is_err());
    assert_eq!(s, before);
    let msg = s.validate().unwrap_err().to_string();
    assert!(msg.contains("elements.ea[2]"), "{msg}");
}

// ---------------------------------------------------------------- mechanisms

#[test]
fn free_node_without_element_is_a_mechanism_naming_it() {
    let text = base_with("x = [0.0, 1.0, 0.0, 1.0]", "x = [0.0, 1.0, 0.0, 1.0, 5.0]")
        .replacen("y = [0.0, 0.0, 1.0, 1.0]", "y = [0.0, 0.0, 1.0, 1.0, 5.0]", 1)
        .replacen("z = [0.0, 0.0, 0.0, 1.0]", "z = [0.0, 0.0, 0.0, 1.0, 5.0]", 1);
    let s = toml(&text);
    s.validate().unwrap();
    match Model::from_scene(&s) {
        Err(Error::Mechanism(m)) => assert!(m.contains("node 4"), "{m}"),
        other => panic!("expected a mechanism naming node 4, got {other:?}"),
    }
    // Partly supported is still a mechanism; fully supported is fine.
    let partly = text.replacen(
        "node = [0, 1, 2]\ndofs = [\"xyz\", \"xyz\", \"xyz\"]",
        "node = [0, 1, 2, 4]\ndofs = [\"xyz\", \"xyz\", \"xyz\", \"xy\"]",
        1,
    );
    assert_ne!(partly, text);
    assert!(matches!(Model::from_scene(&toml(&partly)), Err(Error::Mechanism(m)) if m.contains("node 4")));
    let fully = partly.replacen("\"xy\"]", "\"xyz\"]", 1);
    Model::from_scene(&toml(&fully)).unwrap();
}

// ---------------------------------------------------------------- reference scenes

#[test]
fn reference_scenes_parse_and_validate() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/reference");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().and_then(|e| e.to_str()) != Some("toml") {
            continue;
        }
        let s = Scene::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        s.validate().unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let m = Model::from_scene(&s).unwrap();
        assert!(m.n_free > 0);
        assert_round_trips(&s);
        n += 1;
    }
    assert!(n >= 2, "expected the reference scenes in {}", dir.display());
}

/// The example of docs/scene-format.md: its TOML and JSON versions are the
/// same scene, and solving it gives the values the document explains.
#[test]
fn scene_format_document_example_is_true() {
    let doc = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("docs/scene-format.md")).unwrap();
    let block = |fence: &str| {
        let start = doc.find(fence).unwrap_or_else(|| panic!("no {fence} block")) + fence.len();
        let len = doc[start..].find("```").unwrap();
        doc[start..start + len].to_string()
    };
    let from_toml = toml(&block("```toml\n"));
    let from_json = Scene::from_json_str(&block("```json\n")).unwrap();
    assert_eq!(from_toml, from_json);
    assert_round_trips(&from_toml);
    for method in [Method::Direct, from_toml.solver.method] {
        let mut o = nsdd::solve::SolveOptions::from_scene(&from_toml);
        o.method = method;
        let r = nsdd::solve::solve(&from_toml, &o).unwrap();
        assert!(r.converged);
        assert_eq!(r.slack, [true, false, false]);
        let want_t = [0.0, 3.0, -1.0];
        let want_u1 = [-0.02, -0.001, 0.0];
        for e in 0..3 {
            assert!((r.tensions[e] - want_t[e]).abs() < 1e-9, "{method:?}: {:?}", r.tensions);
            assert!(
                (r.displacements[1][e] - want_u1[e]).abs() < 1e-11,
                "{method:?}: {:?}",
                r.displacements
            );
        }
    }
}

#[test]
fn bundled_scenes_parse_and_validate() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes");
    for (file, _) in generate::bundled() {
        let s = Scene::load(&dir.join(file)).unwrap_or_else(|e| panic!("{file}: {e}"));
        s.validate().unwrap();
        Model::from_scene(&s).unwrap();
    }
}

// ---------------------------------------------------------------- VTK output

/// Checks that `xml` is well formed as far as a `.vtu`/`.pvd` needs (one
/// declaration, balanced and properly nested tags, quoted attributes) and
/// returns the start tags in document order.
fn xml_tags(xml: &str) -> Vec<String> {
    assert!(xml.starts_with("<?xml version=\"1.0\"?>\n"));
    let body = &xml["<?xml version=\"1.0\"?>\n".len()..];
    let mut stack: Vec<String> = Vec::new();
    let mut starts = Vec::new();
    let mut rest = body;
    while let Some(i) = rest.find('<') {
        let text = &rest[..i];
        assert!(
            !text.contains('>') && !text.contains('&'),
            "stray markup in text: {text:?}"
        );
        let j = rest[i..].find('>').expect("unclosed tag") + i;
        let tag = &rest[i + 1..j];
        assert!(!tag.contains('<'), "nested '<' in tag {tag:?}");
        assert_eq!(tag.matches('"').count() % 2, 0, "unbalanced quotes in {tag:?}");
        if let Some(name) = tag.strip_prefix('/') {
            assert_eq!(stack.pop().as_deref(), Some(name), "mismatched </{name}>");
        } else {
            let name = tag.split_whitespace().next().unwrap().trim_end_matches('/').to_string();
            if !tag.ends_with('/') {
                stack.push(name.clone());
            }
            starts.push(tag.to_string());
        }
        rest = &rest[j + 1..];
    }
    assert!(rest.trim().is_empty());
    assert!(stack.is_empty(), "unclosed tags {stack:?}");
    starts
}

fn attr<'a>(tag: &'a str, name: &str) -> Option<&'a str> {
    let key = format!(" {name}=\"");
    let i = tag.find(&key)? + key.len();
    Some(&tag[i..i + tag[i..].find('"')?])
}

/// The whitespace-separated values of the `<DataArray Name="name">`.
fn data_array(xml: &str, name: &str) -> Vec<String> {
    let key = format!("Name=\"{name}\"");
    let i = xml.find(&key).unwrap_or_else(|| panic!("no DataArray {name}"));
    let start = i + xml[i..].find('>').unwrap() + 1;
    let end = start + xml[start..].find("</DataArray>").unwrap();
    xml[start..end].split_whitespace().map(str::to_string).collect()
}

fn floats(xml: &str, name: &str) -> Vec<f64> {
    data_array(xml, name)
        .iter()
        .map(|v| v.parse().unwrap_or_else(|_| panic!("{name}: '{v}'")))
        .collect()
}

fn ints(xml: &str, name: &str) -> Vec<i64> {
    data_array(xml, name)
        .iter()
        .map(|v| v.parse().unwrap_or_else(|_| panic!("{name}: '{v}'")))
        .collect()
}

/// A model with displacements, tensions, slack flags and subdomains.
type VtkCase = (Model, Vec<[f64; 3]>, Vec<f64>, Vec<bool>, Vec<usize>);

fn vtk_case() -> VtkCase {
    let scene = generate::grid(&GridParams {
        nx: 2,
        ny: 3,
        ..Default::default()
    });
    let model = Model::from_scene(&scene).unwrap();
    let special = [0.0, -0.0, 1e-300, -2.5e300, 1.0 / 3.0, 0.1 + 0.2, -7.0, 123456.789];
    let disp: Vec<[f64; 3]> = (0..model.coords.len())
        .map(|i| [special[i % 8], special[(i + 3) % 8] * 0.5, -(i as f64) / 7.0])
        .collect();
    let m = model.elements.len();
    let tensions: Vec<f64> = (0..m)
        .map(|e| if e % 3 == 0 { 0.0 } else { special[e % 8] + e as f64 })
        .collect();
    let slack: Vec<bool> = (0..m).map(|e| e % 3 == 0).collect();
    let sub: Vec<usize> = (0..m).map(|e| e * 4 / m).collect();
    (model, disp, tensions, slack, sub)
}

#[test]
fn vtu_is_well_formed_and_reads_back() {
    let (model, disp, tensions, slack, sub) = vtk_case();
    let xml = nsdd::vtk::to_vtu_string(&model, &disp, &tensions, &slack, Some(&sub)).unwrap();
    let tags = xml_tags(&xml);
    assert_eq!(tags.iter().filter(|t| t.starts_with("DataArray")).count(), 9);
    assert_eq!(xml.matches("</DataArray>").count(), 9);
    let piece = tags.iter().find(|t| t.starts_with("Piece")).unwrap();
    let (n, m) = (model.coords.len(), model.elements.len());
    assert_eq!(attr(piece, "NumberOfPoints"), Some(n.to_string().as_str()));
    assert_eq!(attr(piece, "NumberOfCells"), Some(m.to_string().as_str()));
    assert_eq!(attr(&tags[0], "type"), Some("UnstructuredGrid"));

    let pts = floats(&xml, "Points");
    assert_eq!(pts, model.coords.iter().flatten().copied().collect::<Vec<_>>());
    let d = floats(&xml, "displacement");
    let expected: Vec<f64> = disp.iter().flatten().copied().collect();
    assert_eq!(d.len(), 3 * n);
    for (x, y) in d.iter().zip(&expected) {
        assert_eq!(x.to_bits(), y.to_bits(), "{x} vs {y}");
    }
    assert_eq!(floats(&xml, "tension"), tensions);
    assert_eq!(ints(&xml, "slack"), slack.iter().map(|&s| s as i64).collect::<Vec<_>>());
    assert_eq!(
        ints(&xml, "subdomain"),
        sub.iter().map(|&s| s as i64).collect::<Vec<_>>()
    );
    let kinds: Vec<i64> = model
        .elements
        .iter()
        .map(|e| (e.kind == ElementKind::Cable) as i64)
        .collect();
    assert_eq!(ints(&xml, "kind"), kinds);
    let conn: Vec<i64> = model.elements.iter().flat_map(|e| [e.a as i64, e.b as i64]).collect();
    assert_eq!(ints(&xml, "connectivity"), conn);
    assert_eq!(ints(&xml, "offsets"), (1..=m as i64).map(|e| 2 * e).collect::<Vec<_>>());
    assert_eq!(ints(&xml, "types"), vec![3; m]);

    // Without a decomposition every element is in subdomain 0.
    let xml0 = nsdd::vtk::to_vtu_string(&model, &disp, &tensions, &slack, None).unwrap();
    assert_eq!(ints(&xml0, "subdomain"), vec![0; m]);

    // The file writer writes exactly the string.
    let dir = std::env::temp_dir().join(format!("nsdd-vtk-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("grid.vtu");
    nsdd::vtk::write_vtu(&path, &model, &disp, &tensions, &slack, Some(&sub)).unwrap();
    assert_eq!(std::fs::read_to_string(&path).unwrap(), xml);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn vtu_rejects_mismatched_arrays() {
    let (model, disp, tensions, slack, sub) = vtk_case();
    let field = |r: nsdd::Result<String>| match r {
        Err(Error::InvalidInput { field, .. }) => field,
        other => panic!("{other:?}"),
    };
    assert_eq!(
        field(nsdd::vtk::to_vtu_string(&model, &disp[1..], &tensions, &slack, None)),
        "displacements"
    );
    assert_eq!(
        field(nsdd::vtk::to_vtu_string(&model, &disp, &tensions[1..], &slack, None)),
        "tensions"
    );
    assert_eq!(
        field(nsdd::vtk::to_vtu_string(&model, &disp, &tensions, &slack[1..], None)),
        "slack"
    );
    assert_eq!(
        field(nsdd::vtk::to_vtu_string(
            &model,
            &disp,
            &tensions,
            &slack,
            Some(&sub[1..])
        )),
        "subdomain"
    );
    let missing = std::env::temp_dir().join("nsdd-no-such-dir-for-vtk").join("x.vtu");
    assert!(matches!(
        nsdd::vtk::write_vtu(&missing, &model, &disp, &tensions, &slack, None),
        Err(Error::Io(m)) if m.contains("x.vtu")
    ));
}

#[test]
fn pvd_series_is_well_formed() {
    let steps = vec![
        (0.25, "step-1.vtu".to_string()),
        (0.5, "a&b <2>.vtu".to_string()),
        (1.0, "s\"3\".vtu".into()),
    ];
    let xml = nsdd::vtk::to_pvd_string(&steps).unwrap();
    let tags = xml_tags(&xml);
    assert_eq!(attr(&tags[0], "type"), Some("Collection"));
    let sets: Vec<&String> = tags.iter().filter(|t| t.starts_with("DataSet")).collect();
    assert_eq!(sets.len(), 3);
    let times: Vec<f64> = sets
        .iter()
        .map(|t| attr(t, "timestep").unwrap().parse().unwrap())
        .collect();
    assert_eq!(times, vec![0.25, 0.5, 1.0]);
    assert_eq!(attr(sets[1], "file"), Some("a&amp;b &lt;2&gt;.vtu"));
    assert_eq!(attr(sets[2], "file"), Some("s&quot;3&quot;.vtu"));
    assert!(matches!(
        nsdd::vtk::to_pvd_string(&[(0.0, "a".into()), (f64::NAN, "b".into())]),
        Err(Error::InvalidInput { index: Some(1), .. })
    ));
    let dir = std::env::temp_dir().join(format!("nsdd-pvd-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("series.pvd");
    nsdd::vtk::write_pvd_series(&path, &steps).unwrap();
    assert_eq!(std::fs::read_to_string(&path).unwrap(), xml);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `[solver] macro_degree`: `"auto"` (the default) is not written, 1 to
/// 6 are read back, anything else is refused naming the field.
#[test]
fn macro_degree_round_trips_and_refuses_other_values() {
    use nsdd::settings::MacroDegree;
    let mut scene = Scene::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("scenes/grid-8x8.toml")).unwrap();
    assert_eq!(scene.solver.macro_degree, MacroDegree::Auto);
    let plain = scene.to_toml_string().unwrap();
    assert!(!plain.contains("macro_degree"));
    for (v, text) in [
        (MacroDegree::Fixed(1), "macro_degree = 1"),
        (MacroDegree::Fixed(2), "macro_degree = 2"),
        (MacroDegree::Fixed(4), "macro_degree = 4"),
        (MacroDegree::Fixed(6), "macro_degree = 6"),
        (MacroDegree::Fixed(3), "macro_degree = 3"),
    ] {
        scene.solver.macro_degree = v;
        let toml = scene.to_toml_string().unwrap();
        assert!(toml.contains(text), "{text}");
        assert_eq!(Scene::from_toml_str(&toml).unwrap().solver.macro_degree, v);
    }
    let toml = scene.to_toml_string().unwrap();
    let auto = toml.replace("macro_degree = 3", "macro_degree = \"auto\"");
    assert_eq!(
        Scene::from_toml_str(&auto).unwrap().solver.macro_degree,
        MacroDegree::Auto
    );
    for bad in ["macro_degree = 7", "macro_degree = 0", "macro_degree = \"cubic\""] {
        let err = Scene::from_toml_str(&toml.replace("macro_degree = 3", bad))
            .unwrap_err()
            .to_string();
        assert!(err.contains("solver.macro_degree"), "{bad}: {err}");
    }
}
