// The fused view over the multimodal volume rendering (POST /api/cases/{id}/fused with
// `modalities`, docs/api/render.md): a phantom case on a 2 mm copy of the bundled head (T1, mask,
// photo, ROI uploaded through the API), an fMRI activation map planned by the plan job (a blob
// on the cortex the camera sees), the phantom's true pose stored as its registration. The daemon
// runs in-process (renderer.kind auto: GL through llvmpipe here; the GL tests skip without a
// context), and a second one with the CPU renderer refuses the layers naming why.
// Eigen first: <httplib.h> pulls in <resolv.h>, whose _res macro breaks Eigen's headers.
#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/overlay.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/roi.hpp"
#include "cortexfuse/core/surface.hpp"
#include "cortexfuse/core/volume.hpp"
#include "cortexfuse/daemon/daemon.hpp"
#include "cortexfuse/db/case_store.hpp"

#include "daemon_fixture.hpp"

#include <gtest/gtest.h>
#include <httplib.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <thread>

using namespace cf;
using namespace cf::daemon;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

fs::path g_root;  // every daemon's state lives under it (removed at the end)

using namespace cf::daemon_test;

json test_config(const fs::path& state, const std::string& renderer) {
    json c = base_test_config(state, renderer);
    c["store"]["max_upload_bytes"] = 16 << 20;
    c["tracker"]["enabled"] = false;
    c["camera"]["backend"] = "none";
    c["jobs"]["progress_hz"] = 50;
    return c;
}

/// The phantom: the 2 mm head, its photo and ROI from the true pose, and an fMRI map on the T1's
/// grid with a blob (z up to 10, radius 12 mm) where the ray through the ROI's centre meets the brain.
struct World {
    PhantomCase pc;
    std::string t1_bytes, mask_bytes, photo_png, fmri_bytes;
    std::string ct_bytes;  // a CT-like volume on the T1's grid: bone (900) on the head outside the brain
    Eigen::Vector2d blob_px;  // the blob centre's pixel in the photo
};

const World& world() {
    static const World w = [] {
        World r;
        const fs::path dir = g_root / "src";
        const Head2mm h = head_2mm(dir);
        const Volume& t1s = h.t1;
        const LabelVolume& ms = h.mask;
        const VolumeGeometry& g = t1s.geom;
        r.t1_bytes = h.t1_bytes;
        r.mask_bytes = h.mask_bytes;
        r.pc = generate_phantom_case(build_phantom_surface(t1s, ms), plain_phantom_params(), 0);
        r.photo_png = png_bytes(r.pc.photo_bgr);
        // The first brain voxel along the ray of the ROI's centre.
        Eigen::Vector2d c(0, 0);
        for (const auto& q : r.pc.roi_points) c += q;
        c /= double(std::max<std::size_t>(1, r.pc.roi_points.size()));
        const Pose Tinv = r.pc.T_camera_from_world.inverse();
        std::optional<Eigen::Vector3d> hit;
        for (double z = 20; z < 1500 && !hit; z += 0.5) {
            const Eigen::Vector3d pw = (Tinv * backproject(r.pc.camera, c, z).homogeneous()).head<3>();
            const Eigen::Vector3d ijk = ms.geom.index_from_world() * pw;
            const int i = int(std::lround(ijk.x())), j = int(std::lround(ijk.y())), k = int(std::lround(ijk.z()));
            if (i >= 0 && j >= 0 && k >= 0 && i < ms.geom.dims[0] && j < ms.geom.dims[1] && k < ms.geom.dims[2] && ms.voxels[ms.geom.linear(i, j, k)])
                hit = pw;
        }
        if (!hit) throw std::runtime_error("test world: the ROI's centre ray misses the brain");
        r.blob_px = c;
        Volume fmri = t1s;
        for (int k = 0; k < g.dims[2]; ++k)
            for (int j = 0; j < g.dims[1]; ++j)
                for (int i = 0; i < g.dims[0]; ++i) {
                    const double d = (g.world_from_index() * Eigen::Vector3d(i, j, k) - *hit).norm();
                    fmri.voxels[g.linear(i, j, k)] = d < 12.0 ? float(4.0 + 6.0 * (1.0 - d / 12.0)) : 0.f;
                }
        // The CT: soft tissue (40) in the brain, bone (900) where the head outside it is bright,
        // air (-1000) elsewhere (as the overlay CLI test's plan).
        std::vector<float> sorted = t1s.voxels;
        std::nth_element(sorted.begin(), sorted.begin() + sorted.size() / 2, sorted.end());
        const float p50 = sorted[sorted.size() / 2];
        Volume ct = t1s;
        for (std::size_t i = 0; i < ct.voxels.size(); ++i)
            ct.voxels[i] = ms.voxels[i] ? 40.f : (t1s.voxels[i] > p50 ? 900.f : -1000.f);
        save_volume(ct, dir / "ct.nii.gz");
        r.ct_bytes = read_bytes(dir / "ct.nii.gz");
        save_volume(fmri, dir / "fmri.nii.gz");
        r.fmri_bytes = read_bytes(dir / "fmri.nii.gz");
        return r;
    }();
    return w;
}

