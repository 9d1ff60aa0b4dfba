//! The boundary of the C ABI: the mapping of errors to status codes, the
//! panic guard every exported function runs in, the thread's last-error
//! message and the pointer helpers; the library-wide functions.

use super::*;

// ---------------------------------------------------------------------------
// Errors, the panic guard and pointer helpers.

/// A failure on its way to the caller: status and message.
#[doc(hidden)]
#[derive(Debug, Clone)]
pub struct Fail {
    pub status: NsddStatus,
    pub message: String,
}

pub(super) fn fail(status: NsddStatus, message: impl Into<String>) -> Fail {
    Fail {
        status,
        message: message.into(),
    }
}

pub(super) fn invalid(message: impl Into<String>) -> Fail {
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

pub(super) type FfiResult<T = ()> = std::result::Result<T, Fail>;

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

pub(super) fn set_last_error(message: &str) {
    let clean: Vec<u8> = message.bytes().map(|b| if b == 0 { b'?' } else { b }).collect();
    let c = CString::new(clean).unwrap_or_default();
    // `try_with`: never fails, even during thread teardown.
    let _ = LAST_ERROR.try_with(|e| *e.borrow_mut() = c);
}

pub(super) fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    if let Some(s) = payload.downcast_ref::<&str>() {
        (*s).to_string()
    } else if let Some(s) = payload.downcast_ref::<String>() {
        s.clone()
    } else {
        "unknown panic payload".to_string()
    }
}

/// faer's dense kernels split their work by the thread count and so round
/// differently with 1 and 2 threads, which CG amplifies; nsdd's parallelism
/// goes over subdomains, so the C ABI keeps them sequential, as the command
/// line does: a C caller's results do not depend on `RAYON_NUM_THREADS`.
/// Once per process, before the first call does any work.
fn sequential_dense_kernels() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| faer::set_global_parallelism(faer::Par::Seq));
}

/// Runs one C ABI body: a returned [`Fail`] becomes its status and the
/// thread's last-error message, and a panic becomes
/// [`NsddStatus::Panic`]. Every exported function goes through it.
#[doc(hidden)]
pub fn ffi_guard<F: FnOnce() -> FfiResult>(body: F) -> NsddStatus {
    sequential_dense_kernels();
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

pub(super) fn null(name: &str) -> Fail {
    fail(NsddStatus::NullPointer, format!("{name} is NULL"))
}

pub(super) fn check_ptr<T>(ptr: *const T, name: &str) -> FfiResult {
    if ptr.is_null() {
        return Err(null(name));
    }
    if !ptr.is_aligned() {
        return Err(invalid(format!("{name} is not aligned for its element type")));
    }
    Ok(())
}

pub(super) fn check_len<T>(len: usize, name: &str) -> FfiResult {
    if len > isize::MAX as usize / std::mem::size_of::<T>().max(1) {
        return Err(invalid(format!("{name}: length {len} is too large")));
    }
    Ok(())
}

/// `len` elements at `ptr`; NULL is accepted when `len == 0`.
pub(super) unsafe fn slice<'a, T>(ptr: *const T, len: usize, name: &str) -> FfiResult<&'a [T]> {
    if len == 0 {
        return Ok(&[]);
    }
    check_ptr(ptr, name)?;
    check_len::<T>(len, name)?;
    // SAFETY: non-null, aligned, and the caller promises `len` readable elements.
    Ok(unsafe { std::slice::from_raw_parts(ptr, len) })
}

/// Mutable `len` elements at `ptr`; NULL is accepted when `len == 0`.
pub(super) unsafe fn slice_mut<'a, T>(ptr: *mut T, len: usize, name: &str) -> FfiResult<&'a mut [T]> {
    if len == 0 {
        return Ok(&mut []);
    }
    check_ptr(ptr, name)?;
    check_len::<T>(len, name)?;
    // SAFETY: non-null, aligned, and the caller promises `len` writable elements.
    Ok(unsafe { std::slice::from_raw_parts_mut(ptr, len) })
}

pub(super) unsafe fn handle<'a, T>(ptr: *const T, name: &str) -> FfiResult<&'a T> {
    check_ptr(ptr, name)?;
    // SAFETY: the caller passes a live handle from the matching constructor.
    Ok(unsafe { &*ptr })
}

pub(super) unsafe fn handle_mut<'a, T>(ptr: *mut T, name: &str) -> FfiResult<&'a mut T> {
    check_ptr(ptr, name)?;
    // SAFETY: the caller passes a live handle, not used concurrently.
    Ok(unsafe { &mut *ptr })
}

/// Writes `value` through `ptr` (a required out-parameter).
pub(super) unsafe fn write_out<T>(ptr: *mut T, name: &str, value: T) -> FfiResult {
    check_ptr(ptr, name)?;
    // SAFETY: non-null and aligned; the caller provides writable storage.
    unsafe { ptr.write(value) };
    Ok(())
}

/// Writes `value` through `ptr` unless it is NULL (an optional out-parameter).
pub(super) unsafe fn write_opt<T>(ptr: *mut T, name: &str, value: T) -> FfiResult {
    if ptr.is_null() {
        return Ok(());
    }
    unsafe { write_out(ptr, name, value) }
}

/// Checks a `T** out` argument and sets `*out = NULL`.
pub(super) unsafe fn clear_out<T>(out: *mut *mut T, name: &str) -> FfiResult {
    unsafe { write_out(out, name, std::ptr::null_mut()) }
}

pub(super) unsafe fn c_str<'a>(ptr: *const c_char, name: &str) -> FfiResult<&'a str> {
    if ptr.is_null() {
        return Err(null(name));
    }
    // SAFETY: the caller passes a NUL-terminated string.
    let s = unsafe { CStr::from_ptr(ptr) };
    s.to_str().map_err(|_| invalid(format!("{name} is not valid UTF-8")))
}

pub(super) fn check_finite(name: &str, v: &[f64]) -> FfiResult {
    match v.iter().position(|x| !x.is_finite()) {
        Some(i) => Err(invalid(format!("{name}[{i}] is not a finite number ({})", v[i]))),
        None => Ok(()),
    }
}

pub(super) fn boxed<T>(value: T) -> *mut T {
    Box::into_raw(Box::new(value))
}

/// Releases a handle made by `boxed`.
pub(super) unsafe fn destroy<T>(ptr: *mut T) {
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
