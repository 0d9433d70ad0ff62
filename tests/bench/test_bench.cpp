// The benchmark library and `cortexfuse bench`: output keys, units and error paths.
// Functional only: nothing here asserts a timing.
#include <gtest/gtest.h>
#include <sys/wait.h>

#include <array>
#include <cstdio>
#include <filesystem>
#include <nlohmann/json.hpp>
#include <string>

#include "cortexfuse/bench/bench.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/registration.hpp"
#include "cortexfuse/render/gl_renderer.hpp"

namespace fs = std::filesystem;
using nlohmann::json;

namespace {

struct CmdResult {
    int rc = -1;
    std::string out;
};

// Runs a shell command, returns its exit code and stdout (stderr merged when asked).
CmdResult run_cmd(const std::string& cmd) {
    CmdResult r;
    FILE* p = popen(cmd.c_str(), "r");
    if (!p) return r;
    std::array<char, 4096> buf{};
    size_t n = 0;
    while ((n = fread(buf.data(), 1, buf.size(), p)) > 0) r.out.append(buf.data(), n);
    const int st = pclose(p);
    r.rc = WIFEXITED(st) ? WEXITSTATUS(st) : -1;
    return r;
}

// A small synthetic head: a bright ball in a dark box, on an oblique grid.
fs::path write_ball_volume(const fs::path& dir) {
    cf::Volume v;
    v.geom.dims = {48, 40, 36};
    v.geom.spacing_mm = {4.0, 4.5, 5.0};
    v.geom.origin_mm = {-90, -80, -85};
    v.voxels.resize(v.geom.voxel_count());
    const Eigen::Vector3d c(23.5, 19.5, 17.5);
    for (int k = 0; k < 36; ++k)
        for (int j = 0; j < 40; ++j)
            for (int i = 0; i < 48; ++i) {
                const Eigen::Vector3d d = (Eigen::Vector3d(i, j, k) - c).cwiseProduct(v.geom.spacing_mm);
                v.voxels[v.geom.linear(i, j, k)] = d.norm() < 70 ? 200.f + float(i % 7) : 5.f;
            }
    const fs::path p = dir / "ball.nii.gz";
    cf::save_volume(v, p);
    return p;
}

class BenchTest : public ::testing::Test {
protected:
    void SetUp() override {
        dir_ = fs::temp_directory_path() / ("cf_bench_test_" + std::to_string(::getpid()));
        fs::create_directories(dir_);
    }
    void TearDown() override { fs::remove_all(dir_); }
    fs::path dir_;
};

}  // namespace

TEST(BenchStats, MedianAndPercentiles) {
    const auto s = cf::bench::stats({5, 1, 4, 2, 3});
    EXPECT_DOUBLE_EQ(s.median, 3);
    EXPECT_DOUBLE_EQ(s.min, 1);
    EXPECT_DOUBLE_EQ(s.max, 5);
    EXPECT_DOUBLE_EQ(s.mean, 3);
    EXPECT_DOUBLE_EQ(s.p90, 4.6);  // linear between order statistics
    EXPECT_DOUBLE_EQ(cf::bench::stats({1, 2, 3, 4}).median, 2.5);
    EXPECT_EQ(cf::bench::stats({}).n, 0u);
}

TEST(BenchStats, PeakRssIsPlausible) {
    const double mb = cf::bench::peak_rss_mb();
    EXPECT_GT(mb, 1.0);
    EXPECT_LT(mb, 1e6);
}

TEST(BenchArgs, SizeParsing) {
    EXPECT_EQ(cf::bench::parse_size("375x250"), std::make_pair(375, 250));
    EXPECT_EQ(cf::bench::parse_size("1280X800"), std::make_pair(1280, 800));
    for (const char* bad : {"375", "375x", "x250", "375x250x3", "4x4", "375*250", "99999x10", "-5x10"})
        EXPECT_THROW(cf::bench::parse_size(bad), cf::InputError) << bad;
}

TEST(BenchArgs, UnknownRendererNamed) {
    try {
        cf::bench::check_renderer_name("vulkan");
        FAIL() << "no error";
    } catch (const cf::InputError& e) {
        EXPECT_NE(std::string(e.what()).find("--renderer vulkan"), std::string::npos) << e.what();
        EXPECT_NE(std::string(e.what()).find("cpu"), std::string::npos) << e.what();
    }
    EXPECT_NO_THROW(cf::bench::check_renderer_name("cpu"));
}

