//! `flame::grad` against PyTorch autograd (tests/fixtures/grad_expected.safetensors, written by
//! tools/reference/grad.py from the definitions), the joint positions against the motion decoder,
//! and their vector-Jacobian products against central finite differences as a second,
//! independent source. The layers' input gradients are tested inside the crate (src/grad/tests.rs).

use flame::grad::{
    denormalize_backward, l2_norm_sum_grad, positions, positions_vjp, relu_backward,
    upsample_nearest2_backward,
};
use flame::motion::{Convention, Format, Poses, ReadOptions};
use safetensors::{Dtype, SafeTensors};

/// f32 operations against autograd in f32.
const TOL_F32: f64 = 1e-5;
/// f64 kinematics against autograd in f64.
const TOL_F64: f64 = 1e-9;

fn fixture_bytes() -> Vec<u8> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/fixtures/grad_expected.safetensors");
    std::fs::read(path).unwrap()
}

/// Tensor `name` of the fixture as f64 (f32 tensors widened exactly) and its shape.
fn load(bytes: &[u8], name: &str) -> (Vec<usize>, Vec<f64>) {
    let st = SafeTensors::deserialize(bytes).unwrap();
    let t = st.tensor(name).unwrap();
    let data = match t.dtype() {
        Dtype::F32 => t
            .data()
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()) as f64)
            .collect(),
        Dtype::F64 => t
            .data()
            .chunks_exact(8)
            .map(|b| f64::from_le_bytes(b.try_into().unwrap()))
            .collect(),
        d => panic!("{name}: unexpected dtype {d:?}"),
    };
    (t.shape().to_vec(), data)
}

fn f32s(v: &[f64]) -> Vec<f32> {
    v.iter().map(|&x| x as f32).collect()
}

fn vec3s(v: &[f64]) -> Vec<[f64; 3]> {
    v.chunks_exact(3).map(|c| [c[0], c[1], c[2]]).collect()
}

/// Largest difference relative to max(1, |reference|).
fn rel_diff(got: &[f64], want: &[f64]) -> f64 {
    assert_eq!(got.len(), want.len());
    got.iter()
        .zip(want)
        .map(|(g, w)| (g - w).abs() / w.abs().max(1.0))
        .fold(0.0, f64::max)
}

/// Values in ±[0.1, 1), never zero (xorshift; the seed picks the stream).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        let u = (self.0 >> 11) as f64 / (1u64 << 53) as f64;
        let mag = 0.1 + 0.9 * (2.0 * u).fract();
        if u < 0.5 {
            -mag
        } else {
            mag
        }
    }

    fn vec(&mut self, n: usize) -> Vec<f64> {
        (0..n).map(|_| self.next()).collect()
    }
}

#[test]
fn relu_backward_matches_autograd_including_zero_inputs() {
    let b = fixture_bytes();
    let (x, y, dy, want) = (
        f32s(&load(&b, "relu.x").1),
        f32s(&load(&b, "relu.y").1),
        f32s(&load(&b, "relu.dy").1),
        load(&b, "relu.dx").1,
    );
    assert_eq!(x.iter().filter(|&&v| v == 0.0).count(), 3);
    for sign_source in [&x, &y] {
        let mut g = dy.clone();
        relu_backward(sign_source, &mut g);
        let got: Vec<f64> = g.iter().map(|&v| v as f64).collect();
        assert!(rel_diff(&got, &want) <= TOL_F32);
    }
}

#[test]
fn upsample_backward_matches_autograd() {
    let b = fixture_bytes();
    let (shape, dy) = load(&b, "upsample.dy");
    let (_, want) = load(&b, "upsample.dx");
    let mut g = vec![f32::NAN; 1];
    upsample_nearest2_backward(&f32s(&dy), shape[0] / 2, shape[1], &mut g);
    let got: Vec<f64> = g.iter().map(|&v| v as f64).collect();
    let d = rel_diff(&got, &want);
    assert!(d <= TOL_F32, "{d:e}");
}

