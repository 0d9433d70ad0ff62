// Rigid co-registration: the Eigen side (initialisation, quality gates, NMI, transform files
// and errors); the ITK registration itself is in itk_coregister.cpp.
#include "cortexfuse/core/coregistration.hpp"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <fstream>
#include <regex>
#include <sstream>

#include "cortexfuse/core/error.hpp"
#include "itk_coregister.hpp"
#include "itk_grid.hpp"
#include "joint_nmi.hpp"
#include "nmi_coregistration.hpp"

namespace cf {
namespace {

Eigen::Matrix4d to_matrix(const std::array<double, 9>& m, const std::array<double, 3>& o) {
    Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) T(r, c) = m[size_t(r * 3 + c)];
        T(r, 3) = o[size_t(r)];
    }
    return T;
}

void from_matrix(const Eigen::Matrix4d& T, std::array<double, 9>& m, std::array<double, 3>& o) {
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) m[size_t(r * 3 + c)] = T(r, c);
        o[size_t(r)] = T(r, 3);
    }
}

/// Percentile of a strided subsample (robust range without sorting 16M voxels).
std::pair<double, double> robust_range(const std::vector<float>& v, double lo, double hi) {
    std::vector<float> s;
    const size_t stride = std::max<size_t>(1, v.size() / 200000);
    s.reserve(v.size() / stride + 1);
    for (size_t i = 0; i < v.size(); i += stride)
        if (std::isfinite(v[i])) s.push_back(v[i]);
    if (s.empty()) return {0, 0};
    auto pct = [&](double p) {
        const size_t k = size_t(p * double(s.size() - 1));
        std::nth_element(s.begin(), s.begin() + long(k), s.end());
        return double(s[k]);
    };
    return {pct(lo), pct(hi)};
}

bool trilinear(const Volume& v, const Eigen::Vector3d& ijk, float& out) {
    const auto& d = v.geom.dims;
    if (!(ijk.x() >= 0 && ijk.y() >= 0 && ijk.z() >= 0 && ijk.x() <= d[0] - 1 && ijk.y() <= d[1] - 1 && ijk.z() <= d[2] - 1))
        return false;
    const int i = std::min(int(ijk.x()), d[0] - 2 < 0 ? 0 : d[0] - 2), j = std::min(int(ijk.y()), d[1] - 2 < 0 ? 0 : d[1] - 2),
              k = std::min(int(ijk.z()), d[2] - 2 < 0 ? 0 : d[2] - 2);
    const double fx = ijk.x() - i, fy = ijk.y() - j, fz = ijk.z() - k;
    auto at = [&](int a, int b, int c) {
        return double(v.at(std::min(a, d[0] - 1), std::min(b, d[1] - 1), std::min(c, d[2] - 1)));
    };
    const double c00 = at(i, j, k) * (1 - fx) + at(i + 1, j, k) * fx, c10 = at(i, j + 1, k) * (1 - fx) + at(i + 1, j + 1, k) * fx;
    const double c01 = at(i, j, k + 1) * (1 - fx) + at(i + 1, j, k + 1) * fx,
                 c11 = at(i, j + 1, k + 1) * (1 - fx) + at(i + 1, j + 1, k + 1) * fx;
    out = float((c00 * (1 - fy) + c10 * fy) * (1 - fz) + (c01 * (1 - fy) + c11 * fy) * fz);
    return true;
}

/// Fraction of the mask's voxels (strided) whose transformed centre lies inside `other`.
double overlap_fraction(const LabelVolume& mask, const Eigen::Matrix4d& T, const VolumeGeometry& other) {
    const Eigen::Affine3d W = mask.geom.world_from_index();
    const Eigen::Affine3d I = other.index_from_world();
    const auto& d = mask.geom.dims;
    size_t n = 0, in = 0;
    for (int k = 0; k < d[2]; k += 2)
        for (int j = 0; j < d[1]; j += 2)
            for (int i = 0; i < d[0]; i += 2) {
                if (!mask.at(i, j, k)) continue;
                ++n;
                const Eigen::Vector3d p = W * Eigen::Vector3d(i, j, k);
                const Eigen::Vector3d q = I * (T.topLeftCorner<3, 3>() * p + T.topRightCorner<3, 1>());
                in += q.x() >= -0.5 && q.y() >= -0.5 && q.z() >= -0.5 && q.x() <= other.dims[0] - 0.5 &&
                      q.y() <= other.dims[1] - 0.5 && q.z() <= other.dims[2] - 0.5;
            }
    return n ? double(in) / double(n) : 0.0;
}

