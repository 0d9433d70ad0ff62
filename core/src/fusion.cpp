// Checks of the fusion scene's inputs (the renderers live in their backends).
#include "cortexfuse/core/fusion.hpp"

#include <cmath>

#include "cortexfuse/core/error.hpp"

namespace cf {

void OpaqueMesh::validate(const std::string& context) const {
    const size_t n = p_world_mm.size();
    if (triangles.size() % 3 != 0) throw InputError(context, "triangle index count is not a multiple of 3");
    for (uint32_t i : triangles)
        if (i >= n) throw InputError(context, "triangle index " + std::to_string(i) + " out of range (" + std::to_string(n) + " vertices)");
    if (!colour.empty() && colour.size() != n) throw InputError(context, "colour count differs from vertex count");
    for (const auto& p : p_world_mm)
        if (!p.allFinite()) throw InputError(context, "vertex position is not finite");
    if (!texture.empty()) {
        if (texture.type() != CV_8UC3) throw InputError(context, "texture must be 8-bit, 3 channels");
        if (uv.size() != n) throw InputError(context, "texture set but uv count differs from vertex count");
    }
}

}  // namespace cf
