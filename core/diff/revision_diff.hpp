#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <vector>

#include "core/common/progress.hpp"
#include "core/grid/geometry.hpp"
#include "core/pyramid/patch_key.hpp"
#include "core/tiles/top_down.hpp"

namespace vsm::core {

class LiveModel;
struct ModelSnapshot;

/// Statistics of a signed displacement sampled at surface vertices, each vertex weighted by its
/// share of the surface (a quarter of each full cell around it, a third of each 3-corner cell).
struct DisplacementStats {
  /// Vertices compared, and vertices skipped because the other surface has none over them.
  std::size_t samples = 0;
  std::size_t skipped = 0;
  /// Surface area compared (m^2), and the part of it whose vertex has |d| > max(epsilon, noise).
  double area = 0;
  double changedArea = 0;
  /// The largest displacement float32 storage alone can make (metres): for each sampled leaf, the
  /// rounding of its own vertices plus that of the other revision's leaves around it (half a unit
  /// in the last place of each local coordinate, DisplacementStats::storageNoise). A 131 km leaf
  /// of an ECEF model rounds to ~4 mm; below this no change can be told from rounding.
  double noise = 0;
  /// Extremes of d (metres); +inf / -inf without samples.
  double min = Box3d::kInf;
  double max = -Box3d::kInf;
  /// Area-weighted sums of d and d^2 (over `area`).
  double sum = 0;
  double sumSquares = 0;
  /// M3C2's level of detection at each sample (metres, diffRevisions): its area-weighted sum
  /// (over `area`) and its largest value.
  double lodSum = 0;
  double lodMax = 0;
  /// The part of `changedArea` whose |d| also exceeds the sample's level of detection (m^2), and
  /// the volume between the surfaces over it (m^3, both >= 0): gained where d > 0 (`to` outward
  /// of `from`), lost where d < 0.
  double significantArea = 0;
  double volumeGained = 0;
  double volumeLost = 0;

