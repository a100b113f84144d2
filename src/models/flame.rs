//! FLAME (Kim et al., AAAI 2023): a transformer decoder that denoises a motion conditioned on a
//! language model's token states (kakaobrain/flame `src/models/components/text2motion_model.py`;
//! docs/official/flame.md#denoiser-forward-pass).
//!
//! The target sequence is `[ML, TS, CLS, motion frames]` plus sinusoidal positions; the
//! cross-attention memory is `[ML, TS, CLS, text tokens]` without positions. `ML` is the
//! motion-length embedding, `TS` the raw sinusoidal timestep, `CLS` the projected pooler output.
//! The decoder is post-LN with ReLU feed-forward and no final norm; the output splits into the
//! predicted noise ε and the variance interpolation value v.

use std::any::Any;
use std::sync::Arc;

use serde::Deserialize;

use crate::checkpoint::{ModelFile, Tensor};
use crate::config::validate::{
    check_eps, check_layers, expect_flow, expect_shape, expect_text, heads_divide, in_range,
    one_of, table_fits,
};
use crate::config::{
    section, Config, MAX_FEEDFORWARD, MAX_LAYERS, MAX_MOTION_POSITIONS, MAX_WIDTH,
};
use crate::edit::EditMethod;
use crate::error::{bad_file, invalid_arg, Result};
use crate::kernels::{self, AttentionScratch, WeightType};
use crate::text::TextOutput;

use super::layers::{activation, sized, Attention, CrossAttention, LayerNorm, Linear};
use super::{condition_views, Cancel, Condition, Denoiser, Family, FamilyConfig, TextModel};

/// The family's entry in [`super::FAMILIES`].
pub const FAMILY: Family = Family {
    architectures: &["flame"],
    parse: |arch, v| Ok(Arc::new(section::<FlameConfig>(v, arch, "denoiser")?)),
};

/// Number of tokens prepended to the motion and to the text: ML, TS, CLS.
const AUX_TOKENS: usize = 3;

/// FLAME's `Text2MotionTransformer` sizes (`configs/model/diffusion_hml3d.yaml`;
/// docs/official/flame.md#configuration): the `denoiser` section.
#[derive(Clone, Debug, Deserialize)]
pub struct FlameConfig {
    /// Features per frame, = the motion format's (`smpl24_6d`: 147); the network reads
    /// `[frames, motion_dim]` and outputs `[frames, 2·motion_dim]` (ε, then the variance value).
    pub motion_dim: usize,
    /// Width C of every token in the decoder (official: 768, the RoBERTa hidden size); even.
    pub model_channels: usize,
    /// Post-LN decoder layers (official: 8).
    pub num_layers: usize,
    /// Attention heads per layer; divides `model_channels` (official: 8). Not recoverable from
    /// the tensors' shapes, so the converter is told it.
    pub num_heads: usize,
    /// Width of each layer's feed-forward block (official: 2048).
    pub dim_feedforward: usize,
    /// Rows of the motion-length embedding table (official: 471); a motion of `L` frames uses
    /// row `L`, so at most `max_motion_length − 1` frames are generated.
    pub max_motion_length: usize,
    /// The feed-forward activation: `relu` (the official network and the default) or `gelu`.
    #[serde(default = "relu")]
    pub activation: String,
    /// LayerNorm's epsilon, in (0, 1] (default PyTorch's 1e-5).
    #[serde(default = "ln_eps_torch")]
    pub layer_norm_eps: f32,
}

fn relu() -> String {
    "relu".into()
}

fn ln_eps_torch() -> f32 {
    1e-5
}