Eigen::Vector3d centroid(const LabelVolume& m) {
    const Eigen::Affine3d W = m.geom.world_from_index();
    Eigen::Vector3d s = Eigen::Vector3d::Zero();
    size_t n = 0;
    const auto& d = m.geom.dims;
    for (int k = 0; k < d[2]; ++k)
        for (int j = 0; j < d[1]; ++j)
            for (int i = 0; i < d[0]; ++i)
                if (m.at(i, j, k)) s += Eigen::Vector3d(i, j, k), ++n;
    if (!n) return m.geom.center_world_mm();
    return W * (s / double(n));
}

/// The volume's voxels clipped to [p0.5 - 0.25 span, p99.5] of its foreground's voxels
/// (CoregParams::clip_intensities).
std::vector<float> clipped_to_foreground_range(const Volume& v, const LabelVolume& fg) {
    std::vector<float> inside;
    inside.reserve(fg.count_nonzero());
    for (size_t i = 0; i < v.voxels.size(); ++i)
        if (fg.voxels[i]) inside.push_back(v.voxels[i]);
    const auto [lo, hi] = robust_range(inside, 0.005, 0.995);
    const float a = float(lo - 0.25 * (hi - lo)), b = float(hi);
    std::vector<float> out(v.voxels.size());
    if (!(b > a)) {
        std::copy(v.voxels.begin(), v.voxels.end(), out.begin());
        return out;
    }
    for (size_t i = 0; i < out.size(); ++i) out[i] = std::clamp(v.voxels[i], a, b);
    return out;
}

void check_volume(const Volume& v, const char* what) {
    if (v.geom.voxel_count() == 0 || v.voxels.size() != v.geom.voxel_count())
        throw InputError(what, "empty volume or voxel count does not match its grid");
    for (int a = 0; a < 3; ++a)
        if (v.geom.dims[size_t(a)] < 4) throw InputError(what, "fewer than 4 voxels along an axis");
}

}  // namespace

void CoregParams::validate() const {
    auto bad = [](const char* f, const char* why) { throw InputError(std::string("coregister ") + f, why); };
    if (bins < 8 || bins > 256) bad("bins", "must be in [8, 256]");
    if (shrink.empty() || shrink.size() > 8) bad("shrink", "1 to 8 levels");
    if (smooth_mm.size() != shrink.size()) bad("smooth_mm", "one sigma per level");
    for (int s : shrink)
        if (s < 1 || s > 16) bad("shrink", "factors must be in [1, 16]");
    for (double s : smooth_mm)
        if (!(s >= 0 && s <= 20)) bad("smooth_mm", "sigmas must be in [0, 20] mm");
    if (iterations.empty()) bad("iterations", "at least one value");
    for (int it : iterations)
        if (it < 1 || it > 10000) bad("iterations", "must be in [1, 10000]");
    if (!(sampling > 0 && sampling <= 1)) bad("sampling", "must be in (0, 1]");
    if (!(max_step > 0 && max_step <= 50)) bad("max_step", "must be in (0, 50]");
    if (!(min_step > 0 && min_step < max_step)) bad("min_step", "must be in (0, max_step)");
    if (!(relaxation > 0 && relaxation < 1)) bad("relaxation", "must be in (0, 1)");
    if (!(min_overlap >= 0 && min_overlap <= 1)) bad("min_overlap", "must be in [0, 1]");
    if (!(min_nmi >= 1 && min_nmi <= 2)) bad("min_nmi", "must be in [1, 2]");
    if (!(probe_mm >= 0 && probe_mm <= 20)) bad("probe_mm", "must be in [0, 20]");
    if (!(probe_deg >= 0 && probe_deg <= 20)) bad("probe_deg", "must be in [0, 20]");
    if (!(max_probe_gain >= 0 && max_probe_gain <= 1)) bad("max_probe_gain", "must be in [0, 1]");
}

