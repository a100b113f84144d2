//! A target skeleton read from the user's file ([`Rig`]): bone names, parents, rest transforms
//! (the bind pose) and the rest world frames derived from them. Immutable once made, like a
//! model: one rig serves any number of retargets and threads.
//!
//! A rig is in its file's own axes and units. Rest world rotations are the products of the
//! bones' rest local rotations from the root (scale left out, as three.js's
//! `SkeletonUtils.retarget` and Unreal's retargeter do: a scaled bone still points the same
//! way); rest world positions use the whole transforms, scale included, so they are where the
//! file puts the joints. `metres_per_unit` says how long one unit of the file is (glTF: 1;
//! Mixamo files converted from FBX: 0.01).

use crate::error::{invalid_arg, Result};
use crate::motion::rotation::{self, Mat3, Vec3};

/// At most this many bones: more than any humanoid rig (Unreal's Mannequin has about 90 with
/// fingers and twists; MetaHumans about 1,100 with the face), so a file claiming more is refused
/// before anything is allocated per bone.
pub const MAX_BONES: usize = 4096;

/// A bone's rest transform relative to its parent (glTF's TRS: `T · R · S`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RestTransform {
    /// The origin's offset from the parent's, in the parent's frame (the parent's scale
    /// applies) and the file's units.
    pub translation: Vec3,
    /// The rotation relative to the parent (row-major, acting on column vectors; a proper
    /// rotation: orthonormal, determinant +1).
    pub rotation: Mat3,
    /// Scale along the bone's own axes, applied first; no component zero (a negative one
    /// mirrors).
    pub scale: Vec3,
}

impl RestTransform {
    /// A translation alone (BVH offsets).
    pub fn offset(translation: Vec3) -> RestTransform {
        RestTransform {
            translation,
            rotation: rotation::IDENTITY,
            scale: [1.0; 3],
        }
    }
}

/// One bone of a [`Rig::new`] call.
#[derive(Clone, Debug, PartialEq)]
pub struct BoneSpec {
    /// The bone's name: not empty, unique in the rig; bone maps refer to it.
    pub name: String,
    /// Index of the parent in the same list (any order), `None` for a root.
    pub parent: Option<usize>,
    /// The rest (bind) pose relative to the parent.
    pub rest: RestTransform,
}

/// Where a rig came from, for writers that hand the user's file back.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum RigSource {
    /// A glTF 2.0 / GLB file's skin.
    Gltf {
        /// The skin (index into the file's `skins`) whose joints are the bones.
        skin: usize,
        /// `nodes[i]` is bone `i`'s node index in the file.
        nodes: Vec<usize>,
    },
    /// A VRM file (glTF with the VRMC_vrm 1.0 or VRM 0.x extension).
    Vrm {
        /// VRM 0.x or 1.0: which way the model faces.
        version: VrmVersion,
        /// The skin (index into the file's `skins`) whose joints are the bones; with `None`
        /// the file handed back is not checked against a skin.
        skin: Option<usize>,
        /// `nodes[i]` is bone `i`'s node index in the file.
        nodes: Vec<usize>,
    },
    /// A BVH hierarchy.
    Bvh,
    /// Built in code.
    Code,
}

/// The VRM specification a file follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum VrmVersion {
    /// VRM 0.x (extension `VRM`): the model faces −Z.
    V0,
    /// VRM 1.0 (extension `VRMC_vrm`): the model faces +Z.
    V1,
}

/// A target skeleton (module doc). Bones are stored parents first.
#[derive(Clone, Debug)]
pub struct Rig {
    names: Vec<String>,
    parents: Vec<Option<usize>>,
    rest: Vec<RestTransform>,
    world_rotation: Vec<Mat3>,
    world_position: Vec<Vec3>,
    /// Linear parts (rotation and scale) of the rest world transforms.
    world_linear: Vec<Mat3>,
    metres_per_unit: f64,
    /// Bone map the file declares (VRM humanBones): `(VRM humanBone name, bone)`.
    declared: Vec<(String, usize)>,
    source: RigSource,
}

