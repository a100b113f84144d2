//! Bulk generation: many jobs, one model. [`parse_jobs`](crate::batch::parse_jobs) reads a
//! JSONL file of jobs (one JSON object a line whose keys are `flame generate`'s options, see
//! [`Job`](crate::batch::Job)) or [`jobs_from_prompts`](crate::batch::jobs_from_prompts) makes
//! them from a list of prompts; a [`Runner`](crate::batch::Runner) runs them on sessions over
//! one shared [`Model`](crate::models::Model), writes every output through a temporary file
//! renamed into place (no half-written file ever carries an output's name), and appends one
//! manifest line per job as it finishes ([`Record`](crate::batch::Record)). A job renders its
//! files exactly as `flame generate` does, so each output is the same bytes as that job run
//! alone.
//!
//! This module holds the runner shared by the CLI (`flame batch`), the C ABI
//! (`flame_batch_run`) and through it the Python package; it has no terminal display and no
//! signal handling, which are the fronts' (they raise
//! [`Runner::cancel_flag`](crate::batch::Runner::cancel_flag)).

use std::collections::HashMap;
use std::fs::{File, OpenOptions};
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{mpsc, Arc};
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::error::{invalid_arg, Error, Result};
use crate::models::Model;
use crate::motion::amass::AmassLayout;
use crate::motion::{self, gltf, Convention, Feet, Finish, Format, Layout, Poses, QuatOrder};
use crate::session::{Sampler, Session, SessionParams, Which};
use crate::stages::Stage;

/// The largest jobs file read (a million jobs of a few hundred bytes fit many times over);
/// checked before the file is read, so a wrong path to a huge file fails at once.
pub const MAX_JOBS_BYTES: u64 = 256 << 20;

/// The most jobs one run takes (lines of a JSONL file, or prompts × seeds).
pub const MAX_JOBS: usize = 1_000_000;

/// One job: the options of `flame generate` as JSON keys. Unknown keys are refused (a typo must
/// not silently fall back to a default). Paths are relative to [`RunOptions::base_dir`].
#[derive(Clone, Debug, Default, Deserialize, Serialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Job {
    /// The job's name in the manifest (default: its line number); unique within a run.
    pub id: Option<String>,
    /// The sentence (`--prompt`).
    pub prompt: Option<String>,
    /// Time stages `"TEXT@FRAMES"` in order (`--stage`, repeated).
    pub stages: Option<Vec<String>>,
    /// Frames to generate (`--frames`).
    pub frames: Option<usize>,
    /// Seed of the noise (`--seed`, default 0).
    #[serde(default)]
    pub seed: u64,
    /// Sampling steps (`--steps`).
    pub steps: Option<usize>,
    /// Sampler name (`--sampler`).
    pub sampler: Option<String>,
    /// Respacing string (`--respacing`).
    pub respacing: Option<String>,
    /// DDIM eta (`--eta`).
    pub eta: Option<f32>,
    /// Classifier-free guidance scale (`--guidance`).
    pub guidance: Option<f32>,
    /// The output file (`--out`): .npy, .npz, .bvh, .json, .glb or .gltf.
    pub out: Option<PathBuf>,
    /// World joint positions, .npy (`--positions`).
    pub positions: Option<PathBuf>,
    /// AMASS layout of a .npz, smplh or smplx (`--amass`).
    pub amass: Option<String>,
    /// Pose convention (`--convention`).
    pub convention: Option<String>,
    /// Feature smoothing sigma in frames (`--smooth`).
    pub smooth: Option<f32>,
    /// Quaternion order of a JSON output, wxyz or xyzw (`--quat`).
    pub quat: Option<String>,
    /// Foot contacts, lock or off (`--feet`).
    pub feet: Option<String>,
    /// Lowest contact at height 0 (`--ground on|off`).
    pub ground: Option<bool>,
    /// Output frame rate (`--fps`).
    pub fps: Option<f64>,
    /// keep, in-place or separate (`--root-motion`).
    pub root_motion: Option<String>,
    /// Remove the heading's drift too (`--remove-yaw`).
    #[serde(default)]
    pub remove_yaw: bool,
    /// Contact height in metres (`--contact-height`).
    pub contact_height: Option<f64>,
    /// Contact speed in m/s (`--contact-speed`).
    pub contact_speed: Option<f64>,
}

/// One job as read: its manifest name, its line in the input, and the job or why it could not
/// be read.
#[derive(Clone, Debug)]
pub struct JobEntry {
    /// The job's name in the manifest: its `id`, else its line number.
    pub key: String,
    /// 1-based line of the input it came from.
    pub line: usize,
    /// The job, or the reason the line is not one (reported in the manifest; the others run).
    pub job: std::result::Result<Job, String>,
}

