//! The configuration's validation: every size against its bound and against the tensors it
//! describes (shapes from the safetensors header, before any weight is read or any table
//! allocated), every name against the values the runtime accepts, and the fields against each
//! other, so that a file that loads can always start a session. The bounds are listed in the
//! module comment of [`crate::config`].

use crate::checkpoint::ModelFile;
use crate::diffusion::{
    betas, diffusers_alphas_cumprod, diffusers_timesteps, BetaSchedule, Parameterization, Schedule,
    Spacing, Variance,
};
use crate::error::{bad_file, Result};
use crate::motion::Format;
use crate::session::Sampler;
use crate::text::{ClipConfig, EncoderKind};

use super::*;

/// `lo <= value <= hi`, or an error naming the field and the range.
pub(crate) fn in_range(field: &str, value: usize, lo: usize, hi: usize) -> Result<()> {
    if value < lo || value > hi {
        return Err(bad_file!(
            "config {field} is {value}; it must be between {lo} and {hi}"
        ));
    }
    Ok(())
}

/// A finite value in `lo..=hi` (`lo` excluded when `open_lo`).
pub(crate) fn in_range_f32(field: &str, value: f32, lo: f32, hi: f32, open_lo: bool) -> Result<()> {
    let above = if open_lo { value > lo } else { value >= lo };
    if !(value.is_finite() && above && value <= hi) {
        let above = if open_lo { "above" } else { "at least" };
        return Err(bad_file!(
            "config {field} is {value}; it must be a number {above} {lo} and at most {hi}"
        ));
    }
    Ok(())
}

/// A width split over heads: `heads` in 1..=width, dividing it.
pub(crate) fn heads_divide(
    field: &str,
    width: usize,
    heads_field: &str,
    heads: usize,
) -> Result<()> {
    in_range(heads_field, heads, 1, width)?;
    if !width.is_multiple_of(heads) {
        return Err(bad_file!(
            "config {field} {width} is not divisible by {heads_field} {heads}"
        ));
    }
    Ok(())
}

/// One of `accepted`, or an error naming the field and the accepted values.
pub(crate) fn one_of(field: &str, value: &str, accepted: &[&str]) -> Result<()> {
    if !accepted.contains(&value) {
        return Err(bad_file!(
            "unknown config {field} `{value}` (accepted: {})",
            accepted.join(", ")
        ));
    }
    Ok(())
}

/// Tensor `name` is stored with shape `want` (implied by config `fields`).
pub(crate) fn expect_shape(
    file: &ModelFile,
    name: &str,
    want: &[usize],
    fields: &str,
) -> Result<()> {
    let got = file.shape(name)?;
    if got != want {
        return Err(bad_file!(
            "tensor `{name}` has shape {got:?}, expected {want:?} (from config {fields})"
        ));
    }
    Ok(())
}

/// A stack of `n` layers whose tensors are named `{prefix}{i}.…`: 1..=MAX_LAYERS, layer n−1
/// present and layer n absent in the header (so no per-layer storage is sized from a count the
/// file does not back).
pub(crate) fn check_layers(file: &ModelFile, field: &str, n: usize, prefix: &str) -> Result<()> {
    in_range(field, n, 1, MAX_LAYERS)?;
    let last = format!("{prefix}{}.", n - 1);
    if !file.has_prefix(&last) {
        return Err(bad_file!(
            "config {field} is {n} but the file has no tensor `{last}*`"
        ));
    }
    let next = format!("{prefix}{n}.");
    if file.has_prefix(&next) {
        return Err(bad_file!(
            "config {field} is {n} but the file also has tensors `{next}*`"
        ));
    }
    Ok(())
}

/// A positional table of `rows × width` values computed at load.
pub(crate) fn table_fits(field: &str, rows: usize, width: usize) -> Result<()> {
    match rows.checked_mul(width) {
        Some(n) if n <= MAX_TABLE_VALUES => Ok(()),
        _ => Err(bad_file!(
            "config {field} {rows} × width {width} exceeds the {MAX_TABLE_VALUES} values a \
             positional table may hold"
        )),
    }
}

