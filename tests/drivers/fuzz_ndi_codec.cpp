// libFuzzer target for the NDI codec: arbitrary bytes, in arbitrary splits, through the reply
// decoder and every parser. Invariants: no crash, no sanitizer report, and whatever the decoder
// hands upward re-frames to bytes that decode to the same reply (its CRCs were right).
#include <cstdint>
#include <cstdlib>
#include <string_view>

#include "cortexfuse/drivers/tracker/ndi_codec.hpp"

using namespace cf::tracker;

namespace {
void exercise_parsers(std::span<const std::uint8_t> b) {
    for (std::uint16_t opt : {0x0001, 0x0801, 0x0003, 0x0005, 0x0009, 0x1001, 0x3801, 0x000F}) {
        try {
            const auto r = parse_bx(b, opt);
            for (const auto& t : r.tools)
                if (t.T_tracker_from_tool && !t.T_tracker_from_tool->matrix().allFinite()) std::abort();
        } catch (const ProtocolError&) {
        }
    }
    const std::string_view s(reinterpret_cast<const char*>(b.data()), b.size());
    for (std::uint16_t opt : {0x0001, 0x0801}) {
        try {
            parse_tx(s, opt);
        } catch (const ProtocolError&) {
        }
    }
    try {
        parse_phsr(s);
    } catch (const ProtocolError&) {
    }
    (void)describe_status(classify(s));
    (void)parse_command(s);
}
}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
    if (size == 0) return 0;
    const std::size_t chunk = 1 + data[0] % 23;
    ReplyDecoder dec;
    for (std::size_t i = 1; i < size; i += chunk) {
        dec.feed(std::span<const std::uint8_t>(data + i, std::min(chunk, size - i)));
        while (auto r = dec.next()) {
            ReplyDecoder again;
            if (r->kind == Reply::Kind::binary) {
                again.feed(frame_binary_reply(r->body));
                const auto r2 = again.next();
                if (!r2 || r2->body != r->body) std::abort();
                exercise_parsers(r->body);
            } else {
                for (char c : r->text)
                    if (!((c >= 0x20 && c <= 0x7E) || c == '\n')) std::abort();
                again.feed(frame_ascii_reply(r->text));
                const auto r2 = again.next();
                if (!r2 || r2->text != r->text) std::abort();
                exercise_parsers(std::span<const std::uint8_t>(reinterpret_cast<const std::uint8_t*>(r->text.data()), r->text.size()));
            }
        }
    }
    exercise_parsers(std::span<const std::uint8_t>(data, size));
    return 0;
}
