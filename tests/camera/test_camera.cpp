// Camera drivers with the real libraries: libgphoto2's Directory Browse driver ("disk:/folder")
// for the list/download path, libraw on a DNG written here, V4L2 frame conversion, V4L2 and
// udev against real devices (skipped when there are none), and the simulated camera.
#include <gtest/gtest.h>
#include <unistd.h>

#include <atomic>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/volume.hpp"
#include "cortexfuse/drivers/camera.hpp"
#include "v4l2_convert.hpp"

namespace fs = std::filesystem;
using namespace cf;
using namespace cf::camera;

namespace {

const fs::path kCalib = fs::path(CF_TEST_DATA_DIR) / "calibration";
const fs::path kVolume = fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz";
const fs::path kMask = fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz";

fs::path tmpdir(const std::string& name) {
    auto p = fs::temp_directory_path() / ("cf_test_camera_" + name + "_" + std::to_string(::getpid()));
    fs::remove_all(p);
    fs::create_directories(p);
    return p;
}

std::vector<uint8_t> slurp(const fs::path& p) {
    std::ifstream f(p, std::ios::binary);
    return std::vector<uint8_t>(std::istreambuf_iterator<char>(f), {});
}

/// A camera card: DCIM/100TEST with two photos, and a non-image file the driver must ignore.
fs::path make_card() {
    const fs::path card = tmpdir("card");
    fs::create_directories(card / "DCIM" / "100TEST");
    fs::copy_file(kCalib / "opencv_left01.jpg", card / "DCIM" / "100TEST" / "IMG_0001.jpg");
    fs::copy_file(kCalib / "opencv_left02.jpg", card / "DCIM" / "100TEST" / "IMG_0002.jpg");
    std::ofstream(card / "DCIM" / "notes.txt") << "not a photo";
    return card;
}

// ---- a minimal DNG (TIFF/EP with a CFA), written here so libraw has real raw input

void put16(std::vector<uint8_t>& b, uint16_t v) {
    b.push_back(uint8_t(v & 0xFF));
    b.push_back(uint8_t(v >> 8));
}
void put32(std::vector<uint8_t>& b, uint32_t v) {
    for (int i = 0; i < 4; ++i) b.push_back(uint8_t((v >> (8 * i)) & 0xFF));
}

/// RGGB Bayer mosaic, 12-bit in 16-bit words: left half red, right half blue.
std::vector<uint8_t> make_dng(int W, int H) {
    struct Entry {
        uint16_t tag, type;
        uint32_t count;
        std::vector<uint8_t> data;  // little-endian value bytes
    };
    auto shorts = [](std::initializer_list<uint16_t> v) {
        std::vector<uint8_t> d;
        for (auto x : v) put16(d, x);
        return d;
    };
    auto longs = [](std::initializer_list<uint32_t> v) {
        std::vector<uint8_t> d;
        for (auto x : v) put32(d, x);
        return d;
    };
    auto ascii = [](const std::string& s) {
        std::vector<uint8_t> d(s.begin(), s.end());
        d.push_back(0);
        return d;
    };
    std::vector<uint8_t> pixels;
    for (int y = 0; y < H; ++y)
        for (int x = 0; x < W; ++x) {
            const int c = (y % 2 == 0) ? (x % 2 == 0 ? 0 : 1) : (x % 2 == 0 ? 1 : 2);  // R G / G B
            const bool left = x < W / 2;
            const uint16_t v = c == 0 ? (left ? 3600 : 200) : c == 2 ? (left ? 200 : 3600) : 300;
            put16(pixels, v);
        }
    // sRGB's XYZ -> linear RGB matrix as ColorMatrix1: the "camera" has sRGB primaries.
    const int cm[9] = {32406, -15372, -4986, -9689, 18758, 415, 557, -2040, 10570};
    std::vector<uint8_t> cmd;
    for (int v : cm) put32(cmd, uint32_t(v)), put32(cmd, 10000);
    std::vector<Entry> e = {
        {254, 4, 1, longs({0})},
        {256, 4, 1, longs({uint32_t(W)})},
        {257, 4, 1, longs({uint32_t(H)})},
        {258, 3, 1, shorts({16})},
        {259, 3, 1, shorts({1})},
        {262, 3, 1, shorts({32803})},
        {271, 2, 0, ascii("CortexFuse")},
        {272, 2, 0, ascii("Test DNG")},
        {273, 4, 1, longs({0})},  // strip offset, patched below
        {274, 3, 1, shorts({1})},
        {277, 3, 1, shorts({1})},
        {278, 4, 1, longs({uint32_t(H)})},
        {279, 4, 1, longs({uint32_t(pixels.size())})},
        {284, 3, 1, shorts({1})},
        {33421, 3, 2, shorts({2, 2})},
        {33422, 1, 4, {0, 1, 1, 2}},
        {50706, 1, 4, {1, 4, 0, 0}},
        {50708, 2, 0, ascii("CortexFuse Test DNG")},
        {50717, 4, 1, longs({4095})},
        {50721, 10, 9, cmd},
        {50728, 5, 3, longs({1, 1, 1, 1, 1, 1})},
        {50778, 3, 1, shorts({21})},
    };
    for (auto& x : e)
        if (x.type == 2) x.count = uint32_t(x.data.size());
    std::vector<uint8_t> out = {'I', 'I', 42, 0};
    put32(out, 8);
    const uint32_t ifd_size = 2 + 12 * uint32_t(e.size()) + 4;
    uint32_t extra = 8 + ifd_size;  // values longer than 4 bytes follow the IFD
    std::vector<uint8_t> tail;
    const uint32_t strip_at = [&] {
        uint32_t n = extra;
        for (const auto& x : e)
            if (x.data.size() > 4) n += uint32_t(x.data.size() + (x.data.size() & 1));
        return n;
    }();
    put16(out, uint16_t(e.size()));
    for (auto& x : e) {
        if (x.tag == 273) x.data = longs({strip_at});
        put16(out, x.tag);
        put16(out, x.type);
        put32(out, x.count);
        if (x.data.size() <= 4) {
            std::vector<uint8_t> v = x.data;
            v.resize(4, 0);
            out.insert(out.end(), v.begin(), v.end());
        } else {
            put32(out, extra + uint32_t(tail.size()));
            tail.insert(tail.end(), x.data.begin(), x.data.end());
            if (x.data.size() & 1) tail.push_back(0);
        }
    }
    put32(out, 0);  // no next IFD
    out.insert(out.end(), tail.begin(), tail.end());
    EXPECT_EQ(out.size(), strip_at);
    out.insert(out.end(), pixels.begin(), pixels.end());
    return out;
}

}  // namespace

