//! The interface and cable kernels of the iteration, over plain slices.
//!
//! Each is a single pass with an index array, no bounds checks in the hot
//! loop beyond the slice zips, so the compiler vectorises the arithmetic
//! (the gathers stay scalar loads on x86-64 without AVX-512). The adjoint
//! identities `⟨gather(v), f⟩ = ⟨v, scatter(f)⟩` are tested.

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

/// Sum of squares.
#[inline]
pub fn norm2(v: &[f64]) -> f64 {
    v.iter().map(|x| x * x).sum()
}
