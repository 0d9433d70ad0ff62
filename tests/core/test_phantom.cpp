// The phantom generator and its software rasteriser.
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <iterator>
#include <nlohmann/json.hpp>
#include <opencv2/imgproc.hpp>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/rasterizer.hpp"
#include "cortexfuse/core/roi.hpp"

namespace fs = std::filesystem;
using namespace cf;

namespace {

fs::path tmpdir(const std::string& name) {
    auto p = fs::temp_directory_path() / ("cf_test_phantom_" + name + "_" + std::to_string(::getpid()));
    fs::remove_all(p);
    fs::create_directories(p);
    return p;
}

std::string slurp(const fs::path& p) {
    std::ifstream f(p, std::ios::binary);
    return std::string(std::istreambuf_iterator<char>(f), {});
}

const fs::path kVolume = fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz";
const fs::path kMask = fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz";

Intrinsics small_camera() {
    Intrinsics K;
    K.width = 64;
    K.height = 48;
    K.fx = K.fy = 100;
    K.cx = 31.5;
    K.cy = 23.5;
    return K;
}

}  // namespace

// ---------------------------------------------------------------- rasteriser
TEST(Rasterizer, SquareFacingCameraHasExactDepthAndArea) {
    // A 20 mm square at z = 100 mm: 20 px wide at f = 100 px.
    RasterMesh m;
    m.vertices = {{-10, -10, 100}, {10, -10, 100}, {10, 10, 100}, {-10, 10, 100}};
    m.triangles = {{0, 1, 2}, {0, 2, 3}};
    const Intrinsics K = small_camera();
    const RasterBuffers rb = rasterize(m, K, Pose::Identity());
    int hits = 0;
    for (int v = 0; v < K.height; ++v)
        for (int u = 0; u < K.width; ++u)
            if (rb.hit(u, v)) {
                ++hits;
                EXPECT_NEAR(rb.depth_mm[rb.index(u, v)], 100.f, 1e-3f);
                // The interpolated point is where the pixel's ray meets the plane.
                const Eigen::Vector3f p = interpolate_at(rb, m.triangles, m.vertices, u, v, Eigen::Vector3f::Zero());
                EXPECT_NEAR(p.x(), (u - K.cx) / K.fx * 100, 1e-3);
                EXPECT_NEAR(p.y(), (v - K.cy) / K.fy * 100, 1e-3);
            }
    EXPECT_NEAR(hits, 20 * 20, 2 * 20 + 2 * 20);  // the area, up to edge pixels
    EXPECT_FALSE(rb.hit(0, 0));
    EXPECT_TRUE(std::isinf(rb.depth_mm[0]));
}

TEST(Rasterizer, CubeNearFaceWinsAndPerspectiveIsCorrect) {
    // Unit-ish cube (20 mm) centred at z = 100, seen along +z: the visible face is z = 90.
    RasterMesh m;
    for (int i = 0; i < 8; ++i)
        m.vertices.emplace_back((i & 1) ? 10.f : -10.f, (i & 2) ? 10.f : -10.f, (i & 4) ? 110.f : 90.f);
    const int f[6][4] = {{0, 1, 3, 2}, {4, 5, 7, 6}, {0, 1, 5, 4}, {2, 3, 7, 6}, {0, 2, 6, 4}, {1, 3, 7, 5}};
    for (const auto& q : f) {
        m.triangles.emplace_back(q[0], q[1], q[2]);
        m.triangles.emplace_back(q[0], q[2], q[3]);
    }
    const Intrinsics K = small_camera();
    const RasterBuffers rb = rasterize(m, K, Pose::Identity());
    const int u = 31, v = 23;
    ASSERT_TRUE(rb.hit(u, v));
    EXPECT_NEAR(rb.depth_mm[rb.index(u, v)], 90.f, 1e-3f);
    // Tilted plane: perspective-correct interpolation of z along a slanted quad.
    RasterMesh s;
    s.vertices = {{-30, -30, 60}, {30, -30, 60}, {30, 30, 140}, {-30, 30, 140}};
    s.triangles = {{0, 1, 2}, {0, 2, 3}};
    const RasterBuffers rs = rasterize(s, K, Pose::Identity());
    for (int vv = 0; vv < K.height; vv += 5)
        for (int uu = 0; uu < K.width; uu += 5)
            if (rs.hit(uu, vv)) {
                const Eigen::Vector3f p = interpolate_at(rs, s.triangles, s.vertices, uu, vv, Eigen::Vector3f::Zero());
                const auto px = project_camera(K, p.cast<double>());
                ASSERT_TRUE(px);
                EXPECT_NEAR(px->x(), uu, 1e-2);
                EXPECT_NEAR(px->y(), vv, 1e-2);
                EXPECT_NEAR(rs.depth_mm[rs.index(uu, vv)], p.z(), 1e-2);
            }
}

// ---------------------------------------------------------------- generator
class Phantom : public ::testing::Test {
protected:
    static void SetUpTestSuite() {
        const Volume t1 = load_volume(kVolume);
        const LabelVolume mask = load_mask(kMask);
        surface_ = new PhantomSurface(build_phantom_surface(t1, mask));
    }
    static void TearDownTestSuite() {
        delete surface_;
        surface_ = nullptr;
    }
    static PhantomSurface* surface_;
};
PhantomSurface* Phantom::surface_ = nullptr;

