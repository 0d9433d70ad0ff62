#pragma once
// A case's volumes read from the case store for the daemon's views of that case: which stored
// volume and which brain mask a request means (resolve_case_volume, resolve_plan_volume), and a
// small LRU of the loaded volumes (CaseVolumeCache) shared by the per-case renders, the
// navigation slices and the intensity histograms.
//
// Memory: a loaded 256^3 T1 is 64 MiB (float) plus 16 MiB for its mask; `capacity` bounds how
// many stay loaded (the least recently used is dropped first; a caller still holding one keeps
// it alive until it lets go).
//
// Thread contract: resolve_* from any thread (the store is thread-safe); CaseVolumeCache::get
// from any thread (one mutex; a load happens under it, so two threads never load the same
// volume twice).
#include <cstdint>
#include <filesystem>
#include <list>
#include <memory>
#include <mutex>
#include <optional>
#include <string>

#include "cortexfuse/core/volume.hpp"
#include "cortexfuse/db/case_store.hpp"

namespace cf::daemon {

/// One stored volume of a case and the brain mask that goes with it (by content hash).
struct CaseVolumeRef {
    std::int64_t case_id = 0;
    std::int64_t volume_id = 0;  ///< volumes.id, or the plan result's id for a plan volume
    std::string source;          ///< "volume 3 (T1)", "plan result 12 (plan_ct_on_t1)": for messages and answers
    std::string modality;        ///< "T1", "CT", "fMRI", "mask"
    std::string volume_sha, volume_name;
    std::string mask_sha, mask_name;  ///< empty without a brain mask
    std::string mask_source;          ///< "mask volume 7", "plan result 12 (plan_brain_mask)", or ""
    std::string key() const { return volume_sha + "/" + mask_sha; }
};

/// The case's volume `volume_id` (any modality but mask), else its newest T1, with its brain
/// mask: the newest `mask` volume, else the newest plan's `plan_brain_mask` (the render thread
/// resamples a mask on another grid onto the volume's). ApiError naming `what`: 404 no such case
/// or no such volume in it, 400 a mask volume asked for, 409 no T1.
CaseVolumeRef resolve_case_volume(db::CaseStore& store, std::int64_t case_id, std::optional<std::int64_t> volume_id,
                                  const std::string& what);

/// The newest plan's volume of a modality ("ct": plan_ct_on_t1, "fmri": plan_fmri_on_t1, both
/// on the T1's grid), with the plan's brain mask. ApiError 409 naming `what` and the modality
/// when the case has no plan with it ("run a plan job with a CT first").
CaseVolumeRef resolve_plan_volume(db::CaseStore& store, std::int64_t case_id, const std::string& modality, const std::string& what);

struct LoadedCaseVolume {
    CaseVolumeRef ref;
    Volume volume;
    std::optional<LabelVolume> brain_mask;  ///< on volume's grid
};

class CaseVolumeCache {
public:
    /// `scratch_dir`: where stored files are staged for the readers (removed after each load).
    CaseVolumeCache(db::CaseStore& store, std::filesystem::path scratch_dir, std::size_t capacity);
    /// The loaded volume (and mask) of `ref`, loaded when not cached (hashes verified by the
    /// store). ApiError 422 naming the file when it does not read as a volume.
    std::shared_ptr<const LoadedCaseVolume> get(const CaseVolumeRef& ref);
    std::uint64_t loads() const;  ///< volumes read from the store so far (tests: the cache works)
    std::size_t size() const;

private:
    db::CaseStore& store_;
    std::filesystem::path scratch_;
    std::size_t capacity_;
    mutable std::mutex mu_;
    std::list<std::shared_ptr<const LoadedCaseVolume>> lru_;  // most recent first
    std::uint64_t loads_ = 0, staged_ = 0;
};

}  // namespace cf::daemon
