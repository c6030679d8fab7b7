#pragma once

// Helpers shared by the unit tests: what an operation threw, and the files under a directory.

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <functional>
#include <map>
#include <sstream>
#include <string>

#include "core/common/error.hpp"

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

/// Relative path -> content of every regular file under `dir`.
inline std::map<std::string, std::string> filesUnder(const std::filesystem::path& dir) {
  std::map<std::string, std::string> files;
  for (const auto& entry : std::filesystem::recursive_directory_iterator(dir)) {
    // The writer lock names its holder, not model content.
    if (entry.is_regular_file() && entry.path().filename() != ".vsm-writer.lock") {
      std::ifstream in(entry.path(), std::ios::binary);
      std::stringstream text;
      text << in.rdbuf();
      files[std::filesystem::relative(entry.path(), dir).string()] = text.str();
    }
  }
  return files;
}

}  // namespace vsm::core::test
