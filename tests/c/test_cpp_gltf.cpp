// Session::write_gltf of the C++17 wrapper (bindings/cpp/flame.hpp): the GLB header, the joint
// names, the animation's bytes equal to read()'s in FLAME_CONVENTION_GLTF (found verbatim in the
// binary chunk), both containers, the buffer overload and its BUFFER_TOO_SMALL, and the errors
// as flame::Error. On a smpl24_6d fixture (FLAME) and a humanml263 one (MDM).
//
// usage: test_cpp_gltf FIXTURES_DIR   (tests/fixtures)

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <string>
#include <utility>
#include <vector>

#include "flame.hpp"

#include "check.h"
#include "util.h"

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

static const uint32_t kFrames = 16;

static uint32_t u32(const std::vector<uint8_t> &b, std::size_t at) {
    return (uint32_t)b[at] | (uint32_t)b[at + 1] << 8 | (uint32_t)b[at + 2] << 16 |
           (uint32_t)b[at + 3] << 24;
}

// A GLB's JSON text and binary chunk, after checking the 12-byte header ("glTF", version 2,
// the file's length) and the two chunk headers.
static bool split_glb(const std::vector<uint8_t> &glb, std::string *json, std::vector<uint8_t> *bin) {
    if (glb.size() < 28) {
        return false;
    }
    CHECK(std::memcmp(glb.data(), "glTF", 4) == 0);
    CHECK(u32(glb, 4) == 2);
    CHECK(u32(glb, 8) == glb.size());
    const std::size_t jlen = u32(glb, 12);
    CHECK(std::memcmp(glb.data() + 16, "JSON", 4) == 0 && jlen % 4 == 0);
    if (20 + jlen + 8 > glb.size()) {
        return false;
    }
    json->assign(reinterpret_cast<const char *>(glb.data()) + 20, jlen);
    const std::size_t b = 20 + jlen, blen = u32(glb, b);
    CHECK(std::memcmp(glb.data() + b + 4, "BIN\0", 4) == 0 && b + 8 + blen == glb.size());
    bin->assign(glb.begin() + (long)(b + 8), glb.end());
    return true;
}

// Whether `values`' bytes occur in `bin` (an accessor holds its floats contiguously).
static bool holds(const std::vector<uint8_t> &bin, const std::vector<float> &values) {
    const uint8_t *v = reinterpret_cast<const uint8_t *>(values.data());
    return !values.empty() &&
           std::search(bin.begin(), bin.end(), v, v + values.size() * 4) != bin.end();
}

static std::size_t count(const std::string &text, const std::string &needle) {
    std::size_t n = 0;
    for (std::size_t at = text.find(needle); at != std::string::npos;
         at = text.find(needle, at + 1)) {
        n++;
    }
    return n;
}

// Joint j's track of a [frames, joints, 4] read: frames x 4 values.
static std::vector<float> track(const std::vector<float> &quats, uint32_t joints, uint32_t j) {
    std::vector<float> t;
    for (std::size_t f = 0; f < quats.size() / (joints * 4); ++f) {
        t.insert(t.end(), quats.begin() + (long)((f * joints + j) * 4),
                 quats.begin() + (long)((f * joints + j) * 4 + 4));
    }
    return t;
}

// The file of `s` in GLB with `flags` against its reads in the glTF convention.
static void check_matches_read(const flame::Session &s, const flame::ModelInfo &info,
                               uint32_t flags) {
    std::vector<uint8_t> glb = s.write_gltf(FLAME_WHICH_SAMPLE, FLAME_GLTF_CONTAINER_GLB, flags);
    std::string json;
    std::vector<uint8_t> bin;
    if (!split_glb(glb, &json, &bin)) {
        CHECK(!"a GLB with two chunks");
        return;
    }
    bool named = true;
    for (const std::string &name : info.joint_names) {
        named = named && json.find("\"name\":\"" + name + "\"") != std::string::npos;
    }
    CHECK(named);
    std::vector<float> root =
        s.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_ROOT_TRANSLATION, FLAME_CONVENTION_GLTF, flags);
    std::vector<float> quats =
        s.read(FLAME_WHICH_SAMPLE, FLAME_LAYOUT_LOCAL_QUAT_XYZW, FLAME_CONVENTION_GLTF, flags);
    CHECK(root.size() == kFrames * 3 && quats.size() == kFrames * info.joint_count * 4);
    CHECK(holds(bin, root));
    bool tracks = true;
    for (uint32_t j = 0; j < info.joint_count; ++j) {
        tracks = tracks && holds(bin, track(quats, info.joint_count, j));
    }
    CHECK(tracks);
    // The times, t / fps.
    std::vector<float> times;
    for (uint32_t f = 0; f < kFrames; ++f) {
        times.push_back((float)(f / (double)info.fps));
    }
    CHECK(holds(bin, times));
}

