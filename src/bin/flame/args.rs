//! The command line's grammar (clap, derive API). Named choices (sampler, convention, ...) are
//! parsed by the library's `FromStr`, so a bad value is a usage error (exit 2) with the
//! library's own message; everything checked later (files, models) exits 1.

use std::fmt::Display;
use std::path::PathBuf;
use std::str::FromStr;

use clap::{Args, Parser, Subcommand, ValueEnum};
use flame::models::WeightType;
use flame::motion::amass::AmassLayout;
use flame::motion::{Convention, Feet, QuatOrder, RootMotion, Task};
use flame::robot::export::RobotFormat;
use flame::session::{EditMethod, Sampler};
use flame::targets::TargetSchedule;

const ABOUT: &str =
    "Text to human motion on the CPU with libflame models: FLAME, MDM, Motion Flow \
                     Matching, MoLA, MLD, FineMoGen and OMG-style models.";

const AFTER_HELP: &str = "\
Without --model (and for `info` without MODEL) the model is $FLAME_MODEL, else the demo model
models/demo/flame_demo.safetensors, assembled on first use (see `bash tools/try.sh`).

Exit status: 0 on success, 2 when the command line is not understood (unknown option, missing
or unparsable value), 1 for everything else (files, model, values the model rejects).";

const GENERATE_LONG: &str = "\
Generate a motion from a sentence.

