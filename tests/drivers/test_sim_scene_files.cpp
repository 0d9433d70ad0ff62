// The tracker simulator's files (issue 5, "scripted or following a trajectory file", "fault
// injection, scriptable"): a trajectory file drives a tool's true pose (linear in position, slerp
// in rotation, looped), the other tools keep their scripted motion; bad trajectory and fault
// script files are refused naming the file and the line.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <filesystem>
#include <fstream>

#include "cortexfuse/drivers/sim/tracker_sim.hpp"

namespace fs = std::filesystem;
using cf::sim::Fault;
using cf::sim::TrackerSimConfig;
using cf::sim::TrackerSimulator;

namespace {

struct TempDir {
    fs::path path = fs::temp_directory_path() / ("cf_sim_files_" + std::to_string(::getpid()));
    TempDir() { fs::create_directories(path); }
    ~TempDir() { fs::remove_all(path); }
    fs::path write(const std::string& name, const std::string& text) const {
        std::ofstream(path / name) << text;
        return path / name;
    }
};

std::string error_of(const std::function<void()>& f) {
    try {
        f();
    } catch (const std::invalid_argument& e) {
        return e.what();
    }
    return "(no error)";
}

TEST(SimScene, TrajectoryFileIsInterpolatedAndLooped) {
    TempDir d;
    const double s = std::sqrt(0.5);  // 90 degrees about z: qw = qz = sqrt(1/2)
    TrackerSimConfig c;
    c.frame_rate_hz = 60;
    c.noise_mm = 0.05;
    c.trajectory_file = d.write("path.txt",
                                "# t_s part tx ty tz qw qx qy qz\n"
                                "0 CF-POINTER 0 0 -1000 1 0 0 0\n"
                                "1 CF-POINTER 100 0 -1000 1 0 0 0   # a comment\n"
                                "\n"
                                "2 CF-POINTER 100 50 -1000 " + std::to_string(s) + " 0 0 " + std::to_string(s) + "\n")
                            .string();
    TrackerSimulator sim(c);
    auto at = [&](std::uint32_t frame) {
        auto t = sim.truth("CF-POINTER", frame);
        EXPECT_TRUE(t.has_value());
        return *t;
    };
    // t = 0.5 s: halfway along the first segment.
    EXPECT_LT((at(30).T_tracker_from_tool.translation() - Eigen::Vector3d(50, 0, -1000)).norm(), 1e-9);
    EXPECT_TRUE(at(30).T_tracker_from_tool.linear().isApprox(Eigen::Matrix3d::Identity(), 1e-9));
    // t = 1.5 s: halfway along the second, position linear, rotation slerped to 45 degrees.
    const auto mid = at(90).T_tracker_from_tool;
    EXPECT_LT((mid.translation() - Eigen::Vector3d(100, 25, -1000)).norm(), 1e-9);
    EXPECT_NEAR(Eigen::AngleAxisd(mid.linear()).angle(), M_PI / 4, 1e-6);
    EXPECT_NEAR(std::abs(Eigen::AngleAxisd(mid.linear()).axis().z()), 1.0, 1e-6);
    // Looped with the last key's time as the period: t = 2.5 s is t = 0.5 s again.
    EXPECT_LT((at(150).T_tracker_from_tool.translation() - Eigen::Vector3d(50, 0, -1000)).norm(), 1e-9);
    // The measurement is the truth plus the frame's noise (6 sigma per axis at most).
    EXPECT_LT((at(30).measured.translation() - at(30).T_tracker_from_tool.translation()).norm(), 6 * c.noise_mm * std::sqrt(3.0));
    // A tool the file does not name keeps its scripted pose (the reference is still).
    EXPECT_TRUE(sim.truth("CF-REFERENCE", 30)->T_tracker_from_tool.isApprox(sim.truth("CF-REFERENCE", 150)->T_tracker_from_tool));
    // Without the file the pointer moves on its scripted circle instead.
    TrackerSimConfig plain;
    TrackerSimulator scripted(plain);
    EXPECT_GT((scripted.truth("CF-POINTER", 30)->T_tracker_from_tool.translation() - Eigen::Vector3d(50, 0, -1000)).norm(), 1.0);
}

TEST(SimScene, BadTrajectoryFilesNameTheFileAndLine) {
    TempDir d;
    auto load = [&](const std::string& name, const std::string& text) {
        TrackerSimConfig c;
        c.trajectory_file = d.write(name, text).string();
        return error_of([&] { TrackerSimulator sim(c); });
    };
    EXPECT_NE(load("short.txt", "0 CF-POINTER 0 0 -1000 1 0 0 0\n1 CF-POINTER 1 2 3\n").find("short.txt:2: expected '<t_s> <part>"), std::string::npos);
    EXPECT_NE(load("quat.txt", "0 CF-POINTER 0 0 -1000 2 0 0 0\n").find("quat.txt:1: quaternion is not unit length"), std::string::npos);
    EXPECT_NE(load("order.txt", "1 CF-POINTER 0 0 0 1 0 0 0\n1 CF-POINTER 0 0 0 1 0 0 0\n").find("order.txt:2: times must increase"), std::string::npos);
    TrackerSimConfig c;
    c.trajectory_file = (d.path / "missing.txt").string();
    EXPECT_NE(error_of([&] { TrackerSimulator sim(c); }).find("missing.txt: cannot open the trajectory file"), std::string::npos);
}

TEST(SimScene, FaultScriptIsReadAndBadLinesAreNamed) {
    TempDir d;
    const auto f = cf::sim::load_fault_script(d.write("faults.txt",
                                                      "# at_s fault [tool duration_s]\n"
                                                      "0.5 bit_flip\n"
                                                      "\n"
                                                      "2 disconnect   # pull the cable\n"
                                                      "3.25 tool_missing CF-POINTER 1.5\n")
                                                  .string());
    ASSERT_EQ(f.size(), 3u);
    EXPECT_DOUBLE_EQ(f[0].at_s, 0.5);
    EXPECT_EQ(f[0].kind, Fault::bit_flip);
    EXPECT_EQ(f[1].kind, Fault::disconnect);
    EXPECT_EQ(f[2].kind, Fault::tool_missing);
    EXPECT_EQ(f[2].tool, "CF-POINTER");
    EXPECT_DOUBLE_EQ(f[2].duration_s, 1.5);
    auto bad = [&](const std::string& name, const std::string& text) {
        return error_of([&] { cf::sim::load_fault_script(d.write(name, text).string()); });
    };
    EXPECT_NE(bad("unknown.txt", "1 bit_flip\n2 lightning\n").find("unknown.txt:2: unknown fault 'lightning'"), std::string::npos);
    EXPECT_NE(bad("tool.txt", "1 out_of_volume CF-POINTER\n").find("tool.txt:1: out_of_volume needs a tool part name and a duration"), std::string::npos);
    EXPECT_NE(bad("time.txt", "soon drop\n").find("time.txt:1: expected '<at_s> <fault>"), std::string::npos);
    EXPECT_NE(error_of([&] { cf::sim::load_fault_script((d.path / "none.txt").string()); }).find("none.txt: cannot open the fault script"),
              std::string::npos);
}

}  // namespace
