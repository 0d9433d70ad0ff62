// Drafts of unsaved marks through the daemon (docs/api/case-data.md "Drafts of unsaved marks";
// issue 7, 7.47): kept per case and per owner (the kiosk, each logged-in user), not a revision,
// audited once when kept and once when dropped, refused in words with nothing stored (every bad
// input, an unknown case, a reviewer), and still there after a restart of the daemon.
// The daemon runs in-process on a free port with the CPU renderer, without tracker or camera.
#include "daemon_fixture.hpp"

#include <gtest/gtest.h>

#include <string>

using nlohmann::json;
namespace fs = std::filesystem;

namespace {

using namespace cf::daemon_test;

json test_config(const fs::path& state) {
    json c = base_test_config(state, "cpu");
    c["tracker"]["enabled"] = false;
    c["camera"]["backend"] = "none";
    return c;
}

SharedDaemon& g_d = add_shared_daemon("cf_daemon_drafts", test_config);

/// A case with a 320x240 photo; its id and the photo's id.
struct CasePhoto {
    std::int64_t id = 0, photo_id = 0;
};
CasePhoto case_with_photo(const TestDaemon& d, const std::string& title) {
    CasePhoto c;
    c.id = d.new_case(title);
    const json cam{{"width", 320}, {"height", 240}, {"fx", 400.0}, {"fy", 400.0}, {"cx", 159.5}, {"cy", 119.5}};
    const Reply ph = d.post_raw("/api/cases/" + std::to_string(c.id) + "/photos?name=photo.png&camera=" + url_encode(cam.dump()),
                                png_bytes(cv::Mat(240, 320, CV_8UC3, cv::Scalar(40, 90, 160))));
    EXPECT_EQ(ph.status, 201) << ph.body;
    c.photo_id = ph.j.value("id", std::int64_t{0});
    return c;
}

std::string draft_path(std::int64_t id) { return "/api/cases/" + std::to_string(id) + "/drafts/marks"; }

/// A draft as the UI sends it: two landmark pairs (one dragged) and a three-point ROI.
json good_draft(std::int64_t photo_id, double u0 = 101.25) {
    return {{"photo_id", photo_id},
            {"saved_utc", "2026-11-27T15:42:10.123Z"},
            {"landmarks",
             {{"from_revision", nullptr},
              {"points",
               {{{"label", "L1"}, {"world_mm", {10.5, -20.0, 30.0}}, {"pixel", {u0, 80.5}}},
                {{"label", ""}, {"world_mm", {0.0, 80.0, 5.0}}, {"pixel", {-0.5, 239.5}}}}}}},
            {"roi", {{"from_revision", 2}, {"points", {{10.0, 10.0}, {200.0, 12.0}, {190.0, 150.0}}}}}};
}

/// The case's audit actions of drafts, in order.
std::vector<std::string> draft_audit(const TestDaemon& d, std::int64_t id) {
    const Reply a = d.get("/api/cases/" + std::to_string(id) + "/audit");
    EXPECT_EQ(a.status, 200) << a.body;
    std::vector<std::string> out;
    for (const auto& e : a.j.value("audit", json::array()))
        if (e.value("action", "").rfind("draft.", 0) == 0) out.push_back(e.value("action", "") + ":" + e.value("actor", ""));
    return out;
}

}  // namespace

