#include <fcntl.h>
#include <gtest/gtest.h>
#include <linux/magic.h>
#include <sys/file.h>
#include <sys/mman.h>
#include <sys/statfs.h>
#include <sys/wait.h>
#include <unistd.h>

#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "core/durable/durable_io.hpp"
#include "core/durable/writer_lock.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::core::durable {
namespace {

namespace fs = std::filesystem;
using test::codeOf;
using test::messageOf;

class DurableTest : public test::TempDirTest {
 protected:
  DurableTest() : TempDirTest("durable") {}
};

std::string read(const fs::path& file) {
  std::ifstream in(file, std::ios::binary);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

std::span<const std::byte> bytes(const std::string& text) {
  return std::as_bytes(std::span(text.data(), text.size()));
}

std::size_t entries(const fs::path& dir) {
  return static_cast<std::size_t>(
      std::distance(fs::directory_iterator(dir), fs::directory_iterator()));
}

TEST_F(DurableTest, APendingFileChangesNothingUntilCommittedAndLeavesNothingWhenDropped) {
  writeFileAtomically(dir_ / "a.xml", bytes("old"));
  {
    PendingFile pending(dir_ / "a.xml", bytes("new"));
    EXPECT_EQ(read(dir_ / "a.xml"), "old");
    EXPECT_EQ(entries(dir_), 2u);  // the target and the temporary file
  }
  EXPECT_EQ(read(dir_ / "a.xml"), "old");
  EXPECT_EQ(entries(dir_), 1u);
  {
    PendingFile pending(dir_ / "a.xml", bytes("new"));
    pending.commit();
  }
  EXPECT_EQ(read(dir_ / "a.xml"), "new");
  EXPECT_EQ(entries(dir_), 1u);
}

/// Pages of `file` in the page cache (mincore over a mapping of it).
std::size_t cachedPages(const fs::path& file) {
  const int fd = ::open(file.c_str(), O_RDONLY | O_CLOEXEC);
  const auto size = static_cast<std::size_t>(fs::file_size(file));
  void* map = ::mmap(nullptr, size, PROT_READ, MAP_SHARED, fd, 0);
  ::close(fd);
  const std::size_t page = static_cast<std::size_t>(::sysconf(_SC_PAGESIZE));
  std::vector<unsigned char> resident((size + page - 1) / page);
  const bool known = map != MAP_FAILED && ::mincore(map, size, resident.data()) == 0;
  if (map != MAP_FAILED) {
    ::munmap(map, size);
  }
  EXPECT_TRUE(known);
  return static_cast<std::size_t>(std::count_if(resident.begin(), resident.end(),
                                                [](unsigned char r) { return (r & 1) != 0; }));
}

/// Whether files in `dir` take a direct write of one aligned block that bypasses the page cache
/// (tmpfs is the page cache: it takes them since Linux 6.6).
bool writesBypassTheCache(const fs::path& dir) {
  struct statfs info {};
  if (::statfs(dir.c_str(), &info) != 0 || info.f_type == TMPFS_MAGIC) {
    return false;
  }
  const fs::path probe = dir / "direct-probe";
  const int fd = ::open(probe.c_str(), O_WRONLY | O_CREAT | O_CLOEXEC | O_DIRECT, 0644);
  bool written = false;
  if (fd >= 0) {
    void* block = std::aligned_alloc(4096, 4096);
    std::memset(block, 0, 4096);
    written = ::write(fd, block, 4096) == 4096;
    std::free(block);
    ::close(fd);
  }
  ::unlink(probe.c_str());
  return written;
}

// A hierarchy is staged from thousands of pieces (its runs' memoised text), written a batch of
// pieces at a time: every byte in order, the empty pieces and the batches' seams included. A
// file this large goes to the device directly, through an aligned buffer of 4 MiB: its seams and
// the unaligned tail too; where the file system refuses direct writes, through the cache.
TEST_F(DurableTest, APendingFileOfManyPiecesHoldsThemAllInOrder) {
  std::vector<std::string> texts;
  std::string expected;
  for (int i = 0; i < 3000; ++i) {
    texts.push_back(i % 7 == 3 ? std::string() : std::to_string(i) + std::string(i % 13, 'x'));
    expected += texts.back();
  }
  texts.push_back(std::string(9 << 20, 'y'));  // one large piece after the last batch's seam
  expected += texts.back();
  texts.push_back("the tail, off the block grid");
  expected += texts.back();
  std::vector<std::span<const std::byte>> pieces;
  for (const std::string& text : texts) {
    pieces.push_back(bytes(text));
  }
  ASSERT_NE(expected.size() % 4096, 0u);
  std::vector<fs::path> dirs = {dir_};
  const fs::path shm = fs::path("/dev/shm") / dir_.filename();
  if (fs::is_directory(shm.parent_path())) {
    fs::create_directories(shm);
    dirs.push_back(shm);
  }
  for (const fs::path& dir : dirs) {
    SCOPED_TRACE(dir.string());
    {
      PendingFile pending(dir / "many.xml", pieces);
      pending.commit();
    }
    EXPECT_EQ(entries(dir), 1u);
    if (writesBypassTheCache(dir)) {
      // Only the tail's page went through the page cache.
      EXPECT_LE(cachedPages(dir / "many.xml"), 1u);
    }
    EXPECT_EQ(read(dir / "many.xml"), expected);
  }
  fs::remove_all(shm);
}

TEST_F(DurableTest, TemporaryFilesAreRecognisedByName) {
  EXPECT_TRUE(isTempFileName(".patchhierarchy.xml.tmp-123-4"));
  EXPECT_TRUE(isTempFileName(".2_0_1.tif.tmp-9-0"));
  EXPECT_FALSE(isTempFileName("patchhierarchy.xml"));
  EXPECT_FALSE(isTempFileName(".patchhierarchy.xml.tmp-x-4"));
  EXPECT_FALSE(isTempFileName(".vsm-writer.lock"));
}

TEST_F(DurableTest, AFailedWriteLeavesTheOldFileAndNoTemporaryFile) {
  writeFileAtomically(dir_ / "a.xml", bytes("old"));
  // The temporary file cannot be created in a directory that does not exist: Io, nothing changed.
  EXPECT_EQ(codeOf([&] { writeFileAtomically(dir_ / "missing" / "a.xml", bytes("new")); }),
            ErrorCode::Io);
  EXPECT_EQ(read(dir_ / "a.xml"), "old");
  EXPECT_EQ(entries(dir_), 1u);
}

// `vsmd --port-file port` wrote "port" in the working directory and then failed to sync its
// parent, the empty path ("cannot open for fsync ''"), and exited.
TEST_F(DurableTest, ABareFileNameIsWrittenInTheWorkingDirectory) {
  const fs::path before = fs::current_path();
  fs::current_path(dir_);
  try {
    writeFileAtomically("port", bytes("8080\n"));
  } catch (...) {
    fs::current_path(before);
    throw;
  }
  fs::current_path(before);
  EXPECT_EQ(read(dir_ / "port"), "8080\n");
  EXPECT_EQ(entries(dir_), 1u);
}

TEST_F(DurableTest, RenameNoReplaceNeverReplacesAnExistingDirectory) {
  fs::create_directory(dir_ / "staging");
  fs::create_directory(dir_ / "target");  // empty: a plain rename() would replace it
  EXPECT_EQ(codeOf([&] { renameNoReplace(dir_ / "staging", dir_ / "target"); }),
            ErrorCode::Conflict);
  EXPECT_TRUE(fs::exists(dir_ / "staging"));
  fs::remove(dir_ / "target");
  renameNoReplace(dir_ / "staging", dir_ / "target");
  EXPECT_FALSE(fs::exists(dir_ / "staging"));
  EXPECT_TRUE(fs::is_directory(dir_ / "target"));
}

TEST_F(DurableTest, CreateDirectoryTellsWhetherItCreatedOne) {
  EXPECT_TRUE(createDirectory(dir_ / "d", true));
  EXPECT_FALSE(createDirectory(dir_ / "d", true));
  std::ofstream(dir_ / "file") << "x";
  EXPECT_EQ(codeOf([&] { createDirectory(dir_ / "file", false); }), ErrorCode::Io);
}

TEST_F(DurableTest, DraftsAreWrittenWholeSmallAndLargeAndSyncSucceeds) {
  FileSystemSync sync(dir_);
  DraftWriter drafts;
  std::string large(300 * 1024 + 17, '\0');  // direct I/O for the whole blocks, the tail cached
  for (std::size_t i = 0; i < large.size(); ++i) {
    large[i] = static_cast<char>(i * 7 + 3);
  }
  drafts.write(dir_ / "small", bytes("small"));
  drafts.write(dir_ / "large", bytes(large));
  sync.sync();
  EXPECT_EQ(read(dir_ / "small"), "small");
  EXPECT_EQ(read(dir_ / "large"), large);
}

// A draft rewritten over a hard link of a shared file gets its own new file: the shared file
// and its other names keep their bytes, small (page cache) and large (direct I/O) alike.
TEST_F(DurableTest, ADraftWrittenOverALinkLeavesTheLinkedFileAlone) {
  DraftWriter drafts;
  const std::string large(200 * 1024, 'L');
  for (const std::string& content : {std::string("shared"), large}) {
    writeFileAtomically(dir_ / "shared", bytes(content));
    ASSERT_TRUE(drafts.link(dir_ / "shared", dir_ / "a"));
    ASSERT_TRUE(drafts.link(dir_ / "shared", dir_ / "b"));
    EXPECT_EQ(fs::hard_link_count(dir_ / "shared"), 3u);
    drafts.write(dir_ / "a", bytes(content + " changed"));
    EXPECT_EQ(read(dir_ / "a"), content + " changed");
    EXPECT_EQ(read(dir_ / "shared"), content);
    EXPECT_EQ(read(dir_ / "b"), content);
    EXPECT_EQ(fs::hard_link_count(dir_ / "shared"), 2u);
    fs::remove(dir_ / "a");
    fs::remove(dir_ / "b");
  }
}

// link() replaces what had the name (a file, or a link to another shared file) and says false
// when the source is gone or the name's folder is missing: the caller then writes the bytes, and
// that write reports a missing folder.
TEST_F(DurableTest, ALinkReplacesItsNameAndReportsWhatItCannotDo) {
  DraftWriter drafts;
  writeFileAtomically(dir_ / "one", bytes("one"));
  writeFileAtomically(dir_ / "two", bytes("two"));
  drafts.write(dir_ / "x", bytes("old"));
  ASSERT_TRUE(drafts.link(dir_ / "one", dir_ / "x"));
  EXPECT_EQ(read(dir_ / "x"), "one");
  ASSERT_TRUE(drafts.link(dir_ / "two", dir_ / "x"));
  EXPECT_EQ(read(dir_ / "x"), "two");
  EXPECT_EQ(read(dir_ / "one"), "one");
  EXPECT_FALSE(drafts.link(dir_ / "gone", dir_ / "y"));
  EXPECT_FALSE(fs::exists(dir_ / "y"));
  EXPECT_FALSE(drafts.link(dir_ / "one", dir_ / "no-folder" / "z"));
  EXPECT_EQ(codeOf([&] { drafts.write(dir_ / "no-folder" / "z", bytes("z")); }), ErrorCode::Io);
}

// At the file system's limit of names per file (65000 on ext4) link() says false, so the caller
// writes the bytes instead; the names made before stay. Skipped where there is no such limit
// within 70000 names (tmpfs, btrfs count far higher).
TEST_F(DurableTest, ALinkAtTheFileSystemsLimitOfNamesIsRefusedNotAnError) {
  DraftWriter drafts;
  writeFileAtomically(dir_ / "shared", bytes("shared"));
  fs::create_directory(dir_ / "names");
  int made = 0;
  bool refused = false;
  for (; made < 70000; ++made) {
    if (!drafts.link(dir_ / "shared", dir_ / "names" / std::to_string(made))) {
      refused = true;
      break;
    }
  }
  if (!refused) {
    GTEST_SKIP() << "no limit of names per file within 70000 here";
  }
  EXPECT_EQ(fs::hard_link_count(dir_ / "shared"), static_cast<std::uintmax_t>(made) + 1);
  EXPECT_FALSE(fs::exists(dir_ / "names" / std::to_string(made)));
  EXPECT_EQ(read(dir_ / "names" / "0"), "shared");
}

TEST_F(DurableTest, ASecondWriterIsRefusedWithTheHoldersNameAndPid) {
  const auto lock = WriterLock::acquire(dir_);
  // Another open of the lock file, even in this process, is another writer.
  const std::string message = messageOf([&] { WriterLock::acquire(dir_); });
  EXPECT_NE(
      message.find("is being written by durable_test (pid " + std::to_string(::getpid()) + ")"),
      std::string::npos)
      << message;
  EXPECT_EQ(codeOf([&] { WriterLock::acquire(dir_); }), ErrorCode::Conflict);
}

TEST_F(DurableTest, TheLockIsFreeWhenItsHolderExitsHoweverItExits) {
  int ready[2];
  ASSERT_EQ(::pipe(ready), 0);
  const pid_t child = ::fork();
  ASSERT_GE(child, 0);
  if (child == 0) {
    const auto lock = WriterLock::acquire(dir_);
    (void)!::write(ready[1], "x", 1);
    ::pause();  // killed below, holding the lock
    ::_exit(0);
  }
  char byte = 0;
  ASSERT_EQ(::read(ready[0], &byte, 1), 1);
  const std::string message = messageOf([&] { WriterLock::acquire(dir_); });
  EXPECT_NE(message.find("(pid " + std::to_string(child) + ")"), std::string::npos) << message;
  ::kill(child, SIGKILL);
  int status = 0;
  ::waitpid(child, &status, 0);
  ::close(ready[0]);
  ::close(ready[1]);
  EXPECT_NE(WriterLock::acquire(dir_), nullptr);
}

TEST_F(DurableTest, AHolderThatNamesItselfOddlyIsNotEchoed) {
  // Another program holding the lock with its own content (control characters, no pid).
  const fs::path file = dir_ / ".vsm-writer.lock";
  std::ofstream(file) << "\x1b[31mevil pid 12x\n";
  const int fd = ::open(file.c_str(), O_RDWR | O_CLOEXEC);
  ASSERT_GE(fd, 0);
  ASSERT_EQ(::flock(fd, LOCK_EX | LOCK_NB), 0);
  const std::string message = messageOf([&] { WriterLock::acquire(dir_); });
  ::close(fd);
  EXPECT_NE(message.find("is being written by another process"), std::string::npos) << message;
  EXPECT_EQ(message.find("evil"), std::string::npos) << message;
  EXPECT_NE(WriterLock::acquire(dir_), nullptr);  // released with its descriptor
}

}  // namespace
}  // namespace vsm::core::durable
