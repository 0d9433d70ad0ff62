// BET-like brain surface (Smith 2002). Hand-written: neither ITK nor VTK ships a brain-extraction
// surface model, and FSL's bet2 is not a Debian library. Follows the paper's update terms:
// tangential smoothing, curvature-adaptive normal smoothing and the local-intensity normal force.
// Everything is in index-space millimetres (i * spacing): orientation does not matter here.
#include "bet_surface.hpp"

#include <algorithm>
#include <cmath>
#include <map>
#include <numbers>

namespace cf::bet {
namespace {

using V3 = std::array<double, 3>;

V3 add(const V3& a, const V3& b) { return {a[0] + b[0], a[1] + b[1], a[2] + b[2]}; }
V3 sub(const V3& a, const V3& b) { return {a[0] - b[0], a[1] - b[1], a[2] - b[2]}; }
V3 mul(const V3& a, double s) { return {a[0] * s, a[1] * s, a[2] * s}; }
double dot(const V3& a, const V3& b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
V3 cross(const V3& a, const V3& b) {
    return {a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]};
}
double norm(const V3& a) { return std::sqrt(dot(a, a)); }

// Unit icosphere: icosahedron with each triangle split in four `subdivisions` times.
Mesh icosphere(int subdivisions) {
    const double t = (1.0 + std::sqrt(5.0)) / 2.0;
    Mesh m;
    m.vertices_mm = {{-1, t, 0}, {1, t, 0}, {-1, -t, 0}, {1, -t, 0}, {0, -1, t}, {0, 1, t},
                     {0, -1, -t}, {0, 1, -t}, {t, 0, -1}, {t, 0, 1}, {-t, 0, -1}, {-t, 0, 1}};
    m.triangles = {{0, 11, 5}, {0, 5, 1},  {0, 1, 7},   {0, 7, 10}, {0, 10, 11}, {1, 5, 9}, {5, 11, 4},
                   {11, 10, 2}, {10, 7, 6}, {7, 1, 8},  {3, 9, 4},  {3, 4, 2},   {3, 2, 6}, {3, 6, 8},
                   {3, 8, 9},  {4, 9, 5},  {2, 4, 11}, {6, 2, 10}, {8, 6, 7},   {9, 8, 1}};
    for (auto& v : m.vertices_mm) v = mul(v, 1.0 / norm(v));
    for (int s = 0; s < subdivisions; ++s) {
        std::map<std::pair<int, int>, int> mid;
        auto midpoint = [&](int a, int b) {
            const auto key = std::minmax(a, b);
            if (auto it = mid.find(key); it != mid.end()) return it->second;
            V3 p = mul(add(m.vertices_mm[a], m.vertices_mm[b]), 0.5);
            p = mul(p, 1.0 / norm(p));
            m.vertices_mm.push_back(p);
            return mid[key] = int(m.vertices_mm.size() - 1);
        };
        std::vector<std::array<int, 3>> next;
        next.reserve(m.triangles.size() * 4);
        for (const auto& tr : m.triangles) {
            const int a = midpoint(tr[0], tr[1]), b = midpoint(tr[1], tr[2]), c = midpoint(tr[2], tr[0]);
            next.push_back({tr[0], a, c});
            next.push_back({tr[1], b, a});
            next.push_back({tr[2], c, b});
            next.push_back({a, b, c});
        }
        m.triangles = std::move(next);
    }
    return m;
}

struct Sampler {
    const float* v;
    std::array<int, 3> d;
    std::array<double, 3> sp;
    float outside;
    // Trilinear at a point in index-space mm; `outside` beyond the grid.
    double operator()(const V3& p) const {
        const double x = p[0] / sp[0], y = p[1] / sp[1], z = p[2] / sp[2];
        if (!(x >= 0 && y >= 0 && z >= 0 && x <= d[0] - 1 && y <= d[1] - 1 && z <= d[2] - 1)) return outside;
        // Caller guarantees >= 2 voxels per axis (skull_strip refuses < 8).
        const int i = std::min(int(x), d[0] - 2), j = std::min(int(y), d[1] - 2), k = std::min(int(z), d[2] - 2);
        const double fx = x - i, fy = y - j, fz = z - k;
        const size_t sx = 1, sy = size_t(d[0]), sz = size_t(d[0]) * d[1];
        const size_t o = size_t(k) * sz + size_t(j) * sy + size_t(i);
        const double c00 = v[o] * (1 - fx) + v[o + sx] * fx, c10 = v[o + sy] * (1 - fx) + v[o + sy + sx] * fx;
        const double c01 = v[o + sz] * (1 - fx) + v[o + sz + sx] * fx,
                     c11 = v[o + sz + sy] * (1 - fx) + v[o + sz + sy + sx] * fx;
        return (c00 * (1 - fy) + c10 * fy) * (1 - fz) + (c01 * (1 - fy) + c11 * fy) * fz;
    }
};

void compute_stats(const float* v, const std::array<int, 3>& dims, const std::array<double, 3>& sp,
                   const HeadFrame& frame, BetStats& s) {
    const size_t n = size_t(dims[0]) * dims[1] * dims[2];
    {
        const size_t stride = std::max<size_t>(1, n / 2'000'000);
        std::vector<float> smp;
        for (size_t i = 0; i < n; i += stride) smp.push_back(v[i]);
        auto at = [&](double q) {
            const size_t k = std::min(smp.size() - 1, size_t(q * double(smp.size() - 1)));
            std::nth_element(smp.begin(), smp.begin() + std::ptrdiff_t(k), smp.end());
            return double(smp[k]);
        };
        s.t2 = at(0.02);
        s.t98 = at(0.98);
    }
    s.t = s.t2 + 0.1 * (s.t98 - s.t2);
    auto for_each_voxel = [&](auto&& fn) {
        for (int k = 0; k < dims[2]; ++k)
            for (int j = 0; j < dims[1]; ++j)
                for (int i = 0; i < dims[0]; ++i)
                    fn(V3{i * sp[0], j * sp[1], k * sp[2]}, double(v[(size_t(k) * dims[1] + j) * dims[0] + i]));
    };
    // Top of the head along `up`, from the head voxels' heights (a high percentile, not the
    // maximum, so that a few bright noise voxels above the head do not count).
    std::vector<float> heights;
    for_each_voxel([&](const V3& p, double x) {
        if (x > s.t) heights.push_back(float(dot(p, frame.up)));
    });
    double h_min = -1e30;
    if (!heights.empty()) {
        const size_t k = size_t(0.999 * double(heights.size() - 1));
        std::nth_element(heights.begin(), heights.begin() + std::ptrdiff_t(k), heights.end());
        h_min = heights[k] - frame.cranium_height_mm;
    }
    // Centre of gravity of the cranium, intensity-weighted (clamped at t98) as bet2.
    double w_sum = 0, count = 0;
    V3 c{0, 0, 0};
    for_each_voxel([&](const V3& p, double x) {
        if (x <= s.t || dot(p, frame.up) < h_min) return;
        const double w = std::min(x, s.t98) - s.t2;
        c = add(c, mul(p, w));
        w_sum += w;
        count += 1;
    });
    if (w_sum > 0) c = mul(c, 1.0 / w_sum);
    s.cog_mm = c;
    s.radius_mm = std::cbrt(3.0 * count * sp[0] * sp[1] * sp[2] / (4.0 * std::numbers::pi));
    // Median intensity within the head sphere.
    std::vector<float> in;
    const double r2 = s.radius_mm * s.radius_mm;
    for_each_voxel([&](const V3& p, double x) {
        const V3 d = sub(p, c);
        if (dot(d, d) < r2 && x > s.t2 && x < s.t98) in.push_back(float(x));
    });
    if (!in.empty()) {
        std::nth_element(in.begin(), in.begin() + std::ptrdiff_t(in.size() / 2), in.end());
        s.tm = in[in.size() / 2];
    } else {
        s.tm = 0.5 * (s.t + s.t98);
    }
}

// Signed volume enclosed by a closed mesh (divergence theorem), mm^3; positive for outward normals.
double enclosed_mm3(const Mesh& m) {
    double v6 = 0;
    for (const auto& tr : m.triangles)
        v6 += dot(m.vertices_mm[size_t(tr[0])], cross(m.vertices_mm[size_t(tr[1])], m.vertices_mm[size_t(tr[2])]));
    return v6 / 6.0;
}

// One run of BET's surface evolution with fractional threshold f, from the sphere of the stats.
Mesh evolve(const float* voxels, const std::array<int, 3>& dims, const std::array<double, 3>& spacing_mm,
            const BetParams& p, double f, const BetStats& s, const TickFn& tick) {
    Mesh m = icosphere(p.subdivisions);
    for (auto& v : m.vertices_mm) v = add(s.cog_mm, mul(v, 0.5 * s.radius_mm));
    const size_t nv = m.vertices_mm.size();

    // Vertex neighbours (edges of the triangulation) and incident triangles.
    std::vector<std::vector<int>> nbr(nv), tris(nv);
    for (size_t t = 0; t < m.triangles.size(); ++t)
        for (int e = 0; e < 3; ++e) {
            const int a = m.triangles[t][e], b = m.triangles[t][(e + 1) % 3];
            tris[a].push_back(int(t));
            if (std::find(nbr[a].begin(), nbr[a].end(), b) == nbr[a].end()) nbr[a].push_back(b);
            if (std::find(nbr[b].begin(), nbr[b].end(), a) == nbr[b].end()) nbr[b].push_back(a);
        }

    const Sampler I{voxels, dims, spacing_mm, float(s.t2)};
    const double rmin = p.radius_min_mm, rmax = p.radius_max_mm;
    const double E = 0.5 * (1.0 / rmin + 1.0 / rmax), F = 6.0 / (1.0 / rmin - 1.0 / rmax);
    const double d1 = p.search_in_mm, d2 = 0.5 * d1;
    const double step_mm = std::min({spacing_mm[0], spacing_mm[1], spacing_mm[2], 1.0});
    std::vector<V3> normal(nv), delta(nv);
    for (int it = 0; it < p.iterations; ++it) {
        if (tick && it % 50 == 0) tick(double(it) / p.iterations);
        // Outward vertex normals from the incident face normals.
        for (size_t v = 0; v < nv; ++v) {
            V3 nsum{0, 0, 0};
            for (int t : tris[v]) {
                const auto& tr = m.triangles[size_t(t)];
                nsum = add(nsum, cross(sub(m.vertices_mm[tr[1]], m.vertices_mm[tr[0]]),
                                       sub(m.vertices_mm[tr[2]], m.vertices_mm[tr[0]])));
            }
            const double ln = norm(nsum);
            normal[v] = ln > 0 ? mul(nsum, 1.0 / ln) : V3{0, 0, 1};
        }
        double l_sum = 0;
        size_t l_n = 0;
        for (size_t v = 0; v < nv; ++v)
            for (int b : nbr[v]) {
                l_sum += norm(sub(m.vertices_mm[size_t(b)], m.vertices_mm[v]));
                ++l_n;
            }
        const double l = l_sum / double(l_n);
        for (size_t v = 0; v < nv; ++v) {
            const V3& x = m.vertices_mm[v];
            const V3& n = normal[v];
            V3 mean{0, 0, 0};
            for (int b : nbr[v]) mean = add(mean, m.vertices_mm[size_t(b)]);
            const V3 sv = sub(mul(mean, 1.0 / double(nbr[v].size())), x);
            const double sn_len = dot(sv, n);
            const V3 sn = mul(n, sn_len), st = sub(sv, sn);
            // u1: tangential smoothing (keeps vertices evenly spaced).
            const V3 u1 = mul(st, 0.5);
            // u2: normal smoothing, strong where the local curvature radius is small.
            const double rinv = 2.0 * std::abs(sn_len) / (l * l);
            const double f2 = 0.5 * (1.0 + std::tanh(F * (rinv - E)));
            const V3 u2 = mul(sn, f2);
            // u3: brain/non-brain force from the intensity profile along the inward normal.
            double imin = s.tm, imax = s.t;
            for (double d = step_mm; d <= d1; d += step_mm) {
                const double val = I(sub(x, mul(n, d)));
                imin = std::min(imin, val);
                if (d <= d2) imax = std::max(imax, val);
            }
            imin = std::max(s.t2, imin);
            imax = std::min(s.tm, imax);
            const double tl = (imax - s.t2) * f + s.t2;
            const double f3 = imax - s.t2 > 0 ? 2.0 * (imin - tl) / (imax - s.t2) : 0.0;
            const V3 u3 = mul(n, 0.05 * f3 * l);
            delta[v] = add(add(u1, u2), u3);
        }
        for (size_t v = 0; v < nv; ++v) m.vertices_mm[v] = add(m.vertices_mm[v], delta[v]);
    }
    return m;
}

}  // namespace

Mesh bet_surface(const float* voxels, const std::array<int, 3>& dims, const std::array<double, 3>& spacing_mm,
                 const HeadFrame& frame, const BetParams& p, BetStats& s, const TickFn& tick) {
    compute_stats(voxels, dims, spacing_mm, frame, s);
    // The published default f = 0.5 passes a CSF/bone band that partial volume has made grey
    // (thick slices: the sagittal DICOM series at 4.8 mm) and the surface ends on the scalp.
    // Such a surface encloses more than any brain: BET's usual remedy, a higher f, is applied
    // in steps until the enclosed volume is plausible (or f reaches fraction_max).
    double f = p.fractional_threshold;
    for (int attempt = 0;; ++attempt) {
        const double f0 = double(attempt) / (attempt + 1.0), f1 = double(attempt + 1) / (attempt + 2.0);
        Mesh m = evolve(voxels, dims, spacing_mm, p, f, s,
                        [&](double x) { if (tick) tick(f0 + (f1 - f0) * x); });
        const double ml = enclosed_mm3(m) / 1000.0;
        s.fraction_used = f;
        s.enclosed_ml = ml;
        if (ml <= p.max_enclosed_ml || f + 1e-9 >= p.fraction_max) {
            if (tick) tick(1.0);
            return m;
        }
        f = std::min(p.fraction_max, f + p.fraction_step);
    }
}

std::vector<uint8_t> fill_mesh(const Mesh& m, const std::array<int, 3>& dims, const std::array<double, 3>& sp) {
    const int ny = dims[1], nz = dims[2];
    std::vector<std::vector<double>> cross_x(size_t(ny) * nz);
    // Tiny offsets keep scanlines off mesh edges and vertices (no double-counted crossings).
    const double ey = 1.37e-6, ez = 2.71e-6;
    for (const auto& tr : m.triangles) {
        const V3 &a = m.vertices_mm[tr[0]], &b = m.vertices_mm[tr[1]], &c = m.vertices_mm[tr[2]];
        const double area = (b[1] - a[1]) * (c[2] - a[2]) - (c[1] - a[1]) * (b[2] - a[2]);
        if (std::abs(area) < 1e-12) continue;
        const int j0 = std::max(0, int(std::ceil(std::min({a[1], b[1], c[1]}) / sp[1])));
        const int j1 = std::min(ny - 1, int(std::floor(std::max({a[1], b[1], c[1]}) / sp[1])));
        const int k0 = std::max(0, int(std::ceil(std::min({a[2], b[2], c[2]}) / sp[2])));
        const int k1 = std::min(nz - 1, int(std::floor(std::max({a[2], b[2], c[2]}) / sp[2])));
        for (int k = k0; k <= k1; ++k)
            for (int j = j0; j <= j1; ++j) {
                const double y = j * sp[1] + ey, z = k * sp[2] + ez;
                // Barycentric coordinates of (y, z) in the triangle's projection.
                const double wb = ((y - a[1]) * (c[2] - a[2]) - (c[1] - a[1]) * (z - a[2])) / area;
                const double wc = ((b[1] - a[1]) * (z - a[2]) - (y - a[1]) * (b[2] - a[2])) / area;
                const double wa = 1.0 - wb - wc;
                if (wa < 0 || wb < 0 || wc < 0) continue;
                cross_x[size_t(k) * ny + j].push_back(wa * a[0] + wb * b[0] + wc * c[0]);
            }
    }
    std::vector<uint8_t> out(static_cast<size_t>(dims[0]) * size_t(ny) * size_t(nz), 0);
    for (int k = 0; k < nz; ++k)
        for (int j = 0; j < ny; ++j) {
            auto& xs = cross_x[size_t(k) * ny + j];
            std::sort(xs.begin(), xs.end());
            for (size_t q = 0; q + 1 < xs.size(); q += 2) {
                const int i0 = std::max(0, int(std::ceil(xs[q] / sp[0])));
                const int i1 = std::min(dims[0] - 1, int(std::floor(xs[q + 1] / sp[0])));
                uint8_t* row = out.data() + (size_t(k) * ny + j) * dims[0];
                for (int i = i0; i <= i1; ++i) row[i] = 1;
            }
        }
    return out;
}

}  // namespace cf::bet
