//! Motion decoding parity against an independent NumPy implementation of the official procedures.
//!
//! Reference: tools/motion_reference.py (pytorch3d 6D→matrix and matrix→quaternion, SMPL forward
//! kinematics, scipy's gaussian_filter1d, HumanML3D's recover_root_rot_pos / recover_from_ric /
//! recover_from_rot, written from the official procedures as docs/official/ lists them:
//! docs/official/flame.md#output-post-processing, docs/official/humanml3d.md#recovering-joint-positions,
//! docs/official/smpl.md#forward-kinematics); fixture:
//! tests/fixtures/motion_reference.safetensors (a synthetic walk with root travel and turning,
//! smooth sinusoidal rotations on every joint axis, encoded to both formats).

use std::path::Path;

use flame::checkpoint::ModelFile;
use flame::motion::{
    self, postprocess, Convention, Format, Layout, Normalization, Poses, ReadOptions,
};

const TOL: f32 = 1e-5;

struct Fixture(ModelFile);

impl Fixture {
    fn load() -> Fixture {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("tests/fixtures/motion_reference.safetensors");
        Fixture(ModelFile::open(&path).unwrap())
    }
    fn get(&self, name: &str) -> (Vec<usize>, Vec<f32>) {
        let t = self.0.tensor_any_shape(name).unwrap();
        (t.shape().to_vec(), t.data().to_vec())
    }
    fn data(&self, name: &str) -> Vec<f32> {
        self.get(name).1
    }
}

/// Largest absolute difference; fails the test above `TOL`.
fn check(what: &str, got: &[f32], want: &[f32]) -> f32 {
    assert_eq!(got.len(), want.len(), "{what}: length");
    let err = got
        .iter()
        .zip(want)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    println!("{what}: max abs error {err:.2e} over {} values", got.len());
    assert!(err <= TOL, "{what}: max abs error {err} > {TOL}");
    err
}

fn decode(format: Format, features: &[f32], opts: &ReadOptions) -> Poses {
    let frames = features.len() / format.feature_dim();
    Poses::decode(format, features, frames, opts).unwrap()
}

#[test]
fn smpl24_6d_matches_the_reference() {
    let fx = Fixture::load();
    let (shape, features) = fx.get("smpl_features");
    assert_eq!(shape, vec![36, 147]);
    let raw = ReadOptions {
        continuous: false,
        ..Default::default()
    };
    let poses = decode(Format::Smpl24Rot6d, &features, &raw);
    let native = Convention::Native;
    check(
        "smpl root",
        &poses.layout(Layout::RootTranslation, native).unwrap(),
        &fx.data("smpl_root"),
    );
    check(
        "smpl positions",
        &poses.layout(Layout::GlobalPositions, native).unwrap(),
        &fx.data("smpl_positions"),
    );
    check(
        "smpl local wxyz",
        &poses.layout(Layout::LocalQuatWxyz, native).unwrap(),
        &fx.data("smpl_local_wxyz"),
    );
    check(
        "smpl global wxyz",
        &poses.layout(Layout::GlobalQuatWxyz, native).unwrap(),
        &fx.data("smpl_global_wxyz"),
    );

    let cont = decode(Format::Smpl24Rot6d, &features, &ReadOptions::default());
    check(
        "smpl local wxyz continuous",
        &cont.layout(Layout::LocalQuatWxyz, native).unwrap(),
        &fx.data("smpl_local_wxyz_continuous"),
    );
    check(
        "smpl global wxyz continuous",
        &cont.layout(Layout::GlobalQuatWxyz, native).unwrap(),
        &fx.data("smpl_global_wxyz_continuous"),
    );
    // xyzw is the same numbers reordered.
    let xyzw = cont.layout(Layout::GlobalQuatXyzw, native).unwrap();
    let wxyz = cont.layout(Layout::GlobalQuatWxyz, native).unwrap();
    for (a, b) in xyzw.chunks(4).zip(wxyz.chunks(4)) {
        assert_eq!([a[3], a[0], a[1], a[2]], [b[0], b[1], b[2], b[3]]);
    }
}

