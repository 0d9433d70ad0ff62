#pragma once
// Errors of a recovered pose against ground truth (docs/case-format.md): TRE, MRE (the seed's
// fusion error, cast back onto the brain surface), IPE; and the seed's Table 3.1 protocol.
#include <opencv2/core.hpp>
#include <random>
#include <string>
#include <vector>

#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/rasterizer.hpp"
#include "cortexfuse/core/renderer.hpp"

namespace cf {

struct PoseErrors {
    double tre_mm = 0;   // mean 3D distance of targets mapped by true and recovered pose
    double mre_mm = 0;   // mean distance target -> back-cast hit on the brain surface
    double ipe_px = 0;   // mean image distance of targets projected by both poses
    double ipe_mm = 0;   // the same at each target's depth
    int targets = 0;
    int targets_missed = 0;  // back-cast rays that hit no surface (counted at the ray's closest approach)
    /// Mean of (recovered - true) target positions in the true camera frame: x, y lateral,
    /// z along the view. A bias along z with small x, y is a depth (surface offset) error.
    Eigen::Vector3d offset_camera_mm = Eigen::Vector3d::Zero();
};

/// `surface` renders the brain surface (the registration renderer: first opaque hit = surface).
PoseErrors pose_errors(const Truth& truth, const Intrinsics& K, const Pose& T_recovered, Renderer& surface,
                       double sample_distance_mm = 0.5);

/// The same against the true brain surface mesh (world LPS mm, the one the targets lie on and
/// the photo is texture-mapped onto): MRE casts each true pixel back onto this mesh with the
/// recovered pose, so the true pose scores 0 (the ray-cast surface of `surface` lies a fraction
/// of a millimetre off the mesh, a floor that is not the registration's error).
PoseErrors pose_errors(const Truth& truth, const Intrinsics& K, const Pose& T_recovered, const RasterMesh& surface_world);

/// Where a renderer's surface lies against the true surface mesh, seen from pose T: over the
/// pixels of `mask` (K's size; empty: all) where both are hit, the camera-frame depth of the
/// rendering minus the mesh's (positive: the rendered surface lies behind the true one).
struct SurfaceOffset {
    double median_mm = 0, mean_mm = 0, mad_mm = 0;
    int pixels = 0;
};
SurfaceOffset surface_offset(Renderer& surface, const RenderOptions& options, const RasterMesh& mesh_world,
                             const Intrinsics& K, const Pose& T, const cv::Mat& mask);

/// The first opaque hit along the ray of `pixel` (camera-frame depth), or 0 if none.
double surface_depth_at(Renderer& surface, const Intrinsics& K, const Pose& T, const Eigen::Vector2d& pixel,
                        double sample_distance_mm = 0.5);

/// A random misalignment: each rotation uniform in [-max_deg, max_deg], each translation in
/// [-max_mm, max_mm] (the seed's protocol draws each parameter independently).
PoseParams random_misalignment(std::mt19937_64& rng, double max_mm, double max_deg);

}  // namespace cf
