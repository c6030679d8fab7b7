#include "core/durable/durable_io.hpp"

#include <fcntl.h>
#include <stdio.h>
#include <sys/stat.h>
#include <sys/uio.h>
#include <unistd.h>

#include <cerrno>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <new>
#include <regex>
#include <string>
#include <utility>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"

namespace vsm::core::durable {
namespace fs = std::filesystem;

namespace {

/// Direct I/O granularity: file offsets, lengths and buffer addresses in multiples of this (the
/// largest logical block size of common devices).
constexpr std::size_t kDirectBlock = 4096;
/// Files below this size are written through the page cache (XML and small arrays).
constexpr std::size_t kDirectMinimum = 64 * 1024;
/// Direct writes of a file in pieces (a hierarchy) are copied out into an aligned buffer this
/// large at a time: the thread keeps it.
constexpr std::size_t kDirectChunk = 4 * 1024 * 1024;

/// Closes a descriptor on every path out of a scope; close() errors of a descriptor that was only
/// read or synced carry no information.
class Descriptor {
 public:
  explicit Descriptor(int fd) : fd_(fd) {}
  ~Descriptor() {
    if (fd_ >= 0) {
      ::close(fd_);
    }
  }
  Descriptor(const Descriptor&) = delete;
  Descriptor& operator=(const Descriptor&) = delete;
  int get() const { return fd_; }
  void reset(int fd) {
    if (fd_ >= 0) {
      ::close(fd_);
    }
    fd_ = fd;
  }
  /// Closes now, reporting the error (a written file's close may report a write error).
  int close() { return ::close(std::exchange(fd_, -1)) == 0 ? 0 : errno; }

