//! The game-ready finish on the demo model's locomotion (docs/game-ready.md): with the
//! feet locked, every frame keeps the SMPL skeleton's bone lengths, joints above the knees move
//! by less than 1 cm from the raw motion (apart from the floor's one vertical shift), no foot
//! joint is more than 5 mm under the floor, and the skating ratio of GMD/OmniControl is at most
//! 0.02 (tools/skating.sh measures the same over 16 runs with NumPy).
//!
//! The model: `$FLAME_DEMO_MODEL`, else the assembled demo model, else skipped (tests/common).

use std::sync::Arc;

#[path = "../../../tests/common/mod.rs"]
mod common;

use common::demo_model;
use flame::models::Model;
use flame::motion::{skating, Convention, Finish, Format, Poses};
use flame::session::{Session, SessionParams};

const PROMPTS: [&str; 3] = [
    "a man takes a relaxed walk straight in front of him",
    "somebody jogs forward at a comfortable pace",
    "a person side steps to the right a few times",
];

#[test]
fn locked_feet_keep_the_skeleton_the_body_and_the_floor() {
    let Some(path) = demo_model() else {
        common::skip(
            "demo_feet::locked_feet_keep_the_skeleton_the_body_and_the_floor",
            "no demo model (set FLAME_MINILM_DIR or run tools/try.sh to assemble it)",
        );
        return;
    };
    let model = Arc::new(Model::load(&path).unwrap());
    let skel = Format::Smpl24Rot6d.skeleton();
    let (mut raw_ratio, mut locked_ratio) = (0.0, 0.0);
    for prompt in PROMPTS {
        let params = SessionParams {
            frames: Some(120),
            seed: 0,
            ..Default::default()
        };
        let mut s = Session::new(Arc::clone(&model), &params).unwrap();
        s.set_prompt(prompt).unwrap();
        let x = s.run().unwrap().to_vec();
        let opts = model.read_options(1.0, true);
        let raw = Poses::decode(model.motion_format(), &x, 120, &opts).unwrap();
        let locked = Finish::game_ready().apply(&raw, 20.0).unwrap();
        let (p, q) = (
            raw.positions(Convention::Gltf),
            locked.positions(Convention::Gltf),
        );
        // The floor's shift: the same for every joint and frame, vertical only.
        let shift = q[0][1] - p[0][1];
        for t in 0..120 {
            for j in 0..24 {
                let (a, b) = (p[t * 24 + j], q[t * 24 + j]);
                if let Some(par) = skel.parent(j) {
                    let d: f64 = (0..3)
                        .map(|i| (b[i] - q[t * 24 + par][i]).powi(2))
                        .sum::<f64>()
                        .sqrt();
                    let o = skel.rest_offsets()[j];
                    let rest = (o[0] * o[0] + o[1] * o[1] + o[2] * o[2]).sqrt();
                    assert!(
                        (d - rest).abs() < 1e-5,
                        "{prompt}: frame {t} bone {j}: {d} vs {rest}"
                    );
                }
                if ![4, 5, 7, 8, 10, 11].contains(&j) {
                    let moved = ((b[0] - a[0]).powi(2)
                        + (b[1] - shift - a[1]).powi(2)
                        + (b[2] - a[2]).powi(2))
                    .sqrt();
                    assert!(
                        moved < 0.01,
                        "{prompt}: frame {t} joint {j} moved {moved} m"
                    );
                }
            }
            for j in [7, 8, 10, 11] {
                assert!(
                    q[t * 24 + j][1] > -0.005,
                    "{prompt}: frame {t} foot {j} under the floor"
                );
            }
        }
        raw_ratio += skating::skating_ratio(&p, 120, 24, 20.0).unwrap() / PROMPTS.len() as f64;
        locked_ratio += skating::skating_ratio(&q, 120, 24, 20.0).unwrap() / PROMPTS.len() as f64;
    }
    println!("skating ratio: raw {raw_ratio:.4}, locked {locked_ratio:.4}");
    assert!(
        raw_ratio > 0.1,
        "the raw demo motion should slide ({raw_ratio})"
    );
    assert!(locked_ratio <= 0.02, "locked {locked_ratio}");
}
