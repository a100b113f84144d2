//! MotionLCM (Dai et al., ECCV 2024, "MotionLCM: Real-time Controllable Motion Generation via
//! Latent Consistency Model"; Dai-Wenxun/MotionLCM, tags v1.0 f534a7f and v2.0 086f8db): MLD's
//! latent denoiser distilled into a latent consistency model that makes a whole motion in 1 to 4
//! network evaluations.
//!
//! The network is MLD's ([`super::mld`]; `mld/models/architectures/mld_denoiser.py`,
//! `mld_vae.py`), so this file holds what the distillation changes around it rather than a
//! second copy of the skip transformer:
//! - the guidance embedding: the scale `w` (the session's guidance minus 1, as the official
//!   `_diffusion_reverse` embeds `guidance_scale − 1`) becomes a sine-first sinusoid
//!   ([`crate::kernels::guidance_embedding`]) that `time_embedding.cond_proj` adds to the time
//!   sinusoid; one network pass per step, no unconditional pass ([`Guidance::Embedded`]);
//! - the latent: v1 keeps MLD's `[1, 256]`; v2 samples `[16, 32]`, which `latent_pre` /
//!   `latent_post` carry to and from the width 256, and its VAE decoder reads through its own
//!   `latent_post`; v2's `emb_proj` has no ReLU;
//! - the text encoder: sentence-t5-large's normalised sentence vector, not CLIP
//!   ([`crate::text::t5`]);
//! - the sampler: the latent consistency sampler ([`crate::diffusion::lcm`]), with v1's grid or
//!   v2's table of timesteps and v2's guidance per step count (`defaults.guidance_by_steps`).
//!
//! Schema: the `denoiser` section is MLD's plus `latent_channels` (C), `cond_dim` and
//! `text_activation` (`relu` | `none`); the `vae` section is MLD's plus `latent_channels`
//! (docs/model-files-latent.md).

use std::any::Any;
use std::sync::Arc;

use serde::Deserialize;

use crate::checkpoint::ModelFile;
use crate::checkpoint::Tensor;
use crate::config::validate::{expect_shape, heads_divide, in_range, in_range_f32, one_of};
use crate::config::{
    section, Config, TextConfig, MAX_FEEDFORWARD, MAX_LAYERS, MAX_MOTION_POSITIONS, MAX_WIDTH,
};
use crate::diffusion::Spacing;
use crate::error::{bad_file, invalid_arg, Result};
use crate::kernels::{self, WeightType};

use super::backward::DenoiserTape;
use super::layers::{activation, sized, EncoderLayer, LayerShape, Linear};
use super::mld::{
    LatentParts, MldConfig, MldVaeConfig, MldWorkspace, Part, SkipStack, StackBuffers, Taps,
    VaeDecoder,
};
use super::{
    check_text_vector, text_vector_views, Cancel, Condition, Denoiser, Family, FamilyConfig,
    Guidance, MldDenoiser, MldFamily, MotionDecoder, TextModel, Workspace,
};

/// The family's entry in [`super::FAMILIES`].
pub const FAMILY: Family = Family {
    architectures: &["motionlcm"],
    parse: |arch, v| {
        let denoiser: MotionLcmConfig = section(v, arch, "denoiser")?;
        let vae: MotionLcmVaeConfig = section(v, arch, "vae")?;
        let control: Option<ControlConfig> = match v.get("control") {
            None | Some(serde_json::Value::Null) => None,
            Some(_) => Some(section(v, arch, "control")?),
        };
        Ok(Arc::new(MotionLcmFamily {
            control,
            mld: MldFamily {
                denoiser: denoiser.mld.clone(),
                vae: vae.mld.clone(),
            },
            denoiser,
            vae,
        }))
    },
};

/// The denoiser's section: MLD's sizes and what the distillation adds.
#[derive(Clone, Debug, Deserialize)]
pub struct MotionLcmConfig {
    /// MLD's sizes (`latent_dim` is the transformer's width D, 256 in both releases).
    #[serde(flatten)]
    pub mld: MldConfig,
    /// Channels of a latent token C: D for v1 (`[1, 256]`), 32 for v2 (`[16, 32]`, with
    /// `latent_pre`/`latent_post` between C and D).
    pub latent_channels: usize,
    /// Width of the guidance embedding (`time_embedding.cond_proj`'s inputs: 256), even, ≥ 4.
    pub cond_dim: usize,
    /// What `emb_proj` applies before its Linear: `relu` (v1) or `none` (v2).
    pub text_activation: String,
}

/// The VAE decoder's section: MLD's sizes and the latent's channels.
#[derive(Clone, Debug, Deserialize)]
pub struct MotionLcmVaeConfig {
    /// MLD's decoder sizes.
    #[serde(flatten)]
    pub mld: MldVaeConfig,
    /// = `denoiser.latent_channels`; when it differs from `latent_dim` the decoder reads the
    /// latent through `vae.latent_post` (C → D).
    pub latent_channels: usize,
}

