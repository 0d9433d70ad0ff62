// The device side of the NDI combined API (fact sheet §9): states, handles, .rom storage,
// BX/TX bodies, baud switching, break detection on a pty, and fault injection.
#include "cortexfuse/drivers/sim/tracker_sim.hpp"

#include <arpa/inet.h>
#include <fcntl.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <termios.h>
#include <unistd.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <future>
#include <random>
#include <set>
#include <sstream>
#include <stdexcept>
#include <tuple>

#include "cortexfuse/drivers/tracker/ndi_codec.hpp"

namespace cf::sim {

namespace fs = std::filesystem;
using cf::tracker::crc16;
using cf::tracker::frame_ascii_reply;

namespace {

std::int64_t now_ns() {
    return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

std::uint64_t mix(std::uint64_t x) {  // splitmix64 finaliser
    x += 0x9E3779B97F4A7C15ull;
    x = (x ^ (x >> 30)) * 0xBF58476D1CE4E5B9ull;
    x = (x ^ (x >> 27)) * 0x94D049BB133111EBull;
    return x ^ (x >> 31);
}
double uniform01(std::uint64_t h) { return static_cast<double>(h >> 11) * (1.0 / 9007199254740992.0); }
double gauss(std::uint64_t h) {
    const double u1 = std::max(uniform01(mix(h)), 1e-300), u2 = uniform01(mix(h ^ 0xABCDEF));
    return std::sqrt(-2.0 * std::log(u1)) * std::cos(2.0 * M_PI * u2);
}

std::string hex2(unsigned v) { return cf::tracker::crc_hex(static_cast<std::uint16_t>(v & 0xFF)).substr(2); }

void put_f32(std::vector<std::uint8_t>& b, double v) {
    const float f = static_cast<float>(v);
    std::uint32_t u;
    std::memcpy(&u, &f, 4);
    for (int k = 0; k < 4; ++k) b.push_back(static_cast<std::uint8_t>(u >> (8 * k)));
}
void put_u32(std::vector<std::uint8_t>& b, std::uint32_t u) {
    for (int k = 0; k < 4; ++k) b.push_back(static_cast<std::uint8_t>(u >> (8 * k)));
}

std::string signed_text(double v, int digits, double scale) {
    const long n = std::lround(std::abs(v) * scale);
    std::ostringstream s;
    s << (v < 0 && n != 0 ? '-' : '+');
    s.width(digits);
    s.fill('0');
    s << std::min<long>(n, static_cast<long>(std::pow(10, digits)) - 1);
    return s.str();
}

struct TrajectoryKey {
    double t_s;
    Eigen::Vector3d p;
    Eigen::Quaterniond q;
};

speed_t baud_speed(int baud) {
    switch (baud) {
        case 9600: return B9600;
        case 19200: return B19200;
        case 38400: return B38400;
        case 57600: return B57600;
        case 115200: return B115200;
        case 230400: return B230400;
        case 921600: return B921600;
        default: return B0;  // 14400, 1228739: no termios constant, so the host can never match
    }
}

}  // namespace

const char* fault_name(Fault f) {
    switch (f) {
        case Fault::bit_flip: return "bit_flip";
        case Fault::drop: return "drop";
        case Fault::truncate: return "truncate";
        case Fault::garbage: return "garbage";
        case Fault::delay: return "delay";
        case Fault::split: return "split";
        case Fault::stale_bytes: return "stale_bytes";
        case Fault::disconnect: return "disconnect";
        case Fault::power_cycle: return "power_cycle";
        case Fault::tool_missing: return "tool_missing";
        case Fault::out_of_volume: return "out_of_volume";
    }
    return "?";
}

std::optional<Fault> fault_from_name(const std::string& s) {
    for (Fault f : kAllFaults)
        if (s == fault_name(f)) return f;
    return std::nullopt;
}

FaultRates FaultRates::parse(const std::string& text) {
    FaultRates r;
    std::istringstream in(text);
    std::string item;
    while (std::getline(in, item, ',')) {
        if (item.empty()) continue;
        const auto eq = item.find('=');
        if (eq == std::string::npos) throw std::invalid_argument("--faults " + item + ": expected name=value");
        const std::string k = item.substr(0, eq);
        double v = 0;
        try {
            v = std::stod(item.substr(eq + 1));
        } catch (...) {
            throw std::invalid_argument("--faults " + item + ": value is not a number");
        }
        const bool per_min = k == "disconnects_per_min" || k == "power_cycles_per_min";
        if (v < 0 || (!per_min && v > 1) || (per_min && v > 600)) throw std::invalid_argument("--faults " + item + ": out of range");
        double* p = k == "bit_flip" ? &r.bit_flip : k == "drop" ? &r.drop : k == "truncate" ? &r.truncate
                  : k == "garbage" ? &r.garbage : k == "delay" ? &r.delay : k == "split" ? &r.split
                  : k == "stale_bytes" ? &r.stale_bytes : k == "disconnects_per_min" ? &r.disconnects_per_min
                  : k == "power_cycles_per_min" ? &r.power_cycles_per_min : k == "tool_missing" ? &r.tool_missing
                  : k == "out_of_volume" ? &r.out_of_volume : nullptr;
        if (!p) throw std::invalid_argument("--faults " + item + ": unknown fault name");
        *p = v;
    }
    if (r.bit_flip + r.drop + r.truncate + r.garbage + r.delay + r.split + r.stale_bytes > 1)
        throw std::invalid_argument("--faults " + text + ": reply fault probabilities add up to more than 1");
    if (r.tool_missing + r.out_of_volume > 1) throw std::invalid_argument("--faults " + text + ": tool_missing + out_of_volume > 1");
    return r;
}

std::vector<ScriptedFault> load_fault_script(const std::string& path) {
    std::ifstream in(path);
    if (!in) throw std::invalid_argument(path + ": cannot open the fault script");
    std::vector<ScriptedFault> out;
    std::string line;
    int no = 0;
    while (std::getline(in, line)) {
        ++no;
        if (const auto h = line.find('#'); h != std::string::npos) line.resize(h);
        std::istringstream ls(line);
        ScriptedFault f;
        std::string kind;
        if (!(ls >> f.at_s)) {
            if (line.find_first_not_of(" \t\r") == std::string::npos) continue;
            throw std::invalid_argument(path + ":" + std::to_string(no) + ": expected '<at_s> <fault> [tool duration_s]'");
        }
        if (!(ls >> kind) || !fault_from_name(kind) || f.at_s < 0)
            throw std::invalid_argument(path + ":" + std::to_string(no) + ": unknown fault '" + kind + "'");
        f.kind = *fault_from_name(kind);
        if (f.kind == Fault::tool_missing || f.kind == Fault::out_of_volume) {
            if (!(ls >> f.tool >> f.duration_s) || f.duration_s <= 0)
                throw std::invalid_argument(path + ":" + std::to_string(no) + ": " + kind + " needs a tool part name and a duration in s");
        }
        out.push_back(f);
    }
    return out;
}

void TrackerSimConfig::validate() const {
    if (frame_rate_hz != 20 && frame_rate_hz != 60 && frame_rate_hz != 250)
        throw std::invalid_argument("--rate " + std::to_string(frame_rate_hz) + ": must be 20, 60 or 250 Hz");
    if (noise_mm < 0 || noise_mm > 10) throw std::invalid_argument("--noise-mm: must be 0..10");
    if (noise_deg < 0 || noise_deg > 5) throw std::invalid_argument("--noise-deg: must be 0..5");
    if (unplugged_for.count() < 0 || unplugged_for.count() > 60000) throw std::invalid_argument("unplugged_for: must be 0..60000 ms");
    try {
        thread_priority.validate();
    } catch (const std::exception& e) {
        throw std::invalid_argument(std::string("thread_priority: ") + e.what());
    }
}

std::vector<std::uint8_t> make_synthetic_rom(const std::string& part, std::uint8_t main_type,
                                             const std::vector<Eigen::Vector3f>& markers, std::size_t size) {
    std::vector<std::uint8_t> b = {'N', 'D', 'I', 0, main_type, 'C', 'F', '1'};
    std::string p = part.substr(0, 20);
    p.resize(20, ' ');
    b.insert(b.end(), p.begin(), p.end());
    b.push_back(static_cast<std::uint8_t>(markers.size()));
    b.insert(b.end(), 3, 0);
    for (const auto& m : markers)
        for (int k = 0; k < 3; ++k) put_f32(b, m[k]);
    if (b.size() + 2 > size) size = b.size() + 2;
    b.resize(size - 2, 0);
    const std::uint16_t c = crc16(std::span<const std::uint8_t>(b));
    b.push_back(static_cast<std::uint8_t>(c & 0xFF));
    b.push_back(static_cast<std::uint8_t>(c >> 8));
    return b;
}

// ---------------------------------------------------------------------------------------------

struct TrackerSimulator::Impl {
    TrackerSimConfig cfg;
    TrackerSimulator* owner = nullptr;
    std::vector<std::string> parts;
    std::map<std::string, std::vector<TrajectoryKey>> trajectory;

