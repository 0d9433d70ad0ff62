#pragma once
// The brain surface mesh of the plan: VTK flying edges on the skull-stripped T1 (or on the
// mask), windowed-sinc smoothing, quadric decimation to a triangle budget, consistent
// outward normals. Vertices are in world LPS mm: VTK 9.1's image filters know no direction
// matrix, so the iso-surface is extracted in index space and mapped through the volume's
// own geometry (direction cosines, spacing, origin) before smoothing.
//
// Mesh files (PLY, VTP, STL, OBJ) hold the same LPS millimetres. 3D Slicer reads a
// "SPACE=LPS" header comment in PLY files (written here); for OBJ and STL, load them in
// Slicer with the coordinate system set to LPS.
#include <Eigen/Core>
#include <filesystem>
#include <limits>
#include <vector>

#include "cortexfuse/core/progress.hpp"
#include "cortexfuse/core/rasterizer.hpp"
#include "cortexfuse/core/volume.hpp"

namespace cf {

/// A triangle mesh in world LPS mm with outward unit normals per vertex and triangles
/// wound counter-clockwise seen from outside (right-hand rule gives the outward normal).
struct SurfaceMesh {
    std::vector<Eigen::Vector3f> vertices;   // world LPS mm
    std::vector<Eigen::Vector3f> normals;    // outward, unit, per vertex (may be empty)
    std::vector<Eigen::Vector3i> triangles;

    RasterMesh raster() const { return RasterMesh{vertices, triangles}; }
    /// Throws InputError(context, ...) when there are no triangles or an index is out of range.
    void validate(const std::string& context) const;
};

struct SurfaceParams {
    /// What the iso-surface is taken of. T1Level: the skull-stripped T1 at the CSF / grey
    /// matter boundary (the cortex a photo shows: gyri and sulci); Mask: the mask's envelope.
    enum class Source { T1Level, Mask } source = Source::T1Level;
    /// T1 intensity of the surface; NaN = automatic: between the CSF and grey-matter class
    /// means found inside the mask (0.65 csf + 0.35 gm), so sulci stay narrow.
    double iso_level = std::numeric_limits<double>::quiet_NaN();
    /// Gaussian pre-smoothing of the image, voxels (noise; the mask source uses >= 1). [0, 5]
    double presmooth_sigma_vox = 0.7;
    /// Windowed-sinc smoothing (VTK): iterations [0, 500] and pass band (0, 2].
    int smooth_iterations = 20;
    double smooth_passband = 0.08;
    /// Triangle budget after quadric decimation; 0 = keep all. [0] or [1000, 1e8]
    int max_triangles = 200000;
    /// Keep only the largest connected piece (drops islands of noise).
    bool largest_component = true;

    /// Throws InputError("surface " + field, ...) when out of range.
    void validate() const;
};

/// What build_brain_surface() did (for plan.json).
struct SurfaceInfo {
    double iso_level = 0;
    size_t triangles_extracted = 0, triangles = 0, vertices = 0;
    double seconds = 0;
};

/// Builds the brain surface from a T1 and its brain mask on the same grid (for
/// Source::Mask the T1 is only used for its grid). Throws InputError when the mask is
/// empty, on another grid, or yields no surface. Reports progress, honours cancellation.
SurfaceMesh build_brain_surface(const Volume& t1, const LabelVolume& mask, const SurfaceParams& params = {},
                                const Progress& progress = {}, SurfaceInfo* info = nullptr);

/// Writes by extension: .ply (binary, with a SPACE=LPS comment), .vtp, .stl (binary), .obj.
/// Atomic (temporary file + rename). Throws InputError.
void save_mesh(const SurfaceMesh& mesh, const std::filesystem::path& path);
/// Reads .ply, .vtp, .stl or .obj (polygons triangulated, normals recomputed when absent).
/// Throws InputError naming the file (missing, unreadable, no triangles).
SurfaceMesh load_mesh(const std::filesystem::path& path);

/// Area-weighted vertex normals, flipped as a whole to point away from the centroid.
std::vector<Eigen::Vector3f> outward_vertex_normals(const std::vector<Eigen::Vector3f>& vertices,
                                                    const std::vector<Eigen::Vector3i>& triangles);

}  // namespace cf
