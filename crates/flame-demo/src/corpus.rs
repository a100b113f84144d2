//! The demo corpus: seeded generation of whole motions (one action, or two in sequence, with a
//! short standing lead-in and tail), their descriptions, and the on-disk layout the training
//! script reads (`motions/<id>.npy`, `corpus.jsonl`, `summary.json`; see `docs/demo_corpus.md`).
//!
//! Motion `i` of a corpus depends only on `(seed, i)`, so a corpus of 600 is the first 600
//! motions of a corpus of 4000 with the same seed, and motions are generated in parallel.

use std::collections::BTreeMap;
use std::path::Path;

use rayon::prelude::*;
use serde::Serialize;

use super::actions::{self, Detail, Dice, Place};
use super::family::Family;
use super::rig::{Pose, Rig, FPS};
use super::sentences;
use flame::error::{Error, Result};

/// Written into `summary.json`; bump when the same seed would give different motions.
pub const GENERATOR_VERSION: &str = "flame-demo-corpus/1";
/// Shortest and longest motion, frames (2 s and 10 s at 20 fps).
pub const MIN_FRAMES: usize = 40;
pub const MAX_FRAMES: usize = 200;
/// Fraction of motions that chain two actions.
const SEQUENCE_SHARE: f64 = 0.2;
/// Fewest sentences per motion.
pub const MIN_TEXTS: usize = 6;

/// One generated motion with its metadata.
#[derive(Clone, Debug)]
pub struct CorpusMotion {
    /// Zero-padded index, e.g. `000123`.
    pub id: String,
    pub frames: usize,
    /// `[frames × 147]` `smpl24_6d` features, unnormalised.
    pub features: Vec<f32>,
    /// The first action's family.
    pub family: Family,
    pub actions: Vec<Family>,
    /// Variant names of the actions joined by `+`.
    pub variant: String,
    /// First frame of the second action, for two-action motions.
    pub split_frame: Option<usize>,
    pub texts: Vec<String>,
    pub details: Vec<Detail>,
}

/// A corpus line of `corpus.jsonl`, in the field order of the contract.
#[derive(Serialize)]
struct Line<'a> {
    id: &'a str,
    file: String,
    frames: usize,
    family: &'a str,
    actions: Vec<&'a str>,
    variant: &'a str,
    split_frame: Option<usize>,
    texts: &'a [String],
}

/// The per-motion generator seed: nearby `(seed, index)` pairs give unrelated streams.
fn motion_seed(seed: u64, index: usize) -> u64 {
    seed.wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (index as u64)
            .wrapping_add(1)
            .wrapping_mul(0xD1B5_4A32_D192_ED03)
}

/// Draws a family: walking has the most variants, so it comes up half again as often.
fn pick_family(d: &mut Dice, except: Option<Family>) -> Family {
    loop {
        let x = d.range(0.0, Family::ALL.len() as f64 + 0.5);
        let f = if x >= Family::ALL.len() as f64 {
            Family::Walk
        } else {
            Family::ALL[x as usize]
        };
        if Some(f) != except {
            return f;
        }
    }
}

/// `count` motions from `seed` (deterministic, parallel).
pub fn generate(count: usize, seed: u64) -> Vec<CorpusMotion> {
    (0..count)
        .into_par_iter()
        .map(|i| generate_one(i, seed))
        .collect()
}

/// Motion `index` of the corpus with `seed`.
pub fn generate_one(index: usize, seed: u64) -> CorpusMotion {
    let mut d = Dice::new(motion_seed(seed, index));
    let rig = Rig::get();
    let two = d.chance(SEQUENCE_SHARE);
    let lead = d.range(0.0, 0.4);
    let tail = d.range(0.1, 0.4);
    let origin = Place {
        x: 0.0,
        z: 0.0,
        yaw: 0.0,
    };
    let first = pick_family(&mut d, None);
    let budget = if two { 4.4 } else { 9.4 - lead - tail };
    let a = actions::generate(first, &mut d, origin, budget);
    let mut poses: Vec<Pose> = vec![rig.stand(0.0, 0.0, 0.0); (lead * FPS).round() as usize];
    poses.extend_from_slice(&a.poses);
    let mut details = vec![a.detail];
    let mut split_frame = None;
    let mut end = a.end;
    if two {
        let second = pick_family(&mut d, Some(first));
        let used = poses.len() as f64 / FPS;
        let budget = (9.5 - used - tail).clamp(1.5, 5.0);
        let b = actions::generate(second, &mut d, a.end, budget);
        // Both clips hold the neutral stance at the join; drop the repeated frame.
        split_frame = Some(poses.len());
        poses.extend_from_slice(&b.poses[1..]);
        details.push(b.detail);
        end = b.end;
    }
    let hold = rig.stand(end.x, end.z, end.yaw);
    let tail_frames = ((tail * FPS).round() as usize).max(MIN_FRAMES.saturating_sub(poses.len()));
    poses.extend(std::iter::repeat_n(hold, tail_frames));
    poses.truncate(MAX_FRAMES);
    actions::fit_pelvis_height(&mut poses);
    let texts = sentences::describe(&details, &mut d, MIN_TEXTS);
    let family = details[0].family;
    CorpusMotion {
        id: format!("{index:06}"),
        frames: poses.len(),
        features: rig.encode(&poses),
        family,
        actions: details.iter().map(|x| x.family).collect(),
        variant: details
            .iter()
            .map(|x| x.variant.as_str())
            .collect::<Vec<_>>()
            .join("+"),
        split_frame,
        texts,
        details,
    }
}

