//! FineMoGen through the session: prompts per stage and part (errors, determinism, other
//! families' answer), and masks with the MDM algorithm (replace-x0) on its x0 prediction.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use flame::models::Model;
use flame::motion::{Format, Mask};
use flame::session::{EditMethod, EditParams, Session, SessionParams, Which};
use flame::stages::{BodyPart, Stage};
use flame::Error;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn load(name: &str) -> Arc<Model> {
    Arc::new(Model::load(fixture(name)).unwrap())
}

fn session(m: &Arc<Model>, frames: usize, steps: usize, threads: usize) -> Session {
    let params = SessionParams {
        frames: Some(frames),
        steps: Some(steps),
        seed: 3,
        threads,
        ..Default::default()
    };
    Session::new(Arc::clone(m), &params).unwrap()
}

fn invalid(r: flame::Result<()>, want: &str) {
    match r {
        Err(Error::InvalidArgument(m)) => assert!(m.contains(want), "{m:?} lacks {want:?}"),
        other => panic!("expected InvalidArgument({want:?}), got {other:?}"),
    }
}

#[test]
fn bad_stages_are_refused_with_a_message() {
    let m = load("finemogen_tiny.safetensors");
    let mut s = session(&m, 60, 3, 1);
    invalid(s.set_prompt_stages(&[]), "no stages");
    invalid(
        s.set_prompt_stages(&[Stage::new("walk", 0), Stage::new("jump", 60)]),
        "stage 0 has 0 frames",
    );
    invalid(
        s.set_prompt_stages(&[Stage::new("walk", 30), Stage::new("jump", 20)]),
        "cover 50 frames, the session has 60",
    );
    invalid(
        s.set_prompt_stages(&[Stage::new("walk", 30), Stage::new("  ", 30)]),
        "stage 1 has no text",
    );
    // 196 frames per stage at most (the position table), also for a plain prompt.
    let mut long = session(&m, 400, 3, 1);
    invalid(
        long.set_prompt_stages(&[Stage::new("walk", 200), Stage::new("jump", 200)]),
        "stage 0 has 200 frames: a FineMoGen stage has 1 to 196",
    );
    invalid(
        long.set_prompt("walk"),
        "400 frames for one prompt: FineMoGen generates at most 196",
    );
    long.set_prompt_stages(&[
        Stage::new("walk", 196),
        Stage::new("jump", 196),
        Stage::new("sit", 8),
    ])
    .unwrap();
    assert_eq!(long.sample_rows(), 3 * 196);
    // NaN noise.
    let mut s = session(&m, 60, 3, 1);
    s.set_prompt_stages(&[Stage::new("walk", 30), Stage::new("jump", 30)])
        .unwrap();
    let mut noise = vec![0.5; 2 * 30 * 263];
    noise[17] = f32::NAN;
    invalid(s.set_initial_noise(&noise), "NaN");
    invalid(
        s.set_initial_noise(&vec![0.5; 60 * 200]),
        "expected 15780 (2 stages × 30 frames (the longest) × 263)",
    );
}

#[test]
fn stage_lengths_change_only_before_the_first_step_and_block_edits() {
    let m = load("finemogen_tiny.safetensors");
    let mut s = session(&m, 50, 3, 1);
    s.set_prompt_stages(&[Stage::new("walk", 20), Stage::new("jump", 30)])
        .unwrap();
    assert_eq!(s.sample_rows(), 60);
    s.step().unwrap();
    // New texts, same lengths: allowed between steps.
    s.set_prompt_stages(&[Stage::new("run", 20), Stage::new("sit", 30)])
        .unwrap();
    // The same rows (2 × 30) in another order are other stages too.
    match s.set_prompt_stages(&[Stage::new("walk", 30), Stage::new("jump", 20)]) {
        Err(Error::WrongState(m)) => assert!(m.contains("reset first"), "{m}"),
        other => panic!("{other:?}"),
    }
    match s.set_prompt_stages(&[Stage::new("walk", 25), Stage::new("jump", 25)]) {
        Err(Error::WrongState(m)) => assert!(m.contains("reset first"), "{m}"),
        other => panic!("{other:?}"),
    }
    match s.set_prompt("walk") {
        Err(Error::WrongState(_)) => {}
        other => panic!("{other:?}"),
    }
    invalid(s.set_mask(&vec![0; 50 * 263]), "several time stages");
    s.reset();
    s.set_prompt("walk").unwrap();
    assert_eq!(s.sample_rows(), 50);
    s.run().unwrap();
    assert_eq!(s.motion(Which::Sample).unwrap().1, 50);
}

