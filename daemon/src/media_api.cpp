// Preoperative data from a USB stick (media_api.hpp, docs/api/case-data.md).
#include "media_api.hpp"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <fstream>
#include <map>
#include <string>
#include <system_error>

#include "case_api.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/volume.hpp"
#include "scratch_dir.hpp"

namespace cf::daemon {

namespace fs = std::filesystem;
using nlohmann::json;
using namespace cf::db;

namespace {

ApiError bad(const std::string& what, const std::string& problem) { return ApiError(400, "bad_request", what + ": " + problem); }

/// The volume file kinds an upload takes (docs/api/case-data.md), by name; "" for others.
std::string file_kind(const std::string& name) {
    std::string n = name;
    std::transform(n.begin(), n.end(), n.begin(), [](unsigned char c) { return char(std::tolower(c)); });
    auto ends = [&](const char* e) { const std::string s(e); return n.size() > s.size() && n.compare(n.size() - s.size(), s.size(), s) == 0; };
    if (ends(".nii") || ends(".nii.gz")) return "nifti";
    if (ends(".nrrd")) return "nrrd";
    if (ends(".mha")) return "metaimage";
    return "";
}

/// A DICOM Part 10 file: "DICM" after the 128-byte preamble (what GDCM looks for first).
bool is_dicom_file(const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    char b[132];
    if (!in.read(b, 132)) return false;
    return std::string(b + 128, 4) == "DICM";
}

/// The media root, resolved (symlinks and all); empty when it does not exist.
fs::path resolved_root(const fs::path& root) {
    std::error_code ec;
    const fs::path r = fs::canonical(root, ec);
    return ec ? fs::path() : r;
}

bool inside(const fs::path& p, const fs::path& root) {
    const std::string a = p.string(), r = root.string();
    return a == r || (a.size() > r.size() && a.compare(0, r.size(), r) == 0 && (r.back() == '/' || a[r.size()] == '/'));
}

/// A plain file name for the store made from `s` (letters, digits, '_', '-', '.'; no leading dot).
std::string plain_name(std::string s) {
    for (auto& c : s)
        if (!std::isalnum(static_cast<unsigned char>(c)) && c != '_' && c != '-' && c != '.') c = '_';
    while (!s.empty() && s.front() == '.') s.erase(0, 1);
    if (s.size() > 100) s.resize(100);
    return s.empty() ? "volume" : s;
}

/// `message` with `prefix` + "/" taken out (errors name the file on the stick, not our folders).
std::string without(std::string message, const fs::path& prefix) {
    const std::string p = prefix.string() + "/";
    for (std::size_t k; (k = message.find(p)) != std::string::npos;) message.erase(k, p.size());
    return message;
}

json list_media(const fs::path& configured_root) {
    const fs::path root = resolved_root(configured_root);
    json out{{"root", configured_root.string()}, {"volumes", json::array()}, {"truncated", false}};
    if (root.empty() || !fs::is_directory(root)) {
        out["present"] = false;
        out["note"] = "no removable media: " + configured_root.string() + " does not exist or is not a folder (media.removable_root)";
        return out;
    }
    out["present"] = true;
    struct Dicom {
        int files = 0;
        std::int64_t bytes = 0;
    };
    std::map<std::string, Dicom> dicom_dirs;
    std::vector<json> files;
    std::error_code ec;
    int seen = 0;
    // Not following symlinks (a link on a stick cannot lead the listing elsewhere); at most 6
    // levels and 20000 entries (a stick full of photos is cut off, and says so).
    for (fs::recursive_directory_iterator it(root, fs::directory_options::skip_permission_denied, ec), end; !ec && it != end; it.increment(ec)) {
        if (++seen > 20000) {
            out["truncated"] = true;
            break;
        }
        if (it.depth() >= 6) it.disable_recursion_pending();
        std::error_code e2;
        if (!it->is_regular_file(e2) || it->is_symlink(e2)) continue;
        const fs::path p = it->path();
        const std::string rel = fs::relative(p, root, e2).string();
        const std::string kind = file_kind(p.filename().string());
        const std::int64_t size = std::int64_t(it->file_size(e2));
        if (!kind.empty()) {
            files.push_back({{"path", rel}, {"kind", kind}, {"size_bytes", size}});
        } else if (is_dicom_file(p)) {
            const std::string dir = fs::relative(p.parent_path(), root, e2).string();
            auto& d = dicom_dirs[dir.empty() ? "." : dir];
            d.files++;
            d.bytes += size;
        }
    }
    for (const auto& [dir, d] : dicom_dirs) files.push_back({{"path", dir}, {"kind", "dicom"}, {"files", d.files}, {"size_bytes", d.bytes}});
    std::sort(files.begin(), files.end(), [](const json& a, const json& b) { return a["path"].get<std::string>() < b["path"].get<std::string>(); });
    for (auto& f : files) out["volumes"].push_back(std::move(f));
    return out;
}

}  // namespace

void register_media_endpoints(EndpointRegistry& reg, CaseStore& store, const fs::path& root, const fs::path& work_dir, std::int64_t max_bytes) {
    CaseStore* st = &store;
    reg.add({"GET", "/api/media/volumes", "media.volumes", Access::write,
             "Volumes on removable media under media.removable_root: NIfTI/NRRD/MetaImage files and folders of DICOM files",
             on_own_stack([root](const Request&) { return ok(list_media(root)); })});

    reg.add({"POST", "/api/cases/{id}/volumes/import-media", "cases.import_media_volume", Access::write,
             "Import a volume from removable media {path (relative to media.removable_root), modality?}: read and checked as an upload before it is stored",
             on_own_stack([st, root, work_dir, max_bytes](const Request& r) {
                 const auto id = case_id_param(r);
                 const json& b = r.body;
                 if (!b.is_object()) throw bad("media import", "body must be a JSON object {path, modality?}");
                 for (auto it = b.begin(); it != b.end(); ++it)
                     if (it.key() != "path" && it.key() != "modality" && it.key() != "id") throw bad("media import " + it.key(), "unknown field");
                 if (!b.contains("path") || !b["path"].is_string() || b["path"].get<std::string>().empty())
                     throw bad("media import path", "missing (a file or DICOM folder as GET /api/media/volumes lists it)");
                 const std::string rel = b["path"].get<std::string>();
                 const std::string what = "media " + rel.substr(0, 200);
                 const fs::path relp(rel);
                 if (rel.size() > 1024 || relp.is_absolute()) throw bad(what, "must be a path relative to media.removable_root");
                 for (const auto& part : relp)
                     if (part == "..") throw bad(what, "must not hold '..'");
                 const std::string mod_text = b.contains("modality") ? (b["modality"].is_string() ? b["modality"].get<std::string>() : "") : "T1";
                 Modality mod;
                 try {
                     mod = modality_from_string(mod_text);
                 } catch (const StoreError& e) {
                     throw bad(what + " modality", e.what());
                 }
                 const fs::path rroot = resolved_root(root);
                 if (rroot.empty()) throw ApiError(404, "not_found", what + ": no removable media (" + root.string() + " does not exist)");
                 std::error_code ec;
                 const fs::path full = fs::canonical(rroot / relp, ec);
                 if (ec) throw ApiError(404, "not_found", what + ": no such file or folder on the media");
                 if (!inside(full, rroot)) throw bad(what, "leads outside media.removable_root (a link?)");
                 return guarded([&] {
                     st->get_case(id);  // 404 before reading anything
                     Scratch scratch(work_dir, "media");
                     fs::path file;
                     std::string kind;
                     json geometry;
                     auto geom_json = [](const VolumeGeometry& g) {
                         return json{{"dims", g.dims}, {"spacing_mm", {g.spacing_mm.x(), g.spacing_mm.y(), g.spacing_mm.z()}}};
                     };
                     if (fs::is_directory(full)) {
                         // A DICOM series: read by core (GDCM, one series per folder), stored as NIfTI.
                         kind = "dicom";
                         int dicoms = 0;
                         for (const auto& e : fs::directory_iterator(full, ec))
                             if (e.is_regular_file() && is_dicom_file(e.path())) ++dicoms;
                         if (dicoms == 0) throw bad(what, "the folder holds no DICOM files (and is not a volume file)");
                         file = scratch.dir / (plain_name(full.filename().string()) + ".nii.gz");
                         try {
                             if (mod == Modality::mask) {
                                 const LabelVolume m = load_mask(full);
                                 if (m.count_nonzero() == 0) throw InputError(rel, "the mask is empty (no non-zero voxel)");
                                 save_mask(m, file);
                                 geometry = geom_json(m.geom);
                             } else {
                                 const Volume v = load_volume(full);
                                 save_volume(v, file);
                                 geometry = geom_json(v.geom);
                             }
                         } catch (const std::exception& e) {
                             throw bad(what, "not a readable DICOM series: " + without(without(e.what(), rroot), scratch.dir));
                         }
                     } else {
                         kind = file_kind(full.filename().string());
                         if (kind.empty()) throw bad(what, "not a volume file (.nii, .nii.gz, .nrrd, .mha) nor a DICOM folder");
                         const auto size = std::int64_t(fs::file_size(full, ec));
                         if (ec) throw ApiError(500, "io_error", what + ": cannot read its size: " + ec.message());
                         if (size > max_bytes)
                             throw ApiError(413, "payload_too_large", what + ": " + std::to_string(size) + " bytes is over store.max_upload_bytes (" + std::to_string(max_bytes) + ")");
                         // A copy first: what is checked is what is stored, even if the stick changes.
                         file = scratch.dir / plain_name(full.filename().string());
                         fs::copy_file(full, file, ec);
                         if (ec) throw ApiError(500, "io_error", what + ": cannot copy it from the media: " + ec.message());
                         try {
                             if (mod == Modality::mask) {
                                 const LabelVolume m = load_mask(file);
                                 if (m.count_nonzero() == 0) throw InputError(rel, "the mask is empty (no non-zero voxel)");
                                 geometry = geom_json(m.geom);
                             } else {
                                 geometry = geom_json(load_volume(file).geom);
                             }
                         } catch (const std::exception& e) {
                             throw bad(what, "not a readable volume: " + without(e.what(), scratch.dir));
                         }
                     }
                     const VolumeRecord v = st->import_volume(id, file, mod, actor_of(r.client));
                     json j{{"id", v.id}, {"modality", to_string(v.modality)}, {"original_name", v.original_name}, {"sha256", v.blob.sha256},
                            {"size_bytes", v.blob.size_bytes}, {"geometry", geometry}, {"source", {{"path", rel}, {"kind", kind}}}};
                     return ok(j, 201);
                 });
             })});
}

}  // namespace cf::daemon
