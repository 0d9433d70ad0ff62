#include "tracker_module.hpp"

#include "cortexfuse/drivers/tracker/transport.hpp"

namespace cf::daemon {

using namespace cf::tracker;

namespace {
const char* tool_status(ToolReading::Status s) {
    using S = ToolReading::Status;
    return s == S::ok ? "ok" : s == S::missing ? "missing" : s == S::disabled ? "disabled" : "unoccupied";
}
}  // namespace

nlohmann::json frame_to_json(const TrackerFrame& f) {
    nlohmann::json j{{"seq", f.sequence},
                     {"frame", f.frame_number},
                     {"system_status", f.system_status},
                     {"receive_steady_ns", f.receive_steady_ns},
                     {"latency_us", (f.publish_steady_ns - f.receive_steady_ns) / 1000.0}};
    j["tools"] = nlohmann::json::array();
    for (const auto& t : f.tools) {
        nlohmann::json tj{{"name", t.name}, {"handle", t.handle}, {"status", tool_status(t.status)}, {"stale", t.stale},
                          {"out_of_volume", t.out_of_volume}, {"partially_out_of_volume", t.partially_out_of_volume}};
        if (t.T_tracker_from_tool) {
            const Eigen::Quaterniond q(t.T_tracker_from_tool->linear());
            const Eigen::Vector3d p = t.T_tracker_from_tool->translation();
            tj["q_wxyz"] = {q.w(), q.x(), q.y(), q.z()};
            tj["t_mm"] = {p.x(), p.y(), p.z()};
            tj["rms_mm"] = t.rms_error_mm;
        }
        j["tools"].push_back(tj);
    }
    return j;
}

TrackerModule::TrackerModule(const DaemonConfig& c) : cfg_(c) {}

TrackerModule::~TrackerModule() { stop(); }

void TrackerModule::start() {
    if (!cfg_.tracker_enabled) return;
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
    if (sink_) session_->set_frame_callback(sink_);
    session_->start();
}

void TrackerModule::stop() {
    if (session_) session_->stop();
    if (sim_) sim_->stop();
}

TrackerStatus TrackerModule::status() const { return session_ ? session_->status() : TrackerStatus{}; }

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
    if (sim_) j["simulator"] = {{"rate_hz", cfg_.tracker_sim_rate_hz}, {"replies", sim_->replies_sent()}, {"faults", sim_->total_faults()}};
    return j;
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
