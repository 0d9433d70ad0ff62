#include "cortexfuse/bench/bench.hpp"

#include <sys/resource.h>
#include <tbb/global_control.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cmath>
#include <fstream>
#include <map>
#include <memory>
#include <numeric>
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>
#include <optional>
#include <random>
#include <sstream>
#include <thread>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/evaluation.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/registration.hpp"
#include "cortexfuse/core/similarity.hpp"
#include "cortexfuse/render/renderer_factory.hpp"

namespace fs = std::filesystem;
using nlohmann::json;

namespace cf::bench {
namespace {
using Clock = std::chrono::steady_clock;
double ms_since(Clock::time_point t0) { return std::chrono::duration<double, std::milli>(Clock::now() - t0).count(); }

std::string size_string(int w, int h) { return std::to_string(w) + "x" + std::to_string(h); }

int resolve_threads(int threads) {
    if (threads < 0) throw InputError("--threads " + std::to_string(threads), "must be 0 (all cores) or more");
    return threads > 0 ? threads : int(std::max(1u, std::thread::hardware_concurrency()));
}

void check_count(const char* option, int v, int lo, int hi) {
    if (v < lo || v > hi)
        throw InputError(std::string(option) + " " + std::to_string(v),
                         "must lie in " + std::to_string(lo) + ".." + std::to_string(hi));
}

json stats_json(const Stats& s, const std::string& prefix) {
    return {{prefix + "_median", s.median}, {prefix + "_p90", s.p90}, {prefix + "_min", s.min}, {prefix + "_mean", s.mean}};
}

void merge(json& into, const json& from) {
    for (auto it = from.begin(); it != from.end(); ++it) into[it.key()] = it.value();
}

// The reference beside ours: the same NMI from OpenCV's cv::calcHist (a well-kept library's
// 2-D histogram) and a plain entropy sum. Same binning as cf::Similarity: bin = floor(v * (bins - 1e-3)).
double nmi_opencv(const cv::Mat& a, const cv::Mat& b, const cv::Mat& mask, int bins, cv::Mat& hist) {
    const cv::Mat images[] = {a, b};
    const int channels[] = {0, 1};
    const int hist_size[] = {bins, bins};
    const float range[] = {0.f, float(double(bins) / (double(bins) - 1e-3))};
    const float* ranges[] = {range, range};
    cv::calcHist(images, 2, channels, mask, hist, 2, hist_size, ranges, true, false);
    double n = 0;
    std::vector<double> ma(size_t(bins), 0.0), mb(size_t(bins), 0.0);
    for (int i = 0; i < bins; ++i)
        for (int j = 0; j < bins; ++j) {
            const double c = hist.at<float>(i, j);
            n += c;
            ma[size_t(i)] += c;
            mb[size_t(j)] += c;
        }
    if (n < 2) return 1.0;
    auto entropy = [n](double c) { return c > 0 ? -(c / n) * std::log(c / n) : 0.0; };
    double ha = 0, hb = 0, hab = 0;
    for (int i = 0; i < bins; ++i) {
        ha += entropy(ma[size_t(i)]);
        hb += entropy(mb[size_t(i)]);
        for (int j = 0; j < bins; ++j) hab += entropy(hist.at<float>(i, j));
    }
    return hab > 0 ? (ha + hb) / hab : 1.0;
}

// FNV-1a over raw bytes: a fingerprint of every rendered buffer, so two builds (or two
// renderers) can be checked for bit-identical output along the whole camera path.
void fnv1a(uint64_t& h, const void* data, size_t n) {
    const auto* p = static_cast<const uint8_t*>(data);
    for (size_t i = 0; i < n; ++i) {
        h ^= p[i];
        h *= 1099511628211ull;
    }
}

// Removes a folder this run made, also when it ends by an exception.
struct TempDir {
    fs::path path;
    bool keep = false;
    ~TempDir() {
        std::error_code ec;
        if (!path.empty() && !keep) fs::remove_all(path, ec);
    }
};
}  // namespace

Stats stats(std::vector<double> v) {
    Stats s;
    s.n = v.size();
    if (v.empty()) return s;
    std::sort(v.begin(), v.end());
    // Linear interpolation between order statistics (numpy's default percentile).
    auto pct = [&](double q) {
        const double x = q * double(v.size() - 1);
        const size_t i = size_t(x);
        const double f = x - double(i);
        return i + 1 < v.size() ? v[i] + f * (v[i + 1] - v[i]) : v[i];
    };
    s.median = pct(0.5);
    s.p90 = pct(0.9);
    s.min = v.front();
    s.max = v.back();
    s.mean = std::accumulate(v.begin(), v.end(), 0.0) / double(v.size());
    return s;
}

double peak_rss_mb() {
    std::ifstream in("/proc/self/status");
    std::string line;
    while (std::getline(in, line))
        if (line.rfind("VmHWM:", 0) == 0) {
            std::istringstream ls(line.substr(6));
            double kb = 0;
            if (ls >> kb) return kb / 1024.0;
        }
    rusage ru{};
    getrusage(RUSAGE_SELF, &ru);
    return double(ru.ru_maxrss) / 1024.0;  // kB on Linux
}

std::pair<int, int> parse_size(const std::string& s, const std::string& option) {
    int w = 0, h = 0;
    char x = 0, rest = 0;
    std::istringstream in(s);
    if (!(in >> w >> x >> h) || (x != 'x' && x != 'X') || (in >> rest) || w < 8 || h < 8 || w > 8192 || h > 8192)
        throw InputError(option + " " + s, "expected WIDTHxHEIGHT, each 8..8192");
    return {w, h};
}

TransferFunction transfer_function_arg(const std::string& name_or_file) {
    if (fs::exists(name_or_file)) return load_transfer_function(name_or_file);
    if (name_or_file.find('/') != std::string::npos || name_or_file.ends_with(".json"))
        throw InputError(name_or_file, "transfer function file not found");
    return preset_transfer_function(name_or_file);
}

std::vector<std::string> renderer_names() { return {"cpu", "gl", "auto"}; }

void check_renderer_name(const std::string& name) {
    const auto known = renderer_names();
    if (std::find(known.begin(), known.end(), name) != known.end()) return;
    std::string list;
    for (const auto& n : known) list += (list.empty() ? "" : ", ") + n;
    throw InputError("--renderer " + name, "unknown renderer (known: " + list + ")");
}

std::unique_ptr<Renderer> make_renderer(const std::string& name, const Volume& v, const TransferFunction& tf,
                                        const LabelVolume* mask) {
    check_renderer_name(name);
    // gl: the EGL/OpenGL ray caster (render/gl); auto: gl when a context can be made.
    return cf::make_renderer(parse_renderer_kind(name), v, tf, mask);
}

Intrinsics bench_intrinsics(int width, int height) {
    // As `cortexfuse render` without --camera: a 220 mm head spans the image width.
    Intrinsics K;
    K.width = width;
    K.height = height;
    K.fx = K.fy = 0.5 * width * kBenchDistanceMm / 110.0;
    K.cx = (width - 1) * 0.5;
    K.cy = (height - 1) * 0.5;
    return K;
}

Pose bench_pose(const VolumeGeometry& g, int i) {
    const Eigen::Vector3d centre = g.center_world_mm();
    const Pose T0 = standard_view("left", centre, kBenchDistanceMm);
    const Eigen::Vector3d pivot_camera = T0.topLeftCorner<3, 3>() * centre + T0.topRightCorner<3, 1>();
    // Incommensurate slow sines: every frame differs, steps stay below ~1 deg / 1 mm.
    const double t = double(i);
    const PoseParams x = {3.0 * std::sin(0.23 * t), 3.0 * std::sin(0.17 * t + 1.0), 2.0 * std::sin(0.29 * t + 2.0),
                          3.0 * std::sin(0.19 * t + 3.0), 3.0 * std::sin(0.31 * t + 4.0), 4.0 * std::sin(0.13 * t + 5.0)};
    return apply_params(T0, pivot_camera, x);
}

std::array<double, 2> bench_quantised_range(const Volume& v, const LabelVolume* mask) { return robust_range(v, mask); }

json run_render_bench(const RenderBenchConfig& c, const Progress* progress) {
    check_count("--frames", c.frames, 1, 100000);
    check_count("--warmup", c.warmup, 0, 100000);
    if (!(c.sample_mm >= 0.05 && c.sample_mm <= 10))
        throw InputError("--sample-mm " + std::to_string(c.sample_mm), "must lie in 0.05..10 mm");
    if (c.width < 8 || c.height < 8 || c.width > 8192 || c.height > 8192)
        throw InputError("--size " + size_string(c.width, c.height), "each side must lie in 8..8192");
    // Check the cheap options before loading anything.
    check_renderer_name(c.renderer);
    const TransferFunction tf = transfer_function_arg(c.tf);
    const int threads = resolve_threads(c.threads);

    const Volume v = load_volume(c.volume);
    std::optional<LabelVolume> mask;
    if (!c.mask.empty()) mask = load_mask(c.mask, v.geom);
    const auto t_prep = Clock::now();
    auto r = make_renderer(c.renderer, v, tf, mask ? &*mask : nullptr);
    const double prepare_ms = ms_since(t_prep);

    const Intrinsics K = bench_intrinsics(c.width, c.height);
    RenderOptions ro;
    ro.sample_distance_mm = c.sample_mm;
    ro.shading = c.shading;
    ro.surface_only = c.surface_only;
    ro.ray_start_map = c.ray_start_map;
    ro.threads = threads;
    RenderImage img;
    std::vector<double> ms;
    ms.reserve(size_t(c.frames));
    double coverage = 0;
    uint64_t checksum = 1469598103934665603ull;
    const int total = c.warmup + c.frames;
    for (int i = 0; i < total; ++i) {
        if (progress) {
            progress->check();
            (*progress)(i < c.warmup ? "warm-up" : "render", double(i) / total);
        }
        const Pose T = bench_pose(v.geom, i);
        const auto t0 = Clock::now();
        r->render(K, T, ro, img);
        const double dt = ms_since(t0);
        if (i < c.warmup) continue;
        ms.push_back(dt);
        fnv1a(checksum, img.rgb.data(), img.rgb.size());
        fnv1a(checksum, img.grey.data(), img.grey.size() * sizeof(float));
        fnv1a(checksum, img.depth_mm.data(), img.depth_mm.size() * sizeof(float));
        fnv1a(checksum, img.coverage.data(), img.coverage.size());
        if (i == c.warmup) {
            coverage = double(std::count(img.coverage.begin(), img.coverage.end(), uint8_t(1))) / double(img.coverage.size());
            if (!c.save_frame.empty()) {
                cv::Mat bgr;
                cv::cvtColor(cv::Mat(K.height, K.width, CV_8UC3, img.rgb.data()), bgr, cv::COLOR_RGB2BGR);
                if (!cv::imwrite(c.save_frame.string(), bgr)) throw InputError(c.save_frame.string(), "cannot write PNG");
            }
        }
    }
    if (progress) (*progress)("render", 1.0);
    json j = {{"mode", "render"},
              {"renderer", r->name()},
              {"volume", c.volume.string()},
              {"dims", v.geom.dims},
              {"spacing_mm", {v.geom.spacing_mm.x(), v.geom.spacing_mm.y(), v.geom.spacing_mm.z()}},
              {"mask", c.mask.string()},
              {"size", size_string(c.width, c.height)},
              {"tf", c.tf},
              {"shading", c.shading},
              {"surface_only", c.surface_only},
              {"ray_start_map", c.ray_start_map},
              {"sample_mm", c.sample_mm},
              {"threads", threads},
              {"frames", c.frames},
              {"warmup", c.warmup},
              {"prepare_ms", prepare_ms},
              {"coverage_fraction", coverage},
              {"output_checksum", [&] {
                   char buf[17];
                   std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(checksum));
                   return std::string(buf);
               }()}};
    merge(j, stats_json(stats(ms), "ms_per_frame"));
    j["peak_rss_mb"] = peak_rss_mb();
    return j;
}