// ------------------------------------------------------------------ libgphoto2

TEST(Gphoto2, DirectoryBrowseListsAndDownloadsLikeACameraCard) {
    const fs::path card = make_card();
    auto backend = make_gphoto2_backend();
    std::unique_ptr<Camera> cam = backend->open("disk:" + card.string());
    EXPECT_EQ(cam->info().backend, "gphoto2");
    EXPECT_EQ(cam->info().model, "Directory Browse");

    auto files = cam->list_files();
    std::sort(files.begin(), files.end());
    // The driver serves image files only, from every folder, with paths on the "camera".
    ASSERT_EQ(files.size(), 2u) << (files.empty() ? std::string("none") : files[0]);
    EXPECT_NE(files[0].find("DCIM/100TEST/IMG_0001.jpg"), std::string::npos) << files[0];
    EXPECT_NE(files[1].find("DCIM/100TEST/IMG_0002.jpg"), std::string::npos) << files[1];

    const Photo p = cam->download(files[1]);
    EXPECT_EQ(p.name, "IMG_0002.jpg");
    EXPECT_EQ(p.mime, "image/jpeg");
    EXPECT_FALSE(p.raw);
    EXPECT_EQ(p.bytes, slurp(kCalib / "opencv_left02.jpg"));  // byte for byte what the card holds
    EXPECT_EQ(p.bgr.cols, 640);
    EXPECT_EQ(p.bgr.rows, 480);
    EXPECT_EQ(p.bgr.type(), CV_8UC3);
    EXPECT_GT(p.received_steady_ns, 0);

    // A file that is not there, and a malformed path.
    EXPECT_THROW(cam->download(files[0] + ".missing"), CameraError);
    EXPECT_THROW(cam->download("IMG_0001.jpg"), InputError);
    fs::remove_all(card);
}