    // Link (sim thread; slave path also read by others under mu)
    int master = -1, slave_keep = -1, listen_fd = -1, client = -1;
    std::string slave;
    std::uint16_t port = 0;
    std::int64_t unplugged_until_ns = 0;
    std::int64_t power_back_ns = 0;  // device silent until then
    bool pending_restore = false;

    // Device state (sim thread)
    enum class State { power_up, setup, tracking } state = State::power_up;
    int device_baud = 9600;
    struct Handle {
        std::vector<std::uint8_t> rom = std::vector<std::uint8_t>(2048, 0);
        bool written = false, initialised = false, enabled = false;
        char priority = 'D';
        std::string part;
    };
    std::map<std::uint8_t, Handle> handles;
    std::int64_t t0_ns = 0;
    std::atomic<std::int64_t> frame_base{0};  // frame = base + floor((now - t0) * rate); read by hold() from other threads
    std::string inbuf;

    // Faults (sim thread)
    std::mt19937_64 rng;
    std::int64_t next_disconnect_ns = 0, next_power_cycle_ns = 0;
    std::vector<Fault> forced;  // injected or scripted reply faults, applied to the next BX/TX
    std::size_t script_next = 0;
    std::set<std::tuple<int, std::int64_t, std::string>> counted_blocks;

    std::uint32_t last_tracking_frame = 0;
    mutable std::mutex mu;
    struct Written {
        std::uint32_t frame = 0xFFFFFFFFu;
        std::int64_t written_ns = 0, request_ns = 0;
    };
    std::vector<Written> written = std::vector<Written>(4096);
    std::int64_t input_read_ns = 0;  // sim thread: when the bytes being processed were read
    std::string priority_desc;        // under mu
    std::map<Fault, std::uint64_t> counts;
    std::vector<std::int64_t> restored;
    std::vector<Fault> injected;  // from other threads
    std::atomic<bool> stop{false};
    std::atomic<std::uint64_t> beeps{0};  // BEEP n commands answered: the sum of n
    std::thread thread;

    // Held poses (TrackerSimulator::hold), oldest first; guarded by hold_mu (read by truth()
    // from any thread). Keyed by the first frame they apply to, so truth stays a function of
    // the frame number.
    struct Hold {
        std::size_t tool = 0;
        std::uint32_t from_frame = 0;
        std::optional<Eigen::Isometry3d> T_tracker_from_tool;  // nullopt: the scripted motion
        bool hidden = false;
    };
    mutable std::mutex hold_mu;
    std::vector<Hold> holds;
    std::optional<Hold> hold_at(std::size_t tool, std::uint32_t frame) const {
        std::lock_guard lk(hold_mu);
        for (auto it = holds.rbegin(); it != holds.rend(); ++it)
            if (it->tool == tool && it->from_frame <= frame) return *it;
        return std::nullopt;
    }

