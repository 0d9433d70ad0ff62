#pragma once
// A small software z-buffer triangle rasteriser.
//
// Why hand-written and not VTK: Debian's VTK 9.1 is built against X only (no OSMesa/EGL
// offscreen path), so vtkRenderWindow cannot render on a headless cart or in CI; and the
// phantom generator needs per-pixel geometry buffers (depth, triangle id, barycentrics),
// not a shaded image. A scanline-free edge-function rasteriser is ~100 lines and fast enough
// (a 400k-triangle brain mesh at 1500x1000 in well under a second).
//
// Pixels follow OpenCV: pixel (u, v) covers the square centred on integer (u, v).
#include <Eigen/Core>
#include <cstdint>
#include <limits>
#include <type_traits>
#include <vector>

#include "cortexfuse/core/camera.hpp"

namespace cf {

/// A triangle mesh: vertices (any frame) and index triples.
struct RasterMesh {
    std::vector<Eigen::Vector3f> vertices;
    std::vector<Eigen::Vector3i> triangles;
};

/// Geometry buffers, row-major width*height.
struct RasterBuffers {
    int width = 0, height = 0;
    /// Camera-frame depth (z, mm) of the nearest surface; +inf where nothing was hit.
    std::vector<float> depth_mm;
    /// Index of the visible triangle, -1 where nothing was hit.
    std::vector<int32_t> triangle;
    /// Barycentric weights of the visible point on its triangle (perspective-correct, sum 1).
    std::vector<Eigen::Vector3f> bary;

    bool hit(int u, int v) const { return triangle[size_t(v) * width + u] >= 0; }
    size_t index(int u, int v) const { return size_t(v) * width + u; }
};

/// Rasterises triangles given in screen space: (u, v) pixels and z = depth used for the
/// z-test (smaller is nearer; must be > 0 when `perspective` is true). With `perspective`,
/// barycentrics are corrected for perspective (interpolated as b_i / z_i); otherwise they
/// are affine (an orthographic view). Triangles with a non-positive or non-finite z are skipped.
RasterBuffers rasterize_screen(const std::vector<Eigen::Vector3f>& screen_uvz,
                               const std::vector<Eigen::Vector3i>& triangles, int width, int height,
                               bool perspective);

/// Rasterises a world-space mesh seen by a pinhole camera (lens distortion applied to the
/// vertices; edges stay straight in the distorted image, which is exact enough for
/// triangles a few pixels wide). Triangles with a vertex closer than `near_mm` are skipped.
RasterBuffers rasterize(const RasterMesh& mesh_world, const Intrinsics& K, const Pose& T_camera_from_world,
                        float near_mm = 1.0f);

/// The visible point of pixel (u, v) interpolated from per-vertex values; `fallback` where
/// nothing was hit.
template <class T>
T interpolate_at(const RasterBuffers& rb, const std::vector<Eigen::Vector3i>& triangles,
                 const std::vector<T>& per_vertex, int u, int v, const std::type_identity_t<T>& fallback) {
    const size_t i = rb.index(u, v);
    const int32_t t = rb.triangle[i];
    if (t < 0) return fallback;
    const Eigen::Vector3i& tri = triangles[size_t(t)];
    const Eigen::Vector3f& b = rb.bary[i];
    return per_vertex[size_t(tri[0])] * b[0] + per_vertex[size_t(tri[1])] * b[1] + per_vertex[size_t(tri[2])] * b[2];
}

}  // namespace cf