pub(crate) fn check_eps(field: &str, eps: f32) -> Result<()> {
    in_range_f32(field, eps, 0.0, 1.0, true)
}

impl TextEncoderConfig {
    /// Bounds and names, without the file.
    pub fn check(&self) -> Result<EncoderKind> {
        let kind = match self.kind.as_str() {
            "bert" => EncoderKind::Bert,
            "roberta" => EncoderKind::Roberta,
            other => {
                return Err(bad_file!(
                    "unknown text_encoder.kind `{other}` (supported: bert, roberta, clip)"
                ))
            }
        };
        in_range("text_encoder.vocab_size", self.vocab_size, 1, MAX_VOCAB)?;
        in_range("text_encoder.hidden_size", self.hidden_size, 1, MAX_WIDTH)?;
        in_range("text_encoder.num_layers", self.num_layers, 1, MAX_LAYERS)?;
        heads_divide(
            "text_encoder.hidden_size",
            self.hidden_size,
            "text_encoder.num_heads",
            self.num_heads,
        )?;
        in_range(
            "text_encoder.intermediate_size",
            self.intermediate_size,
            1,
            MAX_FEEDFORWARD,
        )?;
        in_range(
            "text_encoder.max_position_embeddings",
            self.max_position_embeddings,
            1,
            MAX_TEXT_POSITIONS,
        )?;
        in_range(
            "text_encoder.type_vocab_size",
            self.type_vocab_size,
            1,
            MAX_VOCAB,
        )?;
        check_eps("text_encoder.layer_norm_eps", self.layer_norm_eps)?;
        if self.pad_token_id as usize >= self.vocab_size {
            return Err(bad_file!(
                "config text_encoder.pad_token_id {} is not below vocab_size {}",
                self.pad_token_id,
                self.vocab_size
            ));
        }
        in_range(
            "text_encoder.max_length",
            self.max_length,
            1,
            MAX_TEXT_POSITIONS,
        )?;
        // RoBERTa's positions run from pad+1 to pad+max_length.
        let offset = match kind {
            EncoderKind::Bert => 0,
            EncoderKind::Roberta => self.pad_token_id as usize + 1,
        };
        if self.max_length + offset > self.max_position_embeddings {
            return Err(bad_file!(
                "text_encoder.max_length {} (+{offset} position offset) exceeds max_position_embeddings {}",
                self.max_length,
                self.max_position_embeddings
            ));
        }
        if self.hidden_act != "gelu" {
            return Err(bad_file!(
                "text_encoder.hidden_act `{}` is not supported (only exact `gelu`)",
                self.hidden_act
            ));
        }
        Ok(kind)
    }

    /// [`TextEncoderConfig::check`], then the sizes against the tensors under `prefix`.
    pub fn validate(&self, file: &ModelFile, prefix: &str) -> Result<EncoderKind> {
        let kind = self.check()?;
        let (p, e) = (prefix, self.hidden_size);
        expect_shape(
            file,
            &format!("{p}embeddings.word_embeddings.weight"),
            &[self.vocab_size, e],
            "text_encoder.vocab_size, hidden_size",
        )?;
        expect_shape(
            file,
            &format!("{p}embeddings.position_embeddings.weight"),
            &[self.max_position_embeddings, e],
            "text_encoder.max_position_embeddings, hidden_size",
        )?;
        expect_shape(
            file,
            &format!("{p}embeddings.token_type_embeddings.weight"),
            &[self.type_vocab_size, e],
            "text_encoder.type_vocab_size, hidden_size",
        )?;
        check_layers(
            file,
            "text_encoder.num_layers",
            self.num_layers,
            &format!("{p}encoder.layer."),
        )?;
        expect_shape(
            file,
            &format!("{p}encoder.layer.0.intermediate.dense.weight"),
            &[self.intermediate_size, e],
            "text_encoder.intermediate_size, hidden_size",
        )?;
        Ok(kind)
    }
}

