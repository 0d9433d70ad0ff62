#include "case_volumes.hpp"

#include <fstream>
#include <thread>

#include "case_api.hpp"
#include "cortexfuse/core/error.hpp"
#include "cortexfuse/daemon/endpoints.hpp"

namespace cf::daemon {

namespace fs = std::filesystem;
using namespace cf::db;

namespace {
db::CaseRecord get_case(CaseStore& st, std::int64_t case_id) {
    try {
        return st.get_case(case_id);
    } catch (const StoreError& e) {
        rethrow_store_error(e);
    }
}
/// The brain mask of a case: its newest mask volume, else its newest plan_brain_mask.
void attach_mask(const CaseRecord& rec, CaseVolumeRef& ref) {
    std::optional<VolumeRecord> mv;
    for (const auto& v : rec.volumes)
        if (v.modality == Modality::mask && (!mv || v.id > mv->id)) mv = v;
    if (mv) {
        ref.mask_sha = mv->blob.sha256;
        ref.mask_name = "mask_" + mv->original_name;
        ref.mask_source = "mask volume " + std::to_string(mv->id);
        return;
    }
    std::optional<ResultRecord> pm;
    for (const auto& r : rec.results)
        if (r.kind == "plan_brain_mask" && (!pm || r.id > pm->id)) pm = r;
    if (pm) {
        ref.mask_sha = pm->blob.sha256;
        ref.mask_name = "brain_mask.nii.gz";
        ref.mask_source = "plan result " + std::to_string(pm->id) + " (plan_brain_mask)";
    }
}
}  // namespace

CaseVolumeRef resolve_case_volume(CaseStore& st, std::int64_t case_id, std::optional<std::int64_t> volume_id, const std::string& what) {
    const CaseRecord rec = get_case(st, case_id);
    std::optional<VolumeRecord> pick;
    for (const auto& v : rec.volumes) {
        if (volume_id ? v.id == *volume_id : (v.modality == Modality::T1 && (!pick || v.id > pick->id))) pick = v;
    }
    if (!pick) {
        if (volume_id)
            throw ApiError(404, "not_found", what + " volume_id: case " + std::to_string(case_id) + " has no volume " + std::to_string(*volume_id));
        throw ApiError(409, "conflict", what + " case_id: case " + std::to_string(case_id) + " has no T1 volume (upload one first)");
    }
    if (pick->modality == Modality::mask)
        throw ApiError(400, "bad_request", what + " volume_id: volume " + std::to_string(pick->id) + " is a mask, not an image to render");
    CaseVolumeRef ref;
    ref.case_id = case_id;
    ref.volume_id = pick->id;
    ref.modality = to_string(pick->modality);
    ref.source = "volume " + std::to_string(pick->id) + " (" + ref.modality + ")";
    ref.volume_sha = pick->blob.sha256;
    ref.volume_name = pick->original_name;
    attach_mask(rec, ref);
    return ref;
}

CaseVolumeRef resolve_plan_volume(CaseStore& st, std::int64_t case_id, const std::string& modality, const std::string& what) {
    const std::string kind = modality == "ct" ? "plan_ct_on_t1" : modality == "fmri" ? "plan_fmri_on_t1" : "";
    if (kind.empty()) throw ApiError(400, "bad_request", what + ": unknown modality '" + modality.substr(0, 40) + "' (t1, ct or fmri)");
    const CaseRecord rec = get_case(st, case_id);
    std::optional<ResultRecord> pick;
    for (const auto& r : rec.results)
        if (r.kind == kind && (!pick || r.id > pick->id)) pick = r;
    if (!pick)
        throw ApiError(409, "conflict", what + ": case " + std::to_string(case_id) + " has no plan with " + (modality == "ct" ? "a CT" : "an fMRI map") +
                                            " (upload one and run a plan job first)");
    CaseVolumeRef ref;
    ref.case_id = case_id;
    ref.volume_id = pick->id;
    ref.modality = modality == "ct" ? "CT" : "fMRI";
    ref.source = "plan result " + std::to_string(pick->id) + " (" + kind + ")";
    ref.volume_sha = pick->blob.sha256;
    ref.volume_name = kind + ".nii.gz";
    attach_mask(rec, ref);
    return ref;
}

CaseVolumeCache::CaseVolumeCache(CaseStore& store, fs::path scratch_dir, std::size_t capacity)
    : store_(store), scratch_(std::move(scratch_dir)), capacity_(std::max<std::size_t>(1, capacity)) {}

std::shared_ptr<const LoadedCaseVolume> CaseVolumeCache::get(const CaseVolumeRef& ref) {
    std::lock_guard lk(mu_);
    for (auto it = lru_.begin(); it != lru_.end(); ++it)
        if ((*it)->ref.key() == ref.key()) {
            auto hit = *it;
            lru_.erase(it);
            lru_.push_front(hit);
            return hit;
        }
    // The readers take files: stage the stored bytes (hash-checked by the store) in a folder of
    // this load's own, removed after.
    const fs::path dir = scratch_ / ("volume_" + std::to_string(++staged_));
    struct Rm {
        fs::path d;
        ~Rm() {
            std::error_code ec;
            fs::remove_all(d, ec);
        }
    } rm{dir};
    std::error_code ec;
    fs::create_directories(dir, ec);
    auto out = std::make_shared<LoadedCaseVolume>();
    out->ref = ref;
    try {
        // ITK's readers go deeper than civetweb's connection threads' small stacks allow (under
        // ASan by far): the load runs on a thread of its own with the default stack.
        std::exception_ptr err;
        std::thread t([&] {
            try {
                const fs::path vf = dir / ref.volume_name;
                store_.copy_blob_to(ref.volume_sha, vf);
                out->volume = load_volume(vf);
                if (!ref.mask_sha.empty()) {
                    const fs::path mf = dir / ref.mask_name;
                    store_.copy_blob_to(ref.mask_sha, mf);
                    out->brain_mask = load_mask(mf, out->volume.geom);
                }
            } catch (...) {
                err = std::current_exception();
            }
        });
        t.join();
        if (err) std::rethrow_exception(err);
    } catch (const StoreError& e) {
        rethrow_store_error(e);
    } catch (const InputError& e) {
        std::string m = e.what();
        for (std::size_t k; (k = m.find(dir.string() + "/")) != std::string::npos;) m.erase(k, dir.string().size() + 1);
        throw ApiError(422, "unprocessable", "case " + std::to_string(ref.case_id) + " " + ref.source + ": " + m);
    }
    ++loads_;
    lru_.push_front(out);
    while (lru_.size() > capacity_) lru_.pop_back();
    return out;
}

std::uint64_t CaseVolumeCache::loads() const {
    std::lock_guard lk(mu_);
    return loads_;
}
std::size_t CaseVolumeCache::size() const {
    std::lock_guard lk(mu_);
    return lru_.size();
}

}  // namespace cf::daemon
