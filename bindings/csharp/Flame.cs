// C# bindings of libflame (text-to-motion diffusion on the CPU) for Unity (Mono and IL2CPP) and
// .NET: P/Invoke declarations mirroring include/flame.h, SafeHandles for the two handles, and a
// small managed API over them.
//
//   using (var model = FlameModel.Load(path))
//   using (var session = model.NewSession(p))   // p from FlameSessionParams.Default()
//   {
//       session.SetPrompt("a person jumps twice");
//       while (session.Step() > 0) { }          // one step per call; Cancel() from any thread
//       float[] motion = session.Read(FlameWhich.Sample, FlameLayout.Features,
//                                     FlameConvention.Native, 0);
//   }
//
// Written for C# 7.3 (Unity 2018.3+, mcs) and without UTF-8 marshalling attributes, which not
// every runtime supports: strings cross as NUL-terminated UTF-8 byte arrays.
//
// Threads: a FlameModel may be shared by any number of threads; a FlameSession or a FlameStream
// is used by one thread at a time (libflame answers WRONG_STATE to a second thread), except
// Cancel(). Disposing a session while another thread is inside Step() (a stream: Pump()) is
// safe: the SafeHandle defers the free until that call returns (cancel first so it returns soon).

using System;
using System.Collections.Generic;
using System.Runtime.InteropServices;
using System.Text;

namespace Flame
{
    /// <summary>What every fallible call returns (enum FlameStatus).</summary>
    public enum FlameStatus
    {
        Ok = 0,
        InvalidArgument = 1,
        Io = 2,
        BadModelFile = 3,
        WrongState = 4,
        Cancelled = 5,
        Tokenizer = 6,
        BufferTooSmall = 7,
        Internal = 8,
        NotFinite = 9,
    }

    /// <summary>FlameSessionParams.sampler values.</summary>
    public enum FlameSampler
    {
        Default = 0,
        Ddpm = 1,
        Ddim = 2,
        /// <summary>Flow matching (Motion Flow Matching models): Euler steps.</summary>
        Euler = 3,
        /// <summary>Flow matching: Heun, two network evaluations per step.</summary>
        Heun = 4,
        /// <summary>Flow matching: midpoint rule, two network evaluations per step.</summary>
        Midpoint = 5,
        /// <summary>Latent consistency models (MotionLCM): 1 to 4 steps, the guidance embedded in one pass.</summary>
        Lcm = 6,
    }

    /// <summary>Which motion FlameSession.Read returns.</summary>
    public enum FlameWhich
    {
        /// <summary>The current sample x_t (the final motion once every step has run).</summary>
        Sample = 0,
        /// <summary>The model's current estimate of the clean motion (a preview).</summary>
        Estimate = 1,
    }

    /// <summary>How a session imposes the kept reference values (FlameEditParams.method).</summary>
    public enum FlameEditMethod
    {
        /// <summary>The model family's own method.</summary>
        Auto = 0,
        /// <summary>FLAME: the reference, noised to each step's level, overwrites the kept values of x_t (diffusion models).</summary>
        NoisedReference = 1,
        /// <summary>MDM: the reference overwrites the kept values of the clean-motion estimate (diffusion models).</summary>
        ReplaceX0 = 2,
        /// <summary>Motion Flow Matching: the kept values follow the path to the reference while step / steps &lt;= edit_till (flow models).</summary>
        RewriteTrajectory = 3,
    }

    /// <summary>Named groups of channels for FlameSession.KeepPart.</summary>
    public enum FlameBodyPart
    {
        /// <summary>The root's trajectory.</summary>
        RootPath = 0,
        /// <summary>Root path, pelvis and legs.</summary>
        LowerBody = 1,
        /// <summary>Spine, neck, head, collars and arms.</summary>
        UpperBody = 2,
        /// <summary>Collars, shoulders, elbows, wrists (and hands).</summary>
        Arms = 3,
        /// <summary>Hips, knees, ankles and feet (and foot contacts).</summary>
        Legs = 4,
    }

    /// <summary>The standard editing tasks of FlameSession.SetTaskMask (L = the session's frames).</summary>
    public enum FlameEditTask
    {
        /// <summary>Keep all but frames [L/4, 3L/4).</summary>
        Inbetween = 0,
        /// <summary>Keep frames [0, L/4), generate the rest.</summary>
        Predict = 1,
        /// <summary>Keep the lower body on every frame, generate the upper body.</summary>
        UpperBody = 2,
        /// <summary>Keep the root path on every frame, generate the body.</summary>
        Path = 3,
    }

    /// <summary>How the pull of position targets changes with the noise level τ (1 = noise;
    /// FlameTargetParams.schedule).</summary>
    public enum FlameTargetSchedule
    {
        /// <summary>4·τ·(1 − τ): nothing at either end, full strength half way (MoLA's MPGD; default).</summary>
        Mpgd = 0,
        /// <summary>The same weight at every step.</summary>
        Constant = 1,
    }

    /// <summary>The container FlameSession.WriteGltf writes (enum FlameGltfContainer).</summary>
    public enum FlameGltfContainer
    {
        /// <summary>Binary glTF (.glb): what glTFast and other run-time importers load from bytes.</summary>
        Glb = 0,
        /// <summary>JSON glTF (.gltf) with the buffer embedded as a base64 data URI.</summary>
        Gltf = 1,
    }

    /// <summary>Layouts of FlameSession.WriteAmass (FLAME_AMASS_SMPLH / FLAME_AMASS_SMPLX):
    /// which AMASS release's keys the .npz holds.</summary>
    public static class FlameAmassLayout
    {
        /// <summary>AMASS SMPL-H (*_poses.npz): poses [N, 156], trans, betas, gender,
        /// mocap_framerate, dmpls; what PHC and human2humanoid read.</summary>
        public const int Smplh = 0;
        /// <summary>AMASS SMPL-X (*_stageii.npz): root_orient, pose_body, pose_hand, pose_jaw,
        /// pose_eye, trans, betas, num_betas, gender, surface_model_type, mocap_frame_rate,
        /// mocap_time_length, poses [N, 165]; what GMR reads.</summary>
        public const int Smplx = 1;
    }

    /// <summary>Pose layouts of FlameSession.Read (enum FlameLayout; J = joint count). Plain
    /// integers, passed through unchanged, so a layout the library adds works before it is
    /// named here.</summary>
    public static class FlameLayout
    {
        /// <summary>[frames, feature_dim] the model's raw features (convention and flags ignored).</summary>
        public const int Features = 0;
        /// <summary>[frames, 3] the root joint's world position.</summary>
        public const int RootTranslation = 1;
        /// <summary>[frames, J, 4] parent-relative rotations, quaternions x, y, z, w.</summary>
        public const int LocalQuatXyzw = 2;
        /// <summary>[frames, J, 4] parent-relative rotations, quaternions w, x, y, z.</summary>
        public const int LocalQuatWxyz = 3;
        /// <summary>[frames, J, 3, 3] parent-relative rotation matrices, row-major.</summary>
        public const int LocalMatrix = 4;
        /// <summary>[frames, J, 6] parent-relative rotations as the first two matrix rows.</summary>
        public const int Local6d = 5;
        /// <summary>[frames, J, 3] world joint positions.</summary>
        public const int GlobalPositions = 6;
        /// <summary>[frames, J, 4] world rotations, quaternions x, y, z, w.</summary>
        public const int GlobalQuatXyzw = 7;
        /// <summary>[frames, J, 4] world rotations, quaternions w, x, y, z.</summary>
        public const int GlobalQuatWxyz = 8;
        /// <summary>[frames, 4] foot contacts (left ankle, left foot, right ankle, right foot),
        /// 0 or 1; for smpl24 models only in a read with a cleanup (they are detected).</summary>
        public const int FootContacts = 9;
        /// <summary>[frames, 3] the root bone's position (on the ground under the pelvis); only
        /// in a read whose cleanup has FlameRootMotion.Separate.</summary>
        public const int RootBone = 10;

        /// <summary>Floats per frame of a layout for a model (featureDim and jointCount from
        /// ModelInfo), or 0 for a layout not named here: lets a caller count the frames of a
        /// read whose cleanup changed the frame rate.</summary>
        public static int ValuesPerFrame(int layout, int featureDim, int jointCount)
        {
            switch (layout)
            {
                case Features: return featureDim;
                case RootTranslation: case RootBone: return 3;
                case LocalQuatXyzw: case LocalQuatWxyz: case GlobalQuatXyzw: case GlobalQuatWxyz: return jointCount * 4;
                case LocalMatrix: return jointCount * 9;
                case Local6d: return jointCount * 6;
                case GlobalPositions: return jointCount * 3;
                case FootContacts: return 4;
                default: return 0;
            }
        }
    }

    /// <summary>Coordinate conventions of FlameSession.Read (enum FlameConvention; plain
    /// integers, like FlameLayout).</summary>
    public static class FlameConvention
    {
        /// <summary>The motion format's own frame, data untouched.</summary>
        public const int Native = 0;
        /// <summary>Left-handed, Y up, Z forward, metres: new Quaternion(x, y, z, w) as localRotation.</summary>
        public const int Unity = 1;
        /// <summary>Left-handed, Z up, X forward, centimetres.</summary>
        public const int Unreal = 2;
        /// <summary>Right-handed, Z up, X forward, metres.</summary>
        public const int Ros = 3;
        /// <summary>Right-handed, Z up, -Y forward, metres.</summary>
        public const int Blender = 4;
        /// <summary>Right-handed, Y up, Z forward, metres.</summary>
        public const int Gltf = 5;
    }

    /// <summary>Bits of FlameSession.Read's flags.</summary>
    public static class FlameReadFlags
    {
        /// <summary>FLAME_READ_SMOOTH: FLAME's temporal smoothing (sigma = 1 frame) before posing.</summary>
        public const uint Smooth = 1;
        /// <summary>FLAME_READ_RAW_SIGNS: quaternions as computed (w >= 0), not sign-continuous.</summary>
        public const uint RawSigns = 2;
    }

    /// <summary>FlameWeights: what a model's linear layers are held and multiplied in.</summary>
    public enum FlameWeights : int
    {
        /// <summary>f32: exact, the fastest on CPUs without half-precision arithmetic.</summary>
        F32 = 0,
        /// <summary>IEEE half: half the memory.</summary>
        F16 = 1,
        /// <summary>bfloat16: half the memory, coarser than f16.</summary>
        Bf16 = 2,
        /// <summary>bf16 weights and bf16 products (AVX512_BF16; refused at load without it).</summary>
        Bf16Compute = 3,
        /// <summary>8-bit integer weights and products, a quarter of the memory (AVX512_VNNI or
        /// AVX2; refused at load without either).</summary>
        Int8 = 4,
    }

    /// <summary>FlameFeet (FlameCleanupParams.feet): what happens to the feet while they are
    /// planted.</summary>
    public enum FlameFeet
    {
        /// <summary>The raw poses: feet may slide.</summary>
        Off = 0,
        /// <summary>Each planted foot pinned where it stands, the leg solved by two-bone IK; bone
        /// lengths and everything above the knees unchanged.</summary>
        Lock = 1,
    }

    /// <summary>FlameRootMotion (FlameCleanupParams.root_motion): where the clip's horizontal
    /// travel goes.</summary>
    public enum FlameRootMotion
    {
        /// <summary>On the pelvis, as the model made it.</summary>
        Keep = 0,
        /// <summary>Removed: the pelvis stays over the origin (an in-place clip).</summary>
        InPlace = 1,
        /// <summary>On a root bone on the ground under the pelvis (read it as
        /// FlameLayout.RootBone; glTF exports write a node "root"): the pelvis reads in place.
        /// What Unity's Animator applies as root motion.</summary>
        Separate = 2,
    }

    /// <summary>Mirror of the C struct FlameCleanupParams: the post-processing of
    /// FlameSession.Read(..., cleanup) and WriteGltf(..., cleanup). Eleven 32-bit fields (44
    /// bytes), flags as uint 0/1, not bool (one layout under Mono, IL2CPP and .NET). Start from
    /// Default() (game-ready: feet locked, the floor at 0, root motion kept, no wrap, the
    /// model's frame rate) or Raw() (every step off). libflame checks every value
    /// (InvalidArgument naming it).</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameCleanupParams
    {
        public uint struct_size;
        /// <summary>A FlameFeet value.</summary>
        public int feet;
        /// <summary>1: the clip's lowest foot contact put at height 0.</summary>
        public uint ground;
        /// <summary>A FlameRootMotion value.</summary>
        public int root_motion;
        /// <summary>1 (with InPlace or Separate): also remove the heading's drift.</summary>
        public uint remove_yaw;
        /// <summary>1: cross-fade the clip's end into its start so it loops.</summary>
        public uint wrap;
        /// <summary>Output frames per second, 1 to 240; 0 = the model's. Changes the frame
        /// count (the first and last frames' times kept: 40 frames at 20 fps are 59 at 30).</summary>
        public float fps;
        /// <summary>Contact detection (smpl24 models): height above the standing level, metres.</summary>
        public float contact_height;
        /// <summary>Contact detection: speed below which a foot may be planted, m/s.</summary>
        public float contact_speed;
        /// <summary>Contact detection: hysteresis ratio (at least 1) for leaving a contact.</summary>
        public float contact_release;
        /// <summary>Contact detection: shortest contact span and gap kept, seconds.</summary>
        public float contact_min_span;

        /// <summary>flame_cleanup_params_default: feet locked, ground on, root motion kept.</summary>
        public static FlameCleanupParams Default()
        {
            var p = new FlameCleanupParams();
            FlameException.Check(FlameNative.flame_cleanup_params_default(out p));
            return p;
        }

        /// <summary>Default() with every step off (feet free, no floor): set only the fields
        /// you want (fps, root_motion), and the poses change in that way alone.</summary>
        public static FlameCleanupParams Raw()
        {
            var p = Default();
            p.feet = (int)FlameFeet.Off;
            p.ground = 0;
            return p;
        }

        /// <summary>The feet as the enum.</summary>
        public FlameFeet Feet { get { return (FlameFeet)feet; } set { feet = (int)value; } }
        /// <summary>The root motion as the enum.</summary>
        public FlameRootMotion RootMotion { get { return (FlameRootMotion)root_motion; } set { root_motion = (int)value; } }
    }

