//! The C ABI of [`crate::retarget`]: the user's rig ([`FlameRig`], from a glTF/GLB/VRM or BVH
//! file, or from the bones an engine holds), its bone map ([`FlameBoneMap`]) and a retarget
//! ([`FlameRetarget`]) that puts a model's poses onto it, read from a session, a stream or
//! one frame at a time.
//!
//! **Axes.** A rig from a file is in the file's axes (glTF's for glTF/VRM: right-handed, Y
//! up, metres). A rig from an engine's bones is given in the engine's convention and carried
//! into glTF's axes first (`crate::retarget::engine`): the retarget finds a rig's forward with
//! a cross product, so a left-handed rig (Unity, Unreal) taken as it is would have every
//! motion mirrored front to back. Poses come back in the rig's own convention unless the
//! params ask for another.
//!
//! **Threads.** Rigs and bone maps are immutable: any thread, any number at once. A retarget
//! is shareable too: its per-frame scratch sits behind a lock, so calls on one retarget from
//! several threads run one after another and give the same values as from one thread.

use std::ffi::{c_char, CString};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use super::cleanup::{finish_arg, FlameCleanupParams};
use super::errors::{catch_quietly, guard, Fail};
use super::handles::{model_ref, session_ref, FlameModel, FlameSession};
use super::poses::{FlameConvention, FlameLayout};
use super::stream::{flame_stream_read_cleaned, FlameStream};
use super::{check_size, slice_arg, str_arg, struct_arg, write_out, FlameStatus, FlameWhich};
use crate::error::{invalid_arg, Error};
use crate::motion::rotation::{Mat3, Vec3, IDENTITY};
use crate::motion::{Convention, Format, Poses};
use crate::retarget::bonemap::BoneMap;
use crate::retarget::engine::{self, Axes, EngineBone};
use crate::retarget::rig::MAX_BONES;
use crate::retarget::{bvh_rig, gltf_rig, Options, Rig, RigPose, Target};
use crate::session::Which;

/// `kind` of [`flame_rig_load`]: tell the format from the bytes (GLB magic `glTF`, a JSON
/// object, or a BVH `HIERARCHY`).
pub const FLAME_RIG_FORMAT_GUESS: u32 = 0;
/// `kind` of [`flame_rig_load`]: glTF 2.0 (`.glb`, or `.gltf` with its buffers embedded as
/// data URIs), VRM 0.x and 1.0 included.
pub const FLAME_RIG_FORMAT_GLTF: u32 = 1;
/// `kind` of [`flame_rig_load`]: a BVH file's hierarchy (its MOTION section is not read).
pub const FLAME_RIG_FORMAT_BVH: u32 = 2;

/// A rig: the user's skeleton (bone names, parents, rest pose). Immutable: share it between
/// threads freely. Bones are numbered as [`flame_rig_bone_name`] lists them: for a rig from
/// [`flame_rig_from_bones`], in the order they were given; for a file's, parents first.
pub struct FlameRig {
    rig: Rig,
    /// Tells bone maps made for this rig from those of others.
    id: u64,
    /// The convention its poses are given in by default: glTF for glTF/VRM files, the
    /// engine's for engine bones, `None` for a BVH file (whose axes are its own).
    own: Option<Convention>,
    /// Bone `i` of the ABI is rig bone `order[i]`.
    order: Vec<usize>,
    /// Rig bone `b` is bone `of[b]` of the ABI.
    of: Vec<usize>,
    names: Vec<CString>,
}

/// A bone map: which bone of one rig is which humanoid bone (hips, spine, upper arms...).
/// Immutable; only usable with the rig it was made for.
pub struct FlameBoneMap {
    map: BoneMap,
    rig_id: u64,
}

/// One bone of [`flame_rig_from_bones`]: its rest transform relative to its parent (`T · R ·
/// S`, what Unity's `localPosition`/`localRotation`/`localScale` and Unreal's reference pose
/// hold) in the convention the call names. Set `struct_size = sizeof(FlameRigBone)`.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameRigBone {
    /// `sizeof(FlameRigBone)`; every bone of an array has the same.
    pub struct_size: u32,
    /// Index of the parent in the same array (any order: a parent may come after its
    /// children), -1 for a root.
    pub parent: i32,
    /// A unique name (UTF-8, NUL-terminated); automatic bone maps read it (`Hips`,
    /// `mixamorig:LeftArm`, `upperarm_l`...). Read only during the call.
    pub name: *const c_char,
    /// Position relative to the parent, in the convention's unit.
    pub translation: [f32; 3],
    /// Rotation relative to the parent, quaternion x, y, z, w (normalised by the call).
    pub rotation: [f32; 4],
    pub scale: [f32; 3],
}

/// How [`flame_retarget_new`] drives a rig. Initialise with [`flame_retarget_params_default`].
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameRetargetParams {
    /// `sizeof(FlameRetargetParams)`.
    pub struct_size: u32,
    /// A [`FlameConvention`] value for the poses read: `FLAME_CONVENTION_NATIVE` (0, default)
    /// = the rig's own (glTF axes in metres for a glTF/VRM file, the file's axes and unit for a
    /// BVH file, the engine's convention for [`flame_rig_from_bones`]). Any other value
    /// carries the poses from glTF axes into it (`INVALID_ARGUMENT` for a BVH rig, whose
    /// axes are unknown).
    pub convention: i32,
    /// Nonzero (default 1): two-bone IK on the legs puts each ankle where the source's is, so
    /// a rig of other proportions keeps planted feet planted.
    pub feet: u32,
    /// Nonzero (default 0): the same on the arms, for the wrists.
    pub hands: u32,
    /// NULL (default) = the automatic bone map ([`flame_bone_map_auto`]); otherwise a map made
    /// for the same rig. Read only during [`flame_retarget_new`].
    pub map: *const FlameBoneMap,
}

/// A model's poses onto a rig: the rig and its bone map, copied, so both may be freed after
/// [`flame_retarget_new`]. Shareable between threads (calls are serialised on a lock).
pub struct FlameRetarget {
    target: Target,
    /// The motion format whose skeleton drives the rig (the model's).
    format: Format,
    options: Options,
    axes: Axes,
    /// Output bone `i` is rig bone `order[i]` (the rig's ABI order).
    order: Vec<usize>,
    scratch: Mutex<Scratch>,
}

