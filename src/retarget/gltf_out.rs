//! The user's glTF/GLB/VRM file handed back with a retargeted animation added ([`write()`]).
//!
//! - **What is added.** One animation: LINEAR samplers with times `frame / fps`, a rotation
//!   channel on every skin joint's node and a translation channel on the hips' node and on the
//!   nodes of bones beside the body ([`RigMotion::moving`]: Rigify's root-level `DEF-thigh.L`).
//!   Its data is one buffer view appended to the file's buffer (after the existing bytes,
//!   4-byte aligned): the times, then one `x, y, z, w` unit quaternion track per joint
//!   (sign-continuous along the track), then the translations, all `f32`.
//! - **Node values, not bone values.** A [`RigMotion`]'s local rotations are relative to the
//!   parent *bone* and hold the transforms [`super::gltf_rig`] folded in (non-joint nodes
//!   between two joints; for a top joint, the nodes above it such as a Blender/Mixamo
//!   `Armature` with a 90° turn or a 0.01 scale). The file's node tree still has those nodes,
//!   so each joint node gets the rotation that puts it at the motion's world rotation under its
//!   parent node as posed (`Q_parentᵀ · G`, with `Q` the scale-free world rotation of the
//!   posed parent node), and the hips node (and any other moving node) the translation that
//!   puts it at the motion's world position in its parent node's posed frame (scale included: an `Armature` scaled by 0.01
//!   gets centimetres). glTF is in metres and so is a glTF rig (`metres_per_unit` 1), so world
//!   positions need no unit change. Joints' translations are the nodes' own: the hierarchy
//!   reproduces [`RigMotion::positions`] when the nodes rest in the bind pose, as exporters
//!   write them.
//! - **Everything else is kept.** The existing buffer bytes are copied unchanged (a GLB's BIN
//!   chunk up to the buffer's `byteLength`; a `.gltf`'s first buffer, a base64 `data:` URI,
//!   decoded, appended to and encoded again); other chunks of a GLB follow as they were. The
//!   JSON is parsed and serialised again with `serde_json`: every existing value is equal to the
//!   original's (object keys come out sorted and numbers in their shortest form, which JSON does
//!   not distinguish); only `animations`, `accessors`, `bufferViews` and the buffer's
//!   `byteLength` (and `uri`) grow.
//! - **Written again.** The animation's `extras.libflame` records what was added (its buffer
//!   view, its accessors, the buffer's length before, the top-level arrays it created). Before
//!   writing, every animation libflame added is taken out again (the file as it was before
//!   libflame touched it); those with another name are appended again as they were, then the
//!   new one: writing onto a file libflame wrote gives the same bytes as writing onto the
//!   original, and a name is never duplicated.
//!
//! Refused with a message, never a panic: a file that is not the one the rig came from (node or
//! skin indices past the file's, a skin whose joints are not the rig's nodes, names that
//! differ), a motion of another bone count or with non-finite values, a joint node with a
//! `matrix` (glTF animates only `translation`/`rotation`/`scale`), a buffer in an external file
//! (it would have to be rewritten), and libflame data that something else appended after.

use base64::Engine as _;
use serde_json::{json, Map, Value};

use super::gltf_rig::Affine;
use super::pose::RigMotion;
use super::rig::{Rig, RigSource};
use crate::error::{invalid_arg, Result};
use crate::motion::rotation::{self, Mat3, Vec3, IDENTITY};

/// GLB chunk types (little-endian `JSON` and `BIN\0`).
const CHUNK_JSON: u32 = 0x4E4F_534A;
const CHUNK_BIN: u32 = 0x004E_4942;
/// glTF `componentType` FLOAT.
const FLOAT: u64 = 5126;
/// The key under an animation's `extras` that marks it as libflame's.
const MARK: &str = "libflame";

/// `original` (the bytes the rig was read from, `.glb`/`.vrm` or `.gltf`) with `motion` added as
/// the animation `name`, in the same container; an animation of that name written by libflame
/// before is replaced (module doc).
pub fn write(original: &[u8], rig: &Rig, motion: &RigMotion, name: &str) -> Result<Vec<u8>> {
    check_motion(rig, motion)?;
    if name.is_empty() {
        return Err(invalid_arg!("the animation needs a name"));
    }
    let mut file = File::parse(original)?;
    let tree = NodeTree::new(&file.doc)?;
    let joints = source_nodes(&file.doc, rig, &tree)?;
    let kept = file.take_out(name)?;
    for clip in kept {
        file.append(clip)?;
    }
    let clip = clip_of(rig, motion, &tree, &joints, name)?;
    file.append(clip)?;
    file.into_bytes()
}

