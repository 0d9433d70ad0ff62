// cortexfused: the thin executable around cf_daemon. Reads the configuration, starts the
// daemon, talks to systemd (READY=1, STATUS=, WATCHDOG=1 from a thread that checks the
// modules, STOPPING=1), and stops gracefully on SIGTERM / SIGINT (exit 0).
#include <systemd/sd-daemon.h>

#include <CLI/CLI.hpp>
#include <atomic>
#include <chrono>
#include <csignal>
#include <cstdlib>
#include <iostream>
#include <thread>

#include "cortexfuse/core/cpu_baseline.hpp"
#include "cortexfuse/daemon/config.hpp"
#include "cortexfuse/daemon/daemon.hpp"
#include "cortexfuse/daemon/log.hpp"

using namespace cf::daemon;

// A CPU without the build's -march features: one line and exit 69 before anything runs (docs/packaging.md).
CF_CPU_BASELINE_CHECK("cortexfused")

int main(int argc, char** argv) {
    CLI::App app{"cortexfused: the CortexFuse daemon (HTTP API, push channel, tracker, renderer, jobs)"};
    std::string config_path, listen, state_dir;
    bool print_default = false, print_doc = false, check_only = false;
    app.add_option("--config", config_path, "Configuration file (JSON); none: the embedded defaults (simulators, bundled MRI)");
    app.add_option("--listen", listen, "Override http.listen (HOST:PORT)");
    app.add_option("--state-dir", state_dir, "Override state_dir");
    app.add_flag("--print-default-config", print_default, "Print the embedded default configuration and exit");
    app.add_flag("--print-config-doc", print_doc, "Print the table of configuration options (markdown) and exit");
    app.add_flag("--check-config", check_only, "Validate the configuration and exit (0: valid)");
    app.set_version_flag("--version", std::string("cortexfused ") + kVersion);
    CLI11_PARSE(app, argc, argv);

    if (print_default) {
        std::cout << default_config_json().dump(2) << std::endl;
        return 0;
    }
    if (print_doc) {
        std::cout << config_markdown_table();
        return 0;
    }
    if (const char* l = std::getenv("CF_LOG_LEVEL"); l && std::string(l) == "debug") set_log_level(LogLevel::debug);

    DaemonConfig cfg;
    try {
        cfg = config_path.empty() ? parse_config(default_config_json(), "(embedded defaults)") : load_config_file(config_path);
        if (!listen.empty() || !state_dir.empty()) {
            nlohmann::json j = to_json(cfg);
            if (!listen.empty()) j["http"]["listen"] = listen;
            if (!state_dir.empty()) j["state_dir"] = state_dir;
            cfg = parse_config(j, config_path.empty() ? "(command line)" : config_path + " + command line");
        }
    } catch (const std::exception& e) {
        std::cerr << "cortexfused: " << e.what() << std::endl;
        return 2;
    }
    if (check_only) {
        std::cout << "configuration ok" << std::endl;
        return 0;
    }

    // Signals are taken by sigwait on this thread: block them before any thread starts.
    sigset_t set;
    sigemptyset(&set);
    sigaddset(&set, SIGTERM);
    sigaddset(&set, SIGINT);
    pthread_sigmask(SIG_BLOCK, &set, nullptr);
    std::signal(SIGPIPE, SIG_IGN);  // a client that went away must not end the daemon

    Daemon daemon(cfg);
    try {
        daemon.start();
    } catch (const std::exception& e) {
        log(LogLevel::error, "daemon", std::string("cannot start: ") + e.what());
        sd_notifyf(0, "STATUS=cannot start: %s", e.what());
        return 1;
    }
    // The address on stdout, for scripts (and people) that started it in the foreground.
    std::cout << "cortexfused: listening on http://" << cfg.listen.substr(0, cfg.listen.rfind(':')) << ":" << daemon.port() << "/" << std::endl;
    sd_notifyf(0, "READY=1\nSTATUS=%s", daemon.status_line().c_str());

    // Watchdog: ping only while every module is alive; STATUS= kept current.
    std::atomic<bool> stop{false};
    std::uint64_t watchdog_usec = 0;
    const bool watchdog = sd_watchdog_enabled(0, &watchdog_usec) > 0;
    std::thread wd([&] {
        const auto period = watchdog ? std::chrono::microseconds(watchdog_usec / 2) : std::chrono::microseconds(cfg.watchdog_check_ms * 1000);
        const auto check = std::min(period, std::chrono::microseconds(cfg.watchdog_check_ms * 1000));
        auto next_ping = std::chrono::steady_clock::now();
        bool was_healthy = true;
        while (!stop.load()) {
            std::string why;
            const bool ok = daemon.healthy(&why);
            if (ok != was_healthy)
                log(ok ? LogLevel::notice : LogLevel::error, "watchdog", ok ? "modules healthy again" : "unhealthy: " + why);
            was_healthy = ok;
            if (std::chrono::steady_clock::now() >= next_ping) {
                if (ok && watchdog) sd_notify(0, "WATCHDOG=1");
                sd_notifyf(0, "STATUS=%s", ok ? daemon.status_line().c_str() : ("unhealthy: " + why).c_str());
                next_ping = std::chrono::steady_clock::now() + period;
            }
            for (auto t = std::chrono::steady_clock::now() + check; !stop.load() && std::chrono::steady_clock::now() < t;)
                std::this_thread::sleep_for(std::chrono::milliseconds(20));
        }
    });

    int sig = 0;
    sigwait(&set, &sig);
    log(LogLevel::info, "daemon", std::string("signal ") + (sig == SIGTERM ? "SIGTERM" : "SIGINT") + ": stopping");
    sd_notify(0, "STOPPING=1\nSTATUS=stopping");
    stop = true;
    wd.join();
    const bool clean = daemon.stop();
    if (!clean) {
        // A job ignored its cancel within jobs.stop_timeout_ms: exit without waiting for it.
        std::cout.flush();
        std::_Exit(0);
    }
    return 0;
}
