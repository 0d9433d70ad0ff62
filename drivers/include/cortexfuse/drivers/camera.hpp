#pragma once
// One interface for the cameras of the cart: list, open, capture a still, download files
// already on the camera, and live frames. Backends:
//   "gphoto2"  libgphoto2: a DSLR tethered over USB/PTP (and any camera libgphoto2 drives,
//              e.g. "Directory Browse" over a "disk:/folder" port); JPEG and raw (libraw)
//   "v4l2"     a V4L2 video source (/dev/videoN): format negotiation, mmap streaming,
//              MJPEG/YUYV decoded to BGR (libv4l2 converts anything else)
//   "sim"      a simulated camera: phantom photographs rendered for a pose (docs/camera.md)
// Hot-plug of USB cameras and video devices is seen through libudev (HotplugMonitor).
//
// Images are 8-bit BGR cv::Mat (OpenCV order). Errors: CameraError for a device that is
// absent, busy, unplugged or failing (naming the device and the problem); cf::InputError for
// bad input (an unknown backend, a bad option, an undecodable file).
//
// Thread contract: a Camera is used by one thread at a time (the daemon's camera thread
// owns it); stats() may be called from any thread. Backends are stateless enough that list()
// and open() may be called from any thread.
#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include <opencv2/core.hpp>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/progress.hpp"

namespace cf::camera {

/// A device problem: absent, busy, unplugged, an I/O or protocol failure.
class CameraError : public std::runtime_error {
public:
    CameraError(const std::string& device, const std::string& problem)
        : std::runtime_error(device + ": " + problem), device_(device) {}
    const std::string& device() const { return device_; }

private:
    std::string device_;
};

struct CameraInfo {
    std::string backend;  // "gphoto2", "v4l2", "sim"
    std::string id;       // what open() takes: "usb:001,004", "disk:/path", "/dev/video0", "sim:0"
    std::string model;    // human-readable name
    bool can_capture = false;  // can take a still on command
    bool can_stream = false;   // can deliver live frames
};

/// A still photograph as the camera delivered it, and decoded.
struct Photo {
    cv::Mat bgr;                  // decoded, 8-bit BGR
    std::vector<uint8_t> bytes;   // the file as delivered (JPEG or raw), to archive unchanged
    std::string name;             // file name on the camera ("IMG_0001.JPG"), or made up
    std::string mime;             // "image/jpeg", "image/x-canon-cr2", ...
    bool raw = false;             // decoded through libraw
    int64_t received_steady_ns = 0;  // host steady clock when the download finished
    double capture_ms = 0;           // from the capture command to the download's end
    /// Other files the same shot wrote (RAW+JPEG mode): "/folder/name" for download().
    std::vector<std::string> companion_files;
    /// Simulated camera only: the truth it was rendered with.
    std::optional<Pose> T_camera_from_world;
    std::optional<Intrinsics> intrinsics;
};

/// A live frame.
struct Frame {
    cv::Mat bgr;
    uint64_t sequence = 0;        // the device's sequence number (or a counter)
    int64_t received_steady_ns = 0;
};

/// What a stream was negotiated to.
struct StreamFormat {
    int width = 0, height = 0;
    std::string fourcc;  // "MJPG", "YUYV", "BGR3" (converted by libv4l2), "sim"
    double fps = 0;
};

struct StreamRequest {
    int width = 1280, height = 720;  // preferred; the device picks its nearest
    double fps = 30;
};

/// Counters every driver keeps (served by the daemon as the camera's status).
struct CameraStats {
    uint64_t captures = 0, frames = 0, errors = 0, dropped = 0;
    double last_capture_ms = 0;
};

/// An open camera. Owned by its user (unique_ptr); closing is the destructor.
class Camera {
public:
    virtual ~Camera() = default;
    virtual CameraInfo info() const = 0;

    /// Takes one still and downloads it. Cancellable between steps (progress.cancel).
    /// Throws CameraError on failure, cf::Cancelled when cancelled.
    virtual Photo capture(const Progress& progress = {}) = 0;

    /// Image files stored on the camera ("/folder/name"); empty if it has no storage.
    virtual std::vector<std::string> list_files() { return {}; }
    /// Downloads (and decodes) one of list_files(). Throws CameraError / InputError.
    virtual Photo download(const std::string& path);

    /// Live frames: start, pull, stop. next_frame returns false on timeout.
    virtual StreamFormat start_stream(const StreamRequest& request);
    virtual bool next_frame(Frame& out, std::chrono::milliseconds timeout);
    virtual void stop_stream() {}

