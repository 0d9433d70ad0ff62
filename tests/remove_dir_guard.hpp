#pragma once
// A folder a test made, removed when the guard goes: at the end of a test (also one an ASSERT
// stopped early) or, as a function-local static, when the test program ends.
#include <filesystem>
#include <system_error>

namespace cf::test {

struct RemoveDirGuard {
    std::filesystem::path dir;
    ~RemoveDirGuard() {
        std::error_code ec;
        std::filesystem::remove_all(dir, ec);
    }
};

}  // namespace cf::test