/// The trajectory ControlNet's section (`control`; files converted from a control checkpoint).
#[derive(Clone, Debug, Deserialize)]
pub struct ControlConfig {
    /// Joints of a hint frame (HumanML3D's 22); `control.mean_raw`/`std_raw` are `[joints, 3]`.
    pub joints: usize,
    /// Layers of the trajectory encoder's skip stack (odd: 9).
    pub layers: usize,
    /// Its attention heads (4).
    pub heads: usize,
    /// Its feed-forward width (1024).
    pub ff_size: usize,
    /// Rows of its position table: global tokens + hint frames.
    pub max_len: usize,
    /// Between the condition embedding's three Linears: `none` (v1) or `silu` (v2).
    pub embed_activation: String,
    /// The condition embedding's inner width (v1: the latent's 256; v2: 256).
    pub embed_dim: usize,
    /// Which hint frames the encoder attends to: `row_sum` (v1: a frame whose normalised
    /// values do not sum to 0) or `mask` (v2: a frame with any constrained value).
    pub frame_mask: String,
    /// The residuals' factor (v1's `control_scale`: 1).
    #[serde(default = "one")]
    pub scale: f32,
}

fn one() -> f32 {
    1.0
}

/// A MotionLCM file's configuration.
#[derive(Clone, Debug)]
pub struct MotionLcmFamily {
    /// The trajectory ControlNet's section, when the file has one.
    pub control: Option<ControlConfig>,
    /// The denoiser's section.
    pub denoiser: MotionLcmConfig,
    /// The VAE decoder's section.
    pub vae: MotionLcmVaeConfig,
    /// The same sizes as MLD's network reads them.
    mld: MldFamily,
}

impl MotionLcmFamily {
    fn parts(&self) -> LatentParts {
        LatentParts {
            channels: self.denoiser.latent_channels,
            cond_dim: Some(self.denoiser.cond_dim),
            text_relu: self.denoiser.text_activation == "relu",
        }
    }

    /// Whether the latent has projections (v2's `latent_pre`/`latent_post`).
    fn projected(&self) -> bool {
        self.denoiser.latent_channels != self.denoiser.mld.latent_dim
    }
}

impl FamilyConfig for MotionLcmFamily {
    fn architecture(&self) -> &str {
        "motionlcm"
    }

    fn check(&self, cfg: &Config) -> Result<()> {
        self.mld.check_networks(cfg)?;
        let d = &self.denoiser;
        in_range("denoiser.latent_channels", d.latent_channels, 1, MAX_WIDTH)?;
        in_range("denoiser.cond_dim", d.cond_dim, 4, MAX_WIDTH)?;
        if !d.cond_dim.is_multiple_of(2) {
            return Err(bad_file!(
                "config denoiser.cond_dim {} is not even (the guidance embedding's sine and \
                 cosine halves)",
                d.cond_dim
            ));
        }
        one_of(
            "denoiser.text_activation",
            &d.text_activation,
            &["relu", "none"],
        )?;
        if self.vae.latent_channels != d.latent_channels {
            return Err(bad_file!(
                "config vae.latent_channels {} differs from denoiser.latent_channels {}",
                self.vae.latent_channels,
                d.latent_channels
            ));
        }
        if !matches!(cfg.text_encoder, TextConfig::T5(_)) {
            return Err(bad_file!(
                "config text_encoder.kind `{}`: motionlcm conditions on sentence-t5 (`t5`)",
                cfg.text_encoder.kind()
            ));
        }
        let dc = &cfg.diffusion;
        let spacing: Option<Spacing> = dc.spacing.parse().ok();
        if spacing != Some(Spacing::Lcm) {
            return Err(bad_file!(
                "config diffusion.spacing `{}`: motionlcm samples with the latent consistency \
                 sampler (`lcm`)",
                dc.spacing
            ));
        }
        if let Some(k) = &self.control {
            in_range("control.joints", k.joints, 1, MAX_WIDTH)?;
            in_range("control.layers", k.layers, 1, MAX_LAYERS)?;
            if k.layers.is_multiple_of(2) {
                return Err(bad_file!(
                    "config control.layers {} is not odd (a skip stack)",
                    k.layers
                ));
            }
            heads_divide(
                "denoiser.latent_dim",
                d.mld.latent_dim,
                "control.heads",
                k.heads,
            )?;
            in_range("control.ff_size", k.ff_size, 1, MAX_FEEDFORWARD)?;
            in_range(
                "control.max_len",
                k.max_len,
                d.mld.latent_tokens + 1,
                MAX_MOTION_POSITIONS,
            )?;
            in_range("control.embed_dim", k.embed_dim, 1, MAX_WIDTH)?;
            one_of(
                "control.embed_activation",
                &k.embed_activation,
                &["none", "silu"],
            )?;
            one_of("control.frame_mask", &k.frame_mask, &["row_sum", "mask"])?;
            in_range_f32("control.scale", k.scale, 0.0, 1e6, false)?;
        }
        if !matches!(dc.parameterization.trim(), "epsilon" | "eps") {
            return Err(bad_file!(
                "config diffusion.parameterization `{}`: motionlcm predicts the noise (`epsilon`)",
                dc.parameterization
            ));
        }
        Ok(())
    }

