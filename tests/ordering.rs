//! Fill-reducing orderings (issue 21): METIS nested dissection beside AMD,
//! the choice by predicted fill, and the direct active set's symbolic reuse.

mod common;

use common::*;
use nsdd::direct::DirectSolver;
use nsdd::factor::{lower_csc, EliminationOrder, OrderingChoice, OrderingKind, SparseCholesky, PIVOT_RATIO};
use nsdd::generate::{grid, tower, GridParams, TowerParams};
use nsdd::model::Model;

fn stiffness(model: &Model) -> faer::sparse::SparseColMat<usize, f64> {
    let all: Vec<usize> = (0..model.elements.len()).collect();
    lower_csc(model.n_free, &model.stiffness_triplets(&all, Some)).unwrap()
}

fn tower_model(n: usize) -> Model {
    Model::from_scene(&tower(&TowerParams {
        nx: n,
        ny: n,
        nz: n,
        unilateral: false,
        ..Default::default()
    }))
    .unwrap()
}

/// Factors `k` in the order `choice` asks for, returns (nnz(L), kind, K⁻¹ b).
fn solve_with(
    k: &faer::sparse::SparseColMat<usize, f64>,
    b: &[f64],
    choice: OrderingChoice,
) -> (usize, OrderingKind, Vec<f64>) {
    let id: Vec<usize> = (0..k.nrows()).collect();
    let order = EliminationOrder::best_in_reference(k, &id, choice).unwrap();
    let mut chol = SparseCholesky::factor_ordered(k, Some(&order), 1, PIVOT_RATIO).unwrap();
    let mut x = b.to_vec();
    chol.solve_in_place(&mut x);
    assert_eq!(chol.ordering(), order.kind());
    (chol.nnz_l(), order.kind(), x)
}

#[test]
fn nested_dissection_matches_amd_and_fills_less_on_a_tower() {
    let model = tower_model(8);
    let k = stiffness(&model);
    let b = model.rhs(&model.load_cases[0]);
    let (nnz_amd, kind_amd, x_amd) = solve_with(&k, &b, OrderingChoice::Amd);
    let (nnz_nd, kind_nd, x_nd) = solve_with(&k, &b, OrderingChoice::NestedDissection);
    assert_eq!(kind_amd, OrderingKind::Amd);
    assert_eq!(kind_nd, OrderingKind::NestedDissection);
    assert!(rel_err(&x_nd, &x_amd) < 1e-10, "{}", rel_err(&x_nd, &x_amd));
    // A 3D lattice: nested dissection's separators beat minimum degree.
    assert!(
        (nnz_nd as f64) < 0.9 * nnz_amd as f64,
        "nnz(L): nested dissection {nnz_nd}, AMD {nnz_amd}"
    );
    // Auto keeps nested dissection, which saves well over 5 % here.
    let (nnz_auto, kind_auto, _) = solve_with(&k, &b, OrderingChoice::Auto);
    assert_eq!((nnz_auto, kind_auto), (nnz_nd, OrderingKind::NestedDissection));
}

#[test]
fn nested_dissection_matches_amd_on_a_grid_and_auto_keeps_it_only_where_it_pays() {
    let model = Model::from_scene(&grid(&GridParams {
        nx: 24,
        ny: 24,
        ..Default::default()
    }))
    .unwrap();
    let k = stiffness(&model);
    let b = model.rhs(&model.load_cases[0]);
    let (nnz_amd, _, x_amd) = solve_with(&k, &b, OrderingChoice::Amd);
    let (nnz_nd, _, x_nd) = solve_with(&k, &b, OrderingChoice::NestedDissection);
    assert!(rel_err(&x_nd, &x_amd) < 1e-10, "{}", rel_err(&x_nd, &x_amd));
    let (nnz_auto, kind_auto, _) = solve_with(&k, &b, OrderingChoice::Auto);
    // Nested dissection is tried only where AMD fills much, and kept only
    // where it saves at least 5 % of AMD's fill.
    let tried = (nnz_amd as f64) >= nsdd::factor::ND_FILL_RATIO * k.compute_nnz() as f64;
    let expected = if tried && (nnz_nd as f64) <= nsdd::factor::ND_MARGIN * nnz_amd as f64 {
        (nnz_nd, OrderingKind::NestedDissection)
    } else {
        (nnz_amd, OrderingKind::Amd)
    };
    assert_eq!((nnz_auto, kind_auto), expected, "amd {nnz_amd} nd {nnz_nd}");
}

