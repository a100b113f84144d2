// The C++17 wrapper (bindings/cpp/flame.hpp): the happy path, errors as exceptions with the
// library's message, move-only ownership, sessions outliving their Model object, progress
// callbacks (including one that throws), cancel from another thread, and bit-equality with the
// C API and the CLI.
//
// usage: test_cpp MODEL REFERENCE_NPY [STEPS [LOOP_POSITIONS_NPY]]
//   (as test_api: frames from the file, steps 10; LOOP_POSITIONS_NPY is what
//   `flame generate --loop --feet off --ground off --positions` wrote, tests/c/run.sh's
//   loop_positions, which a loop session's positions must equal bit for bit)

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <stdexcept>
#include <string>
#include <thread>
#include <type_traits>
#include <vector>

#include "flame.hpp"

#include "check.h"
#include "util.h"

static_assert(!std::is_copy_constructible<flame::Model>::value, "Model is move-only");
static_assert(!std::is_copy_assignable<flame::Model>::value, "Model is move-only");
static_assert(std::is_nothrow_move_constructible<flame::Model>::value, "");
static_assert(std::is_nothrow_move_assignable<flame::Model>::value, "");
static_assert(!std::is_copy_constructible<flame::Session>::value, "Session is move-only");
static_assert(!std::is_copy_assignable<flame::Session>::value, "Session is move-only");
static_assert(std::is_nothrow_move_constructible<flame::Session>::value, "");
static_assert(std::is_nothrow_move_assignable<flame::Session>::value, "");

static std::string g_model_path;
static std::vector<float> g_cli;  // the CLI's features
static std::vector<float> g_c;    // the same generation through the C API
static std::size_t g_values;      // ref_frames x 147
static std::string g_loop_positions;  // the CLI's loop positions (.npy), or empty

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

// No exception expected; one is a failure with its message.
#define CHECK_NOTHROW(stmt)                                                 \
    do {                                                                    \
        try {                                                               \
            stmt;                                                           \
            check_record(1, __FILE__, __LINE__, #stmt, "");                 \
        } catch (const std::exception &e_) {                                \
            check_record(0, __FILE__, __LINE__, #stmt " threw", e_.what()); \
        }                                                                   \
    } while (0)

static flame::SessionParams reference_params() {
    flame::SessionParams p;
    ref_params(&p);
    return p;
}

static std::vector<float> run(flame::Session &s, const char *prompt = REF_PROMPT) {
    s.set_prompt(prompt);
    while (s.step() > 0) {
    }
    return s.read();
}

static bool same(const std::vector<float> &a, const std::vector<float> &b) {
    return same_bits(a.data(), a.size(), b.data(), b.size());
}

static void test_versions() {
    CHECK(flame::abi_version() == FLAME_ABI_VERSION);
    CHECK(flame::version() == flame_version_string());
}

static void test_happy_path() {
    flame::Model model = flame::Model::load(g_model_path);
    CHECK(static_cast<bool>(model));
    flame::ModelInfo info = model.info();
    CHECK(info.feature_dim == FLAME_TINY_DIM && info.max_frames == FLAME_TINY_MAX_FRAMES);
    CHECK(info.architecture == "flame" && info.motion_format == "smpl24_6d");
    CHECK(info.fps == 20.0f && info.default_sampler == FLAME_SAMPLER_DDPM);
    CHECK(info.joint_names.size() == info.joint_count);

    flame::Session s = model.session(reference_params());
    std::vector<uint32_t> seen;
    s.on_progress([&seen](uint32_t done, uint32_t total) {
        seen.push_back(done);
        (void)total;
    });
    s.set_prompt(REF_PROMPT);
    CHECK(s.progress().done == 0 && s.progress().total == ref_steps);
    uint32_t left = s.step();
    CHECK(left == ref_steps - 1);
    std::vector<float> preview = s.read(FLAME_WHICH_ESTIMATE);
    CHECK(preview.size() == g_values);
    while (left > 0) {
        left = s.step();
    }
    std::vector<float> x = s.read();
    CHECK(same(x, g_cli));
    CHECK(same(x, g_c));
    CHECK(seen.size() == ref_steps && seen.front() == 1 && seen.back() == ref_steps);

    // Pose layouts, conventions and flags.
    std::vector<float> quats = s.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_QUAT_XYZW,
                                      FLAME_CONVENTION_UNITY, FLAME_READ_SMOOTH);
    CHECK(quats.size() == ref_frames * info.joint_count * 4);
    CHECK(s.read_len(FLAME_WHICH_ESTIMATE, FLAME_LAYOUT_GLOBAL_POSITIONS) ==
          ref_frames * info.joint_count * 3);

    // The buffer overload and its length query.
    std::vector<float> buf(s.read_len());
    CHECK(s.read(buf.data(), buf.size()) == buf.size());
    CHECK(same(buf, x));

    // reset reproduces; the prompt is kept.
    s.reset();
    while (s.step() > 0) {
    }
    CHECK(same(s.read(), g_cli));
    CHECK(seen.size() == 2 * ref_steps);

    // Removing the callback.
    s.on_progress(nullptr);
    s.reset();
    s.step();
    CHECK(seen.size() == 2 * ref_steps);
}

static void test_load_from_memory() {
    size_t len = 0;
    unsigned char *bytes = read_file(g_model_path.c_str(), &len);
    std::vector<uint8_t> v(bytes, bytes + len);
    free(bytes);
    flame::ModelParams mp;
    mp.threads = 1;
    flame::Model model = flame::Model::load_from_memory(v, mp);
    v.assign(v.size(), 0);  // copied: the buffer is no longer needed
    flame::Session s = model.session(reference_params());
    CHECK(same(run(s), g_cli));
}

static void test_errors() {
    CHECK_THROWS(flame::Model::load("/nonexistent/flame.safetensors"), FLAME_STATUS_IO,
                 "/nonexistent/flame.safetensors");
    std::vector<uint8_t> garbage(1000, 0x42);
    CHECK_THROWS(flame::Model::load_from_memory(garbage), FLAME_STATUS_BAD_MODEL_FILE, "");

    flame::Model model = flame::Model::load(g_model_path);
    flame::SessionParams p = reference_params();
    p.frames = 471;
    CHECK_THROWS(model.session(p), FLAME_STATUS_INVALID_ARGUMENT, "got 471");
    p = reference_params();
    p.sampler = 7;
    CHECK_THROWS(flame::Session(model, p), FLAME_STATUS_INVALID_ARGUMENT, "sampler 7");
    p = reference_params();
    p.respacing = "ddim999";
    CHECK_THROWS(model.session(p), FLAME_STATUS_INVALID_ARGUMENT, "cannot create exactly 999");
    /* The section rule's "N" is what `steps` N gives: the same bits. */
    {
        const std::string spec = std::to_string(ref_steps);
        p = reference_params();
        p.respacing = spec.c_str();
        p.steps = 0;
        flame::Session r = model.session(p);
        flame::Session plain = model.session(reference_params());
        CHECK(same(run(r), run(plain)));
    }

    flame::Session s = model.session(reference_params());
    CHECK_THROWS(s.step(), FLAME_STATUS_WRONG_STATE, "prompt");
    CHECK_THROWS(s.read(), FLAME_STATUS_WRONG_STATE, "no sample");
    CHECK_THROWS(s.set_prompt(std::string("a\0b", 3)), FLAME_STATUS_INVALID_ARGUMENT, "NUL");
    const std::string values = std::to_string(g_values);
    CHECK_THROWS(s.set_noise(std::vector<float>(10)), FLAME_STATUS_INVALID_ARGUMENT, values);
    CHECK_THROWS(s.set_reference(std::vector<float>(10), ref_frames, FLAME_TINY_DIM),
                 FLAME_STATUS_INVALID_ARGUMENT, "features");
    CHECK_THROWS(s.set_mask(std::vector<uint8_t>(g_values), ref_frames - 1, FLAME_TINY_DIM),
                 FLAME_STATUS_INVALID_ARGUMENT, "mask");
    CHECK_THROWS(s.keep_frames(3, 3), FLAME_STATUS_INVALID_ARGUMENT, "from 3 to 3");
    CHECK_THROWS(s.keep_joints({0, 24}), FLAME_STATUS_INVALID_ARGUMENT, "joint 24");
    s.set_prompt(REF_PROMPT);
    s.step();
    float small[4];
    CHECK_THROWS(s.read(small, 4), FLAME_STATUS_BUFFER_TOO_SMALL, values);
    CHECK_THROWS(s.read(FLAME_WHICH_SAMPLE, static_cast<FlameLayout>(99)),
                 FLAME_STATUS_INVALID_ARGUMENT, "layout 99");
    // Foot contacts are detected for smpl24 models (ABI 3): four per frame.
    CHECK(s.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_FOOT_CONTACTS).size() == ref_frames * 4);

    // flame::Error is a std::runtime_error whose what() starts with the status name.
    try {
        flame::Model::load("");
        CHECK(!"unreachable");
    } catch (const std::runtime_error &e) {
        CHECK(std::strncmp(e.what(), "FLAME_STATUS_IO: ", 17) == 0);
    }
}