/// Reads a JSONL file of jobs (blank lines skipped). Every line becomes an entry, a malformed
/// one carrying its error, so the run reports it and runs the others. `defaults` holds keys
/// every job takes unless its own line sets them. Only more than [`MAX_JOBS`] lines is an error.
pub fn parse_jobs(
    text: &str,
    defaults: Option<&serde_json::Map<String, serde_json::Value>>,
) -> Result<Vec<JobEntry>> {
    let mut entries = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let trimmed = raw.trim();
        if trimmed.is_empty() {
            continue;
        }
        if entries.len() == MAX_JOBS {
            return Err(invalid_arg!("more than {MAX_JOBS} jobs"));
        }
        let job = parse_line(trimmed, defaults).map_err(|e| format!("line {line}: {e}"));
        let key = match &job {
            Ok(Job { id: Some(id), .. }) => id.clone(),
            _ => line.to_string(),
        };
        entries.push(JobEntry { key, line, job });
    }
    Ok(entries)
}

fn parse_line(
    text: &str,
    defaults: Option<&serde_json::Map<String, serde_json::Value>>,
) -> std::result::Result<Job, String> {
    // The line is the whole document to serde, so its "line 1" would mislead: say the column.
    let value: serde_json::Value = serde_json::from_str(text)
        .map_err(|e| e.to_string().replace(" at line 1 column ", " at column "))?;
    let serde_json::Value::Object(mut map) = value else {
        return Err("a job is a JSON object".into());
    };
    for (k, v) in defaults.into_iter().flatten() {
        map.entry(k.clone()).or_insert_with(|| v.clone());
    }
    let job: Job =
        serde_json::from_value(serde_json::Value::Object(map)).map_err(|e| e.to_string())?;
    if job.id.as_deref().is_some_and(|id| id.trim().is_empty()) {
        return Err("`id` is blank".into());
    }
    Ok(job)
}

/// Jobs from a text of prompts (one a line; blank lines and lines starting with `#` skipped),
/// each run with seeds `0..seeds`. `pattern` names the output: `{line}` is the prompt's line,
/// `{seed}` the seed, `{n}` the job's number from 1. `template` gives the other keys.
pub fn jobs_from_prompts(
    text: &str,
    seeds: u64,
    pattern: &str,
    template: &Job,
) -> Result<Vec<JobEntry>> {
    if seeds == 0 {
        return Err(invalid_arg!("seeds must be at least 1"));
    }
    let mut entries = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let prompt = raw.trim();
        if prompt.is_empty() || prompt.starts_with('#') {
            continue;
        }
        for seed in 0..seeds {
            if entries.len() == MAX_JOBS {
                return Err(invalid_arg!("more than {MAX_JOBS} jobs"));
            }
            let line = i + 1;
            let out = pattern
                .replace("{line}", &line.to_string())
                .replace("{seed}", &seed.to_string())
                .replace("{n}", &(entries.len() + 1).to_string());
            let job = Job {
                id: Some(format!("{line}:{seed}")),
                prompt: Some(prompt.to_string()),
                seed,
                out: Some(PathBuf::from(out)),
                ..template.clone()
            };
            entries.push(JobEntry {
                key: format!("{line}:{seed}"),
                line,
                job: Ok(job),
            });
        }
    }
    Ok(entries)
}

/// How a run goes.
#[derive(Clone, Debug, Default)]
pub struct RunOptions {
    /// The manifest (JSONL, one [`Record`] a line, appended as jobs finish).
    pub manifest: PathBuf,
    /// The folder relative job paths start from.
    pub base_dir: PathBuf,
    /// Sessions run at once; 0 = [`thread_policy`]'s choice.
    pub workers: usize,
    /// Kernel threads of each session; 0 = [`thread_policy`]'s choice.
    pub threads: usize,
    /// Skip jobs whose manifest entry says `ok` with the same outputs, all of which exist; keep
    /// the manifest and append to it (without: the manifest is started afresh).
    pub resume: bool,
    /// The model's name, recorded in glTF outputs (`flame generate` records the file's name).
    pub model_name: String,
}

/// How many sessions run at once and how many kernel threads each gets, on `cores` cores for
/// `jobs` jobs: one session per core (no more than there are jobs), and the cores left over
/// shared among the sessions' kernels. Small models scale poorly inside one step (the matrices
/// are narrow), so overlapping whole jobs uses the cores better than wide sessions. An explicit
/// `workers` or `threads` (non-zero) is kept, workers at most [`crate::pool::MAX_THREADS`] (a
/// session refuses more threads than that itself).
pub fn thread_policy(jobs: usize, workers: usize, threads: usize, cores: usize) -> (usize, usize) {
    let cores = cores.max(1);
    // Each worker is a thread of ours: bounded as a session's pool is.
    let workers = match workers {
        0 => cores.min(jobs).max(1),
        w => w,
    }
    .min(crate::pool::MAX_THREADS);
    let threads = match threads {
        0 => (cores / workers).max(1),
        t => t,
    };
    (workers, threads)
}

