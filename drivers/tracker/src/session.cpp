#include "cortexfuse/drivers/tracker/session.hpp"

#include <algorithm>
#include <filesystem>
#include <fstream>
#include <future>
#include <iterator>

namespace cf::tracker {

namespace {
using namespace std::chrono_literals;
constexpr std::uint16_t kTrackOptions = reply_option::transforms | reply_option::all_transforms;  // 0801

void check_range(const char* name, std::int64_t v, std::int64_t lo, std::int64_t hi) {
    if (v < lo || v > hi)
        throw ConfigError(name, std::to_string(v) + " is out of range " + std::to_string(lo) + ".." + std::to_string(hi));
}

std::string hex2(unsigned v) { return crc_hex(static_cast<std::uint16_t>(v & 0xFF)).substr(2); }

// Firmware that needs TX (BX failed with 3+ tools): fact sheet §10 lesson 7.
bool firmware_needs_tx(const std::string& ver) {
    for (const char* s : {"Polaris Spectra Rev 006", "Polaris Spectra Rev 007", "Polaris Vicra Rev 007", "Polaris Vega 008"})
        if (ver.find(s) != std::string::npos) return true;
    return false;
}
}  // namespace

std::int64_t steady_ns() {
    return std::chrono::duration_cast<std::chrono::nanoseconds>(std::chrono::steady_clock::now().time_since_epoch()).count();
}

ToolDefinition load_tool_definition(const std::string& path, char priority) {
    std::ifstream in(path, std::ios::binary);
    if (!in) throw ConfigError(path, "cannot open the tool definition file");
    std::vector<std::uint8_t> bytes((std::istreambuf_iterator<char>(in)), std::istreambuf_iterator<char>());
    if (bytes.size() < 16 || bytes.size() > 2048)
        throw ConfigError(path, "tool definition is " + std::to_string(bytes.size()) + " bytes, expected 16..2048");
    if (!(bytes[0] == 'N' && bytes[1] == 'D' && bytes[2] == 'I' && bytes[3] == 0))
        throw ConfigError(path, "not an NDI tool definition (no \"NDI\\0\" signature)");
    if (priority != 'S' && priority != 'D' && priority != 'B') throw ConfigError(path, "PENA priority must be S, D or B");
    ToolDefinition t;
    t.name = std::filesystem::path(path).stem().string();
    t.rom = std::move(bytes);
    t.priority = priority;
    return t;
}

void SessionConfig::validate(bool serial) const {
    if (serial) {
        const auto rates = host_baud_rates();
        if (std::find(rates.begin(), rates.end(), baud) == rates.end()) {
            std::string list;
            for (int r : rates) list += (list.empty() ? "" : ", ") + std::to_string(r);
            throw ConfigError("baud " + std::to_string(baud), "not a rate the host can set and the device knows (" + list + ")");
        }
    }
    check_range("poll_interval_ms", poll_interval.count(), 2, 1000);
    check_range("reply_timeout_ms", reply_timeout.count(), 10, 5000);
    check_range("command_timeout_ms", command_timeout.count(), 50, 10000);
    check_range("init_timeout_ms", init_timeout.count(), 100, 30000);
    check_range("reset_timeout_ms", reset_timeout.count(), 100, 30000);
    check_range("gap_timeout_ms", gap_timeout.count(), 2, 1000);
    check_range("max_consecutive_corrupt", max_consecutive_corrupt, 1, 1000);
    check_range("stale_after_ms", stale_after.count(), 50, 10000);
    check_range("max_backoff_ms", max_backoff.count(), 10, 10000);
    check_range("max_consecutive_timeouts", max_consecutive_timeouts, 1, 100);
    check_range("link_silence_ms", link_silence.count(), 50, 10000);
    thread_priority.validate();
    if (tools.size() > 24) throw ConfigError("tools", "at most 24 tool definitions");
    for (const auto& t : tools) {
        if (t.rom.empty() || t.rom.size() > 2048) throw ConfigError("tool " + t.name, "definition must be 1..2048 bytes");
        if (t.priority != 'S' && t.priority != 'D' && t.priority != 'B') throw ConfigError("tool " + t.name, "priority must be S, D or B");
    }
}

const char* state_name(TrackerStatus::State s) {
    switch (s) {
        case TrackerStatus::State::stopped: return "stopped";
        case TrackerStatus::State::connecting: return "connecting";
        case TrackerStatus::State::resetting: return "resetting";
        case TrackerStatus::State::initialising: return "initialising";
        case TrackerStatus::State::loading_tools: return "loading_tools";
        case TrackerStatus::State::streaming: return "streaming";
        case TrackerStatus::State::recovering: return "recovering";
    }
    return "?";
}

TrackerSession::TrackerSession(std::unique_ptr<Transport> transport, SessionConfig config)
    : transport_(std::move(transport)), cfg_(std::move(config)) {
    cfg_.validate(transport_->is_serial());
    status_.transport = transport_->describe();
    latencies_ns_.reserve(1024);
    replies_ns_.reserve(1024);
}

TrackerSession::~TrackerSession() { stop(); }

void TrackerSession::set_frame_callback(std::function<void(const TrackerFrame&)> cb) { callback_ = std::move(cb); }

void TrackerSession::start() {
    if (thread_.joinable()) return;
    stop_ = false;
    // The driver thread sets its own priority first; start() returns once it has, so that the
    // caller can read (and log) the outcome in status().
    std::promise<void> prioritised;
    auto ready = prioritised.get_future();
    thread_ = std::thread([this, prioritised = std::move(prioritised)]() mutable {
        const ThreadPriorityResult pr = raise_thread_priority(cfg_.thread_priority);
        {
            std::lock_guard lk(mu_);
            status_.thread_priority = pr.describe();
            status_.thread_priority_note = pr.note;
        }
        prioritised.set_value();
        run();
    });
    ready.wait();
}

void TrackerSession::stop() {
    stop_ = true;
    cv_.notify_all();
    if (thread_.joinable()) thread_.join();
}

void TrackerSession::beep(int n) { beep_request_ = std::clamp(n, 1, 9); }

TrackerStatus TrackerSession::status() const {
    std::lock_guard lk(mu_);
    TrackerStatus s = status_;
    if (!latencies_ns_.empty()) {
        std::vector<std::int64_t> v = latencies_ns_;
        auto pct = [&](double p) {
            const std::size_t k = std::min(v.size() - 1, static_cast<std::size_t>(p * static_cast<double>(v.size())));
            std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
            return static_cast<double>(v[k]) / 1000.0;
        };
        s.latency_p50_us = pct(0.50);
        s.latency_p99_us = pct(0.99);
    }
    if (!replies_ns_.empty()) {
        std::vector<std::int64_t> v = replies_ns_;
        auto pct = [&](double p) {
            const std::size_t k = std::min(v.size() - 1, static_cast<std::size_t>(p * static_cast<double>(v.size())));
            std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(k), v.end());
            return static_cast<double>(v[k]) / 1000.0;
        };
        s.reply_p50_us = pct(0.50);
        s.reply_p99_us = pct(0.99);
    }
    const std::int64_t now = steady_ns();
    std::size_t recent = 0;
    for (auto t : frame_times_ns_) recent += (now - t <= 1'000'000'000) ? 1 : 0;
    s.frame_rate_hz = static_cast<double>(recent);
    return s;
}

std::optional<TrackerFrame> TrackerSession::latest() const {
    std::lock_guard lk(mu_);
    if (!latest_) return std::nullopt;
    TrackerFrame f = *latest_;
    const std::int64_t now = steady_ns();
    for (auto& t : f.tools) {
        const bool stale = t.last_ok_steady_ns == 0 || now - t.last_ok_steady_ns > std::chrono::nanoseconds(cfg_.stale_after).count();
        if (stale) {
            t.stale = true;
            t.T_tracker_from_tool.reset();
        }
    }
    return f;
}

std::optional<TrackerFrame> TrackerSession::wait_frame(std::uint64_t after, std::chrono::milliseconds timeout) const {
    std::unique_lock lk(mu_);
    if (!cv_.wait_for(lk, timeout, [&] { return (latest_ && latest_->sequence > after) || stop_.load(); })) return std::nullopt;
    if (!latest_ || latest_->sequence <= after) return std::nullopt;
    return latest_;
}

void TrackerSession::set_state(TrackerStatus::State s) {
    std::lock_guard lk(mu_);
    status_.state = s;
}

void TrackerSession::note_error(const std::string& e) {
    std::lock_guard lk(mu_);
    status_.last_error = e;
}

void TrackerSession::sync_decoder_counters() {
    const auto& c = decoder_.counters();
    std::lock_guard lk(mu_);
    status_.crc_errors = c.crc_errors;
    status_.resyncs = c.resyncs;
    status_.discarded_bytes = c.discarded_bytes;
    status_.requests = requests_;
    status_.wake_late_max_us = static_cast<double>(wake_late_max_ns_) / 1000.0;
    status_.callback_max_us = static_cast<double>(callback_max_ns_) / 1000.0;
}

bool TrackerSession::sleep_for(std::chrono::milliseconds d) {
    std::unique_lock lk(mu_);
    cv_.wait_for(lk, d, [&] { return stop_.load(); });
    return !stop_;
}

void TrackerSession::run() {
    auto backoff = 20ms;
    bool ever_open = false;
    int failed_setups = 0;
    while (!stop_) {
        try {
            if (!transport_->is_open()) {
                set_state(TrackerStatus::State::connecting);
                transport_->open();
                if (ever_open) {
                    std::lock_guard lk(mu_);
                    ++status_.reconnects;
                }
                ever_open = true;
                decoder_.clear();
            }
            setup();
            failed_setups = 0;
            backoff = 20ms;
            stream();
        } catch (const TransportError& e) {
            note_error(e.what());
            streaming_ = false;
            transport_->close();
            set_state(TrackerStatus::State::connecting);
            if (!sleep_for(backoff)) break;
            backoff = std::min(backoff * 2, cfg_.max_backoff);
        } catch (const std::exception& e) {  // Recover, ProtocolError during setup
            note_error(e.what());
            streaming_ = false;
            set_state(TrackerStatus::State::recovering);
            // TCP has no reset: a fresh connection is its recovery. On serial, reopen too when
            // setups keep failing (a stale descriptor after a re-plug gives no error).
            if (!transport_->is_serial() || ++failed_setups >= 3) {
                transport_->close();
                failed_setups = 0;
            }
            if (!sleep_for(backoff)) break;
            backoff = std::min(backoff * 2, cfg_.max_backoff);
        }
        sync_decoder_counters();
    }
    if (transport_->is_open()) shutdown_device();
    transport_->close();
    sync_decoder_counters();
    set_state(TrackerStatus::State::stopped);
    cv_.notify_all();
}

std::optional<Reply> TrackerSession::await_reply(std::chrono::milliseconds timeout, std::int64_t* receive_ns, bool* heard) {
    const auto deadline = std::chrono::steady_clock::now() + timeout;
    auto last_byte = std::chrono::steady_clock::now();
    std::uint8_t buf[4096];
    if (heard) *heard = false;
    for (;;) {
        const std::uint64_t crc_before = decoder_.counters().crc_errors;
        if (auto r = decoder_.next()) return r;
        const auto now = std::chrono::steady_clock::now();
        // A reply failed its CRC and nothing is pending: it is lost, do not wait for the deadline.
        if (heard && *heard && decoder_.counters().crc_errors > crc_before && decoder_.buffered() == 0) return std::nullopt;
        // A partial reply and no byte for gap_timeout: truncated. Drop it.
        if (decoder_.buffered() > 0 && now - last_byte >= cfg_.gap_timeout) {
            decoder_.clear();
            return std::nullopt;
        }
        const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - now);
        if (left.count() <= 0 || (stop_ && !shutting_down_)) return std::nullopt;
        auto wait = std::min(left, std::chrono::milliseconds(50));
        if (decoder_.buffered() > 0) wait = std::min(wait, cfg_.gap_timeout);
        const std::int64_t t_wait = steady_ns();
        const std::size_t n = transport_->read(buf, wait);
        if (n == 0) {  // woke at the timeout: how late (the thread waited for a core)
            const std::int64_t late = steady_ns() - t_wait - std::chrono::nanoseconds(wait).count();
            if (late > wake_late_max_ns_) wake_late_max_ns_ = late;
        }
        if (n > 0) {
            last_byte = std::chrono::steady_clock::now();
            if (heard) *heard = true;
            if (receive_ns) *receive_ns = steady_ns();
            decoder_.feed(std::span<const std::uint8_t>(buf, n));
        }
    }
}

