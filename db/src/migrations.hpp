#pragma once
// Versioned schema migrations: db/migrations/NNNN_name.sql, embedded at build time.
#include <string>
#include <vector>

#include "sqlite.hpp"

namespace cf::db::detail {

struct Migration {
    int version;       ///< NNNN of the file name; 1, 2, 3, ... without gaps
    const char* name;  ///< the file's stem
    const char* sql;
};

/// The migrations compiled into this binary (generated from db/migrations/*.sql).
const std::vector<Migration>& embedded_migrations();

/// Brings the database to the last of `migrations`: each one not yet applied runs in its own
/// transaction (BEGIN IMMEDIATE, its SQL, PRAGMA user_version = N, COMMIT), so a failing one
/// leaves the database at the previous version. Throws StoreError: Incompatible when the
/// database's user_version is newer than the last migration, Invalid when the list has gaps,
/// the error of the failing SQL otherwise. `what` names the database in messages.
/// Returns the version reached.
int migrate(sql::Db& db, const std::vector<Migration>& migrations, const std::string& what);

int user_version(sql::Db& db);

}  // namespace cf::db::detail