TEST_F(Phantom, SurfaceIsABrainInWorldLps) {
    const auto& s = *surface_;
    ASSERT_GT(s.mesh.triangles.size(), 50000u);
    Eigen::AlignedBox3f box;
    for (const auto& v : s.mesh.vertices) box.extend(v);
    const Eigen::Vector3f ext = box.sizes();
    // An adult brain: ~140 x 170 x 110 mm (LR, AP, SI).
    EXPECT_GT(ext.x(), 110);
    EXPECT_LT(ext.x(), 180);
    EXPECT_GT(ext.y(), 140);
    EXPECT_LT(ext.y(), 210);
    EXPECT_GT(ext.z(), 80);
    EXPECT_LT(ext.z(), 150);
    // Outward normals at the top of the brain point superior (+z in LPS).
    size_t top = 0;
    for (size_t i = 0; i < s.mesh.vertices.size(); ++i)
        if (s.mesh.vertices[i].z() > box.max().z() - 3 && s.smooth_normals[i].z() > 0.5f) ++top;
    EXPECT_GT(top, 20u);
}

TEST_F(Phantom, SameSeedSameCase) {
    PhantomParams p;
    p.seed = 7;
    p.gauze_prob = p.blood_prob = 1.0;
    const PhantomCase a = generate_phantom_case(*surface_, p, 3);
    const PhantomCase b = generate_phantom_case(*surface_, p, 3);
    ASSERT_EQ(a.photo_bgr.size(), b.photo_bgr.size());
    EXPECT_EQ(cv::norm(a.photo_bgr, b.photo_bgr, cv::NORM_INF), 0.0);
    EXPECT_EQ(a.T_camera_from_world, b.T_camera_from_world);
    ASSERT_EQ(a.landmarks.size(), b.landmarks.size());
    for (size_t i = 0; i < a.landmarks.size(); ++i) EXPECT_EQ(a.landmarks[i].pixel, b.landmarks[i].pixel);
    const PhantomCase c = generate_phantom_case(*surface_, p, 4);
    EXPECT_NE(a.T_camera_from_world, c.T_camera_from_world);
}

// The surgical field around the opening (towels, burr holes, scalp clips, the reflected dura, the
// arachnoid's veil) comes from a random
// stream of its own: adding it left every pose of a seed as it was, and the notes say what a
// photo shows.
TEST_F(Phantom, SurgicalFieldIsNotedAndLeavesThePoseAlone) {
    PhantomParams p;
    p.seed = 5;
    p.dslr_fraction = 0.0;
    int with_clips = 0;
    for (int idx = 0; idx < 6; ++idx) {
        SCOPED_TRACE("case " + std::to_string(idx));
        const PhantomCase pc = generate_phantom_case(*surface_, p, idx);
        auto count = [&](const std::string& key) {
            const size_t at = pc.notes.find(" " + key + "=");
            EXPECT_NE(at, std::string::npos) << pc.notes;
            return at == std::string::npos ? -1 : std::stoi(pc.notes.substr(at + key.size() + 2));
        };
        const int towels = count("towels"), burr = count("burr_holes"), clips = count("clips");
        EXPECT_GE(towels, 3);
        EXPECT_LE(towels, 5);
        EXPECT_GE(burr, 1);
        EXPECT_LE(burr, 4);
        EXPECT_TRUE(clips == 0 || clips >= 4) << clips;
        EXPECT_NE(pc.notes.find(" dural_flap="), std::string::npos) << pc.notes;
        EXPECT_NE(pc.notes.find(" arachnoid_veil="), std::string::npos) << pc.notes;
        with_clips += clips > 0;
    }
    EXPECT_GT(with_clips, 0);
    EXPECT_LT(with_clips, 6);
    // Seed 5, case 0 before the field was added (generated at a63ce78, release build). Within
    // 0.1 mm: the sanitized build (-O1, no -march=native) builds the brain surface with other
    // rounding and lands 0.01 mm away; a draw taken from the case's main stream would move the
    // camera by centimetres (distance 200-450 mm, tilt, roll).
    const PhantomCase c0 = generate_phantom_case(*surface_, p, 0);
    const Eigen::Vector3d t = c0.T_camera_from_world.topRightCorner<3, 1>();
    EXPECT_NEAR(t.x(), -7.162929581063061, 0.1);
    EXPECT_NEAR(t.y(), -12.574572239655012, 0.1);
    EXPECT_NEAR(t.z(), 350.9517425323447, 0.1);
}

// The case's notes give `key` (" name=") a value above 0, and its pose, landmarks, ROI and
// targets are those of `plain` (what a stream of its own must leave alone).
static void expect_noted_and_case_alone(const PhantomCase& c, const PhantomCase& plain, const std::string& key) {
    const size_t at = c.notes.find(key);
    ASSERT_NE(at, std::string::npos) << c.notes;
    EXPECT_GT(std::stod(c.notes.substr(at + key.size())), 0.0) << c.notes;
    EXPECT_TRUE(c.T_camera_from_world.isApprox(plain.T_camera_from_world, 0));
    ASSERT_EQ(c.landmarks.size(), plain.landmarks.size());
    for (size_t k = 0; k < c.landmarks.size(); ++k) EXPECT_EQ(c.landmarks[k].pixel, plain.landmarks[k].pixel);
    EXPECT_EQ(c.roi_points, plain.roi_points);
    EXPECT_EQ(c.targets_world_mm, plain.targets_world_mm);
}

// The same case without and with one part of the look (`part`, a flag of PhantomParams), with
// neither gauze nor blood on a small photo: {without, with}.
static std::pair<PhantomCase, PhantomCase> case_without_and_with(const PhantomSurface& surface, PhantomParams p,
                                                                 bool PhantomParams::*part, int index) {
    p.dslr_fraction = 0.0;
    p.gauze_prob = p.blood_prob = 0.0;
    p.*part = false;
    PhantomCase without = generate_phantom_case(surface, p, index);
    p.*part = true;
    PhantomCase with = generate_phantom_case(surface, p, index);
    return {std::move(without), std::move(with)};
}

