#pragma once
// Skull stripping of a T1-weighted head MRI: a binary brain mask (brain + the CSF in sulci and
// ventricles, smooth outer envelope) so the ray caster shows the brain, not the scalp.
// Method and measured accuracy: docs/skull-stripping.md.
#include <filesystem>

#include "cortexfuse/core/progress.hpp"
#include "cortexfuse/core/volume.hpp"

namespace cf {

/// What the mask should hold. `brain`: brain tissue with the CSF of sulci and ventricles, its
/// outer surface on the cortex (what the ray caster must show; the default, used by register).
/// `intracranial`: also the extra-axial CSF up to the inner table of the skull.
enum class SkullStripTarget { brain, intracranial };

/// Tuning of skull_strip(). The defaults are what was validated (docs/skull-stripping.md);
/// every field is range-checked (InputError naming the field).
struct SkullStripParams {
    SkullStripTarget target = SkullStripTarget::brain;
    /// Bound the segmentation by the BET-like surface model (off: thresholds and morphology alone).
    bool surface_model = true;
    /// BET's fractional intensity threshold for the surface model (lower: larger envelope). [0.05, 0.95]
    double bet_fraction = 0.5;
    /// The surface model's interior counts as brain above its centre + this height (the convexity,
    /// where one threshold misses dark cortex); >= 100: never. [-50, 100]
    double support_above_mm = 0.0;
    /// Fine grids (voxels <= 1.3 mm): the surface model's interior only counts as brain where the
    /// brain tissue reaches it within this distance by a path through tissue-like voxels that a
    /// dark layer (CSF, inner table) does not cut; the extra-axial CSF is then grown geodesically
    /// too. Stops the grey and bright layers beyond the CSF (dura, marrow) from entering the
    /// mask as sheets over the cortex. 0 = neither (the former rules). [0, 30]
    double support_gate_mm = 10.0;
    /// Coarse grids (voxels > 1.3 mm): the mask's edge moves outwards downhill into the intensity
    /// valley between brain and skull by up to this distance, so the ray caster does not show the
    /// mask's voxel staircase. 0 = off. [0, 20]
    double valley_snap_mm = 4.0;
    /// Tissue and CSF are only taken within this distance of the BET surface. [0, 20]
    double envelope_margin_mm = 3.0;
    /// Background level = p2 + background_frac * (p98 - p2) of all voxels (as FSL BET). [0.01, 0.5]
    double background_frac = 0.1;
    /// Brain-tissue threshold between the CSF and GM class means found at the head centre:
    /// csf + tissue_split * (gm - csf). Low, because cortex is darker than the central GM/WM
    /// mix the class means come from (bias field, partial volume). [-2, 1]
    double tissue_split = 0.25;
    /// Upper tissue threshold wm + bright_limit * (wm - gm): cuts bright scalp fat and marrow. [0.2, 20]
    double bright_limit = 2.0;
    /// Erosion radius that disconnects brain tissue from scalp and dura before the brain
    /// component is picked; larger is safer against bridges but loses thin gyri. [0.5, 20]
    double erode_mm = 2.0;
    /// Reconstruction reach: candidate tissue connected to the eroded brain and within this
    /// distance of it is brain (thin gyri the erosion cut off come back). [0, 30]
    double reconstruct_mm = 6.0;
    /// Smoothing (Gaussian sigma) of the intensity-bias estimate from the WM found; the tissue
    /// is then found again on the flattened volume. 0 = no bias correction. [0, 100]
    double bias_sigma_mm = 20.0;
    /// Closing radius: fills sulci and smooths the envelope; 0 = no closing. [0, 30]
    double close_mm = 8.0;
    /// Target brain: the CSF growth's reach beyond the tissue envelope (the thin CSF layer over the
    /// cortex that FreeSurfer's brain mask also holds). [0, 20]
    double brain_csf_margin_mm = 6.0;
    /// Extra-axial CSF: voxels next to the brain darker than csf + csf_split * (gm - csf) are CSF
    /// (the brighter grey band beyond, dura and bone partial volume, is not). [-2, 1]
    double csf_split = -0.3;
    /// Target intracranial only: how far beyond the brain envelope the CSF growth may reach (up to
    /// the inner table of the skull); also what stops it from leaking through the skull base. [0, 20]
    double csf_margin_mm = 8.0;
    /// Opening radius at the end: removes sheets thinner than twice this (leaks along the dura,
    /// into the temporal muscle); 0 = none. [0, 20]
    double open_mm = 3.0;
    /// Final dilation (negative: erosion) of the mask. [-10, 10]
    double final_dilate_mm = 0.0;
    /// Plausible mask volume; outside it the input is refused as "not a T1 head". Max in [min, 1e6]
    double min_brain_ml = 500.0;
    double max_brain_ml = 2500.0;
};

/// What skull_strip() found (for logs, tuning and the CLI's --json).
struct SkullStripInfo {
    double p02 = 0, p98 = 0;                      // robust intensity range of the volume
    double t_background = 0, t_low = 0, t_high = 0, t_csf = 0;  // thresholds used, volume units
    double csf = 0, gm = 0, wm = 0;               // tissue class means at the head centre
    double head_ml = 0, brain_ml = 0;
    double working_spacing_mm = 0;                // isotropic grid used for an anisotropic scan; 0: none
    double envelope_ml = 0;                       // volume inside the BET surface
    bool envelope_used = false;                   // false: the surface failed, morphology alone
};

/// Brain mask of a T1 head volume with skull (any intensity range: uint8, int16, scaled),
/// on the grid of `t1`. Reports progress and honours cancellation between steps (throws
/// cf::Cancelled). Throws cf::InputError when the volume holds no head or no brain-like region.
/// Re-entrant. Takes ~8 CPU-seconds for a 1 mm 256^3 head (4-8 s on 2 idle cores).
LabelVolume skull_strip(const Volume& t1, const SkullStripParams& p = {}, const Progress* progress = nullptr,
                        SkullStripInfo* info = nullptr);

/// A check image of a mask over its volume: a 3x3 PNG montage (rows axial, coronal, sagittal;
/// three slices each through the mask), radiological display (patient right on image left),
/// mask contour in red and, when given, a reference mask contour in green. Throws InputError.
void write_mask_check_png(const Volume& v, const LabelVolume& mask, const std::filesystem::path& png,
                          const LabelVolume* reference = nullptr);

}  // namespace cf