#[test]
fn denormalize_backward_matches_autograd_and_rejects_bad_lengths() {
    let b = fixture_bytes();
    let std = f32s(&load(&b, "denorm.std").1);
    let (mut g, want) = (load(&b, "denorm.dy").1, load(&b, "denorm.dx").1);
    denormalize_backward(&mut g, &std).unwrap();
    let d = rel_diff(&g, &want);
    assert!(d <= TOL_F64, "{d:e}");
    let e = denormalize_backward(&mut g[..5], &std).unwrap_err();
    assert!(e.to_string().contains("5 values with 6 stds"), "{e}");
    assert!(denormalize_backward(&mut g, &[]).is_err());
}

#[test]
fn l2_loss_and_gradient_match_autograd() {
    let b = fixture_bytes();
    let pos = vec3s(&load(&b, "l2.pos").1);
    let target = vec3s(&load(&b, "l2.target").1);
    let weight = vec3s(&load(&b, "l2.weight").1);
    let want_grad = load(&b, "l2.grad").1;
    let want_loss = load(&b, "l2.loss").1[0];
    let mut grad = vec![[f64::NAN; 3]; pos.len()];
    let loss = l2_norm_sum_grad(&pos, &target, &weight, &mut grad);
    assert!(
        (loss - want_loss).abs() <= TOL_F64 * want_loss.abs(),
        "{loss} vs {want_loss}"
    );
    let d = rel_diff(&grad.concat(), &want_grad);
    assert!(d <= TOL_F64, "{d:e}");
    // The fixture's exactly-zero residual and its all-zero-weight joint give zero gradients.
    assert_eq!(grad[4], [0.0; 3]);
    assert_eq!(grad[7], [0.0; 3]);
    assert!(weight.iter().flatten().any(|&w| w == 0.0) && loss > 0.0);
}

#[test]
fn positions_and_their_vjp_match_autograd() {
    let b = fixture_bytes();
    for format in [Format::HumanMl263, Format::Smpl24Rot6d] {
        let name = format.name();
        let (shape, x) = load(&b, &format!("{name}.x"));
        let frames = shape[0];
        let want_pos = load(&b, &format!("{name}.positions")).1;
        let d_pos = vec3s(&load(&b, &format!("{name}.d_pos")).1);
        let want_dx = load(&b, &format!("{name}.dx")).1;
        let mut pos = vec![[7.0; 3]; 2];
        positions(format, &x, frames, &mut pos).unwrap();
        let d = rel_diff(&pos.concat(), &want_pos);
        assert!(d <= TOL_F64, "{name} positions: {d:e}");
        let mut dx = vec![f64::NAN; x.len()];
        positions_vjp(format, &x, frames, &d_pos, &mut dx).unwrap();
        let d = rel_diff(&dx, &want_dx);
        assert!(d <= TOL_F64, "{name} vjp: {d:e}");
    }
}

#[test]
fn positions_equal_the_motion_decoder() {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    let opts = ReadOptions {
        smooth_sigma: 0.0,
        continuous: false,
        ..Default::default()
    };
    for (format, frames) in [(Format::HumanMl263, 9), (Format::Smpl24Rot6d, 5)] {
        let features = f32s(&rng.vec(frames * format.feature_dim()));
        let x: Vec<f64> = features.iter().map(|&v| v as f64).collect();
        let mut pos = Vec::new();
        positions(format, &x, frames, &mut pos).unwrap();
        let want = Poses::decode(format, &features, frames, &opts)
            .unwrap()
            .positions(Convention::Native);
        let d = rel_diff(&pos.concat(), &want.concat());
        assert!(d <= 1e-12, "{format}: {d:e}");
    }
}

/// `Σ u · positions(x)`, whose gradient is `positions_vjp(x, u)`.
fn weighted_sum(format: Format, x: &[f64], frames: usize, u: &[[f64; 3]]) -> f64 {
    let mut pos = Vec::new();
    positions(format, x, frames, &mut pos).unwrap();
    pos.iter()
        .zip(u)
        .map(|(p, w)| p[0] * w[0] + p[1] * w[1] + p[2] * w[2])
        .sum()
}

