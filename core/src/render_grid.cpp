// masked_render_copy() (renderer.hpp): the finer copy the ray casters draw a mask on thick
// slices from. See docs/skull-stripping.md ("Rendered check images") for what it fixed.
#include <tbb/parallel_for.h>

#include <algorithm>
#include <cmath>

#include "cortexfuse/core/renderer.hpp"
#include "itk_distance.hpp"

namespace cf {

namespace {

constexpr double kAnisotropy = 1.5;  // an axis thicker than this times the finest is cut
constexpr double kFinestMm = 1.0;    // thick axes are cut to this, or to the finest spacing if coarser
constexpr double kSmoothSigmaMm = 1.5;  // of the mask's signed distance along the fine axes
constexpr double kRampVoxels = 4;       // width of the fade at the mask's edge, in voxels of the copy
constexpr double kMarginMm = 10;        // around the mask's box: > half the ramp + the smoothing's reach

/// Where each voxel of the copy falls on the native axis: knot index and fraction.
struct AxisMap {
    std::vector<int> i0, i1;
    std::vector<float> t;
};

AxisMap axis_map(int n_native, int factor) {
    AxisMap m;
    const int n = (n_native - 1) * factor + 1;
    m.i0.resize(size_t(n));
    m.i1.resize(size_t(n));
    m.t.resize(size_t(n));
    for (int I = 0; I < n; ++I) {
        m.i0[size_t(I)] = I / factor;
        m.i1[size_t(I)] = std::min(I / factor + 1, n_native - 1);
        m.t[size_t(I)] = float(I % factor) / float(factor);  // exact 0 on the native knots
    }
    return m;
}

/// Calls out(linear index in the copy, value) with `src` (native grid `d`) interpolated linearly
/// onto every voxel of the copy (grid `dd`); separable, so this is trilinear interpolation.
template <class Out>
void upsample(const float* src, const std::array<int, 3>& d, const std::array<AxisMap, 3>& m,
              const std::array<int, 3>& dd, Out&& out) {
    const size_t sy = size_t(d[0]), sz = size_t(d[0]) * size_t(d[1]);
    tbb::parallel_for(0, dd[2], [&](int K) {
        const size_t z0 = size_t(m[2].i0[size_t(K)]) * sz, z1 = size_t(m[2].i1[size_t(K)]) * sz;
        const float tz = m[2].t[size_t(K)];
        for (int J = 0; J < dd[1]; ++J) {
            const size_t y0 = size_t(m[1].i0[size_t(J)]) * sy, y1 = size_t(m[1].i1[size_t(J)]) * sy;
            const float ty = m[1].t[size_t(J)];
            const size_t row = (size_t(K) * size_t(dd[1]) + size_t(J)) * size_t(dd[0]);
            for (int I = 0; I < dd[0]; ++I) {
                const size_t x0 = size_t(m[0].i0[size_t(I)]), x1 = size_t(m[0].i1[size_t(I)]);
                const float tx = m[0].t[size_t(I)];
                auto lerp_x = [&](size_t base) { return src[base + x0] + tx * (src[base + x1] - src[base + x0]); };
                const float c00 = lerp_x(z0 + y0), c10 = lerp_x(z0 + y1), c01 = lerp_x(z1 + y0), c11 = lerp_x(z1 + y1);
                const float c0 = c00 + ty * (c10 - c00), c1 = c01 + ty * (c11 - c01);
                out(row + size_t(I), c0 + tz * (c1 - c0));
            }
        }
    });
}

/// Gaussian smoothing of `x` (grid dims `dd`, x fastest) along `axis`, sigma in voxels; edges
/// clamped. Along y or z whole rows are weighed at once, so memory is read in order.
void smooth_axis(std::vector<float>& x, const std::array<int, 3>& dd, int axis, double sigma) {
    const int r = int(std::ceil(3 * sigma));
    if (r < 1) return;
    std::vector<float> w(size_t(2 * r + 1));
    double sum = 0;
    for (int t = -r; t <= r; ++t) sum += w[size_t(t + r)] = float(std::exp(-0.5 * t * t / (sigma * sigma)));
    for (float& v : w) v = float(v / sum);
    const size_t nx = size_t(dd[0]), ny = size_t(dd[1]), nz = size_t(dd[2]);
    if (axis == 0) {
        tbb::parallel_for(size_t(0), ny * nz, [&](size_t row) {
            float* p = x.data() + row * nx;
            std::vector<float> line(p, p + nx);
            for (size_t i = 0; i < nx; ++i) {
                float acc = 0;
                for (int t = -r; t <= r; ++t)
                    acc += w[size_t(t + r)] * line[size_t(std::clamp(int(i) + t, 0, int(nx) - 1))];
                p[i] = acc;
            }
        });
        return;
    }
    // A slab: the n rows of x along `axis` for one value of the remaining axis, copied, then each
    // output row is the weighted sum of its neighbours' rows.
    const size_t n = axis == 1 ? ny : nz, row_stride = axis == 1 ? nx : nx * ny, slabs = axis == 1 ? nz : ny,
                 slab_stride = axis == 1 ? nx * ny : nx;
    tbb::parallel_for(size_t(0), slabs, [&](size_t s) {
        std::vector<float> in(n * nx);
        float* base = x.data() + s * slab_stride;
        for (size_t i = 0; i < n; ++i) std::copy_n(base + i * row_stride, nx, in.data() + i * nx);
        for (size_t i = 0; i < n; ++i) {
            float* out = base + i * row_stride;
            std::fill_n(out, nx, 0.f);
            for (int t = -r; t <= r; ++t) {
                const float* src = in.data() + size_t(std::clamp(int(i) + t, 0, int(n) - 1)) * nx;
                const float wt = w[size_t(t + r)];
                for (size_t u = 0; u < nx; ++u) out[u] += wt * src[u];
            }
        }
    });
}

}  // namespace

std::optional<Volume> masked_render_copy(const Volume& v, const LabelVolume* mask, const std::array<double, 2>& range) {
    if (!mask) return std::nullopt;
    const auto& d = v.geom.dims;
    const Eigen::Vector3d& s = v.geom.spacing_mm;
    const double finest = s.minCoeff();
    if (!(s.maxCoeff() > kAnisotropy * finest)) return std::nullopt;
    const size_t n = v.geom.voxel_count();
    if (v.voxels.size() != n || mask->voxels.size() != n || !mask->geom.same_grid(v.geom)) return std::nullopt;
    const size_t on = mask->count_nonzero();
    if (on == 0 || on == n) return std::nullopt;  // nothing to interpolate

    // Cuts per axis, fewer while the copy would exceed the cap.
    const double target = std::max(finest, kFinestMm);
    std::array<int, 3> f{1, 1, 1};
    for (int a = 0; a < 3; ++a)
        if (s[a] > kAnisotropy * finest && d[a] > 1) f[a] = std::max(1, int(std::ceil(s[a] / target - 1e-6)));
    auto copy_dims = [&] {
        return std::array<int, 3>{(d[0] - 1) * f[0] + 1, (d[1] - 1) * f[1] + 1, (d[2] - 1) * f[2] + 1};
    };
    auto count = [](const std::array<int, 3>& x) { return size_t(x[0]) * size_t(x[1]) * size_t(x[2]); };
    while (count(copy_dims()) > kMaxRenderCopyVoxels) {
        const int a = int(std::max_element(f.begin(), f.end()) - f.begin());
        if (f[a] == 1) break;
        --f[a];
    }
    if (f == std::array<int, 3>{1, 1, 1}) return std::nullopt;
    const std::array<int, 3> dd = copy_dims();

    // The work is done on the mask's bounding box and a margin (about half the DICOM series'
    // grid): beyond the margin the copy is range[0], as the fade would make it.
    std::array<int, 3> b0{d[0], d[1], d[2]}, b1{-1, -1, -1};
    for (int k = 0; k < d[2]; ++k)
        for (int j = 0; j < d[1]; ++j) {
            const uint8_t* row = mask->voxels.data() + v.geom.linear(0, j, k);
            for (int i = 0; i < d[0]; ++i)
                if (row[i]) {
                    b0 = {std::min(b0[0], i), std::min(b0[1], j), std::min(b0[2], k)};
                    b1 = {std::max(b1[0], i), std::max(b1[1], j), std::max(b1[2], k)};
                }
        }
    std::array<int, 3> bd{};
    for (int a = 0; a < 3; ++a) {
        const int margin = std::max(3, int(std::ceil(kMarginMm / s[a])));
        b0[size_t(a)] = std::max(0, b0[size_t(a)] - margin);
        b1[size_t(a)] = std::min(d[size_t(a)] - 1, b1[size_t(a)] + margin);
        bd[size_t(a)] = b1[size_t(a)] - b0[size_t(a)] + 1;
    }
    const size_t nb = count(bd);
    std::vector<float> box_voxels(nb);
    std::vector<uint8_t> box_mask(nb);
    for (int k = 0; k < bd[2]; ++k)
        for (int j = 0; j < bd[1]; ++j) {
            const size_t from = v.geom.linear(b0[0], b0[1] + j, b0[2] + k), to = (size_t(k) * size_t(bd[1]) + size_t(j)) * size_t(bd[0]);
            std::copy_n(v.voxels.data() + from, bd[0], box_voxels.data() + to);
            std::copy_n(mask->voxels.data() + from, bd[0], box_mask.data() + to);
        }

    // The mask's signed distance on the native grid. With one thick axis, per slice: that axis
    // is stretched so far that every nearest voxel lies in the same slice (the distances are the
    // slices' own 2D maps) and interpolating them between slices moves each edge linearly from
    // one slice's outline to the next (shape-based interpolation, Raya & Udupa 1990). A 3D map
    // with the true spacing would reach the next slice first wherever the outline moves more
    // than a slice thickness, and leave flat steps there. In a slice the mask misses (or fills),
    // the nearest voxel is k slices away, at k * stretch and r in-plane: that is put back to the
    // true distance, sqrt((k * thickness)^2 + r^2), so the mask ends within a slice of its last one.
    std::array<double, 3> dist_spacing{s[0], s[1], s[2]};
    int thick = -1, n_thick = 0;
    for (int a = 0; a < 3; ++a)
        if (f[size_t(a)] > 1) {
            thick = a;
            ++n_thick;
        }
    double stretch = 0;
    if (n_thick == 1) {
        double in_plane2 = 0;
        for (int a = 0; a < 3; ++a)
            if (a != thick) in_plane2 += std::pow(bd[size_t(a)] * s[a], 2);
        stretch = 4 * std::sqrt(in_plane2) + s[thick];  // > 4x any distance within a slice
        dist_spacing[size_t(thick)] = stretch;
    }
    std::vector<double> phi_mm;
    itkb::midpoint_signed_distance(bd, dist_spacing, box_mask.data(), phi_mm);
    std::vector<float> phi(nb);
    for (size_t i = 0; i < nb; ++i) {
        double x = phi_mm[i];
        if (n_thick == 1 && std::abs(x) >= 0.5 * stretch) {
            const double k = std::round(std::abs(x) / stretch);
            const double r2 = std::max(0.0, x * x - (k * stretch) * (k * stretch));
            x = std::copysign(std::sqrt((k * s[thick]) * (k * s[thick]) + r2), x);
        }
        phi[i] = float(x);
    }
    phi_mm = {};
    // Smoothed along the fine axes: the distance field of a voxel staircase is that staircase near
    // the edge (the skull strip's mask is nearest-neighbour from its own, coarser working grid:
    // steps of 1-2 voxels in-plane on the DICOM series), and where the mask cuts tissue the
    // ray caster shades every step.
    for (int a = 0; a < 3; ++a)
        if (f[size_t(a)] == 1) smooth_axis(phi, bd, a, kSmoothSigmaMm / s[a]);

    // The box's part of the copy (its first voxel is a native knot, so the same samples).
    const std::array<AxisMap, 3> m{axis_map(bd[0], f[0]), axis_map(bd[1], f[1]), axis_map(bd[2], f[2])};
    const std::array<int, 3> bdd{(bd[0] - 1) * f[0] + 1, (bd[1] - 1) * f[1] + 1, (bd[2] - 1) * f[2] + 1};
    Volume c;
    c.geom = v.geom;
    c.geom.dims = dd;
    for (int a = 0; a < 3; ++a) c.geom.spacing_mm[a] = s[a] / f[a];
    const float lo = float(range[0]), hi = float(range[1]);
    std::vector<float> fine(count(bdd));
    upsample(box_voxels.data(), bd, m, bdd, [&](size_t i, float x) { fine[i] = std::clamp(x, lo, hi); });
    std::vector<float> fine_phi(fine.size());
    upsample(phi.data(), bd, m, bdd, [&](size_t i, float x) { fine_phi[i] = x; });
    // Linear between slices, the clip surface creases at every slice (shaded as a line each
    // 4.8 mm); a Gaussian along the thick axis (sigma half a slice) rounds the creases.
    if (n_thick == 1) smooth_axis(fine_phi, bdd, thick, 0.5 * f[size_t(thick)]);
    // Faded over kRampVoxels voxels of the copy (3.8 mm on the DICOM series): trilinear sampling
    // then follows the ramp (linear in phi) instead of stepping at each voxel as a 0/1 cut does,
    // and a ray sampling each 1 mm meets it over several samples (over two, the composited
    // picture showed wood grain along the cut). phi is divided by its gradient's
    // length, a distance in mm: interpolated between slices it grows by up to an outline's shift
    // per slice thickness, and a ramp in phi alone would be thinner than a voxel there (the copy's
    // lattice then showed as ripples over every cap of the outline).
    const double ramp_mm = kRampVoxels * c.geom.spacing_mm.minCoeff();
    const size_t sy = size_t(bdd[0]), sz = size_t(bdd[0]) * size_t(bdd[1]);
    const Eigen::Vector3d inv_2h = (2 * c.geom.spacing_mm).cwiseInverse();
    tbb::parallel_for(0, bdd[2], [&](int k) {
        for (int j = 0; j < bdd[1]; ++j)
            for (int i = 0; i < bdd[0]; ++i) {
                const size_t at = size_t(k) * sz + size_t(j) * sy + size_t(i);
                const float x = fine_phi[at];
                auto diff = [&](int idx, int len, size_t stride) {
                    const size_t a = idx > 0 ? at - stride : at, b = idx < len - 1 ? at + stride : at;
                    return double(fine_phi[b] - fine_phi[a]) * ((idx > 0 && idx < len - 1) ? 1.0 : 2.0);
                };
                const Eigen::Vector3d g(diff(i, bdd[0], 1) * inv_2h[0], diff(j, bdd[1], sy) * inv_2h[1], diff(k, bdd[2], sz) * inv_2h[2]);
                const double dist_mm = x / std::max(g.norm(), 0.2);
                const float w = float(std::clamp(0.5 - dist_mm / ramp_mm, 0.0, 1.0));
                fine[at] = lo + (fine[at] - lo) * w;
            }
    });
    c.voxels.assign(count(dd), lo);
    const std::array<int, 3> o{b0[0] * f[0], b0[1] * f[1], b0[2] * f[2]};
    for (int k = 0; k < bdd[2]; ++k)
        for (int j = 0; j < bdd[1]; ++j)
            std::copy_n(fine.data() + (size_t(k) * size_t(bdd[1]) + size_t(j)) * size_t(bdd[0]), bdd[0],
                        c.voxels.data() + c.geom.linear(o[0], o[1] + j, o[2] + k));
    return c;
}

}  // namespace cf