// The fixture's RoBERTa window is 20 tokens, <s> and </s> included.
static void test_prompt_info() {
    flame::Model model = flame::Model::load(g_model_path);
    flame::Session s = model.session(reference_params());
    CHECK_THROWS(s.prompt_info(), FLAME_STATUS_WRONG_STATE, "no prompt");
    const std::string prompt = "a person walks forward, turns left, raises both arms, waves with "
                               "the right hand, sits down on a chair and then kicks with the "
                               "right leg";
    s.set_prompt(prompt);
    flame::PromptInfo info = s.prompt_info();
    CHECK(info.window == 20 && info.kept == 20 && info.tokens > 20);
    CHECK(info.truncated && !info.unconditional);
    // The dropped text is the prompt's tail.
    const std::string &d = info.dropped;
    CHECK(!d.empty() && d.size() < prompt.size() &&
          prompt.compare(prompt.size() - d.size(), d.size(), d) == 0);
    const std::string tail = "kicks with the right leg";
    CHECK(d.size() >= tail.size() && d.compare(d.size() - tail.size(), tail.size(), tail) == 0);

    s.set_prompt("a person walks");
    flame::PromptInfo short_info = s.prompt_info();
    CHECK(!short_info.truncated && !short_info.unconditional && short_info.dropped.empty());
    CHECK(short_info.kept == short_info.tokens && short_info.tokens < 20);
    // info holds its own copy of the dropped text: still the tail after the next prompt.
    CHECK(!d.empty() && prompt.compare(prompt.size() - d.size(), d.size(), d) == 0);

    s.set_prompt("");
    flame::PromptInfo none = s.prompt_info();
    CHECK(none.unconditional && !none.truncated && none.dropped.empty());

    flame::Session moved(std::move(s));
    CHECK_THROWS(s.prompt_info(), FLAME_STATUS_INVALID_ARGUMENT, "session");
    CHECK(moved.prompt_info().unconditional);
}

// A prompt encoded once serves another session of the same model: the CLI's bits.
static void test_prompt_from() {
    flame::Model model = flame::Model::load(g_model_path);
    flame::Session a = model.session(reference_params());
    flame::Session b = model.session(reference_params());
    CHECK_THROWS(b.set_prompt_from(a), FLAME_STATUS_WRONG_STATE, "no prompt");
    a.set_prompt(REF_PROMPT);
    b.set_prompt_from(a);
    CHECK(b.prompt_info().tokens == a.prompt_info().tokens);
    while (b.step() > 0) {
    }
    CHECK(same(b.read(), g_cli));
    flame::Model other = flame::Model::load(g_model_path);
    flame::Session c = other.session(reference_params());
    CHECK_THROWS(c.set_prompt_from(a), FLAME_STATUS_INVALID_ARGUMENT, "another model");
}

// MotionLCM's consistency latent tuning (tests/fixtures/motionlcm_v2_control_tiny, next to the
// FLAME model): the report says a pelvis path is followed closer; tuning twice gives the same
// bits; after the first step it is refused.
static void test_latent_tuning() {
    std::string dir = g_model_path.substr(0, g_model_path.find_last_of('/'));
    flame::Model model = flame::Model::load(dir + "/motionlcm_v2_control_tiny.safetensors");
    std::vector<float> hint(24 * 22 * 3, NAN);
    for (int f = 0; f < 24; f++) {
        hint[f * 66] = 0.05f * static_cast<float>(f);
        hint[f * 66 + 1] = 0.9f;
        hint[f * 66 + 2] = 0.02f * static_cast<float>(f);
    }
    std::vector<float> runs[2];
    for (auto& out : runs) {
        flame::SessionParams p;
        p.frames = 24;
        p.steps = 1;
        p.seed = 5;
        p.threads = 1;
        flame::Session s = model.session(p);
        s.set_prompt("a person walks forward");
        s.set_control(hint);
        FlameTuningReport r = s.tune_latent(20);
        CHECK(r.iterations == 20 && r.control_error_after < r.control_error_before);
        while (s.step() > 0) {
        }
        out = s.read();
        CHECK_THROWS(s.tune_latent(5), FLAME_STATUS_WRONG_STATE, "before the first step");
    }
    CHECK(same(runs[0], runs[1]));
}

