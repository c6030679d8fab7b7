#include "core/common/log.hpp"

#include <unistd.h>

#include <atomic>
#include <chrono>
#include <cstdio>
#include <ctime>
#include <string>

namespace vsm::core::log {
namespace {
std::atomic<Level> gLevel{Level::Info};

const char* name(Level level) {
  switch (level) {
    case Level::Debug:
      return "DEBUG";
    case Level::Info:
      return "INFO";
    case Level::Warn:
      return "WARN";
    case Level::Error:
      return "ERROR";
    case Level::Off:
      return "OFF";
  }
  return "?";
}
}  // namespace

void setLevel(Level level) {
  gLevel.store(level);
}
Level level() {
  return gLevel.load();
}

void write(Level lvl, std::string_view message) {
  if (lvl < gLevel.load(std::memory_order_relaxed)) {
    return;
  }
  const auto now = std::chrono::system_clock::now();
  const std::time_t seconds = std::chrono::system_clock::to_time_t(now);
  const auto millis =
      std::chrono::duration_cast<std::chrono::milliseconds>(now.time_since_epoch()).count() % 1000;
  std::tm utc{};
  gmtime_r(&seconds, &utc);
  char stamp[32];
  std::strftime(stamp, sizeof stamp, "%Y-%m-%dT%H:%M:%S", &utc);
  // On a terminal a line starts by erasing the one it lands on: the `vsm` command redraws its
  // progress there (carriage return, no newline), which a log line would otherwise run into.
  static const bool terminal = isatty(STDERR_FILENO) == 1;
  std::string line;
  line.reserve(message.size() + 48);
  if (terminal) {
    line += "\r\x1b[K";
  }
  line += stamp;
  char ms[8];
  std::snprintf(ms, sizeof ms, ".%03dZ ", static_cast<int>(millis));
  line += ms;
  line += name(lvl);
  line += ' ';
  line += message;
  line += '\n';
  // One fwrite per line: stdio locks the stream, so concurrent lines do not interleave.
  std::fwrite(line.data(), 1, line.size(), stderr);
}

}  // namespace vsm::core::log
