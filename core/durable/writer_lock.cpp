#include "core/durable/writer_lock.hpp"

#include <errno.h>
#include <fcntl.h>
#include <sys/file.h>
#include <unistd.h>

#include <string>

#include "core/common/error.hpp"

namespace vsm::core::durable {
namespace fs = std::filesystem;

namespace {

/// "vsmd pid 4242": what the holder writes into the lock file.
std::string holderLine() {
  return std::string(program_invocation_short_name) + " pid " + std::to_string(::getpid());
}

/// The holder as the lock file names it, for the message of a refused writer.
std::string describeHolder(int fd) {
  char text[256];
  const ssize_t n = ::pread(fd, text, sizeof text - 1, 0);
  std::string line(text, n > 0 ? static_cast<std::size_t>(n) : 0);
  if (const auto end = line.find('\n'); end != std::string::npos) {
    line.resize(end);
  }
  // "vsmd pid 4242" -> "vsmd (pid 4242)"; anything else (a holder that has not written its name
  // yet, a foreign file) is not echoed.
  const auto at = line.rfind(" pid ");
  if (at == std::string::npos || at == 0 || line.size() > 200 ||
      line.find_first_not_of("0123456789", at + 5) != std::string::npos) {
    return "another process";
  }
  for (const char c : line) {
    if (c < 0x20 || c > 0x7e) {
      return "another process";
    }
  }
  return line.substr(0, at) + " (pid " + line.substr(at + 5) + ")";
}

}  // namespace

std::unique_ptr<WriterLock> WriterLock::acquire(const fs::path& dir) {
  const fs::path file = dir / std::string(kFileName);
  const int fd = ::open(file.c_str(), O_RDWR | O_CREAT | O_CLOEXEC | O_NOFOLLOW, 0644);
  if (fd < 0) {
    throwIoError("cannot open the writer lock", file.string(), errno);
  }
  if (::flock(fd, LOCK_EX | LOCK_NB) != 0) {
    const int errnum = errno;
    if (errnum == EWOULDBLOCK) {
      const std::string holder = describeHolder(fd);
      ::close(fd);
      throw Error(ErrorCode::Conflict, "'" + dir.string() + "' is being written by " + holder +
                                           "; one writer per model at a time");
    }
    ::close(fd);
    throwIoError("cannot lock", file.string(), errnum);
  }
  // Who holds it, for the others' message. Not synced: after a crash the lock is free anyway.
  const std::string line = holderLine() + "\n";
  if (::ftruncate(fd, 0) != 0 ||
      ::pwrite(fd, line.data(), line.size(), 0) != static_cast<ssize_t>(line.size())) {
    const int errnum = errno;
    ::close(fd);
    throwIoError("cannot write the writer lock", file.string(), errnum);
  }
  return std::unique_ptr<WriterLock>(new WriterLock(dir, fd));
}

WriterLock::~WriterLock() {
  ::close(fd_);  // releases the lock
}

}  // namespace vsm::core::durable