    // ---- scene (pure functions of the frame number) ----
    Eigen::Isometry3d scene_pose(std::size_t tool, std::uint32_t frame) const {
        if (const auto h = hold_at(tool, frame); h && h->T_tracker_from_tool) return *h->T_tracker_from_tool;
        const double t = static_cast<double>(frame) / cfg.frame_rate_hz;
        Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
        const auto tr = trajectory.find(parts[tool]);
        if (tr != trajectory.end() && !tr->second.empty()) {
            const auto& keys = tr->second;
            const double period = keys.back().t_s;
            const double u = period > 0 ? std::fmod(t, period) : 0;
            std::size_t i = 0;
            while (i + 1 < keys.size() && keys[i + 1].t_s < u) ++i;
            const auto& a = keys[i];
            const auto& b = keys[std::min(i + 1, keys.size() - 1)];
            const double w = b.t_s > a.t_s ? std::clamp((u - a.t_s) / (b.t_s - a.t_s), 0.0, 1.0) : 0.0;
            T.linear() = a.q.slerp(w, b.q).toRotationMatrix();
            T.translation() = a.p + w * (b.p - a.p);
            return T;
        }
        if (parts[tool] == "CF-REFERENCE") {  // on the head clamp: still
            T.linear() = (Eigen::AngleAxisd(0.3, Eigen::Vector3d::UnitX()) * Eigen::AngleAxisd(-0.2, Eigen::Vector3d::UnitY())).toRotationMatrix();
            T.translation() = Eigen::Vector3d(40, -25, -1450);
        } else if (parts[tool] == "CF-POINTER") {  // circles over the head, tip wobbling
            const double a = 2 * M_PI * t / 8.0;
            T.linear() = (Eigen::AngleAxisd(a, Eigen::Vector3d::UnitZ()) * Eigen::AngleAxisd(0.4 + 0.1 * std::sin(3 * a), Eigen::Vector3d::UnitX())).toRotationMatrix();
            T.translation() = Eigen::Vector3d(60 * std::cos(a), 60 * std::sin(a), -1350 + 20 * std::sin(2 * a));
        } else {  // a tracked camera on an arm, swaying slowly
            // +-0.1 rad (5.7 deg): at 0.2 the view swung ~60 mm at the cortex and a photo taken
            // near an extreme could miss the craniotomy ("too little cortex visible"; a loaded
            // machine's ctest, 6 Dec 2026). An arm holding a camera moves less than that.
            const double a = 2 * M_PI * t / 20.0;
            T.linear() = Eigen::AngleAxisd(0.1 * std::sin(a), Eigen::Vector3d::UnitY()).toRotationMatrix();
            T.translation() = Eigen::Vector3d(-150, 80 + 10 * std::sin(a), -1250);
        }
        return T;
    }

    std::uint64_t key(std::size_t tool, std::uint64_t x, std::uint64_t salt) const {
        return mix(cfg.seed * 0x100000001B3ull ^ mix(x * 131 + tool * 7919 + salt));
    }

    ToolTruth truth(std::size_t tool, std::uint32_t frame) const {
        ToolTruth tt;
        tt.T_tracker_from_tool = scene_pose(tool, frame);
        const double dt_deg = cfg.noise_deg * gauss(key(tool, frame, 1));
        Eigen::Vector3d axis(gauss(key(tool, frame, 2)), gauss(key(tool, frame, 3)), gauss(key(tool, frame, 4)));
        if (axis.norm() < 1e-9) axis = Eigen::Vector3d::UnitZ();
        Eigen::Isometry3d n = Eigen::Isometry3d::Identity();
        n.linear() = Eigen::AngleAxisd(dt_deg * M_PI / 180, axis.normalized()).toRotationMatrix();
        tt.measured = tt.T_tracker_from_tool * n;
        tt.measured.translation() = tt.T_tracker_from_tool.translation() +
                                    cfg.noise_mm * Eigen::Vector3d(gauss(key(tool, frame, 5)), gauss(key(tool, frame, 6)), gauss(key(tool, frame, 7)));
        // Visibility: per 0.5 s block, from the seed, plus scripted windows.
        const std::int64_t block = static_cast<std::int64_t>(frame / static_cast<std::uint32_t>(cfg.frame_rate_hz / 2));
        const double u = uniform01(key(tool, static_cast<std::uint64_t>(block), 99));
        tt.visible = !(u < cfg.faults.tool_missing);
        tt.out_of_volume = tt.visible && u < cfg.faults.tool_missing + cfg.faults.out_of_volume;
        const double t_s = static_cast<double>(frame) / cfg.frame_rate_hz;
        for (const auto& s : cfg.script) {
            if (s.tool != parts[tool] || t_s < s.at_s || t_s >= s.at_s + s.duration_s) continue;
            if (s.kind == Fault::tool_missing) tt.visible = false;
            if (s.kind == Fault::out_of_volume) tt.out_of_volume = true;
        }
        if (const auto h = hold_at(tool, frame); h && h->hidden) tt.visible = false;
        if (!tt.visible) tt.out_of_volume = false;
        return tt;
    }

    void count(Fault f, std::uint64_t n = 1) {
        std::lock_guard lk(mu);
        counts[f] += n;
    }

    std::uint32_t frame_now() const {
        const double s = static_cast<double>(now_ns() - t0_ns) * 1e-9;
        return static_cast<std::uint32_t>(frame_base + static_cast<std::int64_t>(std::floor(s * cfg.frame_rate_hz)));
    }

