// The C# bindings (bindings/csharp/Flame.cs) against libflame, under Mono.
//
// usage: mono FlameTest.exe MODEL REFERENCE_NPY FLAME_CLI TMPDIR HEADER
//   MODEL          tests/fixtures/flame_tiny.safetensors
//   REFERENCE_NPY  `flame generate` output for RefPrompt with the settings of RefParams()
//   FLAME_CLI      the `flame` executable (for the --noise comparison)
//   TMPDIR         a writable directory
//   HEADER         include/flame.h, which the declarations must cover
//
// Reference: the `flame` CLI (the Rust API); its features must equal the bindings' bit for bit.
// Ends with one line "N passed, N failed"; the exit code is 1 when anything failed.

using System;
using System.Collections.Generic;
using System.Diagnostics;
using System.IO;
using System.Linq;
using System.Reflection;
using System.Runtime.InteropServices;
using System.Text;
using System.Text.RegularExpressions;
using System.Threading;
using Flame;

static class FlameTest
{
    const string RefPrompt = "a person walks forward and waves.";
    const int Dim = 147;
    const int RefFrames = 24;

    static string modelPath, cliPath, tmpDir, header, headerPath;
    static float[] reference;
    static FlameModel model;
    static int passed, failed;

    static int Main(string[] args)
    {
        if (args.Length != 5)
        {
            Console.Error.WriteLine("usage: FlameTest.exe MODEL REFERENCE_NPY FLAME_CLI TMPDIR HEADER");
            return 2;
        }
        headerPath = args[4];
        header = File.ReadAllText(headerPath);
        modelPath = args[0];
        cliPath = args[2];
        tmpDir = args[3];
        int[] shape;
        reference = Npy.Read(args[1], out shape);
        Check(shape.Length == 2 && shape[0] == RefFrames && shape[1] == Dim, "reference shape " + string.Join("x", shape));

        Run("HeaderCoverage", TestHeaderCoverage);
        Run("Version", TestVersion);
        Run("StructLayouts", TestStructLayouts);
        Run("LoadErrors", TestLoadErrors);
        using (model = FlameModel.Load(modelPath, 1))
        {
            Run("Info", TestInfo);
            Run("MatchesCli", TestMatchesCli);
            Run("LoadFromMemory", TestLoadFromMemory);
            Run("HalfWeights", TestHalfWeights);
            Run("StepsEstimateReset", TestStepsEstimateReset);
            Run("SessionErrors", TestSessionErrors);
            Run("Respacing", TestRespacing);
            Run("LoopSession", TestLoopSession);
            Run("LoopRefusals", TestLoopRefusals);
            Run("PromptInfo", TestPromptInfo);
            Run("PromptFrom", TestPromptFrom);
            Run("LatentTuning", TestLatentTuning);
            Run("NullArguments", TestNullArguments);
            Run("ReadInto", TestReadInto);
            Run("PoseLayouts", TestPoseLayouts);
            Run("SetNoiseMatchesCli", TestSetNoiseMatchesCli);
            Run("ProgressCallback", TestProgressCallback);
            Run("ProgressCallbackException", TestProgressCallbackException);
            Run("CancelFromCallback", TestCancelFromCallback);
            Run("CancelFromAnotherThread", TestCancelFromAnotherThread);
            Run("DisposeWhileStepping", TestDisposeWhileStepping);
            Run("Editing", TestEditing);
            Run("EditParams", TestEditParams);
            Run("TaskMasksAndParts", TestTaskMasksAndParts);
            Run("ShortReference", TestShortReference);
            Run("ReferencePoses", TestReferencePoses);
            Run("EditOtherFamilies", TestEditOtherFamilies);
            Run("PromptStages", TestPromptStages);
            Run("PromptStageErrors", TestPromptStageErrors);
            Run("Stream", TestStream);
            Run("StreamCleaned", TestStreamCleaned);
            Run("StreamLooped", TestStreamLooped);
            Run("StreamCancelBetweenPumps", TestStreamCancelBetweenPumps);
            Run("StreamCancelFromAnotherThread", TestStreamCancelFromAnotherThread);
            Run("StreamCancelLongPump", TestStreamCancelLongPump);
            Run("StreamStagesFineMoGen", TestStreamStagesFineMoGen);
            Run("StreamStagesRefused", TestStreamStagesRefused);
            Run("StreamStageErrors", TestStreamStageErrors);
            Run("StreamMola", TestStreamMola);
            Run("FineMoGenStages", TestFineMoGenStages);
            Run("PositionTargets", TestPositionTargets);
            Run("PositionTargetErrors", TestPositionTargetErrors);
            Run("TaskTargets", TestTaskTargets);
            Run("SampleShapeAndReadFrames", TestSampleShapeAndReadFrames);
            Run("LatentModel", TestLatentModel);
            Run("GltfExport", TestGltfExport);
            Run("GltfHumanMl263", TestGltfHumanMl263);
            Run("GltfFiles", TestGltfFiles);
            Run("GltfErrors", TestGltfErrors);
            Run("CleanupOffIsRaw", TestCleanupOffIsRaw);
            Run("CleanupFps", TestCleanupFps);
            Run("CleanupRootMotion", TestCleanupRootMotion);
            Run("CleanupFeetAndGround", TestCleanupFeetAndGround);
            Run("CleanupErrors", TestCleanupErrors);
            Run("CleanupGltf", TestCleanupGltf);
            Run("TwoThreads", TestTwoThreads);
            Run("RetargetLayouts", TestRetargetLayouts);
            Run("RigFromBones", TestRigFromBones);
            Run("RetargetDirections", TestRetargetDirections);
            Run("RetargetReads", TestRetargetReads);
            Run("RetargetStream", TestRetargetStream);
            Run("RigLoad", TestRigLoad);
            Run("RetargetErrors", TestRetargetErrors);
            Run("DisposedHandles", TestDisposedHandles);
        }
        Console.WriteLine(passed + " passed, " + failed + " failed");
        return failed == 0 ? 0 : 1;
    }

    // --- a tiny harness ---------------------------------------------------------------------

    static void Run(string name, Action test)
    {
        int before = failed;
        try
        {
            test();
        }
        catch (Exception e)
        {
            failed++;
            Console.Error.WriteLine("FAIL " + name + ": unexpected " + e);
        }
        Console.WriteLine((failed == before ? "ok   " : "FAIL ") + name);
    }

    static void Check(bool ok, string what)
    {
        if (ok)
        {
            passed++;
            return;
        }
        failed++;
        Console.Error.WriteLine("  check failed: " + what + "\n" + new StackTrace(1, true).GetFrame(0));
    }

    /// <summary>Runs action and checks that it throws a FlameException with this status and a
    /// message containing fragment.</summary>
    static void Throws(FlameStatus status, string fragment, Action action)
    {
        try
        {
            action();
        }
        catch (FlameException e)
        {
            Check(e.Status == status && e.NativeMessage.Contains(fragment),
                  "expected " + status + " containing \"" + fragment + "\", got " + e.Status + " \"" + e.NativeMessage + "\"");
            return;
        }
        catch (Exception e)
        {
            Check(false, "expected FlameException " + status + ", got " + e.GetType().Name + ": " + e.Message);
            return;
        }
        Check(false, "expected FlameException " + status + " containing \"" + fragment + "\", nothing thrown");
    }

    static void ThrowsManaged<T>(Action action) where T : Exception
    {
        try
        {
            action();
        }
        catch (T)
        {
            Check(true, "");
            return;
        }
        catch (Exception e)
        {
            Check(false, "expected " + typeof(T).Name + ", got " + e.GetType().Name + ": " + e.Message);
            return;
        }
        Check(false, "expected " + typeof(T).Name + ", nothing thrown");
    }

    static bool BitEqual(float[] a, float[] b)
    {
        if (a == null || b == null || a.Length != b.Length)
            return false;
        for (int i = 0; i < a.Length; i++)
            if (BitConverter.ToInt32(BitConverter.GetBytes(a[i]), 0) != BitConverter.ToInt32(BitConverter.GetBytes(b[i]), 0))
                return false;
        return true;
    }

    static FlameSessionParams RefParams()
    {
        var p = FlameSessionParams.Default();
        p.frames = RefFrames;
        p.steps = 10;
        p.sampler = (int)FlameSampler.Ddim;
        p.seed = 3;
        p.threads = 1;
        return p;
    }

    static FlameSession RefSession()
    {
        var s = model.NewSession(RefParams());
        s.SetPrompt(RefPrompt);
        return s;
    }

    static float[] RunAll(FlameSession s)
    {
        while (s.StepsLeft > 0)
            s.Step();
        return s.Read();
    }

    // --- tests --------------------------------------------------------------------------------

    static string Key(string name)
    {
        return name.Replace("_", "").ToLowerInvariant();
    }

    /// <summary>name → value of the header's PREFIX_NAME = value (or #define PREFIX_NAME value).</summary>
    static Dictionary<string, long> HeaderValues(string prefix)
    {
        var values = new Dictionary<string, long>();
        foreach (Match m in Regex.Matches(header, prefix + @"(\w+)\s*=?\s*(-?\d+)"))
            values[Key(m.Groups[1].Value)] = long.Parse(m.Groups[2].Value);
        return values;
    }

    static void CheckValues(string prefix, Dictionary<string, long> ours)
    {
        var theirs = HeaderValues(prefix);
        bool same = theirs.Count > 0 && theirs.Count == ours.Count && theirs.All(kv => ours.ContainsKey(kv.Key) && ours[kv.Key] == kv.Value);
        Check(same, prefix + "* values: header {" + string.Join(", ", theirs.Select(kv => kv.Key + "=" + kv.Value)) +
                    "} vs bindings {" + string.Join(", ", ours.Select(kv => kv.Key + "=" + kv.Value)) + "}");
    }

    static Dictionary<string, long> EnumValues(Type t)
    {
        return Enum.GetNames(t).ToDictionary(n => Key(n), n => Convert.ToInt64(Enum.Parse(t, n)));
    }

    static Dictionary<string, long> ConstValues(Type t)
    {
        return t.GetFields(BindingFlags.Public | BindingFlags.Static).Where(f => f.IsLiteral)
                .ToDictionary(f => Key(f.Name), f => Convert.ToInt64(f.GetRawConstantValue()));
    }

    static void TestHeaderCoverage()
    {
        // Every function of the header has a declaration, and the named values agree with it.
        var declared = new HashSet<string>();
        foreach (Match m in Regex.Matches(header, @"^[a-z][^;()]*?\b(flame_\w+)\(", RegexOptions.Multiline))
            declared.Add(m.Groups[1].Value);
        var bound = new HashSet<string>(typeof(FlameNative).GetMethods(BindingFlags.Public | BindingFlags.Static)
                                        .Where(m => (m.Attributes & MethodAttributes.PinvokeImpl) != 0).Select(m => m.Name));
        Check(declared.Count >= 25 && declared.SetEquals(bound),
              "functions: missing {" + string.Join(", ", declared.Except(bound)) + "}, extra {" + string.Join(", ", bound.Except(declared)) + "}");
        CheckValues("FLAME_STATUS_", EnumValues(typeof(FlameStatus)));
        CheckValues("FLAME_SAMPLER_", EnumValues(typeof(FlameSampler)));
        CheckValues("FLAME_WHICH_", EnumValues(typeof(FlameWhich)));
        CheckValues("FLAME_LAYOUT_", ConstValues(typeof(FlameLayout)));
        CheckValues("FLAME_CONVENTION_", ConstValues(typeof(FlameConvention)));
        CheckValues("FLAME_READ_", ConstValues(typeof(FlameReadFlags)));
        CheckValues("FLAME_EDIT_METHOD_", EnumValues(typeof(FlameEditMethod)));
        CheckValues("FLAME_BODY_PART_", EnumValues(typeof(FlameBodyPart)));
        CheckValues("FLAME_EDIT_TASK_", EnumValues(typeof(FlameEditTask)));
        CheckValues("FLAME_WEIGHTS_", EnumValues(typeof(FlameWeights)));
        CheckValues("FLAME_TARGET_SCHEDULE_", EnumValues(typeof(FlameTargetSchedule)));
        CheckValues("FLAME_GLTF_CONTAINER_", EnumValues(typeof(FlameGltfContainer)));
        CheckValues("FLAME_RIG_FORMAT_", ConstValues(typeof(FlameRigFormat)));
        foreach (var f in typeof(FlameRobotFile).GetFields(BindingFlags.Public | BindingFlags.Static))
        {
            string c = Regex.Replace(f.Name, "(?<=[a-z])(?=[A-Z])", "_").ToUpperInvariant();
            Check(header.Contains("#define FLAME_ROBOT_" + c + " " + f.GetRawConstantValue() + "\n"), "FLAME_ROBOT_" + c);
        }
        // The cleanup enums are not in the header (no function takes them by type): their
        // values come from the Rust declarations in src/ffi/cleanup.rs.
        string rust = File.ReadAllText(Path.Combine(Path.GetDirectoryName(Path.GetDirectoryName(Path.GetFullPath(headerPath))),
                                                    "src", "ffi", "cleanup.rs"));
        CheckRustEnum(rust, "FlameFeet", EnumValues(typeof(FlameFeet)));
        CheckRustEnum(rust, "FlameRootMotion", EnumValues(typeof(FlameRootMotion)));
        Check(header.Contains("#define FLAME_ABI_VERSION " + FlameNative.AbiVersion + "\n"), "ABI version");
        Check(header.Contains("#define FLAME_ROOT_TRANSLATION " + FlameNative.RootTranslation + "\n"), "FLAME_ROOT_TRANSLATION");
        Check(header.Contains("#define FLAME_MAX_THREADS " + FlameNative.MaxThreads + "\n"), "FLAME_MAX_THREADS");
    }

    static void CheckRustEnum(string rust, string name, Dictionary<string, long> ours)
    {
        var body = Regex.Match(rust, "pub enum " + name + @" \{(.*?)\n\}", RegexOptions.Singleline).Groups[1].Value;
        var theirs = new Dictionary<string, long>();
        foreach (Match m in Regex.Matches(body, @"^\s*(\w+) = (\d+),", RegexOptions.Multiline))
            theirs[Key(m.Groups[1].Value)] = long.Parse(m.Groups[2].Value);
        Check(theirs.Count > 0 && theirs.Count == ours.Count && theirs.All(kv => ours.ContainsKey(kv.Key) && ours[kv.Key] == kv.Value),
              name + " values: Rust {" + string.Join(", ", theirs.Select(kv => kv.Key + "=" + kv.Value)) + "} vs bindings {" +
              string.Join(", ", ours.Select(kv => kv.Key + "=" + kv.Value)) + "}");
    }

    static void TestVersion()
    {
        Check(FlameNative.flame_abi_version() == FlameNative.AbiVersion, "ABI version");
        Check(FlameLibrary.Version.Split('.').Length == 3, "version " + FlameLibrary.Version);
        Check(FlameNative.Utf8(FlameNative.flame_status_string(3)) == "FLAME_STATUS_BAD_MODEL_FILE", "status string");
        Check(FlameNative.Utf8(FlameNative.flame_status_string(99)) == "FLAME_STATUS_UNKNOWN", "unknown status string");
    }

    static void TestStructLayouts()
    {
        // The library writes sizeof(struct) into struct_size: the C# mirrors must agree.
        Check(FlameModelParams.Default().struct_size == Marshal.SizeOf(typeof(FlameModelParams)), "sizeof FlameModelParams");
        var sp = FlameSessionParams.Default();
        Check(sp.struct_size == Marshal.SizeOf(typeof(FlameSessionParams)), "sizeof FlameSessionParams " + sp.struct_size + " vs " + Marshal.SizeOf(typeof(FlameSessionParams)));
        Check(sp.frames == 0 && sp.steps == 0 && sp.sampler == 0 && sp.eta < 0 && sp.guidance < 0 && sp.seed == 0 && sp.threads == 0, "session defaults");
        Check((int)Marshal.OffsetOf(typeof(FlameSessionParams), "seed") == 24, "offset of seed");
        Check((int)Marshal.OffsetOf(typeof(FlameSessionParams), "respacing") == 40 && sp.respacing == IntPtr.Zero, "respacing field");
        // ABI 4: a uint32 after the pointer (C on x86-64: offsetof looped 48, sizeof 56).
        Check((int)Marshal.OffsetOf(typeof(FlameSessionParams), "looped") == 40 + IntPtr.Size && sp.looped == 0, "looped field");
        Check(Marshal.SizeOf(typeof(FlameSessionParams)) == 56 || IntPtr.Size == 4, "sizeof FlameSessionParams " + Marshal.SizeOf(typeof(FlameSessionParams)));
        Check((int)Marshal.OffsetOf(typeof(FlameModelInfo), "architecture") == 48 || IntPtr.Size == 4, "offset of architecture");
        // ABI 2: two uint32 after the five pointers (C on x86-64: offsetof latent 88, sizeof 96).
        Check((int)Marshal.OffsetOf(typeof(FlameModelInfo), "latent") == 88 || IntPtr.Size == 4, "offset of latent");
        Check((int)Marshal.OffsetOf(typeof(FlameModelInfo), "sample_dim") == 92 || IntPtr.Size == 4, "offset of sample_dim");
        Check((int)Marshal.OffsetOf(typeof(FlameModelInfo), "control") == 96 || IntPtr.Size == 4, "offset of control");
        Check(Marshal.SizeOf(typeof(FlameModelInfo)) == 104 || IntPtr.Size == 4, "sizeof FlameModelInfo " + Marshal.SizeOf(typeof(FlameModelInfo)));
        var ep = FlameEditParams.Default();
        Check(ep.struct_size == Marshal.SizeOf(typeof(FlameEditParams)) && ep.struct_size == 20, "sizeof FlameEditParams " + ep.struct_size);
        // FlamePromptInfo: six uint32 then a pointer, no padding (C: sizeof 32, offsetof dropped 24 on x86-64).
        Check(Marshal.SizeOf(typeof(FlamePromptInfo)) == 24 + IntPtr.Size, "sizeof FlamePromptInfo " + Marshal.SizeOf(typeof(FlamePromptInfo)));
        Check((int)Marshal.OffsetOf(typeof(FlamePromptInfo), "dropped") == 24, "offset of dropped");
        var tp = FlameTargetParams.Default();
        Check(tp.struct_size == Marshal.SizeOf(typeof(FlameTargetParams)) && tp.struct_size == 12, "sizeof FlameTargetParams " + tp.struct_size);
        Check(tp.scale == 0.6f && tp.schedule == (int)FlameTargetSchedule.Mpgd, "target defaults");
        Check(ep.method == (int)FlameEditMethod.Auto && ep.edit_till == 0.2f && ep.paste == 1 && ep.seam_frames == 4, "edit defaults");
        // FlameStage: two uint32 then eight pointers (C: sizeof 72, offsetof text 8 on x86-64).
        Check(Marshal.SizeOf(typeof(FlameStage)) == 8 + 8 * IntPtr.Size, "sizeof FlameStage " + Marshal.SizeOf(typeof(FlameStage)));
        Check((int)Marshal.OffsetOf(typeof(FlameStage), "text") == 8 &&
              (int)Marshal.OffsetOf(typeof(FlameStage), "pelvis") == 8 + 7 * IntPtr.Size, "offsets of FlameStage");
        // FlameGltfParams: three uint32 and a float, then two pointers (C: sizeof 32, offsetof
        // name 16, cleanup 24 on x86-64).
        var gp = FlameGltfParams.Default();
        Check(gp.struct_size == Marshal.SizeOf(typeof(FlameGltfParams)) && gp.struct_size == 16 + 2 * IntPtr.Size,
              "sizeof FlameGltfParams " + gp.struct_size);
        Check((int)Marshal.OffsetOf(typeof(FlameGltfParams), "name") == 16, "offset of FlameGltfParams.name");
        Check((int)Marshal.OffsetOf(typeof(FlameGltfParams), "cleanup") == 16 + IntPtr.Size, "offset of FlameGltfParams.cleanup");
        Check(gp.container == (int)FlameGltfContainer.Glb && gp.flags == 0 && gp.fps == 0 && gp.name == IntPtr.Zero &&
              gp.cleanup == IntPtr.Zero, "glTF defaults");
        // FlameCleanupParams: eleven 32-bit fields (C: sizeof 44), game-ready defaults.
        var cp = FlameCleanupParams.Default();
        Check(cp.struct_size == 44 && Marshal.SizeOf(typeof(FlameCleanupParams)) == 44, "sizeof FlameCleanupParams " + cp.struct_size);
        Check((int)Marshal.OffsetOf(typeof(FlameCleanupParams), "fps") == 24 &&
              (int)Marshal.OffsetOf(typeof(FlameCleanupParams), "contact_min_span") == 40, "offsets of FlameCleanupParams");
        Check(cp.Feet == FlameFeet.Lock && cp.ground == 1 && cp.RootMotion == FlameRootMotion.Keep && cp.remove_yaw == 0 &&
              cp.wrap == 0 && cp.fps == 0, "cleanup defaults: feet locked, ground on, root kept, the model's fps");
        Check(cp.contact_height == 0.05f && cp.contact_speed == 0.8944272f && cp.contact_release == 1.5f && cp.contact_min_span == 0.1f,
              "cleanup defaults: contact detection");
        var raw = FlameCleanupParams.Raw();
        Check(raw.Feet == FlameFeet.Off && raw.ground == 0 && raw.struct_size == 44 && raw.contact_height == 0.05f, "Raw(): every step off");
    }

    static void TestLoadErrors()
    {
        string missing = Path.Combine(tmpDir, "no_such_model.safetensors");
        Throws(FlameStatus.Io, "no_such_model.safetensors", () => FlameModel.Load(missing));
        string bad = Path.Combine(tmpDir, "bad.safetensors");
        File.WriteAllBytes(bad, Encoding.ASCII.GetBytes("not a model"));
        Throws(FlameStatus.BadModelFile, "bad model file", () => FlameModel.Load(bad));
        Throws(FlameStatus.BadModelFile, "too short", () => FlameModel.LoadFromMemory(new byte[0]));
        var truncated = new byte[5000];
        Array.Copy(File.ReadAllBytes(modelPath), truncated, truncated.Length);
        Throws(FlameStatus.BadModelFile, "bad model file", () => FlameModel.LoadFromMemory(truncated));
        ThrowsManaged<ArgumentNullException>(() => FlameModel.Load(null));
        // The exception's text carries the status name.
        try
        {
            FlameModel.Load(missing);
        }
        catch (FlameException e)
        {
            Check(e.Message.StartsWith("FLAME_STATUS_IO: cannot read "), e.Message);
        }
    }