/// The motion's sizes against the rig's, and every value finite.
fn check_motion(rig: &Rig, m: &RigMotion) -> Result<()> {
    let n = rig.bone_count();
    if m.bones != n {
        return Err(invalid_arg!(
            "the motion is for {} bones, the rig has {n}",
            m.bones
        ));
    }
    let total = m.frames.checked_mul(n);
    let sized = |len: usize| Some(len) == total;
    if m.frames == 0
        || !sized(m.world.len())
        || !sized(m.local.len())
        || !sized(m.positions.len())
        || m.hips.len() != m.frames
        || m.hips_bone >= n
    {
        return Err(invalid_arg!(
            "the motion's arrays do not hold {} frames of {n} bones (or it has no frame)",
            m.frames
        ));
    }
    if !(m.fps.is_finite() && m.fps > 0.0) {
        return Err(invalid_arg!(
            "the motion's frame rate must be positive, got {}",
            m.fps
        ));
    }
    let finite = m.world.iter().flatten().flatten().all(|v| v.is_finite())
        && m.positions.iter().flatten().all(|v| v.is_finite());
    if !finite {
        return Err(invalid_arg!(
            "the motion has a NaN or infinite rotation or position"
        ));
    }
    Ok(())
}

/// A glTF file taken apart: its JSON and the bytes of the buffer libflame appends to.
pub(crate) struct File {
    doc: Map<String, Value>,
    glb: bool,
    /// The appended-to buffer's bytes (exactly `byteLength` of them).
    bin: Vec<u8>,
    /// A GLB's chunks after the BIN chunk (or after JSON without one), kept as they were.
    other_chunks: Vec<(u32, Vec<u8>)>,
    /// A `.gltf`'s buffer 0 data URI up to its payload (`data:...;base64,`), kept as it was.
    uri_prefix: Option<String>,
}

impl File {
    /// An empty GLB (for files libflame makes whole, such as `.vrma`).
    pub(crate) fn new_glb(doc: Map<String, Value>) -> File {
        File {
            doc,
            glb: true,
            bin: Vec::new(),
            other_chunks: Vec::new(),
            uri_prefix: None,
        }
    }

    fn parse(bytes: &[u8]) -> Result<File> {
        if bytes.starts_with(b"glTF") {
            return File::parse_glb(bytes);
        }
        let text = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
        let doc = json_object(text)?;
        let mut uri_prefix = None;
        let bin = match buffer0(&doc)? {
            None => Vec::new(),
            Some((_, None)) => {
                return Err(invalid_arg!(
                    "glTF: buffer 0 has no `uri` in a .gltf file (only a GLB's may omit it)"
                ))
            }
            Some((len, Some(uri))) => {
                let (prefix, data) = decode_data_uri(uri)?;
                uri_prefix = Some(prefix.to_string());
                if data.len() < len {
                    return Err(invalid_arg!(
                        "glTF: buffer 0 says {len} bytes but its data URI holds {}",
                        data.len()
                    ));
                }
                data[..len].to_vec()
            }
        };
        Ok(File {
            doc,
            glb: false,
            bin,
            other_chunks: Vec::new(),
            uri_prefix,
        })
    }

    fn parse_glb(bytes: &[u8]) -> Result<File> {
        let word = |at: usize| -> Result<u32> {
            bytes
                .get(at..at + 4)
                .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
                .ok_or_else(|| invalid_arg!("GLB is truncated at byte {at}"))
        };
        if word(4)? != 2 {
            return Err(invalid_arg!("GLB version {} is not 2", word(4)?));
        }
        let total = word(8)? as usize;
        if total > bytes.len() || total < 12 {
            return Err(invalid_arg!(
                "GLB header says {total} bytes, the file has {}",
                bytes.len()
            ));
        }
        let mut chunks = Vec::new();
        let mut at = 12;
        while at < total {
            let len = word(at)? as usize;
            let kind = word(at + 4)?;
            let body = at + 8;
            if len > total.saturating_sub(body) {
                return Err(invalid_arg!(
                    "GLB chunk at byte {at} says {len} bytes, {} are left",
                    total.saturating_sub(body)
                ));
            }
            chunks.push((kind, &bytes[body..body + len]));
            at = body + len;
        }
        let mut chunks = chunks.into_iter();
        let doc = match chunks.next() {
            Some((CHUNK_JSON, text)) => json_object(text)?,
            _ => return Err(invalid_arg!("GLB's first chunk is not JSON")),
        };
        let mut rest: Vec<(u32, &[u8])> = chunks.collect();
        let bin_chunk = match rest.first() {
            Some((CHUNK_BIN, _)) => Some(rest.remove(0).1),
            _ => None,
        };
        let bin = match (buffer0(&doc)?, bin_chunk) {
            (None, None) => Vec::new(),
            (Some((len, None)), Some(chunk)) => {
                if chunk.len() < len {
                    return Err(invalid_arg!(
                        "GLB: buffer 0 says {len} bytes, the BIN chunk holds {}",
                        chunk.len()
                    ));
                }
                chunk[..len].to_vec()
            }
            (Some((_, Some(_))), _) => {
                return Err(invalid_arg!(
                    "GLB: buffer 0 is not the BIN chunk but a file (`uri`): it would have to be rewritten"
                ))
            }
            (Some((_, None)), None) => {
                return Err(invalid_arg!(
                    "GLB: buffer 0 has no `uri` and the file has no BIN chunk"
                ))
            }
            (None, Some(_)) => {
                return Err(invalid_arg!("GLB: a BIN chunk but no buffer declared"))
            }
        };
        Ok(File {
            doc,
            glb: true,
            bin,
            other_chunks: rest.into_iter().map(|(k, b)| (k, b.to_vec())).collect(),
            uri_prefix: None,
        })
    }