#[test]
fn smoothing_matches_scipy_and_the_smoothed_decode() {
    let fx = Fixture::load();
    let features = fx.data("smpl_features");
    let mut x: Vec<f64> = features.iter().map(|&v| v as f64).collect();
    postprocess::gaussian_smooth(&mut x, 36, 147, 1.0);
    let x: Vec<f32> = x.into_iter().map(|v| v as f32).collect();
    check(
        "gaussian_filter1d sigma 1",
        &x,
        &fx.data("smpl_smooth_features"),
    );

    let opts = ReadOptions {
        smooth_sigma: 1.0,
        continuous: false,
        ..Default::default()
    };
    let poses = decode(Format::Smpl24Rot6d, &features, &opts);
    let native = Convention::Native;
    check(
        "smoothed smpl positions",
        &poses.layout(Layout::GlobalPositions, native).unwrap(),
        &fx.data("smpl_smooth_positions"),
    );
    check(
        "smoothed smpl local wxyz",
        &poses.layout(Layout::LocalQuatWxyz, native).unwrap(),
        &fx.data("smpl_smooth_local_wxyz"),
    );
}

#[test]
fn humanml263_matches_the_reference() {
    let fx = Fixture::load();
    let (shape, features) = fx.get("hml_features");
    assert_eq!(shape, vec![30, 263]);
    let (mean, std) = (fx.data("hml_mean"), fx.data("hml_std"));
    let norm = Some(Normalization {
        mean: &mean,
        std: &std,
    });
    let raw = ReadOptions {
        continuous: false,
        normalization: norm,
        ..Default::default()
    };
    let poses = decode(Format::HumanMl263, &features, &raw);
    let native = Convention::Native;
    check(
        "hml root",
        &poses.layout(Layout::RootTranslation, native).unwrap(),
        &fx.data("hml_root"),
    );
    check(
        "hml positions",
        &poses.layout(Layout::GlobalPositions, native).unwrap(),
        &fx.data("hml_positions"),
    );
    check(
        "hml local wxyz",
        &poses.layout(Layout::LocalQuatWxyz, native).unwrap(),
        &fx.data("hml_local_wxyz"),
    );
    check(
        "hml global wxyz",
        &poses.layout(Layout::GlobalQuatWxyz, native).unwrap(),
        &fx.data("hml_global_wxyz"),
    );
    check(
        "hml contacts",
        &poses.layout(Layout::FootContacts, native).unwrap(),
        &fx.data("hml_contacts"),
    );

    let cont = ReadOptions {
        normalization: norm,
        ..Default::default()
    };
    let got = motion::read_layout(
        Format::HumanMl263,
        &features,
        30,
        Layout::LocalQuatWxyz,
        native,
        &cont,
    )
    .unwrap();
    check(
        "hml local wxyz continuous",
        &got,
        &fx.data("hml_local_wxyz_continuous"),
    );
}

#[test]
fn conventions_move_the_reference_motion_rigidly() {
    // Every preset is a fixed change of frame of the native decode: distances between joints are
    // kept (times 100 for centimetres) and the local rotations' angles are kept.
    let fx = Fixture::load();
    let features = fx.data("smpl_features");
    let poses = decode(Format::Smpl24Rot6d, &features, &ReadOptions::default());
    let native = poses.positions(Convention::Native);
    let native_q = poses.quaternions(&poses.local_rotations(Convention::Native));
    for c in Convention::ALL {
        let s = if c == Convention::Unreal { 100.0 } else { 1.0 };
        let p = poses.positions(c);
        for (i, (a, b)) in p.iter().zip(&native).enumerate().skip(1) {
            let (a0, b0) = (&p[i - 1], &native[i - 1]);
            let da =
                ((a[0] - a0[0]).powi(2) + (a[1] - a0[1]).powi(2) + (a[2] - a0[2]).powi(2)).sqrt();
            let db =
                ((b[0] - b0[0]).powi(2) + (b[1] - b0[1]).powi(2) + (b[2] - b0[2]).powi(2)).sqrt();
            assert!((da - s * db).abs() < 1e-9, "{c}");
        }
        let q = poses.quaternions(&poses.local_rotations(c));
        for (j, (a, b)) in q.iter().zip(&native_q).enumerate() {
            if j % 24 != 0 {
                assert!(
                    (a[0].abs() - b[0].abs()).abs() < 1e-12,
                    "{c}: joint {} angle",
                    j % 24
                );
            }
        }
    }
}