impl ClipConfig {
    /// Bounds, without the file.
    pub fn check(&self) -> Result<()> {
        in_range("text_encoder.vocab_size", self.vocab_size, 1, MAX_VOCAB)?;
        in_range("text_encoder.width", self.width, 1, MAX_WIDTH)?;
        in_range("text_encoder.layers", self.layers, 1, MAX_LAYERS)?;
        heads_divide(
            "text_encoder.width",
            self.width,
            "text_encoder.heads",
            self.heads,
        )?;
        if let Some(i) = self.intermediate_size {
            in_range("text_encoder.intermediate_size", i, 1, MAX_FEEDFORWARD)?;
        }
        in_range(
            "text_encoder.context_length",
            self.context_length,
            2,
            MAX_TEXT_POSITIONS,
        )?;
        in_range(
            "text_encoder.projection_dim",
            self.projection_dim,
            1,
            MAX_WIDTH,
        )?;
        check_eps("text_encoder.layer_norm_eps", self.layer_norm_eps)
    }

    /// [`ClipConfig::check`], then the sizes against the tensors under `prefix`.
    pub fn validate(&self, file: &ModelFile, prefix: &str) -> Result<()> {
        self.check()?;
        let (p, w) = (prefix, self.width);
        expect_shape(
            file,
            &format!("{p}text_model.embeddings.token_embedding.weight"),
            &[self.vocab_size, w],
            "text_encoder.vocab_size, width",
        )?;
        expect_shape(
            file,
            &format!("{p}text_model.embeddings.position_embedding.weight"),
            &[self.context_length, w],
            "text_encoder.context_length, width",
        )?;
        check_layers(
            file,
            "text_encoder.layers",
            self.layers,
            &format!("{p}text_model.encoder.layers."),
        )?;
        let fields = if self.intermediate_size.is_some() {
            "text_encoder.intermediate_size, width"
        } else {
            "text_encoder.width: no intermediate_size, so 4 × width"
        };
        expect_shape(
            file,
            &format!("{p}text_model.encoder.layers.0.mlp.fc1.weight"),
            &[self.mlp_size(), w],
            fields,
        )?;
        expect_shape(
            file,
            &format!("{p}text_projection.weight"),
            &[self.projection_dim, w],
            "text_encoder.projection_dim, width",
        )
    }
}

impl ClipTextConfig {
    /// The tower's bounds ([`ClipConfig::check`]) and `max_length` within 2..=`context_length`;
    /// needs no file.
    pub fn check(&self) -> Result<()> {
        self.clip.check()?;
        in_range(
            "text_encoder.max_length",
            self.max_length,
            2,
            self.clip.context_length,
        )
    }
}

/// The message of an `InvalidArgument` (other errors in full).
fn inner(e: crate::Error) -> String {
    match e {
        crate::Error::InvalidArgument(m) => m,
        other => other.to_string(),
    }
}

