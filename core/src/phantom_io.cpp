// Phantom generator: writing case folders (docs/case-format.md) and the batch driver.
#include <opencv2/imgcodecs.hpp>

#include <fstream>
#include <nlohmann/json.hpp>
#include <system_error>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/phantom.hpp"

namespace cf {
namespace fs = std::filesystem;
using nlohmann::json;

namespace {

json matrix_json(const Pose& T) {
    json m = json::array();
    for (int r = 0; r < 4; ++r) m.push_back({T(r, 0), T(r, 1), T(r, 2), T(r, 3)});
    return m;
}
json vec_json(const Eigen::Vector3d& p) { return json::array({p.x(), p.y(), p.z()}); }

void write_text(const fs::path& p, const std::string& text) {
    std::ofstream f(p, std::ios::binary);
    f << text;
    f.close();
    if (!f) throw InputError(p.string(), "cannot write");
}

bool ends_with(const std::string& s, const std::string& suffix) {
    return s.size() >= suffix.size() && s.compare(s.size() - suffix.size(), suffix.size(), suffix) == 0;
}

}  // namespace

void write_phantom_case(const PhantomCase& c, const fs::path& case_dir, const std::string& volume_ref,
                        const std::string& mask_ref) {
    std::error_code ec;
    const fs::path tmp = case_dir.parent_path() / ("." + case_dir.filename().string() + ".tmp");
    fs::remove_all(tmp, ec);
    if (!fs::create_directories(tmp, ec) || ec) throw InputError(tmp.string(), "cannot create folder: " + ec.message());

    const std::string photo_name = c.jpeg ? "photo.jpg" : "photo.png";
    std::vector<int> opts;
    if (c.jpeg) opts = {cv::IMWRITE_JPEG_QUALITY, c.jpeg_quality};
    else opts = {cv::IMWRITE_PNG_COMPRESSION, 3};
    if (!cv::imwrite((tmp / photo_name).string(), c.photo_bgr, opts))
        throw InputError((tmp / photo_name).string(), "cannot write photo");

    const Intrinsics& K = c.camera;
    json cam = {{"width", K.width}, {"height", K.height}, {"fx", K.fx}, {"fy", K.fy}, {"cx", K.cx}, {"cy", K.cy},
                {"distortion", json::array({K.distortion[0], K.distortion[1], K.distortion[2], K.distortion[3], K.distortion[4]})}};
    json cj = {{"format", "cortexfuse-case/1"}, {"volume", volume_ref}, {"photo", photo_name}, {"camera", cam},
               {"landmarks", "landmarks.json"}, {"roi", "roi.json"}};
    if (!mask_ref.empty()) cj["brain_mask"] = mask_ref;
    write_text(tmp / "case.json", cj.dump(2) + "\n");

    json lms = json::array();
    for (const auto& l : c.landmarks)
        lms.push_back({{"label", l.label}, {"world_mm", vec_json(l.world_mm)}, {"pixel", {l.pixel.x(), l.pixel.y()}}});
    write_text(tmp / "landmarks.json", json{{"landmarks", lms}}.dump(2) + "\n");

    json pts = json::array();
    for (const auto& p : c.roi_points) pts.push_back({p.x(), p.y()});
    write_text(tmp / "roi.json", json{{"type", "closed-cardinal-spline"}, {"tension", 0.0}, {"points", pts}}.dump(2) + "\n");

    json targets = json::array();
    for (const auto& p : c.targets_world_mm) targets.push_back(vec_json(p));
    json lm_true = json::array();
    for (const auto& l : c.landmarks) lm_true.push_back({{"label", l.label}, {"world_mm", vec_json(l.true_world_mm)}});
    json tj = {{"T_camera_from_world", matrix_json(c.T_camera_from_world)},
               {"targets_world_mm", targets},
               {"landmarks_true", lm_true},
               {"generator", {{"name", "cortexfuse phantom"}, {"notes", c.notes}}}};
    write_text(tmp / "truth.json", tj.dump(2) + "\n");

    fs::remove_all(case_dir, ec);
    fs::rename(tmp, case_dir, ec);
    if (ec) throw InputError(case_dir.string(), "cannot create case folder: " + ec.message());
}

std::vector<fs::path> generate_phantoms(const fs::path& out_dir, int n, const fs::path& volume_path,
                                        const fs::path& mask_path, const PhantomParams& params, const Progress& progress) {
    if (n < 1 || n > 100000) throw InputError("phantom --n", "must be in 1..100000, got " + std::to_string(n));
    params.validate();
    progress("loading volume", 0.0);
    const Volume t1 = load_volume(volume_path);
    const LabelVolume mask = load_mask(mask_path);
    if (!mask.geom.same_grid(t1.geom))
        throw InputError(mask_path.string(), "brain mask is not on the volume's grid (" + volume_path.string() + ")");
    progress.check();
    Progress surface_progress;
    surface_progress.report = [&](const std::string& s, double f) { progress(s, 0.02 + 0.08 * f); };
    surface_progress.cancel = progress.cancel;
    const PhantomSurface surface = build_phantom_surface(t1, mask, surface_progress);
    std::error_code ec;
    fs::create_directories(out_dir, ec);
    if (ec || !fs::is_directory(out_dir)) throw InputError(out_dir.string(), "cannot create output folder");

    // One shared copy of the volume and mask; cases refer to them as ../t1.nii.gz.
    auto share = [&](const fs::path& src, const char* name, bool is_mask) {
        const fs::path dst = out_dir / name;
        const std::string s = src.string();
        if (!fs::is_directory(src) && (ends_with(s, ".nii.gz"))) {
            fs::remove(dst, ec);  // a previous copy may be read-only (the shipped data is)
            fs::copy_file(src, dst, fs::copy_options::overwrite_existing, ec);
            if (ec) throw InputError(dst.string(), "cannot copy " + s + ": " + ec.message());
            fs::permissions(dst, fs::perms::owner_read | fs::perms::owner_write, fs::perm_options::add, ec);
        } else if (is_mask) {
            save_mask(mask, dst);
        } else {
            save_volume(t1, dst);
        }
    };
    share(volume_path, "t1.nii.gz", false);
    share(mask_path, "brain_mask.nii.gz", true);

    std::vector<fs::path> dirs;
    for (int i = 0; i < n; ++i) {
        progress.check();
        progress("case " + std::to_string(i + 1) + "/" + std::to_string(n), 0.1 + 0.9 * double(i) / n);
        char name[32];
        std::snprintf(name, sizeof name, "case_%04d", i);
        const PhantomCase c = generate_phantom_case(surface, params, i);
        write_phantom_case(c, out_dir / name, "../t1.nii.gz", "../brain_mask.nii.gz");
        dirs.push_back(out_dir / name);
    }
    progress("done", 1.0);
    return dirs;
}

}  // namespace cf
