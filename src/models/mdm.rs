//! MDM (Tevet et al., ICLR 2023) `trans_enc` and Motion Flow Matching's `MDM_Flow`, which is the
//! same network predicting a velocity instead of x0 (GuyTevet/motion-diffusion-model
//! `model/mdm.py`, dongzhuoyao/motionfm `model/mdm_flow.py`;
//! docs/official/mdm.md#denoiser-forward-pass, docs/official/motionfm.md#network).
//!
//! One conditioning token `emb = embed_text(clip) + embed_timestep(pe[t])` is prepended to the
//! `poseEmbedding` of every frame, the interleaved sin/cos table `pe` is added at positions
//! `0..=frames`, a post-LN `TransformerEncoder` (GELU, no final norm) runs over the sequence, the
//! token is dropped and `poseFinal` maps the frames back to features. The unconditional input of
//! classifier-free guidance is the all-zero CLIP vector (so its text token is `embed_text.bias`).
//!
//! Layout: libflame is frame-major, `[frames, njoints]` per batch row; the official tensors are
//! `[B, njoints, 1, frames]`.

use std::any::Any;
use std::sync::Arc;

use serde::Deserialize;

use crate::checkpoint::ModelFile;
use crate::config::validate::{
    check_layers, expect_flow, expect_shape, expect_text, heads_divide, in_range, is_flow, one_of,
    refuse_learned_range, table_fits,
};
use crate::config::{
    section, Config, MAX_FEEDFORWARD, MAX_LAYERS, MAX_MOTION_POSITIONS, MAX_WIDTH,
};
use crate::error::{bad_file, invalid_arg, Result};
use crate::kernels::{self, WeightType};

use super::layers::{activation, sized, EncoderLayer, LayerBuffers, LayerShape, Linear};
use super::{
    check_text_vector, text_vector_uncond, text_vector_views, Cancel, Condition, Denoiser, Family,
    FamilyConfig, TextModel,
};

/// The family's entry in [`super::FAMILIES`]: MDM (x0 or ε prediction) and Motion Flow
/// Matching (velocity), one network.
pub const FAMILY: Family = Family {
    architectures: &["mdm", "motionfm"],
    parse: |arch, v| {
        Ok(Arc::new(MdmFamily {
            flow_matching: arch == "motionfm",
            denoiser: section(v, arch, "denoiser")?,
        }))
    },
};

/// An MDM-family file's configuration: the `denoiser` section and which of the two models.
#[derive(Clone, Debug)]
pub struct MdmFamily {
    /// Motion Flow Matching (`motionfm`): the time input is flow time in [0, 1].
    pub flow_matching: bool,
    /// The network's sizes (the JSON's `denoiser` section).
    pub denoiser: MdmConfig,
}

impl FamilyConfig for MdmFamily {
    fn architecture(&self) -> &str {
        if self.flow_matching {
            "motionfm"
        } else {
            "mdm"
        }
    }

    fn check(&self, cfg: &Config) -> Result<()> {
        let d = &self.denoiser;
        d.check()?;
        expect_text(cfg, &["clip"])?;
        if let crate::config::TextConfig::Clip(c) = &cfg.text_encoder {
            if c.clip.projection_dim != d.clip_dim {
                return Err(bad_file!(
                    "config text_encoder.projection_dim {} differs from denoiser.clip_dim {}",
                    c.clip.projection_dim,
                    d.clip_dim
                ));
            }
        }
        expect_flow(cfg, self.flow_matching)?;
        refuse_learned_range(cfg)?;
        // The time input selects a row of the positional table: step t (MDM) or
        // trunc(1000 t) for t in [0, 1] (Motion Flow Matching).
        let rows = if is_flow(&cfg.diffusion.parameterization) {
            1001
        } else {
            cfg.diffusion.num_timesteps
        };
        if d.max_len < rows {
            return Err(bad_file!(
                "config denoiser.max_len {} has no row for every time input ({rows} needed)",
                d.max_len
            ));
        }
        Ok(())
    }

    fn validate(&self, file: &ModelFile) -> Result<()> {
        self.denoiser.validate(file)
    }

    fn feature_dim(&self) -> usize {
        self.denoiser.njoints
    }

    fn max_frames(&self) -> usize {
        self.denoiser.max_frames()
    }