 private:
  int fd_;
};

/// Writes all of `bytes` to `fd`; 0 or the errno of the failure.
int writeAll(int fd, std::span<const std::byte> bytes) {
  std::size_t done = 0;
  while (done < bytes.size()) {
    const ssize_t n = ::write(fd, bytes.data() + done, bytes.size() - done);
    if (n < 0) {
      if (errno == EINTR) {
        continue;
      }
      return errno;
    }
    done += static_cast<std::size_t>(n);
  }
  return 0;
}

/// Writes the pieces one after the other, up to 1024 (Linux's IOV_MAX) a writev: a hierarchy at
/// 10^6 patches is 43 MB in ~5,500 pieces, and a write each cost ~30 ms of a merge job's publish
/// (8 KB writes against 1 MB ones, dd + fsync). 0 or the errno of the failure.
int writePieces(int fd, std::span<const std::span<const std::byte>> pieces) {
  constexpr std::size_t kBatch = 1024;
  std::vector<iovec> batch;
  std::size_t next = 0;
  for (;;) {
    while (batch.size() < kBatch && next < pieces.size()) {
      const std::span<const std::byte> piece = pieces[next++];
      if (!piece.empty()) {
        batch.push_back({const_cast<std::byte*>(piece.data()), piece.size()});
      }
    }
    if (batch.empty()) {
      return 0;
    }
    const ssize_t n = ::writev(fd, batch.data(), static_cast<int>(batch.size()));
    if (n < 0) {
      if (errno == EINTR) {
        continue;
      }
      return errno;
    }
    // Drop what was written: whole pieces, then the front of a piece written in part.
    auto left = static_cast<std::size_t>(n);
    std::size_t whole = 0;
    while (whole < batch.size() && left >= batch[whole].iov_len) {
      left -= batch[whole].iov_len;
      ++whole;
    }
    if (whole < batch.size()) {
      batch[whole].iov_base = static_cast<std::byte*>(batch[whole].iov_base) + left;
      batch[whole].iov_len -= left;
    }
    batch.erase(batch.begin(), batch.begin() + static_cast<std::ptrdiff_t>(whole));
  }
}

/// Writes the pieces' bytes to `fd`, opened with O_DIRECT: the whole blocks straight to the device,
/// from the one piece when it is aligned, else copied into the thread's aligned buffer up to
/// kDirectChunk at a time; then (O_DIRECT cleared) the rest through the page cache. 0 or the errno
/// of the failure; `refused` is set when the file system refuses direct writes (then everything
/// went through the page cache).
int writeDirect(int fd, std::span<const std::span<const std::byte>> pieces, bool& refused) {
  std::size_t total = 0;
  for (const std::span<const std::byte> piece : pieces) {
    total += piece.size();
  }
  const std::size_t whole = total / kDirectBlock * kDirectBlock;
  const bool inPlace =
      pieces.size() == 1 && reinterpret_cast<std::uintptr_t>(pieces[0].data()) % kDirectBlock == 0;
  const std::span<std::byte> buffer =
      inPlace ? std::span<std::byte>() : DraftWriter::threadBuffer(std::min(whole, kDirectChunk));
  std::size_t piece = 0;  // the cursor: what is not yet copied out begins at pieces[piece][offset]
  std::size_t offset = 0;
  std::size_t done = 0;
  std::span<const std::byte> pending;  // taken from the pieces, not yet written
  while (done < whole) {
    if (pending.empty()) {
      if (inPlace) {
        pending = pieces[0].first(whole);
        offset = whole;
      } else {
        const std::size_t chunk = std::min(whole - done, kDirectChunk);
        for (std::size_t filled = 0; filled < chunk;) {
          const std::size_t n = std::min(chunk - filled, pieces[piece].size() - offset);
          std::memcpy(buffer.data() + filled, pieces[piece].data() + offset, n);
          filled += n;
          offset += n;
          if (offset == pieces[piece].size()) {
            ++piece;
            offset = 0;
          }
        }
        pending = buffer.first(chunk);
      }
    }
    const ssize_t n = ::write(fd, pending.data(), pending.size());
    if (n < 0) {
      if (errno == EINTR) {
        continue;
      }
      if (errno == EINVAL && done == 0) {
        refused = true;
        pending = {};
        piece = 0;
        offset = 0;
        break;
      }
      return errno;
    }
    done += static_cast<std::size_t>(n);
    pending = pending.subspan(static_cast<std::size_t>(n));
    if (done % kDirectBlock != 0) {
      break;  // a short write off the block grid: the rest goes through the page cache
    }
  }
  const int flags = ::fcntl(fd, F_GETFL);
  if (flags < 0 || ::fcntl(fd, F_SETFL, flags & ~O_DIRECT) != 0) {
    return errno;
  }
  std::vector<std::span<const std::byte>> rest;
  rest.reserve(pieces.size() - piece + 1);
  rest.push_back(pending);
  if (piece < pieces.size()) {
    rest.push_back(pieces[piece].subspan(offset));
    rest.insert(rest.end(), pieces.begin() + static_cast<std::ptrdiff_t>(piece) + 1, pieces.end());
  }
  return writePieces(fd, rest);
}

/// Removes what has the name of a draft file about to be written or linked (nothing, usually).
void unlinkDraft(const fs::path& file) {
  if (::unlink(file.c_str()) != 0 && errno != ENOENT) {
    throwIoError("cannot replace", file.string(), errno);
  }
}

void syncPath(const fs::path& path, bool directory) {
  Descriptor fd(::open(path.c_str(), (directory ? O_RDONLY | O_DIRECTORY : O_RDONLY) | O_CLOEXEC));
  if (fd.get() < 0) {
    throwIoError("cannot open for fsync", path.string(), errno);
  }
  if (::fsync(fd.get()) != 0) {
    throwIoError("cannot fsync", path.string(), errno);
  }
}

}  // namespace

bool isTempFileName(std::string_view name) {
  static const std::regex pattern("\\..+\\.tmp-[0-9]+-[0-9]+");
  return std::regex_match(name.begin(), name.end(), pattern);
}

void syncDirectory(const fs::path& dir) {
  // The parent of a bare file name ("port".parent_path()) is empty: the working directory.
  syncPath(dir.empty() ? fs::path(".") : dir, true);
}

void syncFile(const fs::path& file) {
  syncPath(file, false);
}

bool createDirectory(const fs::path& dir, bool sync) {
  if (::mkdir(dir.c_str(), 0755) != 0) {
    const int errnum = errno;
    std::error_code ec;
    if (errnum == EEXIST && fs::is_directory(dir, ec)) {
      return false;
    }
    throwIoError("cannot create directory", dir.string(), errnum);
  }
  if (sync) {
    syncDirectory(dir.parent_path());
  }
  return true;
}

// ---- PendingFile -----------------------------------------------------------------------------

PendingFile::PendingFile(fs::path target, std::span<const std::byte> bytes)
    : PendingFile(std::move(target), std::span<const std::span<const std::byte>>(&bytes, 1)) {}

PendingFile::PendingFile(fs::path target, std::span<const std::span<const std::byte>> pieces)
    : target_(std::move(target)) {
  static std::atomic<unsigned> counter{0};
  temp_ = target_.parent_path() / ("." + target_.filename().string() + ".tmp-" +
                                   std::to_string(::getpid()) + "-" + std::to_string(counter++));
  // A large file (a hierarchy: 43 MB at 10^6 patches) goes to the device directly, as drafts do:
  // through the page cache its write took 40-190 ms of a merge's publish there (page allocation
  // and write-back), direct 35-50 ms, and the cache is left to what others read.
  std::size_t total = 0;
  for (const std::span<const std::byte> piece : pieces) {
    total += piece.size();
  }
  const bool direct = total >= kDirectMinimum;
  const auto create = [this](bool withDirect) {
    return ::open(temp_.c_str(),
                  O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC | (withDirect ? O_DIRECT : 0), 0644);
  };
  Descriptor fd(create(direct));
  if (fd.get() < 0 && direct && errno == EINVAL) {  // no O_DIRECT on this file system (tmpfs)
    ::unlink(temp_.c_str());                        // the refused open may have created it
    fd.reset(create(false));
  }
  if (fd.get() < 0) {
    throwIoError("cannot create", temp_.string(), errno);
  }
  auto fail = [&](std::string_view what, int errnum) {
    ::unlink(temp_.c_str());
    throwIoError(what, temp_.string(), errnum);
  };
  bool refused = false;
  if (const int errnum =
          direct ? writeDirect(fd.get(), pieces, refused) : writePieces(fd.get(), pieces);
      errnum != 0) {
    fail("cannot write", errnum);
  }
  if (::fsync(fd.get()) != 0) {
    fail("cannot fsync", errno);
  }
  if (const int errnum = fd.close(); errnum != 0) {
    fail("cannot close", errnum);
  }
}

PendingFile::~PendingFile() {
  if (!committed_) {
    ::unlink(temp_.c_str());
  }
}

void PendingFile::commit() {
  struct stat staged {};
  const bool stagedKnown = ::stat(temp_.c_str(), &staged) == 0;
  if (::rename(temp_.c_str(), target_.c_str()) != 0) {
    const int errnum = errno;
    // An error does not prove the rename was not applied: over NFS a retransmitted rename that
    // the server applied the first time reports ENOENT. Decided by looking: when the target is
    // the staged file (same device and inode) and the temporary name is gone, it committed.
    struct stat target {};
    if (stagedKnown && ::stat(target_.c_str(), &target) == 0 && target.st_dev == staged.st_dev &&
        target.st_ino == staged.st_ino && ::access(temp_.c_str(), F_OK) != 0 && errno == ENOENT) {
      log::warn("rename into " + target_.string() + " reported " + std::strerror(errnum) +
                " but was applied (the target is the renamed file): committed");
      committed_ = true;
      return;
    }
    ::unlink(temp_.c_str());
    committed_ = true;  // nothing left to remove
    throwIoError("cannot rename into", target_.string(), errnum);
  }
  committed_ = true;
}

void writeFileAtomically(const fs::path& target, std::span<const std::byte> bytes) {
  PendingFile(target, bytes).commit();
  syncDirectory(target.parent_path());
}

void replaceFile(const fs::path& from, const fs::path& to) {
  if (::rename(from.c_str(), to.c_str()) != 0) {
    throwIoError("cannot rename into", to.string(), errno);
  }
  syncDirectory(to.parent_path());
}

// ---- DraftWriter -----------------------------------------------------------------------------

std::span<std::byte> DraftWriter::threadBuffer(std::size_t bytes) {
  // Allocating one buffer per file would fault in and zero fresh pages every time; a thread keeps
  // the largest file it wrote.
  struct Buffer {
    std::byte* data = nullptr;
    std::size_t capacity = 0;
    ~Buffer() { std::free(data); }
  };
  thread_local Buffer buffer;
  if (buffer.capacity < bytes) {
    std::free(buffer.data);
    buffer.capacity = (bytes + kDirectBlock - 1) / kDirectBlock * kDirectBlock;
    buffer.data = static_cast<std::byte*>(std::aligned_alloc(kDirectBlock, buffer.capacity));
    if (buffer.data == nullptr) {
      buffer.capacity = 0;
      throw std::bad_alloc();
    }
  }
  return {buffer.data, bytes};
}

void DraftWriter::write(const fs::path& file, std::span<const std::byte> bytes) {
  // Large files go to the device directly: that saves copying them into the page cache and
  // writing them back from there, and leaves the cache to what others read.
  const bool direct = bytes.size() >= kDirectMinimum && direct_.load();
  // Most drafts are new files (an import writes nothing else): create first, and unlink only
  // what had the name when that fails, which saves an unlink call a file.
  const auto create = [&file](bool withDirect) {
    return ::open(file.c_str(),
                  O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC | (withDirect ? O_DIRECT : 0), 0644);
  };
  Descriptor fd(create(direct));
  if (fd.get() < 0 && errno == EEXIST) {
    unlinkDraft(file);
    fd.reset(create(direct));
  }
  if (fd.get() < 0 && direct && errno == EINVAL) {  // no O_DIRECT on this file system (tmpfs)
    direct_ = false;
    unlinkDraft(file);  // the refused open may have created it
    fd.reset(create(false));
  }
  if (fd.get() < 0) {
    throwIoError("cannot create", file.string(), errno);
  }
  int errnum = 0;
  if (direct && direct_.load()) {
    bool refused = false;
    errnum = writeDirect(fd.get(), std::span<const std::span<const std::byte>>(&bytes, 1), refused);
    if (refused) {
      direct_ = false;  // writeDirect wrote it all through the page cache
    }
  } else {
    errnum = writeAll(fd.get(), bytes);
  }
  if (errnum == 0) {
    errnum = fd.close();
  }
  if (errnum != 0) {
    throwIoError("cannot write", file.string(), errnum);
  }
}

bool DraftWriter::link(const fs::path& existing, const fs::path& file) {
  unlinkDraft(file);
  if (::link(existing.c_str(), file.c_str()) == 0) {
    return true;
  }
  const int errnum = errno;
  if (errnum == EMLINK || errnum == EXDEV || errnum == EPERM || errnum == EOPNOTSUPP ||
      errnum == ENOENT) {
    return false;
  }
  throwIoError("cannot link", file.string(), errnum);
}

// ---- FileSystemSync --------------------------------------------------------------------------

FileSystemSync::FileSystemSync(const fs::path& dir) : dir_(dir) {
  fd_ = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (fd_ < 0) {
    throwIoError("cannot open for syncfs", dir.string(), errno);
  }
}

FileSystemSync::~FileSystemSync() {
  ::close(fd_);
}

void FileSystemSync::sync() {
  if (const int earlier = failed_.load(); earlier != 0) {
    throwIoError("an earlier syncfs failed; not retrying on", dir_.string(), earlier);
  }
  if (::syncfs(fd_) != 0) {
    const int errnum = errno;
    failed_ = errnum;
    throwIoError("cannot syncfs", dir_.string(), errnum);
  }
}

// ---- directories -----------------------------------------------------------------------------

void renameNoReplace(const fs::path& from, const fs::path& to) {
  if (::renameat2(AT_FDCWD, from.c_str(), AT_FDCWD, to.c_str(), RENAME_NOREPLACE) == 0) {
    return;
  }
  int errnum = errno;
  if (errnum == EINVAL || errnum == ENOSYS) {  // file system without RENAME_NOREPLACE
    std::error_code ec;
    if (fs::exists(fs::symlink_status(to, ec))) {
      errnum = EEXIST;
    } else if (::rename(from.c_str(), to.c_str()) == 0) {
      return;
    } else {
      errnum = errno;
    }
  }
  if (errnum == EEXIST || errnum == ENOTEMPTY) {
    throw Error(ErrorCode::Conflict, "output directory '" + to.string() + "' exists");
  }
  throwIoError("cannot rename '" + from.string() + "' to", to.string(), errnum);
}

}  // namespace vsm::core::durable
