//! Editing through the session API: masks that change between steps, the final paste, shorter
//! references, method/model compatibility and bad masks, on the tiny FLAME, MDM and Motion Flow
//! Matching fixture models. (Step-by-step parity of each editing loop with the PyTorch
//! reference is tests/edit_parity.rs.)

use std::path::{Path, PathBuf};
use std::sync::Arc;

use flame::checkpoint::ModelFile;
use flame::models::{Condition, Model};
use flame::session::{EditMethod, EditParams, Sampler, Session, SessionParams};
use flame::Error;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

fn mdm_text() -> Vec<f32> {
    let f = ModelFile::open(&fixture("mdm_expected.safetensors")).unwrap();
    f.tensor_any_shape("text").unwrap().data().to_vec()
}

#[derive(Clone, Copy, PartialEq, Debug)]
enum Family {
    Flame,
    Mdm,
    Flow,
}

const FRAMES: usize = 12;

fn session(family: Family, seed: u64) -> Session {
    let (file, sampler) = match family {
        Family::Flame => ("flame_tiny.safetensors", Sampler::Ddpm),
        Family::Mdm => ("mdm_tiny.safetensors", Sampler::Ddpm),
        Family::Flow => ("motionfm_tiny.safetensors", Sampler::Euler),
    };
    let model = Arc::new(Model::load(fixture(file)).unwrap());
    let params = SessionParams {
        frames: Some(FRAMES),
        steps: Some(10),
        sampler: Some(sampler),
        guidance: Some(2.5),
        seed,
        threads: 1,
        ..Default::default()
    };
    let mut s = Session::new(model, &params).unwrap();
    match family {
        Family::Flame => s.set_prompt("a person walks forward and waves.").unwrap(),
        _ => s.set_condition(Condition::text_vector(mdm_text())).unwrap(),
    }
    s
}

fn dim(s: &Session) -> usize {
    s.model().motion_dim()
}

/// A smooth reference with values in the models' usual range.
fn reference(frames: usize, dim: usize) -> Vec<f32> {
    (0..frames * dim)
        .map(|i| {
            let (f, c) = ((i / dim) as f32, (i % dim) as f32);
            0.6 * (0.3 * f + 0.7 * c).sin()
        })
        .collect()
}

