#pragma once
// NDI Polaris simulator: the device side of the combined API over a pseudo-terminal (the
// driver opens the slave like a serial port) or TCP (like a Vega), with a scene (reference
// tool, pointer, optional tracked camera), measurement noise, 20/60/250 Hz frames and fault
// injection (scripted, and random with a seed).
//
// It shares the codec's CRC and framing helpers, but the device side (command parsing, states,
// handles, .rom storage, BX/TX bodies) is implemented here, on its own.
//
// Truth: the pose of every tool is a pure function of (seed, tool, frame number), so
// truth() can be asked from any thread, at any time, for any frame a driver reported.
//
// Thread contract: start() runs one simulator thread that owns the pty / sockets. truth(),
// fault_counts(), link_restored_ns(), slave_path() and tcp_port() are safe from any thread.
#include <Eigen/Geometry>

#include <array>
#include <atomic>
#include <chrono>
#include <cstdint>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <vector>

#include "cortexfuse/drivers/tracker/thread_priority.hpp"

namespace cf::sim {

/// Kinds of injected faults (fact sheet §9.3), with their names in scripts and summaries.
enum class Fault { bit_flip, drop, truncate, garbage, delay, split, stale_bytes, disconnect, power_cycle, tool_missing, out_of_volume };
inline constexpr std::array<Fault, 11> kAllFaults = {Fault::bit_flip, Fault::drop, Fault::truncate, Fault::garbage, Fault::delay,
                                                     Fault::split, Fault::stale_bytes, Fault::disconnect, Fault::power_cycle,
                                                     Fault::tool_missing, Fault::out_of_volume};
const char* fault_name(Fault f);
std::optional<Fault> fault_from_name(const std::string& s);

struct FaultRates {
    /// Per BX/TX reply, probability of each reply fault (at most one fault per reply).
    double bit_flip = 0, drop = 0, truncate = 0, garbage = 0, delay = 0, split = 0, stale_bytes = 0;
    /// Mean events per minute while tracking (Poisson).
    double disconnects_per_min = 0, power_cycles_per_min = 0;
    /// Fraction of 0.5 s blocks in which a tool is missing / out of volume.
    double tool_missing = 0, out_of_volume = 0;
    /// Parses "bit_flip=0.02,drop=0.01,disconnects_per_min=6,..."; throws std::invalid_argument.
    static FaultRates parse(const std::string& text);
};

struct ScriptedFault {
    double at_s = 0;        ///< seconds after start()
    Fault kind = Fault::drop;
    std::string tool;       ///< tool_missing / out_of_volume: the tool's part name
    double duration_s = 0;  ///< tool_missing / out_of_volume
};
/// Script lines: `<at_s> <fault> [tool] [duration_s]`, '#' comments. Throws std::invalid_argument naming the line.
std::vector<ScriptedFault> load_fault_script(const std::string& path);

struct TrackerSimConfig {
    enum class Link { pty, tcp };
    Link link = Link::pty;
    std::string pty_link;                 ///< optional symlink kept pointing at the current slave
    std::string tcp_host = "127.0.0.1";   ///< loopback only by default
    std::uint16_t tcp_port = 0;           ///< 0: an ephemeral port (see tcp_port())
    double frame_rate_hz = 60;            ///< 20, 60 or 250
    double noise_mm = 0.05;               ///< per axis, Gaussian
    double noise_deg = 0.05;              ///< rotation noise, Gaussian angle about a random axis
    std::uint64_t seed = 1;
    bool camera_tool = false;             ///< add "CF-CAMERA" to the scene
    std::string trajectory_file;          ///< `<t_s> <part> tx ty tz qw qx qy qz` lines, looped
    FaultRates faults;
    std::vector<ScriptedFault> script;
    std::string firmware = "Polaris Spectra Rev 008";  ///< in VER's "Freeze Tag:" line
    std::string api_revision = "G.001.005";
    std::chrono::milliseconds unplugged_for{300};      ///< link outage of a disconnect fault
    std::chrono::milliseconds boot_time{150};          ///< silence after a power cycle
    std::chrono::milliseconds reply_delay{1};          ///< device turnaround per command
    /// The simulator thread's priority. The simulator stands for a device with its own
    /// processor, which a busy host CPU cannot delay; sharing our cores, it may run at a raised
    /// priority (SCHED_FIFO / nice) so that the driver, not the stand-in, is what a load test
    /// measures. Default: unchanged.
    cf::tracker::ThreadPriorityRequest thread_priority{};
    /// Throws std::invalid_argument naming the option.
    void validate() const;
};

/// A frame's truth for one tool.
struct ToolTruth {
    Eigen::Isometry3d T_tracker_from_tool;  ///< noiseless
    Eigen::Isometry3d measured;             ///< with the frame's noise, before float32 rounding
    bool visible = true;                    ///< false: reported MISSING
    bool out_of_volume = false;             ///< reported with port status bit 0x40
};

class TrackerSimulator {
public:
    explicit TrackerSimulator(TrackerSimConfig config);
    ~TrackerSimulator();
    TrackerSimulator(const TrackerSimulator&) = delete;
    TrackerSimulator& operator=(const TrackerSimulator&) = delete;

