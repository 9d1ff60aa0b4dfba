//! The algebraic entry point used directly from Rust: a truss assembled and
//! split by hand against a dense solve of the same matrix, a bundled scene
//! with unilateral prestressed cables against the direct solver, and the
//! errors of bad input naming the subdomain and field.

// Dense elimination and element loops index like their formulas.
#![allow(clippy::needless_range_loop)]

mod common;
use nsdd::algebraic::AlgebraicProblem;
use nsdd::dd::DdProblem;
use nsdd::direct::DirectSolver;
use nsdd::error::Error;
use nsdd::model::Model;
use nsdd::scene::{Method, Scene, SolverSettings};
use nsdd::solve::decompose;
use std::path::PathBuf;

fn settings(method: Method) -> SolverSettings {
    SolverSettings {
        method,
        tolerance: 1e-12,
        ..Default::default()
    }
}

/// A 2D ladder truss of `panels` square panels (side 1, EA = 100): nodes
/// (i, 0) and (i, 1), the two at x = 0 pinned; chords, posts and one
/// both diagonals per panel. Free dof of node n >= 2, component c: 2 (n - 2) + c.
/// Returns the bars `(node a, node b)`, the node coordinates and n_free.
fn ladder(panels: usize) -> (Vec<(usize, usize)>, Vec<[f64; 2]>, usize) {
    let xy: Vec<[f64; 2]> = (0..=panels).flat_map(|i| [[i as f64, 0.0], [i as f64, 1.0]]).collect();
    let mut bars = vec![];
    for i in 0..panels {
        let (a, b, c, d) = (2 * i, 2 * i + 1, 2 * i + 2, 2 * i + 3);
        bars.extend([(a, c), (b, d), (c, d), (a, d), (b, c)]);
    }
    (bars, xy, 2 * (2 * panels))
}

/// The 4x4 stiffness of bar (a, b) on the dofs [ax, ay, bx, by], and those
/// free dof ids (None = pinned).
fn bar(xy: &[[f64; 2]], a: usize, b: usize) -> ([[f64; 4]; 4], [Option<usize>; 4]) {
    let (dx, dy) = (xy[b][0] - xy[a][0], xy[b][1] - xy[a][1]);
    let l = (dx * dx + dy * dy).sqrt();
    let h = [-dx / l, -dy / l, dx / l, dy / l];
    let k = 100.0 / l;
    let mut m = [[0.0; 4]; 4];
    for i in 0..4 {
        for j in 0..4 {
            m[i][j] = k * h[i] * h[j];
        }
    }
    let dof = |n: usize, c: usize| (n >= 2).then(|| 2 * (n - 2) + c);
    (m, [dof(a, 0), dof(a, 1), dof(b, 0), dof(b, 1)])
}

/// Full CSR of a dense symmetric matrix (zeros skipped).
fn csr(k: &[Vec<f64>]) -> (Vec<usize>, Vec<usize>, Vec<f64>) {
    let (mut rp, mut ci, mut va) = (vec![0], vec![], vec![]);
    for row in k {
        for (j, &v) in row.iter().enumerate() {
            if v != 0.0 {
                ci.push(j);
                va.push(v);
            }
        }
        rp.push(ci.len());
    }
    (rp, ci, va)
}

/// Dense Gaussian elimination with partial pivoting: the independent
/// reference.
fn dense_solve(mut a: Vec<Vec<f64>>, mut b: Vec<f64>) -> Vec<f64> {
    let n = b.len();
    for c in 0..n {
        let p = (c..n).max_by(|&i, &j| a[i][c].abs().total_cmp(&a[j][c].abs())).unwrap();
        a.swap(c, p);
        b.swap(c, p);
        for r in c + 1..n {
            let f = a[r][c] / a[c][c];
            for j in c..n {
                a[r][j] -= f * a[c][j];
            }
            b[r] -= f * b[c];
        }
    }
    let mut x = vec![0.0; n];
    for r in (0..n).rev() {
        let s: f64 = (r + 1..n).map(|j| a[r][j] * x[j]).sum();
        x[r] = (b[r] - s) / a[r][r];
    }
    x
}

