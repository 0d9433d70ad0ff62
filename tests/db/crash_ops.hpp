#pragma once
// The writes of the crash test, shared by the writer child (cf_db_crash_writer) and the
// checking parent, so the parent knows exactly what each confirmed write must have stored.
// Write i: i % 4 == 0 creates case "crash-i"; 1 sets landmarks on case "crash-(i-1)"; 2 adds a
// registration with one result blob to "crash-(i-2)"; 3 imports a volume blob into "crash-(i-3)".
#include <cstdint>
#include <string>
#include <vector>

#include "cortexfuse/db/case_store.hpp"

namespace cfcrash {

inline std::string case_title(int i) { return "crash-" + std::to_string(i - i % 4); }

/// Deterministic content of a few kB, different for each write.
inline std::string payload(int i) {
    std::string s(2048 + (i * 37) % 4096, '\0');
    std::uint32_t x = 2463534242u ^ static_cast<std::uint32_t>(i * 2654435761u);
    for (auto& c : s) {
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        c = static_cast<char>(x & 0xff);
    }
    return s;
}

inline std::vector<cf::db::LandmarkPoint> landmark_points(int i) {
    std::vector<cf::db::LandmarkPoint> v;
    for (int k = 0; k < 4; ++k)
        v.push_back({"w" + std::to_string(i) + "-" + std::to_string(k), {1.0 * i, 0.5 * k, -2.0 * i + k}, {10.0 * k, 0.25 * i}});
    return v;
}

inline cf::db::RegistrationInput registration(int i) {
    cf::db::RegistrationInput r;
    r.params = {{"op", i}, {"search_stages", nlohmann::json::array({{{"name", "s"}, {"fwhm_mm", 4}}})}};
    r.final_pose = nlohmann::json{{"T_camera_from_world", {{1, 0, 0, i}, {0, 1, 0, 0}, {0, 0, 1, 0}, {0, 0, 0, 1}}}};
    r.nmi = 1.0 + i / 1000.0;
    r.results.push_back({"fused_png", "fused-" + std::to_string(i) + ".png", "image/png", {}, payload(i), {{"op", i}}});
    return r;
}

inline std::string volume_name(int i) { return "vol-" + std::to_string(i) + ".nii"; }

}  // namespace cfcrash
