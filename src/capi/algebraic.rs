//! The algebraic level of the C ABI: subdomain matrices, local-to-global
//! maps, dof points, kernels and cables, set up once and solved for any
//! number of right-hand sides.

use super::*;

// ---------------------------------------------------------------------------
// Algebraic level.

/// A new algebraic problem with `n_subdomains` (>= 1) subdomains over
/// `n_global_dofs` (>= 1) global dofs, stored in `*out` (NULL on failure).
/// Then: `nsdd_alg_set_subdomain` for every subdomain,
/// `nsdd_alg_set_dof_points` (needed by the multilevel method), optionally
/// `nsdd_alg_set_kernel` and `nsdd_alg_add_cable`, then `nsdd_alg_setup`
/// once and `nsdd_alg_solve` for each right-hand side. Changing anything
/// after `nsdd_alg_setup` discards the set-up (call it again).
///
/// # Safety
/// `out` must point to writable storage for one pointer.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_new(
    n_subdomains: usize,
    n_global_dofs: usize,
    out: *mut *mut NsddAlgebraic,
) -> NsddStatus {
    ffi_guard(|| {
        unsafe { clear_out(out, "out")? };
        if n_subdomains == 0 {
            return Err(invalid("n_subdomains must be at least 1"));
        }
        if n_global_dofs == 0 {
            return Err(invalid("n_global_dofs must be at least 1"));
        }
        if n_subdomains > n_global_dofs {
            return Err(invalid(format!(
                "n_subdomains = {n_subdomains} exceeds n_global_dofs = {n_global_dofs}"
            )));
        }
        let h = NsddAlgebraic {
            n_global: n_global_dofs,
            subdomains: (0..n_subdomains).map(|_| None).collect(),
            dof_points: None,
            cables: Vec::new(),
            setup: None,
        };
        unsafe { out.write(boxed(h)) };
        Ok(())
    })
}

/// Releases an algebraic problem (NULL is ignored).
///
/// # Safety
/// `alg` must be NULL or a live algebraic handle, not used afterwards.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_destroy(alg: *mut NsddAlgebraic) {
    let _ = catch_unwind(AssertUnwindSafe(|| unsafe { destroy(alg) }));
}

pub(super) fn check_subdomain(h: &NsddAlgebraic, s: usize) -> FfiResult {
    if s >= h.subdomains.len() {
        return Err(invalid(format!(
            "subdomain {s} out of range (the problem has {} subdomains)",
            h.subdomains.len()
        )));
    }
    Ok(())
}

