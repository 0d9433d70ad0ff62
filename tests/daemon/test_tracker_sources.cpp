// The daemon's tracker from configuration with an external device (issue 6: "owns the tracker
// ... drivers (real or simulated, from configuration)"): tracker.source serial with
// tracker.serial_port, and tracker.source tcp with tracker.tcp, each against a simulator the
// daemon does not own (the stand-in for a Polaris on a USB-serial adapter and a Vega), with the
// tools from tracker.roms. The daemon must stream through the real driver, report the
// transport it was given, and its poses must be the device's.
#include <gtest/gtest.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <thread>

#include "cortexfuse/daemon/config.hpp"
#include "cortexfuse/daemon/daemon.hpp"
#include "cortexfuse/drivers/sim/tracker_sim.hpp"
#include "daemon_fixture.hpp"

using namespace cf::daemon_test;
using cf::sim::TrackerSimConfig;
using cf::sim::TrackerSimulator;

namespace {

const fs::path kRoms = fs::path(CF_DRIVERS_TEST_DATA) / "roms";

json tracker_config(const fs::path& state) {
    json c = base_test_config(state, "cpu");
    c["camera"]["backend"] = "none";
    c["tracker"]["roms"] = {(kRoms / "cf_reference.rom").string(), (kRoms / "cf_pointer.rom").string()};
    return c;
}

// Waits until the daemon's tracker streams and has published `frames` frames; its status.
json wait_streaming(const TestDaemon& d, int frames) {
    json t;
    for (int i = 0; i < 150; ++i) {
        const Reply r = d.get("/api/status");
        if (r.status == 200) {
            t = r.j["modules"]["tracker"];
            if (t.value("state", "") == "streaming" && t["counters"].value("frames", 0) >= frames) return t;
        }
        std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    ADD_FAILURE() << "the tracker did not stream: " << t.dump();
    return t;
}

// The newest frame the daemon has (GET /api/navigation/pointer) against the device's truth.
void expect_pointer_is_the_devices(const TestDaemon& d, const TrackerSimulator& sim) {
    const Reply r = d.get("/api/navigation/pointer");
    ASSERT_EQ(r.status, 200) << r.body;
    const json& f = r.j["frame"];
    ASSERT_TRUE(f.is_object()) << r.body;
    int checked = 0;
    for (const auto& t : f["tools"]) {
        if (!t.contains("t_mm")) continue;
        const std::string part = t["name"] == "cf_pointer" ? "CF-POINTER" : "CF-REFERENCE";
        const auto truth = sim.truth(part, f["frame"].get<std::uint32_t>());
        ASSERT_TRUE(truth.has_value());
        const Eigen::Vector3d p(t["t_mm"][0].get<double>(), t["t_mm"][1].get<double>(), t["t_mm"][2].get<double>());
        EXPECT_LT((p - truth->measured.translation()).norm(), 1e-3) << t.dump();
        ++checked;
    }
    EXPECT_GT(checked, 0) << r.body;
}

TEST(TrackerSources, SerialPortOfAnExternalDevice) {
    TrackerSimConfig sc;
    TrackerSimulator sim(sc);
    sim.start();
    const fs::path state = fs::temp_directory_path() / ("cf_daemon_src_serial_" + std::to_string(::getpid()));
    {
        json c = tracker_config(state);
        c["tracker"]["source"] = "serial";
        c["tracker"]["serial_port"] = sim.slave_path();
        TestDaemon d(state, c);
        const json t = wait_streaming(d, 20);
        EXPECT_EQ(t.value("source", ""), "serial");
        EXPECT_EQ(t.value("transport", ""), "serial " + sim.slave_path());
        EXPECT_EQ(t.value("baud", 0), 115200);  // COMM switched the link to tracker.baud
        EXPECT_FALSE(t.contains("simulator")) << "the daemon owns no simulator here: " << t.dump();
        expect_pointer_is_the_devices(d, sim);
    }
    sim.stop();
    fs::remove_all(state);
}

TEST(TrackerSources, TcpOfAnExternalDevice) {
    TrackerSimConfig sc;
    sc.link = TrackerSimConfig::Link::tcp;
    TrackerSimulator sim(sc);
    sim.start();
    const fs::path state = fs::temp_directory_path() / ("cf_daemon_src_tcp_" + std::to_string(::getpid()));
    {
        json c = tracker_config(state);
        c["tracker"]["source"] = "tcp";
        c["tracker"]["tcp"] = "127.0.0.1:" + std::to_string(sim.tcp_port());
        TestDaemon d(state, c);
        const json t = wait_streaming(d, 20);
        EXPECT_EQ(t.value("source", ""), "tcp");
        EXPECT_EQ(t.value("transport", ""), "tcp 127.0.0.1:" + std::to_string(sim.tcp_port()));
        expect_pointer_is_the_devices(d, sim);
    }
    sim.stop();
    fs::remove_all(state);
}

}  // namespace
