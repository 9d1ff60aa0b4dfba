//! The automatic subdomain count (issue #20 item 4): `subdomains = 0`
//! (absent, `0` or `"auto"` in a scene, `--subdomains auto`,
//! `nsdd_options_set_subdomains_auto`) is resolved from the size and the
//! thread count in one place, `partition::resolve_subdomains`.

use nsdd::capi::*;
use nsdd::model::Model;
use nsdd::partition::resolve_subdomains;
use nsdd::scene::{Method, Scene};
use nsdd::solve::{auto_subdomains, solve, SolveOptions};
use std::ffi::CString;
use std::ptr::null_mut;

#[test]
fn the_rule() {
    // An explicit count is kept, even an extreme one.
    assert_eq!(resolve_subdomains(7, 100, 10, 2), 7);
    // max(threads, ceil(free / 8000)), at least 2 ...
    assert_eq!(resolve_subdomains(0, 3_000, 10_000, 1), 2);
    assert_eq!(resolve_subdomains(0, 3_000, 10_000, 2), 2);
    assert_eq!(resolve_subdomains(0, 3_000, 10_000, 6), 6);
    assert_eq!(resolve_subdomains(0, 100_000, 100_000, 2), 13);
    assert_eq!(resolve_subdomains(0, 16_000, 100_000, 2), 2);
    assert_eq!(resolve_subdomains(0, 16_001, 100_000, 2), 3);
    // ... at most elements / 16, and at least 1.
    assert_eq!(resolve_subdomains(0, 100_000, 160, 2), 10);
    assert_eq!(resolve_subdomains(0, 1_000, 625, 64), 39);
    assert_eq!(resolve_subdomains(0, 30, 40, 2), 2);
    assert_eq!(resolve_subdomains(0, 30, 20, 2), 1);
    assert_eq!(resolve_subdomains(0, 3, 1, 2), 1);
}

fn grid(nx: usize) -> Scene {
    nsdd::generate::grid(&nsdd::generate::GridParams {
        nx,
        ny: nx,
        ..Default::default()
    })
}

#[test]
fn scenes_read_absent_zero_and_auto_as_automatic_and_write_nothing() {
    let g = grid(3);
    let text = g.to_toml_string().unwrap();
    assert_eq!(g.solver.subdomains, 0, "generators leave the count unset");
    assert!(!text.contains("subdomains"), "{text}");
    assert!(!g.to_json_string().unwrap().contains("subdomains"));
    assert_eq!(Scene::from_toml_str(&text).unwrap().solver.subdomains, 0);
    for (line, want) in [
        ("subdomains = 0", 0),
        ("subdomains = \"auto\"", 0),
        ("subdomains = 6", 6),
    ] {
        let t = text.replace("[solver]\n", &format!("[solver]\n{line}\n"));
        let s = Scene::from_toml_str(&t).unwrap_or_else(|e| panic!("{line}: {e}"));
        assert_eq!(s.solver.subdomains, want, "{line}");
        // An explicit count is written back; automatic is not.
        assert_eq!(s.to_toml_string().unwrap().contains("subdomains"), want > 0, "{line}");
    }
    for bad in ["subdomains = -1", "subdomains = \"many\""] {
        let t = text.replace("[solver]\n", &format!("[solver]\n{bad}\n"));
        let e = Scene::from_toml_str(&t).unwrap_err().to_string();
        assert!(e.contains("subdomains"), "{bad}: {e}");
    }
    assert!(SolveOptions::default().validate().is_ok());
    assert_eq!(SolveOptions::default().subdomains, 0);
}

