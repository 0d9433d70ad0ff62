#include "cortexfuse/daemon/daemon.hpp"

#include <atomic>
#include <condition_variable>
#include <cstdlib>
#include <deque>
#include <filesystem>
#include <future>
#include <limits>
#include <mutex>
#include <regex>
#include <sstream>
#include <thread>

#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/registration.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/daemon/jobs.hpp"
#include "cortexfuse/daemon/log.hpp"
#include "cortexfuse/drivers/camera.hpp"
#include "cortexfuse/drivers/sim/tracked_camera.hpp"
#include "cortexfuse/render/renderer_factory.hpp"
#include "case_api.hpp"
#include "case_jobs.hpp"
#include "cortexfuse/db/case_store.hpp"
#include "http_server.hpp"
#include "navigation_api.hpp"
#include "render_module.hpp"
#include "tags_api.hpp"
#include "landmark_pose_api.hpp"
#include "drafts_api.hpp"
#include "thumbnail_api.hpp"
#include "media_api.hpp"
#include "tracker_module.hpp"

namespace cf::daemon {

namespace fs = std::filesystem;
using cf::tracker::steady_ns;

const char* const kVersion = "0.1.0";

std::string resolve_state_dir(const DaemonConfig& c) {
    if (!c.state_dir.empty()) return c.state_dir;
    if (const char* s = std::getenv("STATE_DIRECTORY"); s && *s) {
        std::string first(s);
        return first.substr(0, first.find(':'));  // systemd may list several
    }
    if (const char* h = std::getenv("HOME"); h && *h) return std::string(h) + "/.local/state/cortexfused";
    return "/tmp/cortexfused";
}

namespace {

/// The camera module: the configured backend, opened on first use, on the camera's own
/// thread (the Camera contract: one thread at a time; and the simulated camera's scene building
/// needs more stack than a connection thread has). Callers wait for their capture.
class CameraModule {
public:
    /// `tracker` (may be null, outlives this): its simulator's camera tool places the simulated
    /// camera (camera.sim_pose).
    CameraModule(const DaemonConfig& c, const TrackerModule* tracker) : cfg_(c), tracker_(tracker) {
        thread_ = std::thread([this] { loop(); });
    }
    ~CameraModule() { stop(); }
    /// Ends the camera thread (closing the camera); later captures answer 503.
    void stop() {
        {
            std::lock_guard lk(q_mu_);
            stop_ = true;
        }
        q_cv_.notify_all();
        if (thread_.joinable()) thread_.join();
    }
    nlohmann::json status_json() const {
        std::lock_guard lk(mu_);
        nlohmann::json j{{"backend", cfg_.camera_backend}, {"device", cfg_.camera_device}, {"state", state_}, {"live", live_on_.load()}};
        if (!pose_source_.empty()) j["pose_source"] = pose_source_;
        if (!error_.empty()) j["last_error"] = error_;
        if (!model_.empty()) {
            j["model"] = model_;
            j["id"] = id_;
            j["counters"] = {{"captures", stats_.captures}, {"frames", stats_.frames}, {"errors", stats_.errors}, {"dropped", stats_.dropped}};
            j["last_capture_ms"] = stats_.last_capture_ms;
        }
        return j;
    }
    /// Live view (docs/api/camera.md): the newest live frame after sequence `after` as JPEG,
    /// waiting up to `wait` for one. Each call keeps the stream running for kLiveIdle more; the
    /// camera thread stops it when nobody asked for that long (the screen was left).
    struct LiveJpeg {
        std::string bytes;
        std::uint64_t sequence = 0;
        int width = 0, height = 0;
    };
    LiveJpeg live_jpeg(std::uint64_t after, int max_width, int quality, std::chrono::milliseconds wait) {
        if (cfg_.camera_backend == "none") throw ApiError(503, "unavailable", "camera: camera.backend is none");
        {
            std::lock_guard lk(q_mu_);
            if (stop_) throw ApiError(503, "unavailable", "camera: the daemon is stopping");
            live_until_ = std::chrono::steady_clock::now() + kLiveIdle;
        }
        {
            std::lock_guard lk(live_mu_);
            live_error_.clear();  // a failure before this request is not its answer
        }
        q_cv_.notify_all();
        // While a request waits the stream runs whatever the idle time (a slow camera's frame can
        // take longer than kLiveIdle); the idle time counts from its answer.
        ++live_waiters_;
        std::unique_lock lk(live_mu_);
        live_cv_.wait_for(lk, wait, [&] { return (live_frame_.sequence > after && !live_frame_.bgr.empty()) || !live_error_.empty(); });
        --live_waiters_;
        {
            std::lock_guard qk(q_mu_);
            live_until_ = std::chrono::steady_clock::now() + kLiveIdle;
        }
        if (live_frame_.bgr.empty() || live_frame_.sequence <= after) {
            if (!live_error_.empty()) throw ApiError(503, "unavailable", "camera live view: " + live_error_);
            const std::string st = status_json().value("state", std::string("?"));
            throw ApiError(503, "unavailable", "camera live view: no new frame within " + std::to_string(wait.count()) + " ms (camera " + st + ")");
        }
        cv::Mat img = live_frame_.bgr;
        const std::uint64_t seq = live_frame_.sequence;
        lk.unlock();
        // Encoded here, on the caller's thread: the camera thread only copies frames.
        if (img.cols > max_width) cv::resize(img, img, cv::Size(max_width, std::max(1, int(std::lround(double(img.rows) * max_width / img.cols)))), 0, 0, cv::INTER_AREA);
        std::vector<uchar> buf;
        cv::imencode(".jpg", img, buf, {cv::IMWRITE_JPEG_QUALITY, quality});
        return {std::string(buf.begin(), buf.end()), seq, img.cols, img.rows};
    }
    cf::camera::Photo capture() {
        if (cfg_.camera_backend == "none") throw ApiError(503, "unavailable", "camera: camera.backend is none");
        std::packaged_task<cf::camera::Photo()> task([this] { return capture_on_thread(); });
        auto fut = task.get_future();
        {
            std::lock_guard lk(q_mu_);
            if (stop_) throw ApiError(503, "unavailable", "camera: the daemon is stopping");
            queue_.push_back(std::move(task));
        }
        q_cv_.notify_all();
        return fut.get();
    }

private:
    void loop() {
        for (;;) {
            std::packaged_task<cf::camera::Photo()> task;
            bool live = false;
            {
                std::unique_lock lk(q_mu_);
                const auto wants_live = [&] { return live_waiters_ > 0 || live_until_ > std::chrono::steady_clock::now(); };
                if (!live_on_) q_cv_.wait(lk, [&] { return stop_ || !queue_.empty() || wants_live(); });
                if (stop_) break;  // abandoned tasks answer broken_promise to their callers
                if (!queue_.empty()) {
                    task = std::move(queue_.front());
                    queue_.pop_front();
                }
                live = wants_live();
            }
            if (task.valid()) {
                task();
                continue;
            }
            if (live) live_step();
            else if (live_on_) stop_live();
        }
        if (live_on_) stop_live();
        queue_.clear();
        cam_.reset();
        backend_.reset();
    }
    /// Camera thread: one live frame (starting the stream first), at most kLiveFps a second.
    void live_step() {
        try {
            open_on_thread();
            if (!live_on_) {
                cam_->start_stream({640, 480, kLiveFps});
                live_on_ = true;
            }
            cf::camera::Frame f;
            if (!cam_->next_frame(f, std::chrono::milliseconds(200)) || f.bgr.empty()) return;
            const auto now = std::chrono::steady_clock::now();
            {
                std::lock_guard lk(live_mu_);
                live_frame_.bgr = f.bgr;
                live_frame_.sequence = ++live_seq_;
                live_error_.clear();
            }
            live_cv_.notify_all();
            {
                std::lock_guard lk(mu_);
                stats_ = cam_->stats();
            }
            // Pace: no faster than kLiveFps whatever the device delivers.
            const auto next = now + std::chrono::microseconds(int64_t(1e6 / kLiveFps));
            std::unique_lock lk(q_mu_);
            q_cv_.wait_until(lk, next, [&] { return stop_ || !queue_.empty(); });
        } catch (const std::exception& e) {
            {
                std::lock_guard lk(live_mu_);
                live_error_ = e.what();
            }
            live_cv_.notify_all();
            {
                std::lock_guard lk(mu_);
                error_ = e.what();
            }
            stop_live();
            std::unique_lock lk(q_mu_);
            live_until_ = {};  // the next request starts it again
            q_cv_.wait_for(lk, std::chrono::milliseconds(500), [&] { return stop_; });  // a failing camera is retried at most twice a second
        }
    }
    void stop_live() {
        if (cam_ && live_on_) {
            try {
                cam_->stop_stream();
            } catch (const std::exception&) {
            }
        }
        live_on_ = false;
    }
    void open_on_thread() {
        if (cam_) return;
        set_state("opening");
        cf::camera::SimCameraConfig sc;
        sc.volume_path = cfg_.t1_path;
        sc.mask_path = cfg_.brain_mask_path;
        auto backend = cf::camera::make_backend(cfg_.camera_backend, sc);
        std::string id = cfg_.camera_device;
        if (id.empty()) {
            const auto list = backend->list();
            if (list.empty()) {
                set_state("failed");
                throw cf::camera::CameraError(cfg_.camera_backend, "no camera found");
            }
            id = list.front().id;
        }
        try {
            auto cam = backend->open(id);
            attach_tracked_pose(*cam);
            cam_ = std::move(cam);
        } catch (...) {
            set_state("failed");
            throw;
        }
        backend_ = std::move(backend);
        const auto info = cam_->info();
        std::lock_guard lk(mu_);
        state_ = "open";
        model_ = info.model;
        id_ = info.id;
    }
    /// camera.sim_pose: the simulated camera photographs from the tracker simulator's camera tool
    /// (composed with the hand-eye transform and the scene's patient registration, chosen so that
    /// the tool's rest pose gives the scene's home framing; cf::sim::tracked_camera_pose_source),
    /// else from its scripted orbit. "tracker" without the camera tool is refused by the config.
    void attach_tracked_pose(cf::camera::Camera& cam) {
        auto* sim_cam = dynamic_cast<cf::camera::SimCamera*>(&cam);
        const bool has_tool = cfg_.tracker_enabled && cfg_.tracker_source == "sim" && cfg_.tracker_sim_camera_tool;
        if (!sim_cam || cfg_.camera_sim_pose == "orbit" || !has_tool) {
            std::lock_guard lk(mu_);
            pose_source_ = sim_cam ? "orbit" : "";
            return;
        }
        cf::sim::TrackerSimulator* sim = tracker_ ? tracker_->simulator() : nullptr;
        if (!sim) throw cf::camera::CameraError("sim:0", "camera.sim_pose: the tracker simulator has not started yet");
        try {
            cf::sim::TrackedCameraRig rig;
            if (!cfg_.camera_sim_T_optics_from_tool.empty())
                rig.T_optics_from_tool = cf::sim::parse_pose7(cfg_.camera_sim_T_optics_from_tool, "camera.sim_T_optics_from_tool");
            cf::sim::register_rig_to_view(rig, *sim, Eigen::Isometry3d(sim_cam->home_pose()));
            sim_cam->set_pose_source(cf::sim::tracked_camera_pose_source(*sim, rig));
        } catch (const std::invalid_argument& e) {
            throw cf::camera::CameraError("sim:0", e.what());
        }
        std::lock_guard lk(mu_);
        pose_source_ = "tracker:" + cf::sim::TrackedCameraRig{}.camera_part;
    }
    cf::camera::Photo capture_on_thread() {
        try {
            if (live_on_) stop_live();  // a still while live: the stream restarts on the next live step
            open_on_thread();
            auto photo = cam_->capture();
            std::lock_guard lk(mu_);
            stats_ = cam_->stats();
            error_.clear();
            return photo;
        } catch (const cf::camera::CameraError& e) {
            std::lock_guard lk(mu_);
            error_ = e.what();
            if (!cam_) state_ = "failed";
            else stats_ = cam_->stats();
            throw ApiError(503, "unavailable", e.what());
        }
    }
    void set_state(const std::string& s) {
        std::lock_guard lk(mu_);
        state_ = s;
    }