TEST(Gphoto2, CaptureOnACameraWithoutCaptureIsACleanError) {
    // Directory Browse cannot take pictures: the error must name the port and the reason.
    const fs::path card = make_card();
    auto cam = make_gphoto2_backend()->open("disk:" + card.string());
    EXPECT_FALSE(cam->info().can_capture);
    try {
        cam->capture();
        FAIL() << "capture on Directory Browse succeeded";
    } catch (const CameraError& e) {
        EXPECT_NE(std::string(e.what()).find("disk:"), std::string::npos) << e.what();
        EXPECT_NE(std::string(e.what()).find("capture"), std::string::npos) << e.what();
    }
    EXPECT_EQ(cam->stats().errors, 1u);
    fs::remove_all(card);
}

TEST(Gphoto2, CorruptFileOnTheCardIsAnInputError) {
    const fs::path card = tmpdir("badcard");
    std::ofstream(card / "BROKEN.jpg") << "this is not a JPEG";
    auto cam = make_gphoto2_backend()->open("disk:" + card.string());
    const auto files = cam->list_files();
    ASSERT_EQ(files.size(), 1u);
    try {
        cam->download(files[0]);
        FAIL() << "a corrupt JPEG was decoded";
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("BROKEN.jpg"), std::string::npos) << e.what();
    }
    fs::remove_all(card);
}

TEST(Gphoto2, UsbCamerasAreListedOrSkipped) {
    const auto cams = make_gphoto2_backend()->list();  // never throws for "none"
    if (cams.empty()) GTEST_SKIP() << "no camera on USB/PTP (gphoto2 autodetect found none): USB capture not tested";
    for (const auto& c : cams) {
        EXPECT_EQ(c.backend, "gphoto2");
        EXPECT_FALSE(c.id.empty());
    }
}

TEST(Gphoto2, UnknownPortIsACameraError) {
    EXPECT_THROW(make_gphoto2_backend()->open("serial:/dev/does-not-exist-cf"), CameraError);
}

// ------------------------------------------------------------------ still decoding

TEST(DecodeStill, JpegAndGarbage) {
    bool raw = true;
    const cv::Mat img = decode_still(slurp(kCalib / "opencv_left03.jpg"), "left03.jpg", &raw);
    EXPECT_EQ(img.size(), cv::Size(640, 480));
    EXPECT_FALSE(raw);
    EXPECT_THROW(decode_still({}, "empty.jpg"), InputError);
    const std::vector<uint8_t> junk(1000, 0x5A);
    try {
        decode_still(junk, "junk.bin");
        FAIL() << "garbage decoded";
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("junk.bin"), std::string::npos);
    }
    EXPECT_THROW(decode_still(junk, "IMG_0001.CR2"), InputError);  // raw by name, not raw inside
}

TEST(DecodeStill, RawDngThroughLibraw) {
    const int W = 128, H = 96;
    bool raw = false;
    const cv::Mat img = decode_still(make_dng(W, H), "IMG_0001.DNG", &raw);
    EXPECT_TRUE(raw);
    ASSERT_EQ(img.type(), CV_8UC3);
    EXPECT_NEAR(img.cols, W, 4);
    EXPECT_NEAR(img.rows, H, 4);
    // Demosaiced colour: the left half red, the right half blue (BGR order).
    const cv::Scalar left = cv::mean(img(cv::Rect(8, 8, img.cols / 2 - 16, img.rows - 16)));
    const cv::Scalar right = cv::mean(img(cv::Rect(img.cols / 2 + 8, 8, img.cols / 2 - 16, img.rows - 16)));
    EXPECT_GT(left[2], left[0] + 60) << "left BGR " << left;
    EXPECT_GT(right[0], right[2] + 60) << "right BGR " << right;
    // Truncated raw data is an error, not a crash.
    auto cut = make_dng(W, H);
    cut.resize(cut.size() / 3);
    EXPECT_THROW(decode_still(cut, "cut.dng"), InputError);
}

// ------------------------------------------------------------------ V4L2

