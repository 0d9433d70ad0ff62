// The camera interface's shared parts: defaults, backend choice, still decoding (OpenCV for
// JPEG/PNG/TIFF, libraw for camera raw).
#include "cortexfuse/drivers/camera.hpp"

#include <libraw/libraw.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "cortexfuse/core/error.hpp"

namespace cf::camera {

Photo Camera::download(const std::string& path) {
    throw CameraError(info().id, "has no storage to download \"" + path + "\" from");
}

StreamFormat Camera::start_stream(const StreamRequest&) { throw CameraError(info().id, "cannot stream live frames"); }

bool Camera::next_frame(Frame&, std::chrono::milliseconds) { throw CameraError(info().id, "cannot stream live frames"); }

std::unique_ptr<Backend> make_backend(const std::string& name, const SimCameraConfig& sim) {
    if (name == "gphoto2") return make_gphoto2_backend();
    if (name == "v4l2") return make_v4l2_backend();
    if (name == "sim") return make_sim_backend(sim);
    throw InputError("camera --backend", "unknown backend \"" + name + "\" (gphoto2, v4l2, sim)");
}

namespace {

std::string lower_extension(const std::string& name) {
    const auto dot = name.rfind('.');
    if (dot == std::string::npos) return {};
    std::string e = name.substr(dot + 1);
    std::transform(e.begin(), e.end(), e.begin(), [](unsigned char c) { return char(std::tolower(c)); });
    return e;
}

bool is_raw_extension(const std::string& ext) {
    // Camera raw formats libraw reads that OpenCV must not see: several are TIFF containers
    // whose first image is a small preview, which OpenCV would happily decode instead.
    static const std::array<const char*, 22> kRaw = {"cr2", "cr3", "crw", "nef", "nrw", "arw", "srf", "sr2",
                                                     "dng", "raf", "orf", "rw2", "pef", "srw", "x3f", "3fr",
                                                     "erf", "kdc", "mos", "mrw", "iiq", "rwl"};
    return std::find_if(kRaw.begin(), kRaw.end(), [&](const char* r) { return ext == r; }) != kRaw.end();
}

cv::Mat decode_raw(const std::vector<uint8_t>& bytes, const std::string& name) {
    // LibRaw is a large object (hundreds of KB): on the heap.
    auto raw = std::make_unique<LibRaw>();
    int rc = raw->open_buffer(const_cast<uint8_t*>(bytes.data()), bytes.size());
    if (rc != LIBRAW_SUCCESS) throw InputError(name, std::string("not a camera raw file libraw can read (") + libraw_strerror(rc) + ")");
    if ((rc = raw->unpack()) != LIBRAW_SUCCESS) throw InputError(name, std::string("raw data unreadable (") + libraw_strerror(rc) + ")");
    raw->imgdata.params.use_camera_wb = 1;  // the white balance the photographer saw
    raw->imgdata.params.output_bps = 8;
    raw->imgdata.params.output_color = 1;  // sRGB
    if ((rc = raw->dcraw_process()) != LIBRAW_SUCCESS)
        throw InputError(name, std::string("raw processing failed (") + libraw_strerror(rc) + ")");
    libraw_processed_image_t* img = raw->dcraw_make_mem_image(&rc);
    if (!img || rc != LIBRAW_SUCCESS) {
        if (img) LibRaw::dcraw_clear_mem(img);
        throw InputError(name, std::string("raw conversion failed (") + libraw_strerror(rc) + ")");
    }
    cv::Mat bgr;
    if (img->type == LIBRAW_IMAGE_BITMAP && img->bits == 8 && (img->colors == 3 || img->colors == 1)) {
        const cv::Mat view(img->height, img->width, img->colors == 3 ? CV_8UC3 : CV_8UC1, img->data);
        cv::cvtColor(view, bgr, img->colors == 3 ? cv::COLOR_RGB2BGR : cv::COLOR_GRAY2BGR);
    }
    LibRaw::dcraw_clear_mem(img);
    if (bgr.empty()) throw InputError(name, "raw conversion gave an unexpected image layout");
    return bgr;
}

}  // namespace

cv::Mat decode_still(const std::vector<uint8_t>& bytes, const std::string& name, bool* was_raw) {
    if (was_raw) *was_raw = false;
    if (bytes.empty()) throw InputError(name, "empty file, not an image");
    if (is_raw_extension(lower_extension(name))) {
        if (was_raw) *was_raw = true;
        return decode_raw(bytes, name);
    }
    cv::Mat img;
    try {
        img = cv::imdecode(cv::Mat(1, int(bytes.size()), CV_8UC1, const_cast<uint8_t*>(bytes.data())), cv::IMREAD_COLOR);
    } catch (const cv::Exception&) {
        img.release();
    }
    if (!img.empty()) return img;
    // An unknown extension may still be raw.
    try {
        cv::Mat r = decode_raw(bytes, name);
        if (was_raw) *was_raw = true;
        return r;
    } catch (const InputError&) {
        throw InputError(name, "not an image OpenCV or libraw can read");
    }
}

}  // namespace cf::camera
