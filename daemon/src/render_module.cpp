#include "render_module.hpp"

#include <algorithm>
#include <cctype>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <set>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <sstream>
#include <string_view>

#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/overlay.hpp"
#include "cortexfuse/core/roi.hpp"
#include "cortexfuse/core/surface.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/renderer.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "cortexfuse/core/fusion.hpp"
#include "cortexfuse/core/volume.hpp"
#include "case_volumes.hpp"
#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/daemon/log.hpp"
#include "cortexfuse/render/gl_renderer.hpp"
#include "cortexfuse/render/renderer_factory.hpp"
#include <list>

namespace cf::daemon {

namespace fs = std::filesystem;

namespace {
using Clock = std::chrono::steady_clock;
std::string fs_name(const std::string& p) {
    const auto k = p.find_last_of('/');
    return k == std::string::npos ? p : p.substr(k + 1);
}
double ms_since(Clock::time_point t) { return std::chrono::duration<double, std::milli>(Clock::now() - t).count(); }

ApiError bad(const std::string& field, const std::string& problem) { return ApiError(400, "bad_request", "render " + field + ": " + problem); }

int get_int(const nlohmann::json& r, const char* key, int def, int lo, int hi) {
    if (!r.contains(key)) return def;
    const auto& v = r[key];
    if (!v.is_number_integer()) throw bad(key, "must be an integer");
    const auto x = v.get<long long>();
    if (x < lo || x > hi) throw bad(key, std::to_string(x) + " is out of range " + std::to_string(lo) + ".." + std::to_string(hi));
    return int(x);
}
double get_num(const nlohmann::json& r, const char* key, double def, double lo, double hi) {
    if (!r.contains(key)) return def;
    const auto& v = r[key];
    if (!v.is_number()) throw bad(key, "must be a number");
    const double x = v.get<double>();
    if (!(x >= lo && x <= hi)) throw bad(key, "is out of range " + std::to_string(lo) + ".." + std::to_string(hi));
    return x;
}
std::string get_str(const nlohmann::json& r, const char* key, const std::string& def) {
    if (!r.contains(key)) return def;
    if (!r[key].is_string()) throw bad(key, "must be a string");
    return r[key].get<std::string>();
}

/// The `tf` field of a render request: core's transfer-function JSON (the presets' shape), with
/// the daemon's own limits on top (unknown keys and absurd point counts are refused: the parser
/// itself ignores extra keys).
TransferFunction parse_request_tf(const nlohmann::json& j) {
    if (!j.is_object()) throw bad("tf", "must be a JSON object {units?, colour, opacity, gradient_opacity?, name?}");
    for (auto it = j.begin(); it != j.end(); ++it) {
        const std::string& k = it.key();
        if (k != "name" && k != "units" && k != "colour" && k != "opacity" && k != "gradient_opacity") throw bad("tf." + k, "unknown field");
    }
    if (j.contains("name") && !j["name"].is_string()) throw bad("tf.name", "must be a string");
    if (j.contains("units") && !j["units"].is_string()) throw bad("tf.units", "must be \"normalized\" or \"absolute\"");
    for (const char* k : {"colour", "opacity", "gradient_opacity"}) {
        if (!j.contains(k)) {
            if (std::string(k) != "gradient_opacity") throw bad(std::string("tf.") + k, "missing");
            continue;
        }
        const auto& a = j[k];
        const std::size_t n = std::string(k) == "colour" ? 4 : 2;
        if (!a.is_array()) throw bad(std::string("tf.") + k, "must be an array of points");
        if (a.size() > 256) throw bad(std::string("tf.") + k, std::to_string(a.size()) + " points is more than 256");
        for (std::size_t i = 0; i < a.size(); ++i) {
            const auto& p = a[i];
            if (!p.is_array() || p.size() != n || !std::all_of(p.begin(), p.end(), [](const nlohmann::json& x) { return x.is_number(); }))
                throw bad(std::string("tf.") + k + "[" + std::to_string(i) + "]", "must be " + std::to_string(n) + " numbers" +
                                                                         (n == 4 ? " [x, r, g, b]" : " [x, value]"));
        }
    }
    try {
        return transfer_function_from_json(j, "render tf");
    } catch (const InputError& e) {
        throw ApiError(400, "bad_request", e.what());
    }
}

}  // namespace

namespace {
nlohmann::json vec(const Eigen::Vector3d& v) { return nlohmann::json::array({v.x(), v.y(), v.z()}); }

/// Axis-aligned LPS box of a set of corner points: {min, max, centre, extent}.
nlohmann::json box_json(const Eigen::Vector3d& lo, const Eigen::Vector3d& hi) {
    return {{"min_lps_mm", vec(lo)}, {"max_lps_mm", vec(hi)}, {"center_lps_mm", vec(0.5 * (lo + hi))}, {"extent_mm", vec(hi - lo)}};
}

/// The grid's centre (as the standard views use it) and its world box (voxel centres).
nlohmann::json geometry_json(const VolumeGeometry& g) {
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = -lo;
    for (int c = 0; c < 8; ++c) {
        const Eigen::Vector3d ijk((c & 1) ? g.dims[0] - 1 : 0, (c & 2) ? g.dims[1] - 1 : 0, (c & 4) ? g.dims[2] - 1 : 0);
        const Eigen::Vector3d w = g.world_from_index(ijk);
        lo = lo.cwiseMin(w);
        hi = hi.cwiseMax(w);
    }
    nlohmann::json j = box_json(lo, hi);
    j["center_lps_mm"] = vec(g.center_world_mm());
    j["dims"] = g.dims;
    j["spacing_mm"] = vec(g.spacing_mm);
    j["radius_mm"] = 0.5 * (hi - lo).norm();
    return j;
}

/// The brain mask's box (non-zero voxels), or null when it is empty.
nlohmann::json mask_bounds_json(const LabelVolume& m) {
    const auto& g = m.geom;
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e300), hi = -lo;
    bool any = false;
    const Eigen::Affine3d W = g.world_from_index();
    for (int k = 0; k < g.dims[2]; ++k)
        for (int j = 0; j < g.dims[1]; ++j) {
            int i0 = -1, i1 = -1;
            const std::size_t row = g.linear(0, j, k);
            for (int i = 0; i < g.dims[0]; ++i)
                if (m.voxels[row + std::size_t(i)]) {
                    if (i0 < 0) i0 = i;
                    i1 = i;
                }
            if (i0 < 0) continue;
            any = true;
            for (int i : {i0, i1}) {
                const Eigen::Vector3d w = W * Eigen::Vector3d(i, j, k);
                lo = lo.cwiseMin(w);
                hi = hi.cwiseMax(w);
            }
        }
    if (!any) return nullptr;
    nlohmann::json b = box_json(lo, hi);
    b["radius_mm"] = 0.5 * (hi - lo).norm();
    return b;
}
}  // namespace

