#pragma once
// Drafts of Photo & marks (issue 7, 7.47 "nothing entered is lost"; docs/api/case-data.md
// "Drafts of unsaved marks"): the UI's unsaved landmark and ROI edits kept by the daemon per
// case and per owner (the kiosk, or a logged-in user), so that a restart of the browser itself
// (the kiosk unit starts chromium with a fresh profile) loses nothing. Stored in the case store's
// `drafts` table: not a revision, not exported, audited once when kept and once when dropped.
//
// Thread contract: the handlers run on any connection thread; the store serialises its calls.
#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/db/case_store.hpp"

namespace cf::daemon {

/// GET, PUT and DELETE /api/cases/{id}/drafts/marks (write access: a reviewer has none).
void register_draft_endpoints(EndpointRegistry& reg, cf::db::CaseStore& store);

}  // namespace cf::daemon