/// What became of a job.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Its outputs are written.
    Ok,
    /// It could not be read, checked or run (see [`Record::error`]); nothing of it is written.
    Failed,
    /// The run was cancelled while it ran; nothing of it is written.
    Cancelled,
    /// `resume` found it done by an earlier run (not written to the manifest again).
    Skipped,
}

/// What the text encoder made of a job's prompt.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PromptReport {
    /// Tokens of the whole prompt, special tokens included.
    pub tokens: usize,
    /// Tokens the encoder saw.
    pub kept: usize,
    /// The text the encoder's window cut off (empty when nothing was).
    pub dropped: String,
    /// The prompt was blank: generated without a text condition.
    pub unconditional: bool,
}

/// One manifest line.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Record {
    /// The job's name ([`JobEntry::key`]).
    pub job: String,
    /// Its line in the input.
    pub line: usize,
    /// What became of it.
    pub status: Status,
    /// The files written (the job's paths joined to the base folder).
    #[serde(default)]
    pub outputs: Vec<String>,
    /// Wall time of the job, sampling and writing.
    #[serde(default)]
    pub seconds: f64,
    /// The prompt's fit in the text encoder (none for time stages).
    #[serde(default)]
    pub prompt: Option<PromptReport>,
    /// Why it failed.
    #[serde(default)]
    pub error: Option<String>,
}

/// The counts of a finished run.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Summary {
    /// Jobs in the input.
    pub total: usize,
    /// Jobs written by this run.
    pub ok: usize,
    /// Jobs that failed.
    pub failed: usize,
    /// Jobs `resume` found done.
    pub skipped: usize,
    /// Jobs cancelled while they ran.
    pub cancelled: usize,
    /// Jobs never started because the run was cancelled.
    pub not_run: usize,
}

/// Runs jobs on sessions over one model.
pub struct Runner {
    model: Arc<Model>,
    cancel: Arc<AtomicBool>,
}

/// A job checked against the model and the other jobs, ready to run.
struct Plan {
    key: String,
    line: usize,
    job: Job,
    out: PathBuf,
    kind: OutKind,
    positions: Option<PathBuf>,
    convention: Convention,
    quat: QuatOrder,
    finish: Finish,
    params: SessionParams,
    stages: Option<Vec<Stage>>,
}

#[derive(Clone, Copy, PartialEq)]
enum OutKind {
    Features,
    Bvh,
    Json,
    Gltf(gltf::Container),
    Amass(AmassLayout),
}

/// Why a job stopped.
enum JobError {
    Cancelled,
    Failed(String),
}

impl From<Error> for JobError {
    fn from(e: Error) -> JobError {
        match e {
            Error::Cancelled => JobError::Cancelled,
            e => JobError::Failed(e.to_string()),
        }
    }
}

impl Runner {
    /// A runner over `model`.
    pub fn new(model: Arc<Model>) -> Runner {
        Runner {
            model,
            cancel: Arc::new(AtomicBool::new(false)),
        }
    }