// The case's ROI polygon filled (255) on a mask of the photo's size.
static cv::Mat roi_mask_of(const PhantomCase& c) {
    cv::Mat mask = cv::Mat::zeros(c.photo_bgr.size(), CV_8U);
    std::vector<cv::Point> poly;
    for (const auto& r : c.roi_points) poly.emplace_back(int(r.x()), int(r.y()));
    cv::fillPoly(mask, std::vector<std::vector<cv::Point>>{poly}, cv::Scalar(255));
    return mask;
}

// Subarachnoid blood and a film of blood are drawn from a stream of their own: turned on, they
// change only cortex pixels, redden them (blood absorbs green and blue far more than red) and
// leave the pose, landmarks, ROI and targets as they were.
TEST_F(Phantom, SulcalBloodAndABloodFilmRedderTheCortexAndLeaveTheCaseAlone) {
    PhantomParams p;
    p.seed = 9;
    p.dslr_fraction = 0.0;
    p.gauze_prob = p.blood_prob = 0.0;  // no pools: unset, the two new forms follow this
    const PhantomCase plain = generate_phantom_case(*surface_, p, 0);
    EXPECT_NE(plain.notes.find(" sulcal_blood=0.00 blood_film_mm=0.00"), std::string::npos) << plain.notes;
    for (const bool film : {false, true}) {
        SCOPED_TRACE(film ? "film" : "sulcal blood");
        PhantomParams q = p;
        (film ? q.blood_film_prob : q.sulcal_blood_prob) = 1.0;
        const PhantomCase c = generate_phantom_case(*surface_, q, 0);
        const std::string key = film ? " blood_film_mm=" : " sulcal_blood=";
        ASSERT_NO_FATAL_FAILURE(expect_noted_and_case_alone(c, plain, key));
        // The pixels that changed: enough of them, all redder, none far outside the ROI.
        ASSERT_EQ(c.photo_bgr.size(), plain.photo_bgr.size());
        cv::Mat roi_mask = roi_mask_of(c);
        cv::dilate(roi_mask, roi_mask, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(41, 41)));
        double d_red = 0, d_green = 0;
        int changed = 0, changed_outside = 0;
        for (int y = 0; y < c.photo_bgr.rows; ++y)
            for (int x = 0; x < c.photo_bgr.cols; ++x) {
                const cv::Vec3b a = c.photo_bgr.at<cv::Vec3b>(y, x), b = plain.photo_bgr.at<cv::Vec3b>(y, x);
                const int dg = int(a[1]) - int(b[1]);
                if (std::abs(dg) < 25) continue;  // JPEG ringing and noise aside
                ++changed;
                changed_outside += roi_mask.at<uint8_t>(y, x) == 0;
                d_red += int(a[2]) - int(b[2]);
                d_green += dg;
            }
        const int npx = c.photo_bgr.rows * c.photo_bgr.cols;
        EXPECT_GT(changed, npx / 200) << "the blood barely shows";
        EXPECT_LT(changed_outside, changed / 20) << "blood off the cortex";
        EXPECT_LT(d_green / changed, -25) << "green is what blood takes away";
        EXPECT_GT(d_red / changed, d_green / changed + 20) << "red must stay far above green";
    }
    PhantomParams bad = p;
    bad.blood_film_prob = 1.5;
    EXPECT_THROW(bad.validate(), InputError);
}

// The OR lamp's spot is light: it dims the skin and drapes more than the opening it is aimed
// at. The iodine prep stains the scalp only, browner (it takes blue and green, not red). Both
// leave the case (pose, landmarks, ROI, targets) as it was.
TEST_F(Phantom, TheLampsSpotAndTheSkinPrepChangeLightAndScalpAndLeaveTheCaseAlone) {
    PhantomParams p;
    p.seed = 9;
    p.dslr_fraction = 0.0;
    p.gauze_prob = p.blood_prob = 0.0;
    p.lamp_spot_prob = p.skin_prep_prob = 0.0;
    p.fill_fraction = {0.5, 0.55};  // framed with the field around the opening in view
    const PhantomCase plain = generate_phantom_case(*surface_, p, 0);
    EXPECT_NE(plain.notes.find(" lamp_spot_mm=0 spot_floor=1.00 skin_prep=0.00"), std::string::npos) << plain.notes;
    const cv::Mat roi_mask = roi_mask_of(plain);
    cv::Mat near_roi;
    cv::dilate(roi_mask, near_roi, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(41, 41)));
    for (const bool spot : {true, false}) {
        SCOPED_TRACE(spot ? "lamp spot" : "skin prep");
        PhantomParams q = p;
        (spot ? q.lamp_spot_prob : q.skin_prep_prob) = 1.0;
        const PhantomCase c = generate_phantom_case(*surface_, q, 0);
        const std::string key = spot ? " lamp_spot_mm=" : " skin_prep=";
        ASSERT_NO_FATAL_FAILURE(expect_noted_and_case_alone(c, plain, key));
        ASSERT_EQ(c.photo_bgr.size(), plain.photo_bgr.size());
        // Mean brightness (sum of channels) inside the ROI and outside its neighbourhood.
        double in_new = 0, in_old = 0, out_new = 0, out_old = 0;
        double blue_new = 0, red_new = 0, blue_old = 0, red_old = 0;
        int n_in = 0, n_out = 0, changed = 0, changed_in_roi = 0;
        for (int y = 0; y < c.photo_bgr.rows; ++y)
            for (int x = 0; x < c.photo_bgr.cols; ++x) {
                const cv::Vec3b a = c.photo_bgr.at<cv::Vec3b>(y, x), b = plain.photo_bgr.at<cv::Vec3b>(y, x);
                const double sa = a[0] + a[1] + a[2], sb = b[0] + b[1] + b[2];
                const bool clipped = std::max({a[0], a[1], a[2], b[0], b[1], b[2]}) == 255;  // says nothing of the light
                if (clipped) continue;
                if (roi_mask.at<uint8_t>(y, x)) in_new += sa, in_old += sb, ++n_in;
                else if (!near_roi.at<uint8_t>(y, x)) out_new += sa, out_old += sb, ++n_out;
                if (std::abs(sa - sb) < 45) continue;  // JPEG ringing and noise aside
                ++changed;
                changed_in_roi += roi_mask.at<uint8_t>(y, x) != 0;
                blue_new += a[0], red_new += a[2], blue_old += b[0], red_old += b[2];
            }
        ASSERT_GT(n_in, 1000);
        ASSERT_GT(n_out, 1000);
        const double ratio_in = in_new / in_old, ratio_out = out_new / out_old;
        if (spot) {
            EXPECT_LT(ratio_out, ratio_in - 0.1) << "the spot must be brighter on the opening than around it";
            EXPECT_GT(ratio_in, 0.8) << "the spot is aimed at the opening";
        } else {
            const int npx = c.photo_bgr.rows * c.photo_bgr.cols;
            EXPECT_GT(changed, npx / 100) << "the prep barely shows";
            EXPECT_EQ(changed_in_roi, 0) << "prep on the cortex";
            // Browner: blue falls against red (skin about 0.65 of red, dried iodine about 0.2).
            EXPECT_LT(blue_new / red_new, blue_old / red_old - 0.08) << "iodine takes blue more than red";
            EXPECT_NEAR(ratio_in, 1.0, 0.01);
        }
    }
    PhantomParams bad = p;
    bad.lamp_spot_prob = 1.5;
    EXPECT_THROW(bad.validate(), InputError);
    bad = p;
    bad.skin_prep_prob = -0.1;
    EXPECT_THROW(bad.validate(), InputError);
}

