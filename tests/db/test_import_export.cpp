// A case moves to another cart intact: export (folder, zip) -> import into a fresh store ->
// the same content. Bad folders and zips are refused with nothing stored.
#include <zip.h>

#include <cstdio>
#include <random>

#include "db_test_util.hpp"

using namespace cf::db;
using namespace cfdbtest;
using nlohmann::json;

namespace {

struct Full {
    std::int64_t case_id;
};

Full make_full_case(CaseStore& s) {
    const auto p = s.create_patient({"MRN-900", "Roe", "Richard", "1980-05-06"});
    const auto c = s.create_case(p.id, "Full case");
    const auto t1 = s.import_volume_bytes(c.id, std::string("T1 volume bytes\0\x01\x02", 18), "t1.nii.gz", Modality::T1);
    s.import_volume_bytes(c.id, "CT volume", "ct.nrrd", Modality::CT);
    s.import_volume_bytes(c.id, "mask volume", "brain_mask.nii.gz", Modality::mask);
    const auto ph = s.add_photo_bytes(c.id, "photo 1", "photo.png", camera_json());
    s.set_landmarks(c.id, landmarks(4), ph.id);
    const auto lm = s.set_landmarks(c.id, landmarks(6, 0.5), ph.id);
    const auto roi = s.set_roi(c.id, roi_json(), ph.id);
    RegistrationInput r;
    r.volume_id = t1.id;
    r.photo_id = ph.id;
    r.landmark_set_id = lm.id;
    r.roi_id = roi.id;
    r.params = {{"bins", 32}, {"search_stages", json::array({{{"name", "s1"}, {"fwhm_mm", 8}}})}};
    r.final_pose = json{{"T_camera_from_world", {{1, 0, 0, 1}, {0, 1, 0, 2}, {0, 0, 1, 3}, {0, 0, 0, 1}}}};
    r.nmi = 1.234;
    r.evaluations = 500;
    r.seconds = 2.5;
    r.results.push_back({"fused_png", "fused.png", "image/png", {}, "fused png bytes", {{"opacity", 0.5}}});
    const auto reg = s.add_registration(c.id, r);
    RegistrationInput failed;
    failed.status = RegistrationStatus::failed;
    failed.error = "photo too dark";
    s.add_registration(c.id, failed);
    s.add_result(c.id, reg.id, {"mesh", "brain.glb", "model/gltf-binary", {}, "glb bytes", {{"faces", 1000}}});
    s.set_state(c.id, CaseState::planned);
    return {c.id};
}

/// Everything of a case that must survive a move, without this store's ids.
json content(CaseStore& s, std::int64_t case_id) {
    const auto c = s.get_case(case_id);
    json j;
    j["uid"] = c.summary.uid;
    j["title"] = c.summary.title;
    j["state"] = to_string(c.summary.state);
    j["created"] = format_utc(c.summary.created_utc);
    j["updated"] = format_utc(c.summary.updated_utc);
    if (c.patient) j["patient"] = {c.patient->mrn, c.patient->family_name, c.patient->given_name, *c.patient->birth_date};
    for (const auto& v : c.volumes)
        j["volumes"].push_back({to_string(v.modality), v.original_name, v.blob.sha256, v.blob.size_bytes, format_utc(v.created_utc)});
    for (const auto& p : c.photos) j["photos"].push_back({p.original_name, p.blob.sha256, p.intrinsics});
    for (const auto& l : s.landmark_history(case_id)) {
        json pts = json::array();
        for (const auto& p : l.points) pts.push_back({p.name, p.world_mm, p.pixel});
        j["landmarks"].push_back({l.revision, pts, l.photo_id.has_value()});
    }
    for (const auto& r : s.roi_history(case_id)) j["rois"].push_back({r.revision, r.roi});
    for (const auto& r : c.registrations) {
        json res = json::array();
        for (const auto& x : r.results) res.push_back(x.blob.sha256);
        j["registrations"].push_back({to_string(r.status), r.params, r.final_pose ? *r.final_pose : json(), r.nmi ? *r.nmi : -1,
                                      r.error ? *r.error : "", r.volume_id.has_value(), r.landmark_set_id.has_value(), res});
    }
    for (const auto& r : c.results) j["results"].push_back({r.kind, r.name, r.media_type, r.blob.sha256, r.params});
    return j;
}

void make_zip(const fs::path& path, const std::vector<std::pair<std::string, std::string>>& entries) {
    int err = 0;
    zip_t* za = zip_open(path.c_str(), ZIP_CREATE | ZIP_TRUNCATE, &err);
    ASSERT_NE(za, nullptr);
    std::vector<std::string> keep;
    keep.reserve(entries.size());
    for (const auto& [name, data] : entries) {
        keep.push_back(data);
        zip_source_t* src = zip_source_buffer(za, keep.back().data(), keep.back().size(), 0);
        ASSERT_GE(zip_file_add(za, name.c_str(), src, ZIP_FL_ENC_UTF_8 | ZIP_FL_OVERWRITE), 0) << name;
    }
    ASSERT_EQ(zip_close(za), 0);
}

std::vector<std::pair<std::string, std::string>> folder_entries(const fs::path& dir) {
    std::vector<std::pair<std::string, std::string>> out;
    for (const auto& e : fs::recursive_directory_iterator(dir))
        if (e.is_regular_file()) out.emplace_back(fs::relative(e.path(), dir).string(), read_file(e.path()));
    return out;
}

struct IoFixture : ::testing::Test {
    TempDir t;
    std::shared_ptr<FakeClock> clock = std::make_shared<FakeClock>();
    std::unique_ptr<CaseStore> src = CaseStore::open(t.path / "cart1", fast_options(clock));
    std::unique_ptr<CaseStore> dst = CaseStore::open(t.path / "cart2", fast_options(clock));