    /// <summary>Mirror of the C struct FlameModelParams.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameModelParams
    {
        public uint struct_size;
        /// <summary>Threads for work done at load; 0 = one per core; at most
        /// FlameNative.MaxThreads (more: InvalidArgument).</summary>
        public uint threads;
        /// <summary>A FlameWeights value: what the linear layers are held and multiplied in.</summary>
        public FlameWeights weights;

        /// <summary>The library's defaults (struct_size set).</summary>
        public static FlameModelParams Default()
        {
            var p = new FlameModelParams();
            FlameException.Check(FlameNative.flame_model_params_default(out p));
            return p;
        }
    }

    /// <summary>Mirror of the C struct FlameModelInfo. The pointers belong to the model and are
    /// valid until it is freed: use the helpers, or FlameModel.Info (a managed copy).</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameModelInfo
    {
        public uint struct_size;
        public uint feature_dim;
        public uint joint_count;
        public uint max_frames;
        public uint default_frames;
        public uint default_steps;
        public uint num_timesteps;
        public int default_sampler;
        public float fps;
        public float default_guidance;
        public float default_eta;
        public IntPtr architecture;
        public IntPtr motion_format;
        public IntPtr text_encoder;
        /// <summary>joint_count pointers to NUL-terminated UTF-8 names (may be NULL if 0).</summary>
        public IntPtr joint_names;
        /// <summary>joint_count int32 parent indices, -1 for the root (may be NULL if 0).</summary>
        public IntPtr joint_parents;
        /// <summary>Nonzero when the model samples a latent that its decoder turns into motion
        /// (MoLA): a read's frames are then the length the decoder decides
        /// (flame_session_read_frames), and masks and reference motions do not apply.</summary>
        public uint latent;
        /// <summary>Channels per row of the sampled space (feature_dim, or the latent's
        /// channels): the width of flame_session_set_noise's rows.</summary>
        public uint sample_dim;
        /// <summary>Nonzero when the model has a trajectory ControlNet (MotionLCM control files):
        /// flame_session_set_control makes its motion follow joint positions.</summary>
        public uint control;

        public string Architecture { get { return FlameNative.Utf8(architecture); } }
        public string MotionFormat { get { return FlameNative.Utf8(motion_format); } }
        public string TextEncoder { get { return FlameNative.Utf8(text_encoder); } }

        public string[] JointNames()
        {
            var names = new string[joint_names == IntPtr.Zero ? 0 : (int)joint_count];
            for (int i = 0; i < names.Length; i++)
                names[i] = FlameNative.Utf8(Marshal.ReadIntPtr(joint_names, i * IntPtr.Size));
            return names;
        }

        public int[] JointParents()
        {
            var parents = new int[joint_parents == IntPtr.Zero ? 0 : (int)joint_count];
            if (parents.Length > 0)
                Marshal.Copy(joint_parents, parents, 0, parents.Length);
            return parents;
        }
    }

    /// <summary>How a batch runs (flame_batch_params_default); the strings are UTF-8 pointers
    /// the caller keeps alive for the call (IntPtr.Zero: the default).</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameBatchParams
    {
        public uint struct_size;
        public uint workers;
        public uint threads;
        public uint resume;
        public IntPtr base_dir;
        public IntPtr model_name;
    }

    /// <summary>The counts of a finished batch run (flame_batch_run).</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameBatchSummary
    {
        public uint struct_size;
        public ulong total;
        public ulong ok;
        public ulong failed;
        public ulong skipped;
    }

    /// <summary>How a stream generates (flame_stream_params_default): 0 = the default for every
    /// count, a negative guidance = the model's.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameStreamParams
    {
        public uint struct_size;
        public uint chunk;
        public uint overlap;
        public uint lookahead;
        public uint window;
        public uint steps;
        /// <summary>A FlameSampler value.</summary>
        public int sampler;
        public float guidance;
        public ulong seed;
        public uint threads;

        /// <summary>The library's defaults.</summary>
        public static FlameStreamParams Default()
        {
            FlameStreamParams p;
            FlameException.Check(FlameNative.flame_stream_params_default(out p));
            return p;
        }
    }

    /// <summary>What a pump did and where a stream stands: frames FirstFrame..Ready can be read.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameStreamStatus
    {
        public uint struct_size;
        public uint steps;
        public ulong ready;
        public ulong first_frame;
        public ulong playhead;
        /// <summary>1: fewer than lookahead frames ready ahead of the playhead and nothing left
        /// to generate them from (push more).</summary>
        public uint starving;
    }

    /// <summary>Mirror of the C struct FlameSessionParams. Start from Default(): zero frames or
    /// steps, sampler Default, a negative eta or guidance and a null respacing mean "the model
    /// file's default".</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameSessionParams
    {
        public uint struct_size;
        public uint frames;
        public uint steps;
        /// <summary>A FlameSampler value.</summary>
        public int sampler;
        public float eta;
        public float guidance;
        public ulong seed;
        /// <summary>Worker threads the session creates and owns; 0 = one per core; at most
        /// FlameNative.MaxThreads (more: InvalidArgument).</summary>
        public uint threads;
        /// <summary>NUL-terminated UTF-8 respacing string, or IntPtr.Zero for none; set it
        /// through FlameModel.NewSession(p, respacing), which keeps the bytes pinned for the
        /// call.</summary>
        public IntPtr respacing;
        /// <summary>1 = generate a loop of frames frames whose end flows into its start (as
        /// `flame generate --loop`); 0 = a plain generation (since ABI 4). The session samples
        /// twice, a generation of frames plus a lead of 0.5 s, then an edit of it that keeps the
        /// lead on both sides of the wrap: Step and StepsTotal count both passes (steps 4 is 8
        /// steps in all). The finished sample reads as the cycle's frames frames: every pose
        /// read applies the wrap's correction (a cleanup's wrap is taken as on), the raw
        /// features drop the next cycle's first frame. NewSession throws InvalidArgument for a
        /// latent model (use a cleanup's wrap on a plain session), a cycle too short or too long
        /// for the model, and any other value than 0 or 1; a loop session refuses time stages,
        /// references, masks and position targets.</summary>
        public uint looped;

        public static FlameSessionParams Default()
        {
            var p = new FlameSessionParams();
            FlameException.Check(FlameNative.flame_session_params_default(out p));
            return p;
        }
    }

    /// <summary>Mirror of the C struct FlameEditParams. Start from Default(): the model family's
    /// method, edit_till 0.2, paste on, 4 seam frames.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameEditParams
    {
        public uint struct_size;
        /// <summary>A FlameEditMethod value.</summary>
        public int method;
        /// <summary>Flow models: the fraction of the steps, from the noise end, that rewrite the trajectory (0..1).</summary>
        public float edit_till;
        /// <summary>Nonzero: the kept values are pasted exactly into the final result and the seams blended; 0: the official behaviour.</summary>
        public uint paste;
        /// <summary>Frames over which a seam's offset fades out (0..1000; 0 = no blending).</summary>
        public uint seam_frames;

        public static FlameEditParams Default()
        {
            var p = new FlameEditParams();
            FlameException.Check(FlameNative.flame_edit_params_default(out p));
            return p;
        }
    }

    /// <summary>Mirror of the C struct FlameTargetParams: how strongly position targets steer
    /// (FlameSession.SetTargetParams). Start from Default(): scale 0.6, the MPGD schedule.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameTargetParams
    {
        public uint struct_size;
        /// <summary>The step size s of ρ = s·w(τ), in [0, 100] (0 = off).</summary>
        public float scale;
        /// <summary>A FlameTargetSchedule value.</summary>
        public int schedule;

        public static FlameTargetParams Default()
        {
            var p = new FlameTargetParams();
            FlameException.Check(FlameNative.flame_target_params_default(out p));
            return p;
        }
    }

    /// <summary>Mirror of the C struct FlameGltfParams: how FlameSession.WriteGltf exports.
    /// Three 32-bit fields and a float, then two pointers (32 bytes on 64-bit targets, 24 on
    /// 32-bit). Start from Default(): GLB, no read flags, the model's frame rate, the animation
    /// named after the prompt, no cleanup.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameGltfParams
    {
        public uint struct_size;
        /// <summary>A FlameGltfContainer value.</summary>
        public int container;
        /// <summary>FlameReadFlags bits applied before posing.</summary>
        public uint flags;
        /// <summary>Animation frames per second; 0 = the model's.</summary>
        public float fps;
        /// <summary>NUL-terminated UTF-8 animation name, or IntPtr.Zero for the prompt's; set it
        /// through FlameSession.WriteGltf(..., name), which keeps the bytes pinned for the
        /// call.</summary>
        public IntPtr name;
        /// <summary>A FlameCleanupParams* applied before export, or IntPtr.Zero for the raw
        /// poses; set it through FlameSession.WriteGltf(..., cleanup), which keeps a copy in
        /// unmanaged memory for the call.</summary>
        public IntPtr cleanup;

        public static FlameGltfParams Default()
        {
            var p = new FlameGltfParams();
            FlameException.Check(FlameNative.flame_gltf_params_default(out p));
            return p;
        }
    }

    /// <summary>Mirror of the C struct FlamePromptInfo: how the last prompt fitted the text
    /// encoder's window. Six uint then a pointer (32 bytes on 64-bit targets, 28 on 32-bit; no
    /// padding either way). `dropped` belongs to the session until its next prompt: use
    /// FlameSession.PromptInfo() (a managed copy).</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlamePromptInfo
    {
        public uint struct_size;
        /// <summary>Tokens of the whole prompt, special tokens included.</summary>
        public uint tokens;
        /// <summary>Tokens the text encoder saw (at most window).</summary>
        public uint kept;
        /// <summary>The encoder's window, special tokens included.</summary>
        public uint window;
        /// <summary>1 when the window cut the prompt.</summary>
        public uint truncated;
        /// <summary>1 when the prompt was empty or blank: generation without text.</summary>
        public uint unconditional;
        /// <summary>The text cut off, NUL-terminated UTF-8 ("" when nothing was).</summary>
        public IntPtr dropped;
    }

    /// <summary>Mirror of the C struct FlameTuningReport: what FlameSession.TuneLatent did (two
    /// uint then four doubles, 40 bytes).</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameTuningReport
    {
        public uint struct_size;
        /// <summary>Iterations run.</summary>
        public uint iterations;
        /// <summary>The hint loss (mean squared distance over the hinted coordinates, m²) at
        /// the first latent.</summary>
        public double hint_loss_before;
        /// <summary>The hint loss at the tuned latent.</summary>
        public double hint_loss_after;
        /// <summary>The mean distance (m) of a hinted joint from its target at the first
        /// latent.</summary>
        public double control_error_before;
        /// <summary>The same at the tuned latent.</summary>
        public double control_error_after;
    }

    /// <summary>Mirror of the C struct FlameStage: one time stage of a prompt, its texts as
    /// NUL-terminated UTF-8 pointers (IntPtr.Zero = none). Two uint then eight pointers (72
    /// bytes on 64-bit targets, 40 on 32-bit). Use FlameSession.SetPromptStages with Stage
    /// objects, which marshals the strings.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameStage
    {
        public uint struct_size;
        public uint frames;
        public IntPtr text;
        public IntPtr head;
        public IntPtr stem;
        public IntPtr left_arm;
        public IntPtr right_arm;
        public IntPtr left_leg;
        public IntPtr right_leg;
        public IntPtr pelvis;
    }

    /// <summary>One time stage of a prompt for FlameSession.SetPromptStages, or one segment of a
    /// stream's timeline for FlameStream.PushStage and InterruptStage: what the whole body does
    /// (Text) for Frames frames, and optionally what single body parts do (the HuMMan-MoGen
    /// annotation's fields; null or "" = the part follows Text). FineMoGen models compose stages
    /// and read the part texts; other models take one stage without part texts.</summary>
    public sealed class Stage
    {
        public string Text;
        public int Frames;
        public string Head;
        /// <summary>The spine.</summary>
        public string Stem;
        public string LeftArm;
        public string RightArm;
        public string LeftLeg;
        public string RightLeg;
        /// <summary>The root's trajectory.</summary>
        public string Pelvis;

        public Stage() { }

        public Stage(string text, int frames)
        {
            Text = text;
            Frames = frames;
        }
    }

    /// <summary>Called after every step, on the stepping thread (FlameProgressCallback).</summary>
    [UnmanagedFunctionPointer(CallingConvention.Cdecl)]
    public delegate void ProgressCallback(IntPtr userData, uint stepsDone, uint stepsTotal);

    /// <summary>Owns a FlameModel*; releasing it calls flame_model_free.</summary>
    public sealed class FlameModelHandle : SafeHandle
    {
        public FlameModelHandle() : base(IntPtr.Zero, true) { }
        public override bool IsInvalid { get { return handle == IntPtr.Zero; } }
        protected override bool ReleaseHandle()
        {
            FlameNative.flame_model_free(handle);
            return true;
        }
    }

    /// <summary>Owns a FlameSession*; releasing it calls flame_session_free (which joins the
    /// session's worker threads).</summary>
    public sealed class FlameSessionHandle : SafeHandle
    {
        /// <summary>The progress callback's user_data (a weak GCHandle to the FlameSession). Freed
        /// only after the native session, so no callback can find it freed.</summary>
        internal GCHandle CallbackTarget;

        public FlameSessionHandle() : base(IntPtr.Zero, true) { }
        public override bool IsInvalid { get { return handle == IntPtr.Zero; } }
        protected override bool ReleaseHandle()
        {
            FlameNative.flame_session_free(handle);
            if (CallbackTarget.IsAllocated)
                CallbackTarget.Free();
            return true;
        }
    }

