#pragma once
// Small file helpers the CLI tests share: JSON in and out, a pose from its JSON matrix, and a
// fresh scratch folder per test process.
#include <unistd.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <string>

#include "cortexfuse/core/camera.hpp"

namespace cf::test {

inline nlohmann::json read_json(const std::filesystem::path& p) {
    std::ifstream in(p);
    return nlohmann::json::parse(in);
}
inline void write_json(const std::filesystem::path& p, const nlohmann::json& j) { std::ofstream(p) << j.dump(2) << "\n"; }

inline Pose pose_of(const nlohmann::json& m) {
    Pose T;
    for (int r = 0; r < 4; ++r)
        for (int c = 0; c < 4; ++c) T(r, c) = m.at(size_t(r)).at(size_t(c)).get<double>();
    return T;
}

/// TMP/cf_cli_NAME_PID, emptied.
inline std::filesystem::path fresh_dir(const std::string& name) {
    const std::filesystem::path p = std::filesystem::temp_directory_path() / ("cf_cli_" + name + "_" + std::to_string(::getpid()));
    std::filesystem::remove_all(p);
    std::filesystem::create_directories(p);
    return p;
}

}  // namespace cf::test