/// A daemon with its own state folder (g_root/<renderer>), and the HTTP calls to it.
struct Server : TestDaemon {
    explicit Server(const std::string& renderer) : TestDaemon(g_root / renderer, test_config(g_root / renderer, renderer), 240) {}

    /// A case with the phantom's T1, mask, photo, ROI and (when asked) fMRI map, planned by the
    /// plan job, registered with the phantom's true pose. Returns its id (0 on failure).
    std::int64_t planned_case(const std::string& title, bool fmri, bool ct = false) const {
        const World& w = world();
        const Reply c = post("/api/cases", {{"title", title}});
        EXPECT_EQ(c.status, 201) << c.body;
        const std::int64_t id = c.j.value("id", std::int64_t{0});
        const std::string base = "/api/cases/" + std::to_string(id);
        EXPECT_EQ(post_raw(base + "/volumes?name=t1.nii.gz&modality=T1", w.t1_bytes).status, 201);
        EXPECT_EQ(post_raw(base + "/volumes?name=mask.nii.gz&modality=mask", w.mask_bytes).status, 201);
        if (fmri) {
            EXPECT_EQ(post_raw(base + "/volumes?name=fmri.nii.gz&modality=fMRI", w.fmri_bytes).status, 201);
        }
        if (ct) {
            EXPECT_EQ(post_raw(base + "/volumes?name=ct.nii.gz&modality=CT", w.ct_bytes).status, 201);
        }
        const Reply ph = post_raw(base + "/photos?name=photo.png&camera=" + url_encode(camera_json(w.pc.camera).dump()), w.photo_png);
        EXPECT_EQ(ph.status, 201) << ph.body;
        json pts = json::array();
        for (const auto& q : w.pc.roi_points) pts.push_back({q.x(), q.y()});
        EXPECT_EQ(post(base + "/roi", {{"points", pts}}).status, 201);
        const Reply job = post("/api/jobs", {{"kind", "plan"}, {"params", {{"case_id", id}, {"max_triangles", 30000}}}});
        EXPECT_EQ(job.status, 202) << job.body;
        std::string s;
        json last;
        const auto t0 = std::chrono::steady_clock::now();
        while (s != "succeeded" && s != "failed" && s != "cancelled" &&
               std::chrono::steady_clock::now() - t0 < std::chrono::seconds(280)) {
            std::this_thread::sleep_for(std::chrono::milliseconds(50));
            last = get("/api/jobs/" + std::to_string(job.j.value("id", 0))).j;
            s = last.value("state", std::string());
        }
        EXPECT_EQ(s, "succeeded") << last.dump();
        if (s != "succeeded") return 0;
        // The registration: the phantom's true pose, stored as a run of the case (what a
        // register job stores), through a second connection to the store.
        store_registration(state() / "store", id, w.pc.T_camera_from_world);
        return id;
    }
};

std::unique_ptr<Server> g_gl;
std::int64_t g_case = 0;

const Server& gl() {
    if (!g_gl) {
        g_root = fs::temp_directory_path() / ("cf_daemon_fused_modalities_" + std::to_string(::getpid()));
        fs::create_directories(g_root);
        ::setenv("LP_NUM_THREADS", "2", 0);
        g_gl = std::make_unique<Server>("auto");
        g_case = g_gl->planned_case("fused fmri", true);
    }
    return *g_gl;
}

class Env : public ::testing::Environment {
public:
    void TearDown() override {
        g_gl.reset();
        if (!g_root.empty()) fs::remove_all(g_root);
    }
};
const auto* const g_env = ::testing::AddGlobalTestEnvironment(new Env);


