// The C++ wrapper's robots (flame::Robot, flame::RobotRetarget, flame::RobotState): the robot's
// queries, every file of RobotRetarget::write equal byte for byte to flame_robot_retarget_write's,
// the per-frame reads equal bit for bit to flame_robot_retarget_read's and
// flame_robot_retarget_read_stream's (a whole read, then frame by frame after reset()), errors
// as flame::Error with the library's message, and moved-from objects freeing nothing twice.
//
// usage: test_cpp_robot FIXTURES_DIR GR1T2.urdf GR1T2.json
//   (tests/fixtures: flame_tiny.safetensors; the URDF fetched by tools/fetch_robots.sh; the
//   configuration libflame ships as robots/gr1t2.json)

#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <iterator>
#include <string>
#include <utility>
#include <vector>

#include "flame.hpp"

#include "check.h"

namespace {

const std::size_t FRAMES = 24;
const std::size_t DOFS = 32;

std::vector<uint8_t> read_bytes(const std::string& path) {
    std::ifstream f(path, std::ios::binary);
    return std::vector<uint8_t>((std::istreambuf_iterator<char>(f)), {});
}

// Runs `f`; true when it throws flame::Error with `status` and a message containing `needle`.
template <typename F>
bool throws(F&& f, FlameStatus status, const char* needle = "") {
    try {
        f();
    } catch (const flame::Error& e) {
        return e.status() == status && e.message().find(needle) != std::string::npos;
    }
    return false;
}

// The C ABI's file for the same arguments.
std::vector<uint8_t> c_write(const flame::RobotRetarget& r, const flame::Session& s, uint32_t file,
                             uint32_t options, const FlameCleanupParams* cleanup) {
    std::size_t n = 0;
    CHECK_OK(flame_robot_retarget_write(r.get(), s.get(), FLAME_WHICH_SAMPLE, 0, cleanup, file,
                                        options, nullptr, 0, &n));
    std::vector<uint8_t> out(n);
    CHECK_OK(flame_robot_retarget_write(r.get(), s.get(), FLAME_WHICH_SAMPLE, 0, cleanup, file,
                                        options, out.data(), out.size(), &n));
    return out;
}

bool same(const std::vector<double>& a, const std::vector<double>& b) {
    return a.size() == b.size() && std::memcmp(a.data(), b.data(), a.size() * sizeof(double)) == 0;
}

bool same(const flame::RobotFrames& a, const flame::RobotFrames& b) {
    return a.frames == b.frames && a.dofs == b.dofs && same(a.root_pos, b.root_pos) &&
           same(a.root_rot_xyzw, b.root_rot_xyzw) && same(a.q, b.q) && same(a.residual, b.residual);
}

}  // namespace