impl FlameConfig {
    /// Bounds and names, without the file.
    pub fn check(&self) -> Result<()> {
        in_range("denoiser.motion_dim", self.motion_dim, 1, MAX_WIDTH)?;
        in_range("denoiser.model_channels", self.model_channels, 2, MAX_WIDTH)?;
        in_range("denoiser.num_layers", self.num_layers, 1, MAX_LAYERS)?;
        if !self.model_channels.is_multiple_of(2) {
            return Err(bad_file!(
                "config denoiser.model_channels {} is not even",
                self.model_channels
            ));
        }
        heads_divide(
            "denoiser.model_channels",
            self.model_channels,
            "denoiser.num_heads",
            self.num_heads,
        )?;
        in_range(
            "denoiser.dim_feedforward",
            self.dim_feedforward,
            1,
            MAX_FEEDFORWARD,
        )?;
        in_range(
            "denoiser.max_motion_length",
            self.max_motion_length,
            2,
            MAX_MOTION_POSITIONS,
        )?;
        table_fits(
            "denoiser.max_motion_length + 3",
            self.max_motion_length + 3,
            self.model_channels,
        )?;
        one_of("denoiser.activation", &self.activation, &["relu", "gelu"])?;
        check_eps("denoiser.layer_norm_eps", self.layer_norm_eps)
    }

    /// [`FlameConfig::check`], then the sizes against the file's tensors (no prefix).
    pub fn validate(&self, file: &ModelFile) -> Result<()> {
        self.check()?;
        let (c, d) = (self.model_channels, self.motion_dim);
        expect_shape(
            file,
            "motion_length_emb.weight",
            &[self.max_motion_length, c],
            "denoiser.max_motion_length, model_channels",
        )?;
        expect_shape(
            file,
            "input_projection.weight",
            &[c, d],
            "denoiser.model_channels, motion_dim",
        )?;
        check_layers(
            file,
            "denoiser.num_layers",
            self.num_layers,
            "tf_decoder.layers.",
        )?;
        expect_shape(
            file,
            "tf_decoder.layers.0.linear1.weight",
            &[self.dim_feedforward, c],
            "denoiser.dim_feedforward, model_channels",
        )?;
        expect_shape(
            file,
            "last_projection.weight",
            &[2 * d, c],
            "denoiser.motion_dim, model_channels",
        )
    }

    /// The largest frame count a session may ask for.
    pub fn max_frames(&self) -> usize {
        self.max_motion_length - 1
    }
}

impl FamilyConfig for FlameConfig {
    fn architecture(&self) -> &str {
        "flame"
    }

    fn check(&self, cfg: &Config) -> Result<()> {
        FlameConfig::check(self)?;
        expect_text(cfg, &["bert", "roberta"])?;
        expect_flow(cfg, false)?;
        if cfg.diffusion.uncond == "zeros" {
            return Err(bad_file!(
                "config diffusion.uncond `zeros`: FLAME models need `empty_prompt`"
            ));
        }
        Ok(())
    }

    fn validate(&self, file: &ModelFile) -> Result<()> {
        FlameConfig::validate(self, file)
    }

    fn feature_dim(&self) -> usize {
        self.motion_dim
    }

    fn max_frames(&self) -> usize {
        FlameConfig::max_frames(self)
    }

    fn summary(&self) -> String {
        format!(
            "FLAME transformer decoder, {} layers x {} channels, {} heads, ff {}",
            self.num_layers, self.model_channels, self.num_heads, self.dim_feedforward
        )
    }

