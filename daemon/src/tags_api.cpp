// Stimulation tags (docs/api/tags.md): marks on the registered photo cast back onto the plan's
// brain surface with the registration's pose, stored as a result of the case per revision.
#include "tags_api.hpp"

#include <atomic>
#include <cmath>
#include <memory>
#include <mutex>
#include <optional>
#include <regex>
#include <set>
#include <thread>

#include "case_api.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/overlay.hpp"
#include "cortexfuse/core/surface.hpp"

namespace cf::daemon {

namespace fs = std::filesystem;
using nlohmann::json;
using namespace cf::db;

namespace {

constexpr std::size_t kMaxTags = 200;
constexpr std::size_t kMaxLabelBytes = 40, kMaxNoteBytes = 500;

ApiError bad(const std::string& what, const std::string& problem) { return ApiError(400, "bad_request", what + ": " + problem); }

struct TagIn {
    std::string label, colour, note;
    Eigen::Vector2d pixel_px;
};

bool has_control_chars(const std::string& s) {
    for (unsigned char c : s)
        if (c < 0x20 || c == 0x7f) return true;
    return false;
}

/// The request's tags, checked for shape (the photo's bounds are checked once it is known).
std::vector<TagIn> parse_tags(const json& body, const std::string& ctx) {
    if (!body.is_object()) throw bad(ctx, "the request must be a JSON object {tags: [...]}");
    for (auto it = body.begin(); it != body.end(); ++it)
        if (it.key() != "tags" && it.key() != "registration_id" && it.key() != "id") throw bad(ctx + " " + it.key(), "unknown field");
    if (!body.contains("tags") || !body["tags"].is_array()) throw bad(ctx + " tags", "must be an array of {label, colour, note?, pixel: [u, v]}");
    const json& a = body["tags"];
    if (a.size() > kMaxTags) throw bad(ctx + " tags", std::to_string(a.size()) + " tags, at most " + std::to_string(kMaxTags));
    static const std::regex colour_re("^#[0-9a-fA-F]{6}$");
    std::vector<TagIn> out;
    std::set<std::string> labels;
    for (std::size_t i = 0; i < a.size(); ++i) {
        const std::string w = ctx + " tags[" + std::to_string(i) + "]";
        const json& t = a[i];
        if (!t.is_object()) throw bad(w, "must be an object {label, colour, note?, pixel}");
        for (auto it = t.begin(); it != t.end(); ++it)
            if (it.key() != "label" && it.key() != "colour" && it.key() != "note" && it.key() != "pixel" && it.key() != "world_mm" &&
                it.key() != "normal_world" && it.key() != "depth_mm")
                throw bad(w + " " + it.key(), "unknown field");
        TagIn in;
        if (!t.contains("label") || !t["label"].is_string()) throw bad(w + " label", "must be a string");
        in.label = t["label"].get<std::string>();
        if (in.label.empty() || in.label.size() > kMaxLabelBytes || has_control_chars(in.label))
            throw bad(w + " label", "must be 1.." + std::to_string(kMaxLabelBytes) + " characters without control characters");
        if (!labels.insert(in.label).second) throw bad(w + " label", "'" + in.label + "' is used twice");
        if (!t.contains("colour") || !t["colour"].is_string() || !std::regex_match(t["colour"].get<std::string>(), colour_re))
            throw bad(w + " colour", "must be \"#rrggbb\"");
        in.colour = t["colour"].get<std::string>();
        if (t.contains("note")) {
            if (!t["note"].is_string()) throw bad(w + " note", "must be a string");
            in.note = t["note"].get<std::string>();
            if (in.note.size() > kMaxNoteBytes) throw bad(w + " note", "longer than " + std::to_string(kMaxNoteBytes) + " bytes");
            for (unsigned char c : in.note)
                if ((c < 0x20 && c != '\n') || c == 0x7f) throw bad(w + " note", "holds control characters");
        }
        const json& p = t.value("pixel", json());
        if (!p.is_array() || p.size() != 2 || !p[0].is_number() || !p[1].is_number()) throw bad(w + " pixel", "must be [u, v] (photo pixels)");
        in.pixel_px = {p[0].get<double>(), p[1].get<double>()};
        if (!std::isfinite(in.pixel_px.x()) || !std::isfinite(in.pixel_px.y())) throw bad(w + " pixel", "must be finite");
        out.push_back(std::move(in));
    }
    return out;
}

/// The registration the tags are cast with, its photo and the plan's surface.
struct TagParts {
    RegistrationRecord reg;
    PhotoRecord photo;
    ResultRecord surface;
    Pose T_camera_from_world;
    Intrinsics K;
};

TagParts tag_parts(const CaseRecord& rec, std::optional<std::int64_t> registration_id, const std::string& c) {
    TagParts f;
    const RegisteredView v = registered_view(rec, registration_id, c, "tags are cast with its pose; run a register job first",
                                             "tags land on the plan's surface; run a plan job first");
    f.reg = v.reg;
    f.photo = v.photo;
    f.T_camera_from_world = v.T_camera_from_world;
    f.surface = v.surface;
    try {
        f.K = parse_camera(json{{"camera", f.photo.intrinsics}}, c + " photo " + std::to_string(f.photo.id));
    } catch (const InputError& e) {
        throw ApiError(500, "internal", e.what());
    }
    return f;
}

std::optional<std::int64_t> registration_id_of(const json& body, const std::string& ctx) {
    if (!body.contains("registration_id")) return std::nullopt;
    const json& v = body["registration_id"];
    if (!v.is_number_integer() || v.get<std::int64_t>() < 1) throw bad(ctx + " registration_id", "must be a positive integer");
    return v.get<std::int64_t>();
}

struct State {
    CaseStore* store = nullptr;
    fs::path work_dir;
    std::mutex write_mutex;  ///< orders revisions: one POST at a time
    std::mutex mesh_mutex;
    std::string mesh_sha;
    std::shared_ptr<const SurfaceMesh> mesh;
    std::atomic<std::uint64_t> scratch_seq{0};

