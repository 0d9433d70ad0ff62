#pragma once
// The render module: one thread that owns the MRI, its brain mask and the renderers (GL when
// renderer.kind allows and a context can be made, else the CPU ray caster: a GL context is
// bound to the thread that made it, so every render runs on this thread). Requests from the
// HTTP/WebSocket threads are queued to it and answered through a future.
//
// Thread contract: start()/stop() from the daemon's main thread; render() and status_json()
// from any thread (render() blocks the caller until the image is ready).
#include <condition_variable>
#include <deque>
#include <future>
#include <mutex>
#include <nlohmann/json.hpp>
#include <string>
#include <thread>

#include "cortexfuse/daemon/config.hpp"

namespace cf::daemon {

struct RenderedImage {
    std::string bytes;  ///< encoded JPEG or PNG
    std::string mime;
    int width = 0, height = 0;
    double render_ms = 0, encode_ms = 0;
    std::string backend;
};

class RenderModule {
public:
    explicit RenderModule(const DaemonConfig& c);
    ~RenderModule();
    /// Starts the thread; the volume loads on it (status "loading" until then).
    void start();
    void stop();
    /// Validates the request (ApiError 400 naming the field), waits for the volume, renders.
    /// Request fields: width, height (16..renderer.max_*), preset (transfer function preset
    /// name) or tf (a custom transfer function, core's JSON shape), opacity (0..1, scales the preset's opacity), brain_only (bool: hide all but the
    /// brain mask; default true for cortex_t1 and surface_white), view ("left", "right",
    /// "anterior", "posterior", "superior", "inferior") and distance_mm, or T_camera_from_world
    /// (4x4 rows, LPS mm -> camera mm); camera (intrinsics JSON as in case.json) or focal_px;
    /// format "jpeg" | "png"; quality (10..100).
    RenderedImage render(const nlohmann::json& request);
    /// The loaded MRI's geometry for clients that place their own camera: centre (the standard
    /// views' target) and box in LPS mm, dims, spacing, and the brain mask's box (`brain`, null
    /// without a mask). ApiError 503 while loading or after a failed load.
    nlohmann::json volume_json() const;
    nlohmann::json status_json() const;
    bool healthy() const;

private:
    struct Job;
    void loop();
    DaemonConfig cfg_;
    std::thread thread_;
    mutable std::mutex mu_;
    std::condition_variable cv_;
    std::deque<std::shared_ptr<Job>> queue_;
    bool stop_ = false;
    std::string state_ = "stopped";  // stopped, loading, ready, failed
    std::string error_;
    nlohmann::json volume_info_;  // set once the volume is loaded
    std::string backend_, backend_reason_;
    std::uint64_t renders_ = 0, failures_ = 0;
    double last_render_ms_ = 0;
    bool thread_done_ = false;
};

}  // namespace cf::daemon
