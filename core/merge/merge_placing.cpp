#include <algorithm>
#include <cmath>
#include <deque>
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

/// A new leaf under a matched leaf: its level below it, its place at that level, its Ball.
struct NewLeaf {
  int level;
  std::uint32_t i, j;
  Ball ball;
};

/// One new leaf as a task computes it: its grid (none when it is empty), its texture, how many
/// of its vertices were placed on B, and its first defined vertex (for a placeholder parent).
struct Computed {
  std::shared_ptr<const PatchGrid> grid;
  std::shared_ptr<const TextureTile> texture;
  std::size_t taken = 0;
  Vec3d firstDefined;
};

/// A matched leaf being placed: what the calling thread reads of it (its grid, pinned until it is
/// planned, and its texture), what planning makes (its subdivider and its new leaves, in the order
/// they are inserted: depth first, quadrant order), and how far its insertion has come.
struct MatchWork {
  std::size_t m = 0;
  std::shared_ptr<const PatchGrid> grid;
  std::shared_ptr<const TextureTile> aTexture;
  std::optional<Subdivider> subdivider;
  std::vector<NewLeaf> leaves;
  std::size_t dispatched = 0;  // leaves handed to tasks
  std::size_t inserted = 0;    // leaves inserted (or found empty)
  std::size_t added = 0;       // patches inserted, placeholders included
};

/// Places the new levels under the matched leaves, in batches of up to kMergeBatch new leaves
/// that run across matched leaves (a batch does not wait for the last, longest leaf of one), the
/// next matched leaf planned by a task of the batch that dispatches the last leaves before it.
class Placing {
 public:
  Placing(MergeTarget& target, PatchSource& detail, const MergePlan& matched,
          const MergeOptions& options, MergeResult& result)
      : target_(target), detail_(detail), matched_(matched), options_(options), result_(result) {}

  void run() {
    const std::size_t count = matched_.matches.size();
    std::size_t next = 0;
    std::vector<PatchKey> finished;  // the last batch's new leaves, stored early by the next
    std::deque<std::unique_ptr<MatchWork>> open;
    while (!open.empty() || next < count) {
      checkCancelled(options_);
      if (open.empty()) {
        open.push_back(start(next++));
        plan(*open.back());
        continue;
      }
      // This batch's leaves, from the open matched leaves in order.
      struct Item {
        MatchWork* work;
        std::size_t leaf;
      };
      std::vector<Item> items;
      for (const std::unique_ptr<MatchWork>& work : open) {
        while (work->dispatched < work->leaves.size() && items.size() < kMergeBatch) {
          items.push_back({work.get(), work->dispatched++});
        }
      }
      std::vector<Computed> computed(items.size());
      std::vector<std::function<void()>> tasks;
      tasks.reserve(finished.size() + items.size() + 1);
      for (const PatchKey& key : finished) {
        tasks.emplace_back([this, key] { target_.writeEarly(key); });
      }
      finished.clear();
      for (std::size_t t = 0; t < items.size(); ++t) {
        tasks.emplace_back([this, &items, &computed, t] {
          compute(*items[t].work, items[t].work->leaves[items[t].leaf], computed[t]);
        });
      }
      // Every open leaf dispatched: the next matched leaf is planned beside them.
      std::unique_ptr<MatchWork> planned;
      if (next < count && open.back()->dispatched == open.back()->leaves.size()) {
        planned = start(next++);
        tasks.emplace_back([this, &planned] { plan(*planned); });
      }
      runTasks(options_.executor, std::move(tasks));
      for (std::size_t t = 0; t < items.size(); ++t) {
        MatchWork& work = *items[t].work;
        if (computed[t].grid) {
          insert(work, work.leaves[items[t].leaf], computed[t], finished);
        }
        ++work.inserted;
      }
      while (!open.empty() && open.front()->inserted == open.front()->leaves.size()) {
        finish(*open.front());
        open.pop_front();
      }
      if (planned) {
        open.push_back(std::move(planned));
      }
      const double done = static_cast<double>(next - open.size()) +
                          (open.empty() || open.front()->leaves.empty()
                               ? 0.0
                               : static_cast<double>(open.front()->inserted) /
                                     static_cast<double>(open.front()->leaves.size()));
      report(options_, "placing", done / static_cast<double>(count));
    }
  }

