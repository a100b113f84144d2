//! A [`Rig`] read from a skinned glTF 2.0 file: binary (`.glb`) or JSON (`.gltf`, buffers
//! embedded as base64 `data:` URIs), VRM 0.x and 1.0 included ([`read`]).
//!
//! - **Skin.** The one named, else the file's only skin. A VRM file may have several (one per
//!   mesh, sharing bones): without a name, the first skin whose joints hold every humanoid bone
//!   the file declares.
//! - **Bones.** The skin's `joints`, in that order (stored parents first, as [`Rig::new`]
//!   does); a bone is named after its node (`name`, or `node{index}` without one). Its parent
//!   is its nearest ancestor node that is also a joint of the skin. The transforms of nodes
//!   between two joints that are not joints themselves are folded into the child's rest
//!   transform, and those of the nodes above a top joint (an `Armature` node with a 90°
//!   rotation or a 0.01 scale, as Blender and Mixamo exports have) into the top joint's, so
//!   rest world positions and rotations are where the file puts them.
//! - **Rest pose.** The bind pose. With `inverseBindMatrices`, joint `i`'s bind world matrix
//!   is `IBM_i⁻¹` (in the scene's frame: glTF ignores the skinned mesh node's own transform),
//!   its rest transform `world_parent⁻¹ · world_i` (a top joint's: its world matrix), split into
//!   translation, rotation and scale; so a file saved in a pose still gives its bind pose.
//!   Without them, the nodes' own transforms (`matrix`, or `translation`, `rotation` in
//!   `x, y, z, w` order and `scale`). A rest transform with shear (a non-uniform scale above a
//!   rotated bone) cannot be a translation, rotation and scale, and is refused.
//! - **Units.** glTF is in metres: `metres_per_unit` is 1 (a scale on an armature node is
//!   already folded into the top joint).
//! - **VRM.** With the `VRMC_vrm` (1.0: `humanoid.humanBones.{bone}.node`) or `VRM` (0.x:
//!   `humanoid.humanBones`, an array of `{bone, node}`) extension, the rig declares its
//!   humanoid bone map ([`Rig::declared_map`], VRM humanBone names) and its source is
//!   [`RigSource::Vrm`]; a humanoid bone whose node is not a joint of the skin is refused by
//!   name.
//!
//! The file's JSON is read as a [`serde_json::Value`] and nothing is written back: a writer
//! that hands the user's file back edits their bytes, not a re-serialisation of this.
//! Every length, offset and index is checked before anything is sliced or allocated; bad input
//! is an [`crate::Error::InvalidArgument`] that names what is wrong, never a panic.

use std::borrow::Cow;
use std::collections::HashSet;

use base64::Engine as _;
use serde_json::{Map, Value};

use super::rig::{BoneSpec, RestTransform, Rig, RigSource, VrmVersion, MAX_BONES};
use crate::error::{invalid_arg, Result};
use crate::motion::rotation::{self, Mat3, Vec3};

/// GLB chunk types (little-endian `JSON` and `BIN\0`).
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;
/// glTF `componentType` FLOAT.
const FLOAT: u64 = 5126;
/// How far the columns of a rest transform's linear part may be from perpendicular (cosine of
/// the angle between two of them) before it counts as shear: f32 matrices and chains of them
/// are good to ~1e-6; 1e-3 is about 0.06°.
const SHEAR_TOLERANCE: f64 = 1e-3;
/// How far a 4×4 matrix's last row may be from `0 0 0 1`.
const AFFINE_TOLERANCE: f64 = 1e-5;

/// The rig of a skinned glTF 2.0 file, `.glb` or `.gltf` (module doc): `skin` names the skin
/// (needed when the file has several, except a VRM file's); otherwise the file's only skin.
/// Errors name what is wrong: a file with no skin or several and no name, a named skin not in
/// the file, a truncated container, an index or accessor out of bounds, cyclic `children` or a
/// node with two parents, shear or a zero scale in a rest transform, a VRM humanoid bone that
/// is not a joint of the skin, an external buffer the rest pose needs.
pub fn read(bytes: &[u8], skin: Option<&str>) -> Result<Rig> {
    let (json, bin) = container(bytes)?;
    let doc = json.as_object().ok_or_else(|| {
        invalid_arg!("glTF: the JSON is not an object (a glTF file's top level is `{{...}}`)")
    })?;
    check_version(doc)?;
    let nodes = objects(doc, "nodes", "node")?;
    let parents = hierarchy(&nodes)?;
    let skins = array(doc, "skins")?;
    let vrm = vrm_bones(doc, &nodes)?;
    let chosen = choose_skin(skins, skin, vrm.as_ref(), &nodes)?;
    let skin_obj = skins[chosen]
        .as_object()
        .ok_or_else(|| invalid_arg!("glTF: skin {chosen} is not an object"))?;
    let listed = skin_joints(skins, chosen, &nodes)?;
    let mut bone_of = vec![None; nodes.len()];
    for (k, &n) in listed.iter().enumerate() {
        bone_of[n] = Some(k);
    }
    let tree = Tree {
        nodes: &nodes,
        parents: &parents,
        bone_of: &bone_of,
    };
    let mut above = vec![None; nodes.len()];
    let listed_parents: Vec<Option<usize>> = listed
        .iter()
        .map(|&n| tree.joint_above(n, &mut above))
        .collect();
    // Bones parents first (the lowest ready joint next, as `Rig::new` stores them), so that
    // the indices given to `Rig::new` and `Rig::with_declared` are the stored ones.
    let order = parents_first(&listed_parents);
    let mut new_index = vec![0; listed.len()];
    for (i, &k) in order.iter().enumerate() {
        new_index[k] = i;
    }
    let joints: Vec<usize> = order.iter().map(|&k| listed[k]).collect();
    let bone_parents: Vec<Option<usize>> = order
        .iter()
        .map(|&k| listed_parents[k].map(|p| new_index[p]))
        .collect();
    let rests = match skin_obj.get("inverseBindMatrices") {
        Some(acc) => {
            let acc = index(acc, || {
                format!("skin `{}`'s inverseBindMatrices", skin_name(skins, chosen))
            })?;
            // One matrix per joint in the skin's order.
            let listed_ibms = inverse_bind_matrices(doc, bin, acc, &listed, &nodes)?;
            let ibms: Vec<Affine> = order.iter().map(|&k| listed_ibms[k]).collect();
            bind_pose(&ibms, &joints, &bone_parents, &nodes)?
        }
        None => tree.node_pose(&joints)?,
    };
    let bones = joints
        .iter()
        .zip(bone_parents)
        .zip(rests)
        .map(|((&n, parent), rest)| BoneSpec {
            name: node_name(&nodes, n),
            parent,
            rest,
        })
        .collect();
    match vrm {
        None => Rig::new(
            bones,
            1.0,
            RigSource::Gltf {
                skin: chosen,
                nodes: joints,
            },
        ),
        Some((version, human)) => {
            let missing: Vec<String> = human
                .iter()
                .filter(|(_, n)| bone_of[*n].is_none())
                .map(|(bone, n)| format!("`{bone}` ({})", node_label(&nodes, *n)))
                .collect();
            if !missing.is_empty() {
                return Err(invalid_arg!(
                    "VRM humanoid bones whose nodes are not joints of skin `{}`: {}",
                    skin_name(skins, chosen),
                    missing.join(", ")
                ));
            }
            let rig = Rig::new(
                bones,
                1.0,
                RigSource::Vrm {
                    version,
                    skin: Some(chosen),
                    nodes: joints,
                },
            )?;
            // By name: the stored index whatever order the rig keeps.
            let declared = human
                .into_iter()
                .map(|(bone, n)| {
                    let b = rig
                        .find(&node_name(&nodes, n))
                        .expect("every joint is a bone");
                    (bone, b)
                })
                .collect();
            rig.with_declared(declared)
        }
    }
}

/// The JSON and, for a GLB, its BIN chunk.
pub(super) fn container(bytes: &[u8]) -> Result<(Value, Option<&[u8]>)> {
    if bytes.starts_with(b"glTF") {
        let (json, bin) = glb_chunks(bytes)?;
        // Chunks are padded with spaces; some writers pad with zeros.
        let end = json
            .iter()
            .rposition(|&b| b != 0 && b != b' ')
            .map_or(0, |i| i + 1);
        let value = serde_json::from_slice(&json[..end])
            .map_err(|e| invalid_arg!("GLB: the JSON chunk is not valid JSON: {e}"))?;
        Ok((value, bin))
    } else {
        let text = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
        let value = serde_json::from_slice(text)
            .map_err(|e| invalid_arg!("not a GLB (no `glTF` magic) and not glTF JSON: {e}"))?;
        Ok((value, None))
    }
}

/// A little-endian `u32` at `at` (the caller has checked `at + 4 <= b.len()`).
fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

fn chunk_kind(kind: u32) -> String {
    match kind {
        CHUNK_JSON => "JSON".into(),
        CHUNK_BIN => "BIN".into(),
        k => format!("{k:#010x}"),
    }
}

