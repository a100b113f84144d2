//! BVH and JSON exports read back: a small BVH reader here (any channel order) poses the written
//! hierarchy and must give libflame's joint positions; the JSON's skeleton and quaternions must
//! do the same. Motion: tests/fixtures/motion_reference.safetensors (tools/motion_reference.py),
//! a walk with root travel and turning.
//!
//! `write_blender_check_files` (ignored) writes the files tools/bvh_roundtrip.sh hands to a real
//! consumer (Blender, or the `bvh` PyPI package): run it with FLAME_BVH_OUT=DIR.

use std::path::Path;

use flame::checkpoint::ModelFile;
use flame::motion::rotation::{self, Mat3, Vec3};
use flame::motion::skeleton::forward_kinematics;
use flame::motion::{
    bvh, json, rest_offsets, Convention, Format, Normalization, Poses, QuatOrder, ReadOptions,
};

fn fixture() -> ModelFile {
    ModelFile::open(
        &Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/motion_reference.safetensors"),
    )
    .unwrap()
}

fn walk(format: Format) -> Poses {
    let fx = fixture();
    let get = |n: &str| fx.tensor_any_shape(n).unwrap().data().to_vec();
    match format {
        Format::Smpl24Rot6d => {
            let f = get("smpl_features");
            Poses::decode(
                format,
                &f,
                f.len() / 147,
                &ReadOptions {
                    smooth_sigma: 1.0,
                    ..Default::default()
                },
            )
            .unwrap()
        }
        Format::HumanMl263 => {
            let (f, mean, std) = (get("hml_features"), get("hml_mean"), get("hml_std"));
            let norm = Some(Normalization {
                mean: &mean,
                std: &std,
            });
            Poses::decode(
                format,
                &f,
                f.len() / 263,
                &ReadOptions {
                    normalization: norm,
                    ..Default::default()
                },
            )
            .unwrap()
        }
    }
}

/// `[frames × joints]` positions of the rest skeleton posed by the local rotations: what any
/// hierarchy consumer (BVH, JSON) reproduces. For smpl24_6d it equals `Poses::positions`.
fn hierarchy_positions(poses: &Poses, c: Convention) -> Vec<Vec3> {
    let format = poses.format();
    let offsets: Vec<Vec3> = rest_offsets(format, c)
        .chunks(3)
        .map(|o| [o[0] as f64, o[1] as f64, o[2] as f64])
        .collect();
    let j = poses.joint_count();
    let local = poses.local_rotations(c);
    let root = poses.root_translation(c);
    let mut out = vec![[0.0; 3]; poses.frames() * j];
    let mut world = vec![rotation::IDENTITY; j];
    for t in 0..poses.frames() {
        let parents = format.skeleton().parents();
        forward_kinematics(
            parents,
            &offsets,
            &root[t],
            &local[t * j..(t + 1) * j],
            &mut out[t * j..(t + 1) * j],
            &mut world,
        )
        .unwrap();
    }
    out
}

/// A parsed BVH: joints in file order with parent, offset and channel names, plus frames.
struct Bvh {
    names: Vec<String>,
    parents: Vec<Option<usize>>,
    offsets: Vec<Vec3>,
    channels: Vec<Vec<String>>,
    frame_time: f64,
    frames: Vec<Vec<f64>>,
}