    /// The import must have changed nothing in dst.
    void expect_nothing_imported(std::size_t audit_before) {
        EXPECT_TRUE(dst->list_cases().empty());
        EXPECT_EQ(dst->audit_trail(std::nullopt).size(), audit_before);
        std::error_code ec;
        if (fs::is_directory(dst->dir() / "tmp")) {
            EXPECT_TRUE(fs::is_empty(dst->dir() / "tmp")) << "temporary import files left behind";
        }
        EXPECT_TRUE(dst->check_integrity().ok);
    }
};

}  // namespace

TEST_F(IoFixture, FolderRoundTripKeepsEverything) {
    const auto f = make_full_case(*src);
    src->export_case_folder(f.case_id, t.path / "out");
    EXPECT_TRUE(fs::is_regular_file(t.path / "out" / "store.json"));
    // case.json in the case-format the batch tool reads.
    const json cj = json::parse(read_file(t.path / "out" / "case.json"));
    EXPECT_EQ(cj["format"], "cortexfuse-case/1");
    EXPECT_EQ(read_file(t.path / "out" / cj["volume"].get<std::string>()), std::string("T1 volume bytes\0\x01\x02", 18));
    EXPECT_EQ(read_file(t.path / "out" / cj["photo"].get<std::string>()), "photo 1");
    EXPECT_EQ(cj["camera"], camera_json());
    const json lj = json::parse(read_file(t.path / "out" / "landmarks.json"));
    ASSERT_EQ(lj["landmarks"].size(), 6u);  // the latest revision
    EXPECT_EQ(lj["landmarks"][0]["label"], "L1");
    EXPECT_EQ(json::parse(read_file(t.path / "out" / "roi.json")), roi_json());
    EXPECT_TRUE(cj.contains("brain_mask"));

    const auto id = dst->import_case_folder(t.path / "out");
    EXPECT_EQ(content(*dst, id), content(*src, f.case_id));
    EXPECT_TRUE(dst->check_integrity().ok);
    // The same case twice: refused.
    expect_store_error([&] { dst->import_case_folder(t.path / "out"); }, StoreError::Kind::Conflict, "already in this store");
    expect_store_error([&] { src->export_case_folder(f.case_id, t.path / "out"); }, StoreError::Kind::Conflict,
                       "already exists");
}

TEST_F(IoFixture, ZipRoundTripKeepsEverything) {
    const auto f = make_full_case(*src);
    src->export_case_zip(f.case_id, t.path / "case.zip");
    const auto id = dst->import_case_zip(t.path / "case.zip");
    EXPECT_EQ(content(*dst, id), content(*src, f.case_id));
    const auto trail = dst->audit_trail(id);
    ASSERT_FALSE(trail.empty());
    EXPECT_EQ(trail.back().action, "case.import");
    EXPECT_TRUE(fs::is_empty(dst->dir() / "tmp"));
    bool exported = false;
    for (const auto& e : src->audit_trail(f.case_id)) exported |= e.action == "case.export";
    EXPECT_TRUE(exported);
}