The writer follows the extension of --out (upper or lower case): .npy = raw features (float32,
frames x feature_dim, untouched by the pose options), .bvh = BVH (Euler ZXY, degrees), .json =
root translation + local quaternions (--quat order, default wxyz as FLAME's official output)
with the skeleton, .glb / .gltf = glTF 2.0 (binary / JSON): the skeleton, a skinned box figure
and the animation, in glTF's convention (Y up, metres), the prompt, model and seed in its
metadata; .npz = AMASS-style SMPL parameters (float64 axis-angles, AMASS's Z-up world) for
robot-learning pipelines: SMPL-H keys by default (`poses` [N, 156], `trans`, `betas`, `gender`,
`mocap_framerate`, `dmpls`; PHC, human2humanoid), SMPL-X keys with --amass smplx
(`root_orient`, `pose_body`, `trans`, `mocap_frame_rate`, ...; GMR), see docs/amass.md; --fps 30
gives the rate trackers expect. With --robot FILE.urdf the poses are retargeted onto the robot
and --out is its joint trajectory: .csv BeyondMimic's rows, .npz GMR's fields, .npy MuJoCo qpos
(--robot-format, --retarget, --csv-header; docs/robots.md). --positions also writes world joint positions (float32, frames x joints x 3);
--preview FILE.png a contact sheet (stick figures side by side and the root path seen from
above), FILE.gif an animation of the same figure beside its path (--preview-fps, default the
model's).

Poses are in --convention: by default gltf (Y up) for a BVH, which Blender's importer and other
BVH readers stand upright, always gltf for .glb/.gltf, and native (the model's own frame) for
JSON and .npy outputs;
--positions follows the same convention. --smooth is the sigma in frames of the temporal
Gaussian smoothing of the features (default 1 for smpl24_6d as FLAME's official output, 0
otherwise; 0 = off).

Pose outputs are game-ready by default: the feet are locked during their contacts (two-bone
IK; bone lengths and everything above the knees unchanged) and the lowest contact is put at
height 0; --feet off gives the raw poses. --fps resamples, --root-motion moves the travel,
--loop makes the end flow into the start (docs/game-ready.md).

Unset options take the model file's defaults (see `flame info`). Every output folder is checked
before the model is loaded.";

const EDIT_LONG: &str = "\
Keep parts of a reference motion and generate the rest from a sentence.

References are .npy model-space features (what `generate --out x.npy` writes) or a BVH written
by libflame (smpl24_6d models; its convention is recognised from the skeleton's offsets and, for
native vs gltf whose offsets agree, from which axis is up; --reference-convention says it
outright). Kept values: --task inbetween (first and last quarter), predict (the first quarter,
or all of a reference shorter than --frames), upper-body (keeps the root path, pelvis and legs),
path (keeps the root path); --keep-frames adds frame ranges (A:B half-open, `:B`, `A:`),
--keep-joints adds joints by index or name (`root` = the root path) on every frame. --frames
defaults to the reference's length. Flow models take 30 steps by default when editing.
--paste off gives the official behaviour (the kept parts are not copied exactly into the
result). The output options are generate's.";

const STREAM_LONG: &str = "\
Generate one continuous motion from a timeline of sentences.

Each --segment TEXT@FRAMES lasts FRAMES frames, one after the other (\"a person walks@120\"
then \"waves@80\" = 200 frames). The motion is generated in chunks of at most --chunk frames
(default the model's default frame count); each chunk keeps the last --overlap frames of the
one before and generates the rest from its segment's sentence (the model's editing algorithm,
the kept frames pasted exactly and the seam blended), in a frame where the root path continues
where the previous chunk left off. A chunk never spans two segments. The result is the same
bytes for every --threads. Chunk k draws its noise from --seed mixed with k. Models that
sample the motion itself (FLAME, MDM, Motion Flow Matching, FineMoGen, OMG-style) keep the
overlap exactly; MoLA, which samples a latent, steers each chunk towards it with position
guidance; MLD is refused (libflame has no gradient of its decoder). The output options are
generate's; the whole timeline is written once.";

const RETARGET_LONG: &str = "\
Carry a motion made earlier onto the user's character. The motion is a BVH or glTF libflame
wrote (`generate --out x.bvh` or `x.glb` of an smpl24_6d model) or .npy features with the model
that made them;
the pose options (feet, fps, root motion, loop wrap aside) apply as in generate, then the poses
are retargeted onto --rig: the rest-relative transform of the VRM Animation specification, the
rig's rest pose first turned to the source's (an A-pose rig's arms are not left 45 degrees off),
the hips translation scaled by the legs' ratio, and the feet put back on the source's
contacts with two-bone IK. --out .glb/.gltf/.vrm hands the rig's own file back with the
animation added (an animation of the same name written before is replaced), .bvh writes the
rig's hierarchy and names, .vrma a VRM Animation. Without --rig, --out x.npz writes the poses as
AMASS SMPL parameters (--amass smplh or smplx, as in generate). With --robot FILE.urdf instead
of --rig, the poses are retargeted onto that robot and --out is its joint trajectory (.csv,
.npz or .npy, as in generate).";

#[derive(Parser)]
#[command(
    name = "flame",
    version,
    about = ABOUT,
    after_help = AFTER_HELP,
    propagate_version = true,
    subcommand_required = true,
    arg_required_else_help = true
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand)]
pub enum Command {
    /// Generate a motion from a sentence
    #[command(long_about = GENERATE_LONG, after_help = AFTER_HELP)]
    Generate(GenerateArgs),
    /// Keep parts of a reference motion and generate the rest from a sentence
    #[command(long_about = EDIT_LONG, after_help = AFTER_HELP)]
    Edit(EditArgs),
    /// Generate one continuous motion from a timeline of sentences, chunk after chunk
    #[command(long_about = STREAM_LONG, after_help = AFTER_HELP)]
    Stream(StreamArgs),
    /// Carry a motion made earlier onto the user's character (--rig) or a robot (--robot)
    #[command(long_about = RETARGET_LONG, after_help = AFTER_HELP)]
    Retarget(RetargetArgs),
    /// Describe a model file: architecture, text encoder, motion format, defaults
    #[command(after_help = AFTER_HELP)]
    Info(InfoArgs),
    /// Complete a denoiser-only file (the demo model's) with a text encoder's weights
    #[command(
        long_about = "Complete a denoiser-only file (the demo model's) with the weights of its \
                      text encoder (a Hugging Face model.safetensors), checked against the \
                      configuration. The result is the same bytes on every run."
    )]
    Assemble(AssembleArgs),
    /// Write an int8 model file calibrated on the model's own runs (GPTQ)
    #[command(long_about = QUANTIZE_LONG)]
    Quantize(QuantizeArgs),
    /// Run many generations with one model load: a JSONL file of jobs or a list of prompts
    #[command(long_about = BATCH_LONG, after_help = AFTER_HELP)]
    Batch(BatchArgs),
}

const BATCH_LONG: &str = "\
Run many generations with one model load.

--jobs FILE.jsonl holds one job a line: a JSON object whose keys are generate's options
(prompt or stages, frames, seed, steps, sampler, respacing, eta, guidance, out, positions,
amass, convention, smooth, quat, feet, ground, fps, root_motion, remove_yaw, contact_height,
contact_speed; id names the job in the manifest). Unknown keys are refused. --prompts FILE
takes one prompt a line instead, each run with --seeds seeds and written to --out-pattern
({line} = the prompt's line, {seed}, {n} = the job's number). --defaults gives keys every job
takes unless it sets them. Paths are relative to the current folder.

Jobs run at once on sessions over the one model: by default one session per core, the cores
left over shared among the sessions' threads (--workers, --threads). Every output is the same
bytes as `flame generate` gives for that job, written under a temporary name and renamed, so a
file never exists half-written. The manifest (JSONL: job, line, status, outputs, seconds,
prompt, error) gets a line as each job finishes; --resume skips the jobs it records as done
whose outputs exist. A job that fails is reported and the others run; Ctrl-C stops the
running jobs without writing their files (a second Ctrl-C ends at once). The exit status is 1
when any job failed or was not run.";

const QUANTIZE_LONG: &str = "Write an int8 model file calibrated on the model's own runs. The \
f32 model samples the calibration prompts while each linear layer records its inputs; each \
weight is then rounded to int8 (one scale per output row) by GPTQ, which carries every rounding \
error onto the inputs not yet rounded so that the layer's outputs, not its weights, stay close. \
The projections from and to the sampled features stay f32. Load the result with --weights int8 \
(the default for such a file): its integers are packed as they are, so every machine on the \
same kernel path gives the same bits. Loaded as f32, f16 or bf16 they are multiplied back out, \
which runs anywhere.";

/// The library's `FromStr`, its message without the error kind's prefix.
/// How `flame edit` imposes the reference: a library editing method, or position guidance
/// toward the reference's joint positions (MoLA's MPGD).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum EditChoice {
    Method(EditMethod),
    Mpgd,
}

fn edit_choice(s: &str) -> Result<EditChoice, String> {
    if s == "mpgd" {
        return Ok(EditChoice::Mpgd);
    }
    lib::<EditMethod>(s)
        .map(EditChoice::Method)
        .map_err(|e| e.replace("rewrite-trajectory)", "rewrite-trajectory or mpgd)"))
}

fn lib<T>(s: &str) -> Result<T, String>
where
    T: FromStr,
    T::Err: Display,
{
    s.parse::<T>().map_err(|e| {
        let m = e.to_string();
        m.strip_prefix("invalid argument: ")
            .map(str::to_string)
            .unwrap_or(m)
    })
}

fn fps(s: &str) -> Result<f64, String> {
    let range = flame::motion::finish::FPS_RANGE;
    match s.parse::<f64>() {
        Ok(v) if range.contains(&v) => Ok(v),
        _ => Err(format!(
            "--fps must be a frame rate from {} to {}, got `{s}`",
            range.start(),
            range.end()
        )),
    }
}

fn sigma(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!(
            "the sigma must be a number of frames, 0 or more, got `{s}`"
        )),
    }
}

