#include <algorithm>
#include <cmath>
#include <functional>
#include <memory>
#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "core/merge/merge_stages.hpp"

namespace vsm::core::merge_stages {

namespace {

constexpr int kMaxNewLevels = 16;

Box3d transformed(const Box3d& box, const std::optional<Mat4d>& transform) {
  if (!transform || box.empty()) {
    return box;
  }
  Box3d out;
  for (int c = 0; c < 8; ++c) {
    out.extend(transform->apply({(c & 1) ? box.max.x : box.min.x, (c & 2) ? box.max.y : box.min.y,
                                 (c & 4) ? box.max.z : box.min.z}));
  }
  return out;
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

/// Mean distance between defined horizontal and vertical grid neighbours, measured in the plane
/// of `frame` (0 when no two neighbours are defined): the spacing at which a patch samples the
/// surface as the merge places it, along `up`. Unlike PatchGrid::resolution (3D distances) it does
/// not grow with the slope, so a steep detail over a flat target still counts as finer.
double planeResolution(const PatchGrid& grid, const UpFrame& frame) {
  double sum = 0;
  std::size_t count = 0;
  auto add = [&](int x0, int y0, int x1, int y1) {
    if (grid.defined(x0, y0) && grid.defined(x1, y1)) {
      const Vec2d a = frame.project(grid.global(x0, y0));
      const Vec2d b = frame.project(grid.global(x1, y1));
      sum += std::sqrt((b.u - a.u) * (b.u - a.u) + (b.v - a.v) * (b.v - a.v));
      ++count;
    }
  };
  for (int y = 0; y < grid.size(); ++y) {
    for (int x = 0; x < grid.size(); ++x) {
      if (x + 1 < grid.size()) {
        add(x, y, x + 1, y);
      }
      if (y + 1 < grid.size()) {
        add(x, y, x, y + 1);
      }
    }
  }
  return count == 0 ? 0 : sum / static_cast<double>(count);
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
  const Vec3d up = options.up ? *options.up : defaultUp(bBox);
  MergePlan plan{UpFrame(bBox.center(), up)};
  plan.up = up;
  const UpFrame& frame = plan.frame;
  const Rect2d bFoot = frame.footprint(bBox);
  const Rect2d aFoot = frame.footprint(aBox);
  if (!aFoot.intersects(bFoot)) {
    throw Error(ErrorCode::InvalidArgument, "detail model lies outside the target");
  }
  const double tolerance =
      1e-6 * std::max({aFoot.max.u - aFoot.min.u, aFoot.max.v - aFoot.min.v, 1.0});
  if (!aFoot.contains(bFoot, tolerance)) {
    throw Error(ErrorCode::InvalidArgument,
                "detail model lies partly outside the target (its footprint is not inside the "
                "target's)");
  }

  // B's leaves with their footprints (metadata only), grown by how far outside its cells B's
  // surface still reaches (SurfaceSampler::kBorderTolerance of a cell; a cell's projection is no
  // longer than the leaf's footprint's diagonal): a new patch whose border vertex lies just
  // outside B takes B there as its neighbour across that border does.
  std::vector<std::pair<PatchKey, Rect2d>>& bLeaves = plan.bLeaves;
  for (const PatchKey& key : b.leaves()) {
    Rect2d foot = frame.footprint(transformed(b.at(key).globalBox, options.transform));
    if (!foot.empty()) {
      const double margin = SurfaceSampler::kBorderTolerance *
                            std::hypot(foot.max.u - foot.min.u, foot.max.v - foot.min.v);
      foot.min = {foot.min.u - margin, foot.min.v - margin};
      foot.max = {foot.max.u + margin, foot.max.v + margin};
      bLeaves.emplace_back(key, foot);
    }
  }

  // A's leaves under B: descend from the root through patches whose footprint meets B's, so the
  // cost follows the affected subtree, not A's size (a parent's box contains its children's).
  std::vector<Match>& matches = plan.matches;
  std::vector<PatchKey> pending{PatchKey::root()};
  std::vector<bool> bUsed(bLeaves.size(), false);
  while (!pending.empty()) {
    const PatchKey key = pending.back();
    pending.pop_back();
    const PatchInfo& info = a.at(key);
    const Rect2d foot = frame.footprint(info.globalBox);
    if (!foot.intersects(bFoot)) {
      continue;
    }
    if (!info.isLeaf()) {
      for (const PatchKey& child : a.children(key)) {
        pending.push_back(child);
      }
      continue;
    }
    Match match{key, {}, 1};
    for (std::size_t i = 0; i < bLeaves.size(); ++i) {
      if (bLeaves[i].second.intersects(foot)) {
        match.detail.push_back(i);
        bUsed[i] = true;
      }
    }
    if (!match.detail.empty()) {
      matches.push_back(std::move(match));
    }
  }
  // planeResolution and the block footprints (for the samplers below) of each B leaf a target
  // leaf meets (reading it is most of the matching's time), in parallel on the executor.
  std::vector<double> bResolution(bLeaves.size(), 0);
  std::vector<std::vector<Rect2d>>& bBlocks = plan.bBlocks;
  bBlocks.resize(bLeaves.size());
  {
    std::vector<std::function<void()>> tasks;
    for (std::size_t i = 0; i < bLeaves.size(); ++i) {
      if (bUsed[i]) {
        tasks.emplace_back([&, i] {
          checkCancelled(options);
          const std::shared_ptr<const PatchGrid> grid = detail.positions(bLeaves[i].first);
          bResolution[i] = planeResolution(*grid, frame);
          bBlocks[i] = SurfaceSampler::blockFootprints(*grid, frame, options.transform);
        });
      }
    }
    runTasks(options.executor, std::move(tasks));
  }
  for (Match& match : matches) {
    double resolutionSum = 0;
    std::size_t resolutionCount = 0;
    for (const std::size_t i : match.detail) {
      if (bResolution[i] > 0) {
        resolutionSum += bResolution[i];
        ++resolutionCount;
      }
    }
    const double aResolution = planeResolution(*target.positions(match.target), frame);
    const double ratio = resolutionCount > 0 && aResolution > 0
                             ? aResolution / (resolutionSum / resolutionCount)
                             : 2.0;  // unknown: one level
    match.levels = levelsFor(ratio);
    if (match.levels > kMaxNewLevels || match.target.depth + match.levels > PatchKey::kMaxDepth) {
      throw Error(ErrorCode::InvalidArgument,
                  "merge: patch " + match.target.toString() + " would need more than " +
                      std::to_string(kMaxNewLevels) + " new levels (resolution ratio " +
                      std::to_string(ratio) + ")");
    }
  }
  if (matches.empty()) {
    throw Error(ErrorCode::InvalidArgument, "detail model lies outside the target");
  }
  std::sort(matches.begin(), matches.end(),
            [](const Match& x, const Match& y) { return x.target < y.target; });
  plan.detailLeaves = static_cast<std::size_t>(std::count(bUsed.begin(), bUsed.end(), true));
  return plan;
}

}  // namespace vsm::core::merge_stages
