//! The C ABI (`include/nsdd.h`, generated from this file by `build.rs` with
//! cbindgen).
//!
//! Conventions, for every exported function:
//! - names start with `nsdd_`; objects are opaque handles created by a
//!   `*_new` / `*_from_*` function and released by the matching `*_destroy`
//!   (which accepts NULL);
//! - a function that can fail returns an [`NsddStatus`]; on failure the
//!   thread's last-error message ([`nsdd_last_error_message`]) says what went
//!   wrong, naming the argument, field and index;
//! - no panic crosses the boundary: every body runs inside one guard
//!   ([`ffi_guard`]) that turns a panic into [`NsddStatus::Panic`];
//! - null pointers, wrong lengths and out-of-range indices are reported as
//!   status codes; a pointer paired with a length of 0 may be NULL;
//! - output arrays are owned by the caller, and their required length is
//!   part of each function's documentation; outputs are written only on
//!   success (except `*out` handles, which are set to NULL first).

use crate::dd::{CableColumn, DdOptions, DdProblem, DdSolver, SubdomainLoad, NO_DOF};
use crate::decomposition::Decomposition;
use crate::error::Error;
use crate::factor::lower_csc;
use crate::partition::Partition;
use crate::result::SolveResult;
use crate::scene::{ElementKind, Method, Nodes, Preconditioner, Scene, SearchDirection, SolverSettings};
use crate::solve::{solve, SolveOptions};
use crate::subdomain::SubdomainOperator;
use faer::Mat;
use rayon::prelude::*;
use std::cell::RefCell;
use std::ffi::{c_char, CStr, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};

/// Status code returned by every fallible function of the C ABI.
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NsddStatus {
    /// Success.
    Ok = 0,
    /// A required pointer argument was NULL.
    NullPointer = 1,
    /// An argument is out of range or an array has the wrong length.
    InvalidArgument = 2,
    /// The scene (or algebraic problem) failed validation; the message names
    /// the field and index.
    InvalidInput = 3,
    /// The scene text could not be parsed (TOML or JSON).
    ParseError = 4,
    /// A file could not be read or written.
    IoError = 5,
    /// The structure has no unique equilibrium (unsupported or a mechanism).
    Mechanism = 6,
    /// A subdomain matrix is indefinite or too badly conditioned.
    IndefiniteSubdomain = 7,
    /// The method cannot run on this problem (e.g. monolevel with a floating
    /// subdomain, or `direct` at the algebraic level).
    MethodNotApplicable = 8,
    /// The iteration diverged.
    Diverged = 9,
    /// An unexpected numerical failure.
    Numerical = 10,
    /// The handle is not in the state the call needs (e.g. `nsdd_alg_solve`
    /// before `nsdd_alg_setup`).
    NotSolved = 11,
    /// An internal error (a Rust panic) was caught at the boundary.
    Panic = 12,
}

/// Solution method (values for `nsdd_options_set_method`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NsddMethod {
    /// One sparse Cholesky of the whole structure (scene level only).
    Direct = 0,
    /// Domain decomposition without the coarse (macro) space.
    Monolevel = 1,
    /// Domain decomposition with the kernel-enriched macro space.
    Multilevel = 2,
    /// Conjugate gradient on the interface problem with the same coarse
    /// step; with unilateral cables, an active set around it.
    Cg = 3,
}

/// Preconditioner of the interface CG (values for
/// `nsdd_options_set_preconditioner`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NsddPreconditioner {
    /// Schur complement of each subdomain on its interface (default): one
    /// interior solve per subdomain and iteration, fewer iterations.
    Dirichlet = 0,
    /// The subdomain stiffness on its interface dofs; no extra factorization.
    Lumped = 1,
}

/// Element kind (values of the `kind` array of `nsdd_scene_set_elements`).
#[repr(C)]
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum NsddElementKind {
    /// Carries tension and compression.
    Bar = 0,
    /// Goes slack instead of pushing when the unilateral effect is on.
    Cable = 1,
}

/// Support mask bit: the x component is blocked.
pub const NSDD_SUPPORT_X: u8 = 1;
/// Support mask bit: the y component is blocked.
pub const NSDD_SUPPORT_Y: u8 = 2;
/// Support mask bit: the z component is blocked.
pub const NSDD_SUPPORT_Z: u8 = 4;
/// Largest number of entries of one cable column (`nsdd_alg_add_cable`).
pub const NSDD_MAX_CABLE_ENTRIES: usize = 6;

/// A scene (nodes, elements, supports, loads, effects, solver settings).
pub struct NsddScene {
    scene: Scene,
}

/// Solver settings for `nsdd_solve` and `nsdd_alg_setup`.
pub struct NsddOptions {
    opts: SolveOptions,
}

/// The result of `nsdd_solve`.
pub struct NsddResult {
    result: SolveResult,
}

