#pragma once
#include <CLI/CLI.hpp>

namespace cf::cli {
/// Registers every subcommand on `app`.
void add_commands(CLI::App& app);
}  // namespace cf::cli
