// Moving a case: export as a case folder (docs/case-format.md, plus store.json with
// everything the store holds) or as a .zip of it (libzip); import of either, and of plain
// case folders. Imports check everything first, write blobs, then insert in one transaction.
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>
#include <zip.h>

#include <cstring>
#include <deque>
#include <fstream>
#include <map>
#include <sstream>

#include "fsutil.hpp"
#include "store_impl.hpp"

namespace cf::db {

namespace fs = std::filesystem;
using K = StoreError::Kind;
using nlohmann::json;

namespace {

constexpr const char* kStoreFormat = "cortexfuse-case-store/1";
constexpr const char* kCaseFormat = "cortexfuse-case/1";
constexpr std::int64_t kMaxJsonBytes = 64 << 20;

// ---- export -------------------------------------------------------------------------------------

struct OutFile {
    std::string rel;    ///< path inside the folder / zip
    std::string sha;    ///< a blob, or
    std::string text;   ///< generated JSON
};

json landmarks_json(const LandmarkSet& s) {
    json a = json::array();
    for (const auto& p : s.points)
        a.push_back({{"label", p.name}, {"world_mm", p.world_mm}, {"pixel", p.pixel}});
    return a;
}

std::string dump(const json& j) { return j.dump(2) + "\n"; }

/// Everything about the case, as files. Caller holds the lock.
std::vector<OutFile> build_export(CaseStore::Impl& I, std::int64_t case_id, const std::string& at) {
    const CaseRecord c = I.get_case(case_id);
    const auto sets = I.landmark_sets(case_id);
    const auto rois = I.rois(case_id);
    std::vector<OutFile> files;
    json m;
    m["format"] = kStoreFormat;
    m["exported_utc"] = at;
    m["case"] = {{"uid", c.summary.uid}, {"title", c.summary.title}, {"state", to_string(c.summary.state)},
                 {"created_utc", format_utc(c.summary.created_utc)}, {"updated_utc", format_utc(c.summary.updated_utc)}};
    if (c.patient)
        m["patient"] = {{"mrn", c.patient->mrn}, {"family_name", c.patient->family_name},
                        {"given_name", c.patient->given_name},
                        {"birth_date", c.patient->birth_date ? json(*c.patient->birth_date) : json(nullptr)},
                        {"created_utc", format_utc(c.patient->created_utc)}};
    else
        m["patient"] = nullptr;
    m["volumes"] = json::array();
    for (const auto& v : c.volumes) {
        const std::string rel = "volumes/" + std::to_string(v.id) + "_" + v.original_name;
        files.push_back({rel, v.blob.sha256, {}});
        m["volumes"].push_back({{"id", v.id}, {"modality", to_string(v.modality)}, {"original_name", v.original_name},
                                {"file", rel}, {"sha256", v.blob.sha256}, {"size_bytes", v.blob.size_bytes},
                                {"created_utc", format_utc(v.created_utc)}});
    }
    m["photos"] = json::array();
    for (const auto& p : c.photos) {
        const std::string rel = "photos/" + std::to_string(p.id) + "_" + p.original_name;
        files.push_back({rel, p.blob.sha256, {}});
        m["photos"].push_back({{"id", p.id}, {"original_name", p.original_name}, {"file", rel}, {"sha256", p.blob.sha256},
                               {"size_bytes", p.blob.size_bytes}, {"intrinsics", p.intrinsics},
                               {"created_utc", format_utc(p.created_utc)}});
    }
    m["landmark_sets"] = json::array();
    for (const auto& s : sets)
        m["landmark_sets"].push_back({{"id", s.id}, {"revision", s.revision},
                                      {"photo_id", s.photo_id ? json(*s.photo_id) : json(nullptr)},
                                      {"created_utc", format_utc(s.created_utc)}, {"landmarks", landmarks_json(s)}});
    m["rois"] = json::array();
    for (const auto& r : rois)
        m["rois"].push_back({{"id", r.id}, {"revision", r.revision},
                             {"photo_id", r.photo_id ? json(*r.photo_id) : json(nullptr)}, {"roi", r.roi},
                             {"created_utc", format_utc(r.created_utc)}});
    auto opt = [](const auto& o) { return o ? json(*o) : json(nullptr); };
    m["registrations"] = json::array();
    for (const auto& r : c.registrations)
        m["registrations"].push_back({{"id", r.id}, {"volume_id", opt(r.volume_id)}, {"photo_id", opt(r.photo_id)},
                                      {"landmark_set_id", opt(r.landmark_set_id)}, {"roi_id", opt(r.roi_id)},
                                      {"status", to_string(r.status)}, {"params", r.params},
                                      {"initial_pose", opt(r.initial_pose)}, {"final_pose", opt(r.final_pose)},
                                      {"nmi", opt(r.nmi)}, {"evaluations", opt(r.evaluations)}, {"seconds", opt(r.seconds)},
                                      {"stages", r.stages}, {"error", opt(r.error)},
                                      {"created_utc", format_utc(r.created_utc)}});
    m["results"] = json::array();
    for (const auto& r : c.results) {
        const std::string rel = "results/" + std::to_string(r.id) + "_" + r.name;
        files.push_back({rel, r.blob.sha256, {}});
        m["results"].push_back({{"id", r.id}, {"registration_id", opt(r.registration_id)}, {"kind", r.kind},
                                {"name", r.name}, {"media_type", r.media_type}, {"file", rel}, {"sha256", r.blob.sha256},
                                {"size_bytes", r.blob.size_bytes}, {"params", r.params},
                                {"created_utc", format_utc(r.created_utc)}});
    }
    files.push_back({"store.json", {}, dump(m)});

    // case.json for `cortexfuse register` and other tools: needs a T1 volume and a photo.
    const VolumeRecord* t1 = nullptr;
    const VolumeRecord* mask = nullptr;
    for (const auto& v : c.volumes) {
        if (v.modality == Modality::T1) t1 = &v;
        if (v.modality == Modality::mask) mask = &v;
    }
    if (t1 && !c.photos.empty()) {
        const auto& photo = c.photos.back();
        json cj;
        cj["format"] = kCaseFormat;
        cj["volume"] = "volumes/" + std::to_string(t1->id) + "_" + t1->original_name;
        cj["photo"] = "photos/" + std::to_string(photo.id) + "_" + photo.original_name;
        cj["camera"] = photo.intrinsics;
        if (c.landmarks) {
            cj["landmarks"] = "landmarks.json";
            files.push_back({"landmarks.json", {}, dump(json{{"landmarks", landmarks_json(*c.landmarks)}})});
        }
        if (c.roi) {
            cj["roi"] = "roi.json";
            files.push_back({"roi.json", {}, dump(c.roi->roi)});
        }
        if (mask) cj["brain_mask"] = "volumes/" + std::to_string(mask->id) + "_" + mask->original_name;
        files.push_back({"case.json", {}, dump(cj)});
    }
    return files;
}

bool already_compressed(const std::string& name) {
    for (const char* ext : {".gz", ".png", ".jpg", ".jpeg", ".zip", ".glb", ".nrrd", ".mha"})
        if (name.size() >= std::strlen(ext) && name.compare(name.size() - std::strlen(ext), std::string::npos, ext) == 0)
            return true;
    return false;
}

// ---- import: paths and JSON fields ----------------------------------------------------------------

/// `root/rel` for a relative path that stays inside `root` and is a regular file (no symlinks).
fs::path safe_file(const fs::path& root, const std::string& rel, const std::string& what) {
    auto bad = [&](const std::string& p) { throw StoreError(K::Invalid, what + ": file '" + rel.substr(0, 120) + "' " + p); };
    if (rel.empty() || rel.size() > 1024) bad("must be a relative path of 1..1024 characters");
    if (rel.front() == '/' || rel.find('\\') != std::string::npos || rel.find(':') != std::string::npos)
        bad("must be a relative path inside the case folder");
    for (const auto& part : fs::path(rel))
        if (part == ".." || part == ".") bad("must not contain '.' or '..' components");
    const fs::path p = root / rel;
    std::error_code ec;
    fs::path cur = root;
    for (const auto& part : fs::path(rel)) {
        cur /= part;
        if (fs::is_symlink(fs::symlink_status(cur, ec))) bad("is (or lies under) a symbolic link");
    }
    const auto st = fs::status(p, ec);
    if (!fs::exists(st)) bad("is missing");
    if (fs::is_directory(st)) bad("is a folder (DICOM series folders are not supported by the case store yet)");
    if (!fs::is_regular_file(st)) bad("is not a regular file");
    return p;
}

json read_json(const fs::path& p, const std::string& what) {
    std::error_code ec;
    const auto size = fs::file_size(p, ec);
    if (ec) throw StoreError(K::Invalid, what + ": cannot read: " + ec.message());
    if (size > static_cast<std::uintmax_t>(kMaxJsonBytes)) throw StoreError(K::Invalid, what + ": larger than 64 MiB");
    std::ifstream in(p, std::ios::binary);
    std::stringstream ss;
    ss << in.rdbuf();
    try {
        return json::parse(ss.str());
    } catch (const json::exception& e) {
        throw StoreError(K::Invalid, what + ": not valid JSON (" + e.what() + ")");
    }
}

struct Fields {
    const json& j;
    std::string where;
    const json& at(const char* k) const {
        if (!j.is_object() || !j.contains(k)) throw StoreError(K::Invalid, where + ": missing \"" + k + "\"");
        return j[k];
    }
    [[noreturn]] void bad(const char* k, const char* expect) const {
        throw StoreError(K::Invalid, where + "." + k + ": expected " + expect);
    }
    std::string str(const char* k) const {
        const auto& v = at(k);
        if (!v.is_string()) bad(k, "a string");
        return v.get<std::string>();
    }
    std::optional<std::string> opt_str(const char* k) const {
        if (!j.contains(k) || j[k].is_null()) return std::nullopt;
        return str(k);
    }
    std::int64_t i64(const char* k) const {
        const auto& v = at(k);
        if (!v.is_number_integer()) bad(k, "an integer");
        return v.get<std::int64_t>();
    }
    std::optional<std::int64_t> opt_i64(const char* k) const {
        if (!j.contains(k) || j[k].is_null()) return std::nullopt;
        return i64(k);
    }
    std::optional<double> opt_f64(const char* k) const {
        if (!j.contains(k) || j[k].is_null()) return std::nullopt;
        if (!j[k].is_number()) bad(k, "a number");
        return j[k].get<double>();
    }
    std::string time(const char* k) const {
        const std::string s = str(k);
        try {
            (void)parse_utc(s);
        } catch (const StoreError&) {
            bad(k, "a UTC time YYYY-MM-DDTHH:MM:SS.mmmZ");
        }
        return s;
    }
    std::string sha(const char* k) const {
        const std::string s = str(k);
        if (!BlobStore::valid_hash(s)) bad(k, "64 lower-case hex digits (SHA-256)");
        return s;
    }
    const json& array(const char* k) const {
        const auto& v = at(k);
        if (!v.is_array()) bad(k, "an array");
        return v;
    }
};

std::vector<LandmarkPoint> parse_landmark_list(const json& a, const std::string& where) {
    if (!a.is_array()) throw StoreError(K::Invalid, where + ": expected an array of landmarks");
    std::vector<LandmarkPoint> out;
    for (std::size_t i = 0; i < a.size(); ++i) {
        const std::string w = where + "[" + std::to_string(i) + "]";
        Fields f{a[i], w};
        LandmarkPoint p;
        p.name = f.str("label");
        const auto& wm = f.at("world_mm");
        const auto& px = f.at("pixel");
        if (!wm.is_array() || wm.size() != 3) f.bad("world_mm", "3 numbers");
        if (!px.is_array() || px.size() != 2) f.bad("pixel", "2 numbers");
        for (int k = 0; k < 3; ++k) {
            if (!wm[k].is_number()) f.bad("world_mm", "3 numbers");
            p.world_mm[k] = wm[k].get<double>();
        }
        for (int k = 0; k < 2; ++k) {
            if (!px[k].is_number()) f.bad("pixel", "2 numbers");
            p.pixel[k] = px[k].get<double>();
        }
        out.push_back(std::move(p));
    }
    validate_landmarks(out, where);
    return out;
}

// One file to bring in as a blob.
struct InFile {
    fs::path path;
    std::string expect_sha;  ///< empty: whatever it hashes to
    std::string what;
    BlobRef ref;
};

struct Plan {
    std::string uid, title, created, updated;
    CaseState state = CaseState::created;
    std::optional<PatientInput> patient;
    std::string patient_created;
    struct Vol { std::int64_t old_id; Modality m; std::string name, created; std::size_t file; };
    struct Pho { std::int64_t old_id; std::string name, created; json intrinsics; std::size_t file; };
    struct Lms { std::int64_t old_id; std::optional<std::int64_t> photo; std::string created; std::vector<LandmarkPoint> pts; };
    struct Roi { std::int64_t old_id; std::optional<std::int64_t> photo; std::string created; json roi; };
    struct Reg { std::int64_t old_id; RegistrationInput in; std::string created; };
    struct Res { std::int64_t old_id; std::optional<std::int64_t> reg; ResultInput in; std::string created; std::size_t file; };
    std::vector<Vol> volumes;
    std::vector<Pho> photos;
    std::vector<Lms> landmark_sets;
    std::vector<Roi> rois;
    std::vector<Reg> registrations;
    std::vector<Res> results;
    std::vector<InFile> files;
    std::string source;
};

void check_ref(const std::optional<std::int64_t>& id, const std::map<std::int64_t, int>& known, const std::string& where,
               const char* what) {
    if (id && !known.count(*id))
        throw StoreError(K::Invalid, where + ": names " + what + " " + std::to_string(*id) + ", which store.json does not hold");
}

Plan plan_store_folder(const fs::path& root) {
    const std::string sj = (root / "store.json").string();
    const json m = read_json(root / "store.json", sj);
    Fields top{m, sj};
    if (top.str("format") != kStoreFormat)
        throw StoreError(K::Invalid, sj + ": format must be \"" + std::string(kStoreFormat) + "\"");
    Plan p;
    p.source = "store.json";
    Fields c{top.at("case"), sj + ": case"};
    p.uid = c.str("uid");
    if (p.uid.size() != 32 || !BlobStore::valid_hash(p.uid + p.uid)) c.bad("uid", "32 lower-case hex digits");
    p.title = c.str("title");
    if (p.title.empty() || p.title.size() > 200) c.bad("title", "1..200 characters");
    try {
        p.state = case_state_from_string(c.str("state"));
    } catch (const StoreError& e) {
        throw StoreError(K::Invalid, sj + ": case: " + e.what());
    }
    p.created = c.time("created_utc");
    p.updated = c.time("updated_utc");
    const json& pj = top.at("patient");
    if (!pj.is_null()) {
        Fields f{pj, sj + ": patient"};
        PatientInput pi;
        pi.mrn = f.str("mrn");
        pi.family_name = f.str("family_name");
        pi.given_name = f.opt_str("given_name").value_or("");
        pi.birth_date = f.opt_str("birth_date");
        if (pi.mrn.empty() || pi.mrn.size() > 64 || pi.family_name.empty())
            throw StoreError(K::Invalid, sj + ": patient: MRN and family name are required");
        p.patient = pi;
        p.patient_created = f.time("created_utc");
    }
    auto add_file = [&](Fields& f, const std::string& what) {
        InFile in;
        in.path = safe_file(root, f.str("file"), what);
        in.expect_sha = f.sha("sha256");
        in.what = what;
        p.files.push_back(std::move(in));
        return p.files.size() - 1;
    };
    std::map<std::int64_t, int> vol_ids, photo_ids, set_ids, roi_ids, reg_ids;
    const auto& va = top.array("volumes");
    for (std::size_t i = 0; i < va.size(); ++i) {
        const std::string w = sj + ": volumes[" + std::to_string(i) + "]";
        Fields f{va[i], w};
        Plan::Vol v;
        v.old_id = f.i64("id");
        try {
            v.m = modality_from_string(f.str("modality"));
        } catch (const StoreError& e) {
            throw StoreError(K::Invalid, w + ": " + e.what());
        }
        v.name = f.str("original_name");
        validate_file_name(v.name, w);
        v.created = f.time("created_utc");
        v.file = add_file(f, w);
        if (!vol_ids.emplace(v.old_id, 1).second) f.bad("id", "an id not used twice");
        p.volumes.push_back(std::move(v));
    }
    const auto& pa = top.array("photos");
    for (std::size_t i = 0; i < pa.size(); ++i) {
        const std::string w = sj + ": photos[" + std::to_string(i) + "]";
        Fields f{pa[i], w};
        Plan::Pho ph;
        ph.old_id = f.i64("id");
        ph.name = f.str("original_name");
        validate_file_name(ph.name, w);
        ph.intrinsics = f.at("intrinsics");
        validate_intrinsics(ph.intrinsics, w);
        ph.created = f.time("created_utc");
        ph.file = add_file(f, w);
        if (!photo_ids.emplace(ph.old_id, 1).second) f.bad("id", "an id not used twice");
        p.photos.push_back(std::move(ph));
    }
    const auto& la = top.array("landmark_sets");
    for (std::size_t i = 0; i < la.size(); ++i) {
        const std::string w = sj + ": landmark_sets[" + std::to_string(i) + "]";
        Fields f{la[i], w};
        Plan::Lms s;
        s.old_id = f.i64("id");
        s.photo = f.opt_i64("photo_id");
        check_ref(s.photo, photo_ids, w, "photo");
        s.created = f.time("created_utc");
        s.pts = parse_landmark_list(f.at("landmarks"), w + ".landmarks");
        if (!set_ids.emplace(s.old_id, 1).second) f.bad("id", "an id not used twice");
        p.landmark_sets.push_back(std::move(s));
    }
    const auto& ra = top.array("rois");
    for (std::size_t i = 0; i < ra.size(); ++i) {
        const std::string w = sj + ": rois[" + std::to_string(i) + "]";
        Fields f{ra[i], w};
        Plan::Roi r;
        r.old_id = f.i64("id");
        r.photo = f.opt_i64("photo_id");
        check_ref(r.photo, photo_ids, w, "photo");
        r.created = f.time("created_utc");
        r.roi = f.at("roi");
        validate_roi(r.roi, w + ".roi");
        if (!roi_ids.emplace(r.old_id, 1).second) f.bad("id", "an id not used twice");
        p.rois.push_back(std::move(r));
    }
    const auto& ga = top.array("registrations");
    for (std::size_t i = 0; i < ga.size(); ++i) {
        const std::string w = sj + ": registrations[" + std::to_string(i) + "]";
        Fields f{ga[i], w};
        Plan::Reg r;
        r.old_id = f.i64("id");
        r.in.volume_id = f.opt_i64("volume_id");
        r.in.photo_id = f.opt_i64("photo_id");
        r.in.landmark_set_id = f.opt_i64("landmark_set_id");
        r.in.roi_id = f.opt_i64("roi_id");
        check_ref(r.in.volume_id, vol_ids, w, "volume");
        check_ref(r.in.photo_id, photo_ids, w, "photo");
        check_ref(r.in.landmark_set_id, set_ids, w, "landmark set");
        check_ref(r.in.roi_id, roi_ids, w, "roi");
        try {
            r.in.status = registration_status_from_string(f.str("status"));
        } catch (const StoreError& e) {
            throw StoreError(K::Invalid, w + ": " + e.what());
        }
        r.in.params = f.at("params");
        if (f.j.contains("initial_pose") && !f.j["initial_pose"].is_null()) r.in.initial_pose = f.j["initial_pose"];
        if (f.j.contains("final_pose") && !f.j["final_pose"].is_null()) r.in.final_pose = f.j["final_pose"];
        r.in.nmi = f.opt_f64("nmi");
        r.in.seconds = f.opt_f64("seconds");
        if (auto e = f.opt_i64("evaluations")) r.in.evaluations = static_cast<int>(*e);
        r.in.stages = f.at("stages");
        r.in.error = f.opt_str("error");
        r.created = f.time("created_utc");
        validate_registration_input(r.in, w);
        if (!reg_ids.emplace(r.old_id, 1).second) f.bad("id", "an id not used twice");
        p.registrations.push_back(std::move(r));
    }
    const auto& sa = top.array("results");
    for (std::size_t i = 0; i < sa.size(); ++i) {
        const std::string w = sj + ": results[" + std::to_string(i) + "]";
        Fields f{sa[i], w};
        Plan::Res r;
        r.old_id = f.i64("id");
        r.reg = f.opt_i64("registration_id");
        check_ref(r.reg, reg_ids, w, "registration");
        r.in.kind = f.str("kind");
        r.in.name = f.str("name");
        r.in.media_type = f.str("media_type");
        r.in.params = f.at("params");
        validate_result_input(r.in, w);
        r.created = f.time("created_utc");
        r.file = add_file(f, w);
        p.results.push_back(std::move(r));
    }
    return p;
}

Plan plan_plain_folder(const fs::path& root, const std::string& title_hint) {
    const std::string cjn = (root / "case.json").string();
    const json cj = read_json(root / "case.json", cjn);
    Fields f{cj, cjn};
    if (!cj.contains("format") || cj["format"] != kCaseFormat)
        throw StoreError(K::Invalid, cjn + ": format must be \"" + std::string(kCaseFormat) + "\"");
    Plan p;
    p.source = "case.json";
    p.uid = random_hex(16);
    std::string title = title_hint;
    if (title.empty()) title = fs::absolute(root).lexically_normal().filename().string();
    if (title.empty()) title = fs::absolute(root).lexically_normal().parent_path().filename().string();
    p.title = title.empty() ? std::string("imported case") : title.substr(0, 200);
    auto add_file = [&](const std::string& rel, const std::string& what) {
        InFile in;
        in.path = safe_file(root, rel, what);
        in.what = what;
        p.files.push_back(std::move(in));
        return p.files.size() - 1;
    };
    const std::string vol = f.str("volume");
    p.volumes.push_back({1, Modality::T1, fs::path(vol).filename().string(), {}, add_file(vol, cjn + ": volume")});
    if (auto mask = f.opt_str("brain_mask"))
        p.volumes.push_back({2, Modality::mask, fs::path(*mask).filename().string(), {},
                             add_file(*mask, cjn + ": brain_mask")});
    const std::string photo = f.str("photo");
    json cam = f.at("camera");
    validate_intrinsics(cam, cjn + ": camera");
    p.photos.push_back({1, fs::path(photo).filename().string(), {}, cam, add_file(photo, cjn + ": photo")});
    p.state = CaseState::photo_captured;
    if (auto lm = f.opt_str("landmarks")) {
        const auto path = safe_file(root, *lm, cjn + ": landmarks");
        const json lj = read_json(path, path.string());
        Fields lf{lj, path.string()};
        p.landmark_sets.push_back({1, 1, {}, parse_landmark_list(lf.at("landmarks"), path.string() + ": landmarks")});
        p.state = CaseState::landmarks;
    }
    if (auto roi = f.opt_str("roi")) {
        const auto path = safe_file(root, *roi, cjn + ": roi");
        json rj = read_json(path, path.string());
        validate_roi(rj, path.string());
        p.rois.push_back({1, 1, {}, rj});
        p.state = CaseState::roi;
    }
    return p;
}

}  // namespace

// ---- export ---------------------------------------------------------------------------------------

void CaseStore::export_case_folder(std::int64_t case_id, const fs::path& out_dir, const Actor& by) {
    std::error_code ec;
    if (fs::exists(fs::symlink_status(out_dir, ec)))
        throw StoreError(K::Conflict, out_dir.string() + ": already exists; export writes a new folder");
    const fs::path parent = out_dir.parent_path().empty() ? fs::path(".") : out_dir.parent_path();
    if (!fs::is_directory(parent, ec)) throw StoreError(K::NotFound, parent.string() + ": no such folder");
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    const auto files = build_export(I, case_id, at);
    const fs::path tmp = parent / ("." + out_dir.filename().string() + ".partial-" + random_hex(6));
    try {
        fs::create_directories(tmp);
        for (const auto& f : files) {
            const fs::path dest = tmp / f.rel;
            fs::create_directories(dest.parent_path());
            if (!f.sha.empty()) I.blobs.copy_to(f.sha, dest);  // verified on the way
            else fsu::write_file_durable(dest, f.text);
        }
        for (const char* sub : {"volumes", "photos", "results"})
            if (fs::is_directory(tmp / sub)) fsu::fsync_dir(tmp / sub);
        fsu::fsync_dir(tmp);
        fs::rename(tmp, out_dir);
        fsu::fsync_dir(parent);
    } catch (const fs::filesystem_error& e) {
        fs::remove_all(tmp, ec);
        throw StoreError(K::Io, out_dir.string() + ": export failed: " + e.what());
    } catch (...) {
        fs::remove_all(tmp, ec);
        throw;
    }
    sql::Tx tx(I.db);
    I.audit_row(by, "case.export", case_id, {{"format", "folder"}, {"files", files.size()}}, at);
    tx.commit();
}

void CaseStore::export_case_zip(std::int64_t case_id, const fs::path& zip_path, const Actor& by) {
    std::error_code ec;
    if (fs::exists(fs::symlink_status(zip_path, ec)))
        throw StoreError(K::Conflict, zip_path.string() + ": already exists; export writes a new file");
    const fs::path parent = zip_path.parent_path().empty() ? fs::path(".") : zip_path.parent_path();
    if (!fs::is_directory(parent, ec)) throw StoreError(K::NotFound, parent.string() + ": no such folder");
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    const auto files = build_export(I, case_id, at);
    for (const auto& f : files)
        if (!f.sha.empty()) I.blobs.verify(f.sha);  // never export a damaged file
    const fs::path tmp = parent / ("." + zip_path.filename().string() + ".partial-" + random_hex(6));
    int zerr = 0;
    zip_t* za = zip_open(tmp.c_str(), ZIP_CREATE | ZIP_EXCL, &zerr);
    if (!za) {
        zip_error_t e;
        zip_error_init_with_code(&e, zerr);
        std::string msg = zip_error_strerror(&e);
        zip_error_fini(&e);
        throw StoreError(K::Io, zip_path.string() + ": cannot create the zip: " + msg);
    }
    auto fail = [&](const std::string& what) {
        std::string msg = what + ": " + zip_strerror(za);
        zip_discard(za);
        fs::remove(tmp, ec);
        throw StoreError(K::Io, zip_path.string() + ": " + msg);
    };
    for (const auto& f : files) {
        zip_source_t* src = f.sha.empty() ? zip_source_buffer(za, f.text.data(), f.text.size(), 0)
                                          : zip_source_file(za, I.blobs.path_of(f.sha).c_str(), 0, -1)  /* -1: to the end (libzip 1.7) */;
        if (!src) fail("adding " + f.rel);
        const zip_int64_t idx = zip_file_add(za, f.rel.c_str(), src, ZIP_FL_ENC_UTF_8);
        if (idx < 0) {
            zip_source_free(src);
            fail("adding " + f.rel);
        }
        if (already_compressed(f.rel)) zip_set_file_compression(za, static_cast<zip_uint64_t>(idx), ZIP_CM_STORE, 0);
    }
    if (zip_close(za) != 0) fail("writing");
    try {
        fsu::Fd fd(::open(tmp.c_str(), O_RDONLY | O_CLOEXEC));
        if (fd.get() < 0 || ::fsync(fd.get()) != 0)
            throw StoreError(K::Io, zip_path.string() + ": cannot sync: " + std::strerror(errno));
        if (::rename(tmp.c_str(), zip_path.c_str()) != 0)
            throw StoreError(K::Io, zip_path.string() + ": cannot move into place: " + std::strerror(errno));
        fsu::fsync_dir(parent);
    } catch (...) {
        fs::remove(tmp, ec);
        throw;
    }
    sql::Tx tx(I.db);
    I.audit_row(by, "case.export", case_id, {{"format", "zip"}, {"files", files.size()}}, at);
    tx.commit();
}

// ---- import ---------------------------------------------------------------------------------------

std::int64_t CaseStore::import_case_folder(const fs::path& dir, const Actor& by) { return import_folder(dir, by, {}); }

std::int64_t CaseStore::import_folder(const fs::path& dir, const Actor& by, const std::string& title_hint) {
    std::error_code ec;
    if (!fs::is_directory(dir, ec)) throw StoreError(K::NotFound, dir.string() + ": no such folder");
    Plan p;
    if (fs::exists(dir / "store.json", ec)) p = plan_store_folder(dir);
    else if (fs::exists(dir / "case.json", ec)) p = plan_plain_folder(dir, title_hint);
    else throw StoreError(K::Invalid, dir.string() + ": holds neither store.json nor case.json");

    std::int64_t total = 0;
    for (const auto& f : p.files) total += static_cast<std::int64_t>(fs::file_size(f.path, ec));
    if (total > impl_->opt.max_import_bytes)
        throw StoreError(K::Invalid, dir.string() + ": " + std::to_string(total) + " bytes, more than the import limit of " +
                                         std::to_string(impl_->opt.max_import_bytes));
    {
        std::lock_guard lk(impl_->mu);
        if (auto st = impl_->db.prepare("SELECT id FROM cases WHERE uid = ?"); st.bind(1, p.uid).step())
            throw StoreError(K::Conflict, dir.string() + ": case " + p.uid + " is already in this store (case " +
                                              std::to_string(st.i64(0)) + ")");
    }
    // Blobs first (durable, content checked against the manifest); an abort past this point
    // leaves only unreferenced blobs.
    for (auto& f : p.files) {
        f.ref = impl_->blobs.put_file(f.path);
        if (!f.expect_sha.empty() && f.ref.sha256 != f.expect_sha)
            throw StoreError(K::Corrupt, f.what + ": " + f.path.filename().string() + " hashes to " +
                                             f.ref.sha256.substr(0, 16) + "..., store.json says " +
                                             f.expect_sha.substr(0, 16) + "... (damaged in transit?)");
    }

    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    auto t = [&](const std::string& s) { return s.empty() ? at : s; };
    sql::Tx tx(I.db);
    std::optional<std::int64_t> patient_id;
    if (p.patient) {
        auto st = I.db.prepare("SELECT id, family_name, given_name, birth_date FROM patients WHERE mrn = ?");
        st.bind(1, p.patient->mrn);
        if (st.step()) {
            if (st.text(1) != p.patient->family_name || st.text(2) != p.patient->given_name ||
                st.opt_text(3) != p.patient->birth_date)
                throw StoreError(K::Conflict, dir.string() + ": the case's patient MRN is patient " +
                                                  std::to_string(st.i64(0)) +
                                                  " here, with other identifiers (name or birth date); resolve first");
            patient_id = st.i64(0);
        } else {
            I.db.prepare("INSERT INTO patients (mrn, family_name, given_name, birth_date, created_utc) VALUES (?,?,?,?,?)")
                .bind(1, p.patient->mrn).bind(2, p.patient->family_name).bind(3, p.patient->given_name)
                .bind(4, p.patient->birth_date).bind(5, t(p.patient_created))
                .run();
            patient_id = I.db.last_id();
        }
    }
    const std::int64_t case_id = I.insert_case(p.uid, patient_id, p.title, p.state, t(p.created), t(p.updated));
    std::map<std::int64_t, std::int64_t> vol, pho, lms, roi, reg;
    for (const auto& v : p.volumes) vol[v.old_id] = I.insert_volume(case_id, v.m, v.name, p.files[v.file].ref, t(v.created));
    for (const auto& ph : p.photos)
        pho[ph.old_id] = I.insert_photo(case_id, ph.name, p.files[ph.file].ref, ph.intrinsics, t(ph.created));
    auto map_opt = [](const std::map<std::int64_t, std::int64_t>& m, const std::optional<std::int64_t>& id) {
        return id ? std::optional<std::int64_t>(m.at(*id)) : std::nullopt;
    };
    // Revisions are renumbered 1, 2, ... in the order of store.json (oldest first).
    for (const auto& s : p.landmark_sets)
        lms[s.old_id] = I.insert_landmarks(case_id, s.pts, map_opt(pho, s.photo), t(s.created), nullptr);
    for (const auto& r : p.rois) roi[r.old_id] = I.insert_roi(case_id, r.roi, map_opt(pho, r.photo), t(r.created), nullptr);
    for (const auto& r : p.registrations) {
        RegistrationInput in = r.in;
        in.volume_id = map_opt(vol, r.in.volume_id);
        in.photo_id = map_opt(pho, r.in.photo_id);
        in.landmark_set_id = map_opt(lms, r.in.landmark_set_id);
        in.roi_id = map_opt(roi, r.in.roi_id);
        reg[r.old_id] = I.insert_registration(case_id, in, t(r.created));
    }
    for (const auto& r : p.results) I.insert_result(case_id, map_opt(reg, r.reg), r.in, p.files[r.file].ref, t(r.created));
    I.audit_row(by, "case.import", case_id, {{"uid", p.uid}, {"from", p.source}, {"files", p.files.size()}}, at);
    tx.commit();
    return case_id;
}

namespace {

std::string zip_err(zip_t* za) { return zip_strerror(za); }

void check_entry_name(const std::string& name, const std::string& what) {
    auto bad = [&](const char* p) {
        throw StoreError(K::Invalid, what + ": entry '" + name.substr(0, 120) + "' " + p + "; nothing imported");
    };
    if (name.empty() || name.size() > 1024) bad("has an empty or too long name");
    if (name.front() == '/' || name.find('\\') != std::string::npos || name.find(':') != std::string::npos)
        bad("has an absolute or non-portable path");
    std::size_t start = 0;
    while (start <= name.size()) {
        const std::size_t end = name.find('/', start);
        const std::string part = name.substr(start, end == std::string::npos ? std::string::npos : end - start);
        if (part == ".." || part == ".") bad("leaves the case folder ('..' or '.' in its path)");
        if (part.empty() && end != std::string::npos && end + 1 != name.size()) bad("has an empty path component");
        if (end == std::string::npos) break;
        start = end + 1;
    }
}

/// Removes a folder tree when it goes out of scope.
struct TreeGuard {
    fs::path p;
    ~TreeGuard() {
        std::error_code ec;
        if (!p.empty()) fs::remove_all(p, ec);
    }
};

}  // namespace

std::int64_t CaseStore::import_case_zip(const fs::path& zip_path, const Actor& by) {
    const std::string what = zip_path.string();
    std::error_code ec;
    if (!fs::is_regular_file(zip_path, ec)) throw StoreError(K::NotFound, what + ": no such file");
    int zerr = 0;
    zip_t* za = zip_open(zip_path.c_str(), ZIP_RDONLY | ZIP_CHECKCONS, &zerr);
    if (!za) {
        zip_error_t e;
        zip_error_init_with_code(&e, zerr);
        std::string msg = zip_error_strerror(&e);
        zip_error_fini(&e);
        throw StoreError(K::Invalid, what + ": not a readable zip archive (" + msg + "); nothing imported");
    }
    std::unique_ptr<zip_t, void (*)(zip_t*)> guard(za, [](zip_t* z) { zip_discard(z); });
    const zip_int64_t n = zip_get_num_entries(za, 0);
    if (n <= 0) throw StoreError(K::Invalid, what + ": the archive is empty; nothing imported");
    if (n > 100000) throw StoreError(K::Invalid, what + ": more than 100000 entries; nothing imported");
    // Check every name and the total size before writing anything.
    std::int64_t total = 0;
    std::vector<std::pair<std::string, zip_uint64_t>> entries;
    for (zip_int64_t i = 0; i < n; ++i) {
        zip_stat_t st;
        zip_stat_init(&st);
        if (zip_stat_index(za, static_cast<zip_uint64_t>(i), 0, &st) != 0 || !(st.valid & ZIP_STAT_NAME) ||
            !(st.valid & ZIP_STAT_SIZE))
            throw StoreError(K::Invalid, what + ": entry " + std::to_string(i) + " cannot be read (" + zip_err(za) +
                                             "); nothing imported");
        const std::string name = st.name;
        check_entry_name(name, what);
        total += static_cast<std::int64_t>(st.size);
        if (total > impl_->opt.max_import_bytes || total < 0)
            throw StoreError(K::Invalid, what + ": unpacks to more than the import limit of " +
                                             std::to_string(impl_->opt.max_import_bytes) + " bytes; nothing imported");
        entries.emplace_back(name, st.size);
    }
    const fs::path tmp_root = impl_->dir / "tmp";
    fs::create_directories(tmp_root, ec);
    TreeGuard tmp{tmp_root / ("import-" + random_hex(8))};
    if (!fs::create_directory(tmp.p, ec))
        throw StoreError(K::Io, tmp.p.string() + ": cannot create the import folder: " + ec.message());
    std::vector<char> buf(1 << 20);
    for (zip_int64_t i = 0; i < n; ++i) {
        const auto& [name, size] = entries[static_cast<std::size_t>(i)];
        const fs::path dest = tmp.p / name;
        if (name.back() == '/') {
            fs::create_directories(dest, ec);
            if (ec) throw StoreError(K::Invalid, what + ": entry '" + name + "': cannot create the folder: " + ec.message());
            continue;
        }
        fs::create_directories(dest.parent_path(), ec);
        fsu::Fd out(::open(dest.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_NOFOLLOW | O_CLOEXEC, 0644));
        if (out.get() < 0)
            throw StoreError(K::Invalid, what + ": entry '" + name + "': cannot be unpacked (" + std::strerror(errno) +
                                             ", a duplicate name?); nothing imported");
        zip_file_t* zf = zip_fopen_index(za, static_cast<zip_uint64_t>(i), 0);
        if (!zf)
            throw StoreError(K::Invalid, what + ": entry '" + name + "' cannot be opened (" + zip_err(za) +
                                             "); nothing imported");
        std::unique_ptr<zip_file_t, int (*)(zip_file_t*)> zfg(zf, zip_fclose);
        zip_uint64_t got = 0;
        for (;;) {
            const zip_int64_t r = zip_fread(zf, buf.data(), buf.size());
            if (r < 0)
                throw StoreError(K::Invalid, what + ": entry '" + name + "' is damaged (" + zip_file_strerror(zf) +
                                                 "); nothing imported");
            if (r == 0) break;
            got += static_cast<zip_uint64_t>(r);
            if (got > size)
                throw StoreError(K::Invalid, what + ": entry '" + name + "' is longer than its header says; nothing imported");
            for (zip_int64_t off = 0; off < r;) {
                const ssize_t w = ::write(out.get(), buf.data() + off, static_cast<std::size_t>(r - off));
                if (w < 0) {
                    if (errno == EINTR) continue;
                    throw StoreError(K::Io, tmp.p.string() + ": cannot unpack '" + name + "': " + std::strerror(errno));
                }
                off += w;
            }
        }
        if (got != size)
            throw StoreError(K::Invalid, what + ": entry '" + name + "' is shorter than its header says; nothing imported");
    }
    guard.reset();
    // The case folder is the archive's root, or its one top folder.
    fs::path root = tmp.p;
    if (!fs::exists(root / "store.json") && !fs::exists(root / "case.json")) {
        std::vector<fs::path> tops;
        for (const auto& e : fs::directory_iterator(root)) tops.push_back(e.path());
        if (tops.size() == 1 && fs::is_directory(tops[0]) &&
            (fs::exists(tops[0] / "store.json") || fs::exists(tops[0] / "case.json")))
            root = tops[0];
        else
            throw StoreError(K::Invalid, what + ": holds neither store.json nor case.json at its root or in one top "
                                                "folder; nothing imported");
    }
    try {
        // A plain case folder is titled after its folder: the archive's top folder or its name.
        const std::string title = root == tmp.p ? zip_path.stem().string() : root.filename().string();
        return import_folder(root, by, title);
    } catch (const StoreError& e) {
        // Name the archive, not the temporary folder.
        std::string msg = e.what();
        const std::string tp = root.string();
        for (std::size_t pos; (pos = msg.find(tp + "/")) != std::string::npos;) msg.replace(pos, tp.size() + 1, what + ": ");
        for (std::size_t pos; (pos = msg.find(tp)) != std::string::npos;) msg.replace(pos, tp.size(), what);
        throw StoreError(e.kind(), msg + "; nothing imported");
    }
}

}  // namespace cf::db
