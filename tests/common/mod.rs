//! Shared helpers of the integration tests.
#![allow(dead_code)]

use nsdd::scene::{Effects, Method, Scene, SceneBuilder, SearchDirection};
use nsdd::solve::{solve, SolveOptions};

/// Relative 2-norm error of `a` against `b`.
pub fn rel_err(a: &[f64], b: &[f64]) -> f64 {
    let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f64>().sqrt();
    let den: f64 = b.iter().map(|y| y * y).sum::<f64>().sqrt();
    if den == 0.0 {
        num
    } else {
        num / den
    }
}

/// Adds `K_G u` to `out` (free dofs): the geometric stiffness of every
/// element (slack cables included: it comes from the prestress and does
/// not change as cables go slack), assembled from the element blocks with
/// no axial part and multiplied out, a path independent of the solvers'
/// and of `Model::unbalanced_forces`.
pub fn add_geometric_forces(model: &nsdd::model::Model, u: &[f64], out: &mut [f64]) {
    let all: Vec<usize> = (0..model.elements.len()).collect();
    // Lower triangle (row >= column), duplicates summed by the products.
    for (r, c, v) in model.stiffness_triplets_with_axial(&all, Some, 0.0) {
        out[r] += v * u[c];
        if r != c {
            out[c] += v * u[r];
        }
    }
}

pub fn flat(v: &[[f64; 3]]) -> Vec<f64> {
    v.iter().flatten().copied().collect()
}

pub fn opts(method: Method, subdomains: usize, tol: f64) -> SolveOptions {
    SolveOptions {
        method,
        subdomains,
        tolerance: tol,
        max_iterations: 200_000,
        search_direction: SearchDirection::Auto,
        preconditioner: Default::default(),
        interface_scaling: Default::default(),
        adaptive_threshold: nsdd::settings::AdaptiveThreshold::OFF,
        adaptive_edges: nsdd::settings::AdaptiveEdges::Off,
        macro_degree: Default::default(),
        partitioner: Default::default(),
        ordering: Default::default(),
    }
}

/// Solves with `method` and with the direct solver and checks the DESIGN
/// criterion: relative errors at most 10× the tolerance, same slack set.
/// Returns the iteration count.
pub fn assert_matches_direct(scene: &Scene, method: Method, subdomains: usize, tol: f64) -> usize {
    assert_matches_direct_with(scene, &opts(method, subdomains, tol))
}

/// [`assert_matches_direct`] with every solver option given.
pub fn assert_matches_direct_with(scene: &Scene, o: &SolveOptions) -> usize {
    let (subdomains, tol) = (o.subdomains, o.tolerance);
    let direct = solve(scene, &opts(Method::Direct, 1, tol)).expect("direct solve");
    let dd = solve(scene, o).unwrap_or_else(|e| panic!("{} with {subdomains} subdomains: {e}", scene.scene.name));
    assert!(
        dd.converged,
        "{} with {subdomains} subdomains: not converged after {}",
        scene.scene.name, dd.iterations
    );
    for v in dd.displacements.iter().flatten().chain(&dd.tensions) {
        assert!(v.is_finite(), "non-finite value in the result");
    }
    let eu = rel_err(&flat(&dd.displacements), &flat(&direct.displacements));
    let et = rel_err(&dd.tensions, &direct.tensions);
    assert!(
        eu <= 10.0 * tol,
        "{} {subdomains}: displacement error {eu:.2e}",
        scene.scene.name
    );
    assert!(
        et <= 10.0 * tol,
        "{} {subdomains}: tension error {et:.2e}",
        scene.scene.name
    );
    assert_eq!(
        dd.slack, direct.slack,
        "{} {subdomains}: slack sets differ",
        scene.scene.name
    );
    dd.iterations
}

/// A planar square grid of `n × n` cells of bars with both diagonals, in
/// the plane z = 0 (z blocked everywhere), supported on its left edge and
/// loaded at the right edge. Node (i, j) is `i * (n + 1) + j`.
pub fn planar_grid(n: usize, user_partition: Option<&dyn Fn(usize, usize) -> usize>) -> Scene {
    let mut b = SceneBuilder::new("planar-grid");
    for i in 0..=n {
        for j in 0..=n {
            b.node(i as f64, j as f64, 0.0);
        }
    }
    let id = |i: usize, j: usize| i * (n + 1) + j;
    let mut part = Vec::new();
    for i in 0..n {
        for j in 0..n {
            let cell = user_partition.map(|f| f(i, j)).unwrap_or(0);
            for (a, c) in [
                (id(i, j), id(i + 1, j)),
                (id(i, j), id(i, j + 1)),
                (id(i, j), id(i + 1, j + 1)),
                (id(i + 1, j), id(i, j + 1)),
            ] {
                b.bar(a, c, 100.0);
                part.push(cell);
            }
            if i == n - 1 {
                b.bar(id(i + 1, j), id(i + 1, j + 1), 100.0);
                part.push(cell);
            }
            if j == n - 1 {
                b.bar(id(i, j + 1), id(i + 1, j + 1), 100.0);
                part.push(cell);
            }
        }
    }
    for j in 0..=n {
        b.support(id(0, j), "xyz");
        for i in 1..=n {
            b.support(id(i, j), "z");
        }
        b.load(id(n, j), [0.3, -1.0, 0.0]);
    }
    let mut s = b.build();
    if user_partition.is_some() {
        s.elements.subdomain = part;
    }
    s
}

