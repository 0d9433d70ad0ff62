// Schema versions: fresh database, idempotent re-open, newer database refused, a failing
// migration rolled back as a whole, WAL and foreign keys on.
#include <sqlite3.h>

#include "db_test_util.hpp"
#include "migrations.hpp"

using namespace cf::db;
using namespace cfdbtest;

namespace {
int raw_user_version(const fs::path& db) {
    sqlite3* h = nullptr;
    sqlite3_open(db.c_str(), &h);
    sqlite3_stmt* s = nullptr;
    sqlite3_prepare_v2(h, "PRAGMA user_version", -1, &s, nullptr);
    sqlite3_step(s);
    const int v = sqlite3_column_int(s, 0);
    sqlite3_finalize(s);
    sqlite3_close(h);
    return v;
}
void raw_exec(const fs::path& db, const std::string& sql) {
    sqlite3* h = nullptr;
    ASSERT_EQ(sqlite3_open(db.c_str(), &h), SQLITE_OK);
    char* err = nullptr;
    const int rc = sqlite3_exec(h, sql.c_str(), nullptr, nullptr, &err);
    EXPECT_EQ(rc, SQLITE_OK) << (err ? err : "");
    sqlite3_free(err);
    sqlite3_close(h);
}
}  // namespace

TEST(DbMigrations, EmbeddedListIsNumberedWithoutGaps) {
    const auto& m = detail::embedded_migrations();
    ASSERT_GE(m.size(), 1u);
    for (std::size_t i = 0; i < m.size(); ++i) EXPECT_EQ(m[i].version, static_cast<int>(i) + 1) << m[i].name;
    EXPECT_STREQ(m[0].name, "0001_initial");
    EXPECT_NE(std::string(m[0].sql).find("CREATE TABLE audit_log"), std::string::npos);
}

TEST(DbMigrations, FreshStoreThenReopenIsIdempotent) {
    TempDir t;
    const fs::path dir = t.path / "store";
    std::int64_t case_id = 0;
    {
        auto s = CaseStore::open(dir, fast_options());
        EXPECT_EQ(s->schema_version(), CaseStore::latest_schema_version());
        EXPECT_TRUE(fs::is_directory(dir / "blobs"));
        case_id = s->create_case(std::nullopt, "first").id;
    }
    EXPECT_EQ(raw_user_version(dir / "cortexfuse.sqlite"), CaseStore::latest_schema_version());
    for (int i = 0; i < 2; ++i) {
        auto s = CaseStore::open(dir, fast_options());
        EXPECT_EQ(s->schema_version(), CaseStore::latest_schema_version());
        EXPECT_EQ(s->get_case(case_id).summary.title, "first");
        EXPECT_EQ(s->list_cases().size(), 1u);
    }
    // WAL is persistent in the file.
    sqlite3* h = nullptr;
    sqlite3_open((dir / "cortexfuse.sqlite").c_str(), &h);
    sqlite3_stmt* st = nullptr;
    sqlite3_prepare_v2(h, "PRAGMA journal_mode", -1, &st, nullptr);
    sqlite3_step(st);
    EXPECT_STREQ(reinterpret_cast<const char*>(sqlite3_column_text(st, 0)), "wal");
    sqlite3_finalize(st);
    sqlite3_close(h);
}

TEST(DbMigrations, EmptyExistingFileIsMigrated) {
    TempDir t;
    write_file(t.path / "s" / "cortexfuse.sqlite", "");
    auto s = CaseStore::open(t.path / "s", fast_options());
    EXPECT_EQ(s->schema_version(), CaseStore::latest_schema_version());
}

TEST(DbMigrations, NewerDatabaseIsRefused) {
    TempDir t;
    { auto s = CaseStore::open(t.path / "s", fast_options()); }
    raw_exec(t.path / "s" / "cortexfuse.sqlite", "PRAGMA user_version = 999");
    expect_store_error([&] { CaseStore::open(t.path / "s", fast_options()); }, StoreError::Kind::Incompatible,
                       "schema version 999 was written by a newer CortexFuse");
}

TEST(DbMigrations, NotADatabaseIsCorrupt) {
    TempDir t;
    write_file(t.path / "s" / "cortexfuse.sqlite", std::string(4096, 'x'));
    expect_store_error([&] { CaseStore::open(t.path / "s", fast_options()); }, StoreError::Kind::Corrupt,
                       "cortexfuse.sqlite");
}

TEST(DbMigrations, FailingMigrationIsRolledBackWhole) {
    TempDir t;
    sql::Db db((t.path / "m.sqlite").string());
    const std::vector<detail::Migration> good = {{1, "0001_a", "CREATE TABLE a (x INTEGER);"}};
    EXPECT_EQ(detail::migrate(db, good, "m"), 1);
    const std::vector<detail::Migration> bad = {
        {1, "0001_a", "CREATE TABLE a (x INTEGER);"},
        {2, "0002_b", "CREATE TABLE b (y INTEGER); INSERT INTO a VALUES (1); THIS IS NOT SQL;"}};
    expect_store_error([&] { detail::migrate(db, bad, "m"); }, StoreError::Kind::Invalid, "migration 0002_b");
    EXPECT_EQ(detail::user_version(db), 1);
    // Neither table b nor the row in a survived.
    auto st = db.prepare("SELECT count(*) FROM sqlite_master WHERE name = 'b'");
    st.step();
    EXPECT_EQ(st.i64(0), 0);
    auto st2 = db.prepare("SELECT count(*) FROM a");
    st2.step();
    EXPECT_EQ(st2.i64(0), 0);
    // Fixed, it applies; applying again is a no-op.
    const std::vector<detail::Migration> fixed = {{1, "0001_a", "CREATE TABLE a (x INTEGER);"},
                                                  {2, "0002_b", "CREATE TABLE b (y INTEGER);"}};
    EXPECT_EQ(detail::migrate(db, fixed, "m"), 2);
    EXPECT_EQ(detail::migrate(db, fixed, "m"), 2);
}

TEST(DbMigrations, GapsInTheListAreRefused) {
    TempDir t;
    sql::Db db((t.path / "m.sqlite").string());
    const std::vector<detail::Migration> gap = {{1, "0001_a", "SELECT 1;"}, {3, "0003_c", "SELECT 1;"}};
    expect_store_error([&] { detail::migrate(db, gap, "m"); }, StoreError::Kind::Invalid, "without gaps");
}
