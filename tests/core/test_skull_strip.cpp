// Skull stripping (in cf_core_tests): accuracy on the shipped real head against its FreeSurfer brain mask, the
// anisotropic path, the check image, cancellation and every bad-input path.
// The target (Dice >= 0.95 at 1 mm) runs in the release build; under the sanitizers it
// is skipped (minutes at -O1) and the same head at 2 mm stands in with a looser bound. Figures on
// all heads come from bench/skullstrip_eval.sh (docs/skull-stripping.md).
#include <gtest/gtest.h>

#include <filesystem>
#include <random>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/progress.hpp"
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

namespace {

// The voxel axis closest to world axis w (LPS) and whether increasing index goes towards +w.
std::pair<int, bool> axis_towards(const VolumeGeometry& g, int w) {
    int best = 0;
    for (int a = 1; a < 3; ++a)
        if (std::abs(g.direction(w, a)) > std::abs(g.direction(w, best))) best = a;
    return {best, g.direction(w, best) > 0};
}

// Voxel offsets within a ball of radius r_mm.
std::vector<std::array<int, 3>> ball(const VolumeGeometry& g, double r_mm) {
    std::vector<std::array<int, 3>> out;
    std::array<int, 3> n{};
    for (int a = 0; a < 3; ++a) n[a] = int(std::ceil(r_mm / g.spacing_mm[a]));
    for (int k = -n[2]; k <= n[2]; ++k)
        for (int j = -n[1]; j <= n[1]; ++j)
            for (int i = -n[0]; i <= n[0]; ++i)
                if (std::pow(i * g.spacing_mm[0], 2) + std::pow(j * g.spacing_mm[1], 2) + std::pow(k * g.spacing_mm[2], 2) <=
                    r_mm * r_mm)
                    out.push_back({i, j, k});
    return out;
}

// What the ray caster would show through a mask, measured on the upper half of a head:
// `outside_ml`, the mask's volume farther than `far_mm` outside the reference mask; and for
// orthographic rays along the voxel axes from the left, the right and the top, the share of
// first opaque voxels (above 0.3 of the in-mask 99.5th percentile: the cortex_t1 preset's
// opacity ramp) that lie farther than `far_mm` outside the reference: extra-axial layers, not
// cortex, on the picture.
struct ConvexityCheck {
    double outside_ml = 0;
    std::array<double, 3> first_hit_outside{0, 0, 0};  // left, right, top
};

ConvexityCheck convexity_check(const Volume& v, const LabelVolume& mask, const LabelVolume& ref, double far_mm) {
    const VolumeGeometry& g = v.geom;
    const auto [lr, lr_up] = axis_towards(g, 0);  // LPS +x: patient left
    const auto [si, si_up] = axis_towards(g, 2);  // LPS +z: superior
    // Upper half: above the reference's centre along the superior axis.
    double centre = 0;
    size_t n_ref = 0;
    std::vector<float> inside;
    for (int k = 0; k < g.dims[2]; ++k)
        for (int j = 0; j < g.dims[1]; ++j)
            for (int i = 0; i < g.dims[0]; ++i) {
                const size_t li = g.linear(i, j, k);
                const std::array<int, 3> x{i, j, k};
                if (ref.voxels[li]) {
                    centre += x[si];
                    ++n_ref;
                }
                if (mask.voxels[li] && v.voxels[li] != 0.f) inside.push_back(v.voxels[li]);
            }
    centre /= double(std::max<size_t>(1, n_ref));
    const size_t q = size_t(0.995 * double(inside.size() - 1));
    std::nth_element(inside.begin(), inside.begin() + long(q), inside.end());
    const float opaque = 0.3f * inside[q];
    auto upper = [&](const std::array<int, 3>& x) { return si_up ? x[si] >= centre : x[si] <= centre; };
    const auto offsets = ball(g, far_mm);
    auto far_outside = [&](const std::array<int, 3>& x) {
        if (ref.voxels[g.linear(x[0], x[1], x[2])]) return false;
        for (const auto& o : offsets) {
            const int a = x[0] + o[0], b = x[1] + o[1], c = x[2] + o[2];
            if (a < 0 || b < 0 || c < 0 || a >= g.dims[0] || b >= g.dims[1] || c >= g.dims[2]) continue;
            if (ref.voxels[g.linear(a, b, c)]) return false;
        }
        return true;
    };
    ConvexityCheck out;
    size_t n_far = 0;
    for (int k = 0; k < g.dims[2]; ++k)
        for (int j = 0; j < g.dims[1]; ++j)
            for (int i = 0; i < g.dims[0]; ++i)
                if (mask.voxels[g.linear(i, j, k)] && upper({i, j, k}) && far_outside({i, j, k})) ++n_far;
    out.outside_ml = double(n_far) * g.spacing_mm.prod() / 1000.0;
    // Rays: from the left and the right along the left-right axis, from the top down.
    const std::array<std::pair<int, bool>, 3> views{{{lr, !lr_up}, {lr, lr_up}, {si, !si_up}}};
    for (int view = 0; view < 3; ++view) {
        const int ax = views[size_t(view)].first;
        const bool from_high = !views[size_t(view)].second;  // rays start at the high-index end
        const int u = (ax + 1) % 3, w = (ax + 2) % 3;
        size_t hits = 0, far = 0;
        for (int b = 0; b < g.dims[w]; ++b)
            for (int a = 0; a < g.dims[u]; ++a)
                for (int s = 0; s < g.dims[ax]; ++s) {
                    std::array<int, 3> x{};
                    x[ax] = from_high ? g.dims[ax] - 1 - s : s;
                    x[u] = a;
                    x[w] = b;
                    const size_t li = g.linear(x[0], x[1], x[2]);
                    if (!mask.voxels[li] || v.voxels[li] <= opaque) continue;
                    if (view == 2 || upper(x)) {  // side views: the upper half of the picture
                        ++hits;
                        far += far_outside(x);
                    }
                    break;
                }
        out.first_hit_outside[size_t(view)] = double(far) / double(std::max<size_t>(1, hits));
    }
    return out;
}

}  // namespace

