//! One generation's state: prompt conditioning, sampler, current sample and clean-motion
//! estimate, noise source and thread pool. A session is cheap next to its [`Model`], which it
//! shares; one thread uses a session at a time.
//!
//! [`Model`]: crate::models::Model

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use crate::cycle::Cycle;
use crate::diffusion::flow::{FlowSampler, FlowScratch, OdeMethod};
use crate::diffusion::lcm::LcmSampler;
use crate::diffusion::{self, DiffusionSampler, X0Replacement};
use crate::edit;
pub use crate::edit::{EditMethod, EditParams};
use crate::error::{invalid_arg, Error, Result};
use crate::models::{Cancel, Condition, Guidance, Model, Workspace};
use crate::pool::WorkerPool;
use crate::rng::{GaussianRng, NoiseSource};
use crate::stages::Stage;
use crate::targets::{self, PositionTargets, TargetParams, TargetScratch};
use crate::text::PromptInfo;
use crate::tuning::{self, TuningParams, TuningReport};

/// The largest classifier-free guidance scale a session (and a model file's default) accepts.
/// Guidance runs from 0 (the unconditional model alone) through 1 (the prompt alone, one network
/// row per step) to this; negative scales (steering away from the prompt) are refused.
pub use crate::config::MAX_GUIDANCE;

/// Which reverse process a session runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Sampler {
    /// Ancestral DDPM with the model's variance type.
    Ddpm,
    /// DDIM with the session's `eta`.
    Ddim,
    /// Flow matching: Euler steps (the Motion Flow Matching paper's sampler).
    Euler,
    /// Flow matching: Heun (second order, two evaluations per step).
    Heun,
    /// Flow matching: the midpoint rule (second order, two evaluations per step).
    Midpoint,
    /// Latent consistency models (MotionLCM): a consistency estimate per step, re-noised
    /// between steps ([`crate::diffusion::lcm`]).
    Lcm,
}

impl std::str::FromStr for Sampler {
    type Err = Error;
    fn from_str(s: &str) -> Result<Sampler> {
        match s {
            "ddpm" => Ok(Sampler::Ddpm),
            "ddim" => Ok(Sampler::Ddim),
            "euler" => Ok(Sampler::Euler),
            "heun" => Ok(Sampler::Heun),
            "midpoint" => Ok(Sampler::Midpoint),
            "lcm" => Ok(Sampler::Lcm),
            _ => Err(invalid_arg!(
                "unknown sampler `{s}` (expected ddpm, ddim, euler, heun, midpoint or lcm)"
            )),
        }
    }
}

/// Settings of one generation. `None` means "the model file's default".
#[derive(Clone, Debug, Default)]
pub struct SessionParams {
    /// Frames to generate; `None` = the model's default, capped at its maximum.
    pub frames: Option<usize>,
    /// Sampling steps, respaced from the trained ones; `None` = the model's default.
    pub steps: Option<usize>,
    /// The sampler; `None` = the model's default.
    pub sampler: Option<Sampler>,
    /// A guided-diffusion respacing string (`"ddim50"`, `"10"`, `"15,15,8,6,6"`) choosing
    /// which training steps to sample; it sets the step count (an explicit `steps` must
    /// agree). Only for models with `diffusion.spacing` `respace`.
    pub respacing: Option<String>,
    /// DDIM eta: how much fresh noise each DDIM step adds (0 = deterministic); `None` = the
    /// model's default.
    pub eta: Option<f32>,
    /// Classifier-free guidance scale in [0, [`MAX_GUIDANCE`]]: 0 = unconditional, 1 = the
    /// prompt alone (no unconditional pass), above 1 strengthens the prompt. A latent
    /// consistency model embeds it instead (one pass per step at any scale); unset, it takes
    /// the file's scale for the step count (`defaults.guidance_by_steps`) or its default.
    pub guidance: Option<f32>,
    /// Clamp the x0 estimate to [-1, 1] at every step (the official FLAME sampling does).
    pub clip_denoised: Option<bool>,
    /// Seed of the session's Gaussian noise: the same seed and settings give the same motion.
    pub seed: u64,
    /// Worker threads for this session's kernels: 1..=[`crate::pool::MAX_THREADS`], or 0 = one
    /// per core (capped at the same bound).
    pub threads: usize,
    /// Generate a loop of `frames` frames ([`crate::cycle`]): the session samples twice (a
    /// generation of `frames` + [`Cycle::lead`] frames, then an edit of it whose end runs into
    /// its start), [`Session::num_steps`] counts both passes, and the finished sample reads as
    /// the cycle plus the next cycle's first frame ([`Session::wraps_to_last`]). Not for latent
    /// models or prompts of several stages; the loop's own edit leaves no room for a caller's
    /// reference, mask or position targets.
    pub looped: bool,
}

/// One generation over a shared [`Model`].
pub struct Session {
    model: Arc<Model>,
    frames: usize,
    guidance: f32,
    seed: u64,
    rule: StepRule,
    cond: Option<Condition>,
    /// The unconditional input set by the caller, in place of the model's.
    uncond: Option<Condition>,
    prompt_info: Option<PromptInfo>,
    pool: Arc<WorkerPool>,
    noise: Box<dyn NoiseSource>,
    initial_noise: Option<Vec<f32>>,
    /// x_T (z0 for flow models) of this generation, kept for trajectory rewriting.
    x_start: Vec<f32>,
    /// Steps not yet taken; the next step runs at spaced index `remaining - 1`.
    remaining: usize,
    started: bool,
    stepped: bool,
    /// Rows of the sampled space (the frames, or a latent's rows).
    rows: usize,
    x: Vec<f32>,
    x0: Vec<f32>,
    /// Decoded motion features of a latent model's sample and estimate, made on demand.
    decoded: [Decoded; 2],
    bufs: StepBuffers,
    cancel: Arc<AtomicBool>,
    /// Test hook: the next step finds the cancel flag raised at this check (see [`Cancel`]).
    cancel_at: Option<usize>,
    /// Why a step failed (non-finite values); steps are refused until a reset.
    failed: Option<String>,
    edit: Edit,
    /// Joint positions the sampler is steered toward, and how strongly.
    targets: Option<PositionTargets>,
    target_params: TargetParams,
    /// L at the latest step's clean-motion estimate (before its guidance moved it).
    target_loss: Option<f64>,
    /// The encoded trajectory control ([`Session::set_control`]), which every step's network
    /// pass takes.
    control: Option<Vec<f32>>,
    /// The positions the control was encoded from (what latent tuning's loss reads).
    control_targets: Option<PositionTargets>,
    /// The frames of each stage when the condition has several: the sample is
    /// `[stages, longest stage, dim]` and the motion their concatenation.
    staged: Option<Vec<usize>>,
    /// A loop's plan, and whether the first pass is over (the edit pass runs or ran).
    looping: Option<Looping>,
}

/// [`SessionParams::looped`]: the plan and the pass.
#[derive(Clone, Copy, Debug)]
struct Looping {
    cycle: Cycle,
    edited: bool,
}

/// A latent sample decoded into motion features, and which state of the session it shows.
#[derive(Default)]
struct Decoded {
    /// The step count (`num_steps − remaining`, + 1 once started) the features were made at.
    at: Option<usize>,
    features: Vec<f32>,
    frames: usize,
    ws: Workspace,
}

/// Which of a session's motions to read.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Which {
    /// The current sample (x_T before the first step; the result at the end).
    Sample,
    /// The latest clean-motion estimate x̂0 (after at least one step).
    Estimate,
}

/// How a step moves the sample: a reverse diffusion step, or an ODE step of flow matching.
enum StepRule {
    Diffusion(Box<DiffusionSampler>),
    Flow(FlowSampler),
    Lcm(LcmSampler),
}

impl StepRule {
    fn num_steps(&self) -> usize {
        match self {
            StepRule::Diffusion(d) => d.num_steps(),
            StepRule::Flow(f) => f.num_steps(),
            StepRule::Lcm(l) => l.len(),
        }
    }
}