/// Per-frame storage, made once per retarget: nothing is allocated per frame.
struct Scratch {
    pose: RigPose,
    world: Vec<Mat3>,
    positions: Vec<Vec3>,
}

fn next_rig_id() -> u64 {
    static NEXT: AtomicU64 = AtomicU64::new(1);
    NEXT.fetch_add(1, Ordering::Relaxed)
}

impl FlameRig {
    fn new(rig: Rig, own: Option<Convention>, order: Vec<usize>) -> FlameRig {
        let mut of = vec![0; order.len()];
        for (i, &b) in order.iter().enumerate() {
            of[b] = i;
        }
        let names = order
            .iter()
            .map(|&b| CString::new(rig.name(b).replace('\0', " ")).unwrap_or_default())
            .collect();
        FlameRig {
            id: next_rig_id(),
            own,
            of,
            order,
            names,
            rig,
        }
    }
}

unsafe fn rig_ref<'a>(rig: *const FlameRig) -> Result<&'a FlameRig, Fail> {
    rig.as_ref()
        .ok_or_else(|| invalid_arg!("`rig` is NULL").into())
}

unsafe fn retarget_ref<'a>(r: *const FlameRetarget) -> Result<&'a FlameRetarget, Fail> {
    r.as_ref()
        .ok_or_else(|| invalid_arg!("`retarget` is NULL").into())
}

/// `map`, checked to be `rig`'s.
unsafe fn map_ref<'a>(
    map: *const FlameBoneMap,
    rig: &FlameRig,
    name: &str,
) -> Result<&'a FlameBoneMap, Fail> {
    let m = map
        .as_ref()
        .ok_or_else(|| Fail::from(invalid_arg!("`{name}` is NULL")))?;
    if m.rig_id != rig.id {
        return Err(invalid_arg!(
            "`{name}` was made for another rig: a bone map names the bones of the rig it was made with"
        )
        .into());
    }
    Ok(m)
}

/// Reads a rig from a file's bytes: `kind` is a `FLAME_RIG_FORMAT_*` value (0 = tell from the
/// content), `skin` the glTF skin to use (NULL: the file's only skin, or for a VRM file the one
/// holding its humanoid bones; must be NULL for BVH). glTF/VRM: the skin's joints, their bind
/// pose, a VRM file's declared humanoid map; BVH: the hierarchy, its unit guessed from its size
/// (above 20 units across: centimetres). The bytes are read only during the call. Errors
/// (`INVALID_ARGUMENT`, message naming the node, bone or line): truncated or malformed files,
/// unknown formats, a skin not found, cycles, zero scales, more than 4096 bones. Free the rig
/// with [`flame_rig_free`].
///
/// # Safety
/// `bytes` points to `len` readable bytes; `skin` is NULL or a NUL-terminated string; `out`
/// points to a writable `FlameRig *`.
#[no_mangle]
pub unsafe extern "C" fn flame_rig_load(
    bytes: *const u8,
    len: usize,
    kind: u32,
    skin: *const c_char,
    out: *mut *mut FlameRig,
) -> FlameStatus {
    guard(|| {
        if out.is_null() {
            return Err(invalid_arg!("`out` is NULL").into());
        }
        let bytes = slice_arg(bytes, len, "bytes")?;
        let skin = if skin.is_null() {
            None
        } else {
            Some(str_arg(skin, "skin")?)
        };
        let kind = match kind {
            FLAME_RIG_FORMAT_GUESS => guess_format(bytes)?,
            FLAME_RIG_FORMAT_GLTF | FLAME_RIG_FORMAT_BVH => kind,
            k => {
                return Err(invalid_arg!(
                    "unknown rig file kind {k} (0 guess, 1 glTF/GLB/VRM, 2 BVH)"
                )
                .into())
            }
        };
        let (rig, own) = if kind == FLAME_RIG_FORMAT_GLTF {
            (gltf_rig::read(bytes, skin)?, Some(Convention::Gltf))
        } else {
            if skin.is_some() {
                return Err(invalid_arg!("`skin` names a glTF skin; a BVH file has none").into());
            }
            let text = std::str::from_utf8(bytes)
                .map_err(|e| invalid_arg!("BVH: the file is not UTF-8 text ({e})"))?;
            (bvh_rig::read(text, None)?, None)
        };
        let order = (0..rig.bone_count()).collect();
        out.write(Box::into_raw(Box::new(FlameRig::new(rig, own, order))));
        Ok(())
    })
}

/// The format of a rig file by its first bytes.
fn guess_format(bytes: &[u8]) -> Result<u32, Fail> {
    let start = bytes.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(bytes);
    let start = &start[start
        .iter()
        .position(|b| !b.is_ascii_whitespace())
        .unwrap_or(start.len())..];
    if bytes.starts_with(b"glTF") || start.starts_with(b"{") {
        Ok(FLAME_RIG_FORMAT_GLTF)
    } else if start.starts_with(b"HIERARCHY") {
        Ok(FLAME_RIG_FORMAT_BVH)
    } else {
        Err(invalid_arg!(
            "the rig file is neither glTF (GLB magic `glTF` or a JSON object) nor BVH (starting \
             with HIERARCHY); {} bytes",
            bytes.len()
        )
        .into())
    }
}

