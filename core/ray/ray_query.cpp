#include "core/ray/ray_query.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <map>
#include <numbers>
#include <string>
#include <utility>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/grid/vec_ops.hpp"
#include "core/merge/surface_caster.hpp"

namespace vsm::core {

namespace {

using vec::cross;
using vec::dot;

/// Block boxes kept per call (about 12 KiB each for 257 x 257 grids); the cache starts over when
/// full.
constexpr std::size_t kCachedBlockBoxes = 1024;
/// Working memory of a ray's caster per cell built: SurfaceCaster::bytes()'s arrays (a vertex,
/// a cell, its projected box and its bin entries: about 110 bytes; caster_bench's resident growth
/// is 63 bytes per triangle, two per cell), with room for cells in many bins.
constexpr std::size_t kBytesPerCell = 320;
/// Per vertex of a grid the caster reads: its index of built cells (4 bytes) and, for the grid
/// being read, its vertex indices (4 bytes, one grid at a time; 29 kept as the earlier bound).
constexpr std::size_t kBytesPerGridVertex = 4;
constexpr std::size_t kBytesPerReadVertex = 29;

std::string rayName(std::size_t index) {
  return "ray " + std::to_string(index + 1);
}

/// The unit normal of `grid`'s surface at grid coordinates (x, y) (a hit's, on or within the
/// border tolerance of a cell): of the cell nearest to (x, y) among those around it with three or
/// four defined corners, the bilinear surface's cross(d/ds, d/dt) at the point clamped onto the
/// cell, or the triangle's normal; turned against `d`. A cell degenerate at that point gives the
/// cross product of its diagonals, one with no area at all -d.
Vec3d hitNormal(const PatchGrid& grid, double x, double y, const Vec3d& d) {
  const int n = grid.size();
  const int fx = std::clamp(static_cast<int>(std::floor(x)), 0, n - 2);
  const int fy = std::clamp(static_cast<int>(std::floor(y)), 0, n - 2);
  int bestX = -1, bestY = -1;
  double bestOutside = std::numeric_limits<double>::infinity();
  for (int cy = std::max(0, fy - 1); cy <= std::min(n - 2, fy + 1); ++cy) {
    for (int cx = std::max(0, fx - 1); cx <= std::min(n - 2, fx + 1); ++cx) {
      const std::array<bool, 4> defined{grid.defined(cx, cy), grid.defined(cx + 1, cy),
                                        grid.defined(cx + 1, cy + 1), grid.defined(cx, cy + 1)};
      const int count = static_cast<int>(std::count(defined.begin(), defined.end(), true));
      if (count < 3) {
        continue;
      }
      const double s = x - cx, t = y - cy;
      double outside = std::hypot(std::max({0.0, -s, s - 1}), std::max({0.0, -t, t - 1}));
      if (count == 3) {
        // The triangle is the square less the half at its missing corner.
        const double cut = !defined[0]   ? 1 - s - t
                           : !defined[1] ? s - t
                           : !defined[2] ? s + t - 1
                                         : t - s;
        outside = std::max(outside, std::max(0.0, cut) / std::numbers::sqrt2);
      }
      if (outside < bestOutside) {
        bestOutside = outside;
        bestX = cx;
        bestY = cy;
      }
    }
  }
  const Vec3d away = d * -1.0;
  if (bestX < 0) {
    return away;
  }
  const std::array<std::pair<int, int>, 4> corners{
      std::pair{bestX, bestY}, {bestX + 1, bestY}, {bestX + 1, bestY + 1}, {bestX, bestY + 1}};
  std::array<Vec3d, 4> p{};
  std::array<bool, 4> defined{};
  for (int k = 0; k < 4; ++k) {
    defined[k] = grid.defined(corners[k].first, corners[k].second);
    if (defined[k]) {
      p[k] = grid.global(corners[k].first, corners[k].second);
    }
  }
  Vec3d normal;
  if (defined[0] && defined[1] && defined[2] && defined[3]) {
    const double s = std::clamp(x - bestX, 0.0, 1.0), t = std::clamp(y - bestY, 0.0, 1.0);
    const Vec3d du = (p[1] - p[0]) * (1 - t) + (p[2] - p[3]) * t;
    const Vec3d dv = (p[3] - p[0]) * (1 - s) + (p[2] - p[1]) * s;
    normal = cross(du, dv);
    if (!(normal.norm() > 0)) {
      normal = cross(p[2] - p[0], p[3] - p[1]);
    }
  } else {
    std::array<Vec3d, 3> tri{};
    int m = 0;
    for (int k = 0; k < 4; ++k) {
      if (defined[k]) {
        tri[m++] = p[k];
      }
    }
    normal = cross(tri[1] - tri[0], tri[2] - tri[0]);
  }
  const double length = normal.norm();
  if (!(length > 0) || !std::isfinite(length)) {
    return away;
  }
  normal = normal * (1 / length);
  return dot(normal, d) > 0 ? normal * -1.0 : normal;
}

void checkRay(const Ray& ray, std::size_t index) {
  if (!ray.origin.finite()) {
    throw Error(ErrorCode::InvalidArgument, rayName(index) + ": the origin must be finite");
  }
  const double length = ray.direction.norm();
  if (!ray.direction.finite() || !(length > 0) || !std::isfinite(length)) {
    throw Error(ErrorCode::InvalidArgument,
                rayName(index) + ": the direction must be finite and not zero");
  }
  if (!(ray.maxDistance >= 0)) {
    throw Error(ErrorCode::InvalidArgument,
                rayName(index) + ": the max distance must be a number >= 0");
  }
}

/// What a call keeps of a leaf: its grid while rays use it, and its block boxes.
struct LeafData {
  std::shared_ptr<const PatchGrid> grid;
  const std::vector<Box3d>* blocks = nullptr;
};

}  // namespace

std::vector<std::optional<RayHit>> castRays(const Model& model, std::span<const Ray> rays,
                                            const Model::GridLoader& load, const RayLimits& limits,
                                            const RayWorkCharge& charge) {
  if (rays.size() > limits.rays) {
    throw Error(ErrorCode::InvalidArgument, std::to_string(rays.size()) + " rays, more than the " +
                                                std::to_string(limits.rays) +
                                                " of one query; split the query");
  }
  for (std::size_t i = 0; i < rays.size(); ++i) {
    checkRay(rays[i], i);
  }
  std::vector<std::optional<RayHit>> hits(rays.size());
  const PatchInfo* root = model.find(PatchKey::root());
  if (root == nullptr) {
    return hits;
  }
  const Box3d rootBox = SurfaceCaster::grownBox(root->globalBox);
  constexpr std::size_t kCellsPerBlock =
      std::size_t{SurfaceCaster::kBlockCells} * SurfaceCaster::kBlockCells;
  std::map<PatchKey, std::vector<Box3d>> blockBoxes;
  // The grids of the last ray, so that the next one reads again only what it newly meets; at
  // most two rays' leaves are held.
  std::map<PatchKey, std::shared_ptr<const PatchGrid>> held;
  for (std::size_t i = 0; i < rays.size(); ++i) {
    const Ray& ray = rays[i];
    const Vec3d d = vec::unit(ray.direction);
    const auto segment = clipToBox(ray.origin, d, 0, ray.maxDistance, rootBox);
    if (!segment) {
      held.clear();
      continue;
    }
    const auto [t0, t1] = *segment;
    // The leaves whose grown box the segment meets.
    const std::vector<PatchKey> leaves = model.leavesWhere([&](const Box3d& box) {
      return clipToBox(ray.origin, d, t0, t1, SurfaceCaster::grownBox(box)).has_value();
    });
    if (leaves.size() > limits.leavesPerRay) {
      throw Error(ErrorCode::InvalidArgument,
                  rayName(i) + " is too long: it meets " + std::to_string(leaves.size()) +
                      " leaves of the model, more than the " + std::to_string(limits.leavesPerRay) +
                      " one ray may read; shorten it with a max distance");
    }
    std::map<PatchKey, std::shared_ptr<const PatchGrid>> grids;
    std::vector<std::shared_ptr<const PatchGrid>> casterGrids;
    std::vector<PatchKey> casterLeaves;
    std::vector<std::vector<Box3d>> kept;  // per caster grid: the blocks the segment meets
    std::size_t cells = 0, gridVertices = 0, largestGrid = 0;
    for (const PatchKey& key : leaves) {
      const auto was = held.find(key);
      std::shared_ptr<const PatchGrid> grid = was != held.end() ? was->second : load(model.at(key));
      grids[key] = grid;
      if (grid == nullptr) {
        continue;
      }
      auto boxes = blockBoxes.find(key);
      if (boxes == blockBoxes.end()) {
        if (blockBoxes.size() >= kCachedBlockBoxes) {
          blockBoxes.clear();
        }
        boxes = blockBoxes.emplace(key, SurfaceCaster::blockBoxes(*grid, std::nullopt)).first;
      }
      std::vector<Box3d> meeting(boxes->second.size());
      std::size_t count = 0;
      for (std::size_t b = 0; b < meeting.size(); ++b) {
        if (!boxes->second[b].empty() &&
            clipToBox(ray.origin, d, t0, t1, SurfaceCaster::grownBox(boxes->second[b]))) {
          meeting[b] = boxes->second[b];
          ++count;
        }
      }
      if (count == 0) {
        continue;
      }
      cells += count * kCellsPerBlock;
      if (cells > limits.cellsPerRay) {
        throw Error(ErrorCode::InvalidArgument,
                    rayName(i) + " is too long: it passes through more than " +
                        std::to_string(limits.cellsPerRay) +
                        " cells' worth of the surface's blocks; shorten it with a max distance");
      }
      const std::size_t vertices = static_cast<std::size_t>(grid->size()) * grid->size();
      gridVertices += vertices;
      largestGrid = std::max(largestGrid, vertices);
      casterGrids.push_back(std::move(grid));
      casterLeaves.push_back(key);
      kept.push_back(std::move(meeting));
    }
    held = std::move(grids);
    if (casterGrids.empty()) {
      continue;
    }
    std::shared_ptr<const void> hold;
    if (charge) {
      hold = charge(cells * kBytesPerCell + gridVertices * kBytesPerGridVertex +
                    largestGrid * kBytesPerReadVertex);
    }
    SurfaceCaster::Clip clip;
    clip.box.extend(ray.origin + d * t0);
    clip.box.extend(ray.origin + d * t1);
    for (const std::vector<Box3d>& blocks : kept) {
      clip.blocks.emplace_back(blocks);
    }
    const SurfaceCaster caster(casterGrids, std::nullopt, clip);
    const std::optional<CastHit> hit =
        caster.cast({ray.origin, d, 0, std::min(ray.maxDistance, t1)});
    if (!hit) {
      continue;
    }
    const PatchKey& leaf = casterLeaves[hit->grid];
    hits[i] =
        RayHit{hit->position, hit->distance, hitNormal(*casterGrids[hit->grid], hit->x, hit->y, d),
               leaf, model.at(leaf).resolution};
  }
  return hits;
}

}  // namespace vsm::core
