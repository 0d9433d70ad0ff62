// Navigation math against known truth: pivot calibration, fiducial registration (FRE, outliers,
// predicted TRE against a Monte Carlo), digitising and brain shift. Seeded noise only.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <limits>
#include <random>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/navigation.hpp"

using namespace cf;
using Eigen::Vector3d;

namespace {

constexpr double kPi = 3.14159265358979323846;

RigidTransform make_T(const Eigen::Matrix3d& R, const Vector3d& t) {
    RigidTransform T = RigidTransform::Identity();
    T.topLeftCorner<3, 3>() = R;
    T.topRightCorner<3, 1>() = t;
    return T;
}

Eigen::Matrix3d axis_angle(const Vector3d& axis, double deg) {
    return Eigen::AngleAxisd(deg * kPi / 180, axis.normalized()).toRotationMatrix();
}

Vector3d apply(const RigidTransform& T, const Vector3d& p) { return T.topLeftCorner<3, 3>() * p + T.topRightCorner<3, 1>(); }

/// Poses of a pointer pivoting about `pivot` with its tip at `tip` (tool frame): handle swivelled
/// within a cone of `cone_deg` about two axes (and spun about the shaft), tracker noise added.
std::vector<RigidTransform> pivot_poses(const Vector3d& tip, const Vector3d& pivot, int n, double cone_deg, double noise_mm,
                                        std::mt19937_64& rng, bool one_axis = false) {
    std::uniform_real_distribution<double> u(-1, 1);
    std::normal_distribution<double> g(0, 1);
    const Eigen::Matrix3d base = axis_angle(Vector3d(0.3, 1, 0.2), 70);
    std::vector<RigidTransform> out;
    for (int i = 0; i < n; ++i) {
        Eigen::Matrix3d R;
        if (one_axis)
            R = base * axis_angle(Vector3d::UnitX(), cone_deg * u(rng));
        else
            R = base * axis_angle(Vector3d::UnitX(), cone_deg * u(rng)) * axis_angle(Vector3d::UnitY(), cone_deg * u(rng)) *
                axis_angle(Vector3d::UnitZ(), 40 * u(rng));
        const Vector3d t = pivot - R * tip + noise_mm * Vector3d(g(rng), g(rng), g(rng));
        out.push_back(make_T(R, t));
    }
    return out;
}

/// Skin fiducials spread over a head-sized ellipsoid (image space, LPS mm).
std::vector<Vector3d> head_fiducials(int n, std::mt19937_64& rng) {
    std::uniform_real_distribution<double> u(-1, 1);
    std::vector<Vector3d> out;
    while (int(out.size()) < n) {
        Vector3d d(u(rng), u(rng), std::abs(u(rng)));  // upper half of the head
        if (d.norm() < 0.2) continue;
        d.normalize();
        out.push_back(Vector3d(75 * d.x(), 95 * d.y(), 80 * d.z()) + Vector3d(2, -20, 30));
    }
    return out;
}

}  // namespace

// ------------------------------------------------------------------ pivot

TEST(Pivot, RecoversTipAndPivotWithNoise) {
    std::mt19937_64 rng(11);
    const Vector3d tip(1.5, -2.0, -160.0), pivot(30, -40, -1200);
    const auto poses = pivot_poses(tip, pivot, 60, 30, 0.25, rng);
    const PivotResult r = pivot_calibration(poses);
    EXPECT_LT((r.tip_tool_mm - tip).norm(), 0.3);
    EXPECT_LT((r.pivot_tracker_mm - pivot).norm(), 0.3);
    // rms of the residual of 3D noise (0.25 mm per axis) is about 0.25*sqrt(3) minus the fit's dof.
    EXPECT_GT(r.rms_mm, 0.25);
    EXPECT_LT(r.rms_mm, 0.5);
    EXPECT_EQ(r.residuals_mm.size(), poses.size());
    EXPECT_GT(r.rotation_spread_deg, 10);
    EXPECT_TRUE(r.warning.empty()) << r.warning;
}

