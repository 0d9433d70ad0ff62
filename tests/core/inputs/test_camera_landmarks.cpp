// The camera model against OpenCV's own functions, and the landmark alignments (PnP with RANSAC,
// the seed's orthographic variant) against poses known exactly.
#include <gtest/gtest.h>

#include <opencv2/calib3d.hpp>
#include <random>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/landmarks.hpp"
#include "cortexfuse/core/pose.hpp"

using namespace cf;

namespace {

Intrinsics dslr_camera() {
    Intrinsics K;
    K.width = 750;
    K.height = 500;
    K.fx = 1400;
    K.fy = 1395;
    K.cx = 380.2;
    K.cy = 244.7;
    K.distortion = {-0.12, 0.05, 0.001, -0.0015, -0.01};
    return K;
}

Pose known_pose() {
    Pose T = Pose::Identity();
    T.topLeftCorner<3, 3>() = rotation_xyz_deg(160, 15, -30);
    T.topRightCorner<3, 1>() = Eigen::Vector3d(4, -7, 320);
    return T;
}

// Landmarks on a gently curved cortical patch (~60 mm across) in front of the camera.
std::vector<Landmark> landmarks_for(const Pose& T, const Intrinsics& K, int n, double pixel_noise, uint32_t seed) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> U(-30, 30);
    std::normal_distribution<double> N(0, pixel_noise);
    const Pose Tinv = T.inverse();
    std::vector<Landmark> out;
    while (int(out.size()) < n) {
        const double x = U(rng), y = U(rng);
        const Eigen::Vector3d pc(x, y, 320 + 0.01 * (x * x + y * y) - 8);  // camera frame
        const Eigen::Vector3d pw = Tinv.topLeftCorner<3, 3>() * pc + Tinv.topRightCorner<3, 1>();
        const auto px = project(K, T, pw);
        if (!px || px->x() < 0 || px->y() < 0 || px->x() > K.width - 1 || px->y() > K.height - 1) continue;
        out.push_back({"L" + std::to_string(out.size() + 1), pw, *px + Eigen::Vector2d(N(rng), N(rng))});
    }
    return out;
}

double angle_deg(const Pose& a, const Pose& b) {
    return Eigen::AngleAxisd(a.topLeftCorner<3, 3>().transpose() * b.topLeftCorner<3, 3>()).angle() * 180 / M_PI;
}

// A steep view: a narrow lens (a 19 deg field) 450 mm from a cortical patch seen 45 deg off its
// normal, as the phantom's evtilt case 0006.
Intrinsics steep_view_camera() {
    Intrinsics K;
    K.width = 763;
    K.height = 572;
    K.fx = K.fy = 2290;
    K.cx = 381;
    K.cy = 286;
    K.distortion = {0, 0, 0, 0, 0};
    return K;
}

Pose steep_view_pose() {  // camera from world; world = the patch's own frame
    Pose T = Pose::Identity();
    T.topLeftCorner<3, 3>() = Eigen::AngleAxisd(45 * M_PI / 180, Eigen::Vector3d::UnitY()).toRotationMatrix();
    T.topRightCorner<3, 1>() = Eigen::Vector3d(0, 0, 450);
    return T;
}

// Five pairs on the gently curved patch (50 mm across), model points off by world_sd_mm (3D,
// 1 sd) and pixels by pixel_sd.
std::vector<Landmark> steep_view_landmarks(const Intrinsics& K, const Pose& T, uint32_t seed, double pixel_sd,
                                           double world_sd_mm) {
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> U(-25, 25);
    std::normal_distribution<double> N(0, 1.0);
    std::vector<Landmark> lms;
    while (lms.size() < 5) {
        const double x = U(rng), y = U(rng);
        const Eigen::Vector3d pw(x, y, -0.006 * (x * x + y * y));
        const auto px = project(K, T, pw);
        if (!px || px->x() < 0 || px->y() < 0 || px->x() > K.width - 1 || px->y() > K.height - 1) continue;
        Eigen::Vector3d picked = pw;
        if (world_sd_mm > 0) picked += world_sd_mm / std::sqrt(3.0) * Eigen::Vector3d(N(rng), N(rng), N(rng));
        const double du = N(rng), dv = N(rng);
        lms.push_back({"L" + std::to_string(lms.size() + 1), picked, *px + pixel_sd * Eigen::Vector2d(du, dv)});
    }
    return lms;
}

}  // namespace