/// Sets subdomain `s` (0-based): its stiffness `K_E` (`n_local × n_local`,
/// symmetric positive semi-definite) in 0-based CSR — `row_ptr` has
/// `n_local + 1` entries, `col_idx` and `values` have `row_ptr[n_local]` —
/// and `local_to_global` (`n_local` distinct global dof ids, any order). Give
/// either the full symmetric matrix or its lower triangle: entries above the
/// diagonal (column > row) are ignored, and duplicates are summed. A matrix
/// given as its upper triangle only is INVALID_ARGUMENT. Global dofs with
/// equal ids in several subdomains are glued (interface dofs). The local
/// numbering given here is the one of `nsdd_alg_set_kernel`,
/// `nsdd_alg_add_cable` and the right-hand sides of `nsdd_alg_solve`. The
/// arrays are copied.
///
/// # Safety
/// `alg` must be a live algebraic handle; the arrays must have the lengths
/// above.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_set_subdomain(
    alg: *mut NsddAlgebraic,
    s: usize,
    n_local: usize,
    row_ptr: *const usize,
    col_idx: *const usize,
    values: *const f64,
    local_to_global: *const usize,
) -> NsddStatus {
    ffi_guard(|| {
        let h = unsafe { handle_mut(alg, "alg")? };
        check_subdomain(h, s)?;
        if n_local == 0 {
            return Err(invalid(format!("subdomain {s}: n_local must be at least 1")));
        }
        let row_ptr = unsafe {
            slice(
                row_ptr,
                n_local.checked_add(1).ok_or_else(|| invalid("n_local too large"))?,
                "row_ptr",
            )?
        };
        if row_ptr[0] != 0 {
            return Err(invalid(format!(
                "subdomain {s}: row_ptr[0] = {}, expected 0 (0-based CSR)",
                row_ptr[0]
            )));
        }
        if let Some(i) = row_ptr.windows(2).position(|w| w[1] < w[0]) {
            return Err(invalid(format!(
                "subdomain {s}: row_ptr[{}] < row_ptr[{i}] (must not decrease)",
                i + 1
            )));
        }
        let nnz = row_ptr[n_local];
        let col_idx = unsafe { slice(col_idx, nnz, "col_idx")? };
        let values = unsafe { slice(values, nnz, "values")? };
        let l2g = unsafe { slice(local_to_global, n_local, "local_to_global")? };
        check_finite("values", values)?;
        if let Some(p) = col_idx.iter().position(|&c| c >= n_local) {
            return Err(invalid(format!(
                "subdomain {s}: col_idx[{p}] = {} out of range (n_local = {n_local})",
                col_idx[p]
            )));
        }
        if let Some(i) = l2g.iter().position(|&g| g >= h.n_global) {
            return Err(invalid(format!(
                "subdomain {s}: local_to_global[{i}] = {} out of range (n_global_dofs = {})",
                l2g[i], h.n_global
            )));
        }
        let mut sorted: Vec<(usize, usize)> = l2g.iter().enumerate().map(|(i, &g)| (g, i)).collect();
        sorted.sort_unstable();
        if let Some(w) = sorted.windows(2).find(|w| w[0].0 == w[1].0) {
            return Err(invalid(format!(
                "subdomain {s}: local_to_global[{}] and local_to_global[{}] are both global dof {}",
                w[0].1.min(w[1].1),
                w[0].1.max(w[1].1),
                w[0].0
            )));
        }
        let mut lower = Vec::with_capacity(nnz);
        let mut n_upper = 0usize;
        let mut n_strict_lower = 0usize;
        for i in 0..n_local {
            for p in row_ptr[i]..row_ptr[i + 1] {
                let j = col_idx[p];
                if j > i {
                    n_upper += 1;
                } else {
                    n_strict_lower += (j < i) as usize;
                    lower.push((i, j, values[p]));
                }
            }
        }
        if n_strict_lower == 0 && n_upper > 0 {
            return Err(invalid(format!(
                "subdomain {s}: only the upper triangle was given (no entry below the diagonal); pass the full symmetric matrix or its lower triangle"
            )));
        }
        h.setup = None;
        h.subdomains[s] = Some(AlgSubdomain {
            n_local,
            lower,
            local_to_global: l2g.to_vec(),
            kernel: None,
        });
        Ok(())
    })
}

/// Sets the point `(xyz[3i], xyz[3i+1], xyz[3i+2])` of the node carrying
/// global dof `i` and its component `component[i]` (0 x, 1 y, 2 z), for
/// every global dof; `n_global` must equal `n_global_dofs`. The multilevel
/// method builds its macro (rigid-body and extension) modes from them.
///
/// # Safety
/// `alg` must be a live algebraic handle; `xyz` must point to `3 *
/// n_global` doubles and `component` to `n_global` bytes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_set_dof_points(
    alg: *mut NsddAlgebraic,
    n_global: usize,
    xyz: *const f64,
    component: *const u8,
) -> NsddStatus {
    ffi_guard(|| {
        let h = unsafe { handle_mut(alg, "alg")? };
        if n_global != h.n_global {
            return Err(invalid(format!(
                "n_global = {n_global}, expected n_global_dofs = {}",
                h.n_global
            )));
        }
        let xyz = unsafe { slice(xyz, 3 * n_global, "xyz")? };
        let comp = unsafe { slice(component, n_global, "component")? };
        check_finite("xyz", xyz)?;
        if let Some(i) = comp.iter().position(|&c| c > 2) {
            return Err(invalid(format!(
                "component[{i}] = {}: expected 0 (x), 1 (y) or 2 (z)",
                comp[i]
            )));
        }
        h.setup = None;
        h.dof_points = Some(
            xyz.chunks_exact(3)
                .zip(comp)
                .map(|(p, &c)| ([p[0], p[1], p[2]], c as usize))
                .collect(),
        );
        Ok(())
    })
}

