// `cortexfuse landscape` as a researcher runs it to see where the similarity peaks about a
// case's pose: the JSON carries each axis' values (so two cases can be compared, where each
// panel of the picture is scaled to its own range), the picture is written, a pose file (a
// register result) is swept about as the truth is, and a bad `--about` or pose file is one line
// naming it, with no picture.
#include <gtest/gtest.h>

#include <opencv2/imgcodecs.hpp>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>
#include <vector>

#include "base_case.hpp"
#include "cli_files.hpp"
#include "process.hpp"

namespace fs = std::filesystem;
using nlohmann::json;
using namespace cf;

namespace {

test::ProcessResult run_landscape(std::vector<std::string> args) {
    std::vector<std::string> argv{test::cortexfuse_exe(), "landscape"};
    argv.insert(argv.end(), args.begin(), args.end());
    return test::run_process(argv, 300.0);
}

}  // namespace

TEST(LandscapeCli, EachAxisCarriesItsValuesAndThePoseLiesWithinThem) {
    const fs::path c = test::base_cases() / "small";
    const fs::path work = test::fresh_dir("landscape");
    // An odd and an even count: with an even one no sample lies on the pose itself, and the
    // nearest one stands for it.
    for (const char* steps : {"9", "8"}) {
        const fs::path png = work / (std::string("l") + steps + ".png");
        const auto r = run_landscape({c.string(), "--out", png.string(), "--steps", steps, "--width-px", "96",
                                      "--range-mm", "6", "--range-deg", "6"});
        ASSERT_EQ(r.exit_code, 0) << r.err;
        const cv::Mat picture = cv::imread(png.string(), cv::IMREAD_COLOR);  // 3 x 2 panels
        EXPECT_EQ(picture.cols, 900);
        EXPECT_EQ(picture.rows, 462);
        const json j = json::parse(r.out);
        EXPECT_EQ(j.at("metric"), "nmi");
        ASSERT_EQ(j.at("peak_offsets").size(), 6u);
        const json& axes = j.at("axes");
        ASSERT_EQ(axes.size(), 6u);
        int i = 0;
        double at_pose = 0;
        for (const char* k : {"rx_deg", "ry_deg", "rz_deg", "tx_mm", "ty_mm", "tz_mm"}) {
            const json& a = axes.at(k);
            const double lo = a.at("similarity_min"), hi = a.at("similarity_peak"), at = a.at("similarity_at_pose");
            EXPECT_LT(lo, hi) << k;  // the photo does vary with the pose
            EXPECT_LE(lo, at) << k;
            EXPECT_LE(at, hi) << k;
            EXPECT_GT(lo, 0.99) << k;  // NMI lies in [1, 2]
            EXPECT_LT(hi, 2.0) << k;
            EXPECT_LE(std::abs(a.at("peak_offset").get<double>()), 6.0 + 1e-9) << k;
            EXPECT_EQ(a.at("peak_offset"), j.at("peak_offsets").at(size_t(i++))) << k;
            // The curve itself: --steps samples from -range to +range, the peak among them.
            const auto xs = a.at("offsets").get<std::vector<double>>(), ys = a.at("similarity").get<std::vector<double>>();
            ASSERT_EQ(xs.size(), size_t(std::stoi(steps))) << k;
            ASSERT_EQ(ys.size(), xs.size()) << k;
            EXPECT_NEAR(xs.front(), -6.0, 1e-9) << k;
            EXPECT_NEAR(xs.back(), 6.0, 1e-9) << k;
            EXPECT_EQ(*std::max_element(ys.begin(), ys.end()), hi) << k;
            EXPECT_EQ(*std::min_element(ys.begin(), ys.end()), lo) << k;
            // The peak's prominence: above the best sample more than 3 (mm or deg) from it.
            const size_t best = size_t(std::max_element(ys.begin(), ys.end()) - ys.begin());
            double rival = lo;
            for (size_t s = 0; s < xs.size(); ++s)
                if (std::abs(xs[s] - xs[best]) > 3) rival = std::max(rival, ys[s]);
            EXPECT_NEAR(a.at("peak_prominence").get<double>(), (hi - rival) / (hi - lo), 1e-9) << k;
            // On an odd count every axis' middle sample is the pose itself: the same value.
            if (std::string(steps) == "9") {
                if (i == 1) at_pose = at;
                EXPECT_DOUBLE_EQ(at, at_pose) << k;
            }
        }
    }
    fs::remove_all(work);
}

