// The EGL platforms (issue 3: the device platform on an NVIDIA GPU, Mesa's surfaceless platform
// on a CPU-only machine): CF_GL_PLATFORM holds the context to one, so each platform this
// machine has is made and draws the CPU's picture; an unknown name is refused naming it.
#include <cstdlib>
#include <iostream>
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

TEST(GlPlatform, EachHeadlessPlatformHereDrawsTheCpusPicture) {
    CF_REQUIRE_GL();
    const Volume v = sphere_volume(48);
    const auto tf = preset_transfer_function("cortex_t1");
    const Intrinsics K = small_camera();
    RenderOptions opt;
    RenderImage cpu_img;
    make_cpu_renderer(v, tf)->render(K, look_at(v.geom.center_world_mm(), {0.3, 0.2, 1}, 250), opt, cpu_img);
    int made = 0;
    for (const char* platform : {"device", "surfaceless"}) {
        SCOPED_TRACE(platform);
        ScopedEnv env("CF_GL_PLATFORM", platform);
        GlInfo info;
        try {
            info = probe_gl();
        } catch (const GlError& e) {
            // Not every machine has both (an NVIDIA driver without Mesa has no surfaceless
            // display); the refusal must still name the platform.
            std::cout << platform << ": not here: " << e.what() << "\n";
            EXPECT_NE(std::string(e.what()).find(platform), std::string::npos) << e.what();
            continue;
        }
        EXPECT_EQ(info.platform, platform) << "the context must come from the platform asked for";
        RenderImage gl_img;
        make_gl_renderer(v, tf)->render(K, look_at(v.geom.center_world_mm(), {0.3, 0.2, 1}, 250), opt, gl_img);
        const ImageDiff d = compare(cpu_img, gl_img);
        std::cout << platform << " (" << info.renderer << "): " << d << "\n";
        for (int c = 0; c < 3; ++c) EXPECT_LE(d.mean_abs_rgb[c], 2.0) << "channel " << c;
        EXPECT_GE(d.coverage_agreement, 0.995);
        ++made;
    }
    EXPECT_GE(made, 1) << "a context was made without CF_GL_PLATFORM, so one of the platforms must give one";
}

TEST(GlPlatform, AnUnknownPlatformIsRefusedNamingItAndAutoFallsBack) {
    ScopedEnv env("CF_GL_PLATFORM", "x11");
    try {
        probe_gl();
        FAIL() << "CF_GL_PLATFORM=x11 was accepted";
    } catch (const GlError& e) {
        EXPECT_NE(std::string(e.what()).find("CF_GL_PLATFORM=x11"), std::string::npos) << e.what();
        EXPECT_NE(std::string(e.what()).find("surfaceless"), std::string::npos) << "says what is allowed: " << e.what();
    }
    const Volume v = sphere_volume(32);
    std::ostringstream log;
    auto r = make_renderer(RendererKind::automatic, v, preset_transfer_function("cortex_t1"), nullptr, &log);
    EXPECT_STREQ(r->name(), "cpu");
    EXPECT_NE(log.str().find("CF_GL_PLATFORM=x11"), std::string::npos) << "the fallback line says why: " << log.str();
}

}  // namespace
}  // namespace cf::test