impl Rig {
    /// A rig from bones in any order (parents need not come first; bones are stored parents
    /// first, otherwise in the given order, so a list that already lists parents first keeps
    /// its indices). Errors name the bone: an
    /// empty list or more than [`MAX_BONES`], an empty or repeated name, a parent out of range
    /// or a cycle, a non-finite value, a zero scale, a rest rotation that is not a rotation.
    /// `source` lists per bone what the file calls it (node indices), in the same order as
    /// `bones`; it is reordered with them.
    pub fn new(bones: Vec<BoneSpec>, metres_per_unit: f64, source: RigSource) -> Result<Rig> {
        let n = bones.len();
        if n == 0 || n > MAX_BONES {
            return Err(invalid_arg!(
                "a rig needs between 1 and {MAX_BONES} bones, got {n}"
            ));
        }
        if !(metres_per_unit.is_finite() && metres_per_unit > 0.0) {
            return Err(invalid_arg!(
                "a rig's unit must be a positive length in metres, got {metres_per_unit}"
            ));
        }
        let mut seen = std::collections::HashMap::with_capacity(n);
        for (i, b) in bones.iter().enumerate() {
            check_bone(b, n)?;
            if let Some(j) = seen.insert(b.name.as_str(), i) {
                return Err(invalid_arg!(
                    "bones {j} and {i} are both named `{}`: a bone map needs unique names",
                    b.name
                ));
            }
        }
        // Parents first, otherwise in the given order (a list already parents-first keeps its
        // indices): Kahn's order, the lowest ready index next. A bone never ready is on a
        // cycle.
        let mut children = vec![Vec::new(); n];
        let mut ready = std::collections::BinaryHeap::new();
        for (i, b) in bones.iter().enumerate() {
            match b.parent {
                Some(p) => children[p].push(i),
                None => ready.push(std::cmp::Reverse(i)),
            }
        }
        let mut order = Vec::with_capacity(n);
        while let Some(std::cmp::Reverse(i)) = ready.pop() {
            order.push(i);
            ready.extend(children[i].iter().map(|&c| std::cmp::Reverse(c)));
        }
        if order.len() != n {
            let mut reached = vec![false; n];
            for &i in &order {
                reached[i] = true;
            }
            let on_cycle = (0..n).find(|&i| !reached[i]).expect("one is missing");
            return Err(invalid_arg!(
                "bone `{}` is its own ancestor (the hierarchy has a cycle)",
                bones[on_cycle].name
            ));
        }
        let mut new_index = vec![0; n];
        for (k, &i) in order.iter().enumerate() {
            new_index[i] = k;
        }
        let source = match source {
            RigSource::Gltf { skin, nodes } => RigSource::Gltf {
                skin,
                nodes: reorder(&nodes, &order, n, "node")?,
            },
            RigSource::Vrm {
                version,
                skin,
                nodes,
            } => RigSource::Vrm {
                version,
                skin,
                nodes: reorder(&nodes, &order, n, "node")?,
            },
            s => s,
        };
        let mut rig = Rig {
            names: Vec::with_capacity(n),
            parents: Vec::with_capacity(n),
            rest: Vec::with_capacity(n),
            world_rotation: Vec::with_capacity(n),
            world_position: Vec::with_capacity(n),
            world_linear: Vec::with_capacity(n),
            metres_per_unit,
            declared: Vec::new(),
            source,
        };
        // World transforms as affine maps (linear part with scale, and translation) for the
        // positions, and scale-free products for the rotations.
        for &i in &order {
            let b = &bones[i];
            let parent = b.parent.map(|p| new_index[p]);
            let scaled = scale_columns(&b.rest.rotation, &b.rest.scale);
            let (rot, lin, pos) = match parent {
                None => (b.rest.rotation, scaled, b.rest.translation),
                Some(p) => (
                    rotation::mul(&rig.world_rotation[p], &b.rest.rotation),
                    rotation::mul(&rig.world_linear[p], &scaled),
                    rotation::add(
                        &rig.world_position[p],
                        &rotation::apply(&rig.world_linear[p], &b.rest.translation),
                    ),
                ),
            };
            if !pos.iter().all(|v| v.is_finite()) || !lin.iter().flatten().all(|v| v.is_finite()) {
                return Err(invalid_arg!(
                    "bone `{}`'s rest position is not finite (scales or offsets too large)",
                    b.name
                ));
            }
            rig.names.push(b.name.clone());
            rig.parents.push(parent);
            rig.rest.push(b.rest);
            rig.world_rotation.push(rot);
            rig.world_position.push(pos);
            rig.world_linear.push(lin);
        }
        Ok(rig)
    }