    // ---- link ----
    void open_pty() {
        master = ::posix_openpt(O_RDWR | O_NOCTTY | O_CLOEXEC);
        if (master < 0 || ::grantpt(master) != 0 || ::unlockpt(master) != 0) throw std::runtime_error(std::string("sim: cannot create a pty: ") + std::strerror(errno));
        int one = 1;
        ::ioctl(master, TIOCPKT, &one);  // see the host's flushes (our break detector, §9.4)
        const char* name = ::ptsname(master);
        if (!name) throw std::runtime_error("sim: ptsname failed");
        {
            std::lock_guard lk(mu);
            slave = name;
        }
        // Keep a slave descriptor so the master never sees a hang-up between host sessions.
        slave_keep = ::open(name, O_RDWR | O_NOCTTY | O_CLOEXEC);
        termios tio{};
        ::tcgetattr(slave_keep, &tio);
        ::cfmakeraw(&tio);
        ::cfsetispeed(&tio, B9600);
        ::cfsetospeed(&tio, B9600);
        ::tcsetattr(slave_keep, TCSANOW, &tio);
        ::fcntl(master, F_SETFL, ::fcntl(master, F_GETFL) | O_NONBLOCK);
        if (!cfg.pty_link.empty()) {
            const std::string tmp = cfg.pty_link + ".tmp";
            ::unlink(tmp.c_str());
            if (::symlink(name, tmp.c_str()) != 0 || ::rename(tmp.c_str(), cfg.pty_link.c_str()) != 0)
                throw std::runtime_error("sim: cannot create the link " + cfg.pty_link + ": " + std::strerror(errno));
        }
    }
    void close_pty() {
        if (!cfg.pty_link.empty()) ::unlink(cfg.pty_link.c_str());
        if (master >= 0) ::close(master);
        if (slave_keep >= 0) ::close(slave_keep);
        master = slave_keep = -1;
    }
    void open_listen() {
        listen_fd = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC | SOCK_NONBLOCK, 0);
        int one = 1;
        ::setsockopt(listen_fd, SOL_SOCKET, SO_REUSEADDR, &one, sizeof one);
        sockaddr_in a{};
        a.sin_family = AF_INET;
        a.sin_port = htons(port ? port : cfg.tcp_port);
        if (::inet_pton(AF_INET, cfg.tcp_host.c_str(), &a.sin_addr) != 1) throw std::runtime_error("sim: --tcp host must be an IPv4 address: " + cfg.tcp_host);
        if (::bind(listen_fd, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0 || ::listen(listen_fd, 4) != 0)
            throw std::runtime_error("sim: cannot listen on " + cfg.tcp_host + ":" + std::to_string(ntohs(a.sin_port)) + ": " + std::strerror(errno));
        socklen_t len = sizeof a;
        ::getsockname(listen_fd, reinterpret_cast<sockaddr*>(&a), &len);
        std::lock_guard lk(mu);
        port = ntohs(a.sin_port);
    }
    void close_client() {
        if (client >= 0) ::close(client);
        client = -1;
    }

    bool link_up() const { return cfg.link == TrackerSimConfig::Link::pty ? master >= 0 : client >= 0; }

    void write_raw(const std::uint8_t* p, std::size_t n) {
        const int fd = cfg.link == TrackerSimConfig::Link::pty ? master : client;
        if (fd < 0) return;
        std::size_t done = 0;
        int spins = 0;
        while (done < n && spins < 200) {
            const ssize_t w = cfg.link == TrackerSimConfig::Link::pty ? ::write(fd, p + done, n - done) : ::send(fd, p + done, n - done, MSG_NOSIGNAL);
            if (w > 0) {
                done += static_cast<std::size_t>(w);
            } else if (w < 0 && (errno == EAGAIN || errno == EINTR)) {
                ++spins;
                std::this_thread::sleep_for(std::chrono::milliseconds(1));
            } else {
                if (cfg.link == TrackerSimConfig::Link::tcp) close_client();
                return;
            }
        }
    }
    void write_bytes(const std::vector<std::uint8_t>& b) { write_raw(b.data(), b.size()); }
    void write_text(const std::string& s) { write_raw(reinterpret_cast<const std::uint8_t*>(s.data()), s.size()); }

    int host_baud() const {
        termios tio{};
        if (master < 0 || ::tcgetattr(master, &tio) != 0) return 0;
        const speed_t s = ::cfgetospeed(&tio);
        for (int b : {9600, 19200, 38400, 57600, 115200, 230400, 921600})
            if (baud_speed(b) == s) return b;
        return -1;
    }

    // ---- device ----
    void power_up() {
        state = State::power_up;
        device_baud = 9600;
        handles.clear();
        inbuf.clear();
    }

    std::string phsr(const std::string& opt) {
        std::string out;
        int n = 0;
        for (const auto& [h, hd] : handles) {
            const bool pick = opt.empty() || opt == "00" || (opt == "02" && !hd.initialised) ||
                              (opt == "03" && hd.initialised && !hd.enabled) || (opt == "04" && hd.enabled);
            if (!pick) continue;
            const unsigned st = 0x001 | (hd.initialised ? 0x010 : 0) | (hd.enabled ? 0x020 : 0);
            out += hex2(h) + cf::tracker::crc_hex(static_cast<std::uint16_t>(st)).substr(1);
            ++n;
        }
        return hex2(static_cast<unsigned>(n)) + out;
    }

    std::vector<std::uint8_t> bx_body(std::uint16_t opt, std::uint32_t frame) {
        std::vector<std::uint8_t> b;
        std::vector<std::uint8_t> enabled;
        for (const auto& [h, hd] : handles)
            if (hd.enabled) enabled.push_back(h);
        b.push_back(static_cast<std::uint8_t>(enabled.size()));
        for (const auto h : enabled) {
            b.push_back(h);
            const auto tool = tool_index(handles[h].part);
            std::optional<ToolTruth> tt;
            if (tool) tt = truth(*tool, frame);
            const bool report = tt && tt->visible && (!tt->out_of_volume || (opt & 0x0800));
            if (tt) note_visibility(*tool, frame, *tt);
            b.push_back(report ? 0x01 : 0x02);
            std::uint32_t port = 0x31;
            if (report) {
                const Eigen::Quaterniond q(tt->measured.linear());
                put_f32(b, q.w());
                put_f32(b, q.x());
                put_f32(b, q.y());
                put_f32(b, q.z());
                for (int k = 0; k < 3; ++k) put_f32(b, tt->measured.translation()[k]);
                put_f32(b, 0.08 + 0.05 * uniform01(key(*tool, frame, 11)));
                if (tt->out_of_volume) port |= 0x40;
            }
            put_u32(b, port);
            put_u32(b, frame);
        }
        b.push_back(0);
        b.push_back(0);
        return b;
    }

