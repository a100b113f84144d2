//! The C ABI: thin functions over the Rust API, and nothing else.
//!
//! Conventions (also in docs/c-abi.md): every handle has a `_new`/`_load` and a `_free` that accepts
//! NULL; a `const` pointer parameter is not mutated; outputs go only through out-pointers and are
//! written only on success; every buffer comes with its length; every fallible call returns a
//! [`FlameStatus`] and leaves a message for [`flame_last_error`]. Every entry point checks its
//! pointers and catches panics, so no panic crosses into the host.

mod amass;
mod batch;
mod cleanup;
mod errors;
mod handles;
mod poses;
mod retarget;
mod robot;
mod stream;

use std::ffi::{c_char, c_void, CStr};
use std::sync::atomic::Ordering;
use std::sync::Arc;

use crate::checkpoint::ModelFile;
use crate::error::{invalid_arg, Error};
use crate::models::{LoadOptions, Model, WeightType};
use crate::session::{EditMethod, EditParams, Sampler, Session, SessionParams};
use crate::targets::{TargetParams, TargetSchedule};

pub use amass::{flame_session_write_amass, FLAME_AMASS_SMPLH, FLAME_AMASS_SMPLX};
pub use batch::{
    flame_batch_cancel, flame_batch_free, flame_batch_new, flame_batch_params_default,
    flame_batch_run, FlameBatch, FlameBatchParams, FlameBatchSummary,
};
use cleanup::finish_arg;
pub use cleanup::{
    flame_cleanup_params_default, flame_session_read_cleaned, FlameCleanupParams, FlameFeet,
    FlameRootMotion,
};
use errors::{catch_quietly, guard, Fail};
pub use errors::{flame_last_error, flame_status_string, FlameStatus};
use handles::{model_ref, session_ref};
pub use handles::{FlameModel, FlameSession};
pub use poses::{FlameConvention, FlameLayout, FLAME_READ_RAW_SIGNS, FLAME_READ_SMOOTH};
pub use robot::{
    FlameRobot, FlameRobotRetarget, FlameRobotState, FLAME_ROBOT_BEYONDMIMIC_CSV_XYZW,
    FLAME_ROBOT_CSV_HEADER, FLAME_ROBOT_GMR_NPZ_XYZW, FLAME_ROBOT_QPOS_CSV_WXYZ,
    FLAME_ROBOT_QPOS_NPY_WXYZ,
};
pub use stream::{
    flame_stream_cancel, flame_stream_close, flame_stream_close_looped, flame_stream_free,
    flame_stream_interrupt, flame_stream_interrupt_stage, flame_stream_new,
    flame_stream_params_default, flame_stream_pump, flame_stream_push, flame_stream_push_stage,
    flame_stream_read, flame_stream_read_cleaned, flame_stream_set_playhead, flame_stream_status,
    FlameStream, FlameStreamParams, FlameStreamStatus,
};

/// The ABI version: bumped whenever a function's signature or a struct's layout changes.
pub const FLAME_ABI_VERSION: u32 = 4;
/// libflame's version, major part.
pub const FLAME_VERSION_MAJOR: u32 = 0;
/// libflame's version, minor part.
pub const FLAME_VERSION_MINOR: u32 = 1;
/// libflame's version, patch part.
pub const FLAME_VERSION_PATCH: u32 = 0;
/// The most worker threads `FlameModelParams.threads` and `FlameSessionParams.threads` may ask
/// for; above it a load or session start fails with `FLAME_STATUS_INVALID_ARGUMENT`.
pub const FLAME_MAX_THREADS: u32 = 256;
/// Passed in `joints` of [`flame_session_keep_joints`] to keep the root translation channels.
pub const FLAME_ROOT_TRANSLATION: i32 = -1;

/// Sampler choice in [`FlameSessionParams`].
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameSampler {
    /// The model file's default.
    Default = 0,
    /// Diffusion: ancestral DDPM steps (fresh noise at every step).
    Ddpm = 1,
    /// Diffusion: DDIM steps (`eta` sets how much fresh noise; 0 = deterministic).
    Ddim = 2,
    /// Flow matching (Motion Flow Matching models): Euler steps.
    Euler = 3,
    /// Flow matching: Heun, two network evaluations per step.
    Heun = 4,
    /// Flow matching: midpoint rule, two network evaluations per step.
    Midpoint = 5,
    /// Latent consistency models (MotionLCM): 1 to 4 steps, the guidance embedded in one pass.
    Lcm = 6,
}

/// How a session imposes the kept reference values ([`FlameEditParams::method`]).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameEditMethod {
    /// The model family's own method: FLAME's for FLAME files, MDM's for MDM files, trajectory
    /// rewriting for flow-matching files.
    Auto = 0,
    /// FLAME: the reference, diffused to each step's noise level, overwrites the kept values of
    /// x_t before the step (diffusion models).
    NoisedReference = 1,
    /// MDM: the reference overwrites the kept values of the predicted clean motion (diffusion
    /// models).
    ReplaceX0 = 2,
    /// Motion Flow Matching: the kept values follow the straight path from the initial noise to
    /// the reference while step / steps <= `edit_till` (flow-matching models).
    RewriteTrajectory = 3,
}

/// Editing settings of a session. Initialise with [`flame_edit_params_default`].
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameEditParams {
    /// `sizeof(FlameEditParams)`.
    pub struct_size: u32,
    /// A [`FlameEditMethod`] value.
    pub method: i32,
    /// Flow models: the fraction of the steps, from the noise end, that rewrite the trajectory
    /// (0..1; default 0.2).
    pub edit_till: f32,
    /// Nonzero (default): after the last step the kept values are pasted exactly into the
    /// result and the seams blended. Zero: the official behaviour.
    pub paste: u32,
    /// Frames over which a seam's offset fades out (default 4; 0 = no blending).
    pub seam_frames: u32,
}

/// How the weight of position targets changes with the noise level τ (0 = clean, 1 = noise).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameTargetSchedule {
    /// `4·τ·(1 − τ)`: nothing at either end, full strength half way (MoLA's MPGD; default).
    Mpgd = 0,
    /// The same weight at every step.
    Constant = 1,
}

/// How strongly position targets steer ([`flame_session_set_position_targets`]). Initialise
/// with [`flame_target_params_default`].
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameTargetParams {
    /// `sizeof(FlameTargetParams)`.
    pub struct_size: u32,
    /// The step size `s` of `ρ = s·w(τ)`, in [0, 100] (default 0.6, MoLA's edit scale; 0 = off).
    pub scale: f32,
    /// A [`FlameTargetSchedule`] value.
    pub schedule: i32,
}

/// One time stage of a prompt for [`flame_session_set_prompt_stages`]: a whole-body text, a
/// frame count, and optionally a text per body part (NULL or empty: the part follows `text`).
/// The part fields are the HuMMan-MoGen annotation's; FineMoGen reads them, other families take
/// one stage without them. Set `struct_size = sizeof(FlameStage)`.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameStage {
    /// `sizeof(FlameStage)`; every stage of an array has the same.
    pub struct_size: u32,
    /// Frames of this stage (1 to the model's stage length; the stages add up to the session's).
    pub frames: u32,
    /// What the whole body does (UTF-8, NUL-terminated).
    pub text: *const c_char,
    /// What the head does (UTF-8, NUL-terminated; NULL = it follows `text`, as every part
    /// below).
    pub head: *const c_char,
    /// The spine.
    pub stem: *const c_char,
    /// The left arm.
    pub left_arm: *const c_char,
    /// The right arm.
    pub right_arm: *const c_char,
    /// The left leg.
    pub left_leg: *const c_char,
    /// The right leg.
    pub right_leg: *const c_char,
    /// The root's trajectory.
    pub pelvis: *const c_char,
}

/// Named groups of channels for [`flame_session_keep_part`].
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameBodyPart {
    /// The root's trajectory (smpl24_6d: the translation; humanml263: root yaw velocity, planar
    /// velocity and height).
    RootPath = 0,
    /// Root path, pelvis and legs (what an upper-body edit keeps).
    LowerBody = 1,
    /// Spine, neck, head, collars and arms.
    UpperBody = 2,
    /// Collars, shoulders, elbows, wrists (and hands).
    Arms = 3,
    /// Hips, knees, ankles and feet (and foot contacts).
    Legs = 4,
}

