//! Model families, one file per architecture named after its paper, and [`Model`]: a loaded
//! model file (configuration, text encoder, denoiser), immutable and shared by any number of
//! sessions and threads.
//!
//! # Adding a family
//!
//! A family is one file here plus its converter sub-command (`tools/convert.py`); the session,
//! the CLI, the C ABI and the bindings hold no family-specific code. The file provides:
//!
//! - a [`FamilyConfig`]: its sections of the model file's configuration (`denoiser`, and any of
//!   its own such as a VAE's), parsed by the function its [`Family`] entry names, checked
//!   against bounds and the other sections ([`FamilyConfig::check`]) and against the file's
//!   tensor shapes ([`FamilyConfig::validate`]) before anything is allocated, and able to build
//!   the network ([`FamilyConfig::load`]);
//! - a [`Denoiser`]: what the sampler moves and what the network predicts —
//!   - the sampled space: `sample_rows(frames) × sample_dim()` values (the motion's features,
//!     or a latent);
//!   - how a prompt becomes a [`Condition`] (an opaque value the family downcasts) and what the
//!     unconditional input is;
//!   - the guidance rule ([`Denoiser::guidance`]: plain classifier-free guidance by default; a
//!     family may weight it by time or skip the unconditional pass);
//!   - the batched forward pass, checking the cancel flag between layers;
//!   - for latent families, a [`MotionDecoder`] turning the sample into motion features and
//!     saying how many frames are valid (the model may decide the length).
//!
//! and one line in [`FAMILIES`]. The noise schedule and the samplers are shared
//! ([`crate::diffusion`]), configured by the file's `diffusion` section; text encoders are
//! shared too ([`TextModel`]).
//!
//! [`Model`]: crate::models::Model
//! [`FamilyConfig`]: crate::models::FamilyConfig
//! [`Family`]: crate::models::Family
//! [`FamilyConfig::check`]: crate::models::FamilyConfig::check
//! [`FamilyConfig::validate`]: crate::models::FamilyConfig::validate
//! [`FamilyConfig::load`]: crate::models::FamilyConfig::load
//! [`Denoiser`]: crate::models::Denoiser
//! [`Condition`]: crate::models::Condition
//! [`Denoiser::guidance`]: crate::models::Denoiser::guidance
//! [`MotionDecoder`]: crate::models::MotionDecoder
//! [`FAMILIES`]: crate::models::FAMILIES
//! [`TextModel`]: crate::models::TextModel

mod backward;
pub mod calibrate;
pub mod finemogen;
pub mod flame;
pub(crate) mod layers;
pub mod mdm;
pub mod mld;
pub mod mola;
pub mod motionlcm;
pub mod omg;

use std::any::Any;
use std::fmt;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::{Arc, OnceLock};

use crate::checkpoint::{ModelFile, StoredDtype, Tensor, TOKENIZER_KEY};
use crate::config::{Config, TextConfig};
use crate::edit::EditMethod;
use crate::error::{bad_file, invalid_arg, Error, Result};
use crate::motion::{Format, Normalization, ReadOptions};
use crate::stages::Stage;
use crate::text::t5::T5Encoder;
use crate::text::{ClipTextEncoder, PromptInfo, TextEncoder, TextTokenizer};

pub use crate::kernels::WeightType;
pub use finemogen::{FinemogenDenoiser, FinemogenFamily};
pub use flame::{FlameCondition, FlameConfig, FlameDenoiser};
pub use mdm::{MdmConfig, MdmDenoiser, TimeIndex};
pub use mld::{MldDenoiser, MldFamily};
pub use mola::{MolaDenoiser, MolaFamily};
pub use motionlcm::{MotionLcmDenoiser, MotionLcmFamily};
pub use omg::{OmgDenoiser, OmgFamily};

/// Every family this build runs: the `architecture` values each reads, and its parser.
pub const FAMILIES: &[Family] = &[
    flame::FAMILY,
    mdm::FAMILY,
    mola::FAMILY,
    mld::FAMILY,
    motionlcm::FAMILY,
    finemogen::FAMILY,
    omg::FAMILY,
];

/// Most rows one forward pass batches (conditional + unconditional rows of guidance, with room
/// to spare).
pub const MAX_BATCH: usize = 4;

/// Prefix of the text encoder's tensors inside a libflame file.
pub const TEXT_PREFIX: &str = "text.";

/// A model family's entry in [`FAMILIES`].
pub struct Family {
    /// The `architecture` values of the files this family reads.
    pub architectures: &'static [&'static str],
    /// Parses the family's sections out of the whole configuration JSON (`architecture` is one
    /// of [`Family::architectures`]); bounds are checked later by [`FamilyConfig::check`].
    pub parse: fn(architecture: &str, config: &serde_json::Value) -> Result<Arc<dyn FamilyConfig>>,
}