TEST_F(Phantom, AFarLampRelightsTheCortexAndLeavesTheCaseAlone) {
    PhantomParams p;
    p.seed = 9;
    p.dslr_fraction = 0.0;
    p.gauze_prob = p.blood_prob = 0.0;
    const PhantomCase near = generate_phantom_case(*surface_, p, 0);
    EXPECT_NE(near.notes.find(" far_lamp_mm=0 "), std::string::npos) << near.notes;
    p.far_lamp_prob = 1.0;
    const PhantomCase far = generate_phantom_case(*surface_, p, 0);
    ASSERT_NO_FATAL_FAILURE(expect_noted_and_case_alone(far, near, " far_lamp_mm="));
    const double d_mm = std::stod(far.notes.substr(far.notes.find(" far_lamp_mm=") + 13));
    EXPECT_GE(d_mm, 800);
    EXPECT_LE(d_mm, 1200);
    // The cortex is lit from elsewhere: its shading changes over much of the opening.
    const cv::Mat roi = roi_mask_of(near);
    ASSERT_EQ(far.photo_bgr.size(), near.photo_bgr.size());
    int n = 0, changed = 0;
    for (int y = 0; y < roi.rows; ++y)
        for (int x = 0; x < roi.cols; ++x) {
            if (!roi.at<uint8_t>(y, x)) continue;
            const cv::Vec3b a = far.photo_bgr.at<cv::Vec3b>(y, x), b = near.photo_bgr.at<cv::Vec3b>(y, x);
            ++n;
            changed += std::abs(int(a[2]) - int(b[2])) > 12;
        }
    ASSERT_GT(n, 1000);
    EXPECT_GT(changed, n / 10) << changed << " of " << n << " ROI pixels";
    std::printf("far lamp: %d of %d ROI pixels changed\n", changed, n);
    PhantomParams bad = p;
    bad.far_lamp_prob = 1.5;
    EXPECT_THROW(bad.validate(), InputError);
}

