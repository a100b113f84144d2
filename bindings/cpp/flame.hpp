// libflame for C++17: a header-only RAII wrapper over the C ABI (flame.h).
//
//   flame::Model model = flame::Model::load("flame_hml3d.safetensors");
//   flame::SessionParams params;            // the model file's defaults
//   params.frames = 120;
//   params.steps = 50;
//   params.sampler = FLAME_SAMPLER_DDIM;
//   flame::Session session = model.session(params);
//   session.set_prompt("a person jumps twice");
//   while (session.step() > 0) {
//       std::vector<float> preview = session.read(FLAME_WHICH_ESTIMATE);
//   }
//   std::vector<float> motion = session.read();  // raw features, frames x feature_dim
//   // frames = session.read_frames(): the session's, or the length a latent model decodes
//   std::vector<float> quats = session.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_QUAT_XYZW,
//                                           FLAME_CONVENTION_UNITY);  // frames x joints x 4
//   std::vector<uint8_t> glb = session.write_gltf();  // a glTF 2.0 file (binary, .glb)
//   // Game-ready poses: feet locked, on the floor, 30 fps, the travel on a root bone.
//   flame::CleanupParams clean;
//   clean.set_fps(30).set_root_motion(flame::RootMotion::Separate);
//   std::vector<float> game = session.read_cleaned(clean, FLAME_WHICH_SAMPLE,
//                                                  FLAME_LAYOUT_LOCAL_QUAT_XYZW,
//                                                  FLAME_CONVENTION_UNITY);
//
//   // Continuous motion from a timeline of prompts (docs/streams.md):
//   flame::Stream stream(model);              // or model.stream(flame::StreamParams())
//   stream.push("a person walks forward.", 120);
//   stream.push("a person waves.", 80);
//   flame::StreamStatus st = stream.pump(4);  // e.g. once per engine frame: at most 4 steps
//   stream.set_playhead(playhead);            // frames first_frame..ready can be read
//   std::vector<float> pose = stream.read(playhead, 1, FLAME_LAYOUT_LOCAL_QUAT_XYZW,
//                                         FLAME_CONVENTION_UNITY);
//
// Ownership: Model, Session and Stream own their C handle and are move-only. A Session or a
// Stream keeps its model alive on the C side, so it stays usable after the Model object that
// made it is destroyed. A moved-from object is empty: its calls throw
// flame::Error(FLAME_STATUS_INVALID_ARGUMENT).
//
// Errors: every failing call throws flame::Error, carrying the FlameStatus and the library's
// message (flame_last_error() at the time of the failure).
//
// Threads: a Model may be shared by any number of threads, sessions and streams; a Session or
// a Stream is used by one thread at a time, except Session::cancel() and Stream::cancel(), which
// any thread may call while another is inside Session::step() or Stream::pump().

#ifndef FLAME_HPP
#define FLAME_HPP

#include <cstddef>
#include <cstdint>
#include <exception>
#include <functional>
#include <initializer_list>
#include <memory>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

#include "flame.h"

namespace flame {

// A failed libflame call: its status and the library's message.
class Error : public std::runtime_error {
public:
    Error(FlameStatus status, const std::string& message)
        : std::runtime_error(std::string(flame_status_string(status)) + ": " + message),
          status_(status),
          message_(message) {}

    FlameStatus status() const noexcept { return status_; }
    // The library's message alone (what() prefixes the status name).
    const std::string& message() const noexcept { return message_; }

private:
    FlameStatus status_;
    std::string message_;
};

namespace detail {

// Throws for a failing status, with this thread's last error message.
inline void check(FlameStatus status) {
    if (status != FLAME_STATUS_OK) {
        // Copy the message before anything else can call into libflame.
        std::string message = flame_last_error();
        throw Error(status, message);
    }
}

// A text argument as a C string; throws for an embedded NUL (`name` names it).
inline const char* c_text(const std::string& s, const std::string& name) {
    if (s.find('\0') != std::string::npos) {
        throw Error(FLAME_STATUS_INVALID_ARGUMENT, "`" + name + "` contains a NUL byte");
    }
    return s.c_str();
}

}  // namespace detail

// The library's ABI version; compare with FLAME_ABI_VERSION (the header's) at startup.
inline uint32_t abi_version() noexcept {
    return flame_abi_version();
}

// The library's version, e.g. "0.1.0".
inline std::string version() {
    return flame_version_string();
}

// Options of Model::load; the defaults come from flame_model_params_default.
struct ModelParams : FlameModelParams {
    ModelParams() : FlameModelParams() { detail::check(flame_model_params_default(this)); }
};

// Settings of one generation; the defaults come from flame_session_params_default (every
// setting from the model file, seed 0, one thread per core). `respacing` is a plain
// `const char*`: it must stay valid until the Session is constructed. `looped = 1` (ABI 4)
// generates a loop of `frames` frames (flame.h): step() and progress() count both of its
// passes, and the finished sample's read_frames() is the cycle's `frames`.
struct SessionParams : FlameSessionParams {
    SessionParams() : FlameSessionParams() { detail::check(flame_session_params_default(this)); }
};

// Editing settings (Session::set_edit_params); the defaults come from flame_edit_params_default
// (the model family's method, edit_till 0.2, paste on, 4 seam frames).
struct EditParams : FlameEditParams {
    EditParams() : FlameEditParams() { detail::check(flame_edit_params_default(this)); }
};

// How strongly position targets steer (Session::set_target_params); the defaults come from
// flame_target_params_default (scale 0.6, FLAME_TARGET_SCHEDULE_MPGD).
struct TargetParams : FlameTargetParams {
    TargetParams() : FlameTargetParams() { detail::check(flame_target_params_default(this)); }
};

// How Session::write_gltf exports; the defaults come from flame_gltf_params_default (GLB, no
// read flags, the model's frame rate, the animation named after the prompt, no cleanup).
// `name` is a plain `const char*` (NULL = the prompt's) and `cleanup` a plain
// `const FlameCleanupParams*` (NULL = the raw poses; point it at a CleanupParams): both must
// stay valid for the call.
struct GltfParams : FlameGltfParams {
    GltfParams() : FlameGltfParams() { detail::check(flame_gltf_params_default(this)); }
};

// FlameCleanupParams::feet (the C header names no enum for it: no function takes one by type).
enum class Feet : int32_t {
    Off = 0,   // the raw poses: feet may slide
    Lock = 1,  // each planted foot pinned where it stands, the leg solved by two-bone IK
};

// FlameCleanupParams::root_motion: where the clip's horizontal travel goes.
enum class RootMotion : int32_t {
    Keep = 0,     // on the pelvis, as the model made it
    InPlace = 1,  // removed: the pelvis stays over the origin
    Separate = 2, // on a root bone under the pelvis (FLAME_LAYOUT_ROOT_BONE; glTF node "root")
};

// Post-processing of Session::read_cleaned and of a glTF export (GltfParams::cleanup). The
// defaults come from flame_cleanup_params_default, game-ready: feet locked, the floor at 0,
// root motion kept, no wrap, the model's frame rate. CleanupParams::none() has every step off
// (set fps or root motion on it to change only that). A `fps` other than the model's changes
// the frame count (the first and last frames' times kept: 40 frames at 20 fps are 59 at 30).
struct CleanupParams : FlameCleanupParams {
    CleanupParams() : FlameCleanupParams() { detail::check(flame_cleanup_params_default(this)); }