    static void TestInfo()
    {
        var i = model.Info;
        Check(i.FeatureDim == Dim && i.MaxFrames == 470 && i.NumTimesteps == 1000, "dims");
        Check(i.DefaultSteps == 1000 && i.DefaultSampler == FlameSampler.Ddpm && i.DefaultGuidance == 8f, "defaults");
        Check(i.DefaultFrames >= 1 && i.DefaultFrames <= i.MaxFrames, "default frames");
        Check(i.Architecture == "flame" && i.MotionFormat == "smpl24_6d" && i.TextEncoder == "roberta",
              i.Architecture + " " + i.MotionFormat + " " + i.TextEncoder);
        Check(i.Fps == 20f, "fps");
        Check(i.JointNames.Length == i.JointCount && i.JointParents.Length == i.JointCount, "joint arrays");
        for (int j = 0; j < i.JointCount; j++)
        {
            int p = i.JointParents[j];
            Check(j == 0 ? p == -1 : (p >= 0 && p < j), "parent of joint " + j + " is " + p);
            Check(!string.IsNullOrEmpty(i.JointNames[j]), "name of joint " + j);
        }
    }

    static void TestMatchesCli()
    {
        using (var s = RefSession())
        {
            var output = RunAll(s);
            Check(output.Length == RefFrames * Dim, "length " + output.Length);
            Check(BitEqual(output, reference), "features equal the CLI's bit for bit");
        }
        var p = RefParams();
        p.threads = 2;
        using (var s = model.NewSession(p))
        {
            s.SetPrompt(RefPrompt);
            Check(BitEqual(RunAll(s), reference), "two threads give the same bits");
        }
    }

    static void TestPromptFrom()
    {
        // A prompt encoded once serves another session of the same model: the CLI's bits.
        using (var a = model.NewSession(RefParams()))
        using (var b = model.NewSession(RefParams()))
        {
            Throws(FlameStatus.WrongState, "no prompt", () => b.SetPromptFrom(a));
            a.SetPrompt(RefPrompt);
            b.SetPromptFrom(a);
            Check(b.PromptInfo().Tokens == a.PromptInfo().Tokens, "the prompt report follows");
            Check(BitEqual(RunAll(b), reference), "features equal the CLI's bit for bit");
            ThrowsManaged<ArgumentNullException>(() => b.SetPromptFrom(null));
            using (var other = FlameModel.Load(modelPath, 1))
            using (var c = other.NewSession(RefParams()))
                Throws(FlameStatus.InvalidArgument, "another model", () => c.SetPromptFrom(a));
        }
    }

    // MotionLCM's consistency latent tuning (tests/fixtures/motionlcm_v2_control_tiny): a pelvis
    // path followed through the ControlNet after 20 iterations, bit for bit the CLI's
    // `generate --control --optimize 20`; the hint is followed closer; refusals.
    static void TestLatentTuning()
    {
        string dir = Path.GetDirectoryName(Path.GetFullPath(modelPath));
        string control = Path.Combine(dir, "motionlcm_v2_control_tiny.safetensors");
        const int frames = 24;
        var hint = new float[frames * 22 * 3];
        for (int i = 0; i < hint.Length; i++)
            hint[i] = float.NaN;
        for (int f = 0; f < frames; f++)
        {
            hint[f * 66] = 0.05f * f;
            hint[f * 66 + 1] = 0.9f;
            hint[f * 66 + 2] = 0.02f * f;
        }
        string hintPath = Path.Combine(tmpDir, "tuning_hint.npy"), outPath = Path.Combine(tmpDir, "tuning_out.npy");
        Npy.WriteShape(hintPath, hint, frames + ", 22, 3");
        string prompt = "a person walks forward";
        var psi = new ProcessStartInfo(cliPath,
            "generate --model \"" + control + "\" --prompt \"" + prompt + "\" --frames 24 --steps 1 --seed 5 --threads 1 " +
            "--convention native --control \"" + hintPath + "\" --optimize 20 --out \"" + outPath + "\"");
        psi.UseShellExecute = false;
        psi.RedirectStandardOutput = true;
        psi.RedirectStandardError = true;
        using (var proc = Process.Start(psi))
        {
            proc.StandardOutput.ReadToEnd();
            string err = proc.StandardError.ReadToEnd();
            proc.WaitForExit();
            Check(proc.ExitCode == 0, "CLI --optimize: exit code " + proc.ExitCode + " " + err);
        }
        int[] shape;
        var expected = Npy.Read(outPath, out shape);
        using (var m = FlameModel.Load(control, 1))
        {
            var p = FlameSessionParams.Default();
            p.frames = frames;
            p.steps = 1;
            p.seed = 5;
            p.threads = 1;
            using (var s = m.NewSession(p))
            {
                s.SetPrompt(prompt);
                Throws(FlameStatus.WrongState, "set one first", () => s.TuneLatent(5));
                s.SetControl(hint, null, FlameConvention.Native);
                var r = s.TuneLatent(20);
                Check(r.iterations == 20 && r.control_error_after < r.control_error_before,
                      "tuning follows the hint closer: " + r.control_error_before + " -> " + r.control_error_after);
                Check(BitEqual(RunAll(s), expected), "tuned motion = CLI --optimize");
                Throws(FlameStatus.WrongState, "before the first step", () => s.TuneLatent(5));
            }
        }
    }

    static void TestLoadFromMemory()
    {
        using (var m = FlameModel.LoadFromMemory(File.ReadAllBytes(modelPath)))
        using (var s = m.NewSession(RefParams()))
        {
            s.SetPrompt(RefPrompt);
            Check(BitEqual(RunAll(s), reference), "from memory = CLI");
        }
    }

    static void TestHalfWeights()
    {
        foreach (var w in new[] { FlameWeights.F16, FlameWeights.Bf16 })
            using (var m = FlameModel.Load(modelPath, 1, w))
            using (var s = m.NewSession(RefParams()))
            {
                s.SetPrompt(RefPrompt);
                var got = RunAll(s);
                bool finite = true;
                foreach (var v in got)
                    finite &= !float.IsNaN(v) && !float.IsInfinity(v);
                Check(finite, w + " weights: finite output");
                Check(!BitEqual(got, reference), w + " weights: narrowed");
            }
    }

    static void TestStepsEstimateReset()
    {
        using (var s = RefSession())
        {
            Check(s.StepsDone == 0 && s.StepsTotal == 10 && s.StepsLeft == 10, "progress before");
            Check(s.Step() == 9, "steps left after one step");
            var est = s.Read(FlameWhich.Estimate, FlameLayout.Features, FlameConvention.Native, 0);
            Check(est.Length == RefFrames * Dim, "estimate length");
            Check(!BitEqual(est, s.Read()), "estimate differs from x_t mid-way");
            int last = -1;
            for (int k = 0; k < 9; k++)
                last = s.Step();
            Check(last == 0, "last step leaves 0");
            Check(BitEqual(s.Read(), reference), "final = CLI");
            Throws(FlameStatus.WrongState, "finished", () => s.Step());
            s.Reset();
            Check(s.StepsLeft == 10, "reset restarts");
            Check(BitEqual(RunAll(s), reference), "reset reproduces");
        }
    }

    // "ddim4" keeps {0, 250, 500, 750} of the 1000 steps, as do four one-step sections
    // "1,1,1,1"; "4" keeps {0, 333, 666, 999}, as steps = 4 does.
    static void TestRespacing()
    {
        Func<uint, string, float[]> run = (steps, spec) =>
        {
            var p = RefParams();
            p.frames = 8;
            p.steps = steps;
            using (var s = model.NewSession(p, spec))
            {
                Check(s.StepsTotal == 4, "4 steps for " + spec);
                s.SetPrompt(RefPrompt);
                return RunAll(s);
            }
        };
        var stride = run(0, "ddim4");
        Check(BitEqual(stride, run(0, "1,1,1,1")), "ddim4 = 1,1,1,1");
        Check(BitEqual(stride, run(4, "ddim4")), "agreeing steps");
        var sections = run(0, "4");
        Check(BitEqual(sections, run(4, null)), "\"4\" = steps 4");
        Check(!BitEqual(stride, sections), "ddim4 differs from 4");
        var q = RefParams();
        q.steps = 5;
        Throws(FlameStatus.InvalidArgument, "steps 5 disagrees with respacing \"ddim4\"", () => model.NewSession(q, "ddim4").Dispose());
        Throws(FlameStatus.InvalidArgument, "cannot create exactly 999 steps", () => model.NewSession(RefParams(), "ddim999").Dispose());
    }

    // --- loops made by the session (FlameSessionParams.looped, ABI 4) ---------------------------
    // Two passes (a generation, then an edit across the wrap); the finished sample reads as the
    // cycle. Reference: `flame generate --loop --feet off --ground off --positions` (as
    // tests/c/run.sh's loop_positions and test_cleanup.c's test_loop).

    const int LoopFrames = 40;

    static FlameSessionParams LoopParams()
    {
        var p = FlameSessionParams.Default();
        p.frames = LoopFrames;
        p.steps = 4;
        p.sampler = (int)FlameSampler.Ddim;
        p.seed = 5;
        p.threads = 1;
        p.looped = 1;
        return p;
    }

    static void TestLoopSession()
    {
        string positionsPath = Path.Combine(tmpDir, "loop_positions.npy");
        var psi = new ProcessStartInfo(cliPath,
            "generate --model \"" + modelPath + "\" --prompt \"" + RefPrompt + "\" --frames 40 --steps 4 --sampler ddim --seed 5 --threads 1 " +
            "--loop --feet off --ground off --positions \"" + positionsPath + "\" --out \"" + Path.Combine(tmpDir, "loop.json") + "\"");
        psi.UseShellExecute = false;
        psi.RedirectStandardOutput = true;
        psi.RedirectStandardError = true;
        using (var proc = Process.Start(psi))
        {
            proc.StandardOutput.ReadToEnd();
            proc.StandardError.ReadToEnd();
            proc.WaitForExit();
            Check(proc.ExitCode == 0, "CLI --loop exit code " + proc.ExitCode);
        }
        int[] shape;
        var cli = Npy.Read(positionsPath, out shape);
        Check(shape.Length == 3 && shape[0] == LoopFrames && shape[1] == 24 && shape[2] == 3, "CLI positions shape " + string.Join("x", shape));

        var seen = new List<int[]>();
        using (var s = model.NewSession(LoopParams()))
        {
            Check(s.Frames == LoopFrames, "Frames = the cycle: " + s.Frames);
            s.SetPrompt(RefPrompt);
            s.SetProgressCallback((done, total) => seen.Add(new[] { done, total }));
            // Both passes: 8 steps, counted down across the edit.
            Check(s.StepsDone == 0 && s.StepsTotal == 8, "progress " + s.StepsDone + "/" + s.StepsTotal);
            var left = new List<int>();
            for (int i = 0; i < 8; i++)
                left.Add(s.Step());
            Check(left.SequenceEqual(new[] { 7, 6, 5, 4, 3, 2, 1, 0 }), "steps left " + string.Join(",", left));
            Check(s.StepsDone == 8 && s.StepsTotal == 8 && s.StepsLeft == 0, "progress at the end " + s.StepsDone + "/" + s.StepsTotal);
            Check(seen.Count == 8 && seen.Select((c, i) => c[0] == i + 1 && c[1] == 8).All(x => x),
                  "callback: " + string.Join(" ", seen.Select(c => c[0] + "/" + c[1])));
            // The cycle's frames; the raw features without the next cycle's first frame.
            Check(s.ReadFrames(FlameWhich.Sample) == LoopFrames, "ReadFrames " + s.ReadFrames(FlameWhich.Sample));
            int featureFrames;
            var features = s.Read(FlameWhich.Sample, FlameLayout.Features, FlameConvention.Native, 0, out featureFrames);
            Check(featureFrames == LoopFrames && features.Length == LoopFrames * Dim, "features " + featureFrames + " frames, " + features.Length + " values");
            Check(features.All(v => !float.IsNaN(v) && !float.IsInfinity(v)), "finite features");
            // A read with no cleanup still wraps: what the CLI wrote, bit for bit.
            int posFrames;
            var pos = s.Read(FlameWhich.Sample, FlameLayout.GlobalPositions, FlameConvention.Native, FlameReadFlags.Smooth, out posFrames);
            Check(posFrames == LoopFrames && pos.Length == LoopFrames * 24 * 3, "positions " + posFrames + " frames, " + pos.Length + " values");
            Check(BitEqual(pos, cli), "loop positions = CLI --loop --positions, bit for bit");
            // The loop's edit is its own.
            Throws(FlameStatus.InvalidArgument, "its own edit", () => s.SetReference(new float[Dim], 1, Dim));
        }
    }

    static void TestLoopRefusals()
    {
        var p = LoopParams();
        p.frames = 12;
        Throws(FlameStatus.InvalidArgument, "at least 40 frames", () => model.NewSession(p).Dispose());
        p = LoopParams();
        p.looped = 2;
        Throws(FlameStatus.InvalidArgument, "`looped`", () => model.NewSession(p).Dispose());
        // looped 0 is the plain session of before (4 steps).
        p = LoopParams();
        p.looped = 0;
        using (var s = model.NewSession(p))
            Check(s.StepsTotal == 4, "plain session: " + s.StepsTotal + " steps");
        string mola = Path.Combine(Path.GetDirectoryName(Path.GetFullPath(modelPath)), "mola_tiny.safetensors");
        using (var m = FlameModel.Load(mola, 1))
        {
            p = LoopParams();
            p.frames = 60;
            Throws(FlameStatus.InvalidArgument, "samples a latent", () => m.NewSession(p).Dispose());
        }
    }

    static void TestSessionErrors()
    {
        using (var s = model.NewSession(RefParams()))
        {
            Throws(FlameStatus.WrongState, "set a prompt", () => s.Step());
            Throws(FlameStatus.WrongState, "no sample yet", () => s.Read());
            s.SetPrompt(RefPrompt);
            Throws(FlameStatus.WrongState, "no clean-motion estimate", () => s.Read(FlameWhich.Estimate, 0, 0, 0));
            Throws(FlameStatus.InvalidArgument, "initial noise has 10 values", () => s.SetNoise(new float[10]));
            var nan = new float[RefFrames * Dim];
            nan[5] = float.NaN;
            Throws(FlameStatus.InvalidArgument, "NaN", () => s.SetNoise(nan));
            s.Step();
            Throws(FlameStatus.InvalidArgument, "unknown layout 999", () => s.Read(FlameWhich.Sample, 999, FlameConvention.Native, 0));
            Throws(FlameStatus.InvalidArgument, "unknown `which` 5", () => s.Read((FlameWhich)5, 0, 0, 0));
            Throws(FlameStatus.InvalidArgument, "frame range from 5 to 5", () => s.KeepFrames(5, 5));
            Throws(FlameStatus.InvalidArgument, "past the session's 24 frames", () => s.KeepFrames(0, 25));
            Throws(FlameStatus.InvalidArgument, "joint 24", () => s.KeepJoints(24));
            Throws(FlameStatus.InvalidArgument, "want 1 to 24 frames", () => s.SetReference(new float[25 * Dim], 25, Dim));
            Throws(FlameStatus.InvalidArgument, "does not match", () => s.SetMask(new byte[RefFrames * 146], RefFrames, 146));
            Throws(FlameStatus.WrongState, "before the first step", () => s.SetNoise(new float[RefFrames * Dim]));
            ThrowsManaged<ArgumentException>(() => s.SetReference(new float[10]));   // checked before native code
            ThrowsManaged<ArgumentException>(() => s.SetMask(new bool[10]));
            ThrowsManaged<ArgumentNullException>(() => s.SetPrompt(null));
        }
        var p = RefParams();
        p.frames = 471;
        Throws(FlameStatus.InvalidArgument, "frames must be between 1 and 470 for this model, got 471", () => model.NewSession(p).Dispose());
        p = RefParams();
        p.steps = 1001;
        Throws(FlameStatus.InvalidArgument, "steps must be between 1 and 1000 for this model, got 1001", () => model.NewSession(p).Dispose());
        p = RefParams();
        p.sampler = 7;
        Throws(FlameStatus.InvalidArgument, "unknown sampler 7", () => model.NewSession(p).Dispose());
        p = RefParams();
        p.guidance = float.NaN;
        Throws(FlameStatus.InvalidArgument, "`guidance` is NaN", () => model.NewSession(p).Dispose());
        p = RefParams();
        p.struct_size = 8;
        Throws(FlameStatus.InvalidArgument, "params.struct_size is 8", () => model.NewSession(p).Dispose());
    }

    // The fixture's RoBERTa window: 20 tokens, <s> and </s> included.
    const int Window = 20;
    const string LongPrompt = "a person walks forward, turns left, raises both arms, waves with the right hand, "
                              + "sits down on a chair and then kicks with the right leg";

    static void TestPromptInfo()
    {
        using (var s = model.NewSession(RefParams()))
        {
            Throws(FlameStatus.WrongState, "no prompt", () => s.PromptInfo());
            s.SetPrompt(LongPrompt);
            var info = s.PromptInfo();
            Check(info.Window == Window && info.Kept == Window && info.Tokens > Window, "long: window " + info.Window + " kept " + info.Kept + " tokens " + info.Tokens);
            Check(info.Truncated && !info.Unconditional, "long: truncated, conditional");
            Check(info.Dropped.Length > 0 && LongPrompt.EndsWith(info.Dropped, StringComparison.Ordinal)
                  && info.Dropped.EndsWith("kicks with the right leg", StringComparison.Ordinal), "dropped is the prompt's tail: \"" + info.Dropped + "\"");
            // What was kept, on its own, fits the window as the cut prompt did.
            s.SetPrompt(LongPrompt.Substring(0, LongPrompt.Length - info.Dropped.Length).TrimEnd());
            var rest = s.PromptInfo();
            Check(!rest.Truncated && rest.Tokens >= Window - 1 && rest.Tokens <= Window, "the kept text fits: " + rest.Tokens);

            s.SetPrompt("a person walks");
            var shortInfo = s.PromptInfo();
            Check(!shortInfo.Truncated && !shortInfo.Unconditional && shortInfo.Dropped == ""
                  && shortInfo.Kept == shortInfo.Tokens && shortInfo.Tokens < Window, "short prompt: " + shortInfo.Tokens);
            foreach (var blank in new[] { "", "  \t " })
            {
                s.SetPrompt(blank);
                var none = s.PromptInfo();
                Check(none.Unconditional && !none.Truncated && none.Dropped == "", "blank prompt is unconditional");
            }
            // Non-ASCII text in the dropped tail comes back as the same string (UTF-8 by hand).
            string accented = LongPrompt + " près du café à l'été";
            s.SetPrompt(accented);
            var acc = s.PromptInfo();
            Check(acc.Truncated && accented.EndsWith(acc.Dropped, StringComparison.Ordinal)
                  && acc.Dropped.EndsWith("café à l'été", StringComparison.Ordinal), "non-ASCII dropped: \"" + acc.Dropped + "\"");

            // The raw call checks struct_size.
            var raw = new FlamePromptInfo();
            raw.struct_size = (uint)Marshal.SizeOf(typeof(FlamePromptInfo)) - 1;
            Throws(FlameStatus.InvalidArgument, "struct_size", () => FlameException.Check(FlameNative.flame_session_prompt_info(s.Handle, ref raw)));
        }
        using (var none = new FlameSessionHandle())
        {
            var raw = new FlamePromptInfo();
            raw.struct_size = (uint)Marshal.SizeOf(typeof(FlamePromptInfo));
            Throws(FlameStatus.InvalidArgument, "`session` is NULL", () => FlameException.Check(FlameNative.flame_session_prompt_info(none, ref raw)));
        }
    }

    static void TestNullArguments()
    {
        // NULL handles and pointers through the raw declarations: INVALID_ARGUMENT, not a crash.
        using (var none = new FlameSessionHandle())
        {
            Throws(FlameStatus.InvalidArgument, "`session` is NULL", () => FlameException.Check(FlameNative.flame_session_reset(none)));
            uint left;
            Throws(FlameStatus.InvalidArgument, "`session` is NULL", () => FlameException.Check(FlameNative.flame_session_step(none, out left)));
            Throws(FlameStatus.InvalidArgument, "`session` is NULL", () => FlameException.Check(FlameNative.flame_session_cancel(none)));
        }
        using (var none = new FlameModelHandle())
        {
            var sp = FlameSessionParams.Default();
            FlameSessionHandle h;
            Throws(FlameStatus.InvalidArgument, "`model` is NULL", () => FlameException.Check(FlameNative.flame_session_new(none, ref sp, out h)));
        }
        var mp = FlameModelParams.Default();
        FlameModelHandle mh;
        Throws(FlameStatus.InvalidArgument, "`path` is NULL", () => FlameException.Check(FlameNative.flame_model_load(null, ref mp, out mh)));
        Throws(FlameStatus.InvalidArgument, "`bytes` is NULL", () => FlameException.Check(FlameNative.flame_model_load_from_memory(null, (UIntPtr)10, ref mp, out mh)));
        using (var s = model.NewSession(RefParams()))
        {
            Throws(FlameStatus.InvalidArgument, "`prompt` is NULL", () => FlameException.Check(FlameNative.flame_session_set_prompt(s.Handle, null)));
            Throws(FlameStatus.InvalidArgument, "not valid UTF-8", () => FlameException.Check(FlameNative.flame_session_set_prompt(s.Handle, new byte[] { 0xff, 0xfe, 0 })));
            Throws(FlameStatus.InvalidArgument, "`noise` is NULL", () => FlameException.Check(FlameNative.flame_session_set_noise(s.Handle, null, (UIntPtr)5)));
            Throws(FlameStatus.InvalidArgument, "`joints` is NULL", () => FlameException.Check(FlameNative.flame_session_keep_joints(s.Handle, null, (UIntPtr)2)));
            // A successful call clears the message.
            FlameException.Check(FlameNative.flame_session_clear_edit(s.Handle));
            Check(FlameNative.Utf8(FlameNative.flame_last_error()) == "", "message cleared after success");
        }
    }

    static void TestReadInto()
    {
        using (var s = RefSession())
        {
            s.Step();
            int n = s.ReadLength(FlameWhich.Sample, FlameLayout.Features, FlameConvention.Native, 0);
            Check(n == RefFrames * Dim, "length query " + n);
            var small = new float[10];
            Throws(FlameStatus.BufferTooSmall, "3528 floats needed, 10 given",
                   () => s.ReadInto(small, FlameWhich.Sample, FlameLayout.Features, FlameConvention.Native, 0));
            UIntPtr needed;
            var st = FlameNative.flame_session_read(s.Handle, 0, 0, 0, 0, small, (UIntPtr)small.Length, out needed);
            Check(st == FlameStatus.BufferTooSmall && (int)needed == n, "BUFFER_TOO_SMALL writes the required length");
            var big = new float[n + 5];
            Check(s.ReadInto(big, FlameWhich.Sample, FlameLayout.Features, FlameConvention.Native, 0) == n, "ReadInto count");
            var exact = s.Read();
            bool same = true;
            for (int i = 0; i < n; i++)
                same &= big[i] == exact[i];
            Check(same, "ReadInto = Read");
        }
    }

