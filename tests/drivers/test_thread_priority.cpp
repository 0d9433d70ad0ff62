// The tracker I/O threads' priority (SCHED_FIFO, else nice, never failing), the kernel tty
// workers' priority on a fake /proc, and gap counting by the device's frame numbers.
#include <gtest/gtest.h>
#include <sched.h>
#include <sys/resource.h>
#include <sys/syscall.h>
#include <unistd.h>

#include <cerrno>
#include <filesystem>
#include <fstream>
#include <mutex>
#include <thread>

#include "cortexfuse/drivers/sim/tracker_sim.hpp"
#include "cortexfuse/drivers/tracker/session.hpp"
#include "cortexfuse/drivers/tracker/thread_priority.hpp"

namespace fs = std::filesystem;
using namespace cf::tracker;
using namespace std::chrono_literals;

namespace {
// Fake system calls: what they were asked, what they answer.
int g_fifo_errno = 0, g_nice_errno = 0, g_nice_now = 0, g_fifo_calls = 0, g_nice_calls = 0;
int fake_fifo(int) {
    ++g_fifo_calls;
    return g_fifo_errno;
}
int fake_set_nice(int n) {
    ++g_nice_calls;
    if (g_nice_errno) return g_nice_errno;
    g_nice_now = n;
    return 0;
}
int fake_get_nice(int* n) {
    *n = g_nice_now;
    return 0;
}
PrioritySyscalls fakes(int fifo_errno, int nice_errno, int nice_now) {
    g_fifo_errno = fifo_errno;
    g_nice_errno = nice_errno;
    g_nice_now = nice_now;
    g_fifo_calls = g_nice_calls = 0;
    return PrioritySyscalls{&fake_fifo, &fake_set_nice, &fake_get_nice};
}
}  // namespace

TEST(ThreadPriority, RealtimeWhenPermitted) {
    const auto r = raise_thread_priority({20, -10}, fakes(0, 0, 0));
    EXPECT_EQ(r.kind, ThreadPriorityResult::Kind::realtime);
    EXPECT_EQ(r.realtime_priority, 20);
    EXPECT_EQ(r.describe(), "SCHED_FIFO 20");
    EXPECT_TRUE(r.note.empty());
    EXPECT_EQ(g_nice_calls, 0);
}

TEST(ThreadPriority, FallsBackToNiceWhenRealtimeIsRefused) {
    const auto r = raise_thread_priority({20, -10}, fakes(EPERM, 0, 0));
    EXPECT_EQ(r.kind, ThreadPriorityResult::Kind::nice);
    EXPECT_EQ(r.nice, -10);
    EXPECT_EQ(r.describe(), "nice -10");
    EXPECT_NE(r.note.find("SCHED_FIFO 20 refused"), std::string::npos) << r.note;
    EXPECT_NE(r.note.find("CAP_SYS_NICE"), std::string::npos) << r.note;
    EXPECT_EQ(g_nice_now, -10);
}

TEST(ThreadPriority, KeepsItsPriorityWhenBothAreRefusedAndSaysWhy) {
    const auto r = raise_thread_priority({20, -10}, fakes(EPERM, EACCES, 3));
    EXPECT_EQ(r.kind, ThreadPriorityResult::Kind::unchanged);
    EXPECT_EQ(r.nice, 3);
    EXPECT_EQ(r.describe(), "nice 3");
    EXPECT_NE(r.note.find("SCHED_FIFO 20 refused"), std::string::npos) << r.note;
    EXPECT_NE(r.note.find("nice -10 refused"), std::string::npos) << r.note;
    EXPECT_NE(r.note.find("keeps nice 3"), std::string::npos) << r.note;
}

TEST(ThreadPriority, NoRealtimeAskedMeansNiceOnly) {
    const auto r = raise_thread_priority({0, 5}, fakes(0, 0, 0));
    EXPECT_EQ(g_fifo_calls, 0);
    EXPECT_EQ(r.kind, ThreadPriorityResult::Kind::nice);
    EXPECT_EQ(r.nice, 5);
    EXPECT_TRUE(r.note.empty());
    // Already at the asked value: nothing to set.
    const auto again = raise_thread_priority({0, 5}, fakes(0, EPERM, 5));
    EXPECT_EQ(again.kind, ThreadPriorityResult::Kind::nice);
    EXPECT_EQ(g_nice_calls, 0);
}

