#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

#include "core/grid/patch_grid.hpp"

namespace vsm::core {

/// A ball around a set of points: centred on their mean, with the
/// largest distance to it as radius (empty: radius < 0). A function of the points alone, so a
/// model turned as a whole has its balls turned with it (unlike axis-aligned boxes): the merge
/// decides "may these meet" with balls, so that turning the scene changes none of its decisions.
struct Ball {
  Vec3d centre;
  double radius = -1;

  bool empty() const { return radius < 0; }
  /// True when the two balls, this one grown by `gap`, overlap (false when either is empty).
  bool meets(const Ball& other, double gap = 0) const;
};
/// The Ball of the finite points among `points`.
Ball ballOf(const std::vector<Vec3d>& points);
/// The Ball of `grid`'s defined vertices, in global coordinates (after `transform` when given).
Ball ballOf(const PatchGrid& grid, const std::optional<Mat4d>& transform = std::nullopt);

/// A's vertices just outside a patch, from its neighbours at the same depth: `west` is the column
/// left of column 0 (x = -1, one per row y), `east` the column right of the last, `south` the row
/// below row 0 (y = -1, one per column x), `north` the row above the last. Each is empty, or has
/// one global position per row or column (NaN where undefined). Normals at the patch's border
/// then see both sides of it, as its neighbour's normals there do, so two neighbouring patches
/// cast their shared border vertices along the same line (a watertight seam).
struct Ring {
  std::vector<Vec3d> west, east, south, north;
};

/// Refines one bottom patch `a` (size s = 2^n+1) by k levels: level j (0 <= j <= k) below `a` is
/// 2^j x 2^j patches whose union is 2^j (s-1) + 1 vertices per side, neighbours sharing their
/// border lines. Every new vertex is interpolated bilinearly, in global double coordinates, from
/// the cell of `a` it falls in; when some of the cell's corners are undefined the weights are
/// re-normalised over the defined ones, and the vertex is undefined when the defined corners have
/// no weight at it (all undefined, or it lies on an edge/corner whose defining vertices are
/// undefined). A vertex at a position of `a`'s own lattice therefore reproduces `a` exactly, so the
/// reduction of the new levels gives back `a` wherever nothing replaced it.
///
/// Each vertex also has a normal of that surface (normals()): the cross product of the central
/// differences of the interpolation one level-k step either side along u and along v (one-sided
/// where a side is undefined; across the patch's border from the Ring). The merge places each
/// new vertex on B's surface along that normal (merge.hpp).
///
/// Union vertex (u, v) at level k, and its normal, are pure functions of (u, v): the border line
/// two neighbouring new patches share is computed once per vertex position and is bit-identical
/// in double before each patch rounds it to float32 around its own origin (originFor(its box)).
///
/// Thread-safe for concurrent const calls.
class Subdivider {
 public:
  /// Copies `a`'s global positions (and `ring`'s). Throws Error(InvalidArgument) unless
  /// 0 <= k <= 16 and a.size() is 2^n+1. With k = 0, level 0 is `a` itself (to place it on a
  /// detail surface in place).
  Subdivider(const PatchGrid& a, int k, const Ring& ring = {});

  int k() const { return k_; }
  int size() const { return size_; }

  /// A's interpolation at union vertex (u, v) of level k (0 <= u, v <= 2^k (s-1)); NaN
  /// components when undefined.
  Vec3d interpolate(std::int64_t u, std::int64_t v) const;
  /// The unit normal of the interpolated surface at union vertex (u, v) (see the class comment);
  /// NaN components where it is undefined (the vertex, or both sides along u or along v).
  Vec3d normal(std::int64_t u, std::int64_t v) const;

  /// Global positions (row-major, size x size, NaN = undefined) of patch (i, j) of level `level`
  /// (0..k; 0 <= i, j < 2^level): A's surface interpolated there.
  std::vector<Vec3d> positions(int level, std::uint32_t i, std::uint32_t j) const;
  /// The normals at those positions (row-major as positions()); `positions` must be
  /// positions(level, i, j): at level k its neighbours inside the patch are taken from it (the
  /// very values normal() would interpolate again), the rest is computed.
  std::vector<Vec3d> normals(int level, std::uint32_t i, std::uint32_t j,
                             const std::vector<Vec3d>& positions) const;

  /// The Ball and the box of a's defined vertices around the cells patch (i, j) of `level`
  /// covers: every position interpolated there lies inside both.
  Ball ball(int level, std::uint32_t i, std::uint32_t j) const;
  Box3d box(int level, std::uint32_t i, std::uint32_t j) const;
  /// The same vertices split into up to `parts` x `parts` groups of neighbouring cells (sharing
  /// their border vertices), a Ball each (empty ones left out): tighter than ball() for a large
  /// patch.
  std::vector<Ball> balls(int level, std::uint32_t i, std::uint32_t j, int parts) const;

  /// A cone holding every normal() of patch (i, j) of `level`: the unit axis and the sine of its
  /// half-angle. The normal of a bilinear cell anywhere in it lies in the convex cone of its four
  /// corners' cross products (its edge vectors crossed), and a normal() on a border between cells
  /// crosses edges of the cells meeting there, so the cone of the cells around the patch's (one
  /// more cell on every side) holds them, and `margin` radians more cover the ring from the
  /// neighbouring leaves. Empty (nullopt) where a cell there has an undefined corner or the cone
  /// reaches 90 degrees: a ray's direction is then anything.
  struct Cone {
    Vec3d axis;
    double sine = 0;
  };
  std::optional<Cone> normalCone(int level, std::uint32_t i, std::uint32_t j, double margin) const;

 private:
  /// at(u, v) for each union vertex of patch (i, j) of `level`, row-major.
  template <typename At>
  std::vector<Vec3d> lattice(int level, std::uint32_t i, std::uint32_t j, At at) const;
  /// The vertices [x0, x1] x [y0, y1] of a around the cells of patch (i, j) of `level` (throws
  /// Error(InvalidArgument) for a patch outside the new levels).
  struct Vertices {
    std::int64_t x0 = 0, x1 = 0, y0 = 0, y1 = 0;
  };
  Vertices vertexRange(int level, std::uint32_t i, std::uint32_t j) const;
  /// The Ball of a's defined vertices [x0, x1] x [y0, y1] (ballOf()'s, without a copy).
  Ball ballOver(std::int64_t x0, std::int64_t x1, std::int64_t y0, std::int64_t y1) const;
  /// normal()'s rule from the position at the vertex and its four neighbours.
  static Vec3d normalFrom(const Vec3d& p, const Vec3d& west, const Vec3d& east, const Vec3d& south,
                          const Vec3d& north);
  /// interpolate(), extended by one level-0 cell beyond a's border into the ring (u or v in
  /// [-2^k, 0) or ((s-1) 2^k, s 2^k]); NaN beyond that or where the ring is undefined.
  Vec3d extended(std::int64_t u, std::int64_t v) const;

  int k_;
  int size_;
  std::vector<Vec3d> global_;  // a's vertices in global double; NaN when undefined
  Ring ring_;
};

/// Turns global positions (size x size, NaN = undefined) into a PatchGrid with originFor(box).
PatchGrid gridFromGlobal(int size, const std::vector<Vec3d>& global);

}  // namespace vsm::core