    static void TestPoseLayouts()
    {
        int J = model.Info.JointCount;
        Check(J == 24 && model.Info.JointNames[0] == "Pelvis", "SMPL-24 skeleton");
        using (var s = RefSession())
        {
            RunAll(s);
            Check(BitEqual(s.Read(FlameWhich.Sample, FlameLayout.Features, FlameConvention.Unity, FlameReadFlags.Smooth), reference),
                  "raw features ignore convention and flags");
            // The tiny model's final motion saturates at ±1, where some 6D rotations are
            // degenerate; the sample after one step is generic.
            s.Reset();
            s.Step();
            var expected = new Dictionary<int, int>
            {
                { FlameLayout.RootTranslation, 3 }, { FlameLayout.LocalQuatXyzw, J * 4 }, { FlameLayout.LocalQuatWxyz, J * 4 },
                { FlameLayout.LocalMatrix, J * 9 }, { FlameLayout.Local6d, J * 6 }, { FlameLayout.GlobalPositions, J * 3 },
                { FlameLayout.GlobalQuatXyzw, J * 4 }, { FlameLayout.GlobalQuatWxyz, J * 4 },
            };
            foreach (var kv in expected)
                Check(s.ReadLength(FlameWhich.Sample, kv.Key, FlameConvention.Unity, 0) == RefFrames * kv.Value, "length of layout " + kv.Key);
            var xyzw = s.Read(FlameWhich.Sample, FlameLayout.LocalQuatXyzw, FlameConvention.Unity, 0);
            var wxyz = s.Read(FlameWhich.Sample, FlameLayout.LocalQuatWxyz, FlameConvention.Unity, 0);
            bool unit = true, permuted = true;
            for (int q = 0; q < xyzw.Length; q += 4)
            {
                double n = Math.Sqrt(xyzw[q] * xyzw[q] + xyzw[q + 1] * xyzw[q + 1] + xyzw[q + 2] * xyzw[q + 2] + xyzw[q + 3] * xyzw[q + 3]);
                unit &= Math.Abs(n - 1) < 1e-5;
                permuted &= wxyz[q] == xyzw[q + 3] && wxyz[q + 1] == xyzw[q] && wxyz[q + 2] == xyzw[q + 1] && wxyz[q + 3] == xyzw[q + 2];
            }
            Check(unit, "unit quaternions");
            Check(permuted, "wxyz is xyzw reordered");
            var raw = s.Read(FlameWhich.Sample, FlameLayout.LocalQuatXyzw, FlameConvention.Unity, FlameReadFlags.RawSigns);
            bool positiveW = true;
            for (int q = 0; q < raw.Length; q += 4)
                positiveW &= raw[q + 3] >= 0;
            Check(positiveW, "RawSigns keeps w >= 0");
            // Foot contacts: detected for smpl24 models (ABI 3), 0 or 1.
            var contacts = s.Read(FlameWhich.Sample, FlameLayout.FootContacts, 0, 0);
            Check(contacts.Length == RefFrames * 4 && contacts.All(c => c == 0 || c == 1), "foot contacts: " + contacts.Length + " values, 0 or 1");
            Throws(FlameStatus.InvalidArgument, "unknown convention 9", () => s.Read(FlameWhich.Sample, FlameLayout.LocalQuatXyzw, 9, 0));
            Throws(FlameStatus.InvalidArgument, "unknown read flags", () => s.Read(FlameWhich.Sample, FlameLayout.LocalQuatXyzw, 0, 4));
        }
    }

    static void TestSetNoiseMatchesCli()
    {
        var rng = new Random(7);
        var noise = new float[RefFrames * Dim];
        for (int i = 0; i < noise.Length; i++)   // Box–Muller: any fixed values would do
            noise[i] = (float)(Math.Sqrt(-2 * Math.Log(1 - rng.NextDouble())) * Math.Cos(2 * Math.PI * rng.NextDouble()));
        string noisePath = Path.Combine(tmpDir, "noise.npy"), outPath = Path.Combine(tmpDir, "noise_out.npy");
        Npy.Write(noisePath, noise, RefFrames, Dim);
        var psi = new ProcessStartInfo(cliPath,
            "generate --model \"" + modelPath + "\" --prompt \"" + RefPrompt + "\" --frames 24 --steps 10 --sampler ddim --seed 3 --threads 1 " +
            "--noise \"" + noisePath + "\" --out \"" + outPath + "\"");
        psi.UseShellExecute = false;
        psi.RedirectStandardOutput = true;
        psi.RedirectStandardError = true;
        using (var proc = Process.Start(psi))
        {
            proc.StandardOutput.ReadToEnd();
            proc.StandardError.ReadToEnd();
            proc.WaitForExit();
            Check(proc.ExitCode == 0, "CLI with --noise exit code " + proc.ExitCode);
        }
        int[] shape;
        var expected = Npy.Read(outPath, out shape);
        using (var s = RefSession())
        {
            s.SetNoise(noise);
            Check(BitEqual(RunAll(s), expected), "SetNoise = CLI --noise");
            Check(!BitEqual(expected, reference), "the noise mattered");
        }
    }

    static void TestProgressCallback()
    {
        var seen = new List<int[]>();
        int thread = Thread.CurrentThread.ManagedThreadId;
        bool sameThread = true;
        using (var s = RefSession())
        {
            s.SetProgressCallback((done, total) =>
            {
                seen.Add(new[] { done, total });
                sameThread &= Thread.CurrentThread.ManagedThreadId == thread;
            });
            var output = RunAll(s);
            Check(seen.Count == 10, "10 calls, got " + seen.Count);
            for (int i = 0; i < seen.Count; i++)
                Check(seen[i][0] == i + 1 && seen[i][1] == 10, "call " + i + ": " + seen[i][0] + "/" + seen[i][1]);
            Check(sameThread, "runs on the stepping thread");
            Check(BitEqual(output, reference), "a callback does not change the output");
            s.SetProgressCallback(null);
            s.Reset();
            s.Step();
            Check(seen.Count == 10, "removed callback is not called");
        }
        GC.Collect();   // the trampoline delegate must survive collections
        GC.WaitForPendingFinalizers();
        int calls = 0;
        using (var s = RefSession())
        {
            s.SetProgressCallback((d, t) => calls++);
            GC.Collect();
            RunAll(s);
        }
        Check(calls == 10, "callback after GC: " + calls);
    }

    static void TestProgressCallbackException()
    {
        using (var s = RefSession())
        {
            s.SetProgressCallback((done, total) => { throw new ApplicationException("boom at " + done); });
            try
            {
                s.Step();
                Check(false, "Step should rethrow the callback's exception");
            }
            catch (InvalidOperationException e)
            {
                Check(e.InnerException is ApplicationException && e.InnerException.Message == "boom at 1", e.ToString());
            }
            Check(s.StepsDone == 1, "the step itself completed");
        }
    }

    static void TestCancelFromCallback()
    {
        // A cancel raised between steps fails the next step; retrying continues the generation.
        using (var s = RefSession())
        {
            s.SetProgressCallback((done, total) => { if (done == 3 || done == 7) s.Cancel(); });
            int cancelled = 0;
            while (s.StepsLeft > 0)
            {
                try
                {
                    s.Step();
                }
                catch (FlameException e)
                {
                    Check(e.Status == FlameStatus.Cancelled && e.NativeMessage == "cancelled", e.Message);
                    cancelled++;
                }
            }
            Check(cancelled == 2, "two cancelled steps, got " + cancelled);
            Check(BitEqual(s.Read(), reference), "cancel + retry = CLI");
        }
    }

    static FlameSession LongSession()
    {
        var p = FlameSessionParams.Default();
        p.frames = 470;
        p.steps = 1000;
        p.seed = 1;
        p.threads = 1;
        var s = model.NewSession(p);
        s.SetPrompt(RefPrompt);
        return s;
    }

    static void TestCancelFromAnotherThread()
    {
        using (var s = LongSession())
        {
            var started = new ManualResetEvent(false);
            s.SetProgressCallback((d, t) => started.Set());
            Exception error = null;
            bool finished = false;
            var worker = new Thread(() =>
            {
                try
                {
                    while (s.StepsLeft > 0)
                        s.Step();
                    finished = true;
                }
                catch (Exception e)
                {
                    error = e;
                }
            });
            worker.Start();
            Check(started.WaitOne(30000), "worker started stepping");
            var watch = Stopwatch.StartNew();
            s.Cancel();
            Check(worker.Join(30000), "worker stopped");
            Check(!finished && error is FlameException && ((FlameException)error).Status == FlameStatus.Cancelled,
                  "CANCELLED on the worker, got " + error);
            Check(watch.ElapsedMilliseconds < 5000, "cancel took " + watch.ElapsedMilliseconds + " ms");
            int done = s.StepsDone;
            Check(done >= 1 && done < 1000, "steps done " + done);
            Check(s.Step() == 1000 - done - 1, "a cancelled session keeps stepping");
        }
    }

    static void TestDisposeWhileStepping()
    {
        // Dispose from another thread while a step runs: the SafeHandle defers the free until
        // the step returns, so there is no use-after-free; later calls see a disposed handle.
        var s = LongSession();
        var started = new ManualResetEvent(false);
        s.SetProgressCallback((d, t) => started.Set());
        Exception error = null;
        var worker = new Thread(() =>
        {
            try
            {
                while (true)
                    s.Step();
            }
            catch (Exception e)
            {
                error = e;
            }
        });
        worker.Start();
        Check(started.WaitOne(30000), "worker started stepping");
        s.Cancel();
        s.Dispose();
        Check(worker.Join(30000), "worker stopped");
        Check(error is FlameException || error is ObjectDisposedException, "worker saw " + error);
    }

    static void TestEditing()
    {
        using (var s = RefSession())
        {
            s.SetReference(reference);
            s.SetMask(new bool[RefFrames * Dim]);   // keeps nothing: plain generation
            Check(BitEqual(RunAll(s), reference), "empty mask = plain");

            s.Reset();
            s.KeepFrames(0, 6);
            var edited = RunAll(s);
            Check(!BitEqual(edited, reference), "keeping frames changes the output");
            s.Reset();
            Check(BitEqual(RunAll(s), edited), "editing is deterministic");

            s.ClearEdit();
            s.Reset();
            Check(BitEqual(RunAll(s), reference), "ClearEdit = plain");

            s.SetReference(reference);
            s.KeepJoints(FlameNative.RootTranslation, 0);
            s.Reset();
            var joints = RunAll(s);
            Check(!BitEqual(joints, reference), "keeping joints changes the output");
            s.KeepJoints();   // adds nothing

            var mask = new byte[RefFrames * Dim];
            for (int f = 0; f < RefFrames; f++)
                for (int c = 0; c < 9; c++)   // root translation 0..3 + joint 0's 6D 3..9
                    mask[f * Dim + c] = 1;
            s.ClearEdit();
            s.SetReference(reference, RefFrames, Dim);
            s.SetMask(mask, RefFrames, Dim);
            s.Reset();
            Check(BitEqual(RunAll(s), joints), "KeepJoints(-1, 0) = the equivalent mask");
        }
    }

    static float[] SmoothReference(int frames, int dim)
    {
        var r = new float[frames * dim];
        for (int i = 0; i < r.Length; i++)
            r[i] = (float)(0.5 * Math.Sin(0.01 * i) + 0.25);
        return r;
    }

    /// <summary>Whether frames [f0, f1) of x are r's, bit for bit.</summary>
    static bool SameFrames(float[] x, float[] r, int dim, int f0, int f1)
    {
        var a = new float[(f1 - f0) * dim];
        var b = new float[(f1 - f0) * dim];
        Array.Copy(x, f0 * dim, a, 0, a.Length);
        Array.Copy(r, f0 * dim, b, 0, b.Length);
        return BitEqual(a, b);
    }

    static float MaxAbsDiff(float[] a, float[] b)
    {
        if (a.Length != b.Length)
            return float.PositiveInfinity;
        float d = 0;
        for (int i = 0; i < a.Length; i++)
            d = Math.Max(d, Math.Abs(a[i] - b[i]));
        return d;
    }

    static void TestEditParams()
    {
        using (var s = RefSession())
        {
            var p = FlameEditParams.Default();
            s.SetEditParams(p);
            p.method = (int)FlameEditMethod.RewriteTrajectory;
            Throws(FlameStatus.InvalidArgument, "does not apply", () => s.SetEditParams(p));
            p = FlameEditParams.Default();
            p.method = 4;
            Throws(FlameStatus.InvalidArgument, "edit method 4", () => s.SetEditParams(p));
            p = FlameEditParams.Default();
            p.edit_till = float.NaN;
            Throws(FlameStatus.InvalidArgument, "edit_till", () => s.SetEditParams(p));
            p.edit_till = 1.5f;
            Throws(FlameStatus.InvalidArgument, "edit_till", () => s.SetEditParams(p));
            p = FlameEditParams.Default();
            p.seam_frames = 1001;
            Throws(FlameStatus.InvalidArgument, "seam_frames", () => s.SetEditParams(p));
            p = FlameEditParams.Default();
            p.struct_size = 8;
            Throws(FlameStatus.InvalidArgument, "struct_size", () => s.SetEditParams(p));
            p = FlameEditParams.Default();
            p.method = (int)FlameEditMethod.ReplaceX0;
            p.paste = 0;
            s.SetEditParams(p);
            s.SetEditParams(FlameEditParams.Default());
            Check(BitEqual(RunAll(s), reference), "settings alone edit nothing");
        }
        using (var none = new FlameSessionHandle())
        {
            var p = FlameEditParams.Default();
            Throws(FlameStatus.InvalidArgument, "`session` is NULL", () => FlameException.Check(FlameNative.flame_session_set_edit_params(none, ref p)));
            Throws(FlameStatus.InvalidArgument, "`session` is NULL", () => FlameException.Check(FlameNative.flame_session_set_task_mask(none, 0)));
            Throws(FlameStatus.InvalidArgument, "`session` is NULL", () => FlameException.Check(FlameNative.flame_session_keep_part(none, 0, 0, 1)));
        }
    }

    static void TestTaskMasksAndParts()
    {
        var r = SmoothReference(RefFrames, Dim);
        using (var s = RefSession())
        {
            s.SetTaskMask(FlameEditTask.Path);
            Throws(FlameStatus.WrongState, "no reference", () => s.Step());
            s.SetReference(r);
            s.SetTaskMask(FlameEditTask.Inbetween);
            var x = RunAll(s);
            Check(SameFrames(x, r, Dim, 0, 6) && SameFrames(x, r, Dim, 18, 24), "in-between: kept frames = the reference (paste on)");
            Check(!SameFrames(x, r, Dim, 6, 18), "in-between: the middle is generated");

            var p = FlameEditParams.Default();
            p.paste = 0;
            s.SetEditParams(p);
            s.Reset();
            Check(!SameFrames(RunAll(s), r, Dim, 0, 6), "paste off: the kept frames are only close");
            s.SetEditParams(FlameEditParams.Default());

            s.SetTaskMask(FlameEditTask.Path);
            s.Reset();
            var path = RunAll(s);
            bool rootKept = true;
            for (int f = 0; f < RefFrames; f++)
                for (int c = 0; c < 3; c++)
                    rootKept &= path[f * Dim + c] == r[f * Dim + c];
            Check(rootKept && !BitEqual(path, x), "path: the root translation is kept");
            s.ClearEdit();
            s.SetReference(r);
            s.KeepPart(FlameBodyPart.RootPath);
            s.Reset();
            Check(BitEqual(RunAll(s), path), "KeepPart(RootPath) = the PATH task");

            Throws(FlameStatus.InvalidArgument, "unknown editing task 4", () => s.SetTaskMask((FlameEditTask)4));
            Throws(FlameStatus.InvalidArgument, "unknown body part 5", () => s.KeepPart((FlameBodyPart)5));
            Throws(FlameStatus.InvalidArgument, "from 3 to 3", () => s.KeepPart(FlameBodyPart.Arms, 3, 3));
            Throws(FlameStatus.InvalidArgument, "from 0 to 25", () => s.KeepPart(FlameBodyPart.Arms, 0, 25));
            ThrowsManaged<ArgumentOutOfRangeException>(() => s.KeepPart(FlameBodyPart.Arms, -1, 3));
        }
    }

    static void TestShortReference()
    {
        var r = SmoothReference(6, Dim);
        using (var s = RefSession())
        {
            s.SetReference(r, 6, Dim);
            Throws(FlameStatus.InvalidArgument, "keeps frame 6", () => s.KeepFrames(0, 7));
            Throws(FlameStatus.InvalidArgument, "keeps frame", () => s.SetTaskMask(FlameEditTask.Inbetween));
            s.SetTaskMask(FlameEditTask.Predict);
            Check(SameFrames(RunAll(s), r, Dim, 0, 6), "PREDICT keeps the short reference's frames");
        }
        using (var s = RefSession())
        {
            s.KeepFrames(0, RefFrames);
            Throws(FlameStatus.InvalidArgument, "keeps frame 6", () => s.SetReference(r, 6, Dim));
        }
    }

    static void TestReferencePoses()
    {
        float[] root, quats, rot6d;
        using (var g = RefSession())
        {
            g.Step();   // a generic motion (the tiny model's final ones hold degenerate rotations)
            root = g.Read(FlameWhich.Sample, FlameLayout.RootTranslation, FlameConvention.Unity, 0);
            quats = g.Read(FlameWhich.Sample, FlameLayout.LocalQuatWxyz, FlameConvention.Unity, 0);
            rot6d = g.Read(FlameWhich.Sample, FlameLayout.Local6d, FlameConvention.Unity, 0);
        }
        using (var s = RefSession())
        {
            s.SetReferencePoses(root, quats, FlameLayout.LocalQuatWxyz, FlameConvention.Unity);
            s.KeepFrames(0, RefFrames);
            RunAll(s);
            Check(MaxAbsDiff(s.Read(FlameWhich.Sample, FlameLayout.RootTranslation, FlameConvention.Unity, 0), root) < 1e-4f, "root round trip");
            Check(MaxAbsDiff(s.Read(FlameWhich.Sample, FlameLayout.Local6d, FlameConvention.Unity, 0), rot6d) < 1e-4f, "rotation round trip");
            Throws(FlameStatus.InvalidArgument, "layout", () => s.SetReferencePoses(root, rot6d, FlameLayout.GlobalQuatXyzw, 0));
            Throws(FlameStatus.InvalidArgument, "convention", () => s.SetReferencePoses(root, rot6d, FlameLayout.Local6d, 6));
            Throws(FlameStatus.InvalidArgument, "rotations", () => s.SetReferencePoses(root, rot6d, FlameLayout.LocalQuatXyzw, 0));
            Throws(FlameStatus.InvalidArgument, "between 1 and 24 (the session's frames), got 25", () => s.SetReferencePoses(new float[25 * 3], new float[25 * 24 * 6], FlameLayout.Local6d, 0));
            ThrowsManaged<ArgumentException>(() => s.SetReferencePoses(new float[5], rot6d, FlameLayout.Local6d, 0));
            ThrowsManaged<ArgumentNullException>(() => s.SetReferencePoses(root, null, FlameLayout.Local6d, 0));
            Throws(FlameStatus.InvalidArgument, "`rotations` is NULL",
                   () => FlameException.Check(FlameNative.flame_session_set_reference_poses(s.Handle, root, (UIntPtr)root.Length, null, (UIntPtr)10,
                                                                                            (uint)RefFrames, FlameLayout.Local6d, 0)));
        }
    }

    // --- position targets -----------------------------------------------------------------

    const int TargetFrames = 16, Joints = 24;

    static FlameSession TargetSession()
    {
        var p = FlameSessionParams.Default();
        p.frames = TargetFrames;
        p.steps = 20;
        p.sampler = (int)FlameSampler.Ddim;
        p.guidance = 2.5f;
        p.seed = 7;
        p.threads = 1;
        var s = model.NewSession(p);
        s.SetPrompt("a person walks forward.");
        return s;
    }

    /// <summary>From where the unguided pelvis starts, a line across the ground in the Unreal
    /// convention (Z up, centimetres: +5 cm in X, -4 cm in Y per frame) at the unguided height;
    /// every other joint NaN (free).</summary>
    static float[] PelvisPath(float[] unguided)
    {
        var t = new float[TargetFrames * Joints * 3];
        for (int i = 0; i < t.Length; i++)
            t[i] = float.NaN;
        for (int f = 0; f < TargetFrames; f++)
        {
            int at = f * Joints * 3;
            t[at] = unguided[0] + 5f * f;
            t[at + 1] = unguided[1] - 4f * f;
            t[at + 2] = unguided[at + 2];
        }
        return t;
    }

    static double MedianPelvisError(float[] positions, float[] target)
    {
        var e = new double[TargetFrames];
        for (int f = 0; f < TargetFrames; f++)
        {
            double d = 0;
            for (int k = 0; k < 3; k++)
            {
                double x = positions[f * Joints * 3 + k] - target[f * Joints * 3 + k];
                d += x * x;
            }
            e[f] = Math.Sqrt(d);
        }
        Array.Sort(e);
        return e[TargetFrames / 2];
    }

    static void TestPositionTargets()
    {
        float[] unguided, pUnguided, guided;
        using (var plain = TargetSession())
        {
            unguided = RunAll(plain);
            pUnguided = plain.Read(FlameWhich.Sample, FlameLayout.GlobalPositions, FlameConvention.Unreal, 0);
        }
        var target = PelvisPath(pUnguided);
        using (var s = TargetSession())
        {
            s.SetPositionTargets(target, FlameConvention.Unreal);
            Throws(FlameStatus.WrongState, "no step has been guided", () => s.TargetLoss());
            guided = RunAll(s);
            double loss = s.TargetLoss();
            Check(!double.IsNaN(loss) && !double.IsInfinity(loss) && loss > 0, "target loss " + loss);
            var pGuided = s.Read(FlameWhich.Sample, FlameLayout.GlobalPositions, FlameConvention.Unreal, 0);
            double before = MedianPelvisError(pUnguided, target), after = MedianPelvisError(pGuided, target);
            Check(before > 5 && after < 0.5 * before, "median pelvis error " + before + " cm unguided, " + after + " cm guided");
            s.Reset();
            Throws(FlameStatus.WrongState, "guided", () => s.TargetLoss());
            Check(BitEqual(RunAll(s), guided), "reset replays the guided run");
            s.ClearPositionTargets();
            Throws(FlameStatus.WrongState, "guided", () => s.TargetLoss());
            s.Reset();
            Check(BitEqual(RunAll(s), unguided), "cleared targets: the unguided run, bit for bit");
        }
        using (var s = TargetSession())
        {
            s.SetPositionTargets(target, FlameConvention.Unreal);
            var p = FlameTargetParams.Default();
            p.scale = 0;
            p.schedule = (int)FlameTargetSchedule.Constant;
            s.SetTargetParams(p);
            Check(BitEqual(RunAll(s), unguided), "scale 0: the unguided run, bit for bit");
            Throws(FlameStatus.WrongState, "guided", () => s.TargetLoss());
        }
        using (var s = TargetSession())
        {
            // The same constraint as a mask (free values arbitrary) = the NaN form.
            var values = new float[target.Length];
            var mask = new bool[target.Length];
            for (int i = 0; i < target.Length; i++)
            {
                mask[i] = !float.IsNaN(target[i]);
                values[i] = mask[i] ? target[i] : 123f;
            }
            s.SetPositionTargets(values, mask, FlameConvention.Unreal);
            Check(BitEqual(RunAll(s), guided), "a mask = NaN for free values");
            var p = FlameTargetParams.Default();
            p.schedule = (int)FlameTargetSchedule.Mpgd;
            s.SetTargetParams(p);
            s.Reset();
            var mpgd = RunAll(s);
            Check(!BitEqual(mpgd, guided) && !BitEqual(mpgd, unguided), "the MPGD schedule is another guided result");
        }
    }

