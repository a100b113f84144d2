//! The model configuration carried as JSON in the model file's metadata (`flame.config`).
//!
//! It says what the tensors' shapes cannot: the architecture, head counts, the text encoder's
//! kind, the motion format, the noise schedule and the sampling defaults. The schema (version 1):
//!
//! ```json
//! {
//!  "format_version": 1,
//!  "architecture": "flame",
//!  "denoiser": {"motion_dim": 147, "model_channels": 768, "num_layers": 8, "num_heads": 8,
//!               "dim_feedforward": 2048, "max_motion_length": 471, "activation": "relu",
//!               "layer_norm_eps": 1e-5},
//!  "text_encoder": {"kind": "roberta", "vocab_size": 50265, "hidden_size": 768, "num_layers": 12,
//!                   "num_heads": 12, "intermediate_size": 3072, "max_position_embeddings": 514,
//!                   "type_vocab_size": 1, "layer_norm_eps": 1e-5, "pad_token_id": 1,
//!                   "max_length": 20, "hidden_act": "gelu"},
//!  "motion": {"format": "smpl24_6d", "fps": 20.0},
//!  "diffusion": {"num_timesteps": 1000, "schedule": "cosine", "parameterization": "epsilon",
//!                "variance": "learned_range", "clip_denoised": true, "uncond": "empty_prompt"},
//!  "defaults": {"sampler": "ddpm", "steps": 1000, "guidance": 8.0, "eta": 0.0, "frames": 200}
//! }
//! ```

use serde::Deserialize;

use crate::checkpoint::{ModelFile, CONFIG_KEY};
use crate::error::{bad_file, Result};
use crate::models::mdm::MdmConfig;
use crate::text::ClipConfig;

/// The highest `format_version` this build reads.
pub const FORMAT_VERSION: u32 = 1;

/// The architectures this build runs.
pub const ARCHITECTURES: &[&str] = &["flame", "mdm", "motionfm"];

/// The whole configuration of a model file.
#[derive(Clone, Debug)]
pub struct Config {
    pub format_version: u32,
    /// `flame`, `mdm` or `motionfm`.
    pub architecture: String,
    pub denoiser: DenoiserConfig,
    pub text_encoder: TextConfig,
    pub motion: MotionConfig,
    pub diffusion: DiffusionConfig,
    pub defaults: Defaults,
}

/// The denoiser's sizes, by architecture.
#[derive(Clone, Debug)]
pub enum DenoiserConfig {
    Flame(FlameConfig),
    /// MDM's `trans_enc`, also Motion Flow Matching's network.
    Mdm(MdmConfig),
}

/// The text encoder's configuration, by kind.
#[derive(Clone, Debug)]
pub enum TextConfig {
    /// `bert` or `roberta`.
    Bert(TextEncoderConfig),
    Clip(ClipTextConfig),
}

/// A CLIP text tower and the context length prompts are truncated to (MDM: 22).
#[derive(Clone, Debug, Deserialize)]
pub struct ClipTextConfig {
    #[serde(flatten)]
    pub clip: ClipConfig,
    pub max_length: usize,
}

impl TextConfig {
    /// `bert`, `roberta` or `clip`.
    pub fn kind(&self) -> &str {
        match self {
            TextConfig::Bert(t) => &t.kind,
            TextConfig::Clip(_) => "clip",
        }
    }
}

/// The raw shape of the JSON, before the per-architecture parts are read.
#[derive(Deserialize)]
struct RawConfig {
    format_version: u32,
    architecture: String,
    denoiser: serde_json::Value,
    text_encoder: serde_json::Value,
    motion: MotionConfig,
    diffusion: DiffusionConfig,
    defaults: Defaults,
}

/// FLAME's `Text2MotionTransformer` sizes (REFERENCE 1.1).
#[derive(Clone, Debug, Deserialize)]
pub struct FlameConfig {
    pub motion_dim: usize,
    pub model_channels: usize,
    pub num_layers: usize,
    pub num_heads: usize,
    pub dim_feedforward: usize,
    pub max_motion_length: usize,
    #[serde(default = "relu")]
    pub activation: String,
    #[serde(default = "ln_eps_torch")]
    pub layer_norm_eps: f32,
}

/// A BERT-family text encoder (BERT, MiniLM, RoBERTa).
#[derive(Clone, Debug, Deserialize)]
pub struct TextEncoderConfig {
    /// `bert` or `roberta`.
    pub kind: String,
    pub vocab_size: usize,
    pub hidden_size: usize,
    pub num_layers: usize,
    pub num_heads: usize,
    pub intermediate_size: usize,
    pub max_position_embeddings: usize,
    pub type_vocab_size: usize,
    pub layer_norm_eps: f32,
    pub pad_token_id: u32,
    /// Prompts are padded/truncated to this many tokens (special tokens included).
    pub max_length: usize,
    #[serde(default = "gelu")]
    pub hidden_act: String,
}

