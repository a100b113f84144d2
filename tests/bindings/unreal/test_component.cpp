/*
 * The Unreal plugin's C++ (bindings/unreal/Flame) compiled against stand-ins for the engine
 * (ue_stubs/ue_stub.h) and run against the real libflame: FFlameModule and UFlameMotionComponent
 * driven the way the engine would (StartupModule, Generate, TickComponent every frame, EndPlay).
 *
 * usage: test_component MODEL REFERENCE_NPY LATENT_MODEL LATENT_REFERENCE_NPY
 * Reference: the `flame` CLI's features for the same settings (tests/bindings/run_unreal.sh), for
 * the FLAME fixture and for a latent one (MoLA, whose decoder decides the frame count).
 * Ends with one line "N passed, N failed"; the exit code is 1 when anything failed.
 */
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <climits>
#include <cstdlib>
#include <cstring>
#include <cstdio>
#include <fstream>
#include <iterator>
#include <string>
#include <thread>
#include <vector>

#include "FlameModule.h"
#include "FlameMotionComponent.h"
#include "flame.h"
#include "mannequin.h"

static int passed, failed;

#define CHECK(cond, ...)                                            \
    do {                                                            \
        if (cond) {                                                 \
            passed++;                                               \
        } else {                                                    \
            failed++;                                               \
            std::fprintf(stderr, "FAIL line %d: %s: ", __LINE__, #cond); \
            std::fprintf(stderr, __VA_ARGS__);                      \
            std::fprintf(stderr, "\n");                             \
        }                                                           \
    } while (0)

/* Ticks the component like the game thread would, until done() or the timeout. */
template <typename F> static bool TickUntil(UFlameMotionComponent& c, F done, double seconds = 30) {
    auto start = std::chrono::steady_clock::now();
    while (!done()) {
        c.TickComponent(0.016f, LEVELTICK_All, &c.PrimaryComponentTick);
        if (std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() > seconds) return false;
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    return true;
}

static bool WaitForThreads(double seconds = 10) {
    auto start = std::chrono::steady_clock::now();
    while (UeStubRunningThreads() > 0) {
        if (std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() > seconds) return false;
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    return true;
}

/* The float32 data of a .npy file: its last frames × dim × 4 bytes. */
static std::vector<float> NpyData(const char* path, size_t count) {
    std::ifstream f(path, std::ios::binary);
    std::vector<char> bytes((std::istreambuf_iterator<char>(f)), std::istreambuf_iterator<char>());
    std::vector<float> data(count);
    if (bytes.size() >= count * 4) std::memcpy(data.data(), bytes.data() + bytes.size() - count * 4, count * 4);
    return data;
}

/* The row count of a 2-D .npy file's shape (0 when there is none). */
static int NpyRows(const char* path) {
    std::ifstream f(path, std::ios::binary);
    std::string header(256, '\0');
    f.read(&header[0], (std::streamsize)header.size());
    const size_t at = header.find("'shape': (");
    return at == std::string::npos ? 0 : std::atoi(header.c_str() + at + 10);
}

/* flame_session_write_gltf on a session of the component's settings (Configure's, with the
 * given frames and steps, and Configure's cleanup: the defaults with feet and floor off),
 * straight through flame.h: what ExportGltf must return. */
static std::vector<uint8_t> DirectGltf(const char* model, int frames, int steps, int container, uint32_t flags) {
    std::vector<uint8_t> out;
    FlameModel* m = nullptr;
    if (flame_model_load(model, nullptr, &m) != FLAME_STATUS_OK) return out;
    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = (uint32_t)frames;
    p.steps = (uint32_t)steps;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.seed = 3;
    p.threads = 1;
    FlameSession* s = nullptr;
    if (flame_session_new(m, &p, &s) == FLAME_STATUS_OK &&
        flame_session_set_prompt(s, "a person walks forward and waves.") == FLAME_STATUS_OK) {
        uint32_t left = 1;
        while (left > 0 && flame_session_step(s, &left) == FLAME_STATUS_OK) {
        }
        FlameGltfParams g;
        flame_gltf_params_default(&g);
        g.container = container;
        g.flags = flags;
        FlameCleanupParams cleanup;
        flame_cleanup_params_default(&cleanup);
        cleanup.feet = FLAME_FEET_OFF;
        cleanup.ground = 0;
        g.cleanup = &cleanup;
        size_t n = 0;
        if (left == 0 && flame_session_write_gltf(s, FLAME_WHICH_SAMPLE, &g, nullptr, 0, &n) == FLAME_STATUS_OK) {
            out.resize(n);
            if (flame_session_write_gltf(s, FLAME_WHICH_SAMPLE, &g, out.data(), n, &n) != FLAME_STATUS_OK) out.clear();
        }
    }
    flame_session_free(s);
    flame_model_free(m);
    return out;
}

static bool SameBytes(const TArray<uint8>& a, const std::vector<uint8_t>& b) {
    return !b.empty() && a.Num() == (int32)b.size() && std::memcmp(a.GetData(), b.data(), b.size()) == 0;
}

static void Configure(UFlameMotionComponent& c, const char* model, int frames, int steps, bool ddim,
                      int layout = 0 /* FLAME_LAYOUT_FEATURES */, int convention = 0) {
    c.Layout = layout;
    c.Convention = convention;
    // Absolute: a relative ModelPath is taken relative to the project's Content directory.
    char* full = realpath(model, nullptr);
    c.ModelPath = FString(UTF8_TO_TCHAR(full ? full : model));
    std::free(full);
    c.Prompt = FString(TEXT("a person walks forward and waves."));
    c.Frames = frames;
    c.Steps = steps;
    c.bUseDdim = ddim;
    c.Seed = 3;
    c.Threads = 1;
    // Cleanup off (its defaults lock the feet and ground the clip): the raw poses, which the
    // tests compare with the CLI and with plain flame_session_read. The cleanup's own test
    // turns it on.
    c.bLockFeet = false;
    c.bGround = false;
}

/* A final sample of Configure's settings (frames, steps; DDIM, seed 3, one thread), read
 * through flame.h with flame_session_read_cleaned (cleanup NULL: raw), or exported to GLB with
 * that cleanup when layout is -1: what the component must publish. */
static std::vector<float> DirectCleaned(const char* model, int frames, int steps, const FlameCleanupParams* cleanup,
                                        int layout, int convention, std::vector<uint8_t>* glb = nullptr,
                                        bool looped = false) {
    std::vector<float> out;
    FlameModel* m = nullptr;
    if (flame_model_load(model, nullptr, &m) != FLAME_STATUS_OK) return out;
    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = (uint32_t)frames;
    p.steps = (uint32_t)steps;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.seed = 3;
    p.threads = 1;
    p.looped = looped ? 1 : 0;
    FlameSession* s = nullptr;
    if (flame_session_new(m, &p, &s) == FLAME_STATUS_OK &&
        flame_session_set_prompt(s, "a person walks forward and waves.") == FLAME_STATUS_OK) {
        uint32_t left = 1;
        while (left > 0 && flame_session_step(s, &left) == FLAME_STATUS_OK) {
        }
        size_t n = 0;
        if (left == 0 && glb != nullptr) {
            FlameGltfParams g;
            flame_gltf_params_default(&g);
            g.cleanup = cleanup;
            if (flame_session_write_gltf(s, FLAME_WHICH_SAMPLE, &g, nullptr, 0, &n) == FLAME_STATUS_OK) {
                glb->resize(n);
                if (flame_session_write_gltf(s, FLAME_WHICH_SAMPLE, &g, glb->data(), n, &n) != FLAME_STATUS_OK) glb->clear();
            }
        } else if (left == 0 &&
                   flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, layout, convention, 0, cleanup, nullptr, 0, &n) ==
                       FLAME_STATUS_OK) {
            out.resize(n);
            if (flame_session_read_cleaned(s, FLAME_WHICH_SAMPLE, layout, convention, 0, cleanup, out.data(), n, &n) !=
                FLAME_STATUS_OK)
                out.clear();
        }
    }
    flame_session_free(s);
    flame_model_free(m);
    return out;
}

static bool SameFloats(const TArray<float>& a, const std::vector<float>& b) {
    return !b.empty() && a.Num() == (int32)b.size() && std::memcmp(a.GetData(), b.data(), b.size() * 4) == 0;
}

/* The retarget of a final sample of Configure's settings onto asset's skeleton, straight
 * through flame.h (flame_rig_from_bones in FLAME_CONVENTION_UNREAL, the automatic map, feet
 * IK on; flame_retarget_read with cleanup): what the component must publish. */
static bool DirectRetarget(const char* model, int frames, int steps, const USkinnedAsset& asset, const FlameCleanupParams* cleanup,
                           std::vector<float>& rot, std::vector<float>& tr) {
    FlameModel* m = nullptr;
    FlameRetarget* r = nullptr;
    FlameSession* s = nullptr;
    const size_t bones = (size_t)asset.GetRefSkeleton().GetNum();
    bool ok = flame_model_load(model, nullptr, &m) == FLAME_STATUS_OK && (r = SkeletonRetarget(m, asset)) != nullptr;
    FlameSessionParams p;
    flame_session_params_default(&p);
    p.frames = (uint32_t)frames;
    p.steps = (uint32_t)steps;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.seed = 3;
    p.threads = 1;
    ok = ok && flame_session_new(m, &p, &s) == FLAME_STATUS_OK &&
         flame_session_set_prompt(s, "a person walks forward and waves.") == FLAME_STATUS_OK;
    uint32_t left = 1;
    while (ok && left > 0) ok = flame_session_step(s, &left) == FLAME_STATUS_OK;
    size_t n = 0;
    ok = ok && flame_retarget_read(r, s, FLAME_WHICH_SAMPLE, 0, cleanup, 0, 0, nullptr, 0, nullptr, 0, &n) == FLAME_STATUS_OK;
    if (ok) {
        rot.assign(n * bones * 4, 0.f);
        tr.assign(n * bones * 3, 0.f);
        ok = flame_retarget_read(r, s, FLAME_WHICH_SAMPLE, 0, cleanup, 0, n, rot.data(), rot.size(), tr.data(), tr.size(), &n) ==
             FLAME_STATUS_OK;
    }
    flame_session_free(s);
    flame_retarget_free(r);
    flame_model_free(m);
    return ok;
}

/* Whether mesh's bone-space transforms hold frame f of the component's retargeted poses. */
static bool MeshHolds(const UPoseableMeshComponent& mesh, const UFlameMotionComponent& c, int f) {
    const int n = c.RigBoneNames.Num();
    bool same = mesh.BoneSpaceTransforms.Num() == n && n > 0;
    for (int b = 0; same && b < n; b++) {
        const FTransform& t = mesh.BoneSpaceTransforms[b];
        const FQuat q = c.GetBoneRotation(f, b);
        const FVector v = c.GetBoneTranslation(f, b);
        same = t.Rotation.X == q.X && t.Rotation.Y == q.Y && t.Rotation.Z == q.Z && t.Rotation.W == q.W &&
               t.Translation.X == v.X && t.Translation.Y == v.Y && t.Translation.Z == v.Z && t.Scale3D.X == 1;
    }
    return same;
}

int main(int argc, char** argv) {
    if (argc != 5) {
        std::fprintf(stderr, "usage: test_component MODEL REFERENCE_NPY LATENT_MODEL LATENT_REFERENCE_NPY\n");
        return 2;
    }
    const int Frames = 24, Dim = 147;
    std::vector<float> reference = NpyData(argv[2], (size_t)Frames * Dim);

    FFlameModule& module = FFlameModule::Get();
    module.StartupModule();
    CHECK(module.IsAvailable(), "module unavailable");

    {   // The CLI's settings: the final Pose is its output, bit for bit.
        UFlameMotionComponent c;
        CHECK(c.PrimaryComponentTick.bCanEverTick, "ticks");
        Configure(c, argv[1], Frames, 10, true);
        int progressCalls = 0, finishedCalls = 0;
        bool succeeded = false;
        c.OnProgress.AddLambda([&](int32, int32) { progressCalls++; });
        c.OnFinished.AddLambda([&](bool ok) { finishedCalls++; succeeded = ok; });
        CHECK(c.Generate(), "Generate: %s", c.LastError.Utf8().c_str());
        CHECK(!c.Generate(), "a second Generate while running");
        CHECK(c.LastError.Utf8() == "a generation is already running", "%s", c.LastError.Utf8().c_str());
        CHECK(TickUntil(c, [&] { return finishedCalls > 0; }), "finished in time");
        CHECK(succeeded && c.LastError.IsEmpty(), "succeeded: %s", c.LastError.Utf8().c_str());
        CHECK(!c.IsGenerating(), "idle after finishing");
        CHECK(progressCalls >= 1 && progressCalls <= 10, "progress calls %d", progressCalls);
        CHECK(c.StepsDone == 10 && c.StepsTotal == 10, "steps %d/%d", c.StepsDone, c.StepsTotal);
        CHECK(c.GetFrameCount() == Frames && c.GetValuesPerFrame() == Dim, "%d x %d", c.GetFrameCount(), c.GetValuesPerFrame());
        CHECK(c.Pose.Num() == Frames * Dim && std::memcmp(c.Pose.GetData(), reference.data(), reference.size() * 4) == 0,
              "Pose = the CLI's features");
        TArray<float> row = c.GetFramePose(1);
        CHECK(row.Num() == Dim && std::memcmp(row.GetData(), reference.data() + Dim, Dim * 4) == 0, "GetFramePose(1)");
        CHECK(c.GetFramePose(Frames).Num() == 0 && c.GetFramePose(-1).Num() == 0, "out-of-range frames");
        CHECK(c.JointNames.Num() == c.JointParents.Num(), "joint arrays");

        // Again, with the cached model: the same motion.
        c.Pose.Reset();
        CHECK(c.Generate(), "Generate again");
        CHECK(TickUntil(c, [&] { return finishedCalls > 1; }), "finished again");
        CHECK(succeeded && std::memcmp(c.Pose.GetData(), reference.data(), reference.size() * 4) == 0, "same again");
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // ExportGltf: the last successful generation's final motion as glTF, byte for byte what
        // flame_session_write_gltf gives for a session of the same settings, read with the
        // component's ReadFlags; nothing to export before a generation, while one runs, after a
        // failed one and after EndPlay.
        UFlameMotionComponent c;
        Configure(c, argv[1], Frames, 10, true, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL);
        c.ReadFlags = FLAME_READ_SMOOTH;
        TArray<uint8> bytes;
        bytes.Add(7);
        CHECK(!c.ExportGltf(true, bytes) && bytes.Num() == 0, "nothing to export before Generate");
        CHECK(c.LastError.Utf8() == "ExportGltf: no finished generation to export", "%s", c.LastError.Utf8().c_str());
        int finishedCalls = 0;
        bool succeeded = false;
        c.OnFinished.AddLambda([&](bool ok) { finishedCalls++; succeeded = ok; });
        CHECK(c.Generate(), "Generate: %s", c.LastError.Utf8().c_str());
        CHECK(!c.ExportGltf(true, bytes) && bytes.Num() == 0 &&
                  c.LastError.Utf8().find("ExportGltf: a generation is running") == 0,
              "nothing to export while generating: %s", c.LastError.Utf8().c_str());
        CHECK(TickUntil(c, [&] { return finishedCalls > 0; }), "finished");
        CHECK(succeeded && c.LastError.IsEmpty(), "succeeded: %s", c.LastError.Utf8().c_str());

        CHECK(c.ExportGltf(true, bytes), "ExportGltf(true): %s", c.LastError.Utf8().c_str());
        auto u32 = [&](int at) {
            return (uint32_t)bytes[at] | (uint32_t)bytes[at + 1] << 8 | (uint32_t)bytes[at + 2] << 16 |
                   (uint32_t)bytes[at + 3] << 24;
        };
        const bool header = bytes.Num() > 28 && std::memcmp(bytes.GetData(), "glTF", 4) == 0 && u32(4) == 2 &&
                            u32(8) == (uint32_t)bytes.Num() && std::memcmp(bytes.GetData() + 16, "JSON", 4) == 0 &&
                            20 + u32(12) <= (uint32_t)bytes.Num();
        CHECK(header, "GLB header: magic, version 2, length %d", bytes.Num());
        if (header) {
            const std::string json((const char*)bytes.GetData() + 20, u32(12));
            bool named = c.JointNames.Num() == 24;
            for (int32 j = 0; j < c.JointNames.Num(); j++)
                named = named && json.find("\"name\":\"" + c.JointNames[j].Utf8() + "\"") != std::string::npos;
            CHECK(named, "the JSON chunk names the %d joints", c.JointNames.Num());
            CHECK(json.find("\"prompt\":\"a person walks forward and waves.\"") != std::string::npos &&
                      json.find("\"seed\":3") != std::string::npos,
                  "asset.extras: prompt and seed");
        }
        const std::vector<uint8_t> glb = DirectGltf(argv[1], Frames, 10, FLAME_GLTF_CONTAINER_GLB, FLAME_READ_SMOOTH);
        CHECK(SameBytes(bytes, glb), "ExportGltf(true) = flame_session_write_gltf (%d vs %d bytes)", bytes.Num(), (int)glb.size());
        CHECK(glb != DirectGltf(argv[1], Frames, 10, FLAME_GLTF_CONTAINER_GLB, 0), "ReadFlags reach the export");
        TArray<uint8> text;
        CHECK(c.ExportGltf(false, text) && text.Num() > 0 && text[0] == '{', "ExportGltf(false): JSON glTF");
        CHECK(SameBytes(text, DirectGltf(argv[1], Frames, 10, FLAME_GLTF_CONTAINER_GLTF, FLAME_READ_SMOOTH)),
              "ExportGltf(false) = flame_session_write_gltf");
        CHECK(c.ExportGltf(true, bytes) && SameBytes(bytes, glb), "export again: the same bytes");

        // A failed generation leaves nothing to export (the previous motion is gone with Generate).
        c.Frames = 471;
        CHECK(c.Generate(), "Generate (bad frames)");
        CHECK(TickUntil(c, [&] { return finishedCalls > 1; }), "finished (bad frames)");
        CHECK(!succeeded, "failed");
        CHECK(!c.ExportGltf(true, bytes) && bytes.Num() == 0 &&
                  c.LastError.Utf8() == "ExportGltf: no finished generation to export",
              "nothing after a failed generation: %s", c.LastError.Utf8().c_str());
        c.Frames = Frames;
        CHECK(c.Generate(), "Generate again");
        CHECK(TickUntil(c, [&] { return finishedCalls > 2; }), "finished again");
        CHECK(succeeded && c.ExportGltf(true, bytes) && SameBytes(bytes, glb), "exportable again");
        c.EndPlay(EEndPlayReason::Destroyed);
        CHECK(!c.ExportGltf(true, bytes) && bytes.Num() == 0, "nothing after EndPlay");
    }
    CHECK(WaitForThreads(), "workers exited");
    CHECK(FFlameModule::ActiveWorkers.GetValue() == 0, "no session kept once the component is gone: %d",
          FFlameModule::ActiveWorkers.GetValue());

    {   // Respacing "10" keeps the 10 steps the section rule gives Steps = 10: the CLI's bits.
        // A string no stride can space fails the generation with libflame's message.
        UFlameMotionComponent c;
        Configure(c, argv[1], Frames, 0, true);
        CHECK(c.Respacing.IsEmpty(), "no respacing by default");
        c.Respacing = FString(TEXT("10"));
        bool finished = false, succeeded = false;
        c.OnFinished.AddLambda([&](bool ok) { finished = true; succeeded = ok; });
        CHECK(c.Generate(), "Generate with respacing");
        CHECK(TickUntil(c, [&] { return finished; }), "finished");
        CHECK(succeeded && c.StepsTotal == 10, "succeeded: %s (%d steps)", c.LastError.Utf8().c_str(), c.StepsTotal);
        CHECK(std::memcmp(c.Pose.GetData(), reference.data(), reference.size() * 4) == 0, "respacing 10 = steps 10");
        finished = false;
        c.Respacing = FString(TEXT("ddim999"));
        CHECK(c.Generate(), "Generate with a bad respacing");
        CHECK(TickUntil(c, [&] { return finished; }), "finished");
        CHECK(!succeeded && c.LastError.Utf8().find("cannot create exactly 999 steps") != std::string::npos,
              "%s", c.LastError.Utf8().c_str());
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // The defaults: local quaternions x, y, z, w and root locations in Unreal's convention.
        UFlameMotionComponent defaults;
        CHECK(defaults.Layout == FLAME_LAYOUT_LOCAL_QUAT_XYZW && defaults.Convention == FLAME_CONVENTION_UNREAL, "defaults");
        // The cleanup's: libflame's game-ready defaults (feet locked, on the ground, root motion
        // kept, the model's frame rate).
        FlameCleanupParams game;
        flame_cleanup_params_default(&game);
        CHECK(defaults.bLockFeet == (game.feet == 1) && defaults.bGround == (game.ground == 1) &&
                  defaults.FrameRate == game.fps && (int)defaults.RootMotion == game.root_motion &&
                  defaults.bRemoveYaw == (game.remove_yaw == 1) && defaults.RootMotion == EFlameRootMotion::Keep,
              "cleanup defaults = flame_cleanup_params_default");
        UFlameMotionComponent c;
        // 200 steps: OnProgress reports the latest pose at a tick, so a fast machine can finish
        // a short generation between two ticks (10 steps once did, and no mid-run pose came).
        Configure(c, argv[1], Frames, 200, true, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL);
        // The tiny model's clean motion saturates at ±1, where some 6D rotations are degenerate:
        // check unit quaternions on the first published pose before the last step, a (generic)
        // noisy sample.
        c.bPreviewEstimate = false;
        bool finished = false, succeeded = false, checkedFirst = false;
        c.OnProgress.AddLambda([&](int32 done, int32 total) {
            if (done >= total || checkedFirst) return;
            checkedFirst = true;
            const int joints = c.GetValuesPerFrame() / 4;
            bool unit = joints == 24;
            for (int f = 0; f < Frames; f++)
                for (int j = 0; j < joints; j++) {
                    FQuat q = c.GetJointRotation(f, j);
                    unit = unit && std::abs(q.X * q.X + q.Y * q.Y + q.Z * q.Z + q.W * q.W - 1) < 1e-4;
                }
            CHECK(unit, "unit quaternions for 24 joints");
        });
        c.OnFinished.AddLambda([&](bool ok) { finished = true; succeeded = ok; });
        CHECK(c.Generate(), "Generate");
        CHECK(TickUntil(c, [&] { return finished; }), "finished");
        CHECK(succeeded && checkedFirst, "succeeded: %s", c.LastError.Utf8().c_str());
        CHECK(c.Pose.Num() == Frames * 24 * 4 && c.RootLocations.Num() == Frames * 3, "%d %d", c.Pose.Num(), c.RootLocations.Num());
        FQuat q = c.GetJointRotation(3, 5);
        const float* raw = c.Pose.GetData() + (3 * 24 + 5) * 4;
        CHECK(q.X == raw[0] && q.Y == raw[1] && q.Z == raw[2] && q.W == raw[3], "GetJointRotation(3, 5) reads x, y, z, w");
        FVector p = c.GetRootLocation(3);
        CHECK(p.X == c.RootLocations[9] && p.Z == c.RootLocations[11], "GetRootLocation(3)");
        FQuat outside = c.GetJointRotation(Frames, 0);
        CHECK(outside.W == 1 && outside.X == 0, "identity out of range");
        CHECK(c.GetRootLocation(-1).X == 0, "zero out of range");
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // A loop (bLoop): the cycle's 40 frames, what a looped session reads with the same
        // cleanup, bit for bit; a loop the model cannot make fails with the library's message.
        const int LF = 40, J = 24;
        UFlameMotionComponent c;
        Configure(c, argv[1], LF, 4, true, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL);
        c.bLoop = true;
        c.bLockFeet = true;
        c.bGround = true;
        int finishedCalls = 0;
        bool succeeded = false;
        c.OnFinished.AddLambda([&](bool ok) { finishedCalls++; succeeded = ok; });
        CHECK(c.Generate(), "Generate (loop): %s", c.LastError.Utf8().c_str());
        CHECK(TickUntil(c, [&] { return finishedCalls > 0; }), "finished (loop)");
        CHECK(succeeded && c.GetFrameCount() == LF && c.Pose.Num() == LF * J * 4,
              "loop: %d frames, %d values: %s", c.GetFrameCount(), c.Pose.Num(), c.LastError.Utf8().c_str());
        FlameCleanupParams game;
        flame_cleanup_params_default(&game);
        CHECK(SameFloats(c.Pose, DirectCleaned(argv[1], LF, 4, &game, FLAME_LAYOUT_LOCAL_QUAT_XYZW,
                                               FLAME_CONVENTION_UNREAL, nullptr, true)),
              "loop: Pose = a looped session's flame_session_read_cleaned");
        CHECK(!SameFloats(c.Pose, DirectCleaned(argv[1], LF, 4, &game, FLAME_LAYOUT_LOCAL_QUAT_XYZW,
                                                FLAME_CONVENTION_UNREAL)),
              "loop: not the plain generation's poses");
        c.Frames = 12;
        CHECK(c.Generate(), "Generate (loop too short) starts");
        CHECK(TickUntil(c, [&] { return finishedCalls > 1; }), "finished (loop too short)");
        CHECK(!succeeded && c.LastError.Utf8().find("at least 40 frames") != std::string::npos,
              "loop too short: %s", c.LastError.Utf8().c_str());
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // Cleanup: what the component publishes is flame_session_read_cleaned with its settings,
        // bit for bit. 30 fps from 40 frames at 20: 59 frames; separate root motion: the root
        // bone on the ground (Unreal: Z up), pelvis + root bone = the raw pelvis at the common
        // times (frame 3k at 30 fps = frame 2k at 20); the export has the "root" node.
        const int CF = 40, CF30 = 59, J = 24;
        UFlameMotionComponent c;
        Configure(c, argv[1], CF, 10, true, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL);
        c.FrameRate = 30.f;
        c.RootMotion = EFlameRootMotion::Separate;
        int finishedCalls = 0;
        bool succeeded = false;
        c.OnFinished.AddLambda([&](bool ok) { finishedCalls++; succeeded = ok; });
        CHECK(c.Generate(), "Generate (cleanup): %s", c.LastError.Utf8().c_str());
        CHECK(TickUntil(c, [&] { return finishedCalls > 0; }), "finished (cleanup)");
        CHECK(succeeded, "succeeded: %s", c.LastError.Utf8().c_str());
        CHECK(c.GetFrameCount() == CF30 && c.Pose.Num() == CF30 * J * 4 && c.RootLocations.Num() == CF30 * 3 &&
                  c.RootBoneLocations.Num() == CF30 * 3 && c.PoseFrameRate == 30.f,
              "59 frames at 30 fps: %d frames, %d values, %d root bone values, %g fps", c.GetFrameCount(), c.Pose.Num(),
              c.RootBoneLocations.Num(), c.PoseFrameRate);
        FlameCleanupParams clean;
        flame_cleanup_params_default(&clean);
        clean.feet = 0;
        clean.ground = 0;
        clean.fps = 30.f;
        clean.root_motion = 2;
        CHECK(SameFloats(c.Pose, DirectCleaned(argv[1], CF, 10, &clean, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL)),
              "Pose = flame_session_read_cleaned");
        CHECK(SameFloats(c.RootBoneLocations, DirectCleaned(argv[1], CF, 10, &clean, FLAME_LAYOUT_ROOT_BONE, FLAME_CONVENTION_UNREAL)),
              "RootBoneLocations = flame_session_read_cleaned(ROOT_BONE)");
        const std::vector<float> raw = DirectCleaned(argv[1], CF, 10, nullptr, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_UNREAL);
        bool grounded = c.RootBoneLocations.Num() == CF30 * 3 && raw.size() == (size_t)CF * 3, sums = grounded;
        double moved = 0;
        for (int f = 0; grounded && f < CF30; f++) {
            FVector b = c.GetRootBoneLocation(f);
            grounded = b.Z == 0;
            moved = std::max(moved, std::abs((double)b.X) + std::abs((double)b.Y));
            if (f % 3 == 0) {
                FVector pelvis = c.GetRootLocation(f);
                const float* r = raw.data() + (f / 3) * 2 * 3;
                // Centimetres: 1e-3 cm = 10 µm of float rounding.
                sums = sums && std::abs(b.X + pelvis.X - r[0]) < 1e-3 && std::abs(b.Y + pelvis.Y - r[1]) < 1e-3;
            }
        }
        CHECK(grounded, "the root bone at height 0");
        CHECK(moved > 0.1, "the root bone travels (%g cm)", moved);
        CHECK(sums, "pelvis + root bone = the raw pelvis at the common frames");
        CHECK(c.GetRootBoneLocation(CF30).X == 0 && c.GetRootBoneLocation(-1).X == 0, "zero out of range");
        TArray<uint8> bytes;
        std::vector<uint8_t> glb;
        DirectCleaned(argv[1], CF, 10, &clean, -1, 0, &glb);
        CHECK(c.ExportGltf(true, bytes) && SameBytes(bytes, glb), "ExportGltf = flame_session_write_gltf with the cleanup");
        const std::string text(bytes.GetData(), bytes.GetData() + bytes.Num());
        CHECK(text.find("\"name\":\"root\"") != std::string::npos, "the export has the root node");

        // Keep root motion: no root bone track. The defaults (feet locked, ground) give what
        // flame_session_read_cleaned gives with flame_cleanup_params_default.
        c.RootMotion = EFlameRootMotion::Keep;
        c.FrameRate = 0.f;
        c.bLockFeet = true;
        c.bGround = true;
        CHECK(c.Generate(), "Generate (game defaults)");
        CHECK(TickUntil(c, [&] { return finishedCalls > 1; }), "finished (game defaults)");
        flame_cleanup_params_default(&clean);
        CHECK(succeeded && c.GetFrameCount() == CF && c.RootBoneLocations.Num() == 0 && c.PoseFrameRate == 20.f,
              "keep: %d frames, %d root bone values", c.GetFrameCount(), c.RootBoneLocations.Num());
        CHECK(SameFloats(c.Pose, DirectCleaned(argv[1], CF, 10, &clean, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL)),
              "feet locked, on the ground: Pose = flame_session_read_cleaned");
        CHECK(!SameFloats(c.RootLocations, DirectCleaned(argv[1], CF, 10, nullptr, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_UNREAL)),
              "the cleanup changed the root locations (the ground moved them)");

        // A bad frame rate fails the generation with libflame's message naming it.
        c.FrameRate = 1000.f;
        CHECK(c.Generate(), "Generate (bad frame rate)");
        CHECK(TickUntil(c, [&] { return finishedCalls > 2; }), "finished (bad frame rate)");
        CHECK(!succeeded && c.LastError.Utf8().find("FLAME_STATUS_INVALID_ARGUMENT") == 0 &&
                  c.LastError.Utf8().find("got 1000") != std::string::npos,
              "%s", c.LastError.Utf8().c_str());

        // Layout 0: the raw features, never post-processed, and the root locations stay raw.
        c.Layout = FLAME_LAYOUT_FEATURES;
        c.FrameRate = 30.f;
        CHECK(c.Generate(), "Generate (features)");
        CHECK(TickUntil(c, [&] { return finishedCalls > 3; }), "finished (features)");
        CHECK(succeeded && c.GetFrameCount() == CF && c.Pose.Num() == CF * Dim && c.RootLocations.Num() == CF * 3,
              "features: %d frames", c.GetFrameCount());
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // Cancel from the game thread: OnFinished(false) with libflame's CANCELLED.
        UFlameMotionComponent c;
        Configure(c, argv[1], 470, 1000, false);
        bool finished = false, succeeded = true;
        c.OnFinished.AddLambda([&](bool ok) { finished = true; succeeded = ok; });
        CHECK(c.Generate(), "Generate long");
        CHECK(TickUntil(c, [&] { return c.StepsDone >= 2; }), "stepping");
        auto t0 = std::chrono::steady_clock::now();
        c.Cancel();
        CHECK(TickUntil(c, [&] { return finished; }, 5), "finished after cancel");
        double took = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        CHECK(!succeeded && c.LastError.Utf8().find("FLAME_STATUS_CANCELLED") == 0, "%s", c.LastError.Utf8().c_str());
        CHECK(took < 2, "cancel took %.3f s", took);
        CHECK(c.StepsDone < 1000, "stopped early at %d", c.StepsDone);
    }
    CHECK(WaitForThreads(), "workers exited after cancel");

    {   // EndPlay mid-generation returns at once; the worker frees everything by itself.
        UFlameMotionComponent* c = new UFlameMotionComponent;
        Configure(*c, argv[1], 470, 1000, false);
        CHECK(c->Generate(), "Generate long");
        CHECK(TickUntil(*c, [&] { return c->StepsDone >= 1; }), "stepping");
        auto t0 = std::chrono::steady_clock::now();
        c->EndPlay(EEndPlayReason::Destroyed);
        delete c;  // the component goes away before its worker
        double took = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
        CHECK(took < 0.05, "EndPlay took %.3f s", took);
        CHECK(WaitForThreads(), "worker exited after EndPlay");
        CHECK(FFlameModule::ActiveWorkers.GetValue() == 0, "active workers %d", FFlameModule::ActiveWorkers.GetValue());
    }

    {   // Editing: a task mask over EditReference; with paste on the kept frames are its bits.
        UFlameMotionComponent c;
        Configure(c, argv[1], Frames, 10, true);
        CHECK(c.EditTask == -1 && c.EditMethod == 0 && c.bEditPaste && c.EditSeamFrames == 4 && c.EditTill == 0.2f,
              "editing defaults");
        std::vector<float> edit((size_t)Frames * Dim);
        for (size_t i = 0; i < edit.size(); i++) edit[i] = 0.5f * std::sin(0.01f * (float)i) + 0.25f;
        c.EditReference.Append(edit.data(), (int32)edit.size());
        c.EditTask = FLAME_EDIT_TASK_PREDICT;
        int finishedCalls = 0;
        bool succeeded = false;
        c.OnFinished.AddLambda([&](bool ok) { finishedCalls++; succeeded = ok; });
        auto generate = [&](const char* what) {
            const int before = finishedCalls;
            CHECK(c.Generate(), "Generate (%s): %s", what, c.LastError.Utf8().c_str());
            CHECK(TickUntil(c, [&] { return finishedCalls > before; }), "finished (%s)", what);
        };
        auto sameFrames = [&](int f0, int f1) {
            return c.Pose.Num() == Frames * Dim &&
                   std::memcmp(c.Pose.GetData() + f0 * Dim, edit.data() + f0 * Dim, (size_t)(f1 - f0) * Dim * 4) == 0;
        };
        generate("predict");
        CHECK(succeeded && c.LastError.IsEmpty(), "edit succeeded: %s", c.LastError.Utf8().c_str());
        CHECK(sameFrames(0, Frames / 4), "the kept quarter is the reference's");
        CHECK(!sameFrames(Frames / 4, Frames), "the rest is generated");

        c.bEditPaste = false;
        generate("paste off");
        CHECK(succeeded && !sameFrames(0, Frames / 4), "paste off: the kept frames are only close");

        c.bEditPaste = true;
        c.EditMethod = FLAME_EDIT_METHOD_REWRITE_TRAJECTORY;
        generate("flow method on a diffusion model");
        CHECK(!succeeded && c.LastError.Utf8().find("does not apply") != std::string::npos, "%s", c.LastError.Utf8().c_str());

        c.EditMethod = 0;
        c.EditTask = 7;
        generate("unknown task");
        CHECK(!succeeded && c.LastError.Utf8().find("unknown editing task 7") != std::string::npos, "%s", c.LastError.Utf8().c_str());

        c.EditTask = FLAME_EDIT_TASK_PATH;
        c.EditReference.Reset();
        c.EditReference.Append(edit.data(), 10);
        generate("bad reference length");
        CHECK(!succeeded && c.LastError.Utf8().find("EditReference has 10 values") == 0, "%s", c.LastError.Utf8().c_str());

        c.EditReference.Reset();
        generate("no reference");
        CHECK(!succeeded && c.LastError.Utf8().find("FLAME_STATUS_WRONG_STATE") == 0 &&
                  c.LastError.Utf8().find("no reference") != std::string::npos,
              "%s", c.LastError.Utf8().c_str());

        c.EditTask = -1;  // back to plain generation: the CLI's features
        generate("plain");
        CHECK(succeeded && std::memcmp(c.Pose.GetData(), reference.data(), reference.size() * 4) == 0, "plain again");
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // Position targets: the pelvis pinned to a path across the ground (Unreal convention,
        // centimetres), from where the unguided pelvis starts, +5 cm in X and -4 cm in Y per
        // frame, Z free (NaN). The guided pelvis follows it; scale 0 = the unguided run.
        const int TF = 16, J = 24;
        UFlameMotionComponent c;
        Configure(c, argv[1], TF, 20, true, FLAME_LAYOUT_GLOBAL_POSITIONS, FLAME_CONVENTION_UNREAL);
        c.Guidance = 2.5f;
        c.Seed = 7;
        c.Prompt = FString(TEXT("a person walks forward."));
        CHECK(c.TargetFrames.Num() == 0 && c.TargetScale == 0.6f && c.TargetSchedule == -1 && c.TargetLoss == -1.f,
              "target defaults");
        int finishedCalls = 0;
        bool succeeded = false;
        c.OnFinished.AddLambda([&](bool ok) { finishedCalls++; succeeded = ok; });
        auto generate = [&](const char* what) {
            const int before = finishedCalls;
            CHECK(c.Generate(), "Generate (%s): %s", what, c.LastError.Utf8().c_str());
            CHECK(TickUntil(c, [&] { return finishedCalls > before; }), "finished (%s)", what);
        };
        generate("unguided");
        CHECK(succeeded && c.Pose.Num() == TF * J * 3 && c.TargetLoss == -1.f, "unguided: %s", c.LastError.Utf8().c_str());
        std::vector<float> unguided(c.Pose.GetData(), c.Pose.GetData() + c.Pose.Num());
        if (unguided.size() == (size_t)TF * J * 3) {
            auto pelvisError = [&](const TArray<float>& pose) {
                std::vector<double> e;
                for (int f = 0; f < TF; f++) {
                    const double dx = pose[f * J * 3] - (unguided[0] + 5.0 * f);
                    const double dy = pose[f * J * 3 + 1] - (unguided[1] - 4.0 * f);
                    e.push_back(std::sqrt(dx * dx + dy * dy));
                }
                std::sort(e.begin(), e.end());
                return e[TF / 2];
            };
            TArray<float> unguidedPose = c.Pose;
            for (int f = 0; f < TF; f++) {
                c.AddJointTarget(f, 0, FVector(unguided[0] + 5.0 * f, unguided[1] - 4.0 * f, std::nan("")));
            }
            generate("guided");
            const double before = pelvisError(unguidedPose), after = pelvisError(c.Pose);
            CHECK(succeeded && c.TargetLoss > 0.f && std::isfinite(c.TargetLoss), "guided: %s, loss %f",
                  c.LastError.Utf8().c_str(), (double)c.TargetLoss);
            CHECK(before > 5.0 && after < 0.5 * before, "median pelvis error %.2f cm unguided, %.2f cm guided", before, after);

            c.TargetScale = 0.f;
            generate("scale 0");
            CHECK(succeeded && c.TargetLoss == -1.f &&
                      std::memcmp(c.Pose.GetData(), unguided.data(), unguided.size() * 4) == 0,
                  "scale 0: the unguided run");

            c.TargetScale = 100.5f;
            generate("scale out of range");
            CHECK(!succeeded && c.LastError.Utf8().find("target scale") != std::string::npos, "%s", c.LastError.Utf8().c_str());
            c.TargetScale = 0.6f;
            c.TargetSchedule = 2;
            generate("unknown schedule");
            CHECK(!succeeded && c.LastError.Utf8().find("unknown target schedule 2") != std::string::npos, "%s",
                  c.LastError.Utf8().c_str());
            c.TargetSchedule = -1;
            c.AddJointTarget(TF, 0, FVector(0, 0, 0));
            generate("a frame past the session's");
            CHECK(!succeeded && c.LastError.Utf8().find("cover 17 frames; the session has 16") != std::string::npos, "%s",
                  c.LastError.Utf8().c_str());
            c.ClearJointTargets();
            c.AddJointTarget(0, J, FVector(0, 0, 0));
            generate("an unknown joint");
            CHECK(!succeeded && c.LastError.Utf8().find("position target 0: frame 0, joint 24 (the model has 24 joints)") == 0,
                  "%s", c.LastError.Utf8().c_str());
            c.ClearJointTargets();
            c.AddJointTarget(0, 0, FVector(std::nan(""), std::nan(""), std::nan("")));
            generate("nothing constrained");
            CHECK(!succeeded && c.LastError.Utf8().find("constrain nothing") != std::string::npos, "%s", c.LastError.Utf8().c_str());
            c.ClearJointTargets();
            c.TargetJoints.Add(0);
            generate("arrays of different lengths");
            CHECK(!succeeded && c.LastError.Utf8().find("hold 0, 1 and 0 entries") != std::string::npos, "%s",
                  c.LastError.Utf8().c_str());
            c.ClearJointTargets();
            generate("no targets");
            CHECK(succeeded && c.TargetLoss == -1.f && std::memcmp(c.Pose.GetData(), unguided.data(), unguided.size() * 4) == 0,
                  "cleared targets: the unguided run");
        }
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // A prompt longer than the text encoder's window (the fixture's RoBERTa: 20 tokens):
        // bPromptTruncated, PromptDropped = the prompt's tail, and one warning in the log.
        UFlameMotionComponent c;
        Configure(c, argv[1], Frames, 2, true);
        const std::string prompt = "a person walks forward, turns left, raises both arms, waves with the right hand, "
                                   "sits down on a chair and then kicks with the right leg";
        c.Prompt = FString(UTF8_TO_TCHAR(prompt.c_str()));
        int finishedCalls = 0;
        c.OnFinished.AddLambda([&](bool) { finishedCalls++; });
        auto warnings = [] {
            int n = 0;
            for (const std::string& line : UeStubLogLines())
                n += line.find("LogFlame: Warning: the prompt has ") == 0;
            return n;
        };
        const int before = warnings();
        CHECK(c.Generate(), "Generate: %s", c.LastError.Utf8().c_str());
        CHECK(TickUntil(c, [&] { return finishedCalls > 0; }), "finished");
        const std::string dropped = c.PromptDropped.Utf8();
        CHECK(c.bPromptTruncated && !dropped.empty() && dropped.size() < prompt.size() &&
                  prompt.compare(prompt.size() - dropped.size(), dropped.size(), dropped) == 0 &&
                  dropped.find("kicks with the right leg") != std::string::npos,
              "dropped \"%s\"", dropped.c_str());
        CHECK(warnings() == before + 1, "one warning, %d", warnings() - before);
        const std::vector<std::string> lines = UeStubLogLines();
        const std::string& last = lines.empty() ? std::string() : lines.back();
        CHECK(last.find("keeps its first 20") != std::string::npos && last.find("\"" + dropped + "\"") != std::string::npos,
              "%s", last.c_str());

        c.Prompt = FString(TEXT("a person walks"));
        CHECK(c.Generate(), "Generate short");
        CHECK(TickUntil(c, [&] { return finishedCalls > 1; }), "finished short");
        CHECK(!c.bPromptTruncated && c.PromptDropped.IsEmpty() && warnings() == before + 1, "a short prompt fits, no warning");
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // Frames = 0: the model's default (the fixture's 200), as flame_session_read_frames
        // reports it for every published pose.
        UFlameMotionComponent c;
        Configure(c, argv[1], 0, 2, true, FLAME_LAYOUT_LOCAL_QUAT_XYZW);
        bool finished = false, succeeded = false, allFrames = true;
        int poses = 0;
        c.OnProgress.AddLambda([&](int32, int32) {
            poses++;
            allFrames = allFrames && c.GetFrameCount() == 200 && c.GetValuesPerFrame() == 24 * 4 &&
                        c.RootLocations.Num() == 200 * 3;
        });
        c.OnFinished.AddLambda([&](bool ok) { finished = true; succeeded = ok; });
        CHECK(c.Generate(), "Generate");
        CHECK(TickUntil(c, [&] { return finished; }), "finished");
        CHECK(succeeded && poses >= 1 && allFrames, "default frames: %d poses, %d frames x %d", poses,
              c.GetFrameCount(), c.GetValuesPerFrame());
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // A latent model: every published pose has the frames libflame reports for its read, and
        // the final one is the CLI's output, frame count and bits (not the 60 frames asked).
        const int LatentFrames = NpyRows(argv[4]), LatentDim = 263;
        std::vector<float> latentReference = NpyData(argv[4], (size_t)LatentFrames * LatentDim);
        UFlameMotionComponent c;
        Configure(c, argv[3], 60, 4, true);
        bool finished = false, succeeded = false, consistent = true;
        c.OnProgress.AddLambda([&](int32, int32) {
            consistent = consistent && c.GetFrameCount() >= 10 && c.GetValuesPerFrame() == LatentDim &&
                         c.Pose.Num() == c.GetFrameCount() * LatentDim && c.RootLocations.Num() == c.GetFrameCount() * 3;
        });
        c.OnFinished.AddLambda([&](bool ok) { finished = true; succeeded = ok; });
        CHECK(c.Generate(), "Generate (latent)");
        CHECK(TickUntil(c, [&] { return finished; }), "finished (latent)");
        CHECK(succeeded && consistent, "latent: %s", c.LastError.Utf8().c_str());
        CHECK(LatentFrames >= 10 && LatentFrames != 60 && c.GetFrameCount() == LatentFrames,
              "latent frames %d, the CLI's %d", c.GetFrameCount(), LatentFrames);
        CHECK(c.Pose.Num() == LatentFrames * LatentDim &&
                  std::memcmp(c.Pose.GetData(), latentReference.data(), latentReference.size() * 4) == 0,
              "latent Pose = the CLI's features");
        CHECK(c.GetFramePose(LatentFrames - 1).Num() == LatentDim && c.GetFramePose(LatentFrames).Num() == 0,
              "GetFramePose at the decoded length");
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // Prompts per time stage on a model that takes one prompt (MDM): one stage is Prompt,
        // bit for bit; two stages, a part text or frames that do not add up fail the generation
        // with libflame's message; ClearPromptStages goes back to Prompt.
        const std::string model = std::string(argv[1]).substr(0, std::string(argv[1]).find_last_of('/') + 1) + "mdm_tiny.safetensors";
        const int SF = 16, MdmDim = 263;
        UFlameMotionComponent c;
        Configure(c, model.c_str(), SF, 3, true);
        CHECK(c.PromptStages.Num() == 0, "no stages by default");
        int finishedCalls = 0;
        bool succeeded = false;
        c.OnFinished.AddLambda([&](bool ok) { finishedCalls++; succeeded = ok; });
        auto generate = [&](const char* what) {
            const int before = finishedCalls;
            CHECK(c.Generate(), "Generate (%s): %s", what, c.LastError.Utf8().c_str());
            CHECK(TickUntil(c, [&] { return finishedCalls > before; }), "finished (%s)", what);
        };
        generate("prompt");
        CHECK(succeeded && c.Pose.Num() == SF * MdmDim, "prompt: %s", c.LastError.Utf8().c_str());
        std::vector<float> plain(c.Pose.GetData(), c.Pose.GetData() + c.Pose.Num());
        auto samePlain = [&] {
            return c.Pose.Num() == (int32)plain.size() && std::memcmp(c.Pose.GetData(), plain.data(), plain.size() * 4) == 0;
        };
        c.AddPromptStage(FFlameStage(c.Prompt, SF));
        c.Prompt = FString(TEXT("ignored while there are stages"));
        generate("one stage");
        CHECK(succeeded && samePlain() && c.GetFrameCount() == SF, "one stage = the prompt: %s", c.LastError.Utf8().c_str());
        FFlameStage second(FString(TEXT("a person jumps")), SF / 2);
        c.PromptStages[0].Frames = SF / 2;
        c.AddPromptStage(second);
        generate("two stages");
        CHECK(!succeeded && c.LastError.Utf8().find("FLAME_STATUS_INVALID_ARGUMENT") == 0 &&
                  c.LastError.Utf8().find("this mdm model takes one prompt per generation (a single stage without part texts)") !=
                      std::string::npos,
              "%s", c.LastError.Utf8().c_str());
        c.ClearPromptStages();
        FFlameStage part(FString(TEXT("a person walks forward and waves.")), SF);
        part.LeftArm = FString(TEXT("waves"));
        c.AddPromptStage(part);
        generate("a part text");
        CHECK(!succeeded && c.LastError.Utf8().find("a single stage without part texts") != std::string::npos, "%s",
              c.LastError.Utf8().c_str());
        c.PromptStages[0].LeftArm = FString();
        c.PromptStages[0].Frames = SF - 1;
        generate("frames that do not add up");
        CHECK(!succeeded && c.LastError.Utf8().find("the stages cover 15 frames, the session has 16") != std::string::npos, "%s",
              c.LastError.Utf8().c_str());
        c.PromptStages[0].Frames = -1;
        generate("negative frames");
        CHECK(!succeeded && c.LastError.Utf8() == "PromptStages[0].Frames is -1", "%s", c.LastError.Utf8().c_str());
        c.ClearPromptStages();
        c.Prompt = FString(TEXT("a person walks forward and waves."));
        generate("cleared stages");
        CHECK(succeeded && c.PromptStages.Num() == 0 && samePlain(), "cleared stages: the prompt again");
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // FineMoGen (tests/fixtures/finemogen_tiny.safetensors; skipped when absent) composes the
        // stages: 24 + 31 frames publish poses of 55 frames, the final one finite.
        const std::string model = std::string(argv[1]).substr(0, std::string(argv[1]).find_last_of('/') + 1) +
                                  "finemogen_tiny.safetensors";
        if (std::FILE* f = std::fopen(model.c_str(), "rb")) {
            std::fclose(f);
            UFlameMotionComponent c;
            Configure(c, model.c_str(), 55, 4, true);
            c.AddPromptStage(FFlameStage(FString(TEXT("a person walks forward")), 24));
            FFlameStage jump(FString(TEXT("a person jumps")), 31);
            jump.RightArm = FString(TEXT("raises the right arm"));
            c.AddPromptStage(jump);
            bool finished = false, succeeded = false, allFrames = true;
            c.OnProgress.AddLambda([&](int32, int32) {
                allFrames = allFrames && c.GetFrameCount() == 55 && c.Pose.Num() == 55 * 263 && c.RootLocations.Num() == 55 * 3;
            });
            c.OnFinished.AddLambda([&](bool ok) { finished = true; succeeded = ok; });
            CHECK(c.Generate(), "Generate (FineMoGen stages)");
            CHECK(TickUntil(c, [&] { return finished; }), "finished (FineMoGen stages)");
            bool finite = c.Pose.Num() == 55 * 263;
            for (int32 i = 0; finite && i < c.Pose.Num(); i++) finite = std::isfinite(c.Pose[i]);
            CHECK(succeeded && allFrames && finite && c.StepsDone == 4, "FineMoGen stages: %s, %d frames",
                  c.LastError.Utf8().c_str(), c.GetFrameCount());
        } else {
            std::printf("skip FineMoGen stages: no %s\n", model.c_str());
        }
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // Retarget onto a Mannequin-named reference skeleton: the published poses are a direct
        // flame_retarget_read's bit for bit, the poseable mesh gets the frame under the playhead.
        USkinnedAsset asset;
        Mannequin(asset);
        const int bones = asset.RefSkeleton.GetNum();
        UPoseableMeshComponent mesh;
        mesh.Asset = &asset;
        mesh.BoneSpaceTransforms.SetNum(bones);
        UFlameMotionComponent c;
        Configure(c, argv[1], Frames, 10, true, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL);
        c.RetargetMesh = &mesh;
        c.bPlayOnMesh = false; // the playhead starts below, from a known time
        bool finished = false, succeeded = false;
        c.OnFinished.AddLambda([&](bool ok) { finished = true; succeeded = ok; });
        CHECK(c.Generate(), "Generate: %s", c.LastError.Utf8().c_str());
        CHECK(TickUntil(c, [&] { return finished; }), "finished");
        CHECK(succeeded, "%s", c.LastError.Utf8().c_str());
        bool names = c.RigBoneNames.Num() == bones;
        for (int b = 0; names && b < bones; b++) names = c.RigBoneNames[b] == asset.RefSkeleton.Names[b].ToString();
        CHECK(names, "RigBoneNames = the reference skeleton's (%d)", c.RigBoneNames.Num());
        FlameCleanupParams cleanup;
        flame_cleanup_params_default(&cleanup);
        cleanup.feet = FLAME_FEET_OFF; // Configure's
        cleanup.ground = 0;
        std::vector<float> rot, tr;
        CHECK(DirectRetarget(argv[1], Frames, 10, asset, &cleanup, rot, tr), "direct retarget");
        CHECK(SameFloats(c.BoneRotations, rot) && SameFloats(c.BoneTranslations, tr) && rot.size() == (size_t)Frames * bones * 4,
              "BoneRotations/BoneTranslations = flame_retarget_read (%d, %d floats)", c.BoneRotations.Num(), (int)rot.size());
        CHECK(c.MeshFrame == -1 && mesh.RefreshCount == 0, "nothing written with bPlayOnMesh off");
        // Played on the mesh from frame 0 at 20 fps: 0.1 s later frame 2; 1.2 s more (24
        // frames) loops back onto frame 2.
        c.bPlayOnMesh = true;
        c.TickComponent(0.f, LEVELTICK_All, &c.PrimaryComponentTick);
        CHECK(c.MeshFrame == 0 && MeshHolds(mesh, c, 0) && mesh.RefreshCount == 1, "mesh posed with frame 0 (frame %d)", c.MeshFrame);
        c.TickComponent(0.1f, LEVELTICK_All, &c.PrimaryComponentTick);
        CHECK(c.MeshFrame == 2 && MeshHolds(mesh, c, 2), "mesh posed with frame 2 after 0.1 s (frame %d)", c.MeshFrame);
        c.TickComponent(1.2f, LEVELTICK_All, &c.PrimaryComponentTick);
        CHECK(c.MeshFrame == 2 && MeshHolds(mesh, c, 2), "looped at 24 frames: frame %d", c.MeshFrame);
        c.bPlayOnMesh = false;
        CHECK(c.ApplyRetargetFrame(17) && MeshHolds(mesh, c, 17), "ApplyRetargetFrame(17)");
        CHECK(!c.ApplyRetargetFrame(Frames) && !c.ApplyRetargetFrame(-1) && c.MeshFrame == 17, "frames out of range refused");
        // The pelvis moves with the motion; the root keeps its reference translation.
        bool pelvisMoves = false, rootStill = true;
        for (int f = 1; f < Frames; f++) {
            pelvisMoves |= c.GetBoneTranslation(f, 1).X != c.GetBoneTranslation(0, 1).X;
            rootStill &= c.GetBoneTranslation(f, 0).X == 0 && c.GetBoneTranslation(f, 0).Z == 0;
        }
        CHECK(pelvisMoves && rootStill, "pelvis moves, root still");
        // Another mesh with other bones: nothing is written to it.
        UPoseableMeshComponent other;
        other.Asset = &asset;
        other.BoneSpaceTransforms.SetNum(3);
        c.RetargetMesh = &other;
        CHECK(!c.ApplyRetargetFrame(3) && other.RefreshCount == 0, "a mesh of other bones is left alone");

        // Errors: a bone map naming a bone the mesh lacks (the message names it), a mesh
        // without a skeletal mesh, bones the automatic map cannot read.
        c.RetargetMesh = &mesh;
        c.BoneMapJson = FString(TEXT("{\"leftHand\": \"hand_lx\"}"));
        finished = false;
        CHECK(c.Generate(), "Generate (bad map)");
        CHECK(TickUntil(c, [&] { return finished; }), "finished (bad map)");
        CHECK(!succeeded && c.LastError.Utf8().find("hand_lx") != std::string::npos && c.BoneRotations.Num() == 0,
              "bad map: %s", c.LastError.Utf8().c_str());
        // Entries over the automatic map: naming what it finds anyway changes nothing.
        c.BoneMapJson = FString(TEXT("{\"hips\": \"pelvis\", \"leftHand\": \"hand_l\"}"));
        finished = false;
        CHECK(c.Generate(), "Generate (map over names)");
        CHECK(TickUntil(c, [&] { return finished; }), "finished (map)");
        CHECK(succeeded && SameFloats(c.BoneRotations, rot), "a map the automatic one agrees with: same poses: %s", c.LastError.Utf8().c_str());
        UPoseableMeshComponent empty;
        c.RetargetMesh = &empty;
        CHECK(!c.Generate() && c.LastError.Utf8().find("no skeletal mesh") != std::string::npos, "%s", c.LastError.Utf8().c_str());
        USkinnedAsset odd = asset;
        for (int b = 0; b < bones; b++) odd.RefSkeleton.Names[b] = FName(UTF8_TO_TCHAR(("b" + std::to_string(b)).c_str()));
        mesh.Asset = &odd;
        c.RetargetMesh = &mesh;
        c.BoneMapJson = FString();
        finished = false;
        CHECK(c.Generate(), "Generate (unreadable names)");
        CHECK(TickUntil(c, [&] { return finished; }), "finished (names)");
        CHECK(!succeeded && c.LastError.Utf8().find("hips") != std::string::npos, "unreadable names: %s", c.LastError.Utf8().c_str());
    }
    CHECK(WaitForThreads(), "workers exited");

    {   // Errors reach LastError and OnFinished(false).
        UFlameMotionComponent c;
        Configure(c, "/nonexistent/model.safetensors", Frames, 10, true);
        bool finished = false, succeeded = true;
        c.OnFinished.AddLambda([&](bool ok) { finished = true; succeeded = ok; });
        CHECK(c.Generate(), "Generate");
        CHECK(TickUntil(c, [&] { return finished; }), "finished");
        CHECK(!succeeded && c.LastError.Utf8().find("FLAME_STATUS_IO: cannot read /nonexistent/model.safetensors") == 0,
              "%s", c.LastError.Utf8().c_str());

        Configure(c, argv[1], 471, 10, true);
        finished = false;
        CHECK(c.Generate(), "Generate");
        CHECK(TickUntil(c, [&] { return finished; }), "finished");
        CHECK(!succeeded && c.LastError.Utf8().find("frames must be between 1 and 470") != std::string::npos, "%s", c.LastError.Utf8().c_str());
    }
    CHECK(WaitForThreads(), "workers exited");
    module.ShutdownModule();

    std::printf("%d passed, %d failed\n", passed, failed);
    return failed == 0 ? 0 : 1;
}
