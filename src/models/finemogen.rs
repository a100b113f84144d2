//! FineMoGen (Zhang et al., NeurIPS 2023, mingyuan-zhang/FineMoGen): diffusion in HumanML3D feature
//! space with spatio-temporal mixture attention (SAMI) over body-part groups, mixtures of experts
//! on the motion and the text, and prompts per time stage (mingyuan-zhang/FineMoGen
//! `mogen/models/transformers/finemogen.py`, `mogen/models/attentions/fine_attention.py`;
//! docs/official/finemogen.md#released-configuration). Where the released code differs from the
//! paper (docs/official/finemogen.md#paper-versus-released-code), this file follows the code, so
//! the released checkpoints give their numbers.
//!
//! - Text: CLIP's `ln_final` over all 77 positions (padding included), `text_pre_proj`, a
//!   2-layer post-LN encoder without padding mask and `text_ln`: once per prompt. The text
//!   mixture of experts of every layer depends on the text alone, so it runs once per prompt too.
//! - Motion: the 263 features gathered into 7 body parts and the whole body, one Linear each to
//!   `part_dim` channels: 8 groups. Each layer is SAMI, then a per-part FFN, each ending in a
//!   FiLM-style stylization block on the time embedding.
//! - SAMI: per-part LayerNorm → motion MoE → (spatial value, key, value); a spatial branch
//!   mixing the parts with softmax(body_weight); the temporal branch builds 64 "templates" per
//!   part as softmax-over-sequence(key)ᵀ·value of text and motion tokens, gives each a time
//!   anchor and a cubic (s, v, a, j) Taylor expansion, and reads them back at every frame with
//!   Gaussian-softmax weights over the frame distance.
//! - Mixture of experts as tutel runs it (9.7): cosine top-k gate, renormalised gates, capacity
//!   `k·⌊f·⌈n/E⌉⌋` with batch-prioritised routing; a choice past an expert's capacity gives 0.
//!   Routing is decided for the whole batch (text rows and null rows compete for slots), and an
//!   expert's cost grows with the tokens routed to it.
//! - Guidance inside the network: w(t) = 1 + scale·t/T on x̂0; the null rows keep the same text
//!   with masked keys and zero values, so they always run beside the text rows (also at w = 1).
//! - Time stages (the released temporal composition, 9.13): a condition of several stages runs
//!   one network row per stage, padded to the longest; every row reads the templates of all the
//!   stages of its group with their time offsets. Body-part texts (not in the release; libflame's
//!   zero-shot use): SAMI head `h` of a stage reads its part's text, head 7 the overall text.
//!
//! Layout: frame-major `[rows, channels]`.

use std::any::Any;
use std::sync::Arc;

use rayon::prelude::*;
use serde::Deserialize;

use crate::checkpoint::{ModelFile, Tensor};
use crate::config::validate::{
    check_eps, check_layers, expect_flow, expect_shape, expect_text, heads_divide, in_range,
    in_range_f32, one_of, refuse_learned_range,
};
use crate::config::{section, Config, TextConfig, MAX_FEEDFORWARD, MAX_LAYERS, MAX_WIDTH};
use crate::error::{bad_file, invalid_arg, Result};
use crate::kernels::{self, Activation, WeightType};
use crate::stages::{Stage, PART_COUNT};

use super::layers::{sized, EncoderLayer, LayerBuffers, LayerNorm, LayerShape, Linear};
use super::{
    Cancel, Condition, Denoiser, Family, FamilyConfig, Guidance, TextModel, Workspace, MAX_BATCH,
};

/// The family's entry in [`super::FAMILIES`].
pub const FAMILY: Family = Family {
    architectures: &["finemogen"],
    parse: |arch, v| {
        Ok(Arc::new(FinemogenFamily {
            denoiser: section(v, arch, "denoiser")?,
        }))
    },
};

/// The `denoiser` section (released HumanML3D sizes in parentheses).
#[derive(Clone, Debug, Deserialize)]
pub struct FinemogenConfig {
    /// Features per frame (263).
    pub input_feats: usize,
    /// Whose body-part table splits the features (`human_ml3d`).
    pub dataset: String,
    /// Channels of each of the 8 groups (64; the latent is 8 × 64).
    pub part_dim: usize,
    /// Denoiser layers, each SAMI attention then the stylised FFN (4).
    pub num_layers: usize,
    /// Width of the time embedding (2048).
    pub time_embed_dim: usize,
    /// Frames of one stage at most; also the unit of normalised time (196).
    pub max_seq_len: usize,
    /// CLIP's width (512).
    pub clip_width: usize,
    /// Width of the text features (256).
    pub text_latent_dim: usize,
    /// Post-LN encoder layers over the CLIP token features (2).
    pub text_layers: usize,
    /// Heads of those layers; divides `text_latent_dim` (4).
    pub text_heads: usize,
    /// Feed-forward width of those layers (2048).
    pub text_ff_size: usize,
    /// Text positions (77, all kept).
    pub max_text_len: usize,
    /// Hidden width of the per-part FFN and of the template MLPs (256).
    pub ffn_dim: usize,
    /// Experts of each mixture-of-experts layer (16).
    pub num_experts: usize,
    /// Experts each token is routed to, 1..=`num_experts` (2).
    pub topk: usize,
    /// tutel's capacity factor f: each expert takes `topk`·⌊f·⌈tokens/num_experts⌉⌋ tokens of a
    /// call, the rest are dropped (1.5; docs/official/finemogen.md#capacity-and-dropping).
    pub capacity_factor: f32,
    /// Width of the cosine gate's projection (256).
    pub gate_dim: usize,
    /// Hidden width of each text-token expert (the converter reads it from `batched_fc1_w`).
    pub text_expert_hidden: usize,
    /// Hidden width of each motion-token expert (likewise read from the expert tensors).
    pub motion_expert_hidden: usize,
    /// LayerNorm's epsilon, in (0, 1] (default 1e-5).
    #[serde(default = "ln_eps")]
    pub layer_norm_eps: f32,
}

fn ln_eps() -> f32 {
    1e-5
}

/// A FineMoGen file's configuration.
#[derive(Clone, Debug)]
pub struct FinemogenFamily {
    /// The network's sizes (the `denoiser` section).
    pub denoiser: FinemogenConfig,
}

/// Body-part groups: the 7 parts of [`crate::stages::BodyPart`] in that order, then the body.
pub const GROUPS: usize = PART_COUNT + 1;
/// The official module names of the groups (`joint_embed.{name}_embed`, `out.{name}_out`).
const GROUP_NAMES: [&str; GROUPS] = [
    "head", "stem", "larm", "rarm", "lleg", "rleg", "root", "body",
];
/// HumanML3D joints of each part (FineMoGen `finemogen.py` `get_t2m_slice`;
/// docs/official/finemogen.md#body-part-split).
const PART_JOINTS: [&[usize]; PART_COUNT] = [
    &[12, 15],
    &[3, 6, 9],
    &[14, 17, 19, 21],
    &[13, 16, 18, 20],
    &[2, 5, 8, 11],
    &[1, 4, 7, 10],
    &[0],
];
const JOINTS: usize = 22;
/// Most stages one condition holds.
pub const MAX_STAGES: usize = 16;

/// HumanML3D-263 indices of joint `j`'s features: the root's 11, another joint's 12 (ric,
/// 6D rotation, local velocity).
fn joint_features(j: usize) -> Vec<usize> {
    if j == 0 {
        return vec![0, 1, 2, 3, 193, 194, 195, 259, 260, 261, 262];
    }
    let ric = 4 + 3 * (j - 1);
    let rot = 67 + 6 * (j - 1);
    let vel = 193 + 3 * j;
    (ric..ric + 3)
        .chain(rot..rot + 6)
        .chain(vel..vel + 3)
        .collect()
}

/// The gather indices of each group: the parts' joints, and all 22 joints for the body (a
/// permutation of the 263 features, not the identity).
fn group_indices() -> [Vec<usize>; GROUPS] {
    std::array::from_fn(|g| {
        let joints: Vec<usize> = if g < PART_COUNT {
            PART_JOINTS[g].to_vec()
        } else {
            (0..JOINTS).collect()
        };
        joints.into_iter().flat_map(joint_features).collect()
    })
}

const D: &str = "denoiser.";

impl FamilyConfig for FinemogenFamily {
    fn architecture(&self) -> &str {
        "finemogen"
    }