    std::string tx_text(std::uint16_t opt, std::uint32_t frame) {
        std::string s;
        int n = 0;
        std::string lines;
        for (auto& [h, hd] : handles) {
            if (!hd.enabled) continue;
            ++n;
            lines += hex2(h);
            const auto tool = tool_index(hd.part);
            std::optional<ToolTruth> tt;
            if (tool) tt = truth(*tool, frame);
            if (tt) note_visibility(*tool, frame, *tt);
            const bool report = tt && tt->visible && (!tt->out_of_volume || (opt & 0x0800));
            std::uint32_t port = 0x31;
            if (report) {
                Eigen::Quaterniond q(tt->measured.linear());
                if (q.w() < 0) q.coeffs() *= -1;
                lines += signed_text(q.w(), 5, 1e4) + signed_text(q.x(), 5, 1e4) + signed_text(q.y(), 5, 1e4) + signed_text(q.z(), 5, 1e4);
                for (int k = 0; k < 3; ++k) lines += signed_text(tt->measured.translation()[k], 6, 100);
                lines += signed_text(0.08, 5, 1e4);
                if (tt->out_of_volume) port |= 0x40;
            } else {
                lines += "MISSING";
            }
            lines += cf::tracker::crc_hex(static_cast<std::uint16_t>(port >> 16)) + cf::tracker::crc_hex(static_cast<std::uint16_t>(port & 0xFFFF));
            lines += cf::tracker::crc_hex(static_cast<std::uint16_t>(frame >> 16)) + cf::tracker::crc_hex(static_cast<std::uint16_t>(frame & 0xFFFF));
            lines += "\n";
        }
        s = hex2(static_cast<unsigned>(n)) + lines + "0000";
        return s;
    }

    void note_visibility(std::size_t tool, std::uint32_t frame, const ToolTruth& tt) {
        if (tt.visible && !tt.out_of_volume) return;
        const std::int64_t block = static_cast<std::int64_t>(frame / static_cast<std::uint32_t>(cfg.frame_rate_hz / 2));
        const int kind = tt.visible ? 1 : 0;
        if (counted_blocks.emplace(kind, block, parts[tool]).second) count(tt.visible ? Fault::out_of_volume : Fault::tool_missing);
    }

    std::optional<std::size_t> tool_index(const std::string& part) const {
        for (std::size_t i = 0; i < parts.size(); ++i)
            if (parts[i] == part) return i;
        return std::nullopt;
    }

    static std::string rom_part(const std::vector<std::uint8_t>& rom) {
        if (!(rom[5] == 'C' && rom[6] == 'F' && rom[7] == '1')) return {};
        std::string p(rom.begin() + 8, rom.begin() + 28);
        while (!p.empty() && p.back() == ' ') p.pop_back();
        return p;
    }
    static bool rom_valid(const std::vector<std::uint8_t>& rom) {
        if (!(rom[0] == 'N' && rom[1] == 'D' && rom[2] == 'I' && rom[3] == 0)) return false;
        if (!(rom[5] == 'C' && rom[6] == 'F' && rom[7] == '1')) return true;  // a real .rom: accepted as is
        // Synthetic: find the CRC over [0, n) stored at n; n = the written length rounded as made.
        for (std::size_t n = 32; n + 2 <= rom.size(); ++n) {
            const std::uint16_t c = crc16(std::span<const std::uint8_t>(rom.data(), n));
            if ((c & 0xFF) == rom[n] && (c >> 8) == rom[n + 1]) return true;
        }
        return false;
    }

