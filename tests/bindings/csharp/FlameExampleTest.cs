// Drives the Unity example (bindings/csharp/FlameExample.cs) outside Unity, with UnityStubs.cs
// standing in for UnityEngine: Start / Update / OnDestroy called as Unity would, on this thread.
//
// usage: mono FlameExampleTest.exe MODEL REFERENCE_NPY   (as for FlameTest.exe)
// Ends with one line "N passed, N failed"; the exit code is 1 when anything failed.

using System;
using System.Collections.Generic;
using System.Diagnostics;
using System.IO;
using System.Reflection;
using System.Threading;
using Flame;

static class FlameExampleTest
{
    static int passed, failed;

    static void Check(bool ok, string what)
    {
        if (ok) { passed++; return; }
        failed++;
        Console.Error.WriteLine("  check failed: " + what);
    }

    static void Call(FlameExample c, string method)
    {
        typeof(FlameExample).GetMethod(method, BindingFlags.Instance | BindingFlags.NonPublic).Invoke(c, null);
    }

    static int Main(string[] args)
    {
        string model = Path.GetFullPath(args[0]);
        var reference = File.ReadAllBytes(args[1]);

        // The CLI's settings and raw features (layout and convention pass through): the final
        // pose must be the CLI's output.
        var c = new FlameExample { modelFile = model, frames = 24, steps = 10, sampler = FlameSampler.Ddim, seed = 3, threads = 1,
                                   layout = FlameLayout.Features, convention = FlameConvention.Native };
        Call(c, "Start");
        var watch = Stopwatch.StartNew();
        while ((c.StepsDone < 10 || c.Pose == null) && c.Error == null && watch.ElapsedMilliseconds < 30000)
        {
            Call(c, "Update");   // as every rendered frame would
            Thread.Sleep(1);
        }
        Thread.Sleep(50);
        Call(c, "Update");
        Check(c.Error == null, "no error: " + c.Error);
        Check(c.StepsDone == 10 && c.StepsTotal == 10, "progress " + c.StepsDone + "/" + c.StepsTotal);
        Check(c.Pose != null && c.Pose.Length == 24 * 147, "pose length");
        if (c.Pose != null)
        {
            var bytes = new byte[c.Pose.Length * 4];
            Buffer.BlockCopy(c.Pose, 0, bytes, 0, bytes.Length);
            bool equal = true;
            for (int i = 0; i < bytes.Length; i++)
                equal &= bytes[i] == reference[reference.Length - bytes.Length + i];
            Check(equal, "final pose = CLI features bit for bit");
        }
        Check(c.FrameCount == 24 && c.RootPositions != null && c.RootPositions.Length == 24 * 3, "root positions");
        Call(c, "OnDestroy");
        ConsoleOk("finished generation");

        // The defaults: local quaternions in Unity's convention, cleaned (feet locked, ground,
        // 30 fps: 24 frames at 20 fps span 1.15 s, 35 frames at 30), played on a rig.
        var bones = new UnityEngine.Transform[24];
        for (int j = 0; j < bones.Length; j++)
            bones[j] = new UnityEngine.Transform();
        c = new FlameExample { modelFile = model, frames = 24, steps = 10, seed = 3, threads = 1, bones = bones };
        Call(c, "Start");
        watch = Stopwatch.StartNew();
        while ((c.StepsDone < 10 || c.Pose == null) && c.Error == null && watch.ElapsedMilliseconds < 30000)
        {
            Call(c, "Update");
            Thread.Sleep(1);
        }
        Thread.Sleep(50);
        UnityEngine.Time.time = 0.5f;   // 30 fps: frame 15
        Call(c, "Update");
        Check(c.Error == null && c.Pose != null && c.Pose.Length == 35 * 24 * 4, "quaternion poses, 35 frames at 30 fps");
        Check(c.JointNames != null && c.JointNames.Length == 24 && c.Fps == 30f && c.FrameCount == 35, "skeleton, fps and frames");
        Check(c.RootMotion == null, "no root bone track without Separate");
        if (c.Pose != null)
        {
            int q = (15 * 24 + 5) * 4;
            var r = bones[5].localRotation;
            Check(r.x == c.Pose[q] && r.y == c.Pose[q + 1] && r.z == c.Pose[q + 2] && r.w == c.Pose[q + 3], "bone 5 posed with frame 15");
            Check(bones[0].localPosition.z == c.RootPositions[15 * 3 + 2], "root posed with frame 15");
            // The default read flags are the CLI's for this smpl24_6d model: FLAME's smoothing.
            using (var m = FlameModel.Load(model))
            {
                var p = FlameSessionParams.Default();
                p.frames = 24; p.steps = 10; p.sampler = (int)FlameSampler.Ddim; p.seed = 3; p.threads = 1;
                using (var s = m.NewSession(p))
                {
                    s.SetPrompt(c.prompt);
                    while (s.Step() > 0) { }
                    var game = FlameCleanupParams.Default();
                    game.fps = 30;
                    var smooth = s.Read(FlameWhich.Sample, FlameLayout.LocalQuatXyzw, FlameConvention.Unity, FlameReadFlags.Smooth, game);
                    var raw = s.Read(FlameWhich.Sample, FlameLayout.LocalQuatXyzw, FlameConvention.Unity, 0, game);
                    Check(Same(c.Pose, smooth), "default read flags: smoothed as the CLI's default, then cleaned");
                    Check(!Same(c.Pose, raw), "default read flags: not the unsmoothed poses");
                    Check(c.CleanupParams().HasValue && c.CleanupParams().Value.Feet == FlameFeet.Lock && c.CleanupParams().Value.ground == 1,
                          "default cleanup: feet locked, on the ground");
                    Check(FlameExample.DefaultReadFlags(m.Info) == FlameReadFlags.Smooth, "DefaultReadFlags(smpl24_6d)");
                }
            }
        }
        Call(c, "OnDestroy");
        ConsoleOk("rig");

        // readFlags = 0 reads the unsmoothed poses.
        c = new FlameExample { modelFile = model, frames = 24, steps = 10, seed = 3, threads = 1, readFlags = 0 };
        Call(c, "Start");
        watch = Stopwatch.StartNew();
        while ((c.StepsDone < 10 || c.Pose == null) && c.Error == null && watch.ElapsedMilliseconds < 30000)
        {
            Call(c, "Update");
            Thread.Sleep(1);
        }
        Thread.Sleep(50);
        Call(c, "Update");
        using (var m = FlameModel.Load(model))
        {
            var p = FlameSessionParams.Default();
            p.frames = 24; p.steps = 10; p.sampler = (int)FlameSampler.Ddim; p.seed = 3; p.threads = 1;
            using (var s = m.NewSession(p))
            {
                s.SetPrompt(c.prompt);
                while (s.Step() > 0) { }
                Check(c.Pose != null && Same(c.Pose, s.Read(FlameWhich.Sample, FlameLayout.LocalQuatXyzw, FlameConvention.Unity, 0,
                                                             c.CleanupParams())), "readFlags = 0: unsmoothed poses");
            }
        }
        Call(c, "OnDestroy");
        ConsoleOk("read flags 0");

        // Cleanup off: the raw poses at the model's 20 fps. Separate root motion at 60 fps: the
        // root bone's track (on the ground: Unity's y = 0) moves rootBone, the pelvis stays over it.
        c = new FlameExample { modelFile = model, frames = 24, steps = 10, seed = 3, threads = 1, readFlags = 0, cleanup = false };
        Wait(c);
        Check(c.Pose != null && c.Pose.Length == 24 * 24 * 4 && c.Fps == 20f && c.FrameCount == 24 && c.CleanupParams() == null, "cleanup off: raw, 20 fps");
        float[] keptRoot = c.RootPositions;
        Call(c, "OnDestroy");
        var rootBone = new UnityEngine.Transform();
        bones = new UnityEngine.Transform[24];
        for (int j = 0; j < bones.Length; j++)
            bones[j] = new UnityEngine.Transform();
        c = new FlameExample { modelFile = model, frames = 24, steps = 10, seed = 3, threads = 1, readFlags = 0, fps = 60f,
                               lockFeet = false, ground = false, rootMotion = FlameRootMotion.Separate, rootBone = rootBone, bones = bones };
        Wait(c);
        UnityEngine.Time.time = 0.5f;   // 60 fps: frame 30 = frame 10 at 20 fps
        Call(c, "Update");
        // 23 intervals of 1/20 s at 60 fps: 70 frames.
        Check(c.Error == null && c.FrameCount == 70 && c.RootMotion != null && c.RootMotion.Length == 70 * 3, "separate at 60 fps: 70 frames");
        if (c.RootMotion != null && keptRoot != null)
        {
            bool grounded = true;
            for (int f = 0; f < 70; f++)
                grounded &= c.RootMotion[f * 3 + 1] == 0;
            Check(grounded, "root bone at height 0");
            Check(rootBone.localPosition.x == c.RootMotion[30 * 3] && rootBone.localPosition.z == c.RootMotion[30 * 3 + 2], "rootBone posed with frame 30");
            // Root bone + in-place pelvis = the raw pelvis at the common time (frame 30 at 60 fps
            // = frame 10 at 20 fps), horizontally.
            float x = c.RootMotion[30 * 3] + c.RootPositions[30 * 3], z = c.RootMotion[30 * 3 + 2] + c.RootPositions[30 * 3 + 2];
            Check(Math.Abs(x - keptRoot[10 * 3]) < 1e-5 && Math.Abs(z - keptRoot[10 * 3 + 2]) < 1e-5,
                  "root bone + pelvis = the raw pelvis: " + x + "," + z + " vs " + keptRoot[10 * 3] + "," + keptRoot[10 * 3 + 2]);
            double moved = 0;
            for (int f = 0; f < 70; f++)
                moved = Math.Max(moved, Math.Max(Math.Abs(c.RootMotion[f * 3] - c.RootMotion[0]), Math.Abs(c.RootMotion[f * 3 + 2] - c.RootMotion[2])));
            Check(moved > 1e-3, "the root bone moves: " + moved);
        }
        Call(c, "OnDestroy");
        ConsoleOk("cleanup off, separate root motion at 60 fps");

        // A Humanoid character whose bone names say nothing (b00, b01...): Unity's Avatar map
        // (GetBoneTransform) is what pairs them with libflame's joints. An Armature Transform
        // above the hips and a twist Transform between upper and lower arm are rig bones too.
        UnityEngine.Animator animator;
        var character = Humanoid(out animator);
        List<RigBone> rigBones;
        string map;
        var collected = FlameHumanoid.Collect(animator, out rigBones, out map);
        Check(collected.Length == 24 && collected[0].name == "Armature" && rigBones.Count == 24, "rig bones: Armature, 21 body bones (no upper chest), 2 twists: " + collected.Length);
        bool parentsFirst = true;
        for (int i = 0; i < collected.Length; i++)
        {
            int p = rigBones[i].Parent;
            parentsFirst &= p < i && (p < 0 ? collected[i].parent == animator.transform : collected[i].parent == collected[p]);
        }
        Check(parentsFirst, "parents first, each bone's parent its Transform's parent");
        Check(map.Contains("\"leftLowerArm\": \"" + character["LeftLowerArm"].name + "\"") && map.Contains("\"hips\": \"" + character["Hips"].name + "\"") &&
              !map.Contains("upperChest") && !map.Contains("Twist"), "map from the Avatar: " + map);
        using (var m = FlameModel.Load(model))
        using (var rig = FlameRig.FromBones(rigBones, FlameConvention.Unity))
        {
            // Without the Avatar's map libflame cannot tell these bones apart.
            try
            {
                FlameRetarget.Create(m, rig).Dispose();
                Check(false, "the automatic map found a body in b00..b25");
            }
            catch (FlameException e)
            {
                Check(e.Status == FlameStatus.InvalidArgument && e.NativeMessage.Contains("hips"), "automatic map refused: " + e.NativeMessage);
            }
        }
        c = new FlameExample { modelFile = model, frames = 24, steps = 10, seed = 3, threads = 1, humanoid = animator };
        Wait(c);
        UnityEngine.Time.time = 0.5f;   // 30 fps: frame 15
        Call(c, "Update");
        Check(c.Error == null && c.HumanoidRotations != null && c.HumanoidRotations.Length == 35 * 24 * 4 &&
              c.HumanoidPositions.Length == 35 * 24 * 3, "humanoid poses, 35 frames at 30 fps: " + c.Error);
        if (c.HumanoidRotations != null)
        {
            // Independent of the example: the same generation, retargeted here with the map the
            // Avatar gave, read as the example reads (the CLI's smoothing, the default cleanup).
            using (var m = FlameModel.Load(model))
            using (var rig = FlameRig.FromBones(rigBones, FlameConvention.Unity))
            using (var bm = FlameBoneMap.FromJson(rig, map))
            using (var r = FlameRetarget.Create(m, rig, bm))
            {
                var p = FlameSessionParams.Default();
                p.frames = 24; p.steps = 10; p.sampler = (int)FlameSampler.Ddim; p.seed = 3; p.threads = 1;
                using (var s = m.NewSession(p))
                {
                    s.SetPrompt(c.prompt);
                    while (s.Step() > 0) { }
                    var rot = new float[35 * 24 * 4];
                    var pos = new float[35 * 24 * 3];
                    r.Read(s, 0, 35, rot, pos, FlameWhich.Sample, FlameReadFlags.Smooth, c.CleanupParams());
                    Check(Same(rot, c.HumanoidRotations) && Same(pos, c.HumanoidPositions), "the example's humanoid poses = a direct retarget read");
                    bool posed = true;
                    for (int b = 0; b < 24; b++)
                    {
                        var q = collected[b].localRotation;
                        var t = collected[b].localPosition;
                        int i = (15 * 24 + b) * 4, k = (15 * 24 + b) * 3;
                        posed &= q.x == rot[i] && q.y == rot[i + 1] && q.z == rot[i + 2] && q.w == rot[i + 3] &&
                                 t.x == pos[k] && t.y == pos[k + 1] && t.z == pos[k + 2];
                    }
                    Check(posed, "every bone Transform posed with frame 15");
                }
            }
        }
        Call(c, "OnDestroy");
        // Not Humanoid: refused before anything starts.
        animator.isHuman = false;
        try
        {
            FlameHumanoid.Collect(animator, out rigBones, out map);
            Check(false, "a generic Animator accepted");
        }
        catch (ArgumentException e)
        {
            Check(e.Message.Contains("Humanoid"), "generic Animator refused: " + e.Message);
        }
        ConsoleOk("humanoid character");

        // Destroyed mid-generation: OnDestroy returns promptly and frees everything.
        c = new FlameExample { modelFile = model, frames = 470, steps = 1000, threads = 1 };
        Call(c, "Start");
        watch = Stopwatch.StartNew();
        while (c.StepsDone < 2 && watch.ElapsedMilliseconds < 30000)
            Thread.Sleep(1);
        Check(c.StepsDone >= 2, "stepping started");
        watch = Stopwatch.StartNew();
        Call(c, "OnDestroy");
        Check(watch.ElapsedMilliseconds < 1000, "OnDestroy took " + watch.ElapsedMilliseconds + " ms");
        int done = c.StepsDone;
        Thread.Sleep(300);
        Check(c.StepsDone == done && done < 1000, "no step after OnDestroy");
        ConsoleOk("destroyed while stepping");

        // Destroyed before the model is even loaded: the worker frees what it creates.
        c = new FlameExample { modelFile = model, frames = 24, steps = 10, threads = 1 };
        Call(c, "Start");
        Call(c, "OnDestroy");
        Thread.Sleep(300);
        Check(c.StepsDone < 10 && c.Error == null, "stopped after an immediate OnDestroy");
        ConsoleOk("destroyed while loading");

        // A missing model reaches Error on the main thread.
        c = new FlameExample { modelFile = "/nonexistent/model.safetensors" };
        Call(c, "Start");
        watch = Stopwatch.StartNew();
        while (c.Error == null && watch.ElapsedMilliseconds < 10000)
        {
            Call(c, "Update");
            Thread.Sleep(1);
        }
        Check(c.Error != null && c.Error.Contains("FLAME_STATUS_IO"), "error surfaced: " + c.Error);
        Call(c, "OnDestroy");
        ConsoleOk("missing model");

        Console.WriteLine(passed + " passed, " + failed + " failed");
        return failed == 0 ? 0 : 1;
    }

