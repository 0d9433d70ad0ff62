// The CPU baseline check of cortexfused and cortexfuse (core/include/cortexfuse/core/cpu_baseline.hpp,
// issue 6's package): the refusal line for a CPU that lacks features, its exit status, and this
// build's own feature list against the CPU that runs the test.
#include <gtest/gtest.h>

#include <cstring>
#include <string>

#include "cortexfuse/core/cpu_baseline.hpp"

namespace {

TEST(CpuBaseline, MessageNamesEveryMissingFeatureOnOneLine) {
    const cf::CpuFeature f[] = {{"sse4.2", true}, {"avx2", false}, {"fma", true}, {"avx512f", false}};
    char buf[512];
    EXPECT_EQ(cf::cpu_baseline_message(f, 4, "cortexfused", buf, sizeof buf), 2u);
    const std::string line(buf);
    EXPECT_EQ(line.rfind("cortexfused: this CPU lacks avx2, avx512f, which this build was compiled for", 0), 0u) << line;
    EXPECT_EQ(line.find("sse4.2"), std::string::npos) << line;
    EXPECT_EQ(line.find("fma"), std::string::npos) << line;
    EXPECT_NE(line.find("docs/packaging.md"), std::string::npos) << line;
    ASSERT_FALSE(line.empty());
    EXPECT_EQ(line.back(), '\n');
    EXPECT_EQ(line.find('\n'), line.size() - 1) << "one line";
}

TEST(CpuBaseline, NothingMissingNothingWritten) {
    const cf::CpuFeature f[] = {{"sse4.2", true}, {"avx2", true}};
    char buf[64];
    std::memset(buf, 'x', sizeof buf);
    EXPECT_EQ(cf::cpu_baseline_message(f, 2, "cortexfuse", buf, sizeof buf), 0u);
    EXPECT_STREQ(buf, "");
    EXPECT_EQ(cf::cpu_baseline_message(f, 0, "cortexfuse", buf, sizeof buf), 0u);
}

TEST(CpuBaseline, MessageIsCutToItsBuffer) {
    const cf::CpuFeature f[] = {{"avx512vp2intersect", false}};
    char buf[16];
    std::memset(buf, 'x', sizeof buf);
    EXPECT_EQ(cf::cpu_baseline_message(f, 1, "cortexfused", buf, sizeof buf), 1u);
    EXPECT_EQ(std::strlen(buf), sizeof buf - 1);
    EXPECT_STREQ(buf, "cortexfused: th");
    EXPECT_EQ(cf::cpu_baseline_message(f, 1, "cortexfused", buf, 0), 0u);  // no room: nothing touched
}

TEST(CpuBaselineDeathTest, ACpuThatLacksAFeatureIsRefusedWithExit69AndTheLine) {
    const cf::CpuFeature f[] = {{"avx2", true}, {"avx512bw", false}};
    EXPECT_EXIT(cf::refuse_if_cpu_lacks(f, 2, "cortexfused"), testing::ExitedWithCode(cf::kCpuBaselineExitCode),
                "^cortexfused: this CPU lacks avx512bw, which this build was compiled for");
}

TEST(CpuBaseline, ACpuThatHasEveryFeatureIsLetThrough) {
    const cf::CpuFeature f[] = {{"avx2", true}};
    cf::refuse_if_cpu_lacks(f, 1, "cortexfused");  // returns; an exit would end the test program
    SUCCEED();
}

// This test program is built with the project's flags (-march=native by default, CF_MARCH for a
// portable build): its list is what the compiler may use, and the CPU running the build's tests
// has all of it.
TEST(CpuBaseline, ThisBuildsFeaturesMatchItsFlagsAndThisCpu) {
    cf::CpuFeature f[cf::kMaxCpuFeatures];
    const std::size_t n = cf::compiled_cpu_features(f);
    ASSERT_LE(n, cf::kMaxCpuFeatures);
    auto listed = [&](const char* name) {
        for (std::size_t i = 0; i < n; ++i)
            if (std::strcmp(f[i].name, name) == 0) return true;
        return false;
    };
#ifdef __SSE4_2__
    EXPECT_TRUE(listed("sse4.2"));
#else
    EXPECT_FALSE(listed("sse4.2"));
#endif
#ifdef __AVX2__
    EXPECT_TRUE(listed("avx2"));
#else
    EXPECT_FALSE(listed("avx2"));
#endif
#ifdef __AVX512F__
    EXPECT_TRUE(listed("avx512f"));
#else
    EXPECT_FALSE(listed("avx512f"));
#endif
    for (std::size_t i = 0; i < n; ++i) EXPECT_TRUE(f[i].supported) << f[i].name << " is used by this build but not on this CPU";
    char buf[512];
    EXPECT_EQ(cf::cpu_baseline_message(f, n, "cf_cpu_baseline_tests", buf, sizeof buf), 0u) << buf;
}

}  // namespace
