#pragma once
// Logging for cortexfused: under journald (JOURNAL_STREAM set, as systemd sets it) each line
// goes through sd_journal_send with structured fields (PRIORITY, CF_MODULE, CF_EVENT and any
// extra CF_* fields); otherwise one plain line on stderr: "<utc> <level> <module>: <message>".
// Never put a patient's name or identifier in a message or a field: logs name cases by their
// id only.
//
// Thread contract: log() may be called from any thread (one write per line).
#include <map>
#include <string>

namespace cf::daemon {

enum class LogLevel { debug = 7, info = 6, notice = 5, warning = 4, error = 3 };

/// `fields`: extra structured fields, upper-case keys without the CF_ prefix ("JOB_ID" -> CF_JOB_ID).
void log(LogLevel level, const std::string& module, const std::string& message,
         const std::map<std::string, std::string>& fields = {});
/// Whether lines go to journald (decided once, from JOURNAL_STREAM).
bool logging_to_journal();
/// Lowest level written (default info; CF_LOG_LEVEL=debug in the environment lowers it).
void set_log_level(LogLevel min_level);

}  // namespace cf::daemon
