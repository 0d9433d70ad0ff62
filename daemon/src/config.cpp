#include "cortexfuse/daemon/config.hpp"

#include <cmath>
#include <cstdlib>
#include <fstream>
#include <map>
#include <set>
#include <sstream>

#include "cortexfuse/core/install_paths.hpp"
#include "cortexfuse/drivers/sim/tracked_camera.hpp"
#include "cortexfuse/drivers/tracker/transport.hpp"

#ifndef CF_DATA_DIR
#define CF_DATA_DIR "data"
#endif
#ifndef CF_UI_DIR
#define CF_UI_DIR "ui/dist"
#endif

namespace cf::daemon {

namespace {

/// $CF_DATA_DIR, else the installed layout's data beside the executable, else the build's
/// (core/install_paths.hpp): an installed cortexfused run without --config finds its MRI.
std::string data_dir() { return cf::bundled_data_dir(CF_DATA_DIR).string(); }

std::string fmt_num(double v) {
    std::ostringstream s;
    s << v;
    return s.str();
}

using T = OptionSpec::Type;

std::vector<OptionSpec> make_options() {
    const std::string data = data_dir();
    std::vector<OptionSpec> o = {
        {"http.listen", T::string, 0, 0, {}, "127.0.0.1:8080",
         "HOST:PORT the HTTP server and the WebSocket listen on (port 0: any free port). 0.0.0.0:8080 opens it to the network (review workstations; they must log in)"},
        {"http.threads", T::integer, 2, 256, {}, 16, "Connection threads; each open WebSocket holds one"},
        {"http.max_body_bytes", T::integer, 1024, 1 << 30, {}, 1 << 20, "Largest request body accepted (413 above it)"},
        {"http.nice", T::integer, 0, 19, {}, 0,
         "Nice value of the connection threads (and the WebSocket writers they start); above 0 the tracker's driver thread wins the CPU first (no measurable gain with the simulator over a pty: docs/performance.md)"},
        {"http.request_timeout_ms", T::integer, 100, 600000, {}, 30000, "Socket read/write timeout per request"},
        {"http.ui_dir", T::string, 0, 0, {}, cf::bundled_ui_dir(CF_UI_DIR).string(), "Folder of the built web UI, served at / (a plain page says so when it has no index.html)"},
        {"http.remote_requires_login", T::boolean, 0, 0, {}, true,
         "Requests from other hosts than loopback need a session for anything but /api/status (sessions arrive with the case store; until then they are refused with 401)"},
        {"push.default_tracker_hz", T::number, 0, 1000, {}, 30,
         "Tracker frames per second sent to a WebSocket client that did not ask for a rate (0: every frame)"},
        {"push.queue_frames", T::integer, 16, 65536, {}, 512, "Messages waiting for the push thread before the oldest are dropped (counted in status)"},
        {"state_dir", T::string, 0, 0, {}, "",
         "Folder for generated cases and job results; empty: $STATE_DIRECTORY (systemd StateDirectory=) or ~/.local/state/cortexfused"},
        {"store.dir", T::string, 0, 0, {}, "", "The case store's folder (SQLite database + blobs); empty: state_dir/store"},
        {"store.max_upload_bytes", T::integer, 1024, 17179869184.0, {}, std::int64_t{1} << 30,
         "Largest file uploaded to a case (volume, photo, case zip; 413 above it); held in memory while it is checked"},
        {"auth.session_ttl_s", T::integer, 60, 2592000, {}, 43200, "Lifetime of a login session (POST /api/login), seconds"},
        {"data.t1", T::string, 0, 0, {}, data + "/t1_head_mne_ecog.nii.gz", "The MRI rendered by /api/render and used for the phantom cases"},
        {"data.brain_mask", T::string, 0, 0, {}, data + "/brainmask_mne_ecog_binary.nii.gz", "Its brain mask (brain-only presets and phantom cases)"},
        {"media.removable_root", T::string, 0, 0, {}, "/media",
         "Folder where removable media (USB sticks) are mounted; the UI lists volumes and DICOM series below it and imports one into a case (docs/api/case-data.md)"},
        {"tracker.enabled", T::boolean, 0, 0, {}, true, "Run the tracker module"},
        {"tracker.nice", T::integer, -20, 19, {}, -10,
         "Nice value the tracker's driver and simulator threads start with (below 0 needs CAP_SYS_NICE; without it they keep the daemon's and a warning is logged)"},
        {"tracker.tty_worker_priority", T::integer, 0, 99, {}, 10,
         "With a serial or pty link: SCHED_FIFO priority given to the kernel's unbound workqueue workers (kworker/u*), which carry a tty's bytes to its reader; restored at stop (0: off; needs CAP_SYS_NICE, else a warning is logged once)"},
        {"tracker.rt_priority", T::integer, 0, 99, {}, 20,
         "SCHED_FIFO priority of the tracker's driver and simulator threads (0: none); refused without CAP_SYS_NICE or RLIMIT_RTPRIO, then tracker.nice applies and a warning is logged once"},
        {"tracker.source", T::string, 0, 0, {"sim", "serial", "tcp"}, "sim",
         "sim: the NDI Polaris simulator in-process, reached through the real driver over a pty or TCP; serial: a Polaris on tracker.serial_port; tcp: a Vega at tracker.tcp"},
        {"tracker.serial_port", T::string, 0, 0, {}, "", "Serial device for source serial, e.g. /dev/serial/by-id/usb-NDI_..."},
        {"tracker.tcp", T::string, 0, 0, {}, "", "HOST:PORT for source tcp (a Vega listens on 8765)"},
        {"tracker.sim_link", T::string, 0, 0, {"pty", "tcp"}, "pty", "How the driver reaches the simulator"},
        {"tracker.sim_rate_hz", T::number, 20, 250, {}, 60, "Simulator frame rate: 20, 60 or 250"},
        {"tracker.sim_seed", T::integer, 0, 2147483647, {}, 1, "Simulator seed (noise, visibility)"},
        {"tracker.sim_faults", T::string, 0, 0, {}, "", "Simulator random faults, e.g. bit_flip=0.01,drop=0.01 (docs/tracker.md)"},
        {"tracker.sim_camera_tool", T::boolean, 0, 0, {}, false,
         "Add a tracked camera (CF-CAMERA) to the simulator's scene; the simulated camera then photographs from its pose (camera.sim_pose)"},
        {"tracker.baud", T::integer, 9600, 921600, {}, 115200, "Serial rate after COMM: 9600, 38400, 57600, 115200, 230400 or 921600"},
        {"tracker.roms", T::string_list, 0, 0, {}, nlohmann::json::array(),
         "Passive tool definitions (.rom files) to load; empty with the simulator: its reference and pointer"},
        {"camera.backend", T::string, 0, 0, {"sim", "gphoto2", "v4l2", "none"}, "sim", "Camera backend"},
        {"camera.device", T::string, 0, 0, {}, "", "Device id as the backend lists it; empty: the first one"},
        {"camera.sim_pose", T::string, 0, 0, {"auto", "orbit", "tracker"}, "auto",
         "Simulated camera's pose per photo: tracker = the tracker simulator's camera tool composed with camera.sim_T_optics_from_tool and the scene's patient registration (needs tracker.source sim and tracker.sim_camera_tool); orbit = a scripted orbit round the craniotomy; auto = tracker when the simulator has the camera tool, else orbit"},
        {"camera.sim_T_optics_from_tool", T::string, 0, 0, {}, "",
         "Simulated tracked camera's hand-eye transform, camera tool's marker frame to its optics, 'tx ty tz qw qx qy qz' (mm); empty: a plate on top of the camera, lens 45 mm ahead and 30 mm below (docs/camera.md)"},
        {"renderer.kind", T::string, 0, 0, {"auto", "gl", "cpu"}, "auto", "Ray caster for views and registration: auto tries GL (EGL, off-screen) then the CPU"},
        {"renderer.max_width", T::integer, 16, 8192, {}, 2048, "Largest view width a render request may ask for"},
        {"renderer.max_height", T::integer, 16, 8192, {}, 2048, "Largest view height"},
        {"renderer.jpeg_quality", T::integer, 10, 100, {}, 85, "Default JPEG quality of rendered views"},
        {"jobs.phantom_cases_at_start", T::integer, 0, 20, {}, 1,
         "Phantom cases generated under state_dir/cases/phantom at start when that folder has none (a 'phantom' job)"},
        {"jobs.phantom_seed", T::integer, 0, 2147483647, {}, 1, "Seed of those phantom cases"},
        {"jobs.stop_timeout_ms", T::integer, 0, 600000, {}, 5000, "On SIGTERM: how long running jobs get to finish after being cancelled"},
        {"jobs.progress_hz", T::number, 0.5, 100, {}, 10, "Most progress events per second per job"},
        {"jobs.threads", T::integer, 0, 1024, {}, 0,
         "Threads a job's parallel work may use (its own TBB arena; llvmpipe's threads too unless LP_NUM_THREADS is set); 0: hardware cores - 1, at least 1"},
        {"jobs.nice", T::integer, 0, 19, {}, 0,
         "Nice value of the job worker threads and the threads they start (e.g. 10: the tracker and HTTP threads win the CPU first, but a cancel takes longer to be seen under load)"},
        {"jobs.kept", T::integer, 1, 100000, {}, 200, "Finished jobs kept in memory for GET /api/jobs"},
        {"watchdog.check_ms", T::integer, 50, 60000, {}, 1000, "How often the watchdog thread checks the modules"},
        {"watchdog.tracker_stall_ms", T::integer, 100, 600000, {}, 5000,
         "A streaming tracker with no frame for this long is reported as stalled (STATUS=, and the watchdog stops pinging)"},
    };
    return o;
}

std::string type_name(T t) {
    switch (t) {
        case T::string: return "string";
        case T::integer: return "integer";
        case T::number: return "number";
        case T::boolean: return "boolean";
        case T::string_list: return "list of strings";
    }
    return "?";
}

// Flattens nested objects into dotted keys; a value that is an object where the schema has no
// prefix is reported as an unknown key.
void flatten(const nlohmann::json& j, const std::string& prefix, std::map<std::string, nlohmann::json>& out,
             const std::set<std::string>& known, const std::set<std::string>& known_prefixes, const std::string& source) {
    for (auto it = j.begin(); it != j.end(); ++it) {
        const std::string key = prefix.empty() ? it.key() : prefix + "." + it.key();
        if (known.count(key)) {
            out[key] = it.value();
        } else if (known_prefixes.count(key)) {
            if (!it.value().is_object()) throw ConfigError("config " + source + ": " + key, "must be an object");
            flatten(it.value(), key, out, known, known_prefixes, source);
        } else {
            throw ConfigError("config " + source + ": " + key, "unknown option (see docs/daemon.md)");
        }
    }
}

void check(const OptionSpec& s, const nlohmann::json& v, const std::string& where) {
    switch (s.type) {
        case T::string:
            if (!v.is_string()) throw ConfigError(where, "must be a string");
            if (!s.choices.empty()) {
                bool ok = false;
                for (const auto& c : s.choices) ok = ok || c == v.get<std::string>();
                if (!ok) throw ConfigError(where, "'" + v.get<std::string>() + "' is not " + s.range_text());
            }
            break;
        case T::integer: {
            if (!v.is_number_integer()) throw ConfigError(where, "must be an integer");
            const double x = double(v.get<std::int64_t>());
            if (x < s.min || x > s.max) throw ConfigError(where, std::to_string(v.get<std::int64_t>()) + " is out of range " + s.range_text());
            break;
        }
        case T::number: {
            if (!v.is_number()) throw ConfigError(where, "must be a number");
            const double x = v.get<double>();
            if (!std::isfinite(x) || x < s.min || x > s.max) throw ConfigError(where, fmt_num(x) + " is out of range " + s.range_text());
            break;
        }
        case T::boolean:
            if (!v.is_boolean()) throw ConfigError(where, "must be true or false");
            break;
        case T::string_list:
            if (!v.is_array()) throw ConfigError(where, "must be a list of strings");
            for (const auto& e : v)
                if (!e.is_string()) throw ConfigError(where, "must be a list of strings");
            break;
    }
}

}  // namespace

std::string OptionSpec::range_text() const {
    if (type == T::integer) return std::to_string(static_cast<long long>(min)) + ".." + std::to_string(static_cast<long long>(max));
    if (type == T::number) return fmt_num(min) + ".." + fmt_num(max);
    if (type == T::string && !choices.empty()) {
        std::string r = "one of ";
        for (size_t i = 0; i < choices.size(); ++i) r += (i ? ", " : "") + choices[i];
        return r;
    }
    if (type == T::boolean) return "true, false";
    return "any";
}

const std::vector<OptionSpec>& config_options() {
    static const std::vector<OptionSpec> opts = make_options();
    return opts;
}

nlohmann::json default_config_json() {
    nlohmann::json j = nlohmann::json::object();
    for (const auto& o : config_options()) j[nlohmann::json::json_pointer("/" + [&] {
        std::string p = o.key;
        for (auto& c : p)
            if (c == '.') c = '/';
        return p;
    }())] = o.default_value;
    return j;
}

DaemonConfig parse_config(const nlohmann::json& j, const std::string& source) {
    if (!j.is_object()) throw ConfigError("config " + source, "must be a JSON object");
    std::set<std::string> known, prefixes;
    std::map<std::string, const OptionSpec*> spec;
    for (const auto& o : config_options()) {
        known.insert(o.key);
        spec[o.key] = &o;
        for (size_t p = o.key.find('.'); p != std::string::npos; p = o.key.find('.', p + 1)) prefixes.insert(o.key.substr(0, p));
    }
    std::map<std::string, nlohmann::json> given;
    flatten(j, "", given, known, prefixes, source);
    std::map<std::string, nlohmann::json> v;
    for (const auto& o : config_options()) v[o.key] = o.default_value;
    for (const auto& [k, val] : given) {
        check(*spec[k], val, "config " + source + ": " + k);
        v[k] = val;
    }
    auto where = [&](const std::string& k) { return "config " + source + ": " + k; };

    DaemonConfig c;
    c.listen = v["http.listen"].get<std::string>();
    try {
        cf::tracker::parse_host_port(c.listen, where("http.listen"), true);
    } catch (const std::exception& e) {
        throw ConfigError(where("http.listen"), "'" + c.listen + "' is not HOST:PORT");
    }
    c.http_threads = v["http.threads"].get<int>();
    c.max_body_bytes = v["http.max_body_bytes"].get<std::int64_t>();
    c.request_timeout_ms = v["http.request_timeout_ms"].get<int>();
    c.http_nice = v["http.nice"].get<int>();
    c.ui_dir = v["http.ui_dir"].get<std::string>();
    c.remote_requires_login = v["http.remote_requires_login"].get<bool>();
    c.push_default_tracker_hz = v["push.default_tracker_hz"].get<double>();
    c.push_queue_frames = v["push.queue_frames"].get<int>();
    c.state_dir = v["state_dir"].get<std::string>();
    c.store_dir = v["store.dir"].get<std::string>();
    c.max_upload_bytes = v["store.max_upload_bytes"].get<std::int64_t>();
    c.session_ttl_s = v["auth.session_ttl_s"].get<int>();
    c.t1_path = v["data.t1"].get<std::string>();
    c.brain_mask_path = v["data.brain_mask"].get<std::string>();
    c.removable_media_root = v["media.removable_root"].get<std::string>();
    c.tracker_enabled = v["tracker.enabled"].get<bool>();
    c.tracker_nice = v["tracker.nice"].get<int>();
    c.tracker_rt_priority = v["tracker.rt_priority"].get<int>();
    c.tracker_tty_worker_priority = v["tracker.tty_worker_priority"].get<int>();
    c.tracker_source = v["tracker.source"].get<std::string>();
    c.tracker_serial_port = v["tracker.serial_port"].get<std::string>();
    c.tracker_tcp = v["tracker.tcp"].get<std::string>();
    c.tracker_sim_link = v["tracker.sim_link"].get<std::string>();
    c.tracker_sim_rate_hz = v["tracker.sim_rate_hz"].get<double>();
    c.tracker_sim_seed = v["tracker.sim_seed"].get<std::int64_t>();
    c.tracker_sim_faults = v["tracker.sim_faults"].get<std::string>();
    c.tracker_sim_camera_tool = v["tracker.sim_camera_tool"].get<bool>();
    c.tracker_baud = v["tracker.baud"].get<int>();
    c.tracker_roms = v["tracker.roms"].get<std::vector<std::string>>();
    c.camera_backend = v["camera.backend"].get<std::string>();
    c.camera_device = v["camera.device"].get<std::string>();
    c.camera_sim_pose = v["camera.sim_pose"].get<std::string>();
    c.camera_sim_T_optics_from_tool = v["camera.sim_T_optics_from_tool"].get<std::string>();
    c.renderer = v["renderer.kind"].get<std::string>();
    c.render_max_width = v["renderer.max_width"].get<int>();
    c.render_max_height = v["renderer.max_height"].get<int>();
    c.jpeg_quality = v["renderer.jpeg_quality"].get<int>();
    c.phantom_cases_at_start = v["jobs.phantom_cases_at_start"].get<int>();
    c.phantom_seed = v["jobs.phantom_seed"].get<std::int64_t>();
    c.stop_timeout_ms = v["jobs.stop_timeout_ms"].get<int>();
    c.job_progress_hz = v["jobs.progress_hz"].get<double>();
    c.job_threads = v["jobs.threads"].get<int>();
    c.job_nice = v["jobs.nice"].get<int>();
    c.jobs_kept = v["jobs.kept"].get<int>();
    c.watchdog_check_ms = v["watchdog.check_ms"].get<int>();
    c.tracker_stall_ms = v["watchdog.tracker_stall_ms"].get<int>();

    // Cross-field checks.
    if (c.tracker_enabled && c.tracker_source == "serial" && c.tracker_serial_port.empty())
        throw ConfigError(where("tracker.serial_port"), "must be set when tracker.source is serial");
    if (c.tracker_enabled && c.tracker_source == "tcp") {
        if (c.tracker_tcp.empty()) throw ConfigError(where("tracker.tcp"), "must be set when tracker.source is tcp");
        try {
            cf::tracker::parse_host_port(c.tracker_tcp, "tracker.tcp");
        } catch (const std::exception&) {
            throw ConfigError(where("tracker.tcp"), "'" + c.tracker_tcp + "' is not HOST:PORT");
        }
    }
    if (c.tracker_sim_rate_hz != 20 && c.tracker_sim_rate_hz != 60 && c.tracker_sim_rate_hz != 250)
        throw ConfigError(where("tracker.sim_rate_hz"), fmt_num(c.tracker_sim_rate_hz) + " is not one of 20, 60, 250");
    {
        const auto rates = cf::tracker::host_baud_rates();
        bool ok = false;
        for (int r : rates) ok = ok || r == c.tracker_baud;
        if (!ok) throw ConfigError(where("tracker.baud"), std::to_string(c.tracker_baud) + " is not a rate the host and the device both know");
    }
    if (c.t1_path.empty()) throw ConfigError(where("data.t1"), "must not be empty");
    if (c.camera_sim_pose == "tracker" && c.camera_backend == "sim" &&
        !(c.tracker_enabled && c.tracker_source == "sim" && c.tracker_sim_camera_tool))
        throw ConfigError(where("camera.sim_pose"),
                          "'tracker' needs the tracker simulator's camera tool (tracker.enabled true, tracker.source sim, "
                          "tracker.sim_camera_tool true)");
    if (!c.camera_sim_T_optics_from_tool.empty()) {
        try {
            cf::sim::parse_pose7(c.camera_sim_T_optics_from_tool, "value");
        } catch (const std::invalid_argument& e) {
            throw ConfigError(where("camera.sim_T_optics_from_tool"), e.what());
        }
    }
    return c;
}

DaemonConfig load_config_file(const std::string& path) {
    std::ifstream f(path);
    if (!f) throw ConfigError("config " + path, "cannot be read (missing or no permission)");
    nlohmann::json j;
    try {
        j = nlohmann::json::parse(f);
    } catch (const nlohmann::json::parse_error& e) {
        throw ConfigError("config " + path, std::string("is not valid JSON: ") + e.what());
    }
    return parse_config(j, path);
}

nlohmann::json to_json(const DaemonConfig& c) {
    return {{"http",
             {{"listen", c.listen},
              {"threads", c.http_threads},
              {"max_body_bytes", c.max_body_bytes},
              {"request_timeout_ms", c.request_timeout_ms},
              {"nice", c.http_nice},
              {"ui_dir", c.ui_dir},
              {"remote_requires_login", c.remote_requires_login}}},
            {"push", {{"default_tracker_hz", c.push_default_tracker_hz}, {"queue_frames", c.push_queue_frames}}},
            {"state_dir", c.state_dir},
            {"store", {{"dir", c.store_dir}, {"max_upload_bytes", c.max_upload_bytes}}},
            {"auth", {{"session_ttl_s", c.session_ttl_s}}},
            {"data", {{"t1", c.t1_path}, {"brain_mask", c.brain_mask_path}}},
            {"media", {{"removable_root", c.removable_media_root}}},
            {"tracker",
             {{"enabled", c.tracker_enabled},
              {"nice", c.tracker_nice},
              {"source", c.tracker_source},
              {"serial_port", c.tracker_serial_port},
              {"tcp", c.tracker_tcp},
              {"sim_link", c.tracker_sim_link},
              {"sim_rate_hz", c.tracker_sim_rate_hz},
              {"sim_seed", c.tracker_sim_seed},
              {"sim_faults", c.tracker_sim_faults},
              {"sim_camera_tool", c.tracker_sim_camera_tool},
              {"baud", c.tracker_baud},
              {"roms", c.tracker_roms}}},
            {"camera",
             {{"backend", c.camera_backend},
              {"device", c.camera_device},
              {"sim_pose", c.camera_sim_pose},
              {"sim_T_optics_from_tool", c.camera_sim_T_optics_from_tool}}},
            {"renderer",
             {{"kind", c.renderer}, {"max_width", c.render_max_width}, {"max_height", c.render_max_height}, {"jpeg_quality", c.jpeg_quality}}},
            {"jobs",
             {{"phantom_cases_at_start", c.phantom_cases_at_start},
              {"phantom_seed", c.phantom_seed},
              {"stop_timeout_ms", c.stop_timeout_ms},
              {"progress_hz", c.job_progress_hz},
              {"threads", c.job_threads},
              {"nice", c.job_nice},
              {"kept", c.jobs_kept}}},
            {"watchdog", {{"check_ms", c.watchdog_check_ms}, {"tracker_stall_ms", c.tracker_stall_ms}}}};
}

std::string config_markdown_table() {
    std::ostringstream s;
    s << "| key | type | range | default | meaning |\n|---|---|---|---|---|\n";
    for (const auto& o : config_options()) {
        std::string def = o.default_value.dump();
        if (o.key == "data.t1" || o.key == "data.brain_mask" || o.key == "http.ui_dir") def = "(from the build: source tree)";
        s << "| `" << o.key << "` | " << type_name(o.type) << " | " << o.range_text() << " | `" << def << "` | " << o.meaning << " |\n";
    }
    return s.str();
}

}  // namespace cf::daemon
