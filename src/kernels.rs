//! The interface and cable kernels of the iteration, over plain slices.
//!
//! The interface kernels come in two forms over the same maps:
//! - *indexed* (`jump`, `gather`, `scatter_add`, `force_update`): one
//!   `u32` local index per entry and side. Each entry is a scalar indexed
//!   load or store (x86-64 has no gather without AVX-512).
//! - *runs* (`jump_runs`, …): the entries as maximal [`Run`]s whose local
//!   dofs are consecutive on both sides. Each run is a slice-to-slice loop
//!   the compiler vectorises, with no per-entry index. The local layout of
//!   `crate::decomposition` (interior dofs first, then interface by
//!   interface) makes an interface's own dofs one run: mean run lengths
//!   22–56 and 89–95 % of the entries in runs of 8 or more on the grids and
//!   towers of `benches/kernels.rs` (5–8 and 47–64 % when each subdomain
//!   numbered its dofs in global order).
//!
//! Both forms perform the same floating-point operations in the same order,
//! so they agree bit for bit; the solver uses the run form, the indexed form
//! is the reference it is tested against. The adjoint identities
//! `⟨gather(v), f⟩ = ⟨v, scatter(f)⟩` are tested for both.

/// Entries `entry..entry+len` of an interface whose local dofs are
/// `lo..lo+len` in its `lo` subdomain and `hi..hi+len` in its `hi` one.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct Run {
    pub entry: u32,
    pub lo: u32,
    pub hi: u32,
    pub len: u32,
}

/// Side of an interface a gather or scatter works on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Side {
    Lo,
    Hi,
}

impl Run {
    /// First local dof of the run on `side`.
    #[inline]
    pub fn start(&self, side: Side) -> usize {
        match side {
            Side::Lo => self.lo as usize,
            Side::Hi => self.hi as usize,
        }
    }
}

/// Maximal runs of the index maps `lo_idx`, `hi_idx` (equal lengths): a new
/// run starts wherever either side is not the previous local dof plus one.
/// Covers entries `0..lo_idx.len()` in order; set-up only (allocates).
pub fn runs(lo_idx: &[u32], hi_idx: &[u32]) -> Vec<Run> {
    assert_eq!(lo_idx.len(), hi_idx.len(), "lo and hi maps differ in length");
    let mut out: Vec<Run> = Vec::new();
    for (j, (&a, &b)) in lo_idx.iter().zip(hi_idx).enumerate() {
        match out.last_mut() {
            Some(r) if r.lo.checked_add(r.len) == Some(a) && r.hi.checked_add(r.len) == Some(b) => r.len += 1,
            _ => out.push(Run {
                entry: j as u32,
                lo: a,
                hi: b,
                len: 1,
            }),
        }
    }
    out
}

/// Interface jump over runs: `out[j] = lo[lo_idx[j]] − hi[hi_idx[j]]`.
#[inline]
pub fn jump_runs(out: &mut [f64], lo: &[f64], hi: &[f64], runs: &[Run]) {
    for r in runs {
        let (e, a, b, n) = (r.entry as usize, r.lo as usize, r.hi as usize, r.len as usize);
        // Slicing first hoists the bounds checks out of the loop, which
        // then vectorises like a copy.
        let (o, x, y) = (&mut out[e..e + n], &lo[a..a + n], &hi[b..b + n]);
        for ((o, &x), &y) in o.iter_mut().zip(x).zip(y) {
            *o = x - y;
        }
    }
}

/// Trace gather over runs: `out[j] = v[idx[j]]` with the `side` map.
#[inline]
pub fn gather_runs(out: &mut [f64], v: &[f64], side: Side, runs: &[Run]) {
    for r in runs {
        let (e, a, n) = (r.entry as usize, r.start(side), r.len as usize);
        out[e..e + n].copy_from_slice(&v[a..a + n]);
    }
}