TEST(BenchCamera, SmallSmoothSteps) {
    cf::VolumeGeometry g;
    g.dims = {256, 256, 256};
    const Eigen::Vector3d c = g.center_world_mm();
    for (int i = 0; i < 60; ++i) {
        const auto d = cf::pose_delta(cf::bench::bench_pose(g, i), cf::bench::bench_pose(g, i + 1), c);
        EXPECT_GT(d.angle_deg + d.translation_mm, 1e-3) << "frame " << i << " does not move";
        EXPECT_LT(d.angle_deg, 1.5) << i;
        EXPECT_LT(d.translation_mm, 1.5) << i;
        // Always on the left of the head, looking at it.
        const cf::Pose T = cf::bench::bench_pose(g, i);
        const Eigen::Vector3d p = T.topLeftCorner<3, 3>() * c + T.topRightCorner<3, 1>();
        EXPECT_NEAR(p.z(), cf::bench::kBenchDistanceMm, 10.0);
    }
}

TEST(BenchNmi, KeysAndValues) {
    cf::bench::NmiBenchConfig c;
    c.frames = 3;
    c.repeat = 2;
    c.warmup = 0;
    const json j = cf::bench::run_nmi_bench(c);
    for (const char* k : {"nmi_us_median", "nmi_us_p90", "mi_us_median", "ncc_us_median", "peak_rss_mb"}) {
        ASSERT_TRUE(j.contains(k)) << k;
        EXPECT_GT(j[k].get<double>(), 0.0) << k;
    }
    EXPECT_EQ(j["size"], "375x250");
    EXPECT_EQ(j["bins"], 64);
    // b is a noisy function of a: clearly related, not identical.
    EXPECT_GT(j["nmi_value"].get<double>(), 1.05);
    EXPECT_LT(j["nmi_value"].get<double>(), 2.0);
    EXPECT_GT(j["ncc_value"].get<double>(), 0.5);
    // The OpenCV reference computes the same measure with the same binning.
    EXPECT_NEAR(j["opencv_calchist_nmi_value"].get<double>(), j["nmi_value"].get<double>(), 1e-3);
    EXPECT_GT(j["opencv_calchist_nmi_us_median"].get<double>(), 0.0);
    c.bins = 1;
    EXPECT_THROW(cf::bench::run_nmi_bench(c), cf::InputError);
}

TEST_F(BenchTest, RenderKeysFrameAndErrors) {
    cf::bench::RenderBenchConfig c;
    c.volume = write_ball_volume(dir_);
    c.width = 64;
    c.height = 48;
    c.frames = 2;
    c.warmup = 1;
    c.threads = 1;
    c.save_frame = dir_ / "frame.png";
    const json j = cf::bench::run_render_bench(c);
    for (const char* k : {"ms_per_frame_median", "ms_per_frame_p90", "peak_rss_mb", "prepare_ms"}) {
        ASSERT_TRUE(j.contains(k)) << k;
        EXPECT_GT(j[k].get<double>(), 0.0) << k;
    }
    EXPECT_EQ(j["renderer"], "cpu");
    EXPECT_EQ(j["size"], "64x48");
    EXPECT_EQ(j["threads"], 1);
    EXPECT_EQ(j["frames"], 2);
    // The ball fills the middle of the view.
    EXPECT_GT(j["coverage_fraction"].get<double>(), 0.1);
    EXPECT_LT(j["coverage_fraction"].get<double>(), 0.95);
    EXPECT_TRUE(fs::exists(c.save_frame));
    // Deterministic: the same frames again give the same checksum, whatever the thread count.
    ASSERT_EQ(j["output_checksum"].get<std::string>().size(), 16u);
    auto again = c;
    again.threads = 2;
    again.save_frame.clear();
    EXPECT_EQ(cf::bench::run_render_bench(again)["output_checksum"], j["output_checksum"]);

    auto bad = c;
    bad.renderer = "vulkan";
    EXPECT_THROW(cf::bench::run_render_bench(bad), cf::InputError);
    bad = c;
    bad.frames = 0;
    EXPECT_THROW(cf::bench::run_render_bench(bad), cf::InputError);
    bad = c;
    bad.tf = "no_such_preset";
    EXPECT_THROW(cf::bench::run_render_bench(bad), cf::InputError);
    bad = c;
    bad.tf = (dir_ / "missing_tf.json").string();
    EXPECT_THROW(cf::bench::run_render_bench(bad), cf::InputError);
    bad = c;
    bad.volume = dir_ / "missing.nii.gz";
    EXPECT_THROW(cf::bench::run_render_bench(bad), cf::InputError);
}

