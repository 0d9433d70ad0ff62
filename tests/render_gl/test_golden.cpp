// Golden images: the GL ray caster against the CPU one (the reference) on the same volume,
// transfer function, camera and options. Thresholds: issue 3 (mean absolute difference
// <= 2/255 per RGB channel), and for grey, coverage and depth what float rounding and a
// different trilinear implementation can explain.
#include <cmath>
#include <filesystem>
#include <iostream>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/pose.hpp"
#include "test_gl_common.hpp"

namespace cf::test {
namespace {

void expect_same_pictures(const Volume& v, const TransferFunction& tf, const LabelVolume* mask, const Intrinsics& K,
                          const Pose& T, const RenderOptions& opt, const char* what) {
    auto cpu = make_cpu_renderer(v, tf, mask);
    auto gl = make_gl_renderer(v, tf, mask);
    RenderImage a, b;
    cpu->render(K, T, opt, a);
    gl->render(K, T, opt, b);
    const ImageDiff d = compare(a, b);
    std::cout << what << ": " << d << "\n";
    SCOPED_TRACE(what);
    size_t covered = 0;
    for (uint8_t c : a.coverage) covered += c;
    ASSERT_GT(covered, a.coverage.size() / 20) << "the view must show something";
    for (int c = 0; c < 3; ++c) EXPECT_LE(d.mean_abs_rgb[c], 2.0) << "channel " << c;
    EXPECT_LE(d.mean_abs_grey, 2.0 / 255);
    EXPECT_GE(d.coverage_agreement, 0.995);
    if (opt.want_depth) {
        EXPECT_LE(d.mean_abs_depth_mm, 0.1);
        EXPECT_LE(d.p95_abs_depth_mm, 0.25);
    }
}

TEST(GlGolden, SphereShadedT1) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume();
    const Intrinsics K = small_camera();
    const Eigen::Vector3d c = v.geom.center_world_mm();
    RenderOptions opt;
    expect_same_pictures(v, preset_transfer_function("cortex_t1"), nullptr, K, look_at(c, {0.3, 0.2, 1}, 250), opt,
                         "cortex_t1 oblique");
    expect_same_pictures(v, preset_transfer_function("surface_white"), nullptr, K, look_at(c, {1, 0, 0}, 250), opt,
                         "surface_white lateral");
}

TEST(GlGolden, SphereOptionsVariants) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(48);
    const Intrinsics K = small_camera(120, 90, 160);
    const Pose T = look_at(v.geom.center_world_mm(), {-0.5, 1, 0.2}, 220);
    RenderOptions opt;
    opt.shading = false;
    opt.sample_distance_mm = 0.5;
    expect_same_pictures(v, preset_transfer_function("cortex_t1"), nullptr, K, T, opt, "unshaded, 0.5 mm");
    opt = RenderOptions{};
    opt.sample_distance_mm = 1.7;
    opt.early_termination_alpha = 0.9;
    opt.coverage_alpha = 0.3;
    expect_same_pictures(v, preset_transfer_function("skin"), nullptr, K, T, opt, "skin, 1.7 mm");
    opt = RenderOptions{};
    opt.light = Light::distant;
    opt.light_direction_camera = {0.4, -0.3, -1};
    expect_same_pictures(v, preset_transfer_function("cortex_t1"), nullptr, K, T, opt, "distant light from aside");
    opt = RenderOptions{};
    opt.light = Light::point;
    opt.light_position_camera_mm = {60, -40, 10};
    expect_same_pictures(v, preset_transfer_function("cortex_t1"), nullptr, K, T, opt, "point light aside");
    opt.surface_only = true;
    expect_same_pictures(v, preset_transfer_function("cortex_t1"), nullptr, K, T, opt, "point light aside, surface only");
    opt = RenderOptions{};
    opt.surface_only = true;
    expect_same_pictures(v, preset_transfer_function("cortex_t1"), nullptr, K, T, opt, "surface only");
}

