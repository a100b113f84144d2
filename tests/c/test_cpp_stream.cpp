// flame::Stream of the C++17 wrapper (bindings/cpp/flame.hpp): continuous motion from a timeline
// of prompts over flame_stream_*.
//
// - move-only ownership, StreamParams' defaults, a stream outliving its Model object, a
//   moved-from stream throwing INVALID_ARGUMENT;
// - push / pump / status / read on the FLAME (smpl24_6d) and MDM (humanml263) fixtures: the
//   features equal, bit for bit, those of the same stream driven through the C API, and those
//   of a stream pumped one step per call on one thread equal those of one pumped all at once
//   on two; a sub-range read equals the same frames of a whole read; every layout's length;
//   the buffer overload and its BUFFER_TOO_SMALL;
// - frames not generated yet throw WRONG_STATE, dropped frames INVALID_ARGUMENT naming the
//   window, a playhead past the frames ready, zero-frame segments and NUL bytes INVALID_ARGUMENT;
// - interrupt, between chunks and with a chunk in flight;
// - cancel(): raised between pumps it cancels the next step; from another std::thread during a
//   pump, that pump throws CANCELLED; pumping again gives the bits of a stream never cancelled;
// - push_stage / interrupt_stage: a stage without part texts is push / interrupt; part texts
//   are refused on FLAME (INVALID_ARGUMENT: only FineMoGen reads them) and composed on
//   FineMoGen;
// - a latent model that cannot continue a motion (MLD): INVALID_ARGUMENT at construction;
// - end_timeline_looped (tests/c/test_stream.c's loop): 120 frames, the first 100 those of
//   end_timeline()'s stream and of the C API's flame_stream_close_looped bit for bit, all 120
//   settled for cleaned reads; a 12-frame bridge and a latent model (mola_tiny) throw
//   INVALID_ARGUMENT naming them, a second close and an empty timeline WRONG_STATE.
//
// usage: test_cpp_stream FIXTURES_DIR   (tests/fixtures; FLAME_TEST_QUICK=1: shorter timelines
// for valgrind)

#include <atomic>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <string>
#include <thread>
#include <type_traits>
#include <utility>
#include <vector>

#include "flame.hpp"

#include "check.h"
#include "util.h"

static_assert(!std::is_copy_constructible<flame::Stream>::value, "Stream is move-only");
static_assert(!std::is_copy_assignable<flame::Stream>::value, "Stream is move-only");
static_assert(std::is_nothrow_move_constructible<flame::Stream>::value, "");
static_assert(std::is_nothrow_move_assignable<flame::Stream>::value, "");
static_assert(std::is_nothrow_default_constructible<flame::Stream>::value, "");

