//! Interface and cable kernels against the memory bandwidth of a plain copy.
//!
//! The interface kernels run over ALL interfaces of a real decomposition
//! (`Partition::bisection` of a generated grid or tower, as the solver
//! builds it), each kernel call per interface into that interface's slice
//! of one global interface vector and the per-subdomain local vectors:
//! - `gather`: lo-side trace, `out = B_lo v_lo`;
//! - `scatter_add`: lo-side force, `r_lo += B_loᵀ f`;
//! - `jump`: `out = B_lo v_lo − B_hi v_hi`;
//! - `force_update`: `f += d (B_lo g_lo − B_hi g_hi)`.
//!
//! Each kernel in two forms over the same maps: `*_idx` the indexed kernel
//! (one `u32` per entry and side), `*_runs` the run kernel (what the solver
//! runs). The throughput is the f64 payload of
//! the interface vector, `8 · n` bytes for `n` entries, for every kernel
//! and for the reference `copy_from_slice` of `n` f64s, so the GiB/s figures
//! compare directly: `kernel GiB/s / copy GiB/s` is the fraction of copy
//! bandwidth reached. `gather` moves the bytes of `copy` (one read, one
//! write per entry); `jump` and `scatter_add` move 1.5 times as many (two
//! reads, one write) and `force_update` twice as many (three reads, one
//! write), so `copy_1.5x` and `copy_2x` copy 1.5 n and 2 n values: the
//! bytes-for-bytes reference of those kernels (the indexed forms also read
//! a 4-byte index per entry and side, not counted). The run statistics of
//! each case are printed on stderr.
//!
//! Run: `cargo bench --bench kernels`.

use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use nsdd::decomposition::Decomposition;
use nsdd::generate::{grid, tower, GridParams, TowerParams};
use nsdd::kernels::{self, Run, Side};
use nsdd::model::Model;
use nsdd::scene::Scene;
use nsdd::solve::decompose;

/// Deterministic xorshift generator (no extra dependency).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }

    /// Uniform in [-1, 1).
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 52) as f64 - 1.0
    }
}

fn random_vec(n: usize, seed: u64) -> Vec<f64> {
    let mut rng = Rng(seed | 1);
    (0..n).map(|_| rng.unit()).collect()
}

/// One interface's maps in the three forms.
struct Iface {
    lo: usize,
    hi: usize,
    start: usize,
    end: usize,
    lo_idx: Vec<u32>,
    hi_idx: Vec<u32>,
    runs: Vec<Run>,
}

/// Every interface of `dec`.
fn interfaces(dec: &Decomposition) -> Vec<Iface> {
    dec.interfaces
        .iter()
        .map(|it| {
            let r = it.start..it.end;
            Iface {
                lo: it.lo,
                hi: it.hi,
                start: it.start,
                end: it.end,
                lo_idx: dec.entry_lo_local[r.clone()].to_vec(),
                hi_idx: dec.entry_hi_local[r.clone()].to_vec(),
                runs: kernels::runs(&dec.entry_lo_local[r.clone()], &dec.entry_hi_local[r]),
            }
        })
        .collect()
}

/// Prints entries, runs, mean run length and the share of entries in runs
/// of 8 or more.
fn run_stats(name: &str, dec: &Decomposition, ifs: &[Iface]) {
    let n: usize = ifs.iter().map(|i| i.end - i.start).sum();
    let runs: Vec<&Run> = ifs.iter().flat_map(|i| &i.runs).collect();
    let long: usize = runs.iter().filter(|r| r.len >= 8).map(|r| r.len as usize).sum();
    let dofs: usize = dec.subdomains.iter().map(|s| s.dofs.len()).sum();
    eprintln!(
        "{name}: {} subdomains, {} local dofs, {} interfaces, {n} entries; runs: {} (mean {:.1}, {:.0} % of entries in runs ≥ 8)",
        dec.len(),
        dofs,
        ifs.len(),
        runs.len(),
        n as f64 / runs.len().max(1) as f64,
        100.0 * long as f64 / n.max(1) as f64,
    );
}

/// Cases: (name, scene, subdomains).
fn cases() -> Vec<(&'static str, Scene, usize)> {
    let g = |n: usize| {
        grid(&GridParams {
            nx: n,
            ny: n,
            ..Default::default()
        })
    };
    let t = |n: usize, nz: usize| {
        tower(&TowerParams {
            nx: n,
            ny: n,
            nz,
            ..Default::default()
        })
    };
    vec![
        ("grid40-16", g(40), 16),
        ("grid300-64", g(300), 64),
        ("tower60-64", t(60, 60), 64),
    ]
}

/// `which` selects the form: 0 indexed, 1 runs.
fn gather_all(out: &mut [f64], v: &[Vec<f64>], ifs: &[Iface], which: u8) {
    for i in ifs {
        let o = &mut out[i.start..i.end];
        match which {
            0 => kernels::gather(o, &v[i.lo], &i.lo_idx),
            _ => kernels::gather_runs(o, &v[i.lo], Side::Lo, &i.runs),
        }
    }
}

fn scatter_all(r: &mut [Vec<f64>], f: &[f64], ifs: &[Iface], coef: f64, which: u8) {
    for i in ifs {
        let (rl, fi) = (&mut r[i.lo], &f[i.start..i.end]);
        match which {
            0 => kernels::scatter_add(rl, &i.lo_idx, fi, coef),
            _ => kernels::scatter_add_runs(rl, Side::Lo, &i.runs, fi, coef),
        }
    }
}