// project() is OpenCV's model: it agrees with cv::projectPoints, and backproject() with
// cv::undistortPoints, over the whole image including the strongly distorted corners.
TEST(CameraModel, AgreesWithOpenCvProjectPoints) {
    const Intrinsics K = dslr_camera();
    const Pose T = known_pose();
    cv::Mat R(3, 3, CV_64F), rvec, tvec(3, 1, CV_64F);
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) R.at<double>(r, c) = T(r, c);
        tvec.at<double>(r) = T(r, 3);
    }
    cv::Rodrigues(R, rvec);
    const cv::Matx33d Kcv(K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1);
    const std::vector<double> dist(K.distortion.begin(), K.distortion.end());
    std::mt19937 rng(9);
    std::uniform_real_distribution<double> U(-40, 40);
    std::vector<cv::Point3d> obj;
    std::vector<Eigen::Vector3d> pts;
    const Pose Tinv = T.inverse();
    for (int i = 0; i < 300; ++i) {
        const Eigen::Vector3d pc(U(rng), U(rng) * 0.66, 300 + U(rng));
        const Eigen::Vector3d pw = Tinv.topLeftCorner<3, 3>() * pc + Tinv.topRightCorner<3, 1>();
        pts.push_back(pw);
        obj.emplace_back(pw.x(), pw.y(), pw.z());
    }
    std::vector<cv::Point2d> ref;
    cv::projectPoints(obj, rvec, tvec, Kcv, dist, ref);
    for (size_t i = 0; i < pts.size(); ++i) {
        const auto p = project(K, T, pts[i]);
        ASSERT_TRUE(p);
        EXPECT_NEAR(p->x(), ref[i].x, 1e-6);
        EXPECT_NEAR(p->y(), ref[i].y, 1e-6);
    }
    // Behind the camera: no pixel.
    EXPECT_FALSE(project_camera(K, Eigen::Vector3d(0, 0, -10)));
    // Back-projection of every pixel of a grid, then projection again, returns the pixel; the
    // per-pixel ray table used by the ray caster holds the same rays.
    const std::vector<Eigen::Vector3f> rays = pixel_rays(K);
    for (int v = 0; v < K.height; v += 37)
        for (int u = 0; u < K.width; u += 41) {
            const Eigen::Vector2d px(u, v);
            const Eigen::Vector3d ray = backproject_ray(K, px);
            EXPECT_NEAR(ray.z(), 1.0, 1e-12);
            const auto q = project_camera(K, ray * 250.0);
            ASSERT_TRUE(q);
            EXPECT_LT((*q - px).norm(), 1e-4) << u << "," << v;
            EXPECT_LT((rays[size_t(v) * K.width + u].cast<double>() - ray).norm(), 1e-4) << u << "," << v;
        }
}

TEST(CameraModel, InvalidIntrinsicsAreInputErrors) {
    Intrinsics K = dslr_camera();
    EXPECT_NO_THROW(K.validate("camera"));
    Intrinsics bad = K;
    bad.fx = -1;
    EXPECT_THROW(bad.validate("camera"), InputError);
    bad = K;
    bad.cx = std::nan("");
    EXPECT_THROW(bad.validate("camera"), InputError);
    bad = K;
    bad.distortion[0] = std::numeric_limits<double>::infinity();
    EXPECT_THROW(bad.validate("camera"), InputError);
    bad = K;
    bad.width = 0;
    EXPECT_THROW(bad.validate("camera"), InputError);
}

// Photos of any size: intrinsics scaled with the image keep every world point on the same
// (scaled) pixel, with distortion, so a DSLR photo can be worked on at 375 px.
TEST(CameraModel, ResizedIntrinsicsProjectToTheScaledPixel) {
    const Intrinsics K = dslr_camera().resized(3000, 2000);
    for (const double s : {0.125, 0.25, 0.5}) {
        const Intrinsics k = K.scaled(s);
        EXPECT_EQ(k.width, int(std::lround(3000 * s)));
        for (const Eigen::Vector3d& p : {Eigen::Vector3d(10, -20, 400), Eigen::Vector3d(-35, 22, 300)}) {
            const auto a = project_camera(K, p), b = project_camera(k, p);
            ASSERT_TRUE(a && b);
            EXPECT_NEAR((a->array() + 0.5).x() * s - 0.5, b->x(), 1e-9);
            EXPECT_NEAR((a->array() + 0.5).y() * s - 0.5, b->y(), 1e-9);
        }
    }
}

