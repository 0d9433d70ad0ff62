#pragma once
// A thin RAII layer over the SQLite C API: a connection, prepared statements, transactions.
// Hand-written (about 150 lines) rather than SQLiteCpp (libsqlitecpp-dev): we need the
// extended result codes to map every failure onto one StoreError kind with a message naming
// the statement's subject, BEGIN IMMEDIATE transactions, and nothing else; one dependency less
// on the cart. Not thread-safe by itself: CaseStore serialises access with its mutex.
#include <sqlite3.h>

#include <cstdint>
#include <optional>
#include <string>
#include <string_view>

#include "cortexfuse/db/error.hpp"

namespace cf::db::sql {

/// Throws StoreError for SQLite result `rc`, `context` saying what was being done.
[[noreturn]] void fail(sqlite3* db, int rc, const std::string& context);

class Stmt {
public:
    Stmt(sqlite3* db, std::string_view sql);
    ~Stmt();
    Stmt(const Stmt&) = delete;
    Stmt& operator=(const Stmt&) = delete;
    Stmt(Stmt&& o) noexcept : db_(o.db_), s_(o.s_), context_(std::move(o.context_)) { o.s_ = nullptr; }

    Stmt& bind(int i, std::int64_t v);
    Stmt& bind(int i, int v) { return bind(i, static_cast<std::int64_t>(v)); }
    Stmt& bind(int i, double v);
    Stmt& bind(int i, std::string_view v);
    Stmt& bind(int i, const char* v) { return bind(i, std::string_view(v)); }
    Stmt& bind(int i, const std::string& v) { return bind(i, std::string_view(v)); }
    Stmt& bind(int i, std::nullptr_t);
    template <class T>
    Stmt& bind(int i, const std::optional<T>& v) {
        return v ? bind(i, *v) : bind(i, nullptr);
    }
    /// Names what this statement is about in error messages ("case 12", ...).
    Stmt& context(std::string c) {
        context_ = std::move(c);
        return *this;
    }

    /// true: a row is available; false: done.
    bool step();
    /// Runs a statement that returns no rows.
    void run() {
        while (step()) {
        }
    }
    void reset();

    bool is_null(int col) const { return sqlite3_column_type(s_, col) == SQLITE_NULL; }
    std::int64_t i64(int col) const { return sqlite3_column_int64(s_, col); }
    double f64(int col) const { return sqlite3_column_double(s_, col); }
    std::string text(int col) const;
    std::optional<std::int64_t> opt_i64(int col) const {
        return is_null(col) ? std::nullopt : std::optional<std::int64_t>(i64(col));
    }
    std::optional<std::string> opt_text(int col) const {
        return is_null(col) ? std::nullopt : std::optional<std::string>(text(col));
    }

private:
    sqlite3* db_;
    sqlite3_stmt* s_ = nullptr;
    std::string context_;
};

class Db {
public:
    Db() = default;
    /// Opens (creating) the file; throws StoreError naming it.
    explicit Db(const std::string& path);
    ~Db();
    Db(const Db&) = delete;
    Db& operator=(const Db&) = delete;
    Db(Db&& o) noexcept : h_(o.h_) { o.h_ = nullptr; }

    sqlite3* get() const { return h_; }
    void exec(const std::string& sql, const std::string& context);
    Stmt prepare(std::string_view sql) { return Stmt(h_, sql); }
    std::int64_t last_id() const { return sqlite3_last_insert_rowid(h_); }
    int changes() const { return sqlite3_changes(h_); }

private:
    sqlite3* h_ = nullptr;
};

/// BEGIN IMMEDIATE (takes the write lock at once, so no busy-upgrade deadlock later);
/// rolls back in the destructor unless commit() was called.
class Tx {
public:
    explicit Tx(Db& db);
    ~Tx();
    Tx(const Tx&) = delete;
    Tx& operator=(const Tx&) = delete;
    void commit();

private:
    Db& db_;
    bool done_ = false;
};

}  // namespace cf::db::sql