json run_nmi_bench(const NmiBenchConfig& c, const Progress* progress) {
    check_count("--frames", c.frames, 1, 1000000);
    check_count("--repeat", c.repeat, 1, 100000);
    check_count("--warmup", c.warmup, 0, 100000);
    check_count("--bins", c.bins, 2, 1024);
    if (c.width < 8 || c.height < 8 || c.width > 8192 || c.height > 8192)
        throw InputError("--size " + size_string(c.width, c.height), "each side must lie in 8..8192");
    // Image a: a smooth random field in [0.2, 1] inside an ellipse, 0 outside (a rendering
    // has a flat background, which piles counts into one bin). Image b: a non-linear,
    // noisy function of a, as a photo is of a rendering.
    std::mt19937_64 rng(7);
    cv::Mat noise(c.height, c.width, CV_32F);
    std::normal_distribution<float> nd(0.f, 1.f);
    for (int y = 0; y < c.height; ++y)
        for (int x = 0; x < c.width; ++x) noise.at<float>(y, x) = nd(rng);
    cv::Mat field;
    cv::GaussianBlur(noise, field, cv::Size(), 6.0);
    cv::normalize(field, field, 0.2, 1.0, cv::NORM_MINMAX);
    cv::Mat inside(c.height, c.width, CV_8U, cv::Scalar(0));
    cv::ellipse(inside, cv::Point(c.width / 2, c.height / 2), cv::Size(int(c.width * 0.45), int(c.height * 0.45)), 0, 0, 360,
                cv::Scalar(255), cv::FILLED);
    cv::Mat a(c.height, c.width, CV_32F, cv::Scalar(0));
    field.copyTo(a, inside);
    cv::Mat b(c.height, c.width, CV_32F);
    for (int y = 0; y < c.height; ++y)
        for (int x = 0; x < c.width; ++x) {
            const float va = a.at<float>(y, x);
            b.at<float>(y, x) = std::clamp(0.8f * va * va + 0.1f + 0.05f * nd(rng), 0.f, 1.f);
        }
    cv::Mat mask;
    if (c.masked) {
        mask = cv::Mat(c.height, c.width, CV_8U, cv::Scalar(0));
        cv::ellipse(mask, cv::Point(c.width / 2, c.height / 2), cv::Size(int(c.width * 0.38), int(c.height * 0.38)), 0, 0, 360,
                    cv::Scalar(255), cv::FILLED);
    }
    Similarity sim(c.bins);
    json j = {{"mode", "nmi"},          {"size", size_string(c.width, c.height)},
              {"bins", c.bins},         {"masked", c.masked},
              {"mask_fraction", c.masked ? double(cv::countNonZero(mask)) / double(mask.total()) : 1.0},
              {"threads", 1},           {"frames", c.frames},
              {"repeat", c.repeat},     {"warmup", c.warmup}};
    const std::pair<SimilarityMetric, const char*> metrics[] = {
        {SimilarityMetric::NMI, "nmi"}, {SimilarityMetric::MI, "mi"}, {SimilarityMetric::NCC, "ncc"}};
    int done = 0;
    for (const auto& [m, name] : metrics) {
        volatile double sink = 0;  // keeps the evaluations from being optimised away
        for (int i = 0; i < c.warmup * c.repeat; ++i) sink = sink + sim.evaluate(m, a, b, mask);
        std::vector<double> us;
        us.reserve(size_t(c.frames));
        for (int f = 0; f < c.frames; ++f) {
            if (progress) {
                progress->check();
                (*progress)(name, double(done++) / (3.0 * c.frames));
            }
            const auto t0 = Clock::now();
            for (int i = 0; i < c.repeat; ++i) sink = sink + sim.evaluate(m, a, b, mask);
            us.push_back(ms_since(t0) * 1000.0 / c.repeat);
        }
        merge(j, stats_json(stats(us), std::string(name) + "_us"));
        j[std::string(name) + "_value"] = sim.evaluate(m, a, b, mask);
    }
    {
        cv::Mat hist;
        volatile double sink = 0;
        for (int i = 0; i < c.warmup * c.repeat; ++i) sink = sink + nmi_opencv(a, b, mask, c.bins, hist);
        std::vector<double> us;
        for (int f = 0; f < c.frames; ++f) {
            if (progress) progress->check();
            const auto t0 = Clock::now();
            for (int i = 0; i < c.repeat; ++i) sink = sink + nmi_opencv(a, b, mask, c.bins, hist);
            us.push_back(ms_since(t0) * 1000.0 / c.repeat);
        }
        merge(j, stats_json(stats(us), "opencv_calchist_nmi_us"));
        j["opencv_calchist_nmi_value"] = nmi_opencv(a, b, mask, c.bins, hist);
        j["ratio_opencv_over_ours"] = j["opencv_calchist_nmi_us_median"].get<double>() / j["nmi_us_median"].get<double>();
    }
    if (progress) (*progress)("ncc", 1.0);
    j["peak_rss_mb"] = peak_rss_mb();
    return j;
}

