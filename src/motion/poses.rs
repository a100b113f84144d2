//! [`Poses`]: a motion decoded once from its features — root translation, local and global
//! joint rotations, joint positions and foot contacts, kept in `f64` in the format's native frame
//! — and read out in any [`Layout`] and [`Convention`].

use super::contacts;
use super::convention::{Change, Convention};
use super::finish::Finish;
use super::format::{Format, Normalization};
use super::layout::Layout;
use super::postprocess;
use super::rotation::{self, Mat3, Vec3};
use super::{humanml263, smpl24_6d};
use crate::error::{invalid_arg, Result};

/// How features are turned into poses.
#[derive(Clone, Copy, Debug)]
pub struct ReadOptions<'a> {
    /// σ (in frames) of the temporal Gaussian smoothing applied to the (de-normalised) features
    /// before decoding; 0 = none. FLAME's official output uses 1.0 (`t2m_sample.py`;
    /// docs/official/flame.md#temporal-smoothing).
    pub smooth_sigma: f32,
    /// Flip quaternions so that consecutive frames of a joint have a non-negative dot product.
    pub continuous: bool,
    /// The model's mean/std, for normalised formats (humanml263); `None` = features are raw.
    pub normalization: Option<Normalization<'a>>,
    /// The hand-over post-processing (contacts, floor, feet, loop, root motion, frame rate)
    /// [`Poses::decode`] applies after decoding; the default does nothing.
    pub finish: Finish,
    /// The frame rate of the features (the model's `motion.fps`), which contact speeds and
    /// resampling are measured against.
    pub fps: f32,
}

impl Default for ReadOptions<'_> {
    /// No smoothing, continuous quaternions, no de-normalisation.
    fn default() -> Self {
        ReadOptions {
            smooth_sigma: 0.0,
            continuous: true,
            normalization: None,
            finish: Finish::default(),
            fps: 20.0,
        }
    }
}

/// A decoded motion. Frame-major: per-joint arrays are `[frames × joints]`.
#[derive(Clone, Debug)]
pub struct Poses {
    pub(crate) format: Format,
    pub(crate) frames: usize,
    pub(crate) continuous: bool,
    pub(crate) root: Vec<Vec3>,
    pub(crate) local: Vec<Mat3>,
    pub(crate) global: Vec<Mat3>,
    pub(crate) positions: Vec<Vec3>,
    /// `[frames]` foot contacts (left ankle, left foot, right ankle, right foot): the features'
    /// for formats that carry them, the finished ones after [`super::Finish::apply`], empty
    /// otherwise (a read then detects them with the default [`super::ContactParams`]).
    pub(crate) contacts: Vec<[f64; 4]>,
    /// `[frames]` the `root` bone's world position (on the ground under the pelvis) when the
    /// root motion is [`super::RootMotion::Separate`], empty otherwise; exporters write the
    /// bone when it is there.
    pub(crate) root_bone: Vec<Vec3>,
}

impl Poses {
    /// Zeroed storage for the decoders to fill.
    pub(crate) fn empty(format: Format, frames: usize) -> Poses {
        let n = frames * format.skeleton().joint_count();
        Poses {
            format,
            frames,
            continuous: true,
            root: vec![[0.0; 3]; frames],
            local: vec![rotation::IDENTITY; n],
            global: vec![rotation::IDENTITY; n],
            positions: vec![[0.0; 3]; n],
            contacts: Vec::new(),
            root_bone: Vec::new(),
        }
    }

    /// Decodes `frames` rows of `format` features (`features.len() == frames × feature_dim`):
    /// de-normalise, smooth, decode, then apply [`ReadOptions::finish`]. Errors name the
    /// offending argument, frame or channel.
    pub fn decode(
        format: Format,
        features: &[f32],
        frames: usize,
        opts: &ReadOptions,
    ) -> Result<Poses> {
        opts.finish.validate()?;
        let poses = Self::decode_from(
            format,
            features,
            frames,
            opts,
            humanml263::RootStart::ORIGIN,
        )?;
        if opts.finish.is_identity() {
            return Ok(poses);
        }
        opts.finish.apply(&poses, opts.fps as f64)
    }

