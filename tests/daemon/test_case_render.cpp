// Per-case views through the daemon's API (docs/api/render.md, docs/api/case-data.md): renders,
// picks and navigation slices of a case's own stored volume (not data.t1), multimodal renders
// of the plan's CT with the T1 (GL fusion; skipped without GL), the intensity histogram of a
// case volume, and the plan job's single store transaction with the `planned` state.
// The daemon runs in-process on a free port (renderer.kind auto: GL through llvmpipe here, the
// CPU without it). Small data: the bundled MRI resampled to 2 mm serves as data.t1, and a copy
// of it moved 30 mm along x as the case's volume.
// Eigen first: <httplib.h> pulls in <resolv.h>, whose _res macro breaks Eigen's headers.
#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "cortexfuse/core/volume.hpp"
#include "cortexfuse/daemon/daemon.hpp"

#include "daemon_fixture.hpp"

#include <gtest/gtest.h>
#include <httplib.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <thread>

#include "case_jobs.hpp"

using namespace cf;
using namespace cf::daemon;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

using namespace cf::daemon_test;

constexpr double kShiftXmm = 30.0;  // the case's volume: data.t1 moved this far along +x (LPS)

json test_config(const fs::path& state) {
    json c = base_test_config(state, "auto");
    c["store"]["max_upload_bytes"] = 16 << 20;
    c["tracker"]["enabled"] = false;
    c["camera"]["backend"] = "none";
    c["jobs"]["progress_hz"] = 50;
    return c;
}

struct Data {
    std::string t1_bytes, mask_bytes, shifted_t1_bytes, shifted_mask_bytes, ct_bytes;
    fs::path t1_path, mask_path;
};
const Data& data();

SharedDaemon& g_d = add_shared_daemon(
    "cf_daemon_case_render",
    [](const fs::path& state) {
        fs::create_directories(state);
        ::setenv("LP_NUM_THREADS", "2", 0);
        json c = test_config(state);
        c["data"]["t1"] = data().t1_path.string();
        c["data"]["brain_mask"] = data().mask_path.string();
        return c;
    },
    180, [] { set_plan_store_hook_for_tests({}); });
const fs::path& g_state = g_d.state();

const Data& data() {
    static const Data d = [] {
        Data r;
        const fs::path dir = g_state / "src";
        Head2mm h = head_2mm(dir);
        Volume& t1s = h.t1;
        LabelVolume& ms = h.mask;
        r.t1_path = h.t1_path;
        r.mask_path = h.mask_path;
        r.t1_bytes = h.t1_bytes;
        r.mask_bytes = h.mask_bytes;
        // The same voxels with the origin moved: the head sits 30 mm further along +x.
        t1s.geom.origin_mm.x() += kShiftXmm;
        ms.geom.origin_mm.x() += kShiftXmm;
        save_volume(t1s, dir / "t1_shifted.nii.gz");
        save_mask(ms, dir / "mask_shifted.nii.gz");
        r.shifted_t1_bytes = read_bytes(dir / "t1_shifted.nii.gz");
        r.shifted_mask_bytes = read_bytes(dir / "mask_shifted.nii.gz");
        // A "CT" on the (unshifted) T1's grid: a changed intensity mapping of the same head.
        t1s.geom.origin_mm.x() -= kShiftXmm;
        Volume ct = t1s;
        for (auto& v : ct.voxels) v = 2.f * v + 100.f;
        save_volume(ct, dir / "ct.nii.gz");
        r.ct_bytes = read_bytes(dir / "ct.nii.gz");
        return r;
    }();
    return d;
}

int port() { return g_d.port(); }
Reply get(const std::string& path) { return g_d.get().get(path); }
Reply post(const std::string& path, const json& body) { return g_d.get().post(path, body); }
Reply post_raw(const std::string& path, const std::string& bytes) { return g_d.get().post_raw(path, bytes); }

void wait_for_volume() { cf::daemon_test::wait_for_volume(g_d.get()); }

