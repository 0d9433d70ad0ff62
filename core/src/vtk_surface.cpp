// Brain surface mesh through VTK: flying edges, windowed-sinc smoothing, quadric
// decimation, normals; mesh files through VTK's readers and writers.
#include <vtkCellArray.h>
#include <vtkCleanPolyData.h>
#include <vtkFlyingEdges3D.h>
#include <vtkFloatArray.h>
#include <vtkIdList.h>
#include <vtkImageData.h>
#include <vtkOBJReader.h>
#include <vtkOBJWriter.h>
#include <vtkPLYReader.h>
#include <vtkPLYWriter.h>
#include <vtkPointData.h>
#include <vtkPoints.h>
#include <vtkPolyDataConnectivityFilter.h>
#include <vtkPolyDataNormals.h>
#include <vtkQuadricDecimation.h>
#include <vtkSTLReader.h>
#include <vtkSTLWriter.h>
#include <vtkTriangleFilter.h>
#include <vtkWindowedSincPolyDataFilter.h>
#include <vtkXMLPolyDataReader.h>
#include <vtkXMLPolyDataWriter.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <system_error>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "vtk_surface_internal.hpp"

namespace cf {
namespace {

template <class T>
using Ptr = vtkSmartPointer<T>;

/// Separable Gaussian blur of a float grid (nx, ny, nz), sigma in voxels.
void gaussian_blur3(std::vector<float>& a, int nx, int ny, int nz, double sigma) {
    const int r = std::max(1, int(std::ceil(2.5 * sigma)));
    std::vector<float> k(size_t(2 * r + 1));
    float ks = 0;
    for (int i = -r; i <= r; ++i) ks += k[size_t(i + r)] = float(std::exp(-0.5 * i * i / (sigma * sigma)));
    for (auto& x : k) x /= ks;
    std::vector<float> line;
    const std::array<int, 3> n{nx, ny, nz};
    const std::array<size_t, 3> stride{1, size_t(nx), size_t(nx) * ny};
    for (int axis = 0; axis < 3; ++axis) {
        const int len = n[size_t(axis)];
        line.resize(size_t(len));
        const int o1 = axis == 0 ? 1 : 0, o2 = axis == 2 ? 1 : 2;
        for (int b = 0; b < n[size_t(o2)]; ++b)
            for (int a0 = 0; a0 < n[size_t(o1)]; ++a0) {
                const size_t base = size_t(a0) * stride[size_t(o1)] + size_t(b) * stride[size_t(o2)];
                const size_t s = stride[size_t(axis)];
                for (int i = 0; i < len; ++i) line[size_t(i)] = a[base + size_t(i) * s];
                for (int i = 0; i < len; ++i) {
                    float acc = 0;
                    for (int j = -r; j <= r; ++j) {
                        const int ii = std::clamp(i + j, 0, len - 1);
                        acc += k[size_t(j + r)] * line[size_t(ii)];
                    }
                    a[base + size_t(i) * s] = acc;
                }
            }
    }
}

SurfaceMesh from_polydata(vtkPolyData* pd, bool take_normals) {
    SurfaceMesh m;
    const vtkIdType np = pd->GetNumberOfPoints();
    m.vertices.resize(size_t(np));
    for (vtkIdType i = 0; i < np; ++i) {
        double p[3];
        pd->GetPoint(i, p);
        m.vertices[size_t(i)] = Eigen::Vector3f(float(p[0]), float(p[1]), float(p[2]));
    }
    vtkCellArray* polys = pd->GetPolys();
    if (polys) {
        m.triangles.reserve(size_t(polys->GetNumberOfCells()));
        auto ids = Ptr<vtkIdList>::New();
        polys->InitTraversal();
        while (polys->GetNextCell(ids)) {
            if (ids->GetNumberOfIds() != 3) continue;
            m.triangles.emplace_back(int(ids->GetId(0)), int(ids->GetId(1)), int(ids->GetId(2)));
        }
    }
    vtkDataArray* n = take_normals ? pd->GetPointData()->GetNormals() : nullptr;
    if (n && n->GetNumberOfTuples() == np && n->GetNumberOfComponents() == 3) {
        m.normals.resize(size_t(np));
        for (vtkIdType i = 0; i < np; ++i) {
            double q[3];
            n->GetTuple(i, q);
            m.normals[size_t(i)] = Eigen::Vector3f(float(q[0]), float(q[1]), float(q[2])).normalized();
        }
    }
    return m;
}

Ptr<vtkPolyData> to_polydata(const SurfaceMesh& m) {
    auto pts = Ptr<vtkPoints>::New();
    pts->SetDataTypeToFloat();
    pts->SetNumberOfPoints(vtkIdType(m.vertices.size()));
    for (size_t i = 0; i < m.vertices.size(); ++i)
        pts->SetPoint(vtkIdType(i), m.vertices[i].x(), m.vertices[i].y(), m.vertices[i].z());
    auto cells = Ptr<vtkCellArray>::New();
    for (const auto& t : m.triangles) {
        const vtkIdType ids[3] = {t[0], t[1], t[2]};
        cells->InsertNextCell(3, ids);
    }
    auto pd = Ptr<vtkPolyData>::New();
    pd->SetPoints(pts);
    pd->SetPolys(cells);
    if (m.normals.size() == m.vertices.size()) {
        auto n = Ptr<vtkFloatArray>::New();
        n->SetName("Normals");
        n->SetNumberOfComponents(3);
        n->SetNumberOfTuples(vtkIdType(m.normals.size()));
        for (size_t i = 0; i < m.normals.size(); ++i) n->SetTuple3(vtkIdType(i), m.normals[i].x(), m.normals[i].y(), m.normals[i].z());
        pd->GetPointData()->SetNormals(n);
    }
    return pd;
}

std::string lower_ext(const std::filesystem::path& p) {
    std::string e = p.extension().string();
    std::transform(e.begin(), e.end(), e.begin(), [](unsigned char c) { return char(std::tolower(c)); });
    return e;
}

}  // namespace

namespace detail {

Ptr<vtkPolyData> windowed_sinc(vtkPolyData* in, int iterations, double passband) {
    auto f = Ptr<vtkWindowedSincPolyDataFilter>::New();
    f->SetInputData(in);
    f->SetNumberOfIterations(iterations);
    f->SetPassBand(passband);
    f->NormalizeCoordinatesOn();
    f->BoundarySmoothingOff();
    f->FeatureEdgeSmoothingOff();
    f->NonManifoldSmoothingOn();
    f->Update();
    Ptr<vtkPolyData> out = f->GetOutput();
    return out;
}

IsoSurface extract_brain_isosurface(const Volume& t1, const LabelVolume& mask, const SurfaceParams& p,
                                    const Progress& progress) {
    if (!mask.geom.same_grid(t1.geom))
        throw InputError("brain mask", "not on the volume's grid (dimensions, spacing, origin and direction must match)");
    if (mask.voxels.size() != mask.geom.voxel_count() || t1.voxels.size() != t1.geom.voxel_count())
        throw InputError("brain mask", "voxel count does not match its grid");
    const auto& d = t1.geom.dims;
    // Bounding box of the mask, with a margin.
    int lo[3] = {d[0], d[1], d[2]}, hi[3] = {-1, -1, -1};
    size_t count = 0;
    for (int k = 0; k < d[2]; ++k)
        for (int j = 0; j < d[1]; ++j)
            for (int i = 0; i < d[0]; ++i)
                if (mask.at(i, j, k)) {
                    ++count;
                    lo[0] = std::min(lo[0], i), hi[0] = std::max(hi[0], i);
                    lo[1] = std::min(lo[1], j), hi[1] = std::max(hi[1], j);
                    lo[2] = std::min(lo[2], k), hi[2] = std::max(hi[2], k);
                }
    if (count < 1000) throw InputError("brain mask", "empty or too small (" + std::to_string(count) + " voxels)");
    progress("surface", 0.05);
    progress.check();
    constexpr int margin = 3;
    for (int a = 0; a < 3; ++a) {
        lo[a] = std::max(0, lo[a] - margin);
        hi[a] = std::min(d[size_t(a)] - 1, hi[a] + margin);
    }
    const int nx = hi[0] - lo[0] + 1, ny = hi[1] - lo[1] + 1, nz = hi[2] - lo[2] + 1;

    const bool use_mask = p.source == SurfaceParams::Source::Mask;
    std::vector<float> img(size_t(nx) * ny * nz, 0.f), inside;
    if (!use_mask) inside.reserve(count);
    for (int k = 0; k < nz; ++k)
        for (int j = 0; j < ny; ++j)
            for (int i = 0; i < nx; ++i)
                if (mask.at(i + lo[0], j + lo[1], k + lo[2])) {
                    const float x = use_mask ? 1.f : t1.at(i + lo[0], j + lo[1], k + lo[2]);
                    img[(size_t(k) * ny + j) * nx + i] = x;
                    if (!use_mask) inside.push_back(x);
                }
    float iso = 0.5f;
    if (!use_mask) {
        if (std::isfinite(p.iso_level)) {
            iso = float(p.iso_level);
        } else {
            const auto means = three_class_means(inside);
            // Grey matter / CSF boundary, towards CSF so that the surface wraps the gyri and
            // sulci stay narrow, as on the exposed cortex.
            iso = float(0.65 * means[0] + 0.35 * means[1]);
        }
    }
    const double sigma = use_mask ? std::max(1.0, p.presmooth_sigma_vox) : p.presmooth_sigma_vox;
    if (sigma > 0) gaussian_blur3(img, nx, ny, nz, sigma);
    progress("surface", 0.2);
    progress.check();

    auto image = Ptr<vtkImageData>::New();
    image->SetDimensions(nx, ny, nz);
    image->SetSpacing(1, 1, 1);
    image->SetOrigin(lo[0], lo[1], lo[2]);  // index space of the full volume
    auto scalars = Ptr<vtkFloatArray>::New();
    scalars->SetNumberOfComponents(1);
    scalars->SetNumberOfTuples(vtkIdType(img.size()));
    std::copy(img.begin(), img.end(), scalars->GetPointer(0));  // VTK order: x fastest, like ours
    image->GetPointData()->SetScalars(scalars);

    auto fe = Ptr<vtkFlyingEdges3D>::New();
    fe->SetInputData(image);
    fe->SetValue(0, iso);
    fe->ComputeNormalsOff();
    fe->ComputeGradientsOff();
    fe->ComputeScalarsOff();
    fe->Update();
    progress("surface", 0.4);
    progress.check();

    Ptr<vtkPolyData> pd;
    auto tri = Ptr<vtkTriangleFilter>::New();
    if (p.largest_component) {
        auto conn = Ptr<vtkPolyDataConnectivityFilter>::New();
        conn->SetInputConnection(fe->GetOutputPort());
        conn->SetExtractionModeToLargestRegion();
        auto clean = Ptr<vtkCleanPolyData>::New();
        clean->SetInputConnection(conn->GetOutputPort());
        clean->PointMergingOff();  // only drop unused points
        tri->SetInputConnection(clean->GetOutputPort());
    } else {
        tri->SetInputConnection(fe->GetOutputPort());
    }
    tri->Update();
    pd = tri->GetOutput();
    if (pd->GetNumberOfPoints() < 100 || pd->GetNumberOfCells() < 100)
        throw InputError("brain mask", "no brain surface found at T1 level " + std::to_string(iso));

    // Index space -> world LPS mm (direction cosines and spacing), before smoothing.
    const Eigen::Affine3d W = t1.geom.world_from_index();
    vtkPoints* pts = pd->GetPoints();
    for (vtkIdType i = 0; i < pts->GetNumberOfPoints(); ++i) {
        double q[3];
        pts->GetPoint(i, q);
        const Eigen::Vector3d w = W * Eigen::Vector3d(q[0], q[1], q[2]);
        pts->SetPoint(i, w.x(), w.y(), w.z());
    }
    progress("surface", 0.55);
    progress.check();

    IsoSurface out;
    out.iso_level = iso;
    out.triangles_extracted = size_t(pd->GetNumberOfCells());
    out.poly = p.smooth_iterations > 0 ? windowed_sinc(pd, p.smooth_iterations, p.smooth_passband) : pd;
    progress("surface", 0.7);
    progress.check();
    return out;
}

}  // namespace detail

void SurfaceMesh::validate(const std::string& context) const {
    if (triangles.empty()) throw InputError(context, "mesh has no triangles");
    const int n = int(vertices.size());
    for (const auto& t : triangles)
        for (int q = 0; q < 3; ++q)
            if (t[q] < 0 || t[q] >= n) throw InputError(context, "triangle index out of range");
    if (!normals.empty() && normals.size() != vertices.size())
        throw InputError(context, "normals do not match the vertices");
    for (const auto& v : vertices)
        if (!v.allFinite()) throw InputError(context, "non-finite vertex coordinate");
}

void SurfaceParams::validate() const {
    if (!(presmooth_sigma_vox >= 0 && presmooth_sigma_vox <= 5))
        throw InputError("surface presmooth_sigma_vox", "must be in [0, 5]");
    if (smooth_iterations < 0 || smooth_iterations > 500)
        throw InputError("surface smooth_iterations", "must be in [0, 500]");
    if (!(smooth_passband > 0 && smooth_passband <= 2)) throw InputError("surface smooth_passband", "must be in (0, 2]");
    if (max_triangles != 0 && (max_triangles < 1000 || max_triangles > 100000000))
        throw InputError("surface max_triangles", "must be 0 (no decimation) or in [1000, 1e8]");
    if (!std::isnan(iso_level) && !std::isfinite(iso_level)) throw InputError("surface iso_level", "must be finite");
}

std::vector<Eigen::Vector3f> outward_vertex_normals(const std::vector<Eigen::Vector3f>& V,
                                                    const std::vector<Eigen::Vector3i>& F) {
    std::vector<Eigen::Vector3f> N(V.size(), Eigen::Vector3f::Zero());
    for (const auto& f : F) {
        const Eigen::Vector3f n = (V[size_t(f[1])] - V[size_t(f[0])]).cross(V[size_t(f[2])] - V[size_t(f[0])]);
        for (int q = 0; q < 3; ++q) N[size_t(f[q])] += n;  // area-weighted
    }
    for (auto& n : N) {
        const float l = n.norm();
        n = l > 0 ? Eigen::Vector3f(n / l) : Eigen::Vector3f(0, 0, 1);
    }
    // Outward on the whole: away from the centroid on average (closed surfaces).
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (const auto& v : V) c += v.cast<double>();
    c /= double(std::max<size_t>(V.size(), 1));
    double s = 0;
    for (size_t i = 0; i < V.size(); ++i) s += double(N[i].dot(V[i] - c.cast<float>()));
    if (s < 0)
        for (auto& n : N) n = -n;
    return N;
}

SurfaceMesh build_brain_surface(const Volume& t1, const LabelVolume& mask, const SurfaceParams& p,
                                const Progress& progress, SurfaceInfo* info) {
    p.validate();
    const auto t0 = std::chrono::steady_clock::now();
    detail::IsoSurface iso = detail::extract_brain_isosurface(t1, mask, p, progress);
    Ptr<vtkPolyData> pd = iso.poly;
    const vtkIdType ncells = pd->GetNumberOfCells();
    if (p.max_triangles > 0 && ncells > p.max_triangles) {
        // Quadric decimation keeps the shape best per triangle spent (Garland & Heckbert).
        auto dec = Ptr<vtkQuadricDecimation>::New();
        dec->SetInputData(pd);
        dec->SetTargetReduction(1.0 - double(p.max_triangles) / double(ncells));
        dec->VolumePreservationOn();
        dec->Update();
        pd = dec->GetOutput();
    }
    progress("surface", 0.85);
    progress.check();
    // Consistent winding, outward orientation (the surface is closed), point normals.
    auto nf = Ptr<vtkPolyDataNormals>::New();
    nf->SetInputData(pd);
    nf->SplittingOff();
    nf->ConsistencyOn();
    nf->AutoOrientNormalsOn();
    nf->ComputePointNormalsOn();
    nf->ComputeCellNormalsOff();
    nf->Update();
    SurfaceMesh m = from_polydata(nf->GetOutput(), true);
    if (m.triangles.empty()) throw InputError("brain mask", "the surface has no triangles after decimation");
    if (m.normals.size() != m.vertices.size()) m.normals = outward_vertex_normals(m.vertices, m.triangles);
    progress("surface", 1.0);
    if (info) {
        info->iso_level = iso.iso_level;
        info->triangles_extracted = iso.triangles_extracted;
        info->triangles = m.triangles.size();
        info->vertices = m.vertices.size();
        info->seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    }
    return m;
}

void save_mesh(const SurfaceMesh& mesh, const std::filesystem::path& path) {
    mesh.validate(path.string());
    const std::string ext = lower_ext(path);
    Ptr<vtkPolyData> pd = to_polydata(mesh);
    // Temporary name in the same folder, then rename: the file is whole or absent. The
    // extension stays last (VTK's PLY writer appends ".ply" to a name without it).
    std::filesystem::path tmp = path;
    tmp.replace_filename(path.stem().string() + ".part" + path.extension().string());
    int ok = 0;
    if (ext == ".ply") {
        auto w = Ptr<vtkPLYWriter>::New();
        w->SetInputData(pd);
        w->SetFileName(tmp.c_str());
        w->SetFileTypeToBinary();
        w->AddComment("SPACE=LPS");
        w->AddComment("cortexfuse brain surface, world LPS millimetres");
        ok = w->Write();
    } else if (ext == ".vtp") {
        auto w = Ptr<vtkXMLPolyDataWriter>::New();
        w->SetInputData(pd);
        w->SetFileName(tmp.c_str());
        w->SetDataModeToBinary();
        ok = w->Write();
    } else if (ext == ".stl") {
        auto w = Ptr<vtkSTLWriter>::New();
        w->SetInputData(pd);
        w->SetFileName(tmp.c_str());
        w->SetFileTypeToBinary();
        w->SetHeader("SPACE=LPS cortexfuse brain surface");
        ok = w->Write();
    } else if (ext == ".obj") {
        auto w = Ptr<vtkOBJWriter>::New();
        w->SetInputData(pd);
        w->SetFileName(tmp.c_str());
        ok = w->Write();
    } else {
        throw InputError(path.string(), "unknown mesh format (use .ply, .vtp, .stl or .obj)");
    }
    std::error_code ec;
    if (!ok || !std::filesystem::exists(tmp)) {
        std::filesystem::remove(tmp, ec);
        throw InputError(path.string(), "cannot write the mesh");
    }
    std::filesystem::rename(tmp, path, ec);
    if (ec) {
        std::filesystem::remove(tmp, ec);
        throw InputError(path.string(), "cannot write the mesh: " + ec.message());
    }
}

SurfaceMesh load_mesh(const std::filesystem::path& path) {
    if (!std::filesystem::is_regular_file(path)) throw InputError(path.string(), "no such mesh file");
    const std::string ext = lower_ext(path);
    Ptr<vtkPolyData> pd;
    if (ext == ".ply") {
        auto r = Ptr<vtkPLYReader>::New();
        r->SetFileName(path.c_str());
        r->Update();
        pd = r->GetOutput();
    } else if (ext == ".vtp") {
        auto r = Ptr<vtkXMLPolyDataReader>::New();
        r->SetFileName(path.c_str());
        r->Update();
        pd = r->GetOutput();
    } else if (ext == ".stl") {
        auto r = Ptr<vtkSTLReader>::New();
        r->SetFileName(path.c_str());
        r->Update();
        pd = r->GetOutput();
    } else if (ext == ".obj") {
        auto r = Ptr<vtkOBJReader>::New();
        r->SetFileName(path.c_str());
        r->Update();
        pd = r->GetOutput();
    } else {
        throw InputError(path.string(), "unknown mesh format (use .ply, .vtp, .stl or .obj)");
    }
    if (!pd || pd->GetNumberOfPoints() == 0) throw InputError(path.string(), "not a mesh or no vertices");
    auto tri = Ptr<vtkTriangleFilter>::New();
    tri->SetInputData(pd);
    tri->PassVertsOff();
    tri->PassLinesOff();
    tri->Update();
    SurfaceMesh m = from_polydata(tri->GetOutput(), true);
    if (m.triangles.empty()) throw InputError(path.string(), "mesh has no triangles");
    if (m.normals.size() != m.vertices.size()) m.normals = outward_vertex_normals(m.vertices, m.triangles);
    m.validate(path.string());
    return m;
}

}  // namespace cf