static flame::Session stepped(const flame::Model &model) {
    flame::SessionParams p;
    p.frames = kFrames;
    p.steps = 4;
    p.sampler = FLAME_SAMPLER_DDIM;
    p.seed = 5;
    p.threads = 1;
    flame::Session s = model.session(p);
    s.set_prompt(REF_PROMPT);
    // Two of four steps: the tiny models' final motions saturate (test_api's pose checks).
    s.step();
    s.step();
    return s;
}

static void test_smpl(const std::string &dir) {
    flame::Model model = flame::Model::load(dir + "/flame_tiny.safetensors");
    flame::ModelInfo info = model.info();
    CHECK(info.motion_format == "smpl24_6d" && info.joint_count == 24);

    flame::GltfParams defaults;
    CHECK(defaults.struct_size == sizeof(FlameGltfParams));
    CHECK(defaults.container == FLAME_GLTF_CONTAINER_GLB && defaults.flags == 0 &&
          defaults.fps == 0.0f && defaults.name == nullptr);

    {
        flame::SessionParams p;
        p.frames = kFrames;
        p.steps = 4;
        p.sampler = FLAME_SAMPLER_DDIM;
        flame::Session fresh = model.session(p);
        CHECK_THROWS(fresh.write_gltf(), FLAME_STATUS_WRONG_STATE, "no sample yet");
        fresh.set_prompt(REF_PROMPT);
        CHECK_THROWS(fresh.write_gltf(), FLAME_STATUS_WRONG_STATE, "no sample yet");
        CHECK_THROWS(fresh.write_gltf(FLAME_WHICH_ESTIMATE), FLAME_STATUS_WRONG_STATE,
                     "no clean-motion estimate");
        CHECK_THROWS(fresh.write_gltf_len(), FLAME_STATUS_WRONG_STATE, "no sample yet");
    }

    flame::Session s = stepped(model);
    std::vector<uint8_t> glb = s.write_gltf();
    std::string json;
    std::vector<uint8_t> bin;
    CHECK(split_glb(glb, &json, &bin));
    CHECK(json.find("\"prompt\":\"" REF_PROMPT "\"") != std::string::npos);
    CHECK(json.find("\"seed\":5") != std::string::npos);
    CHECK(json.find("\"libflame\":\"" + flame::version() + "\"") != std::string::npos);
    CHECK(json.find("\"name\":\"smpl24\"") != std::string::npos);
    CHECK(json.find("\"name\":\"a_person_walks_forward_and_waves\"") != std::string::npos);
    CHECK(count(json, "\"path\":\"rotation\"") == 24 && count(json, "\"path\":\"translation\"") == 1);
    check_matches_read(s, info, 0);
    check_matches_read(s, info, FLAME_READ_SMOOTH);
    check_matches_read(s, info, FLAME_READ_RAW_SIGNS);
    CHECK(s.write_gltf() == glb);  // the same motion and parameters, the same bytes
    CHECK(s.write_gltf(FLAME_WHICH_SAMPLE, flame::GltfParams()) == glb);

    // The raw C call with NULL params gives the same file.
    std::size_t n = 0;
    CHECK_OK(flame_session_write_gltf(s.get(), FLAME_WHICH_SAMPLE, nullptr, nullptr, 0, &n));
    CHECK(n == glb.size() && s.write_gltf_len() == glb.size());

    // The buffer overload: short buffers throw BUFFER_TOO_SMALL, a larger one gets the file.
    std::vector<uint8_t> buf(glb.size() + 8, 0);
    CHECK_THROWS(s.write_gltf(buf.data(), 16), FLAME_STATUS_BUFFER_TOO_SMALL, "buffer too small");
    CHECK_THROWS(s.write_gltf(buf.data(), glb.size() - 1), FLAME_STATUS_BUFFER_TOO_SMALL,
                 "buffer too small");
    CHECK(std::all_of(buf.begin(), buf.end(), [](uint8_t b) { return b == 0; }));
    CHECK(s.write_gltf(buf.data(), buf.size()) == glb.size());
    CHECK(std::equal(glb.begin(), glb.end(), buf.begin()));
    // The C call reports the size with BUFFER_TOO_SMALL.
    n = 0;
    CHECK_STATUS(flame_session_write_gltf(s.get(), FLAME_WHICH_SAMPLE, nullptr, buf.data(), 16, &n),
                 FLAME_STATUS_BUFFER_TOO_SMALL);
    CHECK(n == glb.size());

    // The JSON container: the same accessors, the buffer as a data URI.
    std::vector<uint8_t> gltf = s.write_gltf(FLAME_WHICH_SAMPLE, FLAME_GLTF_CONTAINER_GLTF);
    std::string text(gltf.begin(), gltf.end());
    CHECK(!text.empty() && text[0] == '{');
    CHECK(text.find("\"uri\":\"data:application/octet-stream;base64,") != std::string::npos);
    CHECK(text.find("\"name\":\"Pelvis\"") != std::string::npos);
    flame::GltfParams jp;
    jp.container = FLAME_GLTF_CONTAINER_GLTF;
    CHECK(s.write_gltf_len(FLAME_WHICH_SAMPLE, jp) == gltf.size());

    // fps, name, the estimate.
    std::vector<uint8_t> est = s.write_gltf(FLAME_WHICH_ESTIMATE, FLAME_GLTF_CONTAINER_GLB, 0,
                                            30.0f, "my walk, take 2!");
    CHECK(split_glb(est, &json, &bin));
    CHECK(json.find("\"name\":\"my_walk_take_2\"") != std::string::npos);
    CHECK(json.find("\"fps\":30.0") != std::string::npos);
    CHECK(holds(bin, s.read(FLAME_WHICH_ESTIMATE, FLAME_LAYOUT_ROOT_TRANSLATION,
                            FLAME_CONVENTION_GLTF)));
    CHECK(holds(bin, std::vector<float>{0.0f, 1.0f / 30.0f, 2.0f / 30.0f}));

    // Errors.
    CHECK_THROWS(s.write_gltf(FLAME_WHICH_SAMPLE, static_cast<FlameGltfContainer>(7)),
                 FLAME_STATUS_INVALID_ARGUMENT, "unknown glTF container 7");
    CHECK_THROWS(s.write_gltf(FLAME_WHICH_SAMPLE, FLAME_GLTF_CONTAINER_GLB, 0, -1.0f),
                 FLAME_STATUS_INVALID_ARGUMENT, "frame rate must be positive");
    CHECK_THROWS(s.write_gltf(FLAME_WHICH_SAMPLE, FLAME_GLTF_CONTAINER_GLB, 4),
                 FLAME_STATUS_INVALID_ARGUMENT, "unknown read flags");
    CHECK_THROWS(s.write_gltf(static_cast<FlameWhich>(3)), FLAME_STATUS_INVALID_ARGUMENT,
                 "unknown `which` 3");
    CHECK_THROWS(s.write_gltf(FLAME_WHICH_SAMPLE, FLAME_GLTF_CONTAINER_GLB, 0, 0.0f,
                              std::string("a\0b", 3)),
                 FLAME_STATUS_INVALID_ARGUMENT, "NUL");
    flame::GltfParams small;
    small.struct_size = 8;
    CHECK_THROWS(s.write_gltf(FLAME_WHICH_SAMPLE, small), FLAME_STATUS_INVALID_ARGUMENT,
                 "struct_size");
    flame::Session moved = std::move(s);
    CHECK_THROWS(s.write_gltf(), FLAME_STATUS_INVALID_ARGUMENT, "`session` is NULL");
    CHECK(moved.write_gltf() == glb);
}

