// cortexfuse register CASE_DIR --out RESULT.json (docs/case-format.md).
#include <iostream>
#include <optional>
#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/landmarks.hpp"
#include "cortexfuse/core/registration.hpp"
#include "cortexfuse/render/renderer_factory.hpp"
#include "progress_bar.hpp"

namespace fs = std::filesystem;

namespace cf::cli {

namespace {
struct RegisterOptions {
    std::string case_dir, out, params_file, trace_csv, init = "auto";
    bool seed_schedule = false;
    std::string renderer = "cpu";
};
/// The engine names what it checks generically ("landmarks", "photo", ...); a user wants the
/// case's file. Rethrows `e` naming that file when the case has one.
[[noreturn]] void rethrow_naming_file(const InputError& e, const CaseSpec& spec) {
    std::optional<fs::path> file;
    if (e.input() == "landmarks") file = spec.landmarks_path;
    else if (e.input() == "photo") file = spec.photo_path;
    else if (e.input() == "initial pose") file = spec.initial_pose_path ? spec.initial_pose_path : spec.landmarks_path;
    if (!file) throw e;
    std::string problem = e.what();
    problem = problem.substr(std::min(problem.size(), e.input().size() + 2));
    throw InputError(file->string(), problem);
}
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
    sub->add_option("--init", opt->init,
                    "Landmark alignment: auto (PnP and its mirror alternatives as starts), pnp (solvePnP, RANSAC "
                    "from 6 pairs), ortho (the seed's scaled-orthographic variant)")
        ->check(CLI::IsMember({"auto", "pnp", "ortho"}))
        ->capture_default_str();
    sub->callback([opt] {
        run_guarded("register", [&] {
            // Everything cheap is checked before the long work: parameters, where the outputs go.
            RegistrationParams params = opt->seed_schedule ? RegistrationParams::seed_schedule() : RegistrationParams::defaults();
            if (!opt->params_file.empty())
                params = registration_params_from_json(read_json_file(opt->params_file), opt->params_file);
            params.renderer_factory = renderer_factory(parse_renderer_kind(opt->renderer));
            // --init pnp|ortho: that one fit is the start, without the landmarks' other fits.
            if (opt->init != "auto") params.initial_pose_landmark_moves = false;
            for (const std::string& out : {opt->out, opt->trace_csv}) {
                if (out.empty()) continue;
                const fs::path folder = fs::absolute(fs::path(out)).parent_path();
                std::error_code ec;
                if (fs::is_directory(fs::path(out), ec)) throw InputError(out, "is a folder; name the file to write");
                if (!fs::is_directory(folder, ec)) throw InputError(out, "cannot write: folder " + folder.string() + " does not exist");
            }
            ProgressBar bar("register");
            LoadedCase c = load_case(opt->case_dir, &bar.progress());
            // The landmark fit asked for, with its reprojection RMS; pnp/ortho become the start pose.
            std::optional<LandmarkFit> fit;
            Registration reg(c.volume, c.mask, params);
            RegistrationResult r;
            try {
                if (!c.spec.landmarks.empty() && !c.spec.initial_pose) {
                    fit = opt->init == "ortho" ? fit_pose_orthographic(c.spec.landmarks, c.spec.camera)
                                               : fit_pose_pnp(c.spec.landmarks, c.spec.camera);
                    if (opt->init != "auto") c.photo.initial_pose = fit->T_camera_from_world;
                } else if (opt->init != "auto") {
                    throw InputError("register --init", "needs landmarks in the case (it has an initial_pose instead)");
                }
                if (c.photo.initial_pose) {
                    // A start pose that looks away from the volume is a bad case, not a job to run.
                    const Pose& T = *c.photo.initial_pose;
                    const Eigen::Vector3d centre = T.topLeftCorner<3, 3>() * c.volume.geom.center_world_mm() + T.topRightCorner<3, 1>();
                    if (!(centre.z() > 0))
                        throw InputError("initial pose", "the brain is not in view of the camera at the initial pose (the volume is behind it)");
                }
                r = reg.run(c.photo, &bar.progress());
            } catch (const InputError& e) {
                rethrow_naming_file(e, c.spec);
            }
            nlohmann::json out = result_to_json(r);
            if (fit) {
                out["landmark_fit"] = {{"method", fit->method}, {"rms_px", fit->rms_px}, {"inliers", fit->inliers}};
                if (opt->init != "auto") out["initial_method"] = fit->method;
            }
            write_file_atomic(opt->out, out.dump(2) + "\n");
            if (!opt->trace_csv.empty()) {
                std::string csv = "evaluation,stage,similarity,cost\n";
                for (const auto& t : r.trace)
                    csv += std::to_string(t.evaluation) + "," + r.stages[size_t(t.stage)].name + "," +
                           std::to_string(t.similarity) + "," + std::to_string(t.cost) + "\n";
                write_file_atomic(opt->trace_csv, csv);
            }
            std::cerr << "registered in " << r.seconds << " s, " << r.evaluations << " evaluations, " << r.params.metric
                      << " " << r.initial_similarity << " -> " << r.similarity << "\n";
            for (const auto& w : r.warnings) std::cerr << "warning: " << opt->case_dir << ": " << w << "\n";
            return 0;
        });
    });
}

}  // namespace cf::cli