    fn check(&self, cfg: &Config) -> Result<()> {
        let d = &self.denoiser;
        match d.dataset.as_str() {
            "human_ml3d" => {}
            "kit_ml" => {
                return Err(bad_file!(
                    "config denoiser.dataset `kit_ml`: libflame has no KIT-ML skeleton (251 \
                     features, 21 joints); only HumanML3D FineMoGen models run"
                ))
            }
            other => one_of("denoiser.dataset", other, &["human_ml3d"])?,
        }
        if d.input_feats != 263 {
            return Err(bad_file!(
                "config denoiser.input_feats {} is not HumanML3D's 263",
                d.input_feats
            ));
        }
        in_range("denoiser.part_dim", d.part_dim, 1, MAX_WIDTH / GROUPS)?;
        in_range("denoiser.num_layers", d.num_layers, 1, MAX_LAYERS)?;
        in_range("denoiser.time_embed_dim", d.time_embed_dim, 1, MAX_WIDTH)?;
        in_range("denoiser.max_seq_len", d.max_seq_len, 1, 4096)?;
        in_range("denoiser.clip_width", d.clip_width, 1, MAX_WIDTH)?;
        in_range("denoiser.text_latent_dim", d.text_latent_dim, 1, MAX_WIDTH)?;
        in_range("denoiser.text_layers", d.text_layers, 1, MAX_LAYERS)?;
        heads_divide(
            "denoiser.text_latent_dim",
            d.text_latent_dim,
            "denoiser.text_heads",
            d.text_heads,
        )?;
        in_range("denoiser.text_ff_size", d.text_ff_size, 1, MAX_FEEDFORWARD)?;
        in_range("denoiser.max_text_len", d.max_text_len, 1, 4096)?;
        in_range("denoiser.ffn_dim", d.ffn_dim, 1, MAX_FEEDFORWARD)?;
        in_range("denoiser.num_experts", d.num_experts, 1, 4096)?;
        in_range("denoiser.topk", d.topk, 1, d.num_experts)?;
        in_range_f32(
            "denoiser.capacity_factor",
            d.capacity_factor,
            0.0,
            1024.0,
            true,
        )?;
        in_range("denoiser.gate_dim", d.gate_dim, 1, MAX_WIDTH)?;
        in_range(
            "denoiser.text_expert_hidden",
            d.text_expert_hidden,
            1,
            MAX_FEEDFORWARD,
        )?;
        in_range(
            "denoiser.motion_expert_hidden",
            d.motion_expert_hidden,
            1,
            MAX_FEEDFORWARD,
        )?;
        check_eps("denoiser.layer_norm_eps", d.layer_norm_eps)?;
        expect_text(cfg, &["clip"])?;
        if let TextConfig::Clip(c) = &cfg.text_encoder {
            if c.clip.width != d.clip_width {
                return Err(bad_file!(
                    "config text_encoder.width {} differs from denoiser.clip_width {}",
                    c.clip.width,
                    d.clip_width
                ));
            }
            if c.max_length != d.max_text_len || c.clip.context_length < d.max_text_len {
                return Err(bad_file!(
                    "config text_encoder.max_length {} (context {}) must equal denoiser.max_text_len {}: every text position is a token",
                    c.max_length,
                    c.clip.context_length,
                    d.max_text_len
                ));
            }
        }
        if cfg.diffusion.uncond != "null_text" {
            return Err(bad_file!(
                "config diffusion.uncond `{}`: FineMoGen's unconditional rows are its null text (`null_text`)",
                cfg.diffusion.uncond
            ));
        }
        expect_flow(cfg, false)?;
        refuse_learned_range(cfg)
    }

    fn validate(&self, file: &ModelFile) -> Result<()> {
        let d = &self.denoiser;
        let (p, l) = (d.part_dim, GROUPS * d.part_dim);
        let shape =
            |name: &str, want: &[usize], fields: &str| expect_shape(file, name, want, fields);
        shape(
            &format!("{D}text_pre_proj.weight"),
            &[d.text_latent_dim, d.clip_width],
            "denoiser.text_latent_dim, clip_width",
        )?;
        check_layers(
            file,
            "denoiser.text_layers",
            d.text_layers,
            &format!("{D}textTransEncoder.layers."),
        )?;
        shape(
            &format!("{D}textTransEncoder.layers.0.linear1.weight"),
            &[d.text_ff_size, d.text_latent_dim],
            "denoiser.text_ff_size, text_latent_dim",
        )?;
        shape(
            &format!("{D}time_embed.0.weight"),
            &[d.time_embed_dim, l],
            "denoiser.time_embed_dim, part_dim",
        )?;
        for (g, idx) in GROUP_NAMES.iter().zip(group_indices()) {
            shape(
                &format!("{D}joint_embed.{g}_embed.weight"),
                &[p, idx.len()],
                "denoiser.part_dim",
            )?;
        }
        check_layers(
            file,
            "denoiser.num_layers",
            d.num_layers,
            &format!("{D}temporal_decoder_blocks."),
        )?;
        let ca = format!("{D}temporal_decoder_blocks.0.ca_block.");
        let (e, nt) = (d.num_experts, d.max_text_len);
        shape(
            &format!("{ca}motion_moe.embedding"),
            &[1, d.max_seq_len, GROUPS, p],
            "denoiser.max_seq_len, part_dim",
        )?;
        shape(
            &format!("{ca}text_moe.embedding"),
            &[1, nt, 1, d.text_latent_dim],
            "denoiser.max_text_len, text_latent_dim",
        )?;
        shape(
            &format!("{ca}motion_moe.model.gates.0.sim_matrix"),
            &[d.gate_dim, e],
            "denoiser.gate_dim, num_experts",
        )?;
        shape(
            &format!("{ca}motion_moe.model.experts.batched_fc1_w"),
            &[e, d.motion_expert_hidden, p],
            "denoiser.num_experts, motion_expert_hidden, part_dim",
        )?;
        shape(
            &format!("{ca}text_moe.model.experts.batched_fc1_w"),
            &[e, d.text_expert_hidden, d.text_latent_dim],
            "denoiser.num_experts, text_expert_hidden, text_latent_dim",
        )?;
        shape(
            &format!("{ca}template_s.0.weight"),
            &[d.ffn_dim, p],
            "denoiser.ffn_dim, part_dim",
        )?;
        shape(
            &format!("{ca}proj_out.emb_layers.1.weight"),
            &[2 * l, d.time_embed_dim],
            "denoiser.part_dim, time_embed_dim",
        )
    }

    fn feature_dim(&self) -> usize {
        self.denoiser.input_feats
    }

    /// A session covers up to [`MAX_STAGES`] stages of `max_seq_len` frames; one prompt covers
    /// `max_seq_len` frames ([`Denoiser::check_frames`]).
    fn max_frames(&self) -> usize {
        self.denoiser.max_seq_len * MAX_STAGES
    }