    /// The same rig with the bone map its file declares (VRM humanBones: `(name, bone)`), each
    /// bone index a stored one (look bones up by name with [`Rig::find`]: [`Rig::new`] may have
    /// reordered them).
    pub fn with_declared(mut self, declared: Vec<(String, usize)>) -> Result<Rig> {
        let n = self.names.len();
        if let Some((name, b)) = declared.iter().find(|(_, b)| *b >= n) {
            return Err(invalid_arg!(
                "the file maps humanoid bone `{name}` to bone {b}, past the rig's {n}"
            ));
        }
        self.declared = declared;
        Ok(self)
    }

    /// Bones, parents first.
    pub fn bone_count(&self) -> usize {
        self.names.len()
    }

    /// Every bone's name, parents first (the index is the bone).
    pub fn names(&self) -> &[String] {
        &self.names
    }

    /// Bone `bone`'s name. Panics when `bone` is not below [`Rig::bone_count`].
    pub fn name(&self, bone: usize) -> &str {
        &self.names[bone]
    }

    /// The bone named `name`, if any.
    pub fn find(&self, name: &str) -> Option<usize> {
        self.names.iter().position(|n| n == name)
    }

    /// Every bone's parent (`None` for roots); a parent always comes before its children.
    pub fn parents(&self) -> &[Option<usize>] {
        &self.parents
    }

    /// Bone `bone`'s parent, `None` for a root. Panics when `bone` is not below
    /// [`Rig::bone_count`].
    pub fn parent(&self, bone: usize) -> Option<usize> {
        self.parents[bone]
    }

    /// The bones whose parent is `bone`.
    pub fn children(&self, bone: usize) -> impl Iterator<Item = usize> + '_ {
        (bone + 1..self.names.len()).filter(move |&c| self.parents[c] == Some(bone))
    }

    /// Rest transforms relative to the parent, in the file's units.
    pub fn rest(&self) -> &[RestTransform] {
        &self.rest
    }

    /// Rest world rotations (scale-free products of the rest local rotations).
    pub fn rest_world_rotations(&self) -> &[Mat3] {
        &self.world_rotation
    }

    /// Rest world positions in the file's units.
    pub fn rest_world_positions(&self) -> &[Vec3] {
        &self.world_position
    }

    /// Linear parts (rotation times scale) of the rest world transforms: a rest world position
    /// is its parent's plus the parent's linear part applied to the rest translation.
    pub fn rest_world_linear(&self) -> &[Mat3] {
        &self.world_linear
    }

    /// Metres per unit of the file.
    pub fn metres_per_unit(&self) -> f64 {
        self.metres_per_unit
    }

    /// The bone map the file declares (VRM humanBones), as `(VRM humanBone name, bone)`;
    /// empty for other files.
    pub fn declared_map(&self) -> &[(String, usize)] {
        &self.declared
    }

    /// Where the rig came from: the glTF/VRM skin and node indices a writer needs to hand
    /// the user's file back with the animation added.
    pub fn source(&self) -> &RigSource {
        &self.source
    }
}

fn check_bone(b: &BoneSpec, n: usize) -> Result<()> {
    if b.name.is_empty() {
        return Err(invalid_arg!("a bone has an empty name"));
    }
    if let Some(p) = b.parent {
        if p >= n {
            return Err(invalid_arg!(
                "bone `{}`'s parent {p} is past the rig's {n} bones",
                b.name
            ));
        }
    }
    let r = &b.rest;
    let values = r
        .translation
        .iter()
        .chain(r.scale.iter())
        .chain(r.rotation.iter().flatten());
    if values.clone().any(|v| !v.is_finite()) {
        return Err(invalid_arg!(
            "bone `{}`'s rest transform has a NaN or infinite value",
            b.name
        ));
    }
    if r.scale.iter().any(|s| s.abs() < 1e-12) {
        return Err(invalid_arg!(
            "bone `{}` has scale {:?}: a zero scale collapses the bone",
            b.name,
            r.scale
        ));
    }
    // A rotation: orthonormal with determinant +1 (a mirror is a negative scale, not this).
    let rt = rotation::mul(&rotation::transpose(&r.rotation), &r.rotation);
    let off = (0..3)
        .flat_map(|i| (0..3).map(move |j| (i, j)))
        .map(|(i, j)| (rt[i][j] - if i == j { 1.0 } else { 0.0 }).abs())
        .fold(0.0, f64::max);
    if off > 1e-4 || (rotation::det(&r.rotation) - 1.0).abs() > 1e-4 {
        return Err(invalid_arg!(
            "bone `{}`'s rest rotation is not a rotation (a quaternion of zero length?)",
            b.name
        ));
    }
    Ok(())
}

