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
use crate::config::validate::{expect_shape, in_range, one_of};
use crate::config::{section, Config, TextConfig, MAX_WIDTH};
use crate::diffusion::Spacing;
use crate::error::{bad_file, Result};
use crate::kernels::WeightType;

use super::mld::{LatentParts, MldConfig, MldVaeConfig, VaeDecoder};
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
        Ok(Arc::new(MotionLcmFamily {
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

/// A MotionLCM file's configuration.
#[derive(Clone, Debug)]
pub struct MotionLcmFamily {
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
        )
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
            text_dim: self.denoiser.mld.text_dim,
            default_w: cfg.defaults.guidance - 1.0,
        }))
    }

    fn as_any(&self) -> &dyn Any {
        self
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
    text_dim: usize,
    /// The embedded scale of a plain [`Denoiser::forward`] (the file's default guidance − 1).
    default_w: f32,
}

impl MotionLcmDenoiser {
    /// The underlying MLD network.
    pub fn mld(&self) -> &MldDenoiser {
        &self.net
    }

    /// The VAE decoder.
    pub fn vae(&self) -> &VaeDecoder {
        self.net.vae()
    }
}

impl Denoiser for MotionLcmDenoiser {
    fn sample_dim(&self) -> usize {
        self.net.sample_dim()
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
        self.forward_embedded(x, rows, t, self.default_w, conds, out, ws, cancel)
    }

    fn forward_embedded(
        &self,
        x: &[f32],
        rows: usize,
        t: f32,
        w: f32,
        conds: &[&Condition],
        out: &mut [f32],
        ws: &mut Workspace,
        cancel: &Cancel,
    ) -> Result<()> {
        let (texts, n) = text_vector_views(conds)?;
        self.net
            .forward_guided(x, rows, t, Some(w), &texts[..n], out, ws.get(), cancel)
    }

    fn decoder(&self) -> Option<&dyn MotionDecoder> {
        self.net.decoder()
    }

    fn linear_weight_bytes(&self) -> usize {
        self.net.linear_weight_bytes()
    }

    fn as_any(&self) -> &dyn Any {
        self
    }
}
