// Cases and what they hold: workflow, revisions, registrations with their parameters and
// result files, search, the audit log (append-only), bad inputs refused with nothing stored.
#include <sqlite3.h>

#include "db_test_util.hpp"
#include "sqlite.hpp"

using namespace cf::db;
using namespace cfdbtest;
using nlohmann::json;

namespace {

struct StoreFixture : ::testing::Test {
    TempDir t;
    std::shared_ptr<FakeClock> clock = std::make_shared<FakeClock>();
    std::unique_ptr<CaseStore> s = CaseStore::open(t.path / "store", fast_options(clock));

    std::size_t audit_count() { return s->audit_trail(std::nullopt).size(); }
};

RegistrationInput sample_registration(std::int64_t volume_id, std::int64_t photo_id, double nmi) {
    RegistrationInput r;
    r.volume_id = volume_id;
    r.photo_id = photo_id;
    r.params = {{"transfer_function", "surface_white"}, {"bins", 32},
                {"search_stages", {{{"name", "coarse"}, {"fwhm_mm", 8}, {"step_mm", 10}}}},
                {"final_stages", {{{"name", "fine"}, {"fwhm_mm", 2}, {"step_mm", 3}}}}};
    r.initial_pose = json{{"T_camera_from_world", {{1, 0, 0, 0}, {0, 1, 0, 0}, {0, 0, 1, 300}, {0, 0, 0, 1}}}};
    r.final_pose = json{{"T_camera_from_world", {{1, 0, 0, 1.5}, {0, 1, 0, -2}, {0, 0, 1, 302}, {0, 0, 0, 1}}}};
    r.nmi = nmi;
    r.evaluations = 812;
    r.seconds = 1.7;
    r.stages = json::array({{{"name", "coarse"}, {"best_nmi", 1.1}, {"evaluations", 300}, {"seconds", 0.6}}});
    r.results.push_back(ResultInput{"fused_png", "fused_0.png", "image/png", {}, "\x89PNG fake " + std::to_string(nmi), {{"view", 0}}});
    return r;
}

}  // namespace

