#include "cortexfuse/core/volume.hpp"


#include <algorithm>
#include <cmath>
#include <tbb/parallel_for.h>

#include "cortexfuse/core/error.hpp"
#include "itk_grid.hpp"

namespace fs = std::filesystem;

namespace cf {

Eigen::Affine3d VolumeGeometry::world_from_index() const {
    Eigen::Affine3d A = Eigen::Affine3d::Identity();
    A.linear() = direction * spacing_mm.asDiagonal();
    A.translation() = origin_mm;
    return A;
}

Eigen::Vector3d VolumeGeometry::center_world_mm() const {
    return world_from_index(Eigen::Vector3d((dims[0] - 1) * 0.5, (dims[1] - 1) * 0.5, (dims[2] - 1) * 0.5));
}

bool VolumeGeometry::same_grid(const VolumeGeometry& o, double tol) const {
    return dims == o.dims && (spacing_mm - o.spacing_mm).norm() < tol &&
           (origin_mm - o.origin_mm).norm() < tol && (direction - o.direction).norm() < tol;
}

size_t LabelVolume::count_nonzero() const {
    return size_t(std::count_if(voxels.begin(), voxels.end(), [](uint8_t v) { return v != 0; }));
}

namespace {

using itkb::from_grid;
using itkb::to_grid;

void check_geometry(const itkb::Grid& r, const std::string& name) {
    const VolumeGeometry g = from_grid(r);
    size_t n = 1;
    for (int a = 0; a < 3; ++a) {
        if (g.dims[a] < 2 || g.dims[a] > kMaxVolumeDim)
            throw InputError(name, "absurd volume dimensions " + std::to_string(g.dims[0]) + "x" +
                                       std::to_string(g.dims[1]) + "x" + std::to_string(g.dims[2]) +
                                       " (each must be 2.." + std::to_string(kMaxVolumeDim) + ")");
        n *= size_t(g.dims[a]);
        if (!std::isfinite(g.spacing_mm[a]) || !(g.spacing_mm[a] > 1e-3 && g.spacing_mm[a] < 100.0))
            throw InputError(name, "absurd voxel spacing " + std::to_string(g.spacing_mm[a]) + " mm");
    }
    if (n > kMaxVoxels) throw InputError(name, "volume too large (" + std::to_string(n) + " voxels)");
    if (!g.origin_mm.allFinite() || !g.direction.allFinite() || std::abs(g.direction.determinant()) < 0.5)
        throw InputError(name, "invalid origin or direction cosines");
}

}  // namespace

Volume load_volume(const fs::path& path) {
    itkb::Grid grid;
    Volume v;
    itkb::read_float(path.string(), grid, v.voxels, &check_geometry);
    v.geom = from_grid(grid);
    for (float x : v.voxels)
        if (!std::isfinite(x)) throw InputError(path.string(), "volume holds NaN or infinite voxels");
    return v;
}

LabelVolume load_mask(const fs::path& path) {
    Volume v = load_volume(path);
    LabelVolume m;
    m.geom = v.geom;
    m.voxels.resize(v.voxels.size());
    for (size_t i = 0; i < v.voxels.size(); ++i) m.voxels[i] = v.voxels[i] > 0.5f ? 1 : 0;
    return m;
}

LabelVolume load_mask(const fs::path& path, const VolumeGeometry& grid) {
    LabelVolume m = load_mask(path);
    return m.geom.same_grid(grid) ? m : resample_nearest(m, grid);
}

void save_volume(const Volume& v, const fs::path& path) { itkb::write_float(path.string(), to_grid(v.geom), v.voxels.data()); }
void save_mask(const LabelVolume& m, const fs::path& path) { itkb::write_u8(path.string(), to_grid(m.geom), m.voxels.data()); }

namespace {
inline float trilinear(const Volume& v, const Eigen::Vector3d& ijk, float outside) {
    const auto& d = v.geom.dims;
    const double x = ijk.x(), y = ijk.y(), z = ijk.z();
    if (x < 0 || y < 0 || z < 0 || x > d[0] - 1 || y > d[1] - 1 || z > d[2] - 1) return outside;
    const int i = std::min(int(x), d[0] - 2), j = std::min(int(y), d[1] - 2), k = std::min(int(z), d[2] - 2);
    const float fx = float(x - i), fy = float(y - j), fz = float(z - k);
    const size_t sx = 1, sy = size_t(d[0]), sz = size_t(d[0]) * d[1];
    const float* p = v.voxels.data() + v.geom.linear(i, j, k);
    const float c00 = p[0] + fx * (p[sx] - p[0]);
    const float c10 = p[sy] + fx * (p[sy + sx] - p[sy]);
    const float c01 = p[sz] + fx * (p[sz + sx] - p[sz]);
    const float c11 = p[sz + sy] + fx * (p[sz + sy + sx] - p[sz + sy]);
    const float c0 = c00 + fy * (c10 - c00), c1 = c01 + fy * (c11 - c01);
    return c0 + fz * (c1 - c0);
}
}  // namespace

Volume resample(const Volume& v, const VolumeGeometry& grid, float outside_value) {
    Volume out;
    out.geom = grid;
    out.voxels.assign(grid.voxel_count(), outside_value);
    const Eigen::Affine3d src_from_dst = v.geom.index_from_world() * grid.world_from_index();
    tbb::parallel_for(0, grid.dims[2], [&](int k) {
        for (int j = 0; j < grid.dims[1]; ++j)
            for (int i = 0; i < grid.dims[0]; ++i)
                out.voxels[grid.linear(i, j, k)] =
                    trilinear(v, src_from_dst * Eigen::Vector3d(i, j, k), outside_value);
    });
    return out;
}

LabelVolume resample_nearest(const LabelVolume& m, const VolumeGeometry& grid) {
    LabelVolume out;
    out.geom = grid;
    out.voxels.assign(grid.voxel_count(), 0);
    const Eigen::Affine3d src_from_dst = m.geom.index_from_world() * grid.world_from_index();
    const auto& d = m.geom.dims;
    tbb::parallel_for(0, grid.dims[2], [&](int k) {
        for (int j = 0; j < grid.dims[1]; ++j)
            for (int i = 0; i < grid.dims[0]; ++i) {
                const Eigen::Vector3d s = src_from_dst * Eigen::Vector3d(i, j, k);
                const int a = int(std::lround(s.x())), b = int(std::lround(s.y())), c = int(std::lround(s.z()));
                if (a < 0 || b < 0 || c < 0 || a >= d[0] || b >= d[1] || c >= d[2]) continue;
                out.voxels[grid.linear(i, j, k)] = m.at(a, b, c);
            }
    });
    return out;
}

VolumeGeometry isotropic_grid(const VolumeGeometry& g, double spacing_mm) {
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e30), hi = Eigen::Vector3d::Constant(-1e30);
    for (int c = 0; c < 8; ++c) {
        const Eigen::Vector3d ijk((c & 1) ? g.dims[0] - 1 : 0, (c & 2) ? g.dims[1] - 1 : 0, (c & 4) ? g.dims[2] - 1 : 0);
        const Eigen::Vector3d p = g.world_from_index(ijk);
        lo = lo.cwiseMin(p);
        hi = hi.cwiseMax(p);
    }
    VolumeGeometry out;
    out.spacing_mm = Eigen::Vector3d::Constant(spacing_mm);
    out.origin_mm = lo;
    for (int a = 0; a < 3; ++a) out.dims[a] = int(std::floor((hi[a] - lo[a]) / spacing_mm)) + 1;
    return out;
}

