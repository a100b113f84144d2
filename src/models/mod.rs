//! Denoiser networks, one file per architecture named after its paper, and [`Model`]: a loaded
//! model file (configuration, text encoder, denoiser), immutable and shared by any number of
//! sessions and threads.

pub mod flame;
mod layers;
pub mod mdm;

use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::OnceLock;

use crate::checkpoint::{ModelFile, StoredDtype, Tensor, TOKENIZER_KEY};
use crate::config::{Config, DenoiserConfig, TextConfig};
use crate::error::{bad_file, invalid_arg, Error, Result};
use crate::motion::{Format, Normalization, ReadOptions};
use crate::text::{ClipTextEncoder, PromptInfo, TextEncoder};

pub use crate::kernels::WeightType;
pub use flame::{FlameCondition, FlameDenoiser};
pub use mdm::{MdmDenoiser, TimeIndex};

/// Most rows one forward pass batches (conditional + unconditional rows of guidance, with room
/// to spare).
pub const MAX_BATCH: usize = 4;

/// Prefix of the text encoder's tensors inside a libflame file.
pub const TEXT_PREFIX: &str = "text.";

/// How a model file is loaded.
#[derive(Clone, Debug, Default)]
pub struct LoadOptions {
    /// What the linear layers' weights are held and multiplied in, whatever the file stores
    /// (an f32 file can load as f16 or bf16; an f16 file as f32). Embeddings, norms and biases
    /// stay f32.
    pub weights: WeightType,
}

/// The denoiser of a model, by architecture.
pub enum Denoiser {
    Flame(FlameDenoiser),
    /// MDM (x0 prediction) and Motion Flow Matching (velocity) share this network.
    Mdm(MdmDenoiser),
}

/// The text encoder of a model, by kind.
pub enum TextModel {
    /// BERT or RoBERTa: per-token states and the pooler output (FLAME).
    Bert(TextEncoder),
    /// CLIP: the projected end-of-text vector (MDM), prompts truncated to `context` tokens.
    Clip {
        encoder: ClipTextEncoder,
        context: usize,
    },
}

/// What a denoiser is conditioned on, derived from a prompt once and reused at every step.
#[derive(Clone, Debug)]
pub enum Condition {
    Flame(FlameCondition),
    /// MDM's text vector (CLIP's projection); zeros are the unconditional input.
    Mdm(Vec<f32>),
}

/// Reusable buffers of a forward pass, so steps after the first do not allocate.
#[derive(Default)]
pub struct Workspace {
    flame: flame::Workspace,
    mdm: mdm::Workspace,
}