/// A reference motion, which of its values to keep, and how (see [`crate::edit`]).
#[derive(Default)]
struct Edit {
    /// `[frames, dim]`, zero past `ref_frames` (a reference may be shorter than the session).
    reference: Option<Vec<f32>>,
    ref_frames: usize,
    /// One flag per feature value, `true` = keep the reference.
    keep: Option<Vec<bool>>,
    params: EditParams,
    noised: Vec<f32>,
    noise: Vec<f32>,
    /// The step index `noise` was drawn for: a cancelled step retried reuses it, so the retry
    /// gives the same result as an uninterrupted run.
    noise_step: Option<usize>,
    /// x_t with the kept values imposed; x_t itself changes only when a step completes.
    x_in: Vec<f32>,
}

/// Per-step scratch, sized once per session.
#[derive(Default)]
struct StepBuffers {
    fwd: ForwardBuffers,
    pred: Vec<f32>,
    var: Vec<f32>,
    noise: Vec<f32>,
    x_prev: Vec<f32>,
    /// The step's clean-motion estimate, moved into the session only when the step completes.
    x0_next: Vec<f32>,
    flow: FlowScratch,
    targets: TargetScratch,
}

/// Buffers of one guided network evaluation.
#[derive(Default)]
struct ForwardBuffers {
    batch_x: Vec<f32>,
    out: Vec<f32>,
    pred_uncond: Vec<f32>,
    unused: Vec<f32>,
    ws: Workspace,
    /// A flow step's implied end point, for position targets.
    x1: Vec<f32>,
}

/// What a guided network evaluation needs besides its buffers.
struct Predictor<'a> {
    model: &'a Model,
    /// Rows of the sampled space.
    rows: usize,
    cond: &'a Condition,
    /// The caller's unconditional input, if any (else the model's).
    uncond: Option<&'a Condition>,
    /// The session's guidance scale.
    scale: f32,
    /// The encoded trajectory control, for networks that take one.
    control: Option<&'a [f32]>,
    /// The condition is itself the unconditional input (a blank prompt), so mixing it with
    /// the unconditional pass would change nothing: one conditional pass (an embedded scale
    /// still goes in).
    blank: bool,
}

impl Predictor<'_> {
    /// Runs the network on `x` at time `t` — conditional and unconditional rows as one batch of
    /// two when guided — and writes the guided prediction into `pred` and, for models with
    /// learned variance, the conditional row's variance values into `var`.
    fn predict(
        &self,
        b: &mut ForwardBuffers,
        x: &[f32],
        t: f32,
        pred: &mut Vec<f32>,
        var: &mut Vec<f32>,
        cancel: &Cancel,
    ) -> Result<()> {
        let (d, od) = (self.model.sample_dim(), self.model.output_dim());
        let guidance = match self.model.denoiser().guidance(self.scale, t) {
            Guidance::Mix(_) if self.blank => Guidance::Conditional,
            g => g,
        };
        let (uncond, embedded) = match guidance {
            Guidance::Mix(w) => (
                Some((
                    match self.uncond {
                        Some(u) => u,
                        None => self.model.uncond()?,
                    },
                    w,
                )),
                None,
            ),
            Guidance::Conditional => (None, None),
            Guidance::Embedded(w) => (None, Some(w)),
        };
        let batch = 1 + uncond.is_some() as usize;
        b.batch_x.clear();
        for _ in 0..batch {
            b.batch_x.extend_from_slice(x);
        }
        b.out.resize(batch * self.rows * od, 0.0);
        let both = [self.cond, uncond.map_or(self.cond, |u| u.0)];
        match embedded {
            Some(w) => self.model.forward_embedded(
                &b.batch_x,
                self.rows,
                t,
                w,
                &both[..batch],
                self.control,
                &mut b.out,
                &mut b.ws,
                cancel,
            )?,
            None => self.model.forward_cancellable(
                &b.batch_x,
                self.rows,
                t,
                &both[..batch],
                &mut b.out,
                &mut b.ws,
                cancel,
            )?,
        }
        let n = self.rows * od;
        split_channels(&b.out[..n], d, od, pred, var);
        if let Some((_, w)) = uncond {
            split_channels(&b.out[n..], d, od, &mut b.pred_uncond, &mut b.unused);
            diffusion::guide(pred, &b.pred_uncond, w);
        }
        Ok(())
    }
}

impl Session {
    /// Starts a session; validates the parameters against the model.
    pub fn new(model: Arc<Model>, params: &SessionParams) -> Result<Session> {
        let cfg = model.config();
        let d = &cfg.defaults;
        let mut frames = params.frames.unwrap_or(d.frames.min(model.max_frames()));
        if frames == 0 || frames > model.max_frames() {
            return Err(invalid_arg!(
                "frames must be between 1 and {} for this model, got {frames}",
                model.max_frames()
            ));
        }
        let looping = match params.looped {
            false => None,
            true if model.is_latent() => {
                return Err(invalid_arg!(
                    "a loop is generated by editing the motion, and this {} model samples a \
                     latent: read it with the cleanup's wrap instead",
                    cfg.architecture
                ))
            }
            true => {
                let cycle = Cycle::new(&model, frames)?;
                frames = cycle.frames() + cycle.lead();
                Some(Looping {
                    cycle,
                    edited: false,
                })
            }
        };
        let rule = build_rule(&model, params)?;
        let guidance = params
            .guidance
            .unwrap_or_else(|| d.guidance_for(rule.num_steps()));
        if !crate::config::guidance_in_range(guidance) {
            return Err(invalid_arg!(
                "guidance must be between 0 and {MAX_GUIDANCE}, got {guidance} (0 = unconditional, 1 = the prompt alone, more strengthens the prompt; negative guidance is not supported)"
            ));
        }
        let pool = Arc::new(WorkerPool::new(params.threads)?);
        let n = rule.num_steps();
        let rows = model.sample_rows(frames);
        let len = rows * model.sample_dim();
        let target_params = TargetParams::for_model(&model);
        Ok(Session {
            model,
            frames,
            guidance,
            seed: params.seed,
            rule,
            cond: None,
            uncond: None,
            prompt_info: None,
            pool,
            noise: Box::new(GaussianRng::new(params.seed)),
            initial_noise: None,
            x_start: Vec::new(),
            remaining: n,
            started: false,
            stepped: false,
            rows,
            x: vec![0.0; len],
            x0: vec![0.0; len],
            decoded: Default::default(),
            bufs: StepBuffers::default(),
            cancel: Arc::new(AtomicBool::new(false)),
            cancel_at: None,
            failed: None,
            edit: Edit::default(),
            targets: None,
            target_params,
            target_loss: None,
            control: None,
            control_targets: None,
            staged: None,
            looping,
        })
    }

    /// The model this session samples.
    pub fn model(&self) -> &Arc<Model> {
        &self.model
    }

    /// Frames sampled: for a loop, the cycle's and [`Cycle::lead`] more.
    pub fn frames(&self) -> usize {
        self.frames
    }

    /// The plan of a loop session ([`SessionParams::looped`]).
    pub fn cycle(&self) -> Option<&Cycle> {
        self.looping.as_ref().map(|l| &l.cycle)
    }

    /// Whether [`Session::motion`] of the sample is a finished loop: the cycle's frames and the
    /// next cycle's first frame, which a read targets with [`crate::motion::Finish::wrap`] and
    /// [`crate::motion::Finish::wrap_to_last`] and then drops.
    pub fn wraps_to_last(&self) -> bool {
        self.looping.is_some_and(|l| l.edited) && self.started && self.remaining == 0
    }

    /// The seed of the session's noise generator.
    pub fn seed(&self) -> u64 {
        self.seed
    }

    /// Total sampler steps of this generation (both passes of a loop).
    pub fn num_steps(&self) -> usize {
        self.rule.num_steps() * if self.looping.is_some() { 2 } else { 1 }
    }

    /// Steps left (of both passes of a loop).
    pub fn steps_left(&self) -> usize {
        let second = match self.looping {
            Some(l) if !l.edited => self.rule.num_steps(),
            _ => 0,
        };
        self.remaining + second
    }

    /// Encodes and sets the prompt. Allowed between steps: it takes effect at the next step.
    /// A prompt longer than the text encoder's window is cut ([`Session::prompt_info`] says
    /// what was kept); an empty or blank prompt is unconditional generation: the model's
    /// unconditional input (the empty prompt's encoding, or MDM's zero text vector) with no
    /// guidance pass.
    pub fn set_prompt(&mut self, prompt: &str) -> Result<()> {
        let model = Arc::clone(&self.model);
        let (cond, info) = self.pool.install(|| -> Result<_> {
            let info = model.prompt_info(prompt)?;
            let cond = if info.unconditional {
                model.uncond()?.clone()
            } else {
                model.encode_prompt(prompt)?
            };
            Ok((cond, info))
        })?;
        self.use_condition(cond, Some(info))
    }