    /// The stored surface (a PLY blob), read through a scratch file; the last one is kept.
    std::shared_ptr<const SurfaceMesh> surface(const ResultRecord& r) {
        std::lock_guard lk(mesh_mutex);
        if (mesh && mesh_sha == r.blob.sha256) return mesh;
        const fs::path dir = work_dir / ("tags_" + std::to_string(++scratch_seq));
        std::string ext = fs::path(r.name).extension().string();
        if (ext.empty()) ext = ".ply";
        std::shared_ptr<const SurfaceMesh> m;
        try {
            fs::create_directories(dir);
            store->copy_blob_to(r.blob.sha256, dir / ("surface" + ext));
            m = std::make_shared<const SurfaceMesh>(load_mesh(dir / ("surface" + ext)));
        } catch (...) {
            std::error_code ec;
            fs::remove_all(dir, ec);
            throw;
        }
        std::error_code ec;
        fs::remove_all(dir, ec);
        mesh_sha = r.blob.sha256;
        mesh = m;
        return m;
    }
};

json vec_json(const Eigen::Vector3d& v) { return json::array({v.x(), v.y(), v.z()}); }

/// A stored revision as the API answers it.
json revision_json(CaseStore& st, const ResultRecord& r) {
    json j = json::parse(st.read_blob(r.blob.sha256), nullptr, false);
    if (!j.is_object()) throw ApiError(500, "internal", "tags result " + std::to_string(r.id) + ": stored file is not JSON");
    j["id"] = r.id;
    j["created_utc"] = format_utc(r.created_utc);
    return j;
}

}  // namespace

void register_tags_endpoints(EndpointRegistry& reg, CaseStore& store, const fs::path& work_dir) {
    auto s = std::make_shared<State>();
    s->store = &store;
    s->work_dir = work_dir;

    reg.add({"POST", "/api/cases/{id}/tags", "cases.set_tags", Access::write,
             "Stimulation tags on the registered photo: {tags: [{label, colour, note?, pixel: [u, v]}], registration_id?}; each cast onto the plan's "
             "brain surface with the registration's pose (world_mm, LPS); a new revision",
             on_own_stack([s](const Request& r) {
                 return guarded([&] {
                     const std::int64_t id = case_id_param(r);
                     const std::string ctx = "tags case " + std::to_string(id);
                     if (r.body.is_null()) throw bad(ctx, "the request must be a JSON object {tags: [...]}");
                     std::vector<TagIn> tags = parse_tags(r.body, ctx);
                     const auto reg_id = registration_id_of(r.body, ctx);
                     std::lock_guard lk(s->write_mutex);
                     const CaseRecord rec = s->store->get_case(id);  // 404 for an unknown case
                     const TagParts f = tag_parts(rec, reg_id, ctx);
                     for (std::size_t i = 0; i < tags.size(); ++i) {
                         const Eigen::Vector2d& p = tags[i].pixel_px;
                         if (p.x() < -0.5 || p.y() < -0.5 || p.x() > f.K.width - 0.5 || p.y() > f.K.height - 0.5)
                             throw bad(ctx + " tags[" + std::to_string(i) + "] pixel",
                                       "[" + std::to_string(p.x()) + ", " + std::to_string(p.y()) + "] is outside the photo (" + std::to_string(f.K.width) +
                                           "x" + std::to_string(f.K.height) + ")");
                     }
                     std::shared_ptr<const SurfaceMesh> mesh;
                     try {
                         mesh = s->surface(f.surface);
                     } catch (const InputError& e) {
                         throw ApiError(500, "internal", ctx + ": the stored brain surface cannot be read: " + e.what());
                     }
                     json out_tags = json::array();
                     for (std::size_t i = 0; i < tags.size(); ++i) {
                         const TagIn& t = tags[i];
                         const auto hit = cast_back(*mesh, f.K, f.T_camera_from_world, t.pixel_px);
                         if (!hit)
                             throw ApiError(422, "unprocessable", ctx + " tags[" + std::to_string(i) + "] '" + t.label +
                                                                      "': the photo pixel's ray misses the brain surface");
                         out_tags.push_back({{"label", t.label},
                                             {"colour", t.colour},
                                             {"note", t.note},
                                             {"pixel", {t.pixel_px.x(), t.pixel_px.y()}},
                                             {"world_mm", vec_json(hit->p_world_mm)},
                                             {"normal_world", vec_json(hit->normal_world)},
                                             {"depth_mm", hit->depth_mm}});
                     }
                     int revision = 1;
                     for (const auto& x : rec.results) revision += x.kind == "tags";
                     json doc{{"revision", revision},
                              {"registration_id", f.reg.id},
                              {"photo_id", f.photo.id},
                              {"surface_result_id", f.surface.id},
                              {"T_camera_from_world", pose_to_json(f.T_camera_from_world)},
                              {"frame", "world_mm: LPS mm of the case's T1 (the plan surface's frame); pixel: OpenCV photo pixel"},
                              {"tags", out_tags}};
                     ResultInput in;
                     in.kind = "tags";
                     in.name = "tags_r" + std::to_string(revision) + ".json";
                     in.media_type = "application/json";
                     in.bytes = doc.dump(1);
                     in.params = {{"revision", revision}, {"photo_id", f.photo.id}, {"surface_result_id", f.surface.id}, {"count", out_tags.size()}};
                     const ResultRecord stored = s->store->add_result(id, f.reg.id, in, actor_of(r.client));
                     doc["id"] = stored.id;
                     doc["created_utc"] = format_utc(stored.created_utc);
                     return ok(doc, 201);
                 });
             })});

    reg.add({"GET", "/api/cases/{id}/tags", "cases.tags", Access::read,
             "The case's stimulation tags (latest revision, {revision: 0, tags: []} when none; ?revisions=all for every one)",
             [s](const Request& r) {
                 return guarded([&] {
                     const std::int64_t id = case_id_param(r);
                     std::string which = "latest";
                     if (auto it = r.params.find("revisions"); it != r.params.end()) which = it->second;
                     if (which != "latest" && which != "all") throw bad("tags revisions '" + which + "'", "must be latest or all");
                     const CaseRecord rec = s->store->get_case(id);
                     std::vector<const ResultRecord*> all;
                     for (const auto& x : rec.results)
                         if (x.kind == "tags") all.push_back(&x);
                     if (which == "all") {
                         json a = json::array();
                         for (const auto* x : all) a.push_back(revision_json(*s->store, *x));
                         return ok({{"revisions", a}});
                     }
                     if (all.empty()) return ok({{"revision", 0}, {"registration_id", nullptr}, {"tags", json::array()}});
                     const ResultRecord* newest = all.front();
                     for (const auto* x : all)
                         if (x->id > newest->id) newest = x;
                     return ok(revision_json(*s->store, *newest));
                 });
             }});
}

}  // namespace cf::daemon
