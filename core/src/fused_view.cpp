// Fused views: volume rendering + the photo-textured surface, composited by depth.
#include <algorithm>
#include <cmath>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/overlay.hpp"
#include "cortexfuse/core/rasterizer.hpp"

namespace cf {

Pose orbit_pose(const Pose& T, const Eigen::Vector3d& pivot, double yaw_deg, double pitch_deg) {
    const Eigen::Vector3d pc = T.topLeftCorner<3, 3>() * pivot + T.topRightCorner<3, 1>();
    const Eigen::Matrix3d Rc = (Eigen::AngleAxisd(pitch_deg * M_PI / 180, Eigen::Vector3d::UnitX()) *
                                Eigen::AngleAxisd(yaw_deg * M_PI / 180, Eigen::Vector3d::UnitY()))
                                   .toRotationMatrix();
    // Rotate the scene about the pivot in the camera frame (= orbit the camera the other way).
    Pose M = Pose::Identity();
    M.topLeftCorner<3, 3>() = Rc;
    M.topRightCorner<3, 1>() = pc - Rc * pc;
    return M * T;
}

FusedPasses render_fused_passes(Renderer& volume, const SurfaceMesh& mesh, const Intrinsics& K, const Pose& T,
                                const RenderOptions& options) {
    mesh.validate("mesh");
    K.validate("view camera");
    RenderOptions o = options;
    o.want_rgb = true;
    o.want_depth = true;
    FusedPasses p;
    volume.render(K, T, o, p.volume);
    p.surface = rasterize(mesh.raster(), K, T, 1.0f);
    return p;
}

cv::Mat composite_fused(const FusedPasses& p, const SurfaceMesh& mesh, const TextureMapping& tm, const cv::Mat& tex,
                        double opacity, double depth_slack_mm) {
    if (tm.uv.size() != mesh.vertices.size()) throw InputError("texture mapping", "does not match the mesh");
    if (tex.empty() || tex.type() != CV_8UC4) throw InputError("texture", "must be 8-bit BGRA");
    if (!(opacity >= 0 && opacity <= 1)) throw InputError("opacity", "must be in [0, 1]");
    const RenderImage& img = p.volume;
    const RasterBuffers& rb = p.surface;
    const int W = rb.width, H = rb.height;
    if (img.rgb.size() != size_t(W) * H * 3 || img.depth_mm.size() != size_t(W) * H)
        throw InputError("fused passes", "the volume rendering and the surface buffers differ in size");
    cv::Mat out(H, W, CV_8UC3);
    const int tw = tex.cols, th = tex.rows;
    for (int v = 0; v < H; ++v)
        for (int u = 0; u < W; ++u) {
            const size_t i = size_t(v) * W + u;
            double c[3] = {img.rgb[3 * i + 2] / 255.0, img.rgb[3 * i + 1] / 255.0, img.rgb[3 * i] / 255.0};  // BGR
            const int32_t f = rb.triangle[i];
            if (f >= 0) {
                const auto& tri = mesh.triangles[size_t(f)];
                if (tm.in_roi[size_t(tri[0])] && tm.in_roi[size_t(tri[1])] && tm.in_roi[size_t(tri[2])]) {
                    const float vol_depth = img.depth_mm[i];
                    const bool in_front = !(vol_depth > 0) || rb.depth_mm[i] <= vol_depth + float(depth_slack_mm);
                    if (in_front) {
                        const Eigen::Vector3f& b = rb.bary[i];
                        const Eigen::Vector2f uv = tm.uv[size_t(tri[0])] * b[0] + tm.uv[size_t(tri[1])] * b[1] + tm.uv[size_t(tri[2])] * b[2];
                        // Bilinear sample of the texture at pixel coordinates (u*w - 0.5).
                        const double x = std::clamp(double(uv.x()) * tw - 0.5, 0.0, double(tw - 1));
                        const double y = std::clamp(double(uv.y()) * th - 0.5, 0.0, double(th - 1));
                        const int x0 = std::min(int(x), tw - 2 < 0 ? 0 : tw - 2), y0 = std::min(int(y), th - 2 < 0 ? 0 : th - 2);
                        const int x1 = std::min(x0 + 1, tw - 1), y1 = std::min(y0 + 1, th - 1);
                        const double fx = x - x0, fy = y - y0;
                        double s[4];
                        for (int ch = 0; ch < 4; ++ch) {
                            const double a00 = tex.at<cv::Vec4b>(y0, x0)[ch], a10 = tex.at<cv::Vec4b>(y0, x1)[ch];
                            const double a01 = tex.at<cv::Vec4b>(y1, x0)[ch], a11 = tex.at<cv::Vec4b>(y1, x1)[ch];
                            s[ch] = ((a00 * (1 - fx) + a10 * fx) * (1 - fy) + (a01 * (1 - fx) + a11 * fx) * fy) / 255.0;
                        }
                        const double a = opacity * s[3];
                        for (int ch = 0; ch < 3; ++ch) c[ch] = a * s[ch] + (1 - a) * c[ch];
                    }
                }
            }
            out.at<cv::Vec3b>(v, u) = cv::Vec3b(cv::saturate_cast<uchar>(c[0] * 255), cv::saturate_cast<uchar>(c[1] * 255),
                                                 cv::saturate_cast<uchar>(c[2] * 255));
        }
    return out;
}

cv::Mat render_fused(Renderer& volume, const SurfaceMesh& mesh, const TextureMapping& tm, const cv::Mat& tex,
                     const Intrinsics& K, const Pose& T, double opacity, double depth_slack_mm, const RenderOptions& options) {
    // The inputs of the blend checked before the (costly) passes, as before the split.
    if (tm.uv.size() != mesh.vertices.size()) throw InputError("texture mapping", "does not match the mesh");
    if (tex.empty() || tex.type() != CV_8UC4) throw InputError("texture", "must be 8-bit BGRA");
    if (!(opacity >= 0 && opacity <= 1)) throw InputError("opacity", "must be in [0, 1]");
    return composite_fused(render_fused_passes(volume, mesh, K, T, options), mesh, tm, tex, opacity, depth_slack_mm);
}

}  // namespace cf
