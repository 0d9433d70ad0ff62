#include "cortexfuse/daemon/jobs.hpp"

#include <sys/resource.h>
#include <sys/syscall.h>
#include <tbb/task_arena.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <ctime>
#include <exception>
#include <thread>

#include "cortexfuse/core/error.hpp"
#include "cortexfuse/daemon/endpoints.hpp"
#include "cortexfuse/daemon/log.hpp"
#include "cortexfuse/drivers/tracker/session.hpp"

namespace cf::daemon {

using cf::tracker::steady_ns;

struct JobQueue::Worker {
    std::string kind;
    std::deque<std::uint64_t> queue;
    std::thread thread;
    std::unique_ptr<tbb::task_arena> arena;  // made on the worker thread; its jobs run inside it
    std::uint64_t running = 0;
    std::uint64_t done = 0;
    bool finished = false;  // the loop has returned
};

std::string utc_now_iso() {
    const auto now = std::chrono::system_clock::now();
    const auto ms = std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch()).count();
    const std::time_t t = ms / 1000;
    std::tm tm{};
    gmtime_r(&t, &tm);
    char buf[40];
    std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%S", &tm);
    char out[48];
    std::snprintf(out, sizeof out, "%s.%03dZ", buf, int(ms % 1000));
    return out;
}

const char* state_name(JobInfo::State s) {
    switch (s) {
        case JobInfo::State::queued: return "queued";
        case JobInfo::State::running: return "running";
        case JobInfo::State::succeeded: return "succeeded";
        case JobInfo::State::failed: return "failed";
        case JobInfo::State::cancelled: return "cancelled";
    }
    return "?";
}

nlohmann::json to_json(const JobInfo& j) {
    nlohmann::json o{{"id", j.id},
                     {"kind", j.kind},
                     {"state", state_name(j.state)},
                     {"stage", j.stage},
                     {"fraction", j.fraction},
                     {"message", j.message},
                     {"figures", j.figures},
                     {"params", j.params},
                     {"created_utc", j.created_utc},
                     {"cancel_requested", j.cancel_requested}};
    if (!j.started_utc.empty()) o["started_utc"] = j.started_utc;
    if (!j.finished_utc.empty()) o["finished_utc"] = j.finished_utc;
    if (j.state == JobInfo::State::succeeded) o["result"] = j.result;
    if (!j.error.empty()) o["error"] = j.error;
    return o;
}

void JobContext::report(const std::string& stage, double fraction, const std::string& message) {
    queue_.update(
        id_,
        [&](JobInfo& j) {
            j.stage = stage;
            j.fraction = std::clamp(fraction, 0.0, 1.0);
            if (!message.empty()) j.message = message;
        },
        false);
}

void JobContext::figures(const nlohmann::json& f) {
    std::lock_guard lk(queue_.mu_);
    auto it = queue_.jobs_.find(id_);
    if (it != queue_.jobs_.end()) it->second.figures.update(f);
}

Progress JobContext::progress() {
    Progress p;
    p.report = [this](const std::string& stage, double fraction) { report(stage, fraction); };
    p.cancel = &token_;
    return p;
}

JobQueue::JobQueue(Options o) : opt_(o) {}

JobQueue::~JobQueue() { stop(std::chrono::milliseconds(0)); }

void JobQueue::add_kind(JobKind k) {
    auto w = std::make_unique<Worker>();
    w->kind = k.name;
    workers_[k.name] = std::move(w);
    kinds_[k.name] = std::move(k);
}

void JobQueue::set_listener(std::function<void(const JobInfo&)> cb) { listener_ = std::move(cb); }

void JobQueue::start() {
    std::lock_guard lk(mu_);
    started_ = true;
    for (auto& [name, w] : workers_) {
        Worker* wp = w.get();
        w->thread = std::thread([this, wp] { worker_loop(*wp); });
    }
}

void JobQueue::request_stop() {
    std::vector<JobInfo> dropped;
    {
        std::unique_lock lk(mu_);
        if (stopping_) return;
        stopping_ = true;
        for (auto& [id, ctx] : running_) {
            ctx->token_.cancel();
            jobs_[id].cancel_requested = true;
        }
        for (auto& [name, w] : workers_) {
            for (auto id : w->queue) {
                auto& j = jobs_[id];
                j.state = JobInfo::State::cancelled;
                j.message = "the daemon stopped before the job started";
                j.finished_utc = utc_now_iso();
                dropped.push_back(j);
            }
            w->queue.clear();
        }
    }
    cv_.notify_all();
    for (const auto& j : dropped) emit(j);
}