/// `diffusion.spacing`, `steps_offset` and `set_alpha_to_one`: a known spacing, and the two
/// diffusers fields left at their defaults unless diffusers' spacing uses them.
fn check_spacing(dc: &DiffusionConfig, flow: bool) -> Result<Spacing> {
    // Case and surrounding spaces ignored, as for the other diffusion names.
    let spacing: Spacing = dc.spacing.parse().map_err(|_| {
        bad_file!(
            "unknown config diffusion.spacing `{}` (accepted: respace, leading, trailing, lcm)",
            dc.spacing
        )
    })?;
    if flow && spacing.is_diffusers() {
        return Err(bad_file!(
            "config diffusion.spacing `{spacing}`: a flow-matching model has no diffusion \
             timesteps to space (leave it `respace` or absent)"
        ));
    }
    if dc.steps_offset >= dc.num_timesteps {
        return Err(bad_file!(
            "config diffusion.steps_offset is {}; it must be below diffusion.num_timesteps ({})",
            dc.steps_offset,
            dc.num_timesteps
        ));
    }
    if !spacing.is_diffusers() && dc.steps_offset != 0 {
        return Err(bad_file!(
            "config diffusion.steps_offset {} needs diffusion.spacing `leading` or `trailing` \
             (diffusers' DDIM); `{spacing}` has no offset",
            dc.steps_offset
        ));
    }
    let lcm_fields = dc.lcm_timesteps.is_some()
        || dc.original_inference_steps.is_some()
        || dc.timestep_scaling.is_some();
    if spacing != Spacing::Lcm && lcm_fields {
        return Err(bad_file!(
            "config diffusion.lcm_timesteps, original_inference_steps and timestep_scaling need \
             diffusion.spacing `lcm` (the latent consistency sampler)"
        ));
    }
    if spacing == Spacing::Lcm {
        if flow {
            return Err(bad_file!(
                "config diffusion.spacing `lcm`: a flow-matching model has no diffusion \
                 timesteps to space"
            ));
        }
        crate::diffusion::lcm::LcmTimesteps::from_config(dc)?;
        if let Some(s) = dc.timestep_scaling {
            in_range_f32("diffusion.timestep_scaling", s, 0.0, 1e6, true)?;
        }
        // diffusers' LCMScheduler reads set_alpha_to_one only past the last listed timestep,
        // which the sampler never visits: either value is accepted.
        return Ok(spacing);
    }
    if !spacing.is_diffusers() && !dc.set_alpha_to_one {
        return Err(bad_file!(
            "config diffusion.set_alpha_to_one false needs diffusion.spacing `leading` or \
             `trailing` (diffusers' DDIM); `{spacing}` always ends at ᾱ = 1"
        ));
    }
    Ok(spacing)
}

/// diffusers' float32 ᾱ table must fall strictly inside (0, 1), as every step needs (a β
/// below f32's resolution next to 1, or an underflow, would break it).
fn check_diffusers_table(dc: &DiffusionConfig, schedule: BetaSchedule) -> Result<()> {
    let table = diffusers_alphas_cumprod(&betas(schedule, dc.num_timesteps));
    let mut prev = 1.0;
    for (i, &a) in table.iter().enumerate() {
        if !(a > 0.0 && a < prev) {
            return Err(bad_file!(
                "config diffusion.schedule `{}` with num_timesteps {}: diffusers' float32 \
                 alphas_cumprod[{i}] = {a} does not fall below {prev} and above 0",
                dc.schedule,
                dc.num_timesteps
            ));
        }
        prev = a;
    }
    Ok(())
}

/// Whether the parameterization names a flow-matching model (a velocity predictor).
pub(crate) fn is_flow(parameterization: &str) -> bool {
    matches!(parameterization, "velocity" | "flow")
}

