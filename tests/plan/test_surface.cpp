// Brain surface mesh: world LPS placement on an oblique grid, budget, normals, file round
// trip, bad input.
#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/surface.hpp"
#include "cortexfuse/core/volume.hpp"

namespace fs = std::filesystem;
using namespace cf;

namespace {

/// A ball of radius r_mm on an oblique, flipped, anisotropic grid; returns its world centre.
Eigen::Vector3d make_ball(Volume& v, LabelVolume& m, double r_mm) {
    VolumeGeometry g;
    g.dims = {48, 40, 36};
    g.spacing_mm = Eigen::Vector3d(1.5, 1.8, 2.0);
    g.origin_mm = Eigen::Vector3d(-20, 35, 10);
    g.direction = (Eigen::AngleAxisd(0.4, Eigen::Vector3d(1, 2, 3).normalized()).toRotationMatrix() *
                   Eigen::Vector3d(1, -1, 1).asDiagonal());  // oblique and flipped
    v.geom = m.geom = g;
    v.voxels.assign(g.voxel_count(), 0.f);
    m.voxels.assign(g.voxel_count(), 0);
    const Eigen::Vector3d c = g.world_from_index(Eigen::Vector3d(23.5, 19.5, 17.5));
    for (int k = 0; k < g.dims[2]; ++k)
        for (int j = 0; j < g.dims[1]; ++j)
            for (int i = 0; i < g.dims[0]; ++i) {
                const double d = (g.world_from_index(Eigen::Vector3d(i, j, k)) - c).norm();
                m.voxels[g.linear(i, j, k)] = d < r_mm ? 1 : 0;
                v.voxels[g.linear(i, j, k)] = d < r_mm ? 100.f : 0.f;
            }
    return c;
}

}  // namespace

TEST(Surface, ObliqueGridLandsInWorld) {
    Volume v;
    LabelVolume m;
    const Eigen::Vector3d c = make_ball(v, m, 25.0);
    SurfaceParams p;
    p.source = SurfaceParams::Source::Mask;
    p.max_triangles = 4000;
    SurfaceInfo info;
    const SurfaceMesh s = build_brain_surface(v, m, p, {}, &info);
    ASSERT_GT(s.triangles.size(), 1000u);
    EXPECT_LE(s.triangles.size(), 4000u * 101 / 100);
    ASSERT_EQ(s.normals.size(), s.vertices.size());
    double mean_r = 0;
    int outward = 0;
    for (size_t i = 0; i < s.vertices.size(); ++i) {
        const Eigen::Vector3d d = s.vertices[i].cast<double>() - c;
        mean_r += d.norm();
        EXPECT_NEAR(d.norm(), 25.0, 2.5);
        outward += s.normals[i].cast<double>().dot(d.normalized()) > 0.7;
        // Winding agrees with the normals (right-hand rule points outward).
    }
    mean_r /= double(s.vertices.size());
    EXPECT_NEAR(mean_r, 25.0, 1.2);  // smoothing shrinks a little
    EXPECT_GT(outward, int(s.vertices.size() * 98 / 100));
    int wound_out = 0;
    for (const auto& t : s.triangles) {
        const Eigen::Vector3f a = s.vertices[size_t(t[0])], b = s.vertices[size_t(t[1])], d = s.vertices[size_t(t[2])];
        wound_out += (b - a).cross(d - a).dot((a + b + d) / 3 - c.cast<float>()) > 0;
    }
    EXPECT_GT(wound_out, int(s.triangles.size() * 98 / 100));
}