/// A cubic lattice of `n × n × n` cells (edges bars, face diagonals cables,
/// one body diagonal bar), fixed at z = 0, with a lateral top load.
pub fn cube_lattice(
    n: usize,
    unilateral: bool,
    user_partition: Option<&dyn Fn(usize, usize, usize) -> usize>,
) -> Scene {
    let mut b = SceneBuilder::new("cube-lattice");
    let m = n + 1;
    let id = |i: usize, j: usize, k: usize| (k * m + j) * m + i;
    for k in 0..m {
        for j in 0..m {
            for i in 0..m {
                b.node(i as f64, j as f64, k as f64);
            }
        }
    }
    let mut part = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for k in 0..n {
        for j in 0..n {
            for i in 0..n {
                let cell = user_partition.map(|f| f(i, j, k)).unwrap_or(0);
                let c = |di: usize, dj: usize, dk: usize| id(i + di, j + dj, k + dk);
                let edges = [
                    (c(0, 0, 0), c(1, 0, 0)),
                    (c(0, 1, 0), c(1, 1, 0)),
                    (c(0, 0, 1), c(1, 0, 1)),
                    (c(0, 1, 1), c(1, 1, 1)),
                    (c(0, 0, 0), c(0, 1, 0)),
                    (c(1, 0, 0), c(1, 1, 0)),
                    (c(0, 0, 1), c(0, 1, 1)),
                    (c(1, 0, 1), c(1, 1, 1)),
                    (c(0, 0, 0), c(0, 0, 1)),
                    (c(1, 0, 0), c(1, 0, 1)),
                    (c(0, 1, 0), c(0, 1, 1)),
                    (c(1, 1, 0), c(1, 1, 1)),
                ];
                let faces = [
                    (c(0, 0, 0), c(1, 1, 0)),
                    (c(1, 0, 0), c(0, 1, 0)),
                    (c(0, 0, 1), c(1, 1, 1)),
                    (c(1, 0, 1), c(0, 1, 1)),
                    (c(0, 0, 0), c(1, 0, 1)),
                    (c(1, 0, 0), c(0, 0, 1)),
                    (c(0, 1, 0), c(1, 1, 1)),
                    (c(1, 1, 0), c(0, 1, 1)),
                    (c(0, 0, 0), c(0, 1, 1)),
                    (c(0, 1, 0), c(0, 0, 1)),
                    (c(1, 0, 0), c(1, 1, 1)),
                    (c(1, 1, 0), c(1, 0, 1)),
                ];
                for (a, e) in edges {
                    if seen.insert((a.min(e), a.max(e))) {
                        b.bar(a, e, 50.0);
                        part.push(cell);
                    }
                }
                for (a, e) in faces {
                    if seen.insert((a.min(e), a.max(e))) {
                        let el = b.cable(a, e, 20.0);
                        b.prestress(el, 0.05);
                        part.push(cell);
                    }
                }
                b.bar(c(0, 0, 0), c(1, 1, 1), 50.0);
                part.push(cell);
            }
        }
    }
    for j in 0..m {
        for i in 0..m {
            b.support(id(i, j, 0), "xyz");
            b.load(id(i, j, n), [0.2, 0.05, -0.1]);
        }
    }
    b.effects(Effects {
        unilateral_cables: unilateral,
        prestress: true,
        ..Default::default()
    });
    let mut s = b.build();
    if user_partition.is_some() {
        s.elements.subdomain = part;
    }
    s
}

/// The cables of a set-up problem in global cable order, each with its
/// subdomain and its local dofs and coefficients (unused slots dropped):
/// what a caller of the algebraic level passes for it.
pub fn cable_terms(problem: &nsdd::dd::DdProblem) -> Vec<(usize, nsdd::dd::CableColumn, Vec<usize>, Vec<f64>)> {
    let mut cables: Vec<(usize, nsdd::dd::CableColumn)> = problem
        .loads
        .iter()
        .enumerate()
        .flat_map(|(s, l)| l.cables.iter().map(move |c| (s, *c)))
        .collect();
    cables.sort_by_key(|(_, c)| c.cable);
    cables
        .into_iter()
        .map(|(s, c)| {
            let (dofs, coefs): (Vec<usize>, Vec<f64>) = c
                .dofs
                .iter()
                .zip(&c.coef)
                .filter(|(d, _)| **d != nsdd::dd::NO_DOF)
                .map(|(&d, &v)| (d as usize, v))
                .unzip();
            (s, c, dofs, coefs)
        })
        .collect()
}

/// The README's tower with every cable taut (`gen tower nx=2 ny=2 nz=10
/// unilateral=false`): bars 1e4, cables `ea_cable`.
pub fn taut_tower(ea_cable: f64) -> Scene {
    nsdd::generate::tower(&nsdd::generate::TowerParams {
        nx: 2,
        ny: 2,
        nz: 10,
        ea_cable,
        unilateral: false,
        ..Default::default()
    })
}

/// The scene with nsdd's own partition into `n` subdomains written into
/// `elements.subdomain`: the same subdomains, but the user's, which the
/// set-up does not change (no merging of indefinite subdomains).
pub fn with_user_partition(scene: &Scene, n: usize) -> Scene {
    let model = nsdd::model::Model::from_scene(scene).unwrap();
    let mut scene = scene.clone();
    scene.elements.subdomain = nsdd::partition::Partition::bisection(&model, n).unwrap().part_of;
    scene
}
