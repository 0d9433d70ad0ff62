#pragma once
// The region of interest: a closed cardinal spline through control points in pixels,
// rasterised to a mask. Tension 0 is the Catmull-Rom spline; tension 1 gives straight lines.
#include <Eigen/Core>
#include <opencv2/core.hpp>
#include <vector>

namespace cf {

struct Roi {
    double tension = 0.0;
    std::vector<Eigen::Vector2d> points;  // pixels
};

/// The closed curve sampled with `samples_per_segment` points between control points.
std::vector<Eigen::Vector2d> cardinal_spline_closed(const Roi& roi, int samples_per_segment = 16);
/// 8-bit mask (255 inside) of size width x height. Coordinates scaled by `scale` first
/// (for a photo that was resized).
cv::Mat roi_mask(const Roi& roi, int width, int height, double scale = 1.0);

}  // namespace cf
