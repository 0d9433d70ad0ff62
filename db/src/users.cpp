// Users (argon2id password hashes through libsodium's crypto_pwhash_str) and sessions
// (random 256-bit tokens; only their BLAKE2b hash is stored, so a copy of the database does
// not hand out live sessions).
#include <sodium.h>

#include "store_impl.hpp"

namespace cf::db {

using K = StoreError::Kind;

namespace {

void validate_user_name(const std::string& name) {
    if (name.empty() || name.size() > 64) throw StoreError(K::Invalid, "user name must be 1..64 characters");
    for (char c : name)
        if (!((c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '.' || c == '_' || c == '-'))
            throw StoreError(K::Invalid, "user '" + name + "': name may hold only letters, digits, '.', '_', '-'");
}

void validate_password(const std::string& pw, const std::string& who) {
    if (pw.size() < 8 || pw.size() > 1024) throw StoreError(K::Invalid, who + ": password must be 8..1024 bytes");
}

std::string hash_password(const CaseStore::Impl& I, const std::string& pw) {
    char out[crypto_pwhash_STRBYTES];
    if (crypto_pwhash_str(out, pw.data(), pw.size(), I.opt.pwhash_opslimit, I.opt.pwhash_memlimit_bytes) != 0)
        throw StoreError(K::Io, "password hashing ran out of memory");
    return out;
}

std::string token_hash(const std::string& token) {
    unsigned char h[32];
    crypto_generichash(h, sizeof h, reinterpret_cast<const unsigned char*>(token.data()), token.size(), nullptr, 0);
    static const char* d = "0123456789abcdef";
    std::string s(64, '0');
    for (int i = 0; i < 32; ++i) {
        s[2 * i] = d[h[i] >> 4];
        s[2 * i + 1] = d[h[i] & 15];
    }
    return s;
}

User read_user(sql::Stmt& st) {
    User u;
    u.id = st.i64(0);
    u.name = st.text(1);
    u.role = role_from_string(st.text(2));
    u.created_utc = parse_utc(st.text(3));
    u.disabled = st.i64(4) != 0;
    return u;
}

}  // namespace

User CaseStore::create_user(const std::string& name, const std::string& password, Role role, const Actor& by) {
    validate_user_name(name);
    validate_password(password, "user '" + name + "'");
    const std::string hash = hash_password(*impl_, password);  // slow on purpose: outside the lock
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    {
        auto st = I.db.prepare("SELECT id FROM users WHERE name = ?");
        st.bind(1, name);
        if (st.step()) throw StoreError(K::Conflict, "user '" + name + "': the name is taken");
    }
    I.db.prepare("INSERT INTO users (name, role, password_hash, created_utc) VALUES (?,?,?,?)")
        .bind(1, name).bind(2, to_string(role)).bind(3, hash).bind(4, at)
        .run();
    const auto id = I.db.last_id();
    I.audit_row(by, "user.create", std::nullopt, {{"user_id", id}, {"name", name}, {"role", to_string(role)}}, at);
    tx.commit();
    return User{id, name, role, parse_utc(at), false};
}

std::vector<User> CaseStore::list_users() {
    std::lock_guard lk(impl_->mu);
    auto st = impl_->db.prepare("SELECT id, name, role, created_utc, disabled FROM users ORDER BY name");
    std::vector<User> out;
    while (st.step()) out.push_back(read_user(st));
    return out;
}

User CaseStore::get_user(std::int64_t id) {
    std::lock_guard lk(impl_->mu);
    auto st = impl_->db.prepare("SELECT id, name, role, created_utc, disabled FROM users WHERE id = ?");
    st.bind(1, id);
    if (!st.step()) throw StoreError(K::NotFound, "user " + std::to_string(id) + ": no such user");
    return read_user(st);
}

std::optional<User> CaseStore::verify_password(const std::string& name, const std::string& password) {
    std::optional<User> user;
    std::string hash;
    {
        std::lock_guard lk(impl_->mu);
        auto st = impl_->db.prepare("SELECT id, name, role, created_utc, disabled, password_hash FROM users WHERE name = ?");
        st.bind(1, name);
        if (st.step()) {
            user = read_user(st);
            hash = st.text(5);
        }
        if (!user && impl_->dummy_hash.empty()) impl_->dummy_hash = hash_password(*impl_, "not-a-password-" + random_hex(8));
        if (!user) hash = impl_->dummy_hash;
    }
    // Unknown names cost one verification too, so timing does not tell which names exist.
    const bool match = crypto_pwhash_str_verify(hash.c_str(), password.data(), password.size()) == 0;
    if (!user || !match || user->disabled) return std::nullopt;
    return user;
}

void CaseStore::set_password(std::int64_t user_id, const std::string& password, const Actor& by) {
    validate_password(password, "user " + std::to_string(user_id));
    const std::string hash = hash_password(*impl_, password);
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.db.prepare("UPDATE users SET password_hash = ? WHERE id = ?").bind(1, hash).bind(2, user_id).run();
    if (I.db.changes() == 0) throw StoreError(K::NotFound, "user " + std::to_string(user_id) + ": no such user");
    I.db.prepare("UPDATE sessions SET revoked = 1 WHERE user_id = ?").bind(1, user_id).run();
    I.audit_row(by, "user.password", std::nullopt, {{"user_id", user_id}}, at);
    tx.commit();
}

void CaseStore::set_user_disabled(std::int64_t user_id, bool disabled, const Actor& by) {
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    I.db.prepare("UPDATE users SET disabled = ? WHERE id = ?").bind(1, disabled ? 1 : 0).bind(2, user_id).run();
    if (I.db.changes() == 0) throw StoreError(K::NotFound, "user " + std::to_string(user_id) + ": no such user");
    if (disabled) I.db.prepare("UPDATE sessions SET revoked = 1 WHERE user_id = ?").bind(1, user_id).run();
    I.audit_row(by, disabled ? "user.disable" : "user.enable", std::nullopt, {{"user_id", user_id}}, at);
    tx.commit();
}

Session CaseStore::create_session(std::int64_t user_id, std::chrono::seconds ttl) {
    if (ttl < std::chrono::seconds(1) || ttl > std::chrono::hours(24 * 30))
        throw StoreError(K::Invalid, "session: ttl must be 1 s .. 30 days");
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const UtcTime now = I.opt.now_utc();
    const std::string at = format_utc(now);
    const UtcTime expires = now + std::chrono::duration_cast<std::chrono::milliseconds>(ttl);
    sql::Tx tx(I.db);
    User u;
    {
        auto st = I.db.prepare("SELECT id, name, role, created_utc, disabled FROM users WHERE id = ?");
        st.bind(1, user_id);
        if (!st.step()) throw StoreError(K::NotFound, "user " + std::to_string(user_id) + ": no such user");
        u = read_user(st);
    }
    if (u.disabled) throw StoreError(K::Conflict, "user '" + u.name + "': disabled, no session");
    const std::string token = random_hex(32);
    I.db.prepare("INSERT INTO sessions (token_hash, user_id, created_utc, expires_utc) VALUES (?,?,?,?)")
        .bind(1, token_hash(token)).bind(2, user_id).bind(3, at).bind(4, format_utc(expires))
        .run();
    const auto id = I.db.last_id();
    I.audit_row(Actor{u.name, u.id}, "session.create", std::nullopt, {{"session_id", id}}, at);
    tx.commit();
    return Session{id, token, u, now, expires};
}

std::optional<Session> CaseStore::check_session(const std::string& token) {
    if (!BlobStore::valid_hash(token)) return std::nullopt;  // 64 lower-case hex digits, like ours
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string now = format_utc(I.opt.now_utc());
    auto st = I.db.prepare(
        "SELECT u.id, u.name, u.role, u.created_utc, u.disabled, s.id, s.created_utc, s.expires_utc "
        "FROM sessions s JOIN users u ON u.id = s.user_id "
        "WHERE s.token_hash = ? AND s.revoked = 0 AND s.expires_utc > ? AND u.disabled = 0");
    st.bind(1, token_hash(token)).bind(2, now);
    if (!st.step()) return std::nullopt;
    Session s;
    s.user = read_user(st);
    s.id = st.i64(5);
    s.created_utc = parse_utc(st.text(6));
    s.expires_utc = parse_utc(st.text(7));
    return s;
}

void CaseStore::revoke_session(const std::string& token) {
    if (!BlobStore::valid_hash(token)) return;
    std::lock_guard lk(impl_->mu);
    auto& I = *impl_;
    const std::string at = I.now();
    sql::Tx tx(I.db);
    auto st = I.db.prepare("SELECT s.id, u.id, u.name FROM sessions s JOIN users u ON u.id = s.user_id WHERE s.token_hash = ?");
    st.bind(1, token_hash(token));
    if (!st.step()) return;
    const auto sid = st.i64(0);
    const Actor who{st.text(2), st.i64(1)};
    I.db.prepare("UPDATE sessions SET revoked = 1 WHERE id = ?").bind(1, sid).run();
    I.audit_row(who, "session.revoke", std::nullopt, {{"session_id", sid}}, at);
    tx.commit();
}

}  // namespace cf::db
