#include "test_gl_common.hpp"

#include <algorithm>
#include <cmath>
#include <ostream>
#include <random>

namespace cf::test {

const std::string& gl_unavailable() {
    static const std::string why = [] {
        try {
            probe_gl();
            return std::string();
        } catch (const std::exception& e) {
            return std::string(e.what());
        }
    }();
    return why;
}

namespace {
VolumeGeometry oblique_grid(int dims) {
    VolumeGeometry g;
    g.dims = {dims, dims + 4, dims - 4};
    g.spacing_mm = Eigen::Vector3d(1.1, 0.9, 1.3);
    g.origin_mm = Eigen::Vector3d(-30, -25, -35);
    g.direction = Eigen::AngleAxisd(0.3, Eigen::Vector3d(0.2, 1, 0.4).normalized()).toRotationMatrix();
    return g;
}
}  // namespace

Volume sphere_volume(int dims) {
    Volume v;
    v.geom = oblique_grid(dims);
    v.voxels.resize(v.geom.voxel_count());
    const Eigen::Vector3d c = v.geom.center_world_mm();
    std::mt19937 rng(7);
    std::uniform_real_distribution<float> noise(-40.f, 40.f);
    const auto A = v.geom.world_from_index();
    for (int k = 0; k < v.geom.dims[2]; ++k)
        for (int j = 0; j < v.geom.dims[1]; ++j)
            for (int i = 0; i < v.geom.dims[0]; ++i) {
                const Eigen::Vector3d p = A * Eigen::Vector3d(i, j, k);
                const double r = (p - c).norm();
                // Soft edge at 22 mm, a darker core (an inner boundary), gyri-like ripples.
                const double ripple = 2.0 * std::sin(p.x() * 0.35) * std::sin(p.y() * 0.3);
                double val = 1000.0 / (1.0 + std::exp((r - 22.0 - ripple) / 1.2));
                if (r < 10) val *= 0.6;
                v.voxels[v.geom.linear(i, j, k)] = float(val) + (val > 50 ? noise(rng) : 0.f);
            }
    return v;
}

Volume slab_volume(int dims) {
    Volume v;
    v.geom.dims = {dims, dims, dims};
    v.geom.spacing_mm = Eigen::Vector3d(1.0, 1.0, 1.5);
    v.geom.origin_mm = Eigen::Vector3d(-24, -24, -36);
    v.voxels.resize(v.geom.voxel_count());
    for (int k = 0; k < dims; ++k)
        for (int j = 0; j < dims; ++j)
            for (int i = 0; i < dims; ++i) {
                float val = 0;
                if (k > dims / 3) val = 600;
                if (k > dims / 2 + (i - dims / 2) / 6) val = 1000;
                if (i < 3 || j < 3 || i > dims - 4 || j > dims - 4) val = 0;
                v.voxels[v.geom.linear(i, j, k)] = val;
            }
    return v;
}

Intrinsics small_camera(int w, int h, double f) {
    Intrinsics K;
    K.width = w;
    K.height = h;
    K.fx = K.fy = f;
    K.cx = (w - 1) * 0.5;
    K.cy = (h - 1) * 0.5;
    return K;
}

Pose look_at(const Eigen::Vector3d& target, const Eigen::Vector3d& view_dir, double distance_mm) {
    const Eigen::Vector3d z = view_dir.normalized();
    Eigen::Vector3d up(0, 0, -1);
    if (std::abs(z.dot(up)) > 0.9) up = Eigen::Vector3d(0, -1, 0);
    const Eigen::Vector3d x = up.cross(z).normalized();  // OpenCV: y down = -up
    const Eigen::Vector3d y = z.cross(x);
    Eigen::Matrix3d R_world_from_camera;
    R_world_from_camera << x, y, z;
    const Eigen::Vector3d cam = target - distance_mm * z;
    Pose T = Pose::Identity();
    T.topLeftCorner<3, 3>() = R_world_from_camera.transpose();
    T.topRightCorner<3, 1>() = -R_world_from_camera.transpose() * cam;
    return T;
}

ImageDiff compare(const RenderImage& a, const RenderImage& b) {
    ImageDiff d;
    const size_t n = size_t(a.width) * a.height;
    EXPECT_EQ(a.width, b.width);
    EXPECT_EQ(a.height, b.height);
    if (a.grey.size() != n || b.grey.size() != n) return d;
    if (a.rgb.size() == 3 * n && b.rgb.size() == 3 * n)
        for (size_t i = 0; i < n; ++i)
            for (int c = 0; c < 3; ++c) d.mean_abs_rgb[c] += std::abs(int(a.rgb[3 * i + c]) - int(b.rgb[3 * i + c]));
    size_t same_cov = 0;
    std::vector<double> dz;
    for (size_t i = 0; i < n; ++i) {
        d.mean_abs_grey += std::abs(a.grey[i] - b.grey[i]);
        same_cov += a.coverage[i] == b.coverage[i];
        if (a.coverage[i] && b.coverage[i] && !a.depth_mm.empty() && !b.depth_mm.empty())
            dz.push_back(std::abs(double(a.depth_mm[i]) - b.depth_mm[i]));
    }
    for (double& m : d.mean_abs_rgb) m /= double(n);
    d.mean_abs_grey /= double(n);
    d.coverage_agreement = double(same_cov) / double(n);
    d.covered = dz.size();
    if (!dz.empty()) {
        for (double z : dz) d.mean_abs_depth_mm += z;
        d.mean_abs_depth_mm /= double(dz.size());
        std::nth_element(dz.begin(), dz.begin() + long(dz.size() * 95 / 100), dz.end());
        d.p95_abs_depth_mm = dz[dz.size() * 95 / 100];
    }
    return d;
}

std::ostream& operator<<(std::ostream& os, const ImageDiff& d) {
    return os << "rgb " << d.mean_abs_rgb[0] << "/" << d.mean_abs_rgb[1] << "/" << d.mean_abs_rgb[2] << " (255 units), grey "
              << d.mean_abs_grey << ", coverage agreement " << d.coverage_agreement << ", depth mean " << d.mean_abs_depth_mm
              << " mm p95 " << d.p95_abs_depth_mm << " mm over " << d.covered << " px";
}

}  // namespace cf::test
