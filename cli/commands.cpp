#include "commands.hpp"

#include <iostream>

#include "cortexfuse/core/error.hpp"

namespace cf::cli {

int guarded(const char* command, const std::function<int()>& body) {
    try {
        return body();
    } catch (const cf::InputError& e) {
        std::cerr << "cortexfuse " << command << ": error: " << e.what() << "\n";
        return 1;
    } catch (const cf::Cancelled&) {
        std::cerr << "cortexfuse " << command << ": cancelled\n";
        return 2;
    } catch (const std::exception& e) {
        std::cerr << "cortexfuse " << command << ": error: " << e.what() << "\n";
        return 1;
    }
}

void add_commands(CLI::App& app) {
    add_register(app);
    add_render(app);
    add_evaluate(app);
    add_landscape(app);
    add_skullstrip(app);
    add_phantom(app);
    add_calibrate(app);
    add_camera(app);
    add_navigate(app);
    add_coregister(app);
    add_overlay(app);
    add_plan(app);
    add_sim_tracker(app);
    add_track(app);
    add_bench(app);
}

}  // namespace cf::cli