static void test_humanml(const std::string &dir) {
    flame::Model model = flame::Model::load(dir + "/mdm_tiny.safetensors");
    flame::ModelInfo info = model.info();
    CHECK(info.motion_format == "humanml263" && info.joint_count == 22);
    flame::Session s = stepped(model);
    std::vector<uint8_t> glb = s.write_gltf();
    std::string json;
    std::vector<uint8_t> bin;
    CHECK(split_glb(glb, &json, &bin));
    CHECK(json.find("\"name\":\"humanml22\"") != std::string::npos);
    // Every joint's translation is animated too (humanml263's positions are its own features).
    CHECK(count(json, "\"path\":\"rotation\"") == 22 && count(json, "\"path\":\"translation\"") == 22);
    CHECK(json.find("\"format\":\"humanml263\"") != std::string::npos);
    check_matches_read(s, info, 0);
}

int main(int argc, char **argv) {
    if (argc != 2) {
        std::fprintf(stderr, "usage: test_cpp_gltf FIXTURES_DIR\n");
        return 2;
    }
    const std::string dir = argv[1];
    try {
        test_smpl(dir);
        test_humanml(dir);
    } catch (const std::exception &e) {
        check_record(0, __FILE__, __LINE__, "unexpected exception", e.what());
    }
    return check_summary();
}