#[test]
fn hand_split_truss_matches_a_dense_solve() {
    let panels = 6;
    let (bars, xy, n) = ladder(panels);
    // Global matrix, for the reference.
    let mut kg = vec![vec![0.0; n]; n];
    for &(a, b) in &bars {
        let (m, d) = bar(&xy, a, b);
        for i in 0..4 {
            for j in 0..4 {
                if let (Some(p), Some(q)) = (d[i], d[j]) {
                    kg[p][q] += m[i][j];
                }
            }
        }
    }
    // Three subdomains by panel (2, 2, 2): the last two float. Each
    // subdomain numbers its free dofs in reverse order of first touch, so
    // local and global numbering differ.
    let mut problem = AlgebraicProblem::new(3, n).unwrap();
    for s in 0..3 {
        let mine: Vec<(usize, usize)> = bars
            .iter()
            .copied()
            .filter(|&(a, b)| {
                // Posts on a cut go left: each side's cut nodes keep two
                // bar directions (no zero-stiffness dof).
                let x = 0.5 * (xy[a][0] + xy[b][0]);
                ((x - 1e-9) / 2.0).floor() as usize == s
            })
            .collect();
        let mut l2g: Vec<usize> = vec![];
        for &(a, b) in &mine {
            for g in bar(&xy, a, b).1.into_iter().flatten() {
                if !l2g.contains(&g) {
                    l2g.push(g);
                }
            }
        }
        l2g.reverse();
        let local = |g: usize| l2g.iter().position(|&x| x == g).unwrap();
        let mut kl = vec![vec![0.0; l2g.len()]; l2g.len()];
        for &(a, b) in &mine {
            let (m, d) = bar(&xy, a, b);
            for i in 0..4 {
                for j in 0..4 {
                    if let (Some(p), Some(q)) = (d[i], d[j]) {
                        kl[local(p)][local(q)] += m[i][j];
                    }
                }
            }
        }
        let (rp, ci, va) = csr(&kl);
        problem.subdomain(s, &rp, &ci, &va, &l2g).unwrap();
    }
    let points: Vec<[f64; 3]> = (0..n).map(|g| [xy[g / 2 + 2][0], xy[g / 2 + 2][1], 0.0]).collect();
    let comp: Vec<usize> = (0..n).map(|g| g % 2).collect();
    problem.dof_points(&points, &comp).unwrap();
    // Tip load down and sideways.
    let mut f = vec![0.0; n];
    f[n - 1] = -1.0;
    f[n - 2] = 0.5;
    let want = dense_solve(kg, f.clone());
    let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    // Monolevel too: its coarse space is the floating parts' kernel modes.
    for method in [Method::Monolevel, Method::Multilevel, Method::Cg] {
        let mut solver = problem.build(&settings(method)).unwrap();
        assert_eq!(
            (solver.n_global_dofs(), solver.n_subdomains(), solver.n_cables()),
            (n, 3, 0)
        );
        // Twice: the set-up is reused.
        for _ in 0..2 {
            let out = solver.solve(&f).unwrap();
            assert!(out.converged(), "{method:?}: {:?}", out.status);
            for (g, (u, w)) in out.u.iter().zip(&want).enumerate() {
                assert!((u - w).abs() < 1e-8 * scale, "{method:?}: u[{g}] = {u}, dense {w}");
            }
        }
    }
}

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Full symmetric CSR of a lower-triangular CSC matrix.
fn full_csr(lower: &faer::sparse::SparseColMat<usize, f64>) -> (Vec<usize>, Vec<usize>, Vec<f64>) {
    let a = lower.as_ref();
    let n = a.nrows();
    let mut rows: Vec<Vec<(usize, f64)>> = vec![Vec::new(); n];
    for j in 0..a.ncols() {
        for (i, &v) in a.row_idx_of_col(j).zip(a.val_of_col(j)) {
            rows[i].push((j, v));
            if i != j {
                rows[j].push((i, v));
            }
        }
    }
    // Dense, then CSR without the zeros: exact zeros of the assembly
    // (a dof without stiffness) are left out, as a caller's CSR may.
    let mut k = vec![vec![0.0; n]; n];
    for (i, r) in rows.iter().enumerate() {
        for &(j, v) in r {
            k[i][j] += v;
        }
    }
    csr(&k)
}

