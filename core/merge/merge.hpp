#pragma once

#include <algorithm>
#include <cstddef>
#include <map>
#include <memory>
#include <optional>

#include "core/common/executor.hpp"
#include "core/common/progress.hpp"
#include "core/grid/geometry.hpp"
#include "core/grid/texture_tile.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core {

class LiveModel;
struct ModelSnapshot;
class ModelEdit;

/// Read access to a model's metadata and patch data, as a merge needs it.
class PatchSource {
 public:
  virtual ~PatchSource() = default;
  virtual const Model& model() const = 0;
  /// The vertex data of an existing patch; the data stays available (e.g. pinned in the cache) for
  /// as long as the returned pointer lives. Throws as the store does.
  virtual std::shared_ptr<const PatchGrid> positions(const PatchKey& key) = 0;
  /// The texture tile of an existing patch (kept available as positions()); null when it has
  /// none.
  virtual std::shared_ptr<const TextureTile> texture(const PatchKey& key) = 0;
};

/// A model being changed by a merge (ModelEdit adapts to it).
class MergeTarget : public PatchSource {
 public:
  /// Adds a patch (its parent exists) or replaces a patch's data, with its texture tile or none
  /// (null); marks every ancestor stale.
  virtual void setPositions(const PatchKey& key, std::shared_ptr<const PatchGrid> grid,
                            std::shared_ptr<const TextureTile> texture) = 0;
  /// Recomputes every stale overview bottom-up by reduction, textures by downsampling.
  virtual void refreshStale(const CancelToken* cancel) = 0;
  /// Stores a patch set before, which the merge will not change again, now rather than at the
  /// end (ModelEdit::writeEarly); called from executor tasks, for distinct keys, while no
  /// setPositions runs. Default: nothing (a target without storage).
  virtual void writeEarly(const PatchKey& /*key*/) {}
};

struct MergeOptions {
  /// Receives the stages "matching", "placing" and "reducing".
  Progress* progress = nullptr;
  /// Polled between patches; a cancelled merge throws Error(Cancelled) and leaves the edit to be
  /// discarded.
  const CancelToken* cancel = nullptr;
  /// Rigid transform applied to every vertex (and box) of the detail model, e.g. from
  /// registerModels(). Never applied per patch.
  std::optional<Mat4d> transform;
  /// Registration only (registerModels' residual along it): the merge places B along the
  /// normals of A's surface, whatever the direction. Default: defaultUp() of the detail model's
  /// root box (the local vertical for ECEF models, +z otherwise).
  std::optional<Vec3d> up;
  /// Reads B's matched leaves and computes the new patches of a matched leaf (up to kMergeBatch
  /// at a time) in parallel; null: one after the other on the calling thread. The result is the
  /// same either way.
  Executor* executor = nullptr;
};

/// New patches a merge computes at a time before inserting them (in order) into the target: with
/// the detail surface each task samples from, a bound on the merge's working set beside the
/// cache (see mergeModels).
inline constexpr std::size_t kMergeBatch = 16;
/// The bytes a batch's finished new patches may hold beside the cache: kMergeBatch patches of
/// 257 x 257 vertices with four texels per quad (0.8 MB of grid, 4.2 MB of tile each).
inline constexpr std::size_t kMergeBatchBytes = std::size_t{80} << 20;

/// New patches per batch when a finished one (grid and texture tile) holds `patchBytes`: as many
/// as kMergeBatchBytes holds, at most kMergeBatch and at least 2 (tiles of 4096 texels a side,
/// 64 MiB, go two at a time).
inline std::size_t mergeBatch(std::size_t patchBytes) {
  const std::size_t fit = kMergeBatchBytes / std::max<std::size_t>(patchBytes, 1);
  return std::clamp<std::size_t>(fit, 2, kMergeBatch);
}

struct MergeResult {
  /// Bottom patches of the target placed on the detail (given new levels, or resampled in place).
  std::size_t matchedLeaves = 0;
  /// Bottom patches of the detail model that meet at least one matched target patch.
  std::size_t detailLeaves = 0;
  /// Patches added to the target (all new levels).
  std::size_t newPatches = 0;
  /// Matched leaves already as fine as the detail, placed on it in place (no new level).
  std::size_t resampledLeaves = 0;
  /// New vertices placed on the detail surface (the rest interpolate the target's old data).
  std::size_t verticesFromDetail = 0;
  /// Levels added below each matched target leaf (its deepest new level; 0 where it was
  /// resampled in place), and their maximum.
  std::map<PatchKey, int> levels;
  int maxLevels = 0;
  double seconds = 0;
};

