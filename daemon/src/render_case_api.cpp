// POST /api/render/pick, POST /api/cases/{id}/fused, GET /api/cases/{id}/fused/camera and
// GET /api/jobs/{id}/download (docs/api/render.md, docs/api/jobs.md).
#include <fstream>

#include "case_api.hpp"
#include "case_jobs.hpp"
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
    bool found = false;
    for (const auto& r : rec.registrations) {
        if (registration_id ? r.id != *registration_id : (r.status != RegistrationStatus::succeeded || !r.final_pose)) continue;
        f.reg = r;
        found = true;  // oldest first: the last match is the newest
    }
    if (!found) {
        if (registration_id)
            throw ApiError(404, "not_found", c + " registration_id: case has no registration " + std::to_string(*registration_id));
        throw ApiError(409, "conflict", c + ": no successful registration yet (run a register job first)");
    }
    if (f.reg.status != RegistrationStatus::succeeded || !f.reg.final_pose)
        throw ApiError(409, "conflict", c + " registration " + std::to_string(f.reg.id) + ": it did not succeed (" + to_string(f.reg.status) + ")");
    try {
        // Stored as {"T_camera_from_world": 4x4} (the register job) or as the 4x4 itself.
        const json& fp = *f.reg.final_pose;
        f.T = parse_pose(fp.is_array() ? json{{"T_camera_from_world", fp}} : fp, c + " registration pose");
    } catch (const InputError& e) {
        throw ApiError(500, "internal", e.what());
    }
    bool photo = false;
    for (const auto& p : rec.photos)
        if (f.reg.photo_id ? p.id == *f.reg.photo_id : (!photo || p.id > f.photo.id)) {
            f.photo = p;
            photo = true;
        }
    if (!photo) throw ApiError(409, "conflict", c + ": the registration's photo is not in the case");
    if (f.reg.roi_id) {
        for (const auto& r : st.roi_history(case_id))
            if (r.id == *f.reg.roi_id) f.roi = r;
    } else {
        f.roi = rec.roi;
    }
    bool surface = false, t1 = false;
    for (const auto& r : rec.results) {
        if (r.kind == "plan_brain_surface" && (!surface || r.id > f.surface.id)) {
            f.surface = r;
            surface = true;
        }
        if (r.kind == "plan_brain_mask" && (!f.plan_mask || r.id > f.plan_mask->id)) f.plan_mask = r;
    }
    if (!surface) throw ApiError(409, "conflict", c + ": no brain surface yet (run a plan job first)");
    for (const auto& v : rec.volumes) {
        if (v.modality == Modality::T1 && (f.reg.volume_id ? v.id == *f.reg.volume_id : (!t1 || v.id > f.t1.id))) {
            f.t1 = v;
            t1 = true;
        }
        if (v.modality == Modality::mask && (!f.mask_volume || v.id > f.mask_volume->id)) f.mask_volume = v;
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

}  // namespace

void register_render_case_endpoints(EndpointRegistry& reg, RenderModule& render, CaseStore& store, JobQueue& jobs, const fs::path& work_dir) {
    RenderModule* rm = &render;
    CaseStore* st = &store;
    JobQueue* jq = &jobs;

    reg.add({"POST", "/api/render/pick", "render.pick", Access::read,
             "The world point (LPS mm) under a pixel of a rendered view: the POST /api/render fields plus pixel [u, v]; 422 when no surface is there",
             [rm](const Request& r) {
                 if (r.body.is_null()) throw ApiError(400, "bad_request", "render pick: the request must be a JSON object with pixel [u, v]");
                 return ok(rm->pick(r.body));
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
             "The case's photo-textured brain surface (plan + registration + photo + ROI) over its volume rendering; the POST /api/render fields plus surface_opacity, registration_id",
             [rm, st, work_dir](const Request& r) {
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
                     src->volume_key = f.t1.blob.sha256;
                     src->volume_name = f.t1.original_name;
                     const std::string t1_sha = f.t1.blob.sha256;
                     src->volume_bytes = [st, t1_sha] { return st->read_blob(t1_sha); };
                     if (f.mask_volume || f.plan_mask) {
                         const std::string sha = f.mask_volume ? f.mask_volume->blob.sha256 : f.plan_mask->blob.sha256;
                         src->mask_key = sha;
                         src->mask_name = f.mask_volume ? "mask_" + f.mask_volume->original_name : std::string("brain_mask.nii.gz");
                         src->mask_bytes = [st, sha] { return st->read_blob(sha); };
                     }
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
                     RenderedImage img = rm->fused(body, src);
                     Response resp = Response::binary(std::move(img.bytes), img.mime);
                     resp.headers["X-Render-Ms"] = std::to_string(img.render_ms);
                     resp.headers["X-Renderer"] = img.backend;
                     resp.headers["X-Image-Size"] = std::to_string(img.width) + "x" + std::to_string(img.height);
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
