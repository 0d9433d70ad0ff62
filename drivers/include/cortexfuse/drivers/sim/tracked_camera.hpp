#pragma once
// The simulated operating room's tracked camera: connects the tracker simulator's CF-CAMERA
// tool to the simulated camera (cf::camera::SimCameraConfig::pose_source /
// SimCamera::set_pose_source), so that every photo is taken from where the tracker simulator
// says the camera tool is.
//
// Frames (docs/camera.md, "On the tracker simulator's camera tool"):
//   image    the MRI's world (LPS mm), the phantom scene's world (T_camera_from_world's "world")
//   tracker  the tracker simulator's frame (mm)
//   tool     the camera tool's marker frame (CF-CAMERA), reference the head clamp's (CF-REFERENCE)
//   optics   the camera's optical frame (OpenCV: x right, y down, z along the view, mm)
//
//   T_camera_from_image = T_optics_from_tool * inverse(T_tracker_from_tool) * T_tracker_from_reference
//                         * T_reference_from_image
//
// T_optics_from_tool is the hand-eye calibration of the camera (its marker plate to its lens),
// T_reference_from_image the patient registration; both are fixed parts of the simulated scene.
// The tool poses are the simulator's noiseless truth for the current frame: the photo is taken
// from where the camera really is; the tracker's report of that pose carries the measurement
// noise (TrackerSimConfig::noise_mm / noise_deg).
//
// Thread contract: the pose source may be called from any thread (TrackerSimulator::truth and
// current_frame are); the simulator must outlive it.
#include <Eigen/Geometry>

#include <cstdint>
#include <functional>
#include <string>

#include "cortexfuse/drivers/sim/tracker_sim.hpp"

namespace cf::sim {

/// A camera with its marker plate on top: the plate's z axis points up, away from the view
/// (the optics look along -z_tool), the lens 45 mm in front of and 30 mm below the plate's origin.
Eigen::Isometry3d default_T_optics_from_tool();

struct TrackedCameraRig {
    std::string camera_part = "CF-CAMERA";        ///< the tracked camera's tool (part name)
    std::string reference_part = "CF-REFERENCE";  ///< the patient reference on the head clamp
    Eigen::Isometry3d T_optics_from_tool = default_T_optics_from_tool();  ///< hand-eye, mm
    Eigen::Isometry3d T_reference_from_image = Eigen::Isometry3d::Identity();  ///< patient registration, mm
};

/// Chooses the rig's patient registration (T_reference_from_image) so that the camera tool at its
/// scripted rest pose (its noiseless pose at frame `rest_frame` without holds: frame 0 is the
/// middle of the simulator's slow sway) sees the image from `T_camera_from_image_rest` (the
/// simulated camera's home framing, SimCamera::home_pose()). Throws std::invalid_argument naming a
/// part absent from the simulator's scene or a T_optics_from_tool that is not rigid.
void register_rig_to_view(TrackedCameraRig& rig, const TrackerSimulator& sim, const Eigen::Isometry3d& T_camera_from_image_rest,
                          std::uint32_t rest_frame = 0);

/// T_camera_from_image with the tool poses the simulator has at `frame` (noiseless truth).
/// Throws std::invalid_argument naming a part absent from the scene.
Eigen::Isometry3d camera_from_image(const TrackerSimulator& sim, const TrackedCameraRig& rig, std::uint32_t frame);

/// A pose source for the simulated camera: camera_from_image at the simulator's current frame
/// (started simulator), as a 4x4 T_camera_from_world (world = image). Checks at once (not at the
/// first photo) that both parts are in the scene: std::invalid_argument otherwise, e.g.
/// "sim camera pose: the tracker simulator's scene has no 'CF-CAMERA' tool (start it with the camera tool)".
std::function<Eigen::Matrix4d()> tracked_camera_pose_source(const TrackerSimulator& sim, const TrackedCameraRig& rig);

/// Parses "tx ty tz qw qx qy qz" (mm, unit quaternion; the trajectory file's pose format) into a
/// rigid transform. Throws std::invalid_argument naming `what` and the problem.
Eigen::Isometry3d parse_pose7(const std::string& text, const std::string& what);

}  // namespace cf::sim
