// Errors and the automatic fallback: no EGL (CF_GL_DISABLE), a shader that does not compile or
// does not link (CF_GL_BREAK_SHADER), a volume beyond the GL's 3D texture limit, a GL error, a
// lost context, a bad --renderer value.
#include <epoxy/egl.h>
#include <epoxy/gl.h>

#include <algorithm>
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

TEST(GlFallback, ShaderLinkErrorComesWithTheLogAndFallsBackToCpu) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(32);
    const auto tf = preset_transfer_function("cortex_t1");
    ScopedEnv env("CF_GL_BREAK_SHADER", "link");
    try {
        make_gl_renderer(v, tf);
        FAIL() << "a program without a fragment main was accepted";
    } catch (const GlError& e) {
        const std::string m = e.what();
        EXPECT_NE(m.find("does not link"), std::string::npos) << m;
        EXPECT_NE(m.find("raycast"), std::string::npos) << "names the program: " << m;
        EXPECT_GT(m.size(), m.find("does not link: ") + 16) << "carries the driver's link log: " << m;
    }
    std::ostringstream log;
    auto r = make_renderer(RendererKind::automatic, v, tf, nullptr, &log);
    EXPECT_STREQ(r->name(), "cpu");
    EXPECT_NE(log.str().find("does not link"), std::string::npos) << log.str();
}

TEST(GlFallback, VolumeBeyondTheTextureLimitIsNamedAndAutoFallsBackToCpu) {
    CF_REQUIRE_GL();
    // The limit of this GL, read on a renderer's context (it stays current after construction).
    auto probe = make_gl_renderer(sphere_volume(16), preset_transfer_function("cortex_t1"));
    GLint limit = 0;
    glGetIntegerv(GL_MAX_3D_TEXTURE_SIZE, &limit);
    ASSERT_GT(limit, 16);
    probe.reset();
    // A thin volume, one voxel longer than the limit along k: small in memory, too long for GL.
    Volume v;
    v.geom.dims = {4, 4, limit + 1};
    v.geom.spacing_mm = Eigen::Vector3d(1, 1, 0.1);
    v.voxels.assign(v.geom.voxel_count(), 0.f);
    for (size_t i = 0; i < v.voxels.size(); ++i) v.voxels[i] = float(i % 97);
    const auto tf = preset_transfer_function("cortex_t1");
    try {
        make_gl_renderer(v, tf);
        FAIL() << "a volume beyond GL_MAX_3D_TEXTURE_SIZE was accepted";
    } catch (const GlError& e) {
        const std::string m = e.what();
        EXPECT_NE(m.find("GL_MAX_3D_TEXTURE_SIZE " + std::to_string(limit)), std::string::npos) << m;
        EXPECT_NE(m.find("4x4x" + std::to_string(limit + 1)), std::string::npos) << "names the volume's size: " << m;
    }
    std::ostringstream log;
    auto r = make_renderer(RendererKind::automatic, v, tf, nullptr, &log);
    EXPECT_STREQ(r->name(), "cpu");
    EXPECT_NE(log.str().find("renderer: cpu"), std::string::npos) << log.str();
    EXPECT_NE(log.str().find("GL_MAX_3D_TEXTURE_SIZE"), std::string::npos) << "the log line says why: " << log.str();
}

TEST(GlFallback, AGlErrorIsNamedWithItsStageAndTheRendererGoesOn) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(32);
    auto r = make_gl_renderer(v, preset_transfer_function("cortex_t1"));
    const Pose T = look_at(v.geom.center_world_mm(), Eigen::Vector3d(0, 0, 1), 200);
    RenderImage before, after;
    r->render(small_camera(), T, RenderOptions{}, before);
    // A GL error on the renderer's context (still current): binding a name that was never made
    // is GL_INVALID_OPERATION in a core profile. The next check names it and the stage.
    glBindTexture(GL_TEXTURE_3D, 0x7ffffff0u);
    RenderImage img;
    try {
        r->render(small_camera(), T, RenderOptions{}, img);
        FAIL() << "a pending GL error went unreported";
    } catch (const GlError& e) {
        const std::string m = e.what();
        EXPECT_NE(m.find("GL_INVALID_OPERATION (0x0502)"), std::string::npos) << m;
        EXPECT_NE(m.find(": GL_"), std::string::npos) << "names the stage first: " << m;
    }
    // The error flags were drained: the renderer works again and draws the same picture.
    r->render(small_camera(), T, RenderOptions{}, after);
    EXPECT_EQ(before.rgb, after.rgb);
}

TEST(GlFallback, ALostContextIsNamedAndANewRendererCanBeMade) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(32);
    const auto tf = preset_transfer_function("cortex_t1");
    auto r = make_gl_renderer(v, tf);
    const Pose T = look_at(v.geom.center_world_mm(), Eigen::Vector3d(0, 0, 1), 200);
    RenderImage img;
    r->render(small_camera(), T, RenderOptions{}, img);
    // Take the context away through EGL, as a driver reset or a vanished GPU would: destroyed
    // while current, it goes when released.
    const EGLDisplay dpy = eglGetCurrentDisplay();
    const EGLContext ctx = eglGetCurrentContext();
    ASSERT_NE(ctx, EGL_NO_CONTEXT);
    ASSERT_TRUE(eglDestroyContext(dpy, ctx));
    ASSERT_TRUE(eglMakeCurrent(dpy, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT));
    try {
        r->render(small_camera(), T, RenderOptions{}, img);
        FAIL() << "rendering on a destroyed context went unreported";
    } catch (const GlError& e) {
        const std::string m = e.what();
        EXPECT_NE(m.find("GL context is lost or gone"), std::string::npos) << m;
        EXPECT_NE(m.find("must be made again"), std::string::npos) << "says what to do: " << m;
    }
    r.reset();  // must not touch GL objects of the gone context
    std::ostringstream log;
    auto again = make_renderer(RendererKind::automatic, v, tf, nullptr, &log);
    EXPECT_STREQ(again->name(), "gl") << log.str();
    RenderImage img2;
    again->render(small_camera(), T, RenderOptions{}, img2);
    EXPECT_GT(std::count(img2.coverage.begin(), img2.coverage.end(), uint8_t(1)), 100);
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