    /// Raised (from any thread, a signal handler included), no new job starts and the running
    /// ones stop at their next step without writing anything.
    pub fn cancel_flag(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.cancel)
    }

    /// Runs `jobs` as `opts` says, calling `on_record` (on the calling thread) for every job
    /// as it is decided, with the counts so far. An error is the run's own (the manifest cannot
    /// be opened or written); a job's failure is in its record and the summary.
    pub fn run(
        &self,
        jobs: &[JobEntry],
        opts: &RunOptions,
        on_record: &mut dyn FnMut(&Record, &Summary),
    ) -> Result<Summary> {
        let done = if opts.resume {
            read_manifest(&opts.manifest)?
        } else {
            HashMap::new()
        };
        let mut manifest = open_manifest(&opts.manifest, opts.resume)?;
        let mut summary = Summary {
            total: jobs.len(),
            ..Summary::default()
        };
        let mut report = |rec: Record, summary: &mut Summary| -> Result<()> {
            match rec.status {
                Status::Ok => summary.ok += 1,
                Status::Failed => summary.failed += 1,
                Status::Cancelled => summary.cancelled += 1,
                Status::Skipped => summary.skipped += 1,
            }
            if rec.status != Status::Skipped {
                manifest.write(&rec)?;
            }
            on_record(&rec, summary);
            Ok(())
        };
        let mut queue = Vec::new();
        let mut claimed: HashMap<PathBuf, String> = HashMap::new();
        let mut ids: HashMap<&str, usize> = HashMap::new();
        for entry in jobs {
            let plan = match self.check(entry, opts, &mut claimed, &mut ids) {
                Ok(p) => p,
                Err(e) => {
                    report(failed(entry, e), &mut summary)?;
                    continue;
                }
            };
            if let Some(rec) = done.get(&plan.key) {
                if rec.outputs == plan.outputs() && plan.paths().iter().all(|p| p.is_file()) {
                    let skipped = Record {
                        status: Status::Skipped,
                        ..rec.clone()
                    };
                    report(skipped, &mut summary)?;
                    continue;
                }
            }
            queue.push(plan);
        }
        let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
        let (workers, threads) = thread_policy(queue.len(), opts.workers, opts.threads, cores);
        let next = AtomicUsize::new(0);
        let (tx, rx) = mpsc::channel::<Record>();
        let mut outcome = Ok(());
        std::thread::scope(|s| {
            for _ in 0..workers.min(queue.len()) {
                let tx = tx.clone();
                let (queue, next) = (&queue, &next);
                s.spawn(move || loop {
                    if self.cancel.load(Ordering::Relaxed) {
                        break;
                    }
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some(plan) = queue.get(i) else { break };
                    let rec = self.run_one(plan, threads, &opts.model_name);
                    if tx.send(rec).is_err() {
                        break;
                    }
                });
            }
            drop(tx);
            for rec in rx {
                if outcome.is_ok() {
                    outcome = report(rec, &mut summary);
                    if outcome.is_err() {
                        // The manifest cannot be written: stop rather than run unrecorded jobs.
                        self.cancel.store(true, Ordering::Relaxed);
                    }
                }
            }
        });
        outcome?;
        summary.not_run =
            summary.total - summary.ok - summary.failed - summary.skipped - summary.cancelled;
        Ok(summary)
    }

    /// The job checked before anything runs: its keys, its output paths (folder present, no
    /// other job writing the same file) and its id.
    fn check<'a>(
        &self,
        entry: &'a JobEntry,
        opts: &RunOptions,
        claimed: &mut HashMap<PathBuf, String>,
        ids: &mut HashMap<&'a str, usize>,
    ) -> std::result::Result<Plan, String> {
        let job = entry.job.as_ref().map_err(Clone::clone)?;
        if let Some(line) = ids.insert(&entry.key, entry.line) {
            return Err(format!(
                "line {}: job `{}` is also line {line}'s name",
                entry.line, entry.key
            ));
        }
        let plan = Plan::new(entry, job, &opts.base_dir, &self.model)
            .map_err(|e| format!("line {}: {e}", entry.line))?;
        // `out/a.bvh` and `./out/a.bvh` are one file: compared without `.` components.
        let same = |p: &PathBuf| -> PathBuf {
            p.components()
                .filter(|c| *c != std::path::Component::CurDir)
                .collect()
        };
        for p in plan.paths() {
            if let Some(other) = claimed.get(&same(p)) {
                return Err(format!(
                    "line {}: {} is also an output of job {other}",
                    entry.line,
                    p.display()
                ));
            }
        }
        for p in plan.paths() {
            claimed.insert(same(p), entry.key.clone());
        }
        Ok(plan)
    }

    /// Runs one job; a panic in it fails that job, not the run.
    fn run_one(&self, plan: &Plan, threads: usize, model_name: &str) -> Record {
        let t0 = Instant::now();
        let mut prompt = None;
        let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            self.generate(plan, threads, model_name, &mut prompt)
        }))
        .unwrap_or_else(|p| {
            let what = p
                .downcast_ref::<&str>()
                .map(|s| s.to_string())
                .or_else(|| p.downcast_ref::<String>().cloned())
                .unwrap_or_default();
            Err(JobError::Failed(format!("internal error: {what}")))
        });
        let (status, error) = match result {
            Ok(()) => (Status::Ok, None),
            Err(JobError::Cancelled) => (Status::Cancelled, None),
            Err(JobError::Failed(e)) => {
                let e = e.strip_prefix("invalid argument: ").unwrap_or(&e);
                (Status::Failed, Some(format!("line {}: {e}", plan.line)))
            }
        };
        Record {
            job: plan.key.clone(),
            line: plan.line,
            status,
            outputs: if status == Status::Ok {
                plan.outputs()
            } else {
                Vec::new()
            },
            seconds: t0.elapsed().as_secs_f64(),
            prompt,
            error,
        }
    }

    /// `flame generate`'s path for one job: the session, its prompt, every step, the files.
    fn generate(
        &self,
        plan: &Plan,
        threads: usize,
        model_name: &str,
        prompt: &mut Option<PromptReport>,
    ) -> std::result::Result<(), JobError> {
        let params = SessionParams {
            threads,
            ..plan.params.clone()
        };
        let mut session = Session::new(Arc::clone(&self.model), &params)?;
        match (&plan.stages, &plan.job.prompt) {
            (Some(stages), _) => session.set_prompt_stages(stages)?,
            (None, Some(p)) => session.set_prompt(p)?,
            (None, None) => return Err(JobError::Failed("no prompt".into())),
        }
        *prompt = session.prompt_info().map(|i| PromptReport {
            tokens: i.tokens,
            kept: i.kept,
            dropped: i.dropped.clone(),
            unconditional: i.unconditional,
        });
        while session.steps_left() > 0 {
            if self.cancel.load(Ordering::Relaxed) {
                return Err(JobError::Cancelled);
            }
            session.step()?;
        }
        let (x, frames) = session.motion(Which::Sample)?;
        let files = plan.render(&self.model, x, frames, model_name)?;
        write_files(&files).map_err(JobError::Failed)
    }
}

