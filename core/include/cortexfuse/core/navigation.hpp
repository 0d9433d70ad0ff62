#pragma once
// Navigation math for a tracked pointer (pure computation, no I/O, no driver):
//   - pivot calibration: the pointer tip in the pointer tool's frame, from poses taken while
//     the tip rests in a divot and the handle is swivelled;
//   - paired-point patient-to-image registration from skin fiducials (Umeyama, rigid, no
//     scale), fiducial registration error (FRE) per fiducial, outlier exclusion, and the
//     predicted target registration error (TRE) at a target (Fitzpatrick, West & Maurer 1998);
//   - digitising landmarks with the pointer, and brain shift between two digitisations of
//     the same landmarks (the seed's Table 3.3: dx, dy, dz, |d| per landmark, mean ± sd).
//
// Frames (names say which): "tracker" is the camera of the tracking system, "tool" a tracked
// tool's own frame (pointer or reference), "patient" is the reference tool's frame (the
// reference sits on the head clamp, so the patient does not move in it), "image" is the
// preoperative volume's world space (LPS mm). Every point is in mm.
//
// Errors: bad input (too few poses or fiducials, NaN, non-rigid poses, collinear fiducials,
// mismatched counts or labels) throws cf::InputError naming the input and the problem.
// Re-entrant: no state outside the arguments.
#include <Eigen/Geometry>
#include <string>
#include <vector>

