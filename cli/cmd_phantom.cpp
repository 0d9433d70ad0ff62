// cortexfuse phantom: synthetic case folders with ground truth from a real MRI.
#include <unistd.h>

#include <chrono>
#include <cstdio>
#include <iostream>
#include <memory>

#include "cortexfuse/core/install_paths.hpp"
#include "commands.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/phantom.hpp"

namespace cf::cli {

namespace {
bool parse_size(const std::string& s, int& w, int& h) {
    const auto x = s.find_first_of("xX");
    if (x == std::string::npos) return false;
    try {
        size_t a = 0, b = 0;
        w = std::stoi(s.substr(0, x), &a);
        h = std::stoi(s.substr(x + 1), &b);
        return a == x && b == s.size() - x - 1;
    } catch (const std::exception&) {
        return false;
    }
}
}  // namespace

void add_phantom(CLI::App& app) {
    struct Opts {
        std::string out, volume = cf::bundled_data_dir(CF_DATA_DIR).string() + "/t1_head_mne_ecog.nii.gz",
                         mask = cf::bundled_data_dir(CF_DATA_DIR).string() + "/brainmask_mne_ecog_binary.nii.gz", size = "750x500",
                         dslr_size = "3000x2000";
        int n = 10;
        bool fixed_size = false, quiet = false;
        PhantomParams params;
    };
    auto o = std::make_shared<Opts>();
    auto& p = o->params;
    auto* cmd = app.add_subcommand("phantom", "Synthetic case folders (photo, landmarks, ROI, truth) from a real MRI");
    cmd->add_option("OUTDIR", o->out, "output folder: t1.nii.gz, brain_mask.nii.gz, case_0000/ ...")->required();
    cmd->add_option("--n", o->n, "number of cases")->capture_default_str();
    cmd->add_option("--seed", p.seed, "random seed (same seed, same files)")->capture_default_str();
    cmd->add_option("--volume", o->volume, "T1 volume (NIfTI, NRRD, MHA or DICOM folder)")->capture_default_str();
    cmd->add_option("--mask", o->mask, "brain mask on the volume's grid")->capture_default_str();
    cmd->add_option("--size", o->size, "base photo size WxH (varied +-20% per case unless --fixed-size)")->capture_default_str();
    cmd->add_flag("--fixed-size", o->fixed_size, "use exactly --size for non-DSLR cases");
    cmd->add_option("--dslr-fraction", p.dslr_fraction, "fraction of cases as DSLR-size JPEGs")->capture_default_str();
    cmd->add_option("--dslr-size", o->dslr_size, "DSLR photo size WxH")->capture_default_str();
    cmd->add_option("--gauze-prob", p.gauze_prob, "probability of gauze patties over the cortex")->capture_default_str();
    cmd->add_option("--blood-prob", p.blood_prob, "probability of blood pools over the cortex (and of the two below unless given)")->capture_default_str();
    cmd->add_option("--sulcal-blood-prob", p.sulcal_blood_prob, "probability of subarachnoid blood in the sulci over a patch");
    cmd->add_option("--blood-film-prob", p.blood_film_prob, "probability of a thin film of blood over part of the cortex");
    cmd->add_option("--lamp-spot-prob", p.lamp_spot_prob, "probability that the OR lamp's spot lights the field (else evenly, as a flash)")->capture_default_str();
    cmd->add_option("--far-lamp-prob", p.far_lamp_prob,
                    "probability that the light is the OR's light head 0.8-1.2 m overhead (else a light near the camera)")
        ->capture_default_str();
    cmd->add_option("--skin-prep-prob", p.skin_prep_prob, "probability of iodine skin prep staining the scalp")->capture_default_str();
    cmd->add_flag("!--no-photo-finish", p.photo_finish,
                  "leave out the photographic finish (drape folds in relief, glints in blood, halation, lateral colour, stubble, the rim of the opening by hand)");
    cmd->add_flag("!--no-tissue-optics", p.tissue_optics,
                  "leave out, from the finish, the light scattered under the cortex and the lamp's soft image in blood");
    cmd->add_option("--distortion-prob", p.distortion_prob, "probability of lens distortion")->capture_default_str();
    cmd->add_option("--png-fraction", p.png_fraction, "fraction of non-DSLR photos written as PNG")->capture_default_str();
    cmd->add_option("--max-tilt-deg", p.max_tilt_deg, "largest off-normal tilt of the camera")->capture_default_str();
    cmd->add_flag("--quiet", o->quiet, "no progress on stderr");

    cmd->callback([o] {
        run_guarded("phantom", [o]() -> int {
            auto& prm = o->params;
            if (o->n < 1) throw InputError("phantom --n", "must be at least 1, got " + std::to_string(o->n));
            if (!parse_size(o->size, prm.width, prm.height))
                throw InputError("phantom --size", "expected WxH (e.g. 750x500), got \"" + o->size + "\"");
            if (!parse_size(o->dslr_size, prm.dslr_width, prm.dslr_height))
                throw InputError("phantom --dslr-size", "expected WxH (e.g. 3000x2000), got \"" + o->dslr_size + "\"");
            prm.vary_size = !o->fixed_size;
            prm.validate();
            const bool tty = !o->quiet && ::isatty(STDERR_FILENO);
            Progress progress;
            if (tty)
                progress.report = [](const std::string& stage, double f) {
                    const int w = 30, k = int(f * w + 0.5);
                    std::fprintf(stderr, "\r[%-*s] %3d%% %-24s", w, std::string(size_t(std::clamp(k, 0, w)), '#').c_str(),
                                 int(f * 100 + 0.5), stage.c_str());
                    std::fflush(stderr);
                };
            const auto t0 = std::chrono::steady_clock::now();
            const auto dirs = generate_phantoms(o->out, o->n, o->volume, o->mask, prm, progress);
            if (tty) std::fprintf(stderr, "\n");
            const double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
            if (!o->quiet)
                std::cerr << "cortexfuse phantom: wrote " << dirs.size() << " cases to " << o->out << " in " << s << " s\n";
            return 0;
        });
    });
}

}  // namespace cf::cli
