// Data-driven codec tests: protocol transcripts in tests/drivers/data/codec/*.json (bytes from
// the fact sheet, hex) with the decoded results they must give.
#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>

#include "cortexfuse/drivers/tracker/ndi_codec.hpp"

namespace fs = std::filesystem;
using namespace cf::tracker;
using nlohmann::json;

namespace {
const fs::path kData = fs::path(CF_DRIVERS_TEST_DATA) / "codec";

json load(const std::string& name) {
    std::ifstream in(kData / name);
    EXPECT_TRUE(in.good()) << name;
    return json::parse(in);
}

std::vector<std::uint8_t> hex(const std::string& s) {
    auto v = from_hex(s);
    EXPECT_TRUE(v.has_value()) << s;
    return v.value_or(std::vector<std::uint8_t>{});
}

const char* status_name(ToolReading::Status s) {
    switch (s) {
        case ToolReading::Status::ok: return "ok";
        case ToolReading::Status::missing: return "missing";
        case ToolReading::Status::disabled: return "disabled";
        case ToolReading::Status::unoccupied: return "unoccupied";
    }
    return "?";
}

void check_tracking(const TrackingReply& r, const json& e) {
    ASSERT_EQ(r.tools.size(), e["tools"].size());
    EXPECT_EQ(r.system_status, e["system_status"].get<int>());
    const double tol = e.value("exact", false) ? 1e-9 : 0.0;
    for (std::size_t i = 0; i < r.tools.size(); ++i) {
        const auto& t = r.tools[i];
        const auto& et = e["tools"][i];
        SCOPED_TRACE("tool " + std::to_string(i));
        EXPECT_EQ(t.handle, et["handle"].get<int>());
        EXPECT_STREQ(status_name(t.status), et["status"].get<std::string>().c_str());
        EXPECT_EQ(t.port_status, et["port_status"].get<std::uint32_t>());
        EXPECT_EQ(t.frame_number, et["frame"].get<std::uint32_t>());
        if (et.contains("q")) {
            ASSERT_TRUE(t.T_tracker_from_tool.has_value());
            for (int k = 0; k < 4; ++k) EXPECT_NEAR(t.q_wxyz[k], et["q"][k].get<double>(), tol);
            for (int k = 0; k < 3; ++k) EXPECT_NEAR(t.t_mm[k], et["t_mm"][k].get<double>(), tol);
            EXPECT_NEAR(t.rms_error_mm, et["rms_mm"].get<double>(), tol);
            // The transform maps the tool origin to t and is a rotation.
            EXPECT_TRUE(t.T_tracker_from_tool->translation().isApprox(t.t_mm, 1e-12) || t.t_mm.norm() == 0);
            EXPECT_NEAR(t.T_tracker_from_tool->linear().determinant(), 1.0, 1e-9);
        } else {
            EXPECT_FALSE(t.T_tracker_from_tool.has_value()) << "a tool that is not OK must carry no pose";
        }
        if (et.contains("out_of_volume")) { EXPECT_EQ(t.out_of_volume(), et["out_of_volume"].get<bool>()); }
        if (et.contains("partially_out")) { EXPECT_EQ(t.partially_out_of_volume(), et["partially_out"].get<bool>()); }
    }
}

void check_reply(const Reply& r, const json& e) {
    const std::string kind = e["kind"];
    if (kind == "bx") {
        ASSERT_EQ(r.kind, Reply::Kind::binary);
        const auto opt = static_cast<std::uint16_t>(*parse_hex_u32(e["options"].get<std::string>()));
        if (e.value("protocol_error", false)) {
            EXPECT_THROW(parse_bx(r.body, opt), ProtocolError);
            return;
        }
        check_tracking(parse_bx(r.body, opt), e);
        return;
    }
    ASSERT_EQ(r.kind, Reply::Kind::ascii);
    if (kind == "tx") {
        check_tracking(parse_tx(r.text, static_cast<std::uint16_t>(*parse_hex_u32(e["options"].get<std::string>()))), e);
    } else if (kind == "phsr") {
        const auto hs = parse_phsr(r.text);
        ASSERT_EQ(hs.size(), e["handles"].size());
        for (std::size_t i = 0; i < hs.size(); ++i) {
            EXPECT_EQ(hs[i].handle, e["handles"][i][0].get<int>());
            EXPECT_EQ(hs[i].status, e["handles"][i][1].get<int>());
        }
    } else {
        EXPECT_EQ(r.text, e["text"].get<std::string>());
        const Status s = classify(r.text);
        const std::string st = e["status"];
        const Status::Kind k = st == "okay" ? Status::Kind::okay : st == "error" ? Status::Kind::error
                             : st == "warning" ? Status::Kind::warning : st == "reset" ? Status::Kind::reset : Status::Kind::data;
        EXPECT_EQ(s.kind, k);
        if (e.contains("code")) { EXPECT_EQ(s.code, e["code"].get<int>()); }
    }
}

std::vector<std::string> case_files() {
    std::vector<std::string> out;
    for (const auto& de : fs::directory_iterator(kData))
        if (de.path().extension() == ".json" && de.path().filename() != "commands.json") out.push_back(de.path().filename().string());
    std::sort(out.begin(), out.end());
    return out;
}

class Transcript : public ::testing::TestWithParam<std::string> {};

TEST_P(Transcript, DecodesAsExpected) {
    const json c = load(GetParam());
    ReplyDecoder dec;
    std::vector<Reply> got;
    for (const auto& chunk : c["chunks"]) {
        dec.feed(hex(chunk.get<std::string>()));
        while (auto r = dec.next()) got.push_back(std::move(*r));
    }
    ASSERT_EQ(got.size(), c["expect"].size()) << "replies decoded from " << GetParam();
    for (std::size_t i = 0; i < got.size(); ++i) {
        SCOPED_TRACE("reply " + std::to_string(i));
        check_reply(got[i], c["expect"][i]);
    }
    const auto& k = c["counters"];
    const auto& n = dec.counters();
    if (k.contains("replies")) { EXPECT_EQ(n.replies, k["replies"].get<std::uint64_t>()); }
    if (k.contains("crc_errors")) { EXPECT_EQ(n.crc_errors, k["crc_errors"].get<std::uint64_t>()); }
    if (k.contains("resyncs")) { EXPECT_EQ(n.resyncs, k["resyncs"].get<std::uint64_t>()); }
    if (k.contains("min_crc_errors")) { EXPECT_GE(n.crc_errors, k["min_crc_errors"].get<std::uint64_t>()); }
    if (k.contains("min_resyncs")) { EXPECT_GE(n.resyncs, k["min_resyncs"].get<std::uint64_t>()); }
}

// The same transcript fed in every two-way split must decode the same.
TEST_P(Transcript, SplitAnywhereGivesTheSameReplies) {
    const json c = load(GetParam());
    std::vector<std::uint8_t> all;
    for (const auto& chunk : c["chunks"]) {
        const auto b = hex(chunk.get<std::string>());
        all.insert(all.end(), b.begin(), b.end());
    }
    auto decode = [&](std::size_t split) {
        ReplyDecoder dec;
        std::vector<std::string> out;
        dec.feed(std::span(all).first(split));
        while (auto r = dec.next()) out.push_back(r->kind == Reply::Kind::ascii ? r->text : to_hex(r->body));
        dec.feed(std::span(all).subspan(split));
        while (auto r = dec.next()) out.push_back(r->kind == Reply::Kind::ascii ? r->text : to_hex(r->body));
        return out;
    };
    const auto whole = decode(all.size());
    EXPECT_EQ(whole.size(), c["expect"].size());
    for (std::size_t s = 0; s < all.size(); s += 1 + all.size() / 97) EXPECT_EQ(decode(s), whole) << "split at " << s;
}

INSTANTIATE_TEST_SUITE_P(Codec, Transcript, ::testing::ValuesIn(case_files()),
                         [](const auto& param_info) { return fs::path(param_info.param).stem().string(); });

TEST(Crc16, CatalogueCheckValue) {
    EXPECT_EQ(crc16(std::string_view("123456789")), 0xBB3D);
    EXPECT_EQ(crc16(std::string_view("OKAY")), 0xA896);
    EXPECT_EQ(crc16(std::string_view("Info.Timeout.PINIT=5\n")), 0x96A7);
    // Running the CRC over data + its CRC (low byte first) gives 0 (fact sheet §2.3).
    const std::string d = "RESET";
    const std::uint16_t c = crc16(d);
    std::string dd = d + static_cast<char>(c & 0xFF) + static_cast<char>(c >> 8);
    EXPECT_EQ(crc16(dd), 0);
}

TEST(Commands, EncodeLikeTheFactSheet) {
    const json c = load("commands.json");
    for (const auto& e : c["commands"]) {
        const std::string wire = e["wire"];
        EXPECT_EQ(encode_command(e["name"].get<std::string>(), e["params"].get<std::string>()), wire);
        // The device side parses it back.
        const auto p = parse_command(std::string_view(wire).substr(0, wire.size() - 1));
        ASSERT_TRUE(p.has_value()) << wire;
        EXPECT_EQ(p->name, e["name"].get<std::string>());
        EXPECT_EQ(p->params, e["params"].get<std::string>());
        EXPECT_TRUE(p->had_crc && p->crc_ok) << wire;
    }
    EXPECT_EQ(encode_command_nocrc("INIT"), "INIT \r");
    const auto nocrc = parse_command("PHSR 01");
    ASSERT_TRUE(nocrc);
    EXPECT_FALSE(nocrc->had_crc);
    EXPECT_EQ(nocrc->params, "01");
    const auto bad = parse_command("INIT:E3A6");
    ASSERT_TRUE(bad);
    EXPECT_FALSE(bad->crc_ok);
    EXPECT_FALSE(parse_command("garbage!").has_value());
}

TEST(Status, ErrorAndWarningTexts) {
    EXPECT_EQ(describe_status(classify("ERROR0D")), "ERROR0D (no tool assigned to this port handle)");
    EXPECT_EQ(describe_status(classify("WARNING02")), "WARNING02 (the tool breaks the unique-geometry rules)");
    EXPECT_EQ(classify("ERROR0").kind, Status::Kind::data);
    EXPECT_EQ(classify("OKAYX").kind, Status::Kind::data);
}

TEST(Framing, DeviceSideRoundTrip) {
    ReplyDecoder dec;
    const std::vector<std::uint8_t> body = {1, 2, 3, 0x0D, 0xC4, 0xA5};  // CR and a start sequence inside the body
    dec.feed(frame_binary_reply(body));
    dec.feed(frame_ascii_reply("PHRQ reply 01"));
    auto a = dec.next();
    ASSERT_TRUE(a && a->kind == Reply::Kind::binary);
    EXPECT_EQ(a->body, body);
    auto b = dec.next();
    ASSERT_TRUE(b && b->kind == Reply::Kind::ascii);
    EXPECT_EQ(b->text, "PHRQ reply 01");
    EXPECT_FALSE(dec.next());
}

TEST(Framing, BaudCodes) {
    for (int baud : {9600, 14400, 19200, 38400, 57600, 115200, 921600, 1228739, 230400})
        EXPECT_EQ(comm_baud_rate(comm_baud_code(baud)), baud);
    EXPECT_EQ(comm_baud_code(12345), 0);
}
}  // namespace
