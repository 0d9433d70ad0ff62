// Chessboard calibration through OpenCV's calib3d (see calibration.hpp).
#include "cortexfuse/core/calibration.hpp"

#include <cmath>
#include <nlohmann/json.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"

namespace cf {

namespace fs = std::filesystem;

void ChessboardOptions::validate() const {
    auto bad = [](const std::string& opt, const std::string& why) { throw InputError("calibration " + opt, why); };
    if (inner_cols < 2 || inner_rows < 2 || inner_cols > 100 || inner_rows > 100)
        bad("--board", "inner corners must be 2..100 each, got " + std::to_string(inner_cols) + "x" + std::to_string(inner_rows));
    if (inner_cols == inner_rows)
        bad("--board", "a square board (" + std::to_string(inner_cols) + "x" + std::to_string(inner_rows) +
                           ") is ambiguous under rotation; use one with different counts");
    if (!(square_mm > 0 && std::isfinite(square_mm))) bad("--square-mm", "must be a positive number");
    if (subpix_half_window < 1 || subpix_half_window > 50) bad("--subpix-window", "must be 1..50");
    if (min_views < 3 || min_views > 1000) bad("--min-views", "must be 3..1000");
}

CalibrationResult calibrate_chessboard(const std::vector<fs::path>& photos, const ChessboardOptions& o, const Progress& progress) {
    o.validate();
    if (photos.size() < size_t(o.min_views))
        throw InputError("calibration photos", "need at least " + std::to_string(o.min_views) + " photos of the board, got " +
                                                   std::to_string(photos.size()));
    const cv::Size board(o.inner_cols, o.inner_rows);
    std::vector<cv::Point3f> object;
    for (int r = 0; r < o.inner_rows; ++r)
        for (int c = 0; c < o.inner_cols; ++c) object.emplace_back(float(c * o.square_mm), float(r * o.square_mm), 0.f);

    CalibrationResult res;
    res.board = o;
    std::vector<std::vector<cv::Point2f>> image_points;
    std::vector<std::vector<cv::Point3f>> object_points;
    std::vector<size_t> used_index;
    cv::Size size;
    for (size_t i = 0; i < photos.size(); ++i) {
        progress.check();
        progress("finding corners", double(i) / double(photos.size() + 1));
        CalibrationView v;
        v.file = photos[i];
        const cv::Mat bgr = load_photo(photos[i]);  // InputError naming the file if unreadable
        if (size.empty())
            size = bgr.size();
        else if (bgr.size() != size)
            throw InputError(photos[i].string(), "is " + std::to_string(bgr.cols) + "x" + std::to_string(bgr.rows) +
                                                     " but the first photo is " + std::to_string(size.width) + "x" +
                                                     std::to_string(size.height) + "; one calibration is for one camera mode");
        cv::Mat grey;
        cv::cvtColor(bgr, grey, cv::COLOR_BGR2GRAY);
        std::vector<cv::Point2f> corners;
        const bool found = cv::findChessboardCorners(grey, board, corners,
                                                     cv::CALIB_CB_ADAPTIVE_THRESH | cv::CALIB_CB_NORMALIZE_IMAGE);
        if (!found) {
            const std::string why = "no " + std::to_string(o.inner_cols) + "x" + std::to_string(o.inner_rows) +
                                    " chessboard (inner corners) found";
            if (!o.skip_failed) throw InputError(photos[i].string(), why);
            v.reason = why;
            res.views.push_back(v);
            continue;
        }
        cv::cornerSubPix(grey, corners, cv::Size(o.subpix_half_window, o.subpix_half_window), cv::Size(-1, -1),
                         cv::TermCriteria(cv::TermCriteria::EPS + cv::TermCriteria::COUNT, 30, 0.001));
        image_points.push_back(corners);
        object_points.push_back(object);
        v.used = true;
        used_index.push_back(res.views.size());
        res.views.push_back(v);
    }
    if (image_points.size() < size_t(o.min_views))
        throw InputError("calibration photos", "the board was found in " + std::to_string(image_points.size()) + " of " +
                                                   std::to_string(photos.size()) + " photos; need at least " +
                                                   std::to_string(o.min_views));
    progress.check();
    progress("calibrating", double(photos.size()) / double(photos.size() + 1));

    cv::Mat K, dist;
    std::vector<cv::Mat> rvecs, tvecs;
    res.rms_px = cv::calibrateCamera(object_points, image_points, size, K, dist, rvecs, tvecs);
    if (!std::isfinite(res.rms_px) || K.at<double>(0, 0) <= 0)
        throw InputError("calibration photos", "calibration did not converge; take photos of the board from more varied angles");

    Intrinsics& cam = res.camera;
    cam.width = size.width;
    cam.height = size.height;
    cam.fx = K.at<double>(0, 0);
    cam.fy = K.at<double>(1, 1);
    cam.cx = K.at<double>(0, 2);
    cam.cy = K.at<double>(1, 2);
    for (int k = 0; k < 5; ++k) cam.distortion[size_t(k)] = dist.at<double>(k);

    for (size_t u = 0; u < image_points.size(); ++u) {
        std::vector<cv::Point2f> proj;
        cv::projectPoints(object_points[u], rvecs[u], tvecs[u], K, dist, proj);
        const double e = cv::norm(image_points[u], proj, cv::NORM_L2);
        res.views[used_index[u]].rms_px = e / std::sqrt(double(proj.size()));
    }
    progress("done", 1.0);
    return res;
}

nlohmann::json calibration_to_json(const CalibrationResult& r) {
    nlohmann::json j = camera_to_json(r.camera);
    j["rms_px"] = r.rms_px;
    j["board"] = {{"inner_cols", r.board.inner_cols}, {"inner_rows", r.board.inner_rows}, {"square_mm", r.board.square_mm}};
    nlohmann::json views = nlohmann::json::array();
    for (const auto& v : r.views) {
        nlohmann::json jv = {{"file", v.file.filename().string()}, {"used", v.used}};
        if (v.used)
            jv["rms_px"] = v.rms_px;
        else
            jv["reason"] = v.reason;
        views.push_back(jv);
    }
    j["views"] = views;
    return j;
}

void write_calibration_json(const CalibrationResult& r, const fs::path& out) {
    write_file_atomic(out, calibration_to_json(r).dump(2) + "\n");
}

}  // namespace cf
