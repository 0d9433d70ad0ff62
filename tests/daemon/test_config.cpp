// Configuration validation (every key's type and range, unknown keys, cross-field rules) and
// the endpoint registry's matching and errors.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>

#include "cortexfuse/daemon/config.hpp"
#include "cortexfuse/daemon/endpoints.hpp"

using namespace cf::daemon;
using nlohmann::json;

namespace {
// Sets a dotted key in a JSON object.
json with(json j, const std::string& key, const json& v) {
    std::string p = "/" + key;
    for (auto& c : p)
        if (c == '.') c = '/';
    j[json::json_pointer(p)] = v;
    return j;
}
std::string error_of(const json& j) {
    try {
        parse_config(j, "test.json");
    } catch (const ConfigError& e) {
        return e.what();
    }
    return "";
}
}  // namespace

TEST(DaemonConfig, DefaultsParseAndRoundTrip) {
    const DaemonConfig c = parse_config(default_config_json(), "defaults");
    EXPECT_EQ(c.listen, "127.0.0.1:8080");
    EXPECT_EQ(c.tracker_source, "sim");
    EXPECT_EQ(c.camera_backend, "sim");
    EXPECT_NE(c.t1_path.find("t1_head_mne_ecog.nii.gz"), std::string::npos);
    // The effective configuration served by the API parses back to the same values.
    const DaemonConfig c2 = parse_config(to_json(c), "round trip");
    EXPECT_EQ(to_json(c2), to_json(c));
    // Every declared option is in the defaults, and the docs table lists each.
    const std::string table = config_markdown_table();
    for (const auto& o : config_options()) EXPECT_NE(table.find("`" + o.key + "`"), std::string::npos) << o.key;
}

TEST(DaemonConfig, EmptyObjectTakesDefaults) {
    EXPECT_EQ(to_json(parse_config(json::object(), "empty")), to_json(parse_config(default_config_json(), "d")));
}

struct BadCase {
    std::string key;
    json value;
    std::string expect;  // a fragment of the message
};

TEST(DaemonConfig, EachBadValueIsRefusedNamingTheKey) {
    const std::vector<BadCase> cases = {
        {"http.listen", "localhost", "not HOST:PORT"},
        {"http.listen", 8080, "must be a string"},
        {"http.listen", "127.0.0.1:99999", "not HOST:PORT"},
        {"http.threads", 1, "out of range 2..256"},
        {"http.threads", 1000, "out of range"},
        {"http.threads", 4.5, "must be an integer"},
        {"http.max_body_bytes", 10, "out of range"},
        {"http.request_timeout_ms", 0, "out of range"},
        {"http.ui_dir", false, "must be a string"},
        {"http.remote_requires_login", "yes", "true or false"},
        {"push.default_tracker_hz", -1, "out of range"},
        {"push.default_tracker_hz", "fast", "must be a number"},
        {"push.queue_frames", 1, "out of range"},
        {"state_dir", 3, "must be a string"},
        {"data.t1", "", "must not be empty"},
        {"tracker.enabled", 1, "true or false"},
        {"tracker.source", "usb", "one of sim, serial, tcp"},
        {"tracker.sim_link", "udp", "one of pty, tcp"},
        {"tracker.sim_rate_hz", 30, "not one of 20, 60, 250"},
        {"tracker.sim_rate_hz", 1000, "out of range"},
        {"tracker.sim_seed", -1, "out of range"},
        {"tracker.rt_priority", 100, "out of range 0..99"},
        {"tracker.rt_priority", -1, "out of range"},
        {"tracker.tty_worker_priority", 100, "out of range 0..99"},
        {"tracker.baud", 19200, "not a rate"},
        {"tracker.roms", "a.rom", "list of strings"},
        {"tracker.roms", json::array({1}), "list of strings"},
        {"camera.backend", "webcam", "one of sim, gphoto2, v4l2, none"},
        {"camera.sim_pose", "gps", "one of auto, orbit, tracker"},
        {"camera.sim_T_optics_from_tool", "1 2 3", "expected 'tx ty tz qw qx qy qz'"},
        {"camera.sim_T_optics_from_tool", "0 0 0 2 0 0 0", "quaternion is not unit length"},
        {"tracker.sim_camera_tool", "yes", "true or false"},
        {"renderer.kind", "vulkan", "one of auto, gl, cpu"},
        {"renderer.max_width", 8, "out of range"},
        {"renderer.jpeg_quality", 101, "out of range"},
        {"jobs.phantom_cases_at_start", 21, "out of range"},
        {"jobs.stop_timeout_ms", -5, "out of range"},
        {"jobs.progress_hz", 0, "out of range"},
        {"jobs.kept", 0, "out of range"},
        {"watchdog.check_ms", 10, "out of range"},
        {"watchdog.tracker_stall_ms", 50, "out of range"},
    };
    for (const auto& c : cases) {
        const std::string e = error_of(with(json::object(), c.key, c.value));
        EXPECT_NE(e.find("test.json: " + c.key), std::string::npos) << c.key << " = " << c.value.dump() << " -> " << e;
        EXPECT_NE(e.find(c.expect), std::string::npos) << c.key << " = " << c.value.dump() << " -> " << e;
    }
}

TEST(DaemonConfig, UnknownKeysAndShapes) {
    EXPECT_NE(error_of(json{{"htp", {{"listen", "1.2.3.4:1"}}}}).find("htp: unknown option"), std::string::npos);
    EXPECT_NE(error_of(json{{"http", {{"lisen", "1.2.3.4:1"}}}}).find("http.lisen: unknown option"), std::string::npos);
    EXPECT_NE(error_of(json{{"http", 5}}).find("http: must be an object"), std::string::npos);
    EXPECT_NE(error_of(json::array()).find("must be a JSON object"), std::string::npos);
}

