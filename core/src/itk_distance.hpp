#pragma once
// Bridge to ITK's distance maps for render_grid.cpp. Plain types only (see itk_bridge.hpp).
#include <array>
#include <cstdint>
#include <vector>

namespace cf::itkb {

/// phi = (distance to the nearest voxel of the mask) - (distance to the nearest voxel outside
/// it), in mm with `spacing_mm` (the caller's, which may stretch an axis): negative exactly on
/// the mask's voxels, zero midway between an edge voxel and its outside neighbour. In double:
/// a stretched axis makes distances of 1e4 mm whose in-plane part the caller recovers. `mask`
/// (0/1, x fastest) must hold voxels both inside and outside.
void midpoint_signed_distance(const std::array<int, 3>& dims, const std::array<double, 3>& spacing_mm,
                              const uint8_t* mask, std::vector<double>& phi);

}  // namespace cf::itkb
