// Rigid co-registration by true normalized mutual information, NMI = (H(F)+H(M))/H(F,M)
// (Studholme, Hill & Hawkes 1999), for `--metric nmi`.
//
// Why hand-written: ITK's v4 registration framework has no NMI metric (its metrics are Mattes
// MI, joint-histogram MI, correlation, mean squares, ANTs neighbourhood correlation, demons),
// and its joint-histogram MI, which `--metric nmi` used before, stopped within 9 iterations
// per level on CT-like images, 7-13 mm off (docs/checklists/issue-4-planning-overlay.md,
// 4.6). NMI's derivative through a Parzen joint histogram is not in ITK either, so rather
// than a v4 metric class with a hand-derived gradient, the NMI itself is optimised without
// derivatives: NLopt's Nelder-Mead (cf::nelder_mead, the optimiser the 3D-2D registration
// already uses), multi-resolution (Gaussian smoothing per level, sample stride = the level's
// shrink factor), the same Euler3D parameters and centre as the ITK path.
//
// The NMI is made continuous in the parameters (a simplex needs that): the moving image is
// interpolated trilinearly and its value splatted linearly into its two nearest bins; the fixed
// samples are fixed per level (hard bins). Samples outside the moving field of view are left
// out (the overlap gate in coregister() catches a result that slid out of the volume).
#include "nmi_coregistration.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <random>
#include <sstream>
#include <tbb/parallel_for.h>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/optimizer.hpp"
#include "itk_grid.hpp"
#include "joint_nmi.hpp"

namespace cf::detail {
namespace {

/// Rotation parameters are scaled to millimetres of arc at this radius, so that a simplex
/// step moves brain points about as far by turning as by shifting.
constexpr double kArcRadiusMm = 50.0;

/// One resolution level: the fixed samples (world mm and histogram bin) and the smoothed moving image.
struct Level {
    std::vector<Eigen::Vector3d> points_world_mm;
    std::vector<int> fixed_bin;
    std::vector<float> moving;  // smoothed, on the moving grid
    float moving_lo = 0, moving_hi = 1;
};

class NmiCost {
public:
    NmiCost(const Volume& moving_geom_src, const Level& lv, int bins, const Eigen::Vector3d& center)
        : geom_(moving_geom_src.geom), lv_(lv), bins_(bins), center_(center),
          index_from_world_(moving_geom_src.geom.index_from_world()),
          blocks_((lv.points_world_mm.size() + kBlock - 1) / kBlock),
          partial_(blocks_ * size_t(bins) * size_t(bins)), counts_(blocks_), joint_(size_t(bins) * size_t(bins)) {}

