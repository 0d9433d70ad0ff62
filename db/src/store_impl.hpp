#pragma once
// CaseStore's private state and the helpers shared by case_store.cpp, users.cpp and case_io.cpp.
// Every helper here expects the caller to hold `mu` (and, for writes, an open sql::Tx).
#include <mutex>

#include "cortexfuse/db/case_store.hpp"
#include "sqlite.hpp"

namespace cf::db {

struct CaseStore::Impl {
    std::filesystem::path dir;
    StoreOptions opt;
    sql::Db db;
    BlobStore blobs;
    int version = 0;
    std::mutex mu;
    std::string dummy_hash;  ///< verify_password's stand-in for unknown names (same cost)

    Impl(std::filesystem::path d, StoreOptions o, sql::Db database, BlobStore b)
        : dir(std::move(d)), opt(std::move(o)), db(std::move(database)), blobs(std::move(b)) {}

    std::string now() { return format_utc(opt.now_utc()); }
    CaseSummary summary(std::int64_t case_id);  ///< NotFound naming the case
    void require_case(std::int64_t case_id) { (void)summary(case_id); }
    void touch(std::int64_t case_id, const std::string& at);
    void audit_row(const Actor& by, const std::string& action, std::optional<std::int64_t> case_id,
                   const nlohmann::json& details, const std::string& at);
    /// NotFound unless `table` row `id` exists, Invalid unless it belongs to `case_id`.
    void require_in_case(const char* table, const char* what, std::int64_t id, std::int64_t case_id);

    std::vector<VolumeRecord> volumes(std::int64_t case_id);
    std::vector<PhotoRecord> photos(std::int64_t case_id);
    std::vector<LandmarkSet> landmark_sets(std::int64_t case_id);
    std::vector<RoiRecord> rois(std::int64_t case_id);
    std::vector<ResultRecord> results(std::int64_t case_id);
    std::vector<RegistrationRecord> registrations(std::int64_t case_id, const std::vector<ResultRecord>& results);
    std::optional<Patient> patient(std::int64_t id);
    CaseRecord get_case(std::int64_t case_id);

    std::int64_t insert_case(const std::string& uid, std::optional<std::int64_t> patient_id, const std::string& title,
                             CaseState state, const std::string& created, const std::string& updated);
    std::int64_t insert_volume(std::int64_t case_id, Modality m, const std::string& name, const BlobRef& b,
                               const std::string& at);
    std::int64_t insert_photo(std::int64_t case_id, const std::string& name, const BlobRef& b,
                              const nlohmann::json& intrinsics, const std::string& at);
    std::int64_t insert_landmarks(std::int64_t case_id, const std::vector<LandmarkPoint>& pts,
                                  std::optional<std::int64_t> photo_id, const std::string& at, int* revision_out);
    std::int64_t insert_roi(std::int64_t case_id, const nlohmann::json& roi, std::optional<std::int64_t> photo_id,
                            const std::string& at, int* revision_out);
    std::int64_t insert_registration(std::int64_t case_id, const RegistrationInput& r, const std::string& at);
    std::int64_t insert_result(std::int64_t case_id, std::optional<std::int64_t> registration_id,
                               const ResultInput& r, const BlobRef& b, const std::string& at);
    BlobRef put(const ResultInput& r);
};

// ---- validation shared by the API and the importers (throw StoreError(Invalid) naming `what`) --
void validate_intrinsics(const nlohmann::json& j, const std::string& what);
void validate_roi(const nlohmann::json& j, const std::string& what);
void validate_landmarks(const std::vector<LandmarkPoint>& pts, const std::string& what);
void validate_file_name(const std::string& name, const std::string& what);
void validate_result_input(const ResultInput& r, const std::string& what);
void validate_registration_input(const RegistrationInput& r, const std::string& what);
std::string random_hex(std::size_t bytes);

}  // namespace cf::db
