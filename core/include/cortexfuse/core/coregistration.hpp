#pragma once
// Rigid co-registration of another modality (CT, an fMRI/EPI-space map) to the T1, through
// ITK's v4 registration framework (method, docs/planning.md).
//
// Convention (ITK's): the transform maps points of the FIXED image's world (LPS mm) to the
// MOVING image's world: p_moving = T_moving_from_fixed * p_fixed. Resampling the moving
// volume onto the fixed grid pulls each fixed voxel's value from T * p. Transform files are
// ITK transform files (Euler3DTransform_double_3_3 in .tfm text or .h5 HDF5) and open in
// 3D Slicer as they are (Slicer converts ITK's LPS "from parent" resampling transform itself).
#include <Eigen/Geometry>
#include <filesystem>
#include <string>
#include <vector>

#include "cortexfuse/core/progress.hpp"
#include "cortexfuse/core/volume.hpp"

namespace cf {

struct CoregParams {
    /// Mattes: ITK's Mattes MI (Parzen-windowed, sampled), gradient descent in ITK's v4
    /// framework. Nmi: true normalized mutual information NMI = (H(F)+H(M))/H(F,M)
    /// (Studholme), maximised by NLopt's Nelder-Mead over the same Euler3D parameters,
    /// multi-resolution (hand-written: ITK v4 has no NMI metric; core/src/nmi_coregistration.cpp).
    /// For Nmi, `iterations` bounds the evaluations (4 per iteration) and max_step sets the first
    /// simplex (2 max_step at the coarsest level, halved per level); relaxation is unused.
    enum class Metric { Mattes, Nmi } metric = Metric::Mattes;
    int bins = 32;                                 // [8, 256]
    std::vector<int> shrink{4, 2, 1};              // per level, [1, 16]
    std::vector<double> smooth_mm{2.0, 1.0, 0.0};  // Gaussian sigma per level, mm [0, 20]
    std::vector<int> iterations{200, 100, 50};     // per level (last value repeats) [1, 10000]
    double sampling = 0.05;                        // samples = this fraction of the fixed head's voxels (0, 1]
    double max_step = 2.0;                         // first optimiser step (mm-equivalent) (0, 50]
    double min_step = 0.01;                        // convergence step (0, max_step)
    double relaxation = 0.5;                       // step shrink on a direction change (0, 1)
    uint32_t seed = 1;                             // metric sampling (deterministic)
    /// Initial alignment: Centroids = foreground centroids made to coincide (robust to CT's
    /// -1000 HU air where image moments are not); Geometry = grid centres; Identity.
    enum class Init { Centroids, Geometry, Identity } init = Init::Centroids;
    /// Sample the metric only on the fixed image's foreground (head, not air). Off by default:
    /// a T1's skull is as dark as air, so the head mask leaves out the bone, a CT's strongest
    /// structure (a CT with bone, 8 deg / 11 mm misaligned: 8.1 mm mean error over the brain
    /// with the mask, 0.25 mm without; synthetic CT-like cases 0.145 -> 0.139 mm, EPI-like
    /// 0.24 -> 0.07 mm; docs/planning.md). The sample count stays `sampling` x head voxels.
    /// Both metrics follow this flag.
    bool fixed_foreground_mask = false;
    /// Clip each image to its head foreground's robust range before registration (a copy; the
    /// inputs are not changed): [p0.5 - 0.25 span, p99.5] of the foreground voxels, span =
    /// p99.5 - p0.5. The histograms' bins then cover the tissue, not CT's -1000 HU air or a few
    /// bright outliers (ANTs winsorises for the same reason). Mattes on bench CT case 0:
    /// 0.158 -> 0.145 mm mean error over the brain; EPI-like cases unchanged (docs/planning.md).
    bool clip_intensities = true;
    /// Quality gates (an error, not a silent bad result): at least this fraction of the
    /// fixed foreground must land inside the moving volume's field of view [0, 1], and the
    /// final NMI must exceed min_nmi (1 = independent images) [1, 2].
    double min_overlap = 0.5;
    double min_nmi = 1.02;
    /// Optimum gate: the NMI is also measured with the result moved by +-probe_mm along each
    /// axis and turned by +-probe_deg about each; when a probe raises it by more than
    /// max_probe_gain the result is not at the NMI optimum (not converged) and is refused.
    /// Applies to Metric::Nmi only (a Mattes optimum need not be an NMI optimum).
    /// probe_mm 0 turns the gate off. [0, 20] mm, [0, 20] deg, [0, 1]
    double probe_mm = 2.0, probe_deg = 2.0, max_probe_gain = 0.002;

