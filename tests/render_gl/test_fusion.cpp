// Multimodal fusion and opaque geometry on the GL renderer.
#include "test_gl_common.hpp"

namespace cf::test {
namespace {

double mean_abs_rgb(const RenderImage& a, const RenderImage& b) {
    const ImageDiff d = compare(a, b);
    return (d.mean_abs_rgb[0] + d.mean_abs_rgb[1] + d.mean_abs_rgb[2]) / 3;
}

// A translated copy of the sphere (a second modality, e.g. an fMRI blob off-centre).
Volume shifted(const Volume& v, const Eigen::Vector3d& by_mm) {
    Volume o = v;
    o.geom.origin_mm += by_mm;
    return o;
}

TEST(GlFusion, SettingsUploadNoVolume) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(40);
    auto r = make_gl_fusion_renderer();
    EXPECT_EQ(r->volume_uploads(), 0);
    r->add_layer(v, preset_transfer_function("cortex_t1"));
    r->add_layer(shifted(v, {15, 0, 0}), preset_transfer_function("fmri_hot"));
    EXPECT_EQ(r->volume_uploads(), 2);
    EXPECT_EQ(r->layer_count(), 2);
    const Intrinsics K = small_camera(80, 60, 120);
    const Pose T = look_at(v.geom.center_world_mm(), {0, 0, 1}, 200);
    RenderImage img;
    r->render(K, T, RenderOptions{}, img);
    r->set_layer_transfer_function(1, preset_transfer_function("skin"));
    r->set_transfer_function(preset_transfer_function("surface_white"));
    LayerSettings s = r->layer_settings(1);
    s.weight = 0.3;
    r->set_layer_settings(1, s);
    s.visible = false;
    r->set_layer_settings(1, s);
    s.T_scene_from_layer.topRightCorner<3, 1>() = Eigen::Vector3d(1, 2, 3);
    r->set_layer_settings(1, s);
    r->render(K, T, RenderOptions{}, img);
    EXPECT_EQ(r->volume_uploads(), 2) << "settings changes must not upload volumes";
}

TEST(GlFusion, HiddenOrZeroWeightLayerChangesNothing) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(40);
    const auto tf = preset_transfer_function("cortex_t1");
    const Intrinsics K = small_camera(100, 80, 150);
    const Pose T = look_at(v.geom.center_world_mm(), {0.3, 0.2, 1}, 200);
    auto single = make_gl_renderer(v, tf);
    RenderImage ref;
    single->render(K, T, RenderOptions{}, ref);

    auto fused = make_gl_fusion_renderer();
    fused->add_layer(v, tf);
    LayerSettings hidden;
    hidden.visible = false;
    fused->add_layer(shifted(v, {12, 0, 0}), preset_transfer_function("skin"), nullptr, hidden);
    RenderImage img;
    fused->render(K, T, RenderOptions{}, img);
    EXPECT_EQ(mean_abs_rgb(ref, img), 0.0);

    // Visible: the picture changes (the second sphere shows where the first is not).
    fused->set_layer_settings(1, LayerSettings{});
    fused->render(K, T, RenderOptions{}, img);
    EXPECT_GT(mean_abs_rgb(ref, img), 1.0);
    // Weight 0 is the same as hidden.
    LayerSettings zero;
    zero.weight = 0;
    fused->set_layer_settings(1, zero);
    fused->render(K, T, RenderOptions{}, img);
    EXPECT_EQ(mean_abs_rgb(ref, img), 0.0);
}

TEST(GlFusion, WeightScalesALayersContribution) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(40);
    const Intrinsics K = small_camera(100, 80, 150);
    const Pose T = look_at(v.geom.center_world_mm(), {0, 0, 1}, 200);
    auto r = make_gl_fusion_renderer();
    r->add_layer(v, preset_transfer_function("cortex_t1"));
    r->add_layer(shifted(v, {18, 0, 0}), preset_transfer_function("skin"));
    std::vector<double> coverage;
    for (double w : {0.05, 0.4, 1.0}) {
        LayerSettings s;
        s.weight = w;
        r->set_layer_settings(1, s);
        RenderImage img;
        r->render(K, T, RenderOptions{}, img);
        double sum = 0;
        for (float g : img.grey) sum += g;
        coverage.push_back(sum);
    }
    EXPECT_LT(coverage[0], coverage[1]);
    EXPECT_LT(coverage[1], coverage[2]);
}