impl Family {
    /// The family that reads `architecture`.
    pub fn find(architecture: &str) -> Option<&'static Family> {
        FAMILIES
            .iter()
            .find(|f| f.architectures.contains(&architecture))
    }

    /// Every `architecture` value this build reads.
    pub fn all_architectures() -> Vec<&'static str> {
        FAMILIES
            .iter()
            .flat_map(|f| f.architectures.iter().copied())
            .collect()
    }
}

/// A family's configuration, parsed; see the module comment.
pub trait FamilyConfig: fmt::Debug + Send + Sync {
    /// The file's `architecture` value.
    fn architecture(&self) -> &str;
    /// Bounds and names of the family's sections, and the other sections as this family needs
    /// them (text encoder kind, parameterization, unconditional input, …). No tensor is read.
    fn check(&self, cfg: &Config) -> Result<()>;
    /// Every size against the file's tensor shapes (after [`FamilyConfig::check`]).
    fn validate(&self, file: &ModelFile) -> Result<()>;
    /// Feature channels per frame of the motion the model makes (`motion.format` must match).
    fn feature_dim(&self) -> usize;
    /// The largest frame count a session may ask for.
    fn max_frames(&self) -> usize;
    /// One line describing the denoiser's sizes (`flame info`).
    fn summary(&self) -> String;
    /// The `diffusion.uncond` values the family reads.
    fn unconditional_inputs(&self) -> &'static [&'static str] {
        &["empty_prompt", "zeros"]
    }
    /// Builds the network from the file (after validation), with linear weights held as `ty`.
    fn load(
        &self,
        file: &ModelFile,
        cfg: &Config,
        text: &TextModel,
        ty: WeightType,
    ) -> Result<Box<dyn Denoiser>>;
    /// The concrete configuration, for code that knows the family (tests, benchmarks).
    fn as_any(&self) -> &dyn Any;
}

/// How a step combines the conditional and unconditional branches.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Guidance {
    /// The conditional branch alone: one network row per evaluation.
    Conditional,
    /// `uncond + w · (cond − uncond)`: two rows.
    Mix(f32),
    /// The network takes the scale as an input (MotionLCM's guidance embedding of `w`, the
    /// scale minus 1): one row, through [`Denoiser::forward_embedded`].
    Embedded(f32),
}