TEST(BenchRegister, TimesAScheduleBesideAReferenceOnTheSameCases) {
    // Two tiny schedules that differ in their evaluation budget, on one generated phantom.
    auto tiny = [](int evals) {
        cf::RegistrationParams p = cf::RegistrationParams::defaults();
        p.starts.resize(1);
        p.estimate_light = false;
        p.light_rounds = 1;
        p.search_keep = 0;
        p.search_stages = {{"search", 4, 2, 2, 64, evals, 0.01, 0.01}};
        p.final_stages = {{"final", 2, 1, 1, 96, evals, 0.01, 0.01}};
        p.refine_stages.clear();
        p.depth_scan_mm = 0;  // its renders come on top of the stages' budgets
        return p;
    };
    cf::bench::RegisterBenchConfig c;
    c.volume = fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz";
    c.mask = fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz";
    c.cases = 1;
    c.params = tiny(10);
    c.reference = tiny(20);
    c.reference_name = "bigger";
    const json j = cf::bench::run_register_bench(c);
    ASSERT_TRUE(j.contains("reference"));
    EXPECT_EQ(j["reference"]["name"], "bigger");
    for (const json* v : {&j, &j["reference"]}) {
        EXPECT_GT((*v)["seconds_median"].get<double>(), 0.0);
        EXPECT_EQ((*v)["per_case"].size(), 1u);
        EXPECT_TRUE((*v)["per_case"][0].contains("mre_mm"));  // generated cases carry their truth
    }
    // Each schedule ran its own budget (the simplex may stop early, never late).
    EXPECT_LE(j["evaluations_median"].get<double>(), 2 * 10 + 2);
    EXPECT_GT(j["reference"]["evaluations_median"].get<double>(), j["evaluations_median"].get<double>());
    EXPECT_GT(j["reference_over_params_seconds"].get<double>(), 0.0);
}

TEST(BenchRegister, TheGlRegistrationBesideTheCpuOneOnTheSameCases) {
    // Issue 3's registration time: one schedule with the GL ray caster and again with the CPU's,
    // case by case in turn; each side names the renderer its engine made.
    cf::RegistrationParams p = cf::RegistrationParams::defaults();
    p.starts.resize(1);
    p.estimate_light = false;
    p.search_keep = 0;
    p.search_stages = {{"search", 4, 2, 2, 64, 8, 0.01, 0.01}};
    p.final_stages = {{"final", 2, 1, 1, 96, 8, 0.01, 0.01}};
    p.refine_stages.clear();
    cf::bench::RegisterBenchConfig c;
    c.volume = fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz";
    c.mask = fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz";
    c.cases = 1;
    c.params = p;
    c.renderer = "gl";
    c.reference_renderer = "cpu";
    json j;
    try {
        j = cf::bench::run_register_bench(c);
    } catch (const cf::GlError& e) {
        GTEST_SKIP() << "no OpenGL context here: " << e.what();
    }
    EXPECT_EQ(j["renderer"], "gl");
    ASSERT_TRUE(j.contains("reference"));
    EXPECT_EQ(j["reference"]["renderer"], "cpu");
    EXPECT_EQ(j["reference"]["name"], "renderer cpu");
    // The same pictures (issue 3's golden tests), so the same schedule lands close by.
    EXPECT_NEAR(j["mre_mm_median"].get<double>(), j["reference"]["mre_mm_median"].get<double>(), 0.5);
    c.reference_renderer = "vulkan";
    EXPECT_THROW(cf::bench::run_register_bench(c), cf::InputError);
}

TEST(BenchCli, NmiJsonParses) {
    const CmdResult r = run_cmd(std::string(CF_CLI_EXE) + " bench nmi --frames 3 --repeat 2 --json");
    ASSERT_EQ(r.rc, 0) << r.out;
    const json j = json::parse(r.out);  // exactly one JSON object on stdout
    ASSERT_TRUE(j.is_object());
    for (const char* k : {"nmi_us_median", "mi_us_median", "ncc_us_median", "frames", "size", "bins", "peak_rss_mb"})
        EXPECT_TRUE(j.contains(k)) << k;
    EXPECT_EQ(j["frames"], 3);
}

TEST(BenchCli, BadInputOneLineNonZero) {
    for (const std::string args : {"bench render --renderer vulkan --json", "bench render --size 12 --json",
                                   "bench render --volume /nonexistent/v.nii.gz --json", "bench nmi --bins 0 --json",
                                   "bench register --case-dir /nonexistent --json"}) {
        const CmdResult r = run_cmd(std::string(CF_CLI_EXE) + " " + args + " 2>&1");
        EXPECT_EQ(r.rc, 1) << args << ": " << r.out;
        EXPECT_NE(r.out.find("error:"), std::string::npos) << args << ": " << r.out;
        EXPECT_EQ(std::count(r.out.begin(), r.out.end(), '\n'), 1) << args << ": " << r.out;
    }
}