    /// Sets prompts per time stage, each with its frame count (adding up to the session's
    /// frames) and optional texts per body part: FineMoGen's temporal composition and its
    /// part texts. Other families take one stage without part texts, as a plain prompt. A
    /// condition of several stages samples `[stages, longest stage, motion_dim]` (the official
    /// batch layout: [`Session::sample_rows`], [`Session::set_initial_noise`]) and
    /// [`Session::motion`] concatenates the stages' frames. Between steps, stages may change
    /// their texts, not their frame counts (that changes the sample's layout: reset first).
    pub fn set_prompt_stages(&mut self, stages: &[Stage]) -> Result<()> {
        crate::stages::check(stages, self.frames)?;
        if let [one] = stages {
            if !one.has_parts() && !self.model.denoiser().takes_stages() {
                // Another family's one stage is its plain prompt, with the prompt's report.
                return self.set_prompt(&one.text);
            }
        }
        if self.looping.is_some() {
            return Err(invalid_arg!(
                "a loop session takes one prompt, not time stages (the loop edits one motion)"
            ));
        }
        let model = Arc::clone(&self.model);
        let cond = self.pool.install(|| model.encode_stages(stages))?;
        self.use_condition(cond, None)
    }

    /// Sample rows a condition lays out: one per frame (or the model's latent rows), or the
    /// longest stage's frames per stage.
    fn rows_for(&self, cond: &Condition) -> usize {
        match cond.stage_frames() {
            Some(f) => f.len() * f.iter().copied().max().unwrap_or(0),
            None => self.model.sample_rows(self.frames),
        }
    }

    /// Makes `cond` the session's condition, resizing the sample to its layout (only before
    /// the first step, and only when no edit is set).
    /// Sets the prompt `other` was given, as encoded there (its condition and prompt report),
    /// without running the text encoder again: a large text encoder (MotionLCM's T5-large:
    /// 75–85 ms) is then paid once per prompt, not once per generation. `other` must run the
    /// same loaded model (the same `Arc`) and have a prompt; its stage frame counts, if any,
    /// must fit this session's frames.
    pub fn set_prompt_from(&mut self, other: &Session) -> Result<()> {
        self.take_prompt(&other.model, other.encoded_prompt())
    }

    /// [`Session::set_prompt_from`] with what [`Session::encoded_prompt`] gave on a session of
    /// `model`.
    pub(crate) fn take_prompt(
        &mut self,
        model: &Arc<Model>,
        encoded: Option<(Condition, Option<PromptInfo>)>,
    ) -> Result<()> {
        if !Arc::ptr_eq(&self.model, model) {
            return Err(invalid_arg!(
                "the other session runs another model: an encoded prompt is the model's own"
            ));
        }
        let (cond, info) = encoded
            .ok_or_else(|| Error::WrongState("the other session has no prompt to take".into()))?;
        self.use_condition(cond, info)
    }

    /// The condition the last prompt was encoded to and its report, for a caller that sets the
    /// same prompt again ([`Session::take_prompt`]).
    pub(crate) fn encoded_prompt(&self) -> Option<(Condition, Option<PromptInfo>)> {
        self.cond
            .as_ref()
            .map(|c| (c.clone(), self.prompt_info.clone()))
    }

    fn use_condition(&mut self, cond: Condition, info: Option<PromptInfo>) -> Result<()> {
        self.model.denoiser().check_frames(&cond, self.frames)?;
        let staged = cond.stage_frames().map(<[usize]>::to_vec);
        if self.started && staged != self.staged {
            return Err(Error::WrongState(
                "the new prompt's stage frame counts differ from the generation's: they can \
                 change only before the first step (reset first)"
                    .into(),
            ));
        }
        let rows = self.rows_for(&cond);
        if rows != self.rows {
            if self.started {
                return Err(Error::WrongState(format!(
                    "the new prompt lays the sample out in {rows} rows, the generation has {}: \
                     stage frame counts can change only before the first step (reset first)",
                    self.rows
                )));
            }
            let len = rows * self.model.sample_dim();
            if self.initial_noise.as_ref().is_some_and(|n| n.len() != len) {
                return Err(invalid_arg!(
                    "the initial noise was set for {} rows; this prompt needs {rows} rows × {}: set the noise after the prompt",
                    self.rows,
                    self.model.sample_dim()
                ));
            }
            self.rows = rows;
            self.x = vec![0.0; len];
            self.x0 = vec![0.0; len];
            self.decoded = Default::default();
        }
        self.staged = staged;
        self.cond = Some(cond);
        self.prompt_info = info;
        Ok(())
    }

    /// How the last prompt fitted the text encoder's window (`None` before a prompt, or after
    /// [`Session::set_condition`]).
    pub fn prompt_info(&self) -> Option<&PromptInfo> {
        self.prompt_info.as_ref()
    }

    /// Sets a precomputed condition (for example a text vector computed elsewhere) instead of
    /// a prompt. It must be made for this model's architecture.
    pub fn set_condition(&mut self, cond: Condition) -> Result<()> {
        self.model.check_condition(&cond)?;
        if let Some(f) = cond.stage_frames() {
            let total: usize = f.iter().sum();
            if total != self.frames {
                return Err(invalid_arg!(
                    "the condition's stages cover {total} frames, the session has {}",
                    self.frames
                ));
            }
        }
        self.use_condition(cond, None)
    }

    /// Sets the unconditional input of guidance (for example the empty prompt's text vector
    /// computed elsewhere) in place of the model's own; `None` goes back to the model's. It
    /// must be made for this model's architecture.
    pub fn set_unconditional(&mut self, cond: Option<Condition>) -> Result<()> {
        if let Some(c) = &cond {
            self.model.check_condition(c)?;
        }
        self.uncond = cond;
        Ok(())
    }

    /// Sets x_T explicitly (`[frames, motion_dim]`); only before the first step.
    pub fn set_initial_noise(&mut self, x_t: &[f32]) -> Result<()> {
        if self.started {
            return Err(Error::WrongState(
                "initial noise can only be set before the first step (reset first)".into(),
            ));
        }
        if x_t.len() != self.x.len() {
            let layout = match &self.staged {
                Some(f) => format!(
                    "{} stages × {} frames (the longest) × {}",
                    f.len(),
                    self.rows / f.len(),
                    self.model.sample_dim()
                ),
                None => format!("{} rows × {}", self.rows, self.model.sample_dim()),
            };
            return Err(invalid_arg!(
                "initial noise has {} values, expected {} ({layout})",
                x_t.len(),
                self.x.len()
            ));
        }
        if x_t.iter().any(|v| !v.is_finite()) {
            return Err(invalid_arg!("initial noise contains NaN or infinity"));
        }
        self.initial_noise = Some(x_t.to_vec());
        self.decoded = Default::default();
        Ok(())
    }

    /// Replaces where per-step (and, unless set explicitly, initial) noise comes from.
    pub fn set_noise_source(&mut self, source: Box<dyn NoiseSource>) {
        self.noise = source;
    }

    /// Back to before the first step: same prompt, same settings, the seeded generator restarted
    /// (a loop back to its first pass).
    pub fn reset(&mut self) {
        if let Some(l) = &mut self.looping {
            if l.edited {
                l.edited = false;
                self.drop_edit();
            }
        }
        self.rewind();
    }

    /// Back to before the first step, edits kept.
    fn rewind(&mut self) {
        self.remaining = self.rule.num_steps();
        self.started = false;
        self.stepped = false;
        self.noise = Box::new(GaussianRng::new(self.seed));
        self.edit.noise_step = None;
        self.decoded = Default::default();
        self.failed = None;
        self.target_loss = None;
        self.cancel.store(false, Ordering::SeqCst);
    }

