#pragma once
// Intrinsic camera calibration from chessboard photos, through OpenCV (findChessboardCorners,
// cornerSubPix, calibrateCamera with the 5-coefficient model k1 k2 p1 p2 k3), written as the
// case-format camera JSON (docs/case-format.md) plus the reprojection RMS.
//
// Errors: an unreadable photo, a photo without the board (unless skip_failed), photos of
// different sizes, too few usable views, or bad options throw cf::InputError naming the file
// or option. Re-entrant.
#include <filesystem>
#include <nlohmann/json_fwd.hpp>
#include <string>
#include <vector>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/progress.hpp"

namespace cf {

struct ChessboardOptions {
    int inner_cols = 9, inner_rows = 6;  // inner corners per row / column (a 10x7-square board is 9x6)
    double square_mm = 1.0;              // side of one square; scales only the board's poses
    int subpix_half_window = 11;         // cornerSubPix window = (2w+1)^2 px. 1..50
    int min_views = 3;                   // fewest photos with the board found. 3..1000
    bool skip_failed = false;            // skip photos without the board instead of failing
    void validate() const;               // throws InputError("calibration --option", ...)
};

struct CalibrationView {
    std::filesystem::path file;
    bool used = false;
    double rms_px = 0;   // this view's reprojection rms (used views)
    std::string reason;  // why it was skipped
};

struct CalibrationResult {
    Intrinsics camera;   // width, height, fx, fy, cx, cy, distortion[5]
    double rms_px = 0;   // overall reprojection rms, as cv::calibrateCamera returns it
    std::vector<CalibrationView> views;
    ChessboardOptions board;
};

/// Finds the board in each photo and calibrates. Reports progress per photo; cancellable.
CalibrationResult calibrate_chessboard(const std::vector<std::filesystem::path>& photos, const ChessboardOptions& options,
                                       const Progress& progress = {});

/// The camera JSON: {"width","height","fx","fy","cx","cy","distortion":[5]} (case format)
/// plus "rms_px", "board" and "views" (readers of the case format ignore extra keys).
nlohmann::json calibration_to_json(const CalibrationResult& r);
/// Writes calibration_to_json atomically (temporary file + rename). Throws InputError on I/O failure.
void write_calibration_json(const CalibrationResult& r, const std::filesystem::path& out);

}  // namespace cf