/// One subdomain of an algebraic problem, in the caller's local numbering.
struct AlgSubdomain {
    n_local: usize,
    /// Lower triangle `(row, col, value)`, `row >= col`, caller numbering.
    lower: Vec<(usize, usize, f64)>,
    local_to_global: Vec<usize>,
    /// Caller's kernel basis `(r, n_local × r column-major)`.
    kernel: Option<(usize, Vec<f64>)>,
}

struct AlgCable {
    subdomain: usize,
    dofs: Vec<usize>,
    coefs: Vec<f64>,
    k: f64,
    e0: f64,
}

/// The set-up solver of an algebraic problem.
struct AlgSetup {
    /// Kept alongside the solver it was built from (the solver itself does
    /// not borrow it after construction).
    #[allow(dead_code)]
    decomposition: Box<Decomposition>,
    solver: Box<DdSolver>,
    /// Per subdomain: caller local index of each decomposition local dof.
    order: Vec<Vec<usize>>,
}

/// An algebraic domain-decomposition problem assembled by the caller
/// (subdomain matrices in CSR, local-to-global maps, cables), set up once
/// and solved for any number of right-hand sides.
pub struct NsddAlgebraic {
    n_global: usize,
    subdomains: Vec<Option<AlgSubdomain>>,
    dof_points: Option<Vec<([f64; 3], usize)>>,
    cables: Vec<AlgCable>,
    setup: Option<AlgSetup>,
}

// ---------------------------------------------------------------------------
// Errors, the panic guard and pointer helpers.

/// A failure on its way to the caller: status and message.
#[doc(hidden)]
#[derive(Debug, Clone)]
pub struct Fail {
    pub status: NsddStatus,
    pub message: String,
}

fn fail(status: NsddStatus, message: impl Into<String>) -> Fail {
    Fail {
        status,
        message: message.into(),
    }
}

fn invalid(message: impl Into<String>) -> Fail {
    fail(NsddStatus::InvalidArgument, message)
}

impl From<Error> for Fail {
    fn from(e: Error) -> Fail {
        let status = match &e {
            Error::InvalidInput { .. } => NsddStatus::InvalidInput,
            Error::Parse(_) => NsddStatus::ParseError,
            Error::Io(_) => NsddStatus::IoError,
            Error::Mechanism(_) => NsddStatus::Mechanism,
            Error::IndefiniteSubdomain { .. } => NsddStatus::IndefiniteSubdomain,
            Error::MethodNotApplicable(_) => NsddStatus::MethodNotApplicable,
            Error::Diverged { .. } => NsddStatus::Diverged,
            Error::Numerical(_) => NsddStatus::Numerical,
        };
        Fail {
            status,
            message: e.to_string(),
        }
    }
}

type FfiResult<T = ()> = std::result::Result<T, Fail>;

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

fn set_last_error(message: &str) {
    let clean: Vec<u8> = message.bytes().map(|b| if b == 0 { b'?' } else { b }).collect();
    let c = CString::new(clean).unwrap_or_default();
    // `try_with`: never fails, even during thread teardown.
    let _ = LAST_ERROR.try_with(|e| *e.borrow_mut() = c);
}

fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "unknown panic payload".to_string()
    }
}

/// Runs one C ABI body: a returned [`Fail`] becomes its status and the
/// thread's last-error message, and a panic becomes
/// [`NsddStatus::Panic`]. Every exported function goes through it.
#[doc(hidden)]
pub fn ffi_guard<F: FnOnce() -> FfiResult>(body: F) -> NsddStatus {
    match catch_unwind(AssertUnwindSafe(body)) {
        Ok(Ok(())) => NsddStatus::Ok,
        Ok(Err(f)) => {
            set_last_error(&f.message);
            f.status
        }
        Err(payload) => {
            let msg = panic_message(payload.as_ref());
            // Dropping the payload could itself panic: contain that too.
            let _ = catch_unwind(AssertUnwindSafe(move || drop(payload)));
            set_last_error(&format!("internal error (panic caught at the C boundary): {msg}"));
            NsddStatus::Panic
        }
    }
}

fn null(name: &str) -> Fail {
    fail(NsddStatus::NullPointer, format!("{name} is NULL"))
}

fn check_ptr<T>(ptr: *const T, name: &str) -> FfiResult {
    if ptr.is_null() {
        return Err(null(name));
    }
    if !ptr.is_aligned() {
        return Err(invalid(format!("{name} is not aligned for its element type")));
    }
    Ok(())
}

fn check_len<T>(len: usize, name: &str) -> FfiResult {
    if len > isize::MAX as usize / std::mem::size_of::<T>().max(1) {
        return Err(invalid(format!("{name}: length {len} is too large")));
    }
    Ok(())
}