nlohmann::json volume_geometry_json(const Volume& volume, const LabelVolume* brain_mask) {
    nlohmann::json j = geometry_json(volume.geom);
    j["brain"] = brain_mask ? mask_bounds_json(*brain_mask) : nlohmann::json(nullptr);
    j["frame"] = "LPS mm (DICOM patient: +x left, +y posterior, +z superior)";
    j["default_view"] = {{"distance_mm", 450}, {"focal_px", "0.5 * width * distance_mm / 110"}, {"target", "center_lps_mm"}};
    return j;
}

struct RenderModule::Job {
    enum class Mode { image, pick, fused };
    Mode mode = Mode::image;
    int width = 0, height = 0;
    std::string preset, format, view;
    TransferFunction tf;
    double opacity = 1, distance_mm = 450, focal_px = 0, sample_mm = 1;
    int quality = 85;
    bool brain_only = true;
    std::optional<Pose> pose;
    std::optional<Intrinsics> camera;
    std::string view_key;          // the view's fields as canonical JSON (format/quality/pixel left out)
    Eigen::Vector2d pixel{0, 0};   // pick
    double surface_opacity = 0.5;  // fused
    std::string pass_key;          // fused: the view but its surface opacity, with its sources' keys
    std::string stream;            // a client's stream of views: a newer job of it supersedes this one
    std::shared_ptr<const FusedSource> fused_src;
    std::shared_ptr<const CaseRenderSource> case_src;  // per-case view (else data.t1)
    struct Layer {
        std::string name;
        std::shared_ptr<const CaseRenderSource> src;
        TransferFunction tf;
        double weight = 1;
        bool visible = true;
    };
    std::vector<Layer> layers;  // multimodal view: [0] the reference
    std::promise<RenderedImage> result;
    std::promise<nlohmann::json> pick_result;
};

/// What the render thread holds: the daemon's MRI and its renderers, the last view's depth (for
/// picks of the picture the client shows), and the case volume and textured surface of the last
/// fused view (loaded again only when their keys change).
struct RenderModule::Scene {
    std::optional<Volume> volume;
    std::optional<LabelVolume> mask;
    std::unique_ptr<Renderer> masked, whole;
    std::string last_view_key, last_backend;
    std::vector<float> last_depth_mm;
    /// A case volume's renderers (made on first use: masked for brain_only when it has a mask,
    /// whole otherwise), most recently used first, at most kCaseRenderersCached.
    struct PreparedCase {
        std::string key;
        std::shared_ptr<const LoadedCaseVolume> vol;
        std::unique_ptr<Renderer> masked, whole;
    };
    std::list<PreparedCase> cases;
    /// The last multimodal scene (one GL fusion renderer, its layers' keys in order), and the
    /// one before it: a view toggling between two scenes (the case view's brain-only and whole
    /// presets mask the T1 layer differently, the fused view's CT is cut) uploads nothing again.
    std::string fusion_key;
    std::unique_ptr<FusionRenderer> fusion;
    Eigen::Vector3d fusion_centre_mm = Eigen::Vector3d::Zero();
    std::string fusion_prev_key;
    std::unique_ptr<FusionRenderer> fusion_prev;
    Eigen::Vector3d fusion_prev_centre_mm = Eigen::Vector3d::Zero();
    // fused
    std::string surface_key, texture_key;
    SurfaceMesh mesh;
    TextureMapping mapping;
    cv::Mat texture_bgra;
    Intrinsics photo_K;  // the fused view's photo camera and ROI alpha (photo size; empty: no ROI),
    cv::Mat roi_alpha;   // kept for the CT layer's craniotomy (craniotomy_keep_mask)
    /// The passes (volume rendering, surface buffers) of the last two fused views (a preview and
    /// a full size), by Job::pass_key and renderer: a view that differs only in its surface
    /// opacity (the opacity slider) is blended again from them, nothing rendered.
    struct FusedPassesOf {
        std::string key;
        FusedPasses passes;
    };
    std::list<FusedPassesOf> fused_passes;

    /// After a GL failure (a lost context, a GL error): every GL renderer goes, so the next
    /// request makes new ones (renderer.kind auto: a CPU one when GL cannot be made any more).
    void drop_gl_renderers() {
        auto drop = [](std::unique_ptr<Renderer>& r) {
            if (r && std::string_view(r->name()) == "gl") r.reset();
        };
        drop(masked);
        drop(whole);
        for (auto& c : cases) {
            drop(c.masked);
            drop(c.whole);
        }
        fusion.reset();
        fusion_key.clear();
        fusion_prev.reset();
        fusion_prev_key.clear();
        last_view_key.clear();
        fused_passes.clear();
    }
};

