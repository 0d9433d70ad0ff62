#pragma once
// Jobs and views on a case of the store beyond registration (docs/api/jobs.md, render.md):
//  - the `plan` job: core's preoperative plan (skull stripping or the case's mask, the brain
//    surface, CT/fMRI co-registration) on the case's uploaded volumes; its files are stored as
//    results of the case (content-addressed blobs) tagged with a plan revision, its parameters
//    and timings, all in one store transaction that also moves the case to `planned` (when it
//    was earlier): a revision is there whole or not at all;
//  - the `export` job: the case zip written off the connection thread, downloaded afterwards
//    from GET /api/jobs/{id}/download;
//  - `register` job parameters: the registration schedule overrides (checked by core's
//    RegistrationParams reader; unknown keys refused), see register_params_from_request();
//  - POST /api/render/pick (the world point under a pixel of a rendered view), POST
//    /api/cases/{id}/fused (the case's photo-textured surface over its volume rendering) and
//    GET /api/cases/{id}/fused/camera (the registered camera to snap back to).
//
// Thread contract: job runs on their kind's worker; endpoints on connection threads; the
// store serialises its own calls, the render module queues to its thread.
#include <filesystem>
#include <functional>

#include "cortexfuse/core/registration.hpp"
#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/daemon/jobs.hpp"
#include "cortexfuse/db/case_store.hpp"
#include "render_module.hpp"

namespace cf::daemon {

/// Adds the `plan` and `export` kinds. Scratch folders go under `work_dir` (removed after each
/// job); export zips under `work_dir`/exports (emptied with work/ at start).
void register_case_job_kinds(JobQueue& jobs, cf::db::CaseStore& store, const std::filesystem::path& work_dir);

/// The `params` of a register job request: an object of RegistrationParams keys (as
/// to_json(RegistrationParams) writes them) overriding the defaults. ApiError 400 naming an
/// unknown key or what core's reader refuses. Absent or null: the defaults.
RegistrationParams register_params_from_request(const nlohmann::json& overrides);

/// Test hook: called inside the plan's store transaction after each file's row (a throw rolls
/// the whole revision back). Empty by default; process-wide, set it only while no plan runs.
void set_plan_store_hook_for_tests(std::function<void(std::size_t)> hook);
std::function<void(std::size_t)> plan_store_hook();

/// POST /api/render (per case with case_id, multimodal with modalities), the pick, the case
/// volumes' histograms, the fused view and camera snap endpoints.
void register_render_case_endpoints(EndpointRegistry& reg, RenderModule& render, cf::db::CaseStore& store, JobQueue& jobs,
                                    const std::filesystem::path& work_dir);

}  // namespace cf::daemon
