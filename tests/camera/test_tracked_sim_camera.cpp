// The simulated camera on the tracker simulator's camera tool (issue 5, 5.22): each photo is
// taken from T_optics_from_tool * inverse(T_tracker_from_tool) * T_tracker_from_reference *
// T_reference_from_image at the simulator's current frame.
#include <gtest/gtest.h>

#include <chrono>
#include <memory>
#include <stdexcept>
#include <string>
#include <thread>

#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/volume.hpp"
#include "cortexfuse/drivers/camera.hpp"
#include "cortexfuse/drivers/sim/tracked_camera.hpp"
#include "cortexfuse/drivers/sim/tracker_sim.hpp"

namespace fs = std::filesystem;
using namespace cf;

namespace {

double angle_deg(const Eigen::Matrix3d& a, const Eigen::Matrix3d& b) {
    return Eigen::AngleAxisd(a.transpose() * b).angle() * 180.0 / M_PI;
}

/// Waits until the simulator is at `frame` or later.
void wait_for_frame(const sim::TrackerSimulator& s, std::uint32_t frame) {
    const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(5);
    while (s.current_frame() < frame && std::chrono::steady_clock::now() < until) std::this_thread::sleep_for(std::chrono::milliseconds(2));
    ASSERT_GE(s.current_frame(), frame);
}

}  // namespace

// One test: the phantom scene (the brain surface) is built once.
TEST(TrackedSimCamera, PhotoIsTakenFromTheTrackedCameraToolPose) {
    sim::TrackerSimConfig tc;
    tc.camera_tool = true;
    tc.frame_rate_hz = 250;
    tc.noise_mm = 0.05;
    tc.noise_deg = 0.05;
    sim::TrackerSimulator tracker(tc);
    tracker.start();

    camera::SimCameraConfig c;
    c.surface = std::make_shared<const PhantomSurface>(build_phantom_surface(
        load_volume(fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz"), load_mask(fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz")));
    c.seed = 7;
    c.width = 320;
    c.height = 240;
    c.capture_delay_ms = 0;
    std::unique_ptr<camera::Camera> owned = camera::make_sim_backend(c)->open("sim:0");
    auto& cam = dynamic_cast<camera::SimCamera&>(*owned);

    sim::TrackedCameraRig rig;
    sim::register_rig_to_view(rig, tracker, Eigen::Isometry3d(cam.home_pose()));
    // The registration puts the camera tool's rest pose (frame 0) at the home framing.
    EXPECT_TRUE(sim::camera_from_image(tracker, rig, 0).matrix().isApprox(cam.home_pose(), 1e-9));
    cam.set_pose_source(sim::tracked_camera_pose_source(tracker, rig));

    // The camera tool held at a known pose: its rest pose moved by 6 mm and turned by 4 deg.
    const Eigen::Isometry3d rest = tracker.truth("CF-CAMERA", 0)->T_tracker_from_tool;
    Eigen::Isometry3d held = rest;
    held.translate(Eigen::Vector3d(6, -3, 2));
    held.rotate(Eigen::AngleAxisd(4 * M_PI / 180, Eigen::Vector3d(0.3, 1, 0.2).normalized()));
    const std::uint32_t from = tracker.hold("CF-CAMERA", held);
    wait_for_frame(tracker, from);
    const std::uint32_t before = tracker.current_frame();
    const camera::Photo p = cam.capture();
    ASSERT_TRUE(p.T_camera_from_world.has_value());
    const Eigen::Isometry3d got(*p.T_camera_from_world);

    // Expected, composed here by hand with the frames named.
    const Eigen::Isometry3d T_tracker_from_reference = tracker.truth("CF-REFERENCE", before)->T_tracker_from_tool;
    const Eigen::Isometry3d expected = rig.T_optics_from_tool * held.inverse() * T_tracker_from_reference * rig.T_reference_from_image;
    EXPECT_LT((got.translation() - expected.translation()).norm(), 1e-6);
    EXPECT_LT(angle_deg(got.linear(), expected.linear()), 1e-6);
    // Not the scripted orbit (which starts at home) and not the rest pose: the hold moved it.
    EXPECT_GT((got.translation() - Eigen::Isometry3d(cam.home_pose()).translation()).norm(), 3.0);

    // What the tracker reports for the camera tool (with its noise) composes to the same pose
    // within the noise: 0.05 mm / 0.05 deg per frame; at the ~300 mm viewing distance the
    // rotation noise moves the optics' origin by well under 1 mm.
    const Eigen::Isometry3d measured = tracker.truth("CF-CAMERA", before)->measured;
    const Eigen::Isometry3d reported = rig.T_optics_from_tool * measured.inverse() * T_tracker_from_reference * rig.T_reference_from_image;
    EXPECT_LT((got.translation() - reported.translation()).norm(), 1.0);
    EXPECT_LT(angle_deg(got.linear(), reported.linear()), 0.3);

    // The photo shows the scene from there: it differs from the home framing's photo.
    cam.set_pose(cam.home_pose());
    const camera::Photo home = cam.capture();
    cam.set_pose(std::nullopt);
    cv::Mat diff;
    cv::absdiff(home.bgr, p.bgr, diff);
    EXPECT_GT(cv::mean(diff)[1], 3.0);

    // Released: the camera follows the tool's scripted sway again, still in view (its extremes at
    // 5 s and 15 s of the 20 s period).
    tracker.hold("CF-CAMERA", std::nullopt);
    for (double t_s : {5.0, 15.0}) {
        const Eigen::Isometry3d sway = sim::camera_from_image(tracker, rig, std::uint32_t(t_s * tc.frame_rate_hz));
        cam.set_pose(sway.matrix());
        EXPECT_NO_THROW(cam.capture()) << "sway at " << t_s << " s";
    }
    tracker.stop();
}

