// cortexfuse plan: the preoperative plan folder (brain mask, surface, CT and fMRI on the T1).
#include <iostream>
#include <memory>
#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "cortexfuse/core/plan.hpp"
#include "progress_bar.hpp"

namespace cf::cli {

void add_plan(CLI::App& app) {
    struct Opts {
        std::string t1, out, ct, fmri, fmri_ref, brain_mask, reference_mask, metric = "mattes";
        bool json = false;
        PlanParams params;
    };
    auto o = std::make_shared<Opts>();
    auto* cmd = app.add_subcommand("plan", "Preoperative plan: brain mask, brain surface (PLY, LPS mm), CT and fMRI "
                                           "co-registered to the T1 (docs/planning.md)");
    cmd->add_option("--t1", o->t1, "T1 head volume")->required();
    cmd->add_option("--out", o->out, "plan folder (plan.json, brain_mask.nii.gz, brain_surface.ply, ...)")->required();
    cmd->add_option("--ct", o->ct, "CT of the same patient: registered to the T1 (ct_to_t1.tfm, ct_on_t1.nii.gz)");
    cmd->add_option("--fmri", o->fmri, "fMRI statistic map (t or z): thresholded, clusters, onto the T1 grid");
    cmd->add_option("--fmri-ref", o->fmri_ref, "anatomy in the map's space (mean EPI, template): registered to the T1");
    cmd->add_option("--brain-mask", o->brain_mask, "use this brain mask instead of skull stripping");
    cmd->add_option("--reference-mask", o->reference_mask, "reference brain mask: Dice in plan.json");
    cmd->add_option("--max-triangles", o->params.surface.max_triangles, "surface triangle budget (0: no decimation)")
        ->capture_default_str();
    cmd->add_option("--smooth-iterations", o->params.surface.smooth_iterations, "windowed-sinc iterations")->capture_default_str();
    cmd->add_option("--metric", o->metric, "co-registration metric: mattes or nmi")->check(CLI::IsMember({"nmi", "mattes"}))->capture_default_str();
    cmd->add_option("--fmri-threshold", o->params.fmri.threshold, "statistic threshold (t or z)")->capture_default_str();
    cmd->add_option("--fmri-min-cluster", o->params.fmri.min_cluster_voxels, "smallest cluster kept, voxels of the map")
        ->capture_default_str();
    cmd->add_flag("--fmri-two-sided", o->params.fmri.two_sided, "also keep deactivations (stat <= -threshold)");
    cmd->add_flag("--json", o->json, "print plan.json on stdout");
    cmd->callback([o] {
        run_guarded("plan", [o]() -> int {
            PlanInputs in;
            in.t1 = o->t1;
            if (!o->ct.empty()) in.ct = o->ct;
            if (!o->fmri.empty()) in.fmri = o->fmri;
            if (!o->fmri_ref.empty()) in.fmri_reference = o->fmri_ref;
            if (!o->brain_mask.empty()) in.brain_mask = o->brain_mask;
            if (!o->reference_mask.empty()) in.reference_mask = o->reference_mask;
            const auto m = o->metric == "nmi" ? CoregParams::Metric::Nmi : CoregParams::Metric::Mattes;
            o->params.coreg_ct.metric = o->params.coreg_fmri.metric = m;
            ProgressBar bar("plan");
            const nlohmann::json j = make_plan(in, o->params, o->out, bar.progress());
            if (o->json)
                std::cout << j.dump() << "\n";
            else
                std::cout << "plan: " << o->out << "/plan.json (" << j["seconds_total"].get<double>() << " s)\n";
            return 0;
        });
    });
}

}  // namespace cf::cli
