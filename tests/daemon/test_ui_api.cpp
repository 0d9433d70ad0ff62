// The daemon calls the kiosk UI needs beyond the case data (issue 7): the landmarks' initial
// alignment with its reprojection error (docs/api/case-data.md "Initial alignment") and the
// archive's thumbnails (docs/api/cases.md "Thumbnails") and volumes from a USB stick
// (docs/api/case-data.md "Volumes from removable media").
// The daemon runs in-process on a free port with the CPU renderer, without tracker or camera.
// Eigen first: <httplib.h> pulls in <resolv.h>, whose _res macro breaks Eigen's headers.
#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/landmarks.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/volume.hpp"

#include "daemon_fixture.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <fstream>
#include <map>
#include <opencv2/imgproc.hpp>
#include <random>

using namespace cf;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

using namespace cf::daemon_test;

SharedDaemon& g_d = add_shared_daemon("cf_daemon_ui", [](const fs::path& state) {
    json c = base_test_config(state, "cpu");
    c["store"]["max_upload_bytes"] = 8 << 20;
    c["tracker"]["enabled"] = false;
    c["camera"]["backend"] = "none";
    c["media"]["removable_root"] = (state / "stick").string();  // made by MediaImport.* (absent before)
    return c;
});

Reply get(const std::string& path) { return g_d.get().get(path); }
Reply post(const std::string& path, const json& body) { return g_d.get().post(path, body); }

/// The test camera: 320x240, f = 400 px.
Intrinsics test_camera() {
    Intrinsics K;
    K.width = 320;
    K.height = 240;
    K.fx = K.fy = 400;
    K.cx = 159.5;
    K.cy = 119.5;
    return K;
}

/// A known camera pose: 30 degrees about a tilted axis, the points ~300 mm in front.
Pose true_pose() {
    Pose T = Pose::Identity();
    T.topLeftCorner<3, 3>() = Eigen::AngleAxisd(30.0 * M_PI / 180.0, Eigen::Vector3d(0.3, 1, 0.2).normalized()).toRotationMatrix();
    T.topRightCorner<3, 1>() = Eigen::Vector3d(5, -8, 300);
    return T;
}

/// A case with a 320x240 photo of `test_camera()`; its id.
std::int64_t case_with_photo(const std::string& title) {
    const std::int64_t id = g_d.get().new_case(title);
    const cv::Mat img(240, 320, CV_8UC3, cv::Scalar(40, 90, 160));
    const Reply ph = g_d.get().post_raw("/api/cases/" + std::to_string(id) + "/photos?name=photo.png&camera=" + url_encode(camera_json(test_camera()).dump()),
                                        png_bytes(img));
    EXPECT_EQ(ph.status, 201) << ph.body;
    return id;
}

/// Six points on a curved patch (not coplanar), their pixels under `T` plus `noise_px` of
/// Gaussian noise (seeded).
json pairs_under(const Pose& T, double noise_px, int n = 6) {
    const Intrinsics K = test_camera();
    std::mt19937 rng(7);
    std::normal_distribution<double> g(0, noise_px);
    json a = json::array();
    for (int i = 0; i < n; ++i) {
        const double ang = 2 * M_PI * i / n;
        const Eigen::Vector3d w(30 * std::cos(ang), 25 * std::sin(ang), 6 * std::cos(2 * ang) + (i % 2 ? 4 : -3));
        const auto p = project(K, T, w);
        EXPECT_TRUE(p.has_value());
        const Eigen::Vector2d px = *p + (noise_px > 0 ? Eigen::Vector2d(g(rng), g(rng)) : Eigen::Vector2d::Zero());
        a.push_back({{"label", "P" + std::to_string(i + 1)}, {"world_mm", {w.x(), w.y(), w.z()}}, {"pixel", {px.x(), px.y()}}});
    }
    return a;
}

Pose pose_of(const json& j) { return parse_pose(j, "answer"); }

}  // namespace

