#pragma once
// A tracker frame as JSON: what `cortexfuse track --json` prints and what the daemon pushes
// (notify_tracker_frame, GET /api/tracker/frame). One function, so both say the same.
#include <nlohmann/json.hpp>

#include "cortexfuse/drivers/tracker/session.hpp"

namespace cf::tracker {

/// "ok", "missing", "disabled" or "unoccupied".
const char* tool_status_name(ToolReading::Status s);

/// {seq, frame, system_status, receive_steady_ns, latency_us, tools: [{name, handle, status
/// ("ok", "missing", "disabled", "unoccupied"), stale, out_of_volume, partially_out_of_volume,
/// port_status, and when seen: q_wxyz, t_mm (T_tracker_from_tool), rms_mm}]}.
nlohmann::json frame_to_json(const TrackerFrame& f);

}  // namespace cf::tracker
