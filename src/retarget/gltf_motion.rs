//! A motion libflame wrote as glTF (`flame generate --out walk.glb`), read back so that
//! `flame retarget --in walk.glb --rig hero.glb` can carry a motion made earlier onto a
//! character, as it does for libflame's BVH files.
//!
//! What is read is what [`crate::motion::gltf`] writes for `smpl24_6d` poses: the skeleton's
//! joints as nodes named as SMPL-24 names them, one animation whose channels give each joint's
//! rotation and the pelvis's translation (plus the `root` bone's translation when the clip has
//! one: the pelvis's world position is then the sum, the bone has no rotation), in glTF's own
//! axes and metres (libflame's `gltf` convention), sampled at `asset.extras.fps`. A glTF made by
//! another program (a character, a motion on another skeleton) is refused with what is missing:
//! a character goes in `--rig`, and motions on other skeletons are not read.
//! `humanml263` files are refused too: their rotations do not give their joint positions back
//! (see [`crate::motion::gltf`]), so such a motion is retargeted from its `.npy` features.

use serde_json::{Map, Value};

use super::gltf_rig::{container, count, float_accessor, node_name, objects};
use crate::error::{invalid_arg, Result};
use crate::motion::gltf::ROOT_BONE;
use crate::motion::{reference, Convention, Format, Layout, Skeleton};

/// A motion read from a libflame glTF: `smpl24_6d` features in the model's native frame, ready
/// for [`crate::motion::Poses::decode`].
#[derive(Clone, Debug)]
pub struct GltfMotion {
    /// `[frames × 147]` `smpl24_6d` features (native frame).
    pub features: Vec<f32>,
    /// Number of frames.
    pub frames: usize,
    /// Frames per second (the file's `asset.extras.fps`).
    pub fps: f32,
    /// The prompt the file records (`asset.extras.prompt`), if any.
    pub prompt: Option<String>,
}

/// How far a sample time may be from `t / fps` (seconds): `f32` times of a clip of hours.
const TIME_TOLERANCE_S: f64 = 1e-3;

