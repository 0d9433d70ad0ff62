#pragma once
// One function per subcommand, each in its own cmd_<name>.cpp; commands.cpp calls them all.
#include <CLI/CLI.hpp>

namespace cf::cli {
/// Registers every subcommand on `app`.
void add_commands(CLI::App& app);

void add_register(CLI::App& app);
void add_render(CLI::App& app);
void add_phantom(CLI::App& app);
void add_evaluate(CLI::App& app);
void add_bench(CLI::App& app);
void add_skullstrip(CLI::App& app);
void add_landscape(CLI::App& app);
void add_calibrate(CLI::App& app);
void add_camera(CLI::App& app);  // camera list|capture|files|download
void add_navigate(CLI::App& app);  // navigate pivot|register-fiducials|brain-shift
void add_coregister(CLI::App& app);  // coregister, coregister-synth, coregister-error
void add_overlay(CLI::App& app);
void add_plan(CLI::App& app);
void add_sim_tracker(CLI::App& app);
void add_track(CLI::App& app);

/// Runs `body`, turning cf::InputError and other exceptions into one line on stderr and exit 1
/// (2 for cf::Cancelled). Every command's callback goes through it.
int guarded(const char* command, const std::function<int()>& body);
/// A subcommand callback: runs `body` guarded and throws CLI::RuntimeError(rc) when rc != 0.
inline void run_guarded(const char* command, const std::function<int()>& body) {
    if (const int rc = guarded(command, body)) throw CLI::RuntimeError(rc);
}
}  // namespace cf::cli
