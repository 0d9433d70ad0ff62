// Tracker benchmarks, JSON on stdout:
//  1. codec throughput: BX frames (3 tools) decoded + parsed per second, fed in 64-byte reads,
//     side by side with the floor of the same bytes through CRC-16 only (reference);
//  2. latency from the last byte on the wire (simulator's write of the reply) to the frame
//     available from TrackerSession, and the driver-internal part (read -> published),
//     p50/p99, over a pty at 60 Hz.
// Median of --runs runs; peak RSS from getrusage.
#include <sys/resource.h>

#include <algorithm>
#include <chrono>
#include <cstring>
#include <iostream>
#include <mutex>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>

#include "cortexfuse/drivers/sim/tracker_sim.hpp"
#include "cortexfuse/drivers/tracker/session.hpp"

using namespace cf::tracker;
using Clock = std::chrono::steady_clock;

namespace {
std::vector<std::uint8_t> bx_stream(std::size_t frames) {
    std::vector<std::uint8_t> out;
    for (std::size_t f = 0; f < frames; ++f) {
        std::vector<std::uint8_t> body = {3};
        for (std::uint8_t h = 1; h <= 3; ++h) {
            body.push_back(h);
            body.push_back(h == 3 && f % 7 == 0 ? 0x02 : 0x01);
            if (body.back() == 0x01) {
                const float v[8] = {0.7071f, 0.f, 0.7071f, 0.f, 10.f * h, -20.f, -1500.f + f % 100, 0.12f};
                const auto* p = reinterpret_cast<const std::uint8_t*>(v);
                body.insert(body.end(), p, p + 32);
            }
            const std::uint32_t port = 0x31, fn = static_cast<std::uint32_t>(f);
            const auto* pp = reinterpret_cast<const std::uint8_t*>(&port);
            const auto* fp = reinterpret_cast<const std::uint8_t*>(&fn);
            body.insert(body.end(), pp, pp + 4);
            body.insert(body.end(), fp, fp + 4);
        }
        body.push_back(0);
        body.push_back(0);
        const auto framed = frame_binary_reply(body);
        out.insert(out.end(), framed.begin(), framed.end());
    }
    return out;
}

double median(std::vector<double> v) {
    std::sort(v.begin(), v.end());
    return v.empty() ? 0 : v[v.size() / 2];
}
double pct(std::vector<double> v, double p) {
    if (v.empty()) return 0;
    std::sort(v.begin(), v.end());
    return v[std::min(v.size() - 1, static_cast<std::size_t>(p * static_cast<double>(v.size())))];
}
}  // namespace