    /// Steers the following steps toward joint positions ([`crate::targets`]): the targets
    /// cover the first [`PositionTargets::frames`] frames (at most the session's), in the
    /// model's motion format. Replaces earlier targets; a mask and reference still keep their
    /// values (targets steer the rest).
    pub fn set_position_targets(&mut self, targets: PositionTargets) -> Result<()> {
        targets::supported(&self.model)?;
        if self.staged.is_some() {
            return self.check_editable();
        }
        self.check_span(
            &targets,
            "the position targets are",
            "position targets cover",
        )?;
        self.targets = Some(targets);
        Ok(())
    }

    /// [`Session::set_position_targets`] from `[frames × joints × 3]` values in `convention`,
    /// one mask flag per value (nonzero = constrained) or `None` (NaN = free).
    pub fn set_position_target_values(
        &mut self,
        values: &[f32],
        mask: Option<&[u8]>,
        convention: crate::motion::Convention,
    ) -> Result<()> {
        let t = PositionTargets::new(self.model.motion_format(), values, mask, convention)?;
        self.set_position_targets(t)
    }

    /// Joint positions given to steer the session (targets or a control) are for this model's
    /// skeleton and cover at most its frames; `is` and `covers` start the two messages.
    fn check_span(&self, targets: &PositionTargets, is: &str, covers: &str) -> Result<()> {
        let format = self.model.motion_format();
        if targets.format() != format {
            return Err(invalid_arg!(
                "{is} for {} joints; this model's motion is {format}",
                targets.format()
            ));
        }
        if targets.frames() > self.frames {
            return Err(invalid_arg!(
                "{covers} {} frames; the session has {}",
                targets.frames(),
                self.frames
            ));
        }
        Ok(())
    }

    /// Follows joint positions with the model's trajectory ControlNet (MotionLCM's
    /// `--control`): `targets`' positions where their weight is 1, over the first
    /// `targets.frames()` frames (≤ the session's; later frames are free). Encoded once here;
    /// every later step's network pass takes it. Allowed between steps. Models without a
    /// ControlNet refuse (position targets steer those that take gradients).
    pub fn set_control(&mut self, targets: &PositionTargets) -> Result<()> {
        self.check_span(targets, "the control is", "the control covers")?;
        let model = Arc::clone(&self.model);
        let frames = self.frames;
        let encoded = self.pool.install(|| {
            model
                .denoiser()
                .encode_control(frames, targets.positions(), targets.weights())
        })?;
        self.control = Some(encoded);
        self.control_targets = Some(targets.clone());
        Ok(())
    }

    /// [`Session::set_control`] from `[frames × joints × 3]` values in `convention`, one mask
    /// flag per value (nonzero = followed) or `None` (NaN = free), as position targets take
    /// them.
    pub fn set_control_values(
        &mut self,
        values: &[f32],
        mask: Option<&[u8]>,
        convention: crate::motion::Convention,
    ) -> Result<()> {
        let t = PositionTargets::new(self.model.motion_format(), values, mask, convention)?;
        self.set_control(&t)
    }

    /// Removes the trajectory control: the next steps follow the prompt alone.
    pub fn clear_control(&mut self) {
        self.control = None;
        self.control_targets = None;
    }

    /// Consistency latent tuning (MotionLCM v2's `--optimize`, [`crate::tuning`]): before the
    /// first step, moves the initial latent z_T (the seed's draw, or the one set by
    /// [`Session::set_initial_noise`]) so that the motion the 1-step sampler makes from it
    /// follows the control ([`Session::set_control`]) more closely; the tuned latent becomes
    /// the session's initial noise, kept by [`Session::reset`] as a set one is. Needs a prompt,
    /// a control and a 1-step MotionLCM session. Costs `params.iterations` forward and backward
    /// passes of the denoiser, its ControlNet and the VAE decoder. The cancel flag is seen
    /// before every iteration ([`Error::Cancelled`]: the session is left as it was).
    pub fn tune_latent(&mut self, params: &TuningParams) -> Result<TuningReport> {
        if self.started {
            return Err(Error::WrongState(
                "latent tuning sets the initial latent: call it before the first step (reset \
                 first)"
                    .into(),
            ));
        }
        let mut z = match &self.initial_noise {
            Some(x) => x.clone(),
            None => {
                self.check_tuning()?;
                // Drawn as the first step would draw it, and kept as the initial noise at once:
                // a cancelled or failed tuning leaves the session with the latent it would have
                // sampled from anyway.
                let mut z = vec![0.0; self.x.len()];
                self.noise.fill(&mut z);
                self.initial_noise = Some(z.clone());
                z
            }
        };
        let pool = Arc::clone(&self.pool);
        let flag = Arc::clone(&self.cancel);
        let cancel = Cancel::new(&flag, self.cancel_at.take());
        let report = {
            let problem = self.tuning_problem()?;
            pool.install(|| tuning::tune(&problem, &mut z, params, &cancel))?
        };
        self.initial_noise = Some(z);
        self.decoded = Default::default();
        Ok(report)
    }

    /// The loss latent tuning minimises at the latent `z` (`[rows, sample_dim]`) and its
    /// gradient with respect to `z` (before the tuning normalises it): what each iteration of
    /// [`Session::tune_latent`] follows, for callers with an optimiser of their own.
    pub fn tuning_gradient(&self, z: &[f32], params: &TuningParams) -> Result<(f64, Vec<f64>)> {
        if z.len() != self.x.len() || z.iter().any(|v| !v.is_finite()) {
            return Err(invalid_arg!(
                "a latent of this session holds {} finite values, got {}",
                self.x.len(),
                z.len()
            ));
        }
        let problem = self.tuning_problem()?;
        self.pool
            .install(|| tuning::loss_gradient(&problem, z, params))
    }

    /// Refuses what latent tuning cannot run on.
    fn check_tuning(&self) -> Result<()> {
        self.tuning_problem().map(|_| ())
    }