impl Config {
    /// Everything that needs no tensor: bounds, names, and the fields against each other.
    pub(super) fn check(&self) -> Result<()> {
        match &self.text_encoder {
            TextConfig::Bert(t) => {
                t.check()?;
            }
            TextConfig::Clip(c) => c.check()?,
            TextConfig::T5(t) => {
                in_range(
                    "text_encoder.max_length",
                    t.max_length,
                    2,
                    crate::text::t5::T5_MAX_TOKENS,
                )?;
                in_range(
                    "text_encoder.relative_attention_max_distance",
                    t.relative_attention_max_distance,
                    1,
                    MAX_TEXT_POSITIONS,
                )?;
            }
        }
        // Before the family's checks, which may compare their sizes with it.
        in_range(
            "diffusion.num_timesteps",
            self.diffusion.num_timesteps,
            1,
            MAX_TIMESTEPS,
        )?;
        // The family's own sections, and the others as it needs them.
        self.denoiser.check(self)?;
        let (max_frames, motion_dim) = (self.denoiser.max_frames(), self.denoiser.feature_dim());

        let m = &self.motion;
        let names: Vec<&str> = Format::ALL.iter().map(|f| f.name()).collect();
        one_of("motion.format", &m.format, &names)?;
        let format: Format = m.format.parse()?;
        if format.feature_dim() != motion_dim {
            return Err(bad_file!(
                "motion.format `{format}` has {} features per frame, the denoiser {motion_dim}",
                format.feature_dim()
            ));
        }
        in_range_f32("motion.fps", m.fps, 0.0, MAX_FPS, true)?;

        let dc = &self.diffusion;
        // Exactly what the sampler's parsers take (they ignore case and surrounding spaces).
        let unknown = |field: &str, value: &str, accepted: &[&str]| {
            bad_file!(
                "unknown config {field} `{value}` (accepted: {})",
                accepted.join(", ")
            )
        };
        let schedule: BetaSchedule = dc
            .schedule
            .parse()
            .map_err(|_| unknown("diffusion.schedule", &dc.schedule, SCHEDULES))?;
        let _: Variance = dc
            .variance
            .parse()
            .map_err(|_| unknown("diffusion.variance", &dc.variance, VARIANCES))?;
        one_of(
            "diffusion.uncond",
            &dc.uncond,
            self.denoiser.unconditional_inputs(),
        )?;
        let flow = is_flow(&dc.parameterization);
        if !flow {
            dc.parameterization
                .parse::<Parameterization>()
                .map_err(|_| {
                    let mut all = PARAMETERIZATIONS.to_vec();
                    all.extend(["velocity", "flow"]);
                    unknown("diffusion.parameterization", &dc.parameterization, &all)
                })?;
        }
        let spacing = check_spacing(dc, flow)?;
        if !flow {
            // The schedule must give betas in (0, 1) (a short linear schedule does not).
            Schedule::new(&betas(schedule, dc.num_timesteps)).map_err(|e| {
                let why = match e {
                    crate::Error::InvalidArgument(m) => m,
                    other => other.to_string(),
                };
                bad_file!(
                    "config diffusion.schedule `{}` with num_timesteps {}: {why}",
                    dc.schedule,
                    dc.num_timesteps
                )
            })?;
            if spacing.is_diffusers() {
                check_diffusers_table(dc, schedule)?;
            }
        }

        let df = &self.defaults;
        let samplers: &[&str] = if flow {
            &["euler", "heun", "midpoint"]
        } else if spacing == Spacing::Lcm {
            &["lcm"]
        } else {
            &["ddpm", "ddim"]
        };
        one_of("defaults.sampler", &df.sampler, samplers)?;
        let _: Sampler = df.sampler.parse()?;
        let max_steps = if flow {
            MAX_FLOW_STEPS
        } else {
            dc.num_timesteps
        };
        in_range("defaults.steps", df.steps, 1, max_steps)?;
        if spacing.is_diffusers() {
            diffusers_timesteps(spacing, dc.num_timesteps, df.steps, dc.steps_offset)
                .map_err(|e| bad_file!("config defaults.steps {}: {}", df.steps, inner(e)))?;
        }
        // `check_spacing` has read the rule of an `lcm` model already.
        let lcm_rule = match spacing {
            Spacing::Lcm => Some(crate::diffusion::lcm::LcmTimesteps::from_config(dc)?),
            _ => None,
        };
        if let Some(rule) = lcm_rule {
            rule.timesteps(df.steps, dc.num_timesteps)
                .map_err(|e| bad_file!("config defaults.steps {}: {}", df.steps, inner(e)))?;
        }
        if let Some(map) = &df.guidance_by_steps {
            let Some(rule) = lcm_rule else {
                return Err(bad_file!(
                    "config defaults.guidance_by_steps is for latent consistency models \
                     (diffusion.spacing `lcm`)"
                ));
            };
            for (k, &g) in map {
                let field = format!("defaults.guidance_by_steps.{k}");
                let steps: usize = k
                    .parse()
                    .map_err(|_| bad_file!("config {field}: the key is not a step count"))?;
                rule.timesteps(steps, dc.num_timesteps)
                    .map_err(|e| bad_file!("config {field}: {}", inner(e)))?;
                in_range_f32(&field, g, 0.0, MAX_GUIDANCE, false)?;
            }
        }
        if let Some(spec) = &df.respacing {
            if flow || spacing.is_diffusers() {
                return Err(bad_file!(
                    "config defaults.respacing `{spec}` needs diffusion.spacing `respace`"
                ));
            }
            let kept = crate::diffusion::parse_timestep_respacing(dc.num_timesteps, spec)
                .map_err(|e| bad_file!("config defaults.respacing `{spec}`: {}", inner(e)))?;
            if kept.len() != df.steps {
                return Err(bad_file!(
                    "config defaults.respacing `{spec}` keeps {} steps, defaults.steps is {}",
                    kept.len(),
                    df.steps
                ));
            }
        }
        in_range_f32("defaults.guidance", df.guidance, 0.0, MAX_GUIDANCE, false)?;
        in_range_f32("defaults.eta", df.eta, 0.0, 1.0, false)?;
        in_range("defaults.frames", df.frames, 1, max_frames)
    }

