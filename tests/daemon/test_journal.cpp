// cortexfused under journald (issue 6: "journald logging (structured fields, no patient names in
// logs)"). A child process makes a private mount namespace with a tmpfs on /run and binds the
// journal's datagram socket (/run/systemd/journal/socket) there, starts the real cortexfused with
// JOURNAL_STREAM set (as systemd sets it), and forwards every datagram the daemon sends to the
// test. The test then drives a case with patient identifiers through the API (created, searched,
// refused for bad values that carry the name, exported) and stops the daemon: every entry must
// carry MESSAGE, PRIORITY, SYSLOG_IDENTIFIER=cortexfused and CF_MODULE; the listening entry its
// CF_PORT; and no entry may hold the patient's name, MRN or birth date. Skips without
// CAP_SYS_ADMIN (unshare/mount refused).
#include <gtest/gtest.h>
#include <httplib.h>
#include <sched.h>
#include <signal.h>
#include <sys/mount.h>
#include <sys/socket.h>
#include <sys/stat.h>
#include <sys/un.h>
#include <sys/wait.h>
#include <unistd.h>

#include <chrono>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>
#include <vector>

namespace fs = std::filesystem;
using json = nlohmann::json;

namespace {

constexpr int kSkip = 77;

void write_all(int fd, const std::string& s) {
    std::size_t done = 0;
    while (done < s.size()) {
        const ssize_t n = ::write(fd, s.data() + done, s.size() - done);
        if (n <= 0) return;
        done += std::size_t(n);
    }
}

// The child: namespace, journal socket, the daemon; forwards "<pid>\n" then "<len>\n<datagram>"
// records until the daemon has exited, then "-<exit status>\n".
[[noreturn]] void journal_child(int out_fd, const std::vector<std::string>& args) {
    if (::unshare(CLONE_NEWNS) != 0 || ::mount(nullptr, "/", nullptr, MS_REC | MS_PRIVATE, nullptr) != 0 ||
        ::mount("cf-journal-test", "/run", "tmpfs", 0, "size=1m,mode=0755") != 0) {
        write_all(out_fd, std::string("skip ") + std::strerror(errno) + "\n");
        ::_exit(kSkip);
    }
    ::mkdir("/run/systemd", 0755);
    ::mkdir("/run/systemd/journal", 0755);
    const int s = ::socket(AF_UNIX, SOCK_DGRAM | SOCK_CLOEXEC, 0);
    sockaddr_un a{};
    a.sun_family = AF_UNIX;
    std::snprintf(a.sun_path, sizeof a.sun_path, "%s", "/run/systemd/journal/socket");
    if (s < 0 || ::bind(s, reinterpret_cast<sockaddr*>(&a), sizeof a) != 0) {
        write_all(out_fd, "skip cannot bind the journal socket\n");
        ::_exit(kSkip);
    }
    const pid_t d = ::fork();
    if (d == 0) {
        std::vector<char*> argv;
        for (const auto& x : args) argv.push_back(const_cast<char*>(x.c_str()));
        argv.push_back(nullptr);
        ::setenv("JOURNAL_STREAM", "8:12345", 1);
        ::setenv("CF_LOG_LEVEL", "debug", 1);
        ::execv(argv[0], argv.data());
        ::_exit(127);
    }
    write_all(out_fd, std::to_string(d) + "\n");
    int status = 0;
    for (;;) {
        fd_set fs_;
        FD_ZERO(&fs_);
        FD_SET(s, &fs_);
        timeval tv{0, 50000};
        if (::select(s + 1, &fs_, nullptr, nullptr, &tv) > 0) {
            std::vector<char> buf(1 << 16);
            const ssize_t n = ::recv(s, buf.data(), buf.size(), 0);
            if (n > 0) write_all(out_fd, std::to_string(n) + "\n" + std::string(buf.data(), std::size_t(n)));
            continue;
        }
        if (::waitpid(d, &status, WNOHANG) == d) break;
    }
    // Whatever the daemon sent last.
    for (;;) {
        std::vector<char> buf(1 << 16);
        const ssize_t n = ::recv(s, buf.data(), buf.size(), MSG_DONTWAIT);
        if (n <= 0) break;
        write_all(out_fd, std::to_string(n) + "\n" + std::string(buf.data(), std::size_t(n)));
    }
    write_all(out_fd, "-" + std::to_string(WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status)) + "\n");
    ::_exit(0);
}

