//! MoLA (Uchida et al. 2024, sony/MoLA): latent diffusion of motion. A stable-audio style diffusion
//! transformer denoises a `[T′, 16]` latent under a CLIP text vector; a convolutional VAE decoder
//! turns the latent into HumanML3D features and a validity flag that decides the motion's length
//! (sony/MoLA `models/t2m_latent_diffusion.py`, `models/transformer.py`, `models/vaesan.py`;
//! docs/official/mola-mld.md#mola-denoiser, docs/official/mola-mld.md#mola-vae-decoder).
//!
//! Denoiser: Fourier time features `[cos f, sin f]`, `f = 2π·t·W`, through an MLP, plus the
//! global-condition MLP of the text vector, make ONE token prepended to the latent frames; the
//! latent goes through a k = 1 residual convolution and a bias-free projection in; pre-LN blocks
//! of bias-free attention with rotary positions on the first `rotary_dim` dims of each head
//! (positions count the prepended token) and a SwiGLU feed-forward; a bias-free projection out,
//! the token dropped, and a k = 1 residual convolution out. It predicts ε.
//!
//! VAE decoder: Conv(k3) → ReLU → `upsample_layers` × [dilated residual blocks → nearest ×2 →
//! Conv(k3)] → Conv(k3) → ReLU → Conv(k3) to the features plus one flag channel. The valid
//! length is the first frame whose sigmoid(flag) is at most `flag_threshold` (at least
//! `min_frames`; all frames above it: every frame but the last).
//!
//! Layout: frame-major `[rows, channels]`; the official tensors are `[B, channels, T′]`.

use std::any::Any;
use std::sync::Arc;

use serde::Deserialize;

use crate::checkpoint::{ModelFile, Tensor};
use crate::config::validate::{
    check_eps, check_layers, expect_flow, expect_shape, expect_text, heads_divide, in_range,
    in_range_f32, refuse_learned_range,
};
use crate::config::{
    section, Config, TextConfig, MAX_FEEDFORWARD, MAX_LAYERS, MAX_MOTION_POSITIONS, MAX_WIDTH,
};
use crate::error::{bad_file, invalid_arg, Result};
use crate::kernels::{self, Activation, AttentionScratch, WeightType};

use super::layers::{rotate_qk, self_attend, sized, Conv1d, Linear};
use super::{
    check_text_vector, text_vector_uncond, text_vector_views, Cancel, Condition, Denoiser, Family,
    FamilyConfig, FeatureLoss, Guidance, MotionDecoder, TextModel, Workspace,
};

/// The family's entry in [`super::FAMILIES`].
pub const FAMILY: Family = Family {
    architectures: &["mola"],
    parse: |arch, v| {
        Ok(Arc::new(MolaFamily {
            denoiser: section(v, arch, "denoiser")?,
            vae: section(v, arch, "vae")?,
        }))
    },
};

/// The diffusion transformer's sizes: the `denoiser` section.
#[derive(Clone, Debug, Deserialize)]
pub struct MolaConfig {
    /// Channels of the latent (16).
    pub latent_channels: usize,
    /// Transformer width (512).
    pub embed_dim: usize,
    /// Transformer blocks (9).
    pub depth: usize,
    /// Attention heads per block; divides `embed_dim` (4, of 128 dimensions each).
    pub num_heads: usize,
    /// Leading dims of each head that rotate (64 of 128).
    pub rotary_dim: usize,
    /// SwiGLU hidden width (2048; the input projection has twice as many outputs).
    pub ff_dim: usize,
    /// Width of the text vector (CLIP's projection, 512).
    pub cond_dim: usize,
    /// Rows of the Fourier weight `[time_features, 1]` (128; the features are twice as many).
    pub time_features: usize,
    /// LayerNorm's epsilon, in (0, 1] (default 1e-5).
    #[serde(default = "ln_eps")]
    pub layer_norm_eps: f32,
    /// The most latent rows a session may ask for.
    pub max_latent_frames: usize,
}

/// The VAE decoder's sizes: the `vae` section.
#[derive(Clone, Debug, Deserialize)]
pub struct MolaVaeConfig {
    /// Channels of the convolutions (512).
    pub width: usize,
    /// Output channels: the features and the flag (264).
    pub output_dim: usize,
    /// Stages of [residual blocks → ×2 → conv] (2: four frames per latent row).
    pub upsample_layers: usize,
    /// Residual blocks per stage (3), dilations `growth^(blocks − 1 − i)`.
    pub res_blocks: usize,
    /// Factor between the dilations of successive residual blocks (3: dilations 9, 3, 1).
    pub dilation_growth: usize,
    /// A frame is valid while sigmoid(flag) is above this (0.999).
    pub flag_threshold: f32,
    /// The shortest valid length (10).
    pub min_frames: usize,
}

