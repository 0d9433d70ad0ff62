#include "tracker_module.hpp"

#include "cortexfuse/daemon/log.hpp"
#include "cortexfuse/drivers/tracker/frame_json.hpp"
#include "cortexfuse/drivers/tracker/transport.hpp"

namespace cf::daemon {

using namespace cf::tracker;

TrackerModule::TrackerModule(const DaemonConfig& c) : cfg_(c) {}

TrackerModule::~TrackerModule() { stop(); }

void TrackerModule::start() {
    if (!cfg_.tracker_enabled) return;
    start_threads();
    // The driver's thread (and the simulator's) must be scheduled within the device's reply
    // deadline even when registrations and HTTP clients saturate the CPU: they run at SCHED_FIFO
    // tracker.rt_priority, or at nice tracker.nice where that is refused (no CAP_SYS_NICE /
    // RLIMIT_RTPRIO, RestrictRealtime=). Said once, here; never a reason not to start.
    const TrackerStatus st = session_->status();
    priority_ = st.thread_priority;
    if (!st.thread_priority_note.empty())
        log(LogLevel::warning, "tracker", "driver thread priority: " + st.thread_priority_note + "; it runs at " + st.thread_priority);
    const bool tty_link = cfg_.tracker_source == "serial" || (cfg_.tracker_source == "sim" && cfg_.tracker_sim_link == "pty");
    if (tty_link && cfg_.tracker_tty_worker_priority > 0) {
        tty_stop_ = false;
        tty_thread_ = std::thread([this] { keep_tty_workers(); });
    }
    if (sim_) {
        sim_priority_ = sim_->thread_priority();
        if (sim_priority_.find('(') != std::string::npos) log(LogLevel::warning, "tracker", "simulator thread priority: " + sim_priority_);
    }
}

void TrackerModule::start_threads() {
    const ThreadPriorityRequest priority{cfg_.tracker_rt_priority, cfg_.tracker_nice};
    SessionConfig sc;
    sc.baud = cfg_.tracker_baud;
    sc.thread_priority = priority;
    for (const auto& r : cfg_.tracker_roms) sc.tools.push_back(load_tool_definition(r));
    std::unique_ptr<Transport> t;
    if (cfg_.tracker_source == "sim") {
        cf::sim::TrackerSimConfig simc;
        simc.link = cfg_.tracker_sim_link == "tcp" ? cf::sim::TrackerSimConfig::Link::tcp : cf::sim::TrackerSimConfig::Link::pty;
        simc.tcp_port = 0;
        simc.frame_rate_hz = cfg_.tracker_sim_rate_hz;
        simc.seed = std::uint64_t(cfg_.tracker_sim_seed);
        simc.camera_tool = cfg_.tracker_sim_camera_tool;  // CF-CAMERA: the simulated camera may follow it (camera.sim_pose)
        // The simulator stands for the tracker's own hardware, which our load cannot slow down:
        // its thread gets the driver's priority (docs/tracker.md).
        simc.thread_priority = priority;
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
    if (tty_thread_.joinable()) {
        {
            std::lock_guard lk(tty_mu_);
            tty_stop_ = true;
        }
        tty_cv_.notify_all();
        tty_thread_.join();
    }
}

void TrackerModule::keep_tty_workers() {
    TtyWorkerPriority workers(cfg_.tracker_tty_worker_priority);
    bool said = false;
    std::unique_lock lk(tty_mu_);
    while (!tty_stop_) {
        lk.unlock();
        workers.apply();
        tty_raised_ = workers.raised();
        lk.lock();
        if (!workers.note().empty() && !said) {
            said = true;
            tty_note_ = workers.note();
            log(LogLevel::warning, "tracker", workers.note() + "; a busy CPU can then delay the tracker's bytes in the kernel (docs/tracker.md)");
        }
        tty_cv_.wait_for(lk, std::chrono::seconds(1), [&] { return tty_stop_; });
    }
    lk.unlock();
    workers.restore();
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
        if (sim_)
            cache_sim_ = {{"rate_hz", cfg_.tracker_sim_rate_hz}, {"replies", sim_->replies_sent()}, {"faults", sim_->total_faults()},
                          {"thread_priority", sim_priority_}};
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
                     {"thread_priority", priority_},
                     {"tty_workers_raised", tty_raised_.load()},
                     {"frame_rate_hz", st.frame_rate_hz},
                     {"latency_p50_us", st.latency_p50_us},
                     {"latency_p99_us", st.latency_p99_us},
                     {"reply_p50_us", st.reply_p50_us},
                     {"reply_p99_us", st.reply_p99_us},
                     {"reply_max_us", st.reply_max_us},
                     {"wake_late_max_us", st.wake_late_max_us},
                     {"callback_max_us", st.callback_max_us},
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
                       {"resets", st.resets},
                       {"frame_gaps", st.frame_gaps},
                       {"frames_missed", st.frames_missed},
                       {"out_of_order", st.out_of_order},
                       {"late_replies", st.late_replies},
                       {"requests", st.requests}}}};
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
