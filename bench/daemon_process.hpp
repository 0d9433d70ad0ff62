#pragma once
// What the daemon benchmarks (daemon_load.cpp, daemon_memory.cpp) share about the cortexfused
// process they start: reading files (its log), /proc/<pid>/status fields (RSS), the machine's
// load average, and waiting for it to exit. Header-only; any thread.
#include <sys/types.h>
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

}  // namespace cf::bench