    /// Throws InputError("coregister " + field, ...) when a value is out of range.
    void validate() const;
};

struct CoregLevelInfo {
    int iterations = 0;
    double metric = 0, seconds = 0;
    std::string stop;
};

struct CoregResult {
    Eigen::Matrix4d T_moving_from_fixed = Eigen::Matrix4d::Identity();  // world LPS mm
    Eigen::Vector3d center_world_mm = Eigen::Vector3d::Zero();           // rotation centre (fixed world)
    Eigen::Matrix4d T_initial = Eigen::Matrix4d::Identity();
    double metric = 0;       // ITK's final value (negative MI)
    double nmi = 0;          // (H(F)+H(M))/H(F,M) over the fixed foreground, after registration
    double overlap = 0;      // fraction of the fixed foreground inside the moving field of view
    double probe_gain = 0;   // largest NMI rise of the optimum probes (CoregParams::probe_mm; NMI metric only); <= 0 at an optimum
    double seconds = 0;
    std::vector<CoregLevelInfo> levels;
};

/// Registers `moving` to `fixed` rigidly. Throws InputError on bad input and when the
/// result fails the quality gates (no overlap: other anatomy or field of view; NMI near 1:
/// no shared structure, e.g. another patient's scan or an empty volume). Reports progress
/// ("coregister", level by level), honours cancellation (cf::Cancelled).
CoregResult coregister(const Volume& fixed, const Volume& moving, const CoregParams& params = {},
                       const Progress& progress = {});

/// Moving volume resampled onto `grid` through T_moving_from_fixed (linear, or nearest for
/// label maps); `outside` beyond the moving field of view.
Volume resample_rigid(const Volume& moving, const Eigen::Matrix4d& T_moving_from_fixed, const VolumeGeometry& grid,
                      bool nearest = false, float outside = 0.f);

/// ITK transform files (.tfm, .txt text; .h5, .hdf5 HDF5). Writing is atomic.
void save_transform(const Eigen::Matrix4d& T_moving_from_fixed, const Eigen::Vector3d& center_world_mm,
                    const std::filesystem::path& path);
/// Reads an ITK transform file (first linear transform), or an elastix
/// TransformParameters file with an EulerTransform (for comparisons). Throws InputError.
Eigen::Matrix4d load_transform(const std::filesystem::path& path);

/// Rigid transform from Euler angles (rad; ITK's Euler3DTransform order, ComputeZYX off),
/// translation (mm) and rotation centre (mm).
Eigen::Matrix4d euler_transform(const Eigen::Vector3d& angles_rad, const Eigen::Vector3d& translation_mm,
                                const Eigen::Vector3d& center_mm);

/// Mean and max distance (mm) between T_a * p and T_b * p over the world centres of the
/// mask's voxels (the error of a transform against the truth, over the brain).
struct TransformError {
    double mean_mm = 0, max_mm = 0;
    size_t points = 0;
};
TransformError transform_error(const Eigen::Matrix4d& T_a, const Eigen::Matrix4d& T_b, const LabelVolume& mask);

/// Foreground of a head scan: voxels above p2 + 0.1 (p98 - p2) (air and, for CT, its -1000 HU
/// background excluded). Used for the initial centroids, the metric mask and the overlap gate.
LabelVolume head_foreground(const Volume& v);

/// NMI = (H(A)+H(B))/H(A,B) of `a` and `b` sampled on `a`'s grid through T_b_from_a, over
/// `mask_a` (on a's grid; null = everywhere), `bins` bins per axis on the robust ranges.
double nmi_after_transform(const Volume& a, const Volume& b, const Eigen::Matrix4d& T_b_from_a, const LabelVolume* mask_a,
                           int bins = 64);

}  // namespace cf

namespace cf {

/// A synthetic co-registration case with known truth, from a real T1: the head moved by
/// T_moving_from_fixed^-1, resampled onto a CT-like grid (anisotropic voxels: in-plane
/// `inplane_mm`, slices `slice_mm`, covering the moved head) and its intensities remapped
/// non-monotonically to CT-like values (air -1000, CSF ~10, grey ~40, white ~28, fat
/// negative), with noise. moving(T p) = remap(fixed(p)).
struct SyntheticCoregCase {
    Volume moving;
    Eigen::Matrix4d T_moving_from_fixed = Eigen::Matrix4d::Identity();
    Eigen::Vector3d angles_deg = Eigen::Vector3d::Zero(), translation_mm = Eigen::Vector3d::Zero();
};
/// Random rotation within +-max_angle_deg per axis and translation within +-max_shift_mm,
/// about the fixed grid's centre; deterministic in `seed`.
SyntheticCoregCase make_synthetic_ct_case(const Volume& t1, uint64_t seed, double max_angle_deg = 10,
                                          double max_shift_mm = 15, double inplane_mm = 0.9, double slice_mm = 2.0,
                                          double noise_hu = 5.0);

/// The same for a mean-EPI-like moving image (the anatomy of an fMRI map's space): the moved
/// head on a coarse isotropic grid (`voxel_mm`, 3 mm by default, covering the moved head),
/// blurred before sampling (Gaussian, `blur_fwhm_mm`: the EPI's point spread and the
/// downsampling; no geometric distortion), and a T2*-like contrast remapped non-monotonically
/// from the T1's levels (air 0, CSF brightest 1000, grey 620 above white 450, fat suppressed
/// 120), with noise (`noise` in those units). moving(T p) = blur(remap(fixed))(p).
SyntheticCoregCase make_synthetic_epi_case(const Volume& t1, uint64_t seed, double max_angle_deg = 10,
                                           double max_shift_mm = 15, double voxel_mm = 3.0, double blur_fwhm_mm = 4.0,
                                           double noise = 20.0);

}  // namespace cf
