#pragma once
// Initial alignment from 2D-3D landmark pairs.
#include <string>
#include <vector>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/case.hpp"

namespace cf {

struct LandmarkFit {
    Pose T_camera_from_world = Pose::Identity();
    double rms_px = 0;            // reprojection RMS over all pairs
    std::vector<int> inliers;     // indices used (all, unless RANSAC dropped some)
    std::string method;           // "pnp", "pnp-ransac", "orthographic"
};

/// OpenCV solvePnP (SQPnP, refined by Levenberg-Marquardt); RANSAC from 6 pairs on.
/// Throws InputError when no pose puts the points in front of the camera.
LandmarkFit fit_pose_pnp(const std::vector<Landmark>& lms, const Intrinsics& K);
/// Distinct poses that explain the landmarks about as well as the best one: near-planar
/// cortical landmarks with picking noise leave PnP a mirror ambiguity (the surface tilted one
/// way or the other), which only the image can settle. Best first; each refined by LM. Seeds:
/// EPnP and iterative PnP, the best fit turned 40 deg about four axes, and its planar flip (the
/// landmarks' plane tilted as far the other way about the line of sight, 2x the view's tilt).
/// A fit is kept when its RMS is within 2 x the best's + 2 px + world_sd_mm at the best fit's
/// magnification (f / z px per mm at the landmarks' centroid).
std::vector<LandmarkFit> pnp_candidates(const std::vector<Landmark>& lms, const Intrinsics& K,
                                        double world_sd_mm = 0.0, double min_separation_deg = 5.0);
/// pnp_candidates' limit applied to a best-first list of fits (the best, fits.front(), is kept):
/// the fits of a wider world_sd_mm filtered to a narrower one are that narrower call's own, so
/// one PnP pass serves both.
std::vector<LandmarkFit> landmark_fits_within(std::vector<LandmarkFit> fits, const std::vector<Landmark>& lms,
                                              const Intrinsics& K, double world_sd_mm);
/// The fit Levenberg-Marquardt reaches from `T_start` (OpenCV solvePnPRefineLM): the local fit a
/// given pose lies in. Throws InputError when it leaves the points behind the camera.
LandmarkFit refine_landmark_fit(const std::vector<Landmark>& lms, const Intrinsics& K, const Pose& T_start);
/// Pixels per mm at the landmarks' centroid seen by T (f / z); 0 if it lies behind the camera.
double landmark_px_per_mm(const std::vector<Landmark>& lms, const Intrinsics& K, const Pose& T);
/// The seed's scaled-orthographic variant (affine camera, then orthonormalised), for comparison.
LandmarkFit fit_pose_orthographic(const std::vector<Landmark>& lms, const Intrinsics& K);
double reprojection_rms_px(const std::vector<Landmark>& lms, const Intrinsics& K, const Pose& T);

}  // namespace cf
