#include "server/cli/console.hpp"

#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <iostream>
#include <new>

#include "core/common/error.hpp"

namespace vsm::cli {

const std::string_view kUsage =
    "usage: vsm <command> [arguments]\n"
    "\n"
    "commands:\n"
    "  import <input> <out-dir> [--patch-size N]   import a georeferenced raster (GDAL) or an\n"
    "                                              organized point cloud (.pcd, .ply) into a new "
    "OPC\n"
    "         [--texture <image>]                  and drape an image over it: placed by its\n"
    "                                              georeference, or stretched over the input's\n"
    "                                              extent (a texture tile per patch)\n"
    "  info <opc>                                  depth, patches per level, bounds, resolution, "
    "bytes\n"
    "  validate <opc>                              check every invariant; exit 1 listing findings\n"
    "  merge <target> <detail> [--register] [--out <dir>] [--memory-budget SIZE]\n"
    "                                              insert the detail model into the target (in\n"
    "                                              place, or into a new <dir>); --register aligns\n"
    "                                              it first (ICP); SIZE like 512MiB (default "
    "1GiB)\n"
    "  render-lod <opc> <out.png> [--size N]       top-down picture of which depth covers which\n"
    "                                              area (colours: core/tiles/README.md), N pixels\n"
    "                                              on the longer side (default 1024), and a world\n"
    "                                              file <out>.pgw (lon/lat for ECEF models)\n"
    "  help                                        this text\n";

ConsoleProgress::ConsoleProgress() : tty_(isatty(STDERR_FILENO) == 1) {}

ConsoleProgress::~ConsoleProgress() {
  if (tty_ && drawn_) {
    std::fputc('\n', stderr);
  }
}

void ConsoleProgress::report(std::string_view stage, double fraction) {
  if (stage != stage_) {
    if (tty_ && drawn_) {
      std::fputc('\n', stderr);
    }
    stage_ = std::string(stage);
    lastPercent_ = -1;
  }
  const int percent = static_cast<int>(fraction * 100.0 + 1e-9);
  if (tty_) {
    if (percent == lastPercent_) {
      return;
    }
    constexpr int kWidth = 40;
    const int filled = percent * kWidth / 100;
    std::fprintf(stderr, "\r%-10s [%s%s] %3d%%", stage_.c_str(), std::string(filled, '#').c_str(),
                 std::string(kWidth - filled, ' ').c_str(), percent);
    std::fflush(stderr);
    drawn_ = true;
  } else if (percent / 10 != lastPercent_ / 10 || lastPercent_ < 0) {
    std::fprintf(stderr, "%s %d%%\n", stage_.c_str(), percent / 10 * 10);
  }
  lastPercent_ = percent;
}

std::string formatBytes(std::uintmax_t bytes) {
  const char* units[] = {"B", "KiB", "MiB", "GiB", "TiB"};
  double value = static_cast<double>(bytes);
  int unit = 0;
  while (value >= 1024 && unit < 4) {
    value /= 1024;
    ++unit;
  }
  char text[64];
  std::snprintf(text, sizeof text, unit == 0 ? "%.0f %s" : "%.1f %s", value, units[unit]);
  return text;
}

int runReportingErrors(const std::function<int()>& command) {
  try {
    return command();
  } catch (const UsageError& e) {
    std::cerr << "vsm: " << e.message << "\n\n" << kUsage;
    return 2;
  } catch (const core::Error& e) {
    std::cerr << "vsm: error: " << e.what() << '\n';
    return 1;
  } catch (const std::filesystem::filesystem_error& e) {
    std::cerr << "vsm: error: " << e.what() << '\n';
    return 1;
  } catch (const std::bad_alloc&) {
    std::cerr << "vsm: error: out of memory\n";
    return 1;
  }
}

}  // namespace vsm::cli
