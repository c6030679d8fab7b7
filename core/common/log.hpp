#pragma once

#include <string_view>

namespace vsm::core::log {

enum class Level { Debug = 0, Info = 1, Warn = 2, Error = 3, Off = 4 };

/// Messages below this level are dropped. Thread-safe.
void setLevel(Level level);
Level level();

/// Writes one line "<time> <level> <message>" to stderr. Thread-safe; each line is written whole.
/// When stderr is a terminal the line starts with "\r\x1b[K" (erase the current line), so it
/// replaces a progress line drawn in place instead of running into it.
void write(Level level, std::string_view message);

inline void debug(std::string_view m) {
  write(Level::Debug, m);
}
inline void info(std::string_view m) {
  write(Level::Info, m);
}
inline void warn(std::string_view m) {
  write(Level::Warn, m);
}
inline void error(std::string_view m) {
  write(Level::Error, m);
}

}  // namespace vsm::core::log
