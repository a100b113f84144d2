//! What a prompt became: `Session::prompt_info` reports how the prompt fitted the text
//! encoder's window, and a blank prompt runs on the model's unconditional input.
//!
//! Fixtures: tests/fixtures/flame_tiny.safetensors (RoBERTa, window 20) and mdm_tiny /
//! motionfm_tiny (CLIP, MDM's window 22).

mod common;

use std::sync::Arc;

use flame::config::TextConfig;
use flame::models::{Condition, Model};
use flame::session::{Sampler, Session, SessionParams};

fn model(name: &str) -> Arc<Model> {
    Arc::new(Model::load(common::repo(&format!("tests/fixtures/{name}.safetensors"))).unwrap())
}

fn params(sampler: Sampler) -> SessionParams {
    SessionParams {
        frames: Some(12),
        steps: Some(3),
        sampler: Some(sampler),
        guidance: Some(2.5),
        seed: 7,
        threads: 1,
        ..Default::default()
    }
}

const LONG: &str = "a person walks forward slowly, then turns to the left, raises both arms \
                    above the head, waves with the right hand and finally kicks with the right leg";

#[test]
fn a_long_prompt_is_cut_and_says_what_was_dropped() {
    for (name, sampler) in [("flame_tiny", Sampler::Ddim), ("mdm_tiny", Sampler::Ddim)] {
        let m = model(name);
        let mut s = Session::new(Arc::clone(&m), &params(sampler)).unwrap();
        assert!(s.prompt_info().is_none(), "{name}: no prompt yet");
        s.set_prompt(LONG).unwrap();
        let info = s.prompt_info().unwrap().clone();
        let window = match &m.config().text_encoder {
            TextConfig::Bert(t) => t.max_length,
            TextConfig::Clip(c) => c.max_length,
            TextConfig::T5(t) => t.max_length,
        };
        assert_eq!(info.window, window, "{name}");
        assert_eq!(info.kept, window, "{name}: a long prompt fills the window");
        assert!(info.tokens > window && info.truncated(), "{name}: {info:?}");
        assert!(!info.unconditional);
        // What was dropped is the prompt's tail (CLIP lower-cases, and these are lower case),
        // and the rest on its own fits the window exactly as the cut prompt did.
        assert!(
            !info.dropped.is_empty() && LONG.ends_with(&info.dropped),
            "{name}: {info:?}"
        );
        assert!(info.dropped.ends_with("kicks with the right leg"), "{name}");
        let kept_text = LONG[..LONG.len() - info.dropped.len()].trim_end();
        let rest = m.prompt_info(kept_text).unwrap();
        assert!(rest.tokens <= window, "{name}: {rest:?}");
        assert!(
            rest.tokens >= window - 1,
            "{name}: {rest:?}: nothing kept is reported dropped"
        );

        s.set_prompt("a person walks").unwrap();
        let short = s.prompt_info().unwrap();
        assert!(
            !short.truncated() && short.dropped.is_empty(),
            "{name}: {short:?}"
        );
        assert_eq!(short.kept, short.tokens);
    }
}

/// A blank prompt runs on exactly the unconditional input with no guidance pass: the same bits
/// as setting that input as the condition with guidance 1.
#[test]
fn a_blank_prompt_is_unconditional_generation() {
    for (name, sampler) in [
        ("flame_tiny", Sampler::Ddim),
        ("mdm_tiny", Sampler::Ddim),
        ("motionfm_tiny", Sampler::Euler),
    ] {
        let m = model(name);
        let mut blank = Session::new(Arc::clone(&m), &params(sampler)).unwrap();
        blank.set_prompt("  \t ").unwrap();
        assert!(blank.prompt_info().unwrap().unconditional, "{name}");
        let got = blank.run().unwrap().to_vec();

        let mut p = params(sampler);
        p.guidance = Some(1.0);
        let mut reference = Session::new(Arc::clone(&m), &p).unwrap();
        let uncond: Condition = m.uncond().unwrap().clone();
        if let Some(v) = uncond.as_text_vector() {
            assert!(
                v.iter().all(|&x| x == 0.0),
                "{name}: MDM's unconditional input is zeros"
            );
        }
        reference.set_condition(uncond).unwrap();
        assert!(reference.prompt_info().is_none());
        let want = reference.run().unwrap().to_vec();
        assert_eq!(
            got, want,
            "{name}: blank prompt = unconditional input, unguided"
        );
    }
}

/// `set_prompt_from` takes another session's encoded prompt: the same run, bit for bit, and the
/// same report, as encoding the prompt again (FLAME with RoBERTa, MotionLCM with T5); another
/// model's session and a session without a prompt are refused.
#[test]
fn a_prompt_encoded_once_serves_other_sessions() {
    for (name, sampler) in [
        ("flame_tiny", Sampler::Ddim),
        ("motionlcm_v2_tiny", Sampler::Lcm),
    ] {
        let m = model(name);
        let p = SessionParams {
            steps: Some(2),
            ..params(sampler)
        };
        let mut first = Session::new(Arc::clone(&m), &p).unwrap();
        first.set_prompt(LONG).unwrap();
        let encoded = first.run().unwrap().to_vec();
        let mut second = Session::new(Arc::clone(&m), &p).unwrap();
        second.set_prompt_from(&first).unwrap();
        assert_eq!(second.prompt_info(), first.prompt_info(), "{name}");
        assert_eq!(second.run().unwrap(), &encoded[..], "{name}");
        // Another loaded copy of the same file is another model.
        let other = model(name);
        let mut third = Session::new(other, &p).unwrap();
        let e = third.set_prompt_from(&first).unwrap_err().to_string();
        assert!(e.contains("another model"), "{name}: {e}");
        let empty = Session::new(Arc::clone(&m), &p).unwrap();
        let mut fourth = Session::new(Arc::clone(&m), &p).unwrap();
        let e = fourth.set_prompt_from(&empty).unwrap_err().to_string();
        assert!(e.contains("no prompt"), "{name}: {e}");
    }
}
