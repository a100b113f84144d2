//! MLD (Chen et al., CVPR 2023, ChenFengYe/motion-latent-diffusion): latent diffusion of motion. A
//! skip transformer denoises a `[latent_tokens, latent_dim]` latent under a CLIP text vector; the
//! VAE's skip-transformer decoder turns the latent into as many HumanML3D frames as the caller asks
//! for (ChenFengYe/motion-latent-diffusion `mld/models/architectures/` `mld_denoiser.py` and
//! `mld_vae.py`; docs/official/mola-mld.md#mld-denoiser,
//! docs/official/mola-mld.md#mld-vae-decoder).
//!
//! Denoiser: the sequence `[latent tokens, time, text]` plus a learned positional table, where
//! time = Linear → SiLU → Linear of the cos-first sinusoid of t (`text_dim` wide) and text =
//! Linear(ReLU(vector)); a U-shaped stack of post-LN encoder layers (input blocks whose outputs
//! are kept, a middle block, output blocks each after Linear(2D → D) over `[x, skip]`, skips last
//! in first out) and a final LayerNorm; the latent tokens of the output are ε. Guidance mixes
//! only above scale 1, as MLD's sampler does.
//!
//! VAE decoder: zero queries plus a learned positional table, one per frame, through the same
//! U-shaped stack of post-LN decoder layers attending to the latent, an optional final
//! LayerNorm, and Linear(D → features). Every frame is valid.

use std::any::Any;
use std::sync::Arc;

use serde::Deserialize;

use crate::checkpoint::{ModelFile, Tensor};
use crate::config::validate::{
    check_eps, check_layers, expect_flow, expect_shape, expect_text, heads_divide, in_range,
    one_of, refuse_learned_range,
};
use crate::config::{
    section, Config, TextConfig, MAX_FEEDFORWARD, MAX_LAYERS, MAX_MOTION_POSITIONS, MAX_WIDTH,
};
use crate::error::{bad_file, invalid_arg, Result};
use crate::kernels::{self, WeightType};

use super::backward::VaeTape;
use super::layers::{
    activation, sized, DecoderLayer, EncoderLayer, LayerBuffers, LayerNorm, LayerShape, Linear,
};
use super::{
    check_text_vector, text_vector_uncond, text_vector_views, Cancel, Condition, Denoiser, Family,
    FamilyConfig, Guidance, MotionDecoder, TextModel, Workspace,
};

/// The family's entry in [`super::FAMILIES`].
pub const FAMILY: Family = Family {
    architectures: &["mld"],
    parse: |arch, v| {
        Ok(Arc::new(MldFamily {
            denoiser: section(v, arch, "denoiser")?,
            vae: section(v, arch, "vae")?,
        }))
    },
};

/// The denoiser's sizes: the `denoiser` section.
#[derive(Clone, Debug, Deserialize)]
pub struct MldConfig {
    /// Width of the latent and of the transformer (256).
    pub latent_dim: usize,
    /// Tokens of the latent (1).
    pub latent_tokens: usize,
    /// Width of the text vector and of the time sinusoid (CLIP ViT-L/14's 768).
    pub text_dim: usize,
    /// Layers of the skip stack (odd: 9).
    pub layers: usize,
    /// Attention heads per layer; divides `latent_dim` (official: 4).
    pub heads: usize,
    /// Width of each layer's feed-forward block (official: 1024).
    pub ff_size: usize,
    /// Rows of the learned positional table (`query_pos.pe`; official: 500); the sequence
    /// [latent tokens, time, text] needs `latent_tokens` + 2 of them.
    pub max_len: usize,
    /// The feed-forward activation: `gelu` (exact erf, the default) or `relu`.
    #[serde(default = "gelu")]
    pub activation: String,
    /// LayerNorm's epsilon, in (0, 1] (default 1e-5).
    #[serde(default = "ln_eps")]
    pub layer_norm_eps: f32,
}

/// The VAE decoder's sizes: the `vae` section.
#[derive(Clone, Debug, Deserialize)]
pub struct MldVaeConfig {
    /// Width of the latent and of the decoder; = `denoiser.latent_dim` (256).
    pub latent_dim: usize,
    /// Layers of the skip stack (odd: 9).
    pub layers: usize,
    /// Attention heads per layer; divides `latent_dim`.
    pub heads: usize,
    /// Width of each layer's feed-forward block.
    pub ff_size: usize,
    /// Features per frame (263).
    pub nfeats: usize,
    /// Rows of the learned positional table: the most frames.
    pub max_len: usize,
    /// Whether the stack ends in a LayerNorm (`decoder.norm`).
    pub final_norm: bool,
    /// The feed-forward activation: `gelu` (exact erf, the default) or `relu`.
    #[serde(default = "gelu")]
    pub activation: String,
    /// LayerNorm's epsilon, in (0, 1] (default 1e-5).
    #[serde(default = "ln_eps")]
    pub layer_norm_eps: f32,
}

fn gelu() -> String {
    "gelu".into()
}

fn ln_eps() -> f32 {
    1e-5
}