    fn unconditional_inputs(&self) -> &'static [&'static str] {
        &["null_text"]
    }

    fn summary(&self) -> String {
        let d = &self.denoiser;
        format!(
            "FineMoGen, {} layers of SAMI + SFFN over 8 groups x {}, {} experts (top-{}, capacity factor {}), text {} x {} layers",
            d.num_layers, d.part_dim, d.num_experts, d.topk, d.capacity_factor, d.text_latent_dim, d.text_layers
        )
    }

    fn load(
        &self,
        file: &ModelFile,
        cfg: &Config,
        _text: &TextModel,
        ty: WeightType,
    ) -> Result<Box<dyn Denoiser>> {
        Ok(Box::new(FinemogenDenoiser::load(
            file,
            self,
            cfg.diffusion.num_timesteps,
            ty,
        )?))
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// A two-layer MLP `Linear → GELU → Linear`.
struct Mlp {
    fc1: Linear,
    fc2: Linear,
    hidden: usize,
}

impl Mlp {
    fn load(
        file: &ModelFile,
        p: &str,
        n_in: usize,
        hidden: usize,
        n_out: usize,
        ty: WeightType,
    ) -> Result<Mlp> {
        Ok(Mlp {
            fc1: Linear::load(file, &format!("{p}.0"), n_in, hidden, ty)?,
            fc2: Linear::load(file, &format!("{p}.2"), hidden, n_out, ty)?,
            hidden,
        })
    }

    fn forward(&self, x: &[f32], rows: usize, y: &mut [f32], h: &mut Vec<f32>) {
        let h = sized(h, rows * self.hidden);
        self.fc1.forward_act(x, rows, h, Activation::Gelu);
        self.fc2.forward(h, rows, y);
    }

    fn weight_bytes(&self) -> usize {
        self.fc1.weight_bytes() + self.fc2.weight_bytes()
    }
}

/// One expert of a mixture: `GELU(x·W1ᵀ + b1)·W2 + b2`.
struct Expert {
    fc1: Linear,
    fc2: Linear,
}

/// A mixture of experts with the FineMoGen wrapper around it: `proj(GELU(moe(x + embedding)))`.
struct Moe {
    /// Learned position (and, for the motion, part) embedding, `[positions · heads, dim]`.
    embedding: Tensor,
    dim: usize,
    hidden: usize,
    /// The cosine gate: projection, then the normalised similarity matrix as a bias-free
    /// layer `[experts, gate_dim]`, and `exp(min(temperature, ln 100))`.
    gate: Linear,
    gate_dim: usize,
    similarity: Linear,
    logit_scale: f32,
    experts: Vec<Expert>,
    topk: usize,
    capacity_factor: f32,
    proj: Linear,
    proj_out: usize,
}

impl Moe {
    #[allow(clippy::too_many_arguments)]
    fn load(
        file: &ModelFile,
        p: &str,
        positions: usize,
        heads: usize,
        dim: usize,
        hidden: usize,
        proj_out: usize,
        cfg: &FinemogenConfig,
        ty: WeightType,
    ) -> Result<Moe> {
        let (e, g) = (cfg.num_experts, cfg.gate_dim);
        let embedding = file.tensor(&format!("{p}.embedding"), &[1, positions, heads, dim])?;
        let m = format!("{p}.model");
        let temperature = file
            .tensor(&format!("{m}.gates.0.temperature"), &[1])?
            .data()[0];
        if !temperature.is_finite() {
            return Err(bad_file!("`{m}.gates.0.temperature` is not finite"));
        }
        let sim = file.tensor(&format!("{m}.gates.0.sim_matrix"), &[g, e])?;
        // normalize(sim_matrix, dim = 0): each expert's column to unit length (eps 1e-12).
        let mut simt = vec![0f32; e * g];
        for x in 0..e {
            let norm = (0..g)
                .map(|r| sim.data()[r * e + x].powi(2))
                .sum::<f32>()
                .sqrt()
                .max(1e-12);
            for r in 0..g {
                simt[x * g + r] = sim.data()[r * e + x] / norm;
            }
        }
        let w1 = file.tensor(&format!("{m}.experts.batched_fc1_w"), &[e, hidden, dim])?;
        let b1 = file.tensor(&format!("{m}.experts.batched_fc1_bias"), &[e, hidden])?;
        // fc2 is stored `[hidden, out]` per expert: transposed into a Linear's `[out, hidden]`.
        let w2 = file.tensor(&format!("{m}.experts.batched_fc2_w"), &[e, hidden, dim])?;
        let b2 = file.tensor(&format!("{m}.experts.batched_fc2_bias"), &[e, dim])?;
        let mut experts = Vec::with_capacity(e);
        let mut t = vec![0f32; dim * hidden];
        for x in 0..e {
            let w = &w2.data()[x * hidden * dim..(x + 1) * hidden * dim];
            for (h, row) in w.chunks_exact(dim).enumerate() {
                for (o, &v) in row.iter().enumerate() {
                    t[o * hidden + h] = v;
                }
            }
            experts.push(Expert {
                fc1: Linear::from_weight(
                    &w1.data()[x * hidden * dim..(x + 1) * hidden * dim],
                    Some(&b1.data()[x * hidden..(x + 1) * hidden]),
                    dim,
                    hidden,
                    ty,
                ),
                fc2: Linear::from_weight(
                    &t,
                    Some(&b2.data()[x * dim..(x + 1) * dim]),
                    hidden,
                    dim,
                    ty,
                ),
            });
        }
        Ok(Moe {
            embedding,
            dim,
            hidden,
            gate: Linear::load(file, &format!("{m}.gates.0.cosine_projector"), dim, g, ty)?,
            gate_dim: g,
            similarity: Linear::from_weight(&simt, None, g, e, ty),
            logit_scale: temperature.min(100f32.ln()).exp(),
            experts,
            topk: cfg.topk,
            capacity_factor: cfg.capacity_factor,
            proj: Linear::load(file, &format!("{p}.proj"), dim, proj_out, ty)?,
            proj_out,
        })
    }

    fn weight_bytes(&self) -> usize {
        self.gate.weight_bytes()
            + self.similarity.weight_bytes()
            + self.proj.weight_bytes()
            + self
                .experts
                .iter()
                .map(|x| x.fc1.weight_bytes() + x.fc2.weight_bytes())
                .sum::<usize>()
    }

    fn capacity(&self, n: usize) -> usize {
        capacity(n, self.experts.len(), self.topk, self.capacity_factor)
    }

    /// Routes `n` tokens `x` (`[n, dim]`, the embedding already added) and writes
    /// `proj(GELU(Σ gates · experts))` into `y` (`[n, proj_out]`) for the first `used` tokens
    /// (the rest only compete for slots). Returns the number of dropped choices.
    fn forward(
        &self,
        x: &[f32],
        n: usize,
        used: usize,
        y: &mut [f32],
        ws: &mut MoeScratch,
    ) -> usize {
        // Charged as if no choice were dropped: gate, experts of k choices, projection.
        let (d, h, g, e) = (self.dim, self.hidden, self.gate_dim, self.experts.len());
        let flop = 2 * (n * (d * g + g * e) + used * (self.topk * 2 * d * h + d * self.proj_out));
        kernels::profile::timed(kernels::profile::Kind::Moe, flop, || {
            self.forward_untimed(x, n, used, y, ws)
        })
    }

    fn forward_untimed(
        &self,
        x: &[f32],
        n: usize,
        used: usize,
        y: &mut [f32],
        ws: &mut MoeScratch,
    ) -> usize {
        let (e, k, g) = (self.experts.len(), self.topk, self.gate_dim);
        // Cosine gate: normalize(proj(x)) · normalize(sim) · scale, softmax over the experts.
        let gp = sized(&mut ws.gate, n * g);
        self.gate.forward(x, n, gp);
        for row in gp.chunks_exact_mut(g) {
            let norm = row.iter().map(|v| v * v).sum::<f32>().sqrt().max(1e-12);
            row.iter_mut().for_each(|v| *v /= norm);
        }
        let mut scores_buf = std::mem::take(&mut ws.scores);
        let scores = sized(&mut scores_buf, n * e);
        self.similarity.forward(gp, n, scores);
        for row in scores.chunks_exact_mut(e) {
            row.iter_mut().for_each(|v| *v *= self.logit_scale);
            kernels::softmax_rows(row, e);
        }
        let dropped = route(scores, e, k, self.capacity(n), used, ws);
        ws.scores = scores_buf;
        // Each expert on the tokens routed to it; Σ gates · outputs per token, in expert order.
        // With several threads, each task runs a contiguous range of experts (equal shares of
        // the routed rows) into its own sums, its calls unsplit; the ranges' sums are then
        // added in order. A token's terms are added in the same order either way (the other
        // ranges contribute exact zeros), so the bits do not depend on the thread count.
        let d = self.dim;
        let rows: usize = ws.routed.iter().map(Vec::len).sum();
        let tasks = kernels::threads()
            .min(e)
            .min(rows / EXPERT_ROWS_PER_TASK)
            .max(1);
        let MoeScratch {
            routed,
            parts,
            mix,
            ends,
            ..
        } = ws;
        let routed: &[Vec<(u32, f32)>] = routed;
        if parts.len() < tasks {
            parts.resize_with(tasks, ExpertScratch::default);
        }
        // Sized once for the most rows an expert can get, so that later steps, whose experts
        // get other counts, do not allocate (a range's sums only when there are several).
        let most = self.capacity(n).min(n);
        let sums = if tasks > 1 { used * d } else { 0 };
        for part in &mut parts[..tasks] {
            for (buf, len) in [
                (&mut part.xin, most * d),
                (&mut part.hidden, most * self.hidden),
                (&mut part.out, most * d),
                (&mut part.mix, sums),
            ] {
                buf.reserve(len.saturating_sub(buf.len()));
            }
        }
        let mix = sized(mix, used * d);
        if tasks == 1 {
            self.run_experts(0..e, routed, x, used, mix, &mut parts[0]);
        } else {
            // Range j ends after the expert where the routed rows first reach j + 1 shares.
            ends.clear();
            let mut seen = 0;
            for (expert, list) in routed.iter().enumerate() {
                seen += list.len();
                while ends.len() < tasks - 1 && seen * tasks >= (ends.len() + 1) * rows {
                    ends.push(expert + 1);
                }
            }
            ends.resize(tasks, e);
            let flop = 2 * rows * 2 * d * self.hidden;
            kernels::profile::timed(kernels::profile::Kind::Linear, flop, || {
                parts[..tasks]
                    .par_iter_mut()
                    .enumerate()
                    .for_each(|(j, part)| {
                        let start = if j == 0 { 0 } else { ends[j - 1] };
                        let mut sums = std::mem::take(&mut part.mix);
                        let range = start..ends[j];
                        kernels::serial(|| {
                            self.run_experts(
                                range,
                                routed,
                                x,
                                used,
                                sized(&mut sums, used * d),
                                part,
                            )
                        });
                        part.mix = sums;
                    });
            });
            mix.copy_from_slice(&parts[0].mix[..used * d]);
            for part in &parts[1..tasks] {
                kernels::add_inplace(mix, &part.mix[..used * d]);
            }
        }
        kernels::gelu_erf(mix);
        self.proj.forward(mix, used, &mut y[..used * self.proj_out]);
        dropped
    }

    /// `sums = Σ gate · expert(x[token])` over experts `range` and their routed `(token, gate)`
    /// lists, in expert order (`sums` is overwritten: `[used, dim]`).
    fn run_experts(
        &self,
        range: std::ops::Range<usize>,
        routed: &[Vec<(u32, f32)>],
        x: &[f32],
        used: usize,
        sums: &mut [f32],
        part: &mut ExpertScratch,
    ) {
        let (d, h) = (self.dim, self.hidden);
        let sums = &mut sums[..used * d];
        sums.fill(0.0);
        for (expert, list) in self.experts[range.clone()].iter().zip(&routed[range]) {
            let m = list.len();
            if m == 0 {
                continue;
            }
            let xin = sized(&mut part.xin, m * d);
            for (row, &(t, _)) in xin.chunks_exact_mut(d).zip(list) {
                row.copy_from_slice(&x[t as usize * d..][..d]);
            }
            let hid = sized(&mut part.hidden, m * h);
            expert.fc1.forward_act(xin, m, hid, Activation::Gelu);
            let o = sized(&mut part.out, m * d);
            expert.fc2.forward(hid, m, o);
            for (row, &(t, gate)) in o.chunks_exact(d).zip(list) {
                let dst = &mut sums[t as usize * d..][..d];
                for (a, &b) in dst.iter_mut().zip(row) {
                    *a += gate * b;
                }
            }
        }
    }
}

/// Fewest routed rows per task when a mixture's experts are split over threads: below this a
/// task's work is less than a fork and join costs.
const EXPERT_ROWS_PER_TASK: usize = 64;

/// Slots per expert for `n` tokens: `k · ⌊f · ⌈n / E⌉⌋` (tutel; `f` a Python float).
fn capacity(n: usize, experts: usize, k: usize, f: f32) -> usize {
    k * (f as f64 * n.div_ceil(experts) as f64) as usize
}

/// tutel's routing of `scores` (`[n, e]`, softmax over the experts): each token's top-`k`
/// experts (ties: the lower expert) with gates renormalised over them before any drop; slots by
/// batch priority — tokens by descending top-1 score (stable: the lower index first among equal
/// scores), choice `r` of every token queued after all choices before `r`; a choice whose slot
/// is `cap` or more is dropped. Fills `ws.routed[expert]` with `(token, gate)` for the tokens
/// below `used` and returns the dropped choices (of all tokens).
fn route(
    scores: &[f32],
    e: usize,
    k: usize,
    cap: usize,
    used: usize,
    ws: &mut MoeScratch,
) -> usize {
    let n = scores.len() / e;
    // Top-k per token (ties: the lower expert), gates renormalised before any drop.
    ws.choice.clear();
    ws.gates.clear();
    for row in scores.chunks_exact(e) {
        let start = ws.choice.len();
        for _ in 0..k {
            let mut best = usize::MAX;
            for (x, &s) in row.iter().enumerate() {
                let taken = ws.choice[start..].contains(&(x as u32));
                if !taken && (best == usize::MAX || s > row[best]) {
                    best = x;
                }
            }
            ws.choice.push(best as u32);
        }
        let sum: f32 = ws.choice[start..].iter().map(|&c| row[c as usize]).sum();
        let denom = sum.max(f32::EPSILON);
        for &c in &ws.choice[start..] {
            ws.gates.push(row[c as usize] / denom);
        }
    }
    // Batch-prioritised slots: tokens by descending top-1 score (stable: the lower index
    // first among equal scores); choice r of a token queues after every earlier choice.
    ws.order.clear();
    ws.order.extend(0..n as u32);
    let top1 = |t: u32| scores[t as usize * e + ws.choice[t as usize * k] as usize];
    ws.order.sort_by(|&a, &b| top1(b).total_cmp(&top1(a)));
    ws.count.clear();
    ws.count.resize(e, 0);
    for list in ws.routed.iter_mut() {
        list.clear();
    }
    ws.routed.resize_with(e, Vec::new);
    // No list holds more than `cap` tokens: reserved once, so later steps do not allocate.
    for list in ws.routed.iter_mut() {
        list.reserve(cap.min(n));
    }
    let mut dropped = 0;
    for r in 0..k {
        for &t in &ws.order {
            let i = t as usize * k + r;
            let x = ws.choice[i] as usize;
            let slot = ws.count[x];
            ws.count[x] += 1;
            if slot >= cap {
                dropped += 1;
            } else if (t as usize) < used {
                ws.routed[x].push((t, ws.gates[i]));
            }
        }
    }
    dropped
}

/// Buffers of [`Moe::forward`].
#[derive(Default)]
struct MoeScratch {
    gate: Vec<f32>,
    scores: Vec<f32>,
    choice: Vec<u32>,
    gates: Vec<f32>,
    order: Vec<u32>,
    count: Vec<usize>,
    routed: Vec<Vec<(u32, f32)>>,
    mix: Vec<f32>,
    /// One per task running a range of experts, and where each range ends.
    parts: Vec<ExpertScratch>,
    ends: Vec<usize>,
}

/// Buffers of one task of [`Moe::run_experts`]: the gathered rows, the experts' hidden and
/// output rows, and the range's sums.
#[derive(Default)]
struct ExpertScratch {
    xin: Vec<f32>,
    hidden: Vec<f32>,
    out: Vec<f32>,
    mix: Vec<f32>,
}

/// `out(SiLU(LN(h)·(1 + scale) + shift))` with (scale, shift) from the time embedding.
struct Stylization {
    emb: Linear,
    norm: LayerNorm,
    out: Linear,
}

impl Stylization {
    fn load(file: &ModelFile, p: &str, width: usize, time: usize, ty: WeightType) -> Result<Self> {
        Ok(Stylization {
            emb: Linear::load(file, &format!("{p}.emb_layers.1"), time, 2 * width, ty)?,
            norm: LayerNorm::load(file, &format!("{p}.norm"), width)?,
            out: Linear::load(file, &format!("{p}.out_layers.2"), width, width, ty)?,
        })
    }

    fn weight_bytes(&self) -> usize {
        self.emb.weight_bytes() + self.out.weight_bytes()
    }

    /// `x ← x + block(h)` over `rows` rows; `silu_emb` is SiLU(time embedding).
    #[allow(clippy::too_many_arguments)]
    fn add(
        &self,
        x: &mut [f32],
        h: &mut [f32],
        rows: usize,
        silu_emb: &[f32],
        eps: f32,
        s: &mut Vec<f32>,
        o: &mut Vec<f32>,
    ) {
        let w = self.norm.weight.data().len();
        let ss = sized(s, 2 * w);
        self.emb.forward(silu_emb, 1, ss);
        let (scale, shift) = ss.split_at(w);
        kernels::layer_norm(h, w, self.norm.weight.data(), self.norm.bias.data(), eps);
        for row in h.chunks_exact_mut(w) {
            for ((v, &a), &b) in row.iter_mut().zip(scale).zip(shift) {
                *v = *v * (1.0 + a) + b;
            }
        }
        kernels::silu(h);
        let o = sized(o, rows * w);
        self.out.forward(h, rows, o);
        kernels::add_inplace(x, o);
    }
}

/// One SAMI block (FineMoGen `mogen/models/attentions/fine_attention.py`;
/// docs/official/finemogen.md#sami-attention).
struct Sami {
    norm: LayerNorm,
    text_norm: LayerNorm,
    motion_moe: Moe,
    text_moe: Moe,
    /// softmax(body_weight) over its rows' entries, `[8, 8]`.
    body_mix: Vec<f32>,
    sigma: f32,
    t_sigma: f32,
    template_t: Mlp,
    /// template_s, _v, _a, _j.
    templates: [Mlp; 4],
    proj_out: Stylization,
}

/// The per-part FFN (FineMoGen `finemogen.py` `SFFN`;
/// docs/official/finemogen.md#sffn-and-stylization-block).
struct Sffn {
    parts: Vec<Mlp>,
    proj_out: Stylization,
}

struct Layer {
    sami: Sami,
    ffn: Sffn,
}

/// The network.
pub struct FinemogenDenoiser {
    cfg: FinemogenConfig,
    num_timesteps: usize,
    text_pre_proj: Linear,
    text_layers: Vec<EncoderLayer>,
    text_ln: LayerNorm,
    time_embed: [Linear; 2],
    groups: [Vec<usize>; GROUPS],
    joint_embed: Vec<Linear>,
    out: Vec<Linear>,
    layers: Vec<Layer>,
}

/// One stage of a condition: its frames and, per SAMI head, which of the condition's text
/// sequences it reads.
#[derive(Clone, Debug)]
struct StageText {
    frames: usize,
    heads: [usize; GROUPS],
}

/// A FineMoGen condition: the stages and their encoded texts, with every layer's text-MoE
/// features (they depend on the text alone).
pub struct FinemogenCondition {
    stages: Vec<StageText>,
    /// The stages' frame counts.
    frames: Vec<usize>,
    /// Encoded text sequences `[max_text_len, text_latent_dim]`, distinct within a stage.
    xf: Vec<Vec<f32>>,
    /// Per layer: `[sequences, max_text_len, 2·part_dim]` (key, value) from the text MoE.
    text_feat: Vec<Vec<f32>>,
    /// Dropped text-MoE choices over all layers (for the record).
    pub text_dropped: usize,
}

impl FinemogenCondition {
    /// The stages' frame counts.
    pub fn stage_frames(&self) -> &[usize] {
        &self.frames
    }

    /// The encoded text sequences (after `text_ln`), in the order the text MoE routes them.
    pub fn text_features(&self) -> &[Vec<f32>] {
        &self.xf
    }
}

/// The unconditional rows: the text masked out (FineMoGen `fine_attention.py`;
/// docs/official/finemogen.md#sami-attention).
#[derive(Clone, Copy, Debug)]
pub struct FinemogenNull;

/// Buffers of a forward pass.
#[derive(Default)]
pub struct FinemogenWorkspace {
    emb: Vec<f32>,
    hid: Vec<f32>,
    h: Vec<f32>,
    tmp: Vec<f32>,
    tokens: Vec<f32>,
    feat: Vec<f32>,
    ys: Vec<f32>,
    keys: Vec<f32>,
    vals: Vec<f32>,
    g: Vec<f32>,
    tt: Vec<f32>,
    tpl: [Vec<f32>; 4],
    coef: Vec<f32>,
    acat: Vec<f32>,
    acc: Vec<f32>,
    styl: (Vec<f32>, Vec<f32>),
    mlp: Vec<f32>,
    part_in: Vec<f32>,
    part_out: Vec<f32>,
    /// One per task of [`FinemogenDenoiser::sffn`].
    part_tasks: Vec<PartScratch>,
    moe: MoeScratch,
    /// The right-hand activations of the template products, packed.
    rhs: kernels::PackedWeights,
    /// Dropped motion-MoE choices in the last forward pass.
    pub motion_dropped: usize,
}

/// Buffers of one task of [`FinemogenDenoiser::sffn`]: a part's input and hidden rows, and
/// the outputs of the task's parts, one after another.
#[derive(Default)]
struct PartScratch {
    input: Vec<f32>,
    hidden: Vec<f32>,
    out: Vec<f32>,
}

/// One network row of a batch.
#[derive(Clone, Copy)]
struct NetRow<'a> {
    frames: usize,
    /// Frames of the earlier stages of its group.
    start: usize,
    /// The first row of its group and how many rows the group has.
    group: (usize, usize),
    /// The condition and stage whose text it reads; `None` for a null row.
    text: Option<(&'a FinemogenCondition, usize)>,
}

/// The network rows of one forward pass, on the stack (a step allocates nothing).
struct NetRows<'a> {
    rows: [NetRow<'a>; MAX_BATCH * MAX_STAGES],
    len: usize,
}

impl<'a> NetRows<'a> {
    fn new() -> NetRows<'a> {
        let empty = NetRow {
            frames: 0,
            start: 0,
            group: (0, 0),
            text: None,
        };
        NetRows {
            rows: [empty; MAX_BATCH * MAX_STAGES],
            len: 0,
        }
    }
}

