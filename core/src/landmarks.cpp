#include "cortexfuse/core/landmarks.hpp"

#include <opencv2/calib3d.hpp>
#include <opencv2/core/eigen.hpp>

#include <Eigen/Geometry>
#include <Eigen/SVD>

#include <algorithm>
#include <cmath>
#include <optional>

#include "cortexfuse/core/error.hpp"

namespace cf {

double reprojection_rms_px(const std::vector<Landmark>& lms, const Intrinsics& K, const Pose& T) {
    if (lms.empty()) return 0;
    double s = 0;
    for (const auto& l : lms) {
        const auto p = project(K, T, l.world_mm);
        s += p ? (*p - l.pixel).squaredNorm() : 1e8;
    }
    return std::sqrt(s / double(lms.size()));
}

namespace {
/// The landmark pairs and camera as OpenCV's PnP functions take them.
struct PnpProblem {
    std::vector<cv::Point3d> obj;
    std::vector<cv::Point2d> img;
    cv::Matx33d Kcv;
    std::vector<double> dist;
    PnpProblem(const std::vector<Landmark>& lms, const Intrinsics& K)
        : Kcv(K.fx, 0, K.cx, 0, K.fy, K.cy, 0, 0, 1), dist(K.distortion.begin(), K.distortion.end()) {
        for (const auto& l : lms) {
            obj.emplace_back(l.world_mm.x(), l.world_mm.y(), l.world_mm.z());
            img.emplace_back(l.pixel.x(), l.pixel.y());
        }
    }
};

/// OpenCV's rotation vector and translation of a pose (what solvePnPRefineLM starts from).
void rvec_tvec_from_pose(const Pose& T, cv::Mat& rvec, cv::Mat& tvec) {
    cv::Mat R(3, 3, CV_64F);
    tvec.create(3, 1, CV_64F);
    for (int r = 0; r < 3; ++r) {
        for (int k = 0; k < 3; ++k) R.at<double>(r, k) = T(r, k);
        tvec.at<double>(r) = T(r, 3);
    }
    cv::Rodrigues(R, rvec);
}

Eigen::Vector3d landmark_centroid(const std::vector<Landmark>& lms) {
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (const auto& l : lms) c += l.world_mm;
    return c / double(lms.size());
}

// The normal of the plane nearest the landmarks' model points (least squares): the cortical
// patch they were picked on.
Eigen::Vector3d landmark_plane_normal(const std::vector<Landmark>& lms) {
    const Eigen::Vector3d mean = landmark_centroid(lms);
    Eigen::MatrixXd M(long(lms.size()), 3);
    for (size_t i = 0; i < lms.size(); ++i) M.row(long(i)) = (lms[i].world_mm - mean).transpose();
    const Eigen::JacobiSVD<Eigen::MatrixXd> svd(M, Eigen::ComputeThinV);
    return svd.matrixV().col(2);
}

Pose pose_from_rvec(const cv::Mat& rvec, const cv::Mat& tvec) {
    cv::Mat R;
    cv::Rodrigues(rvec, R);
    Pose T = Pose::Identity();
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) T(r, c) = R.at<double>(r, c);
        T(r, 3) = tvec.at<double>(r);
    }
    return T;
}

bool in_front(const std::vector<Landmark>& lms, const Pose& T) {
    for (const auto& l : lms)
        if ((T.topLeftCorner<3, 3>() * l.world_mm + T.topRightCorner<3, 1>()).z() <= 0) return false;
    return true;
}

/// Levenberg-Marquardt over every pair from (rvec, tvec): the fit it reaches, or nullopt when
/// OpenCV fails, or the pose is not finite or leaves a landmark behind the camera
/// (pnp_candidates' seeds and refine_landmark_fit()).
std::optional<LandmarkFit> refined_fit(const PnpProblem& pnp, const std::vector<Landmark>& lms, const Intrinsics& K,
                                       cv::Mat rvec, cv::Mat tvec, const char* method) {
    try {
        cv::solvePnPRefineLM(pnp.obj, pnp.img, pnp.Kcv, pnp.dist, rvec, tvec);
    } catch (const cv::Exception&) {
        return std::nullopt;
    }
    LandmarkFit f;
    f.T_camera_from_world = pose_from_rvec(rvec, tvec);
    if (!f.T_camera_from_world.allFinite() || !in_front(lms, f.T_camera_from_world)) return std::nullopt;
    f.rms_px = reprojection_rms_px(lms, K, f.T_camera_from_world);
    f.method = method;
    for (size_t i = 0; i < lms.size(); ++i) f.inliers.push_back(int(i));
    return f;
}
}  // namespace

