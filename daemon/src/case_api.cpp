#include "case_api.hpp"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <fstream>
#include <optional>
#include <regex>
#include <sstream>
#include <thread>

#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/daemon/log.hpp"

namespace cf::daemon {

namespace fs = std::filesystem;
using nlohmann::json;
using namespace cf::db;

[[noreturn]] void rethrow_store_error(const StoreError& e) {
    switch (e.kind()) {
        case StoreError::Kind::NotFound: throw ApiError(404, "not_found", e.what());
        case StoreError::Kind::Conflict: throw ApiError(409, "conflict", e.what());
        case StoreError::Kind::Invalid: throw ApiError(400, "bad_request", e.what());
        case StoreError::Kind::Busy: throw ApiError(503, "unavailable", e.what());
        default: break;
    }
    log(LogLevel::error, "store", e.what());  // store messages never carry patient names
    throw ApiError(500, "store_error", e.what());
}

Actor actor_of(const Client& c) {
    Actor a;
    a.name = c.user.empty() ? (c.role.empty() ? "anonymous" : c.role) : c.user;
    a.user_id = c.user_id;
    return a;
}

Response ok(json j, int status) {
    Response r;
    r.status = status;
    r.json = std::move(j);
    return r;
}

RegisteredView registered_view(const cf::db::CaseRecord& rec, std::optional<std::int64_t> registration_id, const std::string& c,
                               const std::string& register_hint, const std::string& surface_hint) {
    using cf::db::RegistrationStatus;
    RegisteredView f;
    bool found = false;
    for (const auto& r : rec.registrations) {
        if (registration_id ? r.id != *registration_id : (r.status != RegistrationStatus::succeeded || !r.final_pose)) continue;
        f.reg = r;
        found = true;  // oldest first: the last match is the newest
    }
    if (!found) {
        if (registration_id) throw ApiError(404, "not_found", c + " registration_id: case has no registration " + std::to_string(*registration_id));
        throw ApiError(409, "conflict", c + ": no successful registration yet (" + register_hint + ")");
    }
    if (f.reg.status != RegistrationStatus::succeeded || !f.reg.final_pose)
        throw ApiError(409, "conflict", c + " registration " + std::to_string(f.reg.id) + ": it did not succeed (" + to_string(f.reg.status) + ")");
    try {
        // Stored as {"T_camera_from_world": 4x4} (the register job) or as the 4x4 itself.
        const json& fp = *f.reg.final_pose;
        f.T_camera_from_world = parse_pose(fp.is_array() ? json{{"T_camera_from_world", fp}} : fp, c + " registration pose");
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
    bool surface = false;
    for (const auto& r : rec.results)
        if (r.kind == "plan_brain_surface" && (!surface || r.id > f.surface.id)) {
            f.surface = r;
            surface = true;
        }
    if (!surface) throw ApiError(409, "conflict", c + ": no brain surface yet (" + surface_hint + ")");
    return f;
}

Handler on_own_stack(Handler h) {
    return [h = std::move(h)](const Request& r) {
        std::optional<Response> out;
        std::exception_ptr err;
        std::thread t([&] {
            try {
                out = h(r);
            } catch (...) {
                err = std::current_exception();
            }
        });
        t.join();
        if (err) std::rethrow_exception(err);
        return std::move(*out);
    };
}

fs::path case_dir_from_name(const fs::path& cases_root, const json& v, const std::string& field) {
    if (!v.is_string()) throw ApiError(400, "bad_request", field + ": must be a string (a case folder such as phantom/case_0000)");
    const std::string name = v.get<std::string>();
    static const std::regex seg("[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}");
    if (name.empty() || name.size() > 512) throw ApiError(400, "bad_request", field + ": must be 1..512 characters");
    std::stringstream ss(name);
    std::string part;
    fs::path rel;
    while (std::getline(ss, part, '/')) {
        if (!std::regex_match(part, seg) || part == "." || part == "..")
            throw ApiError(400, "bad_request", field + " '" + name + "': each part must be letters, digits, _ . - (no '..', no absolute paths)");
        rel /= part;
    }
    const fs::path dir = cases_root / rel;
    std::error_code ec;
    if (!fs::is_regular_file(dir / "case.json", ec)) throw ApiError(404, "not_found", field + " '" + name + "': no such case folder (no case.json)");
    return dir;
}

json case_summary_json(const CaseSummary& s) {
    return {{"id", s.id},
            {"uid", s.uid},
            {"title", s.title},
            {"state", to_string(s.state)},
            {"patient_id", s.patient_id ? json(*s.patient_id) : json(nullptr)},
            {"created_utc", format_utc(s.created_utc)},
            {"updated_utc", format_utc(s.updated_utc)}};
}

json case_record_json(const CaseRecord& r) {
    json j = case_summary_json(r.summary);
    if (r.patient)
        j["patient"] = {{"id", r.patient->id},
                        {"mrn", r.patient->mrn},
                        {"family_name", r.patient->family_name},
                        {"given_name", r.patient->given_name},
                        {"birth_date", r.patient->birth_date ? json(*r.patient->birth_date) : json(nullptr)}};
    j["volumes"] = json::array();
    for (const auto& v : r.volumes)
        j["volumes"].push_back({{"id", v.id}, {"modality", to_string(v.modality)}, {"original_name", v.original_name}, {"sha256", v.blob.sha256},
                                {"size_bytes", v.blob.size_bytes}, {"created_utc", format_utc(v.created_utc)}});
    j["photos"] = json::array();
    for (const auto& p : r.photos)
        j["photos"].push_back({{"id", p.id}, {"original_name", p.original_name}, {"sha256", p.blob.sha256}, {"intrinsics", p.intrinsics},
                               {"created_utc", format_utc(p.created_utc)}});
    if (r.landmarks) {
        json pts = json::array();
        for (const auto& p : r.landmarks->points) pts.push_back({{"name", p.name}, {"world_mm", p.world_mm}, {"pixel", p.pixel}});
        j["landmarks"] = {{"id", r.landmarks->id}, {"revision", r.landmarks->revision}, {"points", pts}};
    }
    if (r.roi) j["roi"] = {{"id", r.roi->id}, {"revision", r.roi->revision}, {"roi", r.roi->roi}};
    j["registrations"] = json::array();
    for (const auto& g : r.registrations) {
        json x{{"id", g.id}, {"status", to_string(g.status)}, {"created_utc", format_utc(g.created_utc)}};
        if (g.nmi) x["nmi"] = *g.nmi;
        if (g.seconds) x["seconds"] = *g.seconds;
        if (g.evaluations) x["evaluations"] = *g.evaluations;
        if (g.final_pose) x["final_pose"] = *g.final_pose;
        if (g.error) x["error"] = *g.error;
        j["registrations"].push_back(x);
    }
    j["results"] = json::array();
    for (const auto& x : r.results)
        j["results"].push_back({{"id", x.id}, {"kind", x.kind}, {"name", x.name}, {"media_type", x.media_type},
                                {"registration_id", x.registration_id ? json(*x.registration_id) : json(nullptr)}});
    return j;
}

std::int64_t case_id_param(const Request& r, const char* key) {
    const auto it = r.params.find(key);
    if (it == r.params.end()) throw ApiError(400, "bad_request", std::string(key) + " missing");
    const std::string& s = it->second;
    if (s.empty() || s.size() > 18 || s.find_first_not_of("0123456789") != std::string::npos)
        throw ApiError(400, "bad_request", std::string(key) + " '" + s + "' is not a number");
    return std::stoll(s);
}

namespace {

std::string str_field(const json& b, const char* key, bool required, const std::string& ctx, std::size_t max_len = 1024) {
    if (!b.contains(key)) {
        if (required) throw ApiError(400, "bad_request", ctx + " " + key + ": missing");
        return {};
    }
    if (!b[key].is_string()) throw ApiError(400, "bad_request", ctx + " " + key + ": must be a string");
    const std::string s = b[key].get<std::string>();
    if (s.size() > max_len) throw ApiError(400, "bad_request", ctx + " " + key + ": longer than " + std::to_string(max_len) + " characters");
    return s;
}

void only_fields(const json& b, std::initializer_list<const char*> known, const std::string& ctx) {
    if (!b.is_object()) throw ApiError(400, "bad_request", ctx + ": body must be a JSON object");
    for (auto it = b.begin(); it != b.end(); ++it) {
        bool ok = false;
        for (const char* k : known) ok = ok || it.key() == k;
        if (!ok) throw ApiError(400, "bad_request", ctx + " " + it.key() + ": unknown field");
    }
}


/// Copies the case folder's files into `staging` and, for each file case.json names outside
/// the folder (it must stay inside `root`), a copy beside them, with case.json pointing at it.
void stage_self_contained(const fs::path& dir, const fs::path& root, const fs::path& staging) {
    std::error_code ec;
    fs::create_directories(staging, ec);
    if (ec) throw ApiError(500, "io_error", "cases.import: cannot create " + staging.string() + ": " + ec.message());
    for (const auto& e : fs::directory_iterator(dir))
        if (e.is_regular_file()) fs::copy_file(e.path(), staging / e.path().filename(), fs::copy_options::overwrite_existing);
    json cj;
    try {
        std::ifstream f(dir / "case.json");
        cj = json::parse(f);
    } catch (const std::exception& e) {
        throw ApiError(400, "bad_request", (dir / "case.json").string() + ": not valid JSON");
    }
    const fs::path root_c = fs::weakly_canonical(root);
    bool changed = false;
    for (const char* key : {"volume", "brain_mask", "photo", "landmarks", "roi", "initial_pose"}) {
        if (!cj.contains(key) || !cj[key].is_string()) continue;
        const fs::path ref = cj[key].get<std::string>();
        if (!ref.has_parent_path()) continue;
        const fs::path src = fs::weakly_canonical(dir / ref, ec);
        const std::string ss = src.string(), rs = root_c.string();
        if (ec || ss.compare(0, rs.size(), rs) != 0 || !fs::is_regular_file(src))
            throw ApiError(400, "bad_request", (dir / "case.json").string() + ": " + key + " '" + ref.string() + "' is not a file inside the cases folder");
        fs::path name = src.filename();
        if (fs::exists(staging / name)) name = std::string(key) + "_" + name.string();
        fs::copy_file(src, staging / name, fs::copy_options::overwrite_existing);
        cj[key] = name.string();
        changed = true;
    }
    if (changed) {
        std::ofstream o(staging / "case.json", std::ios::trunc);
        o << cj.dump(2);
        if (!o) throw ApiError(500, "io_error", "cases.import: cannot write the staged case.json");
    }
}

}  // namespace

void register_case_endpoints(EndpointRegistry& reg, CaseStore& store, const fs::path& cases_dir, const fs::path& work_dir,
                             int session_ttl_s) {
    CaseStore* st = &store;
    reg.add({"POST", "/api/login", "auth.login", Access::open, "Log in: {name, password} -> {token, user, role, expires_utc}",
             [st, session_ttl_s](const Request& r) {
                 only_fields(r.body, {"name", "password"}, "login");
                 const std::string name = str_field(r.body, "name", true, "login", 64);
                 const std::string password = str_field(r.body, "password", true, "login", 1024);
                 return guarded([&] {
                     const auto u = st->verify_password(name, password);
                     if (!u) {
                         st->audit(Actor{"anonymous", std::nullopt}, "user.login_failed", std::nullopt, {{"from", r.client.address}});
                         throw ApiError(401, "unauthorized", "login: unknown user or wrong password");
                     }
                     const Session s = st->create_session(u->id, std::chrono::seconds(session_ttl_s));
                     st->audit(Actor{u->name, u->id}, "user.login", std::nullopt, {{"from", r.client.address}});
                     return ok({{"token", s.token}, {"user", u->name}, {"role", to_string(u->role)}, {"expires_utc", format_utc(s.expires_utc)}});
                 });
             }});
    reg.add({"POST", "/api/logout", "auth.logout", Access::open, "End the session of the bearer token",
             [st](const Request& r) {
                 if (r.client.token.empty()) throw ApiError(400, "bad_request", "logout: no session token (Authorization: Bearer ...)");
                 return guarded([&] {
                     st->revoke_session(r.client.token);
                     return ok({{"logged_out", true}});
                 });
             }});
    reg.add({"GET", "/api/users", "users.list", Access::admin, "Users and their roles",
             [st](const Request&) {
                 return guarded([&] {
                     json a = json::array();
                     for (const auto& u : st->list_users())
                         a.push_back({{"id", u.id}, {"name", u.name}, {"role", to_string(u.role)}, {"disabled", u.disabled}});
                     return ok({{"users", a}});
                 });
             }});
    reg.add({"POST", "/api/users", "users.create", Access::admin, "Create a user: {name, password, role}",
             [st](const Request& r) {
                 only_fields(r.body, {"name", "password", "role"}, "users.create");
                 const std::string name = str_field(r.body, "name", true, "users.create", 64);
                 const std::string password = str_field(r.body, "password", true, "users.create", 1024);
                 const std::string role = str_field(r.body, "role", true, "users.create", 32);
                 return guarded([&] {
                     const User u = st->create_user(name, password, role_from_string(role), actor_of(r.client));
                     return ok({{"id", u.id}, {"name", u.name}, {"role", to_string(u.role)}}, 201);
                 });
             }});
    reg.add({"GET", "/api/cases", "cases.list", Access::read, "Cases in the store (query: text, state, sort, limit, offset)",
             [st](const Request& r) {
                 CaseQuery q;
                 auto p = [&](const char* k) -> const std::string* {
                     auto it = r.params.find(k);
                     return it == r.params.end() ? nullptr : &it->second;
                 };
                 if (auto* t = p("text")) q.text = *t;
                 auto int_q = [&](const char* k, int lo, int hi, int def) {
                     const std::string* s = p(k);
                     if (!s) return def;
                     if (s->empty() || s->size() > 6 || s->find_first_not_of("0123456789") != std::string::npos || std::stoi(*s) < lo || std::stoi(*s) > hi)
                         throw ApiError(400, "bad_request", std::string("cases ") + k + ": '" + *s + "' is not a number " + std::to_string(lo) + ".." + std::to_string(hi));
                     return std::stoi(*s);
                 };
                 q.limit = int_q("limit", 1, 10000, 100);
                 q.offset = int_q("offset", 0, 1000000, 0);
                 if (auto* s = p("sort")) {
                     static const std::map<std::string, CaseQuery::Sort> sorts = {
                         {"updated_desc", CaseQuery::Sort::updated_desc}, {"updated_asc", CaseQuery::Sort::updated_asc},
                         {"created_desc", CaseQuery::Sort::created_desc}, {"created_asc", CaseQuery::Sort::created_asc},
                         {"title_asc", CaseQuery::Sort::title_asc},       {"title_desc", CaseQuery::Sort::title_desc}};
                     auto it = sorts.find(*s);
                     if (it == sorts.end()) throw ApiError(400, "bad_request", "cases sort: '" + *s + "' is not updated_desc, updated_asc, created_desc, created_asc, title_asc or title_desc");
                     q.sort = it->second;
                 }
                 return guarded([&] {
                     if (auto* s = p("state")) q.state = case_state_from_string(*s);
                     json a = json::array();
                     for (const auto& c : st->list_cases(q)) a.push_back(case_summary_json(c));
                     return ok({{"cases", a}});
                 });
             }});
    reg.add({"POST", "/api/cases", "cases.create", Access::write,
             "New case: {title, patient?: {mrn, family_name, given_name?, birth_date?}} (an existing MRN reuses its patient)",
             [st](const Request& r) {
                 only_fields(r.body, {"title", "patient"}, "cases.create");
                 const std::string title = str_field(r.body, "title", true, "cases.create", 200);
                 return guarded([&] {
                     std::optional<std::int64_t> pid;
                     if (r.body.contains("patient")) {
                         const json& pj = r.body["patient"];
                         only_fields(pj, {"mrn", "family_name", "given_name", "birth_date"}, "cases.create patient");
                         PatientInput pi;
                         pi.mrn = str_field(pj, "mrn", true, "cases.create patient", 64);
                         if (auto existing = st->find_patient_by_mrn(pi.mrn)) pid = existing->id;
                         else {
                             pi.family_name = str_field(pj, "family_name", true, "cases.create patient", 200);
                             pi.given_name = str_field(pj, "given_name", false, "cases.create patient", 200);
                             if (pj.contains("birth_date")) pi.birth_date = str_field(pj, "birth_date", true, "cases.create patient", 10);
                             pid = st->create_patient(pi, actor_of(r.client)).id;
                         }
                     }
                     const CaseSummary c = st->create_case(pid, title, actor_of(r.client));
                     Response resp = ok(case_summary_json(c), 201);
                     resp.headers["Location"] = "/api/cases/" + std::to_string(c.id);
                     return resp;
                 });
             }});
    reg.add({"GET", "/api/cases/{id}", "cases.get", Access::read, "A case with everything it holds (audited as case.view)",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 return guarded([&] {
                     json j = case_record_json(st->get_case(id));
                     st->audit(actor_of(r.client), "case.view", id);
                     return ok(j);
                 });
             }});
    reg.add({"POST", "/api/cases/{id}/state", "cases.set_state", Access::write, "Move the case's workflow state: {state}",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 only_fields(r.body, {"state", "id"}, "cases.set_state");
                 const std::string s = str_field(r.body, "state", true, "cases.set_state", 64);
                 return guarded([&] { return ok(case_summary_json(st->set_state(id, case_state_from_string(s), actor_of(r.client)))); });
             }});
    reg.add({"GET", "/api/cases/{id}/audit", "cases.audit", Access::read, "The case's audit trail, oldest first",
             [st](const Request& r) {
                 const auto id = case_id_param(r);
                 return guarded([&] {
                     st->get_case(id);  // 404 for an unknown case
                     json a = json::array();
                     for (const auto& e : st->audit_trail(id))
                         a.push_back({{"id", e.id}, {"at_utc", format_utc(e.at_utc)}, {"actor", e.actor}, {"action", e.action}, {"details", e.details}});
                     return ok({{"audit", a}});
                 });
             }});
    const fs::path cases = cases_dir;
    reg.add({"POST", "/api/cases/import", "cases.import", Access::write,
             "Import a case folder from the state folder's cases/ (e.g. a phantom case): {folder}",
             [st, cases, work_dir](const Request& r) {
                 only_fields(r.body, {"folder"}, "cases.import");
                 if (!r.body.contains("folder")) throw ApiError(400, "bad_request", "cases.import folder: missing");
                 const fs::path dir = case_dir_from_name(cases, r.body["folder"], "cases.import folder");
                 // Phantom cases share their volume one folder up ("../t1.nii.gz"); the store
                 // takes self-contained folders, so a staged copy gets those files beside it.
                 static std::atomic<std::uint64_t> counter{0};
                 const fs::path scratch = work_dir / ("import_" + std::to_string(::getpid()) + "_" + std::to_string(++counter));
                 std::string title = r.body["folder"].get<std::string>();
                 std::replace(title.begin(), title.end(), '/', '_');
                 const fs::path staging = scratch / title;  // the store titles a plain case folder after its name
                 struct Cleanup {
                     fs::path d;
                     ~Cleanup() {
                         std::error_code ec;
                         fs::remove_all(d, ec);
                     }
                 } cleanup{scratch};
                 stage_self_contained(dir, cases, staging);
                 return guarded([&] {
                     const auto id = st->import_case_folder(staging, actor_of(r.client));
                     return ok(case_summary_json(st->get_case(id).summary), 201);
                 });
             }});
}

}  // namespace cf::daemon
