// Views of a stream (request field `stream`, docs/api/render.md): a large view is drawn in bands
// of rows with the very same pixels as whole; a newer view of the same stream makes the render
// thread give the older one up (409 superseded, not counted as a failure), another stream's view
// is drawn; a bad stream is refused naming it. The daemon in-process with the CPU renderer.
// Eigen first: <httplib.h> pulls in <resolv.h>, whose _res macro breaks Eigen's headers.
#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/daemon/daemon.hpp"

#include "daemon_fixture.hpp"
#include "render_module.hpp"

#include <gtest/gtest.h>
#include <httplib.h>

#include <future>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <thread>

using namespace cf;
using namespace cf::daemon_test;
using nlohmann::json;
namespace fs = std::filesystem;

namespace {

json test_config(const fs::path& state) {
    json c = base_test_config(state, "cpu");
    c["tracker"]["enabled"] = false;
    c["camera"]["backend"] = "none";
    return c;
}

SharedDaemon& g_d = add_shared_daemon("cf_daemon_render_stream", test_config);

Reply post(const std::string& path, const json& body) { return g_d.get().post(path, body); }
json renderer_status() { return g_d.get().get("/api/status").j["modules"]["renderer"]; }

/// A view from the left of the MRI's centre, `w` x `h`, focal length fitting the head.
json view(int w, int h, const std::string& v = "left") {
    return {{"width", w}, {"height", h}, {"view", v}, {"focal_px", 0.5 * h * 450 / 95.0}, {"format", "png"}, {"preset", "skin"}};
}

}  // namespace

TEST(RenderStream, ABandedViewHasTheSamePixelsAndDepthAsAWholeOne) {
    wait_for_volume(g_d.get());
    // 400 x 330 = 132000 pixels: more than 2 * kBandPixels, so with a stream it is drawn in bands.
    static_assert(400 * 330 >= 2 * cf::daemon::RenderModule::kBandPixels);
    const auto banded_before = renderer_status()["banded_renders"].get<int>();
    const Reply whole = post("/api/render", view(400, 330));
    EXPECT_EQ(renderer_status()["banded_renders"].get<int>(), banded_before) << "without a stream: drawn whole";
    ASSERT_EQ(whole.status, 200) << whole.body;
    json b = view(400, 330);
    b["stream"] = "test-view-1";
    const Reply banded = post("/api/render", b);
    ASSERT_EQ(banded.status, 200) << banded.body;
    EXPECT_EQ(renderer_status()["banded_renders"].get<int>(), banded_before + 1) << "with a stream: drawn in bands";
    const cv::Mat a = decode(whole), c = decode(banded);
    ASSERT_EQ(a.size(), cv::Size(400, 330));
    ASSERT_EQ(c.size(), a.size());
    EXPECT_EQ(mean_abs_diff(a, c), 0.0);
    cv::Mat grey;
    cv::cvtColor(c, grey, cv::COLOR_BGR2GRAY);
    EXPECT_GT(cv::countNonZero(grey > 30), 400 * 330 / 10) << "the head is drawn";
    // The banded render's depth is kept for picks of that view (the same point as a fresh render).
    json pick = b;
    pick["pixel"] = {200, 165};
    const Reply p1 = post("/api/render/pick", pick);
    ASSERT_EQ(p1.status, 200) << p1.body;
    EXPECT_TRUE(p1.j["reused_render"].get<bool>());
    post("/api/render", view(64, 48, "anterior"));  // another view in between: the pick renders afresh
    const Reply p2 = post("/api/render/pick", pick);
    ASSERT_EQ(p2.status, 200) << p2.body;
    EXPECT_FALSE(p2.j["reused_render"].get<bool>());
    EXPECT_NEAR(p1.j["depth_mm"].get<double>(), p2.j["depth_mm"].get<double>(), 1e-3);
}

