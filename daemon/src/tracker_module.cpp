#include "tracker_module.hpp"

#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

#include "cortexfuse/daemon/log.hpp"
#include "cortexfuse/drivers/tracker/frame_json.hpp"
#include "cortexfuse/drivers/tracker/transport.hpp"

namespace cf::daemon {

using namespace cf::tracker;

TrackerModule::TrackerModule(const DaemonConfig& c) : cfg_(c) {}

TrackerModule::~TrackerModule() { stop(); }

namespace {
/// Runs `f` with this thread's nice value set to `nice`, so the threads `f` starts inherit it
/// (Linux: nice is per thread and copied by clone), then restores it (raising it again is
/// always allowed). Lowering it below the current value needs CAP_SYS_NICE: without it the
/// threads keep the daemon's priority and `why_not` says so.
template <class F>
void with_thread_nice(int nice, F&& f, std::string* why_not) {
    const id_t tid = id_t(::syscall(SYS_gettid));
    errno = 0;
    const int before = ::getpriority(PRIO_PROCESS, tid);
    const bool read_ok = errno == 0;
    bool changed = false;
    if (read_ok && nice != before) {
        if (::setpriority(PRIO_PROCESS, tid, nice) == 0) changed = true;
        else if (why_not) *why_not = std::string("cannot set nice ") + std::to_string(nice) + ": " + std::strerror(errno) + " (needs CAP_SYS_NICE)";
    }
    try {
        f();
    } catch (...) {
        if (changed) ::setpriority(PRIO_PROCESS, tid, before);
        throw;
    }
    if (changed) ::setpriority(PRIO_PROCESS, tid, before);
}
}  // namespace

void TrackerModule::start() {
    if (!cfg_.tracker_enabled) return;
    // The driver's thread (and the simulator's) must be scheduled within the device's reply
    // deadline even when registrations and HTTP clients saturate the CPU: start them at
    // tracker.nice (default -10).
    std::string why_not;
    with_thread_nice(cfg_.tracker_nice, [&] { start_threads(); }, &why_not);
    nice_ = why_not.empty() ? cfg_.tracker_nice : 0;
    if (!why_not.empty()) log(LogLevel::warning, "tracker", "tracker.nice: " + why_not + "; the driver thread runs at the daemon's priority");
}

void TrackerModule::start_threads() {
    SessionConfig sc;
    sc.baud = cfg_.tracker_baud;
    for (const auto& r : cfg_.tracker_roms) sc.tools.push_back(load_tool_definition(r));
    std::unique_ptr<Transport> t;
    if (cfg_.tracker_source == "sim") {
        cf::sim::TrackerSimConfig simc;
        simc.link = cfg_.tracker_sim_link == "tcp" ? cf::sim::TrackerSimConfig::Link::tcp : cf::sim::TrackerSimConfig::Link::pty;
        simc.tcp_port = 0;
        simc.frame_rate_hz = cfg_.tracker_sim_rate_hz;
        simc.seed = std::uint64_t(cfg_.tracker_sim_seed);
        if (!cfg_.tracker_sim_faults.empty()) {
            try {
                simc.faults = cf::sim::FaultRates::parse(cfg_.tracker_sim_faults);
            } catch (const std::exception& e) {
                throw ConfigError("tracker.sim_faults", e.what());
            }
        }
        sim_ = std::make_unique<cf::sim::TrackerSimulator>(simc);
        sim_->start();
        if (sc.tools.empty())  // the simulator's scene: reference (static) and pointer (dynamic)
            sc.tools = {ToolDefinition{"reference", cf::sim::make_synthetic_rom("CF-REFERENCE", 1, {{0, 0, 0}, {0, 50, 0}, {0, 100, 25}}), 'S'},
                        ToolDefinition{"pointer", cf::sim::make_synthetic_rom("CF-POINTER", 2, {{0, 0, 0}, {-30, 0, 0}, {-70, 0, 20}}), 'D'}};
        if (simc.link == cf::sim::TrackerSimConfig::Link::tcp) {
            t = make_tcp_transport("127.0.0.1", sim_->tcp_port());
            source_desc_ = "simulator over tcp";
        } else {
            t = make_serial_transport(sim_->slave_path());
            source_desc_ = "simulator over a pty";
        }
    } else if (cfg_.tracker_source == "serial") {
        t = make_serial_transport(cfg_.tracker_serial_port);
        source_desc_ = "serial";
    } else {
        const auto [host, port] = parse_host_port(cfg_.tracker_tcp, "tracker.tcp");
        t = make_tcp_transport(host, port);
        source_desc_ = "tcp";
    }
    session_ = std::make_unique<TrackerSession>(std::move(t), sc);
    // The driver thread: keep the frame for recent_frames() (a copy under a short lock), then
    // hand it to the daemon's sink.
    session_->set_frame_callback([this](const TrackerFrame& f) {
        {
            std::lock_guard lk(recent_mu_);
            recent_.push_back(f);
            while (recent_.size() > kRecentFrames) recent_.pop_front();
        }
        if (sink_) sink_(f);
    });
    session_->start();
}

void TrackerModule::stop() {
    if (session_) session_->stop();
    if (sim_) sim_->stop();
}

TrackerStatus TrackerModule::status() const {
    if (!session_) return TrackerStatus{};
    // Readers (GET /api/status from every client, thousands a second under load) share one
    // snapshot per kStatusMaxAgeNs: TrackerSession::status() takes the session's mutex, which
    // the driver thread needs for every frame, and sorts its latency window under it; read per
    // request, it kept the driver waiting behind the HTTP threads (a lock convoy).
    std::lock_guard lk(cache_mu_);
    const std::int64_t now = steady_ns();
    if (!cache_ns_ || now - cache_ns_ >= kStatusMaxAgeNs) {
        cache_ = session_->status();
        if (sim_) cache_sim_ = {{"rate_hz", cfg_.tracker_sim_rate_hz}, {"replies", sim_->replies_sent()}, {"faults", sim_->total_faults()}};
        cache_ns_ = now;
    }
    return cache_;
}

nlohmann::json TrackerModule::status_json() const {
    if (!cfg_.tracker_enabled) return {{"enabled", false}, {"state", "disabled"}};
    const TrackerStatus st = status();
    nlohmann::json j{{"enabled", true},
                     {"source", cfg_.tracker_source},
                     {"source_detail", source_desc_},
                     {"state", state_name(st.state)},
                     {"transport", st.transport},
                     {"firmware", st.firmware},
                     {"api_revision", st.api_revision},
                     {"reply_mode", st.reply_mode},
                     {"baud", st.baud},
                     {"thread_nice", nice_},
                     {"frame_rate_hz", st.frame_rate_hz},
                     {"latency_p50_us", st.latency_p50_us},
                     {"latency_p99_us", st.latency_p99_us},
                     {"last_error", st.last_error},
                     {"counters",
                      {{"frames", st.frames},
                       {"duplicate_frames", st.duplicate_frames},
                       {"crc_errors", st.crc_errors},
                       {"resyncs", st.resyncs},
                       {"discarded_bytes", st.discarded_bytes},
                       {"timeouts", st.timeouts},
                       {"lost_replies", st.lost_replies},
                       {"protocol_errors", st.protocol_errors},
                       {"device_errors", st.device_errors},
                       {"warnings", st.warnings},
                       {"reconnects", st.reconnects},
                       {"resets", st.resets}}}};
    if (st.last_frame_steady_ns) j["last_frame_age_ms"] = (steady_ns() - st.last_frame_steady_ns) / 1e6;
    if (sim_) {
        std::lock_guard lk(cache_mu_);
        j["simulator"] = cache_sim_;
    }
    return j;
}

std::vector<TrackerFrame> TrackerModule::recent_frames(std::int64_t window_ns) const {
    const std::int64_t since = steady_ns() - window_ns;
    std::lock_guard lk(recent_mu_);
    std::vector<TrackerFrame> out;
    for (const auto& f : recent_)
        if (f.publish_steady_ns >= since) out.push_back(f);
    return out;
}

nlohmann::json TrackerModule::latest_json() const {
    if (!session_) return nullptr;
    const auto f = session_->latest();
    if (!f) return nullptr;
    return frame_to_json(*f);
}

bool TrackerModule::healthy(int stall_ms) const {
    if (!cfg_.tracker_enabled || !session_) return true;
    const TrackerStatus st = session_->status();
    if (st.state == TrackerStatus::State::stopped) return false;  // the driver thread ended
    if (st.state == TrackerStatus::State::streaming && st.last_frame_steady_ns &&
        steady_ns() - st.last_frame_steady_ns > std::int64_t(stall_ms) * 1'000'000)
        return false;
    return true;
}

}  // namespace cf::daemon