/// `values` (one per bone, in the given order) in the stored order.
fn reorder(values: &[usize], order: &[usize], n: usize, what: &str) -> Result<Vec<usize>> {
    if values.len() != n {
        return Err(invalid_arg!(
            "{} {what} indices for {n} bones",
            values.len()
        ));
    }
    Ok(order.iter().map(|&i| values[i]).collect())
}

/// `R · diag(s)`: the linear part of `T · R · S`.
fn scale_columns(r: &Mat3, s: &Vec3) -> Mat3 {
    let mut m = *r;
    for row in &mut m {
        for (v, k) in row.iter_mut().zip(s) {
            *v *= k;
        }
    }
    m
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bone(name: &str, parent: Option<usize>, t: Vec3) -> BoneSpec {
        BoneSpec {
            name: name.into(),
            parent,
            rest: RestTransform::offset(t),
        }
    }

    #[test]
    fn bones_in_any_order_are_stored_parents_first_with_world_frames() {
        // Given child first: hand (2) under arm (0) under root (1).
        let quarter = rotation::axis_angle(&[0.0, 0.0, 1.0], std::f64::consts::FRAC_PI_2);
        let mut arm = bone("arm", Some(1), [0.0, 1.0, 0.0]);
        arm.rest.rotation = quarter;
        arm.rest.scale = [2.0, 2.0, 2.0];
        let bones = vec![
            arm,
            bone("root", None, [0.0, 0.0, 3.0]),
            bone("hand", Some(0), [1.0, 0.0, 0.0]),
        ];
        let rig = Rig::new(
            bones,
            0.01,
            RigSource::Gltf {
                skin: 0,
                nodes: vec![7, 8, 9],
            },
        )
        .unwrap();
        assert_eq!(rig.names(), ["root", "arm", "hand"]);
        assert_eq!(rig.parents(), [None, Some(0), Some(1)]);
        assert_eq!(
            rig.source(),
            &RigSource::Gltf {
                skin: 0,
                nodes: vec![8, 7, 9]
            }
        );
        // hand = root + arm offset + R_arm · S_arm · (1, 0, 0) = (0, 1, 3) + 2 · (0, 1, 0).
        let p = rig.rest_world_positions()[2];
        for (a, b) in p.iter().zip([0.0, 3.0, 3.0]) {
            assert!((a - b).abs() < 1e-12, "{p:?}");
        }
        // Rotations leave the scale out.
        assert_eq!(rig.rest_world_rotations()[2], quarter);
        assert_eq!(rig.children(0).collect::<Vec<_>>(), [1]);
        assert_eq!(rig.find("hand"), Some(2));
    }

    #[test]
    fn broken_hierarchies_and_transforms_are_refused_by_name() {
        let err = |bones: Vec<BoneSpec>| {
            Rig::new(bones, 1.0, RigSource::Code)
                .unwrap_err()
                .to_string()
        };
        assert!(err(vec![]).contains("between 1 and 4096 bones"));
        let e = err(vec![
            bone("a", Some(1), [0.0; 3]),
            bone("b", Some(0), [0.0; 3]),
        ]);
        assert!(e.contains("is its own ancestor"), "{e}");
        let e = err(vec![
            bone("a", None, [0.0; 3]),
            bone("a", Some(0), [0.0; 3]),
        ]);
        assert!(e.contains("both named `a`"), "{e}");
        let e = err(vec![bone("a", Some(5), [0.0; 3])]);
        assert!(e.contains("parent 5 is past"), "{e}");
        let mut zero = bone("z", None, [0.0; 3]);
        zero.rest.scale = [1.0, 0.0, 1.0];
        assert!(err(vec![zero]).contains("zero scale"));
        let mut nan = bone("n", None, [f64::NAN, 0.0, 0.0]);
        assert!(err(vec![nan.clone()]).contains("NaN"));
        nan.rest.translation = [0.0; 3];
        nan.rest.rotation = [[0.0; 3]; 3];
        assert!(err(vec![nan]).contains("not a rotation"));
        let e = Rig::new(vec![bone("a", None, [0.0; 3])], 0.0, RigSource::Code)
            .unwrap_err()
            .to_string();
        assert!(e.contains("positive length"), "{e}");
    }
}