// Reads the child's records as they come.
struct Reader {
    int fd;
    std::string buf;
    bool fill(double timeout_s) {
        fd_set s;
        FD_ZERO(&s);
        FD_SET(fd, &s);
        timeval tv{long(timeout_s), long((timeout_s - long(timeout_s)) * 1e6)};
        if (::select(fd + 1, &s, nullptr, nullptr, &tv) <= 0) return false;
        char c[65536];
        const ssize_t n = ::read(fd, c, sizeof c);
        if (n <= 0) return false;
        buf.append(c, std::size_t(n));
        return true;
    }
    // Next line (without '\n') or nullopt within the timeout.
    std::optional<std::string> line(double timeout_s) {
        const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
        for (;;) {
            if (const auto nl = buf.find('\n'); nl != std::string::npos) {
                std::string l = buf.substr(0, nl);
                buf.erase(0, nl + 1);
                return l;
            }
            const double left = std::chrono::duration<double>(end - std::chrono::steady_clock::now()).count();
            if (left <= 0 || !fill(left)) return std::nullopt;
        }
    }
    std::optional<std::string> bytes(std::size_t n, double timeout_s) {
        const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
        while (buf.size() < n) {
            const double left = std::chrono::duration<double>(end - std::chrono::steady_clock::now()).count();
            if (left <= 0 || !fill(left)) return std::nullopt;
        }
        std::string b = buf.substr(0, n);
        buf.erase(0, n);
        return b;
    }
};

// A native journal datagram: FIELD=value lines (values here never hold a newline: the daemon's
// messages are one line), parsed into a map.
std::map<std::string, std::string> parse_entry(const std::string& d) {
    std::map<std::string, std::string> m;
    std::size_t at = 0;
    while (at < d.size()) {
        const auto nl = d.find('\n', at);
        const std::string l = d.substr(at, nl == std::string::npos ? std::string::npos : nl - at);
        if (const auto eq = l.find('='); eq != std::string::npos) m[l.substr(0, eq)] = l.substr(eq + 1);
        if (nl == std::string::npos) break;
        at = nl + 1;
    }
    return m;
}

