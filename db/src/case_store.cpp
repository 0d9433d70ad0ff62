#include <sodium.h>

#include <set>

#include "migrations.hpp"
#include "store_impl.hpp"

namespace cf::db {

namespace fs = std::filesystem;
using K = StoreError::Kind;
using nlohmann::json;

namespace {

const char* kDbName = "cortexfuse.sqlite";

json parse_json_column(const std::string& text, const std::string& what) {
    try {
        return json::parse(text);
    } catch (const json::exception&) {
        throw StoreError(K::Corrupt, what + ": stored JSON does not parse");
    }
}

std::optional<json> opt_json(const std::optional<std::string>& t, const std::string& what) {
    if (!t) return std::nullopt;
    return parse_json_column(*t, what);
}

std::string case_name(std::int64_t id) { return "case " + std::to_string(id); }

}  // namespace

// ---- open ---------------------------------------------------------------------------------------

CaseStore::CaseStore(std::unique_ptr<Impl> impl) : impl_(std::move(impl)) {}
CaseStore::~CaseStore() = default;

std::unique_ptr<CaseStore> CaseStore::open(const fs::path& dir, StoreOptions options) {
    if (!options.now_utc) throw StoreError(K::Invalid, "store options: now_utc must be set");
    if (options.busy_timeout_ms < 0 || options.busy_timeout_ms > 600000)
        throw StoreError(K::Invalid, "store options: busy_timeout_ms must be 0..600000");
    if (options.pwhash_opslimit < crypto_pwhash_OPSLIMIT_MIN || options.pwhash_memlimit_bytes < crypto_pwhash_MEMLIMIT_MIN)
        throw StoreError(K::Invalid, "store options: argon2id limits below libsodium's minimum");
    if (sodium_init() < 0) throw StoreError(K::Io, "libsodium: initialisation failed");
    std::error_code ec;
    fs::create_directories(dir, ec);
    if (ec) throw StoreError(K::Io, dir.string() + ": cannot create the store folder: " + ec.message());
    if (!fs::is_directory(dir)) throw StoreError(K::Invalid, dir.string() + ": not a folder");
    const fs::path abs = fs::absolute(dir);
    const fs::path dbpath = abs / kDbName;
    sql::Db db(dbpath.string());
    const std::string what = dbpath.string();
    int version = 0;
    try {
    sqlite3_busy_timeout(db.get(), options.busy_timeout_ms);
    // journal_mode=WAL is persistent in the file; the others are per connection.
    // synchronous=FULL: in WAL mode NORMAL already survives a killed process (the WAL is in the
    // OS cache) but may lose the last commits on power loss; FULL fsyncs the WAL at each commit,
    // so a confirmed write also survives a power cut. The cost is one fsync per write.
    {
        auto st = db.prepare("PRAGMA journal_mode=WAL");
        st.context(what + ": switching to WAL");
        if (!st.step() || st.text(0) != "wal")
            throw StoreError(K::Io, what + ": cannot switch the database to WAL mode");
    }
    db.exec("PRAGMA synchronous=FULL; PRAGMA foreign_keys=ON;", what + ": setting pragmas");
    version = detail::migrate(db, detail::embedded_migrations(), what);
    } catch (const StoreError& e) {
        // Name the database in every message ("file is not a database" alone says too little).
        if (std::string(e.what()).find(what) != std::string::npos) throw;
        throw StoreError(e.kind(), what + ": " + e.what());
    }
    BlobStore blobs(abs / "blobs");
    auto impl = std::make_unique<Impl>(abs, std::move(options), std::move(db), std::move(blobs));
    impl->version = version;
    return std::unique_ptr<CaseStore>(new CaseStore(std::move(impl)));
}

const fs::path& CaseStore::dir() const { return impl_->dir; }
fs::path CaseStore::database_path() const { return impl_->dir / kDbName; }
int CaseStore::schema_version() const { return impl_->version; }
int CaseStore::latest_schema_version() { return static_cast<int>(detail::embedded_migrations().size()); }
const BlobStore& CaseStore::blobs() const { return impl_->blobs; }

// ---- Impl helpers -----------------------------------------------------------------------------

CaseSummary CaseStore::Impl::summary(std::int64_t id) {
    auto st = db.prepare("SELECT id, uid, patient_id, title, state, created_utc, updated_utc FROM cases WHERE id = ?");
    st.bind(1, id);
    if (!st.step()) throw StoreError(K::NotFound, case_name(id) + ": no such case");
    CaseSummary c;
    c.id = st.i64(0);
    c.uid = st.text(1);
    c.patient_id = st.opt_i64(2);
    c.title = st.text(3);
    c.state = case_state_from_string(st.text(4));
    c.created_utc = parse_utc(st.text(5));
    c.updated_utc = parse_utc(st.text(6));
    return c;
}

void CaseStore::Impl::touch(std::int64_t case_id, const std::string& at) {
    db.prepare("UPDATE cases SET updated_utc = ? WHERE id = ?").bind(1, at).bind(2, case_id).run();
}

void CaseStore::Impl::audit_row(const Actor& by, const std::string& action, std::optional<std::int64_t> case_id,
                                const json& details, const std::string& at) {
    if (by.name.empty() || by.name.size() > 64) throw StoreError(K::Invalid, "audit: actor name must be 1..64 characters");
    if (action.empty() || action.size() > 64) throw StoreError(K::Invalid, "audit: action must be 1..64 characters");
    if (!details.is_object()) throw StoreError(K::Invalid, "audit: details must be a JSON object");
    db.prepare("INSERT INTO audit_log (at_utc, actor, user_id, action, case_id, details_json) VALUES (?,?,?,?,?,?)")
        .bind(1, at)
        .bind(2, by.name)
        .bind(3, by.user_id)
        .bind(4, action)
        .bind(5, case_id)
        .bind(6, details.dump())
        .run();
}

void CaseStore::Impl::require_in_case(const char* table, const char* what, std::int64_t id, std::int64_t case_id) {
    auto st = db.prepare(std::string("SELECT case_id FROM ") + table + " WHERE id = ?");
    st.bind(1, id);
    if (!st.step()) throw StoreError(K::NotFound, std::string(what) + " " + std::to_string(id) + ": no such " + what);
    if (st.i64(0) != case_id)
        throw StoreError(K::Invalid, std::string(what) + " " + std::to_string(id) + ": belongs to case " +
                                         std::to_string(st.i64(0)) + ", not to " + case_name(case_id));
}

std::optional<Patient> CaseStore::Impl::patient(std::int64_t id) {
    auto st = db.prepare("SELECT id, mrn, family_name, given_name, birth_date, created_utc FROM patients WHERE id = ?");
    st.bind(1, id);
    if (!st.step()) return std::nullopt;
    Patient p;
    p.id = st.i64(0);
    p.mrn = st.text(1);
    p.family_name = st.text(2);
    p.given_name = st.text(3);
    p.birth_date = st.opt_text(4);
    p.created_utc = parse_utc(st.text(5));
    return p;
}

std::vector<VolumeRecord> CaseStore::Impl::volumes(std::int64_t case_id) {
    auto st = db.prepare("SELECT id, modality, original_name, sha256, size_bytes, created_utc FROM volumes "
                         "WHERE case_id = ? ORDER BY id");
    st.bind(1, case_id);
    std::vector<VolumeRecord> out;
    while (st.step()) {
        VolumeRecord v;
        v.id = st.i64(0);
        v.case_id = case_id;
        v.modality = modality_from_string(st.text(1));
        v.original_name = st.text(2);
        v.blob = blobs.ref(st.text(3), st.i64(4));
        v.created_utc = parse_utc(st.text(5));
        out.push_back(std::move(v));
    }
    return out;
}

std::vector<PhotoRecord> CaseStore::Impl::photos(std::int64_t case_id) {
    auto st = db.prepare("SELECT id, original_name, sha256, size_bytes, intrinsics_json, created_utc FROM photos "
                         "WHERE case_id = ? ORDER BY id");
    st.bind(1, case_id);
    std::vector<PhotoRecord> out;
    while (st.step()) {
        PhotoRecord p;
        p.id = st.i64(0);
        p.case_id = case_id;
        p.original_name = st.text(1);
        p.blob = blobs.ref(st.text(2), st.i64(3));
        p.intrinsics = parse_json_column(st.text(4), "photo " + std::to_string(p.id));
        p.created_utc = parse_utc(st.text(5));
        out.push_back(std::move(p));
    }
    return out;
}

std::vector<LandmarkSet> CaseStore::Impl::landmark_sets(std::int64_t case_id) {
    auto st = db.prepare("SELECT id, revision, photo_id, created_utc FROM landmark_sets WHERE case_id = ? ORDER BY revision");
    st.bind(1, case_id);
    std::vector<LandmarkSet> out;
    while (st.step()) {
        LandmarkSet s;
        s.id = st.i64(0);
        s.case_id = case_id;
        s.revision = static_cast<int>(st.i64(1));
        s.photo_id = st.opt_i64(2);
        s.created_utc = parse_utc(st.text(3));
        out.push_back(std::move(s));
    }
    for (auto& s : out) {
        auto p = db.prepare("SELECT name, world_x_mm, world_y_mm, world_z_mm, pixel_u, pixel_v FROM landmarks "
                            "WHERE set_id = ? ORDER BY idx");
        p.bind(1, s.id);
        while (p.step())
            s.points.push_back(LandmarkPoint{p.text(0), {p.f64(1), p.f64(2), p.f64(3)}, {p.f64(4), p.f64(5)}});
    }
    return out;
}

std::vector<RoiRecord> CaseStore::Impl::rois(std::int64_t case_id) {
    auto st = db.prepare("SELECT id, revision, photo_id, roi_json, created_utc FROM rois WHERE case_id = ? ORDER BY revision");
    st.bind(1, case_id);
    std::vector<RoiRecord> out;
    while (st.step()) {
        RoiRecord r;
        r.id = st.i64(0);
        r.case_id = case_id;
        r.revision = static_cast<int>(st.i64(1));
        r.photo_id = st.opt_i64(2);
        r.roi = parse_json_column(st.text(3), "roi " + std::to_string(r.id));
        r.created_utc = parse_utc(st.text(4));
        out.push_back(std::move(r));
    }
    return out;
}

std::vector<ResultRecord> CaseStore::Impl::results(std::int64_t case_id) {
    auto st = db.prepare("SELECT id, registration_id, kind, name, media_type, sha256, size_bytes, params_json, created_utc "
                         "FROM results WHERE case_id = ? ORDER BY id");
    st.bind(1, case_id);
    std::vector<ResultRecord> out;
    while (st.step()) {
        ResultRecord r;
        r.id = st.i64(0);
        r.case_id = case_id;
        r.registration_id = st.opt_i64(1);
        r.kind = st.text(2);
        r.name = st.text(3);
        r.media_type = st.text(4);
        r.blob = blobs.ref(st.text(5), st.i64(6));
        r.params = parse_json_column(st.text(7), "result " + std::to_string(r.id));
        r.created_utc = parse_utc(st.text(8));
        out.push_back(std::move(r));
    }
    return out;
}

std::vector<RegistrationRecord> CaseStore::Impl::registrations(std::int64_t case_id,
                                                               const std::vector<ResultRecord>& all_results) {
    auto st = db.prepare(
        "SELECT id, volume_id, photo_id, landmark_set_id, roi_id, status, params_json, initial_pose_json, "
        "final_pose_json, nmi, evaluations, seconds, stages_json, error, created_utc FROM registrations "
        "WHERE case_id = ? ORDER BY id");
    st.bind(1, case_id);
    std::vector<RegistrationRecord> out;
    while (st.step()) {
        RegistrationRecord r;
        r.id = st.i64(0);
        const std::string w = "registration " + std::to_string(r.id);
        r.case_id = case_id;
        r.volume_id = st.opt_i64(1);
        r.photo_id = st.opt_i64(2);
        r.landmark_set_id = st.opt_i64(3);
        r.roi_id = st.opt_i64(4);
        r.status = registration_status_from_string(st.text(5));
        r.params = parse_json_column(st.text(6), w);
        r.initial_pose = opt_json(st.opt_text(7), w);
        r.final_pose = opt_json(st.opt_text(8), w);
        if (!st.is_null(9)) r.nmi = st.f64(9);
        if (!st.is_null(10)) r.evaluations = static_cast<int>(st.i64(10));
        if (!st.is_null(11)) r.seconds = st.f64(11);
        r.stages = parse_json_column(st.text(12), w);
        r.error = st.opt_text(13);
        r.created_utc = parse_utc(st.text(14));
        for (const auto& res : all_results)
            if (res.registration_id == r.id) r.results.push_back(res);
        out.push_back(std::move(r));
    }
    return out;
}

CaseRecord CaseStore::Impl::get_case(std::int64_t case_id) {
    CaseRecord c;
    c.summary = summary(case_id);
    if (c.summary.patient_id) c.patient = patient(*c.summary.patient_id);
    c.volumes = volumes(case_id);
    c.photos = photos(case_id);
    auto sets = landmark_sets(case_id);
    if (!sets.empty()) c.landmarks = std::move(sets.back());
    auto rs = rois(case_id);
    if (!rs.empty()) c.roi = std::move(rs.back());
    c.results = results(case_id);
    c.registrations = registrations(case_id, c.results);
    return c;
}

std::int64_t CaseStore::Impl::insert_case(const std::string& uid, std::optional<std::int64_t> patient_id,
                                          const std::string& title, CaseState state, const std::string& created,
                                          const std::string& updated) {
    auto st = db.prepare("INSERT INTO cases (uid, patient_id, title, state, created_utc, updated_utc) VALUES (?,?,?,?,?,?)");
    st.bind(1, uid).bind(2, patient_id).bind(3, title).bind(4, to_string(state)).bind(5, created).bind(6, updated);
    st.context("case " + uid).run();
    return db.last_id();
}

std::int64_t CaseStore::Impl::insert_volume(std::int64_t case_id, Modality m, const std::string& name, const BlobRef& b,
                                            const std::string& at) {
    db.prepare("INSERT INTO volumes (case_id, modality, original_name, sha256, size_bytes, created_utc) VALUES (?,?,?,?,?,?)")
        .bind(1, case_id).bind(2, to_string(m)).bind(3, name).bind(4, b.sha256).bind(5, b.size_bytes).bind(6, at)
        .run();
    return db.last_id();
}

std::int64_t CaseStore::Impl::insert_photo(std::int64_t case_id, const std::string& name, const BlobRef& b,
                                           const json& intrinsics, const std::string& at) {
    db.prepare("INSERT INTO photos (case_id, original_name, sha256, size_bytes, intrinsics_json, created_utc) "
               "VALUES (?,?,?,?,?,?)")
        .bind(1, case_id).bind(2, name).bind(3, b.sha256).bind(4, b.size_bytes).bind(5, intrinsics.dump()).bind(6, at)
        .run();
    return db.last_id();
}

std::int64_t CaseStore::Impl::insert_landmarks(std::int64_t case_id, const std::vector<LandmarkPoint>& pts,
                                               std::optional<std::int64_t> photo_id, const std::string& at,
                                               int* revision_out) {
    auto r = db.prepare("SELECT COALESCE(MAX(revision), 0) + 1 FROM landmark_sets WHERE case_id = ?");
    r.bind(1, case_id);
    r.step();
    const int revision = static_cast<int>(r.i64(0));
    db.prepare("INSERT INTO landmark_sets (case_id, revision, photo_id, created_utc) VALUES (?,?,?,?)")
        .bind(1, case_id).bind(2, revision).bind(3, photo_id).bind(4, at)
        .run();
    const std::int64_t set_id = db.last_id();
    auto ins = db.prepare("INSERT INTO landmarks (set_id, idx, name, world_x_mm, world_y_mm, world_z_mm, pixel_u, pixel_v) "
                          "VALUES (?,?,?,?,?,?,?,?)");
    for (std::size_t i = 0; i < pts.size(); ++i) {
        const auto& p = pts[i];
        ins.reset();
        ins.bind(1, set_id).bind(2, static_cast<std::int64_t>(i)).bind(3, p.name);
        ins.bind(4, p.world_mm[0]).bind(5, p.world_mm[1]).bind(6, p.world_mm[2]).bind(7, p.pixel[0]).bind(8, p.pixel[1]);
        ins.run();
    }
    if (revision_out) *revision_out = revision;
    return set_id;
}

std::int64_t CaseStore::Impl::insert_roi(std::int64_t case_id, const json& roi, std::optional<std::int64_t> photo_id,
                                         const std::string& at, int* revision_out) {
    auto r = db.prepare("SELECT COALESCE(MAX(revision), 0) + 1 FROM rois WHERE case_id = ?");
    r.bind(1, case_id);
    r.step();
    const int revision = static_cast<int>(r.i64(0));
    db.prepare("INSERT INTO rois (case_id, revision, photo_id, roi_json, created_utc) VALUES (?,?,?,?,?)")
        .bind(1, case_id).bind(2, revision).bind(3, photo_id).bind(4, roi.dump()).bind(5, at)
        .run();
    if (revision_out) *revision_out = revision;
    return db.last_id();
}

std::int64_t CaseStore::Impl::insert_registration(std::int64_t case_id, const RegistrationInput& r, const std::string& at) {
    auto st = db.prepare(
        "INSERT INTO registrations (case_id, volume_id, photo_id, landmark_set_id, roi_id, status, params_json, "
        "initial_pose_json, final_pose_json, nmi, evaluations, seconds, stages_json, error, created_utc) "
        "VALUES (?,?,?,?,?,?,?,?,?,?,?,?,?,?,?)");
    st.bind(1, case_id).bind(2, r.volume_id).bind(3, r.photo_id).bind(4, r.landmark_set_id).bind(5, r.roi_id);
    st.bind(6, to_string(r.status)).bind(7, r.params.dump());
    st.bind(8, r.initial_pose ? std::optional<std::string>(r.initial_pose->dump()) : std::nullopt);
    st.bind(9, r.final_pose ? std::optional<std::string>(r.final_pose->dump()) : std::nullopt);
    st.bind(10, r.nmi).bind(11, r.evaluations).bind(12, r.seconds).bind(13, r.stages.dump()).bind(14, r.error).bind(15, at);
    st.run();
    return db.last_id();
}

std::int64_t CaseStore::Impl::insert_result(std::int64_t case_id, std::optional<std::int64_t> registration_id,
                                            const ResultInput& r, const BlobRef& b, const std::string& at) {
    db.prepare("INSERT INTO results (case_id, registration_id, kind, name, media_type, sha256, size_bytes, params_json, "
               "created_utc) VALUES (?,?,?,?,?,?,?,?,?)")
        .bind(1, case_id).bind(2, registration_id).bind(3, r.kind).bind(4, r.name).bind(5, r.media_type)
        .bind(6, b.sha256).bind(7, b.size_bytes).bind(8, r.params.dump()).bind(9, at)
        .run();
    return db.last_id();
}

BlobRef CaseStore::Impl::put(const ResultInput& r) {
    return r.file.empty() ? blobs.put_bytes(r.bytes) : blobs.put_file(r.file);
}

// ---- patients and cases -------------------------------------------------------------------------

Patient CaseStore::create_patient(const PatientInput& in, const Actor& by) {
    if (in.mrn.empty() || in.mrn.size() > 64) throw StoreError(K::Invalid, "patient: MRN must be 1..64 characters");
    if (in.family_name.empty() || in.family_name.size() > 200)
        throw StoreError(K::Invalid, "patient: family name must be 1..200 characters");
    if (in.given_name.size() > 200) throw StoreError(K::Invalid, "patient: given name must be at most 200 characters");
    if (in.birth_date) {
        try {
            (void)parse_utc(*in.birth_date + "T00:00:00.000Z");
        } catch (const StoreError&) {
            throw StoreError(K::Invalid, "patient: birth date must be YYYY-MM-DD");
        }
    }
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    {
        auto st = I.db.prepare("SELECT id FROM patients WHERE mrn = ?");
        st.bind(1, in.mrn);
        if (st.step())
            throw StoreError(K::Conflict, "patient: the MRN is already used by patient " + std::to_string(st.i64(0)));
    }
    I.db.prepare("INSERT INTO patients (mrn, family_name, given_name, birth_date, created_utc) VALUES (?,?,?,?,?)")
        .bind(1, in.mrn).bind(2, in.family_name).bind(3, in.given_name).bind(4, in.birth_date).bind(5, at)
        .context("patient")
        .run();
    const std::int64_t id = I.db.last_id();
    I.audit_row(by, "patient.create", std::nullopt, {{"patient_id", id}}, at);
    tx.commit();
    return *I.patient(id);
}

Patient CaseStore::get_patient(std::int64_t id) {
    std::lock_guard lk(impl_->mu);
    auto p = impl_->patient(id);
    if (!p) throw StoreError(K::NotFound, "patient " + std::to_string(id) + ": no such patient");
    return *p;
}

std::optional<Patient> CaseStore::find_patient_by_mrn(const std::string& mrn) {
    std::lock_guard lk(impl_->mu);
    auto st = impl_->db.prepare("SELECT id FROM patients WHERE mrn = ?");
    st.bind(1, mrn);
    if (!st.step()) return std::nullopt;
    return impl_->patient(st.i64(0));
}

CaseSummary CaseStore::create_case(std::optional<std::int64_t> patient_id, const std::string& title, const Actor& by) {
    if (title.empty() || title.size() > 200) throw StoreError(K::Invalid, "case: title must be 1..200 characters");
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    if (patient_id && !I.patient(*patient_id))
        throw StoreError(K::NotFound, "patient " + std::to_string(*patient_id) + ": no such patient");
    const std::int64_t id = I.insert_case(random_hex(16), patient_id, title, CaseState::created, at, at);
    I.audit_row(by, "case.create", id, {{"case_id", id}}, at);
    tx.commit();
    return I.summary(id);
}

std::vector<CaseSummary> CaseStore::list_cases(const CaseQuery& q) {
    if (q.limit < 1 || q.limit > 10000) throw StoreError(K::Invalid, "case query: limit must be 1..10000");
    if (q.offset < 0) throw StoreError(K::Invalid, "case query: offset must be >= 0");
    if (q.text.size() > 200) throw StoreError(K::Invalid, "case query: text must be at most 200 characters");
    const char* order = "c.updated_utc DESC";
    switch (q.sort) {
        case CaseQuery::Sort::updated_desc: order = "c.updated_utc DESC"; break;
        case CaseQuery::Sort::updated_asc: order = "c.updated_utc ASC"; break;
        case CaseQuery::Sort::created_desc: order = "c.created_utc DESC"; break;
        case CaseQuery::Sort::created_asc: order = "c.created_utc ASC"; break;
        case CaseQuery::Sort::title_asc: order = "c.title COLLATE NOCASE ASC"; break;
        case CaseQuery::Sort::title_desc: order = "c.title COLLATE NOCASE DESC"; break;
    }
    std::string like = "%";
    for (char ch : q.text) {
        if (ch == '%' || ch == '_' || ch == '\\') like += '\\';
        like += ch;
    }
    like += '%';
    std::lock_guard lk(impl_->mu);
    auto st = impl_->db.prepare(
        std::string("SELECT c.id FROM cases c LEFT JOIN patients p ON p.id = c.patient_id "
                    "WHERE (?1 = '' OR c.title LIKE ?2 ESCAPE '\\' OR c.uid LIKE ?2 ESCAPE '\\' OR p.mrn LIKE ?2 ESCAPE '\\' "
                    "OR p.family_name LIKE ?2 ESCAPE '\\' OR p.given_name LIKE ?2 ESCAPE '\\') "
                    "AND (?3 IS NULL OR c.state = ?3) ORDER BY ") +
        order + ", c.id LIMIT ?4 OFFSET ?5");
    st.bind(1, q.text).bind(2, like);
    if (q.state) st.bind(3, to_string(*q.state));
    else st.bind(3, nullptr);
    st.bind(4, q.limit).bind(5, q.offset);
    std::vector<std::int64_t> ids;
    while (st.step()) ids.push_back(st.i64(0));
    std::vector<CaseSummary> out;
    for (auto id : ids) out.push_back(impl_->summary(id));
    return out;
}

CaseRecord CaseStore::get_case(std::int64_t case_id) {
    std::lock_guard lk(impl_->mu);
    // One read transaction: a consistent snapshot even while another connection writes.
    impl_->db.exec("BEGIN", "reading " + case_name(case_id));
    try {
        auto c = impl_->get_case(case_id);
        impl_->db.exec("COMMIT", "reading " + case_name(case_id));
        return c;
    } catch (...) {
        sqlite3_exec(impl_->db.get(), "ROLLBACK", nullptr, nullptr, nullptr);
        throw;
    }
}

std::optional<std::int64_t> CaseStore::find_case_by_uid(const std::string& uid) {
    std::lock_guard lk(impl_->mu);
    auto st = impl_->db.prepare("SELECT id FROM cases WHERE uid = ?");
    st.bind(1, uid);
    if (!st.step()) return std::nullopt;
    return st.i64(0);
}

CaseSummary CaseStore::set_state(std::int64_t case_id, CaseState state, const Actor& by) {
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    const auto cur = I.summary(case_id).state;
    if (static_cast<int>(state) > static_cast<int>(cur) + 1)
        throw StoreError(K::Conflict, case_name(case_id) + ": cannot go from '" + to_string(cur) + "' to '" +
                                          to_string(state) + "' (one step forward at a time, or back to redo a step)");
    I.db.prepare("UPDATE cases SET state = ?, updated_utc = ? WHERE id = ?")
        .bind(1, to_string(state)).bind(2, at).bind(3, case_id)
        .run();
    I.audit_row(by, "case.state", case_id, {{"from", to_string(cur)}, {"to", to_string(state)}}, at);
    tx.commit();
    return I.summary(case_id);
}

// ---- data of a case ----------------------------------------------------------------------------

namespace {
std::string base_name_of(const fs::path& file) { return file.filename().string(); }
}  // namespace

VolumeRecord CaseStore::import_volume(std::int64_t case_id, const fs::path& file, Modality m, const Actor& by) {
    const std::string name = base_name_of(file);
    validate_file_name(name, "volume " + file.string());
    {
        std::lock_guard lk(impl_->mu);
        impl_->require_case(case_id);
    }
    const BlobRef b = impl_->blobs.put_file(file);  // outside the lock: may be large; blobs are race-free
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.require_case(case_id);
    const auto id = I.insert_volume(case_id, m, name, b, at);
    I.touch(case_id, at);
    I.audit_row(by, "volume.import", case_id, {{"volume_id", id}, {"modality", to_string(m)}, {"sha256", b.sha256}}, at);
    tx.commit();
    for (auto& v : I.volumes(case_id))
        if (v.id == id) return v;
    throw StoreError(K::Corrupt, "volume " + std::to_string(id) + ": vanished after insert");
}

VolumeRecord CaseStore::import_volume_bytes(std::int64_t case_id, std::string_view bytes, const std::string& name,
                                            Modality m, const Actor& by) {
    validate_file_name(name, "volume");
    {
        std::lock_guard lk(impl_->mu);
        impl_->require_case(case_id);
    }
    const BlobRef b = impl_->blobs.put_bytes(bytes);
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.require_case(case_id);
    const auto id = I.insert_volume(case_id, m, name, b, at);
    I.touch(case_id, at);
    I.audit_row(by, "volume.import", case_id, {{"volume_id", id}, {"modality", to_string(m)}, {"sha256", b.sha256}}, at);
    tx.commit();
    for (auto& v : I.volumes(case_id))
        if (v.id == id) return v;
    throw StoreError(K::Corrupt, "volume " + std::to_string(id) + ": vanished after insert");
}

namespace {
PhotoRecord add_photo_impl(CaseStore::Impl& I, std::int64_t case_id, const BlobRef& b, const std::string& name,
                           const json& intrinsics, const Actor& by) {
    std::lock_guard lk(I.mu);
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.require_case(case_id);
    const auto id = I.insert_photo(case_id, name, b, intrinsics, at);
    I.touch(case_id, at);
    I.audit_row(by, "photo.add", case_id, {{"photo_id", id}, {"sha256", b.sha256}}, at);
    tx.commit();
    for (auto& p : I.photos(case_id))
        if (p.id == id) return p;
    throw StoreError(K::Corrupt, "photo " + std::to_string(id) + ": vanished after insert");
}
}  // namespace

PhotoRecord CaseStore::add_photo(std::int64_t case_id, const fs::path& file, const json& intrinsics, const Actor& by) {
    const std::string name = base_name_of(file);
    validate_file_name(name, "photo " + file.string());
    validate_intrinsics(intrinsics, "photo " + name);
    {
        std::lock_guard lk(impl_->mu);
        impl_->require_case(case_id);
    }
    const BlobRef b = impl_->blobs.put_file(file);
    return add_photo_impl(*impl_, case_id, b, name, intrinsics, by);
}

PhotoRecord CaseStore::add_photo_bytes(std::int64_t case_id, std::string_view bytes, const std::string& name,
                                       const json& intrinsics, const Actor& by) {
    validate_file_name(name, "photo");
    validate_intrinsics(intrinsics, "photo " + name);
    {
        std::lock_guard lk(impl_->mu);
        impl_->require_case(case_id);
    }
    const BlobRef b = impl_->blobs.put_bytes(bytes);
    return add_photo_impl(*impl_, case_id, b, name, intrinsics, by);
}

LandmarkSet CaseStore::set_landmarks(std::int64_t case_id, const std::vector<LandmarkPoint>& points,
                                     std::optional<std::int64_t> photo_id, const Actor& by) {
    validate_landmarks(points, case_name(case_id));
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.require_case(case_id);
    if (photo_id) I.require_in_case("photos", "photo", *photo_id, case_id);
    int revision = 0;
    const auto id = I.insert_landmarks(case_id, points, photo_id, at, &revision);
    I.touch(case_id, at);
    I.audit_row(by, "landmarks.set", case_id, {{"landmark_set_id", id}, {"revision", revision}, {"count", points.size()}}, at);
    tx.commit();
    return I.landmark_sets(case_id).back();
}

std::vector<LandmarkSet> CaseStore::landmark_history(std::int64_t case_id) {
    std::lock_guard lk(impl_->mu);
    impl_->require_case(case_id);
    return impl_->landmark_sets(case_id);
}

RoiRecord CaseStore::set_roi(std::int64_t case_id, const json& roi, std::optional<std::int64_t> photo_id, const Actor& by) {
    validate_roi(roi, case_name(case_id) + " ROI");
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.require_case(case_id);
    if (photo_id) I.require_in_case("photos", "photo", *photo_id, case_id);
    int revision = 0;
    const auto id = I.insert_roi(case_id, roi, photo_id, at, &revision);
    I.touch(case_id, at);
    I.audit_row(by, "roi.set", case_id, {{"roi_id", id}, {"revision", revision}}, at);
    tx.commit();
    return I.rois(case_id).back();
}

std::vector<RoiRecord> CaseStore::roi_history(std::int64_t case_id) {
    std::lock_guard lk(impl_->mu);
    impl_->require_case(case_id);
    return impl_->rois(case_id);
}

RegistrationRecord CaseStore::add_registration(std::int64_t case_id, const RegistrationInput& r, const Actor& by) {
    validate_registration_input(r, case_name(case_id) + " registration");
    {
        std::lock_guard lk(impl_->mu);
        impl_->require_case(case_id);
    }
    // Blobs first, durable before the rows that name them.
    std::vector<BlobRef> refs;
    for (const auto& res : r.results) refs.push_back(impl_->put(res));
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.require_case(case_id);
    if (r.volume_id) I.require_in_case("volumes", "volume", *r.volume_id, case_id);
    if (r.photo_id) I.require_in_case("photos", "photo", *r.photo_id, case_id);
    if (r.landmark_set_id) I.require_in_case("landmark_sets", "landmark set", *r.landmark_set_id, case_id);
    if (r.roi_id) I.require_in_case("rois", "roi", *r.roi_id, case_id);
    const auto id = I.insert_registration(case_id, r, at);
    json rids = json::array();
    for (std::size_t i = 0; i < r.results.size(); ++i) rids.push_back(I.insert_result(case_id, id, r.results[i], refs[i], at));
    I.touch(case_id, at);
    I.audit_row(by, "registration.add", case_id,
                {{"registration_id", id}, {"status", to_string(r.status)}, {"result_ids", rids}}, at);
    tx.commit();
    const auto all = I.results(case_id);
    for (auto& reg : I.registrations(case_id, all))
        if (reg.id == id) return reg;
    throw StoreError(K::Corrupt, "registration " + std::to_string(id) + ": vanished after insert");
}

ResultRecord CaseStore::add_result(std::int64_t case_id, std::optional<std::int64_t> registration_id,
                                   const ResultInput& r, const Actor& by) {
    validate_result_input(r, case_name(case_id) + " result");
    {
        std::lock_guard lk(impl_->mu);
        impl_->require_case(case_id);
    }
    const BlobRef b = impl_->put(r);
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.require_case(case_id);
    if (registration_id) I.require_in_case("registrations", "registration", *registration_id, case_id);
    const auto id = I.insert_result(case_id, registration_id, r, b, at);
    I.touch(case_id, at);
    I.audit_row(by, "result.add", case_id, {{"result_id", id}, {"kind", r.kind}, {"sha256", b.sha256}}, at);
    tx.commit();
    for (auto& res : I.results(case_id))
        if (res.id == id) return res;
    throw StoreError(K::Corrupt, "result " + std::to_string(id) + ": vanished after insert");
}

std::vector<ResultRecord> CaseStore::add_results(std::int64_t case_id, const std::vector<ResultInput>& rs,
                                             std::optional<CaseState> advance_to, const Actor& by,
                                             const std::function<void(std::size_t)>& after_row) {
    if (rs.empty()) throw StoreError(K::Invalid, case_name(case_id) + " results: none given");
    for (std::size_t i = 0; i < rs.size(); ++i) validate_result_input(rs[i], case_name(case_id) + " result " + std::to_string(i));
    {
        std::lock_guard lk(impl_->mu);
        impl_->require_case(case_id);
    }
    std::vector<BlobRef> refs;  // content-addressed: a blob without a row is harmless (nothing refers to it)
    refs.reserve(rs.size());
    for (const auto& r : rs) refs.push_back(impl_->put(r));
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.require_case(case_id);
    std::vector<std::int64_t> ids;
    for (std::size_t i = 0; i < rs.size(); ++i) {
        ids.push_back(I.insert_result(case_id, std::nullopt, rs[i], refs[i], at));
        I.audit_row(by, "result.add", case_id, {{"result_id", ids.back()}, {"kind", rs[i].kind}, {"sha256", refs[i].sha256}}, at);
        if (after_row) after_row(i);
    }
    if (advance_to) {
        const auto cur = I.summary(case_id).state;
        if (static_cast<int>(*advance_to) > static_cast<int>(cur)) {
            I.db.prepare("UPDATE cases SET state = ?, updated_utc = ? WHERE id = ?").bind(1, to_string(*advance_to)).bind(2, at).bind(3, case_id).run();
            I.audit_row(by, "case.state", case_id, {{"from", to_string(cur)}, {"to", to_string(*advance_to)}}, at);
        }
    }
    I.touch(case_id, at);
    tx.commit();
    const auto all = I.results(case_id);
    std::vector<ResultRecord> out;
    for (const auto id : ids)
        for (const auto& r : all)
            if (r.id == id) out.push_back(r);
    if (out.size() != ids.size()) throw StoreError(K::Corrupt, case_name(case_id) + " results: vanished after insert");
    return out;
}

std::string CaseStore::read_blob(const std::string& sha256) const { return impl_->blobs.read(sha256); }
void CaseStore::copy_blob_to(const std::string& sha256, const fs::path& dest) const { impl_->blobs.copy_to(sha256, dest); }

// ---- audit ----------------------------------------------------------------------------------------

AuditEntry CaseStore::audit(const Actor& by, const std::string& action, std::optional<std::int64_t> case_id,
                            const json& details) {
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.audit_row(by, action, case_id, details, at);
    const auto id = I.db.last_id();
    tx.commit();
    return AuditEntry{id, parse_utc(at), by.name, by.user_id, action, case_id, details};
}

std::vector<AuditEntry> CaseStore::audit_trail(std::optional<std::int64_t> case_id, int limit) {
    if (limit < 1) throw StoreError(K::Invalid, "audit trail: limit must be >= 1");
    std::lock_guard lk(impl_->mu);
    auto st = impl_->db.prepare(
        "SELECT id, at_utc, actor, user_id, action, case_id, details_json FROM audit_log "
        "WHERE (?1 IS NULL OR case_id = ?1) ORDER BY id LIMIT ?2");
    st.bind(1, case_id).bind(2, limit);
    std::vector<AuditEntry> out;
    while (st.step())
        out.push_back(AuditEntry{st.i64(0), parse_utc(st.text(1)), st.text(2), st.opt_i64(3), st.text(4), st.opt_i64(5),
                                 parse_json_column(st.text(6), "audit entry " + std::to_string(st.i64(0)))});
    return out;
}

// ---- checks -----------------------------------------------------------------------------------------

IntegrityReport CaseStore::check_integrity(bool verify_blobs) {
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    IntegrityReport rep;
    {
        auto st = I.db.prepare("PRAGMA integrity_check");
        while (st.step())
            if (st.text(0) != "ok") rep.problems.push_back("integrity_check: " + st.text(0));
    }
    {
        auto st = I.db.prepare("PRAGMA foreign_key_check");
        while (st.step())
            rep.problems.push_back("foreign key: " + st.text(0) + " row " + std::to_string(st.i64(1)) + " names a missing " +
                                   st.text(2) + " row");
    }
    if (verify_blobs) {
        auto st = I.db.prepare("SELECT 'volume', id, sha256, size_bytes FROM volumes UNION ALL "
                               "SELECT 'photo', id, sha256, size_bytes FROM photos UNION ALL "
                               "SELECT 'result', id, sha256, size_bytes FROM results");
        while (st.step()) {
            ++rep.blobs_checked;
            const std::string what = st.text(0) + " " + std::to_string(st.i64(1));
            try {
                I.blobs.verify(st.text(2));
                std::error_code ec;
                const auto sz = fs::file_size(I.blobs.path_of(st.text(2)), ec);
                if (ec || static_cast<std::int64_t>(sz) != st.i64(3))
                    rep.problems.push_back(what + ": blob size differs from the recorded size");
            } catch (const StoreError& e) {
                rep.problems.push_back(what + ": " + e.what());
            }
        }
    }
    rep.ok = rep.problems.empty();
    return rep;
}

std::int64_t CaseStore::remove_unreferenced_blobs(std::chrono::seconds min_age) {
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    std::set<std::string> referenced;
    {
        auto st = I.db.prepare("SELECT sha256 FROM volumes UNION SELECT sha256 FROM photos UNION SELECT sha256 FROM results");
        while (st.step()) referenced.insert(st.text(0));
    }
    const auto cutoff = fs::file_time_type::clock::now() - min_age;
    std::error_code ec;
    auto old_enough = [&](const fs::path& p) {
        const auto t = fs::last_write_time(p, ec);
        return !ec && t < cutoff;
    };
    std::int64_t removed = 0;
    const fs::path root = I.blobs.root();
    for (const auto& top : fs::directory_iterator(root, ec)) {
        const std::string tn = top.path().filename().string();
        if (tn.rfind(".tmp-", 0) == 0) {
            if (old_enough(top.path()) && fs::remove(top.path(), ec)) ++removed;
            continue;
        }
        if (tn.size() != 2 || !top.is_directory(ec)) continue;
        for (const auto& f : fs::directory_iterator(top.path(), ec)) {
            const std::string sha = tn + f.path().filename().string();
            if (!BlobStore::valid_hash(sha) || referenced.count(sha) || !old_enough(f.path())) continue;
            if (fs::remove(f.path(), ec)) ++removed;
        }
    }
    for (const auto& d : fs::directory_iterator(I.dir / "tmp", ec))
        if (d.path().filename().string().rfind("import-", 0) == 0 && old_enough(d.path()))
            removed += fs::remove_all(d.path(), ec) > 0 ? 1 : 0;
    return removed;
}

}  // namespace cf::db
