#pragma once
// The case store's endpoints (cases, logins, users, audit) over cf_db's CaseStore, and the
// mapping of its errors to HTTP statuses. Registered by the daemon when the store opened.
//
// Thread contract: the handlers run on any connection thread; CaseStore serialises its own
// calls (one SQLite connection behind a mutex).
#include <filesystem>
#include <optional>
#include <string>

#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/db/case_store.hpp"

namespace cf::daemon {

/// StoreError -> ApiError (NotFound 404, Conflict 409, Invalid 400, Busy 503, others 500).
[[noreturn]] void rethrow_store_error(const cf::db::StoreError& e);
cf::db::Actor actor_of(const Client& c);
/// A JSON answer with `status`.
Response ok(nlohmann::json j, int status = 200);
/// f(), with a StoreError turned into its ApiError (rethrow_store_error).
template <class F>
Response guarded(F&& f) {
    try {
        return f();
    } catch (const cf::db::StoreError& e) {
        rethrow_store_error(e);
    }
}
/// `h` run on a thread of its own with the default stack, the caller waiting: civetweb's
/// connection threads have small stacks (Debian builds it with a fixed stack size), and ITK's
/// readers, libzip, mesh reading and the exports go deeper than that (under ASan by far).
Handler on_own_stack(Handler h);
/// What a view of a registered case is made of: a succeeded registration (`registration_id`,
/// or the newest one with a pose), its pose, its photo and the plan's newest brain surface.
/// ApiError naming `ctx`: 404 for an unknown registration_id; 409 for no registration, a
/// failed one, its photo missing, or no surface (the hints in parentheses say what to run);
/// 500 for a stored pose that does not parse.
struct RegisteredView {
    cf::db::RegistrationRecord reg;
    cf::db::PhotoRecord photo;
    Pose T_camera_from_world;
    cf::db::ResultRecord surface;
};
RegisteredView registered_view(const cf::db::CaseRecord& rec, std::optional<std::int64_t> registration_id, const std::string& ctx,
                               const std::string& register_hint, const std::string& surface_hint);
/// A case folder named relative to `cases_root` ("phantom/case_0000"): parts of
/// [A-Za-z0-9_.-], no '..', must hold a case.json. ApiError 400 / 404 naming `field`.
std::filesystem::path case_dir_from_name(const std::filesystem::path& cases_root, const nlohmann::json& v, const std::string& field);
/// A numeric path parameter ("id", "photo_id", ...): 400 naming it when not a number.
std::int64_t case_id_param(const Request& r, const char* key = "id");
nlohmann::json case_summary_json(const cf::db::CaseSummary& s);
nlohmann::json case_record_json(const cf::db::CaseRecord& r);

/// `cases_dir`: folders that POST /api/cases/import may name (relative, checked).
/// `work_dir`: scratch space for staged imports.
void register_case_endpoints(EndpointRegistry& reg, cf::db::CaseStore& store, const std::filesystem::path& cases_dir,
                             const std::filesystem::path& work_dir, int session_ttl_s);

/// The data of a case (case_data_api.cpp, docs/api/case-data.md): volume and photo uploads
/// (raw bodies up to `max_upload_bytes`, read by core before they are stored), landmarks, ROI,
/// registrations, result downloads, zip export and import. Scratch files go to `work_dir`.
void register_case_data_endpoints(EndpointRegistry& reg, cf::db::CaseStore& store, const std::filesystem::path& work_dir,
                                  std::int64_t max_upload_bytes);

}  // namespace cf::daemon
