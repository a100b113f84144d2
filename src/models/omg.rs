//! OMG-style models (Liang et al., CVPR 2024, "Towards Open-vocabulary Motion Generation via
//! Mixture of Controllers"): an unconditional diffusion transformer pre-trained on motion alone,
//! and a motion ControlNet that adds text through a Mixture-of-Controllers (the paper, sections 3.1
//! and 3.2; docs/official/omg.md#code-availability). No official code or weights exist: the layout
//! is libflame's, defined by tools/reference/omg.py; every detail the paper leaves open is a
//! configuration field (docs/omg.md lists each choice).
//!
//! - Backbone D_u (DiT with rotary positions): one token per frame, a timestep MLP giving `c`,
//!   adaLN-Zero blocks (LayerNorm without affine; shift, scale and gate for attention and MLP
//!   from SiLU(c)), attention with RoPE on q and k and no absolute positions, an MLP d → 2d → d,
//!   a final adaLN and a linear layer predicting x0.
//! - ControlNet D_c: every block has a trainable copy reading the block's input; its output goes
//!   down to `control_dim` channels, through the MoC block, back up, and is added to the frozen
//!   block's output (zero up-projections give exactly D_u).
//! - MoC: cross-attention from the motion to the text tokens (softmax over tokens), Ada-IN from
//!   the end-of-text feature, and per text token an expert whose PARAMETERS are a softmax blend
//!   of the pool's (the blend depends on the text only: made once per prompt); the token's
//!   residual is masked to the frames that attend to it, and the residuals are summed.
//! - Guidance: x̂0 = D_u + s·(D_c − D_u) (the unconditional branch is the backbone alone).
//!
//! Layout: frame-major `[frames, channels]`.

use std::any::Any;
use std::sync::Arc;

use rayon::prelude::*;
use serde::Deserialize;

use crate::checkpoint::ModelFile;
use crate::config::validate::{
    check_eps, check_layers, expect_flow, expect_shape, expect_text, heads_divide, in_range,
    in_range_f32, one_of, refuse_learned_range,
};
use crate::config::{section, Config, TextConfig, MAX_FEEDFORWARD, MAX_LAYERS, MAX_WIDTH};
use crate::error::{bad_file, invalid_arg, Result};
use crate::kernels::{self, Activation, AttentionScratch, WeightType};

use super::layers::{rotate_qk, self_attend, sized, transpose, Conv1d, Linear};
use super::{Cancel, Condition, Denoiser, Family, FamilyConfig, TextModel, Workspace, MAX_BATCH};

/// The family's entry in [`super::FAMILIES`].
pub const FAMILY: Family = Family {
    architectures: &["omg"],
    parse: |arch, v| {
        Ok(Arc::new(OmgFamily {
            denoiser: section(v, arch, "denoiser")?,
        }))
    },
};

/// The `denoiser` section (OMG-Base in parentheses; see docs/omg.md).
#[derive(Clone, Debug, Deserialize)]
pub struct OmgConfig {
    /// Features per frame (the motion format's).
    pub input_feats: usize,
    /// Width (1024).
    pub d_model: usize,
    /// Transformer blocks (8).
    pub layers: usize,
    /// Attention heads (8; head dim 128).
    pub heads: usize,
    /// MLP hidden width (2 × d_model).
    pub ff_size: usize,
    /// Dims of the timestep sinusoid (256).
    pub time_freq_dim: usize,
    /// RoPE base (10000): inverse frequencies `rope_base^(−2i/rope_dims)`.
    pub rope_base: f32,
    /// How many leading dims of each head rotate (even, at most the head dim; all of them).
    pub rope_dims: usize,
    /// LayerNorm eps (1e-6, DiT's).
    pub norm_eps: f32,
    /// `gelu_tanh` (DiT's) or `gelu` (exact).
    pub mlp_activation: String,
    /// The most frames a generation may have (300: 10 s at 30 fps, as trained).
    pub max_frames: usize,
    /// The ControlNet; `None` for a backbone-only file (unconditional generation only).
    #[serde(default)]
    pub control: Option<ControlConfig>,
}

/// The ControlNet's and MoC's sizes and choices.
#[derive(Clone, Debug, Deserialize)]
pub struct ControlConfig {
    /// d_m (256).
    pub control_dim: usize,
    /// Width of the text tokens' features (CLIP ViT-L/14: 768).
    pub text_dim: usize,
    /// Kernel of the down- and up-projections (odd; 1).
    pub conv_kernel: usize,
    /// Heads of the MoC cross-attention (1: the paper's single-head equation).
    pub attn_heads: usize,
    /// K (12).
    pub experts: usize,
    /// Hidden width of each expert (2 × control_dim).
    pub expert_hidden: usize,
    /// `gelu`, `gelu_tanh` or `silu`.
    pub expert_activation: String,
    /// Hidden width of the 3-layer gating MLP.
    pub gate_hidden: usize,
    /// The gating MLP's activation: `gelu`, `gelu_tanh` or `silu` (the paper does not say;
    /// docs/official/omg.md#mixture-of-controllers-block).
    pub gate_activation: String,
    /// γ and β of the attention mask M_i = sigmoid(γ·(A_i − β·max over frames of A_i)):
    /// γ (24) sets how sharp the mask is.
    pub mask_gamma: f32,
    /// β (0.25): the share of a token's peak attention above which frames are mostly kept.
    pub mask_beta: f32,
    /// The epsilon added to the variance in the AdaIN that normalises each channel over time.
    pub adain_eps: f32,
    /// Whether the text tokens include the padding after end-of-text (false: SOT…EOT).
    pub text_padding: bool,
}