    fn tuning_problem(&self) -> Result<tuning::Problem<'_>> {
        let StepRule::Lcm(sampler) = &self.rule else {
            return Err(invalid_arg!(
                "latent tuning differentiates a latent consistency model's 1-step sampler; this \
                 {} model has none",
                self.model.config().architecture
            ));
        };
        if sampler.len() != 1 {
            return Err(invalid_arg!(
                "latent tuning differentiates the 1-step sampler (the release's setting); this \
                 session runs {} steps",
                sampler.len()
            ));
        }
        let cond = self
            .cond
            .as_ref()
            .ok_or_else(|| Error::WrongState("set a prompt before tuning the latent".into()))?;
        let (Some(control), Some(targets)) = (&self.control, &self.control_targets) else {
            return Err(Error::WrongState(
                "latent tuning follows the control: set one first (set_control, `--control`)"
                    .into(),
            ));
        };
        if self.staged.is_some() {
            return Err(invalid_arg!(
                "latent tuning runs one prompt; this session has stages"
            ));
        }
        let t = sampler.timesteps()[0] as f32;
        let Guidance::Embedded(w) = self.model.denoiser().guidance(self.guidance, t) else {
            return Err(invalid_arg!(
                "latent tuning needs a network that takes the guidance as an input"
            ));
        };
        Ok(tuning::Problem {
            model: &self.model,
            sampler,
            rows: self.rows,
            frames: self.frames,
            w,
            cond,
            control: Some(control),
            targets,
        })
    }

    /// Whether a trajectory control is set.
    pub fn has_control(&self) -> bool {
        self.control.is_some()
    }

    /// Position targets for an editing task from a reference motion (`[frames, feature_dim]`
    /// model-space features, what a session of this model produces; 1 ≤ frames ≤ the
    /// session's): its joint positions where the task keeps them (see
    /// [`PositionTargets::from_task`]; MoLA's MPGD tasks). A model with a trajectory ControlNet
    /// (a MotionLCM control file) takes them as its control hint instead
    /// ([`Session::set_control`]: the official route of MotionLCM's temporal and joint control),
    /// replacing any control set before.
    pub fn set_task_targets(&mut self, features: &[f32], task: crate::motion::Task) -> Result<()> {
        let model = Arc::clone(&self.model);
        let format = model.motion_format();
        let dim = format.feature_dim();
        let frames = features.len() / dim;
        if frames == 0 || !features.len().is_multiple_of(dim) || frames > self.frames {
            return Err(invalid_arg!(
                "the reference holds {} values; expected 1 to {} frames of {dim} features",
                features.len(),
                self.frames
            ));
        }
        let poses =
            crate::motion::Poses::decode(format, features, frames, &model.read_options(0.0, true))?;
        let positions = poses.positions(crate::motion::Convention::Native);
        let t = PositionTargets::from_task(format, &positions, frames, task)?;
        if model.denoiser().takes_control() {
            return self.set_control(&t);
        }
        self.set_position_targets(t)
    }

    /// Removes the position targets: unguided from the next step on.
    pub fn clear_position_targets(&mut self) {
        self.targets = None;
        self.target_loss = None;
    }

    /// The position targets the session steers towards, if any were set.
    pub fn position_targets(&self) -> Option<&PositionTargets> {
        self.targets.as_ref()
    }

    /// How strongly targets steer (scale and schedule).
    pub fn set_target_params(&mut self, params: &TargetParams) -> Result<()> {
        params.validate()?;
        self.target_params = *params;
        Ok(())
    }

    /// How strongly position targets steer (scale and schedule).
    pub fn target_params(&self) -> &TargetParams {
        &self.target_params
    }

    /// The targets' loss `Σ‖(P(x̂) − c)⊙m‖₂` (metres) at the latest step's clean-motion
    /// estimate, before that step's guidance; `None` before a guided step.
    pub fn target_loss(&self) -> Option<f64> {
        self.target_loss
    }

    /// A flag another thread may set to abandon the current or next step.
    pub fn cancel_flag(&self) -> Arc<AtomicBool> {
        Arc::clone(&self.cancel)
    }

    /// Makes `flag` the session's cancel flag (a stream's chunks share the stream's).
    pub(crate) fn share_cancel_flag(&mut self, flag: Arc<AtomicBool>) {
        self.cancel = flag;
    }

    /// The current sample x_t in the sampled space, `[rows, sample_dim]` (the motion's
    /// features, or a latent model's latent; x_T before the first step once started; the
    /// result at the end). [`Session::motion`] gives the motion for every model.
    pub fn sample(&self) -> Option<&[f32]> {
        self.started.then_some(&self.x[..])
    }

    /// The initial noise x_T set by [`Session::set_initial_noise`] or made by
    /// [`Session::tune_latent`] (`None`: the seed's draw at the first step).
    pub fn initial_noise(&self) -> Option<&[f32]> {
        self.initial_noise.as_deref()
    }

    /// The model's latest estimate of the clean sample x0, in the sampled space (after at
    /// least one step).
    pub fn x0_estimate(&self) -> Option<&[f32]> {
        self.stepped.then_some(&self.x0[..])
    }

    /// Rows of the sampled space: the frames, or the latent's rows of a latent model.
    pub fn sample_rows(&self) -> usize {
        self.rows
    }

    /// The motion features of the sample or the estimate, `[frames, motion_dim]` in the
    /// model's (normalised) space, and the frame count. A latent model's sample is decoded
    /// (once per step, on first read) and cut to the valid length the model decides; other
    /// models return their sample as it is. `WrongState` before there is anything to read.
    pub fn motion(&mut self, which: Which) -> Result<(&[f32], usize)> {
        // Between a loop's passes the sample and estimate are still the first pass's.
        let between = self.looping.is_some_and(|l| l.edited);
        let (x, ready, what) = match which {
            Which::Sample => (
                &self.x,
                self.started || between,
                "start generating (step) before reading the sample",
            ),
            Which::Estimate => (
                &self.x0,
                self.stepped || between,
                "step at least once before reading the estimate",
            ),
        };
        if !ready {
            return Err(Error::WrongState(what.into()));
        }
        if which == Which::Sample && self.wraps_to_last() {
            let frames = self.looping.map_or(0, |l| l.cycle.frames()) + 1;
            return Ok((&x[..frames * self.model.motion_dim()], frames));
        }
        if !self.model.is_latent() && self.staged.is_none() {
            return Ok((&x[..], self.frames));
        }
        let at = self.rule.num_steps() - self.remaining + usize::from(self.started);
        let d = &mut self.decoded[which as usize];
        if let (Some(stages), true) = (&self.staged, d.at != Some(at)) {
            // The stages' valid frames, concatenated in order.
            let dim = self.model.sample_dim();
            let t = stages.iter().copied().max().unwrap_or(0);
            d.features.clear();
            for (i, &f) in stages.iter().enumerate() {
                d.features
                    .extend_from_slice(&x[i * t * dim..(i * t + f) * dim]);
            }
            d.frames = self.frames;
            d.at = Some(at);
        }
        if d.at != Some(at) {
            let model = &self.model;
            let frames = self.frames;
            let (features, ws) = (&mut d.features, &mut d.ws);
            let valid = self
                .pool
                .install(|| model.decode(x, frames, features, ws))?;
            d.frames = valid;
            d.at = Some(at);
        }
        Ok((&d.features[..], d.frames))
    }

    /// Refuses mask and reference editing on a latent model (its sample is not the motion).
    fn check_editable(&self) -> Result<()> {
        if self.looping.is_some() {
            return Err(invalid_arg!(
                "a loop session makes its own edit (the end kept to run into the start): \
                 reference motions, masks and position targets do not apply to it"
            ));
        }
        if self.staged.is_some() {
            return Err(invalid_arg!(
                "a prompt of several time stages samples one row per stage, not the motion: \
                 masks, reference motions and position targets apply to single-prompt generations"
            ));
        }
        if self.model.is_latent() {
            return Err(invalid_arg!(
                "this {} model samples a latent, not the motion: masks and reference motions \
                 (replace-x0, noised-reference and trajectory editing) do not apply to it; \
                 generate from a prompt, or set the initial latent",
                self.model.config().architecture
            ));
        }
        Ok(())
    }

    /// Sets the reference motion: model-space features `[ref_frames, motion_dim]` with
    /// 1 ≤ ref_frames ≤ the session's frames. Frames past a shorter reference cannot be kept.
    /// May change between steps: it takes effect at the next step.
    pub fn set_reference(&mut self, features: &[f32]) -> Result<()> {
        self.check_editable()?;
        let dim = self.model.motion_dim();
        if features.is_empty()
            || !features.len().is_multiple_of(dim)
            || features.len() > self.x.len()
        {
            return Err(invalid_arg!(
                "reference has {} values; it must be between 1 and {} whole frames of {dim} values (the session has {} frames)",
                features.len(),
                self.frames,
                self.frames
            ));
        }
        if let Some(i) = features.iter().position(|v| !v.is_finite()) {
            return Err(invalid_arg!(
                "reference value {i} (frame {}, channel {}) is NaN or infinite",
                i / dim,
                i % dim
            ));
        }
        let ref_frames = features.len() / dim;
        if let Some(keep) = &self.edit.keep {
            check_kept_frames(keep, dim, ref_frames)?;
        }
        let mut reference = features.to_vec();
        reference.resize(self.x.len(), 0.0);
        self.edit.reference = Some(reference);
        self.edit.ref_frames = ref_frames;
        Ok(())
    }

    /// [`Session::set_reference`] with features in the motion format's own units (as decoded
    /// poses and BVH files are): normalised first with the model's statistics, if it has any.
    pub fn set_reference_unnormalized(&mut self, features: &[f32]) -> Result<()> {
        let mut x = features.to_vec();
        if let Some(norm) = self.model.read_options(0.0, true).normalization {
            norm.normalize(&mut x)?;
        }
        self.set_reference(&x)
    }

    /// Sets a `smpl24_6d` reference from poses: root (pelvis) positions `[frames, 3]` and local
    /// joint rotations `[frames, 24, …]` in `layout` (local matrices, 6D or quaternions), both
    /// in `convention` (see [`crate::motion::reference::smpl24_features`]).
    pub fn set_reference_poses(
        &mut self,
        root: &[f32],
        rotations: &[f32],
        layout: crate::motion::Layout,
        convention: crate::motion::Convention,
        frames: usize,
    ) -> Result<()> {
        let format = self.model.motion_format();
        if format != crate::motion::Format::Smpl24Rot6d {
            return Err(invalid_arg!(
                "pose references need a smpl24_6d model; this model's format is {format} (give features)"
            ));
        }
        let x =
            crate::motion::reference::smpl24_features(root, rotations, layout, convention, frames)?;
        self.set_reference_unnormalized(&x)
    }

    /// Sets the keep-mask from a [`crate::motion::mask::Mask`] built for this session.
    pub fn set_mask_from(&mut self, mask: &crate::motion::mask::Mask) -> Result<()> {
        if mask.format() != self.model.motion_format() || mask.frames() != self.frames {
            return Err(invalid_arg!(
                "mask is for {} frames of {}, the session has {} frames of {}",
                mask.frames(),
                mask.format(),
                self.frames,
                self.model.motion_format()
            ));
        }
        self.set_keep(mask.flags().to_vec())
    }

    /// Sets the keep-mask, one entry per feature value (`[frames, motion_dim]`, nonzero = keep
    /// the reference). An all-zero mask edits nothing (plain generation); an all-keep mask
    /// reproduces the reference. May change between steps: it takes effect at the next step.
    pub fn set_mask(&mut self, mask: &[u8]) -> Result<()> {
        let keep: Vec<bool> = mask.iter().map(|&m| m != 0).collect();
        self.set_keep(keep)
    }

    /// [`Session::set_mask`] with `bool` flags (for example [`crate::motion::mask::Mask`]'s).
    pub fn set_keep(&mut self, keep: Vec<bool>) -> Result<()> {
        self.check_editable()?;
        if keep.len() != self.x.len() {
            return Err(invalid_arg!(
                "mask has {} values, expected {} (frames {} × {})",
                keep.len(),
                self.x.len(),
                self.frames,
                self.model.motion_dim()
            ));
        }
        if self.edit.reference.is_some() {
            check_kept_frames(&keep, self.model.motion_dim(), self.edit.ref_frames)?;
        }
        self.edit.keep = Some(keep);
        Ok(())
    }

    /// Chooses the editing algorithm and the final paste. Checked against the model: the
    /// diffusion methods need a diffusion model, trajectory rewriting a flow model.
    pub fn set_edit_params(&mut self, params: &EditParams) -> Result<()> {
        params.validate()?;
        self.resolve_method(params.method)?;
        self.edit.params = params.clone();
        Ok(())
    }

    /// The editing settings in force (method, edit-till fraction, paste, seams).
    pub fn edit_params(&self) -> &EditParams {
        &self.edit.params
    }

    /// The algorithm [`EditMethod::Auto`] stands for with this model, or `method` itself if the
    /// model can run it.
    pub fn resolve_method(&self, method: EditMethod) -> Result<EditMethod> {
        let flow = matches!(self.rule, StepRule::Flow(_));
        match (method, flow) {
            (EditMethod::Auto, true) => Ok(EditMethod::RewriteTrajectory),
            (EditMethod::Auto, false) => Ok(self.model.denoiser().default_edit_method()),
            (EditMethod::RewriteTrajectory, true)
            | (EditMethod::NoisedReference | EditMethod::ReplaceX0, false) => Ok(method),
            (m, _) => Err(invalid_arg!(
                "edit method {} does not apply to this {} model",
                m.name(),
                if flow { "flow-matching" } else { "diffusion" }
            )),
        }
    }

    /// Removes the reference and the mask: plain generation from the next step on. A loop
    /// session's own edit stays.
    pub fn clear_edit(&mut self) {
        if self.looping.is_none() {
            self.drop_edit();
        }
    }

    /// No reference and no mask.
    fn drop_edit(&mut self) {
        self.edit.reference = None;
        self.edit.ref_frames = 0;
        self.edit.keep = None;
    }

    /// The current keep-mask, if any.
    pub fn mask(&self) -> Option<&[bool]> {
        self.edit.keep.as_deref()
    }

    /// Whether the mask keeps something (then the reference is set and covers it); an error
    /// when it keeps values no reference provides.
    fn edit_active(&self) -> Result<bool> {
        let Some(keep) = self.edit.keep.as_deref() else {
            return Ok(false);
        };
        if !keep.iter().any(|&k| k) {
            return Ok(false);
        }
        if self.edit.reference.is_none() {
            return Err(Error::WrongState(
                "the mask keeps values but no reference motion is set".into(),
            ));
        }
        check_kept_frames(keep, self.model.motion_dim(), self.edit.ref_frames)?;
        Ok(true)
    }

    /// Writes the step's input into `edit.x_in` when an edit applies before the network runs
    /// (FLAME: the reference diffused to step `t` with fresh noise; flow: the rewritten
    /// trajectory). Returns false, writing nothing, when x_t goes in unchanged.
    fn prepare_input(&mut self, method: EditMethod, t: usize) -> Result<bool> {
        if !self.edit_active()? {
            return Ok(false);
        }
        let Edit {
            reference: Some(reference),
            keep: Some(keep),
            noised,
            noise,
            noise_step,
            x_in,
            params,
            ..
        } = &mut self.edit
        else {
            return Ok(false);
        };
        match (method, &self.rule) {
            (EditMethod::NoisedReference, StepRule::Diffusion(sampler)) => {
                if *noise_step != Some(t) {
                    noise.resize(reference.len(), 0.0);
                    self.noise.fill(noise);
                    *noise_step = Some(t);
                }
                noised.resize(reference.len(), 0.0);
                sampler.try_q_sample(t, reference, noise, noised)?;
                x_in.clear();
                x_in.extend_from_slice(&self.x);
                edit::impose(x_in, noised, keep);
                Ok(true)
            }
            (EditMethod::RewriteTrajectory, StepRule::Flow(sampler)) => {
                let (n, k) = (sampler.num_steps(), sampler.num_steps() - self.remaining);
                if !edit::flow_rewrites(k, n, params.edit_till) {
                    return Ok(false);
                }
                x_in.clear();
                x_in.extend_from_slice(&self.x);
                edit::impose_flow_path(x_in, &self.x_start, reference, keep, k, n);
                Ok(true)
            }
            _ => Ok(false),
        }
    }

    /// Advances one sampler step; returns the number of steps left.
    ///
    /// A raised [`Session::cancel_flag`] is seen before every transformer layer: the step
    /// returns [`Error::Cancelled`] and leaves no trace (sample, estimate, noise stream), so a
    /// retry gives the bits of a run never cancelled. A step whose sample or estimate is not
    /// finite returns [`Error::NotFinite`] naming the step; the sample and estimate keep the
    /// previous step's values and further steps return [`Error::WrongState`] until
    /// [`Session::reset`].
    pub fn step(&mut self) -> Result<usize> {
        if let Some(why) = &self.failed {
            return Err(Error::WrongState(format!(
                "{why}; reset the session to start over"
            )));
        }
        if self.cond.is_none() {
            return Err(Error::WrongState("set a prompt before stepping".into()));
        }
        if self.remaining == 0 {
            return Err(Error::WrongState(
                "the generation is finished; reset to start again".into(),
            ));
        }
        let pool = Arc::clone(&self.pool);
        let flag = Arc::clone(&self.cancel);
        let cancel = Cancel::new(&flag, self.cancel_at.take());
        let left = pool.install(|| self.step_inner(&cancel))?;
        if left == 0 {
            if let Some(l) = self.looping.filter(|l| !l.edited) {
                self.start_loop_edit(l.cycle)?;
            }
        }
        Ok(self.steps_left())
    }

    /// A loop's first pass is over: the same session, rewound (same seed, same noise), edits
    /// the first pass's motion into the loop ([`Cycle::edit`], as `flame generate --loop` did
    /// with a second session).
    fn start_loop_edit(&mut self, cycle: Cycle) -> Result<()> {
        let first = self.x.clone();
        self.rewind();
        // The loop's own edit goes through the checks a caller's would; `check_editable`
        // refuses callers' edits while `looping` is set.
        self.looping = None;
        let edit = cycle.edit(self, &first);
        self.looping = Some(Looping {
            cycle,
            edited: edit.is_ok(),
        });
        edit
    }

    /// Test hook: the next step sees the cancel flag raised at its `check`-th cancellation
    /// check (0 = before anything runs; then one before every layer of every network
    /// evaluation; the last after the network, before the step's result is kept).
    #[cfg(test)]
    pub(crate) fn cancel_at_check(&mut self, check: usize) {
        self.cancel_at = Some(check);
    }

    /// Runs every remaining step and returns the final sample.
    pub fn run(&mut self) -> Result<&[f32]> {
        while self.steps_left() > 0 {
            self.step()?;
        }
        Ok(&self.x)
    }

    fn step_inner(&mut self, cancel: &Cancel) -> Result<usize> {
        cancel.check()?;
        let model = Arc::clone(&self.model);
        let len = self.x.len();
        // Resolved before anything is drawn, so a bad combination leaves the session as it was.
        let method = self.resolve_method(self.edit.params.method)?;
        let active = self.edit_active()?;
        if self.staged.is_some() && (active || self.targets.is_some()) {
            self.check_editable()?;
        }
        if !self.started {
            match &self.initial_noise {
                Some(x) => self.x.copy_from_slice(x),
                None => self.noise.fill(&mut self.x),
            }
            self.x_start.clone_from(&self.x);
            self.started = true;
        }
        let t = self.remaining - 1;
        let edited = self.prepare_input(method, t)?;
        let x_t: &[f32] = if edited { &self.edit.x_in } else { &self.x };
        let replace = match (method, &self.edit.reference, &self.edit.keep) {
            (EditMethod::ReplaceX0, Some(reference), Some(keep)) if active => {
                Some(X0Replacement { reference, keep })
            }
            _ => None,
        };
        // A blank prompt's condition is the unconditional input: guiding it changes nothing.
        let unconditional = self.prompt_info.as_ref().is_some_and(|p| p.unconditional);
        let p = Predictor {
            model: &model,
            rows: self.rows,
            cond: self.cond.as_ref().expect("checked in step"),
            uncond: self.uncond.as_ref(),
            scale: self.guidance,
            control: self.control.as_deref(),
            blank: unconditional,
        };
        let StepBuffers {
            fwd,
            pred,
            var,
            noise,
            x_prev,
            x0_next,
            flow,
            targets: target_scratch,
        } = &mut self.bufs;
        let mut loss = None;
        let targets = self
            .targets
            .as_ref()
            .filter(|_| self.target_params.scale > 0.0);
        let params = self.target_params;
        let rows = self.rows;
        // What an active edit keeps does not move under the targets' pull.
        let kept = match (&self.edit.keep, active) {
            (Some(k), true) => Some(&k[..]),
            _ => None,
        };
        // The targets' pull at noise level `tau` on an estimate x̂ (or, for a flow step, on
        // the velocity that implies it; see `targets::pull`).
        let mut pull = |x_hat: &mut [f32], tau: f64, velocity: Option<(&mut [f32], f32)>| {
            let Some(targets) = targets else {
                return Ok(());
            };
            cancel.check()?;
            let rho = params.rho(tau);
            let l = targets::pull(
                &model,
                targets,
                x_hat,
                rows,
                rho,
                velocity,
                kept,
                target_scratch,
            )?;
            loss = Some(l);
            Ok::<(), Error>(())
        };
        x_prev.resize(len, 0.0);
        x0_next.resize(len, 0.0);
        let n = self.rule.num_steps();
        let step = n - self.remaining + 1;
        match &self.rule {
            StepRule::Diffusion(sampler) => {
                p.predict(fwd, x_t, sampler.model_timestep(t), pred, var, cancel)?;
                // Last chance before the step draws noise: after this it completes.
                cancel.check()?;
                let z = if sampler.needs_noise(t) {
                    noise.resize(len, 0.0);
                    self.noise.fill(noise);
                    Some(&noise[..])
                } else {
                    None
                };
                let v = (model.output_dim() > model.motion_dim()).then_some(&var[..]);
                let tau = sampler.model_timestep(t) as f64
                    / model.config().diffusion.num_timesteps as f64;
                let mut guide = |x0: &mut [f32]| pull(x0, tau, None);
                let guide: Option<&mut diffusion::X0Guide> =
                    targets.is_some().then_some(&mut guide);
                sampler.step_guided(t, x_t, pred, v, z, replace, guide, x_prev, x0_next)?;
            }
            StepRule::Flow(sampler) => {
                // Flow time runs forwards: the first step is k = 0 at t = 0 (noise).
                let k = sampler.num_steps() - self.remaining;
                // The second evaluation of Heun and midpoint checks before its first layer too.
                let mut velocity = |tk: f32, x: &[f32], v: &mut [f32]| {
                    p.predict(fwd, x, tk, pred, var, cancel)?;
                    v.copy_from_slice(pred);
                    if targets.is_some() && tk < 1.0 {
                        // The velocity's implied end point x̂1 = x + (1 − t)·v.
                        let left = 1.0 - tk;
                        let mut x1 = std::mem::take(&mut fwd.x1);
                        x1.clear();
                        x1.extend(x.iter().zip(v.iter()).map(|(&a, &b)| a + left * b));
                        let pulled = pull(&mut x1, left as f64, Some((v, left)));
                        fwd.x1 = x1;
                        pulled?;
                    }
                    Ok(())
                };
                sampler.step(k, x_t, &mut velocity, flow, x_prev, x0_next)?;
                cancel.check()?;
            }
            StepRule::Lcm(sampler) => {
                // Timesteps run in the listed order; step k's consistency estimate is the
                // clean-motion estimate, re-noised to the next listed timestep unless last.
                let k = sampler.len() - self.remaining;
                let tk = sampler.timesteps()[k];
                p.predict(fwd, x_t, tk as f32, pred, var, cancel)?;
                cancel.check()?;
                sampler.denoise(k, pred, x_t, x0_next);
                if k + 1 < sampler.len() {
                    noise.resize(len, 0.0);
                    self.noise.fill(noise);
                    sampler.renoise(k, x0_next, noise, x_prev);
                } else {
                    x_prev.copy_from_slice(x0_next);
                }
            }
        }
        if let Some(why) = non_finite(x_prev, x0_next, model.sample_dim()) {
            let msg = format!(
                "step {step} of {n} produced a non-finite value ({why}): the guidance scale ({}) or the input (reference, noise) is too large or not finite",
                self.guidance
            );
            self.failed = Some(msg.clone());
            return Err(Error::NotFinite(format!(
                "{msg}; reset the session to start over"
            )));
        }
        std::mem::swap(&mut self.x, x_prev);
        std::mem::swap(&mut self.x0, x0_next);
        if loss.is_some() {
            self.target_loss = loss;
        }
        self.remaining -= 1;
        self.stepped = true;
        if self.remaining == 0 && self.edit.params.paste {
            if let (true, Some(reference), Some(keep)) =
                (active, &self.edit.reference, &self.edit.keep)
            {
                let dim = model.motion_dim();
                let seam = self.edit.params.seam_frames;
                edit::paste_with_seams(&mut self.x, reference, keep, self.frames, dim, seam);
            }
        }
        Ok(self.remaining)
    }
}