    /// `doc[key]` as a mutable array, created when absent.
    fn array_mut(&mut self, key: &str) -> Result<&mut Vec<Value>> {
        let v = self
            .doc
            .entry(key)
            .or_insert_with(|| Value::Array(Vec::new()));
        v.as_array_mut()
            .ok_or_else(|| invalid_arg!("glTF: `{key}` is not an array"))
    }

    fn len_of(&self, key: &str) -> usize {
        self.doc
            .get(key)
            .and_then(Value::as_array)
            .map_or(0, Vec::len)
    }

    /// Takes out every animation libflame added (module doc) and returns those not named
    /// `name`, to be appended again.
    fn take_out(&mut self, name: &str) -> Result<Vec<Clip>> {
        let anims = self.len_of("animations");
        let ours: Vec<usize> = (0..anims)
            .filter(|&i| self.doc["animations"][i]["extras"][MARK].is_object())
            .collect();
        if ours.is_empty() {
            return Ok(Vec::new());
        }
        let mut marks = Vec::with_capacity(ours.len());
        for &i in &ours {
            marks.push(Mark::read(&self.doc["animations"][i], i)?);
        }
        // libflame's data must be the tail of the accessors, buffer views and buffer (each
        // animation's its own, in the order written): then taking it out restores the file.
        let first = &marks[0];
        let mut view = first.view;
        let mut accessor = first.accessors.0;
        for m in &marks {
            if m.view != view || m.accessors.0 != accessor {
                return Err(tail_error());
            }
            view += 1;
            accessor += m.accessors.1;
        }
        if view != self.len_of("bufferViews") || accessor != self.len_of("accessors") {
            return Err(tail_error());
        }
        let mut clips = Vec::new();
        for (m, &i) in marks.iter().zip(&ours) {
            let anim = &self.doc["animations"][i];
            if anim.get("name").and_then(Value::as_str) == Some(name) {
                continue;
            }
            clips.push(self.clip_back(anim, m)?);
        }
        let start = self.bin_start(first)?;
        self.bin.truncate(start);
        let animations = self.array_mut("animations")?;
        for &i in ours.iter().rev() {
            animations.remove(i);
        }
        self.array_mut("bufferViews")?.truncate(first.view);
        self.array_mut("accessors")?.truncate(first.accessors.0);
        for key in &first.created {
            // The buffer libflame created holds nothing else.
            if self.len_of(key) == 0 || key == "buffers" {
                self.doc.remove(key);
            }
        }
        if self.len_of("buffers") > 0 {
            self.doc["buffers"][0]["byteLength"] = json!(start);
        }
        Ok(clips)
    }

    /// The buffer length before libflame's first addition, checked against the bytes there are.
    fn bin_start(&self, first: &Mark) -> Result<usize> {
        let start = first.before;
        let view_start = self.doc["bufferViews"][first.view]["byteOffset"]
            .as_u64()
            .map(|v| v as usize);
        match view_start {
            Some(o) if start <= o && o <= self.bin.len() && o - start < 4 => Ok(start),
            _ => Err(tail_error()),
        }
    }

