// Patient navigation through the daemon (docs/api/navigation.md), against the NDI simulator
// reached through the real driver over a pty: the simulator's pointer is placed on fiducials
// (POST /api/tracker/sim/pointer), recorded, registered by core's Umeyama, and the recovered
// T_image_from_reference is compared with the simulator's truth; an outlier is excluded; the
// accepted registration lands in the case store. Every bad input is refused with its status and
// a message naming it, and nothing stored changes.
// Eigen first: <httplib.h> pulls in <resolv.h>, whose _res macro breaks Eigen's headers.
#include <Eigen/Geometry>

#include "cortexfuse/core/volume.hpp"
#include "cortexfuse/daemon/config.hpp"
#include "cortexfuse/daemon/daemon.hpp"

#include "daemon_fixture.hpp"

#include <gtest/gtest.h>
#include <httplib.h>
#include <unistd.h>

#include <atomic>
#include <cmath>
#include <cstdio>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <opencv2/imgcodecs.hpp>
#include <thread>

using namespace cf::daemon;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

using namespace cf::daemon_test;

SharedDaemon& g_d = add_shared_daemon(
    "cf_daemon_nav",
    [](const fs::path& state) {
        json c = base_test_config(state, "cpu");
        c["tracker"]["sim_link"] = "tcp";  // holds its rate on the loaded test machine (docs/daemon.md)
        return c;
    },
    60);
const fs::path& g_state = g_d.state();

Reply request(const std::string& method, const std::string& path, const std::string& body = "", const std::string& token = "") {
    return g_d.get().request(method, path, body, "application/json", token);
}
Reply get(const std::string& path, const std::string& token = "") { return g_d.get().get(path, token); }
Reply post(const std::string& path, const json& body, const std::string& token = "") { return g_d.get().post(path, body, token); }
Reply del(const std::string& path, const std::string& token = "") { return g_d.get().del(path, token); }

std::int64_t new_case(const std::string& title) { return g_d.get().new_case(title); }

std::string token_of(const std::string& name, const std::string& role) { return g_d.get().token_of(name, role); }

Eigen::Vector3d v3(const json& a) { return {a[0].get<double>(), a[1].get<double>(), a[2].get<double>()}; }
Eigen::Matrix4d m4(const json& a) {
    Eigen::Matrix4d T;
    for (int r = 0; r < 4; ++r)
        for (int c = 0; c < 4; ++c) T(r, c) = a[r][c].get<double>();
    return T;
}

/// The newest frame number the daemon has (0 before the first).
std::uint32_t frame_now() {
    const Reply r = get("/api/navigation/pointer");
    return r.j.contains("frame") && r.j["frame"].is_object() ? r.j["frame"]["frame"].get<std::uint32_t>() : 0;
}

