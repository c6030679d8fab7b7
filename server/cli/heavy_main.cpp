// vsm-heavy: the commands of `vsm` that need GDAL, PCL or OpenImageIO (import, merge, render-lod,
// export, diff). `vsm` execs it for them (main.cpp), so that info and validate load none of those
// libraries.
#include <malloc.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <functional>
#include <mutex>
#include <optional>
#include <span>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

#include "core/cache/patch_cache.hpp"
#include "core/common/error.hpp"
#include "core/common/numbers.hpp"
#include "core/diff/diff_json.hpp"
#include "core/diff/diff_picture.hpp"
#include "core/diff/revision_diff.hpp"
#include "core/durable/durable_io.hpp"
#include "core/grid/texture_tile.hpp"
#include "core/io/geotiff.hpp"
#include "core/io/grid_source.hpp"
#include "core/merge/merge.hpp"
#include "core/merge/merge_into.hpp"
#include "core/merge/register.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/texture_file.hpp"
#include "core/store/live_model.hpp"
#include "core/store/model_edit.hpp"
#include "core/tiles/heights.hpp"
#include "core/tiles/lod_render.hpp"
#include "core/tiles/quantized_mesh.hpp"
#include "server/cli/console.hpp"
#include "server/config/config.hpp"

namespace fs = std::filesystem;
using namespace vsm::core;
using vsm::cli::bytesUnder;
using vsm::cli::ConsoleProgress;
using vsm::cli::UsageError;

namespace {

/// Runs a batch of tasks on up to two threads per core, for imports: they wait on the file system
/// (three new files per patch) about as long as they compute, so one thread per core leaves the
/// cores idle half the time (the bench's 8193^2 import: 2.2-2.8 s on 2 threads, 1.5-1.75 s on 4,
/// 1.7-1.9 s on 8, on 2 cores).
class ThreadExecutor final : public Executor {
 public:
  void runAll(std::vector<std::function<void()>> tasks) override {
    const std::size_t threads =
        std::min<std::size_t>(tasks.size(), 2 * std::max(1u, std::thread::hardware_concurrency()));
    std::atomic<std::size_t> next{0};
    std::mutex mutex;
    std::exception_ptr first;
    auto work = [&] {
      for (std::size_t i; (i = next++) < tasks.size();) {
        try {
          tasks[i]();
        } catch (...) {
          std::lock_guard lock(mutex);
          if (!first) {
            first = std::current_exception();
          }
        }
      }
    };
    std::vector<std::jthread> pool;
    for (std::size_t t = 1; t < threads; ++t) {
      pool.emplace_back(work);
    }
    work();
    pool.clear();  // joins
    if (first) {
      std::rethrow_exception(first);
    }
  }
};

/// Loads OpenImageIO's module (loadImageCodec, ~0.45 s) on a thread of its own while the command
/// opens its inputs, for commands that will read texture tiles; joined at the end of the
/// scope. A failure is left to the first texture operation, which tries again and reports it.
class ImageCodecPreload {
 public:
  ImageCodecPreload()
      : thread_([] {
          try {
            loadImageCodec();
          } catch (const Error&) {
          }
        }) {}

