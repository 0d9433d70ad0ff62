// The photographic overlay: texture coordinates with visibility, cast back, exports.
#include "cortexfuse/core/overlay.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <nlohmann/json.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <sstream>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/rasterizer.hpp"

namespace fs = std::filesystem;

namespace cf {
namespace {

/// Writes bytes to a temporary name beside `path` and renames: whole or absent.
void write_bytes_atomic(const fs::path& path, const std::string& bytes) {
    fs::path tmp = path;
    tmp.replace_filename(path.stem().string() + ".part" + path.extension().string());
    {
        std::ofstream f(tmp, std::ios::binary | std::ios::trunc);
        if (!f) throw InputError(path.string(), "cannot write");
        f.write(bytes.data(), std::streamsize(bytes.size()));
        if (!f) {
            f.close();
            std::error_code ec;
            fs::remove(tmp, ec);
            throw InputError(path.string(), "write failed");
        }
    }
    std::error_code ec;
    fs::rename(tmp, path, ec);
    if (ec) {
        fs::remove(tmp, ec);
        throw InputError(path.string(), "cannot write: " + ec.message());
    }
}

std::string png_bytes(const cv::Mat& img, const fs::path& context) {
    std::vector<uchar> buf;
    if (img.empty() || !cv::imencode(".png", img, buf)) throw InputError(context.string(), "cannot encode the texture PNG");
    return std::string(buf.begin(), buf.end());
}

void check_mapping(const SurfaceMesh& mesh, const TextureMapping& tm, const fs::path& out) {
    mesh.validate(out.string());
    if (tm.uv.size() != mesh.vertices.size() || tm.in_roi.size() != mesh.vertices.size())
        throw InputError(out.string(), "texture mapping does not match the mesh");
}

/// Triangles whose three vertices are textured (inside the ROI) and the others.
void split_faces(const SurfaceMesh& mesh, const TextureMapping& tm, std::vector<uint32_t>& textured,
                 std::vector<uint32_t>& plain) {
    for (const auto& t : mesh.triangles) {
        const bool tex = tm.in_roi[size_t(t[0])] && tm.in_roi[size_t(t[1])] && tm.in_roi[size_t(t[2])];
        auto& dst = tex ? textured : plain;
        for (int q = 0; q < 3; ++q) dst.push_back(uint32_t(t[q]));
    }
}

}  // namespace

TextureMapping map_texture(const SurfaceMesh& mesh, const Intrinsics& K, const Pose& T, const cv::Mat& roi_alpha,
                           const TextureParams& P) {
    mesh.validate("mesh");
    K.validate("camera");
    if (!is_rigid(T)) throw InputError("result pose", "T_camera_from_world is not a rigid transform");
    if (!(P.depth_tolerance_mm >= 0 && P.depth_tolerance_mm <= 20 && P.depth_tolerance_px >= 0 && P.depth_tolerance_px <= 10 &&
          P.min_facing >= -1 && P.min_facing <= 1))
        throw InputError("texture parameters", "tolerances out of range");
    if (!roi_alpha.empty() && (roi_alpha.type() != CV_8UC1 || roi_alpha.cols != K.width || roi_alpha.rows != K.height))
        throw InputError("roi", "alpha mask must be 8-bit and of the photo's size");
    const std::vector<Eigen::Vector3f> normals =
        mesh.normals.size() == mesh.vertices.size() ? mesh.normals : outward_vertex_normals(mesh.vertices, mesh.triangles);

    const RasterBuffers rb = rasterize(mesh.raster(), K, T, 1.0f);
    const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
    const Eigen::Vector3d t = T.topRightCorner<3, 1>();
    const size_t n = mesh.vertices.size();
    TextureMapping tm;
    tm.uv.assign(n, Eigen::Vector2f::Zero());
    tm.pixel.assign(n, Eigen::Vector2d::Constant(std::numeric_limits<double>::quiet_NaN()));
    tm.visible.assign(n, 0);
    tm.in_roi.assign(n, 0);
    for (size_t i = 0; i < n; ++i) {
        const Eigen::Vector3d pc = R * mesh.vertices[i].cast<double>() + t;
        const auto px = pc.z() > 1.0 ? project_camera(K, pc) : std::nullopt;
        if (!px || !(px->x() >= -0.5 && px->y() >= -0.5 && px->x() < K.width - 0.5 && px->y() < K.height - 0.5)) {
            ++tm.outside_image;
            continue;
        }
        const Eigen::Vector3d view = pc.normalized();
        const double facing = (R * normals[i].cast<double>()).dot(view);  // < 0: faces the camera
        if (facing >= -P.min_facing) {
            ++tm.back_facing;
            continue;
        }
        const int u = std::clamp(int(std::lround(px->x())), 0, K.width - 1);
        const int v = std::clamp(int(std::lround(px->y())), 0, K.height - 1);
        const float zb = rb.depth_mm[rb.index(u, v)];
        // Slack: the z-buffer holds the surface at the pixel centre, up to ~0.7 px away from
        // the vertex; the depth changes by footprint / |cos| per pixel on a slanted surface.
        const double footprint = pc.z() / std::max(K.fx, K.fy);
        const double tol = P.depth_tolerance_mm + P.depth_tolerance_px * footprint / std::max(0.2, -facing);
        if (!std::isfinite(zb) || pc.z() > double(zb) + tol) {
            ++tm.occluded;
            continue;
        }
        tm.visible[i] = 1;
        ++tm.visible_count;
        tm.pixel[i] = *px;
        tm.uv[i] = Eigen::Vector2f(float((px->x() + 0.5) / K.width), float((px->y() + 0.5) / K.height));
        if (roi_alpha.empty() || roi_alpha.at<uint8_t>(v, u) >= 128) {
            tm.in_roi[i] = 1;
            ++tm.roi_count;
        }
    }
    if (tm.visible_count == 0) {
        // Say why: behind the camera / outside the picture, or looking at the inside.
        const Eigen::Vector3d cam_world = -R.transpose() * t;
        Eigen::Vector3d c = Eigen::Vector3d::Zero();
        for (const auto& p : mesh.vertices) c += p.cast<double>();
        c /= double(n);
        const double along = (R * c + t).z();
        throw InputError("result pose", along <= 0 ? "the camera points away from the brain (the surface is behind it)"
                                                   : "the camera sees no part of the brain surface (outside the picture, "
                                                     "or the camera is inside the brain)");
        (void)cam_world;
    }
    return tm;
}

std::optional<SurfaceHit> cast_back(const SurfaceMesh& mesh, const Intrinsics& K, const Pose& T, const Eigen::Vector2d& pixel) {
    mesh.validate("mesh");
    if (!is_rigid(T)) throw InputError("pose", "T_camera_from_world is not a rigid transform");
    if (!pixel.allFinite()) throw InputError("pixel", "not finite");
    const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
    const Eigen::Vector3d o = -R.transpose() * T.topRightCorner<3, 1>();
    const Eigen::Vector3d d = (R.transpose() * backproject_ray(K, pixel)).normalized();
    double best = std::numeric_limits<double>::infinity();
    SurfaceHit hit;
    for (size_t f = 0; f < mesh.triangles.size(); ++f) {
        const auto& tri = mesh.triangles[f];
        const Eigen::Vector3d a = mesh.vertices[size_t(tri[0])].cast<double>(), b = mesh.vertices[size_t(tri[1])].cast<double>(),
                              c = mesh.vertices[size_t(tri[2])].cast<double>();
        // Möller–Trumbore, both windings.
        const Eigen::Vector3d e1 = b - a, e2 = c - a, pv = d.cross(e2);
        const double det = e1.dot(pv);
        if (std::abs(det) < 1e-12) continue;
        const double inv = 1.0 / det;
        const Eigen::Vector3d tv = o - a;
        const double u = tv.dot(pv) * inv;
        if (u < 0 || u > 1) continue;
        const Eigen::Vector3d qv = tv.cross(e1);
        const double v = d.dot(qv) * inv;
        if (v < 0 || u + v > 1) continue;
        const double s = e2.dot(qv) * inv;
        if (s > 1e-6 && s < best) {
            best = s;
            hit.triangle = int(f);
            hit.bary = Eigen::Vector3d(1 - u - v, u, v);
        }
    }
    if (hit.triangle < 0) return std::nullopt;
    hit.p_world_mm = o + best * d;
    hit.depth_mm = (R * hit.p_world_mm + T.topRightCorner<3, 1>()).z();
    const auto& tri = mesh.triangles[size_t(hit.triangle)];
    if (mesh.normals.size() == mesh.vertices.size()) {
        Eigen::Vector3d nn = Eigen::Vector3d::Zero();
        for (int q = 0; q < 3; ++q) nn += hit.bary[q] * mesh.normals[size_t(tri[q])].cast<double>();
        hit.normal_world = nn.normalized();
    } else {
        const Eigen::Vector3d a = mesh.vertices[size_t(tri[0])].cast<double>();
        hit.normal_world = (mesh.vertices[size_t(tri[1])].cast<double>() - a)
                               .cross(mesh.vertices[size_t(tri[2])].cast<double>() - a)
                               .normalized();
    }
    return hit;
}

LabelVolume craniotomy_keep_mask(const VolumeGeometry& g, const SurfaceMesh& mesh, const Intrinsics& K,
                                 const Pose& T, const cv::Mat& roi_alpha, double depth_margin_mm) {
    mesh.validate("brain surface");
    K.validate("camera");
    if (!is_rigid(T)) throw InputError("pose", "T_camera_from_world is not a rigid transform");
    if (!roi_alpha.empty() && (roi_alpha.type() != CV_8UC1 || roi_alpha.cols != K.width || roi_alpha.rows != K.height))
        throw InputError("roi", "alpha mask must be 8-bit and of the photo's size");
    if (!(depth_margin_mm >= 0 && depth_margin_mm <= 50)) throw InputError("craniotomy depth margin", "out of range 0..50 mm");
    if (g.voxel_count() == 0) throw InputError("CT grid", "has no voxels");
    const RasterBuffers zb = rasterize(mesh.raster(), K, T);
    LabelVolume m;
    m.geom = g;
    m.voxels.assign(g.voxel_count(), 1);
    const Eigen::Affine3d cam_from_index = Eigen::Affine3d(T.matrix()) * g.world_from_index();
    for (int k = 0; k < g.dims[2]; ++k)
        for (int j = 0; j < g.dims[1]; ++j)
            for (int i = 0; i < g.dims[0]; ++i) {
                const Eigen::Vector3d pc = cam_from_index * Eigen::Vector3d(i, j, k);
                if (pc.z() <= 1.0) continue;
                const auto px = project_camera(K, pc);
                if (!px) continue;
                const int u = int(std::lround(px->x())), v = int(std::lround(px->y()));
                if (u < 0 || v < 0 || u >= zb.width || v >= zb.height) continue;
                if (!roi_alpha.empty() && roi_alpha.at<uint8_t>(v, u) < 128) continue;
                const float z = zb.depth_mm[zb.index(u, v)];
                if (std::isfinite(z) && pc.z() < z + depth_margin_mm) m.voxels[g.linear(i, j, k)] = 0;
            }
    return m;
}

cv::Mat texture_rgba(const cv::Mat& photo_bgr, const cv::Mat& roi_alpha) {
    if (photo_bgr.empty() || photo_bgr.type() != CV_8UC3) throw InputError("photo", "must be an 8-bit colour image");
    cv::Mat out;
    cv::cvtColor(photo_bgr, out, cv::COLOR_BGR2BGRA);
    if (!roi_alpha.empty()) {
        if (roi_alpha.size() != photo_bgr.size() || roi_alpha.type() != CV_8UC1)
            throw InputError("roi", "alpha mask must be 8-bit and of the photo's size");
        const int from_to[] = {0, 3};
        cv::mixChannels(&roi_alpha, 1, &out, 1, from_to, 1);
    }
    return out;
}

void write_textured_obj(const SurfaceMesh& mesh, const TextureMapping& tm, const cv::Mat& tex, const fs::path& obj_path) {
    check_mapping(mesh, tm, obj_path);
    const std::string stem = obj_path.stem().string();
    const fs::path dir = obj_path.parent_path();
    const std::string png_name = stem + "_texture.png", mtl_name = stem + ".mtl";
    std::vector<uint32_t> textured, plain;
    split_faces(mesh, tm, textured, plain);
    const std::vector<Eigen::Vector3f> normals =
        mesh.normals.size() == mesh.vertices.size() ? mesh.normals : outward_vertex_normals(mesh.vertices, mesh.triangles);

    write_bytes_atomic(dir / png_name, png_bytes(tex, obj_path));
    std::ostringstream mtl;
    mtl << "# cortexfuse: the photo on the exposed cortex (alpha = ROI), the rest of the surface grey\n"
        << "newmtl photo\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nd 1\nillum 1\nmap_Kd " << png_name << "\nmap_d " << png_name << "\n\n"
        << "newmtl surface\nKa 0.8 0.72 0.68\nKd 0.8 0.72 0.68\nKs 0 0 0\nd 1\nillum 1\n";
    write_bytes_atomic(dir / mtl_name, mtl.str());
    std::ostringstream o;
    o.precision(7);
    o << "# cortexfuse textured brain surface, world LPS millimetres\nmtllib " << mtl_name << "\n";
    for (const auto& v : mesh.vertices) o << "v " << v.x() << ' ' << v.y() << ' ' << v.z() << '\n';
    // OBJ's v axis points up from the image's bottom row.
    for (const auto& uv : tm.uv) o << "vt " << uv.x() << ' ' << 1.0f - uv.y() << '\n';
    for (const auto& nn : normals) o << "vn " << nn.x() << ' ' << nn.y() << ' ' << nn.z() << '\n';
    o << "o brain_surface\nusemtl photo\n";
    for (size_t i = 0; i < textured.size(); i += 3) {
        o << 'f';
        for (int q = 0; q < 3; ++q) {
            const uint32_t k = textured[i + size_t(q)] + 1;
            o << ' ' << k << '/' << k << '/' << k;
        }
        o << '\n';
    }
    o << "usemtl surface\n";
    for (size_t i = 0; i < plain.size(); i += 3) {
        o << 'f';
        for (int q = 0; q < 3; ++q) {
            const uint32_t k = plain[i + size_t(q)] + 1;
            o << ' ' << k << "//" << k;
        }
        o << '\n';
    }
    write_bytes_atomic(obj_path, o.str());
}

// A small GLB writer, hand-written: Debian 12 has no glTF writing library for C++ (VTK 9.1's
// vtkGLTFWriter writes .gltf JSON only, with textures only as external file references and
// no per-vertex texture coordinates from our mapping), and the container is simple:
// a 12-byte header, a JSON chunk and a BIN chunk, each 4-byte aligned (glTF 2.0 spec, "GLB").
void write_textured_glb(const SurfaceMesh& mesh, const TextureMapping& tm, const cv::Mat& tex, const fs::path& glb_path) {
    check_mapping(mesh, tm, glb_path);
    std::vector<uint32_t> textured, plain;
    split_faces(mesh, tm, textured, plain);
    const std::vector<Eigen::Vector3f> normals =
        mesh.normals.size() == mesh.vertices.size() ? mesh.normals : outward_vertex_normals(mesh.vertices, mesh.triangles);
    const size_t n = mesh.vertices.size();

    std::string bin;
    auto align4 = [&bin] { bin.resize((bin.size() + 3) & ~size_t(3), '\0'); };
    auto append = [&bin](const void* p, size_t bytes) { bin.append(static_cast<const char*>(p), bytes); };
    nlohmann::json views = nlohmann::json::array(), accessors = nlohmann::json::array();
    auto add_view = [&](size_t offset, size_t length, int target) {
        nlohmann::json v = {{"buffer", 0}, {"byteOffset", offset}, {"byteLength", length}};
        if (target) v["target"] = target;
        views.push_back(v);
        return int(views.size()) - 1;
    };
    constexpr int kArrayBuffer = 34962, kElementArrayBuffer = 34963, kFloat = 5126, kUint = 5125;

    // LPS mm -> glTF (metres, +Y up): a proper rotation, so winding and normals stay valid.
    std::vector<float> pos(3 * n), nor(3 * n), uv(2 * n);
    float lo[3] = {1e30f, 1e30f, 1e30f}, hi[3] = {-1e30f, -1e30f, -1e30f};
    for (size_t i = 0; i < n; ++i) {
        const Eigen::Vector3f& p = mesh.vertices[i];
        const float g[3] = {-p.x() * 1e-3f, p.z() * 1e-3f, p.y() * 1e-3f};
        for (int a = 0; a < 3; ++a) {
            pos[3 * i + size_t(a)] = g[a];
            lo[a] = std::min(lo[a], g[a]), hi[a] = std::max(hi[a], g[a]);
        }
        const Eigen::Vector3f& q = normals[i];
        nor[3 * i] = -q.x(), nor[3 * i + 1] = q.z(), nor[3 * i + 2] = q.y();
        uv[2 * i] = tm.uv[i].x(), uv[2 * i + 1] = tm.uv[i].y();
    }
    size_t off = bin.size();
    append(pos.data(), pos.size() * 4);
    accessors.push_back({{"bufferView", add_view(off, pos.size() * 4, kArrayBuffer)}, {"componentType", kFloat}, {"count", n},
                         {"type", "VEC3"}, {"min", {lo[0], lo[1], lo[2]}}, {"max", {hi[0], hi[1], hi[2]}}});
    off = bin.size();
    append(nor.data(), nor.size() * 4);
    accessors.push_back({{"bufferView", add_view(off, nor.size() * 4, kArrayBuffer)}, {"componentType", kFloat}, {"count", n}, {"type", "VEC3"}});
    off = bin.size();
    append(uv.data(), uv.size() * 4);
    accessors.push_back({{"bufferView", add_view(off, uv.size() * 4, kArrayBuffer)}, {"componentType", kFloat}, {"count", n}, {"type", "VEC2"}});
    nlohmann::json primitives = nlohmann::json::array();
    for (int which = 0; which < 2; ++which) {
        const auto& idx = which == 0 ? textured : plain;
        if (idx.empty()) continue;  // glTF forbids empty accessors
        off = bin.size();
        append(idx.data(), idx.size() * 4);
        accessors.push_back({{"bufferView", add_view(off, idx.size() * 4, kElementArrayBuffer)}, {"componentType", kUint},
                             {"count", idx.size()}, {"type", "SCALAR"}});
        nlohmann::json prim = {{"attributes", {{"POSITION", 0}, {"NORMAL", 1}}}, {"indices", int(accessors.size()) - 1}, {"material", which}};
        if (which == 0) prim["attributes"]["TEXCOORD_0"] = 2;
        primitives.push_back(prim);
    }
    align4();
    const std::string png = png_bytes(tex, glb_path);
    off = bin.size();
    append(png.data(), png.size());
    const int png_view = add_view(off, png.size(), 0);
    align4();

    const nlohmann::json j = {
        {"asset", {{"version", "2.0"}, {"generator", "cortexfuse overlay"}}},
        {"scene", 0},
        {"scenes", {{{"nodes", {0}}}}},
        {"nodes", {{{"mesh", 0}, {"name", "brain_surface"}}}},
        {"meshes", {{{"name", "brain_surface"}, {"primitives", primitives}}}},
        {"materials",
         {{{"name", "photo"},
           {"pbrMetallicRoughness", {{"baseColorTexture", {{"index", 0}}}, {"metallicFactor", 0.0}, {"roughnessFactor", 0.9}}},
           {"alphaMode", "MASK"},
           {"alphaCutoff", 0.5},
           {"doubleSided", true}},
          {{"name", "surface"},
           {"pbrMetallicRoughness", {{"baseColorFactor", {0.8, 0.72, 0.68, 1.0}}, {"metallicFactor", 0.0}, {"roughnessFactor", 0.9}}},
           {"doubleSided", true}}}},
        {"textures", {{{"source", 0}, {"sampler", 0}}}},
        {"samplers", {{{"magFilter", 9729}, {"minFilter", 9729}, {"wrapS", 33071}, {"wrapT", 33071}}}},
        {"images", {{{"bufferView", png_view}, {"mimeType", "image/png"}}}},
        {"accessors", accessors},
        {"bufferViews", views},
        {"buffers", {{{"byteLength", bin.size()}}}}};
    std::string json = j.dump();
    json.resize((json.size() + 3) & ~size_t(3), ' ');  // JSON chunk padded with spaces

    std::string glb;
    auto u32 = [&glb](uint32_t x) { glb.append(reinterpret_cast<const char*>(&x), 4); };  // little-endian host
    const uint32_t total = uint32_t(12 + 8 + json.size() + 8 + bin.size());
    u32(0x46546C67u);  // "glTF"
    u32(2);
    u32(total);
    u32(uint32_t(json.size()));
    u32(0x4E4F534Au);  // "JSON"
    glb += json;
    u32(uint32_t(bin.size()));
    u32(0x004E4942u);  // "BIN\0"
    glb += bin;
    write_bytes_atomic(glb_path, glb);
}

}  // namespace cf
