//! End-to-end tests of the `nsdd` binary on small scenes: result files,
//! exit codes and messages, generation round trip, the accuracy and scaling
//! studies' CSV and SVG output.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use serde_json::Value;

fn nsdd(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_nsdd"))
        .args(args)
        .output()
        .expect("run nsdd")
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// A fresh, empty directory for one test.
fn tmp(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("cli-{name}"));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn reference_dir() -> PathBuf {
    root().join("tests/data/reference")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn ok(out: &Output) {
    assert!(
        out.status.success(),
        "status {:?}\nstdout:\n{}\nstderr:\n{}",
        out.status,
        text(&out.stdout),
        text(&out.stderr)
    );
}

fn read_json(p: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
}

fn flat_u(v: &Value) -> Vec<f64> {
    v["displacements"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|d| {
            d.as_array()
                .unwrap()
                .iter()
                .map(|x| x.as_f64().unwrap())
                .collect::<Vec<_>>()
        })
        .collect()
}

fn nums(v: &Value, key: &str) -> Vec<f64> {
    v[key].as_array().unwrap().iter().map(|x| x.as_f64().unwrap()).collect()
}

fn bools(v: &Value, key: &str) -> Vec<bool> {
    v[key]
        .as_array()
        .unwrap()
        .iter()
        .map(|x| x.as_bool().unwrap())
        .collect()
}

fn rel_err(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>().sqrt();
    let den: f64 = b.iter().map(|y| y * y).sum::<f64>().sqrt();
    num / den.max(f64::MIN_POSITIVE)
}

/// Displacements and tensions within `tol`, slack sets equal.
fn assert_matches(r: &Value, reference: &Value, tol: f64, what: &str) {
    let eu = rel_err(&flat_u(r), &flat_u(reference));
    let et = rel_err(&nums(r, "tensions"), &nums(reference, "tensions"));
    assert!(eu < tol, "{what}: displacement error {eu:e}");
    assert!(et < tol, "{what}: tension error {et:e}");
    assert_eq!(
        bools(r, "slack"),
        bools(reference, "slack"),
        "{what}: slack sets differ"
    );
}

fn assert_result_fields(v: &Value) {
    for key in [
        "scene",
        "method",
        "effects",
        "stages",
        "converged",
        "iterations",
        "subdomains",
        "displacements",
        "tensions",
        "slack",
        "history",
        "timings_s",
    ] {
        assert!(v.get(key).is_some(), "result lacks '{key}'");
    }
    assert!(v["timings_s"]["setup"].is_number() && v["timings_s"]["solve"].is_number());
    let h = &v["history"][0];
    assert!(h["iteration"].is_u64() && h["time_s"].is_number() && h["indicator"].is_number());
}

fn assert_svg(p: &Path) {
    let t = std::fs::read_to_string(p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
    let t = t.trim();
    assert!(
        t.starts_with("<svg") || t.starts_with("<?xml"),
        "{}: not an SVG",
        p.display()
    );
    assert!(t.ends_with("</svg>"), "{}: truncated SVG", p.display());
    assert!(
        t.contains("<polyline") || t.contains("<path") || t.contains("<circle"),
        "{}: nothing drawn",
        p.display()
    );
}

#[test]
fn solve_grid8_matches_direct_and_writes_outputs() {
    let d = tmp("grid8");
    let scene = root().join("scenes/grid-8x8.toml");
    let (ml, vtu) = (d.join("ml.json"), d.join("ml.vtu"));
    let out = nsdd(&["solve", s(&scene), "--out", s(&ml), "--vtk", s(&vtu), "--threads", "2"]);
    ok(&out);
    let stdout = text(&out.stdout);
    for word in ["multilevel", "converged", "max |u|", "slack", "stages"] {
        assert!(stdout.contains(word), "summary lacks '{word}':\n{stdout}");
    }
    assert!(
        text(&out.stderr).is_empty(),
        "stderr not empty when not a terminal:\n{}",
        text(&out.stderr)
    );
    let direct = d.join("direct.json");
    ok(&nsdd(&["solve", s(&scene), "--method", "direct", "--out", s(&direct)]));
    let (r, rd) = (read_json(&ml), read_json(&direct));
    assert_result_fields(&r);
    assert_eq!(r["method"], "multilevel");
    assert_eq!(r["subdomains"], 4);
    assert_eq!(r["converged"], true);
    assert!(r["stages"].as_array().unwrap().iter().any(|s| s == "coarse"));
    assert_eq!(rd["method"], "direct");
    assert_matches(&r, &rd, 1e-6, "grid-8x8 multilevel vs direct");
    let vt = std::fs::read_to_string(&vtu).unwrap();
    assert!(vt.starts_with("<?xml") && vt.contains("Name=\"subdomain\"") && vt.trim_end().ends_with("</VTKFile>"));
}

#[test]
fn grid4_slack_matches_reference() {
    let d = tmp("grid4");
    let scene = reference_dir().join("grid4-slack.toml");
    let reference: Value = read_json(&reference_dir().join("grid4-slack.ref.json"));
    // The scene's own settings (direct), then the multilevel method.
    let a = d.join("a.json");
    ok(&nsdd(&["solve", s(&scene), "--out", s(&a)]));
    assert_matches(&read_json(&a), &reference, 1e-6, "grid4-slack direct");
    let b = d.join("b.json");
    ok(&nsdd(&[
        "solve",
        s(&scene),
        "--method",
        "multilevel",
        "--subdomains",
        "4",
        "--tolerance",
        "1e-10",
        "--out",
        s(&b),
    ]));
    let rb = read_json(&b);
    assert_result_fields(&rb);
    assert_matches(&rb, &reference, 1e-6, "grid4-slack multilevel");
}

fn write_scene(dir: &Path, name: &str, body: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, body).unwrap();
    p
}

const TWO_BARS: &str = r#"
[nodes]
x = [0.0, 1.0, 2.0]
y = [0.0, 0.0, 0.0]
z = [0.0, 0.0, 0.0]
[elements]
a = [0, 1]
b = [1, 2]
kind = ["bar", "cable"]
ea = [100.0, EA1]
[supports]
node = [0, 1, 2]
dofs = [SUPPORTS]
[loads]
node = [1]
fx = [1.0]
"#;

#[test]
fn bad_scene_fails_naming_field_and_index_without_output() {
    let d = tmp("bad");
    let scene = write_scene(
        &d,
        "bad.toml",
        &TWO_BARS
            .replace("EA1", "-5.0")
            .replace("SUPPORTS", r#""xyz", "yz", "xyz""#),
    );
    let res = d.join("r.json");
    let out = nsdd(&["solve", s(&scene), "--out", s(&res)]);
    assert_eq!(out.status.code(), Some(2), "stderr: {}", text(&out.stderr));
    let err = text(&out.stderr);
    assert!(
        err.contains("elements.ea") && err.contains("[1]"),
        "message does not name elements.ea[1]: {err}"
    );
    assert!(!res.exists(), "a result file was written for a bad scene");

    // Unparsable file and missing file: bad input too.
    let junk = write_scene(&d, "junk.toml", "[nodes\nx = ");
    let out = nsdd(&["solve", s(&junk), "--out", s(&res)]);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out.stderr).contains("cannot parse"));
    let out = nsdd(&["solve", s(&d.join("missing.toml")), "--out", s(&res)]);
    assert_eq!(out.status.code(), Some(2));
    assert!(!res.exists());
}

/// Issue #20 item 3: a negative number after a numeric flag reached clap's
/// "unexpected argument '-1' found"; it must reach the flag's own check,
/// which names the flag, with the bad-input exit status.
#[test]
fn negative_flag_values_reach_the_flags_own_check() {
    let grid = root().join("scenes/grid-4x4-linear.toml");
    let g = s(&grid);
    let cases: &[(&[&str], &str)] = &[
        (
            &["solve", g, "--tolerance", "-1e-6"],
            "'--tolerance <T>': must be a positive number, got -1e-6",
        ),
        (
            &["solve", g, "--tolerance", "-1"],
            "'--tolerance <T>': must be a positive number",
        ),
        (
            &["solve", g, "--tolerance", "0"],
            "'--tolerance <T>': must be a positive number",
        ),
        (
            &["solve", g, "--search-direction", "-1"],
            "'--search-direction <D|auto>': must be a positive number",
        ),
        (
            &["solve", g, "--subdomains", "-2"],
            "'--subdomains <N|auto>': must be a whole number (0 = automatic) or \"auto\", got -2",
        ),
        (
            &["solve", g, "--max-iterations", "-5"],
            "'--max-iterations <K>': must be a whole number",
        ),
        (
            &["solve", g, "--threads", "-1"],
            "'--threads <N>': must be a whole number",
        ),
        (
            &["partition", g, "--subdomains", "-4"],
            "'--subdomains <N|auto>': must be a whole number",
        ),
        (
            &["accuracy", g, "--out", "unused", "--tolerances", "1e-2,-1e-3"],
            "'--tolerances <T,...>': must be a positive number, got -1e-3",
        ),
        (
            &["accuracy", g, "--out", "unused", "--samples", "-1"],
            "'--samples <N>': must be a whole number of at least 0",
        ),
        (
            &["scaling", "--out", "unused", "--tolerance", "-1e-6"],
            "'--tolerance <T>': must be a positive number",
        ),
        (
            &["bench", "direct", "--sizes", "4,-8"],
            "'--sizes <SIZES>': must be a whole number",
        ),
    ];
    for (args, want) in cases {
        let out = nsdd(args);
        let err = text(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{args:?}: {err}");
        assert!(err.contains(want), "{args:?}: expected {want:?} in\n{err}");
        assert!(!err.contains("unexpected argument"), "{args:?}: {err}");
    }
    assert!(!root().join("unused").exists());
}

/// Issue #20: three nodes in the x–z plane, node 1 held by two bars and so
/// free along y. The direct solver printed "component z" (the component
/// after the free one) and the multilevel one named no node at all.
#[test]
fn mechanism_message_names_the_free_node_and_component() {
    let scene = root().join("tests/data/vee-mechanism.toml");
    for (method, subdomains, want) in [
        ("direct", "1", "no stiffness at node 1 component y"),
        ("multilevel", "1", "largest at node 1, component y"),
        (
            "multilevel",
            "2",
            "subdomain 0 is not restrained by its interfaces (largest motion at node 1, component y)",
        ),
        ("cg", "2", "(largest motion at node 1, component y)"),
    ] {
        let out = nsdd(&["solve", s(&scene), "--method", method, "--subdomains", subdomains]);
        assert_eq!(out.status.code(), Some(3), "{method}: {}", text(&out.stderr));
        let err = text(&out.stderr);
        assert!(err.contains(want), "{method} on {subdomains}: {err}");
    }
}

#[test]
fn unsupported_structure_fails_naming_the_cause() {
    let d = tmp("mech");
    // Node 1 is free along x but node 2 is free in y and z: a mechanism.
    let scene = write_scene(
        &d,
        "mech.toml",
        &TWO_BARS
            .replace("EA1", "50.0")
            .replace("SUPPORTS", r#""xyz", "yz", "x""#),
    );
    let res = d.join("r.json");
    let out = nsdd(&["solve", s(&scene), "--out", s(&res)]);
    assert_eq!(out.status.code(), Some(3), "stderr: {}", text(&out.stderr));
    let err = text(&out.stderr);
    assert!(err.contains("no unique solution"), "cause not named: {err}");
    assert!(!res.exists());

    // Monolevel on a decomposition with floating subdomains: solved with
    // their kernel modes as its coarse space (it was refused before).
    let grid = root().join("scenes/grid-8x8.toml");
    let out = nsdd(&[
        "solve",
        s(&grid),
        "--method",
        "monolevel",
        "--subdomains",
        "4",
        "--out",
        s(&res),
    ]);
    assert_eq!(out.status.code(), Some(0), "stderr: {}", text(&out.stderr));
    let r = read_json(&res);
    assert_eq!(r["converged"], Value::Bool(true));
    assert!(
        r["stages"].as_array().unwrap().iter().any(|s| s == "kernel"),
        "{}",
        r["stages"]
    );
}

#[test]
fn unconverged_solve_writes_result_and_exits_5() {
    let d = tmp("unconverged");
    let grid = root().join("scenes/grid-8x8.toml");
    let res = d.join("r.json");
    let out = nsdd(&["solve", s(&grid), "--max-iterations", "3", "--out", s(&res)]);
    assert_eq!(out.status.code(), Some(5));
    assert!(text(&out.stderr).contains("not converged"));
    let r = read_json(&res);
    assert_eq!(r["converged"], false);
    assert_eq!(r["iterations"], 3);
}

/// The README's tower with cables 1e8 times softer than its bars
/// (`ea_cable=1e-4`) and cg on 4 subdomains, asked for 1e-17, gives up
/// (stalled) long before its iteration limit, on the round-off of its
/// tensions after its equilibrium corrections; the result and the message
/// say why, and a tiny limit is reported as such.
#[test]
fn unconverged_solve_names_its_stop_reason() {
    let d = tmp("stop-reason");
    let tower = d.join("tower.toml");
    ok(&nsdd(&[
        "gen",
        "tower",
        "nx=2",
        "ny=2",
        "nz=10",
        "unilateral=false",
        "ea_cable=1e-4",
        "--out",
        s(&tower),
    ]));
    let base = [
        "solve",
        s(&tower),
        "--method",
        "cg",
        "--subdomains",
        "4",
        "--tolerance",
        "1e-17",
    ];
    let res = d.join("r.json");
    let out = nsdd(&[&base[..], &["--out", s(&res)]].concat());
    assert_eq!(out.status.code(), Some(5));
    let err = text(&out.stderr);
    assert!(err.contains("not converged: stalled after"), "{err}");
    assert!(err.contains("(result written anyway)"), "{err}");
    let r = read_json(&res);
    assert_eq!(r["converged"], false);
    assert_eq!(r["status"], "stalled");
    let it = r["iterations"].as_u64().unwrap();
    assert!(it < 20000, "gave up before the limit: {it}");
    assert!(text(&out.stdout).contains("NO, stalled"));

    // Without --out nothing is written, and the message does not claim it.
    let out = nsdd(&base);
    assert_eq!(out.status.code(), Some(5));
    let err = text(&out.stderr);
    assert!(err.contains("stalled after"), "{err}");
    assert!(!err.contains("written"), "{err}");

    let res = d.join("r3.json");
    let out = nsdd(&[&base[..], &["--max-iterations", "3", "--out", s(&res)]].concat());
    assert_eq!(out.status.code(), Some(5));
    assert!(
        text(&out.stderr).contains("iteration limit reached after 3 iterations"),
        "{}",
        text(&out.stderr)
    );
    let r = read_json(&res);
    assert_eq!(r["status"], "iteration_limit");
    assert_eq!(r["iterations"], 3);

    // A converged run says so too.
    let res = d.join("ok.json");
    ok(&nsdd(&["solve", s(&tower), "--out", s(&res)]));
    assert_eq!(read_json(&res)["status"], "converged");
}

#[test]
fn gen_round_trip_and_help() {
    let d = tmp("gen");
    let toml = d.join("g.toml");
    let out = nsdd(&["gen", "grid", "nx=3", "ny=3", "--out", s(&toml)]);
    ok(&out);
    let res = d.join("g.json");
    ok(&nsdd(&["solve", s(&toml), "--out", s(&res)]));
    let r = read_json(&res);
    assert_eq!(r["displacements"].as_array().unwrap().len(), 16 + 9);
    // JSON by extension, solved with both methods. Prestressed, so that no
    // cable sits exactly at zero tension and zero elongation (there the
    // slack flag is a coin toss between methods).
    let json = d.join("scene.json");
    ok(&nsdd(&["gen", "grid", "nx=3", "ny=3", "t0=0.1", "--out", s(&json)]));
    let res1 = d.join("g1.json");
    ok(&nsdd(&["solve", s(&json), "--method", "direct", "--out", s(&res1)]));
    let r = read_json(&res1);
    let sc = read_json(&json);
    assert!(sc["nodes"]["x"].is_array());
    let res2 = d.join("g2.json");
    ok(&nsdd(&[
        "solve",
        s(&json),
        "--method",
        "multilevel",
        "--subdomains",
        "2",
        "--tolerance",
        "1e-10",
        "--out",
        s(&res2),
    ]));
    assert_matches(&read_json(&res2), &r, 1e-6, "generated grid multilevel vs direct");

    let help = text(&nsdd(&["gen", "--help"]).stdout);
    for word in ["grid", "tensegrity", "tower", "nx", "ea_cable"] {
        assert!(help.contains(word), "gen --help lacks '{word}':\n{help}");
    }
    let out = nsdd(&["gen", "grid", "nq=3", "--out", s(&d.join("x.toml"))]);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out.stderr).contains("nq"));
    let out = nsdd(&["gen", "dome"]);
    assert_eq!(out.status.code(), Some(2));
}

#[test]
fn load_path_writes_pvd_series() {
    let d = tmp("loadpath");
    let toml = d.join("g.toml");
    ok(&nsdd(&["gen", "grid", "nx=2", "ny=2", "--out", s(&toml)]));
    let mut t = std::fs::read_to_string(&toml).unwrap();
    t.push_str("\n[load_path]\nsteps = 3\n");
    std::fs::write(&toml, t).unwrap();
    let vtu = d.join("res.vtu");
    ok(&nsdd(&["solve", s(&toml), "--vtk", s(&vtu)]));
    assert!(vtu.exists());
    let pvd = std::fs::read_to_string(d.join("res.pvd")).unwrap();
    for k in 1..=3 {
        let name = format!("res-step{k:03}.vtu");
        assert!(pvd.contains(&name), "pvd lacks {name}");
        assert!(d.join(&name).exists());
    }
}

#[test]
fn partition_reports_quality_and_kernels() {
    let grid = root().join("scenes/grid-8x8.toml");
    let out = nsdd(&["partition", s(&grid), "--subdomains", "4", "--json"]);
    ok(&out);
    let v: Value = serde_json::from_str(&text(&out.stdout)).unwrap();
    assert_eq!(v["quality"]["subdomains"], 4);
    assert!(v["quality"]["interfaces"].as_u64().unwrap() > 0);
    assert_eq!(v["subdomains"].as_array().unwrap().len(), 4);
    assert!(!v["singular"].as_array().unwrap().is_empty());
    // Every factored subdomain reports its local mechanisms, at most its kernel.
    for sd in v["subdomains"].as_array().unwrap() {
        assert!(
            sd["mechanisms"].as_u64().unwrap() <= sd["kernel_dim"].as_u64().unwrap(),
            "{sd}"
        );
    }
    assert!(v.get("subdomains_after_merging").is_none(), "{v}");
    let out = nsdd(&["partition", s(&grid)]);
    ok(&out);
    assert!(text(&out.stdout).contains("singular subdomains"));
    assert!(text(&out.stdout).contains("kernel  mechanisms"));
}

/// The bundled tensegrity grid cut in 16 leaves subdomains indefinite on
/// their own: `nsdd partition` names them and says how many subdomains a
/// solve starts from once they are merged, which is what `multilevel`
/// then reports.
#[test]
fn partition_report_tells_what_merging_leaves() {
    let scene = root().join("scenes/tensegrity-2x2.toml");
    let out = nsdd(&["partition", s(&scene), "--subdomains", "16", "--json"]);
    ok(&out);
    let v: Value = serde_json::from_str(&text(&out.stdout)).unwrap();
    let after = v["subdomains_after_merging"].as_u64().expect("merging predicted");
    assert!((1..16).contains(&after), "{after}");
    let text_out = nsdd(&["partition", s(&scene), "--subdomains", "16"]);
    ok(&text_out);
    assert!(
        text(&text_out.stdout).contains(&format!("starts from {after} subdomain")),
        "{}",
        text(&text_out.stdout)
    );
    let d = tmp("merging");
    let result = d.join("r.json");
    ok(&nsdd(&[
        "solve",
        s(&scene),
        "--method",
        "multilevel",
        "--subdomains",
        "16",
        "--out",
        s(&result),
    ]));
    let r: Value = serde_json::from_str(&std::fs::read_to_string(&result).unwrap()).unwrap();
    assert_eq!(r["subdomains"].as_u64(), Some(after));
}

fn csv_rows(p: &Path) -> (String, Vec<Vec<String>>) {
    let t = std::fs::read_to_string(p).unwrap();
    let mut lines = t.lines();
    let header = lines.next().unwrap().to_string();
    (
        header,
        lines.map(|l| l.split(',').map(String::from).collect()).collect(),
    )
}

#[test]
fn accuracy_study_writes_csv_and_svgs() {
    let d = tmp("accuracy");
    let toml = d.join("g.toml");
    ok(&nsdd(&["gen", "grid", "nx=4", "ny=4", "t0=0.1", "--out", s(&toml)]));
    let out_dir = d.join("acc");
    let out = nsdd(&[
        "accuracy",
        s(&toml),
        "--out",
        s(&out_dir),
        "--subdomains",
        "2",
        "--samples",
        "8",
    ]);
    ok(&out);
    let (header, rows) = csv_rows(&out_dir.join("accuracy.csv"));
    assert!(
        header.starts_with("method,tolerance,error_u,error_t,slack_mismatch,iterations,seconds"),
        "header: {header}"
    );
    assert_eq!(rows.iter().filter(|r| r[0] == "direct").count(), 1);
    let ml: Vec<&Vec<String>> = rows.iter().filter(|r| r[0] == "multilevel").collect();
    assert_eq!(ml.len(), 9, "one multilevel row per decade 1e-2..1e-10");
    let err = |tol: &str| {
        let r = ml
            .iter()
            .find(|r| r[1].parse::<f64>().unwrap() == tol.parse::<f64>().unwrap())
            .unwrap();
        r[2].parse::<f64>().unwrap().max(r[3].parse::<f64>().unwrap())
    };
    assert!(
        err("1e-10") < err("1e-2"),
        "error does not decrease: {} vs {}",
        err("1e-10"),
        err("1e-2")
    );
    assert!(err("1e-10") < 1e-6);
    for r in &ml {
        assert!(r[6].parse::<f64>().unwrap() > 0.0);
    }
    assert_svg(&out_dir.join("accuracy.svg"));
    let (hh, hrows) = csv_rows(&out_dir.join("history-multilevel.csv"));
    assert!(hh.starts_with("iteration,time_s,indicator,error_u"));
    let sampled: Vec<f64> = hrows
        .iter()
        .filter(|r| !r[3].is_empty())
        .map(|r| r[3].parse().unwrap())
        .collect();
    assert!(sampled.len() >= 3 && sampled.len() <= 8, "{} samples", sampled.len());
    assert!(sampled.last().unwrap() < sampled.first().unwrap());
    assert_svg(&out_dir.join("history-multilevel.svg"));
    // The repaired bisection leaves both halves regular here, so monolevel
    // runs too, with its own rows and history.
    let mono: Vec<&Vec<String>> = rows.iter().filter(|r| r[0] == "monolevel").collect();
    assert_eq!(mono.len(), 9, "{}", text(&out.stdout));
    assert_svg(&out_dir.join("history-monolevel.svg"));
    // On a floating split it is skipped with a note instead.
    let out = nsdd(&[
        "accuracy",
        s(&toml),
        "--out",
        s(&d.join("acc8")),
        "--subdomains",
        "8",
        "--samples",
        "4",
    ]);
    ok(&out);
    let (_, rows8) = csv_rows(&d.join("acc8").join("accuracy.csv"));
    let mono8 = rows8.iter().filter(|r| r[0] == "monolevel").count();
    assert!(
        mono8 == 9 || text(&out.stdout).contains("monolevel skipped"),
        "{}",
        text(&out.stdout)
    );
}

#[test]
fn scaling_study_writes_csv_and_svg() {
    let d = tmp("scaling");
    let out = nsdd(&[
        "scaling",
        "--sizes",
        "2,4",
        "--subdomains",
        "2,4",
        "--tolerance",
        "1e-6",
        "--out",
        s(&d),
    ]);
    ok(&out);
    let (header, rows) = csv_rows(&d.join("scaling.csv"));
    assert!(header.starts_with("study,size,subdomains,method"), "{header}");
    let ml: Vec<&Vec<String>> = rows.iter().filter(|r| r[3] == "multilevel").collect();
    assert_eq!(ml.iter().filter(|r| r[0] == "strong").count(), 2);
    assert_eq!(ml.iter().filter(|r| r[0] == "weak").count(), 2);
    assert!(ml.iter().all(|r| r[6].parse::<usize>().unwrap() > 0 && r[7] == "true"));
    // Monolevel rows exist: run, or skipped with a reason.
    assert!(rows
        .iter()
        .filter(|r| r[3] == "monolevel")
        .all(|r| !r[6].is_empty() || r.len() > 12 && !r[12].is_empty()));
    assert_svg(&d.join("scaling.svg"));
}

/// `--preconditioner` reaches the CG: both choices match the direct
/// solution, along different iterations; a bad value is exit 2.
#[test]
fn cg_preconditioner_flag() {
    let d = tmp("cg-precond");
    let scene = d.join("g.toml");
    ok(&nsdd(&[
        "gen",
        "grid",
        "nx=12",
        "ny=12",
        "unilateral=false",
        "--out",
        s(&scene),
    ]));
    let direct = d.join("direct.json");
    ok(&nsdd(&["solve", s(&scene), "--method", "direct", "--out", s(&direct)]));
    let rd = read_json(&direct);
    // cg with `flag value`, checked against the direct solution; its iterations.
    let cg_with = |flag: &str, value: &str| -> u64 {
        let out = d.join(format!("{value}.json"));
        ok(&nsdd(&[
            "solve",
            s(&scene),
            "--method",
            "cg",
            "--subdomains",
            "4",
            "--tolerance",
            "1e-9",
            flag,
            value,
            "--out",
            s(&out),
        ]));
        let r = read_json(&out);
        assert_matches(&r, &rd, 1e-7, value);
        r["iterations"].as_u64().unwrap()
    };
    let iterations: Vec<u64> = ["dirichlet", "lumped"]
        .iter()
        .map(|p| cg_with("--preconditioner", p))
        .collect();
    assert_ne!(iterations[0], iterations[1]);
    // --interface-scaling reaches it too: each value matches the direct
    // solution, economic deluxe (the default, the exact deluxe weights on
    // subdomains this small) in fewer iterations than contrast.
    let its: Vec<u64> = ["economic_deluxe", "deluxe", "contrast", "multiplicity"]
        .iter()
        .map(|k| cg_with("--interface-scaling", k))
        .collect();
    assert_eq!(its[0], iterations[0], "economic_deluxe is the default");
    assert_eq!(its[0], its[1], "exact blocks on small subdomains");
    assert!(its[0] < its[2], "deluxe {} vs contrast {}", its[0], its[2]);
    let out = nsdd(&["solve", s(&scene), "--method", "cg", "--interface-scaling", "rho"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        text(&out.stderr).contains("none, multiplicity, stiffness, contrast, deluxe or economic_deluxe"),
        "{}",
        text(&out.stderr)
    );
    let out = nsdd(&["solve", s(&scene), "--method", "cg", "--preconditioner", "jacobi"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        text(&out.stderr).contains("dirichlet or lumped"),
        "{}",
        text(&out.stderr)
    );
}

/// Issue #20 item 4: a generated scene leaves the subdomain count unset,
/// and `solve --method multilevel` without `--subdomains` chooses it from
/// the size and the thread count (`max(threads, ceil(free dofs / 8000))`,
/// at least 2, at most elements / 16), says so, and matches the direct
/// solution. Before, generated scenes said `subdomains = 1` and the
/// "multilevel" run had no interface at all.
#[test]
fn automatic_subdomain_count() {
    let d = tmp("auto-subdomains");
    let scene = d.join("g.toml");
    ok(&nsdd(&["gen", "grid", "nx=8", "ny=8", "--out", s(&scene)]));
    let body = std::fs::read_to_string(&scene).unwrap();
    assert!(!body.contains("subdomains"), "generated scene sets a count:\n{body}");
    let direct = d.join("direct.json");
    ok(&nsdd(&["solve", s(&scene), "--method", "direct", "--out", s(&direct)]));
    let rd = read_json(&direct);
    // 625 elements, 339 free dofs: the thread count decides (3 ≤ 625/16).
    for extra in [&[][..], &["--subdomains", "auto"][..], &["--subdomains", "0"][..]] {
        let out_json = d.join("ml.json");
        let mut args = vec!["--threads", "3", "solve", s(&scene), "--method", "multilevel"];
        args.extend_from_slice(extra);
        args.extend_from_slice(&["--tolerance", "1e-10", "--out", s(&out_json)]);
        let out = nsdd(&args);
        ok(&out);
        let stdout = text(&out.stdout);
        assert!(stdout.contains("multilevel (3 subdomains"), "{extra:?}:\n{stdout}");
        assert!(
            stdout.contains("subdomains: 3, chosen automatically from 339 free dofs, 625 elements and 3 threads"),
            "{extra:?}:\n{stdout}"
        );
        assert!(!text(&out.stderr).contains("warning"), "{}", text(&out.stderr));
        let r = read_json(&out_json);
        assert_eq!(r["subdomains"], 3);
        assert!(r["stages"].as_array().unwrap().iter().any(|s| s == "interface"));
        assert!(r["notes"]
            .as_array()
            .unwrap()
            .iter()
            .any(|n| n.as_str().unwrap().contains("chosen automatically")));
        assert_matches(&r, &rd, 1e-6, "automatic count vs direct");
    }
    // An explicit count is kept and not called automatic.
    let out = nsdd(&["solve", s(&scene), "--method", "multilevel", "--subdomains", "4"]);
    ok(&out);
    assert!(text(&out.stdout).contains("multilevel (4 subdomains"));
    assert!(!text(&out.stdout).contains("chosen automatically"));
}

/// An extreme count (most free dofs on interfaces) runs but warns on
/// stderr, with the interface fraction and the count; the result's notes
/// carry the warning too. A sensible count does not warn.
#[test]
fn extreme_subdomain_count_warns() {
    let d = tmp("extreme-subdomains");
    let scene = d.join("g.toml");
    ok(&nsdd(&["gen", "grid", "nx=4", "ny=4", "--out", s(&scene)]));
    let r = d.join("r.json");
    let out = nsdd(&[
        "solve",
        s(&scene),
        "--method",
        "multilevel",
        "--subdomains",
        "40",
        "--out",
        s(&r),
    ]);
    ok(&out);
    let err = text(&out.stderr);
    assert!(
        err.contains("warning: 100% of the free dofs (75 of 75) are on interfaces with 40 subdomains"),
        "{err}"
    );
    assert!(
        !text(&out.stdout).contains("warning"),
        "the warning goes to stderr only"
    );
    let notes = read_json(&r)["notes"].clone();
    assert!(notes
        .as_array()
        .unwrap()
        .iter()
        .any(|n| n.as_str().unwrap().starts_with("warning: 100%")));
    let out = nsdd(&["solve", s(&scene), "--method", "multilevel", "--subdomains", "2"]);
    ok(&out);
    assert!(!text(&out.stderr).contains("warning"), "{}", text(&out.stderr));
}

/// The command line's results do not depend on the thread count: faer's
/// dense kernels run sequentially (parallelism goes over subdomains). The
/// 80² plate on 16 subdomains took 69 iterations on one thread and 76 on
/// two before.
#[test]
fn results_do_not_depend_on_the_thread_count() {
    let d = tmp("threads");
    let scene = d.join("plate.toml");
    ok(&nsdd(&[
        "gen",
        "grid",
        "nx=80",
        "ny=80",
        "unilateral=false",
        "t0=0",
        "--out",
        s(&scene),
    ]));
    let run = |threads: &str| -> Value {
        let out = d.join(format!("r{threads}.json"));
        let o = Command::new(env!("CARGO_BIN_EXE_nsdd"))
            .args([
                "--threads",
                threads,
                "solve",
                s(&scene),
                "--method",
                "cg",
                "--subdomains",
                "16",
            ])
            .args(["--tolerance", "1e-8", "--out", s(&out)])
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", text(&o.stderr));
        serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap()
    };
    let (one, two) = (run("1"), run("2"));
    assert_eq!(one["iterations"], two["iterations"]);
    assert_eq!(one["displacements"], two["displacements"], "the same bits");
    assert_eq!(one["tensions"], two["tensions"]);
}

/// `--adaptive-threshold` on the README's tower: cg converges in a handful
/// of iterations, the result notes the columns added and times the set-up
/// phases (a direct solve has none); a threshold of at most 1 is refused,
/// naming the field.
#[test]
fn adaptive_threshold_flag_and_setup_phases() {
    let d = tmp("adaptive");
    let tower = d.join("tower.toml");
    ok(&nsdd(&[
        "gen",
        "tower",
        "nx=2",
        "ny=2",
        "nz=10",
        "unilateral=false",
        "--out",
        s(&tower),
    ]));
    let res = d.join("r.json");
    let out = nsdd(&[
        "solve",
        s(&tower),
        "--method",
        "cg",
        "--subdomains",
        "4",
        "--adaptive-threshold",
        "10",
        "--out",
        s(&res),
    ]);
    ok(&out);
    let stdout = text(&out.stdout);
    assert!(stdout.contains("setup       factor"), "{stdout}");
    let r = read_json(&res);
    assert_eq!(r["converged"], true);
    assert!(r["iterations"].as_u64().unwrap() <= 15, "{}", r["iterations"]);
    let notes: Vec<&str> = r["notes"]
        .as_array()
        .unwrap()
        .iter()
        .filter_map(|n| n.as_str())
        .collect();
    assert!(
        notes
            .iter()
            .any(|n| n.starts_with("adaptive macro space (threshold 10)")),
        "{notes:?}"
    );
    let t = &r["timings_s"];
    let phases = &t["setup_phases"];
    assert!(phases["adaptive"].as_f64().unwrap() > 0.0, "{t}");
    let phase = |k: &str| phases[k].as_f64().unwrap_or_else(|| panic!("setup_phases lacks {k}"));
    // The interiors and the deluxe blocks run beside the coarse problem's
    // factorization: each of the two lines of phases fits in the set-up.
    let setup = t["setup"].as_f64().unwrap();
    let serial = ["factor", "adaptive", "search_direction"]
        .map(phase)
        .iter()
        .sum::<f64>();
    assert!(serial + phase("coarse") <= setup, "{t}");
    assert!(serial + phase("interior") + phase("scaling") <= setup, "{t}");

    let res = d.join("direct.json");
    ok(&nsdd(&["solve", s(&tower), "--method", "direct", "--out", s(&res)]));
    assert!(read_json(&res)["timings_s"].get("setup_phases").is_none());

    let out = nsdd(&["solve", s(&tower), "--method", "cg", "--adaptive-threshold", "0.5"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        text(&out.stderr).contains("solver.adaptive_threshold"),
        "{}",
        text(&out.stderr)
    );

    // `--adaptive-edges` on a 3D contrast tower cut in 8 (edges shared by
    // 3-4 subdomains): constraints on them too, fewer iterations, the same
    // answer as direct; `--adaptive-edges false` gives the faces alone.
    let cube = d.join("cube.toml");
    ok(&nsdd(&[
        "gen",
        "tower",
        "nx=6",
        "ny=6",
        "nz=6",
        "unilateral=false",
        "--out",
        s(&cube),
    ]));
    let run = |edges: &str, name: &str| -> Value {
        let res = d.join(name);
        ok(&nsdd(&[
            "solve",
            s(&cube),
            "--method",
            "cg",
            "--subdomains",
            "8",
            "--adaptive-edges",
            edges,
            "--out",
            s(&res),
        ]));
        read_json(&res)
    };
    let (with, without) = (run("true", "edges.json"), run("false", "faces.json"));
    // "auto", the default, turns them on here (bars 1e4 × the cables).
    assert_eq!(run("auto", "auto.json")["displacements"], with["displacements"]);
    let bad = nsdd(&["solve", s(&cube), "--method", "cg", "--adaptive-edges", "sometimes"]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(text(&bad.stderr).contains("auto"), "{}", text(&bad.stderr));
    let note = |r: &Value| -> String {
        r["notes"]
            .as_array()
            .unwrap()
            .iter()
            .filter_map(|n| n.as_str())
            .find(|n| n.starts_with("adaptive macro space"))
            .unwrap_or_else(|| panic!("{}", r["notes"]))
            .to_string()
    };
    assert!(note(&without).contains(" and 0 on the edges"), "{}", note(&without));
    assert!(!note(&with).contains(" and 0 on the edges"), "{}", note(&with));
    let its = |r: &Value| r["iterations"].as_u64().unwrap();
    assert!(
        with["converged"] == true && 2 * its(&with) < its(&without),
        "{} vs {}",
        its(&with),
        its(&without)
    );
    let res = d.join("cube-direct.json");
    ok(&nsdd(&["solve", s(&cube), "--out", s(&res)]));
    let direct = read_json(&res);
    let flat = |v: &Value| -> Vec<f64> {
        v.as_array()
            .unwrap()
            .iter()
            .flat_map(|x| {
                x.as_array().map_or_else(
                    || vec![x.as_f64().unwrap()],
                    |a| a.iter().map(|y| y.as_f64().unwrap()).collect(),
                )
            })
            .collect()
    };
    let (a, b) = (flat(&with["tensions"]), flat(&direct["tensions"]));
    let err = a.iter().zip(&b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>().sqrt()
        / b.iter().map(|y| y * y).sum::<f64>().sqrt();
    assert!(err < 1e-7, "tensions {err:.2e} off direct");
}

#[test]
fn direct_analysis_predicts_the_factor_without_factoring() {
    let d = tmp("analyse");
    let tower = d.join("tower.toml");
    ok(&nsdd(&[
        "gen",
        "tower",
        "nx=8",
        "ny=8",
        "nz=8",
        "unilateral=false",
        "--out",
        s(&tower),
    ]));
    let json = |args: &[&str]| -> Value {
        let out = nsdd(args);
        ok(&out);
        serde_json::from_str(&text(&out.stdout)).unwrap()
    };
    let factored = json(&["bench", "direct", s(&tower), "--json"]);
    let analysed = json(&["bench", "direct", s(&tower), "--analyse", "--json"]);
    // The symbolic analysis is the factorization's own: same order, same fill.
    for key in ["dofs", "nnz_k", "nnz_l", "ordering"] {
        assert_eq!(analysed[key], factored[key], "{key}");
    }
    assert_eq!(analysed["ordering"], "nested_dissection");
    assert!(analysed.get("factor_s").is_none(), "the analysis does not factor");
    let bytes = analysed["matrix_and_factor_bytes"].as_u64().unwrap();
    assert!(bytes >= 8 * analysed["nnz_l"].as_u64().unwrap());
    // The flag belongs to the direct profile of a scene only.
    let out = nsdd(&["bench", "iteration", "--analyse"]);
    assert!(!out.status.success());
    assert!(text(&out.stderr).contains("--analyse"), "{}", text(&out.stderr));
}

/// `bench iteration --method cg` times the interface CG and puts every
/// interior factor's substitution into its bound (the Dirichlet
/// preconditioner solves with them once per iteration); the stationary
/// method's bound has none. A method the profile does not time is refused
/// by name.
#[test]
fn bench_iteration_times_cg_against_subdomain_and_interior_substitutions() {
    let bench_for = |method: &str, iterations: &str, out: &Path| {
        nsdd(&[
            "bench",
            "iteration",
            "--sizes",
            "12",
            "--subdomains",
            "4",
            "--iterations",
            iterations,
            "--method",
            method,
            "--out",
            s(out),
        ])
    };
    let bench = |method: &str, out: &Path| bench_for(method, "3", out);
    let rows_for = |method: &str, iterations: &str| -> Value {
        let out_path = tmp(&format!("bench-iteration-{method}-{iterations}")).join("rows.jsonl");
        ok(&bench_for(method, iterations, &out_path));
        let body = std::fs::read_to_string(&out_path).unwrap();
        serde_json::from_str(body.lines().next().unwrap()).unwrap()
    };
    let rows = |method: &str| rows_for(method, "3");
    let cg = rows("cg");
    assert_eq!(cg["method"], "cg");
    assert_eq!(cg["iterations_timed"], 3);
    // CG on 795 dofs reaches round-off long before 400 iterations: the time
    // is divided by the iterations it did, not by the 400 asked for.
    let long = rows_for("cg", "400");
    let timed = long["iterations_timed"].as_u64().unwrap();
    assert!(timed > 0 && timed < 400, "timed {timed} of 400 iterations");
    let (sub, int) = (
        cg["substitution_s"].as_f64().unwrap(),
        cg["interior_substitution_s"].as_f64().unwrap(),
    );
    assert!(int > 0.0 && sub > int, "bound {sub} with interiors {int}");
    // A time, not a speed: on 795 dofs one iteration is ~50 µs, and on a
    // busy machine the best of four iterations can come out no slower than
    // the best of one (the difference is then reported as 0).
    let it = cg["iteration_s"].as_f64().unwrap();
    assert!(it.is_finite() && it >= 0.0, "iteration_s {it}");
    // Both methods have a coarse problem here (the grid's 4 subdomains).
    let coarse = cg["coarse_solve_s"].as_f64().unwrap();
    assert!(coarse > 0.0 && coarse.is_finite(), "coarse_solve_s {coarse}");
    let ml = rows("multilevel");
    assert_eq!(ml["method"], "multilevel");
    assert_eq!(ml["interior_substitution_s"].as_f64(), Some(0.0));
    let out = bench("monolevel", &tmp("bench-iteration-monolevel").join("rows.jsonl"));
    assert!(!out.status.success());
    assert!(text(&out.stderr).contains("multilevel or cg"), "{}", text(&out.stderr));
}

/// Output piped into a reader that stops early (`nsdd gen ... | head`)
/// ends the process by SIGPIPE, as it does other command-line tools, not
/// with a panic on the failed write.
#[cfg(unix)]
#[test]
fn a_closed_pipe_ends_quietly() {
    use std::io::Read;
    use std::os::unix::process::ExitStatusExt;
    use std::process::Stdio;
    let mut child = Command::new(env!("CARGO_BIN_EXE_nsdd"))
        .args(["gen", "grid", "nx=80", "ny=80"])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("run nsdd");
    let mut head = [0u8; 64];
    child.stdout.take().unwrap().read_exact(&mut head).unwrap();
    // The read end is dropped here, the scene (megabytes) not yet written.
    let out = child.wait_with_output().unwrap();
    assert_eq!(out.status.signal(), Some(libc::SIGPIPE), "{:?}", out.status);
    assert!(!text(&out.stderr).contains("panicked"), "{}", text(&out.stderr));
}

/// `--ordering` picks the factorizations' fill-reducing ordering; the
/// summary and the result file say which ordering each factor got, and a
/// wrong value is refused with the valid ones.
#[test]
fn ordering_flag_reaches_the_factors_and_the_report() {
    let d = tmp("ordering");
    let scene = d.join("tower.toml");
    ok(&nsdd(&[
        "gen",
        "tower",
        "nx=10",
        "ny=10",
        "nz=10",
        "unilateral=false",
        "--out",
        s(&scene),
    ]));
    let mut nnz = Vec::new();
    for (flag, want) in [
        ("amd", "(nested dissection 0, amd 8)"),
        ("nested_dissection", "(nested dissection 8, amd 0)"),
    ] {
        let out = d.join(format!("{flag}.json"));
        let o = nsdd(&[
            "solve",
            s(&scene),
            "--method",
            "cg",
            "--subdomains",
            "4",
            "--ordering",
            flag,
            "--out",
            s(&out),
        ]);
        assert!(o.status.success(), "{}", text(&o.stderr));
        let stdout = text(&o.stdout);
        assert!(stdout.contains(want), "{stdout}");
        let r: Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
        nnz.push(r["factors"]["nnz_l"].as_u64().unwrap());
    }
    assert!(nnz[1] < nnz[0], "nested dissection fills less on a 3D tower: {nnz:?}");
    let o = nsdd(&["solve", s(&scene), "--ordering", "metis"]);
    assert!(!o.status.success());
    let err = text(&o.stderr);
    assert!(err.contains("nested_dissection") && err.contains("metis"), "{err}");
}

/// `--macro-degree 3` on a 16² plate cut in 16: fewer cg iterations than
/// degree 1, and the direct solver's answer; the default ("auto") keeps
/// degree 1 on this plate's small interfaces (at most 10 nodes), with its
/// bits, and says nothing of polynomial fields; a value other than 1, 2, 3
/// or auto is refused (exit code 2, naming the choices).
#[test]
fn macro_degree_flag_cuts_plate_iterations() {
    let d = tmp("macro-degree");
    let plate = d.join("plate.toml");
    ok(&nsdd(&[
        "gen",
        "grid",
        "nx=16",
        "ny=16",
        "unilateral=false",
        "t0=0",
        "--out",
        s(&plate),
    ]));
    let run = |extra: &[&str], name: &str| -> Value {
        let res = d.join(name);
        let mut args = vec!["solve", s(&plate), "--out", s(&res)];
        args.extend_from_slice(extra);
        ok(&nsdd(&args));
        read_json(&res)
    };
    let direct = run(&["--method", "direct"], "direct.json");
    let one = run(
        &["--method", "cg", "--subdomains", "16", "--macro-degree", "1"],
        "one.json",
    );
    let three = run(
        &["--method", "cg", "--subdomains", "16", "--macro-degree", "3"],
        "three.json",
    );
    let (i1, i3) = (
        one["iterations"].as_u64().unwrap(),
        three["iterations"].as_u64().unwrap(),
    );
    assert!(i3 < i1, "iterations: degree 1 {i1}, degree 3 {i3}");
    assert!(rel_err(&flat_u(&three), &flat_u(&direct)) < 1e-7);
    // The default ("auto") is 1 on these small interfaces; degree 3 says so.
    let default = run(&["--method", "cg", "--subdomains", "16"], "default.json");
    assert_eq!(default["displacements"], one["displacements"]);
    let says_degree = |r: &Value| {
        r["notes"]
            .as_array()
            .unwrap()
            .iter()
            .any(|n| n.as_str().unwrap().contains("polynomial fields up to degree 3"))
    };
    assert!(says_degree(&three), "{}", three["notes"]);
    assert!(!says_degree(&default) && !says_degree(&one), "{}", default["notes"]);
    let bad = nsdd(&["solve", s(&plate), "--method", "cg", "--macro-degree", "7"]);
    assert_eq!(bad.status.code(), Some(2));
    assert!(text(&bad.stderr).contains("auto"), "{}", text(&bad.stderr));
}