RenderModule::RenderModule(const DaemonConfig& c) : cfg_(c) {}
RenderModule::~RenderModule() { stop(); }

void RenderModule::start() {
    std::lock_guard lk(mu_);
    if (thread_.joinable()) return;
    state_ = "loading";
    thread_ = std::thread([this] { loop(); });
}

void RenderModule::stop() {
    {
        std::lock_guard lk(mu_);
        stop_ = true;
    }
    cv_.notify_all();
    if (thread_.joinable()) thread_.join();
}

std::shared_ptr<RenderModule::Job> RenderModule::parse_job(const nlohmann::json& r, const std::vector<std::string>& extra) const {
    if (!r.is_object()) throw ApiError(400, "bad_request", "render: the request must be a JSON object");
    static const std::vector<std::string> known = {"width", "height", "preset", "opacity", "brain_only", "view", "distance_mm",
                                                   "T_camera_from_world", "camera", "focal_px", "format", "quality", "sample_mm", "tf",
                                                   "stream"};
    for (auto it = r.begin(); it != r.end(); ++it)
        if (std::find(known.begin(), known.end(), it.key()) == known.end() && std::find(extra.begin(), extra.end(), it.key()) == extra.end())
            throw bad(it.key(), "unknown field");
    auto job = std::make_shared<Job>();
    job->width = get_int(r, "width", 640, 16, cfg_.render_max_width);
    job->height = get_int(r, "height", 480, 16, cfg_.render_max_height);
    if (r.contains("tf") && r.contains("preset")) throw bad("tf", "give either preset or tf, not both");
    job->preset = get_str(r, "preset", "cortex_t1");
    if (r.contains("tf")) {
        job->tf = parse_request_tf(r["tf"]);
        job->preset.clear();
    } else {
        const auto names = preset_names();
        if (std::find(names.begin(), names.end(), job->preset) == names.end()) {
            std::string list;
            for (const auto& n : names) list += (list.empty() ? "" : ", ") + n;
            throw bad("preset", "'" + job->preset + "' is not a preset (" + list + ")");
        }
        job->tf = preset_transfer_function(job->preset);
    }
    job->opacity = get_num(r, "opacity", 1.0, 0.0, 1.0);
    if (r.contains("brain_only")) {
        if (!r["brain_only"].is_boolean()) throw bad("brain_only", "must be true or false");
        job->brain_only = r["brain_only"].get<bool>();
    } else {
        job->brain_only = job->preset == "cortex_t1" || job->preset == "surface_white";
    }
    job->view = get_str(r, "view", "left");
    job->distance_mm = get_num(r, "distance_mm", 450, 50, 5000);
    job->focal_px = get_num(r, "focal_px", 0, 0, 1e6);
    job->sample_mm = get_num(r, "sample_mm", 1.0, 0.1, 5.0);
    job->format = get_str(r, "format", "jpeg");
    if (job->format != "jpeg" && job->format != "png") throw bad("format", "'" + job->format + "' is not jpeg or png");
    job->quality = get_int(r, "quality", cfg_.jpeg_quality, 10, 100);
    job->stream = get_str(r, "stream", "");
    if (r.contains("stream") &&
        (job->stream.empty() || job->stream.size() > 64 ||
         !std::all_of(job->stream.begin(), job->stream.end(), [](char c) { return std::isalnum((unsigned char)c) || c == '_' || c == '-' || c == '.' || c == ':'; })))
        throw bad("stream", "must be 1..64 characters of A-Z a-z 0-9 _ - . :");
    try {
        if (r.contains("T_camera_from_world")) job->pose = parse_pose(r, "render request");
        else if (!std::set<std::string>{"left", "right", "anterior", "posterior", "superior", "inferior"}.count(job->view))
            throw bad("view", "'" + job->view + "' is not left, right, anterior, posterior, superior or inferior");
        if (r.contains("camera")) {
            if (!r["camera"].is_object()) throw bad("camera", "must be an object (intrinsics as in case.json)");
            // The intrinsics themselves (documented), or wrapped as in case.json ({"camera": {...}}).
            const nlohmann::json& cj = r["camera"];
            Intrinsics K = parse_camera(cj.contains("camera") ? cj : nlohmann::json{{"camera", cj}}, "render request");
            K.validate("render request camera");
            if (K.width != job->width || K.height != job->height) K = K.resized(job->width, job->height);
            job->camera = K;
        }
    } catch (const InputError& e) {
        throw ApiError(400, "bad_request", e.what());
    }
    // The view: everything that changes the picture's geometry or its surface (not its encoding).
    nlohmann::json key = r;
    for (const char* k : {"format", "quality", "pixel", "stream"}) key.erase(k);
    job->view_key = key.dump();
    return job;
}

void RenderModule::enqueue(const std::shared_ptr<Job>& job) {
    {
        std::lock_guard lk(mu_);
        if (stop_ || state_ == "stopped") throw ApiError(503, "unavailable", "render: the renderer is not running");
        if (state_ == "failed") throw ApiError(503, "unavailable", "render: the volume could not be loaded: " + error_);
        queue_.push_back(job);
    }
    cv_.notify_all();
}

namespace {
/// The default look of each modality of a multimodal view.
std::string default_preset(const std::string& modality) {
    return modality == "ct" ? "ct_bone" : modality == "fmri" ? "fmri_hot" : "cortex_t1";
}
}  // namespace