TEST(V4l2Convert, YuyvToBgr) {
    const int W = 8, H = 4;
    std::vector<uint8_t> buf;
    for (int y = 0; y < H; ++y)
        for (int x = 0; x < W / 2; ++x) {
            // left half: red (BT.601 video range Y 81, U 90, V 240); right half: mid grey
            const bool left = x < W / 4;
            const uint8_t Y = left ? 81 : 128, U = left ? 90 : 128, V = left ? 240 : 128;
            buf.insert(buf.end(), {Y, U, Y, V});
        }
    const cv::Mat bgr = detail::convert_frame("YUYV", buf.data(), buf.size(), W, H, 2 * W);
    ASSERT_EQ(bgr.size(), cv::Size(W, H));
    const cv::Vec3b red = bgr.at<cv::Vec3b>(1, 1), grey = bgr.at<cv::Vec3b>(1, W - 2);
    EXPECT_GT(red[2], 200);
    EXPECT_LT(red[1], 60);
    EXPECT_LT(red[0], 60);
    for (int c = 0; c < 3; ++c) EXPECT_NEAR(grey[c], 130, 12);
    // A truncated buffer is dropped, never half-converted.
    EXPECT_TRUE(detail::convert_frame("YUYV", buf.data(), buf.size() - 1, W, H, 2 * W).empty());
    EXPECT_TRUE(detail::convert_frame("H264", buf.data(), buf.size(), W, H, 2 * W).empty());
}

TEST(V4l2Convert, MjpegFrame) {
    const std::vector<uint8_t> jpg = slurp(kCalib / "opencv_left04.jpg");
    const cv::Mat bgr = detail::convert_frame("MJPG", jpg.data(), jpg.size(), 640, 480, 0);
    EXPECT_EQ(bgr.size(), cv::Size(640, 480));
    EXPECT_TRUE(detail::convert_frame("MJPG", jpg.data(), 3, 640, 480, 0).empty());
    EXPECT_EQ(detail::fourcc_string(detail::fourcc_code("MJPG")), "MJPG");
}

TEST(V4l2, StreamsFromARealDeviceOrSkips) {
    auto backend = make_v4l2_backend();
    const auto cams = backend->list();
    if (cams.empty()) GTEST_SKIP() << "no V4L2 capture device (/dev/video*) on this machine: streaming not tested";
    auto cam = backend->open(cams[0].id);
    const StreamFormat f = cam->start_stream({640, 480, 30});
    EXPECT_GT(f.width, 0);
    Frame fr;
    ASSERT_TRUE(cam->next_frame(fr, std::chrono::milliseconds(3000))) << "no frame from " << cams[0].id;
    EXPECT_EQ(fr.bgr.cols, f.width);
    cam->stop_stream();
}

TEST(V4l2, MissingDeviceIsACameraError) {
    EXPECT_THROW(make_v4l2_backend()->open("/dev/video-cf-does-not-exist"), CameraError);
    EXPECT_THROW(make_v4l2_backend()->open("/dev/null"), CameraError);  // not a V4L2 device
}

// ------------------------------------------------------------------ udev hot-plug

TEST(Hotplug, MonitorStartsAndStopsOrSkips) {
    const auto present = HotplugMonitor::present();  // empty without udev; never throws
    std::unique_ptr<HotplugMonitor> mon;
    try {
        mon = std::make_unique<HotplugMonitor>([](const HotplugEvent&) {});
    } catch (const CameraError& e) {
        GTEST_SKIP() << "udev monitor unavailable here (" << e.what() << "): hot-plug not tested";
    }
    mon->stop();
    mon->stop();  // idempotent
    bool usb_device = false;
    for (const auto& d : present) usb_device |= d.subsystem == "usb";
    if (!usb_device) GTEST_SKIP() << "monitor ran, but no USB device is visible through udev here";
}

// ------------------------------------------------------------------ backends

TEST(Backends, ByName) {
    EXPECT_EQ(make_backend("gphoto2")->name(), "gphoto2");
    EXPECT_EQ(make_backend("v4l2")->name(), "v4l2");
    EXPECT_THROW(make_backend("firewire"), InputError);
}

// ------------------------------------------------------------------ simulated camera