static void test_editing() {
    flame::Model model = flame::Model::load(g_model_path);
    flame::Session s = model.session(reference_params());
    std::vector<float> r(g_values, 0.25f);
    std::vector<uint8_t> mask(g_values, 0);
    CHECK_NOTHROW(s.set_reference(r, ref_frames, FLAME_TINY_DIM));
    CHECK_NOTHROW(s.set_mask(mask, ref_frames, FLAME_TINY_DIM));
    // An all-zero mask keeps nothing: the plain generation.
    CHECK(same(run(s), g_cli));
    s.reset();
    CHECK_NOTHROW(s.keep_joints({FLAME_ROOT_TRANSLATION}));
    CHECK_NOTHROW(s.keep_frames(0, 2));
    while (s.step() > 0) {
    }
    CHECK(!same(s.read(), g_cli));
    s.reset();
    CHECK_NOTHROW(s.clear_edit());
    while (s.step() > 0) {
    }
    CHECK(same(s.read(), g_cli));
    std::vector<float> noise(g_values, 0.5f);
    s.reset();
    CHECK_NOTHROW(s.set_noise(noise));
    CHECK_NOTHROW(s.step());
}

static float max_abs_diff(const std::vector<float> &a, const std::vector<float> &b) {
    if (a.size() != b.size()) {
        return INFINITY;
    }
    float d = 0.0f;
    for (std::size_t i = 0; i < a.size(); ++i) {
        d = std::max(d, std::fabs(a[i] - b[i]));
    }
    return d;
}

// Whether frames [f0, f1) of x are r's, bit for bit.
static bool same_frames(const std::vector<float> &x, const std::vector<float> &r, uint32_t f0,
                        uint32_t f1) {
    std::size_t a = std::size_t{f0} * FLAME_TINY_DIM, n = std::size_t{f1 - f0} * FLAME_TINY_DIM;
    return x.size() >= a + n && r.size() >= a + n &&
           std::memcmp(x.data() + a, r.data() + a, n * sizeof(float)) == 0;
}

static void test_edit_params_tasks_parts() {
    flame::Model model = flame::Model::load(g_model_path);
    const uint32_t F = ref_frames, Q = ref_frames / 4;
    flame::EditParams d;
    CHECK(d.struct_size == sizeof(FlameEditParams) && d.method == FLAME_EDIT_METHOD_AUTO);
    CHECK(d.edit_till == 0.2f && d.paste == 1 && d.seam_frames == 4);

    flame::Session s = model.session(reference_params());
    CHECK_NOTHROW(s.set_edit_params());
    flame::EditParams p;
    p.method = FLAME_EDIT_METHOD_REWRITE_TRAJECTORY;
    CHECK_THROWS(s.set_edit_params(p), FLAME_STATUS_INVALID_ARGUMENT, "does not apply");
    p = flame::EditParams();
    p.method = 4;
    CHECK_THROWS(s.set_edit_params(p), FLAME_STATUS_INVALID_ARGUMENT, "edit method");
    p = flame::EditParams();
    p.edit_till = NAN;
    CHECK_THROWS(s.set_edit_params(p), FLAME_STATUS_INVALID_ARGUMENT, "edit_till");
    p = flame::EditParams();
    p.struct_size = 0;
    CHECK_THROWS(s.set_edit_params(p), FLAME_STATUS_INVALID_ARGUMENT, "struct_size");
    CHECK_THROWS(s.keep_part(static_cast<FlameBodyPart>(5), 0, F), FLAME_STATUS_INVALID_ARGUMENT,
                 "body part");
    CHECK_THROWS(s.keep_part(FLAME_BODY_PART_ARMS, 3, 3), FLAME_STATUS_INVALID_ARGUMENT, "from 3 to 3");
    CHECK_THROWS(s.set_task_mask(static_cast<FlameEditTask>(4)), FLAME_STATUS_INVALID_ARGUMENT,
                 "task");

    // A mask with no reference: the step refuses.
    CHECK_NOTHROW(s.set_task_mask(FLAME_EDIT_TASK_PATH));
    s.set_prompt(REF_PROMPT);
    CHECK_THROWS(s.step(), FLAME_STATUS_WRONG_STATE, "no reference");

    // In-betweening with paste on (the default): the kept frames are the reference's.
    std::vector<float> r(g_values);
    for (std::size_t i = 0; i < r.size(); ++i) {
        r[i] = 0.5f * std::sin(0.01f * static_cast<float>(i)) + 0.25f;
    }
    s.reset();
    CHECK_NOTHROW(s.set_reference(r, F, FLAME_TINY_DIM));
    CHECK_NOTHROW(s.set_task_mask(FLAME_EDIT_TASK_INBETWEEN));
    while (s.step() > 0) {
    }
    std::vector<float> pasted = s.read();
    CHECK(same_frames(pasted, r, 0, Q) && same_frames(pasted, r, 3 * F / 4, F));
    CHECK(!same_frames(pasted, r, Q, 3 * F / 4));
    // Paste off: the kept frames are only close.
    p = flame::EditParams();
    p.paste = 0;
    CHECK_NOTHROW(s.set_edit_params(p));
    s.reset();
    while (s.step() > 0) {
    }
    CHECK(!same_frames(s.read(), r, 0, Q));

    // keep_part adds to the mask: the arms on top of the task.
    s.reset();
    CHECK_NOTHROW(s.set_edit_params());
    CHECK_NOTHROW(s.keep_part(FLAME_BODY_PART_ARMS, 0, F));
    while (s.step() > 0) {
    }
    std::vector<float> arms = s.read();
    CHECK(!same(arms, pasted) && same_frames(arms, r, 0, Q));

    // A shorter reference: PREDICT keeps exactly its frames; more is refused.
    flame::Session short_ref = model.session(reference_params());
    CHECK_NOTHROW(short_ref.set_reference(r.data(), Q, FLAME_TINY_DIM));
    CHECK_THROWS(short_ref.keep_frames(0, Q + 1), FLAME_STATUS_INVALID_ARGUMENT,
                 "keeps frame " + std::to_string(Q));
    CHECK_NOTHROW(short_ref.set_task_mask(FLAME_EDIT_TASK_PREDICT));
    CHECK(same_frames(run(short_ref), r, 0, Q));
}

