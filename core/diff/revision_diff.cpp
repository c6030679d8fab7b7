#include "core/diff/revision_diff.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <tuple>

#include "core/common/error.hpp"
#include "core/diff/draw_leaf.hpp"
#include "core/diff/surface_index.hpp"
#include "core/grid/vec_ops.hpp"
#include "core/merge/merge.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "core/tiles/lod_render.hpp"

namespace vsm::core {

namespace {

using namespace diff_detail;

/// One leaf to sample: a changed leaf of `to`, or a leaf of `from` that `to` removed.
struct Work {
  PatchKey key;
  bool removed = false;
  /// The core points are `from`'s leaf of this key (cast into `to`): a removed leaf, or a changed
  /// leaf of `to` whose key is a leaf of `from` too (a new version of the same patch). Otherwise
  /// they are `to`'s leaf's vertices (new, finer leaves).
  bool onFrom = false;
};

/// Throws Error(InvalidArgument) unless `from` (a) and `to` (b) can be compared with `options`.
void checkComparable(const Model& a, const Model& b, const DiffOptions& options) {
  if (a.empty() || b.empty()) {
    throw Error(ErrorCode::InvalidArgument, "diff: a revision is empty");
  }
  if (a.gridSize() != b.gridSize()) {
    throw Error(ErrorCode::InvalidArgument, "diff: the revisions have different grid sizes");
  }
  if (!(options.epsilon >= 0)) {
    throw Error(ErrorCode::InvalidArgument, "diff: epsilon must be >= 0");
  }
  if (!(options.registrationError >= 0) || !std::isfinite(options.registrationError)) {
    throw Error(ErrorCode::InvalidArgument, "diff: the registration error must be >= 0 metres");
  }
  if (!(options.searchDistance >= 0) || !std::isfinite(options.searchDistance)) {
    throw Error(ErrorCode::InvalidArgument, "diff: the search distance must be >= 0 metres");
  }
  if (options.mapSize < 0 || options.mapSize > 16384) {
    throw Error(ErrorCode::InvalidArgument, "diff: the map size must be 0..16384 pixels");
  }
}

/// What changed from `from` (a) to `to` (b), from the metadata alone.
struct Changes {
  /// The changed and removed patches by key, their statistics still empty.
  std::map<PatchKey, PatchDisplacement> patches;
  /// The leaves to sample, shallow to deep.
  std::vector<Work> work;
  /// Patches of `to` shared with `from` (same key and version).
  std::size_t shared = 0;
};

Changes findChanges(const Model& a, const Model& b) {
  Changes out;
  for (const auto& [key, info] : b.patches()) {
    const PatchInfo* old = a.find(key);
    if (old != nullptr && old->version == info.version) {
      ++out.shared;
      continue;
    }
    out.patches[key] = {key, info.globalBox, false, info.isLeaf(), {}};
    if (info.isLeaf()) {
      out.work.push_back({key, false, old != nullptr && old->isLeaf()});
    }
  }
  for (const auto& [key, info] : a.patches()) {
    if (b.find(key) == nullptr) {
      out.patches[key] = {key, info.globalBox, true, info.isLeaf(), {}};
      if (info.isLeaf()) {
        out.work.push_back({key, true, true});
      }
    }
  }
  // Shallow to deep: where both revisions' leaves overlap on the map, the finer one is drawn last.
  std::stable_sort(out.work.begin(), out.work.end(), [](const Work& x, const Work& y) {
    return x.key.depth != y.key.depth ? x.key.depth < y.key.depth : x.key < y.key;
  });
  return out;
}

/// n's side, the model's front (outside): one sign for the whole model, never per patch or per
/// vertex. In a local frame it is the grids' winding (the cross product of the grid's x and y
/// directions), whatever way the scene is turned: a face turned 135 degrees is an overhang whose
/// front still faces out of the rock. Only a body-centred model (ECEF: its root farther than
/// kBodyCentredRadius from the origin) is placed on a planet, where out is away from its centre:
/// its winding is turned when its root's faces point to the centre (rasters' rows run north to
/// south, so their winding faces down), so on georeferenced terrain + is up.
double frontSign(const Model& a, PatchSource& sourceA) {
  const Vec3d centre = a.at(PatchKey::root()).globalBox.center();
  if (centre.norm() > kBodyCentredRadius) {
    const auto root = sourceA.positions(PatchKey::root());
    Vec3d total;
    for (const Vec3d& area : vertexAreas(*root)) {
      total = total + area;
    }
    if (dot(total, upAt(centre)) < 0) {
      return -1;
    }
  }
  return 1;
}

/// One leaf sampled: its grid (pinned) and the displacement at each vertex (NaN where none).
struct Sampled {
  std::shared_ptr<const PatchGrid> grid;
  std::vector<double> d;
  DisplacementStats stats;
};

/// Samples the leaves of either revision against the other one's surface. Both sides' indexes
/// live at once (the leaves of either revision are sampled in depth order): each gets half the
/// bound.
class LeafSampler {
 public:
  LeafSampler(PatchSource& sourceA, PatchSource& sourceB, double sign, const DiffOptions& options)
      : sourceA_(sourceA),
        sourceB_(sourceB),
        sign_(sign),
        options_(options),
        surfaceA_(sourceA, sign, options.indexBytes / 2),
        surfaceB_(sourceB, sign, options.indexBytes / 2) {}

