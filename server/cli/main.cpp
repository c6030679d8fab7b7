// vsm: the offline command. Parses arguments and runs one command; everything else is in core.
//
// Only help, info and validate run here: this binary links the OPC reader and none of GDAL, PCL
// or OpenImageIO, whose ~300 shared libraries took ld.so 0.1-1.5 s to load before main on every
// start (tests/bench/startup_bench.sh). import, merge, render-lod, diff and export need them: they
// are run by exec'ing `vsm-heavy` from the directory of this binary, with the same arguments (same
// process, same exit code and signals).
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <iostream>
#include <string>
#include <string_view>
#include <system_error>
#include <vector>

#include "core/common/error.hpp"
#include "core/opc/opc_index.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/validate.hpp"
#include "server/cli/console.hpp"

namespace fs = std::filesystem;
using namespace vsm::core;
using vsm::cli::UsageError;

namespace {

/// The binary that runs the commands needing GDAL, PCL or OpenImageIO; beside this one.
constexpr std::string_view kHeavyBinary = "vsm-heavy";

std::string formatBox(const Box3d& b) {
  if (b.empty()) {
    return "(empty)";
  }
  char text[256];
  std::snprintf(text, sizeof text, "[%.3f, %.3f, %.3f] .. [%.3f, %.3f, %.3f]", b.min.x, b.min.y,
                b.min.z, b.max.x, b.max.y, b.max.z);
  return text;
}

void printInfo(const fs::path& dir, int gridSize, int depth,
               const std::vector<LevelSummary>& levels, std::size_t patches, std::size_t leaves,
               const Box3d& bounds, bool bytes);

int runInfo(std::vector<std::string_view> args) {
  // Bytes on disk walk every folder (seconds at 10^5 patches): only when asked.
  const auto bytesFlag = std::find(args.begin(), args.end(), "--bytes");
  const bool bytes = bytesFlag != args.end();
  if (bytes) {
    args.erase(bytesFlag);
  }
  if (args.size() != 1) {
    throw UsageError{"info needs <opc> [--bytes]"};
  }
  const fs::path dir(args[0]);
  // The index's head counts no hidden patches: a model with hidden levels (its hierarchy names a
  // second file, read from its last 4 kB) is read whole, from its index when current.
  const std::optional<std::string> hidden = [&]() -> std::optional<std::string> {
    try {
      return hiddenHierarchyNamedBy(patchesDirOf(dir) / "patchhierarchy.xml");
    } catch (const Error&) {
      return std::nullopt;  // no Patches/: readOpcModel says so below
    }
  }();
  if (const std::optional<OpcSummary> summary = hidden ? std::nullopt : readOpcIndexSummary(dir)) {
    // The index's head: a few kB, whatever the model's size (issue 31: < 50 ms at 10^6 patches).
    std::size_t leaves = 0;
    int depth = -1;
    for (const auto& level : summary->levels) {
      leaves += level.leaves;
      depth = std::max(depth, level.depth);
    }
    printInfo(dir, summary->gridSize, depth, summary->levels, summary->patches, leaves,
              summary->bounds, bytes);
    return 0;
  }
  const Model model = readOpcModel(dir);
  const auto levels = model.levels();
  std::size_t leaves = 0;
  for (const auto& level : levels) {
    leaves += level.leaves;
  }
  printInfo(dir, model.gridSize(), model.maxDepth(), levels, model.patchCount(), leaves,
            model.at(PatchKey::root()).globalBox, bytes);
  return 0;
}

void printInfo(const fs::path& dir, int gridSize, int depth,
               const std::vector<LevelSummary>& levels, std::size_t patches, std::size_t leaves,
               const Box3d& bounds, bool bytes) {
  std::printf("model       %s\n", dir.string().c_str());
  std::printf("patch size  %d x %d vertices\n", gridSize, gridSize);
  std::printf("depth       %d (%zu levels)\n", depth, levels.size());
  std::printf("patches     %zu (%zu leaves)\n", patches, leaves);
  std::size_t hidden = 0;
  for (const auto& level : levels) {
    hidden += level.hidden;
  }
  if (const int visible = deepestVisibleDepth(levels); hidden > 0 && visible < depth) {
    std::printf("hidden      %zu patches, depth %d and below: OPC viewers see depth 0 to %d\n",
                hidden, visible + 1, visible);
  } else if (hidden > 0) {
    std::printf("hidden      %zu patches, which OPC viewers do not see\n", hidden);
  }
  std::printf("bounds      %s\n", formatBox(bounds).c_str());
  if (bytes) {
    std::printf("bytes       %s on disk\n",
                vsm::cli::formatBytes(vsm::cli::bytesUnder(dir, vsm::cli::Links::Once)).c_str());
  }
  std::printf("\n%5s %8s %8s %14s  %s\n", "depth", "patches", "leaves", "resolution m", "bounds");
  for (const auto& level : levels) {
    std::printf("%5d %8zu %8zu %14.3f  %s\n", level.depth, level.patches, level.leaves,
                level.resolution, formatBox(level.bounds).c_str());
  }
}

int runIndex(const std::vector<std::string_view>& args) {
  if (args.size() != 1) {
    throw UsageError{"index needs <opc>"};
  }
  const std::size_t patches = writeOpcIndex(fs::path(args[0]));
  std::printf("%s: indexed %zu patches\n", std::string(args[0]).c_str(), patches);
  return 0;
}

int runValidate(const std::vector<std::string_view>& args) {
  if (args.size() != 1) {
    throw UsageError{"validate needs <opc>"};
  }
  vsm::cli::ConsoleProgress progress(vsm::cli::bytesUnder(args[0]));
  const auto findings = validateOpc(fs::path(args[0]), &progress);
  if (findings.empty()) {
    std::printf("%s: valid\n", std::string(args[0]).c_str());
    return 0;
  }
  for (const Finding& finding : findings) {
    std::printf("%s: %s\n", finding.where.c_str(), finding.message.c_str());
  }
  std::printf("%zu finding%s\n", findings.size(), findings.size() == 1 ? "" : "s");
  return 1;
}

/// Replaces this process with vsm-heavy running `command` with the same arguments, argv[0]
/// included: the process stays "vsm" to its user (the writer lock names its holder by it).
/// Returns only by throwing Error(NotFound) naming the missing binary, or Error(Io) when exec
/// fails otherwise.
[[noreturn]] void execHeavy(std::string_view command, char* const* argv) {
  std::error_code ec;
  const fs::path self = fs::read_symlink("/proc/self/exe", ec);
  if (ec) {
    throw Error(ErrorCode::Io, "cannot find the vsm binary (/proc/self/exe): " + ec.message());
  }
  const fs::path heavy = self.parent_path() / kHeavyBinary;
  const std::string file = heavy.string();
  ::execv(file.c_str(), argv);
  const int error = errno;
  if (error == ENOENT) {
    throw Error(ErrorCode::NotFound, std::string(command) + " needs " + file +
                                         " (GDAL, PCL and OpenImageIO), which is missing");
  }
  throw Error(ErrorCode::Io,
              "cannot run " + file + " for " + std::string(command) + ": " + std::strerror(error));
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string_view> args(argv + 1, argv + argc);
  if (args.empty() || args[0] == "help" || args[0] == "--help" || args[0] == "-h") {
    std::cout << vsm::cli::kUsage;
    return args.empty() ? 2 : 0;
  }
  const std::string_view command = args[0];
  args.erase(args.begin());
  return vsm::cli::runReportingErrors([&]() -> int {
    if (command == "info") {
      return runInfo(args);
    }
    if (command == "validate") {
      return runValidate(args);
    }
    if (command == "index") {
      return runIndex(args);
    }
    if (command == "import" || command == "merge" || command == "render-lod" || command == "diff" ||
        command == "export") {
      execHeavy(command, argv);
    }
    throw UsageError{"unknown command '" + std::string(command) + "'"};
  });
}