/// The JSON chunk and the first BIN chunk of a GLB, every length checked against the bytes
/// there are. Chunks of other types are skipped.
fn glb_chunks(bytes: &[u8]) -> Result<(&[u8], Option<&[u8]>)> {
    let have = bytes.len();
    if have < 12 {
        return Err(invalid_arg!(
            "GLB is truncated: {have} bytes, less than its 12-byte header"
        ));
    }
    let version = u32_at(bytes, 4);
    if version != 2 {
        return Err(invalid_arg!(
            "GLB version {version} is not supported: glTF 2.0 files are GLB version 2"
        ));
    }
    let declared = u32_at(bytes, 8) as usize;
    if declared > have {
        return Err(invalid_arg!(
            "GLB is truncated: its header says {declared} bytes, the file has {have}"
        ));
    }
    if declared < 12 {
        return Err(invalid_arg!(
            "GLB header gives a length of {declared} bytes, less than the header itself"
        ));
    }
    let data = &bytes[..declared];
    let (mut json, mut bin) = (None, None);
    let mut at = 12;
    while at < data.len() {
        let left = data.len() - at;
        if left < 8 {
            return Err(invalid_arg!(
                "GLB is truncated inside a chunk header at byte {at} ({left} of its 8 bytes)"
            ));
        }
        let len = u32_at(data, at) as usize;
        let kind = u32_at(data, at + 4);
        let body = at + 8;
        if len > data.len() - body {
            return Err(invalid_arg!(
                "GLB is truncated: the {} chunk at byte {at} says {len} bytes, {} are left",
                chunk_kind(kind),
                data.len() - body
            ));
        }
        let chunk = &data[body..body + len];
        match kind {
            CHUNK_JSON if json.is_none() => json = Some(chunk),
            _ if json.is_none() => {
                return Err(invalid_arg!(
                    "GLB's first chunk is not JSON (type {})",
                    chunk_kind(kind)
                ))
            }
            CHUNK_BIN if bin.is_none() => bin = Some(chunk),
            _ => {}
        }
        at = body + len;
    }
    let json =
        json.ok_or_else(|| invalid_arg!("GLB has no JSON chunk (the file ends after its header)"))?;
    Ok((json, bin))
}

/// glTF 1.0 files are refused by name; a missing `asset` is let through.
fn check_version(doc: &Map<String, Value>) -> Result<()> {
    let version = doc
        .get("asset")
        .and_then(|a| a.get("version"))
        .and_then(Value::as_str);
    match version {
        Some(v) if !v.starts_with('2') => Err(invalid_arg!(
            "glTF version {} is not supported: re-export as glTF 2.0",
            short(v)
        )),
        _ => Ok(()),
    }
}

/// At most 60 characters of `s`, for messages.
pub(super) fn short(s: &str) -> String {
    if s.chars().count() <= 60 {
        s.to_string()
    } else {
        format!("{}…", s.chars().take(60).collect::<String>())
    }
}

/// `doc[key]` as an array (missing: empty).
pub(super) fn array<'a>(doc: &'a Map<String, Value>, key: &str) -> Result<&'a [Value]> {
    match doc.get(key) {
        None => Ok(&[]),
        Some(Value::Array(a)) => Ok(a),
        Some(_) => Err(invalid_arg!("glTF: `{key}` is not an array")),
    }
}

/// `doc[key]` as an array of objects.
pub(super) fn objects<'a>(
    doc: &'a Map<String, Value>,
    key: &str,
    what: &str,
) -> Result<Vec<&'a Map<String, Value>>> {
    array(doc, key)?
        .iter()
        .enumerate()
        .map(|(i, v)| {
            v.as_object()
                .ok_or_else(|| invalid_arg!("glTF: {what} {i} is not an object"))
        })
        .collect()
}

/// `v` as an index (a whole number ≥ 0); `what` names it in the error.
pub(super) fn index(v: &Value, what: impl FnOnce() -> String) -> Result<usize> {
    v.as_u64()
        .and_then(|i| usize::try_from(i).ok())
        .ok_or_else(|| {
            invalid_arg!(
                "glTF: {} must be an index (a whole number from 0), got {}",
                what(),
                short(&v.to_string())
            )
        })
}

/// An optional whole number ≥ 0 field (`byteOffset`, `byteLength`, ...), `default` if absent.
pub(super) fn count(
    obj: &Map<String, Value>,
    key: &str,
    default: Option<usize>,
    what: &str,
) -> Result<usize> {
    match obj.get(key) {
        None => default.ok_or_else(|| invalid_arg!("glTF: {what} has no `{key}`")),
        Some(v) => index(v, || format!("{what}'s `{key}`")),
    }
}

pub(super) fn node_name(nodes: &[&Map<String, Value>], i: usize) -> String {
    match nodes[i].get("name").and_then(Value::as_str) {
        Some(s) if !s.is_empty() => s.to_string(),
        _ => format!("node{i}"),
    }
}

/// `node 3 (`Hips`)`, for messages.
fn node_label(nodes: &[&Map<String, Value>], i: usize) -> String {
    format!("node {i} (`{}`)", short(&node_name(nodes, i)))
}

fn skin_name(skins: &[Value], i: usize) -> String {
    match skins[i].get("name").and_then(Value::as_str) {
        Some(s) if !s.is_empty() => s.to_string(),
        _ => format!("skin{i}"),
    }
}

fn skin_list(skins: &[Value]) -> String {
    (0..skins.len())
        .map(|i| format!("`{}`", short(&skin_name(skins, i))))
        .collect::<Vec<_>>()
        .join(", ")
}

/// Every node's parent, after checking `children`: indices in range, no node with two parents
/// (or listed twice), no cycle.
fn hierarchy(nodes: &[&Map<String, Value>]) -> Result<Vec<Option<usize>>> {
    let n = nodes.len();
    let mut parents: Vec<Option<usize>> = vec![None; n];
    for (p, node) in nodes.iter().enumerate() {
        let children = match node.get("children") {
            None => continue,
            Some(Value::Array(c)) => c,
            Some(_) => {
                return Err(invalid_arg!(
                    "glTF: {}'s `children` is not an array",
                    node_label(nodes, p)
                ))
            }
        };
        for c in children {
            let c = index(c, || format!("a child of {}", node_label(nodes, p)))?;
            if c >= n {
                return Err(invalid_arg!(
                    "glTF: {} has child {c}, but the file has {n} nodes",
                    node_label(nodes, p)
                ));
            }
            if c == p {
                return Err(invalid_arg!(
                    "glTF: {} lists itself among its children (a cycle)",
                    node_label(nodes, p)
                ));
            }
            match parents[c] {
                Some(q) if q == p => {
                    return Err(invalid_arg!(
                        "glTF: {} lists {} twice among its children",
                        node_label(nodes, p),
                        node_label(nodes, c)
                    ))
                }
                Some(q) => {
                    return Err(invalid_arg!(
                        "glTF: {} is a child of both {} and {}: a node has at most one parent",
                        node_label(nodes, c),
                        node_label(nodes, q),
                        node_label(nodes, p)
                    ))
                }
                None => parents[c] = Some(p),
            }
        }
    }
    // With one parent each, a cycle is a walk up that comes back to a node of the same walk.
    let mut walk = vec![usize::MAX; n];
    for start in 0..n {
        let mut cur = start;
        loop {
            if walk[cur] == start {
                return Err(invalid_arg!(
                    "glTF: the nodes' `children` form a cycle: {} is its own ancestor",
                    node_label(nodes, cur)
                ));
            }
            if walk[cur] != usize::MAX {
                break;
            }
            walk[cur] = start;
            match parents[cur] {
                Some(p) => cur = p,
                None => break,
            }
        }
    }
    Ok(parents)
}

/// A VRM file's version and humanoid bones, `(VRM humanBone name, node)`.
type Humanoid = (VrmVersion, Vec<(String, usize)>);

/// The humanoid bones a VRM file declares; `None` for a file without either VRM extension.
fn vrm_bones(doc: &Map<String, Value>, nodes: &[&Map<String, Value>]) -> Result<Option<Humanoid>> {
    let Some(ext) = doc.get("extensions").and_then(Value::as_object) else {
        return Ok(None);
    };
    let mut bones: Vec<(String, usize)> = Vec::new();
    let node_of = |bone: &str, entry: &Value| -> Result<usize> {
        let v = entry
            .get("node")
            .ok_or_else(|| invalid_arg!("VRM humanoid bone `{}` has no `node`", short(bone)))?;
        index(v, || format!("VRM humanoid bone `{}`'s node", short(bone)))
    };
    let version = if let Some(v1) = ext.get("VRMC_vrm") {
        let human = v1
            .get("humanoid")
            .and_then(|h| h.get("humanBones"))
            .and_then(Value::as_object)
            .ok_or_else(|| {
                invalid_arg!(
                    "VRM 1.0: the VRMC_vrm extension has no `humanoid.humanBones` object (a truncated or broken VRM file)"
                )
            })?;
        for (bone, entry) in human {
            bones.push((bone.clone(), node_of(bone, entry)?));
        }
        VrmVersion::V1
    } else if let Some(v0) = ext.get("VRM") {
        let human = v0
            .get("humanoid")
            .and_then(|h| h.get("humanBones"))
            .and_then(Value::as_array)
            .ok_or_else(|| {
                invalid_arg!(
                    "VRM 0.x: the VRM extension has no `humanoid.humanBones` array (a truncated or broken VRM file)"
                )
            })?;
        for (k, entry) in human.iter().enumerate() {
            let bone = entry.get("bone").and_then(Value::as_str).ok_or_else(|| {
                invalid_arg!("VRM 0.x: humanoid.humanBones[{k}] has no `bone` name")
            })?;
            bones.push((bone.to_string(), node_of(bone, entry)?));
        }
        VrmVersion::V0
    } else {
        return Ok(None);
    };
    let mut seen = HashSet::new();
    for (bone, n) in &bones {
        if !seen.insert(bone.as_str()) {
            return Err(invalid_arg!(
                "VRM humanoid bone `{}` is declared twice",
                short(bone)
            ));
        }
        if *n >= nodes.len() {
            return Err(invalid_arg!(
                "VRM humanoid bone `{}` is node {n}, but the file has {} nodes",
                short(bone),
                nodes.len()
            ));
        }
    }
    if !bones.iter().any(|(b, _)| b == "hips") {
        return Err(invalid_arg!(
            "the VRM file declares no `hips` humanoid bone (a truncated or broken VRM file)"
        ));
    }
    Ok(Some((version, bones)))
}

