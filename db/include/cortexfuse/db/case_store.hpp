#pragma once
// The case store: one folder holding `cortexfuse.sqlite` (SQLite, WAL) and `blobs/` (the
// content-addressed files, see blob_store.hpp). Cases, patients' identifiers, volumes,
// photos, landmarks, ROIs, registrations with their parameters, result files, users,
// sessions and the append-only audit log. docs/case-store.md describes schema and guarantees.
//
// Durability: every method that changes something returns only after its transaction has
// committed with synchronous=FULL (and its blobs were fsync'ed and renamed into place before
// the commit). Once it returns, the change survives a SIGKILL of the process and a power cut;
// if it throws, nothing of it is visible (an unreferenced blob may remain, which is harmless).
//
// Thread contract: a CaseStore owns one SQLite connection and serialises its own calls with a
// mutex, so one instance may be shared by the daemon's threads (calls then run one at a time).
// For concurrent reads, open one CaseStore per thread on the same folder: WAL lets readers run
// while one writer commits; writers take the lock with BEGIN IMMEDIATE and wait up to
// busy_timeout before throwing StoreError(Busy). Several processes may open the same folder.
//
// Privacy: patient names, MRNs and birth dates are stored in `patients` only; they never
// appear in error messages or in the audit log's details (which name ids), and this layer logs
// nothing.
//
// Errors: StoreError (error.hpp) with a kind; messages name the thing and the problem.
#include <array>
#include <chrono>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <memory>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "cortexfuse/db/blob_store.hpp"
#include "cortexfuse/db/error.hpp"

