// Volume formats through ITK: world = LPS mm with direction cosines honoured, whatever the
// format and however the voxels are laid out; resampling to a working grid; statistics.
// Checks are against independent truth: DICOM tags read from the raw bytes, a NIfTI header
// written here byte by byte, and re-laid-out copies of the same object.
#include <gtest/gtest.h>
#include <unistd.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <numeric>
#include <random>
#include <sstream>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/volume.hpp"

namespace fs = std::filesystem;
using namespace cf;

namespace {

fs::path tmpdir(const std::string& name) {
    auto p = fs::temp_directory_path() / ("cf_io_" + name + "_" + std::to_string(::getpid()));
    fs::remove_all(p);
    fs::create_directories(p);
    return p;
}

std::string slurp(const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    std::stringstream s;
    s << in.rdbuf();
    return s.str();
}

// A DICOM string attribute (VR DS, explicit VR little endian, as the test series is) parsed from
// the file's bytes: an independent reading of what ITK/GDCM report.
std::vector<double> dicom_ds(const fs::path& file, uint16_t group, uint16_t element) {
    const std::string b = slurp(file);
    const char tag[4] = {char(group & 0xff), char(group >> 8), char(element & 0xff), char(element >> 8)};
    for (size_t at = b.find(std::string(tag, 4)); at != std::string::npos; at = b.find(std::string(tag, 4), at + 1)) {
        if (b.compare(at + 4, 2, "DS") != 0) continue;
        const size_t len = uint8_t(b[at + 6]) | (size_t(uint8_t(b[at + 7])) << 8);
        std::string v = b.substr(at + 8, len);
        std::replace(v.begin(), v.end(), '\\', ' ');
        std::istringstream in(v);
        std::vector<double> out;
        for (double x; in >> x;) out.push_back(x);
        return out;
    }
    return {};
}

Volume with_marker(const VolumeGeometry& g, const std::array<int, 3>& at) {
    Volume v;
    v.geom = g;
    v.voxels.assign(g.voxel_count(), 10.f);
    for (int k = 0; k < g.dims[2]; ++k)
        for (int j = 0; j < g.dims[1]; ++j)
            for (int i = 0; i < g.dims[0]; ++i) v.voxels[g.linear(i, j, k)] = float(10 + (i + 2 * j + 3 * k) % 7);
    v.voxels[g.linear(at[0], at[1], at[2])] = 1000.f;
    return v;
}

Eigen::Vector3d marker_world(const Volume& v) {
    const size_t idx = size_t(std::max_element(v.voxels.begin(), v.voxels.end()) - v.voxels.begin());
    const int nx = v.geom.dims[0], ny = v.geom.dims[1];
    const int i = int(idx % size_t(nx)), j = int((idx / size_t(nx)) % size_t(ny)), k = int(idx / (size_t(nx) * ny));
    return v.geom.world_from_index(Eigen::Vector3d(i, j, k));
}

// The same object with voxel axis a reversed: data mirrored, direction column negated, origin at
// the old far end. World positions must not change.
Volume flip_axis(const Volume& v, int a) {
    Volume r;
    r.geom = v.geom;
    Eigen::Vector3d far = Eigen::Vector3d::Zero();
    far[a] = v.geom.dims[a] - 1;
    r.geom.origin_mm = v.geom.world_from_index(far);
    r.geom.direction.col(a) *= -1;
    r.voxels.resize(v.voxels.size());
    const auto& d = v.geom.dims;
    for (int k = 0; k < d[2]; ++k)
        for (int j = 0; j < d[1]; ++j)
            for (int i = 0; i < d[0]; ++i) {
                std::array<int, 3> s{i, j, k};
                s[a] = d[a] - 1 - s[a];
                r.voxels[r.geom.linear(i, j, k)] = v.at(s[0], s[1], s[2]);
            }
    return r;
}

// The same object with voxel axes i and k swapped (a sagittal <-> axial re-layout).
Volume swap_ik(const Volume& v) {
    Volume r;
    r.geom = v.geom;
    r.geom.dims = {v.geom.dims[2], v.geom.dims[1], v.geom.dims[0]};
    r.geom.spacing_mm = Eigen::Vector3d(v.geom.spacing_mm[2], v.geom.spacing_mm[1], v.geom.spacing_mm[0]);
    r.geom.direction.col(0) = v.geom.direction.col(2);
    r.geom.direction.col(2) = v.geom.direction.col(0);
    r.voxels.resize(v.voxels.size());
    for (int k = 0; k < r.geom.dims[2]; ++k)
        for (int j = 0; j < r.geom.dims[1]; ++j)
            for (int i = 0; i < r.geom.dims[0]; ++i) r.voxels[r.geom.linear(i, j, k)] = v.at(k, j, i);
    return r;
}

const char* const kFormats[] = {"v.nii", "v.nii.gz", "v.nrrd", "v.nhdr", "v.mha", "v.mhd"};

}  // namespace