    /// <summary>Owns a FlameStream*; releasing it calls flame_stream_free.</summary>
    public sealed class FlameStreamHandle : SafeHandle
    {
        public FlameStreamHandle() : base(IntPtr.Zero, true) { }
        public override bool IsInvalid { get { return handle == IntPtr.Zero; } }
        protected override bool ReleaseHandle()
        {
            FlameNative.flame_stream_free(handle);
            return true;
        }
    }

    /// <summary>Continuous motion from a timeline of prompts (docs/streams.md): Push segments,
    /// Pump a bounded number of denoiser steps per call, move the playhead, Read frames. Frames
    /// not generated yet throw with WrongState, dropped ones with InvalidArgument, a cancelled
    /// pump with Cancelled. A latent model whose decoder has a gradient (MoLA) streams through
    /// position targets; Create refuses MLD. Used by one thread at a time, except Cancel().</summary>
    public sealed class FlameStream : IDisposable
    {
        public FlameStreamHandle Handle { get; private set; }

        FlameStream(FlameStreamHandle h) { Handle = h; }

        public static FlameStream Create(FlameModel model, FlameStreamParams? p = null)
        {
            if (model == null)
                throw new ArgumentNullException("model");
            var q = p ?? FlameStreamParams.Default();
            q.struct_size = (uint)Marshal.SizeOf(typeof(FlameStreamParams));
            FlameStreamHandle h;
            FlameException.Check(FlameNative.flame_stream_new(model.Handle, ref q, out h));
            return new FlameStream(h);
        }

        public void Push(string prompt, int frames)
        {
            if (prompt == null)
                throw new ArgumentNullException("prompt");
            if (frames < 0)
                throw new ArgumentOutOfRangeException("frames");
            FlameException.Check(FlameNative.flame_stream_push(Handle, FlameNative.Utf8Z(prompt), (uint)frames));
        }

        /// <summary>Ends the current segment at the next chunk boundary, replacing the queued ones.</summary>
        public void Interrupt(string prompt, int frames)
        {
            if (prompt == null)
                throw new ArgumentNullException("prompt");
            if (frames < 0)
                throw new ArgumentOutOfRangeException("frames");
            FlameException.Check(FlameNative.flame_stream_interrupt(Handle, FlameNative.Utf8Z(prompt), (uint)frames));
        }

        /// <summary>Appends a segment with part texts: a Stage (as SetPromptStages takes them) of
        /// stage.Frames frames. FineMoGen reads the part texts (each chunk of the segment is one
        /// stage with them); other models take a stage without part texts as Push(stage.Text,
        /// stage.Frames) and refuse part texts with InvalidArgument from the Pump that starts the
        /// segment.</summary>
        public void PushStage(Stage stage)
        {
            WithStage(stage, raw => FlameNative.flame_stream_push_stage(Handle, ref raw));
        }

        /// <summary>Interrupt with part texts (see PushStage).</summary>
        public void InterruptStage(Stage stage)
        {
            WithStage(stage, raw => FlameNative.flame_stream_interrupt_stage(Handle, ref raw));
        }

        delegate FlameStatus StageCall(FlameStage raw);

        static void WithStage(Stage stage, StageCall call)
        {
            if (stage == null)
                throw new ArgumentNullException("stage");
            var pins = new List<GCHandle>();
            try
            {
                FlameException.Check(call(FlameSession.NativeStage(stage, "stage", pins)));
            }
            finally
            {
                foreach (var pin in pins)
                    pin.Free();
            }
        }

        /// <summary>Asks the Pump running on another thread to stop: it throws with status
        /// Cancelled within one transformer layer, and the step it was running leaves no trace,
        /// so pumping again gives the frames of a stream never cancelled. With no pump running,
        /// the next Pump's first step is cancelled. Any thread.</summary>
        public void Cancel()
        {
            FlameException.Check(FlameNative.flame_stream_cancel(Handle));
        }

        public void SetPlayhead(ulong frame)
        {
            FlameException.Check(FlameNative.flame_stream_set_playhead(Handle, frame));
        }

        /// <summary>Runs at most maxSteps denoiser steps (uint.MaxValue: as many as needed)
        /// towards the lookahead. Throws with status Cancelled when Cancel stopped it; pump again
        /// to go on.</summary>
        public FlameStreamStatus Pump(uint maxSteps)
        {
            var st = new FlameStreamStatus { struct_size = (uint)Marshal.SizeOf(typeof(FlameStreamStatus)) };
            FlameException.Check(FlameNative.flame_stream_pump(Handle, maxSteps, ref st));
            return st;
        }

        public FlameStreamStatus Status()
        {
            var st = new FlameStreamStatus { struct_size = (uint)Marshal.SizeOf(typeof(FlameStreamStatus)) };
            FlameException.Check(FlameNative.flame_stream_status(Handle, ref st));
            return st;
        }

        /// <summary>Timeline frames firstFrame..firstFrame+count in a layout and convention,
        /// frame-major (layout 0: model-space features).</summary>
        public float[] Read(ulong firstFrame, uint count, int layout, int convention)
        {
            UIntPtr n;
            FlameException.Check(FlameNative.flame_stream_read(Handle, firstFrame, count, layout, convention, 0, null, UIntPtr.Zero, out n));
            var output = new float[(int)n];
            FlameException.Check(FlameNative.flame_stream_read(Handle, firstFrame, count, layout, convention, 0, output, n, out n));
            return output;
        }

        /// <summary>flame_stream_read_cleaned: the post-processed poses of frames firstFrame..,
        /// a frame readable once its cleanup is final (WRONG_STATE before: pump more, or
        /// EndTimeline). The first cleaned read sets the stream's cleanup for good; with a frame
        /// rate, frames count at that rate.</summary>
        public float[] Read(ulong firstFrame, uint count, int layout, int convention, FlameCleanupParams cleanup)
        {
            UIntPtr n;
            FlameException.Check(FlameNative.flame_stream_read_cleaned(Handle, firstFrame, count, layout, convention, ref cleanup, null, UIntPtr.Zero, out n));
            var output = new float[(int)n];
            FlameException.Check(FlameNative.flame_stream_read_cleaned(Handle, firstFrame, count, layout, convention, ref cleanup, output, n, out n));
            return output;
        }

        /// <summary>flame_stream_close: the timeline is complete (Push and Interrupt fail with
        /// WRONG_STATE afterwards); once the pushed segments are generated, every frame's cleanup
        /// settles.</summary>
        public void EndTimeline()
        {
            FlameException.Check(FlameNative.flame_stream_close(Handle));
        }

        /// <summary>flame_stream_close_looped: EndTimeline, and the timeline loops. After the
        /// pushed segments the stream generates a bridge of bridgeFrames frames (the last
        /// segment's prompt) whose end runs into the timeline's first frames, moved by the loop's
        /// root motion, as `flame generate --loop` closes a clip: playing frame 0 after the last
        /// continues the motion. Frames already generated never change; the timeline grows by
        /// bridgeFrames (two chunks' steps more to pump), and cleaned reads settle to its end.
        /// Throws with InvalidArgument for a latent model (MLD, MoLA) and for a bridge shorter
        /// than 1 s or longer than the model's frames allow (overlap + bridge + 0.5 s), with
        /// WrongState when the stream is already closed, has no segment or dropped frame
        /// 0.</summary>
        public void EndTimelineLooped(int bridgeFrames)
        {
            if (bridgeFrames < 0)
                throw new ArgumentOutOfRangeException("bridgeFrames");
            FlameException.Check(FlameNative.flame_stream_close_looped(Handle, (uint)bridgeFrames));
        }

        /// <summary>Frees the stream (deferred until a Pump running on another thread returns:
        /// Cancel first so it returns soon).</summary>
        public void Dispose() { Handle.Dispose(); }
    }

    /// <summary>Files of flame_robot_retarget_write (FLAME_ROBOT_*), the quaternion order in
    /// every name.</summary>
    public static class FlameRobotFile
    {
        /// <summary>BeyondMimic's CSV rows: x, y, z, qx, qy, qz, qw, q_1 ... q_n.</summary>
        public const uint BeyondmimicCsvXyzw = 0;
        /// <summary>GMR's fields as an .npz: fps, root_pos, root_rot (x, y, z, w), dof_pos,
        /// joint_names.</summary>
        public const uint GmrNpzXyzw = 1;
        /// <summary>MuJoCo qpos rows as a CSV: x, y, z, qw, qx, qy, qz, joints in MuJoCo's
        /// order.</summary>
        public const uint QposCsvWxyz = 2;
        /// <summary>The same qpos rows as a float64 .npy.</summary>
        public const uint QposNpyWxyz = 3;
        /// <summary>options flag: a "# " line of column names before a CSV's rows.</summary>
        public const uint CsvHeader = 1;
    }

    /// <summary>kind of FlameRig.Load (FLAME_RIG_FORMAT_*): which reader takes the file's bytes.</summary>
    public static class FlameRigFormat
    {
        /// <summary>Told from the bytes: GLB magic "glTF", a JSON object, or BVH's HIERARCHY.</summary>
        public const uint Guess = 0;
        /// <summary>glTF 2.0 (.glb, or .gltf with its buffers as data URIs), VRM 0.x and 1.0 included.</summary>
        public const uint Gltf = 1;
        /// <summary>A BVH file's hierarchy (its MOTION section is not read).</summary>
        public const uint Bvh = 2;
    }

    /// <summary>Mirror of the C struct FlameRigBone: one bone of flame_rig_from_bones, its rest
    /// transform relative to its parent (T · R · S: Unity's localPosition, localRotation,
    /// localScale; Unreal's reference pose) in the convention the call names. The C struct's
    /// arrays translation[3], rotation[4] (x, y, z, w) and scale[3] are single floats here, so
    /// the struct stays blittable and an array of them crosses without copying: a uint and an
    /// int, a pointer, then ten floats (56 bytes on 64-bit targets, 52 on 32-bit). Use
    /// FlameRig.FromBones with RigBone values, which fills it and pins the names.</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameRigBone
    {
        public uint struct_size;
        /// <summary>Index of the parent in the same array (any order), -1 for a root.</summary>
        public int parent;
        /// <summary>A unique NUL-terminated UTF-8 name, read only during the call.</summary>
        public IntPtr name;
        public float translation_x, translation_y, translation_z;
        public float rotation_x, rotation_y, rotation_z, rotation_w;
        public float scale_x, scale_y, scale_z;
    }

    /// <summary>Mirror of the C struct FlameRetargetParams: how FlameRetarget.Create drives a
    /// rig. Four 32-bit fields then a pointer (24 bytes on 64-bit targets, 20 on 32-bit). Start
    /// from Default(): the rig's own convention, feet IK on, hands IK off, the automatic bone
    /// map; set the map through FlameRetarget.Create(..., map).</summary>
    [StructLayout(LayoutKind.Sequential)]
    public struct FlameRetargetParams
    {
        public uint struct_size;
        /// <summary>A FlameConvention value for the poses read: Native (0) = the rig's own (the
        /// engine's convention for FromBones, glTF axes in metres for a glTF/VRM file).</summary>
        public int convention;
        /// <summary>1: two-bone IK on the legs puts each ankle where the source's is (a rig of
        /// other proportions keeps planted feet planted).</summary>
        public uint feet;
        /// <summary>1: the same on the arms, for the wrists.</summary>
        public uint hands;
        /// <summary>A FlameBoneMap*, or IntPtr.Zero for the automatic map.</summary>
        public IntPtr map;

        public static FlameRetargetParams Default()
        {
            FlameRetargetParams p;
            FlameException.Check(FlameNative.flame_retarget_params_default(out p));
            return p;
        }
    }

    /// <summary>Every function of include/flame.h. Status-returning functions return the raw
    /// status; wrap them in FlameException.Check right away (the message is per thread and valid
    /// only until the next libflame call on it).</summary>
    public static class FlameNative
    {
#if UNITY_IOS && !UNITY_EDITOR
        public const string Lib = "__Internal";
#else
        public const string Lib = "flame";
#endif
        /// <summary>FLAME_ABI_VERSION of the header these declarations mirror.</summary>
        public const uint AbiVersion = 4;
        /// <summary>FLAME_MAX_THREADS: the most worker threads a load or a session may ask for.</summary>
        public const uint MaxThreads = 256;
        /// <summary>FLAME_ROOT_TRANSLATION: the root translation in flame_session_keep_joints.</summary>
        public const int RootTranslation = -1;

        const CallingConvention Cdecl = CallingConvention.Cdecl;

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern uint flame_abi_version();

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern IntPtr flame_version_string();

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_model_params_default(out FlameModelParams p);

        /// <param name="path">NUL-terminated UTF-8 (see Utf8Z).</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_model_load(byte[] path, ref FlameModelParams p, out FlameModelHandle model);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_model_load_from_memory(byte[] bytes, UIntPtr len, ref FlameModelParams p, out FlameModelHandle model);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern void flame_model_free(IntPtr model);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_model_info(FlameModelHandle model, ref FlameModelInfo info);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_params_default(out FlameSessionParams p);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_edit_params_default(out FlameEditParams p);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_edit_params(FlameSessionHandle session, ref FlameEditParams p);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_target_params_default(out FlameTargetParams p);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_target_params(FlameSessionHandle session, ref FlameTargetParams p);

        [DllImport(Lib, CallingConvention = CallingConvention.Cdecl)]
        public static extern FlameStatus flame_session_target_params(FlameSessionHandle session, out FlameTargetParams p);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_position_targets(FlameSessionHandle session, float[] targets, UIntPtr targetsLen,
                                                                            byte[] mask, UIntPtr maskLen, int convention);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_clear_position_targets(FlameSessionHandle session);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_control(FlameSessionHandle session, float[] positions, UIntPtr positionsLen,
                                                                   byte[] mask, UIntPtr maskLen, int convention);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_clear_control(FlameSessionHandle session);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_tune_latent(FlameSessionHandle session, uint iterations,
                                                                   ref FlameTuningReport report);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_target_loss(FlameSessionHandle session, out double loss);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_new(FlameModelHandle model, ref FlameSessionParams p, out FlameSessionHandle session);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern void flame_session_free(IntPtr session);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_reset(FlameSessionHandle session);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_prompt(FlameSessionHandle session, byte[] prompt);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_prompt_from(FlameSessionHandle session, FlameSessionHandle source);

