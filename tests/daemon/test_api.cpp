// The daemon in-process on a free port with a temporary state folder, the simulated tracker
// (through the real driver over a pty) and the CPU renderer; HTTP through cpp-httplib, the
// WebSocket through civetweb's client API.
#include <civetweb.h>
#include <unistd.h>
#include <gtest/gtest.h>
#include <httplib.h>

#include <chrono>
#include <condition_variable>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <thread>

#include "cortexfuse/daemon/daemon.hpp"

using namespace cf::daemon;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

fs::path g_state, g_ui;
std::unique_ptr<Daemon> g_daemon;

/// The daemon starts on first use (config and process tests in this binary do not need it)
/// and stops at the end of the test program.
void start_daemon() {
    const auto base = fs::temp_directory_path() / ("cf_daemon_api_" + std::to_string(::getpid()));
    g_state = base / "state";
    g_ui = base / "ui";
    fs::create_directories(g_ui / "assets");
    std::ofstream(g_ui / "index.html") << "<!doctype html><title>test ui</title>";
    std::ofstream(g_ui / "assets" / "app.js") << "console.log('ui');";
    std::ofstream(base / "secret.txt") << "outside the ui folder";
    json c = default_config_json();
    c["http"]["listen"] = "127.0.0.1:0";
    c["http"]["max_body_bytes"] = 4096;
    c["http"]["ui_dir"] = g_ui.string();
    c["state_dir"] = g_state.string();
    c["renderer"]["kind"] = "cpu";
    // The phantom case generated at start is what the register test needs; other tests
    // (ctest runs each in its own process) skip its few seconds of background work.
    // Asked of gtest rather than read from the filter's text: a negative filter (GTEST_FILTER=-X,
    // as the test command's sanitized half sets) selects the register test too.
    bool register_test_runs = false;
    const ::testing::UnitTest& unit = *::testing::UnitTest::GetInstance();
    for (int i = 0; i < unit.total_test_suite_count(); ++i)
        for (int k = 0; k < unit.GetTestSuite(i)->total_test_count(); ++k) {
            const ::testing::TestInfo& t = *unit.GetTestSuite(i)->GetTestInfo(k);
            register_test_runs |= t.should_run() && std::string(t.name()).find("Register") != std::string::npos;
        }
    c["jobs"]["phantom_cases_at_start"] = register_test_runs ? 1 : 0;
    c["jobs"]["progress_hz"] = 50;
    g_daemon = std::make_unique<Daemon>(parse_config(c, "test"));
    g_daemon->start();
}

int port() {
    if (!g_daemon) start_daemon();
    return g_daemon->port();
}

class DaemonEnv : public ::testing::Environment {
public:
    void TearDown() override {
        if (!g_daemon) return;
        EXPECT_TRUE(g_daemon->stop());
        g_daemon.reset();
        fs::remove_all(g_state.parent_path());
    }
};
const auto* const g_env = ::testing::AddGlobalTestEnvironment(new DaemonEnv);

httplib::Client client() {
    httplib::Client c("127.0.0.1", port());
    c.set_read_timeout(60, 0);
    return c;
}

json get_json(const std::string& path, int expect = 200) {
    auto c = client();
    auto r = c.Get(path.c_str());
    EXPECT_TRUE(r) << path;
    if (!r) return nullptr;
    EXPECT_EQ(r->status, expect) << path << ": " << r->body;
    return json::parse(r->body, nullptr, false);
}

json post_json(const std::string& path, const json& body, int expect) {
    auto c = client();
    auto r = c.Post(path.c_str(), body.dump(), "application/json");
    EXPECT_TRUE(r) << path;
    if (!r) return nullptr;
    EXPECT_EQ(r->status, expect) << path << ": " << r->body;
    return json::parse(r->body, nullptr, false);
}

/// A request with a bearer token; returns (status, parsed body).
std::pair<int, json> call(const std::string& method, const std::string& path, const json& body, const std::string& token) {
    auto c = client();
    httplib::Headers h;
    if (!token.empty()) h.emplace("Authorization", "Bearer " + token);
    httplib::Result r = method == "GET" ? c.Get(path.c_str(), h) : c.Post(path.c_str(), h, body.dump(), "application/json");
    if (!r) return {0, nullptr};
    return {r->status, json::parse(r->body, nullptr, false)};
}

