#pragma once
// A headless EGL context with OpenGL 4.5 core: no window, no surface, no X server.
#include <epoxy/egl.h>

#include <string>

#include "cortexfuse/render/gl_renderer.hpp"

namespace cf::gl {

/// Owns one EGL context (the display is process-wide and never terminated, because other
/// contexts on it may live on). Thread contract: make_current() on the thread that uses it.
class EglContext {
public:
    /// Throws GlError naming what failed (CF_GL_DISABLE=1 makes this fail on purpose).
    EglContext();
    ~EglContext();
    EglContext(const EglContext&) = delete;
    EglContext& operator=(const EglContext&) = delete;

    void make_current() const;
    const GlInfo& info() const { return info_; }
    /// True when the context was created with reset notification (lost-context detection).
    bool robust() const { return robust_; }
    /// Fault injection (CF_GL_LOSE_CONTEXT_AT_FRAME): destroys the context through EGL as a
    /// driver reset or a vanished GPU would; every later make_current() throws GlError.
    void lose();

private:
    EGLDisplay display_ = EGL_NO_DISPLAY;
    EGLContext context_ = EGL_NO_CONTEXT;
    GlInfo info_;
    bool robust_ = false;
};

}  // namespace cf::gl