// The photographic finish is drawn from the look's own stream: the case (pose, landmarks, ROI,
// targets) is the same with it and without. With it, the drapes' folds stand in relief (more
// contrast at the folds' scale on the cloth), and glare spreads a halo around it. (Without it the
// photos are those made before it, byte for byte: checked by hand on ev8, seed 101, when it came.)
TEST_F(Phantom, ThePhotoFinishGivesTheDrapesReliefAndTheGlareAHaloAndLeavesTheCaseAlone) {
    PhantomParams p;
    p.seed = 9;
    p.fill_fraction = {0.5, 0.55};  // framed with the drapes in view
    const auto [plain, c] = case_without_and_with(*surface_, p, &PhantomParams::photo_finish, 7);  // halation 0.40
    EXPECT_NE(plain.notes.find(" photo_finish=no drape_fold_slope=0.00"), std::string::npos) << plain.notes;
    ASSERT_NO_FATAL_FAILURE(expect_noted_and_case_alone(c, plain, " drape_fold_slope="));
    ASSERT_EQ(c.photo_bgr.size(), plain.photo_bgr.size());

    // The cloth: pixels of the drapes' colour (green or blue above red) in both photos.
    cv::Mat cloth(c.photo_bgr.size(), CV_8U, cv::Scalar(0));
    for (int y = 0; y < c.photo_bgr.rows; ++y)
        for (int x = 0; x < c.photo_bgr.cols; ++x) {
            const cv::Vec3b a = c.photo_bgr.at<cv::Vec3b>(y, x), b = plain.photo_bgr.at<cv::Vec3b>(y, x);
            const bool ca = std::max(a[0], a[1]) > a[2] + 15, cb = std::max(b[0], b[1]) > b[2] + 15;
            cloth.at<uint8_t>(y, x) = ca && cb ? 255 : 0;
        }
    cv::erode(cloth, cloth, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(25, 25)));  // away from hems and skin
    ASSERT_GT(cv::countNonZero(cloth), c.photo_bgr.total() / 20) << "too little cloth in view to judge";
    // Contrast at the folds' scale (a difference of Gaussians, 3 and 12 px), on the cloth.
    auto fold_contrast = [&](const cv::Mat& bgr) {
        cv::Mat grey, fine, coarse;
        cv::cvtColor(bgr, grey, cv::COLOR_BGR2GRAY);
        grey.convertTo(grey, CV_32F);
        cv::GaussianBlur(grey, fine, cv::Size(0, 0), 3);
        cv::GaussianBlur(grey, coarse, cv::Size(0, 0), 12);
        return cv::mean(cv::abs(fine - coarse), cloth)[0];
    };
    const double relief_on = fold_contrast(c.photo_bgr), relief_off = fold_contrast(plain.photo_bgr);
    EXPECT_GT(relief_on, 1.5 * relief_off) << "the drapes lie flat";

    // The halo: around the glare (pixels clipped in the plain photo) the finished photo is
    // brighter. The median change over a ring 4-16 px out, as the bone's pits darken a few
    // pixels of a ring that lies on the bone; far from any glare, no change.
    cv::Mat glare(c.photo_bgr.size(), CV_8U, cv::Scalar(0));
    for (int y = 0; y < c.photo_bgr.rows; ++y)
        for (int x = 0; x < c.photo_bgr.cols; ++x) {
            const cv::Vec3b b = plain.photo_bgr.at<cv::Vec3b>(y, x);
            glare.at<uint8_t>(y, x) = std::min({b[0], b[1], b[2]}) >= 250 ? 255 : 0;
        }
    ASSERT_GT(cv::countNonZero(glare), 50) << "no glare to judge the halo by";
    cv::Mat inner, outer, far;
    cv::dilate(glare, inner, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(9, 9)));
    cv::dilate(glare, outer, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(33, 33)));
    cv::dilate(glare, far, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(161, 161)));
    auto median_change = [&](const cv::Mat& where) {
        std::vector<int> d;
        for (int y = 0; y < c.photo_bgr.rows; ++y)
            for (int x = 0; x < c.photo_bgr.cols; ++x)
                if (where.at<uint8_t>(y, x)) {
                    const cv::Vec3b a = c.photo_bgr.at<cv::Vec3b>(y, x), b = plain.photo_bgr.at<cv::Vec3b>(y, x);
                    d.push_back(int(a[0]) + a[1] + a[2] - b[0] - b[1] - b[2]);
                }
        if (d.empty()) return 0;
        std::nth_element(d.begin(), d.begin() + long(d.size() / 2), d.end());
        return d[d.size() / 2];
    };
    // Far from glare, on the cortex (the rim around it is the finish's to change).
    const cv::Mat ring = outer & ~inner, away = ~far & roi_mask_of(c);
    EXPECT_GE(median_change(ring), 3) << "no halo around the glare";
    ASSERT_GT(cv::countNonZero(away), 2000) << "no cortex far from glare to judge";
    EXPECT_LE(std::abs(median_change(away)), 2) << "the finish changed the light far from glare";
}

// The rim as made by hand (part of the finish): the scalp's cut wall shows its layers where the
// blood is wiped off (skin, pale dermis, yellow fat, white galea) instead of one dark red band;
// the dura carries meningeal vessels; the clips are shaped, the dura's edge ragged, sutures and
// trickles of blood drawn, all from the look's own stream, so the case stays as it was.
TEST_F(Phantom, TheRimByHandShowsTheScalpsLayersAndTheDurasVesselsAndLeavesTheCaseAlone) {
    PhantomParams p;
    p.seed = 101;
    const auto [plain, c] = case_without_and_with(*surface_, p, &PhantomParams::photo_finish, 0);
    EXPECT_NE(plain.notes.find(" clip_tilt_deg=0.0 dura_rag=0.00 sutures=0"), std::string::npos) << plain.notes;
    ASSERT_NO_FATAL_FAILURE(expect_noted_and_case_alone(c, plain, " dura_rag="));
    ASSERT_NO_FATAL_FAILURE(expect_noted_and_case_alone(c, plain, " clip_tilt_deg="));
    ASSERT_EQ(c.photo_bgr.size(), plain.photo_bgr.size());

    // The cut wall: pixels a deep red in the plain photo (no pools or gauze in this case; the
    // veins stay as they were). In the finished photo some show the wall's pale and yellow layers
    // where it is wiped: bright, green well up towards red (2301 of 39703 pixels; without the
    // layers, 301: the edge's margin on the skin made ragged).
    int red = 0, layered = 0;
    for (int y = 0; y < c.photo_bgr.rows; ++y)
        for (int x = 0; x < c.photo_bgr.cols; ++x) {
            const cv::Vec3b b = plain.photo_bgr.at<cv::Vec3b>(y, x), a = c.photo_bgr.at<cv::Vec3b>(y, x);
            if (!(b[2] >= 50 && b[1] < 0.4 * b[2] && b[0] < 0.45 * b[2])) continue;
            ++red;
            if (a[2] >= 90 && a[1] > 0.45 * a[2]) ++layered;
        }
    ASSERT_GT(red, 500) << "no cut wall in view to judge";
    EXPECT_GT(layered, red / 40) << layered << " of " << red << " deep red pixels show the scalp's layers";

    // The dura: pale, nearly grey pixels in the plain photo. In the finished one some carry its
    // meningeal vessels and its stained cut edge: red, green well below red (488 of 16568; 319
    // without the dura's vessels, folds and stain, from the rim's other changes and the clips).
    int pale = 0, vessels = 0;
    for (int y = 0; y < c.photo_bgr.rows; ++y)
        for (int x = 0; x < c.photo_bgr.cols; ++x) {
            const cv::Vec3b b = plain.photo_bgr.at<cv::Vec3b>(y, x), a = c.photo_bgr.at<cv::Vec3b>(y, x);
            if (!(b[2] >= 120 && b[2] <= 240 && b[1] > 0.85 * b[2] && b[0] > 0.86 * b[2])) continue;
            ++pale;
            if (a[1] < 0.7 * a[2] && a[0] < 0.7 * a[2]) ++vessels;
        }
    ASSERT_GT(pale, 2000) << "no dura in view to judge";
    EXPECT_GT(vessels, pale / 40) << vessels << " of " << pale << " pale pixels show the dura's vessels";
}

