//! The C ABI of [`crate::batch`]: a JSONL file of jobs run on sessions over one model, the
//! runner `flame batch` uses (the Python package's `flame.batch` calls it). A run is one
//! blocking call; [`flame_batch_cancel`] from another thread stops it.

use std::ffi::c_char;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use super::errors::{catch_quietly, guard, Fail};
use super::handles::{model_ref, FlameModel};
use super::{str_arg, struct_arg, write_out, FlameStatus};
use crate::batch::{self, RunOptions, Runner};
use crate::error::{invalid_arg, Error};

/// A batch runner over one model. [`flame_batch_run`] is used by one thread at a time;
/// [`flame_batch_cancel`] may run on any thread. The runner keeps its model alive.
pub struct FlameBatch {
    runner: Runner,
    cancel: Arc<AtomicBool>,
}

/// Settings of one run. Initialise with [`flame_batch_params_default`].
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameBatchParams {
    /// `sizeof(FlameBatchParams)`.
    pub struct_size: u32,
    /// Sessions run at once; 0 = one per core, at most one per job; at most
    /// `FLAME_MAX_THREADS`.
    pub workers: u32,
    /// Kernel threads of each session; 0 = the cores shared among the sessions.
    pub threads: u32,
    /// Nonzero: skip the jobs the manifest records as done whose outputs exist, and append to
    /// the manifest; zero: start the manifest afresh.
    pub resume: u32,
    /// The folder relative job paths start from (UTF-8); NULL = the current folder.
    pub base_dir: *const c_char,
    /// The model's name recorded in glTF outputs (`flame batch` records the file's name);
    /// NULL = none.
    pub model_name: *const c_char,
}

/// The counts of a finished run. Set `struct_size = sizeof(FlameBatchSummary)` first.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default)]
pub struct FlameBatchSummary {
    /// `sizeof(FlameBatchSummary)`.
    pub struct_size: u32,
    /// Jobs in the file.
    pub total: u64,
    /// Jobs written by this run.
    pub ok: u64,
    /// Jobs that failed (their manifest lines say why).
    pub failed: u64,
    /// Jobs found done by an earlier run (`resume`).
    pub skipped: u64,
}

/// Fills `*params` with the defaults (workers and threads from the cores, no resume, paths
/// relative to the current folder).
///
/// # Safety
/// `params` points to writable memory for a `FlameBatchParams`.
#[no_mangle]
pub unsafe extern "C" fn flame_batch_params_default(params: *mut FlameBatchParams) -> FlameStatus {
    guard(|| write_out(params, default_params(), "params"))
}

fn default_params() -> FlameBatchParams {
    FlameBatchParams {
        struct_size: std::mem::size_of::<FlameBatchParams>() as u32,
        workers: 0,
        threads: 0,
        resume: 0,
        base_dir: std::ptr::null(),
        model_name: std::ptr::null(),
    }
}

/// Creates a batch runner over `model`; free it with [`flame_batch_free`].
///
/// # Safety
/// `model` is a live model; `batch` points to writable memory for a pointer.
#[no_mangle]
pub unsafe extern "C" fn flame_batch_new(
    model: *const FlameModel,
    batch: *mut *mut FlameBatch,
) -> FlameStatus {
    guard(|| {
        let m = model_ref(model)?;
        if batch.is_null() {
            return Err(invalid_arg!("`batch` is NULL").into());
        }
        let runner = Runner::new(Arc::clone(m.model()));
        let handle = Box::new(FlameBatch {
            cancel: runner.cancel_flag(),
            runner,
        });
        write_out(batch, Box::into_raw(handle), "batch")
    })
}

/// Frees a runner; NULL is ignored.
///
/// # Safety
/// `batch` is NULL or a live runner not in use by another thread.
#[no_mangle]
pub unsafe extern "C" fn flame_batch_free(batch: *mut FlameBatch) {
    catch_quietly(|| {
        if !batch.is_null() {
            drop(Box::from_raw(batch));
        }
    });
}