    static void TestTaskTargets()
    {
        float[] reference;
        using (var plain = TargetSession())
            reference = RunAll(plain);
        using (var s = TargetSession())
        {
            s.SetTaskTargets(reference, s.Frames, FlameEditTask.Path);
            var pathed = RunAll(s);
            Check(!BitEqual(pathed, reference) && !double.IsNaN(s.TargetLoss()), "task targets from a reference steer");
            Throws(FlameStatus.InvalidArgument, "unknown editing task 9", () => s.SetTaskTargets(reference, s.Frames, (FlameEditTask)9));
        }
    }

    static void TestPositionTargetErrors()
    {
        int n = 2 * Joints * 3;
        var t = new float[n];
        for (int i = 0; i < n; i++)
            t[i] = 0.1f;
        using (var s = TargetSession())
        {
            var bad = (float[])t.Clone();
            bad[Joints * 3 + 5 * 3 + 1] = float.NaN;
            var mask = new bool[n];
            for (int i = 0; i < n; i++)
                mask[i] = true;
            Throws(FlameStatus.InvalidArgument, "frame 1, joint 5, axis 1 is NaN but constrained", () => s.SetPositionTargets(bad, mask, 0));
            mask[Joints * 3 + 5 * 3 + 1] = false;
            s.SetPositionTargets(bad, mask, 0);
            bad[7] = float.PositiveInfinity;
            Throws(FlameStatus.InvalidArgument, "frame 0, joint 2, axis 1 is inf but constrained", () => s.SetPositionTargets(bad, 0));
            Throws(FlameStatus.InvalidArgument, "multiple of 72", () => s.SetPositionTargets(new float[n - 1], 0));
            Throws(FlameStatus.InvalidArgument, "hold 0 values", () => s.SetPositionTargets(new float[0], 0));
            Throws(FlameStatus.InvalidArgument, "the target mask has 143 flags", () => s.SetPositionTargets(t, new bool[n - 1], 0));
            Throws(FlameStatus.InvalidArgument, "the target mask has 0 flags", () => s.SetPositionTargets(t, new byte[0], 0));
            Throws(FlameStatus.InvalidArgument, "constrain nothing", () => s.SetPositionTargets(t, new bool[n], 0));
            var free = new float[n];
            for (int i = 0; i < n; i++)
                free[i] = float.NaN;
            Throws(FlameStatus.InvalidArgument, "constrain nothing", () => s.SetPositionTargets(free, 0));
            Throws(FlameStatus.InvalidArgument, "cover 17 frames; the session has 16", () => s.SetPositionTargets(new float[17 * Joints * 3], 0));
            Throws(FlameStatus.InvalidArgument, "convention", () => s.SetPositionTargets(t, 6));
            ThrowsManaged<ArgumentNullException>(() => s.SetPositionTargets(null, 0));
            ThrowsManaged<ArgumentNullException>(() => s.SetPositionTargets(t, (bool[])null, 0));
            Throws(FlameStatus.InvalidArgument, "`targets` is NULL",
                   () => FlameException.Check(FlameNative.flame_session_set_position_targets(s.Handle, null, (UIntPtr)72, null, UIntPtr.Zero, 0)));
            Throws(FlameStatus.InvalidArgument, "`mask` is NULL",
                   () => FlameException.Check(FlameNative.flame_session_set_position_targets(s.Handle, t, (UIntPtr)n, null, (UIntPtr)n, 0)));

            foreach (float scale in new[] { -0.1f, float.NaN, 100.5f, float.PositiveInfinity })
            {
                var p = FlameTargetParams.Default();
                p.scale = scale;
                Throws(FlameStatus.InvalidArgument, "target scale", () => s.SetTargetParams(p));
            }
            foreach (int schedule in new[] { 2, -1 })
            {
                var p = FlameTargetParams.Default();
                p.schedule = schedule;
                Throws(FlameStatus.InvalidArgument, "unknown target schedule " + schedule, () => s.SetTargetParams(p));
            }
            var sized = FlameTargetParams.Default();
            sized.struct_size = 8;
            Throws(FlameStatus.InvalidArgument, "struct_size", () => s.SetTargetParams(sized));
            var ok = FlameTargetParams.Default();
            ok.scale = 100;
            s.SetTargetParams(ok);
            ok.scale = 0;
            s.SetTargetParams(ok);
            s.ClearPositionTargets();
            s.ClearPositionTargets();
        }
        using (var none = new FlameSessionHandle())
        {
            var p = FlameTargetParams.Default();
            double loss;
            Throws(FlameStatus.InvalidArgument, "`session` is NULL", () => FlameException.Check(FlameNative.flame_session_set_target_params(none, ref p)));
            Throws(FlameStatus.InvalidArgument, "`session` is NULL", () => FlameException.Check(FlameNative.flame_session_clear_position_targets(none)));
            Throws(FlameStatus.InvalidArgument, "`session` is NULL", () => FlameException.Check(FlameNative.flame_session_target_loss(none, out loss)));
            Throws(FlameStatus.InvalidArgument, "`session` is NULL",
                   () => FlameException.Check(FlameNative.flame_session_set_position_targets(none, t, (UIntPtr)n, null, UIntPtr.Zero, 0)));
        }
    }

    // The families that sample the motion itself: the sampled space is frames × feature_dim and
    // a read has the session's frames (the latent model: TestLatentModel).
    static void TestSampleShapeAndReadFrames()
    {
        string dir = Path.GetDirectoryName(Path.GetFullPath(modelPath));
        var cases = new[] { new { File = "flame_tiny.safetensors", Dim = 147, Joints = 24, Sampler = FlameSampler.Ddim },
                            new { File = "mdm_tiny.safetensors", Dim = 263, Joints = 22, Sampler = FlameSampler.Ddim } };
        foreach (var c in cases)
        {
            using (var m = FlameModel.Load(Path.Combine(dir, c.File), 1))
            {
                var i = m.Info;
                Check(!i.Latent && i.SampleDim == c.Dim && i.FeatureDim == c.Dim && i.JointCount == c.Joints, c.File + ": info latent/sample_dim");
                var p = FlameSessionParams.Default();
                p.frames = 12;
                p.steps = 2;
                p.sampler = (int)c.Sampler;
                p.seed = 1;
                p.threads = 1;
                using (var s = m.NewSession(p))
                {
                    int rows, dim;
                    s.SampleShape(out rows, out dim);
                    Check(rows == 12 && dim == c.Dim, c.File + ": sample shape " + rows + "x" + dim);
                    Throws(FlameStatus.WrongState, "no sample yet", () => s.ReadFrames(FlameWhich.Sample));
                    Throws(FlameStatus.WrongState, "no clean-motion estimate", () => s.ReadFrames(FlameWhich.Estimate));
                    Throws(FlameStatus.InvalidArgument, "unknown `which` 2", () => s.ReadFrames((FlameWhich)2));
                    Throws(FlameStatus.InvalidArgument, "12 rows", () => s.SetNoise(new float[rows * dim - 1]));
                    var noise = new float[rows * dim];
                    for (int k = 0; k < noise.Length; k++)
                        noise[k] = (float)Math.Sin(0.1 * k);
                    s.SetNoise(noise);
                    s.SetPrompt(RefPrompt);
                    s.Step();
                    Check(s.ReadFrames(FlameWhich.Sample) == 12 && s.ReadFrames(FlameWhich.Estimate) == 12, c.File + ": read frames");
                    int frames;
                    var x = s.Read(FlameWhich.Estimate, FlameLayout.GlobalPositions, FlameConvention.Native, 0, out frames);
                    Check(frames == 12 && x.Length == frames * c.Joints * 3, c.File + ": Read(..., out frames) " + frames + ", " + x.Length);
                    Check(s.ReadLength(FlameWhich.Sample, FlameLayout.Features, 0, 0) == s.ReadFrames(FlameWhich.Sample) * c.Dim, c.File + ": length = frames × dim");
                    s.Reset();
                    Throws(FlameStatus.WrongState, "no sample yet", () => s.ReadFrames(FlameWhich.Sample));
                }
            }
        }
    }

    // A latent model (tests/fixtures/mola_tiny.safetensors, MoLA): 60 frames are a latent of
    // 60 / 4 + 1 = 16 rows × 16 channels (tests/fixtures/mola_expected.json); the decoder decides
    // how many frames a read has. Reference: the CLI with the same latent noise.
    static void TestLatentModel()
    {
        string mola = Path.Combine(Path.GetDirectoryName(Path.GetFullPath(modelPath)), "mola_tiny.safetensors");
        var noise = new float[16 * 16];
        var rng = new Random(4);
        for (int i = 0; i < noise.Length; i++)
            noise[i] = (float)(Math.Sqrt(-2 * Math.Log(1 - rng.NextDouble())) * Math.Cos(2 * Math.PI * rng.NextDouble()));
        string noisePath = Path.Combine(tmpDir, "latent_noise.npy"), outPath = Path.Combine(tmpDir, "latent_out.npy");
        Npy.Write(noisePath, noise, 16, 16);
        var psi = new ProcessStartInfo(cliPath,
            "generate --model \"" + mola + "\" --prompt \"" + RefPrompt + "\" --frames 60 --steps 4 --sampler ddim --seed 3 --threads 1 " +
            "--noise \"" + noisePath + "\" --out \"" + outPath + "\"");
        psi.UseShellExecute = false;
        psi.RedirectStandardOutput = true;
        psi.RedirectStandardError = true;
        using (var proc = Process.Start(psi))
        {
            proc.StandardOutput.ReadToEnd();
            proc.StandardError.ReadToEnd();
            proc.WaitForExit();
            Check(proc.ExitCode == 0, "CLI on the latent model: exit code " + proc.ExitCode);
        }
        int[] shape;
        var expected = Npy.Read(outPath, out shape);
        using (var m = FlameModel.Load(mola, 1))
        {
            var i = m.Info;
            Check(i.Latent && i.SampleDim == 16 && i.FeatureDim == 263 && i.JointCount == 22 && i.Architecture == "mola", "latent model info");
            var p = FlameSessionParams.Default();
            p.frames = 60;
            p.steps = 4;
            p.sampler = (int)FlameSampler.Ddim;
            p.seed = 3;
            p.threads = 1;
            using (var s = m.NewSession(p))
            {
                int rows, dim;
                s.SampleShape(out rows, out dim);
                Check(rows == 16 && dim == 16, "latent sample shape " + rows + "x" + dim);
                Throws(FlameStatus.InvalidArgument, "16 rows", () => s.SetNoise(new float[60 * 263]));
                Throws(FlameStatus.InvalidArgument, "samples a latent", () => s.SetReference(new float[60 * 263]));
                s.SetNoise(noise);
                s.SetPrompt(RefPrompt);
                var x = RunAll(s);
                int frames = s.ReadFrames(FlameWhich.Sample);
                Check(shape.Length == 2 && shape[0] == frames && shape[1] == 263 && frames != s.Frames,
                      "frames " + frames + " = the CLI's " + string.Join("x", shape) + ", not the session's " + s.Frames);
                Check(BitEqual(x, expected), "latent model: features = CLI --noise");
                int posFrames;
                var pos = s.Read(FlameWhich.Sample, FlameLayout.GlobalPositions, FlameConvention.Native, 0, out posFrames);
                Check(posFrames == frames && pos.Length == frames * 22 * 3, "positions: " + posFrames + " frames, " + pos.Length + " values");
            }
        }
    }

    static void TestEditOtherFamilies()
    {
        // The fixtures' text towers are placeholders: prompts encode, meaninglessly.
        string dir = Path.GetDirectoryName(Path.GetFullPath(modelPath));
        var p = FlameSessionParams.Default();
        p.frames = 16;
        p.steps = 3;
        p.seed = 1;
        p.threads = 1;
        using (var mdm = FlameModel.Load(Path.Combine(dir, "mdm_tiny.safetensors"), 1))
        {
            int d = mdm.Info.FeatureDim;
            var r = SmoothReference(16, d);
            p.sampler = (int)FlameSampler.Ddim;
            using (var s = mdm.NewSession(p))
            {
                s.SetPrompt(RefPrompt);
                s.SetReference(r);
                s.KeepJoints(FlameNative.RootTranslation);
                var x = RunAll(s);
                bool rootKept = true;
                for (int f = 0; f < 16; f++)
                    for (int c = 0; c < 4; c++)
                        rootKept &= x[f * d + c] == r[f * d + c];
                Check(d == 263 && rootKept && !BitEqual(x, r), "humanml263: KeepJoints(RootTranslation) keeps the root path");
                Throws(FlameStatus.InvalidArgument, "joint 22", () => s.KeepJoints(22));
                var ep = FlameEditParams.Default();
                ep.method = (int)FlameEditMethod.RewriteTrajectory;
                Throws(FlameStatus.InvalidArgument, "does not apply", () => s.SetEditParams(ep));
                Throws(FlameStatus.InvalidArgument, "smpl24_6d", () => s.SetReferencePoses(new float[3], new float[24 * 6], FlameLayout.Local6d, 0));
            }
        }
        using (var fm = FlameModel.Load(Path.Combine(dir, "motionfm_tiny.safetensors"), 1))
        {
            int d = fm.Info.FeatureDim;
            var r = SmoothReference(16, d);
            p.sampler = (int)FlameSampler.Euler;
            using (var s = fm.NewSession(p))
            {
                var ep = FlameEditParams.Default();
                ep.method = (int)FlameEditMethod.NoisedReference;
                Throws(FlameStatus.InvalidArgument, "does not apply", () => s.SetEditParams(ep));
                ep.method = (int)FlameEditMethod.RewriteTrajectory;
                ep.edit_till = 0.5f;
                s.SetEditParams(ep);
                s.SetPrompt(RefPrompt);
                s.SetReference(r);
                s.SetTaskMask(FlameEditTask.Predict);
                var x = RunAll(s);
                Check(SameFrames(x, r, d, 0, 4) && !SameFrames(x, r, d, 4, 16), "flow: PREDICT keeps the first quarter");
            }
        }
    }

    // --- prompts per time stage ------------------------------------------------------------

    static FlameSessionParams StageParams(uint frames)
    {
        var p = FlameSessionParams.Default();
        p.frames = frames;
        p.steps = 3;
        p.sampler = (int)FlameSampler.Ddim;
        p.seed = 5;
        p.threads = 1;
        return p;
    }

    static FlameModel LoadFixture(string file)
    {
        return FlameModel.Load(Path.Combine(Path.GetDirectoryName(Path.GetFullPath(modelPath)), file), 1);
    }

    /// <summary>An MDM generation of 16 frames, its prompt set by set.</summary>
    static float[] MdmRun(FlameModel mdm, Action<FlameSession> set)
    {
        using (var s = mdm.NewSession(StageParams(16)))
        {
            set(s);
            int rows, dim;
            s.SampleShape(out rows, out dim);
            Check(rows == 16 && dim == 263, "one stage: sample shape " + rows + "x" + dim);
            return RunAll(s);
        }
    }

    // A model that takes one prompt (MDM): one stage without part texts is SetPrompt with its
    // text, bit for bit (empty part texts are none); two stages or a part text are refused.
    static void TestPromptStages()
    {
        using (var mdm = LoadFixture("mdm_tiny.safetensors"))
        {
            var plain = MdmRun(mdm, s => s.SetPrompt(RefPrompt));
            Check(BitEqual(MdmRun(mdm, s => s.SetPromptStages(new Stage(RefPrompt, 16))), plain), "one stage = SetPrompt");
            var empty = new Stage(RefPrompt, 16) { Head = "", LeftArm = "", Pelvis = "" };
            Check(BitEqual(MdmRun(mdm, s => s.SetPromptStages(empty)), plain), "empty part texts = none");
            Check(!BitEqual(MdmRun(mdm, s => s.SetPromptStages(new Stage("a person jumps", 16))), plain), "another text differs");
            using (var s = mdm.NewSession(StageParams(16)))
            {
                Throws(FlameStatus.InvalidArgument, "this mdm model takes one prompt per generation (a single stage without part texts)",
                       () => s.SetPromptStages(new Stage("a person walks", 8), new Stage("a person jumps", 8)));
                Throws(FlameStatus.InvalidArgument, "a single stage without part texts",
                       () => s.SetPromptStages(new Stage("a person walks", 16) { RightArm = "waves" }));
                Throws(FlameStatus.WrongState, "prompt", () => s.Step());
            }
        }
    }

    // A stream over the FLAME fixture: two segments, everything pumped, reads and errors.
    static void TestStream()
    {
        string dir = Path.GetDirectoryName(Path.GetFullPath(modelPath));
        var p = FlameStreamParams.Default();
        Check(p.overlap == 20 && p.lookahead == 60 && p.window == 1200 && p.chunk == 0, "stream defaults");
        p.chunk = 40; p.overlap = 10; p.steps = 2; p.lookahead = 100000; p.sampler = (int)FlameSampler.Ddim;
        using (var s = FlameStream.Create(model, p))
        {
            s.Push("a person walks forward.", 30);
            s.Push("a person waves.", 20);
            uint steps = 0;
            FlameStreamStatus st;
            while ((st = s.Pump(1)).steps > 0)
                steps += st.steps;
            Check(steps == 4 && s.Status().ready == 50 && s.Status().starving == 1, "two chunks of 2 steps, 50 frames");
            Check(s.Read(0, 50, FlameLayout.LocalQuatXyzw, (int)FlameConvention.Unity).Length == 50 * 24 * 4, "quaternions");
            Check(s.Read(0, 50, FlameLayout.Features, 0).Length == 50 * 147, "features");
            Throws(FlameStatus.WrongState, "not generated yet", () => s.Read(45, 10, FlameLayout.RootTranslation, 0));
            Throws(FlameStatus.InvalidArgument, "at least one frame", () => s.Push("a person jumps.", 0));
        }
        using (var latent = FlameModel.Load(Path.Combine(dir, "mld_tiny.safetensors"), 1))
            Throws(FlameStatus.InvalidArgument, "gradient", () => FlameStream.Create(latent));
    }

    // flame_stream_read_cleaned: frames read one at a time as they settle are the bytes one read
    // at the end gives; at 30 fps a closed 50-frame timeline (20 fps) has 74 cleaned frames.
    static void TestStreamCleaned()
    {
        var p = FlameStreamParams.Default();
        p.chunk = 40; p.overlap = 10; p.steps = 2; p.lookahead = 100000; p.sampler = (int)FlameSampler.Ddim;
        var cp = FlameCleanupParams.Default();
        cp.fps = 30f;
        using (var a = FlameStream.Create(model, p))
        using (var b = FlameStream.Create(model, p))
        {
            foreach (var s in new[] { a, b })
            {
                s.Push("a person walks forward.", 30);
                s.Push("a person waves.", 20);
                s.EndTimeline();
            }
            Throws(FlameStatus.WrongState, "", () => a.Push("a person jumps.", 10));
            var got = new List<float>();
            uint k = 0;
            while (true)
            {
                uint stepped = a.Pump(1).steps;
                bool read = false;
                try { got.AddRange(a.Read(k, 1, FlameLayout.GlobalPositions, (int)FlameConvention.Gltf, cp)); k++; read = true; }
                catch (FlameException e) { Check(e.Status == FlameStatus.WrongState, "unsettled frames are WRONG_STATE"); }
                if (!read && stepped == 0) break;
            }
            while (b.Pump(uint.MaxValue).steps > 0) { }
            var whole = b.Read(0, 74, FlameLayout.GlobalPositions, (int)FlameConvention.Gltf, cp);
            Check(k == 74 && got.Count == whole.Length, "74 frames at 30 fps, read one at a time");
            bool same = got.Count == whole.Length;
            for (int i = 0; same && i < whole.Length; i++)
                same = BitConverter.SingleToInt32Bits(got[i]) == BitConverter.SingleToInt32Bits(whole[i]);
            Check(same, "frame by frame = one read, bit for bit");
        }
    }

    // tests/c/test_stream.c's loop (the settings of tests/cycle.rs): chunks of 60 frames keeping
    // 20, 3 steps, seed 9; "a person walks" 70 + "a person jumps" 30 = 100 frames, then
    // EndTimelineLooped(20): 120 frames, the first 100 those of EndTimeline's stream bit for bit,
    // all 120 settled for cleaned reads (feet locked); the refusals.
    static FlameStreamParams LoopStreamParams()
    {
        var p = FlameStreamParams.Default();
        p.chunk = 60; p.overlap = 20; p.lookahead = 1000; p.window = 1000; p.steps = 3; p.seed = 9; p.threads = 1;
        return p;
    }