namespace cf {

using RigidTransform = Eigen::Matrix4d;  // 4x4, last row 0 0 0 1

// ------------------------------------------------------------------ pivot calibration

struct PivotOptions {
    /// Below this rotation spread (degrees, see PivotResult::rotation_spread_deg) the result
    /// carries a warning: the tip is poorly constrained along some direction. 0..90.
    double min_rotation_spread_deg = 10.0;
};

struct PivotResult {
    Eigen::Vector3d tip_tool_mm = Eigen::Vector3d::Zero();       // the tip in the pointer's frame
    Eigen::Vector3d pivot_tracker_mm = Eigen::Vector3d::Zero();  // the divot in the tracker frame
    double rms_mm = 0;                                           // rms distance of the tips from the pivot
    std::vector<double> residuals_mm;                            // per pose: |R t + p - pivot|
    /// How far the handle was swivelled, in the least-constrained direction: the rotation
    /// angle whose chord is the rms deviation of the poses' rotations from their mean along
    /// the direction the tip is least constrained (0 when the pointer only spun about one axis).
    double rotation_spread_deg = 0;
    /// Largest angle of any pose's rotation from the first one, degrees (for the report).
    double rotation_range_deg = 0;
    /// Empty when the pointer moved enough; otherwise one line saying what is weak.
    std::string warning;
};

/// Least squares over poses T_tracker_from_pointer (each rigid): solves R_i t + p_i = pivot
/// for t (tip in the tool) and pivot (in the tracker) by SVD. At least 3 poses; throws
/// InputError("pivot poses", ...) for NaN, non-rigid poses, or poses that do not constrain
/// the tip at all (no rotation).
PivotResult pivot_calibration(const std::vector<RigidTransform>& T_tracker_from_pointer, const PivotOptions& options = {});

// ------------------------------------------------------ paired-point fiducial registration

struct FiducialOptions {
    /// A fiducial whose residual exceeds this (mm) after the fit is dropped (the worst first,
    /// then refit), as long as at least 3 remain. <= 0 or +inf: no exclusion.
    double outlier_threshold_mm = 5.0;
    /// Fiducial localisation error (rms, 3D, mm) for the TRE prediction. <= 0: estimated from
    /// the FRE as FRE * sqrt(N / (N - 2)) (Fitzpatrick: <FRE²> = (1 - 2/N) <FLE²>).
    double fle_mm = 0.0;
    /// Fiducials whose rms distance from their best-fit line is below this (mm) are
    /// collinear: the rotation about that line is undetermined, so registration refuses.
    double min_line_distance_mm = 1.0;
};

struct FiducialRegistration {
    RigidTransform T_image_from_patient = RigidTransform::Identity();
    double fre_mm = 0;                 // rms residual over the fiducials used
    std::vector<double> residuals_mm;  // per fiducial, all of them, with the final transform
    std::vector<bool> used;            // false for the excluded ones
    std::vector<int> excluded;         // indices in the order they were dropped
    double fle_mm = 0;                 // the FLE used for TRE predictions (given or estimated)
    /// Fiducial configuration in image space (used ones): centroid, principal axes (columns)
    /// and the rms distance of the fiducials from each axis, for predicted_tre_mm().
    Eigen::Vector3d centroid_image_mm = Eigen::Vector3d::Zero();
    Eigen::Matrix3d axes_image = Eigen::Matrix3d::Identity();
    Eigen::Vector3d rms_axis_distance_mm = Eigen::Vector3d::Zero();
    int n_used = 0;
};

/// Rigid paired-point registration (Eigen::umeyama without scaling) of fiducials digitised in
/// patient space to the same fiducials marked in the image, in the same order. At least 3,
/// not collinear, finite. Throws InputError("fiducials", ...).
FiducialRegistration register_fiducials(const std::vector<Eigen::Vector3d>& p_patient_mm,
                                        const std::vector<Eigen::Vector3d>& p_image_mm, const FiducialOptions& options = {});

/// Predicted rms TRE (mm) at a target in image space (Fitzpatrick, West & Maurer 1998):
/// TRE² = FLE²/N · (1 + 1/3 Σ_k d_k² / f_k²), d_k the target's distance from principal axis k
/// of the fiducial configuration, f_k the fiducials' rms distance from it.
double predicted_tre_mm(const FiducialRegistration& reg, const Eigen::Vector3d& target_image_mm);

// ------------------------------------------------------------------ digitising, brain shift

/// One tracked frame while the pointer rests on a point: both tools' poses in the tracker.
struct PointerFrame {
    RigidTransform T_tracker_from_pointer = RigidTransform::Identity();
    RigidTransform T_tracker_from_reference = RigidTransform::Identity();
};

struct DigitisedPoint {
    std::string label;
    Eigen::Vector3d p_patient_mm = Eigen::Vector3d::Zero();  // in the reference tool's frame
    Eigen::Vector3d p_image_mm = Eigen::Vector3d::Zero();    // mapped by T_image_from_patient
    double spread_mm = 0;                                    // rms of the frames about their mean
    int frames = 0;
};

/// The tip position averaged over frames, in patient (reference) space and in image space.
/// Throws InputError(label, ...) when there are no frames, a pose is not rigid or finite, or
/// the tip moved more than max_spread_mm (rms) while being held still.
DigitisedPoint digitise_point(const std::string& label, const std::vector<PointerFrame>& frames,
                              const Eigen::Vector3d& tip_tool_mm, const RigidTransform& T_image_from_patient,
                              double max_spread_mm = 1.0);

struct ShiftRow {
    std::string label;
    Eigen::Vector3d d_mm = Eigen::Vector3d::Zero();  // later minus earlier, image axes (LPS)
    double magnitude_mm = 0;
};

struct BrainShiftReport {
    std::vector<ShiftRow> rows;  // in the order of `later`, only labels present in both
    Eigen::Vector3d mean_d_mm = Eigen::Vector3d::Zero(), sd_d_mm = Eigen::Vector3d::Zero();  // signed
    Eigen::Vector3d mean_abs_d_mm = Eigen::Vector3d::Zero();
    double mean_magnitude_mm = 0, sd_magnitude_mm = 0, max_magnitude_mm = 0;
    std::vector<std::string> missing_later;    // labels digitised first but not re-digitised
    std::vector<std::string> missing_earlier;  // labels re-digitised without a first digitisation
};

/// Brain shift per landmark (matched by label; image space). Sample sd (n - 1); 0 for one
/// landmark. Throws InputError for duplicate labels, NaN, or no landmark in common.
BrainShiftReport brain_shift(const std::vector<DigitisedPoint>& earlier, const std::vector<DigitisedPoint>& later);

/// The seed's Table 3.3 as plain text: one row per landmark, then mean ± sd.
std::string format_brain_shift_table(const BrainShiftReport& report);

}  // namespace cf
