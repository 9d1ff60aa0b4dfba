//! METIS k-way partition of the node graph as the automatic partitioner
//! (issue 21), beside coordinate bisection.

mod common;

use common::*;
use nsdd::generate::{grid, tower, GridParams, TowerParams};
use nsdd::model::Model;
use nsdd::partition::Partition;
use nsdd::scene::{Method, Partitioner, Scene};

fn tower_scene(n: usize) -> Scene {
    tower(&TowerParams {
        nx: n,
        ny: n,
        nz: n,
        ..Default::default()
    })
}

fn grid_scene(n: usize) -> Scene {
    grid(&GridParams {
        nx: n,
        ny: n,
        t0: 0.1,
        ..Default::default()
    })
}

/// Elements of part `p` in connected pieces (elements linked through a
/// shared node), largest first.
fn pieces(model: &Model, elements: &[usize]) -> Vec<usize> {
    let nn = model.coords.len();
    let mut parent: Vec<usize> = (0..nn).collect();
    fn find(p: &mut [usize], mut i: usize) -> usize {
        while p[i] != i {
            p[i] = p[p[i]];
            i = p[i];
        }
        i
    }
    for &e in elements {
        let (a, b) = (model.elements[e].a, model.elements[e].b);
        let (ra, rb) = (find(&mut parent, a), find(&mut parent, b));
        parent[ra] = rb;
    }
    let mut count = std::collections::BTreeMap::new();
    for &e in elements {
        let r = find(&mut parent, model.elements[e].a);
        *count.entry(r).or_insert(0usize) += 1;
    }
    let mut sizes: Vec<usize> = count.into_values().collect();
    sizes.sort_unstable_by(|a, b| b.cmp(a));
    sizes
}

#[test]
fn metis_partition_covers_every_element_once_is_deterministic_and_connected() {
    for (scene, parts) in [(tower_scene(6), 8), (grid_scene(20), 16), (tower_scene(6), 4)] {
        let model = Model::from_scene(&scene).unwrap();
        let p = Partition::metis(&model, parts).unwrap();
        assert_eq!(p.len(), parts);
        let mut seen = vec![0usize; model.elements.len()];
        for (s, els) in p.elements_of.iter().enumerate() {
            assert!(!els.is_empty(), "subdomain {s} is empty");
            for &e in els {
                seen[e] += 1;
                assert_eq!(p.part_of[e], s);
            }
        }
        assert!(seen.iter().all(|&c| c == 1), "every element in exactly one subdomain");
        assert_eq!(Partition::metis(&model, parts).unwrap(), p, "deterministic");
        let avg = model.elements.len() as f64 / parts as f64;
        for els in &p.elements_of {
            // Balanced (the repair keeps counts within [1/2, 3/2] of the average).
            assert!((els.len() as f64) > 0.5 * avg && (els.len() as f64) < 1.5 * avg);
            // Connected enough: one piece holds nearly all of the part.
            let sizes = pieces(&model, els);
            assert!(
                sizes[0] as f64 >= 0.95 * els.len() as f64,
                "{}: pieces {sizes:?}",
                scene.scene.name
            );
        }
    }
}

#[test]
fn dd_on_a_metis_partition_matches_the_direct_solver() {
    let linear_grid = grid(&GridParams {
        nx: 12,
        ny: 12,
        unilateral: false,
        ..Default::default()
    });
    // Stiff cables: the default tower's soft cables need >1000 cg
    // iterations with either partitioner.
    let linear_tower = tower(&TowerParams {
        nx: 5,
        ny: 5,
        nz: 5,
        unilateral: false,
        ea_cable: 10000.0,
        ..Default::default()
    });
    for (mut scene, parts) in [(linear_grid, 8), (linear_tower, 4)] {
        scene.solver.partitioner = Partitioner::Metis;
        assert_matches_direct(&scene, Method::Cg, parts, 1e-8);
    }
    // Nonsmooth (slack cables): the multilevel method.
    let mut scene = grid_scene(12);
    scene.solver.partitioner = Partitioner::Metis;
    assert_matches_direct(&scene, Method::Multilevel, 8, 1e-8);
}

#[test]
fn the_scene_chooses_the_partitioner() {
    let mut scene = grid_scene(12);
    let model = Model::from_scene(&scene).unwrap();
    scene.solver.partitioner = Partitioner::Bisection;
    let b = nsdd::solve::decompose(&model, &scene, 8).unwrap();
    assert_eq!(b.partition, Partition::bisection(&model, 8).unwrap());
    scene.solver.partitioner = Partitioner::Metis;
    let m = nsdd::solve::decompose(&model, &scene, 8).unwrap();
    assert_eq!(m.partition, Partition::metis(&model, 8).unwrap());
    assert_ne!(m.partition, b.partition);
    // And through the scene file.
    let text = scene.to_toml_string().unwrap();
    assert!(text.contains("partitioner = \"metis\""), "{text}");
}
