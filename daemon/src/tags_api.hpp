#pragma once
// Stimulation tags (issue 7, fused view): marks the surgeon places on the registered photo
// (label, colour, note, photo pixel), cast back onto the plan's brain surface with the
// registration's pose (core's cast_back) and stored as a result of the case (kind "tags", one
// JSON file per revision, linked to the registration). docs/api/tags.md.
//
// Thread contract: the handlers run on any connection thread; the store serialises its own
// calls; a mutex orders the revisions of tags and guards the one cached surface mesh.
#include <filesystem>

#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/db/case_store.hpp"

namespace cf::daemon {

/// POST /api/cases/{id}/tags (write), GET /api/cases/{id}/tags (read). `work_dir`: scratch
/// for reading the stored surface (removed after each read).
void register_tags_endpoints(EndpointRegistry& reg, cf::db::CaseStore& store, const std::filesystem::path& work_dir);

}  // namespace cf::daemon
