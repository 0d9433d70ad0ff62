#pragma once
// The engine's benchmarks: ray casting, similarity and registration timed the same way
// every time, so that a figure can be put beside another tool's measured in the same run
// (bench/render_vs_vtk.sh). Each run returns one JSON object with medians and peak RSS.
//
// The render camera path (bench_intrinsics, bench_pose) and the quantisation of the volume
// (bench_quantised_range) are public so that the VTK reference (vtk_raycast_reference.cpp)
// renders exactly the same frames.
//
// Thread contract: every function is re-entrant; a run uses `threads` worker threads.
#include <filesystem>
#include <optional>
#include <nlohmann/json.hpp>

#include "cortexfuse/core/registration.hpp"
#include <string>
#include <utility>
#include <vector>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/progress.hpp"
#include "cortexfuse/core/renderer.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "cortexfuse/core/volume.hpp"

namespace cf::bench {

/// Order statistics of a sample (milliseconds, microseconds, seconds: the caller's unit).
struct Stats {
    double median = 0, p90 = 0, min = 0, max = 0, mean = 0;
    size_t n = 0;
};
Stats stats(std::vector<double> v);

/// Peak resident set size of this process in MiB (VmHWM from /proc/self/status, else
/// getrusage's ru_maxrss).
double peak_rss_mb();

/// "375x250" -> {375, 250}. Throws InputError(option, ...) unless WxH with each in 8..8192.
std::pair<int, int> parse_size(const std::string& s, const std::string& option = "--size");

/// A preset name or a JSON file (transfer_function.hpp). Throws InputError.
TransferFunction transfer_function_arg(const std::string& name_or_file);

/// The renderers a benchmark can time. "cpu" is the CPU ray caster; a GPU backend plugs in
/// through make_renderer when it exists. Unknown names throw InputError("--renderer NAME").
std::vector<std::string> renderer_names();
void check_renderer_name(const std::string& name);
std::unique_ptr<Renderer> make_renderer(const std::string& name, const Volume& v, const TransferFunction& tf,
                                        const LabelVolume* mask);

// ---- The camera path shared with the VTK reference ----

/// The camera distance from the volume centre, mm, and the focal length that makes a
/// 220 mm wide head fill the image width.
constexpr double kBenchDistanceMm = 400.0;
Intrinsics bench_intrinsics(int width, int height);
/// Frame `i` of the path: the camera on the patient's left looking at the volume centre
/// (standard_view "left"), moved by a small smooth offset about the centre every frame
/// (under 1 deg and 1 mm from frame to frame, a few deg / mm in all), as a registration
/// loop moves it. Warm-up frames are 0..warmup-1, timed frames follow.
Pose bench_pose(const VolumeGeometry& g, int i);

/// The intensity range [lo, hi] the CPU ray caster maps onto its 4096 quantisation levels
/// (robust_range of the volume inside the mask); the reference quantises the same way.
constexpr int kQuantLevels = 4096;
std::array<double, 2> bench_quantised_range(const Volume& v, const LabelVolume* mask);

// ---- The three benchmarks ----

struct RenderBenchConfig {
    std::filesystem::path volume, mask;  // mask empty: none
    int width = 375, height = 250;
    std::string tf = "skin";
    std::string renderer = "cpu";
    int frames = 30, warmup = 5;
    int threads = 0;                      // 0: all cores
    double sample_mm = 1.0;
    bool shading = true;
    bool surface_only = false;  // registration's mode: the first crossing of the surface level, opaque
    bool ray_start_map = true;  // CPU: rays start at the nearest visible brick (false to compare)
    std::filesystem::path save_frame;     // PNG of the first timed frame, if set
};
/// Times `frames` renders (after `warmup`), one camera step each. Throws InputError on bad
/// input. JSON: ms_per_frame_median/_p90/_min/_mean, prepare_ms, coverage_fraction, peak_rss_mb,
/// output_checksum (FNV-1a of every timed frame's rgb, grey, depth and coverage: equal
/// checksums mean bit-identical output along the path) ...
nlohmann::json run_render_bench(const RenderBenchConfig& c, const Progress* progress = nullptr);

struct NmiBenchConfig {
    int width = 375, height = 250;
    int bins = 64;
    int frames = 50;         // samples; each is the mean over `repeat` evaluations
    int repeat = 20;
    int warmup = 3;
    bool masked = false;     // an elliptic mask over ~60 % of the image (as a ROI), else all pixels
};
/// NMI, MI and NCC of two deterministic 375x250 images (a smooth field with a flat
/// background, and a non-linear, noisy function of it), one thread. JSON: nmi_us_median ...
nlohmann::json run_nmi_bench(const NmiBenchConfig& c, const Progress* progress = nullptr);

struct RegisterBenchConfig {
    std::filesystem::path volume, mask;   // for generated phantoms
    std::filesystem::path case_dir;       // a case folder or a folder of case folders; empty: generate
    int cases = 4;                        // phantoms to generate
    uint64_t seed = 1;
    int threads = 0;
    bool keep = false;                    // keep the generated phantom folder (its path is in the JSON)
    /// The schedule timed (default: RegistrationParams::defaults()) and, optionally, a reference
    /// schedule registered on the same cases in the same run, case by case in turn, so both
    /// see the same machine (e.g. the previous defaults or the seed's schedule).
    std::optional<RegistrationParams> params;
    std::optional<RegistrationParams> reference;
    std::string reference_name = "reference";
    /// The similarity's ray caster for `params`: cpu, gl or auto (issue 3: the GL registration
    /// time). `reference_renderer`, when set and no reference schedule is given, registers the
    /// same schedule a second time with that renderer, case by case in turn: GL beside CPU.
    std::string renderer = "cpu";
    std::string reference_renderer;
};
/// Registers each case once from its landmarks and times it.
/// JSON: seconds_median/_p90, evaluations_median, per-case seconds, evaluations and MRE
/// (when the case has truth), prepare_s, peak_rss_mb; with a reference, the same figures for it
/// under "reference" and reference_over_params_seconds (the ratio of the medians); each
/// schedule's renderer as its engine names it ("renderer", "reference.renderer").
nlohmann::json run_register_bench(const RegisterBenchConfig& c, const Progress* progress = nullptr);

}  // namespace cf::bench
