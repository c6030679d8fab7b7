#pragma once
// What both halves of the `vsm` command share: the usage text, argument errors, the progress
// display, byte formatting and the one place that turns errors into messages and exit codes.
// `vsm` (main.cpp) runs help, info and validate itself and hands import, merge and render-lod to
// `vsm-heavy` (heavy_main.cpp), the binary that links GDAL, PCL and OpenImageIO.

#include <chrono>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <string>
#include <string_view>

#include "core/common/progress.hpp"

namespace vsm::cli {

/// The help text of every command, printed by `vsm help` and after an argument error.
extern const std::string_view kUsage;

/// A wrong command line: printed with the usage text, exit code 2.
struct UsageError {
  std::string message;
};

/// Progress on stderr. On a terminal: one line, redrawn in place (carriage return, erase to the
/// end of the line) with the stage, its percentage, the time it has taken and an estimate of the
/// time left (from its pace so far), ended by a newline when done. Otherwise (logs, CI): a line
/// "<stage> <p>%" per 10 % of each stage.
class ConsoleProgress final : public core::Progress {
 public:
  /// `inputBytes`: the size of what the command reads (the raster, the models), shown on a
  /// terminal as a rate: the stage's fraction of it per second (0: no rate).
  explicit ConsoleProgress(std::uintmax_t inputBytes = 0);
  ~ConsoleProgress() override;
  ConsoleProgress(const ConsoleProgress&) = delete;
  ConsoleProgress& operator=(const ConsoleProgress&) = delete;

  void report(std::string_view stage, double fraction) override;

 private:
  using Clock = std::chrono::steady_clock;

  bool tty_;
  std::uintmax_t inputBytes_;
  bool drawn_ = false;
  std::string stage_;
  int lastPercent_ = -1;
  Clock::time_point stageStart_;
  Clock::time_point lastDraw_;
};

/// `bytes` in B, KiB, MiB, GiB or TiB, like "1.5 MiB".
std::string formatBytes(std::uintmax_t bytes);

/// How bytesUnder counts a file with several names (hard links, as an OPC's shared
/// Coordinates.aara): per name, as a reader reads them, or once, as the disk holds them.
enum class Links { PerName, Once };

/// The bytes of every regular file under `path` (or of the file `path`); what cannot be read
/// counts 0 (the command itself reports it).
std::uintmax_t bytesUnder(const std::filesystem::path& path, Links links = Links::PerName);

/// Runs `command` and returns its exit code; the one catch point of both binaries: UsageError is
/// printed with the usage text (2), core::Error, filesystem errors and std::bad_alloc as one line
/// "vsm: error: ..." (1).
int runReportingErrors(const std::function<int()>& command);

}  // namespace vsm::cli