/// Reads a `.glb` or `.gltf` (buffers embedded) that libflame wrote (module doc).
pub fn read(bytes: &[u8]) -> Result<GltfMotion> {
    let (doc, bin) = container(bytes)?;
    let doc = doc
        .as_object()
        .ok_or_else(|| invalid_arg!("glTF: the JSON is not an object"))?;
    let extras = doc
        .get("asset")
        .and_then(|a| a.get("extras"))
        .and_then(Value::as_object);
    let format = extras.and_then(|e| e.get("format")).and_then(Value::as_str);
    match format {
        Some(f) if f == Format::Smpl24Rot6d.name() => {}
        Some(f) if f == Format::HumanMl263.name() => {
            return Err(invalid_arg!(
                "this glTF holds a humanml263 motion, whose rotations do not give its joint \
                 positions back: retarget it from its .npy features (--in x.npy --model M)"
            ))
        }
        Some(f) => {
            return Err(invalid_arg!(
                "this glTF's motion is in format `{f}`; libflame reads back smpl24_6d motions"
            ))
        }
        None => {
            return Err(invalid_arg!(
                "this glTF was not written by libflame (its asset.extras has no `format`): \
                 only libflame's own motions are read back; a character goes in --rig"
            ))
        }
    }
    let fps = extras
        .and_then(|e| e.get("fps"))
        .and_then(Value::as_f64)
        .filter(|f| f.is_finite() && *f > 0.0)
        .ok_or_else(|| {
            invalid_arg!("glTF: asset.extras.fps is missing or not a positive number")
        })?;
    let prompt = extras
        .and_then(|e| e.get("prompt"))
        .and_then(Value::as_str)
        .map(str::to_string);

    // The joints' nodes, by name; each name once.
    let nodes = objects(doc, "nodes", "node")?;
    let skel = Skeleton::smpl24();
    let names = skel.joint_names();
    let find = |name: &str| -> Result<Option<usize>> {
        let mut found = nodes
            .iter()
            .enumerate()
            .filter(|(_, n)| n.get("name").and_then(Value::as_str) == Some(name))
            .map(|(i, _)| i);
        let first = found.next();
        if found.next().is_some() {
            return Err(invalid_arg!("glTF: two nodes are named `{name}`"));
        }
        Ok(first)
    };
    let mut joint_nodes = Vec::with_capacity(names.len());
    for name in names {
        joint_nodes.push(find(name)?.ok_or_else(|| {
            invalid_arg!("glTF: no node is named `{name}` (an SMPL-24 joint libflame writes)")
        })?);
    }
    let bone = find(ROOT_BONE)?;

    // The animation's channels: (node, path) -> sampler.
    let animations = objects(doc, "animations", "animation")?;
    let anim = *animations
        .first()
        .ok_or_else(|| invalid_arg!("glTF: the file has no animation"))?;
    let samplers = objects(anim, "samplers", "animation sampler")?;
    let channels = objects(anim, "channels", "animation channel")?;
    let sampler_of = |node: usize, path: &str| -> Result<Option<&Map<String, Value>>> {
        for (i, c) in channels.iter().enumerate() {
            let what = format!("animation channel {i}");
            let Some(target) = c.get("target").and_then(Value::as_object) else {
                return Err(invalid_arg!("glTF: {what} has no `target`"));
            };
            if target.get("node").and_then(Value::as_u64) != Some(node as u64)
                || target.get("path").and_then(Value::as_str) != Some(path)
            {
                continue;
            }
            let s = count(c, "sampler", None, &what)?;
            return samplers.get(s).copied().map(Some).ok_or_else(|| {
                invalid_arg!(
                    "glTF: {what}'s sampler {s} does not exist (the animation has {})",
                    samplers.len()
                )
            });
        }
        Ok(None)
    };
    let mut frames = None;
    let mut track = |node: usize, path: &str, kind: &str, width: usize| -> Result<Vec<f32>> {
        let label = || format!("the {path} of node `{}`", node_name(&nodes, node));
        let s = sampler_of(node, path)?
            .ok_or_else(|| invalid_arg!("glTF: the animation has no channel for {}", label()))?;
        match s.get("interpolation").and_then(Value::as_str) {
            None | Some("LINEAR") | Some("STEP") => {}
            Some(other) => {
                return Err(invalid_arg!(
                    "glTF: {} is interpolated {other}; libflame writes LINEAR samples",
                    label()
                ))
            }
        }
        let what = format!("the sampler of {}", label());
        let input = count(s, "input", None, &what)?;
        let output = count(s, "output", None, &what)?;
        let times = float_accessor(doc, bin, input, "SCALAR", 1, &format!("{what}'s input"))?;
        match frames {
            None => {
                for (t, &time) in times.iter().enumerate() {
                    if ((time as f64) - t as f64 / fps).abs() > TIME_TOLERANCE_S {
                        return Err(invalid_arg!(
                            "glTF: the animation's sample {t} is at {time} s, not {} s: \
                             libflame reads back motions sampled at asset.extras.fps ({fps})",
                            t as f64 / fps
                        ));
                    }
                }
                frames = Some(times.len());
            }
            Some(n) if n != times.len() => {
                return Err(invalid_arg!(
                    "glTF: {} has {} samples, the other tracks {n}",
                    label(),
                    times.len()
                ))
            }
            Some(_) => {}
        }
        let values = float_accessor(doc, bin, output, kind, width, &format!("{what}'s output"))?;
        if values.len() != times.len() * width {
            return Err(invalid_arg!(
                "glTF: {} has {} values for {} sample times",
                label(),
                values.len() / width,
                times.len()
            ));
        }
        if let Some(k) = values.iter().position(|v| !v.is_finite()) {
            return Err(invalid_arg!(
                "glTF: {} has a NaN or infinite value at sample {}",
                label(),
                k / width
            ));
        }
        Ok(values)
    };

    let mut root = track(joint_nodes[0], "translation", "VEC3", 3)?;
    let rotations: Vec<Vec<f32>> = joint_nodes
        .iter()
        .map(|&n| track(n, "rotation", "VEC4", 4))
        .collect::<Result<_>>()?;
    if let Some(b) = bone {
        let under = track(b, "translation", "VEC3", 3)?;
        for (p, u) in root.iter_mut().zip(&under) {
            *p += u;
        }
    }
    let frames = frames.expect("the root track set it");
    let joints = names.len();
    let mut quats = vec![0.0f32; frames * joints * 4];
    for (j, r) in rotations.iter().enumerate() {
        for t in 0..frames {
            quats[(t * joints + j) * 4..][..4].copy_from_slice(&r[t * 4..t * 4 + 4]);
        }
    }
    let features = reference::smpl24_features(
        &root,
        &quats,
        Layout::LocalQuatXyzw,
        Convention::Gltf,
        frames,
    )?;
    Ok(GltfMotion {
        features,
        frames,
        fps: fps as f32,
        prompt,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::gltf::{self, Container, GltfOptions};
    use crate::motion::{Finish, Poses, ReadOptions, RootMotion};

    /// Features of twelve frames that move every joint and the root.
    fn features() -> Vec<f32> {
        let dim = Format::Smpl24Rot6d.feature_dim();
        (0..12 * dim)
            .map(|i| {
                let (t, k) = ((i / dim) as f32, (i % dim) as f32);
                0.3 * (0.37 * k + 0.21 * t).sin() + if k % 6.0 == 0.0 { 1.0 } else { 0.0 }
            })
            .collect()
    }

    fn decode(x: &[f32], root_motion: RootMotion) -> Poses {
        let opts = ReadOptions {
            finish: Finish {
                root_motion,
                ..Default::default()
            },
            ..Default::default()
        };
        Poses::decode(
            Format::Smpl24Rot6d,
            x,
            x.len() / Format::Smpl24Rot6d.feature_dim(),
            &opts,
        )
        .unwrap()
    }

    fn worst(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(b)
            .flat_map(|(p, q)| (0..3).map(move |k| (p[k] - q[k]).abs()))
            .fold(0.0, f64::max)
    }

    #[test]
    fn a_written_clip_reads_back_to_its_poses() {
        // Written, read, decoded again: every joint's world position and local rotation as
        // before, to f32 rounding, in two conventions; with and without a root bone (whose
        // ground track is added back to the pelvis); .glb and .gltf.
        let x = features();
        let keep = decode(&x, RootMotion::Keep);
        let opts = GltfOptions {
            fps: 30.0,
            prompt: Some("a test"),
            ..Default::default()
        };
        for root_motion in [RootMotion::Keep, RootMotion::Separate] {
            let written = decode(&x, root_motion);
            for container in [Container::Glb, Container::Gltf] {
                let bytes = gltf::to_bytes(&written, &opts, container).unwrap();
                let m = read(&bytes).unwrap();
                assert_eq!((m.frames, m.fps), (12, 30.0));
                assert_eq!(m.prompt.as_deref(), Some("a test"));
                let back = decode(&m.features, RootMotion::Keep);
                for c in [Convention::Native, Convention::Gltf, Convention::Unreal] {
                    let d = worst(&keep.positions(c), &back.positions(c));
                    assert!(d < 1e-5, "{root_motion:?} {container:?} positions {c}: {d}");
                    let (a, b) = (keep.local_rotations(c), back.local_rotations(c));
                    let d = a
                        .iter()
                        .zip(&b)
                        .flat_map(|(p, q)| p.iter().flatten().zip(q.iter().flatten()))
                        .map(|(u, v)| (u - v).abs())
                        .fold(0.0, f64::max);
                    assert!(d < 1e-5, "{root_motion:?} {container:?} rotations {c}: {d}");
                }
            }
        }
    }

    fn doc_and_bin(bytes: &[u8]) -> (Value, Vec<u8>) {
        let (doc, bin) = container(bytes).unwrap();
        (doc, bin.unwrap().to_vec())
    }

    fn glb(doc: &Value, bin: &[u8]) -> Vec<u8> {
        let mut json = serde_json::to_vec(doc).unwrap();
        json.resize(json.len().div_ceil(4) * 4, b' ');
        let total = 12 + 8 + json.len() + 8 + bin.len();
        let mut out = Vec::with_capacity(total);
        out.extend_from_slice(b"glTF");
        out.extend_from_slice(&2u32.to_le_bytes());
        out.extend_from_slice(&(total as u32).to_le_bytes());
        out.extend_from_slice(&(json.len() as u32).to_le_bytes());
        out.extend_from_slice(b"JSON");
        out.extend_from_slice(&json);
        out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
        out.extend_from_slice(b"BIN\0");
        out.extend_from_slice(bin);
        out
    }

    #[test]
    fn files_that_are_not_libflame_motions_are_clear_errors() {
        let x = features();
        let bytes = gltf::to_bytes(
            &decode(&x, RootMotion::Keep),
            &GltfOptions::default(),
            Container::Glb,
        )
        .unwrap();
        let (doc, bin) = doc_and_bin(&bytes);
        let err = |edit: &dyn Fn(&mut Value, &mut Vec<u8>)| {
            let (mut d, mut b) = (doc.clone(), bin.clone());
            edit(&mut d, &mut b);
            read(&glb(&d, &b)).unwrap_err().to_string()
        };
        let e = err(&|d, _| {
            d["asset"]
                .as_object_mut()
                .unwrap()
                .remove("extras")
                .map(drop)
                .unwrap()
        });
        assert!(e.contains("not written by libflame"), "{e}");
        let e = err(&|d, _| d["asset"]["extras"]["format"] = "humanml263".into());
        assert!(e.contains(".npy features"), "{e}");
        let e = err(&|d, _| d["asset"]["extras"]["fps"] = (-3.0).into());
        assert!(e.contains("fps"), "{e}");
        let e = err(&|d, _| d["nodes"][5]["name"] = "knee".into());
        assert!(e.contains("no node is named"), "{e}");
        let e = err(&|d, _| {
            let twin = serde_json::json!({ "name": d["nodes"][7]["name"].clone() });
            d["nodes"].as_array_mut().unwrap().push(twin)
        });
        assert!(e.contains("two nodes are named"), "{e}");
        let e = err(&|d, _| {
            d.as_object_mut()
                .unwrap()
                .remove("animations")
                .map(drop)
                .unwrap()
        });
        assert!(e.contains("no animation"), "{e}");
        let e = err(&|d, _| d["animations"][0]["channels"][3]["target"]["path"] = "scale".into());
        assert!(e.contains("no channel for the rotation"), "{e}");
        let e =
            err(&|d, _| d["animations"][0]["samplers"][0]["interpolation"] = "CUBICSPLINE".into());
        assert!(e.contains("CUBICSPLINE"), "{e}");
        let e = err(&|d, _| d["animations"][0]["channels"][0]["sampler"] = 999.into());
        assert!(e.contains("sampler 999 does not exist"), "{e}");
        // A NaN in a rotation track.
        let e = err(&|d, b| {
            let out = d["animations"][0]["samplers"][2]["output"]
                .as_u64()
                .unwrap() as usize;
            let view = d["accessors"][out]["bufferView"].as_u64().unwrap() as usize;
            let at = d["bufferViews"][view]["byteOffset"].as_u64().unwrap_or(0) as usize;
            b[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
        });
        assert!(e.contains("NaN"), "{e}");
        // Samples not at the declared rate.
        let e = err(&|d, _| d["asset"]["extras"]["fps"] = 7.0.into());
        assert!(e.contains("sampled at asset.extras.fps"), "{e}");
        // Truncated at every length: an error, never a panic.
        for n in (0..bytes.len()).step_by(97) {
            assert!(read(&bytes[..n]).is_err());
        }
    }
}