TEST(Pivot, ExactDataGivesExactTip) {
    std::mt19937_64 rng(3);
    const Vector3d tip(0, 0, -120), pivot(-5, 10, -900);
    const PivotResult r = pivot_calibration(pivot_poses(tip, pivot, 12, 25, 0.0, rng));
    EXPECT_LT((r.tip_tool_mm - tip).norm(), 1e-8);
    EXPECT_LT(r.rms_mm, 1e-8);
}

TEST(Pivot, SmallMotionWarns) {
    std::mt19937_64 rng(5);
    const PivotResult r = pivot_calibration(pivot_poses(Vector3d(0, 0, -150), Vector3d(0, 0, -1000), 30, 3, 0.1, rng));
    EXPECT_LT(r.rotation_spread_deg, 10);
    EXPECT_NE(r.warning.find("did not move enough"), std::string::npos) << r.warning;
}

TEST(Pivot, RotationAboutOneAxisOnlyIsRefused) {
    // Spinning about one axis leaves the tip's component along that axis undetermined.
    std::mt19937_64 rng(6);
    const auto poses = pivot_poses(Vector3d(0, 0, -150), Vector3d(0, 0, -1000), 20, 30, 0.0, rng, true);
    EXPECT_THROW(pivot_calibration(poses), InputError);
}

TEST(Pivot, BadInput) {
    std::mt19937_64 rng(7);
    auto poses = pivot_poses(Vector3d(0, 0, -150), Vector3d(0, 0, -1000), 20, 30, 0.1, rng);
    EXPECT_THROW(pivot_calibration({poses[0], poses[1]}), InputError);  // too few
    auto nan = poses;
    nan[4](1, 3) = std::numeric_limits<double>::quiet_NaN();
    EXPECT_THROW(pivot_calibration(nan), InputError);
    auto sheared = poses;
    sheared[2](0, 1) += 0.2;
    try {
        pivot_calibration(sheared);
        FAIL() << "a non-rigid pose was accepted";
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("pose 2 is not a rigid"), std::string::npos) << e.what();
    }
    PivotOptions o;
    o.min_rotation_spread_deg = -1;
    EXPECT_THROW(pivot_calibration(poses, o), InputError);
}

// ------------------------------------------------------------------ fiducial registration

TEST(Fiducials, ExactDataGivesTruthAndZeroFre) {
    std::mt19937_64 rng(21);
    const auto img = head_fiducials(6, rng);
    const RigidTransform T_patient_from_image = make_T(axis_angle(Vector3d(1, -2, 0.5), 63), Vector3d(-300, 12, 900));
    std::vector<Vector3d> pat;
    for (const auto& p : img) pat.push_back(apply(T_patient_from_image, p));
    const FiducialRegistration r = register_fiducials(pat, img);
    EXPECT_LT((r.T_image_from_patient * T_patient_from_image - RigidTransform::Identity()).norm(), 1e-9);
    EXPECT_LT(r.fre_mm, 1e-9);
    EXPECT_EQ(r.n_used, 6);
    EXPECT_TRUE(r.excluded.empty());
    EXPECT_NEAR(predicted_tre_mm(r, Vector3d(10, 10, 60)), 0.0, 1e-9);
}