#[test]
fn nested_dissection_is_deterministic_and_independent_of_the_numbering() {
    let model = tower_model(5);
    let k = stiffness(&model);
    let n = k.nrows();
    let id: Vec<usize> = (0..n).collect();
    let a = EliminationOrder::nd_in_reference(&k, &id).unwrap();
    let b = EliminationOrder::nd_in_reference(&k, &id).unwrap();
    assert_eq!(a.forward(), b.forward());
    // The same matrix with its rows reversed, ordered in the original
    // numbering as reference, eliminates the same dofs in the same order.
    let rev = |i: usize| n - 1 - i;
    let a_ref = k.as_ref();
    let mut trip = Vec::new();
    for j in 0..n {
        for (i, &v) in a_ref.row_idx_of_col(j).zip(a_ref.val_of_col(j)) {
            let (r, c) = (rev(i), rev(j));
            trip.push((r.max(c), r.min(c), v));
        }
    }
    let k_rev = lower_csc(n, &trip).unwrap();
    let rank: Vec<usize> = (0..n).map(rev).collect();
    let c = EliminationOrder::nd_in_reference(&k_rev, &rank).unwrap();
    let mapped: Vec<usize> = c.forward().iter().map(|&i| rev(i)).collect();
    assert_eq!(mapped, a.forward());
}

#[test]
fn direct_solver_reports_its_ordering() {
    let model = tower_model(8);
    let solver = DirectSolver::new(&model).unwrap();
    assert_eq!(solver.stats().ordering, Some(OrderingKind::NestedDissection));
    assert!(solver.stats().threads >= 1);
}

/// The refactoring path of the direct active set (more than 400 slack
/// cables) reuses `K`'s symbolic analysis: same answer as the Schur path
/// and as a fresh factorization of `K` without the final slack cables.
#[test]
fn many_slack_cables_refactor_on_the_symbolic_analysis_of_k() {
    let scene = grid(&GridParams {
        nx: 24,
        ny: 24,
        t0: 0.1,
        ..Default::default()
    });
    let model = Model::from_scene(&scene).unwrap();
    let b = model.rhs(&model.load_cases[0]);
    let mut refactor = DirectSolver::new(&model).unwrap();
    let c = refactor.solve(&model, &b).unwrap();
    let slack: Vec<bool> = c.lambda.iter().map(|&l| l > 0.0).collect();
    let n_slack = slack.iter().filter(|&&s| s).count();
    assert!(n_slack > 400, "{n_slack} slack cables");
    assert!(refactor.refactorizations() > 0);
    let mut schur = DirectSolver::new(&model).unwrap();
    schur.set_schur_limit(usize::MAX);
    let a = schur.solve(&model, &b).unwrap();
    assert_eq!(schur.refactorizations(), 0);
    assert!(rel_err(&a.u, &c.u) < 1e-10, "{}", rel_err(&a.u, &c.u));
    // Independent: fresh factorization of the taut structure.
    let mut is_slack = vec![false; model.elements.len()];
    for (i, &e) in model.cables.iter().enumerate() {
        is_slack[e] = slack[i];
    }
    let taut: Vec<usize> = (0..model.elements.len()).filter(|&e| !is_slack[e]).collect();
    let k = lower_csc(model.n_free, &model.stiffness_triplets(&taut, Some)).unwrap();
    let mut chol = SparseCholesky::factor(&k, 1).unwrap();
    let mut u = b.clone();
    for (i, &e) in model.cables.iter().enumerate() {
        if slack[i] {
            let el = &model.elements[e];
            model.add_h(e, el.k * el.e0, &mut u);
        }
    }
    chol.solve_in_place(&mut u);
    assert!(rel_err(&u, &c.u) < 1e-10, "{}", rel_err(&u, &c.u));
}