json wait_job(std::uint64_t id, double timeout_s = 240) {
    return poll_job([](const std::string& p) { return get(p); }, id, timeout_s);
}

std::int64_t new_case(const std::string& title) { return g_d.get().new_case(title); }
std::int64_t upload(std::int64_t id, const std::string& name, const std::string& modality, const std::string& bytes) {
    const Reply r = post_raw("/api/cases/" + std::to_string(id) + "/volumes?name=" + name + "&modality=" + modality, bytes);
    EXPECT_EQ(r.status, 201) << r.body;
    return r.j.value("id", std::int64_t{0});
}
std::string base(std::int64_t id) { return "/api/cases/" + std::to_string(id); }

Eigen::Vector3d vec3(const json& a) { return {a[0].get<double>(), a[1].get<double>(), a[2].get<double>()}; }

/// A 160x120 view from a pose (png: exact pixels).
json view_body(const Pose& T) {
    return {{"width", 160}, {"height", 120}, {"focal_px", 600.0}, {"T_camera_from_world", pose_to_json(T)}, {"format", "png"}};
}
Pose translated(const Pose& T, const Eigen::Vector3d& d_world) {
    // The same camera moved by d in the world: T' = T * translate(-d).
    Pose t = Pose::Identity();
    t.topRightCorner<3, 1>() = -d_world;
    return T * t;
}

std::int64_t shifted_case() {
    static const std::int64_t id = [] {
        port();
        const std::int64_t c = new_case("shifted head");
        upload(c, "t1.nii.gz", "T1", data().shifted_t1_bytes);
        upload(c, "mask.nii.gz", "mask", data().shifted_mask_bytes);
        return c;
    }();
    return id;
}

long rss_kib() {
    std::ifstream in("/proc/self/status");
    std::string k;
    while (in >> k)
        if (k == "VmRSS:") {
            long v = 0;
            in >> v;
            return v;
        }
    return -1;
}

// ---------------------------------------------------------------------------------------------
// Per-case rendering

TEST(CaseRender, RendersTheCasesOwnVolumeNotTheBundledOne) {
    wait_for_volume();
    const std::int64_t id = shifted_case();
    const Eigen::Vector3d centre = vec3(get("/api/render/volume").j["brain"]["center_lps_mm"]);
    const Pose T = standard_view("anterior", centre, 450);
    const Reply bundled = post("/api/render", view_body(T));
    ASSERT_EQ(bundled.status, 200) << bundled.body;
    EXPECT_FALSE(bundled.headers.count("X-Render-Volume"));
    json b = view_body(T);
    b["case_id"] = id;
    const Reply mine = post("/api/render", b);
    ASSERT_EQ(mine.status, 200) << mine.body;
    EXPECT_NE(mine.headers.find("X-Render-Volume")->second.find("case " + std::to_string(id)), std::string::npos);
    const cv::Mat a = decode(bundled), c = decode(mine);
    ASSERT_FALSE(a.empty());
    ASSERT_FALSE(c.empty());
    // Seen from the same pose, the moved head looks different ...
    const double differ = mean_abs_diff(a, c);
    EXPECT_GT(differ, 5.0);
    // ... and from a camera moved with it, the same as the bundled head.
    b["T_camera_from_world"] = pose_to_json(translated(T, {kShiftXmm, 0, 0}));
    const Reply moved = post("/api/render", b);
    ASSERT_EQ(moved.status, 200) << moved.body;
    const double same = mean_abs_diff(a, decode(moved));
    EXPECT_LT(same, 0.5) << "moved camera: " << same << " grey levels from the bundled view (unmoved: " << differ << ")";
    // Without brain_only the whole case volume renders (the skin preset shows the head's outline).
    json whole = b;
    whole["preset"] = "skin";
    whole["brain_only"] = false;
    EXPECT_EQ(post("/api/render", whole).status, 200);
    // The named standard views look at the case volume's own centre.
    json named = {{"width", 160}, {"height", 120}, {"view", "left"}, {"format", "png"}, {"case_id", id}};
    const Reply nv = post("/api/render", named);
    ASSERT_EQ(nv.status, 200);
    named.erase("case_id");
    const double named_diff = mean_abs_diff(decode(nv), decode(post("/api/render", named)));
    EXPECT_LT(named_diff, 0.5) << "standard views are centred on each volume";
    // The case volume's geometry: the bundled one's moved by 30 mm.
    const json g0 = get("/api/render/volume").j, g1 = get("/api/render/volume?case_id=" + std::to_string(id)).j;
    ASSERT_TRUE(g1.contains("center_lps_mm")) << g1.dump();
    EXPECT_LT((vec3(g1["center_lps_mm"]) - vec3(g0["center_lps_mm"]) - Eigen::Vector3d(kShiftXmm, 0, 0)).norm(), 1e-3);
    EXPECT_LT((vec3(g1["brain"]["center_lps_mm"]) - vec3(g0["brain"]["center_lps_mm"]) - Eigen::Vector3d(kShiftXmm, 0, 0)).norm(), 1e-3);
    EXPECT_EQ(get("/api/render/volume?case_id=x").status, 400);
    EXPECT_EQ(get("/api/render/volume?case_id=999999").status, 404);
    std::cout << "[ figures ] same pose " << differ << " grey levels apart; camera moved with the head " << same
              << "; renderer " << mine.headers.find("X-Renderer")->second << "; RSS " << rss_kib() / 1024 << " MiB\n";
}