/// The standard editing tasks of [`flame_session_set_task_mask`].
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameEditTask {
    /// Keep the first and last quarter of the frames, generate the middle.
    Inbetween = 0,
    /// Keep the first quarter of the frames, generate the rest.
    Predict = 1,
    /// Keep the lower body on every frame, generate the upper body.
    UpperBody = 2,
    /// Keep the root path on every frame, generate the body.
    Path = 3,
}

/// Which motion [`flame_session_read`] returns.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameWhich {
    /// The current sample x_t (the final motion once every step has run).
    Sample = 0,
    /// The model's current estimate of the clean motion x0 (a preview while stepping).
    Estimate = 1,
}

/// The container [`flame_session_write_gltf`] writes.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameGltfContainer {
    /// Binary glTF (`.glb`): what glTFast and other run-time importers load from bytes.
    Glb = 0,
    /// JSON glTF (`.gltf`) with the buffer embedded as a base64 data URI.
    Gltf = 1,
}

/// How [`flame_session_write_gltf`] exports. Initialise with [`flame_gltf_params_default`].
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameGltfParams {
    /// `sizeof(FlameGltfParams)`.
    pub struct_size: u32,
    /// A [`FlameGltfContainer`] value (default GLB).
    pub container: i32,
    /// Read flags applied before posing: [`FLAME_READ_SMOOTH`], [`FLAME_READ_RAW_SIGNS`]
    /// (default 0).
    pub flags: u32,
    /// Animation frames per second; 0 (default) = the model's.
    pub fps: f32,
    /// The animation's name (sanitised: letters, digits, `-`, `_`); NULL (default) = the
    /// session's prompt, sanitised, or `motion`.
    pub name: *const c_char,
    /// Post-processing before export (since version 2 of this struct); NULL (default) = the
    /// raw poses. Its `fps`, when set, overrides `fps` above. A `separate` root motion adds the
    /// `root` bone to the skeleton.
    pub cleanup: *const FlameCleanupParams,
}

/// Size of version 1 of [`FlameGltfParams`] (up to `name`).
const GLTF_PARAMS_V1: usize = std::mem::offset_of!(FlameGltfParams, cleanup);

/// What a model's linear-layer weights are held and multiplied in ([`FlameModelParams`]),
/// whatever the file stores. Embeddings, norms and biases stay f32.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlameWeights {
    /// f32: exact, the fastest on CPUs without half-precision arithmetic.
    F32 = 0,
    /// IEEE half: half the memory; features within ~1e-3 of f32 on the demo model.
    F16 = 1,
    /// bfloat16: half the memory; coarser than f16 (~5e-2 on the demo model).
    Bf16 = 2,
    /// bf16 weights and bf16 products accumulated in f32 (activations rounded to bf16 per
    /// layer): half the memory and about twice the f32 speed; needs AVX512_BF16
    /// (`INVALID_ARGUMENT` at load otherwise).
    Bf16Compute = 3,
    /// 8-bit weights (per-output scales) and 8-bit activations (per-row scales), integer
    /// products: a quarter of the memory; runs on AVX512_VNNI, or on AVX2 with activations in
    /// 63 levels (`INVALID_ARGUMENT` at load without either). A file written by `flame
    /// quantize` loads its calibrated integers as stored (any other type multiplies them out);
    /// one written with `--group` (a scale per group of inputs) is `INVALID_ARGUMENT` here and
    /// loads as f32, f16 or bf16.
    Int8 = 4,
}

/// Options of [`flame_model_load`]. Initialise with [`flame_model_params_default`].
///
/// Version 1 of this struct ended after `threads` (8 bytes); a caller built against it passes
/// `struct_size = 8` and gets the defaults of every later field.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameModelParams {
    /// `sizeof(FlameModelParams)`: lets later versions add fields.
    pub struct_size: u32,
    /// Threads for work done at load (encoding the guidance prompt): 1 to [`FLAME_MAX_THREADS`],
    /// or 0 = one per core (at most [`FLAME_MAX_THREADS`]); more is `INVALID_ARGUMENT`.
    pub threads: u32,
    /// A [`FlameWeights`] value (since version 2).
    pub weights: i32,
}

/// Size of version 1 of [`FlameModelParams`] (`struct_size`, `threads`).
const MODEL_PARAMS_V1: usize = 8;

/// Settings of one generation. Initialise with [`flame_session_params_default`]; zero (or a
/// negative `eta`/`guidance`, a NULL `respacing`) means "the model file's default".
///
/// Version 1 of this struct ended after `threads` (40 bytes on 64-bit targets), version 2 after
/// `respacing` (48 bytes); a caller built against either passes its `sizeof` and gets the
/// defaults of the later fields (no respacing, no loop).
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameSessionParams {
    /// `sizeof(FlameSessionParams)`.
    pub struct_size: u32,
    /// Frames to generate; 0 = model default.
    pub frames: u32,
    /// Sampler steps (respaced from the trained schedule); 0 = model default.
    pub steps: u32,
    /// A [`FlameSampler`] value.
    pub sampler: i32,
    /// DDIM eta; negative = model default.
    pub eta: f32,
    /// Classifier-free guidance scale; negative = model default.
    pub guidance: f32,
    /// Seed of the session's noise generator.
    pub seed: u64,
    /// Worker threads this session creates and owns: 1 to [`FLAME_MAX_THREADS`], or 0 = one per
    /// core (at most [`FLAME_MAX_THREADS`]); more is `INVALID_ARGUMENT`.
    pub threads: u32,
    /// NULL = none, or a NUL-terminated guided-diffusion respacing string choosing which
    /// training steps to sample: `"ddimN"` (every k-th step, N steps), `"N"` (N evenly spread
    /// steps) or section counts `"15,15,8,6,6"`. It sets the step count (a nonzero `steps` must
    /// agree). Only for models with `diffusion.spacing` `respace` (FLAME, MDM); a model with
    /// diffusers spacing or a flow model refuses it (`INVALID_ARGUMENT`). Read only during
    /// [`flame_session_new`] (since version 2 of this struct).
    pub respacing: *const c_char,
    /// 1 = generate a loop of `frames` frames whose end flows into its start (position and
    /// velocity of every joint): the session samples twice, a generation of `frames` plus a
    /// lead of 0.5 s, then an edit of it that keeps the lead on both sides of the wrap
    /// (`flame generate --loop`). [`flame_session_step`] and the progress count both passes.
    /// The finished sample reads as the `frames` frames of the cycle: every pose read applies
    /// the wrap's correction (any cleanup's `wrap` is taken as 2), raw features drop the next
    /// cycle's first frame. The sampled space (what [`flame_session_set_noise`] takes) has
    /// the `frames` plus the lead's rows. `INVALID_ARGUMENT` for latent models (MLD, MoLA: use the cleanup's
    /// `wrap` on a plain session), a cycle too short or too long for the model; a loop session
    /// refuses time stages, references, masks and position targets. 0 = a plain generation
    /// (since version 3 of this struct).
    pub looped: u32,
}

/// Size of version 1 of [`FlameSessionParams`]: up to `threads` (40 bytes on 64-bit targets,
/// where the padding after `threads` is where `respacing` now starts).
const SESSION_PARAMS_V1: usize = std::mem::offset_of!(FlameSessionParams, respacing);
/// Size of version 2: up to `respacing`.
const SESSION_PARAMS_V2: usize = std::mem::offset_of!(FlameSessionParams, looped);

/// What [`flame_model_info`] reports. Strings and arrays belong to the model and stay valid
/// until it is freed.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlameModelInfo {
    /// Set by the caller to `sizeof(FlameModelInfo)`.
    pub struct_size: u32,
    /// Feature channels per frame (147 for FLAME).
    pub feature_dim: u32,
    /// Joints of the motion format's skeleton.
    pub joint_count: u32,
    /// The largest frame count a session may ask for.
    pub max_frames: u32,
    /// Frames a session generates when `FlameSessionParams.frames` is 0.
    pub default_frames: u32,
    /// Sampling steps a session takes when `FlameSessionParams.steps` is 0.
    pub default_steps: u32,
    /// Steps of the trained diffusion schedule (the most a session may ask for).
    pub num_timesteps: u32,
    /// A [`FlameSampler`] value.
    pub default_sampler: i32,
    /// Frames per second of the motion format.
    pub fps: f32,
    /// Classifier-free guidance scale a session uses when it asks for the default.
    pub default_guidance: f32,
    /// DDIM eta a session uses when it asks for the default.
    pub default_eta: f32,
    /// For example `"flame"`.
    pub architecture: *const c_char,
    /// For example `"smpl24_6d"`.
    pub motion_format: *const c_char,
    /// For example `"roberta"`.
    pub text_encoder: *const c_char,
    /// `joint_count` joint names.
    pub joint_names: *const *const c_char,
    /// `joint_count` parent indices, -1 for the root.
    pub joint_parents: *const i32,
    /// Nonzero when the model samples a latent that its decoder turns into motion (MoLA): the
    /// frames a read returns are then the length the decoder decides
    /// ([`flame_session_read_frames`]), and masks and reference motions do not apply.
    pub latent: u32,
    /// Channels per row of the sampled space (`feature_dim`, or the latent's channels): the
    /// width of [`flame_session_set_noise`]'s rows.
    pub sample_dim: u32,
    /// Nonzero when the model has a trajectory ControlNet: [`flame_session_set_control`]
    /// makes its motion follow joint positions (MotionLCM control files).
    pub control: u32,
}