/// The fused request from the registered camera (png: exact pixels) with these layers; a clear
/// green fMRI look so that the blob stands out from the photo and the cortex.
json fused_body(bool fmri_visible, double fmri_weight, double surface_opacity = 0.5) {
    const json green = {{"colour", {{0, 0, 1, 0}, {1, 0, 1, 0}}}, {"opacity", {{0, 0}, {0.02, 1}, {1, 1}}}};
    return {{"format", "png"},
            {"surface_opacity", surface_opacity},
            {"modalities", json::array({{{"name", "t1"}, {"transfer_function", "cortex_t1"}},
                                        {{"name", "fmri"}, {"transfer_function", green}, {"weight", fmri_weight}, {"visible", fmri_visible}}})}};
}

std::string base() { return "/api/cases/" + std::to_string(g_case); }

size_t files_under(const fs::path& d) {
    size_t n = 0;
    std::error_code ec;
    for (auto it = fs::recursive_directory_iterator(d, ec); !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) n += it->is_regular_file();
    return n;
}

/// Skips (with the daemon's reason) where no GL context can be made.
#define SKIP_WITHOUT_GL(reply)                                                                \
    do {                                                                                          \
        if ((reply).status == 409 && (reply).body.find("GL renderer") != std::string::npos) {     \
            GTEST_SKIP() << "no GL here: " << (reply).body;                                       \
        }                                                                                         \
    } while (0)

// ---------------------------------------------------------------------------------------------

TEST(FusedModalities, TheFmriLayerShowsInFrontOfThePhotoWhereItIsNearer) {
    const Server& s = gl();
    ASSERT_GT(g_case, 0);
    const World& w = world();
    const Reply shown = s.post(base() + "/fused", fused_body(true, 1.0));
    SKIP_WITHOUT_GL(shown);
    ASSERT_EQ(shown.status, 200) << shown.body;
    EXPECT_EQ(shown.headers.find("X-Renderer")->second, "gl");
    const Reply hidden = s.post(base() + "/fused", fused_body(false, 1.0));
    ASSERT_EQ(hidden.status, 200) << hidden.body;
    const cv::Mat a = decode(shown), b = decode(hidden);
    ASSERT_EQ(a.cols, w.pc.camera.width);
    ASSERT_EQ(a.rows, w.pc.camera.height);
    ASSERT_EQ(b.size(), a.size());
    // Inside the brain (where the T1-only picture is not background), around the blob: the
    // fMRI layer changes the picture, and at the blob's centre it is green, drawn over the photo
    // (the blob reaches 12 mm in front of the cortex: the surface is behind the volume's first
    // hit there, so the photo is not blended in).
    cv::Mat grey;
    cv::cvtColor(b, grey, cv::COLOR_BGR2GRAY);
    int brain = 0, changed = 0;
    for (int v = 0; v < a.rows; ++v)
        for (int u = 0; u < a.cols; ++u) {
            if (grey.at<uchar>(v, u) < 8) continue;
            ++brain;
            const cv::Vec3b p = a.at<cv::Vec3b>(v, u), q = b.at<cv::Vec3b>(v, u);
            changed += std::abs(p[0] - q[0]) + std::abs(p[1] - q[1]) + std::abs(p[2] - q[2]) > 30;
        }
    const int u0 = int(std::lround(w.blob_px.x())), v0 = int(std::lround(w.blob_px.y()));
    const cv::Vec3b c = a.at<cv::Vec3b>(v0, u0), c_off = b.at<cv::Vec3b>(v0, u0);
    std::printf("fused fMRI shown vs hidden: %d of %d brain pixels changed by > 30 (sum of BGR); blob centre (%d, %d) BGR shown (%d, %d, %d), "
                "hidden (%d, %d, %d), mean diff %.2f\n",
                changed, brain, u0, v0, c[0], c[1], c[2], c_off[0], c_off[1], c_off[2], mean_abs_diff(a, b));
    EXPECT_GT(brain, 1000);
    EXPECT_GT(changed, 100) << "the fMRI blob (radius 12 mm, ~6 px a mm) shows";
    EXPECT_LT(changed, brain / 2) << "only around the blob";
    EXPECT_GT(int(c[1]), int(c[2]) + 60) << "green over red at the blob's centre";
    EXPECT_GT(int(c[1]), int(c[0]) + 60) << "green over blue at the blob's centre";
    EXPECT_LT(int(c_off[1]), int(c_off[2]) + 30) << "no green there without the layer (the photo / cortex)";
}