/// `len` elements at `ptr`; NULL is accepted when `len == 0`.
unsafe fn slice<'a, T>(ptr: *const T, len: usize, name: &str) -> FfiResult<&'a [T]> {
    if len == 0 {
        return Ok(&[]);
    }
    check_ptr(ptr, name)?;
    check_len::<T>(len, name)?;
    // SAFETY: non-null, aligned, and the caller promises `len` readable elements.
    Ok(unsafe { std::slice::from_raw_parts(ptr, len) })
}

/// Mutable `len` elements at `ptr`; NULL is accepted when `len == 0`.
unsafe fn slice_mut<'a, T>(ptr: *mut T, len: usize, name: &str) -> FfiResult<&'a mut [T]> {
    if len == 0 {
        return Ok(&mut []);
    }
    check_ptr(ptr, name)?;
    check_len::<T>(len, name)?;
    // SAFETY: non-null, aligned, and the caller promises `len` writable elements.
    Ok(unsafe { std::slice::from_raw_parts_mut(ptr, len) })
}

unsafe fn handle<'a, T>(ptr: *const T, name: &str) -> FfiResult<&'a T> {
    check_ptr(ptr, name)?;
    // SAFETY: the caller passes a live handle from the matching constructor.
    Ok(unsafe { &*ptr })
}

unsafe fn handle_mut<'a, T>(ptr: *mut T, name: &str) -> FfiResult<&'a mut T> {
    check_ptr(ptr, name)?;
    // SAFETY: the caller passes a live handle, not used concurrently.
    Ok(unsafe { &mut *ptr })
}

/// Writes `value` through `ptr` (a required out-parameter).
unsafe fn write_out<T>(ptr: *mut T, name: &str, value: T) -> FfiResult {
    check_ptr(ptr, name)?;
    // SAFETY: non-null and aligned; the caller provides writable storage.
    unsafe { ptr.write(value) };
    Ok(())
}

/// Writes `value` through `ptr` unless it is NULL (an optional out-parameter).
unsafe fn write_opt<T>(ptr: *mut T, name: &str, value: T) -> FfiResult {
    if ptr.is_null() {
        return Ok(());
    }
    unsafe { write_out(ptr, name, value) }
}

/// Checks a `T** out` argument and sets `*out = NULL`.
unsafe fn clear_out<T>(out: *mut *mut T, name: &str) -> FfiResult {
    unsafe { write_out(out, name, std::ptr::null_mut()) }
}

unsafe fn c_str<'a>(ptr: *const c_char, name: &str) -> FfiResult<&'a str> {
    if ptr.is_null() {
        return Err(null(name));
    }
    // SAFETY: the caller passes a NUL-terminated string.
    let s = unsafe { CStr::from_ptr(ptr) };
    s.to_str().map_err(|_| invalid(format!("{name} is not valid UTF-8")))
}

fn check_finite(name: &str, v: &[f64]) -> FfiResult {
    match v.iter().position(|x| !x.is_finite()) {
        Some(i) => Err(invalid(format!("{name}[{i}] is not a finite number ({})", v[i]))),
        None => Ok(()),
    }
}

fn boxed<T>(value: T) -> *mut T {
    Box::into_raw(Box::new(value))
}

/// Releases a handle made by `boxed`.
unsafe fn destroy<T>(ptr: *mut T) {
    if !ptr.is_null() {
        // SAFETY: `ptr` came from `Box::into_raw` and is released once.
        drop(unsafe { Box::from_raw(ptr) });
    }
}

// ---------------------------------------------------------------------------
// Library-wide functions.

/// The library version (`"MAJOR.MINOR.PATCH"`), a static NUL-terminated
/// string: do not free it.
#[unsafe(no_mangle)]
pub extern "C" fn nsdd_version() -> *const c_char {
    concat!(env!("CARGO_PKG_VERSION"), "\0").as_ptr().cast()
}

/// The name of a status code (`"NSDD_STATUS_OK"`, ...), a static
/// NUL-terminated string; `"NSDD_STATUS_UNKNOWN"` for any other value.
#[unsafe(no_mangle)]
pub extern "C" fn nsdd_status_name(status: i32) -> *const c_char {
    let s: &'static str = match status {
        0 => "NSDD_STATUS_OK\0",
        1 => "NSDD_STATUS_NULL_POINTER\0",
        2 => "NSDD_STATUS_INVALID_ARGUMENT\0",
        3 => "NSDD_STATUS_INVALID_INPUT\0",
        4 => "NSDD_STATUS_PARSE_ERROR\0",
        5 => "NSDD_STATUS_IO_ERROR\0",
        6 => "NSDD_STATUS_MECHANISM\0",
        7 => "NSDD_STATUS_INDEFINITE_SUBDOMAIN\0",
        8 => "NSDD_STATUS_METHOD_NOT_APPLICABLE\0",
        9 => "NSDD_STATUS_DIVERGED\0",
        10 => "NSDD_STATUS_NUMERICAL\0",
        11 => "NSDD_STATUS_NOT_SOLVED\0",
        12 => "NSDD_STATUS_PANIC\0",
        _ => "NSDD_STATUS_UNKNOWN\0",
    };
    s.as_ptr().cast()
}

