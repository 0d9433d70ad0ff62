// The executable: a bad configuration exits 2 naming the key; SIGTERM stops it cleanly
// (exit 0) while it streams the tracker.
#include <gtest/gtest.h>
#include <httplib.h>
#include <signal.h>
#include <arpa/inet.h>
#include <ifaddrs.h>
#include <netinet/in.h>
#include <sys/socket.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <thread>

namespace fs = std::filesystem;

namespace {
struct Proc {
    pid_t pid = -1;
    int out_fd = -1;  // stdout + stderr
};

Proc spawn(const std::vector<std::string>& args, const std::vector<std::string>& extra_env = {}) {
    int p[2];
    if (pipe(p) != 0) return {};
    const pid_t pid = fork();
    if (pid == 0) {
        dup2(p[1], 1);
        dup2(p[1], 2);
        close(p[0]);
        close(p[1]);
        std::vector<char*> argv;
        for (const auto& a : args) argv.push_back(const_cast<char*>(a.c_str()));
        argv.push_back(nullptr);
        for (const auto& e : extra_env) putenv(const_cast<char*>(e.c_str()));
        execv(argv[0], argv.data());
        _exit(127);
    }
    close(p[1]);
    return {pid, p[0]};
}

/// Reads until `needle` appears or the timeout; returns all read.
std::string read_until(int fd, const std::string& needle, double timeout_s) {
    std::string out;
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    while (std::chrono::steady_clock::now() < end && out.find(needle) == std::string::npos) {
        fd_set s;
        FD_ZERO(&s);
        FD_SET(fd, &s);
        timeval tv{0, 100000};
        if (select(fd + 1, &s, nullptr, nullptr, &tv) > 0) {
            char buf[4096];
            const ssize_t n = read(fd, buf, sizeof buf);
            if (n <= 0) break;
            out.append(buf, std::size_t(n));
        }
    }
    return out;
}

int wait_exit(pid_t pid, double timeout_s) {
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    while (std::chrono::steady_clock::now() < end) {
        int st = 0;
        if (waitpid(pid, &st, WNOHANG) == pid) return WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    kill(pid, SIGKILL);
    waitpid(pid, nullptr, 0);
    return -1;
}
}  // namespace

TEST(DaemonProcess, BadConfigurationExitsTwoNamingTheKey) {
    const auto dir = fs::temp_directory_path() / ("cf_daemon_proc_cfg_" + std::to_string(getpid()));
    fs::create_directories(dir);
    std::ofstream(dir / "bad.json") << R"({"http": {"threads": 1}})";
    Proc p = spawn({CF_CORTEXFUSED, "--config", (dir / "bad.json").string()});
    const std::string out = read_until(p.out_fd, "\n", 10);
    EXPECT_EQ(wait_exit(p.pid, 10), 2);
    EXPECT_NE(out.find("http.threads"), std::string::npos) << out;
    close(p.out_fd);
    // --print-default-config prints JSON that --check-config accepts back.
    p = spawn({CF_CORTEXFUSED, "--print-default-config"});
    const std::string def = read_until(p.out_fd, "\n}\n", 10);
    EXPECT_EQ(wait_exit(p.pid, 10), 0);
    close(p.out_fd);
    std::ofstream(dir / "default.json") << def;
    p = spawn({CF_CORTEXFUSED, "--config", (dir / "default.json").string(), "--check-config"});
    const std::string chk = read_until(p.out_fd, "ok", 10);
    EXPECT_EQ(wait_exit(p.pid, 10), 0) << chk;
    close(p.out_fd);
    fs::remove_all(dir);
}

TEST(DaemonProcess, SigtermStopsCleanlyWithExitZero) {
    const auto dir = fs::temp_directory_path() / ("cf_daemon_proc_" + std::to_string(getpid()));
    fs::create_directories(dir);
    std::ofstream(dir / "c.json") << nlohmann::json{{"jobs", {{"phantom_cases_at_start", 0}}}, {"renderer", {{"kind", "cpu"}}}}.dump();
    Proc p = spawn({CF_CORTEXFUSED, "--config", (dir / "c.json").string(), "--listen", "127.0.0.1:0", "--state-dir", (dir / "state").string()});
    ASSERT_GT(p.pid, 0);
    std::string out = read_until(p.out_fd, "/\n", 30);
    const auto at = out.find("listening on http://127.0.0.1:");
    ASSERT_NE(at, std::string::npos) << out;
    const int port = std::stoi(out.substr(at + std::string("listening on http://127.0.0.1:").size()));
    httplib::Client c("127.0.0.1", port);
    // Wait until the tracker streams, so the stop has a live driver session to end.
    bool streaming = false;
    for (int i = 0; i < 100 && !streaming; ++i) {
        auto r = c.Get("/api/status");
        if (r && r->status == 200) streaming = nlohmann::json::parse(r->body)["modules"]["tracker"]["state"] == "streaming";
        if (!streaming) std::this_thread::sleep_for(std::chrono::milliseconds(100));
    }
    EXPECT_TRUE(streaming);
    // A job running when the signal comes is cancelled and leaves nothing half-written.
    auto job = c.Post("/api/jobs", R"({"kind": "phantom", "params": {"n": 3, "folder": "late"}})", "application/json");
    ASSERT_TRUE(job);
    EXPECT_EQ(job->status, 202) << job->body;
    for (int i = 0; i < 50; ++i) {
        auto r = c.Get("/api/jobs/1");
        if (r && nlohmann::json::parse(r->body)["state"] == "running") break;
        std::this_thread::sleep_for(std::chrono::milliseconds(20));
    }
    const auto t0 = std::chrono::steady_clock::now();
    kill(p.pid, SIGTERM);
    const int code = wait_exit(p.pid, 20);
    const double stop_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    out += read_until(p.out_fd, "daemon: stopped", 2);
    close(p.out_fd);
    EXPECT_EQ(code, 0) << out;
    EXPECT_LT(stop_s, 10);
    EXPECT_NE(out.find("daemon: stopped"), std::string::npos) << out;
    EXPECT_NE(out.find("job 1 (phantom) cancelled"), std::string::npos) << out;
    EXPECT_FALSE(fs::exists(dir / "state" / "cases" / "late"));
    for (const auto& e : fs::directory_iterator(dir / "state" / "cases")) ADD_FAILURE() << "left behind: " << e.path();
    // The port is free again.
    auto r = c.Get("/api/status");
    EXPECT_FALSE(r);
    fs::remove_all(dir);
}

TEST(DaemonProcess, TalksToSystemdThroughNotifySocket) {
    // A datagram socket standing in for systemd's: READY=1 once up, WATCHDOG=1 pings at half
    // WATCHDOG_USEC while healthy, STATUS= lines, STOPPING=1 on SIGTERM.
    const auto dir = fs::temp_directory_path() / ("cf_daemon_notify_" + std::to_string(getpid()));
    fs::create_directories(dir);
    const std::string sock_path = (dir / "notify.sock").string();
    const int s = socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    ASSERT_GE(s, 0);
    sockaddr_un a{};
    a.sun_family = AF_UNIX;
    std::snprintf(a.sun_path, sizeof a.sun_path, "%s", sock_path.c_str());
    ASSERT_EQ(bind(s, reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
    std::ofstream(dir / "c.json") << nlohmann::json{{"jobs", {{"phantom_cases_at_start", 0}}}, {"renderer", {{"kind", "cpu"}}}}.dump();
    Proc p = spawn({CF_CORTEXFUSED, "--config", (dir / "c.json").string(), "--listen", "127.0.0.1:0", "--state-dir", (dir / "state").string()},
                   {"NOTIFY_SOCKET=" + sock_path, "WATCHDOG_USEC=400000"});
    ASSERT_GT(p.pid, 0);
    std::vector<std::string> msgs;
    auto receive_for = [&](double seconds) {
        const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(seconds);
        while (std::chrono::steady_clock::now() < end) {
            fd_set fs_;
            FD_ZERO(&fs_);
            FD_SET(s, &fs_);
            timeval tv{0, 50000};
            if (select(s + 1, &fs_, nullptr, nullptr, &tv) > 0) {
                char buf[4096];
                const ssize_t n = recv(s, buf, sizeof buf, 0);
                if (n > 0) msgs.emplace_back(buf, std::size_t(n));
            }
        }
    };
    auto count = [&](const std::string& what) {
        int n = 0;
        for (const auto& m : msgs) n += m.find(what) != std::string::npos;
        return n;
    };
    receive_for(4.0);
    EXPECT_EQ(count("READY=1"), 1);
    EXPECT_GE(count("WATCHDOG=1"), 5);  // every 0.2 s once up
    EXPECT_GE(count("STATUS=tracker streaming"), 1);
    kill(p.pid, SIGTERM);
    receive_for(1.0);
    EXPECT_EQ(wait_exit(p.pid, 20), 0);
    EXPECT_EQ(count("STOPPING=1"), 1);
    close(s);
    close(p.out_fd);
    fs::remove_all(dir);
}

TEST(DaemonProcess, PortInUseExitsOneNamingTheAddress) {
    const int s = socket(AF_INET, SOCK_STREAM | SOCK_CLOEXEC, 0);
    ASSERT_GE(s, 0);
    sockaddr_in a{};
    a.sin_family = AF_INET;
    a.sin_addr.s_addr = htonl(INADDR_LOOPBACK);
    ASSERT_EQ(bind(s, reinterpret_cast<sockaddr*>(&a), sizeof a), 0);
    ASSERT_EQ(listen(s, 1), 0);
    socklen_t len = sizeof a;
    getsockname(s, reinterpret_cast<sockaddr*>(&a), &len);
    const std::string listen_at = "127.0.0.1:" + std::to_string(ntohs(a.sin_port));
    const auto dir = fs::temp_directory_path() / ("cf_daemon_busy_" + std::to_string(getpid()));
    Proc p = spawn({CF_CORTEXFUSED, "--listen", listen_at, "--state-dir", (dir / "state").string()});
    const std::string out = read_until(p.out_fd, "cannot start", 20);
    EXPECT_EQ(wait_exit(p.pid, 20), 1) << out;
    EXPECT_NE(out.find("http.listen " + listen_at), std::string::npos) << out;
    close(p.out_fd);
    close(s);
    fs::remove_all(dir);
}

TEST(DaemonProcess, OtherHostsNeedALogin) {
    // A non-loopback address of this machine stands in for a review workstation.
    std::string host_ip;
    ifaddrs* ifs = nullptr;
    if (getifaddrs(&ifs) == 0) {
        for (ifaddrs* i = ifs; i && host_ip.empty(); i = i->ifa_next) {
            if (!i->ifa_addr || i->ifa_addr->sa_family != AF_INET) continue;
            char buf[INET_ADDRSTRLEN];
            inet_ntop(AF_INET, &reinterpret_cast<sockaddr_in*>(i->ifa_addr)->sin_addr, buf, sizeof buf);
            if (std::string(buf).rfind("127.", 0) != 0) host_ip = buf;
        }
        freeifaddrs(ifs);
    }
    if (host_ip.empty()) GTEST_SKIP() << "no non-loopback IPv4 address on this machine";
    const auto dir = fs::temp_directory_path() / ("cf_daemon_remote_" + std::to_string(getpid()));
    fs::create_directories(dir);
    std::ofstream(dir / "c.json") << nlohmann::json{{"jobs", {{"phantom_cases_at_start", 0}}}, {"tracker", {{"enabled", false}}}, {"renderer", {{"kind", "cpu"}}}}.dump();
    Proc p = spawn({CF_CORTEXFUSED, "--config", (dir / "c.json").string(), "--listen", "0.0.0.0:0", "--state-dir", (dir / "state").string()});
    std::string out = read_until(p.out_fd, "/\n", 30);
    const auto at = out.find("listening on http://0.0.0.0:");
    ASSERT_NE(at, std::string::npos) << out;
    const int port = std::stoi(out.substr(at + std::string("listening on http://0.0.0.0:").size()));
    httplib::Client kiosk("127.0.0.1", port), remote(host_ip, port);
    // The kiosk (loopback) creates a reviewer.
    auto r = kiosk.Post("/api/users", R"({"name": "rev", "password": "review-only", "role": "reviewer"})", "application/json");
    ASSERT_TRUE(r);
    ASSERT_EQ(r->status, 201) << r->body;
    // From the other address: status is open, the rest needs a session.
    r = remote.Get("/api/status");
    ASSERT_TRUE(r) << host_ip;
    EXPECT_EQ(r->status, 200);
    r = remote.Get("/api/cases");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 401) << r->body;
    r = remote.Post("/api/cases", R"({"title": "from afar"})", "application/json");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 401);
    r = remote.Post("/api/login", R"({"name": "rev", "password": "review-only"})", "application/json");
    ASSERT_TRUE(r);
    ASSERT_EQ(r->status, 200) << r->body;
    const std::string token = nlohmann::json::parse(r->body)["token"];
    httplib::Headers h{{"Authorization", "Bearer " + token}};
    r = remote.Get("/api/cases", h);
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 200) << r->body;
    r = remote.Post("/api/cases", h, R"({"title": "from afar"})", "application/json");
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 403) << r->body;
    kill(p.pid, SIGTERM);
    EXPECT_EQ(wait_exit(p.pid, 20), 0);
    close(p.out_fd);
    fs::remove_all(dir);
}
