#include "migrations.hpp"

namespace cf::db::detail {

int user_version(sql::Db& db) {
    auto st = db.prepare("PRAGMA user_version");
    st.step();
    return static_cast<int>(st.i64(0));
}

int migrate(sql::Db& db, const std::vector<Migration>& migrations, const std::string& what) {
    for (std::size_t i = 0; i < migrations.size(); ++i)
        if (migrations[i].version != static_cast<int>(i) + 1)
            throw StoreError(StoreError::Kind::Invalid, std::string("migration ") + migrations[i].name +
                                                            ": expected version " + std::to_string(i + 1) +
                                                            " (migrations must be numbered 1, 2, ... without gaps)");
    const int latest = static_cast<int>(migrations.size());
    for (const auto& m : migrations) {
        sql::Tx tx(db);
        // Read inside the write transaction: two processes opening a new store at once apply
        // each migration once.
        const int current = user_version(db);
        if (current > latest)
            throw StoreError(StoreError::Kind::Incompatible,
                             what + ": schema version " + std::to_string(current) +
                                 " was written by a newer CortexFuse (this one knows up to " + std::to_string(latest) +
                                 "); refusing to open it");
        if (current >= m.version) continue;  // tx rolls back (nothing written)
        db.exec(m.sql, what + ": migration " + m.name);
        db.exec("PRAGMA user_version = " + std::to_string(m.version), what + ": migration " + m.name);
        tx.commit();
    }
    const int v = user_version(db);
    if (v > latest)
        throw StoreError(StoreError::Kind::Incompatible,
                         what + ": schema version " + std::to_string(v) + " was written by a newer CortexFuse (this one knows up to " +
                             std::to_string(latest) + "); refusing to open it");
    return v;
}

}  // namespace cf::db::detail