        /// <param name="stages">count FlameStage values, their strings valid for the call.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_prompt_stages(FlameSessionHandle session, [In] FlameStage[] stages, UIntPtr count);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_prompt_info(FlameSessionHandle session, ref FlamePromptInfo info);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_noise(FlameSessionHandle session, float[] noise, UIntPtr len);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_reference(FlameSessionHandle session, float[] features, uint frames, uint dim);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_mask(FlameSessionHandle session, byte[] mask, uint frames, uint dim);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_keep_frames(FlameSessionHandle session, uint start, uint end);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_keep_joints(FlameSessionHandle session, int[] joints, UIntPtr count);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_keep_part(FlameSessionHandle session, int part, uint start, uint end);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_task_mask(FlameSessionHandle session, int task);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_task_targets(FlameSessionHandle session, float[] features, uint frames, uint dim, int task);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_reference_poses(FlameSessionHandle session, float[] root, UIntPtr rootLen,
                                                                           float[] rotations, UIntPtr rotationsLen, uint frames,
                                                                           int layout, int convention);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_clear_edit(FlameSessionHandle session);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_set_progress_callback(FlameSessionHandle session, ProgressCallback callback, IntPtr userData);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_step(FlameSessionHandle session, out uint stepsLeft);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_cancel(FlameSessionHandle session);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_progress(FlameSessionHandle session, out uint stepsDone, out uint stepsTotal);