/// What the session needs from a family's network; see the module comment.
pub trait Denoiser: Send + Sync {
    /// Channels per row of the sampled space.
    fn sample_dim(&self) -> usize;
    /// Rows of the sampled space for a generation of `frames` motion frames.
    fn sample_rows(&self, frames: usize) -> usize {
        frames
    }
    /// Whether the network's own layers read the sampled rows with no projection in between
    /// (MLD's and MotionLCM v1's latent is as wide as the skip stack). A quantiser tells the
    /// projections from and to the sampled space by their width, which such a network's every
    /// layer shares.
    fn reads_sample_directly(&self) -> bool {
        false
    }
    /// Channels per row of the network's output (more than [`Denoiser::sample_dim`] when the
    /// network also predicts variance values, which follow the prediction in each row).
    fn output_dim(&self) -> usize {
        self.sample_dim()
    }
    /// Encodes a prompt (never blank: a blank prompt is the unconditional input).
    fn encode_prompt(&self, text: &TextModel, prompt: &str) -> Result<Condition>;
    /// Encodes prompts per time stage and body part (checked by [`crate::stages::check`]);
    /// `None` when the family takes one prompt only.
    fn encode_stages(&self, _text: &TextModel, _stages: &[Stage]) -> Option<Result<Condition>> {
        None
    }
    /// Whether [`Denoiser::encode_stages`] is the family's own (else one stage without part
    /// texts is the plain prompt).
    fn takes_stages(&self) -> bool {
        false
    }
    /// The unconditional input of guidance, as `diffusion.uncond` names it (`empty_prompt` or
    /// `zeros`; the family's check has refused what it cannot use).
    fn unconditional(&self, text: &TextModel, uncond: &str) -> Result<Condition>;
    /// Whether `cond` was made for this network (right type and sizes).
    fn check_condition(&self, cond: &Condition) -> Result<()>;
    /// Whether `cond` can condition a generation of `frames` frames (checked when a session
    /// takes it, so a prompt that cannot run is refused before the first step).
    fn check_frames(&self, _cond: &Condition, _frames: usize) -> Result<()> {
        Ok(())
    }
    /// The guidance rule at scale `scale` (in [0, 100]) and network time `t`. By default
    /// classifier-free guidance: scale 1 is the conditional branch alone.
    fn guidance(&self, scale: f32, _t: f32) -> Guidance {
        if scale == 1.0 {
            Guidance::Conditional
        } else {
            Guidance::Mix(scale)
        }
    }
    /// One batched forward pass: `x` is `[batch, rows, sample_dim]`, `out` is
    /// `[batch, rows, output_dim]`, row `b` conditioned on `conds[b]` (1..=[`MAX_BATCH`]
    /// conditions). `t` is the network's time input. `cancel` is checked before every layer.
    #[allow(clippy::too_many_arguments)]
    fn forward(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        conds: &[&Condition],
        out: &mut [f32],
        ws: &mut Workspace,
        cancel: &Cancel,
    ) -> Result<()>;
    /// Whether the network takes a control signal from joint positions
    /// ([`Denoiser::encode_control`]: MotionLCM's trajectory ControlNet).
    fn takes_control(&self) -> bool {
        false
    }
    /// Encodes joint positions to follow for a generation of `frames` frames into the control
    /// value [`Denoiser::forward_embedded`] takes: `positions` and `weights` (0 or 1 per
    /// coordinate) are `[hint frames × joints]` in the motion format's native frame (metres),
    /// hint frames ≤ `frames`. Families without control refuse.
    fn encode_control(
        &self,
        _frames: usize,
        _positions: &[[f64; 3]],
        _weights: &[[f64; 3]],
    ) -> Result<Vec<f32>> {
        Err(invalid_arg!(
            "this model has no trajectory control (a ControlNet); steer it with position \
             targets where its family takes them"
        ))
    }
    /// [`Denoiser::forward`] for a network that takes the guidance as an input
    /// ([`Guidance::Embedded`]), conditioned on `w` and on `control` (from
    /// [`Denoiser::encode_control`]). Families without one refuse.
    #[allow(clippy::too_many_arguments)]
    fn forward_embedded(
        &self,
        _x: &[f32],
        _rows: usize,
        _t: f32,
        _w: f32,
        _conds: &[&Condition],
        _control: Option<&[f32]>,
        _out: &mut [f32],
        _ws: &mut Workspace,
        _cancel: &Cancel,
    ) -> Result<()> {
        Err(invalid_arg!(
            "this model's network does not take the guidance scale as an input"
        ))
    }
    /// Consistency latent tuning ([`crate::tuning`]): ε̂ of the network with the guidance
    /// embedded as `w` and `control` (as [`Denoiser::forward_embedded`], one sample of `rows`
    /// rows), with what [`Denoiser::eps_vjp`] reads kept in `tape`. Families without a
    /// backward through their network refuse.
    #[allow(clippy::too_many_arguments)]
    fn eps_recorded(
        &self,
        _z: &[f32],
        _rows: usize,
        _t: f32,
        _w: f32,
        _cond: &Condition,
        _control: Option<&[f32]>,
        _eps: &mut [f32],
        _tape: &mut Workspace,
    ) -> Result<()> {
        Err(invalid_arg!(
            "latent tuning differentiates the network, and libflame has no backward through this \
             model's"
        ))
    }
    /// `d_z = (∂ε̂/∂z)ᵀ d_eps` at the pass [`Denoiser::eps_recorded`] kept in `tape`
    /// (overwritten).
    fn eps_vjp(&self, _d_eps: &[f32], _d_z: &mut [f32], _tape: &mut Workspace) -> Result<()> {
        Err(invalid_arg!(
            "latent tuning differentiates the network, and libflame has no backward through this \
             model's"
        ))
    }
    /// For latent families: what turns the sample into motion features. `None`: the sample
    /// is the motion.
    fn decoder(&self) -> Option<&dyn MotionDecoder> {
        None
    }
    /// What [`EditMethod::Auto`] means for this family's diffusion models (flow models always
    /// rewrite the trajectory).
    fn default_edit_method(&self) -> EditMethod {
        EditMethod::ReplaceX0
    }
    /// Bytes of the packed linear weights (the part [`WeightType`] changes).
    fn linear_weight_bytes(&self) -> usize;
    /// The concrete network, for code that knows the family (tests, benchmarks).
    fn as_any(&self) -> &dyn Any;
}

/// Writes the gradient of a loss on `[frames, feature_dim]` motion features (first argument,
/// `frames` the second) into the third argument.
pub type FeatureLoss<'a> = dyn FnMut(&[f32], usize, &mut [f32]) -> Result<()> + 'a;