/// Gives the kernel of subdomain `s`'s matrix (floating subdomains): `r`
/// columns of `n_local` entries, column-major, in the local numbering of
/// `nsdd_alg_set_subdomain` (which must have been called, with the same
/// `n_local`). It must span the kernel the factorization detects (checked at
/// set-up: INVALID_INPUT otherwise). `r = 0` removes a kernel given before.
/// Without it the kernel is computed.
///
/// # Safety
/// `alg` must be a live algebraic handle; `basis` must point to `n_local *
/// r` doubles.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_set_kernel(
    alg: *mut NsddAlgebraic,
    s: usize,
    n_local: usize,
    r: usize,
    basis: *const f64,
) -> NsddStatus {
    ffi_guard(|| {
        let h = unsafe { handle_mut(alg, "alg")? };
        check_subdomain(h, s)?;
        let sub = h.subdomains[s].as_mut().ok_or_else(|| {
            invalid(format!(
                "subdomain {s} has not been set (call nsdd_alg_set_subdomain first)"
            ))
        })?;
        if n_local != sub.n_local {
            return Err(invalid(format!(
                "subdomain {s}: n_local = {n_local}, the subdomain has {}",
                sub.n_local
            )));
        }
        let len = n_local.checked_mul(r).ok_or_else(|| invalid("n_local * r overflows"))?;
        let basis = unsafe { slice(basis, len, "basis")? };
        check_finite("basis", basis)?;
        h.setup = None;
        sub.kernel = if r == 0 { None } else { Some((r, basis.to_vec())) };
        Ok(())
    })
}

/// Adds a unilateral cable to subdomain `s`: its column `h` of
/// `n_entries` (0..6; 0 for a cable whose ends are both fixed) coefficients
/// `coefs` on local dofs `local_dofs`
/// (elongation `e = hᵀ u`), its stiffness `k` (> 0) and prestrain `e0`. The
/// cable is slack when `e + e0 < 0`; its stiffness `k h hᵀ` must be included
/// in the subdomain matrix (the solver removes it when slack), and any
/// prestrain load (`-k e0 h`) belongs in the right-hand side. The cable's
/// index (position in the `lambda` output of `nsdd_alg_solve`: 0, 1, ... in
/// the order of the calls) is stored in `*out_index` (may be NULL).
///
/// # Safety
/// `alg` must be a live algebraic handle; `local_dofs` and `coefs` must
/// point to `n_entries` values (or be NULL when it is 0); `out_index` must
/// be NULL or writable.
#[unsafe(no_mangle)]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn nsdd_alg_add_cable(
    alg: *mut NsddAlgebraic,
    s: usize,
    n_entries: usize,
    local_dofs: *const usize,
    coefs: *const f64,
    k: f64,
    e0: f64,
    out_index: *mut usize,
) -> NsddStatus {
    ffi_guard(|| {
        let h = unsafe { handle_mut(alg, "alg")? };
        check_subdomain(h, s)?;
        let n_local = h.subdomains[s]
            .as_ref()
            .ok_or_else(|| {
                invalid(format!(
                    "subdomain {s} has not been set (call nsdd_alg_set_subdomain first)"
                ))
            })?
            .n_local;
        if n_entries > NSDD_MAX_CABLE_ENTRIES {
            return Err(invalid(format!(
                "n_entries = {n_entries}: expected at most {NSDD_MAX_CABLE_ENTRIES}"
            )));
        }
        let dofs = unsafe { slice(local_dofs, n_entries, "local_dofs")? };
        let coefs = unsafe { slice(coefs, n_entries, "coefs")? };
        if let Some(i) = dofs.iter().position(|&d| d >= n_local) {
            return Err(invalid(format!(
                "local_dofs[{i}] = {} out of range (subdomain {s} has {n_local} dofs)",
                dofs[i]
            )));
        }
        check_finite("coefs", coefs)?;
        if !(k > 0.0 && k.is_finite()) {
            return Err(invalid(format!("k must be positive and finite, got {k}")));
        }
        if !e0.is_finite() {
            return Err(invalid(format!("e0 must be finite, got {e0}")));
        }
        let index = h.cables.len();
        unsafe { write_opt(out_index, "out_index", index)? };
        h.setup = None;
        h.cables.push(AlgCable {
            subdomain: s,
            dofs: dofs.to_vec(),
            coefs: coefs.to_vec(),
            k,
            e0,
        });
        Ok(())
    })
}