impl FinemogenDenoiser {
    /// Reads the tensors (under `denoiser.`) and builds the network, linear weights held as
    /// `ty`; `num_timesteps` (T) sets the guidance ramp w(t) = 1 + scale·t/T.
    pub fn load(
        file: &ModelFile,
        fam: &FinemogenFamily,
        num_timesteps: usize,
        ty: WeightType,
    ) -> Result<FinemogenDenoiser> {
        let d = &fam.denoiser;
        let (p, l, tl) = (d.part_dim, GROUPS * d.part_dim, d.text_latent_dim);
        let lin =
            |name: &str, n_in, n_out| Linear::load(file, &format!("{D}{name}"), n_in, n_out, ty);
        let groups = group_indices();
        let mut joint_embed = Vec::with_capacity(GROUPS);
        let mut out = Vec::with_capacity(GROUPS);
        for (g, idx) in GROUP_NAMES.iter().zip(&groups) {
            joint_embed.push(lin(&format!("joint_embed.{g}_embed"), idx.len(), p)?);
            out.push(lin(&format!("out.{g}_out"), p, idx.len())?);
        }
        let text_layers = (0..d.text_layers)
            .map(|i| {
                EncoderLayer::load(
                    file,
                    &format!("{D}textTransEncoder.layers.{i}"),
                    tl,
                    d.text_ff_size,
                    ty,
                )
            })
            .collect::<Result<Vec<_>>>()?;
        let mut layers = Vec::with_capacity(d.num_layers);
        for i in 0..d.num_layers {
            let c = format!("{D}temporal_decoder_blocks.{i}.ca_block");
            let scalar = |name: &str| -> Result<f32> {
                let v = file.tensor(&format!("{c}.{name}"), &[1])?.data()[0];
                if !(v.is_finite() && v != 0.0) {
                    return Err(bad_file!(
                        "`{c}.{name}` is {v}: it must be finite and nonzero"
                    ));
                }
                Ok(v)
            };
            let bw = file.tensor(&format!("{c}.body_weight"), &[GROUPS, GROUPS])?;
            let mut body_mix = bw.data().to_vec();
            kernels::softmax_rows(&mut body_mix, GROUPS);
            let tpl = |name: &str, n_out| {
                Mlp::load(file, &format!("{c}.{name}"), p, d.ffn_dim, n_out, ty)
            };
            let sami = Sami {
                norm: LayerNorm::load(file, &format!("{c}.norm"), p)?,
                text_norm: LayerNorm::load(file, &format!("{c}.text_norm"), tl)?,
                motion_moe: Moe::load(
                    file,
                    &format!("{c}.motion_moe"),
                    d.max_seq_len,
                    GROUPS,
                    p,
                    d.motion_expert_hidden,
                    3 * p,
                    d,
                    ty,
                )?,
                text_moe: Moe::load(
                    file,
                    &format!("{c}.text_moe"),
                    d.max_text_len,
                    1,
                    tl,
                    d.text_expert_hidden,
                    2 * p,
                    d,
                    ty,
                )?,
                body_mix,
                sigma: scalar("sigma")?,
                t_sigma: scalar("t_sigma")?,
                template_t: tpl("template_t", 1)?,
                templates: [
                    tpl("template_s", p)?,
                    tpl("template_v", p)?,
                    tpl("template_a", p)?,
                    tpl("template_j", p)?,
                ],
                proj_out: Stylization::load(
                    file,
                    &format!("{c}.proj_out"),
                    l,
                    d.time_embed_dim,
                    ty,
                )?,
            };
            let f = format!("{D}temporal_decoder_blocks.{i}.ffn");
            let parts = (0..GROUPS)
                .map(|g| {
                    Ok(Mlp {
                        fc1: Linear::load(
                            file,
                            &format!("{f}.linear1_list.{g}"),
                            p,
                            d.ffn_dim,
                            ty,
                        )?,
                        fc2: Linear::load(
                            file,
                            &format!("{f}.linear2_list.{g}"),
                            d.ffn_dim,
                            p,
                            ty,
                        )?,
                        hidden: d.ffn_dim,
                    })
                })
                .collect::<Result<Vec<_>>>()?;
            let ffn = Sffn {
                parts,
                proj_out: Stylization::load(
                    file,
                    &format!("{f}.proj_out"),
                    l,
                    d.time_embed_dim,
                    ty,
                )?,
            };
            layers.push(Layer { sami, ffn });
        }
        Ok(FinemogenDenoiser {
            cfg: d.clone(),
            num_timesteps,
            text_pre_proj: lin("text_pre_proj", d.clip_width, tl)?,
            text_layers,
            text_ln: LayerNorm::load(file, &format!("{D}text_ln"), tl)?,
            time_embed: [
                lin("time_embed.0", l, d.time_embed_dim)?,
                lin("time_embed.2", d.time_embed_dim, d.time_embed_dim)?,
            ],
            groups,
            joint_embed,
            out,
            layers,
        })
    }

