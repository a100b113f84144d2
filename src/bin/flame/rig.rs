//! `--rig`: the user's character. The rig file is read and its bone map made before any model
//! is loaded, so a rig libflame cannot drive is refused before minutes of sampling; the poses
//! are carried onto it once they are finished (`flame::retarget`).

use std::path::{Path, PathBuf};

use flame::motion::{Format, Poses};
use flame::retarget::{self, bonemap::BoneMap, bvh_rig, gltf_rig, Rig, RigMotion, Target};

use crate::args::{OutputArgs, RigIk};
use crate::paths;

/// What a rig file holds.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum RigFile {
    /// `.glb` or `.vrm` (binary glTF).
    Glb,
    /// `.gltf` (JSON).
    Gltf,
    Bvh,
}

/// A rig given with `--rig`, read and mapped.
pub struct RigOut {
    pub path: PathBuf,
    pub file: RigFile,
    /// The file's bytes, handed back with the animation added.
    bytes: Vec<u8>,
    rig: Rig,
    map: BoneMap,
    options: retarget::Options,
    pub positions: Option<PathBuf>,
}

impl RigOut {
    /// The rig `o` names, or `None`. Errors name the file and what is wrong with it or its map.
    pub fn new(o: &OutputArgs) -> Result<Option<RigOut>, String> {
        let Some(path) = &o.rig else {
            for (given, flag) in [
                (o.rig_map.is_some(), "--rig-map"),
                (o.rig_skin.is_some(), "--rig-skin"),
                (o.rig_unit.is_some(), "--rig-unit"),
                (o.rig_positions.is_some(), "--rig-positions"),
                (o.rig_ik.is_some(), "--rig-ik"),
            ] {
                if given {
                    return Err(format!("{flag} needs --rig"));
                }
            }
            return Ok(None);
        };
        paths::check_readable(path)?;
        let file = match paths::extension(path).as_deref() {
            Some("glb" | "vrm") => RigFile::Glb,
            Some("gltf") => RigFile::Gltf,
            Some("bvh") => RigFile::Bvh,
            _ => {
                return Err(format!(
                    "cannot read {}: --rig must end in .glb, .gltf, .vrm or .bvh",
                    path.display()
                ))
            }
        };
        let cannot = |e: &dyn std::fmt::Display| format!("cannot read {}: {e}", path.display());
        let bytes = std::fs::read(path).map_err(|e| cannot(&e))?;
        if file != RigFile::Bvh && o.rig_unit.is_some() {
            return Err("--rig-unit is for .bvh rigs (glTF is in metres)".into());
        }
        if file == RigFile::Bvh && o.rig_skin.is_some() {
            return Err("--rig-skin is for glTF rigs (a BVH has one hierarchy)".into());
        }
        let rig = match file {
            RigFile::Bvh => {
                let text = std::str::from_utf8(&bytes)
                    .map_err(|_| cannot(&"a BVH file is text and this is not UTF-8"))?;
                bvh_rig::read(text, o.rig_unit)
            }
            _ => gltf_rig::read(&bytes, o.rig_skin.as_deref()),
        }
        .map_err(|e| cannot(&e))?;
        let auto = BoneMap::auto(&rig);
        let map = match &o.rig_map {
            Some(m) => {
                paths::check_readable(m)?;
                let json = std::fs::read_to_string(m)
                    .map_err(|e| format!("cannot read {}: {e}", m.display()))?;
                // The file's entries over whatever the automatic map found.
                BoneMap::from_json(&rig, &json, auto.ok())
                    .map_err(|e| format!("cannot use {}: {e}", m.display()))?
            }
            None => auto.map_err(|e| {
                format!(
                    "{e}\n(name the bones with --rig-map FILE.json: {{\"hips\": \"...\", ...}}, \
                     VRM humanBone names)"
                )
            })?,
        };
        map.check_required(&rig)
            .map_err(|e| format!("cannot retarget onto {}: {e}", path.display()))?;
        // The skeletons share SMPL's first 22 joints; made here once so that a rig the
        // transfer refuses is refused before sampling.
        Target::new(flame::motion::Skeleton::smpl24(), rig.clone(), map.clone())
            .map_err(|e| format!("cannot retarget onto {}: {e}", path.display()))?;
        let ik = o.rig_ik.unwrap_or(RigIk::Feet);
        let options = retarget::Options {
            feet: matches!(ik, RigIk::Feet | RigIk::Both),
            hands: matches!(ik, RigIk::Hands | RigIk::Both),
        };
        if let Some(p) = &o.rig_positions {
            if paths::extension(p).as_deref() != Some("npy") {
                return Err(format!(
                    "cannot write {}: --rig-positions must end in .npy",
                    p.display()
                ));
            }
        }
        Ok(Some(RigOut {
            path: path.clone(),
            file,
            bytes,
            rig,
            map,
            options,
            positions: o.rig_positions.clone(),
        }))
    }

    /// `poses` (of `format`, finished, at `fps`) on the rig.
    pub fn motion(&self, format: Format, poses: &Poses, fps: f64) -> Result<RigMotion, String> {
        let target = Target::new(format.skeleton(), self.rig.clone(), self.map.clone())
            .map_err(|e| format!("cannot retarget onto {}: {e}", self.path.display()))?;
        target
            .motion(poses, fps, &self.options)
            .map_err(|e| e.to_string())
    }

    /// The rig's file with `motion` added as animation `name`.
    pub fn gltf(&self, motion: &RigMotion, name: &str) -> Result<Vec<u8>, String> {
        retarget::gltf_out::write(&self.bytes, &self.rig, motion, name)
            .map_err(|e| format!("cannot add the animation to {}: {e}", self.path.display()))
    }

    /// `motion` as a BVH on the rig's hierarchy.
    pub fn bvh(&self, motion: &RigMotion) -> Result<String, String> {
        retarget::bvh_out::to_string(&self.rig, motion).map_err(|e| e.to_string())
    }

    /// Writes `--rig-positions`: `[frames, bones, 3]` world positions, the rig's axes and
    /// units.
    pub fn write_positions(&self, motion: &RigMotion) -> Result<(), String> {
        let Some(p) = &self.positions else {
            return Ok(());
        };
        let flat: Vec<f32> = motion
            .positions
            .iter()
            .flat_map(|v| v.map(|x| x as f32))
            .collect();
        flame::npy::write_f32(p, &[motion.frames, motion.bones, 3], &flat)
            .map_err(|e| e.to_string())?;
        println!("{}", p.display());
        Ok(())
    }

    /// Whether `out` (with the extension `ext`) can be the rig's file handed back.
    pub fn check_container(&self, out: &Path, ext: &str) -> Result<(), String> {
        let ok = match self.file {
            RigFile::Glb => matches!(ext, "glb" | "vrm"),
            RigFile::Gltf => ext == "gltf",
            RigFile::Bvh => false,
        };
        if ok {
            return Ok(());
        }
        Err(match self.file {
            RigFile::Bvh => format!(
                "cannot write {}: a .bvh rig is handed back as .bvh (there is no glTF to add \
                 the animation to)",
                out.display()
            ),
            RigFile::Glb => format!(
                "cannot write {}: the rig {} is binary glTF, so the file handed back ends in \
                 .glb or .vrm",
                out.display(),
                self.path.display()
            ),
            RigFile::Gltf => format!(
                "cannot write {}: the rig {} is a .gltf, so the file handed back ends in .gltf",
                out.display(),
                self.path.display()
            ),
        })
    }
}
