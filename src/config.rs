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
//!
//! Each family reads its own sections (`denoiser`, and MoLA's and MLD's `vae`) and checks them
//! itself ([`crate::models::FamilyConfig`]); the rows below for `flame`, `mdm` and the latent
//! families are those checks. MoLA and MLD schemas: docs/model-files-latent.md.
//!
//! A model sampled with diffusers' `DDIMScheduler` (MoLA, MLD) adds its spacing to `diffusion`,
//! e.g. `"spacing": "trailing", "set_alpha_to_one": false` (MoLA) or `"spacing": "leading",
//! "steps_offset": 1, "set_alpha_to_one": false` (MLD).
//!
//! MDM and Motion Flow Matching files (`"architecture": "mdm"` / `"motionfm"`) have the
//! denoiser `{"njoints", "latent_dim", "layers", "heads", "ff_size", "activation", "clip_dim",
//! "max_len"}` and a CLIP text encoder `{"kind": "clip", "vocab_size", "width", "layers",
//! "heads", "intermediate_size", "context_length", "projection_dim", "layer_norm_eps",
//! "max_length"}`.
//!
//! # Validation
//!
//! [`Config::from_file`] checks the whole configuration before anything is allocated or
//! computed from it, so a file that loads can always start a session; a violation is
//! `BadModelFile` naming the field. Every size lies within its bound and matches the tensors
//! it describes in the safetensors header (a layer count `n`: tensors of layer `n − 1` present,
//! of layer `n` absent); every name is one the runtime accepts. Bounds (W = [`MAX_WIDTH`]
//! = 65536, F = [`MAX_FEEDFORWARD`] = 262144, L = [`MAX_LAYERS`] = 1024, V = [`MAX_VOCAB`] =
//! 2^24, P = [`MAX_TEXT_POSITIONS`] = 4096, M = [`MAX_MOTION_POSITIONS`] = 100000):
//!
//! | field | bound | checked against |
//! |---|---|---|
//! | `format_version` | 1 | |
//! | `architecture` | `flame`, `mdm`, `motionfm`, `mola`, `mld`, `motionlcm`, `finemogen`, `omg` | the text encoder's kind (flame: bert/roberta; motionlcm: t5; others: clip) |
//! | flame `denoiser.motion_dim` | 1..=W, = the format's features | `input_projection.weight` `[C, motion_dim]`, `last_projection.weight` `[2·motion_dim, C]` |
//! | flame `denoiser.model_channels` (C) | 2..=W, even | `input_projection.weight` |
//! | flame `denoiser.num_layers` | 1..=L | `tf_decoder.layers.{n−1}.*` present, `.{n}.*` absent |
//! | flame `denoiser.num_heads` | 1..=C, divides C | |
//! | flame `denoiser.dim_feedforward` | 1..=F | `tf_decoder.layers.0.linear1.weight` `[ff, C]` |
//! | flame `denoiser.max_motion_length` | 2..=M, (it + 3) × C ≤ 2^26 | `motion_length_emb.weight` `[max_motion_length, C]` |
//! | flame `denoiser.activation` | `relu`, `gelu` | |
//! | every `layer_norm_eps` | finite, in (0, 1] | |
//! | mdm `denoiser.njoints` | 1..=W, = the format's features | `input_process.poseEmbedding.weight` `[latent_dim, njoints]` |
//! | mdm `denoiser.latent_dim` | 2..=W, even | `embed_timestep.time_embed.0.weight` `[latent_dim, latent_dim]` |
//! | mdm `denoiser.layers` | 1..=L | `seqTransEncoder.layers.{n−1}.*` present, `.{n}.*` absent |
//! | mdm `denoiser.heads` | 1..=latent_dim, divides it | |
//! | mdm `denoiser.ff_size` | 1..=F | `seqTransEncoder.layers.0.linear1.weight` |
//! | mdm `denoiser.clip_dim` | 1..=W, = `text_encoder.projection_dim` | `embed_text.weight` `[latent_dim, clip_dim]` |
//! | mdm `denoiser.max_len` | 2..=M, × latent_dim ≤ 2^26, ≥ num_timesteps (mdm) or ≥ 1001 (motionfm) | |
//! | mdm `denoiser.activation` | `gelu`, `relu` | |
//! | `text_encoder.kind` | `bert`, `roberta`, `clip`, `t5` | |
//! | bert `text_encoder.vocab_size` | 1..=V | `text.embeddings.word_embeddings.weight` `[vocab, hidden]` |
//! | bert `text_encoder.hidden_size` | 1..=W | same |
//! | bert `text_encoder.num_layers` | 1..=L | `text.encoder.layer.{n−1}.*` present, `.{n}.*` absent |
//! | bert `text_encoder.num_heads` | 1..=hidden, divides it | |
//! | bert `text_encoder.intermediate_size` | 1..=F | `text.encoder.layer.0.intermediate.dense.weight` |
//! | bert `text_encoder.max_position_embeddings` | 1..=P | `text.embeddings.position_embeddings.weight` |
//! | bert `text_encoder.type_vocab_size` | 1..=V | `text.embeddings.token_type_embeddings.weight` |
//! | bert `text_encoder.pad_token_id` | < vocab_size | the tokenizer's ids |
//! | bert `text_encoder.max_length` | 1..=P, + RoBERTa's pad offset ≤ max_position_embeddings, > the tokenizer's special tokens | |
//! | bert `text_encoder.hidden_act` | `gelu` | |
//! | clip `text_encoder.vocab_size` | 1..=V | `text.text_model.embeddings.token_embedding.weight` `[vocab, width]` |
//! | clip `text_encoder.width` | 1..=W | same |
//! | clip `text_encoder.layers` | 1..=L | `text.text_model.encoder.layers.{n−1}.*` present, `.{n}.*` absent |
//! | clip `text_encoder.heads` | 1..=width, divides it | |
//! | clip `text_encoder.intermediate_size` | 1..=F (absent: 4 × width) | `text.text_model.encoder.layers.0.mlp.fc1.weight` |
//! | clip `text_encoder.context_length` | 2..=P | `text.text_model.embeddings.position_embedding.weight` |
//! | clip `text_encoder.projection_dim` | 1..=W | `text.text_projection.weight` `[projection_dim, width]` |
//! | clip `text_encoder.max_length` | 2..=context_length | |
//! | t5 `text_encoder.max_length` | 2..=4096 | sizes from `text.shared.weight`, `text.encoder.block.*`, `text.dense.weight` |
//! | t5 `text_encoder.relative_attention_max_distance` | 1..=P (default 128), more than the exact buckets | `text.encoder.block.0.layer.0.SelfAttention.relative_attention_bias.weight` |
//! | `motion.format` | `smpl24_6d`, `humanml263` | the denoiser's motion width |
//! | `motion.fps` | finite, in (0, 1000] | |
//! | `diffusion.num_timesteps` | 1..=100000; the schedule's betas in (0, 1) | |
//! | `diffusion.schedule` | `cosine`, `squaredcos_cap_v2`, `linear`, `scaled_linear` | |
//! | `diffusion.parameterization` | `epsilon`/`eps`, `x0`/`sample`/`start_x`, `v`/`v_prediction`; `velocity`/`flow` for (and only for) motionfm | |
//! | `diffusion.variance` | `learned_range` (flame only), `fixed_small`, `fixed_large` | |
//! | `diffusion.uncond` | `empty_prompt`, `zeros` (not flame); `null_text` (finemogen only), `backbone` (omg only) | |
//! | `diffusion.spacing` | `respace` (default), `leading`, `trailing`, `lcm` (motionlcm); diffusion models only | |
//! | `diffusion.lcm_timesteps` | `grid` (with `original_inference_steps` 1..=num_timesteps) or `motionlcm_v2` (num_timesteps 1000); `lcm` only | |
//! | `diffusion.timestep_scaling` | finite, in (0, 10⁶] (default 10); `lcm` only | |
//! | `diffusion.steps_offset` | 0 (default) ..num_timesteps; `leading` and `trailing` only; `leading`: (defaults.steps − 1)·(num_timesteps div steps) + offset < num_timesteps | |
//! | `diffusion.set_alpha_to_one` | `true` (default); `false` needs `leading` or `trailing` | |
//! | `defaults.sampler` | `ddpm`, `ddim` (diffusion); `euler`, `heun`, `midpoint` (motionfm); `lcm` (spacing `lcm`) | |
//! | `defaults.steps` | 1..=num_timesteps (diffusion), 1..=10000 (motionfm); a count the spacing can take | |
//! | `defaults.guidance` | finite, in [0, 100] (also a session's) | |
//! | `defaults.guidance_by_steps` | step count → guidance, each a count the `lcm` rule takes and a guidance in [0, 100]; `lcm` only | |
//! | `defaults.eta` | finite, in [0, 1] | |
//! | `defaults.frames` | 1..=max frames (max_motion_length − 1, max_len − 1) | |
//!
//! The schedule, parameterization, variance and spacing names ignore case and surrounding spaces, as the
//! sampler does. The per-part checks ([`FlameConfig::validate`], [`MdmConfig::validate`],
//! [`TextEncoderConfig::validate`], [`ClipConfig::validate`]) are also what each loader runs
//! first when used on its own.
//!
//! [`Config::from_file`]: crate::config::Config::from_file
//! [`MAX_WIDTH`]: crate::config::MAX_WIDTH
//! [`MAX_FEEDFORWARD`]: crate::config::MAX_FEEDFORWARD
//! [`MAX_LAYERS`]: crate::config::MAX_LAYERS
//! [`MAX_VOCAB`]: crate::config::MAX_VOCAB
//! [`MAX_TEXT_POSITIONS`]: crate::config::MAX_TEXT_POSITIONS
//! [`MAX_MOTION_POSITIONS`]: crate::config::MAX_MOTION_POSITIONS
//! [`FlameConfig::validate`]: crate::models::FlameConfig::validate
//! [`MdmConfig::validate`]: crate::models::MdmConfig::validate
//! [`TextEncoderConfig::validate`]: crate::config::TextEncoderConfig::validate
//! [`ClipConfig::validate`]: crate::text::ClipConfig::validate