    /// Handles one command line; returns the reply bytes (empty: no reply).
    std::vector<std::uint8_t> handle_command(const std::string& line, bool* tracking_reply) {
        *tracking_reply = false;
        auto ascii = [](const std::string& payload) {
            const std::string s = frame_ascii_reply(payload);
            return std::vector<std::uint8_t>(s.begin(), s.end());
        };
        auto err = [&](int code) { return ascii("ERROR" + hex2(static_cast<unsigned>(code))); };
        const auto cmd = cf::tracker::parse_command(line);
        if (!cmd) return err(0x01);
        if (cmd->had_crc && !cmd->crc_ok) return err(0x04);
        const std::string& n = cmd->name;
        const std::string& p = cmd->params;
        auto setup_only = [&]() -> std::optional<std::vector<std::uint8_t>> {
            if (state == State::power_up) return err(0x10);
            if (state == State::tracking) return err(0x0C);
            return std::nullopt;
        };
        if (n == "INIT") {
            if (!p.empty()) return err(0x07);
            state = State::setup;
            handles.clear();  // a fresh client loads its tools again (no handle leak across sessions)
            return ascii("OKAY");
        }
        if (n == "RESET") {
            power_up();
            return ascii("RESET");
        }
        if (n == "VER") {
            if (p.size() != 1 || p[0] < '0' || p[0] > '5') return err(0x07);
            if (p == "5") return ascii("015");
            return ascii("CortexFuse simulated position sensor\nFreeze Tag: " + cfg.firmware + "\nCombined Firmware Revision: 015");
        }
        if (n == "APIREV") return p.empty() ? ascii(cfg.api_revision) : err(0x07);
        if (n == "GETINFO" || n == "GET" || n == "SET") return err(0x01);  // Spectra/Vicra
        if (n == "ECHO") return ascii(p);
        if (n == "BEEP") {
            if (p.size() != 1 || p[0] < '1' || p[0] > '9') return err(0x07);
            beeps += std::uint64_t(p[0] - '0');
            return ascii("1");
        }
        if (n == "COMM") {
            if (p.size() != 5) return err(0x07);
            const int baud = cf::tracker::comm_baud_rate(p[0]);
            if (baud == 0 || p[1] != '0' || p[2] < '0' || p[2] > '2' || p[3] < '0' || p[3] > '1' || p[4] < '0' || p[4] > '1') return err(0x06);
            if (cfg.link == TrackerSimConfig::Link::tcp) return ascii("OKAY");  // no serial settings on TCP
            auto r = ascii("OKAY");
            write_bytes(r);  // OKAY at the old rate, then switch
            device_baud = baud;
            return {};
        }
        if (n == "PHRQ") {
            if (auto e = setup_only()) return *e;
            if (p.size() != 14) return err(0x07);
            std::uint8_t h = 1;
            while (handles.count(h) && h < 0xFF) ++h;
            if (handles.size() >= 24) return err(0x2D);
            handles[h] = Handle{};
            return ascii(hex2(h));
        }
        if (n == "PVWR") {
            if (auto e = setup_only()) return *e;
            if (p.size() != 134) return err(0x07);
            const auto h = cf::tracker::parse_hex_u32(p.substr(0, 2));
            const auto addr = cf::tracker::parse_hex_u32(p.substr(2, 4));
            const auto data = cf::tracker::from_hex(p.substr(6));  // either case (NDI's sample sends lowercase)
            if (!h || !handles.count(static_cast<std::uint8_t>(*h))) return err(0x2B);
            if (!addr || !data || *addr % 64 != 0 || *addr + 64 > 2048) return err(0x23);
            auto& hd = handles[static_cast<std::uint8_t>(*h)];
            std::copy(data->begin(), data->end(), hd.rom.begin() + *addr);
            hd.written = true;
            return ascii("OKAY");
        }
        if (n == "PHSR") {
            if (auto e = setup_only()) return *e;
            if (!p.empty() && p != "00" && p != "01" && p != "02" && p != "03" && p != "04") return err(0x07);
            if (p == "01") return ascii("00");  // nothing waits to be freed
            return ascii(phsr(p));
        }
        auto handle_arg = [&](std::size_t extra) -> std::optional<std::uint8_t> {
            if (p.size() != 2 + extra) return std::nullopt;
            const auto h = cf::tracker::parse_hex_u32(p.substr(0, 2));
            if (!h) return std::nullopt;
            return static_cast<std::uint8_t>(*h);
        };
        if (n == "PHF" || n == "PINIT" || n == "PENA" || n == "PDIS") {
            if (auto e = setup_only()) return *e;
            const auto h = handle_arg(n == "PENA" ? 1 : 0);
            if (!h) return err(0x07);
            if (!handles.count(*h)) return err(0x2B);
            auto& hd = handles[*h];
            if (n == "PHF") {
                handles.erase(*h);
                return ascii("OKAY");
            }
            if (n == "PINIT") {
                if (!hd.written) return err(0x0D);
                if (!rom_valid(hd.rom)) return err(0x40);
                hd.part = rom_part(hd.rom);
                hd.initialised = true;
                return ascii("OKAY");
            }
            if (n == "PENA") {
                if (!hd.initialised) return err(0x0E);
                const char prio = p[2];
                if (prio != 'S' && prio != 'D' && prio != 'B') return err(0x09);
                hd.enabled = true;
                hd.priority = prio;
                return ascii("OKAY");
            }
            hd.enabled = false;  // PDIS
            return ascii("OKAY");
        }
        if (n == "TSTART") {
            if (auto e = setup_only()) return *e;
            if (!p.empty() && p != "80") return err(0x07);
            if (p == "80") frame_base = -static_cast<std::int64_t>(std::floor(static_cast<double>(now_ns() - t0_ns) * 1e-9 * cfg.frame_rate_hz));
            state = State::tracking;
            return ascii("OKAY");
        }
        if (n == "TSTOP") {
            if (state != State::tracking) return err(0x0C);
            state = State::setup;
            return ascii("OKAY");
        }
        if (n == "BX" || n == "TX") {
            if (state != State::tracking) return err(state == State::power_up ? 0x10 : 0x0C);
            const auto opt = p.empty() ? std::optional<std::uint32_t>(1) : cf::tracker::parse_hex_u32(p);
            if (!opt || p.size() > 4 || (*opt != 0x0001 && *opt != 0x0801)) return err(0x23);
            *tracking_reply = true;
            const std::uint32_t frame = frame_now();
            last_tracking_frame = frame;
            if (n == "TX") return ascii(tx_text(static_cast<std::uint16_t>(*opt), frame));
            return cf::tracker::frame_binary_reply(bx_body(static_cast<std::uint16_t>(*opt), frame));
        }
        return err(0x01);
    }

    // ---- faults ----
    double exp_interval_s(double per_min) {
        std::exponential_distribution<double> d(per_min / 60.0);
        return std::max(1.0, d(rng));  // at least a second apart: every outage gets its own resume
    }

    void schedule_time_faults(std::int64_t now) {
        if (cfg.faults.disconnects_per_min > 0 && next_disconnect_ns == 0)
            next_disconnect_ns = now + static_cast<std::int64_t>(exp_interval_s(cfg.faults.disconnects_per_min) * 1e9);
        if (cfg.faults.power_cycles_per_min > 0 && next_power_cycle_ns == 0)
            next_power_cycle_ns = now + static_cast<std::int64_t>(exp_interval_s(cfg.faults.power_cycles_per_min) * 1e9);
    }

    void disconnect(std::int64_t now) {
        count(Fault::disconnect);
        if (cfg.link == TrackerSimConfig::Link::pty) close_pty();
        else {
            close_client();
            if (listen_fd >= 0) ::close(listen_fd);  // refuse connections while "unplugged"
            listen_fd = -1;
        }
        inbuf.clear();
        unplugged_until_ns = now + std::chrono::nanoseconds(cfg.unplugged_for).count();
        pending_restore = true;
    }

    void power_cycle(std::int64_t now) {
        count(Fault::power_cycle);
        power_up();
        power_back_ns = now + std::chrono::nanoseconds(cfg.boot_time).count();
        std::lock_guard lk(mu);
        restored.push_back(power_back_ns);
    }