/// Scatter-add over runs: `r[idx[j]] += coef · f[j]` with the `side` map.
#[inline]
pub fn scatter_add_runs(r: &mut [f64], side: Side, runs: &[Run], f: &[f64], coef: f64) {
    for run in runs {
        let (e, a, n) = (run.entry as usize, run.start(side), run.len as usize);
        for (x, &fj) in r[a..a + n].iter_mut().zip(&f[e..e + n]) {
            *x += coef * fj;
        }
    }
}

/// [`force_update`] over runs:
/// `force[j] += d · (g_lo[lo_idx[j]] − g_hi[hi_idx[j]])`.
#[inline]
pub fn force_update_runs(force: &mut [f64], d: f64, g_lo: &[f64], g_hi: &[f64], runs: &[Run]) {
    for r in runs {
        let (e, a, b, n) = (r.entry as usize, r.lo as usize, r.hi as usize, r.len as usize);
        let (f, x, y) = (&mut force[e..e + n], &g_lo[a..a + n], &g_hi[b..b + n]);
        for ((f, &x), &y) in f.iter_mut().zip(x).zip(y) {
            *f += d * (x - y);
        }
    }
}

/// Interface jump: `out[j] = lo[lo_idx[j]] − hi[hi_idx[j]]`.
#[inline]
pub fn jump(out: &mut [f64], lo: &[f64], lo_idx: &[u32], hi: &[f64], hi_idx: &[u32]) {
    debug_assert!(lo_idx.len() == out.len() && hi_idx.len() == out.len());
    for ((o, &a), &b) in out.iter_mut().zip(lo_idx).zip(hi_idx) {
        *o = lo[a as usize] - hi[b as usize];
    }
}

/// Trace gather: `out[j] = v[idx[j]]`.
#[inline]
pub fn gather(out: &mut [f64], v: &[f64], idx: &[u32]) {
    for (o, &i) in out.iter_mut().zip(idx) {
        *o = v[i as usize];
    }
}

/// Scatter-add: `r[idx[j]] += coef · f[j]` (interface force to subdomain).
#[inline]
pub fn scatter_add(r: &mut [f64], idx: &[u32], f: &[f64], coef: f64) {
    for (&i, &fj) in idx.iter().zip(f) {
        r[i as usize] += coef * fj;
    }
}

/// Local stage of the interface forces with `(X^D)^{-1} = d Σ_E B_Eᵀ B_E`:
/// `force[j] += d · (g_lo[lo_idx[j]] − g_hi[hi_idx[j]])`, where `g_E = B_E jump`.
#[inline]
pub fn force_update(force: &mut [f64], d: f64, g_lo: &[f64], lo_idx: &[u32], g_hi: &[f64], hi_idx: &[u32]) {
    for ((f, &a), &b) in force.iter_mut().zip(lo_idx).zip(hi_idx) {
        *f += d * (g_lo[a as usize] - g_hi[b as usize]);
    }
}

/// Per-cable local stage with `W^D = k_c`: `λ ← max(0, −(e + e0))`.
/// Returns `(Σ Δλ², Σ (k Δλ)²)`: the change as a length and as the force
/// it moves.
#[inline]
pub fn cable_projection(lambda: &mut [f64], elongation: &[f64], e0: &[f64], k: &[f64]) -> (f64, f64) {
    let mut change = 0.0;
    let mut force = 0.0;
    for (((l, &e), &p), &kc) in lambda.iter_mut().zip(elongation).zip(e0).zip(k) {
        let new = (-(e + p)).max(0.0);
        let d = new - *l;
        change += d * d;
        force += (kc * d) * (kc * d);
        *l = new;
    }
    (change, force)
}

/// Sum of squares: [`dot`] of `v` with itself.
#[inline]
pub fn norm2(v: &[f64]) -> f64 {
    dot(v, v)
}

/// `Σ a_i b_i` over the common length, in eight interleaved partial sums
/// (lane `k` takes the indices `≡ k mod 8`), added pairwise at the end.
/// A plain `.sum()` is one chain of dependent additions, which the
/// compiler must keep in order: about 4 cycles per entry, where the dense
/// blocks of an iteration (`Z_Eᵀ r_E`, the deluxe face blocks) have
/// hundreds of thousands (30³ tower at contrast 1e4, 16 subdomains: 11 % of
/// its solve). The order is fixed, so the result is the same on every run
/// and with or without AVX2.
#[inline]
pub fn dot(a: &[f64], b: &[f64]) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if a.len().min(b.len()) >= 32 && std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: AVX2 is present (checked just above).
        return unsafe { dot_avx2(a, b) };
    }
    dot_lanes(a, b)
}

