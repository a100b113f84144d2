//! Retargeted files read back independently of libflame's rig code: `gltf_out::write` on a rig
//! file with a Blender/Mixamo-style `Armature` node (90° about X, scale 0.01) and a non-joint
//! node between two joints, and on the VRM avatar fixture (`tests/fixtures/rigs/avatar.vrm`,
//! written by tools/make_vrm_avatar.py): the node hierarchy of the written file, posed by its
//! own TRS and animation samples (forward kinematics done here, from the JSON), puts every joint
//! where the motion says; the original's bytes and JSON values are kept; writing again is
//! idempotent; bad input is refused. The ignored `write_vrma_check_files` writes the files the
//! three-vrm check compares (tools/vrma_check.sh).

use flame::motion::rotation::{self, Mat3, Vec3};
use flame::motion::{Format, Poses, ReadOptions, Skeleton};
use flame::retarget::bonemap::HumanBone;
use flame::retarget::{gltf_out, gltf_rig, vrma, Options, RigMotion, Target};
use serde_json::{json, Value};

const AVATAR: &str = concat!(
    env!("CARGO_MANIFEST_DIR"),
    "/tests/fixtures/rigs/avatar.vrm"
);

/// A smooth synthetic clip: every smpl24_6d feature a different sinusoid of time (rotations from
/// arbitrary 6D vectors, a drifting root), decoded raw.
fn sinusoid_motion(frames: usize) -> Poses {
    let format = Format::Smpl24Rot6d;
    let dim = format.feature_dim();
    let x: Vec<f32> = (0..frames * dim)
        .map(|i| {
            let (t, c) = ((i / dim) as f32, (i % dim) as f32);
            (0.3 * c + 0.05 * t * (1.0 + c % 3.0)).sin() * 0.8
                + if c % 6.0 == 0.0 { 0.5 } else { 0.0 }
        })
        .collect();
    Poses::decode(format, &x, frames, &ReadOptions::default()).unwrap()
}

// --- Small affine algebra of the test's own (4×4 as a 3×3 linear part and a translation) ---

#[derive(Clone, Copy, Debug)]
struct Affine {
    l: Mat3,
    t: Vec3,
}

fn mat_mul(a: &Mat3, b: &Mat3) -> Mat3 {
    let mut m = [[0.0; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            m[i][j] = (0..3).map(|k| a[i][k] * b[k][j]).sum();
        }
    }
    m
}

fn mat_vec(a: &Mat3, v: &Vec3) -> Vec3 {
    [0, 1, 2].map(|i| (0..3).map(|k| a[i][k] * v[k]).sum())
}

fn transpose(a: &Mat3) -> Mat3 {
    [0, 1, 2].map(|i| [0, 1, 2].map(|j| a[j][i]))
}

impl Affine {
    fn then(&self, c: &Affine) -> Affine {
        let t = mat_vec(&self.l, &c.t);
        Affine {
            l: mat_mul(&self.l, &c.l),
            t: [0, 1, 2].map(|i| self.t[i] + t[i]),
        }
    }

    /// The inverse of a rotation times a uniform scale `s`, plus a translation.
    fn inverse_similarity(&self, s: f64) -> Affine {
        let l = transpose(&self.l).map(|r| r.map(|v| v / (s * s)));
        let t = mat_vec(&l, &self.t).map(|v| -v);
        Affine { l, t }
    }
}

