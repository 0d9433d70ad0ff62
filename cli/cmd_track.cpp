// cortexfuse track: a real Polaris session (serial or TCP) printing one JSON line per frame.
#include <iostream>
#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "cortexfuse/drivers/tracker/frame_json.hpp"
#include "cortexfuse/drivers/tracker/session.hpp"

namespace cf::cli {

namespace {
struct TrackCmd {
    std::string serial, tcp;
    std::vector<std::string> roms;
    int frames = 100, baud = 115200;
    double timeout_s = 30;
    bool json = false, tx = false, bx = false, discover = false;
};

}  // namespace

void add_track(CLI::App& app) {
    auto o = std::make_shared<TrackCmd>();
    auto* sub = app.add_subcommand("track", "Run an NDI Polaris session and print frames (one JSON line each with --json)");
    auto* serial = sub->add_option("--serial", o->serial, "Serial port (a tty, a USB-serial adapter, or a simulator's pty)");
    auto* tcp = sub->add_option("--tcp", o->tcp, "HOST:PORT of a Vega (port 8765) or a simulator");
    serial->excludes(tcp);
    sub->add_flag("--discover", o->discover, "List USB-serial adapters and exit");
    sub->add_option("--rom", o->roms, "Passive tool definition (.rom), repeatable; the file stem names the tool");
    sub->add_option("--frames", o->frames, "Stop after this many frames (1..10000000)")->capture_default_str();
    sub->add_option("--baud", o->baud, "Serial rate after COMM: 9600, 38400, 57600, 115200, 230400 or 921600")->capture_default_str();
    sub->add_option("--timeout-s", o->timeout_s, "Give up when the frames have not all come within this time")->capture_default_str();
    sub->add_flag("--json", o->json, "One JSON object per frame on stdout");
    auto* tx = sub->add_flag("--tx", o->tx, "Force TX (text) replies");
    auto* bx = sub->add_flag("--bx", o->bx, "Force BX (binary) replies (default: BX unless the firmware needs TX)");
    tx->excludes(bx);
    sub->callback([o] {
        run_guarded("track", [&] {
            using namespace cf::tracker;
            if (o->discover) {
                for (const auto& p : discover_serial_ports()) std::cout << p << "\n";
                return 0;
            }
            if (o->serial.empty() == o->tcp.empty()) throw ConfigError("track", "give exactly one of --serial PATH or --tcp HOST:PORT");
            if (o->frames < 1 || o->frames > 10'000'000) throw ConfigError("--frames " + std::to_string(o->frames), "must be 1..10000000");
            if (o->timeout_s <= 0 || o->timeout_s > 86400) throw ConfigError("--timeout-s", "must be in (0, 86400]");
            SessionConfig cfg;
            cfg.baud = o->baud;
            cfg.reply_mode = o->tx ? SessionConfig::ReplyMode::tx : o->bx ? SessionConfig::ReplyMode::bx : SessionConfig::ReplyMode::automatic;
            for (const auto& r : o->roms) cfg.tools.push_back(load_tool_definition(r));
            std::unique_ptr<Transport> t;
            if (!o->serial.empty()) t = make_serial_transport(o->serial);
            else {
                const auto [host, port] = parse_host_port(o->tcp, "--tcp");
                t = make_tcp_transport(host, port);
            }
            TrackerSession s(std::move(t), cfg);
            s.start();
            const auto deadline = std::chrono::steady_clock::now() + std::chrono::duration<double>(o->timeout_s);
            std::uint64_t seq = 0;
            int got = 0;
            while (got < o->frames && std::chrono::steady_clock::now() < deadline) {
                const auto f = s.wait_frame(seq, std::chrono::milliseconds(200));
                if (!f) continue;
                seq = f->sequence;
                ++got;
                if (o->json) std::cout << cf::tracker::frame_to_json(*f).dump() << "\n";
                else {
                    std::cout << "frame " << f->frame_number;
                    for (const auto& tool : f->tools) std::cout << "  " << tool.name << ":" << cf::tracker::tool_status_name(tool.status) << (tool.stale ? "(stale)" : "");
                    std::cout << "\n";
                }
            }
            std::cout.flush();
            s.stop();
            const auto st = s.status();
            nlohmann::json sj{{"state", state_name(st.state)}, {"transport", st.transport}, {"reply_mode", st.reply_mode},
                              {"baud", st.baud}, {"frames", st.frames}, {"crc_errors", st.crc_errors}, {"resyncs", st.resyncs},
                              {"timeouts", st.timeouts}, {"lost_replies", st.lost_replies}, {"reconnects", st.reconnects}, {"resets", st.resets},
                              {"latency_p50_us", st.latency_p50_us}, {"latency_p99_us", st.latency_p99_us}, {"last_error", st.last_error}};
            std::cerr << sj.dump() << "\n";
            if (got < o->frames)
                throw std::runtime_error(st.transport + ": only " + std::to_string(got) + " of " + std::to_string(o->frames) +
                                         " frames within " + std::to_string(o->timeout_s) + " s (last error: " + st.last_error + ")");
            return 0;
        });
    });
}

}  // namespace cf::cli