    /// Animation `anim` (libflame's, with its mark) as a clip to append again.
    fn clip_back(&self, anim: &Value, m: &Mark) -> Result<Clip> {
        let view = &self.doc["bufferViews"][m.view];
        let (offset, len) = match (view["byteOffset"].as_u64(), view["byteLength"].as_u64()) {
            (Some(o), Some(l)) if (o + l) as usize <= self.bin.len() => (o as usize, l as usize),
            _ => return Err(tail_error()),
        };
        let mut accessors = Vec::with_capacity(m.accessors.1);
        for a in m.accessors.0..m.accessors.0 + m.accessors.1 {
            let mut acc = self.doc["accessors"][a].clone();
            if acc["bufferView"].as_u64() != Some(m.view as u64) {
                return Err(tail_error());
            }
            if let Some(o) = acc.as_object_mut() {
                o.remove("bufferView");
            }
            accessors.push(acc);
        }
        let mut anim = anim.clone();
        let base = m.accessors.0 as u64;
        if let Some(samplers) = anim["samplers"].as_array_mut() {
            for s in samplers {
                for key in ["input", "output"] {
                    let a = s[key].as_u64().ok_or_else(tail_error)?;
                    s[key] = json!(a.checked_sub(base).ok_or_else(tail_error)?);
                }
            }
        }
        if let Some(extras) = anim["extras"].as_object_mut() {
            extras.remove(MARK);
        }
        Ok(Clip {
            animation: anim,
            accessors,
            data: self.bin[offset..offset + len].to_vec(),
        })
    }

    /// Appends `clip`: its data as one buffer view at the end of the buffer (4-byte aligned),
    /// its accessors, and the animation with its sampler indices moved onto them and its mark.
    pub(crate) fn append(&mut self, clip: Clip) -> Result<()> {
        let created: Vec<&str> = ["animations", "accessors", "bufferViews", "buffers"]
            .into_iter()
            .filter(|k| self.len_of(k) == 0)
            .collect();
        let before = self.bin.len();
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        let offset = self.bin.len();
        self.bin.extend_from_slice(&clip.data);
        let total = self.bin.len();
        if total > u32::MAX as usize {
            return Err(invalid_arg!("glTF: the buffer would exceed 4 GiB"));
        }
        if self.len_of("buffers") == 0 {
            self.array_mut("buffers")?.push(json!({ "byteLength": 0 }));
        }
        self.doc["buffers"][0]["byteLength"] = json!(total);
        let view = self.len_of("bufferViews");
        self.array_mut("bufferViews")?.push(json!({
            "buffer": 0,
            "byteOffset": offset,
            "byteLength": clip.data.len(),
        }));
        let base = self.len_of("accessors");
        let count = clip.accessors.len();
        for mut a in clip.accessors {
            a["bufferView"] = json!(view);
            self.array_mut("accessors")?.push(a);
        }
        let mut anim = clip.animation;
        if let Some(samplers) = anim["samplers"].as_array_mut() {
            for s in samplers {
                for key in ["input", "output"] {
                    let a = s[key].as_u64().unwrap_or(0) as usize;
                    s[key] = json!(base + a);
                }
            }
        }
        if !anim["extras"].is_object() {
            anim["extras"] = json!({});
        }
        anim["extras"][MARK] = json!({
            "version": env!("CARGO_PKG_VERSION"),
            "bufferView": view,
            "accessors": [base, count],
            "bufferByteLength": before,
            "created": created,
        });
        self.array_mut("animations")?.push(anim);
        Ok(())
    }

    /// The file's bytes in its container.
    pub(crate) fn into_bytes(mut self) -> Result<Vec<u8>> {
        if !self.glb {
            if self.len_of("buffers") > 0 {
                let prefix = self
                    .uri_prefix
                    .as_deref()
                    .unwrap_or("data:application/octet-stream;base64,");
                let uri = format!(
                    "{prefix}{}",
                    base64::engine::general_purpose::STANDARD.encode(&self.bin)
                );
                self.doc["buffers"][0]["uri"] = json!(uri);
            }
            return serde_json::to_vec(&self.doc).map_err(|e| invalid_arg!("glTF JSON: {e}"));
        }
        let mut text = serde_json::to_vec(&self.doc).map_err(|e| invalid_arg!("glTF JSON: {e}"))?;
        // Chunks are 4-byte aligned: JSON padded with spaces, binary chunks with zeros.
        while !text.len().is_multiple_of(4) {
            text.push(b' ');
        }
        let mut bin = self.bin;
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let mut chunks = vec![(CHUNK_JSON, text)];
        if self.doc.get("buffers").is_some() {
            chunks.push((CHUNK_BIN, bin));
        }
        chunks.extend(self.other_chunks);
        let total: usize = 12 + chunks.iter().map(|(_, c)| 8 + c.len()).sum::<usize>();
        let total32 =
            u32::try_from(total).map_err(|_| invalid_arg!("a {total}-byte GLB exceeds 4 GiB"))?;
        let mut out = Vec::with_capacity(total);
        out.extend_from_slice(b"glTF");
        out.extend_from_slice(&2u32.to_le_bytes());
        out.extend_from_slice(&total32.to_le_bytes());
        for (kind, c) in chunks {
            out.extend_from_slice(&(c.len() as u32).to_le_bytes());
            out.extend_from_slice(&kind.to_le_bytes());
            out.extend_from_slice(&c);
        }
        Ok(out)
    }
}