LandmarkFit fit_pose_pnp(const std::vector<Landmark>& lms, const Intrinsics& K) {
    if (lms.size() < 4) throw InputError("landmarks", "needs at least 4 pairs for a pose");
    const PnpProblem pnp(lms, K);
    const auto& [obj, img, Kcv, dist] = pnp;
    cv::Mat rvec, tvec;
    LandmarkFit fit;
    bool ok = false;
    if (lms.size() >= 6) {
        std::vector<int> inl;
        // 1.5 % of the image width: a few pixels of picking noise pass, a mislabelled pair does not.
        const double thr = std::max(4.0, 0.015 * K.width);
        ok = cv::solvePnPRansac(obj, img, Kcv, dist, rvec, tvec, false, 200, float(thr), 0.99, inl, cv::SOLVEPNP_SQPNP);
        if (ok && inl.size() >= 4) {
            fit.inliers = inl;
            fit.method = "pnp-ransac";
            std::vector<cv::Point3d> o2;
            std::vector<cv::Point2d> i2;
            for (int i : inl) {
                o2.push_back(obj[size_t(i)]);
                i2.push_back(img[size_t(i)]);
            }
            cv::solvePnPRefineLM(o2, i2, Kcv, dist, rvec, tvec);
        } else {
            ok = false;
        }
    }
    if (!ok) {
        ok = cv::solvePnP(obj, img, Kcv, dist, rvec, tvec, false, cv::SOLVEPNP_SQPNP);
        if (ok) cv::solvePnPRefineLM(obj, img, Kcv, dist, rvec, tvec);
        fit.method = "pnp";
        fit.inliers.clear();
        for (size_t i = 0; i < lms.size(); ++i) fit.inliers.push_back(int(i));
    }
    if (!ok) throw InputError("landmarks", "no camera pose fits the landmark pairs");
    fit.T_camera_from_world = pose_from_rvec(rvec, tvec);
    if (!in_front(lms, fit.T_camera_from_world)) throw InputError("landmarks", "the fitted pose puts landmarks behind the camera; check the pairs");
    fit.rms_px = reprojection_rms_px(lms, K, fit.T_camera_from_world);
    return fit;
}

LandmarkFit refine_landmark_fit(const std::vector<Landmark>& lms, const Intrinsics& K, const Pose& T_start) {
    cv::Mat rvec, tvec;
    try {
        rvec_tvec_from_pose(T_start, rvec, tvec);
    } catch (const cv::Exception& e) {
        throw InputError("landmarks", std::string("the given pose is not a rotation OpenCV can take: ") + e.what());
    }
    std::optional<LandmarkFit> f = refined_fit(PnpProblem(lms, K), lms, K, rvec, tvec, "refined");
    if (!f) throw InputError("landmarks", "refined from the given pose, the fit fails or puts landmarks behind the camera");
    return *f;
}

double landmark_px_per_mm(const std::vector<Landmark>& lms, const Intrinsics& K, const Pose& T) {
    if (lms.empty()) return 0;
    const double z = (T.topLeftCorner<3, 3>() * landmark_centroid(lms) + T.topRightCorner<3, 1>()).z();
    return z > 0 ? 0.5 * (K.fx + K.fy) / z : 0.0;
}

