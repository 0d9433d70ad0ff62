// The tracker frame's JSON (cortexfuse track --json and the daemon's push channel).
#include <gtest/gtest.h>

#include <Eigen/Geometry>

#include "cortexfuse/drivers/tracker/frame_json.hpp"

using namespace cf::tracker;

TEST(FrameJson, CarriesEveryFieldAndAPoseOnlyForASeenTool) {
    TrackerFrame f;
    f.sequence = 7;
    f.frame_number = 1234;
    f.system_status = 0x10;
    f.receive_steady_ns = 1'000'000;
    f.publish_steady_ns = 1'012'500;
    TrackedTool seen;
    seen.name = "pointer";
    seen.handle = 2;
    seen.status = ToolReading::Status::ok;
    seen.port_status = 0x31;
    seen.rms_error_mm = 0.15;
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.rotate(Eigen::AngleAxisd(M_PI / 2, Eigen::Vector3d::UnitZ()));
    T.translation() = Eigen::Vector3d(10, -20, -1500);
    seen.T_tracker_from_tool = T;
    TrackedTool missing;
    missing.name = "reference";
    missing.handle = 1;
    missing.status = ToolReading::Status::missing;
    missing.port_status = 0x31;
    missing.partially_out_of_volume = true;
    f.tools = {seen, missing};

    const nlohmann::json j = frame_to_json(f);
    EXPECT_EQ(j["seq"], 7);
    EXPECT_EQ(j["frame"], 1234);
    EXPECT_EQ(j["system_status"], 0x10);
    EXPECT_DOUBLE_EQ(j["latency_us"].get<double>(), 12.5);
    ASSERT_EQ(j["tools"].size(), 2u);
    const auto& a = j["tools"][0];
    EXPECT_EQ(a["name"], "pointer");
    EXPECT_EQ(a["status"], "ok");
    EXPECT_EQ(a["port_status"], 0x31);
    EXPECT_NEAR(a["q_wxyz"][0].get<double>(), std::cos(M_PI / 4), 1e-12);
    EXPECT_NEAR(a["q_wxyz"][3].get<double>(), std::sin(M_PI / 4), 1e-12);
    EXPECT_EQ(a["t_mm"], nlohmann::json::array({10.0, -20.0, -1500.0}));
    EXPECT_DOUBLE_EQ(a["rms_mm"].get<double>(), 0.15);
    const auto& b = j["tools"][1];
    EXPECT_EQ(b["status"], "missing");
    EXPECT_TRUE(b["partially_out_of_volume"].get<bool>());
    EXPECT_FALSE(b.contains("q_wxyz"));  // never a pose for a tool not seen in this frame
    EXPECT_FALSE(b.contains("t_mm"));
    EXPECT_STREQ(tool_status_name(ToolReading::Status::unoccupied), "unoccupied");
    EXPECT_STREQ(tool_status_name(ToolReading::Status::disabled), "disabled");
}