 private:
  std::jthread thread_;
};

/// The value of option args[i], advancing i past it.
std::string_view optionValue(const std::vector<std::string_view>& args, std::size_t& i) {
  if (i + 1 >= args.size()) {
    throw UsageError{std::string(args[i]) + " needs a value"};
  }
  return args[++i];
}

/// The value of --memory-budget at args[i] (advancing i): a size like 512MiB.
std::size_t budgetOption(const std::vector<std::string_view>& args, std::size_t& i) {
  try {
    return vsm::server::parseSize(optionValue(args, i));
  } catch (const Error& e) {
    throw UsageError{e.what()};
  }
}

/// The value of option args[i] (advancing i): an integer from lo to hi.
std::int64_t integerOption(const std::vector<std::string_view>& args, std::size_t& i,
                           std::int64_t lo, std::int64_t hi) {
  const std::string name(args[i]);
  const std::string_view text = optionValue(args, i);
  std::int64_t value = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  if (ec != std::errc() || end != text.data() + text.size() || value < lo || value > hi) {
    throw UsageError{name + " must be an integer from " + std::to_string(lo) + " to " +
                     std::to_string(hi)};
  }
  return value;
}

/// Walks a command's arguments: an option (--name) goes to `option(i)`, which takes it, advancing
/// i past its value, and returns true, or returns false for one the command does not know (a usage
/// error); the others are the positional arguments, returned in order.
template <class TakeOption>
std::vector<std::string_view> parseArguments(const std::vector<std::string_view>& args,
                                             TakeOption&& option) {
  std::vector<std::string_view> positional;
  for (std::size_t i = 0; i < args.size(); ++i) {
    if (!args[i].starts_with("--")) {
      positional.push_back(args[i]);
    } else if (!option(i)) {
      throw UsageError{"unknown option " + std::string(args[i])};
    }
  }
  return positional;
}

int runImport(const std::vector<std::string_view>& args) {
  ImportOptions options;
  const auto positional = parseArguments(args, [&](std::size_t& i) {
    if (args[i] == "--patch-size") {
      const auto value = parseInteger(optionValue(args, i));
      if (!value || *value < 3 || *value > 65537) {
        throw UsageError{"--patch-size must be 2^n+1, e.g. 65, 129 or 257"};
      }
      options.patchSize = static_cast<int>(*value);
    } else if (args[i] == "--texels-per-quad") {
      const auto value = parseInteger(optionValue(args, i));
      if (!value || *value < 1 || *value > kMaxTextureTileSize || (*value & (*value - 1)) != 0) {
        throw UsageError{"--texels-per-quad must be a power of two: 1, 2, 4, ..."};
      }
      options.texelsPerQuad = static_cast<int>(*value);
    } else if (args[i] == "--visible-texels-per-quad") {
      const auto value = parseInteger(optionValue(args, i));
      if (!value || *value < 1 || *value > kMaxTextureTileSize || (*value & (*value - 1)) != 0) {
        throw UsageError{"--visible-texels-per-quad must be a power of two: 2, 4, 8, ..."};
      }
      options.visibleTexelsPerQuad = static_cast<int>(*value);
    } else if (args[i] == "--texture") {
      if (i + 1 >= args.size()) {
        throw UsageError{"--texture needs an image or 'none'"};
      }
      const std::string_view value = args[++i];
      if (value == "none") {
        options.drape = ImportOptions::Drape::None;
        options.texture.clear();
      } else {
        options.drape = ImportOptions::Drape::Image;
        options.texture = fs::path(value);
      }
    } else {
      return false;
    }
    return true;
  });
  if (positional.size() != 2) {
    throw UsageError{"import needs <input> and <out-dir>"};
  }
  if (options.drape == ImportOptions::Drape::None &&
      (options.texelsPerQuad != 0 || options.visibleTexelsPerQuad != 0)) {
    throw UsageError{std::string(options.texelsPerQuad != 0 ? "--texels-per-quad"
                                                            : "--visible-texels-per-quad") +
                     " needs a texture (an image or the default relief), not --texture none"};
  }
  if (options.drape == ImportOptions::Drape::None) {
    std::fprintf(stderr,
                 "vsm: warning: --texture none: the model gets no Images/ and no texture "
                 "coordinates, so PRo3D will not open it\n");
  }
  ConsoleProgress progress(bytesUnder(fs::path(positional[0])));
  options.progress = &progress;
  ThreadExecutor executor;
  options.executor = &executor;
  const auto start = std::chrono::steady_clock::now();
  const Model model = importFile(fs::path(positional[0]), fs::path(positional[1]), options);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf("imported %s -> %s: %zu patches, depth %d, %.2f s\n",
              std::string(positional[0]).c_str(), std::string(positional[1]).c_str(),
              model.patchCount(), model.maxDepth(), seconds);
  return 0;
}

/// The copy a merge with --out works on: `<out>.partial-<pid>` beside the output, removed on
/// destruction unless published. Its write-back errors are captured from before the copy on.
class StagingCopy {
 public:
  StagingCopy(const fs::path& from, const fs::path& to)
      : to_(to),
        path_(to.parent_path() /
              (to.filename().string() + ".partial-" + std::to_string(::getpid()))),
        sync_(to.parent_path().empty() ? fs::path(".") : to.parent_path()) {
    std::error_code ec;
    if (fs::exists(fs::symlink_status(to, ec))) {
      throw Error(ErrorCode::Conflict, "output directory '" + to.string() + "' exists");
    }
    // A throwing constructor runs no destructor: a partial copy (the file system full, a read
    // error) is removed here.
    try {
      fs::copy(from, path_, fs::copy_options::recursive);
    } catch (const fs::filesystem_error& e) {
      fs::remove_all(path_, ec);
      throw Error(ErrorCode::Io, "cannot copy '" + from.string() + "' to '" + path_.string() +
                                     "': " + e.code().message());
    } catch (...) {
      fs::remove_all(path_, ec);
      throw;
    }
  }
  ~StagingCopy() {
    if (!path_.empty()) {
      std::error_code ec;
      fs::remove_all(path_, ec);
    }
  }
  StagingCopy(const StagingCopy&) = delete;
  StagingCopy& operator=(const StagingCopy&) = delete;

