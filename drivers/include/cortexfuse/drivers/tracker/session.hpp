#pragma once
// The Polaris session: a driver thread that owns one transport, brings the device up
// (reset, INIT, COMM, VER/APIREV, tool loading, TSTART), streams BX (or TX) frames, and
// recovers on its own from timeouts, CRC errors, garbage, a pulled cable or a power cycle.
//
// Thread contract:
//  - TrackerSession owns its Transport (unique_ptr) and one driver thread, started by start()
//    and joined by stop() or the destructor. Only the driver thread touches the transport and
//    the codec.
//  - status(), latest(), wait_frame(), beep() and stop() may be called from any thread; they
//    take an internal mutex for a short copy and never block on I/O.
//  - The frame callback (set before start()) runs on the driver thread, once per new frame,
//    outside the mutex; it must be quick (copy the frame and return).
#include <Eigen/Geometry>

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <deque>
#include <functional>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "cortexfuse/drivers/tracker/ndi_codec.hpp"
#include "cortexfuse/drivers/tracker/thread_priority.hpp"
#include "cortexfuse/drivers/tracker/transport.hpp"

namespace cf::tracker {

/// The device answered ERRORxx to a command (the message says which and what it means).
class DeviceError : public std::runtime_error {
public:
    DeviceError(const std::string& what, int error_code) : std::runtime_error(what), code(error_code) {}
    int code;
};

/// steady_clock in nanoseconds: drives all logic and the latency figures.
std::int64_t steady_ns();

/// A passive tool definition (.rom) to load with PHRQ/PVWR.
struct ToolDefinition {
    std::string name;                ///< reported with each frame (the file's stem by default)
    std::vector<std::uint8_t> rom;   ///< the file's bytes, 1..2048
    char priority = 'D';             ///< PENA priority: S static, D dynamic, B button box
};
/// Reads a .rom file: must exist, be 16..2048 bytes and start with "NDI\0". Throws ConfigError.
ToolDefinition load_tool_definition(const std::string& path, char priority = 'D');

struct SessionConfig {
    enum class ReplyMode { automatic, bx, tx };
    std::vector<ToolDefinition> tools;
    int baud = 115200;                        ///< serial only; one of host_baud_rates()
    ReplyMode reply_mode = ReplyMode::automatic;  ///< automatic: TX on firmware known to need it
    bool break_reset = true;                  ///< serial: reset with a break before INIT
    std::chrono::milliseconds poll_interval{8};       ///< BX/TX request period (2..1000)
    std::chrono::milliseconds reply_timeout{100};     ///< BX/TX reply deadline (10..5000)
    std::chrono::milliseconds gap_timeout{20};        ///< a partial reply with no byte for this long is lost (2..1000)
    std::chrono::milliseconds command_timeout{1000};  ///< setup commands (50..10000)
    std::chrono::milliseconds init_timeout{5000};     ///< INIT incl. ERROR0C retries (100..30000)
    std::chrono::milliseconds reset_timeout{7000};    ///< wait for RESET after a break (100..30000)
    std::chrono::milliseconds stale_after{500};       ///< a tool not updated this long is stale (50..10000)
    std::chrono::milliseconds max_backoff{500};       ///< reconnect backoff ceiling (10..10000)
    int max_consecutive_timeouts = 3;                 ///< silent requests, then reset (serial) / reconnect (TCP) (1..100)
    int max_consecutive_corrupt = 30;                 ///< corrupt/garbled replies in a row, then the same (1..1000)
    /// Silence before a recovery: besides max_consecutive_timeouts silent requests, no byte
    /// for this long (50..10000). A reply that comes after its deadline (the CPU was busy, the
    /// kernel's tty worker late) is still read and published before the next request
    /// (late_replies), so only a link that stays silent this long is reset.
    std::chrono::milliseconds link_silence{500};
    /// The driver thread's priority, set when it starts (thread_priority.hpp): SCHED_FIFO when
    /// realtime_priority > 0 and permitted, else the nice value. Default: unchanged.
    ThreadPriorityRequest thread_priority{};
    /// Throws ConfigError naming the option and its range.
    void validate(bool serial) const;
};

/// One tool in one published frame.
struct TrackedTool {
    std::string name;
    std::uint8_t handle = 0;
    ToolReading::Status status = ToolReading::Status::missing;  ///< as the device reported it
    /// Present only when the device reported this tool OK in this frame and it is not stale.
    std::optional<Eigen::Isometry3d> T_tracker_from_tool;
    double rms_error_mm = 0;
    std::uint32_t port_status = 0;
    bool out_of_volume = false, partially_out_of_volume = false;
    bool stale = false;                   ///< no OK reading for stale_after
    std::int64_t last_ok_steady_ns = 0;   ///< receive time of the last OK reading (0: never)
};

struct TrackerFrame {
    std::uint64_t sequence = 0;          ///< 1, 2, ... per published frame (this session)
    std::uint32_t frame_number = 0;      ///< the device's frame counter (60 Hz on Polaris)
    std::uint16_t system_status = 0;
    std::int64_t receive_steady_ns = 0;  ///< when the reply's last byte was read from the transport
    std::int64_t publish_steady_ns = 0;  ///< when the frame became available
    std::int64_t request_steady_ns = 0;  ///< when the BX/TX request it answers was written
    /// Device frames between the previous published frame and this one that were never read
    /// (frame_number - previous - 1; 0 for the first frame of a session or after the device's
    /// counter restarted).
    std::uint32_t frames_missed_before = 0;
    bool late = false;                   ///< the reply came after reply_timeout (read before the next request)
    std::vector<TrackedTool> tools;
};

struct TrackerStatus {
    enum class State { stopped, connecting, resetting, initialising, loading_tools, streaming, recovering };
    State state = State::stopped;
    std::string transport, firmware, api_revision, reply_mode, last_error;
    int baud = 0;
    std::uint64_t frames = 0, duplicate_frames = 0, crc_errors = 0, resyncs = 0, discarded_bytes = 0,
                  timeouts = 0, lost_replies = 0, protocol_errors = 0, device_errors = 0, warnings = 0, reconnects = 0, resets = 0;
    /// By the device's frame numbers: jumps between consecutive published frames (frame_gaps)
    /// and the device frames they skipped (frames_missed); replies older than the last
    /// published frame (out_of_order, never published); replies read after their deadline and
    /// published (late_replies).
    std::uint64_t frame_gaps = 0, frames_missed = 0, out_of_order = 0, late_replies = 0;
    double frame_rate_hz = 0;                   ///< new frames over the last second
    double latency_p50_us = 0, latency_p99_us = 0;  ///< wire-to-frame, last 1024 frames
    /// BX/TX round trip (request written -> reply's last byte read), last 1024 frames, and the
    /// largest since start.
    double reply_p50_us = 0, reply_p99_us = 0, reply_max_us = 0;
    /// BX/TX requests written; the largest delay of the driver thread's wake-up past a read
    /// timeout (it waited for a core) and the slowest frame callback, since start.
    std::uint64_t requests = 0;
    double wake_late_max_us = 0, callback_max_us = 0;
    /// What the driver thread got (ThreadPriorityResult::describe()) and, when that is not
    /// what SessionConfig::thread_priority asked, why (one line).
    std::string thread_priority, thread_priority_note;
    std::int64_t last_frame_steady_ns = 0;
};
const char* state_name(TrackerStatus::State s);

class TrackerSession {
public:
    TrackerSession(std::unique_ptr<Transport> transport, SessionConfig config);
    ~TrackerSession();
    TrackerSession(const TrackerSession&) = delete;
    TrackerSession& operator=(const TrackerSession&) = delete;