fn parse_bvh(text: &str) -> Bvh {
    let mut b = Bvh {
        names: vec![],
        parents: vec![],
        offsets: vec![],
        channels: vec![],
        frame_time: 0.0,
        frames: vec![],
    };
    let mut stack: Vec<Option<usize>> = vec![];
    let mut in_end = false;
    let mut lines = text.lines();
    for line in lines.by_ref() {
        let w: Vec<&str> = line.split_whitespace().collect();
        match w.first().copied() {
            Some("ROOT") | Some("JOINT") => {
                b.names.push(w[1].to_string());
                b.parents.push(stack.iter().rev().find_map(|x| *x));
                b.offsets.push([0.0; 3]);
                b.channels.push(vec![]);
            }
            Some("End") => in_end = true,
            Some("{") => stack.push(if in_end {
                None
            } else {
                Some(b.names.len() - 1)
            }),
            // Closing an End Site block (pushed as None) ends it.
            Some("}") => in_end &= stack.pop() != Some(None),
            Some("OFFSET") if !in_end => {
                let v: Vec<f64> = w[1..4].iter().map(|x| x.parse().unwrap()).collect();
                *b.offsets.last_mut().unwrap() = [v[0], v[1], v[2]];
            }
            Some("CHANNELS") => {
                *b.channels.last_mut().unwrap() = w[2..].iter().map(|s| s.to_string()).collect()
            }
            Some("MOTION") => break,
            _ => {}
        }
    }
    let _frames = lines.next().unwrap();
    b.frame_time = lines
        .next()
        .unwrap()
        .split(':')
        .nth(1)
        .unwrap()
        .trim()
        .parse()
        .unwrap();
    b.frames = lines
        .filter(|l| !l.trim().is_empty())
        .map(|l| l.split_whitespace().map(|x| x.parse().unwrap()).collect())
        .collect();
    b
}

/// World joint positions `[frames][file-order joints]` of a parsed BVH, by the usual reading:
/// rotation channels compose in the listed order, the root's position channels are absolute
/// plus its OFFSET.
fn bvh_positions(b: &Bvh) -> Vec<Vec<Vec3>> {
    let axis = |c: &str| match &c[..1] {
        "X" => [1.0, 0.0, 0.0],
        "Y" => [0.0, 1.0, 0.0],
        _ => [0.0, 0.0, 1.0],
    };
    b.frames
        .iter()
        .map(|values| {
            let mut k = 0;
            let mut world: Vec<Mat3> = vec![];
            let mut pos: Vec<Vec3> = vec![];
            for j in 0..b.names.len() {
                let mut r = rotation::IDENTITY;
                let mut p = b.offsets[j];
                for c in &b.channels[j] {
                    let v = values[k];
                    k += 1;
                    if c.ends_with("rotation") {
                        r = rotation::mul(&r, &rotation::axis_angle(&axis(c), v.to_radians()));
                    } else {
                        p[(axis(c).iter().position(|&x| x == 1.0)).unwrap()] += v;
                    }
                }
                match b.parents[j] {
                    Some(pa) => {
                        pos.push(rotation::add(&pos[pa], &rotation::apply(&world[pa], &p)));
                        world.push(rotation::mul(&world[pa], &r));
                    }
                    None => {
                        pos.push(p);
                        world.push(r);
                    }
                }
            }
            pos
        })
        .collect()
}

fn max_error(poses: &Poses, c: Convention, text: &str, want: &[Vec3]) -> f64 {
    let b = parse_bvh(text);
    let names = poses.format().skeleton().joint_names();
    let j = poses.joint_count();
    assert_eq!(b.names.len(), j);
    assert_eq!(b.frames.len(), poses.frames());
    let got = bvh_positions(&b);
    let mut err: f64 = 0.0;
    for (t, frame) in got.iter().enumerate() {
        for (k, p) in frame.iter().enumerate() {
            let idx = names.iter().position(|n| *n == b.names[k]).unwrap();
            let w = &want[t * j + idx];
            err = err.max((0..3).map(|i| (p[i] - w[i]).abs()).fold(0.0, f64::max));
        }
    }
    let _ = c;
    err
}

#[test]
fn bvh_reproduces_libflame_positions_in_every_convention() {
    for format in Format::ALL {
        let poses = walk(format);
        for c in Convention::ALL {
            let text = bvh::to_string(&poses, c, 20.0).unwrap();
            assert!(text.contains("Frame Time: 0.050000"));
            let want = hierarchy_positions(&poses, c);
            let err = max_error(&poses, c, &text, &want);
            // 6 decimals in the file: 1e-6 m (or cm) per value, accumulated along a chain.
            let scale = c.frame(format).unit.scale();
            println!("{format} {c}: BVH vs FK max error {:.2e} m", err / scale);
            assert!(err / scale < 2e-5, "{format} {c}: {err}");
            if format == Format::Smpl24Rot6d {
                // SMPL's FK is the definition of its positions: the BVH gives them exactly.
                let exact = poses.positions(c);
                let e2 = max_error(&poses, c, &text, &exact);
                assert!(e2 / scale < 2e-5, "{c}: {e2}");
            }
        }
    }
}

