//! The algebraic level of the C ABI: subdomain matrices, local-to-global
//! maps, dof points, kernels and cables, set up once and solved for any
//! number of right-hand sides: a thin mirror of
//! [`crate::algebraic`] (the checks and the set-up live there; here are the
//! handles, the pointer checks and the status codes).

use super::*;
use std::ffi::c_int;

/// A bad argument found by the library's checks is INVALID_ARGUMENT here
/// (its message without the "invalid input" prefix); other errors keep
/// their status.
fn arg(e: Error) -> Fail {
    match e {
        Error::InvalidInput { field, index, message } => invalid(match index {
            Some(i) => format!("{field}[{i}]: {message}"),
            None if message.contains(&field) => message,
            None => format!("{field}: {message}"),
        }),
        other => other.into(),
    }
}

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
        let h = NsddAlgebraic {
            problem: AlgebraicProblem::new(n_subdomains, n_global_dofs).map_err(arg)?,
            setup: None,
        };
        unsafe { out.write(boxed(h)) };
        Ok(())
    })
}

/// Like `nsdd_alg_new`, for a problem spread over the ranks of an MPI
/// communicator, given as its Fortran handle `comm` (`MPI_Comm_c2f(comm)`,
/// so this header does not depend on one MPI's `MPI_Comm` type); nsdd works
/// on its own duplicate of it. Every rank calls it with the same sizes;
/// rank `r` of `p` owns subdomains `floor(r n / p)` to `floor((r+1) n / p)
/// - 1` (`nsdd_alg_owned`) and sets only those (matrix, kernel, cables),
/// with the dof points of at least their dofs. `nsdd_alg_setup` and the
/// solves are then collective: every rank calls them, and every rank gets
/// the whole displacement and the same status (an error on one rank, such
/// as an indefinite subdomain, is returned on all of them). `nsdd_alg_solve`
/// takes the right-hand sides of this rank's subdomains only. Cables are
/// numbered rank by rank in the slacks (rank r's after those of the ranks
/// below it). MPI must be initialised with at least MPI_THREAD_FUNNELED and
/// nsdd called from the thread that initialised it. A library built
/// without the `mpi` feature returns METHOD_NOT_APPLICABLE.
///
/// # Safety
/// `out` must point to writable storage for one pointer; `comm` must be
/// the Fortran handle of a live intra-communicator.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_new_mpi(
    n_subdomains: usize,
    n_global_dofs: usize,
    comm: c_int,
    out: *mut *mut NsddAlgebraic,
) -> NsddStatus {
    ffi_guard(|| {
        unsafe { clear_out(out, "out")? };
        #[cfg(feature = "mpi")]
        {
            let c = unsafe { crate::comm::mpi::MpiComm::from_fortran(comm) }.map_err(arg)?;
            let placement = crate::comm::Placement::Mpi(c);
            let h = NsddAlgebraic {
                problem: AlgebraicProblem::new_in(n_subdomains, n_global_dofs, placement).map_err(arg)?,
                setup: None,
            };
            unsafe { out.write(boxed(h)) };
            Ok(())
        }
        #[cfg(not(feature = "mpi"))]
        {
            let _ = (n_subdomains, n_global_dofs, comm);
            Err(
                Error::MethodNotApplicable("this nsdd library was built without MPI (cargo feature `mpi`)".into())
                    .into(),
            )
        }
    })
}

