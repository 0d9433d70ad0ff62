#pragma once
// NDI combined API codec: bytes in, messages out, no I/O, no clocks, no threads.
//
// Everything here follows the protocol fact sheet (docs/tracker.md points at the sections):
// CRC-16/ARC, the command forms, ASCII replies `<payload><CRC 4 hex><CR>`, binary replies
// `C4 A5 <len u16> <hdr CRC u16> <body> <body CRC u16>` (little-endian), BX and TX bodies.
// The decoder resynchronises on garbage and never hands a frame upward whose CRC failed.
// Hand-written on purpose: no Debian package implements this protocol (ndicapi is not
// packaged and copies binary replies with strcpy, see the fact sheet §10 lesson 7).
#include <Eigen/Geometry>

#include <cstdint>
#include <optional>
#include <span>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace cf::tracker {

/// A reply that framed correctly (CRC fine) but whose content is not what the protocol says.
class ProtocolError : public std::runtime_error {
public:
    explicit ProtocolError(const std::string& what) : std::runtime_error(what) {}
};

// ---- CRC and command encoding -------------------------------------------------------------

/// CRC-16/ARC (poly 0x8005 reflected, init 0, no final xor): "123456789" -> 0xBB3D.
std::uint16_t crc16(std::span<const std::uint8_t> bytes, std::uint16_t crc = 0);
std::uint16_t crc16(std::string_view bytes, std::uint16_t crc = 0);
/// Four uppercase hex digits, most significant first (how ASCII replies and commands print it).
std::string crc_hex(std::uint16_t crc);

/// CRC form: `NAME:params<CRC>\r` (the CRC covers NAME, ':' and params).
std::string encode_command(std::string_view name, std::string_view params = {});
/// No-CRC form: `NAME params\r` (a space even without params).
std::string encode_command_nocrc(std::string_view name, std::string_view params = {});

/// Device side helpers (the simulator uses them): `payload<CRC>\r` and the binary envelope.
std::string frame_ascii_reply(std::string_view payload);
std::vector<std::uint8_t> frame_binary_reply(std::span<const std::uint8_t> body);

/// A command as the device receives it: the name, the parameters, whether it carried a CRC
/// and whether that CRC was right. Returns nullopt when the line is not a command at all.
struct ParsedCommand {
    std::string name, params;
    bool had_crc = false;
    bool crc_ok = true;
};
std::optional<ParsedCommand> parse_command(std::string_view line_without_cr);

// ---- Reply framing -----------------------------------------------------------------------

/// One reply that passed its CRC check(s).
struct Reply {
    enum class Kind { ascii, binary };
    Kind kind = Kind::ascii;
    std::string text;                 ///< ascii: the payload (without CRC and CR)
    std::vector<std::uint8_t> body;   ///< binary: the body (without header and CRCs)
};

/// What the decoder threw away, for the driver's counters.
struct DecoderCounters {
    std::uint64_t replies = 0;          ///< replies handed upward
    std::uint64_t crc_errors = 0;       ///< framed replies whose CRC (ASCII, header or body) failed
    std::uint64_t resyncs = 0;          ///< times bytes were discarded to find the next reply start
    std::uint64_t discarded_bytes = 0;  ///< bytes thrown away in total
};

/// Incremental reply decoder. Feed it whatever the transport read, in any split; take the
/// replies out with next(). Not thread-safe (one owner: the driver thread).
class ReplyDecoder {
public:
    static constexpr std::size_t kMaxBinaryBody = 8192;  // BX for 24 handles with markers is < 4 KiB
    static constexpr std::size_t kMaxAsciiLine = 8192;

    void feed(std::span<const std::uint8_t> bytes);
    void feed(std::string_view bytes);
    /// The next complete, CRC-checked reply, or nullopt when more bytes are needed.
    std::optional<Reply> next();
    /// Throws away everything buffered (after a timeout or a reset). Counted as a resync
    /// when bytes were pending.
    void clear();
    std::size_t buffered() const { return buf_.size() - pos_; }
    const DecoderCounters& counters() const { return counters_; }

private:
    void discard(std::size_t n);
    void compact();
    std::vector<std::uint8_t> buf_;
    std::size_t pos_ = 0;
    bool discarding_ = false;  // a run of discarded bytes counts as one resync
    DecoderCounters counters_;
};

