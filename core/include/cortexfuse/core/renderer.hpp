#pragma once
#include <array>
// The renderer interface: one for the CPU ray caster here, one for the EGL/GLSL backend.
// A renderer owns a prepared copy of the volume (quantised, with an empty-space map) and
// renders it from a pinhole camera pose. Thread contract: one render() at a time per
// renderer; distinct renderers are independent (the core is re-entrant).
#include <Eigen/Core>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <vector>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "cortexfuse/core/volume.hpp"

namespace cf {

/// The Lambert light's kind. A headlight lights each sample along its ray (the seed's); a
/// distant light from one direction for the whole picture (a lamp far away); a point light
/// from one place, so that its direction changes across the picture (a ring flash, a
/// headlamp, a microscope's light or a lamp near the camera: at 200-450 mm, across the
/// ROI its direction turns by as much as the rays do, about 10 deg).
enum class Light { headlight, distant, point };

struct RenderOptions {
    double sample_distance_mm = 1.0;     // step along the ray
    /// Samples lie at t = phase + n * step along each ray (t: mm from the camera). Unset, the
    /// phase is 0: the lattice moves with the camera, so a move along the viewing axis by part of
    /// a step shifts every sample by it, and where a ray grazes the surface a 2 mm step finds or
    /// misses it by turns (the similarity saw-toothed in depth). Set, the phase makes one sphere of
    /// the lattice pass through this point (world, mm): near it the samples stay where they are
    /// whatever the camera's depth. Registration anchors them at its pivot.
    std::optional<std::array<double, 3>> sample_anchor_world_mm;
    double ambient = 0.2;                // Lambert shading from a headlight at the camera
    double diffuse = 0.8;
    bool shading = true;
    /// Where the Lambert light comes from (Light). Registration estimates it from the photo: the
    /// lamp is rarely exactly at the lens. Lambert is two-sided, |n.L|, for every kind: a surface
    /// facing away from the light is lit as if it faced it (a one-sided term registered worse:
    /// docs/registration.md).
    Light light = Light::headlight;
    /// Light::distant: camera frame, pointing from the scene towards the light.
    std::array<double, 3> light_direction_camera{0, 0, -1};
    /// Light::point: the lamp's position, camera frame, mm ({0, 0, 0} is the headlight).
    std::array<double, 3> light_position_camera_mm{0, 0, 0};
    /// Show only the first crossing of the transfer function's surface level (where opacity
    /// reaches 0.5), shaded and opaque: no compositing of the samples around it. Registration
    /// uses it: a composited pixel's grey changes with where the sample lattice falls on the
    /// surface, so the similarity saw-toothed along the viewing axis; this does not.
    bool surface_only = false;
    double early_termination_alpha = 0.98;
    double coverage_alpha = 0.5;          // coverage mask and depth: where opacity reaches this
    /// CPU: start each ray where it can first meet a visible brick (the nearest brick on the
    /// edge of the visible set that projects onto its pixel), not where it enters the volume's
    /// box. The pictures are the same; false only to compare (`bench render --no-start-map`).
    bool ray_start_map = true;
    /// Which pixels to cast (row-major, width*height; nonzero: cast); null: every pixel. The
    /// CPU caster leaves the others as no hit (grey 0, depth 0, no coverage); the GLSL backend
    /// casts every pixel regardless, so a caller that leaves pixels out fills them itself (the
    /// registration interpolates them) and both backends give it the same picture. Borrowed
    /// during the call.
    const std::vector<uint8_t>* ray_mask = nullptr;
    bool want_rgb = true;                 // skip work the caller does not need
    bool want_depth = true;
    int threads = 0;                      // 0 = all cores
};

/// Images, row-major, width*height (rgb: 3 bytes a pixel).
struct RenderImage {
    int width = 0, height = 0;
    std::vector<uint8_t> rgb;
    std::vector<float> grey;       // luminance of the composited colour, 0..1
    std::vector<float> depth_mm;   // camera-frame z of the first opaque hit; 0 where none
    std::vector<uint8_t> coverage; // 1 where accumulated opacity >= coverage_alpha
};

class Renderer {
public:
    virtual ~Renderer() = default;
    /// Replaces the transfer function without re-preparing the volume.
    virtual void set_transfer_function(const TransferFunction& tf) = 0;
    virtual void render(const Intrinsics& K, const Pose& T_camera_from_world, const RenderOptions& opt,
                        RenderImage& out) = 0;
    virtual const char* name() const = 0;
};

/// The CPU ray caster. `volume` is copied (quantised); `mask`, if given (same grid), hides
/// everything outside it (skull-stripped rendering). Both are borrowed only during the call.
/// A mask on thick slices is drawn through masked_render_copy().
std::unique_ptr<Renderer> make_cpu_renderer(const Volume& volume, const TransferFunction& tf,
                                            const LabelVolume* mask = nullptr);

/// What the ray casters (CPU and GLSL) draw when a mask hides part of a volume whose grid is
/// markedly anisotropic (an axis more than 1.5x the finest: thick slices). Elsewhere they zero
/// the voxels outside the mask; on 4.8 mm slices that made the mask's edge between two slices a
/// cliff (terraces over the brain whatever the mask), and where the mask cuts tissue its voxel
/// steps show at any spacing. The copy: the same origin and direction cosines (world
/// coordinates unchanged), each thick axis cut into ceil(spacing / max(finest, 1 mm)) steps; the
/// native voxels stay knots of the copy, so its intensities (linear between them) sample
/// trilinearly as the native grid does. The mask is carried by its signed distance phi,
/// interpolated linearly (per slice when one axis is thick: shape-based interpolation) and
/// smoothed a little (sigma 1.5 mm in-plane, half a slice across), and each voxel of the copy
/// is faded towards range[0] by a ramp of phi four copy voxels wide (clamped to `range` first),
/// so the clip surface runs smoothly between slices and voxels. For the 256 x 256 x 35 DICOM
/// series: 256 x 256 x 171 voxels (45 MiB of float while a renderer is made; the CPU's
/// quantised copy 22 MiB); making the renderer takes longer (figures: docs/skull-stripping.md).
/// The renderers quantise the copy with `range` and no mask. At most kMaxRenderCopyVoxels
/// (fewer cuts beyond). nullopt, and no work, without a mask, on a grid within 1.5x, or for a
/// mask all in or all out: the volume is drawn as given.
constexpr size_t kMaxRenderCopyVoxels = size_t(48) << 20;
std::optional<Volume> masked_render_copy(const Volume& volume, const LabelVolume* mask, const std::array<double, 2>& range);

/// The sample lattice's phase in mm for a camera at `camera_world_mm`: 0 without
/// RenderOptions::sample_anchor_world_mm, else the anchor's distance from the camera modulo the
/// sample distance. Shared by the ray casters (CPU and GLSL).
double sample_lattice_phase_mm(const RenderOptions& opt, const Eigen::Vector3d& camera_world_mm);

/// Per block of `block`^3 voxels of the x-fastest grid `q` (dims), the least and greatest value
/// over the block and a one-voxel apron (the reach of trilinear interpolation); `n_blocks` gets
/// the grid of blocks (x fastest). Shared by the ray casters (CPU and GLSL).
void block_min_max(std::span<const uint16_t> q, const std::array<int, 3>& dims, int block, std::array<int, 3>& n_blocks,
                   std::vector<uint16_t>& min, std::vector<uint16_t>& max);

/// Empty-space map shared by the ray casters (CPU and GLSL): for each brick of a grid of
/// `n_bricks` (x fastest), the Chebyshev (L-infinity) distance in bricks to the nearest brick
/// with `visible` != 0, capped at `cap` (0 = visible). A ray in a brick at distance d crosses
/// the empty cube of bricks [b - (d - 1), b + d) in one jump.
std::vector<uint8_t> brick_chebyshev_distance(const std::vector<uint8_t>& visible, const std::array<int, 3>& n_bricks,
                                              int cap);

/// RayStartMap::add's group of a brick: the 4^3 bricks it shares a box with.
inline uint64_t start_map_group(const std::array<int, 3>& b) {
    return (uint64_t(uint32_t(b[2] >> 2)) << 42) | (uint64_t(uint32_t(b[1] >> 2)) << 21) | uint64_t(uint32_t(b[0] >> 2));
}

/// The bricks of `visible` (a grid of `n_bricks`, x fastest) with a brick outside the set, or
/// outside the grid, among their 26 neighbours: a ray from outside the set enters it through one
/// of them. In groups (start_map_group(), ascending), raster order within a group.
std::vector<std::array<int, 3>> frontier_bricks(const std::vector<uint8_t>& visible, const std::array<int, 3>& n_bricks);

/// Where rays may start, shared by the ray casters (CPU and GLSL). Frontier bricks are
/// projected onto a grid over the rays' normalised coordinates (x/z, y/z; about one cell per
/// 4x4 pixels), each cell keeping the nearest camera depth z of a brick that touches it. A ray
/// with unit direction d meets no visible brick before t = z / d.z, so it may start on the first
/// lattice point after that: the same samples that show anything, the same picture. Exact with
/// lens distortion, since the rays are undistorted. Valid only while the camera is outside the
/// visible bricks (callers check their box). Thread contract: one frame at a time.
class RayStartMap {
public:
    /// The grid for these unit camera-frame rays, one per pixel (pixel_rays(K), normalised).
    void set_rays(const std::vector<Eigen::Vector3f>& unit_rays, int width);
    /// Begins a frame: no brick anywhere (every start at infinity).
    void clear();
    /// Adds the frontier bricks (edge `brick_voxels`) of a volume whose voxel index maps to the
    /// camera frame by `T_camera_from_index`. False when one reaches behind the camera: then no
    /// ray may start late this frame. Bricks of one start_map_group() that follow each other
    /// (frontier_bricks()' order) are skipped together when their box cannot change the map;
    /// any order gives the same map.
    bool add(const Eigen::Matrix4d& T_camera_from_index, const std::vector<std::array<int, 3>>& frontier, int brick_voxels);
    /// The camera depth (mm) before which the ray of pixel `px` meets no frontier brick.
    float start_z(size_t px) const { return z_[cell_[px]]; }
    // The grid, for the GLSL ray caster: cells_x() * cells_y() depths, row-major; a ray's cell
    // is floor((x/z - x0, y/z - y0) * inv_cell), clamped to the grid.
    int cells_x() const { return nx_; }
    int cells_y() const { return ny_; }
    float x0() const { return x0_; }
    float y0() const { return y0_; }
    float inv_cell() const { return inv_cell_; }
    const std::vector<float>& cells() const { return z_; }
    bool empty() const { return nx_ == 0; }

private:
    struct Group {
        size_t begin, end;  // the group's bricks in the frontier
        float zmin;         // its box's nearest depth; -inf: the box reaches behind the camera
        int cx0, cx1, cy0, cy1;  // its box's cells (cx0 > cx1: reaches behind)
    };
    std::vector<Group> groups_;    // add()'s scratch
    std::vector<float> z_;         // per cell
    std::vector<uint32_t> cell_;   // per pixel
    int nx_ = 0, ny_ = 0;
    float x0_ = 0, y0_ = 0, inv_cell_ = 1;
};

}  // namespace cf
