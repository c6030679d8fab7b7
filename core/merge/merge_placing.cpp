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

/// A patch's texture tile when it is in vsm's layout (a power of two texels per grid quad side:
/// texelsPerQuadOf); null otherwise (none, or a foreign tile of another size, which the merge
/// cannot place).
std::shared_ptr<const TextureTile> textureOf(PatchSource& source, const PatchKey& key) {
  std::shared_ptr<const TextureTile> tile = source.texture(key);
  if (tile && texelsPerQuadOf(tile->size(), source.model().gridSize()) == 0) {
    log::warn("merge: texture of patch " + key.toString() + " is " + std::to_string(tile->size()) +
              " texels wide, not a power of two per grid quad; it is not carried");
    return nullptr;
  }
  return tile;
}

/// The texture of new patch (i, j) of `level` below a's leaf, whose vertices are `grid`, with as
/// many texels per quad as the finer of a's tile and the B tiles it takes texels from (so each
/// model's imagery keeps its own resolution), capped at kMaxTextureTileSize. Per texel: B's
/// texture where a textured part of B lies at the texel's centre (level k only, `detail` given,
/// with `normals`: the patch's vertices' normals, `onDetail`: where on B each vertex of the patch
/// was placed, and `bTiles` the tiles of B's grids, of `detailGridSize` vertices), else a's tile
/// upsampled (`aTile`, may be null), else the patch's own shaded relief (so every patch a merge
/// writes has a tile, whichever model had none).
std::shared_ptr<const TextureTile> placeTexture(
    const Subdivider& subdivider, int level, std::uint32_t i, std::uint32_t j,
    const PatchGrid& grid, const TextureTile* aTile, const SurfaceCaster* detail, double search,
    const std::vector<Vec3d>& normals, const std::vector<Placed>& onDetail,
    const std::vector<const TextureTile*>& bTiles, int detailGridSize) {
  const bool fromDetail =
      detail != nullptr && level == subdivider.k() &&
      std::any_of(bTiles.begin(), bTiles.end(), [](const TextureTile* t) { return t != nullptr; });
  if (aTile == nullptr && !fromDetail) {
    return std::make_shared<TextureTile>(shadedRelief(grid));
  }
  const int quads = grid.size() - 1;
  const int aTexels = aTile != nullptr ? texelsPerQuadOf(aTile->size(), grid.size()) : 1;
  int texels = aTexels;
  if (fromDetail) {
    for (const TextureTile* t : bTiles) {
      if (t != nullptr) {
        texels = std::max(texels, texelsPerQuadOf(t->size(), detailGridSize));
      }
    }
  }
  texels = std::min(texels, maxTexelsPerQuad(grid.size()));
  // The shaded relief is made only when some texel is left without colour (rarely, where B's
  // texture covers the patch).
  auto tile = std::make_shared<TextureTile>(textureTileSize(grid.size(), texels));
  bool uncoloured = false;
  const int size = tile->size();
  const auto n = static_cast<std::size_t>(grid.size());
  const double scale = std::ldexp(1.0, level);
  // Texel (p, q) lies in the quad between vertices (p / f, q / f) and (p / f + 1, q / f + 1) of
  // the patch (f = texels), union vertices (u0 + p / f, v0 + q / f) and one more of level k, at
  // (sx, sy) across it.
  const std::int64_t u0 = std::int64_t{i} * quads;
  const std::int64_t v0 = std::int64_t{j} * quads;
  // B's colour at the texel's centre. Where the four corners of its quad lie on one grid of B,
  // its parameter there is the bilinear mean of theirs (exact where B's cells and the quad are
  // parallelograms, otherwise off by the second order of the quad's size: a fraction of a texel
  // far below what rounding the colour keeps). Elsewhere (B's border, the seams between its
  // grids) the texel's centre on a's surface (it lies in one cell of a, so the bilinear mean of
  // its corners) is cast onto B along the mean of the corners' normals.
  auto detailColour = [&](int p, int q) -> std::array<std::uint8_t, 4> {
    const int qx = p / texels;
    const int qy = q / texels;
    const double sx = ((p % texels) + 0.5) / texels;
    const double sy = ((q % texels) + 0.5) / texels;
    const double w[4] = {(1 - sx) * (1 - sy), sx * (1 - sy), (1 - sx) * sy, sx * sy};
    const std::size_t corner = static_cast<std::size_t>(qy) * n + static_cast<std::size_t>(qx);
    const std::size_t corners[4] = {corner, corner + 1, corner + n, corner + n + 1};
    std::uint32_t b = 0;
    double x = 0, y = 0;
    if (std::all_of(std::begin(corners), std::end(corners), [&](std::size_t c) {
          return onDetail[c].grid != kNotPlaced && onDetail[c].grid == onDetail[corner].grid;
        })) {
      b = onDetail[corner].grid;
      for (int c = 0; c < 4; ++c) {
        x += onDetail[corners[c]].x * w[c];
        y += onDetail[corners[c]].y * w[c];
      }
    } else {
      // Along the weighted mean of the corners' normals, scaled so the ray's ends are the
      // weighted means of the corners' ray ends: inside the caster's clip, as those are.
      const Vec3d at[4] = {subdivider.interpolate(u0 + qx, v0 + qy),
                           subdivider.interpolate(u0 + qx + 1, v0 + qy),
                           subdivider.interpolate(u0 + qx, v0 + qy + 1),
                           subdivider.interpolate(u0 + qx + 1, v0 + qy + 1)};
      Vec3d centre = at[0] * w[0];
      Vec3d normal = normals[corners[0]] * w[0];
      for (int c = 1; c < 4; ++c) {
        centre = centre + at[c] * w[c];
        normal = normal + normals[corners[c]] * w[c];
      }
      const double reach = search * normal.norm();
      const std::optional<CastHit> hit = detail->cast(CastRay{centre, normal, -reach, reach});
      if (!hit) {
        return {0, 0, 0, 0};
      }
      b = hit->grid;
      x = hit->x;
      y = hit->y;
    }
    if (const TextureTile* t = bTiles[b]) {
      // (x, y) in B's vertex coordinates; its texel centres are at (x f_B - 0.5, y f_B - 0.5).
      const double f = texelsPerQuadOf(t->size(), detailGridSize);
      return sampleBilinear(*t, x * f - 0.5, y * f - 0.5);
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
        // The texel's centre in a's vertex coordinates, then in a's texel centres.
        const double ax = (static_cast<double>(u0) + (p + 0.5) / texels) / scale;
        const double ay = (static_cast<double>(v0) + (q + 0.5) / texels) / scale;
        colour = sampleBilinear(*aTile, ax * aTexels - 0.5, ay * aTexels - 0.5);
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
          const std::uint8_t* shade = relief.at(p / texels, q / texels);
          std::copy(shade, shade + 4, tile->at(p, q));
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
    // What a finished new patch holds, to size the batches (mergeBatch): a grid and a tile as
    // large as the larger of a's first matched leaf's and B's root's, then the largest seen.
    const std::size_t gridBytes = static_cast<std::size_t>(target_.model().gridSize()) *
                                  target_.model().gridSize() * 3 * sizeof(float);
    std::size_t patchBytes = gridBytes;
    if (const auto root = textureOf(detail_, PatchKey::root())) {
      // B's tile at A's grid size: a new patch takes B's texels per quad.
      const int gridSize = target_.model().gridSize();
      const int texels = std::min(texelsPerQuadOf(root->size(), detail_.model().gridSize()),
                                  maxTexelsPerQuad(gridSize));
      const auto side = static_cast<std::size_t>(textureTileSize(gridSize, texels));
      patchBytes = gridBytes + side * side * TextureTile::kChannels;
    }
    std::size_t next = 0;
    std::vector<PatchKey> finished;  // the last batch's new leaves, stored early by the next
    std::deque<std::unique_ptr<MatchWork>> open;
    while (!open.empty() || next < count) {
      checkCancelled(options_);
      if (open.empty()) {
        open.push_back(start(next++));
        if (const TextureTile* a = open.back()->aTexture.get()) {
          patchBytes = std::max(patchBytes, gridBytes + a->bytes());
        }
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
        while (work->dispatched < work->leaves.size() && items.size() < mergeBatch(patchBytes)) {
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
        if (computed[t].texture) {
          patchBytes = std::max(patchBytes, gridBytes + computed[t].texture->bytes());
        }
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
    out.texture =
        placeTexture(*subdivider, leaf.level, leaf.i, leaf.j, *out.grid, work.aTexture.get(),
                     surface, search, normals, onDetail, tiles, detail_.model().gridSize());
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