 private:
  const Match& match(const MatchWork& work) const { return matched_.matches[work.m]; }

  /// On the calling thread: matched leaf `m`'s grid and texture.
  std::unique_ptr<MatchWork> start(std::size_t m) {
    auto work = std::make_unique<MatchWork>();
    work->m = m;
    const Match& leaf = matched_.matches[m];
    work->grid = target_.positions(leaf.target);
    if (work->grid->size() != target_.model().gridSize()) {
      throw Error(ErrorCode::Corrupt,
                  "merge: patch " + leaf.target.toString() + " has a grid of the wrong size");
    }
    work->aTexture = textureOf(target_, leaf.target);
    return work;
  }

  /// On any thread: the subdivider and the new leaves of `work` (its grid then unpinned).
  void plan(MatchWork& work) const {
    checkCancelled(options_);
    const Match& leaf = match(work);
    const int k = leaf.levels;
    work.subdivider.emplace(*work.grid, k, leaf.ring);
    work.grid.reset();
    // Adaptive refinement: a new patch is refined further only where B may have surface;
    // elsewhere it stays a leaf holding a's surface interpolated to its level (the actual surface
    // there is unchanged, only denser), so the cost follows B's area, not a's times 4^k. Every
    // refined patch gets all its (non-empty) children, so reduction covers its whole area.
    std::function<void(int, std::uint32_t, std::uint32_t)> refine = [&](int level, std::uint32_t i,
                                                                        std::uint32_t j) {
      const Ball ball = work.subdivider->ball(level, i, j);
      if (level == k || !reaches(work, level, i, j, ball)) {
        work.leaves.push_back({level, i, j, ball});
        return;
      }
      for (const Quadrant q : kQuadrants) {
        const auto qi = static_cast<std::uint32_t>(q);
        refine(level + 1, 2 * i + (qi & 1), 2 * j + (qi >> 1));
      }
    };
    if (k == 0) {
      refine(0, 0, 0);  // resampled in place
    } else if (reaches(work, 0, 0, 0, work.subdivider->ball(0, 0, 0))) {
      for (const Quadrant q : kQuadrants) {
        const auto qi = static_cast<std::uint32_t>(q);
        refine(1, qi & 1, qi >> 1);
      }
    }
  }

  /// B's leaves that may have surface within `search` of a new patch of ball `ball` (indices into
  /// bLeaves): a function of the surfaces alone, as matching's decisions are.
  std::vector<std::size_t> detailNear(const MatchWork& work, const Ball& ball) const {
    const Match& leaf = match(work);
    std::vector<std::size_t> near;
    for (const std::size_t i : leaf.detail) {
      if (ball.meets(matched_.bLeaves[i].ball, leaf.search + matched_.bLeaves[i].spacing)) {
        near.push_back(i);
      }
    }
    return near;
  }

