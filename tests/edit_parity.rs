//! Editing-loop parity (reference motion + keep-mask) against the PyTorch reference, one edited
//! generation per model family on the committed tiny models, within 1e-4 at every step:
//! FLAME's noised reference imposed on x_t (docs/official/flame.md#editing), MDM's x0 replacement
//! (docs/official/mdm.md#editing) and Motion Flow Matching's trajectory rewriting
//! "euler_replacement_edit_till" (docs/official/motionfm.md#editing).
//!
//! Fixtures: tests/fixtures/edit_expected.{safetensors,json}, written by
//! tools/make_edit_fixtures.py from tools/reference/edit.py (on top of tools/reference/
//! {diffusion,flame,mdm}.py) using tests/fixtures/{flame,mdm,motionfm}_tiny.safetensors.
//! Regenerate with `python tools/make_edit_fixtures.py` (deterministic; needs torch, numpy,
//! safetensors, scipy, transformers). All noise is stored in the order the session draws it and
//! replayed with `ReplayNoise`, so no RNG parity is involved.

use std::path::{Path, PathBuf};
use std::sync::Arc;

use flame::checkpoint::ModelFile;
use flame::models::{Condition, Model};
use flame::rng::ReplayNoise;
use flame::session::{EditMethod, EditParams, Sampler, Session, SessionParams};

const TOL: f32 = 1e-4;
const STEPS: usize = 10;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures")
        .join(name)
}

struct Expected {
    file: ModelFile,
    json: serde_json::Value,
}

impl Expected {
    fn load() -> Expected {
        let file = ModelFile::open(&fixture("edit_expected.safetensors")).unwrap();
        let text = std::fs::read_to_string(fixture("edit_expected.json")).unwrap();
        Expected {
            file,
            json: serde_json::from_str(&text).unwrap(),
        }
    }
    fn get(&self, name: &str) -> Vec<f32> {
        self.file.tensor_any_shape(name).unwrap().data().to_vec()
    }
}

/// One model family's edited generation as stored in the fixture.
#[derive(Clone, Copy)]
struct Family {
    /// Key of the family's section in the JSON and prefix of its tensors.
    name: &'static str,
    sampler: Sampler,
    /// Tensor with x_T (diffusion) or z0 (flow).
    start: &'static str,
    /// Whether the fixture stores noise drawn after the start, and x0 estimates.
    noise: bool,
    x0s: bool,
}

const FLAME: Family = Family {
    name: "flame",
    sampler: Sampler::Ddpm,
    start: "flame_x_T",
    noise: true,
    x0s: true,
};
const MDM: Family = Family {
    name: "mdm",
    sampler: Sampler::Ddpm,
    start: "mdm_x_T",
    noise: true,
    x0s: true,
};
const MOTIONFM: Family = Family {
    name: "motionfm",
    sampler: Sampler::Euler,
    start: "motionfm_z0",
    noise: false,
    x0s: false,
};

