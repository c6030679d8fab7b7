#pragma once

#include <filesystem>
#include <memory>
#include <string_view>

namespace vsm::core::durable {

/// The one writer of a model directory, across processes: an exclusive advisory lock (flock) on
/// the file `.vsm-writer.lock` inside the directory, which also names its holder ("vsmd pid 4242")
/// for the message others get. Other OPC readers ignore the file; vsm's readers never take the
/// lock. The kernel releases it when the holder exits, however it exits, so a crash leaves no
/// stale lock.
///
/// Writers (vsm import on its staging directory, vsm merge on its target, vsmd on every model it
/// opens for writing) hold one from before their first write until after their last; whoever
/// holds it may remove what interrupted writers left behind.
class WriterLock {
 public:
  static constexpr std::string_view kFileName = ".vsm-writer.lock";

  /// Takes the lock of `dir`, which must exist, without waiting. Throws Error(Conflict) with one
  /// line naming the holder ("'<dir>' is being written by vsmd (pid 4242); one writer per model at
  /// a time") when another open file holds it (also one of this process), Error(Io) when the lock
  /// file cannot be created or locked.
  static std::unique_ptr<WriterLock> acquire(const std::filesystem::path& dir);

  ~WriterLock();
  WriterLock(const WriterLock&) = delete;
  WriterLock& operator=(const WriterLock&) = delete;

  const std::filesystem::path& dir() const { return dir_; }

 private:
  WriterLock(std::filesystem::path dir, int fd) : dir_(std::move(dir)), fd_(fd) {}

  std::filesystem::path dir_;
  int fd_;
};

}  // namespace vsm::core::durable