    virtual CameraStats stats() const = 0;
};

class Backend {
public:
    virtual ~Backend() = default;
    virtual std::string name() const = 0;
    /// Cameras present now. Never throws for "none found" (empty list).
    virtual std::vector<CameraInfo> list() = 0;
    /// Opens by id (as list() reports, or a backend-specific address). Throws CameraError.
    virtual std::unique_ptr<Camera> open(const std::string& id) = 0;
};

std::unique_ptr<Backend> make_gphoto2_backend();
std::unique_ptr<Backend> make_v4l2_backend();

/// The simulated camera's scene and behaviour.
struct SimCameraConfig {
    std::string volume_path;  // T1 MRI and its brain mask (the phantom generator's inputs)
    std::string mask_path;
    /// A brain surface already built from them (shared, read-only): opening then skips the
    /// few seconds of building it.
    std::shared_ptr<const PhantomSurface> surface;
    uint64_t seed = 1;        // the scene (craniotomy, vessels, look) comes from the seed
    int case_index = 0;
    int width = 640, height = 480;  // sensor size; the focal length follows the scene's framing
    /// Delay between the capture command and the photo, like a DSLR's shutter + transfer. 0..10000 ms.
    double capture_delay_ms = 300;
    /// Live frames per second. 1..60.
    double stream_fps = 10;
    /// Where the camera is for each capture, unless set_pose() fixed one: nullptr means a
    /// scripted orbit (each capture a few degrees further round the craniotomy); a tracked
    /// pose source (e.g. the tracker simulator's camera tool) goes here. Called on the
    /// capturing thread.
    std::function<Pose()> pose_source;
    /// Orbit step of the scripted trajectory per capture, degrees. 0..45.
    double orbit_step_deg = 5;
    /// JPEG quality of the delivered file. 50..100.
    int jpeg_quality = 92;
    void validate() const;  // throws InputError("sim camera <field>", ...)
};

/// The simulated camera's extra controls (the Camera from a sim backend is one of these).
class SimCamera : public Camera {
public:
    /// The pose of the scene's own framing (the orbit's start).
    virtual Pose home_pose() const = 0;
    virtual Intrinsics intrinsics() const = 0;
    /// Fixes the pose of the following captures (nullopt: back to pose_source / the orbit).
    virtual void set_pose(const std::optional<Pose>& T_camera_from_world) = 0;
    /// Replaces SimCameraConfig::pose_source for the following captures (empty: the scripted
    /// orbit). For a source that needs home_pose() first, e.g. the tracker simulator's camera tool
    /// (cortexfuse/drivers/sim/tracked_camera.hpp). Any thread.
    virtual void set_pose_source(std::function<Pose()> pose_source) = 0;
};

/// The simulated backend lists one camera, "sim:0". Opening it builds the phantom scene
/// (a few seconds: the brain surface from the MRI).
std::unique_ptr<Backend> make_sim_backend(const SimCameraConfig& config);

/// "gphoto2", "v4l2", "sim" -> a backend (sim with `sim` as its configuration).
std::unique_ptr<Backend> make_backend(const std::string& name, const SimCameraConfig& sim = {});

/// Decodes a still from its bytes: JPEG/PNG/TIFF through OpenCV, camera raw (CR2, NEF, ARW,
/// DNG, ...) through libraw. Throws InputError(name, ...) when neither can read it.
cv::Mat decode_still(const std::vector<uint8_t>& bytes, const std::string& name, bool* was_raw = nullptr);

// ------------------------------------------------------------------ hot-plug (libudev)

struct HotplugEvent {
    std::string action;     // "add", "remove", "change", "bind", ...
    std::string subsystem;  // "usb" or "video4linux"
    std::string devnode;    // "/dev/bus/usb/001/004", "/dev/video0" (may be empty)
    std::string vendor_id, product_id;  // USB ids, hex, when known
    std::string model;
};

/// Watches udev for USB devices and video4linux nodes appearing and going away.
/// The callback runs on the monitor's own thread. Owned by its user; stop() or the
/// destructor joins the thread.
class HotplugMonitor {
public:
    using Callback = std::function<void(const HotplugEvent&)>;
    /// Throws CameraError("udev", ...) when the udev netlink socket cannot be opened (no
    /// udev in a container, no permission).
    explicit HotplugMonitor(Callback cb);
    ~HotplugMonitor();
    HotplugMonitor(const HotplugMonitor&) = delete;
    HotplugMonitor& operator=(const HotplugMonitor&) = delete;
    void stop();

    /// Present devices of the same subsystems (udev enumeration; empty without udev).
    static std::vector<HotplugEvent> present();

private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
};

}  // namespace cf::camera