fn tail_error() -> crate::Error {
    invalid_arg!(
        "the file's libflame animations are not the last data in it (another tool appended \
         after them, or their record was edited): write onto the original file"
    )
}

/// What an animation's `extras.libflame` records.
struct Mark {
    view: usize,
    /// First accessor and count.
    accessors: (usize, usize),
    /// The buffer's `byteLength` before the addition.
    before: usize,
    /// Top-level arrays the addition created.
    created: Vec<String>,
}

impl Mark {
    fn read(anim: &Value, i: usize) -> Result<Mark> {
        let m = &anim["extras"][MARK];
        let bad = || invalid_arg!("glTF: animation {i}'s extras.{MARK} record is broken");
        let n = |v: &Value| v.as_u64().map(|v| v as usize).ok_or_else(bad);
        let created = m["created"]
            .as_array()
            .ok_or_else(bad)?
            .iter()
            .map(|k| k.as_str().map(str::to_string).ok_or_else(bad))
            .collect::<Result<Vec<_>>>()?;
        Ok(Mark {
            view: n(&m["bufferView"])?,
            accessors: (n(&m["accessors"][0])?, n(&m["accessors"][1])?),
            before: n(&m["bufferByteLength"])?,
            created,
        })
    }
}

/// One animation ready to append: the animation object (sampler `input`/`output` indices into
/// `accessors`), its accessors (without `bufferView`; `byteOffset` into `data`) and its data.
pub(crate) struct Clip {
    pub(crate) animation: Value,
    pub(crate) accessors: Vec<Value>,
    pub(crate) data: Vec<u8>,
}

impl Clip {
    /// An animation named `name` with LINEAR samplers over `times` (seconds, increasing).
    pub(crate) fn new(name: &str, times: &[f32]) -> Result<Clip> {
        let mut clip = Clip {
            animation: json!({ "name": name, "samplers": [], "channels": [] }),
            accessors: Vec::new(),
            data: Vec::new(),
        };
        clip.floats(times, "SCALAR", true)?;
        Ok(clip)
    }

    /// Appends a float accessor (`width` per element; `bounds` adds min and max).
    fn floats(&mut self, values: &[f32], kind: &str, bounds: bool) -> Result<usize> {
        if values.iter().any(|v| !v.is_finite()) {
            return Err(invalid_arg!(
                "glTF: a {kind} track is not finite in f32 (the motion overflows)"
            ));
        }
        let width = match kind {
            "VEC3" => 3,
            "VEC4" => 4,
            _ => 1,
        };
        let mut a = json!({
            "byteOffset": self.data.len(),
            "componentType": FLOAT,
            "count": values.len() / width,
            "type": kind,
        });
        if bounds {
            let mut lo = vec![f32::INFINITY; width];
            let mut hi = vec![f32::NEG_INFINITY; width];
            for e in values.chunks_exact(width) {
                for k in 0..width {
                    lo[k] = lo[k].min(e[k]);
                    hi[k] = hi[k].max(e[k]);
                }
            }
            a["min"] = json!(lo);
            a["max"] = json!(hi);
        }
        self.data
            .extend(values.iter().flat_map(|v| v.to_le_bytes()));
        self.accessors.push(a);
        Ok(self.accessors.len() - 1)
    }

    /// A channel animating `node`'s `path` (`rotation`: `x, y, z, w` quaternions; `translation`)
    /// with `values`, sampled at the clip's times.
    pub(crate) fn channel(&mut self, node: usize, path: &str, values: &[f32]) -> Result<()> {
        let kind = if path == "rotation" { "VEC4" } else { "VEC3" };
        let output = self.floats(values, kind, false)?;
        let samplers = self.animation["samplers"]
            .as_array_mut()
            .expect("made as an array");
        samplers.push(json!({ "input": 0, "output": output, "interpolation": "LINEAR" }));
        let sampler = samplers.len() - 1;
        self.animation["channels"]
            .as_array_mut()
            .expect("made as an array")
            .push(json!({ "sampler": sampler, "target": { "node": node, "path": path } }));
        Ok(())
    }
}

