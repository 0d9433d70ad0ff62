#pragma once
// The preoperative plan (`cortexfuse plan`): skull stripping, the brain surface, and the
// other modalities (CT, fMRI activation maps) co-registered to the T1 and resampled onto its
// grid. Everything lands in one folder, described by plan.json (docs/planning.md).
#include <filesystem>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>

#include "cortexfuse/core/coregistration.hpp"
#include "cortexfuse/core/progress.hpp"
#include "cortexfuse/core/skull_strip.hpp"
#include "cortexfuse/core/surface.hpp"
#include "cortexfuse/core/volume.hpp"

namespace cf {

/// fMRI activation map: a statistic map (t or z) thresholded, small clusters removed.
struct FmriParams {
    double threshold = 3.1;       // |stat| >= threshold (z 3.1 ~ p < 0.001 one-sided) (0, 100]
    bool two_sided = false;       // also keep stat <= -threshold
    int min_cluster_voxels = 10;  // in the map's own grid [1, 1e6]
    void validate() const;
};

/// Keeps the supra-threshold clusters of a statistic map (ITK connected components, 26-
/// connected); everything else becomes 0. Returns the clusters kept through `clusters`.
Volume threshold_activation(const Volume& stat, const FmriParams& p, int* clusters = nullptr);

/// A fingerprint of a volume's grid and voxels (FNV-1a 64 over dims, spacing, origin,
/// direction and the float voxels, as 16 hex digits). plan.json keeps the T1's as
/// "t1_fingerprint"; `cortexfuse overlay --plan` refuses a plan whose T1 is not the case's
/// (another patient's scan on an identical grid). Hand-written: 10 lines, no library needed.
std::string volume_fingerprint(const Volume& v);

struct PlanInputs {
    std::filesystem::path t1;
    std::optional<std::filesystem::path> brain_mask;      // use instead of skull stripping
    std::optional<std::filesystem::path> reference_mask;  // Dice of the mask against it
    std::optional<std::filesystem::path> ct;
    std::optional<std::filesystem::path> fmri;            // statistic map
    std::optional<std::filesystem::path> fmri_reference;  // anatomy in the map's space (registered to the T1);
                                                          // without it the map is taken as already in the T1's world
};

struct PlanParams {
    SkullStripParams skull;
    SurfaceParams surface;
    CoregParams coreg_ct;    // CT -> T1
    CoregParams coreg_fmri;  // fMRI reference -> T1
    FmriParams fmri;
};

/// Runs the plan into `out_dir` (created; files written atomically) and returns plan.json's
/// content (also written). Throws InputError naming the input on bad input; Cancelled.
nlohmann::json make_plan(const PlanInputs& in, const PlanParams& params, const std::filesystem::path& out_dir,
                         const Progress& progress = {});

}  // namespace cf