/// The skin to read (module doc).
fn choose_skin(
    skins: &[Value],
    name: Option<&str>,
    vrm: Option<&Humanoid>,
    nodes: &[&Map<String, Value>],
) -> Result<usize> {
    if let Some(name) = name {
        return (0..skins.len())
            .find(|&i| skin_name(skins, i) == name)
            .ok_or_else(|| {
                let found = if skins.is_empty() {
                    "none".to_string()
                } else {
                    skin_list(skins)
                };
                invalid_arg!(
                    "the file has no skin named `{}` (its skins: {found})",
                    short(name)
                )
            });
    }
    match (skins.len(), vrm) {
        (0, _) => Err(invalid_arg!(
            "the file has no skin: export the character with its armature/skeleton (a skinned mesh)"
        )),
        (1, _) => Ok(0),
        (n, None) => Err(invalid_arg!(
            "the file has {n} skins ({}): name the one to use",
            skin_list(skins)
        )),
        (n, Some((_, human))) => {
            // The skin holding the most declared bones among those holding the hips (the
            // first of them on ties): every one, in a well-formed file.
            let hips = human
                .iter()
                .find(|(b, _)| b == "hips")
                .map(|(_, node)| *node)
                .expect("vrm_bones checked the hips");
            let mut best: Option<(usize, usize)> = None;
            for i in 0..n {
                let Ok(joints) = skin_joints(skins, i, nodes) else {
                    continue;
                };
                let joints: HashSet<usize> = joints.into_iter().collect();
                if !joints.contains(&hips) {
                    continue;
                }
                let held = human.iter().filter(|(_, n)| joints.contains(n)).count();
                if best.is_none_or(|(_, h)| held > h) {
                    best = Some((i, held));
                }
            }
            best.map(|(i, _)| i).ok_or_else(|| {
                invalid_arg!(
                    "none of the file's {n} skins ({}) has the VRM hips bone ({}) among its joints",
                    skin_list(skins),
                    node_label(nodes, hips)
                )
            })
        }
    }
}

/// Skin `i`'s joints: a non-empty list of distinct node indices, at most [`MAX_BONES`].
fn skin_joints(skins: &[Value], i: usize, nodes: &[&Map<String, Value>]) -> Result<Vec<usize>> {
    let name = || short(&skin_name(skins, i));
    let joints = skins[i]
        .get("joints")
        .and_then(Value::as_array)
        .ok_or_else(|| invalid_arg!("glTF: skin `{}` has no `joints` array", name()))?;
    if joints.is_empty() {
        return Err(invalid_arg!("glTF: skin `{}` has no joints", name()));
    }
    if joints.len() > MAX_BONES {
        return Err(invalid_arg!(
            "glTF: skin `{}` has {} joints, more than the {MAX_BONES} a rig may have",
            name(),
            joints.len()
        ));
    }
    let mut seen = HashSet::with_capacity(joints.len());
    joints
        .iter()
        .enumerate()
        .map(|(k, j)| {
            let n = index(j, || format!("skin `{}`'s joint {k}", name()))?;
            if n >= nodes.len() {
                return Err(invalid_arg!(
                    "glTF: skin `{}`'s joint {k} is node {n}, but the file has {} nodes",
                    name(),
                    nodes.len()
                ));
            }
            if !seen.insert(n) {
                return Err(invalid_arg!(
                    "glTF: skin `{}` lists {} twice among its joints",
                    name(),
                    node_label(nodes, n)
                ));
            }
            Ok(n)
        })
        .collect()
}

/// Positions into a list of bones whose parents (positions in the same list) are `parents`,
/// parents first and otherwise in list order: the lowest ready bone next, the order
/// [`Rig::new`] stores. The hierarchy has no cycle (the nodes' has none).
fn parents_first(parents: &[Option<usize>]) -> Vec<usize> {
    let mut children = vec![Vec::new(); parents.len()];
    let mut ready = std::collections::BinaryHeap::new();
    for (k, p) in parents.iter().enumerate() {
        match p {
            Some(p) => children[*p].push(k),
            None => ready.push(std::cmp::Reverse(k)),
        }
    }
    let mut out = Vec::with_capacity(parents.len());
    while let Some(std::cmp::Reverse(k)) = ready.pop() {
        out.push(k);
        ready.extend(children[k].iter().map(|&c| std::cmp::Reverse(c)));
    }
    out
}

/// An affine map `x ↦ l·x + t` (also the writer's, `super::gltf_out`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Affine {
    pub(crate) l: Mat3,
    pub(crate) t: Vec3,
}

impl Affine {
    /// glTF's `T · R · S`.
    pub(crate) fn trs(t: Vec3, r: &Mat3, s: &Vec3) -> Affine {
        let mut l = *r;
        for row in &mut l {
            for (v, k) in row.iter_mut().zip(s) {
                *v *= k;
            }
        }
        Affine { l, t }
    }

    /// `self · child`.
    pub(crate) fn then(&self, child: &Affine) -> Affine {
        Affine {
            l: rotation::mul(&self.l, &child.l),
            t: rotation::add(&self.t, &rotation::apply(&self.l, &child.t)),
        }
    }

    /// The point `self⁻¹ · p`, `None` when the linear part is singular.
    pub(crate) fn solve(&self, p: &Vec3) -> Option<Vec3> {
        let m = &self.l;
        let det = rotation::det(m);
        if !(det.is_finite() && det.abs() > 1e-300) {
            return None;
        }
        let d = [p[0] - self.t[0], p[1] - self.t[1], p[2] - self.t[2]];
        // Cramer's rule: the inverse's columns are the rows' cross products over det.
        let cols = [
            rotation::cross(&m[1], &m[2]),
            rotation::cross(&m[2], &m[0]),
            rotation::cross(&m[0], &m[1]),
        ];
        let x: Vec3 = [0, 1, 2].map(|r| (0..3).map(|c| cols[c][r] * d[c]).sum::<f64>() / det);
        x.iter().all(|v| v.is_finite()).then_some(x)
    }

    /// The inverse, `None` when singular (relative to the matrix's size) or not finite.
    fn inverse(&self) -> Option<Affine> {
        let m = &self.l;
        let size = m.iter().flatten().fold(0.0f64, |a, v| a.max(v.abs()));
        let det = rotation::det(m);
        if !(det.is_finite() && size > 0.0 && det.abs() > 1e-12 * size * size * size) {
            return None;
        }
        // Columns of the inverse: the rows' cross products over the determinant.
        let cols = [
            rotation::cross(&m[1], &m[2]),
            rotation::cross(&m[2], &m[0]),
            rotation::cross(&m[0], &m[1]),
        ];
        let mut l = [[0.0; 3]; 3];
        for (c, col) in cols.iter().enumerate() {
            for (r, v) in col.iter().enumerate() {
                l[r][c] = v / det;
            }
        }
        let t = rotation::apply(&l, &self.t).map(|v| -v);
        let inv = Affine { l, t };
        let finite = inv.l.iter().flatten().chain(&inv.t).all(|v| v.is_finite());
        finite.then_some(inv)
    }

    /// From 16 column-major numbers whose last row is `0 0 0 1`.
    fn from_columns(m: &[f64; 16]) -> Option<Affine> {
        let affine = [m[3], m[7], m[11]]
            .iter()
            .all(|v| v.abs() <= AFFINE_TOLERANCE)
            && (m[15] - 1.0).abs() <= AFFINE_TOLERANCE;
        affine.then(|| Affine {
            l: [[m[0], m[4], m[8]], [m[1], m[5], m[9]], [m[2], m[6], m[10]]],
            t: [m[12], m[13], m[14]],
        })
    }
}

/// A node's own transform.
#[derive(Clone, Copy, Debug)]
enum NodeTransform {
    /// `translation`, `rotation`, `scale` (an identity when all are absent).
    Trs {
        t: Vec3,
        r: Mat3,
        s: Vec3,
    },
    Matrix(Affine),
}

impl NodeTransform {
    fn affine(&self) -> Affine {
        match self {
            NodeTransform::Trs { t, r, s } => Affine::trs(*t, r, s),
            NodeTransform::Matrix(a) => *a,
        }
    }

    fn is_identity(&self) -> bool {
        let id = Affine {
            l: rotation::IDENTITY,
            t: [0.0; 3],
        };
        self.affine() == id
    }
}

/// `n` finite numbers.
fn numbers<const N: usize>(v: &Value, what: impl Fn() -> String) -> Result<[f64; N]> {
    let bad = || {
        invalid_arg!(
            "glTF: {} must be {N} numbers, got {}",
            what(),
            short(&v.to_string())
        )
    };
    let a = v.as_array().filter(|a| a.len() == N).ok_or_else(bad)?;
    let mut out = [0.0; N];
    for (o, x) in out.iter_mut().zip(a) {
        *o = x.as_f64().filter(|x| x.is_finite()).ok_or_else(bad)?;
    }
    Ok(out)
}

/// Node `i`'s transform (`matrix`, else TRS with glTF's `x, y, z, w` quaternion).
fn node_transform(nodes: &[&Map<String, Value>], i: usize) -> Result<NodeTransform> {
    let node = nodes[i];
    let field = |key: &str| format!("{}'s `{key}`", node_label(nodes, i));
    if let Some(m) = node.get("matrix") {
        let m = numbers::<16>(m, || field("matrix"))?;
        return Affine::from_columns(&m)
            .map(NodeTransform::Matrix)
            .ok_or_else(|| {
                invalid_arg!(
                    "glTF: {} is not an affine transform (its last row is not 0 0 0 1)",
                    field("matrix")
                )
            });
    }
    let t = match node.get("translation") {
        Some(v) => numbers::<3>(v, || field("translation"))?,
        None => [0.0; 3],
    };
    let r = match node.get("rotation") {
        Some(v) => {
            let [x, y, z, w] = numbers::<4>(v, || field("rotation"))?;
            // Scaled to its largest component first, so no square overflows or vanishes.
            let big = [x, y, z, w].iter().fold(0.0f64, |a, v| a.max(v.abs()));
            if big == 0.0 {
                return Err(invalid_arg!(
                    "glTF: {} is a zero quaternion, not a rotation",
                    field("rotation")
                ));
            }
            rotation::quat_to_matrix(&[w / big, x / big, y / big, z / big])
        }
        None => rotation::IDENTITY,
    };
    let s = match node.get("scale") {
        Some(v) => numbers::<3>(v, || field("scale"))?,
        None => [1.0; 3],
    };
    Ok(NodeTransform::Trs { t, r, s })
}

