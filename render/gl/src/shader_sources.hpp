#pragma once
// The GLSL sources of shaders/, embedded at build time (see cmake/embed_shaders.cmake).
#include <string>
#include <vector>

namespace cf::gl {

struct ShaderSource {
    const char* name;  // file name, e.g. "raycast.frag"
    const char* text;
};
const std::vector<ShaderSource>& shader_sources();
/// The text of one embedded shader; throws GlError if there is none of that name.
const char* shader_source(const std::string& name);

}  // namespace cf::gl