    /// Called on the driver thread for every new frame. Set before start().
    void set_frame_callback(std::function<void(const TrackerFrame&)> cb);
    void start();
    /// Stops streaming (TSTOP, and COMM back to 9600 on serial, best effort) and joins.
    void stop();

    TrackerStatus status() const;
    /// The newest frame with staleness evaluated now (stale tools lose their pose).
    std::optional<TrackerFrame> latest() const;
    /// Waits for a frame with sequence > after_sequence.
    std::optional<TrackerFrame> wait_frame(std::uint64_t after_sequence, std::chrono::milliseconds timeout) const;
    /// Asks the driver thread to send BEEP n (1..9) at the next opportunity.
    void beep(int n);

private:
    struct Recover : std::runtime_error {
        using std::runtime_error::runtime_error;
    };
    void run();
    void setup();
    void stream();
    void shutdown_device();
    std::string command(const std::string& name, const std::string& params, std::chrono::milliseconds timeout);
    /// A reply, or nullopt with *heard = whether any byte came (silence vs a corrupt or
    /// truncated reply, which gives up after gap_timeout without bytes instead of the deadline).
    std::optional<Reply> await_reply(std::chrono::milliseconds timeout, std::int64_t* receive_ns, bool* heard = nullptr);
    void set_state(TrackerStatus::State s);
    void note_error(const std::string& e);
    void sync_decoder_counters();
    void publish(const TrackingReply& r, std::int64_t receive_ns, std::int64_t request_ns, bool late);
    /// Before a new request: reads whatever arrived since the last deadline and publishes a
    /// good tracking reply in it (a late one); drops the rest. True when a reply was published.
    bool drain_late_reply(std::int64_t request_ns);
    void record_round_trip(std::int64_t ns);  // under mu_
    bool sleep_for(std::chrono::milliseconds d);  // false when stopping

    std::unique_ptr<Transport> transport_;  // owned; driver thread only
    SessionConfig cfg_;
    ReplyDecoder decoder_;                  // driver thread only
    std::vector<std::pair<std::uint8_t, std::string>> handle_names_;
    bool use_tx_ = false;
    bool streaming_ = false;
    bool shutting_down_ = false;  // TSTOP/COMM after stop(): commands still wait for replies
    std::optional<std::uint32_t> last_frame_number_;   // this setup's last published frame number
    std::optional<std::uint32_t> last_published_frame_;  // across setups, for frames_missed
    std::vector<std::int64_t> last_ok_ns_;  // per handle_names_ entry

    std::function<void(const TrackerFrame&)> callback_;
    std::thread thread_;
    std::atomic<bool> stop_{false};
    std::atomic<int> beep_request_{0};

    mutable std::mutex mu_;
    mutable std::condition_variable cv_;
    TrackerStatus status_;
    std::optional<TrackerFrame> latest_;
    std::deque<std::int64_t> frame_times_ns_;
    std::vector<std::int64_t> latencies_ns_;  // ring of 1024
    std::size_t latency_next_ = 0;
    std::vector<std::int64_t> replies_ns_;    // ring of 1024 round trips
    std::size_t reply_next_ = 0;
    std::uint64_t requests_ = 0;                      // driver thread; copied by sync_decoder_counters
    std::int64_t wake_late_max_ns_ = 0, callback_max_ns_ = 0;  // the same
    std::uint64_t sequence_ = 0;
};

}  // namespace cf::tracker
