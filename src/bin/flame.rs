//! The `flame` command line: generate a motion from a sentence, or describe a model file.

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

use flame::models::Model;
use flame::session::{Session, SessionParams};

const USAGE: &str = "\
usage:
  flame generate --model M --prompt TEXT [--frames N] [--steps S] [--sampler ddpm|ddim]
                 [--eta E] [--guidance G] [--seed K] [--noise FILE.npy] [--threads T]
                 --out FILE.npy
  flame info M

generate writes raw features, float32, frames x feature_dim. Unset options take the model
file's defaults (see `flame info`).";

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
        let key = a.strip_prefix("--").ok_or_else(|| format!("unexpected argument `{a}`"))?;
        if !known.contains(&key) {
            return Err(format!("unknown option `--{key}`"));
        }
        let value = it.next().ok_or_else(|| format!("option `--{key}` needs a value"))?;
        if out.insert(key.to_string(), value.clone()).is_some() {
            return Err(format!("option `--{key}` given twice"));
        }
    }
    Ok(out)
}

fn parsed<T: std::str::FromStr>(flags: &HashMap<String, String>, key: &str) -> Result<Option<T>, String> {
    flags
        .get(key)
        .map(|v| v.parse::<T>().map_err(|_| format!("option `--{key}`: cannot parse `{v}`")))
        .transpose()
}

fn generate(args: &[String]) -> Result<(), String> {
    let flags = parse_flags(
        args,
        &["model", "prompt", "frames", "steps", "sampler", "eta", "guidance", "seed", "noise", "threads", "out"],
    )?;
    let model_path = flags.get("model").ok_or("generate needs `--model M`")?;
    let prompt = flags.get("prompt").ok_or("generate needs `--prompt TEXT`")?;
    let out = PathBuf::from(flags.get("out").ok_or("generate needs `--out FILE.npy`")?);
    if out.extension().and_then(|e| e.to_str()) != Some("npy") {
        return Err(format!("cannot write {}: only .npy output is supported", out.display()));
    }
    let params = SessionParams {
        frames: parsed(&flags, "frames")?,
        steps: parsed(&flags, "steps")?,
        sampler: parsed(&flags, "sampler")?,
        eta: parsed(&flags, "eta")?,
        guidance: parsed(&flags, "guidance")?,
        seed: parsed(&flags, "seed")?.unwrap_or(0),
        threads: parsed(&flags, "threads")?.unwrap_or(0),
    };

    let t0 = Instant::now();
    let model = Arc::new(Model::load(model_path).map_err(|e| format!("cannot load {model_path}: {e}"))?);
    eprintln!("loaded {model_path} in {:.0} ms", t0.elapsed().as_secs_f64() * 1e3);
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
    eprintln!("{n} steps in {:.2} s ({:.1} ms/step)", elapsed, elapsed * 1e3 / n as f64);
    let x = session.sample().expect("finished generation has a sample");
    flame::npy::write_f32(&out, &[session.frames(), model.motion_dim()], x).map_err(|e| e.to_string())?;
    println!("{}", out.display());
    Ok(())
}

fn info(args: &[String]) -> Result<(), String> {
    let [path] = args else {
        return Err("info takes one model file".into());
    };
    let model = Model::load(path).map_err(|e| format!("cannot load {path}: {e}"))?;
    let c = model.config();
    let d = &c.denoiser;
    let t = &c.text_encoder;
    println!("architecture:   {}", c.architecture);
    println!(
        "denoiser:       {} layers, {} wide, {} heads, feed-forward {}, {} activation",
        d.num_layers, d.model_channels, d.num_heads, d.dim_feedforward, d.activation
    );
    println!(
        "text encoder:   {} ({} layers, {} wide, {} heads, vocab {}, max {} tokens)",
        t.kind, t.num_layers, t.hidden_size, t.num_heads, t.vocab_size, t.max_length
    );
    println!("weights dtype:  {}", model.stored_dtype().map_or("-", |x| x.name()));
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