// The real DICOM series, written to every file format and read back, lands at the same world
// positions; those positions are the ones the DICOM tags (read from the bytes here) state.
TEST(VolumeFormats, DicomSeriesAndEveryFileFormatAgreeInLps) {
    const fs::path series = fs::path(CF_TEST_DATA_DIR) / "dicom_mr_sag";
    ASSERT_TRUE(fs::exists(series)) << "tests/data/dicom_mr_sag is part of the repository";
    const Volume dcm = load_volume(series);

    // Independent truth from the raw tags: ImageOrientationPatient gives the in-plane axes,
    // ImagePositionPatient of each slice file the position of its first voxel.
    std::vector<fs::path> files;
    for (const auto& e : fs::directory_iterator(series)) files.push_back(e.path());
    ASSERT_EQ(int(files.size()), dcm.geom.dims[2]);
    const auto iop = dicom_ds(files[0], 0x0020, 0x0037);
    ASSERT_EQ(iop.size(), 6u);
    const Eigen::Vector3d row(iop[0], iop[1], iop[2]), col(iop[3], iop[4], iop[5]);
    EXPECT_NEAR((dcm.geom.direction.col(0) - row).norm(), 0, 1e-4);
    EXPECT_NEAR((dcm.geom.direction.col(1) - col).norm(), 0, 1e-4);
    const auto ps = dicom_ds(files[0], 0x0028, 0x0030);  // PixelSpacing: row spacing (along j), column spacing (along i)
    ASSERT_EQ(ps.size(), 2u);
    EXPECT_NEAR(dcm.geom.spacing_mm[0], ps[1], 1e-4);
    EXPECT_NEAR(dcm.geom.spacing_mm[1], ps[0], 1e-4);
    // Every slice's IPP is the world position of voxel (0, 0, k) for one k.
    for (const auto& f : files) {
        const auto ipp = dicom_ds(f, 0x0020, 0x0032);
        ASSERT_EQ(ipp.size(), 3u) << f;
        const Eigen::Vector3d p(ipp[0], ipp[1], ipp[2]);
        const Eigen::Vector3d ijk = dcm.geom.index_from_world() * p;
        EXPECT_NEAR(ijk.x(), 0, 1e-3) << f;
        EXPECT_NEAR(ijk.y(), 0, 1e-3) << f;
        EXPECT_NEAR(ijk.z(), std::round(ijk.z()), 1e-3) << f;
        EXPECT_GE(ijk.z(), -1e-3);
        EXPECT_LE(ijk.z(), dcm.geom.dims[2] - 1 + 1e-3);
    }

    const fs::path dir = tmpdir("formats");
    for (const char* name : kFormats) {
        save_volume(dcm, dir / name);
        const Volume r = load_volume(dir / name);
        EXPECT_TRUE(r.geom.same_grid(dcm.geom, 1e-3)) << name;
        ASSERT_EQ(r.voxels.size(), dcm.voxels.size()) << name;
        EXPECT_TRUE(std::equal(r.voxels.begin(), r.voxels.end(), dcm.voxels.begin())) << name;
    }
    // MHD keeps its voxels beside the header, in a .raw or .zraw file.
    EXPECT_TRUE(fs::exists(dir / "v.raw") || fs::exists(dir / "v.zraw"));
    fs::remove_all(dir);
}

