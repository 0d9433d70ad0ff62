#pragma once
// A scratch folder under the daemon's work folder for an upload, an import or an export:
// made when constructed, removed with its content when it goes out of scope, so that a refused
// or failed request leaves nothing behind. Thread contract: one request's own object.
#include <atomic>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <string>

#include <unistd.h>

#include "cortexfuse/daemon/endpoints.hpp"

namespace cf::daemon {

struct Scratch {
    std::filesystem::path dir;
    /// <work_dir>/<tag>_<pid>_<n>; ApiError 500 io_error when it cannot be made.
    Scratch(const std::filesystem::path& work_dir, const std::string& tag) {
        static std::atomic<std::uint64_t> counter{0};
        dir = work_dir / (tag + "_" + std::to_string(::getpid()) + "_" + std::to_string(++counter));
        std::error_code ec;
        std::filesystem::create_directories(dir, ec);
        if (ec) throw ApiError(500, "io_error", "work folder " + dir.string() + ": " + ec.message());
    }
    ~Scratch() {
        std::error_code ec;
        std::filesystem::remove_all(dir, ec);
    }
    Scratch(const Scratch&) = delete;
    Scratch& operator=(const Scratch&) = delete;
    /// `message` without this folder's path (errors name the uploaded file, not the scratch).
    std::string strip(std::string message) const {
        const std::string prefix = dir.string() + "/";
        for (std::size_t k; (k = message.find(prefix)) != std::string::npos;) message.erase(k, prefix.size());
        return message;
    }
    /// Writes `bytes` to dir/name; ApiError 500 io_error when it cannot.
    std::filesystem::path write(const std::string& name, const std::string& bytes) const {
        const std::filesystem::path p = dir / name;
        std::ofstream o(p, std::ios::binary | std::ios::trunc);
        o.write(bytes.data(), std::streamsize(bytes.size()));
        o.close();
        if (!o) throw ApiError(500, "io_error", "work folder " + dir.string() + ": cannot write " + name);
        return p;
    }
};

}  // namespace cf::daemon