    /// Opens the pty or the listening socket and starts the simulator thread. Throws
    /// std::runtime_error when the pty or socket cannot be created.
    void start();
    void stop();

    std::string slave_path() const;  ///< current pty slave (changes after a disconnect)
    std::uint16_t tcp_port() const;
    /// Scene tool part names ("CF-REFERENCE", "CF-POINTER", optionally "CF-CAMERA").
    std::vector<std::string> tools() const;
    std::optional<ToolTruth> truth(const std::string& part, std::uint32_t frame_number) const;
    /// The frame number the device is at now (what the next BX/TX reply carries). Any thread.
    std::uint32_t current_frame() const;
    std::map<Fault, std::uint64_t> fault_counts() const;
    std::uint64_t total_faults() const;
    /// Beeps the device was asked for by valid BEEP commands (the sum of their n). Any thread.
    std::uint64_t beeps() const;
    /// steady_ns times at which the link or the device came back after a disconnect or a power cycle.
    std::vector<std::int64_t> link_restored_ns() const;
    /// Scene control for workflows with ground truth (e.g. the pointer resting on a fiducial):
    /// from the next frame on, `part` stays at `T_tracker_from_tool` (nullopt: back to its
    /// scripted motion), and is reported MISSING while `hidden`. Returns the first frame number
    /// it applies to; truth() reflects it for that frame and later ones (a device frame counter
    /// reset by TSTART 80 after a power cycle restarts the numbering, so holds set before it
    /// apply again only from their frame number on). Any thread. Throws std::invalid_argument
    /// for an unknown part or a pose that is not finite.
    std::uint32_t hold(const std::string& part, std::optional<Eigen::Isometry3d> T_tracker_from_tool, bool hidden = false);
    /// Inject a fault now (reply faults apply to the next BX/TX reply).
    void inject(Fault f);
    std::uint64_t replies_sent() const { return replies_sent_.load(); }
    /// steady_ns when the first BX/TX reply carrying `frame_number` was completely written
    /// (the last byte on the wire), for wire-to-frame latency; kept for the last 4096 frames.
    std::optional<std::int64_t> reply_written_ns(std::uint32_t frame_number) const;
    /// steady_ns when the simulator read the request that the reply carrying `frame_number`
    /// answers (same window): with reply_written_ns and the driver's request/receive times it
    /// splits a round trip into host->device, device and device->host.
    std::optional<std::int64_t> request_read_ns(std::uint32_t frame_number) const;
    /// What the simulator thread got (ThreadPriorityResult::describe()) and the note, after start().
    std::string thread_priority() const;

private:
    struct Impl;
    std::unique_ptr<Impl> impl_;
    std::atomic<std::uint64_t> replies_sent_{0};
};

/// The synthetic .rom layout the simulator understands (docs/tracker.md): "NDI\0", main type,
/// "CF1", 20-byte part name, marker count, markers (float32 mm), padding, CRC-16 of the rest.
std::vector<std::uint8_t> make_synthetic_rom(const std::string& part, std::uint8_t main_type,
                                             const std::vector<Eigen::Vector3f>& markers_mm, std::size_t size = 176);

}  // namespace cf::sim