// NIfTI stores RAS; ITK (and so we) report LPS. A header written here byte by byte, with a
// known sform, must come back as the same affine with x and y negated.
TEST(VolumeFormats, NiftiSformIsRasOnDiskAndLpsInMemory) {
    const int nx = 4, ny = 5, nz = 6;
    // An oblique sform: rotation about z by 30 deg, spacing 2, 3, 4 mm.
    const double c = std::cos(M_PI / 6), s = std::sin(M_PI / 6);
    const Eigen::Matrix3d R_ras = (Eigen::Matrix3d() << c, -s, 0, s, c, 0, 0, 0, 1).finished();
    const Eigen::Vector3d sp(2, 3, 4), t_ras(10, 20, 30);
    const Eigen::Matrix3d A_ras = R_ras * sp.asDiagonal();
    std::string hdr(352, '\0');
    auto put = [&](size_t off, auto v) { std::memcpy(&hdr[off], &v, sizeof v); };
    put(0, int32_t(348));
    const int16_t dim[8] = {3, nx, ny, nz, 1, 1, 1, 1};
    std::memcpy(&hdr[40], dim, sizeof dim);
    put(70, int16_t(16));  // datatype float32
    put(72, int16_t(32));  // bitpix
    const float pixdim[8] = {1, float(sp[0]), float(sp[1]), float(sp[2]), 1, 1, 1, 1};
    std::memcpy(&hdr[76], pixdim, sizeof pixdim);
    put(108, float(352));  // vox_offset
    put(252, int16_t(0));  // qform_code
    put(254, int16_t(1));  // sform_code: scanner
    for (int r = 0; r < 3; ++r) {
        const float row[4] = {float(A_ras(r, 0)), float(A_ras(r, 1)), float(A_ras(r, 2)), float(t_ras[r])};
        std::memcpy(&hdr[280 + 16 * r], row, sizeof row);
    }
    std::memcpy(&hdr[344], "n+1\0", 4);
    std::string data(size_t(nx) * ny * nz * 4, '\0');
    for (int k = 0; k < nz; ++k)
        for (int j = 0; j < ny; ++j)
            for (int i = 0; i < nx; ++i) {
                const float v = float(100 * k + 10 * j + i);
                std::memcpy(&data[4 * ((size_t(k) * ny + j) * nx + i)], &v, 4);
            }
    const fs::path dir = tmpdir("nifti_ras");
    std::ofstream(dir / "ras.nii", std::ios::binary) << hdr << data;
    const Volume v = load_volume(dir / "ras.nii");
    ASSERT_EQ(v.geom.dims, (std::array<int, 3>{nx, ny, nz}));
    const Eigen::Matrix3d flip = Eigen::Vector3d(-1, -1, 1).asDiagonal();
    for (int k = 0; k < nz; k += 2)
        for (int j = 0; j < ny; j += 2)
            for (int i = 0; i < nx; i += 3) {
                const Eigen::Vector3d ras = A_ras * Eigen::Vector3d(i, j, k) + t_ras;
                const Eigen::Vector3d lps = v.geom.world_from_index(Eigen::Vector3d(i, j, k));
                EXPECT_NEAR((lps - flip * ras).norm(), 0, 1e-4) << i << " " << j << " " << k;
                EXPECT_EQ(v.at(i, j, k), float(100 * k + 10 * j + i));
            }
    fs::remove_all(dir);
}

