#include <algorithm>
#include <cmath>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/grid/shaded_relief.hpp"
#include "core/merge/merge_stages.hpp"
#include "core/merge/subdivider.hpp"

namespace vsm::core::merge_stages {

namespace {

/// A's texture tile of a patch when it is in vsm's layout (one texel per grid quad); null
/// otherwise (none, or a foreign tile of another size, which the merge cannot place).
std::shared_ptr<const TextureTile> textureOf(PatchSource& source, const PatchKey& key) {
  std::shared_ptr<const TextureTile> tile = source.texture(key);
  if (tile && tile->size() != textureTileSize(source.model().gridSize())) {
    log::warn("merge: texture of patch " + key.toString() + " is " + std::to_string(tile->size()) +
              " texels wide, not one per grid quad; it is not carried");
    return nullptr;
  }
  return tile;
}

/// The texture of new patch (i, j) of `level` below a's leaf, whose vertices are `grid`: per
/// texel, B's texture where a textured part of B lies under the texel's centre (level k only,
/// `detail` given, with `onDetail`: where on B positions() placed each vertex of the patch), else
/// a's tile upsampled (`aTile`, may be null), else the patch's own shaded relief (so every patch a
/// merge writes has a tile, whichever model had none).
std::shared_ptr<const TextureTile> placeTexture(
    const Subdivider& subdivider, int level, std::uint32_t i, std::uint32_t j,
    const PatchGrid& grid, const TextureTile* aTile, const SurfaceSampler* detail,
    const std::vector<std::optional<SurfacePoint>>& onDetail,
    const std::vector<const TextureTile*>& bTiles) {
  const bool fromDetail =
      detail != nullptr && level == subdivider.k() &&
      std::any_of(bTiles.begin(), bTiles.end(), [](const TextureTile* t) { return t != nullptr; });
  if (aTile == nullptr && !fromDetail) {
    return std::make_shared<TextureTile>(shadedRelief(grid));
  }
  // The shaded relief is made only when some texel is left without colour (rarely, where B's
  // texture covers the patch).
  auto tile = std::make_shared<TextureTile>(textureTileSize(grid.size()));
  bool uncoloured = false;
  const int size = tile->size();
  const auto n = static_cast<std::size_t>(grid.size());
  const double scale = std::ldexp(1.0, level);
  // Texel (p, q) covers the quad between vertices (p, q) and (p + 1, q + 1) of the patch, union
  // vertices (u0 + p, v0 + q) and (u0 + p + 1, v0 + q + 1) of level k.
  const std::int64_t u0 = std::int64_t{i} * size;
  const std::int64_t v0 = std::int64_t{j} * size;
  // B's colour under the texel's centre. Where the four corners lie on one grid of B, its
  // parameter there is the mean of theirs (exact where B's cells and the quad are parallelograms,
  // otherwise off by the second order of the texel's size: a fraction of a texel far below what
  // rounding the colour keeps). Elsewhere (B's border, the seams between its grids) the centre
  // of the quad on a's surface (it lies in one cell of a, so the mean of its corners is its
  // bilinear centre) is located on B by its projection.
  auto detailColour = [&](int p, int q) -> std::array<std::uint8_t, 4> {
    const std::size_t corner = static_cast<std::size_t>(q) * n + static_cast<std::size_t>(p);
    const std::optional<SurfacePoint>* c[4] = {&onDetail[corner], &onDetail[corner + 1],
                                               &onDetail[corner + n], &onDetail[corner + n + 1]};
    std::uint32_t b = 0;
    double x = 0, y = 0;
    if (std::all_of(std::begin(c), std::end(c),
                    [&](const auto* h) { return h->has_value() && (*h)->grid == (*c[0])->grid; })) {
      b = (*c[0])->grid;
      for (const auto* h : c) {
        x += (*h)->x * 0.25;
        y += (*h)->y * 0.25;
      }
    } else {
      const Vec3d centre =
          (subdivider.interpolate(u0 + p, v0 + q) + subdivider.interpolate(u0 + p + 1, v0 + q) +
           subdivider.interpolate(u0 + p, v0 + q + 1) +
           subdivider.interpolate(u0 + p + 1, v0 + q + 1)) *
          0.25;
      const std::optional<SurfacePoint> hit = detail->locate(centre);
      if (!hit) {
        return {0, 0, 0, 0};
      }
      b = hit->grid;
      x = hit->x;
      y = hit->y;
    }
    if (const TextureTile* t = bTiles[b]) {
      return sampleBilinear(*t, x - 0.5, y - 0.5);
    }
    return {0, 0, 0, 0};
  };
  for (int q = 0; q < size; ++q) {
    for (int p = 0; p < size; ++p) {
      std::array<std::uint8_t, 4> colour{0, 0, 0, 0};
      if (fromDetail) {
        colour = detailColour(p, q);
      }
      if (colour[3] == 0 && aTile != nullptr) {
        colour = sampleBilinear(*aTile, (static_cast<double>(u0 + p) + 0.5) / scale - 0.5,
                                (static_cast<double>(v0 + q) + 0.5) / scale - 0.5);
      }
      if (colour[3] != 0) {
        std::copy(colour.begin(), colour.end(), tile->at(p, q));
      } else {
        uncoloured = true;
      }
    }
  }
  if (uncoloured) {
    const TextureTile relief = shadedRelief(grid);
    for (int q = 0; q < size; ++q) {
      for (int p = 0; p < size; ++p) {
        if (tile->at(p, q)[3] == 0) {
          std::copy(relief.at(p, q), relief.at(p, q) + 4, tile->at(p, q));
        }
      }
    }
  }
  return tile;
}

/// Places the new levels under matched leaf `m` of `matched` (the body of placeDetail's loop).
/// `finished`: the new leaves of the last batch, which the next batch's tasks store early.
void placeMatch(MergeTarget& target, PatchSource& detail, const MergePlan& matched,
                const MergeOptions& options, std::size_t m, std::vector<PatchKey>& finished,
                MergeResult& result) {
  const Model& a = target.model();
  const std::vector<Match>& matches = matched.matches;
  const std::vector<std::pair<PatchKey, Rect2d>>& bLeaves = matched.bLeaves;
  const std::vector<std::vector<Rect2d>>& bBlocks = matched.bBlocks;
  const UpFrame& frame = matched.frame;
  const Vec3d& up = matched.up;
  const Match& match = matches[m];
  const int k = match.levels;

  // B's leaves over this leaf (footprints, metadata only).
  Rect2d nearFoot;
  for (const std::size_t i : match.detail) {
    nearFoot.extend(bLeaves[i].second.min);
    nearFoot.extend(bLeaves[i].second.max);
  }
  std::optional<Subdivider> subdivider;
  Rect2d aFootprint;
  {
    const std::shared_ptr<const PatchGrid> grid = target.positions(match.target);
    if (grid->size() != a.gridSize()) {
      throw Error(ErrorCode::Corrupt,
                  "merge: patch " + match.target.toString() + " has a grid of the wrong size");
    }
    subdivider.emplace(*grid, k);
    for (int y = 0; y < grid->size(); ++y) {
      for (int x = 0; x < grid->size(); ++x) {
        if (grid->defined(x, y)) {
          aFootprint.extend(frame.project(grid->global(x, y)));
        }
      }
    }
  }
  if (!aFootprint.intersects(nearFoot)) {
    return;
  }
  // B's leaves whose footprint meets `rect` (indices into bLeaves).
  auto detailUnder = [&](const Rect2d& rect) {
    std::vector<std::size_t> under;
    for (const std::size_t i : match.detail) {
      if (bLeaves[i].second.intersects(rect)) {
        under.push_back(i);
      }
    }
    return under;
  };
  const std::shared_ptr<const TextureTile> aTexture = textureOf(target, match.target);
  const PatchKey& top = match.target;

  // Adaptive refinement: a new patch is refined further only where B may have surface;
  // elsewhere it stays a leaf holding a's surface interpolated to its level (the actual surface
  // there is unchanged, only denser), so the cost follows B's area, not a's times 4^k. Every
  // refined patch gets all its (non-empty) children, so reduction covers its whole area. The
  // new leaves, in the order they are inserted (depth first, quadrant order):
  struct NewLeaf {
    int level;
    std::uint32_t i, j;
    Rect2d foot;
  };
  std::vector<NewLeaf> leaves;
  std::function<void(int, std::uint32_t, std::uint32_t)> plan = [&](int level, std::uint32_t i,
                                                                    std::uint32_t j) {
    const Rect2d foot = subdivider->footprint(level, i, j, frame);
    if (level == k || detailUnder(foot).empty()) {
      leaves.push_back({level, i, j, foot});
      return;
    }
    for (const Quadrant q : kQuadrants) {
      const auto qi = static_cast<std::uint32_t>(q);
      plan(level + 1, 2 * i + (qi & 1), 2 * j + (qi >> 1));
    }
  };
  if (k == 0) {
    plan(0, 0, 0);  // resampled in place
  } else {
    for (const Quadrant q : kQuadrants) {
      const auto qi = static_cast<std::uint32_t>(q);
      plan(1, qi & 1, qi >> 1);
    }
  }
  auto keyOf = [&](int level, std::uint32_t i, std::uint32_t j) {
    return PatchKey{top.depth + level, (top.x << level) + i, (top.y << level) + j};
  };

  // One new leaf, computed by a task: its vertices (placed on B's surface at level k, from the
  // B leaves meeting it, read and pinned by this task only, in a sampler clipped to the
  // patch) and its texture; no grid when it is empty.
  struct Computed {
    std::shared_ptr<const PatchGrid> grid;
    std::shared_ptr<const TextureTile> texture;
    std::size_t taken = 0;
    Vec3d firstDefined;  // for a placeholder parent without any defined vertex
  };
  auto compute = [&](const NewLeaf& leaf, Computed& out) {
    checkCancelled(options);
    std::optional<SurfaceSampler> sampler;
    std::vector<std::shared_ptr<const TextureTile>> textures;
    std::vector<const TextureTile*> tiles;
    if (leaf.level == k) {
      const std::vector<std::size_t> under = detailUnder(leaf.foot);
      if (!under.empty()) {
        std::vector<std::shared_ptr<const PatchGrid>> grids;
        SurfaceSampler::Clip clip{frame, leaf.foot};
        grids.reserve(under.size());
        for (const std::size_t i : under) {
          grids.push_back(detail.positions(bLeaves[i].first));
          textures.push_back(textureOf(detail, bLeaves[i].first));
          tiles.push_back(textures.back().get());
          clip.blocks.emplace_back(bBlocks[i]);
        }
        sampler.emplace(grids, up, options.transform, std::move(clip));
      }
    }
    const SurfaceSampler* surface = sampler ? &*sampler : nullptr;
    std::vector<std::optional<SurfacePoint>> onDetail;
    const std::vector<Vec3d> positions =
        subdivider->positions(leaf.level, leaf.i, leaf.j, surface, &out.taken, &onDetail);
    const auto first =
        std::find_if(positions.begin(), positions.end(), [](const Vec3d& p) { return p.finite(); });
    if (first == positions.end()) {
      return;  // an empty patch is omitted
    }
    out.firstDefined = *first;
    out.grid = std::make_shared<const PatchGrid>(gridFromGlobal(a.gridSize(), positions));
    out.texture = placeTexture(*subdivider, leaf.level, leaf.i, leaf.j, *out.grid, aTexture.get(),
                               surface, onDetail, tiles);
  };

  // Inserted in plan order; a refined patch goes in, as a placeholder, just before its first
  // non-empty descendant. Reduction recomputes it from its children (inserting them marks it
  // stale), and nothing reads it before: one defined vertex, that descendant's first, will do
  // (a's surface subdivided there cost the single thread that inserts a few ms per patch).
  std::size_t added = 0;
  auto insert = [&](const NewLeaf& leaf, Computed& computed) {
    for (int level = 1; level < leaf.level; ++level) {
      const int shift = leaf.level - level;
      const std::uint32_t i = leaf.i >> shift, j = leaf.j >> shift;
      const PatchKey parent = keyOf(level, i, j);
      if (target.model().find(parent) != nullptr) {
        continue;
      }
      PatchGrid placeholder(a.gridSize(), Mat4d::translation(computed.firstDefined));
      placeholder.setGlobal(0, 0, computed.firstDefined);
      target.setPositions(parent, std::make_shared<const PatchGrid>(std::move(placeholder)),
                          nullptr);
      ++added;
    }
    target.setPositions(keyOf(leaf.level, leaf.i, leaf.j), std::move(computed.grid),
                        std::move(computed.texture));
    finished.push_back(keyOf(leaf.level, leaf.i, leaf.j));
    ++added;
    result.verticesFromDetail += computed.taken;
  };

  for (std::size_t first = 0; first < leaves.size(); first += kMergeBatch) {
    const std::size_t count = std::min(kMergeBatch, leaves.size() - first);
    std::vector<Computed> computed(count);
    std::vector<std::function<void()>> tasks;
    tasks.reserve(finished.size() + count);
    for (const PatchKey& key : finished) {
      tasks.emplace_back([&target, key] { target.writeEarly(key); });
    }
    finished.clear();
    for (std::size_t t = 0; t < count; ++t) {
      tasks.emplace_back([&, t] { compute(leaves[first + t], computed[t]); });
    }
    runTasks(options.executor, std::move(tasks));
    for (std::size_t t = 0; t < count; ++t) {
      if (computed[t].grid) {
        insert(leaves[first + t], computed[t]);
      }
    }
    report(options, "placing",
           (static_cast<double>(m) +
            static_cast<double>(first + count) / static_cast<double>(leaves.size())) /
               static_cast<double>(matches.size()));
  }
  if (added > 0) {
    ++result.matchedLeaves;
    if (k == 0) {
      ++result.resampledLeaves;
    } else {
      result.newPatches += added;
    }
    result.levels[top] = k;
    result.maxLevels = std::max(result.maxLevels, k);
  }
}

}  // namespace

void placeDetail(MergeTarget& target, PatchSource& detail, const MergePlan& plan,
                 const MergeOptions& options, MergeResult& result) {
  // The new leaves of the last batch: final once inserted (only placeholders and overviews change
  // later, by reduction), so the next batch's tasks store them while it computes.
  std::vector<PatchKey> finished;
  for (std::size_t m = 0; m < plan.matches.size(); ++m) {
    checkCancelled(options);
    placeMatch(target, detail, plan, options, m, finished, result);
  }
}

}  // namespace vsm::core::merge_stages
