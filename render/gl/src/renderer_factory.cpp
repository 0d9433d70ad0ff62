#include "cortexfuse/render/renderer_factory.hpp"

#include <iostream>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/render/gl_renderer.hpp"

namespace cf {

RendererKind parse_renderer_kind(const std::string& s, const std::string& context) {
    if (s == "cpu") return RendererKind::cpu;
    if (s == "gl") return RendererKind::gl;
    if (s == "auto") return RendererKind::automatic;
    throw InputError(context, "unknown renderer \"" + s + "\" (expected cpu, gl or auto)");
}

const char* to_string(RendererKind k) {
    switch (k) {
    case RendererKind::cpu: return "cpu";
    case RendererKind::gl: return "gl";
    case RendererKind::automatic: return "auto";
    }
    return "?";
}

std::unique_ptr<Renderer> make_renderer(RendererKind kind, const Volume& volume, const TransferFunction& tf,
                                        const LabelVolume* mask, std::ostream* log) {
    std::ostream& out = log ? *log : std::clog;
    switch (kind) {
    case RendererKind::cpu: return make_cpu_renderer(volume, tf, mask);
    case RendererKind::gl: return make_gl_renderer(volume, tf, mask);
    case RendererKind::automatic:
        try {
            GlInfo info;
            auto r = make_gl_fusion_renderer(&info);
            r->add_layer(volume, tf, mask);
            out << "renderer: gl (" << info.renderer << ", EGL " << info.platform << " platform)\n";
            return r;
        } catch (const GlError& e) {
            out << "renderer: cpu (GL unavailable: " << e.what() << ")\n";
            return make_cpu_renderer(volume, tf, mask);
        }
    }
    throw InputError("renderer", "unknown kind");
}

RendererFactory renderer_factory(RendererKind kind, std::ostream* log) {
    return [kind, log](const Volume& v, const TransferFunction& tf, const LabelVolume* mask) {
        return make_renderer(kind, v, tf, mask, log);
    };
}

}  // namespace cf