pub(crate) mod validate;

use serde::Deserialize;

use crate::checkpoint::{ModelFile, CONFIG_KEY};
use crate::error::{bad_file, Result};
use crate::models::{Family, FamilyConfig};
use crate::text::ClipConfig;

/// Most layers of any stack (denoiser, text encoder).
pub const MAX_LAYERS: usize = 1024;
/// Most channels of a width: model and hidden sizes, motion and text-vector widths.
pub const MAX_WIDTH: usize = 65536;
/// Most channels of a feed-forward (MLP) layer.
pub const MAX_FEEDFORWARD: usize = 4 * MAX_WIDTH;
/// Most entries of a token (or token-type) vocabulary.
pub const MAX_VOCAB: usize = 1 << 24;
/// Most text positions: position tables, context and prompt lengths.
pub const MAX_TEXT_POSITIONS: usize = 4096;
/// Most rows of a denoiser's motion-position table (`max_motion_length`, `max_len`).
pub const MAX_MOTION_POSITIONS: usize = 100_000;
/// Most values of a positional table computed at load (rows × width; 256 MiB of f32).
pub const MAX_TABLE_VALUES: usize = 1 << 26;
/// Most training timesteps of a diffusion schedule.
pub const MAX_TIMESTEPS: usize = 100_000;
/// Most ODE steps of a flow-matching sampler.
pub const MAX_FLOW_STEPS: usize = 10_000;
/// The largest classifier-free guidance scale (in a file or a session).
pub const MAX_GUIDANCE: f32 = 100.0;
/// The largest frame rate.
pub const MAX_FPS: f32 = 1000.0;