TEST(CaseRender, PickLandsOnTheCasesSurface) {
    wait_for_volume();
    const std::int64_t id = shifted_case();
    const Eigen::Vector3d centre = vec3(get("/api/render/volume").j["brain"]["center_lps_mm"]);
    // Looking along x (the left view): the moved head's surface is 30 mm further along the ray.
    json b = view_body(standard_view("left", centre, 450));
    b["pixel"] = {80, 60};
    const Reply bundled = post("/api/render/pick", b);
    ASSERT_EQ(bundled.status, 200) << bundled.body;
    b["case_id"] = id;
    const Reply mine = post("/api/render/pick", b);
    ASSERT_EQ(mine.status, 200) << mine.body;
    const Eigen::Vector3d d = vec3(mine.j["p_world_mm"]) - vec3(bundled.j["p_world_mm"]);
    EXPECT_LT((d - Eigen::Vector3d(kShiftXmm, 0, 0)).norm(), 1.0) << "pick moved by " << d.transpose();
    EXPECT_NEAR(std::abs(mine.j["depth_mm"].get<double>() - bundled.j["depth_mm"].get<double>()), kShiftXmm, 1.0);
    EXPECT_NE(mine.j.value("volume", std::string()).find("case " + std::to_string(id)), std::string::npos);
    // The same view of the bundled MRI again does not reuse the case's depth.
    b.erase("case_id");
    const Reply again = post("/api/render/pick", b);
    ASSERT_EQ(again.status, 200);
    EXPECT_LT((vec3(again.j["p_world_mm"]) - vec3(bundled.j["p_world_mm"])).norm(), 1e-3);
}

TEST(CaseRender, KeepsPreparedRenderersPerVolume) {
    wait_for_volume();
    const std::int64_t id = shifted_case();
    // brain_only fixed: a custom transfer function otherwise defaults to the whole volume, a
    // renderer of its own (the preset's default is the brain only).
    json b = {{"width", 64}, {"height", 48}, {"view", "left"}, {"case_id", id}, {"brain_only", true}};
    ASSERT_EQ(post("/api/render", b).status, 200);
    const auto prep0 = get("/api/status").j["modules"]["renderer"]["case_preparations"].get<std::uint64_t>();
    for (const char* v : {"right", "superior", "left"}) {
        b["view"] = v;
        ASSERT_EQ(post("/api/render", b).status, 200);
    }
    b["tf"] = {{"colour", {{0, 1, 1, 1}, {1, 1, 1, 1}}}, {"opacity", {{0, 0}, {0.3, 0}, {0.5, 0.8}, {1, 1}}}};
    ASSERT_EQ(post("/api/render", b).status, 200);
    EXPECT_EQ(get("/api/status").j["modules"]["renderer"]["case_preparations"].get<std::uint64_t>(), prep0)
        << "views and transfer functions of a prepared volume prepare nothing again";
}