    fn summary(&self) -> String {
        let d = &self.denoiser;
        format!(
            "MDM trans_enc, {} layers x {}, {} heads, ff {}{}",
            d.layers,
            d.latent_dim,
            d.heads,
            d.ff_size,
            if self.flow_matching {
                " (velocity: Motion Flow Matching)"
            } else {
                ""
            }
        )
    }

    fn load(
        &self,
        file: &ModelFile,
        _cfg: &Config,
        text: &TextModel,
        ty: WeightType,
    ) -> Result<Box<dyn Denoiser>> {
        if text.clip_projection_dim() != self.denoiser.clip_dim {
            return Err(bad_file!(
                "the CLIP projection has {} values, denoiser.clip_dim is {}",
                text.clip_projection_dim(),
                self.denoiser.clip_dim
            ));
        }
        let m = MdmDenoiser::load_with(file, &self.denoiser, ty)?;
        Ok(Box::new(if self.flow_matching {
            m.with_time_index(TimeIndex::FlowMatching)
        } else {
            m
        }))
    }

    fn as_any(&self) -> &dyn Any {
        &self.denoiser
    }
}

/// LayerNorm epsilon of `nn.TransformerEncoderLayer` (PyTorch default;
/// docs/official/mdm.md#conditioning-token-and-encoder).
const LAYER_NORM_EPS: f32 = 1e-5;

/// Positions taken by the conditioning token in front of the frames.
const COND_TOKENS: usize = 1;

/// MDM's `trans_enc` sizes (`utils/model_util.py`, docs/official/mdm.md#configuration; the official
/// names from `args.json`).
#[derive(Clone, Debug, Deserialize)]
pub struct MdmConfig {
    /// Feature channels per frame (263 for HumanML3D).
    pub njoints: usize,
    /// Width of every token in the encoder (official: 512); even.
    pub latent_dim: usize,
    /// Post-LN transformer encoder layers (official: 8).
    pub layers: usize,
    /// Attention heads per layer; divides `latent_dim` (official: 4). Not recoverable from the
    /// tensors' shapes, so the converter is told it.
    pub heads: usize,
    /// Width of each layer's feed-forward block (official: 1024).
    pub ff_size: usize,
    /// `gelu` (exact erf, the official choice) or `relu`.
    #[serde(default = "gelu")]
    pub activation: String,
    /// Width of the text vector fed to `embed_text` (CLIP's projection dim).
    #[serde(default = "clip_dim")]
    pub clip_dim: usize,
    /// Rows of the positional table `pe` (`PositionalEncoding(max_len=5000)`).
    #[serde(default = "max_len")]
    pub max_len: usize,
}

fn gelu() -> String {
    "gelu".into()
}
fn clip_dim() -> usize {
    512
}
fn max_len() -> usize {
    5000
}

impl MdmConfig {
    /// Bounds and names, without the file.
    pub fn check(&self) -> Result<()> {
        in_range("denoiser.njoints", self.njoints, 1, MAX_WIDTH)?;
        in_range("denoiser.latent_dim", self.latent_dim, 2, MAX_WIDTH)?;
        in_range("denoiser.layers", self.layers, 1, MAX_LAYERS)?;
        if !self.latent_dim.is_multiple_of(2) {
            return Err(bad_file!(
                "config denoiser.latent_dim {} is not even",
                self.latent_dim
            ));
        }
        heads_divide(
            "denoiser.latent_dim",
            self.latent_dim,
            "denoiser.heads",
            self.heads,
        )?;
        in_range("denoiser.ff_size", self.ff_size, 1, MAX_FEEDFORWARD)?;
        in_range("denoiser.clip_dim", self.clip_dim, 1, MAX_WIDTH)?;
        in_range("denoiser.max_len", self.max_len, 2, MAX_MOTION_POSITIONS)?;
        table_fits("denoiser.max_len", self.max_len, self.latent_dim)?;
        one_of("denoiser.activation", &self.activation, &["gelu", "relu"])
    }

    /// [`MdmConfig::check`], then the sizes against the file's tensors (no prefix).
    pub fn validate(&self, file: &ModelFile) -> Result<()> {
        self.check()?;
        let c = self.latent_dim;
        expect_shape(
            file,
            "embed_timestep.time_embed.0.weight",
            &[c, c],
            "denoiser.latent_dim",
        )?;
        expect_shape(
            file,
            "embed_text.weight",
            &[c, self.clip_dim],
            "denoiser.latent_dim, clip_dim",
        )?;
        expect_shape(
            file,
            "input_process.poseEmbedding.weight",
            &[c, self.njoints],
            "denoiser.latent_dim, njoints",
        )?;
        check_layers(
            file,
            "denoiser.layers",
            self.layers,
            "seqTransEncoder.layers.",
        )?;
        expect_shape(
            file,
            "seqTransEncoder.layers.0.linear1.weight",
            &[self.ff_size, c],
            "denoiser.ff_size, latent_dim",
        )
    }

