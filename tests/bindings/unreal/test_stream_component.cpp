/*
 * UFlameStreamComponent (bindings/unreal/Flame) compiled against stand-ins for the engine
 * (ue_stubs/ue_stub.h) and run against the real libflame, driven the way the engine would:
 * StartStream (or BeginPlay), the Push and Interrupt calls of Blueprints, TickComponent every frame with
 * a DeltaTime, StopStream / EndPlay.
 *
 * - the frames the component receives equal, bit for bit, those of a flame_stream_* stream with
 *   the same settings and timeline (Pose, RootLocation, GetFramePose, GetJointRotation; the
 *   local quaternions the component reads chunk by chunk = one read of the whole timeline),
 *   with one step per tick as with a hundred: the step budget changes when frames come, not
 *   what they are; StepsPerTick = 0 pauses generation;
 * - PushSegment's seconds become frames at the model's frame rate;
 * - the playhead moves with DeltaTime × PlayRate at the model's fps, stops with bPlaying false,
 *   and waits at the last frame generated (bWaitingForFrames);
 * - OnStarted and OnStarving, the window (frames behind the playhead dropped);
 * - interrupt: the same frames as a flame_stream_* stream interrupted at the same boundary;
 * - PushStage: part texts refused on FLAME (INVALID_ARGUMENT in LastError; an interrupt goes on),
 *   composed on FineMoGen (the frames of flame_stream_push_stage);
 * - errors: a push before StartStream, a non-positive length, a missing model file, a latent
 *   model (OnStarted(false));
 * - StopStream while a long pump runs: it returns at once, the pump is cancelled and its thread
 *   exits soon after; nothing of libflame is left (FFlameModule::ActiveWorkers, LeakSanitizer);
 * - cleanup (bCleanup, off by default; the settings and defaults of UFlameMotionComponent): the
 *   frames the component publishes are, bit for bit, flame_stream_read_cleaned's on a stream
 *   driven the same way, at the cleanup's frame rate (172 frames at 30 fps from 115 at 20, the
 *   playhead counting 30 a second); frames arrive as they settle (feet free) or, with locked
 *   feet on the tiny model, only after EndTimeline (the stream generates on meanwhile, past a
 *   small Lookahead); a changed cleanup is refused (LastError, the log) and the frames go on
 *   with the first; a refused cleanup fails the start; Layout 0 stays raw; a stream refuses a
 *   loop wrap; pushes after EndTimeline are refused.
 *
 * usage: test_stream_component FIXTURES_DIR   (tests/fixtures)
 * Ends with one line "N passed, N failed"; the exit code is 1 when anything failed.
 */
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <vector>

#include "FlameModule.h"
#include "FlameStreamComponent.h"
#include "flame.h"
#include "mannequin.h"

static int passed, failed;