/// How the model's features are laid out.
#[derive(Clone, Debug, Deserialize)]
pub struct MotionConfig {
    /// `smpl24_6d` or `humanml263`.
    pub format: String,
    pub fps: f32,
}

/// The diffusion process the denoiser was trained with.
#[derive(Clone, Debug, Deserialize)]
pub struct DiffusionConfig {
    pub num_timesteps: usize,
    pub schedule: String,
    pub parameterization: String,
    pub variance: String,
    pub clip_denoised: bool,
    /// The unconditional input of classifier-free guidance: `empty_prompt` (FLAME) or `zeros`.
    #[serde(default = "empty_prompt")]
    pub uncond: String,
}

/// Sampling defaults a session starts from.
#[derive(Clone, Debug, Deserialize)]
pub struct Defaults {
    pub sampler: String,
    pub steps: usize,
    pub guidance: f32,
    #[serde(default)]
    pub eta: f32,
    pub frames: usize,
}

fn relu() -> String {
    "relu".into()
}
fn gelu() -> String {
    "gelu".into()
}
fn empty_prompt() -> String {
    "empty_prompt".into()
}
fn ln_eps_torch() -> f32 {
    1e-5
}

impl Config {
    /// Reads and checks the configuration stored in a model file.
    pub fn from_file(file: &ModelFile) -> Result<Config> {
        let text = file.metadata(CONFIG_KEY).ok_or_else(|| {
            bad_file!(
                "no `{CONFIG_KEY}` metadata: not a libflame model file (convert it with tools/convert.py)"
            )
        })?;
        Config::from_json(text)
    }

    /// Parses and checks a configuration from JSON text.
    pub fn from_json(text: &str) -> Result<Config> {
        // Look at version and architecture first so an unknown model says so, rather than
        // complaining about whichever field its schema lacks.
        let v: serde_json::Value = serde_json::from_str(text)
            .map_err(|e| bad_file!("`{CONFIG_KEY}` is not valid JSON: {e}"))?;
        let version = v.get("format_version").and_then(|x| x.as_u64());
        match version {
            Some(n) if n as u32 <= FORMAT_VERSION && n > 0 => {}
            Some(n) => {
                return Err(bad_file!(
                    "format_version {n} is not supported (this build reads up to {FORMAT_VERSION})"
                ))
            }
            None => return Err(bad_file!("`{CONFIG_KEY}` has no integer `format_version`")),
        }
        let arch = v
            .get("architecture")
            .and_then(|x| x.as_str())
            .unwrap_or("")
            .to_string();
        if !ARCHITECTURES.contains(&arch.as_str()) {
            return Err(bad_file!(
                "unknown architecture `{arch}` (supported: {})",
                ARCHITECTURES.join(", ")
            ));
        }
        let schema = |e: serde_json::Error| {
            bad_file!("`{CONFIG_KEY}` does not match the {arch} schema: {e}")
        };
        let raw: RawConfig = serde_json::from_value(v).map_err(schema)?;
        let denoiser = match arch.as_str() {
            "flame" => DenoiserConfig::Flame(serde_json::from_value(raw.denoiser).map_err(schema)?),
            _ => DenoiserConfig::Mdm(serde_json::from_value(raw.denoiser).map_err(schema)?),
        };
        let text_encoder = match raw.text_encoder.get("kind").and_then(|k| k.as_str()) {
            Some("clip") => {
                TextConfig::Clip(serde_json::from_value(raw.text_encoder).map_err(schema)?)
            }
            _ => TextConfig::Bert(serde_json::from_value(raw.text_encoder).map_err(schema)?),
        };
        let cfg = Config {
            format_version: raw.format_version,
            architecture: raw.architecture,
            denoiser,
            text_encoder,
            motion: raw.motion,
            diffusion: raw.diffusion,
            defaults: raw.defaults,
        };
        cfg.check()?;
        Ok(cfg)
    }