/// Turns a latent family's sample into motion features.
pub trait MotionDecoder: Send + Sync {
    /// Decodes `sample` (`[rows, sample_dim]`, of a generation asked for `frames` frames) into
    /// `out` (`[valid, feature_dim]`, only the valid frames) and returns `valid`.
    fn decode(
        &self,
        sample: &[f32],
        rows: usize,
        frames: usize,
        out: &mut Vec<f32>,
        ws: &mut Workspace,
    ) -> Result<usize>;
    /// One line describing the decoder (`flame info`).
    fn summary(&self) -> String;
    /// [`MotionDecoder::decode`] into `frames` frames (every one, `[frames, feature_dim]`),
    /// with what [`MotionDecoder::decode_vjp`] reads kept in `tape`. Decoders without that
    /// backward refuse.
    fn decode_recorded(
        &self,
        _sample: &[f32],
        _rows: usize,
        _frames: usize,
        _out: &mut Vec<f32>,
        _tape: &mut Workspace,
    ) -> Result<()> {
        Err(crate::error::invalid_arg!(
            "latent tuning differentiates the decoder, and libflame has no recorded backward \
             through this one"
        ))
    }
    /// `d_sample = (∂features/∂sample)ᵀ d_features` at the decode kept in `tape`
    /// (overwritten).
    fn decode_vjp(
        &self,
        _d_features: &[f32],
        _d_sample: &mut [f32],
        _tape: &mut Workspace,
    ) -> Result<()> {
        Err(crate::error::invalid_arg!(
            "latent tuning differentiates the decoder, and libflame has no recorded backward \
             through this one"
        ))
    }
    /// Whether [`MotionDecoder::vjp`] is implemented.
    fn has_vjp(&self) -> bool {
        false
    }
    /// The reverse-mode product gradient guidance needs: decodes `sample` (`[rows,
    /// sample_dim]`), hands `loss` the features of every decoded frame (`[frames,
    /// feature_dim]`, model space, before any length cut) to write their gradient into its third
    /// argument (same shape), and writes the gradient with respect to `sample` into `d_sample`.
    fn vjp(
        &self,
        _sample: &[f32],
        _rows: usize,
        _loss: &mut FeatureLoss,
        _d_sample: &mut Vec<f32>,
        _ws: &mut Workspace,
    ) -> Result<()> {
        Err(crate::error::invalid_arg!(
            "this model's decoder has no gradient: position targets do not apply"
        ))
    }
}

/// What a denoiser is conditioned on, derived from a prompt once and reused at every step: a
/// value of the family's own type, cheap to clone. A condition of several time stages also
/// says their frame counts: its sample is laid out `[stages, longest stage, sample_dim]`.
#[derive(Clone)]
pub struct Condition {
    value: Arc<dyn Any + Send + Sync>,
    stages: Option<Arc<[usize]>>,
}

/// A single text vector (MDM, Motion Flow Matching: CLIP's projected end-of-text features).
#[derive(Clone, Debug, PartialEq)]
pub struct TextVector(pub Vec<f32>);

impl Condition {
    /// Wraps a family's condition value.
    pub fn new<T: Any + Send + Sync>(value: T) -> Condition {
        Condition {
            value: Arc::new(value),
            stages: None,
        }
    }

    /// Wraps a family's condition of several time stages of `frames` frames each.
    pub fn with_stages<T: Any + Send + Sync>(value: T, frames: Vec<usize>) -> Condition {
        Condition {
            value: Arc::new(value),
            stages: (frames.len() > 1).then(|| frames.into()),
        }
    }

    /// The frames of each stage, for a condition of two or more stages.
    pub fn stage_frames(&self) -> Option<&[usize]> {
        self.stages.as_deref()
    }

    /// A text vector (for families conditioned on one; see [`TextVector`]).
    pub fn text_vector(v: Vec<f32>) -> Condition {
        Condition::new(TextVector(v))
    }

    /// The family's value, when it is a `T`.
    pub fn get<T: Any>(&self) -> Option<&T> {
        self.value.downcast_ref()
    }

    /// The text vector, for conditions made by [`Condition::text_vector`].
    pub fn as_text_vector(&self) -> Option<&[f32]> {
        self.get::<TextVector>().map(|v| &v.0[..])
    }
}

impl fmt::Debug for Condition {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self.as_text_vector() {
            Some(v) => write!(f, "Condition(text vector of {})", v.len()),
            None => f.write_str("Condition(..)"),
        }
    }
}

/// A forward pass's batch: 1 to [`MAX_BATCH`] conditions.
fn check_batch(conds: &[&Condition]) -> Result<()> {
    if conds.is_empty() || conds.len() > MAX_BATCH {
        return Err(invalid_arg!(
            "a forward pass takes 1 to {MAX_BATCH} conditions, got {}",
            conds.len()
        ));
    }
    Ok(())
}

