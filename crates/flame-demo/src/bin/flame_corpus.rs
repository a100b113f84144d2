//! `flame-corpus`: writes the procedural demo corpus and classifies motions (see `flame_demo`).
//!
//! - `flame-corpus generate --out DIR [--count 4000] [--seed 0]`
//! - `flame-corpus classify FILE.npy` — prints the family (and the measured features with `-v`)
//!   of de-normalised `[frames, 147]` smpl24_6d features (the corpus's files) or of
//!   `[frames, 24, 3]` joint positions in the native convention (`flame generate --positions`)
//! - `flame-corpus check DIR` — classifies a written corpus; prints the confusion table and the
//!   accuracy (two-action motions: each part, split at `split_frame`, must be right)

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

use flame_demo::{classify, corpus, Confusion, Family};

const USAGE: &str = "usage: flame-corpus generate --out DIR [--count N] [--seed S]
       flame-corpus classify [-v] FEATURES.npy|POSITIONS.npy
       flame-corpus check DIR";

fn value<T: std::str::FromStr>(args: &[String], key: &str, default: T) -> Result<T, String> {
    match args.iter().position(|a| a == key) {
        Some(i) => args
            .get(i + 1)
            .and_then(|v| v.parse().ok())
            .ok_or_else(|| format!("{key} needs a valid value")),
        None => Ok(default),
    }
}

fn generate(args: &[String]) -> Result<(), String> {
    let out: String = value(args, "--out", String::new())?;
    if out.is_empty() {
        return Err("generate needs --out DIR".into());
    }
    let count: usize = value(args, "--count", 4000)?;
    let seed: u64 = value(args, "--seed", 0)?;
    let t = Instant::now();
    let motions = corpus::generate(count, seed);
    let generated = t.elapsed().as_secs_f64();
    corpus::write(Path::new(&out), &motions, seed).map_err(|e| e.to_string())?;
    let frames: usize = motions.iter().map(|m| m.frames).sum();
    println!(
        "wrote {count} motions ({frames} frames, seed {seed}) to {out}: generated in {generated:.2} s, written in {:.2} s",
        t.elapsed().as_secs_f64() - generated
    );
    Ok(())
}

fn load(path: &Path) -> Result<(Vec<f32>, usize), String> {
    let (shape, data) = flame::npy::read_f32(path).map_err(|e| e.to_string())?;
    if shape.len() != 2 || shape[1] != 147 {
        return Err(format!(
            "{}: expected [frames, 147] smpl24_6d features, got {shape:?}",
            path.display()
        ));
    }
    Ok((data, shape[0]))
}

fn classify_file(args: &[String]) -> Result<(), String> {
    let verbose = args.iter().any(|a| a == "-v");
    let file = args
        .iter()
        .find(|a| !a.starts_with('-'))
        .ok_or("classify needs FILE.npy")?;
    let path = Path::new(file);
    let (shape, data) = flame::npy::read_f32(path).map_err(|e| e.to_string())?;
    // `flame generate --out x.npy` writes the model's normalised features, which only the
    // model can decode; its `--positions` file is what this reads for generated motions.
    let (positions, frames) = match shape[..] {
        [frames, 147] => (
            classify::positions_of(&data, frames).map_err(|e| e.to_string())?,
            frames,
        ),
        [frames, 24, 3] => (
            data.chunks_exact(3)
                .map(|p| [p[0] as f64, p[1] as f64, p[2] as f64])
                .collect(),
            frames,
        ),
        _ => {
            return Err(format!(
                "{}: expected [frames, 147] smpl24_6d features or [frames, 24, 3] joint \
                 positions (flame generate --positions), got {shape:?}",
                path.display()
            ))
        }
    };
    if frames < 2 {
        return Err(format!(
            "{}: {frames} frame(s), need at least 2",
            path.display()
        ));
    }
    let f = classify::features(&positions, frames, flame_demo::rig::FPS);
    println!("{}", classify::decide(&f));
    if verbose {
        eprintln!("{f:#?}");
    }
    Ok(())
}

/// Classifies the frames `range` of a motion.
fn part(positions: &[[f64; 3]], range: std::ops::Range<usize>) -> Family {
    let j = flame_demo::rig::joint::JOINTS;
    classify::classify(
        &positions[range.start * j..range.end * j],
        range.len(),
        flame_demo::rig::FPS,
    )
}

fn check(args: &[String]) -> Result<(), String> {
    let dir = PathBuf::from(args.first().ok_or("check needs DIR")?);
    let entries = corpus::read_entries(&dir).map_err(|e| e.to_string())?;
    let mut confusion = Confusion::default();
    let (mut right, mut total) = (0, 0);
    let mut wrong = Vec::new();
    for e in &entries {
        let (data, frames) = load(&dir.join(&e.file))?;
        let positions = classify::positions_of(&data, frames).map_err(|e| e.to_string())?;
        // Two-action motions: each part on its own side of the split.
        let cut = e
            .split_frame
            .filter(|_| e.actions.len() == 2)
            .unwrap_or(frames);
        let parts = [0..cut, cut..frames];
        let mut ok = true;
        for (range, &want) in parts.into_iter().zip(&e.actions) {
            let got = part(&positions, range);
            confusion.add(want, got);
            ok &= got == want;
        }
        total += 1;
        if ok {
            right += 1;
        } else {
            wrong.push(e.id.clone());
        }
    }
    print!("{}", confusion.table());
    println!(
        "parts: {}/{} = {:.2}%  motions: {right}/{total} = {:.2}%",
        confusion.correct(),
        confusion.total(),
        100.0 * confusion.accuracy(),
        100.0 * right as f64 / total.max(1) as f64
    );
    if !wrong.is_empty() {
        let shown: Vec<&str> = wrong.iter().take(20).map(String::as_str).collect();
        println!("misclassified: {}", shown.join(" "));
    }
    Ok(())
}

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result = match args.first().map(String::as_str) {
        Some("generate") => generate(&args[1..]),
        Some("classify") => classify_file(&args[1..]),
        Some("check") => check(&args[1..]),
        _ => Err(USAGE.to_string()),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("flame-corpus: {e}");
            ExitCode::from(2)
        }
    }
}
