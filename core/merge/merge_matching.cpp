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
#include "core/merge/merge_stages.hpp"
#include "core/merge/surface_caster.hpp"

namespace vsm::core::merge_stages {

namespace {

constexpr int kMaxNewLevels = 16;

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

/// The smallest k >= 0 with 2^k >= ratio.
int levelsFor(double ratio) {
  int k = 0;
  // A ratio that is a power of two up to rounding (e.g. 4.0000000001) needs no extra level; a
  // leaf already as fine as B (ratio <= 1, e.g. where B was merged before) needs none at all.
  while (k <= kMaxNewLevels && std::ldexp(1.0, k) < ratio * (1 - 1e-9)) {
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
/// no neighbouring B leaf at the same depth) is cast along B's normal there, up to `search` of
/// the target leaves it meets either way, into those target leaves. Throws "partly outside the
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
      const std::shared_ptr<const PatchGrid> grid = detail.positions(key);
      const int s = grid->size();
      auto at = [&](int x, int y) {
        return options.transform ? options.transform->apply(grid->global(x, y))
                                 : grid->global(x, y);
      };
      double search = 0;
      for (const std::size_t a : aOfB[i]) {
        search = std::max(search, aLeaves[a].spacing);
      }
      std::vector<CastRay> rays;
      Box3d reach;
      for (int y = 0; y < s; ++y) {
        for (int x = 0; x < s; ++x) {
          const bool onBorder = (west && x == 0) || (east && x == s - 1) || (south && y == 0) ||
                                (north && y == s - 1);
          if (!onBorder || !grid->defined(x, y)) {
            continue;
          }
          // B's normal: differences to the neighbours within the grid (one-sided on its sides).
          auto difference = [&](int x0, int y0, int x1, int y1) -> std::optional<Vec3d> {
            x0 = std::clamp(x0, 0, s - 1), x1 = std::clamp(x1, 0, s - 1);
            y0 = std::clamp(y0, 0, s - 1), y1 = std::clamp(y1, 0, s - 1);
            if (grid->defined(x0, y0) && grid->defined(x1, y1) && (x0 != x1 || y0 != y1)) {
              return at(x1, y1) - at(x0, y0);
            }
            if (grid->defined(x1, y1) && (x != x1 || y != y1)) {
              return at(x1, y1) - at(x, y);
            }
            if (grid->defined(x0, y0) && (x != x0 || y != y0)) {
              return at(x, y) - at(x0, y0);
            }
            return std::nullopt;
          };
          const std::optional<Vec3d> du = difference(x - 1, y, x + 1, y);
          const std::optional<Vec3d> dv = difference(x, y - 1, x, y + 1);
          if (!du || !dv) {
            continue;
          }
          const Vec3d n{du->y * dv->z - du->z * dv->y, du->z * dv->x - du->x * dv->z,
                        du->x * dv->y - du->y * dv->x};
          if (!(n.norm() > 0)) {
            continue;
          }
          const Vec3d p = at(x, y);
          rays.push_back({p, n, -search, search});
          reach.extend(p);
        }
      }
      if (rays.empty()) {
        return;
      }
      std::vector<std::shared_ptr<const PatchGrid>> grids;
      for (const std::size_t a : aOfB[i]) {
        grids.push_back(target.positions(aLeaves[a].key));
      }
      const SurfaceCaster onA(grids, std::nullopt, SurfaceCaster::Clip{grown(reach, search)});
      std::vector<std::optional<CastHit>> hits(rays.size());
      onA.cast(rays, hits);
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
                    "within the target's spacing), the first at " +
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
      bLeaves.push_back({key, box, false, {}, 0, {}});
      bReach = std::max(bReach, diagonal(box));
    }
  }

  // Candidates by boxes, a superset of the pairs the balls decide below: a leaf's Ball lies in
  // its box grown by the box's diagonal, and its search distance (its spacing) is at most half
  // that diagonal for grids of 3 x 3 and more, so a target leaf whose box grown by 1.5 times its
  // diagonal misses every B leaf's box grown by that leaf's diagonal meets nothing. Descending from
  // the root through such boxes keeps the cost with the affected subtree, not A's size (a parent's
  // box holds its children's).
  std::vector<TargetLeaf> aLeaves;
  std::vector<PatchKey> pending{PatchKey::root()};
  while (!pending.empty()) {
    const PatchKey key = pending.back();
    pending.pop_back();
    const PatchInfo& info = a.at(key);
    const Box3d reach = grown(info.globalBox, 1.5 * diagonal(info.globalBox) + bReach);
    if (!reach.intersects(bBox)) {
      continue;
    }
    if (!info.isLeaf()) {
      for (const PatchKey& child : a.children(key)) {
        pending.push_back(child);
      }
      continue;
    }
    TargetLeaf leaf{key, info.globalBox, {}, {}, 0};
    for (std::size_t i = 0; i < bLeaves.size(); ++i) {
      if (grown(info.globalBox, 1.5 * diagonal(info.globalBox) + diagonal(bLeaves[i].box))
              .intersects(bLeaves[i].box)) {
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
    Match match{leaf.key, {}, 1, leaf.spacing, {}};
    for (const std::size_t i : leaf.candidates) {
      if (leaf.ball.meets(bLeaves[i].ball, leaf.spacing + bLeaves[i].spacing)) {
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