// One test: each ctest process would build the phantom scene (the brain surface) again.
TEST(SimCamera, PhotosForPosesWithTruthLatencyOrbitAndCancel) {
    SimCameraConfig c;
    c.surface = std::make_shared<const PhantomSurface>(build_phantom_surface(load_volume(kVolume), load_mask(kMask)));
    c.seed = 7;
    c.width = 320;
    c.height = 240;
    c.capture_delay_ms = 250;
    std::unique_ptr<Camera> owned = make_sim_backend(c)->open("sim:0");
    SimCamera& cam = dynamic_cast<SimCamera&>(*owned);

    {
        SCOPED_TRACE("size, truth, latency");
        const Photo p = cam.capture();
        EXPECT_EQ(p.bgr.cols, 320);
        EXPECT_EQ(p.bgr.rows, 240);
        EXPECT_EQ(p.bgr.type(), CV_8UC3);
        EXPECT_EQ(p.mime, "image/jpeg");
        EXPECT_EQ(decode_still(p.bytes, p.name).size(), p.bgr.size());  // the bytes are the JPEG delivered
        ASSERT_TRUE(p.T_camera_from_world.has_value());
        ASSERT_TRUE(p.intrinsics.has_value());
        EXPECT_EQ(p.intrinsics->width, 320);
        EXPECT_TRUE(p.T_camera_from_world->isApprox(cam.home_pose()));  // the orbit starts at home
        EXPECT_GE(p.capture_ms, 250.0);  // the configured shutter + transfer delay
        cv::Scalar mean, sd;
        cv::meanStdDev(p.bgr, mean, sd);
        EXPECT_GT(sd[2], 10.0);  // the scene is there: not a flat image
        EXPECT_EQ(cam.stats().captures, 1u);
    }
    {
        SCOPED_TRACE("scripted orbit");
        const Photo b = cam.capture();
        EXPECT_FALSE(b.T_camera_from_world->isApprox(cam.home_pose()));
    }
    {
        SCOPED_TRACE("the photo changes with the pose and repeats for the same pose");
        const Pose home = cam.home_pose();
        cam.set_pose(home);
        const Photo a = cam.capture();
        const Photo a2 = cam.capture();
        EXPECT_EQ(cv::norm(a.bgr, a2.bgr, cv::NORM_L1), 0.0);  // deterministic scene
        EXPECT_TRUE(a.T_camera_from_world->isApprox(home));
        // 8 degrees about a point 300 mm ahead, as a tracked camera moving round the head would.
        const Pose moved = apply_params(home, Eigen::Vector3d(0, 0, 300), {0, 8, 0, 0, 0, 0});
        cam.set_pose(moved);
        const Photo b = cam.capture();
        EXPECT_TRUE(b.T_camera_from_world->isApprox(moved));
        cv::Mat diff;
        cv::absdiff(a.bgr, b.bgr, diff);
        EXPECT_GT(cv::mean(diff)[1], 5.0) << "the photo did not change with the pose";
        // Looking away from the head: a clean error, not a blank photo.
        cam.set_pose(apply_params(home, Eigen::Vector3d(0, 0, 0), {0, 120, 0, 0, 0, 0}));
        EXPECT_THROW(cam.capture(), CameraError);
        cam.set_pose(std::nullopt);
    }
    {
        SCOPED_TRACE("a tracked pose source (what the tracker simulator's camera tool feeds)");
        SimCameraConfig tracked = c;
        int calls = 0;
        const Pose target = apply_params(cam.home_pose(), Eigen::Vector3d(0, 0, 300), {3, -4, 0, 2, 0, 0});
        tracked.pose_source = [&] {
            ++calls;
            return target;
        };
        tracked.capture_delay_ms = 0;
        auto second = make_sim_backend(tracked)->open("sim:0");  // shares the surface
        const Photo t = second->capture();
        EXPECT_EQ(calls, 1);
        EXPECT_TRUE(t.T_camera_from_world->isApprox(target));
        tracked.pose_source = [] { return Pose(Pose::Zero()); };
        EXPECT_THROW(make_sim_backend(tracked)->open("sim:0")->capture(), CameraError);
    }
    {
        SCOPED_TRACE("cancel and bad pose");
        CancelToken cancel;
        cancel.cancel();
        Progress p;
        p.cancel = &cancel;
        EXPECT_THROW(cam.capture(p), Cancelled);
        EXPECT_THROW(cam.set_pose(Pose::Zero()), InputError);
    }
}

TEST(SimCamera, PoseSourceAndBadConfig) {
    SimCameraConfig c;
    c.volume_path = kVolume.string();
    c.mask_path = kMask.string();
    c.width = 10;  // too small
    EXPECT_THROW(make_sim_backend(c)->open("sim:0"), InputError);
    c.width = 320;
    c.capture_delay_ms = -1;
    EXPECT_THROW(make_sim_backend(c)->open("sim:0"), InputError);
    c.capture_delay_ms = 0;
    c.volume_path = "/nonexistent/t1.nii.gz";
    EXPECT_THROW(make_sim_backend(c)->open("sim:0"), InputError);
    EXPECT_THROW(make_sim_backend(c)->open("sim:3"), CameraError);
    EXPECT_EQ(make_sim_backend(c)->list().size(), 1u);
}
