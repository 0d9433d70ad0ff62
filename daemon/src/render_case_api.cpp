// POST /api/render/pick, POST /api/cases/{id}/fused, GET /api/cases/{id}/fused/camera and
// GET /api/jobs/{id}/download (docs/api/render.md, docs/api/jobs.md).
#include <fstream>

#include "case_api.hpp"
#include "case_jobs.hpp"
#include "case_volumes.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/daemon/endpoints.hpp"

namespace cf::daemon {

namespace fs = std::filesystem;
using nlohmann::json;
using namespace cf::db;

namespace {

/// What a fused view of a case is made of: the registration (a succeeded one with a pose), its
/// photo and ROI, the plan's surface, the case's T1 and brain mask.
struct FusedParts {
    RegistrationRecord reg;
    PhotoRecord photo;
    std::optional<RoiRecord> roi;
    ResultRecord surface;
    VolumeRecord t1;
    std::optional<VolumeRecord> mask_volume;
    std::optional<ResultRecord> plan_mask;
    Pose T;
};

FusedParts fused_parts(CaseStore& st, std::int64_t case_id, std::optional<std::int64_t> registration_id) {
    const CaseRecord rec = st.get_case(case_id);
    const std::string c = "fused case " + std::to_string(case_id);
    FusedParts f;
    const RegisteredView v = registered_view(rec, registration_id, c, "run a register job first", "run a plan job first");
    f.reg = v.reg;
    f.photo = v.photo;
    f.T = v.T_camera_from_world;
    f.surface = v.surface;
    if (f.reg.roi_id) {
        for (const auto& r : st.roi_history(case_id))
            if (r.id == *f.reg.roi_id) f.roi = r;
    } else {
        f.roi = rec.roi;
    }
    bool t1 = false;
    for (const auto& r : rec.results)
        if (r.kind == "plan_brain_mask" && (!f.plan_mask || r.id > f.plan_mask->id)) f.plan_mask = r;
    for (const auto& vol : rec.volumes) {
        if (vol.modality == Modality::T1 && (f.reg.volume_id ? vol.id == *f.reg.volume_id : (!t1 || vol.id > f.t1.id))) {
            f.t1 = vol;
            t1 = true;
        }
        if (vol.modality == Modality::mask && (!f.mask_volume || vol.id > f.mask_volume->id)) f.mask_volume = vol;
    }
    if (!t1) throw ApiError(409, "conflict", c + ": no T1 volume");
    return f;
}

std::optional<std::int64_t> optional_id(const json& body, const Request& r, const char* key, const std::string& what) {
    if (body.is_object() && body.contains(key)) {
        if (!body[key].is_number_integer() || body[key].get<std::int64_t>() < 1) throw ApiError(400, "bad_request", what + " " + key + ": must be a positive integer");
        return body[key].get<std::int64_t>();
    }
    if (auto it = r.params.find(key); it != r.params.end()) {
        try {
            std::size_t n = 0;
            const long long v = std::stoll(it->second, &n);
            if (n == it->second.size() && v >= 1) return v;
        } catch (const std::exception&) {
        }
        throw ApiError(400, "bad_request", what + " " + key + ": '" + it->second + "' is not a positive integer");
    }
    return std::nullopt;
}

/// The photo's intrinsics fitted into the renderer's limits (aspect kept): the view's default size.
std::pair<int, int> fitted_size(const json& K, int max_w, int max_h) {
    const int w = K.value("width", 640), h = K.value("height", 480);
    const double s = std::min({1.0, double(max_w) / w, double(max_h) / h});
    return {std::max(16, int(std::lround(w * s))), std::max(16, int(std::lround(h * s)))};
}

/// A render source for a case volume, loaded through the shared cache.
std::shared_ptr<const CaseRenderSource> render_source(const std::shared_ptr<CaseVolumeCache>& cache, const CaseVolumeRef& ref) {
    auto src = std::make_shared<CaseRenderSource>();
    src->key = ref.key();
    src->source = "case " + std::to_string(ref.case_id) + " " + ref.source;
    src->load = [cache, ref] { return cache->get(ref); };
    return src;
}

/// The layers `body["modalities"]` names (when it is a list; the render module checks the rest
/// of each entry and refuses any other shape): `t1` is `t1_src`, `ct` / `fmri` the newest plan's
/// volume on the T1's grid. 400 naming `modalities[i].name` for a missing or unknown name, 409
/// naming the modality when the case has no plan with it.
std::vector<ModalityLayerSource> modality_layers(CaseStore& st, const std::shared_ptr<CaseVolumeCache>& cache, std::int64_t case_id,
                                                 const std::shared_ptr<const CaseRenderSource>& t1_src, const json& body, const std::string& what) {
    std::vector<ModalityLayerSource> out;
    if (!body.is_object() || !body.contains("modalities") || !body["modalities"].is_array()) return out;
    const json& m = body["modalities"];
    for (std::size_t i = 0; i < m.size(); ++i) {
        const std::string f = what + " modalities[" + std::to_string(i) + "].name";
        if (!m[i].is_object() || !m[i].contains("name") || !m[i]["name"].is_string())
            throw ApiError(400, "bad_request", f + ": missing (t1, ct or fmri)");
        const std::string name = m[i]["name"].get<std::string>();
        if (name == "t1") out.push_back({name, t1_src});
        else if (name == "ct" || name == "fmri") out.push_back({name, render_source(cache, resolve_plan_volume(st, case_id, name, f))});
        else throw ApiError(400, "bad_request", f + ": unknown modality '" + name.substr(0, 40) + "' (t1, ct or fmri)");
    }
    return out;
}

/// The case part of a render or pick request: `case_id` (and `volume_id`) name the case's
/// volume, `modalities` the layers of a multimodal view. Both are taken out of `body` (the
/// render module reads the rest); `modalities` stays for the module to read each layer's look.
struct CaseView {
    std::shared_ptr<const CaseRenderSource> src;
    std::vector<ModalityLayerSource> layers;
};
CaseView case_view(CaseStore& st, const std::shared_ptr<CaseVolumeCache>& cache, json& body, const std::string& what) {
    CaseView v;
    if (!body.is_object()) return v;
    std::optional<std::int64_t> case_id, volume_id;
    for (const char* k : {"case_id", "volume_id"})
        if (body.contains(k)) {
            if (!body[k].is_number_integer() || body[k].get<std::int64_t>() < 1) throw ApiError(400, "bad_request", what + " " + k + ": must be a positive integer");
            (std::string(k) == "case_id" ? case_id : volume_id) = body[k].get<std::int64_t>();
            body.erase(k);
        }
    if (volume_id && !case_id) throw ApiError(400, "bad_request", what + " volume_id: given without case_id");
    if (body.contains("modalities") && !case_id)
        throw ApiError(400, "bad_request", what + " modalities: need case_id (the layers are the case's T1 and its plan's CT/fMRI)");
    if (!case_id) return v;
    const CaseVolumeRef t1 = resolve_case_volume(st, *case_id, volume_id, what);
    v.src = render_source(cache, t1);
    v.layers = modality_layers(st, cache, *case_id, v.src, body, what);
    return v;
}

/// Voxel counts over `bins` equal bins of normalized intensity x = (v - lo) / (hi - lo) in
/// [0, 1] (x = 1 in the last bin), split by the mask (inside / outside; all outside without
/// one), and those below 0 or above 1.
json histogram_json(const Volume& v, const LabelVolume* mask, std::array<double, 2> range, int bins) {
    std::vector<std::uint64_t> in(std::size_t(bins), 0), out(std::size_t(bins), 0);
    std::uint64_t below_in = 0, below_out = 0, above_in = 0, above_out = 0;
    const double lo = range[0], span = range[1] - range[0];
    for (std::size_t i = 0; i < v.voxels.size(); ++i) {
        const bool inside = mask && mask->voxels[i];
        const double x = span > 0 ? (double(v.voxels[i]) - lo) / span : 0.0;
        if (x < 0) ++(inside ? below_in : below_out);
        else if (x > 1) ++(inside ? above_in : above_out);
        else (inside ? in : out)[std::min<std::size_t>(std::size_t(bins) - 1, std::size_t(x * bins))]++;
    }
    json j{{"range", {range[0], range[1]}}, {"outside", out}, {"below_outside", below_out}, {"above_outside", above_out}};
    if (mask) {
        j["inside"] = in;
        j["below_inside"] = below_in;
        j["above_inside"] = above_in;
    }
    return j;
}

Response image_response(RenderedImage img, const std::string& source) {
    Response resp = Response::binary(std::move(img.bytes), img.mime);
    resp.headers["X-Render-Ms"] = std::to_string(img.render_ms);
    resp.headers["X-Renderer"] = img.backend;
    resp.headers["X-Image-Size"] = std::to_string(img.width) + "x" + std::to_string(img.height);
    if (!source.empty()) resp.headers["X-Render-Volume"] = source;
    return resp;
}

}  // namespace

void register_render_case_endpoints(EndpointRegistry& reg, RenderModule& render, CaseStore& store, JobQueue& jobs, const fs::path& work_dir) {
    RenderModule* rm = &render;
    CaseStore* st = &store;
    JobQueue* jq = &jobs;
    // Loaded case volumes (float voxels and brain mask, ~80 MiB for a 256^3 T1), shared by
    // per-case renders (loaded once per prepared renderer) and the histograms.
    auto cache = std::make_shared<CaseVolumeCache>(store, work_dir / "case_volumes", 3);

    reg.add({"POST", "/api/render", "render", Access::read,
             "Render a view off-screen (the daemon's MRI, or case_id's volume; modalities for a multimodal view); answers image/jpeg or image/png",
             [rm, st, cache](const Request& r) {
                 return guarded([&] {
                     json body = r.body.is_null() ? json::object() : r.body;
                     CaseView v = case_view(*st, cache, body, "render");
                     RenderedImage img = rm->render(body, v.src, v.layers);
                     return image_response(std::move(img), v.src ? v.src->source : std::string());
                 });
             }});

    reg.add({"GET", "/api/render/volume", "render.volume", Access::read,
             "The rendered MRI's centre and extent (LPS mm) and its brain's box, for placing a camera (?case_id=&volume_id=: the case's volume)",
             [rm, st, cache](const Request& r) {
                 return guarded([&] {
                     if (!r.params.count("case_id")) {
                         if (r.params.count("volume_id")) throw ApiError(400, "bad_request", "render volume volume_id: given without case_id");
                         return ok(rm->volume_json());
                     }
                     const std::int64_t id = case_id_param(r, "case_id");
                     std::optional<std::int64_t> vid;
                     if (r.params.count("volume_id")) vid = case_id_param(r, "volume_id");
                     const auto vol = cache->get(resolve_case_volume(*st, id, vid, "render volume"));
                     json j = volume_geometry_json(vol->volume, vol->brain_mask ? &*vol->brain_mask : nullptr);
                     j["file"] = vol->ref.volume_name;
                     j["case_id"] = id;
                     j["volume_id"] = vol->ref.volume_id;
                     return ok(j);
                 });
             }});

    // The histogram answer of a loaded volume (a stored volume, or a plan volume on the T1 grid).
    auto histogram = [](const Request& r, const LoadedCaseVolume& vol) {
        int bins = 256;
        if (auto it = r.params.find("bins"); it != r.params.end()) {
            std::size_t n = 0;
            long long b = -1;
            try {
                b = std::stoll(it->second, &n);
            } catch (const std::exception&) {
                n = 0;
            }
            if (n != it->second.size() || b < 8 || b > 1024)
                throw ApiError(400, "bad_request", "histogram bins: '" + it->second.substr(0, 20) + "' must be an integer 8..1024");
            bins = int(b);
        }
        const LabelVolume* m = vol.brain_mask ? &*vol.brain_mask : nullptr;
        json norm{{"whole", histogram_json(vol.volume, m, robust_range(vol.volume, nullptr), bins)}};
        norm["brain_only"] = m ? histogram_json(vol.volume, m, robust_range(vol.volume, m), bins) : json(nullptr);
        return json{{"case_id", vol.ref.case_id},
                    {"modality", vol.ref.modality},
                    {"source", vol.ref.source},
                    {"bins", bins},
                    {"voxels", vol.volume.voxels.size()},
                    {"brain_mask", vol.ref.mask_source.empty() ? json(nullptr) : json(vol.ref.mask_source)},
                    {"x", "normalized transfer-function units: bin b holds (intensity - range[0]) / (range[1] - range[0]) in [b, b + 1) / bins"},
                    {"normalizations", norm}};
    };
    reg.add({"GET", "/api/cases/{id}/volumes/{volume_id}/histogram", "cases.volume_histogram", Access::read,
             "Intensity histogram of a case volume in the transfer functions' normalized units (?bins=8..1024), inside and outside its brain mask",
             [st, cache, histogram](const Request& r) {
                 return guarded([&] {
                     const std::int64_t id = case_id_param(r);
                     const std::int64_t vid = case_id_param(r, "volume_id");
                     json j = histogram(r, *cache->get(resolve_case_volume(*st, id, vid, "histogram")));
                     j["volume_id"] = vid;
                     return ok(j);
                 });
             }});
    reg.add({"GET", "/api/cases/{id}/plan/{modality}/histogram", "cases.plan_histogram", Access::read,
             "Intensity histogram of the newest plan's CT or fMRI on the T1 grid (modality ct | fmri; ?bins=8..1024), as the volume histogram",
             [st, cache, histogram](const Request& r) {
                 return guarded([&] {
                     const std::int64_t id = case_id_param(r);
                     const auto it = r.params.find("modality");
                     const std::string mod = it == r.params.end() ? std::string() : it->second;
                     if (mod != "ct" && mod != "fmri") throw ApiError(400, "bad_request", "plan histogram modality: '" + mod.substr(0, 40) + "' must be ct or fmri");
                     const CaseVolumeRef ref = resolve_plan_volume(*st, id, mod, "plan histogram " + mod);
                     json j = histogram(r, *cache->get(ref));
                     j["result_id"] = ref.volume_id;
                     return ok(j);
                 });
             }});

    reg.add({"POST", "/api/render/pick", "render.pick", Access::read,
             "The world point (LPS mm) under a pixel of a rendered view: the POST /api/render fields plus pixel [u, v]; 422 when no surface is there",
             [rm, st, cache](const Request& r) {
                 if (r.body.is_null()) throw ApiError(400, "bad_request", "render pick: the request must be a JSON object with pixel [u, v]");
                 return guarded([&] {
                     json body = r.body;
                     // The shown view's request may hold its modalities (checked): the pick is on the case's T1 surface.
                     CaseView v = case_view(*st, cache, body, "render pick");
                     if (body.is_object()) body.erase("modalities");
                     json a = rm->pick(body, v.src);
                     if (v.src) a["volume"] = v.src->source;
                     return ok(a);
                 });
             }});

    reg.add({"GET", "/api/cases/{id}/fused/camera", "cases.fused_camera", Access::read,
             "The registered camera of the case's fused view (pose and the photo's intrinsics), to snap the view back to it (?registration_id=)",
             [st](const Request& r) {
                 return guarded([&] {
                     const std::int64_t id = case_id_param(r);
                     const FusedParts f = fused_parts(*st, id, optional_id(json(), r, "registration_id", "fused camera"));
                     return ok({{"case_id", id},
                                {"registration_id", f.reg.id},
                                {"photo_id", f.photo.id},
                                {"T_camera_from_world", pose_to_json(f.T)},
                                {"camera", f.photo.intrinsics},
                                {"width", f.photo.intrinsics.value("width", 0)},
                                {"height", f.photo.intrinsics.value("height", 0)}});
                 });
             }});

    reg.add({"POST", "/api/cases/{id}/fused", "cases.fused", Access::read,
             "The case's photo-textured brain surface (plan + registration + photo + ROI) over its volume rendering (multimodal with modalities); the POST /api/render fields plus surface_opacity, registration_id, modalities",
             [rm, st, work_dir, cache](const Request& r) {
                 return guarded([&] {
                     const std::int64_t id = case_id_param(r);
                     json body = r.body.is_null() ? json::object() : r.body;
                     if (!body.is_object()) throw ApiError(400, "bad_request", "fused: the request must be a JSON object");
                     const FusedParts f = fused_parts(*st, id, optional_id(body, r, "registration_id", "fused"));
                     body.erase("registration_id");
                     // Defaults: the registered camera (pose, and the photo's intrinsics at the photo's size within the limits).
                     if (!body.contains("T_camera_from_world")) body["T_camera_from_world"] = pose_to_json(f.T);
                     const auto [w, h] = fitted_size(f.photo.intrinsics, rm->max_width(), rm->max_height());
                     if (!body.contains("width") && !body.contains("height")) {
                         body["width"] = w;
                         body["height"] = h;
                     }
                     if (!body.contains("camera") && !body.contains("focal_px")) body["camera"] = f.photo.intrinsics;
                     auto src = std::make_shared<FusedSource>();
                     src->volume = render_source(cache, resolve_case_volume(*st, id, f.t1.id, "fused"));
                     // `modalities`: the volume pass is the T1 with the plan's CT / fMRI (GL only).
                     std::vector<ModalityLayerSource> layers = modality_layers(*st, cache, id, src->volume, body, "fused");
                     const std::string surf_sha = f.surface.blob.sha256, photo_sha = f.photo.blob.sha256;
                     src->surface_key = surf_sha;
                     src->surface_ply_bytes = [st, surf_sha] { return st->read_blob(surf_sha); };
                     src->photo_bytes = [st, photo_sha] { return st->read_blob(photo_sha); };
                     src->photo_intrinsics = f.photo.intrinsics;
                     if (f.roi) src->roi = f.roi->roi;
                     src->T_registered = f.T;
                     src->texture_key = photo_sha + "/" + surf_sha + "/" + (f.roi ? std::to_string(f.roi->id) : "-") + "/" +
                                        std::to_string(f.reg.id);
                     src->scratch_dir = (work_dir / ("fused_" + std::to_string(id))).string();
                     const std::string source = src->volume->source;
                     RenderedImage img = rm->fused(body, src, std::move(layers));
                     Response resp = image_response(std::move(img), source);
                     resp.headers["X-Registration-Id"] = std::to_string(f.reg.id);
                     return resp;
                 });
             }});

    reg.add({"GET", "/api/jobs/{id}/download", "jobs.download", Access::read, "The file a succeeded export job wrote (the case zip)",
             [jq, work_dir](const Request& r) {
                 const std::int64_t id = case_id_param(r);
                 const auto j = jq->get(std::uint64_t(id));
                 if (!j) throw ApiError(404, "not_found", "job " + std::to_string(id) + ": no such job");
                 if (j->kind != "export") throw ApiError(409, "conflict", "job " + std::to_string(id) + ": a " + j->kind + " job has no file to download");
                 if (j->state != JobInfo::State::succeeded)
                     throw ApiError(409, "conflict", "job " + std::to_string(id) + ": it is " + state_name(j->state) + ", not succeeded");
                 const fs::path p = work_dir / "exports" / j->result.value("file", std::string());
                 std::ifstream in(p, std::ios::binary);
                 if (!in) throw ApiError(410, "gone", "job " + std::to_string(id) + ": its file is gone (exports are kept until the daemon restarts)");
                 std::string bytes((std::istreambuf_iterator<char>(in)), {});
                 Response resp = Response::binary(std::move(bytes), "application/zip");
                 resp.headers["Content-Disposition"] = "attachment; filename=\"" + j->result.value("file", std::string("case.zip")) + "\"";
                 return resp;
             }});
}

}  // namespace cf::daemon