#[derive(Args)]
pub struct ModelArgs {
    /// Model file [default: $FLAME_MODEL, else the demo model]
    #[arg(long, value_name = "M")]
    pub model: Option<PathBuf>,
    /// What the linear layers are held and multiplied in (f16/bf16 halve their memory;
    /// bf16-compute multiplies in bf16, needs AVX512_BF16; int8 multiplies 8-bit integers,
    /// needs AVX512_VNNI or AVX2) [f32|f16|bf16|bf16-compute|int8; default f32]
    #[arg(long, value_name = "W", value_parser = lib::<WeightType>)]
    pub weights: Option<WeightType>,
}

/// How every denoising step is taken (generate, edit and each chunk of a stream).
#[derive(Args)]
pub struct DenoiseArgs {
    /// Sampling steps, respaced from the trained ones [default: the model's]
    #[arg(long, value_name = "S")]
    pub steps: Option<usize>,
    /// Which training steps to sample, as a guided-diffusion respacing string: "ddimN" (every
    /// k-th step), "N" (N evenly spread) or section counts "15,15,8,6,6"; sets the step count.
    /// Only for FLAME/MDM-style models (diffusion.spacing `respace`)
    #[arg(long, value_name = "SPEC")]
    pub respacing: Option<String>,
    /// Sampler [ddpm|ddim (diffusion), euler|heun|midpoint (flow matching) or lcm (latent consistency); default: the model's]
    #[arg(long, value_name = "NAME", value_parser = lib::<Sampler>)]
    pub sampler: Option<Sampler>,
    /// DDIM eta [default: the model's]
    #[arg(long, value_name = "E", allow_negative_numbers = true)]
    pub eta: Option<f32>,
    /// Classifier-free guidance scale [default: the model's]
    #[arg(long, value_name = "G", allow_negative_numbers = true)]
    pub guidance: Option<f32>,
    /// Seed of the noise
    #[arg(long, value_name = "K", default_value_t = 0)]
    pub seed: u64,
    /// Worker threads (0 = one per core)
    #[arg(long, value_name = "T", default_value_t = 0)]
    pub threads: usize,
}