    DaemonConfig cfg_;
    mutable std::mutex mu_;  // status fields
    std::string state_ = "closed", error_, model_, id_;
    std::string pose_source_;  // the simulated camera's: "orbit" or "tracker:CF-CAMERA" (mu_)
    const TrackerModule* tracker_ = nullptr;
    cf::camera::CameraStats stats_;
    std::unique_ptr<cf::camera::Backend> backend_;  // camera thread only
    std::unique_ptr<cf::camera::Camera> cam_;       // camera thread only
    std::mutex q_mu_;
    std::condition_variable q_cv_;
    std::deque<std::packaged_task<cf::camera::Photo()>> queue_;
    bool stop_ = false;
    // Live view: requested until live_until_ (q_mu_); the stream runs on the camera thread.
    static constexpr double kLiveFps = 10;
    static constexpr std::chrono::milliseconds kLiveIdle{2000};
    std::chrono::steady_clock::time_point live_until_{};
    std::atomic<bool> live_on_{false};
    std::atomic<int> live_waiters_{0};  // live requests waiting for a frame
    std::mutex live_mu_;
    std::condition_variable live_cv_;
    cf::camera::Frame live_frame_;  // newest frame (live_mu_)
    std::uint64_t live_seq_ = 0;    // camera thread
    std::string live_error_;        // live_mu_
    std::thread thread_;
};

std::uint64_t parse_id(const Request& r) {
    const auto it = r.params.find("id");
    if (it == r.params.end()) throw ApiError(400, "bad_request", "job id missing");
    const std::string& s = it->second;
    if (s.empty() || s.size() > 19 || s.find_first_not_of("0123456789") != std::string::npos)
        throw ApiError(400, "bad_request", "job id '" + s + "' is not a number");
    return std::stoull(s);
}

std::string folder_name(const nlohmann::json& v, const std::string& field) {
    if (!v.is_string()) throw ApiError(400, "bad_request", field + ": must be a string");
    const std::string s = v.get<std::string>();
    static const std::regex re("[A-Za-z0-9_][A-Za-z0-9_-]{0,63}");
    if (!std::regex_match(s, re)) throw ApiError(400, "bad_request", field + " '" + s + "': 1..64 letters, digits, _ or -");
    return s;
}

std::int64_t int_param(const nlohmann::json& p, const char* key, std::int64_t def, std::int64_t lo, std::int64_t hi, const std::string& kind) {
    if (!p.contains(key)) return def;
    if (!p[key].is_number_integer()) throw ApiError(400, "bad_request", kind + " " + key + ": must be an integer");
    const auto v = p[key].get<std::int64_t>();
    if (v < lo || v > hi)
        throw ApiError(400, "bad_request", kind + " " + key + ": " + std::to_string(v) + " is out of range " + std::to_string(lo) + ".." + std::to_string(hi));
    return v;
}

void reject_unknown(const nlohmann::json& p, const std::vector<std::string>& known, const std::string& kind) {
    if (!p.is_object()) throw ApiError(400, "bad_request", kind + ": params must be a JSON object");
    for (auto it = p.begin(); it != p.end(); ++it)
        if (std::find(known.begin(), known.end(), it.key()) == known.end())
            throw ApiError(400, "bad_request", kind + " " + it.key() + ": unknown parameter");
}

}  // namespace

struct Daemon::Impl {
    DaemonConfig cfg;
    fs::path state_dir, cases_dir, results_dir;
    std::int64_t started_ns = 0;
    std::string started_utc;
    EndpointRegistry registry;
    std::unique_ptr<TrackerModule> tracker;
    std::unique_ptr<RenderModule> render;
    std::unique_ptr<CameraModule> camera;
    std::unique_ptr<JobQueue> jobs;
    std::unique_ptr<HttpServer> http;
    std::unique_ptr<cf::db::CaseStore> store;
    fs::path store_dir, work_dir;
    std::thread monitor;
    std::mutex monitor_mu;
    std::condition_variable monitor_cv;
    bool monitor_stop = false;
    bool started = false, stopped = false;