std::string TrackerSession::command(const std::string& name, const std::string& params, std::chrono::milliseconds timeout) {
    transport_->flush_input();
    decoder_.clear();
    transport_->write(encode_command(name, params));
    for (;;) {
        auto r = await_reply(timeout, nullptr);
        sync_decoder_counters();
        if (stop_ && !shutting_down_) throw Recover("stopping");
        if (!r) {
            std::lock_guard lk(mu_);
            ++status_.timeouts;
            throw Recover(transport_->describe() + ": no reply to " + name + " within " + std::to_string(timeout.count()) + " ms");
        }
        if (r->kind != Reply::Kind::ascii) continue;  // a late BX reply from before: not ours
        const Status st = classify(r->text);
        if (st.kind == Status::Kind::error) {
            {
                std::lock_guard lk(mu_);
                ++status_.device_errors;
            }
            throw DeviceError(name + ": " + describe_status(st), st.code);
        }
        if (st.kind == Status::Kind::warning) {
            std::lock_guard lk(mu_);
            ++status_.warnings;
            status_.last_error = name + ": " + describe_status(st) + " (carried out)";
            return "OKAY";
        }
        return r->text;
    }
}

void TrackerSession::setup() {
    streaming_ = false;
    last_frame_number_.reset();
    const bool serial = transport_->is_serial();
    if (serial && cfg_.break_reset) {
        set_state(TrackerStatus::State::resetting);
        {
            std::lock_guard lk(mu_);
            ++status_.resets;
        }
        decoder_.clear();
        transport_->send_break();
        // The device beeps and sends RESET at 9600. Anything else (a late reply) is skipped.
        const auto deadline = std::chrono::steady_clock::now() + cfg_.reset_timeout;
        bool got_reset = false;
        while (!got_reset && std::chrono::steady_clock::now() < deadline && !stop_) {
            auto r = await_reply(std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now()), nullptr);
            if (!r) break;
            got_reset = r->kind == Reply::Kind::ascii && classify(r->text).kind == Status::Kind::reset;
        }
        if (!got_reset) {
            {
                std::lock_guard lk(mu_);
                ++status_.timeouts;
            }
            throw Recover(transport_->describe() + ": no RESET within " + std::to_string(cfg_.reset_timeout.count()) + " ms of the break");
        }
    }
    set_state(TrackerStatus::State::initialising);
    // INIT: ERROR0C while the unit boots -> retry with a pause until init_timeout.
    const auto init_deadline = std::chrono::steady_clock::now() + cfg_.init_timeout;
    for (;;) {
        try {
            command("INIT", "", cfg_.command_timeout);
            break;
        } catch (const DeviceError& e) {
            if (e.code != 0x0C || std::chrono::steady_clock::now() > init_deadline) throw;
            if (!sleep_for(200ms)) throw Recover("stopping");
        }
    }
    if (serial && cfg_.baud != transport_->baud()) {
        if (!transport_->can_set_baud(cfg_.baud)) throw ConfigError("baud " + std::to_string(cfg_.baud), "the host cannot set this rate");
        command("COMM", std::string(1, comm_baud_code(cfg_.baud)) + "0000", cfg_.command_timeout);
        // OKAY came at the old rate; the device switches, the host follows ~100 ms later.
        if (!sleep_for(100ms)) throw Recover("stopping");
        transport_->set_baud(cfg_.baud);
        transport_->flush_input();
    }
    const std::string ver = command("VER", "4", cfg_.command_timeout);
    const std::string api = command("APIREV", "", cfg_.command_timeout);
    use_tx_ = cfg_.reply_mode == SessionConfig::ReplyMode::tx ||
              (cfg_.reply_mode == SessionConfig::ReplyMode::automatic && firmware_needs_tx(ver));
    {
        std::lock_guard lk(mu_);
        status_.firmware = ver;
        status_.api_revision = api;
        status_.reply_mode = use_tx_ ? "TX" : "BX";
        status_.baud = transport_->baud();
    }

    set_state(TrackerStatus::State::loading_tools);
    for (const auto& h : parse_phsr(command("PHSR", "01", cfg_.command_timeout))) command("PHF", hex2(h.handle), cfg_.command_timeout);
    handle_names_.clear();
    std::vector<char> priorities;
    for (const auto& tool : cfg_.tools) {
        const std::string reply = command("PHRQ", "*********1****", cfg_.command_timeout);
        const auto handle = parse_hex_u32(reply);
        if (reply.size() != 2 || !handle) throw ProtocolError("PHRQ: unexpected reply \"" + reply + "\"");
        // PVWR in 64-byte chunks at byte addresses 0000, 0040, ...; the last chunk zero-padded.
        for (std::size_t off = 0; off < tool.rom.size(); off += 64) {
            std::uint8_t chunk[64] = {};
            std::copy_n(tool.rom.begin() + static_cast<std::ptrdiff_t>(off), std::min<std::size_t>(64, tool.rom.size() - off), chunk);
            const std::string addr = crc_hex(static_cast<std::uint16_t>(off));
            command("PVWR", hex2(*handle) + addr + to_hex(chunk), cfg_.command_timeout);
        }
        handle_names_.emplace_back(static_cast<std::uint8_t>(*handle), tool.name);
        priorities.push_back(tool.priority);
    }
    for (const auto& h : parse_phsr(command("PHSR", "02", cfg_.command_timeout))) command("PINIT", hex2(h.handle), cfg_.command_timeout);
    for (const auto& h : parse_phsr(command("PHSR", "03", cfg_.command_timeout))) {
        char prio = 'D';
        for (std::size_t i = 0; i < handle_names_.size(); ++i)
            if (handle_names_[i].first == h.handle) prio = priorities[i];
        command("PENA", hex2(h.handle) + prio, cfg_.command_timeout);
    }
    command("TSTART", "", cfg_.command_timeout);
    last_ok_ns_.assign(handle_names_.size(), 0);
    streaming_ = true;
    set_state(TrackerStatus::State::streaming);
}

