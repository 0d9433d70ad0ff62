// Patient navigation over HTTP (docs/api/navigation.md); see navigation_api.hpp for what is
// stored where. The math is core's (cortexfuse/core/navigation.hpp): digitise_point averages
// the tip, register_fiducials fits, predicted_tre_mm predicts.
#include "navigation_api.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <unistd.h>
#include <map>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <set>
#include <thread>

#include "case_api.hpp"
#include "case_volumes.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/navigation.hpp"
#include "cortexfuse/core/volume.hpp"
#include "tracker_module.hpp"

namespace cf::daemon {

using nlohmann::json;
using namespace cf::db;
using cf::tracker::TrackerFrame;

namespace {

constexpr const char* kImageKind = "nav_image_fiducials";
constexpr const char* kPatientKind = "nav_patient_fiducials";
constexpr const char* kRegistrationKind = "patient_registration";
constexpr const char* kLandmarkKind = "nav_cortical_landmarks";
constexpr std::size_t kMaxLandmarks = 256;  // over every set of a case
constexpr std::size_t kMaxFiducials = 64;
constexpr int kMinFrames = 4;  // frames a recording averages at least (0.3 s at 20 Hz gives 6)

/// The simulator's patient: where its reference tool sits in the image (LPS mm), the truth a
/// touch given in image space is mapped through. A rotation of some 20 degrees and an offset,
/// so that a registration that returns the identity or only a translation fails the tests.
Eigen::Matrix4d sim_T_image_from_reference() {
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = (Eigen::AngleAxisd(0.35, Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(-0.25, Eigen::Vector3d::UnitX()) *
                  Eigen::AngleAxisd(0.1, Eigen::Vector3d::UnitY()))
                     .toRotationMatrix();
    T.translation() = Eigen::Vector3d(12, -140, 65);
    return T.matrix();
}

ApiError bad(const std::string& what, const std::string& problem) { return ApiError(400, "bad_request", what + ": " + problem); }
ApiError conflict(const std::string& what, const std::string& problem) { return ApiError(409, "conflict", what + ": " + problem); }

/// The body as an object (null: empty), refusing fields other than `allowed`.
json body_object(const Request& r, const std::string& ctx, std::initializer_list<const char*> allowed) {
    const json b = r.body.is_null() ? json::object() : r.body;
    if (!b.is_object()) throw bad(ctx, "the body must be a JSON object");
    for (auto it = b.begin(); it != b.end(); ++it) {
        bool ok = false;
        for (const char* a : allowed) ok = ok || it.key() == a;
        if (!ok) throw bad(ctx + " " + it.key(), "unknown field");
    }
    return b;
}

Eigen::Vector3d vec3(const json& v, const std::string& what) {
    if (!v.is_array() || v.size() != 3) throw bad(what, "must be [x, y, z] (mm)");
    Eigen::Vector3d p;
    for (int i = 0; i < 3; ++i) {
        if (!v[i].is_number()) throw bad(what, "must be [x, y, z] (mm), numbers");
        p[i] = v[i].get<double>();
        if (!std::isfinite(p[i])) throw bad(what, "must be finite");
    }
    return p;
}
json vec_json(const Eigen::Vector3d& p) { return json::array({p.x(), p.y(), p.z()}); }
json mat_json(const Eigen::Matrix4d& T) {
    json rows = json::array();
    for (int r = 0; r < 4; ++r) rows.push_back(json::array({T(r, 0), T(r, 1), T(r, 2), T(r, 3)}));
    return rows;
}
double number(const json& b, const char* key, double def, double lo, double hi, const std::string& ctx) {
    if (!b.contains(key) || b[key].is_null()) return def;
    if (!b[key].is_number()) throw bad(ctx + " " + key, "must be a number");
    const double v = b[key].get<double>();
    if (!(v >= lo && v <= hi)) throw bad(ctx + " " + key, std::to_string(v) + " is out of range " + std::to_string(lo) + ".." + std::to_string(hi));
    return v;
}
std::string text(const json& b, const char* key, const std::string& def, const std::string& ctx) {
    if (!b.contains(key) || b[key].is_null()) return def;
    if (!b[key].is_string()) throw bad(ctx + " " + key, "must be a string");
    return b[key].get<std::string>();
}
std::string label_of(const json& v, const std::string& what) {
    if (!v.is_string()) throw bad(what, "must be a string");
    const std::string s = v.get<std::string>();
    if (s.empty() || s.size() > 64) throw bad(what, "must be 1..64 characters");
    for (unsigned char c : s)
        if (c < 0x20 || c == '/') throw bad(what, "must not hold '/' or control characters");
    return s;
}

/// The newest stored list of `kind` for the case: its result row and its JSON content.
struct Stored {
    std::int64_t revision = 0;  // the result's id; 0: none stored yet
    json content;
    std::string created_utc;
};
Stored newest(CaseStore& store, const CaseRecord& rec, const char* kind) {
    Stored s;
    const ResultRecord* last = nullptr;
    for (const auto& x : rec.results)
        if (x.kind == kind && (!last || x.id > last->id)) last = &x;
    if (!last) return s;
    s.revision = last->id;
    s.created_utc = format_utc(last->created_utc);
    s.content = json::parse(store.read_blob(last->blob.sha256), nullptr, false);  // verified against its hash
    const char* list_key = std::string(kind) == kLandmarkKind ? "landmarks" : "fiducials";
    if (s.content.is_discarded() || !s.content.is_object() || (!s.content.contains(list_key) && std::string(kind) != kRegistrationKind))
        throw ApiError(500, "corrupt", std::string(kind) + " result " + std::to_string(last->id) + ": not the JSON this daemon wrote");
    return s;
}

ResultRecord store_json(CaseStore& store, std::int64_t case_id, const char* kind, const std::string& name, const json& content,
                        const json& params, const Actor& by) {
    ResultInput in;
    in.kind = kind;
    in.name = name;
    in.media_type = "application/json";
    in.bytes = content.dump(2);
    in.params = params;
    return store.add_result(case_id, std::nullopt, in, by);
}

struct ImageFiducial {
    std::string label;
    Eigen::Vector3d p_image_mm;
};
std::vector<ImageFiducial> image_fiducials(const Stored& s) {
    std::vector<ImageFiducial> out;
    if (s.revision == 0) return out;
    for (const auto& f : s.content.at("fiducials")) out.push_back({f.at("label").get<std::string>(), vec3(f.at("p_image_mm"), "stored image fiducial")});
    return out;
}
json patient_list(const Stored& s) { return s.revision ? s.content.at("fiducials") : json::array(); }

// ------------------------------------------------------------------------ tracker frames

const cf::tracker::TrackedTool* find_tool(const TrackerFrame& f, const std::string& name) {
    for (const auto& t : f.tools)
        if (t.name == name) return &t;
    return nullptr;
}
std::string why_absent(const cf::tracker::TrackedTool& t) {
    if (t.stale) return "stale (no valid reading for 0.5 s)";
    if (t.out_of_volume) return "out of the tracking volume";
    return "not seen (missing)";
}

/// The tip digitised over the frames of the last `window_s`: ApiError 409 naming the tool or
/// the motion when it cannot be.
cf::DigitisedPoint digitise(const TrackerModule& tracker, const std::string& label, const std::string& pointer,
                            const std::string& reference, double window_s, double max_spread_mm, const Eigen::Vector3d& tip) {
    if (!tracker.enabled()) throw conflict("tracker", "disabled (tracker.enabled is false): nothing to digitise with");
    const auto frames = tracker.recent_frames(std::int64_t(window_s * 1e9));
    const auto st = tracker.status();
    // Frames of the window from just before a drop are real, but the screen already says the
    // tracker stopped: a point recorded then would contradict what the surgeon is told.
    if (int(frames.size()) < kMinFrames || st.state != cf::tracker::TrackerStatus::State::streaming) {
        throw conflict("tracker", std::to_string(frames.size()) + " frame(s) in the last " + std::to_string(window_s).substr(0, 4) +
                                      " s (state " + cf::tracker::state_name(st.state) + ", " + std::to_string(int(st.frame_rate_hz + 0.5)) +
                                      " Hz): the tracker is not streaming; try again when it is");
    }
    std::vector<cf::PointerFrame> pf;
    for (const std::string* name : {&pointer, &reference}) {
        const auto* last = find_tool(frames.back(), *name);
        if (!last) {
            std::string names;
            for (const auto& t : frames.back().tools) names += (names.empty() ? "" : ", ") + t.name;
            throw conflict(*name, "no such tool is loaded (tools: " + names + ")");
        }
        int absent = 0;
        for (const auto& f : frames) {
            const auto* t = find_tool(f, *name);
            if (!t || !t->T_tracker_from_tool) ++absent;
        }
        if (absent)
            throw conflict(*name, "not tracked in " + std::to_string(absent) + " of the " + std::to_string(frames.size()) +
                                      " frames of the last " + std::to_string(window_s).substr(0, 4) + " s (now " +
                                      (last->T_tracker_from_tool ? std::string("seen") : why_absent(*last)) +
                                      "): keep both tools in view of the camera");
    }
    for (const auto& f : frames)
        pf.push_back({find_tool(f, pointer)->T_tracker_from_tool->matrix(), find_tool(f, reference)->T_tracker_from_tool->matrix()});
    cf::DigitisedPoint d;
    try {
        d = cf::digitise_point(label, pf, tip, Eigen::Matrix4d::Identity(), std::numeric_limits<double>::infinity());
    } catch (const cf::InputError& e) {
        throw conflict(pointer, e.what());
    }
    if (d.spread_mm > max_spread_mm) {
        char buf[200];
        std::snprintf(buf, sizeof buf, "the tip moved %.2f mm rms over the last %.2f s (limit %.2f mm): hold it still on '%s'", d.spread_mm,
                      window_s, max_spread_mm, label.c_str());
        throw conflict(pointer, buf);
    }
    return d;
}

// ------------------------------------------------------------------------ registration

struct Computed {
    json j;
    Eigen::Matrix4d T_image_from_reference = Eigen::Matrix4d::Identity();
};

Computed compute(const Stored& image, const Stored& patient, const json& b, const std::string& ctx) {
    const double outlier_mm = number(b, "outlier_mm", 5.0, 0.0, 1000.0, ctx);
    const double fle_mm = number(b, "fle_mm", 0.0, 0.0, 100.0, ctx);
    const auto img = image_fiducials(image);
    if (img.empty()) throw conflict(ctx, "the case has no image fiducials yet (POST .../navigation/image-fiducials)");
    const json recorded = patient_list(patient);
    std::vector<Eigen::Vector3d> p_patient, p_image;
    json rows = json::array(), missing = json::array();
    std::vector<std::size_t> row_of;  // index in `rows` of each pair
    for (const auto& f : img) {
        const json* hit = nullptr;
        for (const auto& r : recorded)
            if (r.at("label") == f.label) hit = &r;
        if (!hit) {
            missing.push_back(f.label);
            continue;
        }
        p_patient.push_back(vec3(hit->at("p_reference_mm"), "stored patient fiducial"));
        p_image.push_back(f.p_image_mm);
        row_of.push_back(rows.size());
        rows.push_back({{"label", f.label}, {"p_image_mm", vec_json(f.p_image_mm)}, {"p_reference_mm", hit->at("p_reference_mm")}});
    }
    if (p_patient.size() < 3)
        throw conflict(ctx, std::to_string(p_patient.size()) + " fiducial(s) recorded of " + std::to_string(img.size()) +
                                ": record at least 3 with the pointer");
    cf::FiducialOptions fo;
    fo.outlier_threshold_mm = outlier_mm > 0 ? outlier_mm : 0;
    fo.fle_mm = fle_mm;
    cf::FiducialRegistration reg;
    try {
        reg = cf::register_fiducials(p_patient, p_image, fo);
    } catch (const cf::InputError& e) {
        throw conflict(ctx, e.what());
    }
    json excluded = json::array();
    for (std::size_t i = 0; i < row_of.size(); ++i) {
        rows[row_of[i]]["residual_mm"] = reg.residuals_mm[i];
        rows[row_of[i]]["used"] = bool(reg.used[i]);
    }
    for (int k : reg.excluded) excluded.push_back(rows[row_of[std::size_t(k)]]["label"]);
    Eigen::Vector3d target = reg.centroid_image_mm;
    std::string target_name = "centroid of the fiducials";
    if (b.contains("target_image_mm") && !b["target_image_mm"].is_null()) {
        target = vec3(b["target_image_mm"], ctx + " target_image_mm");
        target_name = "given";
    }
    Computed c;
    c.T_image_from_reference = reg.T_image_from_patient;
    c.j = {{"T_image_from_reference", mat_json(reg.T_image_from_patient)},
           {"fre_mm", reg.fre_mm},
           {"fle_mm", reg.fle_mm},
           {"n_used", reg.n_used},
           {"fiducials", rows},
           {"excluded", excluded},
           {"missing", missing},
           {"target_image_mm", vec_json(target)},
           {"target", target_name},
           {"predicted_tre_mm", cf::predicted_tre_mm(reg, target)},
           {"params", {{"outlier_mm", outlier_mm}, {"fle_mm", fle_mm}, {"min_line_distance_mm", fo.min_line_distance_mm}}},
           {"image_fiducials_revision", image.revision},
           {"patient_fiducials_revision", patient.revision}};
    return c;
}

// ------------------------------------------------------------------------ slices

/// The MRI the slices are cut from: loaded on first use (a copy of data.t1 of its own, so the
/// render thread's is never touched), then read-only; intensities windowed at its 1st/99th
/// percentile.
class SliceVolume {
public:
    explicit SliceVolume(std::filesystem::path p) : path_(std::move(p)) {}
    std::shared_ptr<const cf::Volume> get(float& lo, float& hi) {
        std::lock_guard lk(mu_);
        if (!vol_ && error_.empty()) {
            try {
                auto v = std::make_shared<cf::Volume>(cf::load_volume(path_));
                std::vector<float> s;
                for (std::size_t i = 0; i < v->voxels.size(); i += 7) s.push_back(v->voxels[i]);
                if (s.empty()) throw std::runtime_error("empty volume");
                std::nth_element(s.begin(), s.begin() + long(s.size() / 100), s.end());
                lo_ = s[s.size() / 100];
                std::nth_element(s.begin(), s.begin() + long(s.size() * 99 / 100), s.end());
                hi_ = s[s.size() * 99 / 100];
                if (!(hi_ > lo_)) hi_ = lo_ + 1;
                vol_ = std::move(v);
            } catch (const std::exception& e) {
                error_ = e.what();
            }
        }
        if (!vol_) throw ApiError(503, "unavailable", "navigation slices: data.t1 could not be loaded: " + error_);
        lo = lo_;
        hi = hi_;
        return vol_;
    }

private:
    std::mutex mu_;
    std::filesystem::path path_;
    std::shared_ptr<const cf::Volume> vol_;
    std::string error_;
    float lo_ = 0, hi_ = 1;
};

/// The 1st/99th percentile window of a volume (every 7th voxel), as SliceVolume uses.
std::pair<float, float> slice_window(const cf::Volume& v) {
    std::vector<float> s;
    for (std::size_t i = 0; i < v.voxels.size(); i += 7) s.push_back(v.voxels[i]);
    if (s.empty()) return {0.f, 1.f};
    std::nth_element(s.begin(), s.begin() + long(s.size() / 100), s.end());
    const float lo = s[s.size() / 100];
    std::nth_element(s.begin(), s.begin() + long(s.size() * 99 / 100), s.end());
    float hi = s[s.size() * 99 / 100];
    if (!(hi > lo)) hi = lo + 1;
    return {lo, hi};
}

/// The volume slices are cut from: data.t1, or with ?case_id= (and ?volume_id=) the case's
/// own stored volume (its newest T1 by default), loaded through a small cache.
struct SliceSource {
    std::shared_ptr<SliceVolume> bundled;
    std::shared_ptr<CaseVolumeCache> cases;
    cf::db::CaseStore* store = nullptr;
    std::mutex mu;
    std::map<std::string, std::pair<float, float>> windows;  // by volume key
    std::shared_ptr<const cf::Volume> get(const Request& r, float& lo, float& hi, std::string& source) {
        std::optional<std::int64_t> case_id, volume_id;
        for (const char* k : {"case_id", "volume_id"}) {
            const auto it = r.params.find(k);
            if (it == r.params.end()) continue;
            std::size_t n = 0;
            long long v = 0;
            try {
                v = std::stoll(it->second, &n);
            } catch (const std::exception&) {
                n = 0;
            }
            if (n != it->second.size() || v < 1) throw bad(std::string("slices ") + k, "'" + it->second.substr(0, 40) + "' is not a positive integer");
            (std::string(k) == "case_id" ? case_id : volume_id) = v;
        }
        if (volume_id && !case_id) throw bad("slices volume_id", "given without case_id");
        if (!case_id) {
            source = "data.t1";
            return bundled->get(lo, hi);
        }
        const auto ref = resolve_case_volume(*store, *case_id, volume_id, "navigation slices");
        auto loaded = cases->get(ref);
        {
            std::lock_guard lk(mu);
            auto it = windows.find(ref.key());
            if (it == windows.end()) it = windows.emplace(ref.key(), slice_window(loaded->volume)).first;
            lo = it->second.first;
            hi = it->second.second;
        }
        source = "case " + std::to_string(*case_id) + " " + ref.source;
        // Aliasing: the volume lives as long as its loaded entry.
        return std::shared_ptr<const cf::Volume>(loaded, &loaded->volume);
    }
};

/// Trilinear sample at a continuous index; 0 outside.
float sample(const cf::Volume& v, const Eigen::Vector3d& ijk) {
    const auto& d = v.geom.dims;
    const int i = int(std::floor(ijk.x())), j = int(std::floor(ijk.y())), k = int(std::floor(ijk.z()));
    if (i < 0 || j < 0 || k < 0 || i + 1 >= d[0] || j + 1 >= d[1] || k + 1 >= d[2]) return 0.f;
    const double fx = ijk.x() - i, fy = ijk.y() - j, fz = ijk.z() - k;
    auto at = [&](int a, int b, int c) { return double(v.at(i + a, j + b, k + c)); };
    const double c00 = at(0, 0, 0) * (1 - fx) + at(1, 0, 0) * fx, c10 = at(0, 1, 0) * (1 - fx) + at(1, 1, 0) * fx;
    const double c01 = at(0, 0, 1) * (1 - fx) + at(1, 0, 1) * fx, c11 = at(0, 1, 1) * (1 - fx) + at(1, 1, 1) * fx;
    return float((c00 * (1 - fy) + c10 * fy) * (1 - fz) + (c01 * (1 - fy) + c11 * fy) * fz);
}

/// Three orthogonal slices through p (LPS mm) side by side, radiological display: axial (left
/// of the patient on the right of the screen, anterior up), coronal (superior up), sagittal
/// (anterior left, superior up); a crosshair at p on each.
cv::Mat tri_planar(const cf::Volume& v, float lo, float hi, const Eigen::Vector3d& p, int size, double fov_mm) {
    cv::Mat img(size, 3 * size, CV_8UC3, cv::Scalar(0, 0, 0));
    const Eigen::Affine3d index_from_world = v.geom.index_from_world();
    const double px = fov_mm / size;
    const Eigen::Vector3d X(1, 0, 0), Y(0, 1, 0), Z(0, 0, 1);
    const Eigen::Vector3d axes[3][2] = {{X, Y}, {X, -Z}, {Y, -Z}};  // screen u, v directions per panel
    const float scale = 255.f / (hi - lo);
    for (int panel = 0; panel < 3; ++panel) {
        for (int r = 0; r < size; ++r) {
            auto* row = img.ptr<cv::Vec3b>(r) + panel * size;
            for (int c = 0; c < size; ++c) {
                const Eigen::Vector3d w = p + ((c + 0.5 - size / 2.0) * px) * axes[panel][0] + ((r + 0.5 - size / 2.0) * px) * axes[panel][1];
                const float g = std::clamp((sample(v, index_from_world * w) - lo) * scale, 0.f, 255.f);
                row[c] = cv::Vec3b(uchar(g), uchar(g), uchar(g));
            }
        }
        const int cx = panel * size + size / 2, cy = size / 2, gap = std::max(4, size / 40), len = size / 6;
        const cv::Scalar green(80, 255, 80);
        cv::line(img, {cx - gap - len, cy}, {cx - gap, cy}, green, 1);
        cv::line(img, {cx + gap, cy}, {cx + gap + len, cy}, green, 1);
        cv::line(img, {cx, cy - gap - len}, {cx, cy - gap}, green, 1);
        cv::line(img, {cx, cy + gap}, {cx, cy + gap + len}, green, 1);
        cv::circle(img, {cx, cy}, 2, green, cv::FILLED);
        if (panel > 0) cv::line(img, {panel * size, 0}, {panel * size, size - 1}, cv::Scalar(60, 60, 60), 1);
    }
    return img;
}

/// Skin points on the MRI for a first set of fiducials: from the head's centroid, the first
/// voxel above a skin threshold met when marching inwards along six directions (forehead,
/// its left and right, left, right, vertex). Labels name the direction.
json suggested_fiducials(const cf::Volume& v, float lo, float hi) {
    const float thr = lo + 0.2f * (hi - lo);
    const Eigen::Affine3d world_from_index = v.geom.world_from_index(), index_from_world = world_from_index.inverse();
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    double n = 0;
    const auto& d = v.geom.dims;
    for (int k = 0; k < d[2]; k += 4)
        for (int j = 0; j < d[1]; j += 4)
            for (int i = 0; i < d[0]; i += 4)
                if (v.at(i, j, k) > thr) {
                    sum += world_from_index * Eigen::Vector3d(i, j, k);
                    n += 1;
                }
    if (n < 1) throw ApiError(422, "unprocessable", "navigation: no head found in data.t1 (nothing above the skin threshold)");
    const Eigen::Vector3d c = sum / n;
    const std::pair<const char*, Eigen::Vector3d> dirs[] = {
        {"forehead", {0, -1, 0.45}},        {"forehead-left", {0.6, -1, 0.45}}, {"forehead-right", {-0.6, -1, 0.45}},
        {"left", {1, 0, 0.2}},              {"right", {-1, 0, 0.2}},           {"vertex", {0, 0.15, 1}}};
    json out = json::array();
    for (const auto& [name, dir0] : dirs) {
        const Eigen::Vector3d dir = dir0.normalized();
        for (double t = 160; t > 10; t -= 0.5) {
            const Eigen::Vector3d w = c + t * dir;
            if (sample(v, index_from_world * w) > thr) {
                out.push_back({{"label", name}, {"p_image_mm", vec_json(w)}});
                break;
            }
        }
    }
    return out;
}

/// The pointer tip in use (tip_pointer_mm): NavigationOptions' until a pivot calibration is
/// applied (POST /api/navigation/pivot {apply: true}); stored in NavigationOptions::tip_file and read again at start.
class PointerTip {
public:
    explicit PointerTip(const Eigen::Vector3d& t) : tip_(t) {}
    Eigen::Vector3d get() const {
        std::lock_guard lk(mu_);
        return tip_;
    }
    std::string source() const {
        std::lock_guard lk(mu_);
        return source_;
    }
    void set(const Eigen::Vector3d& t, const std::string& source) {
        std::lock_guard lk(mu_);
        tip_ = t;
        source_ = source;
    }

private:
    mutable std::mutex mu_;
    Eigen::Vector3d tip_;
    std::string source_ = "default (the pointer tool's origin)";
};

/// The applied pivot calibration kept on disk (NavigationOptions::tip_file): read at start,
/// written on apply through a temporary file, fsync and rename (never half-written).
/// {"tip_pointer_mm": [x, y, z], "source": "...", "rms_mm": r, "calibrated_utc": "..."}.
std::optional<Eigen::Vector3d> read_stored_tip(const std::filesystem::path& p, std::string& source, std::string& problem) {
    std::error_code ec;
    if (!std::filesystem::exists(p, ec)) return std::nullopt;
    std::ifstream in(p);
    const json j = json::parse(in, nullptr, false);
    const json t = j.is_object() ? j.value("tip_pointer_mm", json()) : json();
    if (!t.is_array() || t.size() != 3) {
        problem = p.string() + ": tip_pointer_mm is not [x, y, z]";
        return std::nullopt;
    }
    Eigen::Vector3d v;
    for (int i = 0; i < 3; ++i) {
        if (!t[i].is_number() || !std::isfinite(t[i].get<double>()) || std::abs(t[i].get<double>()) > 1000) {
            problem = p.string() + ": tip_pointer_mm[" + std::to_string(i) + "] is not a number within +-1000 mm";
            return std::nullopt;
        }
        v[i] = t[i].get<double>();
    }
    source = "stored " + j.value("source", std::string("pivot calibration")) + " (" + j.value("calibrated_utc", std::string("?")) + ")";
    return v;
}

void write_stored_tip(const std::filesystem::path& p, const json& j) {
    const std::filesystem::path tmp = p.string() + ".tmp";
    const std::string text = j.dump(1) + "\n";
    std::FILE* f = std::fopen(tmp.c_str(), "wb");
    bool ok = f && std::fwrite(text.data(), 1, text.size(), f) == text.size() && std::fflush(f) == 0 && ::fsync(::fileno(f)) == 0;
    if (f) ok = std::fclose(f) == 0 && ok;
    std::error_code ec;
    if (ok) std::filesystem::rename(tmp, p, ec);
    if (!ok || ec) {
        std::filesystem::remove(tmp, ec);
        throw ApiError(500, "internal", "pivot: the calibration could not be stored in " + p.string());
    }
}

Eigen::Matrix4d mat4(const json& v, const std::string& what) {
    if (!v.is_array() || v.size() != 4) throw bad(what, "must be 4 rows of 4 numbers");
    Eigen::Matrix4d T;
    for (int r = 0; r < 4; ++r) {
        if (!v[r].is_array() || v[r].size() != 4) throw bad(what, "must be 4 rows of 4 numbers");
        for (int c = 0; c < 4; ++c) {
            if (!v[r][c].is_number()) throw bad(what, "must be 4 rows of 4 numbers");
            T(r, c) = v[r][c].get<double>();
        }
    }
    const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
    if (!T.allFinite() || (R.transpose() * R - Eigen::Matrix3d::Identity()).norm() > 1e-6 || R.determinant() < 0 ||
        (T.row(3) - Eigen::RowVector4d(0, 0, 0, 1)).norm() > 1e-9)
        throw bad(what, "must be a rigid transform (orthonormal rotation, last row 0 0 0 1)");
    return T;
}


// ------------------------------------------------------------------------ cortical landmarks

/// The landmark list of a stored revision ([] when none).
json landmark_list(const Stored& s) { return s.revision ? s.content.at("landmarks") : json::array(); }

/// The sets in the order they were first recorded, with their counts.
json landmark_sets(const json& list) {
    std::vector<std::string> order;
    std::map<std::string, int> count;
    for (const auto& l : list) {
        const std::string set = l.at("set").get<std::string>();
        if (!count.count(set)) order.push_back(set);
        ++count[set];
    }
    json out = json::array();
    for (const auto& s : order) out.push_back({{"set", s}, {"count", count[s]}});
    return out;
}
std::string set_names(const json& list) {
    std::string names;
    for (const auto& s : landmark_sets(list)) names += (names.empty() ? "" : ", ") + s["set"].get<std::string>();
    return names.empty() ? "none recorded" : names;
}

/// The landmarks of one set as core's digitised points (image space).
std::vector<cf::DigitisedPoint> landmarks_of(const json& list, const std::string& set, std::set<std::int64_t>& registrations) {
    std::vector<cf::DigitisedPoint> out;
    for (const auto& l : list) {
        if (l.at("set") != set) continue;
        cf::DigitisedPoint d;
        d.label = l.at("label").get<std::string>();
        d.p_patient_mm = vec3(l.at("p_reference_mm"), "stored landmark");
        d.p_image_mm = vec3(l.at("p_image_mm"), "stored landmark");
        d.spread_mm = l.value("spread_mm", 0.0);
        d.frames = l.value("frames", 0);
        registrations.insert(l.value("registration_revision", std::int64_t{0}));
        out.push_back(d);
    }
    return out;
}

json report_json(const cf::BrainShiftReport& rep, const std::vector<cf::DigitisedPoint>& earlier, const std::vector<cf::DigitisedPoint>& later) {
    auto find = [](const std::vector<cf::DigitisedPoint>& v, const std::string& label) -> const cf::DigitisedPoint* {
        for (const auto& d : v)
            if (d.label == label) return &d;
        return nullptr;
    };
    json rows = json::array();
    for (const auto& row : rep.rows)
        rows.push_back({{"label", row.label},
                        {"earlier_image_mm", vec_json(find(earlier, row.label)->p_image_mm)},
                        {"later_image_mm", vec_json(find(later, row.label)->p_image_mm)},
                        {"d_mm", vec_json(row.d_mm)},
                        {"magnitude_mm", row.magnitude_mm}});
    return {{"rows", rows},
            {"n", rep.rows.size()},
            {"mean_d_mm", vec_json(rep.mean_d_mm)},
            {"sd_d_mm", vec_json(rep.sd_d_mm)},
            {"mean_abs_d_mm", vec_json(rep.mean_abs_d_mm)},
            {"mean_magnitude_mm", rep.mean_magnitude_mm},
            {"sd_magnitude_mm", rep.sd_magnitude_mm},
            {"max_magnitude_mm", rep.max_magnitude_mm},
            {"missing_later", rep.missing_later},
            {"missing_earlier", rep.missing_earlier},
            {"axes", "image LPS mm (x left, y posterior, z superior); d = later - earlier"},
            {"table", cf::format_brain_shift_table(rep)}};
}

}  // namespace

void register_navigation_endpoints(EndpointRegistry& reg, CaseStore& store, TrackerModule& tracker, const NavigationOptions& options) {
    CaseStore* st = &store;
    TrackerModule* tr = &tracker;
    auto tip_state = std::make_shared<PointerTip>(Eigen::Vector3d(options.tip_pointer_mm[0], options.tip_pointer_mm[1], options.tip_pointer_mm[2]));
    // The last applied pivot calibration survives a restart (docs/api/navigation.md).
    const std::filesystem::path tip_file = options.tip_file.empty() ? store.dir() / "pointer_tip.json" : options.tip_file;
    {
        std::string source, problem;
        if (const auto t = read_stored_tip(tip_file, source, problem)) tip_state->set(*t, source);
        else if (!problem.empty()) tip_state->set(tip_state->get(), "default (the stored calibration is unusable: " + problem + ")");
    }
    auto slices = std::make_shared<SliceSource>();
    slices->bundled = std::make_shared<SliceVolume>(options.t1_path);
    slices->store = st;
    slices->cases = std::make_shared<CaseVolumeCache>(store, options.work_dir / "slice_volumes", 1);  // 64 MiB a 256^3 T1
    // Recording and deleting read the newest list of recorded fiducials and store the next
    // one: two at once must not both build on the same list (one would be lost).
    auto list_mu = std::make_shared<std::mutex>();

    // ---- live pointer, slices, suggestions, simulator ----
    reg.add({"GET", "/api/navigation/pointer", "navigation.pointer", Access::read,
             "The newest tracker frame's tools and the pointer tip in the reference frame (p_reference_mm) and the tracker's",
             [tr, tip_in_use = tip_state](const Request&) {
                 const Eigen::Vector3d tip = tip_in_use->get();
                 json j{{"enabled", tr->enabled()}, {"tip_pointer_mm", vec_json(tip)}, {"tip_source", tip_in_use->source()},
                        {"p_reference_mm", nullptr}, {"p_tracker_mm", nullptr}};
                 const auto status = tr->status();
                 j["state"] = cf::tracker::state_name(status.state);
                 j["frame_rate_hz"] = status.frame_rate_hz;
                 const auto frames = tr->recent_frames(std::int64_t(1e9));
                 if (frames.empty()) {
                     j["frame"] = nullptr;
                     return ok(j);
                 }
                 const TrackerFrame& f = frames.back();
                 j["frame"] = cf::tracker::frame_to_json(f);
                 j["age_ms"] = double(cf::tracker::steady_ns() - f.publish_steady_ns) / 1e6;
                 const auto* p = find_tool(f, "pointer");
                 const auto* r = find_tool(f, "reference");
                 if (p && p->T_tracker_from_tool) j["p_tracker_mm"] = vec_json(*p->T_tracker_from_tool * tip);
                 if (p && r && p->T_tracker_from_tool && r->T_tracker_from_tool)
                     j["p_reference_mm"] = vec_json(r->T_tracker_from_tool->inverse() * (*p->T_tracker_from_tool * tip));
                 return ok(j);
             }});
    reg.add({"GET", "/api/navigation/slices", "navigation.slices", Access::read,
             "Axial, coronal and sagittal slices of the MRI through a point (query x, y, z in LPS mm; size, fov_mm, format), side by side",
             [slices](const Request& r) {
                 auto num = [&](const char* k, double def, double lo, double hi) {
                     const auto it = r.params.find(k);
                     if (it == r.params.end()) return def;
                     double v = 0;
                     try {
                         std::size_t used = 0;
                         v = std::stod(it->second, &used);
                         if (used != it->second.size()) throw std::invalid_argument("trailing");
                     } catch (const std::exception&) {
                         throw bad(std::string("slices ") + k, "'" + it->second.substr(0, 40) + "' is not a number");
                     }
                     if (!(v >= lo && v <= hi)) throw bad(std::string("slices ") + k, "out of range " + std::to_string(lo) + ".." + std::to_string(hi));
                     return v;
                 };
                 float lo = 0, hi = 1;
                 std::string source;
                 const auto vol = slices->get(r, lo, hi, source);
                 const Eigen::Vector3d c = vol->geom.center_world_mm();
                 const Eigen::Vector3d p(num("x", c.x(), -5000, 5000), num("y", c.y(), -5000, 5000), num("z", c.z(), -5000, 5000));
                 const int size = int(num("size", 256, 32, 1024));
                 const double fov = num("fov_mm", 220, 10, 1000);
                 const auto fmt = r.params.count("format") ? r.params.at("format") : std::string("jpeg");
                 if (fmt != "jpeg" && fmt != "png") throw bad("slices format", "'" + fmt.substr(0, 20) + "' must be jpeg or png");
                 const cv::Mat img = tri_planar(*vol, lo, hi, p, size, fov);
                 std::vector<uchar> buf;
                 cv::imencode(fmt == "png" ? ".png" : ".jpg", img, buf, fmt == "png" ? std::vector<int>{} : std::vector<int>{cv::IMWRITE_JPEG_QUALITY, 85});
                 Response resp = Response::binary(std::string(buf.begin(), buf.end()), fmt == "png" ? "image/png" : "image/jpeg");
                 resp.headers["X-Slice-Layout"] = "axial,coronal,sagittal";
                 resp.headers["X-Slice-Volume"] = source;
                 resp.headers["Cache-Control"] = "no-store";
                 return resp;
             }});
    reg.add({"GET", "/api/navigation/suggested-fiducials", "navigation.suggested_fiducials", Access::read,
             "Skin points on the MRI (forehead, its left and right, left, right, vertex) to start a fiducial list from",
             [slices](const Request& r) {
                 float lo = 0, hi = 1;
                 std::string source;
                 const auto vol = slices->get(r, lo, hi, source);
                 return ok({{"fiducials", suggested_fiducials(*vol, lo, hi)}});
             }});
    reg.add({"POST", "/api/tracker/sim/pointer", "tracker.sim_pointer", Access::write,
             "Simulator only: place a tool: {tool?: pointer|reference, touch_image_mm | touch_reference_mm | T_reference_from_pointer | hidden: true | free: true}",
             [tr, tip_in_use = tip_state](const Request& r) {
                 const json b = body_object(r, "sim pointer", {"tool", "touch_image_mm", "touch_reference_mm", "T_reference_from_pointer", "hidden", "free"});
                 const Eigen::Vector3d tip = tip_in_use->get();
                 auto* sim = tr->simulator();
                 if (!sim) throw conflict("tracker.source", "no simulator runs (tracker.source is not sim, or the tracker is disabled)");
                 const std::string tool = text(b, "tool", "pointer", "sim pointer");
                 if (tool != "pointer" && tool != "reference") throw bad("sim pointer tool", "'" + tool.substr(0, 40) + "' must be pointer or reference");
                 const std::string part = tool == "pointer" ? "CF-POINTER" : "CF-REFERENCE";
                 const int modes = int(b.contains("touch_image_mm")) + int(b.contains("touch_reference_mm")) + int(b.contains("T_reference_from_pointer")) +
                                   int(b.contains("hidden")) + int(b.contains("free"));
                 if (modes != 1) throw bad("sim pointer", "give exactly one of touch_image_mm, touch_reference_mm, T_reference_from_pointer, hidden, free");
                 const Eigen::Matrix4d T_image_from_reference = sim_T_image_from_reference();
                 json out{{"tool", tool}, {"T_image_from_reference_truth", mat_json(T_image_from_reference)}};
                 if (b.contains("hidden") || b.contains("free")) {
                     const char* k = b.contains("hidden") ? "hidden" : "free";
                     if (!b[k].is_boolean() || !b[k].get<bool>()) throw bad(std::string("sim pointer ") + k, "must be true");
                     out["from_frame"] = sim->hold(part, std::nullopt, b.contains("hidden"));
                     out["state"] = k;
                     return ok(out);
                 }
                 if (tool != "pointer") throw bad("sim pointer tool", "only the pointer touches points");
                 Eigen::Vector3d p_reference;
                 std::optional<Eigen::Matrix4d> given;
                 if (b.contains("T_reference_from_pointer")) {
                     given = mat4(b["T_reference_from_pointer"], "sim pointer T_reference_from_pointer");
                     p_reference = (*given * tip.homogeneous()).head<3>();
                 } else if (b.contains("touch_image_mm")) {
                     const Eigen::Vector3d p_image = vec3(b["touch_image_mm"], "sim pointer touch_image_mm");
                     p_reference = (T_image_from_reference.inverse() * p_image.homogeneous()).head<3>();
                 } else {
                     p_reference = vec3(b["touch_reference_mm"], "sim pointer touch_reference_mm");
                 }
                 // The reference where the simulator has it now (noiseless), and the pointer
                 // coming from above at an angle that depends on the point, its tip on it.
                 const auto frames = tr->recent_frames(std::int64_t(1e9));
                 const std::uint32_t frame = frames.empty() ? 0 : frames.back().frame_number;
                 const auto ref = sim->truth("CF-REFERENCE", frame);
                 if (!ref) throw ApiError(500, "internal", "sim: no reference tool in the scene");
                 Eigen::Isometry3d T_reference_from_pointer = Eigen::Isometry3d::Identity();
                 T_reference_from_pointer.linear() = (Eigen::AngleAxisd(0.5 + 0.002 * p_reference.x(), Eigen::Vector3d::UnitX()) *
                                                      Eigen::AngleAxisd(0.3 - 0.002 * p_reference.y(), Eigen::Vector3d::UnitY()))
                                                         .toRotationMatrix();
                 T_reference_from_pointer.translation() = p_reference - T_reference_from_pointer.linear() * tip;
                 if (given) T_reference_from_pointer.matrix() = *given;
                 out["from_frame"] = sim->hold(part, ref->T_tracker_from_tool * T_reference_from_pointer, false);
                 out["state"] = "touching";
                 out["p_reference_mm"] = vec_json(p_reference);
                 return ok(out);
             }});

    reg.add({"POST", "/api/navigation/pivot", "navigation.pivot", Access::write,
             "Pivot calibration of the pointer tip: poses collected for `seconds` while the tip rests in a divot and the handle swivels: {seconds?, pointer?, min_spread_deg?, apply?}",
             [tr, tip_state, tip_file](const Request& r) {
                 const json b = body_object(r, "pivot", {"seconds", "pointer", "min_spread_deg", "apply"});
                 const double seconds = number(b, "seconds", 5.0, 0.5, 30.0, "pivot");
                 const double min_spread = number(b, "min_spread_deg", 10.0, 0.0, 90.0, "pivot");
                 const std::string pointer = text(b, "pointer", "pointer", "pivot");
                 if (b.contains("apply") && !b["apply"].is_boolean()) throw bad("pivot apply", "must be true or false");
                 const bool apply = b.value("apply", false);
                 if (!tr->enabled()) throw conflict("tracker", "disabled (tracker.enabled is false)");
                 // Every frame of the span, read from the module's recent frames as they come
                 // (it keeps the last 512: re-read every 50 ms, new sequence numbers only).
                 std::vector<cf::RigidTransform> poses;
                 std::uint64_t last_seq = 0;
                 int unseen = 0;
                 const std::int64_t t_start = cf::tracker::steady_ns(), t_end = t_start + std::int64_t(seconds * 1e9);
                 for (;;) {
                     for (const auto& f : tr->recent_frames(std::int64_t(1e9))) {
                         if (f.sequence <= last_seq || f.publish_steady_ns < t_start) continue;
                         last_seq = f.sequence;
                         const auto* t = find_tool(f, pointer);
                         if (t && t->T_tracker_from_tool) poses.push_back(t->T_tracker_from_tool->matrix());
                         else ++unseen;
                     }
                     if (cf::tracker::steady_ns() >= t_end) break;
                     std::this_thread::sleep_for(std::chrono::milliseconds(50));
                 }
                 if (poses.size() < 10)
                     throw conflict(pointer, std::to_string(poses.size()) + " pose(s) in " + std::to_string(seconds).substr(0, 4) + " s (" +
                                                 std::to_string(unseen) + " frames without it): keep the pointer in view while pivoting");
                 cf::PivotOptions po;
                 po.min_rotation_spread_deg = min_spread;
                 cf::PivotResult pr;
                 try {
                     pr = cf::pivot_calibration(poses, po);
                 } catch (const cf::InputError& e) {
                     throw conflict(pointer, e.what());
                 }
                 json res = json::array();
                 for (double v : pr.residuals_mm) res.push_back(v);
                 json out{{"tip_pointer_mm", vec_json(pr.tip_tool_mm)}, {"pivot_tracker_mm", vec_json(pr.pivot_tracker_mm)}, {"rms_mm", pr.rms_mm},
                          {"rotation_spread_deg", pr.rotation_spread_deg}, {"rotation_range_deg", pr.rotation_range_deg},
                          {"warning", pr.warning}, {"poses", poses.size()}, {"frames_without_pointer", unseen}, {"applied", false}};
                 if (apply) {
                     char buf[240];
                     if (!pr.warning.empty() || pr.rms_mm > 1.0) {
                         std::snprintf(buf, sizeof buf, "not applied: rms %.2f mm (limit 1.00), rotation spread %.1f deg%s%s", pr.rms_mm,
                                       pr.rotation_spread_deg, pr.warning.empty() ? "" : ": ", pr.warning.c_str());
                         throw conflict("pivot", buf);
                     }
                     std::snprintf(buf, sizeof buf, "pivot calibration: rms %.2f mm over %zu poses, spread %.1f deg", pr.rms_mm, poses.size(),
                                   pr.rotation_spread_deg);
                     write_stored_tip(tip_file, {{"tip_pointer_mm", vec_json(pr.tip_tool_mm)}, {"source", buf}, {"rms_mm", pr.rms_mm},
                                                 {"rotation_spread_deg", pr.rotation_spread_deg}, {"poses", poses.size()},
                                                 {"calibrated_utc", format_utc(system_now_utc())}});
                     tip_state->set(pr.tip_tool_mm, buf);
                     out["applied"] = true;
                 }
                 return ok(out);
             }});

    // ---- per case ----
    reg.add({"GET", "/api/cases/{id}/navigation", "navigation.get", Access::read,
             "The case's image fiducials, the fiducials recorded with the pointer, and the accepted patient registration",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     const Stored img = newest(*st, rec, kImageKind), pat = newest(*st, rec, kPatientKind), acc = newest(*st, rec, kRegistrationKind);
                     int accepted_count = 0;
                     for (const auto& x : rec.results) accepted_count += x.kind == kRegistrationKind;
                     json accepted = nullptr;
                     if (acc.revision) {
                         accepted = acc.content;
                         accepted["revision"] = acc.revision;
                         accepted["accepted_utc"] = acc.created_utc;
                     }
                     return ok({{"case_id", id},
                                {"state", to_string(rec.summary.state)},
                                {"image_fiducials", {{"revision", img.revision}, {"fiducials", img.revision ? img.content.at("fiducials") : json::array()}}},
                                {"patient_fiducials", {{"revision", pat.revision}, {"fiducials", patient_list(pat)}}},
                                {"accepted", accepted},
                                {"accepted_count", accepted_count}});
                 });
             }});
    reg.add({"POST", "/api/cases/{id}/navigation/image-fiducials", "navigation.set_image_fiducials", Access::write,
             "Set the fiducials' positions in the image (a new revision): {fiducials: [{label, p_image_mm}]}, 3..64, unique labels",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 const json b = body_object(r, "image fiducials", {"fiducials"});
                 if (!b.contains("fiducials") || !b["fiducials"].is_array()) throw bad("image fiducials fiducials", "must be a list of {label, p_image_mm}");
                 const json& list = b["fiducials"];
                 if (list.size() < 3 || list.size() > kMaxFiducials)
                     throw bad("image fiducials", std::to_string(list.size()) + " given: 3.." + std::to_string(kMaxFiducials) + " are needed");
                 json clean = json::array();
                 std::set<std::string> seen;
                 for (std::size_t i = 0; i < list.size(); ++i) {
                     const std::string ctx = "image fiducials fiducials[" + std::to_string(i) + "]";
                     if (!list[i].is_object()) throw bad(ctx, "must be {label, p_image_mm}");
                     for (auto it = list[i].begin(); it != list[i].end(); ++it)
                         if (it.key() != "label" && it.key() != "p_image_mm") throw bad(ctx + " " + it.key(), "unknown field");
                     const std::string label = label_of(list[i].value("label", json()), ctx + " label");
                     if (!seen.insert(label).second) throw bad(ctx + " label", "'" + label + "' is given twice");
                     clean.push_back({{"label", label}, {"p_image_mm", vec_json(vec3(list[i].value("p_image_mm", json()), ctx + " p_image_mm"))}});
                 }
                 return guarded([&] {
                     const ResultRecord x = store_json(*st, id, kImageKind, "image_fiducials.json", {{"fiducials", clean}}, {{"count", clean.size()}},
                                                       actor_of(r.client));
                     return ok({{"revision", x.id}, {"fiducials", clean}}, 201);
                 });
             }});
    reg.add({"POST", "/api/cases/{id}/navigation/record", "navigation.record", Access::write,
             "Record a fiducial: the pointer tip in the reference's frame, averaged over the last window_s (0.3 s): {label, window_s?, max_spread_mm?, pointer?, reference?}",
             [st, tr, tip_in_use = tip_state, list_mu](const Request& r) {
                 const Eigen::Vector3d tip = tip_in_use->get();
                 const auto id = case_id_param(r);
                 const json b = body_object(r, "record", {"label", "window_s", "max_spread_mm", "pointer", "reference"});
                 const std::string label = label_of(b.value("label", json()), "record label");
                 const double window_s = number(b, "window_s", 0.3, 0.1, 2.0, "record");
                 const double max_spread = number(b, "max_spread_mm", 0.5, 0.05, 5.0, "record");
                 const std::string pointer = text(b, "pointer", "pointer", "record"), reference = text(b, "reference", "reference", "record");
                 return guarded([&] {
                     std::lock_guard lk(*list_mu);
                     const CaseRecord rec = st->get_case(id);  // 404 before the tracker is asked
                     const Stored img = newest(*st, rec, kImageKind);
                     const auto fids = image_fiducials(img);
                     if (fids.empty()) throw conflict("record", "case " + std::to_string(id) + " has no image fiducials yet: set them first");
                     if (std::none_of(fids.begin(), fids.end(), [&](const ImageFiducial& f) { return f.label == label; })) {
                         std::string names;
                         for (const auto& f : fids) names += (names.empty() ? "" : ", ") + f.label;
                         throw bad("record label", "'" + label + "' is not one of the image fiducials (" + names + ")");
                     }
                     const cf::DigitisedPoint d = digitise(*tr, label, pointer, reference, window_s, max_spread, tip);
                     const Stored pat = newest(*st, rec, kPatientKind);
                     json list = json::array();
                     for (const auto& f : patient_list(pat))
                         if (f.at("label") != label) list.push_back(f);
                     const json entry{{"label", label}, {"p_reference_mm", vec_json(d.p_patient_mm)}, {"spread_mm", d.spread_mm},
                                      {"frames", d.frames}, {"window_s", window_s}, {"recorded_utc", format_utc(system_now_utc())}};
                     list.push_back(entry);
                     const ResultRecord x = store_json(*st, id, kPatientKind, "patient_fiducials.json", {{"fiducials", list}},
                                                       {{"recorded", label}, {"count", list.size()}}, actor_of(r.client));
                     return ok({{"revision", x.id}, {"recorded", entry}, {"fiducials", list}}, 201);
                 });
             }});
    auto forget = [st, list_mu](const Request& r, const std::optional<std::string>& label) {
        const auto id = case_id_param(r);
        return guarded([&] {
            std::lock_guard lk(*list_mu);
            const CaseRecord rec = st->get_case(id);
            const Stored pat = newest(*st, rec, kPatientKind);
            json list = json::array();
            bool found = false;
            for (const auto& f : patient_list(pat)) {
                if (label && f.at("label") != *label) list.push_back(f);
                else found = true;
            }
            if (label && !found) throw ApiError(404, "not_found", "patient fiducial '" + *label + "': not recorded in case " + std::to_string(id));
            if (!label && !found) return ok({{"revision", pat.revision}, {"fiducials", list}});  // nothing to clear
            const ResultRecord x = store_json(*st, id, kPatientKind, "patient_fiducials.json", {{"fiducials", list}},
                                              {{"deleted", label ? json(*label) : json("all")}, {"count", list.size()}}, actor_of(r.client));
            return ok({{"revision", x.id}, {"fiducials", list}});
        });
    };
    reg.add({"DELETE", "/api/cases/{id}/navigation/patient-fiducials/{label}", "navigation.delete_fiducial", Access::write,
             "Delete one recorded fiducial (a new revision without it)",
             [forget](const Request& r) { return forget(r, label_of(json(r.params.at("label")), "label")); }});
    reg.add({"DELETE", "/api/cases/{id}/navigation/patient-fiducials", "navigation.clear_fiducials", Access::write,
             "Delete every recorded fiducial (redo; a new, empty revision)", [forget](const Request& r) { return forget(r, std::nullopt); }});
    reg.add({"POST", "/api/cases/{id}/navigation/register", "navigation.register", Access::read,
             "Compute the patient registration from the recorded and image fiducials (nothing stored): {outlier_mm?, fle_mm?, target_image_mm?}",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 const json b = body_object(r, "register", {"outlier_mm", "fle_mm", "target_image_mm"});
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     return ok(compute(newest(*st, rec, kImageKind), newest(*st, rec, kPatientKind), b, "register").j);
                 });
             }});
    reg.add({"POST", "/api/cases/{id}/navigation/accept", "navigation.accept", Access::write,
             "Accept the registration computed from the given revisions (stored with its parameters, audited): {image_fiducials_revision, patient_fiducials_revision, outlier_mm?, fle_mm?, target_image_mm?}",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 const json b = body_object(r, "accept", {"image_fiducials_revision", "patient_fiducials_revision", "outlier_mm", "fle_mm", "target_image_mm"});
                 for (const char* k : {"image_fiducials_revision", "patient_fiducials_revision"})
                     if (!b.contains(k) || !b[k].is_number_integer())
                         throw bad(std::string("accept ") + k, "required: the revision the registration shown was computed from");
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     const Stored img = newest(*st, rec, kImageKind), pat = newest(*st, rec, kPatientKind);
                     if (b["image_fiducials_revision"].get<std::int64_t>() != img.revision || b["patient_fiducials_revision"].get<std::int64_t>() != pat.revision)
                         throw conflict("accept", "the fiducials changed since that registration was computed (now image revision " +
                                                      std::to_string(img.revision) + ", patient revision " + std::to_string(pat.revision) + "): compute it again");
                     json c = compute(img, pat, b, "accept").j;
                     c["format"] = "cortexfuse-patient-registration/1";
                     const Actor by = actor_of(r.client);
                     const ResultRecord x = store_json(*st, id, kRegistrationKind, "patient_registration.json", c,
                                                       {{"params", c["params"]}, {"fre_mm", c["fre_mm"]}, {"image_fiducials_revision", img.revision},
                                                        {"patient_fiducials_revision", pat.revision}},
                                                       by);
                     st->audit(by, "navigation.accept", id, {{"result_id", x.id}, {"fre_mm", c["fre_mm"]}, {"n_used", c["n_used"]}, {"excluded", c["excluded"]}});
                     // The workflow: a planned case is now patient_registered (one step forward);
                     // a case elsewhere in its workflow keeps its state.
                     if (rec.summary.state == CaseState::planned) st->set_state(id, CaseState::patient_registered, by);
                     c["revision"] = x.id;
                     c["accepted_utc"] = format_utc(x.created_utc);
                     c["state"] = to_string(st->get_case(id).summary.state);
                     return ok(c, 201);
                 });
             }});

    // ---- cortical landmarks and brain shift (docs/api/navigation.md "Cortical landmarks") ----
    reg.add({"GET", "/api/cases/{id}/navigation/landmarks", "navigation.landmarks", Access::read,
             "The cortical landmarks digitised with the pointer, every set, and the accepted registration they map through",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     const Stored lm = newest(*st, rec, kLandmarkKind), acc = newest(*st, rec, kRegistrationKind);
                     const json list = landmark_list(lm);
                     return ok({{"case_id", id}, {"revision", lm.revision}, {"registration_revision", acc.revision},
                                {"sets", landmark_sets(list)}, {"landmarks", list}});
                 });
             }});
    reg.add({"POST", "/api/cases/{id}/navigation/landmarks/record", "navigation.record_landmark", Access::write,
             "Digitise a cortical landmark with the pointer (averaged over window_s, mapped into the image by the accepted registration): {label, set?: \"initial\", window_s?, max_spread_mm?, pointer?, reference?}",
             [st, tr, tip_in_use = tip_state, list_mu](const Request& r) {
                 const Eigen::Vector3d tip = tip_in_use->get();
                 const auto id = case_id_param(r);
                 const json b = body_object(r, "landmark", {"label", "set", "window_s", "max_spread_mm", "pointer", "reference"});
                 const std::string label = label_of(b.value("label", json()), "landmark label");
                 const std::string set = b.contains("set") && !b["set"].is_null() ? label_of(b["set"], "landmark set") : std::string("initial");
                 const double window_s = number(b, "window_s", 0.3, 0.1, 2.0, "landmark");
                 const double max_spread = number(b, "max_spread_mm", 0.5, 0.05, 5.0, "landmark");
                 const std::string pointer = text(b, "pointer", "pointer", "landmark"), reference = text(b, "reference", "reference", "landmark");
                 return guarded([&] {
                     std::lock_guard lk(*list_mu);
                     const CaseRecord rec = st->get_case(id);
                     const Stored acc = newest(*st, rec, kRegistrationKind);
                     if (!acc.revision)
                         throw conflict("landmark", "case " + std::to_string(id) +
                                                        " has no accepted patient registration: touch the fiducials and accept the registration first "
                                                        "(the pointer cannot be mapped into the image without it)");
                     const Eigen::Matrix4d T = mat4(acc.content.at("T_image_from_reference"), "stored patient registration");
                     const Stored lm = newest(*st, rec, kLandmarkKind);
                     json list = json::array();
                     for (const auto& l : landmark_list(lm))
                         if (!(l.at("label") == label && l.at("set") == set)) list.push_back(l);
                     if (list.size() >= kMaxLandmarks)
                         throw conflict("landmark", "case " + std::to_string(id) + " holds " + std::to_string(list.size()) + " landmarks (at most " +
                                                        std::to_string(kMaxLandmarks) + "): delete some first");
                     const cf::DigitisedPoint d = digitise(*tr, label, pointer, reference, window_s, max_spread, tip);
                     const Eigen::Vector3d p_image = (T * d.p_patient_mm.homogeneous()).head<3>();
                     const json entry{{"label", label}, {"set", set}, {"p_reference_mm", vec_json(d.p_patient_mm)}, {"p_image_mm", vec_json(p_image)},
                                      {"spread_mm", d.spread_mm}, {"frames", d.frames}, {"window_s", window_s},
                                      {"registration_revision", acc.revision}, {"recorded_utc", format_utc(system_now_utc())}};
                     list.push_back(entry);
                     const ResultRecord x = store_json(*st, id, kLandmarkKind, "cortical_landmarks.json", {{"landmarks", list}},
                                                       {{"recorded", label}, {"set", set}, {"count", list.size()}}, actor_of(r.client));
                     return ok({{"revision", x.id}, {"recorded", entry}, {"sets", landmark_sets(list)}, {"landmarks", list}}, 201);
                 });
             }});
    reg.add({"POST", "/api/cases/{id}/navigation/landmarks/rename", "navigation.rename_landmark", Access::write,
             "Rename a landmark (a new revision): {label, new_label, set?}; without set, in every set",
             [st, list_mu](const Request& r) {
                 const auto id = case_id_param(r);
                 const json b = body_object(r, "rename landmark", {"label", "new_label", "set"});
                 const std::string label = label_of(b.value("label", json()), "rename landmark label");
                 const std::string to = label_of(b.value("new_label", json()), "rename landmark new_label");
                 const std::optional<std::string> set =
                     b.contains("set") && !b["set"].is_null() ? std::optional<std::string>(label_of(b["set"], "rename landmark set")) : std::nullopt;
                 if (to == label) throw bad("rename landmark new_label", "'" + to + "' is the label it has");
                 return guarded([&] {
                     std::lock_guard lk(*list_mu);
                     const CaseRecord rec = st->get_case(id);
                     const Stored lm = newest(*st, rec, kLandmarkKind);
                     json list = landmark_list(lm);
                     std::set<std::string> renamed_in;
                     for (const auto& l : list)
                         if (l.at("label") == label && (!set || l.at("set") == *set)) renamed_in.insert(l.at("set").get<std::string>());
                     if (renamed_in.empty())
                         throw ApiError(404, "not_found", "landmark '" + label + "'" + (set ? " in set '" + *set + "'" : std::string()) +
                                                              ": not recorded in case " + std::to_string(id));
                     for (const auto& l : list)
                         if (l.at("label") == to && renamed_in.count(l.at("set").get<std::string>()))
                             throw conflict("rename landmark new_label", "'" + to + "' is already a landmark of set '" + l.at("set").get<std::string>() + "'");
                     for (auto& l : list)
                         if (l.at("label") == label && renamed_in.count(l.at("set").get<std::string>())) l["label"] = to;
                     const ResultRecord x = store_json(*st, id, kLandmarkKind, "cortical_landmarks.json", {{"landmarks", list}},
                                                       {{"renamed", label}, {"to", to}, {"count", list.size()}}, actor_of(r.client));
                     return ok({{"revision", x.id}, {"sets", landmark_sets(list)}, {"landmarks", list}});
                 });
             }});
    reg.add({"POST", "/api/cases/{id}/navigation/landmarks/delete", "navigation.delete_landmark", Access::write,
             "Delete a landmark of a set, or with no label the whole set (a new revision without it): {set, label?}",
             [st, list_mu](const Request& r) {
                 const auto id = case_id_param(r);
                 const json b = body_object(r, "delete landmark", {"set", "label"});
                 const std::string set = label_of(b.value("set", json()), "delete landmark set");
                 const std::optional<std::string> label =
                     b.contains("label") && !b["label"].is_null() ? std::optional<std::string>(label_of(b["label"], "delete landmark label")) : std::nullopt;
                 return guarded([&] {
                     std::lock_guard lk(*list_mu);
                     const CaseRecord rec = st->get_case(id);
                     const Stored lm = newest(*st, rec, kLandmarkKind);
                     json list = json::array();
                     std::size_t gone = 0;
                     for (const auto& l : landmark_list(lm)) {
                         if (l.at("set") == set && (!label || l.at("label") == *label)) ++gone;
                         else list.push_back(l);
                     }
                     if (!gone)
                         throw ApiError(404, "not_found", (label ? "landmark '" + *label + "' in set '" + set + "'" : "landmark set '" + set + "'") +
                                                              ": not recorded in case " + std::to_string(id) + " (sets: " + set_names(landmark_list(lm)) + ")");
                     const ResultRecord x = store_json(*st, id, kLandmarkKind, "cortical_landmarks.json", {{"landmarks", list}},
                                                       {{"deleted", label ? json(*label) : json("all")}, {"set", set}, {"count", list.size()}},
                                                       actor_of(r.client));
                     return ok({{"revision", x.id}, {"deleted", gone}, {"sets", landmark_sets(list)}, {"landmarks", list}});
                 });
             }});
    reg.add({"POST", "/api/cases/{id}/navigation/brain-shift", "navigation.brain_shift", Access::read,
             "Brain shift between two sets of landmarks (core's brain_shift; nothing stored): {earlier?: \"initial\", later?: \"later\", labels?: [..]}",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 const json b = body_object(r, "brain shift", {"earlier", "later", "labels"});
                 const std::string earlier = b.contains("earlier") && !b["earlier"].is_null() ? label_of(b["earlier"], "brain shift earlier") : "initial";
                 const std::string later = b.contains("later") && !b["later"].is_null() ? label_of(b["later"], "brain shift later") : "later";
                 if (earlier == later) throw bad("brain shift later", "'" + later + "' is the earlier set too: give two different sets");
                 std::optional<std::set<std::string>> only;
                 if (b.contains("labels") && !b["labels"].is_null()) {
                     if (!b["labels"].is_array() || b["labels"].empty()) throw bad("brain shift labels", "must be a non-empty list of landmark labels");
                     only.emplace();
                     for (std::size_t i = 0; i < b["labels"].size(); ++i) only->insert(label_of(b["labels"][i], "brain shift labels[" + std::to_string(i) + "]"));
                 }
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     const json list = landmark_list(newest(*st, rec, kLandmarkKind));
                     std::set<std::int64_t> reg_e, reg_l;
                     auto e = landmarks_of(list, earlier, reg_e), l = landmarks_of(list, later, reg_l);
                     for (const auto& [name, v] : {std::pair{&earlier, &e}, std::pair{&later, &l}})
                         if (v->empty())
                             throw conflict("brain shift set '" + *name + "'", "no landmarks recorded in it in case " + std::to_string(id) +
                                                                                 " (sets: " + set_names(list) + ")");
                     if (only) {
                         for (const auto& want : *only) {
                             const auto has = [&](const std::vector<cf::DigitisedPoint>& v) {
                                 return std::any_of(v.begin(), v.end(), [&](const cf::DigitisedPoint& d) { return d.label == want; });
                             };
                             if (!has(e) && !has(l))
                                 throw bad("brain shift labels", "'" + want + "' is a landmark of neither '" + earlier + "' nor '" + later + "'");
                         }
                         const auto keep = [&](std::vector<cf::DigitisedPoint>& v) {
                             v.erase(std::remove_if(v.begin(), v.end(), [&](const cf::DigitisedPoint& d) { return !only->count(d.label); }), v.end());
                         };
                         keep(e);
                         keep(l);
                     }
                     cf::BrainShiftReport rep;
                     try {
                         rep = cf::brain_shift(e, l);
                     } catch (const cf::InputError& err) {
                         throw conflict("brain shift", err.what());
                     }
                     json out = report_json(rep, e, l);
                     out["case_id"] = id;
                     out["earlier"] = earlier;
                     out["later"] = later;
                     out["registration_revisions"] = {{"earlier", json(reg_e)}, {"later", json(reg_l)}};
                     out["same_registration"] = reg_e == reg_l && reg_e.size() == 1;
                     return ok(out);
                 });
             }});
}

}  // namespace cf::daemon