TEST(LandmarkPose, RecoversTheTruePoseFromExactPairsAndReportsEachPairsError) {
    const std::int64_t id = case_with_photo("landmark pose exact");
    const std::string base = "/api/cases/" + std::to_string(id) + "/landmarks";
    // Nothing stored yet: the stored variant says so.
    Reply r = get(base + "/initial-pose");
    EXPECT_EQ(r.status, 404) << r.body;
    EXPECT_NE(r.body.find("no landmarks yet"), std::string::npos) << r.body;

    ASSERT_EQ(post(base, {{"landmarks", pairs_under(true_pose(), 0)}}).status, 201);
    r = get(base + "/initial-pose");
    ASSERT_EQ(r.status, 200) << r.body;
    const Pose T = pose_of(r.j);
    const Pose Tt = true_pose();
    // Exact pixels: the fitted pose is the true one (rotation and translation).
    const double rot_deg = Eigen::AngleAxisd(Tt.topLeftCorner<3, 3>().transpose() * T.topLeftCorner<3, 3>()).angle() * 180 / M_PI;
    EXPECT_LT(rot_deg, 1e-3);
    EXPECT_LT((T.topRightCorner<3, 1>() - Tt.topRightCorner<3, 1>()).norm(), 1e-2);
    EXPECT_LT(r.j["rms_px"].get<double>(), 1e-3);
    ASSERT_EQ(r.j["pairs"].size(), 6u);
    EXPECT_EQ(r.j["pairs"][0]["label"], "P1");
    EXPECT_EQ(r.j["revision"], 1);
    EXPECT_EQ(r.j["method"], "pnp-ransac");  // six pairs: RANSAC first, as the register job
    // Six points round a patch: well spread, no warning.
    EXPECT_GT(r.j["spread"]["world"].get<double>(), 0.5);
    EXPECT_EQ(r.j["warning"], "");
}

TEST(LandmarkPose, PairsNearlyOnALineAreAlignedWithAWarning) {
    const std::int64_t id = case_with_photo("landmark pose thin");
    const Intrinsics K = test_camera();
    json pairs = json::array();
    for (int i = 0; i < 6; ++i) {
        const Eigen::Vector3d w(-25 + 10.0 * i, (i % 2 ? 1.5 : -1.5), 0.5 * i);
        const auto p = project(K, true_pose(), w);
        ASSERT_TRUE(p.has_value());
        pairs.push_back({{"label", "P" + std::to_string(i + 1)}, {"world_mm", {w.x(), w.y(), w.z()}}, {"pixel", {p->x(), p->y()}}});
    }
    const Reply r = post("/api/cases/" + std::to_string(id) + "/landmarks/initial-pose", {{"landmarks", pairs}});
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_LT(r.j["spread"]["world"].get<double>(), kLandmarkSpreadWarn);
    EXPECT_NE(r.j["warning"].get<std::string>().find("nearly on a line"), std::string::npos) << r.body;
}

TEST(LandmarkPose, NoisyPairsGiveThePoseTheRegisterJobStartsFromAndTheirErrors) {
    const std::int64_t id = case_with_photo("landmark pose noisy");
    const std::string base = "/api/cases/" + std::to_string(id) + "/landmarks";
    const json pairs = pairs_under(true_pose(), 1.5);
    ASSERT_EQ(post(base, {{"landmarks", pairs}}).status, 201);
    const Reply r = get(base + "/initial-pose");
    ASSERT_EQ(r.status, 200) << r.body;
    // The same core call Registration::run makes for its T0.
    const auto lms = parse_landmarks(json{{"landmarks", pairs}}, "test");
    const LandmarkFit expected = pnp_candidates(lms, test_camera()).front();
    const Pose T = pose_of(r.j);
    EXPECT_LT((T - expected.T_camera_from_world).cwiseAbs().maxCoeff(), 1e-9);
    // Each error is the distance of the pair's pixel from its world point projected with that
    // pose (computed here independently), and the RMS is theirs.
    double sum_sq = 0;
    for (std::size_t i = 0; i < lms.size(); ++i) {
        const auto p = project(test_camera(), T, lms[i].world_mm);
        ASSERT_TRUE(p.has_value());
        const double e = (*p - lms[i].pixel).norm();
        EXPECT_NEAR(r.j["pairs"][i]["error_px"].get<double>(), e, 1e-9);
        EXPECT_NEAR(r.j["pairs"][i]["projected_pixel"][0].get<double>(), p->x(), 1e-9);
        sum_sq += e * e;
    }
    const double rms = std::sqrt(sum_sq / double(lms.size()));
    EXPECT_NEAR(r.j["rms_px"].get<double>(), rms, 1e-9);
    EXPECT_GT(rms, 0.3);  // the noise shows
    EXPECT_LT(rms, 4.0);
    // The unsaved variant of the same pairs answers the same, and stores nothing.
    const Reply p = post(base + "/initial-pose", {{"landmarks", pairs}});
    ASSERT_EQ(p.status, 200) << p.body;
    EXPECT_NEAR(p.j["rms_px"].get<double>(), rms, 1e-9);
    EXPECT_EQ(get(base + "?revisions=all").j["revisions"].size(), 1u);
    // An edit (one pixel moved by 20 px) raises the error of that pair.
    json moved = pairs;
    moved[2]["pixel"][0] = moved[2]["pixel"][0].get<double>() + 20;
    const Reply m = post(base + "/initial-pose", {{"landmarks", moved}});
    ASSERT_EQ(m.status, 200) << m.body;
    EXPECT_GT(m.j["rms_px"].get<double>(), rms + 2);
}

