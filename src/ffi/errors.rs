//! Status codes, the thread-local last-error message and the panic boundary.
//!
//! No input is expected to panic; the boundary is a last resort. A caught panic becomes
//! `FLAME_STATUS_INTERNAL` with the panic message, and prints nothing on the host's stderr:
//! the first entry point installs a process-wide panic hook that stays silent for panics raised
//! inside a libflame call (on the calling thread or on a libflame worker) and hands every other
//! panic to the hook that was installed before. `FLAME_LOG_PANICS=1` in the environment prints
//! them as Rust normally does.

use std::cell::{Cell, RefCell};
use std::ffi::{c_char, CString};
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::sync::Once;

use crate::error::Error;

/// What every fallible call returns.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameStatus {
    /// The call succeeded.
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
    /// A step produced NaN or infinity; the message names the step. The session refuses
    /// further steps (`WRONG_STATE`) until `flame_session_reset`.
    NotFinite = 9,
}

/// Why an entry point failed.
pub(crate) enum Fail {
    Core(Error),
    BufferTooSmall {
        needed: usize,
        given: usize,
        /// What the buffer holds: `floats`, `bytes`.
        unit: &'static str,
    },
}

thread_local! {
    static LAST_ERROR: RefCell<CString> = RefCell::new(CString::default());
    /// Whether this thread is inside an entry point's body.
    static IN_CALL: Cell<bool> = const { Cell::new(false) };
}

/// The environment variable that makes caught panics print (as `1`).
pub(crate) const LOG_PANICS_ENV: &str = "FLAME_LOG_PANICS";

/// Installs (once per process) the hook that keeps panics of libflame calls off stderr.
fn install_quiet_hook() {
    static ONCE: Once = Once::new();
    ONCE.call_once(|| {
        let previous = std::panic::take_hook();
        std::panic::set_hook(Box::new(move |info| {
            let ours = IN_CALL.with(Cell::get) || crate::pool::is_worker_thread();
            let log = std::env::var_os(LOG_PANICS_ENV).is_some_and(|v| v == "1");
            if !ours || log {
                previous(info);
            }
        }));
    });
}

/// Runs `f` marked as inside a libflame call (restoring the previous mark, for nested calls).
fn in_call<R>(f: impl FnOnce() -> R) -> R {
    struct Restore(bool);
    impl Drop for Restore {
        fn drop(&mut self) {
            IN_CALL.with(|c| c.set(self.0));
        }
    }
    let _restore = Restore(IN_CALL.with(|c| c.replace(true)));
    f()
}

fn set_last_error(msg: String) {
    // Interior NULs cannot appear in a C string; replace them rather than lose the message.
    let c = CString::new(msg.replace('\0', " ")).unwrap_or_default();
    LAST_ERROR.with(|e| *e.borrow_mut() = c);
}

/// Runs an entry point's body: turns errors into a status plus message and panics into
/// `INTERNAL` (silently, see the module comment), so nothing unwinds into the caller.
pub(crate) fn guard(f: impl FnOnce() -> Result<(), Fail>) -> FlameStatus {
    install_quiet_hook();
    match catch_unwind(AssertUnwindSafe(|| in_call(f))) {
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
                Error::NotFinite(_) => FlameStatus::NotFinite,
            };
            set_last_error(e.to_string());
            status
        }
        Ok(Err(Fail::BufferTooSmall {
            needed,
            given,
            unit,
        })) => {
            set_last_error(format!(
                "buffer too small: {needed} {unit} needed, {given} given"
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
        9 => "FLAME_STATUS_NOT_FINITE\0",
        _ => "FLAME_STATUS_UNKNOWN\0",
    };
    s.as_ptr() as *const c_char
}

/// `catch_unwind` for entry points without a status (the `_free` functions), with the same
/// quiet hook.
pub(crate) fn catch_quietly(f: impl FnOnce()) {
    install_quiet_hook();
    let _ = catch_unwind(AssertUnwindSafe(|| in_call(f)));
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::process::Command;

    /// Set in the child process that [`caught_panics_are_silent`] starts.
    const CHILD: &str = "FLAME_TEST_PANIC_CHILD";

    /// In the child: a panic on the calling thread and one on a worker of a libflame pool, both
    /// caught by the boundary. In a normal run: only the status and message are checked.
    #[test]
    fn panic_child() {
        let status = guard(|| panic!("boom on the caller"));
        assert_eq!(status, FlameStatus::Internal);
        let msg = LAST_ERROR.with(|e| e.borrow().to_string_lossy().into_owned());
        assert_eq!(msg, "internal error: boom on the caller");
        let pool = crate::pool::WorkerPool::new(2).unwrap();
        let status = guard(|| pool.install(|| panic!("boom on a worker")));
        assert_eq!(status, FlameStatus::Internal);
        let msg = LAST_ERROR.with(|e| e.borrow().to_string_lossy().into_owned());
        assert_eq!(msg, "internal error: boom on a worker");
        if std::env::var_os(CHILD).is_some() {
            // A panic outside any libflame call still reaches the previous hook.
            let _ = std::thread::spawn(|| panic!("boom outside")).join();
        }
    }

    /// Runs [`panic_child`] in a child process with stderr captured: the caught panics print
    /// nothing unless FLAME_LOG_PANICS=1, and the panic outside a call prints either way.
    #[test]
    fn caught_panics_are_silent() {
        let run = |log: bool| {
            let mut cmd = Command::new(std::env::current_exe().unwrap());
            cmd.args(["--exact", "ffi::errors::tests::panic_child", "--nocapture"])
                .args(["--test-threads", "1"])
                .env(CHILD, "1")
                .env_remove(LOG_PANICS_ENV);
            if log {
                cmd.env(LOG_PANICS_ENV, "1");
            }
            let out = cmd.output().unwrap();
            assert!(out.status.success(), "{out:?}");
            String::from_utf8_lossy(&out.stderr).into_owned()
        };
        let quiet = run(false);
        assert!(!quiet.contains("boom on"), "{quiet}");
        assert!(quiet.contains("boom outside"), "{quiet}");
        let loud = run(true);
        assert!(loud.contains("boom on the caller"), "{loud}");
        assert!(loud.contains("boom on a worker"), "{loud}");
    }
}