/// The Rust API with the default (automatic) count decomposes into the
/// resolved count, says so in `notes`, and matches the direct solver.
#[test]
fn rust_api_automatic_count_matches_direct() {
    let g = grid(8);
    let model = Model::from_scene(&g).unwrap();
    let n = auto_subdomains(&model);
    assert!(n >= 2, "{n}");
    let mut opts = SolveOptions::from_scene(&g);
    opts.method = Method::Multilevel;
    opts.tolerance = 1e-10;
    let r = solve(&g, &opts).unwrap();
    assert!(r.converged);
    assert_eq!(r.subdomains, n);
    let note = format!(
        "subdomains: {n}, chosen automatically from {} free dofs, {} elements and {} threads",
        model.n_free,
        model.elements.len(),
        rayon::current_num_threads()
    );
    assert!(r.notes.contains(&note), "{:?}", r.notes);
    opts.method = Method::Direct;
    let d = solve(&g, &opts).unwrap();
    let (a, b): (Vec<f64>, Vec<f64>) = (
        r.displacements.iter().flatten().copied().collect(),
        d.displacements.iter().flatten().copied().collect(),
    );
    let err = a.iter().zip(&b).map(|(x, y)| (x - y).powi(2)).sum::<f64>().sqrt()
        / b.iter().map(|y| y * y).sum::<f64>().sqrt();
    assert!(err < 1e-6, "{err:e}");
    assert_eq!(r.slack, d.slack);
}

/// The C ABI: `nsdd_options_set_subdomains_auto` (and `_set_subdomains(0)`,
/// and fresh options) solve exactly as the Rust API's automatic count.
#[test]
fn c_abi_auto_matches_the_rust_api() {
    let g = grid(8);
    let mut opts = SolveOptions::from_scene(&g);
    opts.method = Method::Multilevel;
    let want = solve(&g, &opts).unwrap();
    let wu: Vec<u64> = want.displacements.iter().flatten().map(|x| x.to_bits()).collect();
    let text = CString::new(g.to_toml_string().unwrap()).unwrap();
    let dir = std::path::PathBuf::from(env!("CARGO_TARGET_TMPDIR"));
    unsafe {
        let mut s = null_mut();
        assert_eq!(nsdd_scene_from_str(text.as_ptr(), false, &mut s), NsddStatus::Ok);
        for how in ["auto", "zero", "fresh"] {
            let o = nsdd_options_new();
            assert_eq!(
                nsdd_options_set_method(o, NsddMethod::Multilevel as u32),
                NsddStatus::Ok
            );
            match how {
                "auto" => {
                    assert_eq!(nsdd_options_set_subdomains(o, 5), NsddStatus::Ok);
                    assert_eq!(nsdd_options_set_subdomains_auto(o), NsddStatus::Ok);
                }
                "zero" => {
                    assert_eq!(nsdd_options_set_subdomains(o, 5), NsddStatus::Ok);
                    assert_eq!(nsdd_options_set_subdomains(o, 0), NsddStatus::Ok);
                }
                _ => {}
            }
            let mut r = null_mut();
            assert_eq!(nsdd_solve(s, o, &mut r), NsddStatus::Ok, "{how}");
            let mut nn = 0;
            assert_eq!(nsdd_result_num_nodes(r, &mut nn), NsddStatus::Ok);
            let mut u = vec![0.0; 3 * nn];
            assert_eq!(nsdd_result_displacements(r, u.as_mut_ptr(), u.len()), NsddStatus::Ok);
            assert_eq!(u.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), wu, "{how}");
            let path = dir.join(format!("subdomains-{how}.json"));
            let cpath = CString::new(path.to_str().unwrap()).unwrap();
            assert_eq!(nsdd_result_write_json(r, cpath.as_ptr()), NsddStatus::Ok);
            let v: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
            assert_eq!(v["subdomains"], want.subdomains, "{how}");
            assert!(want.subdomains >= 2);
            assert!(
                v["notes"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .any(|n| n.as_str().unwrap().contains("chosen automatically")),
                "{how}: {v}"
            );
            nsdd_result_destroy(r);
            nsdd_options_destroy(o);
        }
        // A null handle is an error, not a crash.
        assert_eq!(nsdd_options_set_subdomains_auto(null_mut()), NsddStatus::NullPointer);
        nsdd_scene_destroy(s);
    }
}
