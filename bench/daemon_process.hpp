#pragma once
// What the daemon benchmarks (daemon_load.cpp, daemon_memory.cpp) share about the cortexfused
// process they start: reading files (its log), /proc/<pid>/status fields (RSS), the machine's
// load average, starting it with its output in a log, reading its port from that log, and
// waiting for it to exit. Header-only; any thread.
#include <fcntl.h>
#include <sys/types.h>
#include <unistd.h>
#include <sys/wait.h>
#include <signal.h>

#include <chrono>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <thread>
#include <vector>

namespace cf::bench {

/// The whole file (empty when it cannot be read).
inline std::string read_file(const std::filesystem::path& p) {
    std::ifstream f(p, std::ios::binary);
    std::stringstream s;
    s << f.rdbuf();
    return s.str();
}

/// A field of /proc/<pid>/status in kB (VmHWM, VmRSS), -1 when absent.
inline long proc_status_kb(pid_t pid, const std::string& field) {
    std::ifstream f("/proc/" + std::to_string(pid) + "/status");
    std::string line;
    while (std::getline(f, line))
        if (line.rfind(field + ":", 0) == 0) return std::atol(line.c_str() + field.size() + 1);
    return -1;
}

/// The 1, 5 and 15 minute load averages.
inline std::vector<double> loadavg() {
    std::istringstream in(read_file("/proc/loadavg"));
    std::vector<double> v(3, 0.0);
    in >> v[0] >> v[1] >> v[2];
    return v;
}

/// Waits up to `timeout_s` for child `pid` to exit: its exit status (128 + signal when killed);
/// past the timeout it is killed (SIGKILL), reaped, and -1 returned.
inline int wait_exit(pid_t pid, double timeout_s) {
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

/// Starts `args` (args[0]: the executable) as a child process with stdout and stderr written
/// to `log` (truncated): its pid.
inline pid_t spawn_logged(std::vector<std::string> args, const std::filesystem::path& log) {
    const pid_t pid = fork();
    if (pid == 0) {
        const int fd = open(log.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
        dup2(fd, 1);
        dup2(fd, 2);
        std::vector<char*> argv;
        for (auto& a : args) argv.push_back(a.data());
        argv.push_back(nullptr);
        execv(argv[0], argv.data());
        _exit(127);
    }
    return pid;
}

/// The port cortexfused prints in `log` ("listening on http://127.0.0.1:PORT"), waiting up to
/// `timeout_s`: 0 when it did not print one in time, -1 when child `pid` exited first (reaped).
inline int wait_for_port(pid_t pid, const std::filesystem::path& log, double timeout_s) {
    const std::string needle = "listening on http://127.0.0.1:";
    const auto end = std::chrono::steady_clock::now() + std::chrono::duration<double>(timeout_s);
    while (std::chrono::steady_clock::now() < end) {
        const std::string text = read_file(log);
        if (const auto at = text.find(needle); at != std::string::npos) {
            const int port = std::atoi(text.c_str() + at + needle.size());
            if (port > 0) return port;
        }
        if (int st = 0; waitpid(pid, &st, WNOHANG) == pid) return -1;
        std::this_thread::sleep_for(std::chrono::milliseconds(50));
    }
    return 0;
}

}  // namespace cf::bench