/// Inserts the detail model B into the target model A (DESIGN.md section 3, thesis 3.3):
///
/// 1. matching: A's bottom patches near B (found by descending A's tree through boxes grown by
///    what their balls can reach, so the cost does not grow with A), paired with B's bottom
///    patches whose balls meet theirs within the search distance (4 of the A leaf's spacings,
///    at least 16 of B's finest);
///    B's outer border must lie on A's surface (cast along B's normals into A), else the merge
///    is refused with where it leaves A;
/// 2. placing: under each matched leaf a, k new levels with 2^k >= res(a) / res(B's matched
///    leaves) (allowing an eighth), resolutions measured on the surface (gridSpacing, in 3D),
///    k >= 0: a leaf already as fine as B (where B or a scan of its resolution was merged before)
///    keeps its place in the tree and is placed on B's surface itself, so merging a scan again
///    replaces its area instead of deepening the tree. A new patch is a's surface subdivided to
///    its level (Subdivider); it is refined further only where B may have surface (balls), down
///    to level k, whose vertices are cast along the normal of a's subdivided surface into B's
///    triangles (SurfaceCaster; the nearest hit within the search distance wins; core/merge/
///    README.md gives the rule for rays, folds and seams). Elsewhere it stays a leaf with a's
///    surface interpolated (the thesis fills the whole new bottom level; this keeps the cost
///    proportional to B's area instead of a's area times 4^k). Refined patches are added before
///    their children as placeholders;
/// 3. reducing: every stale overview, from the new levels up to the root, is recomputed by
///    reduction. Patches outside the matched leaves' subtrees and their ancestors are not touched.
///
/// Every patch the merge writes gets a texture tile (vsm's layout: a power of two texels per grid
/// quad side, textureTileSize; a new patch takes the finer of a's and B's there, so each model's
/// imagery keeps its own resolution), so the result stays complete for PRo3D (OPC.md): a texel
/// of a new level-k patch takes B's texture where B has a textured surface under the texel's centre
/// (located as the vertices are, and sampled bilinearly in B's tile at that point of B's grid),
/// else a's texture bilinearly upsampled (a's texel-to-quad mapping holds on every level of the
/// subdivision), else the new patch's own shaded relief (shadedRelief); a new patch above level k
/// that stays a leaf takes a's texture upsampled, else its shaded relief; every recomputed
/// overview gets its children's tiles downsampled (ModelEdit::refreshStale).
///
/// Memory: the target's and B's patches are read through the cache (charged to its budget, B's
/// grids pinned only while a task samples them). Beside the cache a merge holds the subdivider of
/// the current matched leaf (a's vertices in double, 24 B each), per running task one caster of
/// the B cells within reach of its new patch (SurfaceCaster clipped to the patch's reach: about
/// 300 B per B cell there, caster_bench's figure, e.g. 20 MB for 257 x 257 patches of B at the
/// new level's spacing) and the finished new patches of a batch until they are inserted, in the
/// order a single thread would insert them: kMergeBatch of them, fewer where their tiles are
/// large (mergeBatch: kMergeBatchBytes, 80 MiB, or two patches; a patch of 257 x 257 is about
/// 1 MB at one texel per quad, 5 MB at four, 68 MB at sixteen).
///
/// The target is not published: the caller publishes the edit (or discards it on error).
///
/// Throws Error(InvalidArgument) when either model is empty, when B lies outside A ("detail model
/// lies outside the target") or only partly inside it, or when more than 16 levels would be
/// needed; Error(Cancelled); the stores' errors. Where A is undefined nothing of B is placed (a
/// new vertex needs A's position and normal to look B up); a B whose border lies over A's holes
/// is refused as partly outside.
MergeResult mergeModels(MergeTarget& target, PatchSource& detail, const MergeOptions& options = {});

/// The same over the store: `target` is an open edit of A, `detail` the open model B (read at its
/// current snapshot).
MergeResult mergeModels(ModelEdit& target, LiveModel& detail, const MergeOptions& options = {});

/// Store adapters, also for registerModels().
std::unique_ptr<MergeTarget> editTarget(ModelEdit& edit);
std::unique_ptr<PatchSource> liveSource(LiveModel& model);
/// A source reading one given snapshot (e.g. a kept revision, LiveModel::snapshotAt) of `model`.
std::unique_ptr<PatchSource> liveSource(LiveModel& model,
                                        std::shared_ptr<const ModelSnapshot> snapshot);

}  // namespace vsm::core
