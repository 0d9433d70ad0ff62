#pragma once
// Bridge to the ITK skull-stripping pipeline (itk_skull_strip.cpp). Plain types only: ITK 5.2's
// bundled Eigen clashes with the system Eigen, so this header must never include Eigen.
#include <cstdint>
#include <functional>
#include <vector>

#include "itk_bridge.hpp"

namespace cf::itkb {

/// Mirrors cf::SkullStripParams (documented there).
struct SkullStripConfig {
    double background_frac = 0.1;
    double csf_gm_split = 0.25;
    double csf_split = -0.3;
    double csf_margin_mm = 6.0;
    double bright_limit = 2.0;
    double erode_mm = 2.0;
    double reconstruct_mm = 6.0;
    double bias_sigma_mm = 20.0;
    double close_mm = 8.0;
    double final_dilate_mm = 0.0;
    double envelope_margin_mm = 3.0;
    double open_mm = 3.0;
    double support_gate_mm = 0.0;
    bool csf_geodesic = false;
    double min_brain_ml = 500.0;
    double max_brain_ml = 2500.0;
};

/// Throws cf::InputError naming the first field out of its documented range.
void check_config(const SkullStripConfig& cfg);

/// What the pipeline found, for logs and tuning.
struct SkullStripReport {
    double p02 = 0, p98 = 0;                  // robust intensity range of the volume
    double t_background = 0, t_low = 0, t_high = 0, t_csf = 0;
    double csf = 0, gm = 0, wm = 0;           // class means in the central sphere
    double head_ml = 0, brain_ml = 0;
};

/// Called between steps with a stage name and the fraction done; may throw (cancellation).
using StepFn = std::function<void(const char* stage, double fraction)>;

/// Binary brain mask (0/1) of a T1 head on `grid` (only dims and spacing are used). When
/// `envelope` (0/1 on the grid, e.g. the BET surface) is given, brain tissue and CSF are only
/// taken within cfg.envelope_margin_mm of it. `support` (0/1 on the grid, may be null) is taken
/// as brain before the closing.
/// Throws cf::InputError when no head or no brain-like region is found.
void skull_strip_mask(const Grid& grid, const float* voxels, const uint8_t* envelope, const uint8_t* support,
                      const SkullStripConfig& cfg,
                      const StepFn& step, std::vector<uint8_t>& mask, SkullStripReport& report);

/// Moves the edge of `mask` (0/1 on `grid`) outwards downhill into the intensity valley outside it:
/// a voxel next to the edge joins while it is darker than its neighbour inside (intensities
/// lightly smoothed) and not brighter than `cap`, for at most `max_mm` (in steps of the finest
/// axis); enclosed cavities are filled afterwards. For coarse grids, where the mask's edge
/// otherwise lies in tissue-grey partial volume and the ray caster shows its voxel staircase.
void valley_snap(const Grid& grid, const float* voxels, std::vector<uint8_t>& mask, double cap, double max_mm);

}  // namespace cf::itkb