LabelVolume head_foreground(const Volume& v) {
    const auto [p02, p98] = robust_range(v.voxels, 0.02, 0.98);
    const float t = float(p02 + 0.1 * (p98 - p02));
    LabelVolume m;
    m.geom = v.geom;
    m.voxels.resize(v.voxels.size());
    for (size_t i = 0; i < v.voxels.size(); ++i) m.voxels[i] = v.voxels[i] > t ? 1 : 0;
    return m;
}

double nmi_after_transform(const Volume& a, const Volume& b, const Eigen::Matrix4d& T, const LabelVolume* mask_a, int bins) {
    const auto [alo, ahi] = robust_range(a.voxels, 0.01, 0.99);
    const auto [blo, bhi] = robust_range(b.voxels, 0.01, 0.99);
    if (!(ahi > alo) || !(bhi > blo)) return 1.0;  // a constant image shares nothing
    const Eigen::Affine3d W = a.geom.world_from_index();
    const Eigen::Affine3d I = b.geom.index_from_world();
    std::vector<double> joint(size_t(bins) * bins, 0.0);
    const auto& d = a.geom.dims;
    double n = 0;
    for (int k = 0; k < d[2]; k += 2)
        for (int j = 0; j < d[1]; j += 2)
            for (int i = 0; i < d[0]; i += 2) {
                if (mask_a && !mask_a->at(i, j, k)) continue;
                const Eigen::Vector3d p = W * Eigen::Vector3d(i, j, k);
                const Eigen::Vector3d q = I * (T.topLeftCorner<3, 3>() * p + T.topRightCorner<3, 1>());
                float vb;
                if (!trilinear(b, q, vb)) continue;
                const int ba = std::clamp(int((a.at(i, j, k) - alo) / (ahi - alo) * bins), 0, bins - 1);
                const int bb = std::clamp(int((vb - blo) / (bhi - blo) * bins), 0, bins - 1);
                joint[size_t(ba) * bins + bb] += 1, n += 1;
            }
    if (n < 100) return 1.0;
    return detail::nmi_of_joint(joint, bins, n);
}