TEST_F(StoreFixture, PatientCaseAndEverythingItHolds) {
    const auto p = s->create_patient({"MRN-0042", "Doe", "Jane", "1970-03-14"});
    EXPECT_EQ(s->get_patient(p.id).family_name, "Doe");
    EXPECT_EQ(s->find_patient_by_mrn("MRN-0042")->id, p.id);
    EXPECT_FALSE(s->find_patient_by_mrn("MRN-0043"));
    const auto c = s->create_case(p.id, "Left frontal tumour");
    EXPECT_EQ(c.state, CaseState::created);
    EXPECT_EQ(c.uid.size(), 32u);
    EXPECT_EQ(s->find_case_by_uid(c.uid), c.id);

    clock->advance(std::chrono::seconds(5));
    const auto v = s->import_volume_bytes(c.id, "NIFTI-bytes", "t1.nii.gz", Modality::T1);
    EXPECT_EQ(v.blob.sha256, BlobStore::sha256_of("NIFTI-bytes"));
    EXPECT_EQ(v.original_name, "t1.nii.gz");
    write_file(t.path / "photo.png", "PNG-bytes");
    const auto ph = s->add_photo(c.id, t.path / "photo.png", camera_json());
    EXPECT_EQ(ph.original_name, "photo.png");
    const auto l1 = s->set_landmarks(c.id, landmarks(4), ph.id);
    const auto l2 = s->set_landmarks(c.id, landmarks(5, 1.0), ph.id);
    EXPECT_EQ(l1.revision, 1);
    EXPECT_EQ(l2.revision, 2);
    const auto roi = s->set_roi(c.id, roi_json(), ph.id);
    const auto reg1 = s->add_registration(c.id, sample_registration(v.id, ph.id, 1.21));
    const auto reg2 = s->add_registration(c.id, sample_registration(v.id, ph.id, 1.25));  // a redo: a new row
    ASSERT_EQ(reg1.results.size(), 1u);
    EXPECT_EQ(s->read_blob(reg1.results[0].blob.sha256), "\x89PNG fake 1.210000");
    const auto mesh = s->add_result(c.id, reg2.id, {"mesh", "brain.glb", "model/gltf-binary", {}, "glTF", {{"decimate", 0.5}}});

    const CaseRecord r = s->get_case(c.id);
    ASSERT_TRUE(r.patient);
    EXPECT_EQ(r.patient->mrn, "MRN-0042");
    ASSERT_EQ(r.volumes.size(), 1u);
    ASSERT_EQ(r.photos.size(), 1u);
    EXPECT_EQ(r.photos[0].intrinsics, camera_json());
    ASSERT_TRUE(r.landmarks);
    EXPECT_EQ(r.landmarks->revision, 2);  // the latest
    EXPECT_EQ(r.landmarks->points, landmarks(5, 1.0));
    ASSERT_EQ(s->landmark_history(c.id).size(), 2u);
    EXPECT_EQ(s->landmark_history(c.id)[0].points, landmarks(4));  // the old one stays
    ASSERT_TRUE(r.roi);
    EXPECT_EQ(r.roi->roi, roi_json());
    EXPECT_EQ(r.roi->id, roi.id);
    ASSERT_EQ(r.registrations.size(), 2u);
    EXPECT_EQ(r.registrations[0].params, sample_registration(v.id, ph.id, 1.21).params);
    EXPECT_DOUBLE_EQ(*r.registrations[0].nmi, 1.21);
    EXPECT_DOUBLE_EQ(*r.registrations[1].nmi, 1.25);
    EXPECT_EQ(r.registrations[1].results.size(), 2u);  // its PNG and the mesh
    EXPECT_EQ(r.results.size(), 3u);
    EXPECT_EQ(r.results.back().id, mesh.id);
    EXPECT_EQ(r.results.back().params, (json{{"decimate", 0.5}}));
    EXPECT_GT(r.summary.updated_utc, r.summary.created_utc);
    EXPECT_TRUE(s->check_integrity().ok);

    // Registrations and results are kept as recorded.
    sqlite3* h = nullptr;
    ASSERT_EQ(sqlite3_open(s->database_path().c_str(), &h), SQLITE_OK);
    EXPECT_NE(sqlite3_exec(h, "UPDATE registrations SET nmi = 9", nullptr, nullptr, nullptr), SQLITE_OK);
    EXPECT_NE(sqlite3_exec(h, "DELETE FROM results", nullptr, nullptr, nullptr), SQLITE_OK);
    sqlite3_close(h);
}

TEST_F(StoreFixture, WorkflowForwardOneStepBackAnywhere) {
    const auto c = s->create_case(std::nullopt, "workflow");
    EXPECT_EQ(s->set_state(c.id, CaseState::planned).state, CaseState::planned);
    expect_store_error([&] { s->set_state(c.id, CaseState::registered); }, StoreError::Kind::Conflict,
                       "cannot go from 'planned' to 'registered'");
    for (auto st : {CaseState::patient_registered, CaseState::photo_captured, CaseState::landmarks, CaseState::roi,
                    CaseState::registered})
        EXPECT_EQ(s->set_state(c.id, st).state, st);
    EXPECT_EQ(s->set_state(c.id, CaseState::landmarks).state, CaseState::landmarks);  // redo landmarks
    EXPECT_EQ(s->set_state(c.id, CaseState::roi).state, CaseState::roi);
    EXPECT_EQ(to_string(CaseState::created), std::string("new"));
    EXPECT_EQ(case_state_from_string("patient_registered"), CaseState::patient_registered);
    expect_store_error([&] { case_state_from_string("done"); }, StoreError::Kind::Invalid, "expected one of new, planned");
    const auto trail = s->audit_trail(c.id);
    ASSERT_GE(trail.size(), 8u);
    EXPECT_EQ(trail.back().action, "case.state");
    EXPECT_EQ(trail.back().details, (json{{"from", "landmarks"}, {"to", "roi"}}));
}