    fn load(
        &self,
        file: &ModelFile,
        _cfg: &Config,
        text: &TextModel,
        ty: WeightType,
    ) -> Result<Box<dyn Denoiser>> {
        let TextModel::Bert(t) = text else {
            return Err(bad_file!("FLAME models need a BERT-family text encoder"));
        };
        Ok(Box::new(FlameDenoiser::load_with(
            file,
            self,
            t.hidden_size(),
            ty,
        )?))
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// One `nn.TransformerDecoderLayer` (post-LN).
struct DecoderLayer {
    self_attn: Attention,
    multihead_attn: CrossAttention,
    linear1: Linear,
    linear2: Linear,
    norm1: LayerNorm,
    norm2: LayerNorm,
    norm3: LayerNorm,
}

/// The conditioning FLAME derives from one text, computed once per prompt.
#[derive(Clone, Debug)]
pub struct FlameCondition {
    /// `text_pooler_proj(pooler_output)`: the CLS token, `[C]`.
    cls_token: Vec<f32>,
    text_len: usize,
    /// Every decoder layer's cross-attention keys and values of the memory rows fixed by the
    /// prompt (CLS, then the text tokens): `[layers, text_len + 1, 2C]`, computed once here
    /// rather than at every step.
    memory_kv: Vec<f32>,
}

/// A batch of row blocks inside a strided buffer: batch row `b` holds `len` rows of `stride`
/// values starting at `b * len * stride`; `at(col)` views the columns from `col` on.
#[derive(Clone, Copy)]
struct Rows<'a> {
    data: &'a [f32],
    stride: usize,
    len: usize,
}

impl<'a> Rows<'a> {
    fn at(self, col: usize) -> Rows<'a> {
        Rows {
            data: &self.data[col..],
            ..self
        }
    }

    fn row_block(&self, b: usize) -> &'a [f32] {
        &self.data[b * self.len * self.stride..]
    }
}

/// Reusable buffers for one forward pass, so steps after the first do not allocate.
#[derive(Default)]
pub struct Workspace {
    x: Vec<f32>,
    /// Per-thread attention buffers.
    scratch: AttentionScratch,
    memory: Vec<f32>,
    qkv: Vec<f32>,
    kv: Vec<f32>,
    attn: Vec<f32>,
    proj: Vec<f32>,
    hidden: Vec<f32>,
    frames_in: Vec<f32>,
    /// The raw timestep token.
    ts: Vec<f32>,
    /// Keys and values of the per-step memory rows (ML, TS), `[2, 2C]`.
    step_kv: Vec<f32>,
}

/// FLAME's `Text2MotionTransformer`, inference only.
pub struct FlameDenoiser {
    cfg: FlameConfig,
    text_hidden: usize,
    motion_length_emb: Tensor,
    input_projection: Linear,
    text_pooler_proj: Linear,
    text_h_proj: Linear,
    layers: Vec<DecoderLayer>,
    last_projection: Linear,
    /// Sinusoidal positions for every target position the model can see, `[max_len + 3, C]`.
    positions: Vec<f32>,
}

impl FlameDenoiser {
    /// Reads the denoiser's tensors (official FLAME names, no prefix), in module order so the
    /// first bad tensor is the one reported.
    pub fn load(file: &ModelFile, cfg: &FlameConfig, text_hidden: usize) -> Result<FlameDenoiser> {
        FlameDenoiser::load_with(file, cfg, text_hidden, WeightType::F32)
    }

    /// [`FlameDenoiser::load`] with the linear weights held (and multiplied) as `ty`.
    pub fn load_with(
        file: &ModelFile,
        cfg: &FlameConfig,
        text_hidden: usize,
        ty: WeightType,
    ) -> Result<FlameDenoiser> {
        cfg.validate(file)?;
        let c = cfg.model_channels;
        let d = cfg.motion_dim;
        let motion_length_emb =
            file.tensor("motion_length_emb.weight", &[cfg.max_motion_length, c])?;
        let input_projection = Linear::load(file, "input_projection", d, c, ty)?;
        let text_pooler_proj = Linear::load(file, "text_pooler_proj", text_hidden, c, ty)?;
        let text_h_proj = Linear::load(file, "text_h_proj", text_hidden, c, ty)?;
        let mut layers = Vec::with_capacity(cfg.num_layers);
        for n in 0..cfg.num_layers {
            let p = format!("tf_decoder.layers.{n}");
            layers.push(DecoderLayer {
                self_attn: Attention::load(file, &format!("{p}.self_attn"), c, ty)?,
                multihead_attn: CrossAttention::load(file, &format!("{p}.multihead_attn"), c, ty)?,
                linear1: Linear::load(file, &format!("{p}.linear1"), c, cfg.dim_feedforward, ty)?,
                linear2: Linear::load(file, &format!("{p}.linear2"), cfg.dim_feedforward, c, ty)?,
                norm1: LayerNorm::load(file, &format!("{p}.norm1"), c)?,
                norm2: LayerNorm::load(file, &format!("{p}.norm2"), c)?,
                norm3: LayerNorm::load(file, &format!("{p}.norm3"), c)?,
            });
        }
        let last_projection = Linear::load(file, "last_projection", c, 2 * d, ty)?;
        let rows = cfg.max_motion_length + AUX_TOKENS;
        let mut positions = vec![0.0; rows * c];
        for (p, row) in positions.chunks_exact_mut(c).enumerate() {
            kernels::sinusoid_cos_first(p as f32, row);
        }
        Ok(FlameDenoiser {
            cfg: cfg.clone(),
            text_hidden,
            motion_length_emb,
            input_projection,
            text_pooler_proj,
            text_h_proj,
            layers,
            last_projection,
            positions,
        })
    }

