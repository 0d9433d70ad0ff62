// cortexfuse coregister: rigid co-registration of a moving volume (CT, fMRI map) to a fixed
// one (the T1); coregister-synth / coregister-error: synthetic cases with truth and the
// error of a transform over a mask (bench/coregister_vs_elastix.sh runs them beside elastix).
#include <chrono>
#include <filesystem>
#include <iostream>
#include <memory>
#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/coregistration.hpp"
#include "cortexfuse/core/error.hpp"
#include "progress_bar.hpp"

namespace fs = std::filesystem;

namespace cf::cli {
namespace {

nlohmann::json matrix_json(const Eigen::Matrix4d& T) {
    nlohmann::json m = nlohmann::json::array();
    for (int r = 0; r < 4; ++r) m.push_back({T(r, 0), T(r, 1), T(r, 2), T(r, 3)});
    return m;
}

void add_coreg_options(CLI::App* cmd, CoregParams& p, std::string& metric) {
    cmd->add_option("--metric", metric, "nmi (normalized MI (H(F)+H(M))/H(F,M), Nelder-Mead) or mattes (ITK Mattes MI, gradient descent)")
        ->check(CLI::IsMember({"nmi", "mattes"}))
        ->capture_default_str();
    cmd->add_option("--bins", p.bins, "histogram bins")->capture_default_str();
    cmd->add_option("--shrink", p.shrink, "shrink factor per level")->capture_default_str();
    cmd->add_option("--smooth-mm", p.smooth_mm, "Gaussian sigma per level, mm")->capture_default_str();
    cmd->add_option("--iterations", p.iterations, "optimiser iterations per level")->capture_default_str();
    cmd->add_option("--sampling", p.sampling, "fraction of fixed voxels sampled")->capture_default_str();
    cmd->add_option("--max-step", p.max_step, "first optimiser step")->capture_default_str();
    cmd->add_option("--seed", p.seed, "sampling seed")->capture_default_str();
    cmd->add_option("--min-overlap", p.min_overlap, "quality gate: fixed head inside moving FOV")->capture_default_str();
    cmd->add_option("--min-nmi", p.min_nmi, "quality gate: NMI after registration")->capture_default_str();
    cmd->add_option("--fixed-mask", p.fixed_foreground_mask,
                    "sample the metric only on the fixed image's head foreground (true/false)")
        ->capture_default_str();
    cmd->add_option("--clip-intensities", p.clip_intensities,
                    "clip each image to its head's robust intensity range before registration (true/false)")
        ->capture_default_str();
}

}  // namespace

void add_coregister(CLI::App& app) {
    struct Opts {
        std::string fixed, moving, out, resampled, metric = "mattes";
        bool json = false, nearest = false;
        CoregParams params;
    };
    auto o = std::make_shared<Opts>();
    auto* cmd = app.add_subcommand(
        "coregister",
        "Rigid co-registration of MOVING (CT, fMRI map) to FIXED (the T1). The ITK transform written maps FIXED's "
        "world points (LPS mm) to MOVING's (ITK's resampling convention); 3D Slicer opens it as is.");
    cmd->add_option("FIXED", o->fixed, "fixed volume (the T1)")->required();
    cmd->add_option("MOVING", o->moving, "moving volume (CT, fMRI/EPI-space map)")->required();
    cmd->add_option("--out", o->out, "transform file (.tfm or .h5)")->required();
    cmd->add_option("--resampled", o->resampled, "also write MOVING resampled onto FIXED's grid");
    cmd->add_flag("--nearest", o->nearest, "nearest-neighbour resampling (label maps)");
    cmd->add_flag("--json", o->json, "print the result as one JSON object");
    add_coreg_options(cmd, o->params, o->metric);
    cmd->callback([o] {
        run_guarded("coregister", [o]() -> int {
            o->params.metric = o->metric == "nmi" ? CoregParams::Metric::Nmi : CoregParams::Metric::Mattes;
            o->params.validate();
            const auto t0 = std::chrono::steady_clock::now();
            const Volume fixed = load_volume(o->fixed);
            const Volume moving = load_volume(o->moving);
            const double load_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
            ProgressBar bar("coregister");
            const CoregResult r = coregister(fixed, moving, o->params, bar.progress());
            save_transform(r.T_moving_from_fixed, r.center_world_mm, o->out);
            if (!o->resampled.empty())
                save_volume(resample_rigid(moving, r.T_moving_from_fixed, fixed.geom, o->nearest, 0.f), o->resampled);
            nlohmann::json levels = nlohmann::json::array();
            for (const auto& l : r.levels)
                levels.push_back({{"iterations", l.iterations}, {"metric", l.metric}, {"seconds", l.seconds}, {"stop", l.stop}});
            const nlohmann::json j = {{"fixed", o->fixed},
                                      {"moving", o->moving},
                                      {"transform", o->out},
                                      {"convention", "maps FIXED world (LPS mm) to MOVING world"},
                                      {"metric", o->metric},
                                      {"T_moving_from_fixed", matrix_json(r.T_moving_from_fixed)},
                                      {"final_metric", r.metric},
                                      {"nmi", r.nmi},
                                      {"overlap", r.overlap},
                                      {"seconds_register", r.seconds},
                                      {"seconds_load", load_s},
                                      {"levels", levels}};
            if (o->json)
                std::cout << j.dump() << "\n";
            else
                std::cout << "transform: " << o->out << "\nNMI after: " << r.nmi << ", overlap " << r.overlap * 100
                          << " %\nseconds: " << r.seconds << " (registration), " << load_s << " (loading)\n";
            return 0;
        });
    });

    // Synthetic cases with truth.
    struct SynthOpts {
        std::string t1, out;
        int n = 3;
        uint64_t seed = 1;
        std::string kind = "ct";
        double max_angle_deg = 10, max_shift_mm = 15, inplane_mm = 0.9, slice_mm = 2.0, voxel_mm = 3.0, blur_fwhm_mm = 4.0;
    };
    auto s = std::make_shared<SynthOpts>();
    auto* syn = app.add_subcommand("coregister-synth",
                                   "Synthetic co-registration cases with truth from a real T1 (moving.nii.gz, truth.tfm): "
                                   "CT-like (--kind ct) or mean-EPI-like (--kind epi: coarse, blurred, T2*-like contrast)");
    syn->add_option("T1", s->t1, "real T1 head volume")->required();
    syn->add_option("--out", s->out, "output folder (case_000, ...)")->required();
    syn->add_option("--n", s->n, "number of cases")->check(CLI::Range(1, 100))->capture_default_str();
    syn->add_option("--seed", s->seed, "random seed")->capture_default_str();
    syn->add_option("--max-angle-deg", s->max_angle_deg, "rotation range per axis")->check(CLI::Range(0.0, 45.0))->capture_default_str();
    syn->add_option("--max-shift-mm", s->max_shift_mm, "translation range per axis")->check(CLI::Range(0.0, 100.0))->capture_default_str();
    syn->add_option("--inplane-mm", s->inplane_mm, "CT-like in-plane voxel size")->capture_default_str();
    syn->add_option("--slice-mm", s->slice_mm, "CT-like slice thickness")->capture_default_str();
    syn->add_option("--kind", s->kind, "ct or epi")->check(CLI::IsMember({"ct", "epi"}))->capture_default_str();
    syn->add_option("--voxel-mm", s->voxel_mm, "EPI-like isotropic voxel size")->capture_default_str();
    syn->add_option("--blur-fwhm-mm", s->blur_fwhm_mm, "EPI-like blur (Gaussian FWHM)")->capture_default_str();
    syn->callback([s] {
        run_guarded("coregister-synth", [s]() -> int {
            const Volume t1 = load_volume(s->t1);
            fs::create_directories(s->out);
            nlohmann::json list = nlohmann::json::array();
            for (int i = 0; i < s->n; ++i) {
                const uint64_t seed = s->seed * 1000 + uint64_t(i);
                const SyntheticCoregCase c =
                    s->kind == "epi"
                        ? make_synthetic_epi_case(t1, seed, s->max_angle_deg, s->max_shift_mm, s->voxel_mm, s->blur_fwhm_mm)
                        : make_synthetic_ct_case(t1, seed, s->max_angle_deg, s->max_shift_mm, s->inplane_mm, s->slice_mm);
                char name[32];
                std::snprintf(name, sizeof name, "case_%03d", i);
                const fs::path dir = fs::path(s->out) / name;
                fs::create_directories(dir);
                save_volume(c.moving, dir / "moving.nii.gz");
                save_transform(c.T_moving_from_fixed, t1.geom.center_world_mm(), dir / "truth.tfm");
                list.push_back({{"case", dir.string()},
                                {"kind", s->kind},
                                {"angles_deg", {c.angles_deg.x(), c.angles_deg.y(), c.angles_deg.z()}},
                                {"translation_mm", {c.translation_mm.x(), c.translation_mm.y(), c.translation_mm.z()}}});
            }
            std::cout << list.dump() << "\n";
            return 0;
        });
    });

    // The error of a transform against the truth over a mask.
    struct ErrOpts {
        std::string truth, estimate, mask;
    };
    auto e = std::make_shared<ErrOpts>();
    auto* err = app.add_subcommand("coregister-error",
                                   "Mean/max distance (mm) between two transforms over a mask's voxels (ITK file or elastix "
                                   "TransformParameters with an EulerTransform)");
    err->add_option("TRUTH", e->truth, "true transform")->required();
    err->add_option("ESTIMATE", e->estimate, "estimated transform")->required();
    err->add_option("--mask", e->mask, "mask on the fixed grid (the brain)")->required();
    err->callback([e] {
        run_guarded("coregister-error", [e]() -> int {
            const Eigen::Matrix4d A = load_transform(e->truth), B = load_transform(e->estimate);
            const LabelVolume m = load_mask(e->mask);
            const TransformError te = transform_error(A, B, m);
            std::cout << nlohmann::json{{"mean_mm", te.mean_mm}, {"max_mm", te.max_mm}, {"points", te.points}}.dump() << "\n";
            return 0;
        });
    });
}

}  // namespace cf::cli