    fn validate(&self, file: &ModelFile) -> Result<()> {
        self.mld.validate_networks(file)?;
        let d = &self.denoiser;
        let (e, c) = (d.mld.latent_dim, d.latent_channels);
        expect_shape(
            file,
            "denoiser.time_embedding.cond_proj.weight",
            &[d.mld.text_dim, d.cond_dim],
            "denoiser.text_dim, cond_dim",
        )?;
        let projections = [
            ("denoiser.latent_pre.weight", [e, c]),
            ("denoiser.latent_post.weight", [c, e]),
            ("vae.latent_post.weight", [e, c]),
        ];
        for (name, shape) in projections {
            match (self.projected(), file.contains(name)) {
                (true, _) => {
                    expect_shape(file, name, &shape, "denoiser.latent_dim, latent_channels")?
                }
                (false, true) => {
                    return Err(bad_file!(
                        "the file has `{name}` (MotionLCM v2's latent projection) but its \
                         config says latent_channels = latent_dim = {e} (a v1 latent): convert \
                         the checkpoint again"
                    ))
                }
                (false, false) => {}
            }
        }
        // The text vector's width is the Dense head's outputs.
        expect_shape_rows(
            file,
            "text.dense.weight",
            d.mld.text_dim,
            "denoiser.text_dim",
        )?;
        match &self.control {
            Some(k) => self.validate_control(file, k),
            None if file.has_prefix("controlnet.") || file.has_prefix("traj_encoder.") => {
                Err(bad_file!(
                    "the file has ControlNet tensors (`controlnet.*`, `traj_encoder.*`) but its \
                     config has no `control` section"
                ))
            }
            None => Ok(()),
        }
    }

    fn feature_dim(&self) -> usize {
        self.vae.mld.nfeats
    }

    fn max_frames(&self) -> usize {
        self.vae.mld.max_len
    }