/// The family's views of a batch of conditions, on the stack (a step allocates nothing):
/// `Err` when one was made for another family.
pub fn condition_views<'a, T: Any>(conds: &[&'a Condition]) -> Result<([&'a T; MAX_BATCH], usize)> {
    let wrong = || invalid_arg!("a condition was made for another architecture");
    check_batch(conds)?;
    let first = conds[0].get::<T>().ok_or_else(wrong)?;
    let mut views = [first; MAX_BATCH];
    for (v, c) in views.iter_mut().zip(conds) {
        *v = c.get::<T>().ok_or_else(wrong)?;
    }
    Ok((views, conds.len()))
}

/// The text vectors of a batch of [`TextVector`] conditions, on the stack.
pub fn text_vector_views<'a>(conds: &[&'a Condition]) -> Result<([&'a [f32]; MAX_BATCH], usize)> {
    let (views, n) = condition_views::<TextVector>(conds)?;
    let mut texts = [&[][..]; MAX_BATCH];
    for (t, v) in texts.iter_mut().zip(&views[..n]) {
        *t = &v.0[..];
    }
    Ok((texts, n))
}

/// Reusable buffers of a forward pass (and of a decode), so steps after the first do not
/// allocate: the family keeps a value of its own type here.
#[derive(Default)]
pub struct Workspace(Option<Box<dyn Any + Send>>);

impl Workspace {
    /// The family's buffers, created on first use (and again if another family used this
    /// workspace before).
    pub fn get<T: Any + Send + Default>(&mut self) -> &mut T {
        if !self.0.as_ref().is_some_and(|b| b.is::<T>()) {
            self.0 = Some(Box::new(T::default()));
        }
        self.0
            .as_mut()
            .and_then(|b| b.downcast_mut())
            .expect("set just above")
    }
}

/// How a model file is loaded.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// What the linear layers' weights are held and multiplied in, whatever the file stores
    /// (an f32 file can load as f16 or bf16; an f16 file as f32). Embeddings, norms and biases
    /// stay f32.
    pub weights: WeightType,
}

/// The text encoder of a model, by kind.
pub enum TextModel {
    /// BERT or RoBERTa: per-token states and the pooler output (FLAME).
    Bert(TextEncoder),
    /// CLIP: the projected end-of-text vector (MDM), prompts truncated to `context` tokens.
    Clip {
        /// The CLIP text tower.
        encoder: ClipTextEncoder,
        /// Tokens a prompt keeps, start and end included: the file's `text_encoder.max_length`
        /// (MDM: 22, docs/official/mdm.md#clip-prompt-encoding).
        context: usize,
    },
    /// sentence-t5: the normalised sentence vector (MotionLCM).
    T5 {
        /// The T5 encoder with its Dense head.
        encoder: T5Encoder,
        /// The file's tokenizer.json (T5's Unigram; `</s>` appended, pad 0).
        tokenizer: TextTokenizer,
        /// Tokens a prompt keeps, `</s>` included (`text_encoder.max_length`).
        max_length: usize,
    },
}

impl TextModel {
    /// CLIP's projected end-of-text vector of `prompt`; an error for other encoders.
    pub fn clip_vector(&self, prompt: &str) -> Result<Vec<f32>> {
        match self {
            TextModel::Clip { encoder, context } => {
                Ok(encoder.encode_through_end(prompt, *context)?.projected)
            }
            _ => Err(invalid_arg!("this model's text encoder is not CLIP")),
        }
    }

    /// Width of [`TextModel::clip_vector`]'s vectors (0 for other encoders).
    pub fn clip_projection_dim(&self) -> usize {
        match self {
            TextModel::Clip { encoder, .. } => encoder.projection_dim(),
            _ => 0,
        }
    }

    /// sentence-t5's normalised vector of `prompt` (cut to `max_length` tokens, `</s>`
    /// included); an error for other encoders.
    pub fn t5_vector(&self, prompt: &str) -> Result<Vec<f32>> {
        match self {
            TextModel::T5 {
                encoder,
                tokenizer,
                max_length,
            } => {
                let t = tokenizer.encode(prompt, *max_length, false)?;
                encoder.sentence_embedding(&t.ids, &t.mask)
            }
            _ => Err(invalid_arg!("this model's text encoder is not T5")),
        }
    }

    fn linear_weight_bytes(&self) -> usize {
        match self {
            TextModel::Bert(t) => t.linear_weight_bytes(),
            TextModel::Clip { encoder, .. } => encoder.linear_weight_bytes(),
            TextModel::T5 { encoder, .. } => encoder.linear_weight_bytes(),
        }
    }
}

/// The unconditional input of a family conditioned on one text vector of `dim` values.
pub fn text_vector_uncond(text: &TextModel, uncond: &str, dim: usize) -> Result<Condition> {
    match uncond {
        "zeros" => Ok(Condition::text_vector(vec![0.0; dim])),
        _ => Ok(Condition::text_vector(text.clip_vector("")?)),
    }
}