fn ln_eps() -> f32 {
    1e-5
}

/// A MoLA file's configuration.
#[derive(Clone, Debug)]
pub struct MolaFamily {
    /// The latent denoiser's sizes (the `denoiser` section).
    pub denoiser: MolaConfig,
    /// The convolutional VAE decoder's sizes (the `vae` section), which turns latent rows into
    /// frames and finds the motion's length.
    pub vae: MolaVaeConfig,
}

/// Longest dilation of a residual block (keeps the padding arithmetic small).
const MAX_DILATION: usize = 4096;

const D: &str = "denoiser.";
const V: &str = "vae.decoder.model.";

impl MolaFamily {
    /// Motion frames per latent row.
    fn factor(&self) -> usize {
        1 << self.vae.upsample_layers
    }

    fn dilations(&self) -> Vec<usize> {
        let g = self.vae.dilation_growth;
        (0..self.vae.res_blocks)
            .map(|i| g.pow((self.vae.res_blocks - 1 - i) as u32))
            .collect()
    }
}

impl FamilyConfig for MolaFamily {
    fn architecture(&self) -> &str {
        "mola"
    }

    fn check(&self, cfg: &Config) -> Result<()> {
        let d = &self.denoiser;
        in_range("denoiser.latent_channels", d.latent_channels, 1, MAX_WIDTH)?;
        in_range("denoiser.embed_dim", d.embed_dim, 2, MAX_WIDTH)?;
        in_range("denoiser.depth", d.depth, 1, MAX_LAYERS)?;
        heads_divide(
            "denoiser.embed_dim",
            d.embed_dim,
            "denoiser.num_heads",
            d.num_heads,
        )?;
        let head = d.embed_dim / d.num_heads;
        in_range("denoiser.rotary_dim", d.rotary_dim, 2, head)?;
        if !d.rotary_dim.is_multiple_of(2) {
            return Err(bad_file!(
                "config denoiser.rotary_dim {} is not even",
                d.rotary_dim
            ));
        }
        in_range("denoiser.ff_dim", d.ff_dim, 1, MAX_FEEDFORWARD / 2)?;
        in_range("denoiser.cond_dim", d.cond_dim, 1, MAX_WIDTH)?;
        in_range("denoiser.time_features", d.time_features, 1, MAX_WIDTH)?;
        check_eps("denoiser.layer_norm_eps", d.layer_norm_eps)?;
        let v = &self.vae;
        in_range("vae.width", v.width, 1, MAX_WIDTH)?;
        in_range("vae.upsample_layers", v.upsample_layers, 1, 4)?;
        in_range(
            "denoiser.max_latent_frames",
            d.max_latent_frames,
            1,
            MAX_MOTION_POSITIONS >> v.upsample_layers,
        )?;
        in_range("vae.res_blocks", v.res_blocks, 1, 16)?;
        in_range("vae.dilation_growth", v.dilation_growth, 1, MAX_DILATION)?;
        if v.dilation_growth
            .checked_pow((v.res_blocks - 1) as u32)
            .is_none_or(|x| x > MAX_DILATION)
        {
            return Err(bad_file!(
                "config vae.dilation_growth {} over {} blocks dilates past {MAX_DILATION} frames",
                v.dilation_growth,
                v.res_blocks
            ));
        }
        in_range_f32("vae.flag_threshold", v.flag_threshold, 0.0, 1.0, true)?;
        in_range("vae.min_frames", v.min_frames, 1, self.max_frames())?;
        expect_text(cfg, &["clip"])?;
        if let TextConfig::Clip(c) = &cfg.text_encoder {
            if c.clip.projection_dim != d.cond_dim {
                return Err(bad_file!(
                    "config text_encoder.projection_dim {} differs from denoiser.cond_dim {}",
                    c.clip.projection_dim,
                    d.cond_dim
                ));
            }
        }
        let features = cfg
            .motion
            .format
            .parse::<crate::motion::Format>()
            .map(|f| f.feature_dim())
            .unwrap_or(0);
        if v.output_dim != features + 1 {
            return Err(bad_file!(
                "config vae.output_dim {} is not motion.format `{}`'s {features} features + the flag",
                v.output_dim,
                cfg.motion.format
            ));
        }
        expect_flow(cfg, false)?;
        refuse_learned_range(cfg)
    }

