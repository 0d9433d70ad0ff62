// Hardware-in-the-loop: the simulator on a pty (and on TCP, loopback), the driver streaming at
// 60 Hz through a fault campaign of every kind. No crash, no corrupt frame accepted (every pose
// equals the simulator's measurement for that frame, hence its truth within noise), streaming
// back within 2 s of every reconnect or power cycle.
// Duration: CF_HIL_SECONDS (environment), else the build's default (60 s release, 20 s ASan).
#include <gtest/gtest.h>

#include <algorithm>
#include <cstdlib>
#include <filesystem>
#include <iostream>
#include <mutex>
#include <nlohmann/json.hpp>
#include <thread>

#include "cortexfuse/drivers/sim/tracker_sim.hpp"
#include "cortexfuse/drivers/tracker/session.hpp"

namespace fs = std::filesystem;
using namespace cf::tracker;
using namespace std::chrono_literals;
using cf::sim::Fault;

namespace {
const fs::path kData = CF_DRIVERS_TEST_DATA;

double hil_seconds() {
    if (const char* e = std::getenv("CF_HIL_SECONDS")) {
        const double v = std::atof(e);
        if (v >= 5 && v <= 600) return v;
    }
    return CF_HIL_DEFAULT_SECONDS;
}

struct Seen {
    std::uint32_t frame;
    std::int64_t receive_ns;
    std::vector<std::pair<std::string, std::optional<Eigen::Isometry3d>>> tools;
    std::vector<ToolReading::Status> status;
};

void run_campaign(bool tcp) {
    const double seconds = hil_seconds();
    const bool short_run = seconds < 60;
    cf::sim::TrackerSimConfig sc;
    sc.link = tcp ? cf::sim::TrackerSimConfig::Link::tcp : cf::sim::TrackerSimConfig::Link::pty;
    sc.pty_link = (fs::temp_directory_path() / ("cf_hil_" + std::to_string(::getpid()))).string();
    sc.frame_rate_hz = 60;
    sc.seed = tcp ? 7 : 3;
    sc.camera_tool = true;
    // Per tracking reply (45 % of them damaged); a short (sanitizer) run gets denser faults so
    // that the count stays meaningful. Cheap faults dominate; drops and delays cost a timeout.
    const double k = short_run ? 1.4 : 1.0;
    auto rate = [&](const char* name, double p) { return std::string(name) + "=" + std::to_string(p * k) + ","; };
    sc.faults = cf::sim::FaultRates::parse(rate("bit_flip", 0.12) + rate("garbage", 0.10) + rate("split", 0.06) + rate("stale_bytes", 0.06) +
                                           rate("truncate", 0.06) + rate("delay", 0.02) + rate("drop", 0.03) +
                                           "disconnects_per_min=5,power_cycles_per_min=4,tool_missing=0.12,out_of_volume=0.06");
    sc.reply_delay = 0ms;
    // Every kind at least once, whatever the random draw.
    sc.script = {{2.0, Fault::disconnect, "", 0}, {5.0, Fault::power_cycle, "", 0}, {3.5, Fault::tool_missing, "CF-POINTER", 0.8},
                 {4.5, Fault::out_of_volume, "CF-REFERENCE", 0.5}};
    cf::sim::TrackerSimulator sim(sc);
    sim.start();

    SessionConfig cfg;
    cfg.tools = {load_tool_definition((kData / "roms/cf_reference.rom").string(), 'S'),
                 load_tool_definition((kData / "roms/cf_pointer.rom").string()),
                 load_tool_definition((kData / "roms/cf_camera.rom").string())};
    cfg.poll_interval = 2ms;  // as fast as the link answers: more replies, more faults
    cfg.reply_timeout = 60ms;
    cfg.command_timeout = 300ms;
    cfg.reset_timeout = 600ms;
    cfg.max_backoff = 200ms;
    auto transport = tcp ? make_tcp_transport("127.0.0.1", sim.tcp_port()) : make_serial_transport(sc.pty_link);
    TrackerSession s(std::move(transport), cfg);
    std::mutex mu;
    std::vector<Seen> seen;
    s.set_frame_callback([&](const TrackerFrame& f) {
        Seen x{f.frame_number, f.receive_steady_ns, {}, {}};
        for (const auto& t : f.tools) {
            x.tools.emplace_back(t.name, t.T_tracker_from_tool);
            x.status.push_back(t.status);
        }
        std::lock_guard lk(mu);
        seen.push_back(std::move(x));
    });
    const std::int64_t t_start = steady_ns();
    s.start();
    std::this_thread::sleep_for(std::chrono::duration<double>(seconds));
    const std::int64_t t_end = steady_ns();
    const TrackerStatus st = s.status();
    s.stop();
    sim.stop();

    // 1. No corrupt frame: every pose is the simulator's measurement for its frame number.
    const std::map<std::string, std::string> part = {{"cf_reference", "CF-REFERENCE"}, {"cf_pointer", "CF-POINTER"}, {"cf_camera", "CF-CAMERA"}};
    std::size_t poses = 0, bad = 0, missing_ok = 0;
    double max_dev_mm = 0;
    for (const auto& f : seen) {
        for (std::size_t i = 0; i < f.tools.size(); ++i) {
            const auto truth = sim.truth(part.at(f.tools[i].first), f.frame);
            const auto& pose = f.tools[i].second;
            if (!pose) {
                missing_ok += !truth->visible || f.status[i] != ToolReading::Status::ok;
                if (f.status[i] == ToolReading::Status::ok) ++bad;  // OK without a pose: never
                continue;
            }
            ++poses;
            const double d = (pose->translation() - truth->measured.translation()).norm();
            const double dev = (pose->translation() - truth->T_tracker_from_tool.translation()).norm();
            max_dev_mm = std::max(max_dev_mm, dev);
            if (!truth->visible || d > 1e-3 || !pose->linear().isApprox(truth->measured.linear(), 1e-5) ||
                dev > 6 * sc.noise_mm * std::sqrt(3.0) + 1e-3)
                ++bad;
        }
    }
    EXPECT_EQ(bad, 0u) << "accepted poses that differ from the simulator's truth";
    EXPECT_GT(poses, static_cast<std::size_t>(seconds * 60 * 3 * 0.1)) << "too few frames to mean anything";

    // 2. Streaming back within 2 s of every link or device restoration (when the next outage
    //    did not begin before that).
    auto restored = sim.link_restored_ns();
    std::sort(restored.begin(), restored.end());
    std::vector<double> resume_s;
    std::size_t late = 0;
    for (std::size_t i = 0; i < restored.size(); ++i) {
        const std::int64_t T = restored[i];
        if (T + 2'500'000'000 > t_end) continue;
        const std::int64_t next = i + 1 < restored.size() ? restored[i + 1] - 300'000'000 : t_end;
        const auto it = std::find_if(seen.begin(), seen.end(), [&](const Seen& f) { return f.receive_ns > T; });
        if (it == seen.end()) {
            ++late;
            continue;
        }
        const double r = static_cast<double>(it->receive_ns - T) * 1e-9;
        if (it->receive_ns > next && r > 2.0) continue;  // interrupted by the next outage
        resume_s.push_back(r);
        if (r > 2.0) ++late;
    }
    EXPECT_EQ(late, 0u) << "restorations not followed by a frame within 2 s";
    EXPECT_GE(resume_s.size(), 2u);

    // 3. A fault campaign of every kind, big enough.
    const auto counts = sim.fault_counts();
    for (Fault f : cf::sim::kAllFaults) EXPECT_GT(counts.count(f) ? counts.at(f) : 0u, 0u) << cf::sim::fault_name(f);
    const std::uint64_t total = sim.total_faults();
    EXPECT_GE(total, short_run ? 300u : 2000u);
    EXPECT_GT(st.crc_errors, 0u);
    EXPECT_GT(st.reconnects, 0u);

    std::sort(resume_s.begin(), resume_s.end());
    nlohmann::json j{{"transport", tcp ? "tcp" : "pty"}, {"seconds", static_cast<double>(t_end - t_start) * 1e-9},
                     {"frames", seen.size()}, {"poses_checked", poses}, {"bad_poses", bad}, {"max_deviation_mm", max_dev_mm},
                     {"faults_total", total}, {"crc_errors", st.crc_errors}, {"resyncs", st.resyncs}, {"timeouts", st.timeouts}, {"lost_replies", st.lost_replies},
                     {"protocol_errors", st.protocol_errors}, {"reconnects", st.reconnects}, {"resets", st.resets},
                     {"restorations_checked", resume_s.size()},
                     {"resume_s_median", resume_s.empty() ? 0 : resume_s[resume_s.size() / 2]},
                     {"resume_s_max", resume_s.empty() ? 0 : resume_s.back()},
                     {"latency_p50_us", st.latency_p50_us}, {"latency_p99_us", st.latency_p99_us}};
    for (const auto& [f, n] : counts) j["faults"][cf::sim::fault_name(f)] = n;
    std::cout << "HIL " << j.dump() << std::endl;
}

TEST(TrackerHil, FaultCampaignOverPty) { run_campaign(false); }
TEST(TrackerHil, FaultCampaignOverTcp) { run_campaign(true); }
}  // namespace