// set_reference_poses is read()'s inverse: quaternions in, the same 6D rotations out.
static void test_reference_poses() {
    flame::Model model = flame::Model::load(g_model_path);
    const uint32_t F = ref_frames;
    flame::Session g = model.session(reference_params());
    g.set_prompt(REF_PROMPT);
    g.step();  // a generic motion (the tiny model's final ones have degenerate rotations)
    const FlameConvention U = FLAME_CONVENTION_UNITY;
    std::vector<float> root = g.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION, U);
    std::vector<float> quats = g.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_QUAT_XYZW, U);
    std::vector<float> rot6d = g.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL6D, U);

    flame::Session s = model.session(reference_params());
    CHECK_NOTHROW(s.set_reference_poses(root, quats, FLAME_LAYOUT_LOCAL_QUAT_XYZW, U));
    CHECK_NOTHROW(s.keep_frames(0, F));
    run(s);
    CHECK(max_abs_diff(s.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION, U), root) < 1e-4f);
    CHECK(max_abs_diff(s.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL6D, U), rot6d) < 1e-4f);

    std::vector<float> odd(root.begin(), root.end() - 1);
    CHECK_THROWS(s.set_reference_poses(odd, quats, FLAME_LAYOUT_LOCAL_QUAT_XYZW),
                 FLAME_STATUS_INVALID_ARGUMENT, "multiple of 3");
    CHECK_THROWS(s.set_reference_poses(root, quats, FLAME_LAYOUT_GLOBAL_QUAT_XYZW),
                 FLAME_STATUS_INVALID_ARGUMENT, "layout");
    CHECK_THROWS(s.set_reference_poses(root, rot6d, FLAME_LAYOUT_LOCAL_QUAT_XYZW),
                 FLAME_STATUS_INVALID_ARGUMENT, "rotations");
    CHECK_THROWS(s.set_reference_poses(root.data(), root.size(), nullptr, 10, F,
                                       FLAME_LAYOUT_LOCAL6D),
                 FLAME_STATUS_INVALID_ARGUMENT, "rotations");
}

// Position targets: defaults, errors, and what they do (scale 0 and cleared targets change
// nothing; the defaults pull the pelvis toward a path).
static void test_position_targets() {
    flame::Model model = flame::Model::load(g_model_path);
    flame::SessionParams p;
    p.frames = 16;
    p.steps = 20;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.guidance = 2.5f;
    p.seed = 7;
    p.threads = 1;
    const char *prompt = "a person walks forward.";
    const std::size_t F = 16, J = 24;
    const FlameConvention UE = FLAME_CONVENTION_UNREAL;

    flame::TargetParams d;
    CHECK(d.struct_size == sizeof(FlameTargetParams) && d.scale == 0.6f &&
          d.schedule == FLAME_TARGET_SCHEDULE_MPGD);

    flame::Session plain = model.session(p);
    std::vector<float> unguided = run(plain, prompt);
    std::vector<float> pos = plain.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_POSITIONS, UE);
    // From where the unguided pelvis starts, +5 cm in X and -4 cm in Y per frame at the
    // unguided height (Unreal: Z up, centimetres); every other joint free.
    std::vector<float> target(F * J * 3, NAN);
    for (std::size_t f = 0; f < F; ++f) {
        target[f * J * 3] = pos[0] + 5.0f * static_cast<float>(f);
        target[f * J * 3 + 1] = pos[1] - 4.0f * static_cast<float>(f);
        target[f * J * 3 + 2] = pos[f * J * 3 + 2];
    }
    auto median_error = [&](const std::vector<float> &x) {
        std::vector<double> e(F);
        for (std::size_t f = 0; f < F; ++f) {
            double s2 = 0;
            for (std::size_t k = 0; k < 3; ++k) {
                double v = x[f * J * 3 + k] - target[f * J * 3 + k];
                s2 += v * v;
            }
            e[f] = std::sqrt(s2);
        }
        std::sort(e.begin(), e.end());
        return e[F / 2];
    };

    flame::Session s = model.session(p);
    CHECK_NOTHROW(s.set_position_targets(target, UE));
    CHECK_THROWS(s.target_loss(), FLAME_STATUS_WRONG_STATE, "no step has been guided");
    std::vector<float> guided = run(s, prompt);
    double loss = s.target_loss();
    CHECK(std::isfinite(loss) && loss > 0.0);
    double before = median_error(pos);
    double after = median_error(s.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_POSITIONS, UE));
    CHECK(before > 5.0 && after < 0.5 * before);
    CHECK_NOTHROW(s.clear_position_targets());
    CHECK_THROWS(s.target_loss(), FLAME_STATUS_WRONG_STATE, "guided");
    s.reset();
    CHECK(same(run(s, prompt), unguided));

    // Scale 0: the unguided run; the same constraint as a mask: the NaN form's result.
    flame::Session z = model.session(p);
    CHECK_NOTHROW(z.set_position_targets(target, UE));
    flame::TargetParams off;
    off.scale = 0.0f;
    off.schedule = FLAME_TARGET_SCHEDULE_CONSTANT;
    CHECK_NOTHROW(z.set_target_params(off));
    CHECK(same(run(z, prompt), unguided));
    std::vector<float> values(target.size());
    std::vector<uint8_t> mask(target.size());
    for (std::size_t i = 0; i < target.size(); ++i) {
        mask[i] = !std::isnan(target[i]);
        values[i] = mask[i] ? target[i] : 123.0f;
    }
    flame::Session m = model.session(p);
    CHECK_NOTHROW(m.set_position_targets(values, mask, UE));
    CHECK(same(run(m, prompt), guided));

    // Task targets from a reference motion (the unguided features): a guided run.
    flame::Session k = model.session(p);
    const uint32_t dim = 147, kf = (uint32_t)(unguided.size() / dim);
    CHECK_NOTHROW(k.set_task_targets(unguided, kf, dim, FLAME_EDIT_TASK_PATH));
    std::vector<float> pathed = run(k, prompt);
    CHECK(std::isfinite(k.target_loss()) && !same(pathed, unguided));
    CHECK_THROWS(k.set_task_targets(unguided, kf, dim, (FlameEditTask)7), FLAME_STATUS_INVALID_ARGUMENT,
                 "unknown editing task 7");

    // Errors: the library's messages.
    const FlameStatus INV = FLAME_STATUS_INVALID_ARGUMENT;
    std::vector<float> t(2 * J * 3, 0.1f);
    std::vector<float> bad = t;
    bad[J * 3 + 5 * 3 + 1] = NAN;
    std::vector<uint8_t> all(t.size(), 1);
    CHECK_THROWS(m.set_position_targets(bad, all), INV, "frame 1, joint 5, axis 1 is NaN");
    bad[J * 3 + 5 * 3 + 1] = INFINITY;
    CHECK_THROWS(m.set_position_targets(bad), INV, "is inf but constrained");
    CHECK_THROWS(m.set_position_targets(std::vector<float>(t.size() - 1)), INV, "multiple of 72");
    CHECK_THROWS(m.set_position_targets(t, std::vector<uint8_t>(t.size() - 1, 1)), INV,
                 "the target mask has 143 flags");
    CHECK_THROWS(m.set_position_targets(t, std::vector<uint8_t>()), INV, "0 flags");
    CHECK_THROWS(m.set_position_targets(t, std::vector<uint8_t>(t.size(), 0)), INV,
                 "constrain nothing");
    CHECK_THROWS(m.set_position_targets(std::vector<float>(t.size(), NAN)), INV,
                 "constrain nothing");
    CHECK_THROWS(m.set_position_targets(std::vector<float>(17 * J * 3)), INV,
                 "cover 17 frames; the session has 16");
    CHECK_THROWS(m.set_position_targets(t, static_cast<FlameConvention>(6)), INV, "convention");
    CHECK_THROWS(m.set_position_targets(nullptr, 72, nullptr, 0), INV, "`targets` is NULL");
    CHECK_THROWS(m.set_position_targets(t.data(), t.size(), nullptr, 5), INV, "`mask` is NULL");
    for (float scale : {-0.1f, NAN, 100.5f, INFINITY}) {
        flame::TargetParams q;
        q.scale = scale;
        CHECK_THROWS(m.set_target_params(q), INV, "target scale");
    }
    for (int32_t schedule : {2, -1}) {
        flame::TargetParams q;
        q.schedule = schedule;
        CHECK_THROWS(m.set_target_params(q), INV, "unknown target schedule " + std::to_string(schedule));
    }
    flame::TargetParams small;
    small.struct_size = 8;
    CHECK_THROWS(m.set_target_params(small), INV, "struct_size");
    CHECK_NOTHROW(m.set_target_params());
    flame::Session empty;
    CHECK_THROWS(empty.clear_position_targets(), INV, "session");
    CHECK_THROWS(empty.target_loss(), INV, "session");
}

