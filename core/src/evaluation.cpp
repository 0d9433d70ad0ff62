#include "cortexfuse/core/evaluation.hpp"

#include <cmath>
#include <functional>
#include <numeric>

#include "cortexfuse/core/rasterizer.hpp"

namespace cf {

double surface_depth_at(Renderer& surface, const Intrinsics& K, const Pose& T, const Eigen::Vector2d& pixel,
                        double sample_distance_mm) {
    // A one-pixel camera whose pixel (0,0) is `pixel` of K: shifting the principal point keeps
    // the normalised coordinates, so distortion is honoured too.
    Intrinsics k1 = K;
    k1.width = k1.height = 1;
    k1.cx = K.cx - pixel.x();
    k1.cy = K.cy - pixel.y();
    RenderOptions o;
    o.sample_distance_mm = sample_distance_mm;
    o.want_rgb = false;
    o.shading = false;
    o.threads = 1;
    RenderImage img;
    surface.render(k1, T, o, img);
    return img.coverage[0] ? double(img.depth_mm[0]) : 0.0;
}

namespace {
/// The errors with `depth_at(pixel)` giving the camera-frame depth of the surface seen at a
/// pixel of K with the recovered pose (0 where none).
PoseErrors pose_errors_with(const Truth& truth, const Intrinsics& K, const Pose& Tr,
                            const std::function<double(const Eigen::Vector2d&)>& depth_at) {
    PoseErrors e;
    const Pose& Tt = truth.T_camera_from_world;
    double tre = 0, mre = 0, ipe = 0, ipe_mm = 0;
    int n = 0;
    for (const auto& p : truth.targets_world_mm) {
        const Eigen::Vector3d pt = Tt.topLeftCorner<3, 3>() * p + Tt.topRightCorner<3, 1>();
        const Eigen::Vector3d pr = Tr.topLeftCorner<3, 3>() * p + Tr.topRightCorner<3, 1>();
        const auto ut = project_camera(K, pt), ur = project_camera(K, pr);
        if (!ut) continue;
        ++n;
        tre += (pt - pr).norm();
        e.offset_camera_mm += pr - pt;
        const double dpx = ur ? (*ut - *ur).norm() : 1e3;
        ipe += dpx;
        ipe_mm += dpx * pt.z() / K.fx;
        // MRE: the true pixel cast back with the recovered pose onto the surface.
        const Eigen::Vector3d ray = backproject_ray(K, *ut);
        const double z = depth_at(*ut);
        Eigen::Vector3d hit_cam;
        if (z > 0) {
            hit_cam = ray * z;
        } else {
            // No surface there: take the ray's closest point to the target (a lower bound).
            ++e.targets_missed;
            const Eigen::Vector3d d = ray.normalized();
            hit_cam = d * d.dot(pr);
        }
        const Eigen::Matrix4d Tr_inv = Tr.inverse();
        const Eigen::Vector3d hit_world = Tr_inv.topLeftCorner<3, 3>() * hit_cam + Tr_inv.topRightCorner<3, 1>();
        mre += (hit_world - p).norm();
    }
    e.targets = n;
    if (n) {
        e.tre_mm = tre / n;
        e.mre_mm = mre / n;
        e.ipe_px = ipe / n;
        e.ipe_mm = ipe_mm / n;
        e.offset_camera_mm /= double(n);
    }
    return e;
}

}  // namespace

SurfaceOffset surface_offset(Renderer& surface, const RenderOptions& options, const RasterMesh& mesh_world,
                             const Intrinsics& K, const Pose& T, const cv::Mat& mask) {
    RenderOptions o = options;
    o.want_depth = true;
    RenderImage img;
    surface.render(K, T, o, img);
    const RasterBuffers rb = rasterize(mesh_world, K, T);
    std::vector<double> d;
    for (int v = 0; v < K.height; ++v)
        for (int u = 0; u < K.width; ++u) {
            if (!mask.empty() && !mask.at<uint8_t>(v, u)) continue;
            const size_t i = size_t(v) * K.width + u;
            if (!img.coverage[i] || !rb.hit(u, v)) continue;
            d.push_back(double(img.depth_mm[i]) - rb.depth_mm[rb.index(u, v)]);
        }
    SurfaceOffset s;
    s.pixels = int(d.size());
    if (d.empty()) return s;
    s.mean_mm = std::accumulate(d.begin(), d.end(), 0.0) / double(d.size());
    auto median = [](std::vector<double> a) {
        std::nth_element(a.begin(), a.begin() + long(a.size() / 2), a.end());
        return a[a.size() / 2];
    };
    s.median_mm = median(d);
    for (auto& x : d) x = std::abs(x - s.median_mm);
    s.mad_mm = median(d);
    return s;
}

PoseErrors pose_errors(const Truth& truth, const Intrinsics& K, const Pose& Tr, Renderer& surface, double sample_mm) {
    return pose_errors_with(truth, K, Tr, [&](const Eigen::Vector2d& px) { return surface_depth_at(surface, K, Tr, px, sample_mm); });
}

PoseErrors pose_errors(const Truth& truth, const Intrinsics& K, const Pose& Tr, const RasterMesh& surface_world) {
    // Depth buffer of the mesh at the recovered pose, at most ~1000 px wide (bilinear depth
    // between pixel centres keeps the cast-back sub-pixel).
    const double scale = std::min(1.0, 1000.0 / K.width);
    const Intrinsics Ks = scale < 1 ? K.scaled(scale) : K;
    const RasterBuffers rb = rasterize(surface_world, Ks, Tr);
    return pose_errors_with(truth, K, Tr, [&](const Eigen::Vector2d& px_full) {
        const Eigen::Vector2d px = scale < 1 ? Eigen::Vector2d((px_full.x() + 0.5) * Ks.width / K.width - 0.5,
                                                               (px_full.y() + 0.5) * Ks.height / K.height - 0.5)
                                             : px_full;
        const int u0 = int(std::floor(px.x())), v0 = int(std::floor(px.y()));
        const double fu = px.x() - u0, fv = px.y() - v0;
        double z = 0, wsum = 0, z_near = 0, w_near = -1;
        for (int dv = 0; dv <= 1; ++dv)
            for (int du = 0; du <= 1; ++du) {
                const int u = u0 + du, v = v0 + dv;
                if (u < 0 || v < 0 || u >= rb.width || v >= rb.height || !rb.hit(u, v)) continue;
                const double w = (du ? fu : 1 - fu) * (dv ? fv : 1 - fv);
                const double d = rb.depth_mm[rb.index(u, v)];
                z += w * d;
                wsum += w;
                if (w > w_near) w_near = w, z_near = d;
            }
        if (wsum <= 0) return 0.0;
        // Across a depth edge (a sulcus wall, the surface's rim) interpolation would invent a
        // point in between: take the nearest pixel's surface there.
        return wsum > 0.999 ? z / wsum : z_near;
    });
}

PoseParams random_misalignment(std::mt19937_64& rng, double max_mm, double max_deg) {
    std::uniform_real_distribution<double> U(-1.0, 1.0);
    PoseParams x;
    for (int i = 0; i < 3; ++i) x[size_t(i)] = U(rng) * max_deg;
    for (int i = 3; i < 6; ++i) x[size_t(i)] = U(rng) * max_mm;
    return x;
}

}  // namespace cf