/// An MLD file's configuration.
#[derive(Clone, Debug)]
pub struct MldFamily {
    /// The latent denoiser's sizes (the `denoiser` section).
    pub denoiser: MldConfig,
    /// The VAE decoder's sizes (the `vae` section), which turns a latent into frames.
    pub vae: MldVaeConfig,
}

const D: &str = "denoiser.";

/// Checks a skip stack of `layers` (odd) under `{p}`: its blocks and linear joins.
pub(crate) fn check_stack(file: &ModelFile, field: &str, layers: usize, p: &str) -> Result<()> {
    in_range(field, layers, 1, MAX_LAYERS)?;
    if layers.is_multiple_of(2) {
        return Err(bad_file!(
            "config {field} {layers} is not odd (input blocks, a middle block, output blocks)"
        ));
    }
    let blocks = (layers - 1) / 2;
    for part in ["input_blocks", "output_blocks", "linear_blocks"] {
        let prefix = format!("{p}{part}.");
        if blocks == 0 {
            if file.has_prefix(&prefix) {
                return Err(bad_file!(
                    "config {field} is 1 but the file has tensors `{prefix}*`"
                ));
            }
        } else {
            check_layers(file, field, blocks, &prefix)?;
        }
    }
    Ok(())
}

impl FamilyConfig for MldFamily {
    fn architecture(&self) -> &str {
        "mld"
    }

    fn check(&self, cfg: &Config) -> Result<()> {
        self.check_networks(cfg)?;
        expect_text(cfg, &["clip"])?;
        if let TextConfig::Clip(c) = &cfg.text_encoder {
            if c.clip.projection_dim != self.denoiser.text_dim {
                return Err(bad_file!(
                    "config text_encoder.projection_dim {} differs from denoiser.text_dim {}",
                    c.clip.projection_dim,
                    self.denoiser.text_dim
                ));
            }
        }
        expect_flow(cfg, false)?;
        refuse_learned_range(cfg)
    }

    fn validate(&self, file: &ModelFile) -> Result<()> {
        self.validate_networks(file)
    }

    fn feature_dim(&self) -> usize {
        self.vae.nfeats
    }

    fn max_frames(&self) -> usize {
        self.vae.max_len
    }

    fn summary(&self) -> String {
        let d = &self.denoiser;
        format!(
            "MLD skip transformer, {} layers x {}, {} heads, ff {}, latent {} x {}",
            d.layers, d.latent_dim, d.heads, d.ff_size, d.latent_tokens, d.latent_dim
        )
    }