fn jump_all(out: &mut [f64], v: &[Vec<f64>], ifs: &[Iface], which: u8) {
    for i in ifs {
        let (o, a, b) = (&mut out[i.start..i.end], &v[i.lo], &v[i.hi]);
        match which {
            0 => kernels::jump(o, a, &i.lo_idx, b, &i.hi_idx),
            _ => kernels::jump_runs(o, a, b, &i.runs),
        }
    }
}

fn force_all(f: &mut [f64], d: f64, g: &[Vec<f64>], ifs: &[Iface], which: u8) {
    for i in ifs {
        let (o, a, b) = (&mut f[i.start..i.end], &g[i.lo], &g[i.hi]);
        match which {
            0 => kernels::force_update(o, d, a, &i.lo_idx, b, &i.hi_idx),
            _ => kernels::force_update_runs(o, d, a, b, &i.runs),
        }
    }
}

const FORMS: [(&str, u8); 2] = [("idx", 0), ("runs", 1)];

fn gather_scatter(c: &mut Criterion) {
    let mut g = c.benchmark_group("interface");
    for (name, scene, parts) in cases() {
        let model = Model::from_scene(&scene).unwrap();
        let dec = decompose(&model, &scene, parts).unwrap();
        drop(model);
        let ifs = interfaces(&dec);
        run_stats(name, &dec, &ifs);
        let n = dec.n_entries();
        let v: Vec<Vec<f64>> = dec
            .subdomains
            .iter()
            .enumerate()
            .map(|(s, sd)| random_vec(sd.dofs.len(), 11 + s as u64))
            .collect();
        let mut r = v.clone();
        let src = random_vec(n, 3);
        let mut out = vec![0.0; n];
        g.throughput(Throughput::Bytes((8 * n) as u64));

        g.bench_with_input(BenchmarkId::new("copy", name), &n, |b, _| {
            b.iter(|| {
                out.copy_from_slice(black_box(&src));
                black_box(&mut out);
            })
        });
        // Copies moving as many bytes as the kernels that read two vectors
        // (jump, scatter_add: 24 bytes per entry = a copy of 1.5 n values)
        // or three (force_update: 32 bytes = 2 n values); reported against
        // the same n-entry throughput, so fractions read off directly.
        for (label, m) in [("copy_1.5x", n + n / 2), ("copy_2x", 2 * n)] {
            let big_src = random_vec(m, 4);
            let mut big_out = vec![0.0; m];
            g.bench_with_input(BenchmarkId::new(label, name), &n, |b, _| {
                b.iter(|| {
                    big_out.copy_from_slice(black_box(&big_src));
                    black_box(&mut big_out);
                })
            });
        }
        for (form, which) in FORMS {
            g.bench_with_input(BenchmarkId::new(format!("gather_{form}"), name), &n, |b, _| {
                b.iter(|| {
                    gather_all(&mut out, black_box(&v), &ifs, which);
                    black_box(&mut out);
                })
            });
            g.bench_with_input(BenchmarkId::new(format!("scatter_add_{form}"), name), &n, |b, _| {
                // Alternating signs keep `r` bounded over the iterations.
                let mut coef = 1.0;
                b.iter(|| {
                    scatter_all(&mut r, black_box(&src), &ifs, coef, which);
                    coef = -coef;
                    black_box(&mut r);
                })
            });
            g.bench_with_input(BenchmarkId::new(format!("jump_{form}"), name), &n, |b, _| {
                b.iter(|| {
                    jump_all(&mut out, black_box(&v), &ifs, which);
                    black_box(&mut out);
                })
            });
            g.bench_with_input(BenchmarkId::new(format!("force_update_{form}"), name), &n, |b, _| {
                let mut d = 1e-3;
                b.iter(|| {
                    force_all(&mut out, d, black_box(&v), &ifs, which);
                    d = -d;
                    black_box(&mut out);
                })
            });
        }
    }
    g.finish();
}

/// Cable counts of the `cable_projection` bench.
const SIZES: [usize; 3] = [1_000, 100_000, 1_000_000];

fn cables(c: &mut Criterion) {
    let mut g = c.benchmark_group("cable_projection");
    for &n in &SIZES {
        // About half of the cables slack.
        let elong = random_vec(n, 5);
        let e0: Vec<f64> = random_vec(n, 6).iter().map(|v| 0.1 * v).collect();
        let k: Vec<f64> = random_vec(n, 7).iter().map(|v| 100.0 * (1.5 + v)).collect();
        let mut lambda = vec![0.0; n];
        g.throughput(Throughput::Elements(n as u64));
        g.bench_with_input(BenchmarkId::from_parameter(n), &n, |b, _| {
            b.iter(|| {
                // Branch-free kernel: the cost does not depend on whether
                // λ changed since the last call, so no reset is needed.
                black_box(kernels::cable_projection(&mut lambda, black_box(&elong), &e0, &k))
            })
        });
    }
    g.finish();
}

fn config() -> Criterion {
    Criterion::default()
        .sample_size(10)
        .warm_up_time(Duration::from_millis(300))
        .measurement_time(Duration::from_millis(800))
}

criterion_group! {
    name = benches;
    config = config();
    targets = gather_scatter, cables
}
criterion_main!(benches);
