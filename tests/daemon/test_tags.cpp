// Stimulation tags through the daemon's API (docs/api/tags.md): marks on the registered photo
// cast back onto the plan's brain surface. The daemon runs in-process on a free port with the
// CPU renderer; the case is a phantom on a 2 mm copy of the bundled MRI, its registration the
// phantom's true pose, so a tag on a target's pixel must land on the target.
// Eigen first: <httplib.h> pulls in <resolv.h>, whose _res macro breaks Eigen's headers.
#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/overlay.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/surface.hpp"
#include "cortexfuse/core/volume.hpp"
#include "cortexfuse/daemon/daemon.hpp"
#include "cortexfuse/db/case_store.hpp"

#include "daemon_fixture.hpp"

#include <gtest/gtest.h>
#include <httplib.h>
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <thread>

using namespace cf;
using namespace cf::daemon;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

using namespace cf::daemon_test;

SharedDaemon& g_d = add_shared_daemon("cf_daemon_tags", [](const fs::path& state) {
    json c = base_test_config(state, "cpu");
    c["store"]["max_upload_bytes"] = 8 << 20;
    c["tracker"]["enabled"] = false;
    c["camera"]["backend"] = "none";
    return c;
});
const fs::path& g_state = g_d.state();

int port() { return g_d.port(); }
Reply request(const std::string& method, const std::string& path, const std::string& body = "", const std::string& token = "",
              const std::string& mime = "application/json") {
    return g_d.get().request(method, path, body, mime, token);
}
Reply get(const std::string& path, const std::string& token = "") { return g_d.get().get(path, token); }
Reply post(const std::string& path, const json& body, const std::string& token = "") { return g_d.get().post(path, body, token); }
Reply post_raw(const std::string& path, const std::string& bytes) { return g_d.get().post_raw(path, bytes); }
json wait_job(std::uint64_t id) {
    return poll_job([](const std::string& p) { return get(p); }, id);
}

struct PhantomWorld {
    PhantomCase pc;
    std::string t1_bytes, mask_bytes, photo_png;
};
const PhantomWorld& world() {
    static const PhantomWorld w = [] {
        PhantomWorld r;
        const Head2mm h = head_2mm(g_state / "phantom_src");
        r.t1_bytes = h.t1_bytes;
        r.mask_bytes = h.mask_bytes;
        r.pc = generate_phantom_case(build_phantom_surface(h.t1, h.mask), plain_phantom_params(), 0);
        r.photo_png = png_bytes(r.pc.photo_bgr);
        return r;
    }();
    return w;
}

/// A case with the phantom's T1, mask and photo (no plan, no registration yet).
std::int64_t phantom_case(const std::string& title) {
    port();
    const PhantomWorld& w = world();
    const Reply c = post("/api/cases", {{"title", title}});
    EXPECT_EQ(c.status, 201) << c.body;
    const std::int64_t id = c.j.value("id", std::int64_t{0});
    const std::string base = "/api/cases/" + std::to_string(id);
    EXPECT_EQ(post_raw(base + "/volumes?name=t1.nii.gz&modality=T1", w.t1_bytes).status, 201);
    EXPECT_EQ(post_raw(base + "/volumes?name=mask.nii.gz&modality=mask", w.mask_bytes).status, 201);
    const Reply ph = post_raw(base + "/photos?name=photo.png&camera=" + url_encode(camera_json(w.pc.camera).dump()), w.photo_png);
    EXPECT_EQ(ph.status, 201) << ph.body;
    return id;
}

void plan_and_register_with_truth(std::int64_t id) {
    const Reply j = post("/api/jobs", {{"kind", "plan"}, {"params", {{"case_id", id}, {"max_triangles", 60000}}}});
    ASSERT_EQ(j.status, 202) << j.body;
    const json done = wait_job(j.j.value("id", std::uint64_t{0}));
    ASSERT_EQ(done.value("state", std::string()), "succeeded") << done.dump();
    // The registration: the phantom's true pose, stored as a run of the case (what a register
    // job stores), through a second connection to the store.
    store_registration(g_state / "store", id, world().pc.T_camera_from_world);
}

