//! The two opaque handles behind the C ABI and the per-session state the entry points reach
//! through a lock (which also turns concurrent misuse of one session into an error).

use std::ffi::{c_char, c_void, CString};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Mutex, TryLockError};

use super::errors::Fail;
use super::{FlameModelInfo, FlameProgressCallback, FlamePromptInfo, FlameSampler, FlameWhich};
use crate::error::{invalid_arg, Error};
use crate::models::Model;
use crate::session::{Session, Which};

/// A loaded model: immutable, shareable by any number of sessions and threads.
pub struct FlameModel {
    model: Arc<Model>,
    architecture: CString,
    motion_format: CString,
    text_encoder: CString,
    /// Keeps the strings `joint_name_ptrs` points into alive.
    _joint_names: Vec<CString>,
    joint_name_ptrs: Vec<*const c_char>,
    joint_parents: Vec<i32>,
}

// SAFETY: the raw pointers point into strings this struct owns and never mutates.
unsafe impl Send for FlameModel {}
unsafe impl Sync for FlameModel {}

fn cstring(s: &str) -> CString {
    CString::new(s.replace('\0', " ")).unwrap_or_default()
}

impl FlameModel {
    pub(crate) fn new(model: Arc<Model>) -> FlameModel {
        let cfg = model.config();
        let (names, parents) = super::poses::skeleton(model.motion_format());
        let names: Vec<CString> = names.iter().map(|n| cstring(n)).collect();
        FlameModel {
            architecture: cstring(&cfg.architecture),
            motion_format: cstring(&cfg.motion.format),
            text_encoder: cstring(cfg.text_encoder.kind()),
            joint_name_ptrs: names.iter().map(|n| n.as_ptr()).collect(),
            _joint_names: names,
            joint_parents: parents,
            model,
        }
    }

    pub(crate) fn model(&self) -> &Arc<Model> {
        &self.model
    }

    pub(crate) fn info(&self) -> FlameModelInfo {
        let m = &self.model;
        let c = m.config();
        let sampler = match c.defaults.sampler.as_str() {
            "ddpm" => FlameSampler::Ddpm,
            "ddim" => FlameSampler::Ddim,
            "euler" => FlameSampler::Euler,
            "heun" => FlameSampler::Heun,
            "midpoint" => FlameSampler::Midpoint,
            "lcm" => FlameSampler::Lcm,
            _ => FlameSampler::Default,
        };
        FlameModelInfo {
            struct_size: std::mem::size_of::<FlameModelInfo>() as u32,
            feature_dim: m.motion_dim() as u32,
            joint_count: self.joint_parents.len() as u32,
            max_frames: m.max_frames() as u32,
            default_frames: c.defaults.frames.min(m.max_frames()) as u32,
            default_steps: c.defaults.steps as u32,
            num_timesteps: c.diffusion.num_timesteps as u32,
            default_sampler: sampler as i32,
            fps: c.motion.fps,
            default_guidance: c.defaults.guidance,
            default_eta: c.defaults.eta,
            architecture: self.architecture.as_ptr(),
            motion_format: self.motion_format.as_ptr(),
            text_encoder: self.text_encoder.as_ptr(),
            joint_names: if self.joint_name_ptrs.is_empty() {
                std::ptr::null()
            } else {
                self.joint_name_ptrs.as_ptr()
            },
            joint_parents: if self.joint_parents.is_empty() {
                std::ptr::null()
            } else {
                self.joint_parents.as_ptr()
            },
            latent: m.is_latent() as u32,
            sample_dim: m.sample_dim() as u32,
            control: u32::from(m.denoiser().takes_control()),
        }
    }
}

/// One generation. Used by one thread at a time; only `flame_session_cancel` may run
/// concurrently with another call.
pub struct FlameSession {
    pub(crate) cancel: Arc<AtomicBool>,
    state: Mutex<SessionState>,
}

/// The caller's progress callback and its opaque data.
#[derive(Clone, Copy)]
pub(crate) struct Progress {
    callback: unsafe extern "C" fn(*mut c_void, u32, u32),
    user_data: *mut c_void,
}