/// Rotations as `x, y, z, w` unit quaternions in `f32`, each the sign of the one before (so a
/// LINEAR track never takes the long way round).
pub(crate) fn quaternion_track(rotations: impl Iterator<Item = Mat3>) -> Vec<f32> {
    let mut out = Vec::new();
    let mut prev = [0.0, 0.0, 0.0, 1.0];
    for r in rotations {
        let [w, x, y, z] = rotation::to_quat(&r);
        let n = (w * w + x * x + y * y + z * z).sqrt();
        let mut q = [x / n, y / n, z / n, w / n];
        if q.iter().zip(&prev).map(|(a, b)| a * b).sum::<f64>() < 0.0 {
            q = q.map(|v| -v);
        }
        prev = q;
        out.extend(q.map(|v| v as f32));
    }
    out
}

/// The file's JSON object.
fn json_object(text: &[u8]) -> Result<Map<String, Value>> {
    // A GLB's JSON chunk is padded with spaces (some writers use zeros).
    let end = text
        .iter()
        .rposition(|&b| b != 0 && b != b' ')
        .map_or(0, |i| i + 1);
    match serde_json::from_slice(&text[..end]) {
        Ok(Value::Object(doc)) => Ok(doc),
        Ok(_) => Err(invalid_arg!("glTF: the JSON is not an object")),
        Err(e) => Err(invalid_arg!("not a GLB and not glTF JSON: {e}")),
    }
}

/// Buffer 0's `byteLength` and `uri`, if the file has buffers.
fn buffer0(doc: &Map<String, Value>) -> Result<Option<(usize, Option<&str>)>> {
    let Some(buffers) = doc.get("buffers") else {
        return Ok(None);
    };
    let b = match buffers.as_array().map(Vec::as_slice) {
        Some([]) => return Ok(None),
        Some([b, ..]) => b,
        None => return Err(invalid_arg!("glTF: `buffers` is not an array")),
    };
    let len = b["byteLength"]
        .as_u64()
        .and_then(|l| usize::try_from(l).ok())
        .ok_or_else(|| invalid_arg!("glTF: buffer 0 has no whole `byteLength`"))?;
    match b.get("uri") {
        None => Ok(Some((len, None))),
        Some(Value::String(u)) => Ok(Some((len, Some(u)))),
        Some(_) => Err(invalid_arg!("glTF: buffer 0's `uri` is not a string")),
    }
}

/// A base64 `data:` URI's header (up to `;base64,`) and bytes; any other URI is an external
/// file, refused.
fn decode_data_uri(uri: &str) -> Result<(&str, Vec<u8>)> {
    if !uri.starts_with("data:") {
        return Err(invalid_arg!(
            "glTF: buffer 0 is an external file (`{}`): libflame would have to rewrite it; save \
             a .glb, or a .gltf with its buffers embedded",
            uri.chars().take(60).collect::<String>()
        ));
    }
    let split = uri
        .find(";base64,")
        .map(|k| k + 8)
        .ok_or_else(|| invalid_arg!("glTF: buffer 0's data URI is not base64"))?;
    let (prefix, payload) = uri.split_at(split);
    let engine = base64::engine::GeneralPurpose::new(
        &base64::alphabet::STANDARD,
        base64::engine::GeneralPurposeConfig::new()
            .with_decode_padding_mode(base64::engine::DecodePaddingMode::Indifferent)
            .with_decode_allow_trailing_bits(true),
    );
    let data = engine
        .decode(payload)
        .map_err(|e| invalid_arg!("glTF: buffer 0's data URI: {e}"))?;
    Ok((prefix, data))
}

const ORIGIN: Affine = Affine {
    l: IDENTITY,
    t: [0.0; 3],
};

/// A node's transform from the file.
#[derive(Clone, Copy, Debug)]
struct Node {
    t: Vec3,
    /// The rotation alone (scale-free), for world rotations.
    r: Mat3,
    s: Vec3,
    affine: Affine,
    matrix: bool,
}

/// The file's nodes: parents, transforms, names, and an order with parents first.
struct NodeTree {
    parents: Vec<Option<usize>>,
    nodes: Vec<Node>,
    names: Vec<String>,
    order: Vec<usize>,
}

