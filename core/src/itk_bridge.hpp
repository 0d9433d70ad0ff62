#pragma once
// The one place ITK is reached from. ITK 5.2 ships its own, un-namespaced copy of Eigen
// that clashes with the system Eigen in one translation unit, so ITK code lives in
// itk_*.cpp files that see only these plain types, never an Eigen header.
#include <array>
#include <cstdint>
#include <string>
#include <vector>

namespace cf::itkb {

struct Grid {
    std::array<int, 3> dims{0, 0, 0};
    std::array<double, 3> spacing{1, 1, 1};
    std::array<double, 3> origin{0, 0, 0};
    std::array<double, 9> direction{1, 0, 0, 0, 1, 0, 0, 0, 1};  // row-major, columns = axes
    size_t count() const { return size_t(dims[0]) * dims[1] * dims[2]; }
};

/// Reads a file (format chosen by extension) or a DICOM series folder. Throws InputError.
/// `check` is called with the header's grid before voxels are read (it may throw).
void read_float(const std::string& path, Grid& grid, std::vector<float>& voxels,
                void (*check)(const Grid&, const std::string&));
void write_float(const std::string& path, const Grid& grid, const float* voxels);
void write_u8(const std::string& path, const Grid& grid, const uint8_t* voxels);

}  // namespace cf::itkb
