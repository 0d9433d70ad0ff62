// cortexfuse navigate: pivot calibration, fiducial registration and brain shift from JSON files
// (formats in docs/navigation.md).
#include <cstdio>
#include <iostream>
#include <memory>
#include <nlohmann/json.hpp>

#include "commands.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/navigation.hpp"
#include "cortexfuse/core/navigation_io.hpp"

namespace cf::cli {

namespace {
void emit(const nlohmann::json& j, const std::string& out) {
    if (out.empty())
        std::cout << j.dump(2) << "\n";
    else
        write_file_atomic(out, j.dump(2) + "\n");
}
}  // namespace

void add_navigate(CLI::App& app) {
    struct Opts {
        std::string in, in2, out;
        PivotOptions pivot;
        FiducialOptions fid;
    };
    auto o = std::make_shared<Opts>();
    auto* cmd = app.add_subcommand("navigate", "Tracked-pointer navigation: pivot, register-fiducials, brain-shift");
    cmd->require_subcommand(1);

    auto* pivot = cmd->add_subcommand("pivot", "Pointer tip from poses recorded while pivoting in a divot");
    pivot->add_option("POSES", o->in, "JSON {\"poses\": [4x4 T_tracker_from_pointer, ...]}")->required();
    pivot->add_option("--out", o->out, "result JSON (default: stdout)");
    pivot->add_option("--min-spread-deg", o->pivot.min_rotation_spread_deg, "warn below this rotation spread")
        ->capture_default_str();
    pivot->callback([o] {
        run_guarded("navigate pivot", [o]() -> int {
            const PivotResult r = pivot_calibration(parse_pivot_poses(read_json_file(o->in), o->in), o->pivot);
            emit(pivot_to_json(r), o->out);
            std::fprintf(stderr, "cortexfuse navigate pivot: tip [%.2f %.2f %.2f] mm, RMS %.3f mm, spread %.1f deg\n",
                         r.tip_tool_mm.x(), r.tip_tool_mm.y(), r.tip_tool_mm.z(), r.rms_mm, r.rotation_spread_deg);
            if (!r.warning.empty()) std::cerr << "cortexfuse navigate pivot: warning: " << r.warning << "\n";
            return 0;
        });
    });

    auto* reg = cmd->add_subcommand("register-fiducials", "Patient-to-image registration from paired skin fiducials");
    reg->add_option("FIDUCIALS", o->in, "JSON {\"fiducials\": [{label, patient_mm, image_mm}], \"targets_image_mm\": [...]}")
        ->required();
    reg->add_option("--out", o->out, "result JSON (default: stdout)");
    reg->add_option("--outlier-mm", o->fid.outlier_threshold_mm, "drop the worst fiducial above this residual (0: never)")
        ->capture_default_str();
    reg->add_option("--fle-mm", o->fid.fle_mm, "fiducial localisation error for TRE (0: estimate from FRE)")->capture_default_str();
    reg->callback([o] {
        run_guarded("navigate register-fiducials", [o]() -> int {
            const FiducialPairs pairs = parse_fiducial_pairs(read_json_file(o->in), o->in);
            const FiducialRegistration r = register_fiducials(pairs.p_patient_mm, pairs.p_image_mm, o->fid);
            emit(fiducial_registration_to_json(r, pairs), o->out);
            std::fprintf(stderr, "cortexfuse navigate register-fiducials: FRE %.2f mm over %d fiducials, FLE %.2f mm",
                         r.fre_mm, r.n_used, r.fle_mm);
            for (int i : r.excluded) std::fprintf(stderr, ", excluded %s", pairs.labels[size_t(i)].c_str());
            std::fprintf(stderr, "\n");
            return 0;
        });
    });

    auto* shift = cmd->add_subcommand("brain-shift", "Brain shift per landmark between two digitisations (Table 3.3)");
    shift->add_option("EARLIER", o->in, "JSON {\"landmarks\": [{label, image_mm}]} digitised first")->required();
    shift->add_option("LATER", o->in2, "the same landmarks digitised again")->required();
    shift->add_option("--out", o->out, "result JSON (the table goes to stdout)");
    shift->callback([o] {
        run_guarded("navigate brain-shift", [o]() -> int {
            const BrainShiftReport r =
                brain_shift(parse_digitised(read_json_file(o->in), o->in), parse_digitised(read_json_file(o->in2), o->in2));
            std::cout << format_brain_shift_table(r);
            if (!o->out.empty()) write_file_atomic(o->out, brain_shift_to_json(r).dump(2) + "\n");
            return 0;
        });
    });
}

}  // namespace cf::cli