/// Copies the message of the last failed call *on this thread* into `buf`
/// (at most `len` bytes, always NUL-terminated when `len > 0`, truncated if
/// needed) and returns the buffer size the whole message needs, including
/// the terminating NUL. Successful calls leave the message unchanged; it is
/// empty (returns 1) before any failure. `buf` may be NULL when `len` is 0:
/// `size_t n = nsdd_last_error_message(NULL, 0);` then allocate `n` bytes.
///
/// # Safety
/// `buf` must be NULL or point to `len` writable bytes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_last_error_message(buf: *mut c_char, len: usize) -> usize {
    let r = catch_unwind(AssertUnwindSafe(|| {
        LAST_ERROR
            .try_with(|e| {
                let e = e.borrow();
                let bytes = e.as_bytes();
                if !buf.is_null() && len > 0 {
                    let n = bytes.len().min(len - 1);
                    // SAFETY: `buf` has `len > n` writable bytes.
                    unsafe {
                        std::ptr::copy_nonoverlapping(bytes.as_ptr().cast::<c_char>(), buf, n);
                        *buf.add(n) = 0;
                    }
                }
                bytes.len() + 1
            })
            .unwrap_or(1)
    }));
    r.unwrap_or(1)
}

// ---------------------------------------------------------------------------
// Scenes.

/// A new empty scene (no nodes, no elements, default effects and solver
/// settings), or NULL if memory ran out. Fill it with the `nsdd_scene_set_*`
/// functions; release it with `nsdd_scene_destroy`.
#[unsafe(no_mangle)]
pub extern "C" fn nsdd_scene_new() -> *mut NsddScene {
    catch_unwind(|| {
        boxed(NsddScene {
            scene: Scene::default(),
        })
    })
    .unwrap_or(std::ptr::null_mut())
}

/// Releases a scene (NULL is ignored).
///
/// # Safety
/// `scene` must be NULL or a live scene handle, not used afterwards.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_destroy(scene: *mut NsddScene) {
    let _ = catch_unwind(AssertUnwindSafe(|| unsafe { destroy(scene) }));
}

fn load_validated(scene: Scene, out: *mut *mut NsddScene) -> FfiResult {
    scene.validate()?;
    // SAFETY: `out` was checked by `clear_out`.
    unsafe { out.write(boxed(NsddScene { scene })) };
    Ok(())
}

/// Reads and validates a scene file (`.json` is JSON, anything else TOML,
/// as in SCENE.md) into a new handle stored in `*out` (NULL on failure).
/// Errors: IO_ERROR, PARSE_ERROR, INVALID_INPUT (the message names the field
/// and index).
///
/// # Safety
/// `path` must be a NUL-terminated UTF-8 string; `out` must point to
/// writable storage for one pointer.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_from_file(path: *const c_char, out: *mut *mut NsddScene) -> NsddStatus {
    ffi_guard(|| {
        unsafe { clear_out(out, "out")? };
        let path = unsafe { c_str(path, "path")? };
        load_validated(Scene::load(std::path::Path::new(path))?, out)
    })
}

/// Parses and validates scene text (JSON if `is_json`, else TOML) into a new
/// handle stored in `*out` (NULL on failure). Errors: PARSE_ERROR,
/// INVALID_INPUT.
///
/// # Safety
/// `text` must be a NUL-terminated UTF-8 string; `out` must point to
/// writable storage for one pointer.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_from_str(
    text: *const c_char,
    is_json: bool,
    out: *mut *mut NsddScene,
) -> NsddStatus {
    ffi_guard(|| {
        unsafe { clear_out(out, "out")? };
        let text = unsafe { c_str(text, "text")? };
        let scene = if is_json {
            Scene::from_json_str(text)?
        } else {
            Scene::from_toml_str(text)?
        };
        load_validated(scene, out)
    })
}

/// Sets the scene's name (used in results).
///
/// # Safety
/// `scene` must be a live scene handle; `name` a NUL-terminated UTF-8 string.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_name(scene: *mut NsddScene, name: *const c_char) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let name = unsafe { c_str(name, "name")? };
        s.scene.scene.name = name.to_string();
        Ok(())
    })
}

