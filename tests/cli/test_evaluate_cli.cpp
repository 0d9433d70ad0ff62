// `cortexfuse evaluate` as a researcher runs it: the protocol's misalignments stay within the
// range asked for, the JSON carries every pose a run went through (truth, landmark fit, start,
// each stage, result) so a failure can be taken apart afterwards, and a folder with nothing to
// evaluate is refused without writing anything.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "base_case.hpp"
#include "cli_files.hpp"
#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/pose.hpp"
#include "process.hpp"

namespace fs = std::filesystem;
using nlohmann::json;
using namespace cf;

namespace {

// core's is_rigid, as strict as the poses written here allow (orthonormal to 1e-6).
bool rigid(const Pose& T) { return is_rigid(T, 1e-7); }

test::ProcessResult run_evaluate(std::vector<std::string> args) {
    std::vector<std::string> argv{test::cortexfuse_exe(), "evaluate"};
    argv.insert(argv.end(), args.begin(), args.end());
    return test::run_process(argv, 300.0);
}

// One small case in a set folder and a one-stage schedule: the poses, not the accuracy, are
// under test here (accuracy is measured by bench/ and docs/registration.md).
fs::path make_set(const fs::path& work) {
    fs::create_directories(work / "set");
    fs::copy(test::base_cases() / "small", work / "set" / "case_0000", fs::copy_options::recursive);
    test::write_json(work / "params.json", {{"search_stages", json::array()},
                                      {"final_stages", {{{"name", "one"}, {"max_evaluations", 8}, {"render_width_px", 96}}}}});
    return work / "set";
}

}  // namespace

TEST(EvaluateCli, JsonCarriesEveryPoseAndTheMisalignmentStaysInRange) {
    const fs::path work = test::fresh_dir("evaluate");
    const fs::path set = make_set(work);
    const Pose T_truth = test::pose_of(test::read_json(set / "case_0000" / "truth.json").at("T_camera_from_world"));
    for (const bool wide : {false, true}) {
        std::vector<std::string> args{set.string(), "--trials", "3", "--params", (work / "params.json").string(),
                                      "--json", (work / "e.json").string(), "--md", (work / "e.md").string()};
        if (wide) args.push_back("--wide");
        const auto r = run_evaluate(args);
        ASSERT_EQ(r.exit_code, 0) << r.err;
        const json j = test::read_json(work / "e.json");
        ASSERT_EQ(j.at("runs").size(), 3u);
        const double max_mm = wide ? 20 : 10, max_deg = wide ? 15 : 5;
        EXPECT_EQ(j.at("max_mm").get<double>(), max_mm);
        for (const json& run : j.at("runs")) {
            const Pose T_true = test::pose_of(run.at("truth_T_camera_from_world"));
            EXPECT_TRUE(T_true.isApprox(T_truth, 1e-12));
            const Pose T_lm = test::pose_of(run.at("landmark_T_camera_from_world"));
            const Pose T_init = test::pose_of(run.at("initial").at("T_camera_from_world"));
            const Pose T_reg = test::pose_of(run.at("registered").at("T_camera_from_world"));
            EXPECT_TRUE(rigid(T_lm) && rigid(T_init) && rigid(T_reg));
            // The start is the landmark pose misaligned within the range: turns of at most
            // max_deg about each axis, so at most 3 * max_deg in all (angles of composed turns add
            // at most).
            const Eigen::Matrix3d dR = T_init.topLeftCorner<3, 3>() * T_lm.topLeftCorner<3, 3>().transpose();
            const double angle_deg = Eigen::AngleAxisd(dR).angle() * 180 / M_PI;
            EXPECT_GT(angle_deg, 0.01);
            EXPECT_LE(angle_deg, 3 * max_deg + 1e-6);
            const auto& m = run.at("misalignment");
            for (int i = 0; i < 6; ++i) EXPECT_LE(std::abs(m.at(size_t(i)).get<double>()), i < 3 ? max_deg : max_mm);
            // Every stage records where it left the pose; this schedule's one stage is the result.
            ASSERT_FALSE(run.at("stages").empty());
            for (const json& st : run.at("stages")) EXPECT_TRUE(rigid(test::pose_of(st.at("T_camera_from_world")))) << st.at("name");
            EXPECT_TRUE(test::pose_of(run.at("stages").back().at("T_camera_from_world")).isApprox(T_reg, 1e-9));
        }
        EXPECT_NE(std::ifstream(work / "e.md").peek(), EOF);
    }
    fs::remove_all(work);
}

TEST(EvaluateCli, AFolderWithoutCasesIsRefusedAndNothingIsWritten) {
    const fs::path work = test::fresh_dir("evaluate_empty");
    fs::create_directories(work / "set" / "case_0000");
    test::write_json(work / "set" / "case_0000" / "case.json", json::object());  // no truth.json beside it
    const auto r = run_evaluate({(work / "set").string(), "--trials", "1", "--json", (work / "e.json").string()});
    EXPECT_NE(r.exit_code, 0);
    EXPECT_NE(r.err.find("holds no case folder with case.json and truth.json"), std::string::npos) << r.err;
    EXPECT_FALSE(fs::exists(work / "e.json"));
    const auto bad = run_evaluate({(work / "set").string(), "--trials", "-1"});
    EXPECT_NE(bad.exit_code, 0);
    EXPECT_NE(bad.err.find("--trials"), std::string::npos) << bad.err;
    fs::remove_all(work);
}