TEST(LandmarkFit, PnpRecoversAKnownPoseExactly) {
    const Intrinsics K = dslr_camera();
    const Pose T = known_pose();
    for (const int n : {4, 5, 8}) {
        const auto lms = landmarks_for(T, K, n, 0.0, 1 + uint32_t(n));
        const LandmarkFit f = fit_pose_pnp(lms, K);
        EXPECT_LT(angle_deg(f.T_camera_from_world, T), 1e-4) << n;
        EXPECT_LT((f.T_camera_from_world.topRightCorner<3, 1>() - T.topRightCorner<3, 1>()).norm(), 1e-3) << n;
        EXPECT_LT(f.rms_px, 1e-5) << n;
        EXPECT_EQ(f.method, n >= 6 ? "pnp-ransac" : "pnp");
        EXPECT_TRUE(is_rigid(f.T_camera_from_world));
    }
}

// From 6 pairs on, RANSAC drops a mislabelled pair: the pose stays right and the outlier is not
// among the inliers; the reported RMS (over all pairs) shows the outlier's error.
TEST(LandmarkFit, RansacDropsAMislabelledPair) {
    const Intrinsics K = dslr_camera();
    const Pose T = known_pose();
    auto lms = landmarks_for(T, K, 8, 1.0, 21);
    lms[3].pixel += Eigen::Vector2d(90, -60);  // picked on the wrong vessel
    const LandmarkFit f = fit_pose_pnp(lms, K);
    EXPECT_EQ(f.method, "pnp-ransac");
    EXPECT_EQ(std::count(f.inliers.begin(), f.inliers.end(), 3), 0);
    EXPECT_GE(f.inliers.size(), 6u);
    EXPECT_LT(angle_deg(f.T_camera_from_world, T), 1.5);
    EXPECT_NEAR(f.rms_px, reprojection_rms_px(lms, K, f.T_camera_from_world), 1e-9);
    EXPECT_GT(f.rms_px, 20.0);
}

// The seed's scaled-orthographic variant: close to the truth for a camera far from a shallow
// patch (what it assumes), worse than PnP, and its RMS is what the pose really reprojects to.
TEST(LandmarkFit, OrthographicVariantIsCloseForAFarCamera) {
    Intrinsics K = dslr_camera();
    K.distortion = {0, 0, 0, 0, 0};
    const Pose T = known_pose();
    const auto lms = landmarks_for(T, K, 8, 0.5, 33);
    const LandmarkFit o = fit_pose_orthographic(lms, K);
    const LandmarkFit p = fit_pose_pnp(lms, K);
    EXPECT_EQ(o.method, "orthographic");
    EXPECT_TRUE(is_rigid(o.T_camera_from_world));
    EXPECT_LT(angle_deg(o.T_camera_from_world, T), 8.0);
    EXPECT_LT((o.T_camera_from_world.topRightCorner<3, 1>() - T.topRightCorner<3, 1>()).norm(), 15.0);
    EXPECT_NEAR(o.rms_px, reprojection_rms_px(lms, K, o.T_camera_from_world), 1e-9);
    EXPECT_GE(o.rms_px, p.rms_px);
    EXPECT_LT(o.rms_px, 25.0);
    EXPECT_EQ(o.inliers.size(), lms.size());
}

TEST(LandmarkFit, TooFewOrDegeneratePairsAreInputErrors) {
    const Intrinsics K = dslr_camera();
    const auto lms = landmarks_for(known_pose(), K, 3, 0.0, 5);
    EXPECT_THROW(fit_pose_pnp(lms, K), InputError);
    EXPECT_THROW(fit_pose_orthographic(lms, K), InputError);
    // Collinear pixels: refused by the case validation, naming the file.
    std::vector<Landmark> line;
    for (int i = 0; i < 5; ++i) line.push_back({"L", Eigen::Vector3d(i, 2.0 * i * i, 3), Eigen::Vector2d(10 + 20 * i, 10 + 10 * i)});
    try {
        validate_landmarks(line, K, "lm.json");
        ADD_FAILURE() << "collinear landmarks accepted";
    } catch (const InputError& e) {
        EXPECT_EQ(e.input(), "lm.json");
    }
}