TEST(FusedModalities, WeightZeroEqualsHiddenAndTheT1AloneEqualsThePlainFusedView) {
    const Server& s = gl();
    ASSERT_GT(g_case, 0);
    const Reply hidden = s.post(base() + "/fused", fused_body(false, 1.0));
    SKIP_WITHOUT_GL(hidden);
    ASSERT_EQ(hidden.status, 200) << hidden.body;
    const Reply zero = s.post(base() + "/fused", fused_body(true, 0.0));
    ASSERT_EQ(zero.status, 200) << zero.body;
    const Reply half = s.post(base() + "/fused", fused_body(true, 0.3));
    ASSERT_EQ(half.status, 200) << half.body;
    const Reply plain = s.post(base() + "/fused", {{"format", "png"}, {"surface_opacity", 0.5}});
    ASSERT_EQ(plain.status, 200) << plain.body;
    const cv::Mat h = decode(hidden);
    const double d_zero = mean_abs_diff(h, decode(zero)), d_half = mean_abs_diff(h, decode(half)), d_plain = mean_abs_diff(h, decode(plain));
    std::printf("fused vs fMRI hidden: weight 0 %.3f, weight 0.3 %.3f, no modalities (T1 renderer) %.3f grey levels\n", d_zero, d_half, d_plain);
    EXPECT_LT(d_zero, 0.01) << "weight 0 draws nothing";
    EXPECT_GT(d_half, 0.05) << "weight 0.3 draws something";
    EXPECT_LT(d_plain, 1.0) << "the T1 layer alone looks like the single-volume fused view";
    // Another viewpoint (the UI's orbit) with the layers renders too.
    json turned = fused_body(true, 1.0);
    turned["T_camera_from_world"] = pose_to_json(orbit_pose(world().pc.T_camera_from_world, Eigen::Vector3d(0, 10, 0), 20, 0));
    turned["width"] = 160;
    turned["height"] = 120;
    turned["focal_px"] = 300.0;
    EXPECT_EQ(s.post(base() + "/fused", turned).status, 200);
}

// The CT layer of the fused view gets the craniotomy (core's craniotomy_keep_mask, as the
// overlay CLI): from the registered camera the ROI shows the photo / cortex, not the skull,
// while the bone outside the ROI is drawn. The cut CT is cached with the registration: the CT's
// weight and visibility toggled twice upload no volume.
TEST(FusedModalities, TheCtLayerHasTheCraniotomyAndTogglingItUploadsNothing) {
    const Server& s = gl();
    const World& w = world();
    static std::int64_t ct_case = 0;
    if (!ct_case) ct_case = s.planned_case("fused ct", false, true);
    ASSERT_GT(ct_case, 0);
    const std::string b = "/api/cases/" + std::to_string(ct_case);
    auto body = [](bool ct_visible, double ct_weight) {
        return json{{"format", "png"},
                    {"surface_opacity", 0.5},
                    {"modalities", json::array({{{"name", "t1"}, {"transfer_function", "cortex_t1"}},
                                                {{"name", "ct"}, {"transfer_function", "ct_bone"}, {"weight", ct_weight}, {"visible", ct_visible}}})}};
    };
    auto uploads = [&] { return s.get("/api/status").j["modules"]["renderer"]["fusion_volume_uploads"].get<std::uint64_t>(); };
    const Reply shown = s.post(b + "/fused", body(true, 1.0));
    SKIP_WITHOUT_GL(shown);
    ASSERT_EQ(shown.status, 200) << shown.body;
    const std::uint64_t up0 = uploads();
    const Reply hidden = s.post(b + "/fused", body(false, 1.0));
    ASSERT_EQ(hidden.status, 200) << hidden.body;
    const cv::Mat a = decode(shown), h = decode(hidden);
    ASSERT_EQ(a.size(), h.size());
    // The ROI (photo pixels, the fused view is at the photo's size) and its centre.
    Roi roi_curve;  // as the daemon stores it (tension 0, the default)
    roi_curve.points = w.pc.roi_points;
    const cv::Mat roi = roi_mask(roi_curve, a.cols, a.rows);
    const int u0 = int(std::lround(w.blob_px.x())), v0 = int(std::lround(w.blob_px.y()));
    ASSERT_GT(roi.at<uchar>(v0, u0), 128);
    double in_sum = 0, out_sum = 0;
    int in_n = 0, out_n = 0;
    for (int v = 0; v < a.rows; ++v)
        for (int u = 0; u < a.cols; ++u) {
            const cv::Vec3b p = a.at<cv::Vec3b>(v, u), q = h.at<cv::Vec3b>(v, u);
            const double d = (std::abs(p[0] - q[0]) + std::abs(p[1] - q[1]) + std::abs(p[2] - q[2])) / 3.0;
            if (roi.at<uchar>(v, u) >= 128) in_sum += d, ++in_n;
            else out_sum += d, ++out_n;
        }
    const cv::Rect box = cv::Rect(u0 - 10, v0 - 10, 21, 21) & cv::Rect(0, 0, a.cols, a.rows);
    const double d_centre = mean_abs_diff(a(box), h(box));
    const cv::Vec3b c = a.at<cv::Vec3b>(v0, u0), c_off = h.at<cv::Vec3b>(v0, u0);
    std::printf("fused CT shown vs hidden: mean diff inside the ROI %.2f (%d px), outside %.2f (%d px), 21x21 at the ROI centre %.2f; "
                "centre BGR shown (%d, %d, %d), hidden (%d, %d, %d)\n",
                in_n ? in_sum / in_n : 0.0, in_n, out_n ? out_sum / out_n : 0.0, out_n, d_centre, c[0], c[1], c[2], c_off[0], c_off[1], c_off[2]);
    EXPECT_GT(in_n, 1000);
    EXPECT_GT(out_sum / std::max(1, out_n), 5.0) << "the skull outside the ROI is drawn";
    EXPECT_LT(d_centre, 2.0) << "at the ROI's centre the photo / cortex shows, not the bone";
    EXPECT_LT(in_sum / std::max(1, in_n), 0.25 * out_sum / std::max(1, out_n)) << "the ROI is mostly free of bone";
    // Weight and visibility toggled twice: settings of the kept scene, no upload.
    for (const double wt : {0.3, 1.0, 0.3, 1.0}) ASSERT_EQ(s.post(b + "/fused", body(true, wt)).status, 200);
    EXPECT_EQ(s.post(b + "/fused", body(false, 1.0)).status, 200);
    const Reply again = s.post(b + "/fused", body(true, 1.0));
    ASSERT_EQ(again.status, 200);
    EXPECT_EQ(uploads(), up0) << "changing the CT's weight or visibility uploads no volume";
    EXPECT_EQ(mean_abs_diff(decode(again), a), 0.0) << "the same request draws the same picture";
}

