#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <vector>

#include "core/grid/geometry.hpp"
#include "core/grid/patch_grid.hpp"

namespace vsm::core {

/// Spacing of a grid along its surface, in 3D (global coordinates, after a transform when given):
/// the mean distance between defined neighbours along its rows ((x, y) to (x + 1, y)), along its
/// columns ((x, y) to (x, y + 1)), and over both. 0 where no two such neighbours are defined. This
/// is "resolution on the surface" (issue 33): a vertical wall has its real spacing, where the
/// projection across one up direction (merge.cpp's planeResolution) has almost none.
struct GridSpacing {
  double rows = 0;
  double columns = 0;
  double mean = 0;
};
GridSpacing gridSpacing(const PatchGrid& grid,
                        const std::optional<Mat4d>& transform = std::nullopt);

/// A ray to cast: the line origin + t * direction (direction normalised by the caster, so t is a
/// length) searched for t in [tmin, tmax]. Along a surface normal: tmin = -search, tmax = search.
struct CastRay {
  Vec3d origin;
  Vec3d direction;
  double tmin = 0;
  double tmax = 0;
};

/// Where a ray met B's surface.
struct CastHit {
  /// On the ray (origin + distance * normalised direction), computed in double from the hit cell's
  /// double vertices (see SurfaceCaster).
  Vec3d position;
  /// The grid (index into the caster's `grids`) whose cell was hit, and the point's coordinates in
  /// that grid's vertex space (vertex (x, y) at (x, y)): where a texture tile of that grid is to
  /// be sampled.
  std::uint32_t grid = 0;
  double x = 0, y = 0;
  /// Signed distance from the ray's origin along its (normalised) direction.
  double distance = 0;
};

/// B's surface, indexed for placing and comparing along the surface instead of along one up
/// direction (issue 33): it answers "where does this line, within this distance of its origin,
/// meet B's surface". It does not see B as a height function along one up direction: vertical
/// walls, overhangs and tunnels are all surface.
///
/// B's surface: a cell with four defined corners is the bilinear surface of its corners, a cell
/// with exactly three the triangle of those three, other cells have none. The ray is intersected
/// with a cell in double, from the cell's double vertices: with its bilinear surface (Newton's
/// method from the triangles' barycentric start, cell_geometry.hpp's inversion, in the plane
/// across the ray) or its triangle, so a hit lies on the ray and exactly on B's surface.
///
/// The index: a bounding volume hierarchy that needs no build, B's grid itself seen along one
/// axis. The cells are projected along their dominant normal onto the plane across it, and a
/// uniform grid of bins lists the cells whose projected box (grown by B's border tolerance) meets
/// each bin. A ray's segment [tmin, tmax] (the part of it in the box of every point a hit can
/// report) casts a shadow in that plane; every cell whose box meets the shadow is intersected, in
/// rounds over a growing stretch of the ray around its origin, so that a near hit ends the search.
/// Rays along the axis (a merge's, along the target's normals over a B of about its orientation)
/// have point-sized shadows and meet one or two cells; others meet more, and every answer is exact
/// whatever the axis. (Embree, which the first version used, spent more time building its hierarchy
/// per clipped caster than casting: see tests/bench/results/caster.txt.)
///
/// The rule for folds, overhangs and tunnels: the hit nearest to the origin (smallest |t|) within
/// [tmin, tmax] wins, the positive side on a tie. Where the hit lies on or near a cell's border
/// (a ray through a shared edge or vertex), the cell's neighbours in its grid, and across a seam
/// the other grids' cells sharing a corner with it, are intersected too, and the answer is the
/// smallest (distance outside the cell in grid units, |t|, cell in grid order) of those whose
/// points lie within [tmin, tmax]: it depends neither on the caster's clip nor on its axis. B's
/// border: a ray within kBorderTolerance (cell_geometry.hpp: 1/32) grid units of a cell (its
/// parameter clamped onto the cell, or a triangle's barycentric coordinates clamped and
/// re-normalised) takes the cell's nearest point, at its distance along the ray (the point stays on
/// the ray).
///
/// Seams between B's grids: their border vertices within 1e-4 of a cell edge of each other are
/// one seam group, so a hit there is resolved among the cells of both grids. Everything runs on
/// the calling thread. Thread-safe for concurrent const calls.
class SurfaceCaster {
 public:
  /// Cells per side of the blocks blockBoxes() describes.
  static constexpr int kBlockCells = 16;

  /// Global boxes (after `transform` when given) of `grid`'s blocks of kBlockCells x kBlockCells
  /// cells, row by row (the last ones in a row or column may be smaller), empty where a block has
  /// no defined vertex. Computed once per grid of B, they let the many clipped casters a merge
  /// builds skip the blocks far from their clips.
  static std::vector<Box3d> blockBoxes(const PatchGrid& grid,
                                       const std::optional<Mat4d>& transform);

  /// `box` grown as the caster grows the box of a cell or a block before testing it against a
  /// clip: by kBorderTolerance of its size (both ways along each axis, summed) and by rounding
  /// relative to its coordinates. A cell's grown box lies in its block's, a block's in its
  /// grid's: a search that grows the boxes it descends through this way finds every cell a clip
  /// would build.
  static Box3d grownBox(const Box3d& box);

  /// Where rays will go: a box in global coordinates. Only cells whose box, grown by
  /// kBorderTolerance of its size, meets it are built. A ray whose segment [tmin, tmax] lies inside
  /// `box` gets the answer the whole caster gives.
  struct Clip {
    Box3d box;
    /// Per grid (empty, or one per grid): its blockBoxes(). Blocks far from `box` are skipped
    /// whole; the cells built, and so every answer, are the same.
    std::vector<std::span<const Box3d>> blocks = {};
  };

  /// `grids`: B's bottom grids (vertex data copied in double, after `transform` when given; null
  /// entries are skipped). Throws Error(InvalidArgument) when `clip`'s blocks do not match the
  /// grids.
  explicit SurfaceCaster(const std::vector<std::shared_ptr<const PatchGrid>>& grids,
                         const std::optional<Mat4d>& transform = std::nullopt,
                         const std::optional<Clip>& clip = std::nullopt);
  ~SurfaceCaster();
  SurfaceCaster(SurfaceCaster&&) noexcept;
  SurfaceCaster& operator=(SurfaceCaster&&) noexcept;
  SurfaceCaster(const SurfaceCaster&) = delete;
  SurfaceCaster& operator=(const SurfaceCaster&) = delete;

  /// The nearest hit of each ray (see the class comment); nullopt where there is none within
  /// [tmin, tmax], or for a ray with an undefined or zero direction or origin. `hits` must have
  /// rays.size() elements (Error(InvalidArgument) otherwise).
  void cast(std::span<const CastRay> rays, std::span<std::optional<CastHit>> hits) const;
  std::optional<CastHit> cast(const CastRay& ray) const;

  /// Cells built (full quads and 3-corner triangles), and their triangles (without skirts).
  std::size_t cellCount() const;
  std::size_t triangleCount() const;
  /// Box of the cells built (global).
  const Box3d& bounds() const;
  /// Bytes held by the caster's arrays (vertices, cells, bins).
  std::size_t bytes() const;

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
};

}  // namespace vsm::core
