//! Status codes, the thread-local last-error message and the panic boundary.

use std::cell::RefCell;
use std::ffi::{c_char, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};

use crate::error::Error;

/// What every fallible call returns.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameStatus {
    Ok = 0,
    /// A NULL pointer, a wrong length, a value out of range.
    InvalidArgument = 1,
    /// A file could not be read.
    Io = 2,
    /// The model file is malformed, truncated or unsupported.
    BadModelFile = 3,
    /// A call out of order (for example step before a prompt).
    WrongState = 4,
    /// The step was cancelled by `flame_session_cancel`.
    Cancelled = 5,
    /// The tokenizer rejected the prompt.
    Tokenizer = 6,
    /// The output buffer is too small; the required length was written.
    BufferTooSmall = 7,
    /// A bug inside libflame (a caught panic); the message says where.
    Internal = 8,
}

/// Why an entry point failed.
pub(crate) enum Fail {
    Core(Error),
    BufferTooSmall { needed: usize, given: usize },
}

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
}

fn set_last_error(msg: String) {
    // Interior NULs cannot appear in a C string; replace them rather than lose the message.
    let c = CString::new(msg.replace('\0', " ")).unwrap_or_default();
    LAST_ERROR.with(|e| *e.borrow_mut() = c);
}

/// Runs an entry point's body: turns errors into a status plus message and panics into
/// `INTERNAL`, so nothing unwinds into the caller.
pub(crate) fn guard(f: impl FnOnce() -> Result<(), Fail>) -> FlameStatus {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(())) => {
            set_last_error(String::new());
            FlameStatus::Ok
        }
        Ok(Err(Fail::Core(e))) => {
            let status = match &e {
                Error::Io { .. } | Error::Write { .. } => FlameStatus::Io,
                Error::BadModelFile(_) => FlameStatus::BadModelFile,
                Error::InvalidArgument(_) => FlameStatus::InvalidArgument,
                Error::WrongState(_) => FlameStatus::WrongState,
                Error::Cancelled => FlameStatus::Cancelled,
                Error::Tokenizer(_) => FlameStatus::Tokenizer,
            };
            set_last_error(e.to_string());
            status
        }
        Ok(Err(Fail::BufferTooSmall { needed, given })) => {
            set_last_error(format!(
                "buffer too small: {needed} floats needed, {given} given"
            ));
            FlameStatus::BufferTooSmall
        }
        Err(panic) => {
            let what = panic
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| panic.downcast_ref::<String>().cloned())
                .unwrap_or_else(|| "unknown panic".into());
            set_last_error(format!("internal error: {what}"));
            FlameStatus::Internal
        }
    }
}

/// The message of the last failed call on this thread ("" after a successful call). The
/// pointer stays valid until the next libflame call on the same thread.
#[no_mangle]
pub extern "C" fn flame_last_error() -> *const c_char {
    LAST_ERROR.with(|e| e.borrow().as_ptr())
}

/// A static name for a status code, e.g. `"FLAME_STATUS_BAD_MODEL_FILE"`.
#[no_mangle]
pub extern "C" fn flame_status_string(status: i32) -> *const c_char {
    let s: &'static str = match status {
        0 => "FLAME_STATUS_OK\0",
        1 => "FLAME_STATUS_INVALID_ARGUMENT\0",
        2 => "FLAME_STATUS_IO\0",
        3 => "FLAME_STATUS_BAD_MODEL_FILE\0",
        4 => "FLAME_STATUS_WRONG_STATE\0",
        5 => "FLAME_STATUS_CANCELLED\0",
        6 => "FLAME_STATUS_TOKENIZER\0",
        7 => "FLAME_STATUS_BUFFER_TOO_SMALL\0",
        8 => "FLAME_STATUS_INTERNAL\0",
        _ => "FLAME_STATUS_UNKNOWN\0",
    };
    s.as_ptr() as *const c_char
}
