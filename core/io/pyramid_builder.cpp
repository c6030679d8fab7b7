// Builds a whole pyramid from a GridSource, depth first, and publishes it as a new OPC directory.
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cerrno>
#include <cstdint>
#include <functional>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <regex>
#include <string>
#include <system_error>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/common/random.hpp"
#include "core/common/vectorised.hpp"
#include "core/durable/durable_io.hpp"
#include "core/durable/writer_lock.hpp"
#include "core/io/grid_source.hpp"
#include "core/io/texture_source.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/pyramid/reduce.hpp"

namespace vsm::core {
namespace fs = std::filesystem;
namespace {

std::string quoted(const fs::path& path) {
  return "'" + path.string() + "'";
}

/// Smallest depth D >= 0 with (patchSize - 1) * 2^D >= max(width, height) - 1: the bottom level
/// then covers every sample.
int bottomDepth(int patchSize, int width, int height) {
  const std::int64_t needed = std::int64_t{std::max(width, height)} - 1;
  int depth = 0;
  while ((std::int64_t{patchSize} - 1) << depth < needed) {
    ++depth;
  }
  return depth;
}

/// All three coordinates finite (x - x is 0 for finite x, NaN for NaN and infinities): one
/// comparison instead of three classifications per vertex.
inline bool isFinite(const Vec3d& g) {
  return (g.x - g.x) + (g.y - g.y) + (g.z - g.z) == 0.0;
}

/// The box of the finite points of `points` (n): lo and hi, each x, y, z; lo above hi when there
/// is none.
VSM_VECTORISED void finiteBox(const Vec3d* __restrict points, std::size_t n, double* __restrict lo,
                              double* __restrict hi) {
  constexpr double kInf = std::numeric_limits<double>::infinity();
  lo[0] = lo[1] = lo[2] = kInf;
  hi[0] = hi[1] = hi[2] = -kInf;
  widenBoxInLanes<double>(
      n,
      [points](std::size_t i) {
        const Vec3d& g = points[i];
        return std::array<double, 3>{g.x, g.y, g.z};
      },
      [](const std::array<double, 3>& p) {
        return isFinite({p[0], p[1], p[2]});
      },
      lo, hi);
}

/// out = float(g - origin) for the n points g of a row, NaN (all three) where g is not finite.
/// A loop that vectorises.
VSM_VECTORISED void toLocal(const Vec3d* __restrict points, int n, Vec3d origin,
                            float* __restrict out) {
  constexpr float kNaN = std::numeric_limits<float>::quiet_NaN();
  for (int c = 0; c < n; ++c) {
    const Vec3d& g = points[c];
    const bool finite = isFinite(g);
    out[3 * c] = finite ? static_cast<float>(g.x - origin.x) : kNaN;
    out[3 * c + 1] = finite ? static_cast<float>(g.y - origin.y) : kNaN;
    out[3 * c + 2] = finite ? static_cast<float>(g.z - origin.z) : kNaN;
  }
}

/// Removes the staging directory unless the build was published: on any exception, including
/// Cancelled, nothing half-written stays beside the target.
class StagingDirectory {
 public:
  explicit StagingDirectory(fs::path path) : path_(std::move(path)) {}
  ~StagingDirectory() {
    if (!published_) {
      std::error_code ec;
      fs::remove_all(path_, ec);
      if (ec) {
        log::warn("import: cannot remove staging directory " + quoted(path_) + ": " + ec.message());
      }
    }
  }
  StagingDirectory(const StagingDirectory&) = delete;
  StagingDirectory& operator=(const StagingDirectory&) = delete;

  const fs::path& path() const { return path_; }
  void published() { published_ = true; }