impl NodeTree {
    fn new(doc: &Map<String, Value>) -> Result<NodeTree> {
        let list = match doc.get("nodes") {
            None => &[][..],
            Some(Value::Array(a)) => a.as_slice(),
            Some(_) => return Err(invalid_arg!("glTF: `nodes` is not an array")),
        };
        let n = list.len();
        let mut parents = vec![None; n];
        let mut children = vec![Vec::new(); n];
        let mut nodes = Vec::with_capacity(n);
        let mut names = Vec::with_capacity(n);
        for (i, node) in list.iter().enumerate() {
            let obj = node
                .as_object()
                .ok_or_else(|| invalid_arg!("glTF: node {i} is not an object"))?;
            for c in obj
                .get("children")
                .and_then(Value::as_array)
                .map_or(&[][..], Vec::as_slice)
            {
                let c = c
                    .as_u64()
                    .map(|c| c as usize)
                    .filter(|&c| c < n && c != i)
                    .ok_or_else(|| invalid_arg!("glTF: node {i} has a bad child index {c}"))?;
                if parents[c].replace(i).is_some() {
                    return Err(invalid_arg!("glTF: node {c} has two parents"));
                }
                children[i].push(c);
            }
            nodes.push(node_transform(obj, i)?);
            names.push(match obj.get("name").and_then(Value::as_str) {
                Some(s) if !s.is_empty() => s.to_string(),
                _ => format!("node{i}"),
            });
        }
        // Parents first from the roots; a node never reached is on a cycle.
        let mut order: Vec<usize> = (0..n).filter(|&i| parents[i].is_none()).collect();
        let mut k = 0;
        while k < order.len() {
            let kids = &children[order[k]];
            order.extend(kids);
            k += 1;
        }
        if order.len() != n {
            return Err(invalid_arg!("glTF: the nodes' `children` form a cycle"));
        }
        Ok(NodeTree {
            parents,
            nodes,
            names,
            order,
        })
    }
}

/// `n` finite numbers at `obj[key]`, or `default`.
fn numbers<const N: usize>(
    obj: &Map<String, Value>,
    key: &str,
    i: usize,
    default: [f64; N],
) -> Result<[f64; N]> {
    let Some(v) = obj.get(key) else {
        return Ok(default);
    };
    let bad = || invalid_arg!("glTF: node {i}'s `{key}` is not {N} finite numbers");
    let a = v.as_array().filter(|a| a.len() == N).ok_or_else(bad)?;
    let mut out = [0.0; N];
    for (o, x) in out.iter_mut().zip(a) {
        *o = x.as_f64().filter(|x| x.is_finite()).ok_or_else(bad)?;
    }
    Ok(out)
}

fn node_transform(obj: &Map<String, Value>, i: usize) -> Result<Node> {
    if obj.contains_key("matrix") {
        let m = numbers::<16>(obj, "matrix", i, [0.0; 16])?;
        let l = [[m[0], m[4], m[8]], [m[1], m[5], m[9]], [m[2], m[6], m[10]]];
        // The rotation part: columns normalised (a matrix with shear has none; gltf_rig
        // refuses a rest transform with shear).
        let mut r = l;
        let mut s = [0.0; 3];
        for (c, sc) in s.iter_mut().enumerate() {
            *sc = (0..3).map(|k| l[k][c] * l[k][c]).sum::<f64>().sqrt();
            if *sc < 1e-12 {
                return Err(invalid_arg!("glTF: node {i}'s `matrix` has a zero scale"));
            }
            for row in &mut r {
                row[c] /= *sc;
            }
        }
        let r = rotation::quat_to_matrix(&rotation::to_quat(&r));
        return Ok(Node {
            t: [m[12], m[13], m[14]],
            r,
            s,
            affine: Affine {
                l,
                t: [m[12], m[13], m[14]],
            },
            matrix: true,
        });
    }
    let t = numbers::<3>(obj, "translation", i, [0.0; 3])?;
    let [x, y, z, w] = numbers::<4>(obj, "rotation", i, [0.0, 0.0, 0.0, 1.0])?;
    if x == 0.0 && y == 0.0 && z == 0.0 && w == 0.0 {
        return Err(invalid_arg!(
            "glTF: node {i}'s rotation is a zero quaternion"
        ));
    }
    let r = rotation::quat_to_matrix(&[w, x, y, z]);
    let s = numbers::<3>(obj, "scale", i, [1.0; 3])?;
    Ok(Node {
        t,
        r,
        s,
        affine: Affine::trs(t, &r, &s),
        matrix: false,
    })
}

