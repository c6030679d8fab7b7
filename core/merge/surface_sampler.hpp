#pragma once

#include <algorithm>
#include <array>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <optional>
#include <span>
#include <vector>

#include "core/grid/geometry.hpp"
#include "core/grid/patch_grid.hpp"

namespace vsm::core {

/// A 2D point/extent in the plane perpendicular to a frame's up direction.
struct Vec2d {
  double u = 0, v = 0;
};

/// Axis-aligned rectangle in an UpFrame's plane; empty when min > max (the default).
struct Rect2d {
  static constexpr double kInf = Box3d::kInf;
  Vec2d min{kInf, kInf};
  Vec2d max{-kInf, -kInf};

  bool empty() const { return min.u > max.u || min.v > max.v; }
  void extend(const Vec2d& p) {  // inline: the sampler's inner loops call it per cell corner
    min = {std::min(min.u, p.u), std::min(min.v, p.v)};
    max = {std::max(max.u, p.u), std::max(max.v, p.v)};
  }
  bool intersects(const Rect2d& r) const;
  /// True when `r` lies inside this rectangle, allowing `tolerance` on every side.
  bool contains(const Rect2d& r, double tolerance = 0) const;
};

/// An orthonormal frame (e1, e2, up) around an origin: projects points onto the plane
/// perpendicular to `up`. Merging places B's surface along `up`, so everything that decides
/// "which part of B lies over this point" works in this plane.
struct UpFrame {
  Vec3d origin;
  Vec3d e1{1, 0, 0};
  Vec3d e2{0, 1, 0};
  Vec3d up{0, 0, 1};

  /// Precondition: `up` is finite and non-zero (it is normalised here).
  UpFrame(const Vec3d& origin, const Vec3d& up);

  Vec2d project(const Vec3d& p) const;
  /// Signed distance of `p` above the plane through the origin.
  double height(const Vec3d& p) const;
  /// The rectangle covering the projection of all 8 corners of `box` (conservative footprint).
  Rect2d footprint(const Box3d& box) const;
};

/// A point of B's surface found by SurfaceSampler::locate.
struct SurfacePoint {
  Vec3d position;
  /// The grid (index into the sampler's `grids`) whose cell holds the point, and the point's
  /// coordinates in that grid's vertex space (vertex (x, y) at (x, y)): where a texture tile of
  /// that grid is to be sampled.
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
/// is, not re-gridded (the thesis' section 5.3 limitation).
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
/// projection. So samples of B that a query hits up to rounding (float32 storage of either model,
/// projection along one up direction of points at different heights) are kept on every border:
/// B's outer border, around holes (undefined samples) and at the seams between B's own grids,
/// where the rounded grids may leave slivers of gap or overlap. A point inside some cell is
/// preferred to one only within tolerance of another.
///
/// Thread-safe for concurrent const calls after construction.
class SurfaceSampler {
 public:
  /// How far outside a cell of B (in B's grid units, i.e. sample spacings) a point still takes
  /// B's surface: far above float32 rounding (about 1e-5 of a cell for 257 x 257 grids) and the
  /// projection offsets of ECEF merges (about 5e-3 of a cell for the real merge of issue 18), far
  /// below half a cell, so a lattice half a sample off B's border is decided by its geometry.
  static constexpr double kBorderTolerance = 1.0 / 32;

  /// Where queries will come from: a rectangle in the plane of `frame`, whose up must be the
  /// sampler's. Cells farther from it than kBorderTolerance are left out of the index.
  struct Clip {
    UpFrame frame;
    Rect2d rect;
  };

  /// `grids`: B's bottom grids (their vertex data is copied, in double, after `transform` when
  /// given). `up`: the projection direction (normalised here); throws Error(InvalidArgument) when
  /// it is zero or not finite, or when `clip`'s frame has another up. With `clip`, only the cells
  /// that may hold a point projecting into it are indexed: every query projecting there gets the
  /// answer the whole sampler gives (the frame's origin is still the centre of all of `grids`, and
  /// ties between cells go to the first in grid order), for a fraction of the construction.
  SurfaceSampler(const std::vector<std::shared_ptr<const PatchGrid>>& grids, const Vec3d& up,
                 const std::optional<Mat4d>& transform = std::nullopt,
                 const std::optional<Clip>& clip = std::nullopt);

  /// The point of B's surface on the line through `p` along up; nullopt where B has no surface
  /// (outside B by more than kBorderTolerance, in B's holes, or for an undefined `p`). Where
  /// several layers of B lie over the same point (an overhang) the one nearest to `p` is returned.
  std::optional<Vec3d> sample(const Vec3d& p) const;

  /// sample(p) with where on B it lies.
  std::optional<SurfacePoint> locate(const Vec3d& p) const;

  /// True when some indexed cell's projected bounding rectangle, grown by kBorderTolerance times
  /// maxEdge(), meets `rect` (in frame()): a conservative "may B have surface there".
  bool covers(const Rect2d& rect) const;

  const UpFrame& frame() const { return frame_; }
  /// Indexed cells (full quads and 3-corner triangles).
  std::size_t cellCount() const { return cells_.size() / 4; }
  /// Footprint (in frame()) of every indexed cell.
  const Rect2d& footprint() const { return bounds_; }
  /// Longest projected edge or diagonal over all indexed cells.
  double maxEdge() const { return maxEdge_; }
  /// Bytes held (vertices, cells, index), for accounting.
  std::size_t bytes() const;

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

  /// Where a vertex came from: its grid and its index there.
  struct VertexOrigin {
    std::uint32_t grid;
    std::uint16_t x, y;
  };

  UpFrame frame_;
  std::vector<Vec3d> vertices_;   // global (transformed) positions of defined vertices
  std::vector<Vec2d> projected_;  // their projections into frame_
  std::vector<VertexOrigin> origins_;
  // 4 vertex indices per cell: (0,0), (1,0), (1,1), (0,1) of a full quad, or a triangle's three
  // corners and kNoVertex.
  std::vector<std::uint32_t> cells_;
  std::vector<Rect2d> cellRects_;  // each cell's projected bounding rectangle
  Rect2d bounds_;
  double maxEdge_ = 0;
  // Uniform bucket grid over bounds_: bucket (bx, by) holds the cells whose projected
  // bounding rectangle meets it, as bucketItems_[bucketStart_[b] .. bucketStart_[b + 1]).
  double bucketSize_ = 1;
  double margin_ = 0;  // kBorderTolerance * maxEdge_, and a little for rounding
  int bucketsU_ = 0, bucketsV_ = 0;
  std::vector<std::uint32_t> bucketStart_;
  std::vector<std::uint32_t> bucketItems_;
};

}  // namespace vsm::core