TEST(GlGolden, SlabsWithMaskAndDistortion) {
    CF_REQUIRE_GL();
    const Volume v = slab_volume();
    LabelVolume mask;
    mask.geom = v.geom;
    mask.voxels.assign(v.geom.voxel_count(), 1);
    for (int k = 0; k < v.geom.dims[2]; ++k)
        for (int j = 0; j < v.geom.dims[1] / 3; ++j)
            for (int i = 0; i < v.geom.dims[0]; ++i) mask.voxels[v.geom.linear(i, j, k)] = 0;
    Intrinsics K = small_camera();
    K.distortion = {-0.12, 0.03, 0.001, -0.001, 0.0};
    const Pose T = look_at(v.geom.center_world_mm(), {0.2, -0.3, 1}, 200);
    expect_same_pictures(v, preset_transfer_function("cortex_t1"), &mask, K, T, RenderOptions{}, "slabs, mask, distortion");
}

// A mask on thick slices (1 x 1 x 4.8 mm, oblique): both ray casters draw it from the same
// finer copy (masked_render_copy()), so they must still agree.
TEST(GlGolden, ThickSlicesWithMask) {
    CF_REQUIRE_GL();
    Volume v;
    v.geom.dims = {64, 64, 15};
    v.geom.spacing_mm = Eigen::Vector3d(1.0, 1.0, 4.8);
    v.geom.direction = Eigen::AngleAxisd(0.3, Eigen::Vector3d(1, -1, 2).normalized()).toRotationMatrix();
    v.geom.origin_mm = Eigen::Vector3d(-20, 10, -30);
    const Eigen::Vector3d c = v.geom.center_world_mm();
    v.voxels.resize(v.geom.voxel_count());
    LabelVolume mask;
    mask.geom = v.geom;
    mask.voxels.resize(v.geom.voxel_count());
    for (int k = 0; k < v.geom.dims[2]; ++k)
        for (int j = 0; j < v.geom.dims[1]; ++j)
            for (int i = 0; i < v.geom.dims[0]; ++i) {
                const Eigen::Vector3d p = v.geom.world_from_index(Eigen::Vector3d(i, j, k));
                const double r = (p - c).norm();
                // T1-like: bright inside 30 mm with some texture; the mask cuts it at 24 mm.
                v.voxels[v.geom.linear(i, j, k)] = r < 30 ? float(300 + 60 * std::sin(p.x() * 0.4) * std::cos(p.y() * 0.3)) : 20.f;
                mask.voxels[v.geom.linear(i, j, k)] = r < 24 ? 1 : 0;
            }
    ASSERT_TRUE(masked_render_copy(v, &mask, robust_range(v, &mask)).has_value());
    const Intrinsics K = small_camera();
    expect_same_pictures(v, preset_transfer_function("cortex_t1"), &mask, K, look_at(c, {0.2, 1, 0.1}, 200), RenderOptions{},
                         "thick slices, mask, across the slices");
    RenderOptions surface;
    surface.surface_only = true;
    expect_same_pictures(v, preset_transfer_function("surface_white"), &mask, K, look_at(c, {0.1, 0.2, 1}, 200), surface,
                         "thick slices, mask, along the slices, surface only");
}

TEST(GlGolden, TransferFunctionChangeAndPartialOutputs) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(48);
    const Intrinsics K = small_camera(100, 80, 150);
    const Pose T = look_at(v.geom.center_world_mm(), {0, 1, 0.3}, 200);
    auto cpu = make_cpu_renderer(v, preset_transfer_function("cortex_t1"));
    auto gl = make_gl_renderer(v, preset_transfer_function("cortex_t1"));
    cpu->set_transfer_function(preset_transfer_function("surface_white"));
    gl->set_transfer_function(preset_transfer_function("surface_white"));
    RenderOptions opt;
    opt.want_rgb = false;  // the registration's request: grey and coverage only
    opt.want_depth = false;
    RenderImage a, b;
    cpu->render(K, T, opt, a);
    gl->render(K, T, opt, b);
    EXPECT_TRUE(b.rgb.empty());
    EXPECT_TRUE(b.depth_mm.empty());
    const ImageDiff d = compare(a, b);
    EXPECT_LE(d.mean_abs_grey, 2.0 / 255) << d;
    EXPECT_GE(d.coverage_agreement, 0.995) << d;
    // Rendering again into the same image reuses its buffers (no per-frame allocation).
    const float* grey_before = b.grey.data();
    gl->render(K, T, opt, b);
    EXPECT_EQ(grey_before, b.grey.data());
}

