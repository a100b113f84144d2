//! Denoiser networks, one file per architecture named after its paper, and [`Model`]: a loaded
//! model file (configuration, text encoder, denoiser), immutable and shared by any number of
//! sessions and threads.

pub mod flame;
pub mod mdm;

use std::path::Path;
use std::sync::OnceLock;

use crate::checkpoint::{ModelFile, StoredDtype, Tensor, TOKENIZER_KEY};
use crate::config::Config;
use crate::error::{bad_file, Result};
use crate::motion::{Format, Normalization, ReadOptions};
use crate::text::TextEncoder;

pub use flame::{FlameCondition, FlameDenoiser, Workspace};

/// Prefix of the text encoder's tensors inside a libflame file.
pub const TEXT_PREFIX: &str = "text.";

/// The denoiser of a model, by architecture.
pub enum Denoiser {
    Flame(FlameDenoiser),
}

/// What a denoiser is conditioned on, derived from a prompt once and reused at every step.
#[derive(Clone, Debug)]
pub enum Condition {
    Flame(FlameCondition),
}

/// A loaded model: read-only after loading, `Send + Sync`.
pub struct Model {
    config: Config,
    text: TextEncoder,
    denoiser: Denoiser,
    dtype: Option<StoredDtype>,
    format: Format,
    /// `motion.mean` / `motion.std`: what the denoiser's features are normalised with, if anything.
    stats: Option<(Tensor, Tensor)>,
    /// The unconditional input of classifier-free guidance, computed once per model.
    uncond: OnceLock<Condition>,
}

impl Model {
    /// Loads a libflame model file by memory-mapping it.
    pub fn load(path: impl AsRef<Path>) -> Result<Model> {
        Model::from_file(ModelFile::open(path.as_ref())?)
    }

    /// Loads a model from the bytes of a model file (copied).
    pub fn from_bytes(bytes: &[u8]) -> Result<Model> {
        Model::from_file(ModelFile::from_bytes(bytes)?)
    }

    /// Builds the model from an opened file, validating every tensor against the configuration.
    pub fn from_file(file: ModelFile) -> Result<Model> {
        let config = Config::from_file(&file)?;
        let tokenizer = file
            .metadata(TOKENIZER_KEY)
            .ok_or_else(|| bad_file!("no `{TOKENIZER_KEY}` metadata (the tokenizer.json text)"))?;
        let text = TextEncoder::load(&file, TEXT_PREFIX, &config.text_encoder, tokenizer)?;
        let denoiser = match config.architecture.as_str() {
            "flame" => Denoiser::Flame(FlameDenoiser::load(
                &file,
                &config.denoiser,
                text.hidden_size(),
            )?),
            other => return Err(bad_file!("unknown architecture `{other}`")),
        };
        let format: Format = config
            .motion
            .format
            .parse()
            .map_err(|_| bad_file!("unknown motion.format `{}`", config.motion.format))?;
        let dim = match &denoiser {
            Denoiser::Flame(f) => f.motion_dim(),
        };
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
            format,
            stats,
            uncond: OnceLock::new(),
        })
    }

    pub fn config(&self) -> &Config {
        &self.config
    }

    pub fn text_encoder(&self) -> &TextEncoder {
        &self.text
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

    /// Feature channels per frame.
    pub fn motion_dim(&self) -> usize {
        match &self.denoiser {
            Denoiser::Flame(f) => f.motion_dim(),
        }
    }

    /// The largest frame count a session may ask for.
    pub fn max_frames(&self) -> usize {
        match &self.denoiser {
            Denoiser::Flame(f) => f.max_frames(),
        }
    }

    /// Encodes a prompt into the denoiser's conditioning.
    pub fn encode_prompt(&self, prompt: &str) -> Result<Condition> {
        let out = self.text.encode(prompt)?;
        match &self.denoiser {
            Denoiser::Flame(f) => Ok(Condition::Flame(f.condition(&out)?)),
        }
    }

    /// The unconditional input for guidance (FLAME: the empty prompt), encoded once per model.
    pub fn uncond(&self) -> Result<&Condition> {
        if let Some(c) = self.uncond.get() {
            return Ok(c);
        }
        let c = self.encode_prompt("")?;
        Ok(self.uncond.get_or_init(|| c))
    }

    /// One batched forward pass: `x` is `[batch, frames, motion_dim]`, `out` is
    /// `[batch, frames, output_dim]`, row `b` conditioned on `conds[b]`.
    pub fn forward(
        &self,
        x: &[f32],
        frames: usize,
        t: f32,
        conds: &[&Condition],
        out: &mut [f32],
        ws: &mut Workspace,
    ) -> Result<()> {
        match &self.denoiser {
            Denoiser::Flame(f) => {
                let conds: Vec<&FlameCondition> = conds
                    .iter()
                    .map(|c| match c {
                        Condition::Flame(fc) => fc,
                    })
                    .collect();
                f.forward(x, frames, t, &conds, out, ws)
            }
        }
    }

    /// Output channels per frame of the denoiser.
    pub fn output_dim(&self) -> usize {
        match &self.denoiser {
            Denoiser::Flame(f) => f.output_dim(),
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
