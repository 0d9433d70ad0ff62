// The simulated tracked camera rig (tracked_camera.hpp): the tracker simulator's camera tool
// composed with the hand-eye and patient registration transforms of the simulated scene.
#include <cmath>
#include <sstream>
#include <stdexcept>

#include "cortexfuse/drivers/sim/tracked_camera.hpp"

namespace cf::sim {
namespace {

Eigen::Isometry3d tool_pose(const TrackerSimulator& sim, const std::string& part, std::uint32_t frame) {
    const auto t = sim.truth(part, frame);
    if (!t)
        throw std::invalid_argument("sim camera pose: the tracker simulator's scene has no '" + part + "' tool" +
                                    (part == "CF-CAMERA" ? " (start it with the camera tool: tracker.sim_camera_tool / --camera)" : ""));
    return t->T_tracker_from_tool;
}

bool rigid(const Eigen::Isometry3d& T) {
    const Eigen::Matrix3d R = T.linear();
    return T.matrix().allFinite() && (R.transpose() * R - Eigen::Matrix3d::Identity()).norm() < 1e-6 && R.determinant() > 0;
}

}  // namespace

Eigen::Isometry3d default_T_optics_from_tool() {
    // Optics z (the view) = -z_tool, optics y (down) = -y_tool, x kept: 180 deg about x.
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitX()).toRotationMatrix();
    // The plate's origin seen from the lens: 30 mm above it (-y in optics) and 45 mm behind the
    // lens (-z in optics).
    T.translation() = Eigen::Vector3d(0, -30, -45);
    return T;
}

void register_rig_to_view(TrackedCameraRig& rig, const TrackerSimulator& sim, const Eigen::Isometry3d& T_camera_from_image_rest,
                          std::uint32_t rest_frame) {
    if (!rigid(rig.T_optics_from_tool)) throw std::invalid_argument("sim camera T_optics_from_tool: not a rigid transform");
    if (!rigid(T_camera_from_image_rest)) throw std::invalid_argument("sim camera home pose: not a rigid transform");
    const Eigen::Isometry3d T_tracker_from_tool = tool_pose(sim, rig.camera_part, rest_frame);
    const Eigen::Isometry3d T_tracker_from_reference = tool_pose(sim, rig.reference_part, rest_frame);
    // T_camera_from_image = T_optics_from_tool * T_tool_from_tracker * T_tracker_from_reference * T_reference_from_image
    rig.T_reference_from_image = T_tracker_from_reference.inverse() * T_tracker_from_tool * rig.T_optics_from_tool.inverse() *
                                 T_camera_from_image_rest;
}

Eigen::Isometry3d camera_from_image(const TrackerSimulator& sim, const TrackedCameraRig& rig, std::uint32_t frame) {
    const Eigen::Isometry3d T_tracker_from_tool = tool_pose(sim, rig.camera_part, frame);
    const Eigen::Isometry3d T_tracker_from_reference = tool_pose(sim, rig.reference_part, frame);
    return rig.T_optics_from_tool * T_tracker_from_tool.inverse() * T_tracker_from_reference * rig.T_reference_from_image;
}

std::function<Eigen::Matrix4d()> tracked_camera_pose_source(const TrackerSimulator& sim, const TrackedCameraRig& rig) {
    tool_pose(sim, rig.camera_part, 0);  // both parts present, said now rather than at the first photo
    tool_pose(sim, rig.reference_part, 0);
    if (!rigid(rig.T_optics_from_tool)) throw std::invalid_argument("sim camera T_optics_from_tool: not a rigid transform");
    if (!rigid(rig.T_reference_from_image)) throw std::invalid_argument("sim camera T_reference_from_image: not a rigid transform");
    return [&sim, rig] { return camera_from_image(sim, rig, sim.current_frame()).matrix(); };
}

Eigen::Isometry3d parse_pose7(const std::string& text, const std::string& what) {
    std::istringstream in(text);
    double v[7];
    for (double& x : v)
        if (!(in >> x)) throw std::invalid_argument(what + ": expected 'tx ty tz qw qx qy qz' (mm, unit quaternion), got \"" + text + "\"");
    std::string extra;
    if (in >> extra) throw std::invalid_argument(what + ": more than 7 numbers in \"" + text + "\"");
    for (double x : v)
        if (!std::isfinite(x)) throw std::invalid_argument(what + ": not finite in \"" + text + "\"");
    const Eigen::Quaterniond q(v[3], v[4], v[5], v[6]);
    if (std::abs(q.norm() - 1) > 0.01) throw std::invalid_argument(what + ": the quaternion is not unit length (" + std::to_string(q.norm()) + ")");
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = q.normalized().toRotationMatrix();
    T.translation() = Eigen::Vector3d(v[0], v[1], v[2]);
    return T;
}

}  // namespace cf::sim
