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
#include "core/grid/vec_ops.hpp"
#include "core/merge/merge_stages.hpp"
#include "core/merge/subdivider.hpp"
#include "core/merge/surface_caster.hpp"

namespace vsm::core::merge_stages {

namespace {

/// Where on B a vertex of a new patch was placed: B's grid (index into the caster's grids;
/// kNotPlaced when the vertex was not placed on B) and the point's coordinates in that grid's
/// vertex space (CastHit's), kept for the patch's texture.
constexpr std::uint32_t kNotPlaced = 0xFFFFFFFFu;
struct Placed {
  std::uint32_t grid = kNotPlaced;
  double x = 0, y = 0;
};

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
/// texel, B's texture where a textured part of B lies at the texel's centre (level k only,
/// `detail` given, with `normals`: the patch's vertices' normals, and `onDetail`: where on B each
/// vertex of the patch was placed), else
/// a's tile upsampled (`aTile`, may be null), else the patch's own shaded relief (so every patch a
/// merge writes has a tile, whichever model had none).
std::shared_ptr<const TextureTile> placeTexture(const Subdivider& subdivider, int level,
                                                std::uint32_t i, std::uint32_t j,
                                                const PatchGrid& grid, const TextureTile* aTile,
                                                const SurfaceCaster* detail, double search,
                                                const std::vector<Vec3d>& normals,
                                                const std::vector<Placed>& onDetail,
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
  // B's colour at the texel's centre. Where the four corners lie on one grid of B, its
  // parameter there is the mean of theirs (exact where B's cells and the quad are parallelograms,
  // otherwise off by the second order of the texel's size: a fraction of a texel far below what
  // rounding the colour keeps). Elsewhere (B's border, the seams between its grids) the centre
  // of the quad on a's surface (it lies in one cell of a, so the mean of its corners is its
  // bilinear centre) is cast onto B along the quad's normal (the cross product of its diagonals).
  auto detailColour = [&](int p, int q) -> std::array<std::uint8_t, 4> {
    const std::size_t corner = static_cast<std::size_t>(q) * n + static_cast<std::size_t>(p);
    const Placed* c[4] = {&onDetail[corner], &onDetail[corner + 1], &onDetail[corner + n],
                          &onDetail[corner + n + 1]};
    std::uint32_t b = 0;
    double x = 0, y = 0;
    if (std::all_of(std::begin(c), std::end(c), [&](const Placed* h) {
          return h->grid != kNotPlaced && h->grid == c[0]->grid;
        })) {
      b = c[0]->grid;
      for (const Placed* h : c) {
        x += h->x * 0.25;
        y += h->y * 0.25;
      }
    } else {
      // Along the mean of the corners' normals, scaled so the ray's ends are the means of the
      // corners' ray ends: inside the caster's clip, as those are.
      const Vec3d p00 = subdivider.interpolate(u0 + p, v0 + q);
      const Vec3d p10 = subdivider.interpolate(u0 + p + 1, v0 + q);
      const Vec3d p01 = subdivider.interpolate(u0 + p, v0 + q + 1);
      const Vec3d p11 = subdivider.interpolate(u0 + p + 1, v0 + q + 1);
      const Vec3d normal =
          (normals[corner] + normals[corner + 1] + normals[corner + n] + normals[corner + n + 1]) *
          0.25;
      const double reach = search * normal.norm();
      const std::optional<CastHit> hit =
          detail->cast(CastRay{(p00 + p10 + p01 + p11) * 0.25, normal, -reach, reach});
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
  const std::vector<DetailLeaf>& bLeaves = matched.bLeaves;
  const Match& match = matched.matches[m];
  const int k = match.levels;
  const double search = match.search;

  std::optional<Subdivider> subdivider;
  {
    const std::shared_ptr<const PatchGrid> grid = target.positions(match.target);
    if (grid->size() != a.gridSize()) {
      throw Error(ErrorCode::Corrupt,
                  "merge: patch " + match.target.toString() + " has a grid of the wrong size");
    }
    subdivider.emplace(*grid, k, match.ring);
  }
  // B's leaves that may have surface within `search` of a new patch of ball `ball` (indices into
  // bLeaves): a function of the surfaces alone, as matching's decisions are.
  auto detailNear = [&](const Ball& ball) {
    std::vector<std::size_t> near;
    for (const std::size_t i : match.detail) {
      if (ball.meets(bLeaves[i].ball, search + bLeaves[i].spacing)) {
        near.push_back(i);
      }
    }
    return near;
  };
  // Whether a ray of new patch (level, i, j) of Ball `ball` (subdivider->ball(level, i, j), which
  // the caller has computed already), or of a patch below it, can meet B: a block of a B
  // leaf near it (its Ball) within reach of the rays. A ray leaves a vertex of the patch (inside
  // its Ball) along a normal inside the patch's normal cone, for at most `search`: it stays within
  // `search` of the Ball along the cone's axis and within `search` times the cone's sine across
  // it. On terrain that is a thin slab, so the new levels stay over B and do not spread `search`
  // sideways, as a test of Balls alone would make them (render-lod and terrain measure it).
  // Where the cone is unknown (holes) or too wide, any direction. A hit may lie a border
  // tolerance outside B's cells: one B spacing is allowed for it. A function of the surfaces (no
  // axis of the scene), as matching's decisions are.
  constexpr double kConeMargin = 10 * M_PI / 180;
  constexpr int kParts = 8;  // the patch's vertices in up to 8 x 8 Balls
  auto reaches = [&](int level, std::uint32_t i, std::uint32_t j, const Ball& ball) {
    const std::vector<std::size_t> near = detailNear(ball);
    if (near.empty()) {
      return false;
    }
    const std::optional<Subdivider::Cone> cone = subdivider->normalCone(level, i, j, kConeMargin);
    for (const Ball& part : subdivider->balls(level, i, j, kParts)) {
      for (const std::size_t b : near) {
        for (const Ball& block : bLeaves[b].blockBalls) {
          if (block.empty()) {
            continue;
          }
          const double slack = part.radius + block.radius + bLeaves[b].spacing;
          const Vec3d d = block.centre - part.centre;
          if (!cone) {
            if (d.norm() <= search + slack) {
              return true;
            }
            continue;
          }
          const double along = vec::dot(d, cone->axis);
          const double across = (d - cone->axis * along).norm();
          if (std::fabs(along) <= search + slack && across <= search * cone->sine + slack) {
            return true;
          }
        }
      }
    }
    return false;
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
    Ball ball;
  };
  std::vector<NewLeaf> leaves;
  std::function<void(int, std::uint32_t, std::uint32_t)> plan = [&](int level, std::uint32_t i,
                                                                    std::uint32_t j) {
    const Ball ball = subdivider->ball(level, i, j);
    if (level == k || !reaches(level, i, j, ball)) {
      leaves.push_back({level, i, j, ball});
      return;
    }
    for (const Quadrant q : kQuadrants) {
      const auto qi = static_cast<std::uint32_t>(q);
      plan(level + 1, 2 * i + (qi & 1), 2 * j + (qi >> 1));
    }
  };
  if (k == 0) {
    plan(0, 0, 0);  // resampled in place
  } else if (reaches(0, 0, 0, subdivider->ball(0, 0, 0))) {
    for (const Quadrant q : kQuadrants) {
      const auto qi = static_cast<std::uint32_t>(q);
      plan(1, qi & 1, qi >> 1);
    }
  }
  auto keyOf = [&](int level, std::uint32_t i, std::uint32_t j) {
    return PatchKey{top.depth + level, (top.x << level) + i, (top.y << level) + j};
  };

  // One new leaf, computed by a task: its vertices (at level k placed on B's surface along the
  // subdivided surface's normals, cast into the B leaves near it, read and pinned by this task
  // only, in a caster clipped to the patch's reach) and its texture; no grid when it is empty.
  struct Computed {
    std::shared_ptr<const PatchGrid> grid;
    std::shared_ptr<const TextureTile> texture;
    std::size_t taken = 0;
    Vec3d firstDefined;  // for a placeholder parent without any defined vertex
  };
  auto compute = [&](const NewLeaf& leaf, Computed& out) {
    checkCancelled(options);
    std::vector<Vec3d> positions = subdivider->positions(leaf.level, leaf.i, leaf.j);
    std::optional<SurfaceCaster> caster;
    std::vector<std::shared_ptr<const TextureTile>> textures;
    std::vector<const TextureTile*> tiles;
    std::vector<Placed> onDetail;
    std::vector<Vec3d> normals;
    if (leaf.level == k) {
      const std::vector<std::size_t> near = detailNear(leaf.ball);
      if (!near.empty()) {
        std::vector<std::shared_ptr<const PatchGrid>> grids;
        // The box of the rays' ends: every ray (and every texel's, between its corners') lies
        // in it, and B's cells outside it are not built (a box grown by the search distance on
        // every side would hold all of a small B under a coarse target, for every new patch).
        normals = subdivider->normals(leaf.level, leaf.i, leaf.j, positions);
        Box3d reach;
        for (std::size_t v = 0; v < positions.size(); ++v) {
          if (positions[v].finite() && normals[v].finite()) {
            reach.extend(positions[v] + normals[v] * search);
            reach.extend(positions[v] - normals[v] * search);
          }
        }
        SurfaceCaster::Clip clip{reach};
        grids.reserve(near.size());
        for (const std::size_t i : near) {
          grids.push_back(detail.positions(bLeaves[i].key));
          textures.push_back(textureOf(detail, bLeaves[i].key));
          tiles.push_back(textures.back().get());
          clip.blocks.emplace_back(bLeaves[i].blocks);
        }
        caster.emplace(grids, options.transform, std::move(clip));
        grids.clear();  // the caster holds its own copy: unpinned while the rays are cast
        // In chunks of rays (in grid order), so that no array of all of them (nor of their
        // hits) is made.
        constexpr std::size_t kRays = 1024;
        std::vector<CastRay> rays;
        std::vector<std::optional<CastHit>> hits;
        rays.reserve(kRays);
        onDetail.resize(positions.size());
        for (std::size_t first = 0; first < positions.size(); first += kRays) {
          const std::size_t end = std::min(positions.size(), first + kRays);
          rays.clear();
          for (std::size_t v = first; v < end; ++v) {
            // An undefined origin or normal casts nothing (the caster answers nullopt).
            rays.push_back({positions[v], normals[v], -search, search});
          }
          hits.resize(rays.size());
          caster->cast(rays, hits);
          for (std::size_t v = first; v < end; ++v) {
            if (const std::optional<CastHit>& hit = hits[v - first]) {
              positions[v] = hit->position;
              onDetail[v] = {hit->grid, hit->x, hit->y};
              ++out.taken;
            }
          }
        }
      }
    }
    // Without a caster, placeTexture reads neither normals nor onDetail (both empty).
    const SurfaceCaster* surface = caster ? &*caster : nullptr;
    const auto first =
        std::find_if(positions.begin(), positions.end(), [](const Vec3d& p) { return p.finite(); });
    if (first == positions.end()) {
      return;  // an empty patch is omitted
    }
    out.firstDefined = *first;
    out.grid = std::make_shared<const PatchGrid>(gridFromGlobal(a.gridSize(), positions));
    out.texture = placeTexture(*subdivider, leaf.level, leaf.i, leaf.j, *out.grid, aTexture.get(),
                               surface, search, normals, onDetail, tiles);
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
               static_cast<double>(matched.matches.size()));
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