    static CleanupParams none() {
        CleanupParams p;
        p.feet = static_cast<int32_t>(Feet::Off);
        p.ground = 0;
        return p;
    }
    CleanupParams& set_feet(Feet f) noexcept {
        feet = static_cast<int32_t>(f);
        return *this;
    }
    CleanupParams& set_root_motion(RootMotion r) noexcept {
        root_motion = static_cast<int32_t>(r);
        return *this;
    }
    CleanupParams& set_fps(float f) noexcept {
        fps = f;
        return *this;
    }
};

// What Model::info reports, copied: it stays valid after the model is gone.
struct ModelInfo {
    uint32_t feature_dim = 0;
    uint32_t joint_count = 0;
    uint32_t max_frames = 0;
    uint32_t default_frames = 0;
    uint32_t default_steps = 0;
    uint32_t num_timesteps = 0;
    FlameSampler default_sampler = FLAME_SAMPLER_DEFAULT;
    float fps = 0.0f;
    float default_guidance = 0.0f;
    float default_eta = 0.0f;
    std::string architecture;
    std::string motion_format;
    std::string text_encoder;
    std::vector<std::string> joint_names;
    std::vector<int32_t> joint_parents;
    // The model samples a latent that its decoder turns into motion (MoLA): a read's frames are
    // then Session::read_frames(), the length the decoder decides, and masks and reference
    // motions do not apply.
    bool latent = false;
    // Channels per row of the sampled space (feature_dim, or the latent's channels).
    uint32_t sample_dim = 0;
    // The model has a trajectory ControlNet (MotionLCM control files): Session::set_control.
    bool control = false;
};

// The shape of a session's sampled space, what Session::set_noise takes: rows x dim values
// (frames x feature_dim, or a latent model's latent).
struct SampleShape {
    uint32_t rows = 0;
    uint32_t dim = 0;
    std::size_t size() const noexcept { return static_cast<std::size_t>(rows) * dim; }
};

// Floats per frame of `layout` for a model (0 for a layout not named here): the frame count of
// a Session::read_cleaned whose fps changed it is values.size() / values_per_frame(...).
inline std::size_t values_per_frame(FlameLayout layout, const ModelInfo& info) noexcept {
    const std::size_t j = info.joint_count;
    switch (layout) {
    case FLAME_LAYOUT_FEATURES: return info.feature_dim;
    case FLAME_LAYOUT_ROOT_TRANSLATION:
    case FLAME_LAYOUT_ROOT_BONE: return 3;
    case FLAME_LAYOUT_LOCAL_QUAT_XYZW:
    case FLAME_LAYOUT_LOCAL_QUAT_WXYZ:
    case FLAME_LAYOUT_GLOBAL_QUAT_XYZW:
    case FLAME_LAYOUT_GLOBAL_QUAT_WXYZ: return j * 4;
    case FLAME_LAYOUT_LOCAL_MATRIX: return j * 9;
    case FLAME_LAYOUT_LOCAL6D: return j * 6;
    case FLAME_LAYOUT_GLOBAL_POSITIONS: return j * 3;
    case FLAME_LAYOUT_FOOT_CONTACTS: return 4;
    default: return 0;
    }
}

// What Session::read_motion returns: `frames` frames of values, frame-major.
struct Motion {
    std::vector<float> values;
    uint32_t frames = 0;
    // Values per frame of the layout read (0 when there are no frames).
    std::size_t per_frame() const noexcept { return frames ? values.size() / frames : 0; }
};

// What Session::prompt_info reports about the last prompt, copied (`dropped` stays valid after
// the next prompt): how it fitted the text encoder's window.
struct PromptInfo {
    uint32_t tokens = 0;         // of the whole prompt, special tokens included
    uint32_t kept = 0;           // those the text encoder saw (at most `window`)
    uint32_t window = 0;         // the encoder's window, special tokens included
    bool truncated = false;      // the window cut the prompt
    bool unconditional = false;  // an empty or blank prompt: generation without text
    std::string dropped;         // the text cut off, UTF-8 ("" when nothing was)
};

// One time stage of a prompt for Session::set_prompt_stages: what the whole body does (`text`)
// for `frames` frames, and optionally what single body parts do (the HuMMan-MoGen annotation's
// fields; "" = the part follows `text`). FineMoGen models compose stages and read the part
// texts; other models take one stage without part texts.
//
//   session.set_prompt_stages({{"a person walks forward", 24}, {"a person jumps", 31}});
struct Stage {
    Stage() = default;
    Stage(std::string text_, uint32_t frames_) : text(std::move(text_)), frames(frames_) {}

    std::string text;
    uint32_t frames = 0;
    std::string head;
    std::string stem;  // the spine
    std::string left_arm;
    std::string right_arm;
    std::string left_leg;
    std::string right_leg;
    std::string pelvis;  // the root's trajectory
};

namespace detail {

// `s` as a FlameStage pointing into its strings (valid while `s` is, unchanged): NULL for an
// empty part text. `where` names the stage in errors ("stages[2]", "stage").
inline FlameStage c_stage(const Stage& s, const std::string& where) {
    auto part = [&where](const std::string& t, const char* name) -> const char* {
        const char* c = c_text(t, where + "." + name);
        return t.empty() ? nullptr : c;
    };
    FlameStage st{};
    st.struct_size = sizeof st;
    st.frames = s.frames;
    st.text = c_text(s.text, where + ".text");
    st.head = part(s.head, "head");
    st.stem = part(s.stem, "stem");
    st.left_arm = part(s.left_arm, "left_arm");
    st.right_arm = part(s.right_arm, "right_arm");
    st.left_leg = part(s.left_leg, "left_leg");
    st.right_leg = part(s.right_leg, "right_leg");
    st.pelvis = part(s.pelvis, "pelvis");
    return st;
}

}  // namespace detail

// Settings of a stream (Stream, Model::stream); the defaults come from
// flame_stream_params_default: chunks of the model's default frame count (`chunk` 0), 20 frames
// of overlap, 60 of lookahead, a window of 1200 frames, the model file's steps, sampler and
// guidance, seed 0, one thread per core.
struct StreamParams : FlameStreamParams {
    StreamParams() : FlameStreamParams() { detail::check(flame_stream_params_default(this)); }
};

// Where a stream stands (Stream::pump, Stream::status), copied.
struct StreamStatus {
    uint32_t steps = 0;        // denoiser steps run by this pump (0 from status())
    uint64_t ready = 0;        // frames generated on the timeline: first_frame..ready can be read
    uint64_t first_frame = 0;  // the first frame still held (older ones were dropped)
    uint64_t playhead = 0;     // Stream::set_playhead's
    bool starving = false;     // fewer than `lookahead` frames ahead and no segment left: push more
};

// Steps done and the total of a generation.
struct Progress {
    uint32_t done = 0;
    uint32_t total = 0;
};

class Session;
class Stream;

// A loaded model: immutable, shareable by threads; move-only owner of a FlameModel.
class Model {
public:
    // An empty model (as after a move).
    Model() noexcept = default;
    // Takes ownership of a handle from flame_model_load (NULL makes an empty model).
    explicit Model(FlameModel* owned) noexcept : handle_(owned) {}

    static Model load(const std::string& path, const ModelParams& params = ModelParams()) {
        FlameModel* handle = nullptr;
        detail::check(flame_model_load(path.c_str(), &params, &handle));
        return Model(handle);
    }

    // The bytes are copied: the caller's buffer may go as soon as this returns.
    static Model load_from_memory(const void* bytes, std::size_t len,
                                  const ModelParams& params = ModelParams()) {
        FlameModel* handle = nullptr;
        detail::check(flame_model_load_from_memory(static_cast<const uint8_t*>(bytes), len, &params,
                                                   &handle));
        return Model(handle);
    }

    static Model load_from_memory(const std::vector<uint8_t>& bytes,
                                  const ModelParams& params = ModelParams()) {
        return load_from_memory(bytes.data(), bytes.size(), params);
    }

    Model(const Model&) = delete;
    Model& operator=(const Model&) = delete;
    Model(Model&& other) noexcept : handle_(std::exchange(other.handle_, nullptr)) {}
    Model& operator=(Model&& other) noexcept {
        if (this != &other) {
            flame_model_free(handle_);
            handle_ = std::exchange(other.handle_, nullptr);
        }
        return *this;
    }
    // Releases this reference; sessions made from the model keep it alive.
    ~Model() { flame_model_free(handle_); }

    ModelInfo info() const {
        FlameModelInfo c{};
        c.struct_size = sizeof c;
        detail::check(flame_model_info(handle_, &c));
        ModelInfo info;
        info.feature_dim = c.feature_dim;
        info.joint_count = c.joint_count;
        info.max_frames = c.max_frames;
        info.default_frames = c.default_frames;
        info.default_steps = c.default_steps;
        info.num_timesteps = c.num_timesteps;
        info.default_sampler = static_cast<FlameSampler>(c.default_sampler);
        info.fps = c.fps;
        info.default_guidance = c.default_guidance;
        info.default_eta = c.default_eta;
        info.architecture = c.architecture ? c.architecture : "";
        info.motion_format = c.motion_format ? c.motion_format : "";
        info.text_encoder = c.text_encoder ? c.text_encoder : "";
        for (uint32_t j = 0; j < c.joint_count; ++j) {
            info.joint_names.emplace_back(c.joint_names && c.joint_names[j] ? c.joint_names[j]
                                                                            : "");
            info.joint_parents.push_back(c.joint_parents ? c.joint_parents[j] : -1);
        }
        info.latent = c.latent != 0;
        info.sample_dim = c.sample_dim;
        info.control = c.control != 0;
        return info;
    }

    // A new generation on this model (see Session).
    Session session(const SessionParams& params = SessionParams()) const;

    // A new stream on this model (see Stream).
    Stream stream(const StreamParams& params = StreamParams()) const;

    const FlameModel* get() const noexcept { return handle_; }
    // Gives up ownership: the caller frees the handle with flame_model_free.
    FlameModel* release() noexcept { return std::exchange(handle_, nullptr); }
    explicit operator bool() const noexcept { return handle_ != nullptr; }

private:
    FlameModel* handle_ = nullptr;
};

// One generation; move-only owner of a FlameSession (and of its worker threads).
class Session {
public:
    // Called on the stepping thread after every step with (steps done, steps total).
    using ProgressFn = std::function<void(uint32_t done, uint32_t total)>;