/// Waits until the tracker streams both tools (up to 20 s).
void wait_streaming() {
    const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(20);
    while (std::chrono::steady_clock::now() < until) {
        const Reply r = get("/api/navigation/pointer");
        if (r.status == 200 && r.j["p_reference_mm"].is_array()) return;
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    FAIL() << "the tracker did not stream both tools within 20 s";
}

/// Places the simulated pointer and waits until a whole recording window (0.3 s) of frames
/// shows it there.
json sim_pointer(const json& body) {
    const Reply r = post("/api/tracker/sim/pointer", body);
    EXPECT_EQ(r.status, 200) << r.body;
    const std::uint32_t from = r.j.value("from_frame", 0u);
    const auto until = std::chrono::steady_clock::now() + std::chrono::seconds(10);
    // 60 Hz: 0.3 s is 18 frames; a few more for the frames in flight.
    while (frame_now() < from + 24 && std::chrono::steady_clock::now() < until) std::this_thread::sleep_for(std::chrono::milliseconds(40));
    return r.j;
}

/// What a case holds for navigation, and its results and non-view audit entries.
json snapshot(std::int64_t id) {
    const std::string c = "/api/cases/" + std::to_string(id);
    json audit = json::array();
    const json trail = get(c + "/audit").j["audit"];  // a value: a range-for over a temporary's member would dangle
    for (const auto& e : trail)
        if (e["action"] != "case.view") audit.push_back(e);
    json rec = get(c).j;
    return {{"nav", get(c + "/navigation").j}, {"results", rec["results"]}, {"state", rec["state"]}, {"audit", audit}};
}

const json kImageFiducials = {{{"label", "nasion"}, {"p_image_mm", {2, -95, 10}}},   {{"label", "left ear"}, {"p_image_mm", {75, -5, -5}}},
                              {{"label", "right ear"}, {"p_image_mm", {-74, -3, -6}}}, {{"label", "vertex"}, {"p_image_mm", {3, 10, 92}}},
                              {{"label", "forehead L"}, {"p_image_mm", {45, -80, 45}}}, {{"label", "occiput"}, {"p_image_mm", {-5, 95, 20}}}};

TEST(Navigation, FiducialsTouchedWithTheSimulatedPointerGiveTheTruePatientRegistration) {
    const auto id = new_case("navigation truth");
    const std::string c = "/api/cases/" + std::to_string(id);
    ASSERT_EQ(post(c + "/state", {{"state", "planned"}}).status, 200);
    Reply r = post(c + "/navigation/image-fiducials", {{"fiducials", kImageFiducials}});
    ASSERT_EQ(r.status, 201) << r.body;
    const std::int64_t image_rev = r.j["revision"];
    wait_streaming();

    Eigen::Matrix4d T_truth = Eigen::Matrix4d::Identity();
    for (const auto& f : kImageFiducials) {
        const json s = sim_pointer({{"touch_image_mm", f["p_image_mm"]}});
        T_truth = m4(s["T_image_from_reference_truth"]);
        r = post(c + "/navigation/record", {{"label", f["label"]}});
        ASSERT_EQ(r.status, 201) << f["label"] << ": " << r.body;
        const Eigen::Vector3d p_ref = v3(r.j["recorded"]["p_reference_mm"]);
        // The simulator's noise: 0.05 mm per axis and 0.05 degrees on each tool, averaged.
        EXPECT_LT((p_ref - v3(s["p_reference_mm"])).norm(), 0.25) << f["label"];
        EXPECT_LT(r.j["recorded"]["spread_mm"].get<double>(), 0.3);
        EXPECT_GE(r.j["recorded"]["frames"].get<int>(), 4);  // 0.3 s: 18 frames at 60 Hz, fewer under a sanitizer
    }
    EXPECT_FALSE(T_truth.isIdentity());
    r = get(c + "/navigation");
    ASSERT_EQ(r.j["patient_fiducials"]["fiducials"].size(), kImageFiducials.size());

    r = post(c + "/navigation/register", json::object());
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_LT(r.j["fre_mm"].get<double>(), 0.25) << r.body;
    EXPECT_EQ(r.j["excluded"].size(), 0u);
    EXPECT_EQ(r.j["n_used"], 6);
    const Eigen::Matrix4d T = m4(r.j["T_image_from_reference"]);
    const double angle_deg = Eigen::AngleAxisd(Eigen::Matrix3d(T.topLeftCorner<3, 3>().transpose() * T_truth.topLeftCorner<3, 3>())).angle() * 180 / M_PI;
    EXPECT_LT(angle_deg, 0.3);
    std::printf("registration: FRE %.3f mm over 6, rotation error %.3f deg, predicted TRE %.3f mm\n", r.j["fre_mm"].get<double>(), angle_deg,
                r.j["predicted_tre_mm"].get<double>());
    for (const auto& f : kImageFiducials) {  // every fiducial mapped within the noise
        const Eigen::Vector4d p_ref = T_truth.inverse() * v3(f["p_image_mm"]).homogeneous();
        EXPECT_LT(((T * p_ref).head<3>() - v3(f["p_image_mm"])).norm(), 0.3);
    }
    EXPECT_GT(r.j["predicted_tre_mm"].get<double>(), 0.0);
    EXPECT_LT(r.j["predicted_tre_mm"].get<double>(), 0.3);

    // An 8 mm slip on one fiducial: excluded as an outlier, the rest still fits within noise.
    const json off = {kImageFiducials[3]["p_image_mm"][0].get<double>() + 8.0, kImageFiducials[3]["p_image_mm"][1], kImageFiducials[3]["p_image_mm"][2]};
    sim_pointer({{"touch_image_mm", off}});
    ASSERT_EQ(post(c + "/navigation/record", {{"label", "vertex"}}).status, 201);
    r = post(c + "/navigation/register", {{"outlier_mm", 3}});
    ASSERT_EQ(r.status, 200) << r.body;
    ASSERT_EQ(r.j["excluded"], json::array({"vertex"})) << r.body;
    EXPECT_LT(r.j["fre_mm"].get<double>(), 0.25);
    for (const auto& row : r.j["fiducials"])
        if (row["label"] == "vertex") {
            EXPECT_FALSE(row["used"].get<bool>());
            EXPECT_NEAR(row["residual_mm"].get<double>(), 8.0, 0.5);
        }
    // Without exclusion the slip shows in the FRE.
    EXPECT_GT(post(c + "/navigation/register", {{"outlier_mm", 0}}).j["fre_mm"].get<double>(), 2.0);

    // Accept: stored with its parameters, audited, the case moves to patient_registered.
    const json computed = r.j;
    r = post(c + "/navigation/accept", {{"image_fiducials_revision", computed["image_fiducials_revision"]},
                                        {"patient_fiducials_revision", computed["patient_fiducials_revision"]}, {"outlier_mm", 3}});
    ASSERT_EQ(r.status, 201) << r.body;
    EXPECT_EQ(r.j["state"], "patient_registered");
    EXPECT_EQ(r.j["T_image_from_reference"], computed["T_image_from_reference"]);
    EXPECT_EQ(computed["image_fiducials_revision"], image_rev);
    r = get(c + "/navigation");
    ASSERT_TRUE(r.j["accepted"].is_object()) << r.body;
    EXPECT_EQ(r.j["accepted"]["params"]["outlier_mm"], 3.0);
    EXPECT_EQ(r.j["accepted"]["excluded"], json::array({"vertex"}));
    EXPECT_EQ(r.j["accepted_count"], 1);
    bool audited = false;
    const json trail = get(c + "/audit").j["audit"];
    for (const auto& e : trail) audited = audited || e["action"] == "navigation.accept";
    EXPECT_TRUE(audited);

    // Redo: delete one fiducial, then the old revisions can no longer be accepted.
    ASSERT_EQ(del(c + "/navigation/patient-fiducials/vertex").status, 200);
    r = post(c + "/navigation/accept", {{"image_fiducials_revision", computed["image_fiducials_revision"]},
                                        {"patient_fiducials_revision", computed["patient_fiducials_revision"]}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("changed"), std::string::npos) << r.body;
    ASSERT_EQ(del(c + "/navigation/patient-fiducials").status, 200);
    EXPECT_EQ(get(c + "/navigation").j["patient_fiducials"]["fiducials"].size(), 0u);
    EXPECT_EQ(get(c + "/navigation").j["accepted_count"], 1);  // the accepted one is kept

    // Two recordings at once (two screens): both land, neither list overwrites the other.
    Reply r1, r2;
    std::thread t1([&] { r1 = post(c + "/navigation/record", {{"label", "nasion"}}); });
    std::thread t2([&] { r2 = post(c + "/navigation/record", {{"label", "left ear"}}); });
    t1.join();
    t2.join();
    EXPECT_EQ(r1.status, 201) << r1.body;
    EXPECT_EQ(r2.status, 201) << r2.body;
    EXPECT_EQ(get(c + "/navigation").j["patient_fiducials"]["fiducials"].size(), 2u);
}

TEST(Navigation, BadInputIsRefusedAndNothingStoredChanges) {
    const auto id = new_case("navigation bad input");
    const std::string c = "/api/cases/" + std::to_string(id);
    // No case.
    EXPECT_EQ(get("/api/cases/99999/navigation").status, 404);
    EXPECT_EQ(post("/api/cases/99999/navigation/record", {{"label", "a"}}).status, 404);
    EXPECT_EQ(post("/api/cases/abc/navigation/register", json::object()).status, 400);
    // No image fiducials yet.
    Reply r = post(c + "/navigation/record", {{"label", "nasion"}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_EQ(post(c + "/navigation/register", json::object()).status, 409);
    // Bad image fiducials.
    const json two = {kImageFiducials[0], kImageFiducials[1]};
    json dup = kImageFiducials;
    dup[2]["label"] = "nasion";
    json text = kImageFiducials;
    text[1]["p_image_mm"] = {"1", 2, 3};
    json extra = kImageFiducials;
    extra[0]["colour"] = "red";
    const json empty_snapshot = snapshot(id);
    for (const auto& [body, needle] : std::vector<std::pair<json, std::string>>{{{{"fiducials", two}}, "3.."},
                                                                                {{{"fiducials", dup}}, "twice"},
                                                                                {{{"fiducials", text}}, "p_image_mm"},
                                                                                {{{"fiducials", extra}}, "colour"},
                                                                                {{{"points", kImageFiducials}}, "points"},
                                                                                {json::array(), "object"}}) {
        r = post(c + "/navigation/image-fiducials", body);
        EXPECT_EQ(r.status, 400) << body;
        EXPECT_NE(r.body.find(needle), std::string::npos) << r.body;
    }
    r = request("POST", c + "/navigation/image-fiducials", "{\"fiducials\": [");
    EXPECT_EQ(r.status, 400) << r.body;
    EXPECT_EQ(snapshot(id), empty_snapshot);

    // Collinear image fiducials are stored (3 points), but cannot be registered.
    const json line = {{{"label", "a"}, {"p_image_mm", {0, 0, 0}}}, {{"label", "b"}, {"p_image_mm", {30, 0, 0}}}, {{"label", "c"}, {"p_image_mm", {60, 0.1, 0}}}};
    ASSERT_EQ(post(c + "/navigation/image-fiducials", {{"fiducials", line}}).status, 201);
    wait_streaming();
    for (const auto& f : line) {
        sim_pointer({{"touch_image_mm", f["p_image_mm"]}});
        ASSERT_EQ(post(c + "/navigation/record", {{"label", f["label"]}}).status, 201);
    }
    r = post(c + "/navigation/register", json::object());
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("collinear"), std::string::npos) << r.body;

    ASSERT_EQ(post(c + "/navigation/image-fiducials", {{"fiducials", kImageFiducials}}).status, 201);
    sim_pointer({{"touch_image_mm", kImageFiducials[0]["p_image_mm"]}});
    ASSERT_EQ(post(c + "/navigation/record", {{"label", "nasion"}}).status, 201);
    const json before = snapshot(id);

    // Fewer than 3 paired fiducials.
    r = post(c + "/navigation/register", json::object());
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("at least 3"), std::string::npos) << r.body;
    // Unknown label, bad options, unknown fields, malformed JSON.
    r = post(c + "/navigation/record", {{"label", "chin"}});
    EXPECT_EQ(r.status, 400) << r.body;
    EXPECT_NE(r.body.find("chin"), std::string::npos);
    EXPECT_EQ(post(c + "/navigation/record", {{"label", "nasion"}, {"window_s", 9}}).status, 400);
    EXPECT_EQ(post(c + "/navigation/record", {{"label", "nasion"}, {"hold", true}}).status, 400);
    EXPECT_EQ(post(c + "/navigation/record", json::object()).status, 400);
    EXPECT_EQ(request("POST", c + "/navigation/record", "{label: nasion}").status, 400);
    EXPECT_EQ(post(c + "/navigation/register", {{"outlier_mm", "big"}}).status, 400);
    EXPECT_EQ(post(c + "/navigation/accept", json::object()).status, 400);
    EXPECT_EQ(del(c + "/navigation/patient-fiducials/chin").status, 404);

    // The pointer moving (the simulator's circling motion).
    sim_pointer({{"free", true}});
    r = post(c + "/navigation/record", {{"label", "left ear"}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("moved"), std::string::npos) << r.body;
    // The pointer, then the reference, out of sight (stale after 0.5 s).
    sim_pointer({{"hidden", true}});
    r = post(c + "/navigation/record", {{"label", "left ear"}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("pointer"), std::string::npos) << r.body;
    std::this_thread::sleep_for(std::chrono::milliseconds(600));
    r = post(c + "/navigation/record", {{"label", "left ear"}});
    EXPECT_NE(r.body.find("stale"), std::string::npos) << r.body;
    sim_pointer({{"touch_image_mm", kImageFiducials[1]["p_image_mm"]}});
    sim_pointer({{"tool", "reference"}, {"hidden", true}});
    r = post(c + "/navigation/record", {{"label", "left ear"}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("reference"), std::string::npos) << r.body;
    r = post(c + "/navigation/record", {{"label", "left ear"}, {"pointer", "probe"}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("probe"), std::string::npos) << r.body;
    // A reviewer reads but changes nothing.
    const std::string reviewer = token_of("nav_reviewer", "reviewer");
    EXPECT_EQ(get(c + "/navigation", reviewer).status, 200);
    EXPECT_EQ(post(c + "/navigation/record", {{"label", "left ear"}}, reviewer).status, 403);
    EXPECT_EQ(post(c + "/navigation/image-fiducials", {{"fiducials", kImageFiducials}}, reviewer).status, 403);
    EXPECT_EQ(post(c + "/navigation/accept", {{"image_fiducials_revision", 1}, {"patient_fiducials_revision", 1}}, reviewer).status, 403);
    EXPECT_EQ(del(c + "/navigation/patient-fiducials", reviewer).status, 403);
    EXPECT_EQ(post("/api/tracker/sim/pointer", {{"free", true}}, reviewer).status, 403);
    // Bad simulator requests.
    EXPECT_EQ(post("/api/tracker/sim/pointer", {{"free", true}, {"hidden", true}}).status, 400);
    EXPECT_EQ(post("/api/tracker/sim/pointer", {{"tool", "camera"}, {"free", true}}).status, 400);
    EXPECT_EQ(post("/api/tracker/sim/pointer", {{"touch_image_mm", {1, 2}}}).status, 400);
    EXPECT_EQ(snapshot(id), before);
    sim_pointer({{"tool", "reference"}, {"free", true}});
}

json rows(const Eigen::Matrix4d& T) {
    json j = json::array();
    for (int r = 0; r < 4; ++r) j.push_back({T(r, 0), T(r, 1), T(r, 2), T(r, 3)});
    return j;
}

TEST(Navigation, PivotCalibrationFindsTheTipAndTheRecordingsUseIt) {
    wait_streaming();
    // The simulated pointer swivelled about a divot with its tip 150 mm down the shaft.
    const Eigen::Vector3d tip_true(3, -2, -150), divot_reference(20, 30, 40);
    std::atomic<bool> done{false};
    Eigen::Matrix4d last = Eigen::Matrix4d::Identity();
    std::thread swivel([&] {
        for (int i = 0; !done; ++i) {
            const double a = 2 * M_PI * i / 12;
            Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
            T.linear() = (Eigen::AngleAxisd(0.4 * std::cos(a), Eigen::Vector3d::UnitX()) * Eigen::AngleAxisd(0.4 * std::sin(a), Eigen::Vector3d::UnitY()))
                             .toRotationMatrix();
            T.translation() = divot_reference - T.linear() * tip_true;
            last = T.matrix();
            post("/api/tracker/sim/pointer", {{"T_reference_from_pointer", rows(T.matrix())}});
            std::this_thread::sleep_for(std::chrono::milliseconds(150));
        }
    });
    std::this_thread::sleep_for(std::chrono::milliseconds(300));  // the swivel under way before the calibration starts
    Reply r = post("/api/navigation/pivot", {{"seconds", 2.5}, {"apply", true}});
    done = true;
    swivel.join();
    ASSERT_EQ(r.status, 200) << r.body;
    std::printf("pivot: tip (%.2f, %.2f, %.2f) mm (true 3, -2, -150), rms %.3f mm, spread %.1f deg, %d poses\n", r.j["tip_pointer_mm"][0].get<double>(),
                r.j["tip_pointer_mm"][1].get<double>(), r.j["tip_pointer_mm"][2].get<double>(), r.j["rms_mm"].get<double>(),
                r.j["rotation_spread_deg"].get<double>(), r.j["poses"].get<int>());
    EXPECT_TRUE(r.j["applied"].get<bool>());
    EXPECT_LT((v3(r.j["tip_pointer_mm"]) - tip_true).norm(), 0.5) << r.body;
    EXPECT_LT(r.j["rms_mm"].get<double>(), 0.5);
    EXPECT_GT(r.j["rotation_spread_deg"].get<double>(), 10.0);
    EXPECT_GT(r.j["poses"].get<int>(), 40);
    // The tip in use is the calibrated one: the pointer resting in the divot reads the divot.
    std::this_thread::sleep_for(std::chrono::milliseconds(300));
    r = get("/api/navigation/pointer");
    EXPECT_LT((v3(r.j["tip_pointer_mm"]) - tip_true).norm(), 0.5);
    EXPECT_NE(r.j["tip_source"].get<std::string>().find("pivot calibration"), std::string::npos);
    ASSERT_TRUE(r.j["p_reference_mm"].is_array()) << r.body;
    EXPECT_LT((v3(r.j["p_reference_mm"]) - divot_reference).norm(), 0.6) << r.body;

    // Held still: no rotation, nothing to solve; hidden: no poses. The tip in use stays.
    sim_pointer({{"T_reference_from_pointer", rows(last)}});
    r = post("/api/navigation/pivot", {{"seconds", 0.6}, {"apply", true}});
    EXPECT_EQ(r.status, 409) << r.body;
    sim_pointer({{"hidden", true}});
    r = post("/api/navigation/pivot", {{"seconds", 0.6}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("pointer"), std::string::npos) << r.body;
    EXPECT_EQ(post("/api/navigation/pivot", {{"seconds", 100}}).status, 400);
    EXPECT_EQ(post("/api/navigation/pivot", {{"apply", "yes"}}).status, 400);
    EXPECT_EQ(post("/api/tracker/sim/pointer", {{"T_reference_from_pointer", {{1, 0, 0, 0}, {0, 2, 0, 0}, {0, 0, 1, 0}, {0, 0, 0, 1}}}}).status, 400);
    EXPECT_LT((v3(get("/api/navigation/pointer").j["tip_pointer_mm"]) - tip_true).norm(), 0.5);
    sim_pointer({{"free", true}});

    // The applied calibration survives a restart: a second daemon on the same state folder (the
    // store's pointer_tip.json) starts with it; an unusable file falls back to the default, saying so.
    const fs::path tip_file = g_state / "store" / "pointer_tip.json";
    ASSERT_TRUE(fs::exists(tip_file));
    const auto pointer_after_restart = [&] {
        json c = default_config_json();
        c["http"]["listen"] = "127.0.0.1:0";
        c["state_dir"] = (g_state / "restarted").string();  // its own scratch (work/ is emptied at start)
        c["store"]["dir"] = (g_state / "store").string();    // the same store
        c["tracker"]["enabled"] = false;
        c["camera"]["backend"] = "none";
        c["jobs"]["phantom_cases_at_start"] = 0;
        const TestDaemon d2(g_state / "restarted", c, 60);  // stopped when it goes (the stop expected to succeed)
        return d2.get("/api/navigation/pointer").j;
    };
    json j = pointer_after_restart();
    ASSERT_TRUE(j.is_object()) << j.dump();
    EXPECT_LT((v3(j["tip_pointer_mm"]) - tip_true).norm(), 0.5) << j.dump();
    EXPECT_EQ(j["tip_source"].get<std::string>().rfind("stored pivot calibration", 0), 0u) << j.dump();
    { std::ofstream(tip_file) << R"({"tip_pointer_mm": [1, "x", 3]})"; }
    j = pointer_after_restart();
    EXPECT_LT(v3(j["tip_pointer_mm"]).norm(), 1e-9) << j.dump();
    EXPECT_NE(j["tip_source"].get<std::string>().find("unusable"), std::string::npos) << j.dump();
    fs::remove(tip_file);
}

TEST(Navigation, TriPlanarSlicesAndSuggestedFiducials) {
    Reply r = get("/api/navigation/suggested-fiducials");
    ASSERT_EQ(r.status, 200) << r.body;
    ASSERT_EQ(r.j["fiducials"].size(), 6u) << r.body;
    const Eigen::Vector3d vertex = v3(r.j["fiducials"][5]["p_image_mm"]), left = v3(r.j["fiducials"][3]["p_image_mm"]);
    EXPECT_GT(left.x() - v3(r.j["fiducials"][4]["p_image_mm"]).x(), 100.0);  // a head is wider than 10 cm (LPS: +x left)
    r = get("/api/navigation/slices?x=" + std::to_string(vertex.x()) + "&y=" + std::to_string(vertex.y()) + "&z=" + std::to_string(vertex.z()) +
            "&size=128&format=png");
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.content_type, "image/png");
    const cv::Mat img = cv::imdecode(std::vector<uchar>(r.body.begin(), r.body.end()), cv::IMREAD_COLOR);
    ASSERT_EQ(img.cols, 3 * 128);
    ASSERT_EQ(img.rows, 128);
    const cv::Vec3b centre = img.at<cv::Vec3b>(64, 64);
    EXPECT_GT(centre[1], 200);  // the crosshair's dot, green
    EXPECT_LT(centre[0], 120);
    // At the vertex (skin), the axial panel's top half is head below and air above in the coronal.
    double above = 0, below = 0;
    for (int y = 4; y < 40; ++y) above += img.at<cv::Vec3b>(y, 128 + 64)[0];
    for (int y = 88; y < 124; ++y) below += img.at<cv::Vec3b>(y, 128 + 64)[0];
    EXPECT_GT(below, above + 36 * 20) << "coronal: tissue below the vertex, air above";
    r = get("/api/navigation/slices?size=96");
    ASSERT_EQ(r.status, 200);
    EXPECT_EQ(r.content_type, "image/jpeg");
    EXPECT_EQ(get("/api/navigation/slices?x=abc").status, 400);
    EXPECT_EQ(get("/api/navigation/slices?size=5").status, 400);
    EXPECT_EQ(get("/api/navigation/slices?format=gif").status, 400);
}


// ------------------------------------------------------------------ cortical landmarks

/// Image fiducials set, each touched with the simulated pointer and recorded, and the
/// registration accepted: the case's T_image_from_reference (and the simulator's truth).
Eigen::Matrix4d register_patient(const std::string& c, Eigen::Matrix4d& T_truth) {
    Reply r = post(c + "/navigation/image-fiducials", {{"fiducials", kImageFiducials}});
    EXPECT_EQ(r.status, 201) << r.body;
    wait_streaming();
    for (const auto& f : kImageFiducials) {
        T_truth = m4(sim_pointer({{"touch_image_mm", f["p_image_mm"]}})["T_image_from_reference_truth"]);
        r = post(c + "/navigation/record", {{"label", f["label"]}});
        EXPECT_EQ(r.status, 201) << r.body;
    }
    const Reply reg = post(c + "/navigation/register", json::object());
    EXPECT_EQ(reg.status, 200) << reg.body;
    r = post(c + "/navigation/accept", {{"image_fiducials_revision", reg.j["image_fiducials_revision"]},
                                        {"patient_fiducials_revision", reg.j["patient_fiducials_revision"]}});
    EXPECT_EQ(r.status, 201) << r.body;
    return r.status == 201 ? m4(r.j["T_image_from_reference"]) : Eigen::Matrix4d::Identity();
}

/// N points on the cortex of the bundled brain mask (data/, the phantom's): from the mask's
/// centroid outwards along directions in a 25-degree cone about a left fronto-parietal
/// craniotomy direction, the last voxel inside the mask (nearest neighbour, 0.25 mm steps).
std::vector<Eigen::Vector3d> cortical_points(int n) {
    const cf::Volume m = cf::load_volume(fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz");
    const auto& d = m.geom.dims;
    const Eigen::Affine3d world_from_index = m.geom.world_from_index(), index_from_world = world_from_index.inverse();
    Eigen::Vector3d sum = Eigen::Vector3d::Zero();
    double count = 0;
    for (int k = 0; k < d[2]; k += 2)
        for (int j = 0; j < d[1]; j += 2)
            for (int i = 0; i < d[0]; i += 2)
                if (m.at(i, j, k) > 0.5f) {
                    sum += world_from_index * Eigen::Vector3d(i, j, k);
                    count += 1;
                }
    EXPECT_GT(count, 1000) << "no brain in the mask";
    const Eigen::Vector3d centre = sum / std::max(count, 1.0);
    const auto inside = [&](const Eigen::Vector3d& w) {
        const Eigen::Vector3d ijk = index_from_world * w;
        const int i = int(std::lround(ijk.x())), j = int(std::lround(ijk.y())), k = int(std::lround(ijk.z()));
        return i >= 0 && j >= 0 && k >= 0 && i < d[0] && j < d[1] && k < d[2] && m.at(i, j, k) > 0.5f;
    };
    const Eigen::Vector3d axis = Eigen::Vector3d(0.6, -0.2, 0.77).normalized();  // LPS: left, anterior, superior
    const Eigen::Vector3d u = axis.cross(Eigen::Vector3d::UnitY()).normalized(), v = axis.cross(u);
    std::vector<Eigen::Vector3d> out;
    for (int i = 0; i < n; ++i) {
        const double cone = i == 0 ? 0.0 : 25.0 * M_PI / 180, phi = 2 * M_PI * i / std::max(1, n - 1);
        const Eigen::Vector3d dir = std::cos(cone) * axis + std::sin(cone) * (std::cos(phi) * u + std::sin(phi) * v);
        Eigen::Vector3d last = centre;
        for (double t = 0; t < 150; t += 0.25)
            if (inside(centre + t * dir)) last = centre + t * dir;
        out.push_back(last);
    }
    return out;
}

/// The simulated brain shift: 3 mm sinking along gravity (patient supine: posterior, +y in LPS)
/// plus a per-landmark variation of up to 0.6 mm on each axis.
Eigen::Vector3d true_shift(int i) { return Eigen::Vector3d(0.5 * std::sin(1.3 * i), 3.0 + 0.6 * std::cos(0.9 * i), -0.4 * std::sin(0.7 * i + 1)); }

TEST(CorticalLandmarks, BrainShiftAgainstTheSimulatorsTruth) {
    const auto id = new_case("brain shift truth");
    const std::string c = "/api/cases/" + std::to_string(id);
    Eigen::Matrix4d T_truth = Eigen::Matrix4d::Identity();
    const Eigen::Matrix4d T = register_patient(c, T_truth);
    const std::int64_t reg_rev = get(c + "/navigation").j["accepted"]["revision"];
    const int n = 6;
    const auto points = cortical_points(n);
    ASSERT_EQ(points.size(), std::size_t(n));
    for (int i = 1; i < n; ++i) EXPECT_GT((points[std::size_t(i)] - points[0]).norm(), 10.0) << "landmarks spread over the craniotomy";
    const auto label = [](int i) { return "L" + std::to_string(i + 1); };

    // Initial set: the pointer on each cortical point.
    for (int i = 0; i < n; ++i) {
        sim_pointer({{"touch_image_mm", {points[std::size_t(i)].x(), points[std::size_t(i)].y(), points[std::size_t(i)].z()}}});
        const Reply r = post(c + "/navigation/landmarks/record", {{"label", label(i)}, {"set", "initial"}});
        ASSERT_EQ(r.status, 201) << r.body;
        EXPECT_EQ(r.j["recorded"]["registration_revision"], reg_rev);
        // Through the accepted registration, the tip lands on the point (noise + registration error).
        EXPECT_LT((v3(r.j["recorded"]["p_image_mm"]) - points[std::size_t(i)]).norm(), 0.35) << r.body;
    }
    // Later set: the brain has sunk; L6 is re-digitised under a mistyped label at first.
    std::vector<Eigen::Vector3d> shifted;
    for (int i = 0; i < n; ++i) shifted.push_back(points[std::size_t(i)] + true_shift(i));
    for (int i = 0; i < n; ++i) {
        sim_pointer({{"touch_image_mm", {shifted[std::size_t(i)].x(), shifted[std::size_t(i)].y(), shifted[std::size_t(i)].z()}}});
        const Reply r = post(c + "/navigation/landmarks/record", {{"label", i == n - 1 ? std::string("L6x") : label(i)}, {"set", "later"}});
        ASSERT_EQ(r.status, 201) << r.body;
    }
    Reply r = get(c + "/navigation/landmarks");
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.j["sets"], json::parse(R"([{"set": "initial", "count": 6}, {"set": "later", "count": 6}])")) << r.body;
    EXPECT_EQ(r.j["registration_revision"], reg_rev);

    // The mistyped label shows as missing both ways.
    r = post(c + "/navigation/brain-shift", {{"earlier", "initial"}, {"later", "later"}});
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.j["rows"].size(), 5u);
    EXPECT_EQ(r.j["missing_later"], json::array({"L6"}));
    EXPECT_EQ(r.j["missing_earlier"], json::array({"L6x"}));
    // Renamed: all six pair up.
    r = post(c + "/navigation/landmarks/rename", {{"label", "L6x"}, {"new_label", "L6"}, {"set", "later"}});
    ASSERT_EQ(r.status, 200) << r.body;
    r = post(c + "/navigation/brain-shift", json::object());  // defaults: initial -> later
    ASSERT_EQ(r.status, 200) << r.body;
    ASSERT_EQ(r.j["rows"].size(), std::size_t(n)) << r.body;
    EXPECT_EQ(r.j["missing_later"].size() + r.j["missing_earlier"].size(), 0u);
    EXPECT_TRUE(r.j["same_registration"].get<bool>());

    // Against the truth. Tolerance 0.25 mm per landmark and axis: each recording averages the
    // simulator's noise (0.05 mm, 0.05 deg per tool; the reference's rotation noise at a lever
    // of ~150 mm is ~0.13 mm per frame) over >= 4 frames (18 at 60 Hz), so a difference of two
    // is ~0.05 mm rms (0.09 under a sanitizer, 4 frames), and both sets map through the same
    // registration, so its error (TRE ~0.05 mm) cancels except for its rotation error times the
    // 3 mm shift (< 0.001 mm). The mean over 6 landmarks per axis: within 0.12 mm.
    Eigen::Vector3d sum_err = Eigen::Vector3d::Zero(), max_err = Eigen::Vector3d::Zero(), sum_true = Eigen::Vector3d::Zero();
    for (int i = 0; i < n; ++i) {
        const json& row = r.j["rows"][std::size_t(i)];
        ASSERT_EQ(row["label"], label(i));
        const Eigen::Vector3d d = v3(row["d_mm"]), truth = true_shift(i);
        const Eigen::Vector3d err = (d - truth).cwiseAbs();
        for (int a = 0; a < 3; ++a) EXPECT_LT(err[a], 0.25) << label(i) << " axis " << a << ": " << d.transpose() << " vs " << truth.transpose();
        EXPECT_NEAR(row["magnitude_mm"].get<double>(), truth.norm(), 0.3);
        sum_err += d - truth;
        sum_true += truth;
        max_err = max_err.cwiseMax(err);
    }
    const Eigen::Vector3d mean_err = sum_err / n, mean = v3(r.j["mean_d_mm"]);
    for (int a = 0; a < 3; ++a) EXPECT_LT(std::abs(mean[a] - sum_true[a] / n), 0.12) << "axis " << a;
    EXPECT_GT(mean.y(), 2.5);  // the sinking is seen along gravity
    EXPECT_NE(r.j["table"].get<std::string>().find("L6"), std::string::npos);
    std::printf("%s", r.j["table"].get<std::string>().c_str());
    std::printf("brain shift vs truth over %d landmarks: mean error per axis (LPS) %+.3f %+.3f %+.3f mm, max |error| %.3f %.3f %.3f mm; "
                "true mean shift %.2f %.2f %.2f mm, measured %.2f %.2f %.2f mm\n",
                n, mean_err.x(), mean_err.y(), mean_err.z(), max_err.x(), max_err.y(), max_err.z(), sum_true.x() / n, sum_true.y() / n,
                sum_true.z() / n, mean.x(), mean.y(), mean.z());

    // A subset of labels; deleting one landmark of the later set shows it missing again.
    r = post(c + "/navigation/brain-shift", {{"labels", {"L1", "L2"}}});
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.j["rows"].size(), 2u);
    r = post(c + "/navigation/landmarks/delete", {{"set", "later"}, {"label", "L3"}});
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(post(c + "/navigation/brain-shift", json::object()).j["missing_later"], json::array({"L3"}));
    // Landmarks are stored in the case (one result row per change) and audited as result.add.
    int rows = 0;
    const json results = get(c).j["results"];  // values: a range-for over a temporary's member would dangle
    for (const auto& x : results) rows += x["kind"] == "nav_cortical_landmarks";
    EXPECT_EQ(rows, 2 * n + 2);
    int audited = 0;
    const json trail = get(c + "/audit").j["audit"];
    for (const auto& e : trail) audited += e["action"] == "result.add";
    EXPECT_GE(audited, 2 * n + 2);
    // A whole set deleted.
    r = post(c + "/navigation/landmarks/delete", {{"set", "later"}});
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_EQ(r.j["deleted"], n - 1);
    EXPECT_EQ(r.j["sets"].size(), 1u);

    // A registration accepted again between the sets: earlier landmarks keep their image
    // positions (and their registration's revision); the report says the sets went through
    // different registrations.
    const json initial_before = get(c + "/navigation/landmarks").j["landmarks"];
    const json acc = get(c + "/navigation").j["accepted"];
    r = post(c + "/navigation/accept", {{"image_fiducials_revision", acc["image_fiducials_revision"]},
                                        {"patient_fiducials_revision", acc["patient_fiducials_revision"]}});
    ASSERT_EQ(r.status, 201) << r.body;
    const std::int64_t reg_rev2 = r.j["revision"];
    EXPECT_NE(reg_rev2, reg_rev);
    sim_pointer({{"touch_image_mm", {shifted[0].x(), shifted[0].y(), shifted[0].z()}}});
    r = post(c + "/navigation/landmarks/record", {{"label", "L1"}, {"set", "later"}});
    ASSERT_EQ(r.status, 201) << r.body;
    EXPECT_EQ(r.j["recorded"]["registration_revision"], reg_rev2);
    json initial_now = json::array();
    for (const auto& l : r.j["landmarks"])
        if (l["set"] == "initial") initial_now.push_back(l);
    EXPECT_EQ(initial_now, initial_before);
    r = post(c + "/navigation/brain-shift", json::object());
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_FALSE(r.j["same_registration"].get<bool>());
    EXPECT_EQ(r.j["registration_revisions"]["earlier"], json::array({reg_rev}));
    EXPECT_EQ(r.j["registration_revisions"]["later"], json::array({reg_rev2}));
    (void)T;
}

TEST(CorticalLandmarks, BadInputIsRefusedAndNothingStoredChanges) {
    const auto id = new_case("landmarks bad input");
    const std::string c = "/api/cases/" + std::to_string(id);
    wait_streaming();
    sim_pointer({{"touch_image_mm", {40, -20, 60}}});
    // No accepted registration: the pointer cannot be mapped into the image.
    json before = snapshot(id);
    Reply r = post(c + "/navigation/landmarks/record", {{"label", "L1"}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("no accepted patient registration"), std::string::npos) << r.body;
    EXPECT_EQ(post("/api/cases/99999/navigation/landmarks/record", {{"label", "L1"}}).status, 404);
    EXPECT_EQ(snapshot(id), before);

    Eigen::Matrix4d T_truth;
    register_patient(c, T_truth);
    sim_pointer({{"touch_image_mm", {40, -20, 60}}});
    ASSERT_EQ(post(c + "/navigation/landmarks/record", {{"label", "L1"}}).status, 201);  // set "initial"
    before = snapshot(id);
    const json landmarks_before = get(c + "/navigation/landmarks").j;

    // The report: a set with no landmarks, the same set twice, an unknown label, bad fields.
    r = post(c + "/navigation/brain-shift", json::object());
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("'later'"), std::string::npos) << r.body;
    EXPECT_NE(r.body.find("sets: initial"), std::string::npos) << r.body;
    r = post(c + "/navigation/brain-shift", {{"earlier", "initial"}, {"later", "initial"}});
    EXPECT_EQ(r.status, 400) << r.body;
    sim_pointer({{"touch_image_mm", {42, -20, 57}}});
    ASSERT_EQ(post(c + "/navigation/landmarks/record", {{"label", "L2"}, {"set", "later"}}).status, 201);
    r = post(c + "/navigation/brain-shift", json::object());  // L1 vs L2: nothing in common
    EXPECT_EQ(r.status, 409) << r.body;
    ASSERT_EQ(post(c + "/navigation/landmarks/delete", {{"set", "later"}}).status, 200);
    ASSERT_EQ(post(c + "/navigation/landmarks/record", {{"label", "L1"}, {"set", "later"}}).status, 201);
    ASSERT_EQ(post(c + "/navigation/brain-shift", json::object()).status, 200);
    before = snapshot(id);
    r = post(c + "/navigation/brain-shift", {{"labels", {"L1", "nowhere"}}});
    EXPECT_EQ(r.status, 400) << r.body;
    EXPECT_NE(r.body.find("nowhere"), std::string::npos) << r.body;
    EXPECT_EQ(post(c + "/navigation/brain-shift", {{"labels", json::array()}}).status, 400);
    EXPECT_EQ(post(c + "/navigation/brain-shift", {{"earlier", 3}}).status, 400);
    EXPECT_EQ(post(c + "/navigation/brain-shift", {{"sets", {"a", "b"}}}).status, 400);
    EXPECT_EQ(request("POST", c + "/navigation/brain-shift", "{earlier: initial").status, 400);
    EXPECT_EQ(post("/api/cases/99999/navigation/brain-shift", json::object()).status, 404);

    // Recording: bad fields, malformed JSON.
    EXPECT_EQ(post(c + "/navigation/landmarks/record", json::object()).status, 400);
    EXPECT_EQ(post(c + "/navigation/landmarks/record", {{"label", ""}}).status, 400);
    EXPECT_EQ(post(c + "/navigation/landmarks/record", {{"label", "a/b"}}).status, 400);
    EXPECT_EQ(post(c + "/navigation/landmarks/record", {{"label", "L3"}, {"set", 2}}).status, 400);
    EXPECT_EQ(post(c + "/navigation/landmarks/record", {{"label", "L3"}, {"window_s", 10}}).status, 400);
    EXPECT_EQ(post(c + "/navigation/landmarks/record", {{"label", "L3"}, {"colour", "red"}}).status, 400);
    r = request("POST", c + "/navigation/landmarks/record", "{\"label\": \"L3\"");
    EXPECT_EQ(r.status, 400) << r.body;
    // The pointer moving, then out of sight; an unknown tool.
    sim_pointer({{"free", true}});
    r = post(c + "/navigation/landmarks/record", {{"label", "L3"}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("moved"), std::string::npos) << r.body;
    sim_pointer({{"hidden", true}});
    r = post(c + "/navigation/landmarks/record", {{"label", "L3"}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("pointer: not tracked"), std::string::npos) << r.body;
    sim_pointer({{"touch_image_mm", {40, -20, 60}}});
    r = post(c + "/navigation/landmarks/record", {{"label", "L3"}, {"pointer", "probe"}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("probe"), std::string::npos) << r.body;
    // Rename and delete: unknown landmark or set, a clash, the same label, bad fields.
    r = post(c + "/navigation/landmarks/rename", {{"label", "nowhere"}, {"new_label", "L9"}});
    EXPECT_EQ(r.status, 404) << r.body;
    EXPECT_NE(r.body.find("nowhere"), std::string::npos) << r.body;
    sim_pointer({{"touch_image_mm", {44, -18, 58}}});
    ASSERT_EQ(post(c + "/navigation/landmarks/record", {{"label", "L2"}}).status, 201);
    before = snapshot(id);
    r = post(c + "/navigation/landmarks/rename", {{"label", "L2"}, {"new_label", "L1"}, {"set", "initial"}});
    EXPECT_EQ(r.status, 409) << r.body;
    EXPECT_NE(r.body.find("already"), std::string::npos) << r.body;
    EXPECT_EQ(post(c + "/navigation/landmarks/rename", {{"label", "L2"}, {"new_label", "L2"}}).status, 400);
    EXPECT_EQ(post(c + "/navigation/landmarks/rename", {{"label", "L2"}}).status, 400);
    r = post(c + "/navigation/landmarks/delete", {{"set", "final"}});
    EXPECT_EQ(r.status, 404) << r.body;
    EXPECT_NE(r.body.find("final"), std::string::npos) << r.body;
    EXPECT_EQ(post(c + "/navigation/landmarks/delete", {{"set", "initial"}, {"label", "L7"}}).status, 404);
    EXPECT_EQ(post(c + "/navigation/landmarks/delete", json::object()).status, 400);
    EXPECT_EQ(request("POST", c + "/navigation/landmarks/delete", "[").status, 400);
    // A reviewer reads the landmarks and the report, and changes nothing.
    const std::string reviewer = token_of("lm_reviewer", "reviewer");
    EXPECT_EQ(get(c + "/navigation/landmarks", reviewer).status, 200);
    EXPECT_EQ(post(c + "/navigation/brain-shift", json::object(), reviewer).status, 200);
    EXPECT_EQ(post(c + "/navigation/landmarks/record", {{"label", "L4"}}, reviewer).status, 403);
    EXPECT_EQ(post(c + "/navigation/landmarks/rename", {{"label", "L2"}, {"new_label", "L5"}}, reviewer).status, 403);
    EXPECT_EQ(post(c + "/navigation/landmarks/delete", {{"set", "initial"}}, reviewer).status, 403);
    EXPECT_EQ(snapshot(id), before);
    (void)landmarks_before;
    sim_pointer({{"free", true}});
}

}  // namespace