/// A rig from bones an engine holds (Unreal's reference skeleton, Unity's Transforms):
/// `count` bones (1 to 4096) whose rest transforms are in `convention` (a [`FlameConvention`]
/// value other than native: `FLAME_CONVENTION_UNITY` for Unity, `FLAME_CONVENTION_UNREAL` for
/// Unreal with centimetres). They are carried into right-handed glTF axes in metres before the
/// rig is made (positions `p' = M p / s`, rotations `R' = M R M⁻¹`, keeping up, forward and
/// left), because the retarget derives the rig's forward from a cross product: a left-handed
/// rig taken as it is would get every motion mirrored front to back. Retarget poses come back
/// in `convention` by default, bones numbered as given. The array and names are read only
/// during the call. Errors name the bone: a wrong `struct_size`, a NULL or repeated name, a
/// parent out of range or a cycle, a zero or non-finite quaternion, a zero scale.
///
/// # Safety
/// `bones` points to `count` readable `FlameRigBone`s; `out` points to a writable
/// `FlameRig *`.
#[no_mangle]
pub unsafe extern "C" fn flame_rig_from_bones(
    bones: *const FlameRigBone,
    count: usize,
    convention: i32,
    out: *mut *mut FlameRig,
) -> FlameStatus {
    guard(|| {
        if out.is_null() {
            return Err(invalid_arg!("`out` is NULL").into());
        }
        if count == 0 || count > MAX_BONES {
            return Err(
                invalid_arg!("a rig needs between 1 and {MAX_BONES} bones, got {count}").into(),
            );
        }
        let convention = super::poses::convention(convention)?;
        let given = slice_arg(bones, count, "bones")?;
        let mut list = Vec::with_capacity(count);
        for (i, b) in given.iter().enumerate() {
            check_size(
                b.struct_size,
                std::mem::size_of::<FlameRigBone>(),
                &format!("bones[{i}]"),
            )?;
            let name = str_arg(b.name, &format!("bones[{i}].name"))?;
            let parent = match b.parent {
                -1 => None,
                p if p >= 0 && (p as usize) < count => Some(p as usize),
                p => {
                    return Err(invalid_arg!(
                        "bones[{i}] (`{name}`): parent {p} is neither -1 nor the index of one of the {count} bones"
                    )
                    .into())
                }
            };
            let f = |v: &[f32]| v.iter().map(|&x| x as f64).collect::<Vec<_>>();
            let (t, r, s) = (f(&b.translation), f(&b.rotation), f(&b.scale));
            list.push(EngineBone {
                name: name.to_string(),
                parent,
                translation: [t[0], t[1], t[2]],
                rotation: [r[0], r[1], r[2], r[3]],
                scale: [s[0], s[1], s[2]],
            });
        }
        let (rig, order) = engine::rig_from_bones(&list, convention)?;
        out.write(Box::into_raw(Box::new(FlameRig::new(
            rig,
            Some(convention),
            order,
        ))));
        Ok(())
    })
}

/// Frees a rig (NULL is fine). Retargets made from it stay valid (they hold a copy); bone
/// maps made for it can no longer be used with a rig.
///
/// # Safety
/// `rig` is NULL or a rig not yet freed; its bone names' pointers die with it.
#[no_mangle]
pub unsafe extern "C" fn flame_rig_free(rig: *mut FlameRig) {
    if !rig.is_null() {
        catch_quietly(|| drop(Box::from_raw(rig)));
    }
}

/// The rig's bone count.
///
/// # Safety
/// `rig` is a live rig; `out` points to a writable `size_t`.
#[no_mangle]
pub unsafe extern "C" fn flame_rig_bone_count(
    rig: *const FlameRig,
    out: *mut usize,
) -> FlameStatus {
    guard(|| write_out(out, rig_ref(rig)?.order.len(), "out"))
}

unsafe fn bone_arg(rig: &FlameRig, bone: usize) -> Result<usize, Fail> {
    if bone >= rig.order.len() {
        return Err(invalid_arg!("bone {bone} is past the rig's {}", rig.order.len()).into());
    }
    Ok(bone)
}

/// Bone `bone`'s name (UTF-8, NUL-terminated) into `*out`: owned by the rig, valid until
/// [`flame_rig_free`].
///
/// # Safety
/// `rig` is a live rig; `out` points to a writable `const char *`.
#[no_mangle]
pub unsafe extern "C" fn flame_rig_bone_name(
    rig: *const FlameRig,
    bone: usize,
    out: *mut *const c_char,
) -> FlameStatus {
    guard(|| {
        let r = rig_ref(rig)?;
        let b = bone_arg(r, bone)?;
        write_out(out, r.names[b].as_ptr(), "out")
    })
}

/// Bone `bone`'s parent into `*out` (-1 for a root).
///
/// # Safety
/// `rig` is a live rig; `out` points to a writable `int32_t`.
#[no_mangle]
pub unsafe extern "C" fn flame_rig_bone_parent(
    rig: *const FlameRig,
    bone: usize,
    out: *mut i32,
) -> FlameStatus {
    guard(|| {
        let r = rig_ref(rig)?;
        let b = bone_arg(r, bone)?;
        let parent = r.rig.parent(r.order[b]).map_or(-1, |p| r.of[p] as i32);
        write_out(out, parent, "out")
    })
}

fn boxed_map(map: BoneMap, rig: &FlameRig) -> *mut FlameBoneMap {
    Box::into_raw(Box::new(FlameBoneMap {
        map,
        rig_id: rig.id,
    }))
}

/// The automatic bone map of `rig`: the map a VRM file declares, else one read from the bone
/// names (Mixamo, Unreal/UE5, Unity/VRM, Rigify, Character Creator, SMPL, Biped). Bones it
/// cannot find stay unmapped: [`flame_retarget_new`] then lists the missing ones, and
/// [`flame_bone_map_to_json`] shows what was found. `INVALID_ARGUMENT` when the names found
/// contradict the hierarchy (the message names the bones). Free with [`flame_bone_map_free`].
///
/// # Safety
/// `rig` is a live rig; `out` points to a writable `FlameBoneMap *`.
#[no_mangle]
pub unsafe extern "C" fn flame_bone_map_auto(
    rig: *const FlameRig,
    out: *mut *mut FlameBoneMap,
) -> FlameStatus {
    guard(|| {
        let r = rig_ref(rig)?;
        if out.is_null() {
            return Err(invalid_arg!("`out` is NULL").into());
        }
        let map = BoneMap::auto(&r.rig)?;
        out.write(boxed_map(map, r));
        Ok(())
    })
}