 private:
  fs::path path_;
  bool published_ = false;
};

/// What the builders of one import share: the source (read under a lock by builders without a
/// handle of their own), the writer (whose writePatch may run concurrently for different patches)
/// and the progress.
struct BuildShared {
  GridSource& source;
  OpcWriter& writer;
  /// What is draped over the model; null for an untextured import. Thread-safe itself.
  const TileSource* texture;
  /// Texels per grid quad side of the bottom patches' tiles (ImportOptions::texelsPerQuad, chosen).
  int texelsPerQuad;
  /// How many levels above the bottom are hidden (ImportOptions::visibleTexelsPerQuad): those
  /// and the bottom one are named only in the second hierarchy file, and each parent of a hidden
  /// level has twice its children's texels per quad (their tiles side by side).
  int hiddenLevels;
  const ImportOptions& options;
  std::mutex sourceMutex;
  std::mutex progressMutex;  // guards leavesDone and options.progress
  std::size_t leavesDone = 0;
  std::size_t leavesTotal = 1;
};

/// Handles of the source for the parallel builders, each reused by the tasks that run one after
/// another: a raster handle holds its dataset and a block of 8 MB of samples, which opening one
/// per task parsed, allocated, faulted in and freed again 16 times (the bench import's page
/// faults: 42.5k -> 37.3k). At most one handle per task running at once.
class SourceHandles {
 public:
  explicit SourceHandles(const GridSource& source) : source_(source) {}

  /// An idle handle, else a new one; null when the source cannot reopen itself.
  std::unique_ptr<GridSource> take() {
    {
      std::lock_guard lock(mutex_);
      if (!idle_.empty()) {
        std::unique_ptr<GridSource> handle = std::move(idle_.back());
        idle_.pop_back();
        return handle;
      }
    }
    return source_.reopen();
  }

  void give(std::unique_ptr<GridSource> handle) {
    if (handle) {
      std::lock_guard lock(mutex_);
      idle_.push_back(std::move(handle));
    }
  }

 private:
  const GridSource& source_;
  std::mutex mutex_;
  std::vector<std::unique_ptr<GridSource>> idle_;
};

/// A built patch not written yet: its grid and, in a textured import, its texture tile.
struct BuiltPatch {
  std::unique_ptr<PatchGrid> grid;
  std::unique_ptr<TextureTile> texture;
  explicit operator bool() const { return grid != nullptr; }
};

/// A parent being built: its children's grids (null where a child is missing) and, in a textured
/// import, its own tile, downsampled from each child's as that child is added (the child's tile
/// is then written and freed: the tiles held are one per level, whatever their size).
struct Parent {
  std::array<std::unique_ptr<PatchGrid>, 4> grids;
  std::unique_ptr<TextureTile> texture;
};

/// The depth-first build of one subtree. Holds at most the finished siblings' grids on the path
/// from its top to the current patch (at most 4 per level), one texture tile per level, plus one
/// source window. Builders of disjoint subtrees may run concurrently; each reads through a handle
/// of its own when the source can reopen itself (GridSource::reopen), else through the shared one
/// under a lock.
class PyramidBuilder {
 public:
  PyramidBuilder(BuildShared& shared, std::unique_ptr<GridSource> own)
      : shared_(shared),
        own_(std::move(own)),
        writer_(shared.writer),
        options_(shared.options),
        size_(shared.options.patchSize),
        width_(shared.source.width()),
        height_(shared.source.height()),
        depth_(bottomDepth(size_, width_, height_)),
        visibleDepth_(std::max(0, depth_ - shared.hiddenLevels)),
        window_(static_cast<std::size_t>(size_) * static_cast<std::size_t>(size_)) {}

  /// Number of bottom patches holding a cell of the source.
  static std::size_t leafCount(int size, int width, int height) {
    const std::int64_t step = size - 1;
    return static_cast<std::size_t>(startsAlong(width, step)) *
           static_cast<std::size_t>(startsAlong(height, step));
  }

  int depth() const { return depth_; }