#[derive(Args)]
pub struct SamplingArgs {
    /// Frames to generate [default: the model's]
    #[arg(long, value_name = "N")]
    pub frames: Option<usize>,
    #[command(flatten)]
    pub denoise: DenoiseArgs,
    /// An explicit initial noise x_T (float32 .npy, frames x feature_dim; for latent models
    /// latent_frames x latent_channels, see `flame info`)
    #[arg(long, value_name = "FILE.npy")]
    pub noise: Option<PathBuf>,
    /// Also write the final sample of a latent model (float32 .npy, latent_frames x
    /// latent_channels)
    #[arg(long, value_name = "OUT.npy")]
    pub latent: Option<PathBuf>,
}

#[derive(Args)]
pub struct OutputArgs {
    /// Output file: .npy (raw features in the model's normalised space, the valid frames),
    /// .bvh or .json (poses), .glb or .gltf (a skinned figure with its animation), .npz (AMASS
    /// SMPL parameters, see --amass); with --robot the robot's trajectory (.csv, .npz, .npy)
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
    /// The keys of a .npz: smplh (AMASS SMPL-H `*_poses.npz`: `poses` [N, 156], `trans`,
    /// `mocap_framerate`; PHC, human2humanoid) or smplx (AMASS SMPL-X `*_stageii.npz`:
    /// `root_orient`, `pose_body`, `trans`, `mocap_frame_rate`; GMR) [default smplh; .npz only]
    #[arg(long, value_name = "LAYOUT", value_parser = lib::<AmassLayout>)]
    pub amass: Option<AmassLayout>,
    /// Coordinate convention of the poses [native|unity|unreal|ros|blender|gltf; default gltf
    /// for .bvh and .glb/.gltf (which take no other), native otherwise]
    #[arg(long, value_name = "C", value_parser = lib::<Convention>)]
    pub convention: Option<Convention>,
    /// Sigma in frames of the temporal smoothing of the features, 0 = off [default: 1 for
    /// smpl24_6d, 0 otherwise]
    #[arg(long, value_name = "SIGMA", value_parser = sigma, allow_negative_numbers = true)]
    pub smooth: Option<f32>,
    /// Quaternion component order of the JSON [xyzw|wxyz]
    #[arg(long, value_name = "ORDER", value_parser = lib::<QuatOrder>, default_value = "wxyz")]
    pub quat: QuatOrder,
    /// Also write world joint positions (float32 .npy, frames x joints x 3)
    #[arg(long, value_name = "FILE.npy")]
    pub positions: Option<PathBuf>,
    /// Also write a preview: FILE.png a contact sheet, FILE.gif an animation (repeatable)
    #[arg(long, value_name = "FILE.png|FILE.gif")]
    pub preview: Vec<PathBuf>,
    /// Frame rate of a .gif preview, at most 50 [default: the output's]
    #[arg(long, value_name = "FPS")]
    pub preview_fps: Option<f32>,
    /// Foot contacts: `lock` pins each planted foot where it stands and solves the leg with
    /// two-bone IK (bone lengths and everything above the knees unchanged); `off` gives the raw
    /// poses [default lock; pose outputs only, .npy features are never touched]
    #[arg(long, value_name = "MODE", value_parser = lib::<Feet>)]
    pub feet: Option<Feet>,
    /// Put the lowest foot contact of the clip at height 0, so feet neither float nor sink
    /// [default on, off with --feet off]
    #[arg(long, value_enum, value_name = "ON|OFF")]
    pub ground: Option<OnOff>,
    /// Output frame rate, 1 to 240: rotations slerped, translations interpolated linearly; the
    /// last frame's time is kept (120 frames at 20 fps give 179 at 30) [default: the model's]
    #[arg(long, value_name = "F", value_parser = fps, allow_negative_numbers = true)]
    pub fps: Option<f64>,
    /// Where the horizontal travel goes: keep it on the pelvis, remove it (in-place), or put it
    /// on a `root` bone on the ground under the pelvis (separate; BVH and glTF write the bone)
    /// [keep|in-place|separate]
    #[arg(long, value_name = "MODE", value_parser = lib::<RootMotion>, default_value = "keep")]
    pub root_motion: RootMotion,
    /// With --root-motion in-place or separate: also remove the heading's drift (yaw)
    #[arg(long)]
    pub remove_yaw: bool,
    /// Contact detection of smpl24_6d models: metres above its standing level under which a
    /// foot joint may be planted [default 0.05]
    #[arg(long, value_name = "M", allow_negative_numbers = true)]
    pub contact_height: Option<f64>,
    /// Contact detection: speed in m/s under which a foot joint may be planted [default 0.894,
    /// HumanML3D's own contact labels]
    #[arg(long, value_name = "M/S", allow_negative_numbers = true)]
    pub contact_speed: Option<f64>,
    /// The user's character (a skinned .glb/.gltf/.vrm or a .bvh hierarchy): the finished
    /// poses are retargeted onto its bones; --out .glb/.gltf/.vrm hands the file back with the
    /// animation added (the same container as the rig), .bvh writes the rig's hierarchy
    #[arg(long, value_name = "FILE")]
    pub rig: Option<PathBuf>,
    /// Bone map over the automatic one: JSON {"hips": "BoneName", "leftUpperArm": ..., ...}
    /// with VRM humanBone names as keys (null unmaps a bone)
    #[arg(long, value_name = "FILE.json")]
    pub rig_map: Option<PathBuf>,
    /// The skin to read when the rig's glTF has several
    #[arg(long, value_name = "NAME")]
    pub rig_skin: Option<String>,
    /// Metres per unit of a .bvh rig [default: guessed, centimetres when the skeleton spans
    /// more than 20 units]
    #[arg(long, value_name = "M", allow_negative_numbers = true)]
    pub rig_unit: Option<f64>,
    /// Two-bone IK on the rig after the rotations: feet onto the source's ankles (so planted
    /// feet stay planted on other proportions), hands onto its wrists too, or none
    /// [feet|hands|both|off; default feet]
    #[arg(long, value_name = "IK", value_enum)]
    pub rig_ik: Option<RigIk>,
    /// Also write the rig's bone world positions (float32 .npy, frames x bones x 3, in the rig
    /// file's axes and units, bones in the file's order with parents first)
    #[arg(long, value_name = "FILE.npy")]
    pub rig_positions: Option<PathBuf>,
    /// A humanoid robot's URDF: the finished poses are retargeted onto it (whole-body IK with
    /// joint and velocity limits, feet held on the floor during contacts) and --out is its
    /// joint trajectory: .csv (BeyondMimic's rows x,y,z,qx,qy,qz,qw,joints), .npz (GMR's
    /// fields fps, root_pos, root_rot x,y,z,w, dof_pos, joint_names) or .npy (MuJoCo qpos,
    /// quaternion w first); see --robot-format and docs/robots.md
    #[arg(long, value_name = "FILE.urdf")]
    pub robot: Option<PathBuf>,
    /// The robot's retarget configuration (JSON, GMR's IK tables plus feet and solver keys)
    /// [default: robots/<robot name>.json in the current directory, then <prefix>/share/flame,
    /// then the source tree]
    #[arg(long, value_name = "FILE.json")]
    pub retarget: Option<PathBuf>,
    /// The layout of the robot trajectory: beyondmimic (.csv), gmr (.npz) or qpos (MuJoCo's
    /// qpos rows, w-first root quaternion, MuJoCo's joint order; .csv or .npy) [default: from
    /// the extension, .csv beyondmimic, .npz gmr, .npy qpos]
    #[arg(long, value_name = "F", value_parser = lib::<RobotFormat>)]
    pub robot_format: Option<RobotFormat>,
    /// Start a robot .csv with a line of column names (`# x,y,z,qx,...,joint names`; the `#`
    /// makes it a comment to np.loadtxt, which BeyondMimic's csv_to_npz.py uses)
    #[arg(long)]
    pub csv_header: bool,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum RigIk {
    Feet,
    Hands,
    Both,
    Off,
}

#[derive(Args)]
pub struct RetargetArgs {
    /// The motion: a BVH or a .glb/.gltf libflame wrote (SMPL-24 joints), or .npy features
    /// of the model given with --model
    #[arg(long = "in", value_name = "FILE.bvh|FILE.glb|FILE.npy")]
    pub input: PathBuf,
    /// The model whose features a .npy holds [default: $FLAME_MODEL, else the demo model]
    #[arg(long, value_name = "M")]
    pub model: Option<PathBuf>,
    /// The convention the input BVH was written in [default: the one whose rest offsets the
    /// file has; native and gltf share them and are told apart by which stands the body
    /// upright, which a motion lying down for its whole length cannot tell]
    #[arg(long, value_name = "C", value_parser = lib::<Convention>)]
    pub in_convention: Option<Convention>,
    #[command(flatten)]
    pub output: OutputArgs,
}

#[derive(Args)]
pub struct GenerateArgs {
    #[command(flatten)]
    pub model: ModelArgs,
    /// The sentence to turn into a motion
    #[arg(long, value_name = "TEXT", required_unless_present_any = ["stage", "prompt_file"], conflicts_with_all = ["stage", "prompt_file"])]
    pub prompt: Option<String>,
    /// One time stage: its text and frame count, repeated in order (FineMoGen's temporal
    /// composition; the frames add up to the motion's)
    #[arg(long, value_name = "TEXT@FRAMES", conflicts_with = "prompt_file")]
    pub stage: Vec<String>,
    /// Stages with texts per body part, in the HuMMan-MoGen layout: {"fps": 30, "stages":
    /// [{"start_frame", "end_frame", "all", "head", "stem", "left_arm", "right_arm",
    /// "left_leg", "right_leg", "pelvis"}]} (frames converted to the model's fps)
    #[arg(long, value_name = "FILE.json")]
    pub prompt_file: Option<PathBuf>,
    /// Make a loop: the end flows into the start (position and velocity of every joint), the
    /// horizontal travel kept as root motion. Generated in two passes (the second an edit that
    /// makes the end run into the next cycle's start), then the wrap corrected; models that
    /// cannot edit (latent ones) and time stages get the correction alone
    #[arg(long = "loop")]
    pub looped: bool,
    /// Joint positions the motion follows through the model's trajectory ControlNet
    /// (MotionLCM control files): float32 .npy [frames, joints, 3], metres, in the
    /// --convention's axes, NaN = free; frames at most the motion's (later ones are free)
    #[arg(long, value_name = "FILE.npy")]
    pub control: Option<PathBuf>,
    /// Consistency latent tuning (MotionLCM's --optimize): N Adam iterations on the initial
    /// latent, through the 1-step sampler, the decoder and the joints, toward the --control,
    /// before sampling (the release runs 400; --steps 1)
    #[arg(long, value_name = "N", requires = "control")]
    pub optimize: Option<usize>,
    #[command(flatten)]
    pub sampling: SamplingArgs,
    #[command(flatten)]
    pub output: OutputArgs,
}

#[derive(Clone, Copy, PartialEq, Eq, ValueEnum)]
pub enum OnOff {
    On,
    Off,
}

#[derive(Args)]
pub struct EditArgs {
    #[command(flatten)]
    pub model: ModelArgs,
    /// The reference motion: .npy features or a BVH written by libflame (optional with --targets)
    #[arg(long, value_name = "FILE", required_unless_present = "targets")]
    pub reference: Option<PathBuf>,
    /// Joint positions to steer toward: float32 .npy [frames, joints, 3], metres, in the
    /// --convention's axes, NaN = unconstrained
    #[arg(long, value_name = "FILE.npy")]
    pub targets: Option<PathBuf>,
    /// Step size of the position guidance (MoLA's edit scale) [default 0.6]
    #[arg(long, value_name = "S")]
    pub target_scale: Option<f32>,
    /// How the position guidance weight follows the noise level [mpgd|constant; default mpgd
    /// for latent models, constant for the others]
    #[arg(long, value_name = "SCHEDULE", value_parser = lib::<TargetSchedule>)]
    pub target_schedule: Option<TargetSchedule>,
    /// What to generate the rest of
    #[arg(long, value_name = "TEXT")]
    pub prompt: String,
    /// Editing task [inbetween|predict|upper-body|path]
    #[arg(long, value_name = "TASK", value_parser = lib::<Task>)]
    pub task: Option<Task>,
    /// Frame ranges to keep (A:B half-open, `:B`, `A:`, comma-separated)
    #[arg(long, value_name = "A:B,...")]
    pub keep_frames: Option<String>,
    /// Joints to keep on every frame, by index or name (`root` = the root path)
    #[arg(long, value_name = "J,...")]
    pub keep_joints: Option<String>,
    /// Editing algorithm [auto|noised-reference|replace-x0|rewrite-trajectory|mpgd]; mpgd steers
    /// toward the reference's joint positions (auto picks it for latent models)
    #[arg(long, value_name = "METHOD", value_parser = edit_choice)]
    pub method: Option<EditChoice>,
    /// Flow models: the fraction of the steps during which the trajectory is rewritten [default 0.2]
    #[arg(long, value_name = "F", allow_negative_numbers = true)]
    pub edit_till: Option<f32>,
    /// Copy the kept values exactly into the result and blend the seams
    #[arg(long, value_enum, default_value = "on")]
    pub paste: OnOff,
    /// Frames over which each seam's offset fades out [default 4]
    #[arg(long, value_name = "N")]
    pub seam_frames: Option<usize>,
    /// Convention of a BVH reference [default: recognised from the file]
    #[arg(long, value_name = "C", value_parser = lib::<Convention>)]
    pub reference_convention: Option<Convention>,
    #[command(flatten)]
    pub sampling: SamplingArgs,
    #[command(flatten)]
    pub output: OutputArgs,
}

#[derive(Args)]
pub struct StreamArgs {
    #[command(flatten)]
    pub model: ModelArgs,
    /// One segment of the timeline: its sentence and frame count, repeated in order
    #[arg(
        long,
        value_name = "TEXT@FRAMES",
        required_unless_present = "prompt_file",
        conflicts_with = "prompt_file"
    )]
    pub segment: Vec<String>,
    /// Make the whole timeline loop: its last second is generated to run into its first frames
    /// (the last segment's prompt; kept at both ends, as `generate --loop` does), then the wrap
    /// corrected so position and velocity of every joint flow on; the travel is kept as root
    /// motion. Latent models (MLD, MoLA) get the wrap correction alone
    #[arg(long = "loop")]
    pub looped: bool,
    /// Segments with texts per body part (FineMoGen), in the HuMMan-MoGen layout of `generate
    /// --prompt-file`: each stage is a segment
    #[arg(long, value_name = "FILE.json")]
    pub prompt_file: Option<PathBuf>,
    /// Frames per chunk, kept ones included [default: the model's default frame count]
    #[arg(long, value_name = "N")]
    pub chunk: Option<usize>,
    /// Frames of the previous chunk each chunk keeps
    #[arg(long, value_name = "N", default_value_t = 20)]
    pub overlap: usize,
    #[command(flatten)]
    pub denoise: DenoiseArgs,
    #[command(flatten)]
    pub output: OutputArgs,
}