/// A session's cancel flag as the forward passes see it: checked between transformer layers
/// (never inside a kernel), so a cancelled step returns within about one layer's time.
pub(crate) struct Cancel<'a> {
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
    pub(crate) fn never() -> Cancel<'static> {
        static NEVER: AtomicBool = AtomicBool::new(false);
        Cancel::new(&NEVER, None)
    }

    /// `Err(Cancelled)` when the flag is raised; lowers it, so a cancel abandons one step.
    pub(crate) fn check(&self) -> Result<()> {
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
    denoiser: Denoiser,
    dtype: Option<StoredDtype>,
    weights: WeightType,
    format: Format,
    /// `motion.mean` / `motion.std`: what the denoiser's features are normalised with, if anything.
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
        let config = Config::from_file(&file)?;
        let tokenizer = file
            .metadata(TOKENIZER_KEY)
            .ok_or_else(|| bad_file!("no `{TOKENIZER_KEY}` metadata (the tokenizer.json text)"))?;
        let text = match &config.text_encoder {
            TextConfig::Bert(t) => TextModel::Bert(TextEncoder::load_with(
                &file,
                TEXT_PREFIX,
                t,
                tokenizer,
                ty,
            )?),
            TextConfig::Clip(c) => TextModel::Clip {
                encoder: ClipTextEncoder::load_with(&file, TEXT_PREFIX, &c.clip, tokenizer, ty)?,
                context: c.max_length,
            },
        };
        let denoiser = match (&config.denoiser, &text) {
            (DenoiserConfig::Flame(d), TextModel::Bert(t)) => {
                Denoiser::Flame(FlameDenoiser::load_with(&file, d, t.hidden_size(), ty)?)
            }
            (DenoiserConfig::Mdm(d), TextModel::Clip { encoder, .. }) => {
                if encoder.projection_dim() != d.clip_dim {
                    return Err(bad_file!(
                        "the CLIP projection has {} values, denoiser.clip_dim is {}",
                        encoder.projection_dim(),
                        d.clip_dim
                    ));
                }
                let m = MdmDenoiser::load_with(&file, d, ty)?;
                Denoiser::Mdm(if config.architecture == "motionfm" {
                    m.with_time_index(TimeIndex::FlowMatching)
                } else {
                    m
                })
            }
            _ => {
                return Err(bad_file!(
                    "architecture `{}` cannot use a `{}` text encoder",
                    config.architecture,
                    config.text_encoder.kind()
                ))
            }
        };
        let dim = match &denoiser {
            Denoiser::Flame(f) => f.motion_dim(),
            Denoiser::Mdm(m) => m.motion_dim(),
        };
        let format: Format = config
            .motion
            .format
            .parse()
            .map_err(|_| bad_file!("unknown motion.format `{}`", config.motion.format))?;
        if format.feature_dim() != dim {
            return Err(bad_file!(
                "motion.format `{format}` has {} features per frame, the denoiser {dim}",
                format.feature_dim()
            ));
        }
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

    pub fn config(&self) -> &Config {
        &self.config
    }

    pub fn text_model(&self) -> &TextModel {
        &self.text
    }

    /// The BERT/RoBERTa encoder, for models that use one.
    pub fn text_encoder(&self) -> Option<&TextEncoder> {
        match &self.text {
            TextModel::Bert(t) => Some(t),
            TextModel::Clip { .. } => None,
        }
    }

    pub fn denoiser(&self) -> &Denoiser {
        &self.denoiser
    }

    /// The motion format of the denoiser's features.
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
        let text = match &self.text {
            TextModel::Bert(t) => t.linear_weight_bytes(),
            TextModel::Clip { encoder, .. } => encoder.linear_weight_bytes(),
        };
        text + match &self.denoiser {
            Denoiser::Flame(f) => f.linear_weight_bytes(),
            Denoiser::Mdm(m) => m.linear_weight_bytes(),
        }
    }

    /// Feature channels per frame.
    pub fn motion_dim(&self) -> usize {
        match &self.denoiser {
            Denoiser::Flame(f) => f.motion_dim(),
            Denoiser::Mdm(m) => m.motion_dim(),
        }
    }

    /// Output channels per frame of the denoiser (FLAME adds its variance values).
    pub fn output_dim(&self) -> usize {
        match &self.denoiser {
            Denoiser::Flame(f) => f.output_dim(),
            Denoiser::Mdm(m) => m.output_dim(),
        }
    }

    /// The largest frame count a session may ask for.
    pub fn max_frames(&self) -> usize {
        match &self.denoiser {
            Denoiser::Flame(f) => f.max_frames(),
            Denoiser::Mdm(m) => m.max_frames(),
        }
    }

    /// Encodes a prompt into the denoiser's conditioning.
    pub fn encode_prompt(&self, prompt: &str) -> Result<Condition> {
        match (&self.text, &self.denoiser) {
            (TextModel::Bert(t), Denoiser::Flame(f)) => {
                Ok(Condition::Flame(f.condition(&t.encode(prompt)?)?))
            }
            (TextModel::Clip { encoder, context }, Denoiser::Mdm(_)) => {
                Ok(Condition::Mdm(encoder.encode(prompt, *context)?.projected))
            }
            _ => unreachable!("text encoder and denoiser are paired at load"),
        }
    }

    /// How `prompt` fits the text encoder's window: tokens kept, tokens cut and the cut text.
    pub fn prompt_info(&self, prompt: &str) -> Result<PromptInfo> {
        match &self.text {
            TextModel::Bert(t) => t.tokenizer().fit(prompt, t.max_length()),
            TextModel::Clip { encoder, context } => encoder.fit(prompt, *context),
        }
    }

    /// The unconditional input for guidance, computed once per model: the empty prompt's
    /// encoding (FLAME) or a zero text vector (MDM), as the model file's configuration says.
    pub fn uncond(&self) -> Result<&Condition> {
        if let Some(c) = self.uncond.get() {
            return Ok(c);
        }
        let c = match (&self.denoiser, self.config.diffusion.uncond.as_str()) {
            (Denoiser::Mdm(m), "zeros") => Condition::Mdm(vec![0.0; m.cond_dim()]),
            (Denoiser::Flame(_), "zeros") => {
                return Err(bad_file!(
                    "FLAME models need diffusion.uncond `empty_prompt`"
                ))
            }
            _ => self.encode_prompt("")?,
        };
        Ok(self.uncond.get_or_init(|| c))
    }

    /// Checks that a condition was made for this model's denoiser.
    pub fn check_condition(&self, cond: &Condition) -> Result<()> {
        match (&self.denoiser, cond) {
            (Denoiser::Flame(_), Condition::Flame(_)) => Ok(()),
            (Denoiser::Mdm(m), Condition::Mdm(v)) if v.len() == m.cond_dim() => Ok(()),
            (Denoiser::Mdm(m), Condition::Mdm(v)) => Err(invalid_arg!(
                "text vector has {} values, the model expects {}",
                v.len(),
                m.cond_dim()
            )),
            _ => Err(invalid_arg!(
                "the condition was made for another architecture"
            )),
        }
    }

    /// One batched forward pass: `x` is `[batch, frames, motion_dim]`, `out` is
    /// `[batch, frames, output_dim]`, row `b` conditioned on `conds[b]`. `t` is the network's
    /// time input (a diffusion step, or flow time in [0, 1] for Motion Flow Matching).
    pub fn forward(
        &self,
        x: &[f32],
        frames: usize,
        t: f32,
        conds: &[&Condition],
        out: &mut [f32],
        ws: &mut Workspace,
    ) -> Result<()> {
        self.forward_cancellable(x, frames, t, conds, out, ws, &Cancel::never())
    }

    /// [`Model::forward`] that checks `cancel` before every transformer layer.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward_cancellable<'a>(
        &self,
        x: &[f32],
        frames: usize,
        t: f32,
        conds: &[&'a Condition],
        out: &mut [f32],
        ws: &mut Workspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let wrong = || invalid_arg!("a condition was made for another architecture");
        if conds.is_empty() || conds.len() > MAX_BATCH {
            return Err(invalid_arg!(
                "a forward pass takes 1 to {MAX_BATCH} conditions, got {}",
                conds.len()
            ));
        }
        // The per-architecture views of `conds` live on the stack: a step allocates nothing.
        match &self.denoiser {
            Denoiser::Flame(f) => {
                let pick = |c: &'a Condition| match c {
                    Condition::Flame(fc) => Ok(fc),
                    _ => Err(wrong()),
                };
                let mut views = [pick(conds[0])?; MAX_BATCH];
                for (v, c) in views.iter_mut().zip(conds) {
                    *v = pick(c)?;
                }
                f.forward_cancellable(
                    x,
                    frames,
                    t,
                    &views[..conds.len()],
                    out,
                    &mut ws.flame,
                    cancel,
                )
            }
            Denoiser::Mdm(m) => {
                let pick = |c: &'a Condition| match c {
                    Condition::Mdm(v) => Ok(&v[..]),
                    _ => Err(wrong()),
                };
                let mut views = [pick(conds[0])?; MAX_BATCH];
                for (v, c) in views.iter_mut().zip(conds) {
                    *v = pick(c)?;
                }
                m.forward_cancellable(
                    x,
                    frames,
                    t,
                    &views[..conds.len()],
                    out,
                    &mut ws.mdm,
                    cancel,
                )
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
}