std::vector<LandmarkFit> pnp_candidates(const std::vector<Landmark>& lms, const Intrinsics& K, double world_sd_mm,
                                        double min_sep_deg) {
    std::vector<LandmarkFit> out{fit_pose_pnp(lms, K)};
    const PnpProblem pnp(lms, K);
    const auto& [obj, img, Kcv, dist] = pnp;
    auto consider = [&](cv::Mat rvec, cv::Mat tvec, const char* method) {
        std::optional<LandmarkFit> f = refined_fit(pnp, lms, K, rvec, tvec, method);
        if (!f) return;
        for (const auto& o : out) {
            const Eigen::Matrix3d dR = o.T_camera_from_world.topLeftCorner<3, 3>().transpose() * f->T_camera_from_world.topLeftCorner<3, 3>();
            if (Eigen::AngleAxisd(dR).angle() * 180.0 / M_PI < min_sep_deg) return;
        }
        out.push_back(*f);
    };
    // Other minimisers land in the other basin when it exists.
    for (int flag : {cv::SOLVEPNP_EPNP, cv::SOLVEPNP_ITERATIVE}) {
        cv::Mat rvec, tvec;
        try {
            if (cv::solvePnP(obj, img, Kcv, dist, rvec, tvec, false, flag)) consider(rvec, tvec, "pnp");
        } catch (const cv::Exception&) {
        }
    }
    // The mirror of the best pose: tilt the view about the landmarks' centroid, then refine.
    {
        const Pose T = out.front().T_camera_from_world;  // a copy: consider() grows `out`
        const Eigen::Vector3d pc = T.topLeftCorner<3, 3>() * landmark_centroid(lms) + T.topRightCorner<3, 1>();
        // The best pose turned by R (camera frame) about the centroid, as a start for LM.
        auto consider_turn = [&](const Eigen::Matrix3d& R, const char* method) {
            Pose M = Pose::Identity();
            M.topLeftCorner<3, 3>() = R;
            M.topRightCorner<3, 1>() = pc - R * pc;
            cv::Mat rvec, tvec;
            rvec_tvec_from_pose(M * T, rvec, tvec);
            consider(rvec, tvec, method);
        };
        const std::array<Eigen::Vector3d, 4> axes{Eigen::Vector3d(1, 0, 0), Eigen::Vector3d(0, 1, 0),
                                                  Eigen::Vector3d(1, 1, 0).normalized(), Eigen::Vector3d(1, -1, 0).normalized()};
        for (const auto& axis : axes)
            for (double sign : {-1.0, 1.0})
                consider_turn(Eigen::AngleAxisd(sign * 40.0 * M_PI / 180.0, axis).toRotationMatrix(), "pnp-mirror");
        // The planar flip: a patch seen at tilt t off its normal looks, to a narrow lens, nearly as
        // it does at -t, and the two fits lie 2t apart (90 deg for a 45 deg view), beyond the fixed
        // turns above. Turn the patch's normal to its mirror image across the line of sight.
        const Eigen::Vector3d normal_world = landmark_plane_normal(lms);
        const Eigen::Vector3d n = T.topLeftCorner<3, 3>() * normal_world, sight = pc.normalized();
        const Eigen::Vector3d n_flipped = 2.0 * sight.dot(n) * sight - n;
        if (n.cross(n_flipped).norm() > 1e-6)
            consider_turn(Eigen::Quaterniond::FromTwoVectors(n, n_flipped).toRotationMatrix(), "pnp-flip");
    }
    std::sort(out.begin(), out.end(), [](const LandmarkFit& a, const LandmarkFit& b) { return a.rms_px < b.rms_px; });
    return landmark_fits_within(std::move(out), lms, K, world_sd_mm);
}

std::vector<LandmarkFit> landmark_fits_within(std::vector<LandmarkFit> fits, const std::vector<Landmark>& lms,
                                              const Intrinsics& K, double world_sd_mm) {
    if (fits.empty()) return fits;
    // Keep those that explain the landmarks nearly as well as the best (noise of a few px).
    const double limit = fits.front().rms_px * 2.0 + 2.0 + world_sd_mm * landmark_px_per_mm(lms, K, fits.front().T_camera_from_world);
    fits.erase(std::remove_if(fits.begin(), fits.end(), [&](const LandmarkFit& f) { return f.rms_px > limit; }), fits.end());
    return fits;
}

LandmarkFit fit_pose_orthographic(const std::vector<Landmark>& lms, const Intrinsics& K) {
    // u - cx = s * fx/f (r1 . X + tx) ... with a scaled orthographic camera: [u', v'] = M [X; 1].
    const int n = int(lms.size());
    if (n < 4) throw InputError("landmarks", "needs at least 4 pairs for a pose");
    Eigen::MatrixXd A(n, 4);
    Eigen::VectorXd bu(n), bv(n);
    for (int i = 0; i < n; ++i) {
        A.row(i) << lms[size_t(i)].world_mm.transpose(), 1.0;
        bu(i) = (lms[size_t(i)].pixel.x() - K.cx) / K.fx;
        bv(i) = (lms[size_t(i)].pixel.y() - K.cy) / K.fy;
    }
    const Eigen::Vector4d m1 = A.colPivHouseholderQr().solve(bu);
    const Eigen::Vector4d m2 = A.colPivHouseholderQr().solve(bv);
    Eigen::Vector3d r1 = m1.head<3>(), r2 = m2.head<3>();
    const double s = 0.5 * (r1.norm() + r2.norm());  // 1 / depth
    if (!(s > 1e-9)) throw InputError("landmarks", "orthographic fit degenerate");
    Eigen::Matrix3d R;
    R.row(0) = r1 / s;
    R.row(1) = r2 / s;
    R.row(2) = R.row(0).cross(R.row(1));
    Pose T = Pose::Identity();
    T.topLeftCorner<3, 3>() = R;
    const double tz = 1.0 / s;
    T(0, 3) = m1(3) / s;
    T(1, 3) = m2(3) / s;
    // The affine model's depth is that of the points' centroid; shift so the centroid sits at tz.
    Eigen::Vector3d c = Eigen::Vector3d::Zero();
    for (const auto& l : lms) c += l.world_mm;
    c /= n;
    T = orthonormalize(T);
    T(2, 3) = tz - (T.topLeftCorner<3, 3>().row(2) * c)(0);
    LandmarkFit fit;
    fit.T_camera_from_world = T;
    fit.method = "orthographic";
    for (int i = 0; i < n; ++i) fit.inliers.push_back(i);
    fit.rms_px = reprojection_rms_px(lms, K, T);
    return fit;
}

}  // namespace cf
