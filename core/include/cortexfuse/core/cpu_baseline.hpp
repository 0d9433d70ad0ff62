#pragma once
// The CPU baseline a binary was built for, checked when it starts (issue 6: a .deb built on one
// machine must not die with SIGILL on a cart with an older CPU).
//
// The features come from the compiler's predefined macros of the translation unit that includes
// this header (-march=native on a developer build, -march=x86-64-v3 for the package: CF_MARCH in
// the top-level CMakeLists.txt, docs/packaging.md); each is looked up at run time with
// __builtin_cpu_supports. CF_CPU_BASELINE_CHECK("program") in an executable's main file defines a
// constructor that runs before the executable's other static constructors and before main: on a
// CPU that lacks a feature it writes one line to stderr naming the features and exits with
// kCpuBaselineExitCode, instead of a SIGILL somewhere later.
//
// Why no standard library here: this code is compiled with the same -march as everything else,
// but must itself run on the older CPU. The functions are marked target("arch=x86-64") (the
// x86-64 baseline) and call nothing compiled with the build's flags: no std::string, no vector;
// only write(2) and _exit(2) from the C library, which is built for the baseline.
// Thread contract: none needed (runs before main, single-threaded); the pure functions are
// reentrant.
#include <unistd.h>

#include <cstddef>

