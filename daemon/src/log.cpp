#include "cortexfuse/daemon/log.hpp"

#include <systemd/sd-journal.h>

#include <atomic>
#include <cstdio>
#include <cstdlib>
#include <mutex>
#include <vector>

#include "cortexfuse/daemon/jobs.hpp"

namespace cf::daemon {

namespace {
std::atomic<int> g_min_level{int(LogLevel::info)};

const char* level_name(LogLevel l) {
    switch (l) {
        case LogLevel::debug: return "debug";
        case LogLevel::info: return "info";
        case LogLevel::notice: return "notice";
        case LogLevel::warning: return "warning";
        case LogLevel::error: return "error";
    }
    return "?";
}
}  // namespace

bool logging_to_journal() {
    static const bool journal = [] {
        const char* s = std::getenv("JOURNAL_STREAM");
        return s && *s;
    }();
    return journal;
}

void set_log_level(LogLevel l) { g_min_level.store(int(l)); }

void log(LogLevel level, const std::string& module, const std::string& message, const std::map<std::string, std::string>& fields) {
    if (int(level) > g_min_level.load()) return;
    if (logging_to_journal()) {
        // sd_journal_sendv: one iovec per FIELD=value, no format strings built from input.
        std::vector<std::string> items;
        items.push_back("MESSAGE=" + module + ": " + message);
        items.push_back("PRIORITY=" + std::to_string(int(level)));
        items.push_back("SYSLOG_IDENTIFIER=cortexfused");
        items.push_back("CF_MODULE=" + module);
        for (const auto& [k, v] : fields) items.push_back("CF_" + k + "=" + v);
        std::vector<iovec> iov;
        for (auto& s : items) iov.push_back({s.data(), s.size()});
        sd_journal_sendv(iov.data(), int(iov.size()));
        return;
    }
    std::string line = utc_now_iso() + " " + level_name(level) + " " + module + ": " + message;
    for (const auto& [k, v] : fields) line += " " + k + "=" + v;
    line += "\n";
    static std::mutex mu;
    std::lock_guard lk(mu);
    std::fwrite(line.data(), 1, line.size(), stderr);
}

}  // namespace cf::daemon