CoregResult coregister(const Volume& fixed, const Volume& moving, const CoregParams& p, const Progress& progress) {
    p.validate();
    check_volume(fixed, "fixed volume");
    check_volume(moving, "moving volume");
    const auto t0 = std::chrono::steady_clock::now();
    progress("coregister", 0.0);
    progress.check();
    const LabelVolume ffg = head_foreground(fixed);
    const LabelVolume mfg = head_foreground(moving);
    const size_t nf = ffg.count_nonzero(), nm = mfg.count_nonzero();
    if (nf < 1000) throw InputError("fixed volume", "no foreground (an empty or constant volume?)");
    if (nm < 1000) throw InputError("moving volume", "no foreground (an empty or constant volume?)");

    itkb::CoregConfig cfg;
    cfg.metric = p.metric == CoregParams::Metric::Mattes ? 0 : 1;
    cfg.bins = p.bins;
    cfg.shrink = p.shrink;
    cfg.smooth_mm = p.smooth_mm;
    cfg.iterations = p.iterations;
    // The sample count is `sampling` x the fixed head's voxels either way; without the head
    // mask the samples spread over the whole fixed grid (air and the dark skull of a T1 too).
    const bool head_mask = p.fixed_foreground_mask;
    cfg.sampling = head_mask ? p.sampling : std::min(1.0, p.sampling * double(nf) / double(fixed.geom.voxel_count()));
    cfg.max_step = p.max_step;
    cfg.min_step = p.min_step;
    cfg.relaxation = p.relaxation;
    cfg.seed = p.seed;
    Eigen::Vector3d c_f = fixed.geom.center_world_mm(), t = Eigen::Vector3d::Zero();
    if (p.init == CoregParams::Init::Centroids) {
        c_f = centroid(ffg);
        t = centroid(mfg) - c_f;
    } else if (p.init == CoregParams::Init::Geometry) {
        t = moving.geom.center_world_mm() - c_f;
    }
    for (int a = 0; a < 3; ++a) cfg.center[size_t(a)] = c_f[a], cfg.initial[size_t(3 + a)] = t[a];

    const size_t nlev = p.shrink.size();
    const itkb::CoregStepFn step = [&](int level, double f) {
        progress("coregister", std::min(0.95, (double(level) + f) / double(nlev) * 0.95));
        return !(progress.cancel && progress.cancel->cancelled());
    };
    itkb::CoregOutput out;
    if (p.metric == CoregParams::Metric::Nmi) {
        // True NMI, optimised without derivatives (nmi_coregistration.cpp says why not ITK).
        Volume fv, mv;
        fv.geom = fixed.geom, mv.geom = moving.geom;
        fv.voxels = p.clip_intensities ? clipped_to_foreground_range(fixed, ffg) : fixed.voxels;
        mv.voxels = p.clip_intensities ? clipped_to_foreground_range(moving, mfg) : moving.voxels;
        const size_t samples = size_t(std::max(1000.0, p.sampling * double(nf)));
        out = detail::nmi_coregister(fv, mv, head_mask ? &ffg : nullptr, samples, p, c_f, t, progress);
    } else if (p.clip_intensities) {
        const std::vector<float> fc = clipped_to_foreground_range(fixed, ffg), mc = clipped_to_foreground_range(moving, mfg);
        itkb::coregister_rigid(itkb::to_grid(fixed.geom), fc.data(), itkb::to_grid(moving.geom), mc.data(),
                               head_mask ? ffg.voxels.data() : nullptr, cfg, step, out);
    } else {
        itkb::coregister_rigid(itkb::to_grid(fixed.geom), fixed.voxels.data(), itkb::to_grid(moving.geom), moving.voxels.data(),
                               head_mask ? ffg.voxels.data() : nullptr, cfg, step, out);
    }

    CoregResult r;
    r.T_moving_from_fixed = to_matrix(out.matrix, out.offset);
    r.center_world_mm = Eigen::Vector3d(out.center[0], out.center[1], out.center[2]);
    r.T_initial = Eigen::Matrix4d::Identity();
    r.T_initial.topRightCorner<3, 1>() = t;
    r.metric = out.metric;
    for (const auto& l : out.levels) r.levels.push_back({l.iterations, l.metric, l.seconds, l.stop});
    r.overlap = overlap_fraction(ffg, r.T_moving_from_fixed, moving.geom);
    r.nmi = nmi_after_transform(fixed, moving, r.T_moving_from_fixed, &ffg, 64);
    // Optimum probe: NMI with the result moved by +-probe_mm along each world axis and turned by
    // +-probe_deg about each axis through the rotation centre (fixed side). At a true optimum every
    // probe lowers the NMI; a result more than about half a probe off the NMI optimum has a
    // probe that raises it. Only for the NMI metric, whose optimiser stalls on CT-like images:
    // a Mattes result need not sit at the NMI optimum (on the daemon test's 2 mm CT a 2 mm probe
    // raised the NMI by 0.0027 at a correct registration), and Mattes converges on every input
    // of the benchmark.
    const bool probe = p.probe_mm > 0 && p.metric == CoregParams::Metric::Nmi;
    if (probe) {
        const Eigen::Vector3d c = r.center_world_mm;
        for (int a = 0; a < 6; ++a)
            for (double sgn : {-1.0, 1.0}) {
                Eigen::Affine3d P = Eigen::Affine3d::Identity();
                if (a < 3) {
                    P.translation()[a] = sgn * p.probe_mm;
                } else {
                    P = Eigen::Translation3d(c) * Eigen::AngleAxisd(sgn * p.probe_deg * M_PI / 180.0, Eigen::Vector3d::Unit(a - 3)) *
                        Eigen::Translation3d(-c);
                }
                const double n = nmi_after_transform(fixed, moving, r.T_moving_from_fixed * P.matrix(), &ffg, 64);
                r.probe_gain = std::max(r.probe_gain, n - r.nmi);
            }
    }
    r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
    progress("coregister", 1.0);
    if (r.overlap < p.min_overlap) {
        std::ostringstream s;
        s.precision(2);
        s << "absurd overlap after registration: only " << r.overlap * 100
          << " % of the fixed head lies inside the moving volume (another body part, field of view or patient?)";
        throw InputError("moving volume", s.str());
    }
    if (r.nmi < p.min_nmi) {
        std::ostringstream s;
        s.precision(4);
        s << "no shared structure after registration (NMI " << r.nmi << " < " << p.min_nmi
          << "): another patient, an empty map, or a failed registration";
        throw InputError("moving volume", s.str());
    }
    if (probe && r.probe_gain > p.max_probe_gain) {
        std::ostringstream s;
        s.precision(3);
        s << "the registration did not reach the NMI optimum (moving the result by " << p.probe_mm << " mm / "
          << p.probe_deg << " deg raises the NMI by " << r.probe_gain << " > " << p.max_probe_gain
          << "): not converged; try --metric mattes";
        throw InputError("moving volume", s.str());
    }
    return r;
}

