// TCP keep-alive notices a half-open connection (issue 5: a Vega that vanished without a FIN or
// RST, e.g. its cable pulled or its power cut). In a private network namespace the loopback link
// is taken down after the transport connected: from then on nothing reaches the peer and nothing
// comes back, exactly a half-open connection. Without keep-alive a read would just time out for
// ever (0 bytes each time); with the transport's keep-alive (1 s idle, 3 probes 1 s apart) the
// kernel drops the connection and read() throws "connection lost (... timed out)" within ~4 s,
// which sends the session into recovery. Needs CAP_SYS_ADMIN for unshare(CLONE_NEWNET): skips
// without it.
#include <gtest/gtest.h>
#include <fcntl.h>
#include <net/if.h>
#include <netinet/in.h>
#include <sched.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <unistd.h>

#include <array>
#include <chrono>
#include <cstring>
#include <string>

#include "cortexfuse/drivers/tracker/transport.hpp"

using namespace std::chrono_literals;

namespace {

// Sets or clears IFF_UP on the namespace's loopback.
bool set_loopback_up(bool up) {
    const int s = ::socket(AF_INET, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    if (s < 0) return false;
    ifreq ifr{};
    std::strncpy(ifr.ifr_name, "lo", IFNAMSIZ - 1);
    bool ok = ::ioctl(s, SIOCGIFFLAGS, &ifr) == 0;
    if (ok) {
        ifr.ifr_flags = short(up ? (ifr.ifr_flags | IFF_UP) : (ifr.ifr_flags & ~IFF_UP));
        ok = ::ioctl(s, SIOCSIFFLAGS, &ifr) == 0;
    }
    ::close(s);
    return ok;
}

// Child exit codes.
constexpr int kSkip = 77, kNoError = 10, kWrongError = 11, kSetupFailed = 12, kReadWhileUp = 13;

// Runs in the forked child, inside its own network namespace; writes a line for the parent.
int half_open_child(int report_fd) {
    auto say = [&](const std::string& s) { [[maybe_unused]] auto n = ::write(report_fd, s.data(), s.size()); };
    if (::unshare(CLONE_NEWNET) != 0) {
        say(std::string("unshare(CLONE_NEWNET): ") + std::strerror(errno));
        return kSkip;
    }
    if (!set_loopback_up(true)) return say("loopback up failed"), kSetupFailed;
    const int srv = ::socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    socklen_t len = sizeof a;
    if (srv < 0 || ::bind(srv, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0 || ::listen(srv, 1) != 0 ||
        ::getsockname(srv, reinterpret_cast<sockaddr*>(&a), &len) != 0)
        return say("listener failed"), kSetupFailed;
    auto t = cf::tracker::make_tcp_transport("127.0.0.1", ntohs(a.sin_port), 1000ms);
    try {
        t->open();
    } catch (const std::exception& e) {
        return say(e.what()), kSetupFailed;
    }
    const int peer = ::accept4(srv, nullptr, nullptr, SOCK_CLOEXEC);
    if (peer < 0) return say("accept failed"), kSetupFailed;
    // While the link is up, a quiet peer is just a read timeout (0 bytes), not an error.
    std::array<std::uint8_t, 64> buf{};
    try {
        if (t->read(buf, 200ms) != 0) return say("bytes from a quiet peer"), kReadWhileUp;
    } catch (const std::exception& e) {
        return say(std::string("error while the link was up: ") + e.what()), kReadWhileUp;
    }
    if (!set_loopback_up(false)) return say("loopback down failed"), kSetupFailed;
    const auto t0 = std::chrono::steady_clock::now();
    while (std::chrono::steady_clock::now() - t0 < 15s) {
        try {
            t->read(buf, 500ms);
        } catch (const cf::tracker::TransportError& e) {
            const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
            say(std::to_string(s) + " s: " + e.what());
            return std::string(e.what()).find("connection lost") != std::string::npos ? 0 : kWrongError;
        }
    }
    say("no error within 15 s of the link going silent");
    return kNoError;
}

TEST(TrackerTransport, TcpKeepAliveNoticesAHalfOpenConnection) {
    int p[2];
    ASSERT_EQ(::pipe2(p, O_CLOEXEC), 0);
    const pid_t pid = ::fork();
    ASSERT_GE(pid, 0);
    if (pid == 0) {
        ::close(p[0]);
        ::_exit(half_open_child(p[1]));
    }
    ::close(p[1]);
    std::string said;
    char c[256];
    for (ssize_t n; (n = ::read(p[0], c, sizeof c)) > 0;) said.append(c, std::size_t(n));
    ::close(p[0]);
    int st = 0;
    ASSERT_EQ(::waitpid(pid, &st, 0), pid);
    ASSERT_TRUE(WIFEXITED(st)) << "child ended by signal " << WTERMSIG(st);
    if (WEXITSTATUS(st) == kSkip) GTEST_SKIP() << "no private network namespace here (" << said << ")";
    ASSERT_EQ(WEXITSTATUS(st), 0) << said;
    // 1 s idle + 3 probes 1 s apart: about 4 s; well before the 15 s the loop allows.
    const double s = std::stod(said);
    EXPECT_GT(s, 2.0) << said;
    EXPECT_LT(s, 8.0) << said;
    EXPECT_NE(said.find("tcp 127.0.0.1:"), std::string::npos) << "the error names the transport: " << said;
}

}  // namespace