static void test_moves() {
    flame::Model a = flame::Model::load(g_model_path);
    flame::Model b = std::move(a);
    CHECK(!a && b);
    CHECK_THROWS(a.info(), FLAME_STATUS_INVALID_ARGUMENT, "model");
    CHECK_THROWS(a.session(), FLAME_STATUS_INVALID_ARGUMENT, "model");
    flame::Model c;
    c = std::move(b);
    CHECK(!b && c);

    // A session moved mid-generation keeps its state and its progress callback.
    flame::Session s1 = c.session(reference_params());
    int calls = 0;
    s1.on_progress([&calls](uint32_t, uint32_t) { ++calls; });
    s1.set_prompt(REF_PROMPT);
    s1.step();
    flame::Session s2 = std::move(s1);
    CHECK(!s1 && s2);
    CHECK_THROWS(s1.step(), FLAME_STATUS_INVALID_ARGUMENT, "session");
    CHECK(s2.progress().done == 1);
    while (s2.step() > 0) {
    }
    CHECK(calls == static_cast<int>(ref_steps));
    CHECK(same(s2.read(), g_cli));

    // Move assignment onto a live session frees the old one.
    flame::Session s3 = c.session(reference_params());
    s3.set_prompt("a person jumps.");
    s3 = std::move(s2);
    CHECK(same(s3.read(), g_cli));
    flame::Session empty;
    CHECK_THROWS(empty.progress(), FLAME_STATUS_INVALID_ARGUMENT, "session");
}

// The session keeps the model alive after the Model object is gone.
static void test_session_outlives_model() {
    flame::Session s;
    {
        flame::Model model = flame::Model::load(g_model_path);
        s = model.session(reference_params());
    }
    CHECK(same(run(s), g_cli));
}

static void test_progress_exception() {
    flame::Model model = flame::Model::load(g_model_path);
    flame::Session s = model.session(reference_params());
    s.on_progress([](uint32_t done, uint32_t) {
        if (done == 1) {
            throw std::logic_error("stop at 1");
        }
    });
    s.set_prompt(REF_PROMPT);
    bool thrown = false;
    try {
        s.step();
    } catch (const std::logic_error &e) {
        thrown = std::string(e.what()) == "stop at 1";
    }
    CHECK(thrown);
    // The step itself completed, and the session goes on.
    CHECK(s.progress().done == 1);
    while (s.step() > 0) {
    }
    CHECK(same(s.read(), g_cli));
}

static void test_cancel() {
    flame::Model model = flame::Model::load(g_model_path);
    flame::SessionParams p;
    p.frames = quick_mode() ? 40 : 300;
    p.steps = quick_mode() ? 20 : 200;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.threads = 1;
    flame::Session s = model.session(p);
    std::atomic<uint32_t> done{0};
    s.on_progress([&done](uint32_t d, uint32_t) { done = d; });
    s.set_prompt(REF_PROMPT);
    std::thread canceller([&s, &done] {
        while (done < 2) {
            std::this_thread::yield();
        }
        s.cancel();
    });
    FlameStatus status = FLAME_STATUS_OK;
    try {
        while (s.step() > 0) {
        }
    } catch (const flame::Error &e) {
        status = e.status();
    }
    canceller.join();
    CHECK(status == FLAME_STATUS_CANCELLED);
    CHECK_NOTHROW(s.step());  // retried
}

