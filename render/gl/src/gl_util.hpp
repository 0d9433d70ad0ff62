#pragma once
// Small GL helpers: programs with their info logs, error checks, owned object names.
#include <epoxy/gl.h>

#include <string>
#include <utility>

namespace cf::gl {

/// Compiles and links; throws GlError with the stage, the name and the info log. `log`
/// receives warnings of a successful build.
GLuint build_program(const std::string& name, const std::string& vertex_source, const std::string& fragment_source,
                     std::string* log = nullptr);
/// Throws GlError naming `where` if glGetError() reports anything, or the context was reset.
void check_gl(const char* where);

/// Owns one GL object name; the deleter runs with the owning context current.
template <void (*Delete)(GLuint)>
class Name {
public:
    Name() = default;
    explicit Name(GLuint id) : id_(id) {}
    Name(Name&& o) noexcept : id_(std::exchange(o.id_, 0)) {}
    Name& operator=(Name&& o) noexcept {
        if (this != &o) {
            reset();
            id_ = std::exchange(o.id_, 0);
        }
        return *this;
    }
    ~Name() { reset(); }
    void reset(GLuint id = 0) {
        if (id_) Delete(id_);
        id_ = id;
    }
    /// Forgets the name without deleting it: for a context that is lost or gone, whose objects
    /// went with it (deleting then would call GL with no context, or the wrong one, current).
    void abandon() { id_ = 0; }
    GLuint get() const { return id_; }
    explicit operator bool() const { return id_ != 0; }

private:
    GLuint id_ = 0;
};

inline void delete_texture(GLuint id) { glDeleteTextures(1, &id); }
inline void delete_framebuffer(GLuint id) { glDeleteFramebuffers(1, &id); }
inline void delete_renderbuffer(GLuint id) { glDeleteRenderbuffers(1, &id); }
inline void delete_buffer(GLuint id) { glDeleteBuffers(1, &id); }
inline void delete_vertex_array(GLuint id) { glDeleteVertexArrays(1, &id); }
inline void delete_program(GLuint id) { glDeleteProgram(id); }
using Texture = Name<delete_texture>;
using Framebuffer = Name<delete_framebuffer>;
using Renderbuffer = Name<delete_renderbuffer>;
using Buffer = Name<delete_buffer>;
using VertexArray = Name<delete_vertex_array>;
using Program = Name<delete_program>;

inline GLuint gen_texture() { GLuint t = 0; glGenTextures(1, &t); return t; }
inline GLuint gen_buffer() { GLuint t = 0; glGenBuffers(1, &t); return t; }
inline GLuint gen_framebuffer() { GLuint t = 0; glGenFramebuffers(1, &t); return t; }
inline GLuint gen_renderbuffer() { GLuint t = 0; glGenRenderbuffers(1, &t); return t; }
inline GLuint gen_vertex_array() { GLuint t = 0; glGenVertexArrays(1, &t); return t; }

}  // namespace cf::gl