// Tissue optics (part of the finish, from a stream of its own, so the case stays as it was).
// Light scattered under the cortex's surface softens its fine shading, keeps its mean light, and
// carries red into the shaded sulci's edges (red spreads furthest in tissue). A pool of blood
// mirrors the lamp through an isotropic ripple: the lamp's image breaks into many rounded glints,
// not the few axis-aligned blocks a lattice noise's slopes give.
TEST_F(Phantom, TissueOpticsSoftenTheCortexRedderItsShadowsAndRoundThePoolsGlints) {
    PhantomParams p;
    p.seed = 9;
    const auto [plain, c] = case_without_and_with(*surface_, p, &PhantomParams::tissue_optics, 0);
    EXPECT_NE(plain.notes.find(" scatter_mm=0.00 scatter_share=0.00 pool_lamp_half_deg=0.0 pool_ripple_mm=0.000"), std::string::npos)
        << plain.notes;
    ASSERT_NO_FATAL_FAILURE(expect_noted_and_case_alone(c, plain, " scatter_mm="));
    ASSERT_NO_FATAL_FAILURE(expect_noted_and_case_alone(c, plain, " pool_ripple_mm="));
    ASSERT_EQ(c.photo_bgr.size(), plain.photo_bgr.size());
    {
        // Leave the rest of the finish alone: outside the cortex (the ROI's neighbourhood) nothing
        // but JPEG noise changes.
        cv::Mat near_roi;
        cv::dilate(roi_mask_of(c), near_roi, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(121, 121)));
        cv::Mat diff;
        cv::absdiff(c.photo_bgr, plain.photo_bgr, diff);
        cv::Mat far = ~near_roi;
        EXPECT_LT(cv::mean(diff, far)[0] + cv::mean(diff, far)[1] + cv::mean(diff, far)[2], 1.5) << "changed outside the cortex";
    }
    cv::Mat inside;
    cv::erode(roi_mask_of(c), inside, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(15, 15)));
    ASSERT_GT(cv::countNonZero(inside), 5000);
    auto grey_of = [](const cv::Mat& bgr) {
        cv::Mat g;
        cv::cvtColor(bgr, g, cv::COLOR_BGR2GRAY);
        g.convertTo(g, CV_32F);
        return g;
    };
    const cv::Mat g_on = grey_of(c.photo_bgr), g_off = grey_of(plain.photo_bgr);
    // Unclipped in both: glare says nothing of the diffuse light.
    cv::Mat judged = inside.clone();
    for (int y = 0; y < judged.rows; ++y)
        for (int x = 0; x < judged.cols; ++x) {
            const cv::Vec3b a = c.photo_bgr.at<cv::Vec3b>(y, x), b = plain.photo_bgr.at<cv::Vec3b>(y, x);
            if (std::max({a[0], a[1], a[2], b[0], b[1], b[2]}) >= 250) judged.at<uint8_t>(y, x) = 0;
        }
    auto fine_contrast = [&](const cv::Mat& g) {
        cv::Mat a, b;
        cv::GaussianBlur(g, a, cv::Size(0, 0), 1.0);
        cv::GaussianBlur(g, b, cv::Size(0, 0), 4.0);
        return cv::mean(cv::abs(a - b), judged)[0];
    };
    const double fine_on = fine_contrast(g_on), fine_off = fine_contrast(g_off);
    const double mean_on = cv::mean(g_on, judged)[0], mean_off = cv::mean(g_off, judged)[0];
    // The shaded quarter of the cortex (darkest in the plain photo): its red against green.
    std::vector<float> levels;
    for (int y = 0; y < judged.rows; ++y)
        for (int x = 0; x < judged.cols; ++x)
            if (judged.at<uint8_t>(y, x)) levels.push_back(g_off.at<float>(y, x));
    std::nth_element(levels.begin(), levels.begin() + long(levels.size() / 4), levels.end());
    const float dark = levels[levels.size() / 4];
    double red_on = 0, green_on = 0, red_off = 0, green_off = 0;
    for (int y = 0; y < judged.rows; ++y)
        for (int x = 0; x < judged.cols; ++x)
            if (judged.at<uint8_t>(y, x) && g_off.at<float>(y, x) <= dark) {
                red_on += c.photo_bgr.at<cv::Vec3b>(y, x)[2], green_on += c.photo_bgr.at<cv::Vec3b>(y, x)[1];
                red_off += plain.photo_bgr.at<cv::Vec3b>(y, x)[2], green_off += plain.photo_bgr.at<cv::Vec3b>(y, x)[1];
            }
    EXPECT_LT(fine_on, 0.95 * fine_off) << "the cortex's fine shading is as hard as without scatter";
    EXPECT_NEAR(mean_on / mean_off, 1.0, 0.06) << "scatter moves light, it does not make or take it";
    EXPECT_GT(red_on / green_on, 1.01 * (red_off / green_off)) << "no red carried into the shade";

    // The pools' glints: the phantom command's defaults, seed 7, case 1 (a wide pool). With and
    // without the optics only the cortex's scatter (a few levels) and the pools' mirror differ: the
    // pool is where the photos differ by far more, and its glints its near-white pixels.
    PhantomParams pb;
    pb.seed = 7;
    pb.tissue_optics = false;
    const PhantomCase b_off = generate_phantom_case(*surface_, pb, 1);
    pb.tissue_optics = true;
    const PhantomCase b_on = generate_phantom_case(*surface_, pb, 1);
    ASSERT_EQ(b_on.notes.find(" blood=0"), std::string::npos) << "no pool: " << b_on.notes;
    cv::Mat pool(b_on.photo_bgr.size(), CV_8U, cv::Scalar(0));
    for (int y = 0; y < pool.rows; ++y)
        for (int x = 0; x < pool.cols; ++x) {
            const cv::Vec3b a = b_on.photo_bgr.at<cv::Vec3b>(y, x), o = b_off.photo_bgr.at<cv::Vec3b>(y, x);
            if (std::abs(int(a[1]) - int(o[1])) >= 80) pool.at<uint8_t>(y, x) = 255;
        }
    ASSERT_GT(cv::countNonZero(pool), 100) << "the pool's mirror did not change";
    cv::dilate(pool, pool, cv::getStructuringElement(cv::MORPH_ELLIPSE, cv::Size(41, 41)));
    auto glints_of = [&](const cv::Mat& bgr) {
        cv::Mat g(bgr.size(), CV_8U, cv::Scalar(0));
        for (int y = 0; y < g.rows; ++y)
            for (int x = 0; x < g.cols; ++x) {
                const cv::Vec3b a = bgr.at<cv::Vec3b>(y, x);
                g.at<uint8_t>(y, x) = pool.at<uint8_t>(y, x) && std::min({a[0], a[1], a[2]}) >= 200 ? 255 : 0;
            }
        return g;
    };
    // The share of the glints' outline whose direction is within 10 degrees of the image's axes
    // (4 x 20 of 360 degrees, 22 %, for round outlines; more where they are lattice rectangles).
    auto axis_share = [](const cv::Mat& glint) {
        cv::Mat f, gx, gy;
        glint.convertTo(f, CV_32F, 1.0 / 255);
        cv::GaussianBlur(f, f, cv::Size(0, 0), 1.0);
        cv::Sobel(f, gx, CV_32F, 1, 0);
        cv::Sobel(f, gy, CV_32F, 0, 1);
        double n = 0, near_axis = 0;
        for (int y = 0; y < f.rows; ++y)
            for (int x = 0; x < f.cols; ++x) {
                const double ax = std::abs(gx.at<float>(y, x)), ay = std::abs(gy.at<float>(y, x));
                const double mag = std::hypot(ax, ay);
                if (mag < 0.3) continue;
                const double ang_deg = std::atan2(ay, ax) * 180 / M_PI;
                n += mag;
                if (ang_deg < 10 || ang_deg > 80) near_axis += mag;
            }
        return n > 0 ? near_axis / n : 0.0;
    };
    const cv::Mat glint_on = glints_of(b_on.photo_bgr), glint_off = glints_of(b_off.photo_bgr);
    const double share_on = axis_share(glint_on), share_off = axis_share(glint_off);
    auto blobs_of = [](const cv::Mat& glint) {
        cv::Mat labels, stats, centroids;
        const int n = cv::connectedComponentsWithStats(glint, labels, stats, centroids, 8);
        int big = 0;
        for (int i = 1; i < n; ++i) big += stats.at<int>(i, cv::CC_STAT_AREA) >= 4;
        return big;
    };
    const int blobs_on = blobs_of(glint_on), blobs_off = blobs_of(glint_off);
    // Measured: 0.265 and 13 glints with the optics; 0.337 and 8 on the lattice without them; a
    // mutant with the ripple left out (the bare dome) gave 0.359 and 5.
    EXPECT_LT(share_on, 0.31) << "the glints' outlines follow the image's axes (" << share_off << " without the optics)";
    EXPECT_GE(blobs_on, 9) << "the ripple does not break the lamp's image into glints (" << blobs_off << " without the optics)";
}