/// The node tree seen from the skin.
struct Tree<'a> {
    nodes: &'a [&'a Map<String, Value>],
    parents: &'a [Option<usize>],
    /// The bone of each node that is a joint.
    bone_of: &'a [Option<usize>],
}

impl Tree<'_> {
    /// The bone of node `n`'s nearest ancestor that is a joint. `memo[q]` keeps a non-joint
    /// node's answer (`Some(answer)` once known) so shared chains are walked once.
    fn joint_above(&self, n: usize, memo: &mut [Option<Option<usize>>]) -> Option<usize> {
        let mut path = Vec::new();
        let mut cur = self.parents[n];
        let found = loop {
            let Some(q) = cur else { break None };
            if let Some(b) = self.bone_of[q] {
                break Some(b);
            }
            if let Some(known) = memo[q] {
                break known;
            }
            path.push(q);
            cur = self.parents[q];
        };
        for q in path {
            memo[q] = Some(found);
        }
        found
    }

    /// Rest transforms from the nodes' own transforms, with the non-joint nodes above each
    /// joint (up to the next joint, or to the top) folded in.
    fn node_pose(&self, joints: &[usize]) -> Result<Vec<RestTransform>> {
        // `folded[q]` for a non-joint node q: the product of the non-joint nodes from below
        // its nearest joint ancestor (or the top) down to q, `Some(None)` when all are
        // identities.
        let mut folded: Vec<Option<Option<Affine>>> = vec![None; self.nodes.len()];
        joints
            .iter()
            .map(|&j| {
                let fold = self.fold_above(j, &mut folded)?;
                let own = node_transform(self.nodes, j)?;
                let name = node_name(self.nodes, j);
                match (fold, own) {
                    (None, NodeTransform::Trs { t, r, s }) => Ok(RestTransform {
                        translation: t,
                        rotation: r,
                        scale: s,
                    }),
                    (None, own) => decompose(&own.affine(), &name, "its node `matrix`"),
                    (Some(f), own) => decompose(
                        &f.then(&own.affine()),
                        &name,
                        "its node transform with the nodes above it folded in",
                    ),
                }
            })
            .collect()
    }

    /// The product of the non-joint nodes between joint `j` and its nearest joint ancestor
    /// (all of them up to the top for a top joint); `None` when there are none or all are
    /// identities.
    fn fold_above(
        &self,
        j: usize,
        folded: &mut [Option<Option<Affine>>],
    ) -> Result<Option<Affine>> {
        let mut path = Vec::new();
        let mut acc = None;
        let mut cur = self.parents[j];
        while let Some(q) = cur {
            if self.bone_of[q].is_some() {
                break;
            }
            if let Some(known) = folded[q] {
                acc = known;
                break;
            }
            path.push(q);
            cur = self.parents[q];
        }
        for &q in path.iter().rev() {
            let own = node_transform(self.nodes, q)?;
            if !own.is_identity() {
                acc = Some(match acc {
                    Some(a) => a.then(&own.affine()),
                    None => own.affine(),
                });
            }
            folded[q] = Some(acc);
        }
        Ok(acc)
    }
}

/// The bytes of buffer `i`: a GLB's BIN chunk (a buffer without `uri`, the first) or a base64
/// `data:` URI; an external file is refused.
fn buffer_bytes<'a>(
    doc: &Map<String, Value>,
    i: usize,
    bin: Option<&'a [u8]>,
) -> Result<(Cow<'a, [u8]>, usize)> {
    let buffers = objects(doc, "buffers", "buffer")?;
    let buffer = buffers.get(i).ok_or_else(|| {
        invalid_arg!(
            "glTF: buffer {i} does not exist (the file has {} buffers)",
            buffers.len()
        )
    })?;
    let what = format!("buffer {i}");
    let declared = count(buffer, "byteLength", None, &what)?;
    let data: Cow<'a, [u8]> = match buffer.get("uri") {
        None => match bin {
            Some(bin) if i == 0 => Cow::Borrowed(bin),
            _ if i == 0 => {
                return Err(invalid_arg!(
                    "glTF: buffer 0 has no `uri` and the file has no GLB BIN chunk"
                ))
            }
            _ => return Err(invalid_arg!("glTF: buffer {i} has no `uri`")),
        },
        Some(Value::String(uri)) if uri.starts_with("data:") => {
            let payload = uri
                .find(";base64,")
                .map(|k| &uri[k + 8..])
                .ok_or_else(|| invalid_arg!("glTF: buffer {i}'s data URI is not base64"))?;
            let engine = base64::engine::GeneralPurpose::new(
                &base64::alphabet::STANDARD,
                base64::engine::GeneralPurposeConfig::new()
                    .with_decode_padding_mode(base64::engine::DecodePaddingMode::Indifferent)
                    .with_decode_allow_trailing_bits(true),
            );
            Cow::Owned(
                engine
                    .decode(payload)
                    .map_err(|e| invalid_arg!("glTF: buffer {i}'s data URI: {e}"))?,
            )
        }
        Some(Value::String(uri)) => {
            return Err(invalid_arg!(
                "glTF: buffer {i} is an external file (`{}`) and the rest pose needs it: pass a .glb, or a .gltf with its buffers embedded (data: URIs)",
                short(uri)
            ))
        }
        Some(_) => return Err(invalid_arg!("glTF: buffer {i}'s `uri` is not a string")),
    };
    if data.len() < declared {
        return Err(invalid_arg!(
            "glTF: buffer {i} says {declared} bytes but holds {} (truncated?)",
            data.len()
        ));
    }
    Ok((data, declared))
}

/// Accessor `acc` (`what` names it in errors): `count` elements of `kind` (`SCALAR`, `VEC3`,
/// `VEC4`, `MAT4`, ...; `width` floats each), every offset checked against its buffer view and
/// buffer before anything is allocated. Dense float accessors only.
pub(super) fn float_accessor(
    doc: &Map<String, Value>,
    bin: Option<&[u8]>,
    acc: usize,
    kind: &str,
    width: usize,
    what: &str,
) -> Result<Vec<f32>> {
    let accessors = objects(doc, "accessors", "accessor")?;
    let a = accessors.get(acc).ok_or_else(|| {
        invalid_arg!(
            "glTF: {what} does not exist (the file has {} accessors)",
            accessors.len()
        )
    })?;
    if a.contains_key("sparse") {
        return Err(invalid_arg!(
            "glTF: {what} is sparse, which is not supported"
        ));
    }
    let component = a.get("componentType").and_then(Value::as_u64);
    if component != Some(FLOAT) {
        return Err(invalid_arg!(
            "glTF: {what} has componentType {}; it must be floats ({FLOAT})",
            short(&a.get("componentType").unwrap_or(&Value::Null).to_string())
        ));
    }
    if a.get("type").and_then(Value::as_str) != Some(kind) {
        return Err(invalid_arg!(
            "glTF: {what} has type {}; it must be {kind}",
            short(&a.get("type").unwrap_or(&Value::Null).to_string())
        ));
    }
    let n = count(a, "count", None, what)?;
    if n == 0 {
        return Err(invalid_arg!("glTF: {what} has no elements"));
    }
    let size = 4 * width;
    let view_index = count(a, "bufferView", None, what)?;
    let acc_offset = count(a, "byteOffset", Some(0), what)?;
    let views = objects(doc, "bufferViews", "buffer view")?;
    let view = views.get(view_index).ok_or_else(|| {
        invalid_arg!(
            "glTF: {what}'s buffer view {view_index} does not exist (the file has {} buffer views)",
            views.len()
        )
    })?;
    let view_what = format!("buffer view {view_index}");
    let buffer = count(view, "buffer", None, &view_what)?;
    let view_offset = count(view, "byteOffset", Some(0), &view_what)?;
    let view_len = count(view, "byteLength", None, &view_what)?;
    let stride = count(view, "byteStride", Some(size), &view_what)?;
    if stride < size {
        return Err(invalid_arg!(
            "glTF: {view_what} has byteStride {stride}, less than a float {kind}'s {size} bytes"
        ));
    }
    let (data, buffer_len) = buffer_bytes(doc, buffer, bin)?;
    let view_end = view_offset
        .checked_add(view_len)
        .filter(|&e| e <= buffer_len)
        .ok_or_else(|| {
            invalid_arg!(
                "glTF: {view_what} (bytes {view_offset} + {view_len}) is out of bounds of buffer {buffer} ({buffer_len} bytes)"
            )
        })?;
    stride
        .checked_mul(n - 1)
        .and_then(|b| b.checked_add(size))
        .and_then(|b| b.checked_add(acc_offset))
        .filter(|&b| b <= view_len)
        .ok_or_else(|| {
            invalid_arg!(
                "glTF: {what} is out of bounds: {n} {kind} from byte {acc_offset} need more than {view_what}'s {view_len} bytes"
            )
        })?;
    let bytes = &data[view_offset..view_end];
    let mut out = Vec::with_capacity(n * width);
    for k in 0..n {
        let at = acc_offset + k * stride;
        out.extend(
            bytes[at..at + size]
                .chunks_exact(4)
                .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
        );
    }
    Ok(out)
}