/// Whether `g` is a guidance scale libflame runs: finite, in `[0, MAX_GUIDANCE]`.
pub fn guidance_in_range(g: f32) -> bool {
    g.is_finite() && (0.0..=MAX_GUIDANCE).contains(&g)
}

/// The highest `format_version` this build reads.
pub const FORMAT_VERSION: u32 = 1;

/// The whole configuration of a model file.
#[derive(Clone, Debug)]
pub struct Config {
    /// The schema version the file was written with: 1..=[`FORMAT_VERSION`].
    pub format_version: u32,
    /// The model family's name for this file (see [`crate::models::FAMILIES`]).
    pub architecture: String,
    /// The family's own sections (`denoiser`, and any other it reads).
    pub denoiser: std::sync::Arc<dyn FamilyConfig>,
    /// The prompt encoder: BERT or RoBERTa for FLAME, CLIP for the other families.
    pub text_encoder: TextConfig,
    /// The per-frame feature layout and frame rate of the motion the model produces.
    pub motion: MotionConfig,
    /// The noise schedule and prediction target the denoiser was trained with.
    pub diffusion: DiffusionConfig,
    /// The sampling settings a session uses for whatever its parameters leave unset.
    pub defaults: Defaults,
}

/// The text encoder's configuration, by kind.
#[derive(Clone, Debug)]
pub enum TextConfig {
    /// `bert` or `roberta`.
    Bert(TextEncoderConfig),
    /// `clip`: a CLIP text tower (MDM, Motion Flow Matching and the later families).
    Clip(ClipTextConfig),
    /// `t5`: a T5 v1.0 encoder with sentence-transformers' head (MotionLCM's sentence-t5).
    T5(T5TextConfig),
}

