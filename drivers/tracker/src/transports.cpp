// Serial (termios) and TCP transports. termios rather than libserialport: we need the break,
// the flushes and the raw settings exactly as the fact sheet describes them, and a pty must
// work like a tty for the simulator; termios gives all of that in a few calls.
#include <arpa/inet.h>
#include <fcntl.h>
#include <netdb.h>
#include <netinet/in.h>
#include <netinet/tcp.h>
#include <poll.h>
#include <sys/file.h>
#include <sys/socket.h>
#include <termios.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <map>
#include <set>

#include "cortexfuse/drivers/tracker/transport.hpp"

namespace cf::tracker {

namespace {

const std::map<int, speed_t>& speed_table() {
    static const std::map<int, speed_t> t = {{9600, B9600}, {38400, B38400}, {57600, B57600},
                                             {115200, B115200}, {230400, B230400}, {921600, B921600}};
    return t;
}

std::string errno_text(int e) { return std::strerror(e); }

int poll_ms(std::chrono::milliseconds t) {
    return static_cast<int>(std::clamp<std::int64_t>(t.count(), 0, 60'000));
}

class SerialTransport final : public Transport {
public:
    explicit SerialTransport(std::string path) : path_(std::move(path)) {}
    ~SerialTransport() override { close(); }

    void open() override {
        close();
        fd_ = ::open(path_.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
        if (fd_ < 0) throw TransportError(describe() + ": cannot open: " + errno_text(errno) + (errno == EACCES ? " (is the user in the dialout group?)" : ""));
        if (::flock(fd_, LOCK_EX | LOCK_NB) != 0) {
            const int e = errno;
            close();
            throw TransportError(describe() + ": port busy (another program holds it): " + errno_text(e));
        }
        configure(9600);
    }
    void close() override {
        if (fd_ >= 0) ::close(fd_);
        fd_ = -1;
    }
    bool is_open() const override { return fd_ >= 0; }

    void write(std::string_view bytes) override {
        require_open();
        std::size_t done = 0;
        while (done < bytes.size()) {
            const ssize_t n = ::write(fd_, bytes.data() + done, bytes.size() - done);
            if (n > 0) {
                done += static_cast<std::size_t>(n);
                continue;
            }
            if (n < 0 && errno == EINTR) continue;
            if (n < 0 && errno == EAGAIN) {
                pollfd p{fd_, POLLOUT, 0};
                if (::poll(&p, 1, 1000) <= 0) throw TransportError(describe() + ": write stalled");
                if (p.revents & (POLLERR | POLLHUP | POLLNVAL)) throw TransportError(describe() + ": link lost while writing");
                continue;
            }
            throw TransportError(describe() + ": write failed: " + errno_text(errno));
        }
    }

    std::size_t read(std::span<std::uint8_t> buf, std::chrono::milliseconds timeout) override {
        require_open();
        pollfd p{fd_, POLLIN, 0};
        int r;
        do r = ::poll(&p, 1, poll_ms(timeout));
        while (r < 0 && errno == EINTR);
        if (r < 0) throw TransportError(describe() + ": poll failed: " + errno_text(errno));
        if (r == 0) return 0;
        if ((p.revents & POLLIN) == 0) throw TransportError(describe() + ": link lost (hang-up)");
        const ssize_t n = ::read(fd_, buf.data(), buf.size());
        if (n > 0) return static_cast<std::size_t>(n);
        if (n < 0 && (errno == EAGAIN || errno == EINTR)) return 0;
        // A USB unplug gives EIO/ENXIO; a closed pty master gives EIO or 0.
        throw TransportError(describe() + ": link lost (" + (n == 0 ? std::string("end of file") : errno_text(errno)) + ")");
    }

    void flush_input() override {
        if (fd_ >= 0) ::tcflush(fd_, TCIFLUSH);
    }
    std::string describe() const override { return "serial " + path_; }
    bool is_serial() const override { return true; }
    bool can_set_baud(int baud) const override { return speed_table().count(baud) > 0; }
    void set_baud(int baud) override {
        require_open();
        if (!can_set_baud(baud)) throw TransportError(describe() + ": host cannot set " + std::to_string(baud) + " baud");
        configure(baud);
    }
    int baud() const override { return baud_; }

    void send_break() override {
        require_open();
        configure(9600);
        ::tcflush(fd_, TCIOFLUSH);
        // tcsendbreak(fd, 0) holds the line 0.25..0.5 s on a real port; on a pty it returns at
        // once and nothing crosses (the simulator sees the flush at 9600 instead, §9.4).
        if (::tcsendbreak(fd_, 0) != 0) throw TransportError(describe() + ": break failed: " + errno_text(errno));
    }

private:
    void require_open() const {
        if (fd_ < 0) throw TransportError(describe() + ": not open");
    }
    void configure(int baud) {
        termios tio{};
        if (::tcgetattr(fd_, &tio) != 0) throw TransportError(describe() + ": not a serial port: " + errno_text(errno));
        ::cfmakeraw(&tio);  // no canonical mode, echo, CR/LF translation or XON/XOFF
        tio.c_cflag |= CLOCAL | CREAD;
        tio.c_cflag &= ~(CSTOPB | PARENB | CRTSCTS | CSIZE);
        tio.c_cflag |= CS8;
        tio.c_cc[VMIN] = 0;
        tio.c_cc[VTIME] = 0;
        const speed_t sp = speed_table().at(baud);
        ::cfsetispeed(&tio, sp);
        ::cfsetospeed(&tio, sp);
        if (::tcsetattr(fd_, TCSANOW, &tio) != 0) throw TransportError(describe() + ": cannot set " + std::to_string(baud) + " 8N1: " + errno_text(errno));
        baud_ = baud;
    }

    std::string path_;
    int fd_ = -1;
    int baud_ = 9600;
};

class TcpTransport final : public Transport {
public:
    TcpTransport(std::string host, std::uint16_t port, std::chrono::milliseconds connect_timeout)
        : host_(std::move(host)), port_(port), connect_timeout_(connect_timeout) {}
    ~TcpTransport() override { close(); }

    void open() override {
        close();
        addrinfo hints{};
        hints.ai_family = AF_UNSPEC;
        hints.ai_socktype = SOCK_STREAM;
        addrinfo* res = nullptr;
        const int g = ::getaddrinfo(host_.c_str(), std::to_string(port_).c_str(), &hints, &res);
        if (g != 0) throw TransportError(describe() + ": cannot resolve: " + gai_strerror(g));
        std::string last = "no address";
        for (addrinfo* a = res; a; a = a->ai_next) {
            const int fd = ::socket(a->ai_family, a->ai_socktype | SOCK_NONBLOCK | SOCK_CLOEXEC, a->ai_protocol);
            if (fd < 0) continue;
            int rc = ::connect(fd, a->ai_addr, a->ai_addrlen);
            if (rc != 0 && errno == EINPROGRESS) {
                pollfd p{fd, POLLOUT, 0};
                rc = ::poll(&p, 1, poll_ms(connect_timeout_)) == 1 ? 0 : -1;
                int err = rc == 0 ? 0 : ETIMEDOUT;
                socklen_t len = sizeof err;
                if (rc == 0) ::getsockopt(fd, SOL_SOCKET, SO_ERROR, &err, &len);
                if (err != 0) {
                    errno = err;
                    rc = -1;
                }
            }
            if (rc == 0) {
                fd_ = fd;
                break;
            }
            last = errno_text(errno);
            ::close(fd);
        }
        ::freeaddrinfo(res);
        if (fd_ < 0) throw TransportError(describe() + ": cannot connect: " + last);
        const int one = 1, idle_s = 1, intvl_s = 1, count = 3;
        ::setsockopt(fd_, IPPROTO_TCP, TCP_NODELAY, &one, sizeof one);
        ::setsockopt(fd_, SOL_SOCKET, SO_KEEPALIVE, &one, sizeof one);
        ::setsockopt(fd_, IPPROTO_TCP, TCP_KEEPIDLE, &idle_s, sizeof idle_s);
        ::setsockopt(fd_, IPPROTO_TCP, TCP_KEEPINTVL, &intvl_s, sizeof intvl_s);
        ::setsockopt(fd_, IPPROTO_TCP, TCP_KEEPCNT, &count, sizeof count);
    }
    void close() override {
        if (fd_ >= 0) ::close(fd_);
        fd_ = -1;
    }
    bool is_open() const override { return fd_ >= 0; }

    void write(std::string_view bytes) override {
        require_open();
        std::size_t done = 0;
        while (done < bytes.size()) {
            const ssize_t n = ::send(fd_, bytes.data() + done, bytes.size() - done, MSG_NOSIGNAL);
            if (n > 0) {
                done += static_cast<std::size_t>(n);
                continue;
            }
            if (n < 0 && errno == EINTR) continue;
            if (n < 0 && errno == EAGAIN) {
                pollfd p{fd_, POLLOUT, 0};
                if (::poll(&p, 1, 1000) <= 0) throw TransportError(describe() + ": send stalled (half-open connection?)");
                continue;
            }
            throw TransportError(describe() + ": send failed: " + errno_text(errno));
        }
    }

    std::size_t read(std::span<std::uint8_t> buf, std::chrono::milliseconds timeout) override {
        require_open();
        pollfd p{fd_, POLLIN, 0};
        int r;
        do r = ::poll(&p, 1, poll_ms(timeout));
        while (r < 0 && errno == EINTR);
        if (r < 0) throw TransportError(describe() + ": poll failed: " + errno_text(errno));
        if (r == 0) return 0;
        const ssize_t n = ::recv(fd_, buf.data(), buf.size(), 0);
        if (n > 0) return static_cast<std::size_t>(n);
        if (n < 0 && (errno == EAGAIN || errno == EINTR)) return 0;
        throw TransportError(describe() + ": connection lost (" + (n == 0 ? std::string("closed by peer") : errno_text(errno)) + ")");
    }

    void flush_input() override {
        // Sockets have no tcflush: read and drop what is already here (ndicapi does not, and
        // stale bytes then answer the next command).
        if (fd_ < 0) return;
        std::uint8_t junk[4096];
        for (;;) {
            const ssize_t n = ::recv(fd_, junk, sizeof junk, MSG_DONTWAIT);
            if (n <= 0) break;
        }
    }
    std::string describe() const override { return "tcp " + host_ + ":" + std::to_string(port_); }

private:
    void require_open() const {
        if (fd_ < 0) throw TransportError(describe() + ": not connected");
    }
    std::string host_;
    std::uint16_t port_;
    std::chrono::milliseconds connect_timeout_;
    int fd_ = -1;
};

}  // namespace

std::vector<int> host_baud_rates() {
    std::vector<int> out;
    for (const auto& [b, s] : speed_table()) out.push_back(b);
    return out;
}

std::unique_ptr<Transport> make_serial_transport(std::string path) { return std::make_unique<SerialTransport>(std::move(path)); }

std::unique_ptr<Transport> make_tcp_transport(std::string host, std::uint16_t port, std::chrono::milliseconds connect_timeout) {
    return std::make_unique<TcpTransport>(std::move(host), port, connect_timeout);
}

std::vector<std::string> discover_serial_ports(const std::string& root) {
    namespace fs = std::filesystem;
    std::vector<std::string> out;
    std::set<std::string> targets;
    std::error_code ec;
    const fs::path by_id = fs::path(root) / "serial" / "by-id";
    if (fs::is_directory(by_id, ec)) {
        std::vector<std::string> links;
        for (const auto& de : fs::directory_iterator(by_id, ec)) links.push_back(de.path().string());
        std::sort(links.begin(), links.end());
        for (const auto& l : links) {
            out.push_back(l);
            const fs::path t = fs::weakly_canonical(fs::path(l), ec);
            if (!ec) targets.insert(t.filename().string());
        }
    }
    std::vector<std::string> ttys;
    for (const auto& de : fs::directory_iterator(root, ec)) {
        const std::string n = de.path().filename().string();
        if ((n.starts_with("ttyUSB") || n.starts_with("ttyACM")) && !targets.count(n)) ttys.push_back(de.path().string());
    }
    std::sort(ttys.begin(), ttys.end());
    out.insert(out.end(), ttys.begin(), ttys.end());
    return out;
}

std::pair<std::string, std::uint16_t> parse_host_port(const std::string& text, const std::string& what, bool allow_port_zero) {
    const auto colon = text.rfind(':');
    if (colon == std::string::npos || colon == 0 || colon + 1 == text.size())
        throw ConfigError(what + " " + text, "expected HOST:PORT");
    const std::string port_text = text.substr(colon + 1);
    if (!std::all_of(port_text.begin(), port_text.end(), [](char c) { return c >= '0' && c <= '9'; }) || port_text.size() > 5)
        throw ConfigError(what + " " + text, "port must be a number 1..65535");
    const long port = std::stol(port_text);
    if ((port < 1 && !(allow_port_zero && port == 0)) || port > 65535)
        throw ConfigError(what + " " + text, allow_port_zero ? "port must be 0..65535 (0: any free port)" : "port must be 1..65535");
    return {text.substr(0, colon), static_cast<std::uint16_t>(port)};
}

}  // namespace cf::tracker
