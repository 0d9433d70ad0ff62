#pragma once
// Volumes in world = LPS millimetres, read and written through ITK.
// A volume keeps its own voxel grid (spacing, origin, direction cosines); consumers map
// world points to continuous indices with index_from_world(), so oblique and flipped
// volumes land where they belong without resampling.
#include <Eigen/Geometry>
#include <array>
#include <cstdint>
#include <filesystem>
#include <string>
#include <vector>

namespace cf {

struct VolumeGeometry {
    std::array<int, 3> dims{0, 0, 0};                       // voxels along i, j, k (i fastest)
    Eigen::Vector3d spacing_mm = Eigen::Vector3d::Ones();
    Eigen::Vector3d origin_mm = Eigen::Vector3d::Zero();    // LPS position of voxel (0,0,0)
    Eigen::Matrix3d direction = Eigen::Matrix3d::Identity();  // columns: LPS direction of i, j, k

    size_t voxel_count() const { return size_t(dims[0]) * dims[1] * dims[2]; }
    size_t linear(int i, int j, int k) const {
        return (size_t(k) * dims[1] + j) * dims[0] + i;
    }
    /// p_world_mm = world_from_index * (i, j, k)
    Eigen::Affine3d world_from_index() const;
    Eigen::Affine3d index_from_world() const { return world_from_index().inverse(); }
    Eigen::Vector3d world_from_index(const Eigen::Vector3d& ijk) const {
        return world_from_index() * ijk;
    }
    /// World-space centre of the grid.
    Eigen::Vector3d center_world_mm() const;
    bool same_grid(const VolumeGeometry& o, double tol = 1e-3) const;
};

/// A scalar volume, intensities as float (the modality's own units).
struct Volume {
    VolumeGeometry geom;
    std::vector<float> voxels;

    float at(int i, int j, int k) const { return voxels[geom.linear(i, j, k)]; }
};

/// A binary or label volume on a grid.
struct LabelVolume {
    VolumeGeometry geom;
    std::vector<uint8_t> voxels;

    uint8_t at(int i, int j, int k) const { return voxels[geom.linear(i, j, k)]; }
    size_t count_nonzero() const;
};

struct IntensityStats {
    double min = 0, max = 0, mean = 0, stddev = 0;
    double p01 = 0, p50 = 0, p99 = 0;  // percentiles 1, 50, 99
    size_t count = 0;
};

/// Sanity bounds on what a volume may be (absurd dimensions are refused before allocating).
constexpr int kMaxVolumeDim = 2048;
constexpr size_t kMaxVoxels = size_t(1024) * 1024 * 1024 / 4;  // 1 GiB of float

/// Reads NIfTI (.nii, .nii.gz), NRRD (.nrrd, .nhdr), MetaImage (.mha, .mhd), or a folder
/// holding one DICOM series. Throws InputError naming the path on any failure.
Volume load_volume(const std::filesystem::path& path);
/// Reads a mask; voxels > 0 become 1. Throws InputError.
LabelVolume load_mask(const std::filesystem::path& path);
/// Reads a mask and puts it on `grid` (nearest neighbour) when it lies on another: a mask
/// saved on its volume's grid is taken as it is. Throws InputError.
LabelVolume load_mask(const std::filesystem::path& path, const VolumeGeometry& grid);
/// Writes by extension (NIfTI, NRRD, MHA). Throws InputError on failure.
void save_volume(const Volume& v, const std::filesystem::path& path);
void save_mask(const LabelVolume& m, const std::filesystem::path& path);

/// Trilinear resampling of `v` onto `grid` (LPS world matched through both geometries).
/// Outside samples get `outside_value`.
Volume resample(const Volume& v, const VolumeGeometry& grid, float outside_value = 0.f);
/// Nearest-neighbour resampling of a mask onto `grid`.
LabelVolume resample_nearest(const LabelVolume& m, const VolumeGeometry& grid);
/// An axis-aligned (identity direction) grid with isotropic spacing covering `g`'s extent.
VolumeGeometry isotropic_grid(const VolumeGeometry& g, double spacing_mm);

/// Statistics over all voxels, or only those where mask != 0 (mask on the same grid).
IntensityStats intensity_stats(const Volume& v, const LabelVolume* mask = nullptr);

/// Dice coefficient of two masks on the same grid.
double dice(const LabelVolume& a, const LabelVolume& b);

}  // namespace cf
