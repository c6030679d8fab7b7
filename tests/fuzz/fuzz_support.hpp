#pragma once

// Shared by the fuzz targets of tests/fuzz (libFuzzer): scratch files for readers that take a
// path, and the one rule every target checks: bad input is answered by a core::Error with a
// message, never by a crash, another exception or an unbounded allocation (the sanitizers and
// libFuzzer's -malloc_limit_mb catch those).

#include <unistd.h>

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <optional>
#include <string>
#include <string_view>

#include "core/common/error.hpp"

namespace vsm::fuzz {

/// A directory of this process's own under the temporary directory, removed at exit.
class ScratchDir {
 public:
  explicit ScratchDir(std::string_view name)
      : path_(std::filesystem::temp_directory_path() /
              ("vsm-fuzz-" + std::string(name) + "-" + std::to_string(::getpid()))) {
    std::filesystem::remove_all(path_);
    std::filesystem::create_directories(path_);
  }
  ~ScratchDir() {
    std::error_code ec;
    std::filesystem::remove_all(path_, ec);
  }
  ScratchDir(const ScratchDir&) = delete;
  ScratchDir& operator=(const ScratchDir&) = delete;

  const std::filesystem::path& path() const { return path_; }

 private:
  std::filesystem::path path_;
};

/// Replaces the contents of `file` with `size` bytes at `data`.
inline void writeFile(const std::filesystem::path& file, const void* data, std::size_t size) {
  std::ofstream out(file, std::ios::binary | std::ios::trunc);
  out.write(static_cast<const char*>(data), static_cast<std::streamsize>(size));
  if (!out.flush()) {
    std::fprintf(stderr, "fuzz: cannot write %s\n", file.c_str());
    std::abort();
  }
}

/// Stops the run as a crash when `condition` does not hold (a property of the code under test).
inline void check(bool condition, const char* what) {
  if (!condition) {
    std::fprintf(stderr, "fuzz: property violated: %s\n", what);
    std::abort();
  }
}

/// Runs `f`; true when it returned, false when it threw a core::Error, which must carry a
/// message. Any other exception escapes: libFuzzer reports it as a crash.
template <typename F>
bool succeeds(F&& f) {
  try {
    f();
    return true;
  } catch (const core::Error& e) {
    check(e.what()[0] != '\0', "a core::Error carries a message");
    return false;
  }
}

}  // namespace vsm::fuzz