  /// The displacement at each vertex of `w`'s leaf. Throws Error(Cancelled) and what reading
  /// patches throws.
  Sampled sample(const Work& w);

  /// Releases both indexes' pins.
  void clear() {
    surfaceA_.clear();
    surfaceB_.clear();
  }

 private:
  PatchSource& sourceA_;
  PatchSource& sourceB_;
  const double sign_;
  const DiffOptions& options_;
  SurfaceIndex surfaceA_, surfaceB_;
};

Sampled LeafSampler::sample(const Work& w) {
  if (options_.cancel != nullptr) {
    options_.cancel->throwIfCancelled();
  }
  // The leaf's own revision and the other one.
  PatchSource& own = w.onFrom ? sourceA_ : sourceB_;
  SurfaceIndex& other = w.onFrom ? surfaceB_ : surfaceA_;
  const PatchInfo& info = own.model().at(w.key);
  Sampled out{own.positions(w.key), {}, {}};
  const PatchGrid& grid = *out.grid;
  const double spacing = grid.resolution();
  const std::vector<Vec3d> areas = vertexAreas(grid);
  // The reach: the leaf's box grown along its mean normal by the search distance, and by a
  // twentieth of it (and two samples) across, where lines from its vertices may go.
  Vec3d mean;
  for (const Vec3d& area : areas) {
    mean = mean + area;
  }
  mean = mean * (mean.norm() > 0 ? 1 / mean.norm() : 0.0);
  const double reach = options_.searchDistance > 0 ? options_.searchDistance : 64 * spacing;
  Box3d box = info.globalBox;
  const double across = 0.05 * reach + 2 * spacing;
  const Vec3d grow{reach * std::abs(mean.x) + across, reach * std::abs(mean.y) + across,
                   reach * std::abs(mean.z) + across};
  box.min = box.min - grow;
  box.max = box.max + grow;
  const bool found = !box.empty() && other.around(box);
  out.d.assign(grid.vertexCount(), kNaN);
  if (found) {
    out.stats.noise = storageNoise(info.localBox) + other.noise();
  }
  const double threshold = std::max(options_.epsilon, out.stats.noise);
  const int s = grid.size();
  // The leaf's positions, once (NaN where undefined).
  const std::vector<Vec3d> positions = globalPositions(grid);
  const Points points{positions.data(), s};
  std::vector<Vec3d> inside;
  for (int y = 0; y < s; ++y) {
    for (int x = 0; x < s; ++x) {
      if (!grid.defined(x, y)) {
        continue;
      }
      const Vec3d p = positions[static_cast<std::size_t>(y) * s + x];
      const Vec3d ownNormal = vertexNormal(points, x, y, sign_);
      std::optional<SurfaceIndex::Hit> hit;
      Vec3d n = ownNormal;
      double d = kNaN;
      if (found && ownNormal.finite()) {
        hit = other.cast(p, ownNormal, reach);
      }
      if (hit && w.onFrom) {
        // p is a core point on `from`, n its normal: `to` is where the axis meets it.
        d = hit->t;
      } else if (hit) {
        // p is on `to`: `from` is at a = p + t n0 along p's own normal; the axis is from's
        // normal there and d is p's distance from from's tangent plane at a (as a core point at
        // a would measure p, to first order; exact on a plane).
        n = hit->normal;
        d = -hit->t * dot(ownNormal, n);
      }
      if (!std::isfinite(d)) {
        ++out.stats.skipped;
        continue;
      }
      // `to` minus `from` along from's normal n.
      const std::size_t i = static_cast<std::size_t>(y) * s + x;
      out.d[i] = d;
      // M3C2's level of detection: each side's spread along n in the cylinder around the axis.
      // The cylinder's radius: 1.5 times the coarser side's spacing (3 x 3 vertices of a grid).
      const double otherSpacing = other.resolutionOf(hit->grid);
      const double radius = 1.5 * std::max(spacing, otherSpacing);
      const int window =
          std::clamp(static_cast<int>(std::ceil(radius / std::max(spacing, 1e-300))), 1, 3);
      inside.clear();
      for (int v = std::max(0, y - window); v <= std::min(s - 1, y + window); ++v) {
        for (int u = std::max(0, x - window); u <= std::min(s - 1, x + window); ++u) {
          const Vec3d q = positions[static_cast<std::size_t>(v) * s + u];
          if (q.finite()) {
            const Vec3d r = q - p;
            const double along = dot(r, n);
            if (dot(r, r) - along * along <= radius * radius) {
              inside.push_back(r);
            }
          }
        }
      }
      const int otherWindow =
          std::clamp(static_cast<int>(std::ceil(radius / std::max(otherSpacing, 1e-300))), 1, 3);
      const auto [otherVariance, otherCount] = other.spread(p, n, *hit, radius, otherWindow);
      double spread = 0;
      if (!inside.empty()) {
        spread += roughness(inside, n) / static_cast<double>(inside.size());
      }
      if (otherCount > 0) {
        spread += otherVariance / otherCount;
      }
      const double lod = 1.96 * (std::sqrt(spread) + options_.registrationError);
      out.stats.add(out.d[i], std::abs(dot(areas[i], n)), threshold, lod);
    }
  }
  return out;
}

/// The statistics: every leaf of `changes.work` sampled, its numbers added to the totals of
/// `diff` and to each changed patch at or above it. Returns which leaves changed (changedArea >
/// 0), in the order of `changes.work`.
std::vector<bool> addStatistics(LeafSampler& sampler, Changes& changes, RevisionDiff& diff,
                                Progress* progress) {
  const std::vector<Work>& work = changes.work;
  std::vector<bool> leafChanged(work.size(), false);
  for (std::size_t i = 0; i < work.size(); ++i) {
    const DisplacementStats stats = sampler.sample(work[i]).stats;
    leafChanged[i] = stats.changedArea > 0;
    diff.totals.merge(stats);
    for (std::optional<PatchKey> k = work[i].key; k; k = k->parent()) {
      const auto it = changes.patches.find(*k);
      if (it != changes.patches.end()) {
        it->second.stats.merge(stats);
      }
    }
    if (progress != nullptr) {
      progress->report("sampling", static_cast<double>(i + 1) / static_cast<double>(work.size()));
    }
  }
  return leafChanged;
}

/// The map, over the changed area: the leaves that changed (or every sampled one when none did),
/// and a tenth of that around them for context; their leaves are sampled again to be drawn.
/// Nullopt when none of them has an extent on the map.
std::optional<DisplacementMap> drawMap(LeafSampler& sampler, const Model& a, const Model& b,
                                       PatchSource& sourceB, const std::vector<Work>& work,
                                       const std::vector<bool>& leafChanged,
                                       const DiffOptions& options) {
  const bool any = std::find(leafChanged.begin(), leafChanged.end(), true) != leafChanged.end();
  TopDownGrid view;
  view.geographic = looksEcef(*sourceB.positions(PatchKey::root()));
  const auto extent = [&](const Work& w) {
    const Box3d& box = (w.onFrom ? a : b).at(w.key).globalBox;
    Rect2d r;
    for (int c = 0; c < 8 && !box.empty(); ++c) {
      r.extend(view.plane({(c & 1) ? box.max.x : box.min.x, (c & 2) ? box.max.y : box.min.y,
                           (c & 4) ? box.max.z : box.min.z}));
    }
    return r;
  };
  Rect2d area;
  for (std::size_t i = 0; i < work.size(); ++i) {
    if (leafChanged[i] || !any) {
      const Rect2d r = extent(work[i]);
      if (!r.empty()) {
        area.extend(r.min);
        area.extend(r.max);
      }
    }
  }
  if (area.empty()) {
    return std::nullopt;
  }
  const double gx = 0.1 * (area.max.x - area.min.x), gy = 0.1 * (area.max.y - area.min.y);
  area.min = {area.min.x - gx, area.min.y - gy};
  area.max = {area.max.x + gx, area.max.y + gy};
  DisplacementMap map;
  map.grid = TopDownGrid::fit(view.geographic, area.min.x, area.max.x, area.min.y, area.max.y,
                              options.mapSize);
  map.values.assign(map.grid.pixels(), std::numeric_limits<float>::quiet_NaN());
  for (std::size_t i = 0; i < work.size(); ++i) {
    if (extent(work[i]).intersects(area)) {
      const Sampled leaf = sampler.sample(work[i]);
      diff_detail::drawLeaf(*leaf.grid, leaf.d, map);
    }
    if (options.progress != nullptr) {
      options.progress->report("drawing",
                               static_cast<double>(i + 1) / static_cast<double>(work.size()));
    }
  }
  return map;
}

}  // namespace

void DisplacementStats::add(double d, double weight, double threshold, double lod) {
  ++samples;
  area += weight;
  if (std::abs(d) > threshold) {
    changedArea += weight;
    if (std::abs(d) > lod) {
      significantArea += weight;
      (d > 0 ? volumeGained : volumeLost) += std::abs(d) * weight;
    }
  }
  lodSum += weight * lod;
  lodMax = std::max(lodMax, lod);
  min = std::min(min, d);
  max = std::max(max, d);
  sum += weight * d;
  sumSquares += weight * d * d;
}

void DisplacementStats::merge(const DisplacementStats& o) {
  samples += o.samples;
  skipped += o.skipped;
  area += o.area;
  changedArea += o.changedArea;
  noise = std::max(noise, o.noise);
  min = std::min(min, o.min);
  max = std::max(max, o.max);
  sum += o.sum;
  sumSquares += o.sumSquares;
  lodSum += o.lodSum;
  lodMax = std::max(lodMax, o.lodMax);
  significantArea += o.significantArea;
  volumeGained += o.volumeGained;
  volumeLost += o.volumeLost;
}

double storageNoise(const Box3d& localBox) {
  if (localBox.empty()) {
    return 0;
  }
  double sum = 0;
  for (const auto& [lo, hi] : {std::pair{localBox.min.x, localBox.max.x},
                               {localBox.min.y, localBox.max.y},
                               {localBox.min.z, localBox.max.z}}) {
    const double m = std::max(std::abs(lo), std::abs(hi));
    if (m > 0) {
      // float32 has 24 significant bits: in [2^e, 2^(e+1)) the unit in the last place is 2^(e-23).
      const double half = std::ldexp(1.0, static_cast<int>(std::floor(std::log2(m))) - 24);
      sum += half * half;
    }
  }
  return std::sqrt(sum);
}

double DisplacementStats::mean() const {
  return area > 0 ? sum / area : kNaN;
}

double DisplacementStats::lodMean() const {
  return area > 0 ? lodSum / area : kNaN;
}

double DisplacementStats::rms() const {
  return area > 0 ? std::sqrt(sumSquares / area) : kNaN;
}

double DisplacementStats::maxAbs() const {
  return samples == 0 ? 0.0 : std::max(std::abs(min), std::abs(max));
}

RevisionDiff diffRevisions(LiveModel& live, std::shared_ptr<const ModelSnapshot> from,
                           std::shared_ptr<const ModelSnapshot> to, const DiffOptions& options) {
  const Model& a = *from->model;
  const Model& b = *to->model;
  checkComparable(a, b, options);
  RevisionDiff diff;
  diff.from = from->version;
  diff.to = to->version;
  diff.epsilon = options.epsilon;
  diff.registrationError = options.registrationError;
  const auto sourceA = liveSource(live, from);
  const auto sourceB = liveSource(live, to);
  Changes changes = findChanges(a, b);
  diff.sharedPatches = changes.shared;
  LeafSampler sampler(*sourceA, *sourceB, frontSign(a, *sourceA), options);
  const std::vector<bool> leafChanged = addStatistics(sampler, changes, diff, options.progress);
  if (options.mapSize > 0 && !changes.work.empty()) {
    diff.map = drawMap(sampler, a, b, *sourceB, changes.work, leafChanged, options);
  }
  sampler.clear();
  diff.patches.reserve(changes.patches.size());
  for (auto& [key, patch] : changes.patches) {
    diff.patches.push_back(std::move(patch));
  }
  return diff;
}

}  // namespace vsm::core
