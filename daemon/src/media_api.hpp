#pragma once
// Preoperative data from a USB stick (issue 7, 7.4): the volumes found under the removable-media
// root (config media.removable_root, default /media) listed for the UI, and one imported into a
// case with the checks of an upload (core's readers before anything is stored). NIfTI, NRRD and
// MetaImage files, and folders holding DICOM files (read as one series by core's GDCM reader and
// stored as NIfTI). docs/api/case-data.md "Volumes from removable media".
//
// Thread contract: the handlers run on any connection thread; they read the media folder and the
// store (which serialises its own calls); scratch folders are per request.
#include <cstdint>
#include <filesystem>

#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/db/case_store.hpp"

namespace cf::daemon {

/// GET /api/media/volumes (write: it lists the cart's media), POST /api/cases/{id}/volumes/import-media
/// {path, modality?} (write). `root`: media.removable_root; `max_bytes`: store.max_upload_bytes.
void register_media_endpoints(EndpointRegistry& reg, cf::db::CaseStore& store, const std::filesystem::path& root,
                              const std::filesystem::path& work_dir, std::int64_t max_bytes);

}  // namespace cf::daemon
