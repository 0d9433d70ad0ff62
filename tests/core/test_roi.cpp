// Unit tests of roi.hpp (the closed cardinal spline and its mask) and of the ROI checks of
// case.hpp (parse_roi, validate_roi), where a bad ROI becomes an InputError.
#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/roi.hpp"

using namespace cf;

namespace {

Roi square(double x0, double y0, double side, double tension) {
    Roi r;
    r.tension = tension;
    r.points = {{x0, y0}, {x0 + side, y0}, {x0 + side, y0 + side}, {x0, y0 + side}};
    return r;
}

Roi pentagon(double tension) {
    Roi r;
    r.tension = tension;
    r.points = {{100, 40}, {170, 90}, {150, 170}, {60, 160}, {35, 85}};
    return r;
}

double min_distance(const std::vector<Eigen::Vector2d>& curve, const Eigen::Vector2d& p) {
    double best = std::numeric_limits<double>::infinity();
    for (const auto& q : curve) best = std::min(best, (q - p).norm());
    return best;
}

/// Distance from p to the segment ab.
double segment_distance(const Eigen::Vector2d& p, const Eigen::Vector2d& a, const Eigen::Vector2d& b) {
    const double t = std::clamp((p - a).dot(b - a) / (b - a).squaredNorm(), 0.0, 1.0);
    return (a + t * (b - a) - p).norm();
}

double polygon_area(const std::vector<Eigen::Vector2d>& p) {
    double a = 0;
    for (size_t i = 0; i < p.size(); ++i) {
        const auto& u = p[i];
        const auto& v = p[(i + 1) % p.size()];
        a += u.x() * v.y() - v.x() * u.y();
    }
    return std::abs(a) / 2;
}

Intrinsics camera(int w, int h) {
    Intrinsics K;
    K.width = w;
    K.height = h;
    K.fx = K.fy = 500;
    K.cx = (w - 1) / 2.0;
    K.cy = (h - 1) / 2.0;
    return K;
}

}  // namespace

TEST(Roi, SplinePassesThroughEveryControlPoint) {
    for (const double tension : {-0.5, 0.0, 0.5, 1.0})
        for (const int samples : {4, 16, 25}) {
            const Roi r = pentagon(tension);
            const auto curve = cardinal_spline_closed(r, samples);
            ASSERT_EQ(curve.size(), r.points.size() * size_t(samples));
            for (const auto& p : r.points) EXPECT_LT(min_distance(curve, p), 1e-9) << "tension " << tension;
            // Closed and continuous: consecutive samples (and last -> first) are close.
            double longest = 0;
            for (size_t i = 0; i < curve.size(); ++i) longest = std::max(longest, (curve[i] - curve[(i + 1) % curve.size()]).norm());
            EXPECT_LT(longest, 130.0 / samples * 1.6) << "tension " << tension;
        }
}

TEST(Roi, TensionOneIsThePolygonAndLowerTensionBulgesOutwards) {
    const Roi straight = pentagon(1.0);
    const auto poly = cardinal_spline_closed(straight, 16);
    const auto& p = straight.points;
    for (const auto& q : poly) {
        double d = std::numeric_limits<double>::infinity();
        for (size_t i = 0; i < p.size(); ++i) d = std::min(d, segment_distance(q, p[i], p[(i + 1) % p.size()]));
        EXPECT_LT(d, 1e-9);
    }
    // Catmull-Rom (0) bows out of a convex polygon; tension changes the curve monotonically.
    const double a1 = polygon_area(poly);
    const double a05 = polygon_area(cardinal_spline_closed(pentagon(0.5), 16));
    const double a0 = polygon_area(cardinal_spline_closed(pentagon(0.0), 16));
    EXPECT_NEAR(a1, polygon_area(p), 1e-6);
    EXPECT_GT(a05, a1 + 50);
    EXPECT_GT(a0, a05 + 50);
    // Sample by sample the curves differ between control points.
    const auto c0 = cardinal_spline_closed(pentagon(0.0), 16);
    EXPECT_GT((c0[8] - poly[8]).norm(), 1.0);
    // Fewer than three points: no curve.
    Roi two;
    two.points = {{0, 0}, {10, 10}};
    EXPECT_TRUE(cardinal_spline_closed(two, 16).empty());
}