TEST(Surface, FileRoundTripAllFormats) {
    Volume v;
    LabelVolume m;
    make_ball(v, m, 20.0);
    SurfaceParams p;
    p.source = SurfaceParams::Source::Mask;
    p.max_triangles = 2000;
    const SurfaceMesh s = build_brain_surface(v, m, p);
    const fs::path dir = fs::temp_directory_path() / ("cf_surface_" + std::to_string(::getpid()));
    fs::create_directories(dir);
    for (const char* ext : {".ply", ".vtp", ".stl", ".obj"}) {
        const fs::path f = dir / (std::string("mesh") + ext);
        save_mesh(s, f);
        const SurfaceMesh r = load_mesh(f);
        EXPECT_EQ(r.triangles.size(), s.triangles.size()) << ext;
        // STL stores triangle corners; the reader merges them back.
        if (std::string(ext) != ".stl") {
            ASSERT_EQ(r.vertices.size(), s.vertices.size()) << ext;
            for (size_t i = 0; i < s.vertices.size(); i += 97) EXPECT_LT((r.vertices[i] - s.vertices[i]).norm(), 1e-3) << ext;
        }
        EXPECT_FALSE(fs::exists(dir / (std::string("mesh.part") + ext)));
    }
    EXPECT_THROW(save_mesh(s, dir / "mesh.xyz"), InputError);
    fs::remove_all(dir);
}

TEST(Surface, BadInput) {
    Volume v;
    LabelVolume m;
    make_ball(v, m, 20.0);
    LabelVolume empty = m;
    std::fill(empty.voxels.begin(), empty.voxels.end(), 0);
    EXPECT_THROW(build_brain_surface(v, empty), InputError);
    LabelVolume other = m;
    other.geom.spacing_mm.x() = 1.0;
    EXPECT_THROW(build_brain_surface(v, other), InputError);
    SurfaceParams bad;
    bad.max_triangles = 10;
    EXPECT_THROW(build_brain_surface(v, m, bad), InputError);
    SurfaceMesh none;
    none.vertices.assign(3, Eigen::Vector3f::Zero());
    EXPECT_THROW(none.validate("mesh"), InputError);
    EXPECT_THROW(save_mesh(none, fs::temp_directory_path() / "cf_none.ply"), InputError);
    EXPECT_FALSE(fs::exists(fs::temp_directory_path() / "cf_none.ply"));
    EXPECT_THROW(load_mesh(fs::temp_directory_path() / "cf_no_such_mesh.ply"), InputError);
}

TEST(Surface, RealHeadT1Level) {
    // The shipped head on a 2 mm grid: a cortex-like surface within the budget.
    const Volume t1 = load_volume(fs::path(CF_DATA_DIR) / "t1_head_mne_ecog.nii.gz");
    const LabelVolume mask = load_mask(fs::path(CF_DATA_DIR) / "brainmask_mne_ecog_binary.nii.gz");
    const VolumeGeometry g = isotropic_grid(t1.geom, 2.0);
    const Volume t1s = resample(t1, g);
    const LabelVolume ms = resample_nearest(mask, g);
    SurfaceParams p;
    p.max_triangles = 20000;
    SurfaceInfo info;
    const SurfaceMesh s = build_brain_surface(t1s, ms, p, {}, &info);
    EXPECT_LE(s.triangles.size(), 20200u);
    EXPECT_GT(s.triangles.size(), 15000u);
    EXPECT_GT(info.triangles_extracted, s.triangles.size());
    // Every vertex near the mask (within 4 mm of a mask voxel's world box).
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(1e9), hi = -lo;
    for (int k = 0; k < g.dims[2]; ++k)
        for (int j = 0; j < g.dims[1]; ++j)
            for (int i = 0; i < g.dims[0]; ++i)
                if (ms.at(i, j, k)) {
                    const Eigen::Vector3d w = g.world_from_index(Eigen::Vector3d(i, j, k));
                    lo = lo.cwiseMin(w), hi = hi.cwiseMax(w);
                }
    for (const auto& vtx : s.vertices) {
        EXPECT_TRUE((vtx.cast<double>().array() >= lo.array() - 4).all());
        EXPECT_TRUE((vtx.cast<double>().array() <= hi.array() + 4).all());
    }
}