fn io_err(path: &Path, source: std::io::Error) -> Error {
    Error::Io {
        path: path.display().to_string(),
        source,
    }
}

/// Writes `motions/<id>.npy`, `corpus.jsonl` and `summary.json` under `dir`.
pub fn write(dir: &Path, motions: &[CorpusMotion], seed: u64) -> Result<()> {
    let mdir = dir.join("motions");
    std::fs::create_dir_all(&mdir).map_err(|e| io_err(&mdir, e))?;
    motions.par_iter().try_for_each(|m| {
        flame::npy::write_f32(
            &mdir.join(format!("{}.npy", m.id)),
            &[m.frames, 147],
            &m.features,
        )
    })?;
    let mut jsonl = String::new();
    for m in motions {
        let line = Line {
            id: &m.id,
            file: format!("motions/{}.npy", m.id),
            frames: m.frames,
            family: m.family.name(),
            actions: m.actions.iter().map(|f| f.name()).collect(),
            variant: &m.variant,
            split_frame: m.split_frame,
            texts: &m.texts,
        };
        jsonl.push_str(&serde_json::to_string(&line).expect("corpus line serialises"));
        jsonl.push('\n');
    }
    let path = dir.join("corpus.jsonl");
    std::fs::write(&path, jsonl).map_err(|e| io_err(&path, e))?;
    let mut per_family: BTreeMap<&str, usize> = Family::ALL.iter().map(|f| (f.name(), 0)).collect();
    for m in motions {
        *per_family.entry(m.family.name()).or_default() += 1;
    }
    let sequences = motions.iter().filter(|m| m.actions.len() > 1).count();
    let frames: usize = motions.iter().map(|m| m.frames).sum();
    let summary = serde_json::json!({
        "generator_version": GENERATOR_VERSION,
        "seed": seed,
        "count": motions.len(),
        "fps": FPS,
        "format": "smpl24_6d",
        "two_action_motions": sequences,
        "total_frames": frames,
        "families": per_family,
    });
    let path = dir.join("summary.json");
    let text = serde_json::to_string_pretty(&summary).expect("summary serialises");
    std::fs::write(&path, text + "\n").map_err(|e| io_err(&path, e))
}

/// One corpus line read back: the metadata `check` needs.
#[derive(Clone, Debug)]
pub struct Entry {
    pub id: String,
    pub file: String,
    pub frames: usize,
    pub actions: Vec<Family>,
    pub split_frame: Option<usize>,
    pub texts: Vec<String>,
}

/// Reads `corpus.jsonl` under `dir`.
pub fn read_entries(dir: &Path) -> Result<Vec<Entry>> {
    let path = dir.join("corpus.jsonl");
    let text = std::fs::read_to_string(&path).map_err(|e| io_err(&path, e))?;
    let bad = |n: usize, what: &str| {
        flame::error::Error::InvalidArgument(format!("{} line {}: {what}", path.display(), n + 1))
    };
    let mut out = Vec::new();
    for (n, line) in text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
    {
        let v: serde_json::Value =
            serde_json::from_str(line).map_err(|e| bad(n, &e.to_string()))?;
        let s = |k: &str| v[k].as_str().map(str::to_string).ok_or_else(|| bad(n, k));
        let actions = v["actions"]
            .as_array()
            .ok_or_else(|| bad(n, "actions"))?
            .iter()
            .map(|a| {
                a.as_str()
                    .and_then(Family::from_name)
                    .ok_or_else(|| bad(n, "actions"))
            })
            .collect::<Result<Vec<_>>>()?;
        out.push(Entry {
            id: s("id")?,
            file: s("file")?,
            frames: v["frames"].as_u64().ok_or_else(|| bad(n, "frames"))? as usize,
            actions,
            split_frame: v["split_frame"].as_u64().map(|x| x as usize),
            texts: v["texts"]
                .as_array()
                .ok_or_else(|| bad(n, "texts"))?
                .iter()
                .filter_map(|t| t.as_str().map(str::to_string))
                .collect(),
        });
    }
    Ok(out)
}