  /// Whether a ray of new patch (level, i, j) of Ball `ball` (subdivider->ball(level, i, j),
  /// which the caller has computed already), or of a patch below it, can meet B: a block of a B
  /// leaf near it (its Ball) within reach of the rays. A ray leaves a vertex of the patch (inside
  /// its Ball) along a normal inside the patch's normal cone, for at most `search`: it stays within
  /// `search` of the Ball along the cone's axis and within `search` times the cone's sine across
  /// it. On terrain that is a thin slab, so the new levels stay over B and do not spread `search`
  /// sideways, as a test of Balls alone would make them (render-lod and terrain measure it).
  /// Where the cone is unknown (holes) or too wide, any direction. A hit may lie a border
  /// tolerance outside B's cells: one B spacing is allowed for it. A function of the surfaces (no
  /// axis of the scene), as matching's decisions are.
  bool reaches(const MatchWork& work, int level, std::uint32_t i, std::uint32_t j,
               const Ball& ball) const {
    constexpr double kConeMargin = 10 * M_PI / 180;
    constexpr int kParts = 8;  // the patch's vertices in up to 8 x 8 Balls
    const std::vector<DetailLeaf>& bLeaves = matched_.bLeaves;
    const double search = match(work).search;
    const std::vector<std::size_t> near = detailNear(work, ball);
    if (near.empty()) {
      return false;
    }
    const std::optional<Subdivider::Cone> cone =
        work.subdivider->normalCone(level, i, j, kConeMargin);
    for (const Ball& part : work.subdivider->balls(level, i, j, kParts)) {
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
  }

  /// One new leaf, computed by a task: its vertices (at level k placed on B's surface along the
  /// subdivided surface's normals, cast into the B leaves near it, read and pinned by this task
  /// only, in a caster clipped to the patch's reach) and its texture; no grid when it is empty.
  void compute(const MatchWork& work, const NewLeaf& leaf, Computed& out) const {
    checkCancelled(options_);
    const Subdivider* subdivider = &*work.subdivider;
    const std::vector<DetailLeaf>& bLeaves = matched_.bLeaves;
    const double search = match(work).search;
    const int k = match(work).levels;
    std::vector<Vec3d> positions = subdivider->positions(leaf.level, leaf.i, leaf.j);
    std::optional<SurfaceCaster> caster;
    std::vector<std::shared_ptr<const TextureTile>> textures;
    std::vector<const TextureTile*> tiles;
    std::vector<Placed> onDetail;
    std::vector<Vec3d> normals;
    if (leaf.level == k) {
      const std::vector<std::size_t> near = detailNear(work, leaf.ball);
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
          grids.push_back(detail_.positions(bLeaves[i].key));
          textures.push_back(textureOf(detail_, bLeaves[i].key));
          tiles.push_back(textures.back().get());
          clip.blocks.emplace_back(bLeaves[i].blocks);
        }
        caster.emplace(grids, options_.transform, std::move(clip));
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
    out.grid =
        std::make_shared<const PatchGrid>(gridFromGlobal(target_.model().gridSize(), positions));
    out.texture = placeTexture(*subdivider, leaf.level, leaf.i, leaf.j, *out.grid,
                               work.aTexture.get(), surface, search, normals, onDetail, tiles);
  }

  /// Inserts a computed new leaf (in plan order). A refined patch goes in, as a placeholder, just
  /// before its first non-empty descendant. Reduction recomputes it from its children (inserting
  /// them marks it stale), and nothing reads it before: one defined vertex, that descendant's
  /// first, will do (a's surface subdivided there cost the single thread that inserts a few ms
  /// per patch).
  void insert(MatchWork& work, const NewLeaf& leaf, Computed& computed,
              std::vector<PatchKey>& finished) {
    const PatchKey& top = match(work).target;
    auto keyOf = [&](int level, std::uint32_t i, std::uint32_t j) {
      return PatchKey{top.depth + level, (top.x << level) + i, (top.y << level) + j};
    };
    for (int level = 1; level < leaf.level; ++level) {
      const int shift = leaf.level - level;
      const std::uint32_t i = leaf.i >> shift, j = leaf.j >> shift;
      const PatchKey parent = keyOf(level, i, j);
      if (target_.model().find(parent) != nullptr) {
        continue;
      }
      PatchGrid placeholder(target_.model().gridSize(), Mat4d::translation(computed.firstDefined));
      placeholder.setGlobal(0, 0, computed.firstDefined);
      target_.setPositions(parent, std::make_shared<const PatchGrid>(std::move(placeholder)),
                           nullptr);
      ++work.added;
    }
    target_.setPositions(keyOf(leaf.level, leaf.i, leaf.j), std::move(computed.grid),
                         std::move(computed.texture));
    finished.push_back(keyOf(leaf.level, leaf.i, leaf.j));
    ++work.added;
    result_.verticesFromDetail += computed.taken;
  }

  /// A matched leaf's counts, once its last new leaf is inserted.
  void finish(const MatchWork& work) {
    if (work.added == 0) {
      return;
    }
    const Match& leaf = match(work);
    ++result_.matchedLeaves;
    if (leaf.levels == 0) {
      ++result_.resampledLeaves;
    } else {
      result_.newPatches += work.added;
    }
    result_.levels[leaf.target] = leaf.levels;
    result_.maxLevels = std::max(result_.maxLevels, leaf.levels);
  }

  MergeTarget& target_;
  PatchSource& detail_;
  const MergePlan& matched_;
  const MergeOptions& options_;
  MergeResult& result_;
};

}  // namespace

void placeDetail(MergeTarget& target, PatchSource& detail, const MergePlan& plan,
                 const MergeOptions& options, MergeResult& result) {
  Placing(target, detail, plan, options, result).run();
}

}  // namespace vsm::core::merge_stages
