#pragma once
// The job queue for long work (phantom generation, registration, later planning and exports):
// progress (fraction, stage, message, and kind-specific figures such as the current NMI),
// cancel, and one worker at a time per kind (each kind has its own FIFO and its own thread).
//
// Thread contract:
//  - add_kind() before start(); start() starts one worker thread per kind; stop() cancels
//    what runs, drops what is queued (state "cancelled") and joins, waiting at most a timeout.
//  - submit(), cancel(), get(), list(), status() may be called from any thread.
//  - The listener (set before start()) runs on the worker threads and on the callers of
//    submit()/cancel(), outside the queue's mutex; it must be quick (the daemon posts the
//    event to the push thread).
//  - A kind's run() runs on that kind's worker thread; it reports through JobContext and
//    should call ctx.check() (or pass ctx.progress() to the engine) often enough to cancel.
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <map>
#include <memory>
#include <mutex>
#include <nlohmann/json.hpp>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "cortexfuse/core/progress.hpp"

namespace cf::daemon {

struct JobInfo {
    enum class State { queued, running, succeeded, failed, cancelled };
    std::uint64_t id = 0;
    std::string kind;
    State state = State::queued;
    std::string stage, message;
    double fraction = 0;
    nlohmann::json figures = nlohmann::json::object();  ///< kind-specific live values (e.g. nmi, evaluation)
    nlohmann::json params, result;
    std::string error;
    std::string created_utc, started_utc, finished_utc;
    bool cancel_requested = false;
};
const char* state_name(JobInfo::State s);
nlohmann::json to_json(const JobInfo& j);

class JobContext {
public:
    /// Progress: stage name, overall fraction in [0,1], a short message. Throttled to the
    /// queue's progress rate (always delivered when the stage changes).
    void report(const std::string& stage, double fraction, const std::string& message = {});
    /// Merges live figures ({"nmi": 1.12, "evaluation": 40}); sent with the next report.
    void figures(const nlohmann::json& f);
    /// Throws cf::Cancelled when cancel was requested.
    void check() const { token_.throw_if_cancelled(); }
    bool cancelled() const { return token_.cancelled(); }
    const CancelToken& token() const { return token_; }
    /// A core Progress wired to report() and the cancel token (for the engine).
    Progress progress();
    std::uint64_t id() const { return id_; }

private:
    friend class JobQueue;
    JobContext(class JobQueue& q, std::uint64_t id) : queue_(q), id_(id) {}
    JobQueue& queue_;
    std::uint64_t id_;
    CancelToken token_;
};

struct JobKind {
    std::string name;
    /// Checks the parameters before the job is queued; throws ApiError(400, ...) naming the
    /// parameter. Returns them normalised (defaults filled in).
    std::function<nlohmann::json(const nlohmann::json& params)> validate;
    /// Runs the job; the returned JSON is its result. Throw cf::Cancelled when cancelled,
    /// anything else to fail it (the message is the job's error).
    std::function<nlohmann::json(const nlohmann::json& params, JobContext& ctx)> run;
};

class JobQueue {
public:
    struct Options {
        double progress_hz = 10;
        int kept = 200;  ///< finished jobs kept
        /// Threads a job's parallel work may use: each kind's worker runs its job inside its
        /// own tbb::task_arena of this concurrency, so TBB loops in the engine (the CPU ray
        /// caster, the phantom generator) never take every core from the tracker's driver
        /// thread and the HTTP threads. 0: hardware cores - 1, at least 1.
        int threads = 0;
        /// Nice value of the worker threads (and the threads they start, e.g. llvmpipe's for a
        /// job's GL context), 0..19: the tracker's and HTTP's threads win the CPU first.
        int nice = 0;
    };
    /// The arena concurrency `threads` resolves to (0: hardware cores - 1, at least 1).
    static int resolve_threads(int threads);
    explicit JobQueue(Options o);
    ~JobQueue();
    JobQueue(const JobQueue&) = delete;
    JobQueue& operator=(const JobQueue&) = delete;

    void add_kind(JobKind k);
    void set_listener(std::function<void(const JobInfo&)> cb);
    void start();
    /// Cancels all, waits up to `timeout` for running jobs to end; returns false when one
    /// did not (its thread is then left detached: the process is about to exit).
    bool stop(std::chrono::milliseconds timeout);
    /// The first half of stop(): refuse new jobs, cancel queued and running ones; returns at once.
    void request_stop();

    /// Throws ApiError 400 for an unknown kind or bad params, 503 after stop().
    std::uint64_t submit(const std::string& kind, const nlohmann::json& params);
    /// false when no such job; a finished job stays as it is.
    bool cancel(std::uint64_t id);
    std::optional<JobInfo> get(std::uint64_t id) const;
    std::vector<JobInfo> list() const;
    /// Per kind: queued, running id, done counts; and the workers' heartbeat age.
    nlohmann::json status() const;
    /// All workers alive (for the watchdog): each worker loop has been seen within `max_age`
    /// or is busy in a job.
    bool healthy() const;
    std::vector<std::string> kinds() const;

private:
    friend class JobContext;
    struct Worker;
    void worker_loop(Worker& w);
    void update(std::uint64_t id, const std::function<void(JobInfo&)>& f, bool force_emit);
    void emit(const JobInfo& j);
    void trim_finished();

    Options opt_;
    std::map<std::string, JobKind> kinds_;
    std::map<std::string, std::unique_ptr<Worker>> workers_;
    std::function<void(const JobInfo&)> listener_;

    mutable std::mutex mu_;
    std::condition_variable cv_;
    bool stopping_ = false;
    bool started_ = false;
    std::uint64_t next_id_ = 1;
    std::map<std::uint64_t, JobInfo> jobs_;
    std::map<std::uint64_t, JobContext*> running_;
    std::map<std::uint64_t, std::int64_t> last_emit_ns_;
};

/// UTC now as ISO 8601 with milliseconds ("2026-11-22T15:04:05.123Z").
std::string utc_now_iso();

}  // namespace cf::daemon