TEST(SkullStrip, Seg3dConvexityShowsCortexNotExtraAxialLayers) {
    // seg3d (a clinical T1 with subdural grid electrodes): between its cortex and the skull lie
    // grey layers (dura, a CSF space greyed by partial volume) and a thin skull with bright fatty
    // marrow. The surface model ended on the outer table, its interior was taken as brain over
    // the convexity, and the CSF growth wrapped round the marrow into the dark bone beyond:
    // rendered through the mask, smooth sheets covered the cortex (docs/registration.md, "Why
    // seg3d case 0000 fails"). Measured before the support's gate and the geodesic CSF growth:
    // 32.7 mL of the upper half more than 3 mm outside Seg3D's mask; first hits from the left,
    // right and top 39 / 35 / 25 % outside it. After: 7.4 mL; 7.5 / 13.8 / 2.7 %.
    if (kSanitized) GTEST_SKIP() << "a 1 mm head takes minutes under the sanitizers";
    const Volume v = load_volume(fs::path(CF_TEST_DATA_DIR) / "t1_head_seg3d.nii.gz");
    const LabelVolume ref = load_mask(fs::path(CF_TEST_DATA_DIR) / "brainmask_seg3d_intracranial.nii.gz");
    SkullStripInfo info;
    const LabelVolume mask = skull_strip(v, {}, nullptr, &info);
    ASSERT_TRUE(mask.geom.same_grid(ref.geom));
    const double d = dice(mask, ref);
    RecordProperty("dice_seg3d", std::to_string(d));
    EXPECT_GE(d, 0.92) << "brain " << info.brain_ml << " mL";  // the target; 0.928 measured
    const ConvexityCheck c = convexity_check(v, mask, ref, 3.0);
    RecordProperty("seg3d_outside_ml", std::to_string(c.outside_ml));
    EXPECT_LT(c.outside_ml, 15.0) << "extra-axial tissue taken over the convexity";
    const char* names[3] = {"left", "right", "top"};
    for (int view = 0; view < 3; ++view)
        EXPECT_LT(c.first_hit_outside[size_t(view)], 0.2)
            << "seen from the " << names[view] << ", " << 100 * c.first_hit_outside[size_t(view)]
            << " % of the upper convexity's first opaque voxels lie more than 3 mm outside the reference";
}