/// Replaces the nodes: `x`, `y`, `z` each hold `n` coordinates.
///
/// # Safety
/// `scene` must be a live scene handle; `x`, `y`, `z` must each point to
/// `n` readable doubles (or be NULL when `n` is 0).
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_nodes(
    scene: *mut NsddScene,
    n: usize,
    x: *const f64,
    y: *const f64,
    z: *const f64,
) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let (x, y, z) = unsafe { (slice(x, n, "x")?, slice(y, n, "y")?, slice(z, n, "z")?) };
        check_finite("x", x)?;
        check_finite("y", y)?;
        check_finite("z", z)?;
        s.scene.nodes = Nodes {
            x: x.to_vec(),
            y: y.to_vec(),
            z: z.to_vec(),
        };
        Ok(())
    })
}

/// Replaces the elements: `m` entries each of end nodes `a`, `b` (0-based
/// node indices), `kind` (`NSDD_ELEMENT_KIND_BAR` = 0 or
/// `NSDD_ELEMENT_KIND_CABLE` = 1), axial stiffness `ea` (> 0) and prestress
/// `t0` (tension positive; NULL for none). A kind other than 0 or 1 is
/// INVALID_ARGUMENT; node indices are checked against the nodes when the
/// scene is validated or solved (INVALID_INPUT naming `elements.a` / `.b`).
///
/// # Safety
/// `scene` must be a live scene handle; `a`, `b`, `kind`, `ea` must each
/// point to `m` readable values, `t0` to `m` doubles or be NULL.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_elements(
    scene: *mut NsddScene,
    m: usize,
    a: *const usize,
    b: *const usize,
    kind: *const u8,
    ea: *const f64,
    t0: *const f64,
) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let (a, b) = unsafe { (slice(a, m, "a")?, slice(b, m, "b")?) };
        let kind = unsafe { slice(kind, m, "kind")? };
        let ea = unsafe { slice(ea, m, "ea")? };
        let t0 = if t0.is_null() {
            &[][..]
        } else {
            unsafe { slice(t0, m, "t0")? }
        };
        let kinds = kind
            .iter()
            .enumerate()
            .map(|(i, &k)| match k {
                0 => Ok(ElementKind::Bar),
                1 => Ok(ElementKind::Cable),
                _ => Err(invalid(format!("kind[{i}] = {k}: expected 0 (bar) or 1 (cable)"))),
            })
            .collect::<FfiResult<Vec<_>>>()?;
        let el = &mut s.scene.elements;
        el.a = a.to_vec();
        el.b = b.to_vec();
        el.kind = kinds;
        el.ea = ea.to_vec();
        el.t0 = t0.to_vec();
        Ok(())
    })
}

/// Replaces the supports: `k` entries of `node` and `mask`, where `mask`
/// combines `NSDD_SUPPORT_X` (1), `NSDD_SUPPORT_Y` (2) and `NSDD_SUPPORT_Z`
/// (4); a mask of 0 or above 7 is INVALID_ARGUMENT.
///
/// # Safety
/// `scene` must be a live scene handle; `node` and `mask` must each point
/// to `k` readable values.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_supports(
    scene: *mut NsddScene,
    k: usize,
    node: *const usize,
    mask: *const u8,
) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let (node, mask) = unsafe { (slice(node, k, "node")?, slice(mask, k, "mask")?) };
        let dofs = mask
            .iter()
            .enumerate()
            .map(|(i, &m)| {
                if m == 0 || m > 7 {
                    return Err(invalid(format!(
                        "mask[{i}] = {m}: expected 1..7 (bit 0 x, bit 1 y, bit 2 z)"
                    )));
                }
                Ok(["x", "y", "z"]
                    .iter()
                    .enumerate()
                    .filter(|(c, _)| m & (1 << c) != 0)
                    .map(|(_, s)| *s)
                    .collect())
            })
            .collect::<FfiResult<Vec<String>>>()?;
        s.scene.supports.node = node.to_vec();
        s.scene.supports.dofs = dofs;
        Ok(())
    })
}

/// Replaces the nodal loads (load case 0): `k` entries of `node`, `fx`,
/// `fy`, `fz`.
///
/// # Safety
/// `scene` must be a live scene handle; `node`, `fx`, `fy`, `fz` must each
/// point to `k` readable values.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_loads(
    scene: *mut NsddScene,
    k: usize,
    node: *const usize,
    fx: *const f64,
    fy: *const f64,
    fz: *const f64,
) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let node = unsafe { slice(node, k, "node")? };
        let (fx, fy, fz) = unsafe { (slice(fx, k, "fx")?, slice(fy, k, "fy")?, slice(fz, k, "fz")?) };
        let l = &mut s.scene.loads;
        l.node = node.to_vec();
        l.fx = fx.to_vec();
        l.fy = fy.to_vec();
        l.fz = fz.to_vec();
        Ok(())
    })
}

/// Sets the effects the scene calls for (SCENE.md `[effects]`).
///
/// # Safety
/// `scene` must be a live scene handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_effects(
    scene: *mut NsddScene,
    unilateral_cables: bool,
    prestress: bool,
    geometric_stiffness: bool,
    self_weight: bool,
) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let e = &mut s.scene.effects;
        e.unilateral_cables = unilateral_cables;
        e.prestress = prestress;
        e.geometric_stiffness = geometric_stiffness;
        e.self_weight = self_weight;
        Ok(())
    })
}