TEST_F(IoFixture, ZipWithOneTopFolderIsAccepted) {
    const auto f = make_full_case(*src);
    src->export_case_folder(f.case_id, t.path / "out");
    auto entries = folder_entries(t.path / "out");
    for (auto& e : entries) e.first = "case-42/" + e.first;
    make_zip(t.path / "nested.zip", entries);
    const auto id = dst->import_case_zip(t.path / "nested.zip");
    EXPECT_EQ(content(*dst, id), content(*src, f.case_id));
}

TEST_F(IoFixture, PlainCaseFolderIsImported) {
    const fs::path d = t.path / "phantom_case_3";
    write_file(d / "t1.nii.gz", "t1");
    write_file(d / "photo.png", "png");
    write_file(d / "brain_mask.nii.gz", "mask");
    json lms = json::array();
    for (int i = 0; i < 4; ++i) lms.push_back({{"label", "L" + std::to_string(i)}, {"world_mm", {i, 2.0, 3.0}}, {"pixel", {10 * i, 20}}});
    write_file(d / "landmarks.json", json{{"landmarks", lms}}.dump());
    write_file(d / "roi.json", roi_json().dump());
    write_file(d / "case.json", json{{"format", "cortexfuse-case/1"}, {"volume", "t1.nii.gz"}, {"photo", "photo.png"},
                                     {"camera", camera_json()}, {"landmarks", "landmarks.json"}, {"roi", "roi.json"},
                                     {"brain_mask", "brain_mask.nii.gz"}}
                                    .dump());
    const auto id = dst->import_case_folder(d);
    const auto c = dst->get_case(id);
    EXPECT_EQ(c.summary.title, "phantom_case_3");
    EXPECT_EQ(c.summary.state, CaseState::roi);
    ASSERT_EQ(c.volumes.size(), 2u);
    EXPECT_EQ(c.volumes[0].modality, Modality::T1);
    EXPECT_EQ(dst->read_blob(c.volumes[0].blob.sha256), "t1");
    EXPECT_EQ(c.volumes[1].modality, Modality::mask);
    ASSERT_EQ(c.photos.size(), 1u);
    ASSERT_TRUE(c.landmarks);
    EXPECT_EQ(c.landmarks->points.size(), 4u);
    EXPECT_EQ(c.landmarks->photo_id, c.photos[0].id);
    EXPECT_EQ(c.roi->roi, roi_json());
    // The same folder zipped: titled after the archive.
    auto entries = folder_entries(d);
    make_zip(t.path / "from_zip.zip", entries);
    const auto z = dst->get_case(dst->import_case_zip(t.path / "from_zip.zip"));
    EXPECT_EQ(z.summary.title, "from_zip");
    EXPECT_EQ(z.volumes[0].blob.sha256, c.volumes[0].blob.sha256);
    EXPECT_NE(z.summary.uid, c.summary.uid);  // a plain folder has no uid: a new case each time
}