/// What [`flame_session_prompt_info`] reports about the last prompt: how it fitted the text
/// encoder's window. Set `struct_size = sizeof(FlamePromptInfo)` first.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct FlamePromptInfo {
    /// Set by the caller to `sizeof(FlamePromptInfo)`.
    pub struct_size: u32,
    /// Tokens of the whole prompt, special tokens included.
    pub tokens: u32,
    /// Tokens the text encoder saw (at most `window`).
    pub kept: u32,
    /// The encoder's window: the most tokens it sees, special tokens included.
    pub window: u32,
    /// 1 when the window cut the prompt (`tokens > kept`).
    pub truncated: u32,
    /// 1 when the prompt is empty or blank: generation without text (the model's
    /// unconditional input, no guidance pass).
    pub unconditional: u32,
    /// The text that was cut off, UTF-8 ("" when nothing was). Owned by the session: valid
    /// until its next `flame_session_set_prompt` or `flame_session_free`.
    pub dropped: *const c_char,
}

/// Called after every step with the caller's `user_data`, the steps done and the total.
/// NULL (no callback) is allowed wherever one is passed.
pub type FlameProgressCallback =
    Option<unsafe extern "C" fn(user_data: *mut c_void, steps_done: u32, steps_total: u32)>;

fn check_size(struct_size: u32, needed: usize, what: &str) -> Result<(), Fail> {
    if (struct_size as usize) < needed {
        return Err(invalid_arg!(
            "{what}.struct_size is {struct_size}, expected at least {needed}"
        )
        .into());
    }
    Ok(())
}

/// A parameter struct passed in: not NULL, and declaring at least this library's size.
unsafe fn struct_arg<'a, T>(
    ptr: *const T,
    struct_size: impl FnOnce(&T) -> u32,
    name: &str,
) -> Result<&'a T, Fail> {
    let p = ptr
        .as_ref()
        .ok_or_else(|| Fail::from(invalid_arg!("`{name}` is NULL")))?;
    check_size(struct_size(p), std::mem::size_of::<T>(), name)?;
    Ok(p)
}

/// Copies `values` to a caller buffer of `len` (`out` NULL: only the length is reported), with
/// `BUFFER_TOO_SMALL` when it does not fit; `*out_len` gets the length either way.
unsafe fn copy_out<T: Copy>(
    values: &[T],
    out: *mut T,
    len: usize,
    out_len: *mut usize,
    unit: &'static str,
) -> Result<(), Fail> {
    out_len.write(values.len());
    if out.is_null() {
        return Ok(());
    }
    if len < values.len() {
        return Err(Fail::BufferTooSmall {
            needed: values.len(),
            given: len,
            unit,
        });
    }
    std::ptr::copy_nonoverlapping(values.as_ptr(), out, values.len());
    Ok(())
}

/// Writes through an out-pointer after checking it.
unsafe fn write_out<T>(out: *mut T, value: T, name: &str) -> Result<(), Fail> {
    if out.is_null() {
        return Err(invalid_arg!("`{name}` is NULL").into());
    }
    out.write(value);
    Ok(())
}

/// Runs `f` on a live session with a caller buffer of `frames × dim` values, after checking
/// that shape against the session's.
unsafe fn with_frames_buffer<T>(
    session: *mut FlameSession,
    ptr: *const T,
    frames: u32,
    dim: u32,
    name: &str,
    f: impl FnOnce(&mut Session, &[T]) -> crate::Result<()>,
) -> Result<(), Fail> {
    let s = session_ref(session)?;
    let n = (frames as usize)
        .checked_mul(dim as usize)
        .ok_or_else(|| invalid_arg!("frames × dim overflows"))?;
    let values = slice_arg(ptr, n, name)?;
    s.with(|st| {
        st.check_shape(frames, dim)?;
        Ok(f(&mut st.session, values)?)
    })
}

/// Borrows a caller buffer of `len` elements (NULL is allowed only when `len` is 0).
unsafe fn slice_arg<'a, T>(ptr: *const T, len: usize, name: &str) -> Result<&'a [T], Fail> {
    if len == 0 {
        return Ok(&[]);
    }
    if ptr.is_null() {
        return Err(invalid_arg!("`{name}` is NULL but its length is {len}").into());
    }
    if len > isize::MAX as usize / std::mem::size_of::<T>().max(1) {
        return Err(invalid_arg!("`{name}` length {len} is too large").into());
    }
    Ok(std::slice::from_raw_parts(ptr, len))
}

unsafe fn str_arg<'a>(ptr: *const c_char, name: &str) -> Result<&'a str, Fail> {
    if ptr.is_null() {
        return Err(invalid_arg!("`{name}` is NULL").into());
    }
    CStr::from_ptr(ptr)
        .to_str()
        .map_err(|_| invalid_arg!("`{name}` is not valid UTF-8").into())
}

/// The ABI version this library implements ([`FLAME_ABI_VERSION`]).
#[no_mangle]
pub extern "C" fn flame_abi_version() -> u32 {
    FLAME_ABI_VERSION
}

/// The library version as a static NUL-terminated string, e.g. `"0.1.0"`.
#[no_mangle]
pub extern "C" fn flame_version_string() -> *const c_char {
    concat!(env!("CARGO_PKG_VERSION"), "\0").as_ptr() as *const c_char
}

/// Fills `*params` with the defaults.
///
/// # Safety
/// `params` is NULL or points to writable memory for a `FlameModelParams`.
#[no_mangle]
pub unsafe extern "C" fn flame_model_params_default(params: *mut FlameModelParams) -> FlameStatus {
    guard(|| write_out(params, default_model_params(), "params"))
}

fn default_model_params() -> FlameModelParams {
    FlameModelParams {
        struct_size: std::mem::size_of::<FlameModelParams>() as u32,
        threads: 0,
        weights: FlameWeights::F32 as i32,
    }
}

/// Reads the caller's params: only the `struct_size` bytes it declares (at least version 1's),
/// later fields keeping their defaults.
unsafe fn model_params(params: *const FlameModelParams) -> Result<FlameModelParams, Fail> {
    let mut p = default_model_params();
    if params.is_null() {
        return Ok(p);
    }
    // SAFETY: the caller's struct is readable for at least its first field.
    let declared = std::ptr::read_unaligned(params as *const u32);
    check_size(declared, MODEL_PARAMS_V1, "params")?;
    // Whole fields only: the end of the newest version the declared size covers.
    let n = if declared as usize >= std::mem::size_of::<FlameModelParams>() {
        std::mem::size_of::<FlameModelParams>()
    } else {
        MODEL_PARAMS_V1
    };
    // SAFETY: the caller's struct is readable for the `declared` ≥ n bytes it says it has, and
    // `p` is a plain-data struct of at least n bytes.
    std::ptr::copy_nonoverlapping(params as *const u8, &mut p as *mut _ as *mut u8, n);
    Ok(p)
}

/// The load options a params struct asks for.
fn load_options(p: &FlameModelParams) -> Result<LoadOptions, Fail> {
    let weights = match p.weights {
        0 => WeightType::F32,
        1 => WeightType::F16,
        2 => WeightType::Bf16,
        3 => WeightType::Bf16Compute,
        4 => WeightType::Int8,
        w => {
            return Err(invalid_arg!(
                "params.weights is {w}; expected FLAME_WEIGHTS_F32 (0), FLAME_WEIGHTS_F16 (1), \
                 FLAME_WEIGHTS_BF16 (2), FLAME_WEIGHTS_BF16_COMPUTE (3) or FLAME_WEIGHTS_INT8 (4)"
            )
            .into())
        }
    };
    Ok(LoadOptions { weights })
}

