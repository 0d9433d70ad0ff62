#pragma once
// The content-addressed blob folder beside the database: every imported file (volume, photo,
// result) is stored once, named by the SHA-256 of its content: blobs/ab/cdef... (the first two
// hex digits are a folder, the other 62 the file name).
//
// Writes are durable before they are referenced: the content goes to a temporary file in the
// blobs folder, is fsync'ed, renamed to its hash path, and the folder is fsync'ed. A crash
// leaves either nothing or a complete blob (at worst an unreferenced one, which is harmless).
// Reads verify the content against its name and throw StoreError(Corrupt) naming the file.
//
// Thread contract: all methods are safe to call from several threads and processes at once
// (no shared state in the object; the file system's rename is the only synchronisation).
#include <cstdint>
#include <filesystem>
#include <string>
#include <string_view>

namespace cf::db {

struct BlobRef {
    std::string sha256;            ///< 64 lower-case hex digits
    std::int64_t size_bytes = 0;
    std::filesystem::path path;    ///< absolute path of the blob file
};

class BlobStore {
public:
    /// `root` is the blobs folder; created when missing. Throws StoreError(Io).
    explicit BlobStore(std::filesystem::path root);

    BlobRef put_bytes(std::string_view bytes);
    /// Streams the file in (any size). Throws StoreError(Io / NotFound / Invalid) naming `file`.
    BlobRef put_file(const std::filesystem::path& file);

    std::filesystem::path path_of(const std::string& sha256) const;
    BlobRef ref(const std::string& sha256, std::int64_t size_bytes) const;
    bool contains(const std::string& sha256) const;
    /// Re-hashes the file: throws StoreError(NotFound) when missing, (Corrupt) when its content
    /// does not hash to its name, both naming the file.
    void verify(const std::string& sha256) const;
    /// The content, verified.
    std::string read(const std::string& sha256) const;
    /// Copies the verified content to `dest` (written to a temporary file, then renamed).
    void copy_to(const std::string& sha256, const std::filesystem::path& dest) const;

    const std::filesystem::path& root() const { return root_; }
    static bool valid_hash(std::string_view s);
    /// SHA-256 of a file / of bytes, as lower-case hex.
    static std::string sha256_of_file(const std::filesystem::path& file);
    static std::string sha256_of(std::string_view bytes);

private:
    BlobRef commit_temp(const std::filesystem::path& temp, const std::string& sha, std::int64_t size);
    std::filesystem::path root_;
};

}  // namespace cf::db