/// A bone map from JSON over `base` (NULL: over nothing): an object whose keys are VRM 1.0
/// humanoid bone names (`"hips"`, `"spine"`, `"leftUpperArm"`...; any case) and whose values
/// are the rig's bone names or `null`, e.g. `{"hips": "pelvis", "leftHand": "hand_l"}`. Keys the
/// JSON gives replace `base`'s. `INVALID_ARGUMENT` with the key or name: invalid JSON, over
/// 1 MiB, an unknown key, a bone the rig does not have (with the nearest names), one bone for
/// two keys, a map that contradicts the hierarchy, a `base` made for another rig.
///
/// # Safety
/// `rig` is a live rig; `json` a NUL-terminated UTF-8 string; `base` NULL or a live map;
/// `out` points to a writable `FlameBoneMap *`.
#[no_mangle]
pub unsafe extern "C" fn flame_bone_map_from_json(
    rig: *const FlameRig,
    json: *const c_char,
    base: *const FlameBoneMap,
    out: *mut *mut FlameBoneMap,
) -> FlameStatus {
    guard(|| {
        let r = rig_ref(rig)?;
        if out.is_null() {
            return Err(invalid_arg!("`out` is NULL").into());
        }
        let json = str_arg(json, "json")?;
        let base = if base.is_null() {
            None
        } else {
            Some(map_ref(base, r, "base")?.map.clone())
        };
        let map = BoneMap::from_json(&r.rig, json, base)?;
        out.write(boxed_map(map, r));
        Ok(())
    })
}

/// The map as JSON (every humanoid bone, `null` when unmapped): what
/// [`flame_bone_map_from_json`] reads, for a user to edit. Size protocol: with `buf` NULL,
/// `*len` receives the bytes needed, the terminating NUL included; otherwise `cap` must be at
/// least that (`BUFFER_TOO_SMALL` otherwise, `*len` set to the size) and the NUL-terminated
/// JSON is written, `*len` receiving its size with the NUL.
///
/// # Safety
/// `map` and `rig` are live (the map made for the rig); `buf` is NULL or points to `cap`
/// writable bytes; `len` points to a writable `size_t`.
#[no_mangle]
pub unsafe extern "C" fn flame_bone_map_to_json(
    map: *const FlameBoneMap,
    rig: *const FlameRig,
    buf: *mut c_char,
    cap: usize,
    len: *mut usize,
) -> FlameStatus {
    guard(|| {
        let r = rig_ref(rig)?;
        let m = map_ref(map, r, "map")?;
        if len.is_null() {
            return Err(invalid_arg!("`len` is NULL").into());
        }
        let mut bytes = m.map.to_json(&r.rig).into_bytes();
        bytes.push(0);
        super::copy_out(&bytes, buf as *mut u8, cap, len, "bytes")
    })
}

/// Frees a bone map (NULL is fine).
///
/// # Safety
/// `map` is NULL or a map not yet freed.
#[no_mangle]
pub unsafe extern "C" fn flame_bone_map_free(map: *mut FlameBoneMap) {
    if !map.is_null() {
        catch_quietly(|| drop(Box::from_raw(map)));
    }
}

fn default_params() -> FlameRetargetParams {
    FlameRetargetParams {
        struct_size: std::mem::size_of::<FlameRetargetParams>() as u32,
        convention: FlameConvention::Native as i32,
        feet: 1,
        hands: 0,
        map: std::ptr::null(),
    }
}

/// Fills `*params` with the defaults: the rig's own convention, feet IK on, hands IK off, the
/// automatic bone map.
///
/// # Safety
/// `params` points to writable memory for a `FlameRetargetParams`.
#[no_mangle]
pub unsafe extern "C" fn flame_retarget_params_default(
    params: *mut FlameRetargetParams,
) -> FlameStatus {
    guard(|| write_out(params, default_params(), "params"))
}

/// A retarget of `model`'s poses (its motion format's skeleton: SMPL-24 or HumanML3D-22) onto
/// `rig`, with `params` (NULL = [`flame_retarget_params_default`]). The rig and the map are
/// copied: either may be freed afterwards; the model is not kept. Errors
/// (`INVALID_ARGUMENT`): a required humanoid bone unmapped (hips, spine, head, upper and lower
/// arms and legs, hands, feet; the message lists what is missing, what was found and the
/// rig's bone names), a map made for another rig, a mapped bone of zero length, an unknown
/// convention, a convention asked of a BVH rig. Free with [`flame_retarget_free`].
///
/// # Safety
/// `model` and `rig` are live; `params` is NULL or a valid `FlameRetargetParams`; `out`
/// points to a writable `FlameRetarget *`.
#[no_mangle]
pub unsafe extern "C" fn flame_retarget_new(
    model: *const FlameModel,
    rig: *const FlameRig,
    params: *const FlameRetargetParams,
    out: *mut *mut FlameRetarget,
) -> FlameStatus {
    guard(|| {
        let format = model_ref(model)?.model().motion_format();
        let r = rig_ref(rig)?;
        if out.is_null() {
            return Err(invalid_arg!("`out` is NULL").into());
        }
        let p = if params.is_null() {
            default_params()
        } else {
            *struct_arg(params, |p| p.struct_size, "params")?
        };
        let axes = match (p.convention, r.own) {
            (0, Some(own)) if own != Convention::Gltf => Axes::to(own, r.rig.metres_per_unit())?,
            (0, _) => Axes::identity(),
            (c, Some(_)) => Axes::to(super::poses::convention(c)?, r.rig.metres_per_unit())?,
            (c, None) => {
                super::poses::convention(c)?;
                return Err(invalid_arg!(
                    "params.convention {c}: a BVH rig's axes are its file's own (BVH does not \
                     say which is up), so its poses are given in them: use \
                     FLAME_CONVENTION_NATIVE (0)"
                )
                .into());
            }
        };
        let skeleton = format.skeleton();
        let target = if p.map.is_null() {
            Target::auto(skeleton, r.rig.clone())?
        } else {
            let m = map_ref(p.map, r, "params.map")?;
            Target::new(skeleton, r.rig.clone(), m.map.clone())?
        };
        let joints = skeleton.joint_count();
        let scratch = Scratch {
            pose: RigPose::new(&target),
            world: vec![IDENTITY; joints],
            positions: vec![[0.0; 3]; joints],
        };
        out.write(Box::into_raw(Box::new(FlameRetarget {
            target,
            format,
            options: Options {
                feet: p.feet != 0,
                hands: p.hands != 0,
            },
            axes,
            order: r.order.clone(),
            scratch: Mutex::new(scratch),
        })));
        Ok(())
    })
}

/// Frees a retarget (NULL is fine).
///
/// # Safety
/// `retarget` is NULL or a retarget not yet freed, used by no other thread.
#[no_mangle]
pub unsafe extern "C" fn flame_retarget_free(retarget: *mut FlameRetarget) {
    if !retarget.is_null() {
        catch_quietly(|| drop(Box::from_raw(retarget)));
    }
}

