#pragma once
// Shared VTK surface steps of the plan's brain surface (vtk_surface.cpp) and the phantom
// generator's surface (vtk_phantom_surface.cpp): one iso-surface pipeline, two users.
#include <vtkPolyData.h>
#include <vtkSmartPointer.h>

#include "cortexfuse/core/surface.hpp"

namespace cf::detail {

struct IsoSurface {
    vtkSmartPointer<vtkPolyData> poly;  // world LPS mm, triangles, smoothed, not decimated
    float iso_level = 0;
    size_t triangles_extracted = 0;
};

/// Crops to the mask, pre-smooths, runs flying edges in index space, keeps the largest
/// piece, maps to world LPS mm through t1.geom and applies the windowed-sinc smoothing of
/// `p` (decimation and normals are not done here). Progress fractions 0 .. 0.7 of "surface".
IsoSurface extract_brain_isosurface(const Volume& t1, const LabelVolume& mask, const SurfaceParams& p,
                                    const Progress& progress);

vtkSmartPointer<vtkPolyData> windowed_sinc(vtkPolyData* in, int iterations, double passband);

}  // namespace cf::detail
