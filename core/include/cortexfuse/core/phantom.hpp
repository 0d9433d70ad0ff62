#pragma once
// The synthetic case ("phantom") generator: case folders (docs/case-format.md) with ground
// truth, made from a real T1 MRI and its brain mask, to evaluate photo-to-MRI registration.
//
// The photo is NOT a volume rendering of the MRI: the brain surface mesh (flying edges at a
// grey-matter/CSF level) is rasterised from a random pose by a software z-buffer, and the
// pixels are painted with a procedural surgical look: pinkish cortex whose tint varies per
// case, darker/redder sulci, a vessel network drawn on the surface (dark veins that follow
// sulci, thinner brighter arteries, capillaries), wet specular glare from a light near the
// camera, an irregular craniotomy with bone edge, skin and surgical drapes outside it,
// optional gauze (cottonoid) and blood over part of the cortex, vignetting, colour
// temperature, noise, JPEG artefacts, and optional DSLR size.
//
// Everything random comes from the seed: the same seed and inputs give identical files.
#include <Eigen/Core>
#include <array>
#include <cstdint>
#include <filesystem>
#include <opencv2/core.hpp>
#include <optional>
#include <string>
#include <vector>

#include "cortexfuse/core/camera.hpp"
#include "cortexfuse/core/progress.hpp"
#include "cortexfuse/core/rasterizer.hpp"
#include "cortexfuse/core/volume.hpp"

namespace cf {

/// Options of the generator. Each range [lo, hi] is sampled uniformly per case.
struct PhantomParams {
    uint64_t seed = 1;
    /// Base photo size (case.json camera unless the case is DSLR-size). 64..4000 px each.
    int width = 750, height = 500;
    /// Vary the base size per case (+-20 %, aspect kept between 1.33 and 1.6). Off: exact size.
    bool vary_size = true;
    /// Fraction of cases written as DSLR-size JPEGs (dslr_width x dslr_height). 0..1.
    double dslr_fraction = 0.2;
    int dslr_width = 3000, dslr_height = 2000;
    /// Probability that a case has gauze (cottonoid patties) / blood pools over cortex. 0..1.
    double gauze_prob = 0.3;
    double blood_prob = 0.3;
    /// Probability of subarachnoid blood in the sulci over a patch, and of a thin film of blood
    /// and irrigation over another, each drawn apart from the pools. Unset: `blood_prob`, so
    /// that `blood_prob = 0` still means a case without blood. 0..1.
    std::optional<double> sulcal_blood_prob, blood_film_prob;
    /// Probability that the photo is lit by the OR lamp's focused spot (bright on the opening,
    /// dimmer over the skin and drapes) rather than evenly (a flash), and that the scalp around
    /// the opening is stained by iodine skin prep. Both (and the clips' uneven placing) come from
    /// a random stream of their own, every value drawn whatever the chances: a seed's poses,
    /// landmarks and ROI do not depend on them, nor does one on the other. 0..1.
    double lamp_spot_prob = 0.8;
    double skin_prep_prob = 0.6;
    /// Probability that the light is the OR's light head far overhead (0.8-1.2 m, up to 35 deg
    /// off the camera's axis: rays nearly parallel across the opening) rather than a light near
    /// the camera (a flash, a headlamp, the microscope's; up to 120 mm aside of the lens). From
    /// a stream of its own: at 0 a seed's cases are those it gave before the option. 0..1.
    double far_lamp_prob = 0;
    /// The photographic finish: the drapes' folds in relief under the lamp, the lamp mirrored
    /// in pools of blood (glints, not flecks), halation around glare, the lens' lateral colour,
    /// pores and stubble on the scalp, pits in the bone. Drawn from the look's own stream, so a
    /// seed's poses, landmarks and ROI are the same either way. Off: the appearance before it
    /// (for comparison).
    bool photo_finish = true;
    /// Part of the finish (nothing without it): light scattered under the cortex's surface, so
    /// its shading is soft and reddish at the sulci's edges as in a photograph of tissue, not
    /// hard as on a plastic model; and pools of blood mirroring a lamp of a light head's size
    /// through a rippled surface (rounded glints). Drawn from a stream of its own, so the rest
    /// of the finish and the case are the same either way. Off: the finish before it.
    bool tissue_optics = true;
    /// Probability of non-zero lens distortion (k1 in [-0.15, 0.08], small k2, p1, p2). 0..1.
    double distortion_prob = 0.4;
    /// Camera-to-craniotomy distance, mm. 100..1000.
    std::array<double, 2> distance_mm{200, 450};
    /// Craniotomy diameter (irregular ellipse on the cortex), mm. 20..120.
    std::array<double, 2> craniotomy_mm{40, 80};
    /// Off-normal tilt of the optical axis, degrees. 0..60.
    double max_tilt_deg = 28;
    /// How much of the image height the craniotomy spans. 0.2..1.2.
    std::array<double, 2> fill_fraction{0.55, 0.95};
    /// Landmarks per case (4..12); picking noise at 750 px width (scaled with the width), px;
    /// 3D picking noise, mm (sd per axis).
    int landmarks_min = 4, landmarks_max = 6;
    std::array<double, 2> landmark_pixel_sd{1.5, 3.0};
    double landmark_world_sd_mm = 0.8;
    /// Truth targets on the exposed cortex inside the ROI. 5..200.
    int targets_min = 15, targets_max = 30;
    /// Fraction of PNG photos (the rest are JPEG); DSLR-size cases are always JPEG. 0..1.
    double png_fraction = 0.5;

