// The data of a case over HTTP (docs/api/case-data.md): volume and photo uploads (validated by
// reading them with core's readers before anything is stored), landmarks and ROI (core's
// parsers and validators against the photo's camera), registrations and result downloads, and a
// case as a zip (export, import). Every change is one CaseStore call (one transaction with its
// audit entry); downloads are audited here.
#include <unistd.h>

#include <atomic>
#include <climits>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <optional>
#include <regex>
#include <thread>
#include <sstream>

#include "case_api.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/volume.hpp"
#include "scratch_dir.hpp"

namespace cf::daemon {

namespace fs = std::filesystem;
using nlohmann::json;
using namespace cf::db;

namespace {

/// A raw-body upload endpoint: the body up to `max_upload_bytes` (store.max_upload_bytes), the
/// handler on a full stack (it reads the file with ITK, OpenCV or libzip before storing it).
void add_upload(EndpointRegistry& reg, Endpoint e, std::int64_t max_upload_bytes) {
    e.handler = on_own_stack(std::move(e.handler));
    e.raw_body = true;
    e.max_body_bytes = max_upload_bytes;
    reg.add(std::move(e));
}

/// A file download: its bytes, with a Content-Disposition naming it.
Response attachment(std::string bytes, const std::string& mime, const std::string& filename) {
    Response resp = Response::binary(std::move(bytes), mime);
    resp.headers["Content-Disposition"] = "attachment; filename=\"" + filename + "\"";
    return resp;
}

ApiError bad(const std::string& what, const std::string& problem) { return ApiError(400, "bad_request", what + ": " + problem); }

/// A query parameter (HTTP) or a params field (RPC: strings and integers land in params too).
std::optional<std::string> query(const Request& r, const char* key) {
    const auto it = r.params.find(key);
    if (it == r.params.end()) return std::nullopt;
    return it->second;
}

/// An uploaded file's name: one plain name (no folder, no '..', no leading dot) of letters,
/// digits, '_', '-', '.', ending in one of `exts`. Checked before anything is written, so a
/// name can never place a file outside the scratch folder.
std::string upload_name(const Request& r, const std::string& what, const std::vector<std::string>& exts, const std::string& def) {
    const std::string name = query(r, "name").value_or(def);
    static const std::regex re("[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}");
    if (!std::regex_match(name, re) || name.find("..") != std::string::npos)
        throw bad(what + " name '" + name.substr(0, 80) + "'",
                  "must be a plain file name of 1..128 letters, digits, '_', '-', '.' (no folders, no '..', no leading dot)");
    std::string lower = name;
    for (auto& c : lower) c = char(std::tolower(static_cast<unsigned char>(c)));
    for (const auto& e : exts)
        if (lower.size() > e.size() && lower.compare(lower.size() - e.size(), e.size(), e) == 0) return name;
    std::string list;
    for (const auto& e : exts) list += (list.empty() ? "" : ", ") + e;
    throw bad(what + " name '" + name + "'", "must end in " + list);
}

std::string read_file(const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    std::ostringstream s;
    s << in.rdbuf();
    if (!in && !in.eof()) throw ApiError(500, "io_error", p.string() + ": cannot read");
    return s.str();
}

json volume_json(const VolumeRecord& v) {
    return {{"id", v.id}, {"modality", to_string(v.modality)}, {"original_name", v.original_name}, {"sha256", v.blob.sha256},
            {"size_bytes", v.blob.size_bytes}, {"created_utc", format_utc(v.created_utc)}};
}
json photo_json(const PhotoRecord& p) {
    return {{"id", p.id}, {"original_name", p.original_name}, {"sha256", p.blob.sha256}, {"size_bytes", p.blob.size_bytes},
            {"intrinsics", p.intrinsics}, {"created_utc", format_utc(p.created_utc)}};
}
json landmarks_json(const LandmarkSet& s) {
    json pts = json::array();
    for (const auto& p : s.points) pts.push_back({{"label", p.name}, {"world_mm", p.world_mm}, {"pixel", p.pixel}});
    return {{"id", s.id}, {"revision", s.revision}, {"photo_id", s.photo_id ? json(*s.photo_id) : json(nullptr)}, {"landmarks", pts},
            {"created_utc", format_utc(s.created_utc)}};
}
json roi_json(const RoiRecord& r) {
    json j = r.roi;
    j["id"] = r.id;
    j["revision"] = r.revision;
    j["photo_id"] = r.photo_id ? json(*r.photo_id) : json(nullptr);
    j["created_utc"] = format_utc(r.created_utc);
    return j;
}
json result_json(const ResultRecord& x) {
    return {{"id", x.id},
            {"kind", x.kind},
            {"name", x.name},
            {"media_type", x.media_type},
            {"registration_id", x.registration_id ? json(*x.registration_id) : json(nullptr)},
            {"sha256", x.blob.sha256},
            {"size_bytes", x.blob.size_bytes},
            {"params", x.params},
            {"created_utc", format_utc(x.created_utc)},
            {"download", "/api/cases/" + std::to_string(x.case_id) + "/results/" + std::to_string(x.id)}};
}
json registration_json(const RegistrationRecord& g) {
    json x{{"id", g.id}, {"status", to_string(g.status)}, {"created_utc", format_utc(g.created_utc)}, {"params", g.params}, {"stages", g.stages}};
    auto opt = [&](const char* k, const auto& v) {
        if (v) x[k] = *v;
        else x[k] = nullptr;
    };
    opt("volume_id", g.volume_id);
    opt("photo_id", g.photo_id);
    opt("landmark_set_id", g.landmark_set_id);
    opt("roi_id", g.roi_id);
    opt("initial_pose", g.initial_pose);
    opt("final_pose", g.final_pose);
    opt("nmi", g.nmi);
    opt("seconds", g.seconds);
    opt("evaluations", g.evaluations);
    opt("error", g.error);
    x["results"] = json::array();
    for (const auto& r : g.results) x["results"].push_back(result_json(r));
    return x;
}

/// The photo landmarks and ROIs are checked against: `photo_id` (a photo of this case) or the
/// newest photo. 409 when the case has none.
const PhotoRecord& photo_for(const CaseRecord& rec, const json& body, const std::string& what) {
    if (body.contains("photo_id") && !body["photo_id"].is_null()) {
        if (!body["photo_id"].is_number_integer()) throw bad(what + " photo_id", "must be an integer");
        const auto pid = body["photo_id"].get<std::int64_t>();
        for (const auto& p : rec.photos)
            if (p.id == pid) return p;
        throw ApiError(404, "not_found", what + " photo_id " + std::to_string(pid) + ": no such photo in case " + std::to_string(rec.summary.id));
    }
    if (rec.photos.empty())
        throw ApiError(409, "conflict", what + ": case " + std::to_string(rec.summary.id) + " has no photo yet (upload one first: its size bounds the pixels)");
    return rec.photos.back();
}

Intrinsics intrinsics_of(const PhotoRecord& p) { return parse_camera(json{{"camera", p.intrinsics}}, "photo " + std::to_string(p.id) + " camera"); }

void only_fields(const json& b, std::initializer_list<const char*> known, const std::string& ctx) {
    if (!b.is_object()) throw bad(ctx, "body must be a JSON object");
    for (auto it = b.begin(); it != b.end(); ++it) {
        bool found = false;
        for (const char* k : known) found = found || it.key() == k;
        if (!found) throw bad(ctx + " " + it.key(), "unknown field");
    }
}

bool is_jpeg(const std::string& b) { return b.size() >= 4 && (unsigned char)b[0] == 0xFF && (unsigned char)b[1] == 0xD8 && (unsigned char)b[2] == 0xFF; }
bool is_png(const std::string& b) { return b.size() >= 8 && b.compare(0, 8, "\x89PNG\r\n\x1a\n") == 0; }

}  // namespace

void register_case_data_endpoints(EndpointRegistry& reg, CaseStore& store, const fs::path& work_dir, std::int64_t max_upload_bytes) {
    CaseStore* st = &store;

    // ---- volumes ----
    Endpoint up_vol{"POST", "/api/cases/{id}/volumes", "cases.upload_volume", Access::write,
                    "Upload a volume (body: the file; query: name=t1.nii.gz, modality=T1|CT|fMRI|mask); read before it is stored",
                    [st, work_dir](const Request& r) {
                        const auto id = case_id_param(r);
                        const std::string name = upload_name(r, "volume", {".nii", ".nii.gz", ".nrrd", ".mha"}, "");
                        const std::string mod_text = query(r, "modality").value_or("T1");
                        const std::string what = "volume " + name;
                        Modality mod;
                        try {
                            mod = modality_from_string(mod_text);
                        } catch (const StoreError& e) {
                            throw bad(what + " modality", e.what());
                        }
                        if (r.raw.empty()) throw bad(what, "the request body is empty (send the file's bytes)");
                        return guarded([&] {
                            st->get_case(id);  // 404 before reading the volume
                            Scratch scratch(work_dir, "upload");
                            const fs::path file = scratch.write(name, r.raw);
                            json geometry;
                            try {
                                // Core's readers (ITK): a file that does not read as a volume is refused here.
                                VolumeGeometry g;
                                if (mod == Modality::mask) {
                                    const LabelVolume m = load_mask(file);
                                    if (m.count_nonzero() == 0) throw InputError(file.filename().string(), "the mask is empty (no non-zero voxel)");
                                    g = m.geom;
                                } else {
                                    g = load_volume(file).geom;
                                }
                                geometry = {{"dims", g.dims}, {"spacing_mm", {g.spacing_mm.x(), g.spacing_mm.y(), g.spacing_mm.z()}}};
                            } catch (const std::exception& e) {
                                throw bad(what, "not a readable volume: " + scratch.strip(e.what()));
                            }
                            const VolumeRecord v = st->import_volume(id, file, mod, actor_of(r.client));
                            json j = volume_json(v);
                            j["geometry"] = geometry;
                            Response resp = ok(j, 201);
                            resp.headers["Location"] = "/api/cases/" + std::to_string(id) + "/volumes/" + std::to_string(v.id);
                            return resp;
                        });
                    }};
    add_upload(reg, std::move(up_vol), max_upload_bytes);
    reg.add({"GET", "/api/cases/{id}/volumes/{volume_id}", "cases.volume", Access::read, "Download a volume of the case (its file as uploaded)",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 const auto vid = case_id_param(r, "volume_id");
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     for (const auto& v : rec.volumes)
                         if (v.id == vid) {
                             Response resp = attachment(st->read_blob(v.blob.sha256), "application/octet-stream", v.original_name);
                             st->audit(actor_of(r.client), "volume.download", id, {{"volume_id", vid}});
                             return resp;
                         }
                     throw ApiError(404, "not_found", "volume " + std::to_string(vid) + ": no such volume in case " + std::to_string(id));
                 });
             }});

    // ---- photos ----
    Endpoint up_photo{"POST", "/api/cases/{id}/photos", "cases.upload_photo", Access::write,
                      "Upload a photo (body: JPEG or PNG; query: name=photo.png, camera={intrinsics JSON}); decoded before it is stored",
                      [st](const Request& r) {
                          const auto id = case_id_param(r);
                          const std::string name = upload_name(r, "photo", {".jpg", ".jpeg", ".png"}, "");
                          const std::string what = "photo " + name;
                          json camera;
                          if (r.body.is_object() && r.body.contains("camera") && r.body["camera"].is_object()) camera = r.body["camera"];
                          else if (auto c = query(r, "camera")) {
                              camera = json::parse(*c, nullptr, false);
                              if (camera.is_discarded()) throw bad(what + " camera", "is not valid JSON");
                          } else {
                              throw bad(what + " camera", "missing (the camera's intrinsics: {width, height, fx, fy, cx, cy, distortion?})");
                          }
                          if (!camera.is_object()) throw bad(what + " camera", "must be a JSON object {width, height, fx, fy, cx, cy, distortion?}");
                          Intrinsics K;
                          try {
                              K = parse_camera(json{{"camera", camera}}, what);
                              K.validate(what + " camera");
                          } catch (const InputError& e) {
                              throw ApiError(400, "bad_request", e.what());
                          }
                          if (r.raw.empty()) throw bad(what, "the request body is empty (send the file's bytes)");
                          if (r.raw.size() > std::size_t(INT_MAX)) throw bad(what, "is larger than 2 GiB (no photo is)");
                          std::string lower = name;
                          for (auto& ch : lower) ch = char(std::tolower(static_cast<unsigned char>(ch)));
                          const bool want_png = lower.size() > 4 && lower.compare(lower.size() - 4, 4, ".png") == 0;
                          if (want_png && !is_png(r.raw)) throw bad(what, "is not a PNG file (its first bytes are not the PNG signature)");
                          if (!want_png && !is_jpeg(r.raw)) throw bad(what, "is not a JPEG file (it does not start with FF D8 FF)");
                          // A JPEG cut short still half-decodes: it must end with its EOI marker.
                          if (!want_png && !(r.raw.size() >= 2 && (unsigned char)r.raw[r.raw.size() - 2] == 0xFF && (unsigned char)r.raw[r.raw.size() - 1] == 0xD9))
                              throw bad(what, "the JPEG is truncated (no end-of-image marker)");
                          cv::Mat img;
                          try {
                              img = cv::imdecode(cv::Mat(1, int(r.raw.size()), CV_8U, const_cast<char*>(r.raw.data())), cv::IMREAD_COLOR);
                          } catch (const cv::Exception& e) {
                              throw bad(what, std::string("cannot be decoded: ") + e.what());
                          }
                          if (img.empty()) throw bad(what, "cannot be decoded as an image");
                          if (img.cols != K.width || img.rows != K.height)
                              throw bad(what + " camera", "is " + std::to_string(K.width) + "x" + std::to_string(K.height) + " but the photo is " +
                                                              std::to_string(img.cols) + "x" + std::to_string(img.rows));
                          return guarded([&] {
                              const PhotoRecord p = st->add_photo_bytes(id, r.raw, name, camera_to_json(K), actor_of(r.client));
                              Response resp = ok(photo_json(p), 201);
                              resp.headers["Location"] = "/api/cases/" + std::to_string(id) + "/photos/" + std::to_string(p.id);
                              return resp;
                          });
                      }};
    add_upload(reg, std::move(up_photo), max_upload_bytes);
    reg.add({"GET", "/api/cases/{id}/photos/{photo_id}", "cases.photo", Access::read, "Download a photo of the case (image/jpeg or image/png)",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 const auto pid = case_id_param(r, "photo_id");
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     for (const auto& p : rec.photos)
                         if (p.id == pid) {
                             std::string bytes = st->read_blob(p.blob.sha256);
                             const std::string mime = is_png(bytes) ? "image/png" : "image/jpeg";
                             Response resp = Response::binary(std::move(bytes), mime);
                             st->audit(actor_of(r.client), "photo.download", id, {{"photo_id", pid}});
                             return resp;
                         }
                     throw ApiError(404, "not_found", "photo " + std::to_string(pid) + ": no such photo in case " + std::to_string(id));
                 });
             }});

    // ---- landmarks ----
    reg.add({"GET", "/api/cases/{id}/landmarks", "cases.landmarks", Access::read,
             "The case's landmarks (latest revision; ?revisions=all for every one)",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 const std::string which = query(r, "revisions").value_or("latest");
                 if (which != "latest" && which != "all") throw bad("landmarks revisions '" + which + "'", "must be latest or all");
                 return guarded([&] {
                     const auto hist = st->landmark_history(id);  // NotFound for an unknown case
                     if (which == "all") {
                         json a = json::array();
                         for (const auto& s : hist) a.push_back(landmarks_json(s));
                         return ok({{"revisions", a}});
                     }
                     if (hist.empty()) throw ApiError(404, "not_found", "case " + std::to_string(id) + ": no landmarks yet");
                     return ok(landmarks_json(hist.back()));
                 });
             }});
    reg.add({"POST", "/api/cases/{id}/landmarks", "cases.set_landmarks", Access::write,
             "Set the landmarks (a new revision): {landmarks: [{label, world_mm, pixel}], photo_id?}; >= 4 pairs, inside the photo, not collinear",
             on_own_stack([st](const Request& r) {
                 const auto id = case_id_param(r);
                 const std::string what = "case " + std::to_string(id) + " landmarks";
                 only_fields(r.body, {"landmarks", "photo_id", "id"}, what);
                 if (r.body.contains("landmarks") && r.body["landmarks"].is_array() && r.body["landmarks"].size() > 1000) throw bad(what, "more than 1000 landmarks");
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     const PhotoRecord& photo = photo_for(rec, r.body, what);
                     std::vector<LandmarkPoint> pts;
                     try {
                         // Core's parser and checks, the same a case folder's landmarks.json gets.
                         const auto lms = parse_landmarks(r.body, what);
                         validate_landmarks(lms, intrinsics_of(photo), what);
                         for (const auto& l : lms) pts.push_back({l.label, {l.world_mm.x(), l.world_mm.y(), l.world_mm.z()}, {l.pixel.x(), l.pixel.y()}});
                     } catch (const InputError& e) {
                         throw ApiError(400, "bad_request", e.what());
                     }
                     return ok(landmarks_json(st->set_landmarks(id, pts, photo.id, actor_of(r.client))), 201);
                 });
             })});

    // ---- ROI ----
    reg.add({"GET", "/api/cases/{id}/roi", "cases.roi", Access::read, "The case's ROI (latest revision; ?revisions=all for every one)",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 const std::string which = query(r, "revisions").value_or("latest");
                 if (which != "latest" && which != "all") throw bad("roi revisions '" + which + "'", "must be latest or all");
                 return guarded([&] {
                     const auto hist = st->roi_history(id);
                     if (which == "all") {
                         json a = json::array();
                         for (const auto& s : hist) a.push_back(roi_json(s));
                         return ok({{"revisions", a}});
                     }
                     if (hist.empty()) throw ApiError(404, "not_found", "case " + std::to_string(id) + ": no ROI yet");
                     return ok(roi_json(hist.back()));
                 });
             }});
    reg.add({"POST", "/api/cases/{id}/roi", "cases.set_roi", Access::write,
             "Set the ROI (a new revision): {points: [[u, v], ...] (>= 3, inside the photo), tension?: -1..1, type?, photo_id?}",
             on_own_stack([st](const Request& r) {
                 const auto id = case_id_param(r);
                 const std::string what = "case " + std::to_string(id) + " roi";
                 only_fields(r.body, {"points", "tension", "type", "photo_id", "id"}, what);
                 if (r.body.contains("points") && r.body["points"].is_array() && r.body["points"].size() > 10000) throw bad(what, "more than 10000 points");
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     const PhotoRecord& photo = photo_for(rec, r.body, what);
                     json roi;
                     try {
                         const Roi parsed = parse_roi(r.body, what);
                         validate_roi(parsed, intrinsics_of(photo), what);
                         json pts = json::array();
                         for (const auto& p : parsed.points) pts.push_back({p.x(), p.y()});
                         roi = {{"type", "closed-cardinal-spline"}, {"tension", parsed.tension}, {"points", pts}};
                     } catch (const InputError& e) {
                         throw ApiError(400, "bad_request", e.what());
                     }
                     return ok(roi_json(st->set_roi(id, roi, photo.id, actor_of(r.client))), 201);
                 });
             })});

    // ---- registrations and results ----
    reg.add({"GET", "/api/cases/{id}/registrations", "cases.registrations", Access::read,
             "The case's registration runs: status, parameters, initial and final pose, NMI, timings, result files",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     json a = json::array();
                     for (const auto& g : rec.registrations) a.push_back(registration_json(g));
                     return ok({{"registrations", a}});
                 });
             }});
    reg.add({"GET", "/api/cases/{id}/results", "cases.results", Access::read, "The case's result files (registration JSON, ...) with their download paths",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     json a = json::array();
                     for (const auto& x : rec.results) a.push_back(result_json(x));
                     return ok({{"results", a}});
                 });
             }});
    reg.add({"GET", "/api/cases/{id}/results/{result_id}", "cases.result", Access::read, "Download one result file (its media type)",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 const auto rid = case_id_param(r, "result_id");
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     for (const auto& x : rec.results)
                         if (x.id == rid) {
                             Response resp = attachment(st->read_blob(x.blob.sha256), x.media_type, x.name);
                             st->audit(actor_of(r.client), "result.download", id, {{"result_id", rid}});
                             return resp;
                         }
                     throw ApiError(404, "not_found", "result " + std::to_string(rid) + ": no such result in case " + std::to_string(id));
                 });
             }});

    // ---- moving a case ----
    reg.add({"GET", "/api/cases/{id}/export", "cases.export", Access::read,
             "The case as a zip (case.json + store.json + files; docs/case-store.md), audited as case.export",
             on_own_stack([st, work_dir](const Request& r) {
                 const auto id = case_id_param(r);
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);
                     Scratch scratch(work_dir, "export");
                     const std::string name = "case_" + std::to_string(id) + ".zip";
                     st->export_case_zip(id, scratch.dir / name, actor_of(r.client));
                     return attachment(read_file(scratch.dir / name), "application/zip", name);
                 });
             })});
    Endpoint imp{"POST", "/api/cases/import-zip", "cases.import_zip", Access::write,
                 "Import a case zip (body: the archive; query: name=case.zip titles a plain case); refused whole when anything in it is bad",
                 [st, work_dir](const Request& r) {
                     const std::string name = upload_name(r, "case zip", {".zip"}, "case.zip");
                     if (r.raw.empty()) throw bad("case zip " + name, "the request body is empty (send the archive's bytes)");
                     return guarded([&] {
                         Scratch scratch(work_dir, "import_zip");
                         const fs::path file = scratch.write(name, r.raw);
                         std::int64_t id = 0;
                         try {
                             id = st->import_case_zip(file, actor_of(r.client));
                         } catch (const StoreError& e) {
                             rethrow_store_error(StoreError(e.kind(), scratch.strip(e.what())));
                         }
                         Response resp = ok(case_summary_json(st->get_case(id).summary), 201);
                         resp.headers["Location"] = "/api/cases/" + std::to_string(id);
                         return resp;
                     });
                 }};
    add_upload(reg, std::move(imp), max_upload_bytes);
}

}  // namespace cf::daemon
