#pragma once
// Scheduling priority of an I/O thread that must answer a device within a deadline (the
// tracker's driver thread; the simulator's thread, which stands for hardware that does not
// share our CPU). A registration and HTTP readers can saturate every core; a thread at the
// normal priority then waits tens of milliseconds for a core, longer than a 60 Hz frame.
//
// raise_thread_priority() asks, for the calling thread, first for SCHED_FIFO at
// `realtime_priority` (when > 0), else (or when refused: no CAP_SYS_NICE / RLIMIT_RTPRIO, or
// systemd's RestrictRealtime=) for the nice value `nice` (Linux: per thread, through
// setpriority on the thread id; below 0 needs CAP_SYS_NICE or RLIMIT_NICE). It never throws
// for a refusal: the result says what the thread got and, in `note`, what was refused and why
// (one line, for the caller to log once).
//
// Thread contract: acts on the calling thread only; no shared state.
#include <string>
#include <vector>

namespace cf::tracker {

struct ThreadPriorityRequest {
    int realtime_priority = 0;  ///< 1..99: SCHED_FIFO at this priority; 0: none (nice only)
    int nice = 0;               ///< -20..19: the nice value when SCHED_FIFO is not asked or refused
    /// Throws ConfigError naming the field and its range.
    void validate() const;
};

struct ThreadPriorityResult {
    enum class Kind { realtime, nice, unchanged };
    Kind kind = Kind::unchanged;
    int realtime_priority = 0;  ///< kind realtime: the SCHED_FIFO priority
    int nice = 0;               ///< the thread's nice value afterwards (kind nice / unchanged)
    std::string note;           ///< empty when the request was granted as asked; else what was refused and why
    /// "SCHED_FIFO 20", "nice -10", "nice 0".
    std::string describe() const;
};

/// The system calls raise_thread_priority uses, replaceable in tests. Each returns 0 or an errno.
struct PrioritySyscalls {
    int (*set_fifo)(int priority) = nullptr;  ///< the calling thread to SCHED_FIFO at `priority`
    int (*set_nice)(int nice) = nullptr;      ///< the calling thread's nice value
    int (*get_nice)(int* nice) = nullptr;     ///< the calling thread's nice value
};
/// pthread_setschedparam / setpriority(PRIO_PROCESS, gettid()) / getpriority.
PrioritySyscalls real_priority_syscalls();

/// See the header comment. Validates the request first (ConfigError).
ThreadPriorityResult raise_thread_priority(const ThreadPriorityRequest& request,
                                           const PrioritySyscalls& sys = real_priority_syscalls());

/// Whether a kernel thread's name is an unbound workqueue worker ("kworker/u8:3",
/// "kworker/u8:3-events_unbound"): the threads that run a tty's flip-buffer work.
bool is_unbound_kworker(const std::string& comm);

/// The kernel's side of a serial line or pty: bytes written to a tty reach its reader only after
/// a kernel worker of the unbound workqueue (kworker/u*, SCHED_OTHER nice 0) has run the tty's
/// flip-buffer work (flush_to_ldisc), on a pty in both directions, on a USB-serial adapter for
/// every reply. With the cores saturated that worker waited up to 0.46 s for a CPU (measured,
/// docs/performance.md), however high the driver's own priority. TtyWorkerPriority puts those
/// workers at SCHED_FIFO `realtime_priority` (below the driver's), as an RT-tuned appliance does;
/// the pool makes new workers at nice 0, so apply() is to be called again now and then (cheap:
/// it reads kthreadd's children and touches only workers not yet changed). restore() (and the
/// destructor) puts the ones it changed back to SCHED_OTHER nice 0. This acts on the whole
/// system's unbound kernel work: an appliance setting, off with realtime_priority 0.
///
/// Needs CAP_SYS_NICE; without it apply() changes nothing and note() says why (once).
/// Thread contract: one thread at a time (the caller serialises apply/restore).
class TtyWorkerPriority {
public:
    /// `proc_root` and `set_fifo` are replaceable in tests (set_fifo(tid, priority) returns 0 or
    /// an errno; priority 0 means back to SCHED_OTHER).
    explicit TtyWorkerPriority(int realtime_priority, std::string proc_root = "/proc", int (*set_fifo)(int tid, int priority) = nullptr);
    ~TtyWorkerPriority();
    TtyWorkerPriority(const TtyWorkerPriority&) = delete;
    TtyWorkerPriority& operator=(const TtyWorkerPriority&) = delete;
    /// Raises the workers not raised yet; returns how many it changed this call.
    int apply();
    void restore();
    std::size_t raised() const { return raised_.size(); }
    const std::string& note() const { return note_; }

private:
    int priority_;
    std::string proc_;
    int (*set_)(int, int);
    std::vector<int> raised_;
    std::string note_;
    bool refused_ = false;
};

}  // namespace cf::tracker
