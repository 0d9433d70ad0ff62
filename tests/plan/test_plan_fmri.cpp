// The fMRI path of `cortexfuse plan` end to end (make_plan): a t-map in its own EPI space
// (3 mm voxels, moved by a known rigid transform against the T1) with a mean-EPI-like
// reference; the plan registers the reference to the T1, thresholds the map (t, cluster size),
// resamples the surviving cluster onto the T1 grid where the activation truly is, and writes
// the map's own transfer function (threshold -> peak, hot colours, transparent below).
#include <gtest/gtest.h>

#include <algorithm>
#include <filesystem>
#include <random>

#include "../remove_dir_guard.hpp"
#include "cortexfuse/core/coregistration.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/plan.hpp"
#include "cortexfuse/core/surface.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "cortexfuse/core/volume.hpp"

namespace fs = std::filesystem;
using namespace cf;

namespace {

Eigen::Vector3d centroid_world(const LabelVolume& m) {
    const Eigen::Affine3d W = m.geom.world_from_index();
    Eigen::Vector3d s = Eigen::Vector3d::Zero();
    size_t n = 0;
    for (int k = 0; k < m.geom.dims[2]; ++k)
        for (int j = 0; j < m.geom.dims[1]; ++j)
            for (int i = 0; i < m.geom.dims[0]; ++i)
                if (m.at(i, j, k)) s += Eigen::Vector3d(i, j, k), ++n;
    return W * (s / double(n));
}

}  // namespace

