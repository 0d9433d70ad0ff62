// The landmarks' initial alignment (landmark_pose_api.hpp, docs/api/case-data.md).
#include "landmark_pose_api.hpp"

#include <cmath>
#include <string>
#include <vector>

#include "case_api.hpp"
#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/landmarks.hpp"

namespace cf::daemon {

using nlohmann::json;
using namespace cf::db;

namespace {

ApiError bad(const std::string& what, const std::string& problem) { return ApiError(400, "bad_request", what + ": " + problem); }

const PhotoRecord& photo_by_id(const CaseRecord& rec, std::int64_t pid, const std::string& what) {
    for (const auto& p : rec.photos)
        if (p.id == pid) return p;
    throw ApiError(404, "not_found", what + " photo_id " + std::to_string(pid) + ": no such photo in case " + std::to_string(rec.summary.id));
}

/// The pose the register job starts from for these pairs, and each pair's reprojection error.
/// Checked first as a saved set is (core's validate_landmarks: >= 4 pairs, inside the photo,
/// neither set collinear); an InputError of the fit (no pose in front of the camera) is a 400 too.
json initial_alignment(const std::vector<Landmark>& lms, const PhotoRecord& photo, const std::string& what) {
    const Intrinsics K = parse_camera(json{{"camera", photo.intrinsics}}, "photo " + std::to_string(photo.id) + " camera");
    LandmarkFit fit;
    try {
        validate_landmarks(lms, K, what);
        // Registration::run without an initial pose: T0 = pnp_candidates(landmarks, K).front().
        fit = pnp_candidates(lms, K).front();
    } catch (const InputError& e) {
        throw ApiError(400, "bad_request", e.what());
    }
    json pairs = json::array();
    double sum_sq_px = 0, worst_px = 0;
    for (const auto& l : lms) {
        const auto p = project(K, fit.T_camera_from_world, l.world_mm);
        json x{{"label", l.label}, {"world_mm", {l.world_mm.x(), l.world_mm.y(), l.world_mm.z()}}, {"pixel", {l.pixel.x(), l.pixel.y()}}};
        if (p) {
            const double e = (*p - l.pixel).norm();
            x["projected_pixel"] = {p->x(), p->y()};
            x["error_px"] = e;
            sum_sq_px += e * e;
            worst_px = std::max(worst_px, e);
        } else {  // behind the camera: cannot be for a fit that passed in_front(), kept honest anyway
            x["projected_pixel"] = nullptr;
            x["error_px"] = nullptr;
            sum_sq_px += 1e8;
        }
        pairs.push_back(std::move(x));
    }
    json inl = json::array();
    for (int i : fit.inliers) inl.push_back(i);
    const LandmarkSpread spread = landmark_spread(lms);
    return {{"photo_id", photo.id},
            {"spread", {{"world", spread.world}, {"pixel", spread.pixel}}},
            {"warning", landmark_spread_warning(spread)},
            {"method", fit.method},
            {"T_camera_from_world", pose_to_json(fit.T_camera_from_world)},
            {"rms_px", std::sqrt(sum_sq_px / double(lms.size()))},
            {"max_error_px", worst_px},
            {"inliers", inl},
            {"pairs", pairs},
            {"camera", {{"width", K.width}, {"height", K.height}}}};
}

}  // namespace

void register_landmark_pose_endpoints(EndpointRegistry& reg, CaseStore& store) {
    CaseStore* st = &store;
    reg.add({"GET", "/api/cases/{id}/landmarks/initial-pose", "cases.landmark_pose", Access::read,
             "The initial alignment from the newest landmark set: the pose the register job starts from, each pair's reprojection error (px) and the RMS",
             on_own_stack([st](const Request& r) {
                 const auto id = case_id_param(r);
                 const std::string what = "case " + std::to_string(id) + " landmarks";
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);  // NotFound (404) for an unknown case
                     if (!rec.landmarks) throw ApiError(404, "not_found", what + ": no landmarks yet (save at least 4 pairs first)");
                     const LandmarkSet& s = *rec.landmarks;
                     if (!s.photo_id && rec.photos.empty()) throw ApiError(409, "conflict", what + ": case " + std::to_string(id) + " has no photo");
                     const PhotoRecord& photo = s.photo_id ? photo_by_id(rec, *s.photo_id, what) : rec.photos.back();
                     std::vector<Landmark> lms;
                     for (const auto& p : s.points)
                         lms.push_back({p.name, {p.world_mm[0], p.world_mm[1], p.world_mm[2]}, {p.pixel[0], p.pixel[1]}});
                     json out = initial_alignment(lms, photo, what);
                     out["case_id"] = id;
                     out["landmark_set_id"] = s.id;
                     out["revision"] = s.revision;
                     return ok(out);
                 });
             })});
    reg.add({"POST", "/api/cases/{id}/landmarks/initial-pose", "cases.preview_landmark_pose", Access::read,
             "The initial alignment of unsaved pairs {landmarks: [{label, world_mm, pixel}], photo_id?}: checked as a save, nothing stored",
             on_own_stack([st](const Request& r) {
                 const auto id = case_id_param(r);
                 const std::string what = "case " + std::to_string(id) + " landmarks";
                 if (!r.body.is_object()) throw bad(what, "body must be a JSON object {landmarks: [...], photo_id?}");
                 for (auto it = r.body.begin(); it != r.body.end(); ++it)
                     if (it.key() != "landmarks" && it.key() != "photo_id" && it.key() != "id") throw bad(what + " " + it.key(), "unknown field");
                 if (!r.body.contains("landmarks") || !r.body["landmarks"].is_array()) throw bad(what, "\"landmarks\" must be an array of {label, world_mm, pixel}");
                 if (r.body["landmarks"].size() > 1000) throw bad(what, "more than 1000 landmarks");
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     const PhotoRecord* photo = nullptr;
                     if (r.body.contains("photo_id") && !r.body["photo_id"].is_null()) {
                         if (!r.body["photo_id"].is_number_integer()) throw bad(what + " photo_id", "must be an integer");
                         photo = &photo_by_id(rec, r.body["photo_id"].get<std::int64_t>(), what);
                     } else {
                         if (rec.photos.empty()) throw ApiError(409, "conflict", what + ": case " + std::to_string(id) + " has no photo yet (upload one first)");
                         photo = &rec.photos.back();
                     }
                     std::vector<Landmark> lms;
                     try {
                         lms = parse_landmarks(r.body, what);
                     } catch (const InputError& e) {
                         throw ApiError(400, "bad_request", e.what());
                     }
                     json out = initial_alignment(lms, *photo, what);
                     out["case_id"] = id;
                     return ok(out);
                 });
             })});
}

}  // namespace cf::daemon