    /// The sizes the network was built from.
    pub fn config(&self) -> &FinemogenConfig {
        &self.cfg
    }

    /// CLIP's `ln_final` over every position → `text_pre_proj` → the encoder → `text_ln`:
    /// `[max_text_len, text_latent_dim]`.
    pub fn encode_text(&self, text: &TextModel, prompt: &str) -> Result<Vec<f32>> {
        let TextModel::Clip { encoder, context } = text else {
            return Err(invalid_arg!("FineMoGen needs a CLIP text encoder"));
        };
        let c = &self.cfg;
        let clip = encoder.encode(prompt, *context)?;
        let n = clip.ids.len();
        if n != c.max_text_len {
            return Err(invalid_arg!(
                "the text encoder gave {n} positions, FineMoGen reads {}",
                c.max_text_len
            ));
        }
        let tl = c.text_latent_dim;
        let mut x = vec![0f32; n * tl];
        self.text_pre_proj.forward(&clip.tokens, n, &mut x);
        let shape = LayerShape {
            width: tl,
            heads: c.text_heads,
            ff: c.text_ff_size,
            act: Activation::Gelu,
            eps: c.layer_norm_eps,
        };
        let mut b = LayerBuffers::default();
        for layer in &self.text_layers {
            layer.forward(&mut x, 1, n, shape, &mut b);
        }
        kernels::layer_norm(
            &mut x,
            tl,
            self.text_ln.weight.data(),
            self.text_ln.bias.data(),
            c.layer_norm_eps,
        );
        Ok(x)
    }