/// A session's prompt as encoded, taken out of its lock ([`flame_session_set_prompt_from`]).
///
/// [`flame_session_set_prompt_from`]: crate::ffi::flame_session_set_prompt_from
pub(crate) struct PromptSnapshot {
    model: Arc<crate::models::Model>,
    encoded: Option<(crate::models::Condition, Option<crate::text::PromptInfo>)>,
    dropped: CString,
    prompt: String,
}

pub(crate) struct SessionState {
    pub(crate) session: Session,
    progress: Option<Progress>,
    /// The last prompt's dropped text, which `FlamePromptInfo.dropped` points into.
    dropped: CString,
    /// The last prompt (stages joined by `; `), for the metadata of glTF exports.
    prompt: String,
}

// SAFETY: `user_data` is the caller's and only handed back to the caller's callback, on the
// thread that calls step; the caller promises it may be used from that thread.
unsafe impl Send for SessionState {}

/// A progress callback with the values to report (steps done, total).
pub(crate) type ProgressReport = (Progress, u32, u32);

impl Progress {
    pub(crate) fn report(self, done: u32, total: u32) {
        // SAFETY: the caller registered this callback and its data for this session.
        unsafe { (self.callback)(self.user_data, done, total) }
    }
}

impl FlameSession {
    pub(crate) fn new(session: Session) -> FlameSession {
        FlameSession {
            cancel: session.cancel_flag(),
            state: Mutex::new(SessionState {
                session,
                progress: None,
                dropped: CString::default(),
                prompt: String::new(),
            }),
        }
    }

    /// Runs `f` on the session state; a session busy on another thread is an error, not a wait.
    pub(crate) fn with<R>(
        &self,
        f: impl FnOnce(&mut SessionState) -> Result<R, Fail>,
    ) -> Result<R, Fail> {
        let mut st = match self.state.try_lock() {
            Ok(g) => g,
            Err(TryLockError::WouldBlock) => {
                return Err(
                    Error::WrongState("the session is in use by another thread".into()).into(),
                )
            }
            Err(TryLockError::Poisoned(_)) => {
                return Err(Error::WrongState(
                    "the session is unusable after an internal error; free it".into(),
                )
                .into())
            }
        };
        f(&mut st)
    }
}

pub(crate) unsafe fn model_ref<'a>(model: *const FlameModel) -> Result<&'a FlameModel, Fail> {
    model
        .as_ref()
        .ok_or_else(|| invalid_arg!("`model` is NULL").into())
}

pub(crate) unsafe fn session_ref<'a>(
    session: *const FlameSession,
) -> Result<&'a FlameSession, Fail> {
    session
        .as_ref()
        .ok_or_else(|| invalid_arg!("`session` is NULL").into())
}

impl SessionState {
    pub(crate) fn check_shape(&self, frames: u32, dim: u32) -> Result<(), Fail> {
        let (f, d) = (self.session.frames(), self.session.model().motion_dim());
        if frames as usize != f || dim as usize != d {
            return Err(invalid_arg!(
                "shape {frames} × {dim} does not match the session's {f} frames × {d} features"
            )
            .into());
        }
        Ok(())
    }

    fn mask_or_empty(&self) -> Vec<u8> {
        let n = self.session.frames() * self.session.model().motion_dim();
        self.session
            .mask()
            .map_or(vec![0; n], |m| m.iter().map(|&k| k as u8).collect())
    }

    pub(crate) fn keep_frames(&mut self, start: usize, end: usize) -> Result<(), Fail> {
        let frames = self.session.frames();
        if start >= end || end > frames {
            return Err(
                invalid_arg!("frame range from {start} to {end} (end excluded) is empty or runs past the session's {frames} frames").into(),
            );
        }
        let d = self.session.model().motion_dim();
        let mut mask = self.mask_or_empty();
        mask[start * d..end * d].fill(1);
        Ok(self.session.set_mask(&mask)?)
    }

    pub(crate) fn keep_joints(&mut self, joints: &[i32]) -> Result<(), Fail> {
        let model = Arc::clone(self.session.model());
        let d = model.motion_dim();
        let mut channels = Vec::with_capacity(joints.len());
        for &j in joints {
            channels.extend(super::poses::joint_channels(model.motion_format(), j)?);
        }
        let mut mask = self.mask_or_empty();
        for frame in mask.chunks_exact_mut(d) {
            for &c in &channels {
                frame[c] = 1;
            }
        }
        Ok(self.session.set_mask(&mask)?)
    }