TEST(LandscapeCli, ABadAboutIsOneLineNamingItAndNoPicture) {
    const fs::path c = test::base_cases() / "small";
    const fs::path work = test::fresh_dir("landscape_bad");
    const auto r = run_landscape({c.string(), "--out", (work / "l.png").string(), "--about", "sideways"});
    EXPECT_NE(r.exit_code, 0);
    EXPECT_NE(r.err.find("--about sideways"), std::string::npos) << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    EXPECT_FALSE(fs::exists(work / "l.png"));
    fs::remove_all(work);
}

TEST(LandscapeCli, APoseFileIsSweptAboutAsTheTruthIsAndABadOneIsNamed) {
    const fs::path c = test::base_cases() / "small";
    const fs::path work = test::fresh_dir("landscape_pose");
    const std::vector<std::string> fast{"--steps", "5", "--width-px", "96"};
    auto args = [&](std::vector<std::string> a) {
        a.insert(a.end(), fast.begin(), fast.end());
        return a;
    };
    const auto by_truth = run_landscape(args({c.string(), "--out", (work / "t.png").string()}));
    ASSERT_EQ(by_truth.exit_code, 0) << by_truth.err;
    // truth.json holds T_camera_from_world, as a register result does.
    const auto by_file = run_landscape(args({c.string(), "--out", (work / "p.png").string(), "--pose", (c / "truth.json").string()}));
    ASSERT_EQ(by_file.exit_code, 0) << by_file.err;
    const json a = json::parse(by_truth.out), b = json::parse(by_file.out);
    EXPECT_EQ(b.at("about"), "pose");
    EXPECT_EQ(a.at("axes"), b.at("axes"));
    // Not rigid: refused, named, no picture.
    json bad = test::read_json(c / "truth.json");
    bad["T_camera_from_world"][0][0] = 2.0;
    test::write_json(work / "scaled.json", bad);
    const auto r = run_landscape(args({c.string(), "--out", (work / "s.png").string(), "--pose", (work / "scaled.json").string()}));
    EXPECT_NE(r.exit_code, 0);
    EXPECT_NE(r.err.find("scaled.json"), std::string::npos) << r.err;
    EXPECT_EQ(std::count(r.err.begin(), r.err.end(), '\n'), 1) << r.err;
    EXPECT_FALSE(fs::exists(work / "s.png"));
    // A register result's estimated light is swept under too; a malformed one is named.
    EXPECT_EQ(a.at("light"), "headlight");
    json lit = test::read_json(c / "truth.json");
    lit["light_direction_camera"] = {0, 0, -1};  // how a result without an estimate says headlight
    test::write_json(work / "headlight.json", lit);
    const auto by_headlight = run_landscape(args({c.string(), "--out", (work / "h.png").string(), "--pose", (work / "headlight.json").string()}));
    ASSERT_EQ(by_headlight.exit_code, 0) << by_headlight.err;
    EXPECT_EQ(json::parse(by_headlight.out).at("axes"), a.at("axes"));
    lit["light_position_camera_mm"] = {-80, 80, 0};
    test::write_json(work / "lamp.json", lit);
    const auto by_lamp = run_landscape(args({c.string(), "--out", (work / "lamp.png").string(), "--pose", (work / "lamp.json").string()}));
    ASSERT_EQ(by_lamp.exit_code, 0) << by_lamp.err;
    const json l = json::parse(by_lamp.out);
    EXPECT_EQ(l.at("light"), "point");
    EXPECT_NE(l.at("axes"), a.at("axes"));
    lit["light_position_camera_mm"] = {-80, "up", 0};
    test::write_json(work / "bad_lamp.json", lit);
    const auto bad_lamp = run_landscape(args({c.string(), "--out", (work / "b.png").string(), "--pose", (work / "bad_lamp.json").string()}));
    EXPECT_NE(bad_lamp.exit_code, 0);
    EXPECT_NE(bad_lamp.err.find("bad_lamp.json"), std::string::npos) << bad_lamp.err;
    EXPECT_NE(bad_lamp.err.find("light_position_camera_mm"), std::string::npos) << bad_lamp.err;
    EXPECT_EQ(std::count(bad_lamp.err.begin(), bad_lamp.err.end(), '\n'), 1) << bad_lamp.err;
    EXPECT_FALSE(fs::exists(work / "b.png"));
    fs::remove_all(work);
}