fn frames_mask(frames: usize, dim: usize, kept: impl Fn(usize) -> bool) -> Vec<u8> {
    (0..frames * dim).map(|i| kept(i / dim) as u8).collect()
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn auto_method_follows_the_model_family() {
    let want = [
        (Family::Flame, EditMethod::NoisedReference),
        (Family::Mdm, EditMethod::ReplaceX0),
        (Family::Flow, EditMethod::RewriteTrajectory),
    ];
    for (family, method) in want {
        let mut s = session(family, 0);
        assert_eq!(s.resolve_method(EditMethod::Auto).unwrap(), method);
        // The diffusion methods are interchangeable on diffusion models; flow takes only its own.
        for m in [
            EditMethod::NoisedReference,
            EditMethod::ReplaceX0,
            EditMethod::RewriteTrajectory,
        ] {
            let ok = (family == Family::Flow) == (m == EditMethod::RewriteTrajectory);
            let p = EditParams {
                method: m,
                ..Default::default()
            };
            match s.set_edit_params(&p) {
                Ok(()) => assert!(ok, "{family:?} accepted {m:?}"),
                Err(e) => {
                    assert!(!ok, "{family:?} refused {m:?}: {e}");
                    assert!(e.to_string().contains(m.name()), "{e}");
                }
            }
        }
    }
}

#[test]
fn paste_makes_kept_values_exact_for_every_family() {
    for family in [Family::Flame, Family::Mdm, Family::Flow] {
        let mut s = session(family, 5);
        let d = dim(&s);
        let r = reference(FRAMES, d);
        // In-between: the first and last quarter kept, plus channel 1 everywhere.
        let mask: Vec<u8> = (0..FRAMES * d)
            .map(|i| (i % d == 1 || !(3..9).contains(&(i / d))) as u8)
            .collect();
        s.set_reference(&r).unwrap();
        s.set_mask(&mask).unwrap();
        s.set_edit_params(&EditParams {
            seam_frames: 2,
            ..Default::default()
        })
        .unwrap();
        let out = s.run().unwrap().to_vec();
        for i in 0..out.len() {
            if mask[i] != 0 {
                assert_eq!(out[i].to_bits(), r[i].to_bits(), "{family:?} value {i}");
            }
        }
        // The generated middle is not the reference.
        let changed = (3 * d..9 * d)
            .filter(|&i| mask[i] == 0 && out[i] != r[i])
            .count();
        assert!(
            changed > 4 * d,
            "{family:?}: only {changed} values generated"
        );

        // Paste off: the official behaviour, which leaves FLAME's and flow's kept values near
        // (not equal to) the reference. MDM's last DDPM step returns the replaced x̂0 itself.
        let mut s = session(family, 5);
        s.set_reference(&r).unwrap();
        s.set_mask(&mask).unwrap();
        s.set_edit_params(&EditParams {
            paste: false,
            ..Default::default()
        })
        .unwrap();
        let raw = s.run().unwrap().to_vec();
        let exact = (0..raw.len())
            .filter(|&i| mask[i] != 0 && raw[i].to_bits() == r[i].to_bits())
            .count();
        let kept = mask.iter().filter(|&&m| m != 0).count();
        match family {
            Family::Mdm => assert!(exact * 10 >= kept * 9, "{exact} of {kept}"),
            _ => assert!(exact < kept / 2, "{family:?}: {exact} of {kept} exact"),
        }
        // Far from the seams (frame 6 of 3..9 is 3 frames from each edge, past the 2 seam
        // frames), unkept values are the same with and without the paste.
        let frame6: Vec<usize> = (6 * d..7 * d).filter(|&i| mask[i] == 0).collect();
        let same = frame6.iter().filter(|&&i| out[i] == raw[i]).count();
        assert!(
            same * 10 >= frame6.len() * 9,
            "{family:?}: {same}/{}",
            frame6.len()
        );
    }
}

#[test]
fn a_mask_changed_between_steps_takes_effect_at_the_next_step() {
    // MDM replaces x̂0's kept values: the step after the mask appears returns an x̂0 equal to
    // the reference there, and the steps before are those of an unedited run.
    let mut plain = session(Family::Mdm, 9);
    let mut edited = session(Family::Mdm, 9);
    let d = dim(&edited);
    let r = reference(FRAMES, d);
    edited.set_reference(&r).unwrap();
    let keep_first = frames_mask(FRAMES, d, |f| f < 3);
    for k in 0..10 {
        if k == 4 {
            edited.set_mask(&keep_first).unwrap();
        }
        if k == 7 {
            // Back to nothing kept: from here on the steps run unedited again.
            edited.set_mask(&vec![0; FRAMES * d]).unwrap();
        }
        plain.step().unwrap();
        edited.step().unwrap();
        let x0 = edited.x0_estimate().unwrap();
        let kept_equal = (0..3 * d).all(|i| x0[i].to_bits() == r[i].to_bits());
        if k < 4 {
            assert_eq!(
                bits(plain.sample().unwrap()),
                bits(edited.sample().unwrap())
            );
            assert!(!kept_equal, "step {k}");
        } else if k < 7 {
            assert!(kept_equal, "step {k}: the new mask was not applied");
        } else {
            assert!(!kept_equal, "step {k}: the cleared mask was still applied");
        }
    }

    // FLAME and flow: a mask set before step 5 leaves steps 0..5 as an unedited run's and
    // changes step 5's result.
    for family in [Family::Flame, Family::Flow] {
        let mut plain = session(family, 4);
        let mut edited = session(family, 4);
        let d = dim(&edited);
        edited.set_reference(&reference(FRAMES, d)).unwrap();
        edited
            .set_edit_params(&EditParams {
                edit_till: 1.0,
                ..Default::default()
            })
            .unwrap();
        for k in 0..6 {
            if k == 5 {
                edited.set_mask(&frames_mask(FRAMES, d, |f| f < 3)).unwrap();
            }
            plain.step().unwrap();
            edited.step().unwrap();
            let same = bits(plain.sample().unwrap()) == bits(edited.sample().unwrap());
            assert_eq!(same, k < 5, "{family:?} step {k}");
        }
    }
}

#[test]
fn all_keep_returns_the_reference_and_none_keep_is_plain_generation() {
    for family in [Family::Flame, Family::Mdm, Family::Flow] {
        let mut s = session(family, 2);
        let d = dim(&s);
        let r = reference(FRAMES, d);
        s.set_reference(&r).unwrap();
        s.set_mask(&vec![1; FRAMES * d]).unwrap();
        assert_eq!(bits(s.run().unwrap()), bits(&r), "{family:?}");

        let mut plain = session(family, 2);
        let mut none = session(family, 2);
        none.set_reference(&r).unwrap();
        none.set_mask(&vec![0; FRAMES * d]).unwrap();
        assert_eq!(
            bits(plain.run().unwrap()),
            bits(none.run().unwrap()),
            "{family:?}"
        );
    }
}

#[test]
fn a_shorter_reference_keeps_its_own_frames_only() {
    // Prediction: 4 frames of reference, the rest generated.
    let mut s = session(Family::Mdm, 1);
    let d = dim(&s);
    let r = reference(4, d);
    s.set_reference(&r).unwrap();
    s.set_mask(&frames_mask(FRAMES, d, |f| f < 4)).unwrap();
    let out = s.run().unwrap().to_vec();
    assert_eq!(bits(&out[..4 * d]), bits(&r));

    // Keeping a frame the reference does not have is refused, whichever is set first.
    let mut s = session(Family::Mdm, 1);
    s.set_reference(&r).unwrap();
    let e = s
        .set_mask(&frames_mask(FRAMES, d, |f| f < 5))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("keeps frame 4") && e.contains("only 4 frames"),
        "{e}"
    );
    let mut s = session(Family::Mdm, 1);
    s.set_mask(&frames_mask(FRAMES, d, |f| f < 5)).unwrap();
    let e = s.set_reference(&r).unwrap_err().to_string();
    assert!(e.contains("keeps frame 4"), "{e}");
}