std::string token_of(const std::string& name, const std::string& role) { return g_d.get().token_of(name, role); }

/// What the store holds about a case, minus reads (views and downloads are audited too).
json snapshot(std::int64_t id) {
    json rec = get("/api/cases/" + std::to_string(id)).j;
    rec.erase("updated_utc");
    json audit = json::array();
    const json trail = get("/api/cases/" + std::to_string(id) + "/audit").j["audit"];
    for (const auto& e : trail) {
        const std::string a = e["action"];
        if (a == "case.view" || a.find(".download") != std::string::npos) continue;
        audit.push_back(e);
    }
    return {{"case", rec}, {"audit", audit}, {"tags", get("/api/cases/" + std::to_string(id) + "/tags?revisions=all").j}};
}

Eigen::Vector3d vec3(const json& a) { return {a[0].get<double>(), a[1].get<double>(), a[2].get<double>()}; }

json tag(const std::string& label, const Eigen::Vector2d& px, const std::string& colour = "#ff4040", const std::string& note = "") {
    return {{"label", label}, {"colour", colour}, {"note", note}, {"pixel", {px.x(), px.y()}}};
}

}  // namespace

TEST(Tags, ATagOnATargetsPixelLandsOnTheTargetWithTheTruePose) {
    const std::int64_t id = phantom_case("tags");
    const std::string base = "/api/cases/" + std::to_string(id);
    const PhantomWorld& w = world();
    ASSERT_GE(w.pc.targets_world_mm.size(), 3u);
    // Before a registration: 409 saying what is missing, nothing stored.
    Reply r = post(base + "/tags", {{"tags", json::array({tag("S1", {160, 120})})}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("registration"), std::string::npos) << r.body;
    r = get(base + "/tags");
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.j["revision"], 0);
    EXPECT_TRUE(r.j["tags"].empty());
    plan_and_register_with_truth(id);

    // Every target of the phantom (points of its brain surface seen in the photo), tagged at
    // the pixel the true camera sees it.
    json tags = json::array();
    std::vector<Eigen::Vector3d> truth;
    for (std::size_t i = 0; i < w.pc.targets_world_mm.size(); ++i) {
        const auto px = project(w.pc.camera, w.pc.T_camera_from_world, w.pc.targets_world_mm[i]);
        ASSERT_TRUE(px);
        tags.push_back(tag("T" + std::to_string(i + 1), *px, i % 2 ? "#30c0ff" : "#ff4040", "target " + std::to_string(i + 1)));
        truth.push_back(w.pc.targets_world_mm[i]);
    }
    r = post(base + "/tags", {{"tags", tags}});
    ASSERT_EQ(r.status, 201) << r.body;
    EXPECT_EQ(r.j["revision"], 1);
    ASSERT_EQ(r.j["tags"].size(), truth.size());
    double worst_mm = 0, sum_mm = 0;
    for (std::size_t i = 0; i < truth.size(); ++i) {
        const json& t = r.j["tags"][i];
        EXPECT_EQ(t["label"], tags[i]["label"]);
        EXPECT_EQ(t["colour"], tags[i]["colour"]);
        EXPECT_EQ(t["note"], tags[i]["note"]);
        const double e = (vec3(t["world_mm"]) - truth[i]).norm();
        worst_mm = std::max(worst_mm, e);
        sum_mm += e;
        EXPECT_LT(e, 1.0) << "tag " << i << " lands " << e << " mm from its target";
        EXPECT_GT(t["depth_mm"].get<double>(), 0.0);
    }
    std::printf("tags on %zu phantom targets with the true pose: mean %.4f mm, worst %.4f mm from the target\n", truth.size(),
                sum_mm / double(truth.size()), worst_mm);

    // The cast uses the stored pose: with a registration 2 mm off along the camera's x, the same
    // pixels land about 2 mm away from the targets (and the newest registration is the one used).
    {
        auto store = cf::db::CaseStore::open(g_state / "store");
        Pose T = w.pc.T_camera_from_world;
        T(0, 3) += 2.0;
        cf::db::RegistrationInput in;
        in.final_pose = json{{"T_camera_from_world", pose_to_json(T)}};
        const std::int64_t off_id = store->add_registration(id, in, cf::db::Actor{"test", std::nullopt}).id;
        const Reply off = post(base + "/tags", {{"tags", tags}});
        ASSERT_EQ(off.status, 201) << off.body;
        EXPECT_EQ(off.j["registration_id"], off_id);
        double mean_mm = 0;
        for (std::size_t i = 0; i < truth.size(); ++i) mean_mm += (vec3(off.j["tags"][i]["world_mm"]) - truth[i]).norm() / double(truth.size());
        std::printf("with the pose 2 mm off: mean %.3f mm from the targets\n", mean_mm);
        EXPECT_GT(mean_mm, 1.0);
        // Back to the true pose by naming its registration.
        r = post(base + "/tags", {{"tags", tags}, {"registration_id", off_id - 1}});
        ASSERT_EQ(r.status, 201) << r.body;
        for (std::size_t i = 0; i < truth.size(); ++i) EXPECT_LT((vec3(r.j["tags"][i]["world_mm"]) - truth[i]).norm(), 1.0);
    }
    EXPECT_EQ(r.j["revision"], 3);

    // Read back (latest), a second revision (one tag moved), the first kept.
    r = get(base + "/tags");
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.j["revision"], 3);
    EXPECT_EQ(r.j["tags"].size(), truth.size());
    EXPECT_GT(r.j["registration_id"].get<std::int64_t>(), 0);
    json moved = json::array({tags[0]});
    r = post(base + "/tags", {{"tags", moved}});
    ASSERT_EQ(r.status, 201) << r.body;
    EXPECT_EQ(r.j["revision"], 4);
    r = get(base + "/tags?revisions=all");
    ASSERT_EQ(r.status, 200);
    ASSERT_EQ(r.j["revisions"].size(), 4u);
    EXPECT_EQ(r.j["revisions"][0]["tags"].size(), truth.size());
    EXPECT_EQ(r.j["revisions"][3]["tags"].size(), 1u);
    // Audited as result additions by the kiosk; listed among the case's results.
    int added = 0;
    const json audit = get(base + "/audit").j["audit"];  // a value: a range-for over a temporary's member would dangle
    for (const auto& e : audit)
        if (e["action"] == "result.add" && e.dump().find("\"tags\"") != std::string::npos) ++added;
    EXPECT_EQ(added, 4);
    int listed = 0;
    const json results = get(base + "/results").j["results"];
    for (const auto& x : results) listed += x["kind"] == "tags";
    EXPECT_EQ(listed, 4);
}