TEST(Fiducials, FreAndPredictedTreMatchMonteCarlo) {
    // Fitzpatrick: <FRE²> = (1 - 2/N) FLE², and the TRE formula predicts the rms TRE at a target.
    std::mt19937_64 rng(22);
    const int N = 6;
    const double fle = 1.0;  // rms 3D
    const auto img = head_fiducials(N, rng);
    const RigidTransform T_patient_from_image = make_T(axis_angle(Vector3d(0.2, 1, 0.1), -40), Vector3d(50, -700, 100));
    const Vector3d target(30, 0, 70);  // a cortical target under the fiducials
    std::normal_distribution<double> g(0, fle / std::sqrt(3.0));
    FiducialOptions o;
    o.outlier_threshold_mm = 0;  // no exclusion: the statistics are over all fiducials
    o.fle_mm = fle;
    double fre2 = 0, tre2 = 0, pred = 0;
    const int trials = 800;
    for (int k = 0; k < trials; ++k) {
        // Localisation error on the digitised side only: the FLE of the formula is that one.
        std::vector<Vector3d> pat;
        for (const auto& p : img) pat.push_back(apply(T_patient_from_image, p) + Vector3d(g(rng), g(rng), g(rng)));
        const FiducialRegistration r = register_fiducials(pat, img, o);
        fre2 += r.fre_mm * r.fre_mm;
        const Vector3d mapped = apply(r.T_image_from_patient * T_patient_from_image, target);
        tre2 += (mapped - target).squaredNorm();
        pred += predicted_tre_mm(r, target);
    }
    const double fre_rms = std::sqrt(fre2 / trials), tre_rms = std::sqrt(tre2 / trials);
    pred /= trials;
    EXPECT_NEAR(fre_rms, fle * std::sqrt(1.0 - 2.0 / N), 0.05);
    EXPECT_NEAR(tre_rms / pred, 1.0, 0.1) << "Monte Carlo TRE " << tre_rms << " vs predicted " << pred;
    // Farther from the fiducials' centroid the prediction grows.
    std::vector<Vector3d> pat;
    for (const auto& p : img) pat.push_back(apply(T_patient_from_image, p));
    const auto r = register_fiducials(pat, img, o);
    EXPECT_GT(predicted_tre_mm(r, target + Vector3d(0, 0, 150)), predicted_tre_mm(r, r.centroid_image_mm));
    EXPECT_NEAR(predicted_tre_mm(r, r.centroid_image_mm), fle / std::sqrt(double(N)), 1e-9);
}

TEST(Fiducials, EstimatesFleFromFreWhenNotGiven) {
    std::mt19937_64 rng(23);
    const auto img = head_fiducials(8, rng);
    std::normal_distribution<double> g(0, 0.5);
    std::vector<Vector3d> pat;
    for (const auto& p : img) pat.push_back(p + Vector3d(100, 0, 0) + Vector3d(g(rng), g(rng), g(rng)));
    const auto r = register_fiducials(pat, img);
    EXPECT_NEAR(r.fle_mm, r.fre_mm * std::sqrt(8.0 / 6.0), 1e-12);
}

TEST(Fiducials, DropsTheOutlierAndReportsIt) {
    std::mt19937_64 rng(24);
    const auto img = head_fiducials(7, rng);
    const RigidTransform T_patient_from_image = make_T(axis_angle(Vector3d(1, 1, 1), 30), Vector3d(10, 20, 30));
    std::normal_distribution<double> g(0, 0.3);
    std::vector<Vector3d> pat;
    for (const auto& p : img) pat.push_back(apply(T_patient_from_image, p) + Vector3d(g(rng), g(rng), g(rng)));
    pat[4] += Vector3d(12, -6, 4);  // a skin marker that moved
    const auto r = register_fiducials(pat, img);
    ASSERT_EQ(r.excluded.size(), 1u);
    EXPECT_EQ(r.excluded[0], 4);
    EXPECT_FALSE(r.used[4]);
    EXPECT_EQ(r.n_used, 6);
    EXPECT_LT(r.fre_mm, 1.0);
    EXPECT_GT(r.residuals_mm[4], 10.0);  // reported with the final transform
    const RigidTransform err = r.T_image_from_patient * T_patient_from_image;
    EXPECT_LT(err.topRightCorner(3, 1).norm(), 1.0);

    FiducialOptions off;
    off.outlier_threshold_mm = 0;
    const auto all = register_fiducials(pat, img, off);
    EXPECT_TRUE(all.excluded.empty());
    EXPECT_GT(all.fre_mm, 3.0);
}