Volume resample_rigid(const Volume& moving, const Eigen::Matrix4d& T, const VolumeGeometry& grid, bool nearest, float outside) {
    check_volume(moving, "moving volume");
    std::array<double, 9> m;
    std::array<double, 3> o;
    from_matrix(T, m, o);
    Volume out;
    out.geom = grid;
    itkb::resample_transformed(itkb::to_grid(moving.geom), moving.voxels.data(), m, o, itkb::to_grid(grid), nearest, outside, out.voxels);
    return out;
}

void save_transform(const Eigen::Matrix4d& T, const Eigen::Vector3d& c, const std::filesystem::path& path) {
    std::string ext = path.extension().string();
    std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char ch) { return char(std::tolower(ch)); });
    if (ext != ".tfm" && ext != ".txt" && ext != ".h5" && ext != ".hdf5")
        throw InputError(path.string(), "unknown transform format (use .tfm, .txt, .h5)");
    if (!T.allFinite()) throw InputError(path.string(), "transform is not finite");
    std::array<double, 9> m;
    std::array<double, 3> o;
    from_matrix(T, m, o);
    itkb::write_rigid_transform(path.string(), m, o, {c.x(), c.y(), c.z()});
}

Eigen::Matrix4d euler_transform(const Eigen::Vector3d& ang, const Eigen::Vector3d& tr, const Eigen::Vector3d& c) {
    std::array<double, 9> m;
    std::array<double, 3> o;
    itkb::euler_matrix({ang.x(), ang.y(), ang.z(), tr.x(), tr.y(), tr.z()}, {c.x(), c.y(), c.z()}, m, o);
    return to_matrix(m, o);
}