/// The `[solver] ordering` setting reaches every factorization of a solve:
/// the direct solver's and the DD subdomains' and interiors', for linear and
/// nonsmooth scenes; each ordering gives the direct (auto) answer, the
/// result reports the kinds used, and nested dissection fills less than AMD
/// on a 3D tower.
#[test]
fn the_ordering_setting_reaches_every_factorization() {
    use nsdd::scene::Method;
    use nsdd::solve::solve;
    let scene = tower(&TowerParams {
        nx: 10,
        ny: 10,
        nz: 10,
        unilateral: false,
        ..Default::default()
    });
    let reference = solve(&scene, &opts(Method::Direct, 0, 1e-8)).unwrap();
    let flat = |r: &nsdd::result::SolveResult| r.displacements.iter().flatten().copied().collect::<Vec<f64>>();
    // Subdomain and interior factors sum to nnz(L), not the direct one's.
    let mut fill = Vec::new();
    for choice in [
        OrderingChoice::Amd,
        OrderingChoice::NestedDissection,
        OrderingChoice::Auto,
    ] {
        let mut o = opts(Method::Direct, 0, 1e-8);
        o.ordering = choice;
        let direct = solve(&scene, &o).unwrap();
        let f = direct.factors.clone().expect("direct reports its factor");
        assert_eq!(f.nested_dissection + f.amd, 1);
        assert_eq!(f.amd == 1, choice == OrderingChoice::Amd, "{choice:?}: {f:?}");
        let e = rel_err(&flat(&direct), &flat(&reference));
        assert!(e < 1e-9, "{choice:?}: {e:.1e}");
        let mut o = opts(Method::Cg, 4, 1e-8);
        o.ordering = choice;
        let dd = solve(&scene, &o).unwrap();
        assert!(dd.converged, "{choice:?}: {}", dd.stop_summary());
        let err = rel_err(&flat(&dd), &flat(&reference));
        assert!(err < 1e-7, "{choice:?}: {err:.1e}");
        let f = dd.factors.clone().expect("cg reports its factors");
        // 4 subdomain factors and 4 interiors.
        assert_eq!(f.nested_dissection + f.amd, 8, "{f:?}");
        match choice {
            OrderingChoice::Amd => assert_eq!(f.nested_dissection, 0, "{f:?}"),
            // Every factor has 200 rows or more here.
            OrderingChoice::NestedDissection => assert_eq!(f.amd, 0, "{f:?}"),
            OrderingChoice::Auto => {}
        }
        fill.push(f.nnz_l);
    }
    // (5 % less on these 1k-dof subdomains; 30 % on the 30³ tower's 6k.)
    assert!(fill[1] < fill[0], "nnz(L) nd {} amd {}", fill[1], fill[0]);
    // Nonsmooth cg takes the setting into its set-ups too: same slack set
    // as the direct solver with either ordering.
    let ns = grid(&GridParams {
        nx: 16,
        ny: 16,
        t0: 0.1,
        ..Default::default()
    });
    let want = solve(&ns, &opts(Method::Direct, 0, 1e-8)).unwrap();
    for choice in [OrderingChoice::Amd, OrderingChoice::NestedDissection] {
        let mut o = opts(Method::Cg, 4, 1e-9);
        o.ordering = choice;
        let got = solve(&ns, &o).unwrap();
        assert!(got.converged, "{choice:?}");
        assert_eq!(got.slack, want.slack, "{choice:?}");
        assert!(rel_err(&flat(&got), &flat(&want)) < 1e-6, "{choice:?}");
    }
}

/// A scene names its ordering in `[solver]`; the default is not written, a
/// wrong value is refused with the field's name.
#[test]
fn the_scene_carries_its_ordering() {
    let mut scene = grid(&GridParams {
        nx: 4,
        ny: 4,
        ..Default::default()
    });
    let text = scene.to_toml_string().unwrap();
    assert!(!text.contains("ordering"), "the default is not written");
    scene.solver.ordering = OrderingChoice::NestedDissection;
    let text = scene.to_toml_string().unwrap();
    assert!(
        text.contains("ordering = \"nested_dissection\""),
        "{}",
        &text[..400.min(text.len())]
    );
    let back = nsdd::scene::Scene::from_toml_str(&text).unwrap();
    assert_eq!(back.solver.ordering, OrderingChoice::NestedDissection);
    let bad = text.replace("ordering = \"nested_dissection\"", "ordering = \"metis\"");
    let err = nsdd::scene::Scene::from_toml_str(&bad).unwrap_err().to_string();
    assert!(err.contains("ordering") && err.contains("nested_dissection"), "{err}");
}