TEST(LandmarkPose, BadInputIsRefusedNamingTheProblem) {
    const std::int64_t id = case_with_photo("landmark pose bad");
    const std::string base = "/api/cases/" + std::to_string(id) + "/landmarks/initial-pose";
    struct Case {
        std::string path;
        json body;
        int status;
        std::string words;
    };
    json collinear = json::array();
    for (int i = 0; i < 5; ++i) collinear.push_back({{"world_mm", {10.0 * i, 2.0 * i, 0.0}}, {"pixel", {50.0 + 30 * i, 60.0 + 7 * (i % 2) + 10 * i}}});
    json outside = pairs_under(true_pose(), 0);
    outside[1]["pixel"] = {500.0, 20.0};
    const std::vector<Case> cases{
        {base, {{"landmarks", pairs_under(true_pose(), 0, 3)}}, 400, "needs at least 4 landmark pairs, found 3"},
        {base, {{"landmarks", collinear}}, 400, "world points are collinear"},
        {base, {{"landmarks", outside}}, 400, "outside the 320x240 photo"},
        {base, {{"landmarks", "four"}}, 400, "must be an array"},
        {base, {{"landmarks", pairs_under(true_pose(), 0)}, {"colour", 1}}, 400, "colour: unknown field"},
        {base, {{"landmarks", pairs_under(true_pose(), 0)}, {"photo_id", 999}}, 404, "photo_id 999"},
        {"/api/cases/987654/landmarks/initial-pose", {{"landmarks", pairs_under(true_pose(), 0)}}, 404, "987654"},
    };
    for (const auto& c : cases) {
        const Reply r = post(c.path, c.body);
        EXPECT_EQ(r.status, c.status) << c.body.dump() << " -> " << r.body;
        EXPECT_NE(r.body.find(c.words), std::string::npos) << r.body;
    }
    EXPECT_EQ(get("/api/cases/987654/landmarks/initial-pose").status, 404);
    // A case without a photo: 409 saying so.
    const std::int64_t bare = g_d.get().new_case("no photo");
    const Reply r = post("/api/cases/" + std::to_string(bare) + "/landmarks/initial-pose", {{"landmarks", pairs_under(true_pose(), 0)}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("no photo"), std::string::npos) << r.body;
    // Nothing was stored by any of them.
    EXPECT_EQ(get("/api/cases/" + std::to_string(id) + "/landmarks").status, 404);
}

// ---- thumbnails ----

namespace {

/// The mean BGR of a rectangle of a decoded picture.
cv::Scalar mean_of(const cv::Mat& m, const cv::Rect& r) { return cv::mean(m(r)); }

std::size_t cache_files_of(std::int64_t id) {
    std::size_t n = 0;
    std::error_code ec;
    for (const auto& f : fs::directory_iterator(g_d.state() / "work" / "thumbnails", ec))
        if (f.path().filename().string().rfind("case_" + std::to_string(id) + "_", 0) == 0) ++n;
    return n;
}

}  // namespace

TEST(Thumbnail, ThePhotoShrunkAndCachedUntilANewPhoto) {
    const std::string none = "/api/cases/" + std::to_string(g_d.get().new_case("thumb none")) + "/thumbnail";
    Reply r = get(none);
    EXPECT_EQ(r.status, 404) << r.body;
    EXPECT_NE(r.body.find("no photo or fused view yet"), std::string::npos) << r.body;
    r = get("/api/cases/987654/thumbnail");
    EXPECT_EQ(r.status, 404) << r.body;
    EXPECT_NE(r.body.find("987654"), std::string::npos) << r.body;

    // A photo red on the left half, blue on the right.
    const std::int64_t id = g_d.get().new_case("thumb photo");
    const std::string base = "/api/cases/" + std::to_string(id);
    cv::Mat img(240, 320, CV_8UC3, cv::Scalar(200, 30, 20));
    img(cv::Rect(0, 0, 160, 240)).setTo(cv::Scalar(20, 30, 200));
    const std::string cam = url_encode(camera_json(test_camera()).dump());
    ASSERT_EQ(g_d.get().post_raw(base + "/photos?name=photo.png&camera=" + cam, png_bytes(img)).status, 201);
    r = get(base + "/thumbnail");
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.content_type, "image/jpeg");
    EXPECT_EQ(r.headers.find("X-Thumbnail-Source")->second, "photo");
    EXPECT_EQ(r.headers.find("X-Thumbnail-Cache")->second, "miss");
    cv::Mat t = decode(r);
    ASSERT_EQ(t.cols, 192);
    ASSERT_EQ(t.rows, 144);
    const cv::Scalar left = mean_of(t, cv::Rect(10, 10, 70, 120)), right = mean_of(t, cv::Rect(110, 10, 70, 120));
    EXPECT_GT(left[2], 150);  // red (BGR)
    EXPECT_LT(left[0], 60);
    EXPECT_GT(right[0], 150);  // blue
    EXPECT_LT(right[2], 60);
    // Again: the cached picture, the same bytes.
    const Reply again = get(base + "/thumbnail");
    ASSERT_EQ(again.status, 200);
    EXPECT_EQ(again.headers.find("X-Thumbnail-Cache")->second, "hit");
    EXPECT_EQ(again.body, r.body);
    EXPECT_EQ(cache_files_of(id), 2u);  // the JPEG and its key
    // A new photo (green): a new thumbnail; the old one's files are gone.
    ASSERT_EQ(g_d.get().post_raw(base + "/photos?name=photo2.png&camera=" + cam, png_bytes(cv::Mat(240, 320, CV_8UC3, cv::Scalar(30, 200, 30)))).status, 201);
    r = get(base + "/thumbnail");
    ASSERT_EQ(r.status, 200);
    EXPECT_EQ(r.headers.find("X-Thumbnail-Cache")->second, "miss");
    EXPECT_GT(mean_of(decode(r), cv::Rect(0, 0, 192, 144))[1], 150);
    EXPECT_EQ(cache_files_of(id), 2u);
    // A cache file cut short (a crash while it was written is renamed, so this is damage):
    // its key still matches, but an empty JPEG is not served; the picture is made again.
    for (const auto& f : fs::directory_iterator(g_d.state() / "work" / "thumbnails"))
        if (f.path().extension() == ".jpg" && f.path().filename().string().rfind("case_" + std::to_string(id) + "_", 0) == 0)
            std::ofstream(f.path(), std::ios::trunc).close();
    r = get(base + "/thumbnail");
    ASSERT_EQ(r.status, 200);
    EXPECT_EQ(r.headers.find("X-Thumbnail-Cache")->second, "miss");
    EXPECT_FALSE(decode(r).empty());
}

