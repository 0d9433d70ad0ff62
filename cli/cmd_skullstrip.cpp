// cortexfuse skullstrip: brain mask of a T1 head, with optional check image and Dice.
#include <chrono>
#include <iostream>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/skull_strip.hpp"

namespace cf::cli {

void add_skullstrip(CLI::App& app) {
    struct Opts {
        std::string volume, out, check_png, reference;
        bool json = false, quiet = false;
        SkullStripParams params;
    };
    auto o = std::make_shared<Opts>();
    auto* cmd = app.add_subcommand("skullstrip", "Brain mask of a T1 head MRI (skull stripping)");
    cmd->add_option("VOLUME", o->volume, "T1 head volume (NIfTI, NRRD, MHA or DICOM folder)")->required();
    cmd->add_option("--out", o->out, "output mask (.nii.gz, .nrrd, .mha)")->required();
    cmd->add_option("--check-png", o->check_png, "write a slice montage with the mask contour");
    cmd->add_option("--reference", o->reference, "reference mask on the same grid: print the Dice");
    cmd->add_flag("--json", o->json, "print the result as one JSON object");
    cmd->add_flag("--quiet", o->quiet, "no progress lines on stderr");
    auto& p = o->params;
    cmd->add_option("--target", p.target, "brain (cortex surface, default) or intracranial (CSF to the inner table)")
        ->transform(CLI::CheckedTransformer(std::map<std::string, SkullStripTarget>{
            {"brain", SkullStripTarget::brain}, {"intracranial", SkullStripTarget::intracranial}}));
    cmd->add_option("--bet-fraction", p.bet_fraction, "surface model's fractional threshold (BET's f)")->capture_default_str();
    cmd->add_flag("--no-surface-model{false}", p.surface_model, "thresholds and morphology alone, no BET surface");
    cmd->add_option("--brain-csf-margin-mm", p.brain_csf_margin_mm, "target brain: CSF layer kept over the cortex")->capture_default_str();
    cmd->add_option("--support-above-mm", p.support_above_mm, "surface interior is brain above its centre + this (>= 100: never)")->capture_default_str();
    cmd->add_option("--support-gate-mm", p.support_gate_mm, "fine grids: surface interior only where tissue reaches it past no dark layer (0: off)")->capture_default_str();
    cmd->add_option("--valley-snap-mm", p.valley_snap_mm, "coarse grids: move the mask's edge into the intensity valley (0: off)")->capture_default_str();
    cmd->add_option("--open-mm", p.open_mm, "final opening radius (removes thin leaks)")->capture_default_str();
    cmd->add_option("--envelope-margin-mm", p.envelope_margin_mm, "reach of tissue beyond the surface model")->capture_default_str();
    cmd->add_option("--erode-mm", p.erode_mm, "erosion radius separating brain from scalp")->capture_default_str();
    cmd->add_option("--close-mm", p.close_mm, "closing radius (sulci, envelope)")->capture_default_str();
    cmd->add_option("--final-dilate-mm", p.final_dilate_mm, "final margin (negative: erosion)")->capture_default_str();
    cmd->add_option("--bias-sigma-mm", p.bias_sigma_mm, "bias-field smoothing (0: none)")->capture_default_str();
    cmd->add_option("--reconstruct-mm", p.reconstruct_mm, "reconstruction reach from the eroded brain")->capture_default_str();
    cmd->add_option("--tissue-split", p.tissue_split, "tissue threshold: csf + k (gm - csf)")->capture_default_str();
    cmd->add_option("--csf-split", p.csf_split, "extra-axial CSF threshold: csf + k (gm - csf)")->capture_default_str();
    cmd->add_option("--csf-margin-mm", p.csf_margin_mm, "target intracranial: CSF growth beyond the tissue envelope")->capture_default_str();
    cmd->add_option("--bright-limit", p.bright_limit, "upper threshold: wm + k (wm - gm)")->capture_default_str();

    cmd->callback([o] {
        run_guarded("skullstrip", [o]() -> int {
            const auto t0 = std::chrono::steady_clock::now();
            const Volume v = load_volume(o->volume);
            LabelVolume ref;
            if (!o->reference.empty()) {
                ref = load_mask(o->reference);
                if (!ref.geom.same_grid(v.geom))
                    throw InputError(o->reference, "reference mask is not on the grid of " + o->volume);
            }
            Progress progress;
            if (!o->quiet && !o->json)
                progress.report = [](const std::string& stage, double f) {
                    std::cerr << "  " << int(f * 100) << "% " << stage << "\n";
                };
            const auto t1 = std::chrono::steady_clock::now();
            SkullStripInfo info;
            const LabelVolume mask = skull_strip(v, o->params, &progress, &info);
            const double strip_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t1).count();
            save_mask(mask, o->out);
            if (!o->check_png.empty())
                write_mask_check_png(v, mask, o->check_png, o->reference.empty() ? nullptr : &ref);
            const double total_s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
            const double d = o->reference.empty() ? -1.0 : dice(mask, ref);

            if (o->json) {
                nlohmann::json j = {{"volume", o->volume},
                                    {"out", o->out},
                                    {"brain_ml", info.brain_ml},
                                    {"head_ml", info.head_ml},
                                    {"target", o->params.target == SkullStripTarget::brain ? "brain" : "intracranial"},
                                    {"working_spacing_mm", info.working_spacing_mm},
                                    {"surface_model_ml", info.envelope_ml},
                                    {"surface_model_used", info.envelope_used},
                                    {"seconds_strip", strip_s},
                                    {"seconds_total", total_s},
                                    {"thresholds", {{"background", info.t_background},
                                                    {"low", info.t_low},
                                                    {"high", info.t_high},
                                                    {"csf", info.t_csf}}},
                                    {"classes", {{"csf", info.csf}, {"gm", info.gm}, {"wm", info.wm}}}};
                if (!o->check_png.empty()) j["check_png"] = o->check_png;
                if (d >= 0) j["dice"] = d;
                std::cout << j.dump() << "\n";
            } else {
                std::cout << "mask: " << o->out << " (" << info.brain_ml << " mL)\n"
                          << "classes csf/gm/wm: " << info.csf << " / " << info.gm << " / " << info.wm
                          << ", thresholds " << info.t_low << " .. " << info.t_high << "\n";
                if (d >= 0) std::cout << "dice: " << d << "\n";
                std::cout << "seconds: " << strip_s << " (skull strip), " << total_s << " (total)\n";
            }
            return 0;
        });
    });
}

}  // namespace cf::cli