/// An OMG file's configuration.
#[derive(Clone, Debug)]
pub struct OmgFamily {
    /// The backbone's and, when present, the ControlNet's sizes (the `denoiser` section).
    pub denoiser: OmgConfig,
}

const D: &str = "denoiser.";
const ACTIVATIONS: &[&str] = &["gelu_tanh", "gelu"];
/// Expert and gate activations (the paper suggests GELU or SiLU).
const MOC_ACTIVATIONS: &[&str] = &["gelu", "gelu_tanh", "silu"];

impl FamilyConfig for OmgFamily {
    fn architecture(&self) -> &str {
        "omg"
    }

    fn check(&self, cfg: &Config) -> Result<()> {
        let d = &self.denoiser;
        in_range("denoiser.input_feats", d.input_feats, 1, MAX_WIDTH)?;
        in_range("denoiser.d_model", d.d_model, 2, MAX_WIDTH)?;
        in_range("denoiser.layers", d.layers, 1, MAX_LAYERS)?;
        heads_divide("denoiser.d_model", d.d_model, "denoiser.heads", d.heads)?;
        let hd = d.d_model / d.heads;
        in_range("denoiser.rope_dims", d.rope_dims, 0, hd)?;
        if !d.rope_dims.is_multiple_of(2) {
            return Err(bad_file!(
                "config denoiser.rope_dims {} is not even",
                d.rope_dims
            ));
        }
        in_range_f32("denoiser.rope_base", d.rope_base, 1.0, 1e9, false)?;
        in_range("denoiser.ff_size", d.ff_size, 1, MAX_FEEDFORWARD)?;
        in_range("denoiser.time_freq_dim", d.time_freq_dim, 2, MAX_WIDTH)?;
        if !d.time_freq_dim.is_multiple_of(2) {
            return Err(bad_file!(
                "config denoiser.time_freq_dim {} is not even",
                d.time_freq_dim
            ));
        }
        check_eps("denoiser.norm_eps", d.norm_eps)?;
        one_of("denoiser.mlp_activation", &d.mlp_activation, ACTIVATIONS)?;
        in_range("denoiser.max_frames", d.max_frames, 1, 4096)?;
        if let Some(c) = &d.control {
            in_range("denoiser.control.control_dim", c.control_dim, 1, MAX_WIDTH)?;
            in_range("denoiser.control.text_dim", c.text_dim, 1, MAX_WIDTH)?;
            in_range("denoiser.control.conv_kernel", c.conv_kernel, 1, 63)?;
            if c.conv_kernel.is_multiple_of(2) {
                return Err(bad_file!(
                    "config denoiser.control.conv_kernel {} is not odd (same padding)",
                    c.conv_kernel
                ));
            }
            heads_divide(
                "denoiser.control.control_dim",
                c.control_dim,
                "denoiser.control.attn_heads",
                c.attn_heads,
            )?;
            in_range("denoiser.control.experts", c.experts, 1, 1024)?;
            in_range(
                "denoiser.control.expert_hidden",
                c.expert_hidden,
                1,
                MAX_FEEDFORWARD,
            )?;
            in_range("denoiser.control.gate_hidden", c.gate_hidden, 1, MAX_WIDTH)?;
            one_of(
                "denoiser.control.expert_activation",
                &c.expert_activation,
                MOC_ACTIVATIONS,
            )?;
            one_of(
                "denoiser.control.gate_activation",
                &c.gate_activation,
                MOC_ACTIVATIONS,
            )?;
            in_range_f32(
                "denoiser.control.mask_gamma",
                c.mask_gamma,
                -1e4,
                1e4,
                false,
            )?;
            in_range_f32("denoiser.control.mask_beta", c.mask_beta, -1e4, 1e4, false)?;
            check_eps("denoiser.control.adain_eps", c.adain_eps)?;
            expect_text(cfg, &["clip"])?;
            if let TextConfig::Clip(t) = &cfg.text_encoder {
                if t.clip.width != c.text_dim {
                    return Err(bad_file!(
                        "config text_encoder.width {} differs from denoiser.control.text_dim {}",
                        t.clip.width,
                        c.text_dim
                    ));
                }
            }
        }
        if cfg.diffusion.uncond != "backbone" {
            return Err(bad_file!(
                "config diffusion.uncond `{}`: the unconditional branch of an OMG-style model is its backbone (`backbone`)",
                cfg.diffusion.uncond
            ));
        }
        expect_flow(cfg, false)?;
        refuse_learned_range(cfg)
    }

