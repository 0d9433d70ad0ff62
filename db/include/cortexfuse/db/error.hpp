#pragma once
// Typed errors of the case store. One style for the whole db layer: exceptions of one class,
// StoreError, with a kind the daemon maps to an HTTP status (NotFound 404, Conflict 409,
// Invalid 400/422, Corrupt and Io 500, Busy 503, Incompatible 500).
// Every message names the thing (a case id, a blob file, a zip entry, a JSON field) and the
// problem, in one line. Messages never contain patient names, MRNs or birth dates, so they
// may go to logs as they are.
#include <stdexcept>
#include <string>

namespace cf::db {

class StoreError : public std::runtime_error {
public:
    enum class Kind {
        NotFound,      ///< no such case, user, blob, ...
        Conflict,      ///< unique key taken, a workflow step out of order, the audit log is append-only
        Invalid,       ///< bad input: malformed JSON, a bad zip, a path that leaves its folder, a bad value
        Corrupt,       ///< stored data does not match its hash, or the database file is damaged
        Io,            ///< the file system failed (disk full, permission, ...)
        Busy,          ///< the database stayed locked past the busy timeout
        Incompatible,  ///< the database was written by a newer CortexFuse (schema version too high)
    };
    StoreError(Kind kind, const std::string& what) : std::runtime_error(what), kind_(kind) {}
    Kind kind() const { return kind_; }

private:
    Kind kind_;
};

const char* to_string(StoreError::Kind kind);

}  // namespace cf::db