TEST(GlFusion, LayerTransformEqualsMovingTheCamera) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(40);
    const auto tf = preset_transfer_function("cortex_t1");
    const Intrinsics K = small_camera(100, 80, 150);
    const Pose T = look_at(v.geom.center_world_mm(), {0.2, 0.1, 1}, 200);
    Pose M = Pose::Identity();  // T_scene_from_layer: a small rotation and a shift
    M.topLeftCorner<3, 3>() = Eigen::AngleAxisd(0.15, Eigen::Vector3d(0, 1, 0.3).normalized()).toRotationMatrix();
    M.topRightCorner<3, 1>() = Eigen::Vector3d(4, -3, 2);
    auto moved = make_gl_fusion_renderer();
    LayerSettings s;
    s.T_scene_from_layer = M;
    moved->add_layer(v, tf, nullptr, s);
    auto plain = make_gl_renderer(v, tf);
    RenderImage a, b;
    moved->render(K, T, RenderOptions{}, a);
    plain->render(K, T * M, RenderOptions{}, b);  // camera_from_layer = camera_from_scene * scene_from_layer
    const ImageDiff d = compare(a, b);
    EXPECT_LE(d.mean_abs_rgb[1], 0.5) << d;
    EXPECT_GE(d.coverage_agreement, 0.998) << d;
    // And the CPU renders the same with the moved camera.
    auto cpu = make_cpu_renderer(v, tf);
    RenderImage c;
    cpu->render(K, T * M, RenderOptions{}, c);
    EXPECT_LE(compare(a, c).mean_abs_rgb[1], 2.0);
}

TEST(GlFusion, RayStartMapDoesNotChangePixels) {
    // Two layers, the second moved and off-centre, seen from far, from close and from inside
    // the first layer's box, with and without lens distortion: starting rays at the nearest
    // frontier brick of either layer gives the pixels of starting them at the boxes.
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(48);
    const auto tf = preset_transfer_function("cortex_t1");
    Pose M = Pose::Identity();
    M.topLeftCorner<3, 3>() = Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 1, 0).normalized()).toRotationMatrix();
    M.topRightCorner<3, 1>() = Eigen::Vector3d(18, -10, 6);
    auto r = make_gl_fusion_renderer();
    r->add_layer(v, tf, nullptr);
    LayerSettings s;
    s.T_scene_from_layer = M;
    s.weight = 0.6;
    r->add_layer(shifted(v, {9, 0, 0}), tf, nullptr, s);
    const Eigen::Vector3d c = v.geom.center_world_mm();
    Intrinsics K = small_camera(100, 80, 150);
    Intrinsics Kd = K;
    Kd.distortion = {-0.2, 0.05, 0.001, -0.001, 0};
    int n = 0;
    for (const auto& [T, Kv] : std::vector<std::pair<Pose, const Intrinsics*>>{
             {look_at(c, {0.3, 0.2, 1}, 260), &K}, {look_at(c, {-1, 0.4, 0.2}, 90), &K}, {look_at(c, {0.1, 1, 0.2}, 25), &K},
             {look_at(c, {0.5, -0.3, 1}, 180), &Kd}})
        for (const bool surface_only : {false, true}) {
            RenderOptions with, without;
            with.surface_only = without.surface_only = surface_only;
            without.ray_start_map = false;
            RenderImage a, b;
            r->render(*Kv, T, with, a);
            r->render(*Kv, T, without, b);
            const ImageDiff d = compare(a, b);
            size_t covered = 0;
            for (uint8_t cv : a.coverage) covered += cv;
            EXPECT_GT(covered, 200u) << "view " << n;
            int max_rgb = 0;
            for (size_t i = 0; i < a.rgb.size(); ++i) max_rgb = std::max(max_rgb, std::abs(int(a.rgb[i]) - int(b.rgb[i])));
            EXPECT_EQ(max_rgb, 0) << "view " << n << " surface_only " << surface_only << " " << d;
            EXPECT_GE(d.coverage_agreement, 1.0) << "view " << n << " " << d;
            ++n;
        }
}

