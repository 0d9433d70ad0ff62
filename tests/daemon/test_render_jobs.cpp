// Picking, planning, export jobs, registration parameters and the fused view through the
// daemon's API (docs/api/render.md, docs/api/jobs.md), against the daemon in-process on a free
// port with the CPU renderer. Small data: the bundled MRI resampled to 2 mm for the cases.
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

using namespace cf::daemon_test;

json test_config(const fs::path& state) {
    json c = base_test_config(state, "cpu");
    c["store"]["max_upload_bytes"] = 8 << 20;
    c["tracker"]["enabled"] = false;
    c["camera"]["backend"] = "none";
    c["jobs"]["progress_hz"] = 50;
    return c;
}

SharedDaemon& g_d = add_shared_daemon("cf_daemon_render_jobs", test_config);
const fs::path& g_state = g_d.state();

int port() { return g_d.port(); }
Reply request(int p, const std::string& method, const std::string& path, const std::string& body = "",
              const std::string& mime = "application/json") {
    return http_request(p, method, path, body, mime);
}
Reply get(const std::string& path) { return g_d.get().get(path); }
Reply post(const std::string& path, const json& body) { return g_d.get().post(path, body); }
Reply post_raw(const std::string& path, const std::string& bytes) { return g_d.get().post_raw(path, bytes); }

void wait_for_volume() { cf::daemon_test::wait_for_volume(g_d.get()); }

/// Polls a job until it ends; `stages` collects the stages seen on the way.
json wait_job(std::uint64_t id, std::set<std::string>* stages = nullptr, double timeout_s = 240) {
    return poll_job([](const std::string& p) { return get(p); }, id, timeout_s, stages);
}

Eigen::Vector3d vec3(const json& a) { return {a[0].get<double>(), a[1].get<double>(), a[2].get<double>()}; }

/// The pick view: the left view of the bundled MRI, a long focal length (0.375 mm a pixel at 450 mm).
struct View {
    Intrinsics K;
    Pose T;
    json body;
};
View pick_view(const Pose& T) {
    View v;
    v.K.width = 320;
    v.K.height = 240;
    v.K.fx = v.K.fy = 1200;
    v.K.cx = (v.K.width - 1) * 0.5;
    v.K.cy = (v.K.height - 1) * 0.5;
    v.T = T;
    v.body = {{"width", v.K.width}, {"height", v.K.height}, {"focal_px", 1200.0}, {"T_camera_from_world", pose_to_json(T)}};
    return v;
}

// ---------------------------------------------------------------------------------------------
// Depth pick