/// The bones each pose has: the rig's, numbered as [`flame_rig_bone_name`] lists them.
///
/// # Safety
/// `retarget` is live; `out` points to a writable `size_t`.
#[no_mangle]
pub unsafe extern "C" fn flame_retarget_bone_count(
    retarget: *const FlameRetarget,
    out: *mut usize,
) -> FlameStatus {
    guard(|| write_out(out, retarget_ref(retarget)?.order.len(), "out"))
}

/// The caller's output buffers for `frames` poses of `bones` bones: each NULL (not wanted) or
/// long enough.
struct Outputs<'a> {
    rotations: Option<&'a mut [f32]>,
    translations: Option<&'a mut [f32]>,
}

unsafe fn outputs<'a>(
    rotations: *mut f32,
    rotations_len: usize,
    translations: *mut f32,
    translations_len: usize,
    frames: usize,
    bones: usize,
) -> Result<Outputs<'a>, Fail> {
    let buffer = |ptr: *mut f32, len: usize, per: usize| -> Result<Option<&mut [f32]>, Fail> {
        if ptr.is_null() {
            return Ok(None);
        }
        let need = frames
            .checked_mul(bones)
            .and_then(|n| n.checked_mul(per))
            .filter(|&n| n <= isize::MAX as usize / 4)
            .ok_or_else(|| invalid_arg!("{frames} frames of {bones} bones is too many"))?;
        if len < need {
            return Err(Fail::BufferTooSmall {
                needed: need,
                given: len,
                unit: "floats",
            });
        }
        // SAFETY: the caller gives `len` ≥ `need` writable floats.
        Ok(Some(std::slice::from_raw_parts_mut(ptr, need)))
    };
    Ok(Outputs {
        rotations: buffer(rotations, rotations_len, 4)?,
        translations: buffer(translations, translations_len, 3)?,
    })
}

impl FlameRetarget {
    fn bones(&self) -> usize {
        self.order.len()
    }

    /// Retargets `frames` source frames (glTF axes: world rotations and positions `[frames ×
    /// joints]`, pelvis positions `[frames]`) into the outputs, one frame at a time through
    /// the scratch pose.
    fn drive(
        &self,
        world: &[Mat3],
        positions: &[Vec3],
        roots: &[Vec3],
        out: &mut Outputs,
    ) -> Result<(), Fail> {
        // The scratch is rewritten whole by every frame: a panic that poisoned it left nothing
        // a later call reads.
        let mut s = self.scratch.lock().unwrap_or_else(|e| e.into_inner());
        self.drive_into(&mut s.pose, world, positions, roots, out)
    }

    /// [`FlameRetarget::drive`] through `pose`.
    fn drive_into(
        &self,
        pose: &mut RigPose,
        world: &[Mat3],
        positions: &[Vec3],
        roots: &[Vec3],
        out: &mut Outputs,
    ) -> Result<(), Fail> {
        let joints = self.format.skeleton().joint_count();
        let n = self.bones();
        for (t, root) in roots.iter().enumerate() {
            let span = t * joints..(t + 1) * joints;
            self.target.pose(
                &world[span.clone()],
                &positions[span],
                root,
                &self.options,
                pose,
            )?;
            let r = out
                .rotations
                .as_deref_mut()
                .map(|o| &mut o[t * n * 4..][..n * 4]);
            let tr = out
                .translations
                .as_deref_mut()
                .map(|o| &mut o[t * n * 3..][..n * 3]);
            engine::write_pose(&self.target, pose, &self.order, &self.axes, r, tr);
        }
        Ok(())
    }

    /// Frames `first..first + count` of decoded poses.
    fn drive_poses(
        &self,
        poses: &Poses,
        first: usize,
        count: usize,
        out: &mut Outputs,
    ) -> Result<(), Fail> {
        let part = poses.frames_range(first, count);
        self.drive(
            &part.global_rotations(Convention::Gltf),
            &part.positions(Convention::Gltf),
            &part.root_translation(Convention::Gltf),
            out,
        )
    }
}

/// Retargeted poses of a session: frames `first..first + count` of the motion
/// [`super::flame_session_read_cleaned`] reads with the same `which` (a [`FlameWhich`]),
/// `flags` (`FLAME_READ_SMOOTH`, `FLAME_READ_RAW_SIGNS`) and `cleanup` (NULL = the raw poses;
/// [`super::flame_cleanup_params_default`] gives game-ready ones: feet locked, the floor at
/// 0), put onto the rig. Per frame and bone: `rotations` `[count][bones][4]` the bone's
/// rotation relative to its parent, quaternion x, y, z, w with w ≥ 0 (rest rotations included:
/// set it as the bone's local rotation); `translations` `[count][bones][3]` its position
/// relative to its parent (every bone's: the rest one except where the retarget moves the
/// bone, as the hips), both in the retarget's convention and unit
/// ([`FlameRetargetParams::convention`]); a top bone's are relative to the scene (for a glTF
/// file, the nodes above the skin's top joint folded in). Either buffer may be NULL when not
/// wanted; a given one must hold `count × bones × 4` (or 3) floats (`BUFFER_TOO_SMALL`).
/// `*out_frames` (may be NULL) receives the frames the read has: call with `count` 0 and NULL
/// buffers to size them (a cleanup's frame rate changes it).
///
/// Errors: a session of a model with another motion format, a range past the frames
/// (`INVALID_ARGUMENT`); no sample yet, or no estimate before a step (`WRONG_STATE`); the
/// session busy on another thread (`WRONG_STATE`). Values are the same for any thread count.
///
/// # Safety
/// `retarget` and `session` are live; `cleanup` is NULL or a valid `FlameCleanupParams`;
/// non-NULL buffers point to their lengths' writable floats; `out_frames` is NULL or writable.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn flame_retarget_read(
    retarget: *const FlameRetarget,
    session: *const FlameSession,
    which: i32,
    flags: u32,
    cleanup: *const FlameCleanupParams,
    first: usize,
    count: usize,
    rotations: *mut f32,
    rotations_len: usize,
    translations: *mut f32,
    translations_len: usize,
    out_frames: *mut usize,
) -> FlameStatus {
    guard(|| {
        let r = retarget_ref(retarget)?;
        let s = session_ref(session)?;
        let mut finish = finish_arg(cleanup)?;
        let mut out = outputs(
            rotations,
            rotations_len,
            translations,
            translations_len,
            count,
            r.bones(),
        )?;
        let which_motion = match which {
            w if w == FlameWhich::Sample as i32 => Which::Sample,
            w if w == FlameWhich::Estimate as i32 => Which::Estimate,
            w => return Err(invalid_arg!("unknown `which` {w} (0 sample, 1 estimate)").into()),
        };
        s.with(|st| {
            let model = Arc::clone(st.session.model());
            if model.motion_format() != r.format {
                return Err(invalid_arg!(
                    "the session's model makes {} motion; the retarget was made for {}",
                    model.motion_format().name(),
                    r.format.name()
                )
                .into());
            }
            // As the session's own reads: a finished loop always wraps onto its last frame.
            if which_motion == Which::Sample && st.session.wraps_to_last() {
                finish.wrap = true;
                finish.wrap_to_last = true;
            }
            let (features, frames) = st.session.motion(which_motion)?;
            let poses = super::poses::decode(&model, features, frames, flags, &finish)?;
            let have = poses.frames();
            if first.checked_add(count).is_none_or(|end| end > have) {
                return Err(invalid_arg!(
                    "{count} frames from frame {first} run past the read's {have} frames"
                )
                .into());
            }
            r.drive_poses(&poses, first, count, &mut out)?;
            if !out_frames.is_null() {
                out_frames.write(have);
            }
            Ok(())
        })
    })
}