    /// The largest frame count a session may ask for (one row of `pe` is the condition's).
    pub fn max_frames(&self) -> usize {
        self.max_len - 1
    }
}

/// How the `t` passed to [`MdmDenoiser::forward`] becomes a row of the positional table.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TimeIndex {
    /// MDM: `t` is the integer diffusion step, used as the row directly.
    Diffusion,
    /// Motion Flow Matching: `t ∈ [0, 1]`, row `trunc(f32(t · 1000))` (motionfm
    /// `model/mdm_flow.py`; docs/official/motionfm.md#time-index).
    FlowMatching,
}

impl TimeIndex {
    /// The `pe` row for `t`, or `None` when `t` does not name one (negative, NaN, fractional
    /// diffusion step).
    pub fn row(self, t: f32) -> Option<usize> {
        let s = match self {
            TimeIndex::Diffusion => t,
            // `(t * 1000).long()` on a float32 tensor: one f32 multiply, then truncation.
            TimeIndex::FlowMatching => (t * 1000.0f32).trunc(),
        };
        (s >= 0.0 && s.fract() == 0.0 && s.is_finite()).then_some(s as usize)
    }
}

/// `TimestepEmbedder.time_embed`: Linear → SiLU → Linear on a row of `pe`.
struct TimeEmbed {
    fc0: Linear,
    fc2: Linear,
}

/// Reusable buffers for one forward pass, so steps after the first do not allocate.
#[derive(Default)]
pub struct Workspace {
    x: Vec<f32>,
    layer: LayerBuffers,
    frames: Vec<f32>,
    text: Vec<f32>,
    text_emb: Vec<f32>,
    time_hidden: Vec<f32>,
    time_emb: Vec<f32>,
}

/// MDM's `trans_enc` denoiser (and MotionFM's `MDM_Flow`), inference only.
pub struct MdmDenoiser {
    cfg: MdmConfig,
    time_index: TimeIndex,
    embed_timestep: TimeEmbed,
    embed_text: Linear,
    pose_embedding: Linear,
    layers: Vec<EncoderLayer>,
    pose_final: Linear,
    /// `sequence_pos_encoder.pe` recomputed: `[max_len, latent_dim]`, interleaved sin/cos.
    pe: Vec<f32>,
}

impl MdmDenoiser {
    /// Reads the denoiser's tensors (official MDM names, no prefix) in module order, so the first
    /// bad tensor is the one reported. The `pe` buffers are recomputed, not read. The time
    /// convention starts as [`TimeIndex::Diffusion`]; see [`MdmDenoiser::with_time_index`].
    pub fn load(file: &ModelFile, cfg: &MdmConfig) -> Result<MdmDenoiser> {
        MdmDenoiser::load_with(file, cfg, WeightType::F32)
    }

    /// [`MdmDenoiser::load`] with the linear weights held (and multiplied) as `ty`.
    pub fn load_with(file: &ModelFile, cfg: &MdmConfig, ty: WeightType) -> Result<MdmDenoiser> {
        cfg.validate(file)?;
        let c = cfg.latent_dim;
        let embed_timestep = TimeEmbed {
            fc0: Linear::load(file, "embed_timestep.time_embed.0", c, c, ty)?,
            fc2: Linear::load(file, "embed_timestep.time_embed.2", c, c, ty)?,
        };
        let embed_text = Linear::load(file, "embed_text", cfg.clip_dim, c, ty)?;
        let pose_embedding = Linear::load(file, "input_process.poseEmbedding", cfg.njoints, c, ty)?;
        let mut layers = Vec::with_capacity(cfg.layers);
        for n in 0..cfg.layers {
            let p = format!("seqTransEncoder.layers.{n}");
            layers.push(EncoderLayer::load(file, &p, c, cfg.ff_size, ty)?);
        }
        let pose_final = Linear::load(file, "output_process.poseFinal", c, cfg.njoints, ty)?;
        let mut pe = vec![0.0; cfg.max_len * c];
        for (p, row) in pe.chunks_exact_mut(c).enumerate() {
            kernels::sinusoid_interleaved(p as f32, row);
        }
        Ok(MdmDenoiser {
            cfg: cfg.clone(),
            time_index: TimeIndex::Diffusion,
            embed_timestep,
            embed_text,
            pose_embedding,
            layers,
            pose_final,
            pe,
        })
    }

