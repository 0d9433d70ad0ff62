#pragma once
// Pose parameterisation for optimisation: six numbers (rx, ry, rz in degrees, tx, ty, tz
// in mm) applied as a small rigid motion about a pivot given in the camera frame, so that
// rotations turn the scene about the target region, not about the camera centre.
#include <Eigen/Geometry>
#include <array>
#include <string>

#include "cortexfuse/core/camera.hpp"

namespace cf {

using PoseParams = std::array<double, 6>;  // rx_deg, ry_deg, rz_deg, tx_mm, ty_mm, tz_mm

/// R = Rx * Ry * Rz (the seed's order), angles in degrees.
Eigen::Matrix3d rotation_xyz_deg(double rx_deg, double ry_deg, double rz_deg);
/// Inverse of rotation_xyz_deg.
std::array<double, 3> euler_xyz_deg(const Eigen::Matrix3d& R);

/// T = Trans(t) * Trans(pivot) * R(r) * Trans(-pivot) * T0 (all in the camera frame).
Pose apply_params(const Pose& T0, const Eigen::Vector3d& pivot_camera_mm, const PoseParams& x);
/// The params that take T0 to T about pivot (inverse of apply_params).
PoseParams params_between(const Pose& T0, const Pose& T, const Eigen::Vector3d& pivot_camera_mm);

/// Rotation angle in degrees and translation in mm of the relative motion T1^-1 * T0 ... as
/// seen in the camera frame about a pivot.
/// A camera at `eye_world_mm` looking at `target_world_mm`, image up towards `up_world`.
Pose look_at(const Eigen::Vector3d& eye_world_mm, const Eigen::Vector3d& target_world_mm, const Eigen::Vector3d& up_world);
/// Named views around a point: "left", "right", "anterior", "posterior", "superior",
/// "inferior" (the side of the patient the camera is on), at `distance_mm`.
Pose standard_view(const std::string& side, const Eigen::Vector3d& target_world_mm, double distance_mm);

struct PoseDelta {
    double angle_deg = 0;
    double translation_mm = 0;
};
PoseDelta pose_delta(const Pose& a, const Pose& b, const Eigen::Vector3d& pivot_world_mm);

}  // namespace cf