TEST(ThreadPriority, OutOfRangeRequestsNameTheField) {
    try {
        raise_thread_priority({100, 0}, fakes(0, 0, 0));
        FAIL() << "no error";
    } catch (const ConfigError& e) {
        EXPECT_NE(std::string(e.what()).find("realtime_priority 100"), std::string::npos) << e.what();
    }
    EXPECT_THROW(raise_thread_priority({0, -21}, fakes(0, 0, 0)), ConfigError);
    EXPECT_THROW(raise_thread_priority({-1, 0}, fakes(0, 0, 0)), ConfigError);
}

// The real system calls, on a thread of its own: what the result says is what the kernel has.
TEST(ThreadPriority, RealSyscallsReportWhatTheThreadGot) {
    std::thread([] {
        const auto r = raise_thread_priority({0, 7});  // raising nice is always allowed
        EXPECT_EQ(r.kind, ThreadPriorityResult::Kind::nice);
        EXPECT_EQ(::getpriority(PRIO_PROCESS, static_cast<id_t>(::syscall(SYS_gettid))), 7);
    }).join();
    std::thread([] {
        const auto r = raise_thread_priority({5, 9});
        if (r.kind == ThreadPriorityResult::Kind::realtime) {
            EXPECT_EQ(::sched_getscheduler(0), SCHED_FIFO);
            sched_param p{};
            ::sched_getparam(0, &p);
            EXPECT_EQ(p.sched_priority, 5);
        } else {
            EXPECT_EQ(::sched_getscheduler(0), SCHED_OTHER);
            EXPECT_FALSE(r.note.empty());  // refused: it says why
            EXPECT_EQ(::getpriority(PRIO_PROCESS, static_cast<id_t>(::syscall(SYS_gettid))), r.nice);
        }
    }).join();
}

TEST(TtyWorkers, RecognisesUnboundWorkqueueWorkers) {
    EXPECT_TRUE(is_unbound_kworker("kworker/u8:3"));
    EXPECT_TRUE(is_unbound_kworker("kworker/u8:3-events_unbound"));
    EXPECT_TRUE(is_unbound_kworker("kworker/u128:10-ev"));
    EXPECT_FALSE(is_unbound_kworker("kworker/1:1H-kblockd"));
    EXPECT_FALSE(is_unbound_kworker("kworker/R-rcu_g"));
    EXPECT_FALSE(is_unbound_kworker("kworker/u"));
    EXPECT_FALSE(is_unbound_kworker("kworker/u8:"));
    EXPECT_FALSE(is_unbound_kworker("ksoftirqd/0"));
    EXPECT_FALSE(is_unbound_kworker(""));
}

namespace {
std::mutex g_calls_mu;
std::vector<std::pair<int, int>> g_calls;
int g_set_errno = 0;
int fake_set_tid(int tid, int prio) {
    std::lock_guard lk(g_calls_mu);
    if (g_set_errno) return g_set_errno;
    g_calls.emplace_back(tid, prio);
    return 0;
}
void write_file(const fs::path& p, const std::string& s) {
    fs::create_directories(p.parent_path());
    std::ofstream(p) << s << "\n";
}
}  // namespace