TEST(CaseRender, BadCaseInputIsRefusedNamingIt) {
    wait_for_volume();
    const std::int64_t id = shifted_case();
    const std::int64_t empty = new_case("no volumes");
    struct Bad {
        json extra;
        int status;
        std::string names;
    };
    std::int64_t mask_id = 0;
    const json rec = get(base(id)).j;
    for (const auto& v : rec["volumes"])
        if (v["modality"] == "mask") mask_id = v["id"].get<std::int64_t>();
    ASSERT_GT(mask_id, 0) << rec.dump().substr(0, 400);
    const std::vector<Bad> bad = {
        {{{"case_id", "x"}}, 400, "case_id"},
        {{{"case_id", 0}}, 400, "case_id"},
        {{{"case_id", 999999}}, 404, "999999"},
        {{{"case_id", empty}}, 409, "no T1"},
        {{{"case_id", id}, {"volume_id", 999999}}, 404, "volume_id"},
        {{{"case_id", id}, {"volume_id", mask_id}}, 400, "is a mask"},
        {{{"volume_id", 1}}, 400, "without case_id"},
        {{{"modalities", json::array({{{"name", "t1"}}})}}, 400, "need case_id"},
        {{{"case_id", id}, {"modalities", json::array({{{"name", "pet"}}})}}, 400, "pet"},
        {{{"case_id", id}, {"modalities", json::array({{{"name", "ct"}}})}}, 409, "no plan with a CT"},
        {{{"case_id", id}, {"modalities", json::array({{{"name", "fmri"}}})}}, 409, "fMRI"},
        {{{"case_id", id}, {"modalities", json::array({json::object()})}}, 400, "modalities[0].name"},
        {{{"case_id", id}, {"modalities", json::array({{{"name", "t1"}, {"weight", 2}}})}}, 400, "modalities[0].weight"},
        {{{"case_id", id}, {"modalities", json::array({{{"name", "t1"}, {"transfer_function", "nope"}}})}}, 400, "nope"},
        {{{"case_id", id}, {"modalities", json::array({{{"name", "t1"}, {"visible", 1}}})}}, 400, "visible"},
        {{{"case_id", id}, {"modalities", json::array({{{"name", "t1"}}, {{"name", "t1"}}})}}, 400, "twice"},
        {{{"case_id", id}, {"modalities", json::array({{{"name", "t1"}, {"colour", 1}}})}}, 400, "modalities[0].colour"},
    };
    for (const auto& c : bad) {
        json b = {{"width", 32}, {"height", 32}};
        b.update(c.extra);
        const Reply r = post("/api/render", b);
        EXPECT_EQ(r.status, c.status) << c.extra.dump() << " -> " << r.body;
        EXPECT_NE(r.body.find(c.names), std::string::npos) << c.extra.dump() << " -> " << r.body;
    }
    json p = {{"width", 32}, {"height", 32}, {"pixel", {1, 1}}, {"case_id", 999999}};
    EXPECT_EQ(post("/api/render/pick", p).status, 404);
}