fn failed(entry: &JobEntry, error: String) -> Record {
    Record {
        job: entry.key.clone(),
        line: entry.line,
        status: Status::Failed,
        outputs: Vec::new(),
        seconds: 0.0,
        prompt: None,
        error: Some(error),
    }
}

/// A named value of the library's (`FromStr`), its message under the job's key.
fn named<T>(key: &str, value: &Option<String>) -> std::result::Result<Option<T>, String>
where
    T: FromStr<Err = Error>,
{
    value
        .as_deref()
        .map(|s| {
            s.parse::<T>().map_err(|e| {
                let m = e.to_string();
                let m = m
                    .strip_prefix("invalid argument: ")
                    .unwrap_or(&m)
                    .to_string();
                format!("`{key}`: {m}")
            })
        })
        .transpose()
}

fn extension(path: &Path) -> Option<String> {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
}

/// The folder of `path` exists and is a folder, and `path` is not one.
fn check_folder(key: &str, path: &Path) -> std::result::Result<(), String> {
    let p = path.display();
    if path.is_dir() {
        return Err(format!("`{key}` {p}: it is a folder"));
    }
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    if !dir.is_dir() {
        return Err(format!(
            "`{key}` {p}: the folder {} does not exist",
            dir.display()
        ));
    }
    Ok(())
}