TEST(TtyWorkers, RaisesOnlyUnboundWorkersOnceAndRestoresThem) {
    const fs::path proc = fs::path(::testing::TempDir()) / ("cf_fake_proc_" + std::to_string(::getpid()));
    fs::remove_all(proc);
    write_file(proc / "2/task/2/children", "10 11 12 13");
    write_file(proc / "10/comm", "kworker/u8:1-events_unbound");
    write_file(proc / "11/comm", "kworker/1:1H-kblockd");
    write_file(proc / "12/comm", "kworker/u8:2");
    write_file(proc / "13/comm", "ksoftirqd/0");
    g_calls.clear();
    g_set_errno = 0;
    {
        TtyWorkerPriority w(10, proc.string(), &fake_set_tid);
        EXPECT_EQ(w.apply(), 2);
        EXPECT_EQ(g_calls, (std::vector<std::pair<int, int>>{{10, 10}, {12, 10}}));
        EXPECT_EQ(w.apply(), 0);  // nothing new
        // The pool made a new worker and let worker 10 go.
        write_file(proc / "2/task/2/children", "11 12 13 14");
        write_file(proc / "14/comm", "kworker/u8:5");
        fs::remove_all(proc / "10");
        EXPECT_EQ(w.apply(), 1);
        EXPECT_EQ(w.raised(), 2u);  // 12 and 14
        EXPECT_TRUE(w.note().empty());
        g_calls.clear();
    }  // the destructor restores
    std::sort(g_calls.begin(), g_calls.end());
    EXPECT_EQ(g_calls, (std::vector<std::pair<int, int>>{{12, 0}, {14, 0}}));

    // Refused: nothing changed, a note naming the capability, no retry storm.
    g_calls.clear();
    g_set_errno = EPERM;
    TtyWorkerPriority refused(10, proc.string(), &fake_set_tid);
    EXPECT_EQ(refused.apply(), 0);
    EXPECT_NE(refused.note().find("CAP_SYS_NICE"), std::string::npos) << refused.note();
    EXPECT_EQ(refused.apply(), 0);
    EXPECT_EQ(refused.raised(), 0u);
    g_set_errno = 0;
    // Off: nothing is touched.
    TtyWorkerPriority off(0, proc.string(), &fake_set_tid);
    EXPECT_EQ(off.apply(), 0);
    EXPECT_TRUE(g_calls.empty());
    EXPECT_THROW(TtyWorkerPriority(100, proc.string(), &fake_set_tid), ConfigError);
    fs::remove_all(proc);
}

// Polling slower than the device's frame rate skips frames: every skipped device frame is
// counted, by the frame numbers, in the frame (frames_missed_before) and in the status.
TEST(TrackerSession, CountsGapsByTheDevicesFrameNumbers) {
    cf::sim::TrackerSimConfig sc;
    sc.link = cf::sim::TrackerSimConfig::Link::tcp;
    sc.frame_rate_hz = 250;
    cf::sim::TrackerSimulator sim(sc);
    sim.start();
    SessionConfig c;
    c.tools = {ToolDefinition{"ref", cf::sim::make_synthetic_rom("CF-REFERENCE", 1, {{0, 0, 0}, {0, 50, 0}, {0, 100, 25}}), 'S'}};
    c.poll_interval = 10ms;  // 2.5 device frames per poll
    c.command_timeout = 500ms;
    TrackerSession s(make_tcp_transport("127.0.0.1", sim.tcp_port()), c);
    std::mutex mu;
    std::vector<TrackerFrame> frames;
    s.set_frame_callback([&](const TrackerFrame& f) {
        std::lock_guard lk(mu);
        frames.push_back(f);
    });
    s.start();
    ASSERT_TRUE(s.wait_frame(40, 10s).has_value()) << s.status().last_error;
    s.stop();
    const TrackerStatus st = s.status();
    std::lock_guard lk(mu);
    ASSERT_GE(frames.size(), 40u);
    std::uint64_t missed = 0, gaps = 0;
    for (std::size_t i = 0; i < frames.size(); ++i) {
        EXPECT_EQ(frames[i].sequence, i + 1);
        EXPECT_GT(frames[i].request_steady_ns, 0);
        EXPECT_GE(frames[i].receive_steady_ns, frames[i].request_steady_ns);
        if (i == 0) {
            EXPECT_EQ(frames[i].frames_missed_before, 0u);
            continue;
        }
        ASSERT_GT(frames[i].frame_number, frames[i - 1].frame_number);  // in order
        EXPECT_EQ(frames[i].frames_missed_before, frames[i].frame_number - frames[i - 1].frame_number - 1) << i;
        missed += frames[i].frames_missed_before;
        gaps += frames[i].frames_missed_before > 0;
    }
    EXPECT_GT(missed, frames.size());  // about 1.5 skipped per poll: the test sees gaps
    EXPECT_EQ(st.frames_missed, missed);
    EXPECT_EQ(st.frame_gaps, gaps);
    EXPECT_EQ(st.out_of_order, 0u);
    EXPECT_GT(st.requests, 0u);
    EXPECT_GT(st.reply_p50_us, 0.0);
    EXPECT_GE(st.reply_max_us, st.reply_p99_us);
}