    static void TestStreamLooped()
    {
        using (var plain = FlameStream.Create(model, LoopStreamParams()))
        using (var looped = FlameStream.Create(model, LoopStreamParams()))
        {
            foreach (var s in new[] { plain, looped })
            {
                s.Push("a person walks", 70);
                s.Push("a person jumps", 30);
            }
            plain.EndTimeline();
            looped.EndTimelineLooped(20);
            Throws(FlameStatus.WrongState, "closed", () => looped.EndTimelineLooped(20));
            Throws(FlameStatus.WrongState, "closed", () => looped.Push("a person waves", 10));
            Check(PumpOn(plain, 1) == 0 && PumpOn(looped, 1) == 0, "pumped");
            var st = looped.Status();
            Check(plain.Status().ready == 100 && st.ready == 120 && st.first_frame == 0 && st.starving == 1,
                  "100 frames, 120 looped: " + plain.Status().ready + ", " + st.ready);
            Throws(FlameStatus.WrongState, "not generated yet", () => looped.Read(120, 1, FlameLayout.Features, 0));
            var all = looped.Read(0, 120, FlameLayout.Features, 0);
            var first = new float[100 * Dim];
            Array.Copy(all, first, Math.Min(first.Length, all.Length));
            Check(all.Length == 120 * Dim && all.All(v => !float.IsNaN(v) && !float.IsInfinity(v)), "120 finite frames");
            Check(BitEqual(first, plain.Read(0, 100, FlameLayout.Features, 0)), "the first 100 frames = the plain stream's, bit for bit");
            var cp = FlameCleanupParams.Default();
            Check(cp.Feet == FlameFeet.Lock, "default cleanup locks the feet");
            var pos = looped.Read(0, 120, FlameLayout.GlobalPositions, (int)FlameConvention.Gltf, cp);
            Check(pos.Length == 120 * 24 * 3 && pos.All(v => !float.IsNaN(v) && !float.IsInfinity(v)), "all 120 frames settled");
        }
        using (var s = FlameStream.Create(model, LoopStreamParams()))
        {
            Throws(FlameStatus.WrongState, "push a segment", () => s.EndTimelineLooped(20));
            s.Push("a person walks", 40);
            Throws(FlameStatus.InvalidArgument, "bridge of 12 frames", () => s.EndTimelineLooped(12));
            ThrowsManaged<ArgumentOutOfRangeException>(() => s.EndTimelineLooped(-1));
            s.Push("a person jumps", 20);  // the refused closes left the stream open
            s.EndTimelineLooped(20);
        }
        using (var mola = LoadFixture("mola_tiny.safetensors"))
        {
            var p = LoopStreamParams();
            p.chunk = 32; p.overlap = 8;
            using (var s = FlameStream.Create(mola, p))
            {
                s.Push("a person walks", 40);
                Throws(FlameStatus.InvalidArgument, "samples a latent", () => s.EndTimelineLooped(20));
            }
        }
    }

    // --- streams: cancel, segments with part texts, MoLA ---------------------------------------

    // The settings of tests/c/test_stream.c: chunks of 40 frames keeping 10, 3 DDIM steps, seed
    // 5; the timeline's 50 + 25 + 40 = 115 frames are five chunks of 3 steps.
    const int TimelineFrames = 115;

    static FlameStreamParams SmallStreamParams(uint threads = 1)
    {
        var p = FlameStreamParams.Default();
        p.chunk = 40;
        p.overlap = 10;
        p.lookahead = 1000;
        p.window = 10000;
        p.steps = 3;
        p.sampler = (int)FlameSampler.Ddim;
        p.seed = 5;
        p.threads = threads;
        return p;
    }

    static FlameStream Timeline(FlameModel m, FlameStreamParams p)
    {
        var s = FlameStream.Create(m, p);
        s.Push("a person walks forward.", 50);
        s.Push("a person waves.", 25);
        s.Push("a person sits down.", 40);
        return s;
    }

    /// <summary>Pumps maxSteps at a time until a call runs none; returns the pumps that threw
    /// Cancelled (any other failure propagates).</summary>
    static int PumpOn(FlameStream s, uint maxSteps)
    {
        int cancelled = 0;
        for (int calls = 0; calls < 100000; calls++)
        {
            try
            {
                if (s.Pump(maxSteps).steps == 0)
                    return cancelled;
            }
            catch (FlameException e)
            {
                if (e.Status != FlameStatus.Cancelled)
                    throw;
                cancelled++;
            }
        }
        throw new InvalidOperationException("the stream never finished");
    }

    static float[] TimelineFeatures(FlameModel m)
    {
        using (var s = Timeline(m, SmallStreamParams()))
        {
            Check(PumpOn(s, uint.MaxValue) == 0, "an uncancelled stream");
            return s.Read(0, TimelineFrames, FlameLayout.Features, 0);
        }
    }

    // A cancel with no pump running cancels the next pump's first step; that pump keeps
    // nothing, and the one after it goes on to the frames of a stream never cancelled.
    static void TestStreamCancelBetweenPumps()
    {
        foreach (var name in new[] { "flame_tiny.safetensors", "mdm_tiny.safetensors" })
        {
            using (var m = LoadFixture(name))
            {
                var want = TimelineFeatures(m);
                using (var s = Timeline(m, SmallStreamParams()))
                {
                    Check(s.Pump(4).ready == 40, name + ": the first chunk");
                    s.Cancel();
                    Throws(FlameStatus.Cancelled, "cancel", () => s.Pump(uint.MaxValue));
                    Check(s.Status().ready == 40, name + ": nothing kept from the cancelled pump");
                    var st = s.Pump(uint.MaxValue);
                    Check(st.ready == TimelineFrames && st.steps == 11, name + ": pumped on, " + st.steps + " steps to " + st.ready);
                    Check(BitEqual(s.Read(0, TimelineFrames, FlameLayout.Features, 0), want), name + ": the bits of a stream never cancelled");
                }
            }
        }
    }

    // Cancels from another thread while this one pumps one step per call (as
    // tests/c/test_stream.c does): each lands inside a pump or cancels the next one; pumping on
    // gives the bits of a stream never cancelled.
    static void TestStreamCancelFromAnotherThread()
    {
        foreach (var name in new[] { "flame_tiny.safetensors", "mdm_tiny.safetensors" })
        {
            using (var m = LoadFixture(name))
            {
                var want = TimelineFeatures(m);
                using (var s = Timeline(m, SmallStreamParams()))
                {
                    bool stop = false;
                    var canceller = new Thread(() =>
                    {
                        for (int i = 0; i < 30 && !Volatile.Read(ref stop); i++)
                        {
                            Thread.SpinWait(20000);
                            s.Cancel();
                        }
                    });
                    canceller.Start();
                    int cancelled;
                    try
                    {
                        cancelled = PumpOn(s, 1);
                    }
                    finally
                    {
                        Volatile.Write(ref stop, true);
                        canceller.Join();
                    }
                    // A cancel raised after the last pump would cancel the next one: drain it.
                    cancelled += PumpOn(s, 1);
                    Check(cancelled >= 1, name + ": " + cancelled + " pumps cancelled");
                    Check(s.Status().ready == TimelineFrames, name + ": every frame");
                    Check(BitEqual(s.Read(0, TimelineFrames, FlameLayout.Features, 0), want), name + ": the bits of a stream never cancelled");
                }
            }
        }
    }

    // One pump of a long timeline (about a hundred steps) on a worker thread, cancelled once
    // from this one: it throws Cancelled part way, and pumping on gives the same frames.
    static void TestStreamCancelLongPump()
    {
        var p = SmallStreamParams();
        p.lookahead = 100000;
        float[] want;
        using (var w = FlameStream.Create(model, p))
        {
            w.Push("a person walks forward.", 600);
            w.Push("a person waves.", 400);
            Check(PumpOn(w, uint.MaxValue) == 0, "an uncancelled stream");
            want = w.Read(0, 1000, FlameLayout.Features, 0);
        }
        using (var s = FlameStream.Create(model, p))
        {
            s.Push("a person walks forward.", 600);
            s.Push("a person waves.", 400);
            var started = new ManualResetEvent(false);
            Exception error = null;
            bool finished = false;
            var worker = new Thread(() =>
            {
                started.Set();
                try
                {
                    s.Pump(uint.MaxValue);
                    finished = true;
                }
                catch (Exception e)
                {
                    error = e;
                }
            });
            worker.Start();
            Check(started.WaitOne(30000), "worker started");
            Thread.Sleep(5);
            var watch = Stopwatch.StartNew();
            s.Cancel();
            Check(worker.Join(30000), "worker stopped");
            Check(!finished && error is FlameException && ((FlameException)error).Status == FlameStatus.Cancelled,
                  "CANCELLED on the worker, got " + error);
            Check(watch.ElapsedMilliseconds < 5000, "cancel took " + watch.ElapsedMilliseconds + " ms");
            Check(s.Status().ready < 1000, "stopped part way at " + s.Status().ready);
            Check(PumpOn(s, uint.MaxValue) == 0, "the cancel was spent");
            Check(BitEqual(s.Read(0, 1000, FlameLayout.Features, 0), want), "the bits of a stream never cancelled");
        }
    }

    static Stage EveryPart(string text, int frames)
    {
        return new Stage(text, frames)
        {
            Head = text, Stem = text, LeftArm = text, RightArm = text, LeftLeg = text, RightLeg = text, Pelvis = text,
        };
    }

    /// <summary>A FineMoGen stream (chunks of 30 keeping 8): 20 frames of walking, then what
    /// second adds; its 50 frames' features.</summary>
    static float[] FineMoGenStream(FlameModel m, Action<FlameStream> second)
    {
        var p = SmallStreamParams();
        p.chunk = 30;
        p.overlap = 8;
        using (var s = FlameStream.Create(m, p))
        {
            s.Push("a person walks forward.", 20);
            second(s);
            Check(PumpOn(s, uint.MaxValue) == 0 && s.Status().ready == 50, "50 frames");
            return s.Read(0, 50, FlameLayout.Features, 0);
        }
    }

    /// <summary>A FineMoGen stream: 30 frames of a 100-frame walk, then what interrupt does.</summary>
    static float[] FineMoGenInterrupted(FlameModel m, Action<FlameStream> interrupt)
    {
        var p = SmallStreamParams();
        p.chunk = 30;
        p.overlap = 8;
        using (var s = FlameStream.Create(m, p))
        {
            s.Push("a person walks forward.", 100);
            Check(s.Pump(3).ready == 30, "the first chunk");
            interrupt(s);
            Check(PumpOn(s, uint.MaxValue) == 0 && s.Status().ready == 60, "60 frames");
            return s.Read(0, 60, FlameLayout.Features, 0);
        }
    }

    static bool BitEqualRange(float[] a, float[] b, int start, int end)
    {
        if (a == null || b == null || a.Length < end || b.Length < end)
            return false;
        for (int i = start; i < end; i++)
            if (BitConverter.ToInt32(BitConverter.GetBytes(a[i]), 0) != BitConverter.ToInt32(BitConverter.GetBytes(b[i]), 0))
                return false;
        return true;
    }

    // FineMoGen reads part texts: every part given the segment's own text is the plain push bit
    // for bit; another right-arm text changes the second segment's frames only. InterruptStage
    // likewise against Interrupt.
    static void TestStreamStagesFineMoGen()
    {
        const string wave = "a person waves.";
        using (var m = LoadFixture("finemogen_tiny.safetensors"))
        {
            int dim = m.Info.FeatureDim;
            var plain = FineMoGenStream(m, s => s.Push(wave, 30));
            Check(plain.Length == 50 * dim, "features of 50 frames");
            Check(BitEqual(FineMoGenStream(m, s => s.PushStage(EveryPart(wave, 30))), plain), "every part = the segment's text: the plain push");
            Check(BitEqual(FineMoGenStream(m, s => s.PushStage(new Stage(wave, 30))), plain), "no part texts: the plain push");
            var arm = FineMoGenStream(m, s => s.PushStage(new Stage(wave, 30) { RightArm = "the right arm swings up and down." }));
            Check(BitEqualRange(arm, plain, 0, 20 * dim), "another right arm: the first segment unchanged");
            Check(!BitEqualRange(arm, plain, 20 * dim, 50 * dim), "another right arm: the second segment changed");

            var interrupted = FineMoGenInterrupted(m, s => s.Interrupt(wave, 30));
            Check(BitEqual(FineMoGenInterrupted(m, s => s.InterruptStage(EveryPart(wave, 30))), interrupted), "InterruptStage = Interrupt");
            var left = FineMoGenInterrupted(m, s => s.InterruptStage(new Stage(wave, 30) { LeftArm = "the left arm rises." }));
            Check(BitEqualRange(left, interrupted, 0, 30 * dim) && !BitEqualRange(left, interrupted, 30 * dim, 60 * dim),
                  "another left arm changes the frames after the interrupt only");
        }
    }

    // Other families take a stage without part texts as a plain segment and refuse part texts
    // in the pump that starts the segment.
    static void TestStreamStagesRefused()
    {
        var p = SmallStreamParams();
        float[] plain;
        using (var s = FlameStream.Create(model, p))
        {
            s.Push("a person walks.", 30);
            PumpOn(s, uint.MaxValue);
            plain = s.Read(0, 30, FlameLayout.Features, 0);
        }
        using (var s = FlameStream.Create(model, p))
        {
            s.PushStage(new Stage("a person walks.", 30) { Head = "", LeftArm = "" });
            Check(PumpOn(s, uint.MaxValue) == 0, "empty part texts");
            Check(BitEqual(s.Read(0, 30, FlameLayout.Features, 0), plain), "empty part texts follow the whole-body text");
            s.PushStage(new Stage("a person waves.", 30) { LeftArm = "the left arm waves." });
            Throws(FlameStatus.InvalidArgument, "part", () => s.Pump(uint.MaxValue));
        }
        using (var s = FlameStream.Create(model, p))
        {
            s.InterruptStage(new Stage("a person waves.", 30) { Pelvis = "the pelvis turns." });
            Throws(FlameStatus.InvalidArgument, "part", () => s.Pump(uint.MaxValue));
        }
    }

    static void TestStreamStageErrors()
    {
        var s = FlameStream.Create(model, SmallStreamParams());
        foreach (var push in new Action<Stage>[] { s.PushStage, s.InterruptStage })
        {
            ThrowsManaged<ArgumentNullException>(() => push(null));
            ThrowsManaged<ArgumentNullException>(() => push(new Stage(null, 30)));
            ThrowsManaged<ArgumentOutOfRangeException>(() => push(new Stage("a person walks.", -1)));
            ThrowsManaged<ArgumentException>(() => push(new Stage("a person walks.", 30) { RightLeg = "a\0b" }));
            Throws(FlameStatus.InvalidArgument, "frame", () => push(new Stage("a person walks.", 0)));
        }
        // Nothing was queued by the refused calls.
        var st = s.Pump(uint.MaxValue);
        Check(st.steps == 0 && st.ready == 0 && st.starving == 1, "nothing queued");
        s.Dispose();
        ThrowsManaged<ObjectDisposedException>(() => s.PushStage(new Stage("a person walks.", 30)));
        ThrowsManaged<ObjectDisposedException>(() => s.Cancel());
    }

    // MoLA (a latent model) continues each chunk through position targets: one step per call
    // on one thread and everything at once on two give the same frames.
    static void TestStreamMola()
    {
        using (var m = LoadFixture("mola_tiny.safetensors"))
        {
            Check(m.Info.Latent, "MoLA is latent");
            var got = new List<float[]>();
            foreach (uint threads in new uint[] { 1, 2 })
            {
                var p = SmallStreamParams(threads);
                p.chunk = 32;
                p.overlap = 8;
                using (var s = Timeline(m, p))
                {
                    Check(PumpOn(s, threads == 1 ? 1u : uint.MaxValue) == 0, "pumped");
                    Check(s.Status().ready == TimelineFrames, "every frame");
                    var pos = s.Read(0, TimelineFrames, FlameLayout.GlobalPositions, 0);
                    Check(pos.Length == TimelineFrames * m.Info.JointCount * 3, "positions");
                    Check(pos.All(v => !float.IsNaN(v) && !float.IsInfinity(v)), "finite");
                    got.Add(pos);
                    got.Add(s.Read(0, TimelineFrames, FlameLayout.Features, 0));
                }
            }
            Check(BitEqual(got[0], got[2]) && BitEqual(got[1], got[3]), "deterministic");
        }
    }

    static void TestPromptStageErrors()
    {
        using (var mdm = LoadFixture("mdm_tiny.safetensors"))
        using (var s = mdm.NewSession(StageParams(16)))
        {
            Throws(FlameStatus.InvalidArgument, "0 stages", () => s.SetPromptStages());
            Throws(FlameStatus.InvalidArgument, "stage 0 has no text", () => s.SetPromptStages(new Stage("", 16)));
            Throws(FlameStatus.InvalidArgument, "stage 1 has 0 frames", () => s.SetPromptStages(new Stage("a", 16), new Stage("b", 0)));
            Throws(FlameStatus.InvalidArgument, "the stages cover 15 frames, the session has 16", () => s.SetPromptStages(new Stage(RefPrompt, 15)));
            ThrowsManaged<ArgumentNullException>(() => s.SetPromptStages(null));
            ThrowsManaged<ArgumentNullException>(() => s.SetPromptStages(new Stage(RefPrompt, 8), null));
            ThrowsManaged<ArgumentNullException>(() => s.SetPromptStages(new Stage(null, 16)));
            ThrowsManaged<ArgumentOutOfRangeException>(() => s.SetPromptStages(new Stage(RefPrompt, -1)));
            ThrowsManaged<ArgumentException>(() => s.SetPromptStages(new Stage(RefPrompt, 16) { Stem = "a\0b" }));
            // A failed call changes nothing: the prompt set before it stays.
            s.SetPrompt(RefPrompt);
            Throws(FlameStatus.InvalidArgument, "add up", () => s.SetPromptStages(new Stage(RefPrompt, 17)));
            Check(BitEqual(RunAll(s), MdmRun(mdm, t => t.SetPrompt(RefPrompt))), "a refused call keeps the prompt");
        }
    }

    // FineMoGen (tests/fixtures/finemogen_tiny.safetensors, skipped when absent) composes the
    // stages: 24 + 31 frames sample 2 × 31 rows and read back as 55 frames, the CLI's --stage
    // output bit for bit; stage frame counts are fixed once stepping started.
    static void TestFineMoGenStages()
    {
        string fmg = Path.Combine(Path.GetDirectoryName(Path.GetFullPath(modelPath)), "finemogen_tiny.safetensors");
        if (!File.Exists(fmg))
        {
            Console.WriteLine("skip FineMoGenStages: no " + fmg);
            return;
        }
        string outPath = Path.Combine(tmpDir, "stages_out.npy");
        var psi = new ProcessStartInfo(cliPath,
            "generate --model \"" + fmg + "\" --stage \"a person walks forward@24\" --stage \"a person jumps@31\" " +
            "--frames 55 --steps 4 --sampler ddim --seed 1 --threads 1 --out \"" + outPath + "\"");
        psi.UseShellExecute = false;
        psi.RedirectStandardOutput = true;
        psi.RedirectStandardError = true;
        using (var proc = Process.Start(psi))
        {
            proc.StandardOutput.ReadToEnd();
            proc.StandardError.ReadToEnd();
            proc.WaitForExit();
            Check(proc.ExitCode == 0, "CLI with stages: exit code " + proc.ExitCode);
        }
        int[] shape;
        var expected = Npy.Read(outPath, out shape);
        using (var m = FlameModel.Load(fmg, 1))
        {
            var p = StageParams(55);
            p.steps = 4;
            p.seed = 1;
            using (var s = m.NewSession(p))
            {
                int rows, dim;
                s.SetPromptStages(new Stage("a person walks forward", 24), new Stage("a person jumps", 31));
                s.SampleShape(out rows, out dim);
                Check(rows == 2 * 31 && dim == 263, "stages: sample shape " + rows + "x" + dim);
                var x = RunAll(s);
                Check(s.ReadFrames(FlameWhich.Sample) == 55 && x.Length == 55 * 263 && x.All(v => !float.IsNaN(v) && !float.IsInfinity(v)),
                      "55 finite frames");
                Check(shape.Length == 2 && shape[0] == 55 && BitEqual(x, expected), "stages = the CLI's --stage output");
                s.Reset();
                s.Step();
                Throws(FlameStatus.WrongState, "before the first step",
                       () => s.SetPromptStages(new Stage("a person walks", 25), new Stage("a person jumps", 30)));
                s.SetPromptStages(new Stage("a person jumps", 24), new Stage("a person walks", 31) { LeftArm = "waves" });
                s.Reset();
                s.SetPromptStages(new Stage("a person walks", 25), new Stage("a person jumps", 30));
                s.SampleShape(out rows, out dim);
                Check(rows == 2 * 30, "after a reset: " + rows + " rows");
            }
        }
    }

    static float[] Generate(string prompt, ulong seed)
    {
        var p = FlameSessionParams.Default();
        p.frames = 48;
        p.steps = 20;
        p.sampler = (int)FlameSampler.Ddpm;
        p.seed = seed;
        p.threads = 1;
        using (var s = model.NewSession(p))
        {
            s.SetPrompt(prompt);
            return RunAll(s);
        }
    }

    // --- glTF export --------------------------------------------------------------------------

    static uint U32(byte[] b, int offset)
    {
        return (uint)(b[offset] | (b[offset + 1] << 8) | (b[offset + 2] << 16) | (b[offset + 3] << 24));
    }

    /// <summary>A GLB's JSON chunk (parsed) and binary chunk, after checking its 12-byte header
    /// ("glTF", version 2, the file's length) and the chunk headers.</summary>
    static Dictionary<string, object> SplitGlb(byte[] glb, out byte[] bin)
    {
        bin = null;
        Check(glb.Length > 28 && Encoding.ASCII.GetString(glb, 0, 4) == "glTF", "GLB magic");
        Check(U32(glb, 4) == 2, "GLB version " + U32(glb, 4));
        Check(U32(glb, 8) == glb.Length, "GLB length field " + U32(glb, 8) + " vs " + glb.Length + " bytes");
        int jsonLen = (int)U32(glb, 12);
        Check(Encoding.ASCII.GetString(glb, 16, 4) == "JSON" && jsonLen % 4 == 0, "JSON chunk header");
        var doc = (Dictionary<string, object>)Json.Parse(Encoding.UTF8.GetString(glb, 20, jsonLen));
        int b = 20 + jsonLen;
        int binLen = (int)U32(glb, b);
        Check(Encoding.ASCII.GetString(glb, b + 4, 4) == "BIN\0" && b + 8 + binLen == glb.Length, "BIN chunk header");
        bin = new byte[binLen];
        Buffer.BlockCopy(glb, b + 8, bin, 0, binLen);
        return doc;
    }

    static object At(object o, params object[] path)
    {
        foreach (var k in path)
            o = k is string ? ((Dictionary<string, object>)o)[(string)k] : ((List<object>)o)[(int)k];
        return o;
    }

    static int Int(object o, params object[] path)
    {
        return (int)(double)At(o, path);
    }

    /// <summary>The floats of accessor i, from the binary buffer.</summary>
    static float[] Accessor(Dictionary<string, object> doc, byte[] bin, int i)
    {
        var a = At(doc, "accessors", i);
        var view = At(doc, "bufferViews", Int(a, "bufferView"));
        int offset = Int(view, "byteOffset"), length = Int(view, "byteLength");
        var values = new float[length / 4];
        Buffer.BlockCopy(bin, offset, values, 0, length);
        return values;
    }