    /// Encodes stages: each distinct text once per stage, then every layer's text-MoE
    /// features over the guidance batch (the sequences, then their null copies).
    pub fn encode_stage_texts(
        &self,
        text: &TextModel,
        stages: &[Stage],
    ) -> Result<FinemogenCondition> {
        let c = &self.cfg;
        if stages.is_empty() || stages.len() > MAX_STAGES {
            return Err(invalid_arg!(
                "{} stages: FineMoGen takes 1 to {MAX_STAGES}",
                stages.len()
            ));
        }
        let mut xf: Vec<Vec<f32>> = Vec::new();
        // A text repeated across stages is encoded once and copied: the encoder is
        // deterministic, so the sequences (and the MoE batch below) are the same as encoding it
        // again.
        let mut encoded: Vec<(&str, usize)> = Vec::new();
        fn push<'a>(
            t: &'a str,
            encoded: &mut Vec<(&'a str, usize)>,
            xf: &mut Vec<Vec<f32>>,
            encode: impl FnOnce(&str) -> Result<Vec<f32>>,
        ) -> Result<()> {
            let seq = match encoded.iter().find(|(e, _)| *e == t) {
                Some(&(_, j)) => xf[j].clone(),
                None => encode(t)?,
            };
            encoded.push((t, xf.len()));
            xf.push(seq);
            Ok(())
        }
        let encode = |t: &str| self.encode_text(text, t);
        let mut out = Vec::with_capacity(stages.len());
        for (i, s) in stages.iter().enumerate() {
            if s.frames == 0 || s.frames > c.max_seq_len {
                return Err(invalid_arg!(
                    "stage {i} has {} frames: a FineMoGen stage has 1 to {} (its position table)",
                    s.frames,
                    c.max_seq_len
                ));
            }
            if s.text.trim().is_empty() {
                return Err(invalid_arg!("stage {i} has no text"));
            }
            let mut texts: Vec<&str> = vec![&s.text];
            let first = xf.len();
            push(&s.text, &mut encoded, &mut xf, encode)?;
            let mut heads = [first; GROUPS];
            for (h, part) in s.parts.iter().enumerate() {
                let Some(p) = part.as_deref().filter(|p| !p.trim().is_empty()) else {
                    continue;
                };
                heads[h] = match texts.iter().position(|t| *t == p) {
                    Some(j) => first + j,
                    None => {
                        texts.push(p);
                        push(p, &mut encoded, &mut xf, encode)?;
                        xf.len() - 1
                    }
                };
            }
            out.push(StageText {
                frames: s.frames,
                heads,
            });
        }
        // The text MoE of each layer over [sequences, null copies]: routing sees both.
        let (nt, tl, m) = (c.max_text_len, c.text_latent_dim, xf.len());
        let mut tokens = vec![0f32; 2 * m * nt * tl];
        let mut text_feat = Vec::with_capacity(self.layers.len());
        let mut scratch = MoeScratch::default();
        let mut text_dropped = 0;
        for layer in &self.layers {
            let s = &layer.sami;
            let (half, _) = tokens.split_at_mut(m * nt * tl);
            for (dst, src) in half.chunks_exact_mut(nt * tl).zip(&xf) {
                dst.copy_from_slice(src);
            }
            kernels::layer_norm(
                half,
                tl,
                s.text_norm.weight.data(),
                s.text_norm.bias.data(),
                c.layer_norm_eps,
            );
            for seq in half.chunks_exact_mut(nt * tl) {
                kernels::add_inplace(seq, s.text_moe.embedding.data());
            }
            tokens.copy_within(..m * nt * tl, m * nt * tl);
            let mut feat = vec![0f32; m * nt * 2 * c.part_dim];
            text_dropped +=
                s.text_moe
                    .forward(&tokens, 2 * m * nt, m * nt, &mut feat, &mut scratch);
            text_feat.push(feat);
        }
        Ok(FinemogenCondition {
            frames: out.iter().map(|s| s.frames).collect(),
            stages: out,
            xf,
            text_feat,
            text_dropped,
        })
    }

    /// The network rows of a batch of conditions, each `rows` sample rows: a text condition
    /// gives one row per stage, a null condition the stage layout of the batch's first text
    /// condition (or one stage of `rows` frames). Returns the rows and the padded length.
    fn net_rows<'a>(
        &self,
        conds: &[&'a Condition],
        rows: usize,
        out: &mut NetRows<'a>,
    ) -> Result<usize> {
        // A single stage (a plain prompt) covers the sample's rows.
        let whole = [rows];
        let layout_of = |tc: &'a FinemogenCondition| -> &'a [usize] {
            if tc.frames.len() > 1 {
                &tc.frames
            } else {
                &[]
            }
        };
        let mut layout: &[usize] = conds
            .iter()
            .find_map(|c| c.get::<FinemogenCondition>())
            .map(layout_of)
            .unwrap_or(&[]);
        if layout.is_empty() {
            layout = &whole;
        }
        let t = layout.iter().copied().max().unwrap_or(0);
        if rows != layout.len() * t {
            return Err(invalid_arg!(
                "a sample of {rows} rows does not match the condition's {} stages of up to {t} frames ({} rows)",
                layout.len(),
                layout.len() * t
            ));
        }
        if t > self.cfg.max_seq_len {
            return Err(invalid_arg!(
                "{t} frames in one stage: FineMoGen generates at most {} frames per prompt or stage (give stages for longer motions)",
                self.cfg.max_seq_len
            ));
        }
        out.len = 0;
        for c in conds {
            let text = c.get::<FinemogenCondition>();
            if text.is_none() && c.get::<FinemogenNull>().is_none() {
                return Err(invalid_arg!(
                    "a condition was made for another architecture"
                ));
            }
            if let Some(tc) = text {
                let own = layout_of(tc);
                if own != layout && !(own.is_empty() && layout.len() == 1) {
                    return Err(invalid_arg!(
                        "conditions of one batch must have the same stages"
                    ));
                }
            }
            let first = out.len;
            let mut start = 0;
            for (i, &frames) in layout.iter().enumerate() {
                out.rows[out.len] = NetRow {
                    frames,
                    start,
                    group: (first, layout.len()),
                    text: text.map(|tc| (tc, i)),
                };
                out.len += 1;
                start += frames;
            }
        }
        Ok(t)
    }

    /// The forward pass over network rows of `t` frames each: `x` and `out` are
    /// `[rows.len() · t, input_feats]`.
    #[allow(clippy::too_many_arguments)]
    fn forward_rows(
        &self,
        x: &[f32],
        rows: &[NetRow],
        t: usize,
        step: f32,
        out: &mut [f32],
        ws: &mut FinemogenWorkspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let c = &self.cfg;
        let (p, l, f) = (c.part_dim, GROUPS * c.part_dim, c.input_feats);
        let n = rows.len() * t;
        // Time embedding, shared by every row: sinusoid (cos first) → Linear → SiLU → Linear;
        // the stylization blocks read SiLU of it.
        let sin = sized(&mut ws.tmp, l);
        kernels::sinusoid_cos_first(step, sin);
        let hid = sized(&mut ws.hid, c.time_embed_dim);
        self.time_embed[0].forward(sin, 1, hid);
        kernels::silu(hid);
        let emb = sized(&mut ws.emb, c.time_embed_dim);
        self.time_embed[1].forward(hid, 1, emb);
        kernels::silu(emb);

        // PoseEncoder: each group's features through its Linear.
        let h = sized(&mut ws.h, n * l);
        for (g, (idx, lin)) in self.groups.iter().zip(&self.joint_embed).enumerate() {
            let gi = sized(&mut ws.part_in, n * idx.len());
            for (dst, src) in gi.chunks_exact_mut(idx.len()).zip(x.chunks_exact(f)) {
                for (d, &i) in dst.iter_mut().zip(idx) {
                    *d = src[i];
                }
            }
            let go = sized(&mut ws.part_out, n * p);
            lin.forward(gi, n, go);
            for (dst, src) in h.chunks_exact_mut(l).zip(go.chunks_exact(p)) {
                dst[g * p..(g + 1) * p].copy_from_slice(src);
            }
        }
        ws.motion_dropped = 0;
        for (li, layer) in self.layers.iter().enumerate() {
            cancel.check()?;
            self.sami(li, &layer.sami, rows, t, ws);
            self.sffn(&layer.ffn, n, ws);
        }

        // PoseDecoder: the parts scattered to their features, averaged with the body's output
        // (natural order).
        out[..n * f].fill(0.0);
        let h = &ws.h;
        for (g, (idx, lin)) in self.groups.iter().zip(&self.out).enumerate() {
            let gi = sized(&mut ws.part_in, n * p);
            for (dst, src) in gi.chunks_exact_mut(p).zip(h.chunks_exact(l)) {
                dst.copy_from_slice(&src[g * p..(g + 1) * p]);
            }
            let go = sized(&mut ws.part_out, n * idx.len());
            lin.forward(gi, n, go);
            for (dst, src) in out.chunks_exact_mut(f).zip(go.chunks_exact(idx.len())) {
                if g < PART_COUNT {
                    for (&i, &v) in idx.iter().zip(src) {
                        dst[i] = v;
                    }
                } else {
                    for (d, &v) in dst.iter_mut().zip(src) {
                        *d = (*d + v) / 2.0;
                    }
                }
            }
        }
        Ok(())
    }