TEST(Fiducials, NeverDropsBelowThree) {
    std::mt19937_64 rng(25);
    const auto img = head_fiducials(3, rng);
    std::vector<Vector3d> pat = img;
    pat[1] += Vector3d(0, 0, 40);
    const auto r = register_fiducials(pat, img);
    EXPECT_TRUE(r.excluded.empty());
    EXPECT_EQ(r.n_used, 3);
    // The worst residual is above the 5 mm threshold: only the count kept it.
    EXPECT_GT(*std::max_element(r.residuals_mm.begin(), r.residuals_mm.end()), 5.0);
    EXPECT_GT(r.fre_mm, 3.0);
}

TEST(Fiducials, BadInput) {
    std::mt19937_64 rng(26);
    const auto img = head_fiducials(5, rng);
    EXPECT_THROW(register_fiducials({img[0], img[1]}, {img[0], img[1]}), InputError);           // fewer than 3
    EXPECT_THROW(register_fiducials(img, {img[0], img[1], img[2], img[3]}), InputError);        // count mismatch
    std::vector<Vector3d> line = {Vector3d(0, 0, 0), Vector3d(10, 10, 10), Vector3d(20, 20, 20.1), Vector3d(35, 35, 35)};
    try {
        register_fiducials(line, line);
        FAIL() << "collinear fiducials were accepted";
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("collinear"), std::string::npos) << e.what();
    }
    auto nan = img;
    nan[2].y() = std::numeric_limits<double>::quiet_NaN();
    EXPECT_THROW(register_fiducials(nan, img), InputError);
    EXPECT_THROW(register_fiducials(img, nan), InputError);
    const auto ok = register_fiducials(img, img);
    EXPECT_THROW(predicted_tre_mm(ok, Vector3d(std::numeric_limits<double>::infinity(), 0, 0)), InputError);
}

// ------------------------------------------------------------------ digitising and brain shift

TEST(BrainShift, DigitiseAndRedigitiseRecoverTheShiftPerAxis) {
    std::mt19937_64 rng(31);
    std::normal_distribution<double> g(0, 0.1);
    const Vector3d tip(0, 0, -150);
    const RigidTransform T_tracker_from_reference = make_T(axis_angle(Vector3d(0, 1, 0), 20), Vector3d(-100, 50, -1100));
    const RigidTransform T_image_from_patient = make_T(axis_angle(Vector3d(1, 0, 0.3), 100), Vector3d(5, 6, 7));
    const RigidTransform T_patient_from_image = T_image_from_patient.inverse();
    // Cortical landmarks (image) and their true shift (sinking under gravity, some lateral).
    const std::vector<Vector3d> lm = {{40, -10, 60}, {45, 5, 58}, {38, 15, 55}, {50, -2, 50}, {42, 20, 62}};
    const std::vector<Vector3d> shift = {{0.5, 1.0, -3.0}, {0.2, 0.8, -4.1}, {-0.3, 0.4, -2.2}, {1.0, 1.5, -5.0}, {0.0, 0.2, -1.0}};
    auto digitise = [&](const Vector3d& p_image, const std::string& label) {
        const Vector3d p_tracker = apply(T_tracker_from_reference * T_patient_from_image, p_image);
        std::vector<PointerFrame> frames;
        for (int f = 0; f < 20; ++f) {
            const Eigen::Matrix3d R = axis_angle(Vector3d(0.4, 1, 0.1), 60 + f);  // the handle may tilt while held
            PointerFrame pf;
            pf.T_tracker_from_pointer = make_T(R, p_tracker - R * tip + Vector3d(g(rng), g(rng), g(rng)));
            pf.T_tracker_from_reference = T_tracker_from_reference;
            frames.push_back(pf);
        }
        return digitise_point(label, frames, tip, T_image_from_patient);
    };
    std::vector<DigitisedPoint> before, after;
    for (size_t i = 0; i < lm.size(); ++i) {
        before.push_back(digitise(lm[i], "L" + std::to_string(i + 1)));
        EXPECT_LT((before.back().p_image_mm - lm[i]).norm(), 0.15);
        EXPECT_LT(before.back().spread_mm, 0.3);
    }
    for (size_t i = lm.size(); i-- > 0;) after.push_back(digitise(lm[i] + shift[i], "L" + std::to_string(i + 1)));
    const BrainShiftReport r = brain_shift(before, after);
    ASSERT_EQ(r.rows.size(), lm.size());
    Vector3d mean = Vector3d::Zero();
    for (const auto& row : r.rows) {
        const size_t i = size_t(std::stoi(row.label.substr(1)) - 1);
        EXPECT_LT((row.d_mm - shift[i]).norm(), 0.15) << row.label;
        EXPECT_NEAR(row.magnitude_mm, shift[i].norm(), 0.15);
        mean += shift[i];
    }
    mean /= double(shift.size());
    EXPECT_LT((r.mean_d_mm - mean).norm(), 0.1);
    EXPECT_GT(r.sd_magnitude_mm, 0.5);
    const std::string table = format_brain_shift_table(r);
    EXPECT_NE(table.find("mean ± sd"), std::string::npos);
    EXPECT_NE(table.find("L4"), std::string::npos);
}