/// Largest |a - b| and where; infinite if any value is not finite (so a NaN never hides).
fn max_abs_diff_at(a: &[f32], b: &[f32]) -> (f32, usize) {
    assert_eq!(a.len(), b.len(), "length mismatch");
    a.iter()
        .zip(b)
        .enumerate()
        .fold((0.0, 0), |(m, at), (i, (x, y))| {
            let d = (x - y).abs();
            let d = if d.is_finite() { d } else { f32::INFINITY };
            if d > m {
                (d, i)
            } else {
                (m, at)
            }
        })
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

impl Family {
    fn section<'a>(&self, e: &'a Expected) -> &'a serde_json::Value {
        &e.json[self.name]
    }

    fn tensor(&self, e: &Expected, what: &str) -> Vec<f32> {
        e.get(&format!("{}_{what}", self.name))
    }

    fn keep(&self, e: &Expected) -> Vec<bool> {
        self.tensor(e, "mask").iter().map(|&m| m != 0.0).collect()
    }

    /// A session set up exactly like the fixture's generation, with the given paste settings.
    fn session(&self, e: &Expected, paste: bool, seam_frames: usize) -> Session {
        let sec = self.section(e);
        let model = Arc::new(Model::load(fixture(sec["model"].as_str().unwrap())).unwrap());
        let params = SessionParams {
            frames: Some(sec["frames"].as_u64().unwrap() as usize),
            steps: Some(STEPS),
            sampler: Some(self.sampler),
            guidance: Some(sec["guidance"].as_f64().unwrap() as f32),
            seed: 11,
            threads: 2,
            ..Default::default()
        };
        let mut s = Session::new(model, &params).unwrap();
        match sec["prompt"].as_str() {
            Some(prompt) => s.set_prompt(prompt).unwrap(),
            None => s
                .set_condition(Condition::text_vector(e.get("text")))
                .unwrap(),
        }
        s.set_initial_noise(&e.get(self.start)).unwrap();
        // NaN after the recorded noise: a session that draws more than the reference did (or
        // draws it in another order and runs past the end) produces NaN and fails the test.
        let mut noise = if self.noise {
            self.tensor(e, "noise")
        } else {
            Vec::new()
        };
        let sentinel = 4 * s.frames() * s.model().motion_dim();
        noise.resize(noise.len() + sentinel, f32::NAN);
        s.set_noise_source(Box::new(ReplayNoise::new(noise)));
        s.set_reference(&self.tensor(e, "reference")).unwrap();
        let mask: Vec<u8> = self.keep(e).iter().map(|&k| u8::from(k)).collect();
        s.set_mask(&mask).unwrap();
        let edit_till = sec["edit_till"].as_f64().unwrap_or(0.2) as f32;
        s.set_edit_params(&EditParams {
            method: EditMethod::Auto,
            edit_till,
            paste,
            seam_frames,
        })
        .unwrap();
        s
    }

    /// Runs the session step by step; returns (samples, x0 estimates) after each step.
    fn run(&self, mut s: Session) -> (Vec<Vec<f32>>, Vec<Vec<f32>>) {
        let (mut xs, mut x0s) = (Vec::new(), Vec::new());
        for k in 0..STEPS {
            assert_eq!(s.step().unwrap(), STEPS - 1 - k);
            xs.push(s.sample().unwrap().to_vec());
            if self.x0s {
                x0s.push(s.x0_estimate().unwrap().to_vec());
            }
        }
        (xs, x0s)
    }

    /// Compares every step with the fixture; returns the largest difference seen.
    fn check_parity(&self) -> f32 {
        let e = Expected::load();
        let (xs, x0s) = self.run(self.session(&e, false, 0));
        let (want_xs, want_x0s) = (
            self.tensor(&e, "xs"),
            self.x0s.then(|| self.tensor(&e, "x0s")),
        );
        let n = xs[0].len();
        assert_eq!(want_xs.len(), STEPS * n);
        let mut worst = 0.0f32;
        let dim = n / self.section(&e)["frames"].as_u64().unwrap() as usize;
        let at = |i: usize| format!("frame {}, channel {}", i / dim, i % dim);
        for k in 0..STEPS {
            let (dx, ix) = max_abs_diff_at(&xs[k], &want_xs[k * n..(k + 1) * n]);
            let (d0, i0) = want_x0s.as_ref().map_or((0.0, 0), |w| {
                max_abs_diff_at(&x0s[k], &w[k * n..(k + 1) * n])
            });
            let x0_note = if self.x0s {
                format!(", x0 max abs diff {d0:e} ({})", at(i0))
            } else {
                String::new()
            };
            eprintln!(
                "{} step {k}: x max abs diff {dx:e} ({}){x0_note}",
                self.name,
                at(ix)
            );
            assert!(
                dx <= TOL,
                "{} x at step {k}: max abs diff {dx:e} at {}",
                self.name,
                at(ix)
            );
            assert!(
                d0 <= TOL,
                "{} x0 at step {k}: max abs diff {d0:e} at {}",
                self.name,
                at(i0)
            );
            worst = worst.max(dx).max(d0);
        }
        eprintln!("{}: worst difference over all steps {worst:e}", self.name);
        worst
    }

    /// paste = true changes only the final sample: its kept values become the reference bit for
    /// bit; without seams nothing else changes, with seams only values within `seam` frames of
    /// a kept value of the same channel do.
    fn check_paste(&self, seam: usize) {
        let e = Expected::load();
        let (plain, plain_x0) = self.run(self.session(&e, false, seam));
        let (pasted, pasted_x0) = self.run(self.session(&e, true, seam));
        for k in 0..STEPS - 1 {
            assert_eq!(bits(&plain[k]), bits(&pasted[k]), "{} step {k}", self.name);
            if self.x0s {
                assert_eq!(
                    bits(&plain_x0[k]),
                    bits(&pasted_x0[k]),
                    "{} x0 {k}",
                    self.name
                );
            }
        }
        let reference = self.tensor(&e, "reference");
        let keep = self.keep(&e);
        let (before, after) = (&plain[STEPS - 1], &pasted[STEPS - 1]);
        let frames = self.section(&e)["frames"].as_u64().unwrap() as usize;
        let dim = reference.len() / frames;
        let mut changed = 0;
        for i in 0..reference.len() {
            if keep[i] {
                assert_eq!(
                    after[i].to_bits(),
                    reference[i].to_bits(),
                    "{} kept value {i} (frame {}, channel {}) is not the reference",
                    self.name,
                    i / dim,
                    i % dim
                );
                continue;
            }
            let (f, c) = (i / dim, i % dim);
            let near = (0..frames).any(|g| keep[g * dim + c] && f.abs_diff(g) <= seam);
            if !near {
                assert_eq!(
                    after[i].to_bits(),
                    before[i].to_bits(),
                    "{} edited value {i} (frame {f}, channel {c}) changed by the paste",
                    self.name
                );
            } else if after[i].to_bits() != before[i].to_bits() {
                changed += 1;
            }
        }
        eprintln!(
            "{} paste (seam {seam}): {changed} edited values near seams blended",
            self.name
        );
    }
}