// Spread: 0 on a line, about 1 for a round cloud; a set that nearly lies on a line is accepted
// with a warning (the turn about the line is barely fixed by it), a collinear one refused.
TEST(LandmarkSpread, MeasuresHowFarPairsSpanAnAreaAndWarnsNearALine) {
    const Intrinsics K = dslr_camera();
    std::vector<Landmark> round, thin;
    for (int i = 0; i < 6; ++i) {
        const double a = 2 * M_PI * i / 6;
        round.push_back({"R", Eigen::Vector3d(30 * std::cos(a), 30 * std::sin(a), 2.0 * (i % 2)),
                         Eigen::Vector2d(375 + 150 * std::cos(a), 250 + 150 * std::sin(a))});
        // Along x, 2.4 mm (and 24 px) off the line at most: spread about 0.07, as the phantom's
        // MNI152 case 0004.
        const double off = (i % 2 ? 1.0 : -1.0) * (i == 2 || i == 3 ? 2.4 : 1.2);
        thin.push_back({"T", Eigen::Vector3d(10.0 * i, off, 0.3 * i), Eigen::Vector2d(100 + 100.0 * i, 250 + 10 * off)});
    }
    const LandmarkSpread r = landmark_spread(round), t = landmark_spread(thin);
    EXPECT_GT(r.world, 0.9);
    EXPECT_GT(r.pixel, 0.9);
    EXPECT_LT(t.world, kLandmarkSpreadWarn);
    EXPECT_GT(t.world, kLandmarkSpreadMin);
    EXPECT_LT(t.pixel, kLandmarkSpreadWarn);
    EXPECT_EQ(landmark_spread_warning(r), "");
    const std::string w = landmark_spread_warning(t);
    EXPECT_NE(w.find("nearly on a line"), std::string::npos) << w;
    EXPECT_NO_THROW(validate_landmarks(thin, K, "lm.json"));  // accepted: the image may settle it
    // Only one of the two sets thin is enough for the warning.
    std::vector<Landmark> mixed = round;
    for (size_t i = 0; i < mixed.size(); ++i) mixed[i].world_mm = thin[i].world_mm;
    EXPECT_NE(landmark_spread_warning(landmark_spread(mixed)), "");
}

// A cortical patch seen 45 deg off its normal through a narrow lens (a 19 deg field, 450 mm away)
// looks nearly as it would tilted the other way: with a few pixels of picking noise, PnP's best
// fit is often that mirror, 90 deg off, as on the phantom's steep views (evtilt case 0006: 85 deg).
// The fixed 40 deg turns did not reach the true basin; the planar flip, the normal turned to its
// mirror image across the line of sight, does. Among the draws whose best fit is the mirror, the
// candidates hold a pose within 8 deg of the truth; without the flip, none did.
TEST(LandmarkFit, TheCandidatesHoldTheTruePoseWhereTheBestFitIsTheMirrorOfASteepView) {
    const Intrinsics K = steep_view_camera();
    const Pose T = steep_view_pose();
    int mirrored = 0, recovered = 0, by_flip = 0;
    for (uint32_t seed = 1; seed <= 60; ++seed) {
        const auto lms = steep_view_landmarks(K, T, seed, 3.0, 0.0);
        const auto fits = pnp_candidates(lms, K);
        if (angle_deg(fits.front().T_camera_from_world, T) < 40) continue;
        ++mirrored;
        for (const auto& f : fits)
            if (angle_deg(f.T_camera_from_world, T) < 8) {
                ++recovered;
                by_flip += f.method == "pnp-flip";
                EXPECT_LE(f.rms_px, 2 * fits.front().rms_px + 2) << seed;
                break;
            }
    }
    ASSERT_GE(mirrored, 3) << "too few draws whose best fit is the mirror to test anything";
    // (4 of 60 draws are mirrored, and the flip finds the truth in all 4. Without it, 5 are
    // mirrored and none recovered: once, the flip itself is the best fit.)
    EXPECT_EQ(recovered, mirrored) << by_flip << " by the flip";
    EXPECT_GE(by_flip, 1);
}

