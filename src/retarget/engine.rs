//! Rigs an engine holds in memory (Unity's Transforms, Unreal's reference skeleton) in and
//! rig poses out, in the engine's own convention ([`rig_from_bones`], [`Axes`]).
//!
//! **Why convert.** The retarget finds a rig's up, forward and left from its rest pose, and
//! its forward from a cross product (left × up), which assumes right-handed axes. Unity
//! (left-handed, Y up) and Unreal (left-handed, Z up, centimetres) are mirror worlds: a rig
//! taken in their coordinates as they are would have its forward found pointing backwards, and
//! every motion put on it would be mirrored front to back. So an engine's bones are first
//! carried into glTF's right-handed axes in metres as `crate::motion`'s conventions carry
//! poses (its module doc): positions `p' = M p / s`, rotations `R' = M R M⁻¹` (still proper
//! rotations when `M` is a reflection), scales permuted with the axes; with `M` the signed
//! permutation that keeps up, forward and left (`M` from the engine to glTF, `s` the engine's
//! unit in metres⁻¹). The rig is built and retargeted there, and its poses are carried back
//! with the inverse ([`Axes`]), so the engine reads local rotations and translations it can set
//! on its bones as they are.
//!
//! A rig read from a glTF or VRM file is in glTF's axes already (the glTF 2.0 specification,
//! "Coordinate System and Units": right-handed, +Y up, +Z forward, metres); one read from a BVH
//! file is in the file's own axes, which BVH does not state, so its poses can only be given in
//! them.

use super::pose::RigPose;
use super::rig::{BoneSpec, RestTransform, Rig, RigSource};
use super::target::Target;
use crate::error::{invalid_arg, Result};
use crate::motion::rotation::{self, Mat3, Vec3};
use crate::motion::{Convention, Format};

/// One bone as an engine gives it: its transform relative to its parent in the engine's
/// convention (`T · R · S`, Unity's `localPosition`, `localRotation`, `localScale`; Unreal's
/// reference pose `FTransform`s).
#[derive(Clone, Debug, PartialEq)]
pub struct EngineBone {
    /// The bone's name: not empty, unique in the list; the bone map reads it.
    pub name: String,
    /// Index of the parent in the same list (any order), `None` for a root.
    pub parent: Option<usize>,
    /// Position relative to the parent, in the convention's axes and unit (Unity: metres;
    /// Unreal: centimetres).
    pub translation: Vec3,
    /// Quaternion `x, y, z, w` (normalised here; a zero or non-finite one is refused).
    pub rotation: [f64; 4],
    /// Scale along the bone's own axes (`1, 1, 1`: none); no component zero.
    pub scale: Vec3,
}

/// A change of axes and unit from a rig's glTF axes (in the rig's units) to a convention, and
/// back ([`Axes::to`]). `M` is a signed permutation, so rotations and the inverse are exact up
/// to the unit's scaling.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Axes {
    /// glTF axes → the convention's.
    m: Mat3,
    /// Rig units → the convention's units.
    scale: f64,
}

/// Where `convention` puts up, forward and left (columns), and its unit per metre.
fn basis(convention: Convention) -> Result<(Mat3, f64)> {
    if convention == Convention::Native {
        return Err(invalid_arg!(
            "the native convention is a motion format's frame, not a rig's: give the rig's \
             convention (unity, unreal, ros, blender or gltf)"
        ));
    }
    // Every preset's frame is the same whatever the format; only `native` depends on it.
    let f = convention.frame(Format::Smpl24Rot6d);
    let (u, fw, l) = (f.up.vector(), f.forward.vector(), f.left.vector());
    Ok((
        [
            [u[0], fw[0], l[0]],
            [u[1], fw[1], l[1]],
            [u[2], fw[2], l[2]],
        ],
        f.unit.scale(),
    ))
}

impl Axes {
    /// From glTF axes in units of `metres_per_unit` metres to `convention`.
    pub fn to(convention: Convention, metres_per_unit: f64) -> Result<Axes> {
        let (to, unit) = basis(convention)?;
        let (gltf, _) = basis(Convention::Gltf)?;
        Ok(Axes {
            m: rotation::mul(&to, &rotation::transpose(&gltf)),
            scale: metres_per_unit * unit,
        })
    }

    /// Nothing changed: a rig's poses in its own axes and units.
    pub fn identity() -> Axes {
        Axes {
            m: rotation::IDENTITY,
            scale: 1.0,
        }
    }