/// A sentence-t5 text encoder: its sizes come from the tensors' shapes
/// ([`crate::text::t5::T5Encoder::load`]); the JSON says what shapes cannot.
#[derive(Clone, Debug, Deserialize)]
pub struct T5TextConfig {
    /// Tokens a prompt keeps, the appended `</s>` included (sentence-t5's `max_seq_length`:
    /// 256); 2..=[`crate::text::t5::T5_MAX_TOKENS`].
    pub max_length: usize,
    /// T5's `relative_attention_max_distance` (128 in every released T5).
    #[serde(default = "t5_max_distance")]
    pub relative_attention_max_distance: usize,
}

fn t5_max_distance() -> usize {
    crate::text::t5::T5_MAX_DISTANCE
}

/// A CLIP text tower and the context length prompts are truncated to (MDM: 22).
#[derive(Clone, Debug, Deserialize)]
pub struct ClipTextConfig {
    /// The tower's sizes (the JSON's other `text_encoder` fields).
    #[serde(flatten)]
    pub clip: ClipConfig,
    /// Tokens a prompt keeps, start and end tokens included (2..=`context_length`); longer
    /// prompts are cut and end on the end token, as MDM's `encode_text` does
    /// (docs/official/mdm.md#clip-prompt-encoding).
    pub max_length: usize,
}

impl TextConfig {
    /// `bert`, `roberta`, `clip` or `t5`.
    pub fn kind(&self) -> &str {
        match self {
            TextConfig::Bert(t) => &t.kind,
            TextConfig::Clip(_) => "clip",
            TextConfig::T5(_) => "t5",
        }
    }
}

/// The raw shape of the JSON, before the per-architecture parts are read.
#[derive(Deserialize)]
struct RawConfig {
    format_version: u32,
    architecture: String,
    text_encoder: serde_json::Value,
    motion: MotionConfig,
    diffusion: DiffusionConfig,
    defaults: Defaults,
}

/// A BERT-family text encoder (BERT, MiniLM, RoBERTa).
#[derive(Clone, Debug, Deserialize)]
pub struct TextEncoderConfig {
    /// `bert` or `roberta`.
    pub kind: String,
    /// Rows of the token-embedding table (RoBERTa-base: 50265).
    pub vocab_size: usize,
    /// Width of every token's hidden state (base models: 768).
    pub hidden_size: usize,
    /// Transformer layers (base models: 12).
    pub num_layers: usize,
    /// Attention heads per layer; divides `hidden_size`.
    pub num_heads: usize,
    /// Width of each layer's feed-forward block (base models: 3072).
    pub intermediate_size: usize,
    /// Rows of the position-embedding table. RoBERTa counts positions from `pad_token_id` + 1
    /// (docs/official/text-encoders.md#position-ids), so 514 rows hold 512 tokens.
    pub max_position_embeddings: usize,
    /// Rows of the token-type table (RoBERTa: 1, BERT: 2); only type 0 is used.
    pub type_vocab_size: usize,
    /// The epsilon added to the variance in every LayerNorm (RoBERTa: 1e-5, BERT: 1e-12).
    pub layer_norm_eps: f32,
    /// The padding token's id (RoBERTa: 1, BERT: 0); below `vocab_size`.
    pub pad_token_id: u32,
    /// Prompts are padded/truncated to this many tokens (special tokens included).
    pub max_length: usize,
    /// The feed-forward activation; only `gelu` (exact, erf-based) is accepted, the default.
    #[serde(default = "gelu")]
    pub hidden_act: String,
}

/// How the model's features are laid out.
#[derive(Clone, Debug, Deserialize)]
pub struct MotionConfig {
    /// `smpl24_6d` or `humanml263`.
    pub format: String,
    /// Frames per second of the generated motion, in (0, 1000] (FLAME, HumanML3D models: 20);
    /// a frame count divided by it gives the clip's duration.
    pub fps: f32,
}

