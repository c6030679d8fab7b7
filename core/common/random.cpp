#include "core/common/random.hpp"

#include <cstdio>
#include <mutex>
#include <random>

namespace vsm::core {

std::uint32_t randomWord() {
  static std::mutex mutex;  // guards device
  static std::random_device device;
  const std::lock_guard lock(mutex);
  return static_cast<std::uint32_t>(device());
}

std::string randomHex() {
  char text[9];
  std::snprintf(text, sizeof text, "%08x", randomWord());
  return text;
}

}  // namespace vsm::core
