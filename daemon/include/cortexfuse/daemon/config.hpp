#pragma once
// cortexfused's configuration: one JSON file (or none: the embedded defaults run with the
// simulated tracker and camera and the bundled MRI). Every option is declared once, in
// config_options(), with its type, range, default and meaning; the parser, the validation
// errors, `--print-default-config` and the table in docs/daemon.md all come from that list.
//
// Errors: ConfigError("config <file>: <key>", problem), one line naming the key. Unknown keys
// are errors too (a typo must not silently fall back to a default).
#include <cstdint>
#include <nlohmann/json.hpp>
#include <stdexcept>
#include <string>
#include <vector>

namespace cf::daemon {

class ConfigError : public std::runtime_error {
public:
    ConfigError(const std::string& where, const std::string& problem) : std::runtime_error(where + ": " + problem) {}
};

/// One option: a dotted key ("http.listen"), its JSON type and range.
struct OptionSpec {
    enum class Type { string, integer, number, boolean, string_list };
    std::string key;
    Type type = Type::string;
    double min = 0, max = 0;             ///< integer / number: inclusive range
    std::vector<std::string> choices;    ///< string: allowed values (empty: any)
    nlohmann::json default_value;
    std::string meaning;
    std::string range_text() const;      ///< "1..64", "one of auto, cpu, gl", "any"
};
const std::vector<OptionSpec>& config_options();

struct DaemonConfig {
    // http
    std::string listen = "127.0.0.1:8080";  ///< HOST:PORT; port 0 picks a free one
    int http_threads = 16;
    std::int64_t max_body_bytes = 1 << 20;
    int request_timeout_ms = 30000;
    int http_nice = 0;                       ///< nice value of the connection threads
    std::string ui_dir;                      ///< static files served at /
    bool remote_requires_login = true;
    double push_default_tracker_hz = 30;
    int push_queue_frames = 512;
    // state
    std::string state_dir;                   ///< "" -> $STATE_DIRECTORY or ~/.local/state/cortexfused
    // case store and logins
    std::string store_dir;                   ///< "" -> state_dir/store
    std::int64_t max_upload_bytes = std::int64_t{1} << 30;  ///< volume/photo/zip uploads
    int session_ttl_s = 43200;
    // data
    std::string t1_path, brain_mask_path;
    std::string removable_media_root = "/media";  ///< media.removable_root: where USB sticks are mounted
    // tracker
    bool tracker_enabled = true;
    int tracker_nice = -10;                  ///< nice value of the driver's (and simulator's) threads
    int tracker_rt_priority = 20;            ///< SCHED_FIFO priority of those threads (0: none, nice only)
    int tracker_tty_worker_priority = 10;    ///< SCHED_FIFO priority of the kernel's tty workers (kworker/u*) on a tty link (0: off)
    std::string tracker_source = "sim";      ///< sim | serial | tcp
    std::string tracker_serial_port, tracker_tcp;
    std::string tracker_sim_link = "pty";    ///< pty | tcp
    double tracker_sim_rate_hz = 60;
    std::int64_t tracker_sim_seed = 1;
    std::string tracker_sim_faults;
    bool tracker_sim_camera_tool = false;    ///< add the tracked camera (CF-CAMERA) to the simulator's scene
    int tracker_baud = 115200;
    std::vector<std::string> tracker_roms;
    // camera
    std::string camera_backend = "sim";      ///< sim | gphoto2 | v4l2 | none
    std::string camera_device;               ///< "" -> the first the backend lists
    /// Where the simulated camera takes each photo from: auto (the tracker simulator's camera tool
    /// when its scene has one, else the scripted orbit) | orbit | tracker (the camera tool, required).
    std::string camera_sim_pose = "auto";
    /// Hand-eye of the simulated tracked camera, "tx ty tz qw qx qy qz" (mm); "" -> cf::sim::default_T_optics_from_tool().
    std::string camera_sim_T_optics_from_tool;
    // renderer
    std::string renderer = "auto";           ///< auto | gl | cpu
    int render_max_width = 2048, render_max_height = 2048;
    int jpeg_quality = 85;
    // jobs
    int phantom_cases_at_start = 1;
    std::int64_t phantom_seed = 1;
    int stop_timeout_ms = 5000;
    double job_progress_hz = 10;
    int jobs_kept = 200;
    int job_threads = 0;  ///< a job's TBB arena (and llvmpipe) threads; 0: cores - 1, at least 1
    int job_nice = 0;     ///< nice value of the job worker threads
    // watchdog
    int watchdog_check_ms = 1000;
    int tracker_stall_ms = 5000;
};

/// The embedded defaults as JSON (what --print-default-config prints). Paths to the bundled
/// data come from the build (CF_DATA_DIR) unless CF_DATA_DIR is set in the environment.
nlohmann::json default_config_json();
/// Validates every key (type, range, unknown keys) and fills the struct; missing keys take
/// their defaults. `source` names the file in errors. Throws ConfigError.
DaemonConfig parse_config(const nlohmann::json& j, const std::string& source);
/// Reads and parses a file; errors name the file (missing, unreadable, not JSON).
DaemonConfig load_config_file(const std::string& path);
/// The effective configuration back as JSON (served by GET /api/config).
nlohmann::json to_json(const DaemonConfig& c);
/// The markdown table of options (docs/daemon.md is generated from it).
std::string config_markdown_table();

}  // namespace cf::daemon