/// Builds the step rule the parameters ask for ([`diffusion::build_sampler`]).
fn build_rule(model: &Model, params: &SessionParams) -> Result<StepRule> {
    let cfg = model.config();
    let sampler = params
        .sampler
        .map_or_else(|| cfg.defaults.sampler.parse(), Ok)?;
    let method = match sampler {
        Sampler::Ddpm => diffusion::Method::Ddpm,
        Sampler::Ddim => diffusion::Method::Ddim,
        Sampler::Euler => diffusion::Method::Ode(OdeMethod::Euler),
        Sampler::Heun => diffusion::Method::Ode(OdeMethod::Heun),
        Sampler::Midpoint => diffusion::Method::Ode(OdeMethod::Midpoint),
        Sampler::Lcm => diffusion::Method::Lcm,
    };
    let choice = diffusion::SamplerChoice {
        method,
        steps: params.steps,
        respacing: params.respacing.as_deref(),
        eta: params.eta,
        clip_denoised: params.clip_denoised,
    };
    Ok(
        match diffusion::build_sampler(&cfg.diffusion, &cfg.defaults, &choice)? {
            diffusion::BuiltSampler::Diffusion(d) => StepRule::Diffusion(d),
            diffusion::BuiltSampler::Flow(f) => StepRule::Flow(f),
            diffusion::BuiltSampler::Lcm(l) => StepRule::Lcm(l),
        },
    )
}