    /// NMI at Euler parameters (rx, ry, rz rad, tx, ty, tz mm); 1 when too few samples overlap.
    double nmi(const Eigen::Matrix<double, 6, 1>& euler) {
        const Eigen::Matrix4d T = euler_transform(euler.head<3>(), euler.tail<3>(), center_);
        const Eigen::Matrix3d A = index_from_world_.linear() * T.topLeftCorner<3, 3>();
        const Eigen::Vector3d b = index_from_world_.linear() * T.topRightCorner<3, 1>() + index_from_world_.translation();
        const auto& d = geom_.dims;
        const double scale = double(bins_ - 1) / double(std::max(1e-12f, lv_.moving_hi - lv_.moving_lo));
        const size_t sx = 1, sy = size_t(d[0]), sz = size_t(d[0]) * size_t(d[1]);
        const size_t nb2 = size_t(bins_) * size_t(bins_);
        // Blocks of samples in parallel, each into its own histogram, summed in block order: the
        // same result whatever the thread count (deterministic).
        tbb::parallel_for(size_t(0), blocks_, [&](size_t blk) {
        double* joint = partial_.data() + blk * nb2;
        std::fill(joint, joint + nb2, 0.0);
        double n = 0;
        const size_t end = std::min(lv_.points_world_mm.size(), (blk + 1) * kBlock);
        for (size_t s = blk * kBlock; s < end; ++s) {
            const Eigen::Vector3d q = A * lv_.points_world_mm[s] + b;
            if (!(q.x() >= 0 && q.y() >= 0 && q.z() >= 0 && q.x() < d[0] - 1 && q.y() < d[1] - 1 && q.z() < d[2] - 1)) continue;
            const int i = int(q.x()), j = int(q.y()), k = int(q.z());
            const double fx = q.x() - i, fy = q.y() - j, fz = q.z() - k;
            const float* v = lv_.moving.data() + size_t(i) * sx + size_t(j) * sy + size_t(k) * sz;
            const double c00 = v[0] * (1 - fx) + v[sx] * fx, c10 = v[sy] * (1 - fx) + v[sy + sx] * fx;
            const double c01 = v[sz] * (1 - fx) + v[sz + sx] * fx, c11 = v[sz + sy] * (1 - fx) + v[sz + sy + sx] * fx;
            const double m = (c00 * (1 - fy) + c10 * fy) * (1 - fz) + (c01 * (1 - fy) + c11 * fy) * fz;
            const double u = std::clamp((m - lv_.moving_lo) * scale, 0.0, double(bins_ - 1) - 1e-9);
            const int b0 = int(u);
            const double w = u - b0;
            double* row = joint + size_t(lv_.fixed_bin[s]) * size_t(bins_);
            row[b0] += 1 - w;
            row[b0 + 1] += w;
            n += 1;
        }
        counts_[blk] = n;
        });
        std::fill(joint_.begin(), joint_.end(), 0.0);
        double n = 0;
        for (size_t blk = 0; blk < blocks_; ++blk) {
            n += counts_[blk];
            const double* src = partial_.data() + blk * nb2;
            for (size_t q = 0; q < nb2; ++q) joint_[q] += src[q];
        }
        if (n < 100) return 1.0;
        return nmi_of_joint(n);
    }

private:
    double nmi_of_joint(double n) const { return detail::nmi_of_joint(joint_, bins_, n); }

