#pragma once

// Helpers shared by the unit tests: what an operation threw, a temporary file or directory, the
// files under a directory, and an executor lending one thread per task.

#include <gtest/gtest.h>
#include <unistd.h>

#include <exception>
#include <filesystem>
#include <fstream>
#include <functional>
#include <iterator>
#include <map>
#include <set>
#include <sstream>
#include <string>
#include <string_view>
#include <system_error>
#include <thread>
#include <utility>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/executor.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core::test {

/// The code of the Error `f` throws; a test failure (and Internal) when it throws none.
inline ErrorCode codeOf(const std::function<void()>& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.code();
  }
  ADD_FAILURE() << "no Error thrown";
  return ErrorCode::Internal;
}

/// The message of the Error `f` throws; a test failure (and "") when it throws none.
inline std::string messageOf(const std::function<void()>& f) {
  try {
    f();
  } catch (const Error& e) {
    return e.what();
  }
  ADD_FAILURE() << "no Error thrown";
  return {};
}

/// The code and message of the Error `f` throws; a test failure (and Internal, "") when it throws
/// none.
template <typename F>
std::pair<ErrorCode, std::string> errorOf(F&& f) {
  try {
    f();
  } catch (const Error& e) {
    return {e.code(), e.what()};
  }
  ADD_FAILURE() << "no core::Error thrown";
  return {ErrorCode::Internal, ""};
}

/// A file holding `text` that is removed again at the end of the test.
class TempFile {
 public:
  explicit TempFile(const std::string& text)
      : path_(std::filesystem::temp_directory_path() /
              ("vsm_unit_test_" + std::to_string(getpid()) + "_" + std::to_string(counter_++) +
               ".json")) {
    std::ofstream(path_) << text;
  }
  ~TempFile() { std::filesystem::remove(path_); }
  TempFile(const TempFile&) = delete;
  TempFile& operator=(const TempFile&) = delete;
  std::string path() const { return path_.string(); }

 private:
  static inline int counter_ = 0;
  std::filesystem::path path_;
};

/// A fixture whose every test has its own empty directory `dir_`,
/// <tmp>/vsm-<tag>-test-<pid>-<test name>, made before the test (emptied first: a crashed run may
/// have left it) and removed after the derived fixture's members are gone.
class TempDirTest : public ::testing::Test {
 protected:
  explicit TempDirTest(std::string_view tag)
      : dir_(std::filesystem::temp_directory_path() /
             ("vsm-" + std::string(tag) + "-test-" + std::to_string(::getpid()) + "-" +
              ::testing::UnitTest::GetInstance()->current_test_info()->name())) {
    std::filesystem::remove_all(dir_);
    std::filesystem::create_directories(dir_);
  }
  ~TempDirTest() override {
    std::error_code ignored;
    std::filesystem::remove_all(dir_, ignored);
  }

  std::filesystem::path dir_;
};

/// The patches `b` shares in memory with `a` (Model::shared: the same chunk, copied by neither).
inline std::size_t sharedPatches(const core::Model& a, const core::Model& b) {
  std::size_t shared = 0;
  for (const auto& [key, info] : b.patches()) {
    shared += a.find(key) != nullptr && a.shared(key) == b.shared(key) ? 1 : 0;
  }
  return shared;
}

/// The patches in the chunks of `model` that hold one of `keys` (Model::runOf): what a copy of
/// the model that changed those keys shares no longer.
inline std::size_t patchesInChunksOf(const core::Model& model,
                                     const std::vector<core::PatchKey>& keys) {
  std::set<const void*> chunks;
  for (const core::PatchKey& key : keys) {
    chunks.insert(model.runOf(key).get());
  }
  std::size_t patches = 0;
  for (const core::Model::Run& run : model.runs()) {
    if (chunks.count(run.id.get()) != 0) {
      patches += static_cast<std::size_t>(std::distance(run.begin, run.end));
    }
  }
  return patches;
}

/// `key` and its ancestors up to the root: what changing a patch changes.
inline std::vector<core::PatchKey> withAncestors(core::PatchKey key) {
  std::vector<core::PatchKey> keys{key};
  for (auto parent = key.parent(); parent; parent = parent->parent()) {
    keys.push_back(*parent);
  }
  return keys;
}

inline std::string readFile(const std::filesystem::path& file) {
  std::ifstream in(file, std::ios::binary);
  std::stringstream text;
  text << in.rdbuf();
  return text.str();
}

/// Relative path -> content of every regular file under `dir`.
inline std::map<std::string, std::string> filesUnder(const std::filesystem::path& dir) {
  std::map<std::string, std::string> files;
  for (const auto& entry : std::filesystem::recursive_directory_iterator(dir)) {
    // The writer lock names its holder, not model content.
    if (entry.is_regular_file() && entry.path().filename() != ".vsm-writer.lock") {
      files[std::filesystem::relative(entry.path(), dir).string()] = readFile(entry.path());
    }
  }
  return files;
}

/// Runs each task on its own thread, as a caller lending threads would.
class ThreadPerTask final : public Executor {
 public:
  void runAll(std::vector<std::function<void()>> tasks) override {
    std::vector<std::exception_ptr> errors(tasks.size());
    {
      std::vector<std::jthread> threads;
      for (std::size_t i = 0; i < tasks.size(); ++i) {
        threads.emplace_back([&, i] {
          try {
            tasks[i]();
          } catch (...) {
            errors[i] = std::current_exception();
          }
        });
      }
    }
    ++batches;
    for (const auto& e : errors) {
      if (e) {
        std::rethrow_exception(e);
      }
    }
  }
  int batches = 0;
};

}  // namespace vsm::core::test