    // An empty session (as after a move).
    Session() noexcept = default;

    explicit Session(const Model& model, const SessionParams& params = SessionParams()) {
        detail::check(flame_session_new(model.get(), &params, &handle_));
    }

    Session(const Session&) = delete;
    Session& operator=(const Session&) = delete;
    // The progress hook lives on the heap, so the pointer the C side holds survives moves.
    Session(Session&& other) noexcept
        : handle_(std::exchange(other.handle_, nullptr)), hook_(std::move(other.hook_)) {}
    Session& operator=(Session&& other) noexcept {
        if (this != &other) {
            flame_session_free(handle_);
            handle_ = std::exchange(other.handle_, nullptr);
            hook_ = std::move(other.hook_);
        }
        return *this;
    }
    // Frees the session (joining its worker threads), then the progress hook it used.
    ~Session() { flame_session_free(handle_); }

    // Encoded once, here. The prompt may change between steps.
    void set_prompt(const std::string& prompt) {
        if (prompt.find('\0') != std::string::npos) {
            throw Error(FLAME_STATUS_INVALID_ARGUMENT, "`prompt` contains a NUL byte");
        }
        detail::check(flame_session_set_prompt(handle_, prompt.c_str()));
    }

    // The prompt `source` was given, as encoded there: no second run of the text encoder (a
    // prompt used for many generations is encoded once). `source` runs the same Model.
    void set_prompt_from(const Session& source) {
        detail::check(flame_session_set_prompt_from(handle_, source.handle_));
    }

    // Prompts per time stage, in order; their frames must add up to the session's. A FineMoGen
    // model composes them: its sample is then laid out stages x the longest stage rows
    // (sample_shape(), and what set_noise takes), while read() still returns the session's
    // frames, the stages one after the other. Any other model takes exactly one stage without
    // part texts, as set_prompt(stage.text), and refuses more (INVALID_ARGUMENT). Stage frame
    // counts can change only before the first step (WRONG_STATE after; reset() first).
    void set_prompt_stages(const std::vector<Stage>& stages) {
        std::vector<FlameStage> c;
        c.reserve(stages.size());
        for (std::size_t i = 0; i < stages.size(); ++i) {
            c.push_back(detail::c_stage(stages[i], "stages[" + std::to_string(i) + "]"));
        }
        detail::check(flame_session_set_prompt_stages(handle_, c.data(), c.size()));
    }

    // How the last prompt fitted the text encoder's window; throws WRONG_STATE before a prompt.
    PromptInfo prompt_info() const {
        FlamePromptInfo c{};
        c.struct_size = sizeof c;
        detail::check(flame_session_prompt_info(handle_, &c));
        PromptInfo info;
        info.tokens = c.tokens;
        info.kept = c.kept;
        info.window = c.window;
        info.truncated = c.truncated != 0;
        info.unconditional = c.unconditional != 0;
        info.dropped = c.dropped ? c.dropped : "";
        return info;
    }

    // x_T, sample_shape().rows x sample_shape().dim values (frames x feature_dim, or a latent
    // model's latent), frame-major; only before the first step (or after reset()).
    void set_noise(const float* noise, std::size_t len) {
        detail::check(flame_session_set_noise(handle_, noise, len));
    }
    void set_noise(const std::vector<float>& noise) { set_noise(noise.data(), noise.size()); }

    // The reference motion for editing, frames x dim: the model's dim and 1..the session's
    // frames (frames past a shorter reference cannot be kept).
    void set_reference(const float* features, uint32_t frames, uint32_t dim) {
        detail::check(flame_session_set_reference(handle_, features, frames, dim));
    }
    void set_reference(const std::vector<float>& features, uint32_t frames, uint32_t dim) {
        check_size(features.size(), frames, dim, "features");
        set_reference(features.data(), frames, dim);
    }

    // The keep-mask, frames x dim bytes (1 keeps the reference value).
    void set_mask(const uint8_t* mask, uint32_t frames, uint32_t dim) {
        detail::check(flame_session_set_mask(handle_, mask, frames, dim));
    }
    void set_mask(const std::vector<uint8_t>& mask, uint32_t frames, uint32_t dim) {
        check_size(mask.size(), frames, dim, "mask");
        set_mask(mask.data(), frames, dim);
    }

    // Keeps every feature of frames [start, end).
    void keep_frames(uint32_t start, uint32_t end) {
        detail::check(flame_session_keep_frames(handle_, start, end));
    }

    // Keeps the channels of these joints (FLAME_ROOT_TRANSLATION for the root path).
    void keep_joints(const int32_t* joints, std::size_t count) {
        detail::check(flame_session_keep_joints(handle_, joints, count));
    }
    void keep_joints(const std::vector<int32_t>& joints) {
        keep_joints(joints.data(), joints.size());
    }
    void keep_joints(std::initializer_list<int32_t> joints) {
        keep_joints(joints.begin(), joints.size());
    }

    // A smpl24_6d reference from poses, the inverse of read(): root = frames x 3 pelvis
    // positions, rotations = frames x 24 local rotations in `layout` (LOCAL_QUAT_XYZW/WXYZ,
    // LOCAL_MATRIX or LOCAL6D), both in `convention`.
    void set_reference_poses(const float* root, std::size_t root_len, const float* rotations,
                             std::size_t rotations_len, uint32_t frames, FlameLayout layout,
                             FlameConvention convention = FLAME_CONVENTION_NATIVE) {
        detail::check(flame_session_set_reference_poses(handle_, root, root_len, rotations,
                                                        rotations_len, frames, layout,
                                                        convention));
    }
    // Frames from the root's length (3 values per frame).
    void set_reference_poses(const std::vector<float>& root, const std::vector<float>& rotations,
                             FlameLayout layout,
                             FlameConvention convention = FLAME_CONVENTION_NATIVE) {
        if (root.size() % 3 != 0) {
            throw Error(FLAME_STATUS_INVALID_ARGUMENT,
                        "`root` has " + std::to_string(root.size()) +
                            " values, not a multiple of 3");
        }
        set_reference_poses(root.data(), root.size(), rotations.data(), rotations.size(),
                            static_cast<uint32_t>(root.size() / 3), layout, convention);
    }

    // Keeps a body part's channels on frames [start, end), adding to the mask.
    void keep_part(FlameBodyPart part, uint32_t start, uint32_t end) {
        detail::check(flame_session_keep_part(handle_, part, start, end));
    }

    // Replaces the mask with a standard editing task's.
    void set_task_mask(FlameEditTask task) {
        detail::check(flame_session_set_task_mask(handle_, task));
    }

    // Position targets for an editing task from a reference motion (frames x dim model-space
    // features): its joint positions where the task keeps them (MoLA's MPGD tasks). On a model
    // with a trajectory ControlNet (a MotionLCM control file) they become the control hint.
    void set_task_targets(const std::vector<float>& features, uint32_t frames, uint32_t dim,
                          FlameEditTask task) {
        check_size(features.size(), frames, dim, "features");
        detail::check(flame_session_set_task_targets(handle_, features.data(), frames, dim, task));
    }

    // How the session edits: method, edit_till (flow models), final paste and seam blending.
    void set_edit_params(const EditParams& params = EditParams()) {
        detail::check(flame_session_set_edit_params(handle_, &params));
    }

    void clear_edit() { detail::check(flame_session_clear_edit(handle_)); }

    // Steers the following steps toward joint positions: targets = frames x joints x 3 floats
    // (x, y, z per joint of the model's skeleton, frame-major) in `convention` and its unit
    // (metres; centimetres for FLAME_CONVENTION_UNREAL), covering the first frames (1..the
    // session's). `mask` = one byte per value (nonzero = constrained), or nullptr with
    // mask_len 0: then a NaN is free and every other value constrained. Replaces earlier
    // targets; on error nothing changes.
    void set_position_targets(const float* targets, std::size_t targets_len, const uint8_t* mask,
                              std::size_t mask_len,
                              FlameConvention convention = FLAME_CONVENTION_NATIVE) {
        detail::check(flame_session_set_position_targets(handle_, targets, targets_len, mask,
                                                         mask_len, convention));
    }
    // NaN = free.
    void set_position_targets(const std::vector<float>& targets,
                              FlameConvention convention = FLAME_CONVENTION_NATIVE) {
        set_position_targets(targets.data(), targets.size(), nullptr, 0, convention);
    }
    // With a mask of one byte per value (its length is checked by the library).
    void set_position_targets(const std::vector<float>& targets, const std::vector<uint8_t>& mask,
                              FlameConvention convention = FLAME_CONVENTION_NATIVE) {
        // A non-null pointer even for an empty mask: an empty mask is not "no mask".
        static const uint8_t none = 0;
        set_position_targets(targets.data(), targets.size(), mask.empty() ? &none : mask.data(),
                             mask.size(), convention);
    }