/// Checks a text-vector condition of `dim` values.
pub fn check_text_vector(cond: &Condition, dim: usize) -> Result<()> {
    match cond.as_text_vector() {
        Some(v) if v.len() == dim => Ok(()),
        Some(v) => Err(invalid_arg!(
            "text vector has {} values, the model expects {dim}",
            v.len()
        )),
        None => Err(invalid_arg!(
            "the condition was made for another architecture"
        )),
    }
}

/// A session's cancel flag as the forward passes see it: checked between layers (never inside
/// a kernel), so a cancelled step returns within about one layer's time.
pub struct Cancel<'a> {
    flag: &'a AtomicBool,
    /// Checks made so far in this step.
    checks: AtomicUsize,
    /// Test hook: the check with this index (0-based over the step) finds the flag raised, as
    /// if another thread had raised it just before. `None` outside tests.
    trip_at: Option<usize>,
}

impl<'a> Cancel<'a> {
    pub(crate) fn new(flag: &'a AtomicBool, trip_at: Option<usize>) -> Cancel<'a> {
        Cancel {
            flag,
            checks: AtomicUsize::new(0),
            trip_at,
        }
    }

    /// A flag nobody raises: plain forward passes.
    pub fn never() -> Cancel<'static> {
        static NEVER: AtomicBool = AtomicBool::new(false);
        Cancel::new(&NEVER, None)
    }

    /// `Err(Cancelled)` when the flag is raised; lowers it, so a cancel abandons one step.
    pub fn check(&self) -> Result<()> {
        let n = self.checks.fetch_add(1, Ordering::Relaxed);
        if self.trip_at == Some(n) {
            self.flag.store(true, Ordering::SeqCst);
        }
        if self.flag.load(Ordering::Relaxed) && self.flag.swap(false, Ordering::SeqCst) {
            return Err(Error::Cancelled);
        }
        Ok(())
    }
}

/// A loaded model: read-only after loading, `Send + Sync`.
pub struct Model {
    config: Config,
    text: TextModel,
    denoiser: Box<dyn Denoiser>,
    dtype: Option<StoredDtype>,
    weights: WeightType,
    format: Format,
    /// `motion.mean` / `motion.std`: what the model's features are normalised with, if anything.
    stats: Option<(Tensor, Tensor)>,
    /// The unconditional input of classifier-free guidance, computed once per model.
    uncond: OnceLock<Condition>,
}

impl Model {
    /// Loads a libflame model file by memory-mapping it (f32 weights).
    pub fn load(path: impl AsRef<Path>) -> Result<Model> {
        Model::load_with(path, &LoadOptions::default())
    }

    /// Loads a libflame model file by memory-mapping it, with `opts`.
    pub fn load_with(path: impl AsRef<Path>, opts: &LoadOptions) -> Result<Model> {
        Model::from_file_with(ModelFile::open(path.as_ref())?, opts)
    }

    /// Loads a model from the bytes of a model file (copied).
    pub fn from_bytes(bytes: &[u8]) -> Result<Model> {
        Model::from_file(ModelFile::from_bytes(bytes)?)
    }

    /// Builds the model from an opened file, validating every tensor against the configuration.
    pub fn from_file(file: ModelFile) -> Result<Model> {
        Model::from_file_with(file, &LoadOptions::default())
    }