    /// <summary>The sampler output of the channel animating node's path, or null.</summary>
    static float[] Track(Dictionary<string, object> doc, byte[] bin, int node, string path)
    {
        var anim = At(doc, "animations", 0);
        foreach (var c in (List<object>)At(anim, "channels"))
            if (Int(c, "target", "node") == node && (string)At(c, "target", "path") == path)
                return Accessor(doc, bin, Int(At(anim, "samplers", Int(c, "sampler")), "output"));
        return null;
    }

    static int Channels(Dictionary<string, object> doc, string path)
    {
        return ((List<object>)At(doc, "animations", 0, "channels")).Count(c => (string)At(c, "target", "path") == path);
    }

    /// <summary>Checks a GLB of session s against its reads (Gltf convention, flags): the joint
    /// nodes, the root translation and every joint's rotation, bit for bit.</summary>
    static void CheckGltfMatchesRead(FlameSession s, ModelInfo info, byte[] glb, uint flags, string what)
    {
        byte[] bin;
        var doc = SplitGlb(glb, out bin);
        int J = info.JointCount;
        var nodes = (List<object>)At(doc, "nodes");
        bool named = nodes.Count > J;
        for (int j = 0; named && j < J; j++)
            named &= (string)At(nodes, 1 + j, "name") == info.JointNames[j];
        Check(named, what + ": nodes 1..J are named as the model's joints");
        int frames;
        var root = s.Read(FlameWhich.Sample, FlameLayout.RootTranslation, FlameConvention.Gltf, flags, out frames);
        var quats = s.Read(FlameWhich.Sample, FlameLayout.LocalQuatXyzw, FlameConvention.Gltf, flags);
        Check(BitEqual(Track(doc, bin, 1, "translation"), root), what + ": root translation = Read, bit for bit");
        bool rotations = true;
        for (int j = 0; j < J; j++)
        {
            var track = Track(doc, bin, 1 + j, "rotation");
            rotations &= track != null && track.Length == frames * 4;
            for (int f = 0; rotations && f < frames; f++)
                for (int k = 0; k < 4; k++)
                    rotations &= BitConverter.ToInt32(BitConverter.GetBytes(track[f * 4 + k]), 0) ==
                                 BitConverter.ToInt32(BitConverter.GetBytes(quats[(f * J + j) * 4 + k]), 0);
        }
        Check(rotations, what + ": every joint's rotation = Read, bit for bit");
        var times = Accessor(doc, bin, Int(At(doc, "animations", 0, "samplers", 0), "input"));
        bool timed = times.Length == frames;
        for (int f = 0; timed && f < frames; f++)
            timed &= Math.Abs(times[f] - f / (double)info.Fps) < 1e-6;
        Check(timed, what + ": times t / fps");
    }

    static void TestGltfExport()
    {
        var info = model.Info;
        using (var s = RefSession())
        {
            // Two steps: the final motion of the tiny model saturates (see TestPoseLayouts).
            s.Step();
            s.Step();
            var glb = s.WriteGltf();
            byte[] bin;
            var doc = SplitGlb(glb, out bin);
            Check((string)At(doc, "asset", "version") == "2.0", "asset.version");
            Check((string)At(doc, "nodes", 0, "name") == "smpl24", "node 0 is the skeleton's root");
            var extras = At(doc, "asset", "extras");
            Check((string)At(extras, "prompt") == RefPrompt && Int(extras, "seed") == 3, "extras: prompt and seed");
            Check((string)At(extras, "libflame") == FlameLibrary.Version && (string)At(extras, "format") == "smpl24_6d",
                  "extras: libflame version and format");
            Check((string)At(doc, "animations", 0, "name") == "a_person_walks_forward_and_waves", "animation named after the prompt");
            Check(Channels(doc, "rotation") == info.JointCount && Channels(doc, "translation") == 1,
                  "smpl24_6d: J rotation channels and the root's translation");
            CheckGltfMatchesRead(s, info, glb, 0, "plain");
            CheckGltfMatchesRead(s, info, s.WriteGltf(flags: FlameReadFlags.Smooth), FlameReadFlags.Smooth, "smooth");
            CheckGltfMatchesRead(s, info, s.WriteGltf(FlameWhich.Sample, FlameGltfContainer.Glb, FlameReadFlags.RawSigns),
                                 FlameReadFlags.RawSigns, "raw signs");
            Check(BitEqual(Track(doc, bin, 1, "translation"), s.Read(FlameWhich.Sample, FlameLayout.RootTranslation, FlameConvention.Gltf, 0)),
                  "root translation");
            Check(glb.SequenceEqual(s.WriteGltf()), "the same motion and parameters give the same bytes");

            // The JSON container: the same document, the buffer as a base64 data URI.
            var gltf = s.WriteGltf(FlameWhich.Sample, FlameGltfContainer.Gltf);
            Check(gltf.Length > 0 && gltf[0] == (byte)'{', "JSON container starts with {");
            var jdoc = (Dictionary<string, object>)Json.Parse(Encoding.UTF8.GetString(gltf));
            string uri = (string)At(jdoc, "buffers", 0, "uri");
            const string prefix = "data:application/octet-stream;base64,";
            Check(uri.StartsWith(prefix, StringComparison.Ordinal) &&
                  Convert.FromBase64String(uri.Substring(prefix.Length)).SequenceEqual(bin), "data URI = the GLB's binary chunk");
            Check(Int(jdoc, "buffers", 0, "byteLength") == bin.Length, "buffer byteLength");
            Check((string)At(jdoc, "nodes", 1, "name") == info.JointNames[0], "JSON names the joints");

            // fps, name and the estimate.
            byte[] bin30;
            var doc30 = SplitGlb(s.WriteGltf(FlameWhich.Estimate, FlameGltfContainer.Glb, 0, 30f, "my walk, take 2!"), out bin30);
            var times = Accessor(doc30, bin30, Int(At(doc30, "animations", 0, "samplers", 0), "input"));
            Check(times.Length == RefFrames && Math.Abs(times[3] - 0.1) < 1e-6 && (double)At(doc30, "asset", "extras", "fps") == 30,
                  "fps 30");
            Check((string)At(doc30, "animations", 0, "name") == "my_walk_take_2", "name sanitised");
            Check(BitEqual(Track(doc30, bin30, 1, "translation"),
                           s.Read(FlameWhich.Estimate, FlameLayout.RootTranslation, FlameConvention.Gltf, 0)), "estimate's root");

            // The length protocol through the P/Invoke declaration.
            var p = FlameGltfParams.Default();
            UIntPtr n;
            FlameException.Check(FlameNative.flame_session_write_gltf(s.Handle, 0, ref p, null, UIntPtr.Zero, out n));
            Check((int)n == glb.Length, "NULL buffer: the size " + n);
            var small = new byte[16];
            var st = FlameNative.flame_session_write_gltf(s.Handle, 0, ref p, small, (UIntPtr)small.Length, out n);
            Check(st == FlameStatus.BufferTooSmall && (int)n == glb.Length && small.All(x => x == 0),
                  "BUFFER_TOO_SMALL writes the size, not the file: " + st + " " + n);
            Check(FlameNative.Utf8(FlameNative.flame_last_error()).Contains("buffer too small"), "buffer too small message");
            var big = new byte[glb.Length + 4];
            FlameException.Check(FlameNative.flame_session_write_gltf(s.Handle, 0, ref p, big, (UIntPtr)big.Length, out n));
            Check((int)n == glb.Length && big.Take(glb.Length).SequenceEqual(glb), "a larger buffer gets the file");
            p.struct_size = 8;
            Throws(FlameStatus.InvalidArgument, "struct_size", () => FlameException.Check(
                FlameNative.flame_session_write_gltf(s.Handle, 0, ref p, null, UIntPtr.Zero, out n)));
        }
    }

    static void TestGltfHumanMl263()
    {
        // humanml263 (MDM): its joint positions are its own features, so every non-root joint's
        // translation is animated as well.
        string dir = Path.GetDirectoryName(Path.GetFullPath(modelPath));
        var p = FlameSessionParams.Default();
        p.frames = 16;
        p.steps = 3;
        p.sampler = (int)FlameSampler.Ddim;
        p.seed = 1;
        p.threads = 1;
        using (var mdm = FlameModel.Load(Path.Combine(dir, "mdm_tiny.safetensors"), 1))
        using (var s = mdm.NewSession(p))
        {
            s.SetPrompt(RefPrompt);
            RunAll(s);
            var info = mdm.Info;
            var glb = s.WriteGltf();
            byte[] bin;
            var doc = SplitGlb(glb, out bin);
            Check((string)At(doc, "nodes", 0, "name") == "humanml22" && info.JointCount == 22, "HumanML3D's 22 joints");
            Check(Channels(doc, "translation") == info.JointCount && Channels(doc, "rotation") == info.JointCount,
                  "humanml263: every joint's translation and rotation");
            Check((string)At(doc, "asset", "extras", "format") == "humanml263", "format");
            CheckGltfMatchesRead(s, info, glb, 0, "humanml263");
        }
    }

    static void TestGltfFiles()
    {
        using (var s = RefSession())
        {
            s.Step();
            string glbPath = Path.Combine(tmpDir, "motion.glb"), gltfPath = Path.Combine(tmpDir, "motion.GLTF");
            var glb = s.WriteGltf(glbPath);
            Check(File.ReadAllBytes(glbPath).SequenceEqual(glb) && glb.SequenceEqual(s.WriteGltf()), "path.glb: GLB file = bytes");
            var gltf = s.WriteGltf(gltfPath, FlameWhich.Sample, FlameReadFlags.Smooth);
            Check(File.ReadAllBytes(gltfPath).SequenceEqual(gltf) &&
                  gltf.SequenceEqual(s.WriteGltf(FlameWhich.Sample, FlameGltfContainer.Gltf, FlameReadFlags.Smooth)),
                  "path.GLTF: JSON file = bytes, with the flags");
            string bvh = Path.Combine(tmpDir, "motion.bvh");
            ThrowsManaged<ArgumentException>(() => s.WriteGltf(bvh));
            Check(!File.Exists(bvh), "nothing written for an unknown extension");
            ThrowsManaged<ArgumentNullException>(() => s.WriteGltf((string)null));
        }
    }

    static void TestGltfErrors()
    {
        using (var s = model.NewSession(RefParams()))
        {
            Throws(FlameStatus.WrongState, "no sample yet", () => s.WriteGltf());
            s.SetPrompt(RefPrompt);
            Throws(FlameStatus.WrongState, "no sample yet", () => s.WriteGltf());
            Throws(FlameStatus.WrongState, "no clean-motion estimate", () => s.WriteGltf(FlameWhich.Estimate));
            s.Step();
            Throws(FlameStatus.InvalidArgument, "unknown glTF container 7", () => s.WriteGltf(FlameWhich.Sample, (FlameGltfContainer)7));
            Throws(FlameStatus.InvalidArgument, "unknown glTF container -1", () => s.WriteGltf(FlameWhich.Sample, (FlameGltfContainer)(-1)));
            Throws(FlameStatus.InvalidArgument, "frame rate must be positive", () => s.WriteGltf(fps: -1f));
            Throws(FlameStatus.InvalidArgument, "unknown `which` 4", () => s.WriteGltf((FlameWhich)4));
            Throws(FlameStatus.InvalidArgument, "unknown read flags", () => s.WriteGltf(flags: 4));
            ThrowsManaged<ArgumentException>(() => s.WriteGltf(name: "a\0b"));
            Check(s.WriteGltf(name: "été").Length > 0, "a non-ASCII name");
            s.Reset();
            Throws(FlameStatus.WrongState, "no sample yet", () => s.WriteGltf());
        }
    }

    // --- cleanup (flame_session_read_cleaned) ------------------------------------------------
    // A 40-frame motion of the smpl24 fixture (20 fps), read after two of ten steps (the final
    // motion of the tiny model saturates, see TestPoseLayouts). What a cleanup promises:
    // resampling copies the frames at common times, in-place leaves no horizontal travel, the
    // root bone carries exactly the travel the pelvis lost.

    const int CleanFrames = 40;

    static FlameSession CleanupSession()
    {
        var p = RefParams();
        p.frames = CleanFrames;
        p.seed = 5;
        var s = model.NewSession(p);
        s.SetPrompt(RefPrompt);
        s.Step();
        s.Step();
        return s;
    }

    // World quaternions are left out: they are made sign-continuous along each track after
    // posing, and the frames in between may change a track's sign (q and -q: the same rotation).
    static readonly int[] PoseLayouts = { FlameLayout.RootTranslation, FlameLayout.LocalQuatXyzw, FlameLayout.LocalMatrix, FlameLayout.GlobalPositions };

    static float[] Rows(float[] a, int from, int count, int width)
    {
        var r = new float[count * width];
        Array.Copy(a, from * width, r, 0, count * width);
        return r;
    }

    static void TestCleanupOffIsRaw()
    {
        using (var s = CleanupSession())
        {
            foreach (int layout in PoseLayouts)
            {
                var raw = s.Read(FlameWhich.Sample, layout, FlameConvention.Unity, 0);
                Check(BitEqual(s.Read(FlameWhich.Sample, layout, FlameConvention.Unity, 0, null), raw), "null cleanup = Read, layout " + layout);
                Check(BitEqual(s.Read(FlameWhich.Sample, layout, FlameConvention.Unity, 0, FlameCleanupParams.Raw()), raw),
                      "Raw() = Read, layout " + layout);
                var twenty = FlameCleanupParams.Raw();
                twenty.fps = 20;
                Check(BitEqual(s.Read(FlameWhich.Sample, layout, FlameConvention.Unity, 0, twenty), raw), "fps 20 (the model's) = Read, layout " + layout);
            }
            var odd = FlameCleanupParams.Default();
            odd.fps = 30;
            odd.RootMotion = FlameRootMotion.Separate;
            Check(BitEqual(s.Read(FlameWhich.Sample, FlameLayout.Features, 0, 0, odd), s.Read(FlameWhich.Sample, FlameLayout.Features, 0, 0)),
                  "features are never post-processed");
        }
    }

    static void TestCleanupFps()
    {
        Check(model.Info.Fps == 20f, "the fixture runs at 20 fps");
        using (var s = CleanupSession())
        {
            var thirty = FlameCleanupParams.Raw();
            thirty.fps = 30;
            foreach (int layout in PoseLayouts)
            {
                int width = FlameLayout.ValuesPerFrame(layout, s.FeatureDim, s.JointCount);
                var raw = s.Read(FlameWhich.Sample, layout, FlameConvention.Gltf, 0);
                int frames;
                var output = s.Read(FlameWhich.Sample, layout, FlameConvention.Gltf, 0, thirty, out frames);
                // 39 intervals of 1/20 s = 1.95 s: frames 0..58 at 30 fps, the last one's time kept.
                Check(frames == 59 && output.Length == 59 * width && s.ReadLength(FlameWhich.Sample, layout, FlameConvention.Gltf, 0, thirty) == 59 * width,
                      "layout " + layout + ": " + frames + " frames at 30 fps");
                // Output frame 3k is at input frame 2k's time: copied bit for bit.
                bool common = true;
                for (int k = 0; k < 20; k++)
                    common &= BitEqual(Rows(output, 3 * k, 1, width), Rows(raw, 2 * k, 1, width));
                Check(common, "layout " + layout + ": frames 3k = input frames 2k, bit for bit");
                Check(!BitEqual(Rows(output, 1, 1, width), Rows(raw, 0, 1, width)) && !BitEqual(Rows(output, 1, 1, width), Rows(raw, 1, 1, width)),
                      "layout " + layout + ": frame 1 is new");
            }
            // ReadInto with a caller buffer: the same values; a buffer sized for the raw read is too small.
            var buffer = new float[59 * 3];
            Check(s.ReadInto(buffer, FlameWhich.Sample, FlameLayout.RootTranslation, FlameConvention.Gltf, 0, thirty) == 59 * 3 &&
                  BitEqual(buffer, s.Read(FlameWhich.Sample, FlameLayout.RootTranslation, FlameConvention.Gltf, 0, thirty)), "ReadInto with a cleanup");
            Throws(FlameStatus.BufferTooSmall, "", () => s.ReadInto(new float[CleanFrames * 3], FlameWhich.Sample, FlameLayout.RootTranslation,
                                                                    FlameConvention.Gltf, 0, thirty));
        }
    }

    static void TestCleanupRootMotion()
    {
        using (var s = CleanupSession())
        {
            // Unity: Y up, so x and z are horizontal.
            var keep = s.Read(FlameWhich.Sample, FlameLayout.RootTranslation, FlameConvention.Unity, 0);
            double travel = 0;
            for (int f = 0; f < CleanFrames; f++)
                travel = Math.Max(travel, Math.Max(Math.Abs(keep[f * 3] - keep[0]), Math.Abs(keep[f * 3 + 2] - keep[2])));
            Check(travel > 1e-3, "the raw pelvis travels (" + travel + " m)");

            var inPlace = FlameCleanupParams.Raw();
            inPlace.RootMotion = FlameRootMotion.InPlace;
            var pelvis = s.Read(FlameWhich.Sample, FlameLayout.RootTranslation, FlameConvention.Unity, 0, inPlace);
            bool still = pelvis.Length == CleanFrames * 3, height = still;
            for (int f = 0; still && f < CleanFrames; f++)
            {
                still &= Math.Abs(pelvis[f * 3]) < 1e-6 && Math.Abs(pelvis[f * 3 + 2]) < 1e-6;
                height &= pelvis[f * 3 + 1] == keep[f * 3 + 1];
            }
            Check(still, "in place: no horizontal pelvis translation");
            Check(height, "in place: the height is kept");

            var separate = FlameCleanupParams.Raw();
            separate.RootMotion = FlameRootMotion.Separate;
            int frames;
            var bone = s.Read(FlameWhich.Sample, FlameLayout.RootBone, FlameConvention.Unity, 0, separate, out frames);
            var rest = s.Read(FlameWhich.Sample, FlameLayout.RootTranslation, FlameConvention.Unity, 0, separate);
            bool grounded = frames == CleanFrames && bone.Length == CleanFrames * 3, sums = grounded, moves = false;
            for (int f = 0; grounded && f < CleanFrames; f++)
            {
                grounded &= bone[f * 3 + 1] == 0;
                moves |= Math.Abs(bone[f * 3]) > 1e-3 || Math.Abs(bone[f * 3 + 2]) > 1e-3;
                sums &= Math.Abs(bone[f * 3] + rest[f * 3] - keep[f * 3]) < 1e-5 && Math.Abs(bone[f * 3 + 2] + rest[f * 3 + 2] - keep[f * 3 + 2]) < 1e-5;
            }
            Check(grounded, "separate: the root bone at height 0");
            Check(moves, "separate: the root bone carries the travel");
            Check(sums, "separate: pelvis + root bone = the kept pelvis (horizontal)");
            Throws(FlameStatus.InvalidArgument, "root", () => s.Read(FlameWhich.Sample, FlameLayout.RootBone, FlameConvention.Unity, 0, FlameCleanupParams.Default()));
            Throws(FlameStatus.InvalidArgument, "root", () => s.Read(FlameWhich.Sample, FlameLayout.RootBone, FlameConvention.Unity, 0));
        }
    }

    static void TestCleanupFeetAndGround()
    {
        using (var s = CleanupSession())
        {
            // The motion two steps in is close to noise: its feet move too fast for the default
            // contact detection, so the test widens it (which checks that the contact fields
            // reach libflame: the default finds fewer contacts).
            var wide = FlameCleanupParams.Default();
            wide.contact_height = 1f;
            wide.contact_speed = 20f;
            wide.contact_min_span = 0f;
            var defaults = s.Read(FlameWhich.Sample, FlameLayout.FootContacts, 0, 0, FlameCleanupParams.Default());
            var contacts = s.Read(FlameWhich.Sample, FlameLayout.FootContacts, 0, 0, wide);
            Check(contacts.Length == CleanFrames * 4 && contacts.All(c => c == 0 || c == 1) && contacts.Count(c => c == 1) > defaults.Count(c => c == 1),
                  "contacts: 0 or 1, more with the wider detection");
            Check(BitEqual(s.Read(FlameWhich.Sample, FlameLayout.FootContacts, 0, 0), defaults), "a raw read detects with the defaults");
            // ground: the lowest joint of a planted foot (ankle or toe, in a frame where that
            // leg's ankle or toe is in contact; contact columns left ankle, left foot, right
            // ankle, right foot = smpl24 joints 7, 10, 8, 11) at height 0 (Unity: y).
            var ground = FlameCleanupParams.Raw();
            ground.ground = 1;
            ground.contact_height = wide.contact_height;
            ground.contact_speed = wide.contact_speed;
            ground.contact_min_span = wide.contact_min_span;
            var grounded = s.Read(FlameWhich.Sample, FlameLayout.GlobalPositions, FlameConvention.Unity, 0, ground);
            var raw = s.Read(FlameWhich.Sample, FlameLayout.GlobalPositions, FlameConvention.Unity, 0);
            int J = s.JointCount;
            int[][] legs = { new[] { 0, 1, 7, 10 }, new[] { 2, 3, 8, 11 } };
            Func<float[], double> floor = positions =>
            {
                double lowest = double.MaxValue;
                for (int f = 0; f < CleanFrames; f++)
                    foreach (var leg in legs)
                        if (contacts[f * 4 + leg[0]] == 1 || contacts[f * 4 + leg[1]] == 1)
                            lowest = Math.Min(lowest, Math.Min(positions[(f * J + leg[2]) * 3 + 1], positions[(f * J + leg[3]) * 3 + 1]));
                return lowest;
            };
            Check(Math.Abs(floor(grounded)) < 1e-5, "ground: the lowest contact at 0, got " + floor(grounded));
            Check(Math.Abs(floor(raw)) > 1e-2, "the raw floor was elsewhere: " + floor(raw));
            // Feet lock moves the feet, not the pelvis.
            var locked = s.Read(FlameWhich.Sample, FlameLayout.GlobalPositions, FlameConvention.Unity, 0, wide);
            double pelvis = 0, foot = 0;
            for (int f = 0; f < CleanFrames; f++)
                for (int k = 0; k < 3; k++)
                {
                    pelvis = Math.Max(pelvis, Math.Abs(locked[(f * J) * 3 + k] - grounded[(f * J) * 3 + k]));
                    foot = Math.Max(foot, Math.Abs(locked[(f * J + 10) * 3 + k] - grounded[(f * J + 10) * 3 + k]));
                    foot = Math.Max(foot, Math.Abs(locked[(f * J + 11) * 3 + k] - grounded[(f * J + 11) * 3 + k]));
                }
            Check(pelvis == 0 && foot > 1e-3, "feet lock: pelvis moved " + pelvis + ", feet " + foot);
        }
    }