// Model info's latent/sample_dim, sample_shape(), read_frames() and read_motion() on the
// families that sample the motion itself: the sampled space is frames x feature_dim and a read
// has the session's frames.
static void test_sample_shape_and_read_frames() {
    std::string dir = g_model_path.substr(0, g_model_path.find_last_of('/') + 1);
    struct Case {
        const char *file;
        uint32_t dim, joints;
    };
    for (const Case &c : {Case{"flame_tiny.safetensors", FLAME_TINY_DIM, 24},
                          Case{"mdm_tiny.safetensors", 263, 22}}) {
        flame::Model model = flame::Model::load(dir + c.file);
        flame::ModelInfo info = model.info();
        CHECK(!info.latent && info.sample_dim == c.dim && info.feature_dim == c.dim);
        CHECK(info.joint_count == c.joints);
        flame::SessionParams p;
        p.frames = 12;
        p.steps = 2;
        p.sampler = FLAME_SAMPLER_DDIM;
        p.seed = 1;
        p.threads = 1;
        flame::Session s = model.session(p);
        flame::SampleShape shape = s.sample_shape();
        CHECK(shape.rows == 12 && shape.dim == c.dim && shape.size() == 12u * c.dim);
        CHECK_THROWS(s.read_frames(), FLAME_STATUS_WRONG_STATE, "no sample yet");
        CHECK_THROWS(s.read_frames(FLAME_WHICH_ESTIMATE), FLAME_STATUS_WRONG_STATE,
                     "no clean-motion estimate");
        CHECK_THROWS(s.read_motion(), FLAME_STATUS_WRONG_STATE, "no sample yet");
        CHECK_THROWS(s.read_frames(static_cast<FlameWhich>(2)), FLAME_STATUS_INVALID_ARGUMENT,
                     "unknown `which` 2");
        std::vector<float> noise(shape.size());
        for (std::size_t i = 0; i < noise.size(); i++) {
            noise[i] = 0.5f * std::sin(0.1f * static_cast<float>(i));
        }
        CHECK_THROWS(s.set_noise(noise.data(), noise.size() - 1), FLAME_STATUS_INVALID_ARGUMENT,
                     "12 rows");
        CHECK_NOTHROW(s.set_noise(noise));
        s.set_prompt(REF_PROMPT);
        s.step();
        CHECK(s.read_frames() == 12 && s.read_frames(FLAME_WHICH_ESTIMATE) == 12);
        flame::Motion m = s.read_motion(FLAME_WHICH_ESTIMATE, FLAME_LAYOUT_GLOBAL_POSITIONS);
        CHECK(m.frames == 12 && m.values.size() == 12u * c.joints * 3);
        CHECK(m.per_frame() == c.joints * 3);
        flame::Motion f = s.read_motion();
        CHECK(f.frames == 12 && f.per_frame() == c.dim && same(f.values, s.read()));
        s.reset();
        CHECK_THROWS(s.read_frames(), FLAME_STATUS_WRONG_STATE, "no sample yet");
        CHECK(s.sample_shape().rows == 12);
    }
    flame::Motion empty;
    CHECK(empty.per_frame() == 0);
}

// A latent model (tests/fixtures/mola_tiny.safetensors, MoLA): 60 frames are a latent of
// 60 / 4 + 1 = 16 x 16 (tests/fixtures/mola_expected.json); reads have the decoder's length.
static void test_latent_model() {
    std::string dir = g_model_path.substr(0, g_model_path.find_last_of('/') + 1);
    flame::Model model = flame::Model::load(dir + "mola_tiny.safetensors");
    flame::ModelInfo info = model.info();
    CHECK(info.latent && info.sample_dim == 16 && info.feature_dim == 263);
    flame::SessionParams p;
    p.frames = 60;
    p.steps = 3;
    p.seed = 3;
    p.threads = 1;
    flame::Session s = model.session(p);
    flame::SampleShape shape = s.sample_shape();
    CHECK(shape.rows == 16 && shape.dim == 16);
    CHECK_THROWS(s.set_noise(std::vector<float>(60 * 263)), FLAME_STATUS_INVALID_ARGUMENT,
                 "16 rows");
    std::vector<float> noise(shape.size());
    for (std::size_t i = 0; i < noise.size(); i++) {
        noise[i] = 1.5f * std::sin(0.37f * static_cast<float>(i));
    }
    CHECK_NOTHROW(s.set_noise(noise));
    run(s);
    flame::Motion m = s.read_motion();
    CHECK(m.frames == s.read_frames() && m.frames >= 10 && m.frames <= 63);
    CHECK(m.per_frame() == 263 && m.values.size() == m.frames * 263u);
    flame::Motion pos = s.read_motion(FLAME_WHICH_ESTIMATE, FLAME_LAYOUT_GLOBAL_POSITIONS);
    CHECK(pos.frames == s.read_frames(FLAME_WHICH_ESTIMATE) && pos.per_frame() == 22 * 3);
}

// Prompts per time stage (flame::Stage, Session::set_prompt_stages). On a model that takes one
// prompt (MDM) one stage is set_prompt with its text, bit for bit, and more are refused; on
// FineMoGen (tests/fixtures/finemogen_tiny.safetensors, skipped when absent) 24 + 31 frames
// sample 2 x 31 rows and read back as 55 finite frames.
static void test_prompt_stages() {
    std::string dir = g_model_path.substr(0, g_model_path.find_last_of('/') + 1);
    flame::Model mdm = flame::Model::load(dir + "mdm_tiny.safetensors");
    flame::SessionParams p;
    p.frames = 16;
    p.steps = 3;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.seed = 5;
    p.threads = 1;
    std::vector<float> plain;
    {
        flame::Session s = mdm.session(p);
        plain = run(s, REF_PROMPT);
    }
    {
        flame::Session s = mdm.session(p);
        s.set_prompt_stages({{REF_PROMPT, 16}});
        CHECK(s.sample_shape().rows == 16 && s.sample_shape().dim == 263);
        while (s.step() > 0) {
        }
        CHECK(same(s.read(), plain));
    }
    {
        flame::Session s = mdm.session(p);
        CHECK_THROWS(s.set_prompt_stages({{"a person walks", 8}, {"a person jumps", 8}}),
                     FLAME_STATUS_INVALID_ARGUMENT, "a single stage without part texts");
        flame::Stage part{"a person walks", 16};
        part.left_arm = "waves";
        CHECK_THROWS(s.set_prompt_stages({part}), FLAME_STATUS_INVALID_ARGUMENT,
                     "a single stage without part texts");
        CHECK_THROWS(s.set_prompt_stages({}), FLAME_STATUS_INVALID_ARGUMENT, "0 stages");
        CHECK_THROWS(s.set_prompt_stages({{REF_PROMPT, 15}}), FLAME_STATUS_INVALID_ARGUMENT,
                     "the stages cover 15 frames, the session has 16");
        CHECK_THROWS(s.set_prompt_stages({{"", 16}}), FLAME_STATUS_INVALID_ARGUMENT,
                     "stage 0 has no text");
        flame::Stage nul{REF_PROMPT, 16};
        nul.pelvis = std::string("a\0b", 3);
        CHECK_THROWS(s.set_prompt_stages({nul}), FLAME_STATUS_INVALID_ARGUMENT,
                     "`stages[0].pelvis` contains a NUL byte");
        CHECK_THROWS(s.step(), FLAME_STATUS_WRONG_STATE, "prompt");  // nothing was set
    }

    std::FILE *f = std::fopen((dir + "finemogen_tiny.safetensors").c_str(), "rb");
    if (!f) {
        std::printf("skip FineMoGen stages: no %sfinemogen_tiny.safetensors\n", dir.c_str());
        return;
    }
    std::fclose(f);
    flame::Model fmg = flame::Model::load(dir + "finemogen_tiny.safetensors");
    p.frames = 55;
    p.steps = 4;
    p.seed = 1;
    flame::Session s = fmg.session(p);
    s.set_prompt_stages({{"a person walks forward", 24}, {"a person jumps", 31}});
    CHECK(s.sample_shape().rows == 2 * 31 && s.sample_shape().dim == 263);
    while (s.step() > 0) {
    }
    flame::Motion m = s.read_motion();
    CHECK(m.frames == 55 && m.values.size() == 55u * 263);
    CHECK(std::all_of(m.values.begin(), m.values.end(), [](float v) { return std::isfinite(v); }));
    s.reset();
    s.step();
    CHECK_THROWS(s.set_prompt_stages({{"a person walks", 25}, {"a person jumps", 30}}),
                 FLAME_STATUS_WRONG_STATE, "before the first step");
    flame::Stage waving{"a person jumps", 31};
    waving.right_arm = "waves";
    CHECK_NOTHROW(s.set_prompt_stages({{"a person walks", 24}, waving}));
}

