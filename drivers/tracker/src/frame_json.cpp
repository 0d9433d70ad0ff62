#include "cortexfuse/drivers/tracker/frame_json.hpp"

#include <Eigen/Geometry>

namespace cf::tracker {

const char* tool_status_name(ToolReading::Status s) {
    using S = ToolReading::Status;
    return s == S::ok ? "ok" : s == S::missing ? "missing" : s == S::disabled ? "disabled" : "unoccupied";
}

nlohmann::json frame_to_json(const TrackerFrame& f) {
    nlohmann::json j{{"seq", f.sequence},
                     {"frame", f.frame_number},
                     {"system_status", f.system_status},
                     {"receive_steady_ns", f.receive_steady_ns},
                     {"latency_us", (f.publish_steady_ns - f.receive_steady_ns) / 1000.0},
                     {"missed_before", f.frames_missed_before}};
    if (f.late) j["late"] = true;
    j["tools"] = nlohmann::json::array();
    for (const auto& t : f.tools) {
        nlohmann::json tj{{"name", t.name},
                          {"handle", t.handle},
                          {"status", tool_status_name(t.status)},
                          {"stale", t.stale},
                          {"out_of_volume", t.out_of_volume},
                          {"partially_out_of_volume", t.partially_out_of_volume},
                          {"port_status", t.port_status}};
        if (t.T_tracker_from_tool) {
            const Eigen::Quaterniond q(t.T_tracker_from_tool->linear());
            const Eigen::Vector3d p = t.T_tracker_from_tool->translation();
            tj["q_wxyz"] = {q.w(), q.x(), q.y(), q.z()};
            tj["t_mm"] = {p.x(), p.y(), p.z()};
            tj["rms_mm"] = t.rms_error_mm;
        }
        j["tools"].push_back(tj);
    }
    return j;
}

}  // namespace cf::tracker