/// Runs the jobs of `jobs_path` (JSONL, the keys of `flame batch`'s job format) and appends a
/// line per job to `manifest_path` as each finishes. Returns `FLAME_STATUS_OK` when every job
/// was decided, even if some failed (`summary->failed`, and their manifest lines say why);
/// `FLAME_STATUS_CANCELLED` when [`flame_batch_cancel`] stopped the run (the running jobs
/// write nothing; the manifest records what finished); `IO` or `INVALID_ARGUMENT` when the
/// jobs file cannot be read (larger than 256 MiB, or not UTF-8) or the manifest cannot be
/// written. `summary` may be NULL; it is written only on `FLAME_STATUS_OK`.
///
/// # Safety
/// `batch` is a live runner; `jobs_path` and `manifest_path` NUL-terminated strings; `params`
/// NULL or a valid `FlameBatchParams` whose strings are NULL or NUL-terminated; `summary` NULL
/// or a writable `FlameBatchSummary` with its `struct_size` set.
#[no_mangle]
pub unsafe extern "C" fn flame_batch_run(
    batch: *const FlameBatch,
    jobs_path: *const c_char,
    manifest_path: *const c_char,
    params: *const FlameBatchParams,
    summary: *mut FlameBatchSummary,
) -> FlameStatus {
    guard(|| {
        let b = batch
            .as_ref()
            .ok_or_else(|| Fail::from(invalid_arg!("`batch` is NULL")))?;
        let jobs_path = PathBuf::from(str_arg(jobs_path, "jobs_path")?);
        let manifest = PathBuf::from(str_arg(manifest_path, "manifest_path")?);
        let defaults = default_params();
        let p = if params.is_null() {
            &defaults
        } else {
            struct_arg(params, |p| p.struct_size, "params")?
        };
        if let Some(s) = summary.as_ref() {
            super::check_size(
                s.struct_size,
                std::mem::size_of::<FlameBatchSummary>(),
                "summary",
            )?;
        }
        let optional = |ptr: *const c_char, name: &str| -> Result<String, Fail> {
            if ptr.is_null() {
                Ok(String::new())
            } else {
                str_arg(ptr, name).map(str::to_string)
            }
        };
        let opts = RunOptions {
            manifest,
            base_dir: PathBuf::from(optional(p.base_dir, "params.base_dir")?),
            workers: p.workers as usize,
            threads: p.threads as usize,
            resume: p.resume != 0,
            model_name: optional(p.model_name, "params.model_name")?,
        };
        let text = batch::read_jobs_file(&jobs_path)?;
        let jobs = batch::parse_jobs(&text, None)?;
        let result = b.runner.run(&jobs, &opts, &mut |_, _| {});
        // A cancel is for the run it stopped (or the next one, raised between runs).
        let cancelled = b.cancel.swap(false, Ordering::SeqCst);
        let s = result?;
        if cancelled && (s.cancelled > 0 || s.not_run > 0) {
            return Err(Error::Cancelled.into());
        }
        if let Some(out) = summary.as_mut() {
            let n = |v: usize| v as u64;
            *out = FlameBatchSummary {
                struct_size: out.struct_size,
                total: n(s.total),
                ok: n(s.ok),
                failed: n(s.failed),
                skipped: n(s.skipped),
            };
        }
        Ok(())
    })
}

/// Stops the [`flame_batch_run`] running on another thread: no further job starts, the running
/// ones stop at their next step without writing, and the run returns
/// `FLAME_STATUS_CANCELLED`. With no run going, the next run is cancelled. Any thread.
///
/// # Safety
/// `batch` is a live runner.
#[no_mangle]
pub unsafe extern "C" fn flame_batch_cancel(batch: *const FlameBatch) -> FlameStatus {
    guard(|| {
        let b = batch
            .as_ref()
            .ok_or_else(|| Fail::from(invalid_arg!("`batch` is NULL")))?;
        b.cancel.store(true, Ordering::SeqCst);
        Ok(())
    })
}
