#pragma once
// The landmarks' initial alignment for the UI's Photo & marks screen (issue 7, 7.19): the
// camera pose the register job starts from when a case has landmark pairs (core's
// pnp_candidates(...).front(), the same call Registration::run makes), with the reprojection
// error of each pair in pixels and their RMS. docs/api/case-data.md "Initial alignment".
//
// Thread contract: the handlers run on any connection thread; they only read the store (which
// serialises its own calls) and compute; nothing is stored.
#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/db/case_store.hpp"

namespace cf::daemon {

/// GET  /api/cases/{id}/landmarks/initial-pose (read): from the newest stored landmark set and
///      the intrinsics of its photo.
/// POST /api/cases/{id}/landmarks/initial-pose (read; stores nothing): from the pairs in the
///      body {landmarks: [...], photo_id?} (an edit not saved yet), checked as a save would be.
void register_landmark_pose_endpoints(EndpointRegistry& reg, cf::db::CaseStore& store);

}  // namespace cf::daemon