    /// [`Poses::decode`] with humanml263's root path starting at `start` (ignored by formats
    /// whose root is absolute).
    pub(crate) fn decode_from(
        format: Format,
        features: &[f32],
        frames: usize,
        opts: &ReadOptions,
        start: humanml263::RootStart,
    ) -> Result<Poses> {
        let dim = format.feature_dim();
        let want = frames
            .checked_mul(dim)
            .ok_or_else(|| invalid_arg!("{frames} frames of {format} features overflow"))?;
        if features.len() != want {
            return Err(invalid_arg!(
                "features hold {} values; {frames} frames of {format} need {want} ({frames} x {dim})",
                features.len()
            ));
        }
        if let Some(i) = features.iter().position(|v| !v.is_finite()) {
            return Err(invalid_arg!(
                "features are not finite at frame {}, channel {}",
                i / dim,
                i % dim
            ));
        }
        let sigma = opts.smooth_sigma;
        if !(sigma.is_finite() && sigma >= 0.0) {
            return Err(invalid_arg!(
                "smoothing sigma must be a finite number of frames, 0 or more, got {sigma}"
            ));
        }
        let mut x: Vec<f64> = features.iter().map(|&v| v as f64).collect();
        if let Some(norm) = opts.normalization {
            denormalize(&mut x, dim, norm)?;
        }
        postprocess::gaussian_smooth(&mut x, frames, dim, sigma as f64);
        let mut poses = match format {
            Format::Smpl24Rot6d => smpl24_6d::decode(&x, frames)?,
            Format::HumanMl263 => humanml263::decode(&x, frames, start),
        };
        poses.continuous = opts.continuous;
        Ok(poses)
    }

    /// The feature format the poses were decoded from; it fixes the skeleton.
    pub fn format(&self) -> Format {
        self.format
    }

    /// Number of frames (after any resampling by the finish).
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// Joints per frame: 24 for smpl24_6d, 22 for humanml263 (the format's skeleton).
    pub fn joint_count(&self) -> usize {
        self.format.skeleton().joint_count()
    }

    /// `[frames]` root (pelvis) positions in `convention`.
    pub fn root_translation(&self, convention: Convention) -> Vec<Vec3> {
        let ch = Change::new(self.format, convention);
        self.root.iter().map(|p| ch.position(p)).collect()
    }

    /// `[frames × joints]` world joint positions in `convention`.
    pub fn positions(&self, convention: Convention) -> Vec<Vec3> {
        let ch = Change::new(self.format, convention);
        self.positions.iter().map(|p| ch.position(p)).collect()
    }

    /// `[frames × joints]` parent-relative rotations in `convention` (the root's is its world
    /// rotation).
    pub fn local_rotations(&self, convention: Convention) -> Vec<Mat3> {
        let ch = Change::new(self.format, convention);
        let joints = self.joint_count();
        self.local
            .iter()
            .enumerate()
            .map(|(i, r)| {
                if i % joints == 0 {
                    ch.global(r)
                } else {
                    ch.local(r)
                }
            })
            .collect()
    }

    /// `[frames × joints]` world rotations in `convention`.
    pub fn global_rotations(&self, convention: Convention) -> Vec<Mat3> {
        let ch = Change::new(self.format, convention);
        self.global.iter().map(|r| ch.global(r)).collect()
    }

    /// `[frames]` foot contacts (left ankle, left foot, right ankle, right foot), or `None` when
    /// the format has none.
    pub fn foot_contacts(&self) -> Option<&[[f64; 4]]> {
        (!self.contacts.is_empty()).then_some(&self.contacts[..])
    }

    /// Quaternions (w first) of `[frames × joints]` rotations, continuous if asked at decode.
    pub fn quaternions(&self, rotations: &[Mat3]) -> Vec<[f64; 4]> {
        let mut q: Vec<[f64; 4]> = rotations.iter().map(rotation::to_quat).collect();
        if self.continuous {
            let joints = self.joint_count();
            postprocess::make_continuous(&mut q, rotations.len() / joints.max(1), joints);
        }
        q
    }

