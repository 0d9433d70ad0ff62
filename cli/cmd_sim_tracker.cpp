// cortexfuse sim tracker: the NDI Polaris simulator on a pty (prints the slave path) or on
// TCP, with a scene and fault options. Runs until --duration-s or SIGINT/SIGTERM.
#include <csignal>
#include <iostream>
#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "cortexfuse/drivers/sim/tracker_sim.hpp"
#include "cortexfuse/drivers/tracker/transport.hpp"

namespace cf::cli {

namespace {
struct SimTrackerCmd {
    bool pty = false;
    std::string tcp, link, trajectory, faults, fault_script, firmware = "Polaris Spectra Rev 008";
    double rate_hz = 60, noise_mm = 0.05, noise_deg = 0.05, duration_s = 0;
    std::uint64_t seed = 1;
    bool camera = false;
};

CLI::App* sim_group(CLI::App& app) {
    try {
        return app.get_subcommand("sim");
    } catch (const CLI::OptionNotFound&) {
        auto* s = app.add_subcommand("sim", "Hardware-in-the-loop simulators speaking the real wire protocols");
        s->require_subcommand(1);
        return s;
    }
}
}  // namespace

void add_sim_tracker(CLI::App& app) {
    auto o = std::make_shared<SimTrackerCmd>();
    auto* sub = sim_group(app)->add_subcommand("tracker", "NDI Polaris simulator (combined API over a pty or TCP)");
    auto* pty = sub->add_flag("--pty", o->pty, "Serve on a pseudo-terminal; prints the slave path");
    auto* tcp = sub->add_option("--tcp", o->tcp, "Serve on HOST:PORT (e.g. 127.0.0.1:8765; port 0 picks one)");
    pty->excludes(tcp);
    sub->add_option("--link", o->link, "With --pty: keep this symlink pointing at the current slave (it changes after a disconnect fault)");
    sub->add_option("--rate", o->rate_hz, "Frame rate in Hz: 20, 60 or 250")->capture_default_str();
    sub->add_option("--noise-mm", o->noise_mm, "Translation noise per axis (sigma, mm)")->capture_default_str();
    sub->add_option("--noise-deg", o->noise_deg, "Rotation noise (sigma, degrees)")->capture_default_str();
    sub->add_option("--seed", o->seed, "Seed for noise, visibility and random faults")->capture_default_str();
    sub->add_flag("--camera", o->camera, "Add a tracked camera (CF-CAMERA) to the scene");
    sub->add_option("--trajectory", o->trajectory, "Trajectory file: '<t_s> <part> tx ty tz qw qx qy qz' lines, looped");
    sub->add_option("--faults", o->faults, "Random faults, e.g. bit_flip=0.02,drop=0.01,truncate=0.01,garbage=0.01,delay=0.01,"
                                           "split=0.01,stale_bytes=0.01,disconnects_per_min=2,power_cycles_per_min=1,tool_missing=0.1,out_of_volume=0.05");
    sub->add_option("--fault-script", o->fault_script, "Scripted faults: '<at_s> <fault> [part duration_s]' lines");
    sub->add_option("--firmware", o->firmware, "Firmware in VER's Freeze Tag (e.g. 'Polaris Vicra Rev 007' makes drivers fall back to TX)")->capture_default_str();
    sub->add_option("--duration-s", o->duration_s, "Stop after this many seconds (0: until interrupted)")->capture_default_str();
    sub->callback([o] {
        run_guarded("sim tracker", [&] {
            if (!o->pty && o->tcp.empty()) throw std::invalid_argument("give --pty or --tcp HOST:PORT");
            if (o->duration_s < 0) throw std::invalid_argument("--duration-s must be >= 0");
            cf::sim::TrackerSimConfig c;
            c.link = o->pty ? cf::sim::TrackerSimConfig::Link::pty : cf::sim::TrackerSimConfig::Link::tcp;
            c.pty_link = o->link;
            if (!o->tcp.empty()) {
                const auto [host, port] = cf::tracker::parse_host_port(o->tcp, "--tcp", true);
                c.tcp_host = host;
                c.tcp_port = port;
            }
            c.frame_rate_hz = o->rate_hz;
            c.noise_mm = o->noise_mm;
            c.noise_deg = o->noise_deg;
            c.seed = o->seed;
            c.camera_tool = o->camera;
            c.trajectory_file = o->trajectory;
            c.firmware = o->firmware;
            if (!o->faults.empty()) c.faults = cf::sim::FaultRates::parse(o->faults);
            if (!o->fault_script.empty()) c.script = cf::sim::load_fault_script(o->fault_script);

            sigset_t set;
            sigemptyset(&set);
            sigaddset(&set, SIGINT);
            sigaddset(&set, SIGTERM);
            pthread_sigmask(SIG_BLOCK, &set, nullptr);  // before the simulator thread starts

            cf::sim::TrackerSimulator sim(c);
            sim.start();
            if (o->pty) std::cout << (o->link.empty() ? sim.slave_path() : o->link) << std::endl;
            else std::cout << "tcp " << c.tcp_host << ":" << sim.tcp_port() << std::endl;
            const auto t0 = std::chrono::steady_clock::now();
            for (;;) {
                timespec ts{0, 100'000'000};
                if (sigtimedwait(&set, nullptr, &ts) > 0) break;
                if (o->duration_s > 0 && std::chrono::steady_clock::now() - t0 >= std::chrono::duration<double>(o->duration_s)) break;
            }
            sim.stop();
            nlohmann::json j;
            for (const auto& [k, v] : sim.fault_counts()) j["faults"][cf::sim::fault_name(k)] = v;
            j["replies"] = sim.replies_sent();
            std::cerr << j.dump() << std::endl;
            return 0;
        });
    });
}

}  // namespace cf::cli
