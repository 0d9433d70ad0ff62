#include "base_case.hpp"

#include <unistd.h>

#include <limits>
#include <mutex>
#include <string>

#include "cortexfuse/core/phantom.hpp"
#include "cortexfuse/core/volume.hpp"

namespace fs = std::filesystem;

namespace cf::test {

namespace {

// A 64^3 isotropic, axis-aligned grid around the brain (plus a margin): small enough that a
// case loads in milliseconds, large enough that the phantom surface is still a brain.
VolumeGeometry small_grid_around(const LabelVolume& mask) {
    Eigen::Vector3d lo = Eigen::Vector3d::Constant(std::numeric_limits<double>::max()), hi = -lo;
    const auto& d = mask.geom.dims;
    for (int k = 0; k < d[2]; k += 2)
        for (int j = 0; j < d[1]; j += 2)
            for (int i = 0; i < d[0]; i += 2)
                if (mask.at(i, j, k)) {
                    const Eigen::Vector3d p = mask.geom.world_from_index(Eigen::Vector3d(i, j, k));
                    lo = lo.cwiseMin(p);
                    hi = hi.cwiseMax(p);
                }
    VolumeGeometry g;
    g.dims = {64, 64, 64};
    const double spacing_mm = ((hi - lo).maxCoeff() + 24.0) / 63.0;
    g.spacing_mm = Eigen::Vector3d::Constant(spacing_mm);
    g.origin_mm = 0.5 * (lo + hi) - Eigen::Vector3d::Constant(31.5 * spacing_mm);
    return g;
}

void write_case(const PhantomSurface& surface, const Volume& t1, const LabelVolume& mask, const fs::path& dir, int width,
                int height, uint64_t seed) {
    PhantomParams p;
    p.seed = seed;
    p.width = width;
    p.height = height;
    p.vary_size = false;
    p.dslr_fraction = 0;
    p.gauze_prob = 0;
    p.blood_prob = 0;
    p.distortion_prob = 0;
    p.png_fraction = 1;
    p.landmarks_min = p.landmarks_max = 6;
    p.max_tilt_deg = 15;
    const PhantomCase c = generate_phantom_case(surface, p, 0);
    write_phantom_case(c, dir, "t1.nii.gz", "brain_mask.nii.gz");
    save_volume(t1, dir / "t1.nii.gz");
    save_mask(mask, dir / "brain_mask.nii.gz");
}

}  // namespace

void make_base_cases(const fs::path& root) {
    const fs::path data(CF_DATA_DIR);
    const Volume t1_full = load_volume(data / "t1_head_mne_ecog.nii.gz");
    const LabelVolume mask_full = load_mask(data / "brainmask_mne_ecog_binary.nii.gz");
    const VolumeGeometry g = small_grid_around(mask_full);
    const Volume t1 = resample(t1_full, g, 0.f);
    const LabelVolume mask = resample_nearest(mask_full, g);
    const PhantomSurface surface = build_phantom_surface(t1, mask);

    const fs::path tmp = root.string() + ".tmp" + std::to_string(::getpid());
    fs::remove_all(tmp);
    fs::create_directories(tmp);
    write_case(surface, t1, mask, tmp / "small", 375, 250, 11);
    write_case(surface, t1, mask, tmp / "medium", 750, 500, 11);
    std::error_code ec;
    fs::create_directories(root.parent_path(), ec);
    fs::rename(tmp, root, ec);
    if (ec) fs::remove_all(tmp, ec);  // another process made it first
}

const fs::path& base_cases() {
    static std::once_flag once;
    static fs::path root(CF_CLI_BASE_DIR);
    std::call_once(once, [] {
        if (!fs::exists(root / "medium" / "case.json")) make_base_cases(root);
    });
    return root;
}

std::string cortexfuse_exe() { return CF_CORTEXFUSE_EXE; }

}  // namespace cf::test