/// The diffusion process the denoiser was trained with.
#[derive(Clone, Debug, Deserialize)]
pub struct DiffusionConfig {
    /// Training timesteps T (FLAME: 1000); sampling steps are picked among them.
    /// 1..=[`MAX_TIMESTEPS`].
    pub num_timesteps: usize,
    /// The beta schedule: `cosine` (guided-diffusion's, docs/official/flame.md#noise-schedule),
    /// `squaredcos_cap_v2` (diffusers' name for it), `linear` or `scaled_linear`.
    pub schedule: String,
    /// What the network predicts: `epsilon` (the noise), `x0` (the clean motion), `v`, or
    /// `velocity` for a flow-matching model.
    pub parameterization: String,
    /// The variance of each DDPM step: `learned_range` (the network outputs it in a second
    /// half of its channels; FLAME), `fixed_small` (the posterior variance) or `fixed_large`
    /// (β_t).
    pub variance: String,
    /// Whether the clean-motion estimate is clamped to [−1, 1] at every step
    /// (docs/official/flame.md#ddpm-step); a session's `clip_denoised` overrides it.
    pub clip_denoised: bool,
    /// The unconditional input of classifier-free guidance: `empty_prompt` (FLAME) or `zeros`.
    #[serde(default = "empty_prompt")]
    pub uncond: String,
    /// How sampling steps are picked from the training steps: `respace` (guided-diffusion's
    /// respaced process, the default), `leading` or `trailing` (diffusers' `DDIMScheduler`).
    #[serde(default = "respace")]
    pub spacing: String,
    /// diffusers' `steps_offset`, added to every `leading` timestep (MLD: 1); `trailing`
    /// ignores it, as diffusers does.
    #[serde(default)]
    pub steps_offset: usize,
    /// diffusers' `set_alpha_to_one`: the last step goes to ᾱ = 1 (true) or to the training
    /// table's ᾱ_0 (false: MoLA, MLD).
    #[serde(default = "yes")]
    pub set_alpha_to_one: bool,
    /// `spacing` `lcm` only: the latent consistency sampler's timestep rule, `grid` (diffusers'
    /// `LCMScheduler` grid from `original_inference_steps`: MotionLCM v1) or `motionlcm_v2`
    /// (MotionLCM v2's table of 1, 2 and 4 steps).
    #[serde(default)]
    pub lcm_timesteps: Option<String>,
    /// `spacing` `lcm`, `grid` rule: the distillation's step count the grid is taken from
    /// (MotionLCM v1: 50), 1..=num_timesteps.
    #[serde(default)]
    pub original_inference_steps: Option<usize>,
    /// `spacing` `lcm`: diffusers' `timestep_scaling` of the boundary condition (10).
    #[serde(default)]
    pub timestep_scaling: Option<f32>,
}

/// Sampling defaults a session starts from.
#[derive(Clone, Debug, Deserialize)]
pub struct Defaults {
    /// `ddpm` or `ddim` for diffusion models; `euler`, `heun` or `midpoint` for flow matching.
    pub sampler: String,
    /// Sampling steps: 1..=`num_timesteps` for diffusion (fewer than T skip training steps, as
    /// `diffusion.spacing` picks them), 1..=[`MAX_FLOW_STEPS`] ODE steps for flow matching.
    pub steps: usize,
    /// Classifier-free guidance scale in [0, [`MAX_GUIDANCE`]]: 0 = unconditional, 1 = the
    /// prompt alone, above 1 strengthens the prompt (FLAME: 8, MDM: 2.5).
    pub guidance: f32,
    /// DDIM's η in [0, 1]: the share of fresh noise each DDIM step adds (0, the default, is
    /// deterministic); ignored by the other samplers.
    #[serde(default)]
    pub eta: f32,
    /// Frames generated when a session does not say, at most the model's maximum
    /// (`max_motion_length` − 1 or `max_len` − 1).
    pub frames: usize,
    /// The respacing string sessions use when they ask for neither a step count nor a
    /// respacing (FineMoGen: `"15,15,8,6,6"`); models with `diffusion.spacing` `respace` only.
    #[serde(default)]
    pub respacing: Option<String>,
    /// The guidance scale per step count, where the model's authors tuned one for each
    /// (MotionLCM v2's "dynamic" scale: 1 → 8.0, 2 → 12.5, 4 → 13.5); a session that sets no
    /// guidance takes its step count's entry, else `guidance`.
    #[serde(default)]
    pub guidance_by_steps: Option<std::collections::BTreeMap<String, f32>>,
}

impl Defaults {
    /// The guidance a session of `steps` steps uses when it sets none.
    pub fn guidance_for(&self, steps: usize) -> f32 {
        self.guidance_by_steps
            .as_ref()
            .and_then(|m| m.get(&steps.to_string()))
            .copied()
            .unwrap_or(self.guidance)
    }
}

fn gelu() -> String {
    "gelu".into()
}
fn empty_prompt() -> String {
    "empty_prompt".into()
}
fn respace() -> String {
    "respace".into()
}
fn yes() -> bool {
    true
}