// The same object stored with its voxel axes flipped or permuted, and with the whole grid moved
// by a rigid motion, in every format: a known voxel lands at the LPS point it belongs to.
TEST(VolumeFormats, ObliqueFlippedAndPermutedLayoutsPutAVoxelWhereItBelongs) {
    VolumeGeometry g;
    g.dims = {11, 9, 7};
    g.spacing_mm = {1.2, 0.8, 2.5};
    g.origin_mm = {-40, 15, 22};
    g.direction = rotation_xyz_deg(12, -25, 40);
    const Volume base = with_marker(g, {7, 2, 5});
    const Eigen::Vector3d p_marker = marker_world(base);
    EXPECT_NEAR((p_marker - g.world_from_index(Eigen::Vector3d(7, 2, 5))).norm(), 0, 1e-9);

    // Rotating the direction matrix and the origin together moves the object rigidly.
    const Eigen::Matrix3d R = rotation_xyz_deg(-30, 50, 160);
    const Eigen::Vector3d t(5, -12, 33);
    Volume moved = base;
    moved.geom.direction = R * g.direction;
    moved.geom.origin_mm = R * g.origin_mm + t;

    const std::vector<std::pair<std::string, std::pair<Volume, Eigen::Vector3d>>> variants = {
        {"base", {base, p_marker}},
        {"flip_i", {flip_axis(base, 0), p_marker}},
        {"flip_j_k", {flip_axis(flip_axis(base, 1), 2), p_marker}},
        {"swap_ik", {swap_ik(base), p_marker}},
        {"moved", {moved, R * p_marker + t}},
        {"moved_flipped", {flip_axis(swap_ik(moved), 1), R * p_marker + t}},
    };
    const fs::path dir = tmpdir("layouts");
    for (const auto& [label, vp] : variants) {
        const auto& [vol, expected] = vp;
        for (const char* name : kFormats) {
            const fs::path f = dir / (label + "_" + name);
            save_volume(vol, f);
            const Volume r = load_volume(f);
            EXPECT_LT((marker_world(r) - expected).norm(), 1e-3) << label << " " << name;
            // The direction cosines stay orthonormal (a flipped axis gives det -1, kept as is).
            EXPECT_NEAR(std::abs(r.geom.direction.determinant()), 1.0, 1e-5) << label << " " << name;
        }
    }
    fs::remove_all(dir);
}

// Resampling onto a working grid (axis-aligned, isotropic) keeps structures at their world place.
TEST(VolumeResample, BlobKeepsItsWorldCentreOnAnIsotropicGrid) {
    VolumeGeometry g;
    g.dims = {30, 24, 20};
    g.spacing_mm = {1.0, 1.4, 2.0};
    g.origin_mm = {12, -30, 8};
    g.direction = rotation_xyz_deg(20, 10, -35);
    g.direction.col(1) *= -1;  // and flipped
    const Eigen::Vector3d centre = g.world_from_index(Eigen::Vector3d(14.3, 11.6, 9.2));
    Volume v;
    v.geom = g;
    v.voxels.resize(g.voxel_count());
    LabelVolume m;
    m.geom = g;
    m.voxels.resize(g.voxel_count());
    for (int k = 0; k < g.dims[2]; ++k)
        for (int j = 0; j < g.dims[1]; ++j)
            for (int i = 0; i < g.dims[0]; ++i) {
                const double r = (g.world_from_index(Eigen::Vector3d(i, j, k)) - centre).norm();
                v.voxels[g.linear(i, j, k)] = float(100.0 * std::exp(-r * r / (2 * 4.0 * 4.0)));
                m.voxels[g.linear(i, j, k)] = r < 6.0;
            }
    const VolumeGeometry iso = isotropic_grid(g, 1.0);
    EXPECT_TRUE(iso.direction.isIdentity(1e-12));
    EXPECT_NEAR(iso.spacing_mm.minCoeff(), 1.0, 1e-12);
    const Volume r = resample(v, iso, 0.f);
    const LabelVolume rm = resample_nearest(m, iso);
    Eigen::Vector3d c_int = Eigen::Vector3d::Zero(), c_mask = Eigen::Vector3d::Zero();
    double w = 0;
    size_t n = 0;
    for (int k = 0; k < iso.dims[2]; ++k)
        for (int j = 0; j < iso.dims[1]; ++j)
            for (int i = 0; i < iso.dims[0]; ++i) {
                const Eigen::Vector3d p = iso.world_from_index(Eigen::Vector3d(i, j, k));
                c_int += r.at(i, j, k) * p;
                w += r.at(i, j, k);
                if (rm.at(i, j, k)) {
                    c_mask += p;
                    ++n;
                }
            }
    EXPECT_LT((c_int / w - centre).norm(), 0.1);
    EXPECT_LT((c_mask / double(n) - centre).norm(), 0.3);
    // The ball of radius 6 mm: 905 mm^3, and 1 mm voxels now.
    EXPECT_NEAR(double(n), 4.0 / 3.0 * M_PI * 216.0, 60.0);
}

