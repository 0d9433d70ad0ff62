// Rigid co-registration: accuracy on a synthetic CT-like case with truth (small grid, so
// fast), transform files, quality gates, fMRI thresholding.
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <random>
#include <sstream>

#include "cortexfuse/core/coregistration.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/plan.hpp"
#include "cortexfuse/core/volume.hpp"

namespace fs = std::filesystem;
using namespace cf;

namespace {

struct Head {
    Volume t1;
    LabelVolume brain;
};

const Head& head3mm() {
    static const Head h = [] {
        Head r;
        const Volume t1 = load_volume(fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz");
        const LabelVolume m = load_mask(fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz");
        const VolumeGeometry g = isotropic_grid(t1.geom, 3.0);
        r.t1 = resample(t1, g);
        r.brain = resample_nearest(m, g);
        return r;
    }();
    return h;
}

CoregParams fast_params() {
    CoregParams p;
    p.shrink = {2, 1};
    p.smooth_mm = {3.0, 0.0};
    p.iterations = {150, 80};
    p.sampling = 0.2;
    return p;
}

/// A synthetic case registered with `metric`: the result and its error over the brain before
/// (the initial alignment) and after.
struct Recovery {
    CoregResult r;
    TransformError before, after;
};
Recovery recover(const Head& h, const SyntheticCoregCase& c, CoregParams::Metric metric) {
    CoregParams p = fast_params();
    p.metric = metric;
    Recovery out{coregister(h.t1, c.moving, p), {}, {}};
    out.before = transform_error(c.T_moving_from_fixed, out.r.T_initial, h.brain);
    out.after = transform_error(c.T_moving_from_fixed, out.r.T_moving_from_fixed, h.brain);
    return out;
}

fs::path temp_dir(const char* name) {
    const fs::path d = fs::temp_directory_path() / (std::string(name) + "_" + std::to_string(::getpid()));
    fs::create_directories(d);
    return d;
}

}  // namespace

TEST(Coregister, RecoversSyntheticCtLikeMisalignment) {
    const Head& h = head3mm();
    for (uint64_t seed : {11u, 12u}) {
        const SyntheticCoregCase c = make_synthetic_ct_case(h.t1, seed, 10, 15, 3.0, 4.0, 5.0);
        // Both metrics: Mattes MI through ITK, and true NMI (Nelder-Mead on (H(F)+H(M))/H(F,M)),
        // held to the same figure.
        for (auto metric : {CoregParams::Metric::Mattes, CoregParams::Metric::Nmi}) {
            const auto [r, before, e] = recover(h, c, metric);
            // 3 mm voxels here; the 1 mm figure (<= 0.5 mm) comes from bench/coregister_vs_elastix.sh.
            EXPECT_LT(e.mean_mm, 1.0) << "seed " << seed << " metric " << int(metric) << " initial " << before.mean_mm;
            EXPECT_GT(before.mean_mm, 3.0);
            EXPECT_GT(r.nmi, 1.05);
            EXPECT_GT(r.overlap, 0.9);
            EXPECT_EQ(r.levels.size(), 2u);
            std::printf("ct seed %d metric %d: error %.3f mm, nmi %.4f, probe gain %.5f, %.2f s\n", int(seed), int(metric), e.mean_mm, r.nmi,
                        r.probe_gain, r.seconds);
        }
    }
}

// An fMRI map's space: a mean-EPI-like image (coarse 3 mm voxels, blurred 4 mm FWHM, T2*-like
// contrast: CSF bright, grey above white, fat suppressed) moved by a known rigid transform.
// Both metrics must recover it (the 1 mm T1 figure comes from bench/coregister_vs_elastix.sh).
TEST(Coregister, RecoversSyntheticEpiLikeMisalignmentWithBothMetrics) {
    const Head& h = head3mm();
    for (uint64_t seed : {21u, 22u}) {
        const SyntheticCoregCase c = make_synthetic_epi_case(h.t1, seed, 10, 15, 3.0, 4.0, 20.0);
        EXPECT_NEAR(c.moving.geom.spacing_mm.x(), 3.0, 1e-9);
        for (auto metric : {CoregParams::Metric::Mattes, CoregParams::Metric::Nmi}) {
            const auto [r, before, e] = recover(h, c, metric);
            EXPECT_LT(e.mean_mm, 1.0) << "seed " << seed << " metric " << int(metric) << " initial " << before.mean_mm;
            EXPECT_GT(before.mean_mm, 3.0) << "seed " << seed;
            EXPECT_GT(r.overlap, 0.9);
            std::printf("epi seed %d metric %d: error %.3f mm, nmi %.4f, probe gain %.5f\n", int(seed), int(metric), e.mean_mm, r.nmi,
                        r.probe_gain);
        }
    }
}

// A CT with bone (the skull, +1200 HU, where the T1 is dark just outside the brain; soft
// tissue 40 HU; air -1000 HU), moved by 8 deg / 11 mm. The T1's skull is as dark as air, so a
// metric sampled on the T1's head foreground never saw the bone: the gallery's CT ended 8.1 mm
// off that way. Sampled over the whole grid (the default) it is found.
TEST(Coregister, RecoversACtWithBone) {
    const Head& h = head3mm();
    const auto& g = h.t1.geom;
    std::vector<float> sorted(h.t1.voxels);
    std::nth_element(sorted.begin(), sorted.begin() + long(sorted.size() * 99 / 100), sorted.end());
    const float hi = sorted[sorted.size() * 99 / 100];
    // The brain dilated by 3 voxels (9 mm): skull and scalp lie in that shell.
    LabelVolume near = h.brain;
    for (int it = 0; it < 3; ++it) {
        LabelVolume grown = near;
        for (int k = 1; k + 1 < g.dims[2]; ++k)
            for (int j = 1; j + 1 < g.dims[1]; ++j)
                for (int i = 1; i + 1 < g.dims[0]; ++i)
                    if (!near.at(i, j, k) && (near.at(i - 1, j, k) || near.at(i + 1, j, k) || near.at(i, j - 1, k) ||
                                              near.at(i, j + 1, k) || near.at(i, j, k - 1) || near.at(i, j, k + 1)))
                        grown.voxels[g.linear(i, j, k)] = 1;
        near = std::move(grown);
    }
    Volume ct = h.t1;
    std::mt19937 rng(9);
    std::normal_distribution<float> noise(0.f, 10.f);
    for (size_t i = 0; i < ct.voxels.size(); ++i) {
        const bool bone = near.voxels[i] && !h.brain.voxels[i] && h.t1.voxels[i] < 0.25f * hi;
        const bool tissue = h.t1.voxels[i] > 0.12f * hi || h.brain.voxels[i];
        ct.voxels[i] = bone ? 1200.f + noise(rng) : tissue ? 40.f + noise(rng) : -1000.f;
    }
    const Eigen::Matrix4d T = euler_transform(Eigen::Vector3d(0.087, 0.0, 0.14), Eigen::Vector3d(6, -8, 5), g.center_world_mm());
    const Volume moving = resample_rigid(ct, T.inverse(), g, false, -1000.f);
    const CoregResult r = coregister(h.t1, moving, fast_params());
    const TransformError e = transform_error(T, r.T_moving_from_fixed, h.brain);
    EXPECT_LT(e.mean_mm, 1.0) << "max " << e.max_mm;
    EXPECT_GT(transform_error(T, r.T_initial, h.brain).mean_mm, 3.0);
    CoregParams nmi = fast_params();
    nmi.metric = CoregParams::Metric::Nmi;
    const TransformError en = transform_error(T, coregister(h.t1, moving, nmi).T_moving_from_fixed, h.brain);
    EXPECT_LT(en.mean_mm, 1.0) << "nmi, max " << en.max_mm;
    std::printf("ct with bone, nmi: %.3f mm\n", en.mean_mm);
    CoregParams masked = fast_params();
    masked.fixed_foreground_mask = true;
    masked.min_nmi = 1.0;
    masked.probe_mm = 0;
    try {
        const CoregResult m = coregister(h.t1, moving, masked);
        std::printf("ct with bone: %.3f mm sampled everywhere, %.3f mm on the T1's head mask\n", e.mean_mm,
                    transform_error(T, m.T_moving_from_fixed, h.brain).mean_mm);
    } catch (const std::exception& x) {
        std::printf("ct with bone: %.3f mm sampled everywhere; on the T1's head mask: %s\n", e.mean_mm, x.what());
    }
}

// --metric nmi (true NMI, Nelder-Mead) on the CT-like case: accurate, and at the NMI optimum
// (no probe gains). The optimum gate must still refuse a result that is not at the optimum:
// the same case stopped after a few evaluations of a single coarse level ends millimetres
// off, is returned as such with the gate off, and is refused with it on (the NMI gate is
// relaxed to 1 so that only the optimum gate can refuse it).
TEST(Coregister, NmiOnCtLikeIsAccurateAndTheOptimumGateRefusesAnUnconvergedResult) {
    const Head& h = head3mm();
    const SyntheticCoregCase c = make_synthetic_ct_case(h.t1, 11, 10, 15, 3.0, 4.0, 5.0);
    CoregParams p = fast_params();
    p.metric = CoregParams::Metric::Nmi;
    const CoregResult good = coregister(h.t1, c.moving, p);
    const double good_mm = transform_error(c.T_moving_from_fixed, good.T_moving_from_fixed, h.brain).mean_mm;
    EXPECT_LT(good_mm, 1.0);
    EXPECT_LE(good.probe_gain, p.max_probe_gain);
    EXPECT_EQ(good.levels.size(), 2u);

    CoregParams stopped = p;
    stopped.shrink = {2};
    stopped.smooth_mm = {3.0};
    stopped.iterations = {2};  // 8 evaluations: the simplex has barely been built
    stopped.min_nmi = 1.0;
    CoregParams no_gate = stopped;
    no_gate.probe_mm = 0;
    const CoregResult bad = coregister(h.t1, c.moving, no_gate);
    const double bad_mm = transform_error(c.T_moving_from_fixed, bad.T_moving_from_fixed, h.brain).mean_mm;
    EXPECT_GT(bad_mm, 2.0) << "the stopped run must be wrong for this test to mean anything";
    std::printf("nmi on ct: converged %.3f mm (probe gain %.5f), stopped %.3f mm\n", good_mm, good.probe_gain, bad_mm);
    try {
        coregister(h.t1, c.moving, stopped);
        ADD_FAILURE() << "an unconverged NMI result (" << bad_mm << " mm off) passed the optimum gate";
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("moving volume: the registration did not reach the NMI optimum"), std::string::npos)
            << e.what();
    }
}

// The file's convention: it maps FIXED world points to MOVING world points (ITK's resampling
// convention, docs/planning.md). The .tfm written for a known case is read back by ITK's
// transform reader, and its text (what 3D Slicer parses: Euler angles, translation and the
// centre as FixedParameters) gives the same point mapping by hand: p_moving = R (p - c) + c + t.
TEST(Coregister, TransformFileMapsFixedWorldToMovingWorld) {
    const Head& h = head3mm();
    const SyntheticCoregCase c = make_synthetic_ct_case(h.t1, 12, 10, 15, 3.0, 4.0, 5.0);
    const CoregResult r = coregister(h.t1, c.moving, fast_params());
    const fs::path d = temp_dir("cf_tfm_convention");
    save_transform(r.T_moving_from_fixed, r.center_world_mm, d / "ct_to_t1.tfm");
    const Eigen::Matrix4d T = load_transform(d / "ct_to_t1.tfm");  // ITK's TransformFileReader
    EXPECT_LT((T - r.T_moving_from_fixed).norm(), 1e-9);
    // Fixed world -> moving world: the truth maps the same way (moving(T p) = remap(fixed(p))).
    EXPECT_LT(transform_error(c.T_moving_from_fixed, T, h.brain).mean_mm, 1.0);
    EXPECT_GT(transform_error(c.T_moving_from_fixed.inverse(), T, h.brain).mean_mm, 5.0);
    // The text a third party reads.
    std::ifstream f(d / "ct_to_t1.tfm");
    std::string line, params, fixed;
    bool euler = false;
    while (std::getline(f, line)) {
        if (line == "Transform: Euler3DTransform_double_3_3") euler = true;
        if (line.rfind("Parameters: ", 0) == 0) params = line.substr(12);
        if (line.rfind("FixedParameters: ", 0) == 0) fixed = line.substr(17);
    }
    EXPECT_TRUE(euler);
    std::istringstream ps(params), fx(fixed);
    Eigen::Vector3d ang, tr, ctr;
    ps >> ang.x() >> ang.y() >> ang.z() >> tr.x() >> tr.y() >> tr.z();
    fx >> ctr.x() >> ctr.y() >> ctr.z();
    ASSERT_FALSE(ps.fail() || fx.fail()) << params << " / " << fixed;
    EXPECT_LT((ctr - r.center_world_mm).norm(), 1e-6);
    // ITK's Euler3D (ComputeZYX off): R = Rz Rx Ry.
    const Eigen::Matrix3d R = (Eigen::AngleAxisd(ang.z(), Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(ang.x(), Eigen::Vector3d::UnitX()) *
                               Eigen::AngleAxisd(ang.y(), Eigen::Vector3d::UnitY()))
                                  .toRotationMatrix();
    const Eigen::Vector3d p(10, -20, 30);
    const Eigen::Vector3d by_hand = R * (p - ctr) + ctr + tr;
    EXPECT_LT((by_hand - (T.topLeftCorner<3, 3>() * p + T.topRightCorner<3, 1>())).norm(), 1e-4);
    fs::remove_all(d);
}

TEST(Coregister, TransformFilesRoundTrip) {
    const fs::path d = temp_dir("cf_tfm");
    const Eigen::Vector3d c(1, -20, 30);
    const Eigen::Matrix4d T = euler_transform(Eigen::Vector3d(0.1, -0.05, 0.2), Eigen::Vector3d(5, -3, 7), c);
    EXPECT_NEAR((T.topLeftCorner<3, 3>().determinant()), 1.0, 1e-12);
    // The centre is fixed by the rotation part: T c = c + t.
    EXPECT_LT((T.topLeftCorner<3, 3>() * c + T.topRightCorner<3, 1>() - (c + Eigen::Vector3d(5, -3, 7))).norm(), 1e-9);
    for (const char* name : {"t.tfm", "t.h5"}) {
        save_transform(T, c, d / name);
        const Eigen::Matrix4d R = load_transform(d / name);
        EXPECT_LT((R - T).norm(), 1e-9) << name;
        EXPECT_FALSE(fs::exists(d / (std::string("t.part") + fs::path(name).extension().string())));
    }
    // The .tfm is ITK's text format that 3D Slicer reads.
    std::ifstream f(d / "t.tfm");
    std::string first;
    std::getline(f, first);
    EXPECT_EQ(first, "#Insight Transform File V1.0");
    // elastix's parameter file, same transform.
    {
        std::ofstream e(d / "TransformParameters.0.txt");
        e << "(Transform \"EulerTransform\")\n(NumberOfParameters 6)\n(TransformParameters 0.1 -0.05 0.2 5 -3 7)\n"
             "(CenterOfRotationPoint 1 -20 30)\n";
    }
    EXPECT_LT((load_transform(d / "TransformParameters.0.txt") - T).norm(), 1e-9);
    EXPECT_THROW(save_transform(T, c, d / "t.xyz"), InputError);
    EXPECT_THROW(load_transform(d / "missing.tfm"), InputError);
    {
        std::ofstream g(d / "garbage.tfm");
        g << "not a transform\n";
    }
    EXPECT_THROW(load_transform(d / "garbage.tfm"), InputError);
    fs::remove_all(d);
}

TEST(Coregister, RefusesEmptyAbsurdAndUnrelatedVolumes) {
    const Head& h = head3mm();
    CoregParams p = fast_params();
    // Empty (constant) moving volume.
    Volume flat = h.t1;
    std::fill(flat.voxels.begin(), flat.voxels.end(), 7.f);
    EXPECT_THROW(coregister(h.t1, flat, p), InputError);
    // Absurd overlap: a 12 mm slab of the head can hold only a small part of it.
    Volume slab;
    slab.geom = h.t1.geom;
    slab.geom.dims[2] = 4;
    slab.voxels.assign(h.t1.voxels.begin(), h.t1.voxels.begin() + long(slab.geom.voxel_count()));
    const size_t zoff = size_t(h.t1.geom.dims[0]) * h.t1.geom.dims[1] * size_t(h.t1.geom.dims[2] / 2);
    std::copy(h.t1.voxels.begin() + long(zoff), h.t1.voxels.begin() + long(zoff + slab.geom.voxel_count()), slab.voxels.begin());
    slab.geom.origin_mm = h.t1.geom.world_from_index(Eigen::Vector3d(0, 0, h.t1.geom.dims[2] / 2));
    try {
        coregister(h.t1, slab, p);
        ADD_FAILURE() << "a slab was accepted";
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("overlap"), std::string::npos) << e.what();
    }
    // Unrelated content (noise blobs, "another patient's" nothing in common): the NMI gate.
    Volume noise = h.t1;
    std::mt19937 rng(3);
    std::uniform_real_distribution<float> u(0.f, 100.f);
    for (auto& v : noise.voxels) v = u(rng);
    EXPECT_THROW(coregister(h.t1, noise, p), InputError);
    CoregParams bad = p;
    bad.shrink = {2, 1, 1};
    EXPECT_THROW(coregister(h.t1, h.t1, bad), InputError);
}

TEST(Fmri, ThresholdKeepsClustersAboveSize) {
    Volume s;
    s.geom.dims = {30, 30, 30};
    s.geom.spacing_mm = Eigen::Vector3d(2, 2, 2);
    s.voxels.assign(s.geom.voxel_count(), 0.f);
    auto blob = [&](int ci, int cj, int ck, int r, float v) {
        for (int k = 0; k < 30; ++k)
            for (int j = 0; j < 30; ++j)
                for (int i = 0; i < 30; ++i)
                    if ((i - ci) * (i - ci) + (j - cj) * (j - cj) + (k - ck) * (k - ck) <= r * r) s.voxels[s.geom.linear(i, j, k)] = v;
    };
    blob(8, 8, 8, 4, 5.0f);     // big, active
    blob(22, 22, 22, 1, 6.0f);  // 7 voxels: below the cluster size
    blob(22, 8, 8, 4, 2.0f);    // big, below threshold
    blob(8, 22, 22, 3, -5.0f);  // deactivation
    FmriParams p;
    p.threshold = 3.1;
    p.min_cluster_voxels = 10;
    int n = 0;
    const Volume t = threshold_activation(s, p, &n);
    EXPECT_EQ(n, 1);
    EXPECT_EQ(t.voxels[s.geom.linear(8, 8, 8)], 5.0f);
    EXPECT_EQ(t.voxels[s.geom.linear(22, 22, 22)], 0.0f);
    EXPECT_EQ(t.voxels[s.geom.linear(22, 8, 8)], 0.0f);
    EXPECT_EQ(t.voxels[s.geom.linear(8, 22, 22)], 0.0f);
    p.two_sided = true;
    threshold_activation(s, p, &n);
    EXPECT_EQ(n, 2);
    p.threshold = -1;
    EXPECT_THROW(threshold_activation(s, p), InputError);
}
