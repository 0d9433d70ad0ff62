// Skull stripping (in cf_core_tests): accuracy on the shipped real head against its FreeSurfer brain mask, the
// anisotropic path, the check image, cancellation and every bad-input path.
// The target (Dice >= 0.95 at 1 mm) runs in the release build; under the sanitizers it
// is skipped (minutes at -O1) and the same head at 2 mm stands in with a looser bound. Figures on
// all heads come from bench/skullstrip_eval.sh (docs/skull-stripping.md).
#include <gtest/gtest.h>

#include <filesystem>
#include <random>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/skull_strip.hpp"
#include "cortexfuse/core/volume.hpp"
#include "../sanitized.hpp"

namespace fs = std::filesystem;
using namespace cf;

namespace {

struct Head {
    Volume t1;
    LabelVolume reference;
};

using cf::test::kSanitized;

// The shipped MNE head (1 mm, 256^3) and its FreeSurfer mask (loaded once).
const Head& head_1mm() {
    static const Head h{load_volume(fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz"),
                        load_mask(fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz")};
    return h;
}

// The same on a 2 mm grid.
const Head& head_2mm() {
    static const Head h = [] {
        const Head& full = head_1mm();
        const VolumeGeometry g = isotropic_grid(full.t1.geom, 2.0);
        return Head{resample(full.t1, g, 0.f), resample_nearest(full.reference, g)};
    }();
    return h;
}

Volume blank(std::array<int, 3> dims, double spacing_mm, float value) {
    Volume v;
    v.geom.dims = dims;
    v.geom.spacing_mm = Eigen::Vector3d::Constant(spacing_mm);
    v.voxels.assign(v.geom.voxel_count(), value);
    return v;
}

std::string error_of(const Volume& v, const SkullStripParams& p = {}) {
    try {
        skull_strip(v, p);
    } catch (const InputError& e) {
        return e.what();
    }
    return "";
}

}  // namespace

TEST(SkullStrip, RealHeadMatchesFreeSurferMask) {
    if (kSanitized) GTEST_SKIP() << "1 mm head takes minutes under the sanitizers; RealHeadAt2mm stands in";
    const Head& h = head_1mm();
    SkullStripInfo info;
    const LabelVolume mask = skull_strip(h.t1, {}, nullptr, &info);
    ASSERT_TRUE(mask.geom.same_grid(h.t1.geom));
    const double d = dice(mask, h.reference);
    RecordProperty("dice_1mm", std::to_string(d));
    EXPECT_GE(d, 0.95) << "brain " << info.brain_ml << " mL";
    // The FreeSurfer mask holds 1318 mL; a mask that only matched by swallowing the head would not.
    EXPECT_NEAR(info.brain_ml, 1318.0, 150.0);
    EXPECT_LT(info.brain_ml, 0.7 * info.head_ml);
}

TEST(SkullStrip, RealHeadAt2mm) {
    // Coarser grid: the morphology works in whole voxels of 2 mm, so the bound is looser.
    const Head& h = head_2mm();
    SkullStripInfo info;
    const LabelVolume mask = skull_strip(h.t1, {}, nullptr, &info);
    ASSERT_TRUE(mask.geom.same_grid(h.t1.geom));
    const double d = dice(mask, h.reference);
    RecordProperty("dice_2mm", std::to_string(d));
    EXPECT_GE(d, 0.90) << "brain " << info.brain_ml << " mL";  // measured 0.914
    EXPECT_LT(info.brain_ml, 0.7 * info.head_ml);
}

TEST(SkullStrip, ThickSliceDicomSeriesStaysOffTheScalp) {
    // The real sagittal T1 series (1 x 1 x 4.8 mm, neck and face in the field of view): at BET's
    // published f = 0.5 the surface model passed the partial-volume-grey skull and ended on the
    // scalp over the vertex (a 1984 mL "brain"); the surface must now enclose a plausible volume
    // and the mask must be a brain-sized one.
    const Volume v = load_volume(fs::path(CF_TEST_DATA_DIR) / "dicom_mr_sag");
    SkullStripInfo info;
    const LabelVolume mask = skull_strip(v, {}, nullptr, &info);
    ASSERT_TRUE(mask.geom.same_grid(v.geom));
    EXPECT_TRUE(info.envelope_used);
    EXPECT_GT(info.working_spacing_mm, 0.0);
    EXPECT_LT(info.envelope_ml, 2300.0);
    EXPECT_GT(info.brain_ml, 1100.0);
    EXPECT_LT(info.brain_ml, 1650.0);
    // Nothing of the mask in the top 4 mm of the head (scalp and skull over the vertex).
    const Eigen::Affine3d world = v.geom.world_from_index();
    double top_head = -1e9, top_mask = -1e9;
    for (int k = 0; k < v.geom.dims[2]; ++k)
        for (int j = 0; j < v.geom.dims[1]; ++j)
            for (int i = 0; i < v.geom.dims[0]; ++i) {
                const size_t li = v.geom.linear(i, j, k);
                const double s = (world * Eigen::Vector3d(i, j, k)).z();  // LPS: +S is superior
                if (v.voxels[li] > info.t_background) top_head = std::max(top_head, s);
                if (mask.voxels[li]) top_mask = std::max(top_mask, s);
            }
    RecordProperty("dicom_top_gap_mm", std::to_string(top_head - top_mask));
    EXPECT_LT(top_mask, top_head - 4.0) << "mask reaches the scalp over the vertex (head top " << top_head
                                        << " mm, mask top " << top_mask << " mm)";
}

TEST(SkullStrip, IntracranialTargetIsLargerThanBrain) {
    const Head& h = head_2mm();
    SkullStripParams p;
    SkullStripInfo brain, ic;
    const LabelVolume b = skull_strip(h.t1, p, nullptr, &brain);
    p.target = SkullStripTarget::intracranial;
    const LabelVolume i = skull_strip(h.t1, p, nullptr, &ic);
    EXPECT_GT(ic.brain_ml, brain.brain_ml + 20.0);
    // The intracranial mask contains (nearly all of) the brain mask.
    size_t in_brain = 0, in_both = 0;
    for (size_t k = 0; k < b.voxels.size(); ++k) {
        in_brain += b.voxels[k] != 0;
        in_both += b.voxels[k] && i.voxels[k];
    }
    EXPECT_GE(double(in_both), 0.98 * double(in_brain));
}

TEST(SkullStrip, AnisotropicScanGivesMaskOnItsOwnGrid) {
    // Thick slices (as a 2D sagittal DICOM series): the strip runs on an isotropic copy and the
    // mask comes back on the input grid.
    const Head& h = head_2mm();
    VolumeGeometry g = h.t1.geom;
    g.spacing_mm = Eigen::Vector3d(2.0, 2.0, 5.0);
    g.dims[2] = int(h.t1.geom.dims[2] * 2.0 / 5.0);
    const Volume thick = resample(h.t1, g, 0.f);
    SkullStripInfo info;
    const LabelVolume mask = skull_strip(thick, {}, nullptr, &info);
    ASSERT_TRUE(mask.geom.same_grid(thick.geom));
    EXPECT_GT(info.working_spacing_mm, 0.0);
    EXPECT_GE(dice(mask, resample_nearest(h.reference, g)), 0.85)
        << "brain " << info.brain_ml << " mL, surface " << info.envelope_ml << " mL";
}

TEST(SkullStrip, CheckImageIsWrittenAndGridMismatchRefused) {
    const Head& h = head_2mm();
    const auto dir = fs::temp_directory_path() / ("cf_skullstrip_" + std::to_string(::getpid()));
    fs::create_directories(dir);
    const auto png = dir / "check.png";
    write_mask_check_png(h.t1, h.reference, png, &h.reference);
    EXPECT_GT(fs::file_size(png), 10'000u);
    LabelVolume other = h.reference;
    other.geom.dims[0] -= 1;
    other.voxels.resize(other.geom.voxel_count());
    EXPECT_THROW(write_mask_check_png(h.t1, other, dir / "bad.png"), InputError);
    EXPECT_FALSE(fs::exists(dir / "bad.png"));
    fs::remove_all(dir);
}

TEST(SkullStrip, CancelStops) {
    CancelToken cancel;
    cancel.cancel();
    Progress progress;
    progress.cancel = &cancel;
    EXPECT_THROW(skull_strip(head_2mm().t1, {}, &progress), Cancelled);
}

TEST(SkullStrip, EmptyVolumeRefused) {
    Volume v;
    EXPECT_NE(error_of(v).find("do not match"), std::string::npos) << error_of(v);
}

TEST(SkullStrip, ConstantVolumeRefused) {
    const std::string e = error_of(blank({64, 64, 64}, 2.0, 100.f));
    EXPECT_NE(e.find("constant"), std::string::npos) << e;
}

TEST(SkullStrip, TinyVolumeRefused) {
    const std::string e = error_of(blank({4, 64, 64}, 2.0, 100.f));
    EXPECT_NE(e.find("too small"), std::string::npos) << e;
}

TEST(SkullStrip, NonFiniteVoxelsRefused) {
    Volume v = head_2mm().t1;
    v.voxels[v.voxels.size() / 2] = std::numeric_limits<float>::quiet_NaN();
    const std::string e = error_of(v);
    EXPECT_NE(e.find("NaN"), std::string::npos) << e;
}

TEST(SkullStrip, NoHeadRefused) {
    // Pure noise: nothing head-like anywhere.
    Volume noise = blank({80, 80, 80}, 2.0, 0.f);
    std::mt19937 rng(7);
    std::uniform_real_distribution<float> u(0.f, 100.f);
    for (float& x : noise.voxels) x = u(rng);
    const std::string e1 = error_of(noise);
    EXPECT_FALSE(e1.empty()) << "noise was accepted as a head";
    EXPECT_NE(e1.find("skull strip"), std::string::npos) << e1;

    // A small bright ball (a phantom bottle, 65 mL): too small to be a head.
    Volume ball = blank({80, 80, 80}, 2.0, 0.f);
    for (int k = 0; k < 80; ++k)
        for (int j = 0; j < 80; ++j)
            for (int i = 0; i < 80; ++i)
                if ((i - 40) * (i - 40) + (j - 40) * (j - 40) + (k - 40) * (k - 40) < 12 * 12)
                    ball.voxels[ball.geom.linear(i, j, k)] = 500.f;
    const std::string e2 = error_of(ball);
    EXPECT_NE(e2.find("no head"), std::string::npos) << e2;
}

TEST(SkullStrip, ParametersOutOfRangeRefused) {
    SkullStripParams p;
    p.erode_mm = -1.0;
    EXPECT_NE(error_of(head_2mm().t1, p).find("erode_mm"), std::string::npos);
    p = {};
    p.bet_fraction = 2.0;
    EXPECT_NE(error_of(head_2mm().t1, p).find("bet_fraction"), std::string::npos);
}
