// Hot-plug (issue 5): the production HotplugMonitor (a libudev netlink monitor) and
// HotplugMonitor::present() against devices in a umockdev testbed: a DSLR and a UVC camera are
// plugged and unplugged, and the monitor reports each event with the device's USB ids, whole
// USB devices only (not their interfaces). umockdev (Debian's umockdev, a well-kept library:
// its preload gives libudev a sysfs and a uevent socket of the test's own) stands in for the
// kernel, so the udev code is what runs. The test must run under umockdev-wrapper (ctest does
// that); run bare, it skips.
#include <umockdev.h>

#include <gtest/gtest.h>

#include <chrono>
#include <condition_variable>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include "cortexfuse/drivers/camera.hpp"

using cf::camera::HotplugEvent;
using cf::camera::HotplugMonitor;

namespace {

/// Events the monitor delivered (on its own thread), waited for by the test thread.
struct Received {
    std::mutex m;
    std::condition_variable cv;
    std::vector<HotplugEvent> events;

    void push(const HotplugEvent& e) {
        std::lock_guard lk(m);
        events.push_back(e);
        cv.notify_all();
    }
    /// The n-th event (0-based), waiting up to `wait`; nullopt when it did not come.
    std::optional<HotplugEvent> at(std::size_t n, std::chrono::milliseconds wait = std::chrono::milliseconds(5000)) {
        std::unique_lock lk(m);
        if (!cv.wait_for(lk, wait, [&] { return events.size() > n; })) return std::nullopt;
        return events[n];
    }
};

struct Testbed {
    UMockdevTestbed* tb = umockdev_testbed_new();
    ~Testbed() { g_object_unref(tb); }
};

}  // namespace

TEST(HotplugUmockdev, PlugAndUnplugArriveWithTheDevicesIdsAndInterfacesAreLeftOut) {
    Testbed bed;  // first: umockdev tells a mock environment by /sys being the testbed's
    if (!umockdev_in_mock_environment()) GTEST_SKIP() << "not under umockdev-wrapper (ctest runs it so)";
    Received got;
    HotplugMonitor mon([&](const HotplugEvent& e) { got.push(e); });

    // Adding a device to the testbed sends its "add" uevent, as the kernel would on a plug.
    // A DSLR on the bus (what gphoto2 would open): a whole USB device.
    gchar* dslr = umockdev_testbed_add_device(bed.tb, "usb", "1-1", nullptr,
                                              // sysfs attributes
                                              "idVendor", "04a9", "idProduct", "32d9", "product", "Canon EOS R6", nullptr,
                                              // udev properties
                                              "DEVTYPE", "usb_device", "DEVNAME", "/dev/bus/usb/001/002", nullptr);
    ASSERT_NE(dslr, nullptr);
    // One of its interfaces: not a device of its own, so no event.
    gchar* intf = umockdev_testbed_add_device(bed.tb, "usb", "1-1:1.0", dslr, "bInterfaceClass", "06", nullptr, "DEVTYPE",
                                              "usb_interface", nullptr);
    ASSERT_NE(intf, nullptr);
    // A UVC camera: its video4linux node carries the ids of its USB parent.
    gchar* uvc = umockdev_testbed_add_device(bed.tb, "usb", "1-2", nullptr, "idVendor", "046d", "idProduct", "085e", "product",
                                             "Logitech BRIO", nullptr, "DEVTYPE", "usb_device", "DEVNAME", "/dev/bus/usb/001/003",
                                             nullptr);
    ASSERT_NE(uvc, nullptr);
    gchar* video = umockdev_testbed_add_device(bed.tb, "video4linux", "video0", uvc, "name", "Logitech BRIO", nullptr, "DEVNAME",
                                               "/dev/video0", nullptr);
    ASSERT_NE(video, nullptr);

    struct Want {
        const char *subsystem, *devnode, *vendor, *product, *model;
    };
    const Want want[] = {{"usb", "/dev/bus/usb/001/002", "04a9", "32d9", "Canon EOS R6"},
                         {"usb", "/dev/bus/usb/001/003", "046d", "085e", "Logitech BRIO"},
                         {"video4linux", "/dev/video0", "046d", "085e", "Logitech BRIO"}};
    for (std::size_t i = 0; i < 3; ++i) {
        const auto e = got.at(i);
        ASSERT_TRUE(e) << "event " << i << " (" << want[i].subsystem << " " << want[i].devnode << ") did not come";
        EXPECT_EQ(e->action, "add");
        EXPECT_EQ(e->subsystem, want[i].subsystem) << "event " << i;
        EXPECT_EQ(e->devnode, want[i].devnode) << "event " << i << " (an interface's event would have no node)";
        EXPECT_EQ(e->vendor_id, want[i].vendor) << "event " << i;
        EXPECT_EQ(e->product_id, want[i].product) << "event " << i;
        EXPECT_EQ(e->model, want[i].model) << "event " << i;
    }
    // The interface's uevent, sent again on its own: still nothing.
    umockdev_testbed_uevent(bed.tb, intf, "change");
    EXPECT_FALSE(got.at(3, std::chrono::milliseconds(300))) << "an interface's event was reported";

    // What is plugged in now: both cameras' USB devices and the video node, no interface.
    const auto present = HotplugMonitor::present();
    int dslrs = 0, uvcs = 0, nodes = 0;
    for (const auto& d : present) {
        dslrs += d.subsystem == "usb" && d.vendor_id == "04a9";
        uvcs += d.subsystem == "usb" && d.vendor_id == "046d";
        nodes += d.subsystem == "video4linux" && d.devnode == "/dev/video0";
    }
    EXPECT_EQ(dslrs, 1);
    EXPECT_EQ(uvcs, 1);
    EXPECT_EQ(nodes, 1);

    // Unplugged: the DSLR's remove arrives with its ids.
    umockdev_testbed_uevent(bed.tb, dslr, "remove");
    const auto r = got.at(3);
    ASSERT_TRUE(r) << "no event for the DSLR's remove";
    EXPECT_EQ(r->action, "remove");
    EXPECT_EQ(r->subsystem, "usb");
    EXPECT_EQ(r->vendor_id, "04a9");
    EXPECT_EQ(r->devnode, "/dev/bus/usb/001/002");
    // After stop(), nothing more is delivered.
    mon.stop();
    umockdev_testbed_uevent(bed.tb, uvc, "remove");
    EXPECT_FALSE(got.at(4, std::chrono::milliseconds(300))) << "an event after stop()";
    g_free(dslr);
    g_free(intf);
    g_free(uvc);
    g_free(video);
}