// Every request of a view sets its transfer function again; the empty-space skipping is made
// again only when the table entries with opacity > 0 change (gl_renderer.cpp). A table showing
// the same entries (half the opacity), then one showing others (skin), then the first again: each
// drawn exactly as by a renderer made with that transfer function.
TEST(GlGolden, SkippingIsKeptOnlyWhileTheShownRangeIsTheSame) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(48);
    const Intrinsics K = small_camera(100, 80, 150);
    const Pose T = look_at(v.geom.center_world_mm(), {0.2, 1, 0.3}, 200);
    TransferFunction half = preset_transfer_function("cortex_t1");
    for (auto& p : half.opacity) p[1] *= 0.5;
    auto gl = make_gl_renderer(v, preset_transfer_function("cortex_t1"));
    RenderOptions opt;
    RenderImage warm;
    gl->render(K, T, opt, warm);
    for (const auto& [tf, what] : {std::pair{half, "the same range at half the opacity"}, std::pair{preset_transfer_function("skin"), "skin"},
                                   std::pair{preset_transfer_function("cortex_t1"), "cortex_t1 again"}}) {
        SCOPED_TRACE(what);
        gl->set_transfer_function(tf);
        auto fresh = make_gl_renderer(v, tf);
        RenderImage a, b;
        gl->render(K, T, opt, a);
        fresh->render(K, T, opt, b);
        const ImageDiff d = compare(b, a);
        std::cout << what << ": " << d << "\n";
        for (int c = 0; c < 3; ++c) EXPECT_EQ(d.mean_abs_rgb[c], 0.0) << "channel " << c;
        EXPECT_EQ(d.coverage_agreement, 1.0);
    }
}

TEST(GlGolden, BundledMriCrop) {
    CF_REQUIRE_GL();
    const std::filesystem::path t1 = std::filesystem::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz";
    const std::filesystem::path bm = std::filesystem::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz";
    if (!std::filesystem::exists(t1) || !std::filesystem::exists(bm)) GTEST_SKIP() << "bundled MRI not found";
    const Volume full = load_volume(t1);
    const LabelVolume full_mask = load_mask(bm, full.geom);
    // A 96^3 crop of the upper left hemisphere: cortex, sulci, skin.
    const std::array<int, 3> size{96, 96, 96};
    std::array<int, 3> start{};
    for (int a = 0; a < 3; ++a) start[size_t(a)] = std::max(0, full.geom.dims[size_t(a)] / 2 - size[size_t(a)] / 2);
    Volume v;
    LabelVolume mask;
    v.geom = full.geom;
    v.geom.dims = size;
    v.geom.origin_mm = full.geom.world_from_index(Eigen::Vector3d(start[0], start[1], start[2]));
    mask.geom = v.geom;
    v.voxels.resize(v.geom.voxel_count());
    mask.voxels.resize(v.geom.voxel_count());
    for (int k = 0; k < size[2]; ++k)
        for (int j = 0; j < size[1]; ++j)
            for (int i = 0; i < size[0]; ++i) {
                const size_t src = full.geom.linear(i + start[0], j + start[1], k + start[2]);
                v.voxels[v.geom.linear(i, j, k)] = full.voxels[src];
                mask.voxels[v.geom.linear(i, j, k)] = full_mask.voxels[src];
            }
    const Intrinsics K = small_camera(150, 100, 200);
    const Eigen::Vector3d c = v.geom.center_world_mm();
    expect_same_pictures(v, preset_transfer_function("cortex_t1"), &mask, K, standard_view("left", c, 250), RenderOptions{},
                         "MRI crop, brain mask, cortex_t1");
    RenderOptions surface;
    surface.surface_only = true;
    surface.want_rgb = false;
    expect_same_pictures(v, preset_transfer_function("surface_white"), &mask, K, standard_view("left", c, 250), surface,
                         "MRI crop, brain mask, surface_white, surface only (registration)");
    surface.sample_distance_mm = 2;
    surface.sample_anchor_world_mm = std::array<double, 3>{c.x() - 20, c.y() + 7, c.z() + 3};  // a lattice phase off 0
    expect_same_pictures(v, preset_transfer_function("surface_white"), &mask, K, standard_view("left", c, 250), surface,
                         "MRI crop, brain mask, surface_white, surface only, 2 mm samples anchored (registration)");
    expect_same_pictures(v, preset_transfer_function("skin"), nullptr, K, standard_view("superior", c, 250),
                         RenderOptions{}, "MRI crop, skin");
}

}  // namespace
}  // namespace cf::test
