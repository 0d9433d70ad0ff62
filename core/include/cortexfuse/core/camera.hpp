#pragma once
// Pinhole camera with OpenCV conventions: +x right, +y down, +z into the scene; pixel
// (0,0) is the centre of the top-left pixel. Poses are T_camera_from_world (LPS mm -> camera mm).
#include <Eigen/Geometry>
#include <array>
#include <optional>
#include <vector>

namespace cf {

struct Intrinsics {
    int width = 0, height = 0;
    double fx = 0, fy = 0, cx = 0, cy = 0;
    std::array<double, 5> distortion{0, 0, 0, 0, 0};  // k1, k2, p1, p2, k3 (OpenCV order)

    bool has_distortion() const;
    /// The same camera for an image resized by `scale` (pixel centres kept consistent).
    Intrinsics scaled(double scale) const;
    /// The same camera resized to exactly w x h.
    Intrinsics resized(int w, int h) const;
    /// Throws InputError(context, ...) if not usable.
    void validate(const std::string& context) const;
};

using Pose = Eigen::Matrix4d;  // rigid, T_camera_from_world

/// True if the upper 3x3 is a rotation (orthonormal, det +1) and the last row 0 0 0 1.
bool is_rigid(const Eigen::Matrix4d& T, double tol = 1e-4);
/// Nearest rotation (SVD) for matrices that are rigid up to rounding.
Eigen::Matrix4d orthonormalize(const Eigen::Matrix4d& T);

/// Pixel of a camera-frame point (with distortion). nullopt if behind the camera.
std::optional<Eigen::Vector2d> project_camera(const Intrinsics& K, const Eigen::Vector3d& p_camera_mm);
std::optional<Eigen::Vector2d> project(const Intrinsics& K, const Pose& T_camera_from_world,
                                      const Eigen::Vector3d& p_world_mm);
/// Unit-free normalised ray direction (x, y, 1) in the camera frame for a distorted pixel.
Eigen::Vector3d backproject_ray(const Intrinsics& K, const Eigen::Vector2d& pixel);
/// The camera-frame point at depth z_mm along the ray of `pixel`.
Eigen::Vector3d backproject(const Intrinsics& K, const Eigen::Vector2d& pixel, double z_mm);

/// Per-pixel normalised ray directions (x, y, 1), undistorted, row-major w*h.
/// Computed once per camera and reused by the ray caster.
std::vector<Eigen::Vector3f> pixel_rays(const Intrinsics& K);

}  // namespace cf