    fn validate(&self, file: &ModelFile) -> Result<()> {
        let d = &self.denoiser;
        let (f, e) = (d.input_feats, d.d_model);
        let shape =
            |name: &str, want: &[usize], fields: &str| expect_shape(file, name, want, fields);
        shape(
            &format!("{D}x_embed.weight"),
            &[e, f],
            "denoiser.d_model, input_feats",
        )?;
        shape(
            &format!("{D}t_embed.mlp.0.weight"),
            &[e, d.time_freq_dim],
            "denoiser.d_model, time_freq_dim",
        )?;
        check_layers(file, "denoiser.layers", d.layers, &format!("{D}blocks."))?;
        shape(
            &format!("{D}blocks.0.mlp.fc1.weight"),
            &[d.ff_size, e],
            "denoiser.ff_size, d_model",
        )?;
        shape(
            &format!("{D}final_layer.linear.weight"),
            &[f, e],
            "denoiser.input_feats, d_model",
        )?;
        match &d.control {
            None => {
                if file.has_prefix(&format!("{D}control.")) {
                    return Err(bad_file!(
                        "config denoiser.control is null but the file has `{D}control.*` tensors"
                    ));
                }
            }
            Some(c) => {
                check_layers(
                    file,
                    "denoiser.layers (ControlNet copies)",
                    d.layers,
                    &format!("{D}control.blocks."),
                )?;
                let m = c.control_dim;
                shape(
                    &format!("{D}control.down.0.weight"),
                    &[m, e, c.conv_kernel],
                    "denoiser.control.control_dim, d_model, conv_kernel",
                )?;
                shape(
                    &format!("{D}control.moc.0.k.weight"),
                    &[m, c.text_dim],
                    "denoiser.control.control_dim, text_dim",
                )?;
                shape(
                    &format!("{D}control.moc.0.experts.w0"),
                    &[c.experts, m, c.expert_hidden],
                    "denoiser.control.experts, control_dim, expert_hidden",
                )?;
                shape(
                    &format!("{D}control.moc.0.gate.0.weight"),
                    &[c.gate_hidden, c.text_dim],
                    "denoiser.control.gate_hidden, text_dim",
                )?;
            }
        }
        Ok(())
    }

    fn feature_dim(&self) -> usize {
        self.denoiser.input_feats
    }

    fn max_frames(&self) -> usize {
        self.denoiser.max_frames
    }

