#include "cortexfuse/core/case.hpp"

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <Eigen/SVD>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <nlohmann/json.hpp>
#include <sstream>
#include <unistd.h>

#include "cortexfuse/core/error.hpp"

namespace fs = std::filesystem;
using nlohmann::json;

namespace cf {

json read_json_file(const fs::path& path) {
    std::error_code ec;
    if (!fs::exists(path, ec)) throw InputError(path.string(), "no such file");
    if (fs::is_directory(path, ec)) throw InputError(path.string(), "is a folder, not a JSON file");
    std::ifstream in(path);
    if (!in) throw InputError(path.string(), "cannot open file");
    try {
        return json::parse(in);
    } catch (const json::exception& e) {
        std::string m = e.what();
        throw InputError(path.string(), "not valid JSON (" + m.substr(m.find(']') == std::string::npos ? 0 : m.find(']') + 2) + ")");
    }
}

void write_file_atomic(const fs::path& path, const std::string& text) {
    const fs::path tmp = path.string() + ".tmp" + std::to_string(::getpid());
    {
        std::ofstream out(tmp, std::ios::binary);
        if (!out) throw InputError(path.string(), "cannot write file");
        out << text;
        out.flush();
        if (!out) {
            std::error_code ec;
            fs::remove(tmp, ec);
            throw InputError(path.string(), "cannot write file (disk full?)");
        }
    }
    std::error_code ec;
    fs::rename(tmp, path, ec);
    if (ec) {
        fs::remove(tmp, ec);
        throw InputError(path.string(), "cannot write file: " + ec.message());
    }
}

namespace {

double num(const json& j, const std::string& file, const std::string& field) {
    if (!j.is_number()) throw InputError(file, "\"" + field + "\" must be a number");
    const double v = j.get<double>();
    if (!std::isfinite(v)) throw InputError(file, "\"" + field + "\" is not finite");
    return v;
}

const json& field(const json& j, const char* key, const std::string& file) {
    if (!j.is_object()) throw InputError(file, "expected a JSON object");
    if (!j.contains(key)) throw InputError(file, std::string("missing \"") + key + "\"");
    return j.at(key);
}

std::string str(const json& j, const char* key, const std::string& file) {
    const json& v = field(j, key, file);
    if (!v.is_string() || v.get<std::string>().empty()) throw InputError(file, std::string("\"") + key + "\" must be a non-empty string");
    return v.get<std::string>();
}

}  // namespace

Intrinsics parse_camera(const json& j, const std::string& file) {
    const json& c = field(j, "camera", file);
    if (!c.is_object()) throw InputError(file, "\"camera\" must be an object");
    Intrinsics K;
    const double w = num(field(c, "width", file), file, "camera.width"), h = num(field(c, "height", file), file, "camera.height");
    if (w != std::floor(w) || h != std::floor(h) || w < 1 || h < 1 || w > 20000 || h > 20000)
        throw InputError(file, "camera width/height must be whole numbers in 1..20000");
    K.width = int(w);
    K.height = int(h);
    K.fx = num(field(c, "fx", file), file, "camera.fx");
    K.fy = num(field(c, "fy", file), file, "camera.fy");
    K.cx = num(field(c, "cx", file), file, "camera.cx");
    K.cy = num(field(c, "cy", file), file, "camera.cy");
    if (c.contains("distortion")) {
        const json& d = c.at("distortion");
        if (!d.is_array() || (d.size() != 4 && d.size() != 5))
            throw InputError(file, "camera.distortion must be [k1, k2, p1, p2] or [k1, k2, p1, p2, k3]");
        for (size_t i = 0; i < d.size(); ++i) K.distortion[i] = num(d[i], file, "camera.distortion");
    }
    K.validate(file);
    return K;
}

json camera_to_json(const Intrinsics& K) {
    return {{"width", K.width}, {"height", K.height}, {"fx", K.fx}, {"fy", K.fy}, {"cx", K.cx}, {"cy", K.cy},
            {"distortion", std::vector<double>(K.distortion.begin(), K.distortion.end())}};
}

Pose parse_pose(const json& j, const std::string& file, const char* key) {
    const json& m = field(j, key, file);
    if (!m.is_array() || m.size() != 4) throw InputError(file, std::string("\"") + key + "\" must be a 4x4 array");
    Pose T;
    for (int r = 0; r < 4; ++r) {
        if (!m[size_t(r)].is_array() || m[size_t(r)].size() != 4) throw InputError(file, std::string("\"") + key + "\" must be a 4x4 array");
        for (int c = 0; c < 4; ++c) T(r, c) = num(m[size_t(r)][size_t(c)], file, key);
    }
    if (!is_rigid(T, 1e-3)) throw InputError(file, std::string("\"") + key + "\" is not a rigid transform (rotation + translation, last row 0 0 0 1)");
    return orthonormalize(T);
}

json pose_to_json(const Pose& T) {
    json m = json::array();
    for (int r = 0; r < 4; ++r) m.push_back({T(r, 0), T(r, 1), T(r, 2), T(r, 3)});
    return m;
}

std::vector<Landmark> parse_landmarks(const json& j, const std::string& file) {
    const json& arr = field(j, "landmarks", file);
    if (!arr.is_array()) throw InputError(file, "\"landmarks\" must be an array");
    std::vector<Landmark> out;
    for (size_t i = 0; i < arr.size(); ++i) {
        const json& l = arr[i];
        const std::string where = "landmark " + std::to_string(i + 1);
        if (!l.is_object()) throw InputError(file, where + " must be an object");
        Landmark lm;
        lm.label = l.contains("label") && l["label"].is_string() ? l["label"].get<std::string>() : "L" + std::to_string(i + 1);
        const json& w = field(l, "world_mm", file);
        const json& p = field(l, "pixel", file);
        if (!w.is_array() || w.size() != 3) throw InputError(file, where + ": \"world_mm\" must be [x, y, z]");
        if (!p.is_array() || p.size() != 2) throw InputError(file, where + ": \"pixel\" must be [u, v]");
        for (int k = 0; k < 3; ++k) lm.world_mm[k] = num(w[size_t(k)], file, where + " world_mm");
        for (int k = 0; k < 2; ++k) lm.pixel[k] = num(p[size_t(k)], file, where + " pixel");
        out.push_back(lm);
    }
    return out;
}

LandmarkSpread landmark_spread(const std::vector<Landmark>& lms) {
    auto ratio = [&](auto point_of) {
        using V = std::decay_t<decltype(point_of(lms.front()))>;
        if (lms.size() < 2) return 0.0;
        V mean = V::Zero();
        for (const auto& l : lms) mean += point_of(l);
        mean /= double(lms.size());
        Eigen::MatrixXd M(long(lms.size()), mean.size());
        for (size_t i = 0; i < lms.size(); ++i) M.row(long(i)) = (point_of(lms[i]) - mean).transpose();
        const Eigen::JacobiSVD<Eigen::MatrixXd> svd(M);
        const auto s = svd.singularValues();
        return s.size() >= 2 ? s(1) / std::max(s(0), 1e-12) : 0.0;
    };
    return {ratio([](const Landmark& l) { return l.world_mm; }), ratio([](const Landmark& l) { return l.pixel; })};
}

std::string landmark_spread_warning(const LandmarkSpread& s) {
    const double worst = std::min(s.world, s.pixel);
    if (!(worst < kLandmarkSpreadWarn)) return "";
    char buf[160];
    std::snprintf(buf, sizeof buf, "the landmarks lie nearly on a line (spread %.2f, under %.2f): ", worst, kLandmarkSpreadWarn);
    return std::string(buf) + "the turn about that line rests on the image alone; add a pair away from the line";
}

void validate_landmarks(const std::vector<Landmark>& lms, const Intrinsics& K, const std::string& file) {
    if (lms.size() < 4) throw InputError(file, "needs at least 4 landmark pairs, found " + std::to_string(lms.size()));
    for (const auto& l : lms)
        if (l.pixel.x() < -0.5 || l.pixel.y() < -0.5 || l.pixel.x() > K.width - 0.5 || l.pixel.y() > K.height - 0.5)
            throw InputError(file, "landmark " + l.label + " pixel (" + std::to_string(l.pixel.x()) + ", " +
                                       std::to_string(l.pixel.y()) + ") is outside the " + std::to_string(K.width) + "x" +
                                       std::to_string(K.height) + " photo");
    // Collinear (or coincident) points leave the pose undetermined: check the spread of both sets.
    const LandmarkSpread sp = landmark_spread(lms);
    if (sp.pixel < kLandmarkSpreadMin) throw InputError(file, "landmark pixels are collinear; pick points that span an area");
    if (sp.world < kLandmarkSpreadMin) throw InputError(file, "landmark world points are collinear; pick points that span an area");
}

Roi parse_roi(const json& j, const std::string& file) {
    Roi roi;
    if (j.contains("type") && (!j["type"].is_string() || j["type"].get<std::string>() != "closed-cardinal-spline"))
        throw InputError(file, "ROI \"type\" must be \"closed-cardinal-spline\"");
    if (j.contains("tension")) roi.tension = num(j["tension"], file, "tension");
    if (roi.tension < -1 || roi.tension > 1) throw InputError(file, "ROI tension must lie in [-1, 1]");
    const json& pts = field(j, "points", file);
    if (!pts.is_array()) throw InputError(file, "\"points\" must be an array of [u, v]");
    for (const auto& p : pts) {
        if (!p.is_array() || p.size() != 2) throw InputError(file, "each ROI point must be [u, v]");
        roi.points.emplace_back(num(p[0], file, "points"), num(p[1], file, "points"));
    }
    return roi;
}

void validate_roi(const Roi& roi, const Intrinsics& K, const std::string& file) {
    if (roi.points.size() < 3) throw InputError(file, "ROI needs at least 3 points, found " + std::to_string(roi.points.size()));
    for (const auto& p : roi.points)
        if (p.x() < -0.5 || p.y() < -0.5 || p.x() > K.width - 0.5 || p.y() > K.height - 0.5)
            throw InputError(file, "ROI point (" + std::to_string(p.x()) + ", " + std::to_string(p.y()) + ") is outside the " +
                                       std::to_string(K.width) + "x" + std::to_string(K.height) + " photo");
    const cv::Mat m = roi_mask(roi, K.width, K.height);
    if (cv::countNonZero(m) < 100) throw InputError(file, "ROI encloses fewer than 100 pixels");
}

cv::Mat load_photo(const fs::path& path) {
    std::error_code ec;
    if (!fs::exists(path, ec)) throw InputError(path.string(), "no such file");
    if (fs::is_directory(path, ec)) throw InputError(path.string(), "is a folder, not an image file");
    if (fs::file_size(path, ec) == 0) throw InputError(path.string(), "empty file, not an image");
    {
        std::ifstream in(path, std::ios::binary);
        if (!in) throw InputError(path.string(), "cannot open file (permissions?)");
        // libjpeg decodes a truncated JPEG with a grey lower part and only a warning: a JPEG
        // must end with its EOI marker (FF D9), possibly followed by padding.
        unsigned char soi[2] = {0, 0};
        in.read(reinterpret_cast<char*>(soi), 2);
        if (soi[0] == 0xFF && soi[1] == 0xD8) {
            const auto size = fs::file_size(path, ec);
            const std::streamoff tail = std::streamoff(std::min<uintmax_t>(size, 4096));
            std::string end(size_t(tail), '\0');
            in.seekg(-tail, std::ios::end);
            in.read(end.data(), tail);
            if (end.rfind("\xFF\xD9") == std::string::npos)
                throw InputError(path.string(), "truncated JPEG (no end-of-image marker)");
        }
        // libpng prints its own error lines for a truncated PNG: its IEND chunk must be there.
        if (soi[0] == 0x89 && soi[1] == 'P') {
            const auto size = fs::file_size(path, ec);
            const std::streamoff tail = std::streamoff(std::min<uintmax_t>(size, 64));
            std::string end(size_t(tail), '\0');
            in.clear();
            in.seekg(-tail, std::ios::end);
            in.read(end.data(), tail);
            if (end.find("IEND") == std::string::npos) throw InputError(path.string(), "truncated PNG (no IEND chunk)");
        }
    }
    cv::Mat img;
    try {
        img = cv::imread(path.string(), cv::IMREAD_COLOR);
    } catch (const cv::Exception&) {
        img.release();
    }
    if (img.empty()) throw InputError(path.string(), "not a readable image (expected an 8-bit RGB PNG or JPEG)");
    if (img.cols < 8 || img.rows < 8) throw InputError(path.string(), "image too small");
    return img;
}

CaseSpec read_case(const fs::path& dir) {
    CaseSpec c;
    c.dir = dir;
    std::error_code ec;
    if (!fs::is_directory(dir, ec)) throw InputError(dir.string(), "not a case folder");
    const fs::path case_json = dir / "case.json";
    const std::string cf_name = case_json.string();
    const json j = read_json_file(case_json);
    if (!j.is_object()) throw InputError(cf_name, "expected a JSON object");
    if (j.contains("format") && (!j["format"].is_string() || j["format"].get<std::string>().rfind("cortexfuse-case/", 0) != 0))
        throw InputError(cf_name, "\"format\" must be \"cortexfuse-case/1\"");
    auto resolve = [&](const std::string& rel) { return fs::path(rel).is_absolute() ? fs::path(rel) : dir / rel; };
    c.volume_path = resolve(str(j, "volume", cf_name));
    c.photo_path = resolve(str(j, "photo", cf_name));
    c.camera = parse_camera(j, cf_name);
    if (!fs::exists(c.volume_path, ec)) throw InputError(c.volume_path.string(), "no such file (named by case.json \"volume\")");
    if (!fs::exists(c.photo_path, ec)) throw InputError(c.photo_path.string(), "no such file (named by case.json \"photo\")");
    if (j.contains("brain_mask") && !j["brain_mask"].is_null()) {
        c.brain_mask_path = resolve(str(j, "brain_mask", cf_name));
        if (!fs::exists(*c.brain_mask_path, ec)) throw InputError(c.brain_mask_path->string(), "no such file (named by case.json \"brain_mask\")");
    }
    if (j.contains("landmarks") && !j["landmarks"].is_null()) {
        const fs::path p = resolve(str(j, "landmarks", cf_name));
        c.landmarks_path = p;
        c.landmarks = parse_landmarks(read_json_file(p), p.string());
        validate_landmarks(c.landmarks, c.camera, p.string());
    }
    if (j.contains("initial_pose") && !j["initial_pose"].is_null()) {
        const fs::path p = resolve(str(j, "initial_pose", cf_name));
        c.initial_pose_path = p;
        c.initial_pose = parse_pose(read_json_file(p), p.string());
    }
    if (c.landmarks.empty() && !c.initial_pose)
        throw InputError(cf_name, "names neither \"landmarks\" nor \"initial_pose\": nothing to start the registration from");
    if (j.contains("roi") && !j["roi"].is_null()) {
        const fs::path p = resolve(str(j, "roi", cf_name));
        c.roi_path = p;
        c.roi = parse_roi(read_json_file(p), p.string());
        validate_roi(*c.roi, c.camera, p.string());
    }
    const fs::path tp = dir / "truth.json";
    if (fs::exists(tp, ec)) {
        const json t = read_json_file(tp);
        Truth tr;
        tr.T_camera_from_world = parse_pose(t, tp.string());
        const json& tg = field(t, "targets_world_mm", tp.string());
        if (!tg.is_array()) throw InputError(tp.string(), "\"targets_world_mm\" must be an array");
        for (const auto& p : tg) {
            if (!p.is_array() || p.size() != 3) throw InputError(tp.string(), "each target must be [x, y, z]");
            tr.targets_world_mm.emplace_back(num(p[0], tp.string(), "targets"), num(p[1], tp.string(), "targets"), num(p[2], tp.string(), "targets"));
        }
        c.truth = tr;
    }
    return c;
}

}  // namespace cf