namespace cf::db {

// ---- time ------------------------------------------------------------------------------------
using UtcTime = std::chrono::sys_time<std::chrono::milliseconds>;
/// Where "now" comes from (injected in tests; the system clock by default).
using UtcClock = std::function<UtcTime()>;
UtcTime system_now_utc();
/// "2026-11-22T14:50:00.000Z"; parse_utc throws StoreError(Invalid) naming the text.
std::string format_utc(UtcTime t);
UtcTime parse_utc(std::string_view text);

// ---- enumerations (stored as the strings to_string gives) -----------------------------------
/// The workflow of a case. set_state moves forward one step at a time, or back to any earlier
/// step (redo); results of earlier runs are kept.
enum class CaseState { created, planned, patient_registered, photo_captured, landmarks, roi, registered, reviewed };
enum class Modality { T1, CT, fMRI, mask };
enum class Role { surgeon, technician, reviewer, admin };
enum class RegistrationStatus { succeeded, failed, cancelled };

const char* to_string(CaseState s);  ///< "new", "planned", ... (created is "new")
const char* to_string(Modality m);   ///< "T1", "CT", "fMRI", "mask"
const char* to_string(Role r);       ///< "surgeon", ...
const char* to_string(RegistrationStatus s);
/// Throw StoreError(Invalid) naming the text and the accepted values.
CaseState case_state_from_string(std::string_view s);
Modality modality_from_string(std::string_view s);
Role role_from_string(std::string_view s);
RegistrationStatus registration_status_from_string(std::string_view s);

/// Who does something: written to the audit log with every change.
struct Actor {
    std::string name = "system";          ///< a user name, "kiosk", "system"
    std::optional<std::int64_t> user_id;  ///< users.id when a logged-in user
};

// ---- records ---------------------------------------------------------------------------------
struct PatientInput {
    std::string mrn;          ///< medical record number, 1..64 characters, unique in the store
    std::string family_name;  ///< required
    std::string given_name;
    std::optional<std::string> birth_date;  ///< "YYYY-MM-DD"
};
struct Patient : PatientInput {
    std::int64_t id = 0;
    UtcTime created_utc{};
};

struct CaseSummary {
    std::int64_t id = 0;
    std::string uid;  ///< 32 hex digits, random, kept when the case moves to another store
    std::optional<std::int64_t> patient_id;
    std::string title;
    CaseState state = CaseState::created;
    UtcTime created_utc{}, updated_utc{};
};

struct VolumeRecord {
    std::int64_t id = 0, case_id = 0;
    Modality modality = Modality::T1;
    std::string original_name;  ///< the imported file's name (keeps its extension: .nii.gz, ...)
    BlobRef blob;
    UtcTime created_utc{};
};

struct PhotoRecord {
    std::int64_t id = 0, case_id = 0;
    std::string original_name;
    BlobRef blob;
    nlohmann::json intrinsics;  ///< case-format.md "camera": width, height, fx, fy, cx, cy, distortion
    UtcTime created_utc{};
};

struct LandmarkPoint {
    std::string name;                 ///< the label ("L1"); unique within a set
    std::array<double, 3> world_mm{}; ///< LPS mm
    std::array<double, 2> pixel{};    ///< OpenCV pixel (u, v) in the photo
    bool operator==(const LandmarkPoint&) const = default;
};
struct LandmarkSet {
    std::int64_t id = 0, case_id = 0;
    int revision = 0;  ///< 1, 2, ... per case; set_landmarks adds one
    std::optional<std::int64_t> photo_id;
    std::vector<LandmarkPoint> points;
    UtcTime created_utc{};
};

struct RoiRecord {
    std::int64_t id = 0, case_id = 0;
    int revision = 0;
    std::optional<std::int64_t> photo_id;
    nlohmann::json roi;  ///< case-format.md roi.json: {"type":"closed-cardinal-spline","tension":t,"points":[[u,v],...]}
    UtcTime created_utc{};
};

/// A file to store: `file` when not empty, else `bytes`.
struct ResultInput {
    std::string kind;        ///< "fused_png", "mesh", "overlay", ... (1..64 characters)
    std::string name;        ///< file name for export ("fused_0.png"); no folders
    std::string media_type;  ///< "image/png", "model/gltf-binary", ...
    std::filesystem::path file;
    std::string bytes;
    nlohmann::json params = nlohmann::json::object();  ///< what produced it
};
struct ResultRecord {
    std::int64_t id = 0, case_id = 0;
    std::optional<std::int64_t> registration_id;
    std::string kind, name, media_type;
    BlobRef blob;
    nlohmann::json params;
    UtcTime created_utc{};
};

/// One registration run as the engine reported it (core's result_to_json pieces).
struct RegistrationInput {
    std::optional<std::int64_t> volume_id, photo_id, landmark_set_id, roi_id;  ///< what it used (this case's)
    RegistrationStatus status = RegistrationStatus::succeeded;
    nlohmann::json params = nlohmann::json::object();  ///< to_json(RegistrationParams), stage lists included
    std::optional<nlohmann::json> initial_pose, final_pose;  ///< {"T_camera_from_world": 4x4} or the 4x4 itself
    std::optional<double> nmi, seconds;
    std::optional<int> evaluations;
    nlohmann::json stages = nlohmann::json::array();  ///< per-stage reports (name, evaluations, seconds, ...)
    std::optional<std::string> error;                 ///< why it failed
    std::vector<ResultInput> results;                 ///< files stored in the same transaction
};
struct RegistrationRecord {
    std::int64_t id = 0, case_id = 0;
    std::optional<std::int64_t> volume_id, photo_id, landmark_set_id, roi_id;
    RegistrationStatus status = RegistrationStatus::succeeded;
    nlohmann::json params;
    std::optional<nlohmann::json> initial_pose, final_pose;
    std::optional<double> nmi, seconds;
    std::optional<int> evaluations;
    nlohmann::json stages;
    std::optional<std::string> error;
    std::vector<ResultRecord> results;  ///< its result files
    UtcTime created_utc{};
};

/// A case with everything it holds. `landmarks` and `roi` are the latest revisions;
/// registrations and results are all of them, oldest first.
struct CaseRecord {
    CaseSummary summary;
    std::optional<Patient> patient;
    std::vector<VolumeRecord> volumes;
    std::vector<PhotoRecord> photos;
    std::optional<LandmarkSet> landmarks;
    std::optional<RoiRecord> roi;
    std::vector<RegistrationRecord> registrations;
    std::vector<ResultRecord> results;  ///< every result, registration-linked ones included
};

struct CaseQuery {
    std::string text;  ///< matches title, uid, MRN, patient family/given name (case-insensitive substring)
    std::optional<CaseState> state;
    enum class Sort { updated_desc, updated_asc, created_desc, created_asc, title_asc, title_desc };
    Sort sort = Sort::updated_desc;
    int limit = 100;  ///< 1..10000
    int offset = 0;
};

struct User {
    std::int64_t id = 0;
    std::string name;
    Role role = Role::reviewer;
    UtcTime created_utc{};
    bool disabled = false;
};

struct Session {
    std::int64_t id = 0;
    std::string token;  ///< only filled by create_session: 64 hex digits; only its hash is stored
    User user;
    UtcTime created_utc{}, expires_utc{};
};

struct AuditEntry {
    std::int64_t id = 0;
    UtcTime at_utc{};
    std::string actor;
    std::optional<std::int64_t> user_id;
    std::string action;
    std::optional<std::int64_t> case_id;
    nlohmann::json details;
};

/// A draft: unsaved edits of one screen kept for one owner (docs/case-store.md "Drafts").
/// Not a revision: one per (case, kind, owner), replaced by each keep, gone once dropped.
struct DraftRecord {
    std::int64_t case_id = 0;
    std::string kind;   ///< "marks" (Photo & marks: landmarks and ROI)
    std::string owner;  ///< "kiosk", or "user:ID" for a logged-in user
    std::optional<std::int64_t> user_id;
    nlohmann::json body;    ///< the edits as the client sent them (a JSON object)
    UtcTime saved_utc{};    ///< when the client made the edit (its clock)
    UtcTime updated_utc{};  ///< when the store kept it
};
/// The largest draft body kept (its compact JSON, bytes).
inline constexpr std::size_t kMaxDraftBytes = 512 * 1024;

struct IntegrityReport {
    bool ok = true;
    std::vector<std::string> problems;  ///< one line each: integrity_check, foreign keys, blobs
    std::int64_t blobs_checked = 0;
};

struct StoreOptions {
    UtcClock now_utc = system_now_utc;
    int busy_timeout_ms = 5000;  ///< 0..600000
    /// argon2id cost for new password hashes (libsodium's INTERACTIVE limits by default; tests
    /// lower them). Verification always uses the cost stored in the hash.
    unsigned long long pwhash_opslimit = 2;
    std::size_t pwhash_memlimit_bytes = 64u << 20;
    /// Refuse imports (zip entries, case folders) larger than this in total.
    std::int64_t max_import_bytes = std::int64_t{16} << 30;
};

class CaseStore {
public:
    /// Opens the store in `dir` (created with its database and blobs/ when missing), applies
    /// pending migrations. Throws StoreError: Incompatible for a database from a newer
    /// CortexFuse, Corrupt for a file that is not a database, Io, Invalid for bad options.
    static std::unique_ptr<CaseStore> open(const std::filesystem::path& dir, StoreOptions options = {});
    ~CaseStore();
    CaseStore(const CaseStore&) = delete;
    CaseStore& operator=(const CaseStore&) = delete;