void TrackerSession::stream() {
    const std::string request = encode_command(use_tx_ ? "TX" : "BX", "0801");
    int consecutive_failures = 0, consecutive_corrupt = 0;
    std::int64_t last_request_ns = 0;      // the newest request (its reply may come late)
    std::int64_t last_heard_ns = steady_ns();  // the newest byte from the device
    transport_->flush_input();
    auto next_poll = std::chrono::steady_clock::now();
    while (!stop_) {
        if (const int n = beep_request_.exchange(0)) {
            try {
                command("BEEP", std::to_string(n), cfg_.command_timeout);
            } catch (const Recover&) {
                // a lost BEEP reply is not worth a reset
            }
        }
        const auto now = std::chrono::steady_clock::now();
        if (next_poll > now && !sleep_for(std::chrono::duration_cast<std::chrono::milliseconds>(next_poll - now))) break;
        next_poll = std::chrono::steady_clock::now() + cfg_.poll_interval;

        // What came after the last deadline: a late reply is published (the link works, the
        // CPU or the kernel's tty worker was slow), anything else dropped, before asking again.
        if (last_request_ns && drain_late_reply(last_request_ns)) consecutive_failures = 0;
        decoder_.clear();
        const std::int64_t request_ns = steady_ns();
        transport_->write(request);
        ++requests_;
        last_request_ns = request_ns;
        std::int64_t receive_ns = 0;
        std::optional<Reply> r;
        bool heard = false, heard_any = false;
        // Skip replies of the wrong kind (stale bytes of an earlier command) until the deadline.
        const auto deadline = std::chrono::steady_clock::now() + cfg_.reply_timeout;
        for (;;) {
            const auto left = std::chrono::duration_cast<std::chrono::milliseconds>(deadline - std::chrono::steady_clock::now());
            if (left.count() <= 0) break;
            r = await_reply(left, &receive_ns, &heard);
            heard_any = heard_any || heard;
            if (!r) break;
            if (use_tx_ || r->kind == Reply::Kind::binary) break;
            const Status st = classify(r->text);
            if (st.kind == Status::Kind::error || st.kind == Status::Kind::reset) break;
            r.reset();
        }
        sync_decoder_counters();
        if (stop_) break;
        if (heard_any) last_heard_ns = steady_ns();
        if (!r && heard_any) {
            // Bytes came but no good reply (CRC error, truncated, garbage): the link is alive.
            {
                std::lock_guard lk(mu_);
                ++status_.lost_replies;
            }
            consecutive_failures = 0;
            if (++consecutive_corrupt >= cfg_.max_consecutive_corrupt)
                throw Recover(transport_->describe() + ": " + std::to_string(consecutive_corrupt) + " garbled tracking replies in a row (baud out of step?)");
            next_poll = std::chrono::steady_clock::now();  // ask again at once
            continue;
        }
        if (!r) {
            {
                std::lock_guard lk(mu_);
                ++status_.timeouts;
            }
            // Recover only when the device has also been silent for link_silence: a reply that
            // is merely late is read before the next request (drain_late_reply).
            if (++consecutive_failures >= cfg_.max_consecutive_timeouts &&
                steady_ns() - last_heard_ns >= std::chrono::nanoseconds(cfg_.link_silence).count())
                throw Recover(transport_->describe() + ": " + std::to_string(consecutive_failures) + " tracking requests without a reply (" +
                              std::to_string((steady_ns() - last_heard_ns) / 1'000'000) + " ms silent)");
            continue;
        }
        if (r->kind == Reply::Kind::ascii) {
            const Status st = classify(r->text);
            if (st.kind == Status::Kind::reset) throw Recover("device reset itself (RESET received while tracking)");
            if (st.kind == Status::Kind::error) {
                {
                    std::lock_guard lk(mu_);
                    ++status_.device_errors;
                    status_.last_error = std::string(use_tx_ ? "TX" : "BX") + ": " + describe_status(st);
                }
                // 0C (not tracking) / 10 (not initialised): the device lost its state (power blip).
                if (st.code == 0x0C || st.code == 0x10 || ++consecutive_failures >= cfg_.max_consecutive_timeouts)
                    throw Recover("device answered " + describe_status(st) + " while tracking");
                continue;
            }
        }
        TrackingReply tr;
        try {
            tr = r->kind == Reply::Kind::binary ? parse_bx(r->body, kTrackOptions) : parse_tx(r->text, kTrackOptions);
        } catch (const ProtocolError& e) {
            std::lock_guard lk(mu_);
            ++status_.protocol_errors;
            status_.last_error = e.what();
            continue;
        }
        consecutive_failures = 0;
        consecutive_corrupt = 0;
        publish(tr, receive_ns, request_ns, false);
        last_request_ns = 0;  // answered
    }
}