TEST_F(StoreFixture, ListSearchSortAndFilter) {
    const auto p = s->create_patient({"MRN-7", "Smith", "Ann", std::nullopt});
    const auto a = s->create_case(p.id, "Alpha");
    clock->advance(std::chrono::seconds(1));
    const auto b = s->create_case(std::nullopt, "beta 100%");
    clock->advance(std::chrono::seconds(1));
    const auto c = s->create_case(std::nullopt, "Gamma");
    clock->advance(std::chrono::seconds(1));
    s->set_state(b.id, CaseState::planned);  // b is now the most recently updated

    auto ids = [](const std::vector<CaseSummary>& v) {
        std::vector<std::int64_t> out;
        for (const auto& x : v) out.push_back(x.id);
        return out;
    };
    EXPECT_EQ(ids(s->list_cases()), (std::vector<std::int64_t>{b.id, c.id, a.id}));
    CaseQuery q;
    q.sort = CaseQuery::Sort::title_asc;
    EXPECT_EQ(ids(s->list_cases(q)), (std::vector<std::int64_t>{a.id, b.id, c.id}));
    q.sort = CaseQuery::Sort::created_asc;
    q.limit = 2;
    q.offset = 1;
    EXPECT_EQ(ids(s->list_cases(q)), (std::vector<std::int64_t>{b.id, c.id}));
    CaseQuery by_name;
    by_name.text = "smi";  // the patient's family name, case-insensitive
    EXPECT_EQ(ids(s->list_cases(by_name)), (std::vector<std::int64_t>{a.id}));
    CaseQuery by_mrn;
    by_mrn.text = "MRN-7";
    EXPECT_EQ(ids(s->list_cases(by_mrn)), (std::vector<std::int64_t>{a.id}));
    CaseQuery literal;
    literal.text = "0%";  // % is literal, not a wildcard
    EXPECT_EQ(ids(s->list_cases(literal)), (std::vector<std::int64_t>{b.id}));
    CaseQuery planned;
    planned.state = CaseState::planned;
    EXPECT_EQ(ids(s->list_cases(planned)), (std::vector<std::int64_t>{b.id}));
    CaseQuery bad;
    bad.limit = 0;
    expect_store_error([&] { s->list_cases(bad); }, StoreError::Kind::Invalid, "limit must be 1..10000");
}