    fn validate(&self, file: &ModelFile) -> Result<()> {
        let (d, v) = (&self.denoiser, &self.vae);
        let (c, e, tf) = (d.latent_channels, d.embed_dim, d.time_features);
        let shape =
            |name: &str, want: &[usize], fields: &str| expect_shape(file, name, want, fields);
        shape(
            &format!("{D}timestep_features.weight"),
            &[tf, 1],
            "denoiser.time_features",
        )?;
        shape(
            &format!("{D}to_timestep_embed.0.weight"),
            &[e, 2 * tf],
            "denoiser.embed_dim, time_features",
        )?;
        shape(
            &format!("{D}to_global_embed.0.weight"),
            &[e, d.cond_dim],
            "denoiser.embed_dim, cond_dim",
        )?;
        shape(
            &format!("{D}preprocess_conv.weight"),
            &[c, c, 1],
            "denoiser.latent_channels",
        )?;
        shape(
            &format!("{D}transformer.project_in.weight"),
            &[e, c],
            "denoiser.embed_dim, latent_channels",
        )?;
        check_layers(
            file,
            "denoiser.depth",
            d.depth,
            &format!("{D}transformer.layers."),
        )?;
        shape(
            &format!("{D}transformer.layers.0.ff.ff.0.proj.weight"),
            &[2 * d.ff_dim, e],
            "denoiser.ff_dim, embed_dim",
        )?;
        shape(
            &format!("{V}0.weight"),
            &[v.width, c, 3],
            "vae.width, denoiser.latent_channels",
        )?;
        for s in 0..v.upsample_layers {
            check_layers(
                file,
                "vae.res_blocks",
                v.res_blocks,
                &format!("{V}{}.0.model.", 2 + s),
            )?;
        }
        let next = format!("{V}{}.0.", 2 + v.upsample_layers);
        if file.has_prefix(&next) {
            return Err(bad_file!(
                "config vae.upsample_layers is {} but the file also has tensors `{next}*`",
                v.upsample_layers
            ));
        }
        shape(
            &format!("{V}{}.weight", 4 + v.upsample_layers),
            &[v.output_dim, v.width, 3],
            "vae.output_dim, width",
        )
    }

    fn feature_dim(&self) -> usize {
        self.vae.output_dim.saturating_sub(1)
    }

    fn max_frames(&self) -> usize {
        // rows = frames / factor + 1 must stay within max_latent_frames.
        (self.denoiser.max_latent_frames * self.factor()).saturating_sub(1)
    }

    fn summary(&self) -> String {
        let d = &self.denoiser;
        format!(
            "MoLA diffusion transformer, {} blocks x {}, {} heads (rotary on {} dims), SwiGLU {}, latent {} channels",
            d.depth, d.embed_dim, d.num_heads, d.rotary_dim, d.ff_dim, d.latent_channels
        )
    }

