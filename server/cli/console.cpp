#include "server/cli/console.hpp"

#include <sys/stat.h>
#include <unistd.h>

#include <cstdio>
#include <filesystem>
#include <iostream>
#include <new>
#include <set>
#include <string>
#include <utility>

#include "core/common/error.hpp"

namespace vsm::cli {

const std::string_view kUsage =
    "usage: vsm <command> [arguments]\n"
    "\n"
    "commands:\n"
    "  import <input> <out-dir> [--patch-size N]   import a georeferenced raster (GDAL) or an\n"
    "                                              organized point cloud (.pcd, .ply) into a new "
    "OPC\n"
    "         [--texture <image>|none]             the texture tile of every patch: <image>\n"
    "                                              placed by its georeference, or stretched over\n"
    "                                              the input's extent; by default the surface's\n"
    "                                              own shaded relief (grey, Lambertian, sun at\n"
    "                                              azimuth 315, altitude 45 degrees in the local\n"
    "                                              east-north-up frame, no vertical\n"
    "                                              exaggeration); none: no texture (PRo3D will\n"
    "                                              then not open the model)\n"
    "         [--texels-per-quad N]                N x N texels per grid quad in every tile (a\n"
    "                                              power of two); by default as many as keep\n"
    "                                              every pixel of the image (tiles up to 4096\n"
    "                                              texels a side), 1 for the relief\n"
    "         [--visible-texels-per-quad K]        hidden levels (thesis 5.2): OPC viewers see\n"
    "                                              the levels down to K texels per quad; the\n"
    "                                              finer ones, to the input's full resolution,\n"
    "                                              are named in a second hierarchy file only vsm\n"
    "                                              reads\n"
    "  info <opc> [--bytes]                        depth, patches per level, bounds, resolution\n"
    "                                              (from the index when current); --bytes adds\n"
    "                                              the bytes on disk (walks every folder)\n"
    "  index <opc>                                 read the model in full and write its index\n"
    "                                              (Patches/patchhierarchy.vsmidx; a publish\n"
    "                                              writes it too)\n"
    "  validate <opc>                              check every invariant; exit 1 listing findings\n"
    "  merge <target> <detail> [--register] [--out <dir>] [--memory-budget SIZE]\n"
    "        [--keep-revisions N]                  insert the detail model into the target (in\n"
    "                                              place, or into a new <dir>); --register aligns\n"
    "                                              it first (ICP); SIZE like 512MiB (default "
    "1GiB);\n"
    "                                              the target keeps its last N revisions (default\n"
    "                                              8, at least 2; vsmd reads them with ?rev=)\n"
    "  render-lod <opc> <out.png> [--size N]       top-down picture of which depth covers which\n"
    "                                              area (colours: core/tiles/README.md), N pixels\n"
    "                                              on the longer side (default 1024), and a world\n"
    "                                              file <out>.pgw (lon/lat for ECEF models)\n"
    "  diff <opc> --from A --to B [--json <out>] [--png <out>] [--geotiff <out>] [--size N]\n"
    "       [--memory-budget SIZE]                 what changed between two kept revisions: the\n"
    "       [--registration-error M]               displacement of the surface along A's normal\n"
    "       [--search-distance M]                  (m, + = outward; M3C2-like), the area changed,\n"
    "                                              the volume gained and lost beyond the level\n"
    "                                              of detection (raised by the registration\n"
    "                                              error between A and B, m) per changed patch\n"
    "                                              and in total; a map (PNG blue-white-red with\n"
    "                                              a world file, float32 GeoTIFF in lon/lat for\n"
    "                                              ECEF models), N pixels on the longer side\n"
    "                                              (1024)\n"
    "  export <opc> <out.tif> [--bounds w,s,e,n] [--resolution DEG] [--crs EPSG:4326]\n"
    "         [--rev N] [--memory-budget SIZE]     heights from the finest leaves as a float32\n"
    "                                              cloud-optimised GeoTIFF (lon/lat, NaN "
    "no-data);\n"
    "                                              default: the whole model at its finest\n"
    "                                              resolution, pixel centres on its vertices\n"
    "  help                                        this text\n";

ConsoleProgress::ConsoleProgress(std::uintmax_t inputBytes)
    : tty_(isatty(STDERR_FILENO) == 1), inputBytes_(inputBytes) {}

ConsoleProgress::~ConsoleProgress() {
  if (tty_ && drawn_) {
    std::fputc('\n', stderr);
  }
}

namespace {

/// "4 s", "2 min 05 s", "1 h 02 min".
std::string formatDuration(double seconds) {
  const auto total = static_cast<long long>(seconds + 0.5);
  char text[64];
  if (total < 60) {
    std::snprintf(text, sizeof text, "%lld s", total);
  } else if (total < 3600) {
    std::snprintf(text, sizeof text, "%lld min %02lld s", total / 60, total % 60);
  } else {
    std::snprintf(text, sizeof text, "%lld h %02lld min", total / 3600, total % 3600 / 60);
  }
  return text;
}

}  // namespace

void ConsoleProgress::report(std::string_view stage, double fraction) {
  const Clock::time_point now = Clock::now();
  if (stage != stage_) {
    stage_ = std::string(stage);
    lastPercent_ = -1;
    stageStart_ = now;
  }
  const int percent = static_cast<int>(fraction * 100.0 + 1e-9);
  if (tty_) {
    // Redrawn when the percentage changes, and twice a second for the clock.
    if (percent == lastPercent_ && now - lastDraw_ < std::chrono::milliseconds(500)) {
      return;
    }
    const double elapsed = std::chrono::duration<double>(now - stageStart_).count();
    std::string line = stage_ + " " + std::to_string(percent) + "%, " + formatDuration(elapsed);
    if (inputBytes_ > 0 && fraction > 0 && elapsed >= 1.0) {
      line += ", " +
              formatBytes(static_cast<std::uintmax_t>(fraction * static_cast<double>(inputBytes_) /
                                                      elapsed)) +
              "/s";
    }
    if (fraction >= 0.01 && fraction < 1.0 && elapsed >= 1.0) {
      line += ", ETA " + formatDuration(elapsed * (1.0 - fraction) / fraction);
    }
    std::fprintf(stderr, "\r%s\x1b[K", line.c_str());
    std::fflush(stderr);
    drawn_ = true;
    lastDraw_ = now;
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

std::uintmax_t bytesUnder(const std::filesystem::path& path, Links links) {
  std::set<std::pair<dev_t, ino_t>> seen;  // files with several names, Links::Once
  const auto bytesOf = [&](const std::filesystem::path& file) -> std::uintmax_t {
    struct stat st {};
    if (::stat(file.c_str(), &st) != 0 || !S_ISREG(st.st_mode)) {
      return 0;
    }
    if (links == Links::Once && st.st_nlink > 1 && !seen.emplace(st.st_dev, st.st_ino).second) {
      return 0;
    }
    return static_cast<std::uintmax_t>(st.st_size);
  };
  std::error_code ec;
  if (!std::filesystem::is_directory(path, ec)) {
    return bytesOf(path);
  }
  std::uintmax_t total = 0;
  for (std::filesystem::recursive_directory_iterator it(path, ec), end; !ec && it != end;
       it.increment(ec)) {
    total += bytesOf(it->path());
  }
  return total;
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
