// libgphoto2 backend: DSLRs tethered over USB/PTP (and whatever else libgphoto2 drives, e.g.
// the "Directory Browse" driver on a "disk:/folder" port, which the tests use).
#include <gphoto2/gphoto2.h>

#include <atomic>
#include <chrono>
#include <cstdlib>
#include <memory>
#include <mutex>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/drivers/camera.hpp"

namespace cf::camera {

namespace {

int64_t steady_ns() {
    return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

/// A GPContext that remembers libgphoto2's last error message and asks our CancelToken
/// whether to stop. Owns the context.
class Context {
public:
    Context() : ctx_(gp_context_new()) {
        gp_context_set_error_func(ctx_, &Context::on_error, this);
        gp_context_set_cancel_func(ctx_, &Context::on_cancel, this);
        gp_context_set_progress_funcs(ctx_, &Context::on_start, &Context::on_update, nullptr, this);
    }
    ~Context() { gp_context_unref(ctx_); }
    Context(const Context&) = delete;
    Context& operator=(const Context&) = delete;
    GPContext* get() const { return ctx_; }

    /// Borrowed for the duration of one operation.
    void set_progress(const Progress* p, const std::string& stage) {
        progress_ = p;
        stage_ = stage;
    }
    std::string take_message() {
        std::string m;
        m.swap(message_);
        return m;
    }
    bool cancelled() const { return progress_ && progress_->cancel && progress_->cancel->cancelled(); }

private:
    static void on_error(GPContext*, const char* text, void* data) { static_cast<Context*>(data)->message_ = text ? text : ""; }
    static GPContextFeedback on_cancel(GPContext*, void* data) {
        return static_cast<Context*>(data)->cancelled() ? GP_CONTEXT_FEEDBACK_CANCEL : GP_CONTEXT_FEEDBACK_OK;
    }
    static unsigned int on_start(GPContext*, float target, const char*, void* data) {
        static_cast<Context*>(data)->target_ = target > 0 ? target : 1.f;
        return 0;
    }
    static void on_update(GPContext*, unsigned int, float current, void* data) {
        auto* self = static_cast<Context*>(data);
        if (self->progress_) (*self->progress_)(self->stage_, std::min(1.0, double(current / self->target_)));
    }

    GPContext* ctx_;
    std::string message_;
    const Progress* progress_ = nullptr;
    std::string stage_;
    float target_ = 1.f;
};

struct ListDeleter {
    void operator()(CameraList* l) const { gp_list_free(l); }
};
using ListPtr = std::unique_ptr<CameraList, ListDeleter>;
ListPtr new_list() {
    CameraList* l = nullptr;
    if (gp_list_new(&l) < GP_OK) throw CameraError("gphoto2", "out of memory");
    return ListPtr(l);
}

struct FileDeleter {
    void operator()(CameraFile* f) const { gp_file_unref(f); }
};

std::string join(const std::string& folder, const std::string& name) {
    return folder == "/" ? "/" + name : folder + "/" + name;
}

class Gphoto2Camera final : public Camera {
public:
    Gphoto2Camera(const std::string& port, const std::string& model) : port_(port), model_(model) {
        if (gp_camera_new(&cam_) < GP_OK) throw CameraError(port, "out of memory");
        try {
            set_abilities_and_port();
            check(gp_camera_init(cam_, ctx_.get()), "cannot open the camera");
        } catch (...) {
            gp_camera_unref(cam_);
            throw;
        }
    }
    ~Gphoto2Camera() override {
        gp_camera_exit(cam_, ctx_.get());
        gp_camera_unref(cam_);
    }

    CameraInfo info() const override {
        CameraAbilities a;
        const bool have = gp_camera_get_abilities(cam_, &a) == GP_OK;
        return {"gphoto2", port_, model_, have && (a.operations & GP_OPERATION_CAPTURE_IMAGE), false};
    }

    Photo capture(const Progress& progress) override {
        const auto t0 = std::chrono::steady_clock::now();
        progress.check();
        ctx_.set_progress(&progress, "capturing");
        CameraFilePath path{};
        int rc = gp_camera_capture(cam_, GP_CAPTURE_IMAGE, &path, ctx_.get());
        if (rc < GP_OK) {
            ctx_.set_progress(nullptr, {});
            ++errors_;
            if (rc == GP_ERROR_CANCEL) throw Cancelled();
            check(rc, "capture failed");
        }
        // RAW+JPEG: the camera announces the second file as an event after the first; collect
        // those briefly so the caller knows (they stay on the card, download() fetches them).
        std::vector<std::string> companions;
        for (int i = 0; i < 20; ++i) {
            CameraEventType type;
            void* data = nullptr;
            if (gp_camera_wait_for_event(cam_, 50, &type, &data, ctx_.get()) < GP_OK) break;
            if (type == GP_EVENT_FILE_ADDED && data) {
                const auto* fp = static_cast<CameraFilePath*>(data);
                const std::string added = join(fp->folder, fp->name);
                if (added != join(path.folder, path.name)) companions.push_back(added);  // some announce the shot itself too
            }
            free(data);
            if (type == GP_EVENT_TIMEOUT || type == GP_EVENT_CAPTURE_COMPLETE) break;
        }
        Photo p = fetch(path.folder, path.name, progress);
        p.capture_ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        p.companion_files = std::move(companions);
        ++captures_;
        last_capture_ms_ = p.capture_ms;
        return p;
    }

    std::vector<std::string> list_files() override {
        std::vector<std::string> out;
        walk("/", out, 0);
        return out;
    }

    Photo download(const std::string& path) override {
        const auto slash = path.rfind('/');
        if (path.empty() || path[0] != '/' || slash == std::string::npos || slash + 1 == path.size())
            throw InputError("camera file \"" + path + "\"", "expected /folder/name as list_files() gives");
        const std::string folder = slash == 0 ? "/" : path.substr(0, slash);
        return fetch(folder, path.substr(slash + 1), {});
    }

    CameraStats stats() const override {
        CameraStats s;
        s.captures = captures_;
        s.errors = errors_;
        s.last_capture_ms = last_capture_ms_;
        return s;
    }

private:
    [[noreturn]] void fail(int rc, const std::string& what) {
        std::string detail = ctx_.take_message();
        std::string msg = what + ": " + gp_result_as_string(rc);
        if (!detail.empty()) msg += " (" + detail + ")";
        throw CameraError(port_, msg);
    }
    void check(int rc, const std::string& what) {
        if (rc < GP_OK) fail(rc, what);
    }

    void set_abilities_and_port() {
        CameraAbilitiesList* al = nullptr;
        check(gp_abilities_list_new(&al), "libgphoto2");
        std::unique_ptr<CameraAbilitiesList, int (*)(CameraAbilitiesList*)> al_guard(al, gp_abilities_list_free);
        check(gp_abilities_list_load(al, ctx_.get()), "cannot load libgphoto2's camera drivers");
        if (!model_.empty()) {
            const int m = gp_abilities_list_lookup_model(al, model_.c_str());
            if (m < GP_OK) throw CameraError(port_, "libgphoto2 has no driver for the model \"" + model_ + "\"");
            CameraAbilities a;
            check(gp_abilities_list_get_abilities(al, m, &a), "camera abilities");
            check(gp_camera_set_abilities(cam_, a), "camera abilities");
        }
        GPPortInfoList* pl = nullptr;
        check(gp_port_info_list_new(&pl), "libgphoto2");
        std::unique_ptr<GPPortInfoList, int (*)(GPPortInfoList*)> pl_guard(pl, gp_port_info_list_free);
        check(gp_port_info_list_load(pl), "cannot load libgphoto2's port drivers");
        // Exact paths ("usb:001,004") and patterns ("disk:" matches any "disk:/folder").
        const int p = gp_port_info_list_lookup_path(pl, port_.c_str());
        if (p < GP_OK) throw CameraError(port_, "no such port (try `cortexfuse camera list`)");
        GPPortInfo info;
        check(gp_port_info_list_get_info(pl, p, &info), "port info");
        check(gp_camera_set_port_info(cam_, info), "port info");
    }

    void walk(const std::string& folder, std::vector<std::string>& out, int depth) {
        if (depth > 8) return;  // DCIM/100CANON is two deep; stop at anything pathological
        ListPtr files = new_list();
        check(gp_camera_folder_list_files(cam_, folder.c_str(), files.get(), ctx_.get()), "cannot list " + folder);
        for (int i = 0, n = gp_list_count(files.get()); i < n; ++i) {
            const char* name = nullptr;
            gp_list_get_name(files.get(), i, &name);
            if (name) out.push_back(join(folder, name));
        }
        ListPtr dirs = new_list();
        check(gp_camera_folder_list_folders(cam_, folder.c_str(), dirs.get(), ctx_.get()), "cannot list " + folder);
        for (int i = 0, n = gp_list_count(dirs.get()); i < n; ++i) {
            const char* name = nullptr;
            gp_list_get_name(dirs.get(), i, &name);
            if (name) walk(join(folder, name), out, depth + 1);
        }
    }

    Photo fetch(const std::string& folder, const std::string& name, const Progress& progress) {
        CameraFile* raw_file = nullptr;
        check(gp_file_new(&raw_file), "libgphoto2");
        std::unique_ptr<CameraFile, FileDeleter> file(raw_file);
        ctx_.set_progress(&progress, "downloading");
        const int rc = gp_camera_file_get(cam_, folder.c_str(), name.c_str(), GP_FILE_TYPE_NORMAL, file.get(), ctx_.get());
        ctx_.set_progress(nullptr, {});
        if (rc < GP_OK) {
            ++errors_;
            if (rc == GP_ERROR_CANCEL) throw Cancelled();
            fail(rc, "cannot download " + join(folder, name));
        }
        const char* data = nullptr;
        unsigned long size = 0;
        check(gp_file_get_data_and_size(file.get(), &data, &size), "download");
        const char* mime = nullptr;
        gp_file_get_mime_type(file.get(), &mime);
        Photo p;
        p.name = name;
        p.mime = mime ? mime : "";
        if (p.mime.empty() || p.mime == GP_MIME_UNKNOWN || p.mime == "unknown/unknown") {
            // Some drivers (Directory Browse) leave the file's type unset; the file info has it.
            CameraFileInfo fi;
            if (gp_camera_file_get_info(cam_, folder.c_str(), name.c_str(), &fi, ctx_.get()) == GP_OK &&
                (fi.file.fields & GP_FILE_INFO_TYPE))
                p.mime = fi.file.type;
        }
        p.bytes.assign(reinterpret_cast<const uint8_t*>(data), reinterpret_cast<const uint8_t*>(data) + size);
        p.received_steady_ns = steady_ns();
        p.bgr = decode_still(p.bytes, join(folder, name), &p.raw);
        return p;
    }

    std::string port_, model_;
    Context ctx_;
    ::Camera* cam_ = nullptr;  // owned (gp_camera_unref)
    std::atomic<uint64_t> captures_{0}, errors_{0};
    std::atomic<double> last_capture_ms_{0};
};

class Gphoto2Backend final : public Backend {
public:
    std::string name() const override { return "gphoto2"; }

    std::vector<CameraInfo> list() override {
        Context ctx;
        ListPtr l = new_list();
        std::vector<CameraInfo> out;
        // Autodetect sees USB (and serial/PTP-IP if configured); a missing camera is an empty list.
        if (gp_camera_autodetect(l.get(), ctx.get()) < GP_OK) return out;
        for (int i = 0, n = gp_list_count(l.get()); i < n; ++i) {
            const char *model = nullptr, *port = nullptr;
            gp_list_get_name(l.get(), i, &model);
            gp_list_get_value(l.get(), i, &port);
            if (model && port) out.push_back({"gphoto2", port, model, true, false});
        }
        return out;
    }

    std::unique_ptr<Camera> open(const std::string& id) override {
        // "disk:/folder" is libgphoto2's Directory Browse driver; otherwise the model comes
        // from autodetection on that port (libgphoto2 picks it for USB when none is set).
        if (id.rfind("disk:", 0) == 0) return std::make_unique<Gphoto2Camera>(id, "Directory Browse");
        std::string model;
        for (const auto& c : list())
            if (c.id == id) model = c.model;
        if (model.empty() && id.rfind("usb:", 0) != 0)
            throw CameraError(id, "no camera found on this port (try `cortexfuse camera list`)");
        return std::make_unique<Gphoto2Camera>(id, model);
    }
};

}  // namespace

std::unique_ptr<Backend> make_gphoto2_backend() { return std::make_unique<Gphoto2Backend>(); }

}  // namespace cf::camera