#[test]
fn staged_generation_is_deterministic_for_any_thread_count() {
    let m = load("finemogen_tiny.safetensors");
    let stages = [
        Stage::new("a person walks", 17),
        Stage::new("a person jumps", 23).with_part(BodyPart::RightArm, "raises the right arm"),
        Stage::new("a person sits down", 12),
    ];
    let run = |threads| {
        let mut s = session(&m, 52, 5, threads);
        s.set_prompt_stages(&stages).unwrap();
        s.run().unwrap();
        let (x, frames) = s.motion(Which::Sample).unwrap();
        assert_eq!(frames, 52);
        x.to_vec()
    };
    let one = run(1);
    assert!(one.iter().all(|v| v.is_finite()));
    // 2 and 3 threads split each mixture's experts, and SFFN's part FFNs, into as many ranges.
    for threads in [2, 3] {
        let other = run(threads);
        assert!(
            one.iter()
                .zip(&other)
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "{threads} threads"
        );
    }
    // The paper's editing: change one stage's text, regenerate from the same seed.
    let mut edited = stages.clone();
    edited[1].text = "a person kicks".into();
    let mut s = session(&m, 52, 5, 2);
    s.set_prompt_stages(&edited).unwrap();
    s.run().unwrap();
    let (x, _) = s.motion(Which::Sample).unwrap();
    let changed = (0..52).filter(|&f| x[f * 263..(f + 1) * 263] != one[f * 263..(f + 1) * 263]);
    assert!(changed.clone().any(|f| (17..40).contains(&f)));
}

#[test]
fn other_families_take_one_stage_as_a_plain_prompt() {
    let m = load("mdm_tiny.safetensors");
    let mut a = session(&m, 30, 3, 1);
    a.set_prompt("a person walks").unwrap();
    let plain = a.run().unwrap().to_vec();
    let mut b = session(&m, 30, 3, 1);
    b.set_prompt_stages(&[Stage::new("a person walks", 30)])
        .unwrap();
    assert_eq!(plain, b.run().unwrap());
    invalid(
        b.set_prompt_stages(&[Stage::new("walk", 10), Stage::new("jump", 20)]),
        "this mdm model takes one prompt per generation",
    );
    invalid(
        b.set_prompt_stages(&[Stage::new("walk", 30).with_part(BodyPart::Head, "nods")]),
        "prompts per time stage and body part are FineMoGen's",
    );
}

#[test]
fn masks_run_the_mdm_algorithm_on_finemogen() {
    // Replace-x0: x̂0 takes the reference's kept values at every step, and DDIM's last step
    // returns x̂0 (ᾱ_prev = 1), so the kept values come out exactly even without the paste.
    let m = load("finemogen_tiny.safetensors");
    let frames = 40;
    let reference: Vec<f32> = (0..frames * 263)
        .map(|i| ((i * 37 % 101) as f32 / 50.0 - 1.0) * 0.8)
        .collect();
    let mut mask = Mask::new(Format::HumanMl263, frames).unwrap();
    mask.keep_frames(0, 12).unwrap();
    let run = |edit: bool| {
        let mut s = session(&m, frames, 6, 2);
        s.set_prompt("a person walks").unwrap();
        if edit {
            s.set_reference(&reference).unwrap();
            s.set_mask_from(&mask).unwrap();
            s.set_edit_params(&EditParams {
                method: EditMethod::Auto,
                paste: false,
                ..Default::default()
            })
            .unwrap();
            assert_eq!(
                s.resolve_method(EditMethod::Auto).unwrap(),
                EditMethod::ReplaceX0
            );
        }
        s.run().unwrap().to_vec()
    };
    let plain = run(false);
    let edited = run(true);
    let kept = 12 * 263;
    assert_eq!(&edited[..kept], &reference[..kept]);
    assert_ne!(&plain[..kept], &reference[..kept]);
    // The generated frames follow the kept ones (the network saw them at every step).
    assert!(edited[kept..] != plain[kept..]);
}