#[test]
fn flame_noised_reference_editing_matches_reference() {
    FLAME.check_parity();
}

#[test]
fn mdm_x0_replacement_editing_matches_reference() {
    MDM.check_parity();
}

#[test]
fn motionfm_trajectory_rewriting_matches_reference() {
    MOTIONFM.check_parity();
}

#[test]
fn auto_method_follows_the_model_family() {
    let e = Expected::load();
    for (fam, want) in [
        (FLAME, EditMethod::NoisedReference),
        (MDM, EditMethod::ReplaceX0),
        (MOTIONFM, EditMethod::RewriteTrajectory),
    ] {
        let s = fam.session(&e, false, 0);
        assert_eq!(
            s.resolve_method(EditMethod::Auto).unwrap(),
            want,
            "{}",
            fam.name
        );
    }
}

#[test]
fn flame_paste_sets_only_the_final_kept_values() {
    FLAME.check_paste(0);
    FLAME.check_paste(4);
}

#[test]
fn motionfm_paste_sets_only_the_final_kept_values() {
    MOTIONFM.check_paste(0);
    MOTIONFM.check_paste(4);
}

#[test]
fn mdm_final_kept_values_are_the_reference_even_without_paste() {
    // Respaced DDPM's last step (t = 0) has c1 = 1, c2 = 0 and no noise: it returns the
    // replaced x0, so the kept values already are the reference and pasting changes nothing
    // there (the seams may still blend the edited frames next to them).
    let e = Expected::load();
    let (xs, x0s) = MDM.run(MDM.session(&e, false, 0));
    let reference = MDM.tensor(&e, "reference");
    let keep = MDM.keep(&e);
    let last = &xs[STEPS - 1];
    assert_eq!(
        bits(last),
        bits(&x0s[STEPS - 1]),
        "final sample = replaced x0"
    );
    for x0 in &x0s {
        for i in (0..keep.len()).filter(|&i| keep[i]) {
            assert_eq!(x0[i].to_bits(), reference[i].to_bits(), "x0 value {i}");
        }
    }
    MDM.check_paste(0);
    MDM.check_paste(4);
}