    fn unconditional_inputs(&self) -> &'static [&'static str] {
        &["empty_prompt"]
    }

    fn summary(&self) -> String {
        let d = &self.denoiser;
        format!(
            "MotionLCM (MLD skip transformer), {} layers x {}, {} heads, ff {}, latent {} x {}, \
             guidance embedding {}",
            d.mld.layers,
            d.mld.latent_dim,
            d.mld.heads,
            d.mld.ff_size,
            d.mld.latent_tokens,
            d.latent_channels,
            d.cond_dim
        )
    }

    fn load(
        &self,
        file: &ModelFile,
        cfg: &Config,
        _text: &TextModel,
        ty: WeightType,
    ) -> Result<Box<dyn Denoiser>> {
        Ok(Box::new(MotionLcmDenoiser {
            net: MldDenoiser::load_with(file, &self.mld, self.parts(), ty)?,
            control: match &self.control {
                Some(k) => Some(ControlNet::load(file, self, k, ty)?),
                None => None,
            },
            text_dim: self.denoiser.mld.text_dim,
            default_w: cfg.defaults.guidance - 1.0,
        }))
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

impl MotionLcmFamily {
    /// The ControlNet's tensors against the sizes: the copy has the denoiser's, the trajectory
    /// encoder its section's.
    fn validate_control(&self, file: &ModelFile, k: &ControlConfig) -> Result<()> {
        let d = &self.denoiser;
        let (e, c, l) = (d.mld.latent_dim, d.latent_channels, d.mld.latent_tokens);
        let shape =
            |name: &str, want: &[usize], fields: &str| expect_shape(file, name, want, fields);
        shape(
            "controlnet.query_pos.pe",
            &[d.mld.max_len, 1, e],
            "denoiser.max_len, latent_dim",
        )?;
        shape(
            "controlnet.time_embedding.cond_proj.weight",
            &[d.mld.text_dim, d.cond_dim],
            "denoiser.text_dim, cond_dim",
        )?;
        super::mld::check_stack(file, "denoiser.layers", d.mld.layers, "controlnet.encoder.")?;
        if file.contains("controlnet.encoder.norm.weight") {
            return Err(bad_file!(
                "`controlnet.encoder.norm.weight`: a ControlNet's copy has no final norm"
            ));
        }
        for (i, (n_in, n_out)) in self.embed_shapes(k).into_iter().enumerate() {
            let name = format!(
                "controlnet.controlnet_cond_embedding.{}.weight",
                self.embed_key(k, i)
            );
            shape(
                &name,
                &[n_out, n_in],
                "denoiser.latent_channels, control.embed_dim",
            )?;
        }
        for i in 0..d.mld.layers {
            shape(
                &format!("controlnet.controlnet_down_mid_blocks.{i}.weight"),
                &[e, e],
                "denoiser.latent_dim",
            )?;
        }
        if file.contains(&format!(
            "controlnet.controlnet_down_mid_blocks.{}.weight",
            d.mld.layers
        )) {
            return Err(bad_file!(
                "the file has more `controlnet.controlnet_down_mid_blocks` than denoiser.layers ({})",
                d.mld.layers
            ));
        }
        shape(
            "traj_encoder.skel_embedding.weight",
            &[e, 3 * k.joints],
            "denoiser.latent_dim, control.joints",
        )?;
        shape(
            "traj_encoder.global_motion_token",
            &[l, e],
            "denoiser.latent_tokens, latent_dim",
        )?;
        shape(
            "traj_encoder.query_pos_encoder.pe",
            &[k.max_len, 1, e],
            "control.max_len, denoiser.latent_dim",
        )?;
        super::mld::check_stack(file, "control.layers", k.layers, "traj_encoder.encoder.")?;
        shape(
            "traj_encoder.encoder.middle_block.linear1.weight",
            &[k.ff_size, e],
            "control.ff_size, denoiser.latent_dim",
        )?;
        match (
            self.projected(),
            file.contains("traj_encoder.latent_proj.weight"),
        ) {
            (true, _) => shape(
                "traj_encoder.latent_proj.weight",
                &[c, e],
                "denoiser.latent_channels, latent_dim",
            )?,
            (false, true) => {
                return Err(bad_file!(
                    "the file has `traj_encoder.latent_proj.weight` (MotionLCM v2) but its config \
                     says latent_channels = latent_dim (a v1 latent)"
                ))
            }
            (false, false) => {}
        }
        shape("control.mean_raw", &[k.joints, 3], "control.joints")?;
        shape("control.std_raw", &[k.joints, 3], "control.joints")
    }

    /// `(in, out)` of the condition embedding's three Linears.
    fn embed_shapes(&self, k: &ControlConfig) -> [(usize, usize); 3] {
        let (c, m) = (self.denoiser.latent_channels, k.embed_dim);
        [(c, m), (m, m), (m, c)]
    }

    /// The official key of the condition embedding's Linear `i`: `Sequential` indices count
    /// the activations between them (v2: 0, 2, 4; v1, without activations: 0, 1, 2).
    fn embed_key(&self, k: &ControlConfig, i: usize) -> usize {
        if k.embed_activation == "silu" {
            2 * i
        } else {
            i
        }
    }
}

/// `name` is 2-D with `rows` rows (its other side is checked where it is loaded).
fn expect_shape_rows(file: &ModelFile, name: &str, rows: usize, fields: &str) -> Result<()> {
    match *file.shape(name)? {
        [r, _] if r == rows => Ok(()),
        ref other => Err(bad_file!(
            "tensor `{name}` has shape {other:?}; config {fields} says {rows} rows"
        )),
    }
}

/// MotionLCM's network: MLD's denoiser and VAE decoder with the distillation's additions.
pub struct MotionLcmDenoiser {
    net: MldDenoiser,
    /// The trajectory ControlNet, when the file has one.
    control: Option<ControlNet>,
    text_dim: usize,
    /// The embedded scale of a plain [`Denoiser::forward`] (the file's default guidance − 1).
    default_w: f32,
}

impl MotionLcmDenoiser {
    /// The VAE decoder.
    pub fn vae(&self) -> Option<&VaeDecoder> {
        self.net.vae()
    }

    /// The trajectory encoder's output (`[latent_tokens, latent_channels]`, MotionLCM's
    /// `controlnet_cond`) for normalised hint rows `[frames, 3·joints]` and the frames that
    /// hold a followed value (`hinted`, one per frame).
    pub fn control_condition(
        &self,
        hint: &[f32],
        hinted: &[bool],
        frames: usize,
    ) -> Result<Vec<f32>> {
        match &self.control {
            Some(c) => c.encode(hint, hinted, frames),
            None => Err(invalid_arg!("this MotionLCM file has no ControlNet")),
        }
    }

    /// The normalised hint rows (`[frames, 3·joints]`) of positions and weights as
    /// [`Denoiser::encode_control`] takes them.
    pub fn control_hint(&self, positions: &[[f64; 3]], weights: &[[f64; 3]]) -> Result<Vec<f32>> {
        match &self.control {
            Some(c) => c.hint(positions, weights),
            None => Err(invalid_arg!("this MotionLCM file has no ControlNet")),
        }
    }

    /// The ControlNet's residuals (`[blocks, latent_tokens + 2, latent_dim]`, scaled) for one
    /// sample `x`, for tests that compare them with the reference.
    pub fn control_residuals(
        &self,
        x: &[f32],
        t: f32,
        w: f32,
        text: &[f32],
        control: &[f32],
    ) -> Result<Vec<f32>> {
        let c = self
            .control
            .as_ref()
            .ok_or_else(|| invalid_arg!("this MotionLCM file has no ControlNet"))?;
        let mut ws = MotionLcmWorkspace::default();
        let rows = self.net.sample_rows(0);
        c.residuals(x, rows, t, w, &[text], control, &mut ws, &Cancel::never())?;
        Ok(ws.residuals)
    }
}

impl Denoiser for MotionLcmDenoiser {
    fn sample_dim(&self) -> usize {
        self.net.sample_dim()
    }

    fn reads_sample_directly(&self) -> bool {
        self.net.reads_sample_directly()
    }

    fn sample_rows(&self, frames: usize) -> usize {
        self.net.sample_rows(frames)
    }

    fn encode_prompt(&self, text: &TextModel, prompt: &str) -> Result<Condition> {
        Ok(Condition::text_vector(text.t5_vector(prompt)?))
    }

    fn unconditional(&self, text: &TextModel, _uncond: &str) -> Result<Condition> {
        Ok(Condition::text_vector(text.t5_vector("")?))
    }

    fn check_condition(&self, cond: &Condition) -> Result<()> {
        check_text_vector(cond, self.text_dim)
    }

    /// Always embedded: the distilled network was trained on the guided teacher's output at the
    /// embedded scale, and has no unconditional pass to mix.
    fn guidance(&self, scale: f32, _t: f32) -> Guidance {
        Guidance::Embedded(scale - 1.0)
    }

    /// At the file's default guidance (what calibration and plain forward passes use).
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
        self.forward_embedded(x, rows, t, self.default_w, conds, None, out, ws, cancel)
    }

    fn forward_embedded(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        w: f32,
        conds: &[&Condition],
        control: Option<&[f32]>,
        out: &mut [f32],
        ws: &mut Workspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let (texts, n) = text_vector_views(conds)?;
        let ws: &mut MotionLcmWorkspace = ws.get();
        let residuals = match (control, &self.control) {
            (None, _) => None,
            (Some(cond), Some(net)) => {
                net.residuals(x, rows, t, w, &texts[..n], cond, ws, cancel)?;
                Some(&ws.residuals[..])
            }
            (Some(_), None) => {
                return Err(invalid_arg!("this MotionLCM file has no ControlNet"));
            }
        };
        self.net.forward_guided(
            x,
            rows,
            t,
            Some(w),
            &texts[..n],
            residuals,
            out,
            &mut ws.main,
            cancel,
        )
    }

    fn takes_control(&self) -> bool {
        self.control.is_some()
    }

    fn eps_recorded(
        &self,
        z: &[f32],
        rows: usize,
        t: f32,
        w: f32,
        cond: &Condition,
        control: Option<&[f32]>,
        eps: &mut [f32],
        tape: &mut Workspace,
    ) -> Result<()> {
        let (texts, _) = text_vector_views(&[cond])?;
        let text = texts[0];
        let MotionLcmTape {
            main,
            copy,
            ws,
            recorded,
        } = tape.get();
        *recorded = None;
        if rows != self.net.sample_rows(0) || eps.len() != z.len() {
            return Err(invalid_arg!(
                "latent tuning runs one sample of {} rows, got {rows} rows and {} ε values for \
                 {} sample values",
                self.net.sample_rows(0),
                eps.len(),
                z.len()
            ));
        }
        let residuals = match (control, &self.control) {
            (None, _) => None,
            (Some(c), Some(net)) => {
                net.residuals_recorded(z, t, w, text, c, copy, ws)?;
                Some(&ws.residuals[..])
            }
            (Some(_), None) => return Err(invalid_arg!("this MotionLCM file has no ControlNet")),
        };
        self.net
            .eps_recorded(z, t, Some(w), text, residuals, eps, main)?;
        *recorded = Some((z.len(), residuals.is_some()));
        Ok(())
    }

    fn eps_vjp(&self, d_eps: &[f32], d_z: &mut [f32], tape: &mut Workspace) -> Result<()> {
        let tape: &mut MotionLcmTape = tape.get();
        let Some((len, controlled)) = tape.recorded else {
            return Err(invalid_arg!(
                "the network's backward needs a recorded pass first (eps_recorded)"
            ));
        };
        if d_eps.len() != len || d_z.len() != len {
            return Err(invalid_arg!(
                "the recorded pass has {len} sample values; got gradients of {} and {}",
                d_eps.len(),
                d_z.len()
            ));
        }
        d_z.fill(0.0);
        match (&self.control, controlled) {
            (Some(net), true) => {
                let mut d_residuals = Vec::new();
                self.net
                    .eps_backward(&tape.main, d_eps, Some(&mut d_residuals), d_z);
                net.residuals_backward(&tape.copy, &d_residuals, d_z);
            }
            _ => self.net.eps_backward(&tape.main, d_eps, None, d_z),
        }
        Ok(())
    }

    fn encode_control(
        &self,
        frames: usize,
        positions: &[[f64; 3]],
        weights: &[[f64; 3]],
    ) -> Result<Vec<f32>> {
        let c = self.control.as_ref().ok_or_else(|| {
            invalid_arg!(
                "this MotionLCM file has no ControlNet: convert a trajectory-control checkpoint \
                 (experiments_control/...) to follow joint positions"
            )
        })?;
        let hint = c.hint(positions, weights)?;
        let j = c.cfg.joints;
        let hint_frames = positions.len() / j;
        if hint_frames > frames {
            return Err(invalid_arg!(
                "the control covers {hint_frames} frames; the generation has {frames}"
            ));
        }
        // Frames past the hint are free: zero rows, left out of the encoder's attention.
        let mut rows = hint;
        rows.resize(frames * 3 * j, 0.0);
        let mut hinted: Vec<bool> = weights
            .chunks_exact(j)
            .map(|f| f.iter().flatten().any(|&w| w > 0.0))
            .collect();
        hinted.resize(frames, false);
        c.encode(&rows, &hinted, frames)
    }

    fn decoder(&self) -> Option<&dyn MotionDecoder> {
        self.net.decoder()
    }

    fn linear_weight_bytes(&self) -> usize {
        self.net.linear_weight_bytes() + self.control.as_ref().map_or(0, ControlNet::weight_bytes)
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}

/// Buffers of MotionLCM's forward pass: the denoiser's, the ControlNet copy's and the residuals.
#[derive(Default)]
pub struct MotionLcmWorkspace {
    main: MldWorkspace,
    copy: MldWorkspace,
    x: Vec<f32>,
    embed: [Vec<f32>; 2],
    collect: Vec<f32>,
    residuals: Vec<f32>,
}

/// What [`Denoiser::eps_recorded`] keeps for [`Denoiser::eps_vjp`]: the denoiser's pass, the
/// ControlNet copy's and, once recorded, the sample's length and whether control was on.
#[derive(Default)]
struct MotionLcmTape {
    main: DenoiserTape,
    copy: DenoiserTape,
    ws: MotionLcmWorkspace,
    recorded: Option<(usize, bool)>,
}

/// MotionLCM's trajectory ControlNet (Dai-Wenxun/MotionLCM v1.0 f534a7f and v2.0 086f8db:
/// `mld/models/architectures/mld_traj_encoder.py`, `mld_denoiser.py` with `is_controlnet`,
/// `mld/models/operator/attention.py`, `mld/models/modeltype/mld.py`).
///
/// The hint (joint positions normalised with `Mean_raw`/`Std_raw`, zero where free) goes
/// through the trajectory encoder once per control; at every step the ControlNet, a copy of
/// the denoiser without its final norm, runs on the sample plus the embedded encoder output
/// and hands one residual per block (through its own Linear) to the denoiser, which adds it
/// right after that block.
struct ControlNet {
    cfg: ControlConfig,
    copy: MldDenoiser,
    /// The condition embedding's three Linears (v2: SiLU after the first two).
    embed: [Linear; 3],
    silu: bool,
    down: Vec<Linear>,
    traj: TrajEncoder,
    mean_raw: Tensor,
    std_raw: Tensor,
}

/// The trajectory encoder: per-frame Linear, global tokens, learned positions, a masked skip
/// encoder with its final norm, the global tokens out (v2: through `latent_proj`).
struct TrajEncoder {
    skel: Linear,
    tokens: Tensor,
    pe: Tensor,
    encoder: SkipStack<EncoderLayer>,
    proj: Option<Linear>,
}

impl ControlNet {
    fn load(
        file: &ModelFile,
        fam: &MotionLcmFamily,
        k: &ControlConfig,
        ty: WeightType,
    ) -> Result<ControlNet> {
        let d = &fam.denoiser;
        let (e, c, l) = (d.mld.latent_dim, d.latent_channels, d.mld.latent_tokens);
        let part = Part {
            prefix: "controlnet.",
            main: false,
        };
        let shapes = fam.embed_shapes(k);
        let embed = |i: usize| {
            let (n_in, n_out) = shapes[i];
            let name = format!(
                "controlnet.controlnet_cond_embedding.{}",
                fam.embed_key(k, i)
            );
            Linear::load(file, &name, n_in, n_out, ty)
        };
        let shape = LayerShape {
            width: e,
            heads: k.heads,
            ff: k.ff_size,
            act: activation(&d.mld.activation),
            eps: d.mld.layer_norm_eps,
        };
        Ok(ControlNet {
            copy: MldDenoiser::load_part(file, &fam.mld, fam.parts(), part, ty)?,
            embed: [embed(0)?, embed(1)?, embed(2)?],
            silu: k.embed_activation == "silu",
            down: (0..d.mld.layers)
                .map(|i| {
                    let name = format!("controlnet.controlnet_down_mid_blocks.{i}");
                    Linear::load(file, &name, e, e, ty)
                })
                .collect::<Result<_>>()?,
            traj: TrajEncoder {
                skel: Linear::load(file, "traj_encoder.skel_embedding", 3 * k.joints, e, ty)?,
                tokens: file.tensor("traj_encoder.global_motion_token", &[l, e])?,
                pe: file.tensor("traj_encoder.query_pos_encoder.pe", &[k.max_len, 1, e])?,
                encoder: SkipStack::load(file, "traj_encoder.encoder.", k.layers, true, shape, ty)?,
                proj: if c != e {
                    Some(Linear::load(file, "traj_encoder.latent_proj", e, c, ty)?)
                } else {
                    None
                },
            },
            mean_raw: finite_stats(file.tensor("control.mean_raw", &[k.joints, 3])?, false)?,
            std_raw: finite_stats(file.tensor("control.std_raw", &[k.joints, 3])?, true)?,
            cfg: k.clone(),
        })
    }

    fn weight_bytes(&self) -> usize {
        self.copy.linear_weight_bytes()
            + self.embed.iter().map(Linear::weight_bytes).sum::<usize>()
            + self.down.iter().map(Linear::weight_bytes).sum::<usize>()
            + self.traj.skel.weight_bytes()
            + self.traj.encoder.weight_bytes()
            + self.traj.proj.as_ref().map_or(0, Linear::weight_bytes)
    }

    /// The normalised hint rows `[frames, 3·joints]`: `(p − Mean_raw)/Std_raw` where the
    /// weight is 1, 0 where it is 0 (the dataset's `random_mask`, v2.0
    /// `mld/data/humanml/dataset.py`).
    fn hint(&self, positions: &[[f64; 3]], weights: &[[f64; 3]]) -> Result<Vec<f32>> {
        let j = self.cfg.joints;
        if positions.is_empty()
            || !positions.len().is_multiple_of(j)
            || weights.len() != positions.len()
        {
            return Err(invalid_arg!(
                "a control hint holds frames × {j} joints, got {} positions and {} weights",
                positions.len(),
                weights.len()
            ));
        }
        let (mean, std) = (self.mean_raw.data(), self.std_raw.data());
        let mut out = Vec::with_capacity(positions.len() * 3);
        for (i, (p, w)) in positions.iter().zip(weights).enumerate() {
            let joint = i % j;
            for a in 0..3 {
                let v = if w[a] > 0.0 {
                    ((p[a] as f32 - mean[joint * 3 + a]) / std[joint * 3 + a]) * w[a] as f32
                } else {
                    0.0
                };
                if !v.is_finite() {
                    return Err(invalid_arg!(
                        "control hint frame {}, joint {joint}: not finite",
                        i / j
                    ));
                }
                out.push(v);
            }
        }
        Ok(out)
    }

    /// The trajectory encoder over hint rows `[frames, 3·joints]` (`hinted`: the frames with
    /// a followed value): `[latent_tokens, C]`.
    fn encode(&self, hint: &[f32], hinted: &[bool], frames: usize) -> Result<Vec<f32>> {
        let width = 3 * self.cfg.joints;
        if frames == 0 || hint.len() != frames * width || hinted.len() != frames {
            return Err(invalid_arg!(
                "control hint rows hold {} values and {} frame flags, expected {frames} frames \
                 × {width}",
                hint.len(),
                hinted.len()
            ));
        }
        let t = &self.traj;
        let e = t.skel.outputs();
        let l = t.tokens.data().len() / e;
        let seq = l + frames;
        if seq > self.cfg.max_len {
            return Err(invalid_arg!(
                "the trajectory encoder takes at most {} frames, got {frames}",
                self.cfg.max_len - l
            ));
        }
        // Which frames the encoder attends to (true = left out, PyTorch's key padding).
        let padding: Vec<bool> = (0..seq)
            .map(|i| {
                if i < l {
                    return false;
                }
                let f = i - l;
                match self.cfg.frame_mask.as_str() {
                    // v1: `hint.sum(-1) != 0` on the normalised rows, so a followed value
                    // that normalises to 0 can drop its frame.
                    "row_sum" => hint[f * width..(f + 1) * width].iter().sum::<f32>() == 0.0,
                    // v2: the mask's frames.
                    _ => !hinted[f],
                }
            })
            .collect();
        let mut x = vec![0f32; seq * e];
        x[..l * e].copy_from_slice(t.tokens.data());
        t.skel.forward(hint, frames, &mut x[l * e..]);
        kernels::add_inplace(&mut x, &t.pe.data()[..seq * e]);
        let taps = Taps {
            key_padding: Some(&padding),
            ..Taps::default()
        };
        let mut b = StackBuffers::default();
        t.encoder
            .forward_taps(&mut x, 1, seq, &[], 0, taps, &mut b, &Cancel::never())?;
        let tokens = &x[..l * e];
        Ok(match &t.proj {
            Some(p) => {
                let mut out = vec![0f32; l * p.outputs()];
                p.forward(tokens, l, &mut out);
                out
            }
            None => tokens.to_vec(),
        })
    }

    /// The residuals of one step into `ws.residuals` (`[blocks, batch × seq, D]`): the copy
    /// runs on `x + embed(control)` with the denoiser's time, guidance and text.
    #[allow(clippy::too_many_arguments)]
    fn residuals(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        w: f32,
        texts: &[&[f32]],
        control: &[f32],
        ws: &mut MotionLcmWorkspace,
        cancel: &Cancel,
    ) -> Result<()> {
        self.conditioned_input(x, rows, texts.len(), control, ws)?;
        let taps = Taps {
            collect: Some(&mut ws.collect),
            ..Taps::default()
        };
        self.copy
            .sequence(&ws.x, rows, t, Some(w), texts, taps, &mut ws.copy, cancel)?;
        self.project_down(&ws.collect, &mut ws.residuals);
        Ok(())
    }

    /// The copy's input `x + embed(control)` (`batch` samples) into `ws.x`.
    fn conditioned_input(
        &self,
        x: &[f32],
        rows: usize,
        batch: usize,
        control: &[f32],
        ws: &mut MotionLcmWorkspace,
    ) -> Result<()> {
        let c = self.embed[2].outputs();
        if control.len() != rows * c || x.len() != batch * rows * c {
            return Err(invalid_arg!(
                "the control value holds {} values, the ControlNet takes {rows} × {c}",
                control.len()
            ));
        }
        let [a, b] = &mut ws.embed;
        let a = sized(a, rows * self.embed[0].outputs());
        self.embed[0].forward(control, rows, a);
        if self.silu {
            kernels::silu(a);
        }
        let b = sized(b, rows * self.embed[1].outputs());
        self.embed[1].forward(a, rows, b);
        if self.silu {
            kernels::silu(b);
        }
        let xin = sized(&mut ws.x, x.len());
        let m = self.embed[1].outputs();
        let [a, b] = &mut ws.embed;
        let emb = sized(a, rows * c);
        self.embed[2].forward(&b[..rows * m], rows, emb);
        xin.copy_from_slice(x);
        for sample in xin.chunks_exact_mut(rows * c) {
            kernels::add_inplace(sample, emb);
        }
        Ok(())
    }

    /// Every block's collected output through its own `controlnet_down_mid_blocks` Linear,
    /// times the scale: the residuals (`[blocks, rows, D]`).
    fn project_down(&self, collect: &[f32], residuals: &mut Vec<f32>) {
        let e = self.down[0].outputs();
        let n = collect.len() / self.down.len();
        let r = sized(residuals, collect.len());
        for (i, lin) in self.down.iter().enumerate() {
            lin.forward(
                &collect[i * n..(i + 1) * n],
                n / e,
                &mut r[i * n..(i + 1) * n],
            );
        }
        if self.cfg.scale != 1.0 {
            r.iter_mut().for_each(|v| *v *= self.cfg.scale);
        }
    }

    /// [`ControlNet::residuals`] for one sample `z`, recorded into `copy` (the residuals in
    /// `ws.residuals`).
    #[allow(clippy::too_many_arguments)]
    fn residuals_recorded(
        &self,
        z: &[f32],
        t: f32,
        w: f32,
        text: &[f32],
        control: &[f32],
        copy: &mut DenoiserTape,
        ws: &mut MotionLcmWorkspace,
    ) -> Result<()> {
        let rows = self.copy.sample_rows(0);
        self.conditioned_input(z, rows, 1, control, ws)?;
        self.copy
            .sequence_recorded(&ws.x, t, Some(w), text, None, Some(&mut ws.collect), copy)?;
        self.project_down(&ws.collect, &mut ws.residuals);
        Ok(())
    }

    /// The backward of [`ControlNet::residuals_recorded`]: ADDS to `d_z` the gradient of the
    /// residuals' gradients `d_residuals` (the condition embedding does not depend on `z`, so
    /// the copy's input gradient is `z`'s).
    fn residuals_backward(&self, copy: &DenoiserTape, d_residuals: &[f32], d_z: &mut [f32]) {
        let e = self.down[0].outputs();
        let n = d_residuals.len() / self.down.len();
        let mut scaled = d_residuals.to_vec();
        if self.cfg.scale != 1.0 {
            scaled.iter_mut().for_each(|v| *v *= self.cfg.scale);
        }
        let mut d_collect = vec![0.0; scaled.len()];
        for (i, lin) in self.down.iter().enumerate() {
            lin.backward_input(
                &scaled[i * n..(i + 1) * n],
                n / e,
                &mut d_collect[i * n..(i + 1) * n],
            );
        }
        // The copy's own output (its last sequence) is not used: only its blocks' outputs.
        let mut d_seq = vec![0.0; n];
        self.copy
            .sequence_backward(copy, &mut d_seq, Some(&d_collect), None, d_z);
    }
}

/// A `[joints, 3]` statistics tensor, finite (and positive for the std), or a clear error.
fn finite_stats(t: Tensor, std: bool) -> Result<Tensor> {
    let name = if std {
        "control.std_raw"
    } else {
        "control.mean_raw"
    };
    if let Some(v) = t
        .data()
        .iter()
        .find(|v| !v.is_finite() || (std && **v <= 0.0))
    {
        return Err(bad_file!(
            "`{name}` holds {v}; it must be finite{}",
            if std { " and positive" } else { "" }
        ));
    }
    Ok(t)
}