TEST(PlanFmri, EpiSpaceMapIsThresholdedRegisteredAndResampledOntoTheT1) {
    const fs::path dir = fs::temp_directory_path() / ("cf_plan_fmri_" + std::to_string(::getpid()));
    fs::remove_all(dir);
    fs::create_directories(dir);
    const cf::test::RemoveDirGuard guard{dir};

    const Volume t1_full = load_volume(fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz");
    const LabelVolume m_full = load_mask(fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz");
    const VolumeGeometry g = isotropic_grid(t1_full.geom, 3.0);
    save_volume(resample(t1_full, g), dir / "t1.nii.gz");
    save_mask(resample_nearest(m_full, g), dir / "brain_mask.nii.gz");
    const Volume t1 = load_volume(dir / "t1.nii.gz");
    const LabelVolume brain = load_mask(dir / "brain_mask.nii.gz");

    // The EPI space: the head moved by a known rigid transform, mean-EPI-like contrast.
    const SyntheticCoregCase epi = make_synthetic_epi_case(t1, 31, 8, 12, 3.0, 4.0, 20.0);
    save_volume(epi.moving, dir / "mean_epi.nii.gz");
    // The t-map on the EPI grid: a Gaussian activation (peak 8, sigma 5 mm) at p0 (T1 world),
    // a single supra-threshold voxel at p1 (a cluster below the size limit), noise below 3.1.
    const Eigen::Vector3d c = centroid_world(brain);
    const Eigen::Vector3d p0 = c + Eigen::Vector3d(25, -10, 20), p1 = c + Eigen::Vector3d(-30, 15, -5);
    const Eigen::Matrix4d T_fixed_from_moving = epi.T_moving_from_fixed.inverse();
    Volume tmap;
    tmap.geom = epi.moving.geom;
    tmap.voxels.assign(tmap.geom.voxel_count(), 0.f);
    std::mt19937 rng(4);
    std::uniform_real_distribution<float> noise(-1.5f, 1.5f);
    const Eigen::Affine3d W = tmap.geom.world_from_index();
    const Eigen::Vector3d p1_epi = epi.T_moving_from_fixed.topLeftCorner<3, 3>() * p1 + epi.T_moving_from_fixed.topRightCorner<3, 1>();
    const Eigen::Vector3d p1_ijk = tmap.geom.index_from_world() * p1_epi;
    for (int k = 0; k < tmap.geom.dims[2]; ++k)
        for (int j = 0; j < tmap.geom.dims[1]; ++j)
            for (int i = 0; i < tmap.geom.dims[0]; ++i) {
                const Eigen::Vector3d q = W * Eigen::Vector3d(i, j, k);
                const Eigen::Vector3d p = T_fixed_from_moving.topLeftCorner<3, 3>() * q + T_fixed_from_moving.topRightCorner<3, 1>();
                float v = noise(rng) + float(8.0 * std::exp(-(p - p0).squaredNorm() / (2 * 5.0 * 5.0)));
                if (i == int(std::lround(p1_ijk.x())) && j == int(std::lround(p1_ijk.y())) && k == int(std::lround(p1_ijk.z())))
                    v = 6.f;
                tmap.voxels[tmap.geom.linear(i, j, k)] = v;
            }
    save_volume(tmap, dir / "tmap.nii.gz");

    // A reference mask that differs from the brain mask (its upper third cut off): the plan
    // reports their Dice.
    LabelVolume ref = brain;
    for (int k = 2 * ref.geom.dims[2] / 3; k < ref.geom.dims[2]; ++k)
        for (int j = 0; j < ref.geom.dims[1]; ++j)
            for (int i = 0; i < ref.geom.dims[0]; ++i) ref.voxels[ref.geom.linear(i, j, k)] = 0;
    save_mask(ref, dir / "reference_mask.nii.gz");
    size_t both = 0, na = 0, nb = 0;
    for (size_t i = 0; i < brain.voxels.size(); ++i) {
        na += brain.voxels[i] != 0, nb += ref.voxels[i] != 0;
        both += brain.voxels[i] != 0 && ref.voxels[i] != 0;
    }
    const double expected_dice = 2.0 * double(both) / double(na + nb);
    ASSERT_LT(expected_dice, 0.99);

    PlanInputs in;
    in.t1 = dir / "t1.nii.gz";
    in.brain_mask = dir / "brain_mask.nii.gz";
    in.reference_mask = dir / "reference_mask.nii.gz";
    in.fmri = dir / "tmap.nii.gz";
    in.fmri_reference = dir / "mean_epi.nii.gz";
    PlanParams P;
    P.surface.max_triangles = 20000;
    P.coreg_fmri.shrink = {2, 1};
    P.coreg_fmri.smooth_mm = {3.0, 0.0};
    P.coreg_fmri.iterations = {150, 80};
    P.coreg_fmri.sampling = 0.2;
    P.fmri.threshold = 3.1;
    P.fmri.min_cluster_voxels = 5;
    const nlohmann::json plan = make_plan(in, P, dir / "plan");

    EXPECT_EQ(plan["t1_fingerprint"], volume_fingerprint(t1));
    // Every step with its seconds; the mask step with the Dice against the reference.
    for (const auto& st : plan["steps"]) EXPECT_TRUE(st.contains("seconds")) << st.dump();
    EXPECT_NEAR(plan["steps"][1]["dice"].get<double>(), expected_dice, 1e-9) << plan["steps"][1].dump();
    EXPECT_TRUE(load_mask(dir / "plan" / "brain_mask.nii.gz").geom.same_grid(t1.geom));
    // The surface in world LPS mm: on the brain (inside the mask's world box, 6 mm slack).
    {
        const SurfaceMesh mesh = load_mesh(dir / "plan" / "brain_surface.ply");
        ASSERT_FALSE(mesh.triangles.empty());
        const Eigen::Affine3d I = brain.geom.index_from_world();
        size_t inside = 0;
        for (const auto& v : mesh.vertices) {
            const Eigen::Vector3d q = I * v.cast<double>();
            inside += q.x() > -2 && q.y() > -2 && q.z() > -2 && q.x() < brain.geom.dims[0] + 1 && q.y() < brain.geom.dims[1] + 1 &&
                      q.z() < brain.geom.dims[2] + 1 && brain.at(std::clamp(int(std::lround(q.x())), 0, brain.geom.dims[0] - 1),
                                                                 std::clamp(int(std::lround(q.y())), 0, brain.geom.dims[1] - 1),
                                                                 std::clamp(int(std::lround(q.z())), 0, brain.geom.dims[2] - 1));
        }
        EXPECT_GT(double(inside) / double(mesh.vertices.size()), 0.5) << "surface vertices on the brain mask";
    }
    const nlohmann::json* step = nullptr;
    for (const auto& s : plan["steps"])
        if (s["step"] == "fmri") step = &s;
    ASSERT_NE(step, nullptr) << plan.dump();
    EXPECT_EQ((*step)["clusters"].get<int>(), 1) << step->dump();  // the single voxel is gone

    // The registration recovered the EPI space's transform (error over the brain).
    const Eigen::Matrix4d T = load_transform(dir / "plan" / "fmri_to_t1.tfm");
    EXPECT_LT(transform_error(epi.T_moving_from_fixed, T, brain).mean_mm, 1.5);

    // On the T1 grid, where the activation truly is, thresholded values only.
    const Volume on_t1 = load_volume(dir / "plan" / "fmri_on_t1.nii.gz");
    ASSERT_TRUE(on_t1.geom.same_grid(t1.geom));
    const Eigen::Affine3d Wt = on_t1.geom.world_from_index();
    Eigen::Vector3d s = Eigen::Vector3d::Zero();
    size_t n = 0;
    double peak = 0;
    for (int k = 0; k < on_t1.geom.dims[2]; ++k)
        for (int j = 0; j < on_t1.geom.dims[1]; ++j)
            for (int i = 0; i < on_t1.geom.dims[0]; ++i) {
                const float v = on_t1.voxels[on_t1.geom.linear(i, j, k)];
                if (v == 0.f) continue;
                EXPECT_GE(v, 3.1f);
                s += Wt * Eigen::Vector3d(i, j, k), ++n, peak = std::max(peak, double(v));
            }
    ASSERT_GT(n, 20u);
    EXPECT_LT((s / double(n) - p0).norm(), 3.0) << "activation centroid off the truth";
    const Eigen::Vector3d p1_ijk_t1 = on_t1.geom.index_from_world() * p1;
    EXPECT_EQ(on_t1.at(int(std::lround(p1_ijk_t1.x())), int(std::lround(p1_ijk_t1.y())), int(std::lround(p1_ijk_t1.z()))), 0.f);
    EXPECT_GT(peak, 6.0);

    // Its own transfer function, in the map's units: transparent below the threshold, dark red
    // at it, yellow at the peak.
    const TransferFunction tf = load_transfer_function(dir / "plan" / "fmri_transfer_function.json");
    EXPECT_FALSE(tf.normalized);
    ASSERT_GE(tf.colour.size(), 2u);
    EXPECT_DOUBLE_EQ(tf.colour.front()[0], 3.1);
    EXPECT_GT(tf.colour.front()[1], 0.5);
    EXPECT_EQ(tf.colour.front()[3], 0.0);                       // dark red
    EXPECT_NEAR(tf.colour.back()[0], (*step)["peak"].get<double>(), 1e-9);
    EXPECT_GT(tf.colour.back()[2], 0.9);                        // yellow
    for (const auto& o : tf.opacity) {
        if (o[0] < 3.1) {
            EXPECT_EQ(o[1], 0.0) << o[0];
        }
    }
}