    void register_endpoints();
    void register_job_kinds();
    nlohmann::json status() const;
    void monitor_loop();
};

Daemon::Daemon(DaemonConfig config) : impl_(std::make_unique<Impl>()) { impl_->cfg = std::move(config); }

Daemon::~Daemon() { stop(); }

const DaemonConfig& Daemon::config() const { return impl_->cfg; }

int Daemon::port() const { return impl_->http ? impl_->http->port() : 0; }

void Daemon::start() {
    Impl& d = *impl_;
    d.started_ns = steady_ns();
    d.started_utc = utc_now_iso();
    d.state_dir = resolve_state_dir(d.cfg);
    d.cases_dir = d.state_dir / "cases";
    d.results_dir = d.state_dir / "results";
    std::error_code ec;
    for (const auto& p : {d.state_dir, d.cases_dir, d.results_dir}) {
        fs::create_directories(p, ec);
        if (ec || !fs::is_directory(p)) throw std::runtime_error("state_dir " + p.string() + ": cannot create the folder" + (ec ? ": " + ec.message() : ""));
    }
    // Leftovers of a phantom job interrupted by a crash are temporary folders: remove them.
    for (const auto& e : fs::directory_iterator(d.cases_dir, ec))
        if (e.path().filename().string().rfind(".tmp-", 0) == 0) fs::remove_all(e.path(), ec);

    d.work_dir = d.state_dir / "work";
    fs::remove_all(d.work_dir, ec);  // exports of an interrupted job: nothing in them is kept
    fs::create_directories(d.work_dir, ec);
    d.store_dir = d.cfg.store_dir.empty() ? d.state_dir / "store" : fs::path(d.cfg.store_dir);
    try {
        d.store = cf::db::CaseStore::open(d.store_dir);
    } catch (const std::exception& e) {
        throw std::runtime_error("store.dir " + d.store_dir.string() + ": " + e.what());
    }

    // llvmpipe (Mesa's software GL, the renderer on a cart without a GPU) starts one rasterizer
    // thread per core for each context, outside any TBB arena: cap them like the jobs' arena
    // (unless LP_NUM_THREADS is set), so a registration rendering with GL cannot take every
    // core from the tracker's driver thread. Set before any thread of ours or any GL context
    // exists; a GPU driver ignores it.
    if (d.cfg.renderer != "cpu" && !std::getenv("LP_NUM_THREADS"))
        ::setenv("LP_NUM_THREADS", std::to_string(JobQueue::resolve_threads(d.cfg.job_threads)).c_str(), 0);
    d.tracker = std::make_unique<TrackerModule>(d.cfg);
    d.render = std::make_unique<RenderModule>(d.cfg);
    d.camera = std::make_unique<CameraModule>(d.cfg, d.tracker.get());
    d.jobs = std::make_unique<JobQueue>(JobQueue::Options{d.cfg.job_progress_hz, d.cfg.jobs_kept, d.cfg.job_threads, d.cfg.job_nice});
    d.http = std::make_unique<HttpServer>(d.cfg, d.registry);
    d.register_job_kinds();
    d.register_endpoints();
    register_case_endpoints(d.registry, *d.store, d.cases_dir, d.work_dir, d.cfg.session_ttl_s);
    register_case_data_endpoints(d.registry, *d.store, d.work_dir, d.cfg.max_upload_bytes);
    register_tags_endpoints(d.registry, *d.store, d.work_dir);  // stimulation tags (tags_api.cpp)
    register_landmark_pose_endpoints(d.registry, *d.store);     // landmarks' initial alignment (landmark_pose_api.cpp)
    register_draft_endpoints(d.registry, *d.store);             // unsaved marks kept across a browser restart (drafts_api.cpp)
    register_thumbnail_endpoints(d.registry, *d.store, d.work_dir);  // the archive's thumbnails (thumbnail_api.cpp)
    register_media_endpoints(d.registry, *d.store, d.cfg.removable_media_root, d.work_dir, d.cfg.max_upload_bytes);  // USB sticks (media_api.cpp)
    NavigationOptions nav_options;
    nav_options.t1_path = d.cfg.t1_path;
    nav_options.work_dir = d.work_dir;
    register_navigation_endpoints(d.registry, *d.store, *d.tracker, nav_options);
    cf::db::CaseStore* store = d.store.get();
    d.http->set_authenticator([store](const std::string& token, Client& c) {
        try {
            const auto s = store->check_session(token);
            if (!s) return false;
            c.role = cf::db::to_string(s->user.role);
            c.user = s->user.name;
            c.user_id = s->user.id;
            return true;
        } catch (const std::exception& e) {
            log(LogLevel::error, "http", std::string("session check failed: ") + e.what());
            return false;
        }
    });

    HttpServer* http = d.http.get();
    d.jobs->set_listener([http](const JobInfo& j) {
        http->publish("jobs", "notify_job", to_json(j), steady_ns());
        if (j.state != JobInfo::State::queued && j.state != JobInfo::State::running)
            log(j.state == JobInfo::State::failed ? LogLevel::warning : LogLevel::info, "jobs",
                "job " + std::to_string(j.id) + " (" + j.kind + ") " + state_name(j.state) + (j.error.empty() ? "" : ": " + j.error),
                {{"JOB_ID", std::to_string(j.id)}, {"JOB_KIND", j.kind}, {"JOB_STATE", state_name(j.state)}});
    });
    d.tracker->set_frame_sink([http](const cf::tracker::TrackerFrame& f) {
        http->publish("tracker", "notify_tracker_frame", frame_to_json(f), f.publish_steady_ns);
    });

    d.http->start();  // first: a port in use fails before any thread of ours runs
    log(LogLevel::info, "http", "listening on " + d.cfg.listen + " (port " + std::to_string(d.http->port()) + ")",
        {{"PORT", std::to_string(d.http->port())}});
    d.render->start();
    d.jobs->start();
    try {
        d.tracker->start();
    } catch (const std::exception& e) {
        d.http->stop();
        d.jobs->stop(std::chrono::milliseconds(0));
        d.render->stop();
        throw std::runtime_error(std::string("tracker: ") + e.what());
    }
    d.monitor = std::thread([&d] { d.monitor_loop(); });
    d.started = true;

    if (d.cfg.phantom_cases_at_start > 0 && !fs::exists(d.cases_dir / "phantom", ec)) {
        d.jobs->submit("phantom", {{"n", d.cfg.phantom_cases_at_start}, {"seed", d.cfg.phantom_seed}, {"folder", "phantom"}});
    }
    log(LogLevel::info, "daemon", std::string("cortexfused ") + kVersion + " started; state in " + d.state_dir.string());
}

bool Daemon::stop() {
    Impl& d = *impl_;
    if (!d.started || d.stopped) return true;
    d.stopped = true;
    log(LogLevel::info, "daemon", "stopping");
    {
        std::lock_guard lk(d.monitor_mu);
        d.monitor_stop = true;
    }
    d.monitor_cv.notify_all();
    if (d.monitor.joinable()) d.monitor.join();
    const std::int64_t t0 = steady_ns();
    auto step = [&](const char* what) { log(LogLevel::debug, "daemon", std::string(what) + " at " + std::to_string((steady_ns() - t0) / 1000000) + " ms"); };
    d.jobs->request_stop();  // cancel now: the jobs wind down while the server stops
    d.http->stop();          // no new requests; WebSockets closed
    step("http stopped");
    const bool jobs_clean = d.jobs->stop(std::chrono::milliseconds(d.cfg.stop_timeout_ms));
    if (!jobs_clean) log(LogLevel::warning, "jobs", "a job did not end within jobs.stop_timeout_ms; abandoned");
    step("jobs stopped");
    d.tracker->stop();
    step("tracker stopped");
    d.render->stop();
    d.camera->stop();
    step("render and camera stopped");
    log(LogLevel::info, "daemon", "stopped");
    return jobs_clean;
}

bool Daemon::healthy(std::string* why) const {
    const Impl& d = *impl_;
    auto fail = [&](const std::string& w) {
        if (why) *why = w;
        return false;
    };
    if (!d.started || d.stopped) return fail("not running");
    if (!d.http->healthy()) return fail("http server or push thread stopped");
    if (!d.jobs->healthy()) return fail("a job worker stopped");
    if (!d.render->healthy()) return fail("render thread stopped");
    if (!d.tracker->healthy(d.cfg.tracker_stall_ms)) return fail("tracker stalled or its driver thread stopped");
    return true;
}

nlohmann::json Daemon::status_json() const { return impl_->status(); }

std::string Daemon::status_line() const {
    const Impl& d = *impl_;
    std::ostringstream s;
    const auto st = d.tracker->status();
    if (d.cfg.tracker_enabled) s << "tracker " << cf::tracker::state_name(st.state) << " " << int(st.frame_rate_hz + 0.5) << " Hz";
    else s << "tracker off";
    int running = 0, queued = 0;
    for (const auto& j : d.jobs->list()) {
        running += j.state == JobInfo::State::running;
        queued += j.state == JobInfo::State::queued;
    }
    s << ", jobs " << running << " running " << queued << " queued, http port " << port();
    return s.str();
}

nlohmann::json Daemon::Impl::status() const {
    std::string why;
    nlohmann::json j{{"name", "cortexfused"},
                     {"version", kVersion},
                     {"started_utc", started_utc},
                     {"uptime_s", (steady_ns() - started_ns) / 1e9},
                     {"modules",
                      {{"tracker", tracker->status_json()},
                       {"camera", camera->status_json()},
                       {"renderer", render->status_json()},
                       {"jobs", jobs->status()},
                       {"http", http->status_json()},
                       {"case_store", {{"state", store ? "open" : "closed"}, {"dir", store_dir.string()}, {"schema_version", store ? store->schema_version() : 0}}}}}};
    return j;
}

void Daemon::Impl::monitor_loop() {
    // Status notifications once a second (the watchdog's health check lives in main.cpp).
    std::unique_lock lk(monitor_mu);
    while (!monitor_cv.wait_for(lk, std::chrono::seconds(1), [&] { return monitor_stop; })) {
        lk.unlock();
        const auto st = status();
        http->publish("status", "notify_status",
                      {{"uptime_s", st["uptime_s"]},
                       {"tracker", {{"state", st["modules"]["tracker"]["state"]}, {"frame_rate_hz", st["modules"]["tracker"].value("frame_rate_hz", 0.0)}}},
                       {"renderer", {{"state", st["modules"]["renderer"]["state"]}, {"backend", st["modules"]["renderer"]["backend"]}}},
                       {"jobs", st["modules"]["jobs"]["kinds"]}},
                      steady_ns());
        lk.lock();
    }
}

void Daemon::Impl::register_job_kinds() {
    const fs::path cases = cases_dir, results = results_dir;
    const DaemonConfig c = cfg;

    JobKind phantom;
    phantom.name = "phantom";
    phantom.validate = [cases, c](const nlohmann::json& p) {
        reject_unknown(p, {"n", "seed", "folder"}, "phantom");
        nlohmann::json out;
        out["n"] = int_param(p, "n", 1, 1, 20, "phantom");
        out["seed"] = int_param(p, "seed", c.phantom_seed, 0, 2147483647, "phantom");
        out["folder"] = folder_name(p.value("folder", nlohmann::json("phantom")), "phantom folder");
        std::error_code ec;
        if (fs::exists(cases / out["folder"].get<std::string>(), ec))
            throw ApiError(409, "conflict", "phantom folder '" + out["folder"].get<std::string>() + "' exists already");
        return out;
    };
    phantom.run = [cases, c](const nlohmann::json& p, JobContext& ctx) {
        const std::string folder = p["folder"].get<std::string>();
        const fs::path tmp = cases / (".tmp-" + folder + "-" + std::to_string(ctx.id()));
        const fs::path dest = cases / folder;
        PhantomParams pp;
        pp.seed = std::uint64_t(p["seed"].get<std::int64_t>());
        pp.dslr_fraction = 0;  // small photos: quick registrations on the cart
        std::error_code ec;
        try {
            const auto dirs = generate_phantoms(tmp, p["n"].get<int>(), c.t1_path, c.brain_mask_path, pp, ctx.progress());
            ctx.check();
            fs::rename(tmp, dest, ec);
            if (ec) throw std::runtime_error("cases folder " + dest.string() + ": " + ec.message());
        } catch (...) {
            fs::remove_all(tmp, ec);  // a cancelled or failed generation leaves nothing behind
            throw;
        }
        nlohmann::json names = nlohmann::json::array();
        for (const auto& e : fs::directory_iterator(dest))
            if (fs::is_regular_file(e.path() / "case.json")) names.push_back(folder + "/" + e.path().filename().string());
        std::sort(names.begin(), names.end());
        return nlohmann::json{{"cases", names}};
    };
    jobs->add_kind(phantom);

    JobKind reg;
    reg.name = "register";
    Impl* self = this;
    reg.validate = [cases, self](const nlohmann::json& p) {
        reject_unknown(p, {"case", "case_id", "params"}, "register");
        nlohmann::json overrides = nlohmann::json::object();
        if (p.contains("params")) {
            register_params_from_request(p["params"]);  // 400 naming the key core's reader refuses
            overrides = p["params"];
        }
        if (p.contains("case") == p.contains("case_id"))
            throw ApiError(400, "bad_request", "register: give exactly one of case (a case folder such as phantom/case_0000) or case_id (a case in the store)");
        if (p.contains("case")) {
            case_dir_from_name(cases, p["case"], "register case");
            return nlohmann::json{{"case", p["case"]}, {"params", overrides}};
        }
        if (!p["case_id"].is_number_integer()) throw ApiError(400, "bad_request", "register case_id: must be an integer");
        try {
            const auto rec = self->store->get_case(p["case_id"].get<std::int64_t>());
            if (rec.photos.empty() || rec.volumes.empty())
                throw ApiError(409, "conflict", "register case_id " + std::to_string(rec.summary.id) + ": the case needs a volume and a photo first");
        } catch (const cf::db::StoreError& e) {
            rethrow_store_error(e);
        }
        return nlohmann::json{{"case_id", p["case_id"]}, {"params", overrides}};
    };
    reg.run = [cases, results, c, self](const nlohmann::json& p, JobContext& ctx) {
        // A case of the store is exported to a work folder (a case folder, blobs verified),
        // registered there, and the run is stored back with its parameters, whatever its end.
        std::optional<std::int64_t> case_id;
        fs::path dir;
        if (p.contains("case_id")) {
            case_id = p["case_id"].get<std::int64_t>();
            dir = self->work_dir / ("register_" + std::to_string(ctx.id()));
            std::error_code ec;
            fs::remove_all(dir, ec);
            ctx.report("exporting case", 0);
            try {
                self->store->export_case_folder(*case_id, dir, cf::db::Actor{"jobs", std::nullopt});
            } catch (const cf::db::StoreError& e) {
                throw std::runtime_error(std::string("case ") + std::to_string(*case_id) + ": " + e.what());
            }
        } else {
            dir = case_dir_from_name(cases, p["case"], "register case");
        }
        struct Cleanup {
            fs::path d;
            bool remove;
            ~Cleanup() {
                std::error_code ec;
                if (remove) fs::remove_all(d, ec);
            }
        } cleanup{dir, case_id.has_value()};
        RegistrationParams rp = register_params_from_request(p.value("params", nlohmann::json::object()));
        auto store_run = [&](cf::db::RegistrationStatus status, const RegistrationResult* r, const std::string& error,
                             const std::string& result_json) -> std::optional<std::int64_t> {
            if (!case_id) return std::nullopt;
            cf::db::RegistrationInput in;
            in.status = status;
            in.params = to_json(rp);
            if (!error.empty()) in.error = error;
            if (r) {
                in.initial_pose = nlohmann::json{{"T_camera_from_world", pose_to_json(r->initial_T_camera_from_world)}};
                in.final_pose = nlohmann::json{{"T_camera_from_world", pose_to_json(r->T_camera_from_world)}};
                in.nmi = r->similarity;
                in.seconds = r->seconds;
                in.evaluations = r->evaluations;
                in.stages = result_to_json(*r).value("stages", nlohmann::json::array());
                cf::db::ResultInput file;
                file.kind = "registration_json";
                file.name = "registration.json";
                file.media_type = "application/json";
                file.bytes = result_json;
                in.results.push_back(std::move(file));
            }
            return self->store->add_registration(*case_id, in, cf::db::Actor{"jobs", std::nullopt}).id;
        };
        try {
            Progress prog = ctx.progress();
            ctx.report("loading case", 0);
            LoadedCase lc = load_case(dir, &prog);
            ctx.check();
            std::ostringstream why;
            rp.renderer_factory = renderer_factory(parse_renderer_kind(c.renderer, "renderer.kind"), &why);
            Registration engine(lc.volume, lc.mask, rp);
            prog.evaluation = [&ctx](int e, double s, double best) { ctx.figures({{"evaluation", e}, {"nmi", s}, {"best_nmi", best}}); };
            const RegistrationResult r = engine.run(lc.photo, &prog);
            ctx.check();
            nlohmann::json full = result_to_json(r);
            if (case_id) full["case_id"] = *case_id;
            else full["case"] = p["case"];
            const std::string full_text = full.dump(2);
            const fs::path out = results / ("register_" + std::to_string(ctx.id()) + ".json");
            write_file_atomic(out, full_text);
            nlohmann::json summary{{"similarity", r.similarity},
                                   {"initial_similarity", r.initial_similarity},
                                   {"evaluations", r.evaluations},
                                   {"seconds", r.seconds},
                                   {"renderer", engine.renderer().name()},
                                   {"T_camera_from_world", pose_to_json(r.T_camera_from_world)},
                                   {"result_file", out.filename().string()},
                                   {"warnings", r.warnings}};
            if (case_id) summary["case_id"] = *case_id;
            else summary["case"] = p["case"];
            if (lc.spec.truth && !lc.spec.truth->targets_world_mm.empty()) {
                // Mean 3D displacement of the truth targets between the true and the found pose (camera frame).
                double sum = 0;
                const Pose& Tt = lc.spec.truth->T_camera_from_world;
                for (const auto& t : lc.spec.truth->targets_world_mm) {
                    const Eigen::Vector4d h(t.x(), t.y(), t.z(), 1);
                    sum += ((Tt * h).head<3>() - (r.T_camera_from_world * h).head<3>()).norm();
                }
                summary["target_error_mm"] = sum / double(lc.spec.truth->targets_world_mm.size());
            }
            if (auto rid = store_run(cf::db::RegistrationStatus::succeeded, &r, "", full_text)) summary["registration_id"] = *rid;
            return summary;
        } catch (const cf::Cancelled&) {
            try {
                store_run(cf::db::RegistrationStatus::cancelled, nullptr, "cancelled", "");
            } catch (const std::exception& e) {
                log(LogLevel::error, "jobs", std::string("could not record the cancelled run: ") + e.what());
            }
            throw;
        } catch (const std::exception& e) {
            // A cancel may surface as another error of the engine (e.g. while the case loads):
            // the run is recorded as cancelled then, with its parameters.
            const bool cancelled = ctx.cancelled();
            try {
                if (cancelled) store_run(cf::db::RegistrationStatus::cancelled, nullptr, "cancelled", "");
                else store_run(cf::db::RegistrationStatus::failed, nullptr, e.what(), "");
            } catch (const std::exception& e2) {
                log(LogLevel::error, "jobs", std::string("could not record the failed run: ") + e2.what());
            }
            throw;
        }
    };
    jobs->add_kind(reg);
    register_case_job_kinds(*jobs, *store, work_dir);  // plan, export (case_jobs.cpp)
}

void Daemon::Impl::register_endpoints() {
    Impl* d = this;
    auto json_ok = [](nlohmann::json j, int status = 200) {
        Response r;
        r.status = status;
        r.json = std::move(j);
        return r;
    };
    registry.add({"GET", "/api/status", "status.get", Access::open, "Version, uptime and every module's status (no login)",
                  [d, json_ok](const Request&) { return json_ok(d->status()); }});
    registry.add({"GET", "/api/endpoints", "endpoints.list", Access::open, "This list",
                  [d, json_ok](const Request&) { return json_ok({{"endpoints", d->registry.list()}}); }});
    registry.add({"GET", "/api/config", "config.get", Access::admin, "The effective configuration",
                  [d, json_ok](const Request&) { return json_ok(to_json(d->cfg)); }});
    registry.add({"GET", "/api/tracker", "tracker.status", Access::read, "Tracker module status and the newest frame",
                  [d, json_ok](const Request&) { return json_ok({{"status", d->tracker->status_json()}, {"frame", d->tracker->latest_json()}}); }});
    registry.add({"GET", "/api/tracker/frame", "tracker.frame", Access::read, "The newest tracker frame (404 before the first)",
                  [d, json_ok](const Request&) {
                      auto f = d->tracker->latest_json();
                      if (f.is_null()) throw ApiError(404, "not_found", "tracker: no frame yet (state " + d->tracker->status_json().value("state", std::string("?")) + ")");
                      return json_ok(f);
                  }});
    registry.add({"GET", "/api/camera", "camera.status", Access::read, "Camera module status",
                  [d, json_ok](const Request&) { return json_ok(d->camera->status_json()); }});
    registry.add({"POST", "/api/camera/capture", "camera.capture", Access::write, "Take a photo; answers the file as the camera delivered it (JPEG)",
                  [d](const Request&) {
                      auto photo = d->camera->capture();
                      Response r = Response::binary(std::string(photo.bytes.begin(), photo.bytes.end()), photo.mime.empty() ? "image/jpeg" : photo.mime);
                      r.headers["X-Capture-Ms"] = std::to_string(photo.capture_ms);
                      return r;
                  }});
    registry.add({"GET", "/api/camera/live", "camera.live", Access::write,
                  "The camera's newest live frame as JPEG (?after=SEQ waits for a newer one, max_width, quality); polling keeps the stream on, it stops 2 s after the last request",
                  [d](const Request& r) {
                      const auto num = [&](const char* k, long long lo, long long hi, long long def) {
                          auto it = r.params.find(k);
                          if (it == r.params.end()) return def;
                          try {
                              std::size_t n = 0;
                              const long long v = std::stoll(it->second, &n);
                              if (n == it->second.size() && v >= lo && v <= hi) return v;
                          } catch (const std::exception&) {
                          }
                          throw ApiError(400, "bad_request", std::string("camera live ") + k + ": '" + it->second + "' is not an integer in " +
                                                                 std::to_string(lo) + ".." + std::to_string(hi));
                      };
                      const auto after = num("after", 0, std::numeric_limits<long long>::max(), 0);
                      const auto max_w = num("max_width", 16, 4096, 640);
                      const auto q = num("quality", 10, 100, 70);
                      auto f = d->camera->live_jpeg(std::uint64_t(after), int(max_w), int(q), std::chrono::milliseconds(5000));
                      Response resp = Response::binary(std::move(f.bytes), "image/jpeg");
                      resp.headers["X-Frame-Seq"] = std::to_string(f.sequence);
                      resp.headers["X-Image-Size"] = std::to_string(f.width) + "x" + std::to_string(f.height);
                      resp.headers["Cache-Control"] = "no-store";
                      return resp;
                  }});
    registry.add({"GET", "/api/jobs", "jobs.list", Access::read, "All jobs (queued, running, the last finished ones)",
                  [d, json_ok](const Request&) {
                      nlohmann::json a = nlohmann::json::array();
                      for (const auto& j : d->jobs->list()) a.push_back(to_json(j));
                      return json_ok({{"jobs", a}, {"kinds", d->jobs->kinds()}});
                  }});
    registry.add({"GET", "/api/jobs/{id}", "jobs.get", Access::read, "One job",
                  [d, json_ok](const Request& r) {
                      const auto id = parse_id(r);
                      auto j = d->jobs->get(id);
                      if (!j) throw ApiError(404, "not_found", "job " + std::to_string(id) + ": no such job");
                      return json_ok(to_json(*j));
                  }});
    registry.add({"POST", "/api/jobs", "jobs.create", Access::write, "Queue a job: {kind, params}; answers 202 with the job",
                  [d, json_ok](const Request& r) {
                      if (!r.body.is_object()) throw ApiError(400, "bad_request", "jobs.create: body must be a JSON object {\"kind\": ..., \"params\": {...}}");
                      if (!r.body.contains("kind") || !r.body["kind"].is_string()) throw ApiError(400, "bad_request", "jobs.create kind: missing or not a string");
                      for (auto it = r.body.begin(); it != r.body.end(); ++it)
                          if (it.key() != "kind" && it.key() != "params") throw ApiError(400, "bad_request", "jobs.create " + it.key() + ": unknown field");
                      const auto id = d->jobs->submit(r.body["kind"].get<std::string>(), r.body.value("params", nlohmann::json::object()));
                      Response resp = json_ok(to_json(*d->jobs->get(id)), 202);
                      resp.headers["Location"] = "/api/jobs/" + std::to_string(id);
                      return resp;
                  }});
    registry.add({"POST", "/api/jobs/{id}/cancel", "jobs.cancel", Access::write, "Cancel a queued or running job",
                  [d, json_ok](const Request& r) {
                      const auto id = parse_id(r);
                      if (!d->jobs->cancel(id)) throw ApiError(404, "not_found", "job " + std::to_string(id) + ": no such job");
                      return json_ok(to_json(*d->jobs->get(id)));
                  }});
    registry.add({"GET", "/api/case-folders", "case_folders.list", Access::read, "Case folders under the state folder's cases/ (phantom cases; import them with POST /api/cases/import)",
                  [d, json_ok](const Request&) {
                      nlohmann::json a = nlohmann::json::array();
                      std::error_code ec;
                      for (auto it = fs::recursive_directory_iterator(d->cases_dir, ec); !ec && it != fs::recursive_directory_iterator(); it.increment(ec)) {
                          if (it.depth() > 2) {
                              it.disable_recursion_pending();
                              continue;
                          }
                          const auto name = it->path().filename().string();
                          if (!name.empty() && name[0] == '.') {
                              it.disable_recursion_pending();
                              continue;
                          }
                          if (it->is_regular_file() && name == "case.json")
                              a.push_back(fs::relative(it->path().parent_path(), d->cases_dir).string());
                      }
                      std::sort(a.begin(), a.end());
                      return json_ok({{"folders", a}});
                  }});
    registry.add({"GET", "/api/render/presets", "render.presets", Access::read, "Transfer function presets (names and their JSON, the shape POST /api/render takes as tf)",
                  [json_ok](const Request&) {
                      nlohmann::json tfs = nlohmann::json::object();
                      for (const auto& n : preset_names()) tfs[n] = to_json(preset_transfer_function(n));
                      return json_ok({{"presets", preset_names()}, {"transfer_functions", tfs}});
                  }});
    register_render_case_endpoints(registry, *render, *store, *jobs, work_dir);  // render (per case too), pick, fused view, histograms, job downloads
}

}  // namespace cf::daemon
