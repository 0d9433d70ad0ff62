#include "cortexfuse/core/pose.hpp"

#include <cmath>
#include <stdexcept>

namespace cf {

namespace {
constexpr double kDeg = M_PI / 180.0;
}

Eigen::Matrix3d rotation_xyz_deg(double rx, double ry, double rz) {
    return (Eigen::AngleAxisd(rx * kDeg, Eigen::Vector3d::UnitX()) * Eigen::AngleAxisd(ry * kDeg, Eigen::Vector3d::UnitY()) *
            Eigen::AngleAxisd(rz * kDeg, Eigen::Vector3d::UnitZ()))
        .toRotationMatrix();
}

std::array<double, 3> euler_xyz_deg(const Eigen::Matrix3d& R) {
    // R = Rx(a) Ry(b) Rz(c): R(0,2) = sin b.
    const double b = std::asin(std::clamp(R(0, 2), -1.0, 1.0));
    double a, c;
    if (std::abs(std::cos(b)) > 1e-9) {
        a = std::atan2(-R(1, 2), R(2, 2));
        c = std::atan2(-R(0, 1), R(0, 0));
    } else {
        a = std::atan2(R(2, 1), R(1, 1));
        c = 0;
    }
    return {a / kDeg, b / kDeg, c / kDeg};
}

Pose apply_params(const Pose& T0, const Eigen::Vector3d& pivot, const PoseParams& x) {
    Eigen::Matrix4d M = Eigen::Matrix4d::Identity();
    const Eigen::Matrix3d R = rotation_xyz_deg(x[0], x[1], x[2]);
    M.topLeftCorner<3, 3>() = R;
    M.topRightCorner<3, 1>() = pivot - R * pivot + Eigen::Vector3d(x[3], x[4], x[5]);
    return M * T0;
}

PoseParams params_between(const Pose& T0, const Pose& T, const Eigen::Vector3d& pivot) {
    const Eigen::Matrix4d M = T * T0.inverse();
    const Eigen::Matrix3d R = M.topLeftCorner<3, 3>();
    const auto e = euler_xyz_deg(R);
    const Eigen::Vector3d t = M.topRightCorner<3, 1>() - (pivot - R * pivot);
    return {e[0], e[1], e[2], t.x(), t.y(), t.z()};
}

Pose look_at(const Eigen::Vector3d& eye, const Eigen::Vector3d& target, const Eigen::Vector3d& up) {
    const Eigen::Vector3d z = (target - eye).normalized();          // optical axis
    const Eigen::Vector3d x = (-up).cross(z).normalized();          // image right: y (down) x z
    const Eigen::Vector3d y = z.cross(x);
    Eigen::Matrix3d R;  // rows: camera axes in world
    R.row(0) = x;
    R.row(1) = y;
    R.row(2) = z;
    Pose T = Pose::Identity();
    T.topLeftCorner<3, 3>() = R;
    T.topRightCorner<3, 1>() = -R * eye;
    return T;
}

Pose standard_view(const std::string& side, const Eigen::Vector3d& target, double distance_mm) {
    // LPS: +x left, +y posterior, +z superior.
    Eigen::Vector3d dir, up(0, 0, 1);
    if (side == "left") dir = {1, 0, 0};
    else if (side == "right") dir = {-1, 0, 0};
    else if (side == "anterior") dir = {0, -1, 0};
    else if (side == "posterior") dir = {0, 1, 0};
    else if (side == "superior") { dir = {0, 0, 1}; up = {0, -1, 0}; }
    else if (side == "inferior") { dir = {0, 0, -1}; up = {0, -1, 0}; }
    else throw std::invalid_argument("unknown view \"" + side + "\" (left, right, anterior, posterior, superior, inferior)");
    return look_at(target + dir * distance_mm, target, up);
}

PoseDelta pose_delta(const Pose& a, const Pose& b, const Eigen::Vector3d& pivot_world_mm) {
    const Eigen::Matrix4d M = b * a.inverse();
    const Eigen::AngleAxisd aa(Eigen::Matrix3d(M.topLeftCorner<3, 3>()));
    const Eigen::Vector3d pa = a.topLeftCorner<3, 3>() * pivot_world_mm + a.topRightCorner<3, 1>();
    const Eigen::Vector3d pb = b.topLeftCorner<3, 3>() * pivot_world_mm + b.topRightCorner<3, 1>();
    return {std::abs(aa.angle()) / kDeg, (pa - pb).norm()};
}

}  // namespace cf
