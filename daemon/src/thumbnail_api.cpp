// Thumbnails of the case archive (thumbnail_api.hpp, docs/api/cases.md "Thumbnails").
#include "thumbnail_api.hpp"

#include <fstream>
#include <functional>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>
#include <string>
#include <system_error>

#include "case_api.hpp"
#include "cortexfuse/core/case.hpp"

namespace cf::daemon {

namespace fs = std::filesystem;
using nlohmann::json;
using namespace cf::db;

namespace {

struct Source {
    std::string kind;  // "fused" or "photo"
    std::string key;   // what the picture is made of; its hash names the cache file
    std::optional<PhotoRecord> photo;
};

/// What the case's thumbnail shows now: its fused view (a succeeded registration with a pose and
/// a plan surface, registered_view's choice, as the Fused screen's), else its newest photo.
std::optional<Source> source_of(const CaseRecord& rec) {
    std::optional<Source> photo_src;
    if (!rec.photos.empty()) {
        const PhotoRecord& p = rec.photos.back();
        photo_src = Source{"photo", "photo " + p.blob.sha256, p};
    }
    try {
        const RegisteredView v = registered_view(rec, std::nullopt, "thumbnail", "", "");
        const std::string roi = rec.roi ? std::to_string(rec.roi->id) : "-";
        return Source{"fused", "fused reg " + std::to_string(v.reg.id) + " photo " + v.photo.blob.sha256 + " surface " + v.surface.blob.sha256 + " roi " + roi,
                      v.photo};
    } catch (const ApiError&) {
        return photo_src;  // not registered (or no surface yet): the photo, or nothing
    }
}

std::string hex64(std::uint64_t v) {
    static const char* d = "0123456789abcdef";
    std::string s(16, '0');
    for (int i = 15; i >= 0; --i, v >>= 4) s[std::size_t(i)] = d[v & 15];
    return s;
}

/// FNV-1a over the key: only names the cache file (the key itself is stored beside the JPEG
/// and compared, so a collision cannot serve another picture).
std::uint64_t fnv1a(const std::string& s) {
    std::uint64_t h = 1469598103934665603ull;
    for (unsigned char c : s) h = (h ^ c) * 1099511628211ull;
    return h;
}

std::string read_all(const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    if (!in) return {};
    std::ostringstream s;
    s << in.rdbuf();
    return s.str();
}

/// The photo shrunk to kThumbnailWidthPx wide (area averaging), as JPEG.
std::string photo_thumbnail(CaseStore& st, const PhotoRecord& p, const std::string& what) {
    const std::string bytes = st.read_blob(p.blob.sha256);
    const cv::Mat img = cv::imdecode(cv::Mat(1, int(bytes.size()), CV_8U, const_cast<char*>(bytes.data())), cv::IMREAD_COLOR);
    if (img.empty()) throw ApiError(500, "io_error", what + ": photo " + std::to_string(p.id) + " (" + p.original_name + ") does not decode");
    const int w = std::min(kThumbnailWidthPx, img.cols), h = std::max(1, int(std::lround(double(img.rows) * w / img.cols)));
    cv::Mat small;
    cv::resize(img, small, cv::Size(w, h), 0, 0, cv::INTER_AREA);
    std::vector<uchar> out;
    cv::imencode(".jpg", small, out, {cv::IMWRITE_JPEG_QUALITY, 82});
    return std::string(out.begin(), out.end());
}

/// The fused view at thumbnail size from the POST /api/cases/{id}/fused endpoint itself (the
/// registered camera, the photo's aspect ratio), as JPEG.
std::string fused_thumbnail(const EndpointRegistry& reg, std::int64_t id, const PhotoRecord& photo, const Client& client) {
    const std::string path = "/api/cases/" + std::to_string(id) + "/fused";
    const Endpoint* e = reg.find("POST", path);
    if (!e) throw ApiError(503, "unavailable", "thumbnail: the fused view is not available in this daemon");
    const int pw = photo.intrinsics.value("width", 0), ph = photo.intrinsics.value("height", 0);
    if (pw <= 0 || ph <= 0) throw ApiError(500, "io_error", "thumbnail: photo " + std::to_string(photo.id) + " has no size in its intrinsics");
    Request req;
    req.method = "POST";
    req.path = path;
    req.params["id"] = std::to_string(id);
    req.client = client;
    req.body = {{"width", kThumbnailWidthPx},
                {"height", std::max(16, int(std::lround(double(ph) * kThumbnailWidthPx / pw)))},
                {"format", "jpeg"},
                {"quality", 82},
                {"surface_opacity", 0.7}};
    Response r = e->handler(req);
    if (r.status != 200 || r.bytes.empty()) throw ApiError(500, "io_error", "thumbnail: the fused view answered no picture");
    return std::move(r.bytes);
}

}  // namespace

void register_thumbnail_endpoints(EndpointRegistry& reg, CaseStore& store, const fs::path& work_dir) {
    CaseStore* st = &store;
    const EndpointRegistry* registry = &reg;
    const fs::path dir = work_dir / "thumbnails";
    auto mu = std::make_shared<std::mutex>();
    reg.add({"GET", "/api/cases/{id}/thumbnail", "cases.thumbnail", Access::read,
             "A small JPEG of the case for the archive list: its fused view when registered and planned, else its newest photo (made once, cached)",
             on_own_stack([st, registry, dir, mu](const Request& r) {
                 const std::int64_t id = case_id_param(r);
                 const std::string what = "case " + std::to_string(id) + " thumbnail";
                 return guarded([&] {
                     const CaseRecord rec = st->get_case(id);  // 404 for an unknown case
                     const auto src = source_of(rec);
                     if (!src) throw ApiError(404, "not_found", what + ": no photo or fused view yet (add a photo, or register the case)");
                     const std::string stem = "case_" + std::to_string(id) + "_" + hex64(fnv1a(src->key));
                     const fs::path jpg = dir / (stem + ".jpg"), keyf = dir / (stem + ".key");
                     std::lock_guard lk(*mu);
                     std::string bytes, note;
                     std::string kind = src->kind;
                     bool hit = false;
                     const std::string stored_key = read_all(keyf);
                     if (stored_key.rfind(src->key + "\n", 0) == 0) {  // "<key>\n<kind>\n<note>"
                         bytes = read_all(jpg);
                         hit = !bytes.empty();
                         if (hit) {
                             std::istringstream in(stored_key.substr(src->key.size() + 1));
                             std::getline(in, kind);
                             std::getline(in, note);
                         }
                     }
                     if (!hit) {
                         kind = src->kind;
                         if (src->kind == "fused") {
                             try {
                                 bytes = fused_thumbnail(*registry, id, *src->photo, r.client);
                             } catch (const ApiError& e) {
                                 // A registered case whose fused view does not make a picture (e.g.
                                 // the camera points away from the surface): its photo, saying why.
                                 if (e.status >= 500) throw;  // busy or broken: not cached as a fallback
                                 note = e.what();
                                 kind = "photo";
                                 bytes = photo_thumbnail(*st, *src->photo, what);
                             }
                         } else {
                             bytes = photo_thumbnail(*st, *src->photo, what);
                         }
                         // JPEG first, then its key: a key names only a complete picture. Both are
                         // written beside and renamed; older pictures of the case are removed.
                         std::error_code ec;
                         fs::create_directories(dir, ec);
                         try {
                             write_file_atomic(jpg, bytes);
                             write_file_atomic(keyf, src->key + "\n" + kind + "\n" + note);
                         } catch (const std::exception& e) {
                             fs::remove(keyf, ec);
                             fs::remove(jpg, ec);
                             throw ApiError(500, "io_error", what + ": could not cache it: " + e.what());
                         }
                         for (const auto& f : fs::directory_iterator(dir, ec)) {
                             const std::string n = f.path().filename().string();
                             if (n.rfind("case_" + std::to_string(id) + "_", 0) == 0 && n.rfind(stem, 0) != 0) fs::remove(f.path(), ec);
                         }
                     }
                     Response resp = Response::binary(std::move(bytes), "image/jpeg");
                     resp.headers["X-Thumbnail-Source"] = kind;
                     resp.headers["X-Thumbnail-Cache"] = hit ? "hit" : "miss";
                     if (!note.empty()) resp.headers["X-Thumbnail-Note"] = note.substr(0, 200);
                     resp.headers["Cache-Control"] = "no-cache";
                     return resp;
                 });
             })});
}

}  // namespace cf::daemon
