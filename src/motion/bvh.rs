//! BVH export: the format's skeleton as the hierarchy, one frame of channels per motion frame.
//!
//! - Hierarchy: joints in depth-first order from the root, children in index order, OFFSETs
//!   = the rest offsets in the chosen convention and unit; the root's OFFSET is zero so that
//!   readers that add it to the root's position channels and readers that do not agree. Each
//!   leaf gets an `End Site` half its own bone long, along that bone (readers such as Blender
//!   need a non-zero tail).
//! - Channels: root `Xposition Yposition Zposition Zrotation Xrotation Yrotation`, every other
//!   joint `Zrotation Xrotation Yrotation`; the rotation is `Rz · Rx · Ry` (degrees), i.e. the
//!   listed order from parent side to child side; the root position is the pelvis's world
//!   position in the convention.
//! - `Frame Time` = 1 / fps.
//!
//! BVH has no handedness field; most readers (Blender among them) take Y up and right-handed,
//! so `gltf` (or `native` for humanml263) is the convention to write for them; Blender's
//! importer then turns Y-up into its Z-up world, which gives exactly libflame's `blender`
//! convention (see tools/blender_bvh_check.py).

use std::fmt::Write;

use super::convention::{Change, Convention};
use super::poses::Poses;
use super::rotation::{self, Vec3};
use super::skeleton::Skeleton;
use crate::error::{invalid_arg, Result};

/// The BVH text of `poses` in `convention`, `fps` frames per second.
pub fn to_string(poses: &Poses, convention: Convention, fps: f32) -> Result<String> {
    if !(fps.is_finite() && fps > 0.0) {
        return Err(invalid_arg!("BVH frame rate must be positive, got {fps}"));
    }
    if poses.frames() == 0 {
        return Err(invalid_arg!("a BVH needs at least one frame"));
    }
    let skel = poses.format().skeleton();
    let ch = Change::new(poses.format(), convention);
    let offsets: Vec<Vec3> = skel.rest_offsets().iter().map(|o| ch.offset(o)).collect();
    let mut order = Vec::with_capacity(skel.joint_count());
    let mut out = String::from("HIERARCHY\n");
    write_joint(&mut out, skel, &offsets, 0, 0, &mut order);

    let joints = skel.joint_count();
    let root = poses.root_translation(convention);
    let local = poses.local_rotations(convention);
    let _ = write!(
        out,
        "MOTION\nFrames: {}\nFrame Time: {:.6}\n",
        poses.frames(),
        1.0 / fps as f64
    );
    for (t, p) in root.iter().enumerate() {
        let _ = write!(out, "{:.6} {:.6} {:.6}", p[0], p[1], p[2]);
        for &j in &order {
            let e = rotation::to_euler_zxy_degrees(&local[t * joints + j]);
            let _ = write!(out, " {:.6} {:.6} {:.6}", e[0], e[1], e[2]);
        }
        out.push('\n');
    }
    Ok(out)
}

/// Writes joint `j` and its subtree, recording the depth-first order of the channels.
fn write_joint(
    out: &mut String,
    skel: &Skeleton,
    offsets: &[Vec3],
    j: usize,
    depth: usize,
    order: &mut Vec<usize>,
) {
    let pad = "\t".repeat(depth);
    let name = skel.joint_names()[j];
    let o = if j == 0 { [0.0; 3] } else { offsets[j] };
    order.push(j);
    if j == 0 {
        let _ = writeln!(out, "ROOT {name}\n{{");
        let _ = writeln!(out, "\tOFFSET {:.6} {:.6} {:.6}", o[0], o[1], o[2]);
        let _ = writeln!(
            out,
            "\tCHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation"
        );
    } else {
        let _ = writeln!(out, "{pad}JOINT {name}\n{pad}{{");
        let _ = writeln!(out, "{pad}\tOFFSET {:.6} {:.6} {:.6}", o[0], o[1], o[2]);
        let _ = writeln!(out, "{pad}\tCHANNELS 3 Zrotation Xrotation Yrotation");
    }
    let mut leaf = true;
    for c in skel.children(j) {
        leaf = false;
        write_joint(out, skel, offsets, c, depth + 1, order);
    }
    if leaf {
        let e = o.map(|x| 0.5 * x);
        let _ = writeln!(
            out,
            "{pad}\tEnd Site\n{pad}\t{{\n{pad}\t\tOFFSET {:.6} {:.6} {:.6}\n{pad}\t}}",
            e[0], e[1], e[2]
        );
    }
    let _ = writeln!(out, "{pad}}}");
}
