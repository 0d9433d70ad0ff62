#pragma once
// Patient navigation over HTTP (docs/api/navigation.md): the pointer tip live, fiducials
// digitised with the pointer (averaged over the last frames, refused when a tool is missing or
// stale or the tip moved), the image-space fiducials, the paired-point registration by core's
// navigation (Umeyama, FRE, residuals, outlier exclusion, predicted TRE), its acceptance into
// the case store, tri-planar slices of the MRI at a point, and the simulator's pointer placed
// on a point (ground truth for tests and the demo).
//
// Storage: everything a case keeps is a result file of the case store (immutable rows, each
// write one transaction with its audit entry "result.add"): kind "nav_image_fiducials" and
// "nav_patient_fiducials" (each change a new revision: the full list as JSON), and
// "patient_registration" (an accepted registration with its parameters, also audited as
// "navigation.accept"). The newest of each kind is the current one.
//
// Thread contract: handlers run on any connection thread; the tracker module, the case store
// and the slice volume (loaded once, then read-only) are thread-safe.
#include <filesystem>

#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/db/case_store.hpp"

namespace cf::daemon {

class TrackerModule;

struct NavigationOptions {
    std::filesystem::path t1_path;  ///< the MRI the slices are cut from (data.t1)
    /// Where the pointer's tip is in the pointer tool's frame (mm). NDI's pointer .rom files
    /// put the tool's origin at the calibrated tip, as the simulator's pointer does: zero.
    /// POST /api/navigation/pivot {apply: true} replaces it and stores it in `tip_file`, which
    /// is read at start (so an applied calibration survives a restart).
    double tip_pointer_mm[3] = {0, 0, 0};
    /// The stored pivot calibration; empty: pointer_tip.json in the case store's folder.
    std::filesystem::path tip_file;
    /// Where a case's stored volumes are staged for the reader (slices with ?case_id=).
    std::filesystem::path work_dir = std::filesystem::temp_directory_path();
};

void register_navigation_endpoints(EndpointRegistry& reg, cf::db::CaseStore& store, TrackerModule& tracker,
                                   const NavigationOptions& options);

}  // namespace cf::daemon