    /// Adds a body part's channels on frames `start..end` to the mask.
    pub(crate) fn keep_part(
        &mut self,
        part: crate::motion::BodyPart,
        start: usize,
        end: usize,
    ) -> Result<(), Fail> {
        let format = self.session.model().motion_format();
        let flags = self.mask_or_empty();
        let mut mask = crate::motion::Mask::from_flags(format, self.session.frames(), &flags)?;
        mask.keep_part(part, start, end)?;
        Ok(self.session.set_mask_from(&mask)?)
    }

    /// Sets the prompt and keeps its dropped text for [`SessionState::prompt_info`].
    pub(crate) fn set_prompt(&mut self, text: &str) -> Result<(), Fail> {
        self.session.set_prompt(text)?;
        let dropped = self.session.prompt_info().map_or("", |p| &p.dropped);
        self.dropped = cstring(dropped);
        self.prompt = text.to_string();
        Ok(())
    }

    /// The prompt as encoded here, with its text and dropped part, for
    /// [`SessionState::take_prompt`] on another session.
    pub(crate) fn prompt_snapshot(&self) -> PromptSnapshot {
        PromptSnapshot {
            model: Arc::clone(self.session.model()),
            encoded: self.session.encoded_prompt(),
            dropped: self.dropped.clone(),
            prompt: self.prompt.clone(),
        }
    }

    /// Sets the prompt of [`SessionState::prompt_snapshot`] ([`Session::set_prompt_from`]).
    pub(crate) fn take_prompt(&mut self, p: PromptSnapshot) -> Result<(), Fail> {
        self.session.take_prompt(&p.model, p.encoded)?;
        self.dropped = p.dropped;
        self.prompt = p.prompt;
        Ok(())
    }

    /// Sets prompts per stage; [`SessionState::prompt_info`] has no fit to report after it.
    pub(crate) fn set_prompt_stages(
        &mut self,
        stages: &[crate::stages::Stage],
    ) -> Result<(), Fail> {
        self.session.set_prompt_stages(stages)?;
        self.dropped = cstring("");
        self.prompt = stages
            .iter()
            .map(|s| s.text.as_str())
            .collect::<Vec<_>>()
            .join("; ");
        Ok(())
    }

    /// The last prompt's fit; `dropped` points into the state, valid until the next prompt.
    pub(crate) fn prompt_info(&self) -> Result<FlamePromptInfo, Fail> {
        let info = self
            .session
            .prompt_info()
            .ok_or_else(|| Error::WrongState("no prompt has been set".into()))?;
        let count = |n: usize| u32::try_from(n).unwrap_or(u32::MAX);
        Ok(FlamePromptInfo {
            struct_size: std::mem::size_of::<FlamePromptInfo>() as u32,
            tokens: count(info.tokens),
            kept: count(info.kept),
            window: count(info.window),
            truncated: info.truncated() as u32,
            unconditional: info.unconditional as u32,
            dropped: self.dropped.as_ptr(),
        })
    }

    pub(crate) fn set_progress(&mut self, callback: FlameProgressCallback, user_data: *mut c_void) {
        self.progress = callback.map(|callback| Progress {
            callback,
            user_data,
        });
    }

    /// Runs one step; returns the steps left and the progress report to deliver once the
    /// session's lock is released (so the callback may call back into the session).
    pub(crate) fn step(&mut self) -> Result<(usize, Option<ProgressReport>), Fail> {
        let left = self.session.step()?;
        let n = self.session.num_steps();
        Ok((
            left,
            self.progress.map(|p| (p, (n - left) as u32, n as u32)),
        ))
    }

    fn which(which: i32) -> Result<Which, Fail> {
        match which {
            w if w == FlameWhich::Sample as i32 => Ok(Which::Sample),
            w if w == FlameWhich::Estimate as i32 => Ok(Which::Estimate),
            w => Err(invalid_arg!("unknown `which` {w} (0 sample, 1 estimate)").into()),
        }
    }