/// Finishes a load: encodes the guidance prompt once, with the requested threads.
fn finish_load(model: Model, params: &FlameModelParams) -> Result<Box<FlameModel>, Fail> {
    let pool = crate::pool::WorkerPool::new(params.threads as usize)?;
    pool.install(|| model.uncond().map(|_| ()))?;
    Ok(Box::new(FlameModel::new(Arc::new(model))))
}

/// Loads a model file. `params` may be NULL for the defaults. On success `*model` owns the
/// new model; free it with [`flame_model_free`].
///
/// # Safety
/// `path` is a NUL-terminated string; `params` is NULL or a valid `FlameModelParams`;
/// `model` points to writable memory for a pointer.
#[no_mangle]
pub unsafe extern "C" fn flame_model_load(
    path: *const c_char,
    params: *const FlameModelParams,
    model: *mut *mut FlameModel,
) -> FlameStatus {
    guard(|| {
        if model.is_null() {
            return Err(invalid_arg!("`model` is NULL").into());
        }
        let p = model_params(params)?;
        let path = str_arg(path, "path")?;
        let opts = load_options(&p)?;
        let m = finish_load(Model::load_with(path, &opts)?, &p)?;
        write_out(model, Box::into_raw(m), "model")
    })
}

/// Loads a model from the bytes of a model file, which are copied (the caller keeps its buffer).
///
/// # Safety
/// `bytes` points to `len` readable bytes; `params` and `model` as in [`flame_model_load`].
#[no_mangle]
pub unsafe extern "C" fn flame_model_load_from_memory(
    bytes: *const u8,
    len: usize,
    params: *const FlameModelParams,
    model: *mut *mut FlameModel,
) -> FlameStatus {
    guard(|| {
        if model.is_null() {
            return Err(invalid_arg!("`model` is NULL").into());
        }
        let p = model_params(params)?;
        let bytes = slice_arg(bytes, len, "bytes")?;
        let opts = load_options(&p)?;
        let m = finish_load(
            Model::from_file_with(ModelFile::from_bytes(bytes)?, &opts)?,
            &p,
        )?;
        write_out(model, Box::into_raw(m), "model")
    })
}

/// Releases the caller's reference to a model; NULL is ignored. Sessions keep their model
/// alive, so a model may be freed while its sessions still run.
///
/// # Safety
/// `model` is NULL or a pointer returned by a load function and not yet freed.
#[no_mangle]
pub unsafe extern "C" fn flame_model_free(model: *mut FlameModel) {
    catch_quietly(|| {
        if !model.is_null() {
            drop(Box::from_raw(model));
        }
    });
}

/// Describes a model. Set `info->struct_size = sizeof(FlameModelInfo)` first.
///
/// # Safety
/// `model` is a live model; `info` points to a writable `FlameModelInfo`.
#[no_mangle]
pub unsafe extern "C" fn flame_model_info(
    model: *const FlameModel,
    info: *mut FlameModelInfo,
) -> FlameStatus {
    guard(|| {
        let m = model_ref(model)?;
        if info.is_null() {
            return Err(invalid_arg!("`info` is NULL").into());
        }
        check_size(
            (*info).struct_size,
            std::mem::size_of::<FlameModelInfo>(),
            "info",
        )?;
        info.write(m.info());
        Ok(())
    })
}

/// Fills `*params` with the defaults (every setting taken from the model file, seed 0, one
/// thread per core).
///
/// # Safety
/// `params` points to writable memory for a `FlameSessionParams`.
#[no_mangle]
pub unsafe extern "C" fn flame_session_params_default(
    params: *mut FlameSessionParams,
) -> FlameStatus {
    guard(|| write_out(params, default_session_params(), "params"))
}

fn default_session_params() -> FlameSessionParams {
    FlameSessionParams {
        struct_size: std::mem::size_of::<FlameSessionParams>() as u32,
        frames: 0,
        steps: 0,
        sampler: FlameSampler::Default as i32,
        eta: -1.0,
        guidance: -1.0,
        seed: 0,
        threads: 0,
        respacing: std::ptr::null(),
        looped: 0,
    }
}

/// Reads the caller's session params: only the `struct_size` bytes it declares (at least
/// version 1's), later fields keeping their defaults (`respacing` NULL, `looped` 0).
unsafe fn session_params_in(params: *const FlameSessionParams) -> Result<SessionParams, Fail> {
    // SAFETY: the caller's struct is readable for at least its first field.
    let declared = std::ptr::read_unaligned(params as *const u32);
    check_size(declared, SESSION_PARAMS_V1, "params")?;
    let full = std::mem::size_of::<FlameSessionParams>();
    let n = [full, SESSION_PARAMS_V2, SESSION_PARAMS_V1]
        .into_iter()
        .find(|&n| declared as usize >= n)
        .unwrap_or(SESSION_PARAMS_V1);
    let mut p = default_session_params();
    // SAFETY: the caller's struct is readable for the `declared` ≥ n bytes it says it has, and
    // `p` is a plain-data struct of at least n bytes.
    std::ptr::copy_nonoverlapping(params as *const u8, &mut p as *mut _ as *mut u8, n);
    session_params(&p)
}

/// # Safety
/// `p.respacing` is NULL or a NUL-terminated string.
unsafe fn session_params(p: &FlameSessionParams) -> Result<SessionParams, Fail> {
    let nonzero = |v: u32| (v != 0).then_some(v as usize);
    let default_if_negative = |v: f32, name: &str| -> Result<Option<f32>, Fail> {
        if v.is_nan() {
            return Err(invalid_arg!("`{name}` is NaN").into());
        }
        Ok((v >= 0.0).then_some(v))
    };
    let sampler = match p.sampler {
        0 => None,
        1 => Some(Sampler::Ddpm),
        2 => Some(Sampler::Ddim),
        3 => Some(Sampler::Euler),
        4 => Some(Sampler::Heun),
        5 => Some(Sampler::Midpoint),
        6 => Some(Sampler::Lcm),
        s => {
            return Err(invalid_arg!(
                "unknown sampler {s} (0 default, 1 DDPM, 2 DDIM, 3 Euler, 4 Heun, 5 midpoint, 6 \
                 LCM)"
            )
            .into())
        }
    };
    Ok(SessionParams {
        frames: nonzero(p.frames),
        steps: nonzero(p.steps),
        sampler,
        eta: default_if_negative(p.eta, "eta")?,
        guidance: default_if_negative(p.guidance, "guidance")?,
        clip_denoised: None,
        seed: p.seed,
        threads: p.threads as usize,
        respacing: match p.respacing.is_null() {
            true => None,
            false => Some(str_arg(p.respacing, "respacing")?.to_owned()),
        },
        looped: match p.looped {
            0 => false,
            1 => true,
            v => return Err(invalid_arg!("`looped` is {v}: 0 (plain) or 1 (a loop)").into()),
        },
    })
}

/// Fills `*params` with the editing defaults: the model family's method, `edit_till` 0.2,
/// paste on, 4 seam frames.
///
/// # Safety
/// `params` points to writable memory for a `FlameEditParams`.
#[no_mangle]
pub unsafe extern "C" fn flame_edit_params_default(params: *mut FlameEditParams) -> FlameStatus {
    guard(|| {
        let d = EditParams::default();
        let p = FlameEditParams {
            struct_size: std::mem::size_of::<FlameEditParams>() as u32,
            method: FlameEditMethod::Auto as i32,
            edit_till: d.edit_till,
            paste: d.paste as u32,
            seam_frames: d.seam_frames as u32,
        };
        write_out(params, p, "params")
    })
}

/// Sets how the session edits (method, `edit_till`, final paste). Checked against the model:
/// FLAME's and MDM's methods need a diffusion model, trajectory rewriting a flow model.
///
/// # Safety
/// `session` is a live session; `params` points to a valid `FlameEditParams`.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_edit_params(
    session: *mut FlameSession,
    params: *const FlameEditParams,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let p = struct_arg(params, |p| p.struct_size, "params")?;
        let method = u32::try_from(p.method)
            .map_err(|_| invalid_arg!("unknown edit method {}", p.method))
            .and_then(EditMethod::from_u32)?;
        let e = EditParams {
            method,
            edit_till: p.edit_till,
            paste: p.paste != 0,
            seam_frames: p.seam_frames as usize,
        };
        s.with(|st| Ok(st.session.set_edit_params(&e)?))
    })
}

