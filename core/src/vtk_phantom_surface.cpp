// Brain surface for the phantom generator: the plan's iso-surface pipeline (vtk_surface.cpp:
// flying edges at the CSF/grey level, largest component, world LPS mm, windowed-sinc
// smoothing), no decimation, plus a heavily smoothed hull for sulcal depth.
#include <vtkCellArray.h>
#include <vtkIdList.h>
#include <vtkPolyData.h>
#include <vtkSmartPointer.h>

#include <algorithm>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/surface.hpp"
#include "vtk_surface_internal.hpp"

namespace cf {
namespace {

template <class T>
using Ptr = vtkSmartPointer<T>;

}  // namespace

PhantomSurface build_phantom_surface(const Volume& t1, const LabelVolume& mask, const Progress& progress) {
    SurfaceParams sp;  // T1 level (automatic), 20 windowed-sinc iterations at 0.08
    sp.max_triangles = 0;
    sp.smooth_iterations = 20;
    sp.smooth_passband = 0.08;
    const detail::IsoSurface iso = detail::extract_brain_isosurface(t1, mask, sp, progress);
    Ptr<vtkPolyData> smooth = iso.poly;
    const float iso_level = iso.iso_level;
    Ptr<vtkPolyData> hull = detail::windowed_sinc(smooth, 100, 0.0003);
    progress("surface", 0.9);

    PhantomSurface s;
    s.iso_level = iso_level;
    const vtkIdType np = smooth->GetNumberOfPoints();
    s.mesh.vertices.resize(size_t(np));
    s.smooth_vertices.resize(size_t(np));
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (vtkIdType i = 0; i < np; ++i) {
        double p[3], q[3];
        smooth->GetPoint(i, p);
        hull->GetPoint(i, q);
        s.mesh.vertices[size_t(i)] = Eigen::Vector3f(float(p[0]), float(p[1]), float(p[2]));
        s.smooth_vertices[size_t(i)] = Eigen::Vector3f(float(q[0]), float(q[1]), float(q[2]));
        c += Eigen::Vector3d(p[0], p[1], p[2]);
    }
    s.centroid_world_mm = (c / double(std::max<vtkIdType>(np, 1))).cast<float>();
    vtkCellArray* polys = smooth->GetPolys();
    s.mesh.triangles.reserve(size_t(polys->GetNumberOfCells()));
    auto ids = Ptr<vtkIdList>::New();
    polys->InitTraversal();
    while (polys->GetNextCell(ids)) {
        if (ids->GetNumberOfIds() != 3) continue;
        s.mesh.triangles.emplace_back(int(ids->GetId(0)), int(ids->GetId(1)), int(ids->GetId(2)));
    }
    s.normals = outward_vertex_normals(s.mesh.vertices, s.mesh.triangles);
    s.smooth_normals = outward_vertex_normals(s.smooth_vertices, s.mesh.triangles);
    s.sulcal_depth_mm.resize(size_t(np));
    for (size_t i = 0; i < size_t(np); ++i)
        s.sulcal_depth_mm[i] = (s.smooth_vertices[i] - s.mesh.vertices[i]).dot(s.smooth_normals[i]);
    progress("surface", 1.0);
    return s;
}

}  // namespace cf