// Model points off by 1.5 mm (where on the MRI the surgeon clicked) cost the true pose about
// 1.5 x f / z pixels, and five pairs fit six parameters closely enough to hide it: a wrong pose
// can beat the truth by several pixels (evsmall2x case 0002: 55 deg off at 1.4 px, the truth at
// 9.3 px). With world_sd_mm the limit on the other fits' RMS grows by that error in pixels. The
// list only grows (every fit kept without it is kept with it), and every fit kept lies within
// its limit.
TEST(LandmarkFit, TheModelPointsErrorInPixelsWidensTheCandidatesLimit) {
    // The steep view above (5.1 px per mm), model points off by 1.5 mm.
    const Intrinsics K = steep_view_camera();
    const Pose T = steep_view_pose();
    EXPECT_NEAR(landmark_px_per_mm({{"c", Eigen::Vector3d::Zero(), Eigen::Vector2d::Zero()}}, K, T), 2290.0 / 450, 1e-9);
    int grew = 0;
    for (uint32_t seed = 1; seed <= 60; ++seed) {
        const auto lms = steep_view_landmarks(K, T, seed, 2.0, 1.5);
        const auto without = pnp_candidates(lms, K);
        const auto with = pnp_candidates(lms, K, 1.5);
        ASSERT_GE(with.size(), without.size()) << seed;
        grew += with.size() > without.size();
        for (const auto& f : without) {
            bool kept = false;
            for (const auto& g : with) kept |= angle_deg(f.T_camera_from_world, g.T_camera_from_world) < 1e-9;
            EXPECT_TRUE(kept) << seed;
        }
        const double best = with.front().rms_px;
        const double px_per_mm = landmark_px_per_mm(lms, K, with.front().T_camera_from_world);
        EXPECT_GT(px_per_mm, 3.5) << seed;  // f / z at the best fit's depth (the truth's: 5.1)
        for (const auto& g : with) EXPECT_LE(g.rms_px, 2 * best + 2 + 1.5 * px_per_mm + 1e-9) << seed;
        for (const auto& f : without) EXPECT_LE(f.rms_px, 2 * best + 2 + 1e-9) << seed;
        // The registration fits once: the widened list filtered to the plain limit is the plain
        // call's list, pose for pose and in order.
        const auto filtered = landmark_fits_within(with, lms, K, 0.0);
        ASSERT_EQ(filtered.size(), without.size()) << seed;
        for (size_t i = 0; i < filtered.size(); ++i) {
            EXPECT_TRUE(filtered[i].T_camera_from_world == without[i].T_camera_from_world) << seed << " fit " << i;
            EXPECT_EQ(filtered[i].rms_px, without[i].rms_px) << seed << " fit " << i;
        }
    }
    EXPECT_GE(grew, 3);  // 11 of the 60 draws keep more fits
    EXPECT_TRUE(landmark_fits_within({}, steep_view_landmarks(K, T, 1, 2.0, 1.5), K, 1.5).empty());
}

// refine_landmark_fit(): the local fit a given pose lies in. From a pose near the best fit it
// returns the best fit; from the mirror of a steep view it stays in the mirror's basin, which is
// what lets a given pose there be moved to the best fit (landmark_moves_from_nearest_fit).
TEST(LandmarkFit, RefiningAPoseFindsTheFitWhoseBasinItLiesIn) {
    const Intrinsics K = steep_view_camera();
    const Pose T = steep_view_pose();
    int two_basins = 0, stays = 0;
    for (uint32_t seed = 1; seed <= 60; ++seed) {
        const auto lms = steep_view_landmarks(K, T, seed, 3.0, 0.0);
        const auto fits = pnp_candidates(lms, K);
        Pose near_best = fits.front().T_camera_from_world;
        near_best(0, 3) += 1.0;
        const LandmarkFit back = refine_landmark_fit(lms, K, near_best);
        EXPECT_LT(angle_deg(back.T_camera_from_world, fits.front().T_camera_from_world), 1e-3) << seed;
        EXPECT_NEAR(back.rms_px, fits.front().rms_px, 1e-3) << seed;
        EXPECT_EQ(back.method, "refined");
        for (size_t i = 1; i < fits.size(); ++i) {
            if (angle_deg(fits[i].T_camera_from_world, fits.front().T_camera_from_world) < 20) continue;
            ++two_basins;
            // A candidate is where LM stopped (at its iteration limit, on a flat valley), not always
            // a minimum: refined again it stays in its own basin, away from the best fit, or (once
            // in these draws) walks on down to the best fit itself; never worse than it was.
            const LandmarkFit again = refine_landmark_fit(lms, K, fits[i].T_camera_from_world);
            const double to_own = angle_deg(again.T_camera_from_world, fits[i].T_camera_from_world),
                         to_best = angle_deg(again.T_camera_from_world, fits.front().T_camera_from_world);
            EXPECT_TRUE(to_best < 1e-3 || (to_own < to_best && to_best > 10.0)) << seed << " fit " << i << ": " << to_own << " " << to_best;
            stays += to_best > 10.0;
            EXPECT_LE(again.rms_px, fits[i].rms_px + 1e-9) << seed << " fit " << i;
        }
    }
    EXPECT_GE(two_basins, 3);
    EXPECT_GE(stays, two_basins - 1);
    // A pose that puts the landmarks behind the camera is named.
    Pose behind = T;
    behind.topRightCorner<3, 1>() *= -1.0;
    behind.topLeftCorner<3, 3>() = -behind.topLeftCorner<3, 3>();
    behind(0, 0) = -behind(0, 0);  // still a rotation
    EXPECT_THROW(refine_landmark_fit(steep_view_landmarks(K, T, 1, 3.0, 0.0), K, behind), InputError);
}