TEST(MarksDrafts, KeptPerOwnerNotARevisionAndDroppedOnce) {
    TestDaemon& d = g_d.get();
    const CasePhoto c = case_with_photo(d, "drafts kept");
    const std::string p = draft_path(c.id);
    const std::string updated_before = d.get("/api/cases/" + std::to_string(c.id)).j.value("updated_utc", "");

    Reply r = d.get(p);
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_TRUE(r.j.at("draft").is_null());

    r = d.put(p, good_draft(c.photo_id));
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_TRUE(r.j.value("new", false));
    r = d.get(p);
    ASSERT_EQ(r.status, 200) << r.body;
    const json& k = r.j.at("draft");
    EXPECT_EQ(k.value("owner", ""), "kiosk");
    EXPECT_EQ(k.value("photo_id", std::int64_t{0}), c.photo_id);
    EXPECT_EQ(k.value("saved_utc", ""), "2026-11-27T15:42:10.123Z");
    EXPECT_EQ(k["landmarks"]["points"], good_draft(c.photo_id)["landmarks"]["points"]);
    EXPECT_TRUE(k["landmarks"]["from_revision"].is_null());
    EXPECT_EQ(k["roi"]["points"], good_draft(c.photo_id)["roi"]["points"]);
    EXPECT_EQ(k["roi"]["from_revision"], 2);

    // An update replaces it in place: no second audit line.
    json upd = good_draft(c.photo_id, 140.0);
    upd.erase("roi");
    upd["saved_utc"] = "2026-11-27T15:42:11.500Z";
    r = d.put(p, upd);
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_FALSE(r.j.value("new", true));
    r = d.get(p);
    EXPECT_EQ(r.j["draft"]["landmarks"]["points"][0]["pixel"][0], 140.0);
    EXPECT_FALSE(r.j["draft"].contains("roi"));
    EXPECT_EQ(r.j["draft"].value("saved_utc", ""), "2026-11-27T15:42:11.500Z");

    // Not a revision: no landmarks or ROI stored, the case not touched.
    EXPECT_EQ(d.get("/api/cases/" + std::to_string(c.id) + "/landmarks").status, 404);
    EXPECT_EQ(d.get("/api/cases/" + std::to_string(c.id) + "/roi").status, 404);
    EXPECT_EQ(d.get("/api/cases/" + std::to_string(c.id)).j.value("updated_utc", ""), updated_before);
    EXPECT_EQ(draft_audit(d, c.id), std::vector<std::string>{"draft.keep:kiosk"});

    // A technician's drafts are hers; the kiosk's are not given to her, nor hers to the kiosk.
    const std::string tina = d.token_of("tina", "technician");
    r = d.get(p, tina);
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_TRUE(r.j.at("draft").is_null()) << r.body;
    json hers = good_draft(c.photo_id, 55.0);
    hers.erase("landmarks");
    ASSERT_EQ(d.put(p, hers, tina).status, 200);
    EXPECT_EQ(d.get(p, tina).j["draft"].value("owner", "").rfind("user:", 0), 0u);
    EXPECT_FALSE(d.get(p, tina).j["draft"].contains("landmarks"));
    EXPECT_EQ(d.get(p).j["draft"]["landmarks"]["points"][0]["pixel"][0], 140.0);

    // A reviewer has none: every call refused in words, nothing changed.
    const std::string rex = d.token_of("rex", "reviewer");
    for (const auto& [m, body] : {std::pair<std::string, std::string>{"GET", ""}, {"PUT", good_draft(c.photo_id).dump()}, {"DELETE", ""}}) {
        r = d.request(m, p, body, "application/json", rex);
        EXPECT_EQ(r.status, 403) << m << " " << r.body;
        EXPECT_NE(r.body.find("role 'reviewer' may not " + m), std::string::npos) << r.body;
    }
    EXPECT_EQ(d.get(p).j["draft"]["landmarks"]["points"][0]["pixel"][0], 140.0);

    // Saved: dropped once (one audit line with the reason), then nothing to drop.
    r = d.del(p + "?reason=saved");
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_TRUE(r.j.value("dropped", false));
    EXPECT_TRUE(d.get(p).j.at("draft").is_null());
    r = d.del(p);
    ASSERT_EQ(r.status, 200) << r.body;
    EXPECT_FALSE(r.j.value("dropped", true));
    EXPECT_FALSE(d.get(p, tina).j.at("draft").is_null()) << "the kiosk's Save leaves tina's draft";
    ASSERT_TRUE(d.del(p + "?reason=discarded", tina).j.value("dropped", false));
    EXPECT_EQ(draft_audit(d, c.id), (std::vector<std::string>{"draft.keep:kiosk", "draft.keep:tina", "draft.drop:kiosk", "draft.drop:tina"}));
    const Reply a = d.get("/api/cases/" + std::to_string(c.id) + "/audit");
    int saved = 0, discarded = 0;
    for (const auto& e : a.j["audit"])
        if (e.value("action", "") == "draft.drop") (e["details"].value("reason", "") == "saved" ? saved : discarded)++;
    EXPECT_EQ(saved, 1);
    EXPECT_EQ(discarded, 1);
}