TEST(RenderPick, LandsOnTheRenderedSurfaceSeenFromAnotherView) {
    wait_for_volume();
    const json vol = get("/api/render/volume").j;
    const Eigen::Vector3d centre = vec3(vol["brain"]["center_lps_mm"]);
    const View a = pick_view(standard_view("left", centre, 450));
    json body = a.body;
    body["pixel"] = {160, 120};
    const Reply r = post("/api/render/pick", body);
    ASSERT_EQ(r.status, 200) << r.body;
    const Eigen::Vector3d p = vec3(r.j["p_world_mm"]);
    EXPECT_EQ(r.j["pixel"], json({160, 120}));
    // Round trip 1: the point projects back onto the pixel's centre, at the depth answered.
    const Eigen::Vector3d pc = (a.T * p.homogeneous()).head<3>();
    EXPECT_NEAR(pc.z(), r.j["depth_mm"].get<double>(), 1e-3);
    const auto px = project(a.K, a.T, p);
    ASSERT_TRUE(px);
    EXPECT_NEAR(px->x(), 160, 1e-3);
    EXPECT_NEAR(px->y(), 120, 1e-3);
    // The point is on the brain (brain_only render): a mask voxel within one voxel of it.
    const LabelVolume mask = load_mask(fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz");
    const Eigen::Vector3d ijk = mask.geom.index_from_world() * p;
    bool near_mask = false;
    for (int dk = -1; dk <= 1; ++dk)
        for (int dj = -1; dj <= 1; ++dj)
            for (int di = -1; di <= 1; ++di) {
                const int i = int(std::lround(ijk.x())) + di, j = int(std::lround(ijk.y())) + dj, k = int(std::lround(ijk.z())) + dk;
                if (i >= 0 && j >= 0 && k >= 0 && i < mask.geom.dims[0] && j < mask.geom.dims[1] && k < mask.geom.dims[2])
                    near_mask |= mask.voxels[mask.geom.linear(i, j, k)] != 0;
            }
    EXPECT_TRUE(near_mask) << "picked point " << p.transpose() << " is not on the brain";
    // Round trip 2: seen from a view turned 12 degrees about the brain's centre, the renderer's
    // depth at the point's pixel gives back the same point (within a voxel, 1 mm).
    const View b = pick_view(orbit_pose(a.T, centre, 12, 6));
    const auto pb = project(b.K, b.T, p);
    ASSERT_TRUE(pb);
    json body_b = b.body;
    body_b["pixel"] = {pb->x(), pb->y()};
    const Reply rb = post("/api/render/pick", body_b);
    ASSERT_EQ(rb.status, 200) << rb.body;
    const Eigen::Vector3d p2 = vec3(rb.j["p_world_mm"]);
    EXPECT_LT((p2 - p).norm(), 1.0) << "view a " << p.transpose() << ", view b " << p2.transpose();
    EXPECT_FALSE(rb.j["reused_render"].get<bool>());
}

TEST(RenderPick, ReusesTheLastRenderOfTheSameView) {
    wait_for_volume();
    const json vol = get("/api/render/volume").j;
    const View a = pick_view(standard_view("superior", vec3(vol["brain"]["center_lps_mm"]), 450));
    json render = a.body;
    render["format"] = "png";
    Reply img = post("/api/render", render);
    ASSERT_EQ(img.status, 200) << img.body;
    json body = a.body;
    body["pixel"] = {150, 110};
    const Reply r1 = post("/api/render/pick", body);
    ASSERT_EQ(r1.status, 200) << r1.body;
    EXPECT_TRUE(r1.j["reused_render"].get<bool>());
    // Another view in between: the pick renders afresh, and finds the same point.
    post("/api/render", pick_view(standard_view("left", vec3(vol["brain"]["center_lps_mm"]), 450)).body);
    const Reply r2 = post("/api/render/pick", body);
    ASSERT_EQ(r2.status, 200) << r2.body;
    EXPECT_FALSE(r2.j["reused_render"].get<bool>());
    EXPECT_LT((vec3(r1.j["p_world_mm"]) - vec3(r2.j["p_world_mm"])).norm(), 1e-3);
}

TEST(RenderPick, BadInputIsRefusedNamingIt) {
    wait_for_volume();
    const json vol = get("/api/render/volume").j;
    const View a = pick_view(standard_view("left", vec3(vol["center_lps_mm"]), 450));
    auto with = [&](const json& pixel) {
        json b = a.body;
        b["pixel"] = pixel;
        return post("/api/render/pick", b);
    };
    Reply r = with({0, 0});  // the corner: background
    EXPECT_EQ(r.status, 422) << r.body;
    EXPECT_NE(r.body.find("no surface"), std::string::npos) << r.body;
    r = with({320, 10});
    EXPECT_EQ(r.status, 400) << r.body;
    EXPECT_NE(r.body.find("outside the 320x240 image"), std::string::npos) << r.body;
    r = with({-1, 10});
    EXPECT_EQ(r.status, 400) << r.body;
    r = with({-0.5, -0.5});  // the corner pixel's outer edge: inside, answered for pixel (0, 0)
    EXPECT_EQ(r.status, 422) << r.body;
    EXPECT_NE(r.body.find("(0, 0)"), std::string::npos) << r.body;
    r = with({10});
    EXPECT_EQ(r.status, 400) << r.body;
    EXPECT_NE(r.body.find("pixel"), std::string::npos) << r.body;
    r = with({"a", 10});
    EXPECT_EQ(r.status, 400) << r.body;
    r = post("/api/render/pick", a.body);  // no pixel
    EXPECT_EQ(r.status, 400) << r.body;
    EXPECT_NE(r.body.find("pixel"), std::string::npos) << r.body;
    json b = a.body;
    b["pixel"] = {10, 10};
    b["colour"] = 3;
    r = post("/api/render/pick", b);
    EXPECT_EQ(r.status, 400) << r.body;
    EXPECT_NE(r.body.find("colour"), std::string::npos) << r.body;
    r = request(port(), "POST", "/api/render/pick", "{\"pixel\": [1, 2");
    EXPECT_EQ(r.status, 400) << r.body;
}

TEST(RenderPick, WithoutAVolumeAnswers503) {
    const fs::path state = fs::temp_directory_path() / ("cf_daemon_render_novol_" + std::to_string(::getpid()));
    json c = test_config(state);
    c["data"]["t1"] = (state / "missing_t1.nii.gz").string();
    Daemon d(parse_config(c, "test"));
    d.start();
    Reply r;
    for (int i = 0; i < 100; ++i) {
        r = request(d.port(), "POST", "/api/render/pick", json{{"width", 64}, {"height", 48}, {"pixel", {10, 10}}}.dump());
        if (r.status == 503 && r.body.find("could not be loaded") != std::string::npos) break;
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    EXPECT_EQ(r.status, 503) << r.body;
    EXPECT_NE(r.body.find("could not be loaded"), std::string::npos) << r.body;
    EXPECT_TRUE(d.stop());
    fs::remove_all(state);
}

// ---------------------------------------------------------------------------------------------
// A phantom case on a 2 mm copy of the bundled head, uploaded through the API.

struct PhantomWorld {
    fs::path dir;
    PhantomCase pc;
    std::string t1_bytes, mask_bytes, photo_png;
};
const PhantomWorld& world() {
    static const PhantomWorld w = [] {
        PhantomWorld r;
        r.dir = g_state / "phantom_src";
        const Head2mm h = head_2mm(r.dir);
        r.t1_bytes = h.t1_bytes;
        r.mask_bytes = h.mask_bytes;
        r.pc = generate_phantom_case(build_phantom_surface(h.t1, h.mask), plain_phantom_params(), 0);
        r.photo_png = png_bytes(r.pc.photo_bgr);
        return r;
    }();
    return w;
}

/// A new case holding the phantom's T1 (+ mask, photo, ROI when asked).
std::int64_t phantom_case(const std::string& title, bool mask, bool photo) {
    port();
    const PhantomWorld& w = world();
    const Reply c = post("/api/cases", {{"title", title}});
    EXPECT_EQ(c.status, 201) << c.body;
    const std::int64_t id = c.j.value("id", std::int64_t{0});
    const std::string base = "/api/cases/" + std::to_string(id);
    EXPECT_EQ(post_raw(base + "/volumes?name=t1.nii.gz&modality=T1", w.t1_bytes).status, 201);
    if (mask) {
        EXPECT_EQ(post_raw(base + "/volumes?name=mask.nii.gz&modality=mask", w.mask_bytes).status, 201);
    }
    if (photo) {
        const Reply ph = post_raw(base + "/photos?name=photo.png&camera=" + url_encode(camera_json(w.pc.camera).dump()), w.photo_png);
        EXPECT_EQ(ph.status, 201) << ph.body;
        json pts = json::array();
        for (const auto& q : w.pc.roi_points) pts.push_back({q.x(), q.y()});
        const Reply roi = post(base + "/roi", {{"points", pts}});
        EXPECT_EQ(roi.status, 201) << roi.body;
    }
    return id;
}

/// The case's record without what reads change.
json results_of(std::int64_t id) { return get("/api/cases/" + std::to_string(id) + "/results").j["results"]; }

size_t files_under(const fs::path& d) {
    size_t n = 0;
    std::error_code ec;
    for (auto it = fs::recursive_directory_iterator(d, ec); !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) n += it->is_regular_file();
    return n;
}

std::uint64_t submit(const json& body, int expect = 202) {
    const Reply r = post("/api/jobs", body);
    EXPECT_EQ(r.status, expect) << r.body;
    return r.j.value("id", std::uint64_t{0});
}

// ---------------------------------------------------------------------------------------------
// Plan job

TEST(PlanJob, StoresTheSurfaceAndMaskAsARevisionWithParametersAndTimings) {
    const std::int64_t id = phantom_case("plan", true, false);
    std::set<std::string> stages;
    const std::uint64_t job = submit({{"kind", "plan"}, {"params", {{"case_id", id}, {"max_triangles", 20000}}}});
    const json done = wait_job(job, &stages);
    ASSERT_EQ(done.value("state", std::string()), "succeeded") << done.dump();
    EXPECT_EQ(done["params"]["brain_mask"], "case_mask");
    EXPECT_EQ(done["result"]["plan_revision"], 1);
    EXPECT_GT(stages.size(), 2u) << "progress stages seen: " << json(stages).dump();
    std::map<std::string, json> by_kind;
    for (const auto& r : results_of(id)) by_kind[r["kind"]] = r;
    ASSERT_TRUE(by_kind.count("plan_json") && by_kind.count("plan_brain_surface") && by_kind.count("plan_brain_mask")) << results_of(id).dump();
    const json& pj = by_kind["plan_json"];
    EXPECT_EQ(pj["params"]["plan_revision"], 1);
    EXPECT_GT(pj["params"]["seconds"].get<double>(), 0);
    EXPECT_EQ(pj["params"]["params"]["max_triangles"], 20000);
    EXPECT_TRUE(pj["params"]["plan"].is_object());
    EXPECT_EQ(pj["params"]["plan"].dump().find("/work/"), std::string::npos) << "no scratch path in plan.json";
    const Reply stored_plan = get(pj["download"].get<std::string>());
    ASSERT_EQ(stored_plan.status, 200);
    EXPECT_EQ(stored_plan.j["steps"], pj["params"]["plan"]["steps"]);
    EXPECT_EQ(stored_plan.body.find("/work/"), std::string::npos) << stored_plan.body.substr(0, 300);
    // The stored surface: a mesh within the head, within the triangle budget.
    const Reply mesh = get(by_kind["plan_brain_surface"]["download"].get<std::string>());
    ASSERT_EQ(mesh.status, 200);
    const fs::path ply = g_state / "check_surface.ply";
    std::ofstream(ply, std::ios::binary) << mesh.body;
    const SurfaceMesh m = load_mesh(ply);
    EXPECT_GT(m.triangles.size(), 1000u);
    EXPECT_LE(m.triangles.size(), 20000u);
    const Volume t1 = load_volume(world().dir / "t1.nii.gz");
    Eigen::Vector3f lo = m.vertices[0], hi = lo;
    for (const auto& v : m.vertices) lo = lo.cwiseMin(v), hi = hi.cwiseMax(v);
    EXPECT_GT((hi - lo).minCoeff(), 80.f) << "the brain is > 80 mm in every direction";
    EXPECT_LT(((lo + hi) * 0.5f).cast<double>().norm() - t1.geom.center_world_mm().norm(), 60.0);
    // A second plan: revision 2, the first kept.
    const json again = wait_job(submit({{"kind", "plan"}, {"params", {{"case_id", id}, {"max_triangles", 10000}}}}));
    ASSERT_EQ(again.value("state", std::string()), "succeeded") << again.dump();
    EXPECT_EQ(again["result"]["plan_revision"], 2);
    int plans = 0;
    for (const auto& r : results_of(id)) plans += r["kind"] == "plan_json";
    EXPECT_EQ(plans, 2);
    EXPECT_EQ(files_under(g_state / "work" / ("plan_" + std::to_string(job))), 0u);
}

TEST(PlanJob, CancelAndBadInputStoreNothing) {
    const std::int64_t id = phantom_case("plan cancel", false, false);
    const std::string before = get("/api/cases/" + std::to_string(id)).j["results"].dump();
    const size_t jobs_before = get("/api/jobs").j["jobs"].size();
    // Bad input: refused before anything is queued.
    struct Bad {
        json params;
        int status;
        const char* names;
    };
    const std::vector<Bad> bad = {
        {{{"case_id", id}, {"bogus", 1}}, 400, "bogus"},
        {{{"case_id", "x"}}, 400, "case_id"},
        {json::object(), 400, "case_id"},
        {{{"case_id", 999999}}, 404, "999999"},
        {{{"case_id", id}, {"brain_mask", "case_mask"}}, 409, "mask"},
        {{{"case_id", id}, {"brain_mask", "magic"}}, 400, "brain_mask"},
        {{{"case_id", id}, {"max_triangles", 5}}, 400, "max_triangles"},
        {{{"case_id", id}, {"ct_volume_id", 999999}}, 404, "ct_volume_id"},
        {{{"case_id", id}, {"ct", "yes"}}, 400, "ct"},
    };
    for (const auto& b : bad) {
        const Reply r = post("/api/jobs", {{"kind", "plan"}, {"params", b.params}});
        EXPECT_EQ(r.status, b.status) << b.params.dump() << " -> " << r.body;
        EXPECT_NE(r.body.find(b.names), std::string::npos) << r.body;
    }
    // A T1 given as the CT.
    const json vols = get("/api/cases/" + std::to_string(id)).j["volumes"];
    const Reply wrong = post("/api/jobs", {{"kind", "plan"}, {"params", {{"case_id", id}, {"ct_volume_id", vols[0]["id"]}}}});
    EXPECT_EQ(wrong.status, 400) << wrong.body;
    EXPECT_NE(wrong.body.find("not CT"), std::string::npos) << wrong.body;
    // A case without a T1.
    const Reply empty_case = post("/api/cases", {{"title", "no volumes"}});
    const Reply no_t1 = post("/api/jobs", {{"kind", "plan"}, {"params", {{"case_id", empty_case.j["id"]}}}});
    EXPECT_EQ(no_t1.status, 409) << no_t1.body;
    EXPECT_EQ(get("/api/jobs").j["jobs"].size(), jobs_before);
    // Cancel while it runs (skull stripping: the longest part).
    const std::uint64_t job = submit({{"kind", "plan"}, {"params", {{"case_id", id}}}});
    for (int i = 0; i < 400 && get("/api/jobs/" + std::to_string(job)).j.value("state", std::string()) == "queued"; ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    EXPECT_EQ(post("/api/jobs/" + std::to_string(job) + "/cancel", json::object()).status, 200);
    const json end = wait_job(job, nullptr, 60);
    EXPECT_EQ(end.value("state", std::string()), "cancelled") << end.dump();
    EXPECT_EQ(get("/api/cases/" + std::to_string(id)).j["results"].dump(), before);
    EXPECT_FALSE(fs::exists(g_state / "work" / ("plan_" + std::to_string(job))));
}

// ---------------------------------------------------------------------------------------------
// Export job

TEST(ExportJob, WritesTheZipOffTheConnectionAndServesIt) {
    const std::int64_t id = phantom_case("export", true, false);
    std::set<std::string> stages;
    const std::uint64_t job = submit({{"kind", "export"}, {"params", {{"case_id", id}}}});
    const json done = wait_job(job, &stages);
    ASSERT_EQ(done.value("state", std::string()), "succeeded") << done.dump();
    const Reply zip = get(done["result"]["download"].get<std::string>());
    ASSERT_EQ(zip.status, 200);
    EXPECT_EQ(zip.body.substr(0, 2), "PK");
    EXPECT_EQ(std::int64_t(zip.body.size()), done["result"]["size_bytes"].get<std::int64_t>());
    EXPECT_GT(zip.body.size(), world().t1_bytes.size());  // holds the T1 (stored, not recompressed smaller than gzip)
    // The zip imports as the same case (uid already there: 409), so it is a real export.
    const Reply imp = request(port(), "POST", "/api/cases/import-zip?name=case.zip", zip.body, "application/octet-stream");
    EXPECT_EQ(imp.status, 409) << imp.body;
    // Bad input.
    EXPECT_EQ(post("/api/jobs", {{"kind", "export"}, {"params", {{"case_id", 999999}}}}).status, 404);
    EXPECT_EQ(post("/api/jobs", {{"kind", "export"}, {"params", {{"case_id", id}, {"to", "/etc"}}}}).status, 400);
    EXPECT_EQ(post("/api/jobs", {{"kind", "export"}, {"params", json::object()}}).status, 400);
    // Downloads: not an export job, unknown job.
    const std::uint64_t plan = submit({{"kind", "plan"}, {"params", {{"case_id", id}, {"max_triangles", 5000}}}});
    wait_job(plan);
    EXPECT_EQ(get("/api/jobs/" + std::to_string(plan) + "/download").status, 409);
    EXPECT_EQ(get("/api/jobs/999999/download").status, 404);
    EXPECT_EQ(get("/api/jobs/abc/download").status, 400);
}

// ---------------------------------------------------------------------------------------------
// Register parameters

TEST(RegisterJob, ScheduleOverridesAreCheckedAndSavedWithTheRun) {
    const std::int64_t id = phantom_case("register params", true, true);
    const size_t jobs_before = get("/api/jobs").j["jobs"].size();
    for (const json& p : {json{{"bogus_key", 1}}, json{{"bins", -3}}, json{{"search_stages", "fast"}}, json("defaults"),
                          json{{"metric", "ssd"}}}) {
        const Reply r = post("/api/jobs", {{"kind", "register"}, {"params", {{"case_id", id}, {"params", p}}}});
        EXPECT_EQ(r.status, 400) << p.dump() << " -> " << r.body;
        EXPECT_NE(r.body.find("register params"), std::string::npos) << p.dump() << " -> " << r.body;
    }
    EXPECT_EQ(get("/api/jobs").j["jobs"].size(), jobs_before);
    EXPECT_EQ(get("/api/cases/" + std::to_string(id) + "/registrations").j["registrations"].size(), 0u);
    // A valid override: queued with it, and the run (cancelled at once: quick) is stored with it.
    const std::uint64_t job = submit({{"kind", "register"}, {"params", {{"case_id", id}, {"params", {{"bins", 24}, {"keep_best", 2}}}}}});
    EXPECT_EQ(get("/api/jobs/" + std::to_string(job)).j["params"]["params"]["bins"], 24);
    for (int i = 0; i < 400 && get("/api/jobs/" + std::to_string(job)).j.value("state", std::string()) == "queued"; ++i)
        std::this_thread::sleep_for(std::chrono::milliseconds(10));
    post("/api/jobs/" + std::to_string(job) + "/cancel", json::object());
    const json end = wait_job(job, nullptr, 120);
    EXPECT_EQ(end.value("state", std::string()), "cancelled") << end.dump();
    const json regs = get("/api/cases/" + std::to_string(id) + "/registrations").j["registrations"];
    ASSERT_EQ(regs.size(), 1u) << regs.dump() << " job " << end.dump();
    EXPECT_EQ(regs[0]["params"]["bins"], 24);
    EXPECT_EQ(regs[0]["params"]["keep_best"], 2);
}

// ---------------------------------------------------------------------------------------------
// Fused view

TEST(FusedView, RoiPixelsShowThePhotoFromTheRegisteredCamera) {
    const std::int64_t id = phantom_case("fused", true, true);
    const std::string base = "/api/cases/" + std::to_string(id);
    // Before a plan and a registration: 409 saying what is missing.
    Reply r = post(base + "/fused", json::object());
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("registration"), std::string::npos) << r.body;
    const json plan = wait_job(submit({{"kind", "plan"}, {"params", {{"case_id", id}, {"max_triangles", 60000}}}}));
    ASSERT_EQ(plan.value("state", std::string()), "succeeded") << plan.dump();
    // The registration: the phantom's true pose, stored as a run of the case (what a register
    // job stores), through a second connection to the store.
    const PhantomWorld& w = world();
    store_registration(g_state / "store", id, w.pc.T_camera_from_world);
    // Snap to camera: the registered pose and the photo's camera.
    r = get(base + "/fused/camera");
    ASSERT_EQ(r.status, 200) << r.body;
    const Pose T = parse_pose(r.j, "answer");
    EXPECT_LT((T - w.pc.T_camera_from_world).cwiseAbs().maxCoeff(), 1e-9);
    EXPECT_EQ(r.j["width"], w.pc.camera.width);
    EXPECT_EQ(r.j["camera"]["fx"].get<double>(), w.pc.camera.fx);
    // The fused picture from the registered camera: inside the ROI (eroded 4 px) the pixels
    // where the surface is textured are the photo's.
    auto fused = [&](double opacity) {
        const Reply f = post(base + "/fused", {{"surface_opacity", opacity}, {"format", "png"}});
        EXPECT_EQ(f.status, 200) << "fused answer: " << f.j.dump();
        return cv::imdecode(cv::Mat(1, int(f.body.size()), CV_8U, const_cast<char*>(f.body.data())), cv::IMREAD_COLOR);
    };
    const cv::Mat on = fused(1.0), off = fused(0.0);
    ASSERT_EQ(on.cols, w.pc.camera.width);
    ASSERT_EQ(on.rows, w.pc.camera.height);
    Roi roi;
    roi.points = w.pc.roi_points;
    cv::Mat inside = roi_mask(roi, on.cols, on.rows);
    cv::erode(inside, inside, cv::getStructuringElement(cv::MORPH_ELLIPSE, {9, 9}));
    auto match_fraction = [&](const cv::Mat& img, double* mean_diff) {
        int n = 0, close = 0;
        double sum = 0;
        for (int v = 0; v < img.rows; ++v)
            for (int u = 0; u < img.cols; ++u) {
                if (!inside.at<uchar>(v, u)) continue;
                const cv::Vec3b a = img.at<cv::Vec3b>(v, u), b = w.pc.photo_bgr.at<cv::Vec3b>(v, u);
                const double d = (std::abs(a[0] - b[0]) + std::abs(a[1] - b[1]) + std::abs(a[2] - b[2])) / 3.0;
                sum += d;
                close += d <= 12;
                ++n;
            }
        *mean_diff = sum / std::max(n, 1);
        return double(close) / std::max(n, 1);
    };
    double diff_on = 0, diff_off = 0;
    const double frac_on = match_fraction(on, &diff_on), frac_off = match_fraction(off, &diff_off);
    std::printf("fused ROI pixels within 12 grey levels of the photo: opacity 1 %.1f %% (mean diff %.1f), opacity 0 %.1f %% (mean %.1f)\n",
                100 * frac_on, diff_on, 100 * frac_off, diff_off);
    EXPECT_GT(frac_on, 0.9);
    EXPECT_LT(diff_on, 6.0);
    EXPECT_LT(frac_off, 0.5);
    // Another viewpoint (the UI's orbit) still answers, and bad input is refused.
    const Pose T2 = orbit_pose(T, w.pc.targets_world_mm.empty() ? Eigen::Vector3d(0, 0, 0) : w.pc.targets_world_mm[0], 20, 0);
    r = post(base + "/fused", {{"T_camera_from_world", pose_to_json(T2)}, {"width", 160}, {"height", 120}, {"focal_px", 300.0}});
    EXPECT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(post(base + "/fused", {{"surface_opacity", 2}}).status, 400);
    EXPECT_EQ(post(base + "/fused", {{"registration_id", 999999}}).status, 404);
    EXPECT_EQ(post("/api/cases/999999/fused", json::object()).status, 404);
    EXPECT_EQ(get(base + "/fused/camera?registration_id=abc").status, 400);
}

}  // namespace
