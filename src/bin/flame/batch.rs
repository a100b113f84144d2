//! `flame batch`: the command-line front of `flame::batch`. It reads the jobs, loads the model
//! once, shows progress (a bar with rate and ETA on a terminal, one line per job otherwise),
//! turns Ctrl-C into the runner's cancel flag, and sums up at the end. The jobs themselves,
//! the manifest and resume are the library's.

use std::io::IsTerminal;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicPtr, Ordering};
use std::sync::Arc;
use std::time::Instant;

use flame::batch::{self, Job, Record, RunOptions, Runner, Status, Summary};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::args::BatchArgs;
use crate::{load_model, paths};

pub fn batch(a: &BatchArgs) -> Result<(), String> {
    let defaults = match &a.defaults {
        Some(text) => match serde_json::from_str::<serde_json::Value>(text) {
            Ok(serde_json::Value::Object(m)) => Some(m),
            Ok(_) => return Err("--defaults must be a JSON object".into()),
            Err(e) => return Err(format!("--defaults: {e}")),
        },
        None => None,
    };
    let (input, jobs) = match (&a.jobs, &a.prompts) {
        (Some(path), _) => {
            paths::check_readable(path)?;
            let text = batch::read_jobs_file(path).map_err(|e| e.to_string())?;
            let jobs = batch::parse_jobs(&text, defaults.as_ref()).map_err(|e| e.to_string())?;
            (path, jobs)
        }
        (None, Some(path)) => {
            paths::check_readable(path)?;
            let text = batch::read_jobs_file(path).map_err(|e| e.to_string())?;
            // The defaults are checked as a job's keys would be.
            let template: Job = match &defaults {
                Some(m) => serde_json::from_value(serde_json::Value::Object(m.clone()))
                    .map_err(|e| format!("--defaults: {e}"))?,
                None => Job::default(),
            };
            let pattern = a.out_pattern.as_deref().unwrap_or_default();
            let jobs = batch::jobs_from_prompts(&text, a.seeds, pattern, &template)
                .map_err(|e| e.to_string())?;
            (path, jobs)
        }
        (None, None) => unreachable!("clap requires --jobs or --prompts"),
    };
    if jobs.is_empty() {
        return Err(format!("{} holds no job", input.display()));
    }
    let manifest = a.manifest.clone().unwrap_or_else(|| {
        let mut name = input.clone().into_os_string();
        name.push(".manifest.jsonl");
        PathBuf::from(name)
    });
    paths::check_writable(&manifest)?;
    let loaded = load_model(&a.model)?;
    let runner = Runner::new(Arc::clone(&loaded.model));
    on_ctrl_c(runner.cancel_flag());
    let opts = RunOptions {
        manifest: manifest.clone(),
        base_dir: PathBuf::new(),
        workers: a.workers,
        threads: a.threads,
        resume: a.resume,
        model_name: loaded.name.clone(),
    };
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let (workers, threads) = batch::thread_policy(jobs.len(), a.workers, a.threads, cores);
    let plural = |n: usize, what: &str| format!("{n} {what}{}", if n == 1 { "" } else { "s" });
    eprintln!(
        "{}, {} at once with {} each",
        plural(jobs.len(), "job"),
        plural(workers.min(jobs.len()), "session"),
        plural(threads, "thread")
    );
    let mut progress = Progress::new(jobs.len());
    let mut failures = Vec::new();
    let summary = runner
        .run(&jobs, &opts, &mut |rec, sum| {
            if rec.status == Status::Failed {
                failures.push(rec.error.clone().unwrap_or_default());
            }
            progress.record(rec, sum);
        })
        .map_err(|e| e.to_string())?;
    progress.finish();
    eprintln!(
        "{} written, {} failed, {} skipped (done before), {} cancelled, {} not run in {:.1} s; \
         manifest {}",
        summary.ok,
        summary.failed,
        summary.skipped,
        summary.cancelled,
        summary.not_run,
        progress.start.elapsed().as_secs_f64(),
        manifest.display()
    );
    for f in &failures {
        eprintln!("failed: {f}");
    }
    if summary.failed > 0 || summary.cancelled > 0 || summary.not_run > 0 {
        return Err(format!(
            "{} of {} jobs not written",
            summary.failed + summary.cancelled + summary.not_run,
            summary.total
        ));
    }
    Ok(())
}

/// A bar on a terminal, plain lines otherwise (a log, a pipe, CI).
struct Progress {
    bar: Option<ProgressBar>,
    start: Instant,
}

impl Progress {
    fn new(total: usize) -> Progress {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar = ProgressBar::with_draw_target(
                Some(total as u64),
                ProgressDrawTarget::stderr_with_hz(4),
            );
            let style = ProgressStyle::with_template(
                "{wide_bar} {pos}/{len} jobs, {per_sec}, ETA {eta} {msg}",
            )
            .expect("the template is valid");
            bar.set_style(style);
            bar
        });
        Progress {
            bar,
            start: Instant::now(),
        }
    }

    fn record(&mut self, rec: &Record, sum: &Summary) {
        let done = sum.ok + sum.failed + sum.skipped + sum.cancelled;
        let line = match rec.status {
            Status::Ok => format!(
                "[{done}/{}] {} {} ({:.2} s)",
                sum.total,
                rec.job,
                rec.outputs.join(" "),
                rec.seconds
            ),
            Status::Failed => format!(
                "[{done}/{}] {} failed: {}",
                sum.total,
                rec.job,
                rec.error.as_deref().unwrap_or_default()
            ),
            Status::Cancelled => format!("[{done}/{}] {} cancelled", sum.total, rec.job),
            Status::Skipped => format!("[{done}/{}] {} done before", sum.total, rec.job),
        };
        match &self.bar {
            Some(bar) => {
                if rec.status == Status::Failed {
                    bar.println(line);
                }
                bar.set_position(done as u64);
            }
            None => {
                let rate = done as f64 / self.start.elapsed().as_secs_f64().max(1e-9);
                eprintln!("{line} {rate:.2} jobs/s");
            }
        }
    }

    fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish();
        }
    }
}

/// The flag Ctrl-C raises: the runner's, leaked so that the handler can reach it for the rest
/// of the process.
static CANCEL: AtomicPtr<AtomicBool> = AtomicPtr::new(std::ptr::null_mut());

/// The first Ctrl-C raises `flag` (running jobs stop at their next step and write nothing); the
/// handler then gives SIGINT back its default, so a second Ctrl-C ends the process at once
/// (outputs are renamed into place whole, so even then none is half-written).
#[cfg(unix)]
fn on_ctrl_c(flag: Arc<AtomicBool>) {
    extern "C" fn handler(_: libc::c_int) {
        let p = CANCEL.load(Ordering::SeqCst);
        if !p.is_null() {
            // SAFETY: `p` comes from `Arc::into_raw` and is never released.
            unsafe { (*p).store(true, Ordering::SeqCst) };
        }
        // SAFETY: signal(2) is async-signal-safe.
        unsafe { libc::signal(libc::SIGINT, libc::SIG_DFL) };
    }
    CANCEL.store(Arc::into_raw(flag).cast_mut(), Ordering::SeqCst);
    let handler: extern "C" fn(libc::c_int) = handler;
    // SAFETY: the handler only touches an atomic and calls signal(2).
    unsafe { libc::signal(libc::SIGINT, handler as libc::sighandler_t) };
}

/// Elsewhere Ctrl-C ends the process as usual (outputs are still renamed into place whole).
#[cfg(not(unix))]
fn on_ctrl_c(_flag: Arc<AtomicBool>) {
    let _ = &CANCEL;
}