    const VolumeGeometry& geom_;
    const Level& lv_;
    int bins_;
    Eigen::Vector3d center_;
    Eigen::Affine3d index_from_world_;
    static constexpr size_t kBlock = 8192;  // samples per parallel block
    size_t blocks_;
    std::vector<double> partial_, counts_;  // per block: joint histogram, sample count
    std::vector<double> joint_;
};

Level make_level(const Volume& fixed, const Volume& moving, const LabelVolume* mask, size_t samples, int shrink,
                 double sigma_mm, int bins, uint32_t seed) {
    Level lv;
    std::vector<float> f = fixed.voxels;
    itkb::smooth_gaussian(itkb::to_grid(fixed.geom), f, sigma_mm);
    lv.moving = moving.voxels;
    itkb::smooth_gaussian(itkb::to_grid(moving.geom), lv.moving, sigma_mm);
    const auto [mlo, mhi] = std::minmax_element(lv.moving.begin(), lv.moving.end());
    lv.moving_lo = *mlo, lv.moving_hi = *mhi;
    // Candidates: every shrink-th voxel of the fixed grid (inside the mask when there is one),
    // thinned at random (deterministic in `seed`) to about `samples`.
    const auto& d = fixed.geom.dims;
    size_t candidates = 0;
    for (int k = 0; k < d[2]; k += shrink)
        for (int j = 0; j < d[1]; j += shrink)
            for (int i = 0; i < d[0]; i += shrink) candidates += !mask || mask->at(i, j, k);
    const double keep = candidates > samples ? double(samples) / double(candidates) : 1.0;
    std::mt19937 rng(seed);
    std::uniform_real_distribution<double> u(0.0, 1.0);
    const Eigen::Affine3d W = fixed.geom.world_from_index();
    float flo = std::numeric_limits<float>::max(), fhi = -flo;
    std::vector<float> fv;
    for (int k = 0; k < d[2]; k += shrink)
        for (int j = 0; j < d[1]; j += shrink)
            for (int i = 0; i < d[0]; i += shrink) {
                if (mask && !mask->at(i, j, k)) continue;
                if (keep < 1.0 && u(rng) >= keep) continue;
                lv.points_world_mm.push_back(W * Eigen::Vector3d(i, j, k));
                const float v = f[fixed.geom.linear(i, j, k)];
                fv.push_back(v);
                flo = std::min(flo, v), fhi = std::max(fhi, v);
            }
    const double fscale = fhi > flo ? double(bins) / double(fhi - flo) : 0.0;
    lv.fixed_bin.reserve(fv.size());
    for (float v : fv) lv.fixed_bin.push_back(std::clamp(int((v - flo) * fscale), 0, bins - 1));
    return lv;
}

}  // namespace

itkb::CoregOutput nmi_coregister(const Volume& fixed, const Volume& moving, const LabelVolume* fixed_mask, size_t samples,
                                 const CoregParams& p, const Eigen::Vector3d& center, const Eigen::Vector3d& t0,
                                 const Progress& progress) {
    using Clock = std::chrono::steady_clock;
    itkb::CoregOutput out;
    // x = (rx, ry, rz) * kArcRadiusMm, (tx, ty, tz): all in mm.
    std::vector<double> x{0, 0, 0, t0.x(), t0.y(), t0.z()};
    auto euler_of = [](const std::vector<double>& v) {
        Eigen::Matrix<double, 6, 1> e;
        for (int a = 0; a < 3; ++a) e[a] = v[size_t(a)] / kArcRadiusMm, e[3 + a] = v[size_t(3 + a)];
        return e;
    };
    const size_t nlev = p.shrink.size();
    double best = 0;
    for (size_t l = 0; l < nlev; ++l) {
        progress.check();
        const auto t_level = Clock::now();
        const Level lv = make_level(fixed, moving, fixed_mask, samples, p.shrink[l], p.smooth_mm[l], p.bins, p.seed + uint32_t(l));
        if (lv.points_world_mm.size() < 100) throw InputError("fixed volume", "fewer than 100 samples for the NMI (empty mask?)");
        NmiCost cost(moving, lv, p.bins, center);
        const int it = l < p.iterations.size() ? p.iterations[l] : p.iterations.back();
        const int budget = 4 * it;  // Nelder-Mead takes 1-2 evaluations per iteration, more on shrinks
        int evals = 0;
        const auto f = [&](const std::vector<double>& v) {
            ++evals;
            progress("coregister", std::min(0.95, (double(l) + std::min(1.0, double(evals) / budget)) / double(nlev) * 0.95));
            return -cost.nmi(euler_of(v));
        };
        // The first simplex spans 2 max_step at the coarsest level, halved per level; restarts
        // from the best point (a fresh simplex, half as large) until one no longer gains: a
        // collapsed simplex is Nelder-Mead's known failure.
        double step_mm = 2.0 * p.max_step / double(1u << std::min<size_t>(l, 8));
        SimplexOptions o;
        o.xtol_abs.assign(6, p.min_step);
        o.ftol_abs = 1e-7;
        SimplexResult r{x, -cost.nmi(euler_of(x)), 1};
        int restarts = 0;
        while (evals < budget) {
            o.initial_step.assign(6, step_mm);
            o.max_evaluations = budget - evals;
            const SimplexResult s = nelder_mead(f, r.x, o, progress.cancel);
            const bool gained = s.f < r.f - 1e-6;
            if (s.f < r.f) r = {s.x, s.f, r.evaluations};
            if (!gained || step_mm <= 4 * p.min_step) break;
            step_mm *= 0.5;
            ++restarts;
        }
        x = r.x;
        best = r.f;
        itkb::CoregLevel info;
        info.iterations = evals;
        info.metric = r.f;
        info.seconds = std::chrono::duration<double>(Clock::now() - t_level).count();
        std::ostringstream stop;
        stop << "Nelder-Mead on NMI: " << evals << " evaluations of " << budget << ", " << restarts << " restarts, "
             << lv.points_world_mm.size() << " samples";
        info.stop = stop.str();
        out.levels.push_back(info);
    }
    const Eigen::Matrix<double, 6, 1> e = euler_of(x);
    for (int a = 0; a < 6; ++a) out.params[size_t(a)] = e[a];
    for (int a = 0; a < 3; ++a) out.center[size_t(a)] = center[a];
    itkb::euler_matrix(out.params, out.center, out.matrix, out.offset);
    out.metric = best;  // negative NMI (minimised), like ITK's negative MI
    return out;
}

}  // namespace cf::detail