  /// Builds the patch `key` and its subtree, writes every descendant (not `key` itself) and
  /// returns its grid and texture; empty when nothing of it can be shown.
  BuiltPatch build(const PatchKey& key) {
    if (options_.cancel != nullptr) {
      options_.cancel->throwIfCancelled();
    }
    if (key.depth == depth_) {
      return readBottom(key);
    }
    Parent parent;
    for (const Quadrant q : kQuadrants) {
      const PatchKey child = key.child(q);
      if (inside(child)) {
        add(parent, child, build(child));
      }
    }
    return combine(key, parent);
  }

  /// Writes the built patch `key` (nothing when it is empty) and adds it to its `parent`: its
  /// tile downsampled into its quadrant of the parent's (then freed), its grid kept for the
  /// reduction. `parentMutex`, when given, guards `parent` (the write runs outside it).
  void add(Parent& parent, const PatchKey& key, BuiltPatch built,
           std::mutex* parentMutex = nullptr) {
    if (!built) {
      return;
    }
    write(key, *built.grid, built.texture.get());
    std::unique_lock lock =
        parentMutex != nullptr ? std::unique_lock(*parentMutex) : std::unique_lock<std::mutex>();
    const int q = static_cast<int>(key.quadrant());
    if (built.texture) {
      if (!parent.texture) {
        parent.texture = std::make_unique<TextureTile>(tileSize(key.depth - 1));
      }
      // 2 x 2 box filter, the child in its quadrant (above a hidden level: the child as it is).
      downsampleQuadrant(*built.texture, q, *parent.texture);
    }
    parent.grids[q] = std::move(built.grid);
  }

  /// The patch of `parent`'s children (built by this builder or adopted from others, written) by
  /// reduction, with its tile. Null, and the subtree dropped, when nothing of it can be shown.
  BuiltPatch combine(const PatchKey& key, Parent& parent) {
    std::array<const PatchGrid*, 4> present{};
    for (int q = 0; q < 4; ++q) {
      present[q] = parent.grids[q].get();
    }
    if (std::all_of(present.begin(), present.end(), [](const PatchGrid* g) { return !g; })) {
      return {};
    }
    BuiltPatch built;
    built.grid = std::make_unique<PatchGrid>(reduce(present));
    parent.grids = {};
    if (!built.grid->anyDefined()) {
      // Every defined child vertex sits between the vertices this level keeps (isolated samples
      // in an empty area). A patch needs a defined vertex to be written and must exist for its
      // children to be reachable, so this subtree cannot be stored.
      dropSubtree(key);
      return {};
    }
    built.texture = std::move(parent.texture);
    return built;
  }

  /// Hands back this builder's own handle of the source (its subtree is built); null when it
  /// had none.
  std::unique_ptr<GridSource> releaseSource() { return std::move(own_); }

  /// Takes over what `other` wrote (a subtree built concurrently).
  void adopt(PyramidBuilder& other) {
    written_.insert(written_.end(), std::make_move_iterator(other.written_.begin()),
                    std::make_move_iterator(other.written_.end()));
    boxes_.merge(other.boxes_);
    other.written_.clear();
  }

  /// True when the patch's area holds a cell of the source (see startsAlong).
  bool inside(const PatchKey& key) const {
    const std::int64_t span = std::int64_t{size_ - 1} << (depth_ - key.depth);
    const std::int64_t x0 = span * key.x;
    const std::int64_t y0 = span * key.y;
    return (x0 == 0 || x0 < width_ - 1) && (y0 == 0 || y0 < height_ - 1);
  }

  /// Writes one patch (with its texture tile when given) and remembers its metadata.
  void write(const PatchKey& key, const PatchGrid& grid, const TextureTile* texture) {
    PatchInfo info;
    info.key = key;
    info.hidden = key.depth > visibleDepth_;
    Box3d children;
    for (const Quadrant q : kQuadrants) {
      if (const auto it = boxes_.find(key.child(q)); it != boxes_.end()) {
        children.extend(it->second);
        boxes_.erase(it);  // a box is needed once, by the parent
      }
    }
    if (texture != nullptr) {
      writer_.writeTexture(info, *texture);
    }
    writer_.writePatch(info, grid, children);
    boxes_.emplace(key, info.globalBox);
    written_.push_back(std::move(info));
  }