/// The session under CPU saturation: simulator and driver in this process over a pty or TCP
/// at 60 Hz while `load_threads` threads spin at nice 0; both I/O threads at `priority`. Per
/// frame the round trip is split with the simulator's timestamps: host->device (driver wrote
/// the request -> simulator read it: the tty layer's worker and the simulator's wake-up),
/// device (read -> reply written), device->host (written -> driver read the last byte).
nlohmann::json under_load(bool tcp, int load_threads, double seconds, const ThreadPriorityRequest& priority, int readers,
                          int tty_worker_priority) {
    // As the daemon does on a tty link (tracker.tty_worker_priority): the kernel's tty workers up.
    TtyWorkerPriority workers(tcp ? 0 : tty_worker_priority);
    workers.apply();
    cf::sim::TrackerSimConfig sc;
    sc.link = tcp ? cf::sim::TrackerSimConfig::Link::tcp : cf::sim::TrackerSimConfig::Link::pty;
    sc.thread_priority = priority;
    cf::sim::TrackerSimulator sim(sc);
    sim.start();
    SessionConfig cfg;
    cfg.tools = {ToolDefinition{"ref", cf::sim::make_synthetic_rom("CF-REFERENCE", 1, {{0, 0, 0}, {0, 50, 0}, {0, 100, 25}}), 'S'},
                 ToolDefinition{"ptr", cf::sim::make_synthetic_rom("CF-POINTER", 2, {{0, 0, 0}, {-30, 0, 0}, {-70, 0, 20}}), 'D'}};
    cfg.thread_priority = priority;
    TrackerSession s(tcp ? make_tcp_transport("127.0.0.1", sim.tcp_port()) : make_serial_transport(sim.slave_path()), cfg);
    std::mutex mu;
    std::vector<double> h2d_ms, dev_ms, d2h_ms, rtt_ms;
    std::uint64_t frames = 0, missed = 0, gaps = 0, late = 0;
    std::atomic<bool> counting{false};
    s.set_frame_callback([&](const TrackerFrame& f) {
        if (!counting) return;
        const auto rd = sim.request_read_ns(f.frame_number);
        const auto wr = sim.reply_written_ns(f.frame_number);
        std::lock_guard lk(mu);
        ++frames;
        missed += f.frames_missed_before;
        gaps += f.frames_missed_before > 0;
        late += f.late;
        if (f.request_steady_ns) rtt_ms.push_back(static_cast<double>(f.receive_steady_ns - f.request_steady_ns) / 1e6);
        if (rd && wr && f.request_steady_ns && *rd >= f.request_steady_ns) {
            h2d_ms.push_back(static_cast<double>(*rd - f.request_steady_ns) / 1e6);
            dev_ms.push_back(static_cast<double>(*wr - *rd) / 1e6);
            d2h_ms.push_back(static_cast<double>(f.receive_steady_ns - *wr) / 1e6);
        }
    });
    s.start();
    if (!s.wait_frame(0, std::chrono::seconds(10))) return {{"error", "no frame within 10 s"}};
    const TrackerStatus st0 = s.status();
    std::atomic<bool> stop_load{false};
    std::vector<std::thread> load;
    for (int i = 0; i < load_threads; ++i)
        load.emplace_back([&] {
            volatile std::uint64_t x = 0;
            while (!stop_load) x = x + 1;
        });
    // Readers of the session's and the simulator's status at normal priority, as the daemon's
    // HTTP threads read them (each at 10 Hz).
    for (int i = 0; i < readers; ++i)
        load.emplace_back([&] {
            while (!stop_load) {
                const auto st = s.status();
                const auto nf = sim.total_faults();
                if (st.frames == 0 && nf == 1) std::cerr << "";
                std::this_thread::sleep_for(std::chrono::milliseconds(100));
            }
        });
    counting = true;
    const auto t0 = Clock::now();
    while (Clock::now() - t0 < std::chrono::duration<double>(seconds)) {
        std::this_thread::sleep_for(std::chrono::milliseconds(500));
        workers.apply();
    }
    counting = false;
    const double window = std::chrono::duration<double>(Clock::now() - t0).count();
    stop_load = true;
    for (auto& t : load) t.join();
    const TrackerStatus st = s.status();
    const std::string sim_prio = sim.thread_priority();
    s.stop();
    sim.stop();
    std::lock_guard lk(mu);
    auto pcts = [](const std::vector<double>& v) {
        return nlohmann::json{{"p50", pct(v, 0.5)}, {"p99", pct(v, 0.99)}, {"max", v.empty() ? 0.0 : *std::max_element(v.begin(), v.end())}};
    };
    return {{"transport", tcp ? "tcp" : "pty"}, {"load_threads", load_threads}, {"status_readers", readers}, {"seconds", window},
            {"driver_priority", st.thread_priority}, {"tty_workers_raised", workers.raised()}, {"tty_workers_note", workers.note()}, {"driver_priority_note", st.thread_priority_note}, {"simulator_priority", sim_prio},
            {"frames", frames}, {"rate_hz", static_cast<double>(frames) / window}, {"gaps", gaps}, {"frames_missed", missed},
            {"late_replies", late}, {"timeouts", st.timeouts - st0.timeouts}, {"resets", st.resets - st0.resets},
            {"reconnects", st.reconnects - st0.reconnects}, {"out_of_order", st.out_of_order - st0.out_of_order},
            {"round_trip_ms", pcts(rtt_ms)}, {"host_to_device_ms", pcts(h2d_ms)}, {"device_ms", pcts(dev_ms)},
            {"device_to_host_ms", pcts(d2h_ms)}};
}