json run_register_bench(const RegisterBenchConfig& c, const Progress* progress) {
    check_renderer_name(c.renderer);  // before any phantom is made
    if (!c.reference_renderer.empty()) check_renderer_name(c.reference_renderer);
    const int threads = resolve_threads(c.threads);
    // Limits every TBB loop of this run (ray caster, phantom generator) to `threads`.
    tbb::global_control limit(tbb::global_control::max_allowed_parallelism, size_t(threads));
    TempDir tmp;
    std::vector<fs::path> dirs;
    double generate_s = 0;
    if (!c.case_dir.empty()) {
        if (!fs::is_directory(c.case_dir)) throw InputError(c.case_dir.string(), "not a folder");
        if (fs::exists(c.case_dir / "case.json")) {
            dirs.push_back(c.case_dir);
        } else {
            for (const auto& e : fs::directory_iterator(c.case_dir))
                if (e.is_directory() && fs::exists(e.path() / "case.json")) dirs.push_back(e.path());
            std::sort(dirs.begin(), dirs.end());
        }
        if (dirs.empty()) throw InputError(c.case_dir.string(), "holds no case folder with case.json");
    } else {
        check_count("--cases", c.cases, 1, 1000);
        std::string tmpl = (fs::temp_directory_path() / "cortexfuse-bench-XXXXXX").string();
        if (!mkdtemp(tmpl.data())) throw InputError(tmpl, "cannot create a temporary folder");
        tmp.path = tmpl;
        tmp.keep = c.keep;
        PhantomParams p;
        p.seed = c.seed;
        Progress inner;
        if (progress) {
            inner.cancel = progress->cancel;
            inner.report = [&](const std::string& stage, double f) { (*progress)("phantom " + stage, 0.2 * f); };
        }
        const auto t0 = Clock::now();
        dirs = generate_phantoms(tmp.path, c.cases, c.volume, c.mask, p, inner);
        generate_s = ms_since(t0) / 1000.0;
    }
    // One schedule's figures; cases of one phantom run share a volume, so each schedule
    // prepares its engine once per volume file.
    struct Variant {
        RegistrationParams params;
        std::map<std::string, std::unique_ptr<Registration>> engines;
        std::vector<double> seconds, evals, mre;
        json per_case = json::array();
        double prepare_s = 0;
    };
    const bool second = c.reference || !c.reference_renderer.empty();
    std::vector<Variant> variants(second ? 2 : 1);
    variants[0].params = c.params ? *c.params : RegistrationParams::defaults();
    variants[0].params.renderer_factory = renderer_factory(parse_renderer_kind(c.renderer));
    if (second) {
        variants[1].params = c.reference ? *c.reference : variants[0].params;
        const std::string rr = c.reference_renderer.empty() ? c.renderer : c.reference_renderer;
        variants[1].params.renderer_factory = renderer_factory(parse_renderer_kind(rr));
    }
    for (size_t i = 0; i < dirs.size(); ++i) {
        if (progress) progress->check();
        LoadedCase lc = load_case(dirs[i]);
        const std::string key = lc.spec.volume_path.string() + "|" + (lc.spec.brain_mask_path ? lc.spec.brain_mask_path->string() : "");
        for (size_t v = 0; v < variants.size(); ++v) {
            Variant& V = variants[v];
            auto& engine = V.engines[key];
            if (!engine) {
                const auto t0 = Clock::now();
                engine = std::make_unique<Registration>(lc.volume, lc.mask, V.params);
                V.prepare_s += ms_since(t0) / 1000.0;
            }
            Progress inner;
            if (progress) {
                inner.cancel = progress->cancel;
                inner.report = [&](const std::string& stage, double f) {
                    const double done = (double(i) + (double(v) + f) / double(variants.size())) / double(dirs.size());
                    (*progress)(dirs[i].filename().string() + (v ? " (" + c.reference_name + ") " : " ") + stage, 0.2 + 0.8 * done);
                };
            }
            const RegistrationResult r = engine->run(lc.photo, &inner);
            V.seconds.push_back(r.seconds);
            V.evals.push_back(r.evaluations);
            json row = {{"case", dirs[i].filename().string()},
                        {"photo_size", size_string(lc.spec.camera.width, lc.spec.camera.height)},
                        {"seconds", r.seconds},
                        {"evaluations", r.evaluations}};
            if (lc.spec.truth) {
                const PoseErrors e = pose_errors(*lc.spec.truth, lc.spec.camera, r.T_camera_from_world, engine->renderer());
                V.mre.push_back(e.mre_mm);
                row["mre_mm"] = e.mre_mm;
            }
            V.per_case.push_back(row);
        }
    }
    if (progress) (*progress)("done", 1.0);
    auto figures = [&](const Variant& V) {
        json j = {{"prepare_s", V.prepare_s}};
        // The renderer the engine actually made (auto may have fallen back to the CPU).
        if (!V.engines.empty()) j["renderer"] = V.engines.begin()->second->renderer().name();
        merge(j, stats_json(stats(V.seconds), "seconds"));
        j["evaluations_median"] = stats(V.evals).median;
        j["ms_per_evaluation_median"] = stats([&] {
            std::vector<double> v;
            for (size_t i = 0; i < V.seconds.size(); ++i) v.push_back(1000.0 * V.seconds[i] / std::max(1.0, V.evals[i]));
            return v;
        }()).median;
        if (!V.mre.empty()) j["mre_mm_median"] = stats(V.mre).median;
        j["per_case"] = V.per_case;
        return j;
    };
    json j = {{"mode", "register"},
              {"cases", dirs.size()},
              {"case_dir", c.case_dir.empty() ? (c.keep ? tmp.path.string() : "") : c.case_dir.string()},
              {"generated", c.case_dir.empty()},
              {"seed", c.seed},
              {"threads", threads},
              {"generate_s", generate_s}};
    merge(j, figures(variants[0]));
    if (second) {
        json r = figures(variants[1]);
        r["name"] = c.reference ? c.reference_name : "renderer " + c.reference_renderer;
        j["reference"] = r;
        j["reference_over_params_seconds"] = r["seconds_median"].get<double>() / std::max(1e-9, j["seconds_median"].get<double>());
    }
    j["peak_rss_mb"] = peak_rss_mb();
    return j;
}

}  // namespace cf::bench
