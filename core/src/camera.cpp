#include "cortexfuse/core/camera.hpp"

#include <opencv2/calib3d.hpp>
#include <cmath>
#include <string>

#include "cortexfuse/core/error.hpp"

namespace cf {

bool Intrinsics::has_distortion() const {
    for (double d : distortion)
        if (d != 0.0) return true;
    return false;
}

Intrinsics Intrinsics::scaled(double scale) const {
    return resized(std::max(1, int(std::lround(width * scale))), std::max(1, int(std::lround(height * scale))));
}

Intrinsics Intrinsics::resized(int w, int h) const {
    Intrinsics k = *this;
    const double sx = double(w) / width, sy = double(h) / height;
    k.width = w;
    k.height = h;
    k.fx = fx * sx;
    k.fy = fy * sy;
    // Pixel centres: continuous coordinate u maps to (u + 0.5) * s - 0.5.
    k.cx = (cx + 0.5) * sx - 0.5;
    k.cy = (cy + 0.5) * sy - 0.5;
    return k;
}

void Intrinsics::validate(const std::string& context) const {
    auto finite = [](double v) { return std::isfinite(v); };
    if (width < 8 || height < 8 || width > 20000 || height > 20000)
        throw InputError(context, "camera size " + std::to_string(width) + "x" + std::to_string(height) +
                                      " out of range (8..20000)");
    if (!finite(fx) || !finite(fy) || fx <= 0 || fy <= 0) throw InputError(context, "camera fx, fy must be positive numbers");
    if (!finite(cx) || !finite(cy) || cx < -width || cx > 2.0 * width || cy < -height || cy > 2.0 * height)
        throw InputError(context, "camera principal point (cx, cy) is far outside the image");
    for (double d : distortion)
        if (!finite(d) || std::abs(d) > 10) throw InputError(context, "camera distortion coefficients out of range");
}

bool is_rigid(const Eigen::Matrix4d& T, double tol) {
    if (!T.allFinite()) return false;
    if (std::abs(T(3, 0)) > tol || std::abs(T(3, 1)) > tol || std::abs(T(3, 2)) > tol || std::abs(T(3, 3) - 1) > tol)
        return false;
    const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
    return (R.transpose() * R - Eigen::Matrix3d::Identity()).norm() < tol * 10 && std::abs(R.determinant() - 1) < tol * 10;
}

Eigen::Matrix4d orthonormalize(const Eigen::Matrix4d& T) {
    Eigen::JacobiSVD<Eigen::Matrix3d> svd(T.topLeftCorner<3, 3>(), Eigen::ComputeFullU | Eigen::ComputeFullV);
    Eigen::Matrix3d R = svd.matrixU() * svd.matrixV().transpose();
    if (R.determinant() < 0) {
        Eigen::Matrix3d U = svd.matrixU();
        U.col(2) *= -1;
        R = U * svd.matrixV().transpose();
    }
    Eigen::Matrix4d out = Eigen::Matrix4d::Identity();
    out.topLeftCorner<3, 3>() = R;
    out.topRightCorner<3, 1>() = T.topRightCorner<3, 1>();
    return out;
}

std::optional<Eigen::Vector2d> project_camera(const Intrinsics& K, const Eigen::Vector3d& p) {
    if (p.z() <= 1e-9) return std::nullopt;
    double x = p.x() / p.z(), y = p.y() / p.z();
    if (K.has_distortion()) {
        // OpenCV's model (k1, k2, p1, p2, k3), as cv::projectPoints computes it.
        const auto& d = K.distortion;
        const double r2 = x * x + y * y, r4 = r2 * r2, r6 = r4 * r2;
        const double radial = 1 + d[0] * r2 + d[1] * r4 + d[4] * r6;
        const double xd = x * radial + 2 * d[2] * x * y + d[3] * (r2 + 2 * x * x);
        const double yd = y * radial + d[2] * (r2 + 2 * y * y) + 2 * d[3] * x * y;
        x = xd;
        y = yd;
    }
    return Eigen::Vector2d(K.fx * x + K.cx, K.fy * y + K.cy);
}

std::optional<Eigen::Vector2d> project(const Intrinsics& K, const Pose& T, const Eigen::Vector3d& p_world_mm) {
    const Eigen::Vector3d pc = T.topLeftCorner<3, 3>() * p_world_mm + T.topRightCorner<3, 1>();
    return project_camera(K, pc);
}

Eigen::Vector3d backproject_ray(const Intrinsics& K, const Eigen::Vector2d& pixel) {
    if (!K.has_distortion()) return {(pixel.x() - K.cx) / K.fx, (pixel.y() - K.cy) / K.fy, 1.0};
    const cv::Matx33d Kcv(K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1);
    const std::vector<double> dist(K.distortion.begin(), K.distortion.end());
    std::vector<cv::Point2d> in{{pixel.x(), pixel.y()}}, out;
    cv::undistortPoints(in, out, Kcv, dist, cv::noArray(), cv::noArray(),
                        cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 50, 1e-12));
    return {out[0].x, out[0].y, 1.0};
}

Eigen::Vector3d backproject(const Intrinsics& K, const Eigen::Vector2d& pixel, double z_mm) {
    return backproject_ray(K, pixel) * z_mm;
}

std::vector<Eigen::Vector3f> pixel_rays(const Intrinsics& K) {
    std::vector<Eigen::Vector3f> rays(size_t(K.width) * K.height);
    if (!K.has_distortion()) {
        for (int v = 0; v < K.height; ++v)
            for (int u = 0; u < K.width; ++u)
                rays[size_t(v) * K.width + u] = Eigen::Vector3f(float((u - K.cx) / K.fx), float((v - K.cy) / K.fy), 1.f);
        return rays;
    }
    std::vector<cv::Point2d> in(rays.size()), out;
    for (int v = 0; v < K.height; ++v)
        for (int u = 0; u < K.width; ++u) in[size_t(v) * K.width + u] = {double(u), double(v)};
    const cv::Matx33d Kcv(K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1);
    const std::vector<double> dist(K.distortion.begin(), K.distortion.end());
    cv::undistortPoints(in, out, Kcv, dist, cv::noArray(), cv::noArray(),
                        cv::TermCriteria(cv::TermCriteria::COUNT | cv::TermCriteria::EPS, 30, 1e-10));
    for (size_t i = 0; i < rays.size(); ++i) rays[i] = Eigen::Vector3f(float(out[i].x), float(out[i].y), 1.f);
    return rays;
}

}  // namespace cf