// CleanupParams and Session::read_cleaned: the defaults, the frame rate (40 frames at 20 fps are
// 59 at 30, frames at common times copied), separate root motion on a grounded root bone,
// errors as exceptions naming the value, and a glTF export with a cleanup.
static void test_cleanup() {
    flame::Model model = flame::Model::load(g_model_path);
    const flame::ModelInfo info = model.info();
    flame::SessionParams p = reference_params();
    p.frames = 40;
    flame::Session s = model.session(p);
    s.set_prompt(REF_PROMPT);
    s.step();  // two steps: generic poses (the final motion of the tiny model saturates)
    s.step();

    flame::CleanupParams game;
    CHECK(game.struct_size == sizeof(FlameCleanupParams));
    CHECK(game.feet == static_cast<int32_t>(flame::Feet::Lock) && game.ground == 1);
    CHECK(game.root_motion == static_cast<int32_t>(flame::RootMotion::Keep) && game.fps == 0.0f);
    flame::CleanupParams none = flame::CleanupParams::none();
    CHECK(none.feet == static_cast<int32_t>(flame::Feet::Off) && none.ground == 0);

    // Every step off: the raw read.
    CHECK(same(s.read_cleaned(none, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_QUAT_XYZW,
                              FLAME_CONVENTION_UNITY),
               s.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_UNITY)));

    // Rotation matrices: a quaternion layout's signs may differ between tracks of another
    // frame count (q and -q are the same rotation).
    flame::CleanupParams thirty = flame::CleanupParams::none();
    thirty.set_fps(30.0f);
    const std::vector<float> raw =
        s.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_MATRIX, FLAME_CONVENTION_GLTF);
    const std::vector<float> out =
        s.read_cleaned(thirty, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_MATRIX,
                       FLAME_CONVENTION_GLTF);
    const std::size_t width = flame::values_per_frame(FLAME_LAYOUT_LOCAL_MATRIX, info);
    CHECK(width == 24 * 9 && raw.size() == 40 * width);
    CHECK(out.size() == 59 * width);
    CHECK(s.read_cleaned_len(thirty, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_MATRIX,
                             FLAME_CONVENTION_GLTF) == out.size());
    bool common = out.size() == 59 * width && raw.size() == 40 * width;
    for (std::size_t k = 0; common && 3 * k < 59; k++) {
        common = std::memcmp(out.data() + 3 * k * width, raw.data() + 2 * k * width,
                             width * sizeof(float)) == 0;
    }
    CHECK(common);
    std::vector<float> small(40 * 3);
    CHECK_THROWS(s.read_cleaned(small.data(), small.size(), thirty, FLAME_WHICH_SAMPLE,
                                FLAME_LAYOUT_ROOT_TRANSLATION),
                 FLAME_STATUS_BUFFER_TOO_SMALL, "");

    // Separate root motion: the root bone on the ground (Unity: y), the pelvis + the bone =
    // the kept pelvis.
    flame::CleanupParams separate = flame::CleanupParams::none();
    separate.set_root_motion(flame::RootMotion::Separate);
    const std::vector<float> bone = s.read_cleaned(separate, FLAME_WHICH_SAMPLE,
                                                   FLAME_LAYOUT_ROOT_BONE, FLAME_CONVENTION_UNITY);
    const std::vector<float> pelvis = s.read_cleaned(
        separate, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_UNITY);
    const std::vector<float> keep =
        s.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_UNITY);
    CHECK(bone.size() == 40 * 3 && pelvis.size() == 40 * 3 && keep.size() == 40 * 3);
    bool grounded = bone.size() == 40 * 3 && pelvis.size() == 40 * 3 && keep.size() == 40 * 3;
    bool sums = grounded;
    for (std::size_t f = 0; grounded && f < 40; f++) {
        grounded = bone[f * 3 + 1] == 0.0f;
        sums = sums && std::fabs(bone[f * 3] + pelvis[f * 3] - keep[f * 3]) < 1e-5f &&
               std::fabs(bone[f * 3 + 2] + pelvis[f * 3 + 2] - keep[f * 3 + 2]) < 1e-5f;
    }
    CHECK(grounded);
    CHECK(sums);

    // Errors name the value.
    flame::CleanupParams bad;
    bad.set_fps(std::nanf(""));
    CHECK_THROWS(s.read_cleaned(bad), FLAME_STATUS_INVALID_ARGUMENT, "got NaN");
    bad = flame::CleanupParams();
    bad.contact_height = -0.5f;
    CHECK_THROWS(s.read_cleaned(bad), FLAME_STATUS_INVALID_ARGUMENT, "got -0.5");
    CHECK_THROWS(s.read_cleaned(game, FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_BONE),
                 FLAME_STATUS_INVALID_ARGUMENT, "root");

    // glTF with the cleanup: a node named "root".
    flame::GltfParams g;
    g.cleanup = &separate;
    const std::vector<uint8_t> glb = s.write_gltf(FLAME_WHICH_SAMPLE, g);
    const std::string bytes(glb.begin(), glb.end());
    CHECK(bytes.find("\"name\":\"root\"") != std::string::npos);
    const std::vector<uint8_t> plain = s.write_gltf();
    CHECK(std::string(plain.begin(), plain.end()).find("\"name\":\"root\"") == std::string::npos);
}