bool TrackerSession::drain_late_reply(std::int64_t request_ns) {
    std::uint8_t buf[4096];
    std::int64_t receive_ns = 0;
    bool published = false;
    for (int i = 0; i < 16; ++i) {  // bounded: a device babbling garbage cannot hold us here
        const std::size_t n = transport_->read(buf, std::chrono::milliseconds(0));
        if (n == 0) break;
        receive_ns = steady_ns();
        decoder_.feed(std::span<const std::uint8_t>(buf, n));
    }
    while (auto r = decoder_.next()) {
        if (use_tx_ ? r->kind != Reply::Kind::ascii : r->kind != Reply::Kind::binary) continue;
        if (use_tx_) {
            const auto st = classify(r->text);
            if (st.kind == Status::Kind::error || st.kind == Status::Kind::reset || st.kind == Status::Kind::warning) continue;
        }
        try {
            const TrackingReply tr = r->kind == Reply::Kind::binary ? parse_bx(r->body, kTrackOptions) : parse_tx(r->text, kTrackOptions);
            {
                std::lock_guard lk(mu_);
                ++status_.late_replies;
            }
            publish(tr, receive_ns, request_ns, true);
            published = true;
        } catch (const ProtocolError&) {
            // not a tracking reply we can use; dropped like any stale byte
        }
    }
    sync_decoder_counters();
    decoder_.clear();
    return published;
}

