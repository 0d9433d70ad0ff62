#include "case_jobs.hpp"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <fstream>
#include <functional>
#include <set>

#include "case_api.hpp"
#include "cortexfuse/core/case.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/core/plan.hpp"
#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/daemon/log.hpp"

namespace cf::daemon {

namespace fs = std::filesystem;
using nlohmann::json;
using namespace cf::db;

namespace {

using Clock = std::chrono::steady_clock;

ApiError bad(const std::string& what, const std::string& problem) { return ApiError(400, "bad_request", what + ": " + problem); }

void reject_unknown_params(const json& p, const std::vector<std::string>& known, const std::string& kind) {
    if (!p.is_object()) throw bad(kind, "params must be a JSON object");
    for (auto it = p.begin(); it != p.end(); ++it)
        if (std::find(known.begin(), known.end(), it.key()) == known.end()) throw bad(kind + " " + it.key(), "unknown parameter");
}

std::int64_t id_param(const json& p, const char* key, const std::string& kind) {
    if (!p.contains(key)) throw bad(kind + " " + key, "missing");
    if (!p[key].is_number_integer() || p[key].get<std::int64_t>() < 1) throw bad(kind + " " + key, "must be a positive integer");
    return p[key].get<std::int64_t>();
}

CaseRecord case_or_throw(CaseStore& store, std::int64_t id) {
    try {
        return store.get_case(id);
    } catch (const StoreError& e) {
        rethrow_store_error(e);
    }
}

/// The case's volume `key` (when given: it must be of this case and of `m`) or its newest of `m`.
std::optional<VolumeRecord> pick_volume(const CaseRecord& rec, const json& p, const char* key, Modality m, const std::string& kind) {
    if (p.contains(key) && !p[key].is_null()) {
        const std::int64_t id = id_param(p, key, kind);
        for (const auto& v : rec.volumes)
            if (v.id == id) {
                if (v.modality != m)
                    throw bad(kind + " " + key, "volume " + std::to_string(id) + " is " + to_string(v.modality) + ", not " + to_string(m));
                return v;
            }
        throw ApiError(404, "not_found", kind + " " + key + ": case " + std::to_string(rec.summary.id) + " has no volume " + std::to_string(id));
    }
    std::optional<VolumeRecord> newest;
    for (const auto& v : rec.volumes)
        if (v.modality == m && (!newest || v.id > newest->id)) newest = v;
    return newest;
}

/// A scratch folder removed with its content when it goes out of scope.
struct ScratchDir {
    fs::path dir;
    explicit ScratchDir(fs::path d) : dir(std::move(d)) {
        std::error_code ec;
        fs::remove_all(dir, ec);
        fs::create_directories(dir, ec);
        if (ec) throw std::runtime_error("work folder " + dir.string() + ": " + ec.message());
    }
    ~ScratchDir() {
        std::error_code ec;
        fs::remove_all(dir, ec);
    }
};

/// The stored file's kind and media type for each file make_plan writes.
struct PlanFile {
    const char* name;
    const char* kind;
    const char* media_type;
};
constexpr PlanFile kPlanFiles[] = {
    {"brain_mask.nii.gz", "plan_brain_mask", "application/gzip"},
    {"brain_surface.ply", "plan_brain_surface", "application/octet-stream"},
    {"ct_to_t1.tfm", "plan_ct_transform", "text/plain"},
    {"ct_on_t1.nii.gz", "plan_ct_on_t1", "application/gzip"},
    {"fmri_to_t1.tfm", "plan_fmri_transform", "text/plain"},
    {"fmri_on_t1.nii.gz", "plan_fmri_on_t1", "application/gzip"},
    {"fmri_transfer_function.json", "plan_fmri_transfer_function", "application/json"},
    {"plan.json", "plan_json", "application/json"},  // last: a revision with its plan.json is complete
};

}  // namespace

namespace {
std::function<void(std::size_t)>& plan_store_hook_slot() {
    static std::function<void(std::size_t)> hook;
    return hook;
}
}  // namespace
void set_plan_store_hook_for_tests(std::function<void(std::size_t)> hook) { plan_store_hook_slot() = std::move(hook); }
std::function<void(std::size_t)> plan_store_hook() { return plan_store_hook_slot(); }

RegistrationParams register_params_from_request(const json& o) {
    if (o.is_null()) return RegistrationParams::defaults();
    if (!o.is_object()) throw bad("register params", "must be a JSON object of registration parameters (docs/registration.md)");
    const json known = to_json(RegistrationParams::defaults());
    for (auto it = o.begin(); it != o.end(); ++it)
        if (!known.contains(it.key())) throw bad("register params." + it.key(), "unknown registration parameter");
    try {
        return registration_params_from_json(o, "register params");
    } catch (const InputError& e) {
        const std::string m = e.what();
        throw ApiError(400, "bad_request", m.rfind("register params", 0) == 0 ? m : "register params: " + m);
    }
}

void register_case_job_kinds(JobQueue& jobs, CaseStore& store, const fs::path& work_dir) {
    CaseStore* st = &store;

    // ---- plan
    JobKind plan;
    plan.name = "plan";
    plan.validate = [st](const json& p) {
        reject_unknown_params(p, {"case_id", "t1_volume_id", "ct_volume_id", "fmri_volume_id", "brain_mask", "max_triangles", "ct", "fmri"},
                              "plan");
        const std::int64_t case_id = id_param(p, "case_id", "plan");
        const CaseRecord rec = case_or_throw(*st, case_id);
        json out{{"case_id", case_id}};
        const auto t1 = pick_volume(rec, p, "t1_volume_id", Modality::T1, "plan");
        if (!t1) throw ApiError(409, "conflict", "plan case_id " + std::to_string(case_id) + ": the case has no T1 volume (upload one first)");
        out["t1_volume_id"] = t1->id;
        for (const char* flag : {"ct", "fmri"})
            if (p.contains(flag) && !p[flag].is_boolean()) throw bad(std::string("plan ") + flag, "must be true or false");
        // CT / fMRI: the named volume, else the case's newest of that modality unless ct/fmri is false.
        if (p.value("ct", true)) {
            if (auto ct = pick_volume(rec, p, "ct_volume_id", Modality::CT, "plan")) out["ct_volume_id"] = ct->id;
        } else if (p.contains("ct_volume_id")) {
            throw bad("plan ct_volume_id", "given with ct false");
        }
        if (p.value("fmri", true)) {
            if (auto f = pick_volume(rec, p, "fmri_volume_id", Modality::fMRI, "plan")) out["fmri_volume_id"] = f->id;
        } else if (p.contains("fmri_volume_id")) {
            throw bad("plan fmri_volume_id", "given with fmri false");
        }
        const auto mask = pick_volume(rec, json::object(), "", Modality::mask, "plan");
        std::string bm = mask ? "case_mask" : "skull_strip";
        if (p.contains("brain_mask")) {
            if (!p["brain_mask"].is_string() || (p["brain_mask"] != "case_mask" && p["brain_mask"] != "skull_strip"))
                throw bad("plan brain_mask", "must be \"skull_strip\" (the engine's) or \"case_mask\" (the case's mask volume)");
            bm = p["brain_mask"].get<std::string>();
            if (bm == "case_mask" && !mask) throw ApiError(409, "conflict", "plan brain_mask: case " + std::to_string(case_id) + " has no mask volume");
        }
        out["brain_mask"] = bm;
        if (bm == "case_mask") out["mask_volume_id"] = mask->id;
        std::int64_t tri = 200000;
        if (p.contains("max_triangles")) {
            if (!p["max_triangles"].is_number_integer()) throw bad("plan max_triangles", "must be an integer");
            tri = p["max_triangles"].get<std::int64_t>();
            if (tri < 1000 || tri > 5000000) throw bad("plan max_triangles", std::to_string(tri) + " is out of range 1000..5000000");
        }
        out["max_triangles"] = tri;
        return out;
    };
    plan.run = [st, work_dir](const json& p, JobContext& ctx) {
        const auto t0 = Clock::now();
        const std::int64_t case_id = p["case_id"].get<std::int64_t>();
        ScratchDir scratch(work_dir / ("plan_" + std::to_string(ctx.id())));
        ctx.report("reading volumes", 0);
        CaseRecord rec;
        try {
            rec = st->get_case(case_id);
        } catch (const StoreError& e) {
            throw std::runtime_error("plan case " + std::to_string(case_id) + ": " + e.what());
        }
        auto stage = [&](const char* key, const std::string& prefix) -> std::optional<fs::path> {
            if (!p.contains(key)) return std::nullopt;
            const std::int64_t id = p[key].get<std::int64_t>();
            for (const auto& v : rec.volumes)
                if (v.id == id) {
                    const fs::path f = scratch.dir / "in" / (prefix + v.original_name);
                    fs::create_directories(f.parent_path());
                    st->copy_blob_to(v.blob.sha256, f);  // verified against its hash
                    return f;
                }
            throw std::runtime_error("plan " + std::string(key) + ": volume " + std::to_string(id) + " is no longer in case " + std::to_string(case_id));
        };
        PlanInputs in;
        in.t1 = *stage("t1_volume_id", "t1_");
        in.ct = stage("ct_volume_id", "ct_");
        in.fmri = stage("fmri_volume_id", "fmri_");
        in.brain_mask = stage("mask_volume_id", "mask_");
        ctx.check();
        PlanParams pp;
        pp.surface.max_triangles = int(p["max_triangles"].get<std::int64_t>());
        const fs::path out_dir = scratch.dir / "plan";
        json plan_json;
        try {
            plan_json = make_plan(in, pp, out_dir, ctx.progress());
        } catch (const InputError& e) {
            // Errors name the staged file: say which of the case's volumes instead.
            std::string m = e.what();
            const std::string prefix = (scratch.dir / "in").string() + "/";
            for (std::size_t k; (k = m.find(prefix)) != std::string::npos;) m.erase(k, prefix.size());
            throw std::runtime_error("plan case " + std::to_string(case_id) + ": " + m);
        }
        // plan.json names its inputs by file: the staged copies' names, not the work folder's path.
        const std::string staged = (scratch.dir / "in").string() + "/";
        std::function<void(json&)> strip = [&](json& j) {
            if (j.is_string()) {
                std::string v = j.get<std::string>();
                for (std::size_t k; (k = v.find(staged)) != std::string::npos;) v.erase(k, staged.size());
                j = v;
            } else if (j.is_structured()) {
                for (auto& x : j) strip(x);
            }
        };
        strip(plan_json);
        ctx.check();  // the last point a cancel takes effect: from here on the results are stored
        ctx.report("storing", 0.97);
        int revision = 1;
        for (const auto& r : st->get_case(case_id).results)
            if (r.kind == "plan_json") revision = std::max(revision, r.params.value("plan_revision", 0) + 1);
        const double seconds = std::chrono::duration<double>(Clock::now() - t0).count();
        json inputs = json::object();
        for (const char* k : {"t1_volume_id", "ct_volume_id", "fmri_volume_id", "mask_volume_id"})
            if (p.contains(k)) inputs[k] = p[k];
        json stored = json::array();
        std::vector<ResultInput> files;
        for (const auto& f : kPlanFiles) {
            const fs::path file = out_dir / f.name;
            if (!fs::exists(file)) continue;
            ResultInput ri;
            ri.kind = f.kind;
            ri.name = "plan" + std::to_string(revision) + "_" + f.name;
            ri.media_type = f.media_type;
            if (std::string(f.kind) == "plan_json") ri.bytes = plan_json.dump(2) + "\n";  // without the work folder's paths
            else ri.file = file;
            ri.params = {{"plan_revision", revision},
                         {"job_id", ctx.id()},
                         {"inputs", inputs},
                         {"params", {{"brain_mask", p["brain_mask"]}, {"max_triangles", p["max_triangles"]}}},
                         {"seconds", seconds}};
            if (std::string(f.kind) == "plan_json") ri.params["plan"] = plan_json;
            files.push_back(std::move(ri));
        }
        // Every file of the revision and the case's state (planned, when it was earlier) in one
        // store transaction: a crash or an error leaves either the whole revision or none of it.
        std::vector<ResultRecord> rows;
        try {
            rows = st->add_results(case_id, files, CaseState::planned, Actor{"jobs", std::nullopt}, plan_store_hook());
        } catch (const StoreError& e) {
            throw std::runtime_error("plan case " + std::to_string(case_id) + ": storing the plan failed, nothing stored: " + e.what());
        }
        for (const auto& r : rows)
            stored.push_back({{"id", r.id}, {"kind", r.kind}, {"name", r.name}, {"sha256", r.blob.sha256}, {"size_bytes", r.blob.size_bytes}});
        log(LogLevel::info, "jobs", "plan of case " + std::to_string(case_id) + " stored as revision " + std::to_string(revision));
        return json{{"case_id", case_id}, {"plan_revision", revision}, {"results", stored}, {"seconds", seconds}, {"plan", plan_json}};
    };
    jobs.add_kind(plan);

    // ---- export
    JobKind exp;
    exp.name = "export";
    exp.validate = [st](const json& p) {
        reject_unknown_params(p, {"case_id"}, "export");
        const std::int64_t case_id = id_param(p, "case_id", "export");
        case_or_throw(*st, case_id);
        return json{{"case_id", case_id}};
    };
    exp.run = [st, work_dir](const json& p, JobContext& ctx) {
        const std::int64_t case_id = p["case_id"].get<std::int64_t>();
        const fs::path dir = work_dir / "exports";
        std::error_code ec;
        fs::create_directories(dir, ec);
        const fs::path zip = dir / ("case_" + std::to_string(case_id) + "_job" + std::to_string(ctx.id()) + ".zip");
        ctx.report("exporting", 0.05);
        ctx.check();
        try {
            st->export_case_zip(case_id, zip, Actor{"jobs", std::nullopt});  // written beside and renamed by the store
        } catch (const StoreError& e) {
            throw std::runtime_error("export case " + std::to_string(case_id) + ": " + e.what());
        }
        if (ctx.cancelled()) {
            fs::remove(zip, ec);
            ctx.check();
        }
        ctx.report("exported", 1.0);
        return json{{"case_id", case_id},
                    {"file", zip.filename().string()},
                    {"size_bytes", std::int64_t(fs::file_size(zip))},
                    {"download", "/api/jobs/" + std::to_string(ctx.id()) + "/download"}};
    };
    jobs.add_kind(exp);
}

}  // namespace cf::daemon