    fn load(
        &self,
        file: &ModelFile,
        _cfg: &Config,
        _text: &TextModel,
        ty: WeightType,
    ) -> Result<Box<dyn Denoiser>> {
        Ok(Box::new(MldDenoiser::load(file, self, ty)?))
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

impl MldFamily {
    /// The denoiser's and the VAE decoder's sections, and the motion format against the
    /// decoder's features (everything of [`FamilyConfig::check`] but the text encoder and the
    /// diffusion section, which MotionLCM checks its own way).
    pub(crate) fn check_networks(&self, cfg: &Config) -> Result<()> {
        let (d, v) = (&self.denoiser, &self.vae);
        in_range("denoiser.latent_dim", d.latent_dim, 1, MAX_WIDTH)?;
        heads_divide(
            "denoiser.latent_dim",
            d.latent_dim,
            "denoiser.heads",
            d.heads,
        )?;
        in_range("denoiser.text_dim", d.text_dim, 2, MAX_WIDTH)?;
        if !d.text_dim.is_multiple_of(2) {
            return Err(bad_file!(
                "config denoiser.text_dim {} is not even (the time sinusoid's width)",
                d.text_dim
            ));
        }
        in_range("denoiser.layers", d.layers, 1, MAX_LAYERS)?;
        in_range("denoiser.ff_size", d.ff_size, 1, MAX_FEEDFORWARD)?;
        in_range("denoiser.max_len", d.max_len, 3, MAX_MOTION_POSITIONS)?;
        in_range("denoiser.latent_tokens", d.latent_tokens, 1, d.max_len - 2)?;
        one_of("denoiser.activation", &d.activation, &["gelu", "relu"])?;
        check_eps("denoiser.layer_norm_eps", d.layer_norm_eps)?;
        if v.latent_dim != d.latent_dim {
            return Err(bad_file!(
                "config vae.latent_dim {} differs from denoiser.latent_dim {}",
                v.latent_dim,
                d.latent_dim
            ));
        }
        heads_divide("vae.latent_dim", v.latent_dim, "vae.heads", v.heads)?;
        in_range("vae.layers", v.layers, 1, MAX_LAYERS)?;
        in_range("vae.ff_size", v.ff_size, 1, MAX_FEEDFORWARD)?;
        in_range("vae.max_len", v.max_len, 1, MAX_MOTION_POSITIONS)?;
        one_of("vae.activation", &v.activation, &["gelu", "relu"])?;
        check_eps("vae.layer_norm_eps", v.layer_norm_eps)?;
        let features = cfg
            .motion
            .format
            .parse::<crate::motion::Format>()
            .map(|f| f.feature_dim())
            .unwrap_or(0);
        if v.nfeats != features {
            return Err(bad_file!(
                "config vae.nfeats {} differs from motion.format `{}`'s {features} features",
                v.nfeats,
                cfg.motion.format
            ));
        }
        Ok(())
    }

    /// Every size of the two networks against the file's shapes.
    pub(crate) fn validate_networks(&self, file: &ModelFile) -> Result<()> {
        let (d, v) = (&self.denoiser, &self.vae);
        let e = d.latent_dim;
        let shape =
            |name: &str, want: &[usize], fields: &str| expect_shape(file, name, want, fields);
        shape(
            &format!("{D}query_pos.pe"),
            &[d.max_len, 1, e],
            "denoiser.max_len, latent_dim",
        )?;
        shape(
            &format!("{D}time_embedding.linear_1.weight"),
            &[e, d.text_dim],
            "denoiser.latent_dim, text_dim",
        )?;
        shape(
            &format!("{D}emb_proj.1.weight"),
            &[e, d.text_dim],
            "denoiser.latent_dim, text_dim",
        )?;
        check_stack(file, "denoiser.layers", d.layers, &format!("{D}encoder."))?;
        shape(
            &format!("{D}encoder.middle_block.linear1.weight"),
            &[d.ff_size, e],
            "denoiser.ff_size, latent_dim",
        )?;
        shape(
            "vae.query_pos_decoder.pe",
            &[v.max_len, 1, e],
            "vae.max_len, latent_dim",
        )?;
        check_stack(file, "vae.layers", v.layers, "vae.decoder.")?;
        shape(
            "vae.decoder.middle_block.linear1.weight",
            &[v.ff_size, e],
            "vae.ff_size, latent_dim",
        )?;
        if v.final_norm != file.contains("vae.decoder.norm.weight") {
            return Err(bad_file!(
                "config vae.final_norm is {} but the file {} `vae.decoder.norm.weight`",
                v.final_norm,
                if v.final_norm { "has no" } else { "has" }
            ));
        }
        shape(
            "vae.final_layer.weight",
            &[v.nfeats, e],
            "vae.nfeats, latent_dim",
        )
    }
}

/// A layer of a skip stack: runs over `batch` blocks of `seq` rows, with the memory rows of
/// the block (decoder layers) or none.
pub(crate) trait StackLayer {
    fn load(file: &ModelFile, p: &str, e: usize, ff: usize, ty: WeightType) -> Result<Self>
    where
        Self: Sized;
    fn weight_bytes(&self) -> usize;
    /// `key_padding` (one flag per row of a block, true = excluded as a key) is for encoder
    /// layers; decoder stacks pass none.
    #[allow(clippy::too_many_arguments)]
    fn run(
        &self,
        x: &mut [f32],
        batch: usize,
        seq: usize,
        memory: &[f32],
        mem_len: usize,
        key_padding: Option<&[bool]>,
        s: LayerShape,
        b: &mut LayerBuffers,
    );
}

impl StackLayer for EncoderLayer {
    fn load(file: &ModelFile, p: &str, e: usize, ff: usize, ty: WeightType) -> Result<Self> {
        EncoderLayer::load(file, p, e, ff, ty)
    }
    fn weight_bytes(&self) -> usize {
        EncoderLayer::weight_bytes(self)
    }
    fn run(
        &self,
        x: &mut [f32],
        batch: usize,
        seq: usize,
        _memory: &[f32],
        _mem_len: usize,
        key_padding: Option<&[bool]>,
        s: LayerShape,
        b: &mut LayerBuffers,
    ) {
        self.forward_padded(x, batch, seq, key_padding, s, b)
    }
}

impl StackLayer for DecoderLayer {
    fn load(file: &ModelFile, p: &str, e: usize, ff: usize, ty: WeightType) -> Result<Self> {
        DecoderLayer::load(file, p, e, ff, ty)
    }
    fn weight_bytes(&self) -> usize {
        DecoderLayer::weight_bytes(self)
    }
    fn run(
        &self,
        x: &mut [f32],
        batch: usize,
        seq: usize,
        memory: &[f32],
        mem_len: usize,
        key_padding: Option<&[bool]>,
        s: LayerShape,
        b: &mut LayerBuffers,
    ) {
        debug_assert!(key_padding.is_none(), "decoder stacks run unmasked");
        self.forward(x, batch, seq, memory, mem_len, s, b)
    }
}

/// MLD's U-shaped stack (`input_blocks`, `middle_block`, `output_blocks`, `linear_blocks`,
/// `norm`).
pub(crate) struct SkipStack<L> {
    pub(crate) input: Vec<L>,
    pub(crate) middle: L,
    pub(crate) output: Vec<L>,
    pub(crate) joins: Vec<Linear>,
    pub(crate) norm: Option<LayerNorm>,
    pub(crate) shape: LayerShape,
}

/// What [`SkipStack::forward_taps`] adds to a plain pass.
#[derive(Default)]
pub(crate) struct Taps<'a> {
    /// One flag per row of a block: true excludes the row as a key (a single block).
    pub key_padding: Option<&'a [bool]>,
    /// `[blocks, rows, width]`: added to the output of block i.
    pub residuals: Option<&'a [f32]>,
    /// Receives `[blocks, rows, width]`: every block's output.
    pub collect: Option<&'a mut Vec<f32>>,
}

/// Buffers of a skip stack's forward pass.
#[derive(Default)]
pub(crate) struct StackBuffers {
    layer: LayerBuffers,
    skips: Vec<Vec<f32>>,
    cat: Vec<f32>,
}

impl<L: StackLayer> SkipStack<L> {
    pub(crate) fn load(
        file: &ModelFile,
        p: &str,
        layers: usize,
        norm: bool,
        shape: LayerShape,
        ty: WeightType,
    ) -> Result<SkipStack<L>> {
        let (e, ff) = (shape.width, shape.ff);
        let blocks = (layers - 1) / 2;
        let load = |name: String| L::load(file, &format!("{p}{name}"), e, ff, ty);
        Ok(SkipStack {
            input: (0..blocks)
                .map(|i| load(format!("input_blocks.{i}")))
                .collect::<Result<_>>()?,
            middle: load("middle_block".into())?,
            output: (0..blocks)
                .map(|i| load(format!("output_blocks.{i}")))
                .collect::<Result<_>>()?,
            joins: (0..blocks)
                .map(|i| Linear::load(file, &format!("{p}linear_blocks.{i}"), 2 * e, e, ty))
                .collect::<Result<_>>()?,
            norm: if norm {
                Some(LayerNorm::load(file, &format!("{p}norm"), e)?)
            } else {
                None
            },
            shape,
        })
    }

