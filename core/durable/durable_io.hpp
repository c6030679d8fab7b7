#pragma once

#include <atomic>
#include <filesystem>
#include <span>
#include <string_view>

namespace vsm::core::durable {

/// The one place where vsm makes files durable. Every writer of a model (import, merge, `--out`,
/// publish, textures) goes through these functions, so the rules live here only:
///
/// - a file others may read is written to a temporary name in its directory, fsynced, renamed
///   into place, and the directory fsynced: a crash leaves the old file or the new one;
/// - files in a directory nobody reads yet (a staging directory, an edit's draft folders) are
///   written in place and made durable together by one FileSystemSync before anything names them;
/// - a finished directory is published by one rename that never replaces an existing entry;
/// - a failed fsync or syncfs is never retried on the same pages: after it the data of the pages
///   is unknown (the kernel may have dropped them), so callers discard what they wrote.
///
/// Every function throws Error(Io) naming the path and the system's message; nothing here
/// retries.

/// Temporary files of interrupted atomic writes are named ".<name>.tmp-<pid>-<n>". True for such
/// a name (what an open of a model may remove).
bool isTempFileName(std::string_view name);

/// fsync of a directory: makes its entries (creations, renames, removals) durable.
void syncDirectory(const std::filesystem::path& dir);

/// Creates `dir` (not its parents). True when it was created, false when it existed already as
/// a directory. With `sync`, the parent is fsynced after a creation.
bool createDirectory(const std::filesystem::path& dir, bool sync);

/// A file written completely and fsynced under a temporary name beside `target`, waiting to be
/// renamed into place by commit(). The rename is the commit point of whoever owns the file: before
/// it, nothing at `target` changed; from its return on, `target` holds the new bytes (durable once
/// the directory is synced). Destroying an uncommitted PendingFile removes the temporary file.
class PendingFile {
 public:
  /// Writes and fsyncs the temporary file. Throws Error(Io); nothing is left behind then.
  PendingFile(std::filesystem::path target, std::span<const std::byte> bytes);
  /// The same with the bytes in `pieces`, one after the other (a file written from parts kept
  /// apart, without joining them in memory first).
  PendingFile(std::filesystem::path target, std::span<const std::span<const std::byte>> pieces);
  ~PendingFile();
  PendingFile(const PendingFile&) = delete;
  PendingFile& operator=(const PendingFile&) = delete;

  /// Renames the temporary file to the target. Throws Error(Io) when the rename fails (the target
  /// is unchanged and the temporary file removed). A rename that reports an error but was applied
  /// (over NFS, a retransmitted rename reports ENOENT) is told by looking: the target is the
  /// staged file and its temporary name is gone; it returns as committed then (logged). Does not
  /// sync the directory.
  void commit();

  const std::filesystem::path& target() const { return target_; }
  /// The temporary file holding the bytes until commit() (its inode, size and modification time
  /// are the target's after the rename).
  const std::filesystem::path& staged() const { return temp_; }

 private:
  std::filesystem::path target_;
  std::filesystem::path temp_;
  bool committed_ = false;
};

/// PendingFile + commit + syncDirectory of the target's directory: the file is replaced
/// atomically and durably.
void writeFileAtomically(const std::filesystem::path& target, std::span<const std::byte> bytes);

/// Renames the file `from` over `to` (same directory or file system) and syncs `to`'s directory:
/// for a file a library wrote under a temporary name of ours. `from` must have been fsynced.
void replaceFile(const std::filesystem::path& from, const std::filesystem::path& to);

/// fsync of one regular file.
void syncFile(const std::filesystem::path& file);

/// Writes files in place, for a directory nobody reads until a FileSystemSync made it durable.
/// Files of 64 KiB and more go to the device with O_DIRECT (no copy in the page cache) where the
/// file system allows it; the first refusal switches this writer to the page cache for good.
/// Thread-safe: write() may run concurrently for different files.
class DraftWriter {
 public:
  /// Writes `file` as a new file: whatever had its name (an earlier write, or a link()) is
  /// unlinked first, never truncated, since truncating a hard link would change every name of it.
  void write(const std::filesystem::path& file, std::span<const std::byte> bytes);

  /// Makes `file` another name (a hard link) of `existing`, a file that is never written again
  /// (written once by writeFileAtomically): a draft file whose bytes are already on disk costs no
  /// write. Whatever had the name is unlinked first. Returns false where the file system refuses
  /// the link (too many links to `existing`, no hard links, another file system) or `existing` is
  /// gone: the caller writes the bytes instead. Throws Error(Io) for any other failure, naming
  /// `file`.
  bool link(const std::filesystem::path& existing, const std::filesystem::path& file);

  /// A buffer of at least `bytes`, aligned for direct I/O, owned by the calling thread and reused
  /// by its next call (a writer can build a file's bytes in it so write() sends them without a
  /// copy). Throws std::bad_alloc.
  static std::span<std::byte> threadBuffer(std::size_t bytes);

 private:
  std::atomic<bool> direct_{true};
};

/// Captures every write-back error of the file system holding `dir` from its construction on, and
/// makes everything written there durable with one syncfs (one journal commit, where fsyncing
/// thousands of files costs one each).
///
/// The descriptor is opened at construction and held: syncfs reports the write-back errors since
/// that descriptor was opened (Linux >= 5.8), also when another process or an earlier call saw
/// them first. So create it before the first write it must cover. After a failure every later
/// sync() fails too: the pages it covered are not written again.
///
/// Thread-safe.
class FileSystemSync {
 public:
  explicit FileSystemSync(const std::filesystem::path& dir);
  ~FileSystemSync();
  FileSystemSync(const FileSystemSync&) = delete;
  FileSystemSync& operator=(const FileSystemSync&) = delete;

  /// syncfs. Throws Error(Io).
  void sync();

 private:
  std::filesystem::path dir_;
  int fd_ = -1;
  std::atomic<int> failed_{0};  // errno of the first failure, 0 while none
};

/// Renames the finished directory `from` to `to` unless `to` exists: RENAME_NOREPLACE, or where
/// the file system lacks it, a check and a plain rename. This is the commit point of a staged
/// directory; the caller syncs `to`'s parent after it (syncDirectory). Throws Error(Conflict) when
/// `to` exists, Error(Io) otherwise; nothing changed then.
void renameNoReplace(const std::filesystem::path& from, const std::filesystem::path& to);

}  // namespace vsm::core::durable