/// The subdomains this process sets: `*out_first` and `*out_count` (all
/// of them for `nsdd_alg_new`, the rank's block for `nsdd_alg_new_mpi`).
///
/// # Safety
/// `alg` must be a live algebraic handle; the outputs must point to
/// writable `size_t`s.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_owned(
    alg: *const NsddAlgebraic,
    out_first: *mut usize,
    out_count: *mut usize,
) -> NsddStatus {
    ffi_guard(|| {
        let h = unsafe { handle(alg, "alg")? };
        let held = h.problem.owned();
        unsafe {
            write_out(out_first, "out_first", held.start)?;
            write_out(out_count, "out_count", held.len())
        }
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

/// Sets subdomain `s` (0-based): its stiffness `K_E` (`n_local × n_local`,
/// symmetric positive semi-definite) in 0-based CSR — `row_ptr` has
/// `n_local + 1` entries, `col_idx` and `values` have `row_ptr[n_local]` —
/// and `local_to_global` (`n_local` distinct global dof ids, any order). Give
/// either the full symmetric matrix or its lower triangle: duplicates are
/// summed, and only the lower triangle is kept. A full matrix that is not
/// symmetric (up to round-off), or one given as its upper triangle only, is
/// INVALID_ARGUMENT. Global dofs with
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
        let row_ptr = unsafe {
            slice(
                row_ptr,
                n_local.checked_add(1).ok_or_else(|| invalid("n_local too large"))?,
                "row_ptr",
            )?
        };
        let nnz = row_ptr.last().copied().unwrap_or(0);
        let col_idx = unsafe { slice(col_idx, nnz, "col_idx")? };
        let values = unsafe { slice(values, nnz, "values")? };
        let l2g = unsafe { slice(local_to_global, n_local, "local_to_global")? };
        h.problem.subdomain(s, row_ptr, col_idx, values, l2g).map_err(arg)?;
        h.setup = None;
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
        if n_global != h.problem.n_global_dofs() {
            return Err(invalid(format!(
                "n_global = {n_global}, expected n_global_dofs = {}",
                h.problem.n_global_dofs()
            )));
        }
        let xyz = unsafe { slice(xyz, 3 * n_global, "xyz")? };
        let comp = unsafe { slice(component, n_global, "component")? };
        let points: Vec<[f64; 3]> = xyz.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect();
        let comp: Vec<usize> = comp.iter().map(|&c| c as usize).collect();
        h.problem.dof_points(&points, &comp).map_err(arg)?;
        h.setup = None;
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
        // The C call names n_local: check it against the subdomain before
        // reading the basis.
        let have = h.problem.n_local(s);
        if have.is_none() {
            // Out of range or not set: the library's message says which.
            h.problem.kernel(s, &[]).map_err(arg)?;
        }
        let have = have.unwrap_or(0);
        if n_local != have {
            return Err(invalid(format!(
                "subdomain {s}: n_local = {n_local}, the subdomain has {have}"
            )));
        }
        let len = n_local.checked_mul(r).ok_or_else(|| invalid("n_local * r overflows"))?;
        let basis = unsafe { slice(basis, len, "basis")? };
        h.problem.kernel(s, basis).map_err(arg)?;
        h.setup = None;
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
        let dofs = unsafe { slice(local_dofs, n_entries, "local_dofs")? };
        let coefs = unsafe { slice(coefs, n_entries, "coefs")? };
        if !out_index.is_null() {
            // Checked first: a failed call adds no cable.
            check_ptr(out_index, "out_index")?;
        }
        let index = h.problem.cable(s, dofs, coefs, k, e0).map_err(arg)?;
        h.setup = None;
        unsafe { write_opt(out_index, "out_index", index)? };
        Ok(())
    })
}

/// Number of cables into `*out`: after `nsdd_alg_setup`, the entries of
/// the slacks `out_lambda` (under MPI, every rank's cables); before it, the
/// cables this process added so far.
///
/// # Safety
/// `alg` must be a live algebraic handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_num_cables(alg: *const NsddAlgebraic, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let h = unsafe { handle(alg, "alg")? };
        let n = h.setup.as_ref().map_or(h.problem.n_cables(), |st| st.n_cables());
        unsafe { write_out(out, "out", n) }
    })
}

pub(super) fn alg_setup(h: &mut NsddAlgebraic, opts: &SolveOptions) -> FfiResult {
    h.setup = None;
    // Settings errors keep their status; the completeness checks are bad
    // arguments; the set-up's own errors (bad kernel, mechanism, ...) keep
    // theirs. All of them on every rank under MPI.
    let checked = DdOptions::from_settings(opts)
        .map_err(Fail::from)
        .and_then(|o| h.problem.check_complete(o.coarse).map_err(arg));
    collective(h.problem.placement(), checked)?;
    h.setup = Some(h.problem.build(opts)?);
    Ok(())
}