    /// Every size against the file's tensors (and each part's bounds again): what
    /// [`Config::from_file`] does after [`Config::from_json`]'s checks, before a model is built.
    pub fn validate(&self, file: &ModelFile) -> Result<()> {
        let prefix = crate::models::TEXT_PREFIX;
        match &self.text_encoder {
            TextConfig::Bert(t) => {
                t.validate(file, prefix)?;
            }
            TextConfig::Clip(c) => c.clip.validate(file, prefix)?,
            // The encoder reads its sizes from the shapes and checks them as it loads.
            TextConfig::T5(_) => {}
        }
        self.denoiser.validate(file)
    }
}

/// `diffusion.schedule` values ([`BetaSchedule`]'s spellings).
const SCHEDULES: &[&str] = &["cosine", "squaredcos_cap_v2", "linear", "scaled_linear"];
/// `diffusion.variance` values ([`Variance`]).
const VARIANCES: &[&str] = &["learned_range", "fixed_small", "fixed_large"];
/// `diffusion.parameterization` values of diffusion models ([`Parameterization`]).
const PARAMETERIZATIONS: &[&str] = &[
    "epsilon",
    "eps",
    "x0",
    "sample",
    "start_x",
    "v",
    "v_prediction",
];

// The lists above are exactly what the parsers take.
/// The text encoder kinds a family takes (`bert`/`roberta`/`clip`).
pub(crate) fn expect_text(cfg: &Config, kinds: &[&str]) -> Result<()> {
    if !kinds.contains(&cfg.text_encoder.kind()) {
        return Err(bad_file!(
            "architecture `{}` cannot use a `{}` text encoder",
            cfg.architecture,
            cfg.text_encoder.kind()
        ));
    }
    Ok(())
}

/// A family's parameterization: a velocity (flow matching) when `flow`, else a diffusion one.
pub(crate) fn expect_flow(cfg: &Config, flow: bool) -> Result<()> {
    let (p, arch) = (&cfg.diffusion.parameterization, &cfg.architecture);
    match (flow, is_flow(p)) {
        (true, false) => Err(bad_file!(
            "config diffusion.parameterization `{p}`: a {arch} model predicts a velocity \
             (`velocity` or `flow`)"
        )),
        (false, true) => Err(bad_file!(
            "config diffusion.parameterization `{p}` is for flow-matching models; {arch} takes {}",
            PARAMETERIZATIONS.join(", ")
        )),
        _ => Ok(()),
    }
}

/// `learned_range` needs a network that outputs variance values; most families do not.
pub(crate) fn refuse_learned_range(cfg: &Config) -> Result<()> {
    let v: Variance = cfg.diffusion.variance.parse()?;
    if v == Variance::LearnedRange {
        return Err(bad_file!(
            "config diffusion.variance `learned_range` needs a denoiser that outputs variance \
             values (flame); {} takes fixed_small or fixed_large",
            cfg.architecture
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accepted_names_parse() {
        for s in SCHEDULES {
            s.parse::<BetaSchedule>().unwrap();
        }
        for s in VARIANCES {
            s.parse::<Variance>().unwrap();
        }
        for s in PARAMETERIZATIONS {
            s.parse::<Parameterization>().unwrap();
        }
        for s in ["ddpm", "ddim", "euler", "heun", "midpoint"] {
            s.parse::<Sampler>().unwrap();
        }
    }
}
