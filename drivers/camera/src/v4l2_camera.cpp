// V4L2 backend: video sources (/dev/videoN). Format negotiation (MJPEG preferred for its
// bandwidth, then YUYV, else BGR24 which libv4l2 converts to from anything it knows), mmap
// streaming, conversion to BGR. All device calls go through libv4l2's wrappers (v4l2_open,
// v4l2_ioctl, v4l2_mmap) so that its format emulation is available.
#include <fcntl.h>
#include <libv4l2.h>
#include <linux/videodev2.h>
#include <poll.h>
#include <sys/mman.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <vector>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/drivers/camera.hpp"
#include "v4l2_convert.hpp"

namespace cf::camera {

namespace detail {

uint32_t fourcc_code(const std::string& s) {
    if (s.size() != 4) return 0;
    return uint32_t(uint8_t(s[0])) | uint32_t(uint8_t(s[1])) << 8 | uint32_t(uint8_t(s[2])) << 16 | uint32_t(uint8_t(s[3])) << 24;
}

std::string fourcc_string(uint32_t c) {
    std::string s(4, ' ');
    for (int i = 0; i < 4; ++i) s[size_t(i)] = char((c >> (8 * i)) & 0xFF);
    return s;
}

cv::Mat convert_frame(const std::string& fourcc, const uint8_t* data, size_t bytes, int w, int h, int bpl) {
    if (!data || w <= 0 || h <= 0) return {};
    cv::Mat out;
    if (fourcc == "MJPG" || fourcc == "JPEG") {
        if (bytes < 4) return {};
        try {
            out = cv::imdecode(cv::Mat(1, int(bytes), CV_8UC1, const_cast<uint8_t*>(data)), cv::IMREAD_COLOR);
        } catch (const cv::Exception&) {
            return {};
        }
        return out;
    }
    if (fourcc == "YUYV") {
        if (bpl < 2 * w) bpl = 2 * w;
        if (bytes < size_t(bpl) * size_t(h)) return {};  // truncated buffer: drop the frame
        const cv::Mat yuyv(h, w, CV_8UC2, const_cast<uint8_t*>(data), size_t(bpl));
        cv::cvtColor(yuyv, out, cv::COLOR_YUV2BGR_YUYV);
        return out;
    }
    if (fourcc == "BGR3" || fourcc == "RGB3") {
        if (bpl < 3 * w) bpl = 3 * w;
        if (bytes < size_t(bpl) * size_t(h)) return {};
        const cv::Mat view(h, w, CV_8UC3, const_cast<uint8_t*>(data), size_t(bpl));
        if (fourcc == "RGB3")
            cv::cvtColor(view, out, cv::COLOR_RGB2BGR);
        else
            out = view.clone();
        return out;
    }
    return {};
}

}  // namespace detail

namespace {

int64_t steady_ns() {
    return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

int xioctl(int fd, unsigned long req, void* arg) {
    int r;
    do r = v4l2_ioctl(fd, req, arg);
    while (r == -1 && errno == EINTR);
    return r;
}

bool capture_capable(const v4l2_capability& cap) {
    const uint32_t caps = (cap.capabilities & V4L2_CAP_DEVICE_CAPS) ? cap.device_caps : cap.capabilities;
    return (caps & V4L2_CAP_VIDEO_CAPTURE) && (caps & V4L2_CAP_STREAMING);
}

class V4l2Camera final : public Camera {
public:
    explicit V4l2Camera(const std::string& path) : path_(path) {
        fd_ = v4l2_open(path.c_str(), O_RDWR | O_NONBLOCK);
        if (fd_ < 0) throw CameraError(path, std::string("cannot open: ") + std::strerror(errno));
        v4l2_capability cap{};
        if (xioctl(fd_, VIDIOC_QUERYCAP, &cap) < 0) {
            const int e = errno;
            v4l2_close(fd_);
            throw CameraError(path, std::string("not a V4L2 device: ") + std::strerror(e));
        }
        if (!capture_capable(cap)) {
            v4l2_close(fd_);
            throw CameraError(path, "is not a video capture device with streaming I/O");
        }
        model_ = reinterpret_cast<const char*>(cap.card);
    }
    ~V4l2Camera() override {
        stop_stream();
        v4l2_close(fd_);
    }

    CameraInfo info() const override { return {"v4l2", path_, model_, true, true}; }

    StreamFormat start_stream(const StreamRequest& req) override {
        if (req.width < 16 || req.height < 16 || req.width > 16384 || req.height > 16384 || !(req.fps > 0 && req.fps <= 1000))
            throw InputError("stream request", "size 16..16384 px and fps in (0, 1000] expected");
        stop_stream();
        // Native formats the device offers (libv4l2 adds its emulated ones to the list too).
        std::vector<uint32_t> offered;
        v4l2_fmtdesc d{};
        d.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        for (d.index = 0; xioctl(fd_, VIDIOC_ENUM_FMT, &d) == 0; ++d.index) offered.push_back(d.pixelformat);
        uint32_t want = V4L2_PIX_FMT_BGR24;
        for (uint32_t f : {uint32_t(V4L2_PIX_FMT_MJPEG), uint32_t(V4L2_PIX_FMT_YUYV)})
            if (std::find(offered.begin(), offered.end(), f) != offered.end()) {
                want = f;
                break;
            }
        v4l2_format fmt{};
        fmt.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        fmt.fmt.pix.width = uint32_t(req.width);
        fmt.fmt.pix.height = uint32_t(req.height);
        fmt.fmt.pix.pixelformat = want;
        fmt.fmt.pix.field = V4L2_FIELD_ANY;
        if (xioctl(fd_, VIDIOC_S_FMT, &fmt) < 0) fail("cannot set the format " + detail::fourcc_string(want));
        // The driver picks its nearest size and may even change the format.
        format_.width = int(fmt.fmt.pix.width);
        format_.height = int(fmt.fmt.pix.height);
        format_.fourcc = detail::fourcc_string(fmt.fmt.pix.pixelformat);
        bytes_per_line_ = int(fmt.fmt.pix.bytesperline);
        if (format_.fourcc != "MJPG" && format_.fourcc != "YUYV" && format_.fourcc != "BGR3" && format_.fourcc != "RGB3")
            throw CameraError(path_, "the device gave the unsupported format " + format_.fourcc);

        v4l2_streamparm parm{};
        parm.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        parm.parm.capture.timeperframe.numerator = 1000;
        parm.parm.capture.timeperframe.denominator = uint32_t(req.fps * 1000);
        format_.fps = req.fps;
        if (xioctl(fd_, VIDIOC_S_PARM, &parm) == 0 && parm.parm.capture.timeperframe.numerator > 0)
            format_.fps = double(parm.parm.capture.timeperframe.denominator) / parm.parm.capture.timeperframe.numerator;

        v4l2_requestbuffers rb{};
        rb.count = 4;
        rb.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        rb.memory = V4L2_MEMORY_MMAP;
        if (xioctl(fd_, VIDIOC_REQBUFS, &rb) < 0) fail("cannot allocate mmap buffers");
        if (rb.count < 2) throw CameraError(path_, "the driver gave fewer than 2 buffers");
        for (uint32_t i = 0; i < rb.count; ++i) {
            v4l2_buffer b{};
            b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
            b.memory = V4L2_MEMORY_MMAP;
            b.index = i;
            if (xioctl(fd_, VIDIOC_QUERYBUF, &b) < 0) fail("cannot query buffer");
            void* p = v4l2_mmap(nullptr, b.length, PROT_READ | PROT_WRITE, MAP_SHARED, fd_, b.m.offset);
            if (p == MAP_FAILED) fail("cannot map buffer");
            buffers_.push_back({p, b.length});
            if (xioctl(fd_, VIDIOC_QBUF, &b) < 0) fail("cannot queue buffer");
        }
        v4l2_buf_type type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
        if (xioctl(fd_, VIDIOC_STREAMON, &type) < 0) fail("cannot start streaming");
        streaming_ = true;
        return format_;
    }

    bool next_frame(Frame& out, std::chrono::milliseconds timeout) override {
        if (!streaming_) throw CameraError(path_, "not streaming (start_stream first)");
        const auto deadline = std::chrono::steady_clock::now() + timeout;
        for (;;) {
            const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
            if (left.count() < 0) return false;
            pollfd pfd{fd_, POLLIN, 0};
            const int pr = ::poll(&pfd, 1, int(left.count()));
            if (pr < 0 && errno == EINTR) continue;
            if (pr < 0) fail("poll");
            if (pr == 0) return false;
            if (pfd.revents & (POLLERR | POLLHUP)) {
                ++errors_;
                throw CameraError(path_, "device error or unplugged while streaming");
            }
            v4l2_buffer b{};
            b.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
            b.memory = V4L2_MEMORY_MMAP;
            if (xioctl(fd_, VIDIOC_DQBUF, &b) < 0) {
                if (errno == EAGAIN) continue;
                ++errors_;
                fail("cannot dequeue a frame");
            }
            cv::Mat bgr;
            if (b.index < buffers_.size() && !(b.flags & V4L2_BUF_FLAG_ERROR))
                bgr = detail::convert_frame(format_.fourcc, static_cast<const uint8_t*>(buffers_[b.index].start),
                                            std::min<size_t>(b.bytesused, buffers_[b.index].length), format_.width,
                                            format_.height, bytes_per_line_);
            if (b.sequence > last_sequence_ + 1 && frames_ > 0) dropped_ += b.sequence - last_sequence_ - 1;
            last_sequence_ = b.sequence;
            if (xioctl(fd_, VIDIOC_QBUF, &b) < 0) fail("cannot requeue a buffer");
            if (bgr.empty()) {  // a corrupt or truncated frame: count it, never hand it up
                ++errors_;
                continue;
            }
            out.bgr = std::move(bgr);
            out.sequence = b.sequence;
            out.received_steady_ns = steady_ns();
            ++frames_;
            return true;
        }
    }

    void stop_stream() override {
        if (streaming_) {
            v4l2_buf_type type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
            xioctl(fd_, VIDIOC_STREAMOFF, &type);
            streaming_ = false;
        }
        for (const auto& b : buffers_) v4l2_munmap(b.start, b.length);
        if (!buffers_.empty()) {
            v4l2_requestbuffers rb{};
            rb.type = V4L2_BUF_TYPE_VIDEO_CAPTURE;
            rb.memory = V4L2_MEMORY_MMAP;
            xioctl(fd_, VIDIOC_REQBUFS, &rb);  // count 0 frees the driver's buffers
        }
        buffers_.clear();
    }

    Photo capture(const Progress& progress) override {
        const auto t0 = std::chrono::steady_clock::now();
        const bool was_streaming = streaming_;
        if (!was_streaming) start_stream(StreamRequest{1920, 1080, 30});
        Frame f;
        // A few frames first: auto exposure and white balance settle after stream start.
        const int skip = was_streaming ? 0 : 5;
        for (int i = 0; i <= skip; ++i) {
            progress.check();
            progress("capturing", double(i) / (skip + 1));
            if (!next_frame(f, std::chrono::milliseconds(2000))) {
                if (!was_streaming) stop_stream();
                ++errors_;
                throw CameraError(path_, "no frame within 2 s");
            }
        }
        if (!was_streaming) stop_stream();
        Photo p;
        p.bgr = f.bgr;
        p.name = "frame_" + std::to_string(f.sequence) + ".jpg";
        p.mime = "image/jpeg";
        cv::imencode(".jpg", p.bgr, p.bytes, {cv::IMWRITE_JPEG_QUALITY, 95});
        p.received_steady_ns = f.received_steady_ns;
        p.capture_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        ++captures_;
        last_capture_ms_ = p.capture_ms;
        return p;
    }

    CameraStats stats() const override {
        CameraStats s;
        s.captures = captures_;
        s.frames = frames_;
        s.errors = errors_;
        s.dropped = dropped_;
        s.last_capture_ms = last_capture_ms_;
        return s;
    }

private:
    [[noreturn]] void fail(const std::string& what) { throw CameraError(path_, what + ": " + std::strerror(errno)); }

    struct Buffer {
        void* start;
        size_t length;
    };
    std::string path_, model_;
    int fd_ = -1;
    bool streaming_ = false;
    StreamFormat format_;
    int bytes_per_line_ = 0;
    std::vector<Buffer> buffers_;
    uint32_t last_sequence_ = 0;
    std::atomic<uint64_t> captures_{0}, frames_{0}, errors_{0}, dropped_{0};
    std::atomic<double> last_capture_ms_{0};
};

class V4l2Backend final : public Backend {
public:
    std::string name() const override { return "v4l2"; }

    std::vector<CameraInfo> list() override {
        std::vector<CameraInfo> out;
        std::error_code ec;
        std::vector<std::string> nodes;
        for (const auto& e : std::filesystem::directory_iterator("/dev", ec)) {
            const std::string n = e.path().filename().string();
            if (n.rfind("video", 0) == 0) nodes.push_back(e.path().string());
        }
        std::sort(nodes.begin(), nodes.end());
        for (const auto& n : nodes) {
            const int fd = v4l2_open(n.c_str(), O_RDWR | O_NONBLOCK);
            if (fd < 0) continue;
            v4l2_capability cap{};
            // Metadata nodes of UVC cameras (a second /dev/videoN each) are not capture devices.
            if (xioctl(fd, VIDIOC_QUERYCAP, &cap) == 0 && capture_capable(cap))
                out.push_back({"v4l2", n, reinterpret_cast<const char*>(cap.card), true, true});
            v4l2_close(fd);
        }
        return out;
    }

    std::unique_ptr<Camera> open(const std::string& id) override { return std::make_unique<V4l2Camera>(id); }
};

}  // namespace

std::unique_ptr<Backend> make_v4l2_backend() { return std::make_unique<V4l2Backend>(); }

}  // namespace cf::camera