int main(int argc, char** argv) {
    if (argc < 4) {
        std::fprintf(stderr, "usage: %s FIXTURES_DIR ROBOT.urdf CONFIG.json\n", argv[0]);
        return 2;
    }
    std::vector<uint8_t> urdf = read_bytes(argv[2]);
    std::vector<uint8_t> config_bytes = read_bytes(argv[3]);
    if (urdf.empty() || config_bytes.empty()) {
        std::fprintf(stderr, "cannot read %s or %s (bash tools/fetch_robots.sh)\n", argv[2],
                     argv[3]);
        return 2;
    }
    std::string config(config_bytes.begin(), config_bytes.end());

    // The robot and its queries; a moved robot.
    flame::Robot loaded = flame::Robot::load(urdf);
    flame::Robot robot = std::move(loaded);
    CHECK(!loaded && loaded.get() == nullptr && robot);
    CHECK(robot.name() == "gr1t2");
    CHECK(robot.dof_count() == DOFS);
    std::vector<std::string> names = robot.dof_names();
    CHECK(names.size() == DOFS && names[0] == "left_hip_roll_joint");
    CHECK(robot.dof_name(DOFS - 1) == names.back());
    CHECK(throws([&] { robot.dof_name(DOFS); }, FLAME_STATUS_INVALID_ARGUMENT, "past"));
    CHECK(throws([&] { flame::Robot::load(urdf.data(), urdf.size() / 2); },
                 FLAME_STATUS_INVALID_ARGUMENT));
    CHECK(throws([&] { loaded.name(); }, FLAME_STATUS_INVALID_ARGUMENT, "robot"));

    // The retarget (from the text and from bytes); the robot may go once it is made.
    flame::RobotRetarget moved(robot, config);
    flame::RobotRetarget r = std::move(moved);
    CHECK(moved.get() == nullptr && r);
    flame::RobotRetarget r2(robot, config_bytes.data(), config_bytes.size());
    CHECK(throws([&] { flame::RobotRetarget(robot, "{\"robot_root_name\": \"no_such_body\"}"); },
                 FLAME_STATUS_INVALID_ARGUMENT, "no_such_body"));
    CHECK(throws([&] { flame::RobotRetarget(robot, "{"); }, FLAME_STATUS_INVALID_ARGUMENT));
    robot = flame::Robot();
    CHECK(!robot);
    CHECK(r.dof_count() == DOFS && r2.dof_count() == DOFS);
    CHECK(throws([&] { moved.dof_count(); }, FLAME_STATUS_INVALID_ARGUMENT, "retarget"));

    // A session, read after two of ten steps (the tiny model's final motion saturates).
    std::string dir = argv[1];
    flame::Model model = flame::Model::load(dir + "/flame_tiny.safetensors");
    flame::SessionParams sp;
    sp.frames = FRAMES;
    sp.steps = 10;
    sp.sampler = FLAME_SAMPLER_DDIM;
    sp.seed = 5;
    sp.threads = 1;
    flame::Session s = model.session(sp);
    s.set_prompt("a person walks forward and waves.");
    CHECK(throws([&] { r.write(s); }, FLAME_STATUS_WRONG_STATE));
    s.step();
    s.step();

    // Whole clips: each file as the C ABI writes it.
    flame::CleanupParams clean;
    clean.set_fps(30);
    std::vector<uint8_t> csv = r.write(s);
    CHECK(csv == c_write(r, s, FLAME_ROBOT_BEYONDMIMIC_CSV_XYZW, 0, nullptr));
    std::string text(csv.begin(), csv.end());
    std::size_t rows = 0, commas = 0;
    for (char ch : text) {
        rows += ch == '\n';
        commas += ch == ',';
    }
    CHECK(rows == FRAMES && commas == FRAMES * (7 + DOFS - 1) && text[0] != '#');
    std::vector<uint8_t> csvh = r.write(s, FLAME_ROBOT_BEYONDMIMIC_CSV_XYZW, FLAME_ROBOT_CSV_HEADER);
    std::string texth(csvh.begin(), csvh.end());
    CHECK(texth.rfind("# x,y,z,qx,qy,qz,qw,left_hip_roll_joint,", 0) == 0);
    CHECK(texth.find('\n') != std::string::npos && texth.substr(texth.find('\n') + 1) == text);
    std::vector<uint8_t> npz = r.write(s, FLAME_ROBOT_GMR_NPZ_XYZW, 0, &clean);
    CHECK(npz == c_write(r, s, FLAME_ROBOT_GMR_NPZ_XYZW, 0, &clean));
    CHECK(npz.size() > 4 && std::memcmp(npz.data(), "PK\x03\x04", 4) == 0);
    std::vector<uint8_t> npy = r.write(s, FLAME_ROBOT_QPOS_NPY_WXYZ);
    CHECK(npy == c_write(r, s, FLAME_ROBOT_QPOS_NPY_WXYZ, 0, nullptr));
    CHECK(std::string(npy.begin(), npy.end()).find("'shape': (24, 39)") != std::string::npos);
    std::vector<uint8_t> qcsv = r.write(s, FLAME_ROBOT_QPOS_CSV_WXYZ, FLAME_ROBOT_CSV_HEADER);
    CHECK(std::string(qcsv.begin(), qcsv.end()).rfind("# x,y,z,qw,qx,qy,qz,", 0) == 0);
    CHECK(throws([&] { r.write(s, 4); }, FLAME_STATUS_INVALID_ARGUMENT,
                 "robot trajectory file 4"));
    CHECK(throws([&] { r.write(s, FLAME_ROBOT_BEYONDMIMIC_CSV_XYZW, 2); },
                 FLAME_STATUS_INVALID_ARGUMENT, "options"));

    // Per-frame reads: the whole clip equals the C ABI's from a fresh state, bit for bit, and
    // frame by frame after reset() equals reading in chunks.
    flame::RobotState st = r.state();
    flame::RobotFrames all = r.read(s, st, 0, SIZE_MAX, &clean);
    CHECK(all.frames > FRAMES && all.dofs == DOFS);  // more frames at 30 fps than at 20
    CHECK(all.root_pos.size() == all.frames * 3 && all.root_rot_xyzw.size() == all.frames * 4 &&
          all.q.size() == all.frames * DOFS && all.residual.size() == all.frames);
    {
        FlameRobotState* cst = nullptr;
        CHECK_OK(flame_robot_state_new(r.get(), &cst));
        const std::size_t n = all.frames;
        std::vector<double> pos(n * 3), rot(n * 4), q(n * DOFS), res(n);
        std::size_t frames = 0;
        CHECK_OK(flame_robot_retarget_read(r.get(), cst, s.get(), FLAME_WHICH_SAMPLE, 0, &clean, 0,
                                           n, pos.data(), pos.size(), rot.data(), rot.size(),
                                           q.data(), q.size(), res.data(), res.size(), &frames));
        CHECK(frames == n);
        CHECK(same(pos, all.root_pos) && same(rot, all.root_rot_xyzw) && same(q, all.q) &&
              same(res, all.residual));
        flame_robot_state_free(cst);
    }
    double worst = 0.0;
    bool finite = true;
    for (std::size_t f = 0; f < all.frames; ++f) {
        double nq = 0.0;
        for (int k = 0; k < 4; ++k) {
            nq += all.root_rot_xyzw[4 * f + k] * all.root_rot_xyzw[4 * f + k];
        }
        worst = std::fmax(worst, std::fabs(std::sqrt(nq) - 1.0));
        finite = finite && std::isfinite(all.residual[f]) && all.residual[f] >= 0.0;
    }
    CHECK(worst < 1e-9 && finite);

    flame::RobotState chunked = r.state();
    flame::RobotFrames a = r.read(s, chunked, 0, 6);
    flame::RobotFrames b = r.read(s, chunked, 6, 6);
    chunked.reset();
    bool frame_by_frame = true;
    for (std::size_t f = 0; f < 12; ++f) {
        flame::RobotFrames one = r.read(s, chunked, f, 1);
        const flame::RobotFrames& from = f < 6 ? a : b;
        const std::size_t i = f % 6;
        frame_by_frame = frame_by_frame && one.frames == 1 &&
                         std::memcmp(one.q.data(), from.q.data() + i * DOFS,
                                     DOFS * sizeof(double)) == 0 &&
                         std::memcmp(one.root_rot_xyzw.data(), from.root_rot_xyzw.data() + i * 4,
                                     4 * sizeof(double)) == 0 &&
                         one.residual[0] == from.residual[i];
    }
    CHECK(frame_by_frame);
    CHECK(r.read(s, chunked, FRAMES - 2).frames == 2);  // to the end
    CHECK(throws([&] { r.read(s, st, FRAMES, 1); }, FLAME_STATUS_INVALID_ARGUMENT, "past"));
    flame::RobotState other = r2.state();
    CHECK(throws([&] { r.read(s, other, 0, 1); }, FLAME_STATUS_INVALID_ARGUMENT,
                 "another retarget"));
    flame::RobotState taken = std::move(other);
    CHECK(!other && taken);
    CHECK(throws([&] { r.read(s, other, 0, 1); }, FLAME_STATUS_INVALID_ARGUMENT, "state"));
    CHECK(throws([&] { other.reset(); }, FLAME_STATUS_INVALID_ARGUMENT));

    // A stream: frames as they come, cleaned; the same bits as the C ABI's from a fresh state.
    flame::StreamParams stp;
    stp.threads = 1;
    flame::Stream stream = model.stream(stp);
    stream.push("a person walks forward.", 40);
    flame::CleanupParams c;
    flame::RobotState live = r.state();
    CHECK(throws([&] { r.read_stream(stream, live, 0, 4, &c); }, FLAME_STATUS_WRONG_STATE));
    flame::StreamStatus ss;
    for (int k = 0; k < 200 && ss.ready < 40; ++k) {
        ss = stream.pump(10);
    }
    CHECK(ss.ready >= 40);
    stream.end_timeline();
    flame::RobotFrames s0 = r.read_stream(stream, live, 0, 4, &c);
    flame::RobotFrames s1 = r.read_stream(stream, live, 4, 4, &c);
    CHECK(s0.frames == 4 && s0.q.size() == 4 * DOFS && s1.frames == 4);
    {
        FlameRobotState* cst = nullptr;
        CHECK_OK(flame_robot_state_new(r.get(), &cst));
        std::vector<double> pos(8 * 3), rot(8 * 4), q(8 * DOFS), res(8);
        CHECK_OK(flame_robot_retarget_read_stream(r.get(), cst, stream.get(), 0, 4, &c,
                                                  pos.data(), 12, rot.data(), 16, q.data(),
                                                  4 * DOFS, res.data(), 4));
        CHECK_OK(flame_robot_retarget_read_stream(r.get(), cst, stream.get(), 4, 4, &c,
                                                  pos.data() + 12, 12, rot.data() + 16, 16,
                                                  q.data() + 4 * DOFS, 4 * DOFS, res.data() + 4,
                                                  4));
        std::vector<double> wq(s0.q), wres(s0.residual);
        wq.insert(wq.end(), s1.q.begin(), s1.q.end());
        wres.insert(wres.end(), s1.residual.begin(), s1.residual.end());
        CHECK(same(q, wq) && same(res, wres));
        flame_robot_state_free(cst);
    }
    live.reset();
    CHECK(same(r.read_stream(stream, live, 0, 4, &c), s0));
    flame::Stream gone;
    CHECK(throws([&] { r.read_stream(gone, live, 0, 1); }, FLAME_STATUS_INVALID_ARGUMENT,
                 "stream"));
    return check_summary();
}