// `expr` must throw flame::Error with `status` and a message containing `needle`.
#define CHECK_THROWS(expr, want, needle)                                                          \
    do {                                                                                          \
        bool thrown_ = false;                                                                     \
        try {                                                                                     \
            (void)(expr);                                                                         \
        } catch (const flame::Error &e_) {                                                        \
            thrown_ = true;                                                                       \
            bool ok_ = e_.status() == (want) && e_.message().find(needle) != std::string::npos && \
                       std::string(e_.what()).find(flame_status_string(want)) == 0;               \
            std::string what_ = std::string(#expr " throws " #want " about ") + (needle);         \
            check_record(ok_, __FILE__, __LINE__, what_.c_str(), e_.what());                      \
        }                                                                                         \
        if (!thrown_) {                                                                           \
            check_record(0, __FILE__, __LINE__, #expr " throws flame::Error", "");                \
        }                                                                                         \
    } while (0)

static std::string g_dir;
static bool g_quick = false;

static flame::Model load(const char *name) {
    flame::ModelParams mp;
    mp.threads = 1;
    return flame::Model::load(g_dir + "/" + name + ".safetensors", mp);
}

// The settings of tests/c/test_stream.c (and tests/stream.rs): chunks of 40 frames keeping 10,
// 3 DDIM steps, seed 5.
static flame::StreamParams small_params(uint32_t threads) {
    flame::StreamParams p;
    p.chunk = 40;
    p.overlap = 10;
    p.lookahead = 1000;
    p.window = 10000;
    p.steps = 3;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.seed = 5;
    p.threads = threads;
    return p;
}

// 50 + 25 + 40 = 115 frames: chunks of 40 + 10, 25, 30 + 10 new frames (five of 3 steps).
static const uint32_t kTimeline = 115;
static void timeline(flame::Stream &s) {
    s.push("a person walks forward.", 50);
    s.push("a person waves.", 25);
    s.push("a person sits down.", 40);
}

// Pumps `per_call` steps at a time until a pump runs none; returns the pumps.
static int run(flame::Stream &s, uint32_t per_call) {
    int calls = 0;
    for (;;) {
        flame::StreamStatus st = s.pump(per_call);
        calls++;
        if (st.steps == 0 || calls > 100000) {
            return calls;
        }
    }
}

static bool same(const std::vector<float> &a, const std::vector<float> &b) {
    return same_bits(a.data(), a.size(), b.data(), b.size());
}

static bool finite(const std::vector<float> &v) {
    for (float x : v) {
        if (!std::isfinite(x)) {
            return false;
        }
    }
    return !v.empty();
}

// ---- defaults and ownership -------------------------------------------------------------

static void test_defaults() {
    flame::StreamParams p;
    CHECK(p.struct_size == sizeof(FlameStreamParams));
    CHECK(p.chunk == 0 && p.overlap == 20 && p.lookahead == 60 && p.window == 1200);
    CHECK(p.steps == 0 && p.sampler == FLAME_SAMPLER_DEFAULT && p.guidance < 0);
    CHECK(p.seed == 0 && p.threads == 0);

    flame::Stream empty;
    CHECK(!empty && empty.get() == nullptr);
    CHECK_THROWS(empty.status(), FLAME_STATUS_INVALID_ARGUMENT, "`stream` is NULL");
    CHECK_THROWS(empty.push("a person walks.", 10), FLAME_STATUS_INVALID_ARGUMENT,
                 "`stream` is NULL");

    flame::Stream s;
    {
        flame::Model model = load("flame_tiny");
        flame::StreamParams d;  // the defaults, but few steps
        d.steps = 3;
        d.sampler = FLAME_SAMPLER_DDIM;
        d.threads = 1;
        s = model.stream(d);
        flame::Stream t(model);  // every default
        CHECK(static_cast<bool>(t));
    }
    // The model object is gone; the stream keeps the model alive.
    CHECK(static_cast<bool>(s));
    flame::StreamStatus st = s.status();
    CHECK(st.steps == 0 && st.ready == 0 && st.first_frame == 0 && st.playhead == 0);
    CHECK(st.starving);
    CHECK_THROWS(s.read(0, 1), FLAME_STATUS_WRONG_STATE, "not generated yet");
    s.push("a person walks forward.", 30);
    st = s.pump(flame::Stream::all_steps);
    CHECK(st.steps > 0 && st.ready == 30 && st.starving);
    CHECK(s.read(0, 30).size() == 30u * FLAME_TINY_DIM);

    // Moves: the handle goes with the object; the moved-from one is empty.
    FlameStream *raw = s.get();
    flame::Stream moved(std::move(s));
    CHECK(moved.get() == raw && !s);
    CHECK_THROWS(s.pump(1), FLAME_STATUS_INVALID_ARGUMENT, "`stream` is NULL");
    CHECK_THROWS(s.read(0, 1), FLAME_STATUS_INVALID_ARGUMENT, "`stream` is NULL");
    CHECK_THROWS(s.cancel(), FLAME_STATUS_INVALID_ARGUMENT, "`stream` is NULL");
    CHECK(moved.status().ready == 30);
    flame::Stream other;
    other = std::move(moved);
    CHECK(other.get() == raw && !moved);
    CHECK(other.read(29, 1).size() == FLAME_TINY_DIM);
}

// ---- push, pump, read ---------------------------------------------------------------------

// The same timeline through the C API, pumped all at once: its features.
static std::vector<float> c_api_features(const flame::Model &m, const flame::StreamParams &p) {
    std::vector<float> out;
    FlameStream *s = nullptr;
    if (!CHECK_OK(flame_stream_new(m.get(), &p, &s))) {
        return out;
    }
    CHECK_OK(flame_stream_push(s, "a person walks forward.", 50));
    CHECK_OK(flame_stream_push(s, "a person waves.", 25));
    CHECK_OK(flame_stream_push(s, "a person sits down.", 40));
    CHECK_OK(flame_stream_pump(s, UINT32_MAX, nullptr));
    size_t need = 0;
    CHECK_OK(flame_stream_read(s, 0, kTimeline, FLAME_LAYOUT_FEATURES, 0, 0, nullptr, 0, &need));
    out.resize(need);
    CHECK_OK(flame_stream_read(s, 0, kTimeline, FLAME_LAYOUT_FEATURES, 0, 0, out.data(), need,
                               &need));
    flame_stream_free(s);
    return out;
}

static void test_round_trip(const char *name) {
    flame::Model m = load(name);
    const flame::ModelInfo info = m.info();
    const uint32_t dim = info.feature_dim, joints = info.joint_count;

    flame::Stream a(m, small_params(1));
    timeline(a);
    CHECK(run(a, 1) == 16);  // 15 steps, then one pump that runs none
    flame::StreamStatus st = a.status();
    CHECK(st.steps == 0 && st.ready == kTimeline && st.first_frame == 0 && st.playhead == 0);
    CHECK(st.starving);  // fewer than 1000 frames ahead and nothing left

    flame::Stream b = m.stream(small_params(2));
    timeline(b);
    st = b.pump(flame::Stream::all_steps);
    CHECK(st.steps == 15 && st.ready == kTimeline && st.starving);

    // Determinism: the pump pattern and the threads change nothing; neither does the wrapper.
    const std::vector<float> fa = a.read(0, kTimeline);
    const std::vector<float> fb = b.read(0, kTimeline);
    CHECK(fa.size() == static_cast<std::size_t>(kTimeline) * dim);
    CHECK(same(fa, fb));
    CHECK(finite(fa));
    CHECK(same(fa, c_api_features(m, small_params(1))));
    if (!same(fa, fb)) {
        std::fprintf(stderr, "     (%s)\n", name);
    }

    // A sub-range is the same frames of the whole (features and decoded poses).
    const std::vector<float> sub = a.read(30, 20);
    CHECK(sub.size() == 20u * dim &&
          std::memcmp(sub.data(), fa.data() + 30u * dim, sub.size() * sizeof(float)) == 0);
    const std::vector<float> root =
        a.read(0, kTimeline, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_GLTF);
    const std::vector<float> tail =
        a.read(70, 45, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_GLTF);
    CHECK(root.size() == kTimeline * 3u && finite(root));
    CHECK(tail.size() == 45u * 3 && root.size() == kTimeline * 3u &&
          std::memcmp(tail.data(), root.data() + 70 * 3, tail.size() * sizeof(float)) == 0);

    // Every layout's length, and a read in it of that length.
    const struct {
        FlameLayout layout;
        std::size_t per_frame;
    } layouts[] = {
        {FLAME_LAYOUT_FEATURES, dim},
        {FLAME_LAYOUT_ROOT_TRANSLATION, 3},
        {FLAME_LAYOUT_LOCAL_QUAT_XYZW, joints * 4u},
        {FLAME_LAYOUT_LOCAL_QUAT_WXYZ, joints * 4u},
        {FLAME_LAYOUT_LOCAL_MATRIX, joints * 9u},
        {FLAME_LAYOUT_LOCAL6D, joints * 6u},
        {FLAME_LAYOUT_GLOBAL_POSITIONS, joints * 3u},
        {FLAME_LAYOUT_GLOBAL_QUAT_XYZW, joints * 4u},
        {FLAME_LAYOUT_GLOBAL_QUAT_WXYZ, joints * 4u},
    };
    bool lengths = true;
    for (const auto &l : layouts) {
        lengths = lengths && b.read_len(5, 7, l.layout, FLAME_CONVENTION_UNITY) == 7 * l.per_frame &&
                  b.read(5, 7, l.layout, FLAME_CONVENTION_UNITY).size() == 7 * l.per_frame;
    }
    CHECK(lengths);
    // Quaternions read one frame at a time are those of one read of every frame (the tracks
    // keep their signs over the whole timeline).
    {
        const std::vector<float> all =
            a.read(0, kTimeline, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNITY);
        std::vector<float> frames;
        for (uint32_t f = 0; f < kTimeline; ++f) {
            const std::vector<float> one =
                a.read(f, 1, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNITY);
            frames.insert(frames.end(), one.begin(), one.end());
        }
        CHECK(all.size() == kTimeline * joints * 4u && same(frames, all));
    }
    // The layout's values, converted: the same as the C call gives.
    {
        const std::vector<float> quats =
            b.read(5, 7, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNREAL);
        std::vector<float> direct(quats.size() + 1);
        size_t n = 0;
        CHECK_OK(flame_stream_read(b.get(), 5, 7, FLAME_LAYOUT_LOCAL_QUAT_XYZW,
                                   FLAME_CONVENTION_UNREAL, 0, direct.data(), direct.size(), &n));
        direct.resize(n);
        CHECK(same(quats, direct));
    }
    // Foot contacts: humanml263's own, smpl24_6d's detected; 4 per frame either way.
    CHECK(b.read(0, 3, FLAME_LAYOUT_FOOT_CONTACTS).size() == 12);
    CHECK(b.read(10, 0, FLAME_LAYOUT_GLOBAL_POSITIONS).empty());  // zero frames: nothing

    // The buffer overload and its length protocol.
    const std::size_t need = b.read_len(2, 6, FLAME_LAYOUT_GLOBAL_POSITIONS);
    CHECK(need == 6u * joints * 3);
    std::vector<float> buf(need + 8, -7.0f);
    CHECK_THROWS(b.read(buf.data(), need - 1, 2, 6, FLAME_LAYOUT_GLOBAL_POSITIONS),
                 FLAME_STATUS_BUFFER_TOO_SMALL, "floats");
    bool untouched = true;
    for (float x : buf) {
        untouched = untouched && x == -7.0f;
    }
    CHECK(untouched);
    CHECK(b.read(buf.data(), buf.size(), 2, 6, FLAME_LAYOUT_GLOBAL_POSITIONS) == need);
    const std::vector<float> whole = b.read(2, 6, FLAME_LAYOUT_GLOBAL_POSITIONS);
    CHECK(std::memcmp(buf.data(), whole.data(), need * sizeof(float)) == 0);
    CHECK(buf[need] == -7.0f && buf[need + 7] == -7.0f);

    // Unknown layouts and conventions.
    CHECK_THROWS(b.read(0, 1, static_cast<FlameLayout>(10)), FLAME_STATUS_INVALID_ARGUMENT,
                 "layout");
    CHECK_THROWS(b.read(0, 1, FLAME_LAYOUT_ROOT_TRANSLATION, static_cast<FlameConvention>(6)),
                 FLAME_STATUS_INVALID_ARGUMENT, "convention");

    // Frames not generated yet: WRONG_STATE, also one frame past the end; the playhead cannot
    // pass the frames ready.
    CHECK_THROWS(b.read(0, kTimeline + 1), FLAME_STATUS_WRONG_STATE, "not generated yet");
    CHECK_THROWS(b.read(kTimeline, 1, FLAME_LAYOUT_GLOBAL_POSITIONS), FLAME_STATUS_WRONG_STATE,
                 "not generated yet");
    CHECK_THROWS(b.read_len(kTimeline, 1), FLAME_STATUS_WRONG_STATE, "not generated yet");
    CHECK_THROWS(b.set_playhead(kTimeline + 1), FLAME_STATUS_INVALID_ARGUMENT, "past the");

    // Bad segments: nothing is queued by them.
    CHECK_THROWS(b.push("a person jumps.", 0), FLAME_STATUS_INVALID_ARGUMENT,
                 "at least one frame");
    CHECK_THROWS(b.interrupt("a person jumps.", 0), FLAME_STATUS_INVALID_ARGUMENT,
                 "at least one frame");
    CHECK_THROWS(b.push(std::string("a\0b", 3), 10), FLAME_STATUS_INVALID_ARGUMENT,
                 "`prompt` contains a NUL byte");
    CHECK_THROWS(b.interrupt(std::string("a\0b", 3), 10), FLAME_STATUS_INVALID_ARGUMENT,
                 "`prompt` contains a NUL byte");
    CHECK_THROWS(b.push("\xff\xfe", 10), FLAME_STATUS_INVALID_ARGUMENT, "UTF-8");
    st = b.pump(flame::Stream::all_steps);
    CHECK(st.steps == 0 && st.ready == kTimeline);
}

// The window: frames more than `window` behind the playhead are dropped.
static void test_window() {
    flame::Model m = load("flame_tiny");
    flame::StreamParams p = small_params(1);
    p.window = 20;
    flame::Stream s(m, p);
    timeline(s);
    s.pump(flame::Stream::all_steps);
    const std::vector<float> before = s.read(70, 45);
    s.set_playhead(90);
    flame::StreamStatus st = s.status();
    CHECK(st.first_frame == 70 && st.playhead == 90 && st.ready == kTimeline);
    CHECK_THROWS(s.read(60, 10, FLAME_LAYOUT_ROOT_TRANSLATION), FLAME_STATUS_INVALID_ARGUMENT,
                 "were dropped");
    CHECK_THROWS(s.read(69, 2), FLAME_STATUS_INVALID_ARGUMENT,
                 "keeps 20 frames behind the playhead 90");
    CHECK(same(s.read(70, 45), before));
}

// ---- cleaned reads ------------------------------------------------------------------------

// read_cleaned / end_timeline: frames read one at a time as they settle are the bytes one read
// at the end gives; at 30 fps the 115-frame timeline (20 fps) has 172 cleaned frames.
static void test_cleaned() {
    flame::Model m = load("flame_tiny");
    FlameCleanupParams c;
    CHECK(flame_cleanup_params_default(&c) == FLAME_STATUS_OK);
    c.fps = 30.0f;
    flame::Stream a(m, small_params(1)), b(m, small_params(1));
    timeline(a);
    timeline(b);
    a.end_timeline();
    b.end_timeline();
    CHECK_THROWS(a.push("a person jumps.", 10), FLAME_STATUS_WRONG_STATE, "");
    std::vector<float> got;
    uint32_t k = 0;
    for (;;) {
        const uint32_t stepped = a.pump(1).steps;
        bool read = false;
        try {
            const std::vector<float> f =
                a.read_cleaned(c, k, 1, FLAME_LAYOUT_GLOBAL_POSITIONS, FLAME_CONVENTION_GLTF);
            got.insert(got.end(), f.begin(), f.end());
            k++;
            read = true;
        } catch (const flame::Error &e) {
            CHECK(e.status() == FLAME_STATUS_WRONG_STATE);
        }
        if (!read && stepped == 0) break;
    }
    b.pump(flame::Stream::all_steps);
    const std::vector<float> whole =
        b.read_cleaned(c, 0, 172, FLAME_LAYOUT_GLOBAL_POSITIONS, FLAME_CONVENTION_GLTF);
    CHECK(k == 172);
    CHECK(same(got, whole));
    c.fps = 60.0f;
    CHECK_THROWS(b.read_cleaned(c, 0, 1, FLAME_LAYOUT_GLOBAL_POSITIONS), FLAME_STATUS_WRONG_STATE,
                 "");
}

// ---- a timeline closed into a loop -------------------------------------------------------

// tests/c/test_stream.c's loop (the settings of tests/cycle.rs): chunks of 60 frames keeping 20,
// 3 steps, seed 9; "a person walks" 70 + "a person jumps" 30 = 100 frames, a 20-frame bridge.
static flame::StreamParams loop_params() {
    flame::StreamParams p;
    p.chunk = 60;
    p.overlap = 20;
    p.lookahead = 1000;
    p.window = 1000;
    p.steps = 3;
    p.seed = 9;
    p.threads = 1;
    return p;
}

static void test_end_timeline_looped() {
    flame::Model m = load("flame_tiny");
    const uint32_t dim = m.info().feature_dim, joints = m.info().joint_count;
    flame::Stream plain(m, loop_params()), looped(m, loop_params());
    for (flame::Stream *s : {&plain, &looped}) {
        s->push("a person walks", 70);
        s->push("a person jumps", 30);
    }
    plain.end_timeline();
    looped.end_timeline_looped(20);
    CHECK_THROWS(looped.push("a person waves", 10), FLAME_STATUS_WRONG_STATE, "closed");
    CHECK_THROWS(looped.end_timeline_looped(20), FLAME_STATUS_WRONG_STATE, "closed");
    run(plain, 1);
    run(looped, 1);
    CHECK(plain.status().ready == 100);
    const flame::StreamStatus st = looped.status();
    CHECK(st.ready == 120 && st.starving);
    CHECK_THROWS(looped.read(120, 1), FLAME_STATUS_WRONG_STATE, "not generated yet");

    // The bridge only appends: the first 100 frames are the plain stream's, bit for bit.
    const std::vector<float> base = plain.read(0, 100);
    const std::vector<float> all = looped.read(0, 120);
    CHECK(base.size() == 100u * dim && all.size() == 120u * dim && finite(all));
    CHECK(all.size() >= base.size() &&
          std::memcmp(all.data(), base.data(), base.size() * sizeof(float)) == 0);

    // The C API's looped close gives the same frames.
    {
        const flame::StreamParams p = loop_params();
        FlameStream *c = nullptr;
        if (CHECK_OK(flame_stream_new(m.get(), &p, &c))) {
            CHECK_OK(flame_stream_push(c, "a person walks", 70));
            CHECK_OK(flame_stream_push(c, "a person jumps", 30));
            CHECK_OK(flame_stream_close_looped(c, 20));
            CHECK_OK(flame_stream_pump(c, UINT32_MAX, nullptr));
            std::vector<float> direct(all.size() + 1);
            size_t n = 0;
            CHECK_OK(flame_stream_read(c, 0, 120, FLAME_LAYOUT_FEATURES, 0, 0, direct.data(),
                                       direct.size(), &n));
            direct.resize(n);
            CHECK(same(direct, all));
            flame_stream_free(c);
        }
    }

    // Cleaned reads (the default cleanup: feet locked) settle all 120 frames.
    FlameCleanupParams c;
    CHECK(flame_cleanup_params_default(&c) == FLAME_STATUS_OK);
    const std::vector<float> clean =
        looped.read_cleaned(c, 0, 120, FLAME_LAYOUT_GLOBAL_POSITIONS, FLAME_CONVENTION_GLTF);
    CHECK(clean.size() == 120u * joints * 3 && finite(clean));

    // Refusals: nothing to loop, a bridge under 1 s (the stream stays open), a latent model.
    flame::Stream s(m, loop_params());
    CHECK_THROWS(s.end_timeline_looped(20), FLAME_STATUS_WRONG_STATE, "push a segment");
    s.push("a person walks", 40);
    CHECK_THROWS(s.end_timeline_looped(12), FLAME_STATUS_INVALID_ARGUMENT, "bridge of 12 frames");
    s.push("a person jumps", 20);
    s.end_timeline_looped(20);
    flame::Stream empty;
    CHECK_THROWS(empty.end_timeline_looped(20), FLAME_STATUS_INVALID_ARGUMENT, "`stream` is NULL");
    flame::Model mola = load("mola_tiny");
    flame::StreamParams lp = loop_params();
    lp.chunk = 32;
    lp.overlap = 8;
    flame::Stream latent(mola, lp);
    latent.push("a person walks", 40);
    CHECK_THROWS(latent.end_timeline_looped(20), FLAME_STATUS_INVALID_ARGUMENT,
                 "samples a latent");
}

// ---- interrupt ----------------------------------------------------------------------------

static void test_interrupt() {
    flame::Model m = load("flame_tiny");
    // Between chunks: the current segment ends at the 40 frames ready.
    flame::Stream s(m, small_params(1));
    s.push("a person walks forward.", 100);
    s.push("a person sits down.", 100);
    CHECK(s.pump(3).ready == 40);
    s.interrupt("a person waves.", 20);
    flame::StreamStatus st = s.pump(flame::Stream::all_steps);
    CHECK(st.ready == 60 && st.starving);

    // With a chunk in flight: it finishes, then the new segment starts.
    flame::Stream t(m, small_params(1));
    t.push("a person walks forward.", 100);
    CHECK(t.pump(1).ready == 0);
    t.interrupt("a person waves.", 20);
    st = t.pump(flame::Stream::all_steps);
    CHECK(st.ready == 60 && st.starving);
    // The frames of both: the same timeline, the same bits.
    CHECK(same(s.read(0, 60), t.read(0, 60)));

    // An interrupt on an empty timeline is a push.
    flame::Stream u(m, small_params(1));
    u.interrupt("a person waves.", 15);
    st = u.pump(flame::Stream::all_steps);
    CHECK(st.steps == 3 && st.ready == 15);
}

// ---- cancel -------------------------------------------------------------------------------

// A timeline long enough that pumping it all takes many steps: `segments` segments of 100
// frames, 10 DDIM steps (5 with FLAME_TEST_QUICK) per chunk of 40 frames (30 new ones after the
// first).
static uint32_t cancel_steps() { return g_quick ? 5 : 10; }
static flame::StreamParams cancel_params() {
    flame::StreamParams p = small_params(1);
    p.steps = cancel_steps();
    return p;
}
static uint64_t long_timeline(flame::Stream &s, int segments) {
    static const char *const prompts[] = {"a person walks forward.", "a person waves.",
                                          "a person jumps.", "a person sits down."};
    for (int i = 0; i < segments; ++i) {
        s.push(prompts[i % 4], 100);
    }
    return 100u * static_cast<uint64_t>(segments);
}

struct Pumper {
    flame::Stream *stream = nullptr;
    std::atomic<bool> started{false};
    FlameStatus status = FLAME_STATUS_OK;
    std::string message;
    uint32_t steps = 0;  // of a pump that was not cancelled
    std::chrono::steady_clock::time_point end;

    void operator()() {
        started = true;
        try {
            steps = stream->pump(flame::Stream::all_steps).steps;
        } catch (const flame::Error &e) {
            status = e.status();
            message = e.message();
        }
        end = std::chrono::steady_clock::now();
    }
};

static void test_cancel() {
    flame::Model m = load("flame_tiny");
    const int segments = g_quick ? 1 : 6;

    // The reference: never cancelled.
    flame::Stream ref(m, cancel_params());
    const uint64_t total = long_timeline(ref, segments);
    const auto t0 = std::chrono::steady_clock::now();
    CHECK(ref.pump(flame::Stream::all_steps).ready == total);
    // How long the whole pump takes here: the cancel below comes a quarter of it in.
    const auto whole = std::chrono::steady_clock::now() - t0;
    const std::vector<float> want = ref.read(0, static_cast<uint32_t>(total));

    // Raised between pumps: the next step is cancelled, and only that one.
    {
        flame::Stream s(m, cancel_params());
        long_timeline(s, segments);
        s.cancel();
        CHECK_THROWS(s.pump(1), FLAME_STATUS_CANCELLED, "");
        flame::StreamStatus st = s.status();
        CHECK(st.ready == 0);
        st = s.pump(cancel_steps());  // the first chunk, all its steps
        CHECK(st.steps == cancel_steps() && st.ready == 40);
        s.cancel();
        CHECK_THROWS(s.pump(flame::Stream::all_steps), FLAME_STATUS_CANCELLED, "");
        CHECK(s.status().ready == 40);
        CHECK(s.pump(flame::Stream::all_steps).ready == total);
        CHECK(same(s.read(0, static_cast<uint32_t>(total)), want));
    }

    // From another thread while a pump runs: that pump throws CANCELLED soon after (the cancel
    // comes a quarter of the way into a pump of the whole timeline; had it come before the pump
    // started, it would cancel the pump's first step, the same status); the stream is usable at
    // once and pumping again gives the reference's bits.
    {
        flame::Stream s(m, cancel_params());
        long_timeline(s, segments);
        Pumper w;
        w.stream = &s;
        std::thread t(std::ref(w));
        while (!w.started) {
            std::this_thread::yield();
        }
        std::this_thread::sleep_for(whole / 4);
        const auto cancelled_at = std::chrono::steady_clock::now();
        s.cancel();  // while the worker is inside pump()
        t.join();
        const double latency = std::chrono::duration<double>(w.end - cancelled_at).count();
        std::printf("stream cancel latency: %.2f ms\n", latency * 1e3);
        CHECK(w.status == FLAME_STATUS_CANCELLED);
        if (w.status != FLAME_STATUS_CANCELLED) {
            std::fprintf(stderr, "     (the pump returned %s after %u steps: %s)\n",
                         flame_status_string(w.status), w.steps, w.message.c_str());
        }
        CHECK(latency < 5.0);
        const flame::StreamStatus st = s.status();
        CHECK(st.ready < total);
        std::printf("cancelled with %llu of %llu frames ready\n",
                    static_cast<unsigned long long>(st.ready),
                    static_cast<unsigned long long>(total));
        // Frames generated before the cancel are readable and final.
        CHECK(st.ready == 0 ||
              std::memcmp(s.read(0, static_cast<uint32_t>(st.ready)).data(), want.data(),
                          static_cast<std::size_t>(st.ready) * FLAME_TINY_DIM * sizeof(float)) ==
                  0);
        // One step at a time from here: the same bits as all at once, never cancelled.
        run(s, 1);
        CHECK(s.status().ready == total);
        CHECK(same(s.read(0, static_cast<uint32_t>(total)), want));
    }

    // A cancel from another thread while nobody pumps cancels the next step only.
    {
        flame::Stream s(m, cancel_params());
        long_timeline(s, segments);
        std::thread t([&s] { s.cancel(); });
        t.join();
        CHECK_THROWS(s.pump(flame::Stream::all_steps), FLAME_STATUS_CANCELLED, "");
        CHECK(s.pump(flame::Stream::all_steps).ready == total);
        CHECK(same(s.read(0, static_cast<uint32_t>(total)), want));
    }
}

// ---- stages: part texts -------------------------------------------------------------------

static flame::Stage waving_stage(uint32_t frames) {
    flame::Stage st("a person walks forward.", frames);
    st.left_arm = "waves the left arm";
    return st;
}

static void test_stages_flame() {
    flame::Model m = load("flame_tiny");

    // A stage without part texts is push(text, frames); interrupt_stage is interrupt.
    flame::Stream plain(m, small_params(1));
    plain.push("a person walks forward.", 50);
    plain.pump(3);
    plain.interrupt("a person waves.", 25);
    plain.pump(flame::Stream::all_steps);
    flame::Stream staged(m, small_params(1));
    staged.push_stage(flame::Stage("a person walks forward.", 50));
    staged.pump(3);
    staged.interrupt_stage(flame::Stage("a person waves.", 25));
    const flame::StreamStatus st = staged.pump(flame::Stream::all_steps);
    CHECK(st.ready == 65 && plain.status().ready == 65);
    CHECK(same(staged.read(0, 65), plain.read(0, 65)));

    // Part texts: FLAME reads none.
    flame::Stream s(m, small_params(1));
    bool refused = false;
    try {
        s.push_stage(waving_stage(40));
        s.pump(flame::Stream::all_steps);  // refused when its chunk starts, if not at the push
    } catch (const flame::Error &e) {
        refused = e.status() == FLAME_STATUS_INVALID_ARGUMENT &&
                  e.message().find("part text") != std::string::npos;
        if (!refused) {
            std::fprintf(stderr, "     (%s)\n", e.what());
        }
    }
    CHECK(refused);
    flame::Stream i(m, small_params(1));
    refused = false;
    try {
        i.interrupt_stage(waving_stage(40));
        i.pump(flame::Stream::all_steps);
    } catch (const flame::Error &e) {
        refused = e.status() == FLAME_STATUS_INVALID_ARGUMENT &&
                  e.message().find("part text") != std::string::npos;
        if (!refused) {
            std::fprintf(stderr, "     (%s)\n", e.what());
        }
    }
    CHECK(refused);

    // The wrapper's own checks: NUL bytes name the field.
    flame::Stage nul("a person walks.", 10);
    nul.right_leg = std::string("kicks\0", 6);
    CHECK_THROWS(s.push_stage(nul), FLAME_STATUS_INVALID_ARGUMENT,
                 "`stage.right_leg` contains a NUL byte");
    nul = flame::Stage(std::string("a\0b", 3), 10);
    CHECK_THROWS(s.interrupt_stage(nul), FLAME_STATUS_INVALID_ARGUMENT,
                 "`stage.text` contains a NUL byte");
    CHECK_THROWS(s.push_stage(flame::Stage("a person walks.", 0)), FLAME_STATUS_INVALID_ARGUMENT,
                 "at least one frame");
}

static void test_stages_finemogen() {
    const std::string path = g_dir + "/finemogen_tiny.safetensors";
    if (std::FILE *f = std::fopen(path.c_str(), "rb")) {
        std::fclose(f);
    } else {
        std::printf("skip FineMoGen stages: no %s\n", path.c_str());
        return;
    }
    flame::Model m = load("finemogen_tiny");
    const uint32_t dim = m.info().feature_dim;
    flame::StreamParams p = small_params(1);
    p.chunk = 0;  // the model's default frames per chunk
    const uint32_t frames = 30;

    flame::Stream parts(m, p);
    parts.push_stage(waving_stage(frames));
    flame::StreamStatus st = parts.pump(flame::Stream::all_steps);
    CHECK(st.steps == 3 && st.ready == frames && st.starving);
    const std::vector<float> with_parts = parts.read(0, frames);
    CHECK(with_parts.size() == static_cast<std::size_t>(frames) * dim && finite(with_parts));

    // The part text is read: the same segment without it is another motion.
    flame::Stream whole(m, p);
    whole.push("a person walks forward.", frames);
    whole.pump(flame::Stream::all_steps);
    CHECK(!same(whole.read(0, frames), with_parts));

    // Deterministic, and interrupt_stage with part texts is accepted too.
    flame::Stream again(m, p);
    again.push("a person walks forward.", 100);
    again.interrupt_stage(waving_stage(frames));
    CHECK(again.pump(flame::Stream::all_steps).ready == frames);
    CHECK(same(again.read(0, frames), with_parts));
}

// ---- creation errors ----------------------------------------------------------------------

static void test_bad_params() {
    flame::Model m = load("flame_tiny");
    flame::StreamParams p = small_params(1);
    p.chunk = FLAME_TINY_MAX_FRAMES + 1;
    CHECK_THROWS(flame::Stream(m, p), FLAME_STATUS_INVALID_ARGUMENT, "exceeds");
    p = small_params(1);
    p.overlap = 40;
    CHECK_THROWS(m.stream(p), FLAME_STATUS_INVALID_ARGUMENT, "overlap");
    p = small_params(1);
    p.sampler = 99;
    CHECK_THROWS(m.stream(p), FLAME_STATUS_INVALID_ARGUMENT, "sampler");
    p = small_params(1);
    p.struct_size = 8;
    CHECK_THROWS(m.stream(p), FLAME_STATUS_INVALID_ARGUMENT, "struct_size");
    flame::Model mld = load("mld_tiny");
    CHECK_THROWS(mld.stream(small_params(1)), FLAME_STATUS_INVALID_ARGUMENT, "latent");
}

int main(int argc, char **argv) {
    if (argc != 2) {
        std::fprintf(stderr, "usage: test_cpp_stream FIXTURES_DIR\n");
        return 2;
    }
    g_dir = argv[1];
    const char *quick = std::getenv("FLAME_TEST_QUICK");
    g_quick = quick && std::strcmp(quick, "1") == 0;
    const struct {
        const char *name;
        void (*fn)();
    } tests[] = {
        {"defaults", test_defaults},
        {"round trip (FLAME)", [] { test_round_trip("flame_tiny"); }},
        {"round trip (MDM)", [] { test_round_trip("mdm_tiny"); }},
        {"window", test_window},
        {"cleaned reads", test_cleaned},
        {"end_timeline_looped", test_end_timeline_looped},
        {"interrupt", test_interrupt},
        {"cancel", test_cancel},
        {"stages (FLAME)", test_stages_flame},
        {"stages (FineMoGen)", test_stages_finemogen},
        {"bad params", test_bad_params},
    };
    for (const auto &t : tests) {
        const auto t0 = std::chrono::steady_clock::now();
        try {
            t.fn();
        } catch (const std::exception &e) {
            std::string what = std::string("unexpected exception in ") + t.name;
            check_record(0, __FILE__, __LINE__, what.c_str(), e.what());
        }
        std::printf("%s: %.2f s\n", t.name,
                    std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count());
    }
    return check_summary();
}