    fn load(
        &self,
        file: &ModelFile,
        _cfg: &Config,
        _text: &TextModel,
        ty: WeightType,
    ) -> Result<Box<dyn Denoiser>> {
        Ok(Box::new(MolaDenoiser::load(file, self, ty)?))
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// One pre-LN transformer block.
struct Block {
    pre_norm: Tensor,
    to_qkv: Linear,
    to_out: Linear,
    ff_norm: Tensor,
    ff_in: Linear,
    ff_out: Linear,
}

/// The diffusion transformer and the VAE decoder.
pub struct MolaDenoiser {
    cfg: MolaFamily,
    time_w: Tensor,
    time_embed: [Linear; 2],
    global_embed: [Linear; 2],
    preprocess: Linear,
    postprocess: Linear,
    project_in: Linear,
    project_out: Linear,
    blocks: Vec<Block>,
    /// `10000^(−2i/rotary_dim)`, as the model's `inv_freq` buffer.
    inv_freq: Vec<f32>,
    /// LayerNorm's shift: zero (the official beta is a zero buffer).
    zeros: Vec<f32>,
    vae: VaeDecoder,
}

/// Reusable buffers of the denoiser.
#[derive(Default)]
pub struct MolaWorkspace {
    time: Vec<f32>,
    token: Vec<f32>,
    hidden: Vec<f32>,
    x: Vec<f32>,
    normed: Vec<f32>,
    qkv: Vec<f32>,
    attn: Vec<f32>,
    proj: Vec<f32>,
    ff: Vec<f32>,
    glu: Vec<f32>,
    lat: Vec<f32>,
    out: Vec<f32>,
    cos: Vec<f32>,
    sin: Vec<f32>,
    scratch: AttentionScratch,
}

/// A k = 1 convolution `[c, c, 1]` without bias, as a linear layer.
fn conv1x1(file: &ModelFile, name: &str, c: usize, ty: WeightType) -> Result<Linear> {
    let w = file.tensor(&format!("{name}.weight"), &[c, c, 1])?;
    Ok(Linear::from_weight(w.data(), None, c, c, ty))
}

impl MolaDenoiser {
    /// Reads the tensors (official names, `denoiser.` and `vae.decoder.model.`), in module order.
    pub fn load(file: &ModelFile, cfg: &MolaFamily, ty: WeightType) -> Result<MolaDenoiser> {
        let d = &cfg.denoiser;
        let (c, e, tf) = (d.latent_channels, d.embed_dim, d.time_features);
        let lin =
            |name: &str, n_in, n_out| Linear::load(file, &format!("{D}{name}"), n_in, n_out, ty);
        let nob = |name: &str, n_in, n_out| {
            Linear::load_no_bias(file, &format!("{D}{name}"), n_in, n_out, ty)
        };
        let time_w = file.tensor(&format!("{D}timestep_features.weight"), &[tf, 1])?;
        let time_embed = [
            lin("to_timestep_embed.0", 2 * tf, e)?,
            lin("to_timestep_embed.2", e, e)?,
        ];
        let global_embed = [
            nob("to_global_embed.0", d.cond_dim, e)?,
            nob("to_global_embed.2", e, e)?,
        ];
        let preprocess = conv1x1(file, &format!("{D}preprocess_conv"), c, ty)?;
        let postprocess = conv1x1(file, &format!("{D}postprocess_conv"), c, ty)?;
        let project_in = nob("transformer.project_in", c, e)?;
        let project_out = nob("transformer.project_out", e, c)?;
        let mut blocks = Vec::with_capacity(d.depth);
        for i in 0..d.depth {
            let p = format!("transformer.layers.{i}.");
            blocks.push(Block {
                pre_norm: file.tensor(&format!("{D}{p}pre_norm.gamma"), &[e])?,
                to_qkv: nob(&format!("{p}self_attn.to_qkv"), e, 3 * e)?,
                to_out: nob(&format!("{p}self_attn.to_out"), e, e)?,
                ff_norm: file.tensor(&format!("{D}{p}ff_norm.gamma"), &[e])?,
                ff_in: lin(&format!("{p}ff.ff.0.proj"), e, 2 * d.ff_dim)?,
                ff_out: lin(&format!("{p}ff.ff.2"), d.ff_dim, e)?,
            });
        }
        let r = d.rotary_dim;
        let inv_freq = (0..r / 2)
            .map(|i| 1.0 / 10000f32.powf((2 * i) as f32 / r as f32))
            .collect();
        Ok(MolaDenoiser {
            cfg: cfg.clone(),
            time_w,
            time_embed,
            global_embed,
            preprocess,
            postprocess,
            project_in,
            project_out,
            blocks,
            inv_freq,
            zeros: vec![0.0; e],
            vae: VaeDecoder::load(file, cfg, ty)?,
        })
    }

    /// The sizes the network and its VAE decoder were built from.
    pub fn config(&self) -> &MolaFamily {
        &self.cfg
    }

    /// The VAE decoder.
    pub fn vae(&self) -> &VaeDecoder {
        &self.vae
    }

    /// The denoiser alone: `x` is `[batch, rows, latent_channels]`, ε out in the same shape.
    #[allow(clippy::too_many_arguments)]
    pub fn forward_texts(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        texts: &[&[f32]],
        out: &mut [f32],
        ws: &mut MolaWorkspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let d = &self.cfg.denoiser;
        let (c, e, batch) = (d.latent_channels, d.embed_dim, texts.len());
        if rows == 0 || rows > d.max_latent_frames {
            return Err(invalid_arg!(
                "latent rows must be between 1 and {} for this model, got {rows}",
                d.max_latent_frames
            ));
        }
        if x.len() != batch * rows * c || out.len() != batch * rows * c {
            return Err(invalid_arg!(
                "forward buffers do not match batch {batch} × {rows} latent rows × {c}"
            ));
        }
        if let Some(v) = texts.iter().find(|v| v.len() != d.cond_dim) {
            return Err(invalid_arg!(
                "text vector has {} values, the model expects {}",
                v.len(),
                d.cond_dim
            ));
        }
        let seq = rows + 1;
        let eps = d.layer_norm_eps;

        // The time token: [cos f, sin f] with f = fl32(fl32(2π)·t)·W, then the MLP.
        let tf = d.time_features;
        let time = sized(&mut ws.time, 2 * tf);
        let two_pi_t = std::f32::consts::TAU * t;
        for (i, w) in self.time_w.data().iter().enumerate() {
            let f = two_pi_t * w;
            time[i] = f.cos();
            time[tf + i] = f.sin();
        }
        let hidden = sized(&mut ws.hidden, e);
        self.time_embed[0].forward(time, 1, hidden);
        kernels::silu(hidden);
        let token = sized(&mut ws.token, batch * e);
        self.time_embed[1].forward(hidden, 1, &mut token[..e]);
        let (first, rest) = token.split_at_mut(e);
        for r in rest.chunks_exact_mut(e) {
            r.copy_from_slice(first);
        }
        // Plus the global condition of each row: Linear → SiLU → Linear, no biases.
        let glob = sized(&mut ws.glu, batch * e);
        for (b, text) in texts.iter().enumerate() {
            let h = sized(&mut ws.hidden, e);
            self.global_embed[0].forward(text, 1, h);
            kernels::silu(h);
            self.global_embed[1].forward(h, 1, &mut glob[b * e..(b + 1) * e]);
        }
        kernels::add_inplace(token, glob);

        // x ← x + conv1x1(x); project in; the token in front of the rows.
        let lat = sized(&mut ws.lat, batch * rows * c);
        self.preprocess.forward(x, batch * rows, lat);
        kernels::add_inplace(lat, x);
        let proj = sized(&mut ws.proj, batch * rows * e);
        self.project_in.forward(lat, batch * rows, proj);
        let xs = sized(&mut ws.x, batch * seq * e);
        for b in 0..batch {
            let blk = &mut xs[b * seq * e..(b + 1) * seq * e];
            blk[..e].copy_from_slice(&token[b * e..(b + 1) * e]);
            blk[e..].copy_from_slice(&proj[b * rows * e..(b + 1) * rows * e]);
        }

        self.rotary_tables(seq, ws);
        for block in &self.blocks {
            cancel.check()?;
            self.block(block, batch, seq, eps, ws);
        }

        // Project out, drop the token, x ← x + conv1x1(x).
        let xs = &ws.x;
        let lat = sized(&mut ws.lat, batch * rows * e);
        for b in 0..batch {
            lat[b * rows * e..(b + 1) * rows * e]
                .copy_from_slice(&xs[(b * seq + 1) * e..(b + 1) * seq * e]);
        }
        let o = sized(&mut ws.out, batch * rows * c);
        self.project_out.forward(lat, batch * rows, o);
        self.postprocess.forward(o, batch * rows, out);
        kernels::add_inplace(out, o);
        Ok(())
    }

    /// cos and sin of `position · inv_freq` for positions `0..seq`, `[seq, rotary_dim / 2]`.
    fn rotary_tables(&self, seq: usize, ws: &mut MolaWorkspace) {
        let half = self.inv_freq.len();
        let (cos, sin) = (
            sized(&mut ws.cos, seq * half),
            sized(&mut ws.sin, seq * half),
        );
        for p in 0..seq {
            for (i, f) in self.inv_freq.iter().enumerate() {
                let a = p as f32 * f;
                cos[p * half + i] = a.cos();
                sin[p * half + i] = a.sin();
            }
        }
    }

    /// `x ← x + Attn(LN(x)); x ← x + FF(LN(x))` over `batch` blocks of `seq` rows.
    fn block(&self, blk: &Block, batch: usize, seq: usize, eps: f32, ws: &mut MolaWorkspace) {
        let d = &self.cfg.denoiser;
        let (e, heads) = (d.embed_dim, d.num_heads);
        let hd = e / heads;
        let rows = batch * seq;
        let normed = sized(&mut ws.normed, rows * e);
        normed.copy_from_slice(&ws.x);
        kernels::layer_norm(normed, e, blk.pre_norm.data(), &self.zeros, eps);
        let qkv = sized(&mut ws.qkv, rows * 3 * e);
        blk.to_qkv.forward(normed, rows, qkv);
        // Rotary positions on q and k: pairs (i, i + half) of the first rotary_dim dims.
        rotate_qk(qkv, e, hd, seq, &ws.cos, &ws.sin);
        let attn = sized(&mut ws.attn, rows * e);
        self_attend(&mut ws.scratch, qkv, e, heads, seq, attn);
        let proj = sized(&mut ws.proj, rows * e);
        blk.to_out.forward(attn, rows, proj);
        kernels::add_inplace(&mut ws.x, proj);

        let normed = sized(&mut ws.normed, rows * e);
        normed.copy_from_slice(&ws.x);
        kernels::layer_norm(normed, e, blk.ff_norm.data(), &self.zeros, eps);
        let f = d.ff_dim;
        let ff = sized(&mut ws.ff, rows * 2 * f);
        blk.ff_in.forward(normed, rows, ff);
        // SwiGLU: value · SiLU(gate), value the first half of each row.
        let glu = sized(&mut ws.glu, rows * f);
        for (g, r) in glu.chunks_exact_mut(f).zip(ff.chunks_exact_mut(2 * f)) {
            let (value, gate) = r.split_at_mut(f);
            kernels::silu(gate);
            for ((o, v), s) in g.iter_mut().zip(value.iter()).zip(gate.iter()) {
                *o = v * s;
            }
        }
        let proj = sized(&mut ws.proj, rows * e);
        blk.ff_out.forward(glu, rows, proj);
        kernels::add_inplace(&mut ws.x, proj);
    }

    fn rows_for(&self, frames: usize) -> usize {
        frames / self.cfg.factor() + 1
    }
}

impl Denoiser for MolaDenoiser {
    fn sample_dim(&self) -> usize {
        self.cfg.denoiser.latent_channels
    }

    /// The official rule: `(frames + 4) // 4` latent rows for four frames per row.
    fn sample_rows(&self, frames: usize) -> usize {
        self.rows_for(frames)
    }

    fn encode_prompt(&self, text: &TextModel, prompt: &str) -> Result<Condition> {
        Ok(Condition::text_vector(text.clip_vector(prompt)?))
    }

    fn unconditional(&self, text: &TextModel, uncond: &str) -> Result<Condition> {
        text_vector_uncond(text, uncond, self.cfg.denoiser.cond_dim)
    }

    fn check_condition(&self, cond: &Condition) -> Result<()> {
        check_text_vector(cond, self.cfg.denoiser.cond_dim)
    }

    /// As the official sampler: scale 0 or exactly 1 runs the conditional pass alone.
    fn guidance(&self, scale: f32, _t: f32) -> Guidance {
        if scale == 0.0 || scale == 1.0 {
            Guidance::Conditional
        } else {
            Guidance::Mix(scale)
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
        Some(&self.vae)
    }

    fn linear_weight_bytes(&self) -> usize {
        let blocks: usize = self
            .blocks
            .iter()
            .map(|b| {
                b.to_qkv.weight_bytes()
                    + b.to_out.weight_bytes()
                    + b.ff_in.weight_bytes()
                    + b.ff_out.weight_bytes()
            })
            .sum();
        blocks
            + [
                &self.time_embed[0],
                &self.time_embed[1],
                &self.global_embed[0],
                &self.global_embed[1],
                &self.preprocess,
                &self.postprocess,
                &self.project_in,
                &self.project_out,
            ]
            .iter()
            .map(|l| l.weight_bytes())
            .sum::<usize>()
            + self.vae.weight_bytes()
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// One residual block: `x + conv2(ReLU(conv1(ReLU(x))))`, conv1 dilated k3, conv2 k1.
struct ResBlock {
    conv1: Conv1d,
    conv2: Conv1d,
}

/// The VAE decoder of MoLA (ReLU throughout, as the released text-to-motion inference).
pub struct VaeDecoder {
    cfg: MolaVaeConfig,
    first: Conv1d,
    /// Per stage: residual blocks, then the conv after the ×2 upsampling.
    stages: Vec<(Vec<ResBlock>, Conv1d)>,
    last_hidden: Conv1d,
    out: Conv1d,
}

/// Reusable buffers of the decoder.
#[derive(Default)]
pub struct VaeWorkspace {
    x: Vec<f32>,
    h: Vec<f32>,
    h2: Vec<f32>,
    cols: Vec<f32>,
    out: Vec<f32>,
}

/// Buffers of [`VaeDecoder::backward`]: the saved activations and the gradients.
#[derive(Default)]
pub struct VaeGradWorkspace {
    saved: Vec<Vec<f32>>,
    x: Vec<f32>,
    h: Vec<f32>,
    g: Vec<f32>,
    g2: Vec<f32>,
    cols: Vec<f32>,
    features: Vec<f32>,
}

impl VaeDecoder {
    fn load(file: &ModelFile, cfg: &MolaFamily, ty: WeightType) -> Result<VaeDecoder> {
        let v = &cfg.vae;
        let w = v.width;
        let conv = |name: String, n_in, n_out, k, dil| {
            Conv1d::load(file, &format!("{V}{name}"), n_in, n_out, k, dil, true, ty)
        };
        let first = conv("0".into(), cfg.denoiser.latent_channels, w, 3, 1)?;
        let dilations = cfg.dilations();
        let mut stages = Vec::with_capacity(v.upsample_layers);
        for s in 0..v.upsample_layers {
            let m = 2 + s;
            let mut blocks = Vec::with_capacity(v.res_blocks);
            for (i, &dil) in dilations.iter().enumerate() {
                blocks.push(ResBlock {
                    conv1: conv(format!("{m}.0.model.{i}.conv1"), w, w, 3, dil)?,
                    conv2: conv(format!("{m}.0.model.{i}.conv2"), w, w, 1, 1)?,
                });
            }
            stages.push((blocks, conv(format!("{m}.2"), w, w, 3, 1)?));
        }
        let n = 2 + v.upsample_layers;
        Ok(VaeDecoder {
            cfg: v.clone(),
            first,
            stages,
            last_hidden: conv(format!("{n}"), w, w, 3, 1)?,
            out: conv(format!("{}", n + 2), w, v.output_dim, 3, 1)?,
        })
    }

    fn weight_bytes(&self) -> usize {
        let stages: usize = self
            .stages
            .iter()
            .map(|(blocks, up)| {
                up.weight_bytes()
                    + blocks
                        .iter()
                        .map(|b| b.conv1.weight_bytes() + b.conv2.weight_bytes())
                        .sum::<usize>()
            })
            .sum();
        stages
            + self.first.weight_bytes()
            + self.last_hidden.weight_bytes()
            + self.out.weight_bytes()
    }

    /// The decoder's raw output `[rows · 2^upsample_layers, output_dim]` (features and flag).
    pub fn decode_raw<'w>(
        &self,
        latent: &[f32],
        rows: usize,
        ws: &'w mut VaeWorkspace,
    ) -> &'w [f32] {
        let VaeWorkspace {
            x,
            h,
            h2,
            cols,
            out,
        } = ws;
        let t = self.forward(latent, rows, [x, h, h2, cols, out], None);
        &out[..t * self.cfg.output_dim]
    }

    /// The decoder's forward pass into `out` (buffers `[x, h, h2, cols, out]`); returns the
    /// decoded frames. With `saved`, it keeps what [`VaeDecoder::backward`] needs, in order:
    /// the first conv's output, per residual block its input and its inner ReLU's output, the
    /// last hidden ReLU's output.
    fn forward(
        &self,
        latent: &[f32],
        rows: usize,
        [x, h, h2, cols, out]: [&mut Vec<f32>; 5],
        mut saved: Option<&mut [Vec<f32>]>,
    ) -> usize {
        let w = self.cfg.width;
        let mut slot = 0;
        let mut keep = |v: &[f32]| {
            if let Some(s) = saved.as_deref_mut() {
                s[slot].clear();
                s[slot].extend_from_slice(v);
            }
            slot += 1;
        };
        self.first.forward(latent, rows, x, cols, Activation::Relu);
        keep(x);
        let mut t = rows;
        for (blocks, up) in &self.stages {
            for b in blocks {
                keep(&x[..t * w]);
                h.clear();
                h.extend_from_slice(&x[..t * w]);
                kernels::relu(h);
                b.conv1.forward(h, t, h2, cols, Activation::Relu);
                keep(h2);
                b.conv2.forward(h2, t, h, cols, Activation::None);
                kernels::add_inplace(&mut x[..t * w], &h[..t * w]);
            }
            // Nearest ×2: every frame twice.
            let hh = sized(h, 2 * t * w);
            for (i, f) in x[..t * w].chunks_exact(w).enumerate() {
                hh[2 * i * w..(2 * i + 1) * w].copy_from_slice(f);
                hh[(2 * i + 1) * w..(2 * i + 2) * w].copy_from_slice(f);
            }
            t *= 2;
            up.forward(h, t, x, cols, Activation::None);
        }
        self.last_hidden.forward(x, t, h, cols, Activation::Relu);
        keep(h);
        self.out.forward(h, t, out, cols, Activation::None);
        t
    }

    /// The decoder's reverse-mode product (MPGD, docs/official/mola-mld.md#mola-mpgd-editing): a
    /// forward pass that keeps each
    /// activation the backward needs, `loss` on the features of every decoded frame (flag
    /// dropped: its gradient is 0), then the chain backwards — conv transposes, ReLU masks, the
    /// residual sums and the ×2 upsampling's pair sums — into `d_sample` (`[rows,
    /// latent_channels]`).
    pub fn backward(
        &self,
        latent: &[f32],
        rows: usize,
        loss: &mut FeatureLoss,
        d_sample: &mut Vec<f32>,
        ws: &mut VaeGradWorkspace,
    ) -> Result<()> {
        let w = self.cfg.width;
        let od = self.cfg.output_dim;
        let VaeGradWorkspace {
            saved,
            x,
            h,
            g,
            g2,
            cols,
            features,
        } = ws;
        let blocks: usize = self.stages.iter().map(|(b, _)| b.len()).sum();
        saved.resize_with(2 * blocks + 2, Vec::new);
        let mut t = self.forward(latent, rows, [x, g2, g, cols, h], Some(saved));

        // The loss on the features; the flag channel's gradient is 0.
        let fd = od - 1;
        features.clear();
        for f in h[..t * od].chunks_exact(od) {
            features.extend_from_slice(&f[..fd]);
        }
        g.clear();
        g.resize(t * fd, 0.0);
        loss(features, t, g)?;
        let d_raw = sized(g2, t * od);
        for (d, s) in d_raw.chunks_exact_mut(od).zip(g.chunks_exact(fd)) {
            d[..fd].copy_from_slice(s);
            d[fd] = 0.0;
        }

        // Backward.
        let mut saved = saved.iter().rev();
        self.out.backward_input(g2, t, g, cols);
        crate::grad::relu_backward(saved.next().expect("saved"), g);
        self.last_hidden.backward_input(g, t, g2, cols);
        // g2 = d(x) at the last stage's output.
        for (stage_blocks, up) in self.stages.iter().rev() {
            up.backward_input(g2, t, g, cols);
            t /= 2;
            crate::grad::upsample_nearest2_backward(g, t, w, g2);
            for b in stage_blocks.iter().rev() {
                let inner = saved.next().expect("saved");
                let input = saved.next().expect("saved");
                b.conv2.backward_input(g2, t, g, cols);
                crate::grad::relu_backward(inner, g);
                b.conv1.backward_input(g, t, x, cols);
                crate::grad::relu_backward(input, x);
                kernels::add_inplace(&mut g2[..t * w], &x[..t * w]);
            }
        }
        crate::grad::relu_backward(saved.next().expect("saved"), g2);
        self.first.backward_input(g2, rows, d_sample, cols);
        Ok(())
    }

    /// The valid length of a raw output of `frames` frames (see the module comment).
    pub fn valid_frames(&self, raw: &[f32], frames: usize) -> usize {
        let od = self.cfg.output_dim;
        let cut = raw
            .chunks_exact(od)
            .take(frames)
            .position(|f| sigmoid(f[od - 1]) <= self.cfg.flag_threshold)
            .unwrap_or(frames.saturating_sub(1));
        cut.max(self.cfg.min_frames).min(frames)
    }
}

fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

impl MotionDecoder for VaeDecoder {
    fn decode(
        &self,
        sample: &[f32],
        rows: usize,
        _frames: usize,
        out: &mut Vec<f32>,
        ws: &mut Workspace,
    ) -> Result<usize> {
        let frames = rows << self.cfg.upsample_layers;
        let od = self.cfg.output_dim;
        let raw = self.decode_raw(sample, rows, ws.get());
        let valid = self.valid_frames(raw, frames);
        out.clear();
        for f in raw.chunks_exact(od).take(valid) {
            out.extend_from_slice(&f[..od - 1]);
        }
        Ok(valid)
    }

    fn has_vjp(&self) -> bool {
        true
    }

    fn vjp(
        &self,
        sample: &[f32],
        rows: usize,
        loss: &mut FeatureLoss,
        d_sample: &mut Vec<f32>,
        ws: &mut Workspace,
    ) -> Result<()> {
        self.backward(sample, rows, loss, d_sample, ws.get())
    }

    fn summary(&self) -> String {
        format!(
            "MoLA VAE decoder, {} wide, {} x2 stages of {} residual blocks; length from the flag (sigmoid <= {}, at least {} frames)",
            self.cfg.width,
            self.cfg.upsample_layers,
            self.cfg.res_blocks,
            self.cfg.flag_threshold,
            self.cfg.min_frames
        )
    }
}