// The fused view's opacity slider (7.32): a view that differs only in surface_opacity is blended
// again from the kept passes (volume rendering and surface buffers), nothing rendered; the
// picture is the one a fresh render gives. Any other change (a layer's weight, the pose) renders.
TEST(FusedModalities, TheOpacitySliderBlendsTheKeptPassesAgain) {
    const Server& s = gl();
    ASSERT_GT(g_case, 0);
    auto reused = [&] { return s.get("/api/status").j["modules"]["renderer"]["fused_passes_reused"].get<std::uint64_t>(); };
    // A viewpoint no other test asks for: its first picture is rendered, not reused.
    auto at = [&](double surface_opacity, double fmri_weight = 1.0, double yaw_deg = 7) {
        json b = fused_body(true, fmri_weight, surface_opacity);
        b["T_camera_from_world"] = pose_to_json(orbit_pose(world().pc.T_camera_from_world, Eigen::Vector3d(0, 10, 0), yaw_deg, 0));
        return b;
    };
    const Reply first = s.post(base() + "/fused", at(0.8));
    SKIP_WITHOUT_GL(first);
    ASSERT_EQ(first.status, 200) << first.body;
    const std::uint64_t r0 = reused();
    const Reply faint = s.post(base() + "/fused", at(0.2));
    ASSERT_EQ(faint.status, 200) << faint.body;
    EXPECT_EQ(reused(), r0 + 1) << "another surface opacity blends the kept passes";
    const Reply again = s.post(base() + "/fused", at(0.8));
    ASSERT_EQ(again.status, 200) << again.body;
    EXPECT_EQ(reused(), r0 + 2);
    const cv::Mat a = decode(first), f = decode(faint), g = decode(again);
    EXPECT_EQ(mean_abs_diff(g, a), 0.0) << "blended again: the very picture of the first, rendered, request";
    EXPECT_GT(mean_abs_diff(f, a), 0.5) << "the photo fainter at 0.2";
    // A layer's weight or the pose is another view: rendered.
    ASSERT_EQ(s.post(base() + "/fused", at(0.8, 0.4)).status, 200);
    ASSERT_EQ(s.post(base() + "/fused", at(0.8, 1.0, 9)).status, 200);
    EXPECT_EQ(reused(), r0 + 2) << "a weight or pose change is rendered, not blended";
}

