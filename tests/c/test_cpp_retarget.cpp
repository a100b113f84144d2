/*
 * The C++ wrapper's retargeting (flame::Rig, flame::BoneMap, flame::Retarget): the wrapper's
 * reads equal the C ABI's bit for bit (mixamo.glb, automatic map, game-ready cleanup), the bone
 * map's JSON round-trips, errors are flame::Error with the library's message, and moved-from
 * objects free nothing twice.
 *
 * usage: test_cpp_retarget FIXTURES_DIR
 */
#include <cstring>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "flame.hpp"

#include "check.h"

int main(int argc, char** argv) {
    if (argc < 2) {
        std::fprintf(stderr, "usage: %s FIXTURES_DIR\n", argv[0]);
        return 2;
    }
    std::string dir = argv[1];
    std::ifstream f(dir + "/rigs/mixamo.glb", std::ios::binary);
    if (!f) {
        std::printf("skip: no %s/rigs/mixamo.glb\n", dir.c_str());
        CHECK(1);
        return check_summary();
    }
    std::vector<uint8_t> bytes((std::istreambuf_iterator<char>(f)), {});
    flame::Model model = flame::Model::load(dir + "/flame_tiny.safetensors");
    flame::Rig rig = flame::Rig::load(bytes);
    CHECK(rig.bone_count() > 22);
    CHECK(rig.bone_name(0) == "mixamorig:Hips" && rig.bone_parent(0) == -1);
    flame::BoneMap map = flame::BoneMap::automatic(rig);
    std::string json = map.to_json(rig);
    CHECK(json.find("\"hips\": \"mixamorig:Hips\"") != std::string::npos);
    CHECK(flame::BoneMap::from_json(rig, json).to_json(rig) == json);
    flame::RetargetParams params;
    params.map = map.get();
    flame::Retarget moved(model, rig, params);
    flame::Retarget r = std::move(moved);
    CHECK(moved.get() == nullptr);

    flame::SessionParams sp;
    sp.frames = 20;
    sp.steps = 10;
    sp.sampler = FLAME_SAMPLER_DDIM;
    sp.seed = 11;
    sp.threads = 1;
    flame::Session s = model.session(sp);
    s.set_prompt("a person walks forward and waves.");
    s.step();
    s.step();
    flame::CleanupParams cleanup;
    flame::RigPoses poses = r.read(s, 0, SIZE_MAX, &cleanup);
    CHECK(poses.frames == 20 && poses.bones == rig.bone_count());
    std::vector<float> rot(poses.rotations.size()), tr(poses.translations.size());
    CHECK_OK(flame_retarget_read(r.get(), s.get(), FLAME_WHICH_SAMPLE, 0, &cleanup, 0, 20,
                                 rot.data(), rot.size(), tr.data(), tr.size(), nullptr));
    CHECK(std::memcmp(rot.data(), poses.rotations.data(), rot.size() * sizeof(float)) == 0);
    CHECK(std::memcmp(tr.data(), poses.translations.data(), tr.size() * sizeof(float)) == 0);
    flame::RigPoses part = r.read(s, 5, 3, &cleanup);
    CHECK(std::memcmp(part.rotations.data(), rot.data() + 5 * poses.bones * 4,
                      part.rotations.size() * sizeof(float)) == 0);

    bool threw = false;
    try {
        flame::BoneMap::from_json(rig, "{\"hips\": \"Nope\"}");
    } catch (const flame::Error& e) {
        threw = e.status() == FLAME_STATUS_INVALID_ARGUMENT &&
                e.message().find("Nope") != std::string::npos;
    }
    CHECK(threw);
    threw = false;
    try {
        r.read(s, 19, 2);
    } catch (const flame::Error& e) {
        threw = e.status() == FLAME_STATUS_INVALID_ARGUMENT;
    }
    CHECK(threw);
    threw = false;
    try {
        std::vector<uint8_t> cut(bytes.begin(), bytes.begin() + bytes.size() / 2);
        flame::Rig::load(cut);
    } catch (const flame::Error& e) {
        threw = e.status() == FLAME_STATUS_INVALID_ARGUMENT;
    }
    CHECK(threw);
    return check_summary();
}