TEST_F(StoreFixture, BadInputsAreRefusedAndNothingIsStored) {
    const auto c = s->create_case(std::nullopt, "inputs");
    const auto other = s->create_case(std::nullopt, "other");
    const auto ph_other = s->add_photo_bytes(other.id, "P", "p.png", camera_json());
    const std::size_t audit_before = audit_count();
    const auto before = s->get_case(c.id);
    using K = StoreError::Kind;

    expect_store_error([&] { s->get_case(999); }, K::NotFound, "case 999: no such case");
    expect_store_error([&] { s->create_case(12345, "x"); }, K::NotFound, "patient 12345");
    expect_store_error([&] { s->create_case(std::nullopt, ""); }, K::Invalid, "title must be 1..200");
    expect_store_error([&] { s->import_volume_bytes(999, "x", "t1.nii", Modality::T1); }, K::NotFound, "case 999");
    expect_store_error([&] { s->import_volume_bytes(c.id, "x", "../t1.nii", Modality::T1); }, K::Invalid, "file name");
    expect_store_error([&] { s->import_volume(c.id, t.path / "missing.nii.gz", Modality::T1); }, K::NotFound,
                       "missing.nii.gz: no such file");
    json cam = camera_json();
    cam["fx"] = -1;
    expect_store_error([&] { s->add_photo_bytes(c.id, "P", "p.png", cam); }, K::Invalid, "\"fx\" must be a positive number");
    expect_store_error([&] { s->add_photo_bytes(c.id, "P", "p.png", json::array()); }, K::Invalid, "must be a JSON object");
    auto nan_lms = landmarks(4);
    nan_lms[2].world_mm[1] = std::nan("");
    expect_store_error([&] { s->set_landmarks(c.id, nan_lms); }, K::Invalid, "landmark 2: world_mm must be finite");
    auto dup = landmarks(4);
    dup[3].name = "L1";
    expect_store_error([&] { s->set_landmarks(c.id, dup); }, K::Invalid, "name 'L1' used twice");
    expect_store_error([&] { s->set_landmarks(c.id, landmarks(4), ph_other.id); }, K::Invalid,
                       "photo " + std::to_string(ph_other.id) + ": belongs to case " + std::to_string(other.id));
    json roi = roi_json();
    roi["points"] = {{1, 2}, {3, 4}};
    expect_store_error([&] { s->set_roi(c.id, roi); }, K::Invalid, "3..10000 [u, v] pairs");
    roi = roi_json();
    roi["type"] = "polygon";
    expect_store_error([&] { s->set_roi(c.id, roi); }, K::Invalid, "closed-cardinal-spline");
    RegistrationInput r;
    r.params = json::array();
    expect_store_error([&] { s->add_registration(c.id, r); }, K::Invalid, "params must be a JSON object");
    r.params = json::object();
    expect_store_error([&] { s->add_registration(c.id, r); }, K::Invalid, "succeeded registration needs its final pose");
    r.status = RegistrationStatus::failed;
    r.photo_id = ph_other.id;
    expect_store_error([&] { s->add_registration(c.id, r); }, K::Invalid, "belongs to case");
    r.photo_id = 777;
    expect_store_error([&] { s->add_registration(c.id, r); }, K::NotFound, "photo 777: no such photo");
    expect_store_error([&] { s->add_result(c.id, 4242, {"mesh", "m.glb", "model/gltf-binary", {}, "x", json::object()}); },
                       K::NotFound, "registration 4242");
    expect_store_error([&] { s->add_result(c.id, std::nullopt, {"mesh", "a/b.glb", "model/gltf-binary", {}, "x", json::object()}); },
                       K::Invalid, "file name");
    expect_store_error([&] { s->audit(Actor{}, "x", c.id, json::array()); }, K::Invalid, "details must be a JSON object");

    const auto after = s->get_case(c.id);
    EXPECT_EQ(after.volumes.size(), before.volumes.size());
    EXPECT_EQ(after.photos.size(), 0u);
    EXPECT_FALSE(after.landmarks);
    EXPECT_FALSE(after.roi);
    EXPECT_TRUE(after.registrations.empty());
    EXPECT_TRUE(after.results.empty());
    EXPECT_EQ(after.summary.updated_utc, before.summary.updated_utc);
    EXPECT_EQ(audit_count(), audit_before);
    // A failed registration with its reason is a valid record.
    r.photo_id.reset();
    r.error = "cancelled by the user";
    r.status = RegistrationStatus::cancelled;
    EXPECT_EQ(s->add_registration(c.id, r).error, "cancelled by the user");
}

