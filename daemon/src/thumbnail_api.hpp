#pragma once
// Thumbnails of the case archive (issue 7, 7.2): one small JPEG per case, of its fused view when
// the case has one (a succeeded registration and a plan surface: the registered camera's fused
// view, drawn by the POST /api/cases/{id}/fused endpoint itself), else of its newest photo.
// Made on first request and cached under `work_dir`/thumbnails, keyed by what it was made from
// (registration, photo, surface and ROI, or the photo's hash), so a new registration, photo or
// plan makes a new one. docs/api/cases.md "Thumbnails".
//
// Thread contract: the handler runs on any connection thread; a mutex serialises the making and
// the cache files (written beside and renamed: a failed or interrupted write leaves none).
#include <filesystem>

#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/db/case_store.hpp"

namespace cf::daemon {

/// Thumbnail width in px (the height follows the photo's aspect ratio).
inline constexpr int kThumbnailWidthPx = 192;

/// GET /api/cases/{id}/thumbnail (read): image/jpeg, headers X-Thumbnail-Source (fused|photo),
/// X-Thumbnail-Cache (hit|miss), X-Thumbnail-Note (why a registered case shows its photo).
/// 404 for an unknown case or a case with neither a photo nor a fused view. `reg` is looked up
/// at request time for the fused endpoint (registered by the render module).
void register_thumbnail_endpoints(EndpointRegistry& reg, cf::db::CaseStore& store, const std::filesystem::path& work_dir);

}  // namespace cf::daemon