    /// Feature channels per frame (147 for FLAME's SMPL format).
    pub fn motion_dim(&self) -> usize {
        self.cfg.motion_dim
    }

    /// Output channels per frame: ε then the variance value.
    pub fn output_dim(&self) -> usize {
        2 * self.cfg.motion_dim
    }

    /// The largest frame count the motion-length embedding covers.
    pub fn max_frames(&self) -> usize {
        self.cfg.max_motion_length - 1
    }

    /// Bytes of the packed linear weights (the part [`WeightType`] changes).
    pub fn linear_weight_bytes(&self) -> usize {
        let layers: usize = self
            .layers
            .iter()
            .map(|l| {
                l.self_attn.weight_bytes()
                    + l.multihead_attn.weight_bytes()
                    + l.linear1.weight_bytes()
                    + l.linear2.weight_bytes()
            })
            .sum();
        layers
            + [
                &self.input_projection,
                &self.text_pooler_proj,
                &self.text_h_proj,
                &self.last_projection,
            ]
            .iter()
            .map(|l| l.weight_bytes())
            .sum::<usize>()
    }

    /// Projects a text encoding into FLAME's conditioning (once per prompt, not per step),
    /// including every layer's cross-attention keys and values of the prompt's memory rows.
    pub fn condition(&self, text: &TextOutput) -> Result<FlameCondition> {
        let c = self.cfg.model_channels;
        if text.pooled.len() != self.text_hidden || text.hidden.len() != text.len * self.text_hidden
        {
            return Err(invalid_arg!(
                "text encoding has hidden size {}, the denoiser expects {}",
                text.pooled.len(),
                self.text_hidden
            ));
        }
        let mut cls_token = vec![0.0; c];
        self.text_pooler_proj
            .forward(&text.pooled, 1, &mut cls_token);
        let mut text_tokens = vec![0.0; text.len * c];
        self.text_h_proj
            .forward(&text.hidden, text.len, &mut text_tokens);
        let fixed = text.len + 1;
        let mut memory = Vec::with_capacity(fixed * c);
        memory.extend_from_slice(&cls_token);
        memory.extend_from_slice(&text_tokens);
        let mut memory_kv = vec![0.0; self.layers.len() * fixed * 2 * c];
        for (layer, kv) in self
            .layers
            .iter()
            .zip(memory_kv.chunks_exact_mut(fixed * 2 * c))
        {
            layer.multihead_attn.kv.forward(&memory, fixed, kv);
        }
        Ok(FlameCondition {
            cls_token,
            text_len: text.len,
            memory_kv,
        })
    }