    pub(crate) fn weight_bytes(&self) -> usize {
        self.input
            .iter()
            .chain(&self.output)
            .chain([&self.middle])
            .map(|l| l.weight_bytes())
            .sum::<usize>()
            + self.joins.iter().map(|l| l.weight_bytes()).sum::<usize>()
    }

    /// The stack over `batch` blocks of `seq` rows in `x`, checking `cancel` before each layer.
    #[allow(clippy::too_many_arguments)]
    fn forward(
        &self,
        x: &mut [f32],
        batch: usize,
        seq: usize,
        memory: &[f32],
        mem_len: usize,
        b: &mut StackBuffers,
        cancel: &Cancel,
    ) -> Result<()> {
        self.forward_taps(x, batch, seq, memory, mem_len, Taps::default(), b, cancel)
    }

    /// [`SkipStack::forward`] with MotionLCM's taps: a key padding mask, ControlNet residuals
    /// added after every block (before the skip is kept and before the final norm, as
    /// Dai-Wenxun/MotionLCM v2.0 `mld/models/operator/attention.py` adds them), and every
    /// block's output collected (the ControlNet's own pass).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward_taps(
        &self,
        x: &mut [f32],
        batch: usize,
        seq: usize,
        memory: &[f32],
        mem_len: usize,
        mut taps: Taps<'_>,
        b: &mut StackBuffers,
        cancel: &Cancel,
    ) -> Result<()> {
        let (s, e) = (self.shape, self.shape.width);
        let rows = batch * seq;
        let n = rows * e;
        let kp = taps.key_padding;
        if let Some(c) = taps.collect.as_deref_mut() {
            c.clear();
        }
        let mut block = 0;
        let mut tap = |x: &mut [f32], taps: &mut Taps<'_>| {
            if let Some(r) = taps.residuals {
                kernels::add_inplace(x, &r[block * n..(block + 1) * n]);
            }
            if let Some(c) = taps.collect.as_deref_mut() {
                c.extend_from_slice(x);
            }
            block += 1;
        };
        b.skips.resize_with(self.input.len(), Vec::new);
        for (layer, skip) in self.input.iter().zip(b.skips.iter_mut()) {
            cancel.check()?;
            layer.run(x, batch, seq, memory, mem_len, kp, s, &mut b.layer);
            tap(x, &mut taps);
            skip.clear();
            skip.extend_from_slice(x);
        }
        cancel.check()?;
        self.middle
            .run(x, batch, seq, memory, mem_len, kp, s, &mut b.layer);
        tap(x, &mut taps);
        for (i, (layer, join)) in self.output.iter().zip(&self.joins).enumerate() {
            cancel.check()?;
            // Skips last in, first out: output block i joins input block n − 1 − i.
            let skip = &b.skips[self.input.len() - 1 - i];
            let cat = sized(&mut b.cat, rows * 2 * e);
            for ((c, xr), sr) in cat
                .chunks_exact_mut(2 * e)
                .zip(x.chunks_exact(e))
                .zip(skip.chunks_exact(e))
            {
                c[..e].copy_from_slice(xr);
                c[e..].copy_from_slice(sr);
            }
            join.forward(cat, rows, x);
            layer.run(x, batch, seq, memory, mem_len, kp, s, &mut b.layer);
            tap(x, &mut taps);
        }
        if let Some(n) = &self.norm {
            kernels::layer_norm(x, e, n.weight.data(), n.bias.data(), s.eps);
        }
        Ok(())
    }

    /// Blocks of the stack (the residuals a ControlNet provides, one per block).
    pub(crate) fn blocks(&self) -> usize {
        2 * self.input.len() + 1
    }
}

