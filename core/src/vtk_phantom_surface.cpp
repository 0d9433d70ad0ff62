// Brain surface for the phantom generator, through VTK (flying edges, windowed-sinc
// smoothing, connectivity). VTK works in index space here; vertices are mapped to world
// LPS mm through the volume geometry (direction cosines included) before smoothing.
#include <vtkCellArray.h>
#include <vtkCleanPolyData.h>
#include <vtkFlyingEdges3D.h>
#include <vtkFloatArray.h>
#include <vtkIdList.h>
#include <vtkImageData.h>
#include <vtkPointData.h>
#include <vtkPoints.h>
#include <vtkPolyData.h>
#include <vtkPolyDataConnectivityFilter.h>
#include <vtkSmartPointer.h>
#include <vtkTriangleFilter.h>
#include <vtkWindowedSincPolyDataFilter.h>

#include <algorithm>
#include <cmath>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/phantom.hpp"

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

/// 1D k-means with 3 classes (CSF, grey, white matter) on intensities; returns sorted means.
std::array<double, 3> three_class_means(const std::vector<float>& values) {
    std::vector<float> v = values;
    std::sort(v.begin(), v.end());
    auto pct = [&](double p) { return double(v[size_t(p * double(v.size() - 1))]); };
    std::array<double, 3> m{pct(0.1), pct(0.45), pct(0.85)};
    // Histogram-based Lloyd iterations.
    const double lo = pct(0.001), hi = pct(0.999);
    constexpr int nb = 512;
    std::vector<double> hist(nb, 0.0);
    for (float x : v) {
        const int b = std::clamp(int((x - lo) / (hi - lo) * nb), 0, nb - 1);
        hist[size_t(b)] += 1;
    }
    for (int it = 0; it < 50; ++it) {
        std::array<double, 3> s{0, 0, 0}, c{0, 0, 0};
        for (int b = 0; b < nb; ++b) {
            const double x = lo + (b + 0.5) * (hi - lo) / nb;
            int best = 0;
            for (int q = 1; q < 3; ++q)
                if (std::abs(x - m[size_t(q)]) < std::abs(x - m[size_t(best)])) best = q;
            s[size_t(best)] += x * hist[size_t(b)];
            c[size_t(best)] += hist[size_t(b)];
        }
        for (int q = 0; q < 3; ++q)
            if (c[size_t(q)] > 0) m[size_t(q)] = s[size_t(q)] / c[size_t(q)];
        std::sort(m.begin(), m.end());
    }
    return m;
}

std::vector<Eigen::Vector3f> vertex_normals(const std::vector<Eigen::Vector3f>& V, const std::vector<Eigen::Vector3i>& F) {
    std::vector<Eigen::Vector3f> N(V.size(), Eigen::Vector3f::Zero());
    for (const auto& f : F) {
        const Eigen::Vector3f n = (V[size_t(f[1])] - V[size_t(f[0])]).cross(V[size_t(f[2])] - V[size_t(f[0])]);
        for (int q = 0; q < 3; ++q) N[size_t(f[q])] += n;  // area-weighted
    }
    for (auto& n : N) {
        const float l = n.norm();
        n = l > 0 ? Eigen::Vector3f(n / l) : Eigen::Vector3f(0, 0, 1);
    }
    return N;
}

/// Flips all normals if they point inward on the whole (closed surface, outward means away
/// from the centroid on average).
void orient_outward(std::vector<Eigen::Vector3f>& N, const std::vector<Eigen::Vector3f>& V, const Eigen::Vector3f& c) {
    double s = 0;
    for (size_t i = 0; i < V.size(); ++i) s += double(N[i].dot(V[i] - c));
    if (s < 0)
        for (auto& n : N) n = -n;
}

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

}  // namespace

PhantomSurface build_phantom_surface(const Volume& t1, const LabelVolume& mask, const Progress& progress) {
    if (!mask.geom.same_grid(t1.geom))
        throw InputError("brain mask", "not on the volume's grid (dimensions, spacing, origin and direction must match)");
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

    // Skull-stripped T1 on the cropped grid; intensity statistics inside the mask.
    std::vector<float> img(size_t(nx) * ny * nz, 0.f), inside;
    inside.reserve(count);
    for (int k = 0; k < nz; ++k)
        for (int j = 0; j < ny; ++j)
            for (int i = 0; i < nx; ++i)
                if (mask.at(i + lo[0], j + lo[1], k + lo[2])) {
                    const float x = t1.at(i + lo[0], j + lo[1], k + lo[2]);
                    img[(size_t(k) * ny + j) * nx + i] = x;
                    inside.push_back(x);
                }
    const auto means = three_class_means(inside);
    // Grey matter / CSF boundary: between the CSF and grey-matter class means, towards CSF
    // so that the surface wraps the gyri and sulci stay narrow, as on the exposed cortex.
    const float iso = float(0.65 * means[0] + 0.35 * means[1]);
    // Light smoothing (voxel noise), anisotropy ignored at this scale.
    gaussian_blur3(img, nx, ny, nz, 0.7);
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

    auto conn = Ptr<vtkPolyDataConnectivityFilter>::New();
    conn->SetInputConnection(fe->GetOutputPort());
    conn->SetExtractionModeToLargestRegion();
    auto clean = Ptr<vtkCleanPolyData>::New();
    clean->SetInputConnection(conn->GetOutputPort());
    clean->PointMergingOff();  // only drop unused points
    auto tri = Ptr<vtkTriangleFilter>::New();
    tri->SetInputConnection(clean->GetOutputPort());
    tri->Update();
    Ptr<vtkPolyData> pd = tri->GetOutput();
    if (pd->GetNumberOfPoints() < 100 || pd->GetNumberOfCells() < 100)
        throw InputError("brain mask", "no brain surface found at T1 level " + std::to_string(iso));

    // Index space -> world LPS mm (direction cosines and spacing), before smoothing.
    const Eigen::Affine3d W = t1.geom.world_from_index();
    vtkPoints* pts = pd->GetPoints();
    for (vtkIdType i = 0; i < pts->GetNumberOfPoints(); ++i) {
        double p[3];
        pts->GetPoint(i, p);
        const Eigen::Vector3d w = W * Eigen::Vector3d(p[0], p[1], p[2]);
        pts->SetPoint(i, w.x(), w.y(), w.z());
    }
    progress("surface", 0.55);
    progress.check();

    Ptr<vtkPolyData> smooth = windowed_sinc(pd, 20, 0.08);
    progress("surface", 0.7);
    progress.check();
    Ptr<vtkPolyData> hull = windowed_sinc(smooth, 100, 0.0003);
    progress("surface", 0.9);

    PhantomSurface s;
    s.iso_level = iso;
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
    s.normals = vertex_normals(s.mesh.vertices, s.mesh.triangles);
    orient_outward(s.normals, s.mesh.vertices, s.centroid_world_mm);
    s.smooth_normals = vertex_normals(s.smooth_vertices, s.mesh.triangles);
    orient_outward(s.smooth_normals, s.smooth_vertices, s.centroid_world_mm);
    s.sulcal_depth_mm.resize(size_t(np));
    for (size_t i = 0; i < size_t(np); ++i)
        s.sulcal_depth_mm[i] = (s.smooth_vertices[i] - s.mesh.vertices[i]).dot(s.smooth_normals[i]);
    progress("surface", 1.0);
    return s;
}

}  // namespace cf