    /// `M R Mᵀ`: a rotation in the convention.
    pub fn rotation(&self, r: &Mat3) -> Mat3 {
        rotation::mul(&self.m, &rotation::mul(r, &rotation::transpose(&self.m)))
    }

    /// `s M t`: a translation in the convention.
    pub fn translation(&self, t: &Vec3) -> Vec3 {
        rotation::apply(&self.m, t).map(|v| v * self.scale)
    }

    /// `Mᵀ R M`: undoes [`Axes::rotation`].
    pub fn inverse_rotation(&self, r: &Mat3) -> Mat3 {
        rotation::mul(&rotation::transpose(&self.m), &rotation::mul(r, &self.m))
    }

    /// `Mᵀ t / s`: undoes [`Axes::translation`].
    pub fn inverse_translation(&self, t: &Vec3) -> Vec3 {
        rotation::apply(&rotation::transpose(&self.m), t).map(|v| v / self.scale)
    }

    /// A scale's components moved with the axes (`M S Mᵀ` of a diagonal `S` is diagonal).
    fn inverse_scale(&self, s: &Vec3) -> Vec3 {
        let mt = rotation::transpose(&self.m);
        let mut out = [0.0; 3];
        for (i, row) in mt.iter().enumerate() {
            for (j, v) in row.iter().enumerate() {
                if *v != 0.0 {
                    out[i] = s[j];
                }
            }
        }
        out
    }
}

/// A quaternion `x, y, z, w` as a rotation matrix, refused when zero or not finite.
pub fn quat_xyzw_to_matrix(q: &[f64; 4], what: &dyn Fn() -> String) -> Result<Mat3> {
    let n2: f64 = q.iter().map(|v| v * v).sum();
    if !(n2.is_finite() && n2 > 1e-12) {
        return Err(invalid_arg!(
            "{}'s rotation quaternion {q:?} is zero or not finite",
            what()
        ));
    }
    Ok(rotation::quat_to_matrix(&[q[3], q[0], q[1], q[2]]))
}

/// A rotation matrix as a quaternion `x, y, z, w` with `w ≥ 0`.
pub fn matrix_to_quat_xyzw(m: &Mat3) -> [f64; 4] {
    let [w, x, y, z] = rotation::to_quat(m);
    [x, y, z, w]
}

/// The [`Rig`] of an engine's bones given in `convention` (module doc: carried into glTF axes
/// in metres first), and for each given bone its index in the rig ([`Rig::new`] stores bones
/// parents first). Errors name the bone: a zero or non-finite quaternion, and [`Rig::new`]'s.
pub fn rig_from_bones(bones: &[EngineBone], convention: Convention) -> Result<(Rig, Vec<usize>)> {
    let axes = Axes::to(convention, 1.0)?;
    let mut specs = Vec::with_capacity(bones.len().min(super::rig::MAX_BONES + 1));
    for (i, b) in bones.iter().enumerate() {
        let what = || format!("bone {i} (`{}`)", b.name);
        let r = quat_xyzw_to_matrix(&b.rotation, &what)?;
        specs.push(BoneSpec {
            name: b.name.clone(),
            parent: b.parent,
            rest: RestTransform {
                translation: axes.inverse_translation(&b.translation),
                rotation: axes.inverse_rotation(&r),
                scale: axes.inverse_scale(&b.scale),
            },
        });
    }
    let rig = Rig::new(specs, 1.0, RigSource::Code)?;
    let order = bones
        .iter()
        .map(|b| rig.find(&b.name).expect("Rig::new keeps every name"))
        .collect();
    Ok((rig, order))
}

/// Bone `b`'s translation relative to its parent in `pose` (rig units): the rest one, except
/// for the bones the retarget moves (the hips, bones beside the body).
pub fn local_translation(_target: &Target, pose: &RigPose, b: usize) -> Vec3 {
    pose.translation[b]
}

