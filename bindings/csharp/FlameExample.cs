// A Unity example of the libflame bindings: generates a motion on a worker thread, hands the
// latest poses to the main thread and plays them on a rig. Put Flame.cs and this file under
// Assets/, the native library under Assets/Plugins/ (see bindings/csharp/README.md), the model
// under Assets/StreamingAssets/ (or assign it as a TextAsset renamed to .bytes): the demo model,
// models/demo/flame_demo.safetensors of the libflame checkout, which `bash tools/try.sh`
// assembles.
//
// Why it is shaped like this:
// - The main thread never waits for libflame: loading and every step run on the worker.
// - A FlameSession is used by one thread at a time, so the worker also reads the poses (between
//   its steps) and publishes them under a lock; Update only copies them.
// - The poses are read game-ready (flame_session_read_cleaned): feet pinned while planted, the
//   floor at 0, resampled to the game's animation rate, the root motion where the character
//   controller wants it. The raw features (layout Features) are never post-processed.
// - Native statics survive domain reloads (entering play mode again keeps the library loaded):
//   libflame keeps no global state to reset, and everything this component creates is freed in
//   OnDestroy. Rebuilding the native library needs an Editor restart to be picked up.
#if UNITY_5_3_OR_NEWER
using System;
using System.IO;
using System.Threading;
using UnityEngine;

namespace Flame
{
    public class FlameExample : MonoBehaviour
    {
        [Tooltip("Model file under StreamingAssets (ignored when Model Asset is set).")]
        public string modelFile = "flame_demo.safetensors";
        [Tooltip("The model as a TextAsset (a copy named *.bytes); needed where StreamingAssets is not a folder (Android).")]
        public TextAsset modelAsset;
        public string prompt = "a person walks forward and waves.";
        public int frames = 120;
        public int steps = 50;
        public FlameSampler sampler = FlameSampler.Ddim;
        public float guidance = -1f;   // negative: the model's default
        public long seed = 1;
        [Tooltip("Worker threads of the session; 0 = one per core. Leave some for the game.")]
        public int threads = 2;
        [Tooltip("Show the clean-motion estimate while stepping (a preview), not the noisy sample.")]
        public bool previewEstimate = true;
        [Tooltip("FlameLayout of Pose; bones are driven only with LocalQuatXyzw (2).")]
        public int layout = FlameLayout.LocalQuatXyzw;
        [Tooltip("FlameConvention of Pose and RootPositions; Unity is 1.")]
        public int convention = FlameConvention.Unity;
        [Tooltip("FlameReadFlags bits (1 = FLAME's temporal smoothing, sigma = 1 frame); negative = what the flame CLI does: smoothing for smpl24_6d models (FLAME), none for others.")]
        public int readFlags = -1;
        [Tooltip("One Transform per model joint, in the model's joint order (JointNames); optional.")]
        public Transform[] bones;

        [Tooltip("Post-process the poses for a game (the settings below); off: the raw poses at the model's rate.")]
        public bool cleanup = true;
        [Tooltip("Pin each planted foot where it stands (two-bone IK on the legs): no foot sliding.")]
        public bool lockFeet = true;
        [Tooltip("Put the lowest foot contact of the clip at height 0.")]
        public bool ground = true;
        [Tooltip("Frames per second of the poses, 1 to 240 (30 or 60 for a game); 0 = the model's (20 for FLAME).")]
        public float fps = 30f;
        [Tooltip("Keep: the pelvis travels. InPlace: the clip stays over the origin. Separate: the travel goes to Root Bone (RootMotion), the pelvis in place.")]
        public FlameRootMotion rootMotion = FlameRootMotion.Keep;
        [Tooltip("With InPlace or Separate: also remove the heading's drift.")]
        public bool removeYaw = false;
        [Tooltip("Moved by the root bone track with Separate root motion (the character's root); optional.")]
        public Transform rootBone;

