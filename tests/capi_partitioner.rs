//! `nsdd_options_set_partitioner` (issue 21): the C ABI solves on the
//! partition the Rust API makes with the same partitioner.

use nsdd::capi::*;
use nsdd::scene::{Method, Partitioner};
use nsdd::solve::{solve, SolveOptions};
use std::ffi::CString;
use std::ptr::null_mut;

/// Solves `s` with `o` through the C ABI and checks that the displacements
/// have the bits of the Rust API's `want`; returns the result handle (to be
/// destroyed) and the displacements.
///
/// # Safety
/// `s` and `o` must be live handles.
unsafe fn solve_as_rust_does(
    s: *const NsddScene,
    o: *const NsddOptions,
    want: &nsdd::result::SolveResult,
    what: &str,
) -> (*mut NsddResult, Vec<f64>) {
    unsafe {
        let mut r = null_mut();
        assert_eq!(nsdd_solve(s, o, &mut r), NsddStatus::Ok);
        let mut nn = 0;
        assert_eq!(nsdd_result_num_nodes(r, &mut nn), NsddStatus::Ok);
        let mut u = vec![0.0; 3 * nn];
        assert_eq!(nsdd_result_displacements(r, u.as_mut_ptr(), u.len()), NsddStatus::Ok);
        let wu: Vec<f64> = want.displacements.iter().flatten().copied().collect();
        assert_eq!(
            u.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            wu.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            "{what}"
        );
        (r, u)
    }
}

#[test]
fn c_partitioner_option_matches_the_rust_api_bit_for_bit() {
    let mut scene = nsdd::generate::grid(&nsdd::generate::GridParams {
        nx: 10,
        ny: 10,
        unilateral: false,
        ..Default::default()
    });
    let text = CString::new(scene.to_toml_string().unwrap()).unwrap();
    let mut opts = SolveOptions::from_scene(&scene);
    opts.method = Method::Cg;
    opts.subdomains = 8;
    unsafe {
        let mut s = null_mut();
        assert_eq!(nsdd_scene_from_str(text.as_ptr(), false, &mut s), NsddStatus::Ok);
        let o = nsdd_options_new();
        assert_eq!(nsdd_options_set_method(o, NsddMethod::Cg as u32), NsddStatus::Ok);
        assert_eq!(nsdd_options_set_subdomains(o, 8), NsddStatus::Ok);
        let mut results = Vec::new();
        for (p, code) in [
            (Partitioner::Bisection, NsddPartitioner::Bisection as u32),
            (Partitioner::Metis, NsddPartitioner::Metis as u32),
        ] {
            // The settings carry the partitioner (the scene's is copied
            // into them by from_scene): set both, as a Rust caller would.
            scene.solver.partitioner = p;
            opts.partitioner = p;
            let want = solve(&scene, &opts).unwrap();
            assert_eq!(nsdd_options_set_partitioner(o, code), NsddStatus::Ok);
            let (r, u) = solve_as_rust_does(s, o, &want, &format!("{p:?}"));
            let mut it = 0;
            assert_eq!(nsdd_result_iterations(r, &mut it), NsddStatus::Ok);
            assert_eq!(it, want.iterations);
            results.push(u);
            nsdd_result_destroy(r);
        }
        // Different partitions give different round-off: the option did
        // reach the solver.
        assert_ne!(results[0], results[1]);
        assert_eq!(nsdd_options_set_partitioner(o, 2), NsddStatus::InvalidArgument);
        nsdd_options_destroy(o);
        nsdd_scene_destroy(s);
    }
}

/// `nsdd_options_set_ordering` (issue 21): the C ABI factors in the ordering
/// the Rust API uses with the same setting, bit for bit, and its result file
/// names the orderings used.
#[test]
fn c_ordering_option_matches_the_rust_api_bit_for_bit() {
    use nsdd::scene::OrderingChoice;
    let scene = nsdd::generate::tower(&nsdd::generate::TowerParams {
        nx: 10,
        ny: 10,
        nz: 10,
        unilateral: false,
        ..Default::default()
    });
    let text = CString::new(scene.to_toml_string().unwrap()).unwrap();
    let mut opts = SolveOptions::from_scene(&scene);
    opts.method = Method::Cg;
    opts.subdomains = 4;
    let dir = std::env::temp_dir().join(format!("nsdd-capi-ordering-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    unsafe {
        let mut s = null_mut();
        assert_eq!(nsdd_scene_from_str(text.as_ptr(), false, &mut s), NsddStatus::Ok);
        let o = nsdd_options_new();
        assert_eq!(nsdd_options_set_method(o, NsddMethod::Cg as u32), NsddStatus::Ok);
        assert_eq!(nsdd_options_set_subdomains(o, 4), NsddStatus::Ok);
        for (choice, code) in [
            (OrderingChoice::Auto, NsddOrdering::Auto as u32),
            (OrderingChoice::Amd, NsddOrdering::Amd as u32),
            (OrderingChoice::NestedDissection, NsddOrdering::NestedDissection as u32),
        ] {
            opts.ordering = choice;
            let want = solve(&scene, &opts).unwrap();
            assert_eq!(nsdd_options_set_ordering(o, code), NsddStatus::Ok);
            let (r, _) = solve_as_rust_does(s, o, &want, &format!("{choice:?}"));
            let path = dir.join(format!("r{code}.json"));
            let cpath = CString::new(path.to_str().unwrap()).unwrap();
            assert_eq!(nsdd_result_write_json(r, cpath.as_ptr()), NsddStatus::Ok);
            let json: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
            let f = &json["factors"];
            let (nd, amd) = (f["nested_dissection"].as_u64().unwrap(), f["amd"].as_u64().unwrap());
            assert_eq!(nd + amd, 8, "{f}");
            match choice {
                OrderingChoice::Amd => assert_eq!(nd, 0, "{f}"),
                OrderingChoice::NestedDissection => assert_eq!(amd, 0, "{f}"),
                OrderingChoice::Auto => {}
            }
            assert_eq!(
                f["nnz_l"].as_u64().unwrap() as usize,
                want.factors.as_ref().unwrap().nnz_l
            );
            nsdd_result_destroy(r);
        }
        assert_eq!(nsdd_options_set_ordering(o, 3), NsddStatus::InvalidArgument);
        nsdd_options_destroy(o);
        nsdd_scene_destroy(s);
    }
    let _ = std::fs::remove_dir_all(&dir);
}
