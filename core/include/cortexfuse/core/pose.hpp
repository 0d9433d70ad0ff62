#pragma once
// Pose parameterisation for optimisation: six numbers (rx, ry, rz in degrees, tx, ty, tz
// in mm) applied as a small rigid motion about a pivot given in the camera frame, so that
// rotations turn the scene about the target region, not about the camera centre.
#include <Eigen/Geometry>
#include <array>

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
struct PoseDelta {
    double angle_deg = 0;
    double translation_mm = 0;
};
PoseDelta pose_delta(const Pose& a, const Pose& b, const Eigen::Vector3d& pivot_world_mm);

}  // namespace cf