    /// Recomputes frame `t`'s world rotations from its local ones and, where positions are the
    /// forward kinematics of the rotations ([`Format::positions_are_kinematic`]), its joint
    /// positions from the root and the rest offsets. humanml263's own positions are left as
    /// they are: a caller that changes rotations moves them itself.
    pub(crate) fn refresh_frame(&mut self, t: usize) {
        let skel = self.format.skeleton();
        let joints = skel.joint_count();
        let span = t * joints..(t + 1) * joints;
        if self.format.positions_are_kinematic() {
            // Cannot fail: every slice has the skeleton's joint count.
            let _ = super::skeleton::forward_kinematics(
                skel.parents(),
                skel.rest_offsets(),
                &self.root[t],
                &self.local[span.clone()],
                &mut self.positions[span.clone()],
                &mut self.global[span],
            );
            return;
        }
        for j in 0..joints {
            let g = match skel.parent(j) {
                Some(p) => rotation::mul(&self.global[t * joints + p], &self.local[t * joints + j]),
                None => self.local[t * joints],
            };
            self.global[t * joints + j] = g;
        }
    }

    /// Frames `start..start + count` (which must exist).
    pub(crate) fn frames_range(&self, start: usize, count: usize) -> Poses {
        let j = self.joint_count();
        let (a, b) = (start * j, (start + count) * j);
        Poses {
            format: self.format,
            frames: count,
            continuous: self.continuous,
            root: self.root[start..start + count].to_vec(),
            local: self.local[a..b].to_vec(),
            global: self.global[a..b].to_vec(),
            positions: self.positions[a..b].to_vec(),
            contacts: if self.contacts.is_empty() {
                Vec::new()
            } else {
                self.contacts[start..start + count].to_vec()
            },
            root_bone: if self.root_bone.is_empty() {
                Vec::new()
            } else {
                self.root_bone[start..start + count].to_vec()
            },
        }
    }

    /// One layout, frame-major `f32` (shape in [`Layout`]'s documentation).
    pub fn layout(&self, layout: Layout, convention: Convention) -> Result<Vec<f32>> {
        layout.frame_shape(self.format)?;
        let out: Vec<f64> = match layout {
            Layout::RootTranslation => self.root_translation(convention).concat(),
            Layout::GlobalPositions => self.positions(convention).concat(),
            Layout::LocalMatrix => self
                .local_rotations(convention)
                .iter()
                .flat_map(|m| m.concat())
                .collect(),
            Layout::Local6d => self
                .local_rotations(convention)
                .iter()
                .flat_map(rotation::to_6d_rows)
                .collect(),
            Layout::LocalQuatXyzw
            | Layout::LocalQuatWxyz
            | Layout::GlobalQuatXyzw
            | Layout::GlobalQuatWxyz => {
                let rotations = match layout {
                    Layout::LocalQuatXyzw | Layout::LocalQuatWxyz => {
                        self.local_rotations(convention)
                    }
                    _ => self.global_rotations(convention),
                };
                let order = layout
                    .quat_order()
                    .unwrap_or(super::layout::QuatOrder::Wxyz);
                self.quaternions(&rotations)
                    .iter()
                    .flat_map(|q| order.arrange(q))
                    .collect()
            }
            Layout::FootContacts if self.contacts.is_empty() => {
                contacts::of(self, self.format.fps() as f64, &Default::default())
                    .iter()
                    .flat_map(|c| c.map(|on| on as u8 as f64))
                    .collect()
            }
            Layout::FootContacts => self.contacts.concat(),
            Layout::RootBone if self.root_bone.is_empty() => {
                return Err(invalid_arg!(
                    "these poses have no root bone (layout root_bone needs root motion `separate`)"
                ))
            }
            Layout::RootBone => {
                let ch = Change::new(self.format, convention);
                self.root_bone.iter().flat_map(|p| ch.position(p)).collect()
            }
        };
        Ok(out.into_iter().map(|v| v as f32).collect())
    }
}

/// `x · std + mean`, channel by channel, after checking the statistics' lengths and values.
fn denormalize(x: &mut [f64], dim: usize, norm: Normalization) -> Result<()> {
    for (name, v) in [("mean", norm.mean), ("std", norm.std)] {
        if v.len() != dim {
            return Err(invalid_arg!(
                "normalisation {name} has {} values, the format has {dim} features",
                v.len()
            ));
        }
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(invalid_arg!(
                "normalisation {name} is not finite at channel {i}"
            ));
        }
    }
    for row in x.chunks_exact_mut(dim) {
        for ((v, &m), &s) in row.iter_mut().zip(norm.mean).zip(norm.std) {
            *v = *v * s as f64 + m as f64;
        }
    }
    Ok(())
}