impl Plan {
    fn new(
        entry: &JobEntry,
        job: &Job,
        base: &Path,
        model: &Model,
    ) -> std::result::Result<Plan, String> {
        let stages = match (&job.prompt, &job.stages) {
            (Some(_), Some(_)) => return Err("`prompt` and `stages` exclude each other".into()),
            (None, None) => return Err("a job needs `prompt` or `stages`".into()),
            (None, Some(s)) if s.is_empty() => return Err("`stages` is empty".into()),
            (None, Some(s)) => Some(
                s.iter()
                    .map(|s| crate::stages::parse_stage(s).map_err(|e| format!("`stages`: {e}")))
                    .collect::<std::result::Result<Vec<_>, _>>()?,
            ),
            (Some(_), None) => None,
        };
        let mut frames = job.frames;
        if let Some(stages) = &stages {
            let total = stages
                .iter()
                .try_fold(0usize, |a, s| a.checked_add(s.frames))
                .ok_or("`stages`: too many frames")?;
            match frames {
                Some(f) if f != total => {
                    return Err(format!(
                        "`frames` {f}: the stages add up to {total} frames (leave `frames` out)"
                    ))
                }
                _ => frames = Some(total),
            }
        }
        let out = base.join(job.out.as_ref().ok_or("a job needs `out`")?);
        let kind = match extension(&out).as_deref() {
            Some("npy") => OutKind::Features,
            Some("npz") => OutKind::Amass(
                named::<AmassLayout>("amass", &job.amass)?.unwrap_or(AmassLayout::SmplH),
            ),
            Some("bvh") => OutKind::Bvh,
            Some("json") => OutKind::Json,
            Some(e @ ("glb" | "gltf")) => {
                OutKind::Gltf(gltf::Container::from_extension(e).unwrap_or(gltf::Container::Glb))
            }
            _ => {
                return Err(format!(
                    "`out` {}: must end in .npy, .npz, .bvh, .json, .glb or .gltf",
                    out.display()
                ))
            }
        };
        if job.amass.is_some() && !matches!(kind, OutKind::Amass(_)) {
            return Err(format!(
                "`amass` is for an AMASS .npz; `out` {} is not one",
                out.display()
            ));
        }
        check_folder("out", &out)?;
        let positions = job.positions.as_ref().map(|p| base.join(p));
        if let Some(p) = &positions {
            if extension(p).as_deref() != Some("npy") {
                return Err(format!("`positions` {}: must end in .npy", p.display()));
            }
            check_folder("positions", p)?;
            if *p == out {
                return Err(format!(
                    "`out` and `positions` name the same file {}",
                    p.display()
                ));
            }
        }
        let convention = match (kind, named::<Convention>("convention", &job.convention)?) {
            (OutKind::Gltf(_), Some(c)) if c != Convention::Gltf => {
                return Err(format!(
                    "`convention` {c}: a glTF file is always in glTF's own convention"
                ))
            }
            (OutKind::Amass(_), Some(c)) => {
                return Err(format!(
                    "`convention` {c}: an AMASS .npz is always in AMASS's world"
                ))
            }
            (_, Some(c)) => c,
            (OutKind::Bvh | OutKind::Gltf(_), None) => Convention::Gltf,
            _ => Convention::Native,
        };
        if let Some(s) = job.smooth {
            if !(s.is_finite() && s >= 0.0) {
                return Err(format!(
                    "`smooth` must be a number of frames, 0 or more, got {s}"
                ));
            }
        }
        let feet = named::<Feet>("feet", &job.feet)?.unwrap_or(Feet::Lock);
        let root_motion =
            named::<motion::RootMotion>("root_motion", &job.root_motion)?.unwrap_or_default();
        if job.remove_yaw && root_motion == motion::RootMotion::Keep {
            return Err("`remove_yaw` needs `root_motion` in-place or separate".into());
        }
        let defaults = motion::ContactParams::default();
        let finish = Finish {
            contacts: motion::ContactParams {
                height: job.contact_height.unwrap_or(defaults.height),
                speed: job.contact_speed.unwrap_or(defaults.speed),
                ..defaults
            },
            ground: job.ground.unwrap_or(feet == Feet::Lock),
            feet,
            root_motion,
            remove_yaw: job.remove_yaw,
            fps: job.fps,
            ..Finish::default()
        };
        finish.validate().map_err(|e| e.to_string())?;
        let params = SessionParams {
            frames,
            steps: job.steps,
            sampler: named::<Sampler>("sampler", &job.sampler)?,
            respacing: job.respacing.clone(),
            eta: job.eta,
            guidance: job.guidance,
            clip_denoised: None,
            seed: job.seed,
            threads: 1,
            looped: false,
        };
        if let Some(f) = frames {
            if f == 0 || f > model.max_frames() {
                return Err(format!(
                    "`frames` must be between 1 and {} for this model, got {f}",
                    model.max_frames()
                ));
            }
        }
        Ok(Plan {
            key: entry.key.clone(),
            line: entry.line,
            job: job.clone(),
            out,
            kind,
            positions,
            convention,
            quat: named::<QuatOrder>("quat", &job.quat)?.unwrap_or(QuatOrder::Wxyz),
            finish,
            params,
            stages,
        })
    }

    /// The files the job writes.
    fn paths(&self) -> Vec<&PathBuf> {
        std::iter::once(&self.out)
            .chain(self.positions.as_ref())
            .collect()
    }

    /// The files the job writes, as the manifest records them.
    fn outputs(&self) -> Vec<String> {
        self.paths()
            .iter()
            .map(|p| p.display().to_string())
            .collect()
    }

    /// The prompt glTF files record: the stages' texts joined as `flame generate` joins them.
    fn prompt_text(&self) -> String {
        match &self.stages {
            Some(s) => s
                .iter()
                .map(|s| s.text.as_str())
                .collect::<Vec<_>>()
                .join("; "),
            None => self.job.prompt.clone().unwrap_or_default(),
        }
    }

