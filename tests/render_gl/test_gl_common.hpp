#pragma once
// Shared fixtures of the GL tests: small synthetic volumes, cameras, image comparisons.
#include <gtest/gtest.h>

#include <string>

#include "cortexfuse/core/renderer.hpp"
#include "cortexfuse/render/gl_renderer.hpp"

namespace cf::test {

/// Empty string when a GL context can be made here, else the reason (for GTEST_SKIP).
const std::string& gl_unavailable();

#define CF_REQUIRE_GL()                                                          \
    do {                                                                         \
        if (!::cf::test::gl_unavailable().empty())                               \
            GTEST_SKIP() << "no OpenGL context: " << ::cf::test::gl_unavailable(); \
    } while (0)

/// A sphere of T1-like intensity (soft edge, some inner texture) in a dims^3 grid with
/// anisotropic spacing and an oblique direction, so the index/world mapping is exercised.
Volume sphere_volume(int dims = 64);
/// Two slabs of different intensity along k (a flat surface and an inner boundary).
Volume slab_volume(int dims = 48);
Intrinsics small_camera(int w = 160, int h = 120, double f = 220);
/// Camera `distance_mm` from `target`, looking along `view_dir` (world), up roughly -z.
Pose look_at(const Eigen::Vector3d& target, const Eigen::Vector3d& view_dir, double distance_mm);

struct ImageDiff {
    double mean_abs_rgb[3] = {0, 0, 0};  // 0..255 units
    double mean_abs_grey = 0;
    double coverage_agreement = 1;       // fraction of pixels with equal coverage
    double mean_abs_depth_mm = 0;        // over pixels covered in both
    double p95_abs_depth_mm = 0;
    size_t covered = 0;                  // pixels covered in both
};
ImageDiff compare(const RenderImage& a, const RenderImage& b);
std::ostream& operator<<(std::ostream& os, const ImageDiff& d);

}  // namespace cf::test