#[derive(Args)]
pub struct InfoArgs {
    /// Model file [default: $FLAME_MODEL, else the demo model]
    pub model: Option<PathBuf>,
}

#[derive(Args)]
pub struct AssembleArgs {
    /// The denoiser-only file (tools/convert.py --denoiser-only)
    #[arg(value_name = "DENOISER.safetensors")]
    pub denoiser: PathBuf,
    /// The text encoder's Hugging Face model.safetensors
    #[arg(value_name = "TEXT_WEIGHTS.safetensors")]
    pub text: PathBuf,
    /// The model file to write
    #[arg(value_name = "OUT.safetensors")]
    pub out: PathBuf,
    /// Record the action families the denoiser was trained on (comma-separated), printed by
    /// `flame info`
    #[arg(
        long,
        value_name = "A,B,...",
        value_delimiter = ',',
        conflicts_with = "demo_actions"
    )]
    pub actions: Vec<String>,
    /// Record the demo corpus's action families (for the demo denoiser, see docs/demo_corpus.md)
    #[arg(long)]
    pub demo_actions: bool,
}

#[derive(Args)]
pub struct BatchArgs {
    #[command(flatten)]
    pub model: ModelArgs,
    /// The jobs: one JSON object a line (keys: generate's options, see above)
    #[arg(
        long,
        value_name = "FILE.jsonl",
        required_unless_present = "prompts",
        conflicts_with = "prompts"
    )]
    pub jobs: Option<PathBuf>,
    /// Prompts, one a line (blank lines and `#` lines skipped), with --seeds and --out-pattern
    #[arg(long, value_name = "FILE", requires = "out_pattern")]
    pub prompts: Option<PathBuf>,
    /// Seeds per prompt of --prompts (0..N)
    #[arg(long, value_name = "N", default_value_t = 1, requires = "prompts")]
    pub seeds: u64,
    /// Output of each --prompts job: {line}, {seed} and {n} are replaced
    #[arg(long, value_name = "PATTERN", requires = "prompts")]
    pub out_pattern: Option<String>,
    /// Keys every job takes unless it sets them: a JSON object (`{"steps": 10, "feet": "off"}`)
    #[arg(long, value_name = "JSON")]
    pub defaults: Option<String>,
    /// The manifest to write [default: the jobs or prompts file with .manifest.jsonl added]
    #[arg(long, value_name = "FILE.jsonl")]
    pub manifest: Option<PathBuf>,
    /// Skip the jobs the manifest records as done whose outputs exist; append to it
    #[arg(long)]
    pub resume: bool,
    /// Sessions run at once (0 = one per core, at most one per job)
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub workers: usize,
    /// Kernel threads of each session (0 = the cores shared among the sessions)
    #[arg(long, value_name = "T", default_value_t = 0)]
    pub threads: usize,
}

