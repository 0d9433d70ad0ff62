#pragma once
// The off-screen OpenGL ray caster: an EGL context with no window and no X server (EGL device
// platform on an NVIDIA GPU, Mesa's surfaceless platform with llvmpipe on a CPU-only machine,
// chosen automatically), OpenGL 4.5 core through libepoxy, GLSL from shaders/ embedded at
// build time, framebuffer objects as render targets. Same pictures as the CPU ray caster
// (same sampling lattice, trilinear interpolation, surface refinement, shading, compositing
// and outputs), plus the fusion scene of cortexfuse/core/fusion.hpp.
//
// Thread contract: each renderer owns its own GL context and makes it current on the calling
// thread for each call; one call at a time per renderer.
#include <memory>
#include <stdexcept>
#include <string>

#include "cortexfuse/core/fusion.hpp"

namespace cf {

/// Everything that goes wrong with GL: no EGL, no suitable config or context, a shader that
/// does not compile or link (the message carries the info log), a GL error, a lost context.
class GlError : public std::runtime_error {
public:
    explicit GlError(const std::string& what) : std::runtime_error("OpenGL: " + what) {}
};

/// What the context turned out to be.
struct GlInfo {
    std::string platform;  // "device" (EGL_EXT_platform_device) or "surfaceless" (Mesa)
    std::string vendor, renderer, version;
};

/// An empty fusion scene on a fresh context; `info` (optional) receives what the context is.
/// Throws GlError.
std::unique_ptr<FusionRenderer> make_gl_fusion_renderer(GlInfo* info = nullptr);
/// The GL counterpart of make_cpu_renderer(): one layer. Throws GlError (and InputError for a
/// mask on another grid).
std::unique_ptr<FusionRenderer> make_gl_renderer(const Volume& volume, const TransferFunction& tf,
                                                 const LabelVolume* mask = nullptr);

/// Makes a context and reports what it is; throws GlError with the reason when none can be made.
GlInfo probe_gl();

/// Compiles and links a program from vertex and fragment sources in a fresh context; throws
/// GlError with the info log. Returns the driver's (possibly empty) warnings log.
std::string check_gl_program(const std::string& vertex_source, const std::string& fragment_source);

/// Names and texts of the embedded shaders (shaders/*.vert, *.frag).
struct EmbeddedShader {
    const char* name;
    const char* text;
};
std::vector<EmbeddedShader> embedded_shaders();

}  // namespace cf