/// Sets the data of the self-weight effect: `m` masses per unit length (one
/// per element) and the gravity vector `gravity[3]` (NULL for the default
/// of SCENE.md).
///
/// # Safety
/// `scene` must be a live scene handle; `mass_per_length` must point to `m`
/// doubles; `gravity` must be NULL or point to 3 doubles.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_set_self_weight(
    scene: *mut NsddScene,
    m: usize,
    mass_per_length: *const f64,
    gravity: *const f64,
) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle_mut(scene, "scene")? };
        let mpl = unsafe { slice(mass_per_length, m, "mass_per_length")? };
        let g = if gravity.is_null() {
            None
        } else {
            let g = unsafe { slice(gravity, 3, "gravity")? };
            Some([g[0], g[1], g[2]])
        };
        s.scene.elements.mass_per_length = mpl.to_vec();
        s.scene.scene.gravity = g;
        Ok(())
    })
}

/// Checks every field of the scene, as `nsdd_solve` does first. Errors:
/// INVALID_INPUT, with a message naming the field and index.
///
/// # Safety
/// `scene` must be a live scene handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_validate(scene: *const NsddScene) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle(scene, "scene")? };
        s.scene.validate()?;
        Ok(())
    })
}

/// Number of nodes of the scene into `*out`.
///
/// # Safety
/// `scene` must be a live scene handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_num_nodes(scene: *const NsddScene, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle(scene, "scene")? };
        unsafe { write_out(out, "out", s.scene.nodes.x.len()) }
    })
}

/// Number of elements of the scene into `*out`.
///
/// # Safety
/// `scene` must be a live scene handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_scene_num_elements(scene: *const NsddScene, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let s = unsafe { handle(scene, "scene")? };
        unsafe { write_out(out, "out", s.scene.elements.a.len()) }
    })
}

// ---------------------------------------------------------------------------
// Solver options.

fn default_options() -> SolveOptions {
    let s = SolverSettings::default();
    SolveOptions {
        method: s.method,
        subdomains: s.subdomains,
        tolerance: s.tolerance,
        max_iterations: s.max_iterations,
        search_direction: s.search_direction,
        preconditioner: s.preconditioner,
    }
}

/// New solver options with the defaults of SCENE.md (direct, 1 subdomain,
/// tolerance 1e-8, 20000 iterations, automatic search direction), or NULL
/// if memory ran out. Release with `nsdd_options_destroy`.
#[unsafe(no_mangle)]
pub extern "C" fn nsdd_options_new() -> *mut NsddOptions {
    catch_unwind(|| {
        boxed(NsddOptions {
            opts: default_options(),
        })
    })
    .unwrap_or(std::ptr::null_mut())
}

/// New solver options copied from the scene's own `[solver]` settings into
/// `*out` (NULL on failure).
///
/// # Safety
/// `scene` must be a live scene handle; `out` must point to writable
/// storage for one pointer.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_from_scene(scene: *const NsddScene, out: *mut *mut NsddOptions) -> NsddStatus {
    ffi_guard(|| {
        unsafe { clear_out(out, "out")? };
        let s = unsafe { handle(scene, "scene")? };
        unsafe {
            out.write(boxed(NsddOptions {
                opts: SolveOptions::from_scene(&s.scene),
            }))
        };
        Ok(())
    })
}

/// Releases options (NULL is ignored).
///
/// # Safety
/// `options` must be NULL or a live options handle, not used afterwards.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_destroy(options: *mut NsddOptions) {
    let _ = catch_unwind(AssertUnwindSafe(|| unsafe { destroy(options) }));
}

/// Sets the method: one of `NsddMethod` (0 direct, 1 monolevel, 2
/// multilevel, 3 cg); any other value is INVALID_ARGUMENT.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_method(options: *mut NsddOptions, method: u32) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.method = match method {
            0 => Method::Direct,
            1 => Method::Monolevel,
            2 => Method::Multilevel,
            3 => Method::Cg,
            _ => {
                return Err(invalid(format!(
                    "method = {method}: expected 0 (direct), 1 (monolevel), 2 (multilevel) or 3 (cg)"
                )))
            }
        };
        Ok(())
    })
}

/// Sets the preconditioner of the `cg` method: one of `NsddPreconditioner`
/// (0 dirichlet, 1 lumped); any other value is INVALID_ARGUMENT. Ignored
/// by the other methods.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_preconditioner(options: *mut NsddOptions, preconditioner: u32) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        o.opts.preconditioner = match preconditioner {
            0 => Preconditioner::Dirichlet,
            1 => Preconditioner::Lumped,
            _ => {
                return Err(invalid(format!(
                    "preconditioner = {preconditioner}: expected 0 (dirichlet) or 1 (lumped)"
                )))
            }
        };
        Ok(())
    })
}