Eigen::Matrix4d load_transform(const std::filesystem::path& path) {
    if (!std::filesystem::is_regular_file(path)) throw InputError(path.string(), "no such transform file");
    {
        // elastix's TransformParameters.N.txt: "(Transform "EulerTransform")" ... parsed here
        // so that the benchmark compares both tools through one error function.
        std::ifstream f(path);
        std::stringstream ss;
        ss << f.rdbuf();
        const std::string s = ss.str();
        if (s.find("(Transform \"EulerTransform\")") != std::string::npos) {
            auto numbers = [&](const char* key) {
                std::vector<double> v;
                const std::regex re(std::string("\\(") + key + "([^)]*)\\)");
                std::smatch m;
                if (!std::regex_search(s, m, re)) throw InputError(path.string(), std::string("elastix file without ") + key);
                std::istringstream in(m[1].str());
                double x;
                while (in >> x) v.push_back(x);
                return v;
            };
            const auto tp = numbers("TransformParameters");
            const auto cr = numbers("CenterOfRotationPoint");
            if (tp.size() != 6 || cr.size() != 3) throw InputError(path.string(), "elastix Euler transform needs 6 parameters");
            if (s.find("(ComputeZYX \"true\")") != std::string::npos)
                throw InputError(path.string(), "elastix ComputeZYX true is not supported");
            return euler_transform({tp[0], tp[1], tp[2]}, {tp[3], tp[4], tp[5]}, {cr[0], cr[1], cr[2]});
        }
    }
    std::array<double, 9> m;
    std::array<double, 3> o;
    itkb::read_rigid_transform(path.string(), m, o);
    return to_matrix(m, o);
}

TransformError transform_error(const Eigen::Matrix4d& A, const Eigen::Matrix4d& B, const LabelVolume& mask) {
    TransformError e;
    const Eigen::Affine3d W = mask.geom.world_from_index();
    const auto& d = mask.geom.dims;
    double sum = 0;
    for (int k = 0; k < d[2]; ++k)
        for (int j = 0; j < d[1]; ++j)
            for (int i = 0; i < d[0]; ++i) {
                if (!mask.at(i, j, k)) continue;
                const Eigen::Vector4d p = (W * Eigen::Vector3d(i, j, k)).homogeneous();
                const double dist = ((A - B) * p).head<3>().norm();
                sum += dist;
                e.max_mm = std::max(e.max_mm, dist);
                ++e.points;
            }
    if (!e.points) throw InputError("brain mask", "empty: no voxel to measure the error on");
    e.mean_mm = sum / double(e.points);
    return e;
}

}  // namespace cf

#include <random>

namespace cf {

namespace {

/// A synthetic moving image: the T1 remapped through `lut` (normalised T1 level -> value,
/// piecewise linear), optionally blurred on the T1's grid, moved by a random rigid transform
/// and resampled onto an identity-direction grid of `spacing` covering the moved head, noise added.
SyntheticCoregCase make_synthetic_case(const Volume& t1, uint64_t seed, double max_angle_deg, double max_shift_mm,
                                       const Eigen::Vector3d& spacing, const std::vector<std::pair<double, double>>& lut,
                                       double blur_fwhm_mm, double noise, float outside) {
    check_volume(t1, "T1 volume");
    std::mt19937_64 rng(seed);
    std::uniform_real_distribution<double> u(-1.0, 1.0);
    SyntheticCoregCase c;
    c.angles_deg = Eigen::Vector3d(u(rng), u(rng), u(rng)) * max_angle_deg;
    c.translation_mm = Eigen::Vector3d(u(rng), u(rng), u(rng)) * max_shift_mm;
    const Eigen::Vector3d center = t1.geom.center_world_mm();
    c.T_moving_from_fixed = euler_transform(c.angles_deg * M_PI / 180.0, c.translation_mm, center);

    // Identity direction, covering the moved head's bounding box.
    const Eigen::Affine3d W = t1.geom.world_from_index();
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e18), hi = -lo;
    const auto& d = t1.geom.dims;
    for (int corner = 0; corner < 8; ++corner) {
        const Eigen::Vector3d ijk((corner & 1) ? d[0] - 1 : 0, (corner & 2) ? d[1] - 1 : 0, (corner & 4) ? d[2] - 1 : 0);
        const Eigen::Vector3d q = c.T_moving_from_fixed.topLeftCorner<3, 3>() * (W * ijk) + c.T_moving_from_fixed.topRightCorner<3, 1>();
        lo = lo.cwiseMin(q), hi = hi.cwiseMax(q);
    }
    VolumeGeometry g;
    g.spacing_mm = spacing;
    g.origin_mm = lo;
    for (int a = 0; a < 3; ++a) g.dims[size_t(a)] = int(std::ceil((hi[a] - lo[a]) / g.spacing_mm[a])) + 1;
    if (g.voxel_count() > kMaxVoxels) throw InputError("synthetic case", "moving grid too large");