/// What MotionLCM (Dai-Wenxun/MotionLCM v1.0 f534a7f, v2.0 086f8db,
/// `mld/models/architectures/mld_denoiser.py`, `mld_vae.py`) adds to MLD's networks; MLD itself
/// has none of it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) struct LatentParts {
    /// Channels of a latent token (C). When it differs from the width, `latent_pre` (C → D)
    /// and `latent_post` (D → C) wrap the denoiser's stack and the VAE decoder's `latent_post`
    /// (C → D) reads the latent (MotionLCM v2: 32 against 256).
    pub channels: usize,
    /// Width of the guidance embedding `time_embedding.cond_proj` takes (MotionLCM: 256).
    pub cond_dim: Option<usize>,
    /// Whether `emb_proj` applies ReLU before its Linear (MLD, MotionLCM v1) or nothing (v2).
    pub text_relu: bool,
}

impl LatentParts {
    /// MLD's own network: none of the additions.
    pub(crate) fn mld(cfg: &MldConfig) -> LatentParts {
        LatentParts {
            channels: cfg.latent_dim,
            cond_dim: None,
            text_relu: true,
        }
    }
}

/// MotionLCM v2's projections between the latent's channels and the width.
pub(crate) struct LatentIo {
    /// `latent_pre` (C → D).
    pub(crate) pre: Linear,
    /// `latent_post` (D → C); none in a ControlNet's copy.
    pub(crate) post: Option<Linear>,
}

impl LatentIo {
    fn weight_bytes(&self) -> usize {
        self.pre.weight_bytes() + self.post.as_ref().map_or(0, Linear::weight_bytes)
    }
}

/// MLD's denoiser and VAE decoder.
pub struct MldDenoiser {
    pub(crate) cfg: MldFamily,
    pub(crate) parts: LatentParts,
    time: [Linear; 2],
    /// `time_embedding.cond_proj` (no bias): the guidance embedding into the time sinusoid.
    cond_proj: Option<Linear>,
    /// `latent_pre` (C → D) and `latent_post` (D → C) around the stack.
    pub(crate) latent_io: Option<LatentIo>,
    emb_proj: Linear,
    /// `query_pos.pe` `[max_len, D]`.
    pe: Tensor,
    pub(crate) encoder: SkipStack<EncoderLayer>,
    /// The VAE decoder (none in a ControlNet's copy of the denoiser).
    vae: Option<VaeDecoder>,
}

/// How [`MldDenoiser::load_part`] reads a denoiser: MLD's (and MotionLCM's) own under
/// `denoiser.` with the VAE decoder and the stack's final norm, or a ControlNet's copy under
/// `controlnet.` without either.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Part<'a> {
    /// Tensor name prefix.
    pub prefix: &'a str,
    /// Whether the stack ends in `encoder.norm` and the file holds the VAE decoder.
    pub main: bool,
}

/// Reusable buffers of the denoiser.
#[derive(Default)]
pub struct MldWorkspace {
    sinusoid: Vec<f32>,
    guidance: Vec<f32>,
    latent_in: Vec<f32>,
    hidden: Vec<f32>,
    time: Vec<f32>,
    text: Vec<f32>,
    texts: Vec<f32>,
    pub(crate) x: Vec<f32>,
    stack: StackBuffers,
}

impl MldDenoiser {
    /// Reads the tensors (official names under `denoiser.` and `vae.`), in module order.
    pub fn load(file: &ModelFile, cfg: &MldFamily, ty: WeightType) -> Result<MldDenoiser> {
        MldDenoiser::load_with(file, cfg, LatentParts::mld(&cfg.denoiser), ty)
    }

    /// [`MldDenoiser::load`] with MotionLCM's additions.
    pub(crate) fn load_with(
        file: &ModelFile,
        cfg: &MldFamily,
        parts: LatentParts,
        ty: WeightType,
    ) -> Result<MldDenoiser> {
        let part = Part {
            prefix: D,
            main: true,
        };
        MldDenoiser::load_part(file, cfg, parts, part, ty)
    }

