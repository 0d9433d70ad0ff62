// Errors and the automatic fallback: no EGL (CF_GL_DISABLE), a shader that does not compile
// (CF_GL_BREAK_SHADER), a bad --renderer value.
#include <cstdlib>
#include <sstream>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/render/renderer_factory.hpp"
#include "test_gl_common.hpp"

namespace cf::test {
namespace {

struct ScopedEnv {
    std::string name;
    ScopedEnv(const char* n, const char* v) : name(n) { setenv(n, v, 1); }
    ~ScopedEnv() { unsetenv(name.c_str()); }
};

TEST(GlFallback, ParseRendererKind) {
    EXPECT_EQ(parse_renderer_kind("cpu"), RendererKind::cpu);
    EXPECT_EQ(parse_renderer_kind("gl"), RendererKind::gl);
    EXPECT_EQ(parse_renderer_kind("auto"), RendererKind::automatic);
    try {
        parse_renderer_kind("vulkan");
        FAIL();
    } catch (const InputError& e) {
        EXPECT_NE(std::string(e.what()).find("--renderer"), std::string::npos) << e.what();
        EXPECT_NE(std::string(e.what()).find("vulkan"), std::string::npos) << e.what();
    }
}

TEST(GlFallback, NoEglFallsBackToCpu) {
    const Volume v = sphere_volume(32);
    const auto tf = preset_transfer_function("cortex_t1");
    ScopedEnv env("CF_GL_DISABLE", "1");
    EXPECT_THROW(probe_gl(), GlError);
    EXPECT_THROW(make_gl_renderer(v, tf), GlError);
    EXPECT_THROW(make_renderer(RendererKind::gl, v, tf), GlError);
    std::ostringstream log;
    auto r = make_renderer(RendererKind::automatic, v, tf, nullptr, &log);
    EXPECT_STREQ(r->name(), "cpu");
    EXPECT_NE(log.str().find("renderer: cpu"), std::string::npos) << log.str();
    EXPECT_NE(log.str().find("CF_GL_DISABLE"), std::string::npos) << "the log line says why: " << log.str();
    const std::string line = log.str();
    EXPECT_EQ(std::count(line.begin(), line.end(), '\n'), 1) << "one line: " << line;
}

TEST(GlFallback, ShaderCompileErrorFallsBackToCpu) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(32);
    const auto tf = preset_transfer_function("cortex_t1");
    ScopedEnv env("CF_GL_BREAK_SHADER", "1");
    try {
        make_gl_renderer(v, tf);
        FAIL() << "the broken shader was accepted";
    } catch (const GlError& e) {
        EXPECT_NE(std::string(e.what()).find("does not compile"), std::string::npos) << e.what();
    }
    std::ostringstream log;
    auto r = make_renderer(RendererKind::automatic, v, tf, nullptr, &log);
    EXPECT_STREQ(r->name(), "cpu");
    EXPECT_NE(log.str().find("does not compile"), std::string::npos) << log.str();
}

TEST(GlFallback, AutoChoosesGlWhenAvailable) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(32);
    std::ostringstream log;
    auto r = make_renderer(RendererKind::automatic, v, preset_transfer_function("cortex_t1"), nullptr, &log);
    EXPECT_STREQ(r->name(), "gl");
    EXPECT_NE(log.str().find("renderer: gl"), std::string::npos) << log.str();
}

TEST(GlFallback, BadInputsNameTheProblem) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(32);
    auto r = make_gl_renderer(v, preset_transfer_function("cortex_t1"));
    LabelVolume other;
    other.geom = v.geom;
    other.geom.dims[0] += 1;
    other.voxels.assign(other.geom.voxel_count(), 1);
    EXPECT_THROW(make_gl_renderer(v, preset_transfer_function("cortex_t1"), &other), InputError);
    EXPECT_THROW(r->set_layer_settings(3, LayerSettings{}), InputError);
    LayerSettings s;
    s.weight = 1.5;
    EXPECT_THROW(r->set_layer_settings(0, s), InputError);
    RenderImage img;
    RenderOptions opt;
    opt.sample_distance_mm = 0;
    EXPECT_THROW(r->render(small_camera(), Pose::Identity(), opt, img), InputError);
    for (int i = 1; i < FusionRenderer::kMaxLayers; ++i) r->add_layer(v, preset_transfer_function("skin"));
    EXPECT_THROW(r->add_layer(v, preset_transfer_function("skin")), InputError);
    OpaqueMesh m;
    m.p_world_mm = {{0, 0, 0}, {1, 0, 0}};
    m.triangles = {0, 1, 2};
    EXPECT_THROW(r->set_mesh(&m), InputError);
}

}  // namespace
}  // namespace cf::test
