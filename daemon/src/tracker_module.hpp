#pragma once
// The tracker module: owns the tracker driver session (and, with tracker.source "sim", the
// NDI Polaris simulator the driver talks to over a pty or TCP: the real driver code runs).
//
// Thread contract: start()/stop() from the daemon's main thread. The session's driver thread
// calls the frame sink (set before start()) for every new frame; it must be quick (the daemon
// queues the frame for the push thread). status_json() and latest_json() from any thread.
#include <atomic>
#include <condition_variable>
#include <deque>
#include <thread>
#include <functional>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <string>

#include "cortexfuse/daemon/config.hpp"
#include "cortexfuse/drivers/sim/tracker_sim.hpp"
#include "cortexfuse/drivers/tracker/frame_json.hpp"
#include "cortexfuse/drivers/tracker/session.hpp"

namespace cf::daemon {

using cf::tracker::frame_to_json;  // the push channel's and the CLI's tracker frame JSON

class TrackerModule {
public:
    explicit TrackerModule(const DaemonConfig& c);
    ~TrackerModule();
    void set_frame_sink(std::function<void(const cf::tracker::TrackerFrame&)> sink) { sink_ = std::move(sink); }
    /// Starts the simulator (if any) and the session. Throws ConfigError / std::runtime_error
    /// when the simulator or a ROM file cannot be set up (a missing device is not an error:
    /// the session keeps retrying and says so in its status).
    void start();
    void stop();
    bool enabled() const { return cfg_.tracker_enabled; }
    nlohmann::json status_json() const;
    nlohmann::json latest_json() const;
    /// For the watchdog: false when the session should stream and has not published a frame
    /// for `stall_ms` while in state streaming.
    bool healthy(int stall_ms) const;
    /// The session's status (stopped when disabled), at most kStatusMaxAgeNs old: one snapshot
    /// is shared by all readers so they do not contend with the driver thread for its mutex.
    cf::tracker::TrackerStatus status() const;
    static constexpr std::int64_t kStatusMaxAgeNs = 100'000'000;
    /// The frames published within the last `window_ns` (steady clock, publish time), oldest
    /// first, with staleness as published; at most kRecentFrames are kept (navigation averages
    /// the pointer tip over them). Any thread.
    std::vector<cf::tracker::TrackerFrame> recent_frames(std::int64_t window_ns) const;
    static constexpr std::size_t kRecentFrames = 512;  // 2 s at 250 Hz
    /// The in-process simulator (tracker.source sim, after start()), else nullptr; its scene
    /// can be controlled from any thread (TrackerSimulator::hold).
    cf::sim::TrackerSimulator* simulator() const { return sim_.get(); }

private:
    void start_threads();
    DaemonConfig cfg_;
    std::string priority_, sim_priority_;  // what the driver's / simulator's threads got (after start())
    // The kernel's tty workers at a raised priority (tty links only): kept by tty_thread_, which
    // re-applies it every second (the pool makes new workers) and restores it at stop().
    void keep_tty_workers();
    std::thread tty_thread_;
    std::mutex tty_mu_;
    std::condition_variable tty_cv_;
    bool tty_stop_ = false;
    std::atomic<std::size_t> tty_raised_{0};
    std::string tty_note_;  // under tty_mu_
    std::function<void(const cf::tracker::TrackerFrame&)> sink_;
    std::unique_ptr<cf::sim::TrackerSimulator> sim_;
    std::unique_ptr<cf::tracker::TrackerSession> session_;
    std::string source_desc_;
    mutable std::mutex recent_mu_;  // guards recent_ (the driver thread appends)
    std::deque<cf::tracker::TrackerFrame> recent_;
    mutable std::mutex cache_mu_;  // guards the three below
    mutable cf::tracker::TrackerStatus cache_;
    mutable nlohmann::json cache_sim_;
    mutable std::int64_t cache_ns_ = 0;
};

}  // namespace cf::daemon
