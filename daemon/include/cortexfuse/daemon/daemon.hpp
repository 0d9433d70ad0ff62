#pragma once
// cortexfused as a library (the executable is a thin main around it; tests start it
// in-process on port 0 with a temporary state folder).
//
// Modules, each with its own thread(s) and a status object served by GET /api/status:
//   tracker  the tracker driver session (and the simulator it talks to, when configured)
//   camera   the configured camera backend (opened on first use)
//   render   the MRI and the renderers (GL off-screen, else CPU), one render thread
//   jobs     the job queue: one worker thread per kind (phantom, register)
//   http     civetweb's connection threads and the push thread
//   watchdog (main.cpp / systemd): checks healthy() and pings systemd
//
// Thread contract: construct, start(), then stop() from one thread (main); port(), healthy(),
// status_json() from any thread. stop() is idempotent and is also run by the destructor.
#include <chrono>
#include <memory>
#include <nlohmann/json.hpp>
#include <string>

#include "cortexfuse/daemon/config.hpp"

namespace cf::daemon {

extern const char* const kVersion;

class Daemon {
public:
    explicit Daemon(DaemonConfig config);
    ~Daemon();
    Daemon(const Daemon&) = delete;
    Daemon& operator=(const Daemon&) = delete;

    /// Creates the state folder, starts the modules and the HTTP server. Throws
    /// std::runtime_error naming the failing module and option (port in use, unusable state
    /// folder, a tracker ROM that cannot be read).
    void start();
    /// Graceful stop: stop accepting requests, cancel running jobs and wait for them up to
    /// jobs.stop_timeout_ms, stop the tracker, the renderer. Returns false when a job had to
    /// be abandoned (it did not end within the timeout).
    bool stop();

    /// The port the HTTP server listens on (resolved when http.listen asked for port 0).
    int port() const;
    /// Every module's thread alive and the tracker not stalled (for the systemd watchdog).
    /// `why` gets the first problem.
    bool healthy(std::string* why = nullptr) const;
    nlohmann::json status_json() const;
    /// One line for systemd's STATUS= ("tracker streaming 60 Hz, 0 jobs running, http :8080").
    std::string status_line() const;
    const DaemonConfig& config() const;

private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

/// The state folder a configuration resolves to (state_dir, else $STATE_DIRECTORY, else
/// ~/.local/state/cortexfused).
std::string resolve_state_dir(const DaemonConfig& c);

}  // namespace cf::daemon
