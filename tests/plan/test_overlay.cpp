// The photographic overlay against phantom ground truth: texture coordinates, occlusion,
// cast back, exports, fused views, bad input.
#include <gtest/gtest.h>

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <opencv2/calib3d.hpp>
#include <opencv2/core/eigen.hpp>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/overlay.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/renderer.hpp"
#include "cortexfuse/core/transfer_function.hpp"

namespace fs = std::filesystem;
using namespace cf;

namespace {

struct World {
    Volume t1;
    LabelVolume mask;
    PhantomSurface surface;
    SurfaceMesh mesh;
    PhantomCase pc;
    cv::Mat alpha;
};

// One phantom case on a 2 mm copy of the shipped head (fast), with lens distortion.
const World& world() {
    static const World w = [] {
        World r;
        const Volume t1 = load_volume(fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz");
        const LabelVolume m = load_mask(fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz");
        const VolumeGeometry g = isotropic_grid(t1.geom, 2.0);
        r.t1 = resample(t1, g);
        r.mask = resample_nearest(m, g);
        r.surface = build_phantom_surface(r.t1, r.mask);
        r.mesh.vertices = r.surface.mesh.vertices;
        r.mesh.triangles = r.surface.mesh.triangles;
        r.mesh.normals = r.surface.normals;
        PhantomParams p;
        p.seed = 5;
        p.width = 360;
        p.height = 240;
        p.vary_size = false;
        p.dslr_fraction = 0;
        p.distortion_prob = 1.0;
        p.gauze_prob = 0;
        p.blood_prob = 0;
        r.pc = generate_phantom_case(r.surface, p, 0);
        Roi roi;
        roi.points = r.pc.roi_points;
        r.alpha = roi_mask(roi, r.pc.camera.width, r.pc.camera.height);
        return r;
    }();
    return w;
}

/// Independent ray test (no rasteriser): distance along the ray from `o` towards `p` to the
/// nearest triangle hit, brute force.
double first_hit(const SurfaceMesh& m, const Eigen::Vector3d& o, const Eigen::Vector3d& d) {
    double best = 1e30;
    for (const auto& t : m.triangles) {
        const Eigen::Vector3d a = m.vertices[size_t(t[0])].cast<double>(), b = m.vertices[size_t(t[1])].cast<double>(),
                              c = m.vertices[size_t(t[2])].cast<double>();
        const Eigen::Vector3d e1 = b - a, e2 = c - a, pv = d.cross(e2);
        const double det = e1.dot(pv);
        if (std::abs(det) < 1e-12) continue;
        const Eigen::Vector3d tv = o - a;
        const double u = tv.dot(pv) / det;
        if (u < 0 || u > 1) continue;
        const Eigen::Vector3d qv = tv.cross(e1);
        const double v = d.dot(qv) / det;
        if (v < 0 || u + v > 1) continue;
        const double s = e2.dot(qv) / det;
        if (s > 1e-6) best = std::min(best, s);
    }
    return best;
}

}  // namespace

TEST(Overlay, VisibleVerticesReprojectToTruth) {
    const World& w = world();
    const Intrinsics& K = w.pc.camera;
    ASSERT_TRUE(K.has_distortion());
    const TextureMapping tm = map_texture(w.mesh, K, w.pc.T_camera_from_world, w.alpha);
    ASSERT_GT(tm.visible_count, 500u);
    ASSERT_GT(tm.roi_count, 100u);
    EXPECT_GT(tm.back_facing, 0u);
    EXPECT_GT(tm.occluded, 0u);
    // Reference projection through OpenCV (independent of our camera code).
    const Eigen::Matrix3d R = w.pc.T_camera_from_world.topLeftCorner<3, 3>();
    cv::Mat Rcv, rvec;
    cv::eigen2cv(R, Rcv);
    cv::Rodrigues(Rcv, rvec);
    const Eigen::Vector3d t = w.pc.T_camera_from_world.topRightCorner<3, 1>();
    const cv::Mat tvec = (cv::Mat_<double>(3, 1) << t.x(), t.y(), t.z());
    const cv::Mat Kcv = (cv::Mat_<double>(3, 3) << K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1);
    const cv::Mat dist(1, 5, CV_64F, const_cast<double*>(K.distortion.data()));
    std::vector<cv::Point3d> obj;
    std::vector<size_t> idx;
    for (size_t i = 0; i < w.mesh.vertices.size(); ++i)
        if (tm.visible[i]) obj.emplace_back(w.mesh.vertices[i].x(), w.mesh.vertices[i].y(), w.mesh.vertices[i].z()), idx.push_back(i);
    std::vector<cv::Point2d> img;
    cv::projectPoints(obj, rvec, tvec, Kcv, dist, img);
    double worst = 0;
    for (size_t q = 0; q < idx.size(); ++q) {
        const Eigen::Vector2f uv = tm.uv[idx[q]];
        const double x = double(uv.x()) * K.width - 0.5, y = double(uv.y()) * K.height - 0.5;
        worst = std::max(worst, std::hypot(x - img[q].x, y - img[q].y));
    }
    EXPECT_LT(worst, 0.5);
    // Not visible -> no texture coordinates.
    for (size_t i = 0; i < w.mesh.vertices.size(); ++i)
        if (!tm.visible[i]) {
            EXPECT_EQ(tm.uv[i], Eigen::Vector2f::Zero());
            EXPECT_FALSE(tm.in_roi[i]);
        }
}

TEST(Overlay, OccludedVerticesGetNone) {
    const World& w = world();
    const Pose& T = w.pc.T_camera_from_world;
    const TextureMapping tm = map_texture(w.mesh, w.pc.camera, T, w.alpha);
    const Eigen::Matrix3d R = T.topLeftCorner<3, 3>();
    const Eigen::Vector3d o = -R.transpose() * T.topRightCorner<3, 1>();
    // Check a sample of vertices with an exact ray test: an occluded vertex has surface in
    // front of it; a visible one has none (beyond the depth-test slack).
    int occluded_checked = 0, visible_checked = 0;
    for (size_t i = 0; i < w.mesh.vertices.size() && (occluded_checked < 20 || visible_checked < 20); i += 7) {
        const Eigen::Vector3d p = w.mesh.vertices[i].cast<double>();
        const double dist = (p - o).norm();
        // The exact ray test goes through every triangle: only for vertices that are checked.
        auto hit_along = [&] { return first_hit(w.mesh, o, (p - o) / dist); };
        if (tm.visible[i] && visible_checked < 20) {
            const double hit = hit_along();
            EXPECT_GT(hit, dist - 2.0) << "vertex " << i << " is textured but surface lies in front of it";
            ++visible_checked;
        } else if (!tm.visible[i] && occluded_checked < 20) {
            const Eigen::Vector3d pc = R * p + T.topRightCorner<3, 1>();
            const auto px = project_camera(w.pc.camera, pc);
            const bool in_image = px && px->x() > 2 && px->y() > 2 && px->x() < w.pc.camera.width - 3 && px->y() < w.pc.camera.height - 3;
            const bool front = (R * w.mesh.normals[i].cast<double>()).dot(pc.normalized()) < -0.3;
            if (in_image && front) {  // front-facing and in the picture, yet not visible: must be hidden
                const double hit = hit_along();
                EXPECT_LT(hit, dist - 0.3) << "vertex " << i << " got no texture but nothing hides it";
                ++occluded_checked;
            }
        }
    }
    EXPECT_EQ(visible_checked, 20);
    EXPECT_GT(occluded_checked, 5);
}

TEST(Overlay, SyntheticOcclusionByAPlate) {
    // A small plate at 100 mm in front of a large one at 200 mm: the large plate's vertices in
    // the small one's shadow are hidden, the others are seen.
    SurfaceMesh m;
    auto plate = [&m](double half, double z, int n) {
        const int base = int(m.vertices.size());
        for (int j = 0; j <= n; ++j)
            for (int i = 0; i <= n; ++i) {
                m.vertices.emplace_back(float(-half + 2 * half * i / n), float(-half + 2 * half * j / n), float(z));
                m.normals.emplace_back(0.f, 0.f, -1.f);  // towards the camera at the origin
            }
        for (int j = 0; j < n; ++j)
            for (int i = 0; i < n; ++i) {
                const int a = base + j * (n + 1) + i;
                m.triangles.emplace_back(a, a + 1, a + n + 2);
                m.triangles.emplace_back(a, a + n + 2, a + n + 1);
            }
    };
    plate(20, 100, 10);
    plate(80, 200, 40);
    Intrinsics K;
    K.width = 400, K.height = 400, K.fx = K.fy = 500, K.cx = K.cy = 199.5;
    const TextureMapping tm = map_texture(m, K, Pose::Identity());
    int hidden = 0, seen = 0;
    for (size_t i = 121; i < m.vertices.size(); ++i) {
        const Eigen::Vector3f& p = m.vertices[i];
        const bool shadow = std::abs(p.x()) < 39 && std::abs(p.y()) < 39;  // small plate spans +-40 at 200 mm
        const bool clear = std::abs(p.x()) > 41 || std::abs(p.y()) > 41;
        const bool in_view = std::abs(p.x()) < 79 && std::abs(p.y()) < 79;
        if (shadow) {
            EXPECT_FALSE(tm.visible[i]) << p.transpose();
            ++hidden;
        }
        if (clear && in_view) {
            EXPECT_TRUE(tm.visible[i]) << p.transpose();
            ++seen;
        }
    }
    for (size_t i = 0; i < 121; ++i) EXPECT_TRUE(tm.visible[i]);
    EXPECT_GT(hidden, 100);
    EXPECT_GT(seen, 500);
    // Turned around, the plates are back-facing: nothing visible -> a clear error.
    for (auto& n : m.normals) n = -n;
    EXPECT_THROW(map_texture(m, K, Pose::Identity()), InputError);
}

TEST(Overlay, CastBackLandsOnTruthTargets) {
    const World& w = world();
    const Pose& T = w.pc.T_camera_from_world;
    ASSERT_GE(w.pc.targets_world_mm.size(), 5u);
    for (const auto& target : w.pc.targets_world_mm) {
        const auto px = project(w.pc.camera, T, target);
        ASSERT_TRUE(px);
        const auto hit = cast_back(w.mesh, w.pc.camera, T, *px);
        ASSERT_TRUE(hit);
        EXPECT_LT((hit->p_world_mm - target).norm(), 0.5);
        EXPECT_GT(hit->normal_world.dot(-(T.topLeftCorner<3, 3>().transpose() * (T.topLeftCorner<3, 3>() * target + T.topRightCorner<3, 1>())).normalized()), 0.0);
    }
    // A pixel far outside the brain misses.
    Intrinsics wide = w.pc.camera;
    EXPECT_FALSE(cast_back(w.mesh, wide, T, Eigen::Vector2d(-5000, -5000)));
}

TEST(Overlay, ExportsObjAndGlb) {
    const World& w = world();
    const TextureMapping tm = map_texture(w.mesh, w.pc.camera, w.pc.T_camera_from_world, w.alpha);
    const cv::Mat tex = texture_rgba(w.pc.photo_bgr, w.alpha);
    ASSERT_EQ(tex.type(), CV_8UC4);
    const fs::path d = fs::temp_directory_path() / ("cf_overlay_" + std::to_string(::getpid()));
    fs::create_directories(d);
    write_textured_obj(w.mesh, tm, tex, d / "s.obj");
    write_textured_glb(w.mesh, tm, tex, d / "s.glb");
    // OBJ: every vertex, every triangle once, the textured ones with the photo material.
    std::ifstream obj(d / "s.obj");
    std::string line;
    size_t v = 0, vt = 0, f = 0;
    while (std::getline(obj, line)) {
        if (line.rfind("v ", 0) == 0) ++v;
        if (line.rfind("vt ", 0) == 0) ++vt;
        if (line.rfind("f ", 0) == 0) ++f;
    }
    EXPECT_EQ(v, w.mesh.vertices.size());
    EXPECT_EQ(vt, w.mesh.vertices.size());
    EXPECT_EQ(f, w.mesh.triangles.size());
    EXPECT_TRUE(fs::exists(d / "s.mtl"));
    const cv::Mat png = cv::imread((d / "s_texture.png").string(), cv::IMREAD_UNCHANGED);
    ASSERT_EQ(png.channels(), 4);
    // GLB: header, chunk lengths, JSON that names what the binary holds.
    std::ifstream g(d / "s.glb", std::ios::binary);
    std::string bytes((std::istreambuf_iterator<char>(g)), {});
    ASSERT_GT(bytes.size(), 28u);
    uint32_t hdr[5];
    std::memcpy(hdr, bytes.data(), 20);
    EXPECT_EQ(hdr[0], 0x46546C67u);
    EXPECT_EQ(hdr[1], 2u);
    EXPECT_EQ(hdr[2], bytes.size());
    EXPECT_EQ(hdr[4], 0x4E4F534Au);
    EXPECT_EQ(hdr[3] % 4, 0u);
    const auto j = nlohmann::json::parse(bytes.substr(20, hdr[3]));
    EXPECT_EQ(j["asset"]["version"], "2.0");
    EXPECT_EQ(j["accessors"][0]["count"], w.mesh.vertices.size());
    uint32_t bin_len;
    std::memcpy(&bin_len, bytes.data() + 20 + hdr[3], 4);
    EXPECT_EQ(bin_len, j["buffers"][0]["byteLength"].get<uint32_t>());
    EXPECT_EQ(20 + hdr[3] + 8 + bin_len, bytes.size());
    size_t idx_total = 0;
    for (const auto& p : j["meshes"][0]["primitives"]) idx_total += j["accessors"][p["indices"].get<int>()]["count"].get<size_t>();
    EXPECT_EQ(idx_total, 3 * w.mesh.triangles.size());
    // A mesh with no triangles is refused, nothing written.
    SurfaceMesh none;
    EXPECT_THROW(write_textured_glb(none, tm, tex, d / "none.glb"), InputError);
    EXPECT_FALSE(fs::exists(d / "none.glb"));
    fs::remove_all(d);
}

TEST(Overlay, FusedViewShowsThePhotoInTheRoi) {
    const World& w = world();
    const Pose& T = w.pc.T_camera_from_world;
    const TextureMapping tm = map_texture(w.mesh, w.pc.camera, T, w.alpha);
    const cv::Mat tex = texture_rgba(w.pc.photo_bgr, w.alpha);
    auto r = make_cpu_renderer(w.t1, preset_transfer_function("cortex_t1"), &w.mask);
    RenderOptions o;
    o.threads = 2;
    const cv::Mat plain = render_fused(*r, w.mesh, tm, tex, w.pc.camera, T, 0.0, 3.0, o);
    const cv::Mat full = render_fused(*r, w.mesh, tm, tex, w.pc.camera, T, 1.0, 3.0, o);
    cv::Mat er;
    cv::erode(w.alpha, er, cv::Mat::ones(9, 9, CV_8U));
    double diff_in = 0, diff_out = 0, photo_err = 0;
    int nin = 0, nout = 0;
    for (int v = 0; v < plain.rows; ++v)
        for (int u = 0; u < plain.cols; ++u) {
            const double d = cv::norm(plain.at<cv::Vec3b>(v, u), full.at<cv::Vec3b>(v, u));
            if (er.at<uint8_t>(v, u)) {
                diff_in += d;
                photo_err += cv::norm(full.at<cv::Vec3b>(v, u), w.pc.photo_bgr.at<cv::Vec3b>(v, u));
                ++nin;
            } else if (!w.alpha.at<uint8_t>(v, u)) {
                diff_out += d, ++nout;
            }
        }
    ASSERT_GT(nin, 100);
    EXPECT_GT(diff_in / nin, 10.0);      // the photo changes the picture inside the ROI
    EXPECT_LT(diff_out / nout, 1e-9);    // and nothing outside it
    EXPECT_LT(photo_err / nin, 25.0);    // at full opacity from the camera's pose it is the photo
    // A pose looking away from the brain: a clear error.
    Pose away = T;
    away.topLeftCorner<3, 3>() = Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitX()).toRotationMatrix() * T.topLeftCorner<3, 3>();
    away.topRightCorner<3, 1>() = Eigen::AngleAxisd(M_PI, Eigen::Vector3d::UnitX()).toRotationMatrix() * T.topRightCorner<3, 1>();
    try {
        map_texture(w.mesh, w.pc.camera, away, w.alpha);
        ADD_FAILURE() << "a pose looking away was accepted";
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("away"), std::string::npos) << e.what();
    }
    Pose bent = T;
    bent(0, 0) *= 2;
    EXPECT_THROW(map_texture(w.mesh, w.pc.camera, bent), InputError);
}
