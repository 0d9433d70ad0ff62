#pragma once
// The 3D-2D registration: landmark-initialised, intensity-based. The volume is ray-cast from
// the current pose, compared with the photo by NMI inside the ROI, and the pose is optimised by
// the seed's multi-stage Downhill Simplex. Every stage's parameters are data (saved with the
// result), every stage reports progress, can be cancelled, and is timed.
#include <array>
#include <functional>
#include <limits>
#include <memory>
#include <nlohmann/json.hpp>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <utility>
#include <vector>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/pose.hpp"
#include "cortexfuse/core/progress.hpp"
#include "cortexfuse/core/renderer.hpp"
#include "cortexfuse/core/roi.hpp"
#include "cortexfuse/core/volume.hpp"

namespace cf {

/// One simplex search at one blur level and image size.
struct StageParams {
    std::string name;
    double fwhm_mm = 4;        // Gaussian blur of photo and rendering, FWHM at the cortex
    double step_mm = 2;        // initial simplex step for translations
    double step_deg = 2;       // ... and for rotations
    int render_width_px = 190; // working image width (height follows the aspect)
    int max_evaluations = 120;
    double xtol_mm = 0.1;      // stop when the simplex is smaller than this
    double xtol_deg = 0.1;
    /// The weakly seen directions get their own first steps (0: step_mm / step_deg): depth
    /// (tz) scales the picture by ~1 % per 3 mm, and tilts (rx, ry) about the pivot on the
    /// cortex move it less than the turn about the view axis (rz) does.
    double step_depth_mm = 0;
    double step_tilt_deg = 0;
    /// Ray-cast sample distance for this stage (0: RegistrationParams::sample_distance_mm).
    double sample_distance_mm = 0;
};

struct RegistrationParams {
    std::string transfer_function = "surface_white";  // render style: a preset name
    /// Photo channel compared with the rendering: "red" (sees through thin blood: blood absorbs
    /// green and blue far more than red), "grey", "green", "blue_minus_half_red" (hides vessels).
    std::string photo_channel = "red";
    std::string metric = "nmi";
    int bins = 32;
    /// Joint histogram binning: "linear" (partial volume: smooth in the pose) or "hard".
    std::string binning = "hard";
    /// After the high-pass, rescale by the 1st-99th percentiles inside the mask (true) or by
    /// the minimum and maximum (false, noisy: one pixel moves the whole histogram).
    bool robust_range = false;
    /// The photo's light is rarely at the lens (an OR lamp or the microscope's light): with a
    /// headlight rendering, NMI peaks about 1.4 mm off the truth on phantom photos lit from up to
    /// 25 deg aside, 0.4 mm when lit from the lens. When on, after the search stages the light
    /// direction is estimated at the best pose by a grid over the offsets (x, y) of the
    /// camera-frame direction (x, y, -1), |x|, |y| <= light_max_offset, and the final stages
    /// render with it; each later round re-estimates it at the refined pose and re-runs the
    /// final stages.
    bool estimate_light = false;
    double light_max_offset = 0.5;
    int light_grid = 5;    // points per axis of the first grid (a finer 3 x 3 follows)
    /// What the grid's (x, y) place: "distant", a light from direction (x, y, -1) for the whole
    /// picture; "point", a lamp in the lens plane at (x, y, 0) times the pivot's depth, whose
    /// direction turns across the picture as a flash's or a lamp's near the camera does ((0, 0)
    /// is the headlight exactly).
    std::string light_model = "distant";
    int light_rounds = 1;  // estimate + final stages, repeated
    /// Also estimate the light after the first search stage, at the best screened pose, so
    /// the later search stages render with it rather than with a headlight.
    bool light_after_screen = false;
    /// Before the final stages, the light is estimated at each finalist's own pose rather than
    /// once at the best one's: a finalist at a wrong pose then does not hand the others a light
    /// fitted to it, and each pose is judged with the light that explains the photo best there.
    bool light_per_finalist = false;
    /// Working width the light grid is scored at; 0: the first final stage's. The light's
    /// direction is a broad trend, visible at a small size.
    int light_width_px = 0;
    bool mask_glare = true;          // drop specular glare, gauze and drapes from the similarity mask
    /// Drop vessels and blood: pixels more saturated or darker than the ROI's median by this many
    /// median absolute deviations. 0 disables.
    double vessel_mask_mad = 3.0;
    /// How the vessel mask finds the pia's saturation: tissue_median_mad() with this window, which
    /// holds when blood covers half the ROI. 0: the plain median and MAD of the ROI (before
    /// 2026-11-29), which a pool of blood or a dense vessel network broke.
    double vessel_mask_window = 15.0;
    /// Remove shading trends wider than this FWHM (mm at the cortex) from photo and rendering
    /// before comparing them. 0 disables.
    double highpass_fwhm_mm = 12.0;
    /// Blur photo and rendering over the usable pixels only (a normalised convolution with the
    /// photo's mask, for the stage's blur and the high-pass alike): with a plain blur, gauze,
    /// blood, vessels and glare, which the mask drops, still spread their light into the usable
    /// pixels around them. false: the plain blur. The defaults turn it on for the FWHM 2 mm
    /// stages only (masked_blur_max_fwhm_mm 3, thirty-eighth session, docs/registration.md).
    bool masked_blur = false;
    /// With masked_blur, the pixels the blur reads:
    /// - "usable": the photo's usable pixels, the ROI less glare, vessels, gauze and blood (the
    ///   thirty-seventh session's form);
    /// - "roi": the whole ROI; what lies outside it is left out, what the mask drops inside it is
    ///   blurred in as with the plain blur;
    /// - "usable_and_outside": what lies outside the ROI is blurred in as with the plain blur,
    ///   and only what the mask drops inside it is left out.
    /// Without an ROI, "roi" is the plain blur and "usable_and_outside" is "usable".
    std::string masked_blur_over = "usable";
    /// With masked_blur, only the stages whose blur (FWHM, mm) lies in [min, max] use it; the
    /// others blur plainly. The defaults, 0 and 100, take every stage. The screens (8 and 4 mm)
    /// choose the basin, where the leak is widest; the final stages (2 mm) make the fit.
    double masked_blur_min_fwhm_mm = 0;
    double masked_blur_max_fwhm_mm = 100;
    /// Soft prior: penalty weight * max(0, rms - rms_landmark - tolerance)^2, rms in pixels at
    /// 375 px width. Holds depth and tilt, which a single photo barely constrains. 0 disables.
    double landmark_prior_weight = 0.01;
    double landmark_prior_tolerance_px = 1.0;
    /// Measure the excess from the rms the true pose is expected to have, not from the fit's:
    /// a 6-dof fit to n noisy pairs absorbs part of the noise, so the truth's rms is about
    /// rms_fit * sqrt(2n / (2n - 6)) (twice the fit's for n = 4). Without this the prior pulls
    /// every run towards the landmark pose.
    bool landmark_prior_expected = false;
    /// The landmarks' model-point error (mm, 1 sd: where on the MRI the surgeon clicked). A few
    /// pairs fit six parameters closely enough to hide it, yet at the landmarks' magnification it
    /// costs the true pose f / z pixels per mm. When > 0, that many pixels are added to the prior's
    /// tolerance and to the RMS limit under which other landmark fits become starts. 0: pixels
    /// only (opt-in since the thirty-fourth session; docs/registration.md).
    double landmark_world_sd_mm = 0.0;
    /// With landmark_world_sd_mm > 0: the starts and the search stay as with 0, and the landmarks'
    /// fits within the limit widened by that error are screened apart under the widened prior; the
    /// best of them is searched on under it. The final stages widen the prior only when that
    /// candidate beats every other, all charged by the widened prior, by landmark_world_sd_margin
    /// (the image prefers a pose that only the model points' error allows), and the last round only
    /// when the winner of the final stages came from a landmark fit
    /// (RegistrationResult::landmark_prior_widened). Otherwise the run is the plain prior's.
    /// (Registration::score, which knows no run, charges by the widened prior.)
    bool landmark_world_sd_by_image = false;
    /// The cost margin that the widened fit has to win by (NMI units; docs/registration.md).
    double landmark_world_sd_margin = 0.02;
    /// Two witnesses from the photo besides the margin, each a sweep of the similarity in tx and ty
    /// (prominence_sweep_mm either side, prominence_sweep_steps samples, at the first final stage's
    /// size and blur, with a headlight, as the prominence gate), taken only once the margin is met:
    /// the plain prior must be holding its best candidate off the photo's peak (the sweep across
    /// it peaks at least landmark_world_sd_peak_apart_mm away, the two axes averaged), and the
    /// widened fit must sit on a peak that stands clear (peak_prominence() of its sweep, the two
    /// axes averaged, at least landmark_world_sd_min_prominence). 0 turns a witness off. A lead
    /// alone is noise on a photo that pins the pose weakly: the thresholds lie in the gaps between
    /// the runs widening rescued and those it harmed (thirty-sixth session, docs/registration.md).
    /// The sweeps are reported as the stages "witness-peak-apart" and "witness-prominence".
    double landmark_world_sd_peak_apart_mm = 2.5;
    double landmark_world_sd_min_prominence = 0.45;
    double sample_distance_mm = 1.0;
    /// The optimiser's translation frame: false, the camera's axes (tz along the optical axis);
    /// true, tz along the line of sight through the pivot and tx, ty across it, so a depth step
    /// only scales the picture about the ROI instead of also shifting it sideways.
    bool depth_along_pivot_ray = false;
    /// With an initial pose (PhotoInput::initial_pose) and >= 4 landmarks, the landmarks' own
    /// ambiguity becomes extra starts too: the move from their best fit to each other fit that
    /// explains them about as well (pnp_candidates: the mirror turn and the depth that near-planar
    /// landmarks on a narrow view leave open), applied about the pivot to the given pose. From the
    /// landmarks alone those fits are starts already; a given pose had none of them. Not for
    /// landmarks nearly on a line (landmark_spread_warning()), whose other fits only sample the
    /// free turn about it.
    bool initial_pose_landmark_moves = false;
    /// Those moves start from the local fit the given pose lies in (Levenberg-Marquardt on the
    /// landmarks from the given pose) when that lies over 5 deg from the best fit, and go to every
    /// fit, the best included: a pose near another fit (the plain PnP fit where the planar flip
    /// fits better, even one too poor to be kept among the fits) gets a move to the best one.
    /// From the landmarks alone, or for a pose in the best fit's basin, nothing changes.
    bool landmark_moves_from_nearest_fit = false;
    /// Depth scan before the final (and refine) stages: the cost at 2 * depth_scan_steps + 1
    /// points depth_scan_mm apart along the line of sight through the pivot (a pure change of
    /// scale about the ROI), scored at the stage's size and blur; the simplex starts from the
    /// best. Depth is the weakest seen direction, and the coarse stages leave it where the
    /// landmarks and the misalignment put it. 0: off.
    double depth_scan_mm = 0;
    int depth_scan_steps = 3;
    /// NLopt's local derivative-free method for every stage: "neldermead" (the seed's downhill
    /// simplex), "sbplx" (Rowan's subplex) or "bobyqa" (Powell's quadratic model).
    std::string optimizer = "neldermead";
    /// Render only the first crossing of the surface level, opaque (RenderOptions::surface_only):
    /// a composited rendering's grey depends on where the sample lattice falls on the surface,
    /// which made the similarity saw-tooth along the viewing axis.
    bool surface_only = false;
    /// Where the rendered surface lies, in tissue terms: the transfer function's opacity ramp
    /// is centred on CSF + f * (grey - CSF), the class means (three_class_means()) inside the
    /// brain mask, instead of on the preset's fixed fraction of the robust range. A fixed
    /// fraction lands at different tissue on every scanner (0.42 of the range is f = 0.48 on the
    /// bundled head, 0.41 on the chris and seg3d heads, -0.24, below the CSF mean, on the
    /// sagittal DICOM series). NaN: the preset as it is.
    double surface_tissue_fraction = std::numeric_limits<double>::quiet_NaN();
    /// What the rendering contributes to the similarity: (1 - w) * shading + w * relief, where
    /// relief is the negated depth of the first surface hit (1 unit per 10 mm); after the
    /// high-pass it is the local sulcal depth, which does not depend on where the light was.
    /// 0: shading only (the seed).
    double depth_weight = 0.0;
    /// Sulcal darkening of the rendering: shade * (1 - w * smoothstep(lo, hi, relief)), relief =
    /// the hit's depth below the local mean depth (blurred over sulcal_hull_fwhm_mm). Exposed
    /// cortex looks dark in its sulci (shadow, CSF, the veins that run there), which Lambert
    /// shading of the surface alone does not show. 0: shading only (the seed).
    double sulcal_weight = 0.0;
    double sulcal_lo_mm = 0.5, sulcal_hi_mm = 3.0, sulcal_hull_fwhm_mm = 8.0;
    /// Rendering is cropped to the ROI's bounding box plus this fraction of the working width
    /// on each side (context for the blurs). Larger than 1 renders the whole frame.
    double roi_margin_fraction = 0.12;
    /// Rays cast beyond the reach of the stage's blur (4 sigma, where OpenCV cuts its kernel)
    /// from every usable ROI pixel: one every `outer_ray_stride` pixels along each axis, the
    /// rest interpolated from them. Those pixels reach the similarity only through the wide
    /// blurs (the high-pass's shading trends and the sulcal hull, 12 mm), which a coarser
    /// lattice feeds as well. 1: every ray.
    int outer_ray_stride = 1;
    /// A stage whose blur would span more than this many pixels (FWHM at the pivot's depth) at
    /// its render width is rendered narrower, so that it spans this many: a camera close to the
    /// cortex or zoomed in sees the ROI large, and the blurred images then hold nothing the
    /// extra rays add. Fixed once a run from the initial pivot depth, so every finalist is scored
    /// on the same grid. 0: every stage at its render_width_px.
    double max_fwhm_px = 0;
    /// Anchor the ray caster's sample lattice at the pivot (RenderOptions::sample_anchor_world_mm)
    /// instead of at the camera: with the lattice riding on the camera, a step along the viewing
    /// axis by part of the sample distance moves every sample near the surface by it, and the
    /// similarity saw-toothed in depth with the sample distance's period. false: the camera's.
    /// Off by default: smoother in depth, but no nearer the truth over 520 paired runs
    /// (docs/registration.md, "The sample lattice anchored at the pivot"); for diagnosis.
    bool sample_anchor_at_pivot = false;
    /// The seed's subspaces: starting offsets (rx, ry, rz deg, tx, ty, tz mm) about the pivot,
    /// each searched independently through `search_stages`.
    std::vector<PoseParams> starts = {{0, 0, 0, 0, 0, 0}};
    std::vector<StageParams> search_stages;
    /// After the first search stage only this many starts (the lowest costs) go on through the
    /// later search stages: a cheap screen of every subspace, then work where it pays. 0: all.
    int search_keep = 0;
    /// Beside those, the best this many of the starts that come from the landmarks' other fits
    /// (from the landmarks alone: the fits after the best; with an initial pose: the moves of
    /// initial_pose_landmark_moves) go on too when none of them is among the search_keep. A
    /// start 10 mm / 5 deg off screened at FWHM 8 mm for 30 evaluations can lose to a plain start
    /// that is further from the truth. 0: the screen alone decides.
    int search_keep_fits = 0;
    int keep_best = 1;  // candidates carried into the final stages
    /// The prominence gate: after the last round the similarity is swept across the winner in
    /// tx and ty (prominence_sweep_mm either side, prominence_sweep_steps samples, at the first
    /// final stage's size and blur, with a headlight), and each curve's peak_prominence() is
    /// taken. When their mean is under this, the photo does not pin the pose (a rival ridge
    /// nearly as high: a template with no sulci, thick slices), so the last round's stages run
    /// again from the winner with the landmark prior at prominence_gate_prior_weight, and the
    /// result says so in `warnings`. 0: off (no sweep). Needs >= 4 landmarks and a prior.
    double prominence_gate = 0;
    double prominence_gate_prior_weight = 0.03;
    double prominence_sweep_mm = 10;
    int prominence_sweep_steps = 41;
    std::vector<StageParams> final_stages;
    /// Stages of the later light rounds (the winner only, after the light is re-estimated at
    /// its refined pose); empty: `final_stages` again.
    std::vector<StageParams> refine_stages;
    /// Makes the similarity renderer (not serialised); empty: the CPU ray caster. The CLI sets
    /// it from --renderer through cf_render_gl's renderer_factory() (core links no GL).
    std::function<std::unique_ptr<Renderer>(const Volume&, const TransferFunction&, const LabelVolume*)> renderer_factory;