  /// Metadata of every written patch, in the order written.
  std::vector<PatchInfo> takeWritten() { return std::move(written_); }

 private:
  /// Number of patch starts k * step (k >= 0) holding at least one cell of an axis of `extent`
  /// samples: every start before the last sample (a patch starting on it would only repeat its
  /// neighbour's border line), or the single start 0 of a one-sample axis.
  static std::int64_t startsAlong(int extent, std::int64_t step) {
    return extent <= 1 ? 1 : (extent - 1 + step - 1) / step;
  }

  BuiltPatch readBottom(const PatchKey& key) {
    const int x0 = static_cast<int>(key.x) * (size_ - 1);
    const int y0 = static_cast<int>(key.y) * (size_ - 1);
    const int w = std::min(size_, width_ - x0);
    const int h = std::min(size_, height_ - y0);
    const std::size_t count = static_cast<std::size_t>(w) * static_cast<std::size_t>(h);
    if (own_) {
      own_->read(x0, y0, w, h, std::span<Vec3d>(window_.data(), count));
    } else {
      std::lock_guard lock(shared_.sourceMutex);
      shared_.source.read(x0, y0, w, h, std::span<Vec3d>(window_.data(), count));
    }
    {
      std::lock_guard lock(shared_.progressMutex);
      ++shared_.leavesDone;
      if (options_.progress != nullptr) {
        options_.progress->report("import", static_cast<double>(shared_.leavesDone) /
                                                static_cast<double>(shared_.leavesTotal));
      }
    }

    // Two passes over the window: the origin is the centre of the defined vertices' box.
    double lo[3], hi[3];
    finiteBox(window_.data(), count, lo, hi);
    if (!(lo[0] <= hi[0])) {
      return {};
    }
    auto grid = std::make_unique<PatchGrid>(
        size_, originFor(Box3d{{lo[0], lo[1], lo[2]}, {hi[0], hi[1], hi[2]}}));
    // The origin is a pure translation: local = global - origin, rounded once to float32.
    const Vec3d origin = grid->local2global().translationPart();
    float* positions = grid->positions().data();
    for (int r = 0; r < h; ++r) {
      toLocal(window_.data() + static_cast<std::size_t>(r) * w, w, origin,
              positions + static_cast<std::size_t>(r) * size_ * 3);
    }
    BuiltPatch built{std::move(grid), nullptr};
    if (shared_.texture != nullptr) {
      built.texture = std::make_unique<TextureTile>(tileSize(depth_));
      shared_.texture->fillTile(x0, y0, *built.grid, *built.texture);
    }
    return built;
  }

  /// The tile size at `depth`: the bottom's texels per quad, doubled for each hidden level below.
  int tileSize(int depth) const {
    return textureTileSize(size_,
                           shared_.texelsPerQuad << std::min(depth_ - depth, shared_.hiddenLevels));
  }

  /// Forgets and deletes every patch written below `key`.
  void dropSubtree(const PatchKey& key) {
    log::warn("import: the samples under patch " + key.toString() +
              " are too sparse to appear in its overview; that area is left out of the model");
    auto below = [&key](const PatchKey& k) {
      const int levels = k.depth - key.depth;
      return levels > 0 && (k.x >> levels) == key.x && (k.y >> levels) == key.y;
    };
    for (const PatchInfo& info : written_) {
      if (below(info.key)) {
        writer_.removePatchFiles(info);
        boxes_.erase(info.key);
      }
    }
    std::erase_if(written_, [&below](const PatchInfo& info) { return below(info.key); });
  }