/// A failed inner call's status and message as a failure of this call.
fn inner_failure(status: FlameStatus) -> Fail {
    // SAFETY: flame_last_error returns a NUL-terminated string valid until the next call.
    let msg = unsafe { std::ffi::CStr::from_ptr(super::flame_last_error()) }
        .to_string_lossy()
        .into_owned();
    match status {
        FlameStatus::WrongState => Error::WrongState(msg).into(),
        FlameStatus::Internal => std::panic::panic_any(msg),
        _ => Error::InvalidArgument(msg).into(),
    }
}

/// One layout of stream frames through the stream's own read (cleaned when `cleanup` is not
/// NULL), in glTF axes, checked to have `per` floats a frame.
unsafe fn stream_layout(
    stream: *const FlameStream,
    first: u64,
    count: u32,
    layout: FlameLayout,
    cleanup: *const FlameCleanupParams,
    per: usize,
) -> Result<Vec<f32>, Fail> {
    let want = count as usize * per;
    let mut values = vec![0.0f32; want];
    let mut len = 0usize;
    let gltf = FlameConvention::Gltf as i32;
    let status = flame_stream_read_cleaned(
        stream,
        first,
        count,
        layout as i32,
        gltf,
        cleanup,
        values.as_mut_ptr(),
        want,
        &mut len,
    );
    match status {
        FlameStatus::Ok if len == want => Ok(values),
        FlameStatus::Ok | FlameStatus::BufferTooSmall => Err(invalid_arg!(
            "the stream's model makes motion of another skeleton than the retarget's"
        )
        .into()),
        s => Err(inner_failure(s)),
    }
}

/// [`flame_retarget_read`] for a stream: timeline frames `first_frame..first_frame + count`
/// as [`super::flame_stream_read_cleaned`] gives them with `cleanup` (NULL = the raw frames of
/// `flame_stream_read`; the first cleanup passed sets the stream's, as there), put onto the rig.
/// Buffers as `flame_retarget_read`. Frames not generated (or not settled) yet are
/// `WRONG_STATE` (pump more); dropped ones `INVALID_ARGUMENT`; a stream of a model with
/// another skeleton `INVALID_ARGUMENT`.
///
/// # Safety
/// `retarget` and `stream` are live; `cleanup` is NULL or a valid `FlameCleanupParams`;
/// non-NULL buffers point to their lengths' writable floats.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn flame_retarget_read_stream(
    retarget: *const FlameRetarget,
    stream: *const FlameStream,
    first_frame: u64,
    count: u32,
    cleanup: *const FlameCleanupParams,
    rotations: *mut f32,
    rotations_len: usize,
    translations: *mut f32,
    translations_len: usize,
) -> FlameStatus {
    guard(|| {
        let r = retarget_ref(retarget)?;
        if stream.is_null() {
            return Err(invalid_arg!("`stream` is NULL").into());
        }
        let n = count as usize;
        let mut out = outputs(
            rotations,
            rotations_len,
            translations,
            translations_len,
            n,
            r.bones(),
        )?;
        let joints = r.format.skeleton().joint_count();
        let quats = stream_layout(
            stream,
            first_frame,
            count,
            FlameLayout::GlobalQuatXyzw,
            cleanup,
            joints * 4,
        )?;
        let pos = stream_layout(
            stream,
            first_frame,
            count,
            FlameLayout::GlobalPositions,
            cleanup,
            joints * 3,
        )?;
        let root = stream_layout(
            stream,
            first_frame,
            count,
            FlameLayout::RootTranslation,
            cleanup,
            3,
        )?;
        let mut world = Vec::with_capacity(n * joints);
        for (k, q) in quats.chunks_exact(4).enumerate() {
            let q = [0, 1, 2, 3].map(|i| q[i] as f64);
            world.push(engine::quat_xyzw_to_matrix(&q, &|| format!("joint {k}"))?);
        }
        let vec3 = |v: &[f32]| [v[0] as f64, v[1] as f64, v[2] as f64];
        let positions: Vec<Vec3> = pos.chunks_exact(3).map(vec3).collect();
        let roots: Vec<Vec3> = root.chunks_exact(3).map(vec3).collect();
        r.drive(&world, &positions, &roots, &mut out)
    })
}

