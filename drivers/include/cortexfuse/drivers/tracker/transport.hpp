#pragma once
// Byte transports for the NDI combined API: a serial port (termios; Spectra/Vicra through
// RS-232 or a USB-serial adapter) and TCP (Vega, port 8765). Both carry the same bytes through
// the same codec (ndi_codec.hpp); the session (session.hpp) owns one transport.
//
// Thread contract: a transport is owned and used by one thread (the driver thread). Nothing
// here is thread-safe.
#include <chrono>
#include <cstdint>
#include <memory>
#include <span>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

namespace cf::tracker {

/// The link failed: open refused, EOF, EIO (USB unplug), connection reset. The message names
/// the transport ("serial /dev/ttyUSB0: ..." or "tcp 10.0.0.5:8765: ...").
class TransportError : public std::runtime_error {
public:
    explicit TransportError(const std::string& what) : std::runtime_error(what) {}
};

/// A configuration value out of range or a bad input file: "input: problem", one line.
class ConfigError : public std::runtime_error {
public:
    ConfigError(const std::string& input, const std::string& problem) : std::runtime_error(input + ": " + problem) {}
};

class Transport {
public:
    virtual ~Transport() = default;
    /// Opens the link (serial: 9600 8N1 raw, no handshake). Throws TransportError.
    virtual void open() = 0;
    virtual void close() = 0;
    virtual bool is_open() const = 0;
    /// Writes all bytes or throws TransportError.
    virtual void write(std::string_view bytes) = 0;
    /// Waits up to `timeout` for bytes; returns how many were read (0 on timeout). Throws
    /// TransportError when the link is gone.
    virtual std::size_t read(std::span<std::uint8_t> buf, std::chrono::milliseconds timeout) = 0;
    /// Drops whatever has arrived and not been read (stale replies from a timed-out command).
    virtual void flush_input() = 0;
    /// "serial /dev/ttyUSB0" or "tcp 127.0.0.1:8765".
    virtual std::string describe() const = 0;

    // Serial-only operations; a TCP transport has no baud rate and no break.
    virtual bool is_serial() const { return false; }
    /// Whether the host can really run the line at `baud` (only such rates are requested).
    virtual bool can_set_baud(int /*baud*/) const { return false; }
    /// Host side to `baud` 8N1, no handshake (after the device's OKAY to COMM).
    virtual void set_baud(int /*baud*/) {}
    virtual int baud() const { return 0; }
    /// Hardware reset: host to 9600 8N1, flush both queues, hold a break (fact sheet §1.2).
    virtual void send_break() {}
};

/// Baud rates a Linux host can set through termios and that the device's COMM knows. 19200
/// is left out on purpose: NDI's USB driver aliases it to 1.2 Mbaud (fact sheet §1.1).
std::vector<int> host_baud_rates();

/// Serial port at `path` (a tty, a USB-serial adapter, or a pty slave). Takes an advisory
/// lock so a second program on the same port is reported as "port busy".
std::unique_ptr<Transport> make_serial_transport(std::string path);
/// TCP client to host:port, TCP_NODELAY, keep-alive probing after 1 s idle (3 probes 1 s
/// apart) so a half-open connection is noticed even when the driver does not poll.
std::unique_ptr<Transport> make_tcp_transport(std::string host, std::uint16_t port,
                                              std::chrono::milliseconds connect_timeout = std::chrono::milliseconds(2000));

/// USB-serial adapters present now: /dev/serial/by-id/* (stable names, preferred), then
/// /dev/ttyUSB* and /dev/ttyACM* not already listed through a by-id link. `root` is for tests.
std::vector<std::string> discover_serial_ports(const std::string& root = "/dev");

/// "HOST:PORT" -> (host, port); throws ConfigError naming `what`. Port 0 ("any free port")
/// only when `allow_port_zero` (a server picking its port).
std::pair<std::string, std::uint16_t> parse_host_port(const std::string& text, const std::string& what, bool allow_port_zero = false);

}  // namespace cf::tracker