    /// `h ← h + stylization(spatial + temporal)` for one SAMI block.
    fn sami(&self, li: usize, s: &Sami, rows: &[NetRow], t: usize, ws: &mut FinemogenWorkspace) {
        let c = &self.cfg;
        let (p, l) = (c.part_dim, GROUPS * c.part_dim);
        let n = rows.len() * t;
        let eps = c.layer_norm_eps;
        // Motion tokens: per-part LayerNorm + the (frame, part) embedding → MoE → (spatial
        // value, key, value).
        let tokens = sized(&mut ws.tokens, n * l);
        tokens.copy_from_slice(&ws.h[..n * l]);
        kernels::layer_norm(tokens, p, s.norm.weight.data(), s.norm.bias.data(), eps);
        let emb = &s.motion_moe.embedding.data()[..t * l];
        for row in tokens.chunks_exact_mut(t * l) {
            kernels::add_inplace(row, emb);
        }
        let feat = sized(&mut ws.feat, n * GROUPS * 3 * p);
        ws.motion_dropped +=
            s.motion_moe
                .forward(tokens, n * GROUPS, n * GROUPS, feat, &mut ws.moe);

        // Spatial branch: y_s[h] = Σ_g softmax(body_weight)[h, g] · value_s[g].
        let y = sized(&mut ws.ys, n * l);
        for (dst, src) in y.chunks_exact_mut(l).zip(feat.chunks_exact(GROUPS * 3 * p)) {
            for hh in 0..GROUPS {
                let o = &mut dst[hh * p..(hh + 1) * p];
                o.fill(0.0);
                for g in 0..GROUPS {
                    let w = s.body_mix[hh * GROUPS + g];
                    for (a, &b) in o.iter_mut().zip(&src[g * 3 * p..g * 3 * p + p]) {
                        *a += w * b;
                    }
                }
            }
        }

        // Templates per (row, head): softmax over the sequence of each key channel, then
        // G[d, :] = Σ_n w[n, d] · value[n, :]. Masked tokens (null rows' text, padded frames:
        // keys offset by −1e6, values zeroed in the official code) have weight exactly 0 after
        // the f32 softmax and are left out.
        let nt = c.max_text_len;
        let gsz = p * p;
        let g_all = sized(&mut ws.g, rows.len() * GROUPS * gsz);
        for (b, row) in rows.iter().enumerate() {
            for hh in 0..GROUPS {
                let text = row.text.map(|(tc, i)| {
                    let seq = tc.stages[i].heads[if hh < PART_COUNT { hh } else { PART_COUNT }];
                    &tc.text_feat[li][seq * nt * 2 * p..(seq + 1) * nt * 2 * p]
                });
                let tn = if text.is_some() { nt } else { 0 };
                let len = tn + row.frames;
                // Keys transposed `[p, len]` (one key channel per row) and values `[len, p]`:
                // text tokens first, then the valid frames.
                let kt = sized(&mut ws.keys, p * len);
                let vals = sized(&mut ws.vals, len * p);
                if let Some(tf) = text {
                    for (j, src) in tf.chunks_exact(2 * p).enumerate() {
                        for (d, &k) in src[..p].iter().enumerate() {
                            kt[d * len + j] = k;
                        }
                        vals[j * p..(j + 1) * p].copy_from_slice(&src[p..]);
                    }
                }
                for k in 0..row.frames {
                    let src = &feat[((b * t + k) * GROUPS + hh) * 3 * p..][..3 * p];
                    for (d, &key) in src[p..2 * p].iter().enumerate() {
                        kt[d * len + tn + k] = key;
                    }
                    vals[(tn + k) * p..(tn + k + 1) * p].copy_from_slice(&src[2 * p..]);
                }
                kernels::softmax_rows(kt, len);
                let g = &mut g_all[(b * GROUPS + hh) * gsz..][..gsz];
                ws.rhs.repack_kn(vals, len, p);
                kernels::linear_packed(kt, &ws.rhs, None, Activation::None, g, p);
            }
        }
        // Anchors and Taylor coefficients of every template row.
        let nrows = rows.len() * GROUPS * p;
        let tt = sized(&mut ws.tt, nrows);
        s.template_t.forward(g_all, nrows, tt, &mut ws.mlp);
        for (i, tpl) in s.templates.iter().enumerate() {
            let o = sized(&mut ws.tpl[i], nrows * p);
            tpl.forward(g_all, nrows, o, &mut ws.mlp);
        }
        let len_unit = c.max_seq_len as f32;
        // τ = sigmoid(t/t_sigma)·len/S + start/S per (row, head, template).
        for (b, row) in rows.iter().enumerate() {
            let scale = row.frames as f32 / len_unit;
            let offset = row.start as f32 / len_unit;
            for v in &mut tt[b * GROUPS * p..(b + 1) * GROUPS * p] {
                let raw = 1.0 / (1.0 + (-(*v / s.t_sigma)).exp());
                *v = raw * scale + offset;
            }
        }
        // Power-series coefficients: a0 = s − vτ + aτ² − jτ³, a1 = v − 2aτ + 3jτ²,
        // a2 = a − 3jτ, a3 = j (in place of s, v, a, j).
        {
            let [ts, tv, ta, tj] = &mut ws.tpl;
            for (r, &tau) in tt.iter().enumerate() {
                let (tau2, tau3) = (tau * tau, tau * tau * tau);
                for k in r * p..(r + 1) * p {
                    let (sv, vv, av, jv) = (ts[k], tv[k], ta[k], tj[k]);
                    ts[k] = sv - vv * tau + av * tau2 - jv * tau3;
                    tv[k] = vv - 2.0 * av * tau + 3.0 * jv * tau2;
                    ta[k] = av - 3.0 * jv * tau;
                }
            }
        }
        // Read back at every frame (padded ones too): weights softmax_j(−((t_k − τ_j)·S)²/σ)
        // over the templates of every stage of the row's group.
        let ytmp = sized(&mut ws.tmp, n * l);
        for (b, row) in rows.iter().enumerate() {
            let (g0, gn) = row.group;
            let nj = gn * p;
            for hh in 0..GROUPS {
                let coef = sized(&mut ws.coef, t * nj);
                for k in 0..t {
                    let tk = k as f32 / len_unit + row.start as f32 / len_unit;
                    let cr = &mut coef[k * nj..(k + 1) * nj];
                    for (gi, cj) in cr.chunks_exact_mut(p).enumerate() {
                        let taus = &tt[((g0 + gi) * GROUPS + hh) * p..][..p];
                        for (cv, &tau) in cj.iter_mut().zip(taus) {
                            let dist = (tk - tau) * len_unit;
                            *cv = -(dist * dist) / s.sigma;
                        }
                    }
                    kernels::softmax_rows(cr, nj);
                }
                // The group's coefficients `[templates, a0 | a1 | a2 | a3]`, mixed by one GEMM.
                let acat = sized(&mut ws.acat, nj * 4 * p);
                for (j, dst) in acat.chunks_exact_mut(4 * p).enumerate() {
                    let r = ((g0 + j / p) * GROUPS + hh) * p + j % p;
                    for q in 0..4 {
                        dst[q * p..(q + 1) * p].copy_from_slice(&ws.tpl[q][r * p..(r + 1) * p]);
                    }
                }
                let acc = sized(&mut ws.acc, t * 4 * p);
                ws.rhs.repack_kn(acat, nj, 4 * p);
                kernels::linear_packed(coef, &ws.rhs, None, Activation::None, acc, t);
                for (k, a) in acc.chunks_exact(4 * p).enumerate() {
                    let tk = k as f32 / len_unit + row.start as f32 / len_unit;
                    let (t2, t3) = (tk * tk, tk * tk * tk);
                    let dst = &mut ytmp[(b * t + k) * l + hh * p..][..p];
                    for (i, o) in dst.iter_mut().enumerate() {
                        *o = a[i] + a[p + i] * tk + a[2 * p + i] * t2 + a[3 * p + i] * t3;
                    }
                }
            }
        }
        kernels::add_inplace(y, ytmp);
        let (s1, s2) = (&mut ws.styl.0, &mut ws.styl.1);
        s.proj_out
            .add(&mut ws.h[..n * l], y, n, &ws.emb, eps, s1, s2);
    }

    /// `h ← h + stylization(per-part FFN(h))`. With several threads each task runs a
    /// contiguous range of the parts with its calls unsplit (each part's output is its own
    /// columns, so the bits do not depend on the split).
    fn sffn(&self, ffn: &Sffn, n: usize, ws: &mut FinemogenWorkspace) {
        let c = &self.cfg;
        let (p, l) = (c.part_dim, GROUPS * c.part_dim);
        let parts = ffn.parts.len();
        let tasks = kernels::threads().min(parts).max(1);
        if ws.part_tasks.len() < tasks {
            ws.part_tasks.resize_with(tasks, PartScratch::default);
        }
        let range = |j: usize| parts * j / tasks..parts * (j + 1) / tasks;
        let h = &ws.h[..n * l];
        let run = |j: usize, buf: &mut PartScratch| {
            let out = sized(&mut buf.out, range(j).len() * n * p);
            for (g, go) in range(j).zip(out.chunks_exact_mut(n * p)) {
                let gi = sized(&mut buf.input, n * p);
                for (dst, src) in gi.chunks_exact_mut(p).zip(h.chunks_exact(l)) {
                    dst.copy_from_slice(&src[g * p..(g + 1) * p]);
                }
                ffn.parts[g].forward(gi, n, go, &mut buf.hidden);
            }
        };
        if tasks == 1 {
            run(0, &mut ws.part_tasks[0]);
        } else {
            ws.part_tasks[..tasks]
                .par_iter_mut()
                .enumerate()
                .for_each(|(j, buf)| kernels::serial(|| run(j, buf)));
        }
        let y = sized(&mut ws.ys, n * l);
        for (j, buf) in ws.part_tasks[..tasks].iter().enumerate() {
            for (g, go) in range(j).zip(buf.out.chunks_exact(n * p)) {
                for (dst, src) in y.chunks_exact_mut(l).zip(go.chunks_exact(p)) {
                    dst[g * p..(g + 1) * p].copy_from_slice(src);
                }
            }
        }
        let (s1, s2) = (&mut ws.styl.0, &mut ws.styl.1);
        ffn.proj_out
            .add(&mut ws.h[..n * l], y, n, &ws.emb, c.layer_norm_eps, s1, s2);
    }