TEST(BrainShift, ExactStatistics) {
    auto pt = [](const std::string& l, double x, double y, double z) {
        DigitisedPoint d;
        d.label = l;
        d.p_image_mm = Vector3d(x, y, z);
        return d;
    };
    const std::vector<DigitisedPoint> a = {pt("A", 0, 0, 0), pt("B", 10, 0, 0), pt("C", 0, 10, 0), pt("D", 5, 5, 5)};
    const std::vector<DigitisedPoint> b = {pt("A", 3, 0, -4), pt("B", 10, 0, 0), pt("E", 1, 1, 1)};
    const auto r = brain_shift(a, b);
    ASSERT_EQ(r.rows.size(), 2u);
    EXPECT_DOUBLE_EQ(r.rows[0].magnitude_mm, 5.0);
    EXPECT_DOUBLE_EQ(r.mean_magnitude_mm, 2.5);
    EXPECT_NEAR(r.sd_magnitude_mm, std::sqrt(12.5), 1e-12);
    EXPECT_DOUBLE_EQ(r.mean_d_mm.z(), -2.0);
    EXPECT_DOUBLE_EQ(r.mean_abs_d_mm.x(), 1.5);
    EXPECT_EQ(r.missing_later, (std::vector<std::string>{"C", "D"}));
    EXPECT_EQ(r.missing_earlier, (std::vector<std::string>{"E"}));
}

TEST(BrainShift, BadInput) {
    DigitisedPoint a;
    a.label = "A";
    DigitisedPoint b = a;
    b.label = "B";
    EXPECT_THROW(brain_shift({a, a}, {a}), InputError);  // duplicate label
    EXPECT_THROW(brain_shift({a}, {b}), InputError);     // nothing in common
    DigitisedPoint n = a;
    n.p_image_mm.x() = std::numeric_limits<double>::quiet_NaN();
    EXPECT_THROW(brain_shift({a}, {n}), InputError);

    // Digitising: no frames, a tip that wanders.
    EXPECT_THROW(digitise_point("L1", {}, Vector3d(0, 0, -150), RigidTransform::Identity()), InputError);
    std::vector<PointerFrame> frames(10);
    for (int i = 0; i < 10; ++i) frames[size_t(i)].T_tracker_from_pointer.topRightCorner<3, 1>() = Vector3d(0, 0, i * 1.0);
    try {
        digitise_point("L7", frames, Vector3d(0, 0, -150), RigidTransform::Identity());
        FAIL() << "a moving tip was accepted";
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("landmark L7"), std::string::npos) << e.what();
        EXPECT_NE(std::string(e.what()).find("moved"), std::string::npos) << e.what();
    }
}