        /// <summary>Steps done and total, for a progress bar (written by the worker).</summary>
        public int StepsDone { get { return Volatile.Read(ref stepsDone); } }
        public int StepsTotal { get { return Volatile.Read(ref stepsTotal); } }
        /// <summary>The last error on the worker, if any (read on the main thread).</summary>
        public string Error { get; private set; }
        /// <summary>The latest poses in `layout`, frame-major; null until the first step.</summary>
        public float[] Pose { get; private set; }
        /// <summary>The latest root positions, frames × 3, in `convention`.</summary>
        public float[] RootPositions { get; private set; }
        /// <summary>With Separate root motion, the root bone's positions, frames × 3, in
        /// `convention` (height 0); null otherwise.</summary>
        public float[] RootMotion { get; private set; }
        /// <summary>The model's skeleton, set with the first poses.</summary>
        public string[] JointNames { get; private set; }
        /// <summary>Frames per second of Pose: the cleanup's fps, or the model's.</summary>
        public float Fps { get; private set; }
        public int FrameCount { get; private set; }

        // The handles are created on the worker and freed in OnDestroy; handlesLock makes sure a
        // worker still loading when the component is destroyed frees what it creates itself.
        readonly object handlesLock = new object();
        FlameModel model;        // guarded by handlesLock
        FlameSession session;    // guarded by handlesLock
        bool stopping;           // guarded by handlesLock
        Thread worker;
        int stepsDone, stepsTotal;

        // What the worker publishes, guarded by latestLock.
        readonly object latestLock = new object();
        float[] latestPose, latestRoot, latestRootMotion;
        bool latestIsNew;
        float latestFps;
        string workerError;
        ModelInfo info;

        void Start()
        {
            // Unity objects only on the main thread: resolve the path / copy the bytes here.
            byte[] bytes = modelAsset != null ? modelAsset.bytes : null;
            string path = Path.Combine(Application.streamingAssetsPath, modelFile);
            worker = new Thread(() => Generate(path, bytes)) { IsBackground = true, Name = "flame" };
            worker.Start();
        }

        void Generate(string path, byte[] bytes)
        {
            try
            {
                var m = bytes != null ? FlameModel.LoadFromMemory(bytes) : FlameModel.Load(path);
                var p = FlameSessionParams.Default();
                p.frames = (uint)frames;
                p.steps = (uint)steps;
                p.sampler = (int)sampler;
                p.guidance = guidance;
                p.seed = (ulong)seed;
                p.threads = (uint)threads;
                var s = m.NewSession(p);
                lock (handlesLock)
                {
                    if (stopping)
                    {
                        s.Dispose();
                        m.Dispose();
                        return;
                    }
                    model = m;
                    session = s;
                }
                s.SetProgressCallback((done, total) =>
                {
                    Volatile.Write(ref stepsDone, done);
                    Volatile.Write(ref stepsTotal, total);
                });
                s.SetPrompt(prompt);
                Publish(s, m.Info);
            }
            catch (FlameException e)
            {
                if (e.Status != FlameStatus.Cancelled)
                    lock (latestLock) workerError = e.Message;
            }
            catch (ObjectDisposedException)
            {
                // OnDestroy disposed the session while this thread was finishing: nothing to do.
            }
            catch (Exception e)
            {
                lock (latestLock) workerError = e.ToString();
            }
        }

        /// <summary>The FlameCleanupParams of the inspector's settings, or null for raw poses.</summary>
        public FlameCleanupParams? CleanupParams()
        {
            if (!cleanup)
                return null;
            var c = FlameCleanupParams.Default();   // contact detection stays libflame's
            c.Feet = lockFeet ? FlameFeet.Lock : FlameFeet.Off;
            c.ground = ground ? 1u : 0u;            // uint, not bool: the C struct's layout
            c.fps = fps;
            c.RootMotion = rootMotion;
            c.remove_yaw = removeYaw ? 1u : 0u;
            return c;
        }

        /// <summary>Steps to the end, publishing the poses after every step.</summary>
        void Publish(FlameSession s, ModelInfo modelInfo)
        {
            uint flags = readFlags >= 0 ? (uint)readFlags : DefaultReadFlags(modelInfo);
            // Raw features are never post-processed: with them, the root positions stay raw too,
            // so both span the same frames.
            var clean = layout == FlameLayout.Features ? null : CleanupParams();
            bool separate = clean.HasValue && clean.Value.RootMotion == FlameRootMotion.Separate;
            float[] pose = null, root = null, rootMotionTrack = null;
            int left = s.StepsLeft;
            while (left > 0)
            {
                // OnDestroy cancels the running step; this catches a destroy between steps.
                lock (handlesLock)
                    if (stopping)
                        return;
                left = s.Step();
                var which = previewEstimate && left > 0 ? FlameWhich.Estimate : FlameWhich.Sample;
                // The preview is cleaned too, so it plays at the same rate as the final motion.
                pose = Fill(s, pose, which, layout, flags, clean);
                root = Fill(s, root, which, FlameLayout.RootTranslation, flags, clean);
                if (separate)
                    rootMotionTrack = Fill(s, rootMotionTrack, which, FlameLayout.RootBone, flags, clean);
                lock (latestLock)
                {
                    // Swap instead of copying: the worker gets the previous buffers back to fill.
                    Swap(ref pose, ref latestPose);
                    Swap(ref root, ref latestRoot);
                    Swap(ref rootMotionTrack, ref latestRootMotion);
                    latestIsNew = true;
                    info = modelInfo;
                    latestFps = clean.HasValue && clean.Value.fps > 0 ? clean.Value.fps : modelInfo.Fps;
                }
            }
        }