    /// Every file's bytes, rendered as `flame generate` renders them (features untouched,
    /// poses decoded, finished and written in the job's convention).
    fn render(
        &self,
        model: &Model,
        x: &[f32],
        frames: usize,
        model_name: &str,
    ) -> Result<Vec<(PathBuf, Vec<u8>)>> {
        let dim = model.motion_dim();
        if self.kind == OutKind::Features && self.positions.is_none() {
            return Ok(vec![(
                self.out.clone(),
                crate::npy::encode_f32(&[frames, dim], x),
            )]);
        }
        let format = model.motion_format();
        // FLAME's official output smooths its features; other formats are left as they are.
        let default_smooth = if format == Format::Smpl24Rot6d {
            1.0
        } else {
            0.0
        };
        let opts = model.read_options(self.job.smooth.unwrap_or(default_smooth), true);
        let raw = Poses::decode(format, x, frames, &opts)?;
        let source_fps = model.config().motion.fps;
        let poses = self.finish.apply(&raw, source_fps as f64)?;
        let fps = self.finish.output_fps(source_fps as f64) as f32;
        let prompt = self.prompt_text();
        let bytes = match self.kind {
            OutKind::Features => crate::npy::encode_f32(&[raw.frames(), dim], x),
            OutKind::Bvh => motion::bvh::to_string(&poses, self.convention, fps)?.into_bytes(),
            OutKind::Json => {
                motion::json::to_string(&poses, self.convention, fps, self.quat)?.into_bytes()
            }
            OutKind::Gltf(container) => {
                let opts = gltf::GltfOptions {
                    fps,
                    prompt: Some(&prompt),
                    model: Some(model_name),
                    seed: Some(self.job.seed),
                    name: None,
                };
                gltf::to_bytes(&poses, &opts, container)?
            }
            OutKind::Amass(layout) => motion::amass::to_npz(&poses, fps as f64, layout)?,
        };
        let mut files = vec![(self.out.clone(), bytes)];
        if let Some(p) = &self.positions {
            let pos = poses.layout(Layout::GlobalPositions, self.convention)?;
            files.push((
                p.clone(),
                crate::npy::encode_f32(&[poses.frames(), poses.joint_count(), 3], &pos),
            ));
        }
        Ok(files)
    }
}

/// A temporary name beside `path`, unique to this process and call.
fn temp_path(path: &Path) -> PathBuf {
    static COUNTER: AtomicUsize = AtomicUsize::new(0);
    let n = COUNTER.fetch_add(1, Ordering::Relaxed);
    let mut name = std::ffi::OsString::from(".");
    name.push(path.file_name().unwrap_or_default());
    name.push(format!(".flame-tmp-{}-{n}", std::process::id()));
    path.with_file_name(name)
}

/// Writes every file under a temporary name, then renames them all into place: a reader (or a
/// resumed run) never sees a half-written output, only a whole one or none.
fn write_files(files: &[(PathBuf, Vec<u8>)]) -> std::result::Result<(), String> {
    let mut temps = Vec::with_capacity(files.len());
    let cleanup = |temps: &[PathBuf]| {
        for t in temps {
            let _ = std::fs::remove_file(t);
        }
    };
    for (path, bytes) in files {
        let tmp = temp_path(path);
        if let Err(e) = std::fs::write(&tmp, bytes) {
            cleanup(&temps);
            let _ = std::fs::remove_file(&tmp);
            return Err(format!("cannot write {}: {e}", path.display()));
        }
        temps.push(tmp);
    }
    for (i, ((path, _), tmp)) in files.iter().zip(&temps).enumerate() {
        if let Err(e) = std::fs::rename(tmp, path) {
            cleanup(&temps[i..]);
            return Err(format!("cannot write {}: {e}", path.display()));
        }
    }
    Ok(())
}

/// The manifest being written: one JSON line per record, flushed at once so that a run stopped
/// any way leaves every finished job recorded.
struct Manifest {
    file: BufWriter<File>,
    path: PathBuf,
}

impl Manifest {
    fn write(&mut self, rec: &Record) -> Result<()> {
        let err = |source| Error::Write {
            path: self.path.display().to_string(),
            source,
        };
        let line = serde_json::to_string(rec).map_err(|e| err(e.into()))?;
        writeln!(self.file, "{line}").map_err(err)?;
        self.file.flush().map_err(err)
    }
}

fn open_manifest(path: &Path, append: bool) -> Result<Manifest> {
    let file = OpenOptions::new()
        .create(true)
        .write(true)
        .append(append)
        .truncate(!append)
        .open(path)
        .map_err(|source| Error::Write {
            path: path.display().to_string(),
            source,
        })?;
    Ok(Manifest {
        file: BufWriter::new(file),
        path: path.to_path_buf(),
    })
}

/// The jobs an earlier run's manifest records as written (the last `ok` record of each name).
/// A missing manifest records none; an unreadable line (a run killed mid-line) is passed over.
pub fn read_manifest(path: &Path) -> Result<HashMap<String, Record>> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(HashMap::new()),
        Err(source) => {
            return Err(Error::Io {
                path: path.display().to_string(),
                source,
            })
        }
    };
    let mut done = HashMap::new();
    for line in text.lines() {
        if let Ok(rec) = serde_json::from_str::<Record>(line) {
            if rec.status == Status::Ok {
                done.insert(rec.job.clone(), rec);
            }
        }
    }
    Ok(done)
}