TEST(Thumbnail, ARegisteredCaseShowsItsFusedViewAndAPoseThatMissesShowsThePhotoSayingWhy) {
    // A phantom case on the 2 mm head: T1, mask, photo; planned; its true pose stored as a run.
    const Head2mm h = head_2mm(g_d.state() / "phantom_src");
    const PhantomCase pc = generate_phantom_case(build_phantom_surface(h.t1, h.mask), plain_phantom_params(), 0);
    const std::int64_t id = g_d.get().new_case("thumb fused");
    const std::string base = "/api/cases/" + std::to_string(id);
    ASSERT_EQ(g_d.get().post_raw(base + "/volumes?name=t1.nii.gz&modality=T1", h.t1_bytes).status, 201);
    ASSERT_EQ(g_d.get().post_raw(base + "/volumes?name=mask.nii.gz&modality=mask", h.mask_bytes).status, 201);
    ASSERT_EQ(g_d.get().post_raw(base + "/photos?name=photo.png&camera=" + url_encode(camera_json(pc.camera).dump()), png_bytes(pc.photo_bgr)).status, 201);
    Reply r = get(base + "/thumbnail");
    ASSERT_EQ(r.status, 200);
    EXPECT_EQ(r.headers.find("X-Thumbnail-Source")->second, "photo");  // not registered yet
    const cv::Mat photo_thumb = decode(r);
    const Reply j = post("/api/jobs", {{"kind", "plan"}, {"params", {{"case_id", id}, {"max_triangles", 20000}}}});
    ASSERT_EQ(j.status, 202) << j.body;
    const json done = poll_job([](const std::string& p) { return get(p); }, j.j.value("id", std::uint64_t{0}));
    ASSERT_EQ(done.value("state", std::string()), "succeeded") << done.dump();
    store_registration(g_d.state() / "store", id, pc.T_camera_from_world);

    r = get(base + "/thumbnail");
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.headers.find("X-Thumbnail-Source")->second, "fused");
    const cv::Mat fused_thumb = decode(r);
    const int th = int(std::lround(double(pc.camera.height) * 192 / pc.camera.width));
    ASSERT_EQ(fused_thumb.cols, 192);
    ASSERT_EQ(fused_thumb.rows, th);
    // It is the fused view of the registered camera at that size (the endpoint's own picture).
    const Reply fv = post(base + "/fused", {{"width", 192}, {"height", th}, {"format", "jpeg"}, {"quality", 82}, {"surface_opacity", 0.7}});
    ASSERT_EQ(fv.status, 200) << fv.body;
    EXPECT_LT(mean_abs_diff(decode(fv), fused_thumb), 1.0);
    // ... and not the photo.
    cv::Mat photo_same;
    cv::resize(photo_thumb, photo_same, fused_thumb.size());
    EXPECT_GT(mean_abs_diff(photo_same, fused_thumb), 5.0);

    // A later run whose pose looks away from the head: the fused view makes no picture (422),
    // so the thumbnail is the photo with the reason in X-Thumbnail-Note.
    Pose away = pc.T_camera_from_world;
    away.topRightCorner<3, 1>() += Eigen::Vector3d(0, 0, -5000);
    store_registration(g_d.state() / "store", id, away);
    r = get(base + "/thumbnail");
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.headers.find("X-Thumbnail-Source")->second, "photo");
    ASSERT_NE(r.headers.find("X-Thumbnail-Note"), r.headers.end());
    std::printf("thumbnail of a run looking away: %s\n", r.headers.find("X-Thumbnail-Note")->second.c_str());
    EXPECT_EQ(get(base + "/thumbnail").headers.find("X-Thumbnail-Cache")->second, "hit");
}