#define CHECK(cond, ...)                                                 \
    do {                                                                 \
        if (cond) {                                                      \
            passed++;                                                    \
        } else {                                                         \
            failed++;                                                    \
            std::fprintf(stderr, "FAIL line %d: %s: ", __LINE__, #cond); \
            std::fprintf(stderr, __VA_ARGS__);                           \
            std::fprintf(stderr, "\n");                                  \
        }                                                                \
    } while (0)

static std::string g_dir;

/* Ticks the component like the game thread would (DeltaTime `dt`) until done() or the timeout. */
template <typename F> static bool TickUntil(UFlameStreamComponent& c, F done, float dt = 0.f, double seconds = 60) {
    auto start = std::chrono::steady_clock::now();
    while (!done()) {
        c.TickComponent(dt, LEVELTICK_All, &c.PrimaryComponentTick);
        if (std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() > seconds) return false;
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    return true;
}

static void Tick(UFlameStreamComponent& c, float dt) { c.TickComponent(dt, LEVELTICK_All, &c.PrimaryComponentTick); }

static bool WaitForThreads(double seconds = 20) {
    auto start = std::chrono::steady_clock::now();
    while (UeStubRunningThreads() > 0) {
        if (std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() > seconds) return false;
        std::this_thread::sleep_for(std::chrono::milliseconds(1));
    }
    return true;
}

static std::string Path(const char* name) { return g_dir + "/" + name + ".safetensors"; }

static bool Exists(const std::string& path) {
    if (std::FILE* f = std::fopen(path.c_str(), "rb")) {
        std::fclose(f);
        return true;
    }
    return false;
}

/* The component's settings of tests/c/test_stream.c: chunks of 40 frames keeping 10, 3 DDIM
 * steps, seed 5, everything generated ahead (lookahead 1000). */
static void Configure(UFlameStreamComponent& c, const std::string& model) {
    char* full = realpath(model.c_str(), nullptr);
    c.ModelPath = FString(UTF8_TO_TCHAR(full ? full : model.c_str()));
    std::free(full);
    c.bAutoStart = false;
    c.Chunk = 40;
    c.Overlap = 10;
    c.Lookahead = 1000;
    c.Window = 10000;
    c.Steps = 3;
    c.bUseDdim = true;
    c.Seed = 5;
    c.Threads = 1;
}

/* The same stream straight through flame.h. */
struct Direct {
    FlameModel* model = nullptr;
    FlameStream* stream = nullptr;
    explicit Direct(const std::string& path, uint32_t chunk = 40) {
        flame_model_load(path.c_str(), nullptr, &model);
        FlameStreamParams p;
        flame_stream_params_default(&p);
        p.chunk = chunk;
        p.overlap = 10;
        p.lookahead = 1000;
        p.window = 10000;
        p.steps = 3;
        p.sampler = FLAME_SAMPLER_DDIM;
        p.seed = 5;
        p.threads = 1;
        if (model) flame_stream_new(model, &p, &stream);
    }
    ~Direct() {
        flame_stream_free(stream);
        flame_model_free(model);
    }
    Direct(const Direct&) = delete;
    bool push(const char* text, uint32_t frames) { return flame_stream_push(stream, text, frames) == FLAME_STATUS_OK; }
    bool interrupt(const char* text, uint32_t frames) { return flame_stream_interrupt(stream, text, frames) == FLAME_STATUS_OK; }
    uint64_t pump(uint32_t steps) {
        FlameStreamStatus st;
        std::memset(&st, 0, sizeof st);
        st.struct_size = sizeof st;
        flame_stream_pump(stream, steps, &st);
        return st.ready;
    }
    std::vector<float> read(uint64_t first, uint32_t count, int32_t layout, int32_t convention) {
        size_t n = 0;
        std::vector<float> out;
        if (flame_stream_read(stream, first, count, layout, convention, 0, nullptr, 0, &n) != FLAME_STATUS_OK) return out;
        out.resize(n);
        flame_stream_read(stream, first, count, layout, convention, 0, out.data(), n, &n);
        return out;
    }
    /* flame_stream_read_cleaned (empty when refused or not settled). */
    std::vector<float> read_cleaned(uint64_t first, uint32_t count, int32_t layout, int32_t convention,
                                    const FlameCleanupParams& cleanup) {
        size_t n = 0;
        std::vector<float> out;
        if (flame_stream_read_cleaned(stream, first, count, layout, convention, &cleanup, nullptr, 0, &n) != FLAME_STATUS_OK)
            return out;
        out.resize(n);
        flame_stream_read_cleaned(stream, first, count, layout, convention, &cleanup, out.data(), n, &n);
        return out;
    }
    /* The cleaned frames settled so far: read one at a time until one is not. */
    int64 settled(int32_t layout, int32_t convention, const FlameCleanupParams& cleanup) {
        int64 k = 0;
        size_t n = 0;
        while (flame_stream_read_cleaned(stream, (uint64_t)k, 1, layout, convention, &cleanup, nullptr, 0, &n) == FLAME_STATUS_OK)
            k++;
        return k;
    }
};

/* Whether frames first..first+count of the component equal `want` (count × per-frame values). */
static bool SameFrames(const UFlameStreamComponent& c, int64 first, int64 count, const std::vector<float>& want) {
    const int32 per = c.GetValuesPerFrame();
    if (per <= 0 || want.size() != (size_t)(count * per)) return false;
    for (int64 f = 0; f < count; f++) {
        TArray<float> row = c.GetFramePose(first + f);
        if (row.Num() != per || std::memcmp(row.GetData(), want.data() + f * per, (size_t)per * 4) != 0) {
            std::fprintf(stderr, "     frame %d differs\n", (int)(first + f));
            return false;
        }
    }
    return true;
}

static bool SameRoots(const UFlameStreamComponent& c, int64 first, int64 count, const std::vector<float>& want) {
    if (want.size() != (size_t)(count * 3)) return false;
    for (int64 f = 0; f < count; f++) {
        const FVector v = c.GetRootLocationAt(first + f);
        const float* w = want.data() + f * 3;
        if ((float)v.X != w[0] || (float)v.Y != w[1] || (float)v.Z != w[2]) return false;
    }
    return true;
}

static bool SameRootBones(const UFlameStreamComponent& c, int64 first, int64 count, const std::vector<float>& want) {
    if (want.size() != (size_t)(count * 3)) return false;
    for (int64 f = 0; f < count; f++) {
        const FVector v = c.GetRootBoneLocationAt(first + f);
        const float* w = want.data() + f * 3;
        if ((float)v.X != w[0] || (float)v.Y != w[1] || (float)v.Z != w[2]) return false;
    }
    return true;
}

/* The timeline of tests/c/test_stream.c: 50 + 25 + 40 = 115 frames, 15 steps. */
static const int64 kTimeline = 115;

/* Pushes it through the component (the middle segment as 1.25 s: 25 frames at 20 fps) and ticks
 * until every frame is in; returns the largest StepsLastPump seen. */
static int RunTimeline(UFlameStreamComponent& c, int stepsPerTick) {
    c.StepsPerTick = stepsPerTick;
    CHECK(c.PushSegmentFrames(FString(TEXT("a person walks forward.")), 50), "push: %s", c.LastError.Utf8().c_str());
    CHECK(c.PushSegment(FString(TEXT("a person waves.")), 1.25f), "push seconds: %s", c.LastError.Utf8().c_str());
    CHECK(c.PushSegmentFrames(FString(TEXT("a person sits down.")), 40), "push: %s", c.LastError.Utf8().c_str());
    int most = 0;
    CHECK(TickUntil(c, [&] {
              most = c.StepsLastPump > most ? c.StepsLastPump : most;
              return c.ReadyFrames == kTimeline && c.StepsTotal == 15 && c.GetFramePose(kTimeline - 1).Num() > 0;
          }),
          "all %d frames generated (%d ready, %d steps)", (int)kTimeline, (int)c.ReadyFrames, (int)c.StepsTotal);
    return most;
}

static void TestPlayback() {
    const std::string model = Path("flame_tiny");
    Direct d(model);
    d.push("a person walks forward.", 50);
    d.push("a person waves.", 25);
    d.push("a person sits down.", 40);
    CHECK(d.pump(UINT32_MAX) == (uint64_t)kTimeline, "direct stream");
    const std::vector<float> quats = d.read(0, kTimeline, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL);
    const std::vector<float> roots = d.read(0, kTimeline, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_UNREAL);

    UFlameStreamComponent c;
    CHECK(c.PrimaryComponentTick.bCanEverTick, "ticks");
    CHECK(c.Layout == FLAME_LAYOUT_LOCAL_QUAT_XYZW && c.Convention == FLAME_CONVENTION_UNREAL && c.bAutoStart &&
              c.StepsPerTick == 4 && c.bPlaying && c.PlayRate == 1.f,
          "defaults");
    Configure(c, model);
    c.StepsPerTick = 1;
    CHECK(!c.PushSegmentFrames(FString(TEXT("a person walks.")), 10) &&
              c.LastError.Utf8().find("the stream is not running") == 0,
          "a push before StartStream: %s", c.LastError.Utf8().c_str());
    int started = 0, starving = 0;
    bool startedOk = false;
    c.OnStarted.AddLambda([&](bool ok) { started++; startedOk = ok; });
    c.OnStarving.AddLambda([&] { starving++; });
    CHECK(c.StartStream(), "StartStream: %s", c.LastError.Utf8().c_str());
    CHECK(c.IsStreaming(), "streaming");
    CHECK(!c.StartStream() && c.LastError.Utf8().find("already running") != std::string::npos, "a second StartStream");
    CHECK(c.CurrentFrame == -1 && c.Pose.Num() == 0, "no pose before the first frames");
    CHECK(!c.PushSegment(FString(TEXT("a person walks.")), 0.f) && !c.PushSegment(FString(TEXT("a person walks.")), -1.f) &&
              !c.PushSegmentFrames(FString(TEXT("a person walks.")), 0) &&
              c.LastError.Utf8().find("a segment needs a positive length") == 0,
          "non-positive lengths: %s", c.LastError.Utf8().c_str());
    c.LastError.Reset();

    const int most = RunTimeline(c, 1);
    CHECK(most == 1, "one step per tick at most: %d", most);
    CHECK(started == 1 && startedOk && c.Fps == 20.f && c.JointNames.Num() == 24 && c.JointParents.Num() == 24,
          "OnStarted(true), the skeleton and fps %f", (double)c.Fps);
    CHECK(c.LastError.IsEmpty(), "no error: %s", c.LastError.Utf8().c_str());
    // Everything is generated and nothing more is pushed: starving (OnStarving may also have
    // come for the empty stream, before the first pump had the segments).
    CHECK(TickUntil(c, [&] { return c.bStarving; }) && (starving == 1 || starving == 2), "OnStarving (%d)", starving);
    const int starvingBefore = starving;
    CHECK(c.GetValuesPerFrame() == 24 * 4, "values per frame %d", c.GetValuesPerFrame());
    CHECK(SameFrames(c, 0, kTimeline, quats), "every frame = one flame_stream_read of them all, bit for bit");
    CHECK(SameRoots(c, 0, kTimeline, roots), "every root location = flame_stream_read's");
    CHECK(c.GetFramePose(kTimeline).Num() == 0 && c.GetFramePose(-1).Num() == 0, "frames outside the held ones");

    // The playhead: no game time yet, frame 0.
    CHECK(c.CurrentFrame == 0 && c.Pose.Num() == 24 * 4 && std::memcmp(c.Pose.GetData(), quats.data(), 24 * 4 * 4) == 0,
          "Pose = frame 0 (frame %d)", (int)c.CurrentFrame);
    CHECK((float)c.RootLocation.X == roots[0] && (float)c.RootLocation.Y == roots[1] && (float)c.RootLocation.Z == roots[2],
          "RootLocation = frame 0's");
    const FQuat q = c.GetJointRotation(3);
    CHECK((float)q.X == quats[12] && (float)q.Y == quats[13] && (float)q.Z == quats[14] && (float)q.W == quats[15],
          "GetJointRotation(3)");
    const FQuat none = c.GetJointRotation(24);
    CHECK(none.X == 0 && none.Y == 0 && none.Z == 0 && none.W == 1, "an unknown joint: identity");
    // Game time at 20 fps: 0.05 s is a frame.
    Tick(c, 0.05f);
    CHECK(c.CurrentFrame == 1 && std::memcmp(c.Pose.GetData(), quats.data() + 96, 96 * 4) == 0, "one frame later: %d",
          (int)c.CurrentFrame);
    Tick(c, 0.1f);
    CHECK(c.CurrentFrame == 3, "two frames later: %d", (int)c.CurrentFrame);
    c.PlayRate = 2.f;
    Tick(c, 0.05f);
    CHECK(c.CurrentFrame == 5, "twice as fast: %d", (int)c.CurrentFrame);
    c.PlayRate = 1.f;
    c.bPlaying = false;
    Tick(c, 1.f);
    CHECK(c.CurrentFrame == 5 && !c.bWaitingForFrames, "paused: %d", (int)c.CurrentFrame);
    c.bPlaying = true;
    Tick(c, 0.5f);
    CHECK(c.CurrentFrame == 15 && std::memcmp(c.Pose.GetData(), quats.data() + 15 * 96, 96 * 4) == 0, "half a second: %d",
          (int)c.CurrentFrame);
    // Past the frames generated: the playhead waits at the last one.
    Tick(c, 100.f);
    CHECK(c.CurrentFrame == kTimeline - 1 && c.bWaitingForFrames, "held at the last frame: %d", (int)c.CurrentFrame);
    CHECK(c.Pose.Num() == 96 && c.GetFramePose(kTimeline - 1).Num() == 96 &&
              std::memcmp(c.Pose.GetData(), c.GetFramePose(kTimeline - 1).GetData(), 96 * 4) == 0,
          "Pose = the last frame");
    // More segments: the playhead goes on with them.
    CHECK(c.PushSegmentFrames(FString(TEXT("a person jumps.")), 30), "push more");
    CHECK(TickUntil(c, [&] { return c.ReadyFrames == kTimeline + 30; }, 0.05f), "generated: %d", (int)c.ReadyFrames);
    CHECK(TickUntil(c, [&] { return c.CurrentFrame > kTimeline; }, 0.05f), "the playhead moves on: %d", (int)c.CurrentFrame);
    CHECK(TickUntil(c, [&] { return c.bStarving; }) && starving == starvingBefore + 1, "starving again: OnStarving again (%d)",
          starving - starvingBefore);

    c.EndPlay(EEndPlayReason::Destroyed);
    CHECK(!c.IsStreaming(), "EndPlay stops the stream");
    CHECK(!c.PushSegmentFrames(FString(TEXT("a person walks.")), 10), "nothing to push to after EndPlay");
}

/* The step budget changes when frames come, not what they are; 0 pauses generation. */
static void TestBudget() {
    const std::string model = Path("flame_tiny");
    UFlameStreamComponent one, many;
    Configure(one, model);
    Configure(many, model);
    one.Convention = many.Convention = FLAME_CONVENTION_GLTF;
    one.Layout = many.Layout = FLAME_LAYOUT_GLOBAL_POSITIONS;
    one.StepsPerTick = 1;
    many.StepsPerTick = 0;
    CHECK(one.StartStream() && many.StartStream(), "StartStream");
    RunTimeline(one, 1);
    many.StepsPerTick = 0;
    CHECK(many.PushSegmentFrames(FString(TEXT("a person walks forward.")), 50), "push");
    for (int i = 0; i < 50; i++) {
        Tick(many, 0.05f);
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
    CHECK(many.StepsTotal == 0 && many.ReadyFrames == 0 && many.CurrentFrame == -1, "StepsPerTick 0: paused (%d steps)",
          (int)many.StepsTotal);
    many.StepsPerTick = 100;
    CHECK(many.PushSegment(FString(TEXT("a person waves.")), 1.25f) &&
              many.PushSegmentFrames(FString(TEXT("a person sits down.")), 40),
          "push");
    CHECK(TickUntil(many, [&] { return many.ReadyFrames == kTimeline && many.GetFramePose(kTimeline - 1).Num() > 0; }),
          "generated with 100 steps per tick");
    CHECK(many.StepsTotal == 15 && many.GetValuesPerFrame() == 24 * 3, "%d steps, %d values", (int)many.StepsTotal,
          many.GetValuesPerFrame());
    bool same = true;
    for (int64 f = 0; f < kTimeline; f++) {
        TArray<float> a = one.GetFramePose(f), b = many.GetFramePose(f);
        same = same && a.Num() == 72 && b.Num() == 72 && std::memcmp(a.GetData(), b.GetData(), 72 * 4) == 0;
    }
    CHECK(same, "1 step per tick = 100 steps per tick, bit for bit");
    one.StopStream();
    many.StopStream();
}

/* Window: frames more than Window behind the playhead are dropped. */
static void TestWindow() {
    UFlameStreamComponent c;
    Configure(c, Path("flame_tiny"));
    c.Window = 20;
    CHECK(c.StartStream(), "StartStream");
    RunTimeline(c, 100);
    Tick(c, 5.f); // 100 frames
    CHECK(c.CurrentFrame == 100 && c.FirstHeldFrame == 80, "frame %d, first held %d", (int)c.CurrentFrame,
          (int)c.FirstHeldFrame);
    CHECK(c.GetFramePose(79).Num() == 0 && c.GetFramePose(80).Num() == 96 && c.GetFramePose(kTimeline - 1).Num() == 96,
          "held frames");
    c.StopStream();
}

/* An interrupt: the frames of a flame_stream_* stream interrupted at the same chunk boundary. */
static void TestInterrupt() {
    const std::string model = Path("flame_tiny");
    UFlameStreamComponent c;
    Configure(c, model);
    c.Layout = 0; // features
    c.StepsPerTick = 3; // one chunk per pump
    CHECK(c.StartStream(), "StartStream");
    CHECK(c.PushSegmentFrames(FString(TEXT("a person walks forward.")), 100) &&
              c.PushSegmentFrames(FString(TEXT("a person sits down.")), 100),
          "push");
    CHECK(TickUntil(c, [&] { return c.ReadyFrames >= 40; }), "a first chunk");
    // The next chunk's pump may have taken the interrupt or not: it ends the first segment at
    // 40 or at 70 frames.
    CHECK(c.InterruptSegmentFrames(FString(TEXT("a person waves.")), 20), "interrupt");
    CHECK(TickUntil(c, [&] { return c.bStarving && (c.ReadyFrames == 60 || c.ReadyFrames == 90); }),
          "the interrupt's 20 frames after the boundary: %d", (int)c.ReadyFrames);
    const int64 ready = c.ReadyFrames;
    Direct d(model);
    d.push("a person walks forward.", 100);
    d.push("a person sits down.", 100);
    d.pump(3);
    if (ready == 90) d.pump(3);
    d.interrupt("a person waves.", 20);
    CHECK(d.pump(UINT32_MAX) == (uint64_t)ready, "direct: the same length");
    TickUntil(c, [&] { return c.GetFramePose(ready - 1).Num() > 0; });
    CHECK(SameFrames(c, 0, ready, d.read(0, (uint32_t)ready, FLAME_LAYOUT_FEATURES, 0)),
          "the interrupted timeline's features (%d frames)", (int)ready);
    c.StopStream();
}

/* PushStage: part texts refused on FLAME, composed on FineMoGen. */
static void TestStages() {
    {
        UFlameStreamComponent c;
        Configure(c, Path("flame_tiny"));
        c.StepsPerTick = 100;
        CHECK(c.StartStream(), "StartStream");
        FFlameStage stage(FString(TEXT("a person walks forward.")), 40);
        stage.LeftArm = FString(TEXT("waves the left arm"));
        CHECK(c.PushStage(stage), "PushStage queues");
        CHECK(TickUntil(c, [&] { return !c.LastError.IsEmpty(); }), "an error arrives");
        CHECK(c.LastError.Utf8().find("FLAME_STATUS_INVALID_ARGUMENT") == 0 &&
                  c.LastError.Utf8().find("part text") != std::string::npos,
              "%s", c.LastError.Utf8().c_str());
        CHECK(c.ReadyFrames == 0, "no frames from it");
        // An interrupt replaces it: the stream goes on.
        CHECK(c.InterruptSegmentFrames(FString(TEXT("a person waves.")), 20), "interrupt");
        CHECK(TickUntil(c, [&] { return c.ReadyFrames == 20 && c.GetFramePose(19).Num() > 0; }), "20 frames: %d",
              (int)c.ReadyFrames);
        // A stage without part texts is a plain segment.
        CHECK(c.PushStage(FFlameStage(FString(TEXT("a person jumps.")), 15)), "PushStage without parts");
        CHECK(TickUntil(c, [&] { return c.ReadyFrames == 35; }), "35 frames: %d", (int)c.ReadyFrames);
        c.StopStream();
    }
    const std::string fmg = Path("finemogen_tiny");
    if (!Exists(fmg)) {
        std::printf("skip FineMoGen stages: no %s\n", fmg.c_str());
        return;
    }
    UFlameStreamComponent c;
    Configure(c, fmg);
    c.Chunk = 0;
    c.Layout = 0;
    c.StepsPerTick = 100;
    CHECK(c.StartStream(), "StartStream (FineMoGen)");
    FFlameStage stage(FString(TEXT("a person walks forward.")), 30);
    stage.LeftArm = FString(TEXT("waves the left arm"));
    CHECK(c.PushStage(stage), "PushStage (FineMoGen)");
    CHECK(TickUntil(c, [&] { return c.ReadyFrames == 30 && c.GetFramePose(29).Num() > 0; }), "FineMoGen: %d frames, %s",
          (int)c.ReadyFrames, c.LastError.Utf8().c_str());
    CHECK(c.LastError.IsEmpty() && c.GetValuesPerFrame() == 263, "FineMoGen: %s", c.LastError.Utf8().c_str());
    // The frames of flame_stream_push_stage with the same texts.
    Direct d(fmg, 0);
    FlameStage raw;
    std::memset(&raw, 0, sizeof raw);
    raw.struct_size = sizeof raw;
    raw.frames = 30;
    raw.text = "a person walks forward.";
    raw.left_arm = "waves the left arm";
    CHECK(flame_stream_push_stage(d.stream, &raw) == FLAME_STATUS_OK, "direct push_stage: %s", flame_last_error());
    CHECK(d.pump(UINT32_MAX) == 30, "direct FineMoGen stream");
    CHECK(SameFrames(c, 0, 30, d.read(0, 30, FLAME_LAYOUT_FEATURES, 0)), "FineMoGen: flame_stream_push_stage's frames");
    c.StopStream();
}

static void TestErrors() {
    {
        UFlameStreamComponent c;
        Configure(c, "/nonexistent/model.safetensors");
        int started = 0;
        bool ok = true;
        c.OnStarted.AddLambda([&](bool b) { started++; ok = b; });
        CHECK(c.StartStream(), "StartStream");
        CHECK(c.PushSegmentFrames(FString(TEXT("a person walks.")), 10), "queued while loading");
        CHECK(TickUntil(c, [&] { return started > 0; }), "OnStarted");
        CHECK(!ok && !c.IsStreaming(), "OnStarted(false)");
        CHECK(c.LastError.Utf8().find("FLAME_STATUS_IO: cannot read /nonexistent/model.safetensors") == 0, "%s",
              c.LastError.Utf8().c_str());
    }
    {
        UFlameStreamComponent c;
        Configure(c, Path("mld_tiny"));
        int started = 0;
        bool ok = true;
        c.OnStarted.AddLambda([&](bool b) { started++; ok = b; });
        CHECK(c.StartStream(), "StartStream");
        CHECK(TickUntil(c, [&] { return started > 0; }), "OnStarted");
        CHECK(!ok && c.LastError.Utf8().find("FLAME_STATUS_INVALID_ARGUMENT") == 0 &&
                  c.LastError.Utf8().find("latent") != std::string::npos,
              "a latent model: %s", c.LastError.Utf8().c_str());
    }
    {   // Settings libflame refuses.
        UFlameStreamComponent c;
        Configure(c, Path("flame_tiny"));
        c.Overlap = 40;
        bool ok = true;
        c.OnStarted.AddLambda([&](bool b) { ok = b; });
        CHECK(c.StartStream(), "StartStream");
        CHECK(TickUntil(c, [&] { return !c.IsStreaming(); }), "stopped");
        CHECK(!ok && c.LastError.Utf8().find("overlap") != std::string::npos, "%s", c.LastError.Utf8().c_str());
    }
}

/* StopStream while a long pump runs: it cancels it; BeginPlay starts the stream (bAutoStart),
 * reusing the loaded model after a restart. */
static void TestStop() {
    UFlameStreamComponent c;
    Configure(c, Path("flame_tiny"));
    c.Steps = 20;
    c.Chunk = 200;
    c.Lookahead = 100000000;
    c.Window = 100000000;
    c.StepsPerTick = 100000000;
    c.bAutoStart = true;
    c.BeginPlay();
    CHECK(c.IsStreaming(), "BeginPlay started the stream");
    // Many hours of motion: one pump would take far longer than the test.
    bool pushed = true;
    for (int i = 0; i < 100; i++) {
        pushed = pushed && c.PushSegmentFrames(FString(TEXT("a person walks forward.")), 1000000);
    }
    CHECK(pushed, "push");
    // Let the pump with the segments get going (the first may have come before them), then stop.
    CHECK(TickUntil(c, [&] { return c.Fps > 0.f; }), "loaded");
    for (int i = 0; i < 10; i++) {
        Tick(c, 0.f);
        std::this_thread::sleep_for(std::chrono::milliseconds(2));
    }
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    const auto t0 = std::chrono::steady_clock::now();
    c.StopStream();
    CHECK(!c.IsStreaming(), "stopped");
    CHECK(WaitForThreads(10), "the pump's thread exits soon after the cancel");
    const double secs = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    std::printf("stream component: the cancelled pump ended %.1f ms after StopStream\n", secs * 1e3);
    CHECK(FFlameModule::ActiveWorkers.GetValue() == 0, "no stream left: %d", FFlameModule::ActiveWorkers.GetValue());
    // Started again: a fresh stream of the same model.
    c.Steps = 3;
    c.Chunk = 40;
    c.StepsPerTick = 100;
    c.BeginPlay();
    CHECK(c.IsStreaming() && c.CurrentFrame == -1 && c.ReadyFrames == 0 && c.StepsTotal == 0, "restarted afresh");
    CHECK(c.PushSegmentFrames(FString(TEXT("a person walks forward.")), 30), "push");
    CHECK(TickUntil(c, [&] { return c.ReadyFrames == 30 && c.Pose.Num() > 0; }), "generated after a restart");
    c.EndPlay(EEndPlayReason::Quit);
}

/* ---- retarget ------------------------------------------------------------------------------- */

/* RetargetMesh: every frame received, put onto a Mannequin-named skeleton, is
 * flame_retarget_read_stream's on a stream driven the same way, bit for bit; the mesh holds the
 * frame under the playhead. */
static void TestRetarget() {
    const std::string model = Path("flame_tiny");
    USkinnedAsset asset;
    Mannequin(asset);
    const int bones = asset.RefSkeleton.GetNum();
    Direct d(model);
    d.push("a person walks forward.", 50);
    d.push("a person waves.", 25);
    d.push("a person sits down.", 40);
    CHECK(d.pump(UINT32_MAX) == (uint64_t)kTimeline, "direct stream");
    FlameRetarget* r = SkeletonRetarget(d.model, asset);
    std::vector<float> rot((size_t)kTimeline * bones * 4), tr((size_t)kTimeline * bones * 3);
    CHECK(r != nullptr && flame_retarget_read_stream(r, d.stream, 0, (uint32_t)kTimeline, nullptr, rot.data(), rot.size(), tr.data(),
                                                     tr.size()) == FLAME_STATUS_OK,
          "direct retarget: %s", flame_last_error());
    flame_retarget_free(r);

    UPoseableMeshComponent mesh;
    mesh.Asset = &asset;
    mesh.BoneSpaceTransforms.SetNum(bones);
    UFlameStreamComponent c;
    Configure(c, model);
    c.StepsPerTick = 2;
    c.RetargetMesh = &mesh;
    CHECK(c.StartStream(), "StartStream: %s", c.LastError.Utf8().c_str());
    CHECK(c.PushSegmentFrames(FString(TEXT("a person walks forward.")), 50) &&
              c.PushSegmentFrames(FString(TEXT("a person waves.")), 25) &&
              c.PushSegmentFrames(FString(TEXT("a person sits down.")), 40),
          "push");
    CHECK(TickUntil(c, [&] { return c.ReadyFrames == kTimeline && c.GetFramePose(kTimeline - 1).Num() > 0; }),
          "all frames (%d): %s", (int)c.ReadyFrames, c.LastError.Utf8().c_str());
    CHECK(c.RigBoneNames.Num() == bones, "RigBoneNames");
    bool same = true;
    for (int64 f = 0; same && f < kTimeline; f++)
        for (int b = 0; same && b < bones; b++) {
            const FQuat q = c.GetBoneRotationAt(f, b);
            const FVector v = c.GetBoneTranslationAt(f, b);
            const float* w = rot.data() + (f * bones + b) * 4;
            const float* t = tr.data() + (f * bones + b) * 3;
            same = (float)q.X == w[0] && (float)q.Y == w[1] && (float)q.Z == w[2] && (float)q.W == w[3] && (float)v.X == t[0] &&
                   (float)v.Y == t[1] && (float)v.Z == t[2];
            if (!same) std::fprintf(stderr, "     frame %d bone %d differs\n", (int)f, b);
        }
    CHECK(same, "every frame's retarget = flame_retarget_read_stream's, bit for bit");
    // 0.5 s at 20 fps: frame 10 in BoneRotations and on the mesh.
    Tick(c, 0.5f);
    bool posed = c.CurrentFrame == 10 && c.BoneRotations.Num() == bones * 4 && mesh.RefreshCount > 0;
    for (int b = 0; posed && b < bones; b++) {
        const FTransform& t = mesh.BoneSpaceTransforms[b];
        const float* w = rot.data() + (10 * bones + b) * 4;
        posed = (float)t.Rotation.X == w[0] && (float)t.Rotation.W == w[3] && c.BoneRotations[b * 4 + 3] == w[3] &&
                (float)t.Translation.Z == tr[(size_t)(10 * bones + b) * 3 + 2];
    }
    CHECK(posed, "frame %d on the mesh and in BoneRotations", (int)c.CurrentFrame);
    c.StopStream();
    // A bone map naming a bone the mesh lacks fails the start, the bone named.
    c.BoneMapJson = FString(TEXT("{\"head\": \"head_x\"}"));
    int started = 0;
    bool ok = true;
    c.OnStarted.AddLambda([&](bool s) { started++; ok = s; });
    CHECK(c.StartStream(), "StartStream (bad map)");
    CHECK(TickUntil(c, [&] { return started > 0; }), "OnStarted (bad map)");
    CHECK(!ok && c.LastError.Utf8().find("head_x") != std::string::npos && !c.IsStreaming(), "bad map: %s", c.LastError.Utf8().c_str());
    UPoseableMeshComponent empty;
    c.RetargetMesh = &empty;
    CHECK(!c.StartStream() && c.LastError.Utf8().find("no skeletal mesh") != std::string::npos, "%s", c.LastError.Utf8().c_str());
}

/* ---- cleanup -------------------------------------------------------------------------------- */

/* At 30 fps the 115 frames at 20 fps are 172 cleaned frames (the last frame's time kept), as in
 * the Python, C# and C++ bindings' tests. */
static const int64 kCleaned30 = 172;

/* The timeline pushed straight into a Direct stream. */
static void DirectTimeline(Direct& d) {
    d.push("a person walks forward.", 50);
    d.push("a person waves.", 25);
    d.push("a person sits down.", 40);
}

static bool Logged(const std::string& text) {
    for (const std::string& line : UeStubLogLines())
        if (line.find(text) != std::string::npos) return true;
    return false;
}

/* Feet free (contacts and the floor only): frames settle a few frames behind the generated
 * ones and arrive as they do; at 30 fps; a second cleanup refused; EndTimeline settles the
 * last frames. */
static void TestCleanedAsTheySettle() {
    const std::string model = Path("flame_tiny");
    FlameCleanupParams cleanup;
    flame_cleanup_params_default(&cleanup);
    cleanup.feet = FLAME_FEET_OFF;
    cleanup.fps = 30.f;
    // The independent path: the same stream through flame.h, generated whole, read before and
    // after flame_stream_close.
    Direct d(model);
    DirectTimeline(d);
    CHECK(d.pump(UINT32_MAX) == (uint64_t)kTimeline, "direct stream");
    const int64 open = d.settled(FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL, cleanup);
    CHECK(open > 0 && open < kCleaned30, "direct: %d cleaned frames settle before the timeline ends", (int)open);
    const std::vector<float> quatsOpen =
        d.read_cleaned(0, (uint32_t)open, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL, cleanup);
    CHECK(flame_stream_close(d.stream) == FLAME_STATUS_OK, "direct close");
    d.pump(UINT32_MAX);
    CHECK(d.settled(FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL, cleanup) == kCleaned30, "direct: 172 after close");
    const std::vector<float> quats =
        d.read_cleaned(0, kCleaned30, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL, cleanup);
    const std::vector<float> roots =
        d.read_cleaned(0, kCleaned30, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_UNREAL, cleanup);
    CHECK(quats.size() == (size_t)kCleaned30 * 96 && roots.size() == (size_t)kCleaned30 * 3, "direct cleaned reads");

    UFlameStreamComponent c;
    // The cleanup settings: UFlameMotionComponent's names and defaults, and off.
    CHECK(!c.bCleanup && c.bLockFeet && c.bGround && c.FrameRate == 0.f && c.RootMotion == EFlameRootMotion::Keep &&
              !c.bRemoveYaw,
          "cleanup defaults");
    Configure(c, model);
    c.bCleanup = true;
    c.bLockFeet = false;
    c.FrameRate = 30.f;
    c.StepsPerTick = 1;
    CHECK(c.StartStream(), "StartStream: %s", c.LastError.Utf8().c_str());
    CHECK(c.PushSegmentFrames(FString(TEXT("a person walks forward.")), 50) &&
              c.PushSegment(FString(TEXT("a person waves.")), 1.25f) &&
              c.PushSegmentFrames(FString(TEXT("a person sits down.")), 40),
          "push: %s", c.LastError.Utf8().c_str());
    // The frames come over several pumps, as they settle.
    int arrivals = 0;
    int64 seen = 0;
    CHECK(TickUntil(c, [&] {
              if (c.ReadyFrames > seen) {
                  arrivals++;
                  seen = c.ReadyFrames;
              }
              return c.StepsTotal == 15 && c.bStarving && c.ReadyFrames == open && c.GetFramePose(open - 1).Num() > 0;
          }),
          "%d settled frames (%d ready, %d generated, %d steps): %s", (int)open, (int)c.ReadyFrames, (int)c.GeneratedFrames,
          (int)c.StepsTotal, c.LastError.Utf8().c_str());
    CHECK(arrivals >= 3, "frames arrived in %d pumps", arrivals);
    CHECK(c.Fps == 20.f && c.PoseFrameRate == 30.f && c.GeneratedFrames == kTimeline, "fps %f, Pose at %f, %d generated",
          (double)c.Fps, (double)c.PoseFrameRate, (int)c.GeneratedFrames);
    CHECK(c.LastError.IsEmpty(), "frames not settled yet are no error: %s", c.LastError.Utf8().c_str());
    CHECK(SameFrames(c, 0, open, quatsOpen), "the settled frames = flame_stream_read_cleaned's, bit for bit");
    CHECK(c.GetFramePose(open).Num() == 0, "no frame past the settled ones");
    // The playhead counts cleaned frames at 30 a second.
    CHECK(c.CurrentFrame == 0 && c.Pose.Num() == 96 && std::memcmp(c.Pose.GetData(), quats.data(), 96 * 4) == 0,
          "Pose = cleaned frame 0 (frame %d)", (int)c.CurrentFrame);
    Tick(c, 0.1f);
    CHECK(c.CurrentFrame == 3 && std::memcmp(c.Pose.GetData(), quats.data() + 3 * 96, 96 * 4) == 0,
          "0.1 s: cleaned frame 3 (%d)", (int)c.CurrentFrame);
    CHECK((float)c.RootLocation.X == roots[9] && (float)c.RootLocation.Y == roots[10] && (float)c.RootLocation.Z == roots[11],
          "RootLocation = the cleaned root's");
    Tick(c, 1.f);
    CHECK(c.CurrentFrame == 33, "1.1 s: cleaned frame 33 (%d)", (int)c.CurrentFrame);

    // Another cleanup: refused by the stream, the frames go on with the first. The playhead
    // moves (a pump every tick), so a report repeated by every pump would show.
    c.FrameRate = 60.f;
    CHECK(TickUntil(c, [&] { return !c.LastError.IsEmpty(); }, 0.02f), "a changed cleanup reports");
    const std::string refused = c.LastError.Utf8();
    CHECK(refused.find("FLAME_STATUS_WRONG_STATE") == 0 && refused.find("set once") != std::string::npos &&
              refused.find("StopStream and StartStream") != std::string::npos,
          "refused: %s", refused.c_str());
    CHECK(Logged("stream: FLAME_STATUS_WRONG_STATE"), "and logged");
    c.LastError.Reset();
    const int64 before = c.CurrentFrame;
    for (int i = 0; i < 20; i++) {
        Tick(c, 0.02f);
        std::this_thread::sleep_for(std::chrono::milliseconds(3));
    }
    CHECK(c.CurrentFrame > before && c.CurrentFrame < open - 1, "the playhead moved: %d to %d", (int)before, (int)c.CurrentFrame);
    CHECK(c.LastError.IsEmpty() && c.PoseFrameRate == 30.f, "reported once; still 30 fps: %s", c.LastError.Utf8().c_str());
    CHECK(SameFrames(c, 0, open, quatsOpen), "the frames still the first cleanup's");
    c.FrameRate = 1000.f; // not a cleanup at all
    CHECK(TickUntil(c, [&] { return !c.LastError.IsEmpty(); }) &&
              c.LastError.Utf8().find("FLAME_STATUS_INVALID_ARGUMENT") == 0 &&
              c.LastError.Utf8().find("frame rate") != std::string::npos,
          "a bad frame rate refused: %s", c.LastError.Utf8().c_str());
    c.FrameRate = 30.f; // the stream's again
    c.LastError.Reset();
    Tick(c, 100.f);
    CHECK(c.CurrentFrame == open - 1 && c.bWaitingForFrames, "held at the last settled frame: %d", (int)c.CurrentFrame);

    // EndTimeline: the last frames settle; the timeline takes no more segments.
    CHECK(c.EndTimeline() && c.bTimelineEnded, "EndTimeline");
    CHECK(TickUntil(c, [&] { return c.ReadyFrames == kCleaned30 && c.GetFramePose(kCleaned30 - 1).Num() > 0; }),
          "172 cleaned frames after EndTimeline: %d", (int)c.ReadyFrames);
    CHECK(c.GetFramePose(kCleaned30).Num() == 0 && c.GeneratedFrames == kTimeline, "172, no more");
    CHECK(SameFrames(c, 0, kCleaned30, quats), "all 172 = one flame_stream_read_cleaned after close, bit for bit");
    CHECK(SameRoots(c, 0, kCleaned30, roots), "the cleaned root locations");
    CHECK(c.GetRootBoneLocationAt(5).X == 0 && c.RootBoneLocation.X == 0, "no root bone without Separate");
    CHECK(c.LastError.IsEmpty(), "no error: %s", c.LastError.Utf8().c_str());
    CHECK(TickUntil(c, [&] { return c.CurrentFrame == kCleaned30 - 1; }, 0.05f), "the playhead reaches frame 171: %d",
          (int)c.CurrentFrame);
    CHECK(!c.PushSegmentFrames(FString(TEXT("a person jumps.")), 10) &&
              c.LastError.Utf8().find("the timeline was ended") == 0,
          "a push after EndTimeline: %s", c.LastError.Utf8().c_str());
    c.StopStream();
}

/* Locked feet (libflame's defaults) on the tiny model: no frame settles until the timeline
 * ends, yet the stream generates all of it past a Lookahead of 40 frames; EndTimeline brings
 * the 172 frames at 30 fps. The Python test's cleanup: separate root motion, world positions
 * in glTF's convention. */
static void TestCleanedFeetLocked() {
    const std::string model = Path("flame_tiny");
    FlameCleanupParams cleanup;
    flame_cleanup_params_default(&cleanup);
    cleanup.fps = 30.f;
    cleanup.root_motion = FLAME_ROOT_MOTION_SEPARATE;
    Direct d(model);
    DirectTimeline(d);
    CHECK(d.pump(UINT32_MAX) == (uint64_t)kTimeline, "direct stream");
    CHECK(d.settled(FLAME_LAYOUT_GLOBAL_POSITIONS, FLAME_CONVENTION_GLTF, cleanup) == 0, "direct: nothing settles while open");
    CHECK(flame_stream_close(d.stream) == FLAME_STATUS_OK, "direct close");
    d.pump(UINT32_MAX);
    const std::vector<float> positions =
        d.read_cleaned(0, kCleaned30, FLAME_LAYOUT_GLOBAL_POSITIONS, FLAME_CONVENTION_GLTF, cleanup);
    const std::vector<float> roots = d.read_cleaned(0, kCleaned30, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_GLTF, cleanup);
    const std::vector<float> bones = d.read_cleaned(0, kCleaned30, FLAME_LAYOUT_ROOT_BONE, FLAME_CONVENTION_GLTF, cleanup);
    CHECK(positions.size() == (size_t)kCleaned30 * 72 && bones.size() == (size_t)kCleaned30 * 3, "direct cleaned reads");

    UFlameStreamComponent c;
    Configure(c, model);
    c.Lookahead = 40;
    c.Layout = FLAME_LAYOUT_GLOBAL_POSITIONS;
    c.Convention = FLAME_CONVENTION_GLTF;
    c.bCleanup = true;
    c.FrameRate = 30.f;
    c.RootMotion = EFlameRootMotion::Separate;
    c.StepsPerTick = 100;
    CHECK(c.StartStream(), "StartStream");
    CHECK(c.PushSegmentFrames(FString(TEXT("a person walks forward.")), 50) &&
              c.PushSegmentFrames(FString(TEXT("a person waves.")), 25) &&
              c.PushSegmentFrames(FString(TEXT("a person sits down.")), 40),
          "push");
    CHECK(TickUntil(c, [&] { return c.GeneratedFrames == kTimeline && c.bStarving; }, 0.05f),
          "the whole timeline generated past Lookahead while nothing settles (%d generated)", (int)c.GeneratedFrames);
    CHECK(c.StepsTotal == 15 && c.ReadyFrames == 0 && c.CurrentFrame == -1 && c.Pose.Num() == 0 && !c.bWaitingForFrames,
          "nothing published yet: %d ready, frame %d", (int)c.ReadyFrames, (int)c.CurrentFrame);
    CHECK(c.LastError.IsEmpty(), "waiting is no error: %s", c.LastError.Utf8().c_str());
    CHECK(c.EndTimeline(), "EndTimeline");
    CHECK(TickUntil(c, [&] { return c.ReadyFrames == kCleaned30 && c.GetFramePose(kCleaned30 - 1).Num() > 0; }),
          "the 172 frames after EndTimeline: %d", (int)c.ReadyFrames);
    CHECK(c.GetValuesPerFrame() == 72 && SameFrames(c, 0, kCleaned30, positions),
          "positions = flame_stream_read_cleaned's, bit for bit");
    CHECK(SameRoots(c, 0, kCleaned30, roots) && SameRootBones(c, 0, kCleaned30, bones), "root and root bone");
    bool ground = true;
    for (int64 f = 0; f < kCleaned30; f++) ground = ground && c.GetRootBoneLocationAt(f).Y == 0;
    CHECK(ground, "the root bone on the ground (glTF: Y up)");
    const FVector bone = c.RootBoneLocation;
    CHECK(c.CurrentFrame == 0 && (float)bone.X == bones[0] && (float)bone.Y == bones[1] && (float)bone.Z == bones[2],
          "RootBoneLocation of frame %d", (int)c.CurrentFrame);
    CHECK(c.LastError.IsEmpty(), "no error: %s", c.LastError.Utf8().c_str());
    c.StopStream();
}

/* A cleanup libflame refuses fails the start; a stream refuses a loop wrap (so the component
 * has no wrap setting); Layout 0 stays raw; EndTimeline needs a stream. */
static void TestCleanupRefusals() {
    const std::string model = Path("flame_tiny");
    {
        UFlameStreamComponent c;
        Configure(c, model);
        c.bCleanup = true;
        c.FrameRate = 1000.f;
        bool ok = true;
        int started = 0;
        c.OnStarted.AddLambda([&](bool b) { started++; ok = b; });
        CHECK(c.StartStream(), "StartStream");
        CHECK(TickUntil(c, [&] { return started > 0; }), "OnStarted");
        CHECK(!ok && !c.IsStreaming() && c.LastError.Utf8().find("FLAME_STATUS_INVALID_ARGUMENT") == 0 &&
                  c.LastError.Utf8().find("frame rate") != std::string::npos,
              "a frame rate of 1000: %s", c.LastError.Utf8().c_str());
    }
    {
        Direct d(model);
        FlameCleanupParams wrap;
        flame_cleanup_params_default(&wrap);
        wrap.wrap = 1;
        size_t n = 0;
        const FlameStatus st =
            flame_stream_read_cleaned(d.stream, 0, 1, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL, &wrap, nullptr, 0, &n);
        CHECK(st == FLAME_STATUS_INVALID_ARGUMENT && std::string(flame_last_error()).find("cannot wrap") != std::string::npos,
              "a stream refuses a wrap: %d %s", (int)st, flame_last_error());
    }
    {
        UFlameStreamComponent c;
        CHECK(!c.EndTimeline() && c.LastError.Utf8().find("the stream is not running") == 0, "EndTimeline before StartStream");
        Configure(c, model);
        c.Layout = FLAME_LAYOUT_FEATURES;
        c.bCleanup = true;
        c.FrameRate = 30.f;
        c.StepsPerTick = 100;
        CHECK(c.StartStream(), "StartStream");
        CHECK(c.PushSegmentFrames(FString(TEXT("a person walks forward.")), 40), "push");
        CHECK(TickUntil(c, [&] { return c.ReadyFrames == 40 && c.GetFramePose(39).Num() > 0; }), "40 raw frames: %d",
              (int)c.ReadyFrames);
        Direct d(model);
        d.push("a person walks forward.", 40);
        d.pump(UINT32_MAX);
        CHECK(c.PoseFrameRate == 20.f && SameFrames(c, 0, 40, d.read(0, 40, FLAME_LAYOUT_FEATURES, 0)),
              "Layout 0: the raw features at the model's rate (%f)", (double)c.PoseFrameRate);
        c.StopStream();
    }
}

int main(int argc, char** argv) {
    if (argc != 2) {
        std::fprintf(stderr, "usage: test_stream_component FIXTURES_DIR\n");
        return 2;
    }
    g_dir = argv[1];
    FFlameModule& module = FFlameModule::Get();
    module.StartupModule();
    CHECK(module.IsAvailable(), "module unavailable");

    TestPlayback();
    CHECK(WaitForThreads(), "pumps exited");
    TestBudget();
    CHECK(WaitForThreads(), "pumps exited");
    TestWindow();
    CHECK(WaitForThreads(), "pumps exited");
    TestInterrupt();
    CHECK(WaitForThreads(), "pumps exited");
    TestStages();
    CHECK(WaitForThreads(), "pumps exited");
    TestErrors();
    CHECK(WaitForThreads(), "pumps exited");
    TestStop();
    CHECK(WaitForThreads(), "pumps exited");
    TestCleanedAsTheySettle();
    CHECK(WaitForThreads(), "pumps exited");
    TestCleanedFeetLocked();
    CHECK(WaitForThreads(), "pumps exited");
    TestCleanupRefusals();
    CHECK(WaitForThreads(), "pumps exited");
    TestRetarget();
    CHECK(WaitForThreads(), "pumps exited");
    CHECK(FFlameModule::ActiveWorkers.GetValue() == 0, "nothing of libflame left: %d", FFlameModule::ActiveWorkers.GetValue());
    module.ShutdownModule();

    std::printf("%d passed, %d failed\n", passed, failed);
    return failed == 0 ? 0 : 1;
}