/// `r` on every rank under MPI: a failure on one rank (a NULL or short
/// array, a bad option) is returned with its status and message on all of
/// them, so that none waits in a collective step for a rank that returned.
fn collective<T>(placement: &crate::comm::Placement, r: FfiResult<T>) -> FfiResult<T> {
    placement.agree_by(
        r,
        |f| {
            let mut v = (f.status as i32).to_le_bytes().to_vec();
            v.extend_from_slice(f.message.as_bytes());
            v
        },
        |b| {
            let code = b.get(..4).map_or(NsddStatus::Numerical as i32, |c| {
                i32::from_le_bytes([c[0], c[1], c[2], c[3]])
            });
            let status = [
                NsddStatus::NullPointer,
                NsddStatus::InvalidArgument,
                NsddStatus::InvalidInput,
                NsddStatus::ParseError,
                NsddStatus::IoError,
                NsddStatus::Mechanism,
                NsddStatus::IndefiniteSubdomain,
                NsddStatus::MethodNotApplicable,
                NsddStatus::Diverged,
                NsddStatus::Numerical,
                NsddStatus::NotSolved,
                NsddStatus::Panic,
            ]
            .into_iter()
            .find(|s| *s as i32 == code)
            .unwrap_or(NsddStatus::Numerical);
            fail(status, String::from_utf8_lossy(b.get(4..).unwrap_or_default()))
        },
    )
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
        unsafe { write_out(out, "out", st.search_direction()) }
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
    out: crate::outcome::Outcome,
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
    unsafe { slice_mut(out_u, h.problem.n_global_dofs(), "out_u")? }.copy_from_slice(&out.u);
    if !out_lambda.is_null() {
        unsafe { slice_mut(out_lambda, out.lambda.len(), "out_lambda")? }.copy_from_slice(&out.lambda);
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
/// pointers (this rank's `count` of `nsdd_alg_owned` under MPI), each to
/// `n_local(s)` doubles; outputs as described above.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_alg_solve(
    alg: *mut NsddAlgebraic,
    rhs: *const *const f64,
    out_u: *mut f64,
    out_lambda: *mut f64,
    out_iterations: *mut usize,
    out_converged: *mut bool,
) -> NsddStatus {
    unsafe {
        alg_solve_with(alg, out_u, out_lambda, out_iterations, out_converged, |problem, st| {
            let held = problem.owned();
            let local = (|| -> FfiResult<Vec<&[f64]>> {
                let ptrs = slice(rhs, held.len(), "rhs")?;
                let mut local: Vec<&[f64]> = Vec::with_capacity(held.len());
                for (s, &p) in held.clone().zip(ptrs) {
                    let n = problem.n_local(s).unwrap_or(0);
                    local.push(slice(p, n, &format!("rhs[{s}]"))?);
                }
                Ok(local)
            })();
            let local = collective(problem.placement(), local)?;
            st.solve_local(&local).map_err(arg)
        })
    }
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
    unsafe {
        alg_solve_with(alg, out_u, out_lambda, out_iterations, out_converged, |problem, st| {
            let f = collective(problem.placement(), slice(f, problem.n_global_dofs(), "f"))?;
            st.solve(f).map_err(arg)
        })
    }
}

/// The common part of the algebraic solves: checks the handle, that it is
/// set up and the output pointers, runs `solve` on the set-up and writes
/// its outcome.
///
/// # Safety
/// As for `nsdd_alg_solve`; `solve` reads only pointers the caller vouches for.
unsafe fn alg_solve_with(
    alg: *mut NsddAlgebraic,
    out_u: *mut f64,
    out_lambda: *mut f64,
    out_iterations: *mut usize,
    out_converged: *mut bool,
    solve: impl FnOnce(&AlgebraicProblem, &mut AlgebraicSolver) -> FfiResult<crate::outcome::Outcome>,
) -> NsddStatus {
    ffi_guard(|| {
        let h = unsafe { handle_mut(alg, "alg")? };
        let st = h.setup.as_mut().ok_or_else(not_set_up)?;
        collective(h.problem.placement(), check_out_ptrs(out_u, out_lambda, st.n_cables()))?;
        let out = solve(&h.problem, st)?;
        unsafe { alg_write_outcome(h, out, out_u, out_lambda, out_iterations, out_converged) }
    })
}