/// Reads a jobs file, its size checked first.
pub fn read_jobs_file(path: &Path) -> Result<String> {
    let io = |source| Error::Io {
        path: path.display().to_string(),
        source,
    };
    let len = std::fs::metadata(path).map_err(io)?.len();
    if len > MAX_JOBS_BYTES {
        return Err(invalid_arg!(
            "{}: {len} bytes, more than the {MAX_JOBS_BYTES} a jobs file may have",
            path.display()
        ));
    }
    std::fs::read_to_string(path).map_err(io)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_line_becomes_an_entry_and_bad_ones_say_why() {
        let text = "{\"prompt\": \"a\", \"out\": \"a.bvh\"}\n\n{\"prompt\": \"b\",\n\
                    {\"prompt\": \"c\", \"out\": \"c.bvh\", \"sed\": 1}\n[1]\n\
                    {\"id\": \"x\", \"stages\": [\"walk@10\"], \"out\": \"x.npy\", \"seed\": 4}\n";
        let e = parse_jobs(text, None).unwrap();
        assert_eq!(e.len(), 5);
        assert_eq!(e[0].key, "1");
        assert_eq!(e[0].job.as_ref().unwrap().prompt.as_deref(), Some("a"));
        assert_eq!(e[1].line, 3);
        let err = e[1].job.as_ref().unwrap_err();
        assert_eq!(err, "line 3: EOF while parsing a value at column 15");
        let err = e[2].job.as_ref().unwrap_err();
        assert!(err.starts_with("line 4: unknown field `sed`"), "{err}");
        assert_eq!(
            e[3].job.as_ref().unwrap_err(),
            "line 5: a job is a JSON object"
        );
        assert_eq!(e[4].key, "x");
        assert_eq!(e[4].job.as_ref().unwrap().seed, 4);
    }

    #[test]
    fn defaults_fill_what_a_line_leaves_out() {
        let d: serde_json::Map<_, _> = serde_json::from_str("{\"steps\": 3, \"seed\": 9}").unwrap();
        let e = parse_jobs(
            "{\"prompt\": \"a\", \"out\": \"a.bvh\", \"seed\": 1}",
            Some(&d),
        )
        .unwrap();
        let j = e[0].job.as_ref().unwrap();
        assert_eq!((j.steps, j.seed), (Some(3), 1));
    }

    #[test]
    fn prompts_times_seeds_name_their_outputs() {
        let e = jobs_from_prompts(
            "walk\n# no\n\nrun\n",
            2,
            "o/{line}_{seed}.bvh",
            &Job::default(),
        )
        .unwrap();
        let outs: Vec<_> = e
            .iter()
            .map(|e| e.job.as_ref().unwrap().out.clone().unwrap())
            .collect();
        let want = ["o/1_0.bvh", "o/1_1.bvh", "o/4_0.bvh", "o/4_1.bvh"];
        assert_eq!(outs, want.map(PathBuf::from));
        assert_eq!(e[3].key, "4:1");
        assert_eq!(e[3].job.as_ref().unwrap().seed, 1);
        assert!(jobs_from_prompts("a", 0, "x", &Job::default()).is_err());
    }

    #[test]
    fn the_policy_gives_each_core_a_session() {
        assert_eq!(thread_policy(200, 0, 0, 2), (2, 1));
        assert_eq!(thread_policy(1, 0, 0, 8), (1, 8));
        assert_eq!(thread_policy(3, 0, 0, 8), (3, 2));
        assert_eq!(thread_policy(200, 1, 0, 4), (1, 4));
        assert_eq!(thread_policy(200, 0, 3, 2), (2, 3));
        assert_eq!(
            thread_policy(10_000, 1 << 30, 1, 2).0,
            crate::pool::MAX_THREADS
        );
    }

    #[test]
    fn outputs_appear_whole_or_not_at_all() {
        let d = std::env::temp_dir().join(format!("flame_batch_write_{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        let files = vec![
            (d.join("a.bin"), vec![1u8, 2]),
            (d.join("missing/b.bin"), vec![3u8]),
        ];
        assert!(write_files(&files).unwrap_err().contains("missing/b.bin"));
        assert_eq!(
            std::fs::read_dir(&d).unwrap().count(),
            0,
            "a.bin's temporary removed"
        );
        write_files(&files[..1]).unwrap();
        assert_eq!(std::fs::read(d.join("a.bin")).unwrap(), [1, 2]);
        let names: Vec<_> = std::fs::read_dir(&d).unwrap().collect();
        assert_eq!(names.len(), 1, "no temporary file left");
        std::fs::remove_dir_all(&d).unwrap();
    }
}