    /// One forward pass with its workspace exposed (tests read the dropped counts).
    #[allow(clippy::too_many_arguments)]
    pub fn forward_with(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        conds: &[&Condition],
        out: &mut [f32],
        ws: &mut FinemogenWorkspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let f = self.cfg.input_feats;
        if conds.is_empty() || conds.len() > MAX_BATCH {
            return Err(invalid_arg!(
                "a forward pass takes 1 to {MAX_BATCH} conditions"
            ));
        }
        if x.len() != conds.len() * rows * f || out.len() != x.len() {
            return Err(invalid_arg!(
                "forward buffers do not match batch {} × {rows} rows × {f}",
                conds.len()
            ));
        }
        let mut net = NetRows::new();
        let tmax = self.net_rows(conds, rows, &mut net)?;
        self.forward_rows(x, &net.rows[..net.len], tmax, t, out, ws, cancel)
    }
}

impl Denoiser for FinemogenDenoiser {
    fn sample_dim(&self) -> usize {
        self.cfg.input_feats
    }

    fn encode_prompt(&self, text: &TextModel, prompt: &str) -> Result<Condition> {
        // One stage; its frame count is the session's, set when the session checks it.
        // One stage covering the session's frames (the layout reads a single stage as such).
        let stage = Stage::new(prompt, self.cfg.max_seq_len);
        Ok(Condition::new(self.encode_stage_texts(text, &[stage])?))
    }

    fn encode_stages(&self, text: &TextModel, stages: &[Stage]) -> Option<Result<Condition>> {
        Some(self.encode_stage_texts(text, stages).map(|c| {
            let frames = c.stage_frames().to_vec();
            Condition::with_stages(c, frames)
        }))
    }

    fn takes_stages(&self) -> bool {
        true
    }

    fn unconditional(&self, _text: &TextModel, _uncond: &str) -> Result<Condition> {
        Ok(Condition::new(FinemogenNull))
    }

    fn check_condition(&self, cond: &Condition) -> Result<()> {
        if let Some(c) = cond.get::<FinemogenCondition>() {
            let ok = c.text_feat.len() == self.layers.len()
                && c.xf
                    .iter()
                    .all(|x| x.len() == self.cfg.max_text_len * self.cfg.text_latent_dim);
            if !ok {
                return Err(invalid_arg!(
                    "the condition was made for another FineMoGen model"
                ));
            }
            return Ok(());
        }
        if cond.get::<FinemogenNull>().is_some() {
            return Ok(());
        }
        Err(invalid_arg!(
            "the condition was made for another architecture"
        ))
    }

    fn check_frames(&self, cond: &Condition, frames: usize) -> Result<()> {
        let max = self.cfg.max_seq_len;
        if cond.stage_frames().is_none() && frames > max {
            return Err(invalid_arg!(
                "{frames} frames for one prompt: FineMoGen generates at most {max} frames per prompt or stage (give stages for longer motions)"
            ));
        }
        Ok(())
    }

    /// w(t) = 1 + scale·t/T on x̂0, and always both row groups (the null rows take expert
    /// slots from the text rows, also at w = 1).
    fn guidance(&self, scale: f32, t: f32) -> Guidance {
        Guidance::Mix(1.0 + scale * t / self.num_timesteps as f32)
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
        self.forward_with(
            x,
            rows,
            t,
            conds,
            out,
            ws.get::<FinemogenWorkspace>(),
            cancel,
        )
    }

    fn linear_weight_bytes(&self) -> usize {
        let mut n = self.text_pre_proj.weight_bytes()
            + self
                .text_layers
                .iter()
                .map(|l| l.weight_bytes())
                .sum::<usize>()
            + self
                .time_embed
                .iter()
                .map(|l| l.weight_bytes())
                .sum::<usize>()
            + self
                .joint_embed
                .iter()
                .chain(&self.out)
                .map(|l| l.weight_bytes())
                .sum::<usize>();
        for l in &self.layers {
            let s = &l.sami;
            n += s.motion_moe.weight_bytes()
                + s.text_moe.weight_bytes()
                + s.template_t.weight_bytes()
                + s.templates.iter().map(|m| m.weight_bytes()).sum::<usize>()
                + s.proj_out.weight_bytes()
                + l.ffn.parts.iter().map(|m| m.weight_bytes()).sum::<usize>()
                + l.ffn.proj_out.weight_bytes();
        }
        n
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_parts_partition_the_features_and_the_body_permutes_them() {
        let g = group_indices();
        let sizes: Vec<usize> = g.iter().map(Vec::len).collect();
        assert_eq!(sizes, [24, 36, 48, 48, 48, 48, 11, 263]);
        let mut parts: Vec<usize> = g[..PART_COUNT].iter().flatten().copied().collect();
        parts.sort_unstable();
        assert_eq!(parts, (0..263).collect::<Vec<_>>());
        let mut body = g[PART_COUNT].clone();
        assert_eq!(
            &body[..11],
            &[0, 1, 2, 3, 193, 194, 195, 259, 260, 261, 262]
        );
        // Joint 1: ric 4..7, rot6d 67..73, local velocity 196..199.
        assert_eq!(
            &body[11..23],
            &[4, 5, 6, 67, 68, 69, 70, 71, 72, 196, 197, 198]
        );
        assert_ne!(body, (0..263).collect::<Vec<_>>());
        body.sort_unstable();
        assert_eq!(body, (0..263).collect::<Vec<_>>());
        // Head: joints 12 and 15.
        assert_eq!(&g[0][..3], &[37, 38, 39]);
        assert_eq!(&g[0][12..15], &[46, 47, 48]);
    }

    #[test]
    fn capacity_is_tutels() {
        // microsoft/tutel `fast_dispatch.py`, docs/official/finemogen.md#capacity-and-dropping:
        // k·⌊1.5·⌈n/16⌉⌋ — 30 slots for one prompt's text rows (2 × 77 tokens),
        // 588 for one 196-frame motion (2 × 196 × 8).
        assert_eq!(capacity(154, 16, 2, 1.5), 30);
        assert_eq!(capacity(3136, 16, 2, 1.5), 588);
        // ⌈5/4⌉ = 2, ⌊1.25·2⌋ = 2.
        assert_eq!(capacity(5, 4, 1, 1.25), 2);
    }

    fn routed(ws: &MoeScratch) -> Vec<Vec<(u32, f32)>> {
        ws.routed.clone()
    }

    #[test]
    fn routing_follows_priority_and_queues_second_choices_after_first_ones() {
        // Top-1: t0 → e0 (0.6), t1 → e1 (0.7), t2 → e0 (0.55); priority t1, t0, t2; two slots.
        // First choices: e1 ← t1, e0 ← t0, t2. Second choices queue after e0's two and e1's
        // one: t1 → e0 slot 2 (dropped), t0 → e1 slot 1, t2 → e1 slot 2 (dropped).
        let scores = [0.6, 0.4, 0.3, 0.7, 0.55, 0.45];
        let mut ws = MoeScratch::default();
        let dropped = route(&scores, 2, 2, 2, 3, &mut ws);
        assert_eq!(dropped, 2);
        assert_eq!(
            routed(&ws),
            vec![vec![(0, 0.6), (2, 0.55)], vec![(1, 0.7), (0, 0.4)]]
        );
        // Tokens past `used` compete for slots but are not routed.
        let dropped = route(&scores, 2, 2, 2, 1, &mut ws);
        assert_eq!(dropped, 2);
        assert_eq!(routed(&ws), vec![vec![(0, 0.6)], vec![(0, 0.4)]]);
    }

    #[test]
    fn routing_breaks_ties_by_token_order_and_renormalises_top_k() {
        // Equal tokens (a text row and its null copy): the first keeps the one slot.
        let scores = [0.5, 0.3, 0.2, 0.5, 0.3, 0.2];
        let mut ws = MoeScratch::default();
        assert_eq!(route(&scores, 3, 1, 1, 2, &mut ws), 1);
        assert_eq!(routed(&ws), vec![vec![(0, 1.0)], vec![], vec![]]);
        // Top-2 of [0.5, 0.3, 0.2]: gates 0.5/0.8 and 0.3/0.8, before any drop.
        assert_eq!(route(&scores[..3], 3, 2, 1, 1, &mut ws), 0);
        assert_eq!(
            routed(&ws),
            vec![vec![(0, 0.625)], vec![(0, 0.375)], vec![]]
        );
    }
}