bool JobQueue::stop(std::chrono::milliseconds timeout) {
    {
        std::lock_guard lk(mu_);
        if (stopping_ && !started_) return true;
    }
    request_stop();
    std::unique_lock lk(mu_);
    const bool all_done = cv_.wait_for(lk, timeout, [&] {
        for (auto& [n, w] : workers_)
            if (w->thread.joinable() && !w->finished) return false;
        return true;
    });
    lk.unlock();
    for (auto& [n, w] : workers_) {
        if (!w->thread.joinable()) continue;
        if (all_done) w->thread.join();
        else {
            bool fin;
            {
                std::lock_guard l2(mu_);
                fin = w->finished;
            }
            if (fin) w->thread.join();
            else w->thread.detach();  // stuck in a job that ignores cancel: abandoned, the process exits
        }
    }
    std::lock_guard l3(mu_);
    started_ = false;
    return all_done;
}

std::uint64_t JobQueue::submit(const std::string& kind, const nlohmann::json& params) {
    auto k = kinds_.find(kind);
    if (k == kinds_.end()) {
        std::string names;
        for (const auto& [n, _] : kinds_) names += (names.empty() ? "" : ", ") + n;
        throw ApiError(400, "bad_request", "kind '" + kind + "' is not a job kind (" + names + ")");
    }
    const nlohmann::json p = k->second.validate ? k->second.validate(params.is_null() ? nlohmann::json::object() : params)
                                                : params;
    JobInfo copy;
    {
        std::lock_guard lk(mu_);
        if (stopping_) throw ApiError(503, "unavailable", "the daemon is stopping; no new jobs");
        JobInfo j;
        j.id = next_id_++;
        j.kind = kind;
        j.params = p;
        j.created_utc = utc_now_iso();
        j.stage = "queued";
        jobs_[j.id] = j;
        workers_[kind]->queue.push_back(j.id);
        copy = j;
        trim_finished();
    }
    cv_.notify_all();
    emit(copy);
    return copy.id;
}

bool JobQueue::cancel(std::uint64_t id) {
    JobInfo copy;
    bool emit_now = false;
    {
        std::lock_guard lk(mu_);
        auto it = jobs_.find(id);
        if (it == jobs_.end()) return false;
        JobInfo& j = it->second;
        if (j.state == JobInfo::State::queued) {
            for (auto& [n, w] : workers_) std::erase(w->queue, id);
            j.state = JobInfo::State::cancelled;
            j.cancel_requested = true;
            j.message = "cancelled before it started";
            j.finished_utc = utc_now_iso();
            copy = j;
            emit_now = true;
        } else if (j.state == JobInfo::State::running) {
            j.cancel_requested = true;
            if (auto r = running_.find(id); r != running_.end()) r->second->token_.cancel();
            copy = j;
            emit_now = true;
        }
    }
    if (emit_now) emit(copy);
    return true;
}

std::optional<JobInfo> JobQueue::get(std::uint64_t id) const {
    std::lock_guard lk(mu_);
    auto it = jobs_.find(id);
    if (it == jobs_.end()) return std::nullopt;
    return it->second;
}

std::vector<JobInfo> JobQueue::list() const {
    std::lock_guard lk(mu_);
    std::vector<JobInfo> v;
    for (const auto& [id, j] : jobs_) v.push_back(j);
    return v;
}

nlohmann::json JobQueue::status() const {
    std::lock_guard lk(mu_);
    nlohmann::json k = nlohmann::json::object();
    for (const auto& [n, w] : workers_)
        k[n] = {{"queued", w->queue.size()}, {"running", w->running ? nlohmann::json(w->running) : nlohmann::json(nullptr)}, {"done", w->done}};
    return {{"kinds", k}, {"jobs", jobs_.size()}, {"stopping", stopping_}};
}

bool JobQueue::healthy() const {
    std::lock_guard lk(mu_);
    if (!started_) return false;
    for (const auto& [n, w] : workers_)
        if (w->finished) return false;
    return true;
}

std::vector<std::string> JobQueue::kinds() const {
    std::vector<std::string> v;
    for (const auto& [n, _] : kinds_) v.push_back(n);
    return v;
}

void JobQueue::update(std::uint64_t id, const std::function<void(JobInfo&)>& f, bool force_emit) {
    JobInfo copy;
    bool send = force_emit;
    {
        std::lock_guard lk(mu_);
        auto it = jobs_.find(id);
        if (it == jobs_.end()) return;
        const std::string old_stage = it->second.stage;
        f(it->second);
        const std::int64_t now = steady_ns();
        auto& last = last_emit_ns_[id];
        if (it->second.stage != old_stage || now - last >= std::int64_t(1e9 / opt_.progress_hz)) send = true;
        if (send) {
            last = now;
            copy = it->second;
        }
    }
    if (send) emit(copy);
}