/// Fills `*params` with MoLA's target defaults: scale 0.6, the MPGD schedule. A session that
/// never receives target params uses its family's defaults instead: MPGD for latent models,
/// the constant schedule for FLAME, MDM and Motion Flow Matching (see docs/targets.md).
///
/// # Safety
/// `params` points to writable memory for a `FlameTargetParams`.
#[no_mangle]
pub unsafe extern "C" fn flame_target_params_default(
    params: *mut FlameTargetParams,
) -> FlameStatus {
    guard(|| {
        let d = TargetParams::default();
        let p = FlameTargetParams {
            struct_size: std::mem::size_of::<FlameTargetParams>() as u32,
            scale: d.scale,
            schedule: FlameTargetSchedule::Mpgd as i32,
        };
        write_out(params, p, "params")
    })
}

/// Sets how strongly position targets steer.
///
/// # Safety
/// `session` is a live session; `params` points to a valid `FlameTargetParams`.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_target_params(
    session: *mut FlameSession,
    params: *const FlameTargetParams,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let p = struct_arg(params, |p| p.struct_size, "params")?;
        let schedule = u32::try_from(p.schedule)
            .map_err(|_| invalid_arg!("unknown target schedule {}", p.schedule))
            .and_then(TargetSchedule::from_u32)?;
        let t = TargetParams {
            scale: p.scale,
            schedule,
        };
        s.with(|st| Ok(st.session.set_target_params(&t)?))
    })
}

/// The session's target params in `*params`: the family's defaults (scale 0.6; MPGD for latent
/// models, the constant schedule for FLAME, MDM and Motion Flow Matching) until
/// [`flame_session_set_target_params`] changes them. Start from these to change one field.
///
/// # Safety
/// `session` is a live session; `params` points to writable memory for a `FlameTargetParams`.
#[no_mangle]
pub unsafe extern "C" fn flame_session_target_params(
    session: *const FlameSession,
    params: *mut FlameTargetParams,
) -> FlameStatus {
    guard(|| {
        let p = session_ref(session)?.with(|st| Ok(*st.session.target_params()))?;
        let out = FlameTargetParams {
            struct_size: std::mem::size_of::<FlameTargetParams>() as u32,
            scale: p.scale,
            schedule: match p.schedule {
                TargetSchedule::Mpgd => FlameTargetSchedule::Mpgd,
                TargetSchedule::Constant => FlameTargetSchedule::Constant,
            } as i32,
        };
        write_out(params, out, "params")
    })
}

/// A per-value mask argument: NULL with length 0 is "no mask" (NaN = free); NULL with a length
/// is an error.
///
/// # Safety
/// `mask` is NULL or points to `mask_len` bytes.
unsafe fn optional_mask<'a>(mask: *const u8, mask_len: usize) -> Result<Option<&'a [u8]>, Fail> {
    match mask.is_null() {
        true if mask_len == 0 => Ok(None),
        true => Err(invalid_arg!("`mask` is NULL but its length is {mask_len}").into()),
        false => Ok(Some(slice_arg(mask, mask_len, "mask")?)),
    }
}

/// Steers the following steps toward joint positions: `targets` = `frames` × joints × 3 floats
/// (x, y, z per joint, the joints of the model's skeleton as [`FlameModelInfo::joint_count`] counts
/// them, frame-major), in `convention` (a [`FlameConvention`]) and its unit (metres or
/// centimetres), covering the motion's first `frames` frames (1 <= frames <= the session's
/// frames; `targets_len` must be a multiple of joints × 3). `mask` = one byte per value of
/// `targets` (nonzero = constrained), or NULL: then a NaN value is free and every other value
/// is constrained. A constrained value must be finite and at least one must be constrained.
/// Each step then moves its clean-motion estimate down the gradient of the sum over frames and
/// joints of ‖(position − target) ⊙ mask‖ (MoLA's MPGD; see docs/targets.md). A mask and reference
/// set for editing still keep their values. Replaces earlier targets; on error nothing changes.
///
/// # Safety
/// `session` is a live session; `targets` points to `targets_len` floats; `mask` is NULL or
/// points to `mask_len` bytes.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_position_targets(
    session: *mut FlameSession,
    targets: *const f32,
    targets_len: usize,
    mask: *const u8,
    mask_len: usize,
    convention: i32,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let values = slice_arg(targets, targets_len, "targets")?;
        let mask = optional_mask(mask, mask_len)?;
        let convention = poses::convention(convention)?;
        s.with(|st| {
            Ok(st
                .session
                .set_position_target_values(values, mask, convention)?)
        })
    })
}

/// Position targets for an editing task (`task` as in [`flame_session_set_task_mask`]) from a
/// reference motion: `frames` × `dim` model-space features (what a session of this model
/// produces), 1 <= `frames` <= the session's frames. The reference's joint positions become
/// targets where the task keeps them: `path` the pelvis on every frame, `upper-body` the pelvis
/// and legs on every frame, `inbetween` and `predict` every joint on the frames their masks
/// keep (MoLA's MPGD tasks; for latent models, whose sample is not the motion, this is how a
/// reference edits). Replaces earlier targets. On a model with a trajectory ControlNet
/// (`FlameModelInfo.control`: a MotionLCM control file) the same joints become the control
/// hint instead, replacing one set by [`flame_session_set_control`].
///
/// # Safety
/// `session` is a live session; `features` points to `frames * dim` floats.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_task_targets(
    session: *mut FlameSession,
    features: *const f32,
    frames: u32,
    dim: u32,
    task: i32,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let task = usize::try_from(task)
            .ok()
            .and_then(|t| crate::motion::Task::ALL.get(t).copied())
            .ok_or_else(|| invalid_arg!("unknown editing task {task} (a FlameEditTask, 0 to 3)"))?;
        let values = reference_arg(features, frames, dim)?;
        s.with(|st| {
            check_reference_shape(st, frames, dim)?;
            Ok(st.session.set_task_targets(values, task)?)
        })
    })
}

/// Removes the position targets.
///
/// # Safety
/// `session` is a live session.
#[no_mangle]
pub unsafe extern "C" fn flame_session_clear_position_targets(
    session: *mut FlameSession,
) -> FlameStatus {
    guard(|| {
        session_ref(session)?.with(|st| {
            st.session.clear_position_targets();
            Ok(())
        })
    })
}

/// Makes the following steps follow joint positions through the model's trajectory ControlNet
/// (MotionLCM files converted from a control checkpoint: [`FlameModelInfo::control`] is
/// nonzero). `positions` = `frames` × joints × 3 floats as for
/// [`flame_session_set_position_targets`] (frame-major, in `convention` and its unit, covering
/// the motion's first `frames` frames; later frames are free); `mask` = one byte per value
/// (nonzero = followed) or NULL (NaN = free). The positions are encoded once here; every later
/// network pass takes them. Allowed between steps. A model without a ControlNet, a wrong joint
/// count, more frames than the session's or nothing to follow is `FLAME_INVALID_ARGUMENT`;
/// on error the earlier control stays.
///
/// # Safety
/// `session` is a live session; `positions` points to `positions_len` floats; `mask` is NULL
/// or points to `mask_len` bytes.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_control(
    session: *mut FlameSession,
    positions: *const f32,
    positions_len: usize,
    mask: *const u8,
    mask_len: usize,
    convention: i32,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let values = slice_arg(positions, positions_len, "positions")?;
        let mask = optional_mask(mask, mask_len)?;
        let convention = poses::convention(convention)?;
        s.with(|st| Ok(st.session.set_control_values(values, mask, convention)?))
    })
}

/// Removes the trajectory control: the next steps follow the prompt alone.
///
/// # Safety
/// `session` is a live session.
#[no_mangle]
pub unsafe extern "C" fn flame_session_clear_control(session: *mut FlameSession) -> FlameStatus {
    guard(|| {
        session_ref(session)?.with(|st| {
            st.session.clear_control();
            Ok(())
        })
    })
}

/// What [`flame_session_tune_latent`] did.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default)]
pub struct FlameTuningReport {
    /// Set by the caller to `sizeof(FlameTuningReport)`.
    pub struct_size: u32,
    /// Iterations run.
    pub iterations: u32,
    /// The hint loss Σ m (J − H)² / Σ m (m²) at the first latent.
    pub hint_loss_before: f64,
    /// The hint loss at the tuned latent.
    pub hint_loss_after: f64,
    /// The mean distance (m) of a hinted joint from its target at the first latent.
    pub control_error_before: f64,
    /// The same at the tuned latent.
    pub control_error_after: f64,
}