/// The `modalities` of a request (with `layers`: one source per entry, in order) into the job's
/// layers, the T1 first; 400 naming `modalities[i]...` for a bad entry.
void RenderModule::parse_layers(Job& job, const nlohmann::json& r, const std::vector<ModalityLayerSource>& layers) const {
    if (r.contains("modalities")) {
        const auto& m = r["modalities"];
        if (!m.is_array() || m.empty() || m.size() > std::size_t(FusionRenderer::kMaxLayers))
            throw bad("modalities", "must be a list of 1.." + std::to_string(FusionRenderer::kMaxLayers) +
                                        " {name, preset | tf, weight, visible}");
        if (layers.size() != m.size()) throw bad("modalities", "need case_id (the case's volumes and plan)");
        for (std::size_t i = 0; i < m.size(); ++i) {
            const std::string f = "modalities[" + std::to_string(i) + "]";
            const auto& e = m[i];
            if (!e.is_object()) throw bad(f, "must be an object {name, preset | tf, weight, visible}");
            for (auto it = e.begin(); it != e.end(); ++it)
                if (it.key() != "name" && it.key() != "preset" && it.key() != "tf" && it.key() != "transfer_function" &&
                    it.key() != "weight" && it.key() != "visible")
                    throw bad(f + "." + it.key(), "unknown field");
            Job::Layer L;
            L.name = layers[i].name;
            L.src = layers[i].volume;
            for (const auto& o : job.layers)
                if (o.name == L.name) throw bad(f + ".name", "'" + L.name + "' is listed twice");
            // transfer_function: a preset name or core's TF JSON; tf / preset as in the request.
            nlohmann::json tfj = e.contains("transfer_function") ? e["transfer_function"] : e.contains("tf") ? e["tf"] : nlohmann::json(nullptr);
            if (int(e.contains("transfer_function")) + int(e.contains("tf")) + int(e.contains("preset")) > 1)
                throw bad(f, "give one of transfer_function, tf or preset");
            if (e.contains("preset")) tfj = e["preset"];
            if (tfj.is_null()) tfj = default_preset(L.name);
            if (tfj.is_string()) {
                const auto names = preset_names();
                const std::string n = tfj.get<std::string>();
                if (std::find(names.begin(), names.end(), n) == names.end()) throw bad(f + ".transfer_function", "unknown preset '" + n.substr(0, 40) + "'");
                L.tf = preset_transfer_function(n);
            } else {
                try {
                    L.tf = parse_request_tf(tfj);
                } catch (const ApiError& ex) {
                    std::string msg = ex.what();
                    const std::string pre = "render tf";
                    if (msg.rfind(pre, 0) == 0) msg = "render " + f + ".transfer_function" + msg.substr(pre.size());
                    throw ApiError(400, "bad_request", msg);
                }
            }
            if (e.contains("weight")) {
                if (!e["weight"].is_number()) throw bad(f + ".weight", "must be a number");
                L.weight = e["weight"].get<double>();
                if (!(L.weight >= 0 && L.weight <= 1)) throw bad(f + ".weight", "is out of range 0..1");
            }
            if (e.contains("visible") && !e["visible"].is_boolean()) throw bad(f + ".visible", "must be true or false");
            L.visible = e.value("visible", true);
            job.layers.push_back(std::move(L));
        }
        // The reference layer (surface depth, shading) is the T1 when it is listed.
        std::stable_partition(job.layers.begin(), job.layers.end(), [](const Job::Layer& L) { return L.name == "t1"; });
    }
}

RenderedImage RenderModule::render(const nlohmann::json& r, std::shared_ptr<const CaseRenderSource> src,
                                   std::vector<ModalityLayerSource> layers) {
    auto job = parse_job(r, {"modalities"});
    job->case_src = std::move(src);
    if (job->case_src) job->view_key += "|" + job->case_src->key;
    parse_layers(*job, r, layers);
    auto fut = job->result.get_future();
    enqueue(job);
    return fut.get();  // rethrows what the render thread set
}

nlohmann::json RenderModule::pick(const nlohmann::json& r, std::shared_ptr<const CaseRenderSource> src) {
    if (!r.is_object()) throw ApiError(400, "bad_request", "render pick: the request must be a JSON object");
    auto job = parse_job(r, {"pixel"});
    job->mode = Job::Mode::pick;
    job->case_src = std::move(src);
    if (job->case_src) job->view_key += "|" + job->case_src->key;
    if (!r.contains("pixel")) throw bad("pixel", "missing: give the pixel [u, v] of the view to pick");
    const auto& p = r["pixel"];
    if (!p.is_array() || p.size() != 2 || !p[0].is_number() || !p[1].is_number() || !std::isfinite(p[0].get<double>()) ||
        !std::isfinite(p[1].get<double>()))
        throw bad("pixel", "must be [u, v], two finite numbers (OpenCV pixel of the view)");
    job->pixel = {p[0].get<double>(), p[1].get<double>()};
    if (job->pixel.x() < -0.5 || job->pixel.x() >= job->width - 0.5 || job->pixel.y() < -0.5 || job->pixel.y() >= job->height - 0.5) {
        std::ostringstream m;
        m << "(" << job->pixel.x() << ", " << job->pixel.y() << ") is outside the " << job->width << "x" << job->height << " image";
        throw bad("pixel", m.str());
    }
    auto fut = job->pick_result.get_future();
    enqueue(job);
    return fut.get();
}

RenderedImage RenderModule::fused(const nlohmann::json& r, std::shared_ptr<const FusedSource> src, std::vector<ModalityLayerSource> layers) {
    auto job = parse_job(r, {"surface_opacity", "modalities"});
    job->mode = Job::Mode::fused;
    job->surface_opacity = get_num(r, "surface_opacity", 0.5, 0.0, 1.0);
    if (!job->pose) throw bad("T_camera_from_world", "missing (the fused view needs a pose)");
    job->fused_src = std::move(src);
    {
        nlohmann::json k = r;
        for (const char* f : {"format", "quality", "pixel", "stream", "surface_opacity"}) k.erase(f);
        job->pass_key = k.dump() + "|" + job->fused_src->texture_key + "|" + job->fused_src->surface_key + "|" +
                        (job->fused_src->volume ? job->fused_src->volume->key : std::string("-"));
        for (const auto& L : layers) job->pass_key += "|" + L.name + "=" + (L.volume ? L.volume->key : std::string("-"));
    }
    parse_layers(*job, r, layers);
    auto fut = job->result.get_future();
    enqueue(job);
    return fut.get();
}

