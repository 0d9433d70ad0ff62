// The CPU ray caster's distant light (RenderOptions::light, Light::distant), which registration
// uses to match a photo lit from aside: along the lens axis it looks like the headlight, from
// the camera's +x side it brightens the sphere's +x half.
#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <memory>

#include "cortexfuse/core/renderer.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "cortexfuse/core/volume.hpp"

using namespace cf;

namespace {

Volume ball() {
    Volume v;
    v.geom.dims = {64, 64, 64};
    v.voxels.resize(v.geom.voxel_count());
    const Eigen::Vector3d c = v.geom.center_world_mm();
    for (int k = 0; k < 64; ++k)
        for (int j = 0; j < 64; ++j)
            for (int i = 0; i < 64; ++i) {
                const double r = (v.geom.world_from_index(Eigen::Vector3d(i, j, k)) - c).norm();
                // A soft edge at 22 mm: bright inside, dark outside (a T1-like brain surface).
                v.voxels[v.geom.linear(i, j, k)] = float(100.0 / (1.0 + std::exp((r - 22.0) / 1.0)));
            }
    return v;
}

Intrinsics camera() {
    Intrinsics K;
    K.width = 96;
    K.height = 96;
    K.fx = K.fy = 300;
    K.cx = K.cy = 47.5;
    return K;
}

/// Camera 200 mm in front of the ball's centre along world +z, looking at it.
Pose facing(const Eigen::Vector3d& c) {
    Pose T = Pose::Identity();
    T.topRightCorner<3, 1>() = -c + Eigen::Vector3d(0, 0, 200);
    return T;
}

double mean_grey(const RenderImage& im, bool left_half) {
    double s = 0;
    int n = 0;
    for (int v = 0; v < im.height; ++v)
        for (int u = 0; u < im.width; ++u) {
            const size_t i = size_t(v) * im.width + u;
            if (!im.coverage[i] || (u < im.width / 2) != left_half) continue;
            s += im.grey[i];
            ++n;
        }
    return n ? s / n : 0.0;
}

/// The ball before the camera (renderer, camera, pose), pictured grey under one light at a time.
struct BallScene {
    Volume v = ball();
    std::unique_ptr<Renderer> r = make_cpu_renderer(v, preset_transfer_function("surface_white"), nullptr);
    Intrinsics K = camera();
    Pose T = facing(v.geom.center_world_mm());

    RenderImage lit(Light kind, std::array<double, 3> direction_or_position = {0, 0, -1}) const {
        RenderOptions opt;
        opt.want_rgb = false;
        opt.light = kind;
        if (kind == Light::point) opt.light_position_camera_mm = direction_or_position;
        else opt.light_direction_camera = direction_or_position;
        RenderImage im;
        r->render(K, T, opt, im);
        return im;
    }
};

}  // namespace

TEST(Lighting, DistantLightAlongTheAxisLooksLikeTheHeadlightAndFromAsideShadesThatSide) {
    const BallScene scene;
    const RenderImage head = scene.lit(Light::headlight), axis = scene.lit(Light::distant, {0, 0, -1});
    const RenderImage aside = scene.lit(Light::distant, {1, 0, -1});  // 45 deg towards the camera's +x (image right)

    ASSERT_GT(mean_grey(head, true), 0.05) << "the ball must be in view";
    // Headlight rays diverge by at most ~9 deg here: nearly the same picture.
    double diff = 0;
    for (size_t i = 0; i < head.grey.size(); ++i) diff += std::abs(head.grey[i] - axis.grey[i]);
    EXPECT_LT(diff / double(head.grey.size()), 0.02);
    // Lit from the right: the right half is brighter than the left; with the headlight the two
    // halves are alike.
    EXPECT_GT(mean_grey(aside, false), mean_grey(aside, true) + 0.05);
    EXPECT_NEAR(mean_grey(head, false), mean_grey(head, true), 0.02);
}

TEST(Lighting, APointLightAtTheLensIsTheHeadlightAFarOneADistantLightAndOneAsideShadesThatSide) {
    const BallScene scene;
    const RenderImage head = scene.lit(Light::headlight), at_lens = scene.lit(Light::point, {0, 0, 0});
    const RenderImage far = scene.lit(Light::point, {1e5, 0, -1e5});  // 141 m off towards the camera's +x and back
    const RenderImage distant = scene.lit(Light::distant, {1, 0, -1});
    const RenderImage aside = scene.lit(Light::point, {200, 0, 0});  // in the lens plane, as far aside as the ball is away

    ASSERT_GT(mean_grey(head, true), 0.05) << "the ball must be in view";
    double max_lens = 0, sum_far = 0, sum_head = 0;
    for (size_t i = 0; i < head.grey.size(); ++i) {
        max_lens = std::max(max_lens, double(std::abs(head.grey[i] - at_lens.grey[i])));
        sum_far += std::abs(far.grey[i] - distant.grey[i]);
        sum_head += std::abs(far.grey[i] - head.grey[i]);
    }
    EXPECT_LT(max_lens, 1e-5);  // the lamp at the lens lights each sample along its ray
    EXPECT_LT(sum_far / double(head.grey.size()), 2e-3);  // from afar its rays are parallel
    EXPECT_GT(sum_head / double(head.grey.size()), 0.02);
    // Lit from the right: the right half brighter than the left.
    EXPECT_GT(mean_grey(aside, false), mean_grey(aside, true) + 0.05);
}