    /// The simulated camera: photograph the case's scene (craniotomy, vessels, look: all from
    /// the seed, so unchanged) from this pose and/or with this camera instead of the random
    /// framing. Unset (the default): the random framing. The random draws are made either way.
    std::optional<Pose> fixed_T_camera_from_world;
    std::optional<Intrinsics> fixed_camera;

    /// Throws InputError("phantom " + field, ...) when a value is out of range.
    void validate() const;
};

/// The brain surface used by the generator, in world LPS mm.
struct PhantomSurface {
    RasterMesh mesh;                              // world LPS mm
    std::vector<Eigen::Vector3f> normals;         // outward unit normals per vertex
    std::vector<Eigen::Vector3f> smooth_vertices; // heavily smoothed copy (same indexing)
    std::vector<Eigen::Vector3f> smooth_normals;  // its outward normals
    std::vector<float> sulcal_depth_mm;           // depth below the smoothed surface (> 0 in sulci)
    float iso_level = 0;                          // T1 intensity of the surface
    Eigen::Vector3f centroid_world_mm = Eigen::Vector3f::Zero();
};

/// Builds the brain surface (VTK flying edges + windowed-sinc smoothing + largest component)
/// from a T1 and a brain mask on the same grid. Throws InputError when the mask is empty
/// or on a different grid.
PhantomSurface build_phantom_surface(const Volume& t1, const LabelVolume& mask, const Progress& progress = {});

struct PhantomLandmark {
    std::string label;
    Eigen::Vector3d world_mm;  // with picking noise
    Eigen::Vector2d pixel;     // with picking noise
    Eigen::Vector3d true_world_mm;
};

/// One generated case, in memory.
struct PhantomCase {
    Intrinsics camera;
    Pose T_camera_from_world = Pose::Identity();
    cv::Mat photo_bgr;  // 8-bit BGR, camera.width x camera.height
    bool jpeg = false;  // written as photo.jpg (else photo.png)
    int jpeg_quality = 92;
    std::vector<PhantomLandmark> landmarks;
    std::vector<Eigen::Vector2d> roi_points;  // closed Catmull-Rom control points, pixels
    std::vector<Eigen::Vector3d> targets_world_mm;
    /// Description of the randomised appearance (written into truth.json for analysis).
    std::string notes;
};

/// Generates case number `index` of a run with `params` (the case's own randomness is
/// derived from params.seed and index).
PhantomCase generate_phantom_case(const PhantomSurface& surface, const PhantomParams& params, int index);

/// Writes a case folder: case.json, photo.png|jpg, landmarks.json, roi.json, truth.json.
/// `volume_ref` and `mask_ref` are written as is into case.json ("volume", "brain_mask";
/// relative paths resolve against the case folder). Writes into a temporary folder and
/// renames, so a case folder is whole or absent. Throws InputError on I/O failure.
void write_phantom_case(const PhantomCase& c, const std::filesystem::path& case_dir, const std::string& volume_ref,
                        const std::string& mask_ref);

/// The whole batch: loads the volume and mask, copies them once into out_dir (t1.nii.gz,
/// brain_mask.nii.gz) and writes n cases out_dir/case_0000 ... Returns the case folders.
std::vector<std::filesystem::path> generate_phantoms(const std::filesystem::path& out_dir, int n,
                                                     const std::filesystem::path& volume_path,
                                                     const std::filesystem::path& mask_path,
                                                     const PhantomParams& params, const Progress& progress = {});

}  // namespace cf