TEST(RenderStream, ANewerViewOfTheStreamSupersedesTheOlderOne) {
    wait_for_volume(g_d.get());
    const json before = renderer_status();
    // A slow view (the largest, 0.1 mm steps: about a second or more on the CPU), then a small one
    // of the same stream while it is drawn or still queued: the slow one is given up.
    json slow = view(1280, 1024);
    slow["sample_mm"] = 0.1;
    slow["stream"] = "s1";
    auto fut = std::async(std::launch::async, [&] { return post("/api/render", slow); });
    std::this_thread::sleep_for(std::chrono::milliseconds(60));
    json quick = view(160, 128, "anterior");
    quick["stream"] = "s1";
    const Reply q = post("/api/render", quick);
    const Reply s = fut.get();
    EXPECT_EQ(q.status, 200) << q.body;
    EXPECT_EQ(decode(q).size(), cv::Size(160, 128));
    ASSERT_EQ(s.status, 409) << s.body.substr(0, 300);
    EXPECT_EQ(s.j["error"]["code"], "superseded") << s.body;
    EXPECT_NE(s.body.find("stream 's1'"), std::string::npos) << s.body;
    const json after = renderer_status();
    EXPECT_GE(after["superseded"].get<int>(), before["superseded"].get<int>() + 1);
    EXPECT_EQ(after["failures"], before["failures"]) << "a view given up is no failure";

    // Another stream's view, or one without a stream, is drawn, not given up.
    json other = view(480, 400);
    other["stream"] = "s2";
    auto fut2 = std::async(std::launch::async, [&] { return post("/api/render", other); });
    std::this_thread::sleep_for(std::chrono::milliseconds(50));
    json third = view(96, 80);
    third["stream"] = "s3";
    const Reply t = post("/api/render", third);
    const Reply o = fut2.get();
    EXPECT_EQ(t.status, 200) << t.body;
    EXPECT_EQ(o.status, 200) << o.body.substr(0, 300);
    EXPECT_EQ(decode(o).size(), cv::Size(480, 400));
}

TEST(RenderStream, ABadStreamIsRefusedNamingIt) {
    wait_for_volume(g_d.get());
    for (const json& bad : {json(""), json(std::string(65, 'a')), json("two words"), json("a/b"), json(7), json(nullptr)}) {
        json b = view(32, 24);
        b["stream"] = bad;
        const Reply r = post("/api/render", b);
        EXPECT_EQ(r.status, 400) << bad.dump() << " " << r.body;
        EXPECT_NE(r.body.find("render stream"), std::string::npos) << r.body;
    }
    json ok = view(32, 24);
    ok["stream"] = std::string("case-view_1.a:") + std::string(50, 'z');
    EXPECT_EQ(post("/api/render", ok).status, 200);
}

// A GL failure mid-run (the context lost at the renderer's second frame, injected through EGL
// by CF_GL_LOSE_CONTEXT_AT_FRAME): that request gets 503 naming the lost context, the render
// module drops its GL renderers, and the next request is drawn by a new renderer with the same
// picture as before the loss. A daemon of its own with renderer.kind gl; skipped without GL.
TEST(RenderStream, ALostGlContextFailsOneRequestNamingItAndTheNextIsDrawnAfresh) {
    setenv("CF_GL_LOSE_CONTEXT_AT_FRAME", "2", 1);
    struct Unset {
        ~Unset() { unsetenv("CF_GL_LOSE_CONTEXT_AT_FRAME"); }
    } unset;
    const fs::path state = fs::temp_directory_path() / ("cf_daemon_gl_loss_" + std::to_string(::getpid()));
    fs::remove_all(state);
    {
        json c = base_test_config(state, "gl");
        c["tracker"]["enabled"] = false;
        c["camera"]["backend"] = "none";
        TestDaemon d(state, c);
        wait_for_volume(d);
        const json v = view(96, 72);
        const Reply first = d.post("/api/render", v);
        if (first.status == 503 && first.body.find("GL") != std::string::npos && d.get("/api/status").j["modules"]["renderer"]["renders"] == 0)
            GTEST_SKIP() << "no GL here: " << first.body;
        ASSERT_EQ(first.status, 200) << first.body;
        const Reply lost = d.post("/api/render", v);
        EXPECT_EQ(lost.status, 503) << lost.body;
        EXPECT_NE(lost.body.find("GL context is lost or gone"), std::string::npos) << lost.body;
        EXPECT_NE(lost.body.find("the next request makes a new renderer"), std::string::npos) << lost.body;
        const json st = d.get("/api/status").j["modules"]["renderer"];
        EXPECT_EQ(st["gl_failures"], 1) << st.dump();
        EXPECT_NE(st["backend_reason"].get<std::string>().find("lost or gone"), std::string::npos) << st.dump();
        const Reply again = d.post("/api/render", v);
        ASSERT_EQ(again.status, 200) << again.body;
        EXPECT_EQ(mean_abs_diff(decode(first), decode(again)), 0.0) << "a new GL renderer draws the same picture";
        EXPECT_EQ(d.get("/api/status").j["modules"]["renderer"]["backend"], "gl");
    }
    fs::remove_all(state);
}