TEST_F(IoFixture, BadFoldersAreRefusedWithNothingStored) {
    const auto f = make_full_case(*src);
    src->export_case_folder(f.case_id, t.path / "good");
    const std::size_t audit0 = dst->audit_trail(std::nullopt).size();
    using K = StoreError::Kind;
    const json manifest = json::parse(read_file(t.path / "good" / "store.json"));
    int n = 0;
    auto variant = [&](const std::function<void(const fs::path&)>& edit) {
        const fs::path d = t.path / ("bad" + std::to_string(n++));
        fs::copy(t.path / "good", d, fs::copy_options::recursive);
        edit(d);
        return d;
    };
    auto with_manifest = [&](const std::function<void(json&)>& edit) {
        return variant([&](const fs::path& d) {
            json m = manifest;
            edit(m);
            write_file(d / "store.json", m.dump());
        });
    };
    struct Case {
        fs::path dir;
        K kind;
        std::string needle;
    };
    const std::vector<Case> cases = {
        {variant([](const fs::path& d) { write_file(d / "store.json", "{\"format\": \"cortexfuse-case-store/1\", "); }),
         K::Invalid, "store.json: not valid JSON"},
        {with_manifest([](json& m) { m["format"] = "cortexfuse-case-store/9"; }), K::Invalid, "format must be"},
        {with_manifest([](json& m) { m["volumes"][0]["file"] = "../../etc/passwd"; }), K::Invalid, "'.' or '..'"},
        {with_manifest([](json& m) { m["volumes"][0]["file"] = "/etc/passwd"; }), K::Invalid, "relative path inside"},
        {variant([&](const fs::path& d) { fs::remove(d / manifest["photos"][0]["file"].get<std::string>()); }), K::Invalid,
         "is missing"},
        {variant([&](const fs::path& d) { write_file(d / manifest["results"][0]["file"].get<std::string>(), "tampered"); }),
         K::Corrupt, "store.json says"},
        {with_manifest([](json& m) { m["volumes"][0]["sha256"] = 12; }), K::Invalid, "volumes[0].sha256: expected a string"},
        {with_manifest([](json& m) { m["registrations"][0]["photo_id"] = 999; }), K::Invalid,
         "names photo 999, which store.json does not hold"},
        {with_manifest([](json& m) { m["case"]["state"] = "finished"; }), K::Invalid, "case state 'finished'"},
        {with_manifest([](json& m) { m["landmark_sets"][0]["landmarks"][0]["world_mm"] = {1, 2}; }), K::Invalid,
         "world_mm: expected 3 numbers"},
        {with_manifest([](json& m) { m["rois"][0]["roi"]["points"] = "none"; }), K::Invalid, "points"},
        {with_manifest([](json& m) { m["photos"][0]["intrinsics"].erase("fx"); }), K::Invalid, "\"fx\""},
        {with_manifest([](json& m) { m["case"]["created_utc"] = "yesterday"; }), K::Invalid, "created_utc: expected a UTC time"},
        {with_manifest([](json& m) { m.erase("results"); }), K::Invalid, "missing \"results\""},
        {variant([&](const fs::path& d) {
             const fs::path vf = d / manifest["volumes"][0]["file"].get<std::string>();
             fs::remove(vf);
             fs::create_symlink("/etc/hostname", vf);
         }),
         K::Invalid, "symbolic link"},
        {variant([](const fs::path& d) { fs::remove(d / "store.json"); fs::remove(d / "case.json"); }), K::Invalid,
         "neither store.json nor case.json"},
    };
    for (const auto& c : cases) {
        SCOPED_TRACE(c.dir.string() + " / " + c.needle);
        expect_store_error([&] { dst->import_case_folder(c.dir); }, c.kind, c.needle);
        expect_nothing_imported(audit0);
    }
    expect_store_error([&] { dst->import_case_folder(t.path / "nope"); }, K::NotFound, "no such folder");
    // After all that, the good one still imports.
    EXPECT_NO_THROW(dst->import_case_folder(t.path / "good"));
}

TEST_F(IoFixture, BadZipsAreRefusedWithNothingStored) {
    const auto f = make_full_case(*src);
    src->export_case_zip(f.case_id, t.path / "good.zip");
    src->export_case_folder(f.case_id, t.path / "good");
    const std::size_t audit0 = dst->audit_trail(std::nullopt).size();
    using K = StoreError::Kind;
    const std::string zip_bytes = read_file(t.path / "good.zip");

    write_file(t.path / "truncated.zip", zip_bytes.substr(0, zip_bytes.size() / 2));
    expect_store_error([&] { dst->import_case_zip(t.path / "truncated.zip"); }, K::Invalid, "not a readable zip archive");
    expect_nothing_imported(audit0);

    write_file(t.path / "notzip.zip", "just text");
    expect_store_error([&] { dst->import_case_zip(t.path / "notzip.zip"); }, K::Invalid, "notzip.zip: not a readable zip");
    expect_nothing_imported(audit0);

    auto entries = folder_entries(t.path / "good");
    auto traversal = entries;
    traversal.emplace_back("../../etc/passwd", "root:x:0:0");
    make_zip(t.path / "traversal.zip", traversal);
    expect_store_error([&] { dst->import_case_zip(t.path / "traversal.zip"); }, K::Invalid,
                       "entry '../../etc/passwd' leaves the case folder");
    expect_nothing_imported(audit0);
    EXPECT_FALSE(fs::exists(dst->dir() / "etc"));

    auto absolute = entries;
    absolute.emplace_back("/tmp/evil", "x");
    make_zip(t.path / "absolute.zip", absolute);
    expect_store_error([&] { dst->import_case_zip(t.path / "absolute.zip"); }, K::Invalid, "absolute");
    expect_nothing_imported(audit0);

    auto missing = entries;
    const json manifest = json::parse(read_file(t.path / "good" / "store.json"));
    const std::string vol = manifest["volumes"][1]["file"];
    std::erase_if(missing, [&](const auto& e) { return e.first == vol; });
    make_zip(t.path / "missing.zip", missing);
    expect_store_error([&] { dst->import_case_zip(t.path / "missing.zip"); }, K::Invalid,
                       "missing.zip: store.json: volumes[1]: file '" + vol + "' is missing");
    expect_nothing_imported(audit0);

    auto badjson = entries;
    for (auto& e : badjson)
        if (e.first == "store.json") e.second = "{not json";
    make_zip(t.path / "badjson.zip", badjson);
    expect_store_error([&] { dst->import_case_zip(t.path / "badjson.zip"); }, K::Invalid, "not valid JSON");
    expect_nothing_imported(audit0);

    // Damaged content inside a well-formed archive (one byte flipped): the CRC or the hash catches it.
    std::string flipped = zip_bytes;
    const std::size_t at = flipped.find("fused png bytes");
    ASSERT_NE(at, std::string::npos);  // stored, not deflated? then flip inside it
    flipped[at + 3] ^= 0x20;
    write_file(t.path / "flipped.zip", flipped);
    try {
        dst->import_case_zip(t.path / "flipped.zip");
        ADD_FAILURE() << "a damaged archive was imported";
    } catch (const StoreError& e) {
        EXPECT_TRUE(e.kind() == K::Invalid || e.kind() == K::Corrupt) << e.what();
        EXPECT_NE(std::string(e.what()).find("flipped.zip"), std::string::npos) << e.what();
    }
    expect_nothing_imported(audit0);

    StoreOptions small = fast_options(clock);
    small.max_import_bytes = 50;
    auto tiny = CaseStore::open(t.path / "cart3", small);
    expect_store_error([&] { tiny->import_case_zip(t.path / "good.zip"); }, K::Invalid, "more than the import limit");
    EXPECT_TRUE(tiny->list_cases().empty());

    EXPECT_NO_THROW(dst->import_case_zip(t.path / "good.zip"));
}