    const std::filesystem::path& dir() const;
    std::filesystem::path database_path() const;
    int schema_version() const;
    static int latest_schema_version();
    const BlobStore& blobs() const;

    // -- patients and cases --
    Patient create_patient(const PatientInput& p, const Actor& by = {});
    Patient get_patient(std::int64_t id);
    std::optional<Patient> find_patient_by_mrn(const std::string& mrn);
    CaseSummary create_case(std::optional<std::int64_t> patient_id, const std::string& title, const Actor& by = {});
    std::vector<CaseSummary> list_cases(const CaseQuery& q = {});
    CaseRecord get_case(std::int64_t case_id);
    std::optional<std::int64_t> find_case_by_uid(const std::string& uid);
    /// Forward one step, or back to any earlier step; otherwise StoreError(Conflict).
    CaseSummary set_state(std::int64_t case_id, CaseState state, const Actor& by = {});

    // -- data of a case (each call one transaction; blobs written before it) --
    VolumeRecord import_volume(std::int64_t case_id, const std::filesystem::path& file, Modality m, const Actor& by = {});
    VolumeRecord import_volume_bytes(std::int64_t case_id, std::string_view bytes, const std::string& original_name,
                                     Modality m, const Actor& by = {});
    PhotoRecord add_photo(std::int64_t case_id, const std::filesystem::path& file, const nlohmann::json& intrinsics,
                          const Actor& by = {});
    PhotoRecord add_photo_bytes(std::int64_t case_id, std::string_view bytes, const std::string& original_name,
                                const nlohmann::json& intrinsics, const Actor& by = {});
    /// A new revision; 0..1000 points, unique non-empty names, finite numbers.
    LandmarkSet set_landmarks(std::int64_t case_id, const std::vector<LandmarkPoint>& points,
                              std::optional<std::int64_t> photo_id = std::nullopt, const Actor& by = {});
    std::vector<LandmarkSet> landmark_history(std::int64_t case_id);  ///< every revision, oldest first
    RoiRecord set_roi(std::int64_t case_id, const nlohmann::json& roi, std::optional<std::int64_t> photo_id = std::nullopt,
                      const Actor& by = {});
    std::vector<RoiRecord> roi_history(std::int64_t case_id);
    /// The registration row and its result files in one transaction.
    RegistrationRecord add_registration(std::int64_t case_id, const RegistrationInput& r, const Actor& by = {});
    ResultRecord add_result(std::int64_t case_id, std::optional<std::int64_t> registration_id, const ResultInput& r,
                            const Actor& by = {});
    /// Several result files and, when `advance_to` is later than the case's state, the state
    /// moved to it, in ONE transaction (blobs written before it): every row or none (a plan's
    /// files are one revision). `after_row(i)`, when given, runs inside the transaction after
    /// row i is inserted (progress; a throw there rolls every row back and is rethrown).
    /// Results in the order given.
    std::vector<ResultRecord> add_results(std::int64_t case_id, const std::vector<ResultInput>& rs,
                                          std::optional<CaseState> advance_to = std::nullopt, const Actor& by = {},
                                          const std::function<void(std::size_t)>& after_row = {});