    // Remap intensities on the T1's own grid first (the remap is pointwise), then blur, then resample.
    const auto [p02, p98] = robust_range(t1.voxels, 0.02, 0.98);
    const double span = std::max(1e-6, p98 - p02);
    Volume remapped;
    remapped.geom = t1.geom;
    remapped.voxels.resize(t1.voxels.size());
    for (size_t i = 0; i < t1.voxels.size(); ++i) {
        const double x = (t1.voxels[i] - p02) / span;
        double y = lut.back().second;
        if (x <= lut.front().first) y = lut.front().second;
        for (size_t q = 0; q + 1 < lut.size(); ++q)
            if (x >= lut[q].first && x < lut[q + 1].first) {
                const double f = (x - lut[q].first) / (lut[q + 1].first - lut[q].first);
                y = lut[q].second * (1 - f) + lut[q + 1].second * f;
                break;
            }
        remapped.voxels[i] = float(y);
    }
    // FWHM = 2 sqrt(2 ln 2) sigma.
    itkb::smooth_gaussian(itkb::to_grid(remapped.geom), remapped.voxels, blur_fwhm_mm / 2.354820045);
    // moving(q) = remapped(T^-1 q): resample through the fixed-from-moving transform.
    c.moving = resample_rigid(remapped, c.T_moving_from_fixed.inverse(), g, false, outside);
    std::normal_distribution<double> n(0.0, noise);
    for (auto& v : c.moving.voxels) v = float(v + n(rng));
    return c;
}

}  // namespace

SyntheticCoregCase make_synthetic_ct_case(const Volume& t1, uint64_t seed, double max_angle_deg, double max_shift_mm,
                                          double inplane_mm, double slice_mm, double noise_hu) {
    if (!(inplane_mm >= 0.2 && inplane_mm <= 5 && slice_mm >= 0.2 && slice_mm <= 10))
        throw InputError("synthetic case", "voxel size out of [0.2, 5] mm in-plane / [0.2, 10] mm slices");
    // Normalised T1 level -> CT-like value (piecewise linear, non-monotonic: white matter
    // darker than grey, fat negative), so that the two images relate by MI only.
    return make_synthetic_case(t1, seed, max_angle_deg, max_shift_mm, Eigen::Vector3d(inplane_mm, inplane_mm, slice_mm),
                               {{0.0, -1000}, {0.08, -1000}, {0.2, 12}, {0.45, 42}, {0.7, 28}, {0.9, -60}, {1.3, -100}}, 0.0,
                               noise_hu, -1000.f);
}

SyntheticCoregCase make_synthetic_epi_case(const Volume& t1, uint64_t seed, double max_angle_deg, double max_shift_mm,
                                           double voxel_mm, double blur_fwhm_mm, double noise) {
    if (!(voxel_mm >= 1 && voxel_mm <= 6)) throw InputError("synthetic case", "EPI voxel size out of [1, 6] mm");
    if (!(blur_fwhm_mm >= 0 && blur_fwhm_mm <= 12)) throw InputError("synthetic case", "EPI blur out of [0, 12] mm FWHM");
    // Normalised T1 level -> T2*-like mean EPI value: dark air, CSF brightest, grey above
    // white (the T1's order reversed), fat suppressed: non-monotonic.
    return make_synthetic_case(t1, seed, max_angle_deg, max_shift_mm, Eigen::Vector3d::Constant(voxel_mm),
                               {{0.0, 0}, {0.08, 0}, {0.2, 1000}, {0.45, 620}, {0.7, 450}, {0.9, 120}, {1.3, 80}}, blur_fwhm_mm,
                               noise, 0.f);
}

}  // namespace cf
