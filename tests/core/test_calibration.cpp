// Intrinsic calibration on OpenCV's real chessboard photos (tests/data/calibration), against
// the reference result computed independently with OpenCV's Python bindings (same photos,
// square = 1 unit, cornerSubPix 11x11): RMS 0.520 px, fx 538.98, fy 539.20, cx 339.38, cy 237.31.
#include <gtest/gtest.h>
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "cortexfuse/core/calibration.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"

namespace fs = std::filesystem;
using namespace cf;

namespace {

const fs::path kDir = fs::path(CF_TEST_DATA_DIR) / "calibration";

std::vector<fs::path> photos() {
    std::vector<fs::path> v;
    for (const char* n : {"opencv_left01.jpg", "opencv_left02.jpg", "opencv_left03.jpg", "opencv_left04.jpg",
                          "opencv_left05.jpg", "opencv_left12.jpg"})
        v.push_back(kDir / n);
    return v;
}

fs::path tmp(const std::string& name) {
    auto p = fs::temp_directory_path() / ("cf_test_calib_" + std::to_string(::getpid()));
    fs::create_directories(p);
    return p / name;
}

}  // namespace

TEST(Calibration, ReproducesTheReferenceOnOpenCvPhotos) {
    ChessboardOptions o;  // 9x6, square 1, window 11
    int reports = 0;
    Progress progress;
    progress.report = [&](const std::string&, double f) {
        EXPECT_GE(f, 0.0);
        EXPECT_LE(f, 1.0);
        ++reports;
    };
    const CalibrationResult r = calibrate_chessboard(photos(), o, progress);
    EXPECT_EQ(r.camera.width, 640);
    EXPECT_EQ(r.camera.height, 480);
    EXPECT_NEAR(r.rms_px, 0.520, 0.005);
    EXPECT_NEAR(r.camera.fx, 538.98, 0.3);
    EXPECT_NEAR(r.camera.fy, 539.20, 0.3);
    EXPECT_NEAR(r.camera.cx, 339.38, 0.3);
    EXPECT_NEAR(r.camera.cy, 237.31, 0.3);
    EXPECT_NEAR(r.camera.distortion[0], -0.2605, 0.005);
    EXPECT_NEAR(r.camera.distortion[4], 0.2762, 0.03);
    ASSERT_EQ(r.views.size(), 6u);
    for (const auto& v : r.views) {
        EXPECT_TRUE(v.used);
        EXPECT_GT(v.rms_px, 0.1);
        EXPECT_LT(v.rms_px, 1.5);
    }
    EXPECT_GE(reports, 7);

    // The JSON is a case-format camera (parse_camera reads it back) plus the RMS.
    const fs::path out = tmp("camera.json");
    write_calibration_json(r, out);
    const nlohmann::json j = read_json_file(out);
    const Intrinsics back = parse_camera(nlohmann::json{{"camera", j}}, out.string());
    EXPECT_EQ(back.width, 640);
    EXPECT_DOUBLE_EQ(back.fx, r.camera.fx);
    EXPECT_DOUBLE_EQ(back.distortion[1], r.camera.distortion[1]);
    EXPECT_DOUBLE_EQ(j.at("rms_px").get<double>(), r.rms_px);
    fs::remove_all(out.parent_path());
}

TEST(Calibration, SquareSizeScalesPosesNotIntrinsics) {
    ChessboardOptions o;
    o.square_mm = 25.0;
    auto p = photos();
    p.resize(4);
    const CalibrationResult a = calibrate_chessboard(p, o);
    o.square_mm = 1.0;
    const CalibrationResult b = calibrate_chessboard(p, o);
    EXPECT_NEAR(a.camera.fx, b.camera.fx, 1e-3 * b.camera.fx);
    EXPECT_NEAR(a.rms_px, b.rms_px, 1e-3);
}

TEST(Calibration, BadInput) {
    const fs::path dir = tmp("");
    // A photo with no chessboard: a flat grey image.
    const fs::path blank = dir / "blank.png";
    {
        std::vector<uint8_t> png;
        cv::Mat grey(480, 640, CV_8UC3, cv::Scalar(128, 128, 128));
        cv::imencode(".png", grey, png);
        std::ofstream(blank, std::ios::binary).write(reinterpret_cast<const char*>(png.data()), std::streamsize(png.size()));
    }
    const fs::path junk = dir / "junk.jpg";
    std::ofstream(junk) << "not a jpeg";

    auto with = [&](const fs::path& extra) {
        auto v = photos();
        v.resize(3);
        v.push_back(extra);
        return v;
    };
    ChessboardOptions o;
    try {
        calibrate_chessboard(with(blank), o);
        FAIL() << "a photo without the board was accepted";
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("blank.png"), std::string::npos) << e.what();
        EXPECT_NE(std::string(e.what()).find("no 9x6 chessboard"), std::string::npos) << e.what();
    }
    // --skip-bad: the photo is skipped and reported.
    o.skip_failed = true;
    const CalibrationResult r = calibrate_chessboard(with(blank), o);
    EXPECT_FALSE(r.views.back().used);
    EXPECT_FALSE(r.views.back().reason.empty());
    o.skip_failed = false;

    try {
        calibrate_chessboard(with(junk), o);
        FAIL() << "an unreadable file was accepted";
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("junk.jpg"), std::string::npos) << e.what();
    }
    EXPECT_THROW(calibrate_chessboard(with(dir / "missing.jpg"), o), InputError);

    // Too few views: two photos, or three of which one has no board.
    auto two = photos();
    two.resize(2);
    EXPECT_THROW(calibrate_chessboard(two, o), InputError);
    o.skip_failed = true;
    auto three = photos();
    three.resize(2);
    three.push_back(blank);
    try {
        calibrate_chessboard(three, o);
        FAIL() << "two usable views were accepted";
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("found in 2 of 3"), std::string::npos) << e.what();
    }
    o.skip_failed = false;

    // Photos of different sizes: two camera modes mixed.
    const fs::path small = dir / "small.png";
    {
        cv::Mat img = cv::imread((kDir / "opencv_left01.jpg").string());
        cv::resize(img, img, cv::Size(320, 240));
        cv::imwrite(small.string(), img);
    }
    EXPECT_THROW(calibrate_chessboard(with(small), o), InputError);

    // Options.
    ChessboardOptions bad;
    bad.inner_cols = 1;
    EXPECT_THROW(calibrate_chessboard(photos(), bad), InputError);
    bad = {};
    bad.square_mm = 0;
    EXPECT_THROW(calibrate_chessboard(photos(), bad), InputError);
    bad = {};
    bad.inner_cols = bad.inner_rows = 6;
    EXPECT_THROW(calibrate_chessboard(photos(), bad), InputError);

    // Cancel.
    CancelToken cancel;
    cancel.cancel();
    Progress p;
    p.cancel = &cancel;
    EXPECT_THROW(calibrate_chessboard(photos(), ChessboardOptions{}, p), Cancelled);
    fs::remove_all(dir);
}
