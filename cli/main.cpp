// cortexfuse: the batch tool. Thin commands over the core; see docs/cli.md.
#include <CLI/CLI.hpp>
#include <iostream>

#include "commands.hpp"
#include "cortexfuse/core/cpu_baseline.hpp"
#include "cortexfuse/core/error.hpp"

// A CPU without the build's -march features: one line and exit 69 before anything runs (docs/packaging.md).
CF_CPU_BASELINE_CHECK("cortexfuse")

int main(int argc, char** argv) {
    CLI::App app{"cortexfuse: photo-to-MRI fusion, batch tool"};
    app.require_subcommand(1);
    cf::cli::add_commands(app);
    try {
        app.parse(argc, argv);
    } catch (const CLI::RuntimeError& e) {
        return e.get_exit_code();  // a command failed; it already printed its one line
    } catch (const CLI::ParseError& e) {
        return app.exit(e);
    }
    return 0;
}
