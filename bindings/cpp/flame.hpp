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
//
// Ownership: Model and Session own their C handle and are move-only. A Session keeps its model
// alive on the C side, so it stays usable after the Model object that made it is destroyed.
// A moved-from object is empty: its calls throw flame::Error(FLAME_STATUS_INVALID_ARGUMENT).
//
// Errors: every failing call throws flame::Error, carrying the FlameStatus and the library's
// message (flame_last_error() at the time of the failure).
//
// Threads: a Model may be shared by any number of threads and sessions; a Session is used by
// one thread at a time, except Session::cancel(), which any thread may call while another is
// inside step().

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
// `const char*`: it must stay valid until the Session is constructed.
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
// read flags, the model's frame rate, the animation named after the prompt). `name` is a plain
// `const char*` (NULL = the prompt's): it must stay valid for the call.
struct GltfParams : FlameGltfParams {
    GltfParams() : FlameGltfParams() { detail::check(flame_gltf_params_default(this)); }
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
};

// The shape of a session's sampled space, what Session::set_noise takes: rows x dim values
// (frames x feature_dim, or a latent model's latent).
struct SampleShape {
    uint32_t rows = 0;
    uint32_t dim = 0;
    std::size_t size() const noexcept { return static_cast<std::size_t>(rows) * dim; }
};

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

// Steps done and the total of a generation.
struct Progress {
    uint32_t done = 0;
    uint32_t total = 0;
};

class Session;

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
        return info;
    }

    // A new generation on this model (see Session).
    Session session(const SessionParams& params = SessionParams()) const;

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

    // Prompts per time stage, in order; their frames must add up to the session's. A FineMoGen
    // model composes them: its sample is then laid out stages x the longest stage rows
    // (sample_shape(), and what set_noise takes), while read() still returns the session's
    // frames, the stages one after the other. Any other model takes exactly one stage without
    // part texts, as set_prompt(stage.text), and refuses more (INVALID_ARGUMENT). Stage frame
    // counts can change only before the first step (WRONG_STATE after; reset() first).
    void set_prompt_stages(const std::vector<Stage>& stages) {
        std::vector<FlameStage> c(stages.size());
        for (std::size_t i = 0; i < stages.size(); ++i) {
            const Stage& s = stages[i];
            FlameStage& st = c[i];
            st.struct_size = sizeof st;
            st.frames = s.frames;
            st.text = text_arg(s.text, i, "text", false);
            st.head = text_arg(s.head, i, "head", true);
            st.stem = text_arg(s.stem, i, "stem", true);
            st.left_arm = text_arg(s.left_arm, i, "left_arm", true);
            st.right_arm = text_arg(s.right_arm, i, "right_arm", true);
            st.left_leg = text_arg(s.left_leg, i, "left_leg", true);
            st.right_leg = text_arg(s.right_leg, i, "right_leg", true);
            st.pelvis = text_arg(s.pelvis, i, "pelvis", true);
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
    // features): its joint positions where the task keeps them (MoLA's MPGD tasks).
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

    // Frames a read of `which` returns now: the session's frames, or a latent model's valid
    // length (decided anew after each step). Throws WRONG_STATE before there is anything to
    // read.
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

    // The sample (or estimate) as a glTF 2.0 file (flame_session_write_gltf): the skeleton as
    // nodes named after ModelInfo::joint_names (node 0 the skeleton's root, node 1 + j joint
    // j), a skinned box figure and one animation in glTF's convention (Y up, right-handed,
    // metres), whose root translation and joint rotations are what read() gives for
    // FLAME_LAYOUT_ROOT_TRANSLATION and FLAME_LAYOUT_LOCAL_QUAT_XYZW in FLAME_CONVENTION_GLTF
    // with the same flags, bit for bit. FLAME_GLTF_CONTAINER_GLB is binary glTF,
    // FLAME_GLTF_CONTAINER_GLTF JSON with the buffer as a base64 data URI. `fps` 0 = the
    // model's; an empty `name` names the animation after the prompt. Throws WRONG_STATE before
    // there is anything to read, INVALID_ARGUMENT for an unknown container or a bad fps.
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

    // A stage's text for the C call (valid while `s` is): NULL for an empty part text.
    static const char* text_arg(const std::string& s, std::size_t stage, const char* name,
                                bool part) {
        if (s.find('\0') != std::string::npos) {
            throw Error(FLAME_STATUS_INVALID_ARGUMENT, "`stages[" + std::to_string(stage) + "]." +
                                                           name + "` contains a NUL byte");
        }
        return part && s.empty() ? nullptr : s.c_str();
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

inline Session Model::session(const SessionParams& params) const {
    return Session(*this, params);
}

}  // namespace flame

#endif  // FLAME_HPP