    /// One forward pass over a batch: row `b` denoises `x[b]` (`[frames, motion_dim]`) under
    /// `conds[b]` at model timestep `t`, writing `[frames, 2·motion_dim]` into `out[b]`.
    /// Every frame is valid (sampling never pads), so no key-padding mask is needed.
    pub fn forward(
        &self,
        x: &[f32],
        frames: usize,
        t: f32,
        conds: &[&FlameCondition],
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
        conds: &[&FlameCondition],
        out: &mut [f32],
        ws: &mut Workspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let c = self.cfg.model_channels;
        let d = self.cfg.motion_dim;
        let batch = conds.len();
        if frames == 0 || frames > self.max_frames() {
            return Err(invalid_arg!(
                "frames must be between 1 and {} for this model, got {frames}",
                self.max_frames()
            ));
        }
        if x.len() != batch * frames * d || out.len() != batch * frames * 2 * d {
            return Err(invalid_arg!(
                "forward buffers do not match batch {batch} × {frames} frames"
            ));
        }
        let seq = frames + AUX_TOKENS;
        let mem_len = conds.first().map_or(0, |k| k.text_len) + AUX_TOKENS;
        if conds.iter().any(|k| k.text_len + AUX_TOKENS != mem_len) {
            return Err(invalid_arg!(
                "all conditions in a batch must have the same text length"
            ));
        }

        // Motion tokens for the whole batch in one GEMM.
        let motion = sized(&mut ws.frames_in, batch * frames * c);
        self.input_projection.forward(x, batch * frames, motion);

        let ml = &self.motion_length_emb.data()[frames * c..(frames + 1) * c];
        let ts = sized(&mut ws.ts, c);
        kernels::sinusoid_cos_first(t, ts);
        let ts = &ws.ts[..c];

        // The memory rows that change per step (ML, TS) are shared by the batch; the prompt's
        // rows were projected to keys and values with the condition.
        let memory = sized(&mut ws.memory, 2 * c);
        memory[..c].copy_from_slice(ml);
        memory[c..].copy_from_slice(ts);

        let h = sized(&mut ws.x, batch * seq * c);
        for (b, cond) in conds.iter().enumerate() {
            let tgt = &mut h[b * seq * c..(b + 1) * seq * c];
            tgt[..c].copy_from_slice(ml);
            tgt[c..2 * c].copy_from_slice(ts);
            tgt[2 * c..3 * c].copy_from_slice(&cond.cls_token);
            tgt[3 * c..].copy_from_slice(&motion[b * frames * c..(b + 1) * frames * c]);
            for (v, p) in tgt.iter_mut().zip(&self.positions[..seq * c]) {
                *v += p;
            }
        }

        for (l, layer) in self.layers.iter().enumerate() {
            cancel.check()?;
            self.decoder_layer(l, layer, conds, seq, mem_len, ws);
        }

        // Keep the motion positions and project to ε and v.
        let h = &ws.x;
        let motion_out = sized(&mut ws.frames_in, batch * frames * c);
        for b in 0..batch {
            let src = &h[(b * seq + AUX_TOKENS) * c..(b + 1) * seq * c];
            motion_out[b * frames * c..(b + 1) * frames * c].copy_from_slice(src);
        }
        self.last_projection
            .forward(motion_out, batch * frames, out);
        Ok(())
    }

    /// Multi-head attention of every batch row's queries over that row's keys and values.
    fn attend(
        &self,
        batch: usize,
        q: Rows,
        k: Rows,
        v: Rows,
        out: &mut [f32],
        scratch: &mut AttentionScratch,
    ) {
        let c = self.cfg.model_channels;
        let heads = self.cfg.num_heads;
        for (b, out) in out.chunks_exact_mut(q.len * c).take(batch).enumerate() {
            scratch.attend(
                q.row_block(b),
                q.stride,
                k.row_block(b),
                k.stride,
                v.row_block(b),
                v.stride,
                q.len,
                k.len,
                heads,
                c / heads,
                None,
                false,
                out,
            );
        }
    }