#[test]
fn bad_masks_and_references_get_clear_errors() {
    let mut s = session(Family::Flame, 0);
    let d = dim(&s);
    let n = FRAMES * d;
    let msg = |r: flame::Result<()>| r.unwrap_err().to_string();

    // Wrong sizes.
    let e = msg(s.set_mask(&vec![1; n - 1]));
    assert!(e.contains(&format!("expected {n}")), "{e}");
    assert!(s.set_mask(&vec![1; n + 1]).is_err());
    assert!(s.set_mask(&[]).is_err());
    let e = msg(s.set_reference(&vec![0.0; n + d]));
    assert!(e.contains("between 1 and 12 whole frames"), "{e}");
    assert!(s.set_reference(&vec![0.0; d + 1]).is_err());
    assert!(s.set_reference(&[]).is_err());

    // NaN and infinity in the reference name the frame and channel.
    let mut r = reference(FRAMES, d);
    r[2 * d + 5] = f32::NAN;
    let e = msg(s.set_reference(&r));
    assert!(e.contains("frame 2, channel 5") && e.contains("NaN"), "{e}");
    r[2 * d + 5] = f32::INFINITY;
    assert!(s.set_reference(&r).is_err());

    // A mask without a reference: an error at the step, which leaves the session unchanged.
    s.set_mask(&vec![1; n]).unwrap();
    match s.step() {
        Err(Error::WrongState(e)) => assert!(e.contains("no reference"), "{e}"),
        other => panic!("{other:?}"),
    }
    assert_eq!(s.steps_left(), 10);
    assert!(s.sample().is_none());

    // Bad parameters.
    for till in [-0.5, 1.01, f32::NAN] {
        let p = EditParams {
            edit_till: till,
            ..Default::default()
        };
        assert!(msg(s.set_edit_params(&p)).contains("edit_till"));
    }
    // After clearing, plain generation works.
    s.clear_edit();
    assert!(s.mask().is_none());
    s.step().unwrap();
}

#[test]
fn flow_rewriting_stops_after_edit_till() {
    // With edit_till = 0.2 and 10 steps, steps k = 0, 1, 2 rewrite (k/N ≤ 0.2) and later steps
    // do not: a mask set before step 3 changes nothing, one set before step 2 does.
    let run = |mask_from: usize| {
        let mut s = session(Family::Flow, 6);
        let d = dim(&s);
        s.set_reference(&reference(FRAMES, d)).unwrap();
        s.set_edit_params(&EditParams {
            paste: false,
            ..Default::default()
        })
        .unwrap();
        for k in 0..10 {
            if k == mask_from {
                s.set_mask(&frames_mask(FRAMES, d, |f| f < 6)).unwrap();
            }
            s.step().unwrap();
        }
        bits(s.sample().unwrap())
    };
    let plain = run(usize::MAX);
    assert_eq!(run(3), plain);
    assert_ne!(run(2), plain);
}
