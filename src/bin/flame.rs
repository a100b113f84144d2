//! The `flame` command line: generate a motion from a sentence, or describe a model file.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

use flame::config::{DenoiserConfig, TextConfig};
use flame::models::Model;
use flame::motion::{self, Convention, Format, Layout, Poses, QuatOrder};
use flame::session::{Session, SessionParams};

const USAGE: &str = "\
usage:
  flame generate --model M --prompt TEXT [--frames N] [--steps S] [--sampler ddpm|ddim|euler|heun|midpoint]
                 [--eta E] [--guidance G] [--seed K] [--noise FILE.npy] [--threads T]
                 --out FILE.npy|FILE.bvh|FILE.json
                 [--convention native|unity|unreal|ros|blender|gltf] [--smooth SIGMA]
                 [--quat xyzw|wxyz] [--positions FILE.npy]
  flame info M

generate picks the writer by the extension of --out: .npy = raw features (float32, frames x
feature_dim, untouched by the pose options), .bvh = BVH (Euler ZXY, degrees), .json = root
translation + local quaternions (--quat order, default wxyz as FLAME's official output) with
the skeleton. --positions also writes world joint positions (float32, frames x joints x 3).
Poses are in --convention (default native); --smooth is the sigma in frames of the temporal
Gaussian smoothing of the features (default 1 for smpl24_6d as FLAME's official output, 0
otherwise; 0 = off). For Blender's BVH importer write the BVH with --convention gltf. Unset
options take the model file's defaults (see `flame info`).";

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result = match args.first().map(String::as_str) {
        Some("generate") => generate(&args[1..]),
        Some("info") => info(&args[1..]),
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

fn generate(args: &[String]) -> Result<(), String> {
    let flags = parse_flags(
        args,
        &[
            "model",
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
        ],
    )?;
    let model_path = flags.get("model").ok_or("generate needs `--model M`")?;
    let prompt = flags
        .get("prompt")
        .ok_or("generate needs `--prompt TEXT`")?;
    let outputs = Outputs::from_flags(&flags)?;
    let params = SessionParams {
        frames: parsed(&flags, "frames")?,
        steps: parsed(&flags, "steps")?,
        sampler: parsed(&flags, "sampler")?,
        eta: parsed(&flags, "eta")?,
        guidance: parsed(&flags, "guidance")?,
        clip_denoised: None,
        seed: parsed(&flags, "seed")?.unwrap_or(0),
        threads: parsed(&flags, "threads")?.unwrap_or(0),
    };

    let t0 = Instant::now();
    let model =
        Arc::new(Model::load(model_path).map_err(|e| format!("cannot load {model_path}: {e}"))?);
    eprintln!(
        "loaded {model_path} in {:.0} ms",
        t0.elapsed().as_secs_f64() * 1e3
    );
    // Check the pose side before spending minutes on sampling.
    let decoder = outputs.decoder(&model);
    let mut session = Session::new(Arc::clone(&model), &params).map_err(|e| e.to_string())?;
    if let Some(noise) = flags.get("noise") {
        let (_, x) = flame::npy::read_f32(Path::new(noise)).map_err(|e| e.to_string())?;
        session.set_initial_noise(&x).map_err(|e| e.to_string())?;
    }
    session.set_prompt(prompt).map_err(|e| e.to_string())?;
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
    let x = session.sample().expect("finished generation has a sample");
    outputs.write(x, session.frames(), &model, decoder.as_ref())
}

/// What `generate` writes, from `--out`, `--positions` and the pose options.
struct Outputs {
    out: PathBuf,
    kind: OutKind,
    positions: Option<PathBuf>,
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
                .ok_or("generate needs `--out FILE.npy|FILE.bvh|FILE.json`")?,
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
            convention,
            smooth,
            quat,
        })
    }

    /// The decoder for `model`, or `None` when only raw features are written. The model has
    /// already checked its motion format and loaded any normalisation statistics.
    fn decoder(&self, model: &Model) -> Option<Decoder> {
        if self.kind == OutKind::Features && self.positions.is_none() {
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
        Ok(())
    }
}

fn info(args: &[String]) -> Result<(), String> {
    let [path] = args else {
        return Err("info takes one model file".into());
    };
    let model = Model::load(path).map_err(|e| format!("cannot load {path}: {e}"))?;
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
