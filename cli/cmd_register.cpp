// cortexfuse register CASE_DIR --out RESULT.json (docs/case-format.md).
#include <iostream>
#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/registration.hpp"
#include "cortexfuse/render/renderer_factory.hpp"
#include "progress_bar.hpp"

namespace fs = std::filesystem;

namespace cf::cli {

namespace {
struct RegisterOptions {
    std::string case_dir, out, params_file, trace_csv;
    bool seed_schedule = false;
    std::string renderer = "cpu";
};
}  // namespace

void add_register(CLI::App& app) {
    auto opt = std::make_shared<RegisterOptions>();
    auto* sub = app.add_subcommand("register", "Register a case folder's photo to its volume");
    sub->add_option("case_dir", opt->case_dir, "Case folder holding case.json")->required();
    sub->add_option("--out", opt->out, "Result JSON to write")->required();
    sub->add_option("--params", opt->params_file, "Registration parameters (JSON, see docs/registration.md)");
    sub->add_flag("--seed-schedule", opt->seed_schedule, "Use the seed's original stage schedule");
    sub->add_option("--renderer", opt->renderer, "Ray caster for the similarity: cpu, gl (EGL/OpenGL) or auto")
        ->capture_default_str();
    sub->add_option("--trace", opt->trace_csv, "Write every evaluation (stage, similarity, cost) as CSV");
    sub->callback([opt] {
        run_guarded("register", [&] {
            ProgressBar bar("register");
            LoadedCase c = load_case(opt->case_dir, &bar.progress());
            RegistrationParams params = opt->seed_schedule ? RegistrationParams::seed_schedule() : RegistrationParams::defaults();
            if (!opt->params_file.empty())
                params = registration_params_from_json(read_json_file(opt->params_file), opt->params_file);
            params.renderer_factory = renderer_factory(parse_renderer_kind(opt->renderer));
            Registration reg(c.volume, c.mask, params);
            const RegistrationResult r = reg.run(c.photo, &bar.progress());
            write_file_atomic(opt->out, result_to_json(r).dump(2) + "\n");
            if (!opt->trace_csv.empty()) {
                std::string csv = "evaluation,stage,similarity,cost\n";
                for (const auto& t : r.trace)
                    csv += std::to_string(t.evaluation) + "," + r.stages[size_t(t.stage)].name + "," +
                           std::to_string(t.similarity) + "," + std::to_string(t.cost) + "\n";
                write_file_atomic(opt->trace_csv, csv);
            }
            std::cerr << "registered in " << r.seconds << " s, " << r.evaluations << " evaluations, " << r.params.metric
                      << " " << r.initial_similarity << " -> " << r.similarity << "\n";
            return 0;
        });
    });
}

}  // namespace cf::cli