/// glTF's `x, y, z, w` quaternion as a matrix (unit-normalised first).
fn quat_xyzw(q: &[f64]) -> Mat3 {
    let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    let (x, y, z, w) = (q[0] / n, q[1] / n, q[2] / n, q[3] / n);
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

/// A rotation matrix as `x, y, z, w` (Shepperd's method).
fn to_xyzw(m: &Mat3) -> [f64; 4] {
    let tr = m[0][0] + m[1][1] + m[2][2];
    let q = if tr > 0.0 {
        let s = (tr + 1.0).sqrt() * 2.0;
        [
            (m[2][1] - m[1][2]) / s,
            (m[0][2] - m[2][0]) / s,
            (m[1][0] - m[0][1]) / s,
            0.25 * s,
        ]
    } else if m[0][0] > m[1][1] && m[0][0] > m[2][2] {
        let s = (1.0 + m[0][0] - m[1][1] - m[2][2]).sqrt() * 2.0;
        [
            0.25 * s,
            (m[0][1] + m[1][0]) / s,
            (m[0][2] + m[2][0]) / s,
            (m[2][1] - m[1][2]) / s,
        ]
    } else if m[1][1] > m[2][2] {
        let s = (1.0 + m[1][1] - m[0][0] - m[2][2]).sqrt() * 2.0;
        [
            (m[0][1] + m[1][0]) / s,
            0.25 * s,
            (m[1][2] + m[2][1]) / s,
            (m[0][2] - m[2][0]) / s,
        ]
    } else {
        let s = (1.0 + m[2][2] - m[0][0] - m[1][1]).sqrt() * 2.0;
        [
            (m[0][2] + m[2][0]) / s,
            (m[1][2] + m[2][1]) / s,
            0.25 * s,
            (m[1][0] - m[0][1]) / s,
        ]
    };
    if q[3] < 0.0 {
        q.map(|v| -v)
    } else {
        q
    }
}

fn axis_angle(axis: Vec3, angle: f64) -> Mat3 {
    let n = axis.iter().map(|v| v * v).sum::<f64>().sqrt();
    let h = angle / 2.0;
    let s = h.sin() / n;
    quat_xyzw(&[axis[0] * s, axis[1] * s, axis[2] * s, h.cos()])
}

// --- A rig file of the test's own ---

/// SMPL's first 22 joints under Mixamo's names (BoneMap::auto maps them).
const MIXAMO: [&str; 22] = [
    "mixamorig:Hips",
    "mixamorig:LeftUpLeg",
    "mixamorig:RightUpLeg",
    "mixamorig:Spine",
    "mixamorig:LeftLeg",
    "mixamorig:RightLeg",
    "mixamorig:Spine1",
    "mixamorig:LeftFoot",
    "mixamorig:RightFoot",
    "mixamorig:Spine2",
    "mixamorig:LeftToeBase",
    "mixamorig:RightToeBase",
    "mixamorig:Neck",
    "mixamorig:LeftShoulder",
    "mixamorig:RightShoulder",
    "mixamorig:Head",
    "mixamorig:LeftArm",
    "mixamorig:RightArm",
    "mixamorig:LeftForeArm",
    "mixamorig:RightForeArm",
    "mixamorig:LeftHand",
    "mixamorig:RightHand",
];

/// The joint the non-joint node `spine_socket` sits above (SMPL's spine3 under spine2).
const SOCKET_CHILD: usize = 9;

/// A skinned-skeleton glTF file like a Blender export of a Mixamo character: node 0 `Armature`
/// (rotation 90° about X, scale 0.01: the joints below are in centimetres, Z up), then the 22
/// joints at SMPL's rest positions (world, metres, Y up) with a different world rest rotation
/// each, and a non-joint node `spine_socket` (translated, rotated) between spine2 and spine3.
/// Inverse bind matrices of that rest pose, an idle animation, an extension and extras of the
/// user's own. `glb`: the binary container, else JSON with a data-URI buffer.
fn rig_file(glb: bool) -> Vec<u8> {
    let skel = Skeleton::smpl24();
    let mut pos = vec![[0.0, 0.95, 0.0]; 22];
    for j in 1..22 {
        let p = skel.parent(j).unwrap();
        let o = skel.rest_offsets()[j];
        pos[j] = [0, 1, 2].map(|k| pos[p][k] + o[k]);
    }
    let world_rot: Vec<Mat3> = (0..22)
        .map(|j| {
            let a = j as f64;
            axis_angle([0.3 + a, 1.0 - 0.2 * a, 0.5], 0.4 + 0.13 * a)
        })
        .collect();
    let cm = 0.01;
    let armature = Affine {
        l: axis_angle([1.0, 0.0, 0.0], std::f64::consts::FRAC_PI_2).map(|r| r.map(|v| v * cm)),
        t: [0.0; 3],
    };
    let joint_world = |j: usize| Affine {
        l: world_rot[j].map(|r| r.map(|v| v * cm)),
        t: pos[j],
    };
    // The socket: 40% of the way from spine2 to spine3, turned its own way.
    let parent_of_socket = skel.parent(SOCKET_CHILD).unwrap();
    let socket = Affine {
        l: axis_angle([0.2, 0.1, 1.0], 0.7).map(|r| r.map(|v| v * cm)),
        t: [0, 1, 2].map(|k| 0.6 * pos[parent_of_socket][k] + 0.4 * pos[SOCKET_CHILD][k]),
    };
    // Node i + 1 is joint i; node 23 the socket; node 0 the armature.
    let world_of = |n: usize| match n {
        0 => armature,
        23 => socket,
        j => joint_world(j - 1),
    };
    let parent_node = |n: usize| -> Option<usize> {
        match n {
            0 => None,
            23 => Some(1 + parent_of_socket),
            1 => Some(0),
            j if j - 1 == SOCKET_CHILD => Some(23),
            j => Some(1 + skel.parent(j - 1).unwrap()),
        }
    };
    let mut nodes = Vec::new();
    for n in 0..24 {
        let w = world_of(n);
        let local = match parent_node(n) {
            None => w,
            Some(p) => world_of(p).inverse_similarity(cm).then(&w),
        };
        // Uniform scale: the linear part's column length.
        let s = (0..3)
            .map(|k| local.l[k][0] * local.l[k][0])
            .sum::<f64>()
            .sqrt();
        let r = local.l.map(|row| row.map(|v| v / s));
        let mut node = json!({
            "name": match n { 0 => "Armature", 23 => "spine_socket", j => MIXAMO[j - 1] },
            "translation": local.t,
            "rotation": to_xyzw(&r),
        });
        if (s - 1.0).abs() > 1e-9 {
            node["scale"] = json!([s, s, s]);
        }
        let children: Vec<usize> = (1..24).filter(|&c| parent_node(c) == Some(n)).collect();
        if !children.is_empty() {
            node["children"] = json!(children);
        }
        nodes.push(node);
    }
    // Inverse bind matrices (column-major f32), then an idle track: the hips turning a little.
    let mut bin: Vec<u8> = Vec::new();
    for j in 0..22 {
        let inv = joint_world(j).inverse_similarity(cm);
        let mut m = [0.0f32; 16];
        for c in 0..3 {
            for r in 0..3 {
                m[c * 4 + r] = inv.l[r][c] as f32;
            }
            m[12 + c] = inv.t[c] as f32;
        }
        m[15] = 1.0;
        bin.extend(m.iter().flat_map(|v| v.to_le_bytes()));
    }
    let ibm_len = bin.len();
    let hips_rot = nodes[1]["rotation"].clone();
    for t in [0.0f32, 1.0] {
        bin.extend(t.to_le_bytes());
    }
    for k in 0..2 {
        let q: Vec<f64> = (0..4)
            .map(|i| hips_rot[i].as_f64().unwrap() + 0.01 * k as f64)
            .collect();
        let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
        bin.extend(q.iter().flat_map(|v| ((v / n) as f32).to_le_bytes()));
    }
    // An odd length: libflame's data must start on the next 4-byte boundary.
    bin.push(7);
    let mut doc = json!({
        "asset": { "version": "2.0", "generator": "retarget_files test", "extras": { "artist": "me" } },
        "extensionsUsed": ["KHR_materials_unlit"],
        "scene": 0,
        "scenes": [{ "nodes": [0] }],
        "nodes": nodes,
        "skins": [{ "name": "Armature", "joints": (1..23).collect::<Vec<_>>(), "inverseBindMatrices": 0, "skeleton": 0 }],
        "materials": [{ "name": "skin", "extensions": { "KHR_materials_unlit": {} } }],
        "bufferViews": [
            { "buffer": 0, "byteOffset": 0, "byteLength": ibm_len },
            { "buffer": 0, "byteOffset": ibm_len, "byteLength": 8 },
            { "buffer": 0, "byteOffset": ibm_len + 8, "byteLength": 32 },
        ],
        "accessors": [
            { "bufferView": 0, "componentType": 5126, "count": 22, "type": "MAT4" },
            { "bufferView": 1, "componentType": 5126, "count": 2, "type": "SCALAR", "min": [0.0], "max": [1.0] },
            { "bufferView": 2, "componentType": 5126, "count": 2, "type": "VEC4" },
        ],
        "animations": [{
            "name": "Idle",
            "samplers": [{ "input": 1, "output": 2 }],
            "channels": [{ "sampler": 0, "target": { "node": 1, "path": "rotation" } }],
        }],
        "buffers": [{ "byteLength": bin.len() }],
        "extras": { "note": "kept as it is" },
    });
    if glb {
        glb_bytes(&doc, &bin)
    } else {
        use base64::Engine as _;
        doc["buffers"][0]["uri"] = json!(format!(
            "data:application/gltf-buffer;base64,{}",
            base64::engine::general_purpose::STANDARD.encode(&bin)
        ));
        serde_json::to_vec_pretty(&doc).unwrap()
    }
}

fn glb_bytes(doc: &Value, bin: &[u8]) -> Vec<u8> {
    let mut text = serde_json::to_vec(doc).unwrap();
    while !text.len().is_multiple_of(4) {
        text.push(b' ');
    }
    let mut bin = bin.to_vec();
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let mut out = b"glTF".to_vec();
    out.extend(2u32.to_le_bytes());
    out.extend(((12 + 8 + text.len() + 8 + bin.len()) as u32).to_le_bytes());
    out.extend((text.len() as u32).to_le_bytes());
    out.extend(b"JSON");
    out.extend(&text);
    out.extend((bin.len() as u32).to_le_bytes());
    out.extend(b"BIN\0");
    out.extend(&bin);
    out
}

/// A file's JSON and its buffer 0's bytes (`byteLength` of them), either container.
fn split(file: &[u8]) -> (Value, Vec<u8>) {
    if file.starts_with(b"glTF") {
        let word = |o: usize| u32::from_le_bytes(file[o..o + 4].try_into().unwrap()) as usize;
        assert_eq!(word(8), file.len());
        let jlen = word(12);
        assert_eq!(&file[16..20], b"JSON");
        let doc: Value = serde_json::from_slice(&file[20..20 + jlen]).unwrap();
        let b = 20 + jlen;
        assert_eq!(&file[b + 4..b + 8], b"BIN\0");
        let blen = word(b);
        assert_eq!(blen % 4, 0);
        let declared = doc["buffers"][0]["byteLength"].as_u64().unwrap() as usize;
        assert!(declared <= blen && blen - declared < 4);
        (doc, file[b + 8..b + 8 + declared].to_vec())
    } else {
        use base64::Engine as _;
        let doc: Value = serde_json::from_slice(file).unwrap();
        let uri = doc["buffers"][0]["uri"].as_str().unwrap();
        let data = uri.split_once(";base64,").unwrap().1;
        let bin = base64::engine::general_purpose::STANDARD
            .decode(data)
            .unwrap();
        assert_eq!(
            bin.len() as u64,
            doc["buffers"][0]["byteLength"].as_u64().unwrap()
        );
        (doc, bin)
    }
}

/// Accessor `i`'s floats.
fn floats(doc: &Value, bin: &[u8], i: usize) -> Vec<f64> {
    let a = &doc["accessors"][i];
    assert_eq!(a["componentType"], 5126);
    let v = &doc["bufferViews"][a["bufferView"].as_u64().unwrap() as usize];
    let off = v["byteOffset"].as_u64().unwrap_or(0) + a["byteOffset"].as_u64().unwrap_or(0);
    let width = match a["type"].as_str().unwrap() {
        "SCALAR" => 1,
        "VEC3" => 3,
        "VEC4" => 4,
        t => panic!("{t}"),
    };
    let n = a["count"].as_u64().unwrap() as usize * width;
    bin[off as usize..off as usize + 4 * n]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()) as f64)
        .collect()
}

