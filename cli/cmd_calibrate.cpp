// cortexfuse calibrate: camera intrinsics from chessboard photos (OpenCV), as case-format JSON.
#include <unistd.h>

#include <cstdio>
#include <iostream>
#include <memory>

#include "commands.hpp"
#include "cortexfuse/core/calibration.hpp"
#include "cortexfuse/core/error.hpp"

namespace cf::cli {

void add_calibrate(CLI::App& app) {
    struct Opts {
        std::vector<std::string> photos;
        std::string board = "9x6", out;
        ChessboardOptions opt;
        bool quiet = false;
    };
    auto o = std::make_shared<Opts>();
    auto* cmd = app.add_subcommand("calibrate", "Camera intrinsics from chessboard photos, written as case-format camera JSON");
    cmd->add_option("PHOTOS", o->photos, "photos of a flat chessboard from varied angles (same camera, same size)")->required();
    cmd->add_option("--board", o->board, "inner corners COLSxROWS (a 10x7-square board is 9x6)")->capture_default_str();
    cmd->add_option("--square-mm", o->opt.square_mm, "side of one square in mm")->capture_default_str();
    cmd->add_option("--out", o->out, "camera JSON to write (width, height, fx, fy, cx, cy, distortion, rms_px)")->required();
    cmd->add_option("--subpix-window", o->opt.subpix_half_window, "cornerSubPix half window, px")->capture_default_str();
    cmd->add_option("--min-views", o->opt.min_views, "fewest photos with the board found")->capture_default_str();
    cmd->add_flag("--skip-bad", o->opt.skip_failed, "skip photos where the board is not found instead of failing");
    cmd->add_flag("--quiet", o->quiet, "only errors on stderr");
    cmd->callback([o] {
        run_guarded("calibrate", [o]() -> int {
            const auto x = o->board.find_first_of("xX");
            try {
                size_t a = 0, b = 0;
                if (x == std::string::npos) throw std::invalid_argument("no x");
                o->opt.inner_cols = std::stoi(o->board.substr(0, x), &a);
                o->opt.inner_rows = std::stoi(o->board.substr(x + 1), &b);
                if (a != x || b != o->board.size() - x - 1) throw std::invalid_argument("trailing");
            } catch (const std::exception&) {
                throw InputError("calibrate --board", "expected COLSxROWS of inner corners (e.g. 9x6), got \"" + o->board + "\"");
            }
            std::vector<std::filesystem::path> photos(o->photos.begin(), o->photos.end());
            Progress progress;
            const bool tty = !o->quiet && ::isatty(STDERR_FILENO);
            if (tty)
                progress.report = [](const std::string& stage, double f) {
                    std::fprintf(stderr, "\r%-20s %3d%%", stage.c_str(), int(f * 100 + 0.5));
                    std::fflush(stderr);
                };
            const CalibrationResult r = calibrate_chessboard(photos, o->opt, progress);
            if (tty) std::fprintf(stderr, "\n");
            write_calibration_json(r, o->out);
            if (!o->quiet) {
                int used = 0;
                for (const auto& v : r.views) {
                    used += v.used;
                    if (!v.used) std::cerr << "cortexfuse calibrate: skipped " << v.file.string() << ": " << v.reason << "\n";
                }
                std::fprintf(stderr,
                             "cortexfuse calibrate: %d of %zu photos, RMS %.3f px, fx %.2f fy %.2f cx %.2f cy %.2f, "
                             "k1 %.4f k2 %.4f p1 %.4f p2 %.4f k3 %.4f -> %s\n",
                             used, r.views.size(), r.rms_px, r.camera.fx, r.camera.fy, r.camera.cx, r.camera.cy,
                             r.camera.distortion[0], r.camera.distortion[1], r.camera.distortion[2], r.camera.distortion[3],
                             r.camera.distortion[4], o->out.c_str());
            }
            return 0;
        });
    });
}

}  // namespace cf::cli
