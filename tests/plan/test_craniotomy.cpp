// The craniotomy of a fused CT (core's craniotomy_keep_mask, overlay.hpp), on a synthetic scene:
// the camera at the origin looking along +z, the "brain surface" a plane at z = 50 mm facing it,
// a 2 mm CT grid from z = 20 to 98 mm, the ROI the left half of the photo.
#include <gtest/gtest.h>

#include <opencv2/core.hpp>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/overlay.hpp"

namespace {

struct Scene {
    cf::VolumeGeometry grid;
    cf::SurfaceMesh plane;
    cf::Intrinsics K;
    cf::Pose T = cf::Pose::Identity();
    cv::Mat roi_left;  // 255 for u < 50
    Scene() {
        grid.dims = {20, 20, 40};
        grid.spacing_mm = Eigen::Vector3d(2, 2, 2);
        grid.origin_mm = Eigen::Vector3d(-19, -19, 20);  // x, y in -19..19, z in 20..98
        plane.vertices = {{-60, -60, 50}, {60, -60, 50}, {60, 60, 50}, {-60, 60, 50}};
        plane.triangles = {{0, 1, 2}, {0, 2, 3}};
        K.width = K.height = 100;
        K.fx = K.fy = 100;
        K.cx = K.cy = 49.5;
        roi_left = cv::Mat(100, 100, CV_8UC1, cv::Scalar(0));
        roi_left(cv::Rect(0, 0, 50, 100)).setTo(255);
    }
    /// The voxel at world (x, y, z) mm (on the grid).
    size_t at(double x, double y, double z) const {
        const Eigen::Vector3d ijk = grid.index_from_world() * Eigen::Vector3d(x, y, z);
        return grid.linear(int(std::lround(ijk.x())), int(std::lround(ijk.y())), int(std::lround(ijk.z())));
    }
};

TEST(Craniotomy, HidesBoneInFrontOfTheCortexInsideTheRoiDownToTheMargin) {
    const Scene s;
    const cf::LabelVolume m = cf::craniotomy_keep_mask(s.grid, s.plane, s.K, s.T, s.roi_left, 3.0);
    ASSERT_TRUE(m.geom.same_grid(s.grid));
    ASSERT_EQ(m.voxels.size(), s.grid.voxel_count());
    // Inside the ROI (x = -11 projects to u ~ 13..30): in front of the surface and down to 3 mm below, hidden.
    EXPECT_EQ(m.voxels[s.at(-11, 1, 30)], 0) << "bone in front of the cortex in the ROI";
    EXPECT_EQ(m.voxels[s.at(-11, 1, 50)], 0) << "on the surface";
    EXPECT_EQ(m.voxels[s.at(-11, 1, 52)], 0) << "2 mm below the surface (margin 3 mm)";
    EXPECT_EQ(m.voxels[s.at(-11, 1, 54)], 1) << "4 mm below the surface: deeper than the margin";
    EXPECT_EQ(m.voxels[s.at(-11, 1, 90)], 1);
    // Outside the ROI (x = +11 projects to u ~ 86): kept at every depth.
    EXPECT_EQ(m.voxels[s.at(11, 1, 30)], 1) << "bone outside the ROI";
    EXPECT_EQ(m.voxels[s.at(11, 1, 50)], 1);
    // Something is hidden, most is not.
    size_t hidden = 0;
    for (auto v : m.voxels) hidden += v == 0;
    EXPECT_GT(hidden, 100u);
    EXPECT_LT(hidden, m.voxels.size() / 2);
}

TEST(Craniotomy, MarginAndEmptyRoiAndAPoseThatLooksAway) {
    const Scene s;
    const cf::LabelVolume m0 = cf::craniotomy_keep_mask(s.grid, s.plane, s.K, s.T, s.roi_left, 0.0);
    EXPECT_EQ(m0.voxels[s.at(-11, 1, 48)], 0);
    EXPECT_EQ(m0.voxels[s.at(-11, 1, 52)], 1) << "margin 0: nothing below the surface is hidden";
    // No ROI: the whole photo.
    const cf::LabelVolume all = cf::craniotomy_keep_mask(s.grid, s.plane, s.K, s.T, cv::Mat(), 3.0);
    EXPECT_EQ(all.voxels[s.at(11, 1, 30)], 0);
    EXPECT_EQ(all.voxels[s.at(-11, 1, 30)], 0);
    EXPECT_EQ(all.voxels[s.at(11, 1, 60)], 1);
    // The camera turned away (rotated 180 degrees about y): nothing is seen, nothing is hidden.
    cf::Pose away = cf::Pose::Identity();
    away(0, 0) = -1;
    away(2, 2) = -1;
    const cf::LabelVolume none = cf::craniotomy_keep_mask(s.grid, s.plane, s.K, away, cv::Mat(), 3.0);
    for (auto v : none.voxels) ASSERT_EQ(v, 1);
}

TEST(Craniotomy, BadInputsAreRefusedNamingThem) {
    const Scene s;
    auto msg = [&](auto&& f) {
        try {
            f();
        } catch (const cf::InputError& e) {
            return std::string(e.what());
        }
        return std::string("no error");
    };
    EXPECT_NE(msg([&] { cf::craniotomy_keep_mask(s.grid, s.plane, s.K, s.T, cv::Mat(50, 50, CV_8UC1), 3.0); }).find("roi"),
              std::string::npos);
    EXPECT_NE(msg([&] { cf::craniotomy_keep_mask(s.grid, s.plane, s.K, s.T, s.roi_left, -1.0); }).find("margin"), std::string::npos);
    EXPECT_NE(msg([&] { cf::craniotomy_keep_mask(s.grid, cf::SurfaceMesh{}, s.K, s.T, s.roi_left, 3.0); }).find("brain surface"),
              std::string::npos);
    cf::Pose sheared = cf::Pose::Identity();
    sheared(0, 1) = 0.5;
    EXPECT_NE(msg([&] { cf::craniotomy_keep_mask(s.grid, s.plane, s.K, sheared, s.roi_left, 3.0); }).find("pose"), std::string::npos);
    cf::VolumeGeometry empty;
    EXPECT_NE(msg([&] { cf::craniotomy_keep_mask(empty, s.plane, s.K, s.T, s.roi_left, 3.0); }).find("CT grid"), std::string::npos);
}

}  // namespace
