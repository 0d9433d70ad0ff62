// Every embedded shader compiles and links (the info log is printed), and a broken one
// fails with its log in the error.
#include <cstring>
#include <map>

#include "test_gl_common.hpp"

namespace cf::test {
namespace {

std::string source(const std::string& name) {
    for (const auto& s : embedded_shaders())
        if (name == s.name) return s.text;
    ADD_FAILURE() << "no embedded shader " << name;
    return {};
}

std::string with_define(std::string src, const std::string& def) {
    src.insert(src.find('\n') + 1, def + "\n");
    return src;
}

TEST(GlShaders, EmbeddedAtBuildTime) {
    std::map<std::string, size_t> names;
    for (const auto& s : embedded_shaders()) names[s.name] = std::strlen(s.text);
    for (const char* n : {"raycast.vert", "raycast.frag", "mesh.vert", "mesh.frag"}) {
        ASSERT_TRUE(names.count(n)) << n;
        EXPECT_GT(names[n], 50u) << n;
    }
    EXPECT_EQ(source("raycast.frag").rfind("#version 450 core", 0), 0u);
}

TEST(GlShaders, CompileAndLink) {
    CF_REQUIRE_GL();
    for (int layers = 1; layers <= FusionRenderer::kMaxLayers; ++layers) {
        const std::string log = check_gl_program(source("raycast.vert"),
                                                 with_define(source("raycast.frag"), "#define NLAYERS " + std::to_string(layers)));
        std::cout << "raycast, " << layers << " layer(s): " << (log.empty() ? "no warnings" : log) << "\n";
    }
    const std::string log = check_gl_program(source("mesh.vert"), source("mesh.frag"));
    std::cout << "mesh: " << (log.empty() ? "no warnings" : log) << "\n";
}

TEST(GlShaders, CompileErrorCarriesTheInfoLog) {
    CF_REQUIRE_GL();
    try {
        check_gl_program(source("raycast.vert"), "#version 450 core\nout vec4 c;\nvoid main() { c = undefined_thing; }\n");
        FAIL() << "a broken shader compiled";
    } catch (const GlError& e) {
        const std::string m = e.what();
        EXPECT_NE(m.find("fragment shader"), std::string::npos) << m;
        EXPECT_NE(m.find("does not compile"), std::string::npos) << m;
        EXPECT_NE(m.find("undefined_thing"), std::string::npos) << "the info log names the culprit: " << m;
    }
    // Link error: the fragment shader reads a varying the vertex shader does not write.
    try {
        check_gl_program("#version 450 core\nvoid main() { gl_Position = vec4(0); }\n",
                         "#version 450 core\nin vec3 v_missing;\nout vec4 c;\nvoid main() { c = vec4(v_missing, 1); }\n");
        FAIL() << "a mismatched program linked";
    } catch (const GlError& e) {
        EXPECT_NE(std::string(e.what()).find("does not link"), std::string::npos) << e.what();
    }
}

}  // namespace
}  // namespace cf::test