    /// Checks the values that shapes alone would not catch.
    fn check(&self) -> Result<()> {
        let positive = |name: &str, value: usize| -> Result<()> {
            if value == 0 {
                return Err(bad_file!("config `{name}` must be positive"));
            }
            Ok(())
        };
        let divisible = |name: &str, width: usize, heads: usize| -> Result<()> {
            if !width.is_multiple_of(heads) || !width.is_multiple_of(2) {
                return Err(bad_file!(
                    "config {name} {width} is not even or not divisible by its {heads} heads"
                ));
            }
            Ok(())
        };
        match &self.denoiser {
            DenoiserConfig::Flame(d) => {
                for (name, value) in [
                    ("denoiser.motion_dim", d.motion_dim),
                    ("denoiser.model_channels", d.model_channels),
                    ("denoiser.num_layers", d.num_layers),
                    ("denoiser.num_heads", d.num_heads),
                    ("denoiser.dim_feedforward", d.dim_feedforward),
                    ("denoiser.max_motion_length", d.max_motion_length),
                ] {
                    positive(name, value)?;
                }
                divisible("denoiser.model_channels", d.model_channels, d.num_heads)?;
                if d.activation != "relu" && d.activation != "gelu" {
                    return Err(bad_file!("unknown denoiser.activation `{}`", d.activation));
                }
            }
            DenoiserConfig::Mdm(d) => {
                for (name, value) in [
                    ("denoiser.njoints", d.njoints),
                    ("denoiser.latent_dim", d.latent_dim),
                    ("denoiser.layers", d.layers),
                    ("denoiser.heads", d.heads),
                    ("denoiser.ff_size", d.ff_size),
                    ("denoiser.clip_dim", d.clip_dim),
                    ("denoiser.max_len", d.max_len),
                ] {
                    positive(name, value)?;
                }
                divisible("denoiser.latent_dim", d.latent_dim, d.heads)?;
            }
        }
        match &self.text_encoder {
            TextConfig::Bert(t) => {
                positive("text_encoder.hidden_size", t.hidden_size)?;
                positive("text_encoder.num_heads", t.num_heads)?;
                positive("text_encoder.max_length", t.max_length)?;
                if t.hidden_size % t.num_heads != 0 {
                    return Err(bad_file!(
                        "config text_encoder.hidden_size {} is not divisible by num_heads {}",
                        t.hidden_size,
                        t.num_heads
                    ));
                }
                if !matches!(t.kind.as_str(), "bert" | "roberta") {
                    return Err(bad_file!(
                        "unknown text_encoder.kind `{}` (supported: bert, roberta, clip)",
                        t.kind
                    ));
                }
            }
            TextConfig::Clip(c) => positive("text_encoder.max_length", c.max_length)?,
        }
        positive("diffusion.num_timesteps", self.diffusion.num_timesteps)?;
        if self.motion.fps.is_nan() || self.motion.fps <= 0.0 {
            return Err(bad_file!("config motion.fps must be positive"));
        }
        if !matches!(self.diffusion.uncond.as_str(), "empty_prompt" | "zeros") {
            return Err(bad_file!(
                "unknown diffusion.uncond `{}`",
                self.diffusion.uncond
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    pub(crate) const EXAMPLE: &str = r#"{
     "format_version": 1, "architecture": "flame",
     "denoiser": {"motion_dim": 147, "model_channels": 64, "num_layers": 2, "num_heads": 4,
                  "dim_feedforward": 128, "max_motion_length": 471, "activation": "relu", "layer_norm_eps": 1e-5},
     "text_encoder": {"kind": "roberta", "vocab_size": 1000, "hidden_size": 48, "num_layers": 2, "num_heads": 4,
                      "intermediate_size": 96, "max_position_embeddings": 64, "type_vocab_size": 1,
                      "layer_norm_eps": 1e-5, "pad_token_id": 1, "max_length": 20, "hidden_act": "gelu"},
     "motion": {"format": "smpl24_6d", "fps": 20.0},
     "diffusion": {"num_timesteps": 1000, "schedule": "cosine", "parameterization": "epsilon",
                   "variance": "learned_range", "clip_denoised": true, "uncond": "empty_prompt"},
     "defaults": {"sampler": "ddpm", "steps": 1000, "guidance": 8.0, "eta": 0.0, "frames": 200}}"#;

    #[test]
    fn parses_the_documented_schema() {
        let c = Config::from_json(EXAMPLE).unwrap();
        let DenoiserConfig::Flame(d) = &c.denoiser else {
            panic!("a FLAME config")
        };
        assert_eq!(d.model_channels, 64);
        assert_eq!(c.text_encoder.kind(), "roberta");
        assert_eq!(c.defaults.guidance, 8.0);
    }

    #[test]
    fn clear_errors() {
        let e = Config::from_json("{not json").unwrap_err().to_string();
        assert!(e.contains("is not valid JSON"), "{e}");
        let e = Config::from_json(&EXAMPLE.replace("\"flame\"", "\"unet\""))
            .unwrap_err()
            .to_string();
        assert_eq!(
            e,
            "bad model file: unknown architecture `unet` (supported: flame, mdm, motionfm)"
        );
        let e =
            Config::from_json(&EXAMPLE.replace("\"format_version\": 1", "\"format_version\": 9"))
                .unwrap_err()
                .to_string();
        assert!(e.contains("format_version 9 is not supported"), "{e}");
        let e = Config::from_json(&EXAMPLE.replace("\"num_heads\": 4,\n", "\"num_heads\": 5,\n"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("not divisible"), "{e}");
        // ("not even or not divisible" for the denoiser, "not divisible" for the text encoder)
        let e = Config::from_json(&EXAMPLE.replace("\"max_motion_length\": 471,", ""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing field `max_motion_length`"), "{e}");
    }
}