    // Removes the position targets: unguided from the next step on.
    void clear_position_targets() { detail::check(flame_session_clear_position_targets(handle_)); }

    // Follows joint positions through the model's trajectory ControlNet (MotionLCM control
    // files; ModelInfo::control): positions as for set_position_targets, NaN = free. On error
    // the earlier control stays.
    void set_control(const std::vector<float>& positions,
                     FlameConvention convention = FLAME_CONVENTION_NATIVE) {
        detail::check(flame_session_set_control(handle_, positions.data(), positions.size(),
                                                nullptr, 0, convention));
    }
    // Removes the trajectory control.
    void clear_control() { detail::check(flame_session_clear_control(handle_)); }

    // Consistency latent tuning (MotionLCM's --optimize): before the first step, `iterations`
    // Adam iterations (the release runs 400) move the initial latent so that the 1-step motion
    // made from it follows the control more closely; it becomes the session's initial noise.
    // Needs a prompt, a control and a 1-step MotionLCM session; cancel() is seen before every
    // iteration. The report's before/after values: hint loss (m²) and control error (m).
    FlameTuningReport tune_latent(uint32_t iterations = 400) {
        FlameTuningReport r{};
        r.struct_size = sizeof r;
        detail::check(flame_session_tune_latent(handle_, iterations, &r));
        return r;
    }

    // How strongly position targets steer: scale and schedule.
    void set_target_params(const TargetParams& params = TargetParams()) {
        detail::check(flame_session_set_target_params(handle_, &params));
    }

    // The session's target params: the family's defaults (0.6; MPGD for latent models, constant
    // for the others) until set_target_params changes them.
    TargetParams target_params() const {
        TargetParams p;
        detail::check(flame_session_target_params(handle_, &p));
        return p;
    }

    // The position targets' loss (metres, summed over constrained joints and frames) at the
    // latest step's clean-motion estimate, before that step's pull; throws WRONG_STATE before a
    // guided step (none since the targets were set or the session reset, or scale 0).
    double target_loss() const {
        double loss = 0;
        detail::check(flame_session_target_loss(handle_, &loss));
        return loss;
    }

    // Runs after every step on the stepping thread; an empty function removes it. An exception
    // it throws is caught at the C boundary and rethrown by the step() that ran it (the step
    // itself has completed by then). The callback may read() the preview and query progress();
    // it must not step, reset or destroy the session.
    void on_progress(ProgressFn fn) {
        if (!fn) {
            detail::check(flame_session_set_progress_callback(handle_, nullptr, nullptr));
            hook_.reset();
            return;
        }
        auto hook = std::make_unique<Hook>();
        hook->fn = std::move(fn);
        detail::check(
            flame_session_set_progress_callback(handle_, &Session::trampoline, hook.get()));
        hook_ = std::move(hook);
    }

    // One sampler step; returns the steps still to run.
    uint32_t step() {
        uint32_t left = 0;
        detail::check(flame_session_step(handle_, &left));
        if (hook_ && hook_->error) {
            std::rethrow_exception(std::exchange(hook_->error, nullptr));
        }
        return left;
    }

    // Asks the step running on another thread (or the next step) to stop; it then throws
    // Error(FLAME_STATUS_CANCELLED) and may be retried.
    void cancel() const { detail::check(flame_session_cancel(handle_)); }

    // Back to before the first step, with the same prompt, settings and edits.
    void reset() { detail::check(flame_session_reset(handle_)); }

    Progress progress() const {
        Progress p;
        detail::check(flame_session_progress(handle_, &p.done, &p.total));
        return p;
    }

    // The shape of the sampled space (what set_noise takes); known from the start.
    SampleShape sample_shape() const {
        SampleShape shape;
        detail::check(flame_session_sample_shape(handle_, &shape.rows, &shape.dim));
        return shape;
    }

    // Frames a read of `which` returns now: the session's frames (a finished loop's sample: the
    // cycle), or a latent model's valid length (decided anew after each step). Throws
    // WRONG_STATE before there is anything to read.
    uint32_t read_frames(FlameWhich which = FLAME_WHICH_SAMPLE) const {
        uint32_t frames = 0;
        detail::check(flame_session_read_frames(handle_, which, &frames));
        return frames;
    }

    // read() with the frames its values span.
    Motion read_motion(FlameWhich which = FLAME_WHICH_SAMPLE,
                       FlameLayout layout = FLAME_LAYOUT_FEATURES,
                       FlameConvention convention = FLAME_CONVENTION_NATIVE,
                       uint32_t flags = 0) const {
        Motion m;
        m.values = read(which, layout, convention, flags);
        m.frames = read_frames(which);  // no step in between: the frames of that read
        return m;
    }

    // The sample (or estimate) in a layout, converted to a convention, with read flags
    // (FLAME_READ_SMOOTH, FLAME_READ_RAW_SIGNS): read_frames(which) frames of the layout's
    // values, frame-major. The default is the raw features.
    std::vector<float> read(FlameWhich which = FLAME_WHICH_SAMPLE,
                            FlameLayout layout = FLAME_LAYOUT_FEATURES,
                            FlameConvention convention = FLAME_CONVENTION_NATIVE,
                            uint32_t flags = 0) const {
        std::size_t len = 0;
        detail::check(
            flame_session_read(handle_, which, layout, convention, flags, nullptr, 0, &len));
        std::vector<float> out(len);
        detail::check(flame_session_read(handle_, which, layout, convention, flags, out.data(),
                                         out.size(), &len));
        out.resize(len);
        return out;
    }

    // Into a caller buffer; returns the count written (throws BUFFER_TOO_SMALL when `len` is
    // short; read_len() tells the length needed).
    std::size_t read(float* out, std::size_t len, FlameWhich which = FLAME_WHICH_SAMPLE,
                     FlameLayout layout = FLAME_LAYOUT_FEATURES,
                     FlameConvention convention = FLAME_CONVENTION_NATIVE,
                     uint32_t flags = 0) const {
        std::size_t written = 0;
        detail::check(
            flame_session_read(handle_, which, layout, convention, flags, out, len, &written));
        return written;
    }

    std::size_t read_len(FlameWhich which = FLAME_WHICH_SAMPLE,
                         FlameLayout layout = FLAME_LAYOUT_FEATURES,
                         FlameConvention convention = FLAME_CONVENTION_NATIVE,
                         uint32_t flags = 0) const {
        std::size_t len = 0;
        detail::check(
            flame_session_read(handle_, which, layout, convention, flags, nullptr, 0, &len));
        return len;
    }

    // read() after a cleanup (flame_session_read_cleaned): feet, floor, loop, root motion and
    // frame rate applied to the poses. The frame count follows cleanup.fps (values_per_frame()
    // gives the width); FLAME_LAYOUT_ROOT_BONE needs RootMotion::Separate; the raw features
    // (FLAME_LAYOUT_FEATURES) are never post-processed. Throws INVALID_ARGUMENT naming a bad
    // value (an fps outside 1..240, a negative contact height, ...).
    std::vector<float> read_cleaned(const FlameCleanupParams& cleanup,
                                    FlameWhich which = FLAME_WHICH_SAMPLE,
                                    FlameLayout layout = FLAME_LAYOUT_LOCAL_QUAT_XYZW,
                                    FlameConvention convention = FLAME_CONVENTION_NATIVE,
                                    uint32_t flags = 0) const {
        std::size_t len = read_cleaned_len(cleanup, which, layout, convention, flags);
        std::vector<float> out(len);
        detail::check(flame_session_read_cleaned(handle_, which, layout, convention, flags,
                                                 &cleanup, out.data(), out.size(), &len));
        out.resize(len);
        return out;
    }

    // Into a caller buffer; returns the count written (throws BUFFER_TOO_SMALL when `len` is
    // short; read_cleaned_len() tells the length needed).
    std::size_t read_cleaned(float* out, std::size_t len, const FlameCleanupParams& cleanup,
                             FlameWhich which = FLAME_WHICH_SAMPLE,
                             FlameLayout layout = FLAME_LAYOUT_LOCAL_QUAT_XYZW,
                             FlameConvention convention = FLAME_CONVENTION_NATIVE,
                             uint32_t flags = 0) const {
        std::size_t written = 0;
        detail::check(flame_session_read_cleaned(handle_, which, layout, convention, flags,
                                                 &cleanup, out, len, &written));
        return written;
    }

    std::size_t read_cleaned_len(const FlameCleanupParams& cleanup,
                                 FlameWhich which = FLAME_WHICH_SAMPLE,
                                 FlameLayout layout = FLAME_LAYOUT_LOCAL_QUAT_XYZW,
                                 FlameConvention convention = FLAME_CONVENTION_NATIVE,
                                 uint32_t flags = 0) const {
        std::size_t len = 0;
        detail::check(flame_session_read_cleaned(handle_, which, layout, convention, flags,
                                                 &cleanup, nullptr, 0, &len));
        return len;
    }