        /// <summary>The read flags of the flame CLI's default output: FLAME's temporal smoothing
        /// (sigma = 1) for smpl24_6d models, as FLAME's official output; none for others.</summary>
        public static uint DefaultReadFlags(ModelInfo modelInfo)
        {
            return modelInfo.MotionFormat == "smpl24_6d" ? FlameReadFlags.Smooth : 0u;
        }

        float[] Fill(FlameSession s, float[] buffer, FlameWhich which, int readLayout, uint flags, FlameCleanupParams? clean)
        {
            // The length first: a cleanup's fps changes the frame count.
            int n = s.ReadLength(which, readLayout, convention, flags, clean);
            if (buffer == null || buffer.Length != n)
                buffer = new float[n];
            s.ReadInto(buffer, which, readLayout, convention, flags, clean);
            return buffer;
        }

        static void Swap(ref float[] a, ref float[] b)
        {
            var t = a;
            a = b;
            b = t;
        }

        void Update()
        {
            lock (latestLock)
            {
                if (workerError != null)
                {
                    Error = workerError;
                    workerError = null;
                    Debug.LogError("libflame: " + Error);
                }
                if (latestIsNew)
                {
                    Pose = Copy(latestPose, Pose);
                    RootPositions = Copy(latestRoot, RootPositions);
                    RootMotion = latestRootMotion == null ? null : Copy(latestRootMotion, RootMotion);
                    JointNames = info.JointNames;
                    Fps = latestFps;
                    FrameCount = RootPositions.Length / 3;
                    latestIsNew = false;
                }
            }
            if (Pose != null && FrameCount > 0)
                ApplyFrame((int)(Time.time * Fps) % FrameCount);
        }

        static float[] Copy(float[] source, float[] target)
        {
            if (target == null || target.Length != source.Length)
                target = new float[source.Length];
            Array.Copy(source, target, source.Length);
            return target;
        }

        /// <summary>Poses the bones with one frame: local rotations from Pose (x, y, z, w, as
        /// libflame's Unity convention gives them) and the root joint's position.</summary>
        public void ApplyFrame(int frame)
        {
            // Separate root motion: the pelvis reads in place, the travel moves the root.
            if (rootBone != null && RootMotion != null && RootMotion.Length >= (frame + 1) * 3)
                rootBone.localPosition = new Vector3(RootMotion[frame * 3], RootMotion[frame * 3 + 1], RootMotion[frame * 3 + 2]);
            if (bones == null || layout != FlameLayout.LocalQuatXyzw || JointNames == null || bones.Length != JointNames.Length)
                return;
            int joints = bones.Length;
            for (int j = 0; j < joints; j++)
            {
                int q = (frame * joints + j) * 4;
                if (bones[j] != null)
                    bones[j].localRotation = new Quaternion(Pose[q], Pose[q + 1], Pose[q + 2], Pose[q + 3]);
            }
            if (bones[0] != null)
                bones[0].localPosition = new Vector3(RootPositions[frame * 3], RootPositions[frame * 3 + 1], RootPositions[frame * 3 + 2]);
        }

        void OnDestroy()
        {
            FlameModel m;
            FlameSession s;
            lock (handlesLock)
            {
                stopping = true;
                m = model;
                s = session;
                model = null;
                session = null;
            }
            if (s != null)
                s.Cancel();
            // Cancel makes a running step return soon; still, never hang the main thread on it:
            // disposing while a step runs is safe (the SafeHandle defers the free until it returns).
            if (worker != null)
                worker.Join(500);
            if (s != null)
                s.Dispose();
            if (m != null)
                m.Dispose();
        }
    }
}
#endif