/// Splits rows of `od` channels into the first `d` (prediction) and the rest (variance value).
fn split_channels(out: &[f32], d: usize, od: usize, pred: &mut Vec<f32>, var: &mut Vec<f32>) {
    pred.clear();
    var.clear();
    for row in out.chunks_exact(od) {
        pred.extend_from_slice(&row[..d]);
        var.extend_from_slice(&row[d..]);
    }
}

/// Where the first NaN or infinity of a step's new sample (or else its clean-motion estimate)
/// is, as "frame F, channel C of the sample"; `None` when both are finite.
fn non_finite(x: &[f32], x0: &[f32], dim: usize) -> Option<String> {
    [(x, "sample"), (x0, "clean-motion estimate")]
        .iter()
        .find_map(|(v, what)| {
            let i = v.iter().position(|v| !v.is_finite())?;
            Some(format!(
                "frame {}, channel {} of the {what}",
                i / dim,
                i % dim
            ))
        })
}

/// Errors when `keep` keeps a value in a frame at or past `ref_frames`.
fn check_kept_frames(keep: &[bool], dim: usize, ref_frames: usize) -> Result<()> {
    match keep[ref_frames * dim..].iter().position(|&k| k) {
        Some(i) => Err(invalid_arg!(
            "the mask keeps frame {} but the reference has only {ref_frames} frames",
            ref_frames + i / dim
        )),
        None => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn model(file: &str) -> Arc<Model> {
        let path = format!("{}/tests/fixtures/{file}", env!("CARGO_MANIFEST_DIR"));
        Arc::new(Model::load(path).unwrap())
    }

    /// A 16-frame, 4-step session; FLAME DDPM sessions edit (noised reference), so each step
    /// draws both the edit's noise and the sampler's.
    fn session(model: &Arc<Model>, sampler: Sampler, guidance: f32) -> Session {
        let params = SessionParams {
            frames: Some(16),
            steps: Some(4),
            sampler: Some(sampler),
            guidance: Some(guidance),
            seed: 11,
            threads: 1,
            ..Default::default()
        };
        let mut s = Session::new(Arc::clone(model), &params).unwrap();
        s.set_prompt("a person walks forward").unwrap();
        if sampler == Sampler::Ddpm {
            let dim = model.motion_dim();
            let r: Vec<f32> = (0..16 * dim).map(|i| (i as f32 * 0.01).sin()).collect();
            s.set_reference(&r).unwrap();
            s.set_keep((0..16 * dim).map(|i| i < 4 * dim).collect())
                .unwrap();
        }
        s
    }

    fn bits(v: &[f32]) -> Vec<u32> {
        v.iter().map(|x| x.to_bits()).collect()
    }

    /// Sample and estimate after every step of an uncancelled run.
    fn trajectory(mut s: Session) -> Vec<(Vec<u32>, Vec<u32>)> {
        let mut out = Vec::new();
        while s.steps_left() > 0 {
            s.step().unwrap();
            out.push((bits(s.sample().unwrap()), bits(s.x0_estimate().unwrap())));
        }
        out
    }

    /// A step can be cancelled at each of its checks: at the start, before every layer of
    /// every network evaluation (two for Heun and midpoint) and after the network. Wherever it
    /// is cancelled, it returns `Cancelled`, leaves sample, estimate and step count as they were,
    /// and the retried generation has the bits of one never cancelled. One check past the last
    /// the step completes, so the count of checks is exact.
    #[test]
    fn a_step_cancelled_at_any_layer_leaves_no_trace() {
        let flame = model("flame_tiny.safetensors");
        let mdm = model("mdm_tiny.safetensors");
        let motionfm = model("motionfm_tiny.safetensors");
        let cases = [
            (&flame, Sampler::Ddpm, 2.5, 2, 1),
            (&flame, Sampler::Ddim, 1.0, 2, 1),
            (&mdm, Sampler::Ddim, 2.5, 0, 1),
            (&motionfm, Sampler::Heun, 2.5, 0, 2),
            (&motionfm, Sampler::Midpoint, 1.0, 0, 2),
        ];
        for (m, sampler, guidance, cancelled_step, evals) in cases {
            let any = m.config().denoiser.as_any();
            let layers = match any.downcast_ref::<crate::models::FlameConfig>() {
                Some(c) => c.num_layers,
                None => {
                    any.downcast_ref::<crate::models::MdmConfig>()
                        .unwrap()
                        .layers
                }
            };
            let checks = 2 + evals * layers;
            let want = trajectory(session(m, sampler, guidance));
            for check in 0..=checks {
                let what = format!("{sampler:?}, guidance {guidance}, check {check}");
                let mut s = session(m, sampler, guidance);
                for _ in 0..cancelled_step {
                    s.step().unwrap();
                }
                let before = (s.sample().map(bits), s.x0_estimate().map(bits));
                s.cancel_at_check(check);
                let r = s.step();
                if check == checks {
                    assert_eq!(r.unwrap(), 3 - cancelled_step, "{what}: no check left");
                    continue;
                }
                assert!(matches!(r, Err(Error::Cancelled)), "{what}: {r:?}");
                assert_eq!(s.steps_left(), 4 - cancelled_step, "{what}");
                assert!(
                    !s.cancel.load(Ordering::SeqCst),
                    "{what}: the flag is lowered"
                );
                if cancelled_step > 0 || check > 0 {
                    // The first step's x_T is drawn once and kept for the retry.
                    assert!(
                        before.0.is_none() || before.0 == s.sample().map(bits),
                        "{what}"
                    );
                }
                assert!(
                    before.1 == s.x0_estimate().map(bits),
                    "{what}: estimate untouched"
                );
                let mut got = Vec::new();
                while s.steps_left() > 0 {
                    s.step().unwrap();
                    got.push((bits(s.sample().unwrap()), bits(s.x0_estimate().unwrap())));
                }
                assert!(got == want[cancelled_step..], "{what}: retry differs");
            }
        }
    }

    /// Initial noise of ±1e30 is finite (`set_initial_noise` takes it) but overflows inside the
    /// network: the first step fails naming itself, nothing of it is kept, steps are refused
    /// until a reset, and after the reset a valid generation has a fresh session's bits.
    #[test]
    fn a_non_finite_step_is_named_and_reset_recovers() {
        let flame = model("flame_tiny.safetensors");
        let motionfm = model("motionfm_tiny.safetensors");
        for (m, sampler) in [(&flame, Sampler::Ddim), (&motionfm, Sampler::Heun)] {
            let len = 16 * m.motion_dim();
            let huge: Vec<f32> = (0..len)
                .map(|i| if i % 2 == 0 { 1e30 } else { -1e30 })
                .collect();
            let calm: Vec<f32> = (0..len).map(|i| (i as f32 * 0.37).sin()).collect();
            let mut s = session(m, sampler, 2.5);
            s.set_initial_noise(&huge).unwrap();
            let e = s.step().unwrap_err();
            assert!(matches!(e, Error::NotFinite(_)), "{sampler:?}: {e}");
            let msg = e.to_string();
            assert!(msg.contains("step 1 of 4"), "{msg}");
            assert!(
                msg.contains("guidance scale (2.5)") && msg.contains("frame "),
                "{msg}"
            );
            assert_eq!(s.steps_left(), 4);
            assert!(
                s.x0_estimate().is_none(),
                "the failed step's estimate is not kept"
            );
            assert!(
                bits(s.sample().unwrap()) == bits(&huge),
                "the sample is still x_T"
            );
            let again = s.step().unwrap_err();
            assert!(
                matches!(again, Error::WrongState(_)) && again.to_string().contains("reset"),
                "{again}"
            );
            s.reset();
            s.set_initial_noise(&calm).unwrap();
            let mut fresh = session(m, sampler, 2.5);
            fresh.set_initial_noise(&calm).unwrap();
            assert!(trajectory(s) == trajectory(fresh), "{sampler:?}");
        }
    }

    #[test]
    fn guidance_outside_0_to_100_is_refused() {
        let m = model("flame_tiny.safetensors");
        let new = |g: f32| {
            Session::new(
                Arc::clone(&m),
                &SessionParams {
                    guidance: Some(g),
                    ..Default::default()
                },
            )
        };
        for g in [-1.0, -0.0001, f32::NAN, f32::INFINITY, 1e30, 100.5] {
            let e = new(g).err().unwrap();
            assert!(matches!(e, Error::InvalidArgument(_)), "{g}: {e}");
            assert!(e.to_string().contains("guidance"), "{g}: {e}");
        }
        for g in [0.0, 1.0, 2.5, MAX_GUIDANCE] {
            assert!(new(g).is_ok(), "{g}");
        }
    }
}
