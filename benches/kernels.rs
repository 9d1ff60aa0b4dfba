//! Interface and cable kernels against the memory bandwidth of a plain copy.
//!
//! Every gather/scatter kernel runs over an index array of interface shape:
//! nodes of 3 consecutive dofs, sorted, with small random gaps (0–4 nodes)
//! and an occasional swap of neighbouring nodes, into a local vector about
//! 2.5× longer than the interface. The throughput is the f64 payload of the
//! interface, `8 · n` bytes, for every kernel and for the reference
//! `copy_from_slice` of `n` f64s, so the GB/s figures compare directly:
//! `kernel GB/s / copy GB/s` is the fraction of copy bandwidth reached.
//! (The kernels also read a 4-byte index per entry, `jump` and
//! `force_update` two values and two indices per entry: that traffic is not
//! counted.)
//!
//! Run: `cargo bench --bench kernels`.

use std::hint::black_box;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use nsdd::kernels;

/// Interface sizes (entries).
const SIZES: [usize; 3] = [1_000, 100_000, 1_000_000];

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

/// An interface index array of `n` entries and the length of the local
/// vector it points into.
fn interface_indices(n: usize, seed: u64) -> (Vec<u32>, usize) {
    let mut rng = Rng(seed | 1);
    let n_nodes = n.div_ceil(3);
    let mut nodes = Vec::with_capacity(n_nodes);
    let mut node = 0usize;
    for _ in 0..n_nodes {
        node += 1 + (rng.next() % 5) as usize;
        nodes.push(node);
    }
    // Sorted-ish: swap a few neighbouring nodes.
    for k in 1..n_nodes {
        if rng.next() % 16 == 0 {
            nodes.swap(k - 1, k);
        }
    }
    let mut idx = Vec::with_capacity(n);
    'outer: for &p in &nodes {
        for d in 0..3 {
            if idx.len() == n {
                break 'outer;
            }
            idx.push((3 * p + d) as u32);
        }
    }
    let len = 3 * (node + 2);
    (idx, len)
}

fn random_vec(n: usize, seed: u64) -> Vec<f64> {
    let mut rng = Rng(seed | 1);
    (0..n).map(|_| rng.unit()).collect()
}

fn gather_scatter(c: &mut Criterion) {
    let mut g = c.benchmark_group("interface");
    for &n in &SIZES {
        let (lo_idx, lo_len) = interface_indices(n, 0x9e37_79b9_7f4a_7c15);
        let (hi_idx, hi_len) = interface_indices(n, 0xd1b5_4a32_d192_ed03);
        let lo = random_vec(lo_len, 1);
        let hi = random_vec(hi_len, 2);
        let src = random_vec(n, 3);
        let mut out = vec![0.0; n];
        let mut r = random_vec(lo_len, 4);
        g.throughput(Throughput::Bytes((8 * n) as u64));

        g.bench_with_input(BenchmarkId::new("copy", n), &n, |b, _| {
            b.iter(|| {
                out.copy_from_slice(black_box(&src));
                black_box(&mut out);
            })
        });
        g.bench_with_input(BenchmarkId::new("gather", n), &n, |b, _| {
            b.iter(|| {
                kernels::gather(&mut out, black_box(&lo), &lo_idx);
                black_box(&mut out);
            })
        });
        g.bench_with_input(BenchmarkId::new("scatter_add", n), &n, |b, _| {
            // Alternating signs keep `r` bounded over the iterations.
            let mut coef = 1.0;
            b.iter(|| {
                kernels::scatter_add(&mut r, &lo_idx, black_box(&src), coef);
                coef = -coef;
                black_box(&mut r);
            })
        });
        g.bench_with_input(BenchmarkId::new("jump", n), &n, |b, _| {
            b.iter(|| {
                kernels::jump(&mut out, black_box(&lo), &lo_idx, black_box(&hi), &hi_idx);
                black_box(&mut out);
            })
        });
        g.bench_with_input(BenchmarkId::new("force_update", n), &n, |b, _| {
            let mut d = 1e-3;
            b.iter(|| {
                kernels::force_update(&mut out, d, black_box(&lo), &lo_idx, black_box(&hi), &hi_idx);
                d = -d;
                black_box(&mut out);
            })
        });
    }
    g.finish();
}

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
