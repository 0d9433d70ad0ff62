#pragma once
// Progress reporting and cancellation for long operations.
// Thread contract: report() may be called from the worker thread only; cancel() from any.
#include <atomic>
#include <functional>
#include <string>

#include "cortexfuse/core/error.hpp"

namespace cf {

class CancelToken {
public:
    void cancel() { flag_.store(true, std::memory_order_relaxed); }
    bool cancelled() const { return flag_.load(std::memory_order_relaxed); }
    void throw_if_cancelled() const {
        if (cancelled()) throw Cancelled();
    }

private:
    std::atomic<bool> flag_{false};
};

/// A progress sink: stage name and overall fraction in [0,1]. Borrowed by the operation.
struct Progress {
    std::function<void(const std::string& stage, double fraction)> report;
    const CancelToken* cancel = nullptr;  // borrowed, may be null
    /// Optional, for live plots: called once per similarity evaluation of a registration
    /// (1-based evaluation count, its similarity, the best similarity so far), on the same
    /// thread as report(); must be quick.
    std::function<void(int evaluation, double similarity, double best_similarity)> evaluation;

    void operator()(const std::string& stage, double fraction) const {
        if (report) report(stage, fraction);
    }
    void check() const {
        if (cancel) cancel->throw_if_cancelled();
    }
};

}  // namespace cf
