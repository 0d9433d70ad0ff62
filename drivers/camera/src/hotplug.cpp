// Hot-plug through libudev: a netlink monitor on "usb" (devices) and "video4linux", read on
// the monitor's own thread; stop() wakes it through a pipe.
#include <fcntl.h>
#include <libudev.h>
#include <poll.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <thread>

#include "cortexfuse/drivers/camera.hpp"

namespace cf::camera {

namespace {

std::string str(const char* s) { return s ? s : ""; }

HotplugEvent describe(udev_device* dev, const char* action) {
    HotplugEvent e;
    e.action = str(action);
    e.subsystem = str(udev_device_get_subsystem(dev));
    e.devnode = str(udev_device_get_devnode(dev));
    // USB ids: on the device itself, or on its USB parent for a video4linux node.
    udev_device* usb = e.subsystem == "usb" ? dev : udev_device_get_parent_with_subsystem_devtype(dev, "usb", "usb_device");
    if (usb) {
        e.vendor_id = str(udev_device_get_sysattr_value(usb, "idVendor"));
        e.product_id = str(udev_device_get_sysattr_value(usb, "idProduct"));
        e.model = str(udev_device_get_sysattr_value(usb, "product"));
    }
    if (e.vendor_id.empty()) e.vendor_id = str(udev_device_get_property_value(dev, "ID_VENDOR_ID"));
    if (e.product_id.empty()) e.product_id = str(udev_device_get_property_value(dev, "ID_MODEL_ID"));
    if (e.model.empty()) e.model = str(udev_device_get_property_value(dev, "ID_MODEL"));
    return e;
}

}  // namespace

struct HotplugMonitor::Impl {
    udev* u = nullptr;              // owned
    udev_monitor* mon = nullptr;    // owned
    int wake[2] = {-1, -1};         // pipe: stop() writes, the thread wakes
    std::thread thread;
    Callback cb;

    ~Impl() {
        if (mon) udev_monitor_unref(mon);
        if (u) udev_unref(u);
        for (int fd : wake)
            if (fd >= 0) ::close(fd);
    }

    void run() {
        const int mfd = udev_monitor_get_fd(mon);
        for (;;) {
            pollfd p[2] = {{mfd, POLLIN, 0}, {wake[0], POLLIN, 0}};
            if (::poll(p, 2, -1) < 0) {
                if (errno == EINTR) continue;
                return;
            }
            if (p[1].revents) return;
            if (p[0].revents & POLLIN) {
                udev_device* dev = udev_monitor_receive_device(mon);
                if (!dev) continue;
                const char* devtype = udev_device_get_devtype(dev);
                const std::string sub = str(udev_device_get_subsystem(dev));
                // USB: whole devices only (not each interface).
                if (sub != "usb" || (devtype && std::strcmp(devtype, "usb_device") == 0)) {
                    const HotplugEvent e = describe(dev, udev_device_get_action(dev));
                    try {
                        cb(e);
                    } catch (...) {
                        // The callback's failure must not end hot-plug monitoring.
                    }
                }
                udev_device_unref(dev);
            }
        }
    }
};

HotplugMonitor::HotplugMonitor(Callback cb) : impl_(std::make_unique<Impl>()) {
    impl_->cb = std::move(cb);
    impl_->u = udev_new();
    if (!impl_->u) throw CameraError("udev", "cannot create a udev context");
    impl_->mon = udev_monitor_new_from_netlink(impl_->u, "udev");
    if (!impl_->mon) throw CameraError("udev", "cannot open the udev netlink monitor (no udev here, or no permission)");
    udev_monitor_filter_add_match_subsystem_devtype(impl_->mon, "usb", "usb_device");
    udev_monitor_filter_add_match_subsystem_devtype(impl_->mon, "video4linux", nullptr);
    if (udev_monitor_enable_receiving(impl_->mon) < 0)
        throw CameraError("udev", "cannot receive udev events (no udev here, or no permission)");
    if (::pipe2(impl_->wake, O_CLOEXEC) != 0) throw CameraError("udev", std::string("pipe: ") + std::strerror(errno));
    impl_->thread = std::thread([this] { impl_->run(); });
}

HotplugMonitor::~HotplugMonitor() { stop(); }

void HotplugMonitor::stop() {
    if (impl_ && impl_->thread.joinable()) {
        const char c = 1;
        [[maybe_unused]] const ssize_t n = ::write(impl_->wake[1], &c, 1);
        impl_->thread.join();
    }
}

std::vector<HotplugEvent> HotplugMonitor::present() {
    std::vector<HotplugEvent> out;
    udev* u = udev_new();
    if (!u) return out;
    udev_enumerate* en = udev_enumerate_new(u);
    if (en) {
        udev_enumerate_add_match_subsystem(en, "usb");
        udev_enumerate_add_match_subsystem(en, "video4linux");
        udev_enumerate_scan_devices(en);
        udev_list_entry* entry;
        udev_list_entry_foreach(entry, udev_enumerate_get_list_entry(en)) {
            udev_device* dev = udev_device_new_from_syspath(u, udev_list_entry_get_name(entry));
            if (!dev) continue;
            const char* devtype = udev_device_get_devtype(dev);
            const std::string sub = str(udev_device_get_subsystem(dev));
            if (sub != "usb" || (devtype && std::strcmp(devtype, "usb_device") == 0)) out.push_back(describe(dev, "present"));
            udev_device_unref(dev);
        }
        udev_enumerate_unref(en);
    }
    udev_unref(u);
    return out;
}

}  // namespace cf::camera
