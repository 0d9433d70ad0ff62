// The preoperative plan: skull strip, surface, co-registered CT and fMRI on the T1 grid.
#include "cortexfuse/core/plan.hpp"

#include <chrono>
#include <cmath>
#include <cstdio>

#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/transfer_function.hpp"
#include "itk_coregister.hpp"

namespace fs = std::filesystem;

namespace cf {
namespace {

using Clock = std::chrono::steady_clock;
double since(Clock::time_point t) { return std::chrono::duration<double>(Clock::now() - t).count(); }

nlohmann::json matrix_json(const Eigen::Matrix4d& T) {
    nlohmann::json m = nlohmann::json::array();
    for (int r = 0; r < 4; ++r) m.push_back({T(r, 0), T(r, 1), T(r, 2), T(r, 3)});
    return m;
}

nlohmann::json coreg_json(const CoregParams& p, const CoregResult& r) {
    nlohmann::json levels = nlohmann::json::array();
    for (const auto& l : r.levels)
        levels.push_back({{"iterations", l.iterations}, {"metric", l.metric}, {"seconds", l.seconds}, {"stop", l.stop}});
    return {{"metric", p.metric == CoregParams::Metric::Mattes ? "mattes" : "nmi"},
            {"bins", p.bins},
            {"shrink", p.shrink},
            {"smooth_mm", p.smooth_mm},
            {"iterations", p.iterations},
            {"sampling", p.sampling},
            {"T_moving_from_fixed", matrix_json(r.T_moving_from_fixed)},
            {"convention", "maps T1 world points (LPS mm) to the modality's world points (ITK)"},
            {"nmi_after", r.nmi},
            {"overlap", r.overlap},
            {"seconds", r.seconds},
            {"levels", levels}};
}

/// Progress of one step mapped into [a, b] of the whole plan.
Progress sub_progress(const Progress& p, double a, double b) {
    Progress s;
    s.cancel = p.cancel;
    if (p.report) s.report = [p, a, b](const std::string& stage, double f) { p.report(stage, a + (b - a) * f); };
    return s;
}

}  // namespace

std::string volume_fingerprint(const Volume& v) {
    uint64_t h = 1469598103934665603ull;
    auto mix = [&h](const void* data, size_t n) {
        const auto* b = static_cast<const unsigned char*>(data);
        for (size_t i = 0; i < n; ++i) h = (h ^ b[i]) * 1099511628211ull;
    };
    mix(v.geom.dims.data(), sizeof(int) * 3);
    for (int a = 0; a < 3; ++a) {
        const double s = v.geom.spacing_mm[a], o = v.geom.origin_mm[a];
        mix(&s, sizeof s), mix(&o, sizeof o);
        for (int b = 0; b < 3; ++b) {
            const double d = v.geom.direction(a, b);
            mix(&d, sizeof d);
        }
    }
    mix(v.voxels.data(), v.voxels.size() * sizeof(float));
    char buf[17];
    std::snprintf(buf, sizeof buf, "%016llx", static_cast<unsigned long long>(h));
    return buf;
}

void FmriParams::validate() const {
    if (!(threshold > 0 && threshold <= 100)) throw InputError("fmri threshold", "must be in (0, 100]");
    if (min_cluster_voxels < 1 || min_cluster_voxels > 1000000) throw InputError("fmri min_cluster_voxels", "must be in [1, 1e6]");
}

Volume threshold_activation(const Volume& stat, const FmriParams& p, int* clusters) {
    p.validate();
    if (stat.voxels.empty() || stat.voxels.size() != stat.geom.voxel_count()) throw InputError("fmri map", "empty volume");
    std::vector<uint8_t> m(stat.voxels.size());
    for (size_t i = 0; i < m.size(); ++i) {
        const float v = stat.voxels[i];
        m[i] = std::isfinite(v) && (v >= p.threshold || (p.two_sided && v <= -p.threshold)) ? 1 : 0;
    }
    itkb::Grid g;
    g.dims = stat.geom.dims;
    for (int a = 0; a < 3; ++a) {
        g.spacing[size_t(a)] = stat.geom.spacing_mm[a];
        g.origin[size_t(a)] = stat.geom.origin_mm[a];
        for (int b = 0; b < 3; ++b) g.direction[size_t(a * 3 + b)] = stat.geom.direction(a, b);
    }
    const int n = itkb::keep_clusters(g, m, p.min_cluster_voxels);
    if (clusters) *clusters = n;
    Volume out;
    out.geom = stat.geom;
    out.voxels.resize(stat.voxels.size());
    for (size_t i = 0; i < m.size(); ++i) out.voxels[i] = m[i] ? stat.voxels[i] : 0.f;
    return out;
}

nlohmann::json make_plan(const PlanInputs& in, const PlanParams& P, const fs::path& out_dir, const Progress& progress) {
    P.surface.validate();
    P.coreg_ct.validate();
    P.coreg_fmri.validate();
    P.fmri.validate();
    const auto t_all = Clock::now();
    nlohmann::json plan = {{"format", "cortexfuse-plan/1"}, {"t1", in.t1.string()}};
    nlohmann::json steps = nlohmann::json::array();

    // Load everything first: a bad input fails before any long work.
    auto t = Clock::now();
    const Volume t1 = load_volume(in.t1);
    plan["t1_fingerprint"] = volume_fingerprint(t1);
    std::optional<Volume> ct, fmri, fmri_ref;
    if (in.ct) ct = load_volume(*in.ct);
    if (in.fmri) fmri = load_volume(*in.fmri);
    if (in.fmri_reference) {
        if (!in.fmri) throw InputError(in.fmri_reference->string(), "an fMRI reference needs an fMRI map (--fmri)");
        fmri_ref = load_volume(*in.fmri_reference);
    }
    std::optional<LabelVolume> ref;
    if (in.reference_mask) {
        ref = load_mask(*in.reference_mask);
        if (!ref->geom.same_grid(t1.geom)) throw InputError(in.reference_mask->string(), "reference mask is not on the T1's grid");
    }
    std::optional<LabelVolume> given_mask;
    if (in.brain_mask) {
        given_mask = load_mask(*in.brain_mask);
        if (!given_mask->geom.same_grid(t1.geom)) throw InputError(in.brain_mask->string(), "brain mask is not on the T1's grid");
        if (given_mask->count_nonzero() == 0) throw InputError(in.brain_mask->string(), "brain mask is empty");
    }
    if (fmri_ref && !fmri_ref->geom.same_grid(fmri->geom) &&
        (fmri_ref->geom.center_world_mm() - fmri->geom.center_world_mm()).norm() > 50)
        throw InputError(in.fmri_reference->string(), "the fMRI reference and map do not share a space (centres > 50 mm apart)");
    steps.push_back({{"step", "load"}, {"seconds", since(t)}});
    progress.check();
    fs::create_directories(out_dir);

    // Brain mask.
    t = Clock::now();
    LabelVolume mask;
    nlohmann::json mstep = {{"step", "brain_mask"}};
    if (given_mask) {
        mask = std::move(*given_mask);
        mstep["source"] = in.brain_mask->string();
    } else {
        SkullStripInfo info;
        const Progress sp = sub_progress(progress, 0.0, 0.25);
        mask = skull_strip(t1, P.skull, &sp, &info);
        mstep["source"] = "skull_strip";
        mstep["brain_ml"] = info.brain_ml;
        mstep["thresholds"] = {{"background", info.t_background}, {"low", info.t_low}, {"high", info.t_high}, {"csf", info.t_csf}};
    }
    if (ref) mstep["dice"] = dice(mask, *ref), mstep["reference_mask"] = in.reference_mask->string();
    save_mask(mask, out_dir / "brain_mask.nii.gz");
    mstep["file"] = "brain_mask.nii.gz";
    mstep["seconds"] = since(t);
    steps.push_back(mstep);

    // Surface.
    t = Clock::now();
    SurfaceInfo si;
    const SurfaceMesh mesh = build_brain_surface(t1, mask, P.surface, sub_progress(progress, 0.25, 0.45), &si);
    save_mesh(mesh, out_dir / "brain_surface.ply");
    steps.push_back({{"step", "brain_surface"},
                     {"file", "brain_surface.ply"},
                     {"frame", "world LPS mm"},
                     {"source", P.surface.source == SurfaceParams::Source::T1Level ? "t1_level" : "mask"},
                     {"iso_level", si.iso_level},
                     {"smooth_iterations", P.surface.smooth_iterations},
                     {"smooth_passband", P.surface.smooth_passband},
                     {"max_triangles", P.surface.max_triangles},
                     {"triangles_extracted", si.triangles_extracted},
                     {"triangles", si.triangles},
                     {"vertices", si.vertices},
                     {"seconds", since(t)}});

    // CT.
    if (ct) {
        t = Clock::now();
        const CoregResult r = coregister(t1, *ct, P.coreg_ct, sub_progress(progress, 0.45, 0.7));
        save_transform(r.T_moving_from_fixed, r.center_world_mm, out_dir / "ct_to_t1.tfm");
        save_volume(resample_rigid(*ct, r.T_moving_from_fixed, t1.geom, false, -1000.f), out_dir / "ct_on_t1.nii.gz");
        nlohmann::json j = coreg_json(P.coreg_ct, r);
        j["step"] = "ct";
        j["input"] = in.ct->string();
        j["transform"] = "ct_to_t1.tfm";
        j["resampled"] = "ct_on_t1.nii.gz";
        j["transfer_function"] = "ct_bone";
        j["seconds_total"] = since(t);
        steps.push_back(j);
    }

    // fMRI.
    if (fmri) {
        t = Clock::now();
        nlohmann::json j = {{"step", "fmri"}, {"input", in.fmri->string()}};
        Eigen::Matrix4d T = Eigen::Matrix4d::Identity();
        Eigen::Vector3d c = t1.geom.center_world_mm();
        if (fmri_ref) {
            const CoregResult r = coregister(t1, *fmri_ref, P.coreg_fmri, sub_progress(progress, 0.7, 0.95));
            T = r.T_moving_from_fixed;
            c = r.center_world_mm;
            j["registration"] = coreg_json(P.coreg_fmri, r);
            j["reference"] = in.fmri_reference->string();
        } else {
            j["registration"] = "none: the map is taken as already in the T1's world (give --fmri-ref to register)";
        }
        int clusters = 0;
        const Volume thr = threshold_activation(*fmri, P.fmri, &clusters);
        // Nearest neighbour keeps the cluster edges sharp and values unblended with zeros.
        const Volume on_t1 = resample_rigid(thr, T, t1.geom, true, 0.f);
        size_t active = 0;
        double vmax = P.fmri.threshold;
        for (float v : on_t1.voxels)
            if (v != 0) ++active, vmax = std::max(vmax, double(std::abs(v)));
        if (active == 0)
            throw InputError(in.fmri->string(), "no activation above the threshold survives inside the T1's field of view");
        save_transform(T, c, out_dir / "fmri_to_t1.tfm");
        save_volume(on_t1, out_dir / "fmri_on_t1.nii.gz");
        // Its own transfer function: hot colours from the threshold to the peak, in the map's units.
        TransferFunction tf;
        tf.name = "fmri_activation";
        tf.normalized = false;
        tf.colour = {{P.fmri.threshold, 0.7, 0.0, 0.0}, {(P.fmri.threshold + vmax) / 2, 1.0, 0.5, 0.0}, {vmax, 1.0, 1.0, 0.3}};
        tf.opacity = {{0.0, 0.0}, {P.fmri.threshold * 0.999, 0.0}, {P.fmri.threshold, 0.6}, {vmax, 0.9}};
        tf.validate("fmri transfer function");
        write_file_atomic(out_dir / "fmri_transfer_function.json", to_json(tf).dump(1));
        j["threshold"] = P.fmri.threshold;
        j["two_sided"] = P.fmri.two_sided;
        j["min_cluster_voxels"] = P.fmri.min_cluster_voxels;
        j["clusters"] = clusters;
        j["active_voxels_on_t1"] = active;
        j["peak"] = vmax;
        j["transform"] = "fmri_to_t1.tfm";
        j["resampled"] = "fmri_on_t1.nii.gz";
        j["transfer_function"] = "fmri_transfer_function.json";
        j["seconds"] = since(t);
        steps.push_back(j);
    }
    plan["steps"] = steps;
    plan["seconds_total"] = since(t_all);
    write_file_atomic(out_dir / "plan.json", plan.dump(1));
    progress("plan", 1.0);
    return plan;
}

}  // namespace cf