// A camera-facing square of `half_mm` at camera depth z_mm, in world coordinates, coloured.
// Centred on the ray of `pixel` when given (else the optical axis).
OpaqueMesh square_at_depth(const Pose& T, double z_mm, double half_mm, const Eigen::Vector3f& colour,
                           const Intrinsics* K = nullptr, Eigen::Vector2d pixel = {0, 0}) {
    OpaqueMesh m;
    const Pose Tw = T.inverse();
    const Eigen::Vector2d c = K ? Eigen::Vector2d((pixel.x() - K->cx) / K->fx * z_mm, (pixel.y() - K->cy) / K->fy * z_mm)
                                : Eigen::Vector2d(0, 0);
    for (auto [x, y] : {std::pair{-1, -1}, {1, -1}, {1, 1}, {-1, 1}}) {
        const Eigen::Vector4d p_cam(c.x() + x * half_mm, c.y() + y * half_mm, z_mm, 1);
        m.p_world_mm.push_back((Tw * p_cam).head<3>().cast<float>());
        m.colour.push_back(colour);
    }
    m.triangles = {0, 1, 2, 0, 2, 3};
    return m;
}

TEST(GlFusion, MeshInFrontHidesTheVolumeAndBehindIsHidden) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(40);
    const Intrinsics K = small_camera(100, 80, 150);
    const Pose T = look_at(v.geom.center_world_mm(), {0, 0, 1}, 200);
    auto r = make_gl_renderer(v, preset_transfer_function("surface_white"));
    RenderImage vol;
    r->render(K, T, RenderOptions{}, vol);
    const size_t centre = size_t(K.height / 2) * K.width + K.width / 2;
    ASSERT_EQ(vol.coverage[centre], 1);
    const float z_surface = vol.depth_mm[centre];
    ASSERT_GT(z_surface, 150.f);
    ASSERT_LT(z_surface, 200.f);

    // In front: the square's colour and depth at the centre.
    const OpaqueMesh front = square_at_depth(T, z_surface - 20, 8, {1, 0, 0});
    r->set_mesh(&front);
    RenderImage img;
    r->render(K, T, RenderOptions{}, img);
    EXPECT_EQ(img.rgb[3 * centre], 255);
    EXPECT_EQ(img.rgb[3 * centre + 1], 0);
    EXPECT_EQ(img.rgb[3 * centre + 2], 0);
    EXPECT_NEAR(img.depth_mm[centre], z_surface - 20, 0.01);
    // Outside the square (a corner pixel far from it) nothing changed.
    EXPECT_EQ(img.rgb[0], vol.rgb[0]);

    // Behind the opaque surface: hidden, the picture is the volume's.
    const OpaqueMesh behind = square_at_depth(T, z_surface + 30, 8, {1, 0, 0});
    r->set_mesh(&behind);
    r->render(K, T, RenderOptions{}, img);
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(int(img.rgb[3 * centre + c]), int(vol.rgb[3 * centre + c]), 6) << c;
    EXPECT_NEAR(img.depth_mm[centre], z_surface, 0.01);

    // Beside the volume (no volume there): the mesh shows, with coverage.
    const size_t corner = size_t(4) * K.width + 4;
    ASSERT_EQ(vol.coverage[corner], 0);
    const OpaqueMesh side = square_at_depth(T, 190, 2, {0, 1, 0}, &K, {4, 4});
    r->set_mesh(&side);
    r->render(K, T, RenderOptions{}, img);
    EXPECT_EQ(img.rgb[3 * corner + 1], 255);
    EXPECT_EQ(img.coverage[corner], 1);
    EXPECT_NEAR(img.depth_mm[corner], 190, 0.01);

    // A textured mesh: the texture's colour (BGR image, OpenCV convention).
    OpaqueMesh tex = square_at_depth(T, z_surface - 20, 8, {1, 1, 1});
    tex.texture = cv::Mat(4, 4, CV_8UC3, cv::Scalar(255, 0, 0));  // blue in BGR
    tex.uv = {{0, 0}, {1, 0}, {1, 1}, {0, 1}};
    r->set_mesh(&tex);
    r->render(K, T, RenderOptions{}, img);
    EXPECT_EQ(img.rgb[3 * centre + 2], 255);
    EXPECT_EQ(img.rgb[3 * centre], 0);
    r->set_mesh(nullptr);
    r->render(K, T, RenderOptions{}, img);
    EXPECT_EQ(mean_abs_rgb(vol, img), 0.0);
}

}  // namespace
}  // namespace cf::test