/// Sets the number of subdomains of the automatic partition (>= 1; ignored
/// by the direct method and at the algebraic level).
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_subdomains(options: *mut NsddOptions, subdomains: usize) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        if subdomains == 0 {
            return Err(invalid("subdomains must be at least 1"));
        }
        o.opts.subdomains = subdomains;
        Ok(())
    })
}

/// Sets the stopping tolerance on the iteration indicator (finite, > 0).
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_tolerance(options: *mut NsddOptions, tolerance: f64) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        if !(tolerance > 0.0 && tolerance.is_finite()) {
            return Err(invalid(format!(
                "tolerance must be positive and finite, got {tolerance}"
            )));
        }
        o.opts.tolerance = tolerance;
        Ok(())
    })
}

/// Sets the iteration limit (>= 1).
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_max_iterations(
    options: *mut NsddOptions,
    max_iterations: usize,
) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        if max_iterations == 0 {
            return Err(invalid("max_iterations must be at least 1"));
        }
        o.opts.max_iterations = max_iterations;
        Ok(())
    })
}

/// Sets the search direction `d` of the local stage; `d <= 0` selects the
/// automatic choice. NaN or infinity is INVALID_ARGUMENT.
///
/// # Safety
/// `options` must be a live options handle.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_options_set_search_direction(options: *mut NsddOptions, d: f64) -> NsddStatus {
    ffi_guard(|| {
        let o = unsafe { handle_mut(options, "options")? };
        if !d.is_finite() {
            return Err(invalid(format!("search direction must be finite, got {d}")));
        }
        o.opts.search_direction = if d <= 0.0 {
            SearchDirection::Auto
        } else {
            SearchDirection::Value(d)
        };
        Ok(())
    })
}

// ---------------------------------------------------------------------------
// Solving a scene and reading the result.

/// Validates and solves the scene with `options` (NULL: the scene's own
/// `[solver]` settings) and stores a new result handle in `*out_result`
/// (NULL on failure). A run that stops at the iteration limit is not an
/// error: check `nsdd_result_converged`. Errors: INVALID_INPUT, MECHANISM,
/// INDEFINITE_SUBDOMAIN, METHOD_NOT_APPLICABLE, DIVERGED, NUMERICAL.
///
/// # Safety
/// `scene` must be a live scene handle, `options` NULL or a live options
/// handle, `out_result` must point to writable storage for one pointer.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_solve(
    scene: *const NsddScene,
    options: *const NsddOptions,
    out_result: *mut *mut NsddResult,
) -> NsddStatus {
    ffi_guard(|| {
        unsafe { clear_out(out_result, "out_result")? };
        let s = unsafe { handle(scene, "scene")? };
        let opts = if options.is_null() {
            SolveOptions::from_scene(&s.scene)
        } else {
            unsafe { handle(options, "options")? }.opts.clone()
        };
        let result = solve(&s.scene, &opts)?;
        unsafe { out_result.write(boxed(NsddResult { result })) };
        Ok(())
    })
}

/// Releases a result (NULL is ignored).
///
/// # Safety
/// `result` must be NULL or a live result handle, not used afterwards.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_destroy(result: *mut NsddResult) {
    let _ = catch_unwind(AssertUnwindSafe(|| unsafe { destroy(result) }));
}

/// Number of nodes of the solved scene into `*out`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_num_nodes(result: *const NsddResult, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", r.result.displacements.len()) }
    })
}

/// Number of elements of the solved scene into `*out`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_num_elements(result: *const NsddResult, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", r.result.tensions.len()) }
    })
}

fn check_exact(name: &str, len: usize, expected: usize, what: &str) -> FfiResult {
    if len != expected {
        return Err(invalid(format!("{name}: len = {len}, expected {expected} ({what})")));
    }
    Ok(())
}

/// Nodal displacements into `out`, node after node (`ux0, uy0, uz0, ux1,
/// ...`); `len` must be exactly `3 * num_nodes`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to `len`
/// writable doubles.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_displacements(result: *const NsddResult, out: *mut f64, len: usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        let d = &r.result.displacements;
        check_exact("displacements", len, 3 * d.len(), "3 * num_nodes")?;
        let out = unsafe { slice_mut(out, len, "out")? };
        for (o, v) in out.chunks_exact_mut(3).zip(d) {
            o.copy_from_slice(v);
        }
        Ok(())
    })
}

/// Element tensions (axial forces, tension positive) into `out`; `len`
/// must be exactly `num_elements`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to `len`
/// writable doubles.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_tensions(result: *const NsddResult, out: *mut f64, len: usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        check_exact("tensions", len, r.result.tensions.len(), "num_elements")?;
        unsafe { slice_mut(out, len, "out")? }.copy_from_slice(&r.result.tensions);
        Ok(())
    })
}