#[derive(Args)]
pub struct QuantizeArgs {
    /// The model file to quantise (f32, f16 or bf16)
    #[arg(long, value_name = "MODEL.safetensors")]
    pub model: PathBuf,
    /// The int8 model file to write
    #[arg(long, value_name = "OUT.safetensors")]
    pub out: PathBuf,
    /// Calibration prompts, one per line (default: 16 built-in prompts, one per kind of motion)
    #[arg(long, value_name = "FILE")]
    pub prompts: Option<PathBuf>,
    /// Seeds per prompt
    #[arg(long, default_value_t = 1, value_name = "N")]
    pub seeds: u64,
    /// Frames per calibration run (the model's default when left out)
    #[arg(long, value_name = "N")]
    pub frames: Option<usize>,
    /// Sampling steps per calibration run (the model's default, at most 50, when left out)
    #[arg(long, value_name = "N")]
    pub steps: Option<usize>,
    /// Threads (0: all cores)
    #[arg(long, default_value_t = 0, value_name = "N")]
    pub threads: usize,
    /// Keep a weight f32: a tensor name, or a prefix such as `tf_decoder.layers.3.` for a whole
    /// layer (repeatable; `--verbose` lists the names)
    #[arg(long = "keep-f32", value_name = "NAME")]
    pub keep_f32: Vec<String>,
    /// One scale per group of N inputs instead of one per output row: a file for float
    /// activations (runs as f16 by default; the int8 kernels take per-row scales only)
    #[arg(long, value_name = "N")]
    pub group: Option<usize>,
    /// Print each weight's relative output error, rounded at load and as written
    #[arg(long)]
    pub verbose: bool,
}