TEST(Roi, MaskAreaOfASquare) {
    // A 100 px square (pixel centres 50..150) with straight sides: ~100^2 pixels.
    const cv::Mat m = roi_mask(square(50, 50, 100, 1.0), 200, 220);
    ASSERT_EQ(m.type(), CV_8U);
    EXPECT_EQ(m.cols, 200);
    EXPECT_EQ(m.rows, 220);
    const int area = cv::countNonZero(m);
    EXPECT_NEAR(area, 100 * 100, 0.03 * 100 * 100);
    EXPECT_EQ(m.at<uint8_t>(100, 100), 255);
    EXPECT_EQ(m.at<uint8_t>(40, 100), 0);
    EXPECT_EQ(m.at<uint8_t>(100, 160), 0);
    double mn, mx;
    cv::minMaxLoc(m, &mn, &mx);
    EXPECT_EQ(mx, 255);
    // The same spline with tension 0 is rounder and bulges out of the square.
    const int round = cv::countNonZero(roi_mask(square(50, 50, 100, 0.0), 200, 220));
    EXPECT_NEAR(round, polygon_area(cardinal_spline_closed(square(50, 50, 100, 0.0), 64)), 0.03 * round);
    EXPECT_GT(round, area + 500);
    // Scaled for a photo resized by 0.5: a quarter of the area.
    const int half = cv::countNonZero(roi_mask(square(50, 50, 100, 1.0), 100, 110, 0.5));
    EXPECT_NEAR(half, 50 * 50, 0.05 * 50 * 50);
    // Degenerate ROI: an empty mask of the right size.
    Roi two;
    two.points = {{0, 0}, {10, 10}};
    const cv::Mat e = roi_mask(two, 30, 20);
    EXPECT_EQ(e.cols, 30);
    EXPECT_EQ(cv::countNonZero(e), 0);
}

TEST(Roi, TooFewPointsOrPointsOutsideThePhotoAreInputErrors) {
    const Intrinsics K = camera(320, 240);
    EXPECT_NO_THROW(validate_roi(square(10, 10, 100, 0.0), K, "roi.json"));
    Roi two = square(10, 10, 100, 0.0);
    two.points.resize(2);
    try {
        validate_roi(two, K, "roi.json");
        ADD_FAILURE() << "2 points accepted";
    } catch (const InputError& e) {
        EXPECT_EQ(e.input(), "roi.json");
        EXPECT_NE(std::string(e.what()).find("at least 3 points"), std::string::npos) << e.what();
    }
    for (const Eigen::Vector2d& bad : {Eigen::Vector2d(320, 10), Eigen::Vector2d(10, -1), Eigen::Vector2d(10, 240)}) {
        Roi r = square(10, 10, 100, 0.0);
        r.points[2] = bad;
        try {
            validate_roi(r, K, "roi.json");
            ADD_FAILURE() << "point " << bad.transpose() << " accepted";
        } catch (const InputError& e) {
            EXPECT_EQ(e.input(), "roi.json");
            EXPECT_NE(std::string(e.what()).find("outside the 320x240 photo"), std::string::npos) << e.what();
        }
    }
    // Inside but enclosing almost nothing.
    EXPECT_THROW(validate_roi(square(10, 10, 5, 1.0), K, "roi.json"), InputError);
}

TEST(Roi, ParseRoiChecksTypeTensionAndPoints) {
    using nlohmann::json;
    const Roi r = parse_roi(json{{"type", "closed-cardinal-spline"}, {"tension", 0.25}, {"points", {{1, 2}, {3, 4}, {5, 7}}}}, "roi.json");
    EXPECT_DOUBLE_EQ(r.tension, 0.25);
    ASSERT_EQ(r.points.size(), 3u);
    EXPECT_EQ(r.points[2], Eigen::Vector2d(5, 7));
    auto fails = [](const json& j, const std::string& problem) {
        try {
            parse_roi(j, "roi.json");
            ADD_FAILURE() << "accepted " << j.dump();
        } catch (const InputError& e) {
            EXPECT_EQ(e.input(), "roi.json");
            EXPECT_NE(std::string(e.what()).find(problem), std::string::npos) << e.what();
        }
    };
    fails(json{{"type", "polygon"}, {"points", {{1, 2}, {3, 4}, {5, 7}}}}, "closed-cardinal-spline");
    fails(json{{"tension", 2.0}, {"points", {{1, 2}, {3, 4}, {5, 7}}}}, "tension must lie in [-1, 1]");
    fails(json{{"points", 5}}, "\"points\" must be an array");
    fails(json{{"points", {{1, 2, 3}, {3, 4}, {5, 7}}}}, "each ROI point must be [u, v]");
}