    // The sample (or estimate) as a glTF 2.0 file (flame_session_write_gltf): the skeleton as
    // nodes named after ModelInfo::joint_names (node 0 the skeleton's root, node 1 + j joint
    // j), a skinned box figure and one animation in glTF's convention (Y up, right-handed,
    // metres), whose root translation and joint rotations are what read() gives for
    // FLAME_LAYOUT_ROOT_TRANSLATION and FLAME_LAYOUT_LOCAL_QUAT_XYZW in FLAME_CONVENTION_GLTF
    // with the same flags, bit for bit. FLAME_GLTF_CONTAINER_GLB is binary glTF,
    // FLAME_GLTF_CONTAINER_GLTF JSON with the buffer as a base64 data URI. `fps` 0 = the
    // model's; an empty `name` names the animation after the prompt. Throws WRONG_STATE before
    // there is anything to read, INVALID_ARGUMENT for an unknown container or a bad fps. With
    // a cleanup, set GltfParams::cleanup and call write_gltf(which, params): its fps overrides
    // `fps`, and RootMotion::Separate adds a node "root", the pelvis's parent.
    std::vector<uint8_t> write_gltf(FlameWhich which = FLAME_WHICH_SAMPLE,
                                    FlameGltfContainer container = FLAME_GLTF_CONTAINER_GLB,
                                    uint32_t flags = 0, float fps = 0.0f,
                                    const std::string& name = std::string()) const {
        if (name.find('\0') != std::string::npos) {
            throw Error(FLAME_STATUS_INVALID_ARGUMENT, "`name` contains a NUL byte");
        }
        GltfParams params;
        params.container = container;
        params.flags = flags;
        params.fps = fps;
        params.name = name.empty() ? nullptr : name.c_str();
        return write_gltf(which, params);
    }

    // With every field of FlameGltfParams (start from GltfParams()).
    std::vector<uint8_t> write_gltf(FlameWhich which, const GltfParams& params) const {
        std::size_t len = 0;
        detail::check(flame_session_write_gltf(handle_, which, &params, nullptr, 0, &len));
        std::vector<uint8_t> out(len);
        detail::check(
            flame_session_write_gltf(handle_, which, &params, out.data(), out.size(), &len));
        out.resize(len);
        return out;
    }

    // Into a caller buffer; returns the bytes written (throws BUFFER_TOO_SMALL when `len` is
    // short; write_gltf_len() tells the size). Each call builds the file afresh.
    std::size_t write_gltf(uint8_t* out, std::size_t len, FlameWhich which = FLAME_WHICH_SAMPLE,
                           const GltfParams& params = GltfParams()) const {
        std::size_t written = 0;
        detail::check(flame_session_write_gltf(handle_, which, &params, out, len, &written));
        return written;
    }

    // The file's size in bytes (the same for the same motion and parameters).
    std::size_t write_gltf_len(FlameWhich which = FLAME_WHICH_SAMPLE,
                               const GltfParams& params = GltfParams()) const {
        std::size_t len = 0;
        detail::check(flame_session_write_gltf(handle_, which, &params, nullptr, 0, &len));
        return len;
    }

    // The sample (or estimate) as an AMASS-style .npz (flame_session_write_amass), what
    // numpy.load reads: SMPL axis-angles (radians, parent-relative, the root's global) and
    // `trans` (metres) in AMASS's Z-up world, float64, betas 16 zeros, gender "neutral".
    // FLAME_AMASS_SMPLH: `poses` [N, 156], `trans`, `mocap_framerate`, ... (PHC,
    // human2humanoid); FLAME_AMASS_SMPLX: `root_orient`, `pose_body`, `trans`,
    // `mocap_frame_rate`, ... (GMR). `cleanup` NULL = the raw poses; its fps (30 or 50 for
    // trackers) is the file's rate. Throws WRONG_STATE before there is anything to read,
    // INVALID_ARGUMENT for an unknown layout or flags.
    std::vector<uint8_t> write_amass(FlameWhich which = FLAME_WHICH_SAMPLE,
                                     int32_t layout = FLAME_AMASS_SMPLH, uint32_t flags = 0,
                                     const FlameCleanupParams* cleanup = nullptr) const {
        std::size_t len = 0;
        detail::check(
            flame_session_write_amass(handle_, which, layout, flags, cleanup, nullptr, 0, &len));
        std::vector<uint8_t> out(len);
        detail::check(flame_session_write_amass(handle_, which, layout, flags, cleanup,
                                                out.data(), out.size(), &len));
        out.resize(len);
        return out;
    }

    FlameSession* get() const noexcept { return handle_; }
    explicit operator bool() const noexcept { return handle_ != nullptr; }

private:
    struct Hook {
        ProgressFn fn;
        std::exception_ptr error;
    };

    // No exception may unwind into libflame: park it for step() to rethrow.
    static void trampoline(void* user_data, uint32_t done, uint32_t total) noexcept {
        Hook* hook = static_cast<Hook*>(user_data);
        try {
            hook->fn(done, total);
        } catch (...) {
            if (!hook->error) {
                hook->error = std::current_exception();
            }
        }
    }

    static void check_size(std::size_t size, uint32_t frames, uint32_t dim, const char* name) {
        if (size != static_cast<std::size_t>(frames) * dim) {
            throw Error(FLAME_STATUS_INVALID_ARGUMENT,
                        std::string("`") + name + "` has " + std::to_string(size) +
                            " values, expected frames x dim = " +
                            std::to_string(static_cast<std::size_t>(frames) * dim));
        }
    }

    FlameSession* handle_ = nullptr;
    std::unique_ptr<Hook> hook_;
};

// Continuous motion from a timeline of prompts (docs/streams.md); move-only owner of a
// FlameStream (and of its worker threads). Push segments (a prompt for a number of frames),
// pump a bounded number of denoiser steps at a time (e.g. once per engine frame), move the
// playhead and read frames by their position on the timeline. Chunks of `chunk` frames are
// generated ahead of the playhead, each keeping the last `overlap` frames of the motion so far;
// the frames depend only on the timeline (segments and where interrupts fell) and the seed,
// never on how the steps are spread over pumps nor on the thread count.
//
// Used by one thread at a time (a call while another thread is inside one throws WRONG_STATE
// "in use by another thread"), except cancel(), which any thread may call.
class Stream {
public:
    // pump()'s budget for "as many steps as needed" (up to `lookahead` frames ahead).
    static constexpr uint32_t all_steps = UINT32_MAX;

    // An empty stream (as after a move).
    Stream() noexcept = default;

    // Throws INVALID_ARGUMENT for a latent model that cannot continue a motion (MLD), a
    // `chunk` above the model's maximum frames, `overlap` not below `chunk`, or settings a
    // session refuses (sampler, threads, guidance).
    explicit Stream(const Model& model, const StreamParams& params = StreamParams()) {
        detail::check(flame_stream_new(model.get(), &params, &handle_));
    }

    Stream(const Stream&) = delete;
    Stream& operator=(const Stream&) = delete;
    Stream(Stream&& other) noexcept : handle_(std::exchange(other.handle_, nullptr)) {}
    Stream& operator=(Stream&& other) noexcept {
        if (this != &other) {
            flame_stream_free(handle_);
            handle_ = std::exchange(other.handle_, nullptr);
        }
        return *this;
    }
    // Frees the stream, joining its worker threads (no other thread may be inside a call).
    ~Stream() { flame_stream_free(handle_); }

    // Appends a segment: `prompt` for `frames` frames (at least 1), after the segments before.
    void push(const std::string& prompt, uint32_t frames) {
        detail::check(flame_stream_push(handle_, detail::c_text(prompt, "prompt"), frames));
    }

    // Ends the current segment at the next chunk boundary (the end of the chunk being
    // generated, or the frames ready when none is), drops the queued segments and appends
    // `prompt` for `frames` frames in their place: a change of action without waiting.
    void interrupt(const std::string& prompt, uint32_t frames) {
        detail::check(flame_stream_interrupt(handle_, detail::c_text(prompt, "prompt"), frames));
    }

    // push() of a segment with part texts: `stage.text` for `stage.frames` frames, and what
    // single body parts do ("" = the part follows `text`). Only FineMoGen models read part
    // texts; the other families take a stage without them (the same as push(text, frames)) and
    // refuse part texts with INVALID_ARGUMENT.
    void push_stage(const Stage& stage) {
        const FlameStage c = detail::c_stage(stage, "stage");
        detail::check(flame_stream_push_stage(handle_, &c));
    }

    // interrupt() with a segment with part texts (see push_stage).
    void interrupt_stage(const Stage& stage) {
        const FlameStage c = detail::c_stage(stage, "stage");
        detail::check(flame_stream_interrupt_stage(handle_, &c));
    }