    static RegistrationParams defaults();
    /// The seed's original schedule (FWHM 8 -> 2 mm, steps 10 mm / 10 deg, final 3 mm / 3 deg).
    static RegistrationParams seed_schedule();
    /// Throws InputError(context, ...) on bad values.
    void validate(const std::string& context) const;
    /// The stage that runs last (refine, final or search): the result's similarity is reported
    /// at its size and blur.
    const StageParams& last_stage() const;
};

nlohmann::json to_json(const RegistrationParams& p);
RegistrationParams registration_params_from_json(const nlohmann::json& j, const std::string& context);

struct StageReport {
    std::string name;
    int start = 0;
    StageParams params;
    double best_similarity = 0;
    double best_cost = 0;
    int evaluations = 0;
    double seconds = 0;
    /// The width it rendered at: params.render_width_px, or narrower by max_fwhm_px.
    int render_width_used_px = 0;
    /// The pose the stage ended at (its best); the light grid's report: the pose it scored.
    Pose T_camera_from_world = Pose::Identity();
};

struct TracePoint {
    int evaluation;
    int stage;  // index into RegistrationResult::stages
    double similarity;
    double cost;
};

struct RegistrationResult {
    Pose T_camera_from_world = Pose::Identity();
    Pose initial_T_camera_from_world = Pose::Identity();
    std::string initial_method;  // "pnp", "pnp-ransac", "initial_pose"
    double initial_landmark_rms_px = 0, final_landmark_rms_px = 0;
    /// With a given pose and RegistrationParams::landmark_moves_from_nearest_fit: 1 when the
    /// moves to the landmarks' fits started from the local fit the pose lies in, 0 from the best.
    int landmark_moves_from_fit = 0;
    /// The landmarks' spread (case.hpp; both 0 without landmarks) and what a person should know
    /// about this run (e.g. landmarks nearly on a line), in words.
    LandmarkSpread landmark_spread;
    std::vector<std::string> warnings;
    double similarity = 0;        // final metric value (NMI by default)
    double initial_similarity = 0;
    int evaluations = 0;
    double seconds = 0;
    std::vector<StageReport> stages;
    std::vector<TracePoint> trace;  // every evaluation, for the convergence plot
    RegistrationParams params;
    Eigen::Vector3d pivot_world_mm = Eigen::Vector3d::Zero();
    /// The light direction the final stages rendered with (camera frame, towards the light);
    /// (0, 0, -1) with a headlight.
    Eigen::Vector3d light_direction_camera{0, 0, -1};
    /// With RegistrationParams::light_model "point": the lamp's position (camera frame, mm), and
    /// light_direction_camera is its direction from the pivot; nullopt otherwise.
    std::optional<Eigen::Vector3d> light_position_camera_mm;
    /// The prominence gate (RegistrationParams::prominence_gate): the mean peak prominence of tx
    /// and ty about the winner (NaN when the gate did not run), and whether it fell under the
    /// gate so that the landmarks were weighed up for the last round.
    double peak_prominence = std::numeric_limits<double>::quiet_NaN();
    bool landmarks_weighed_up = false;
    /// The prior was widened by landmark_world_sd_mm (RegistrationParams::landmark_world_sd_by_image).
    bool landmark_prior_widened = false;
    /// With landmark_world_sd_by_image: by how much the fit searched under the widened prior beat
    /// the best other candidate (both charged by it; compared with landmark_world_sd_margin). NaN
    /// when there was no such fit.
    double landmark_widened_fit_lead = std::numeric_limits<double>::quiet_NaN();
    /// The witnesses (RegistrationParams::landmark_world_sd_peak_apart_mm, _min_prominence): how
    /// far from the best plain candidate the photo's peak lies (mm, tx and ty averaged), and the
    /// prominence of the widened fit's peak. NaN where not swept (the margin not met, or off).
    double landmark_plain_fit_peak_apart_mm = std::numeric_limits<double>::quiet_NaN();
    double landmark_widened_fit_prominence = std::numeric_limits<double>::quiet_NaN();
};

nlohmann::json result_to_json(const RegistrationResult& r);

/// What the photo side of a registration needs.
struct PhotoInput {
    cv::Mat photo_bgr;       // 8-bit, any size with the camera's aspect ratio
    Intrinsics camera;       // for the camera's own width x height
    std::vector<Landmark> landmarks;
    std::optional<Roi> roi;
    std::optional<Pose> initial_pose;  // used instead of the landmark fit when given
};

/// Similarity along each pose parameter about a pose (rx, ry, rz in deg, tx, ty, tz in mm,
/// about the pivot in the camera frame): the landscape the optimiser sees.
struct SimilaritySweep {
    std::array<std::vector<double>, 6> offsets, similarity;
    Eigen::Vector3d pivot_world_mm = Eigen::Vector3d::Zero();
};

/// How far a similarity curve's peak stands above the best it reaches more than `apart_from_peak`
/// (mm or deg, in `offsets`' unit) from it, as a fraction of the curve's range: near 1, one clear
/// peak; near 0, a rival as high. 1 when no sample lies that far from the peak, 0 on a flat
/// curve. Throws std::invalid_argument when the two lists differ in length or are empty.
double peak_prominence(const std::vector<double>& offsets, const std::vector<double>& similarity,
                       double apart_from_peak = 3);

/// A registration engine for one volume: prepares the renderer once, then runs any number of
/// registrations (the evaluation reuses it). Thread contract: one run() at a time.
class Registration {
public:
    /// `volume` and `brain_mask` are borrowed only during construction.
    Registration(const Volume& volume, const LabelVolume& brain_mask, RegistrationParams params);
    ~Registration();
    RegistrationResult run(const PhotoInput& in, const Progress* progress = nullptr);
    /// The similarity landscape about `T_center` at one stage's size and blur (diagnosis), under
    /// the light given as for score() (a result's estimate; the headlight when neither is given).
    SimilaritySweep sweep(const PhotoInput& in, const Pose& T_center, const StageParams& stage, double range_mm = 10,
                          double range_deg = 10, int steps = 41,
                          std::optional<Eigen::Vector3d> light_direction_camera = std::nullopt,
                          std::optional<Eigen::Vector3d> light_position_camera_mm = std::nullopt);
    /// Similarity and cost (with the landmark prior) of pose `T` as the optimiser sees them at
    /// `stage`, with the pivot and blur depth taken from `T_reference` (the run's start). The
    /// evaluation scores the true pose with it: a final cost below the truth's means the
    /// similarity, not the search, limits accuracy.
    struct PoseScore {
        double similarity = 0, cost = 0;
    };
    /// The light (a result's estimate): a point light at `light_position_camera_mm` when given,
    /// else a distant light from `light_direction_camera` when given, else the headlight.
    PoseScore score(const PhotoInput& in, const Pose& T, const Pose& T_reference, const StageParams& stage,
                    std::optional<Eigen::Vector3d> light_direction_camera = std::nullopt,
                    std::optional<Eigen::Vector3d> light_position_camera_mm = std::nullopt);
    /// What the similarity compares at `stage` for pose `T` (pivot, blur depth and light as for
    /// score()), for a person to look at: the photo's channel and the rendering, both filtered by the
    /// stage's blur (and high-pass), and the photo's usable pixels, all at the stage's working
    /// size and crop. The images are the engine's own, copied out.
    struct SimilarityInputs {
        cv::Mat photo;     // CV_32F, the filtered photo channel
        cv::Mat rendered;  // CV_32F, the filtered rendering
        cv::Mat usable;    // CV_8U, 255 where the similarity counts the pixel
        double similarity = 0;
    };
    SimilarityInputs similarity_inputs(const PhotoInput& in, const Pose& T, const Pose& T_reference, const StageParams& stage,
                                       std::optional<Eigen::Vector3d> light_direction_camera = std::nullopt,
                                       std::optional<Eigen::Vector3d> light_position_camera_mm = std::nullopt);
    const RegistrationParams& params() const { return params_; }
    /// The renderer used for the similarity (registration style), e.g. for depth lookups.
    Renderer& renderer() { return *renderer_; }
    /// The intensity the rendered surface lies at (volume units) when
    /// RegistrationParams::surface_tissue_fraction placed it; NaN otherwise.
    double surface_level() const { return surface_level_; }

private:
    RegistrationParams params_;
    std::unique_ptr<Renderer> renderer_;
    double surface_level_ = std::numeric_limits<double>::quiet_NaN();
};

/// A case folder loaded and checked, every error naming its file: the volume, the brain mask
/// (read, resampled onto the volume grid if needed, or computed by skull stripping) and the photo.
struct LoadedCase {
    CaseSpec spec;
    Volume volume;
    LabelVolume mask;
    bool mask_computed = false;  // true when skull stripping made it
    PhotoInput photo;
};
LoadedCase load_case(const std::filesystem::path& dir, const Progress* progress = nullptr);

/// The preprocessed photo channel in [0,1] and its similarity mask at a working size.
struct PhotoChannel {
    cv::Mat channel;  // CV_32F
    cv::Mat valid;    // CV_8U, 255 where pixels count
};
/// `vessel_mad` and `vessel_window` as RegistrationParams' vessel_mask_mad and vessel_mask_window.
PhotoChannel photo_channel(const cv::Mat& photo_bgr_working, const std::string& channel, bool mask_glare,
                           const cv::Mat& roi_mask, double vessel_mad = 0,
                           double vessel_window = RegistrationParams{}.vessel_mask_window);

/// The median and median absolute deviation of the tissue's values when up to half of them are
/// something else that lies well above them (blood and vessels: more saturated): taken over the
/// values within `window` MADs (as the densest quarter that starts in the lower half estimates
/// them) of that quarter's middle. On uncontaminated values, close to the plain median and MAD.
std::pair<float, float> tissue_median_mad(std::vector<float> values, double window);

}  // namespace cf
