//! The demo model understands sentences it was not trained on: each held-out prompt of
//! tests/fixtures/demo_eval_prompts.tsv (new wording and synonyms, none among the corpus's
//! sentences, see crates/flame-demo/tests/demo_corpus.rs) is generated with 3 seeds at the model's defaults, as
//! `flame generate` would, and the motion is labelled by the rule-based classifier of
//! `flame_demo::classify`; at least 80% must be the intended family. Prints the confusion table
//! (`cargo test -p flame-demo --test demo_eval -- --nocapture`).
//!
//! The model: `$FLAME_DEMO_MODEL`, else models/demo/flame_demo.safetensors when assembled, else
//! the committed denoiser assembled here with `$FLAME_MINILM_DIR`. Skipped without any of them
//! unless FLAME_REQUIRE_REAL_WEIGHTS=1.
//!
//! The shipped model (docs/demo_training.md, phase 3) measures 92.7% (139 of 150) here.
//! Settings are tuned on corpus sentences, never on these prompts: `FLAME_DEMO_EVAL_PROMPTS`
//! (a family<TAB>prompt file), `FLAME_DEMO_EVAL_GUIDANCE` and `FLAME_DEMO_EVAL_STEPS` override
//! the prompts and the model's defaults for such runs, `FLAME_DEMO_EVAL_FRAMES` the length,
//! `FLAME_DEMO_EVAL_WEIGHTS` the weight type the model is loaded as.

use std::path::PathBuf;
use std::sync::Arc;

// The repository's test helpers (tests/common), shared with the runtime's tests.
#[path = "../../../tests/common/mod.rs"]
mod common;

use common::{demo_model, repo};
use flame::models::{LoadOptions, Model};
use flame::motion::{Convention, Poses};
use flame::session::{Session, SessionParams};
use flame_demo::classify::{self, Features};
use flame_demo::{Confusion, Family};

const SEEDS: [u64; 3] = [0, 1, 2];
/// What the issue asks of a demo model (the shipped one measures 0.927).
const TARGET_ACCURACY: f64 = 0.80;

fn prompts() -> Vec<(Family, String)> {
    let path = std::env::var_os("FLAME_DEMO_EVAL_PROMPTS").map_or_else(
        || repo("tests/fixtures/demo_eval_prompts.tsv"),
        PathBuf::from,
    );
    let text = std::fs::read_to_string(path).unwrap();
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let (family, prompt) = l.split_once('\t').expect("family<TAB>prompt");
            let family = Family::from_name(family).unwrap_or_else(|| panic!("family {family}"));
            (family, prompt.to_string())
        })
        .collect()
}

/// What `flame generate --prompt P --seed S` produces, labelled, with the measurements the
/// label was decided on.
fn generate_and_classify(model: &Arc<Model>, prompt: &str, seed: u64) -> (Family, Features) {
    let env = |name: &str| std::env::var(name).ok().map(|v| v.parse().unwrap());
    let params = SessionParams {
        seed,
        guidance: env("FLAME_DEMO_EVAL_GUIDANCE"),
        steps: env("FLAME_DEMO_EVAL_STEPS").map(|s: f32| s as usize),
        frames: env("FLAME_DEMO_EVAL_FRAMES").map(|s: f32| s as usize),
        ..SessionParams::default()
    };
    let mut session = Session::new(Arc::clone(model), &params).unwrap();
    session.set_prompt(prompt).unwrap();
    let frames = session.frames();
    let x = session.run().unwrap().to_vec();
    // The CLI's pose defaults for smpl24_6d: sigma-1 smoothing, continuous rotations.
    let poses = Poses::decode(
        model.motion_format(),
        &x,
        frames,
        &model.read_options(1.0, true),
    )
    .unwrap();
    let fps = model.config().motion.fps as f64;
    let features = classify::features(&poses.positions(Convention::Native), frames, fps);
    (classify::decide(&features), features)
}

#[test]
fn held_out_prompts_are_classified_as_intended() {
    let Some(path) = demo_model() else {
        common::skip(
            "demo_eval::held_out_prompts_are_classified_as_intended",
            "no demo model (set FLAME_MINILM_DIR or run tools/try.sh to assemble it)",
        );
        return;
    };
    // FLAME_DEMO_EVAL_WEIGHTS (f32, f16, bf16, bf16-compute, int8) measures a weight type
    // (docs/performance.md's accuracy table).
    let weights = std::env::var("FLAME_DEMO_EVAL_WEIGHTS")
        .map(|w| w.parse().unwrap())
        .unwrap_or_default();
    let model = Arc::new(Model::load_with(&path, &LoadOptions { weights }).unwrap());
    let prompts = prompts();
    assert!(prompts.len() >= 40, "{} prompts", prompts.len());
    let mut confusion = Confusion::default();
    let mut misses = Vec::new();
    for (family, prompt) in &prompts {
        for seed in SEEDS {
            let (got, f) = generate_and_classify(&model, prompt, seed);
            confusion.add(*family, got);
            if got != *family {
                misses.push(format!(
                    "  {prompt:?} seed {seed}: {}\n    {f:.2?}",
                    got.name()
                ));
            }
        }
    }
    println!("{}", confusion.table());
    println!(
        "{} prompts x {} seeds: {:.1}% classified as intended ({} of {})",
        prompts.len(),
        SEEDS.len(),
        100.0 * confusion.accuracy(),
        confusion.correct(),
        confusion.total()
    );
    println!("misses:\n{}", misses.join("\n"));
    assert!(
        confusion.accuracy() >= TARGET_ACCURACY,
        "accuracy {:.1}% < {:.0}%",
        100.0 * confusion.accuracy(),
        100.0 * TARGET_ACCURACY
    );
}