IntensityStats intensity_stats(const Volume& v, const LabelVolume* mask) {
    if (mask && (mask->voxels.size() != v.voxels.size() || mask->geom.dims != v.geom.dims))
        throw std::invalid_argument("intensity_stats: mask on another grid than the volume");
    std::vector<float> vals;
    vals.reserve(v.voxels.size());
    for (size_t i = 0; i < v.voxels.size(); ++i)
        if (!mask || mask->voxels[i]) vals.push_back(v.voxels[i]);
    IntensityStats s;
    s.count = vals.size();
    if (vals.empty()) return s;
    double sum = 0, sum2 = 0;
    for (float x : vals) {
        sum += x;
        sum2 += double(x) * x;
    }
    s.mean = sum / vals.size();
    s.stddev = std::sqrt(std::max(0.0, sum2 / vals.size() - s.mean * s.mean));
    auto pct = [&](double q) {
        const size_t idx = std::min(vals.size() - 1, size_t(q * (vals.size() - 1)));
        std::nth_element(vals.begin(), vals.begin() + idx, vals.end());
        return double(vals[idx]);
    };
    s.p01 = pct(0.01);
    s.p50 = pct(0.5);
    s.p99 = pct(0.99);
    const auto [mn, mx] = std::minmax_element(vals.begin(), vals.end());
    s.min = *mn;
    s.max = *mx;
    return s;
}

double dice(const LabelVolume& a, const LabelVolume& b) {
    if (a.voxels.size() != b.voxels.size()) throw std::invalid_argument("dice: masks on different grids");
    size_t na = 0, nb = 0, nab = 0;
    for (size_t i = 0; i < a.voxels.size(); ++i) {
        const bool x = a.voxels[i] != 0, y = b.voxels[i] != 0;
        na += x;
        nb += y;
        nab += x && y;
    }
    return na + nb ? 2.0 * nab / double(na + nb) : 1.0;
}

}  // namespace cf