    // Moves the playhead (the frame being played) to timeline frame `frame`, at most the
    // frames ready (INVALID_ARGUMENT past them). Frames more than `window` before it are
    // dropped; pump() keeps `lookahead` frames ready after it.
    void set_playhead(uint64_t frame) { detail::check(flame_stream_set_playhead(handle_, frame)); }

    // Runs at most `max_steps` denoiser steps (all_steps: as many as needed) towards
    // `lookahead` frames ready ahead of the playhead, starting chunks as the pushed segments
    // allow; returns early when that many are ready or no segment is left. A chunk's frames
    // become readable when its last step has run. Throws CANCELLED when cancel() stopped it:
    // the stream is then as it was before the step that was cancelled, and pumping again gives
    // the frames of a stream never cancelled.
    StreamStatus pump(uint32_t max_steps) {
        FlameStreamStatus c{};
        c.struct_size = sizeof c;
        detail::check(flame_stream_pump(handle_, max_steps, &c));
        return convert(c);
    }

    // Where the stream stands, without running a step (`steps` is 0).
    StreamStatus status() const {
        FlameStreamStatus c{};
        c.struct_size = sizeof c;
        detail::check(flame_stream_status(handle_, &c));
        return convert(c);
    }

    // Asks the pump running on another thread to stop: it throws Error(FLAME_STATUS_CANCELLED)
    // within about one transformer layer. Raised between pumps, it cancels the next step.
    void cancel() const { detail::check(flame_stream_cancel(handle_)); }

    // Timeline frames first_frame..first_frame + count in a layout (FLAME_LAYOUT_FEATURES: the
    // model's features, the root path continuous across chunks), converted to a convention:
    // count x the layout's values per frame, frame-major. Frames not generated yet throw
    // WRONG_STATE (pump more); frames dropped behind the playhead INVALID_ARGUMENT.
    std::vector<float> read(uint64_t first_frame, uint32_t count,
                            FlameLayout layout = FLAME_LAYOUT_FEATURES,
                            FlameConvention convention = FLAME_CONVENTION_NATIVE) const {
        std::size_t len = read_len(first_frame, count, layout, convention);
        std::vector<float> out(len);
        detail::check(flame_stream_read(handle_, first_frame, count, layout, convention, 0,
                                        out.data(), out.size(), &len));
        out.resize(len);
        return out;
    }

    // Into a caller buffer; returns the count written (throws BUFFER_TOO_SMALL when `len` is
    // short; read_len() tells the length needed).
    std::size_t read(float* out, std::size_t len, uint64_t first_frame, uint32_t count,
                     FlameLayout layout = FLAME_LAYOUT_FEATURES,
                     FlameConvention convention = FLAME_CONVENTION_NATIVE) const {
        std::size_t written = 0;
        detail::check(flame_stream_read(handle_, first_frame, count, layout, convention, 0, out,
                                        len, &written));
        return written;
    }

    std::size_t read_len(uint64_t first_frame, uint32_t count,
                         FlameLayout layout = FLAME_LAYOUT_FEATURES,
                         FlameConvention convention = FLAME_CONVENTION_NATIVE) const {
        std::size_t len = 0;
        detail::check(flame_stream_read(handle_, first_frame, count, layout, convention, 0,
                                        nullptr, 0, &len));
        return len;
    }

    // read() after a cleanup (flame_stream_read_cleaned): a frame is readable once its cleanup
    // is final (WRONG_STATE before: pump more, or end_timeline()), and never changes after; the
    // first cleaned read sets the stream's cleanup for good; with a frame rate, frames count at
    // that rate.
    std::vector<float> read_cleaned(const FlameCleanupParams& cleanup, uint64_t first_frame,
                                    uint32_t count, FlameLayout layout,
                                    FlameConvention convention = FLAME_CONVENTION_NATIVE) const {
        std::size_t len = 0;
        detail::check(flame_stream_read_cleaned(handle_, first_frame, count, layout, convention,
                                                &cleanup, nullptr, 0, &len));
        std::vector<float> out(len);
        detail::check(flame_stream_read_cleaned(handle_, first_frame, count, layout, convention,
                                                &cleanup, out.data(), out.size(), &len));
        out.resize(len);
        return out;
    }

    // flame_stream_close: the timeline is complete (push and interrupt throw WRONG_STATE
    // afterwards); once the pushed segments are generated, every frame's cleanup settles.
    void end_timeline() const { detail::check(flame_stream_close(handle_)); }

    // flame_stream_close_looped: end_timeline(), and the timeline loops. After the pushed
    // segments the stream generates a bridge of `bridge_frames` frames (the last segment's
    // prompt) whose end runs into the timeline's first frames, moved by the loop's root motion,
    // as `flame generate --loop` closes a clip: playing frame 0 after the last continues the
    // motion. Frames already generated never change; the timeline grows by bridge_frames (two
    // chunks' steps more to pump), and cleaned reads settle to its end. Throws
    // INVALID_ARGUMENT for a latent model (MLD, MoLA) and for a bridge shorter than 1 s or
    // longer than the model's frames allow (overlap + bridge + 0.5 s), WRONG_STATE when the
    // stream is already closed, has no segment or dropped frame 0.
    void end_timeline_looped(uint32_t bridge_frames) const {
        detail::check(flame_stream_close_looped(handle_, bridge_frames));
    }

    FlameStream* get() const noexcept { return handle_; }
    explicit operator bool() const noexcept { return handle_ != nullptr; }

private:
    static StreamStatus convert(const FlameStreamStatus& c) noexcept {
        StreamStatus st;
        st.steps = c.steps;
        st.ready = c.ready;
        st.first_frame = c.first_frame;
        st.playhead = c.playhead;
        st.starving = c.starving != 0;
        return st;
    }

    FlameStream* handle_ = nullptr;
};

// ---- retargeting -----------------------------------------------------------------------------

// One bone of Rig::from_bones: its rest transform relative to its parent (T·R·S) in the rig's
// convention; `parent` -1 for a root; rotation x, y, z, w.
struct RigBone {
    std::string name;
    int32_t parent = -1;
    float translation[3] = {0, 0, 0};
    float rotation[4] = {0, 0, 0, 1};
    float scale[3] = {1, 1, 1};
};

// The user's skeleton; immutable, shareable by threads; move-only owner of a FlameRig.
class Rig {
public:
    Rig() noexcept = default;
    explicit Rig(FlameRig* owned) noexcept : handle_(owned) {}

    // A rig from a file's bytes: `kind` FLAME_RIG_FORMAT_GUESS/GLTF/BVH, `skin` a glTF skin's
    // name ("" = the only one, or a VRM file's humanoid one).
    static Rig load(const void* bytes, std::size_t len, uint32_t kind = FLAME_RIG_FORMAT_GUESS,
                    const std::string& skin = "") {
        FlameRig* h = nullptr;
        const char* s = skin.empty() ? nullptr : detail::c_text(skin, "skin");
        detail::check(flame_rig_load(static_cast<const uint8_t*>(bytes), len, kind, s, &h));
        return Rig(h);
    }
    static Rig load(const std::vector<uint8_t>& bytes, uint32_t kind = FLAME_RIG_FORMAT_GUESS,
                    const std::string& skin = "") {
        return load(bytes.data(), bytes.size(), kind, skin);
    }

    // A rig from bones an engine holds, in `convention` (FLAME_CONVENTION_UNITY, _UNREAL with
    // centimetres, ...; not native): carried into right-handed glTF axes so a left-handed rig
    // is not driven mirrored; poses come back in `convention`, bones in the given order.
    static Rig from_bones(const std::vector<RigBone>& bones, FlameConvention convention) {
        std::vector<FlameRigBone> c(bones.size());
        for (std::size_t i = 0; i < bones.size(); ++i) {
            FlameRigBone& b = c[i];
            b.struct_size = sizeof(FlameRigBone);
            b.parent = bones[i].parent;
            b.name = detail::c_text(bones[i].name, "name");
            for (int k = 0; k < 3; ++k) {
                b.translation[k] = bones[i].translation[k];
                b.scale[k] = bones[i].scale[k];
            }
            for (int k = 0; k < 4; ++k) {
                b.rotation[k] = bones[i].rotation[k];
            }
        }
        FlameRig* h = nullptr;
        detail::check(flame_rig_from_bones(c.data(), c.size(), convention, &h));
        return Rig(h);
    }

    Rig(const Rig&) = delete;
    Rig& operator=(const Rig&) = delete;
    Rig(Rig&& o) noexcept : handle_(std::exchange(o.handle_, nullptr)) {}
    Rig& operator=(Rig&& o) noexcept {
        if (this != &o) {
            flame_rig_free(handle_);
            handle_ = std::exchange(o.handle_, nullptr);
        }
        return *this;
    }
    ~Rig() { flame_rig_free(handle_); }