#[test]
fn scene_with_slack_cables_matches_the_direct_solver() {
    // grid-8x8: unilateral prestressed cables, some slack under the load.
    let scene = Scene::load(&root().join("scenes").join("grid-8x8.toml")).unwrap();
    let model = Model::from_scene(&scene).unwrap();
    let dec = decompose(&model, &scene, 4).unwrap();
    let dd = DdProblem::from_model(&model, &dec).unwrap();
    let mut problem = AlgebraicProblem::new(4, model.n_free).unwrap();
    for (s, op) in dd.operators.iter().enumerate() {
        let (rp, ci, va) = full_csr(&op.stiffness);
        problem.subdomain(s, &rp, &ci, &va, &dec.subdomains[s].dofs).unwrap();
    }
    for (s, c, dofs, coefs) in common::cable_terms(&dd) {
        assert_eq!(problem.cable(s, &dofs, &coefs, c.k, c.e0).unwrap(), c.cable);
    }
    let points: Vec<[f64; 3]> = dd.dof_points.iter().map(|(p, _)| *p).collect();
    let comp: Vec<usize> = dd.dof_points.iter().map(|(_, c)| *c).collect();
    problem.dof_points(&points, &comp).unwrap();
    let mut solver = problem.build(&settings(Method::Multilevel)).unwrap();

    // Local right-hand sides: each subdomain's share of the load plus its
    // prestrain load (nothing is added by the solver).
    let f = &model.load_cases[0];
    let rhs: Vec<Vec<f64>> = dec
        .subdomains
        .iter()
        .zip(&dd.loads)
        .map(|(sd, load)| {
            sd.dofs
                .iter()
                .enumerate()
                .map(|(l, &d)| f[d] / sd.multiplicity[l] as f64 + load.constant[l])
                .collect()
        })
        .collect();
    let views: Vec<&[f64]> = rhs.iter().map(|r| r.as_slice()).collect();
    let out = solver.solve_local(&views).unwrap();
    assert!(out.converged());

    let mut direct = DirectSolver::new(&model).unwrap();
    let want = direct.solve(&model, &model.rhs(f)).unwrap();
    assert!(want.lambda.iter().any(|&l| l > 0.0), "the test needs slack cables");
    let scale = want.u.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let err = out.u.iter().zip(&want.u).fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    assert!(err < 1e-6 * scale, "max |u - u_direct| = {err:e}, scale {scale:e}");
    // The same slack set.
    let lscale = want.lambda.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for (c, (a, b)) in out.lambda.iter().zip(&want.lambda).enumerate() {
        assert_eq!(
            *a > 1e-6 * lscale,
            *b > 1e-6 * lscale,
            "cable {c}: lambda {a} vs direct {b}"
        );
    }
}

/// The message of an error, which must be invalid input.
fn msg<T>(r: nsdd::Result<T>) -> String {
    match r {
        Err(e @ Error::InvalidInput { .. }) => e.to_string(),
        Err(e) => panic!("expected invalid input, got {e}"),
        Ok(_) => panic!("expected an error"),
    }
}

fn assert_mentions(m: &str, needles: &[&str]) {
    for n in needles {
        assert!(m.contains(n), "message {m:?} does not mention {n:?}");
    }
}

#[test]
fn bad_csr_is_refused_naming_the_subdomain() {
    let mut p = AlgebraicProblem::new(2, 3).unwrap();
    let l2g = [1, 2];
    let ok = |p: &mut AlgebraicProblem| {
        p.subdomain(1, &[0, 2, 4], &[0, 1, 0, 1], &[2.0, -1.0, -1.0, 2.0], &l2g)
            .map(|_| ())
    };
    ok(&mut p).unwrap();
    // Non-symmetric: entry (0, 1) without its mirror (1, 0), and a full
    // matrix whose mirrored values differ.
    let m = msg(p
        .subdomain(1, &[0, 2, 3], &[0, 1, 1], &[2.0, -1.0, 2.0], &l2g)
        .map(|_| ()));
    assert_mentions(&m, &["subdomain 1", "upper triangle"]);
    let m = msg(p
        .subdomain(1, &[0, 2, 4], &[0, 1, 0, 1], &[2.0, -1.0, -1.5, 2.0], &l2g)
        .map(|_| ()));
    assert_mentions(&m, &["subdomain 1", "not symmetric", "(1, 0)"]);
    // Entry (2, 0) without its mirror (0, 2) in a full matrix.
    let m = msg(AlgebraicProblem::new(1, 3)
        .unwrap()
        .subdomain(
            0,
            &[0, 2, 4, 6],
            &[0, 1, 0, 1, 0, 2],
            &[2.0, -1.0, -1.0, 2.0, 0.5, 1.0],
            &[0, 1, 2],
        )
        .map(|_| ()));
    assert_mentions(&m, &["subdomain 0", "not symmetric", "(2, 0) = 0.5"]);
    // Out-of-range column index and global dof.
    let m = msg(p
        .subdomain(1, &[0, 2, 4], &[0, 1, 0, 2], &[2.0, -1.0, -1.0, 2.0], &l2g)
        .map(|_| ()));
    assert_mentions(&m, &["subdomain 1", "col_idx[3] = 2 out of range"]);
    let m = msg(p
        .subdomain(1, &[0, 2, 4], &[0, 1, 0, 1], &[2.0, -1.0, -1.0, 2.0], &[1, 3])
        .map(|_| ()));
    assert_mentions(&m, &["subdomain 1", "local_to_global[1] = 3"]);
    // Wrong lengths.
    let m = msg(p.subdomain(1, &[0, 2], &[0, 1], &[2.0, -1.0], &l2g).map(|_| ()));
    assert_mentions(&m, &["subdomain 1", "row_ptr has 2 entries, expected n_local + 1 = 3"]);
    let m = msg(p
        .subdomain(1, &[0, 2, 4], &[0, 1, 0], &[2.0, -1.0, -1.0, 2.0], &l2g)
        .map(|_| ()));
    assert_mentions(&m, &["subdomain 1", "col_idx has 3 entries", "= 4"]);
    let m = msg(p
        .subdomain(1, &[0, 2, 4], &[0, 1, 0, 1], &[2.0, -1.0, -1.0], &l2g)
        .map(|_| ()));
    assert_mentions(&m, &["subdomain 1", "values has 3 entries"]);
    // Other CSR faults.
    let m = msg(p.subdomain(1, &[0, 3, 2], &[0, 1], &[2.0, 2.0], &l2g).map(|_| ()));
    assert_mentions(&m, &["subdomain 1", "must not decrease"]);
    let m = msg(p
        .subdomain(1, &[0, 2, 4], &[0, 1, 0, 1], &[2.0, f64::NAN, -1.0, 2.0], &l2g)
        .map(|_| ()));
    assert_mentions(&m, &["subdomain 1", "values[1]"]);
    let m = msg(p
        .subdomain(1, &[0, 2, 4], &[0, 1, 0, 1], &[2.0, -1.0, -1.0, 2.0], &[2, 2])
        .map(|_| ()));
    assert_mentions(&m, &["subdomain 1", "both global dof 2"]);
    let m = msg(p.subdomain(2, &[0, 1], &[0], &[1.0], &[0]).map(|_| ()));
    assert_mentions(&m, &["subdomain 2 out of range"]);
    // A failed call leaves the subdomain as it was.
    assert_eq!(p.n_local(1), Some(2));
}

