#pragma once
// JSON files of the navigation commands (docs/navigation.md): pivot poses, fiducial pairs,
// digitised landmarks, and the results. Parsers throw InputError(file, ...) naming the field.
#include <Eigen/Core>
#include <nlohmann/json_fwd.hpp>
#include <string>
#include <vector>

#include "cortexfuse/core/navigation.hpp"

namespace cf {

/// {"poses": [4x4, ...]}: T_tracker_from_pointer per frame (row-major, mm).
std::vector<RigidTransform> parse_pivot_poses(const nlohmann::json& j, const std::string& file);

struct FiducialPairs {
    std::vector<std::string> labels;
    std::vector<Eigen::Vector3d> p_patient_mm, p_image_mm;
    std::vector<Eigen::Vector3d> targets_image_mm;  // optional: where to predict TRE
};
/// {"fiducials": [{"label": "F1", "patient_mm": [x,y,z], "image_mm": [x,y,z]}, ...],
///  "targets_image_mm": [[x,y,z], ...]}   (targets optional)
FiducialPairs parse_fiducial_pairs(const nlohmann::json& j, const std::string& file);

/// {"landmarks": [{"label": "L1", "image_mm": [x,y,z]}, ...]}
std::vector<DigitisedPoint> parse_digitised(const nlohmann::json& j, const std::string& file);

nlohmann::json pivot_to_json(const PivotResult& r);
nlohmann::json fiducial_registration_to_json(const FiducialRegistration& r, const FiducialPairs& pairs);
nlohmann::json brain_shift_to_json(const BrainShiftReport& r);

}  // namespace cf