    static void TestCleanupErrors()
    {
        using (var s = CleanupSession())
        {
            var nan = FlameCleanupParams.Default();
            nan.fps = float.NaN;
            Throws(FlameStatus.InvalidArgument, "got NaN", () => s.Read(FlameWhich.Sample, FlameLayout.RootTranslation, 1, 0, nan));
            var huge = FlameCleanupParams.Default();
            huge.fps = 1e9f;
            Throws(FlameStatus.InvalidArgument, "got 1000000000", () => s.Read(FlameWhich.Sample, FlameLayout.RootTranslation, 1, 0, huge));
            var below = FlameCleanupParams.Default();
            below.contact_height = -0.5f;
            Throws(FlameStatus.InvalidArgument, "contact height (m) must be between 0 and 1, got -0.5",
                   () => s.Read(FlameWhich.Sample, FlameLayout.RootTranslation, 1, 0, below));
            var feet = FlameCleanupParams.Default();
            feet.feet = 7;
            Throws(FlameStatus.InvalidArgument, "feet mode 7", () => s.Read(FlameWhich.Sample, FlameLayout.RootTranslation, 1, 0, feet));
            // A struct_size below the struct's is refused (an older caller's would name fewer fields).
            var small = FlameCleanupParams.Default();
            small.struct_size = 8;
            Throws(FlameStatus.InvalidArgument, "cleanup.struct_size is 8, expected at least 44", () => s.Read(FlameWhich.Sample, FlameLayout.RootTranslation, 1, 0, small));
            Throws(FlameStatus.InvalidArgument, "got NaN", () => s.WriteGltf(cleanup: nan));
        }
    }

    static void TestCleanupGltf()
    {
        using (var s = CleanupSession())
        {
            byte[] bin;
            var doc = SplitGlb(s.WriteGltf(), out bin);
            var names = ((List<object>)At(doc, "nodes")).Select(n => ((Dictionary<string, object>)n).ContainsKey("name") ? (string)At(n, "name") : null).ToList();
            Check(!names.Contains("root"), "raw export: no root node");
            Check(Accessor(doc, bin, Int(At(doc, "animations", 0, "samplers", 0), "input")).Length == CleanFrames, "raw export: 40 keys");
            var c = FlameCleanupParams.Raw();
            c.RootMotion = FlameRootMotion.Separate;
            c.fps = 30;
            doc = SplitGlb(s.WriteGltf(cleanup: c), out bin);
            names = ((List<object>)At(doc, "nodes")).Select(n => ((Dictionary<string, object>)n).ContainsKey("name") ? (string)At(n, "name") : null).ToList();
            int root = names.IndexOf("root"), pelvis = names.IndexOf("Pelvis");
            Check(root >= 0 && pelvis >= 0, "separate: a node named root");
            Check(root >= 0 && ((Dictionary<string, object>)At(doc, "nodes", root)).ContainsKey("children") &&
                  ((List<object>)At(doc, "nodes", root, "children")).Any(x => (int)(double)x == pelvis), "the root node is the pelvis's parent");
            Check(Accessor(doc, bin, Int(At(doc, "animations", 0, "samplers", 0), "input")).Length == 59, "fps 30: 59 keys");
            // The root bone's track is the RootBone read in glTF's convention.
            var track = Track(doc, bin, root, "translation");
            Check(BitEqual(track, s.Read(FlameWhich.Sample, FlameLayout.RootBone, FlameConvention.Gltf, 0, c)), "root node track = RootBone read, bit for bit");
        }
    }

    static void TestTwoThreads()
    {
        string[] prompts = { RefPrompt, "a person jumps twice." };
        ulong[] seeds = { 3, 11 };
        var sequential = new float[2][];
        for (int i = 0; i < 2; i++)
            sequential[i] = Generate(prompts[i], seeds[i]);
        var parallel = new float[2][];
        var threads = new Thread[2];
        for (int i = 0; i < 2; i++)
        {
            int k = i;
            threads[k] = new Thread(() => parallel[k] = Generate(prompts[k], seeds[k]));
            threads[k].Start();
        }
        foreach (var t in threads)
            t.Join();
        Check(BitEqual(parallel[0], sequential[0]) && BitEqual(parallel[1], sequential[1]), "two threads = sequential");
        Check(!BitEqual(sequential[0], sequential[1]), "different prompts differ");
    }

    // --- retargeting (flame_rig_*, flame_bone_map_*, flame_retarget_*) -------------------------

    static string RepoRoot()
    {
        return Path.GetDirectoryName(Path.GetDirectoryName(Path.GetFullPath(headerPath)));
    }

    /// <summary>Quaternion x, y, z, w product a·b (doubles).</summary>
    static double[] QMul(double[] a, double[] b)
    {
        return new[]
        {
            a[3] * b[0] + a[0] * b[3] + a[1] * b[2] - a[2] * b[1],
            a[3] * b[1] - a[0] * b[2] + a[1] * b[3] + a[2] * b[0],
            a[3] * b[2] + a[0] * b[1] - a[1] * b[0] + a[2] * b[3],
            a[3] * b[3] - a[0] * b[0] - a[1] * b[1] - a[2] * b[2],
        };
    }

    static double[] QConj(double[] q)
    {
        return new[] { -q[0], -q[1], -q[2], q[3] };
    }

    /// <summary>v rotated by the unit quaternion q (q v q*).</summary>
    static double[] QRotate(double[] q, double[] v)
    {
        var r = QMul(QMul(q, new[] { v[0], v[1], v[2], 0 }), QConj(q));
        return new[] { r[0], r[1], r[2] };
    }

    static double[] QAxisAngle(double x, double y, double z, double degrees)
    {
        double n = Math.Sqrt(x * x + y * y + z * z), h = degrees * Math.PI / 360;
        return new[] { x / n * Math.Sin(h), y / n * Math.Sin(h), z / n * Math.Sin(h), Math.Cos(h) };
    }

    static double AngleDeg(double[] a, double[] b)
    {
        double dot = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
        double na = Math.Sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]), nb = Math.Sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2]);
        return Math.Acos(Math.Max(-1, Math.Min(1, dot / (na * nb)))) * 180 / Math.PI;
    }

    static double[] Sub(double[] a, double[] b)
    {
        return new[] { a[0] - b[0], a[1] - b[1], a[2] - b[2] };
    }

    /// <summary>A humanoid in Unity's convention (metres, Y up, facing +Z, its left at -X),
    /// unlike SMPL: arms in an A-pose (45° down), longer limbs, a root above the hips, a twist
    /// bone, and a different roll on every bone (rest rotations the retarget must see through).
    /// Given as world positions and rotations, turned into parent-relative bones here.</summary>
    static List<RigBone> UnityHumanoid(Func<string, string> rename = null)
    {
        double s = Math.Sqrt(0.5);
        var spec = new List<Tuple<string, string, double[]>>();
        Action<string, string, double, double, double> add = (name, parent, x, y, z) =>
            spec.Add(Tuple.Create(name, parent, new[] { x, y, z }));
        add("Root", null, 0, 0, 0);
        add("Hips", "Root", 0, 1.0, 0.02);
        add("Spine", "Hips", 0, 1.1, 0);
        add("Chest", "Spine", 0, 1.25, -0.01);
        add("Neck", "Chest", 0, 1.5, 0);
        add("Head", "Neck", 0, 1.62, 0.02);
        foreach (var side in new[] { "Left", "Right" })
        {
            double m = side == "Left" ? -1 : 1;
            add(side + "Shoulder", "Chest", m * 0.04, 1.45, 0);
            add(side + "UpperArm", side + "Shoulder", m * 0.17, 1.45, 0);
            add(side + "UpperArmTwist", side + "UpperArm", m * (0.17 + 0.15 * s), 1.45 - 0.15 * s, 0);
            add(side + "LowerArm", side + "UpperArm", m * (0.17 + 0.3 * s), 1.45 - 0.3 * s, 0);
            add(side + "Hand", side + "LowerArm", m * (0.17 + 0.57 * s), 1.45 - 0.57 * s, 0);
            add(side + "UpperLeg", "Hips", m * 0.1, 0.94, 0);
            add(side + "LowerLeg", side + "UpperLeg", m * 0.1, 0.5, 0.01);
            add(side + "Foot", side + "LowerLeg", m * 0.1, 0.08, 0);
            add(side + "Toes", side + "Foot", m * 0.1, 0.0, 0.13);
        }
        var index = new Dictionary<string, int>();
        var world = new List<double[]>();
        for (int i = 0; i < spec.Count; i++)
        {
            index[spec[i].Item1] = i;
            world.Add(QAxisAngle(1 + i % 3, 2 - i % 2, 0.5 * i, 17 * i));   // some roll per bone
        }
        var bones = new List<RigBone>();
        for (int i = 0; i < spec.Count; i++)
        {
            int p = spec[i].Item2 == null ? -1 : index[spec[i].Item2];
            double[] t = spec[i].Item3, r = world[i];
            if (p >= 0)
            {
                var inv = QConj(world[p]);
                t = QRotate(inv, Sub(spec[i].Item3, spec[p].Item3));
                r = QMul(inv, world[i]);
            }
            string name = rename == null ? spec[i].Item1 : rename(spec[i].Item1);
            bones.Add(new RigBone(name, p, new[] { (float)t[0], (float)t[1], (float)t[2] },
                                  new[] { (float)r[0], (float)r[1], (float)r[2], (float)r[3] }));
        }
        return bones;
    }

    /// <summary>World positions (and rotations) of one frame's retargeted pose by forward
    /// kinematics from the local rotations and translations (the rig's bones list parents
    /// before children, as UnityHumanoid gives them).</summary>
    static double[][] Fk(int[] parents, float[] rot, float[] tr, int frame)
    {
        int n = parents.Length;
        var pos = new double[n][];
        var wrot = new double[n][];
        for (int b = 0; b < n; b++)
        {
            int q = (frame * n + b) * 4, t = (frame * n + b) * 3;
            var local = new double[] { rot[q], rot[q + 1], rot[q + 2], rot[q + 3] };
            var offset = new double[] { tr[t], tr[t + 1], tr[t + 2] };
            int p = parents[b];
            if (p < 0)
            {
                wrot[b] = local;
                pos[b] = offset;
            }
            else
            {
                wrot[b] = QMul(wrot[p], local);
                var o = QRotate(wrot[p], offset);
                pos[b] = new[] { pos[p][0] + o[0], pos[p][1] + o[1], pos[p][2] + o[2] };
            }
        }
        return pos;
    }

    /// <summary>The rotation taking the source directions (pair[1]) of two pairs onto their rig
    /// directions (pair[0]): the triad method, exact for exact data.</summary>
    static double[][] Triad(double[][] p, double[][] q)
    {
        Func<double[], double[], double[][]> frame = (a, b) =>
        {
            var t1 = Normalize(a);
            var t2 = Normalize(Cross(a, b));
            var t3 = Cross(t1, t2);
            return new[] { t1, t2, t3 };
        };
        var rig = frame(p[0], q[0]);
        var src = frame(p[1], q[1]);
        var c = new double[3][];
        for (int i = 0; i < 3; i++)
        {
            c[i] = new double[3];
            for (int j = 0; j < 3; j++)
                for (int k = 0; k < 3; k++)
                    c[i][j] += rig[k][i] * src[k][j];
        }
        return c;
    }

    static double[] Cross(double[] a, double[] b)
    {
        return new[] { a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0] };
    }

    static double[] Normalize(double[] a)
    {
        double n = Math.Sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
        return new[] { a[0] / n, a[1] / n, a[2] / n };
    }

    static double[] MatVec(double[][] m, double[] v)
    {
        return new[] { m[0][0] * v[0] + m[0][1] * v[1] + m[0][2] * v[2], m[1][0] * v[0] + m[1][1] * v[1] + m[1][2] * v[2],
                       m[2][0] * v[0] + m[2][1] * v[1] + m[2][2] * v[2] };
    }

    // Rig bone → its mapped child, and the SMPL joints they stand for (SMPL's order:
    // 1/2 hips, 4/5 knees, 7/8 ankles, 10/11 feet, 12 neck, 13/14 collars, 15 head,
    // 16/17 shoulders, 18/19 elbows, 20/21 wrists).
    static readonly string[,] LimbPairs =
    {
        { "LeftUpperArm", "LeftLowerArm", "16", "18" }, { "LeftLowerArm", "LeftHand", "18", "20" },
        { "RightUpperArm", "RightLowerArm", "17", "19" }, { "RightLowerArm", "RightHand", "19", "21" },
        { "LeftUpperLeg", "LeftLowerLeg", "1", "4" }, { "LeftLowerLeg", "LeftFoot", "4", "7" },
        { "RightUpperLeg", "RightLowerLeg", "2", "5" }, { "RightLowerLeg", "RightFoot", "5", "8" },
        { "LeftFoot", "LeftToes", "7", "10" }, { "RightFoot", "RightToes", "8", "11" },
        { "LeftShoulder", "LeftUpperArm", "13", "16" }, { "RightShoulder", "RightUpperArm", "14", "17" },
        { "Neck", "Head", "12", "15" },
    };

    static void TestRetargetLayouts()
    {
        // FlameRetargetParams: four 32-bit fields then a pointer (C on x86-64: sizeof 24,
        // offsetof map 16); the library writes its sizeof into struct_size.
        var p = FlameRetargetParams.Default();
        Check(p.struct_size == Marshal.SizeOf(typeof(FlameRetargetParams)) && p.struct_size == 16 + IntPtr.Size,
              "sizeof FlameRetargetParams " + p.struct_size + " vs " + Marshal.SizeOf(typeof(FlameRetargetParams)));
        Check((int)Marshal.OffsetOf(typeof(FlameRetargetParams), "map") == 16, "offset of FlameRetargetParams.map");
        Check(p.convention == FlameConvention.Native && p.feet == 1 && p.hands == 0 && p.map == IntPtr.Zero,
              "retarget defaults: the rig's convention, feet IK on, hands off, the automatic map");
        // FlameRigBone: uint32, int32, a pointer, float[3], float[4], float[3] (C on x86-64:
        // sizeof 56, offsetof name 8, translation 16, rotation 28, scale 44).
        int ptr = IntPtr.Size;
        Check(Marshal.SizeOf(typeof(FlameRigBone)) == 48 + ptr, "sizeof FlameRigBone " + Marshal.SizeOf(typeof(FlameRigBone)));
        Check((int)Marshal.OffsetOf(typeof(FlameRigBone), "name") == 8 &&
              (int)Marshal.OffsetOf(typeof(FlameRigBone), "translation_x") == 8 + ptr &&
              (int)Marshal.OffsetOf(typeof(FlameRigBone), "rotation_x") == 20 + ptr &&
              (int)Marshal.OffsetOf(typeof(FlameRigBone), "scale_x") == 36 + ptr, "offsets of FlameRigBone");
        // libflame checks struct_size against its own sizeof: ours is accepted, one less is not.
        var name = GCHandle.Alloc(FlameNative.Utf8Z("Hips"), GCHandleType.Pinned);
        try
        {
            var bone = new FlameRigBone { struct_size = (uint)Marshal.SizeOf(typeof(FlameRigBone)), parent = -1, name = name.AddrOfPinnedObject(),
                                          rotation_w = 1, scale_x = 1, scale_y = 1, scale_z = 1 };
            FlameRigHandle h;
            FlameException.Check(FlameNative.flame_rig_from_bones(new[] { bone }, (UIntPtr)1, FlameConvention.Unity, out h));
            h.Dispose();
            bone.struct_size -= 1;
            Throws(FlameStatus.InvalidArgument, "bones[0].struct_size is " + bone.struct_size + ", expected at least " + Marshal.SizeOf(typeof(FlameRigBone)),
                   () => FlameException.Check(FlameNative.flame_rig_from_bones(new[] { bone }, (UIntPtr)1, FlameConvention.Unity, out h)));
        }
        finally
        {
            name.Free();
        }
    }

    static void TestRigFromBones()
    {
        var bones = UnityHumanoid();
        using (var rig = FlameRig.FromBones(bones, FlameConvention.Unity))
        {
            // Bones numbered as given, whatever order libflame keeps them in.
            Check(rig.BoneCount == bones.Count, "bone count " + rig.BoneCount);
            bool same = true;
            for (int i = 0; i < bones.Count; i++)
                same &= rig.BoneNames[i] == bones[i].Name && rig.BoneParents[i] == bones[i].Parent;
            Check(same, "names and parents as given");
            Check(rig.BoneIndex("LeftHand") == bones.FindIndex(b => b.Name == "LeftHand") && rig.BoneIndex("nope") == -1, "BoneIndex");
            using (var map = FlameBoneMap.Auto(rig))
            {
                string json = map.ToJson();
                // Unity's (and VRM's) names are found; the twist bone and the root are not body bones.
                foreach (var pair in new[] { "hips\": \"Hips", "leftUpperArm\": \"LeftUpperArm", "rightLowerLeg\": \"RightLowerLeg",
                                             "leftToes\": \"LeftToes", "upperChest\": null" })
                    Check(json.Contains("\"" + pair.Replace("\": null", "\": null")), "auto map has " + pair + ": " + json);
                Check(!json.Contains("Twist") && !json.Contains("\"Root\""), "twist and root unmapped: " + json);
                // What ToJson writes, FromJson reads back to the same map.
                using (var again = FlameBoneMap.FromJson(rig, json))
                    Check(again.ToJson() == json, "JSON round trip");
                // Keys over a base: only the named bone changes.
                using (var moved = FlameBoneMap.FromJson(rig, "{\"HEAD\": \"Neck\", \"neck\": null}", map))
                {
                    string j2 = moved.ToJson();
                    Check(j2.Contains("\"head\": \"Neck\"") && j2.Contains("\"neck\": null") && j2.Contains("\"hips\": \"Hips\""),
                          "FromJson over a base: " + j2);
                }
            }
        }
        // Parents may come after their children: the same rig, listed backwards.
        var reversed = new List<RigBone>();
        for (int i = bones.Count - 1; i >= 0; i--)
            reversed.Add(new RigBone(bones[i].Name, bones[i].Parent < 0 ? -1 : bones.Count - 1 - bones[i].Parent,
                                     bones[i].Translation, bones[i].Rotation));
        using (var rig = FlameRig.FromBones(reversed, FlameConvention.Unity))
            Check(rig.BoneNames[0] == "RightToes" && rig.BoneParents[0] == bones.Count - 1 - bones.FindIndex(b => b.Name == "RightFoot"),
                  "children before parents kept in the given order");
    }

    /// <summary>The reference session after one step: a motion whose rotations are all proper
    /// (the tiny model's final ones hold degenerate rotations, a random network's saturated 6D
    /// pairs), read as the sample.</summary>
    static FlameSession MovingSession()
    {
        var s = RefSession();
        s.Step();
        return s;
    }

    /// <summary>The reference generation, finished, and a Unity rig's retarget of it.</summary>
    static FlameRetarget UnityRetarget(FlameRig rig, bool feet)
    {
        var p = FlameRetargetParams.Default();
        p.feet = feet ? 1u : 0u;
        return FlameRetarget.Create(model, rig, null, p);
    }

    static void TestRetargetDirections()
    {
        // Independent check: forward kinematics (here, in C#) of the returned local rotations and
        // translations puts every mapped limb bone along its SMPL joint's direction, as the
        // session's own joint positions (GlobalPositions, Unity's convention) give it.
        var bones = UnityHumanoid();
        using (var rig = FlameRig.FromBones(bones, FlameConvention.Unity))
        using (var r = UnityRetarget(rig, false))
        using (var s = MovingSession())
        {
            int n = r.BoneCount, frames = r.Frames(s);
            Check(n == bones.Count && frames == RefFrames, "bones " + n + ", frames " + frames);
            var rot = new float[frames * n * 4];
            var tr = new float[frames * n * 3];
            Check(r.Read(s, 0, frames, rot, tr) == RefFrames, "read returns the frames");
            var joints = s.Read(FlameWhich.Sample, FlameLayout.GlobalPositions, FlameConvention.Unity, 0);
            // Bone k's direction on the rig and its joints' in the source, frame f.
            Func<int, int, double[][]> dirs = (f, k) =>
            {
                var pos = Fk(rig.BoneParents, rot, tr, f);
                Func<int, double[]> joint = j => new double[] { joints[(f * 24 + j) * 3], joints[(f * 24 + j) * 3 + 1], joints[(f * 24 + j) * 3 + 2] };
                return new[]
                {
                    Sub(pos[rig.BoneIndex(LimbPairs[k, 1])], pos[rig.BoneIndex(LimbPairs[k, 0])]),
                    Sub(joint(int.Parse(LimbPairs[k, 3])), joint(int.Parse(LimbPairs[k, 2]))),
                };
            };
            // The rig's up, left and forward are found from its rest (hips to head, right to left
            // thigh), not assumed equal to SMPL's: one fixed rotation C carries source directions
            // into the rig's. C from frame 0's left upper arm and left thigh (a triad), then every
            // bone of every frame must be C times its source bone.
            var axes = Triad(dirs(0, 0), dirs(0, 4));
            double cAngle = Math.Acos(Math.Min(1, (axes[0][0] + axes[1][1] + axes[2][2] - 1) / 2)) * 180 / Math.PI;
            Check(cAngle < 5, "the rig's axes are the source's up to " + cAngle + " deg (a mirrored or turned rig is far off)");
            var worst = new double[LimbPairs.GetLength(0)];
            for (int f = 0; f < frames; f++)
                for (int k = 0; k < worst.Length; k++)
                {
                    var d = dirs(f, k);
                    worst[k] = Math.Max(worst[k], AngleDeg(d[0], MatVec(axes, d[1])));
                }
            Check(worst.Max() < 0.01, "bone directions within 0.01 deg of C times the source's over " + frames + " frames: " +
                  string.Join(", ", Enumerable.Range(0, worst.Length).Select(k => LimbPairs[k, 0] + " " + worst[k].ToString("G3"))));
            // Bones no source drives keep their rest translation: the root and the twist bone.
            bool rest = true;
            foreach (var name in new[] { "Root", "LeftUpperArmTwist", "LeftLowerArm" })
            {
                int b = rig.BoneIndex(name);
                for (int f = 0; f < frames; f++)
                    for (int c = 0; c < 3; c++)
                        rest &= Math.Abs(tr[(f * n + b) * 3 + c] - bones[b].Translation[c]) < 1e-6;
            }
            Check(rest, "undriven translations at rest");
            // Local rotations are unit quaternions with w >= 0.
            bool unit = true;
            for (int i = 0; i < rot.Length; i += 4)
            {
                double len = Math.Sqrt(rot[i] * rot[i] + rot[i + 1] * rot[i + 1] + rot[i + 2] * rot[i + 2] + rot[i + 3] * rot[i + 3]);
                unit &= Math.Abs(len - 1) < 1e-5 && rot[i + 3] >= 0;
            }
            Check(unit, "unit quaternions, w >= 0");

            // Feet IK moves the legs onto the source's placed ankles; the arms are untouched.
            using (var withFeet = UnityRetarget(rig, true))
            {
                var rotFeet = new float[rot.Length];
                withFeet.Read(s, 0, frames, rotFeet, null);
                int arm = rig.BoneIndex("LeftLowerArm"), shin = rig.BoneIndex("LeftLowerLeg");
                bool armSame = true;
                double shinDiff = 0;
                for (int f = 0; f < frames; f++)
                    for (int c = 0; c < 4; c++)
                    {
                        armSame &= rot[(f * n + arm) * 4 + c] == rotFeet[(f * n + arm) * 4 + c];
                        shinDiff = Math.Max(shinDiff, Math.Abs(rot[(f * n + shin) * 4 + c] - rotFeet[(f * n + shin) * 4 + c]));
                    }
                Check(armSame && shinDiff > 1e-4, "feet IK changes the legs (" + shinDiff + "), not the arms");
            }
        }
    }

    static void TestRetargetReads()
    {
        using (var rig = FlameRig.FromBones(UnityHumanoid(), FlameConvention.Unity))
        using (var r = UnityRetarget(rig, true))
        using (var s = MovingSession())
        {
            int n = r.BoneCount;
            var a = new float[RefFrames * n * 4];
            var b = new float[RefFrames * n * 4];
            var ta = new float[RefFrames * n * 3];
            r.Read(s, 0, RefFrames, a, ta);
            r.Read(s, 0, RefFrames, b, null);
            Check(BitEqual(a, b), "the same read twice: the same bits");
            // A range is the same frames' slice of the whole.
            var part = new float[4 * n * 4];
            r.Read(s, 5, 4, part, null);
            Check(BitEqual(part, a.Skip(5 * n * 4).Take(4 * n * 4).ToArray()), "frames 5..9 = the slice of all frames");
            // Pose(): frame 7 from the source's own world rotations and positions (glTF axes).
            var world = s.Read(FlameWhich.Sample, FlameLayout.GlobalQuatXyzw, FlameConvention.Gltf, 0);
            var pos = s.Read(FlameWhich.Sample, FlameLayout.GlobalPositions, FlameConvention.Gltf, 0);
            var one = new float[n * 4];
            var oneT = new float[n * 3];
            r.Pose(world.Skip(7 * 24 * 4).Take(24 * 4).ToArray(), pos.Skip(7 * 24 * 3).Take(24 * 3).ToArray(), one, oneT);
            double qd = 0, td = 0;
            for (int i = 0; i < n * 4; i++)
                qd = Math.Max(qd, Math.Abs(one[i] - a[7 * n * 4 + i]));
            for (int i = 0; i < n * 3; i++)
                td = Math.Max(td, Math.Abs(oneT[i] - ta[7 * n * 3 + i]));
            Check(qd < 1e-5 && td < 1e-5, "Pose(frame 7) = Read's frame 7: " + qd + ", " + td);
            // A cleanup's frame rate changes the frames: 24 at 20 fps are 35 at 30.
            var game = FlameCleanupParams.Default();
            game.fps = 30;
            Check(r.Frames(s, FlameWhich.Sample, 0, game) == 35, "35 frames at 30 fps");
            var cleaned = new float[35 * n * 4];
            Check(r.Read(s, 0, 35, cleaned, null, FlameWhich.Sample, 0, game) == 35, "cleaned read");
            // The estimate is another motion than the sample (after the last step they agree: reset).
            Check(!BitEqual(cleaned.Take(RefFrames * n * 4).ToArray(), a), "cleaned poses differ from raw ones");
            // The retarget holds its own copy of the rig: disposing the rig changes nothing.
            rig.Dispose();
            r.Read(s, 0, RefFrames, b, null);
            Check(BitEqual(a, b), "rig disposed: same poses");
        }
    }

    static void TestRetargetStream()
    {
        var p = FlameStreamParams.Default();
        p.chunk = 40; p.overlap = 10; p.steps = 2; p.lookahead = 100000; p.sampler = (int)FlameSampler.Ddim;
        using (var rig = FlameRig.FromBones(UnityHumanoid(), FlameConvention.Unity))
        using (var r = UnityRetarget(rig, true))
        using (var st = FlameStream.Create(model, p))
        {
            st.Push("a person walks forward.", 30);
            while (st.Pump(1).steps > 0) { }
            int n = r.BoneCount;
            var rot = new float[30 * n * 4];
            var tr = new float[30 * n * 3];
            r.ReadStream(st, 0, 30, rot, tr);
            // Each frame as Pose() puts the stream's own frame (glTF axes) on the rig.
            var world = st.Read(0, 30, FlameLayout.GlobalQuatXyzw, FlameConvention.Gltf);
            var pos = st.Read(0, 30, FlameLayout.GlobalPositions, FlameConvention.Gltf);
            var one = new float[n * 4];
            double d = 0;
            for (int f = 0; f < 30; f += 7)
            {
                r.Pose(world.Skip(f * 96).Take(96).ToArray(), pos.Skip(f * 72).Take(72).ToArray(), one, null);
                for (int i = 0; i < n * 4; i++)
                    d = Math.Max(d, Math.Abs(one[i] - rot[f * n * 4 + i]));
            }
            Check(d < 1e-5, "stream frames = Pose() of the stream's frames: " + d);
            Throws(FlameStatus.WrongState, "", () => r.ReadStream(st, 25, 10, rot, tr));
            Throws(FlameStatus.BufferTooSmall, "", () => r.ReadStream(st, 0, 30, new float[10], null));
        }
    }

    static void TestRigLoad()
    {
        // A BVH hierarchy (cm: the unit is guessed from its size), parents listed first.
        string bvh = "HIERARCHY\nROOT Hips\n{\n OFFSET 0 100 0\n CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation\n" +
                     " JOINT Spine\n {\n  OFFSET 0 10 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n" +
                     "  JOINT Head\n  {\n   OFFSET 0 50 0\n   CHANNELS 3 Zrotation Xrotation Yrotation\n   End Site\n   {\n    OFFSET 0 10 0\n   }\n  }\n }\n" +
                     " JOINT LeftUpLeg\n {\n  OFFSET 10 -5 0\n  CHANNELS 3 Zrotation Xrotation Yrotation\n   End Site\n   {\n    OFFSET 0 -40 0\n   }\n }\n}\n" +
                     "MOTION\nFrames: 1\nFrame Time: 0.05\n0 100 0 0 0 0 0 0 0 0 0 0 0 0 0\n";
        using (var rig = FlameRig.Load(Encoding.ASCII.GetBytes(bvh)))
        {
            Check(rig.BoneNames.SequenceEqual(new[] { "Hips", "Spine", "Head", "LeftUpLeg" }), "BVH bones: " + string.Join(",", rig.BoneNames));
            Check(rig.BoneParents.SequenceEqual(new[] { -1, 0, 1, 0 }), "BVH parents: " + string.Join(",", rig.BoneParents));
            // Too few bones for a body: the retarget names what is missing.
            Throws(FlameStatus.InvalidArgument, "leftUpperArm", () => FlameRetarget.Create(model, rig).Dispose());
            // A BVH file's axes are its own: no convention may be asked of it.
            var p = FlameRetargetParams.Default();
            p.convention = FlameConvention.Unity;
            Throws(FlameStatus.InvalidArgument, "BVH", () => FlameRetarget.Create(model, rig, null, p).Dispose());
        }
        Throws(FlameStatus.InvalidArgument, "neither glTF", () => FlameRig.Load(Encoding.ASCII.GetBytes("not a rig")));
        Throws(FlameStatus.InvalidArgument, "", () => FlameRig.Load(Encoding.ASCII.GetBytes("glTF\u0002\0\0\0"), FlameRigFormat.Gltf));
        Throws(FlameStatus.InvalidArgument, "unknown rig file kind 7", () => FlameRig.Load(Encoding.ASCII.GetBytes(bvh), 7));
        // The rig files of tests/fixtures/rigs, when present: each loads, maps itself and is driven.
        string dir = Path.Combine(RepoRoot(), "tests", "fixtures", "rigs");
        var files = Directory.Exists(dir) ? Directory.GetFiles(dir, "*.glb") : new string[0];
        Console.WriteLine("  rig fixtures: " + (files.Length == 0 ? "none in " + dir : string.Join(", ", files.Select(Path.GetFileName))));
        using (var s = MovingSession())
        {
            foreach (var file in files)
            {
                try
                {
                    using (var rig = FlameRig.Load(File.ReadAllBytes(file)))
                    using (var r = FlameRetarget.Create(model, rig))
                    {
                        var rot = new float[RefFrames * r.BoneCount * 4];
                        r.Read(s, 0, RefFrames, rot, null);
                        bool unit = true;
                        for (int i = 0; i < rot.Length; i += 4)
                            unit &= Math.Abs(rot[i] * rot[i] + rot[i + 1] * rot[i + 1] + rot[i + 2] * rot[i + 2] + rot[i + 3] * rot[i + 3] - 1) < 1e-4;
                        bool parentsFirst = rig.BoneParents.Select((p, k) => p < k).All(x => x);
                        Check(rig.BoneCount > 15 && r.BoneCount == rig.BoneCount && unit && parentsFirst,
                              Path.GetFileName(file) + ": " + rig.BoneCount + " bones, parents first, unit rotations");
                    }
                }
                catch (FlameException e)
                {
                    Check(false, Path.GetFileName(file) + ": " + e.Message);
                }
            }
        }
    }

    static void TestRetargetErrors()
    {
        var bones = UnityHumanoid();
        using (var rig = FlameRig.FromBones(bones, FlameConvention.Unity))
        using (var other = FlameRig.FromBones(bones, FlameConvention.Unity))
        using (var r = UnityRetarget(rig, true))
        {
            // NULL handles and pointers through the raw declarations.
            using (var none = new FlameRigHandle())
            {
                UIntPtr count;
                Throws(FlameStatus.InvalidArgument, "`rig` is NULL", () => FlameException.Check(FlameNative.flame_rig_bone_count(none, out count)));
                FlameBoneMapHandle mh;
                Throws(FlameStatus.InvalidArgument, "`rig` is NULL", () => FlameException.Check(FlameNative.flame_bone_map_auto(none, out mh)));
                var p = FlameRetargetParams.Default();
                FlameRetargetHandle rh;
                Throws(FlameStatus.InvalidArgument, "`rig` is NULL", () => FlameException.Check(FlameNative.flame_retarget_new(model.Handle, none, ref p, out rh)));
            }
            using (var none = new FlameRetargetHandle())
            using (var s = RefSession())
            {
                UIntPtr frames;
                Throws(FlameStatus.InvalidArgument, "`retarget` is NULL", () => FlameException.Check(
                    FlameNative.flame_retarget_read(none, s.Handle, 0, 0, IntPtr.Zero, UIntPtr.Zero, UIntPtr.Zero, null, UIntPtr.Zero, null, UIntPtr.Zero, out frames)));
                // Wrong order: a read before any step.
                Throws(FlameStatus.WrongState, "", () => r.Read(s, 0, 1, new float[r.BoneCount * 4], null));
                RunAll(s);
                int n = r.BoneCount;
                Throws(FlameStatus.BufferTooSmall, (RefFrames * n * 4) + " floats needed, 10 given", () => r.Read(s, 0, RefFrames, new float[10], null));
                Throws(FlameStatus.BufferTooSmall, "", () => r.Read(s, 0, 2, null, new float[2 * n * 3 - 1]));
                Throws(FlameStatus.InvalidArgument, "past the read's 24 frames", () => r.Read(s, 20, 5, null, null));
                Throws(FlameStatus.InvalidArgument, "`session` is NULL", () => FlameException.Check(
                    FlameNative.flame_retarget_read(r.Handle, new FlameSessionHandle(), 0, 0, IntPtr.Zero, UIntPtr.Zero, UIntPtr.Zero, null, UIntPtr.Zero, null, UIntPtr.Zero, out frames)));
                Throws(FlameStatus.InvalidArgument, "which", () => r.Read(s, 0, 1, null, null, (FlameWhich)5));
                ThrowsManaged<ArgumentOutOfRangeException>(() => r.Read(s, -1, 1, null, null));
                ThrowsManaged<ArgumentNullException>(() => r.Read(null, 0, 1, null, null));
            }
            // Pose(): lengths not the skeleton's, a zero quaternion, a non-finite position.
            var w = new float[24 * 4];
            var pos = new float[24 * 3];
            for (int j = 0; j < 24; j++)
                w[j * 4 + 3] = 1;
            r.Pose(w, pos, new float[r.BoneCount * 4], null);   // the rest pose is fine
            Throws(FlameStatus.InvalidArgument, "24 × 4", () => r.Pose(new float[22 * 4], pos, null, null));
            w[5 * 4 + 3] = 0;
            Throws(FlameStatus.InvalidArgument, "joint 5", () => r.Pose(w, pos, null, null));
            w[5 * 4 + 3] = 1;
            pos[3 * 3 + 1] = float.NaN;
            Throws(FlameStatus.InvalidArgument, "joint 3", () => r.Pose(w, pos, null, null));

            // Bone maps: a missing bone named (with the nearest names), an unknown key, bad JSON,
            // one bone for two keys, a map of another rig.
            Throws(FlameStatus.InvalidArgument, "LeftHnd", () => FlameBoneMap.FromJson(rig, "{\"leftHand\": \"LeftHnd\"}"));
            Throws(FlameStatus.InvalidArgument, "leftElbow", () => FlameBoneMap.FromJson(rig, "{\"leftElbow\": \"LeftLowerArm\"}"));
            Throws(FlameStatus.InvalidArgument, "", () => FlameBoneMap.FromJson(rig, "{\"hips\": "));
            Throws(FlameStatus.InvalidArgument, "Hips", () => FlameBoneMap.FromJson(rig, "{\"hips\": \"Hips\", \"spine\": \"Hips\"}"));
            using (var theirs = FlameBoneMap.Auto(other))
            {
                Throws(FlameStatus.InvalidArgument, "another rig", () => FlameRetarget.Create(model, rig, theirs).Dispose());
                Throws(FlameStatus.InvalidArgument, "another rig", () => FlameBoneMap.FromJson(rig, "{}", theirs).Dispose());
            }
            // A map leaving a required bone out: the retarget lists it.
            using (var noHand = FlameBoneMap.FromJson(rig, "{\"leftHand\": null}", FlameBoneMap.Auto(rig)))
                Throws(FlameStatus.InvalidArgument, "leftHand", () => FlameRetarget.Create(model, rig, noHand).Dispose());
            // Disposed handles are refused by the managed side, not passed on.
            var gone = FlameBoneMap.Auto(rig);
            gone.Dispose();
            ThrowsManaged<ObjectDisposedException>(() => gone.ToJson());
        }
        // Bones: a missing name, a repeated one, a parent out of range, a cycle, a zero
        // quaternion, a zero scale, the wrong number of values, no bones, the native convention.
        Func<Action<List<RigBone>>, Action> rigWith = change => () =>
        {
            var b = UnityHumanoid();
            change(b);
            FlameRig.FromBones(b, FlameConvention.Unity).Dispose();
        };
        Throws(FlameStatus.InvalidArgument, "bones[3].name", rigWith(b => b[3].Name = null));
        Throws(FlameStatus.InvalidArgument, "Spine", rigWith(b => b[4].Name = "Spine"));
        Throws(FlameStatus.InvalidArgument, "parent 99", rigWith(b => b[2].Parent = 99));
        Throws(FlameStatus.InvalidArgument, "", rigWith(b => { b[1].Parent = 2; b[2].Parent = 1; }));
        Throws(FlameStatus.InvalidArgument, "Chest", rigWith(b => b[3].Rotation = new float[4]));
        Throws(FlameStatus.InvalidArgument, "Neck", rigWith(b => b[4].Scale = new float[] { 1, 0, 1 }));
        ThrowsManaged<ArgumentException>(rigWith(b => b[4].Translation = new float[2]));
        ThrowsManaged<ArgumentNullException>(rigWith(b => b[4] = null));
        Throws(FlameStatus.InvalidArgument, "between 1 and 4096 bones, got 0", () => FlameRig.FromBones(new List<RigBone>(), FlameConvention.Unity));
        Throws(FlameStatus.InvalidArgument, "native", () => FlameRig.FromBones(UnityHumanoid(), FlameConvention.Native));
        // Names the automatic map cannot read: the retarget says which humanoid bones it lacks.
        using (var odd = FlameRig.FromBones(UnityHumanoid(name => "bone_" + name.Length + "_" + name.GetHashCode()), FlameConvention.Unity))
            Throws(FlameStatus.InvalidArgument, "hips", () => FlameRetarget.Create(model, odd).Dispose());
    }

    static void TestDisposedHandles()
    {
        var s = RefSession();
        s.Dispose();
        s.Dispose();   // twice is fine
        ThrowsManaged<ObjectDisposedException>(() => s.Step());
        var m = FlameModel.Load(modelPath);
        var s2 = m.NewSession(RefParams());
        m.Dispose();   // the session keeps the model alive natively
        s2.SetPrompt(RefPrompt);
        Check(BitEqual(RunAll(s2), reference), "session outlives its model's handle");
        s2.Dispose();
        ThrowsManaged<ObjectDisposedException>(() => m.NewSession());
    }
}

