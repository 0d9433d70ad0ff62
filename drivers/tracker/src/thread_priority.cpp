#include "cortexfuse/drivers/tracker/thread_priority.hpp"

#include <pthread.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "cortexfuse/drivers/tracker/transport.hpp"

namespace cf::tracker {

namespace {
int sys_set_fifo(int priority) {
    sched_param p{};
    p.sched_priority = priority;
    return ::pthread_setschedparam(::pthread_self(), SCHED_FIFO, &p);  // returns the error number
}
id_t self_tid() { return static_cast<id_t>(::syscall(SYS_gettid)); }
int sys_set_nice(int nice) { return ::setpriority(PRIO_PROCESS, self_tid(), nice) == 0 ? 0 : errno; }
int sys_get_nice(int* nice) {
    errno = 0;
    const int v = ::getpriority(PRIO_PROCESS, self_tid());
    if (v == -1 && errno != 0) return errno;
    *nice = v;
    return 0;
}
}  // namespace

void ThreadPriorityRequest::validate() const {
    if (realtime_priority < 0 || realtime_priority > 99)
        throw ConfigError("realtime_priority " + std::to_string(realtime_priority), "out of range 0..99 (0: no SCHED_FIFO)");
    if (nice < -20 || nice > 19) throw ConfigError("nice " + std::to_string(nice), "out of range -20..19");
}

std::string ThreadPriorityResult::describe() const {
    if (kind == Kind::realtime) return "SCHED_FIFO " + std::to_string(realtime_priority);
    return "nice " + std::to_string(nice);
}

PrioritySyscalls real_priority_syscalls() { return PrioritySyscalls{&sys_set_fifo, &sys_set_nice, &sys_get_nice}; }

ThreadPriorityResult raise_thread_priority(const ThreadPriorityRequest& request, const PrioritySyscalls& sys) {
    request.validate();
    ThreadPriorityResult r;
    std::string refused;
    if (request.realtime_priority > 0) {
        const int e = sys.set_fifo(request.realtime_priority);
        if (e == 0) {
            r.kind = ThreadPriorityResult::Kind::realtime;
            r.realtime_priority = request.realtime_priority;
            return r;
        }
        refused = "SCHED_FIFO " + std::to_string(request.realtime_priority) + " refused (" + std::strerror(e) +
                  (e == EPERM ? ": needs CAP_SYS_NICE or RLIMIT_RTPRIO, and no RestrictRealtime=" : "") + ")";
    }
    int before = 0;
    const int ge = sys.get_nice(&before);
    if (ge == 0 && before == request.nice) {
        r.kind = ThreadPriorityResult::Kind::nice;
        r.nice = before;
        r.note = refused.empty() ? "" : refused + "; nice " + std::to_string(before);
        return r;
    }
    const int e = sys.set_nice(request.nice);
    if (e == 0) {
        r.kind = ThreadPriorityResult::Kind::nice;
        r.nice = request.nice;
        r.note = refused.empty() ? "" : refused + "; nice " + std::to_string(request.nice) + " instead";
        return r;
    }
    r.kind = ThreadPriorityResult::Kind::unchanged;
    r.nice = ge == 0 ? before : 0;
    r.note = (refused.empty() ? "" : refused + "; ") + "nice " + std::to_string(request.nice) + " refused (" + std::strerror(e) +
             (e == EPERM || e == EACCES ? ": below the current value needs CAP_SYS_NICE or RLIMIT_NICE" : "") +
             "); the thread keeps nice " + std::to_string(r.nice);
    return r;
}

bool is_unbound_kworker(const std::string& comm) {
    const std::string prefix = "kworker/u";
    if (comm.compare(0, prefix.size(), prefix) != 0) return false;
    std::size_t i = prefix.size();
    const std::size_t digits = i;
    while (i < comm.size() && std::isdigit(static_cast<unsigned char>(comm[i]))) ++i;
    if (i == digits || i >= comm.size() || comm[i] != ':') return false;
    ++i;
    return i < comm.size() && std::isdigit(static_cast<unsigned char>(comm[i]));
}

namespace {
int sys_set_fifo_tid(int tid, int priority) {
    sched_param p{};
    p.sched_priority = priority;
    return ::sched_setscheduler(tid, priority > 0 ? SCHED_FIFO : SCHED_OTHER, &p) == 0 ? 0 : errno;
}
std::string first_line(const std::filesystem::path& p) {
    std::ifstream in(p);
    std::string s;
    std::getline(in, s);
    return s;
}
}  // namespace

TtyWorkerPriority::TtyWorkerPriority(int realtime_priority, std::string proc_root, int (*set_fifo)(int, int))
    : priority_(realtime_priority), proc_(std::move(proc_root)), set_(set_fifo ? set_fifo : &sys_set_fifo_tid) {
    if (realtime_priority < 0 || realtime_priority > 99)
        throw ConfigError("tty worker priority " + std::to_string(realtime_priority), "out of range 0..99 (0: off)");
}

TtyWorkerPriority::~TtyWorkerPriority() { restore(); }

int TtyWorkerPriority::apply() {
    if (priority_ == 0 || refused_) return 0;
    // kthreadd (pid 2) starts every kernel thread; its children file lists them.
    std::vector<int> tids;
    {
        std::istringstream in(first_line(std::filesystem::path(proc_) / "2" / "task" / "2" / "children"));
        for (int t; in >> t;) tids.push_back(t);
    }
    int changed = 0;
    for (int tid : tids) {
        if (std::find(raised_.begin(), raised_.end(), tid) != raised_.end()) continue;
        if (!is_unbound_kworker(first_line(std::filesystem::path(proc_) / std::to_string(tid) / "comm"))) continue;
        const int e = set_(tid, priority_);
        if (e == ESRCH) continue;  // the pool let it go meanwhile
        if (e != 0) {
            refused_ = true;
            note_ = std::string("cannot raise the tty workers (kworker/u*) to SCHED_FIFO ") + std::to_string(priority_) + ": " +
                    std::strerror(e) + (e == EPERM ? " (needs CAP_SYS_NICE)" : "");
            return changed;
        }
        raised_.push_back(tid);
        ++changed;
    }
    // Forget workers that have exited (their ids may be reused by other threads).
    std::erase_if(raised_, [&](int tid) { return !std::filesystem::exists(std::filesystem::path(proc_) / std::to_string(tid)); });
    return changed;
}

void TtyWorkerPriority::restore() {
    for (int tid : raised_)
        if (is_unbound_kworker(first_line(std::filesystem::path(proc_) / std::to_string(tid) / "comm"))) set_(tid, 0);
    raised_.clear();
}

}  // namespace cf::tracker