#[test]
fn bvh_declares_hierarchy_channels_and_end_sites() {
    let poses = walk(Format::Smpl24Rot6d);
    let text = bvh::to_string(&poses, Convention::Gltf, 30.0).unwrap();
    assert!(text.starts_with("HIERARCHY\nROOT Pelvis\n{\n\tOFFSET 0.000000 0.000000 0.000000\n\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n"));
    assert_eq!(
        text.matches("CHANNELS 3 Zrotation Xrotation Yrotation")
            .count(),
        23
    );
    assert_eq!(text.matches("End Site").count(), 5); // feet, head, hands
    assert!(text.contains("Frames: 36\nFrame Time: 0.033333\n"));
    assert!(bvh::to_string(&poses, Convention::Gltf, 0.0).is_err());
    let empty = Poses::decode(Format::Smpl24Rot6d, &[], 0, &ReadOptions::default()).unwrap();
    assert!(bvh::to_string(&empty, Convention::Gltf, 20.0).is_err());
}

#[test]
fn joint_index_order_is_the_hierarchy_breadth_first_order() {
    // tools/blender_bvh_check.py and tools/bvh_pypi_check.py rely on it to map BVH joints back to
    // libflame's joint order without a name table.
    for format in Format::ALL {
        let skel = format.skeleton();
        let mut order = vec![0usize];
        let mut i = 0;
        while i < order.len() {
            order.extend(skel.children(order[i]));
            i += 1;
        }
        assert_eq!(
            order,
            (0..skel.joint_count()).collect::<Vec<_>>(),
            "{format}"
        );
    }
}

#[test]
fn json_carries_a_skeleton_that_reproduces_the_poses() {
    for format in Format::ALL {
        let poses = walk(format);
        for (c, order) in [
            (Convention::Unity, QuatOrder::Xyzw),
            (Convention::Native, QuatOrder::Wxyz),
        ] {
            let text = json::to_string(&poses, c, 20.0, order).unwrap();
            let v: serde_json::Value = serde_json::from_str(&text).unwrap();
            assert_eq!(v["format"], format.name());
            assert_eq!(v["convention"], c.name());
            assert_eq!(v["rotation_quat_order"], order.name());
            assert_eq!(v["frames"], poses.frames());
            assert_eq!(v["fps"], 20.0);
            let j = poses.joint_count();
            assert_eq!(v["joint_names"].as_array().unwrap().len(), j);
            assert_eq!(v["foot_contacts"].is_array(), format.has_foot_contacts());
            if c == Convention::Unity {
                assert_eq!(
                    (
                        v["handedness"].as_str(),
                        v["up"].as_str(),
                        v["unit"].as_str()
                    ),
                    (Some("left"), Some("+y"), Some("m"))
                );
            }
            let f = |x: &serde_json::Value| x.as_f64().unwrap();
            let parents: Vec<i32> = v["parents"]
                .as_array()
                .unwrap()
                .iter()
                .map(|p| p.as_i64().unwrap() as i32)
                .collect();
            let offsets: Vec<Vec3> = v["offsets"]
                .as_array()
                .unwrap()
                .iter()
                .map(|o| [f(&o[0]), f(&o[1]), f(&o[2])])
                .collect();
            let want = hierarchy_positions(&poses, c);
            let mut err: f64 = 0.0;
            for t in 0..poses.frames() {
                let tr = &v["translation"][t];
                let local: Vec<Mat3> = (0..j)
                    .map(|k| {
                        let q = &v["rotation_quat"][t][k];
                        let q = [f(&q[0]), f(&q[1]), f(&q[2]), f(&q[3])];
                        let wxyz = if order == QuatOrder::Xyzw {
                            [q[3], q[0], q[1], q[2]]
                        } else {
                            q
                        };
                        rotation::quat_to_matrix(&wxyz)
                    })
                    .collect();
                let (mut p, mut w) = (vec![[0.0; 3]; j], vec![rotation::IDENTITY; j]);
                forward_kinematics(
                    &parents,
                    &offsets,
                    &[f(&tr[0]), f(&tr[1]), f(&tr[2])],
                    &local,
                    &mut p,
                    &mut w,
                )
                .unwrap();
                for k in 0..j {
                    err = err.max(
                        (0..3)
                            .map(|i| (p[k][i] - want[t * j + k][i]).abs())
                            .fold(0.0, f64::max),
                    );
                }
            }
            println!("{format} {c} JSON vs FK max error {err:.2e}");
            assert!(err < 1e-5, "{format} {c}: {err}");
        }
    }
}