TEST(Tags, BadInputStoresNothing) {
    const std::int64_t id = phantom_case("tags bad");
    const std::string base = "/api/cases/" + std::to_string(id);
    plan_and_register_with_truth(id);
    const PhantomWorld& w = world();
    const Eigen::Vector2d good = *project(w.pc.camera, w.pc.T_camera_from_world, w.pc.targets_world_mm[0]);
    ASSERT_EQ(post(base + "/tags", {{"tags", json::array({tag("S1", good)})}}).status, 201);
    const json before = snapshot(id);
    const std::string reviewer = token_of("rita", "reviewer");

    // A photo pixel whose ray misses the surface: found with the stored plan surface itself.
    std::optional<Eigen::Vector2d> miss;
    {
        std::string sha;
        const json results = get(base + "/results").j["results"];
        for (const auto& x : results)
            if (x["kind"] == "plan_brain_surface") sha = x["sha256"];
        ASSERT_FALSE(sha.empty());
        auto store = cf::db::CaseStore::open(g_state / "store");
        const fs::path ply = g_state / "tags_test_surface.ply";
        store->copy_blob_to(sha, ply);
        const SurfaceMesh mesh = load_mesh(ply);
        fs::remove(ply);
        for (int v = 0; v < w.pc.camera.height && !miss; v += 8)
            for (int u = 0; u < w.pc.camera.width && !miss; u += 8)
                if (!cast_back(mesh, w.pc.camera, w.pc.T_camera_from_world, {double(u), double(v)})) miss = Eigen::Vector2d(u, v);
    }

    struct Bad {
        std::string what, body;
        int status = 0;
        std::string says = {};
        std::string token = {};
    };
    const auto one = [&](const json& t) { return json{{"tags", json::array({tag("S1", good), t})}}.dump(); };
    std::vector<Bad> bad = {
        {"pixel right of the photo", one(tag("S2", {double(w.pc.camera.width), 10})), 400, "outside the photo"},
        {"pixel above the photo", one(tag("S2", {10, -1})), 400, "outside the photo"},
        {"malformed JSON", "{\"tags\": [", 400, ""},
        {"a JSON array", "[]", 400, "JSON object"},
        {"no tags", "{}", 400, "tags"},
        {"tags not an array", R"({"tags": 3})", 400, "tags"},
        {"pixel of one number", one(json{{"label", "S2"}, {"colour", "#ffffff"}, {"pixel", {3}}}), 400, "pixel"},
        {"pixel as text", one(json{{"label", "S2"}, {"colour", "#ffffff"}, {"pixel", {"a", 3}}}), 400, "pixel"},
        {"bad colour", one(tag("S2", good, "red")), 400, "colour"},
        {"duplicate label", one(tag("S1", good)), 400, "used twice"},
        {"empty label", one(tag("", good)), 400, "label"},
        {"control character in label", one(tag("S\x01", good)), 400, "label"},
        {"note too long", one(tag("S2", good, "#ffffff", std::string(600, 'x'))), 400, "note"},
        {"unknown field in a tag", one(json{{"label", "S2"}, {"colour", "#ffffff"}, {"pixel", {3, 3}}, {"size", 3}}), 400, "unknown field"},
        {"unknown field", json{{"tags", json::array()}, {"x", 1}}.dump(), 400, "unknown field"},
        {"registration_id not a number", json{{"tags", json::array()}, {"registration_id", "a"}}.dump(), 400, "registration_id"},
        {"unknown registration", json{{"tags", json::array()}, {"registration_id", 99999}}.dump(), 404, "registration"},
        {"reviewer", one(tag("S2", good)), 403, "", reviewer},
    };
    if (miss) bad.push_back({"a pixel beside the brain", one(tag("S2", *miss)), 422, "misses the brain surface"});
    else ADD_FAILURE() << "no photo pixel misses the brain surface on an 8 px grid";
    for (const Bad& b : bad) {
        const Reply r = request("POST", base + "/tags", b.body, b.token);
        EXPECT_EQ(r.status, b.status) << b.what << ": " << r.body;
        if (!b.says.empty()) {
            EXPECT_NE(r.body.find(b.says), std::string::npos) << b.what << ": " << r.body;
        }
        EXPECT_EQ(snapshot(id), before) << b.what << " changed what is stored";
    }
    EXPECT_EQ(post("/api/cases/99999/tags", {{"tags", json::array()}}).status, 404);
    EXPECT_EQ(post("/api/cases/abc/tags", {{"tags", json::array()}}).status, 400);
    EXPECT_EQ(get(base + "/tags?revisions=some").status, 400);
    // The reviewer reads them.
    const Reply r = get(base + "/tags", reviewer);
    EXPECT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.j["tags"].size(), 1u);
    // No scratch left behind.
    std::size_t scratch = 0;
    for (const auto& e : fs::directory_iterator(g_state / "work")) scratch += e.path().filename().string().rfind("tags_", 0) == 0;
    EXPECT_EQ(scratch, 0u);
}
