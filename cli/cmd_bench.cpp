// cortexfuse bench render|nmi|register: the engine's timings as one JSON object on stdout
// (medians, p90, peak RSS). The logic lives in bench/ (cortexfuse/bench/bench.hpp).
#include <filesystem>
#include <iostream>
#include <memory>

#include "cortexfuse/core/install_paths.hpp"
#include "commands.hpp"
#include "cortexfuse/bench/bench.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/registration.hpp"
#include "progress_bar.hpp"

namespace cf::cli {

namespace {
void print(const nlohmann::json& j, bool json_out) {
    if (json_out) {
        std::cout << j.dump() << "\n";
    } else {
        std::cout << j.dump(2) << "\n";
    }
}
}  // namespace

void add_bench(CLI::App& app) {
    struct Opts {
        std::string volume = cf::bundled_data_dir(CF_DATA_DIR).string() + "/t1_head_mne_ecog.nii.gz";
        std::string mask, size = "375x250", tf = "skin", renderer = "cpu", save_frame, case_dir, params_file, reference_file;
        std::string register_renderer = "cpu", reference_renderer;
        std::string phantom_mask = cf::bundled_data_dir(CF_DATA_DIR).string() + "/brainmask_mne_ecog_binary.nii.gz";
        int frames = 30, warmup = 5, threads = 0, bins = 64, repeat = 20, cases = 4;
        double sample_mm = 1.0;
        uint64_t seed = 1;
        bool json = false, no_shading = false, surface_only = false, no_start_map = false, masked = false, keep = false, reference_seed = false;
    };
    auto o = std::make_shared<Opts>();
    auto* bench = app.add_subcommand("bench", "Time the engine: one JSON object with medians on stdout");
    bench->require_subcommand(1);

    auto* render = bench->add_subcommand("render", "Ray-cast frames along a small camera path (ms per frame)");
    render->add_option("--volume", o->volume, "Volume (NIfTI, NRRD, MHA or a DICOM folder)")->capture_default_str();
    render->add_option("--mask", o->mask, "Render only inside this mask");
    render->add_option("--size", o->size, "Image size WxH")->capture_default_str();
    render->add_option("--tf", o->tf, "Transfer function: a preset name or a JSON file")->capture_default_str();
    render->add_option("--renderer", o->renderer, "Renderer backend: cpu, gl (EGL/OpenGL) or auto")->capture_default_str();
    render->add_option("--frames", o->frames, "Timed frames")->capture_default_str();
    render->add_option("--warmup", o->warmup, "Untimed frames first")->capture_default_str();
    render->add_option("--threads", o->threads, "Worker threads (0: all cores)")->capture_default_str();
    render->add_option("--sample-mm", o->sample_mm, "Sample distance along rays, mm")->capture_default_str();
    render->add_flag("--no-shading", o->no_shading, "Turn Lambert shading off");
    render->add_flag("--surface-only", o->surface_only, "Registration's rendering: the first crossing of the surface level only");
    render->add_flag("--no-start-map", o->no_start_map, "CPU: rays start where they enter the volume's box, not at the nearest visible brick (same pictures; to compare)");
    render->add_option("--save-frame", o->save_frame, "Write the first timed frame as PNG");
    render->add_flag("--json", o->json, "One line of JSON (default: indented)");
    render->callback([o] {
        run_guarded("bench render", [&] {
            bench::RenderBenchConfig c;
            c.volume = o->volume;
            c.mask = o->mask;
            std::tie(c.width, c.height) = bench::parse_size(o->size);
            c.tf = o->tf;
            c.renderer = o->renderer;
            c.frames = o->frames;
            c.warmup = o->warmup;
            c.threads = o->threads;
            c.sample_mm = o->sample_mm;
            c.shading = !o->no_shading;
            c.surface_only = o->surface_only;
            c.ray_start_map = !o->no_start_map;
            c.save_frame = o->save_frame;
            ProgressBar bar("bench render");
            const auto j = bench::run_render_bench(c, &bar.progress());
            print(j, o->json);
            return 0;
        });
    });

    auto* nmi = bench->add_subcommand("nmi", "NMI, MI and NCC of two images (us per evaluation, one thread)");
    nmi->add_option("--size", o->size, "Image size WxH")->capture_default_str();
    nmi->add_option("--bins", o->bins, "Histogram bins")->capture_default_str();
    nmi->add_option("--frames", o->frames, "Timed samples")->capture_default_str();
    nmi->add_option("--repeat", o->repeat, "Evaluations per sample")->capture_default_str();
    nmi->add_option("--warmup", o->warmup, "Untimed samples first")->capture_default_str();
    nmi->add_flag("--masked", o->masked, "Count only an elliptic ROI (~45 % of the pixels)");
    nmi->add_flag("--json", o->json, "One line of JSON (default: indented)");
    nmi->callback([o] {
        run_guarded("bench nmi", [&] {
            bench::NmiBenchConfig c;
            std::tie(c.width, c.height) = bench::parse_size(o->size);
            c.bins = o->bins;
            c.frames = o->frames;
            c.repeat = o->repeat;
            c.warmup = o->warmup;
            c.masked = o->masked;
            ProgressBar bar("bench nmi");
            print(bench::run_nmi_bench(c, &bar.progress()), o->json);
            return 0;
        });
    });

    auto* reg = bench->add_subcommand("register", "Register phantom cases from their landmarks (s per registration)");
    reg->add_option("--volume", o->volume, "T1 volume for the generated phantoms")->capture_default_str();
    reg->add_option("--mask", o->phantom_mask, "Its brain mask")->capture_default_str();
    reg->add_option("--case-dir", o->case_dir, "A case folder or a folder of them, instead of generating phantoms");
    reg->add_option("--cases", o->cases, "Phantom cases to generate")->capture_default_str();
    reg->add_option("--seed", o->seed, "Phantom seed")->capture_default_str();
    reg->add_option("--threads", o->threads, "Worker threads (0: all cores)")->capture_default_str();
    reg->add_flag("--keep", o->keep, "Keep the generated cases (the folder is in the JSON)");
    reg->add_option("--params", o->params_file, "Registration parameters to time (JSON; default: the defaults)");
    reg->add_option("--reference", o->reference_file,
                    "A reference schedule (JSON) registered on the same cases in the same run, case by case in turn");
    reg->add_flag("--reference-seed", o->reference_seed, "The seed's schedule as the reference");
    reg->add_option("--renderer", o->register_renderer, "Ray caster for the similarity: cpu, gl (EGL/OpenGL) or auto")
        ->capture_default_str();
    reg->add_option("--reference-renderer", o->reference_renderer,
                    "Also register the same schedule with this renderer, case by case in turn (e.g. --renderer gl "
                    "--reference-renderer cpu)");
    reg->add_flag("--json", o->json, "One line of JSON (default: indented)");
    reg->callback([o] {
        run_guarded("bench register", [&] {
            bench::RegisterBenchConfig c;
            c.volume = o->volume;
            c.mask = o->phantom_mask;
            c.case_dir = o->case_dir;
            c.cases = o->cases;
            c.seed = o->seed;
            c.threads = o->threads;
            c.keep = o->keep;
            c.renderer = o->register_renderer;
            c.reference_renderer = o->reference_renderer;
            if (!o->params_file.empty())
                c.params = registration_params_from_json(read_json_file(o->params_file), o->params_file);
            if (!o->reference_file.empty()) {
                c.reference = registration_params_from_json(read_json_file(o->reference_file), o->reference_file);
                c.reference_name = std::filesystem::path(o->reference_file).stem().string();
            } else if (o->reference_seed) {
                c.reference = RegistrationParams::seed_schedule();
                c.reference_name = "seed_schedule";
            }
            ProgressBar bar("bench register");
            print(bench::run_register_bench(c, &bar.progress()), o->json);
            return 0;
        });
    });
}

}  // namespace cf::cli