TEST(SkullStrip, CoarseGridMaskEdgeLiesInTheIntensityValley) {
    // On a 2 mm grid partial volume greys the CSF over the cortex; a mask edge in those grey
    // voxels is opaque to the ray caster, which then shows the mask's voxel staircase instead of
    // the cortex (the MNI152 2 mm head). The edge is moved downhill into the valley between brain
    // and skull: measured on this head, upper-half edge voxels above 0.3 of the in-mask 99.5th
    // percentile 58 % before, 15 % after (MNI152 2 mm: 71 -> 7 %).
    const Head& h = head_2mm();
    const LabelVolume mask = skull_strip(h.t1, {});
    const VolumeGeometry& g = mask.geom;
    const auto [si, si_up] = axis_towards(g, 2);
    std::vector<float> inside;
    double centre = 0;
    size_t n = 0;
    for (int k = 0; k < g.dims[2]; ++k)
        for (int j = 0; j < g.dims[1]; ++j)
            for (int i = 0; i < g.dims[0]; ++i) {
                const size_t li = g.linear(i, j, k);
                if (!mask.voxels[li]) continue;
                centre += std::array<int, 3>{i, j, k}[si];
                ++n;
                if (h.t1.voxels[li] != 0.f) inside.push_back(h.t1.voxels[li]);
            }
    ASSERT_GT(n, 0u);
    centre /= double(n);
    const size_t q = size_t(0.995 * double(inside.size() - 1));
    std::nth_element(inside.begin(), inside.begin() + long(q), inside.end());
    const float opaque = 0.3f * inside[q];
    size_t edge = 0, opaque_edge = 0;
    for (int k = 1; k + 1 < g.dims[2]; ++k)
        for (int j = 1; j + 1 < g.dims[1]; ++j)
            for (int i = 1; i + 1 < g.dims[0]; ++i) {
                const size_t li = g.linear(i, j, k);
                const std::array<int, 3> x{i, j, k};
                if (!mask.voxels[li] || (si_up ? x[si] < centre : x[si] > centre)) continue;
                const bool on_edge = !mask.voxels[g.linear(i - 1, j, k)] || !mask.voxels[g.linear(i + 1, j, k)] ||
                                     !mask.voxels[g.linear(i, j - 1, k)] || !mask.voxels[g.linear(i, j + 1, k)] ||
                                     !mask.voxels[g.linear(i, j, k - 1)] || !mask.voxels[g.linear(i, j, k + 1)];
                if (!on_edge) continue;
                ++edge;
                opaque_edge += h.t1.voxels[li] > opaque;
            }
    const double share = double(opaque_edge) / double(std::max<size_t>(1, edge));
    RecordProperty("opaque_edge_2mm", std::to_string(share));
    EXPECT_LT(share, 0.3) << edge << " upper edge voxels, " << opaque_edge << " opaque";
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
    // Refused before any work: no stage reported (the surface model used to evolve over it first).
    std::vector<std::string> stages;
    Progress progress;
    progress.report = [&](const std::string& stage, double) { stages.push_back(stage); };
    EXPECT_THROW(skull_strip(blank({64, 64, 64}, 2.0, 100.f), {}, &progress), InputError);
    EXPECT_TRUE(stages.empty()) << stages.front();
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
    p = {};
    p.support_gate_mm = 40.0;
    EXPECT_NE(error_of(head_2mm().t1, p).find("support_gate_mm"), std::string::npos);
    p = {};
    p.valley_snap_mm = -1.0;
    EXPECT_NE(error_of(head_2mm().t1, p).find("valley_snap_mm"), std::string::npos);
}