TEST(MarksDrafts, BadInputIsRefusedInWordsAndNothingIsStored) {
    TestDaemon& d = g_d.get();
    const CasePhoto c = case_with_photo(d, "drafts refused");
    const CasePhoto other = case_with_photo(d, "another case");
    const std::string p = draft_path(c.id);
    ASSERT_EQ(d.put(p, good_draft(c.photo_id)).status, 200);
    const json kept = d.get(p).j;
    const auto audit_before = draft_audit(d, c.id);

    auto with = [&](const std::function<void(json&)>& f) {
        json b = good_draft(c.photo_id, 77.0);
        f(b);
        return b.dump();
    };
    std::string labels(201, 'a');
    json many_lm = json::array(), many_roi = json::array(), big_lm = json::array(), big_roi = json::array();
    for (int i = 0; i < 1001; ++i) many_lm.push_back({{"label", "L"}, {"world_mm", {1, 2, 3}}, {"pixel", {1, 1}}});
    for (int i = 0; i < 10001; ++i) many_roi.push_back({1, 1});
    for (int i = 0; i < 1000; ++i) big_lm.push_back({{"label", std::string(200, 'x')}, {"world_mm", {1.123456789012345, 2.123456789012345, 3.123456789012345}}, {"pixel", {1, 1}}});
    for (int i = 0; i < 10000; ++i) big_roi.push_back({1.123456789012345, 2.123456789012345});
    struct Bad {
        std::string what, body;
        int status;
        std::string words;
    };
    const std::vector<Bad> bads = {
        {"not JSON", "{\"photo_id\": ", 400, "not valid JSON"},
        {"an array", "[1, 2]", 400, "must be a JSON object"},
        {"no body", "", 400, "must be a JSON object"},
        {"unknown field", with([](json& b) { b["colour"] = "red"; }), 400, "marks draft colour: unknown field"},
        {"no photo_id", with([](json& b) { b.erase("photo_id"); }), 400, "photo_id: must be the id of the photo"},
        {"photo_id text", with([](json& b) { b["photo_id"] = "1"; }), 400, "photo_id: must be the id"},
        {"another case's photo", with([&](json& b) { b["photo_id"] = other.photo_id; }), 404, "no such photo in case"},
        {"no saved_utc", with([](json& b) { b.erase("saved_utc"); }), 400, "saved_utc: must be the time of the edit"},
        {"bad saved_utc", with([](json& b) { b["saved_utc"] = "yesterday"; }), 400, "saved_utc 'yesterday': must be a UTC time"},
        {"nothing to keep", with([](json& b) { b.erase("landmarks"); b.erase("roi"); }), 400, "nothing to keep"},
        {"landmarks not an object", with([](json& b) { b["landmarks"] = json::array(); }), 400, "landmarks: must be {from_revision"},
        {"landmarks unknown field", with([](json& b) { b["landmarks"]["tension"] = 0; }), 400, "landmarks tension: unknown field"},
        {"landmark points missing", with([](json& b) { b["landmarks"].erase("points"); }), 400, "landmarks points: must be an array"},
        {"landmark not an object", with([](json& b) { b["landmarks"]["points"][1] = 5; }), 400, "points[1]: must be {label"},
        {"landmark unknown field", with([](json& b) { b["landmarks"]["points"][0]["x"] = 1; }), 400, "points[0] x: unknown field"},
        {"label missing", with([](json& b) { b["landmarks"]["points"][0].erase("label"); }), 400, "points[0] label: must be a string"},
        {"label control", with([](json& b) { b["landmarks"]["points"][0]["label"] = "L\x01"; }), 400, "label: holds control characters"},
        {"label long", with([&](json& b) { b["landmarks"]["points"][0]["label"] = labels; }), 400, "label: longer than 200 bytes"},
        {"world_mm short", with([](json& b) { b["landmarks"]["points"][0]["world_mm"] = {1, 2}; }), 400, "world_mm: must be [x, y, z]"},
        {"world_mm text", with([](json& b) { b["landmarks"]["points"][0]["world_mm"][2] = "3"; }), 400, "world_mm[2]: must be a number"},
        {"pixel missing", with([](json& b) { b["landmarks"]["points"][1].erase("pixel"); }), 400, "points[1] pixel: must be [u, v]"},
        {"pixel outside", with([](json& b) { b["landmarks"]["points"][0]["pixel"] = {320.0, 10.0}; }), 400, "is outside photo"},
        {"pixel negative", with([](json& b) { b["roi"]["points"][2] = {5.0, -0.6}; }), 400, "roi points[2]: [5.00, -0.60] is outside photo"},
        {"from_revision 0", with([](json& b) { b["landmarks"]["from_revision"] = 0; }), 400, "from_revision: must be null or a revision number"},
        {"from_revision text", with([](json& b) { b["roi"]["from_revision"] = "2"; }), 400, "roi from_revision: must be null"},
        {"roi not an object", with([](json& b) { b["roi"] = "all"; }), 400, "roi: must be {from_revision"},
        {"roi points not array", with([](json& b) { b["roi"]["points"] = 3; }), 400, "roi points: must be an array"},
        {"roi point short", with([](json& b) { b["roi"]["points"][0] = {1.0}; }), 400, "roi points[0]: must be [u, v]"},
        {"1001 landmarks", with([&](json& b) { b["landmarks"]["points"] = many_lm; }), 400, "1001 landmarks, at most 1000"},
        {"10001 roi points", with([&](json& b) { b["roi"]["points"] = many_roi; }), 400, "10001 points, at most 10000"},
        {"over 512 KiB", with([&](json& b) { b["landmarks"]["points"] = big_lm; b["roi"]["points"] = big_roi; }), 413, "are kept; save the marks instead"},
        {"over http.max_body_bytes", std::string(1 << 20, ' ') + "{}", 413, "http.max_body_bytes"},
    };
    for (const Bad& b : bads) {
        const Reply r = d.request("PUT", p, b.body);
        EXPECT_EQ(r.status, b.status) << b.what << ": " << r.body.substr(0, 300);
        EXPECT_NE(r.body.find(b.words), std::string::npos) << b.what << ": " << r.body.substr(0, 300);
        EXPECT_EQ(d.get(p).j, kept) << b.what << ": the kept draft changed";
    }
    // An unknown case, a case id that is not a number, a reason that is neither.
    Reply r = d.put(draft_path(999999), good_draft(c.photo_id));
    EXPECT_EQ(r.status, 404) << r.body;
    EXPECT_NE(r.body.find("case 999999: no such case"), std::string::npos) << r.body;
    EXPECT_EQ(d.get(draft_path(999999)).status, 404);
    EXPECT_EQ(d.del(draft_path(999999)).status, 404);
    EXPECT_EQ(d.get("/api/cases/x/drafts/marks").status, 400);
    r = d.del(p + "?reason=maybe");
    EXPECT_EQ(r.status, 400) << r.body;
    EXPECT_NE(r.body.find("reason 'maybe': must be saved or discarded"), std::string::npos) << r.body;
    EXPECT_EQ(d.get(p).j, kept);
    EXPECT_EQ(draft_audit(d, c.id), audit_before);
    // The registry lists the three calls (GET /api/endpoints).
    int listed = 0;
    const Reply eps = d.get("/api/endpoints");
    for (const auto& e : eps.j["endpoints"])
        if (e.value("path", "") == "/api/cases/{id}/drafts/marks") {
            ++listed;
            EXPECT_EQ(e.value("access", ""), "write");
        }
    EXPECT_EQ(listed, 3);
}