/// Number of cables added so far into `*out`.
///
/// # Safety
/// `alg` must be a live algebraic handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_num_cables(alg: *const NsddAlgebraic, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let h = unsafe { handle(alg, "alg")? };
        unsafe { write_out(out, "out", h.cables.len()) }
    })
}

pub(super) fn alg_setup(h: &mut NsddAlgebraic, opts: &SolveOptions) -> FfiResult {
    h.setup = None;
    // The one mapping of a method to its configuration (and the one
    // validation of the settings); `direct` is refused here.
    let dd_options = DdOptions::from_settings(opts)?;
    let coarse = dd_options.coarse;
    let ns = h.subdomains.len();
    let mut subs = Vec::with_capacity(ns);
    for (s, sub) in h.subdomains.iter().enumerate() {
        subs.push(
            sub.as_ref()
                .ok_or_else(|| invalid(format!("subdomain {s} has not been set (nsdd_alg_set_subdomain)")))?,
        );
    }
    let mut covered = vec![false; h.n_global];
    for sub in &subs {
        for &g in &sub.local_to_global {
            covered[g] = true;
        }
    }
    if let Some(g) = covered.iter().position(|c| !c) {
        return Err(invalid(format!("global dof {g} belongs to no subdomain")));
    }
    let dof_points = match (&h.dof_points, coarse) {
        (Some(p), _) => p.clone(),
        (None, false) => vec![([0.0; 3], 0); h.n_global],
        (None, true) => {
            return Err(invalid(
                "the multilevel method needs the dof points (call nsdd_alg_set_dof_points)",
            ))
        }
    };
    for (c, cable) in h.cables.iter().enumerate() {
        let n = subs[cable.subdomain].n_local;
        if let Some(&d) = cable.dofs.iter().find(|&&d| d >= n) {
            return Err(invalid(format!(
                "cable {c}: local dof {d} out of range (subdomain {} now has {n} dofs)",
                cable.subdomain
            )));
        }
    }
    // The decomposition takes each subdomain's dofs in increasing global
    // order and lays them out its own way (interior first, then interface
    // by interface): its local dof p is the caller's local dof order[p];
    // inverse[caller] = p.
    let sorted: Vec<Vec<usize>> = subs
        .iter()
        .map(|sub| {
            let mut o: Vec<usize> = (0..sub.n_local).collect();
            o.sort_unstable_by_key(|&i| sub.local_to_global[i]);
            o
        })
        .collect();
    let dof_sets: Vec<Vec<usize>> = subs
        .iter()
        .zip(&sorted)
        .map(|(sub, o)| o.iter().map(|&i| sub.local_to_global[i]).collect())
        .collect();
    let partition = Partition {
        part_of: vec![],
        elements_of: vec![vec![]; ns],
    };
    let dec = Box::new(Decomposition::from_dof_sets(partition, dof_sets, h.n_global));
    let order: Vec<Vec<usize>> = dec
        .subdomains
        .iter()
        .zip(&sorted)
        .map(|(sd, o)| {
            let mut ord = vec![0; o.len()];
            for (k, &l) in sd.by_global.iter().enumerate() {
                ord[l as usize] = o[k];
            }
            ord
        })
        .collect();
    let inverse: Vec<Vec<usize>> = order
        .iter()
        .map(|o| {
            let mut inv = vec![0; o.len()];
            for (p, &i) in o.iter().enumerate() {
                inv[i] = p;
            }
            inv
        })
        .collect();

    let ops: Vec<crate::Result<SubdomainOperator>> = subs
        .par_iter()
        .enumerate()
        .map(|(s, sub)| {
            let inv = &inverse[s];
            let trip: Vec<(usize, usize, f64)> = sub
                .lower
                .iter()
                .map(|&(i, j, v)| {
                    let (a, b) = (inv[i], inv[j]);
                    (a.max(b), a.min(b), v)
                })
                .collect();
            let stiffness = lower_csc(sub.n_local, &trip)
                .map_err(|e| Error::Numerical(format!("subdomain {s}: cannot build the matrix: {e:?}")))?;
            let kernel = sub.kernel.as_ref().map(|(r, b)| {
                let n = sub.n_local;
                Mat::from_fn(n, *r, |p, q| b[q * n + order[s][p]])
            });
            let name = |p: usize| {
                let i = order[s][p];
                format!("local dof {i} (global dof {})", sub.local_to_global[i])
            };
            let rank = dec.subdomains[s].reference_rank();
            SubdomainOperator::from_matrix(s, stiffness, 64, kernel.as_ref(), Some(&rank), &name)
        })
        .collect();
    let mut operators = Vec::with_capacity(ns);
    for op in ops {
        operators.push(op?);
    }
    let mut loads: Vec<SubdomainLoad> = subs
        .iter()
        .map(|sub| SubdomainLoad {
            constant: vec![0.0; sub.n_local],
            cables: Vec::new(),
        })
        .collect();
    for (c, cable) in h.cables.iter().enumerate() {
        let mut dofs = [NO_DOF; 6];
        let mut coef = [0.0; 6];
        for (k, (&d, &v)) in cable.dofs.iter().zip(&cable.coefs).enumerate() {
            dofs[k] = inverse[cable.subdomain][d] as u32;
            coef[k] = v;
        }
        loads[cable.subdomain].cables.push(CableColumn {
            cable: c,
            dofs,
            coef,
            k: cable.k,
            e0: cable.e0,
        });
    }
    let problem = DdProblem {
        decomposition: &dec,
        operators,
        loads,
        dof_points,
        n_cables: h.cables.len(),
    };
    let solver = DdSolver::from_problem(problem, dd_options)?;
    h.setup = Some(AlgSetup {
        decomposition: dec,
        solver: Box::new(solver),
        order,
    });
    Ok(())
}