    /// The motion of `which` (decoded for latent models) and its frame count.
    fn motion(&mut self, which: i32) -> Result<(&[f32], usize), Fail> {
        let which = Self::which(which)?;
        self.session.motion(which).map_err(|e| match (e, which) {
            (Error::WrongState(_), Which::Sample) => {
                Error::WrongState("no sample yet: the first step draws x_T".into()).into()
            }
            (Error::WrongState(_), Which::Estimate) => {
                Error::WrongState("no clean-motion estimate yet: run a step first".into()).into()
            }
            (e, _) => e.into(),
        })
    }

    /// Frames a read of `which` returns now (a finished loop's cycle, without the next cycle's
    /// first frame).
    pub(crate) fn read_frames(&mut self, which: i32) -> Result<usize, Fail> {
        let (_, frames) = self.motion(which)?;
        Ok(frames - usize::from(self.wraps(which)))
    }

    /// Whether a read of `which` is a finished loop ([`crate::session::Session::wraps_to_last`]).
    fn wraps(&self, which: i32) -> bool {
        which == FlameWhich::Sample as i32 && self.session.wraps_to_last()
    }

    /// `finish` as a read of `which` applies it: a finished loop always wraps onto its last
    /// frame (the next cycle's first), whatever the caller's `wrap`.
    fn finish_for(&self, which: i32, finish: &crate::motion::Finish) -> crate::motion::Finish {
        let mut f = *finish;
        if self.wraps(which) {
            f.wrap = true;
            f.wrap_to_last = true;
        }
        f
    }

    /// The poses of `which` after `finish` (decoded with read `flags`) and their frame rate:
    /// the finish's, else the model's.
    pub(crate) fn poses(
        &mut self,
        which: i32,
        flags: u32,
        finish: &crate::motion::Finish,
    ) -> Result<(crate::motion::Poses, f64), Fail> {
        let model = Arc::clone(self.session.model());
        let finish = &self.finish_for(which, finish);
        let (features, frames) = self.motion(which)?;
        let poses = super::poses::decode(&model, features, frames, flags, finish)?;
        let fps = finish.fps.unwrap_or(model.config().motion.fps as f64);
        Ok((poses, fps))
    }

    /// The motion of `which` as a glTF file (see `motion::gltf`), with the session's prompt,
    /// the model's architecture and the seed as metadata.
    pub(crate) fn gltf(
        &mut self,
        which: i32,
        container: crate::motion::gltf::Container,
        flags: u32,
        fps: f32,
        name: Option<&str>,
        finish: &crate::motion::Finish,
    ) -> Result<Vec<u8>, Fail> {
        use crate::motion::gltf;
        let model = Arc::clone(self.session.model());
        let seed = self.session.seed();
        let prompt = self.prompt.clone();
        let finish = &self.finish_for(which, finish);
        let (features, frames) = self.motion(which)?;
        let poses = super::poses::decode(&model, features, frames, flags, finish)?;
        let fps = match finish.fps {
            Some(f) => f as f32,
            None if fps == 0.0 => model.config().motion.fps,
            None => fps,
        };
        let opts = gltf::GltfOptions {
            fps,
            prompt: Some(&prompt),
            model: Some(&model.config().architecture),
            seed: Some(seed),
            name,
        };
        Ok(gltf::to_bytes(&poses, &opts, container)?)
    }

    pub(crate) fn read(
        &mut self,
        which: i32,
        layout: i32,
        convention: i32,
        flags: u32,
        finish: &crate::motion::Finish,
    ) -> Result<Vec<f32>, Fail> {
        let model = Arc::clone(self.session.model());
        let finish = &self.finish_for(which, finish);
        let wraps = self.wraps(which);
        let (features, frames) = self.motion(which)?;
        if wraps && layout == super::poses::FlameLayout::Features as i32 {
            // Raw features: the cycle, without the next cycle's first frame.
            let dim = features.len() / frames;
            return Ok(features[..(frames - 1) * dim].to_vec());
        }
        Ok(super::poses::read(
            &model, features, frames, layout, convention, flags, finish,
        )?)
    }
}
