#include "cortexfuse/core/roi.hpp"

#include <opencv2/imgproc.hpp>

namespace cf {

std::vector<Eigen::Vector2d> cardinal_spline_closed(const Roi& roi, int samples) {
    const auto& p = roi.points;
    const size_t n = p.size();
    std::vector<Eigen::Vector2d> out;
    if (n < 3) return out;
    const double s = (1.0 - roi.tension) * 0.5;
    out.reserve(n * size_t(samples));
    for (size_t i = 0; i < n; ++i) {
        const Eigen::Vector2d& p0 = p[(i + n - 1) % n];
        const Eigen::Vector2d& p1 = p[i];
        const Eigen::Vector2d& p2 = p[(i + 1) % n];
        const Eigen::Vector2d& p3 = p[(i + 2) % n];
        const Eigen::Vector2d m1 = s * (p2 - p0), m2 = s * (p3 - p1);
        for (int k = 0; k < samples; ++k) {
            const double t = double(k) / samples, t2 = t * t, t3 = t2 * t;
            // Cubic Hermite basis.
            out.push_back((2 * t3 - 3 * t2 + 1) * p1 + (t3 - 2 * t2 + t) * m1 + (-2 * t3 + 3 * t2) * p2 + (t3 - t2) * m2);
        }
    }
    return out;
}

cv::Mat roi_mask(const Roi& roi, int width, int height, double scale) {
    cv::Mat mask(height, width, CV_8U, cv::Scalar(0));
    const auto curve = cardinal_spline_closed(roi, 24);
    if (curve.empty()) return mask;
    // fillPoly with sub-pixel precision (4 fractional bits); pixel centres at integers.
    constexpr int kShift = 4;
    std::vector<cv::Point> poly;
    poly.reserve(curve.size());
    for (const auto& q : curve) {
        const double u = (q.x() + 0.5) * scale - 0.5, v = (q.y() + 0.5) * scale - 0.5;
        poly.emplace_back(int(std::lround(u * (1 << kShift))), int(std::lround(v * (1 << kShift))));
    }
    cv::fillPoly(mask, std::vector<std::vector<cv::Point>>{poly}, cv::Scalar(255), cv::LINE_8, kShift);
    return mask;
}

}  // namespace cf