TEST(CaseRender, NavigationSlicesCutTheCasesVolume) {
    wait_for_volume();
    const std::int64_t id = shifted_case();
    const Eigen::Vector3d c = vec3(get("/api/render/volume").j["center_lps_mm"]);
    auto slices = [&](const Eigen::Vector3d& p, const std::string& extra) {
        const Reply r = get("/api/navigation/slices?size=96&format=png&x=" + std::to_string(p.x()) + "&y=" + std::to_string(p.y()) + "&z=" +
                            std::to_string(p.z()) + extra);
        EXPECT_EQ(r.status, 200) << r.body;
        return r;
    };
    const Reply bundled = slices(c, "");
    const Reply here = slices(c, "&case_id=" + std::to_string(id));
    const Reply moved = slices(c + Eigen::Vector3d(kShiftXmm, 0, 0), "&case_id=" + std::to_string(id));
    EXPECT_NE(here.headers.find("X-Slice-Volume")->second.find("case " + std::to_string(id)), std::string::npos);
    EXPECT_GT(mean_abs_diff(decode(bundled), decode(here)), 3.0);
    EXPECT_LT(mean_abs_diff(decode(bundled), decode(moved)), 0.5) << "the case's slices through the moved point are the bundled ones";
    EXPECT_EQ(get("/api/navigation/slices?case_id=abc").status, 400);
    EXPECT_EQ(get("/api/navigation/slices?volume_id=3").status, 400);
    EXPECT_EQ(get("/api/navigation/slices?case_id=999999").status, 404);
}

// ---------------------------------------------------------------------------------------------
// Histogram

TEST(CaseHistogram, CountsMatchADirectCountInTheRenderersUnits) {
    port();
    // A small volume with known values: a ramp, zeros in one corner, and a mask over half.
    Volume v;
    v.geom.dims = {7, 6, 5};
    v.geom.spacing_mm = {1.5, 1.5, 2.0};
    v.voxels.resize(v.geom.voxel_count());
    LabelVolume m;
    m.geom = v.geom;
    m.voxels.assign(v.geom.voxel_count(), 0);
    for (int k = 0; k < 5; ++k)
        for (int j = 0; j < 6; ++j)
            for (int i = 0; i < 7; ++i) {
                const std::size_t n = v.geom.linear(i, j, k);
                v.voxels[n] = (i < 2 && j < 2) ? 0.f : float(10 * i + 3 * j + 17 * k) + 0.25f;
                m.voxels[n] = i < 4;  // the lower values: a brain range of its own
            }
    const fs::path dir = g_state / "hist";
    fs::create_directories(dir);
    save_volume(v, dir / "small.nii.gz");
    save_mask(m, dir / "small_mask.nii.gz");
    const Volume vr = load_volume(dir / "small.nii.gz");  // as stored (NIfTI floats)
    const std::int64_t id = new_case("histogram");
    const std::int64_t vid = upload(id, "small.nii.gz", "T1", read_bytes(dir / "small.nii.gz"));
    const Reply noms = get(base(id) + "/volumes/" + std::to_string(vid) + "/histogram?bins=16");
    ASSERT_EQ(noms.status, 200) << noms.body;
    EXPECT_TRUE(noms.j["normalizations"]["brain_only"].is_null());
    EXPECT_FALSE(noms.j["normalizations"]["whole"].contains("inside"));
    upload(id, "small_mask.nii.gz", "mask", read_bytes(dir / "small_mask.nii.gz"));
    const Reply r = get(base(id) + "/volumes/" + std::to_string(vid) + "/histogram?bins=16");
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.j["bins"], 16);
    EXPECT_EQ(r.j["voxels"], 7 * 6 * 5);
    const LabelVolume mr = load_mask(dir / "small_mask.nii.gz");
    for (const bool brain : {false, true}) {
        const auto range = robust_range(vr, brain ? &mr : nullptr);  // the renderer's normalisation
        const json& h = r.j["normalizations"][brain ? "brain_only" : "whole"];
        ASSERT_TRUE(h.is_object()) << r.body;
        EXPECT_NEAR(h["range"][0].get<double>(), range[0], 1e-9);
        EXPECT_NEAR(h["range"][1].get<double>(), range[1], 1e-9);
        std::vector<std::uint64_t> in(16, 0), out(16, 0);
        std::uint64_t below = 0, above = 0, total = 0;
        for (std::size_t n = 0; n < vr.voxels.size(); ++n) {
            const double x = (vr.voxels[n] - range[0]) / (range[1] - range[0]);
            if (x < 0) ++below;
            else if (x > 1) ++above;
            else {
                int b = 0;
                while (b < 15 && x >= double(b + 1) / 16) ++b;  // the bin whose [b, b+1)/16 holds x
                (mr.voxels[n] ? in : out)[std::size_t(b)]++;
            }
        }
        EXPECT_EQ(h["inside"].get<std::vector<std::uint64_t>>(), in) << (brain ? "brain" : "whole");
        EXPECT_EQ(h["outside"].get<std::vector<std::uint64_t>>(), out) << (brain ? "brain" : "whole");
        const std::uint64_t b_all = h["below_inside"].get<std::uint64_t>() + h["below_outside"].get<std::uint64_t>();
        const std::uint64_t a_all = h["above_inside"].get<std::uint64_t>() + h["above_outside"].get<std::uint64_t>();
        EXPECT_EQ(b_all, below);
        EXPECT_EQ(a_all, above);
        for (auto c : in) total += c;
        for (auto c : out) total += c;
        EXPECT_EQ(total + below + above, vr.voxels.size());
    }
    EXPECT_NE(r.j["normalizations"]["whole"]["range"], r.j["normalizations"]["brain_only"]["range"]) << "the mask changes the range";
    // Bad input.
    EXPECT_EQ(get(base(id) + "/volumes/" + std::to_string(vid) + "/histogram?bins=4").status, 400);
    EXPECT_EQ(get(base(id) + "/volumes/" + std::to_string(vid) + "/histogram?bins=x").status, 400);
    EXPECT_EQ(get(base(id) + "/volumes/999999/histogram").status, 404);
    EXPECT_EQ(get("/api/cases/999999/volumes/1/histogram").status, 404);
}

