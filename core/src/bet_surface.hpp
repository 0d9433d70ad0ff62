#pragma once
// A BET-like deformable brain surface (Smith 2002, "Fast robust automated brain extraction",
// Human Brain Mapping 17:143). Internal to core: skull_strip() uses it as the envelope that
// bounds the tissue segmentation (docs/skull-stripping.md). Plain types only (the ITK bridge
// includes this header and must not see Eigen).
#include <array>
#include <cstdint>
#include <functional>
#include <vector>

namespace cf::bet {

struct BetParams {
    double fractional_threshold = 0.5;  // BET's f: lower = larger brain estimate. [0.05, 0.95]
    int iterations = 1000;              // BET's default
    int subdivisions = 4;               // icosahedron subdivisions (4: 2562 vertices)
    double search_in_mm = 20.0;         // BET's d1: inward search for the local minimum
    double radius_min_mm = 3.33;        // curvature smoothing: BET's r_min, r_max
    double radius_max_mm = 10.0;
    /// A surface enclosing more than this (no brain does; the surface passed the skull) is evolved
    /// again with f raised by fraction_step, up to fraction_max.
    double max_enclosed_ml = 2300.0;
    double fraction_step = 0.1;
    double fraction_max = 0.8;
};

/// Head-size limit for the statistics: only head voxels within this height below the top of
/// the head count for the centre and radius (a long neck or shoulders in the field of view
/// would pull the starting sphere out of the cranium). `up` = superior in index-space mm.
struct HeadFrame {
    std::array<double, 3> up{0, 0, 1};
    double cranium_height_mm = 150.0;
};

/// Intensity statistics BET derives from the whole volume (as bet2: t2, t98, t, tm, COG, r).
struct BetStats {
    double t2 = 0, t98 = 0, t = 0, tm = 0;
    std::array<double, 3> cog_mm{0, 0, 0};  // in index-space millimetres (i * spacing)
    double radius_mm = 0;
    double fraction_used = 0;  // f of the surface returned
    double enclosed_ml = 0;    // volume the returned surface encloses
};

struct Mesh {
    std::vector<std::array<double, 3>> vertices_mm;  // index-space millimetres
    std::vector<std::array<int, 3>> triangles;       // counter-clockwise seen from outside
};

/// Called between iterations with the fraction done; may throw (cancellation).
using TickFn = std::function<void(double fraction)>;

/// Runs BET's surface evolution on a volume of `dims` voxels with `spacing_mm` (x fastest).
/// `stats` is computed as bet2 does, over the cranium part of the head (see HeadFrame).
Mesh bet_surface(const float* voxels, const std::array<int, 3>& dims, const std::array<double, 3>& spacing_mm,
                 const HeadFrame& frame, const BetParams& p, BetStats& stats, const TickFn& tick);

/// Voxels inside the closed mesh (scanline parity along x, voxel centres), 0/1 on the grid.
std::vector<uint8_t> fill_mesh(const Mesh& m, const std::array<int, 3>& dims, const std::array<double, 3>& spacing_mm);

}  // namespace cf::bet