TEST_F(IoFixture, ExportRefusesDamagedBlobs) {
    const auto f = make_full_case(*src);
    const auto c = src->get_case(f.case_id);
    write_file(c.photos[0].blob.path, "photo X");
    expect_store_error([&] { src->export_case_zip(f.case_id, t.path / "x.zip"); }, StoreError::Kind::Corrupt,
                       c.photos[0].blob.path.string());
    EXPECT_FALSE(fs::exists(t.path / "x.zip"));
    expect_store_error([&] { src->export_case_folder(f.case_id, t.path / "xdir"); }, StoreError::Kind::Corrupt,
                       "blob is corrupt");
    EXPECT_FALSE(fs::exists(t.path / "xdir"));
    for (const auto& e : fs::directory_iterator(t.path))
        EXPECT_EQ(e.path().filename().string().find(".partial-"), std::string::npos) << e.path();
}

// Damaged archives of every kind (seeded random byte flips and truncations): each import is
// either refused with a StoreError or brings in exactly the original content; never a crash,
// never a half-imported case, never scratch files left behind.
TEST_F(IoFixture, MutatedZipsNeverHalfImport) {
    const auto f = make_full_case(*src);
    src->export_case_zip(f.case_id, t.path / "good.zip");
    const std::string good = read_file(t.path / "good.zip");
    const json expected = content(*src, f.case_id);
    std::mt19937 rng(6);
    int refused = 0, imported = 0;
    for (int round = 0; round < 80; ++round) {
        std::string z = good;
        if (round % 5 == 4) {
            z.resize(std::uniform_int_distribution<std::size_t>(0, z.size() - 1)(rng));
        } else {
            const int flips = std::uniform_int_distribution<int>(1, 6)(rng);
            for (int k = 0; k < flips; ++k)
                z[std::uniform_int_distribution<std::size_t>(0, z.size() - 1)(rng)] ^=
                    static_cast<char>(1 << std::uniform_int_distribution<int>(0, 7)(rng));
        }
        const fs::path p = t.path / ("m" + std::to_string(round) + ".zip");
        write_file(p, z);
        // One receiving store for all (opening a store per round costs its fsyncs). After an
        // intact import, a later intact one is refused as a Conflict (same uid): also a refusal.
        const std::size_t cases_before = dst->list_cases().size();
        try {
            const auto id = dst->import_case_zip(p);
            EXPECT_EQ(content(*dst, id), expected) << p;
            ++imported;
        } catch (const StoreError& e) {
            ++refused;
            EXPECT_NE(std::string(e.what()).find(p.string()), std::string::npos) << e.what();
            EXPECT_EQ(dst->list_cases().size(), cases_before) << p;
        }
        if (fs::is_directory(dst->dir() / "tmp")) {
            EXPECT_TRUE(fs::is_empty(dst->dir() / "tmp")) << p;
        }
    }
    EXPECT_TRUE(dst->check_integrity().ok);
    std::printf("mutated zips: %d refused, %d imported intact\n", refused, imported);
    EXPECT_GT(refused, 40);
}