    fn decoder_layer(
        &self,
        l: usize,
        layer: &DecoderLayer,
        conds: &[&FlameCondition],
        seq: usize,
        mem_len: usize,
        ws: &mut Workspace,
    ) {
        let c = self.cfg.model_channels;
        let batch = conds.len();
        let eps = self.cfg.layer_norm_eps;
        let rows = batch * seq;

        // Self-attention: x ← norm1(x + SelfAttn(x)).
        let heads = self.cfg.num_heads;
        layer.self_attn.self_attention(
            &ws.x,
            batch,
            seq,
            c,
            heads,
            &mut ws.qkv,
            &mut ws.attn,
            &mut ws.proj,
            &mut ws.scratch,
        );
        let proj = &ws.proj[..rows * c];
        layer.norm1.add_norm(&mut ws.x, proj, eps);

        // Cross-attention to the memory: x ← norm2(x + CrossAttn(x, memory)).
        let ca = &layer.multihead_attn;
        let q = sized(&mut ws.qkv, rows * c);
        ca.q.forward(&ws.x, rows, q);
        let step_kv = sized(&mut ws.step_kv, 2 * 2 * c);
        ca.kv.forward(&ws.memory, 2, step_kv);
        let fixed = (mem_len - 2) * 2 * c;
        let kv = sized(&mut ws.kv, batch * mem_len * 2 * c);
        for (dst, cond) in kv.chunks_exact_mut(mem_len * 2 * c).zip(conds) {
            dst[..2 * 2 * c].copy_from_slice(&ws.step_kv[..2 * 2 * c]);
            dst[2 * 2 * c..].copy_from_slice(&cond.memory_kv[l * fixed..(l + 1) * fixed]);
        }
        let attn = sized(&mut ws.attn, rows * c);
        let keys = Rows {
            data: kv,
            stride: 2 * c,
            len: mem_len,
        };
        let queries = Rows {
            data: q,
            stride: c,
            len: seq,
        };
        self.attend(
            batch,
            queries,
            keys.at(0),
            keys.at(c),
            attn,
            &mut ws.scratch,
        );
        let proj = sized(&mut ws.proj, rows * c);
        ca.out_proj.forward(attn, rows, proj);
        layer.norm2.add_norm(&mut ws.x, proj, eps);

        // Feed-forward: x ← norm3(x + linear2(act(linear1(x)))).
        let f = self.cfg.dim_feedforward;
        let hidden = sized(&mut ws.hidden, rows * f);
        let act = activation(&self.cfg.activation);
        layer.linear1.forward_act(&ws.x, rows, hidden, act);
        let proj = sized(&mut ws.proj, rows * c);
        layer.linear2.forward(hidden, rows, proj);
        layer.norm3.add_norm(&mut ws.x, proj, eps);
    }
}

impl Denoiser for FlameDenoiser {
    fn sample_dim(&self) -> usize {
        self.motion_dim()
    }

    fn output_dim(&self) -> usize {
        FlameDenoiser::output_dim(self)
    }

    fn encode_prompt(&self, text: &TextModel, prompt: &str) -> Result<Condition> {
        let TextModel::Bert(t) = text else {
            return Err(invalid_arg!("FLAME models need a BERT-family text encoder"));
        };
        Ok(Condition::new(self.condition(&t.encode(prompt)?)?))
    }

    fn unconditional(&self, text: &TextModel, _uncond: &str) -> Result<Condition> {
        // The configuration's check allows only `empty_prompt`.
        self.encode_prompt(text, "")
    }

    fn check_condition(&self, cond: &Condition) -> Result<()> {
        match cond.get::<FlameCondition>() {
            Some(_) => Ok(()),
            None => Err(invalid_arg!(
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
        ws: &mut super::Workspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let (views, n) = condition_views::<FlameCondition>(conds)?;
        self.forward_cancellable(x, rows, t, &views[..n], out, ws.get(), cancel)
    }

    fn default_edit_method(&self) -> EditMethod {
        EditMethod::NoisedReference
    }

    fn linear_weight_bytes(&self) -> usize {
        FlameDenoiser::linear_weight_bytes(self)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}