    void send_tracking_reply(std::vector<std::uint8_t> r) {
        std::optional<Fault> f;
        if (!forced.empty()) {
            f = forced.front();
            forced.erase(forced.begin());
        } else {
            const auto& q = cfg.faults;
            double u = std::uniform_real_distribution<double>(0, 1)(rng);
            const std::pair<double, Fault> table[] = {{q.bit_flip, Fault::bit_flip}, {q.drop, Fault::drop}, {q.truncate, Fault::truncate},
                                                      {q.garbage, Fault::garbage}, {q.delay, Fault::delay}, {q.split, Fault::split},
                                                      {q.stale_bytes, Fault::stale_bytes}};
            for (const auto& [prob, kind] : table) {
                if (u < prob) {
                    f = kind;
                    break;
                }
                u -= prob;
            }
        }
        if (f) count(*f);
        std::uniform_int_distribution<std::size_t> any(0, r.size() - 1);
        switch (f.value_or(Fault::power_cycle)) {  // power_cycle: "no reply fault"
            case Fault::bit_flip: r[any(rng)] ^= static_cast<std::uint8_t>(1u << (rng() % 8)); break;
            case Fault::drop: return;
            case Fault::truncate: r.resize(1 + any(rng) % (r.size() - 1)); break;
            case Fault::garbage: {
                std::vector<std::uint8_t> g(1 + rng() % 24);
                for (auto& b : g) b = static_cast<std::uint8_t>(rng());
                if (rng() % 4 == 0) g.push_back(0x0D);
                write_bytes(g);
                break;
            }
            case Fault::delay: std::this_thread::sleep_for(std::chrono::milliseconds(10 + rng() % 60)); break;
            case Fault::split: {
                const std::size_t cut = 1 + any(rng) % (r.size() - 1);
                write_raw(r.data(), cut);
                std::this_thread::sleep_for(std::chrono::milliseconds(2 + rng() % 8));
                write_raw(r.data() + cut, r.size() - cut);
                owner->replies_sent_++;
                return;
            }
            case Fault::stale_bytes: write_text(frame_ascii_reply("OKAY")); break;
            default: break;
        }
        write_bytes(r);
        owner->replies_sent_++;
        if (!f) {
            std::lock_guard lk(mu);
            auto& slot = written[last_tracking_frame % written.size()];
            if (slot.frame != last_tracking_frame) slot = {last_tracking_frame, now_ns(), input_read_ns};
        }
    }

    void process_input(const std::uint8_t* p, std::size_t n) {
        const std::int64_t now = now_ns();
        if (now < power_back_ns) return;  // booting: deaf
        // Out of step (host at another baud, fact sheet §9.3 fault 4): the bytes are noise to us.
        if (cfg.link == TrackerSimConfig::Link::pty && host_baud() != device_baud) return;
        for (std::size_t i = 0; i < n; ++i) {
            if (p[i] != '\r') {
                if (inbuf.size() < 4096) inbuf.push_back(static_cast<char>(p[i]));
                continue;
            }
            const std::string line = std::move(inbuf);
            inbuf.clear();
            if (line.empty()) continue;
            if (cfg.reply_delay.count() > 0) std::this_thread::sleep_for(cfg.reply_delay);
            bool tracking = false;
            auto reply = handle_command(line, &tracking);
            if (reply.empty()) continue;
            if (tracking) send_tracking_reply(std::move(reply));
            else {
                write_bytes(reply);
                owner->replies_sent_++;
            }
        }
    }