        /// <param name="output">NULL (null) to query the length into outLen.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_read(FlameSessionHandle session, int which, int layout, int convention, uint flags,
                                                            [Out] float[] output, UIntPtr len, out UIntPtr outLen);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_params_default(out FlameStreamParams p);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_new(FlameModelHandle model, ref FlameStreamParams p, out FlameStreamHandle stream);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern void flame_stream_free(IntPtr stream);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_push(FlameStreamHandle stream, byte[] prompt, uint frames);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_interrupt(FlameStreamHandle stream, byte[] prompt, uint frames);

        /// <param name="stage">its strings valid for the call.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_push_stage(FlameStreamHandle stream, ref FlameStage stage);

        /// <param name="stage">its strings valid for the call.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_interrupt_stage(FlameStreamHandle stream, ref FlameStage stage);

        /// <summary>Any thread, even while another is inside flame_stream_pump.</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_cancel(FlameStreamHandle stream);

        // The batch runner (docs/batch.md): declared so that every function of flame.h is
        // reachable; the C# wrapper has no class over it yet. FlameBatch* is an IntPtr here.
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_batch_params_default(out FlameBatchParams p);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_batch_new(FlameModelHandle model, out IntPtr batch);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern void flame_batch_free(IntPtr batch);

        /// <param name="jobsPath">UTF-8, NUL-terminated (Utf8Z).</param>
        /// <param name="manifestPath">UTF-8, NUL-terminated (Utf8Z).</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_batch_run(IntPtr batch, byte[] jobsPath, byte[] manifestPath,
                                                         ref FlameBatchParams p, ref FlameBatchSummary summary);

        /// <summary>Any thread, even while another is inside flame_batch_run.</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_batch_cancel(IntPtr batch);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_set_playhead(FlameStreamHandle stream, ulong frame);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_pump(FlameStreamHandle stream, uint maxSteps, ref FlameStreamStatus status);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_status(FlameStreamHandle stream, ref FlameStreamStatus status);

        /// <param name="output">NULL (null) to query the length into outLen.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_read(FlameStreamHandle stream, ulong firstFrame, uint count, int layout, int convention, uint flags,
                                                           [Out] float[] output, UIntPtr len, out UIntPtr outLen);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_read_cleaned(FlameStreamHandle stream, ulong firstFrame, uint count, int layout, int convention,
                                                                   ref FlameCleanupParams cleanup, [Out] float[] output, UIntPtr len, out UIntPtr outLen);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_close(FlameStreamHandle stream);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_stream_close_looped(FlameStreamHandle stream, uint bridgeFrames);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_cleanup_params_default(out FlameCleanupParams p);

        /// <summary>flame_session_read with a cleanup (the frame count follows its fps: query the
        /// length with output null).</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_read_cleaned(FlameSessionHandle session, int which, int layout, int convention, uint flags,
                                                                    ref FlameCleanupParams cleanup, [Out] float[] output, UIntPtr len, out UIntPtr outLen);

        /// <summary>The same with a NULL cleanup (IntPtr.Zero): exactly flame_session_read.</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_read_cleaned(FlameSessionHandle session, int which, int layout, int convention, uint flags,
                                                                    IntPtr cleanup, [Out] float[] output, UIntPtr len, out UIntPtr outLen);

        /// <summary>The sample or estimate as an AMASS-style .npz (layout a FlameAmassLayout
        /// value); output null queries the size in bytes into outLen.</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_write_amass(FlameSessionHandle session, int which, int layout, uint flags,
                                                                   ref FlameCleanupParams cleanup, [Out] byte[] output, UIntPtr len, out UIntPtr outLen);

        /// <summary>The same with a NULL cleanup (IntPtr.Zero): the raw poses.</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_write_amass(FlameSessionHandle session, int which, int layout, uint flags,
                                                                   IntPtr cleanup, [Out] byte[] output, UIntPtr len, out UIntPtr outLen);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_gltf_params_default(out FlameGltfParams p);

        /// <param name="output">null to query the file's size in bytes into outLen; too short:
        /// BufferTooSmall, with the size in outLen.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_write_gltf(FlameSessionHandle session, int which, ref FlameGltfParams p,
                                                                  [Out] byte[] output, UIntPtr len, out UIntPtr outLen);

        /// <summary>rows × dim of the sampled space (what flame_session_set_noise takes).</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_sample_shape(FlameSessionHandle session, out uint rows, out uint dim);

        /// <summary>Frames a flame_session_read of which returns now.</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_session_read_frames(FlameSessionHandle session, int which, out uint frames);

        // --- retargeting onto a user's rig (flame_rig_*, flame_bone_map_*, flame_retarget_*) ---

        /// <param name="skin">NUL-terminated UTF-8 glTF skin name, or null for the file's only one.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_rig_load(byte[] bytes, UIntPtr len, uint kind, byte[] skin, out FlameRigHandle rig);

        /// <param name="bones">count bones whose names stay valid (pinned) for the call.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_rig_from_bones([In] FlameRigBone[] bones, UIntPtr count, int convention, out FlameRigHandle rig);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern void flame_rig_free(IntPtr rig);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_rig_bone_count(FlameRigHandle rig, out UIntPtr count);

        /// <param name="name">receives a NUL-terminated UTF-8 name owned by the rig.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_rig_bone_name(FlameRigHandle rig, UIntPtr bone, out IntPtr name);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_rig_bone_parent(FlameRigHandle rig, UIntPtr bone, out int parent);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_bone_map_auto(FlameRigHandle rig, out FlameBoneMapHandle map);

        /// <param name="json">NUL-terminated UTF-8.</param>
        /// <param name="baseMap">a map of the same rig under the JSON's keys, or IntPtr.Zero.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_bone_map_from_json(FlameRigHandle rig, byte[] json, IntPtr baseMap, out FlameBoneMapHandle map);

        /// <param name="buf">null to query the size (the NUL included) into len.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_bone_map_to_json(FlameBoneMapHandle map, FlameRigHandle rig, [Out] byte[] buf, UIntPtr cap, out UIntPtr len);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern void flame_bone_map_free(IntPtr map);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_retarget_params_default(out FlameRetargetParams p);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_retarget_new(FlameModelHandle model, FlameRigHandle rig, ref FlameRetargetParams p, out FlameRetargetHandle retarget);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern void flame_retarget_free(IntPtr retarget);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_retarget_bone_count(FlameRetargetHandle retarget, out UIntPtr count);

        /// <param name="rotations">null when not wanted; count × bones × 4 floats otherwise.</param>
        /// <param name="translations">null when not wanted; count × bones × 3 floats otherwise.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_retarget_read(FlameRetargetHandle retarget, FlameSessionHandle session, int which, uint flags,
                                                             ref FlameCleanupParams cleanup, UIntPtr first, UIntPtr count,
                                                             [Out] float[] rotations, UIntPtr rotationsLen,
                                                             [Out] float[] translations, UIntPtr translationsLen, out UIntPtr frames);

        /// <summary>The same with a NULL cleanup (IntPtr.Zero): the raw poses.</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_retarget_read(FlameRetargetHandle retarget, FlameSessionHandle session, int which, uint flags,
                                                             IntPtr cleanup, UIntPtr first, UIntPtr count,
                                                             [Out] float[] rotations, UIntPtr rotationsLen,
                                                             [Out] float[] translations, UIntPtr translationsLen, out UIntPtr frames);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_retarget_read_stream(FlameRetargetHandle retarget, FlameStreamHandle stream, ulong firstFrame, uint count,
                                                                    ref FlameCleanupParams cleanup,
                                                                    [Out] float[] rotations, UIntPtr rotationsLen,
                                                                    [Out] float[] translations, UIntPtr translationsLen);

        /// <summary>The same with a NULL cleanup: the stream's raw frames.</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_retarget_read_stream(FlameRetargetHandle retarget, FlameStreamHandle stream, ulong firstFrame, uint count,
                                                                    IntPtr cleanup,
                                                                    [Out] float[] rotations, UIntPtr rotationsLen,
                                                                    [Out] float[] translations, UIntPtr translationsLen);

        /// <param name="sourceWorld">joints × 4 world quaternions x, y, z, w (glTF axes).</param>
        /// <param name="sourcePositions">joints × 3 joint positions (glTF axes, metres).</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_retarget_pose(FlameRetargetHandle retarget, float[] sourceWorld, UIntPtr sourceWorldLen,
                                                             float[] sourcePositions, UIntPtr sourcePositionsLen,
                                                             [Out] float[] rotations, UIntPtr rotationsLen,
                                                             [Out] float[] translations, UIntPtr translationsLen);

        // --- humanoid robots (flame_robot_*): quaternion order in every name ---

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_robot_load(byte[] urdf, UIntPtr len, out FlameRobotHandle robot);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern void flame_robot_free(IntPtr robot);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_robot_dof_count(FlameRobotHandle robot, out UIntPtr count);

        /// <param name="name">receives a NUL-terminated UTF-8 joint name owned by the robot.</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_robot_dof_name(FlameRobotHandle robot, UIntPtr index, out IntPtr name);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_robot_name(FlameRobotHandle robot, out IntPtr name);

        /// <param name="configJson">the retarget configuration's UTF-8 JSON (robots/&lt;name&gt;.json).</param>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_robot_retarget_new(FlameRobotHandle robot, byte[] configJson, UIntPtr len,
                                                                  out FlameRobotRetargetHandle retarget);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern void flame_robot_retarget_free(IntPtr retarget);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_robot_retarget_dof_count(FlameRobotRetargetHandle retarget, out UIntPtr count);

        /// <summary>A session's whole clip on the robot as a file (file a FlameRobotFile value,
        /// options FlameRobotFile.CsvHeader or 0); output null queries the size into outLen.</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_robot_retarget_write(FlameRobotRetargetHandle retarget, FlameSessionHandle session, int which,
                                                                    uint flags, ref FlameCleanupParams cleanup, uint file, uint options,
                                                                    [Out] byte[] output, UIntPtr len, out UIntPtr outLen);

        /// <summary>The same with a NULL cleanup (IntPtr.Zero): the raw poses.</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_robot_retarget_write(FlameRobotRetargetHandle retarget, FlameSessionHandle session, int which,
                                                                    uint flags, IntPtr cleanup, uint file, uint options,
                                                                    [Out] byte[] output, UIntPtr len, out UIntPtr outLen);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_robot_state_new(FlameRobotRetargetHandle retarget, out FlameRobotStateHandle state);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern void flame_robot_state_free(IntPtr state);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_robot_state_reset(FlameRobotStateHandle state);

        /// <summary>Session frames first..first+count solved in order from state: per frame the
        /// root position [3], root quaternion x, y, z, w [4], joints [n], residual [1]; any
        /// output may be null.</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_robot_retarget_read(FlameRobotRetargetHandle retarget, FlameRobotStateHandle state,
                                                                   FlameSessionHandle session, int which, uint flags, IntPtr cleanup,
                                                                   UIntPtr first, UIntPtr count,
                                                                   [Out] double[] rootPos, UIntPtr rootPosLen,
                                                                   [Out] double[] rootRotXyzw, UIntPtr rootRotLen,
                                                                   [Out] double[] q, UIntPtr qLen,
                                                                   [Out] double[] residual, UIntPtr residualLen, out UIntPtr frames);

        /// <summary>flame_robot_retarget_read for a stream's timeline frames (cleanup may be
        /// IntPtr.Zero or a pinned FlameCleanupParams).</summary>
        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern FlameStatus flame_robot_retarget_read_stream(FlameRobotRetargetHandle retarget, FlameRobotStateHandle state,
                                                                          FlameStreamHandle stream, ulong firstFrame, uint count,
                                                                          IntPtr cleanup,
                                                                          [Out] double[] rootPos, UIntPtr rootPosLen,
                                                                          [Out] double[] rootRotXyzw, UIntPtr rootRotLen,
                                                                          [Out] double[] q, UIntPtr qLen,
                                                                          [Out] double[] residual, UIntPtr residualLen);

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern IntPtr flame_last_error();

        [DllImport(Lib, CallingConvention = Cdecl)]
        public static extern IntPtr flame_status_string(int status);

        /// <summary>A NUL-terminated UTF-8 copy of s (null stays null, i.e. NULL).</summary>
        public static byte[] Utf8Z(string s)
        {
            if (s == null)
                return null;
            var bytes = new byte[Encoding.UTF8.GetByteCount(s) + 1];
            Encoding.UTF8.GetBytes(s, 0, s.Length, bytes, 0);
            return bytes;
        }

        /// <summary>Decodes a NUL-terminated UTF-8 string (NULL gives "").</summary>
        public static string Utf8(IntPtr p)
        {
            if (p == IntPtr.Zero)
                return "";
            int n = 0;
            while (Marshal.ReadByte(p, n) != 0)
                n++;
            var bytes = new byte[n];
            Marshal.Copy(p, bytes, 0, n);
            return Encoding.UTF8.GetString(bytes);
        }
    }

    /// <summary>A failed libflame call: its status and flame_last_error()'s message.</summary>
    public class FlameException : Exception
    {
        public FlameStatus Status { get; private set; }
        /// <summary>flame_last_error() as it was right after the failing call.</summary>
        public string NativeMessage { get; private set; }

        public FlameException(FlameStatus status, string message)
            : base(FlameNative.Utf8(FlameNative.flame_status_string((int)status)) + ": " + message)
        {
            Status = status;
            NativeMessage = message;
        }

        /// <summary>Throws for a non-OK status. Call it on the thread that made the call, before
        /// any other libflame call there: the message is per thread and is overwritten.</summary>
        public static void Check(FlameStatus status)
        {
            if (status != FlameStatus.Ok)
                throw new FlameException(status, FlameNative.Utf8(FlameNative.flame_last_error()));
        }
    }

    /// <summary>The library as a whole.</summary>
    public static class FlameLibrary
    {
        public static string Version { get { return FlameNative.Utf8(FlameNative.flame_version_string()); } }

        /// <summary>Throws when the loaded library's ABI is not the one these bindings mirror.</summary>
        public static void CheckAbi()
        {
            uint abi = FlameNative.flame_abi_version();
            if (abi != FlameNative.AbiVersion)
                throw new InvalidOperationException("libflame ABI version " + abi + " does not match the bindings' " + FlameNative.AbiVersion);
        }
    }

    /// <summary>A managed copy of FlameModelInfo.</summary>
    public sealed class ModelInfo
    {
        public int FeatureDim, JointCount, MaxFrames, DefaultFrames, DefaultSteps, NumTimesteps;
        public FlameSampler DefaultSampler;
        public float Fps, DefaultGuidance, DefaultEta;
        public string Architecture, MotionFormat, TextEncoder;
        public string[] JointNames;
        public int[] JointParents;
        /// <summary>The model samples a latent that its decoder turns into motion (MoLA): a
        /// read's frames are FlameSession.ReadFrames, and masks and references do not apply.</summary>
        public bool Latent;
        /// <summary>Channels per row of the sampled space (FeatureDim, or the latent's channels).</summary>
        public int SampleDim;
        /// <summary>The model has a trajectory ControlNet: FlameSession.SetControl applies.</summary>
        public bool Control;

        internal ModelInfo(FlameModelInfo i)
        {
            Latent = i.latent != 0;
            Control = i.control != 0;
            SampleDim = (int)i.sample_dim;
            FeatureDim = (int)i.feature_dim;
            JointCount = (int)i.joint_count;
            MaxFrames = (int)i.max_frames;
            DefaultFrames = (int)i.default_frames;
            DefaultSteps = (int)i.default_steps;
            NumTimesteps = (int)i.num_timesteps;
            DefaultSampler = (FlameSampler)i.default_sampler;
            Fps = i.fps;
            DefaultGuidance = i.default_guidance;
            DefaultEta = i.default_eta;
            Architecture = i.Architecture;
            MotionFormat = i.MotionFormat;
            TextEncoder = i.TextEncoder;
            JointNames = i.JointNames();
            JointParents = i.JointParents();
        }
    }

    /// <summary>A managed copy of FlamePromptInfo: what the last prompt became.</summary>
    public sealed class PromptInfo
    {
        /// <summary>Tokens of the whole prompt and those the text encoder kept (at most
        /// Window), special tokens included.</summary>
        public int Tokens, Kept, Window;
        /// <summary>The window cut the prompt: the encoder ignored Dropped.</summary>
        public bool Truncated;
        /// <summary>The prompt was empty or blank: generation without text.</summary>
        public bool Unconditional;
        /// <summary>The text cut off ("" when nothing was).</summary>
        public string Dropped;

        internal PromptInfo(FlamePromptInfo i)
        {
            Tokens = (int)i.tokens;
            Kept = (int)i.kept;
            Window = (int)i.window;
            Truncated = i.truncated != 0;
            Unconditional = i.unconditional != 0;
            Dropped = FlameNative.Utf8(i.dropped);
        }
    }

    /// <summary>A loaded model: immutable, shareable by any number of sessions and threads.
    /// Sessions keep it alive natively, so disposing it does not invalidate them.</summary>
    public sealed class FlameModel : IDisposable
    {
        public FlameModelHandle Handle { get; private set; }
        /// <summary>Copied at load.</summary>
        public ModelInfo Info { get; private set; }

        FlameModel(FlameModelHandle handle)
        {
            Handle = handle;
            var raw = new FlameModelInfo();
            raw.struct_size = (uint)Marshal.SizeOf(typeof(FlameModelInfo));
            FlameException.Check(FlameNative.flame_model_info(handle, ref raw));
            Info = new ModelInfo(raw);
        }

        /// <summary>Loads a model file; threads are for work at load (0 = one per core), weights
        /// what the linear layers are held in.</summary>
        public static FlameModel Load(string path, uint threads = 0, FlameWeights weights = FlameWeights.F32)
        {
            if (path == null)
                throw new ArgumentNullException("path");
            FlameLibrary.CheckAbi();
            var p = FlameModelParams.Default();
            p.threads = threads;
            p.weights = weights;
            FlameModelHandle h;
            FlameException.Check(FlameNative.flame_model_load(FlameNative.Utf8Z(path), ref p, out h));
            return new FlameModel(h);
        }

        /// <summary>Loads a model from the bytes of a model file (copied; e.g. a TextAsset's bytes).</summary>
        public static FlameModel LoadFromMemory(byte[] bytes, uint threads = 0, FlameWeights weights = FlameWeights.F32)
        {
            if (bytes == null)
                throw new ArgumentNullException("bytes");
            FlameLibrary.CheckAbi();
            var p = FlameModelParams.Default();
            p.threads = threads;
            p.weights = weights;
            FlameModelHandle h;
            FlameException.Check(FlameNative.flame_model_load_from_memory(bytes, (UIntPtr)bytes.Length, ref p, out h));
            return new FlameModel(h);
        }

        /// <summary>Starts a generation with the model file's defaults.</summary>
        public FlameSession NewSession()
        {
            return NewSession(FlameSessionParams.Default());
        }

        /// <summary>Starts a generation; start p from FlameSessionParams.Default().</summary>
        public FlameSession NewSession(FlameSessionParams p)
        {
            FlameSessionHandle h;
            FlameException.Check(FlameNative.flame_session_new(Handle, ref p, out h));
            int frames = p.frames != 0 ? (int)p.frames : Info.DefaultFrames;
            return new FlameSession(h, frames, Info.FeatureDim, Info.JointCount, Info.Fps);
        }

        /// <summary>Starts a generation whose training steps a guided-diffusion respacing string
        /// picks: "ddim50" (every 20th of 1000), "50" (50 evenly spread) or section counts
        /// "15,15,8,6,6"; null = none. It sets the step count (a nonzero p.steps must agree).
        /// FLAME and MDM models take it; flow models and models with diffusers spacing (MoLA,
        /// MLD) refuse it (InvalidArgument).</summary>
        public FlameSession NewSession(FlameSessionParams p, string respacing)
        {
            var bytes = FlameNative.Utf8Z(respacing);
            if (bytes == null)
                return NewSession(p);
            var pin = GCHandle.Alloc(bytes, GCHandleType.Pinned);
            try
            {
                p.respacing = pin.AddrOfPinnedObject();
                return NewSession(p);
            }
            finally
            {
                pin.Free();
            }
        }

        public void Dispose()
        {
            Handle.Dispose();
        }
    }

    /// <summary>One generation. See the file's header for the threading rules.</summary>
    public sealed class FlameSession : IDisposable
    {
        // One static delegate for every session (IL2CPP needs a static, attributed method; the
        // field keeps the delegate alive); user_data names the session through a weak GCHandle.
        static readonly ProgressCallback Trampoline = OnProgress;

        public FlameSessionHandle Handle { get; private set; }
        /// <summary>Frames this session was asked for (what a reference or mask spans; a loop's
        /// cycle, FlameSessionParams.looped). A read's frames are ReadFrames: the same (a
        /// finished loop reads as its cycle), except for a latent model, whose decoder decides
        /// the valid length.</summary>
        public int Frames { get; private set; }
        /// <summary>Feature channels per frame.</summary>
        public int FeatureDim { get; private set; }
        /// <summary>Joints of the model's skeleton (ModelInfo.JointCount).</summary>
        public int JointCount { get; private set; }
        /// <summary>The model's frame rate (ModelInfo.Fps): what a read without a cleanup's fps
        /// plays at.</summary>
        public float Fps { get; private set; }

        Action<int, int> progress;
        Exception callbackError;

        internal FlameSession(FlameSessionHandle handle, int frames, int featureDim, int jointCount, float fps)
        {
            Handle = handle;
            Frames = frames;
            FeatureDim = featureDim;
            JointCount = jointCount;
            Fps = fps;
        }

        public void SetPrompt(string prompt)
        {
            if (prompt == null)
                throw new ArgumentNullException("prompt");
            FlameException.Check(FlameNative.flame_session_set_prompt(Handle, FlameNative.Utf8Z(prompt)));
        }

        /// <summary>Sets the prompt <paramref name="source"/> was given, as encoded there, without
        /// running the text encoder again: a prompt used for many generations is encoded once
        /// (MotionLCM's T5-large takes 75–85 ms a prompt on 2 cores). The source must be a
        /// session of the same FlameModel with a prompt.</summary>
        public void SetPromptFrom(FlameSession source)
        {
            if (source == null)
                throw new ArgumentNullException("source");
            FlameException.Check(FlameNative.flame_session_set_prompt_from(Handle, source.Handle));
        }

        /// <summary>Sets prompts per time stage, in order; their Frames must add up to Frames. A
        /// FineMoGen model composes them: its sample is then laid out stages × the longest stage
        /// rows (SampleShape, and what SetNoise takes), while Read still returns Frames frames,
        /// the stages one after the other. Any other model takes exactly one stage without part
        /// texts, as SetPrompt(stage.Text), and refuses more (FlameException, InvalidArgument).
        /// Stage frame counts can change only before the first step (WrongState after; Reset
        /// first); texts may change between steps. The strings are copied to pinned UTF-8 for
        /// the call only.</summary>
        public void SetPromptStages(params Stage[] stages)
        {
            if (stages == null)
                throw new ArgumentNullException("stages");
            var raw = new FlameStage[stages.Length];
            var pins = new List<GCHandle>();
            try
            {
                for (int i = 0; i < stages.Length; i++)
                    raw[i] = NativeStage(stages[i], "stages[" + i + "]", pins);
                FlameException.Check(FlameNative.flame_session_set_prompt_stages(Handle, raw, (UIntPtr)raw.Length));
            }
            finally
            {
                foreach (var pin in pins)
                    pin.Free();
            }
        }

        /// <summary>st as a FlameStage whose strings are pinned UTF-8 (name names it in
        /// exceptions), their handles added to pins for the caller to free.</summary>
        internal static FlameStage NativeStage(Stage st, string name, List<GCHandle> pins)
        {
            if (st == null)
                throw new ArgumentNullException(name);
            if (st.Text == null)
                throw new ArgumentNullException(name + ".Text");
            if (st.Frames < 0)
                throw new ArgumentOutOfRangeException(name + ".Frames", st.Frames, "a stage's frames cannot be negative");
            var raw = new FlameStage();
            raw.struct_size = (uint)Marshal.SizeOf(typeof(FlameStage));
            raw.frames = (uint)st.Frames;
            raw.text = Pin(st.Text, name + ".Text", pins);
            raw.head = Pin(st.Head, name + ".Head", pins);
            raw.stem = Pin(st.Stem, name + ".Stem", pins);
            raw.left_arm = Pin(st.LeftArm, name + ".LeftArm", pins);
            raw.right_arm = Pin(st.RightArm, name + ".RightArm", pins);
            raw.left_leg = Pin(st.LeftLeg, name + ".LeftLeg", pins);
            raw.right_leg = Pin(st.RightLeg, name + ".RightLeg", pins);
            raw.pelvis = Pin(st.Pelvis, name + ".Pelvis", pins);
            return raw;
        }

        /// <summary>s as pinned NUL-terminated UTF-8 (IntPtr.Zero for null), its handle added to
        /// pins for the caller to free.</summary>
        static IntPtr Pin(string s, string name, List<GCHandle> pins)
        {
            if (s == null)
                return IntPtr.Zero;
            if (s.IndexOf('\0') >= 0)
                throw new ArgumentException(name + " contains a NUL character", name);
            var pin = GCHandle.Alloc(FlameNative.Utf8Z(s), GCHandleType.Pinned);
            pins.Add(pin);
            return pin.AddrOfPinnedObject();
        }

        /// <summary>How the last prompt fitted the text encoder's window: its tokens, those
        /// kept, and the text cut off when it was too long. Throws FlameException (WrongState)
        /// before a prompt is set.</summary>
        public PromptInfo PromptInfo()
        {
            var raw = new FlamePromptInfo();
            raw.struct_size = (uint)Marshal.SizeOf(typeof(FlamePromptInfo));
            FlameException.Check(FlameNative.flame_session_prompt_info(Handle, ref raw));
            return new PromptInfo(raw);  // copies `dropped` before the session can free it
        }

        /// <summary>Sets x_T: rows × dim floats of SampleShape (Frames × FeatureDim, or a latent
        /// model's latent), frame-major; before the first step only.</summary>
        public void SetNoise(float[] noise)
        {
            if (noise == null)
                throw new ArgumentNullException("noise");
            FlameException.Check(FlameNative.flame_session_set_noise(Handle, noise, (UIntPtr)noise.Length));
        }

        /// <summary>The reference motion for editing, Frames × FeatureDim floats.</summary>
        public void SetReference(float[] features)
        {
            SetReference(features, Frames, FeatureDim);
        }

        /// <summary>frames × dim floats: the model's dim and 1..Frames frames (the frames past a
        /// shorter reference cannot be kept).</summary>
        public void SetReference(float[] features, int frames, int dim)
        {
            CheckLength(features, features == null ? 0 : features.Length, frames, dim, "features");
            FlameException.Check(FlameNative.flame_session_set_reference(Handle, features, (uint)frames, (uint)dim));
        }

        /// <summary>Position targets for an editing task from a reference motion (frames ×
        /// FeatureDim model-space features): its joint positions where the task keeps them
        /// (MoLA's MPGD tasks; how a latent model edits). On a model with a trajectory
        /// ControlNet (a MotionLCM control file) they become the control hint instead.</summary>
        public void SetTaskTargets(float[] features, int frames, FlameEditTask task)
        {
            CheckLength(features, features == null ? 0 : features.Length, frames, FeatureDim, "features");
            FlameException.Check(FlameNative.flame_session_set_task_targets(Handle, features, (uint)frames, (uint)FeatureDim, (int)task));
        }

        /// <summary>The keep-mask, Frames × FeatureDim values: true keeps the reference value.</summary>
        public void SetMask(bool[] mask)
        {
            if (mask == null)
                throw new ArgumentNullException("mask");
            var bytes = new byte[mask.Length];
            for (int i = 0; i < mask.Length; i++)
                bytes[i] = mask[i] ? (byte)1 : (byte)0;
            SetMask(bytes, Frames, FeatureDim);
        }

        public void SetMask(byte[] mask, int frames, int dim)
        {
            CheckLength(mask, mask == null ? 0 : mask.Length, frames, dim, "mask");
            FlameException.Check(FlameNative.flame_session_set_mask(Handle, mask, (uint)frames, (uint)dim));
        }

        /// <summary>Keeps every feature of frames start..end (end exclusive), adding to the mask.</summary>
        public void KeepFrames(int start, int end)
        {
            if (start < 0 || end < 0)
                throw new ArgumentOutOfRangeException(start < 0 ? "start" : "end");
            FlameException.Check(FlameNative.flame_session_keep_frames(Handle, (uint)start, (uint)end));
        }

        /// <summary>Keeps these joints' channels in every frame (FlameNative.RootTranslation for
        /// the root path), adding to the mask.</summary>
        public void KeepJoints(params int[] joints)
        {
            if (joints == null)
                throw new ArgumentNullException("joints");
            FlameException.Check(FlameNative.flame_session_keep_joints(Handle, joints, (UIntPtr)joints.Length));
        }

        /// <summary>Keeps a body part's channels on frames start..end (end exclusive), adding to the mask.</summary>
        public void KeepPart(FlameBodyPart part, int start, int end)
        {
            if (start < 0 || end < 0)
                throw new ArgumentOutOfRangeException(start < 0 ? "start" : "end");
            FlameException.Check(FlameNative.flame_session_keep_part(Handle, (int)part, (uint)start, (uint)end));
        }

        /// <summary>Keeps a body part's channels on every frame, adding to the mask.</summary>
        public void KeepPart(FlameBodyPart part)
        {
            KeepPart(part, 0, Frames);
        }

        /// <summary>Replaces the mask with a standard editing task's.</summary>
        public void SetTaskMask(FlameEditTask task)
        {
            FlameException.Check(FlameNative.flame_session_set_task_mask(Handle, (int)task));
        }

        /// <summary>How the session edits; start p from FlameEditParams.Default(). The library
        /// checks the method against the model.</summary>
        public void SetEditParams(FlameEditParams p)
        {
            FlameException.Check(FlameNative.flame_session_set_edit_params(Handle, ref p));
        }

        /// <summary>A smpl24_6d reference from poses, the inverse of Read: root = frames × 3 pelvis
        /// positions, rotations = frames × 24 local rotations in layout (FlameLayout.LocalQuatXyzw,
        /// LocalQuatWxyz, LocalMatrix or Local6d), both in convention. Frames = root.Length / 3.</summary>
        public void SetReferencePoses(float[] root, float[] rotations, int layout, int convention)
        {
            if (root == null)
                throw new ArgumentNullException("root");
            if (rotations == null)
                throw new ArgumentNullException("rotations");
            if (root.Length % 3 != 0)
                throw new ArgumentException("root has " + root.Length + " values, not frames × 3", "root");
            FlameException.Check(FlameNative.flame_session_set_reference_poses(Handle, root, (UIntPtr)root.Length, rotations,
                                                                               (UIntPtr)rotations.Length, (uint)(root.Length / 3),
                                                                               layout, convention));
        }

        /// <summary>Steers the following steps toward joint positions: targets = frames × joints
        /// × 3 floats (x, y, z per joint of the model's skeleton, frame-major) in convention and
        /// its unit (metres; centimetres for FlameConvention.Unreal), covering the first frames
        /// (1..Frames). A NaN is free, every other value constrained. Replaces earlier targets; on
        /// error nothing changes.</summary>
        public void SetPositionTargets(float[] targets, int convention)
        {
            SetPositionTargets(targets, (byte[])null, convention);
        }

        /// <summary>As SetPositionTargets(targets, convention), with mask = one flag per value of
        /// targets (true = constrained; a free value's number does not matter).</summary>
        public void SetPositionTargets(float[] targets, bool[] mask, int convention)
        {
            if (mask == null)
                throw new ArgumentNullException("mask");
            var bytes = new byte[mask.Length];
            for (int i = 0; i < mask.Length; i++)
                bytes[i] = mask[i] ? (byte)1 : (byte)0;
            SetPositionTargets(targets, bytes, convention);
        }

        /// <summary>mask: one byte per value of targets (nonzero = constrained), or null (NaN =
        /// free).</summary>
        public void SetPositionTargets(float[] targets, byte[] mask, int convention)
        {
            if (targets == null)
                throw new ArgumentNullException("targets");
            FlameException.Check(FlameNative.flame_session_set_position_targets(Handle, targets, (UIntPtr)targets.Length, mask,
                                                                                (UIntPtr)(mask == null ? 0 : mask.Length), convention));
        }

        /// <summary>Removes the position targets: unguided from the next step on.</summary>
        public void ClearPositionTargets()
        {
            FlameException.Check(FlameNative.flame_session_clear_position_targets(Handle));
        }

        /// <summary>Makes the following steps follow joint positions through the model's
        /// trajectory ControlNet (MotionLCM control files; ModelInfo.Control): positions as for
        /// SetPositionTargets, mask one byte per value (nonzero = followed) or null (NaN = free).
        /// On error the earlier control stays.</summary>
        public void SetControl(float[] positions, byte[] mask, int convention)
        {
            if (positions == null)
                throw new ArgumentNullException("positions");
            FlameException.Check(FlameNative.flame_session_set_control(Handle, positions, (UIntPtr)positions.Length, mask,
                                                                       (UIntPtr)(mask == null ? 0 : mask.Length), convention));
        }

        /// <summary>Removes the trajectory control: the prompt alone from the next step on.</summary>
        public void ClearControl()
        {
            FlameException.Check(FlameNative.flame_session_clear_control(Handle));
        }

        /// <summary>Consistency latent tuning (MotionLCM's --optimize): before the first step,
        /// `iterations` Adam iterations (the release runs 400) move the initial latent so that
        /// the 1-step motion made from it follows the control (SetControl) more closely; the
        /// tuned latent becomes the session's initial noise. Needs a prompt, a control and a
        /// 1-step MotionLCM session; Cancel() is seen before every iteration. Costs one forward
        /// and backward pass of the networks per iteration: run it off the game thread.</summary>
        public FlameTuningReport TuneLatent(uint iterations)
        {
            var r = new FlameTuningReport();
            r.struct_size = (uint)Marshal.SizeOf(typeof(FlameTuningReport));
            FlameException.Check(FlameNative.flame_session_tune_latent(Handle, iterations, ref r));
            return r;
        }

        /// <summary>How strongly position targets steer; start p from FlameTargetParams.Default().</summary>
        public void SetTargetParams(FlameTargetParams p)
        {
            FlameException.Check(FlameNative.flame_session_set_target_params(Handle, ref p));
        }

        /// <summary>The session's target params: the family's defaults (0.6; MPGD for latent
        /// models, constant for the others) until SetTargetParams changes them.</summary>
        public FlameTargetParams TargetParams()
        {
            FlameException.Check(FlameNative.flame_session_target_params(Handle, out FlameTargetParams p));
            return p;
        }

        /// <summary>The position targets' loss at the latest step's clean-motion estimate, before
        /// that step's pull: the sum over constrained joints and frames of their distance to the
        /// target, in metres. Throws FlameException (WrongState) before a guided step (none yet
        /// since the targets were set or the session reset, or scale 0).</summary>
        public double TargetLoss()
        {
            double loss;
            FlameException.Check(FlameNative.flame_session_target_loss(Handle, out loss));
            return loss;
        }

        public void ClearEdit()
        {
            FlameException.Check(FlameNative.flame_session_clear_edit(Handle));
        }

        /// <summary>Starts over: same prompt, settings and edit, so the same output follows.</summary>
        public void Reset()
        {
            FlameException.Check(FlameNative.flame_session_reset(Handle));
        }

        /// <summary>Runs one step; returns the steps left. Throws FlameException with status
        /// Cancelled when cancelled (the step may be retried).</summary>
        public int Step()
        {
            callbackError = null;
            uint left;
            FlameException.Check(FlameNative.flame_session_step(Handle, out left));
            var e = callbackError;
            if (e != null)
            {
                callbackError = null;
                throw new InvalidOperationException("the progress callback threw", e);
            }
            return (int)left;
        }

        /// <summary>Asks the step running on another thread (or the next one) to stop. Any thread.</summary>
        public void Cancel()
        {
            FlameException.Check(FlameNative.flame_session_cancel(Handle));
        }

        public int StepsDone { get { uint d, t; Progress(out d, out t); return (int)d; } }
        public int StepsTotal { get { uint d, t; Progress(out d, out t); return (int)t; } }
        public int StepsLeft { get { uint d, t; Progress(out d, out t); return (int)(t - d); } }

        void Progress(out uint done, out uint total)
        {
            FlameException.Check(FlameNative.flame_session_progress(Handle, out done, out total));
        }

        /// <summary>The shape of the sampled space, what SetNoise takes: Frames × FeatureDim, or
        /// a latent model's latent rows × channels.</summary>
        public void SampleShape(out int rows, out int dim)
        {
            uint r, d;
            FlameException.Check(FlameNative.flame_session_sample_shape(Handle, out r, out d));
            rows = (int)r;
            dim = (int)d;
        }

        /// <summary>Frames a Read of which returns now: Frames, or a latent model's valid
        /// length (decided anew after each step). Throws with status WrongState before there
        /// is anything to read.</summary>
        public int ReadFrames(FlameWhich which)
        {
            uint frames;
            FlameException.Check(FlameNative.flame_session_read_frames(Handle, (int)which, out frames));
            return (int)frames;
        }

        /// <summary>Floats Read would return: ReadFrames(which) × the layout's values per frame.</summary>
        public int ReadLength(FlameWhich which, int layout, int convention, uint flags)
        {
            UIntPtr n;
            FlameException.Check(FlameNative.flame_session_read(Handle, (int)which, layout, convention, flags, null, UIntPtr.Zero, out n));
            return (int)n;
        }

        /// <summary>The sample or clean-motion estimate in a layout and convention, frame-major.</summary>
        public float[] Read(FlameWhich which, int layout, int convention, uint flags)
        {
            var output = new float[ReadLength(which, layout, convention, flags)];
            ReadInto(output, which, layout, convention, flags);
            return output;
        }

        /// <summary>Read, and the frames the values span (ReadFrames): the values per frame are
        /// the array's length / frames.</summary>
        public float[] Read(FlameWhich which, int layout, int convention, uint flags, out int frames)
        {
            var output = Read(which, layout, convention, flags);
            frames = ReadFrames(which);  // no step in between: the same read
            return output;
        }

        /// <summary>The final motion's raw features.</summary>
        public float[] Read()
        {
            return Read(FlameWhich.Sample, FlameLayout.Features, FlameConvention.Native, 0);
        }

        /// <summary>Reads into a caller buffer (no allocation); returns the floats written.
        /// Throws with status BufferTooSmall when it is shorter than ReadLength.</summary>
        public int ReadInto(float[] output, FlameWhich which, int layout, int convention, uint flags)
        {
            if (output == null)
                throw new ArgumentNullException("output");
            UIntPtr n;
            FlameException.Check(FlameNative.flame_session_read(Handle, (int)which, layout, convention, flags, output, (UIntPtr)output.Length, out n));
            return (int)n;
        }

        // --- reads with a cleanup (flame_session_read_cleaned) ---------------------------------
        // cleanup null = the raw poses (exactly the reads above). A cleanup's fps changes the
        // frame count: size buffers with ReadLength(..., cleanup), count frames with
        // Read(..., cleanup, out frames). FlameLayout.RootBone needs FlameRootMotion.Separate;
        // FlameLayout.Features is never post-processed.

        static FlameStatus ReadCleaned(FlameSessionHandle h, FlameWhich which, int layout, int convention, uint flags,
                                       FlameCleanupParams? cleanup, float[] output, out UIntPtr n)
        {
            UIntPtr len = output == null ? UIntPtr.Zero : (UIntPtr)output.Length;
            if (cleanup.HasValue)
            {
                var c = cleanup.Value;
                return FlameNative.flame_session_read_cleaned(h, (int)which, layout, convention, flags, ref c, output, len, out n);
            }
            return FlameNative.flame_session_read_cleaned(h, (int)which, layout, convention, flags, IntPtr.Zero, output, len, out n);
        }

        /// <summary>Floats Read(..., cleanup) would return.</summary>
        public int ReadLength(FlameWhich which, int layout, int convention, uint flags, FlameCleanupParams? cleanup)
        {
            UIntPtr n;
            FlameException.Check(ReadCleaned(Handle, which, layout, convention, flags, cleanup, null, out n));
            return (int)n;
        }

        /// <summary>The sample or clean-motion estimate after a cleanup (null: raw), frame-major.</summary>
        public float[] Read(FlameWhich which, int layout, int convention, uint flags, FlameCleanupParams? cleanup)
        {
            var output = new float[ReadLength(which, layout, convention, flags, cleanup)];
            int n = ReadInto(output, which, layout, convention, flags, cleanup);
            if (n != output.Length)
                Array.Resize(ref output, n);
            return output;
        }

        /// <summary>Read(..., cleanup) and the frames it spans: the array's length / the
        /// layout's values per frame (FlameLayout.ValuesPerFrame; for a layout not named
        /// there, ReadFrames when the cleanup keeps the model's frame rate, else 0).</summary>
        public float[] Read(FlameWhich which, int layout, int convention, uint flags, FlameCleanupParams? cleanup, out int frames)
        {
            var output = Read(which, layout, convention, flags, cleanup);
            int width = FlameLayout.ValuesPerFrame(layout, FeatureDim, JointCount);
            if (width > 0)
                frames = output.Length / width;
            else if (!cleanup.HasValue || cleanup.Value.fps == 0 || cleanup.Value.fps == Fps)
                frames = ReadFrames(which);
            else
                frames = 0;
            return output;
        }

        /// <summary>ReadInto after a cleanup (null: raw); returns the floats written.</summary>
        public int ReadInto(float[] output, FlameWhich which, int layout, int convention, uint flags, FlameCleanupParams? cleanup)
        {
            if (output == null)
                throw new ArgumentNullException("output");
            UIntPtr n;
            FlameException.Check(ReadCleaned(Handle, which, layout, convention, flags, cleanup, output, out n));
            return (int)n;
        }

        /// <summary>The sample or clean-motion estimate as an AMASS-style .npz
        /// (flame_session_write_amass), what numpy.load reads: SMPL axis-angles (radians,
        /// parent-relative, the root's global) and trans (metres) in AMASS's Z-up world, float64,
        /// betas 16 zeros, gender "neutral"; layout FlameAmassLayout.Smplh (PHC, human2humanoid)
        /// or Smplx (GMR). cleanup (null: the raw poses) post-processes first; its fps (30 or 50
        /// for trackers) is the file's rate. Throws with status WrongState before there is
        /// anything to read, InvalidArgument for an unknown layout or flags.</summary>
        public byte[] WriteAmass(FlameWhich which = FlameWhich.Sample, int layout = FlameAmassLayout.Smplh,
                                 uint flags = 0, FlameCleanupParams? cleanup = null)
        {
            UIntPtr n;
            FlameException.Check(WriteAmassInto(which, layout, flags, cleanup, null, out n));
            var output = new byte[(int)n];
            FlameException.Check(WriteAmassInto(which, layout, flags, cleanup, output, out n));
            if ((int)n != output.Length)
                Array.Resize(ref output, (int)n);
            return output;
        }

        FlameStatus WriteAmassInto(FlameWhich which, int layout, uint flags, FlameCleanupParams? cleanup, byte[] output,
                                   out UIntPtr n)
        {
            UIntPtr len = output == null ? UIntPtr.Zero : (UIntPtr)output.Length;
            if (cleanup.HasValue)
            {
                var c = cleanup.Value;
                return FlameNative.flame_session_write_amass(Handle, (int)which, layout, flags, ref c, output, len, out n);
            }
            return FlameNative.flame_session_write_amass(Handle, (int)which, layout, flags, IntPtr.Zero, output, len, out n);
        }

        /// <summary>The sample or clean-motion estimate as a glTF 2.0 file
        /// (flame_session_write_gltf): the skeleton as nodes named after Info.JointNames (node
        /// 0 the skeleton's root, node 1 + j joint j), a skinned box figure and one animation
        /// in glTF's convention (Y up, right-handed, metres). Its root translation and joint
        /// rotations are what Read gives for FlameLayout.RootTranslation and LocalQuatXyzw in
        /// FlameConvention.Gltf with the same flags, bit for bit. fps 0 = the model's; name
        /// null = the prompt's (libflame keeps letters, digits, '-' and '_'). Throws with status
        /// WrongState before there is anything to read, InvalidArgument for an unknown
        /// container or a bad fps. cleanup (null: the raw poses) post-processes the poses
        /// first, as Read(..., cleanup) does; its fps, when set, overrides fps, and
        /// FlameRootMotion.Separate adds a node "root" (the pelvis's parent) with the travel.</summary>
        public byte[] WriteGltf(FlameWhich which = FlameWhich.Sample, FlameGltfContainer container = FlameGltfContainer.Glb,
                                uint flags = 0, float fps = 0, string name = null, FlameCleanupParams? cleanup = null)
        {
            var p = FlameGltfParams.Default();
            p.container = (int)container;
            p.flags = flags;
            p.fps = fps;
            if (name != null && name.IndexOf('\0') >= 0)
                throw new ArgumentException("name contains a NUL character", "name");
            var nameBytes = FlameNative.Utf8Z(name);
            var pin = nameBytes == null ? default(GCHandle) : GCHandle.Alloc(nameBytes, GCHandleType.Pinned);
            // The cleanup goes by pointer inside the struct: a copy in unmanaged memory, which
            // no garbage collection moves, freed after the calls.
            IntPtr cleanupCopy = IntPtr.Zero;
            try
            {
                if (pin.IsAllocated)
                    p.name = pin.AddrOfPinnedObject();
                if (cleanup.HasValue)
                {
                    cleanupCopy = Marshal.AllocHGlobal(Marshal.SizeOf(typeof(FlameCleanupParams)));
                    Marshal.StructureToPtr(cleanup.Value, cleanupCopy, false);
                    p.cleanup = cleanupCopy;
                }
                UIntPtr n;
                FlameException.Check(FlameNative.flame_session_write_gltf(Handle, (int)which, ref p, null, UIntPtr.Zero, out n));
                var output = new byte[(int)n];
                FlameException.Check(FlameNative.flame_session_write_gltf(Handle, (int)which, ref p, output, (UIntPtr)output.Length, out n));
                if ((int)n != output.Length)
                    Array.Resize(ref output, (int)n);
                return output;
            }
            finally
            {
                if (pin.IsAllocated)
                    pin.Free();
                if (cleanupCopy != IntPtr.Zero)
                    Marshal.FreeHGlobal(cleanupCopy);
            }
        }

        /// <summary>WriteGltf, the bytes also written to path (created or replaced). The
        /// container follows path's extension: ".gltf" JSON, ".glb" (or none) binary, any
        /// case; another extension throws ArgumentException before anything is written.</summary>
        public byte[] WriteGltf(string path, FlameWhich which = FlameWhich.Sample, uint flags = 0, float fps = 0, string name = null,
                                FlameCleanupParams? cleanup = null)
        {
            if (path == null)
                throw new ArgumentNullException("path");
            string ext = System.IO.Path.GetExtension(path).ToLowerInvariant();
            FlameGltfContainer container;
            if (ext == ".gltf")
                container = FlameGltfContainer.Gltf;
            else if (ext == ".glb" || ext == "")
                container = FlameGltfContainer.Glb;
            else
                throw new ArgumentException("cannot tell the glTF container from \"" + path + "\": name it .glb or .gltf", "path");
            var bytes = WriteGltf(which, container, flags, fps, name, cleanup);
            System.IO.File.WriteAllBytes(path, bytes);
            return bytes;
        }

        /// <summary>Calls callback(stepsDone, stepsTotal) after every step, on the stepping
        /// thread (not Unity's main thread when stepping on a worker). An exception it throws is
        /// rethrown by Step. null removes it.</summary>
        public void SetProgressCallback(Action<int, int> callback)
        {
            if (callback == null)
            {
                FlameException.Check(FlameNative.flame_session_set_progress_callback(Handle, null, IntPtr.Zero));
                progress = null;
                return;
            }
            if (!Handle.CallbackTarget.IsAllocated)
                Handle.CallbackTarget = GCHandle.Alloc(this, GCHandleType.Weak);
            progress = callback;
            FlameException.Check(FlameNative.flame_session_set_progress_callback(Handle, Trampoline, GCHandle.ToIntPtr(Handle.CallbackTarget)));
        }

        [AOT.MonoPInvokeCallback(typeof(ProgressCallback))]
        static void OnProgress(IntPtr userData, uint stepsDone, uint stepsTotal)
        {
            // No exception may unwind into native code: keep it for Step to rethrow.
            FlameSession s = null;
            try
            {
                s = GCHandle.FromIntPtr(userData).Target as FlameSession;
                if (s != null && s.progress != null)
                    s.progress((int)stepsDone, (int)stepsTotal);
            }
            catch (Exception e)
            {
                if (s != null)
                    s.callbackError = e;
            }
        }

        static void CheckLength(Array a, int length, int frames, int dim, string name)
        {
            if (a == null)
                throw new ArgumentNullException(name);
            if (frames < 0 || dim < 0 || (long)frames * dim != length)
                throw new ArgumentException(name + " has " + length + " values, expected " + frames + " × " + dim, name);
        }

        /// <summary>Frees the session (deferred until a Step running on another thread returns).</summary>
        public void Dispose()
        {
            Handle.Dispose();
        }
    }

    // --- retargeting onto a user's rig ---------------------------------------------------------

    /// <summary>Owns a FlameRig*; releasing it calls flame_rig_free.</summary>
    public sealed class FlameRigHandle : SafeHandle
    {
        public FlameRigHandle() : base(IntPtr.Zero, true) { }
        public override bool IsInvalid { get { return handle == IntPtr.Zero; } }
        protected override bool ReleaseHandle()
        {
            FlameNative.flame_rig_free(handle);
            return true;
        }
    }

    /// <summary>Owns a FlameBoneMap*; releasing it calls flame_bone_map_free.</summary>
    public sealed class FlameBoneMapHandle : SafeHandle
    {
        public FlameBoneMapHandle() : base(IntPtr.Zero, true) { }
        public override bool IsInvalid { get { return handle == IntPtr.Zero; } }
        protected override bool ReleaseHandle()
        {
            FlameNative.flame_bone_map_free(handle);
            return true;
        }
    }

    /// <summary>Owns a FlameRobot*; releasing it calls flame_robot_free.</summary>
    public sealed class FlameRobotHandle : SafeHandle
    {
        public FlameRobotHandle() : base(IntPtr.Zero, true) { }
        public override bool IsInvalid { get { return handle == IntPtr.Zero; } }
        protected override bool ReleaseHandle()
        {
            FlameNative.flame_robot_free(handle);
            return true;
        }
    }

    /// <summary>Owns a FlameRobotRetarget*; releasing it calls flame_robot_retarget_free.</summary>
    public sealed class FlameRobotRetargetHandle : SafeHandle
    {
        public FlameRobotRetargetHandle() : base(IntPtr.Zero, true) { }
        public override bool IsInvalid { get { return handle == IntPtr.Zero; } }
        protected override bool ReleaseHandle()
        {
            FlameNative.flame_robot_retarget_free(handle);
            return true;
        }
    }

    /// <summary>Owns a FlameRobotState*; releasing it calls flame_robot_state_free.</summary>
    public sealed class FlameRobotStateHandle : SafeHandle
    {
        public FlameRobotStateHandle() : base(IntPtr.Zero, true) { }
        public override bool IsInvalid { get { return handle == IntPtr.Zero; } }
        protected override bool ReleaseHandle()
        {
            FlameNative.flame_robot_state_free(handle);
            return true;
        }
    }

    /// <summary>Owns a FlameRetarget*; releasing it calls flame_retarget_free.</summary>
    public sealed class FlameRetargetHandle : SafeHandle
    {
        public FlameRetargetHandle() : base(IntPtr.Zero, true) { }
        public override bool IsInvalid { get { return handle == IntPtr.Zero; } }
        protected override bool ReleaseHandle()
        {
            FlameNative.flame_retarget_free(handle);
            return true;
        }
    }

    /// <summary>One bone of FlameRig.FromBones: its name, parent (an index of the same list, -1
    /// for a root) and rest transform relative to the parent in the call's convention: what
    /// Unity's Transform.localPosition, localRotation (x, y, z, w) and localScale hold, or an
    /// Unreal reference pose FTransform. Null Translation, Rotation or Scale mean zero, identity
    /// and one.</summary>
    public sealed class RigBone
    {
        public string Name;
        public int Parent = -1;
        /// <summary>3 floats, or null.</summary>
        public float[] Translation;
        /// <summary>4 floats, quaternion x, y, z, w (normalised by libflame), or null.</summary>
        public float[] Rotation;
        /// <summary>3 floats, or null.</summary>
        public float[] Scale;

        public RigBone() { }

        public RigBone(string name, int parent, float[] translation, float[] rotation = null, float[] scale = null)
        {
            Name = name;
            Parent = parent;
            Translation = translation;
            Rotation = rotation;
            Scale = scale;
        }
    }

    /// <summary>A user's character skeleton (flame_rig_*): bone names, parents and rest pose,
    /// read from a glTF/GLB/VRM or BVH file, or given as an engine's bones (FromBones).
    /// Immutable: any number of threads and retargets may share it. Bones are numbered as
    /// BoneNames lists them: for FromBones in the order given, for a file parents first.</summary>
    public sealed class FlameRig : IDisposable
    {
        public FlameRigHandle Handle { get; private set; }
        /// <summary>Copied at creation.</summary>
        public string[] BoneNames { get; private set; }
        /// <summary>Each bone's parent, -1 for a root; copied at creation.</summary>
        public int[] BoneParents { get; private set; }
        public int BoneCount { get { return BoneNames.Length; } }

        FlameRig(FlameRigHandle handle)
        {
            Handle = handle;
            UIntPtr n;
            FlameException.Check(FlameNative.flame_rig_bone_count(handle, out n));
            BoneNames = new string[(int)n];
            BoneParents = new int[(int)n];
            for (int i = 0; i < BoneNames.Length; i++)
            {
                IntPtr name;
                FlameException.Check(FlameNative.flame_rig_bone_name(handle, (UIntPtr)i, out name));
                BoneNames[i] = FlameNative.Utf8(name);
                int parent;
                FlameException.Check(FlameNative.flame_rig_bone_parent(handle, (UIntPtr)i, out parent));
                BoneParents[i] = parent;
            }
        }

        /// <summary>A rig from a file's bytes (a TextAsset's, File.ReadAllBytes'): kind a
        /// FlameRigFormat value, skin the glTF skin's name (null: the file's only skin, or a VRM
        /// file's humanoid one; null for BVH). Throws with InvalidArgument naming the node, bone
        /// or line for a malformed file.</summary>
        public static FlameRig Load(byte[] bytes, uint kind = FlameRigFormat.Guess, string skin = null)
        {
            if (bytes == null)
                throw new ArgumentNullException("bytes");
            FlameRigHandle h;
            FlameException.Check(FlameNative.flame_rig_load(bytes, (UIntPtr)bytes.Length, kind, FlameNative.Utf8Z(skin), out h));
            return new FlameRig(h);
        }

        /// <summary>A rig from the bones an engine holds, their rest transforms in convention
        /// (a FlameConvention value: Unity for Transforms, Unreal for a reference skeleton).
        /// libflame carries them into right-handed axes itself, and retargeted poses come back
        /// in convention, bones in the order given. Throws with InvalidArgument naming the bone
        /// for a missing or repeated name, a parent out of range or a cycle, a zero quaternion,
        /// a zero scale; with ArgumentException for a Translation, Rotation or Scale of the
        /// wrong length.</summary>
        public static FlameRig FromBones(IList<RigBone> bones, int convention)
        {
            if (bones == null)
                throw new ArgumentNullException("bones");
            var raw = new FlameRigBone[bones.Count];
            var pins = new List<GCHandle>();
            try
            {
                for (int i = 0; i < raw.Length; i++)
                    raw[i] = NativeBone(bones[i], "bones[" + i + "]", pins);
                FlameRigHandle h;
                FlameException.Check(FlameNative.flame_rig_from_bones(raw, (UIntPtr)raw.Length, convention, out h));
                return new FlameRig(h);
            }
            finally
            {
                foreach (var pin in pins)
                    pin.Free();
            }
        }

        static FlameRigBone NativeBone(RigBone b, string name, List<GCHandle> pins)
        {
            if (b == null)
                throw new ArgumentNullException(name);
            var t = Values(b.Translation, 3, 0f, name + ".Translation");
            var r = b.Rotation == null ? new float[] { 0, 0, 0, 1 } : Values(b.Rotation, 4, 0f, name + ".Rotation");
            var s = Values(b.Scale, 3, 1f, name + ".Scale");
            var raw = new FlameRigBone
            {
                struct_size = (uint)Marshal.SizeOf(typeof(FlameRigBone)),
                parent = b.Parent,
                translation_x = t[0], translation_y = t[1], translation_z = t[2],
                rotation_x = r[0], rotation_y = r[1], rotation_z = r[2], rotation_w = r[3],
                scale_x = s[0], scale_y = s[1], scale_z = s[2],
            };
            // A null name stays NULL: libflame refuses it by the bone's index.
            if (b.Name != null)
            {
                if (b.Name.IndexOf('\0') >= 0)
                    throw new ArgumentException(name + ".Name contains a NUL character", name);
                var pin = GCHandle.Alloc(FlameNative.Utf8Z(b.Name), GCHandleType.Pinned);
                pins.Add(pin);
                raw.name = pin.AddrOfPinnedObject();
            }
            return raw;
        }

        static float[] Values(float[] v, int n, float fill, string name)
        {
            if (v == null)
                return new float[] { fill, fill, fill, fill };
            if (v.Length != n)
                throw new ArgumentException(name + " has " + v.Length + " values, expected " + n, name);
            return v;
        }

        /// <summary>The index of the bone named name, or -1.</summary>
        public int BoneIndex(string name)
        {
            return Array.IndexOf(BoneNames, name);
        }

        public void Dispose() { Handle.Dispose(); }
    }

    /// <summary>Which bone of a rig is which VRM 1.0 humanoid bone (hips, spine, leftUpperArm...):
    /// automatic (Auto: a VRM file's declared map, else the bone names of Mixamo, Unreal, Unity,
    /// Rigify, Character Creator...) or given as JSON (FromJson). Immutable; usable only with the
    /// rig it was made for.</summary>
    public sealed class FlameBoneMap : IDisposable
    {
        public FlameBoneMapHandle Handle { get; private set; }
        /// <summary>The rig the map names bones of.</summary>
        public FlameRig Rig { get; private set; }

        FlameBoneMap(FlameBoneMapHandle handle, FlameRig rig)
        {
            Handle = handle;
            Rig = rig;
        }

        /// <summary>The automatic map: bones it cannot find stay unmapped (ToJson shows them as
        /// null; FlameRetarget.Create then names the required ones missing).</summary>
        public static FlameBoneMap Auto(FlameRig rig)
        {
            if (rig == null)
                throw new ArgumentNullException("rig");
            FlameBoneMapHandle h;
            FlameException.Check(FlameNative.flame_bone_map_auto(rig.Handle, out h));
            return new FlameBoneMap(h, rig);
        }

        /// <summary>A map from JSON, {"hips": "pelvis", "leftHand": "hand_l", ...} (VRM humanBone
        /// names as keys, any case; rig bone names or null as values), over baseMap's entries
        /// (null: over nothing). Throws with InvalidArgument naming the key or bone: invalid
        /// JSON, an unknown key, a bone the rig lacks (with the nearest names), one bone for two
        /// keys, a map contradicting the hierarchy, a baseMap of another rig.</summary>
        public static FlameBoneMap FromJson(FlameRig rig, string json, FlameBoneMap baseMap = null)
        {
            if (rig == null)
                throw new ArgumentNullException("rig");
            if (json == null)
                throw new ArgumentNullException("json");
            bool added = false;
            try
            {
                IntPtr b = IntPtr.Zero;
                if (baseMap != null)
                {
                    // The raw pointer crosses inside no SafeHandle parameter: keep it alive by hand.
                    baseMap.Handle.DangerousAddRef(ref added);
                    b = baseMap.Handle.DangerousGetHandle();
                }
                FlameBoneMapHandle h;
                FlameException.Check(FlameNative.flame_bone_map_from_json(rig.Handle, FlameNative.Utf8Z(json), b, out h));
                return new FlameBoneMap(h, rig);
            }
            finally
            {
                if (added)
                    baseMap.Handle.DangerousRelease();
            }
        }

        /// <summary>The map as JSON: every humanoid bone libflame drives, null when unmapped
        /// (what FromJson reads back).</summary>
        public string ToJson()
        {
            UIntPtr n;
            FlameException.Check(FlameNative.flame_bone_map_to_json(Handle, Rig.Handle, null, UIntPtr.Zero, out n));
            var bytes = new byte[(int)n];
            FlameException.Check(FlameNative.flame_bone_map_to_json(Handle, Rig.Handle, bytes, (UIntPtr)bytes.Length, out n));
            return Encoding.UTF8.GetString(bytes, 0, Math.Max(0, (int)n - 1));   // without the NUL
        }

        public void Dispose() { Handle.Dispose(); }
    }

    /// <summary>A model's poses put onto a rig (flame_retarget_*): per frame and bone the local
    /// rotation (x, y, z, w, rest included: set it as the bone's local rotation) and the
    /// translation relative to the parent, in the rig's convention (FromBones': the engine's).
    /// The rig and map are copied: they may be disposed after Create. Shareable between threads
    /// (calls on one retarget run one after another). Reads write into the caller's arrays and
    /// allocate nothing.</summary>
    public sealed class FlameRetarget : IDisposable
    {
        public FlameRetargetHandle Handle { get; private set; }
        /// <summary>Bones per pose: the rig's, in its order.</summary>
        public int BoneCount { get; private set; }

        FlameRetarget(FlameRetargetHandle handle)
        {
            Handle = handle;
            UIntPtr n;
            FlameException.Check(FlameNative.flame_retarget_bone_count(handle, out n));
            BoneCount = (int)n;
        }

        /// <summary>A retarget of model's poses onto rig through map (null: the automatic map)
        /// with p (null: FlameRetargetParams.Default(); its map field is set from map). Throws
        /// with InvalidArgument listing the required humanoid bones the map lacks (hips, spine,
        /// head, arms, legs, hands, feet), for a map of another rig, a zero-length mapped
        /// bone.</summary>
        public static FlameRetarget Create(FlameModel model, FlameRig rig, FlameBoneMap map = null, FlameRetargetParams? p = null)
        {
            if (model == null)
                throw new ArgumentNullException("model");
            if (rig == null)
                throw new ArgumentNullException("rig");
            var q = p ?? FlameRetargetParams.Default();
            q.struct_size = (uint)Marshal.SizeOf(typeof(FlameRetargetParams));
            q.map = IntPtr.Zero;
            bool added = false;
            try
            {
                if (map != null)
                {
                    map.Handle.DangerousAddRef(ref added);
                    q.map = map.Handle.DangerousGetHandle();
                }
                FlameRetargetHandle h;
                FlameException.Check(FlameNative.flame_retarget_new(model.Handle, rig.Handle, ref q, out h));
                return new FlameRetarget(h);
            }
            finally
            {
                if (added)
                    map.Handle.DangerousRelease();
            }
        }

        /// <summary>Frames a Read of session with these settings has (a cleanup's fps changes
        /// it): size the arrays as frames × BoneCount × 4 (rotations) and × 3 (translations).</summary>
        public int Frames(FlameSession session, FlameWhich which = FlameWhich.Sample, uint flags = 0, FlameCleanupParams? cleanup = null)
        {
            return Read(session, 0, 0, null, null, which, flags, cleanup);
        }

        /// <summary>Frames first..first + count of the session's motion, read as
        /// FlameSession.Read(which, ..., flags, cleanup) reads it (null cleanup: the raw poses),
        /// put onto the rig: rotations[count × BoneCount × 4], translations[count × BoneCount ×
        /// 3], either null when not wanted, frame-major. Returns the frames the read has.
        /// Throws with BufferTooSmall for a short array, InvalidArgument for a range past the
        /// frames or a session of a model of another skeleton, WrongState before the first
        /// step.</summary>
        public int Read(FlameSession session, int first, int count, float[] rotations, float[] translations,
                        FlameWhich which = FlameWhich.Sample, uint flags = 0, FlameCleanupParams? cleanup = null)
        {
            if (session == null)
                throw new ArgumentNullException("session");
            CheckRange(first, count);
            UIntPtr frames;
            var rl = Len(rotations);
            var tl = Len(translations);
            if (cleanup.HasValue)
            {
                var c = cleanup.Value;
                FlameException.Check(FlameNative.flame_retarget_read(Handle, session.Handle, (int)which, flags, ref c, (UIntPtr)first, (UIntPtr)count,
                                                                     rotations, rl, translations, tl, out frames));
            }
            else
            {
                FlameException.Check(FlameNative.flame_retarget_read(Handle, session.Handle, (int)which, flags, IntPtr.Zero, (UIntPtr)first,
                                                                     (UIntPtr)count, rotations, rl, translations, tl, out frames));
            }
            return (int)frames;
        }

        /// <summary>Timeline frames firstFrame..firstFrame + count of a stream, read as
        /// FlameStream.Read (null cleanup: raw) or Read(..., cleanup) reads them, put onto the
        /// rig; arrays as Read. Frames not generated (or settled) yet throw with WrongState
        /// (pump more), dropped ones with InvalidArgument.</summary>
        public void ReadStream(FlameStream stream, ulong firstFrame, int count, float[] rotations, float[] translations,
                               FlameCleanupParams? cleanup = null)
        {
            if (stream == null)
                throw new ArgumentNullException("stream");
            CheckRange(0, count);
            if (cleanup.HasValue)
            {
                var c = cleanup.Value;
                FlameException.Check(FlameNative.flame_retarget_read_stream(Handle, stream.Handle, firstFrame, (uint)count, ref c,
                                                                            rotations, Len(rotations), translations, Len(translations)));
            }
            else
            {
                FlameException.Check(FlameNative.flame_retarget_read_stream(Handle, stream.Handle, firstFrame, (uint)count, IntPtr.Zero,
                                                                            rotations, Len(rotations), translations, Len(translations)));
            }
        }

        /// <summary>One pose from any source: sourceWorld[joints × 4] the model skeleton's world
        /// rotations (x, y, z, w) and sourcePositions[joints × 3] its joint positions, both in
        /// FlameConvention.Gltf (a read of FlameLayout.GlobalQuatXyzw and GlobalPositions in
        /// it), into rotations[BoneCount × 4] and translations[BoneCount × 3] (either may be
        /// null).</summary>
        public void Pose(float[] sourceWorld, float[] sourcePositions, float[] rotations, float[] translations)
        {
            if (sourceWorld == null)
                throw new ArgumentNullException("sourceWorld");
            if (sourcePositions == null)
                throw new ArgumentNullException("sourcePositions");
            FlameException.Check(FlameNative.flame_retarget_pose(Handle, sourceWorld, (UIntPtr)sourceWorld.Length, sourcePositions,
                                                                 (UIntPtr)sourcePositions.Length, rotations, Len(rotations),
                                                                 translations, Len(translations)));
        }

        static UIntPtr Len(float[] a)
        {
            return a == null ? UIntPtr.Zero : (UIntPtr)a.Length;
        }

        static void CheckRange(int first, int count)
        {
            if (first < 0)
                throw new ArgumentOutOfRangeException("first");
            if (count < 0)
                throw new ArgumentOutOfRangeException("count");
        }

        public void Dispose() { Handle.Dispose(); }
    }
}

#if !UNITY_5_3_OR_NEWER
namespace AOT
{
    /// <summary>Unity's marker for native-callable static methods (IL2CPP needs it); defined
    /// here for builds outside Unity.</summary>
    [AttributeUsage(AttributeTargets.Method)]
    public sealed class MonoPInvokeCallbackAttribute : Attribute
    {
        public MonoPInvokeCallbackAttribute(Type type) { }
    }
}
#endif