    std::size_t bone_count() const {
        std::size_t n = 0;
        detail::check(flame_rig_bone_count(handle_, &n));
        return n;
    }
    std::string bone_name(std::size_t bone) const {
        const char* name = nullptr;
        detail::check(flame_rig_bone_name(handle_, bone, &name));
        return name;
    }
    int32_t bone_parent(std::size_t bone) const {
        int32_t p = -1;
        detail::check(flame_rig_bone_parent(handle_, bone, &p));
        return p;
    }

    const FlameRig* get() const noexcept { return handle_; }
    explicit operator bool() const noexcept { return handle_ != nullptr; }

private:
    FlameRig* handle_ = nullptr;
};

// Which bone of a rig is which humanoid bone; only for the rig it was made for.
class BoneMap {
public:
    BoneMap() noexcept = default;
    explicit BoneMap(FlameBoneMap* owned) noexcept : handle_(owned) {}

    static BoneMap automatic(const Rig& rig) {
        FlameBoneMap* h = nullptr;
        detail::check(flame_bone_map_auto(rig.get(), &h));
        return BoneMap(h);
    }
    // {"hips": "pelvis", "leftHand": "hand_l", ...} over `base` (NULL: over nothing).
    static BoneMap from_json(const Rig& rig, const std::string& json,
                             const BoneMap* base = nullptr) {
        FlameBoneMap* h = nullptr;
        detail::check(flame_bone_map_from_json(rig.get(), detail::c_text(json, "json"),
                                               base ? base->get() : nullptr, &h));
        return BoneMap(h);
    }
    std::string to_json(const Rig& rig) const {
        std::size_t n = 0;
        detail::check(flame_bone_map_to_json(handle_, rig.get(), nullptr, 0, &n));
        std::string out(n, '\0');
        detail::check(flame_bone_map_to_json(handle_, rig.get(), &out[0], n, &n));
        out.resize(n ? n - 1 : 0);  // without the terminating NUL
        return out;
    }

    BoneMap(const BoneMap&) = delete;
    BoneMap& operator=(const BoneMap&) = delete;
    BoneMap(BoneMap&& o) noexcept : handle_(std::exchange(o.handle_, nullptr)) {}
    BoneMap& operator=(BoneMap&& o) noexcept {
        if (this != &o) {
            flame_bone_map_free(handle_);
            handle_ = std::exchange(o.handle_, nullptr);
        }
        return *this;
    }
    ~BoneMap() { flame_bone_map_free(handle_); }

    const FlameBoneMap* get() const noexcept { return handle_; }

private:
    FlameBoneMap* handle_ = nullptr;
};

// Options of Retarget (flame_retarget_params_default's: the rig's own convention, feet IK on,
// hands off, the automatic map).
struct RetargetParams : FlameRetargetParams {
    RetargetParams() : FlameRetargetParams() { detail::check(flame_retarget_params_default(this)); }
};

// Retargeted poses: `frames` × `bones` local rotations (x, y, z, w) and translations.
struct RigPoses {
    std::size_t frames = 0;
    std::size_t bones = 0;
    std::vector<float> rotations;     // [frames][bones][4]
    std::vector<float> translations;  // [frames][bones][3]
};

// A model's poses onto a rig; shareable by threads (calls run one after another). The rig and
// map are copied: either may go once this is made.
class Retarget {
public:
    Retarget() noexcept = default;
    Retarget(const Model& model, const Rig& rig, const RetargetParams& params = RetargetParams()) {
        detail::check(flame_retarget_new(model.get(), rig.get(), &params, &handle_));
    }

    Retarget(const Retarget&) = delete;
    Retarget& operator=(const Retarget&) = delete;
    Retarget(Retarget&& o) noexcept : handle_(std::exchange(o.handle_, nullptr)) {}
    Retarget& operator=(Retarget&& o) noexcept {
        if (this != &o) {
            flame_retarget_free(handle_);
            handle_ = std::exchange(o.handle_, nullptr);
        }
        return *this;
    }
    ~Retarget() { flame_retarget_free(handle_); }

    std::size_t bone_count() const {
        std::size_t n = 0;
        detail::check(flame_retarget_bone_count(handle_, &n));
        return n;
    }

    // Frames first..first+count of the session's motion as Session::read_cleaned gives it
    // (cleanup NULL = raw), on the rig; count SIZE_MAX = to the end.
    RigPoses read(const Session& session, std::size_t first = 0, std::size_t count = SIZE_MAX,
                  const FlameCleanupParams* cleanup = nullptr,
                  FlameWhich which = FLAME_WHICH_SAMPLE, uint32_t flags = 0) const {
        if (count == SIZE_MAX) {
            std::size_t frames = 0;
            detail::check(flame_retarget_read(handle_, session.get(), which, flags, cleanup, 0, 0,
                                              nullptr, 0, nullptr, 0, &frames));
            count = frames > first ? frames - first : 0;
        }
        RigPoses p = empty(count);
        detail::check(flame_retarget_read(handle_, session.get(), which, flags, cleanup, first,
                                          count, p.rotations.data(), p.rotations.size(),
                                          p.translations.data(), p.translations.size(),
                                          nullptr));
        return p;
    }

    // Timeline frames of a stream as Stream::read_cleaned gives them, on the rig.
    RigPoses read_stream(const Stream& stream, uint64_t first, uint32_t count,
                         const FlameCleanupParams* cleanup = nullptr) const {
        RigPoses p = empty(count);
        detail::check(flame_retarget_read_stream(handle_, stream.get(), first, count, cleanup,
                                                 p.rotations.data(), p.rotations.size(),
                                                 p.translations.data(), p.translations.size()));
        return p;
    }

    // One frame from any source: world rotations [joints][4] and positions [joints][3] of the
    // model's skeleton, glTF axes, metres.
    RigPoses pose(const std::vector<float>& world, const std::vector<float>& positions) const {
        RigPoses p = empty(1);
        detail::check(flame_retarget_pose(handle_, world.data(), world.size(), positions.data(),
                                          positions.size(), p.rotations.data(),
                                          p.rotations.size(), p.translations.data(),
                                          p.translations.size()));
        return p;
    }

    const FlameRetarget* get() const noexcept { return handle_; }

private:
    RigPoses empty(std::size_t frames) const {
        RigPoses p;
        p.frames = frames;
        p.bones = bone_count();
        p.rotations.resize(frames * p.bones * 4);
        p.translations.resize(frames * p.bones * 3);
        return p;
    }

    FlameRetarget* handle_ = nullptr;
};

// ---- robots ----------------------------------------------------------------------------------

// A robot from its URDF (docs/robots.md): kinematic tree, joint limits, collision primitives.
// Immutable, shareable by threads; move-only owner of a FlameRobot. Retargets made from it
// hold a copy: it may go once they are made.
class Robot {
public:
    Robot() noexcept = default;
    explicit Robot(FlameRobot* owned) noexcept : handle_(owned) {}

    // A robot from a URDF's text (`len` bytes of UTF-8, read only during the call). Throws
    // INVALID_ARGUMENT for malformed XML, a cycle, a missing link, ... (the message names it).
    static Robot load(const void* urdf, std::size_t len) {
        FlameRobot* h = nullptr;
        detail::check(flame_robot_load(static_cast<const uint8_t*>(urdf), len, &h));
        return Robot(h);
    }
    static Robot load(const std::vector<uint8_t>& urdf) { return load(urdf.data(), urdf.size()); }

    Robot(const Robot&) = delete;
    Robot& operator=(const Robot&) = delete;
    Robot(Robot&& o) noexcept : handle_(std::exchange(o.handle_, nullptr)) {}
    Robot& operator=(Robot&& o) noexcept {
        if (this != &o) {
            flame_robot_free(handle_);
            handle_ = std::exchange(o.handle_, nullptr);
        }
        return *this;
    }
    ~Robot() { flame_robot_free(handle_); }

    // `<robot name>` (the shipped configurations are robots/<name>.json).
    std::string name() const {
        const char* n = nullptr;
        detail::check(flame_robot_name(handle_, &n));
        return n;
    }
    // Degrees of freedom: the length of every joint vector (RobotFrames::q's per frame).
    std::size_t dof_count() const {
        std::size_t n = 0;
        detail::check(flame_robot_dof_count(handle_, &n));
        return n;
    }
    // The joint of degree of freedom `index` (INVALID_ARGUMENT past dof_count()).
    std::string dof_name(std::size_t index) const {
        const char* n = nullptr;
        detail::check(flame_robot_dof_name(handle_, index, &n));
        return n;
    }
    // Every degree of freedom's joint, in the order of the joint vectors.
    std::vector<std::string> dof_names() const {
        std::vector<std::string> names;
        const std::size_t n = dof_count();
        names.reserve(n);
        for (std::size_t i = 0; i < n; ++i) {
            names.push_back(dof_name(i));
        }
        return names;
    }