    /// Sets how `t` maps to a `pe` row: [`TimeIndex::FlowMatching`] for Motion Flow Matching.
    pub fn with_time_index(mut self, time_index: TimeIndex) -> MdmDenoiser {
        self.time_index = time_index;
        self
    }

    /// How the time input picks its `pe` row (MDM's integer step, or flow time).
    pub fn time_index(&self) -> TimeIndex {
        self.time_index
    }

    /// Bytes of the packed linear weights (the part [`WeightType`] changes).
    pub fn linear_weight_bytes(&self) -> usize {
        let layers: usize = self.layers.iter().map(|l| l.weight_bytes()).sum();
        layers
            + [
                &self.embed_timestep.fc0,
                &self.embed_timestep.fc2,
                &self.embed_text,
                &self.pose_embedding,
                &self.pose_final,
            ]
            .iter()
            .map(|l| l.weight_bytes())
            .sum::<usize>()
    }

    /// The sizes the network was built from.
    pub fn config(&self) -> &MdmConfig {
        &self.cfg
    }

    /// Feature channels per frame (263 for HumanML3D); also the output width.
    pub fn motion_dim(&self) -> usize {
        self.cfg.njoints
    }

    /// Output channels per frame: the x0 (MDM) or velocity (MotionFM) prediction.
    pub fn output_dim(&self) -> usize {
        self.cfg.njoints
    }

    /// Width of the text vector each row is conditioned on (zeros = unconditional).
    pub fn cond_dim(&self) -> usize {
        self.cfg.clip_dim
    }

    /// The largest frame count the positional table covers (position 0 is the cond token).
    pub fn max_frames(&self) -> usize {
        self.cfg.max_len - COND_TOKENS
    }

    /// One forward pass over a batch: row `b` denoises `x[b]` (`[frames, njoints]`) under the
    /// text vector `conds[b]` (`[clip_dim]`; all zeros for the unconditional pass) at time `t`
    /// (see [`TimeIndex`]), writing `[frames, njoints]` into `out[b]`. Every frame is valid, so
    /// no key-padding mask is applied.
    pub fn forward(
        &self,
        x: &[f32],
        frames: usize,
        t: f32,
        conds: &[&[f32]],
        out: &mut [f32],
        ws: &mut Workspace,
    ) -> Result<()> {
        self.forward_cancellable(x, frames, t, conds, out, ws, &Cancel::never())
    }

    /// [`Self::forward`] that checks `cancel` before every layer.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward_cancellable(
        &self,
        x: &[f32],
        frames: usize,
        t: f32,
        conds: &[&[f32]],
        out: &mut [f32],
        ws: &mut Workspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let c = self.cfg.latent_dim;
        let d = self.cfg.njoints;
        let batch = conds.len();
        if frames == 0 || frames > self.max_frames() {
            return Err(invalid_arg!(
                "frames must be between 1 and {} for this model, got {frames}",
                self.max_frames()
            ));
        }
        if x.len() != batch * frames * d || out.len() != batch * frames * d {
            return Err(invalid_arg!(
                "forward buffers do not match batch {batch} × {frames} frames × {d}"
            ));
        }
        if let Some(k) = conds.iter().position(|v| v.len() != self.cfg.clip_dim) {
            return Err(invalid_arg!(
                "condition {k} has {} values, the denoiser expects {}",
                conds[k].len(),
                self.cfg.clip_dim
            ));
        }
        let row = self
            .time_index
            .row(t)
            .filter(|&r| r < self.cfg.max_len)
            .ok_or_else(|| invalid_arg!("t {t} has no positional row ({:?})", self.time_index))?;

        // Time token: time_embed(pe[t]), shared by the batch.
        let time_hidden = sized(&mut ws.time_hidden, c);
        self.embed_timestep
            .fc0
            .forward(&self.pe[row * c..(row + 1) * c], 1, time_hidden);
        kernels::silu(time_hidden);
        let time_emb = sized(&mut ws.time_emb, c);
        self.embed_timestep
            .fc2
            .forward(&ws.time_hidden[..c], 1, time_emb);