/// Factors every subdomain (in parallel), builds the interfaces, the macro
/// space and the coarse problem, and picks the search direction. `options`
/// gives the method (monolevel, multilevel or cg; direct is
/// METHOD_NOT_APPLICABLE), tolerance, iteration limit and search direction;
/// NULL means multilevel with the defaults. Its subdomain count is ignored.
/// Errors: INVALID_ARGUMENT (a subdomain or the dof points not set, a
/// global dof in no subdomain), INVALID_INPUT (bad kernel), MECHANISM,
/// INDEFINITE_SUBDOMAIN, METHOD_NOT_APPLICABLE, NUMERICAL.
///
/// # Safety
/// `alg` must be a live algebraic handle; `options` NULL or a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_setup(alg: *mut NsddAlgebraic, options: *const NsddOptions) -> NsddStatus {
    ffi_guard(|| {
        let h = unsafe { handle_mut(alg, "alg")? };
        let opts = if options.is_null() {
            SolveOptions {
                method: Method::Multilevel,
                ..default_options()
            }
        } else {
            unsafe { handle(options, "options")? }.opts.clone()
        };
        alg_setup(h, &opts)
    })
}

/// The search direction `d` chosen at set-up into `*out`. Errors: NOT_SOLVED
/// before `nsdd_alg_setup`.
///
/// # Safety
/// `alg` must be a live algebraic handle; `out` must point to a writable double.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_search_direction(alg: *const NsddAlgebraic, out: *mut f64) -> NsddStatus {
    ffi_guard(|| {
        let h = unsafe { handle(alg, "alg")? };
        let st = h.setup.as_ref().ok_or_else(not_set_up)?;
        unsafe { write_out(out, "out", st.solver.search_direction()) }
    })
}

pub(super) fn not_set_up() -> Fail {
    fail(
        NsddStatus::NotSolved,
        "the algebraic problem is not set up (call nsdd_alg_setup)",
    )
}

#[allow(clippy::too_many_arguments)]
pub(super) unsafe fn alg_write_outcome(
    h: &NsddAlgebraic,
    out: crate::dd::DdOutcome,
    out_u: *mut f64,
    out_lambda: *mut f64,
    out_iterations: *mut usize,
    out_converged: *mut bool,
) -> FfiResult {
    // A diverged run keeps its status code (outputs are written only on
    // success).
    if let Some(e) = out.divergence() {
        return Err(e.into());
    }
    unsafe { slice_mut(out_u, h.n_global, "out_u")? }.copy_from_slice(&out.u);
    if !out_lambda.is_null() {
        unsafe { slice_mut(out_lambda, h.cables.len(), "out_lambda")? }.copy_from_slice(&out.lambda);
    }
    unsafe {
        write_opt(out_iterations, "out_iterations", out.iterations)?;
        write_opt(out_converged, "out_converged", out.converged())?;
    }
    Ok(())
}