/// The rig's bones' nodes, checked against the file: the rig must have been read from it.
fn source_nodes(doc: &Map<String, Value>, rig: &Rig, tree: &NodeTree) -> Result<Vec<usize>> {
    let (skin, nodes) = match rig.source() {
        RigSource::Gltf { skin, nodes } => (Some(*skin), nodes),
        RigSource::Vrm { skin, nodes, .. } => (*skin, nodes),
        _ => {
            return Err(invalid_arg!(
                "the rig was not read from a glTF/VRM file: there is no file to hand back"
            ))
        }
    };
    let count = tree.nodes.len();
    for (b, &n) in nodes.iter().enumerate() {
        if n >= count {
            return Err(invalid_arg!(
                "the rig's bone `{}` is node {n}, but the file has {count} nodes: not the file the rig was read from",
                rig.name(b)
            ));
        }
        if tree.names[n] != rig.name(b) {
            return Err(invalid_arg!(
                "the rig's bone `{}` is node {n}, which the file names `{}`: not the file the rig was read from",
                rig.name(b),
                tree.names[n]
            ));
        }
        if tree.nodes[n].matrix {
            return Err(invalid_arg!(
                "joint node {n} (`{}`) has a `matrix`: glTF animates only nodes with translation, rotation and scale",
                rig.name(b)
            ));
        }
    }
    if let Some(skin) = skin {
        let joints = doc
            .get("skins")
            .and_then(|s| s.get(skin))
            .and_then(|s| s.get("joints"))
            .and_then(Value::as_array)
            .ok_or_else(|| {
                invalid_arg!("the file has no skin {skin}: not the file the rig was read from")
            })?;
        let mut listed: Vec<u64> = joints.iter().filter_map(Value::as_u64).collect();
        let mut ours: Vec<u64> = nodes.iter().map(|&n| n as u64).collect();
        listed.sort_unstable();
        ours.sort_unstable();
        if listed != ours {
            return Err(invalid_arg!(
                "skin {skin}'s joints are not the rig's bones: not the file the rig was read from"
            ));
        }
    }
    Ok(nodes.clone())
}

/// The animation: per frame, the node tree posed top down, joint nodes at the motion's world
/// rotations, the hips node at its world position (module doc).
fn clip_of(
    rig: &Rig,
    m: &RigMotion,
    tree: &NodeTree,
    joints: &[usize],
    name: &str,
) -> Result<Clip> {
    let count = tree.nodes.len();
    let mut bone_of = vec![None; count];
    for (b, &n) in joints.iter().enumerate() {
        bone_of[n] = Some(b);
    }
    let nb = rig.bone_count();
    let mut rotations = vec![IDENTITY; m.frames * nb];
    // Translation tracks of the bones whose translation moves: the hips, and bones beside the
    // body placed from another bone (`RigMotion::moving`).
    let mut moves = vec![false; nb];
    for &b in &m.moving {
        if b >= nb {
            return Err(invalid_arg!("moving bone {b} is past the rig's {nb} bones"));
        }
        moves[b] = true;
    }
    moves[m.hips_bone] = true;
    let mut tracks: Vec<Vec<f32>> = (0..nb)
        .map(|b| Vec::with_capacity(if moves[b] { m.frames * 3 } else { 0 }))
        .collect();
    let mut world_rot = vec![IDENTITY; count];
    let mut world = vec![ORIGIN; count];
    for t in 0..m.frames {
        let g = m.world_frame(t);
        for &n in &tree.order {
            let node = &tree.nodes[n];
            let (q_parent, a_parent) = match tree.parents[n] {
                Some(p) => (world_rot[p], world[p]),
                None => (IDENTITY, ORIGIN),
            };
            let Some(b) = bone_of[n] else {
                world_rot[n] = rotation::mul(&q_parent, &node.r);
                world[n] = a_parent.then(&node.affine);
                continue;
            };
            let r = rotation::mul(&rotation::transpose(&q_parent), &g[b]);
            rotations[b * m.frames + t] = r;
            let tr = if moves[b] {
                let p = a_parent.solve(&m.positions_frame(t)[b]).ok_or_else(|| {
                    invalid_arg!("the parent node of `{}` has a zero scale", rig.name(b))
                })?;
                tracks[b].extend(p.map(|v| v as f32));
                p
            } else {
                node.t
            };
            world_rot[n] = g[b];
            world[n] = a_parent.then(&Affine::trs(tr, &r, &node.s));
        }
    }
    let times: Vec<f32> = (0..m.frames).map(|t| (t as f64 / m.fps) as f32).collect();
    let mut clip = Clip::new(name, &times)?;
    for (b, &n) in joints.iter().enumerate() {
        let track = &rotations[b * m.frames..(b + 1) * m.frames];
        clip.channel(n, "rotation", &quaternion_track(track.iter().copied()))?;
    }
    for (b, &n) in joints.iter().enumerate() {
        if moves[b] {
            clip.channel(n, "translation", &tracks[b])?;
        }
    }
    Ok(clip)
}