/// Slack flags into `out` (1 for a slack cable, 0 otherwise); `len` must be
/// exactly `num_elements`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to `len`
/// writable bytes.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_slack(result: *const NsddResult, out: *mut u8, len: usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        check_exact("slack", len, r.result.slack.len(), "num_elements")?;
        for (o, &s) in unsafe { slice_mut(out, len, "out")? }.iter_mut().zip(&r.result.slack) {
            *o = s as u8;
        }
        Ok(())
    })
}

/// Iterations of the (last) solve into `*out`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_iterations(result: *const NsddResult, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", r.result.iterations) }
    })
}

/// Whether every solve reached the tolerance, into `*out`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `bool`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_converged(result: *const NsddResult, out: *mut bool) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", r.result.converged) }
    })
}

/// Number of entries of the convergence history into `*out`.
///
/// # Safety
/// `result` must be a live result handle; `out` must point to a writable `size_t`.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_history_len(result: *const NsddResult, out: *mut usize) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        unsafe { write_out(out, "out", r.result.history.len()) }
    })
}

/// The convergence history: the stopping indicator and the elapsed time in
/// seconds of every iteration, into `indicator` and `time_s` (either may be
/// NULL to skip it); `len` must be exactly `history_len`.
///
/// # Safety
/// `result` must be a live result handle; `indicator` and `time_s` must
/// each be NULL or point to `len` writable doubles.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_history(
    result: *const NsddResult,
    indicator: *mut f64,
    time_s: *mut f64,
    len: usize,
) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        let h = &r.result.history;
        check_exact("history", len, h.len(), "history_len")?;
        if !indicator.is_null() {
            for (o, e) in unsafe { slice_mut(indicator, len, "indicator")? }.iter_mut().zip(h) {
                *o = e.indicator;
            }
        }
        if !time_s.is_null() {
            for (o, e) in unsafe { slice_mut(time_s, len, "time_s")? }.iter_mut().zip(h) {
                *o = e.time_s;
            }
        }
        Ok(())
    })
}

/// Writes the result as JSON (the `--out result.json` format of SCENE.md)
/// to `path`. Errors: IO_ERROR.
///
/// # Safety
/// `result` must be a live result handle; `path` a NUL-terminated UTF-8 string.
#[unsafe(no_mangle)]
pub unsafe extern "C" fn nsdd_result_write_json(result: *const NsddResult, path: *const c_char) -> NsddStatus {
    ffi_guard(|| {
        let r = unsafe { handle(result, "result")? };
        let path = unsafe { c_str(path, "path")? };
        std::fs::write(path, r.result.to_json()).map_err(|e| fail(NsddStatus::IoError, format!("{path}: {e}")))
    })
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

fn check_subdomain(h: &NsddAlgebraic, s: usize) -> FfiResult {
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

fn alg_setup(h: &mut NsddAlgebraic, opts: &SolveOptions) -> FfiResult {
    h.setup = None;
    let coarse = match opts.method {
        Method::Direct => {
            return Err(fail(
                NsddStatus::MethodNotApplicable,
                "method not applicable: the algebraic level runs monolevel, multilevel or cg, not direct",
            ))
        }
        Method::Monolevel => false,
        Method::Multilevel | Method::Cg => true,
    };
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
    let solver = DdSolver::from_problem(
        problem,
        DdOptions {
            coarse,
            tolerance: opts.tolerance,
            max_iterations: opts.max_iterations,
            search_direction: opts.search_direction,
            krylov: opts.method == Method::Cg,
            preconditioner: opts.preconditioner,
        },
    )?;
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

fn not_set_up() -> Fail {
    fail(
        NsddStatus::NotSolved,
        "the algebraic problem is not set up (call nsdd_alg_setup)",
    )
}

#[allow(clippy::too_many_arguments)]
unsafe fn alg_write_outcome(
    h: &NsddAlgebraic,
    out: crate::dd::DdOutcome,
    out_u: *mut f64,
    out_lambda: *mut f64,
    out_iterations: *mut usize,
    out_converged: *mut bool,
) -> FfiResult {
    unsafe { slice_mut(out_u, h.n_global, "out_u")? }.copy_from_slice(&out.u);
    if !out_lambda.is_null() {
        unsafe { slice_mut(out_lambda, h.cables.len(), "out_lambda")? }.copy_from_slice(&out.lambda);
    }
    unsafe {
        write_opt(out_iterations, "out_iterations", out.iterations)?;
        write_opt(out_converged, "out_converged", out.converged)?;
    }
    Ok(())
}

fn check_out_ptrs(out_u: *mut f64, out_lambda: *mut f64, n_cables: usize) -> FfiResult {
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