// --inputs: the photo and rendering as the similarity compares them, side by side and overlaid.
// Three panels of one size; where the ROI's margin lies the panels carry the "not counted"
// colour, and the ROI itself shows the images. An unwritable path is one line naming it.
TEST(LandscapeCli, TheInputsPictureShowsThePhotoAndRenderingTheSimilarityCompared) {
    const fs::path c = test::base_cases() / "small";
    const fs::path work = test::fresh_dir("landscape_inputs");
    const fs::path inputs = work / "inputs.png";
    const auto r = run_landscape({c.string(), "--out", (work / "l.png").string(), "--inputs", inputs.string(), "--steps",
                                  "3", "--width-px", "96"});
    ASSERT_EQ(r.exit_code, 0) << r.err;
    const cv::Mat picture = cv::imread(inputs.string(), cv::IMREAD_COLOR);
    ASSERT_FALSE(picture.empty());
    ASSERT_EQ(picture.cols % 3, 0);
    const int pw = picture.cols / 3;
    EXPECT_GE(pw, 400);
    const cv::Mat panels = picture(cv::Rect(0, 26, picture.cols, picture.rows - 26));
    const cv::Vec3b not_counted(60, 30, 30);
    for (int k = 0; k < 3; ++k) {
        const cv::Mat panel = panels(cv::Rect(k * pw, 0, pw, panels.rows));
        int dimmed = 0, shown = 0;
        for (int y = 0; y < panel.rows; ++y)
            for (int x = 0; x < panel.cols; ++x) (panel.at<cv::Vec3b>(y, x) == not_counted ? dimmed : shown)++;
        EXPECT_GT(dimmed, 0) << "panel " << k;
        EXPECT_GT(shown, panel.rows * panel.cols / 10) << "panel " << k;
    }
    // The photo panel is grey; the overlay has the two in different channels, so it is not.
    cv::Mat photo_panel = panels(cv::Rect(0, 0, pw, panels.rows)), overlay = panels(cv::Rect(2 * pw, 0, pw, panels.rows));
    std::vector<cv::Mat> ch;
    cv::split(photo_panel, ch);
    cv::Mat shown_mask;
    cv::inRange(photo_panel, cv::Scalar(60, 30, 30), cv::Scalar(60, 30, 30), shown_mask);
    cv::bitwise_not(shown_mask, shown_mask);
    EXPECT_EQ(cv::norm(ch[0], ch[1], cv::NORM_L1, shown_mask), 0);
    cv::split(overlay, ch);
    EXPECT_GT(cv::norm(ch[0], ch[1], cv::NORM_L1, shown_mask), 0);

    const auto bad = run_landscape({c.string(), "--out", (work / "m.png").string(), "--inputs",
                                    (work / "no_such_dir" / "i.png").string(), "--steps", "3", "--width-px", "96"});
    EXPECT_NE(bad.exit_code, 0);
    EXPECT_NE(bad.err.find("no_such_dir"), std::string::npos) << bad.err;
    EXPECT_EQ(std::count(bad.err.begin(), bad.err.end(), '\n'), 1) << bad.err;
    EXPECT_FALSE(fs::exists(work / "m.png"));
    fs::remove_all(work);
}
