// The simulated camera: the phantom generator's scene (core/phantom.hpp) photographed from a
// pose per capture, delivered as a JPEG after a configurable delay, with the truth attached.
// It is a C++ backend, not a wire-level simulator: a camera on USB/PTP has no byte stream
// we could reproduce faithfully here, and v4l2loopback needs a kernel module.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <mutex>
#include <opencv2/imgcodecs.hpp>
#include <thread>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/volume.hpp"
#include "cortexfuse/drivers/camera.hpp"

namespace cf::camera {

void SimCameraConfig::validate() const {
    auto bad = [](const std::string& f, const std::string& why) { throw InputError("sim camera " + f, why); };
    if (width < 64 || height < 64 || width > 4000 || height > 4000) bad("size", "must be 64..4000 px each");
    if (!(capture_delay_ms >= 0 && capture_delay_ms <= 10000)) bad("capture_delay_ms", "must be in [0, 10000]");
    if (!(stream_fps >= 1 && stream_fps <= 60)) bad("stream_fps", "must be in [1, 60]");
    if (!(orbit_step_deg >= 0 && orbit_step_deg <= 45)) bad("orbit_step_deg", "must be in [0, 45]");
    if (jpeg_quality < 50 || jpeg_quality > 100) bad("jpeg_quality", "must be in [50, 100]");
    if (case_index < 0) bad("case_index", "must be >= 0");
    if (!surface && (volume_path.empty() || mask_path.empty())) bad("volume", "a T1 volume and its brain mask are needed");
}

namespace {

int64_t steady_ns() {
    return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

/// Sleeps until `until`, in slices, so a cancel is seen within ~10 ms.
void sleep_until(std::chrono::steady_clock::time_point until, const Progress& progress) {
    while (std::chrono::steady_clock::now() < until) {
        progress.check();
        std::this_thread::sleep_for(std::min<std::chrono::steady_clock::duration>(std::chrono::milliseconds(10),
                                                                                  until - std::chrono::steady_clock::now()));
    }
}

class SimCameraImpl final : public SimCamera {
public:
    explicit SimCameraImpl(const SimCameraConfig& c) : cfg_(c) {
        cfg_.validate();
        if (cfg_.surface) {
            surface_ = cfg_.surface;
        } else {
            const Volume t1 = load_volume(cfg_.volume_path);
            const LabelVolume mask = load_mask(cfg_.mask_path);
            surface_ = std::make_shared<const PhantomSurface>(build_phantom_surface(t1, mask));
        }
        params_.seed = cfg_.seed;
        params_.width = cfg_.width;
        params_.height = cfg_.height;
        params_.vary_size = false;
        params_.dslr_fraction = 0;
        params_.validate();
        // The scene's own framing fixes the camera (focal length) and the orbit's start.
        const PhantomCase home = generate_phantom_case(*surface_, params_, cfg_.case_index);
        home_ = home.T_camera_from_world;
        K_ = home.camera;
        pivot_world_.setZero();
        for (const auto& t : home.targets_world_mm) pivot_world_ += t;
        if (!home.targets_world_mm.empty()) pivot_world_ /= double(home.targets_world_mm.size());
        params_.fixed_camera = K_;
    }

    CameraInfo info() const override { return {"sim", "sim:0", "CortexFuse simulated camera (phantom scene)", true, true}; }
    Pose home_pose() const override { return home_; }
    Intrinsics intrinsics() const override { return K_; }
    void set_pose(const std::optional<Pose>& T) override {
        if (T && !is_rigid(*T)) throw InputError("sim camera pose", "is not a rigid transform");
        std::lock_guard<std::mutex> lock(mu_);
        fixed_ = T;
    }
    void set_pose_source(std::function<Pose()> source) override {
        std::lock_guard<std::mutex> lock(mu_);
        cfg_.pose_source = std::move(source);
    }

    Photo capture(const Progress& progress) override {
        const auto t0 = std::chrono::steady_clock::now();
        progress.check();
        progress("capturing", 0.0);
        const Pose T = next_pose();
        Photo p = render(T, "IMG_" + std::to_string(10000 + captures_) + ".JPG");
        // A DSLR's shutter, processing and USB transfer take a while; rendering counts towards it.
        sleep_until(t0 + std::chrono::microseconds(int64_t(cfg_.capture_delay_ms * 1000)), progress);
        p.received_steady_ns = steady_ns();
        p.capture_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        ++captures_;
        last_capture_ms_ = p.capture_ms;
        progress("capturing", 1.0);
        return p;
    }

    StreamFormat start_stream(const StreamRequest&) override {
        streaming_ = true;
        next_frame_at_ = std::chrono::steady_clock::now();
        return {K_.width, K_.height, "sim", cfg_.stream_fps};
    }
    bool next_frame(Frame& out, std::chrono::milliseconds timeout) override {
        if (!streaming_) throw CameraError("sim:0", "not streaming (start_stream first)");
        const auto now = std::chrono::steady_clock::now();
        if (next_frame_at_ > now + timeout) return false;
        sleep_until(next_frame_at_, {});
        next_frame_at_ = std::max(next_frame_at_ + std::chrono::microseconds(int64_t(1e6 / cfg_.stream_fps)),
                                  std::chrono::steady_clock::now());
        Photo p = render(next_pose(), "frame.jpg");
        out.bgr = p.bgr;
        out.sequence = frames_++;
        out.received_steady_ns = steady_ns();
        return true;
    }
    void stop_stream() override { streaming_ = false; }

    CameraStats stats() const override {
        CameraStats s;
        s.captures = captures_;
        s.frames = frames_;
        s.errors = errors_;
        s.last_capture_ms = last_capture_ms_;
        return s;
    }

private:
    Pose next_pose() {
        std::function<Pose()> source;
        {
            std::lock_guard<std::mutex> lock(mu_);
            if (fixed_) return *fixed_;
            source = cfg_.pose_source;
        }
        if (source) {
            const Pose T = source();
            if (!is_rigid(T)) throw CameraError("sim:0", "the pose source gave a non-rigid transform");
            return T;
        }
        // Scripted orbit: a back-and-forth sweep about the camera's vertical axis through the
        // craniotomy, 0, +1, .. +4, +3, .. -4, .. steps (stays in view for small steps).
        const int k = int(orbit_index_++ % 16);
        const int tri = k <= 4 ? k : (k <= 12 ? 8 - k : k - 16);
        const Eigen::Vector3d pivot_camera = home_.topLeftCorner<3, 3>() * pivot_world_ + home_.topRightCorner<3, 1>();
        return apply_params(home_, pivot_camera, {0, cfg_.orbit_step_deg * tri, 0, 0, 0, 0});
    }

    Photo render(const Pose& T, const std::string& name) {
        PhantomParams prm = params_;
        prm.fixed_T_camera_from_world = T;
        PhantomCase c;
        try {
            c = generate_phantom_case(*surface_, prm, cfg_.case_index);
        } catch (const InputError& e) {
            ++errors_;
            throw CameraError("sim:0", std::string("nothing to photograph from this pose (") + e.what() + ")");
        }
        Photo p;
        p.name = name;
        p.mime = "image/jpeg";
        cv::imencode(".jpg", c.photo_bgr, p.bytes, {cv::IMWRITE_JPEG_QUALITY, cfg_.jpeg_quality});
        // What a camera delivers is the JPEG: decode it back, artefacts and all.
        p.bgr = cv::imdecode(p.bytes, cv::IMREAD_COLOR);
        p.T_camera_from_world = T;
        p.intrinsics = K_;
        return p;
    }

    SimCameraConfig cfg_;
    std::shared_ptr<const PhantomSurface> surface_;  // shared, read-only
    PhantomParams params_;
    Pose home_ = Pose::Identity();
    Intrinsics K_;
    Eigen::Vector3d pivot_world_;
    std::mutex mu_;  // guards fixed_ and cfg_.pose_source (set_pose / set_pose_source may come from another thread than capture)
    std::optional<Pose> fixed_;
    uint64_t orbit_index_ = 0;
    bool streaming_ = false;
    std::chrono::steady_clock::time_point next_frame_at_;
    std::atomic<uint64_t> captures_{0}, frames_{0}, errors_{0};
    std::atomic<double> last_capture_ms_{0};
};

class SimBackend final : public Backend {
public:
    explicit SimBackend(const SimCameraConfig& c) : cfg_(c) {}
    std::string name() const override { return "sim"; }
    std::vector<CameraInfo> list() override {
        return {{"sim", "sim:0", "CortexFuse simulated camera (phantom scene)", true, true}};
    }
    std::unique_ptr<Camera> open(const std::string& id) override {
        if (id != "sim:0" && id != "sim") throw CameraError(id, "the simulated backend has one camera, \"sim:0\"");
        return std::make_unique<SimCameraImpl>(cfg_);
    }

private:
    SimCameraConfig cfg_;
};

}  // namespace

std::unique_ptr<Backend> make_sim_backend(const SimCameraConfig& config) { return std::make_unique<SimBackend>(config); }

}  // namespace cf::camera