TEST(DaemonConfig, CrossFieldRules) {
    EXPECT_NE(error_of(json{{"tracker", {{"source", "serial"}}}}).find("tracker.serial_port: must be set"), std::string::npos);
    EXPECT_NE(error_of(json{{"tracker", {{"source", "tcp"}}}}).find("tracker.tcp: must be set"), std::string::npos);
    EXPECT_NE(error_of(json{{"tracker", {{"source", "tcp"}, {"tcp", "nohost"}}}}).find("tracker.tcp: 'nohost' is not HOST:PORT"), std::string::npos);
    // The simulated camera on the tracker simulator's camera tool needs that tool in the scene.
    EXPECT_NE(error_of(json{{"camera", {{"sim_pose", "tracker"}}}})
                  .find("camera.sim_pose: 'tracker' needs the tracker simulator's camera tool"),
              std::string::npos);
    EXPECT_NE(error_of(json{{"camera", {{"sim_pose", "tracker"}}}, {"tracker", {{"sim_camera_tool", true}, {"enabled", false}}}})
                  .find("camera.sim_pose: 'tracker' needs"),
              std::string::npos);
    EXPECT_EQ(error_of(json{{"camera", {{"sim_pose", "tracker"}}}, {"tracker", {{"sim_camera_tool", true}}}}), "");
    // A disabled tracker does not need its device.
    EXPECT_EQ(error_of(json{{"tracker", {{"enabled", false}, {"source", "serial"}}}}), "");
    EXPECT_EQ(error_of(json{{"http", {{"listen", "0.0.0.0:0"}}}}), "");
}

TEST(DaemonConfig, FileErrorsNameTheFile) {
    const auto dir = std::filesystem::temp_directory_path() / ("cf_daemon_cfg_" + std::to_string(::getpid()));
    std::filesystem::create_directories(dir);
    try {
        load_config_file((dir / "missing.json").string());
        FAIL();
    } catch (const ConfigError& e) {
        EXPECT_NE(std::string(e.what()).find("missing.json: cannot be read"), std::string::npos) << e.what();
    }
    std::ofstream(dir / "bad.json") << "{\"http\": {";
    try {
        load_config_file((dir / "bad.json").string());
        FAIL();
    } catch (const ConfigError& e) {
        EXPECT_NE(std::string(e.what()).find("bad.json: is not valid JSON"), std::string::npos) << e.what();
    }
    std::ofstream(dir / "ok.json") << "{\"http\": {\"listen\": \"127.0.0.1:9999\"}, \"tracker\": {\"enabled\": false}}";
    const DaemonConfig c = load_config_file((dir / "ok.json").string());
    EXPECT_EQ(c.listen, "127.0.0.1:9999");
    EXPECT_FALSE(c.tracker_enabled);
    std::filesystem::remove_all(dir);
}

TEST(EndpointRegistry, MatchesPathsAndRefusesWithTheRightStatus) {
    std::map<std::string, std::string> p;
    EXPECT_TRUE(match_path("/api/jobs/{id}", "/api/jobs/12", p));
    EXPECT_EQ(p["id"], "12");
    EXPECT_FALSE(match_path("/api/jobs/{id}", "/api/jobs", p));
    EXPECT_FALSE(match_path("/api/jobs/{id}", "/api/jobs/1/cancel", p));

    EndpointRegistry r;
    r.add({"GET", "/api/x/{id}", "x.get", Access::read, "", [](const Request& q) {
               Response resp;
               resp.json = {{"id", q.params.at("id")}};
               return resp;
           }});
    r.add({"POST", "/api/x/{id}", "x.set", Access::write, "", [](const Request&) { return Response{}; }});
    r.add({"GET", "/api/open", "open.get", Access::open, "", [](const Request&) { return Response{}; }});
    Request q;
    q.client.role = "kiosk";
    q.method = "GET";
    q.path = "/api/x/7";
    EXPECT_EQ(r.dispatch_http(q).json["id"], "7");
    auto status_of = [&](Request rq) {
        try {
            r.dispatch_http(rq);
        } catch (const ApiError& e) {
            return e.status;
        }
        return 200;
    };
    q.method = "DELETE";
    EXPECT_EQ(status_of(q), 405);
    q.path = "/api/nothing";
    EXPECT_EQ(status_of(q), 404);
    // No session: 401 except for open endpoints; a reviewer may read, not write.
    Request anon;
    anon.method = "GET";
    anon.path = "/api/x/1";
    EXPECT_EQ(status_of(anon), 401);
    anon.path = "/api/open";
    EXPECT_EQ(status_of(anon), 200);
    Request reviewer;
    reviewer.client.role = "reviewer";
    reviewer.method = "POST";
    reviewer.path = "/api/x/1";
    EXPECT_EQ(status_of(reviewer), 403);
    reviewer.method = "GET";
    EXPECT_EQ(status_of(reviewer), 200);
    // The same endpoints by JSON-RPC name, path parameters from params.
    Client kiosk;
    kiosk.role = "kiosk";
    EXPECT_EQ(r.dispatch_rpc("x.get", {{"id", "9"}}, kiosk).json["id"], "9");
    EXPECT_THROW(r.dispatch_rpc("x.nope", nullptr, kiosk), ApiError);
    EXPECT_THROW(r.dispatch_rpc("x.get", json::array(), kiosk), ApiError);
    // Registering the same name twice is a programming error.
    EXPECT_THROW(r.add({"GET", "/api/y", "x.get", Access::read, "", nullptr}), std::logic_error);
}
