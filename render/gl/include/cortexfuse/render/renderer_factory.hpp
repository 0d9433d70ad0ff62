#pragma once
// Choosing the ray-casting backend: --renderer cpu|gl|auto on every command that renders.
#include <functional>
#include <memory>
#include <string>

#include "cortexfuse/core/renderer.hpp"

namespace cf {

enum class RendererKind { cpu, gl, automatic };

/// "cpu", "gl" or "auto"; throws InputError(context, ...) otherwise.
RendererKind parse_renderer_kind(const std::string& s, const std::string& context = "--renderer");
const char* to_string(RendererKind k);

/// cpu: the CPU ray caster. gl: the GL one, or GlError. automatic: GL when a context can be
/// made and the shaders build, else the CPU one; writes one line to `log` saying which and
/// why (nullptr: std::clog). The environment variable CF_GL_DISABLE=1 makes GL unavailable
/// (tests of the fallback; machines where GL misbehaves).
std::unique_ptr<Renderer> make_renderer(RendererKind kind, const Volume& volume, const TransferFunction& tf,
                                        const LabelVolume* mask = nullptr, std::ostream* log = nullptr);

/// The same as a factory for RegistrationParams::renderer_factory.
using RendererFactory =
    std::function<std::unique_ptr<Renderer>(const Volume&, const TransferFunction&, const LabelVolume*)>;
RendererFactory renderer_factory(RendererKind kind, std::ostream* log = nullptr);

}  // namespace cf