    /// [`MldDenoiser::load_with`] of the denoiser `part` names.
    pub(crate) fn load_part(
        file: &ModelFile,
        cfg: &MldFamily,
        parts: LatentParts,
        part: Part<'_>,
        ty: WeightType,
    ) -> Result<MldDenoiser> {
        let d = &cfg.denoiser;
        let c = parts.channels;
        let e = d.latent_dim;
        let p = part.prefix;
        let lin =
            |name: &str, n_in, n_out| Linear::load(file, &format!("{p}{name}"), n_in, n_out, ty);
        let shape = LayerShape {
            width: e,
            heads: d.heads,
            ff: d.ff_size,
            act: activation(&d.activation),
            eps: d.layer_norm_eps,
        };
        Ok(MldDenoiser {
            time: [
                lin("time_embedding.linear_1", d.text_dim, e)?,
                lin("time_embedding.linear_2", e, e)?,
            ],
            cond_proj: match parts.cond_dim {
                Some(g) => Some(Linear::load_no_bias(
                    file,
                    &format!("{p}time_embedding.cond_proj"),
                    g,
                    d.text_dim,
                    ty,
                )?),
                None => None,
            },
            latent_io: match (c != e, part.main) {
                (true, true) => Some(LatentIo {
                    pre: lin("latent_pre", c, e)?,
                    post: Some(lin("latent_post", e, c)?),
                }),
                // A ControlNet's output is its blocks' residuals: its `latent_post` is unused.
                (true, false) => Some(LatentIo {
                    pre: lin("latent_pre", c, e)?,
                    post: None,
                }),
                (false, _) => None,
            },
            emb_proj: lin("emb_proj.1", d.text_dim, e)?,
            pe: file.tensor(&format!("{p}query_pos.pe"), &[d.max_len, 1, e])?,
            encoder: SkipStack::load(
                file,
                &format!("{p}encoder."),
                d.layers,
                part.main,
                shape,
                ty,
            )?,
            vae: if part.main {
                Some(VaeDecoder::load(file, &cfg.vae, parts, ty)?)
            } else {
                None
            },
            cfg: cfg.clone(),
            parts,
        })
    }

    /// The sizes the network and its VAE decoder were built from.
    pub fn config(&self) -> &MldFamily {
        &self.cfg
    }

    /// The VAE decoder (`None` for a ControlNet's copy of the denoiser).
    pub fn vae(&self) -> Option<&VaeDecoder> {
        self.vae.as_ref()
    }

    /// The denoiser alone: `x` is `[batch, latent_tokens, latent_dim]`, ε out the same.
    #[allow(clippy::too_many_arguments)]
    pub fn forward_texts(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        texts: &[&[f32]],
        out: &mut [f32],
        ws: &mut MldWorkspace,
        cancel: &Cancel,
    ) -> Result<()> {
        self.forward_guided(x, rows, t, None, texts, None, out, ws, cancel)
    }