// ---- volumes from removable media ----

TEST(MediaImport, ListsVolumesAndDicomSeriesAndImportsThemCheckedAsAnUpload) {
    const fs::path stick = g_d.state() / "stick";
    // No stick yet: the listing says so (not an error), an import is 404.
    Reply r = get("/api/media/volumes");
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.j["present"], false);
    EXPECT_NE(r.j.value("note", std::string()).find("no removable media"), std::string::npos) << r.body;

    // The stick: a small NIfTI, a corrupt one, six slices of a DICOM series (from tests/data,
    // a scanner's), a folder without DICOM, and a link that leads out of the stick.
    fs::create_directories(stick / "patient" / "MR_T1");
    fs::create_directories(stick / "notes");
    Volume small;
    small.geom.dims = {10, 12, 8};
    small.geom.spacing_mm = Eigen::Vector3d(1.5, 1.5, 2.0);
    small.voxels.resize(small.geom.voxel_count());
    for (std::size_t i = 0; i < small.voxels.size(); ++i) small.voxels[i] = float(i % 97);
    save_volume(small, stick / "small.nii.gz");
    std::ofstream(stick / "bad_t1.nii.gz", std::ios::binary) << "this is not a NIfTI file, only text on a stick";
    std::ofstream(stick / "notes" / "readme.txt") << "hello";
    std::vector<fs::path> slices;
    for (const auto& e : fs::directory_iterator(fs::path(CF_TEST_DATA_DIR) / "dicom_mr_sag")) slices.push_back(e.path());
    std::sort(slices.begin(), slices.end());
    ASSERT_GE(slices.size(), 16u);
    for (std::size_t i = 10; i < 16; ++i) fs::copy_file(slices[i], stick / "patient" / "MR_T1" / slices[i].filename());
    fs::create_directory_symlink(g_d.state() / "store", stick / "escape");

    r = get("/api/media/volumes");
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.j["present"], true);
    std::map<std::string, json> listed;
    for (const auto& v : r.j["volumes"]) listed[v["path"].get<std::string>()] = v;
    ASSERT_EQ(listed.size(), 3u) << r.body;  // not the text file, not through the link
    EXPECT_EQ(listed["small.nii.gz"]["kind"], "nifti");
    EXPECT_EQ(listed["bad_t1.nii.gz"]["kind"], "nifti");
    EXPECT_EQ(listed["patient/MR_T1"]["kind"], "dicom");
    EXPECT_EQ(listed["patient/MR_T1"]["files"], 6);

    const std::int64_t id = g_d.get().new_case("media import");
    const std::string imp = "/api/cases/" + std::to_string(id) + "/volumes/import-media";
    // The DICOM series: read by core's GDCM reader, stored as NIfTI; the stored file reads back
    // to the very voxels core reads from the stick.
    r = post(imp, {{"path", "patient/MR_T1"}, {"modality", "T1"}});
    ASSERT_EQ(r.status, 201) << r.body;
    EXPECT_EQ(r.j["source"]["kind"], "dicom");
    EXPECT_EQ(r.j["original_name"], "MR_T1.nii.gz");
    const Volume from_stick = load_volume(stick / "patient" / "MR_T1");
    EXPECT_EQ(r.j["geometry"]["dims"], json(from_stick.geom.dims));
    const Reply dl = get("/api/cases/" + std::to_string(id) + "/volumes/" + std::to_string(r.j["id"].get<std::int64_t>()));
    ASSERT_EQ(dl.status, 200);
    const fs::path back = g_d.state() / "dicom_back.nii.gz";
    std::ofstream(back, std::ios::binary) << dl.body;
    const Volume stored = load_volume(back);
    ASSERT_EQ(stored.geom.dims, from_stick.geom.dims);
    EXPECT_EQ(stored.voxels, from_stick.voxels);
    EXPECT_LT((stored.geom.spacing_mm - from_stick.geom.spacing_mm).norm(), 1e-4);
    EXPECT_LT((stored.geom.origin_mm - from_stick.geom.origin_mm).norm(), 1e-3);
    // A NIfTI file as a mask-less CT.
    r = post(imp, {{"path", "small.nii.gz"}, {"modality", "CT"}});
    ASSERT_EQ(r.status, 201) << r.body;
    EXPECT_EQ(r.j["geometry"]["dims"], json({10, 12, 8}));
    EXPECT_EQ(r.j["modality"], "CT");

    // Bad input: each refused naming the file and the problem; nothing stored.
    struct Bad {
        json body;
        int status;
        std::string words;
    };
    const std::vector<Bad> bads{
        {{{"path", "bad_t1.nii.gz"}}, 400, "media bad_t1.nii.gz: not a readable volume"},
        {{{"path", "notes"}}, 400, "media notes: the folder holds no DICOM files"},
        {{{"path", "notes/readme.txt"}}, 400, "not a volume file"},
        {{{"path", "../store"}}, 400, "must not hold '..'"},
        {{{"path", "/etc/passwd"}}, 400, "relative to media.removable_root"},
        {{{"path", "escape"}}, 400, "leads outside media.removable_root"},
        {{{"path", "missing.nii"}}, 404, "media missing.nii: no such file"},
        {{{"path", "small.nii.gz"}, {"modality", "PET"}}, 400, "modality"},
        {{{"path", 3}}, 400, "media import path: missing"},
        {{{"path", "small.nii.gz"}, {"from", "x"}}, 400, "from: unknown field"},
    };
    for (const auto& b : bads) {
        const Reply x = post(imp, b.body);
        EXPECT_EQ(x.status, b.status) << b.body.dump() << " -> " << x.body;
        EXPECT_NE(x.body.find(b.words), std::string::npos) << x.body;
    }
    const Reply bad_case = post("/api/cases/987654/volumes/import-media", {{"path", "small.nii.gz"}});
    EXPECT_EQ(bad_case.status, 404) << bad_case.body;
    EXPECT_EQ(get("/api/cases/" + std::to_string(id)).j["volumes"].size(), 2u);
    // No scratch folder is left behind.
    for (const auto& e : fs::directory_iterator(g_d.state() / "work")) EXPECT_EQ(e.path().filename().string().rfind("media_", 0), std::string::npos) << e.path();
    // A reviewer may neither list the cart's media nor import.
    const std::string tok = g_d.get().token_of("rev", "reviewer");
    EXPECT_EQ(g_d.get().get("/api/media/volumes", tok).status, 403);
}