/// Polls a job until pred holds or the timeout ends; returns the last state.
json wait_job(std::uint64_t id, const std::function<bool(const json&)>& pred, double timeout_s) {
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    json j;
    while (std::chrono::steady_clock::now() < end) {
        j = get_json("/api/jobs/" + std::to_string(id));
        if (pred(j)) return j;
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    return j;
}

/// A minimal WebSocket client on civetweb's client API: collects text messages.
struct WsClient {
    std::mutex mu;
    std::condition_variable cv;
    std::vector<json> messages;
    bool closed = false;
    mg_connection* conn = nullptr;

    static int on_data(mg_connection*, int flags, char* data, size_t len, void* self) {
        auto* w = static_cast<WsClient*>(self);
        if ((flags & 0x0f) == MG_WEBSOCKET_OPCODE_TEXT) {
            std::lock_guard lk(w->mu);
            w->messages.push_back(json::parse(data, data + len, nullptr, false));
            w->cv.notify_all();
        }
        return 1;
    }
    static void on_close(const mg_connection*, void* self) {
        auto* w = static_cast<WsClient*>(self);
        std::lock_guard lk(w->mu);
        w->closed = true;
        w->cv.notify_all();
    }
    bool connect() {
        char err[256] = {0};
        conn = mg_connect_websocket_client("127.0.0.1", port(), 0, err, sizeof err, "/api/ws", nullptr, on_data, on_close, this);
        return conn != nullptr;
    }
    void send(const json& j) {
        const std::string s = j.dump();
        mg_websocket_client_write(conn, MG_WEBSOCKET_OPCODE_TEXT, s.data(), s.size());
    }
    void send_raw(const std::string& s) { mg_websocket_client_write(conn, MG_WEBSOCKET_OPCODE_TEXT, s.data(), s.size()); }
    /// Waits for a message matching pred (searching all received so far).
    std::optional<json> wait_for(const std::function<bool(const json&)>& pred, double timeout_s) {
        std::unique_lock lk(mu);
        std::optional<json> found;
        cv.wait_for(lk, std::chrono::duration<double>(timeout_s), [&] {
            for (const auto& m : messages)
                if (pred(m)) {
                    found = m;
                    return true;
                }
            return closed;
        });
        return found;
    }
    std::optional<json> reply(int id, double timeout_s = 30) {
        return wait_for([id](const json& m) { return m.contains("id") && m["id"] == id; }, timeout_s);
    }
    ~WsClient() {
        if (conn) mg_close_connection(conn);
    }
};

}  // namespace

TEST(DaemonApi, StatusAnswersEveryModule) {
    port();
    const json s = get_json("/api/status");
    EXPECT_EQ(s["name"], "cortexfused");
    EXPECT_TRUE(s["version"].is_string());
    EXPECT_GE(s["uptime_s"].get<double>(), 0);
    const json& m = s["modules"];
    for (const char* k : {"tracker", "camera", "renderer", "jobs", "http"}) EXPECT_TRUE(m.contains(k)) << k;
    EXPECT_EQ(m["tracker"]["source"], "sim");
    EXPECT_TRUE(m["tracker"]["counters"].contains("crc_errors"));
    EXPECT_TRUE(m["jobs"]["kinds"].contains("register"));
    EXPECT_EQ(m["renderer"]["requested"], "cpu");
    // The tracker reaches streaming through the real driver and the frame rate is measured.
    const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(20);
    json t;
    while (std::chrono::steady_clock::now() < end) {
        t = get_json("/api/status")["modules"]["tracker"];
        if (t["state"] == "streaming" && t["counters"]["frames"].get<int>() > 120) break;  // the rate is over the last second
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    EXPECT_EQ(t["state"], "streaming") << t.dump();
    EXPECT_NEAR(t["frame_rate_hz"].get<double>(), 60, 15) << t.dump();
    EXPECT_GT(t["counters"]["frames"].get<int>(), 0);
    std::string why;
    EXPECT_TRUE(g_daemon->healthy(&why)) << why;
    EXPECT_NE(g_daemon->status_line().find("tracker streaming"), std::string::npos) << g_daemon->status_line();
}

// The tracker's threads say what priority they got (SCHED_FIFO with CAP_SYS_NICE, else the nice
// fallback), the kernel's tty workers are raised on the pty link when permitted, and the driver
// counts gaps by the device's frame numbers.
TEST(DaemonApi, TrackerReportsItsPrioritiesAndFrameNumberGaps) {
    port();
    json t;
    const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(20);
    while (std::chrono::steady_clock::now() < end) {
        t = get_json("/api/status")["modules"]["tracker"];
        if (t["state"] == "streaming" && t["counters"]["frames"].get<int>() > 30) break;
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    ASSERT_EQ(t["state"], "streaming") << t.dump();
    const std::string prio = t.value("thread_priority", "");
    const std::string sim_prio = t["simulator"].value("thread_priority", "");
    if (::geteuid() == 0) {  // root has CAP_SYS_NICE: what the defaults ask is granted
        EXPECT_EQ(prio, "SCHED_FIFO 20") << t.dump();
        EXPECT_EQ(sim_prio, "SCHED_FIFO 20") << t.dump();
        // The keeper thread raises them within its first pass (the pool always has some).
        for (int i = 0; i < 30 && t.value("tty_workers_raised", 0) == 0; ++i) {
            std::this_thread::sleep_for(std::chrono::milliseconds(100));
            t = get_json("/api/status")["modules"]["tracker"];
        }
        EXPECT_GT(t.value("tty_workers_raised", 0), 0) << t.dump();
    } else {
        EXPECT_TRUE(prio == "SCHED_FIFO 20" || prio.rfind("nice ", 0) == 0) << prio;
    }
    for (const char* k : {"frame_gaps", "frames_missed", "out_of_order", "late_replies", "requests"})
        EXPECT_TRUE(t["counters"].contains(k)) << k;
    EXPECT_GE(t["counters"]["requests"].get<std::uint64_t>(), t["counters"]["frames"].get<std::uint64_t>());
    EXPECT_GE(t["reply_max_us"].get<double>(), t["reply_p99_us"].get<double>());
    EXPECT_GE(t["reply_p99_us"].get<double>(), t["reply_p50_us"].get<double>());
    EXPECT_GT(t["reply_p50_us"].get<double>(), 0.0);
}

TEST(DaemonApi, ErrorsAreJsonWithTheRightStatus) {
    auto c = client();
    // Unknown endpoint.
    auto r = c.Get("/api/nothing/here");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 404);
    json e = json::parse(r->body);
    EXPECT_EQ(e["error"]["code"], "not_found");
    EXPECT_NE(e["error"]["message"].get<std::string>().find("/api/nothing/here"), std::string::npos);
    // Wrong method: 405 naming the allowed ones.
    r = c.Delete("/api/status");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 405);
    EXPECT_EQ(r->get_header_value("Allow"), "GET");
    EXPECT_EQ(json::parse(r->body)["error"]["code"], "method_not_allowed");
    // Malformed JSON.
    r = c.Post("/api/jobs", "{\"kind\": \"register\",", "application/json");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 400);
    EXPECT_NE(json::parse(r->body)["error"]["message"].get<std::string>().find("not valid JSON"), std::string::npos);
    // Oversized body (limit 4096 in this test's configuration).
    r = c.Post("/api/render", std::string(10000, ' '), "application/json");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 413);
    EXPECT_EQ(json::parse(r->body)["error"]["code"], "payload_too_large");
    // A job id that is not a number, a job that does not exist.
    r = c.Get("/api/jobs/abc");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 400);
    r = c.Get("/api/jobs/999999");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 404);
    // Bad job requests: unknown kind, unknown field, a case path that leaves the cases folder,
    // a case that does not exist.
    post_json("/api/jobs", {{"kind", "format_disk"}}, 400);
    post_json("/api/jobs", {{"kind", "register"}, {"priority", 1}}, 400);
    auto j = post_json("/api/jobs", {{"kind", "register"}, {"params", {{"case", "../../etc"}}}}, 400);
    EXPECT_NE(j["error"]["message"].get<std::string>().find("register case"), std::string::npos);
    post_json("/api/jobs", {{"kind", "register"}, {"params", {{"case", "/etc"}}}}, 400);
    post_json("/api/jobs", {{"kind", "register"}, {"params", {{"case", "nope/case_0000"}}}}, 404);
    post_json("/api/jobs", {{"kind", "register"}, {"params", {{"case", 5}}}}, 400);
    post_json("/api/jobs", {{"kind", "phantom"}, {"params", {{"n", 0}}}}, 400);
    post_json("/api/jobs", {{"kind", "phantom"}, {"params", {{"folder", "../x"}}}}, 400);
    // GET on /api/ws without an upgrade.
    r = c.Get("/api/ws");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 400);
    // Nothing was queued by the refused requests.
    const json all_jobs = get_json("/api/jobs");
    for (const auto& job : all_jobs["jobs"]) EXPECT_EQ(job["kind"], "phantom");
}