#[test]
fn positions_vjp_matches_central_differences() {
    let mut rng = Rng(0x2545_f491_4f6c_dd1d);
    let h = 1e-6;
    for (format, frames) in [(Format::HumanMl263, 7), (Format::Smpl24Rot6d, 3)] {
        let dim = format.feature_dim();
        let joints = format.skeleton().joint_count();
        let x = rng.vec(frames * dim);
        let u = vec3s(&rng.vec(frames * joints * 3));
        let mut dx = vec![0.0; x.len()];
        positions_vjp(format, &x, frames, &u, &mut dx).unwrap();
        let fd = |v: &[f64]| {
            let shifted =
                |s: f64| -> Vec<f64> { x.iter().zip(v).map(|(a, b)| a + s * b).collect() };
            (weighted_sum(format, &shifted(h), frames, &u)
                - weighted_sum(format, &shifted(-h), frames, &u))
                / (2.0 * h)
        };
        // A random direction through every channel at once.
        let v = rng.vec(x.len());
        let (want, got) = (fd(&v), dx.iter().zip(&v).map(|(a, b)| a * b).sum::<f64>());
        assert!(
            (got - want).abs() <= 1e-6 * want.abs().max(1.0),
            "{format} direction: {got} vs {want}"
        );
        // Every channel of the first and the last frame alone.
        for i in (0..dim).chain((frames - 1) * dim..frames * dim) {
            let mut e = vec![0.0; x.len()];
            e[i] = 1.0;
            let want = fd(&e);
            assert!(
                (dx[i] - want).abs() <= 1e-6 * want.abs().max(1.0),
                "{format} frame {} channel {}: {} vs {want}",
                i / dim,
                i % dim,
                dx[i]
            );
        }
        if format == Format::HumanMl263 {
            // Rotations, velocities and contacts do not move the joints; the last frame's root
            // velocities are never integrated.
            assert!(dx
                .chunks_exact(dim)
                .all(|r| r[67..].iter().all(|&g| g == 0.0)));
            assert_eq!(&dx[(frames - 1) * dim..(frames - 1) * dim + 3], &[0.0; 3]);
            assert!(dx[..67].iter().all(|&g| g != 0.0));
        } else {
            // A leaf's rotation (feet, head, hands) turns no bone: its gradient is exactly 0.
            let skel = format.skeleton();
            for (i, &g) in dx.iter().enumerate() {
                let c = i % dim;
                let leaf = c >= 3 && skel.children((c - 3) / 6).next().is_none();
                assert_eq!(g == 0.0, leaf, "channel {c}: {g}");
            }
        }
    }
}

#[test]
fn bad_input_is_an_error() {
    let f = Format::Smpl24Rot6d;
    let x = vec![0.5; 2 * 147];
    let mut pos = Vec::new();
    let msg = |r: flame::Result<()>| r.unwrap_err().to_string();
    assert!(msg(positions(f, &[], 0, &mut pos)).contains("at least one frame"));
    assert!(msg(positions(f, &x[..100], 1, &mut pos)).contains("features hold 100 values"));
    let mut nan = x.clone();
    nan[150] = f64::NAN;
    assert!(msg(positions(f, &nan, 2, &mut pos)).contains("frame 1, channel 3"));
    assert!(msg(positions(f, &x, usize::MAX, &mut pos)).contains("overflow"));
    let d_pos = vec![[1.0; 3]; 48];
    let mut dx = vec![0.0; x.len()];
    assert!(msg(positions_vjp(f, &x, 2, &d_pos[..47], &mut dx)).contains("holds 47 joints"));
    assert!(msg(positions_vjp(f, &x, 2, &d_pos, &mut dx[..3])).contains("holds 3 values"));
    let mut bad = d_pos.clone();
    bad[30][1] = f64::INFINITY;
    assert!(msg(positions_vjp(f, &x, 2, &bad, &mut dx)).contains("frame 1, joint 6"));
    assert!(
        msg(positions_vjp(Format::HumanMl263, &x, 2, &d_pos, &mut dx))
            .contains("humanml263 need 526")
    );
    positions_vjp(f, &x, 2, &d_pos, &mut dx).unwrap();
}
