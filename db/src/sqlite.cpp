#include "sqlite.hpp"

namespace cf::db {

const char* to_string(StoreError::Kind kind) {
    switch (kind) {
        case StoreError::Kind::NotFound: return "not found";
        case StoreError::Kind::Conflict: return "conflict";
        case StoreError::Kind::Invalid: return "invalid";
        case StoreError::Kind::Corrupt: return "corrupt";
        case StoreError::Kind::Io: return "i/o";
        case StoreError::Kind::Busy: return "busy";
        case StoreError::Kind::Incompatible: return "incompatible";
    }
    return "?";
}

}  // namespace cf::db

namespace cf::db::sql {

void fail(sqlite3* db, int rc, const std::string& context) {
    const int primary = rc & 0xff;
    std::string msg = context + ": " + (db ? sqlite3_errmsg(db) : sqlite3_errstr(rc));
    using K = StoreError::Kind;
    K kind = K::Invalid;
    switch (primary) {
        case SQLITE_CONSTRAINT:
            // UNIQUE / PRIMARY KEY and the keep-as-recorded triggers: a conflict with what is
            // stored; CHECK / NOT NULL / FOREIGN KEY: a bad value that got past validation.
            kind = (rc == SQLITE_CONSTRAINT_CHECK || rc == SQLITE_CONSTRAINT_NOTNULL || rc == SQLITE_CONSTRAINT_FOREIGNKEY)
                       ? K::Invalid
                       : K::Conflict;
            break;
        case SQLITE_BUSY:
        case SQLITE_LOCKED: kind = K::Busy; break;
        case SQLITE_CORRUPT:
        case SQLITE_NOTADB: kind = K::Corrupt; break;
        case SQLITE_IOERR:
        case SQLITE_FULL:
        case SQLITE_CANTOPEN:
        case SQLITE_READONLY:
        case SQLITE_PERM:
        case SQLITE_NOMEM: kind = K::Io; break;
        default: kind = K::Invalid;
    }
    throw StoreError(kind, msg);
}

Stmt::Stmt(sqlite3* db, std::string_view sqltext) : db_(db) {
    const int rc = sqlite3_prepare_v2(db, sqltext.data(), static_cast<int>(sqltext.size()), &s_, nullptr);
    if (rc != SQLITE_OK) fail(db, rc, "preparing SQL '" + std::string(sqltext.substr(0, 60)) + "'");
}

Stmt::~Stmt() { sqlite3_finalize(s_); }

Stmt& Stmt::bind(int i, std::int64_t v) {
    if (int rc = sqlite3_bind_int64(s_, i, v); rc != SQLITE_OK) fail(db_, rc, "binding a value");
    return *this;
}
Stmt& Stmt::bind(int i, double v) {
    if (int rc = sqlite3_bind_double(s_, i, v); rc != SQLITE_OK) fail(db_, rc, "binding a value");
    return *this;
}
Stmt& Stmt::bind(int i, std::string_view v) {
    if (int rc = sqlite3_bind_text64(s_, i, v.data(), v.size(), SQLITE_TRANSIENT, SQLITE_UTF8); rc != SQLITE_OK)
        fail(db_, rc, "binding a value");
    return *this;
}
Stmt& Stmt::bind(int i, std::nullptr_t) {
    if (int rc = sqlite3_bind_null(s_, i); rc != SQLITE_OK) fail(db_, rc, "binding a value");
    return *this;
}

bool Stmt::step() {
    const int rc = sqlite3_step(s_);
    if (rc == SQLITE_ROW) return true;
    if (rc == SQLITE_DONE) return false;
    const std::string ctx = context_.empty() ? std::string("running SQL '") + std::string(sqlite3_sql(s_)).substr(0, 60) + "'"
                                             : context_;
    sqlite3_reset(s_);
    fail(db_, rc, ctx);
}

void Stmt::reset() {
    sqlite3_reset(s_);
    sqlite3_clear_bindings(s_);
}

std::string Stmt::text(int col) const {
    const auto* p = reinterpret_cast<const char*>(sqlite3_column_text(s_, col));
    const int n = sqlite3_column_bytes(s_, col);
    return p ? std::string(p, static_cast<std::size_t>(n)) : std::string();
}

Db::Db(const std::string& path) {
    const int rc = sqlite3_open_v2(path.c_str(), &h_, SQLITE_OPEN_READWRITE | SQLITE_OPEN_CREATE | SQLITE_OPEN_NOMUTEX,
                                   nullptr);
    if (rc != SQLITE_OK) {
        std::string m = h_ ? sqlite3_errmsg(h_) : sqlite3_errstr(rc);
        sqlite3_close_v2(h_);
        h_ = nullptr;
        throw StoreError(StoreError::Kind::Io, path + ": cannot open the database: " + m);
    }
    sqlite3_extended_result_codes(h_, 1);
}

Db::~Db() { sqlite3_close_v2(h_); }

void Db::exec(const std::string& sqltext, const std::string& context) {
    char* err = nullptr;
    const int rc = sqlite3_exec(h_, sqltext.c_str(), nullptr, nullptr, &err);
    if (rc != SQLITE_OK) {
        std::string m = err ? err : sqlite3_errstr(rc);
        sqlite3_free(err);
        // Keep sqlite3_errmsg's text (the same) but the kind from rc.
        fail(h_, rc, context);
    }
}

Tx::Tx(Db& db) : db_(db) { db_.exec("BEGIN IMMEDIATE", "starting a write transaction"); }

Tx::~Tx() {
    if (!done_) sqlite3_exec(db_.get(), "ROLLBACK", nullptr, nullptr, nullptr);
}

void Tx::commit() {
    db_.exec("COMMIT", "committing a write transaction");
    done_ = true;
}

}  // namespace cf::db::sql