void JobQueue::emit(const JobInfo& j) {
    if (listener_) listener_(j);
}

void JobQueue::trim_finished() {
    // Called with mu_ held: drop the oldest finished jobs beyond opt_.kept.
    std::size_t finished = 0;
    for (const auto& [id, j] : jobs_)
        if (j.state != JobInfo::State::queued && j.state != JobInfo::State::running) ++finished;
    for (auto it = jobs_.begin(); it != jobs_.end() && finished > std::size_t(opt_.kept);) {
        if (it->second.state != JobInfo::State::queued && it->second.state != JobInfo::State::running) {
            last_emit_ns_.erase(it->first);
            it = jobs_.erase(it);
            --finished;
        } else {
            ++it;
        }
    }
}

int JobQueue::resolve_threads(int threads) {
    if (threads > 0) return threads;
    const int hw = int(std::thread::hardware_concurrency());
    return std::max(1, hw - 1);
}

void JobQueue::worker_loop(Worker& w) {
    const JobKind& kind = kinds_.at(w.kind);
    // Lower this thread's priority (Linux: nice is per thread; threads it starts inherit it).
    // Raising it back needs CAP_SYS_NICE, so this is one-way, and only for the job threads.
    const id_t tid = id_t(::syscall(SYS_gettid));
    errno = 0;
    const int current = ::getpriority(PRIO_PROCESS, tid);
    if (opt_.nice > 0 && errno == 0 && current < opt_.nice && ::setpriority(PRIO_PROCESS, tid, opt_.nice) != 0)
        log(LogLevel::warning, "jobs", "worker '" + w.kind + "': cannot set nice " + std::to_string(opt_.nice));
    // One slot, taken by this thread; the other threads - 1 come from TBB's pool.
    w.arena = std::make_unique<tbb::task_arena>(resolve_threads(opt_.threads), 1);
    for (;;) {
        std::uint64_t id = 0;
        nlohmann::json params;
        JobInfo started;
        {
            std::unique_lock lk(mu_);
            cv_.wait(lk, [&] { return stopping_ || !w.queue.empty(); });
            if (stopping_) break;
            id = w.queue.front();
            w.queue.pop_front();
            w.running = id;
            auto& j = jobs_[id];
            j.state = JobInfo::State::running;
            j.started_utc = utc_now_iso();
            j.stage = "starting";
            params = j.params;
            started = j;
        }
        emit(started);
        JobContext ctx(*this, id);
        {
            std::lock_guard lk(mu_);
            running_[id] = &ctx;
            if (jobs_[id].cancel_requested) ctx.token_.cancel();
        }
        JobInfo::State end = JobInfo::State::succeeded;
        nlohmann::json result;
        std::string error;
        try {
            // Parallel loops inside the job (tbb::parallel_for without an arena of its own)
            // run in this arena, at most `threads` at once.
            std::exception_ptr thrown;
            w.arena->execute([&] {
                try {
                    result = kind.run(params, ctx);
                } catch (...) {
                    thrown = std::current_exception();
                }
            });
            if (thrown) std::rethrow_exception(thrown);
            if (ctx.cancelled()) end = JobInfo::State::cancelled;
        } catch (const cf::Cancelled&) {
            end = JobInfo::State::cancelled;
        } catch (const std::exception& e) {
            end = ctx.cancelled() ? JobInfo::State::cancelled : JobInfo::State::failed;
            error = e.what();
        }
        JobInfo done;
        {
            std::lock_guard lk(mu_);
            running_.erase(id);
            w.running = 0;
            ++w.done;
            auto& j = jobs_[id];
            j.state = end;
            j.finished_utc = utc_now_iso();
            if (end == JobInfo::State::succeeded) {
                j.result = result;
                j.fraction = 1;
                j.stage = "done";
            } else if (end == JobInfo::State::cancelled) {
                j.stage = "cancelled";
                if (j.message.empty() || j.message.rfind("cancel", 0) != 0) j.message = "cancelled";
            } else {
                j.error = error;
                j.stage = "failed";
            }
            done = j;
            trim_finished();
        }
        emit(done);
    }
    {
        std::lock_guard lk(mu_);
        w.finished = true;
    }
    cv_.notify_all();
}

}  // namespace cf::daemon