  BuildShared& shared_;
  std::unique_ptr<GridSource> own_;  // this builder's handle of the source, when it has one
  OpcWriter& writer_;
  const ImportOptions& options_;
  int size_;
  int width_;
  int height_;
  int depth_;
  int visibleDepth_;           // the deepest level OPC readers see
  std::vector<Vec3d> window_;  // one source window, reused
  std::vector<PatchInfo> written_;
  /// Global boxes of written patches whose parent is not written yet.
  std::map<PatchKey, Box3d> boxes_;
};

}  // namespace

std::size_t removeAbandonedImports(const fs::path& parent, std::string_view target) {
  static const std::regex staging("(.+)\\.partial-[0-9]+(-[0-9a-f]+)?");
  std::size_t removed = 0;
  std::error_code ec;
  for (const auto& entry : fs::directory_iterator(parent, ec)) {
    const std::string name = entry.path().filename().string();
    std::smatch match;
    if (!std::regex_match(name, match, staging) || (!target.empty() && match[1].str() != target) ||
        !entry.is_directory(ec) || entry.is_symlink(ec)) {
      continue;
    }
    try {
      // Held while removing: an import cannot start writing into it meanwhile.
      const auto lock = durable::WriterLock::acquire(entry.path());
      fs::remove_all(entry.path());
      log::info("removed " + quoted(entry.path()) + ", left by an interrupted import");
      ++removed;
    } catch (const Error& e) {
      if (e.code() != ErrorCode::Conflict) {
        log::warn("cannot remove " + quoted(entry.path()) +
                  " left by an interrupted import: " + e.what());
      }
    } catch (const fs::filesystem_error& e) {
      log::warn("cannot remove " + quoted(entry.path()) +
                " left by an interrupted import: " + e.what());
    }
  }
  return removed;
}

Model buildOpc(GridSource& source, const fs::path& outDir, const ImportOptions& options) {
  Model model(options.patchSize);  // validates the patch size
  if ((options.drape == ImportOptions::Drape::Image) == options.texture.empty()) {
    throw Error(ErrorCode::InvalidArgument,
                "an image texture needs an image file, and only an image texture takes one");
  }
  if (const int f = options.texelsPerQuad;
      f != 0 && (options.drape == ImportOptions::Drape::None || f < 0 || (f & (f - 1)) != 0 ||
                 f > maxTexelsPerQuad(options.patchSize))) {
    throw Error(ErrorCode::InvalidArgument,
                "texels per quad must be a power of two whose tiles (patch size - 1 times as many "
                "texels a side) stay within " +
                    std::to_string(kMaxTextureTileSize) + ", and only with a texture; not " +
                    std::to_string(options.texelsPerQuad) + " at patch size " +
                    std::to_string(options.patchSize));
  }
  if (const int k = options.visibleTexelsPerQuad;
      k != 0 && (options.drape == ImportOptions::Drape::None || k < 0 || (k & (k - 1)) != 0 ||
                 k > maxTexelsPerQuad(options.patchSize))) {
    throw Error(ErrorCode::InvalidArgument,
                "visible texels per quad must be a power of two whose tiles (patch size - 1 times "
                "as many texels a side) stay within " +
                    std::to_string(kMaxTextureTileSize) + ", and only with a texture; not " +
                    std::to_string(k) + " at patch size " + std::to_string(options.patchSize));
  }
  if (source.width() < 1 || source.height() < 1) {
    throw Error(ErrorCode::InvalidArgument, "source " + source.describe() + " has no samples");
  }
  if (bottomDepth(options.patchSize, source.width(), source.height()) > PatchKey::kMaxDepth) {
    throw Error(ErrorCode::InvalidArgument, "source " + source.describe() +
                                                " is too large for patch size " +
                                                std::to_string(options.patchSize));
  }

  const fs::path target = outDir.filename().empty() ? outDir.parent_path() : outDir;
  std::error_code ec;
  if (fs::exists(fs::symlink_status(target, ec))) {
    throw Error(ErrorCode::Conflict, "output directory " + quoted(target) + " exists");
  }
  const fs::path parent = target.parent_path().empty() ? fs::path(".") : target.parent_path();
  fs::create_directories(parent, ec);
  if (ec) {
    throwIoError("cannot create directory", parent.string(), ec.value());
  }
  removeAbandonedImports(parent, target.filename().string());
  // The pid names the writer for people; the random part keeps names apart where pids repeat (a
  // container's process is pid 1 every time).
  StagingDirectory staging(parent / (target.filename().string() + ".partial-" +
                                     std::to_string(static_cast<long long>(::getpid())) + "-" +
                                     randomHex()));
  if (!fs::create_directory(staging.path(), ec)) {
    if (ec) {
      throwIoError("cannot create directory", staging.path().string(), ec.value());
    }
    staging.published();  // not ours: leave it alone
    throw Error(ErrorCode::Conflict, "staging directory " + quoted(staging.path()) +
                                         " exists: another import into " + quoted(target) +
                                         " is running or was interrupted");
  }

  // Held from before the first write: the one syncfs at the end reports every write-back error of
  // the import. The lock moves with the directory to the target when it is published.
  durable::FileSystemSync sync(staging.path());
  const std::unique_ptr<durable::WriterLock> lock = durable::WriterLock::acquire(staging.path());

  std::unique_ptr<TileSource> texture;
  switch (options.drape) {
    case ImportOptions::Drape::ShadedRelief:
      texture = std::make_unique<ShadedReliefSource>();
      break;
    case ImportOptions::Drape::Image:
      texture = std::make_unique<TextureSource>(options.texture, source.width(), source.height(),
                                                source.georeference());
      break;
    case ImportOptions::Drape::None:
      break;
  }
  const int texelsPerQuad =
      !texture ? 1
               : (options.texelsPerQuad > 0 ? options.texelsPerQuad
                                            : texture->naturalTexelsPerQuad(options.patchSize));
  if (texture) {
    // An image is worth a line of its own (where it was placed); the default relief is not.
    (options.drape == ImportOptions::Drape::Image ? log::info : log::debug)(
        "import: texture " + texture->describe() + ", " + std::to_string(texelsPerQuad) + " texel" +
        (texelsPerQuad == 1 ? "" : "s") + " per grid quad side (tiles of " +
        std::to_string(textureTileSize(options.patchSize, texelsPerQuad)) + " texels)");
  }
  // Hidden levels: as many as doublings take the bottom's texels per quad to the visible ones.
  int hiddenLevels = 0;
  while ((texelsPerQuad << hiddenLevels) < options.visibleTexelsPerQuad) {
    ++hiddenLevels;
  }
  if (hiddenLevels > 0) {
    log::info("import: " + std::to_string(hiddenLevels) + " hidden level" +
              (hiddenLevels == 1 ? "" : "s") + " below the " +
              std::to_string(options.visibleTexelsPerQuad) +
              " texels per quad side OPC readers see (tiles of " +
              std::to_string(textureTileSize(options.patchSize, options.visibleTexelsPerQuad)) +
              " texels there)");
  } else if (options.visibleTexelsPerQuad > 0) {
    log::info("import: no hidden level: the tiles hold " + std::to_string(texelsPerQuad) +
              " texels per quad side already, not fewer than the " +
              std::to_string(options.visibleTexelsPerQuad) + " visible ones asked for");
  }
  OpcWriter writer(staging.path(), OpcWriter::Durability::Deferred);
  BuildShared shared{source,
                     writer,
                     texture.get(),
                     texelsPerQuad,
                     hiddenLevels,
                     options,
                     {},
                     {},
                     0,
                     PyramidBuilder::leafCount(options.patchSize, source.width(), source.height())};
  PyramidBuilder builder(shared, nullptr);
  BuiltPatch root;
  if (options.executor != nullptr && builder.depth() > 0) {
    // The subtrees below depth `split` as parallel tasks, each by its own builder reading through
    // its own handle of the source where it has one; the levels above from their results. 16
    // subtrees rather than 4 keep the workers busy to the end (the corner subtrees are often
    // partial).
    const int split = std::min(2, builder.depth());
    std::vector<PatchKey> tops;
    for (std::uint32_t y = 0; y < (1u << split); ++y) {
      for (std::uint32_t x = 0; x < (1u << split); ++x) {
        if (builder.inside({split, x, y})) {
          tops.push_back({split, x, y});
        }
      }
    }
    std::vector<std::optional<PyramidBuilder>> subtrees(tops.size());
    // The tops' parents, each top added by its task (writing the top's tile and freeing it).
    std::map<PatchKey, Parent> level;
    for (const PatchKey& top : tops) {
      level.try_emplace(*top.parent());
    }
    std::mutex levelMutex;  // guards the Parents in `level`
    SourceHandles handles(source);
    std::vector<std::function<void()>> tasks;
    for (std::size_t i = 0; i < tops.size(); ++i) {
      tasks.emplace_back([&, i] {
        PyramidBuilder& subtree = subtrees[i].emplace(shared, handles.take());
        BuiltPatch built = subtree.build(tops[i]);
        handles.give(subtree.releaseSource());
        subtree.add(level.at(*tops[i].parent()), tops[i], std::move(built), &levelMutex);
        // What the subtree wrote goes to disk while the other tasks compute: syncfs blocks this
        // thread only, and leaves the commit's syncfs below next to nothing (it took 0.3-0.6 s,
        // mostly the metadata of ~5,000 new files, with the cores idle).
        sync.sync();
      });
    }
    options.executor->runAll(std::move(tasks));
    for (std::optional<PyramidBuilder>& subtree : subtrees) {
      builder.adopt(*subtree);
    }
    // Up to the root, one level at a time.
    for (int depth = split - 1; depth >= 0; --depth) {
      std::map<PatchKey, Parent> parents;
      for (auto& [key, parent] : level) {
        BuiltPatch built = builder.combine(key, parent);
        if (!built) {
          continue;
        }
        if (depth == 0) {
          root = std::move(built);
          break;
        }
        builder.add(parents[*key.parent()], key, std::move(built));
      }
      level = std::move(parents);
    }
  } else {
    root = builder.build(PatchKey::root());
  }
  if (!root) {
    throw Error(ErrorCode::InvalidArgument,
                "source " + source.describe() + " has no defined sample");
  }
  builder.write(PatchKey::root(), *root.grid, root.texture.get());
  root = {};

  std::vector<PatchInfo> infos = builder.takeWritten();
  std::sort(infos.begin(), infos.end(),
            [](const PatchInfo& a, const PatchInfo& b) { return a.key < b.key; });
  for (PatchInfo& info : infos) {
    model.insert(std::move(info));  // parents first: the key order is by depth
  }
  writer.writeHierarchy(model);
  sync.sync();
  if (options.cancel != nullptr) {
    options.cancel->throwIfCancelled();
  }

  // The commit point: the complete model appears at the target, or nothing does.
  durable::renameNoReplace(staging.path(), target);
  staging.published();
  try {
    durable::syncDirectory(parent);
  } catch (const Error& e) {
    throw Error(ErrorCode::Io, "the model is imported at " + quoted(target) + ", but " + e.what());
  }
  if (options.progress != nullptr) {
    options.progress->report("import", 1.0);
  }
  log::debug("import: " + source.describe() + " -> " + quoted(target) + ": " +
             std::to_string(model.patchCount()) + " patches, depth " +
             std::to_string(builder.depth()));
  return model;
}

}  // namespace vsm::core