namespace {
/// Writes `bytes` under `dir/name` for a reader that wants a file; removed by the caller.
fs::path stage_file(const std::string& dir, const std::string& name, const std::string& bytes) {
    std::error_code ec;
    fs::create_directories(dir, ec);
    const fs::path p = fs::path(dir) / name;
    std::ofstream o(p, std::ios::binary | std::ios::trunc);
    o.write(bytes.data(), std::streamsize(bytes.size()));
    o.close();
    if (!o) throw std::runtime_error("render: cannot stage " + p.string());
    return p;
}
struct RemoveDir {
    std::string d;
    ~RemoveDir() {
        std::error_code ec;
        if (!d.empty()) fs::remove_all(d, ec);
    }
};
}  // namespace

bool RenderModule::superseded_locked(const Job& job) const {
    if (job.stream.empty() || job.mode == Job::Mode::pick) return false;
    return std::any_of(queue_.begin(), queue_.end(),
                       [&](const std::shared_ptr<Job>& q) { return q->mode != Job::Mode::pick && q->stream == job.stream; });
}

ApiError RenderModule::superseded_error(const Job& job) {
    return ApiError(409, "superseded", "render: superseded by a newer view of stream '" + job.stream + "' (nothing was drawn)");
}

void RenderModule::render_in_bands(Renderer& r, const Intrinsics& K, const Pose& T, const RenderOptions& ro, RenderImage& img,
                                   const Job& job) {
    const std::size_t W = std::size_t(K.width), H = std::size_t(K.height), n = W * H;
    if (job.stream.empty() || n < 2 * std::size_t(kBandPixels)) {
        r.render(K, T, ro, img);
        return;
    }
    // Rows of the same camera: the principal point moved up by the band's first row, so every
    // pixel keeps its own ray (the picture equals the one rendered whole; tested).
    const int rows = std::max(16, int(kBandPixels / K.width));
    {
        std::lock_guard lk(mu_);
        ++banded_;
    }
    img = RenderImage{};
    img.width = K.width;
    img.height = K.height;
    for (int y0 = 0; y0 < K.height; y0 += rows) {
        if (y0 > 0) {
            std::lock_guard lk(mu_);
            if (superseded_locked(job)) {
                ++superseded_;
                ++superseded_in_flight_;
                throw superseded_error(job);
            }
        }
        Intrinsics Kb = K;
        Kb.height = std::min(rows, K.height - y0);
        Kb.cy = K.cy - y0;
        RenderImage b;
        r.render(Kb, T, ro, b);
        auto put = [&](auto& dst, const auto& src, std::size_t per_px) {
            if (src.empty()) return;
            if (dst.empty()) dst.resize(n * per_px);
            std::copy(src.begin(), src.end(), dst.begin() + std::ptrdiff_t(std::size_t(y0) * W * per_px));
        };
        put(img.rgb, b.rgb, 3);
        put(img.grey, b.grey, 1);
        put(img.depth_mm, b.depth_mm, 1);
        put(img.coverage, b.coverage, 1);
    }
}