/// One frame from any source onto the rig: `source_world` `[joints][4]` the source skeleton's
/// world rotations (quaternions x, y, z, w; normalised here) and `source_positions`
/// `[joints][3]` its joint positions, in glTF axes and metres with the floor at height 0
/// (`FLAME_LAYOUT_GLOBAL_QUAT_XYZW` and `FLAME_LAYOUT_GLOBAL_POSITIONS` of a read in
/// `FLAME_CONVENTION_GLTF`), `joints` being the model's (`FlameModelInfo.joint_count`, the
/// SMPL-24 or HumanML3D-22 order); the pelvis is joint 0. Writes one pose as
/// [`flame_retarget_read`] does (either buffer may be NULL). Allocates nothing.
/// `INVALID_ARGUMENT` for lengths that are not the skeleton's, a zero or non-finite quaternion,
/// a non-finite position.
///
/// # Safety
/// `retarget` is live; the source arrays point to their lengths' floats; non-NULL outputs to
/// their lengths' writable floats.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn flame_retarget_pose(
    retarget: *const FlameRetarget,
    source_world: *const f32,
    source_world_len: usize,
    source_positions: *const f32,
    source_positions_len: usize,
    rotations: *mut f32,
    rotations_len: usize,
    translations: *mut f32,
    translations_len: usize,
) -> FlameStatus {
    guard(|| {
        let r = retarget_ref(retarget)?;
        let joints = r.format.skeleton().joint_count();
        for (len, per, name) in [
            (source_world_len, 4, "source_world"),
            (source_positions_len, 3, "source_positions"),
        ] {
            if len != joints * per {
                return Err(invalid_arg!(
                    "`{name}` has {len} floats; the {} skeleton needs {joints} × {per} = {}",
                    r.format.skeleton().name(),
                    joints * per
                )
                .into());
            }
        }
        let q = slice_arg(source_world, source_world_len, "source_world")?;
        let p = slice_arg(source_positions, source_positions_len, "source_positions")?;
        let mut out = outputs(
            rotations,
            rotations_len,
            translations,
            translations_len,
            1,
            r.bones(),
        )?;
        let mut lock = r.scratch.lock().unwrap_or_else(|e| e.into_inner());
        let Scratch {
            pose,
            world,
            positions,
        } = &mut *lock;
        for j in 0..joints {
            let v = [0, 1, 2, 3].map(|i| q[4 * j + i] as f64);
            world[j] = engine::quat_xyzw_to_matrix(&v, &|| format!("source joint {j}"))?;
            positions[j] = [0, 1, 2].map(|i| p[3 * j + i] as f64);
            if !positions[j].iter().all(|v| v.is_finite()) {
                return Err(invalid_arg!("source joint {j}'s position is not finite").into());
            }
        }
        let root = [positions[0]];
        r.drive_into(pose, world, positions, &root, &mut out)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ffi::{
        flame_cleanup_params_default, flame_model_free, flame_model_load, flame_session_free,
        flame_session_new, flame_session_params_default, flame_session_set_prompt,
        flame_session_step, FlameSessionParams,
    };
    use crate::retarget::transfer::tests::test_rig;

    const MODEL: &str = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/tests/fixtures/flame_tiny.safetensors\0"
    );

    /// A finished 12-frame session of the tiny FLAME model.
    unsafe fn session(model: *const FlameModel, steps: u32) -> *mut FlameSession {
        let mut p: FlameSessionParams = std::mem::zeroed();
        flame_session_params_default(&mut p);
        (p.frames, p.steps, p.seed, p.threads) = (12, 2, 7, 1);
        let mut s = std::ptr::null_mut();
        assert_eq!(flame_session_new(model, &p, &mut s), FlameStatus::Ok);
        let prompt = c"a person walks forward.";
        assert_eq!(
            flame_session_set_prompt(s, prompt.as_ptr()),
            FlameStatus::Ok
        );
        for _ in 0..steps {
            assert_eq!(flame_session_step(s, std::ptr::null_mut()), FlameStatus::Ok);
        }
        s
    }

    fn rig_handle() -> *mut FlameRig {
        let (rig, _, _) = test_rig(3);
        let order = (0..rig.bone_count()).collect();
        Box::into_raw(Box::new(FlameRig::new(rig, None, order)))
    }

    #[test]
    fn a_session_read_is_target_motion_on_the_sessions_cleaned_poses() {
        unsafe {
            let mut model = std::ptr::null_mut();
            let path = MODEL.as_ptr() as *const c_char;
            assert_eq!(
                flame_model_load(path, std::ptr::null(), &mut model),
                FlameStatus::Ok
            );
            let rig = rig_handle();
            let mut r = std::ptr::null_mut();
            assert_eq!(
                flame_retarget_new(model, rig, std::ptr::null(), &mut r),
                FlameStatus::Ok
            );
            let n = (*rig).order.len();
            let mut cleanup = std::mem::zeroed();
            flame_cleanup_params_default(&mut cleanup);
            let (mut rot, mut tr) = (vec![0.0f32; 12 * n * 4], vec![0.0f32; 12 * n * 3]);

            // Before the first step there is no sample: a wrong-order call.
            let s = session(model, 0);
            let read = |s, first, count, rot: &mut Vec<f32>, tr: &mut Vec<f32>, frames| {
                flame_retarget_read(
                    r,
                    s,
                    0,
                    0,
                    &cleanup,
                    first,
                    count,
                    rot.as_mut_ptr(),
                    rot.len(),
                    tr.as_mut_ptr(),
                    tr.len(),
                    frames,
                )
            };
            assert_eq!(
                read(s, 0, 12, &mut rot, &mut tr, std::ptr::null_mut()),
                FlameStatus::WrongState
            );
            flame_session_free(s);

            let s = session(model, 2);
            let mut frames = 0usize;
            assert_eq!(
                read(s, 0, 12, &mut rot, &mut tr, &mut frames),
                FlameStatus::Ok
            );
            assert_eq!(frames, 12);

            // The same poses decoded by hand, driven by Target::motion.
            let st = &*s;
            let (poses, target) = st
                .with(|st| {
                    let m = Arc::clone(st.session.model());
                    let finish = finish_arg(&cleanup)?;
                    let (f, k) = st.session.motion(Which::Sample)?;
                    let poses = crate::ffi::poses::decode(&m, f, k, 0, &finish)?;
                    let target = Target::auto(m.motion_format().skeleton(), test_rig(3).0)?;
                    Ok((poses, target))
                })
                .ok()
                .unwrap();
            let motion = target.motion(&poses, 20.0, &Options::default()).unwrap();
            let hips = motion.hips_bone;
            for t in 0..12 {
                for b in 0..n {
                    let q =
                        engine::matrix_to_quat_xyzw(&motion.local_frame(t)[b]).map(|v| v as f32);
                    assert_eq!(rot[(t * n + b) * 4..][..4], q, "frame {t} bone {b}");
                    let want = motion.translation[t * n + b];
                    assert_eq!(
                        tr[(t * n + b) * 3..][..3],
                        want.map(|v| v as f32),
                        "frame {t} bone {b}"
                    );
                }
            }
            // The hips move: the test reads a motion, not the rest pose.
            let h0 = &tr[hips * 3..][..3];
            let h11 = &tr[(11 * n + hips) * 3..][..3];
            assert!(
                h0.iter().zip(h11).any(|(a, b)| (a - b).abs() > 1.0),
                "{h0:?} {h11:?}"
            );

            // A range read is the same bits; from four threads at once too.
            let mut part = (vec![0.0f32; 5 * n * 4], vec![0.0f32; 5 * n * 3]);
            assert_eq!(
                read(s, 4, 5, &mut part.0, &mut part.1, std::ptr::null_mut()),
                FlameStatus::Ok
            );
            assert_eq!(part.0, rot[4 * n * 4..9 * n * 4]);
            let (ra, sa) = (r as usize, s as usize);
            let threads: Vec<_> = (0..4)
                .map(|_| {
                    std::thread::spawn(move || {
                        let mut q = vec![0.0f32; 12 * n * 4];
                        let mut c = std::mem::zeroed();
                        flame_cleanup_params_default(&mut c);
                        // A session busy on another thread is refused, not waited for: retry.
                        loop {
                            let st = flame_retarget_read(
                                ra as *const FlameRetarget,
                                sa as *const FlameSession,
                                0,
                                0,
                                &c,
                                0,
                                12,
                                q.as_mut_ptr(),
                                q.len(),
                                std::ptr::null_mut(),
                                0,
                                std::ptr::null_mut(),
                            );
                            if st != FlameStatus::WrongState {
                                assert_eq!(st, FlameStatus::Ok);
                                return q;
                            }
                        }
                    })
                })
                .collect();
            for t in threads {
                assert_eq!(t.join().unwrap(), rot);
            }

            // One frame from any source: frame 3's cleaned poses in glTF axes, as f32.
            let t = 3;
            let g: Vec<f32> = poses
                .quaternions(&poses.global_rotations(Convention::Gltf)[t * 24..(t + 1) * 24])
                .iter()
                .flat_map(|q| [q[1], q[2], q[3], q[0]])
                .map(|v| v as f32)
                .collect();
            let p: Vec<f32> = poses.positions(Convention::Gltf)[t * 24..(t + 1) * 24]
                .iter()
                .flatten()
                .map(|&v| v as f32)
                .collect();
            let mut one = (vec![0.0f32; n * 4], vec![0.0f32; n * 3]);
            assert_eq!(
                flame_retarget_pose(
                    r,
                    g.as_ptr(),
                    g.len(),
                    p.as_ptr(),
                    p.len(),
                    one.0.as_mut_ptr(),
                    one.0.len(),
                    one.1.as_mut_ptr(),
                    one.1.len()
                ),
                FlameStatus::Ok
            );
            let worst = one
                .0
                .iter()
                .zip(&rot[t * n * 4..(t + 1) * n * 4])
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f32::max);
            assert!(worst < 1e-4, "{worst}");

            // Refusals.
            assert_eq!(
                read(s, 8, 5, &mut rot, &mut tr, std::ptr::null_mut()),
                FlameStatus::InvalidArgument
            );
            assert_eq!(
                read(s, usize::MAX, 2, &mut rot, &mut tr, std::ptr::null_mut()),
                FlameStatus::InvalidArgument
            );
            assert_eq!(
                flame_retarget_read(
                    r,
                    s,
                    0,
                    0,
                    &cleanup,
                    0,
                    12,
                    rot.as_mut_ptr(),
                    12 * n * 4 - 1,
                    std::ptr::null_mut(),
                    0,
                    std::ptr::null_mut()
                ),
                FlameStatus::BufferTooSmall
            );
            assert_eq!(
                flame_retarget_read(
                    r,
                    s,
                    0,
                    0,
                    &cleanup,
                    0,
                    usize::MAX / 2,
                    rot.as_mut_ptr(),
                    1,
                    std::ptr::null_mut(),
                    0,
                    std::ptr::null_mut()
                ),
                FlameStatus::InvalidArgument
            );
            assert_eq!(
                flame_retarget_pose(
                    r,
                    g.as_ptr(),
                    g.len() - 4,
                    p.as_ptr(),
                    p.len(),
                    std::ptr::null_mut(),
                    0,
                    std::ptr::null_mut(),
                    0
                ),
                FlameStatus::InvalidArgument
            );
            let mut bad = g.clone();
            bad[..4].fill(0.0);
            assert_eq!(
                flame_retarget_pose(
                    r,
                    bad.as_ptr(),
                    bad.len(),
                    p.as_ptr(),
                    p.len(),
                    std::ptr::null_mut(),
                    0,
                    std::ptr::null_mut(),
                    0
                ),
                FlameStatus::InvalidArgument
            );
            let mut params = default_params();
            params.struct_size -= 1;
            let mut r2 = std::ptr::null_mut();
            assert_eq!(
                flame_retarget_new(model, rig, &params, &mut r2),
                FlameStatus::InvalidArgument
            );
            params = default_params();
            params.convention = FlameConvention::Unity as i32;
            assert_eq!(
                flame_retarget_new(model, rig, &params, &mut r2),
                FlameStatus::InvalidArgument
            );
            assert!(r2.is_null());
            // A map of another rig.
            let other = rig_handle();
            let mut m = std::ptr::null_mut();
            assert_eq!(flame_bone_map_auto(other, &mut m), FlameStatus::Ok);
            params = default_params();
            params.map = m;
            assert_eq!(
                flame_retarget_new(model, rig, &params, &mut r2),
                FlameStatus::InvalidArgument
            );
            flame_bone_map_free(m);
            flame_rig_free(other);

            flame_session_free(s);
            flame_retarget_free(r);
            flame_rig_free(rig);
            flame_model_free(model);
        }
    }
}
