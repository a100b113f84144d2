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
// - A Humanoid character (the `humanoid` Animator) is driven through libflame's retarget: its
//   bone Transforms are the rig, in Unity's convention, and Unity's own Humanoid avatar says
//   which Transform is which body bone (Animator.GetBoneTransform), so no name matching is
//   needed. FlameHumanoid (below) holds that part; it uses no engine call beyond Transforms.
#if UNITY_5_3_OR_NEWER
using System;
using System.Collections.Generic;
using System.IO;
using System.Text;
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
        [Tooltip("A Humanoid character to drive (its Animator, Avatar set to Humanoid): the motion is retargeted onto its bones, taken in the pose they have at Start as the rest pose. Disable the Animator's controller so it does not overwrite them.")]
        public Animator humanoid;
        [Tooltip("Retarget: two-bone IK on the character's legs so planted feet stay planted on its proportions.")]
        public bool humanoidFeetIk = true;

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
        /// <summary>With humanoid: the character's bones the retarget drives (HumanoidRig's).</summary>
        public Transform[] HumanoidBones { get; private set; }
        /// <summary>With humanoid: the retargeted local rotations (x, y, z, w) and positions of
        /// HumanoidBones, frames × bones × 4 and × 3, in Unity's convention; null before the
        /// first step.</summary>
        public float[] HumanoidRotations { get; private set; }
        public float[] HumanoidPositions { get; private set; }
        /// <summary>With humanoid: the bone map given to libflame (VRM humanBone names → Transform
        /// names), from the Avatar.</summary>
        public string HumanoidMap { get; private set; }

        // The handles are created on the worker and freed in OnDestroy; handlesLock makes sure a
        // worker still loading when the component is destroyed frees what it creates itself.
        readonly object handlesLock = new object();
        FlameModel model;        // guarded by handlesLock
        FlameSession session;    // guarded by handlesLock
        FlameRetarget retarget;  // guarded by handlesLock; with humanoid
        bool stopping;           // guarded by handlesLock
        Thread worker;
        int stepsDone, stepsTotal;

        // What the worker publishes, guarded by latestLock.
        readonly object latestLock = new object();
        float[] latestPose, latestRoot, latestRootMotion, latestRigRot, latestRigPos;
        bool latestIsNew;
        // The humanoid as data for the worker (Transforms are read on the main thread only).
        List<RigBone> humanoidRig;
        float latestFps;
        string workerError;
        ModelInfo info;

        void Start()
        {
            // Unity objects only on the main thread: resolve the path / copy the bytes here.
            byte[] bytes = modelAsset != null ? modelAsset.bytes : null;
            string path = Path.Combine(Application.streamingAssetsPath, modelFile);
            if (humanoid != null)
            {
                List<RigBone> rig;
                string map;
                HumanoidBones = FlameHumanoid.Collect(humanoid, out rig, out map);
                humanoidRig = rig;
                HumanoidMap = map;
            }
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
                if (humanoidRig != null)
                {
                    // Made here, not on the main thread: it needs the model. The rig and map are
                    // copied into the retarget, so they go right away.
                    using (var rig = FlameRig.FromBones(humanoidRig, FlameConvention.Unity))
                    using (var map = FlameBoneMap.FromJson(rig, HumanoidMap))
                    {
                        var rp = FlameRetargetParams.Default();
                        rp.feet = humanoidFeetIk ? 1u : 0u;
                        lock (handlesLock)
                            retarget = FlameRetarget.Create(m, rig, map, rp);
                    }
                }
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
            float[] pose = null, root = null, rootMotionTrack = null, rigRot = null, rigPos = null;
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
                FlameRetarget r;
                lock (handlesLock)
                    r = retarget;
                if (r != null)
                {
                    // The same motion as Pose (which, flags, cleanup), on the character's bones.
                    int n = r.Frames(s, which, flags, clean) * r.BoneCount;
                    if (rigRot == null || rigRot.Length != n * 4)
                    {
                        rigRot = new float[n * 4];
                        rigPos = new float[n * 3];
                    }
                    r.Read(s, 0, n / r.BoneCount, rigRot, rigPos, which, flags, clean);
                }
                lock (latestLock)
                {
                    Swap(ref rigRot, ref latestRigRot);
                    Swap(ref rigPos, ref latestRigPos);
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
                    HumanoidRotations = latestRigRot == null ? null : Copy(latestRigRot, HumanoidRotations);
                    HumanoidPositions = latestRigPos == null ? null : Copy(latestRigPos, HumanoidPositions);
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
            if (HumanoidBones != null && HumanoidRotations != null)
                FlameHumanoid.Apply(HumanoidBones, HumanoidRotations, HumanoidPositions, frame);
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
            FlameRetarget r;
            lock (handlesLock)
            {
                stopping = true;
                m = model;
                s = session;
                r = retarget;
                model = null;
                session = null;
                retarget = null;
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
            // A worker between its last read and its exit holds none: reads take it under the lock
            // and a disposed handle makes a late read throw, which the worker catches.
            if (r != null)
                r.Dispose();
        }
    }

    /// <summary>A Unity Humanoid character as a libflame rig: its Avatar's body bones
    /// (Animator.GetBoneTransform, https://docs.unity3d.com/ScriptReference/Animator.GetBoneTransform.html)
    /// named by VRM 1.0 humanBone names for the bone map, the Transforms between them and the
    /// character's root as the rig's other bones, and retargeted poses written back to them.</summary>
    public static class FlameHumanoid
    {
        /// <summary>Unity's HumanBodyBones (https://docs.unity3d.com/ScriptReference/HumanBodyBones.html)
        /// that libflame drives, with their VRM 1.0 humanBone names (vrm-c/vrm-specification,
        /// specification/VRMC_vrm-1.0/humanoid.md): the body; eyes, jaw and fingers are not driven.</summary>
        public static readonly KeyValuePair<HumanBodyBones, string>[] Body =
        {
            Pair(HumanBodyBones.Hips, "hips"), Pair(HumanBodyBones.Spine, "spine"), Pair(HumanBodyBones.Chest, "chest"),
            Pair(HumanBodyBones.UpperChest, "upperChest"), Pair(HumanBodyBones.Neck, "neck"), Pair(HumanBodyBones.Head, "head"),
            Pair(HumanBodyBones.LeftShoulder, "leftShoulder"), Pair(HumanBodyBones.LeftUpperArm, "leftUpperArm"),
            Pair(HumanBodyBones.LeftLowerArm, "leftLowerArm"), Pair(HumanBodyBones.LeftHand, "leftHand"),
            Pair(HumanBodyBones.RightShoulder, "rightShoulder"), Pair(HumanBodyBones.RightUpperArm, "rightUpperArm"),
            Pair(HumanBodyBones.RightLowerArm, "rightLowerArm"), Pair(HumanBodyBones.RightHand, "rightHand"),
            Pair(HumanBodyBones.LeftUpperLeg, "leftUpperLeg"), Pair(HumanBodyBones.LeftLowerLeg, "leftLowerLeg"),
            Pair(HumanBodyBones.LeftFoot, "leftFoot"), Pair(HumanBodyBones.LeftToes, "leftToes"),
            Pair(HumanBodyBones.RightUpperLeg, "rightUpperLeg"), Pair(HumanBodyBones.RightLowerLeg, "rightLowerLeg"),
            Pair(HumanBodyBones.RightFoot, "rightFoot"), Pair(HumanBodyBones.RightToes, "rightToes"),
        };

        static KeyValuePair<HumanBodyBones, string> Pair(HumanBodyBones b, string vrm)
        {
            return new KeyValuePair<HumanBodyBones, string>(b, vrm);
        }

        /// <summary>The rig of animator's character: every body bone the Avatar maps and every
        /// Transform between them and the Animator's own Transform (which is not a bone: the top
        /// bones' rest is relative to it), parents before children, each bone's rest its current
        /// localPosition, localRotation and localScale (Unity's convention). map receives the bone
        /// map JSON, {"hips": "&lt;Transform name&gt;", ...}, for FlameBoneMap.FromJson. Returns the
        /// Transforms in the rig's order, for Apply. Throws ArgumentException for an Animator that
        /// is not Humanoid, and for two rig Transforms with the same name (libflame names bones
        /// by them).</summary>
        public static Transform[] Collect(Animator animator, out List<RigBone> rig, out string map)
        {
            if (animator == null)
                throw new ArgumentNullException("animator");
            if (!animator.isHuman)
                throw new ArgumentException("the Animator's Avatar is not Humanoid: set Animation Type to Humanoid in the model's import settings", "animator");
            var top = animator.transform;
            var bones = new List<Transform>();
            var index = new Dictionary<Transform, int>();
            var json = new StringBuilder("{");
            foreach (var pair in Body)
            {
                var t = animator.GetBoneTransform(pair.Key);
                if (t == null)
                    continue;   // an optional bone the Avatar leaves out (upperChest, toes...)
                // The Transform and its ancestors below the Animator's, parents first.
                var chain = new List<Transform>();
                for (var a = t; a != null && a != top && !index.ContainsKey(a); a = a.parent)
                    chain.Add(a);
                for (int i = chain.Count - 1; i >= 0; i--)
                {
                    index[chain[i]] = bones.Count;
                    bones.Add(chain[i]);
                }
                json.Append(json.Length > 1 ? ", " : "").Append(Quote(pair.Value)).Append(": ").Append(Quote(t.name));
            }
            map = json.Append("}").ToString();
            rig = new List<RigBone>(bones.Count);
            var names = new HashSet<string>();
            foreach (var b in bones)
            {
                if (!names.Add(b.name))
                    throw new ArgumentException("two of the character's bones are named \"" + b.name + "\": rename one (libflame tells bones by name)", "animator");
                Vector3 p = b.localPosition, s = b.localScale;
                Quaternion q = b.localRotation;
                int parent;
                rig.Add(new RigBone(b.name, b.parent != null && index.TryGetValue(b.parent, out parent) ? parent : -1,
                                    new[] { p.x, p.y, p.z }, new[] { q.x, q.y, q.z, q.w }, new[] { s.x, s.y, s.z }));
            }
            return bones.ToArray();
        }

        /// <summary>Poses bones (Collect's) with frame of a retarget read: rotations frames ×
        /// bones × 4 (x, y, z, w) as localRotation, positions frames × bones × 3 as localPosition
        /// (null: rotations only). A frame past the arrays is ignored.</summary>
        public static void Apply(IList<Transform> bones, float[] rotations, float[] positions, int frame)
        {
            int n = bones.Count;
            if (n == 0 || frame < 0 || rotations == null || (long)(frame + 1) * n * 4 > rotations.Length)
                return;
            bool withPositions = positions != null && (long)(frame + 1) * n * 3 <= positions.Length;
            for (int b = 0; b < n; b++)
            {
                int q = (frame * n + b) * 4, t = (frame * n + b) * 3;
                bones[b].localRotation = new Quaternion(rotations[q], rotations[q + 1], rotations[q + 2], rotations[q + 3]);
                if (withPositions)
                    bones[b].localPosition = new Vector3(positions[t], positions[t + 1], positions[t + 2]);
            }
        }

        /// <summary>s as a JSON string.</summary>
        static string Quote(string s)
        {
            var o = new StringBuilder("\"");
            foreach (char c in s)
            {
                if (c == '"' || c == '\\')
                    o.Append('\\').Append(c);
                else if (c < ' ')
                    o.Append("\\u").Append(((int)c).ToString("x4"));
                else
                    o.Append(c);
            }
            return o.Append('"').ToString();
        }
    }
}
#endif