int main(int argc, char** argv) {
    int runs = 5;
    double latency_s = 5;
    int load_threads = -1;
    double load_s = 20;
    std::string link = "pty";
    int readers = 0, tty_workers = 10;
    ThreadPriorityRequest prio{20, -10};
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        if (a == "--runs" && i + 1 < argc) runs = std::clamp(std::atoi(argv[++i]), 1, 50);
        else if (a == "--latency-s" && i + 1 < argc) latency_s = std::clamp(std::atof(argv[++i]), 1.0, 120.0);
        else if (a == "--load-threads" && i + 1 < argc) load_threads = std::clamp(std::atoi(argv[++i]), 0, 256);
        else if (a == "--load-s" && i + 1 < argc) load_s = std::clamp(std::atof(argv[++i]), 1.0, 600.0);
        else if (a == "--link" && i + 1 < argc && (std::string(argv[i + 1]) == "pty" || std::string(argv[i + 1]) == "tcp")) link = argv[++i];
        else if (a == "--rt-priority" && i + 1 < argc) prio.realtime_priority = std::atoi(argv[++i]);
        else if (a == "--nice" && i + 1 < argc) prio.nice = std::atoi(argv[++i]);
        else if (a == "--tty-worker-priority" && i + 1 < argc) tty_workers = std::clamp(std::atoi(argv[++i]), 0, 99);
        else if (a == "--status-readers" && i + 1 < argc) readers = std::clamp(std::atoi(argv[++i]), 0, 64);
        else {
            std::cerr << "usage: cf_bench_tracker [--runs N] [--latency-s S]\n"
                         "       cf_bench_tracker --load-threads N [--load-s S] [--link pty|tcp] [--rt-priority P] [--nice N] [--status-readers N] [--tty-worker-priority P] [--runs N]\n"
                         "  (the second form: the session under N spinning threads, per run and the median)\n";
            return 2;
        }
    }
    try {
        prio.validate();
    } catch (const std::exception& e) {
        std::cerr << "cf_bench_tracker: " << e.what() << "\n";
        return 2;
    }
    if (load_threads >= 0) {
        nlohmann::json all = nlohmann::json::array();
        std::vector<double> rate, gaps, missed, timeouts, resets, rtt99;
        for (int r = 0; r < runs; ++r) {
            auto j = under_load(link == "tcp", load_threads, load_s, prio, readers, tty_workers);
            std::cerr << j.dump() << "\n";
            if (j.contains("error")) {
                std::cout << j.dump(1) << std::endl;
                return 1;
            }
            rate.push_back(j["rate_hz"]);
            gaps.push_back(j["gaps"]);
            missed.push_back(j["frames_missed"]);
            timeouts.push_back(j["timeouts"]);
            resets.push_back(j["resets"]);
            rtt99.push_back(j["round_trip_ms"]["p99"]);
            all.push_back(std::move(j));
        }
        rusage ru{};
        getrusage(RUSAGE_SELF, &ru);
        std::cout << nlohmann::json{{"benchmark", "tracker_under_load"},
                                    {"runs", all},
                                    {"median", {{"rate_hz", median(rate)}, {"gaps", median(gaps)}, {"frames_missed", median(missed)},
                                                {"timeouts", median(timeouts)}, {"resets", median(resets)}, {"round_trip_p99_ms", median(rtt99)}}},
                                    {"peak_rss_mb", static_cast<double>(ru.ru_maxrss) / 1024.0}}
                         .dump(1)
                  << std::endl;
        return 0;
    }
    const std::size_t n_frames = 200'000;
    const auto bytes = bx_stream(n_frames);
    std::vector<double> decode_fps, crc_fps;
    std::uint64_t sink = 0;
    for (int r = 0; r < runs; ++r) {
        auto t0 = Clock::now();
        ReplyDecoder dec;
        std::size_t got = 0;
        for (std::size_t i = 0; i < bytes.size(); i += 64) {
            dec.feed(std::span<const std::uint8_t>(bytes.data() + i, std::min<std::size_t>(64, bytes.size() - i)));
            while (auto rep = dec.next()) {
                const auto tr = parse_bx(rep->body, 0x0801);
                sink += tr.tools.size();
                ++got;
            }
        }
        double s = std::chrono::duration<double>(Clock::now() - t0).count();
        if (got != n_frames) {
            std::cerr << "decoded " << got << " of " << n_frames << "\n";
            return 1;
        }
        decode_fps.push_back(static_cast<double>(got) / s);
        // Reference: the same bytes through the CRC only (what any correct decoder must do at least).
        t0 = Clock::now();
        std::uint16_t c = 0;
        for (std::size_t i = 0; i < bytes.size(); i += 64) c ^= crc16(std::span<const std::uint8_t>(bytes.data() + i, std::min<std::size_t>(64, bytes.size() - i)));
        s = std::chrono::duration<double>(Clock::now() - t0).count();
        sink += c;
        crc_fps.push_back(static_cast<double>(n_frames) / s);
    }

    // Latency: simulator on a pty, session streaming at 60 Hz, no faults.
    cf::sim::TrackerSimConfig sc;
    sc.reply_delay = std::chrono::milliseconds(0);
    cf::sim::TrackerSimulator sim(sc);
    sim.start();
    SessionConfig cfg;
    cfg.tools = {ToolDefinition{"ref", cf::sim::make_synthetic_rom("CF-REFERENCE", 1, {{0, 0, 0}, {0, 50, 0}, {0, 100, 25}}), 'S'},
                 ToolDefinition{"ptr", cf::sim::make_synthetic_rom("CF-POINTER", 2, {{0, 0, 0}, {-30, 0, 0}, {-70, 0, 20}}), 'D'}};
    cfg.poll_interval = std::chrono::milliseconds(4);
    TrackerSession s(make_serial_transport(sim.slave_path()), cfg);
    std::vector<double> wire_us, internal_us;
    std::mutex mu;
    s.set_frame_callback([&](const TrackerFrame& f) {
        const auto w = sim.reply_written_ns(f.frame_number);
        std::lock_guard lk(mu);
        internal_us.push_back(static_cast<double>(f.publish_steady_ns - f.receive_steady_ns) / 1000.0);
        if (w) wire_us.push_back(static_cast<double>(f.publish_steady_ns - *w) / 1000.0);
    });
    s.start();
    s.wait_frame(0, std::chrono::seconds(10));
    {
        std::lock_guard lk(mu);
        wire_us.clear();
        internal_us.clear();
    }
    std::this_thread::sleep_for(std::chrono::duration<double>(latency_s));
    const auto st = s.status();
    s.stop();
    sim.stop();

    rusage ru{};
    getrusage(RUSAGE_SELF, &ru);
    std::lock_guard lk(mu);
    nlohmann::json j{
        {"benchmark", "tracker"},
        {"codec", {{"frames_per_run", n_frames}, {"bytes_per_frame", static_cast<double>(bytes.size()) / n_frames}, {"runs", runs},
                   {"bx_decode_frames_per_s_median", median(decode_fps)}, {"reference_crc_only_frames_per_s_median", median(crc_fps)},
                   {"decode_vs_crc_only_ratio", median(crc_fps) / median(decode_fps)}}},
        {"latency", {{"transport", "pty"}, {"frame_rate_hz", sc.frame_rate_hz}, {"seconds", latency_s}, {"frames", wire_us.size()},
                     {"wire_to_frame_us_p50", pct(wire_us, 0.5)}, {"wire_to_frame_us_p99", pct(wire_us, 0.99)},
                     {"read_to_frame_us_p50", pct(internal_us, 0.5)}, {"read_to_frame_us_p99", pct(internal_us, 0.99)},
                     {"session_frame_rate_hz", st.frame_rate_hz}}},
        {"peak_rss_mb", static_cast<double>(ru.ru_maxrss) / 1024.0},
        {"sink", sink % 2}};
    std::cout << j.dump(1) << std::endl;
    return 0;
}
