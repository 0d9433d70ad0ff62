// Users, argon2id password hashes, sessions with expiry (injected clock, no sleeping).
#include <sqlite3.h>

#include "db_test_util.hpp"

using namespace cf::db;
using namespace cfdbtest;

namespace {
struct UsersFixture : ::testing::Test {
    TempDir t;
    std::shared_ptr<FakeClock> clock = std::make_shared<FakeClock>();
    std::unique_ptr<CaseStore> s = CaseStore::open(t.path / "store", fast_options(clock));
};

std::string stored_hash(const CaseStore& s, const std::string& name) {
    sqlite3* h = nullptr;
    sqlite3_open(s.database_path().c_str(), &h);
    sqlite3_stmt* st = nullptr;
    sqlite3_prepare_v2(h, "SELECT password_hash FROM users WHERE name = ?", -1, &st, nullptr);
    sqlite3_bind_text(st, 1, name.c_str(), -1, SQLITE_TRANSIENT);
    std::string out;
    if (sqlite3_step(st) == SQLITE_ROW) out = reinterpret_cast<const char*>(sqlite3_column_text(st, 0));
    sqlite3_finalize(st);
    sqlite3_close(h);
    return out;
}
}  // namespace

TEST_F(UsersFixture, PasswordsAreArgon2idAndVerify) {
    const auto u = s->create_user("dr.house", "correct horse battery", Role::surgeon);
    EXPECT_EQ(u.role, Role::surgeon);
    const std::string h = stored_hash(*s, "dr.house");
    EXPECT_EQ(h.rfind("$argon2id$", 0), 0u) << h;
    EXPECT_EQ(h.find("correct horse"), std::string::npos);
    ASSERT_TRUE(s->verify_password("dr.house", "correct horse battery"));
    EXPECT_EQ(s->verify_password("dr.house", "correct horse battery")->id, u.id);
    EXPECT_FALSE(s->verify_password("dr.house", "correct horse batterY"));
    EXPECT_FALSE(s->verify_password("dr.house", ""));
    EXPECT_FALSE(s->verify_password("nobody", "correct horse battery"));
    // Same password, another user: another salt.
    s->create_user("wilson", "correct horse battery", Role::reviewer);
    EXPECT_NE(stored_hash(*s, "wilson"), h);
    s->set_password(u.id, "a new long password");
    EXPECT_FALSE(s->verify_password("dr.house", "correct horse battery"));
    EXPECT_TRUE(s->verify_password("dr.house", "a new long password"));
    const auto users = s->list_users();
    ASSERT_EQ(users.size(), 2u);
    EXPECT_EQ(users[0].name, "dr.house");
}

TEST_F(UsersFixture, BadUsersAreRefused) {
    using K = StoreError::Kind;
    s->create_user("tech", "password1", Role::technician);
    expect_store_error([&] { s->create_user("tech", "password2", Role::admin); }, K::Conflict, "user 'tech': the name is taken");
    expect_store_error([&] { s->create_user("a b", "password1", Role::admin); }, K::Invalid, "may hold only letters");
    expect_store_error([&] { s->create_user("", "password1", Role::admin); }, K::Invalid, "1..64 characters");
    expect_store_error([&] { s->create_user("short", "1234567", Role::admin); }, K::Invalid, "password must be 8..1024 bytes");
    expect_store_error([&] { role_from_string("root"); }, K::Invalid, "expected one of surgeon, technician, reviewer, admin");
    EXPECT_EQ(s->list_users().size(), 1u);
}

TEST_F(UsersFixture, SessionsExpireAndCanBeRevoked) {
    const auto u = s->create_user("rev", "reviewer-pass", Role::reviewer);
    const auto sess = s->create_session(u.id, std::chrono::minutes(30));
    EXPECT_EQ(sess.token.size(), 64u);
    EXPECT_EQ(sess.expires_utc, clock->now + std::chrono::minutes(30));
    auto ok = s->check_session(sess.token);
    ASSERT_TRUE(ok);
    EXPECT_EQ(ok->user.name, "rev");
    EXPECT_EQ(ok->user.role, Role::reviewer);
    EXPECT_TRUE(ok->token.empty());  // never handed out again

    clock->advance(std::chrono::minutes(30) - std::chrono::milliseconds(1));
    EXPECT_TRUE(s->check_session(sess.token));
    clock->advance(std::chrono::milliseconds(1));
    EXPECT_FALSE(s->check_session(sess.token));  // expired exactly at expires_utc

    const auto s2 = s->create_session(u.id, std::chrono::hours(8));
    EXPECT_TRUE(s->check_session(s2.token));
    s->revoke_session(s2.token);
    EXPECT_FALSE(s->check_session(s2.token));

    // Tokens that are not ours.
    EXPECT_FALSE(s->check_session(""));
    EXPECT_FALSE(s->check_session(std::string(64, '0')));
    EXPECT_FALSE(s->check_session("' OR 1=1 --"));
    std::string tampered = s2.token;
    tampered[0] = tampered[0] == 'a' ? 'b' : 'a';
    EXPECT_FALSE(s->check_session(tampered));
    // The database holds only token hashes.
    sqlite3* h = nullptr;
    sqlite3_open(s->database_path().c_str(), &h);
    sqlite3_stmt* st = nullptr;
    sqlite3_prepare_v2(h, "SELECT count(*) FROM sessions WHERE token_hash = ?", -1, &st, nullptr);
    sqlite3_bind_text(st, 1, s2.token.c_str(), -1, SQLITE_TRANSIENT);
    sqlite3_step(st);
    EXPECT_EQ(sqlite3_column_int(st, 0), 0);
    sqlite3_finalize(st);
    sqlite3_close(h);

    expect_store_error([&] { s->create_session(u.id, std::chrono::seconds(0)); }, StoreError::Kind::Invalid, "ttl");
    expect_store_error([&] { s->create_session(9999, std::chrono::seconds(10)); }, StoreError::Kind::NotFound, "user 9999");
}

TEST_F(UsersFixture, DisablingAUserEndsItsSessionsAndLogins) {
    const auto u = s->create_user("sur", "surgeon-pass", Role::surgeon);
    const auto sess = s->create_session(u.id, std::chrono::hours(1));
    s->set_user_disabled(u.id, true, Actor{"admin", std::nullopt});
    EXPECT_FALSE(s->check_session(sess.token));
    EXPECT_FALSE(s->verify_password("sur", "surgeon-pass"));
    expect_store_error([&] { s->create_session(u.id, std::chrono::hours(1)); }, StoreError::Kind::Conflict, "disabled");
    s->set_user_disabled(u.id, false);
    EXPECT_TRUE(s->verify_password("sur", "surgeon-pass"));
    EXPECT_FALSE(s->check_session(sess.token));  // revoked for good
    bool seen = false;
    for (const auto& e : s->audit_trail(std::nullopt))
        if (e.action == "user.disable" && e.actor == "admin") seen = true;
    EXPECT_TRUE(seen);
}
