#pragma once
// Bridge to ITK's v4 registration framework (itk_coregister.cpp). Plain types only: ITK 5.2's
// bundled Eigen clashes with the system Eigen, so this header must never include Eigen.
#include <array>
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include "itk_bridge.hpp"

namespace cf::itkb {

/// Mirrors cf::CoregParams (documented there).
struct CoregConfig {
    int metric = 0;  // 0 Mattes MI, 1 joint-histogram MI
    int bins = 32;
    std::vector<int> shrink{4, 2, 1};
    std::vector<double> smooth_mm{2.0, 1.0, 0.0};
    std::vector<int> iterations{200, 100, 50};
    double sampling = 0.05;
    double max_step = 2.0;        // first step of the regular-step gradient descent, mm-equivalent
    double min_step = 1e-3;
    double relaxation = 0.5;
    uint32_t seed = 1;
    // Initial Euler parameters (rx, ry, rz rad, tx, ty, tz mm) about `center` (fixed world mm).
    std::array<double, 6> initial{0, 0, 0, 0, 0, 0};
    std::array<double, 3> center{0, 0, 0};
};

struct CoregLevel {
    int iterations = 0;
    double metric = 0;
    double seconds = 0;
    std::string stop;
};

struct CoregOutput {
    std::array<double, 6> params{};   // Euler3D (rx, ry, rz, tx, ty, tz), ITK convention
    std::array<double, 3> center{};
    std::array<double, 9> matrix{};   // row-major: p_moving = matrix * p_fixed + offset
    std::array<double, 3> offset{};
    double metric = 0;
    std::vector<CoregLevel> levels;
};

/// Called per optimiser iteration with the level and fraction done; returning false stops
/// the registration (cancellation).
using CoregStepFn = std::function<bool(int level, double fraction)>;

/// Rigid registration, maps fixed world points to moving world points. `fixed_mask`
/// (0/1 on the fixed grid, may be null) limits where the metric samples.
void coregister_rigid(const Grid& fg, const float* fixed, const Grid& mg, const float* moving, const uint8_t* fixed_mask,
                      const CoregConfig& cfg, const CoregStepFn& step, CoregOutput& out);

/// Matrix and offset of an Euler3D transform (ITK's convention, ComputeZYX off).
void euler_matrix(const std::array<double, 6>& params, const std::array<double, 3>& center, std::array<double, 9>& matrix,
                  std::array<double, 3>& offset);

/// Writes an Euler3DTransform (from matrix + offset, centre kept) as .tfm/.txt (ITK text) or
/// .h5 / .hdf5 (ITK HDF5). Throws InputError.
void write_rigid_transform(const std::string& path, const std::array<double, 9>& matrix, const std::array<double, 3>& offset,
                           const std::array<double, 3>& center);
/// Reads the first transform of an ITK transform file (any matrix-offset transform: Euler,
/// Versor, Affine...). Throws InputError.
void read_rigid_transform(const std::string& path, std::array<double, 9>& matrix, std::array<double, 3>& offset);

/// Resamples `moving` onto `out_grid` through p_moving = matrix * p_out + offset; linear or
/// nearest-neighbour interpolation; `outside` where the point leaves the moving volume.
void resample_transformed(const Grid& mg, const float* moving, const std::array<double, 9>& matrix,
                          const std::array<double, 3>& offset, const Grid& out_grid, bool nearest, float outside,
                          std::vector<float>& out);

}  // namespace cf::itkb

namespace cf::itkb {
/// Connected components (26-connected) of a 0/1 mask; components smaller than
/// `min_voxels` are removed (ITK ConnectedComponentImageFilter + RelabelComponentImageFilter).
/// Returns the number of components kept.
int keep_clusters(const Grid& g, std::vector<uint8_t>& mask, int min_voxels);
/// Gaussian smoothing in place, sigma in mm along every axis (ITK's recursive Gaussian,
/// SmoothingRecursiveGaussianImageFilter, spacing-aware). sigma_mm <= 0 leaves it as it is.
void smooth_gaussian(const Grid& g, std::vector<float>& voxels, double sigma_mm);
}  // namespace cf::itkb
