#include "cortexfuse/db/blob_store.hpp"

#include <fcntl.h>
#include <sodium.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <vector>

#include "cortexfuse/db/error.hpp"
#include "fsutil.hpp"

namespace cf::db {

namespace fs = std::filesystem;
using K = StoreError::Kind;

namespace {

std::string hex(const unsigned char* p, std::size_t n) {
    static const char* d = "0123456789abcdef";
    std::string s(2 * n, '0');
    for (std::size_t i = 0; i < n; ++i) {
        s[2 * i] = d[p[i] >> 4];
        s[2 * i + 1] = d[p[i] & 15];
    }
    return s;
}

struct Sha256 {
    crypto_hash_sha256_state st;
    Sha256() { crypto_hash_sha256_init(&st); }
    void update(const void* p, std::size_t n) {
        crypto_hash_sha256_update(&st, static_cast<const unsigned char*>(p), n);
    }
    std::string final_hex() {
        unsigned char out[crypto_hash_sha256_BYTES];
        crypto_hash_sha256_final(&st, out);
        return hex(out, sizeof out);
    }
};

constexpr std::size_t kChunk = 1 << 20;

}  // namespace

BlobStore::BlobStore(fs::path root) : root_(std::move(root)) {
    if (sodium_init() < 0) throw StoreError(K::Io, "libsodium: initialisation failed");
    std::error_code ec;
    fs::create_directories(root_, ec);
    if (ec) throw StoreError(K::Io, root_.string() + ": cannot create the blobs folder: " + ec.message());
    root_ = fs::absolute(root_);
}

bool BlobStore::valid_hash(std::string_view s) {
    if (s.size() != 64) return false;
    for (char c : s)
        if (!((c >= '0' && c <= '9') || (c >= 'a' && c <= 'f'))) return false;
    return true;
}

fs::path BlobStore::path_of(const std::string& sha) const {
    if (!valid_hash(sha)) throw StoreError(K::Invalid, "blob '" + sha.substr(0, 80) + "': not a SHA-256 hex digest");
    return root_ / sha.substr(0, 2) / sha.substr(2);
}

BlobRef BlobStore::ref(const std::string& sha, std::int64_t size) const { return BlobRef{sha, size, path_of(sha)}; }

bool BlobStore::contains(const std::string& sha) const {
    std::error_code ec;
    return fs::is_regular_file(path_of(sha), ec);
}

std::string BlobStore::sha256_of(std::string_view bytes) {
    Sha256 h;
    h.update(bytes.data(), bytes.size());
    return h.final_hex();
}

std::string BlobStore::sha256_of_file(const fs::path& file) {
    fsu::Fd fd(::open(file.c_str(), O_RDONLY | O_CLOEXEC));
    if (fd.get() < 0)
        throw StoreError(errno == ENOENT ? K::NotFound : K::Io, file.string() + ": cannot open: " + std::strerror(errno));
    Sha256 h;
    std::vector<char> buf(kChunk);
    for (;;) {
        const ssize_t n = ::read(fd.get(), buf.data(), buf.size());
        if (n < 0) {
            if (errno == EINTR) continue;
            throw StoreError(K::Io, file.string() + ": read failed: " + std::strerror(errno));
        }
        if (n == 0) break;
        h.update(buf.data(), static_cast<std::size_t>(n));
    }
    return h.final_hex();
}

BlobRef BlobStore::commit_temp(const fs::path& temp, const std::string& sha, std::int64_t size) {
    const fs::path dir = root_ / sha.substr(0, 2);
    const fs::path dest = dir / sha.substr(2);
    std::error_code ec;
    if (fs::is_regular_file(dest, ec)) {
        // Dedupe: the same content is already there. Check it is intact; a damaged copy is
        // replaced by the good one we just wrote.
        bool intact = false;
        try {
            intact = sha256_of_file(dest) == sha;
        } catch (const StoreError&) {
        }
        if (intact) {
            fs::remove(temp, ec);
            return BlobRef{sha, size, dest};
        }
    }
    if (!fs::is_directory(dir, ec)) {
        if (::mkdir(dir.c_str(), 0755) != 0 && errno != EEXIST)
            throw StoreError(K::Io, dir.string() + ": cannot create the blob folder: " + std::strerror(errno));
        fsu::fsync_dir(root_);
    }
    if (::rename(temp.c_str(), dest.c_str()) != 0) {
        const int e = errno;
        fs::remove(temp, ec);
        throw StoreError(K::Io, dest.string() + ": cannot move the blob into place: " + std::strerror(e));
    }
    fsu::fsync_dir(dir);
    return BlobRef{sha, size, dest};
}

BlobRef BlobStore::put_bytes(std::string_view bytes) {
    const std::string sha = sha256_of(bytes);
    fsu::TempFile t(root_);
    t.write_all(bytes.data(), bytes.size());
    t.sync_close();
    return commit_temp(t.release(), sha, static_cast<std::int64_t>(bytes.size()));
}

BlobRef BlobStore::put_file(const fs::path& file) {
    std::error_code ec;
    const auto st = fs::status(file, ec);
    if (ec || !fs::exists(st)) throw StoreError(K::NotFound, file.string() + ": no such file");
    if (!fs::is_regular_file(st)) throw StoreError(K::Invalid, file.string() + ": not a regular file");
    fsu::Fd in(::open(file.c_str(), O_RDONLY | O_CLOEXEC));
    if (in.get() < 0) throw StoreError(K::Io, file.string() + ": cannot open: " + std::strerror(errno));
    fsu::TempFile t(root_);
    Sha256 h;
    std::vector<char> buf(kChunk);
    std::int64_t size = 0;
    for (;;) {
        const ssize_t n = ::read(in.get(), buf.data(), buf.size());
        if (n < 0) {
            if (errno == EINTR) continue;
            throw StoreError(K::Io, file.string() + ": read failed: " + std::strerror(errno));
        }
        if (n == 0) break;
        h.update(buf.data(), static_cast<std::size_t>(n));
        t.write_all(buf.data(), static_cast<std::size_t>(n));
        size += n;
    }
    t.sync_close();
    return commit_temp(t.release(), h.final_hex(), size);
}

void BlobStore::verify(const std::string& sha) const {
    const fs::path p = path_of(sha);
    std::error_code ec;
    if (!fs::is_regular_file(p, ec))
        throw StoreError(K::NotFound, p.string() + ": blob missing (content " + sha.substr(0, 12) + "...)");
    const std::string got = sha256_of_file(p);
    if (got != sha)
        throw StoreError(K::Corrupt, p.string() + ": blob is corrupt: its content hashes to " + got.substr(0, 16) +
                                         "..., its name says " + sha.substr(0, 16) + "...");
}

std::string BlobStore::read(const std::string& sha) const {
    const fs::path p = path_of(sha);
    fsu::Fd fd(::open(p.c_str(), O_RDONLY | O_CLOEXEC));
    if (fd.get() < 0)
        throw StoreError(errno == ENOENT ? K::NotFound : K::Io,
                         p.string() + ": cannot open the blob: " + std::strerror(errno));
    std::string out;
    std::vector<char> buf(kChunk);
    for (;;) {
        const ssize_t n = ::read(fd.get(), buf.data(), buf.size());
        if (n < 0) {
            if (errno == EINTR) continue;
            throw StoreError(K::Io, p.string() + ": read failed: " + std::strerror(errno));
        }
        if (n == 0) break;
        out.append(buf.data(), static_cast<std::size_t>(n));
    }
    const std::string got = sha256_of(out);
    if (got != sha)
        throw StoreError(K::Corrupt, p.string() + ": blob is corrupt: its content hashes to " + got.substr(0, 16) +
                                         "..., its name says " + sha.substr(0, 16) + "...");
    return out;
}

void BlobStore::copy_to(const std::string& sha, const fs::path& dest) const {
    const fs::path p = path_of(sha);
    fsu::Fd in(::open(p.c_str(), O_RDONLY | O_CLOEXEC));
    if (in.get() < 0)
        throw StoreError(errno == ENOENT ? K::NotFound : K::Io,
                         p.string() + ": cannot open the blob: " + std::strerror(errno));
    const fs::path dir = dest.parent_path().empty() ? fs::path(".") : dest.parent_path();
    fsu::TempFile t(dir);
    Sha256 h;
    std::vector<char> buf(kChunk);
    for (;;) {
        const ssize_t n = ::read(in.get(), buf.data(), buf.size());
        if (n < 0) {
            if (errno == EINTR) continue;
            throw StoreError(K::Io, p.string() + ": read failed: " + std::strerror(errno));
        }
        if (n == 0) break;
        h.update(buf.data(), static_cast<std::size_t>(n));
        t.write_all(buf.data(), static_cast<std::size_t>(n));
    }
    const std::string got = h.final_hex();
    if (got != sha)
        throw StoreError(K::Corrupt, p.string() + ": blob is corrupt: its content hashes to " + got.substr(0, 16) +
                                         "..., its name says " + sha.substr(0, 16) + "...");
    t.sync_close();
    const fs::path temp = t.release();
    if (::rename(temp.c_str(), dest.c_str()) != 0) {
        const int e = errno;
        std::error_code ec;
        fs::remove(temp, ec);
        throw StoreError(K::Io, dest.string() + ": cannot write: " + std::strerror(e));
    }
}

}  // namespace cf::db