// A loop made by the session (SessionParams::looped, ABI 4), as test_cleanup.c's test_loop:
// both passes counted (steps 4 are 8), the finished sample read as the cycle's 40 frames, its
// smoothed positions equal to the CLI's `--loop` output, and the refusals as flame::Error.
static void test_loop() {
    auto loop_params = [] {
        flame::SessionParams p;
        p.frames = 40;
        p.steps = 4;
        p.sampler = FLAME_SAMPLER_DDIM;
        p.seed = 5;
        p.threads = 1;
        p.looped = 1;
        return p;
    };
    flame::Model model = flame::Model::load(g_model_path);
    {
        flame::Session s = model.session(loop_params());
        s.set_prompt(REF_PROMPT);
        std::vector<flame::Progress> seen;
        s.on_progress([&seen](uint32_t done, uint32_t total) { seen.push_back({done, total}); });
        flame::Progress at = s.progress();
        CHECK(at.done == 0 && at.total == 8);
        bool order = true;
        for (uint32_t want = 8; want-- > 0;) {
            order = order && s.step() == want;
        }
        CHECK(order);
        at = s.progress();
        CHECK(at.done == 8 && at.total == 8);
        bool counted = seen.size() == 8;
        for (std::size_t k = 0; counted && k < seen.size(); k++) {
            counted = seen[k].done == k + 1 && seen[k].total == 8;
        }
        CHECK(counted);
        // The cycle's frames; the raw features without the next cycle's first frame.
        CHECK(s.read_frames() == 40);
        flame::Motion f = s.read_motion();
        CHECK(f.frames == 40 && f.values.size() == 40u * FLAME_TINY_DIM);
        // A read with no cleanup still wraps: what the CLI wrote with --feet off --ground off.
        flame::Motion pos = s.read_motion(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_GLOBAL_POSITIONS,
                                          FLAME_CONVENTION_NATIVE, FLAME_READ_SMOOTH);
        CHECK(pos.frames == 40 && pos.values.size() == 40u * 24 * 3);
        if (!g_loop_positions.empty()) {
            size_t rows = 0, cols = 0;
            float *cli = read_npy_f32(g_loop_positions.c_str(), &rows, &cols);
            CHECK(cli && rows == 40 && cols == 24 * 3);
            CHECK(cli && same_bits(pos.values.data(), pos.values.size(), cli, rows * cols));
            free(cli);
        } else {
            std::printf("loop: no LOOP_POSITIONS_NPY, the CLI comparison skipped\n");
        }
        // The loop's edit is its own.
        CHECK_THROWS(s.set_reference(std::vector<float>(FLAME_TINY_DIM), 1, FLAME_TINY_DIM),
                     FLAME_STATUS_INVALID_ARGUMENT, "its own edit");
    }
    // Refused when the session is made.
    flame::SessionParams p = loop_params();
    p.frames = 12;
    CHECK_THROWS(model.session(p), FLAME_STATUS_INVALID_ARGUMENT, "at least 40 frames");
    p = loop_params();
    p.looped = 2;
    CHECK_THROWS(model.session(p), FLAME_STATUS_INVALID_ARGUMENT, "`looped`");
    p = loop_params();
    p.looped = 0;  // the plain session of before
    CHECK(model.session(p).progress().total == 4);
    std::string dir = g_model_path.substr(0, g_model_path.find_last_of('/') + 1);
    flame::Model mola = flame::Model::load(dir + "mola_tiny.safetensors");
    p = loop_params();
    p.frames = 60;
    CHECK_THROWS(mola.session(p), FLAME_STATUS_INVALID_ARGUMENT, "samples a latent");
}

int main(int argc, char **argv) {
    if (argc < 3 || argc > 5) {
        std::fprintf(stderr, "usage: %s MODEL REFERENCE_NPY [STEPS [LOOP_POSITIONS_NPY]]\n",
                     argv[0]);
        return 2;
    }
    ref_steps = argc >= 4 ? static_cast<uint32_t>(std::strtoul(argv[3], nullptr, 10)) : 10;
    g_model_path = argv[1];
    g_loop_positions = argc == 5 ? argv[4] : "";
    size_t rows = 0, cols = 0;
    float *ref = read_npy_f32(argv[2], &rows, &cols);
    if (!ref || rows < 2 || cols != FLAME_TINY_DIM || ref_steps < 2) {
        std::fprintf(stderr, "cannot read a frames x 147 float32 array from %s (or STEPS < 2)\n",
                     argv[2]);
        return 2;
    }
    ref_frames = static_cast<uint32_t>(rows);
    g_values = rows * cols;
    g_cli.assign(ref, ref + rows * cols);
    free(ref);

    // The same generation through the C API alone.
    FlameModel *m = nullptr;
    CHECK_OK(flame_model_load(g_model_path.c_str(), nullptr, &m));
    FlameSessionParams p;
    ref_params(&p);
    FlameStatus st;
    size_t n = 0;
    float *x = generate(m, &p, REF_PROMPT, &n, &st);
    CHECK_OK(st);
    if (x) {
        g_c.assign(x, x + n);
    }
    free(x);
    flame_model_free(m);
    CHECK(same(g_c, g_cli));

    double t0 = now_seconds();
    try {
        test_versions();
        test_happy_path();
        test_load_from_memory();
        test_errors();
        test_prompt_info();
        test_prompt_from();
        test_latent_tuning();
        test_editing();
        test_edit_params_tasks_parts();
        test_reference_poses();
        test_position_targets();
        test_moves();
        test_session_outlives_model();
        test_progress_exception();
        test_cancel();
        test_sample_shape_and_read_frames();
        test_latent_model();
        test_prompt_stages();
        test_cleanup();
        test_loop();
    } catch (const std::exception &e) {
        check_record(0, __FILE__, __LINE__, "unexpected exception", e.what());
    }
    std::printf("test_cpp: %.2f s\n", now_seconds() - t0);
    return check_summary();
}