#[inline(always)]
fn dot_lanes(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len().min(b.len());
    let (a, b) = (&a[..n], &b[..n]);
    let mut acc = [0.0f64; 8];
    let (ca, cb) = (a.chunks_exact(8), b.chunks_exact(8));
    let (ra, rb) = (ca.remainder(), cb.remainder());
    for (x, y) in ca.zip(cb) {
        for k in 0..8 {
            acc[k] += x[k] * y[k];
        }
    }
    for (k, (x, y)) in ra.iter().zip(rb).enumerate() {
        acc[k] += x * y;
    }
    ((acc[0] + acc[4]) + (acc[1] + acc[5])) + ((acc[2] + acc[6]) + (acc[3] + acc[7]))
}

/// [`dot_lanes`] compiled for AVX2 (the same operations in the same order).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn dot_avx2(a: &[f64], b: &[f64]) -> f64 {
    dot_lanes(a, b)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic xorshift (no extra dependency).
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> u64 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            self.0
        }
        fn below(&mut self, n: usize) -> usize {
            (self.next() % n as u64) as usize
        }
        fn unit(&mut self) -> f64 {
            (self.next() >> 11) as f64 / (1u64 << 52) as f64 - 1.0
        }
    }

    /// Injective maps of `n` entries into `0..len` made of stretches of
    /// random length (1–9), random gaps, and cross-point-like entries placed
    /// far away; `lo` and `hi` break at different places.
    fn maps(rng: &mut Rng, n: usize) -> (Vec<u32>, Vec<u32>, usize) {
        let one = |rng: &mut Rng| {
            let mut idx: Vec<u32> = Vec::with_capacity(n);
            let mut next = rng.below(4);
            while idx.len() < n {
                let stretch = (1 + rng.below(9)).min(n - idx.len());
                for _ in 0..stretch {
                    idx.push(next as u32);
                    next += 1;
                }
                next += rng.below(3);
            }
            // Move a few entries to the end of the vector (cross points).
            let mut tail = next + 1;
            for v in idx.iter_mut() {
                if rng.below(8) == 0 {
                    *v = tail as u32;
                    tail += 1 + rng.below(2);
                }
            }
            (idx, tail + 1)
        };
        let (lo, nl) = one(rng);
        let (hi, nh) = one(rng);
        (lo, hi, nl.max(nh))
    }

    fn dot(a: &[f64], b: &[f64]) -> f64 {
        a.iter().zip(b).map(|(x, y)| x * y).sum()
    }

    /// The lane sums agree with the plain sum to round-off, on every length
    /// around the lane and dispatch boundaries, and both code paths give the
    /// same bits.
    #[test]
    fn dot_in_lanes_is_the_dot_product() {
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        for n in [0, 1, 7, 8, 9, 31, 32, 33, 100, 1003] {
            let a: Vec<f64> = (0..n).map(|_| rng.unit()).collect();
            let b: Vec<f64> = (0..n).map(|_| rng.unit()).collect();
            let (plain, lanes) = (dot(&a, &b), super::dot(&a, &b));
            let mag: f64 = a.iter().zip(&b).map(|(x, y)| (x * y).abs()).sum();
            assert!(
                (plain - lanes).abs() <= 1e-15 * mag.max(1e-300) * n as f64,
                "{n}: {plain} {lanes}"
            );
            assert_eq!(lanes.to_bits(), super::dot_lanes(&a, &b).to_bits(), "{n}");
            assert_eq!(super::norm2(&a).to_bits(), super::dot(&a, &a).to_bits());
        }
        // Unequal lengths: the common part.
        assert_eq!(super::dot(&[1.0, 2.0, 3.0], &[4.0, 5.0]), 14.0);
    }

    #[test]
    fn runs_cover_the_maps() {
        assert!(runs(&[], &[]).is_empty());
        let r = runs(&[4, 5, 6, 9, 10, 0], &[0, 1, 3, 4, 5, 6]);
        let want = [(0, 4, 0, 2), (2, 6, 3, 1), (3, 9, 4, 2), (5, 0, 6, 1)];
        let got: Vec<_> = r.iter().map(|r| (r.entry, r.lo, r.hi, r.len)).collect();
        assert_eq!(got, want);
        let mut rng = Rng(0x2545_f491_4f6c_dd1d);
        for n in [1, 2, 3, 17, 200] {
            let (lo, hi, _) = maps(&mut rng, n);
            let r = runs(&lo, &hi);
            let mut j = 0;
            for run in &r {
                assert_eq!(run.entry as usize, j);
                for k in 0..run.len {
                    assert_eq!(lo[j], run.lo + k);
                    assert_eq!(hi[j], run.hi + k);
                    j += 1;
                }
            }
            assert_eq!(j, n);
        }
    }

    /// The run kernels equal the indexed ones bit for bit (same operations
    /// in the same order) on random maps, and satisfy the adjoint
    /// identities; runs of length 0 are no-ops.
    #[test]
    fn run_kernels_match_indexed() {
        let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
        for n in [0, 1, 2, 5, 31, 64, 257] {
            let (lo_idx, hi_idx, len) = maps(&mut rng, n);
            let mut r = runs(&lo_idx, &hi_idx);
            // Empty runs anywhere change nothing.
            r.insert(0, Run::default());
            r.push(Run {
                entry: n as u32,
                lo: len as u32,
                hi: len as u32,
                len: 0,
            });
            let lo: Vec<f64> = (0..len).map(|_| rng.unit()).collect();
            let hi: Vec<f64> = (0..len).map(|_| rng.unit()).collect();
            let f: Vec<f64> = (0..n).map(|_| rng.unit()).collect();

            let (mut a, mut b) = (vec![0.0; n], vec![0.0; n]);
            jump(&mut a, &lo, &lo_idx, &hi, &hi_idx);
            jump_runs(&mut b, &lo, &hi, &r);
            assert_eq!(a, b);

            for (side, idx, v) in [(Side::Lo, &lo_idx, &lo), (Side::Hi, &hi_idx, &hi)] {
                gather(&mut a, v, idx);
                gather_runs(&mut b, v, side, &r);
                assert_eq!(a, b);
                let (mut sa, mut sb) = (v.clone(), v.clone());
                scatter_add(&mut sa, idx, &f, -0.75);
                scatter_add_runs(&mut sb, side, &r, &f, -0.75);
                assert_eq!(sa, sb);
                // ⟨gather(v), f⟩ = ⟨v, scatter(f)⟩
                let mut s = vec![0.0; len];
                scatter_add_runs(&mut s, side, &r, &f, 1.0);
                let (lhs, rhs) = (dot(&b, &f), dot(v, &s));
                assert!((lhs - rhs).abs() <= 1e-12 * lhs.abs().max(1.0));
            }

            let (mut fa, mut fb) = (f.clone(), f.clone());
            force_update(&mut fa, 0.3, &lo, &lo_idx, &hi, &hi_idx);
            force_update_runs(&mut fb, 0.3, &lo, &hi, &r);
            assert_eq!(fa, fb);

            // ⟨J(lo, hi), f⟩ = ⟨lo, Bᵀ_lo f⟩ − ⟨hi, Bᵀ_hi f⟩
            jump_runs(&mut b, &lo, &hi, &r);
            let (mut sl, mut sh) = (vec![0.0; len], vec![0.0; len]);
            scatter_add_runs(&mut sl, Side::Lo, &r, &f, 1.0);
            scatter_add_runs(&mut sh, Side::Hi, &r, &f, -1.0);
            let (lhs, rhs) = (dot(&b, &f), dot(&lo, &sl) + dot(&hi, &sh));
            assert!((lhs - rhs).abs() <= 1e-12 * lhs.abs().max(1.0));
        }
    }
}
