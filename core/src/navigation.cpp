// Navigation math: pivot calibration, paired-point fiducial registration with FRE/TRE,
// digitising and brain shift. See navigation.hpp for frames and references.
#include "cortexfuse/core/navigation.hpp"

#include <Eigen/Eigenvalues>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <map>
#include <numeric>
#include <sstream>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/error.hpp"

namespace cf {

namespace {

constexpr double kRadToDeg = 180.0 / 3.14159265358979323846;

bool finite(const Eigen::MatrixXd& m) { return m.allFinite(); }

void check_rigid(const RigidTransform& T, const std::string& input, size_t i) {
    if (!finite(T)) throw InputError(input, "pose " + std::to_string(i) + " has a non-finite value");
    // Tracker rotations come from normalised quaternions: orthonormal to rounding.
    if (!is_rigid(T, 1e-4)) throw InputError(input, "pose " + std::to_string(i) + " is not a rigid transform");
}

Eigen::Vector3d apply(const RigidTransform& T, const Eigen::Vector3d& p) {
    return T.topLeftCorner<3, 3>() * p + T.topRightCorner<3, 1>();
}

RigidTransform inverse(const RigidTransform& T) {
    RigidTransform inv = RigidTransform::Identity();
    const Eigen::Matrix3d Rt = T.topLeftCorner<3, 3>().transpose();
    inv.topLeftCorner<3, 3>() = Rt;
    inv.topRightCorner<3, 1>() = -Rt * T.topRightCorner<3, 1>();
    return inv;
}

double rotation_angle_deg(const Eigen::Matrix3d& R) {
    const double c = std::clamp((R.trace() - 1.0) / 2.0, -1.0, 1.0);
    return std::acos(c) * kRadToDeg;
}

/// Covariance eigen-decomposition of a point set about its centroid (eigenvalues ascending).
struct Spread {
    Eigen::Vector3d centroid;
    Eigen::Vector3d eigenvalues;  // ascending, mean squared extent along each axis
    Eigen::Matrix3d axes;         // columns, matching eigenvalues
    /// rms distance of the points from their best-fit line.
    double line_distance() const { return std::sqrt(std::max(0.0, eigenvalues(0) + eigenvalues(1))); }
};

Spread spread_of(const std::vector<Eigen::Vector3d>& pts, const std::vector<bool>& use) {
    Spread s;
    s.centroid.setZero();
    int n = 0;
    for (size_t i = 0; i < pts.size(); ++i)
        if (use[i]) s.centroid += pts[i], ++n;
    s.centroid /= double(n);
    Eigen::Matrix3d C = Eigen::Matrix3d::Zero();
    for (size_t i = 0; i < pts.size(); ++i)
        if (use[i]) {
            const Eigen::Vector3d x = pts[i] - s.centroid;
            C += x * x.transpose();
        }
    C /= double(n);
    Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es(C);
    s.eigenvalues = es.eigenvalues().cwiseMax(0.0);
    s.axes = es.eigenvectors();
    return s;
}

std::string mm(double v, int prec = 2) {
    char b[64];
    std::snprintf(b, sizeof b, "%.*f", prec, v);
    return b;
}

}  // namespace

// ------------------------------------------------------------------ pivot calibration

PivotResult pivot_calibration(const std::vector<RigidTransform>& T, const PivotOptions& options) {
    const std::string input = "pivot poses";
    if (!(options.min_rotation_spread_deg >= 0 && options.min_rotation_spread_deg <= 90))
        throw InputError("pivot min_rotation_spread_deg", "must be in [0, 90], got " + mm(options.min_rotation_spread_deg));
    if (T.size() < 3) throw InputError(input, "need at least 3 poses, got " + std::to_string(T.size()));
    for (size_t i = 0; i < T.size(); ++i) check_rigid(T[i], input, i);

    const size_t n = T.size();
    // How much the tip is constrained: M = mean (R_i - R̄)ᵀ (R_i - R̄). For a tip direction u,
    // uᵀ M u is the mean squared change of R_i u about its mean: the chord of the rotation
    // that moves u. Its smallest eigenvalue is the least-constrained direction (zero when the
    // pointer only spun about one axis: the tip along that axis is then undetermined).
    Eigen::Matrix3d Rbar = Eigen::Matrix3d::Zero();
    for (const auto& Ti : T) Rbar += Ti.topLeftCorner<3, 3>();
    Rbar /= double(n);
    Eigen::Matrix3d M = Eigen::Matrix3d::Zero();
    double range_deg = 0;
    const Eigen::Matrix3d R0 = T[0].topLeftCorner<3, 3>();
    for (const auto& Ti : T) {
        const Eigen::Matrix3d D = Ti.topLeftCorner<3, 3>() - Rbar;
        M += D.transpose() * D;
        range_deg = std::max(range_deg, rotation_angle_deg(R0.transpose() * Ti.topLeftCorner<3, 3>()));
    }
    M /= double(n);
    const double lmin = std::max(0.0, Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d>(M).eigenvalues()(0));
    const double chord = std::sqrt(lmin);
    const double spread_deg = 2.0 * std::asin(std::min(1.0, chord / 2.0)) * kRadToDeg;
    if (spread_deg < 0.01)
        throw InputError(input, "the poses do not constrain the tip: the pointer was not swivelled about two axes (rotation spread " +
                                    mm(spread_deg, 4) + " deg)");

    // R_i t - pivot = -p_i, stacked: [R_i  -I] [t; pivot] = -p_i. Least squares by SVD
    // (6 unknowns; the spread check above ensures full rank).
    Eigen::MatrixXd A(3 * n, 6);
    Eigen::VectorXd b(3 * n);
    for (size_t i = 0; i < n; ++i) {
        A.block<3, 3>(3 * i, 0) = T[i].topLeftCorner<3, 3>();
        A.block<3, 3>(3 * i, 3) = -Eigen::Matrix3d::Identity();
        b.segment<3>(3 * i) = -T[i].topRightCorner<3, 1>();
    }
    const Eigen::VectorXd x = A.jacobiSvd(Eigen::ComputeThinU | Eigen::ComputeThinV).solve(b);

    PivotResult r;
    r.tip_tool_mm = x.head<3>();
    r.pivot_tracker_mm = x.tail<3>();
    double ss = 0;
    for (size_t i = 0; i < n; ++i) {
        const double e = (apply(T[i], r.tip_tool_mm) - r.pivot_tracker_mm).norm();
        r.residuals_mm.push_back(e);
        ss += e * e;
    }
    r.rms_mm = std::sqrt(ss / double(n));
    r.rotation_spread_deg = spread_deg;
    r.rotation_range_deg = range_deg;
    if (spread_deg < options.min_rotation_spread_deg)
        r.warning = "the pointer did not move enough: rotation spread " + mm(spread_deg, 1) + " deg (want at least " +
                    mm(options.min_rotation_spread_deg, 1) +
                    " deg); swivel the handle further about two axes, the tip is poorly determined";
    else if (n < 10)
        r.warning = "only " + std::to_string(n) + " poses; 10 or more give a steadier tip";
    return r;
}

// ------------------------------------------------------ paired-point fiducial registration

FiducialRegistration register_fiducials(const std::vector<Eigen::Vector3d>& pp, const std::vector<Eigen::Vector3d>& pi,
                                        const FiducialOptions& o) {
    const std::string input = "fiducials";
    if (pp.size() != pi.size())
        throw InputError(input, std::to_string(pp.size()) + " patient points but " + std::to_string(pi.size()) + " image points");
    if (pp.size() < 3) throw InputError(input, "need at least 3 fiducials, got " + std::to_string(pp.size()));
    for (size_t i = 0; i < pp.size(); ++i)
        if (!pp[i].allFinite() || !pi[i].allFinite())
            throw InputError(input, "fiducial " + std::to_string(i) + " has a non-finite coordinate");
    if (std::isnan(o.outlier_threshold_mm) || std::isnan(o.fle_mm) || !(o.min_line_distance_mm >= 0))
        throw InputError("fiducial options", "outlier threshold, FLE and line distance must be numbers (line distance >= 0)");

    const size_t n = pp.size();
    std::vector<bool> used(n, true);
    for (const auto* set : {&pp, &pi}) {
        const double d = spread_of(*set, used).line_distance();
        if (d < o.min_line_distance_mm)
            throw InputError(input, std::string(set == &pp ? "patient" : "image") +
                                        " points are collinear (rms distance from their line " + mm(d, 3) + " mm < " +
                                        mm(o.min_line_distance_mm) + " mm): the rotation about that line is undetermined");
    }

    FiducialRegistration r;
    auto fit = [&] {
        const int m = int(std::count(used.begin(), used.end(), true));
        Eigen::Matrix3Xd src(3, m), dst(3, m);
        for (size_t i = 0, k = 0; i < n; ++i)
            if (used[i]) src.col(Eigen::Index(k)) = pp[i], dst.col(Eigen::Index(k)) = pi[i], ++k;
        r.T_image_from_patient = Eigen::umeyama(src, dst, false);
        r.residuals_mm.assign(n, 0.0);
        for (size_t i = 0; i < n; ++i) r.residuals_mm[i] = (apply(r.T_image_from_patient, pp[i]) - pi[i]).norm();
    };
    const bool exclude = o.outlier_threshold_mm > 0 && std::isfinite(o.outlier_threshold_mm);
    for (;;) {
        fit();
        if (!exclude || std::count(used.begin(), used.end(), true) <= 3) break;
        size_t worst = n;
        for (size_t i = 0; i < n; ++i)
            if (used[i] && (worst == n || r.residuals_mm[i] > r.residuals_mm[worst])) worst = i;
        if (r.residuals_mm[worst] <= o.outlier_threshold_mm) break;
        used[worst] = false;
        if (spread_of(pp, used).line_distance() < o.min_line_distance_mm ||
            spread_of(pi, used).line_distance() < o.min_line_distance_mm) {
            used[worst] = true;  // dropping it would leave a collinear set: keep it
            break;
        }
        r.excluded.push_back(int(worst));
    }
    if (!r.excluded.empty()) fit();  // residuals of all fiducials with the final transform

    double ss = 0;
    int m = 0;
    for (size_t i = 0; i < n; ++i)
        if (used[i]) ss += r.residuals_mm[i] * r.residuals_mm[i], ++m;
    r.used = used;
    r.n_used = m;
    r.fre_mm = std::sqrt(ss / m);
    r.fle_mm = o.fle_mm > 0 ? o.fle_mm : r.fre_mm * std::sqrt(double(m) / double(m - 2));
    const Spread s = spread_of(pi, used);
    r.centroid_image_mm = s.centroid;
    r.axes_image = s.axes;
    const double total = s.eigenvalues.sum();
    for (int k = 0; k < 3; ++k) r.rms_axis_distance_mm(k) = std::sqrt(std::max(0.0, total - s.eigenvalues(k)));
    return r;
}

double predicted_tre_mm(const FiducialRegistration& reg, const Eigen::Vector3d& target) {
    if (!target.allFinite()) throw InputError("TRE target", "has a non-finite coordinate");
    if (reg.n_used < 3) throw InputError("TRE", "registration has fewer than 3 fiducials");
    const Eigen::Vector3d r = target - reg.centroid_image_mm;
    double sum = 0;
    for (int k = 0; k < 3; ++k) {
        const double along = r.dot(reg.axes_image.col(k));
        const double d2 = std::max(0.0, r.squaredNorm() - along * along);
        const double f2 = reg.rms_axis_distance_mm(k) * reg.rms_axis_distance_mm(k);
        // f_k is 0 only for the long axis of a collinear set, which registration refuses.
        if (f2 > 0) sum += d2 / f2;
    }
    return std::sqrt(reg.fle_mm * reg.fle_mm / reg.n_used * (1.0 + sum / 3.0));
}

// ------------------------------------------------------------------ digitising, brain shift

DigitisedPoint digitise_point(const std::string& label, const std::vector<PointerFrame>& frames,
                              const Eigen::Vector3d& tip_tool_mm, const RigidTransform& T_image_from_patient,
                              double max_spread_mm) {
    const std::string input = "landmark " + label;
    if (frames.empty()) throw InputError(input, "no tracked frames");
    if (!tip_tool_mm.allFinite()) throw InputError(input, "pointer tip has a non-finite coordinate");
    check_rigid(T_image_from_patient, input + " T_image_from_patient", 0);
    std::vector<Eigen::Vector3d> pts;
    for (size_t i = 0; i < frames.size(); ++i) {
        check_rigid(frames[i].T_tracker_from_pointer, input + " pointer", i);
        check_rigid(frames[i].T_tracker_from_reference, input + " reference", i);
        pts.push_back(apply(inverse(frames[i].T_tracker_from_reference) * frames[i].T_tracker_from_pointer, tip_tool_mm));
    }
    DigitisedPoint d;
    d.label = label;
    d.frames = int(pts.size());
    for (const auto& p : pts) d.p_patient_mm += p;
    d.p_patient_mm /= double(pts.size());
    double ss = 0;
    for (const auto& p : pts) ss += (p - d.p_patient_mm).squaredNorm();
    d.spread_mm = std::sqrt(ss / double(pts.size()));
    if (d.spread_mm > max_spread_mm)
        throw InputError(input, "the pointer tip moved while digitising (rms " + mm(d.spread_mm) + " mm > " + mm(max_spread_mm) +
                                    " mm); hold it still and digitise again");
    d.p_image_mm = apply(T_image_from_patient, d.p_patient_mm);
    return d;
}

BrainShiftReport brain_shift(const std::vector<DigitisedPoint>& earlier, const std::vector<DigitisedPoint>& later) {
    auto index = [](const std::vector<DigitisedPoint>& v, const std::string& which) {
        std::map<std::string, size_t> m;
        for (size_t i = 0; i < v.size(); ++i) {
            if (!v[i].p_image_mm.allFinite()) throw InputError(which + " landmark " + v[i].label, "non-finite coordinate");
            if (!m.emplace(v[i].label, i).second) throw InputError(which + " landmarks", "label \"" + v[i].label + "\" appears twice");
        }
        return m;
    };
    const auto e = index(earlier, "earlier"), l = index(later, "later");
    BrainShiftReport r;
    for (const auto& d : later) {
        const auto it = e.find(d.label);
        if (it == e.end()) {
            r.missing_earlier.push_back(d.label);
            continue;
        }
        ShiftRow row;
        row.label = d.label;
        row.d_mm = d.p_image_mm - earlier[it->second].p_image_mm;
        row.magnitude_mm = row.d_mm.norm();
        r.rows.push_back(row);
    }
    for (const auto& d : earlier)
        if (!l.count(d.label)) r.missing_later.push_back(d.label);
    if (r.rows.empty()) throw InputError("brain shift", "no landmark label is in both digitisations");

    const double n = double(r.rows.size());
    for (const auto& row : r.rows) {
        r.mean_d_mm += row.d_mm;
        r.mean_abs_d_mm += row.d_mm.cwiseAbs();
        r.mean_magnitude_mm += row.magnitude_mm;
        r.max_magnitude_mm = std::max(r.max_magnitude_mm, row.magnitude_mm);
    }
    r.mean_d_mm /= n;
    r.mean_abs_d_mm /= n;
    r.mean_magnitude_mm /= n;
    if (r.rows.size() > 1) {
        Eigen::Vector3d v = Eigen::Vector3d::Zero();
        double vm = 0;
        for (const auto& row : r.rows) {
            v += (row.d_mm - r.mean_d_mm).cwiseAbs2();
            vm += (row.magnitude_mm - r.mean_magnitude_mm) * (row.magnitude_mm - r.mean_magnitude_mm);
        }
        r.sd_d_mm = (v / (n - 1)).cwiseSqrt();
        r.sd_magnitude_mm = std::sqrt(vm / (n - 1));
    }
    return r;
}

std::string format_brain_shift_table(const BrainShiftReport& r) {
    std::ostringstream os;
    char line[256];
    // Cells 12 columns wide; "±" is two bytes in UTF-8 but one column: pad to 13 bytes.
    auto pm = [&](double m, double sd) {
        std::snprintf(line, sizeof line, "%.2f±%.2f", m, sd);
        const std::string v(line);
        return " " + std::string(size_t(std::max(0, 13 - int(v.size()))), ' ') + v;
    };
    std::snprintf(line, sizeof line, "%-12s %12s %12s %12s %12s\n", "landmark", "dx mm", "dy mm", "dz mm", "|d| mm");
    os << line;
    for (const auto& row : r.rows) {
        std::snprintf(line, sizeof line, "%-12s %12.2f %12.2f %12.2f %12.2f\n", row.label.c_str(), row.d_mm.x(), row.d_mm.y(),
                      row.d_mm.z(), row.magnitude_mm);
        os << line;
    }
    const std::string mx = pm(r.mean_d_mm.x(), r.sd_d_mm.x()), my = pm(r.mean_d_mm.y(), r.sd_d_mm.y()),
                      mz = pm(r.mean_d_mm.z(), r.sd_d_mm.z()), mm_ = pm(r.mean_magnitude_mm, r.sd_magnitude_mm);
    os << "mean ± sd   " << mx << my << mz << mm_ << "\n";
    if (!r.missing_later.empty()) {
        os << "not re-digitised:";
        for (const auto& s : r.missing_later) os << " " << s;
        os << "\n";
    }
    if (!r.missing_earlier.empty()) {
        os << "no first digitisation:";
        for (const auto& s : r.missing_earlier) os << " " << s;
        os << "\n";
    }
    return os.str();
}

}  // namespace cf
