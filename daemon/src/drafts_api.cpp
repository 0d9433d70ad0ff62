// Drafts of Photo & marks (docs/api/case-data.md "Drafts of unsaved marks"): the UI's unsaved
// landmarks and ROI, kept per case and owner in the case store so that a restart of the browser
// itself loses nothing. Checked for shape, size and the photo's bounds before anything is kept;
// a refused request changes nothing.
#include "drafts_api.hpp"

#include <cmath>
#include <cstdio>

#include "case_api.hpp"

namespace cf::daemon {

using nlohmann::json;
using namespace cf::db;

namespace {

constexpr std::size_t kMaxLandmarks = 1000, kMaxRoiPoints = 10000, kMaxLabelBytes = 200;

ApiError bad(const std::string& what, const std::string& problem) { return ApiError(400, "bad_request", what + ": " + problem); }

/// Whose draft a request touches: the kiosk's (the cart's own browser, no login) or a user's.
/// From the session, never from the body.
std::string owner_of(const Client& c) {
    if (c.user_id) return "user:" + std::to_string(*c.user_id);
    return c.role.empty() ? "anonymous" : c.role;
}

void only_fields(const json& o, std::initializer_list<const char*> known, const std::string& ctx) {
    for (auto it = o.begin(); it != o.end(); ++it) {
        bool found = false;
        for (const char* k : known) found = found || it.key() == k;
        if (!found) throw bad(ctx + " " + it.key(), "unknown field");
    }
}

/// The photo's size in pixels (its intrinsics' width and height).
struct PhotoSize {
    std::int64_t id = 0;
    double width = 0, height = 0;
};

double finite(const json& v, const std::string& what) {
    if (!v.is_number()) throw bad(what, "must be a number");
    const double x = v.get<double>();
    if (!std::isfinite(x)) throw bad(what, "must be finite");
    return x;
}

json pixel(const json& p, const PhotoSize& ph, const std::string& what) {
    if (!p.is_array() || p.size() != 2) throw bad(what, "must be [u, v] (photo pixels)");
    const double u = finite(p[0], what + "[0]"), v = finite(p[1], what + "[1]");
    if (u < -0.5 || v < -0.5 || u > ph.width - 0.5 || v > ph.height - 0.5) {
        char b[160];
        std::snprintf(b, sizeof b, "[%.2f, %.2f] is outside photo %lld (%.0fx%.0f)", u, v, static_cast<long long>(ph.id), ph.width, ph.height);
        throw bad(what, b);
    }
    return json::array({u, v});
}

json from_revision(const json& part, const std::string& what) {
    if (!part.contains("from_revision") || part["from_revision"].is_null()) return nullptr;
    const json& r = part["from_revision"];
    if (!r.is_number_integer() || r.get<std::int64_t>() < 1) throw bad(what + " from_revision", "must be null or a revision number (1, 2, ...)");
    return r;
}

/// A part `{from_revision, points: [...]}` of the body (`w` names it): its points, checked for
/// shape and count (`shape`: one point's, `unit`: what `max` counts).
const json& part_points(const json& part, const std::string& w, const std::string& shape, std::size_t max, const char* unit) {
    if (!part.is_object()) throw bad(w, "must be {from_revision, points: [" + shape + ", ...]}");
    only_fields(part, {"from_revision", "points"}, w);
    if (!part.contains("points") || !part["points"].is_array()) throw bad(w + " points", "must be an array of " + shape);
    const json& a = part["points"];
    if (a.size() > max) throw bad(w + " points", std::to_string(a.size()) + " " + unit + ", at most " + std::to_string(max));
    return a;
}

/// The body kept: the parts checked and written again (nothing else of the request is kept).
json checked_draft(const json& body, const PhotoSize& ph, const std::string& ctx) {
    json out{{"photo_id", ph.id}};
    if (body.contains("landmarks")) {
        const std::string w = ctx + " landmarks";
        const json& l = body["landmarks"];
        const json& a = part_points(l, w, "{label, world_mm: [x, y, z], pixel: [u, v]}", kMaxLandmarks, "landmarks");
        json pts = json::array();
        for (std::size_t i = 0; i < a.size(); ++i) {
            const std::string wi = w + " points[" + std::to_string(i) + "]";
            const json& p = a[i];
            if (!p.is_object()) throw bad(wi, "must be {label, world_mm: [x, y, z], pixel: [u, v]}");
            only_fields(p, {"label", "world_mm", "pixel"}, wi);
            // The label as typed so far: empty or repeated is fine in a draft (Save checks it).
            if (!p.contains("label") || !p["label"].is_string()) throw bad(wi + " label", "must be a string");
            const std::string label = p["label"].get<std::string>();
            if (label.size() > kMaxLabelBytes) throw bad(wi + " label", "longer than " + std::to_string(kMaxLabelBytes) + " bytes");
            for (unsigned char c : label)
                if (c < 0x20 || c == 0x7f) throw bad(wi + " label", "holds control characters");
            const json& wm = p.value("world_mm", json());
            if (!wm.is_array() || wm.size() != 3) throw bad(wi + " world_mm", "must be [x, y, z] (LPS mm)");
            json world = json::array();
            for (int k = 0; k < 3; ++k) world.push_back(finite(wm[k], wi + " world_mm[" + std::to_string(k) + "]"));
            pts.push_back({{"label", label}, {"world_mm", world}, {"pixel", pixel(p.value("pixel", json()), ph, wi + " pixel")}});
        }
        out["landmarks"] = {{"from_revision", from_revision(l, w)}, {"points", pts}};
    }
    if (body.contains("roi")) {
        const std::string w = ctx + " roi";
        const json& r = body["roi"];
        const json& a = part_points(r, w, "[u, v] (photo pixels)", kMaxRoiPoints, "points");
        json pts = json::array();
        for (std::size_t i = 0; i < a.size(); ++i) pts.push_back(pixel(a[i], ph, w + " points[" + std::to_string(i) + "]"));
        out["roi"] = {{"from_revision", from_revision(r, w)}, {"points", pts}};
    }
    return out;
}

json draft_json(const DraftRecord& d) {
    json j = d.body;
    j["owner"] = d.owner;
    j["saved_utc"] = format_utc(d.saved_utc);
    j["updated_utc"] = format_utc(d.updated_utc);
    return j;
}

}  // namespace

void register_draft_endpoints(EndpointRegistry& reg, CaseStore& store) {
    CaseStore* st = &store;
    const std::string path = "/api/cases/{id}/drafts/marks";

    reg.add({"GET", path, "cases.marks_draft", Access::write,
             "This user's (or the kiosk's) unsaved landmarks and ROI of the case, kept by the daemon: {draft: null} or "
             "{draft: {photo_id, saved_utc, updated_utc, owner, landmarks?, roi?}}",
             [st](const Request& r) {
                 return guarded([&] {
                     const std::int64_t id = case_id_param(r);
                     const auto d = st->get_draft(id, "marks", owner_of(r.client));  // 404 for an unknown case
                     return ok({{"draft", d ? draft_json(*d) : json(nullptr)}});
                 });
             }});

    reg.add({"PUT", path, "cases.keep_marks_draft", Access::write,
             "Keep unsaved marks (not a revision): {photo_id, saved_utc, landmarks?: {from_revision, points: [{label, world_mm, pixel}]}, "
             "roi?: {from_revision, points: [[u, v]]}}; replaces this user's draft of the case",
             [st](const Request& r) {
                 return guarded([&] {
                     const std::int64_t id = case_id_param(r);
                     const std::string ctx = "case " + std::to_string(id) + " marks draft";
                     const json& b = r.body;
                     if (!b.is_object()) throw bad(ctx, "the request must be a JSON object {photo_id, saved_utc, landmarks?, roi?}");
                     only_fields(b, {"photo_id", "saved_utc", "landmarks", "roi", "id"}, ctx);
                     if (!b.contains("photo_id") || !b["photo_id"].is_number_integer() || b["photo_id"].get<std::int64_t>() < 1)
                         throw bad(ctx + " photo_id", "must be the id of the photo the pixels are on");
                     if (!b.contains("saved_utc") || !b["saved_utc"].is_string())
                         throw bad(ctx + " saved_utc", "must be the time of the edit, e.g. \"2026-11-27T15:42:10.123Z\"");
                     UtcTime saved;
                     try {
                         saved = parse_utc(b["saved_utc"].get<std::string>());
                     } catch (const StoreError&) {
                         throw bad(ctx + " saved_utc '" + b["saved_utc"].get<std::string>().substr(0, 40) + "'",
                                   "must be a UTC time like \"2026-11-27T15:42:10.123Z\"");
                     }
                     if (!b.contains("landmarks") && !b.contains("roi"))
                         throw bad(ctx, "nothing to keep: send landmarks and/or roi (DELETE drops the draft)");
                     const CaseRecord rec = st->get_case(id);  // 404 for an unknown case
                     const std::int64_t pid = b["photo_id"].get<std::int64_t>();
                     PhotoSize ph;
                     for (const auto& p : rec.photos)
                         if (p.id == pid) ph = {p.id, p.intrinsics.value("width", 0.0), p.intrinsics.value("height", 0.0)};
                     if (ph.id == 0) throw ApiError(404, "not_found", ctx + " photo_id " + std::to_string(pid) + ": no such photo in case " + std::to_string(id));
                     const json kept = checked_draft(b, ph, ctx);
                     const std::size_t bytes = kept.dump().size();
                     if (bytes > kMaxDraftBytes)
                         throw ApiError(413, "payload_too_large",
                                        ctx + ": " + std::to_string(bytes) + " bytes, at most " + std::to_string(kMaxDraftBytes) + " are kept; save the marks instead");
                     json audit{{"photo_id", pid},
                                {"landmarks", kept.contains("landmarks") ? json(kept["landmarks"]["points"].size()) : json(nullptr)},
                                {"roi_points", kept.contains("roi") ? json(kept["roi"]["points"].size()) : json(nullptr)}};
                     const std::string owner = owner_of(r.client);
                     const bool created = st->keep_draft(id, "marks", owner, kept, saved, actor_of(r.client), audit);
                     const auto d = st->get_draft(id, "marks", owner);
                     return ok({{"kept", true}, {"new", created}, {"draft", d ? draft_json(*d) : json(nullptr)}});
                 });
             }});

    reg.add({"DELETE", path, "cases.drop_marks_draft", Access::write,
             "Drop this user's unsaved marks of the case (?reason=saved|discarded, default discarded): {dropped: true|false}",
             [st](const Request& r) {
                 return guarded([&] {
                     const std::int64_t id = case_id_param(r);
                     std::string reason = "discarded";
                     if (auto it = r.params.find("reason"); it != r.params.end()) reason = it->second;
                     if (reason != "saved" && reason != "discarded")
                         throw bad("case " + std::to_string(id) + " marks draft reason '" + reason.substr(0, 40) + "'", "must be saved or discarded");
                     return ok({{"dropped", st->drop_draft(id, "marks", owner_of(r.client), reason, actor_of(r.client))}});
                 });
             }});
}

}  // namespace cf::daemon
