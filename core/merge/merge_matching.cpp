#include <algorithm>
#include <cmath>
#include <cstdio>
#include <functional>
#include <limits>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "core/grid/vec_ops.hpp"
#include "core/merge/merge_stages.hpp"
#include "core/merge/surface_caster.hpp"

namespace vsm::core::merge_stages {

namespace {

constexpr int kMaxNewLevels = 16;

/// The Balls of `grid`'s blocks of SurfaceCaster::kBlockCells cells (the blocks blockBoxes()
/// describes, in its order): of each block's defined vertices, in global coordinates (after
/// `transform`). Empty for a block without any.
std::vector<Ball> blockBalls(const PatchGrid& grid, const std::optional<Mat4d>& transform) {
  constexpr int kCells = SurfaceCaster::kBlockCells;
  const int s = grid.size();
  const int perSide = (s - 1 + kCells - 1) / kCells;
  std::vector<Ball> balls;
  balls.reserve(static_cast<std::size_t>(perSide) * perSide);
  std::vector<Vec3d> points;
  for (int by = 0; by < perSide; ++by) {
    for (int bx = 0; bx < perSide; ++bx) {
      points.clear();
      for (int y = by * kCells; y <= std::min((by + 1) * kCells, s - 1); ++y) {
        for (int x = bx * kCells; x <= std::min((bx + 1) * kCells, s - 1); ++x) {
          if (grid.defined(x, y)) {
            points.push_back(transform ? transform->apply(grid.global(x, y)) : grid.global(x, y));
          }
        }
      }
      balls.push_back(ballOf(points));
    }
  }
  return balls;
}

/// A new vertex looks for B's surface this many of its target leaf's spacings either way along
/// its normal, and at least kSearchDetailSpacings of B's finest spacing: B's features and
/// changes (a bump, a rockfall's cavity, a registration offset) may lie farther from A's surface
/// than one of its cells (merge.border's details are 5 to 9 m off a 3.4 m target; a 0.5 m
/// cavity scanned at 6 cm, merged into a model already that fine, needs 8 of its spacings).
constexpr double kSearchSpacings = 4;
constexpr double kSearchDetailSpacings = 16;

Box3d transformed(const Box3d& box, const std::optional<Mat4d>& transform) {
  if (!transform || box.empty()) {
    return box;
  }
  return transformBox(*transform, box);
}

/// `box` grown by `margin` on every side.
Box3d grown(Box3d box, double margin) {
  if (!box.empty()) {
    box.min = box.min - Vec3d{margin, margin, margin};
    box.max = box.max + Vec3d{margin, margin, margin};
  }
  return box;
}

double diagonal(const Box3d& box) {
  return box.empty() ? 0 : box.size().norm();
}

/// The smallest k >= 0 with 2^k >= ratio, allowing the new level to be an eighth coarser than B:
/// spacings on a curved or uneven surface scatter around their nominal ratio (a tunnel's leaves
/// read 3.93 to 4.06 for a detail 4 times finer), and without that slack neighbouring leaves
/// would take 2 or 3 levels by that noise: twice B's density, and T-junctions between them. A
/// leaf already as fine as B (ratio <= 1, e.g. where B was merged before) needs no level at all.
int levelsFor(double ratio) {
  int k = 0;
  while (k <= kMaxNewLevels && std::ldexp(1.0, k) < ratio * (1 - 1.0 / 8)) {
    ++k;
  }
  return k;
}

std::string where(const Vec3d& p) {
  char text[96];
  std::snprintf(text, sizeof text, "(%.3f, %.3f, %.3f)", p.x, p.y, p.z);
  return text;
}

/// What matching reads of a target leaf.
struct TargetLeaf {
  PatchKey key;
  Box3d box;
  std::vector<std::size_t> candidates;  // B leaves near its box
  Ball ball;
  double spacing = 0;
  double search = 0;  // kSearchSpacings times spacing
};

/// The target's vertices around `key` from its neighbours at the same depth (Ring): each side
/// only where the neighbour exists and its border line is the leaf's (within `tolerance`; a
/// foreign or inconsistent neighbour is left out, and the leaf's normals there are one-sided).
Ring ringOf(MergeTarget& target, const PatchKey& key, const PatchGrid& grid, double tolerance) {
  Ring ring;
  const int s = grid.size();
  const std::uint64_t side = std::uint64_t{1} << key.depth;
  auto take = [&](std::int64_t dx, std::int64_t dy, std::vector<Vec3d>& out) {
    const std::int64_t x = static_cast<std::int64_t>(key.x) + dx;
    const std::int64_t y = static_cast<std::int64_t>(key.y) + dy;
    if (x < 0 || y < 0 || static_cast<std::uint64_t>(x) >= side ||
        static_cast<std::uint64_t>(y) >= side) {
      return;
    }
    const PatchKey neighbour{key.depth, static_cast<std::uint32_t>(x),
                             static_cast<std::uint32_t>(y)};
    if (target.model().find(neighbour) == nullptr) {
      return;
    }
    const std::shared_ptr<const PatchGrid> other = target.positions(neighbour);
    if (other->size() != s) {
      return;
    }
    // Vertex t along the shared border: ours (mine), the neighbour's copy of it (shared) and the
    // neighbour's next one inward (beyond).
    std::vector<Vec3d> beyond(static_cast<std::size_t>(s));
    for (int t = 0; t < s; ++t) {
      const int mx = dx < 0 ? 0 : dx > 0 ? s - 1 : t, my = dy < 0 ? 0 : dy > 0 ? s - 1 : t;
      const int sx = dx < 0 ? s - 1 : dx > 0 ? 0 : t, sy = dy < 0 ? s - 1 : dy > 0 ? 0 : t;
      const int bx = dx < 0 ? s - 2 : dx > 0 ? 1 : t, by = dy < 0 ? s - 2 : dy > 0 ? 1 : t;
      const bool mine = grid.defined(mx, my), shared = other->defined(sx, sy);
      if (mine != shared ||
          (mine && (grid.global(mx, my) - other->global(sx, sy)).norm() > tolerance)) {
        return;
      }
      const double nan = std::numeric_limits<double>::quiet_NaN();
      beyond[static_cast<std::size_t>(t)] =
          other->defined(bx, by) ? other->global(bx, by) : Vec3d{nan, nan, nan};
    }
    out = std::move(beyond);
  };
  take(-1, 0, ring.west);
  take(1, 0, ring.east);
  take(0, -1, ring.south);
  take(0, 1, ring.north);
  return ring;
}

/// B's outer border must lie on A's surface: each border vertex of a B leaf (on a grid side with
/// no neighbouring B leaf at the same depth) is cast along B's normal there, and where that
/// misses along the leaf's mean normal, up to `search` of the target leaves it meets either way,
/// into those target leaves. Throws "partly outside the
/// target" with where and how many when some miss: B leaves A's surface there (beside it, beyond
/// its border, or over its holes), and placing along A's normals would silently drop that part.
void checkBorderOnTarget(MergeTarget& target, PatchSource& detail, const MergePlan& plan,
                         const std::vector<TargetLeaf>& aLeaves,
                         const std::vector<std::vector<std::size_t>>& aOfB,
                         const MergeOptions& options) {
  const Model& b = detail.model();
  struct Outcome {
    std::size_t border = 0, missed = 0;
    Vec3d first;
  };
  std::vector<Outcome> outcomes(plan.bLeaves.size());
  std::vector<std::function<void()>> tasks;
  for (std::size_t i = 0; i < plan.bLeaves.size(); ++i) {
    if (aOfB[i].empty()) {
      continue;
    }
    tasks.emplace_back([&, i] {
      checkCancelled(options);
      const DetailLeaf& leaf = plan.bLeaves[i];
      const PatchKey& key = leaf.key;
      const std::uint64_t side = std::uint64_t{1} << key.depth;
      auto open = [&](std::int64_t dx, std::int64_t dy) {
        const std::int64_t x = static_cast<std::int64_t>(key.x) + dx;
        const std::int64_t y = static_cast<std::int64_t>(key.y) + dy;
        return x < 0 || y < 0 || static_cast<std::uint64_t>(x) >= side ||
               static_cast<std::uint64_t>(y) >= side ||
               b.find(PatchKey{key.depth, static_cast<std::uint32_t>(x),
                               static_cast<std::uint32_t>(y)}) == nullptr;
      };
      const bool west = open(-1, 0), east = open(1, 0), south = open(0, -1), north = open(0, 1);
      if (!west && !east && !south && !north) {
        return;
      }
      std::shared_ptr<const PatchGrid> grid = detail.positions(key);
      const int s = grid->size();
      auto at = [&](int x, int y) {
        return options.transform ? options.transform->apply(grid->global(x, y))
                                 : grid->global(x, y);
      };
      double search = 0;
      for (const std::size_t a : aOfB[i]) {
        search = std::max(search, aLeaves[a].search);
      }
      // B's normal at (x, y): vec::vertexNormal of the grid as the merge sees it (transformed).
      struct Transformed {
        const PatchGrid& grid;
        const std::function<Vec3d(int, int)>& at;
        int size() const { return grid.size(); }
        bool defined(int x, int y) const { return grid.defined(x, y); }
        Vec3d global(int x, int y) const { return at(x, y); }
      };
      const std::function<Vec3d(int, int)> global = at;
      const Transformed view{*grid, global};
      auto normalAt = [&](int x, int y) -> std::optional<Vec3d> {
        const Vec3d n = vec::vertexNormal(view, x, y);
        return n.finite() ? std::optional<Vec3d>(n) : std::nullopt;
      };
      // The leaf's mean normal, for the vertices whose own normal is no guide: at the foot of a
      // groove or on a rough scan a border vertex's normal may run along A instead of across it.
      // Over every kMeanStride-th vertex each way and the border's: a direction, not a
      // measurement.
      constexpr int kMeanStride = 4;
      Vec3d mean;
      std::vector<CastRay> rays;
      Box3d reach;
      for (int y = 0; y < s; ++y) {
        const bool row = y % kMeanStride == 0;
        const bool borderRow = (south && y == 0) || (north && y == s - 1);
        if (!row && !borderRow && !west && !east) {
          continue;
        }
        for (int x = 0; x < s; ++x) {
          const bool onBorder = borderRow || (west && x == 0) || (east && x == s - 1);
          const bool inMean = row && x % kMeanStride == 0;
          if ((!onBorder && !inMean) || !grid->defined(x, y)) {
            continue;
          }
          const std::optional<Vec3d> n = normalAt(x, y);
          if (!n) {
            continue;
          }
          mean = mean + *n;
          if (onBorder) {
            const Vec3d p = at(x, y);
            rays.push_back({p, *n, -search, search});
            reach.extend(p);
          }
        }
      }
      if (rays.empty()) {
        return;
      }
      // The A leaves within reach, each copied and unpinned at once (the caster keeps its own
      // copy of what it uses): a tight budget need not hold them all at a time.
      grid.reset();
      const Box3d clip = grown(reach, search);
      std::vector<std::shared_ptr<const PatchGrid>> grids;
      for (const std::size_t a : aOfB[i]) {
        if (aLeaves[a].box.intersects(clip)) {
          grids.push_back(std::make_shared<const PatchGrid>(*target.positions(aLeaves[a].key)));
        }
      }
      const SurfaceCaster onA(grids, std::nullopt, SurfaceCaster::Clip{clip});
      grids.clear();
      std::vector<std::optional<CastHit>> hits(rays.size());
      onA.cast(rays, hits);
      for (std::size_t r = 0; r < rays.size(); ++r) {
        if (!hits[r]) {
          hits[r] = onA.cast({rays[r].origin, mean, -search, search});
        }
      }
      Outcome& outcome = outcomes[i];
      outcome.border = rays.size();
      for (std::size_t r = 0; r < rays.size(); ++r) {
        if (!hits[r]) {
          if (outcome.missed++ == 0) {
            outcome.first = rays[r].origin;
          }
        }
      }
    });
  }
  runTasks(options.executor, std::move(tasks));
  std::size_t border = 0, missed = 0;
  std::optional<Vec3d> first;
  for (const Outcome& outcome : outcomes) {
    border += outcome.border;
    missed += outcome.missed;
    if (outcome.missed > 0 && !first) {
      first = outcome.first;
    }
  }
  if (missed > 0) {
    throw Error(ErrorCode::InvalidArgument,
                "detail model lies partly outside the target: " + std::to_string(missed) +
                    " of its " + std::to_string(border) +
                    " border vertices are not over the target's surface (along their normal, "
                    "within 4 of the target's spacings), the first at " +
                    where(*first));
  }
}

}  // namespace

MergePlan matchLeaves(MergeTarget& target, PatchSource& detail, const MergeOptions& options) {
  const Model& a = target.model();
  const Model& b = detail.model();
  const Box3d bBox = transformed(b.at(PatchKey::root()).globalBox, options.transform);
  const Box3d aBox = a.at(PatchKey::root()).globalBox;
  if (bBox.empty() || aBox.empty()) {
    throw Error(ErrorCode::InvalidArgument, "merge: a model has no defined vertex");
  }
  MergePlan plan;
  std::vector<DetailLeaf>& bLeaves = plan.bLeaves;
  double bReach = 0;  // the largest B leaf's diagonal
  for (const PatchKey& key : b.leaves()) {
    const Box3d box = transformed(b.at(key).globalBox, options.transform);
    if (!box.empty()) {
      bLeaves.push_back({key, box, false, {}, 0, {}, {}});
      bReach = std::max(bReach, diagonal(box));
    }
  }

  // B's finest level's resolution (its metadata, a property of the surface alone).
  double bFinest = 0;
  for (const LevelSummary& level : b.levels()) {
    if (level.depth == b.maxDepth()) {
      bFinest = level.resolution;
    }
  }
  const double bSearch = kSearchDetailSpacings * bFinest;

  // Candidates by boxes, a superset of the pairs the balls decide below: a leaf's Ball lies in
  // its box grown by the box's diagonal, and its search distance is at most kSearchSpacings
  // diagonals / (grid size - 1) for a regular grid, or bSearch, so a target leaf whose box grown
  // by that much misses every B leaf's box grown by that leaf's diagonal meets nothing.
  // Descending from the root through such boxes keeps the cost with the affected subtree, not A's
  // size (a parent's box holds its children's).
  std::vector<TargetLeaf> aLeaves;
  std::vector<PatchKey> pending{PatchKey::root()};
  while (!pending.empty()) {
    const PatchKey key = pending.back();
    pending.pop_back();
    const PatchInfo& info = a.at(key);
    const double aReach =
        diagonal(info.globalBox) * (1 + kSearchSpacings / (a.gridSize() - 1)) + bSearch;
    const Box3d reach = grown(info.globalBox, aReach + bReach);
    if (!reach.intersects(bBox)) {
      continue;
    }
    if (!info.isLeaf()) {
      for (const PatchKey& child : a.children(key)) {
        pending.push_back(child);
      }
      continue;
    }
    TargetLeaf leaf{key, info.globalBox, {}, {}, 0, 0};
    for (std::size_t i = 0; i < bLeaves.size(); ++i) {
      if (grown(info.globalBox, aReach + diagonal(bLeaves[i].box)).intersects(bLeaves[i].box)) {
        leaf.candidates.push_back(i);
      }
    }
    if (!leaf.candidates.empty()) {
      aLeaves.push_back(std::move(leaf));
    }
  }

  // The candidates' grids: balls and spacings on the surface (in 3D: a wall has its real
  // spacing), and B's block boxes for the casters placing builds, in parallel on the executor.
  std::vector<bool> bCandidate(bLeaves.size(), false);
  for (const TargetLeaf& leaf : aLeaves) {
    for (const std::size_t i : leaf.candidates) {
      bCandidate[i] = true;
    }
  }
  {
    std::vector<std::function<void()>> tasks;
    for (std::size_t i = 0; i < bLeaves.size(); ++i) {
      if (bCandidate[i]) {
        tasks.emplace_back([&, i] {
          checkCancelled(options);
          DetailLeaf& leaf = bLeaves[i];
          const std::shared_ptr<const PatchGrid> grid = detail.positions(leaf.key);
          leaf.ball = ballOf(*grid, options.transform);
          leaf.spacing = gridSpacing(*grid, options.transform).mean;
          leaf.blocks = SurfaceCaster::blockBoxes(*grid, options.transform);
          leaf.blockBalls = blockBalls(*grid, options.transform);
          leaf.read = true;
        });
      }
    }
    for (TargetLeaf& leaf : aLeaves) {
      tasks.emplace_back([&] {
        checkCancelled(options);
        const std::shared_ptr<const PatchGrid> grid = target.positions(leaf.key);
        leaf.ball = ballOf(*grid);
        leaf.spacing = gridSpacing(*grid).mean;
        leaf.search = std::max(kSearchSpacings * leaf.spacing, bSearch);
      });
    }
    runTasks(options.executor, std::move(tasks));
  }

  // The pairs: balls that meet within the target leaf's search distance and the B leaf's spacing
  // (functions of the surfaces alone, so the same decisions however the scene is turned).
  std::vector<std::vector<std::size_t>> aOfB(bLeaves.size());
  std::vector<Match>& matches = plan.matches;
  for (std::size_t l = 0; l < aLeaves.size(); ++l) {
    const TargetLeaf& leaf = aLeaves[l];
    Match match{leaf.key, {}, 1, leaf.search, {}};
    for (const std::size_t i : leaf.candidates) {
      if (leaf.ball.meets(bLeaves[i].ball, leaf.search + bLeaves[i].spacing)) {
        match.detail.push_back(i);
        aOfB[i].push_back(l);
      }
    }
    if (match.detail.empty()) {
      continue;
    }
    double spacingSum = 0;
    std::size_t spacingCount = 0;
    for (const std::size_t i : match.detail) {
      if (bLeaves[i].spacing > 0) {
        spacingSum += bLeaves[i].spacing;
        ++spacingCount;
      }
    }
    const double ratio = spacingCount > 0 && leaf.spacing > 0
                             ? leaf.spacing / (spacingSum / static_cast<double>(spacingCount))
                             : 2.0;  // unknown: one level
    match.levels = levelsFor(ratio);
    if (match.levels > kMaxNewLevels || match.target.depth + match.levels > PatchKey::kMaxDepth) {
      throw Error(ErrorCode::InvalidArgument,
                  "merge: patch " + match.target.toString() + " would need more than " +
                      std::to_string(kMaxNewLevels) + " new levels (resolution ratio " +
                      std::to_string(ratio) + ")");
    }
    matches.push_back(std::move(match));
  }
  if (matches.empty()) {
    throw Error(ErrorCode::InvalidArgument, "detail model lies outside the target");
  }
  for (std::size_t i = 0; i < bLeaves.size(); ++i) {
    if (bLeaves[i].read && aOfB[i].empty()) {
      throw Error(ErrorCode::InvalidArgument,
                  "detail model lies partly outside the target: its patch " +
                      bLeaves[i].key.toString() + " around " + where(bLeaves[i].ball.centre) +
                      " is farther than the target's spacing from every target patch");
    }
  }
  for (std::size_t i = 0; i < bLeaves.size(); ++i) {
    if (!bLeaves[i].read) {
      // Far from every target leaf: the balls cannot meet (see the candidates above).
      throw Error(ErrorCode::InvalidArgument,
                  "detail model lies partly outside the target: its patch " +
                      bLeaves[i].key.toString() + " around " + where(bLeaves[i].box.center()) +
                      " is far from every target patch");
    }
  }
  checkBorderOnTarget(target, detail, plan, aLeaves, aOfB, options);

  // The rings of the matched leaves, read before placing changes any leaf (a leaf resampled in
  // place is replaced while its neighbours are still to be placed).
  {
    std::vector<std::function<void()>> tasks;
    for (Match& match : matches) {
      tasks.emplace_back([&] {
        checkCancelled(options);
        const std::shared_ptr<const PatchGrid> grid = target.positions(match.target);
        const Box3d box = grid->globalBox();
        const double largest =
            std::max({std::fabs(box.min.x), std::fabs(box.min.y), std::fabs(box.min.z),
                      std::fabs(box.max.x), std::fabs(box.max.y), std::fabs(box.max.z)});
        match.ring = ringOf(target, match.target, *grid, 1e-3 * match.search + 1e-6 * largest);
      });
    }
    runTasks(options.executor, std::move(tasks));
  }
  std::sort(matches.begin(), matches.end(),
            [](const Match& x, const Match& y) { return x.target < y.target; });
  plan.detailLeaves = static_cast<std::size_t>(
      std::count_if(aOfB.begin(), aOfB.end(), [](const auto& v) { return !v.empty(); }));
  return plan;
}

}  // namespace vsm::core::merge_stages
