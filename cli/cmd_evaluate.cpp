// cortexfuse evaluate: the seed's Table 3.1 protocol on phantom cases with ground truth.
// Each case (a photo pose) gets N random initial misalignments about its landmark pose; every
// run is registered and scored by MRE, TRE and IPE. Output: a Markdown table on stdout, and
// optionally JSON and a PNG of the error distributions.
#include <opencv2/imgcodecs.hpp>
#include <opencv2/imgproc.hpp>

#include <algorithm>
#include <cmath>
#include <iostream>
#include <map>
#include <nlohmann/json.hpp>
#include <numeric>
#include <sstream>

#include "commands.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/evaluation.hpp"
#include "cortexfuse/core/landmarks.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/registration.hpp"
#include "cortexfuse/core/roi.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "cortexfuse/render/renderer_factory.hpp"
#include "progress_bar.hpp"

namespace fs = std::filesystem;
using nlohmann::json;

namespace cf::cli {

namespace {

struct EvalCmd {
    std::string dir, params_file, out_json, out_md, out_png;
    int trials = 10;
    double max_mm = 10, max_deg = 5;
    bool wide = false, seed_schedule = false, no_prior = false, from_truth = false;
    std::string renderer = "cpu";
    uint64_t seed = 1;
    int limit_cases = 0;
    double success_mm = 3.0;
};

struct Stat {
    double mean = 0, sd = 0, median = 0, max = 0;
};

Stat stat(std::vector<double> v) {
    Stat s;
    if (v.empty()) return s;
    s.mean = std::accumulate(v.begin(), v.end(), 0.0) / double(v.size());
    double ss = 0;
    for (double x : v) ss += (x - s.mean) * (x - s.mean);
    s.sd = v.size() > 1 ? std::sqrt(ss / double(v.size() - 1)) : 0.0;
    std::sort(v.begin(), v.end());
    s.median = v[v.size() / 2];
    s.max = v.back();
    return s;
}

std::string fmt(double v, int prec = 2) {
    std::ostringstream o;
    o.setf(std::ios::fixed);
    o.precision(prec);
    o << v;
    return o.str();
}

struct Row {
    std::string name;
    std::vector<double> mre, tre, ipe_px, ipe_mm, seconds, evals;
};

// A result's optional figure (NaN: not measured) as a number or null.
json number_or_null(double v) { return std::isnan(v) ? json(nullptr) : json(v); }

json row_json(const Row& r, double success_mm) {
    const Stat m = stat(r.mre), t = stat(r.tre), ip = stat(r.ipe_px), im = stat(r.ipe_mm), s = stat(r.seconds);
    const double succ = r.mre.empty() ? 0.0 : double(std::count_if(r.mre.begin(), r.mre.end(), [&](double x) { return x < success_mm; })) / double(r.mre.size());
    return {{"name", r.name}, {"n", r.mre.size()}, {"mre_mm_mean", m.mean}, {"mre_mm_sd", m.sd}, {"mre_mm_median", m.median},
            {"mre_mm_max", m.max}, {"tre_mm_mean", t.mean}, {"tre_mm_sd", t.sd}, {"tre_mm_median", t.median},
            {"ipe_px_mean", ip.mean}, {"ipe_mm_mean", im.mean}, {"success_rate", succ},
            {"seconds_median", s.median}, {"seconds_mean", s.mean}, {"evaluations_median", stat(r.evals).median}};
}

std::string markdown(const std::vector<Row>& rows, double success_mm) {
    std::string md = "| | runs | MRE mm (mean ± sd) | MRE max | TRE mm (mean ± sd) | IPE px | IPE mm | success (MRE < " +
                     fmt(success_mm, 0) + " mm) | time s (median) |\n|---|---|---|---|---|---|---|---|---|\n";
    for (const auto& r : rows) {
        const json j = row_json(r, success_mm);
        md += "| " + r.name + " | " + std::to_string(r.mre.size()) + " | " + fmt(j["mre_mm_mean"]) + " ± " + fmt(j["mre_mm_sd"]) +
              " | " + fmt(j["mre_mm_max"]) + " | " + fmt(j["tre_mm_mean"]) + " ± " + fmt(j["tre_mm_sd"]) + " | " +
              fmt(j["ipe_px_mean"]) + " | " + fmt(j["ipe_mm_mean"]) + " | " + fmt(100.0 * j["success_rate"].get<double>(), 0) +
              " % | " + (r.seconds.empty() ? std::string("-") : fmt(j["seconds_median"])) + " |\n";
    }
    return md;
}

/// Error distributions as a picture: one horizontal strip per row, each run a dot at its MRE.
void write_png(const std::vector<Row>& rows, double success_mm, const std::string& path) {
    const int W = 900, rowh = 70, left = 170, H = 60 + rowh * int(rows.size());
    cv::Mat img(H, W, CV_8UC3, cv::Scalar(255, 255, 255));
    double xmax = success_mm * 2;
    for (const auto& r : rows)
        for (double v : r.mre) xmax = std::max(xmax, std::min(v, 40.0));
    auto X = [&](double v) { return left + int((W - left - 20) * std::min(v, xmax) / xmax); };
    for (int t = 0; t <= 10; ++t) {
        const double v = xmax * t / 10;
        cv::line(img, {X(v), 20}, {X(v), H - 30}, cv::Scalar(225, 225, 225));
        cv::putText(img, fmt(v, 1), {X(v) - 12, H - 10}, cv::FONT_HERSHEY_SIMPLEX, 0.4, cv::Scalar(60, 60, 60));
    }
    cv::line(img, {X(success_mm), 15}, {X(success_mm), H - 30}, cv::Scalar(0, 0, 220), 2);
    cv::putText(img, "MRE mm (red: success limit)", {left, 14}, cv::FONT_HERSHEY_SIMPLEX, 0.45, cv::Scalar(0, 0, 0));
    std::mt19937 jitter(1);
    std::uniform_int_distribution<int> J(-rowh / 3, rowh / 3);
    for (size_t i = 0; i < rows.size(); ++i) {
        const int y = 40 + rowh * int(i) + rowh / 2;
        cv::putText(img, rows[i].name, {8, y + 5}, cv::FONT_HERSHEY_SIMPLEX, 0.45, cv::Scalar(0, 0, 0));
        for (double v : rows[i].mre)
            cv::circle(img, {X(v), y + J(jitter)}, 3, v < success_mm ? cv::Scalar(60, 160, 60) : cv::Scalar(40, 40, 200), cv::FILLED);
        const Stat s = stat(rows[i].mre);
        cv::line(img, {X(s.median), y - rowh / 2 + 4}, {X(s.median), y + rowh / 2 - 4}, cv::Scalar(0, 0, 0), 2);
    }
    if (!cv::imwrite(path, img)) throw InputError(path, "cannot write PNG");
}

}  // namespace

void add_evaluate(CLI::App& app) {
    auto o = std::make_shared<EvalCmd>();
    auto* sub = app.add_subcommand("evaluate", "The seed's Table 3.1 protocol on phantom cases (MRE, TRE, IPE, success)");
    sub->add_option("cases_dir", o->dir, "Folder of case folders with truth.json (from cortexfuse phantom)")->required();
    sub->add_option("--trials", o->trials, "Random initial misalignments per case (0: one run from the landmarks alone)")->capture_default_str();
    sub->add_option("--max-mm", o->max_mm, "Largest misalignment per translation")->capture_default_str();
    sub->add_option("--max-deg", o->max_deg, "Largest misalignment per rotation")->capture_default_str();
    sub->add_flag("--wide", o->wide, "The wider capture test: +-20 mm / +-15 deg");
    sub->add_option("--seed", o->seed, "Random seed of the misalignments")->capture_default_str();
    sub->add_option("--params", o->params_file, "Registration parameters (JSON)");
    sub->add_flag("--seed-schedule", o->seed_schedule, "Use the seed's original stage schedule");
    sub->add_flag("--no-prior", o->no_prior, "Turn the landmark prior off");
    sub->add_flag("--from-truth", o->from_truth,
                  "Start every run at the true pose (diagnosis: how far the similarity's own optimum lies from the truth)");
    sub->add_option("--renderer", o->renderer, "Ray caster for the similarity: cpu, gl (EGL/OpenGL) or auto")
        ->capture_default_str();
    sub->add_option("--limit-cases", o->limit_cases, "Use only the first N cases");
    sub->add_option("--json", o->out_json, "Write the summary and every run as JSON");
    sub->add_option("--md", o->out_md, "Write the Markdown table to this file too");
    sub->add_option("--png", o->out_png, "Write the error distributions as a PNG");
    sub->callback([o] {
        run_guarded("evaluate", [&] {
            if (o->wide) {
                o->max_mm = 20;
                o->max_deg = 15;
            }
            if (o->trials < 0 || o->trials > 10000) throw InputError("--trials", "must be 0..10000");
            const bool from_landmarks = o->trials == 0;
            const int trials = std::max(1, o->trials);
            std::vector<fs::path> cases;
            std::error_code ec;
            if (!fs::is_directory(o->dir, ec)) throw InputError(o->dir, "not a folder");
            for (const auto& e : fs::directory_iterator(o->dir))
                if (e.is_directory() && fs::exists(e.path() / "case.json") && fs::exists(e.path() / "truth.json")) cases.push_back(e.path());
            std::sort(cases.begin(), cases.end());
            if (o->limit_cases > 0 && int(cases.size()) > o->limit_cases) cases.resize(size_t(o->limit_cases));
            if (cases.empty()) throw InputError(o->dir, "holds no case folder with case.json and truth.json");

            RegistrationParams params = o->seed_schedule ? RegistrationParams::seed_schedule() : RegistrationParams::defaults();
            if (!o->params_file.empty()) params = registration_params_from_json(read_json_file(o->params_file), o->params_file);
            if (o->no_prior) params.landmark_prior_weight = 0;
            params.renderer_factory = renderer_factory(parse_renderer_kind(o->renderer));

            // "true pose": the errors of the true pose itself, the floor of the measurement.
            Row floor{"true pose (floor)", {}, {}, {}, {}, {}, {}}, lm{"landmarks only", {}, {}, {}, {}, {}, {}}, init{"initial (misaligned)", {}, {}, {}, {}, {}, {}},
                reg{"registered", {}, {}, {}, {}, {}, {}};
            json runs = json::array();
            std::mt19937_64 rng(o->seed);
            ProgressBar bar("evaluate");
            // Cases from one phantom share a volume: keep the prepared engine per volume file.
            std::map<std::string, std::unique_ptr<Registration>> engines;
            std::map<std::string, std::unique_ptr<PhantomSurface>> surfaces;
            // The registration's surface rendering, to measure how far it lies from the true mesh.
            const int total = int(cases.size()) * trials;
            int done = 0;
            for (const auto& dir : cases) {
                LoadedCase c = load_case(dir);
                if (!c.spec.truth) throw InputError((dir / "truth.json").string(), "missing");
                const std::string key = c.spec.volume_path.string() + "|" + (c.spec.brain_mask_path ? c.spec.brain_mask_path->string() : "");
                auto& engine = engines[key];
                if (!engine) engine = std::make_unique<Registration>(c.volume, c.mask, params);
                // The true brain surface (the phantom's mesh, on which the targets lie): MRE is
                // measured by casting back onto it.
                auto& surface = surfaces[key];
                if (!surface) surface = std::make_unique<PhantomSurface>(build_phantom_surface(c.volume, c.mask));
                const RasterMesh& mesh = surface->mesh;
                const Truth& truth = *c.spec.truth;
                const Intrinsics& K = c.spec.camera;
                const PoseErrors e_true = pose_errors(truth, K, truth.T_camera_from_world, mesh);
                SurfaceOffset offset;
                {
                    const double s = std::min(1.0, 375.0 / K.width);
                    const Intrinsics Ks = s < 1 ? K.scaled(s) : K;
                    RenderOptions ro;
                    ro.surface_only = params.surface_only;
                    ro.sample_distance_mm = params.sample_distance_mm;
                    ro.want_rgb = false;
                    const cv::Mat roi = c.photo.roi ? roi_mask(*c.photo.roi, Ks.width, Ks.height, s) : cv::Mat();
                    // The engine's own renderer: its surface level (surface_tissue_fraction) is the one compared.
                    offset = surface_offset(engine->renderer(), ro, mesh, Ks, truth.T_camera_from_world, roi);
                }
                floor.mre.push_back(e_true.mre_mm);
                floor.tre.push_back(e_true.tre_mm);
                floor.ipe_px.push_back(e_true.ipe_px);
                floor.ipe_mm.push_back(e_true.ipe_mm);
                const LandmarkFit fit = fit_pose_pnp(c.spec.landmarks, K);
                const PoseErrors e_lm = pose_errors(truth, K, fit.T_camera_from_world, mesh);
                lm.mre.push_back(e_lm.mre_mm);
                lm.tre.push_back(e_lm.tre_mm);
                lm.ipe_px.push_back(e_lm.ipe_px);
                lm.ipe_mm.push_back(e_lm.ipe_mm);
                // Misalign about the landmarks' centroid, in the camera frame.
                Eigen::Vector3d c_world = Eigen::Vector3d::Zero();
                for (const auto& l : c.spec.landmarks) c_world += l.world_mm;
                c_world /= double(c.spec.landmarks.size());
                const Eigen::Vector3d pivot_cam = fit.T_camera_from_world.topLeftCorner<3, 3>() * c_world + fit.T_camera_from_world.topRightCorner<3, 1>();
                for (int t = 0; t < trials; ++t) {
                    const PoseParams x = from_landmarks ? PoseParams{0, 0, 0, 0, 0, 0} : random_misalignment(rng, o->max_mm, o->max_deg);
                    const Pose T_init = o->from_truth ? truth.T_camera_from_world : apply_params(fit.T_camera_from_world, pivot_cam, x);
                    PhotoInput in = c.photo;
                    if (!from_landmarks || o->from_truth) in.initial_pose = T_init;
                    Progress inner;
                    inner.cancel = bar.progress().cancel;
                    inner.report = [&](const std::string& stage, double f) {
                        bar.progress()(dir.filename().string() + " " + stage, (done + f) / total);
                    };
                    const RegistrationResult r = engine->run(in, &inner);
                    // Search or similarity? The truth's cost at the last stage beside the result's.
                    const StageParams& last = params.last_stage();
                    const Pose T_ref = in.initial_pose ? *in.initial_pose : r.initial_T_camera_from_world;
                    const bool lit = params.estimate_light;
                    const auto light = lit ? std::optional<Eigen::Vector3d>(r.light_direction_camera) : std::nullopt;
                    const auto lamp = lit ? r.light_position_camera_mm : std::nullopt;
                    const auto s_truth = engine->score(in, truth.T_camera_from_world, T_ref, last, light, lamp);
                    const auto s_final = engine->score(in, r.T_camera_from_world, T_ref, last, light, lamp);
                    const PoseErrors e0 = pose_errors(truth, K, T_init, mesh);
                    const PoseErrors e1 = pose_errors(truth, K, r.T_camera_from_world, mesh);
                    init.mre.push_back(e0.mre_mm);
                    init.tre.push_back(e0.tre_mm);
                    init.ipe_px.push_back(e0.ipe_px);
                    init.ipe_mm.push_back(e0.ipe_mm);
                    reg.mre.push_back(e1.mre_mm);
                    reg.tre.push_back(e1.tre_mm);
                    reg.ipe_px.push_back(e1.ipe_px);
                    reg.ipe_mm.push_back(e1.ipe_mm);
                    // Where each stage left the pose: which stage gains or loses.
                    json stages = json::array();
                    for (const auto& st : r.stages) {
                        const PoseErrors es = pose_errors(truth, K, st.T_camera_from_world, mesh);
                        stages.push_back({{"name", st.name}, {"start", st.start}, {"cost", st.best_cost}, {"mre_mm", es.mre_mm},
                                          {"offset_camera_mm", {es.offset_camera_mm.x(), es.offset_camera_mm.y(), es.offset_camera_mm.z()}},
                                          {"T_camera_from_world", pose_to_json(st.T_camera_from_world)}});
                    }
                    reg.seconds.push_back(r.seconds);
                    reg.evals.push_back(r.evaluations);
                    runs.push_back({{"case", dir.filename().string()}, {"trial", t}, {"misalignment", x},
                                    {"truth_T_camera_from_world", pose_to_json(truth.T_camera_from_world)},
                                    {"landmark_T_camera_from_world", pose_to_json(fit.T_camera_from_world)},
                                    {"initial", {{"mre_mm", e0.mre_mm}, {"tre_mm", e0.tre_mm}, {"ipe_px", e0.ipe_px},
                                                 {"T_camera_from_world", pose_to_json(T_init)}}},
                                    {"registered", {{"mre_mm", e1.mre_mm}, {"tre_mm", e1.tre_mm}, {"ipe_px", e1.ipe_px},
                                                    {"targets_missed", e1.targets_missed},
                                                    {"T_camera_from_world", pose_to_json(r.T_camera_from_world)},
                                                    {"offset_camera_mm", {e1.offset_camera_mm.x(), e1.offset_camera_mm.y(), e1.offset_camera_mm.z()}}}},
                                    {"landmarks_only", {{"mre_mm", e_lm.mre_mm}, {"tre_mm", e_lm.tre_mm},
                                                        {"offset_camera_mm", {e_lm.offset_camera_mm.x(), e_lm.offset_camera_mm.y(), e_lm.offset_camera_mm.z()}}}},
                                    {"surface_offset_mm", {{"median", offset.median_mm}, {"mean", offset.mean_mm}, {"mad", offset.mad_mm}, {"pixels", offset.pixels}}},
                                    {"seconds", r.seconds}, {"evaluations", r.evaluations}, {"similarity", r.similarity}, {"stages", stages},
                                    {"peak_prominence", number_or_null(r.peak_prominence)},
                                    {"landmarks_weighed_up", r.landmarks_weighed_up},
                                    {"landmark_prior_widened", r.landmark_prior_widened},
                                    {"landmark_widened_fit_lead", number_or_null(r.landmark_widened_fit_lead)},
                                    {"landmark_plain_fit_peak_apart_mm", number_or_null(r.landmark_plain_fit_peak_apart_mm)},
                                    {"landmark_widened_fit_prominence", number_or_null(r.landmark_widened_fit_prominence)},
                                    {"truth_score", {{"similarity", s_truth.similarity}, {"cost", s_truth.cost}}},
                                    {"final_score", {{"similarity", s_final.similarity}, {"cost", s_final.cost}}}});
                    ++done;
                }
            }
            const std::vector<Row> rows{floor, lm, init, reg};
            const std::string protocol =
                from_landmarks ? "Protocol: " + std::to_string(cases.size()) + " cases, each registered once from its landmarks alone"
                               : "Protocol: " + std::to_string(cases.size()) + " cases x " + std::to_string(o->trials) +
                                     " misalignments within +-" + fmt(o->max_mm, 0) + " mm / +-" + fmt(o->max_deg, 0) +
                                     " deg of the landmark pose (seed " + std::to_string(o->seed) + ")";
            const std::string md = protocol + "\n\n" + markdown(rows, o->success_mm);
            std::cout << md;
            if (!o->out_md.empty()) write_file_atomic(o->out_md, md);
            if (!o->out_json.empty()) {
                json j = {{"cases", cases.size()}, {"trials_per_case", o->trials}, {"max_mm", o->max_mm}, {"max_deg", o->max_deg},
                          {"seed", o->seed}, {"success_mre_mm", o->success_mm}, {"parameters", to_json(params)},
                          {"summary", json::array({row_json(floor, o->success_mm), row_json(lm, o->success_mm), row_json(init, o->success_mm), row_json(reg, o->success_mm)})},
                          {"runs", runs}};
                write_file_atomic(o->out_json, j.dump(2) + "\n");
            }
            if (!o->out_png.empty()) write_png(rows, o->success_mm, o->out_png);
            return 0;
        });
    });
}

}  // namespace cf::cli