void RenderModule::loop() {
    Scene sc;
    try {
        const auto t0 = Clock::now();
        sc.volume = load_volume(cfg_.t1_path);
        if (!cfg_.brain_mask_path.empty()) sc.mask = load_mask(cfg_.brain_mask_path, sc.volume->geom);
        log(LogLevel::info, "render", "volume loaded in " + std::to_string(int(ms_since(t0))) + " ms");
        nlohmann::json info = geometry_json(sc.volume->geom);
        if (sc.mask) info["brain"] = mask_bounds_json(*sc.mask);
        std::lock_guard lk(mu_);
        volume_info_ = std::move(info);
        state_ = "ready";
    } catch (const std::exception& e) {
        log(LogLevel::error, "render", std::string("volume not loaded: ") + e.what());
        std::lock_guard lk(mu_);
        state_ = "failed";
        error_ = e.what();
    }
    const RendererKind kind = parse_renderer_kind(cfg_.renderer, "renderer.kind");
    auto make = [&](const Volume& v, const LabelVolume* m) {
        std::ostringstream why;
        auto r = make_renderer(kind, v, preset_transfer_function("cortex_t1"), m, &why);
        std::string reason = why.str();
        while (!reason.empty() && (reason.back() == '\n' || reason.back() == '\r')) reason.pop_back();
        std::lock_guard lk(mu_);
        backend_ = r->name();
        if (!reason.empty()) backend_reason_ = reason;
        else if (backend_reason_.empty()) backend_reason_ = std::string("renderer.kind ") + cfg_.renderer;
        return r;
    };
    if (sc.volume) {
        // The default view's renderer now, so the status says at once which backend runs and why.
        try {
            sc.masked = make(*sc.volume, sc.mask ? &*sc.mask : nullptr);
        } catch (const std::exception& e) {
            log(LogLevel::error, "render", std::string("no renderer: ") + e.what());
            std::lock_guard lk(mu_);
            state_ = "failed";
            error_ = e.what();
        }
    }
    // A case volume's renderer (LRU of prepared volumes by key): masked for brain_only when the
    // case has a brain mask, else the whole volume.
    auto case_renderer = [&](const CaseRenderSource& src, bool brain_only, Eigen::Vector3d& centre_mm) -> Renderer* {
        auto it = std::find_if(sc.cases.begin(), sc.cases.end(), [&](const Scene::PreparedCase& p) { return p.key == src.key; });
        if (it == sc.cases.end()) {
            Scene::PreparedCase pc;
            pc.key = src.key;
            pc.vol = src.load();
            sc.cases.push_front(std::move(pc));
            while (sc.cases.size() > kCaseRenderersCached) sc.cases.pop_back();
            it = sc.cases.begin();
        } else if (it != sc.cases.begin()) {
            sc.cases.splice(sc.cases.begin(), sc.cases, it);
            it = sc.cases.begin();
        }
        centre_mm = it->vol->volume.geom.center_world_mm();
        const bool masked = brain_only && it->vol->brain_mask.has_value();
        auto& rr = masked ? it->masked : it->whole;
        if (!rr) {
            rr = make(it->vol->volume, masked ? &*it->vol->brain_mask : nullptr);
            std::lock_guard lk(mu_);
            ++case_preparations_;
        }
        return rr.get();
    };
    // The multimodal scene of a job's layers: one GL fusion renderer, made again only when the
    // layers' volumes (or brain_only, which masks the T1 layer) change; their transfer
    // functions, weights and visibility are settings of the kept scene (no upload).
    auto fusion_renderer = [&](const Job& job) -> FusionRenderer* {
        // A fused view cuts the craniotomy into the CT layer (the bone the camera sees inside the
        // ROI, down to kCraniotomyMarginMm below the brain surface, is hidden, as `cortexfuse
        // overlay --plan` does): the cut CT depends on the registration (photo, ROI, pose,
        // surface: the texture key), so the scene is made again only when that changes; the
        // CT's visibility, weight and TF stay settings of the kept scene (no upload).
        constexpr double kCraniotomyMarginMm = 3.0;
        const bool cut_ct = job.mode == Job::Mode::fused && job.fused_src;
        std::string key = job.brain_only ? "brain|" : "whole|";
        for (const auto& L : job.layers) {
            key += L.name + "=" + L.src->key + ";";
            if (cut_ct && L.name == "ct") key += "cut=" + job.fused_src->texture_key + ";";
        }
        if ((sc.fusion_key != key || !sc.fusion) && sc.fusion_prev && sc.fusion_prev_key == key) {
            std::swap(sc.fusion, sc.fusion_prev);
            std::swap(sc.fusion_key, sc.fusion_prev_key);
            std::swap(sc.fusion_centre_mm, sc.fusion_prev_centre_mm);
        }
        if (sc.fusion_key != key || !sc.fusion) {
            // The current scene becomes the one before (the older one is dropped first: at most two).
            sc.fusion_prev.reset();
            sc.fusion_prev_key.clear();
            if (sc.fusion) {
                sc.fusion_prev = std::move(sc.fusion);
                sc.fusion_prev_key = sc.fusion_key;
                sc.fusion_prev_centre_mm = sc.fusion_centre_mm;
            }
            sc.fusion.reset();
            sc.fusion_key.clear();
            const std::string what = job.mode == Job::Mode::fused ? "fused modalities" : "render modalities";
            if (kind == RendererKind::cpu)
                throw ApiError(409, "conflict", what + ": multimodal views need the GL renderer (renderer.kind is cpu)");
            std::unique_ptr<FusionRenderer> fr;
            try {
                fr = make_gl_fusion_renderer();
            } catch (const GlError& e) {
                throw ApiError(409, "conflict", what + ": multimodal views need the GL renderer, and none can be made: " + e.what());
            }
            for (const auto& L : job.layers) {
                const auto vol = L.src->load();
                const bool masked = L.name == "t1" && job.brain_only && vol->brain_mask;
                if (&L == &job.layers.front()) sc.fusion_centre_mm = vol->volume.geom.center_world_mm();
                const LabelVolume* mask = masked ? &*vol->brain_mask : nullptr;
                LabelVolume keep;
                if (cut_ct && L.name == "ct") {
                    keep = craniotomy_keep_mask(vol->volume.geom, sc.mesh, sc.photo_K, job.fused_src->T_registered, sc.roi_alpha,
                                                kCraniotomyMarginMm);
                    mask = &keep;
                }
                fr->add_layer(vol->volume, L.tf, mask, LayerSettings{L.weight, L.visible, Pose::Identity()});
            }
            {
                std::lock_guard lk(mu_);
                fusion_uploads_ += std::uint64_t(fr->volume_uploads());
                ++case_preparations_;
                backend_ = fr->name();
            }
            sc.fusion = std::move(fr);
            sc.fusion_key = key;
        }
        const int before = sc.fusion->volume_uploads();
        for (std::size_t i = 0; i < job.layers.size(); ++i) {
            TransferFunction tf = job.layers[i].tf;
            for (auto& p : tf.opacity) p[1] *= job.opacity;
            sc.fusion->set_layer_transfer_function(int(i), tf);
            LayerSettings ls = sc.fusion->layer_settings(int(i));
            ls.weight = job.layers[i].weight;
            ls.visible = job.layers[i].visible;
            sc.fusion->set_layer_settings(int(i), ls);
        }
        std::lock_guard lk(mu_);
        fusion_uploads_ += std::uint64_t(sc.fusion->volume_uploads() - before);
        return sc.fusion.get();
    };
    // The textured surface of a fused view (cached by their keys).
    auto prepare_fused = [&](const FusedSource& src) {
        if (sc.surface_key != src.surface_key) {
            sc.surface_key.clear();
            sc.texture_key.clear();
            RemoveDir rm{src.scratch_dir};
            sc.mesh = load_mesh(stage_file(src.scratch_dir, "brain_surface.ply", src.surface_ply_bytes()));
            sc.surface_key = src.surface_key;
        }
        if (sc.texture_key != src.texture_key) {
            sc.texture_key.clear();
            const std::string bytes = src.photo_bytes();
            const cv::Mat photo = cv::imdecode(cv::Mat(1, int(bytes.size()), CV_8U, const_cast<char*>(bytes.data())), cv::IMREAD_COLOR);
            if (photo.empty()) throw ApiError(422, "unprocessable", "fused: the case's photo does not decode");
            Intrinsics K = parse_camera(nlohmann::json{{"camera", src.photo_intrinsics}}, "fused photo");
            K.validate("fused photo camera");
            const cv::Mat alpha = src.roi.is_null() ? cv::Mat() : roi_mask(parse_roi(src.roi, "fused roi"), photo.cols, photo.rows);
            sc.mapping = map_texture(sc.mesh, K, src.T_registered, alpha);
            sc.texture_bgra = texture_rgba(photo, alpha);
            sc.photo_K = K;
            sc.roi_alpha = alpha;
            sc.texture_key = src.texture_key;
        }
    };
    for (;;) {
        std::shared_ptr<Job> job;
        {
            std::unique_lock lk(mu_);
            cv_.wait(lk, [&] { return stop_ || !queue_.empty(); });
            if (stop_) {
                for (auto& j : queue_) {
                    auto e = std::make_exception_ptr(ApiError(503, "unavailable", "render: the daemon is stopping"));
                    if (j->mode == Job::Mode::pick) j->pick_result.set_exception(e);
                    else j->result.set_exception(e);
                }
                queue_.clear();
                break;
            }
            job = queue_.front();
            queue_.pop_front();
            if (superseded_locked(*job)) {
                // A newer view of the same stream is queued: this one would be thrown away.
                ++superseded_;
                job->result.set_exception(std::make_exception_ptr(superseded_error(*job)));
                continue;
            }
        }
        try {
            if (!sc.volume) throw ApiError(503, "unavailable", "render: the volume could not be loaded: " + error_);
            Renderer* r = nullptr;
            Eigen::Vector3d centre_mm = sc.volume->geom.center_world_mm();
            bool layered = false;  // the multimodal scene holds the transfer functions
            if (job->mode == Job::Mode::fused) {
                try {
                    // The multimodal scene when the request lists modalities (the textured surface
                    // is composited by depth over whatever the volume pass shows), else the T1 alone.
                    // The textured surface first: the CT layer's craniotomy needs its mesh and ROI.
                    prepare_fused(*job->fused_src);
                    if (!job->layers.empty()) {
                        r = fusion_renderer(*job);
                        centre_mm = sc.fusion_centre_mm;
                        layered = true;
                    } else {
                        r = case_renderer(*job->fused_src->volume, job->brain_only, centre_mm);
                    }
                } catch (const InputError& e) {
                    throw ApiError(422, "unprocessable", std::string("fused: ") + e.what());
                }
            } else if (!job->layers.empty()) {
                try {
                    r = fusion_renderer(*job);
                } catch (const InputError& e) {
                    throw ApiError(422, "unprocessable", std::string("render modalities: ") + e.what());
                }
                centre_mm = sc.fusion_centre_mm;
                layered = true;
            } else if (job->case_src) {
                try {
                    r = case_renderer(*job->case_src, job->brain_only, centre_mm);
                } catch (const InputError& e) {
                    throw ApiError(422, "unprocessable", "render case volume: " + std::string(e.what()));
                }
            } else {
                const bool use_mask = job->brain_only || !sc.mask.has_value();  // 'masked' is the maskless one without a mask
                auto& rr = use_mask ? sc.masked : sc.whole;
                if (!rr) rr = make(*sc.volume, use_mask && sc.mask ? &*sc.mask : nullptr);
                r = rr.get();
            }
            TransferFunction tf = job->tf;
            for (auto& p : tf.opacity) p[1] *= job->opacity;
            Intrinsics K;
            if (job->camera) K = *job->camera;
            else {
                K.width = job->width;
                K.height = job->height;
                K.fx = K.fy = job->focal_px > 0 ? job->focal_px : 0.5 * job->width * job->distance_mm / 110.0;
                K.cx = (job->width - 1) * 0.5;
                K.cy = (job->height - 1) * 0.5;
            }
            const Pose T = job->pose ? *job->pose : standard_view(job->view, centre_mm, job->distance_mm);
            RenderOptions ro;
            ro.sample_distance_mm = job->sample_mm;
            ro.want_depth = true;  // kept for picks of this view (the CPU caster has it anyway; GL reads one more buffer)
            if (job->mode == Job::Mode::pick) {
                // The pixel whose centre the ray goes through (the depth belongs to pixel centres).
                const int u = std::clamp(int(std::lround(job->pixel.x())), 0, K.width - 1);
                const int v = std::clamp(int(std::lround(job->pixel.y())), 0, K.height - 1);
                const bool reuse = sc.last_view_key == job->view_key && sc.last_depth_mm.size() == std::size_t(K.width) * K.height;
                if (!reuse) {
                    if (!layered) r->set_transfer_function(tf);
                    ro.want_rgb = false;
                    RenderImage img;
                    r->render(K, T, ro, img);
                    sc.last_depth_mm = std::move(img.depth_mm);
                    sc.last_view_key = job->view_key;
                    sc.last_backend = r->name();
                }
                const float z_mm = sc.last_depth_mm[std::size_t(v) * K.width + u];
                if (!(z_mm > 0)) {
                    std::ostringstream m;
                    m << "render pick pixel: no surface at (" << u << ", " << v << "): the ray misses the rendered volume";
                    throw ApiError(422, "no_surface", m.str());
                }
                const Eigen::Vector3d p_cam = backproject(K, Eigen::Vector2d(u, v), z_mm);
                const Eigen::Vector3d p_world = (T.inverse() * p_cam.homogeneous()).head<3>();
                job->pick_result.set_value({{"pixel", {u, v}},
                                            {"p_world_mm", {p_world.x(), p_world.y(), p_world.z()}},
                                            {"depth_mm", z_mm},
                                            {"frame", "LPS mm"},
                                            {"reused_render", reuse},
                                            {"renderer", sc.last_backend}});
                continue;
            }
            if (!layered) r->set_transfer_function(tf);
            RenderImage img;
            cv::Mat bgr;
            const auto t0 = Clock::now();
            if (job->mode == Job::Mode::fused) {
                const std::string key = job->pass_key + "|" + r->name();
                auto it = std::find_if(sc.fused_passes.begin(), sc.fused_passes.end(), [&](const auto& p) { return p.key == key; });
                if (it == sc.fused_passes.end()) {
                    sc.fused_passes.push_front({key, render_fused_passes(*r, sc.mesh, K, T, ro)});
                    if (sc.fused_passes.size() > 2) sc.fused_passes.pop_back();
                } else {
                    sc.fused_passes.splice(sc.fused_passes.begin(), sc.fused_passes, it);
                    std::lock_guard lk(mu_);
                    ++fused_passes_reused_;
                }
                bgr = composite_fused(sc.fused_passes.front().passes, sc.mesh, sc.mapping, sc.texture_bgra, job->surface_opacity, 3.0);
            } else {
                render_in_bands(*r, K, T, ro, img, *job);
                sc.last_depth_mm = std::move(img.depth_mm);
                sc.last_view_key = job->view_key;
                sc.last_backend = r->name();
            }
            RenderedImage out;
            out.render_ms = ms_since(t0);
            const auto t1 = Clock::now();
            if (job->mode != Job::Mode::fused) cv::cvtColor(cv::Mat(K.height, K.width, CV_8UC3, img.rgb.data()), bgr, cv::COLOR_RGB2BGR);
            std::vector<uchar> buf;
            if (job->format == "png") {
                cv::imencode(".png", bgr, buf);
                out.mime = "image/png";
            } else {
                cv::imencode(".jpg", bgr, buf, {cv::IMWRITE_JPEG_QUALITY, job->quality});
                out.mime = "image/jpeg";
            }
            out.bytes.assign(buf.begin(), buf.end());
            out.encode_ms = ms_since(t1);
            out.width = K.width;
            out.height = K.height;
            out.backend = r->name();
            {
                std::lock_guard lk(mu_);
                ++renders_;
                last_render_ms_ = out.render_ms;
            }
            job->result.set_value(std::move(out));
        } catch (...) {
            bool superseded = false;  // given up for a newer view: counted apart, not a failure
            std::exception_ptr err = std::current_exception();
            try {
                throw;
            } catch (const ApiError& e) {
                superseded = e.code == "superseded";
            } catch (const GlError& e) {
                sc.drop_gl_renderers();
                const std::string what = std::string("render: the GL renderer failed (") + e.what() +
                                         "); the next request makes a new renderer";
                log(LogLevel::error, "render", what);
                {
                    std::lock_guard lk(mu_);
                    backend_reason_ = what;
                    ++gl_failures_;
                }
                err = std::make_exception_ptr(ApiError(503, "unavailable", what));
            } catch (...) {
            }
            if (!superseded) {
                std::lock_guard lk(mu_);
                ++failures_;
            }
            if (job->mode == Job::Mode::pick) job->pick_result.set_exception(err);
            else job->result.set_exception(err);
        }
    }
    std::lock_guard lk(mu_);
    thread_done_ = true;
    state_ = "stopped";
}