    /// [`Model::from_file`] with `opts`.
    pub fn from_file_with(file: ModelFile, opts: &LoadOptions) -> Result<Model> {
        let ty = opts.weights;
        if !ty.native_on_this_cpu() {
            return Err(invalid_arg!(
                "weights {} need {} (this CPU or the kernel chosen, {}, lacks it); use f32, \
                 f16 or bf16",
                ty.name(),
                if ty == WeightType::Int8 {
                    "AVX2 or AVX512_VNNI on the avx2 or avx512 kernel"
                } else {
                    "AVX512_BF16 on the avx512 kernel"
                },
                crate::kernels::kernel_name()
            ));
        }
        if let (WeightType::Int8, Some(g)) = (ty, file.int8_group()?) {
            return Err(invalid_arg!(
                "{} holds int8 weights with one scale per group of {g} inputs, which the int8 \
                 kernels (one scale per output row) do not run; load it as f32, f16 or bf16",
                file.source()
            ));
        }
        let config = Config::from_file(&file)?;
        let tokenizer = file
            .metadata(TOKENIZER_KEY)
            .ok_or_else(|| bad_file!("no `{TOKENIZER_KEY}` metadata (the tokenizer.json text)"))?;
        // The text encoder runs once per prompt: reduced precision would buy nothing there and
        // perturb the condition of every step, so both compute types keep its weights in f32
        // (bf16 storage there was 40% of bf16-compute's error on the demo model: 0.090 → 0.052).
        let text_ty = match ty {
            WeightType::Bf16Compute | WeightType::Int8 => WeightType::F32,
            other => other,
        };
        let text = match &config.text_encoder {
            TextConfig::Bert(t) => TextModel::Bert(TextEncoder::load_with(
                &file,
                TEXT_PREFIX,
                t,
                tokenizer,
                text_ty,
            )?),
            TextConfig::Clip(c) => TextModel::Clip {
                encoder: ClipTextEncoder::load_with(
                    &file,
                    TEXT_PREFIX,
                    &c.clip,
                    tokenizer,
                    text_ty,
                )?,
                context: c.max_length,
            },
            TextConfig::T5(c) => {
                let encoder = T5Encoder::load(
                    &file,
                    TEXT_PREFIX,
                    Some(&format!("{TEXT_PREFIX}dense")),
                    c.relative_attention_max_distance,
                    text_ty,
                )?;
                // T5's `<pad>` is id 0; the tokenizer's ids must fit the embedding table.
                let tokenizer = TextTokenizer::from_json(tokenizer, encoder.dims().vocab, 0)?;
                TextModel::T5 {
                    encoder,
                    tokenizer,
                    max_length: c.max_length,
                }
            }
        };
        let denoiser = config.denoiser.load(&file, &config, &text, ty)?;
        // The configuration's check has matched the format to the family's features.
        let format: Format = config.motion.format.parse()?;
        let dim = format.feature_dim();
        let stats = if file.contains("motion.mean") || format.is_normalized() {
            Some((
                file.tensor("motion.mean", &[dim])?,
                file.tensor("motion.std", &[dim])?,
            ))
        } else {
            None
        };
        let dtype = file.dominant_dtype();
        Ok(Model {
            config,
            text,
            denoiser,
            dtype,
            weights: ty,
            format,
            stats,
            uncond: OnceLock::new(),
        })
    }

    /// The validated configuration read from the model file.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// The prompt encoder, of whichever kind the model uses.
    pub fn text_model(&self) -> &TextModel {
        &self.text
    }

    /// The BERT/RoBERTa encoder, for models that use one.
    pub fn text_encoder(&self) -> Option<&TextEncoder> {
        match &self.text {
            TextModel::Bert(t) => Some(t),
            _ => None,
        }
    }

    /// The family's network, behind the interface sessions drive.
    pub fn denoiser(&self) -> &dyn Denoiser {
        &*self.denoiser
    }

    /// The motion format of the model's features.
    pub fn motion_format(&self) -> Format {
        self.format
    }