/// The animation named `name` (exactly one).
fn animation<'a>(doc: &'a Value, name: &str) -> &'a Value {
    let found: Vec<&Value> = doc["animations"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|a| a["name"] == name)
        .collect();
    assert_eq!(found.len(), 1, "animations named {name}");
    found[0]
}

/// World transforms of every node at key `key` of animation `name`: the nodes' own TRS, with
/// the animated paths replaced by the samples, composed down the `children` hierarchy.
fn posed_nodes(doc: &Value, bin: &[u8], name: &str, key: Option<usize>) -> Vec<Affine> {
    let nodes = doc["nodes"].as_array().unwrap();
    let mut trs: Vec<(Vec3, Mat3, Vec3)> = nodes
        .iter()
        .map(|n| {
            let v = |key: &str, d: Vec<f64>| -> Vec<f64> {
                n.get(key).map_or(d, |a| {
                    a.as_array()
                        .unwrap()
                        .iter()
                        .map(|x| x.as_f64().unwrap())
                        .collect()
                })
            };
            assert!(n.get("matrix").is_none());
            let t = v("translation", vec![0.0; 3]);
            let r = v("rotation", vec![0.0, 0.0, 0.0, 1.0]);
            let s = v("scale", vec![1.0; 3]);
            ([t[0], t[1], t[2]], quat_xyzw(&r), [s[0], s[1], s[2]])
        })
        .collect();
    // `None`: the rest pose, the nodes' own TRS.
    if let Some(k) = key {
        let anim = animation(doc, name);
        for ch in anim["channels"].as_array().unwrap() {
            let node = ch["target"]["node"].as_u64().unwrap() as usize;
            let sampler = &anim["samplers"][ch["sampler"].as_u64().unwrap() as usize];
            let out = floats(doc, bin, sampler["output"].as_u64().unwrap() as usize);
            match ch["target"]["path"].as_str().unwrap() {
                "rotation" => trs[node].1 = quat_xyzw(&out[4 * k..4 * k + 4]),
                "translation" => trs[node].0 = [out[3 * k], out[3 * k + 1], out[3 * k + 2]],
                p => panic!("unexpected path {p}"),
            }
        }
    }
    let mut parent = vec![None; nodes.len()];
    for (p, n) in nodes.iter().enumerate() {
        for c in n["children"].as_array().into_iter().flatten() {
            parent[c.as_u64().unwrap() as usize] = Some(p);
        }
    }
    fn world(
        n: usize,
        parent: &[Option<usize>],
        trs: &[(Vec3, Mat3, Vec3)],
        memo: &mut Vec<Option<Affine>>,
    ) -> Affine {
        if let Some(w) = memo[n] {
            return w;
        }
        let (t, r, s) = trs[n];
        let l = [0, 1, 2].map(|i| [0, 1, 2].map(|j| r[i][j] * s[j]));
        let local = Affine { l, t };
        let w = match parent[n] {
            Some(p) => world(p, parent, trs, memo).then(&local),
            None => local,
        };
        memo[n] = Some(w);
        w
    }
    let mut memo = vec![None; nodes.len()];
    (0..nodes.len())
        .map(|n| world(n, &parent, &trs, &mut memo))
        .collect()
}

