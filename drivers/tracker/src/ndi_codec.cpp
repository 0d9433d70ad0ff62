#include "cortexfuse/drivers/tracker/ndi_codec.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>

namespace cf::tracker {

namespace {

constexpr std::array<std::uint16_t, 256> make_crc_table() {
    std::array<std::uint16_t, 256> t{};
    for (unsigned i = 0; i < 256; ++i) {
        std::uint16_t c = static_cast<std::uint16_t>(i);
        for (int k = 0; k < 8; ++k) c = (c & 1) ? static_cast<std::uint16_t>((c >> 1) ^ 0xA001) : static_cast<std::uint16_t>(c >> 1);
        t[i] = c;
    }
    return t;
}
constexpr auto kCrcTable = make_crc_table();

constexpr std::uint8_t kCR = 0x0D, kLF = 0x0A;

bool printable(std::uint8_t b) { return (b >= 0x20 && b <= 0x7E) || b == kLF; }
bool upper_hex(char c) { return (c >= '0' && c <= '9') || (c >= 'A' && c <= 'F'); }
int hex_value(char c) {
    if (c >= '0' && c <= '9') return c - '0';
    if (c >= 'A' && c <= 'F') return c - 'A' + 10;
    if (c >= 'a' && c <= 'f') return c - 'a' + 10;
    return -1;
}

std::uint16_t le16(const std::uint8_t* p) { return static_cast<std::uint16_t>(p[0] | (p[1] << 8)); }
std::uint32_t le32(const std::uint8_t* p) {
    return static_cast<std::uint32_t>(p[0]) | (static_cast<std::uint32_t>(p[1]) << 8) |
           (static_cast<std::uint32_t>(p[2]) << 16) | (static_cast<std::uint32_t>(p[3]) << 24);
}
float lef32(const std::uint8_t* p) {
    const std::uint32_t u = le32(p);
    float f;
    std::memcpy(&f, &u, 4);
    return f;
}

// Bounds-checked reader over a BX body.
class Cursor {
public:
    explicit Cursor(std::span<const std::uint8_t> b) : b_(b) {}
    const std::uint8_t* take(std::size_t n, const char* what) {
        if (n > b_.size() - i_) throw ProtocolError(std::string("BX reply too short for ") + what);
        const std::uint8_t* p = b_.data() + i_;
        i_ += n;
        return p;
    }
    std::uint8_t u8(const char* what) { return *take(1, what); }
    std::size_t left() const { return b_.size() - i_; }

private:
    std::span<const std::uint8_t> b_;
    std::size_t i_ = 0;
};

// Signed decimal of fixed width: sign + (width-1) digits.
double signed_field(std::string_view s, std::size_t& i, std::size_t width, double scale, const char* what) {
    if (s.size() - i < width) throw ProtocolError(std::string("TX reply too short for ") + what);
    const char sign = s[i];
    if (sign != '+' && sign != '-') throw ProtocolError(std::string("TX reply: bad sign in ") + what);
    long v = 0;
    for (std::size_t k = 1; k < width; ++k) {
        const char c = s[i + k];
        if (c < '0' || c > '9') throw ProtocolError(std::string("TX reply: bad digit in ") + what);
        v = v * 10 + (c - '0');
    }
    i += width;
    return (sign == '-' ? -v : v) / scale;
}
std::uint32_t hex_field(std::string_view s, std::size_t& i, std::size_t width, const char* what) {
    if (s.size() - i < width) throw ProtocolError(std::string("reply too short for ") + what);
    const auto v = parse_hex_u32(s.substr(i, width));
    if (!v) throw ProtocolError(std::string("reply: bad hex in ") + what);
    i += width;
    return *v;
}

}  // namespace

// ---- CRC and encoding ----------------------------------------------------------------------

std::uint16_t crc16(std::span<const std::uint8_t> bytes, std::uint16_t crc) {
    for (const std::uint8_t b : bytes) crc = static_cast<std::uint16_t>((crc >> 8) ^ kCrcTable[(crc ^ b) & 0xFF]);
    return crc;
}
std::uint16_t crc16(std::string_view bytes, std::uint16_t crc) {
    return crc16(std::span<const std::uint8_t>(reinterpret_cast<const std::uint8_t*>(bytes.data()), bytes.size()), crc);
}

std::string crc_hex(std::uint16_t crc) {
    static const char* d = "0123456789ABCDEF";
    return {d[(crc >> 12) & 15], d[(crc >> 8) & 15], d[(crc >> 4) & 15], d[crc & 15]};
}

std::string encode_command(std::string_view name, std::string_view params) {
    std::string s;
    s.reserve(name.size() + params.size() + 6);
    s.append(name).push_back(':');
    s.append(params);
    s += crc_hex(crc16(s));
    s.push_back('\r');
    return s;
}

std::string encode_command_nocrc(std::string_view name, std::string_view params) {
    std::string s(name);
    s.push_back(' ');
    s.append(params);
    s.push_back('\r');
    return s;
}

std::string frame_ascii_reply(std::string_view payload) {
    std::string s(payload);
    s += crc_hex(crc16(payload));
    s.push_back('\r');
    return s;
}

std::vector<std::uint8_t> frame_binary_reply(std::span<const std::uint8_t> body) {
    std::vector<std::uint8_t> out(6 + body.size() + 2);
    out[0] = 0xC4;
    out[1] = 0xA5;
    out[2] = static_cast<std::uint8_t>(body.size() & 0xFF);
    out[3] = static_cast<std::uint8_t>((body.size() >> 8) & 0xFF);
    const std::uint16_t hc = crc16(std::span<const std::uint8_t>(out.data(), 4));
    out[4] = static_cast<std::uint8_t>(hc & 0xFF);
    out[5] = static_cast<std::uint8_t>(hc >> 8);
    std::copy(body.begin(), body.end(), out.begin() + 6);
    const std::uint16_t bc = crc16(body);
    out[6 + body.size()] = static_cast<std::uint8_t>(bc & 0xFF);
    out[7 + body.size()] = static_cast<std::uint8_t>(bc >> 8);
    return out;
}

std::optional<ParsedCommand> parse_command(std::string_view line) {
    std::size_t n = 0;
    while (n < line.size() && ((line[n] >= 'A' && line[n] <= 'Z') || (line[n] >= '0' && line[n] <= '9'))) ++n;
    if (n == 0 || n == line.size() || (line[n] != ':' && line[n] != ' ')) return std::nullopt;
    ParsedCommand c;
    c.name = std::string(line.substr(0, n));
    if (line[n] == ' ') {
        c.params = std::string(line.substr(n + 1));
        return c;
    }
    // CRC form: the last four characters are the CRC of everything before them.
    c.had_crc = true;
    const std::string_view rest = line.substr(n + 1);
    if (rest.size() < 4) {
        c.crc_ok = false;
        return c;
    }
    const auto sent = parse_hex_u32(rest.substr(rest.size() - 4));
    c.params = std::string(rest.substr(0, rest.size() - 4));
    c.crc_ok = sent && *sent == crc16(line.substr(0, line.size() - 4));
    return c;
}

// ---- Decoder -------------------------------------------------------------------------------

void ReplyDecoder::feed(std::span<const std::uint8_t> bytes) {
    compact();
    buf_.insert(buf_.end(), bytes.begin(), bytes.end());
}
void ReplyDecoder::feed(std::string_view bytes) {
    feed(std::span<const std::uint8_t>(reinterpret_cast<const std::uint8_t*>(bytes.data()), bytes.size()));
}

void ReplyDecoder::compact() {
    if (pos_ > 0 && (pos_ == buf_.size() || pos_ > 4096)) {
        buf_.erase(buf_.begin(), buf_.begin() + static_cast<std::ptrdiff_t>(pos_));
        pos_ = 0;
    }
}

void ReplyDecoder::discard(std::size_t n) {
    n = std::min(n, buf_.size() - pos_);
    if (n == 0) return;
    if (!discarding_) ++counters_.resyncs;
    discarding_ = true;
    counters_.discarded_bytes += n;
    pos_ += n;
}

void ReplyDecoder::clear() {
    if (buffered() > 0) discard(buffered());
    buf_.clear();
    pos_ = 0;
    discarding_ = false;
}

std::optional<Reply> ReplyDecoder::next() {
    for (;;) {
        const std::size_t avail = buf_.size() - pos_;
        if (avail == 0) return std::nullopt;
        const std::uint8_t* p = buf_.data() + pos_;

        if (p[0] == 0xC4) {
            if (avail < 2) return std::nullopt;
            if (p[1] != 0xA5) {
                discard(1);
                continue;
            }
            if (avail < 6) return std::nullopt;
            const std::size_t n = le16(p + 2);
            if (crc16(std::span<const std::uint8_t>(p, 4)) != le16(p + 4) || n > kMaxBinaryBody) {
                ++counters_.crc_errors;
                discard(1);
                continue;
            }
            if (avail < n + 8) return std::nullopt;
            if (crc16(std::span<const std::uint8_t>(p + 6, n)) != le16(p + 6 + n)) {
                // Drop only the start sequence: the length may belong to a truncated reply,
                // and the next reply's start is then somewhere inside the "body".
                ++counters_.crc_errors;
                discard(2);
                continue;
            }
            Reply r;
            r.kind = Reply::Kind::binary;
            r.body.assign(p + 6, p + 6 + n);
            pos_ += n + 8;
            discarding_ = false;
            ++counters_.replies;
            return r;
        }

        if (!printable(p[0])) {
            discard(1);
            continue;
        }
        // An ASCII reply: printable bytes (and LF) up to a single CR.
        std::size_t i = 0;
        while (i < avail && printable(p[i])) ++i;
        if (i == avail) {
            if (avail > kMaxAsciiLine) discard(avail);
            return std::nullopt;
        }
        if (p[i] != kCR) {  // a non-printable byte before any CR: what came before is garbage
            discard(i);
            continue;
        }
        const std::string_view line(reinterpret_cast<const char*>(p), i);
        bool accepted = false;
        std::size_t start = 0;
        if (line.size() >= 5 && std::all_of(line.end() - 4, line.end(), upper_hex)) {
            const std::uint16_t sent = static_cast<std::uint16_t>(*parse_hex_u32(line.substr(line.size() - 4)));
            // Whole line first; else a suffix (garbage or the tail of a truncated reply in
            // front of a good reply). A suffix must start like a reply does.
            for (std::size_t j = 0; j + 5 <= line.size() && !accepted; ++j) {
                const char c = line[j];
                if (j > 0 && !((c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9'))) continue;
                if (crc16(line.substr(j, line.size() - 4 - j)) == sent) {
                    accepted = true;
                    start = j;
                }
            }
            if (!accepted) ++counters_.crc_errors;
        }
        if (!accepted) {
            discard(i + 1);
            continue;
        }
        if (start > 0) discard(start);
        Reply r;
        r.kind = Reply::Kind::ascii;
        r.text.assign(line.substr(start, line.size() - 4 - start));
        pos_ += (i + 1) - start;
        discarding_ = false;
        ++counters_.replies;
        return r;
    }
}

// ---- Reply content -------------------------------------------------------------------------

Status classify(std::string_view s) {
    Status st;
    auto code = [&](std::size_t at) -> std::optional<int> {
        if (s.size() != at + 2) return std::nullopt;
        const int a = hex_value(s[at]), b = hex_value(s[at + 1]);
        if (a < 0 || b < 0) return std::nullopt;
        return a * 16 + b;
    };
    if (s == "OKAY") st.kind = Status::Kind::okay;
    else if (s == "RESET") st.kind = Status::Kind::reset;
    else if (s.starts_with("ERROR") && code(5)) {
        st.kind = Status::Kind::error;
        st.code = *code(5);
    } else if (s.starts_with("WARNING") && code(7)) {
        st.kind = Status::Kind::warning;
        st.code = *code(7);
    }
    return st;
}

std::string error_text(int code) {
    switch (code) {
        case 0x01: return "invalid or unknown command";
        case 0x02: return "command too long";
        case 0x03: return "command too short";
        case 0x04: return "bad CRC in the command";
        case 0x05: return "command timed out inside the device";
        case 0x06: return "new COMM parameters could not be applied";
        case 0x07: return "wrong number of parameters";
        case 0x08: return "invalid port handle";
        case 0x09: return "invalid mode or tracking priority";
        case 0x0A: return "invalid LED";
        case 0x0B: return "invalid LED state";
        case 0x0C: return "command not allowed in the current mode";
        case 0x0D: return "no tool assigned to this port handle";
        case 0x0E: return "port handle not initialised";
        case 0x0F: return "port handle not enabled";
        case 0x10: return "system not initialised";
        case 0x11: return "could not stop tracking";
        case 0x12: return "could not start tracking";
        case 0x13: return "could not initialise the tool (tool or SROM fault)";
        case 0x14: return "invalid position-sensor characterisation parameters";
        case 0x15: return "could not initialise the system";
        case 0x16: return "could not start diagnostic mode";
        case 0x17: return "could not stop diagnostic mode";
        case 0x19: return "could not read the firmware version";
        case 0x1A: return "internal system error";
        case 0x1C: return "could not set the marker firing signature";
        case 0x1E: return "could not read the SROM";
        case 0x1F: return "could not write the SROM";
        case 0x21: return "tool current test failed";
        case 0x22: return "marker wavelength not supported by the selected volume";
        case 0x23: return "parameter out of range";
        case 0x24: return "could not select the volume";
        case 0x25: return "could not determine the supported-features list";
        case 0x28: return "too many tools enabled, or tool type not supported";
        case 0x2A: return "no memory for dynamic allocation";
        case 0x2B: return "port handle not allocated";
        case 0x2C: return "port handle has become unoccupied";
        case 0x2D: return "all port handles are in use";
        case 0x2E: return "incompatible firmware versions";
        case 0x2F: return "invalid port description";
        case 0x30: return "port already has a port handle";
        case 0x32: return "operation not valid for this port handle's device";
        case 0x33: return "feature not available";
        case 0x34: return "user parameter does not exist";
        case 0x35: return "wrong value type";
        case 0x36: return "user parameter value out of range";
        case 0x37: return "user parameter index out of range";
        case 0x38: return "user parameter size wrong";
        case 0x39: return "permission denied";
        case 0x3B: return "file not found";
        case 0x3C: return "file write error";
        case 0x3D: return "file read error";
        case 0x40: return "tool definition file invalid";
        case 0x41: return "tool characteristics not supported";
        case 0x42: return "required device not connected";
        case 0xF1: return "too much environmental infrared";
        case 0xF4: return "Flash EPROM erase failed";
        case 0xF5: return "Flash EPROM write failed";
        case 0xF6: return "Flash EPROM read failed";
        default: return "reserved or unknown error";
    }
}

std::string warning_text(int code) {
    switch (code) {
        case 0x01: return "possible hardware fault";
        case 0x02: return "the tool breaks the unique-geometry rules";
        case 0x03: return "the tool is incompatible with other loaded tools";
        case 0x04: return "the tool breaks the unique-geometry rules and is incompatible with other tools";
        case 0x05: return "no marker wavelength in the tool definition, default used";
        default: return "unknown warning";
    }
}

std::string describe_status(const Status& s) {
    auto two = [](int c) { return crc_hex(static_cast<std::uint16_t>(c)).substr(2); };
    switch (s.kind) {
        case Status::Kind::okay: return "OKAY";
        case Status::Kind::reset: return "RESET";
        case Status::Kind::error: return "ERROR" + two(s.code) + " (" + error_text(s.code) + ")";
        case Status::Kind::warning: return "WARNING" + two(s.code) + " (" + warning_text(s.code) + ")";
        case Status::Kind::data: return "data";
    }
    return "data";
}

std::uint32_t TrackingReply::frame_number() const {
    for (const auto& t : tools)
        if (t.status == ToolReading::Status::ok || t.status == ToolReading::Status::missing) return t.frame_number;
    return 0;
}

Eigen::Isometry3d pose_from_quaternion(const Eigen::Vector4d& q, const Eigen::Vector3d& t_mm) {
    if (!q.allFinite() || !t_mm.allFinite()) throw ProtocolError("tracking reply: non-finite pose value");
    const double norm = q.norm();
    if (std::abs(norm - 1.0) > 0.01) throw ProtocolError("tracking reply: quaternion norm " + std::to_string(norm) + " is not 1");
    const Eigen::Quaterniond qq(q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm);
    Eigen::Isometry3d T = Eigen::Isometry3d::Identity();
    T.linear() = qq.toRotationMatrix();
    T.translation() = t_mm;
    return T;
}

TrackingReply parse_bx(std::span<const std::uint8_t> body, std::uint16_t options) {
    using namespace reply_option;
    Cursor c(body);
    TrackingReply r;
    const std::size_t n = c.u8("handle count");
    r.tools.reserve(n);
    for (std::size_t h = 0; h < n; ++h) {
        ToolReading t;
        t.handle = c.u8("handle");
        const std::uint8_t hs = c.u8("handle status");
        if (hs == 0x04) {
            t.status = ToolReading::Status::disabled;
            r.tools.push_back(std::move(t));
            continue;
        }
        if (hs != 0x01 && hs != 0x02) throw ProtocolError("BX reply: unknown handle status " + std::to_string(hs));
        t.status = hs == 0x01 ? ToolReading::Status::ok : ToolReading::Status::missing;
        if (options & transforms) {
            if (t.status == ToolReading::Status::ok) {
                const std::uint8_t* f = c.take(32, "transform");
                t.q_wxyz = {lef32(f), lef32(f + 4), lef32(f + 8), lef32(f + 12)};
                t.t_mm = {lef32(f + 16), lef32(f + 20), lef32(f + 24)};
                t.rms_error_mm = lef32(f + 28);
                if (!std::isfinite(t.rms_error_mm) || t.rms_error_mm < 0) throw ProtocolError("BX reply: bad RMS error value");
                t.T_tracker_from_tool = pose_from_quaternion(t.q_wxyz, t.t_mm);
            }
            t.port_status = le32(c.take(4, "port status"));
            t.frame_number = le32(c.take(4, "frame number"));
        }
        if (options & tool_info) c.take(11, "tool and marker information");
        if (options & stray_active) {
            const std::uint8_t st = c.u8("stray active marker status");
            if (st == 0x01 || (st == 0x08 && (options & all_transforms))) c.take(12, "stray active marker");
        }
        if (options & tool_markers) {
            const std::size_t m = c.u8("marker count");
            c.take((m + 7) / 8 + m * 12, "tool markers");
        }
        r.tools.push_back(std::move(t));
    }
    if (options & stray_passive) {
        const std::size_t m = c.u8("stray marker count");
        r.stray_markers = m;
        c.take((m + 7) / 8 + m * 12, "stray markers");
        if (options & stray_extended) c.take((m + 1) / 2, "stray marker status");
    }
    r.system_status = le16(c.take(2, "system status"));
    if (c.left() != 0) throw ProtocolError("BX reply: " + std::to_string(c.left()) + " unexpected trailing bytes");
    return r;
}

TrackingReply parse_tx(std::string_view s, std::uint16_t options) {
    using namespace reply_option;
    if ((options & ~(transforms | all_transforms)) != 0 || !(options & transforms))
        throw ProtocolError("TX reply: only options 0001 and 0801 are supported");
    TrackingReply r;
    std::size_t i = 0;
    const std::size_t n = hex_field(s, i, 2, "handle count");
    for (std::size_t h = 0; h < n; ++h) {
        ToolReading t;
        t.handle = static_cast<std::uint8_t>(hex_field(s, i, 2, "handle"));
        const std::string_view rest = s.substr(i);
        if (rest.starts_with("UNOCCUPIED")) {
            t.status = ToolReading::Status::unoccupied;
            const auto lf = s.find('\n', i);
            if (lf == std::string_view::npos) throw ProtocolError("TX reply: no LF after UNOCCUPIED");
            i = lf + 1;
            r.tools.push_back(std::move(t));
            continue;
        }
        if (rest.starts_with("MISSING")) {
            t.status = ToolReading::Status::missing;
            i += 7;
        } else if (rest.starts_with("DISABLED")) {
            t.status = ToolReading::Status::disabled;
            i += 8;
        } else {
            t.status = ToolReading::Status::ok;
            for (int k = 0; k < 4; ++k) t.q_wxyz[k] = signed_field(s, i, 6, 10000.0, "quaternion");
            for (int k = 0; k < 3; ++k) t.t_mm[k] = signed_field(s, i, 7, 100.0, "translation");
            t.rms_error_mm = signed_field(s, i, 6, 10000.0, "error");
            if (t.rms_error_mm < 0) throw ProtocolError("TX reply: negative RMS error");
            t.T_tracker_from_tool = pose_from_quaternion(t.q_wxyz, t.t_mm);
        }
        t.port_status = hex_field(s, i, 8, "port status");
        t.frame_number = hex_field(s, i, 8, "frame number");
        if (i >= s.size() || s[i] != '\n') throw ProtocolError("TX reply: no LF after handle " + std::to_string(t.handle));
        ++i;
        r.tools.push_back(std::move(t));
    }
    r.system_status = static_cast<std::uint16_t>(hex_field(s, i, 4, "system status"));
    if (i != s.size()) throw ProtocolError("TX reply: unexpected trailing characters");
    return r;
}

std::vector<HandleInfo> parse_phsr(std::string_view s) {
    std::size_t i = 0;
    const std::size_t n = hex_field(s, i, 2, "PHSR handle count");
    if (s.size() != 2 + 5 * n) throw ProtocolError("PHSR reply: length " + std::to_string(s.size()) + " does not match " + std::to_string(n) + " handles");
    std::vector<HandleInfo> out;
    for (std::size_t k = 0; k < n; ++k) {
        HandleInfo h;
        h.handle = static_cast<std::uint8_t>(hex_field(s, i, 2, "PHSR handle"));
        h.status = static_cast<std::uint16_t>(hex_field(s, i, 3, "PHSR handle status"));
        out.push_back(h);
    }
    return out;
}

char comm_baud_code(int baud) {
    switch (baud) {
        case 9600: return '0';
        case 14400: return '1';
        case 19200: return '2';
        case 38400: return '3';
        case 57600: return '4';
        case 115200: return '5';
        case 921600: return '6';
        case 1228739: return '7';
        case 230400: return 'A';
        default: return 0;
    }
}
int comm_baud_rate(char code) {
    switch (code) {
        case '0': return 9600;
        case '1': return 14400;
        case '2': return 19200;
        case '3': return 38400;
        case '4': return 57600;
        case '5': return 115200;
        case '6': return 921600;
        case '7': return 1228739;
        case 'A': return 230400;
        default: return 0;
    }
}

std::string to_hex(std::span<const std::uint8_t> bytes) {
    static const char* d = "0123456789ABCDEF";
    std::string s;
    s.reserve(bytes.size() * 2);
    for (const auto b : bytes) {
        s.push_back(d[b >> 4]);
        s.push_back(d[b & 15]);
    }
    return s;
}

std::optional<std::vector<std::uint8_t>> from_hex(std::string_view hex) {
    if (hex.size() % 2) return std::nullopt;
    std::vector<std::uint8_t> out(hex.size() / 2);
    for (std::size_t i = 0; i < out.size(); ++i) {
        const int a = hex_value(hex[2 * i]), b = hex_value(hex[2 * i + 1]);
        if (a < 0 || b < 0) return std::nullopt;
        out[i] = static_cast<std::uint8_t>(a * 16 + b);
    }
    return out;
}

std::optional<std::uint32_t> parse_hex_u32(std::string_view hex) {
    if (hex.empty() || hex.size() > 8) return std::nullopt;
    std::uint32_t v = 0;
    for (const char c : hex) {
        const int d = hex_value(c);
        if (d < 0) return std::nullopt;
        v = (v << 4) | static_cast<std::uint32_t>(d);
    }
    return v;
}

}  // namespace cf::tracker