/// <summary>Reads and writes little-endian float32 C-order .npy files (format 1.0–3.0).</summary>
static class Npy
{
    public static float[] Read(string path, out int[] shape)
    {
        var bytes = File.ReadAllBytes(path);
        if (bytes.Length < 10 || bytes[0] != 0x93 || Encoding.ASCII.GetString(bytes, 1, 5) != "NUMPY")
            throw new InvalidDataException(path + " is not a .npy file");
        int major = bytes[6];
        int headerLen, start;
        if (major == 1)
        {
            headerLen = bytes[8] | (bytes[9] << 8);
            start = 10;
        }
        else
        {
            headerLen = BitConverter.ToInt32(bytes, 8);
            start = 12;
        }
        string header = Encoding.UTF8.GetString(bytes, start, headerLen);
        if (!header.Contains("'descr': '<f4'") || !header.Contains("'fortran_order': False"))
            throw new InvalidDataException(path + ": only little-endian float32 C-order arrays: " + header);
        int open = header.IndexOf('(', header.IndexOf("'shape'")), close = header.IndexOf(')', open);
        var dims = new List<int>();
        foreach (var part in header.Substring(open + 1, close - open - 1).Split(','))
            if (part.Trim().Length > 0)
                dims.Add(int.Parse(part.Trim()));
        shape = dims.ToArray();
        long count = 1;
        foreach (var d in shape)
            count *= d;
        int offset = start + headerLen;
        if (bytes.Length - offset != count * 4)
            throw new InvalidDataException(path + ": " + (bytes.Length - offset) + " data bytes for " + count + " floats");
        var data = new float[count];
        Buffer.BlockCopy(bytes, offset, data, 0, (int)count * 4);   // little-endian host assumed
        return data;
    }

    public static void Write(string path, float[] data, int rows, int cols)
    {
        WriteShape(path, data, rows + ", " + cols);
    }

    /// <summary>A float32 .npy of the given shape, written as numpy's tuple ("24, 22, 3").</summary>
    public static void WriteShape(string path, float[] data, string shape)
    {
        string header = "{'descr': '<f4', 'fortran_order': False, 'shape': (" + shape + "), }";
        int total = 10 + header.Length + 1;
        header += new string(' ', (64 - total % 64) % 64) + "\n";
        using (var f = new BinaryWriter(File.Create(path)))
        {
            f.Write((byte)0x93);
            f.Write(Encoding.ASCII.GetBytes("NUMPY"));
            f.Write((byte)1);
            f.Write((byte)0);
            f.Write((ushort)header.Length);
            f.Write(Encoding.ASCII.GetBytes(header));
            var raw = new byte[data.Length * 4];
            Buffer.BlockCopy(data, 0, raw, 0, raw.Length);
            f.Write(raw);
        }
    }
}

/// <summary>A small JSON reader for the tests (objects, arrays, strings, numbers as double,
/// true/false/null): enough to check libflame's glTF documents without a JSON library.</summary>
static class Json
{
    public static object Parse(string text)
    {
        int i = 0;
        var v = Value(text, ref i);
        Space(text, ref i);
        if (i != text.Length)
            throw new FormatException("trailing characters at " + i);
        return v;
    }

    static void Space(string s, ref int i)
    {
        while (i < s.Length && char.IsWhiteSpace(s[i]))
            i++;
    }

    static object Value(string s, ref int i)
    {
        Space(s, ref i);
        if (i >= s.Length)
            throw new FormatException("unexpected end");
        char c = s[i];
        if (c == '{')
        {
            var o = new Dictionary<string, object>();
            i++;
            Space(s, ref i);
            if (s[i] == '}') { i++; return o; }
            while (true)
            {
                Space(s, ref i);
                string key = Str(s, ref i);
                Space(s, ref i);
                Expect(s, ref i, ':');
                o[key] = Value(s, ref i);
                Space(s, ref i);
                if (s[i] == ',') { i++; continue; }
                Expect(s, ref i, '}');
                return o;
            }
        }
        if (c == '[')
        {
            var a = new List<object>();
            i++;
            Space(s, ref i);
            if (s[i] == ']') { i++; return a; }
            while (true)
            {
                a.Add(Value(s, ref i));
                Space(s, ref i);
                if (s[i] == ',') { i++; continue; }
                Expect(s, ref i, ']');
                return a;
            }
        }
        if (c == '"')
            return Str(s, ref i);
        foreach (var word in new[] { "true", "false", "null" })
            if (string.CompareOrdinal(s, i, word, 0, word.Length) == 0)
            {
                i += word.Length;
                return word == "null" ? null : (object)(word == "true");
            }
        int start = i;
        while (i < s.Length && "+-0123456789.eE".IndexOf(s[i]) >= 0)
            i++;
        if (i == start)
            throw new FormatException("unexpected '" + c + "' at " + i);
        return double.Parse(s.Substring(start, i - start), System.Globalization.CultureInfo.InvariantCulture);
    }

    static void Expect(string s, ref int i, char c)
    {
        if (i >= s.Length || s[i] != c)
            throw new FormatException("expected '" + c + "' at " + i);
        i++;
    }

    static string Str(string s, ref int i)
    {
        Expect(s, ref i, '"');
        var sb = new StringBuilder();
        while (s[i] != '"')
        {
            char c = s[i++];
            if (c != '\\')
            {
                sb.Append(c);
                continue;
            }
            char e = s[i++];
            switch (e)
            {
                case 'n': sb.Append('\n'); break;
                case 't': sb.Append('\t'); break;
                case 'r': sb.Append('\r'); break;
                case 'b': sb.Append('\b'); break;
                case 'f': sb.Append('\f'); break;
                case 'u': sb.Append((char)Convert.ToInt32(s.Substring(i, 4), 16)); i += 4; break;
                default: sb.Append(e); break;
            }
        }
        i++;
        return sb.ToString();
    }
}
