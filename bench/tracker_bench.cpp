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

int main(int argc, char** argv) {
    int runs = 5;
    double latency_s = 5;
    for (int i = 1; i < argc; ++i) {
        const std::string a = argv[i];
        if (a == "--runs" && i + 1 < argc) runs = std::clamp(std::atoi(argv[++i]), 1, 50);
        else if (a == "--latency-s" && i + 1 < argc) latency_s = std::clamp(std::atof(argv[++i]), 1.0, 120.0);
        else {
            std::cerr << "usage: cf_bench_tracker [--runs N] [--latency-s S]\n";
            return 2;
        }
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