/// Writes, into $FLAME_BVH_OUT, `{smpl,hml}_walk.bvh` (convention gltf: Y up, the axes Blender's
/// BVH importer assumes by default) and `{smpl,hml}_walk_blender.npy` (frames × joints × 3, f32:
/// the positions the hierarchy gives, in convention blender — what the importer's default Y-up →
/// Z-up axis conversion must produce). Also `cli_walk.bvh`, what `flame generate --out x.bvh`
/// writes WITHOUT `--convention` (model: $FLAME_BVH_MODEL, default the tiny fixture), and its
/// `cli_walk_blender.npy`, computed here from the same generation's raw features.
#[test]
#[ignore = "writes files for tools/bvh_roundtrip.sh"]
fn write_blender_check_files() {
    let dir = std::env::var("FLAME_BVH_OUT").expect("set FLAME_BVH_OUT to a directory");
    write_cli_check_files(Path::new(&dir));
    for (format, name) in [
        (Format::Smpl24Rot6d, "smpl_walk"),
        (Format::HumanMl263, "hml_walk"),
    ] {
        let poses = walk(format);
        let text = bvh::to_string(&poses, Convention::Gltf, format.fps()).unwrap();
        std::fs::write(Path::new(&dir).join(format!("{name}.bvh")), text).unwrap();
        let p: Vec<f32> = hierarchy_positions(&poses, Convention::Blender)
            .concat()
            .iter()
            .map(|&x| x as f32)
            .collect();
        let shape = [poses.frames(), poses.joint_count(), 3];
        flame::npy::write_f32(
            &Path::new(&dir).join(format!("{name}_blender.npy")),
            &shape,
            &p,
        )
        .unwrap();
    }
}

/// `cli_walk.bvh` from the CLI's default convention and the Blender-frame positions the same
/// features must give (decoded as the CLI decodes them: the model's normalisation, FLAME's
/// default smoothing of 1 frame for smpl24_6d).
fn write_cli_check_files(dir: &Path) {
    let model = std::env::var("FLAME_BVH_MODEL")
        .ok()
        .filter(|m| !m.is_empty())
        .unwrap_or_else(|| {
            let p =
                Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/flame_tiny.safetensors");
            p.display().to_string()
        });
    let run = |out: &Path| {
        let o = std::process::Command::new(env!("CARGO_BIN_EXE_flame"))
            .args([
                "generate",
                "--model",
                &model,
                "--prompt",
                "a person walks forward.",
            ])
            .args(["--frames", "60", "--seed", "1", "--out"])
            .arg(out)
            .output()
            .unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    };
    let (bvh_path, npy) = (dir.join("cli_walk.bvh"), dir.join("cli_walk_features.npy"));
    run(&bvh_path);
    run(&npy);
    let m = flame::models::Model::load(&model).unwrap();
    let (shape, x) = flame::npy::read_f32(&npy).unwrap();
    let format = m.motion_format();
    let smooth = if format == Format::Smpl24Rot6d {
        1.0
    } else {
        0.0
    };
    // The CLI's default BVH is game-ready: feet locked, floor at 0, the model's frame rate.
    let opts = flame::motion::ReadOptions {
        finish: flame::motion::Finish::game_ready(),
        ..m.read_options(smooth, true)
    };
    let poses = Poses::decode(format, &x, shape[0], &opts).unwrap();
    let p: Vec<f32> = hierarchy_positions(&poses, Convention::Blender)
        .concat()
        .iter()
        .map(|&v| v as f32)
        .collect();
    let shape = [poses.frames(), poses.joint_count(), 3];
    flame::npy::write_f32(&dir.join("cli_walk_blender.npy"), &shape, &p).unwrap();
}