TEST_F(StoreFixture, PatientIdentifiersNeverInMessagesOrAudit) {
    const auto p = s->create_patient({"MRN-SECRET-1", "Zyxwvuts", "Qponm", "1950-01-02"});
    expect_store_error([&] { s->create_patient({"MRN-SECRET-1", "Zyxwvuts", "Qponm", std::nullopt}); },
                       StoreError::Kind::Conflict, "MRN is already used by patient " + std::to_string(p.id));
    try {
        s->create_patient({"MRN-SECRET-1", "Zyxwvuts", "Qponm", std::nullopt});
    } catch (const StoreError& e) {
        const std::string m = e.what();
        EXPECT_EQ(m.find("SECRET"), std::string::npos) << m;
        EXPECT_EQ(m.find("Zyxwvuts"), std::string::npos) << m;
    }
    expect_store_error([&] { s->create_patient({"MRN-2", "Doe", "", "1950-13-40"}); }, StoreError::Kind::Invalid,
                       "birth date must be YYYY-MM-DD");
    s->create_case(p.id, "case");
    for (const auto& e : s->audit_trail(std::nullopt)) {
        const std::string d = e.details.dump();
        EXPECT_EQ(d.find("SECRET"), std::string::npos) << d;
        EXPECT_EQ(d.find("Zyxwvuts"), std::string::npos) << d;
        EXPECT_EQ(d.find("1950"), std::string::npos) << d;
    }
}

TEST_F(StoreFixture, AuditLogIsAppendOnly) {
    const auto c = s->create_case(std::nullopt, "audited");
    const Actor alice{"alice", std::nullopt};
    const auto e = s->audit(alice, "case.view", c.id, {{"view", "summary"}});
    EXPECT_EQ(e.actor, "alice");
    EXPECT_EQ(e.at_utc, clock->now);
    const auto trail = s->audit_trail(c.id);
    ASSERT_EQ(trail.size(), 2u);
    EXPECT_EQ(trail[0].action, "case.create");
    EXPECT_EQ(trail[0].actor, "system");
    EXPECT_EQ(trail[1].action, "case.view");
    EXPECT_EQ(trail[1].details, (json{{"view", "summary"}}));

    // Another connection (a tool, an attacker with the file) cannot rewrite or remove it.
    sqlite3* h = nullptr;
    ASSERT_EQ(sqlite3_open(s->database_path().c_str(), &h), SQLITE_OK);
    char* err = nullptr;
    EXPECT_NE(sqlite3_exec(h, "UPDATE audit_log SET actor = 'mallory'", nullptr, nullptr, &err), SQLITE_OK);
    ASSERT_NE(err, nullptr);
    EXPECT_NE(std::string(err).find("append-only"), std::string::npos) << err;
    sqlite3_free(err);
    err = nullptr;
    EXPECT_NE(sqlite3_exec(h, "DELETE FROM audit_log WHERE id = 1", nullptr, nullptr, &err), SQLITE_OK);
    ASSERT_NE(err, nullptr);
    EXPECT_NE(std::string(err).find("append-only"), std::string::npos) << err;
    sqlite3_free(err);
    EXPECT_EQ(sqlite3_exec(h, "INSERT INTO audit_log (at_utc, actor, action) VALUES ('2027-01-01T00:00:00.000Z', 'x', 'y')",
                           nullptr, nullptr, nullptr),
              SQLITE_OK);
    sqlite3_close(h);
    const auto all = s->audit_trail(std::nullopt);
    EXPECT_EQ(all[0].actor, "system");
    EXPECT_EQ(all.back().actor, "x");
}

TEST(DbSqlite, ConstraintFailuresMapToKinds) {
    TempDir t;
    sql::Db db((t.path / "c.sqlite").string());
    db.exec("CREATE TABLE a (x INTEGER UNIQUE CHECK (x > 0)); "
            "CREATE TABLE k (y INTEGER); CREATE TRIGGER k_no_delete BEFORE DELETE ON k BEGIN SELECT RAISE(ABORT, 'kept'); END; "
            "INSERT INTO a VALUES (1); INSERT INTO k VALUES (1);", "setup");
    expect_store_error([&] { db.prepare("INSERT INTO a VALUES (1)").context("row a 1").run(); }, StoreError::Kind::Conflict,
                       "row a 1: UNIQUE constraint failed");
    expect_store_error([&] { db.prepare("INSERT INTO a VALUES (-1)").context("row a -1").run(); }, StoreError::Kind::Invalid,
                       "row a -1: CHECK constraint failed");
    expect_store_error([&] { db.exec("DELETE FROM k", "deleting k"); }, StoreError::Kind::Conflict, "deleting k: kept");
    expect_store_error([&] { db.exec("SELECT * FROM nope", "reading nope"); }, StoreError::Kind::Invalid, "no such table");
}