TEST(DaemonApi, StaticFilesStayInTheUiFolder) {
    auto c = client();
    auto r = c.Get("/");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 200);
    EXPECT_NE(r->body.find("test ui"), std::string::npos);
    r = c.Get("/assets/app.js");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 200);
    EXPECT_NE(r->body.find("console.log"), std::string::npos);
    r = c.Get("/missing.js");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 404);
    for (const char* evil : {"/../../etc/passwd", "/../secret.txt", "/assets/../../secret.txt", "/%2e%2e/secret.txt",
                             "/%2e%2e/%2e%2e/%2e%2e/etc/passwd", "/..%2fsecret.txt", "/assets/..%5c..%5csecret.txt"}) {
        r = c.Get(evil);
        ASSERT_TRUE(r) << evil;
        EXPECT_TRUE(r->status == 400 || r->status == 404) << evil << " -> " << r->status;
        EXPECT_EQ(r->body.find("root:"), std::string::npos) << evil;
        EXPECT_EQ(r->body.find("outside the ui folder"), std::string::npos) << evil;
    }
    r = c.Post("/index.html", "x", "text/plain");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 405);
}

TEST(DaemonApi, RenderReturnsADecodableImageOfTheAskedSize) {
    auto c = client();
    auto r = c.Post("/api/render", json{{"width", 160}, {"height", 120}, {"preset", "cortex_t1"}, {"opacity", 0.8}, {"view", "left"}}.dump(),
                    "application/json");
    ASSERT_TRUE(r);
    ASSERT_EQ(r->status, 200) << r->body;
    EXPECT_EQ(r->get_header_value("Content-Type"), "image/jpeg");
    const std::vector<uchar> bytes(r->body.begin(), r->body.end());
    cv::Mat img = cv::imdecode(bytes, cv::IMREAD_COLOR);
    ASSERT_FALSE(img.empty());
    EXPECT_EQ(img.cols, 160);
    EXPECT_EQ(img.rows, 120);
    // Something was rendered (the head is not all background).
    double lo, hi;
    cv::minMaxLoc(img.reshape(1), &lo, &hi);
    EXPECT_GT(hi - lo, 50);
    // PNG, with an explicit pose.
    const json pose = json::array({json::array({0, -1, 0, 0}), json::array({0, 0, -1, 0}), json::array({1, 0, 0, 450}), json::array({0, 0, 0, 1})});
    r = c.Post("/api/render", json{{"width", 64}, {"height", 48}, {"format", "png"}, {"T_camera_from_world", pose}, {"preset", "skin"}}.dump(),
               "application/json");
    ASSERT_TRUE(r);
    ASSERT_EQ(r->status, 200) << r->body;
    EXPECT_EQ(r->get_header_value("Content-Type"), "image/png");
    img = cv::imdecode(std::vector<uchar>(r->body.begin(), r->body.end()), cv::IMREAD_COLOR);
    EXPECT_EQ(img.cols, 64);
    EXPECT_EQ(img.rows, 48);
    // Bad requests name the field.
    for (const auto& [body, field] : std::vector<std::pair<json, std::string>>{
             {{{"width", 100000}}, "width"},
             {{{"width", "wide"}}, "width"},
             {{{"preset", "rainbow"}}, "preset"},
             {{{"opacity", 2}}, "opacity"},
             {{{"view", "sideways"}}, "view"},
             {{{"format", "gif"}}, "format"},
             {{{"colour", 1}}, "colour"},
             {{{"T_camera_from_world", json::array({1, 2})}}, "T_camera_from_world"}}) {
        r = c.Post("/api/render", body.dump(), "application/json");
        ASSERT_TRUE(r);
        EXPECT_EQ(r->status, 400) << body.dump();
        EXPECT_NE(r->body.find(field), std::string::npos) << body.dump() << " -> " << r->body;
    }
    const json st = get_json("/api/status")["modules"]["renderer"];
    EXPECT_EQ(st["backend"], "cpu") << st.dump();
    EXPECT_GE(st["renders"].get<int>(), 2);
}