/// Consistency latent tuning (MotionLCM's `--optimize`): before the first step, `iterations`
/// Adam iterations (the release runs 400) move the initial latent so that the 1-step motion
/// made from it follows the control ([`flame_session_set_control`]) more closely; the tuned
/// latent becomes the session's initial noise (kept by a reset, as one set with
/// [`flame_session_set_noise`]). Needs a prompt, a control and a 1-step MotionLCM session
/// (`FLAME_STATUS_WRONG_STATE` without a prompt or a control or after the first step,
/// `FLAME_STATUS_INVALID_ARGUMENT` for another sampler, another step count or 0 iterations).
/// [`flame_session_cancel`] is seen before every iteration (`FLAME_STATUS_CANCELLED`: the
/// session keeps the latent it would have sampled from). `report` is NULL or a writable
/// `FlameTuningReport` whose `struct_size` is set.
///
/// # Safety
/// `session` is a live session; `report` is NULL or points to a writable `FlameTuningReport`.
#[no_mangle]
pub unsafe extern "C" fn flame_session_tune_latent(
    session: *mut FlameSession,
    iterations: u32,
    report: *mut FlameTuningReport,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        if !report.is_null() {
            check_size(
                (*report).struct_size,
                std::mem::size_of::<FlameTuningReport>(),
                "report",
            )?;
        }
        let params = crate::tuning::TuningParams::new(iterations as usize);
        let r = s.with(|st| Ok(st.session.tune_latent(&params)?))?;
        if !report.is_null() {
            report.write(FlameTuningReport {
                struct_size: std::mem::size_of::<FlameTuningReport>() as u32,
                iterations: r.iterations as u32,
                hint_loss_before: r.hint_loss[0],
                hint_loss_after: r.hint_loss[1],
                control_error_before: r.control_error[0],
                control_error_after: r.control_error[1],
            });
        }
        Ok(())
    })
}

/// The position targets' loss (the sum of distances, in metres, over constrained joints and
/// frames) at the latest step's clean-motion estimate, before that step's guidance, in `*loss`.
/// FLAME_STATUS_WRONG_STATE before a guided step.
///
/// # Safety
/// `session` is a live session; `loss` points to writable memory for a double.
#[no_mangle]
pub unsafe extern "C" fn flame_session_target_loss(
    session: *const FlameSession,
    loss: *mut f64,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let l = s.with(|st| {
            st.session.target_loss().ok_or_else(|| {
                Error::WrongState("no step has been guided by position targets yet".into()).into()
            })
        })?;
        write_out(loss, l, "loss")
    })
}

/// Starts a generation on `model`. `params` may be NULL for the defaults. The session keeps
/// the model alive; free it with [`flame_session_free`].
///
/// # Safety
/// `model` is a live model; `params` is NULL or a valid `FlameSessionParams`; `session` points
/// to writable memory for a pointer.
#[no_mangle]
pub unsafe extern "C" fn flame_session_new(
    model: *const FlameModel,
    params: *const FlameSessionParams,
    session: *mut *mut FlameSession,
) -> FlameStatus {
    guard(|| {
        let m = model_ref(model)?;
        if session.is_null() {
            return Err(invalid_arg!("`session` is NULL").into());
        }
        let p = if params.is_null() {
            SessionParams::default()
        } else {
            session_params_in(params)?
        };
        let s = Session::new(Arc::clone(m.model()), &p)?;
        write_out(
            session,
            Box::into_raw(Box::new(FlameSession::new(s))),
            "session",
        )
    })
}

/// Frees a session and joins its worker threads; NULL is ignored.
///
/// # Safety
/// `session` is NULL or a live session not in use by another thread.
#[no_mangle]
pub unsafe extern "C" fn flame_session_free(session: *mut FlameSession) {
    catch_quietly(|| {
        if !session.is_null() {
            drop(Box::from_raw(session));
        }
    });
}

/// Starts the generation over: same prompt, settings, reference and mask; the seeded noise
/// generator restarts, so the same output follows.
///
/// # Safety
/// `session` is a live session.
#[no_mangle]
pub unsafe extern "C" fn flame_session_reset(session: *mut FlameSession) -> FlameStatus {
    guard(|| {
        session_ref(session)?.with(|s| {
            s.session.reset();
            Ok(())
        })
    })
}

/// Sets the prompt (UTF-8, NUL-terminated). It is encoded once here, not at every step; it may
/// be changed between steps.
///
/// # Safety
/// `session` is a live session; `prompt` a NUL-terminated string.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_prompt(
    session: *mut FlameSession,
    prompt: *const c_char,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let text = str_arg(prompt, "prompt")?;
        s.with(|st| st.set_prompt(text))
    })
}

/// Sets the prompt `source` was given, as encoded there, without running the text encoder
/// again: a game that makes many motions from one prompt encodes it once (MotionLCM's
/// T5-large takes 75–85 ms a prompt on 2 cores; a whole 1-step motion 12–28 ms). `source` must
/// be a session of the same `FlameModel` with a prompt (WRONG_STATE without one,
/// INVALID_ARGUMENT for another model); `session` may be `source` itself. The prompt report
/// (`flame_session_prompt_info`) and the export metadata follow the prompt.
///
/// # Safety
/// `session` and `source` are live sessions.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_prompt_from(
    session: *mut FlameSession,
    source: *const FlameSession,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let src = source
            .as_ref()
            .ok_or_else(|| Fail::from(invalid_arg!("`source` is NULL")))?;
        // The source is locked, read and released before the session is locked (the same
        // session twice, or two threads copying in opposite directions, never wait on each
        // other).
        let taken = src.with(|st| Ok(st.prompt_snapshot()))?;
        s.with(|st| st.take_prompt(taken))
    })
}

/// Sets prompts per time stage (and body part): `count` stages in order, their frames adding
/// up to the session's. FineMoGen composes them (the sample is then laid out
/// `[count, longest stage, motion_dim]`: see [`flame_session_sample_shape`]); other families
/// take one stage without part texts as a plain prompt and refuse more (INVALID_ARGUMENT). A
/// stage's frame counts can change only before the first step (WRONG_STATE after).
///
/// # Safety
/// `session` is a live session; `stages` points to `count` `FlameStage`s whose non-NULL
/// strings are NUL-terminated.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_prompt_stages(
    session: *mut FlameSession,
    stages: *const FlameStage,
    count: usize,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        if count == 0 || count > 1024 {
            return Err(invalid_arg!("{count} stages: give 1 to 1024").into());
        }
        let first = struct_arg(stages, |st| st.struct_size, "stages[0]")?;
        // A newer header's larger struct: step by its size, read the fields this library knows.
        let stride = first.struct_size as usize;
        if !stride.is_multiple_of(std::mem::align_of::<FlameStage>()) || stride > 1 << 16 {
            return Err(invalid_arg!(
                "stages[0].struct_size {stride} is not the size of a FlameStage"
            )
            .into());
        }
        let mut out = Vec::with_capacity(count);
        for i in 0..count {
            let st = &*((stages as *const u8).add(i * stride) as *const FlameStage);
            if st.struct_size != first.struct_size {
                return Err(invalid_arg!(
                    "stages[{i}].struct_size is {}, stages[0]'s {}",
                    st.struct_size,
                    first.struct_size
                )
                .into());
            }
            out.push(stage_arg(st, &format!("stages[{i}]"))?);
        }
        s.with(|st| st.set_prompt_stages(&out))
    })
}

/// The stage a `FlameStage` describes (`what` names it in errors); empty part texts follow the
/// whole-body text.
///
/// # Safety
/// The struct's non-NULL strings are NUL-terminated.
pub(crate) unsafe fn stage_arg(st: &FlameStage, what: &str) -> Result<crate::stages::Stage, Fail> {
    let text = str_arg(st.text, &format!("{what}.text"))?;
    let part = |p: *const c_char, name: &str| -> Result<Option<String>, Fail> {
        if p.is_null() {
            return Ok(None);
        }
        let t = str_arg(p, &format!("{what}.{name}"))?;
        Ok((!t.trim().is_empty()).then(|| t.to_string()))
    };
    Ok(crate::stages::Stage {
        text: text.to_string(),
        frames: st.frames as usize,
        parts: [
            part(st.head, "head")?,
            part(st.stem, "stem")?,
            part(st.left_arm, "left_arm")?,
            part(st.right_arm, "right_arm")?,
            part(st.left_leg, "left_leg")?,
            part(st.right_leg, "right_leg")?,
            part(st.pelvis, "pelvis")?,
        ],
    })
}