/// The worst distance between the written file's posed joints and `motion.positions`, over
/// every frame; `joints[b]` is bone b's node.
fn worst_position_error(file: &[u8], motion: &RigMotion, joints: &[usize], name: &str) -> f64 {
    let (doc, bin) = split(file);
    let anim = animation(&doc, name);
    let times = floats(
        &doc,
        &bin,
        anim["samplers"][0]["input"].as_u64().unwrap() as usize,
    );
    assert_eq!(times.len(), motion.frames);
    for (k, t) in times.iter().enumerate() {
        assert!((t - k as f64 / motion.fps).abs() < 1e-6);
    }
    let mut worst = 0.0f64;
    for k in 0..motion.frames {
        let world = posed_nodes(&doc, &bin, name, Some(k));
        for (b, &n) in joints.iter().enumerate() {
            let want = motion.positions[k * motion.bones + b];
            let got = world[n].t;
            let d = (0..3)
                .map(|i| (got[i] - want[i]).powi(2))
                .sum::<f64>()
                .sqrt();
            worst = worst.max(d);
        }
    }
    worst
}

/// The rig of `file`, the motion retargeted onto it, and each bone's node index (by name).
fn retarget(
    file: &[u8],
    frames: usize,
    options: &Options,
) -> (flame::retarget::Rig, RigMotion, Vec<usize>) {
    let rig = gltf_rig::read(file, None).unwrap();
    let target = Target::auto(Skeleton::smpl24(), rig.clone()).unwrap();
    let motion = target
        .motion(&sinusoid_motion(frames), 20.0, options)
        .unwrap();
    let (doc, _) = split(file);
    let names: Vec<&str> = doc["nodes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|n| n["name"].as_str().unwrap_or(""))
        .collect();
    let joints = (0..rig.bone_count())
        .map(|b| names.iter().position(|&n| n == rig.name(b)).unwrap())
        .collect();
    (rig, motion, joints)
}

#[test]
fn the_written_hierarchy_puts_every_joint_where_the_motion_does() {
    for glb in [true, false] {
        let file = rig_file(glb);
        let (rig, motion, joints) = retarget(&file, 24, &Options::default());
        // The Armature's scale is folded into the rig: its rest hips are in metres.
        let hips = rig.rest_world_positions()[motion.hips_bone];
        assert!((hips[1] - 0.95).abs() < 1e-5, "{hips:?}");
        let out = gltf_out::write(&file, &rig, &motion, "walk").unwrap();
        let worst = worst_position_error(&out, &motion, &joints, "walk");
        assert!(
            worst < 1e-5,
            "glb {glb}: a joint is {worst} m off the motion"
        );
        // The hips node's translation is in the Armature's centimetres, Z up.
        let (doc, bin) = split(&out);
        let anim = animation(&doc, "walk");
        let ch = anim["channels"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["target"]["path"] == "translation")
            .unwrap();
        assert_eq!(ch["target"]["node"], 1);
        let tr = floats(
            &doc,
            &bin,
            anim["samplers"][ch["sampler"].as_u64().unwrap() as usize]["output"]
                .as_u64()
                .unwrap() as usize,
        );
        let p = motion.positions[motion.hips_bone];
        // The Armature turns local y onto world z and local z onto world −y: world (x, y, z)
        // metres is Armature-local (x, z, −y) centimetres.
        for (a, b) in [
            (tr[0], p[0] * 100.0),
            (tr[1], p[2] * 100.0),
            (tr[2], -p[1] * 100.0),
        ] {
            assert!((a - b).abs() < 1e-3, "{tr:?} vs {p:?}");
        }
        assert_eq!(anim["channels"].as_array().unwrap().len(), 23);
        // The same with the feet's IK off (other local rotations, same hierarchy).
        let (_, plain, _) = retarget(
            &file,
            24,
            &Options {
                feet: false,
                hands: false,
            },
        );
        let out = gltf_out::write(&file, &rig, &plain, "walk").unwrap();
        assert!(worst_position_error(&out, &plain, &joints, "walk") < 1e-5);
    }
}

#[test]
fn the_vrm_avatar_is_animated_through_its_own_rest_rotations() {
    let file = std::fs::read(AVATAR).unwrap();
    let (rig, motion, joints) = retarget(&file, 20, &Options::default());
    let out = gltf_out::write(&file, &rig, &motion, "clip").unwrap();
    let worst = worst_position_error(&out, &motion, &joints, "clip");
    assert!(worst < 1e-5, "a joint is {worst} m off the motion");
}

/// Every value of `old` is in `new` unchanged; arrays may have grown (their old elements
/// equal), except where `skip` names a JSON pointer whose value may differ.
fn assert_kept(old: &Value, new: &Value, at: &str, skip: &[&str]) {
    if skip.contains(&at) {
        return;
    }
    match (old, new) {
        (Value::Object(a), Value::Object(b)) => {
            for (k, v) in a {
                let child = format!("{at}/{k}");
                let w = b.get(k).unwrap_or_else(|| panic!("{child} is gone"));
                assert_kept(v, w, &child, skip);
            }
        }
        (Value::Array(a), Value::Array(b)) => {
            assert!(b.len() >= a.len(), "{at} shrank");
            for (i, v) in a.iter().enumerate() {
                assert_kept(v, &b[i], &format!("{at}/{i}"), skip);
            }
        }
        _ => assert_eq!(old, new, "{at} changed"),
    }
}

#[test]
fn the_original_bytes_and_values_are_kept_and_writing_again_replaces() {
    for glb in [true, false] {
        let file = rig_file(glb);
        let (rig, motion, _) = retarget(&file, 10, &Options::default());
        let once = gltf_out::write(&file, &rig, &motion, "walk").unwrap();
        let (old, old_bin) = split(&file);
        let (new, new_bin) = split(&once);
        assert_eq!(
            &new_bin[..old_bin.len()],
            &old_bin[..],
            "the buffer's bytes changed"
        );
        assert!(new_bin.len() > old_bin.len());
        // libflame's buffer view starts on the next 4-byte boundary after the old bytes.
        let view = new["bufferViews"].as_array().unwrap().last().unwrap();
        assert_eq!(
            view["byteOffset"].as_u64().unwrap() as usize,
            old_bin.len().div_ceil(4) * 4
        );
        assert_kept(&old, &new, "", &["/buffers/0/byteLength", "/buffers/0/uri"]);
        assert_eq!(new["animations"].as_array().unwrap().len(), 2);
        // Written again under the same name: the same bytes; under another name: both, once.
        let twice = gltf_out::write(&once, &rig, &motion, "walk").unwrap();
        assert!(twice == once, "glb {glb}: writing again changed the file");
        let other = retarget(&file, 6, &Options::default()).1;
        let both = gltf_out::write(&once, &rig, &other, "run").unwrap();
        let again = gltf_out::write(&both, &rig, &motion, "walk").unwrap();
        let (doc, _) = split(&again);
        let names: Vec<&str> = doc["animations"]
            .as_array()
            .unwrap()
            .iter()
            .map(|a| a["name"].as_str().unwrap())
            .collect();
        assert_eq!(names, ["Idle", "run", "walk"]);
        assert_kept(&old, &doc, "", &["/buffers/0/byteLength", "/buffers/0/uri"]);
        // "run" moved in front of the new "walk" and still plays what it played.
        let (_, _, joints) = retarget(&file, 6, &Options::default());
        assert!(worst_position_error(&again, &other, &joints, "run") < 1e-5);
        assert!(worst_position_error(&again, &motion, &joints, "walk") < 1e-5);
        // Taking "walk" back out of `both` by writing "run" over it again gives what writing
        // "run" alone over `once`'s original gives after "walk": the same three animations.
        let run_only = gltf_out::write(&file, &rig, &other, "run").unwrap();
        let run_then_walk = gltf_out::write(&run_only, &rig, &motion, "walk").unwrap();
        assert!(
            run_then_walk == again,
            "the order of writes changed the bytes"
        );
    }
}

#[test]
fn files_motions_and_buffers_that_do_not_fit_are_refused() {
    let file = rig_file(true);
    let (rig, motion, _) = retarget(&file, 5, &Options::default());
    let err = |bytes: &[u8], m: &RigMotion| {
        gltf_out::write(bytes, &rig, m, "walk")
            .unwrap_err()
            .to_string()
    };
    // Another file: a node renamed, nodes missing.
    let (mut doc, bin) = split(&file);
    doc["nodes"][5]["name"] = json!("somebody_else");
    let e = err(&glb_bytes(&doc, &bin), &motion);
    assert!(e.contains("not the file the rig was read from"), "{e}");
    let (mut doc, bin) = split(&file);
    doc["nodes"].as_array_mut().unwrap().truncate(10);
    doc["nodes"][0]["children"] = json!([1]);
    for n in 1..10 {
        let kids: Vec<u64> = doc["nodes"][n]["children"]
            .as_array()
            .map(|c| {
                c.iter()
                    .filter_map(Value::as_u64)
                    .filter(|&c| c < 10)
                    .collect()
            })
            .unwrap_or_default();
        doc["nodes"][n]["children"] = json!(kids);
    }
    let e = err(&glb_bytes(&doc, &bin), &motion);
    assert!(e.contains("the file has 10 nodes"), "{e}");
    // A skin whose joints are other nodes.
    let (mut doc, bin) = split(&file);
    doc["skins"][0]["joints"][3] = json!(23);
    let e = err(&glb_bytes(&doc, &bin), &motion);
    assert!(e.contains("joints are not the rig's bones"), "{e}");
    // A motion for another rig, a NaN, no frame.
    let mut short = motion.clone();
    short.bones -= 1;
    assert!(err(&file, &short).contains("bones, the rig has 22"));
    let mut nan = motion.clone();
    nan.positions[7][1] = f64::NAN;
    assert!(err(&file, &nan).contains("NaN or infinite"));
    let mut inf = motion.clone();
    inf.world[3][0][0] = f64::INFINITY;
    assert!(err(&file, &inf).contains("NaN or infinite"));
    let mut slow = motion.clone();
    slow.fps = 0.0;
    assert!(err(&file, &slow).contains("frame rate"));
    // A .gltf whose buffer is an external file: appending would mean rewriting it.
    let (mut doc, _) = split(&rig_file(false));
    doc["buffers"][0]["uri"] = json!("rig.bin");
    let e = err(&serde_json::to_vec(&doc).unwrap(), &motion);
    assert!(e.contains("external file"), "{e}");
    // A joint node given as a matrix: glTF cannot animate it.
    let (mut doc, bin) = split(&file);
    let node = doc["nodes"][4].as_object_mut().unwrap();
    node.remove("rotation");
    node.remove("translation");
    node.insert(
        "matrix".into(),
        json!([1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]),
    );
    let e = err(&glb_bytes(&doc, &bin), &motion);
    assert!(e.contains("has a `matrix`"), "{e}");
    // Not glTF at all, a truncated GLB, a rig built in code.
    assert!(err(b"BVH", &motion).contains("not a GLB"));
    assert!(err(&file[..file.len() / 2], &motion).contains("GLB"));
    let code = flame::retarget::Rig::new(
        vec![flame::retarget::BoneSpec {
            name: "a".into(),
            parent: None,
            rest: flame::retarget::RestTransform::offset([0.0; 3]),
        }],
        1.0,
        flame::retarget::RigSource::Code,
    )
    .unwrap();
    let mut one = motion.clone();
    one.bones = 1;
    one.world = vec![rotation::IDENTITY; motion.frames];
    one.local = one.world.clone();
    one.positions = vec![[0.0; 3]; motion.frames];
    one.hips_bone = 0;
    let e = gltf_out::write(&file, &code, &one, "walk")
        .unwrap_err()
        .to_string();
    assert!(e.contains("not read from a glTF"), "{e}");
    // libflame's data no longer last: something appended an accessor after it.
    let once = gltf_out::write(&file, &rig, &motion, "walk").unwrap();
    let (mut doc, bin) = split(&once);
    let extra = doc["accessors"][0].clone();
    doc["accessors"].as_array_mut().unwrap().push(extra);
    let e = err(&glb_bytes(&doc, &bin), &motion);
    assert!(e.contains("not the last data"), "{e}");
}

/// Every humanoid bone's rotation in three-vrm's normalized space (identity rest, world
/// aligned: `N_b = D_parentᵀ · D_b`, `D = G' · W'ᵀ` the posed world rotation times the rest
/// world rotation's inverse, the parent the nearest mapped humanoid ancestor) for every frame,
/// from libflame's retarget of `poses` onto the avatar itself (no IK), as `x, y, z, w`.
fn avatar_normalized(poses: &Poses, fps: f64) -> Vec<(HumanBone, Vec<[f64; 4]>)> {
    let file = std::fs::read(AVATAR).unwrap();
    let rig = gltf_rig::read(&file, None).unwrap();
    let target = Target::auto(Skeleton::smpl24(), rig.clone()).unwrap();
    let plain = Options {
        feet: false,
        hands: false,
    };
    let m = target.motion(poses, fps, &plain).unwrap();
    let rest = rig.rest_world_rotations();
    let bone_of = |h: HumanBone| target.map().bone(h);
    let delta = |t: usize, b: usize| mat_mul(&m.world_frame(t)[b], &transpose(&rest[b]));
    HumanBone::ALL
        .iter()
        .map(|&h| {
            let b = bone_of(h).unwrap();
            let mut up = h.parent();
            while let Some(p) = up.filter(|&p| bone_of(p).is_none()) {
                up = p.parent();
            }
            let track = (0..m.frames)
                .map(|t| {
                    let parent = up.map_or(rotation::IDENTITY, |p| delta(t, bone_of(p).unwrap()));
                    to_xyzw(&mat_mul(&transpose(&parent), &delta(t, b)))
                })
                .collect();
            (h, track)
        })
        .collect()
}

/// The VRMA's node of each humanoid bone, after checking the extension.
fn vrma_bones(doc: &Value) -> Vec<(HumanBone, usize)> {
    let ext = &doc["extensions"]["VRMC_vrm_animation"];
    assert_eq!(ext["specVersion"], "1.0");
    assert_eq!(doc["extensionsUsed"], json!(["VRMC_vrm_animation"]));
    let bones = ext["humanoid"]["humanBones"].as_object().unwrap();
    assert_eq!(bones.len(), 22);
    bones
        .iter()
        .map(|(name, v)| {
            let n = v["node"].as_u64().unwrap() as usize;
            assert_eq!(doc["nodes"][n]["name"], name.as_str());
            (HumanBone::from_name(name).unwrap(), n)
        })
        .collect()
}

#[test]
fn a_vrma_holds_the_t_pose_retarget_and_what_it_gives_an_avatar() {
    let (fps, frames) = (30.0, 25);
    let poses = sinusoid_motion(frames);
    let file = vrma::to_glb(&poses, fps, "motion").unwrap();
    let (doc, bin) = split(&file);
    let bones = vrma_bones(&doc);
    // The T-pose: identity rest rotations, no scale, the lowest joint on the floor, the left
    // hand at +X at the left shoulder's height, the head above the hips.
    let rest = posed_nodes(&doc, &bin, "", None);
    let at = |h: HumanBone| rest[bones.iter().find(|b| b.0 == h).unwrap().1].t;
    for node in doc["nodes"].as_array().unwrap() {
        assert!(node.get("rotation").is_none() && node.get("scale").is_none());
    }
    let lowest = rest.iter().map(|a| a.t[1]).fold(f64::INFINITY, f64::min);
    assert!(lowest.abs() < 1e-6, "{lowest}");
    let (hand, arm) = (at(HumanBone::LeftHand), at(HumanBone::LeftUpperArm));
    assert!(hand[0] > arm[0] + 0.4 && (hand[1] - arm[1]).abs() < 1e-6);
    assert!(at(HumanBone::Head)[1] > at(HumanBone::Hips)[1] + 0.4);
    // Played: the hierarchy puts the joints where libflame's retarget onto the same T-pose rig
    // puts them.
    let target = Target::auto(Skeleton::smpl24(), vrma::t_pose_rig().unwrap()).unwrap();
    let plain = Options {
        feet: false,
        hands: false,
    };
    let m = target.motion(&poses, fps, &plain).unwrap();
    let joints: Vec<usize> = (0..22)
        .map(|b| bones.iter().find(|x| x.0.index() == b).unwrap().1)
        .collect();
    let worst = worst_position_error(&file, &m, &joints, "motion");
    assert!(worst < 1e-5, "a VRMA joint is {worst} m off");
    // What three-vrm-animation does with the file (q' = P · q · W⁻¹ with the file's rest world
    // rotations, identities here, so q' = q) equals libflame's own retarget onto the avatar in
    // normalized space: the avatar shares the T-pose's bone directions and spine split
    // (tools/make_vrm_avatar.py), so the two routes must agree.
    let anim = animation(&doc, "motion");
    let mut worst = 0.0f64;
    for (h, want) in avatar_normalized(&poses, fps) {
        let node = bones.iter().find(|b| b.0 == h).unwrap().1;
        let ch = anim["channels"]
            .as_array()
            .unwrap()
            .iter()
            .find(|c| c["target"]["node"] == node && c["target"]["path"] == "rotation")
            .unwrap();
        let sampler = &anim["samplers"][ch["sampler"].as_u64().unwrap() as usize];
        let got = floats(&doc, &bin, sampler["output"].as_u64().unwrap() as usize);
        for (t, w) in want.iter().enumerate() {
            // Sign-insensitive component difference (f32 storage: ~6e-8).
            let q = &got[4 * t..4 * t + 4];
            let same = (0..4).map(|k| (q[k] - w[k]).abs()).fold(0.0, f64::max);
            let flip = (0..4).map(|k| (q[k] + w[k]).abs()).fold(0.0, f64::max);
            worst = worst.max(same.min(flip));
        }
    }
    assert!(worst < 1e-6, "a normalized rotation differs by {worst}");
    // Refusals.
    assert!(vrma::to_glb(&poses, 0.0, "m").is_err());
    assert!(vrma::to_glb(&sinusoid_motion(0), 30.0, "m").is_err());
}

#[test]
#[ignore = "writes the three-vrm check's files into $FLAME_RETARGET_OUT (tools/vrma_check.sh)"]
fn write_vrma_check_files() {
    let dir = std::env::var("FLAME_RETARGET_OUT").expect("set FLAME_RETARGET_OUT to a directory");
    let dir = std::path::Path::new(&dir);
    let (fps, frames) = (30.0, 40);
    let poses = sinusoid_motion(frames);
    std::fs::write(
        dir.join("motion.vrma"),
        vrma::to_glb(&poses, fps, "motion").unwrap(),
    )
    .unwrap();
    let bones: serde_json::Map<String, Value> = avatar_normalized(&poses, fps)
        .into_iter()
        .map(|(h, track)| (h.name().to_string(), json!(track)))
        .collect();
    let expected = json!({ "fps": fps, "frames": frames, "bones": bones });
    std::fs::write(dir.join("expected.json"), expected.to_string()).unwrap();
    // The avatar handed back with the motion (foot IK on), for the validator.
    let file = std::fs::read(AVATAR).unwrap();
    let (rig, motion, _) = retarget(&file, frames, &Options::default());
    let out = gltf_out::write(&file, &rig, &motion, "libflame").unwrap();
    std::fs::write(dir.join("avatar_animated.vrm"), out).unwrap();
}