// ---- Reply content -----------------------------------------------------------------------

/// ERROR / WARNING / OKAY / RESET, recognised from an ASCII payload.
struct Status {
    enum class Kind { okay, error, warning, reset, data };
    Kind kind = Kind::data;
    int code = 0;  ///< for error/warning
};
Status classify(std::string_view payload);
/// Human text for an ERRORxx / WARNINGxx code (fact sheet §3).
std::string error_text(int code);
std::string warning_text(int code);
/// "ERROR0D (no tool assigned to this port handle)"
std::string describe_status(const Status& s);

/// Port status bits (fact sheet §6.4).
namespace port_bits {
inline constexpr std::uint32_t occupied = 0x0001, initialised = 0x0010, enabled = 0x0020,
                               out_of_volume = 0x0040, partially_out = 0x0080;
}

/// One handle's entry in a BX/TX reply.
struct ToolReading {
    enum class Status { ok, missing, disabled, unoccupied };
    std::uint8_t handle = 0;
    Status status = Status::missing;
    /// Present only when status == ok. Never a copy of an older pose.
    std::optional<Eigen::Isometry3d> T_tracker_from_tool;
    Eigen::Vector4d q_wxyz = Eigen::Vector4d::Zero();  ///< as sent (scalar first), valid when ok
    Eigen::Vector3d t_mm = Eigen::Vector3d::Zero();    ///< as sent, valid when ok
    double rms_error_mm = 0;
    std::uint32_t port_status = 0;
    std::uint32_t frame_number = 0;
    bool out_of_volume() const { return port_status & port_bits::out_of_volume; }
    bool partially_out_of_volume() const { return port_status & port_bits::partially_out; }
};

struct TrackingReply {
    std::vector<ToolReading> tools;
    std::uint16_t system_status = 0;
    std::size_t stray_markers = 0;
    /// The frame number of the first tool that carries one (0 when none does).
    std::uint32_t frame_number() const;
};

/// Reply-option bits for BX and TX (fact sheet §6.2).
namespace reply_option {
inline constexpr std::uint16_t transforms = 0x0001, tool_info = 0x0002, stray_active = 0x0004,
                               tool_markers = 0x0008, all_transforms = 0x0800,
                               stray_passive = 0x1000, stray_extended = 0x2000;
}

/// Parses a BX body (the bytes between the header and the body CRC) sent for `options`.
/// Throws ProtocolError on any inconsistency (sizes, unknown handle status, trailing bytes).
TrackingReply parse_bx(std::span<const std::uint8_t> body, std::uint16_t options);
/// Parses a TX payload for options 0001 (+0800). Throws ProtocolError.
TrackingReply parse_tx(std::string_view payload, std::uint16_t options);

/// A unit quaternion (w, x, y, z) + translation in mm -> rigid transform. Normalises q
/// (device quaternions are rounded: |q| = 0.9999x); throws ProtocolError when |q| is far
/// from 1 or a value is not finite.
Eigen::Isometry3d pose_from_quaternion(const Eigen::Vector4d& q_wxyz, const Eigen::Vector3d& t_mm);

/// PHSR reply: handles and their 3-hex status.
struct HandleInfo {
    std::uint8_t handle = 0;
    std::uint16_t status = 0;
};
std::vector<HandleInfo> parse_phsr(std::string_view payload);

/// COMM baud code character <-> baud rate (fact sheet §5.2). 0 when unknown.
char comm_baud_code(int baud);
int comm_baud_rate(char code);

/// Hex helpers shared with the simulator.
std::string to_hex(std::span<const std::uint8_t> bytes);  // uppercase
std::optional<std::vector<std::uint8_t>> from_hex(std::string_view hex);  // either case
std::optional<std::uint32_t> parse_hex_u32(std::string_view hex);

}  // namespace cf::tracker
