// cf_cli_tests: GoogleTest main, plus `--make-base DIR`, the ctest fixture step that generates
// the base cases once before the tests run in parallel.
#include <gtest/gtest.h>

#include <cstring>
#include <filesystem>
#include <iostream>

#include "base_case.hpp"

int main(int argc, char** argv) {
    if (argc == 3 && std::strcmp(argv[1], "--make-base") == 0) {
        try {
            std::filesystem::remove_all(argv[2]);
            cf::test::make_base_cases(argv[2]);
        } catch (const std::exception& e) {
            std::cerr << "cf_cli_tests --make-base: " << e.what() << "\n";
            return 1;
        }
        return 0;
    }
    testing::InitGoogleTest(&argc, argv);
    return RUN_ALL_TESTS();
}