    /// [`MldDenoiser::forward_texts`] over latents of `channels` per token, with the guidance
    /// embedding of `w` added to the time sinusoid (MotionLCM: `w` is the scale minus 1;
    /// required exactly when the network has `cond_proj`) and ControlNet residuals
    /// (`[blocks, batch × (latent_tokens + 2), latent_dim]`) added after each block.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn forward_guided(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        w: Option<f32>,
        texts: &[&[f32]],
        residuals: Option<&[f32]>,
        out: &mut [f32],
        ws: &mut MldWorkspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let d = &self.cfg.denoiser;
        let (e, l, batch) = (d.latent_dim, d.latent_tokens, texts.len());
        let c = self.parts.channels;
        if out.len() != batch * l * c {
            return Err(invalid_arg!(
                "forward buffers do not match batch {batch} × {l} latent tokens × {c}"
            ));
        }
        let taps = Taps {
            residuals,
            ..Taps::default()
        };
        self.sequence(x, rows, t, w, texts, taps, ws, cancel)?;
        let seq = l + 2;
        let xs = &ws.x[..batch * seq * e];
        match &self.latent_io {
            Some(LatentIo {
                post: Some(post), ..
            }) => {
                for b in 0..batch {
                    let tokens = &xs[b * seq * e..][..l * e];
                    post.forward(tokens, l, &mut out[b * l * c..(b + 1) * l * c]);
                }
            }
            _ => {
                for b in 0..batch {
                    out[b * l * e..(b + 1) * l * e].copy_from_slice(&xs[b * seq * e..][..l * e]);
                }
            }
        }
        Ok(())
    }

    /// The whole token sequence `[batch, latent_tokens + 2, latent_dim]` after the stack, in
    /// `ws.x`, with `taps` (a ControlNet's copy collects its blocks' outputs through them).
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn sequence(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        w: Option<f32>,
        texts: &[&[f32]],
        taps: Taps<'_>,
        ws: &mut MldWorkspace,
        cancel: &Cancel,
    ) -> Result<()> {
        self.embed_sequence(x, rows, t, w, texts, ws)?;
        let (batch, seq, e) = (
            texts.len(),
            self.cfg.denoiser.latent_tokens + 2,
            self.cfg.denoiser.latent_dim,
        );
        if let Some(r) = taps.residuals {
            let need = self.encoder.blocks() * batch * seq * e;
            if r.len() != need {
                return Err(invalid_arg!(
                    "ControlNet residuals hold {} values, the stack takes {need}",
                    r.len()
                ));
            }
        }
        let xs = &mut ws.x[..batch * seq * e];
        self.encoder
            .forward_taps(xs, batch, seq, &[], 0, taps, &mut ws.stack, cancel)
    }

    /// The stack's input sequence `[batch, latent_tokens + 2, latent_dim]` into `ws.x`: the
    /// latent's tokens (through `latent_pre`), the time token (with the guidance embedding of
    /// `w`) and the text token, plus the learned positions.
    pub(crate) fn embed_sequence(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        w: Option<f32>,
        texts: &[&[f32]],
        ws: &mut MldWorkspace,
    ) -> Result<()> {
        let d = &self.cfg.denoiser;
        let (e, l, batch) = (d.latent_dim, d.latent_tokens, texts.len());
        let c = self.parts.channels;
        if rows != l || x.len() != batch * l * c {
            return Err(invalid_arg!(
                "forward buffers do not match batch {batch} × {l} latent tokens × {c}"
            ));
        }
        if w.is_some() != self.cond_proj.is_some() {
            return Err(invalid_arg!(
                "this network {} a guidance embedding",
                if w.is_some() { "takes no" } else { "needs" }
            ));
        }
        if let Some(v) = texts.iter().find(|v| v.len() != d.text_dim) {
            return Err(invalid_arg!(
                "text vector has {} values, the model expects {}",
                v.len(),
                d.text_dim
            ));
        }
        let seq = l + 2;
        let sin = sized(&mut ws.sinusoid, d.text_dim);
        kernels::sinusoid_cos_first(t, sin);
        if let (Some(proj), Some(w), Some(g)) = (&self.cond_proj, w, self.parts.cond_dim) {
            let emb = sized(&mut ws.guidance, g);
            kernels::guidance_embedding(w, emb);
            let add = sized(&mut ws.hidden, d.text_dim);
            proj.forward(emb, 1, add);
            kernels::add_inplace(sin, add);
        }
        let hidden = sized(&mut ws.hidden, e);
        self.time[0].forward(sin, 1, hidden);
        kernels::silu(hidden);
        let time = sized(&mut ws.time, e);
        self.time[1].forward(hidden, 1, time);
        let texts_in = sized(&mut ws.texts, batch * d.text_dim);
        for (dst, v) in texts_in.chunks_exact_mut(d.text_dim).zip(texts) {
            dst.copy_from_slice(v);
        }
        if self.parts.text_relu {
            kernels::relu(texts_in);
        }
        let text = sized(&mut ws.text, batch * e);
        self.emb_proj.forward(texts_in, batch, text);
        let x = match &self.latent_io {
            Some(io) => {
                let projected = sized(&mut ws.latent_in, batch * l * e);
                io.pre.forward(x, batch * l, projected);
                &*projected
            }
            None => x,
        };
        let xs = sized(&mut ws.x, batch * seq * e);
        let pe = &self.pe.data()[..seq * e];
        for b in 0..batch {
            let blk = &mut xs[b * seq * e..(b + 1) * seq * e];
            blk[..l * e].copy_from_slice(&x[b * l * e..(b + 1) * l * e]);
            blk[l * e..(l + 1) * e].copy_from_slice(time);
            blk[(l + 1) * e..].copy_from_slice(&text[b * e..(b + 1) * e]);
            kernels::add_inplace(blk, pe);
        }
        Ok(())
    }
}

impl Denoiser for MldDenoiser {
    fn sample_dim(&self) -> usize {
        self.parts.channels
    }

    fn reads_sample_directly(&self) -> bool {
        self.parts.channels == self.cfg.denoiser.latent_dim
    }

    /// The latent's tokens, whatever the length.
    fn sample_rows(&self, _frames: usize) -> usize {
        self.cfg.denoiser.latent_tokens
    }

    fn encode_prompt(&self, text: &TextModel, prompt: &str) -> Result<Condition> {
        Ok(Condition::text_vector(text.clip_vector(prompt)?))
    }

    fn unconditional(&self, text: &TextModel, uncond: &str) -> Result<Condition> {
        text_vector_uncond(text, uncond, self.cfg.denoiser.text_dim)
    }

    fn check_condition(&self, cond: &Condition) -> Result<()> {
        check_text_vector(cond, self.cfg.denoiser.text_dim)
    }

    /// As MLD's sampler: guidance mixes only above scale 1 (below, the conditional pass alone).
    fn guidance(&self, scale: f32, _t: f32) -> Guidance {
        if scale > 1.0 {
            Guidance::Mix(scale)
        } else {
            Guidance::Conditional
        }
    }

    fn forward(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        conds: &[&Condition],
        out: &mut [f32],
        ws: &mut Workspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let (texts, n) = text_vector_views(conds)?;
        self.forward_texts(x, rows, t, &texts[..n], out, ws.get(), cancel)
    }

    fn decoder(&self) -> Option<&dyn MotionDecoder> {
        self.vae.as_ref().map(|v| v as &dyn MotionDecoder)
    }