/// Accessor `acc`: one float MAT4 per joint.
fn inverse_bind_matrices(
    doc: &Map<String, Value>,
    bin: Option<&[u8]>,
    acc: usize,
    joints: &[usize],
    nodes: &[&Map<String, Value>],
) -> Result<Vec<Affine>> {
    let what = format!("accessor {acc} (inverseBindMatrices)");
    let floats = float_accessor(doc, bin, acc, "MAT4", 16, &what)?;
    let n = floats.len() / 16;
    if n != joints.len() {
        return Err(invalid_arg!(
            "glTF: {what} has {n} matrices for the skin's {} joints",
            joints.len()
        ));
    }
    floats
        .chunks_exact(16)
        .enumerate()
        .map(|(k, f)| {
            let m: [f64; 16] = std::array::from_fn(|e| f[e] as f64);
            let joint = || node_label(nodes, joints[k]);
            if m.iter().any(|v| !v.is_finite()) {
                return Err(invalid_arg!(
                    "glTF: joint {}'s inverse bind matrix has a NaN or infinite value",
                    joint()
                ));
            }
            Affine::from_columns(&m).ok_or_else(|| {
                invalid_arg!(
                    "glTF: joint {}'s inverse bind matrix is not affine (its last row is not 0 0 0 1)",
                    joint()
                )
            })
        })
        .collect()
}

/// Rest transforms from the inverse bind matrices (module doc).
fn bind_pose(
    ibms: &[Affine],
    joints: &[usize],
    parents: &[Option<usize>],
    nodes: &[&Map<String, Value>],
) -> Result<Vec<RestTransform>> {
    let worlds: Vec<Affine> = ibms
        .iter()
        .zip(joints)
        .map(|(ibm, &n)| {
            ibm.inverse().ok_or_else(|| {
                invalid_arg!(
                    "glTF: joint {}'s inverse bind matrix is singular (a zero scale)",
                    node_label(nodes, n)
                )
            })
        })
        .collect::<Result<_>>()?;
    worlds
        .iter()
        .zip(parents)
        .zip(joints)
        .map(|((world, parent), &n)| {
            let local = match parent {
                None => *world,
                // The inverse of an inverse bind matrix can still be too ill-conditioned to
                // invert again in floating point (scales of 1e-3 and 1e5 on one bone).
                Some(p) => worlds[*p]
                    .inverse()
                    .ok_or_else(|| {
                        invalid_arg!(
                            "joint `{}`'s bind pose (inverse bind matrices) is too close to \
                             singular to put its children under it",
                            short(&node_name(nodes, joints[*p]))
                        )
                    })?
                    .then(world),
            };
            decompose(
                &local,
                &node_name(nodes, n),
                "its bind pose (inverse bind matrices)",
            )
        })
        .collect()
}