TEST(MarksDrafts, SurviveADaemonRestart) {
    const fs::path state = fs::temp_directory_path() / ("cf_daemon_drafts_restart_" + std::to_string(::getpid()));
    fs::remove_all(state);
    CasePhoto c;
    json kiosk_draft, tina_draft;
    {
        TestDaemon d(state, test_config(state));
        c = case_with_photo(d, "drafts across a restart");
        ASSERT_EQ(d.put(draft_path(c.id), good_draft(c.photo_id, 12.75)).status, 200);
        const std::string tina = d.token_of("tina", "technician");
        json hers = good_draft(c.photo_id, 99.0);
        hers.erase("roi");
        ASSERT_EQ(d.put(draft_path(c.id), hers, tina).status, 200);
        kiosk_draft = d.get(draft_path(c.id)).j;
        tina_draft = d.get(draft_path(c.id), tina).j;
    }
    {
        TestDaemon d(state, test_config(state));
        const Reply r = d.get(draft_path(c.id));
        ASSERT_EQ(r.status, 200) << r.body;
        EXPECT_EQ(r.j, kiosk_draft);
        EXPECT_EQ(r.j["draft"]["landmarks"]["points"][0]["pixel"][0], 12.75);
        const Reply t = d.get(draft_path(c.id), d.token_of("tina", "technician"));
        EXPECT_EQ(t.j, tina_draft);
        EXPECT_EQ(draft_audit(d, c.id), (std::vector<std::string>{"draft.keep:kiosk", "draft.keep:tina"}));
    }
    fs::remove_all(state);
}