namespace cf {

// Exit status when the CPU lacks a feature the binary was built for (EX_UNAVAILABLE, sysexits.h).
inline constexpr int kCpuBaselineExitCode = 69;

struct CpuFeature {
    const char* name;  // __builtin_cpu_supports's name, e.g. "avx2"
    bool supported;    // on the CPU this runs on
};

// Most features the compiler can use from -march; the binary's own list is those its flags enable.
inline constexpr std::size_t kMaxCpuFeatures = 48;

// Fills out[] with each feature this translation unit was compiled to use and whether the CPU
// running it has it; returns the count (<= kMaxCpuFeatures).
[[gnu::target("arch=x86-64")]] inline std::size_t compiled_cpu_features(CpuFeature* out) {
    std::size_t n = 0;
    (void)out;  // a build for the baseline itself lists nothing
#if defined(__x86_64__) || defined(__i386__)
    __builtin_cpu_init();  // required when called from a constructor
#define CF_CPU_FEATURE(name) out[n++] = CpuFeature{name, __builtin_cpu_supports(name) != 0}
#ifdef __SSE3__
    CF_CPU_FEATURE("sse3");
#endif
#ifdef __SSSE3__
    CF_CPU_FEATURE("ssse3");
#endif
#ifdef __SSE4_1__
    CF_CPU_FEATURE("sse4.1");
#endif
#ifdef __SSE4_2__
    CF_CPU_FEATURE("sse4.2");
#endif
#ifdef __SSE4A__
    CF_CPU_FEATURE("sse4a");
#endif
#ifdef __POPCNT__
    CF_CPU_FEATURE("popcnt");
#endif
#ifdef __AVX__
    CF_CPU_FEATURE("avx");
#endif
#ifdef __AVX2__
    CF_CPU_FEATURE("avx2");
#endif
#ifdef __FMA__
    CF_CPU_FEATURE("fma");
#endif
#ifdef __BMI__
    CF_CPU_FEATURE("bmi");
#endif
#ifdef __BMI2__
    CF_CPU_FEATURE("bmi2");
#endif
#ifdef __F16C__
    CF_CPU_FEATURE("f16c");
#endif
#ifdef __LZCNT__
    CF_CPU_FEATURE("lzcnt");
#endif
#ifdef __MOVBE__
    CF_CPU_FEATURE("movbe");
#endif
#ifdef __XSAVE__
    CF_CPU_FEATURE("xsave");
#endif
#ifdef __AES__
    CF_CPU_FEATURE("aes");
#endif
#ifdef __PCLMUL__
    CF_CPU_FEATURE("pclmul");
#endif
#ifdef __SHA__
    CF_CPU_FEATURE("sha");
#endif
#ifdef __ADX__
    CF_CPU_FEATURE("adx");
#endif
#ifdef __GFNI__
    CF_CPU_FEATURE("gfni");
#endif
#ifdef __VAES__
    CF_CPU_FEATURE("vaes");
#endif
#ifdef __VPCLMULQDQ__
    CF_CPU_FEATURE("vpclmulqdq");
#endif
#ifdef __AVXVNNI__
    CF_CPU_FEATURE("avxvnni");
#endif
#ifdef __AVX512F__
    CF_CPU_FEATURE("avx512f");
#endif
#ifdef __AVX512BW__
    CF_CPU_FEATURE("avx512bw");
#endif
#ifdef __AVX512CD__
    CF_CPU_FEATURE("avx512cd");
#endif
#ifdef __AVX512DQ__
    CF_CPU_FEATURE("avx512dq");
#endif
#ifdef __AVX512VL__
    CF_CPU_FEATURE("avx512vl");
#endif
#ifdef __AVX512IFMA__
    CF_CPU_FEATURE("avx512ifma");
#endif
#ifdef __AVX512VBMI__
    CF_CPU_FEATURE("avx512vbmi");
#endif
#ifdef __AVX512VBMI2__
    CF_CPU_FEATURE("avx512vbmi2");
#endif
#ifdef __AVX512VNNI__
    CF_CPU_FEATURE("avx512vnni");
#endif
#ifdef __AVX512BITALG__
    CF_CPU_FEATURE("avx512bitalg");
#endif
#ifdef __AVX512VPOPCNTDQ__
    CF_CPU_FEATURE("avx512vpopcntdq");
#endif
#ifdef __AVX512BF16__
    CF_CPU_FEATURE("avx512bf16");
#endif
#ifdef __AVX512VP2INTERSECT__
    CF_CPU_FEATURE("avx512vp2intersect");
#endif
#undef CF_CPU_FEATURE
#endif
    return n;
}

namespace detail {
// Appends s to buf[0..len) within size (one byte kept for the NUL); returns the new length. (No
// lambda: a lambda's body does not inherit its enclosing function's target attribute.)
[[gnu::target("arch=x86-64")]] inline std::size_t append(char* buf, std::size_t size, std::size_t len, const char* s) {
    for (; *s && len + 1 < size; ++s) buf[len++] = *s;
    return len;
}
}  // namespace detail

// The one-line refusal for features[0..n) into buf (NUL-terminated, cut to size): "PROGRAM: this
// CPU lacks avx2, fma, which this build was compiled for (-march; docs/packaging.md): install a
// package built for this CPU's baseline, ...". Returns the number of missing features (0: buf is
// the empty string).
[[gnu::target("arch=x86-64")]] inline std::size_t cpu_baseline_message(const CpuFeature* features, std::size_t n,
                                                                       const char* program, char* buf,
                                                                       std::size_t size) {
    std::size_t len = 0, missing = 0;
    if (size == 0) return 0;
    buf[0] = '\0';
    for (std::size_t i = 0; i < n; ++i) {
        if (features[i].supported) continue;
        if (missing++ == 0) {
            len = detail::append(buf, size, len, program);
            len = detail::append(buf, size, len, ": this CPU lacks ");
        } else {
            len = detail::append(buf, size, len, ", ");
        }
        len = detail::append(buf, size, len, features[i].name);
    }
    if (missing > 0)
        len = detail::append(buf, size, len,
                             ", which this build was compiled for (-march; docs/packaging.md): install a package built "
                             "for this CPU's baseline, e.g. CF_MARCH=x86-64-v2 scripts/build-package.sh\n");
    buf[len] = '\0';
    return missing;
}

// When any of features[0..n) is unsupported: writes the line to stderr and exits with
// kCpuBaselineExitCode; otherwise returns.
[[gnu::target("arch=x86-64")]] inline void refuse_if_cpu_lacks(const CpuFeature* features, std::size_t n,
                                                               const char* program) {
    char line[1024];
    if (cpu_baseline_message(features, n, program, line, sizeof line) == 0) return;
    std::size_t len = 0;
    while (line[len]) ++len;
    [[maybe_unused]] const ssize_t w = ::write(2, line, len);
    ::_exit(kCpuBaselineExitCode);
}

// Checks this binary's features; on a CPU that lacks one, writes the line to stderr and exits.
[[gnu::target("arch=x86-64")]] inline void check_cpu_baseline_or_exit(const char* program) {
    CpuFeature features[kMaxCpuFeatures];
    refuse_if_cpu_lacks(features, compiled_cpu_features(features), program);
}

}  // namespace cf

// In the file with main(): runs the check before the executable's other static constructors
// (priority 101; shared libraries are built for the distribution's baseline).
#define CF_CPU_BASELINE_CHECK(program)                                                                  \
    [[gnu::constructor(101), gnu::target("arch=x86-64")]] static void cf_cpu_baseline_check_ctor() { \
        ::cf::check_cpu_baseline_or_exit(program);                                                  \
    }