/// Reports how the last prompt fitted the text encoder's window (tokens kept, whether it was
/// cut and the text that was dropped). `WRONG_STATE` before a prompt is set.
///
/// # Safety
/// `session` is a live session; `info` points to a writable `FlamePromptInfo` whose
/// `struct_size` is set.
#[no_mangle]
pub unsafe extern "C" fn flame_session_prompt_info(
    session: *const FlameSession,
    info: *mut FlamePromptInfo,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        if info.is_null() {
            return Err(invalid_arg!("`info` is NULL").into());
        }
        check_size(
            (*info).struct_size,
            std::mem::size_of::<FlamePromptInfo>(),
            "info",
        )?;
        let out = s.with(|st| st.prompt_info())?;
        info.write(out);
        Ok(())
    })
}

/// Sets the initial noise x_T explicitly: `len` = rows × dim values, frame-major, as
/// [`flame_session_sample_shape`] says (frames × feature_dim, or a latent model's latent).
/// Only before the first step (or after a reset).
///
/// # Safety
/// `session` is a live session; `noise` points to `len` floats.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_noise(
    session: *mut FlameSession,
    noise: *const f32,
    len: usize,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let x = slice_arg(noise, len, "noise")?;
        s.with(|st| Ok(st.session.set_initial_noise(x)?))
    })
}

/// Sets the reference motion for editing: `frames` × `dim` model-space features, frame-major;
/// `dim` is the model's feature dim and 1 <= `frames` <= the session's frames (the frames past a
/// shorter reference cannot be kept). May change between steps.
///
/// # Safety
/// `session` is a live session; `features` points to `frames * dim` floats.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_reference(
    session: *mut FlameSession,
    features: *const f32,
    frames: u32,
    dim: u32,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let values = reference_arg(features, frames, dim)?;
        s.with(|st| {
            check_reference_shape(st, frames, dim)?;
            Ok(st.session.set_reference(values)?)
        })
    })
}

/// A reference motion's `frames × dim` features.
unsafe fn reference_arg<'a>(
    features: *const f32,
    frames: u32,
    dim: u32,
) -> Result<&'a [f32], Fail> {
    let n = (frames as usize)
        .checked_mul(dim as usize)
        .ok_or_else(|| invalid_arg!("frames × dim overflows"))?;
    slice_arg(features, n, "features")
}

/// A reference holds 1..=the session's frames of the model's features.
fn check_reference_shape(st: &handles::SessionState, frames: u32, dim: u32) -> Result<(), Fail> {
    let (f, d) = (st.session.frames(), st.session.model().motion_dim());
    if frames == 0 || frames as usize > f || dim as usize != d {
        return Err(invalid_arg!(
            "reference shape {frames} × {dim}: want 1 to {f} frames × {d} features"
        )
        .into());
    }
    Ok(())
}

/// Sets the keep-mask: `frames` × `dim` bytes, 1 = keep the reference value, 0 = generate it.
/// May change between steps; it takes effect at the next step.
///
/// # Safety
/// `session` is a live session; `mask` points to `frames * dim` bytes.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_mask(
    session: *mut FlameSession,
    mask: *const u8,
    frames: u32,
    dim: u32,
) -> FlameStatus {
    guard(|| with_frames_buffer(session, mask, frames, dim, "mask", |s, v| s.set_mask(v)))
}

/// Marks every feature of frames `start..end` (end exclusive) as kept, adding to the current
/// mask (an absent mask starts all-generate).
///
/// # Safety
/// `session` is a live session.
#[no_mangle]
pub unsafe extern "C" fn flame_session_keep_frames(
    session: *mut FlameSession,
    start: u32,
    end: u32,
) -> FlameStatus {
    guard(|| session_ref(session)?.with(|st| st.keep_frames(start as usize, end as usize)))
}

/// Marks the channels of the given joints as kept in every frame, adding to the current mask.
/// A joint index is a skeleton joint of the model's motion format, or
/// [`FLAME_ROOT_TRANSLATION`] for the root translation (the root path).
///
/// # Safety
/// `session` is a live session; `joints` points to `count` integers.
#[no_mangle]
pub unsafe extern "C" fn flame_session_keep_joints(
    session: *mut FlameSession,
    joints: *const i32,
    count: usize,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let j = slice_arg(joints, count, "joints")?;
        s.with(|st| st.keep_joints(j))
    })
}

/// Marks a body part's channels on frames `start..end` (end exclusive) as kept, adding to the
/// current mask. `part` is a [`FlameBodyPart`] value.
///
/// # Safety
/// `session` is a live session.
#[no_mangle]
pub unsafe extern "C" fn flame_session_keep_part(
    session: *mut FlameSession,
    part: i32,
    start: u32,
    end: u32,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let part = usize::try_from(part)
            .ok()
            .and_then(|p| crate::motion::BodyPart::ALL.get(p).copied())
            .ok_or_else(|| invalid_arg!("unknown body part {part} (a FlameBodyPart, 0 to 4)"))?;
        s.with(|st| st.keep_part(part, start as usize, end as usize))
    })
}

/// Replaces the mask with a standard task's: `task` is a [`FlameEditTask`] value.
///
/// # Safety
/// `session` is a live session.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_task_mask(
    session: *mut FlameSession,
    task: i32,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let task = usize::try_from(task)
            .ok()
            .and_then(|t| crate::motion::Task::ALL.get(t).copied())
            .ok_or_else(|| invalid_arg!("unknown editing task {task} (a FlameEditTask, 0 to 3)"))?;
        s.with(|st| {
            let format = st.session.model().motion_format();
            let mask = crate::motion::Mask::for_task(format, st.session.frames(), task)?;
            Ok(st.session.set_mask_from(&mask)?)
        })
    })
}

/// Sets a smpl24_6d reference from poses instead of features: `root` = `frames` × 3 root
/// (pelvis) positions, `rotations` = `frames` × 24 local joint rotations in `layout`
/// (FLAME_LAYOUT_LOCAL_QUAT_XYZW/WXYZ, _LOCAL_MATRIX or _LOCAL_6D), both in `convention` (a
/// [`FlameConvention`] value) and its unit: the inverse of [`flame_session_read`]. Quaternions
/// are normalised; matrices must be rotations. 1 <= `frames` <= the session's frames.
///
/// # Safety
/// `session` is a live session; `root` points to `root_len` floats and `rotations` to
/// `rotations_len` floats.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn flame_session_set_reference_poses(
    session: *mut FlameSession,
    root: *const f32,
    root_len: usize,
    rotations: *const f32,
    rotations_len: usize,
    frames: u32,
    layout: i32,
    convention: i32,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let root = slice_arg(root, root_len, "root")?;
        let rotations = slice_arg(rotations, rotations_len, "rotations")?;
        let layout = poses::rotation_layout(layout)?;
        let convention = poses::convention(convention)?;
        s.with(|st| {
            let f = st.session.frames();
            if frames == 0 || frames as usize > f {
                return Err(invalid_arg!("reference frames must be between 1 and {f} (the session's frames), got {frames}").into());
            }
            Ok(st.session.set_reference_poses(
                root,
                rotations,
                layout,
                convention,
                frames as usize,
            )?)
        })
    })
}

/// Removes the reference and the mask.
///
/// # Safety
/// `session` is a live session.
#[no_mangle]
pub unsafe extern "C" fn flame_session_clear_edit(session: *mut FlameSession) -> FlameStatus {
    guard(|| {
        session_ref(session)?.with(|st| {
            st.session.clear_edit();
            Ok(())
        })
    })
}

/// Sets (or, with NULL, removes) a callback run on the stepping thread after every step.
///
/// # Safety
/// `session` is a live session; `callback` and `user_data` stay valid while set.
#[no_mangle]
pub unsafe extern "C" fn flame_session_set_progress_callback(
    session: *mut FlameSession,
    callback: FlameProgressCallback,
    user_data: *mut c_void,
) -> FlameStatus {
    guard(|| {
        session_ref(session)?.with(|st| {
            st.set_progress(callback, user_data);
            Ok(())
        })
    })
}

/// Advances one sampler step. `*steps_left` (may be NULL) receives the steps still to run.
/// Errors: no prompt yet, the generation finished (`WRONG_STATE`), or cancelled (`CANCELLED`;
/// the step is abandoned and may be retried).
///
/// # Safety
/// `session` is a live session used by no other thread; `steps_left` is NULL or writable.
#[no_mangle]
pub unsafe extern "C" fn flame_session_step(
    session: *mut FlameSession,
    steps_left: *mut u32,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let (left, progress) = s.with(|st| st.step())?;
        if !steps_left.is_null() {
            steps_left.write(left as u32);
        }
        // Outside the session's lock, so the callback may read the session.
        if let Some((p, done, total)) = progress {
            p.report(done, total);
        }
        Ok(())
    })
}