    /// Verified content of a blob this store holds (StoreError Corrupt naming the file).
    std::string read_blob(const std::string& sha256) const;
    /// Verified copy of a blob to `dest` (e.g. a volume under its original name for a reader).
    void copy_blob_to(const std::string& sha256, const std::filesystem::path& dest) const;

    // -- drafts (unsaved edits; not revisions, not exported, the case's updated_utc untouched) --
    /// The owner's draft of `kind` for the case, or nullopt. NotFound for an unknown case.
    std::optional<DraftRecord> get_draft(std::int64_t case_id, const std::string& kind, const std::string& owner);
    /// Keeps `body` (a JSON object of at most kMaxDraftBytes) as the owner's draft, replacing
    /// the one there. Audited `draft.keep` (with `audit_details`) only when there was none:
    /// updates are not changes of the case. Returns true when it was new. One transaction.
    bool keep_draft(std::int64_t case_id, const std::string& kind, const std::string& owner, const nlohmann::json& body,
                    UtcTime saved_utc, const Actor& by = {}, const nlohmann::json& audit_details = nlohmann::json::object());
    /// Removes the owner's draft; audited `draft.drop` with `reason` ("saved" or "discarded")
    /// when there was one. Returns whether there was one. NotFound for an unknown case.
    bool drop_draft(std::int64_t case_id, const std::string& kind, const std::string& owner, const std::string& reason,
                    const Actor& by = {});

    // -- users and sessions --
    /// name: 1..64 of [A-Za-z0-9._-]; password: 8..1024 bytes. Conflict when the name is taken.
    User create_user(const std::string& name, const std::string& password, Role role, const Actor& by = {});
    std::vector<User> list_users();
    User get_user(std::int64_t id);
    /// The user when the name exists, is not disabled and the password matches; nullopt
    /// otherwise (the same time is spent for an unknown name).
    std::optional<User> verify_password(const std::string& name, const std::string& password);
    void set_password(std::int64_t user_id, const std::string& password, const Actor& by = {});
    void set_user_disabled(std::int64_t user_id, bool disabled, const Actor& by = {});  ///< also revokes sessions
    /// ttl: 1 s .. 30 days.
    Session create_session(std::int64_t user_id, std::chrono::seconds ttl);
    /// The session when the token is known, not revoked, not expired at now_utc() and its
    /// user not disabled; nullopt otherwise. `token` is never stored, only its BLAKE2b hash.
    std::optional<Session> check_session(const std::string& token);
    void revoke_session(const std::string& token);

    // -- audit --
    /// Appends one entry (e.g. "case.view" by the daemon). details: a JSON object, no patient names.
    AuditEntry audit(const Actor& by, const std::string& action, std::optional<std::int64_t> case_id,
                     const nlohmann::json& details = nlohmann::json::object());
    /// A case's entries (or all when case_id is nullopt), oldest first, at most `limit`.
    std::vector<AuditEntry> audit_trail(std::optional<std::int64_t> case_id, int limit = 10000);

    // -- moving a case (docs/case-store.md "Import and export") --
    /// Writes the case as a case folder (case.json + store.json + files) into `out_dir`, which
    /// must not exist (it is written beside and renamed into place). Blobs are verified.
    void export_case_folder(std::int64_t case_id, const std::filesystem::path& out_dir, const Actor& by = {});
    /// The same content as a .zip at `zip_path` (written beside and renamed into place).
    void export_case_zip(std::int64_t case_id, const std::filesystem::path& zip_path, const Actor& by = {});
    /// Imports a folder written by export_case_folder (store.json: everything, same uid) or a
    /// plain case folder (case.json only: a new case). Everything is checked before anything is
    /// stored; then blobs, then one transaction. Returns the new case id.
    std::int64_t import_case_folder(const std::filesystem::path& dir, const Actor& by = {});
    /// A .zip of such a folder (at its root or in one top folder). Bad archives (truncated,
    /// entries leaving the folder, too big) are refused with nothing stored.
    std::int64_t import_case_zip(const std::filesystem::path& zip_path, const Actor& by = {});

    // -- checks --
    /// PRAGMA integrity_check, foreign_key_check, and (verify_blobs) every referenced blob.
    IntegrityReport check_integrity(bool verify_blobs = true);
    /// Removes what a crash or a refused import can leave behind: blobs no row names, blob
    /// temporaries and zip-import scratch folders, each only when older than `min_age` (so an
    /// import in flight in another process keeps its blobs). Returns how many were removed.
    std::int64_t remove_unreferenced_blobs(std::chrono::seconds min_age = std::chrono::hours(1));

    struct Impl;

private:
    explicit CaseStore(std::unique_ptr<Impl> impl);
    std::int64_t import_folder(const std::filesystem::path& dir, const Actor& by, const std::string& title_hint);
    std::unique_ptr<Impl> impl_;
};

}  // namespace cf::db