TEST(FusedModalities, BadModalitiesAreRefusedNamingThemAndNothingIsStored) {
    const Server& s = gl();
    ASSERT_GT(g_case, 0);
    const json before_case = s.get(base()).j;
    const json before_regs = s.get(base() + "/registrations").j;
    const std::size_t before_files = files_under(s.state() / "store");
    // A modality the plan lacks: 409 naming it.
    json no_ct = fused_body(true, 1.0);
    no_ct["modalities"].push_back({{"name", "ct"}});
    Reply r = s.post(base() + "/fused", no_ct);
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("modalities[2]"), std::string::npos) << r.body;
    EXPECT_NE(r.body.find("no plan with a CT"), std::string::npos) << r.body;
    // Malformed lists and entries: 400 naming the field.
    const std::vector<std::pair<json, std::string>> bad = {
        {"fmri", "modalities"},
        {json::array(), "modalities"},
        {json::array({5}), "modalities[0].name"},
        {json::array({{{"weight", 1}}}), "modalities[0].name"},
        {json::array({{{"name", "pet"}}}), "unknown modality 'pet'"},
        {json::array({{{"name", "t1"}}, {{"name", "t1"}}}), "listed twice"},
        {json::array({{{"name", "t1"}}, {{"name", "fmri"}, {"weight", 2}}}), "modalities[1].weight"},
        {json::array({{{"name", "t1"}}, {{"name", "fmri"}, {"weight", "heavy"}}}), "modalities[1].weight"},
        {json::array({{{"name", "t1"}}, {{"name", "fmri"}, {"visible", "yes"}}}), "modalities[1].visible"},
        {json::array({{{"name", "t1"}}, {{"name", "fmri"}, {"colour", 1}}}), "modalities[1].colour"},
        {json::array({{{"name", "t1"}}, {{"name", "fmri"}, {"transfer_function", "sunset"}}}), "unknown preset 'sunset'"},
        {json::array({{{"name", "t1"}}, {{"name", "fmri"}, {"transfer_function", {{"colour", 1}}}}}), "modalities[1].transfer_function"},
        {json::array({{{"name", "t1"}}, {{"name", "fmri"}}, {{"name", "t1"}}, {{"name", "fmri"}}, {{"name", "t1"}}}), "modalities"},
    };
    for (const auto& [m, needle] : bad) {
        json b = {{"format", "png"}, {"modalities", m}};
        r = s.post(base() + "/fused", b);
        EXPECT_EQ(r.status, 400) << m.dump() << " -> " << r.body;
        EXPECT_NE(r.body.find(needle), std::string::npos) << m.dump() << " -> " << r.body;
    }
    // Renders and refusals store nothing: the case, its registrations and the store's files are as they were.
    const Reply ok = s.post(base() + "/fused", fused_body(true, 1.0));
    EXPECT_TRUE(ok.status == 200 || ok.status == 409) << ok.body;
    const json after_case = s.get(base()).j, bc = before_case;
    EXPECT_EQ(after_case.value("results", json()), bc.value("results", json()));
    EXPECT_EQ(after_case.value("volumes", json()), bc.value("volumes", json()));
    EXPECT_EQ(after_case.value("photos", json()), bc.value("photos", json()));
    EXPECT_EQ(s.get(base() + "/registrations").j, before_regs);
    EXPECT_EQ(files_under(s.state() / "store"), before_files) << "no blob written by a render";
}

// A daemon with the CPU ray caster: the fused view with layers is refused naming the reason
// (the UI then shows the T1 alone and says why), and without them it still renders.
TEST(FusedModalities, TheCpuRendererRefusesLayersNamingWhy) {
    gl();  // the shared test data and folder
    Server cpu("cpu");
    const std::int64_t id = cpu.planned_case("fused cpu", false);
    ASSERT_GT(id, 0);
    const std::string b = "/api/cases/" + std::to_string(id);
    json body = {{"format", "png"}, {"width", 160}, {"height", 120}, {"modalities", json::array({{{"name", "t1"}}})}};
    Reply r = cpu.post(b + "/fused", body);
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("fused modalities: multimodal views need the GL renderer"), std::string::npos) << r.body;
    // A modality the plan lacks is named first, on any renderer.
    body["modalities"] = json::array({{{"name", "t1"}}, {{"name", "fmri"}}});
    r = cpu.post(b + "/fused", body);
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("no plan with an fMRI map"), std::string::npos) << r.body;
    body.erase("modalities");
    r = cpu.post(b + "/fused", body);
    EXPECT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.headers.find("X-Renderer")->second, "cpu");
}

}  // namespace
