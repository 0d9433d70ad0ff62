// Drafts (docs/case-store.md "Drafts"): one per case, kind and owner, replaced in place, audited
// when first kept and when dropped, bad keys and bodies refused with nothing changed, not
// exported; and schema version 2 reached from a version-1 database with its data intact.
#include <sqlite3.h>

#include "db_test_util.hpp"
#include "migrations.hpp"

using namespace cf::db;
using namespace cfdbtest;
using nlohmann::json;

namespace {

std::size_t actions(CaseStore& s, std::int64_t case_id, const std::string& action) {
    std::size_t n = 0;
    for (const auto& e : s.audit_trail(case_id)) n += e.action == action;
    return n;
}

}  // namespace

TEST(DbDrafts, KeptPerOwnerReplacedInPlaceAuditedOnceAndNotExported) {
    TempDir t;
    auto clock = std::make_shared<FakeClock>();
    auto s = CaseStore::open(t.path / "store", fast_options(clock));
    const auto c = s->create_case(std::nullopt, "case with marks");
    const UtcTime updated = s->get_case(c.id).summary.updated_utc;
    const Actor kiosk{"kiosk", std::nullopt};
    const json body{{"photo_id", 1}, {"roi", {{"from_revision", nullptr}, {"points", {{1, 2}, {3, 4}, {5, 6}}}}}};
    const UtcTime edit_at = parse_utc("2026-11-27T15:42:10.123Z");

    EXPECT_FALSE(s->get_draft(c.id, "marks", "kiosk"));
    clock->advance(std::chrono::seconds(5));
    EXPECT_TRUE(s->keep_draft(c.id, "marks", "kiosk", body, edit_at, kiosk, {{"roi_points", 3}}));
    json body2 = body;
    body2["roi"]["points"].push_back({7, 8});
    EXPECT_FALSE(s->keep_draft(c.id, "marks", "kiosk", body2, edit_at + std::chrono::seconds(1), kiosk));
    EXPECT_TRUE(s->keep_draft(c.id, "marks", "user:3", body, edit_at, Actor{"tina", 3}));
    const auto d = s->get_draft(c.id, "marks", "kiosk");
    ASSERT_TRUE(d);
    EXPECT_EQ(d->body, body2);
    EXPECT_EQ(d->saved_utc, edit_at + std::chrono::seconds(1));
    EXPECT_EQ(d->updated_utc, clock->now);
    EXPECT_FALSE(d->user_id);
    EXPECT_EQ(s->get_draft(c.id, "marks", "user:3")->body, body);
    EXPECT_EQ(s->get_draft(c.id, "marks", "user:3")->user_id, 3);
    EXPECT_EQ(actions(*s, c.id, "draft.keep"), 2u);  // kiosk once (not per update), tina once
    EXPECT_EQ(s->audit_trail(c.id).back().details.value("kind", ""), "marks");
    EXPECT_EQ(s->get_case(c.id).summary.updated_utc, updated) << "a draft is not a change of the case";

    // Refused, nothing changed: unknown case, kind, owner, a body that is not an object or too big.
    const std::size_t audit_n = s->audit_trail(std::nullopt).size();
    expect_store_error([&] { s->keep_draft(999, "marks", "kiosk", body, edit_at); }, StoreError::Kind::NotFound, "case 999: no such case");
    expect_store_error([&] { s->keep_draft(c.id, "tags", "kiosk", body, edit_at); }, StoreError::Kind::Invalid, "kind 'tags': must be marks");
    expect_store_error([&] { s->keep_draft(c.id, "marks", "", body, edit_at); }, StoreError::Kind::Invalid, "owner: must be 1..80");
    expect_store_error([&] { s->keep_draft(c.id, "marks", "kiosk", json::array(), edit_at); }, StoreError::Kind::Invalid, "must be a JSON object");
    expect_store_error([&] { s->keep_draft(c.id, "marks", "kiosk", {{"x", std::string(kMaxDraftBytes, 'a')}}, edit_at); },
                       StoreError::Kind::Invalid, "at most 524288");
    expect_store_error([&] { s->drop_draft(c.id, "marks", "kiosk", "later"); }, StoreError::Kind::Invalid, "must be saved or discarded");
    EXPECT_EQ(s->get_draft(c.id, "marks", "kiosk")->body, body2);
    EXPECT_EQ(s->audit_trail(std::nullopt).size(), audit_n);

    // Not exported with the case (its store.json has no drafts).
    s->export_case_folder(c.id, t.path / "out");
    EXPECT_EQ(read_file(t.path / "out" / "store.json").find("draft"), std::string::npos);

    // Dropped: audited once with the reason; a second drop finds none and writes nothing.
    EXPECT_TRUE(s->drop_draft(c.id, "marks", "kiosk", "saved", kiosk));
    EXPECT_FALSE(s->drop_draft(c.id, "marks", "kiosk", "discarded", kiosk));
    EXPECT_FALSE(s->get_draft(c.id, "marks", "kiosk"));
    EXPECT_TRUE(s->get_draft(c.id, "marks", "user:3"));
    EXPECT_EQ(actions(*s, c.id, "draft.drop"), 1u);
    EXPECT_EQ(s->audit_trail(c.id).back().details.value("reason", ""), "saved");
    EXPECT_TRUE(s->check_integrity().ok);
}

TEST(DbMigrations, VersionOneDatabaseGainsDraftsWithItsDataKept) {
    TempDir t;
    const fs::path dir = t.path / "store";
    fs::create_directories(dir);
    {
        // A store as schema version 1 left it, with a case in it.
        sql::Db db((dir / "cortexfuse.sqlite").string());
        const std::vector<detail::Migration> v1(detail::embedded_migrations().begin(), detail::embedded_migrations().begin() + 1);
        ASSERT_EQ(detail::migrate(db, v1, "v1"), 1);
        db.exec("INSERT INTO cases (uid, title, created_utc, updated_utc) VALUES ('0123456789abcdef0123456789abcdef', 'from v1', "
                "'2026-11-01T10:00:00.000Z', '2026-11-01T10:00:00.000Z')",
                "v1 case");
    }
    auto s = CaseStore::open(dir, fast_options());
    EXPECT_EQ(s->schema_version(), CaseStore::latest_schema_version());
    EXPECT_GE(s->schema_version(), 2);
    const auto cases = s->list_cases();
    ASSERT_EQ(cases.size(), 1u);
    EXPECT_EQ(cases[0].title, "from v1");
    EXPECT_TRUE(s->keep_draft(cases[0].id, "marks", "kiosk", {{"photo_id", 1}}, parse_utc("2026-11-27T15:42:10.123Z")));
    EXPECT_TRUE(s->get_draft(cases[0].id, "marks", "kiosk"));
    EXPECT_TRUE(s->check_integrity().ok);
}