/// Asks the session to abandon its current step (or its next one). Safe to call from any
/// thread while another thread is inside [`flame_session_step`].
///
/// # Safety
/// `session` is a live session.
#[no_mangle]
pub unsafe extern "C" fn flame_session_cancel(session: *const FlameSession) -> FlameStatus {
    guard(|| {
        session_ref(session)?.cancel.store(true, Ordering::SeqCst);
        Ok(())
    })
}

/// Reports steps done and the total (either pointer may be NULL).
///
/// # Safety
/// `session` is a live session.
#[no_mangle]
pub unsafe extern "C" fn flame_session_progress(
    session: *const FlameSession,
    steps_done: *mut u32,
    steps_total: *mut u32,
) -> FlameStatus {
    guard(|| {
        let (done, total) = session_ref(session)?.with(|st| {
            let n = st.session.num_steps();
            Ok((n - st.session.steps_left(), n))
        })?;
        if !steps_done.is_null() {
            steps_done.write(done as u32);
        }
        if !steps_total.is_null() {
            steps_total.write(total as u32);
        }
        Ok(())
    })
}

/// Reads the current sample or clean-motion estimate (`which`, a [`FlameWhich`]) in a
/// [`FlameLayout`], converted to a [`FlameConvention`], with post-processing `flags`
/// ([`FLAME_READ_SMOOTH`], [`FLAME_READ_RAW_SIGNS`]).
///
/// The values are `frames` frames of the layout's per-frame size. `frames` is the session's
/// frame count, except for latent models (`FlameModelInfo.latent` nonzero): their decoder
/// decides the valid length, which [`flame_session_read_frames`] reports (the same for every
/// layout until the next step).
///
/// With `out` NULL, `*out_len` receives the required number of floats and nothing else is
/// done. Otherwise `len` must be at least that (`BUFFER_TOO_SMALL` otherwise, with `*out_len`
/// set to the required length) and `*out_len` receives the number written. Reading the sample
/// before the first step, or the estimate before a step has run, is `WRONG_STATE`.
///
/// # Safety
/// `session` is a live session; `out` is NULL or points to `len` writable floats; `out_len`
/// points to a writable `size_t`.
#[no_mangle]
#[allow(clippy::too_many_arguments)]
pub unsafe extern "C" fn flame_session_read(
    session: *const FlameSession,
    which: i32,
    layout: i32,
    convention: i32,
    flags: u32,
    out: *mut f32,
    len: usize,
    out_len: *mut usize,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        if out_len.is_null() {
            return Err(invalid_arg!("`out_len` is NULL").into());
        }
        s.with(|st| {
            let values = st.read(which, layout, convention, flags, &Default::default())?;
            copy_out(&values, out, len, out_len, "floats")
        })
    })
}

/// Fills `*params` with the glTF export defaults: GLB, no read flags, the model's frame rate,
/// the animation named after the prompt.
///
/// # Safety
/// `params` points to writable memory for a `FlameGltfParams`.
#[no_mangle]
pub unsafe extern "C" fn flame_gltf_params_default(params: *mut FlameGltfParams) -> FlameStatus {
    guard(|| {
        let p = FlameGltfParams {
            struct_size: std::mem::size_of::<FlameGltfParams>() as u32,
            container: FlameGltfContainer::Glb as i32,
            flags: 0,
            fps: 0.0,
            name: std::ptr::null(),
            cleanup: std::ptr::null(),
        };
        write_out(params, p, "params")
    })
}

/// Reads the caller's glTF params (NULL = the defaults): only the `struct_size` bytes it
/// declares (at least version 1's), `cleanup` NULL when version 1 has none.
unsafe fn gltf_params(params: *const FlameGltfParams) -> Result<FlameGltfParams, Fail> {
    let mut p = std::mem::zeroed::<FlameGltfParams>();
    flame_gltf_params_default(&mut p);
    if params.is_null() {
        return Ok(p);
    }
    // SAFETY: the caller's struct is readable for at least its first field.
    let declared = std::ptr::read_unaligned(params as *const u32);
    check_size(declared, GLTF_PARAMS_V1, "params")?;
    // Whole fields only: the end of the newest version the declared size covers.
    let n = if declared as usize >= std::mem::size_of::<FlameGltfParams>() {
        std::mem::size_of::<FlameGltfParams>()
    } else {
        GLTF_PARAMS_V1
    };
    // SAFETY: the caller's struct is readable for the `declared` ≥ n bytes it says it has;
    // `p` is a plain-data struct of at least n bytes.
    std::ptr::copy_nonoverlapping(params as *const u8, &mut p as *mut _ as *mut u8, n);
    Ok(p)
}

/// Writes the current sample or clean-motion estimate (`which`, a [`FlameWhich`]) as a glTF 2.0
/// file: the skeleton as nodes named after its joints, a skinned box figure, one animation
/// (root translation and joint rotations, LINEAR at the model's fps, glTF's convention: Y up,
/// right-handed, metres), and the prompt, architecture, seed and libflame version in
/// `asset.extras` (docs/exports.md). `params` NULL means [`flame_gltf_params_default`].
///
/// With `out` NULL, `*out_len` receives the file's size in bytes and nothing else is done.
/// Otherwise `len` must be at least that (`BUFFER_TOO_SMALL` otherwise, with `*out_len` set to
/// the size) and `*out_len` receives the bytes written. Each call builds the file afresh (a
/// few milliseconds); the size is the same for the same motion and parameters. A motion whose
/// poses are not finite in `f32` is refused (`INVALID_ARGUMENT`) before anything is written.
///
/// # Safety
/// `session` is a live session; `params` is NULL or points to a valid `FlameGltfParams` whose
/// `name` is NULL or a NUL-terminated UTF-8 string; `out` is NULL or points to `len` writable
/// bytes; `out_len` points to a writable `size_t`.
#[no_mangle]
pub unsafe extern "C" fn flame_session_write_gltf(
    session: *const FlameSession,
    which: i32,
    params: *const FlameGltfParams,
    out: *mut u8,
    len: usize,
    out_len: *mut usize,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        if out_len.is_null() {
            return Err(invalid_arg!("`out_len` is NULL").into());
        }
        let p = &gltf_params(params)?;
        let container = match p.container {
            c if c == FlameGltfContainer::Glb as i32 => crate::motion::gltf::Container::Glb,
            c if c == FlameGltfContainer::Gltf as i32 => crate::motion::gltf::Container::Gltf,
            c => return Err(invalid_arg!("unknown glTF container {c} (0 GLB, 1 glTF)").into()),
        };
        let name = if p.name.is_null() {
            None
        } else {
            Some(str_arg(p.name, "params.name")?)
        };
        let finish = finish_arg(p.cleanup)?;
        s.with(|st| {
            let bytes = st.gltf(which, container, p.flags, p.fps, name, &finish)?;
            copy_out(&bytes, out, len, out_len, "bytes")
        })
    })
}

/// The shape of the sampled space: `*out_rows` rows of `*out_dim` values (the session's frames
/// × feature_dim, or for a latent model the latent's rows × channels). Either pointer may be
/// NULL.
///
/// # Safety
/// `session` is a live session; non-NULL pointers point to writable `uint32_t`s.
#[no_mangle]
pub unsafe extern "C" fn flame_session_sample_shape(
    session: *const FlameSession,
    out_rows: *mut u32,
    out_dim: *mut u32,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        let (rows, dim) =
            s.with(|st| Ok((st.session.sample_rows(), st.session.model().sample_dim())))?;
        if !out_rows.is_null() {
            out_rows.write(rows as u32);
        }
        if !out_dim.is_null() {
            out_dim.write(dim as u32);
        }
        Ok(())
    })
}

/// How many frames [`flame_session_read`] of `which` returns now: the session's frames, or a
/// latent model's valid length (decoded on first read after each step).
///
/// # Safety
/// `session` is a live session; `out_frames` points to a writable `uint32_t`.
#[no_mangle]
pub unsafe extern "C" fn flame_session_read_frames(
    session: *const FlameSession,
    which: i32,
    out_frames: *mut u32,
) -> FlameStatus {
    guard(|| {
        let s = session_ref(session)?;
        if out_frames.is_null() {
            return Err(invalid_arg!("`out_frames` is NULL").into());
        }
        s.with(|st| {
            let frames = st.read_frames(which)?;
            out_frames.write(u32::try_from(frames).unwrap_or(u32::MAX));
            Ok(())
        })
    })
}

impl From<Error> for Fail {
    fn from(e: Error) -> Fail {
        Fail::Core(e)
    }
}