TEST_F(Phantom, DslrCaseIsFullSizeJpeg) {
    PhantomParams p;
    p.seed = 3;
    p.dslr_fraction = 1.0;
    const PhantomCase c = generate_phantom_case(*surface_, p, 0);
    EXPECT_EQ(c.camera.width, 3000);
    EXPECT_EQ(c.camera.height, 2000);
    EXPECT_EQ(c.photo_bgr.cols, 3000);
    EXPECT_EQ(c.photo_bgr.rows, 2000);
    EXPECT_TRUE(c.jpeg);
}

TEST_F(Phantom, CasesAreValidConsistentAndPhotoLike) {
    PhantomParams p;
    p.seed = 11;
    p.dslr_fraction = 0.0;
    p.gauze_prob = p.blood_prob = 0.5;
    p.distortion_prob = 0.5;
    const fs::path dir = tmpdir("cases");
    for (int idx = 0; idx < 4; ++idx) {
        SCOPED_TRACE("case " + std::to_string(idx));
        const PhantomCase pc = generate_phantom_case(*surface_, p, idx);
        const fs::path cd = dir / ("case_" + std::to_string(idx));
        // Refer to the shipped volume by absolute path (cases written by the batch use ../t1.nii.gz).
        write_phantom_case(pc, cd, kVolume.string(), kMask.string());
        ASSERT_TRUE(fs::exists(cd / "truth.json"));

        // Valid per docs/case-format.md: the case reader accepts it.
        const CaseSpec cs = read_case(cd);
        ASSERT_TRUE(cs.truth.has_value());
        ASSERT_TRUE(cs.roi.has_value());
        const Intrinsics& K = cs.camera;
        EXPECT_GE(cs.landmarks.size(), 4u);
        EXPECT_LE(cs.landmarks.size(), 6u);
        const Pose& T = cs.truth->T_camera_from_world;
        EXPECT_TRUE(is_rigid(T));
        const auto& targets = cs.truth->targets_world_mm;
        EXPECT_GE(targets.size(), 15u);
        EXPECT_LE(targets.size(), 30u);

        // Targets project inside the image and the ROI.
        const cv::Mat roi = roi_mask(*cs.roi, K.width, K.height);
        for (const auto& t : targets) {
            const auto px = project(K, T, t);
            ASSERT_TRUE(px);
            const int u = int(std::lround(px->x())), v = int(std::lround(px->y()));
            ASSERT_TRUE(u >= 0 && v >= 0 && u < K.width && v < K.height);
            EXPECT_EQ(roi.at<uint8_t>(v, u), 255) << "target outside the ROI at " << u << "," << v;
        }
        // Landmark pixels are within picking noise of the true projections.
        const nlohmann::json truth = nlohmann::json::parse(slurp(cd / "truth.json"));
        const auto& lt = truth.at("landmarks_true");
        ASSERT_EQ(lt.size(), cs.landmarks.size());
        const double sd_px = p.landmark_pixel_sd[1] * K.width / 750.0;
        for (size_t i = 0; i < cs.landmarks.size(); ++i) {
            const Eigen::Vector3d w(lt[i]["world_mm"][0], lt[i]["world_mm"][1], lt[i]["world_mm"][2]);
            const auto px = project(K, T, w);
            ASSERT_TRUE(px);
            EXPECT_LT((*px - cs.landmarks[i].pixel).norm(), 5 * sd_px);
            EXPECT_LT((w - cs.landmarks[i].world_mm).norm(), 5 * p.landmark_world_sd_mm + 1e-9);
        }

        // The photo looks like a surgical photo, not a grey rendering: reddish tissue, dark
        // red vessels inside the ROI, some glare.
        const cv::Mat photo = load_photo(cs.photo_path);
        ASSERT_EQ(photo.cols, K.width);
        ASSERT_EQ(photo.rows, K.height);
        int inside = 0, vessel = 0, glare = 0;
        cv::Vec3d mean(0, 0, 0);
        for (int v = 0; v < K.height; ++v)
            for (int u = 0; u < K.width; ++u) {
                if (!roi.at<uint8_t>(v, u)) continue;
                const cv::Vec3b c = photo.at<cv::Vec3b>(v, u);  // BGR
                ++inside;
                mean += cv::Vec3d(c[0], c[1], c[2]);
                if (c[2] < 170 && c[2] > 1.6 * c[1] && c[2] > 1.3 * c[0]) ++vessel;
                if (c[0] > 235 && c[1] > 235 && c[2] > 235) ++glare;
            }
        ASSERT_GT(inside, 1000);
        mean /= inside;
        EXPECT_GT(mean[2], mean[1] + 15) << "cortex should be reddish";
        EXPECT_GT(vessel, inside / 500) << "dark red vessels expected";
        EXPECT_GT(glare, 0) << "specular glare expected";
    }
    fs::remove_all(dir);
}