/// `a` as translation, rotation and scale (a mirror is a negative x scale). Refuses a zero
/// scale and shear, naming `bone` and where the transform came from (`from`).
fn decompose(a: &Affine, bone: &str, from: &str) -> Result<RestTransform> {
    let bone = short(bone);
    if a.l.iter().flatten().chain(&a.t).any(|v| !v.is_finite()) {
        return Err(invalid_arg!(
            "bone `{bone}`'s rest transform ({from}) is not finite"
        ));
    }
    let col = |c: usize| [a.l[0][c], a.l[1][c], a.l[2][c]];
    let cols = [col(0), col(1), col(2)];
    let mut s = cols.map(|c| c[0].hypot(c[1]).hypot(c[2]));
    let largest = s.iter().fold(0.0f64, |m, v| m.max(*v));
    if !largest.is_finite() || s.iter().any(|&v| v < 1e-12 || v < 1e-8 * largest) {
        return Err(invalid_arg!(
            "bone `{bone}` has a zero scale in {from} (scale {s:?})"
        ));
    }
    let shear = [(0, 1), (0, 2), (1, 2)]
        .iter()
        .map(|&(i, j)| (rotation::dot(&cols[i], &cols[j]) / (s[i] * s[j])).abs())
        .fold(0.0, f64::max);
    if shear > SHEAR_TOLERANCE {
        return Err(invalid_arg!(
            "bone `{bone}`'s rest transform ({from}) has shear (axes {:.2}° from perpendicular), which a translation, rotation and scale cannot hold: a non-uniform scale above a rotated bone?",
            90.0 - shear.min(1.0).acos().to_degrees()
        ));
    }
    if rotation::det(&a.l) < 0.0 {
        s[0] = -s[0];
    }
    let mut r = [[0.0; 3]; 3];
    for (row, out) in r.iter_mut().enumerate() {
        for (c, v) in out.iter_mut().enumerate() {
            *v = a.l[row][c] / s[c];
        }
    }
    // Nearly orthonormal: made exactly so through its quaternion.
    let r = rotation::quat_to_matrix(&rotation::to_quat(&r));
    Ok(RestTransform {
        translation: a.t,
        rotation: r,
        scale: s,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;
    use std::f64::consts::FRAC_1_SQRT_2 as H;

    /// A GLB of `doc` and `bin` (chunks padded to 4 bytes: JSON with spaces, BIN with zeros).
    fn glb(doc: &Value, bin: &[u8]) -> Vec<u8> {
        let mut json = serde_json::to_vec(doc).unwrap();
        while !json.len().is_multiple_of(4) {
            json.push(b' ');
        }
        let mut bin = bin.to_vec();
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let total = 12 + 8 + json.len() + if bin.is_empty() { 0 } else { 8 + bin.len() };
        let mut out = b"glTF".to_vec();
        out.extend_from_slice(&2u32.to_le_bytes());
        out.extend_from_slice(&(total as u32).to_le_bytes());
        out.extend_from_slice(&(json.len() as u32).to_le_bytes());
        out.extend_from_slice(b"JSON");
        out.extend_from_slice(&json);
        if !bin.is_empty() {
            out.extend_from_slice(&(bin.len() as u32).to_le_bytes());
            out.extend_from_slice(b"BIN\0");
            out.extend_from_slice(&bin);
        }
        assert_eq!(out.len(), total);
        out
    }

    /// The same as `.gltf` text, `bin` as buffer 0's base64 data URI.
    fn gltf_text(doc: &Value, bin: &[u8]) -> Vec<u8> {
        let mut doc = doc.clone();
        if !bin.is_empty() {
            doc["buffers"][0]["uri"] = json!(format!(
                "data:application/octet-stream;base64,{}",
                base64::engine::general_purpose::STANDARD.encode(bin)
            ));
        }
        serde_json::to_vec_pretty(&doc).unwrap()
    }

    fn f32_bytes(v: &[f32]) -> Vec<u8> {
        v.iter().flat_map(|x| x.to_le_bytes()).collect()
    }

    fn assert_vec(a: &Vec3, b: &Vec3, tol: f64) {
        assert!(
            a.iter().zip(b).all(|(x, y)| (x - y).abs() <= tol),
            "{a:?} != {b:?}"
        );
    }

    fn assert_mat(a: &Mat3, b: &Mat3, tol: f64) {
        let ok = (0..3).all(|r| (0..3).all(|c| (a[r][c] - b[r][c]).abs() <= tol));
        assert!(ok, "{a:?} != {b:?}");
    }

    fn err(bytes: &[u8], skin: Option<&str>) -> String {
        read(bytes, skin).unwrap_err().to_string()
    }

    /// −90° about X (Z-up to Y-up): (x, y, z) ↦ (x, z, −y).
    const RX_M90: Mat3 = [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]];
    /// 90° about Z.
    const RZ_90: Mat3 = [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];

    /// A Blender/Mixamo-style file: an `Armature` node (−90° about X, scale 0.01) above a
    /// Z-up skeleton in centimetres; the skinned mesh node beside the joints.
    fn armature_doc() -> Value {
        json!({
            "asset": {"version": "2.0"},
            "nodes": [
                {"name": "Armature", "rotation": [-H, 0, 0, H], "scale": [0.01, 0.01, 0.01],
                 "children": [1, 4]},
                {"name": "Hips", "translation": [0, 0, 100], "children": [2, 3]},
                {"name": "Spine", "translation": [0, 0, 10], "rotation": [0, 0, H, H]},
                {"name": "LeftUpLeg", "translation": [10, 0, -5]},
                {"name": "Body", "skin": 0}
            ],
            "skins": [{"name": "Armature", "joints": [1, 2, 3]}]
        })
    }

    fn check_armature_rig(rig: &Rig, tol: f64) {
        assert_eq!(rig.names(), ["Hips", "Spine", "LeftUpLeg"]);
        assert_eq!(rig.parents(), [None, Some(0), Some(0)]);
        assert_eq!(rig.metres_per_unit(), 1.0);
        // Hips: Rx(−90) · 0.01 · (0, 0, 100) = (0, 1, 0); Spine: + Rx(−90) · (0, 0, 0.1);
        // LeftUpLeg: + Rx(−90) · (0.1, 0, −0.05) = (0.1, −0.05, 0).
        let p = rig.rest_world_positions();
        assert_vec(&p[0], &[0.0, 1.0, 0.0], tol);
        assert_vec(&p[1], &[0.0, 1.1, 0.0], tol);
        assert_vec(&p[2], &[0.1, 0.95, 0.0], tol);
        let hips = rig.rest()[0];
        assert_vec(&hips.translation, &[0.0, 1.0, 0.0], tol);
        assert_mat(&hips.rotation, &RX_M90, tol);
        assert_vec(&hips.scale, &[0.01; 3], tol * 0.01);
        let spine = rig.rest()[1];
        assert_vec(&spine.translation, &[0.0, 0.0, 10.0], tol * 100.0);
        assert_mat(&spine.rotation, &RZ_90, tol);
        assert_vec(&spine.scale, &[1.0; 3], tol);
        let w = rig.rest_world_rotations();
        assert_mat(&w[0], &RX_M90, tol);
        assert_mat(&w[1], &rotation::mul(&RX_M90, &RZ_90), tol);
        assert_eq!(
            rig.source(),
            &RigSource::Gltf {
                skin: 0,
                nodes: vec![1, 2, 3]
            }
        );
    }

    #[test]
    fn an_armature_nodes_rotation_and_scale_are_folded_into_the_root_bone() {
        let doc = armature_doc();
        check_armature_rig(&read(&glb(&doc, &[]), None).unwrap(), 1e-12);
        check_armature_rig(&read(&gltf_text(&doc, &[]), None).unwrap(), 1e-12);
        check_armature_rig(
            &read(&gltf_text(&doc, &[]), Some("Armature")).unwrap(),
            1e-12,
        );

        // The same bind pose as inverse bind matrices (column-major), by hand:
        // Hips world = (0.01 Rx(−90), (0, 1, 0)), inverse (100 Rx(90), (0, 0, −100));
        // Spine world = (0.01 Rx(−90) Rz(90), (0, 1.1, 0)), inverse
        //   (100 [[0,0,−1],[−1,0,0],[0,1,0]], (0, 0, −110));
        // LeftUpLeg world = (0.01 Rx(−90), (0.1, 0.95, 0)), inverse (100 Rx(90), (−10, 0, −95)).
        #[rustfmt::skip]
        let ibms = f32_bytes(&[
            100.0, 0.0, 0.0, 0.0,   0.0, 0.0, 100.0, 0.0,   0.0, -100.0, 0.0, 0.0,   0.0, 0.0, -100.0, 1.0,
            0.0, -100.0, 0.0, 0.0,  0.0, 0.0, 100.0, 0.0,   -100.0, 0.0, 0.0, 0.0,   0.0, 0.0, -110.0, 1.0,
            100.0, 0.0, 0.0, 0.0,   0.0, 0.0, 100.0, 0.0,   0.0, -100.0, 0.0, 0.0,   -10.0, 0.0, -95.0, 1.0,
        ]);
        let mut doc = armature_doc();
        doc["skins"][0]["inverseBindMatrices"] = json!(0);
        doc["accessors"] =
            json!([{"bufferView": 0, "componentType": 5126, "count": 3, "type": "MAT4"}]);
        doc["bufferViews"] = json!([{"buffer": 0, "byteLength": 192}]);
        doc["buffers"] = json!([{"byteLength": 192}]);
        check_armature_rig(&read(&glb(&doc, &ibms), None).unwrap(), 1e-6);
        check_armature_rig(&read(&gltf_text(&doc, &ibms), None).unwrap(), 1e-6);
    }

    #[test]
    fn a_node_between_two_joints_is_folded_into_the_child() {
        let doc = json!({
            "nodes": [
                {"name": "Hips", "translation": [0, 1, 0], "children": [1]},
                {"name": "Offset", "translation": [0, 1, 0], "rotation": [0, H, 0, H], "children": [2]},
                {"name": "Spine", "translation": [0, 0, 1], "children": [3]},
                {"name": "Head", "translation": [0, 0, 1]}
            ],
            "skins": [{"joints": [0, 2, 3]}]
        });
        let rig = read(&gltf_text(&doc, &[]), None).unwrap();
        assert_eq!(rig.names(), ["Hips", "Spine", "Head"]);
        assert_eq!(rig.parents(), [None, Some(0), Some(1)]);
        // Spine's rest: Offset · Spine = ((0, 1, 0) + Ry(90) (0, 0, 1), Ry(90)) = ((1, 1, 0), Ry(90)).
        let ry90 = [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]];
        let spine = rig.rest()[1];
        assert_vec(&spine.translation, &[1.0, 1.0, 0.0], 1e-12);
        assert_mat(&spine.rotation, &ry90, 1e-12);
        assert_vec(&spine.scale, &[1.0; 3], 1e-12);
        // Head = Spine + Ry(90) (0, 0, 1) = (1, 2, 0) + (1, 0, 0).
        let p = rig.rest_world_positions();
        assert_vec(&p[1], &[1.0, 2.0, 0.0], 1e-12);
        assert_vec(&p[2], &[2.0, 2.0, 0.0], 1e-12);
        assert_mat(&rig.rest_world_rotations()[2], &ry90, 1e-12);
    }

    /// Nodes that say one thing (a posed file) and inverse bind matrices another, with the
    /// matrices at byte 16 of their view and the view at byte 8 of the buffer.
    fn posed_doc_and_bin() -> (Value, Vec<u8>) {
        let doc = json!({
            "asset": {"version": "2.0"},
            "nodes": [
                {"name": "Hips", "translation": [0, 5, 0], "children": [1]},
                {"name": "Spine", "translation": [0, 1, 0]},
                {"name": "Body", "skin": 0}
            ],
            "skins": [{"name": "Body", "joints": [0, 1], "inverseBindMatrices": 0}],
            "accessors": [{"bufferView": 0, "byteOffset": 16, "componentType": 5126, "count": 2,
                           "type": "MAT4"}],
            "bufferViews": [{"buffer": 0, "byteOffset": 8, "byteLength": 144}],
            "buffers": [{"byteLength": 152}]
        });
        // Bind worlds: Hips at (0, 1, 0); Spine at (0, 1.5, 0) turned 90° about Z.
        // Inverses: (I, (0, −1, 0)) and (Rz(−90), Rz(−90) (0, −1.5, 0) = (−1.5, 0, 0)).
        let mut bin = vec![0xAB; 24];
        #[rustfmt::skip]
        bin.extend(f32_bytes(&[
            1.0, 0.0, 0.0, 0.0,   0.0, 1.0, 0.0, 0.0,   0.0, 0.0, 1.0, 0.0,   0.0, -1.0, 0.0, 1.0,
            0.0, -1.0, 0.0, 0.0,  1.0, 0.0, 0.0, 0.0,   0.0, 0.0, 1.0, 0.0,   -1.5, 0.0, 0.0, 1.0,
        ]));
        (doc, bin)
    }

    #[test]
    fn an_ill_conditioned_bind_pose_is_an_error_not_a_panic() {
        // Hips' inverse bind matrix diag(1e3, 1e3, 1e-5) passes its own inversion; its inverse
        // diag(1e-3, 1e-3, 1e5), which the child's local pose needs inverted again, does not.
        let (doc, _) = posed_doc_and_bin();
        let mut bin = vec![0xAB; 24];
        #[rustfmt::skip]
        bin.extend(f32_bytes(&[
            1e3, 0.0, 0.0, 0.0,   0.0, 1e3, 0.0, 0.0,   0.0, 0.0, 1e-5, 0.0,   0.0, 0.0, 0.0, 1.0,
            1.0, 0.0, 0.0, 0.0,   0.0, 1.0, 0.0, 0.0,   0.0, 0.0, 1.0, 0.0,    0.0, 0.0, 0.0, 1.0,
        ]));
        // Listed as the file lists them, and child first: either way an error naming Hips
        // (its own near-zero scale, or its bind pose too singular to put Spine under it).
        let e = err(&glb(&doc, &bin), None);
        assert!(e.contains("Hips"), "{e}");
        let mut swapped = doc.clone();
        swapped["skins"][0]["joints"] = json!([1, 0]);
        let mut bin2 = vec![0xAB; 24];
        bin2.extend_from_slice(&bin[24 + 64..24 + 128]);
        bin2.extend_from_slice(&bin[24..24 + 64]);
        let e = err(&glb(&swapped, &bin2), None);
        assert!(e.contains("Hips"), "{e}");
    }

    #[test]
    fn inverse_bind_matrices_win_over_node_transforms() {
        let (doc, bin) = posed_doc_and_bin();
        for bytes in [glb(&doc, &bin), gltf_text(&doc, &bin)] {
            let rig = read(&bytes, None).unwrap();
            let r = rig.rest();
            assert_vec(&r[0].translation, &[0.0, 1.0, 0.0], 1e-7);
            assert_mat(&r[0].rotation, &rotation::IDENTITY, 1e-7);
            assert_vec(&r[1].translation, &[0.0, 0.5, 0.0], 1e-7);
            assert_mat(&r[1].rotation, &RZ_90, 1e-7);
            assert_vec(&r[1].scale, &[1.0; 3], 1e-7);
            assert_vec(&rig.rest_world_positions()[1], &[0.0, 1.5, 0.0], 1e-7);
        }
        // Without the matrices, the nodes.
        let mut doc = doc;
        doc["skins"][0]
            .as_object_mut()
            .unwrap()
            .remove("inverseBindMatrices");
        let rig = read(&glb(&doc, &bin), None).unwrap();
        assert_eq!(rig.rest_world_positions()[1], [0.0, 6.0, 0.0]);
    }

    #[test]
    fn quaternions_are_x_y_z_w_and_matrices_column_major() {
        // (x, y, z, w) = (0, 0, 0.6, 0.8): θ about Z with cos θ/2 = 0.8, so cos θ = 0.28 and
        // sin θ = 0.96 (read w first, it would be 180° about (0, 0.6, 0.8)).
        let doc = json!({
            "nodes": [
                {"name": "a", "rotation": [0, 0, 0.6, 0.8], "children": [1]},
                {"name": "b", "matrix": [2, 0, 0, 0,  0, 2, 0, 0,  0, 0, 2, 0,  1, 2, 3, 1]}
            ],
            "skins": [{"joints": [0, 1]}]
        });
        let rig = read(&gltf_text(&doc, &[]), None).unwrap();
        let want = [[0.28, -0.96, 0.0], [0.96, 0.28, 0.0], [0.0, 0.0, 1.0]];
        assert_mat(&rig.rest()[0].rotation, &want, 1e-12);
        let b = rig.rest()[1];
        assert_vec(&b.translation, &[1.0, 2.0, 3.0], 1e-12);
        assert_vec(&b.scale, &[2.0; 3], 1e-12);
        assert_mat(&b.rotation, &rotation::IDENTITY, 1e-12);
        // b's world: a's rotation applied to (1, 2, 3).
        assert_vec(
            &rig.rest_world_positions()[1],
            &[0.28 - 1.92, 0.96 + 0.56, 3.0],
            1e-12,
        );
    }

    #[test]
    fn joints_listed_children_first_keep_names_parents_and_matrices_together() {
        let (mut doc, bin) = posed_doc_and_bin();
        // The same skin with its joints (and matrices) listed Spine first.
        doc["skins"][0]["joints"] = json!([1, 0]);
        let mut swapped = bin[..24].to_vec();
        swapped.extend_from_slice(&bin[24 + 64..]);
        swapped.extend_from_slice(&bin[24..24 + 64]);
        let rig = read(&glb(&doc, &swapped), None).unwrap();
        assert_eq!(rig.names(), ["Hips", "Spine"]);
        assert_vec(&rig.rest()[1].translation, &[0.0, 0.5, 0.0], 1e-7);
        assert_eq!(
            rig.source(),
            &RigSource::Gltf {
                skin: 0,
                nodes: vec![0, 1]
            }
        );
    }

    /// A VRM 1.0 avatar: two skins (hair and body) sharing the head; nodes without names.
    fn vrm_doc() -> Value {
        json!({
            "asset": {"version": "2.0"},
            "nodes": [
                {"name": "Root", "children": [1, 5, 6]},
                {"name": "J_Bip_C_Hips", "translation": [0, 1, 0], "children": [2]},
                {"name": "J_Bip_C_Spine", "translation": [0, 0.1, 0], "children": [3]},
                {"name": "J_Bip_C_Head", "translation": [0, 0.5, 0], "children": [4]},
                {"translation": [0, 0.1, 0]},
                {"name": "Body", "skin": 1},
                {"name": "Hair", "skin": 0}
            ],
            "skins": [{"name": "Hair", "joints": [3, 4]}, {"name": "Body", "joints": [1, 2, 3, 4]}],
            "extensions": {"VRMC_vrm": {"specVersion": "1.0", "humanoid": {"humanBones": {
                "hips": {"node": 1}, "spine": {"node": 2}, "head": {"node": 3}
            }}}}
        })
    }

    fn declared(rig: &Rig) -> Vec<(String, String)> {
        let mut d: Vec<_> = rig
            .declared_map()
            .iter()
            .map(|(bone, b)| (bone.clone(), rig.name(*b).to_string()))
            .collect();
        d.sort();
        d
    }

    #[test]
    fn vrm_files_declare_their_humanoid_bones() {
        let want = vec![
            ("head".to_string(), "J_Bip_C_Head".to_string()),
            ("hips".to_string(), "J_Bip_C_Hips".to_string()),
            ("spine".to_string(), "J_Bip_C_Spine".to_string()),
        ];
        // 1.0: two skins and no name, the one holding the humanoid bones.
        let doc = vrm_doc();
        let rig = read(&glb(&doc, &[]), None).unwrap();
        assert_eq!(
            rig.names(),
            ["J_Bip_C_Hips", "J_Bip_C_Spine", "J_Bip_C_Head", "node4"]
        );
        assert_eq!(declared(&rig), want);
        assert_eq!(
            rig.source(),
            &RigSource::Vrm {
                version: VrmVersion::V1,
                skin: Some(1),
                nodes: vec![1, 2, 3, 4]
            }
        );
        assert_vec(&rig.rest_world_positions()[3], &[0.0, 1.7, 0.0], 1e-12);

        // 0.x: an array of {bone, node}.
        let mut doc = vrm_doc();
        doc["extensions"] = json!({"VRM": {"humanoid": {"humanBones": [
            {"bone": "hips", "node": 1}, {"bone": "spine", "node": 2}, {"bone": "head", "node": 3}
        ]}}});
        let rig = read(&gltf_text(&doc, &[]), None).unwrap();
        assert_eq!(declared(&rig), want);
        assert!(matches!(
            rig.source(),
            RigSource::Vrm {
                version: VrmVersion::V0,
                skin: Some(1),
                ..
            }
        ));

        // The humanoid bones must be joints of the skin: of the one named, or of any.
        let e = err(&glb(&vrm_doc(), &[]), Some("Hair"));
        assert!(e.contains("`hips` (node 1 (`J_Bip_C_Hips`))"), "{e}");
        assert!(e.contains("`spine`") && e.contains("skin `Hair`"), "{e}");
        let mut doc = vrm_doc();
        doc["skins"][1]["joints"] = json!([1, 2, 4]);
        let e = err(&glb(&doc, &[]), None);
        assert!(e.contains("`head` (node 3 (`J_Bip_C_Head`))"), "{e}");
        assert!(!e.contains("`hips`"), "{e}");
        doc["skins"][1]["joints"] = json!([2, 4]);
        let e = err(&glb(&doc, &[]), None);
        assert!(
            e.contains("has the VRM hips bone") && e.contains("`Hair`, `Body`"),
            "{e}"
        );

        // Broken or truncated VRM data.
        let mut doc = vrm_doc();
        doc["extensions"]["VRMC_vrm"] = json!({"specVersion": "1.0"});
        let e = err(&glb(&doc, &[]), None);
        assert!(e.contains("humanoid.humanBones"), "{e}");
        let mut doc = vrm_doc();
        doc["extensions"]["VRMC_vrm"]["humanoid"]["humanBones"] = json!({"spine": {"node": 2}});
        assert!(err(&glb(&doc, &[]), None).contains("no `hips`"));
        doc["extensions"]["VRMC_vrm"]["humanoid"]["humanBones"] = json!({"hips": {"node": 40}});
        assert!(err(&glb(&doc, &[]), None).contains("`hips` is node 40"));
        doc["extensions"]["VRMC_vrm"]["humanoid"]["humanBones"] = json!({"hips": {}});
        assert!(err(&glb(&doc, &[]), None).contains("`hips` has no `node`"));
        let bytes = glb(&vrm_doc(), &[]);
        for cut in 0..bytes.len() {
            let e = err(&bytes[..cut], None);
            assert!(e.contains("GLB"), "{cut}: {e}");
        }
    }

    #[test]
    fn skins_are_chosen_by_name_or_refused_by_name() {
        let mut doc = armature_doc();
        doc["skins"] = json!([]);
        let e = err(&glb(&doc, &[]), None);
        assert!(
            e.contains("has no skin: export the character with its armature"),
            "{e}"
        );
        doc.as_object_mut().unwrap().remove("skins");
        assert!(err(&glb(&doc, &[]), None).contains("has no skin"));
        let e = err(&glb(&doc, &[]), Some("Body"));
        assert!(e.contains("no skin named `Body` (its skins: none)"), "{e}");

        let mut doc = armature_doc();
        doc["skins"] = json!([{"name": "Body", "joints": [1, 2, 3]}, {"name": "Hair", "joints": [2]}, {"joints": [3]}]);
        let e = err(&glb(&doc, &[]), None);
        assert!(
            e.contains("3 skins (`Body`, `Hair`, `skin2`): name the one"),
            "{e}"
        );
        let e = err(&glb(&doc, &[]), Some("Face"));
        assert!(
            e.contains("no skin named `Face` (its skins: `Body`, `Hair`, `skin2`)"),
            "{e}"
        );
        assert_eq!(
            read(&glb(&doc, &[]), Some("Hair")).unwrap().names(),
            ["Spine"]
        );
        assert_eq!(
            read(&glb(&doc, &[]), Some("skin2")).unwrap().names(),
            ["LeftUpLeg"]
        );
        // Hair's only joint is Spine: the Armature and Hips fold into it.
        let spine = read(&glb(&doc, &[]), Some("Hair"))
            .unwrap()
            .rest_world_positions()[0];
        assert_vec(&spine, &[0.0, 1.1, 0.0], 1e-12);
    }

    #[test]
    fn truncated_glbs_are_errors_at_every_length() {
        let (doc, bin) = posed_doc_and_bin();
        let bytes = glb(&doc, &bin);
        let json_len = u32_at(&bytes, 12) as usize;
        let bin_at = 20 + json_len;
        for cut in 0..bytes.len() {
            let e = err(&bytes[..cut], None);
            let want = if cut < 4 { "not a GLB" } else { "truncated" };
            assert!(e.contains(want), "{cut}: {e}");
        }
        // Cut with the header's length made to agree: each chunk header and body.
        let cut_at = |cut: usize| {
            let mut b = bytes[..cut].to_vec();
            b[8..12].copy_from_slice(&(cut as u32).to_le_bytes());
            err(&b, None)
        };
        assert!(cut_at(12).contains("no JSON chunk"));
        assert!(cut_at(16).contains("inside a chunk header at byte 12 (4 of its 8 bytes)"));
        let e = cut_at(30);
        assert!(
            e.contains(&format!(
                "the JSON chunk at byte 12 says {json_len} bytes, 10 are left"
            )),
            "{e}"
        );
        // Without its BIN chunk, the matrices are missing.
        let e = cut_at(bin_at);
        assert!(e.contains("no GLB BIN chunk"), "{e}");
        assert!(cut_at(bin_at + 5).contains("inside a chunk header"));
        let e = cut_at(bin_at + 8 + 100);
        assert!(
            e.contains("the BIN chunk") && e.contains("100 are left"),
            "{e}"
        );
        // Other magic and versions.
        let mut v1 = bytes.clone();
        v1[4] = 1;
        assert!(err(&v1, None).contains("GLB version 1"));
        assert!(err(b"glTF", None).contains("less than its 12-byte header"));
        // A chunk of another type between JSON and BIN is skipped.
        let mut extra = bytes[..bin_at].to_vec();
        extra.extend_from_slice(&4u32.to_le_bytes());
        extra.extend_from_slice(b"XTRA1234");
        extra.extend_from_slice(&bytes[bin_at..]);
        let len = extra.len() as u32;
        extra[8..12].copy_from_slice(&len.to_le_bytes());
        assert_eq!(read(&extra, None).unwrap().bone_count(), 2);
    }

    #[test]
    fn truncated_gltf_text_is_never_a_panic() {
        let (doc, bin) = posed_doc_and_bin();
        let text = gltf_text(&doc, &bin);
        for cut in 0..text.len() {
            assert!(read(&text[..cut], None).is_err(), "{cut}");
        }
    }

    #[test]
    fn json_that_is_not_a_gltf_object_is_refused() {
        let e = err(b"[1, 2]", None);
        assert!(e.contains("not an object"), "{e}");
        assert!(err(&glb(&json!(42), &[]), None).contains("not an object"));
        assert!(err(b"\x00\x01binary", None).contains("not a GLB"));
        let e = err(br#"{"asset": {"version": "1.0"}}"#, None);
        assert!(e.contains("glTF version 1.0 is not supported"), "{e}");
        assert!(err(br#"{"nodes": 3}"#, None).contains("`nodes` is not an array"));
        assert!(err(br#"{"nodes": [3]}"#, None).contains("node 0 is not an object"));
    }

    #[test]
    fn accessors_views_and_buffers_are_checked_against_each_other() {
        let (doc, bin) = posed_doc_and_bin();
        let case = |edit: &dyn Fn(&mut Value)| {
            let mut d = doc.clone();
            edit(&mut d);
            err(&glb(&d, &bin), None)
        };
        // Two matrices from byte 16 need 144 bytes of the view.
        let e = case(&|d| d["bufferViews"][0]["byteLength"] = json!(143));
        assert!(
            e.contains("accessor 0 (inverseBindMatrices) is out of bounds"),
            "{e}"
        );
        let e = case(&|d| d["accessors"][0]["byteOffset"] = json!(17));
        assert!(e.contains("out of bounds"), "{e}");
        let e = case(&|d| d["bufferViews"][0]["byteOffset"] = json!(9));
        assert!(
            e.contains("buffer view 0 (bytes 9 + 144) is out of bounds of buffer 0"),
            "{e}"
        );
        let e = case(&|d| d["buffers"][0]["byteLength"] = json!(1000));
        assert!(e.contains("buffer 0 says 1000 bytes but holds 152"), "{e}");
        let e = case(&|d| d["accessors"][0]["count"] = json!(1));
        assert!(e.contains("has 1 matrices for the skin's 2 joints"), "{e}");
        let e = case(&|d| d["accessors"][0]["componentType"] = json!(5123));
        assert!(e.contains("componentType 5123"), "{e}");
        let e = case(&|d| d["accessors"][0]["type"] = json!("VEC4"));
        assert!(e.contains("has type \"VEC4\"; it must be MAT4"), "{e}");
        let e = case(&|d| d["skins"][0]["inverseBindMatrices"] = json!(3));
        assert!(
            e.contains("accessor 3 (inverseBindMatrices) does not exist"),
            "{e}"
        );
        let e = case(&|d| d["accessors"][0]["bufferView"] = json!(-1));
        assert!(e.contains("must be an index"), "{e}");
        let e = case(&|d| d["bufferViews"][0]["byteStride"] = json!(16));
        assert!(e.contains("byteStride 16"), "{e}");
        // Bounds are checked before anything is allocated.
        let e = case(&|d| d["accessors"][0]["count"] = json!(u64::MAX));
        assert!(e.contains("is out of bounds"), "{e}");
        let e = case(&|d| d["bufferViews"][0]["byteLength"] = json!(u64::MAX));
        assert!(e.contains("out of bounds"), "{e}");
        let e = case(&|d| {
            d["bufferViews"][0]["byteStride"] = json!(u64::MAX / 2);
            d["bufferViews"][0]["byteLength"] = json!(144);
        });
        assert!(e.contains("out of bounds"), "{e}");
        // A singular or non-affine matrix.
        let mut zero = bin.clone();
        zero[24 + 64..24 + 128].fill(0);
        let e = err(&glb(&doc, &zero), None);
        assert!(
            e.contains("node 1 (`Spine`)'s inverse bind matrix is not affine"),
            "{e}"
        );
        zero[24 + 64 + 60..24 + 128].copy_from_slice(&1f32.to_le_bytes());
        let e = err(&glb(&doc, &zero), None);
        assert!(e.contains("inverse bind matrix is singular"), "{e}");
        let mut nan = bin.clone();
        nan[24..28].copy_from_slice(&f32::NAN.to_le_bytes());
        assert!(err(&glb(&doc, &nan), None).contains("NaN"));
    }

    #[test]
    fn external_buffers_are_refused_only_when_the_rest_pose_needs_them() {
        let (mut doc, _) = posed_doc_and_bin();
        doc["buffers"][0]["uri"] = json!("character.bin");
        let text = serde_json::to_vec(&doc).unwrap();
        let e = err(&text, None);
        assert!(
            e.contains("external file (`character.bin`)") && e.contains("pass a .glb"),
            "{e}"
        );
        doc["skins"][0]
            .as_object_mut()
            .unwrap()
            .remove("inverseBindMatrices");
        let text = serde_json::to_vec(&doc).unwrap();
        assert_eq!(read(&text, None).unwrap().bone_count(), 2);
        // A data URI that is not base64, or whose bytes are too few.
        let (mut doc, _) = posed_doc_and_bin();
        doc["buffers"][0]["uri"] = json!("data:application/octet-stream,abc");
        assert!(err(&serde_json::to_vec(&doc).unwrap(), None).contains("not base64"));
        doc["buffers"][0]["uri"] = json!("data:application/octet-stream;base64,AAAA");
        assert!(err(&serde_json::to_vec(&doc).unwrap(), None).contains("holds 3"));
        doc["buffers"][0]["uri"] = json!("data:application/octet-stream;base64,A$A");
        assert!(err(&serde_json::to_vec(&doc).unwrap(), None).contains("data URI"));
    }

    #[test]
    fn broken_hierarchies_and_transforms_are_refused_by_name() {
        let base = armature_doc();
        let case = |edit: &dyn Fn(&mut Value)| {
            let mut d = base.clone();
            edit(&mut d);
            err(&gltf_text(&d, &[]), None)
        };
        // Cycles and a node with two parents, found before any walk.
        let e = case(&|d| d["nodes"][3]["children"] = json!([0]));
        assert!(e.contains("form a cycle"), "{e}");
        let e = case(&|d| d["nodes"][2]["children"] = json!([2]));
        assert!(
            e.contains("node 2 (`Spine`) lists itself among its children"),
            "{e}"
        );
        let e = case(&|d| d["nodes"][2]["children"] = json!([3]));
        assert!(
            e.contains(
                "node 3 (`LeftUpLeg`) is a child of both node 1 (`Hips`) and node 2 (`Spine`)"
            ),
            "{e}"
        );
        let e = case(&|d| d["nodes"][1]["children"] = json!([2, 2]));
        assert!(e.contains("lists node 2 (`Spine`) twice"), "{e}");
        let e = case(&|d| d["nodes"][1]["children"] = json!([2, 9]));
        assert!(e.contains("has child 9, but the file has 5 nodes"), "{e}");
        // Skin joints.
        let e = case(&|d| d["skins"][0]["joints"] = json!([1, 99]));
        assert!(
            e.contains("joint 1 is node 99, but the file has 5 nodes"),
            "{e}"
        );
        let e = case(&|d| d["skins"][0]["joints"] = json!([1, 2, 1]));
        assert!(e.contains("lists node 1 (`Hips`) twice"), "{e}");
        let e = case(&|d| d["skins"][0]["joints"] = json!([]));
        assert!(e.contains("skin `Armature` has no joints"), "{e}");
        let e = case(&|d| d["nodes"][3]["name"] = json!("Spine"));
        assert!(e.contains("both named `Spine`"), "{e}");
        // Shear: a non-uniform scale above a rotated root bone.
        let e = case(&|d| {
            d["nodes"][0]["rotation"] = json!([0, 0, 0, 1]);
            d["nodes"][0]["scale"] = json!([1, 2, 1]);
            d["nodes"][1]["rotation"] = json!([0, 0, 0.38268343236508984, 0.9238795325112867]);
        });
        assert!(
            e.contains("bone `Hips`'s rest transform") && e.contains("has shear"),
            "{e}"
        );
        // Zero scales: on a joint, and on the armature folded into the root.
        let e = case(&|d| d["nodes"][2]["scale"] = json!([1, 0, 1]));
        assert!(
            e.contains("bone `Spine` has scale [1.0, 0.0, 1.0]: a zero scale"),
            "{e}"
        );
        let e = case(&|d| d["nodes"][0]["scale"] = json!([0, 0, 0]));
        assert!(e.contains("bone `Hips` has a zero scale"), "{e}");
        let e = case(&|d| d["nodes"][2]["rotation"] = json!([0, 0, 0, 0]));
        assert!(
            e.contains("node 2 (`Spine`)'s `rotation` is a zero quaternion"),
            "{e}"
        );
        let e = case(&|d| d["nodes"][2]["translation"] = json!([0, 0]));
        assert!(e.contains("`translation` must be 3 numbers"), "{e}");
        let e = case(&|d| {
            d["nodes"][1]["matrix"] = json!([1, 0, 0, 1, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1])
        });
        assert!(
            e.contains("node 1 (`Hips`)'s `matrix` is not an affine transform"),
            "{e}"
        );
        let e = case(&|d| {
            d["nodes"][0]["scale"] = json!([1e300, 1e300, 1e300]);
            d["nodes"][1]["translation"] = json!([0, 0, 1e300]);
        });
        assert!(
            e.contains("bone `Hips`'s rest transform") && e.contains("not finite"),
            "{e}"
        );
    }

    #[test]
    fn a_mirrored_joint_keeps_a_proper_rotation() {
        let doc = json!({
            "nodes": [{"name": "Root", "scale": [-1, 1, 1], "children": [1]},
                      {"name": "Hips", "rotation": [0, 0, H, H]}],
            "skins": [{"joints": [1]}]
        });
        let rig = read(&gltf_text(&doc, &[]), None).unwrap();
        let r = rig.rest()[0];
        assert_vec(&r.scale, &[-1.0, 1.0, 1.0], 1e-12);
        // diag(−1, 1, 1) · Rz(90) = [[0, 1, 0], [1, 0, 0], [0, 0, 1]] (determinant −1) =
        // R · diag(−1, 1, 1) with R = Rz(−90), a proper rotation.
        assert_mat(&r.rotation, &rotation::transpose(&RZ_90), 1e-12);
    }
}