    void loop() {
        std::uint8_t buf[4096];
        while (!stop) {
            const std::int64_t now = now_ns();
            // Injected and scripted faults.
            {
                std::vector<Fault> inj;
                {
                    std::lock_guard lk(mu);
                    inj.swap(injected);
                }
                const double t_s = static_cast<double>(now - t0_ns) * 1e-9;
                while (script_next < cfg.script.size() && cfg.script[script_next].at_s <= t_s) {
                    const auto& s = cfg.script[script_next++];
                    if (s.kind != Fault::tool_missing && s.kind != Fault::out_of_volume) inj.push_back(s.kind);
                }
                for (Fault f : inj) {
                    if (f == Fault::disconnect) {
                        if (link_up()) disconnect(now);
                    } else if (f == Fault::power_cycle) {
                        power_cycle(now);
                    } else if (f != Fault::tool_missing && f != Fault::out_of_volume) {
                        forced.push_back(f);
                    }
                }
            }
            if (state == State::tracking && link_up()) {
                schedule_time_faults(now);
                if (next_disconnect_ns && now >= next_disconnect_ns) {
                    next_disconnect_ns = 0;
                    disconnect(now);
                } else if (next_power_cycle_ns && now >= next_power_cycle_ns) {
                    next_power_cycle_ns = 0;
                    power_cycle(now);
                }
            }
            if (pending_restore && now >= unplugged_until_ns) {
                pending_restore = false;
                if (cfg.link == TrackerSimConfig::Link::pty) open_pty();
                else open_listen();
                std::lock_guard lk(mu);
                restored.push_back(now_ns());
            }

            pollfd fds[2];
            int nf = 0;
            if (cfg.link == TrackerSimConfig::Link::pty) {
                if (master >= 0) fds[nf++] = {master, POLLIN, 0};
            } else {
                if (listen_fd >= 0) fds[nf++] = {listen_fd, POLLIN, 0};
                if (client >= 0) fds[nf++] = {client, POLLIN, 0};
            }
            if (nf == 0) {
                std::this_thread::sleep_for(std::chrono::milliseconds(2));
                continue;
            }
            if (::poll(fds, static_cast<nfds_t>(nf), 5) <= 0) continue;
            for (int i = 0; i < nf; ++i) {
                if (!(fds[i].revents & (POLLIN | POLLHUP | POLLERR))) continue;
                if (fds[i].fd == listen_fd) {
                    const int c = ::accept4(listen_fd, nullptr, nullptr, SOCK_CLOEXEC | SOCK_NONBLOCK);
                    if (c >= 0) {
                        close_client();  // the newest client is the master connection
                        client = c;
                        int one = 1;
                        ::setsockopt(client, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
                        inbuf.clear();
                    }
                } else if (fds[i].fd == client) {
                    const ssize_t r = ::recv(client, buf, sizeof buf, 0);
                    input_read_ns = now_ns();
                    if (r > 0) process_input(buf, static_cast<std::size_t>(r));
                    else if (r == 0 || (errno != EAGAIN && errno != EINTR)) close_client();
                } else if (fds[i].fd == master) {
                    const ssize_t r = ::read(master, buf, sizeof buf);
                    input_read_ns = now_ns();
                    if (r <= 0) continue;
                    if (buf[0] == TIOCPKT_DATA) {
                        process_input(buf + 1, static_cast<std::size_t>(r - 1));
                    } else if ((buf[0] & TIOCPKT_FLUSHWRITE) && host_baud() == 9600 && now_ns() >= power_back_ns) {
                        // The host flushed both queues at 9600: ndicapi's (and our) break recipe.
                        // A break does not cross a pty (§9.4), so this is our break.
                        power_up();
                        write_text(frame_ascii_reply("RESET"));
                        owner->replies_sent_++;
                    }
                }
            }
        }
    }
};

TrackerSimulator::TrackerSimulator(TrackerSimConfig config) : impl_(std::make_unique<Impl>()) {
    config.validate();
    impl_->cfg = std::move(config);
    impl_->owner = this;
    impl_->parts = {"CF-REFERENCE", "CF-POINTER"};
    if (impl_->cfg.camera_tool) impl_->parts.push_back("CF-CAMERA");
    impl_->rng.seed(impl_->cfg.seed);
    if (!impl_->cfg.trajectory_file.empty()) {
        std::ifstream in(impl_->cfg.trajectory_file);
        if (!in) throw std::invalid_argument(impl_->cfg.trajectory_file + ": cannot open the trajectory file");
        std::string line;
        int no = 0;
        while (std::getline(in, line)) {
            ++no;
            if (const auto h = line.find('#'); h != std::string::npos) line.resize(h);
            if (line.find_first_not_of(" \t\r") == std::string::npos) continue;
            std::istringstream ls(line);
            TrajectoryKey k;
            std::string part;
            double qw, qx, qy, qz;
            if (!(ls >> k.t_s >> part >> k.p.x() >> k.p.y() >> k.p.z() >> qw >> qx >> qy >> qz))
                throw std::invalid_argument(impl_->cfg.trajectory_file + ":" + std::to_string(no) + ": expected '<t_s> <part> tx ty tz qw qx qy qz'");
            k.q = Eigen::Quaterniond(qw, qx, qy, qz);
            if (std::abs(k.q.norm() - 1) > 0.01) throw std::invalid_argument(impl_->cfg.trajectory_file + ":" + std::to_string(no) + ": quaternion is not unit length");
            k.q.normalize();
            auto& v = impl_->trajectory[part];
            if (!v.empty() && k.t_s <= v.back().t_s) throw std::invalid_argument(impl_->cfg.trajectory_file + ":" + std::to_string(no) + ": times must increase per tool");
            v.push_back(k);
        }
    }
}

TrackerSimulator::~TrackerSimulator() { stop(); }

void TrackerSimulator::start() {
    auto& m = *impl_;
    if (m.thread.joinable()) return;
    m.t0_ns = now_ns();
    m.stop = false;
    if (m.cfg.link == TrackerSimConfig::Link::pty) m.open_pty();
    else m.open_listen();
    std::promise<void> prioritised;
    auto ready = prioritised.get_future();
    m.thread = std::thread([&m, prioritised = std::move(prioritised)]() mutable {
        const auto pr = cf::tracker::raise_thread_priority(m.cfg.thread_priority);
        {
            std::lock_guard lk(m.mu);
            m.priority_desc = pr.describe() + (pr.note.empty() ? "" : " (" + pr.note + ")");
        }
        prioritised.set_value();
        m.loop();
    });
    ready.wait();
}

void TrackerSimulator::stop() {
    auto& m = *impl_;
    m.stop = true;
    if (m.thread.joinable()) m.thread.join();
    m.close_pty();
    m.close_client();
    if (m.listen_fd >= 0) ::close(m.listen_fd);
    m.listen_fd = -1;
}

std::string TrackerSimulator::slave_path() const {
    std::lock_guard lk(impl_->mu);
    return impl_->slave;
}
std::uint16_t TrackerSimulator::tcp_port() const {
    std::lock_guard lk(impl_->mu);
    return impl_->port;
}
std::vector<std::string> TrackerSimulator::tools() const { return impl_->parts; }

std::optional<ToolTruth> TrackerSimulator::truth(const std::string& part, std::uint32_t frame) const {
    const auto i = impl_->tool_index(part);
    if (!i) return std::nullopt;
    return impl_->truth(*i, frame);
}

std::uint32_t TrackerSimulator::current_frame() const { return impl_->frame_now(); }

std::uint32_t TrackerSimulator::hold(const std::string& part, std::optional<Eigen::Isometry3d> T_tracker_from_tool, bool hidden) {
    const auto i = impl_->tool_index(part);
    if (!i) throw std::invalid_argument("sim hold: no tool '" + part + "' in the scene");
    if (T_tracker_from_tool && !T_tracker_from_tool->matrix().allFinite()) throw std::invalid_argument("sim hold: the pose of '" + part + "' is not finite");
    const std::uint32_t from = impl_->frame_now() + 1;
    std::lock_guard lk(impl_->hold_mu);
    impl_->holds.push_back({*i, from, std::move(T_tracker_from_tool), hidden});
    return from;
}

std::map<Fault, std::uint64_t> TrackerSimulator::fault_counts() const {
    std::lock_guard lk(impl_->mu);
    return impl_->counts;
}
std::uint64_t TrackerSimulator::beeps() const { return impl_->beeps.load(); }
std::uint64_t TrackerSimulator::total_faults() const {
    std::uint64_t n = 0;
    for (const auto& [k, v] : fault_counts()) n += v;
    return n;
}
std::vector<std::int64_t> TrackerSimulator::link_restored_ns() const {
    std::lock_guard lk(impl_->mu);
    return impl_->restored;
}
std::optional<std::int64_t> TrackerSimulator::reply_written_ns(std::uint32_t frame) const {
    std::lock_guard lk(impl_->mu);
    const auto& slot = impl_->written[frame % impl_->written.size()];
    if (slot.frame != frame) return std::nullopt;
    return slot.written_ns;
}
std::optional<std::int64_t> TrackerSimulator::request_read_ns(std::uint32_t frame) const {
    std::lock_guard lk(impl_->mu);
    const auto& slot = impl_->written[frame % impl_->written.size()];
    if (slot.frame != frame || slot.request_ns == 0) return std::nullopt;
    return slot.request_ns;
}
std::string TrackerSimulator::thread_priority() const {
    std::lock_guard lk(impl_->mu);
    return impl_->priority_desc;
}

void TrackerSimulator::inject(Fault f) {
    std::lock_guard lk(impl_->mu);
    impl_->injected.push_back(f);
}

}  // namespace cf::sim
