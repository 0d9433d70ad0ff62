// JSON files of the navigation commands.
#include "cortexfuse/core/navigation_io.hpp"

#include <cmath>
#include <nlohmann/json.hpp>

#include "cortexfuse/core/error.hpp"

namespace cf {

using json = nlohmann::json;

namespace {

double number(const json& j, const std::string& file, const std::string& where) {
    if (!j.is_number()) throw InputError(file, where + " must be a number");
    const double v = j.get<double>();
    if (!std::isfinite(v)) throw InputError(file, where + " is not finite");
    return v;
}

Eigen::Vector3d vec3(const json& j, const std::string& file, const std::string& where) {
    if (!j.is_array() || j.size() != 3) throw InputError(file, where + " must be [x, y, z]");
    return {number(j[0], file, where), number(j[1], file, where), number(j[2], file, where)};
}

const json& array_field(const json& j, const char* key, const std::string& file) {
    if (!j.is_object() || !j.contains(key)) throw InputError(file, std::string("missing \"") + key + "\"");
    const json& a = j.at(key);
    if (!a.is_array()) throw InputError(file, std::string("\"") + key + "\" must be an array");
    return a;
}

std::string label_of(const json& e, const std::string& file, const std::string& where, size_t i) {
    if (!e.contains("label")) return "#" + std::to_string(i + 1);
    if (!e.at("label").is_string()) throw InputError(file, where + " label must be a string");
    return e.at("label").get<std::string>();
}

json v3(const Eigen::Vector3d& v) { return json::array({v.x(), v.y(), v.z()}); }

json m4(const RigidTransform& T) {
    json rows = json::array();
    for (int r = 0; r < 4; ++r) rows.push_back(json::array({T(r, 0), T(r, 1), T(r, 2), T(r, 3)}));
    return rows;
}

}  // namespace

std::vector<RigidTransform> parse_pivot_poses(const json& j, const std::string& file) {
    std::vector<RigidTransform> out;
    const json& a = array_field(j, "poses", file);
    for (size_t i = 0; i < a.size(); ++i) {
        const std::string where = "poses[" + std::to_string(i) + "]";
        const json& m = a[i];
        if (!m.is_array() || m.size() != 4) throw InputError(file, where + " must be a 4x4 array");
        RigidTransform T;
        for (int r = 0; r < 4; ++r) {
            if (!m[size_t(r)].is_array() || m[size_t(r)].size() != 4) throw InputError(file, where + " must be a 4x4 array");
            for (int c = 0; c < 4; ++c) T(r, c) = number(m[size_t(r)][size_t(c)], file, where);
        }
        out.push_back(T);
    }
    return out;
}

FiducialPairs parse_fiducial_pairs(const json& j, const std::string& file) {
    FiducialPairs f;
    const json& a = array_field(j, "fiducials", file);
    for (size_t i = 0; i < a.size(); ++i) {
        const std::string where = "fiducials[" + std::to_string(i) + "]";
        const json& e = a[i];
        if (!e.is_object() || !e.contains("patient_mm") || !e.contains("image_mm"))
            throw InputError(file, where + " needs \"patient_mm\" and \"image_mm\"");
        f.labels.push_back(label_of(e, file, where, i));
        f.p_patient_mm.push_back(vec3(e.at("patient_mm"), file, where + ".patient_mm"));
        f.p_image_mm.push_back(vec3(e.at("image_mm"), file, where + ".image_mm"));
    }
    if (j.contains("targets_image_mm")) {
        const json& t = array_field(j, "targets_image_mm", file);
        for (size_t i = 0; i < t.size(); ++i)
            f.targets_image_mm.push_back(vec3(t[i], file, "targets_image_mm[" + std::to_string(i) + "]"));
    }
    return f;
}

std::vector<DigitisedPoint> parse_digitised(const json& j, const std::string& file) {
    std::vector<DigitisedPoint> out;
    const json& a = array_field(j, "landmarks", file);
    for (size_t i = 0; i < a.size(); ++i) {
        const std::string where = "landmarks[" + std::to_string(i) + "]";
        const json& e = a[i];
        if (!e.is_object() || !e.contains("image_mm")) throw InputError(file, where + " needs \"image_mm\"");
        DigitisedPoint d;
        d.label = label_of(e, file, where, i);
        d.p_image_mm = vec3(e.at("image_mm"), file, where + ".image_mm");
        out.push_back(d);
    }
    return out;
}

json pivot_to_json(const PivotResult& r) {
    return {{"tip_tool_mm", v3(r.tip_tool_mm)},
            {"pivot_tracker_mm", v3(r.pivot_tracker_mm)},
            {"rms_mm", r.rms_mm},
            {"residuals_mm", r.residuals_mm},
            {"rotation_spread_deg", r.rotation_spread_deg},
            {"rotation_range_deg", r.rotation_range_deg},
            {"warning", r.warning}};
}

json fiducial_registration_to_json(const FiducialRegistration& r, const FiducialPairs& pairs) {
    json fid = json::array();
    for (size_t i = 0; i < r.residuals_mm.size(); ++i)
        fid.push_back({{"label", i < pairs.labels.size() ? pairs.labels[i] : "#" + std::to_string(i + 1)},
                       {"residual_mm", r.residuals_mm[i]},
                       {"used", bool(r.used[i])}});
    json excluded = json::array();
    for (int i : r.excluded) excluded.push_back(size_t(i) < pairs.labels.size() ? pairs.labels[size_t(i)] : std::to_string(i));
    json targets = json::array();
    for (const auto& t : pairs.targets_image_mm) targets.push_back({{"image_mm", v3(t)}, {"predicted_tre_mm", predicted_tre_mm(r, t)}});
    return {{"T_image_from_patient", m4(r.T_image_from_patient)},
            {"fre_mm", r.fre_mm},
            {"fle_mm", r.fle_mm},
            {"fiducials", fid},
            {"excluded", excluded},
            {"targets", targets}};
}

json brain_shift_to_json(const BrainShiftReport& r) {
    json rows = json::array();
    for (const auto& row : r.rows)
        rows.push_back({{"label", row.label},
                        {"dx_mm", row.d_mm.x()},
                        {"dy_mm", row.d_mm.y()},
                        {"dz_mm", row.d_mm.z()},
                        {"magnitude_mm", row.magnitude_mm}});
    return {{"landmarks", rows},
            {"mean_d_mm", v3(r.mean_d_mm)},
            {"sd_d_mm", v3(r.sd_d_mm)},
            {"mean_abs_d_mm", v3(r.mean_abs_d_mm)},
            {"mean_magnitude_mm", r.mean_magnitude_mm},
            {"sd_magnitude_mm", r.sd_magnitude_mm},
            {"max_magnitude_mm", r.max_magnitude_mm},
            {"missing_later", r.missing_later},
            {"missing_earlier", r.missing_earlier}};
}

}  // namespace cf