    /// Options for decoding this model's features into poses: its normalisation statistics, a
    /// temporal smoothing σ in frames (0 = none) and quaternion sign continuity.
    pub fn read_options(&self, smooth_sigma: f32, continuous: bool) -> ReadOptions<'_> {
        ReadOptions {
            smooth_sigma,
            continuous,
            normalization: self.stats.as_ref().map(|(m, s)| Normalization {
                mean: m.data(),
                std: s.data(),
            }),
            finish: Default::default(),
            fps: self.config.motion.fps,
        }
    }

    /// The dtype most of the file's weights are stored in.
    pub fn stored_dtype(&self) -> Option<StoredDtype> {
        self.dtype
    }

    /// What the linear layers' weights are held in (the load option).
    pub fn weight_type(&self) -> WeightType {
        self.weights
    }

    /// Bytes of the denoiser's and text encoder's packed linear weights.
    pub fn linear_weight_bytes(&self) -> usize {
        self.text.linear_weight_bytes() + self.denoiser.linear_weight_bytes()
    }

    /// Feature channels per frame of the motion the model makes (its format's).
    pub fn motion_dim(&self) -> usize {
        self.format.feature_dim()
    }

    /// Channels per row of the sampled space: [`Model::motion_dim`] unless the model samples
    /// a latent.
    pub fn sample_dim(&self) -> usize {
        self.denoiser.sample_dim()
    }

    /// Rows of the sampled space for `frames` motion frames.
    pub fn sample_rows(&self, frames: usize) -> usize {
        self.denoiser.sample_rows(frames)
    }

    /// Whether the model samples a latent that a decoder turns into motion.
    pub fn is_latent(&self) -> bool {
        self.denoiser.decoder().is_some()
    }

    /// Output channels per row of the denoiser (FLAME adds its variance values).
    pub fn output_dim(&self) -> usize {
        self.denoiser.output_dim()
    }

    /// The largest frame count a session may ask for.
    pub fn max_frames(&self) -> usize {
        self.config.denoiser.max_frames()
    }

    /// Encodes a prompt into the denoiser's conditioning.
    pub fn encode_prompt(&self, prompt: &str) -> Result<Condition> {
        self.denoiser.encode_prompt(&self.text, prompt)
    }

    /// Encodes prompts per time stage (and body part): the family's own encoding, or for a
    /// family that takes one prompt, one stage without part texts as that prompt.
    pub fn encode_stages(&self, stages: &[Stage]) -> Result<Condition> {
        if let Some(c) = self.denoiser.encode_stages(&self.text, stages) {
            return c;
        }
        match stages {
            [one] if !one.has_parts() => self.encode_prompt(&one.text),
            _ => Err(invalid_arg!(
                "this {} model takes one prompt per generation (a single stage without part texts); prompts per time stage and body part are FineMoGen's",
                self.config.architecture
            )),
        }
    }

    /// How `prompt` fits the text encoder's window: tokens kept, tokens cut and the cut text.
    pub fn prompt_info(&self, prompt: &str) -> Result<PromptInfo> {
        match &self.text {
            TextModel::Bert(t) => t.tokenizer().fit(prompt, t.max_length()),
            TextModel::Clip { encoder, context } => encoder.fit(prompt, *context),
            TextModel::T5 {
                tokenizer,
                max_length,
                ..
            } => tokenizer.fit(prompt, *max_length),
        }
    }

    /// The unconditional input for guidance, computed once per model, as the configuration's
    /// `diffusion.uncond` says (the empty prompt's encoding, or a zero text vector).
    pub fn uncond(&self) -> Result<&Condition> {
        if let Some(c) = self.uncond.get() {
            return Ok(c);
        }
        let c = self
            .denoiser
            .unconditional(&self.text, &self.config.diffusion.uncond)?;
        Ok(self.uncond.get_or_init(|| c))
    }

    /// Checks that a condition was made for this model's denoiser.
    pub fn check_condition(&self, cond: &Condition) -> Result<()> {
        self.denoiser.check_condition(cond)
    }

    /// One batched forward pass: `x` is `[batch, rows, sample_dim]`, `out` is
    /// `[batch, rows, output_dim]`, row `b` conditioned on `conds[b]`. `t` is the network's
    /// time input (a diffusion step, or flow time in [0, 1] for Motion Flow Matching).
    pub fn forward(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        conds: &[&Condition],
        out: &mut [f32],
        ws: &mut Workspace,
    ) -> Result<()> {
        self.forward_cancellable(x, rows, t, conds, out, ws, &Cancel::never())
    }

    /// [`Model::forward`] that checks `cancel` before every layer.
    #[allow(clippy::too_many_arguments)]
    pub fn forward_cancellable(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        conds: &[&Condition],
        out: &mut [f32],
        ws: &mut Workspace,
        cancel: &Cancel,
    ) -> Result<()> {
        check_batch(conds)?;
        self.denoiser.forward(x, rows, t, conds, out, ws, cancel)
    }

    /// [`Model::forward_cancellable`] with the guidance embedded as an input `w`
    /// ([`Guidance::Embedded`]) and an optional control value ([`Denoiser::encode_control`]).
    #[allow(clippy::too_many_arguments)]
    pub fn forward_embedded(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        w: f32,
        conds: &[&Condition],
        control: Option<&[f32]>,
        out: &mut [f32],
        ws: &mut Workspace,
        cancel: &Cancel,
    ) -> Result<()> {
        check_batch(conds)?;
        if !w.is_finite() {
            return Err(invalid_arg!(
                "the embedded guidance must be finite, got {w}"
            ));
        }
        self.denoiser
            .forward_embedded(x, rows, t, w, conds, control, out, ws, cancel)
    }

    /// Decodes a sample of a generation of `frames` frames into motion features (`[valid,
    /// motion_dim]`, returns `valid`); for a model that samples the motion itself, a copy.
    pub fn decode(
        &self,
        sample: &[f32],
        frames: usize,
        out: &mut Vec<f32>,
        ws: &mut Workspace,
    ) -> Result<usize> {
        let rows = self.sample_rows(frames);
        if sample.len() != rows * self.sample_dim() {
            return Err(invalid_arg!(
                "a sample of {frames} frames has {rows} × {} values, got {}",
                self.sample_dim(),
                sample.len()
            ));
        }
        match self.denoiser.decoder() {
            Some(d) => d.decode(sample, rows, frames, out, ws),
            None => {
                out.clear();
                out.extend_from_slice(sample);
                Ok(frames)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    fn assert_send_sync<T: Send + Sync>() {}

    #[test]
    fn model_is_shareable() {
        assert_send_sync::<super::Model>();
    }

    #[test]
    fn every_architecture_has_one_family() {
        let all = super::Family::all_architectures();
        let mut unique = all.clone();
        unique.sort();
        unique.dedup();
        assert_eq!(all.len(), unique.len(), "{all:?}");
    }
}
