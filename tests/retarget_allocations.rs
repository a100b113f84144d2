//! Carrying a frame onto a rig ([`flame::retarget::Target::pose`]) allocates nothing: an engine
//! calls it every tick. Counted with a global allocator wrapper, on a 60-bone rig (SMPL's body,
//! fifteen finger bones per hand, twist bones), with the foot and hand IK on.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

use flame::motion::{Convention, Format, Poses, ReadOptions, Skeleton};
use flame::retarget::{bvh_rig, Options, RigPose, Target};

struct Counting;

static ALLOCATIONS: AtomicUsize = AtomicUsize::new(0);

// SAFETY: forwards to the system allocator; only counts.
unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        System.alloc(layout)
    }
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        System.alloc_zeroed(layout)
    }
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        ALLOCATIONS.fetch_add(1, Ordering::Relaxed);
        System.realloc(ptr, layout, new_size)
    }
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        System.dealloc(ptr, layout)
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// SMPL-24's hierarchy as a BVH in centimetres with five three-bone fingers under each wrist,
/// a twist bone halfway down each upper arm and thigh, and a head end and jaw: 24 + 30 + 4 + 2
/// = 60 bones.
fn sixty_bone_rig() -> String {
    let s = Skeleton::smpl24();
    let names = s.joint_names();
    let mut out = String::from("HIERARCHY\n");
    let mut channels = 0;
    fn open(out: &mut String, kind: &str, name: &str, o: [f64; 3], root: bool, ch: &mut usize) {
        out.push_str(&format!(
            "{kind} {name}\n{{\nOFFSET {} {} {}\n",
            o[0] * 100.0,
            o[1] * 100.0,
            o[2] * 100.0
        ));
        if root {
            out.push_str(
                "CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n",
            );
            *ch += 6;
        } else {
            out.push_str("CHANNELS 3 Zrotation Xrotation Yrotation\n");
            *ch += 3;
        }
    }
    fn leaf(out: &mut String) {
        out.push_str("End Site\n{\nOFFSET 0 1 0\n}\n");
    }
    fn joint(s: &Skeleton, names: &[&str], j: usize, out: &mut String, ch: &mut usize) {
        let o = s.rest_offsets()[j];
        open(
            out,
            if j == 0 { "ROOT" } else { "JOINT" },
            names[j],
            o,
            j == 0,
            ch,
        );
        let kids: Vec<usize> = s.children(j).collect();
        // Twist bones: halfway along the upper arm (shoulder → elbow) and thigh (hip → knee).
        if [1, 2, 16, 17].contains(&j) {
            let child = kids[0];
            let h = s.rest_offsets()[child].map(|v| v / 2.0);
            open(out, "JOINT", &format!("{}_twist", names[j]), h, false, ch);
            leaf(out);
            out.push_str("}\n");
        }
        // Fingers: three bones of 3 cm, 2 cm apart, under each wrist.
        if j == 20 || j == 21 {
            let side = if j == 20 { 1.0 } else { -1.0 };
            for f in 0..5 {
                let spread = (f as f64 - 2.0) * 0.02;
                let mut first = [side * 0.08, 0.0, spread];
                for k in 0..3 {
                    open(
                        out,
                        "JOINT",
                        &format!("{}_finger{f}_{k}", names[j]),
                        first,
                        false,
                        ch,
                    );
                    first = [side * 0.03, 0.0, 0.0];
                }
                leaf(out);
                out.push_str("}\n}\n}\n");
            }
        }
        // The head's end and a jaw, as game rigs have.
        if j == 15 {
            for (name, o) in [("head_top", [0.0, 0.12, 0.0]), ("jaw", [0.0, -0.02, 0.06])] {
                open(out, "JOINT", name, o, false, ch);
                leaf(out);
                out.push_str("}\n");
            }
        }
        if kids.is_empty() && ![15, 20, 21].contains(&j) {
            leaf(out);
        }
        for c in kids {
            joint(s, names, c, out, ch);
        }
        out.push_str("}\n");
    }
    joint(s, names, 0, &mut out, &mut channels);
    out.push_str(&format!(
        "MOTION\nFrames: 1\nFrame Time: 0.05\n{}\n",
        vec!["0"; channels].join(" ")
    ));
    out
}

#[test]
fn a_frame_on_a_sixty_bone_rig_allocates_nothing() {
    let rig = bvh_rig::read(&sixty_bone_rig(), None).unwrap();
    assert_eq!(rig.bone_count(), 60);
    let target = Target::auto(Skeleton::smpl24(), rig).unwrap();
    let frames = 50;
    let dim = Format::Smpl24Rot6d.feature_dim();
    let x: Vec<f32> = (0..frames * dim)
        .map(|i| (0.37 * (i % dim) as f32 + 0.05 * (i / dim) as f32).sin() * 0.8)
        .collect();
    let poses = Poses::decode(Format::Smpl24Rot6d, &x, frames, &ReadOptions::default()).unwrap();
    let world = poses.global_rotations(Convention::Gltf);
    let pos = poses.positions(Convention::Gltf);
    let root = poses.root_translation(Convention::Gltf);
    let mut out = RigPose::new(&target);
    let both = Options {
        feet: true,
        hands: true,
    };
    let before = ALLOCATIONS.load(Ordering::Relaxed);
    let mut moved = 0.0f64;
    for (f, root) in root.iter().enumerate() {
        let span = f * 24..(f + 1) * 24;
        target
            .pose(&world[span.clone()], &pos[span], root, &both, &mut out)
            .unwrap();
        moved += out.positions.iter().map(|p| p[0].abs()).sum::<f64>();
    }
    let after = ALLOCATIONS.load(Ordering::Relaxed);
    assert_eq!(
        after - before,
        0,
        "{} allocations in {frames} frames",
        after - before
    );
    // The frames were really computed (a skipped call would leave the rest pose).
    assert!(moved.is_finite() && moved > 0.0);
}