// ---------------------------------------------------------------------------------------------
// Plan job: one transaction, the planned state

std::uint64_t submit_plan(std::int64_t id) {
    const Reply r = post("/api/jobs", {{"kind", "plan"}, {"params", {{"case_id", id}, {"max_triangles", 5000}}}});
    EXPECT_EQ(r.status, 202) << r.body;
    return r.j.value("id", std::uint64_t{0});
}
int plan_rows(std::int64_t id) {
    int n = 0;
    const json results = get(base(id) + "/results").j["results"];  // kept: the reply is a temporary
    for (const auto& r : results) n += r["kind"].get<std::string>().rfind("plan_", 0) == 0;
    return n;
}

TEST(PlanStore, AFailureMidStoreLeavesNoPlanRowsAndTheStateAsItWas) {
    port();
    const std::int64_t id = new_case("plan atomic");
    upload(id, "t1.nii.gz", "T1", data().t1_bytes);
    upload(id, "mask.nii.gz", "mask", data().mask_bytes);
    ASSERT_EQ(get(base(id)).j["state"], "new");
    std::size_t rows_seen = 0;
    set_plan_store_hook_for_tests([&](std::size_t i) {
        rows_seen = i + 1;
        if (i == 1) throw std::runtime_error("injected failure after the second plan row");
    });
    const json failed = wait_job(submit_plan(id));
    set_plan_store_hook_for_tests({});
    EXPECT_EQ(failed.value("state", std::string()), "failed") << failed.dump();
    EXPECT_NE(failed.dump().find("injected failure"), std::string::npos) << failed.dump();
    EXPECT_EQ(rows_seen, 2u) << "the failure came after rows were inserted";
    EXPECT_EQ(plan_rows(id), 0) << "no partial revision";
    EXPECT_EQ(get(base(id)).j["state"], "new");
    // Without the failure: the whole revision and the planned state.
    const json ok = wait_job(submit_plan(id));
    ASSERT_EQ(ok.value("state", std::string()), "succeeded") << ok.dump();
    EXPECT_EQ(ok["result"]["plan_revision"], 1);
    EXPECT_EQ(plan_rows(id), int(ok["result"]["results"].size())) << get(base(id) + "/results").body;
    EXPECT_GE(plan_rows(id), 3);
    EXPECT_EQ(get(base(id)).j["state"], "planned");
    bool audited = false;
    const json audit = get(base(id) + "/audit").j.value("audit", json::array());
    for (const auto& e : audit)
        audited |= e.value("action", std::string()) == "case.state" && e["details"].value("to", std::string()) == "planned";
    EXPECT_TRUE(audited) << "the state change is in the audit trail";
}