void TrackerSession::publish(const TrackingReply& r, std::int64_t receive_ns, std::int64_t request_ns, bool late) {
    const std::uint32_t fn = r.frame_number();
    if (last_frame_number_ && *last_frame_number_ == fn) {
        std::lock_guard lk(mu_);
        ++status_.duplicate_frames;  // polled faster than the frame rate: same data again
        record_round_trip(receive_ns - request_ns);
        return;
    }
    // Frame numbers increase; the difference in 32 bits is signed so that a wrap is not an
    // old frame. Within one setup an older frame is never published (a reply out of order).
    if (last_frame_number_ && static_cast<std::int32_t>(fn - *last_frame_number_) < 0) {
        std::lock_guard lk(mu_);
        ++status_.out_of_order;
        return;
    }
    last_frame_number_ = fn;
    TrackerFrame f;
    f.frame_number = fn;
    f.request_steady_ns = request_ns;
    f.late = late;
    // Across a recovery the device's counter normally runs on (then the frames lost during the
    // recovery count as missed); a counter that went back (a power cycle) starts afresh.
    if (last_published_frame_) {
        const std::int32_t d = static_cast<std::int32_t>(fn - *last_published_frame_);
        if (d > 1) f.frames_missed_before = static_cast<std::uint32_t>(d - 1);
    }
    last_published_frame_ = fn;
    f.system_status = r.system_status;
    f.receive_steady_ns = receive_ns;
    const std::int64_t stale_ns = std::chrono::nanoseconds(cfg_.stale_after).count();
    for (std::size_t i = 0; i < handle_names_.size(); ++i) {
        TrackedTool t;
        t.handle = handle_names_[i].first;
        t.name = handle_names_[i].second;
        const auto it = std::find_if(r.tools.begin(), r.tools.end(), [&](const ToolReading& x) { return x.handle == t.handle; });
        if (it != r.tools.end()) {
            t.status = it->status;
            t.port_status = it->port_status;
            t.out_of_volume = it->out_of_volume();
            t.partially_out_of_volume = it->partially_out_of_volume();
            if (it->status == ToolReading::Status::ok && it->T_tracker_from_tool) {
                t.T_tracker_from_tool = it->T_tracker_from_tool;  // from this reply only, never an older one
                t.rms_error_mm = it->rms_error_mm;
                last_ok_ns_[i] = receive_ns;
            }
        } else {
            t.status = ToolReading::Status::unoccupied;
        }
        t.last_ok_steady_ns = last_ok_ns_[i];
        t.stale = !t.T_tracker_from_tool && (last_ok_ns_[i] == 0 || receive_ns - last_ok_ns_[i] > stale_ns);
        f.tools.push_back(std::move(t));
    }
    {
        std::lock_guard lk(mu_);
        f.sequence = ++sequence_;
        f.publish_steady_ns = steady_ns();
        const std::int64_t lat = f.publish_steady_ns - receive_ns;
        if (latencies_ns_.size() < 1024) latencies_ns_.push_back(lat);
        else latencies_ns_[latency_next_++ % 1024] = lat;
        record_round_trip(receive_ns - request_ns);
        if (f.frames_missed_before > 0) {
            ++status_.frame_gaps;
            status_.frames_missed += f.frames_missed_before;
        }
        ++status_.frames;
        status_.last_frame_steady_ns = f.publish_steady_ns;
        frame_times_ns_.push_back(f.publish_steady_ns);
        while (!frame_times_ns_.empty() && f.publish_steady_ns - frame_times_ns_.front() > 1'000'000'000) frame_times_ns_.pop_front();
        latest_ = f;
    }
    cv_.notify_all();
    if (callback_) {
        const std::int64_t t = steady_ns();
        callback_(f);
        callback_max_ns_ = std::max(callback_max_ns_, steady_ns() - t);
    }
}

void TrackerSession::shutdown_device() {
    // Best effort: a clean device for the next session (fact sheet §4 steps 15-16).
    shutting_down_ = true;
    try {
        if (streaming_) command("TSTOP", "", cfg_.command_timeout);
        if (transport_->is_serial() && transport_->baud() != 9600) {
            command("COMM", "00000", cfg_.command_timeout);
            std::this_thread::sleep_for(100ms);
            transport_->set_baud(9600);
        }
    } catch (const std::exception& e) {
        note_error(std::string("shutdown: ") + e.what());
    }
    streaming_ = false;
    shutting_down_ = false;
}

}  // namespace cf::tracker

namespace cf::tracker {
void TrackerSession::record_round_trip(std::int64_t ns) {
    if (ns <= 0) return;
    if (replies_ns_.size() < 1024) replies_ns_.push_back(ns);
    else replies_ns_[reply_next_++ % 1024] = ns;
    status_.reply_max_us = std::max(status_.reply_max_us, static_cast<double>(ns) / 1000.0);
}
}  // namespace cf::tracker
