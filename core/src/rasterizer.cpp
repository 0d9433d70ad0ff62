// Software z-buffer rasteriser (see rasterizer.hpp for why it is hand-written).
#include "cortexfuse/core/rasterizer.hpp"

#include <algorithm>
#include <cmath>

namespace cf {

RasterBuffers rasterize_screen(const std::vector<Eigen::Vector3f>& uvz, const std::vector<Eigen::Vector3i>& triangles,
                               int width, int height, bool perspective) {
    RasterBuffers rb;
    rb.width = width;
    rb.height = height;
    const size_t n = size_t(width) * size_t(height);
    rb.depth_mm.assign(n, std::numeric_limits<float>::infinity());
    rb.triangle.assign(n, -1);
    rb.bary.assign(n, Eigen::Vector3f::Zero());

    for (size_t t = 0; t < triangles.size(); ++t) {
        const Eigen::Vector3i& tri = triangles[t];
        const Eigen::Vector3f& a = uvz[size_t(tri[0])];
        const Eigen::Vector3f& b = uvz[size_t(tri[1])];
        const Eigen::Vector3f& c = uvz[size_t(tri[2])];
        if (!a.allFinite() || !b.allFinite() || !c.allFinite()) continue;
        if (perspective && (a.z() <= 0 || b.z() <= 0 || c.z() <= 0)) continue;
        // Signed doubled area; either winding is accepted (no back-face culling).
        const float area = (b.x() - a.x()) * (c.y() - a.y()) - (b.y() - a.y()) * (c.x() - a.x());
        if (std::abs(area) < 1e-12f) continue;
        const float inv_area = 1.0f / area;
        const int u0 = std::max(0, int(std::ceil(std::min({a.x(), b.x(), c.x()}))));
        const int u1 = std::min(width - 1, int(std::floor(std::max({a.x(), b.x(), c.x()}))));
        const int v0 = std::max(0, int(std::ceil(std::min({a.y(), b.y(), c.y()}))));
        const int v1 = std::min(height - 1, int(std::floor(std::max({a.y(), b.y(), c.y()}))));
        if (u0 > u1 || v0 > v1) continue;
        const float iza = perspective ? 1.0f / a.z() : 0.f, izb = perspective ? 1.0f / b.z() : 0.f,
                    izc = perspective ? 1.0f / c.z() : 0.f;
        for (int v = v0; v <= v1; ++v) {
            const float py = float(v);
            for (int u = u0; u <= u1; ++u) {
                const float px = float(u);
                // Screen-space barycentrics from edge functions.
                float w0 = ((b.x() - px) * (c.y() - py) - (b.y() - py) * (c.x() - px)) * inv_area;
                float w1 = ((c.x() - px) * (a.y() - py) - (c.y() - py) * (a.x() - px)) * inv_area;
                float w2 = 1.0f - w0 - w1;
                // Small tolerance so that shared edges leave no cracks.
                constexpr float eps = -1e-5f;
                if (w0 < eps || w1 < eps || w2 < eps) continue;
                float z;
                if (perspective) {
                    const float iz = w0 * iza + w1 * izb + w2 * izc;
                    z = 1.0f / iz;
                    w0 = w0 * iza * z;
                    w1 = w1 * izb * z;
                    w2 = 1.0f - w0 - w1;
                } else {
                    z = w0 * a.z() + w1 * b.z() + w2 * c.z();
                }
                const size_t i = size_t(v) * width + u;
                if (z < rb.depth_mm[i]) {
                    rb.depth_mm[i] = z;
                    rb.triangle[i] = int32_t(t);
                    rb.bary[i] = Eigen::Vector3f(w0, w1, w2);
                }
            }
        }
    }
    return rb;
}

RasterBuffers rasterize(const RasterMesh& mesh, const Intrinsics& K, const Pose& T, float near_mm) {
    const Eigen::Matrix3f R = T.topLeftCorner<3, 3>().cast<float>();
    const Eigen::Vector3f t = T.topRightCorner<3, 1>().cast<float>();
    const bool dist = K.has_distortion();
    const auto& d = K.distortion;
    std::vector<Eigen::Vector3f> uvz(mesh.vertices.size());
    const float nan = std::numeric_limits<float>::quiet_NaN();
    for (size_t i = 0; i < mesh.vertices.size(); ++i) {
        const Eigen::Vector3f pc = R * mesh.vertices[i] + t;
        if (pc.z() < near_mm) {
            uvz[i] = Eigen::Vector3f(nan, nan, nan);
            continue;
        }
        double x = double(pc.x()) / pc.z(), y = double(pc.y()) / pc.z();
        if (dist) {  // OpenCV's model, as in project_camera().
            const double r2 = x * x + y * y, r4 = r2 * r2, r6 = r4 * r2;
            const double radial = 1 + d[0] * r2 + d[1] * r4 + d[4] * r6;
            const double xd = x * radial + 2 * d[2] * x * y + d[3] * (r2 + 2 * x * x);
            const double yd = y * radial + d[2] * (r2 + 2 * y * y) + 2 * d[3] * x * y;
            x = xd;
            y = yd;
        }
        uvz[i] = Eigen::Vector3f(float(K.fx * x + K.cx), float(K.fy * y + K.cy), pc.z());
    }
    return rasterize_screen(uvz, mesh.triangles, K.width, K.height, true);
}

}  // namespace cf
