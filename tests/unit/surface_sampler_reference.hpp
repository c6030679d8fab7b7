#pragma once

// The unit tests' reference for SurfaceCaster (core/merge): B's surface seen as a height function
// along one `up`, found by a 2D bucket grid instead of a ray-tracing hierarchy. Merges placed B
// with it before they cast along the surface (issue 33); nothing in the product uses it now. The
// caster must agree with it: a ray along `up` meets B where sample() puts the point, in the cell
// locate() names, and B's border is the same (kBorderTolerance).

#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <vector>

#include "core/grid/geometry.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/merge/cell_geometry.hpp"

namespace vsm::core::test {

/// A point of B's surface found by SurfaceSampler::locate.
struct SurfacePoint {
  Vec3d position;
  /// The grid (index into the sampler's `grids`) whose cell holds the point, and the point's
  /// coordinates in that grid's vertex space (vertex (x, y) at (x, y)).
  std::uint32_t grid = 0;
  double x = 0, y = 0;
};

/// B's surface as a function over the plane perpendicular to `up`: built from B's bottom grids in
/// global coordinates, it answers "where does the line through p along up meet B's surface".
///
/// B's surface is its grid's own: in a cell (quad) whose four corners are defined, the bilinear
/// surface of the corners; in a cell with one undefined corner, the triangle of the other three;
/// cells with two or more undefined corners have none. Cells are indexed by their projection in a
/// uniform 2D bucket grid. sample(p) finds the cell whose projection contains p's projection (a
/// full cell is tested as its two triangles), inverts the projected bilinear map by Newton's method
/// (starting from the triangle's barycentric estimate) and evaluates the 3D bilinear surface there,
/// so the result projects exactly onto p's projection: only p's height changes. Each query is
/// located by its own coordinates: a rotated, sheared or unevenly spaced B is reproduced as it
/// is, not re-gridded.
///
/// Interpolation error. Let B sample a smooth height field h over the plane (height along up), and
/// let M bound the second directional derivative of h (the spectral norm of its Hessian). Both
/// interpolants are convex combinations sum_i w_i v_i of the cell's corners that reproduce the
/// query position (w_i >= 0, sum w_i = 1, sum w_i v_i = p in the plane). Taylor expansion around p
/// gives  sum_i w_i h(v_i) - h(p) = 1/2 sum_i w_i (v_i - p)^T H(xi_i) (v_i - p),  and for the
/// centre c of any disc of radius R holding the corners, sum_i w_i |v_i - p|^2 = sum_i w_i |v_i -
/// c|^2 - |p - c|^2 <= R^2. Hence
///   |sample(p) - h(p)| <= (1/2) M R^2,
/// i.e. (1/4) M s^2 for a square cell of side s (R = s / sqrt 2) and <= (1/6) M h^2 for a
/// triangle with longest edge h. Add float32 rounding of B's stored vertices (maxAbsLocal * 2^-24
/// per coordinate).
///
/// B's border. Inside/outside is decided per cell in B's own parameter space (the cell's (s, t)
/// in [0, 1]^2, or the triangle's grid coordinates), not by projected coordinates, and a point
/// whose parameter lies within kBorderTolerance grid units of a cell (Euclidean, measured to the
/// nearest point of the cell, or along the clamping for a triangle) belongs to that cell: it takes
/// the height of the cell's nearest point (the parameter clamped onto the cell) and keeps its own
/// projection. So samples of B that a query hits up to rounding are kept on every border: B's
/// outer border, around holes (undefined samples) and at the seams between B's own grids, where
/// the rounded grids may leave slivers of gap or overlap. A point inside some cell is preferred to
/// one only within tolerance of another.
///
/// Thread-safe for concurrent const calls after construction.
class SurfaceSampler {
 public:
  /// B's border tolerance, the caster's (cell_geometry.hpp).
  static constexpr double kBorderTolerance = cell_geometry::kBorderTolerance;

  /// `grids`: B's bottom grids (their vertex data is copied, in double). `up`: the projection
  /// direction (normalised here); throws Error(InvalidArgument) when it is zero or not finite.
  SurfaceSampler(const std::vector<std::shared_ptr<const PatchGrid>>& grids, const Vec3d& up);

  /// The point of B's surface on the line through `p` along up; nullopt where B has no surface
  /// (outside B by more than kBorderTolerance, in B's holes, or for an undefined `p`). Where
  /// several layers of B lie over the same point (an overhang) the one nearest to `p` is returned.
  std::optional<Vec3d> sample(const Vec3d& p) const;

  /// sample(p) with where on B it lies.
  std::optional<SurfacePoint> locate(const Vec3d& p) const;

  /// Indexed cells (full quads and 3-corner triangles).
  std::size_t cellCount() const { return cells_.size() / 4; }

 private:
  /// Weights of a cell's corners (in cells_ order; 0 for a triangle's missing fourth) at the
  /// point of the cell nearest to q, and how far q lies outside the cell in grid units (0 inside).
  using Weights = std::array<double, 4>;
  struct CellHit {
    Weights weights;
    double outside = 0;
  };
  /// The hit when q lies within kBorderTolerance grid units of the cell.
  std::optional<CellHit> onTriangle(const std::uint32_t* corners, const Vec2d& q) const;
  /// onTriangle with q's barycentric coordinates in the projected triangle.
  std::optional<CellHit> onTriangle(const std::uint32_t* corners,
                                    const std::array<double, 3>& barycentric) const;
  std::optional<CellHit> onQuad(const std::uint32_t* corners, const Vec2d& q) const;

  /// Signed distance of `p` above the frame's plane.
  double height(const Vec3d& p) const;

  /// Where a vertex came from: its grid and its index there.
  struct VertexOrigin {
    std::uint32_t grid;
    std::uint16_t x, y;
  };
  /// A projected bounding rectangle.
  struct Extent {
    Vec2d min{Box3d::kInf, Box3d::kInf};
    Vec2d max{-Box3d::kInf, -Box3d::kInf};
  };

  UpFrame frame_;
  std::vector<Vec3d> vertices_;   // global positions of defined vertices
  std::vector<Vec2d> projected_;  // their projections into frame_
  std::vector<VertexOrigin> origins_;
  // 4 vertex indices per cell: (0,0), (1,0), (1,1), (0,1) of a full quad, or a triangle's three
  // corners and kNoVertex.
  std::vector<std::uint32_t> cells_;
  std::vector<Extent> cellExtents_;  // each cell's projected bounding rectangle
  Extent bounds_;
  // Uniform bucket grid over bounds_: bucket (bx, by) holds the cells whose projected
  // bounding rectangle meets it, as bucketItems_[bucketStart_[b] .. bucketStart_[b + 1]).
  double bucketSize_ = 1;
  double margin_ = 0;  // kBorderTolerance * the longest projected edge, and a little for rounding
  int bucketsU_ = 0, bucketsV_ = 0;
  std::vector<std::uint32_t> bucketStart_;
  std::vector<std::uint32_t> bucketItems_;
};

}  // namespace vsm::core::test