        // Text tokens: embed_text(clip) for every row in one GEMM.
        let text_in = sized(&mut ws.text, batch * self.cfg.clip_dim);
        for (dst, cond) in text_in.chunks_exact_mut(self.cfg.clip_dim).zip(conds) {
            dst.copy_from_slice(cond);
        }
        let text_emb = sized(&mut ws.text_emb, batch * c);
        self.embed_text.forward(&ws.text, batch, text_emb);
        let (time_emb, text_emb) = (&ws.time_emb[..c], &ws.text_emb[..batch * c]);

        // Frame tokens for the whole batch in one GEMM.
        let motion = sized(&mut ws.frames, batch * frames * c);
        self.pose_embedding.forward(x, batch * frames, motion);

        let seq = frames + COND_TOKENS;
        let h = sized(&mut ws.x, batch * seq * c);
        for b in 0..batch {
            let tokens = &mut h[b * seq * c..(b + 1) * seq * c];
            // emb = time_emb + text_emb (MDM's "add" policy, time first as in the official sum).
            for ((v, &te), &xe) in tokens[..c]
                .iter_mut()
                .zip(time_emb)
                .zip(&text_emb[b * c..(b + 1) * c])
            {
                *v = te + xe;
            }
            tokens[c..].copy_from_slice(&motion[b * frames * c..(b + 1) * frames * c]);
            for (v, p) in tokens.iter_mut().zip(&self.pe[..seq * c]) {
                *v += p;
            }
        }

        let shape = LayerShape {
            width: c,
            heads: self.cfg.heads,
            ff: self.cfg.ff_size,
            act: activation(&self.cfg.activation),
            eps: LAYER_NORM_EPS,
        };
        for layer in &self.layers {
            cancel.check()?;
            layer.forward(&mut ws.x, batch, seq, shape, &mut ws.layer);
        }

        // Drop the cond token and project back to features.
        let h = &ws.x;
        let motion_out = sized(&mut ws.frames, batch * frames * c);
        for b in 0..batch {
            let src = &h[(b * seq + COND_TOKENS) * c..(b + 1) * seq * c];
            motion_out[b * frames * c..(b + 1) * frames * c].copy_from_slice(src);
        }
        self.pose_final.forward(motion_out, batch * frames, out);
        Ok(())
    }
}

impl Denoiser for MdmDenoiser {
    fn sample_dim(&self) -> usize {
        self.motion_dim()
    }

    fn encode_prompt(&self, text: &TextModel, prompt: &str) -> Result<Condition> {
        Ok(Condition::text_vector(text.clip_vector(prompt)?))
    }

    fn unconditional(&self, text: &TextModel, uncond: &str) -> Result<Condition> {
        text_vector_uncond(text, uncond, self.cond_dim())
    }

    fn check_condition(&self, cond: &Condition) -> Result<()> {
        check_text_vector(cond, self.cond_dim())
    }

    fn forward(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        conds: &[&Condition],
        out: &mut [f32],
        ws: &mut super::Workspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let (texts, n) = text_vector_views(conds)?;
        self.forward_cancellable(x, rows, t, &texts[..n], out, ws.get(), cancel)
    }

    fn linear_weight_bytes(&self) -> usize {
        MdmDenoiser::linear_weight_bytes(self)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

#[cfg(test)]
mod tests {
    use super::TimeIndex;

    #[test]
    fn time_rows() {
        assert_eq!(TimeIndex::Diffusion.row(999.0), Some(999));
        assert_eq!(TimeIndex::Diffusion.row(2.5), None);
        assert_eq!(TimeIndex::Diffusion.row(-1.0), None);
        assert_eq!(TimeIndex::FlowMatching.row(0.0), Some(0));
        assert_eq!(TimeIndex::FlowMatching.row(0.5), Some(500));
        // 0.01f32 · 5 rounds below 0.05 in f32 and the product truncates
        // (docs/official/motionfm.md#time-index).
        assert_eq!(TimeIndex::FlowMatching.row(0.01f32 * 5.0), Some(49));
        // The custom loops' grid i/N as an f32 division lands exactly.
        assert_eq!(TimeIndex::FlowMatching.row(5.0f32 / 100.0), Some(50));
        assert_eq!(TimeIndex::FlowMatching.row(f32::NAN), None);
    }
}