TEST(PlanStore, APlanDoesNotMoveALaterStateBack) {
    port();
    const std::int64_t id = new_case("plan later state");
    upload(id, "t1.nii.gz", "T1", data().t1_bytes);
    upload(id, "mask.nii.gz", "mask", data().mask_bytes);
    for (const char* s : {"planned", "patient_registered"}) ASSERT_EQ(post(base(id) + "/state", {{"state", s}}).status, 200) << s;
    const json ok = wait_job(submit_plan(id));
    ASSERT_EQ(ok.value("state", std::string()), "succeeded") << ok.dump();
    EXPECT_EQ(get(base(id)).j["state"], "patient_registered");
}

// ---------------------------------------------------------------------------------------------
// Multimodal: the case's T1 with its plan's CT (GL fusion renderer)

TEST(CaseMultimodal, SettingsChangeWithoutUploadingAVolumeAgain) {
    wait_for_volume();
    const std::int64_t id = new_case("multimodal");
    upload(id, "t1.nii.gz", "T1", data().t1_bytes);
    upload(id, "mask.nii.gz", "mask", data().mask_bytes);
    upload(id, "ct.nii.gz", "CT", data().ct_bytes);
    const json planned = wait_job(submit_plan(id));
    ASSERT_EQ(planned.value("state", std::string()), "succeeded") << planned.dump();
    // The plan's CT histogram (for its tab in the UI): in its own units; fMRI: none planned.
    const Reply ch = get(base(id) + "/plan/ct/histogram?bins=32");
    ASSERT_EQ(ch.status, 200) << ch.body;
    EXPECT_EQ(ch.j["modality"], "CT");
    EXPECT_EQ(ch.j["bins"], 32);
    EXPECT_GT(ch.j["normalizations"]["whole"]["range"][1].get<double>(), 200.0) << "the CT's intensities (2 T1 + 100)";
    EXPECT_EQ(get(base(id) + "/plan/fmri/histogram").status, 409);
    EXPECT_EQ(get(base(id) + "/plan/pet/histogram").status, 400);
    json b = {{"width", 96}, {"height", 72}, {"view", "anterior"}, {"format", "png"}, {"case_id", id}};
    b["modalities"] = json::array({{{"name", "t1"}, {"transfer_function", "cortex_t1"}, {"weight", 1.0}},
                                   {{"name", "ct"}, {"transfer_function", "ct_bone"}, {"weight", 0.6}, {"visible", true}}});
    const Reply first = post("/api/render", b);
    if (first.status == 409 && first.body.find("GL renderer") != std::string::npos) GTEST_SKIP() << "no GL here: " << first.body;
    ASSERT_EQ(first.status, 200) << first.body;
    EXPECT_EQ(first.headers.find("X-Renderer")->second, "gl");
    const auto uploads0 = get("/api/status").j["modules"]["renderer"]["fusion_volume_uploads"].get<std::uint64_t>();
    EXPECT_GE(uploads0, 2u);
    // Visibility, weight and transfer function changes: new pictures, no upload.
    json hide = b;
    hide["modalities"][1]["visible"] = false;
    const Reply no_ct = post("/api/render", hide);
    ASSERT_EQ(no_ct.status, 200) << no_ct.body;
    json light = b;
    light["modalities"][1]["weight"] = 0.1;
    const Reply light_ct = post("/api/render", light);
    ASSERT_EQ(light_ct.status, 200);
    json tf = hide;
    tf["modalities"][0]["transfer_function"] = {{"colour", {{0, 1, 0, 0}, {1, 1, 0, 0}}}, {"opacity", {{0, 0}, {0.3, 0}, {0.4, 1}, {1, 1}}}};
    const Reply red = post("/api/render", tf);
    ASSERT_EQ(red.status, 200) << red.body;
    EXPECT_EQ(get("/api/status").j["modules"]["renderer"]["fusion_volume_uploads"].get<std::uint64_t>(), uploads0);
    const cv::Mat a = decode(first);
    EXPECT_GT(mean_abs_diff(a, decode(no_ct)), 1.0) << "the CT layer shows";
    EXPECT_GT(mean_abs_diff(a, decode(light_ct)), 0.2) << "its weight matters";
    EXPECT_GT(mean_abs_diff(decode(no_ct), decode(red)), 1.0) << "the T1's transfer function matters";
    // The T1 alone through the fusion scene (the CT hidden) equals the plain per-case render.
    json plain = {{"width", 96}, {"height", 72}, {"view", "anterior"}, {"format", "png"}, {"case_id", id}};
    const Reply single = post("/api/render", plain);
    ASSERT_EQ(single.status, 200);
    EXPECT_LT(mean_abs_diff(decode(single), decode(no_ct)), 1.0);
}

}  // namespace

