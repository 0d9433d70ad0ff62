#pragma once
// Transfer functions: piecewise-linear colour and opacity over intensity, optionally
// modulated by gradient magnitude, read from JSON presets and baked to lookup tables.
#include <array>
#include <filesystem>
#include <nlohmann/json_fwd.hpp>
#include <string>
#include <vector>

#include "cortexfuse/core/volume.hpp"

namespace cf {

struct TransferFunction {
    std::string name;
    /// "normalized": control-point x in [0,1] over the volume's robust range (robust_range():
    /// from min(0, 1st percentile) to the 99.5th percentile of non-zero voxels, so 0..p99.5 for
    /// an MRI), so one preset fits any MRI scaling. "absolute": x in
    /// the volume's own units (e.g. CT Hounsfield units).
    bool normalized = true;
    std::vector<std::array<double, 4>> colour;   // x, r, g, b (0..1)
    std::vector<std::array<double, 2>> opacity;  // x, opacity per mm of ray (0..1)
    /// Optional: x = gradient magnitude in normalized units per mm, y = opacity factor.
    std::vector<std::array<double, 2>> gradient_opacity;

    /// Throws InputError(context, ...) when points are unsorted, out of range or NaN.
    void validate(const std::string& context) const;
};

TransferFunction transfer_function_from_json(const nlohmann::json& j, const std::string& context);
nlohmann::json to_json(const TransferFunction& tf);
TransferFunction load_transfer_function(const std::filesystem::path& path);
/// Built-in presets: "cortex_t1" (the seed's look: T1 intensity under the brain surface),
/// "surface_white" (white Lambert surface of the brain: the registration default), "skin",
/// "ct_bone", "fmri_hot".
TransferFunction preset_transfer_function(const std::string& name);
std::vector<std::string> preset_names();

/// A transfer function baked for one volume: `size` RGBA entries over [lo, hi] volume units.
struct BakedTransferFunction {
    double lo = 0, hi = 1;                 // intensity range covered by the table
    std::vector<std::array<float, 4>> rgba;  // r, g, b, opacity per mm
    std::vector<std::array<double, 2>> gradient_opacity;  // in volume units per mm
    bool uses_gradient() const { return !gradient_opacity.empty(); }
    float gradient_factor(float gmag_units_per_mm) const;
};

/// Resolves normalized control points against `range` (the volume's robust range) and
/// samples the piecewise-linear functions into `size` entries.
BakedTransferFunction bake(const TransferFunction& tf, double range_lo, double range_hi, int size = 1024);

/// The robust intensity range used by normalized transfer functions.
std::array<double, 2> robust_range(const Volume& v, const LabelVolume* mask = nullptr);

/// Means of three intensity classes (CSF, grey matter, white matter on a T1 inside a brain
/// mask), sorted: a 1D k-means over a histogram of `values`. Used to place a surface between
/// CSF and grey matter whatever the scanner's scaling and contrast.
std::array<double, 3> three_class_means(const std::vector<float>& values);

}  // namespace cf