    fn linear_weight_bytes(&self) -> usize {
        self.encoder.weight_bytes()
            + self.time[0].weight_bytes()
            + self.time[1].weight_bytes()
            + self.emb_proj.weight_bytes()
            + self.cond_proj.as_ref().map_or(0, |l| l.weight_bytes())
            + self.latent_io.as_ref().map_or(0, LatentIo::weight_bytes)
            + self.vae.as_ref().map_or(0, VaeDecoder::weight_bytes)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// MLD's VAE decoder.
pub struct VaeDecoder {
    pub(crate) cfg: MldVaeConfig,
    /// `latent_post` (C → D), applied to the latent first (MotionLCM v2).
    pub(crate) latent_post: Option<Linear>,
    pub(crate) channels: usize,
    /// `query_pos_decoder.pe` `[max_len, D]`.
    pub(crate) pe: Tensor,
    pub(crate) decoder: SkipStack<DecoderLayer>,
    pub(crate) final_layer: Linear,
}

/// Reusable buffers of the decoder.
#[derive(Default)]
pub struct VaeWorkspace {
    x: Vec<f32>,
    memory: Vec<f32>,
    stack: StackBuffers,
}

impl VaeDecoder {
    fn load(
        file: &ModelFile,
        v: &MldVaeConfig,
        parts: LatentParts,
        ty: WeightType,
    ) -> Result<VaeDecoder> {
        let e = v.latent_dim;
        let c = parts.channels;
        let shape = LayerShape {
            width: e,
            heads: v.heads,
            ff: v.ff_size,
            act: activation(&v.activation),
            eps: v.layer_norm_eps,
        };
        Ok(VaeDecoder {
            pe: file.tensor("vae.query_pos_decoder.pe", &[v.max_len, 1, e])?,
            decoder: SkipStack::load(file, "vae.decoder.", v.layers, v.final_norm, shape, ty)?,
            final_layer: Linear::load(file, "vae.final_layer", e, v.nfeats, ty)?,
            latent_post: if c != e {
                Some(Linear::load(file, "vae.latent_post", c, e, ty)?)
            } else {
                None
            },
            channels: c,
            cfg: v.clone(),
        })
    }

    fn weight_bytes(&self) -> usize {
        self.decoder.weight_bytes()
            + self.final_layer.weight_bytes()
            + self.latent_post.as_ref().map_or(0, |l| l.weight_bytes())
    }

    /// Whether a latent of `rows` tokens can be decoded into `frames` frames.
    pub(crate) fn check_decode(&self, latent: &[f32], rows: usize, frames: usize) -> Result<()> {
        if frames == 0 || frames > self.cfg.max_len {
            return Err(invalid_arg!(
                "frames must be between 1 and {} for this model, got {frames}",
                self.cfg.max_len
            ));
        }
        if latent.len() != rows * self.channels {
            return Err(invalid_arg!(
                "a latent of {rows} tokens × {} channels has {} values, got {}",
                self.channels,
                rows * self.channels,
                latent.len()
            ));
        }
        Ok(())
    }

    /// The rows the decoder attends to: the latent through `latent_post` (into `buf`), or the
    /// latent itself.
    pub(crate) fn memory<'a>(
        &self,
        latent: &'a [f32],
        rows: usize,
        buf: &'a mut Vec<f32>,
    ) -> &'a [f32] {
        match &self.latent_post {
            Some(post) => {
                let m = sized(buf, rows * self.cfg.latent_dim);
                post.forward(latent, rows, m);
                &*m
            }
            None => latent,
        }
    }

    /// Decodes a latent of `rows` tokens into `frames` frames of features.
    pub fn decode_frames(
        &self,
        latent: &[f32],
        rows: usize,
        frames: usize,
        out: &mut Vec<f32>,
        ws: &mut VaeWorkspace,
    ) -> Result<()> {
        let e = self.cfg.latent_dim;
        self.check_decode(latent, rows, frames)?;
        let memory = self.memory(latent, rows, &mut ws.memory);
        let x = sized(&mut ws.x, frames * e);
        x.copy_from_slice(&self.pe.data()[..frames * e]);
        self.decoder
            .forward(x, 1, frames, memory, rows, &mut ws.stack, &Cancel::never())?;
        let y = sized(out, frames * self.cfg.nfeats);
        self.final_layer.forward(x, frames, y);
        Ok(())
    }
}

impl MotionDecoder for VaeDecoder {
    fn decode(
        &self,
        sample: &[f32],
        rows: usize,
        frames: usize,
        out: &mut Vec<f32>,
        ws: &mut Workspace,
    ) -> Result<usize> {
        self.decode_frames(sample, rows, frames, out, ws.get())?;
        Ok(frames)
    }

    fn decode_recorded(
        &self,
        sample: &[f32],
        rows: usize,
        frames: usize,
        out: &mut Vec<f32>,
        tape: &mut Workspace,
    ) -> Result<()> {
        let tape: &mut VaeTape = tape.get();
        self.decode_recorded_into(sample, rows, frames, out, tape)
    }

    fn decode_vjp(
        &self,
        d_features: &[f32],
        d_sample: &mut [f32],
        tape: &mut Workspace,
    ) -> Result<()> {
        let tape: &mut VaeTape = tape.get();
        self.decode_backward(tape, d_features, d_sample)
    }

    fn summary(&self) -> String {
        format!(
            "MLD VAE decoder, {} layers x {}, {} heads, any length up to {} frames",
            self.cfg.layers, self.cfg.latent_dim, self.cfg.heads, self.cfg.max_len
        )
    }
}
