// cortexfuse: the batch tool. Thin commands over the core; see docs/cli.md.
#include <CLI/CLI.hpp>
#include <iostream>

#include "commands.hpp"
#include "cortexfuse/core/error.hpp"

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