TEST(DaemonApi, RenderTakesACustomTransferFunction) {
    auto c = client();
    // The presets answer their JSON: the shape `tf` takes.
    const json presets = get_json("/api/render/presets");
    ASSERT_TRUE(presets["transfer_functions"].contains("skin")) << presets.dump();
    json skin = presets["transfer_functions"]["skin"];
    auto render = [&](const json& body) {
        auto r = c.Post("/api/render", body.dump(), "application/json");
        EXPECT_TRUE(r);
        if (!r) return std::make_pair(0, cv::Mat());
        if (r->status != 200) return std::make_pair(r->status, cv::Mat());
        return std::make_pair(r->status, cv::imdecode(std::vector<uchar>(r->body.begin(), r->body.end()), cv::IMREAD_GRAYSCALE));
    };
    const json base{{"width", 64}, {"height", 48}, {"format", "png"}, {"brain_only", false}};
    json with_skin = base;
    with_skin["tf"] = skin;
    auto [s1, as_tf] = render(with_skin);
    ASSERT_EQ(s1, 200);
    json with_preset = base;
    with_preset["preset"] = "skin";
    auto [s2, as_preset] = render(with_preset);
    ASSERT_EQ(s2, 200);
    // The preset's own JSON as tf renders the same picture as the preset.
    EXPECT_EQ(cv::norm(as_tf, as_preset, cv::NORM_INF), 0);
    // A transparent transfer function renders nothing: the tf is used, not a preset.
    json clear = base;
    clear["tf"] = {{"colour", {{0, 1, 1, 1}, {1, 1, 1, 1}}}, {"opacity", {{0, 0}, {1, 0}}}};
    auto [s3, empty] = render(clear);
    ASSERT_EQ(s3, 200);
    double lo, hi;
    cv::minMaxLoc(empty, &lo, &hi);
    EXPECT_EQ(hi - lo, 0);
    cv::minMaxLoc(as_tf, &lo, &hi);
    EXPECT_GT(hi - lo, 50);
    // Bad transfer functions: 400 naming the field.
    const json good_colour = {{0, 1, 1, 1}, {1, 1, 1, 1}};
    for (const auto& [tf, field] : std::vector<std::pair<json, std::string>>{
             {json("skin"), "tf"},
             {json{{"opacity", {{0, 0}, {1, 1}}}}, "tf.colour"},
             {json{{"colour", good_colour}}, "tf.opacity"},
             {json{{"colour", {{0, 1, 1}}}, {"opacity", {{0, 0}}}}, "tf.colour[0]"},
             {json{{"colour", good_colour}, {"opacity", {{0, "x"}}}}, "tf.opacity[0]"},
             {json{{"colour", good_colour}, {"opacity", {{1, 0}, {0, 1}}}}, "sorted"},
             {json{{"colour", good_colour}, {"opacity", {{0, 2}}}}, "[0, 1]"},
             {json{{"colour", good_colour}, {"opacity", {{0, 1}}}, {"units", "furlongs"}}, "units"},
             {json{{"colour", good_colour}, {"opacity", {{0, 1}}}, {"shininess", 3}}, "tf.shininess"},
             {json{{"colour", good_colour}, {"opacity", json::array()}, {"gradient_opacity", 5}}, "tf.gradient_opacity"}}) {
        json body = base;
        body["tf"] = tf;
        auto r = c.Post("/api/render", body.dump(), "application/json");
        ASSERT_TRUE(r);
        EXPECT_EQ(r->status, 400) << body.dump();
        EXPECT_NE(r->body.find(field), std::string::npos) << body.dump() << " -> " << r->body;
    }
    json both = with_skin;
    both["preset"] = "skin";
    auto r = c.Post("/api/render", both.dump(), "application/json");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 400);
    EXPECT_NE(r->body.find("not both"), std::string::npos) << r->body;
}