TEST(TrackedSimCamera, BadConfigurationsAreNamed) {
    sim::TrackerSimConfig tc;  // no camera tool
    sim::TrackerSimulator tracker(tc);
    sim::TrackedCameraRig rig;
    try {
        sim::tracked_camera_pose_source(tracker, rig);
        ADD_FAILURE() << "a pose source without a camera tool was made";
    } catch (const std::invalid_argument& e) {
        EXPECT_NE(std::string(e.what()).find("no 'CF-CAMERA' tool"), std::string::npos) << e.what();
    }
    EXPECT_THROW(sim::register_rig_to_view(rig, tracker, Eigen::Isometry3d::Identity()), std::invalid_argument);

    sim::TrackerSimConfig with_camera;
    with_camera.camera_tool = true;
    sim::TrackerSimulator tracker2(with_camera);
    sim::TrackedCameraRig scaled;
    scaled.T_optics_from_tool.linear() *= 1.1;
    try {
        sim::register_rig_to_view(scaled, tracker2, Eigen::Isometry3d::Identity());
        ADD_FAILURE() << "a scaled hand-eye transform was accepted";
    } catch (const std::invalid_argument& e) {
        EXPECT_NE(std::string(e.what()).find("T_optics_from_tool: not a rigid transform"), std::string::npos) << e.what();
    }
    EXPECT_THROW(sim::parse_pose7("1 2 3 1 0 0", "camera.sim_T_optics_from_tool"), std::invalid_argument);
    EXPECT_THROW(sim::parse_pose7("1 2 3 2 0 0 0", "camera.sim_T_optics_from_tool"), std::invalid_argument);
    const Eigen::Isometry3d T = sim::parse_pose7("1 2 3 0.7071067811865476 0.7071067811865476 0 0", "x");
    EXPECT_LT((T.translation() - Eigen::Vector3d(1, 2, 3)).norm(), 1e-12);
    EXPECT_NEAR(Eigen::AngleAxisd(T.linear()).angle(), M_PI / 2, 1e-9);
}
