#pragma once
// The photographic overlay: the photo texture-mapped onto the brain surface with the
// recovered pose, and the cast back from a photo pixel to the surface point it shows.
//
// Visibility of a vertex (it gets texture coordinates only if all hold): in front of the
// camera, projecting inside the image (lens distortion applied), front-facing (outward
// normal towards the camera) and not hidden behind other surface (depth test against the
// z-buffer of the whole mesh rasterised from the camera, core/rasterizer.hpp).
// The ROI (a closed cardinal spline on the photo) becomes the texture's alpha channel.
//
// Texture coordinates: u = (x + 0.5) / width, v = (y + 0.5) / height with (x, y) the
// OpenCV pixel (v grows downwards, glTF's convention; the OBJ writer flips v).
#include <Eigen/Core>
#include <filesystem>
#include <opencv2/core.hpp>
#include <optional>
#include <vector>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/rasterizer.hpp"
#include "cortexfuse/core/renderer.hpp"
#include "cortexfuse/core/roi.hpp"
#include "cortexfuse/core/surface.hpp"
#include "cortexfuse/core/volume.hpp"

namespace cf {

struct TextureParams {
    /// Depth test slack: a vertex is visible when its depth is within
    /// depth_tolerance_mm + depth_tolerance_px * (pixel footprint at its depth) of the
    /// z-buffer at its pixel. [0, 20] mm, [0, 10] px
    double depth_tolerance_mm = 0.5;
    double depth_tolerance_px = 1.5;
    /// A vertex is back-facing when normal . view direction >= -min_facing (0: any grazing
    /// vertex counts as front-facing). [-1, 1]
    double min_facing = 0.0;
};

struct TextureMapping {
    std::vector<Eigen::Vector2f> uv;     // per vertex; (0, 0) where not visible
    std::vector<Eigen::Vector2d> pixel;  // per vertex photo pixel (distorted); NaN where not visible
    std::vector<uint8_t> visible;        // 1: the camera sees this vertex
    std::vector<uint8_t> in_roi;         // 1: visible and inside the ROI (alpha >= 128)
    size_t visible_count = 0, roi_count = 0;
    size_t back_facing = 0, occluded = 0, outside_image = 0;  // why the others are not visible
};

/// Projects every vertex with the pose, intrinsics and distortion. `roi_alpha` (8-bit,
/// photo size, may be empty) marks the exposed cortex. Throws InputError for a mesh with no
/// triangles, a bad camera, or a pose that does not look at the mesh (no vertex visible:
/// the camera points away from the brain or sits inside it).
TextureMapping map_texture(const SurfaceMesh& mesh, const Intrinsics& K, const Pose& T_camera_from_world,
                           const cv::Mat& roi_alpha = {}, const TextureParams& params = {});

/// What a photo pixel shows: the first surface point along its ray.
struct SurfaceHit {
    Eigen::Vector3d p_world_mm;
    Eigen::Vector3d normal_world;  // outward, interpolated
    int triangle = -1;
    Eigen::Vector3d bary;          // barycentric weights on the triangle
    double depth_mm = 0;           // camera-frame z
};

/// Casts the ray of photo pixel `pixel` (distorted, OpenCV) through the pose and returns the
/// nearest surface point it hits (exact ray-triangle intersection, Möller–Trumbore), or
/// nullopt when the ray misses the mesh.
std::optional<SurfaceHit> cast_back(const SurfaceMesh& mesh, const Intrinsics& K, const Pose& T_camera_from_world,
                                    const Eigen::Vector2d& pixel);

/// The craniotomy of a CT fused with the photo: which CT voxels stay shown so that the skull
/// does not cover the photographed cortex from the camera's pose (the bone flap is off in the
/// photo). A voxel of `ct_grid` (the CT's own grid, or the CT resampled on the T1 grid; world
/// LPS mm either way) is hidden (0) when all hold: it lies more than 1 mm in front of the lens
/// (camera-frame z > 1 mm), it projects (lens distortion applied, nearest pixel) inside the
/// photo onto a pixel that is inside the ROI (`roi_alpha` >= 128; an empty `roi_alpha` means
/// the whole photo) and where `brain_surface_world_mm` (the brain surface, rasterised from the
/// camera, core/rasterizer.hpp) is seen, and its depth is less than that surface depth +
/// `depth_margin_mm` (everything between the lens and depth_margin_mm below the cortex).
/// Every other voxel is shown (1). The result has `ct_grid`'s geometry, to pass as the CT
/// layer's mask (FusionRenderer::add_layer); it is the caller's (a value, nothing kept).
/// `roi_alpha`: 8-bit, K.width x K.height, or empty. depth_margin_mm: [0, 50] mm.
/// Throws InputError naming the input: a mesh with no triangles, a bad camera, a pose that is
/// not rigid, an alpha mask of another size or type, a margin out of range, an empty grid.
/// Cost: one rasterisation plus one projection per voxel (single thread).
LabelVolume craniotomy_keep_mask(const VolumeGeometry& ct_grid, const SurfaceMesh& brain_surface_world_mm,
                                 const Intrinsics& K, const Pose& T_camera_from_world, const cv::Mat& roi_alpha,
                                 double depth_margin_mm = 3.0);

/// The photo with the ROI as alpha: 8-bit BGRA (OpenCV order) for a PNG texture.
cv::Mat texture_rgba(const cv::Mat& photo_bgr, const cv::Mat& roi_alpha);

/// Exports. The textured part holds the triangles whose three vertices are in the ROI; the
/// rest of the surface is written untextured (a grey material), so the model stays whole.
/// OBJ + MTL + PNG: positions in world LPS mm (as the PLY). Throws InputError; atomic per file.
void write_textured_obj(const SurfaceMesh& mesh, const TextureMapping& tm, const cv::Mat& texture_bgra,
                        const std::filesystem::path& obj_path);
/// Binary glTF 2.0 (.glb) with the PNG texture embedded. glTF's frame is metres with +Y up:
/// x_gltf = -x_lps (patient right), y_gltf = z_lps (superior), z_gltf = y_lps (posterior),
/// scaled by 0.001 (a rotation, handedness kept).
void write_textured_glb(const SurfaceMesh& mesh, const TextureMapping& tm, const cv::Mat& texture_bgra,
                        const std::filesystem::path& glb_path);

/// The fused picture: the volume rendering (any Renderer, e.g. the CPU ray caster with the
/// plan's transfer functions) from (K_view, T_view), with the textured surface blended over
/// it at `opacity` (0..1; the seed shows 0.5) times the ROI alpha, composited by depth: the
/// photo shows where the textured surface is in front of, or within `depth_slack_mm` of,
/// the volume's first opaque hit. 8-bit BGR of K_view's size.
cv::Mat render_fused(Renderer& volume, const SurfaceMesh& mesh, const TextureMapping& tm, const cv::Mat& texture_bgra,
                     const Intrinsics& K_view, const Pose& T_view, double opacity, double depth_slack_mm = 3.0,
                     const RenderOptions& options = {});

/// render_fused in two steps, so that a caller can keep the passes of a view and blend them
/// again at another opacity (the fused view's opacity slider): the volume rendering (RGB and
/// first-hit depth) and the surface's geometry buffers from (K_view, T_view) ...
struct FusedPasses {
    RenderImage volume;
    RasterBuffers surface;
};
FusedPasses render_fused_passes(Renderer& volume, const SurfaceMesh& mesh, const Intrinsics& K_view, const Pose& T_view,
                                const RenderOptions& options = {});
/// ... and the picture from them: the same pixels render_fused gives for the same arguments.
cv::Mat composite_fused(const FusedPasses& passes, const SurfaceMesh& mesh, const TextureMapping& tm, const cv::Mat& texture_bgra,
                        double opacity, double depth_slack_mm = 3.0);

/// A free viewpoint: the camera orbited about `pivot_world_mm` by yaw (about the camera's
/// vertical axis) and pitch (about its horizontal axis), distance kept.
Pose orbit_pose(const Pose& T_camera_from_world, const Eigen::Vector3d& pivot_world_mm, double yaw_deg, double pitch_deg);

}  // namespace cf
