#pragma once
// Shared helpers of the case store tests: a scratch folder per test, fast argon2id settings,
// an injectable clock.
#include <gtest/gtest.h>
#include <stdlib.h>

#include <filesystem>
#include <fstream>
#include <memory>
#include <string>

#include "cortexfuse/db/case_store.hpp"

namespace cfdbtest {

namespace fs = std::filesystem;

/// A fresh folder under the test temp dir, removed at the end.
struct TempDir {
    fs::path path;
    TempDir() {
        std::string t = (fs::path(::testing::TempDir()) / "cf_db_XXXXXX").string();
        if (!mkdtemp(t.data())) throw std::runtime_error("mkdtemp failed");
        path = t;
    }
    ~TempDir() {
        std::error_code ec;
        fs::permissions(path, fs::perms::owner_all, fs::perm_options::add, ec);
        fs::remove_all(path, ec);
    }
};

/// A clock the test moves by hand.
struct FakeClock {
    cf::db::UtcTime now = cf::db::UtcTime(std::chrono::milliseconds(1'800'000'000'000));  // 2027-01-15
    void advance(std::chrono::milliseconds d) { now += d; }
};

inline cf::db::StoreOptions fast_options(std::shared_ptr<FakeClock> clock = nullptr) {
    cf::db::StoreOptions o;
    o.pwhash_opslimit = 1;            // argon2id minimum: tests only
    o.pwhash_memlimit_bytes = 8192;
    if (clock) o.now_utc = [clock] { return clock->now; };
    return o;
}

inline void write_file(const fs::path& p, const std::string& bytes) {
    fs::create_directories(p.parent_path());
    std::ofstream(p, std::ios::binary) << bytes;
}

inline std::string read_file(const fs::path& p) {
    std::ifstream in(p, std::ios::binary);
    return std::string(std::istreambuf_iterator<char>(in), {});
}

inline nlohmann::json camera_json() {
    return {{"width", 750}, {"height", 500}, {"fx", 1400.0}, {"fy", 1400.0}, {"cx", 374.5}, {"cy", 249.5},
            {"distortion", {0, 0, 0, 0, 0}}};
}

inline nlohmann::json roi_json() {
    return {{"type", "closed-cardinal-spline"}, {"tension", 0.0}, {"points", {{100, 100}, {600, 120}, {500, 400}, {150, 380}}}};
}

inline std::vector<cf::db::LandmarkPoint> landmarks(int n, double offset = 0) {
    std::vector<cf::db::LandmarkPoint> v;
    for (int i = 0; i < n; ++i)
        v.push_back({"L" + std::to_string(i + 1), {10.0 * i + offset, -5.0 + i, 40.5}, {100.0 + 50 * i, 200.0 - 7 * i}});
    return v;
}

/// Expects `f` to throw StoreError of `kind` whose message contains `needle`.
template <class F>
void expect_store_error(F&& f, cf::db::StoreError::Kind kind, const std::string& needle) {
    try {
        f();
        ADD_FAILURE() << "expected StoreError(" << cf::db::to_string(kind) << ") containing '" << needle << "'";
    } catch (const cf::db::StoreError& e) {
        EXPECT_EQ(e.kind(), kind) << e.what();
        EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << "message: " << e.what();
    }
}

}  // namespace cfdbtest