TEST(VolumeStats, MatchAStraightComputation) {
    VolumeGeometry g;
    g.dims = {10, 10, 10};
    Volume v;
    v.geom = g;
    v.voxels.resize(1000);
    std::iota(v.voxels.begin(), v.voxels.end(), 0.f);  // 0 .. 999
    std::shuffle(v.voxels.begin(), v.voxels.end(), std::mt19937(4));
    const IntensityStats s = intensity_stats(v);
    EXPECT_EQ(s.count, 1000u);
    EXPECT_DOUBLE_EQ(s.min, 0);
    EXPECT_DOUBLE_EQ(s.max, 999);
    EXPECT_NEAR(s.mean, 499.5, 1e-9);
    EXPECT_NEAR(s.stddev, std::sqrt((1000.0 * 1000.0 - 1) / 12.0), 1e-6);  // discrete uniform
    EXPECT_NEAR(s.p50, 499.5, 1.0);
    EXPECT_NEAR(s.p01, 10, 1.0);
    EXPECT_NEAR(s.p99, 989, 1.0);
    // Inside a mask: only the voxels with value >= 900.
    LabelVolume m;
    m.geom = g;
    m.voxels.resize(1000);
    for (size_t i = 0; i < 1000; ++i) m.voxels[i] = v.voxels[i] >= 900.f;
    const IntensityStats sm = intensity_stats(v, &m);
    EXPECT_EQ(sm.count, 100u);
    EXPECT_DOUBLE_EQ(sm.min, 900);
    EXPECT_NEAR(sm.mean, 949.5, 1e-9);
    // A mask on another grid is a programming error, refused rather than read out of bounds.
    LabelVolume other;
    other.geom.dims = {5, 5, 5};
    other.voxels.resize(125, 1);
    EXPECT_THROW(intensity_stats(v, &other), std::invalid_argument);
}

// Headers that promise absurd sizes are refused before anything is allocated for them.
TEST(VolumeFormats, AbsurdHeadersAreRefusedWithoutAllocating) {
    const fs::path dir = tmpdir("absurd");
    std::ofstream(dir / "huge.mha") << "ObjectType = Image\nNDims = 3\nDimSize = 100000 100000 100000\n"
                                       "ElementSpacing = 1 1 1\nElementType = MET_FLOAT\nElementDataFile = LOCAL\nxxxx";
    std::ofstream(dir / "flat.nrrd") << "NRRD0004\ntype: float\ndimension: 3\nsizes: 64 64 1\nencoding: raw\n"
                                        "endian: little\n\n" << std::string(64 * 64 * 4, '\0');
    std::ofstream(dir / "zero_spacing.mhd") << "ObjectType = Image\nNDims = 3\nDimSize = 4 4 4\nElementSpacing = 0 1 1\n"
                                               "ElementType = MET_UCHAR\nElementDataFile = zero_spacing.raw\n";
    std::ofstream(dir / "zero_spacing.raw") << std::string(64, 'x');
    for (const auto& [name, what] : std::vector<std::pair<std::string, std::string>>{
             {"huge.mha", "absurd volume dimensions 100000x100000x100000"},
             {"flat.nrrd", "absurd volume dimensions 64x64x1"},
             {"zero_spacing.mhd", "absurd voxel spacing"}}) {
        try {
            load_volume(dir / name);
            ADD_FAILURE() << name << " was accepted";
        } catch (const InputError& e) {
            EXPECT_NE(std::string(e.what()).find(name), std::string::npos) << e.what();
            EXPECT_NE(std::string(e.what()).find(what), std::string::npos) << e.what();
            EXPECT_EQ(std::string(e.what()).find('\n'), std::string::npos) << e.what();
        }
    }
    fs::remove_all(dir);
}