/// Reads section `name` of a family's configuration (`v` is the whole JSON) into `T`, or an
/// error naming the family's schema.
pub(crate) fn section<T: serde::de::DeserializeOwned>(
    v: &serde_json::Value,
    architecture: &str,
    name: &str,
) -> Result<T> {
    let part = v.get(name).cloned().unwrap_or(serde_json::Value::Null);
    serde_json::from_value(part).map_err(|e| {
        bad_file!("`{CONFIG_KEY}` does not match the {architecture} schema: {name}: {e}")
    })
}

impl Config {
    /// Reads the configuration stored in a model file and validates all of it, against the
    /// bounds and against the file's tensor shapes ([`Config::validate`]).
    pub fn from_file(file: &ModelFile) -> Result<Config> {
        let text = file.metadata(CONFIG_KEY).ok_or_else(|| {
            bad_file!(
                "no `{CONFIG_KEY}` metadata: not a libflame model file (convert it with tools/convert.py)"
            )
        })?;
        let cfg = Config::from_json(text)?;
        cfg.validate(file)?;
        Ok(cfg)
    }

    /// Parses a configuration from JSON text and checks everything that needs no tensor
    /// (bounds, names, the fields against each other).
    pub fn from_json(text: &str) -> Result<Config> {
        // Look at version and architecture first so an unknown model says so, rather than
        // complaining about whichever field its schema lacks.
        let v: serde_json::Value = serde_json::from_str(text)
            .map_err(|e| bad_file!("`{CONFIG_KEY}` is not valid JSON: {e}"))?;
        let version = v.get("format_version").and_then(|x| x.as_u64());
        match version {
            Some(n) if n <= u64::from(FORMAT_VERSION) && n > 0 => {}
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
        let Some(family) = Family::find(&arch) else {
            return Err(bad_file!(
                "unknown architecture `{arch}` (supported: {})",
                Family::all_architectures().join(", ")
            ));
        };
        let schema = |e: serde_json::Error| {
            bad_file!("`{CONFIG_KEY}` does not match the {arch} schema: {e}")
        };
        let denoiser = (family.parse)(&arch, &v)?;
        let raw: RawConfig = serde_json::from_value(v).map_err(schema)?;
        let text_encoder = match raw.text_encoder.get("kind").and_then(|k| k.as_str()) {
            Some("clip") => {
                TextConfig::Clip(serde_json::from_value(raw.text_encoder).map_err(schema)?)
            }
            Some("bert" | "roberta") => {
                TextConfig::Bert(serde_json::from_value(raw.text_encoder).map_err(schema)?)
            }
            Some("t5") => TextConfig::T5(serde_json::from_value(raw.text_encoder).map_err(schema)?),
            other => {
                return Err(bad_file!(
                    "unknown text_encoder.kind `{}` (supported: bert, roberta, clip, t5)",
                    other.unwrap_or("")
                ))
            }
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
        let d = c
            .denoiser
            .as_any()
            .downcast_ref::<crate::models::FlameConfig>()
            .expect("a FLAME config");
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
            "bad model file: unknown architecture `unet` (supported: flame, mdm, motionfm, mola, mld, motionlcm, finemogen, omg)"
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
        // ("not even" / "not divisible" for the denoiser, "not divisible" for the text encoder)
        let e = Config::from_json(&EXAMPLE.replace("\"max_motion_length\": 471,", ""))
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing field `max_motion_length`"), "{e}");
    }

    /// EXAMPLE with `section.key` (top level when `section` is empty) set to `value`.
    fn with(section: &str, key: &str, value: serde_json::Value) -> String {
        let mut v: serde_json::Value = serde_json::from_str(EXAMPLE).unwrap();
        let target = if section.is_empty() {
            &mut v
        } else {
            &mut v[section]
        };
        target[key] = value;
        v.to_string()
    }

    fn err(section: &str, key: &str, value: serde_json::Value) -> String {
        match Config::from_json(&with(section, key, value.clone())) {
            Ok(_) => panic!("{section}.{key} = {value} was accepted"),
            Err(e) => {
                assert!(matches!(e, crate::Error::BadModelFile(_)), "{e}");
                e.to_string()
            }
        }
    }

    #[test]
    fn every_count_is_bounded() {
        let counts = [
            ("denoiser", "motion_dim"),
            ("denoiser", "model_channels"),
            ("denoiser", "num_layers"),
            ("denoiser", "num_heads"),
            ("denoiser", "dim_feedforward"),
            ("denoiser", "max_motion_length"),
            ("text_encoder", "vocab_size"),
            ("text_encoder", "hidden_size"),
            ("text_encoder", "num_layers"),
            ("text_encoder", "num_heads"),
            ("text_encoder", "intermediate_size"),
            ("text_encoder", "max_position_embeddings"),
            ("text_encoder", "type_vocab_size"),
            ("text_encoder", "max_length"),
            ("diffusion", "num_timesteps"),
            ("defaults", "steps"),
            ("defaults", "frames"),
        ];
        for (section, key) in counts {
            for n in [1_000_000_000u64, u64::MAX] {
                let e = err(section, key, n.into());
                assert!(
                    e.contains(&format!("{section}.{key} is {n}; it must be between")),
                    "{e}"
                );
            }
            let e = err(section, key, 0.into());
            assert!(e.contains(key), "{e}");
            err(section, key, (-1).into());
            err(section, key, 1e9.into());
        }
        let e = err("text_encoder", "pad_token_id", 1_000_000_000.into());
        assert!(
            e.contains("pad_token_id 1000000000 is not below vocab_size"),
            "{e}"
        );
        let e = err("", "format_version", u64::MAX.into());
        assert!(e.contains("is not supported"), "{e}");
        // 2^32 + 1 does not wrap around to version 1.
        let e = err("", "format_version", ((1u64 << 32) + 1).into());
        assert!(e.contains("is not supported"), "{e}");
    }

    #[test]
    fn floats_are_finite_and_bounded() {
        for (section, key, bad) in [
            ("motion", "fps", vec![0.0, -20.0, 1e30, 1000.5]),
            ("defaults", "guidance", vec![-1.0, 1e30, 100.5]),
            ("defaults", "eta", vec![-0.5, 1.5, 1e30]),
            ("denoiser", "layer_norm_eps", vec![0.0, -1e-5, 2.0]),
            ("text_encoder", "layer_norm_eps", vec![0.0, 1e30]),
        ] {
            for v in bad {
                let e = err(section, key, v.into());
                assert!(e.contains(&format!("config {section}.{key}")), "{e}");
            }
        }
        for (section, key, good) in [
            ("motion", "fps", 1000.0),
            ("defaults", "guidance", 100.0),
            ("defaults", "guidance", 0.0),
            ("defaults", "eta", 1.0),
        ] {
            Config::from_json(&with(section, key, good.into())).unwrap();
        }
    }

    #[test]
    fn names_are_checked_at_parse_time() {
        for (section, key, value, needle) in [
            ("diffusion", "schedule", "cosinus", "unknown config diffusion.schedule `cosinus` (accepted: cosine, squaredcos_cap_v2, linear, scaled_linear)"),
            ("diffusion", "parameterization", "noise", "unknown config diffusion.parameterization `noise`"),
            ("diffusion", "parameterization", "velocity", "is for flow-matching models"),
            ("diffusion", "variance", "learned", "unknown config diffusion.variance `learned`"),
            ("diffusion", "uncond", "none", "unknown config diffusion.uncond `none`"),
            ("diffusion", "uncond", "zeros", "FLAME models need `empty_prompt`"),
            ("defaults", "sampler", "dpm", "unknown config defaults.sampler `dpm` (accepted: ddpm, ddim)"),
            ("defaults", "sampler", "heun", "unknown config defaults.sampler `heun`"),
            ("motion", "format", "bvh", "unknown config motion.format `bvh` (accepted: smpl24_6d, humanml263)"),
            ("motion", "format", "humanml263", "has 263 features per frame, the denoiser 147"),
            ("denoiser", "activation", "swish", "unknown config denoiser.activation `swish`"),
            ("text_encoder", "hidden_act", "relu", "hidden_act `relu`"),
            ("text_encoder", "kind", "t6", "unknown text_encoder.kind `t6` (supported: bert, roberta, clip, t5)"),
            ("text_encoder", "kind", "t5", "architecture `flame` cannot use a `t5` text encoder"),
        ] {
            let e = err(section, key, value.into());
            assert!(e.contains(needle), "{section}.{key} = {value}: {e}");
        }
        // The sampler's own spellings still pass.
        for (section, key, value) in [
            ("diffusion", "schedule", "Linear"),
            ("diffusion", "parameterization", "v_prediction"),
            ("diffusion", "variance", "fixed_large"),
            ("defaults", "sampler", "ddim"),
        ] {
            Config::from_json(&with(section, key, value.into())).unwrap();
        }
    }

    #[test]
    fn diffusers_spacing_fields() {
        let c = Config::from_json(EXAMPLE).unwrap();
        let d = &c.diffusion;
        assert_eq!(
            (d.spacing.as_str(), d.steps_offset, d.set_alpha_to_one),
            ("respace", 0, true)
        );
        let diffusion = |fields: &[(&str, serde_json::Value)], steps: u64| {
            let mut v: serde_json::Value = serde_json::from_str(EXAMPLE).unwrap();
            for (k, x) in fields {
                v["diffusion"][*k] = x.clone();
            }
            v["defaults"]["steps"] = steps.into();
            Config::from_json(&v.to_string())
        };
        // MoLA's and MLD's settings load (trailing keeps an offset it ignores, as diffusers does).
        for (spacing, offset) in [("trailing", 1), ("leading", 1), ("Leading", 19)] {
            let f = [
                ("spacing", spacing.into()),
                ("steps_offset", offset.into()),
                ("set_alpha_to_one", false.into()),
            ];
            let c = diffusion(&f, 50).unwrap();
            assert!(!c.diffusion.set_alpha_to_one);
        }
        for (fields, steps, needle) in [
            (
                vec![("spacing", "linspace".into())],
                50,
                "unknown config diffusion.spacing `linspace` (accepted: respace, leading, trailing, lcm)",
            ),
            (
                vec![("steps_offset", 1.into())],
                50,
                "config diffusion.steps_offset 1 needs diffusion.spacing `leading` or `trailing`",
            ),
            (
                vec![("set_alpha_to_one", false.into())],
                50,
                "config diffusion.set_alpha_to_one false needs diffusion.spacing `leading`",
            ),
            (
                vec![("spacing", "leading".into()), ("steps_offset", 1000.into())],
                50,
                "config diffusion.steps_offset is 1000; it must be below diffusion.num_timesteps (1000)",
            ),
            (
                vec![("spacing", "leading".into()), ("steps_offset", 20.into())],
                50,
                "config defaults.steps 50: leading spacing with 50 steps and steps_offset 20 reaches timestep 1000",
            ),
            (
                vec![("spacing", "trailing".into())],
                61,
                "config defaults.steps 61: trailing spacing cannot take 61 steps over 1000",
            ),
            (
                vec![("steps_offset", (-1).into())],
                50,
                "does not match the flame schema",
            ),
            (
                vec![("set_alpha_to_one", "no".into())],
                50,
                "does not match the flame schema",
            ),
        ] {
            let e = diffusion(&fields, steps).unwrap_err();
            assert!(matches!(e, crate::Error::BadModelFile(_)), "{e}");
            assert!(e.to_string().contains(needle), "{fields:?}: {e}");
        }
        // A flow-matching model has no timesteps to space.
        let path = format!(
            "{}/tests/fixtures/motionfm_tiny.safetensors",
            env!("CARGO_MANIFEST_DIR")
        );
        let file = ModelFile::open(std::path::Path::new(&path)).unwrap();
        let mut v: serde_json::Value =
            serde_json::from_str(file.metadata(CONFIG_KEY).unwrap()).unwrap();
        Config::from_json(&v.to_string()).unwrap();
        v["diffusion"]["spacing"] = "trailing".into();
        let e = Config::from_json(&v.to_string()).unwrap_err().to_string();
        assert!(
            e.contains("a flow-matching model has no diffusion timesteps"),
            "{e}"
        );
    }

    #[test]
    fn a_loadable_configuration_starts_a_session() {
        // A short linear schedule has betas above 1: refused at load, not at session start.
        let short = with("diffusion", "num_timesteps", 10.into());
        let short = short.replace("\"cosine\"", "\"linear\"");
        let short: serde_json::Value = serde_json::from_str(&short).unwrap();
        let mut v = short.clone();
        v["defaults"]["steps"] = 10.into();
        let e = Config::from_json(&v.to_string()).unwrap_err().to_string();
        assert!(
            e.contains("config diffusion.schedule `linear` with num_timesteps 10"),
            "{e}"
        );
        assert!(e.contains("must be between 0 and 1, both excluded"), "{e}");
        let e = err("defaults", "steps", 1001.into());
        assert!(
            e.contains("defaults.steps is 1001; it must be between 1 and 1000"),
            "{e}"
        );
        let e = err("defaults", "frames", 471.into());
        assert!(
            e.contains("defaults.frames is 471; it must be between 1 and 470"),
            "{e}"
        );
    }
}
