#pragma once
// Runs the built `cortexfuse` as a child process and captures its exit status, stdout and
// stderr: the CLI tests check what a user sees, not what the library returns.
#include <string>
#include <vector>

namespace cf::test {

struct ProcessResult {
    int exit_code = -1;    // the child's exit status; 128 + signal when it was killed
    bool timed_out = false;
    std::string out, err;  // stdout, stderr
};

/// Runs `argv` (argv[0] is the executable path) in `cwd` with a wall-clock limit. Outside a
/// sanitizer build the child's address space is capped at `max_address_space_gib`, so a
/// command that tries to allocate for an absurd header fails here instead of swapping.
ProcessResult run_process(const std::vector<std::string>& argv, double timeout_s = 120.0,
                          double max_address_space_gib = 16.0);

}  // namespace cf::test