  /// Adds a sample of area `weight`, changed when |d| > threshold, significant when also
  /// |d| > lod (its volume d * weight counted then).
  void add(double d, double weight, double threshold, double lod = 0);
  void merge(const DisplacementStats& other);
  /// Area-weighted mean and root mean square of d (NaN when no sample has area).
  double mean() const;
  /// Area-weighted mean level of detection (NaN when no sample has area).
  double lodMean() const;
  double rms() const;
  /// max(|min|, |max|), 0 without samples.
  double maxAbs() const;
};

/// The largest error float32 rounding of a patch's local coordinates (local box `localBox`)
/// makes along any unit direction: the norm of the per-axis half units in the last place.
double storageNoise(const Box3d& localBox);

/// One changed patch: a patch of `to` not shared with `from` (another version, or new), or a
/// patch of `from` that `to` removed. A leaf's statistics are its own vertices'; an overview's are
/// those of the changed (or removed) leaves below it.
struct PatchDisplacement {
  PatchKey key;
  /// Global box, from the revision that holds the patch (`to`, or `from` when removed).
  Box3d box;
  bool removed = false;
  bool leaf = false;
  DisplacementStats stats;
};

/// A top-down map of the displacement (a TopDownGrid over the changed area: the leaves with a
/// change, and a tenth of their extent around them), NaN where nothing was compared.
struct DisplacementMap {
  TopDownGrid grid;
  /// Row-major, top row first, grid.pixels() values.
  std::vector<float> values;
};

/// DiffOptions::indexBytes's default, the one bound of `vsm diff` and vsmd: 48 MiB a side.
/// Measured (largest neighbourhood of one side): PRISM + Jacksboro at patch size 65, 0.9 MB; the
/// demo's (patch size 257, the import's default), 14.7 MB over 4 leaves, so about 33 MB for the
/// 9 leaves around an inner 257 x 257 leaf.
inline constexpr std::size_t kDiffIndexBytes = std::size_t{96} << 20;

struct DiffOptions {
  /// The displacement that counts as a change (metres).
  double epsilon = 1e-3;
  /// The registration error between the revisions (metres, >= 0), added to the level of
  /// detection as in M3C2: 1.96 (sqrt(s1^2/n1 + s2^2/n2) + registrationError). `vsm diff
  /// --registration-error M`, GET /v1/models/{m}/diff?registration_error=M.
  double registrationError = 0;
  /// How far along the normal the other surface is looked for (metres); 0: 64 times the local
  /// resolution (the larger of the two revisions' spacing there).
  double searchDistance = 0;
  /// The most memory the spatial indexes of the two revisions may take together (bytes, half a
  /// side): each holds one leaf's neighbourhood, its leaves' global positions (24 bytes a vertex)
  /// and their cells bucketed in a uniform 3D grid (8 bytes per (bucket, cell) entry). A
  /// neighbourhood that needs more is refused
  /// (Error(ResourceExhausted)); the bound never changes an answer (the buckets are twice the
  /// leaves' spacing). The server charges it as the diff's work memory. `vsm diff` and vsmd both
  /// use this default, so they give the same answer or the same refusal.
  std::size_t indexBytes = kDiffIndexBytes;
  /// When > 0, also draw a DisplacementMap of about this many pixels along its longer side.
  int mapSize = 0;
  Progress* progress = nullptr;
  const CancelToken* cancel = nullptr;
};

struct RevisionDiff {
  std::uint64_t from = 0;
  std::uint64_t to = 0;
  double epsilon = 0;
  double registrationError = 0;
  /// Changed and removed patches, in key order.
  std::vector<PatchDisplacement> patches;
  /// Over every sampled leaf (each vertex once per leaf that holds it).
  DisplacementStats totals;
  /// Patches of `to` shared with `from` (same key and version): zero by construction, not sampled.
  std::size_t sharedPatches = 0;
  /// Present when DiffOptions::mapSize > 0 and something was compared.
  std::optional<DisplacementMap> map;
};

/// The displacement from `from`'s surface to `to`'s (two snapshots of `live`, e.g. from
/// LiveModel::snapshotAt), comparing surfaces, not files: the same surface stored in another patch
/// layout differs by zero. M3C2-like (Lague et al. 2013), along the surface, for any orientation:
///
/// Every leaf of `to` not shared with `from` is sampled at its defined vertices p (the core
/// points). The axis through p is `from`'s normal there: `from`'s surface is found along p's own
/// vertex normal, and its normal at that point (the vertex normals of the hit cell, central
/// differences over the grid, interpolated) is the axis. The axis meets `from`'s triangulated
/// leaves at a (the nearest hit within the search distance wins: folds, overhangs); the
/// displacement is d = (p - a) . n, signed + where `to` lies outward of `from` (n's side, one for
/// the whole model: in a local frame the grids' winding, x cross y, however the scene is turned;
/// for a body-centred (ECEF) model the winding turned when its root faces the planet's centre,
/// so + is up on georeferenced terrain). On a
/// height field it is today's tangent-plane distance. Every leaf of `from` that `to` removed is
/// sampled at its vertices along its own normal against `to`'s surface (the same sign). Vertices
/// where the other surface is not found are skipped (counted).
///
/// Each sample's area is its share of its cells projected onto n (the area on `from`'s surface),
/// so volumes are d times area. Its level of detection is 1.96 (sqrt(s1^2/n1 + s2^2/n2) +
/// registrationError), s and n the spread along n and the count of each side's vertices within a
/// cylinder of radius r (the larger grid spacing of the two sides there) around the axis.
///
/// Patch data is read through the cache a few patches at a time (the leaf and the other
/// revision's leaves around it), pins released after each leaf.
///
/// Throws Error(InvalidArgument) for snapshots of different grid sizes, an empty model, a
/// negative epsilon, registration error or search distance, Error(ResourceExhausted) when a
/// leaf's neighbourhood needs more than indexBytes, Error(Cancelled), and what reading patches
/// throws.
RevisionDiff diffRevisions(LiveModel& live, std::shared_ptr<const ModelSnapshot> from,
                           std::shared_ptr<const ModelSnapshot> to,
                           const DiffOptions& options = {});

}  // namespace vsm::core