namespace {

// A daemon with the CPU ray caster: a multimodal request is refused naming the reason, and the
// T1 alone still renders.
TEST(CaseMultimodal, TheCpuRendererRefusesLayersNamingWhy) {
    port();  // the shared test data
    const fs::path state = fs::temp_directory_path() / ("cf_daemon_case_render_cpu_" + std::to_string(::getpid()));
    json c = test_config(state);
    c["renderer"]["kind"] = "cpu";
    c["data"]["t1"] = data().t1_path.string();
    auto d = std::make_unique<TestDaemon>(state, c, 180);
    auto req = [&](const std::string& method, const std::string& path, const std::string& body, const std::string& mime) {
        return d->request(method, path, body, mime);
    };
    const std::int64_t id = req("POST", "/api/cases", json{{"title", "cpu"}}.dump(), "application/json").j.value("id", std::int64_t{0});
    for (const auto& [name, mod, bytes] : {std::tuple{"t1.nii.gz", "T1", &data().t1_bytes}, std::tuple{"mask.nii.gz", "mask", &data().mask_bytes},
                                           std::tuple{"ct.nii.gz", "CT", &data().ct_bytes}})
        ASSERT_EQ(req("POST", base(id) + "/volumes?name=" + name + "&modality=" + mod, *bytes, "application/octet-stream").status, 201);
    const Reply job = req("POST", "/api/jobs", json{{"kind", "plan"}, {"params", {{"case_id", id}, {"max_triangles", 5000}}}}.dump(), "application/json");
    ASSERT_EQ(job.status, 202) << job.body;
    std::string state_s;
    for (int i = 0; i < 2400 && state_s != "succeeded" && state_s != "failed"; ++i) {
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
        state_s = req("GET", "/api/jobs/" + std::to_string(job.j["id"].get<int>()), "", "").j.value("state", std::string());
    }
    ASSERT_EQ(state_s, "succeeded");
    json b = {{"width", 48}, {"height", 36}, {"view", "left"}, {"case_id", id}};
    b["modalities"] = json::array({{{"name", "t1"}}, {{"name", "ct"}}});
    const Reply r = req("POST", "/api/render", b.dump(), "application/json");
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("need the GL renderer"), std::string::npos) << r.body;
    b.erase("modalities");
    EXPECT_EQ(req("POST", "/api/render", b.dump(), "application/json").status, 200);
    d.reset();  // stopped, the stop expected to succeed
    fs::remove_all(state);
}

}  // namespace
