#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <random>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/volume.hpp"

namespace fs = std::filesystem;
using namespace cf;

namespace {
fs::path tmpdir(const std::string& name) {
    auto p = fs::temp_directory_path() / ("cf_test_" + name + "_" + std::to_string(::getpid()));
    fs::create_directories(p);
    return p;
}

Volume ramp_volume(const VolumeGeometry& g) {
    Volume v;
    v.geom = g;
    v.voxels.resize(g.voxel_count());
    for (int k = 0; k < g.dims[2]; ++k)
        for (int j = 0; j < g.dims[1]; ++j)
            for (int i = 0; i < g.dims[0]; ++i) {
                const Eigen::Vector3d p = g.world_from_index(Eigen::Vector3d(i, j, k));
                v.voxels[g.linear(i, j, k)] = float(p.x() + 2 * p.y() + 3 * p.z());
            }
    return v;
}
}  // namespace

TEST(Volume, ReadsShippedMriInLps) {
    const Volume v = load_volume(fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz");
    EXPECT_EQ(v.geom.dims[0], 256);
    EXPECT_EQ(v.geom.dims[2], 256);
    // NIfTI LIA on disk: ITK reports LPS direction cosines. i -> Left (+x LPS).
    EXPECT_NEAR(v.geom.direction(0, 0), 1.0, 1e-6);
    // j -> Inferior: -z in LPS.
    EXPECT_NEAR(v.geom.direction(2, 1), -1.0, 1e-6);
    const auto s = intensity_stats(v);
    EXPECT_GE(s.max, 200);
    EXPECT_GE(s.min, 0);
}

TEST(Volume, FormatsRoundTripWithObliqueFlippedGeometry) {
    VolumeGeometry g;
    g.dims = {12, 10, 8};
    g.spacing_mm = {1.5, 0.9, 2.0};
    g.origin_mm = {-30, 12, 40};
    // Oblique and flipped: a rotation times a reflection of one axis is not allowed (det -1 kept by ITK too).
    Eigen::Matrix3d R = rotation_xyz_deg(20, -10, 35);
    R.col(1) *= -1;
    g.direction = R;
    const Volume v = ramp_volume(g);
    const auto dir = tmpdir("fmt");
    for (const char* name : {"a.nii.gz", "a.nii", "a.nrrd", "a.mha"}) {
        save_volume(v, dir / name);
        const Volume r = load_volume(dir / name);
        ASSERT_TRUE(r.geom.same_grid(v.geom, 1e-4)) << name;
        // A world point lands where it belongs: the ramp value equals the world formula.
        for (int probe = 0; probe < 20; ++probe) {
            const int i = probe % 12, j = (probe * 3) % 10, k = (probe * 5) % 8;
            const Eigen::Vector3d p = r.geom.world_from_index(Eigen::Vector3d(i, j, k));
            EXPECT_NEAR(r.at(i, j, k), p.x() + 2 * p.y() + 3 * p.z(), 1e-3) << name;
        }
    }
    fs::remove_all(dir);
}

TEST(Volume, ResampleOntoIsotropicGridKeepsWorldValues) {
    VolumeGeometry g;
    g.dims = {20, 18, 16};
    g.spacing_mm = {1.0, 1.2, 1.5};
    g.direction = rotation_xyz_deg(0, 0, 90);
    const Volume v = ramp_volume(g);
    const VolumeGeometry iso = isotropic_grid(g, 1.0);
    const Volume r = resample(v, iso, -1e6f);
    int checked = 0;
    for (int k = 2; k < iso.dims[2] - 2; k += 3)
        for (int j = 2; j < iso.dims[1] - 2; j += 3)
            for (int i = 2; i < iso.dims[0] - 2; i += 3) {
                const float val = r.at(i, j, k);
                if (val < -1e5f) continue;
                const Eigen::Vector3d p = iso.world_from_index(Eigen::Vector3d(i, j, k));
                EXPECT_NEAR(val, p.x() + 2 * p.y() + 3 * p.z(), 1e-2);
                ++checked;
            }
    EXPECT_GT(checked, 50);
}

TEST(Volume, AMaskIsLoadedOntoItsVolumesGridWhenItLiesOnAnother) {
    // A mask saved on a coarser, turned grid (as a plan's or another tool's may be) lands on
    // the volume's grid as resample_nearest puts it; one on the volume's grid comes as saved.
    VolumeGeometry g;
    g.dims = {20, 18, 16};
    g.spacing_mm = {1.0, 1.0, 1.0};
    VolumeGeometry coarse = g;
    coarse.dims = {10, 9, 8};
    coarse.spacing_mm = {2.0, 2.0, 2.0};
    coarse.direction = rotation_xyz_deg(0, 0, 10);
    LabelVolume m;
    m.geom = coarse;
    m.voxels.assign(coarse.voxel_count(), 0);
    for (int k = 2; k < 6; ++k)
        for (int j = 2; j < 7; ++j)
            for (int i = 3; i < 8; ++i) m.voxels[coarse.linear(i, j, k)] = 1;
    const fs::path dir = tmpdir("mask_on_grid");
    save_mask(m, dir / "coarse.nii.gz");
    const LabelVolume on_g = load_mask(dir / "coarse.nii.gz", g);
    EXPECT_TRUE(on_g.geom.same_grid(g));
    EXPECT_EQ(on_g.voxels, resample_nearest(load_mask(dir / "coarse.nii.gz"), g).voxels);
    EXPECT_GT(on_g.count_nonzero(), 100u);
    save_mask(on_g, dir / "fine.nii.gz");
    const LabelVolume again = load_mask(dir / "fine.nii.gz", g);
    EXPECT_EQ(again.voxels, on_g.voxels);
    EXPECT_THROW(load_mask(dir / "missing.nii.gz", g), InputError);
    fs::remove_all(dir);
}

TEST(Volume, ReadsDicomSeriesFolder) {
    const fs::path dir = fs::path(CF_TEST_DATA_DIR) / "dicom_mr_sag";
    if (!fs::exists(dir)) GTEST_SKIP() << "no DICOM test series";
    const Volume v = load_volume(dir);
    EXPECT_EQ(v.geom.dims[0], 256);
    EXPECT_EQ(v.geom.dims[2], 35);
    // Sagittal: in-plane rows go along +y (posterior), columns along -z (inferior).
    EXPECT_NEAR(std::abs(v.geom.direction(1, 0)), 1.0, 1e-3);
}

TEST(Volume, BadFilesGiveClearErrors) {
    const auto dir = tmpdir("bad");
    EXPECT_THROW(load_volume(dir / "missing.nii.gz"), InputError);
    {
        std::ofstream(dir / "junk.nii.gz") << "this is not a volume";
    }
    try {
        load_volume(dir / "junk.nii.gz");
        FAIL();
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("junk.nii.gz"), std::string::npos);
    }
    // Truncated gzip of a real volume.
    {
        std::ifstream in(fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz", std::ios::binary);
        std::string bytes((std::istreambuf_iterator<char>(in)), {});
        std::ofstream(dir / "trunc.nii.gz", std::ios::binary).write(bytes.data(), std::streamsize(bytes.size() / 2));
    }
    EXPECT_THROW(load_volume(dir / "trunc.nii.gz"), InputError);
    EXPECT_THROW(load_volume(dir / "file.txt"), InputError);
    EXPECT_THROW(load_volume(dir), InputError);  // folder without DICOM
    fs::remove_all(dir);
}

TEST(Camera, ProjectBackprojectRoundTripWithDistortion) {
    Intrinsics K;
    K.width = 640;
    K.height = 480;
    K.fx = 538.98;
    K.fy = 539.2;
    K.cx = 339.38;
    K.cy = 237.31;
    K.distortion = {-0.2605, -0.0738, 0.0030, -0.0005, 0.2762};
    std::mt19937 rng(3);
    std::uniform_real_distribution<double> U(0, 1);
    for (int n = 0; n < 200; ++n) {
        const Eigen::Vector2d px(20 + U(rng) * 600, 20 + U(rng) * 440);
        const double z = 100 + 400 * U(rng);
        const Eigen::Vector3d p = backproject(K, px, z);
        EXPECT_NEAR(p.z(), z, 1e-9);
        const auto q = project_camera(K, p);
        ASSERT_TRUE(q);
        EXPECT_NEAR((*q - px).norm(), 0.0, 1e-3);
    }
    // Pose round trip.
    Pose T = Pose::Identity();
    T.topLeftCorner<3, 3>() = rotation_xyz_deg(10, -20, 30);
    T.topRightCorner<3, 1>() = Eigen::Vector3d(5, -3, 300);
    const Eigen::Vector3d pw(12, -7, 9);
    const auto px = project(K, T, pw);
    ASSERT_TRUE(px);
    const Eigen::Vector3d pc = T.topLeftCorner<3, 3>() * pw + T.topRightCorner<3, 1>();
    const Eigen::Vector3d back = backproject(K, *px, pc.z());
    EXPECT_NEAR((back - pc).norm(), 0.0, 1e-3);
}

TEST(Camera, ScaledIntrinsicsKeepPixelCentres) {
    Intrinsics K{3000, 2000, 5600, 5600, 1499.5, 999.5, {0, 0, 0, 0, 0}};
    const Intrinsics k = K.resized(375, 250);
    EXPECT_NEAR(k.fx, 700, 1e-9);
    EXPECT_NEAR(k.cx, 187, 1e-9);
    const Eigen::Vector3d p(10, -20, 400);
    const auto a = project_camera(K, p), b = project_camera(k, p);
    EXPECT_NEAR(((*a).array() + 0.5).x() / 8.0 - 0.5, (*b).x(), 1e-9);
}

TEST(Pose, ParamsRoundTripAboutPivot) {
    Pose T0 = Pose::Identity();
    T0.topLeftCorner<3, 3>() = rotation_xyz_deg(5, 80, -30);
    T0.topRightCorner<3, 1>() = Eigen::Vector3d(3, 4, 350);
    const Eigen::Vector3d pivot(0, 0, 350);
    const PoseParams x{4, -3, 7, 2, -1, 5};
    const Pose T = apply_params(T0, pivot, x);
    EXPECT_TRUE(is_rigid(T));
    const PoseParams y = params_between(T0, T, pivot);
    for (int i = 0; i < 6; ++i) EXPECT_NEAR(x[i], y[i], 1e-9);
    // A pure rotation about the pivot leaves the pivot in place.
    const Pose Tr = apply_params(T0, pivot, {10, 10, 10, 0, 0, 0});
    const Eigen::Vector3d pw = T0.inverse().topLeftCorner<3, 3>() * pivot + T0.inverse().topRightCorner<3, 1>();
    const Eigen::Vector3d pc = Tr.topLeftCorner<3, 3>() * pw + Tr.topRightCorner<3, 1>();
    EXPECT_NEAR((pc - pivot).norm(), 0, 1e-9);
}