pub(super) fn check_out_ptrs(out_u: *mut f64, out_lambda: *mut f64, n_cables: usize) -> FfiResult {
    check_ptr(out_u, "out_u")?;
    if !out_lambda.is_null() && n_cables > 0 {
        check_ptr(out_lambda, "out_lambda")?;
    }
    Ok(())
}

/// Solves for right-hand sides given per subdomain: `rhs[s]` points to
/// `n_local(s)` doubles in the local numbering of `nsdd_alg_set_subdomain`
/// (each subdomain's share of the load; a force on an interface dof may be
/// split between subdomains in any way). Nothing is added to them: include
/// prestrain loads. Writes the global displacement (`n_global_dofs`
/// doubles, the average of the subdomain copies) to `out_u`, the cable
/// slacks `lambda` (`num_cables` doubles, > 0 for a slack cable) to
/// `out_lambda`, the iteration count and whether the tolerance was reached;
/// `out_lambda`, `out_iterations` and `out_converged` may be NULL. Can be
/// called any number of times after one `nsdd_alg_setup`; each solve starts
/// from zero. Errors: NOT_SOLVED before set-up, DIVERGED.
///
/// # Safety
/// `alg` must be a live algebraic handle; `rhs` must point to `n_subdomains`
/// pointers, each to `n_local(s)` doubles; outputs as described above.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_solve(
    alg: *mut NsddAlgebraic,
    rhs: *const *const f64,
    out_u: *mut f64,
    out_lambda: *mut f64,
    out_iterations: *mut usize,
    out_converged: *mut bool,
) -> NsddStatus {
    ffi_guard(|| {
        let h = unsafe { handle_mut(alg, "alg")? };
        if h.setup.is_none() {
            return Err(not_set_up());
        }
        check_out_ptrs(out_u, out_lambda, h.cables.len())?;
        let ns = h.subdomains.len();
        let ptrs = unsafe { slice(rhs, ns, "rhs")? };
        let st = h.setup.as_mut().ok_or_else(not_set_up)?;
        let mut local: Vec<Vec<f64>> = Vec::with_capacity(ns);
        for (s, (&p, order)) in ptrs.iter().zip(&st.order).enumerate() {
            let r = unsafe { slice(p, order.len(), &format!("rhs[{s}]"))? };
            check_finite(&format!("rhs[{s}]"), r)?;
            local.push(order.iter().map(|&i| r[i]).collect());
        }
        let views: Vec<&[f64]> = local.iter().map(|v| v.as_slice()).collect();
        let out = st.solver.solve_local(&views, false, None)?;
        unsafe { alg_write_outcome(h, out, out_u, out_lambda, out_iterations, out_converged) }
    })
}

/// Like `nsdd_alg_solve`, with the right-hand side given as one global
/// vector `f` of `n_global_dofs` doubles: a value on a dof shared by `m`
/// subdomains is split equally between them.
///
/// # Safety
/// `alg` must be a live algebraic handle; `f` must point to `n_global_dofs`
/// doubles; outputs as for `nsdd_alg_solve`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_solve_global(
    alg: *mut NsddAlgebraic,
    f: *const f64,
    out_u: *mut f64,
    out_lambda: *mut f64,
    out_iterations: *mut usize,
    out_converged: *mut bool,
) -> NsddStatus {
    ffi_guard(|| {
        let h = unsafe { handle_mut(alg, "alg")? };
        if h.setup.is_none() {
            return Err(not_set_up());
        }
        check_out_ptrs(out_u, out_lambda, h.cables.len())?;
        let f = unsafe { slice(f, h.n_global, "f")? };
        check_finite("f", f)?;
        let st = h.setup.as_mut().ok_or_else(not_set_up)?;
        let out = st.solver.solve(f, false, None)?;
        unsafe { alg_write_outcome(h, out, out_u, out_lambda, out_iterations, out_converged) }
    })
}