  const fs::path& path() const { return path_; }
  /// Makes the finished copy durable and renames it to the output: the commit point of a merge
  /// with --out.
  void publish() {
    sync_.sync();
    durable::renameNoReplace(path_, to_);
    path_.clear();
    try {
      durable::syncDirectory(to_.parent_path().empty() ? fs::path(".") : to_.parent_path());
    } catch (const Error& e) {
      throw Error(ErrorCode::Io, "the merged model is at '" + to_.string() + "', but " + e.what());
    }
  }

 private:
  fs::path to_;
  fs::path path_;
  durable::FileSystemSync sync_;
};

int runMerge(const std::vector<std::string_view>& args) {
  bool registerFirst = false;
  std::optional<fs::path> out;
  std::size_t budget = std::size_t{1} << 30;
  PublishOptions publish;
  const auto positional = parseArguments(args, [&](std::size_t& i) {
    if (args[i] == "--register") {
      registerFirst = true;
    } else if (args[i] == "--keep-revisions") {
      publish.keepRevisions = static_cast<unsigned>(integerOption(args, i, 2, 10000));
    } else if (args[i] == "--out") {
      out = fs::path(optionValue(args, i));
    } else if (args[i] == "--memory-budget") {
      budget = budgetOption(args, i);
    } else {
      return false;
    }
    return true;
  });
  if (positional.size() != 2) {
    throw UsageError{"merge needs <target> and <detail>"};
  }
  const fs::path target(positional[0]);
  const fs::path detailDir(positional[1]);
  const auto start = std::chrono::steady_clock::now();
  const ImageCodecPreload preload;  // the models' texture tiles
  PatchCache cache(budget);
  // In place, the target's writer lock comes first: a model another writer (vsmd, another vsm
  // merge) holds fails at once, naming the holder. The detail model is only read (no lock). With
  // --out both are read before anything is copied: a corrupt model fails there and nothing is
  // written.
  std::unique_ptr<LiveModel> live;
  if (!out) {
    live = LiveModel::open(target, "target", cache);
  }
  auto detail = LiveModel::open(detailDir, "detail", cache, LiveModel::Access::Read);
  std::optional<StagingCopy> copy;
  if (out) {
    readOpcModel(target);
    copy.emplace(target, *out);
    live = LiveModel::open(copy->path(), "target", cache);
  }
  ConsoleProgress progress(bytesUnder(detailDir));
  ThreadExecutor executor;
  MergeIntoOptions options;
  options.registerFirst = registerFirst;
  options.progress = &progress;
  options.merge.executor = &executor;
  options.publish = publish;
  options.publish.executor = &executor;
  live->removeLeftovers();  // even when the merge fails before its edit (the detail outside)
  const MergeIntoResult merged = mergeInto(*live, *detail, options);
  if (const auto& r = merged.registration) {
    std::printf("registration: fitness %.6g m^2, rms %.4g m, %s, %d stages, %.2f s\n", r->fitness,
                r->rms, r->converged ? "converged" : "NOT converged", r->stages, r->seconds);
    for (int row = 0; row < 3; ++row) {
      const auto& m = r->transform.m;
      std::printf("  [%.9f %.9f %.9f %.4f]\n", m[row * 4], m[row * 4 + 1], m[row * 4 + 2],
                  m[row * 4 + 3]);
    }
  }
  const MergeResult& result = merged.merge;
  live.reset();
  if (copy) {
    copy->publish();
  }
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const CacheStats stats = cache.stats();
  std::printf(
      "merged %s into %s: %zu target leaves matched, %zu detail leaves, %zu new patches, %zu "
      "leaves resampled in place, up to %d new levels, %.2f s\n",
      detailDir.string().c_str(), out.value_or(target).string().c_str(), result.matchedLeaves,
      result.detailLeaves, result.newPatches, result.resampledLeaves, result.maxLevels, seconds);
  std::printf("memory: budget %s, peak resident %s, %llu evictions, %llu write-backs\n",
              vsm::cli::formatBytes(stats.budgetBytes).c_str(),
              vsm::cli::formatBytes(stats.peakResidentBytes).c_str(),
              static_cast<unsigned long long>(stats.evictions),
              static_cast<unsigned long long>(stats.writeBacks));
  return 0;
}

/// The world file beside a picture (<out>.pgw) so GDAL and GIS tools place it: pixel sizes,
/// rotations, then the centre of the upper-left pixel.
void writeWorldFile(const fs::path& out, double x0, double y0, double dx, double dy) {
  fs::path world = out;
  world.replace_extension(".pgw");
  char text[256];
  const int length = std::snprintf(text, sizeof text, "%.17g\n0\n0\n%.17g\n%.17g\n%.17g\n", dx, -dy,
                                   x0 + 0.5 * dx, y0 - 0.5 * dy);
  durable::writeFileAtomically(
      world, std::as_bytes(std::span(text, static_cast<std::size_t>(std::max(length, 0)))));
}

/// `vsm render-lod`: the leaves coloured by depth, seen from above, as an RGBA PNG (transparent
/// where no leaf is) plus a world file so GDAL and GIS tools place it.
int runRenderLod(const std::vector<std::string_view>& args) {
  LodRenderOptions options;
  const auto positional = parseArguments(args, [&](std::size_t& i) {
    if (args[i] != "--size") {
      return false;
    }
    options.size = static_cast<int>(integerOption(args, i, 1, 16384));
    return true;
  });
  if (positional.size() != 2) {
    throw UsageError{"render-lod needs <opc> and <out.png>"};
  }
  const fs::path dir(positional[0]);
  const fs::path out(positional[1]);
  const Model model = readOpcModel(dir);
  ConsoleProgress progress(bytesUnder(dir));
  options.progress = &progress;
  const LodImage image = renderLod(
      model,
      [&](const PatchInfo& info) {
        return std::make_shared<const PatchGrid>(readPatchGrid(dir, model, info));
      },
      options);

  // The format is the one the extension names; replaced atomically: a reader never sees half a
  // picture.
  durable::writeFileAtomically(
      out, encodeImageFile(out.filename().string(), image.rgba.data(), image.width, image.height));
  writeWorldFile(out, image.x0, image.y0, image.dx, image.dy);

  std::printf("%s: %d x %d pixels, %s x %.10g .. %.10g, y %.10g .. %.10g\n", out.string().c_str(),
              image.width, image.height, image.geographic ? "lon/lat (degrees)" : "global x/y,",
              image.x0, image.x0 + image.width * image.dx, image.y0 - image.height * image.dy,
              image.y0);
  for (std::size_t depth = 0; depth < image.pixelsPerDepth.size(); ++depth) {
    const Rgb8 c = depthColour(static_cast<int>(depth));
    std::printf("depth %2zu  #%02x%02x%02x  %zu pixels\n", depth, c.r, c.g, c.b,
                image.pixelsPerDepth[depth]);
  }
  return 0;
}

/// Four comma-separated numbers "w,s,e,n".
GeoRect boundsOption(const std::vector<std::string_view>& args, std::size_t& i) {
  const std::string_view text = optionValue(args, i);
  double v[4] = {0, 0, 0, 0};
  std::size_t at = 0;
  for (int k = 0; k < 4; ++k) {
    const std::size_t comma = k < 3 ? text.find(',', at) : text.size();
    const auto parsed =
        comma == std::string_view::npos ? std::nullopt : parseDouble(text.substr(at, comma - at));
    if (!parsed || !std::isfinite(*parsed) || (k == 3 && comma != text.size())) {
      throw UsageError{"--bounds takes west,south,east,north in degrees, not '" +
                       std::string(text) + "'"};
    }
    v[k] = *parsed;
    at = comma + 1;
  }
  return {v[0], v[1], v[2], v[3]};
}

/// `vsm export`: the model's heights from its finest leaves as a float32 cloud-optimised GeoTIFF
/// in lon/lat (EPSG:4326), sampled in strips so memory stays bounded.
int runExport(const std::vector<std::string_view>& args) {
  std::vector<std::string_view> positional;
  std::optional<GeoRect> bounds;
  std::optional<double> resolution;
  std::optional<std::uint64_t> rev;
  std::size_t budget = std::size_t{1} << 30;
  for (std::size_t i = 0; i < args.size(); ++i) {
    if (args[i] == "--bounds") {
      bounds = boundsOption(args, i);
    } else if (args[i] == "--resolution") {
      const std::string_view text = optionValue(args, i);
      resolution = parseDouble(text);
      if (!resolution || !(*resolution > 0)) {
        throw UsageError{"--resolution takes a positive number of degrees, not '" +
                         std::string(text) + "'"};
      }
    } else if (args[i] == "--crs") {
      const std::string_view crs = optionValue(args, i);
      if (crs != "EPSG:4326" && crs != "epsg:4326" && crs != "OGC:CRS84") {
        throw UsageError{"--crs " + std::string(crs) +
                         ": only EPSG:4326 (longitude/latitude on WGS 84) is written; reproject "
                         "with gdalwarp"};
      }
    } else if (args[i] == "--rev") {
      rev = static_cast<std::uint64_t>(integerOption(args, i, 1, INT64_MAX));
    } else if (args[i] == "--memory-budget") {
      budget = budgetOption(args, i);
    } else if (args[i].starts_with("--")) {
      throw UsageError{"unknown option " + std::string(args[i])};
    } else {
      positional.push_back(args[i]);
    }
  }
  if (positional.size() != 2) {
    throw UsageError{"export needs <opc> and <out.tif>"};
  }
  PatchCache cache(budget);
  const fs::path dir = fs::path(positional[0]).lexically_normal();
  const std::string name = (dir.has_filename() ? dir : dir.parent_path()).filename().string();
  auto live = LiveModel::open(dir, name, cache, LiveModel::Access::Read);
  const auto snapshot = rev ? live->snapshotAt(*rev) : live->snapshot();
  const Model& model = *snapshot->model;
  const TerrainGridLoader load = [&](const PatchInfo& info) {
    return live->positions(*snapshot, info.key).get<PatchGrid>();
  };
  const auto start = std::chrono::steady_clock::now();
  const TerrainLayer layer = buildTerrainLayer(model, load);
  if (!layer.heightField) {
    throw Error(ErrorCode::InvalidArgument,
                "model '" + name + "' is no height field: " + layer.reason);
  }
  if (!resolution) {
    resolution = finestSpacingDegrees(model, layer, layer.bounds, load);
  }
  if (!bounds) {
    // The pixel centres on the outermost vertices.
    const GeoRect& b = layer.bounds;
    const double half = *resolution / 2;
    bounds = GeoRect{b.west - half, b.south - half, b.east + half, b.north + half};
  }
  const TopDownGrid view = heightPicture(*bounds, *resolution, std::size_t{1} << 34);
  StripRaster raster;
  raster.width = view.width;
  raster.height = view.height;
  raster.geoTransform = {view.x0, view.dx, 0, view.y0, 0, -view.dy};
  raster.wgs84 = true;
  std::size_t defined = 0;
  raster.fill = [&](int row, int rows, std::span<float> values) {
    sampleHeightGrid(model, layer, pictureRows(view, row, rows), load, values);
    for (const float v : values) {
      defined += std::isnan(v) ? 0 : 1;
    }
  };
  writeCogGeoTiff(positional[1], raster);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::printf(
      "%s: %d x %d pixels of %.10g deg, lon %.10g .. %.10g, lat %.10g .. %.10g, revision "
      "%llu, %zu pixels with a height, %.2f s\n",
      std::string(positional[1]).c_str(), view.width, view.height, view.dx, view.x0,
      view.x0 + view.width * view.dx, view.y0 - view.height * view.dy, view.y0,
      static_cast<unsigned long long>(snapshot->version), defined, seconds);
  return 0;
}

/// `vsm diff`: what changed between two kept revisions of a model, as numbers (stdout, --json),
/// a picture (--png, with a world file) and a float32 GeoTIFF of the displacement (--geotiff).
int runDiff(const std::vector<std::string_view>& args) {
  std::optional<std::uint64_t> from, to;
  std::optional<fs::path> json, png, geotiff;
  DiffOptions options;
  int size = 1024;
  std::size_t budget = std::size_t{1} << 30;
  const auto positional = parseArguments(args, [&](std::size_t& i) {
    if (args[i] == "--from") {
      from = static_cast<std::uint64_t>(integerOption(args, i, 1, INT64_MAX));
    } else if (args[i] == "--to") {
      to = static_cast<std::uint64_t>(integerOption(args, i, 1, INT64_MAX));
    } else if (args[i] == "--size") {
      size = static_cast<int>(integerOption(args, i, 1, 16384));
    } else if (args[i] == "--json") {
      json = fs::path(optionValue(args, i));
    } else if (args[i] == "--png") {
      png = fs::path(optionValue(args, i));
    } else if (args[i] == "--geotiff") {
      geotiff = fs::path(optionValue(args, i));
    } else if (args[i] == "--memory-budget") {
      budget = budgetOption(args, i);
    } else if (args[i] == "--registration-error" || args[i] == "--search-distance") {
      const std::string name(args[i]);
      const std::string text(optionValue(args, i));
      char* end = nullptr;
      const double value = std::strtod(text.c_str(), &end);
      if (text.empty() || end != text.c_str() + text.size() || !(value >= 0) ||
          !std::isfinite(value)) {
        throw UsageError{name + " needs a length in metres >= 0"};
      }
      (name == "--registration-error" ? options.registrationError : options.searchDistance) = value;
    } else {
      return false;
    }
    return true;
  });
  if (positional.size() != 1 || !from || !to) {
    throw UsageError{"diff needs <opc> --from A --to B"};
  }
  PatchCache cache(budget);
  const fs::path dir = fs::path(positional[0]).lexically_normal();
  const std::string name =
      (dir.has_filename() ? dir : dir.parent_path()).filename().string();  // "prism/" too
  auto live = LiveModel::open(dir, name, cache, LiveModel::Access::Read);
  ConsoleProgress progress;
  options.progress = &progress;
  options.mapSize = png || geotiff ? size : 0;
  const auto start = std::chrono::steady_clock::now();
  const RevisionDiff diff =
      diffRevisions(*live, live->snapshotAt(*from), live->snapshotAt(*to), options);
  const double seconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  const std::string body = diffJson(diff, live->name());
  if (json) {
    durable::writeFileAtomically(*json, std::as_bytes(std::span(body.data(), body.size())));
  }
  const std::string legend = diffLegend(diff);
  if (diff.map) {
    const TopDownGrid& g = diff.map->grid;
    if (png) {
      durable::writeFileAtomically(*png, diffPng(diff, 1));
      writeWorldFile(*png, g.x0, g.y0, g.dx, g.dy);
    }
    if (geotiff) {
      FloatRaster raster;
      raster.width = g.width;
      raster.height = g.height;
      raster.values = diff.map->values;
      raster.geoTransform = {g.x0, g.dx, 0, g.y0, 0, -g.dy};
      raster.wgs84 = g.geographic;
      writeFloatGeoTiff(*geotiff, raster);
    }
  } else if (png || geotiff) {
    std::fprintf(stderr, "vsm: nothing changed between revisions %llu and %llu: no map written\n",
                 static_cast<unsigned long long>(diff.from),
                 static_cast<unsigned long long>(diff.to));
  }
  const DisplacementStats& t = diff.totals;
  std::size_t removed = 0;
  for (const PatchDisplacement& p : diff.patches) {
    removed += p.removed ? 1 : 0;
  }
  std::printf(
      "revision %llu -> %llu: %zu patches changed, %zu removed, %zu shared; %zu vertices "
      "compared, %zu skipped, %.6g m^2 changed (|d| > %g m and > float32 noise, at most %.3g m) of "
      "%.6g m^2, %.2f s\n",
      static_cast<unsigned long long>(diff.from), static_cast<unsigned long long>(diff.to),
      diff.patches.size() - removed, removed, diff.sharedPatches, t.samples, t.skipped,
      t.changedArea, diff.epsilon, t.noise, t.area, seconds);
  if (t.samples > 0) {
    std::printf("displacement m: min %.6g, max %.6g, mean %.6g, rms %.6g\n", t.min, t.max, t.mean(),
                t.rms());
    std::printf(
        "beyond the level of detection (mean %.3g m, largest %.3g m, registration error %g m): "
        "%.6g m^2 significant, volume gained %.6g m^3, lost %.6g m^3\n",
        t.lodMean(), t.lodMax, diff.registrationError, t.significantArea, t.volumeGained,
        t.volumeLost);
  }
  if (diff.map) {
    std::printf("map: %d x %d pixels, %s; %s\n", diff.map->grid.width, diff.map->grid.height,
                diff.map->grid.geographic ? "lon/lat (WGS 84)" : "global x/y", legend.c_str());
  }
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  // Imports and merges allocate and free buffers of a few MB per patch on every thread. glibc's
  // defaults hand them back to the kernel (munmap, heap trimming) and fault the pages in again on
  // the next patch: 149k page faults in the merge bench's (b), 88k with these settings, and
  // 15-20 % less time placing. Every command here is one short process whose working sets the
  // memory budget already bounds, so freed memory stays with it.
  mallopt(M_MMAP_THRESHOLD, 32 << 20);
  mallopt(M_TRIM_THRESHOLD, 1 << 30);
  std::vector<std::string_view> args(argv + 1, argv + argc);
  return vsm::cli::runReportingErrors([&]() -> int {
    if (args.empty()) {
      throw UsageError{"no command"};
    }
    const std::string_view command = args[0];
    args.erase(args.begin());
    if (command == "import") {
      return runImport(args);
    }
    if (command == "merge") {
      return runMerge(args);
    }
    if (command == "render-lod") {
      return runRenderLod(args);
    }
    if (command == "diff") {
      return runDiff(args);
    }
    if (command == "export") {
      return runExport(args);
    }
    throw UsageError{"unknown command '" + std::string(command) + "'"};
  });
}