    /// <summary>A T-posed humanoid in Unity's axes (Y up, facing +Z, its left at -X; metres)
    /// under an Animator's Transform, bones named b00, b01... in creation order, the Avatar's
    /// map filled for 21 body bones (no upper chest). Returns the Transforms by body name.</summary>
    static Dictionary<string, UnityEngine.Transform> Humanoid(out UnityEngine.Animator animator)
    {
        var top = new UnityEngine.Transform { name = "Character" };
        animator = new UnityEngine.Animator { transform = top };
        var all = new Dictionary<string, UnityEngine.Transform>();
        var world = new Dictionary<string, float[]>();
        Action<string, string, float, float, float> add = (name, parent, x, y, z) =>
        {
            var t = new UnityEngine.Transform { name = name == "Armature" ? name : "b" + all.Count.ToString("00") };
            t.parent = parent == null ? top : all[parent];
            var pw = parent == null ? new float[3] : world[parent];
            t.localPosition = new UnityEngine.Vector3(x - pw[0], y - pw[1], z - pw[2]);
            all[name] = t;
            world[name] = new[] { x, y, z };
        };
        add("Armature", null, 0, 0, 0);
        add("Hips", "Armature", 0, 1.0f, 0);
        add("Spine", "Hips", 0, 1.1f, 0);
        add("Chest", "Spine", 0, 1.25f, 0);
        add("Neck", "Chest", 0, 1.5f, 0);
        add("Head", "Neck", 0, 1.62f, 0);
        foreach (var side in new[] { "Left", "Right" })
        {
            float m = side == "Left" ? -1 : 1;
            add(side + "Shoulder", "Chest", m * 0.04f, 1.45f, 0);
            add(side + "UpperArm", side + "Shoulder", m * 0.17f, 1.45f, 0);
            add(side + "Twist", side + "UpperArm", m * 0.3f, 1.45f, 0);
            add(side + "LowerArm", side + "Twist", m * 0.45f, 1.45f, 0);
            add(side + "Hand", side + "LowerArm", m * 0.7f, 1.45f, 0);
            add(side + "UpperLeg", "Hips", m * 0.1f, 0.94f, 0);
            add(side + "LowerLeg", side + "UpperLeg", m * 0.1f, 0.5f, 0.01f);
            add(side + "Foot", side + "LowerLeg", m * 0.1f, 0.08f, 0);
            add(side + "Toes", side + "Foot", m * 0.1f, 0, 0.13f);
        }
        foreach (var kv in all)
        {
            UnityEngine.HumanBodyBones b;
            if (Enum.TryParse(kv.Key, out b))
                animator.Bones[b] = kv.Value;
        }
        return all;
    }

    /// <summary>Starts c and updates it, as Unity would, until its generation is done.</summary>
    static void Wait(FlameExample c)
    {
        Call(c, "Start");
        var watch = Stopwatch.StartNew();
        while ((c.StepsDone < 10 || c.Pose == null) && c.Error == null && watch.ElapsedMilliseconds < 30000)
        {
            Call(c, "Update");
            Thread.Sleep(1);
        }
        // The worker publishes the final (cleaned) poses after the last step: wait for it.
        var worker = (Thread)typeof(FlameExample).GetField("worker", BindingFlags.Instance | BindingFlags.NonPublic).GetValue(c);
        worker.Join(30000);
        Call(c, "Update");
    }

    static bool Same(float[] a, float[] b)
    {
        if (a == null || b == null || a.Length != b.Length)
            return false;
        for (int i = 0; i < a.Length; i++)
            if (BitConverter.ToInt32(BitConverter.GetBytes(a[i]), 0) != BitConverter.ToInt32(BitConverter.GetBytes(b[i]), 0))
                return false;
        return true;
    }

    static void ConsoleOk(string name)
    {
        Console.WriteLine("---- example: " + name);
    }
}