TEST(DaemonJournal, EntriesHaveStructuredFieldsAndNoPatientIdentifiers) {
    const auto dir = fs::temp_directory_path() / ("cf_daemon_journal_" + std::to_string(::getpid()));
    fs::create_directories(dir);
    std::ofstream(dir / "c.json") << json{{"jobs", {{"phantom_cases_at_start", 0}}}, {"tracker", {{"enabled", false}}},
                                          {"renderer", {{"kind", "cpu"}}}}
                                         .dump();
    const std::vector<std::string> args = {CF_CORTEXFUSED, "--config", (dir / "c.json").string(), "--listen", "127.0.0.1:0",
                                           "--state-dir", (dir / "state").string()};
    int p[2];
    ASSERT_EQ(::pipe(p), 0);
    const pid_t child = ::fork();
    ASSERT_GE(child, 0);
    if (child == 0) {
        ::close(p[0]);
        journal_child(p[1], args);
    }
    ::close(p[1]);
    Reader rd{p[0], {}};
    const auto first = rd.line(10);
    ASSERT_TRUE(first.has_value());
    if (first->rfind("skip", 0) == 0) {
        int st = 0;
        ::waitpid(child, &st, 0);
        ::close(p[0]);
        fs::remove_all(dir);
        GTEST_SKIP() << "no private mount namespace here (" << *first << ")";
    }
    const pid_t daemon_pid = std::stoi(*first);
    std::vector<std::map<std::string, std::string>> entries;
    std::string raw;
    int daemon_exit = -1;
    // Reads records until `until` says stop or the timeout; returns whether it stopped.
    auto read_records = [&](const std::function<bool()>& until, double timeout_s) {
        const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
        while (std::chrono::steady_clock::now() < end) {
            if (until()) return true;
            const auto l = rd.line(0.2);
            if (!l) continue;
            if (!l->empty() && (*l)[0] == '-') {
                daemon_exit = std::stoi(l->substr(1));
                return until();
            }
            const auto d = rd.bytes(std::stoul(*l), 5);
            if (!d) break;
            raw += *d + "\n";
            entries.push_back(parse_entry(*d));
        }
        return until();
    };
    int port = 0;
    ASSERT_TRUE(read_records(
        [&] {
            for (const auto& e : entries)
                if (e.count("CF_PORT")) port = std::stoi(e.at("CF_PORT"));
            return port > 0;
        },
        30))
        << "no listening entry in the journal:\n"
        << raw;

    // A case with patient identifiers, through the API the kiosk uses (loopback: no login).
    const std::string family = "Zabriskiequist", given = "Quentinella", mrn = "MRN-QX77311", birth = "1961-04-05";
    httplib::Client c("127.0.0.1", port);
    auto post = [&](const std::string& path, const json& body) {
        auto r = c.Post(path, body.dump(), "application/json");
        return r ? r->status : -1;
    };
    EXPECT_EQ(post("/api/cases", {{"title", "journal test"}, {"patient", {{"mrn", mrn}, {"family_name", family}, {"given_name", given}, {"birth_date", birth}}}}), 201);
    // Refused inputs that carry the identifiers (their answers may name them; the logs may not).
    EXPECT_EQ(post("/api/cases", {{"title", "bad date"}, {"patient", {{"mrn", mrn + "X"}, {"family_name", family}, {"birth_date", "05/04/1961 " + family}}}}), 400);
    EXPECT_EQ(post("/api/cases", {{"title", "long"}, {"patient", {{"mrn", mrn + "Y"}, {"family_name", std::string(250, 'z') + family}}}}), 400);
    EXPECT_EQ(post("/api/cases", {{"title", "field"}, {"patient", {{"mrn", mrn}, {family, given}}}}), 400);
    const int state_status = post("/api/cases/999999/state", {{"state", family}});
    EXPECT_TRUE(state_status == 400 || state_status == 404) << state_status;
    auto r = c.Get("/api/cases?text=" + family);
    ASSERT_TRUE(r);
    EXPECT_EQ(r->status, 200);
    const json found = json::parse(r->body)["cases"];
    ASSERT_EQ(found.size(), 1u) << "the search by the patient's name finds the case: " << r->body;
    EXPECT_EQ(found[0]["title"], "journal test");
    // The case with its patient (the answer names them; the logs may not).
    const int case_id = found[0]["id"];
    r = c.Get("/api/cases/" + std::to_string(case_id));
    ASSERT_TRUE(r);
    EXPECT_NE(r->body.find(family), std::string::npos) << r->body;
    // The export job (a zip of the case, patient data included) logs as it runs.
    EXPECT_EQ(post("/api/jobs", {{"kind", "export"}, {"params", {{"case_id", case_id}}}}), 202);
    std::this_thread::sleep_for(std::chrono::milliseconds(500));

    ::kill(daemon_pid, SIGTERM);
    EXPECT_TRUE(read_records([&] { return daemon_exit >= 0; }, 30)) << "the daemon did not stop";
    int st = 0;
    ::waitpid(child, &st, 0);
    ::close(p[0]);
    EXPECT_EQ(daemon_exit, 0);

    ASSERT_GE(entries.size(), 3u) << raw;
    bool stopped = false;
    for (const auto& e : entries) {
        EXPECT_TRUE(e.count("MESSAGE")) << raw;
        EXPECT_TRUE(e.count("PRIORITY")) << raw;
        EXPECT_EQ(e.count("SYSLOG_IDENTIFIER") ? e.at("SYSLOG_IDENTIFIER") : "", "cortexfused");
        ASSERT_TRUE(e.count("CF_MODULE")) << raw;
        if (e.count("MESSAGE")) {
            EXPECT_EQ(e.at("MESSAGE").rfind(e.at("CF_MODULE") + ": ", 0), 0u) << e.at("MESSAGE");
        }
        stopped = stopped || (e.count("MESSAGE") && e.at("MESSAGE") == "daemon: stopped");
    }
    EXPECT_TRUE(stopped) << raw;
    for (const std::string& id : {family, given, mrn, birth}) {
        EXPECT_EQ(raw.find(id), std::string::npos) << id << " in the journal:\n" << raw;
    }
    fs::remove_all(dir);
}

}  // namespace
