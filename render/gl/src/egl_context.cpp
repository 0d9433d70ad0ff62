// Headless EGL: the device platform first (an NVIDIA GPU, or Mesa's software device), then
// Mesa's surfaceless platform (llvmpipe). Without an explicit platform EGL tries X11 and
// fails on a machine with no display, so the default display is never used. CF_GL_PLATFORM
// holds it to one of the two.
#include "egl_context.hpp"

#include <epoxy/gl.h>

#include <cstdlib>
#include <cstring>
#include <mutex>
#include <vector>

namespace cf::gl {
namespace {

std::string egl_error_name(EGLint e) {
    switch (e) {
    case EGL_SUCCESS: return "EGL_SUCCESS";
    case EGL_NOT_INITIALIZED: return "EGL_NOT_INITIALIZED";
    case EGL_BAD_ACCESS: return "EGL_BAD_ACCESS";
    case EGL_BAD_ALLOC: return "EGL_BAD_ALLOC";
    case EGL_BAD_ATTRIBUTE: return "EGL_BAD_ATTRIBUTE";
    case EGL_BAD_CONFIG: return "EGL_BAD_CONFIG";
    case EGL_BAD_CONTEXT: return "EGL_BAD_CONTEXT";
    case EGL_BAD_DISPLAY: return "EGL_BAD_DISPLAY";
    case EGL_BAD_MATCH: return "EGL_BAD_MATCH";
    case EGL_BAD_PARAMETER: return "EGL_BAD_PARAMETER";
    case EGL_CONTEXT_LOST: return "EGL_CONTEXT_LOST";
    default: return "EGL error " + std::to_string(e);
    }
}

struct Candidate {
    EGLDisplay display;
    std::string platform;
};

// Displays to try, in order. EGL initialisation is process-wide state in the EGL library;
// a mutex keeps concurrent renderer constructions from racing in it.
std::vector<Candidate> candidate_displays(std::string& notes) {
    std::vector<Candidate> out;
    const bool client_ext = epoxy_has_egl_extension(EGL_NO_DISPLAY, "EGL_EXT_platform_base");
    if (!client_ext) {
        notes += "EGL_EXT_platform_base missing; ";
        return out;
    }
    if (epoxy_has_egl_extension(EGL_NO_DISPLAY, "EGL_EXT_device_enumeration") &&
        epoxy_has_egl_extension(EGL_NO_DISPLAY, "EGL_EXT_platform_device")) {
        EGLint n = 0;
        if (eglQueryDevicesEXT(0, nullptr, &n) && n > 0) {
            std::vector<EGLDeviceEXT> devices(size_t(n), nullptr);
            eglQueryDevicesEXT(n, devices.data(), &n);
            for (EGLint i = 0; i < n; ++i) {
                EGLDisplay d = eglGetPlatformDisplayEXT(EGL_PLATFORM_DEVICE_EXT, devices[size_t(i)], nullptr);
                if (d != EGL_NO_DISPLAY) out.push_back({d, "device"});
            }
        } else {
            notes += "no EGL device; ";
        }
    }
    if (epoxy_has_egl_extension(EGL_NO_DISPLAY, "EGL_MESA_platform_surfaceless")) {
        EGLDisplay d = eglGetPlatformDisplayEXT(EGL_PLATFORM_SURFACELESS_MESA, EGL_DEFAULT_DISPLAY, nullptr);
        if (d != EGL_NO_DISPLAY) out.push_back({d, "surfaceless"});
    } else {
        notes += "EGL_MESA_platform_surfaceless missing; ";
    }
    return out;
}

std::mutex& egl_mutex() {
    static std::mutex m;
    return m;
}

}  // namespace

EglContext::EglContext() {
    if (const char* e = std::getenv("CF_GL_DISABLE"); e && std::strcmp(e, "0") != 0 && *e)
        throw GlError("disabled by CF_GL_DISABLE");
    std::lock_guard lock(egl_mutex());
    // CF_GL_PLATFORM=device|surfaceless keeps only that platform: a cart whose GPU driver
    // misbehaves can be held to Mesa, and the tests run each platform this machine has.
    std::string only;
    if (const char* e = std::getenv("CF_GL_PLATFORM"); e && *e) {
        only = e;
        if (only != "device" && only != "surfaceless")
            throw GlError("CF_GL_PLATFORM=" + only + ": not an EGL platform (device or surfaceless)");
    }
    std::string notes;
    std::vector<Candidate> candidates;
    try {
        candidates = candidate_displays(notes);
    } catch (const std::exception& ex) {
        // libepoxy aborts or throws when libEGL cannot be loaded at all.
        throw GlError(std::string("no EGL library: ") + ex.what());
    }
    if (!only.empty()) {
        std::erase_if(candidates, [&](const Candidate& c) { return c.platform != only; });
        if (candidates.empty())
            throw GlError("CF_GL_PLATFORM=" + only + ": no such EGL display here (" + notes + "unset it to try every platform)");
    }
    if (candidates.empty()) throw GlError("no headless EGL display (" + notes + "need a GPU driver or Mesa)");
    for (const auto& c : candidates) {
        EGLint major = 0, minor = 0;
        if (!eglInitialize(c.display, &major, &minor)) {
            notes += c.platform + ": eglInitialize " + egl_error_name(eglGetError()) + "; ";
            continue;
        }
        const bool surfaceless = epoxy_has_egl_extension(c.display, "EGL_KHR_surfaceless_context");
        const bool create_ctx = epoxy_has_egl_extension(c.display, "EGL_KHR_create_context");
        if (!surfaceless || !create_ctx) {
            notes += c.platform + ": no EGL_KHR_surfaceless_context/EGL_KHR_create_context; ";
            continue;
        }
        if (!eglBindAPI(EGL_OPENGL_API)) {
            notes += c.platform + ": no desktop OpenGL API; ";
            continue;
        }
        const EGLint config_attribs[] = {EGL_SURFACE_TYPE, EGL_PBUFFER_BIT, EGL_RENDERABLE_TYPE, EGL_OPENGL_BIT,
                                         EGL_RED_SIZE, 8, EGL_GREEN_SIZE, 8, EGL_BLUE_SIZE, 8, EGL_NONE};
        EGLConfig config = nullptr;
        EGLint nconf = 0;
        if (!eglChooseConfig(c.display, config_attribs, &config, 1, &nconf) || nconf < 1) {
            notes += c.platform + ": no suitable EGL config (OpenGL, RGB8); ";
            continue;
        }
        const bool robustness = epoxy_has_egl_extension(c.display, "EGL_EXT_create_context_robustness");
        for (bool robust : {true, false}) {
            if (robust && !robustness) continue;
            std::vector<EGLint> attribs = {EGL_CONTEXT_MAJOR_VERSION, 4, EGL_CONTEXT_MINOR_VERSION, 5,
                                           EGL_CONTEXT_OPENGL_PROFILE_MASK, EGL_CONTEXT_OPENGL_CORE_PROFILE_BIT};
            if (robust) {
                attribs.push_back(EGL_CONTEXT_OPENGL_RESET_NOTIFICATION_STRATEGY_EXT);
                attribs.push_back(EGL_LOSE_CONTEXT_ON_RESET_EXT);
            }
            attribs.push_back(EGL_NONE);
            context_ = eglCreateContext(c.display, config, EGL_NO_CONTEXT, attribs.data());
            if (context_ != EGL_NO_CONTEXT) {
                robust_ = robust;
                break;
            }
        }
        if (context_ == EGL_NO_CONTEXT) {
            notes += c.platform + ": no OpenGL 4.5 core context (" + egl_error_name(eglGetError()) + "); ";
            continue;
        }
        if (!eglMakeCurrent(c.display, EGL_NO_SURFACE, EGL_NO_SURFACE, context_)) {
            notes += c.platform + ": eglMakeCurrent " + egl_error_name(eglGetError()) + "; ";
            eglDestroyContext(c.display, context_);
            context_ = EGL_NO_CONTEXT;
            continue;
        }
        display_ = c.display;
        info_.platform = c.platform;
        auto str = [](GLenum e) {
            const auto* s = reinterpret_cast<const char*>(glGetString(e));
            return std::string(s ? s : "");
        };
        info_.vendor = str(GL_VENDOR);
        info_.renderer = str(GL_RENDERER);
        info_.version = str(GL_VERSION);
        return;
    }
    throw GlError("no OpenGL 4.5 core context could be made (" + notes.substr(0, notes.size() - 2) + ")");
}

EglContext::~EglContext() {
    if (context_ != EGL_NO_CONTEXT) {
        std::lock_guard lock(egl_mutex());
        if (eglGetCurrentContext() == context_) eglMakeCurrent(display_, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
        eglDestroyContext(display_, context_);
    }
}

void EglContext::lose() {
    std::lock_guard lock(egl_mutex());
    if (eglGetCurrentContext() == context_) eglMakeCurrent(display_, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT);
    eglDestroyContext(display_, context_);  // the handle stays: using it is what fails
}

void EglContext::make_current() const {
    if (eglGetCurrentContext() == context_) return;
    if (!eglMakeCurrent(display_, EGL_NO_SURFACE, EGL_NO_SURFACE, context_)) {
        const EGLint e = eglGetError();
        // A lost (reset) or destroyed context cannot be made current again: say so, so that the
        // owner drops this renderer and makes a new one (or, with auto, a CPU one).
        throw GlError("the GL context is lost or gone (eglMakeCurrent: " + egl_error_name(e) +
                      "); the GL renderer must be made again");
    }
}

}  // namespace cf::gl
