#pragma once
// Small POSIX helpers for durable files: an owned descriptor, a temporary file that is
// removed unless released, fsync of a folder. (std::filesystem has no fsync.)
#include <fcntl.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <string>

#include "cortexfuse/db/error.hpp"

namespace cf::db::fsu {

class Fd {
public:
    explicit Fd(int fd = -1) : fd_(fd) {}
    ~Fd() {
        if (fd_ >= 0) ::close(fd_);
    }
    Fd(const Fd&) = delete;
    Fd& operator=(const Fd&) = delete;
    int get() const { return fd_; }
    int release() {
        int f = fd_;
        fd_ = -1;
        return f;
    }

private:
    int fd_;
};

inline void fsync_dir(const std::filesystem::path& dir) {
    Fd fd(::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC));
    if (fd.get() < 0 || ::fsync(fd.get()) != 0)
        throw StoreError(StoreError::Kind::Io, dir.string() + ": cannot sync the folder: " + std::strerror(errno));
}

/// A new file `dir/.tmp-XXXXXX`; removed in the destructor unless release()d.
class TempFile {
public:
    explicit TempFile(const std::filesystem::path& dir) {
        std::string templ = (dir / ".tmp-XXXXXX").string();
        fd_ = ::mkostemp(templ.data(), O_CLOEXEC);
        if (fd_ < 0)
            throw StoreError(StoreError::Kind::Io,
                             dir.string() + ": cannot create a temporary file: " + std::strerror(errno));
        path_ = templ;
        ::fchmod(fd_, 0644);
    }
    ~TempFile() {
        if (fd_ >= 0) ::close(fd_);
        if (!path_.empty()) ::unlink(path_.c_str());
    }
    TempFile(const TempFile&) = delete;
    TempFile& operator=(const TempFile&) = delete;

    void write_all(const char* p, std::size_t n) {
        while (n > 0) {
            const ssize_t w = ::write(fd_, p, n);
            if (w < 0) {
                if (errno == EINTR) continue;
                throw StoreError(StoreError::Kind::Io, path_.string() + ": write failed: " + std::strerror(errno));
            }
            p += w;
            n -= static_cast<std::size_t>(w);
        }
    }
    /// fsync + close; throws on failure (a full disk shows up here at the latest).
    void sync_close() {
        if (::fsync(fd_) != 0)
            throw StoreError(StoreError::Kind::Io, path_.string() + ": fsync failed: " + std::strerror(errno));
        const int f = fd_;
        fd_ = -1;
        if (::close(f) != 0)
            throw StoreError(StoreError::Kind::Io, path_.string() + ": close failed: " + std::strerror(errno));
    }
    /// The file is the caller's from now on.
    std::filesystem::path release() {
        auto p = path_;
        path_.clear();
        return p;
    }
    const std::filesystem::path& path() const { return path_; }

private:
    int fd_ = -1;
    std::filesystem::path path_;
};

/// Writes `text` to `path` durably and atomically (temp + fsync + rename + fsync folder).
inline void write_file_durable(const std::filesystem::path& path, const std::string& text) {
    const auto dir = path.parent_path().empty() ? std::filesystem::path(".") : path.parent_path();
    TempFile t(dir);
    t.write_all(text.data(), text.size());
    t.sync_close();
    const auto temp = t.release();
    if (::rename(temp.c_str(), path.c_str()) != 0) {
        const int e = errno;
        ::unlink(temp.c_str());
        throw StoreError(StoreError::Kind::Io, path.string() + ": cannot write: " + std::strerror(e));
    }
    fsync_dir(dir);
}

}  // namespace cf::db::fsu
