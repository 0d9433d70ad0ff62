#include "gl_util.hpp"

#include <cstring>
#include <vector>

#include "cortexfuse/render/gl_renderer.hpp"
#include "shader_sources.hpp"

namespace cf::gl {
namespace {

std::string info_log(GLuint obj, bool program) {
    GLint len = 0;
    if (program) glGetProgramiv(obj, GL_INFO_LOG_LENGTH, &len);
    else glGetShaderiv(obj, GL_INFO_LOG_LENGTH, &len);
    if (len <= 1) return {};
    std::string s(size_t(len), '\0');
    if (program) glGetProgramInfoLog(obj, len, nullptr, s.data());
    else glGetShaderInfoLog(obj, len, nullptr, s.data());
    while (!s.empty() && (s.back() == '\0' || s.back() == '\n')) s.pop_back();
    return s;
}

GLuint compile(GLenum stage, const std::string& name, const std::string& src, std::string* log) {
    const GLuint sh = glCreateShader(stage);
    const char* p = src.c_str();
    glShaderSource(sh, 1, &p, nullptr);
    glCompileShader(sh);
    GLint ok = 0;
    glGetShaderiv(sh, GL_COMPILE_STATUS, &ok);
    const std::string l = info_log(sh, false);
    if (!ok) {
        glDeleteShader(sh);
        throw GlError(std::string(stage == GL_VERTEX_SHADER ? "vertex" : "fragment") + " shader of " + name +
                      " does not compile: " + l);
    }
    if (log && !l.empty()) *log += l + "\n";
    return sh;
}

}  // namespace

GLuint build_program(const std::string& name, const std::string& vs, const std::string& fs, std::string* log) {
    const GLuint v = compile(GL_VERTEX_SHADER, name, vs, log);
    GLuint f = 0;
    try {
        f = compile(GL_FRAGMENT_SHADER, name, fs, log);
    } catch (...) {
        glDeleteShader(v);
        throw;
    }
    const GLuint prog = glCreateProgram();
    glAttachShader(prog, v);
    glAttachShader(prog, f);
    glLinkProgram(prog);
    glDeleteShader(v);
    glDeleteShader(f);
    GLint ok = 0;
    glGetProgramiv(prog, GL_LINK_STATUS, &ok);
    const std::string l = info_log(prog, true);
    if (!ok) {
        glDeleteProgram(prog);
        throw GlError("program " + name + " does not link: " + l);
    }
    if (log && !l.empty()) *log += l + "\n";
    return prog;
}

void check_gl(const char* where) {
    if (const GLenum r = glGetGraphicsResetStatus(); r != GL_NO_ERROR)
        throw GlError(std::string(where) + ": the GL context was lost (" +
                      (r == GL_GUILTY_CONTEXT_RESET ? "GL_GUILTY_CONTEXT_RESET" : r == GL_INNOCENT_CONTEXT_RESET ? "GL_INNOCENT_CONTEXT_RESET" : "GL_UNKNOWN_CONTEXT_RESET") +
                      "); the GL renderer must be made again");
    const GLenum e = glGetError();
    if (e == GL_NO_ERROR) return;
    const char* n = e == GL_INVALID_ENUM ? "GL_INVALID_ENUM"
                    : e == GL_INVALID_VALUE ? "GL_INVALID_VALUE"
                    : e == GL_INVALID_OPERATION ? "GL_INVALID_OPERATION"
                    : e == GL_INVALID_FRAMEBUFFER_OPERATION ? "GL_INVALID_FRAMEBUFFER_OPERATION"
                    : e == GL_OUT_OF_MEMORY ? "GL_OUT_OF_MEMORY"
                    : "GL error";
    while (glGetError() != GL_NO_ERROR) {
    }
    throw GlError(std::string(where) + ": " + n + " (0x" + [&] {
        char b[16];
        std::snprintf(b, sizeof b, "%04x", unsigned(e));
        return std::string(b);
    }() + ")");
}

const char* shader_source(const std::string& name) {
    for (const auto& s : shader_sources())
        if (name == s.name) return s.text;
    throw GlError("no embedded shader " + name);
}

}  // namespace cf::gl