TEST(DaemonApi, RenderVolumeGivesTheCentreAndExtent) {
    json v;
    for (int i = 0; i < 200; ++i) {  // the volume loads on the render thread after start
        auto c = client();
        auto r = c.Get("/api/render/volume");
        ASSERT_TRUE(r);
        if (r->status == 200) {
            v = json::parse(r->body);
            break;
        }
        ASSERT_EQ(r->status, 503) << r->body;
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    ASSERT_TRUE(v.is_object());
    ASSERT_EQ(v["center_lps_mm"].size(), 3u);
    ASSERT_EQ(v["dims"].size(), 3u);
    for (int a = 0; a < 3; ++a) {
        const double lo = v["min_lps_mm"][a], hi = v["max_lps_mm"][a], c = v["center_lps_mm"][a], e = v["extent_mm"][a];
        EXPECT_LT(lo, hi);
        EXPECT_NEAR(e, hi - lo, 1e-6);
        EXPECT_GT(c, lo);
        EXPECT_LT(c, hi);
        EXPECT_GT(e, 100);  // a head
        EXPECT_LT(e, 400);
        // The brain lies inside the head's box.
        ASSERT_TRUE(v["brain"].is_object()) << v.dump();
        EXPECT_GE(v["brain"]["min_lps_mm"][a].get<double>(), lo - 1e-6);
        EXPECT_LE(v["brain"]["max_lps_mm"][a].get<double>(), hi + 1e-6);
        EXPECT_LT(v["brain"]["extent_mm"][a].get<double>(), e);
    }
    // A view at the documented distance, aimed at the centre, shows the head (the UI's orbit).
    const double cx = v["center_lps_mm"][0], cy = v["center_lps_mm"][1], cz = v["center_lps_mm"][2];
    // Camera on the patient's left (+x) looking right: z_cam = -x, y_cam = -z (down), x_cam = y.
    const json pose = json::array({json::array({0, 1, 0, -cy}), json::array({0, 0, -1, cz}), json::array({-1, 0, 0, cx + 450}),
                                   json::array({0, 0, 0, 1})});
    auto c = client();
    auto r = c.Post("/api/render", json{{"width", 64}, {"height", 48}, {"preset", "skin"}, {"T_camera_from_world", pose}}.dump(), "application/json");
    ASSERT_TRUE(r);
    ASSERT_EQ(r->status, 200) << r->body;
    cv::Mat img = cv::imdecode(std::vector<uchar>(r->body.begin(), r->body.end()), cv::IMREAD_GRAYSCALE);
    ASSERT_FALSE(img.empty());
    // The centre pixel is the head, a corner is background.
    EXPECT_GT(int(img.at<uchar>(24, 32)), int(img.at<uchar>(0, 0)) + 20);
}

TEST(DaemonApi, WebSocketCarriesRpcAndTrackerFramesInOrder) {
    WsClient ws;
    ASSERT_TRUE(ws.connect());
    // RPC: the same registry as HTTP.
    ws.send({{"jsonrpc", "2.0"}, {"id", 1}, {"method", "status.get"}});
    auto rep = ws.reply(1);
    ASSERT_TRUE(rep);
    EXPECT_EQ((*rep)["result"]["name"], "cortexfused");
    ws.send({{"jsonrpc", "2.0"}, {"id", 2}, {"method", "no.such.method"}});
    rep = ws.reply(2);
    ASSERT_TRUE(rep);
    EXPECT_EQ((*rep)["error"]["code"], 404);
    ws.send_raw("{not json");
    auto perr = ws.wait_for([](const json& m) { return m.contains("error") && m["error"]["code"] == -32700; }, 10);
    EXPECT_TRUE(perr);
    ws.send({{"jsonrpc", "2.0"}, {"id", 3}, {"method", "push.subscribe"}, {"params", {{"tracker_hz", -3}}}});
    rep = ws.reply(3);
    ASSERT_TRUE(rep);
    EXPECT_EQ((*rep)["error"]["code"], 400);
    // Render over the WebSocket: base64 JPEG.
    ws.send({{"jsonrpc", "2.0"}, {"id", 4}, {"method", "render"}, {"params", {{"width", 48}, {"height", 32}}}});
    rep = ws.reply(4, 60);
    ASSERT_TRUE(rep);
    EXPECT_EQ((*rep)["result"]["mime"], "image/jpeg");
    EXPECT_GT((*rep)["result"]["base64"].get<std::string>().size(), 100u);

    // Every frame: sequence numbers consecutive, device frame numbers increasing.
    ws.send({{"jsonrpc", "2.0"}, {"id", 5}, {"method", "push.subscribe"}, {"params", {{"tracker_hz", 0}, {"topics", {"tracker"}}}}});
    rep = ws.reply(5);
    ASSERT_TRUE(rep);
    EXPECT_EQ((*rep)["result"]["tracker_hz"], 0);
    auto frames = [&] {
        std::lock_guard lk(ws.mu);
        std::vector<json> f;
        bool after = false;
        for (const auto& m : ws.messages) {
            if (m.contains("id") && m["id"] == 5) after = true;
            else if (after && m.value("method", "") == "notify_tracker_frame") f.push_back(m["params"]);
        }
        return f;
    };
    const auto end = std::chrono::steady_clock::now() + std::chrono::seconds(20);
    while (frames().size() < 90 && std::chrono::steady_clock::now() < end) std::this_thread::sleep_for(std::chrono::milliseconds(50));
    auto f = frames();
    ASSERT_GE(f.size(), 90u);
    for (size_t i = 1; i < f.size(); ++i) {
        ASSERT_EQ(f[i]["seq"].get<std::uint64_t>(), f[i - 1]["seq"].get<std::uint64_t>() + 1) << "gap at " << i;
        ASSERT_GT(f[i]["frame"].get<std::uint64_t>(), f[i - 1]["frame"].get<std::uint64_t>());
    }
    EXPECT_EQ(f.back()["tools"].size(), 2u);
    // Throttled: 10 Hz gives about a sixth of the 60 Hz frames.
    ws.send({{"jsonrpc", "2.0"}, {"id", 6}, {"method", "push.subscribe"}, {"params", {{"tracker_hz", 10}}}});
    ASSERT_TRUE(ws.reply(6));
    std::size_t before;
    {
        std::lock_guard lk(ws.mu);
        before = ws.messages.size();
    }
    std::this_thread::sleep_for(std::chrono::seconds(2));
    std::size_t tracker_msgs = 0;
    {
        std::lock_guard lk(ws.mu);
        for (size_t i = before; i < ws.messages.size(); ++i) tracker_msgs += ws.messages[i].value("method", "") == "notify_tracker_frame";
    }
    EXPECT_GE(tracker_msgs, 12u);
    EXPECT_LE(tracker_msgs, 28u);
}

TEST(DaemonApi, RegisterJobReportsProgressAndCancels) {
    // The phantom case generated at start (a 'phantom' job).
    json jobs = get_json("/api/jobs");
    std::uint64_t phantom_id = 0;
    for (const auto& j : jobs["jobs"])
        if (j["kind"] == "phantom") phantom_id = j["id"];
    ASSERT_NE(phantom_id, 0u);
    json ph = wait_job(phantom_id, [](const json& j) { return j["state"] != "queued" && j["state"] != "running"; }, 240);
    ASSERT_EQ(ph["state"], "succeeded") << ph.dump();
    ASSERT_EQ(ph["result"]["cases"].size(), 1u);
    const std::string case_name = ph["result"]["cases"][0];
    // A second phantom job into the same folder is refused (nothing overwritten).
    post_json("/api/jobs", {{"kind", "phantom"}, {"params", {{"folder", "phantom"}}}}, 409);

    WsClient ws;
    ASSERT_TRUE(ws.connect());
    ws.send({{"jsonrpc", "2.0"}, {"id", 1}, {"method", "push.subscribe"}, {"params", {{"topics", {"jobs"}}}}});
    ASSERT_TRUE(ws.reply(1));

    json created = post_json("/api/jobs", {{"kind", "register"}, {"params", {{"case", case_name}}}}, 202);
    const std::uint64_t id = created["id"];
    // Progress with a stage and the NMI of the evaluations.
    json running = wait_job(id, [](const json& j) { return j["fraction"].get<double>() > 0 && j["figures"].contains("nmi"); }, 120);
    ASSERT_EQ(running["state"], "running") << running.dump();
    EXPECT_GT(running["figures"]["nmi"].get<double>(), 1.0);  // NMI is in [1, 2]
    EXPECT_FALSE(running["stage"].get<std::string>().empty());
    // Cancel: the engine stops at its next check.
    post_json("/api/jobs/" + std::to_string(id) + "/cancel", json::object(), 200);
    json done = wait_job(id, [](const json& j) { return j["state"] != "running"; }, 60);
    EXPECT_EQ(done["state"], "cancelled") << done.dump();
    EXPECT_FALSE(fs::exists(g_state / "results" / ("register_" + std::to_string(id) + ".json")));
    // The push channel carried the job's progress and its end.
    auto ev = ws.wait_for([&](const json& m) { return m.value("method", "") == "notify_job" && m["params"]["id"] == id && m["params"]["state"] == "cancelled"; }, 10);
    EXPECT_TRUE(ev);
    {
        std::lock_guard lk(ws.mu);
        int progress_events = 0;
        for (const auto& m : ws.messages)
            progress_events += m.value("method", "") == "notify_job" && m["params"]["id"] == id && m["params"]["state"] == "running" && m["params"]["figures"].contains("nmi");
        EXPECT_GE(progress_events, 1);
    }

    // The same case through the case store: import the folder, register by case id, cancel;
    // the store keeps the cancelled run.
    EXPECT_EQ(get_json("/api/case-folders")["folders"][0], case_name);
    json imported = post_json("/api/cases/import", {{"folder", case_name}}, 201);
    const std::int64_t case_id = imported["id"];
    EXPECT_EQ(imported["title"], "phantom_case_0000");
    post_json("/api/cases/import", {{"folder", "../../etc"}}, 400);
    post_json("/api/jobs", {{"kind", "register"}, {"params", {{"case_id", 424242}}}}, 404);
    post_json("/api/jobs", {{"kind", "register"}, {"params", {{"case_id", case_id}, {"case", case_name}}}}, 400);
    json c2 = post_json("/api/jobs", {{"kind", "register"}, {"params", {{"case_id", case_id}}}}, 202);
    const std::uint64_t id2 = c2["id"];
    json r2 = wait_job(id2, [](const json& j) { return j["figures"].contains("nmi") || (j["state"] != "running" && j["state"] != "queued"); }, 120);
    ASSERT_EQ(r2["state"], "running") << r2.dump();
    post_json("/api/jobs/" + std::to_string(id2) + "/cancel", json::object(), 200);
    r2 = wait_job(id2, [](const json& j) { return j["state"] != "running"; }, 60);
    EXPECT_EQ(r2["state"], "cancelled") << r2.dump();
    const json rec = get_json("/api/cases/" + std::to_string(case_id));
    ASSERT_EQ(rec["registrations"].size(), 1u) << rec.dump();
    EXPECT_EQ(rec["registrations"][0]["status"], "cancelled");
    EXPECT_EQ(rec["volumes"].size(), 2u);  // T1 and its brain mask, staged beside the case
    EXPECT_TRUE(fs::is_empty(g_state / "work"));  // the export and the staged import are gone
}

TEST(DaemonApi, CasesLoginsAndRoles) {
    // From loopback without a token: the kiosk (every access).
    auto [st, u] = call("POST", "/api/users", {{"name", "rita"}, {"password", "correct horse"}, {"role", "reviewer"}}, "");
    ASSERT_EQ(st, 201) << u.dump();
    EXPECT_EQ(call("POST", "/api/users", {{"name", "rita"}, {"password", "another one"}, {"role", "reviewer"}}, "").first, 409);
    EXPECT_EQ(call("POST", "/api/users", {{"name", "sam"}, {"password", "longenough"}, {"role", "janitor"}}, "").first, 400);
    EXPECT_EQ(call("POST", "/api/users", {{"name", "sam"}, {"password", "short"}, {"role", "surgeon"}}, "").first, 400);
    ASSERT_EQ(call("POST", "/api/users", {{"name", "sam"}, {"password", "scalpel-please"}, {"role", "surgeon"}}, "").first, 201);

    auto [s1, created] = call("POST", "/api/cases", {{"title", "left frontal"}, {"patient", {{"mrn", "MRN-1"}, {"family_name", "Doe"}}}}, "");
    ASSERT_EQ(s1, 201) << created.dump();
    const std::int64_t cid = created["id"];
    const std::size_t n_cases = get_json("/api/cases")["cases"].size();
    // Bad requests change nothing.
    EXPECT_EQ(call("POST", "/api/cases", {{"patient", {{"mrn", "MRN-2"}, {"family_name", "Roe"}}}}, "").first, 400);
    EXPECT_EQ(call("POST", "/api/cases", {{"title", "x"}, {"patient", {{"mrn", "MRN-3"}}}}, "").first, 400);
    EXPECT_EQ(call("POST", "/api/cases", {{"title", 5}}, "").first, 400);
    EXPECT_EQ(get_json("/api/cases")["cases"].size(), n_cases);
    EXPECT_EQ(call("POST", "/api/cases/" + std::to_string(cid) + "/state", {{"state", "flying"}}, "").first, 400);
    EXPECT_EQ(call("POST", "/api/cases/" + std::to_string(cid) + "/state", {{"state", "registered"}}, "").first, 409);  // steps skipped
    EXPECT_EQ(call("GET", "/api/cases/99999", nullptr, "").first, 404);
    EXPECT_EQ(call("GET", "/api/cases?sort=sideways", nullptr, "").first, 400);
    EXPECT_EQ(call("GET", "/api/cases?limit=0", nullptr, "").first, 400);

    // Logins.
    EXPECT_EQ(call("POST", "/api/login", {{"name", "rita"}, {"password", "wrong horse"}}, "").first, 401);
    EXPECT_EQ(call("POST", "/api/login", {{"name", "nobody"}, {"password", "whatever1"}}, "").first, 401);
    EXPECT_EQ(call("POST", "/api/login", {{"name", "rita"}}, "").first, 400);
    auto [s2, login] = call("POST", "/api/login", {{"name", "rita"}, {"password", "correct horse"}}, "");
    ASSERT_EQ(s2, 200) << login.dump();
    EXPECT_EQ(login["role"], "reviewer");
    const std::string reviewer = login["token"];
    // A reviewer reads and never changes.
    auto [s3, one] = call("GET", "/api/cases/" + std::to_string(cid), nullptr, reviewer);
    EXPECT_EQ(s3, 200);
    EXPECT_EQ(one["patient"]["mrn"], "MRN-1");
    EXPECT_EQ(call("POST", "/api/cases", {{"title", "sneaky"}}, reviewer).first, 403);
    EXPECT_EQ(call("POST", "/api/cases/" + std::to_string(cid) + "/state", {{"state", "planned"}}, reviewer).first, 403);
    EXPECT_EQ(call("POST", "/api/jobs", {{"kind", "phantom"}, {"params", {{"folder", "r"}}}}, reviewer).first, 403);
    EXPECT_EQ(call("POST", "/api/users", {{"name", "evil"}, {"password", "12345678"}, {"role", "admin"}}, reviewer).first, 403);
    EXPECT_EQ(get_json("/api/cases")["cases"].size(), n_cases);
    // A surgeon changes; the audit trail names who viewed and changed what.
    const std::string surgeon = call("POST", "/api/login", {{"name", "sam"}, {"password", "scalpel-please"}}, "").second["token"];
    EXPECT_EQ(call("POST", "/api/cases/" + std::to_string(cid) + "/state", {{"state", "planned"}}, surgeon).first, 200);
    const json audit = call("GET", "/api/cases/" + std::to_string(cid) + "/audit", nullptr, reviewer).second["audit"];
    bool viewed_by_rita = false, changed_by_sam = false;
    for (const auto& e : audit) {
        viewed_by_rita = viewed_by_rita || (e["action"] == "case.view" && e["actor"] == "rita");
        changed_by_sam = changed_by_sam || (e["actor"] == "sam" && e["action"] != "case.view");
    }
    EXPECT_TRUE(viewed_by_rita) << audit.dump();
    EXPECT_TRUE(changed_by_sam) << audit.dump();
    // Unknown tokens and ended sessions are refused (also from loopback).
    EXPECT_EQ(call("GET", "/api/cases", nullptr, "not-a-token").first, 401);
    EXPECT_EQ(call("POST", "/api/logout", json::object(), reviewer).first, 200);
    EXPECT_EQ(call("GET", "/api/cases", nullptr, reviewer).first, 401);
    // /api/status needs no login at all.
    EXPECT_EQ(call("GET", "/api/status", nullptr, "not-a-token").first, 200);
    // The WebSocket with a bad token is refused at the upgrade.
    char err[256] = {0};
    mg_connection* bad = mg_connect_websocket_client("127.0.0.1", port(), 0, err, sizeof err, "/api/ws?token=nope", nullptr,
                                                     WsClient::on_data, WsClient::on_close, nullptr);
    EXPECT_EQ(bad, nullptr);
    if (bad) mg_close_connection(bad);
}

TEST(DaemonApi, CancelAQueuedJob) {
    // Two phantom jobs: the second waits behind the first (one worker per kind).
    json a = post_json("/api/jobs", {{"kind", "phantom"}, {"params", {{"folder", "extra_a"}, {"n", 1}}}}, 202);
    json b = post_json("/api/jobs", {{"kind", "phantom"}, {"params", {{"folder", "extra_b"}, {"n", 1}}}}, 202);
    json bj = post_json("/api/jobs/" + std::to_string(b["id"].get<int>()) + "/cancel", json::object(), 200);
    EXPECT_EQ(bj["state"], "cancelled");
    json aj = post_json("/api/jobs/" + std::to_string(a["id"].get<int>()) + "/cancel", json::object(), 200);
    aj = wait_job(a["id"], [](const json& j) { return j["state"] != "running" && j["state"] != "queued"; }, 60);
    EXPECT_EQ(aj["state"], "cancelled") << aj.dump();
    // A cancelled generation leaves no folder behind.
    EXPECT_FALSE(fs::exists(g_state / "cases" / "extra_a"));
    EXPECT_FALSE(fs::exists(g_state / "cases" / "extra_b"));
    for (const auto& e : fs::directory_iterator(g_state / "cases")) EXPECT_NE(e.path().filename().string().rfind(".tmp-", 0), 0u) << e.path();
}

TEST(DaemonApi, CameraCaptureReturnsThePhoto) {
    auto c = client();
    auto r = c.Post("/api/camera/capture", "", "application/json");
    ASSERT_TRUE(r);
    ASSERT_EQ(r->status, 200) << r->body;
    EXPECT_EQ(r->get_header_value("Content-Type"), "image/jpeg");
    const cv::Mat img = cv::imdecode(std::vector<uchar>(r->body.begin(), r->body.end()), cv::IMREAD_COLOR);
    EXPECT_EQ(img.cols, 640);
    EXPECT_EQ(img.rows, 480);
    const json cam = get_json("/api/camera");
    EXPECT_EQ(cam["state"], "open");
    EXPECT_EQ(cam["counters"]["captures"], 1);
    r = c.Get("/api/camera/capture");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 405);
}