nlohmann::json RenderModule::volume_json() const {
    std::lock_guard lk(mu_);
    if (state_ == "failed" && volume_info_.is_null()) throw ApiError(503, "unavailable", "render: the volume could not be loaded: " + error_);
    if (volume_info_.is_null()) throw ApiError(503, "unavailable", "render: the volume is still loading (state " + state_ + "); try again");
    nlohmann::json j = volume_info_;
    j["file"] = fs_name(cfg_.t1_path);
    j["frame"] = "LPS mm (DICOM patient: +x left, +y posterior, +z superior)";
    j["default_view"] = {{"distance_mm", 450}, {"focal_px", "0.5 * width * distance_mm / 110"}, {"target", "center_lps_mm"}};
    return j;
}

nlohmann::json RenderModule::status_json() const {
    std::lock_guard lk(mu_);
    nlohmann::json j{{"state", state_},
                     {"requested", cfg_.renderer},
                     {"backend", backend_.empty() ? nlohmann::json(nullptr) : nlohmann::json(backend_)},
                     {"backend_reason", backend_reason_.empty() ? "chosen on the first render" : backend_reason_},
                     {"renders", renders_},
                     {"failures", failures_},
                     {"last_render_ms", last_render_ms_},
                     {"case_preparations", case_preparations_},
                     {"fusion_volume_uploads", fusion_uploads_},
                     {"banded_renders", banded_},
                     {"superseded", superseded_},
                     {"superseded_in_flight", superseded_in_flight_},
                     {"fused_passes_reused", fused_passes_reused_},
                     {"gl_failures", gl_failures_},
                     {"queued", queue_.size()}};
    if (!error_.empty()) j["error"] = error_;
    return j;
}

std::uint64_t RenderModule::fusion_volume_uploads() const {
    std::lock_guard lk(mu_);
    return fusion_uploads_;
}
std::uint64_t RenderModule::case_preparations() const {
    std::lock_guard lk(mu_);
    return case_preparations_;
}

bool RenderModule::healthy() const {
    std::lock_guard lk(mu_);
    return thread_.joinable() && !thread_done_;
}

}  // namespace cf::daemon