    fn unconditional_inputs(&self) -> &'static [&'static str] {
        &["backbone"]
    }

    fn summary(&self) -> String {
        let d = &self.denoiser;
        let control = match &d.control {
            Some(c) => format!(
                "ControlNet on every block, MoC {} experts x {} ({}; gate MLP {} wide, {}), d_m {}, {} attention head(s), conv k{}, mask gamma {} beta {}, Ada-IN eps {}, text {} ({})",
                c.experts,
                c.expert_hidden,
                c.expert_activation,
                c.gate_hidden,
                c.gate_activation,
                c.control_dim,
                c.attn_heads,
                c.conv_kernel,
                c.mask_gamma,
                c.mask_beta,
                c.adain_eps,
                c.text_dim,
                if c.text_padding { "all 77 positions" } else { "SOT..EOT" }
            ),
            None => "backbone only (unconditional)".into(),
        };
        format!(
            "OMG-style DiT, {} blocks x {}, {} heads (RoPE base {} on {} dims), MLP {} ({}), LayerNorm eps {}, time sinusoid {}, up to {} frames; {control}",
            d.layers,
            d.d_model,
            d.heads,
            d.rope_base,
            d.rope_dims,
            d.ff_size,
            d.mlp_activation,
            d.norm_eps,
            d.time_freq_dim,
            d.max_frames
        )
    }

    fn load(
        &self,
        file: &ModelFile,
        _cfg: &Config,
        _text: &TextModel,
        ty: WeightType,
    ) -> Result<Box<dyn Denoiser>> {
        Ok(Box::new(OmgDenoiser::load(file, self, ty)?))
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// An activation of the configuration, in place: `gelu` (exact), `gelu_tanh` or `silu`.
fn activate(x: &mut [f32], name: &str) {
    match name {
        "gelu_tanh" => kernels::gelu_tanh(x),
        "silu" => kernels::silu(x),
        _ => kernels::gelu_erf(x),
    }
}

/// One adaLN-Zero DiT block.
struct Block {
    modulation: Linear,
    qkv: Linear,
    proj: Linear,
    fc1: Linear,
    fc2: Linear,
}

impl Block {
    fn load(file: &ModelFile, p: &str, d: &OmgConfig, ty: WeightType) -> Result<Block> {
        let e = d.d_model;
        let lin =
            |name: &str, n_in, n_out| Linear::load(file, &format!("{p}.{name}"), n_in, n_out, ty);
        Ok(Block {
            modulation: lin("adaLN_modulation.1", e, 6 * e)?,
            qkv: lin("attn.qkv", e, 3 * e)?,
            proj: lin("attn.proj", e, e)?,
            fc1: lin("mlp.fc1", e, d.ff_size)?,
            fc2: lin("mlp.fc2", d.ff_size, e)?,
        })
    }

    fn weight_bytes(&self) -> usize {
        [
            &self.modulation,
            &self.qkv,
            &self.proj,
            &self.fc1,
            &self.fc2,
        ]
        .iter()
        .map(|l| l.weight_bytes())
        .sum()
    }
}

/// The MoC block of one layer: what does not depend on the prompt.
struct Moc {
    q: Linear,
    k: Linear,
    v: Linear,
    gamma: Linear,
    beta: Linear,
    /// The expert pool, one row per expert `[K, pool_row]`: W0ᵀ `[hidden, d_m]` (fc1's
    /// `[out, in]`), W1ᵀ `[d_m, hidden]`, b0 `[hidden]`, b1 `[d_m]`. Blending is linear, so
    /// the tokens' blended parameters are one product `ω [n, K] · pool`, read once per prompt.
    pool: Vec<f32>,
    gate: [Linear; 3],
}

struct ControlLayer {
    block: Block,
    down: Conv1d,
    moc: Moc,
    up: Conv1d,
}

/// The network.
pub struct OmgDenoiser {
    cfg: OmgConfig,
    ty: WeightType,
    x_embed: Linear,
    t_embed: [Linear; 2],
    blocks: Vec<Block>,
    final_modulation: Linear,
    final_linear: Linear,
    control: Option<Vec<ControlLayer>>,
    /// `base^(−2i/r)`, in f64: the tables are rounded to f32 once.
    inv_freq: Vec<f64>,
    unit: UnitNorm,
}

/// One token's blended expert: `act(x·W0 + b0)·W1 + b1` as two layers.
struct BlendedExpert {
    fc1: Linear,
    fc2: Linear,
}

/// What a prompt gives one ControlNet layer.
struct LayerText {
    /// `[n, d_m]` projections of the text tokens.
    k: Vec<f32>,
    v: Vec<f32>,
    /// Ada-IN's γ and β from the end-of-text feature, `[d_m]`.
    gamma: Vec<f32>,
    beta: Vec<f32>,
    experts: Vec<BlendedExpert>,
}

/// An OMG condition: the text tokens and, per ControlNet layer, what depends on them alone.
pub struct OmgCondition {
    /// Text tokens' CLIP features `[n, text_dim]`.
    pub tokens: Vec<f32>,
    n: usize,
    layers: Vec<LayerText>,
}

impl OmgCondition {
    /// Text tokens the ControlNet attends to.
    pub fn token_count(&self) -> usize {
        self.n
    }
}

/// The unconditional branch: the backbone alone.
#[derive(Clone, Copy, Debug)]
pub struct OmgBackbone;

/// Buffers of a forward pass.
#[derive(Default)]
pub struct OmgWorkspace {
    t: Vec<f32>,
    c: Vec<f32>,
    mods: Vec<f32>,
    h: Vec<f32>,
    h_in: Vec<f32>,
    normed: Vec<f32>,
    qkv: Vec<f32>,
    attn: Vec<f32>,
    proj: Vec<f32>,
    ff: Vec<f32>,
    g: Vec<f32>,
    f: Vec<f32>,
    cols: Vec<f32>,
    q: Vec<f32>,
    scores: Vec<f32>,
    av: Vec<f32>,
    mask: Vec<f32>,
    hidden: Vec<f32>,
    out: Vec<f32>,
    r: Vec<f32>,
    up: Vec<f32>,
    cos: Vec<f32>,
    sin: Vec<f32>,
    scratch: AttentionScratch,
}

impl OmgDenoiser {
    /// Reads the tensors (under `denoiser.`) and builds the network, linear weights held as
    /// `ty`; the configuration has been validated against the file.
    pub fn load(file: &ModelFile, fam: &OmgFamily, ty: WeightType) -> Result<OmgDenoiser> {
        let d = &fam.denoiser;
        let (f, e) = (d.input_feats, d.d_model);
        let lin =
            |name: &str, n_in, n_out| Linear::load(file, &format!("{D}{name}"), n_in, n_out, ty);
        let blocks = (0..d.layers)
            .map(|i| Block::load(file, &format!("{D}blocks.{i}"), d, ty))
            .collect::<Result<Vec<_>>>()?;
        let control = match &d.control {
            None => None,
            Some(c) => {
                let (m, dt, k, x, h) = (
                    c.control_dim,
                    c.text_dim,
                    c.conv_kernel,
                    c.experts,
                    c.expert_hidden,
                );
                let mut layers = Vec::with_capacity(d.layers);
                for i in 0..d.layers {
                    let p = format!("{D}control.moc.{i}");
                    let ml = |name: &str, n_in, n_out| {
                        Linear::load(file, &format!("{p}.{name}"), n_in, n_out, ty)
                    };
                    layers.push(ControlLayer {
                        block: Block::load(file, &format!("{D}control.blocks.{i}"), d, ty)?,
                        down: Conv1d::load(
                            file,
                            &format!("{D}control.down.{i}"),
                            e,
                            m,
                            k,
                            1,
                            true,
                            ty,
                        )?,
                        moc: Moc {
                            q: ml("q", m, m)?,
                            k: ml("k", dt, m)?,
                            v: ml("v", dt, m)?,
                            gamma: ml("adain.gamma", dt, m)?,
                            beta: ml("adain.beta", dt, m)?,
                            pool: expert_pool(file, &format!("{p}.experts"), x, m, h)?,
                            gate: [
                                ml("gate.0", dt, c.gate_hidden)?,
                                ml("gate.2", c.gate_hidden, c.gate_hidden)?,
                                ml("gate.4", c.gate_hidden, x)?,
                            ],
                        },
                        up: Conv1d::load(
                            file,
                            &format!("{D}control.up.{i}"),
                            m,
                            e,
                            k,
                            1,
                            true,
                            ty,
                        )?,
                    });
                }
                Some(layers)
            }
        };
        let r = d.rope_dims;
        let inv_freq = (0..r / 2)
            .map(|i| (d.rope_base as f64).powf(-((2 * i) as f64) / r as f64))
            .collect();
        Ok(OmgDenoiser {
            cfg: d.clone(),
            ty,
            x_embed: lin("x_embed", f, e)?,
            t_embed: [
                lin("t_embed.mlp.0", d.time_freq_dim, e)?,
                lin("t_embed.mlp.2", e, e)?,
            ],
            blocks,
            final_modulation: lin("final_layer.adaLN_modulation.1", e, 2 * e)?,
            final_linear: lin("final_layer.linear", e, f)?,
            control,
            inv_freq,
            unit: UnitNorm {
                ones: vec![1.0; e],
                zeros: vec![0.0; e],
            },
        })
    }

    /// The sizes the network was built from.
    pub fn config(&self) -> &OmgConfig {
        &self.cfg
    }

    /// Whether the file has a ControlNet (else it generates unconditionally only).
    pub fn has_control(&self) -> bool {
        self.control.is_some()
    }

    /// The text tokens' CLIP features `[n, text_dim]` and the end-of-text feature.
    pub fn text_tokens(&self, text: &TextModel, prompt: &str) -> Result<(Vec<f32>, usize)> {
        let (TextModel::Clip { encoder, context }, Some(c)) = (text, &self.cfg.control) else {
            return Err(invalid_arg!("this model has no text path"));
        };
        let out = if c.text_padding {
            encoder.encode(prompt, *context)?
        } else {
            encoder.encode_through_end(prompt, *context)?
        };
        Ok((out.tokens, out.pooled_index))
    }

    /// Encodes a prompt: per ControlNet layer the tokens' keys and values, Ada-IN's γ and β,
    /// and each token's expert, the pool's parameters blended by the gating MLP's softmax.
    pub fn encode(&self, text: &TextModel, prompt: &str) -> Result<OmgCondition> {
        let (Some(layers), Some(c)) = (&self.control, &self.cfg.control) else {
            return Err(invalid_arg!(
                "this OMG-style file has no ControlNet: it generates unconditionally only (give an empty prompt)"
            ));
        };
        let (tokens, eos) = self.text_tokens(text, prompt)?;
        let (dt, m, h, x) = (c.text_dim, c.control_dim, c.expert_hidden, c.experts);
        let n = tokens.len() / dt;
        let eos_feat = &tokens[eos * dt..(eos + 1) * dt];
        let mut out = Vec::with_capacity(layers.len());
        for layer in layers {
            let moc = &layer.moc;
            let mut k = vec![0f32; n * m];
            let mut v = vec![0f32; n * m];
            moc.k.forward(&tokens, n, &mut k);
            moc.v.forward(&tokens, n, &mut v);
            let mut gamma = vec![0f32; m];
            let mut beta = vec![0f32; m];
            moc.gamma.forward(eos_feat, 1, &mut gamma);
            moc.beta.forward(eos_feat, 1, &mut beta);
            // ω = softmax(G(c_i)) over the experts.
            let gh = c.gate_hidden;
            let mut g1 = vec![0f32; n * gh];
            moc.gate[0].forward(&tokens, n, &mut g1);
            activate(&mut g1, &c.gate_activation);
            let mut g2 = vec![0f32; n * gh];
            moc.gate[1].forward(&g1, n, &mut g2);
            activate(&mut g2, &c.gate_activation);
            let mut omega = vec![0f32; n * x];
            moc.gate[2].forward(&g2, n, &mut omega);
            kernels::softmax_rows(&mut omega, x);
            // Every token's blended parameters at once, already in the layers' `[out, in]`.
            let row = moc.pool.len() / x;
            let mut blended = vec![0f32; n * row];
            kernels::matmul_nn(&omega, &moc.pool, &mut blended, n, x, row);
            let experts = blended
                .par_chunks_exact(row)
                .map(|p| {
                    let (fc1, rest) = p.split_at(h * m);
                    let (fc2, rest) = rest.split_at(m * h);
                    let (bias0, bias1) = rest.split_at(h);
                    BlendedExpert {
                        fc1: Linear::from_weight(fc1, Some(bias0), m, h, self.ty),
                        fc2: Linear::from_weight(fc2, Some(bias1), h, m, self.ty),
                    }
                })
                .collect();
            out.push(LayerText {
                k,
                v,
                gamma,
                beta,
                experts,
            });
        }
        Ok(OmgCondition {
            tokens,
            n,
            layers: out,
        })
    }

    /// cos and sin of `position · inv_freq` for positions `0..frames`.
    fn rotary_tables(&self, frames: usize, ws: &mut OmgWorkspace) {
        let half = self.inv_freq.len();
        let (cos, sin) = (
            sized(&mut ws.cos, frames * half),
            sized(&mut ws.sin, frames * half),
        );
        for p in 0..frames {
            for (i, f) in self.inv_freq.iter().enumerate() {
                let a = p as f64 * f;
                cos[p * half + i] = a.cos() as f32;
                sin[p * half + i] = a.sin() as f32;
            }
        }
    }

    /// `x ← block(x)` over `rows` sequences of `frames` tokens; `mods` is the block's
    /// modulation `[6d]` (shift, scale, gate of attention; shift, scale, gate of the MLP).
    #[allow(clippy::too_many_arguments)]
    fn block(
        &self,
        blk: &Block,
        x: &mut [f32],
        rows: usize,
        frames: usize,
        mods: &[f32],
        ws: &mut OmgWorkspace,
    ) {
        let d = &self.cfg;
        let (e, heads) = (d.d_model, d.heads);
        let hd = e / heads;
        let n = rows * frames;
        let eps = d.norm_eps;
        let (shift_a, rest) = mods.split_at(e);
        let (scale_a, rest) = rest.split_at(e);
        let (gate_a, rest) = rest.split_at(e);
        let (shift_m, rest) = rest.split_at(e);
        let (scale_m, gate_m) = rest.split_at(e);
        let normed = sized(&mut ws.normed, n * e);
        modulate(x, normed, &self.unit, eps, shift_a, scale_a);
        let qkv = sized(&mut ws.qkv, n * 3 * e);
        blk.qkv.forward(normed, n, qkv);
        // RoPE on q and k: rotate-half pairs (i, i + r/2) of each head's first r dims.
        rotate_qk(qkv, e, hd, frames, &ws.cos, &ws.sin);
        let attn = sized(&mut ws.attn, n * e);
        self_attend(&mut ws.scratch, qkv, e, heads, frames, attn);
        let proj = sized(&mut ws.proj, n * e);
        blk.proj.forward(attn, n, proj);
        add_gated(x, proj, gate_a, e);
        let normed = sized(&mut ws.normed, n * e);
        modulate(x, normed, &self.unit, eps, shift_m, scale_m);
        let ff = sized(&mut ws.ff, n * d.ff_size);
        let tanh = d.mlp_activation == "gelu_tanh";
        if tanh {
            blk.fc1.forward(normed, n, ff);
            kernels::gelu_tanh(ff);
        } else {
            blk.fc1.forward_act(normed, n, ff, Activation::Gelu);
        }
        let proj = sized(&mut ws.proj, n * e);
        blk.fc2.forward(ff, n, proj);
        add_gated(x, proj, gate_m, e);
    }

    /// The MoC residual of one layer for one sequence: `f` `[frames, d_m]` in, `Σ_i r_i` out
    /// in `ws.r`.
    fn moc(
        &self,
        c: &ControlConfig,
        text: &LayerText,
        moc: &Moc,
        frames: usize,
        ws: &mut OmgWorkspace,
    ) {
        let m = c.control_dim;
        let n = text.k.len() / m;
        let heads = c.attn_heads;
        let hd = m / heads;
        let f = &mut ws.f;
        // Cross-attention to the tokens: A = softmax(Q·Kᵀ/√d) over the tokens; f′ = f + A·V.
        let q = sized(&mut ws.q, frames * m);
        moc.q.forward(&f[..frames * m], frames, q);
        let scale = (1.0 / (hd as f64).sqrt()) as f32;
        let mask = sized(&mut ws.mask, frames * n);
        mask.fill(0.0);
        let scores = sized(&mut ws.scores, frames * n);
        let av = sized(&mut ws.av, frames * hd);
        for hh in 0..heads {
            for t in 0..frames {
                let qr = &q[t * m + hh * hd..][..hd];
                for i in 0..n {
                    let kr = &text.k[i * m + hh * hd..][..hd];
                    scores[t * n + i] = qr.iter().zip(kr).map(|(a, b)| a * b).sum::<f32>() * scale;
                }
            }
            kernels::softmax_rows(scores, n);
            for t in 0..frames {
                let o = &mut av[t * hd..(t + 1) * hd];
                o.fill(0.0);
                for i in 0..n {
                    let w = scores[t * n + i];
                    for (a, &b) in o.iter_mut().zip(&text.v[i * m + hh * hd..][..hd]) {
                        *a += w * b;
                    }
                }
                for (dst, &a) in f[t * m + hh * hd..][..hd].iter_mut().zip(o.iter()) {
                    *dst += a;
                }
            }
            for (mv, &s) in mask.iter_mut().zip(scores.iter()) {
                *mv += s / heads as f32;
            }
        }
        // Ada-IN over time, per channel, from the end-of-text feature.
        let fr = frames as f32;
        for ch in 0..m {
            let mean = (0..frames).map(|t| f[t * m + ch]).sum::<f32>() / fr;
            let var = (0..frames)
                .map(|t| (f[t * m + ch] - mean).powi(2))
                .sum::<f32>()
                / fr;
            let inv = 1.0 / (var + c.adain_eps).sqrt();
            for t in 0..frames {
                let v = &mut f[t * m + ch];
                *v = text.gamma[ch] * ((*v - mean) * inv) + text.beta[ch];
            }
        }
        // M[t, i] = sigmoid(γ·(A[t, i] − β·max_t A[t, i])).
        for i in 0..n {
            let max = (0..frames)
                .map(|t| mask[t * n + i])
                .fold(f32::NEG_INFINITY, f32::max);
            for t in 0..frames {
                let z = c.mask_gamma * (mask[t * n + i] - c.mask_beta * max);
                mask[t * n + i] = 1.0 / (1.0 + (-z).exp());
            }
        }
        // Σ_i M_i ⊙ expert_i(f″).
        let r = sized(&mut ws.r, frames * m);
        r.fill(0.0);
        for (i, ex) in text.experts.iter().enumerate() {
            let hid = sized(&mut ws.hidden, frames * c.expert_hidden);
            ex.fc1.forward(&f[..frames * m], frames, hid);
            activate(hid, &c.expert_activation);
            let o = sized(&mut ws.out, frames * m);
            ex.fc2.forward(hid, frames, o);
            for t in 0..frames {
                let w = mask[t * n + i];
                for (a, &b) in r[t * m..(t + 1) * m].iter_mut().zip(&o[t * m..(t + 1) * m]) {
                    *a += w * b;
                }
            }
        }
    }

    /// One forward pass: `x` `[conds.len() · frames, F]`, a row per condition (a text
    /// condition runs D_c, the backbone marker D_u).
    #[allow(clippy::too_many_arguments)]
    pub fn forward_with(
        &self,
        x: &[f32],
        frames: usize,
        t: f32,
        conds: &[&Condition],
        out: &mut [f32],
        ws: &mut OmgWorkspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let d = &self.cfg;
        let (f, e) = (d.input_feats, d.d_model);
        let rows = conds.len();
        if frames == 0 || frames > d.max_frames {
            return Err(invalid_arg!(
                "{frames} frames: this OMG-style model generates 1 to {} (its positional range as trained)",
                d.max_frames
            ));
        }
        if x.len() != rows * frames * f || out.len() != x.len() {
            return Err(invalid_arg!(
                "forward buffers do not match {rows} × {frames} frames × {f}"
            ));
        }
        if rows == 0 || rows > MAX_BATCH {
            return Err(invalid_arg!(
                "a forward pass takes 1 to {MAX_BATCH} conditions"
            ));
        }
        // Per row: the prompt's condition, or None for the backbone alone (on the stack).
        let mut texts: [Option<&OmgCondition>; MAX_BATCH] = [None; MAX_BATCH];
        for (slot, c) in texts.iter_mut().zip(conds) {
            if c.get::<OmgBackbone>().is_none() {
                *slot = Some(c.get::<OmgCondition>().ok_or_else(|| {
                    invalid_arg!("a condition was made for another architecture")
                })?);
            }
        }
        let texts = &texts[..rows];
        let n = rows * frames;
        // c = MLP(sinusoid(t)); blocks read SiLU(c).
        let tf = sized(&mut ws.t, d.time_freq_dim);
        kernels::sinusoid_cos_first(t, tf);
        let c = sized(&mut ws.c, e);
        let hid = sized(&mut ws.proj, e);
        self.t_embed[0].forward(tf, 1, hid);
        kernels::silu(hid);
        self.t_embed[1].forward(hid, 1, c);
        kernels::silu(c);
        let h = sized(&mut ws.h, n * e);
        self.x_embed.forward(x, n, h);
        self.rotary_tables(frames, ws);
        let mut h = std::mem::take(&mut ws.h);
        for (li, blk) in self.blocks.iter().enumerate() {
            cancel.check()?;
            // The ControlNet copies read the block's input.
            let controlled = self.control.is_some() && texts.iter().any(Option::is_some);
            if controlled {
                ws.h_in.clear();
                ws.h_in.extend_from_slice(&h[..n * e]);
            }
            let mut mods = std::mem::take(&mut ws.mods);
            let m6 = sized(&mut mods, 6 * e);
            blk.modulation.forward(&ws.c, 1, m6);
            self.block(blk, &mut h[..n * e], rows, frames, m6, ws);
            if let (true, Some(layers), Some(cc)) = (controlled, &self.control, &d.control) {
                let layer = &layers[li];
                layer.block.modulation.forward(&ws.c, 1, m6);
                for (r, text) in texts.iter().enumerate() {
                    let Some(text) = text else { continue };
                    let mut g = std::mem::take(&mut ws.g);
                    g.clear();
                    g.extend_from_slice(&ws.h_in[r * frames * e..(r + 1) * frames * e]);
                    self.block(&layer.block, &mut g, 1, frames, m6, ws);
                    let mut fbuf = std::mem::take(&mut ws.f);
                    layer
                        .down
                        .forward(&g, frames, &mut fbuf, &mut ws.cols, Activation::None);
                    ws.f = fbuf;
                    self.moc(cc, &text.layers[li], &layer.moc, frames, ws);
                    let r_sum = std::mem::take(&mut ws.r);
                    let mut up = std::mem::take(&mut ws.up);
                    layer
                        .up
                        .forward(&r_sum, frames, &mut up, &mut ws.cols, Activation::None);
                    kernels::add_inplace(
                        &mut h[r * frames * e..(r + 1) * frames * e],
                        &up[..frames * e],
                    );
                    ws.up = up;
                    ws.r = r_sum;
                    ws.g = g;
                }
            }
            ws.mods = mods;
        }
        // Final adaLN (shift, scale) and the linear layer to x̂0.
        let mut mods = std::mem::take(&mut ws.mods);
        let m2 = sized(&mut mods, 2 * e);
        self.final_modulation.forward(&ws.c, 1, m2);
        let (shift, scale) = m2.split_at(e);
        let normed = sized(&mut ws.normed, n * e);
        modulate(&h[..n * e], normed, &self.unit, d.norm_eps, shift, scale);
        self.final_linear.forward(normed, n, &mut out[..n * f]);
        ws.mods = mods;
        ws.h = h;
        Ok(())
    }
}

/// The `{p}.w0`, `b0`, `w1`, `b1` expert pool (`[K, d_m, hidden]`, `[K, hidden]`,
/// `[K, hidden, d_m]`, `[K, d_m]`) as [`Moc::pool`]'s rows.
fn expert_pool(file: &ModelFile, p: &str, x: usize, m: usize, h: usize) -> Result<Vec<f32>> {
    let w0 = file.tensor(&format!("{p}.w0"), &[x, m, h])?;
    let b0 = file.tensor(&format!("{p}.b0"), &[x, h])?;
    let w1 = file.tensor(&format!("{p}.w1"), &[x, h, m])?;
    let b1 = file.tensor(&format!("{p}.b1"), &[x, m])?;
    let (w0, b0, w1, b1) = (w0.data(), b0.data(), w1.data(), b1.data());
    let row = 2 * m * h + h + m;
    let mut pool = Vec::with_capacity(x * row);
    for j in 0..x {
        pool.extend(transpose(&w0[j * m * h..(j + 1) * m * h], m, h));
        pool.extend(transpose(&w1[j * h * m..(j + 1) * h * m], h, m));
        pool.extend_from_slice(&b0[j * h..(j + 1) * h]);
        pool.extend_from_slice(&b1[j * m..(j + 1) * m]);
    }
    for name in ["w0", "b0", "w1", "b1"] {
        file.release(&format!("{p}.{name}"));
    }
    Ok(pool)
}

/// `out = LN(x)·(1 + scale) + shift` (LayerNorm without affine), row-wise over `e`.
fn modulate(x: &[f32], out: &mut [f32], ln: &UnitNorm, eps: f32, shift: &[f32], scale: &[f32]) {
    out.copy_from_slice(&x[..out.len()]);
    let e = ln.ones.len();
    kernels::layer_norm(out, e, &ln.ones, &ln.zeros, eps);
    for row in out.chunks_exact_mut(e) {
        for ((v, &a), &b) in row.iter_mut().zip(scale).zip(shift) {
            *v = *v * (1.0 + a) + b;
        }
    }
}

/// LayerNorm without affine, as a LayerNorm with γ = 1 and β = 0.
struct UnitNorm {
    ones: Vec<f32>,
    zeros: Vec<f32>,
}

/// `x += gate ⊙ y`, the gate per channel.
fn add_gated(x: &mut [f32], y: &[f32], gate: &[f32], e: usize) {
    for (xr, yr) in x.chunks_exact_mut(e).zip(y.chunks_exact(e)) {
        for ((a, &b), &g) in xr.iter_mut().zip(yr).zip(gate) {
            *a += g * b;
        }
    }
}

impl Denoiser for OmgDenoiser {
    fn sample_dim(&self) -> usize {
        self.cfg.input_feats
    }

    fn encode_prompt(&self, text: &TextModel, prompt: &str) -> Result<Condition> {
        Ok(Condition::new(self.encode(text, prompt)?))
    }

    fn unconditional(&self, _text: &TextModel, _uncond: &str) -> Result<Condition> {
        Ok(Condition::new(OmgBackbone))
    }

    fn check_condition(&self, cond: &Condition) -> Result<()> {
        if cond.get::<OmgBackbone>().is_some() {
            return Ok(());
        }
        match (cond.get::<OmgCondition>(), &self.control) {
            (Some(c), Some(layers)) if c.layers.len() == layers.len() => Ok(()),
            (Some(_), None) => Err(invalid_arg!(
                "this OMG-style file has no ControlNet: it generates unconditionally only"
            )),
            (Some(_), _) => Err(invalid_arg!(
                "the condition was made for another OMG-style model"
            )),
            (None, _) => Err(invalid_arg!(
                "the condition was made for another architecture"
            )),
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
        self.forward_with(x, rows, t, conds, out, ws.get::<OmgWorkspace>(), cancel)
    }

    fn linear_weight_bytes(&self) -> usize {
        let mut n = self.x_embed.weight_bytes()
            + self.t_embed.iter().map(|l| l.weight_bytes()).sum::<usize>()
            + self.blocks.iter().map(Block::weight_bytes).sum::<usize>()
            + self.final_modulation.weight_bytes()
            + self.final_linear.weight_bytes();
        for l in self.control.iter().flatten() {
            let m = &l.moc;
            n += l.block.weight_bytes() + l.down.weight_bytes() + l.up.weight_bytes();
            for x in [
                &m.q, &m.k, &m.v, &m.gamma, &m.beta, &m.gate[0], &m.gate[1], &m.gate[2],
            ] {
                n += x.weight_bytes();
            }
        }
        n
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}