TEST(PhantomBatch, WritesIdenticalFilesForTheSameSeed) {
    PhantomParams p;
    p.seed = 5;
    p.dslr_fraction = 0.0;
    const fs::path a = tmpdir("batch_a"), b = tmpdir("batch_b");
    const auto da = generate_phantoms(a, 2, kVolume, kMask, p);
    const auto db = generate_phantoms(b, 2, kVolume, kMask, p);
    ASSERT_EQ(da.size(), 2u);
    EXPECT_TRUE(fs::exists(a / "t1.nii.gz"));
    EXPECT_TRUE(fs::exists(a / "brain_mask.nii.gz"));
    for (size_t i = 0; i < da.size(); ++i) {
        size_t files = 0;
        for (const auto& e : fs::directory_iterator(da[i])) {
            ++files;
            EXPECT_EQ(slurp(e.path()), slurp(db[i] / e.path().filename())) << e.path();
        }
        EXPECT_EQ(files, 5u);  // case.json, photo, landmarks.json, roi.json, truth.json
        // The relative volume reference resolves.
        const CaseSpec cs = read_case(da[i]);
        EXPECT_TRUE(fs::exists(cs.volume_path));
        ASSERT_TRUE(cs.brain_mask_path.has_value());
        EXPECT_TRUE(fs::exists(*cs.brain_mask_path));
    }
    fs::remove_all(a);
    fs::remove_all(b);
}

TEST(PhantomBatch, BadInputsAreInputErrors) {
    const fs::path d = tmpdir("bad");
    PhantomParams p;
    EXPECT_THROW(generate_phantoms(d, 0, kVolume, kMask, p), InputError);
    EXPECT_THROW(generate_phantoms(d, 1, d / "missing.nii.gz", kMask, p), InputError);
    p.gauze_prob = 1.5;
    EXPECT_THROW(p.validate(), InputError);
    // A mask on another grid.
    Volume v;
    v.geom.dims = {20, 20, 20};
    v.voxels.assign(v.geom.voxel_count(), 1.f);
    LabelVolume m;
    m.geom = v.geom;
    m.geom.spacing_mm = Eigen::Vector3d(2, 2, 2);
    m.voxels.assign(m.geom.voxel_count(), 1);
    EXPECT_THROW(build_phantom_surface(v, m), InputError);
    fs::remove_all(d);
}