    const FlameRobot* get() const noexcept { return handle_; }
    explicit operator bool() const noexcept { return handle_ != nullptr; }

private:
    FlameRobot* handle_ = nullptr;
};

// Robot frames of RobotRetarget::read / read_stream, frame-major, float64: the base (root link)
// position (metres, Z up), its quaternion x, y, z, w, the joint positions in the robot's
// degree-of-freedom order and the weighted task residual (large when the robot cannot reach).
struct RobotFrames {
    std::size_t frames = 0;
    std::size_t dofs = 0;
    std::vector<double> root_pos;       // [frames][3]
    std::vector<double> root_rot_xyzw;  // [frames][4]
    std::vector<double> q;              // [frames][dofs]
    std::vector<double> residual;       // [frames]
};

class RobotRetarget;

// One run's state of frame-by-frame reads (RobotRetarget::read, read_stream): where the next
// frame starts from (warm start, joint velocity limits, planted feet). Used by one thread at a
// time, only with the retarget that made it; move-only owner of a FlameRobotState.
class RobotState {
public:
    RobotState() noexcept = default;
    explicit RobotState(FlameRobotState* owned) noexcept : handle_(owned) {}
    // A fresh state for `retarget` (the robot at its configured initial configuration).
    explicit RobotState(const RobotRetarget& retarget);

    RobotState(const RobotState&) = delete;
    RobotState& operator=(const RobotState&) = delete;
    RobotState(RobotState&& o) noexcept : handle_(std::exchange(o.handle_, nullptr)) {}
    RobotState& operator=(RobotState&& o) noexcept {
        if (this != &o) {
            flame_robot_state_free(handle_);
            handle_ = std::exchange(o.handle_, nullptr);
        }
        return *this;
    }
    ~RobotState() { flame_robot_state_free(handle_); }

    // Back to the start of a run: call it before reading other frames than the ones after the
    // last read.
    void reset() const { detail::check(flame_robot_state_reset(handle_)); }

    const FlameRobotState* get() const noexcept { return handle_; }
    explicit operator bool() const noexcept { return handle_ != nullptr; }

private:
    FlameRobotState* handle_ = nullptr;
};

// A retarget of the model's motion onto a robot with its configuration (GMR's IK tables plus
// libflame's feet and solver keys; libflame ships robots/<robot name>.json). Immutable,
// shareable by threads (per-run state is a RobotState); the robot is copied. Move-only owner
// of a FlameRobotRetarget.
//
//   flame::Robot robot = flame::Robot::load(urdf_bytes);
//   flame::RobotRetarget r(robot, config_json);
//   std::vector<uint8_t> csv = r.write(session);  // BeyondMimic's CSV of the whole clip
//   flame::RobotState state = r.state();
//   flame::RobotFrames f = r.read(session, state, 0, 10);  // frames 0..10, read in order
class RobotRetarget {
public:
    RobotRetarget() noexcept = default;
    explicit RobotRetarget(FlameRobotRetarget* owned) noexcept : handle_(owned) {}
    // `config_json`: `len` bytes of UTF-8 JSON. Throws INVALID_ARGUMENT for malformed JSON, an
    // unknown key, a body or joint that does not exist (named), negative weights.
    RobotRetarget(const Robot& robot, const void* config_json, std::size_t len) {
        detail::check(flame_robot_retarget_new(
            robot.get(), static_cast<const uint8_t*>(config_json), len, &handle_));
    }
    RobotRetarget(const Robot& robot, const std::string& config_json)
        : RobotRetarget(robot, config_json.data(), config_json.size()) {}

    RobotRetarget(const RobotRetarget&) = delete;
    RobotRetarget& operator=(const RobotRetarget&) = delete;
    RobotRetarget(RobotRetarget&& o) noexcept : handle_(std::exchange(o.handle_, nullptr)) {}
    RobotRetarget& operator=(RobotRetarget&& o) noexcept {
        if (this != &o) {
            flame_robot_retarget_free(handle_);
            handle_ = std::exchange(o.handle_, nullptr);
        }
        return *this;
    }
    // States made for it can no longer be used.
    ~RobotRetarget() { flame_robot_retarget_free(handle_); }

    // The robot's degrees of freedom (RobotFrames::dofs).
    std::size_t dof_count() const {
        std::size_t n = 0;
        detail::check(flame_robot_retarget_dof_count(handle_, &n));
        return n;
    }

    // A fresh RobotState for read() and read_stream().
    RobotState state() const { return RobotState(*this); }

    // The session's whole sample (or estimate) retargeted and written as `file`
    // (flame_robot_retarget_write): FLAME_ROBOT_BEYONDMIMIC_CSV_XYZW, _GMR_NPZ_XYZW,
    // _QPOS_CSV_WXYZ or _QPOS_NPY_WXYZ; `options` FLAME_ROBOT_CSV_HEADER starts a CSV with a
    // "# " line of column names. `cleanup` NULL = the raw poses; its fps (30 or 50 for trackers)
    // is the file's rate. Throws WRONG_STATE before there is anything to read,
    // INVALID_ARGUMENT for an unknown file or options.
    std::vector<uint8_t> write(const Session& session,
                               uint32_t file = FLAME_ROBOT_BEYONDMIMIC_CSV_XYZW,
                               uint32_t options = 0, const FlameCleanupParams* cleanup = nullptr,
                               FlameWhich which = FLAME_WHICH_SAMPLE, uint32_t flags = 0) const {
        std::size_t len = 0;
        detail::check(flame_robot_retarget_write(handle_, session.get(), which, flags, cleanup,
                                                 file, options, nullptr, 0, &len));
        std::vector<uint8_t> out(len);
        detail::check(flame_robot_retarget_write(handle_, session.get(), which, flags, cleanup,
                                                 file, options, out.data(), out.size(), &len));
        out.resize(len);
        return out;
    }

    // Frames first..first+count of the session's motion as Session::read_cleaned gives it
    // (cleanup NULL = raw; a cleanup with its ground on puts the motion on the robot's floor),
    // each solved from where `state` left the previous one: read in order, reset() the state
    // before jumping. count SIZE_MAX = to the end. Throws INVALID_ARGUMENT for frames past the
    // read or a state of another retarget, WRONG_STATE before there is a sample; on an error
    // the state is reset.
    RobotFrames read(const Session& session, const RobotState& state, std::size_t first = 0,
                     std::size_t count = SIZE_MAX, const FlameCleanupParams* cleanup = nullptr,
                     FlameWhich which = FLAME_WHICH_SAMPLE, uint32_t flags = 0) const {
        if (count == SIZE_MAX) {
            std::size_t frames = 0;
            detail::check(flame_robot_retarget_read(handle_, state.get(), session.get(), which,
                                                    flags, cleanup, 0, 0, nullptr, 0, nullptr, 0,
                                                    nullptr, 0, nullptr, 0, &frames));
            count = frames > first ? frames - first : 0;
        }
        RobotFrames f = empty(count);
        detail::check(flame_robot_retarget_read(
            handle_, state.get(), session.get(), which, flags, cleanup, first, count,
            f.root_pos.data(), f.root_pos.size(), f.root_rot_xyzw.data(), f.root_rot_xyzw.size(),
            f.q.data(), f.q.size(), f.residual.data(), f.residual.size(), nullptr));
        return f;
    }

    // Timeline frames first_frame..first_frame+count of a stream as Stream::read_cleaned gives
    // them, with the stream's foot contacts, from `state`: a few frames per call, in order, to
    // drive a robot at run time. Frames not generated or settled yet throw WRONG_STATE (pump
    // more), dropped ones INVALID_ARGUMENT.
    RobotFrames read_stream(const Stream& stream, const RobotState& state, uint64_t first_frame,
                            uint32_t count, const FlameCleanupParams* cleanup = nullptr) const {
        RobotFrames f = empty(count);
        detail::check(flame_robot_retarget_read_stream(
            handle_, state.get(), stream.get(), first_frame, count, cleanup, f.root_pos.data(),
            f.root_pos.size(), f.root_rot_xyzw.data(), f.root_rot_xyzw.size(), f.q.data(),
            f.q.size(), f.residual.data(), f.residual.size()));
        return f;
    }

    const FlameRobotRetarget* get() const noexcept { return handle_; }
    explicit operator bool() const noexcept { return handle_ != nullptr; }

private:
    RobotFrames empty(std::size_t frames) const {
        RobotFrames f;
        f.frames = frames;
        f.dofs = dof_count();
        f.root_pos.resize(frames * 3);
        f.root_rot_xyzw.resize(frames * 4);
        f.q.resize(frames * f.dofs);
        f.residual.resize(frames);
        return f;
    }

    FlameRobotRetarget* handle_ = nullptr;
};

inline RobotState::RobotState(const RobotRetarget& retarget) {
    detail::check(flame_robot_state_new(retarget.get(), &handle_));
}

inline Session Model::session(const SessionParams& params) const {
    return Session(*this, params);
}

inline Stream Model::stream(const StreamParams& params) const {
    return Stream(*this, params);
}

}  // namespace flame

#endif  // FLAME_HPP