#[test]
fn incomplete_problems_and_bad_right_hand_sides() {
    let mut p = AlgebraicProblem::new(2, 3).unwrap();
    let m = msg(p.kernel(0, &[1.0]).map(|_| ()));
    assert_mentions(&m, &["subdomain 0 has not been set"]);
    let m = msg(p.build(&settings(Method::Monolevel)).map(|_| ()));
    assert_mentions(&m, &["subdomain 0 has not been set"]);
    // Subdomain 0: dofs 0, 1 (grounded); subdomain 1: dof 1, 2 (floating).
    p.subdomain(0, &[0, 1, 3], &[0, 0, 1], &[2.0, -1.0, 1.0], &[0, 1])
        .unwrap();
    p.subdomain(1, &[0, 1, 3], &[0, 0, 1], &[1.0, -1.0, 1.0], &[1, 2])
        .unwrap();
    // The multilevel method needs the dof points; direct is not a DD method.
    let m = msg(p.build(&settings(Method::Multilevel)).map(|_| ()));
    assert_mentions(&m, &["dof points"]);
    assert!(matches!(
        p.build(&settings(Method::Direct)),
        Err(Error::MethodNotApplicable(_))
    ));
    let m = msg(p.cable(1, &[0, 5], &[1.0, -1.0], 1.0, 0.0));
    assert_mentions(&m, &["local_dofs[1] = 5", "subdomain 1"]);
    let m = msg(p.kernel(1, &[1.0, 1.0, 1.0]));
    assert_mentions(&m, &["subdomain 1", "multiple of n_local = 2"]);
    let points = [[0.0; 3], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0]];
    let m = msg(p.dof_points(&points[..2], &[0, 0]).map(|_| ()));
    assert_mentions(&m, &["points has 2 entries", "n_global_dofs = 3"]);
    p.dof_points(&points, &[0; 3]).unwrap();
    let mut solver = p
        .kernel(1, &[1.0, 1.0])
        .unwrap()
        .build(&settings(Method::Multilevel))
        .unwrap();
    // u = (1, 2, 3) for a unit load at the end.
    let out = solver.solve_local(&[&[0.0, 0.0], &[0.0, 1.0]]).unwrap();
    for (g, u) in out.u.iter().enumerate() {
        assert!((u - (g + 1) as f64).abs() < 1e-9, "u[{g}] = {u}");
    }
    let m = msg(solver.solve_local(&[&[0.0, 0.0], &[0.0]]));
    assert_mentions(&m, &["rhs[1]", "subdomain 1 has 2 dofs"]);
    let m = msg(solver.solve_local(&[&[0.0, 0.0], &[f64::NAN, 0.0]]));
    assert_mentions(&m, &["rhs[1][0]"]);
    let m = msg(solver.solve_local(&[&[0.0, 0.0]]));
    assert_mentions(&m, &["1 subdomain vectors given, expected 2"]);
    let m = msg(solver.solve(&[0.0; 2]));
    assert_mentions(&m, &["f has 2 entries"]);
}