/// Writes `pose` for the bones `order` lists (output bone `i` is rig bone `order[i]`) in
/// `axes`: local rotations as quaternions `x, y, z, w` (`w ≥ 0`) into `rotations`
/// (`4 × order.len()` values) and local translations into `translations` (`3 × order.len()`),
/// either skipped when `None`.
pub fn write_pose(
    target: &Target,
    pose: &RigPose,
    order: &[usize],
    axes: &Axes,
    rotations: Option<&mut [f32]>,
    translations: Option<&mut [f32]>,
) {
    if let Some(out) = rotations {
        for (q, &b) in out.chunks_exact_mut(4).zip(order) {
            let v = matrix_to_quat_xyzw(&axes.rotation(&pose.local[b]));
            for (o, v) in q.iter_mut().zip(v) {
                *o = v as f32;
            }
        }
    }
    if let Some(out) = translations {
        for (t, &b) in out.chunks_exact_mut(3).zip(order) {
            let v = axes.translation(&local_translation(target, pose, b));
            for (o, v) in t.iter_mut().zip(v) {
                *o = v as f32;
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::motion::Skeleton;
    use crate::retarget::pose::Options;
    use crate::retarget::transfer::tests::{source_motion, test_rig};

    /// `rig`'s bones as an engine in `convention` holds them: every rest transform carried out
    /// of glTF axes (metres) by the convention's change, independently of [`rig_from_bones`]'s
    /// inverse (the Unreal and Unity matrices written out from their axes).
    fn engine_bones(rig: &Rig, convention: Convention) -> Vec<EngineBone> {
        // glTF (x left, y up, z forward) → Unreal (X forward, Y right, Z up), centimetres;
        // → Unity (X right, Y up, Z forward), metres.
        let (m, s): (Mat3, f64) = match convention {
            Convention::Unreal => ([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], 100.0),
            Convention::Unity => ([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], 1.0),
            _ => (rotation::IDENTITY, 1.0),
        };
        let mt = rotation::transpose(&m);
        (0..rig.bone_count())
            .map(|b| {
                let r = rig.rest()[b];
                let rot = rotation::mul(&m, &rotation::mul(&r.rotation, &mt));
                EngineBone {
                    name: rig.name(b).to_string(),
                    parent: rig.parent(b),
                    translation: rotation::apply(&m, &r.translation)
                        .map(|v| v * s * rig.metres_per_unit()),
                    rotation: matrix_to_quat_xyzw(&rot),
                    scale: [1.0; 3],
                }
            })
            .collect()
    }

    /// The unlike test rig (Z up, cm) brought into glTF axes in metres: a glTF-convention
    /// engine rig.
    fn gltf_rig() -> Rig {
        let (built, _, _) = test_rig(3);
        let to_y_up = rotation::axis_angle(&[1.0, 0.0, 0.0], -std::f64::consts::FRAC_PI_2);
        let bones: Vec<EngineBone> = (0..built.bone_count())
            .map(|b| {
                let r = built.rest()[b];
                let (t, rot) = if built.parent(b).is_none() {
                    (
                        rotation::apply(&to_y_up, &r.translation),
                        rotation::mul(&to_y_up, &r.rotation),
                    )
                } else {
                    (r.translation, r.rotation)
                };
                EngineBone {
                    name: built.name(b).to_string(),
                    parent: built.parent(b),
                    translation: t.map(|v| v * 0.01),
                    rotation: matrix_to_quat_xyzw(&rot),
                    scale: [1.0; 3],
                }
            })
            .collect();
        rig_from_bones(&bones, Convention::Gltf).unwrap().0
    }

    fn dist(a: &Vec3, b: &Vec3) -> f64 {
        (0..3).map(|i| (a[i] - b[i]).powi(2)).sum::<f64>().sqrt()
    }

    /// World positions of a pose read back in an engine's convention, by forward kinematics
    /// on the engine's own numbers.
    fn engine_fk(parents: &[Option<usize>], rot: &[f32], tr: &[f32]) -> Vec<Vec3> {
        let n = parents.len();
        let (mut world, mut pos) = (vec![rotation::IDENTITY; n], vec![[0.0; 3]; n]);
        for b in 0..n {
            let q: Vec<f64> = rot[4 * b..4 * b + 4].iter().map(|&v| v as f64).collect();
            let r = rotation::quat_to_matrix(&[q[3], q[0], q[1], q[2]]);
            let t = [0, 1, 2].map(|i| tr[3 * b + i] as f64);
            (world[b], pos[b]) = match parents[b] {
                Some(p) => (
                    rotation::mul(&world[p], &r),
                    rotation::add(&pos[p], &rotation::apply(&world[p], &t)),
                ),
                None => (r, t),
            };
        }
        pos
    }

    #[test]
    fn an_unreal_rig_that_mirrors_a_gltf_rig_moves_the_same_way() {
        // The same character held by Unreal (left-handed, Z up, cm) and in glTF (right-handed,
        // Y up, m): driven by the same motion, each read in its own convention and brought
        // back to glTF axes, their joints coincide. Taken as they are, the Unreal numbers
        // would face the rig backwards and mirror the motion front to back.
        let gltf = gltf_rig();
        let unreal_bones = engine_bones(&gltf, Convention::Unreal);
        let (unreal, order) = rig_from_bones(&unreal_bones, Convention::Unreal).unwrap();
        assert_eq!(order, (0..gltf.bone_count()).collect::<Vec<_>>());
        let ta = Target::auto(Skeleton::smpl24(), gltf.clone()).unwrap();
        let tb = Target::auto(Skeleton::smpl24(), unreal).unwrap();
        let (mut pa, mut pb) = (RigPose::new(&ta), RigPose::new(&tb));
        let n = gltf.bone_count();
        let (mut ra, mut ta_, mut rb, mut tb_) = (
            vec![0.0; 4 * n],
            vec![0.0; 3 * n],
            vec![0.0; 4 * n],
            vec![0.0; 3 * n],
        );
        let ax_b = Axes::to(Convention::Unreal, 1.0).unwrap();
        let mut worst = 0.0f64;
        let mut moved = 0.0f64;
        for (g, p, root) in source_motion(20) {
            ta.pose(&g, &p, &root, &Options::default(), &mut pa)
                .unwrap();
            tb.pose(&g, &p, &root, &Options::default(), &mut pb)
                .unwrap();
            write_pose(
                &ta,
                &pa,
                &order,
                &Axes::identity(),
                Some(&mut ra),
                Some(&mut ta_),
            );
            write_pose(&tb, &pb, &order, &ax_b, Some(&mut rb), Some(&mut tb_));
            let a = engine_fk(gltf.parents(), &ra, &ta_);
            let b = engine_fk(gltf.parents(), &rb, &tb_);
            let rest = gltf.rest_world_positions();
            for k in 0..n {
                // Unreal → glTF by hand: x = −Y, y = Z, z = X, centimetres to metres.
                let back = [-b[k][1] / 100.0, b[k][2] / 100.0, b[k][0] / 100.0];
                worst = worst.max(dist(&a[k], &back));
                moved = moved.max(dist(&a[k], &rest[k]));
            }
        }
        assert!(moved > 0.1, "the motion hardly moves the rig ({moved} m)");
        assert!(worst < 1e-5, "the two rigs part by {worst} m");
    }

    #[test]
    fn axes_undo_themselves_and_keep_rotations_proper() {
        let r = rotation::axis_angle(&[0.3, -1.0, 0.5], 1.2);
        let t = [0.25, -1.5, 3.0];
        for c in &Convention::ALL[1..] {
            let a = Axes::to(*c, 1.0).unwrap();
            assert!((rotation::det(&a.rotation(&r)) - 1.0).abs() < 1e-12, "{c}");
            assert_eq!(a.inverse_translation(&a.translation(&t)), t, "{c}");
            let back = a.inverse_rotation(&a.rotation(&r));
            for (x, y) in back.iter().flatten().zip(r.iter().flatten()) {
                assert!((x - y).abs() < 1e-15, "{c}");
            }
        }
        // Unreal: glTF's left (+X) is Unreal's −Y, up (+Y) its +Z, forward (+Z) its +X.
        let u = Axes::to(Convention::Unreal, 1.0).unwrap();
        assert_eq!(u.translation(&[1.0, 2.0, 3.0]), [300.0, -100.0, 200.0]);
        assert!(Axes::to(Convention::Native, 1.0).is_err());
    }

    #[test]
    fn bad_engine_bones_are_refused_by_name() {
        let bone = |name: &str, parent, rotation| EngineBone {
            name: name.into(),
            parent,
            translation: [0.0, 1.0, 0.0],
            rotation,
            scale: [1.0; 3],
        };
        let e = rig_from_bones(
            &[
                bone("a", None, [0.0, 0.0, 0.0, 1.0]),
                bone("b", Some(0), [0.0; 4]),
            ],
            Convention::Unity,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("bone 1 (`b`)"), "{e}");
        let nan = [f64::NAN, 0.0, 0.0, 1.0];
        assert!(rig_from_bones(&[bone("a", None, nan)], Convention::Unity).is_err());
        // A child listed before its parent keeps its place for the caller.
        let (rig, order) = rig_from_bones(
            &[
                bone("b", Some(1), [0.0, 0.0, 0.0, 1.0]),
                bone("a", None, [0.0, 0.0, 0.0, 1.0]),
            ],
            Convention::Unity,
        )
        .unwrap();
        assert_eq!(order, vec![1, 0]);
        assert_eq!(rig.name(0), "a");
    }
}