TEST_F(StoreFixture, CorruptBlobIsReportedByIntegrityCheckAndRead) {
    const auto c = s->create_case(std::nullopt, "blobs");
    const auto v = s->import_volume_bytes(c.id, "volume content", "t1.nii", Modality::T1);
    EXPECT_TRUE(s->check_integrity().ok);
    write_file(v.blob.path, "volume c0ntent");
    const auto rep = s->check_integrity();
    EXPECT_FALSE(rep.ok);
    ASSERT_EQ(rep.problems.size(), 1u);
    EXPECT_NE(rep.problems[0].find("volume " + std::to_string(v.id)), std::string::npos) << rep.problems[0];
    EXPECT_NE(rep.problems[0].find(v.blob.path.string()), std::string::npos) << rep.problems[0];
    expect_store_error([&] { s->read_blob(v.blob.sha256); }, StoreError::Kind::Corrupt, v.blob.path.string());
    // A row whose blob is gone (half there) is reported too.
    const auto reg = s->add_registration(c.id, sample_registration(v.id, s->add_photo_bytes(c.id, "p", "p.png", camera_json()).id, 1.1));
    fs::remove(reg.results[0].blob.path);
    const auto rep2 = s->check_integrity();
    ASSERT_EQ(rep2.problems.size(), 2u);
    EXPECT_NE(rep2.problems[1].find("result " + std::to_string(reg.results[0].id) + ": "), std::string::npos) << rep2.problems[1];
    EXPECT_NE(rep2.problems[1].find("blob missing"), std::string::npos) << rep2.problems[1];
    expect_store_error([&] { s->read_blob(reg.results[0].blob.sha256); }, StoreError::Kind::NotFound, "cannot open the blob");
}

TEST_F(StoreFixture, TwoStoresOnOneFolderSeeEachOther) {
    auto s2 = CaseStore::open(t.path / "store", fast_options(clock));
    const auto c = s->create_case(std::nullopt, "shared");
    EXPECT_EQ(s2->get_case(c.id).summary.title, "shared");
    s2->set_landmarks(c.id, landmarks(4));
    EXPECT_EQ(s->get_case(c.id).landmarks->points.size(), 4u);
}

TEST_F(StoreFixture, UnreferencedBlobsAreRemovedWhenOld) {
    const auto c = s->create_case(std::nullopt, "gc");
    const auto kept = s->import_volume_bytes(c.id, "referenced", "v.nii", Modality::T1);
    BlobStore raw(s->dir() / "blobs");
    const auto orphan_old = raw.put_bytes("orphan, old");    // as left by a crash before the commit
    const auto orphan_new = raw.put_bytes("orphan, young");  // an import in flight elsewhere
    write_file(s->dir() / "blobs" / ".tmp-abc123", "half a blob");
    const auto two_hours_ago = fs::file_time_type::clock::now() - std::chrono::hours(2);
    fs::last_write_time(orphan_old.path, two_hours_ago);
    fs::last_write_time(kept.blob.path, two_hours_ago);
    fs::last_write_time(s->dir() / "blobs" / ".tmp-abc123", two_hours_ago);
    EXPECT_EQ(s->remove_unreferenced_blobs(std::chrono::hours(1)), 2);
    EXPECT_FALSE(fs::exists(orphan_old.path));
    EXPECT_FALSE(fs::exists(s->dir() / "blobs" / ".tmp-abc123"));
    EXPECT_TRUE(fs::exists(orphan_new.path));
    EXPECT_EQ(s->read_blob(kept.blob.sha256), "referenced");
    EXPECT_TRUE(s->check_integrity().ok);
}
