#include "core/merge/surface_caster.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <initializer_list>
#include <limits>
#include <string>

#include <Eigen/Eigenvalues>

#include "core/common/error.hpp"
#include "core/merge/cell_geometry.hpp"

namespace vsm::core {

namespace {

using namespace cell_geometry;

constexpr std::uint32_t kNone = std::numeric_limits<std::uint32_t>::max();

// A hit this close (grid units) to its cell's border, or outside it, is also intersected with the
// cell's neighbours: far above kBarycentricSlack, so a neighbour that could tie is always looked
// at.
constexpr double kNearBorder = 1e-6;

/// What rounding may move a value computed from values of these magnitudes (coordinates,
/// distances; a 1 among them for values near 0): 1e-9 of the sum of their absolute values, far
/// above double's rounding and far below any length the caster decides by.
double roundingSlack(std::initializer_list<double> values) {
  double sum = 0;
  for (const double v : values) {
    sum += std::fabs(v);
  }
  return 1e-9 * sum;
}

/// A float at or below x, at or above x (a float box holding a double one): x moved outwards by
/// more than float's rounding before it is rounded.
float below(double x) {
  return static_cast<float>(x - std::fabs(x) * 0x1p-22 - 0x1p-126);
}
float above(double x) {
  return static_cast<float>(x + std::fabs(x) * 0x1p-22 + 0x1p-126);
}

double dot(const Vec3d& a, const Vec3d& b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}

// Grid offsets of a cell's corners, in the order (0,0), (1,0), (1,1), (0,1).
constexpr int kCornerX[4] = {0, 1, 1, 0};
constexpr int kCornerY[4] = {0, 0, 1, 1};

}  // namespace

GridSpacing gridSpacing(const PatchGrid& grid, const std::optional<Mat4d>& transform) {
  const int s = grid.size();
  auto global = [&](int x, int y) {
    const Vec3d g = grid.global(x, y);
    return transform ? transform->apply(g) : g;
  };
  double rowSum = 0, columnSum = 0;
  std::size_t rowCount = 0, columnCount = 0;
  std::vector<Vec3d> previous(static_cast<std::size_t>(s));  // row y - 1
  std::vector<char> previousDefined(static_cast<std::size_t>(s), 0);
  for (int y = 0; y < s; ++y) {
    Vec3d left;
    bool leftDefined = false;
    for (int x = 0; x < s; ++x) {
      const bool defined = grid.defined(x, y);
      const Vec3d p = defined ? global(x, y) : Vec3d{};
      if (defined && leftDefined) {
        rowSum += (p - left).norm();
        ++rowCount;
      }
      if (defined && previousDefined[x]) {
        columnSum += (p - previous[x]).norm();
        ++columnCount;
      }
      left = p;
      leftDefined = defined;
      previous[x] = p;
      previousDefined[x] = defined ? 1 : 0;
    }
  }
  GridSpacing spacing;
  spacing.rows = rowCount == 0 ? 0 : rowSum / static_cast<double>(rowCount);
  spacing.columns = columnCount == 0 ? 0 : columnSum / static_cast<double>(columnCount);
  const std::size_t count = rowCount + columnCount;
  spacing.mean = count == 0 ? 0 : (rowSum + columnSum) / static_cast<double>(count);
  return spacing;
}

struct SurfaceCaster::Impl {
  /// A cell: its corners' indices into vertices (order (0,0), (1,0), (1,1), (0,1); kNone for the
  /// missing corner of a 3-corner cell), its grid and its (0,0) corner there.
  struct Cell {
    std::array<std::uint32_t, 4> corners;
    std::uint32_t grid;
    std::uint32_t x, y;
    /// Whether all four corners are defined (else the cell is the triangle of the other three).
    bool full() const {
      return corners[0] != kNone && corners[1] != kNone && corners[2] != kNone &&
             corners[3] != kNone;
    }
    /// A 3-corner cell's defined corners: their places in `corners`, in order.
    std::array<int, 3> triangle() const {
      std::array<int, 3> which{};
      int n = 0;
      for (int k = 0; k < 4 && n < 3; ++k) {
        if (corners[k] != kNone) {
          which[n++] = k;
        }
      }
      return which;
    }
  };
  /// Where a grid's built cells are: the rectangle [x0, x0 + width) x [y0, y0 + height) of cells,
  /// and their indices in it (kNone where not built).
  struct GridCells {
    int x0 = 0, y0 = 0, width = 0, height = 0;
    std::vector<std::uint32_t> index;
    std::uint32_t at(int x, int y) const {
      if (x < x0 || y < y0 || x >= x0 + width || y >= y0 + height) {
        return kNone;
      }
      return index[static_cast<std::size_t>(y - y0) * width + (x - x0)];
    }
  };

  std::vector<Vec3d> vertices;       // global (transformed) double positions of the cells' corners
  std::vector<Cell> cells;           // in grid order
  std::size_t surfaceTriangles = 0;  // the cells' (a full cell's two, a 3-corner cell's one)
  // Seams between B's grids: per vertex on a grid's border that coincides (within rounding) with
  // a vertex of another grid, its group (index into seamCells, else kNone), and per group the
  // cells with a corner in it.
  std::vector<std::uint32_t> seamGroup;
  std::vector<std::vector<std::uint32_t>> seamCells;
  std::vector<GridCells> gridCells;
  Box3d bounds;
  Box3d reachBox;  // holds every point a hit can report (bounds grown by the cells' margins)

  /// The bins: the cells projected along `axis` (binFrame's up: the cells' dominant normal) onto
  /// the plane across it, each cell's projected box grown by its border reach, and a uniform grid
  /// of square bins over them (binsU x binsV of side binSize from (binU0, binV0)) listing, per
  /// bin, cells with their boxes (binEntries[binStart[b]..binStart[b + 1]]): a cell whose box is
  /// no wider than a bin in the bin of its box's centre only, a wider one in every bin its box
  /// meets. A box meets a region only if the region grown by half a bin holds its centre or
  /// (a wide one) meets one of its bins.
  struct Box2 {
    double u0, v0, u1, v1;
  };
  /// A cell in a bin, with its box relative to (binU0, binV0) in float, rounded outwards (it
  /// holds the cell's box): a ray tests the boxes of a bin's cells without looking them up.
  struct BinEntry {
    float u0, v0, u1, v1;
    std::uint32_t cell;
  };
  UpFrame binFrame{Vec3d{}, Vec3d{0, 0, 1}};
  double binU0 = 0, binV0 = 0, binSize = 1, perBin = 1;  // perBin = 1 / binSize
  int binsU = 0, binsV = 0;
  std::vector<std::uint32_t> binStart;
  std::unique_ptr<BinEntry[]> binEntries;  // binStart.back() of them
  bool anyWide = false;                    // whether a cell is in more than one bin

  /// A cell's area-weighted normal: the cross product of a full cell's diagonals, of a 3-corner
  /// cell's two sides (twice the area of what it spans, in the grid's orientation).
  Vec3d normal(const Cell& c) const {
    const auto& k = c.corners;
    if (c.full()) {
      return vec::cross(vertices[k[2]] - vertices[k[0]], vertices[k[3]] - vertices[k[1]]);
    }
    const std::array<int, 3> t = c.triangle();
    return vec::cross(vertices[k[t[1]]] - vertices[k[t[0]]], vertices[k[t[2]]] - vertices[k[t[0]]]);
  }

  /// The bins a projected box, relative to (binU0, binV0), meets (inclusive), clamped onto the
  /// grid of bins; empty (u0 > u1) when it lies off the grid or is not finite.
  struct BinRange {
    int u0 = 0, v0 = 0, u1 = -1, v1 = -1;
  };
  BinRange binRange(const Box2& b) const {
    const double fu0 = std::floor(b.u0 * perBin);
    const double fv0 = std::floor(b.v0 * perBin);
    const double fu1 = std::floor(b.u1 * perBin);
    const double fv1 = std::floor(b.v1 * perBin);
    if (!(fu1 >= 0 && fv1 >= 0 && fu0 < binsU && fv0 < binsV)) {
      return {};
    }
    return {static_cast<int>(std::max(fu0, 0.0)), static_cast<int>(std::max(fv0, 0.0)),
            static_cast<int>(std::min(fu1, binsU - 1.0)),
            static_cast<int>(std::min(fv1, binsV - 1.0))};
  }

  /// A ray in double: origin, unit direction, and the frame across it (origin at the ray's).
  struct Line {
    Vec3d origin;
    Vec3d direction;
    UpFrame frame;
  };

  /// The ray's intersection with cell `c`: weights of its corners and how far (grid units) outside
  /// the cell the intersection lies (0 inside); nullopt beyond kBorderTolerance or
  /// where the cell is degenerate across the ray.
  struct CellHit {
    std::array<double, 4> weights;
    double outside = 0;
    bool nearBorder = false;
  };

  static std::optional<CellHit> onTriangle(const std::array<int, 3>& which,
                                           const std::array<double, 3>& l) {
    // The point clamped onto the triangle, in the cell's grid units.
    const std::optional<ClampedPoint> point = clampOntoTriangle(
        l, {double(kCornerX[which[0]]), double(kCornerX[which[1]]), double(kCornerX[which[2]])},
        {double(kCornerY[which[0]]), double(kCornerY[which[1]]), double(kCornerY[which[2]])});
    if (!point || !(point->outside <= kBorderTolerance)) {
      return std::nullopt;
    }
    CellHit hit{{0, 0, 0, 0}, point->outside, false};
    for (int k = 0; k < 3; ++k) {
      hit.weights[which[k]] = point->weights[k];
    }
    hit.nearBorder = hit.outside > 0 || std::min({l[0], l[1], l[2]}) < kNearBorder;
    return hit;
  }

  /// Whether the ray (the origin of the plane across it) may take a point of a cell whose
  /// projected corners are `corners`: it lies in their box grown, per coordinate, by
  /// kBorderTolerance times the sum of |reach| (how far the cell's border measure lets a point
  /// move per unit of it), plus rounding. A cheap refusal before the inversion.
  static bool mayMeet(const Vec2d* corners, int n, const Vec2d* reach, int m) {
    double u0 = corners[0].u, u1 = u0, v0 = corners[0].v, v1 = v0;
    for (int k = 1; k < n; ++k) {
      u0 = std::min(u0, corners[k].u);
      u1 = std::max(u1, corners[k].u);
      v0 = std::min(v0, corners[k].v);
      v1 = std::max(v1, corners[k].v);
    }
    double mu = 0, mv = 0;
    for (int k = 0; k < m; ++k) {
      mu += std::fabs(reach[k].u);
      mv += std::fabs(reach[k].v);
    }
    const double round = roundingSlack({u0, u1, v0, v1});
    mu = kBorderTolerance * mu + round;
    mv = kBorderTolerance * mv + round;
    // Not finite (a degenerate projection): let the inversion decide.
    return !(u0 - mu > 0 || u1 + mu < 0 || v0 - mv > 0 || v1 + mv < 0);
  }

  std::optional<CellHit> intersect(const Cell& cell, const Line& line) const {
    const Vec2d q{0, 0};  // the ray, projected across itself
    if (!cell.full()) {
      const std::array<int, 3> which = cell.triangle();
      std::array<Vec2d, 3> p{};
      for (int n = 0; n < 3; ++n) {
        p[n] = line.frame.project(vertices[cell.corners[which[n]]]);
      }
      // A point within kBorderTolerance (grid units) of the triangle moves by at most that
      // times each of its sides' extents away from the corners' box.
      const Vec2d sides[3] = {sub2(p[1], p[0]), sub2(p[2], p[1]), sub2(p[0], p[2])};
      if (!mayMeet(p.data(), 3, sides, 3)) {
        return std::nullopt;
      }
      // Triangles' sides: for a corner cell, "near the border" also holds along its diagonal,
      // where no neighbour lies; harmless (the neighbours are just looked at).
      return onTriangle(which, barycentric(p[0], p[1], p[2], q));
    }
    // The bilinear cell: its (s, t) where the ray meets it, inverted in the plane across the ray.
    const Vec2d p00 = line.frame.project(vertices[cell.corners[0]]);
    const Vec2d p10 = line.frame.project(vertices[cell.corners[1]]);
    const Vec2d p11 = line.frame.project(vertices[cell.corners[2]]);
    const Vec2d p01 = line.frame.project(vertices[cell.corners[3]]);
    {
      // p(s, t) = p00 + s e + t f + s t g. Within kBorderTolerance of the cell, (s, t) and s t move
      // by at most the tolerance and three times it from the cell's: the point by at most
      // tolerance * (|e| + |f| + 3 |g|) per coordinate from the corners' box (also for the
      // triangles the fallback below uses, whose sides are e, f + g, e + g and f).
      const Vec2d e = sub2(p10, p00), f = sub2(p01, p00);
      const Vec2d g{p11.u - p10.u - p01.u + p00.u, p11.v - p10.v - p01.v + p00.v};
      const Vec2d corners[4] = {p00, p10, p11, p01};
      const Vec2d reach[4] = {e, f, g, Vec2d{2 * g.u, 2 * g.v}};
      if (!mayMeet(corners, 4, reach, 4)) {
        return std::nullopt;
      }
    }
    const cell_geometry::BilinearPoint point = invertBilinear(p00, p10, p11, p01, q);
    const auto& l1 = point.first;
    const auto& l2 = point.second;
    const double s = point.s, t = point.t;
    const bool converged = point.converged;
    const double cs = point.cs, ct = point.ct, outside = point.outside;
    if (!converged || !std::isfinite(s) || !std::isfinite(t) || !(outside <= kBorderTolerance)) {
      // A cell seen edge-on or strongly distorted across the ray, or a point outside it: its
      // triangles (split along the (0,0)-(1,1) diagonal), the nearer one.
      std::optional<CellHit> a = onTriangle({0, 1, 2}, l1);
      std::optional<CellHit> b = onTriangle({0, 2, 3}, l2);
      if (a && (!b || a->outside <= b->outside)) {
        return a;
      }
      return b;
    }
    CellHit hit{{(1 - cs) * (1 - ct), cs * (1 - ct), cs * ct, (1 - cs) * ct},
                outside <= kBarycentricSlack ? 0.0 : outside,
                false};
    hit.nearBorder = hit.outside > 0 || std::min({s, 1 - s, t, 1 - t}) < kNearBorder;
    return hit;
  }

  /// Where along the line (signed distance from its origin) the cell's point of `hit` lies, and
  /// (when asked) that point's grid coordinates.
  double distance(const Cell& cell, const CellHit& hit, const Line& line, double* x = nullptr,
                  double* y = nullptr) const {
    Vec3d p{0, 0, 0};
    double gx = 0, gy = 0;
    for (int k = 0; k < 4; ++k) {
      if (hit.weights[k] != 0) {
        p = p + vertices[cell.corners[k]] * hit.weights[k];
        gx += (cell.x + kCornerX[k]) * hit.weights[k];
        gy += (cell.y + kCornerY[k]) * hit.weights[k];
      }
    }
    if (x != nullptr) {
      *x = gx;
      *y = gy;
    }
    return dot(p - line.origin, line.direction);
  }

  /// The answer for a ray that meets cell `cellIndex` (`hit`: intersect() of that cell): the best
  /// of that cell and (near its border) its neighbours whose points lie within [tmin, tmax], by
  /// (outside, |t|, cell); nullopt when none does.
  std::optional<CastHit> resolve(std::uint32_t cellIndex, const CellHit& hit, const Line& line,
                                 double tmin, double tmax) const {
    std::optional<CastHit> best;
    double bestOutside = std::numeric_limits<double>::infinity();
    double bestAbs = std::numeric_limits<double>::infinity();
    std::uint32_t bestCell = kNone;
    auto consider = [&](std::uint32_t index, std::optional<CellHit> h) -> bool {  // nearBorder
      const Cell& cell = cells[index];
      if (!h) {
        return false;
      }
      double x = 0, y = 0;
      const double t = distance(cell, *h, line, &x, &y);
      const double a = std::fabs(t);
      // Out of [tmin, tmax] a neighbour takes no part (a clip need not have built it).
      if (!(t >= tmin && t <= tmax)) {
        return h->nearBorder;
      }
      if (h->outside < bestOutside ||
          (h->outside == bestOutside && (a < bestAbs || (a == bestAbs && index < bestCell)))) {
        bestOutside = h->outside;
        bestAbs = a;
        bestCell = index;
        // On the ray: the point of the cell at the ray's own projection (or, clamped onto the
        // cell, its distance along the ray).
        best = CastHit{line.origin + line.direction * t, cell.grid, x, y, t};
      }
      return h->nearBorder;
    };
    if (consider(cellIndex, hit)) {
      const Cell& cell = cells[cellIndex];
      const GridCells& grid = gridCells[cell.grid];
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          const std::uint32_t n =
              grid.at(static_cast<int>(cell.x) + dx, static_cast<int>(cell.y) + dy);
          if ((dx != 0 || dy != 0) && n != kNone) {
            consider(n, intersect(cells[n], line));
          }
        }
      }
      // Across a seam: the other grids' cells sharing a corner with this one.
      for (const std::uint32_t corner : cell.corners) {
        if (corner != kNone && seamGroup[corner] != kNone) {
          for (const std::uint32_t n : seamCells[seamGroup[corner]]) {
            if (cells[n].grid != cell.grid) {
              consider(n, intersect(cells[n], line));
            }
          }
        }
      }
    }
    return best;
  }
};

Box3d SurfaceCaster::grownBox(const Box3d& b) {
  const Vec3d size = b.size();
  const double margin = 2 * kBorderTolerance * (size.x + size.y + size.z) +
                        roundingSlack({b.min.x, b.min.y, b.min.z, 1});
  return {{b.min.x - margin, b.min.y - margin, b.min.z - margin},
          {b.max.x + margin, b.max.y + margin, b.max.z + margin}};
}

std::vector<Box3d> SurfaceCaster::blockBoxes(const PatchGrid& grid,
                                             const std::optional<Mat4d>& transform) {
  const int s = grid.size();
  const int blocksPerSide = (s - 1 + kBlockCells - 1) / kBlockCells;
  std::vector<Box3d> blocks(static_cast<std::size_t>(blocksPerSide) * blocksPerSide);
  for (int y = 0; y < s; ++y) {
    for (int x = 0; x < s; ++x) {
      if (!grid.defined(x, y)) {
        continue;
      }
      const Vec3d g = grid.global(x, y);
      const Vec3d p = transform ? transform->apply(g) : g;
      for (int by = std::max(0, (y - 1) / kBlockCells); by <= std::min(y, s - 2) / kBlockCells;
           ++by) {
        for (int bx = std::max(0, (x - 1) / kBlockCells); bx <= std::min(x, s - 2) / kBlockCells;
             ++bx) {
          blocks[static_cast<std::size_t>(by) * blocksPerSide + bx].extend(p);
        }
      }
    }
  }
  return blocks;
}

SurfaceCaster::SurfaceCaster(const std::vector<std::shared_ptr<const PatchGrid>>& grids,
                             const std::optional<Mat4d>& transform, const std::optional<Clip>& clip)
    : impl_(std::make_unique<Impl>()) {
  Impl& m = *impl_;
  if (clip && !clip->blocks.empty() && clip->blocks.size() != grids.size()) {
    throw Error(ErrorCode::InvalidArgument,
                "surface caster: the clip's block footprints do not match the grids");
  }
  // Whether a box (of a cell or a block), grown by kBorderTolerance of its size, meets the clip.
  auto wanted = [&](const Box3d& b) {
    if (!clip) {
      return true;
    }
    return grownBox(b).intersects(clip->box);
  };

  // Per grid, per block: 0 skipped, 1 its cells tested one by one against the clip, 2 all wanted
  // (no clip, or the block's grown box inside the clip's box: a cell's grown box lies in its
  // block's); and the rectangle of blocks not skipped (none when bx1 < 0).
  struct GridPlan {
    std::vector<char> state;
    int blocksPerSide = 0;
    int bx0 = 0, by0 = 0, bx1 = -1, by1 = -1;
  };
  std::vector<GridPlan> plans(grids.size());
  // At most this many cells and vertices: reserved once, so that the arrays are neither copied
  // nor their memory touched twice as they grow (a merge builds a caster per new patch).
  std::size_t cellBound = 0, vertexBound = 0;
  for (std::size_t gridIndex = 0; gridIndex < grids.size(); ++gridIndex) {
    const auto& grid = grids[gridIndex];
    if (!grid) {
      continue;
    }
    GridPlan& plan = plans[gridIndex];
    const int s = grid->size();
    const int blocksPerSide = (s - 1 + kBlockCells - 1) / kBlockCells;
    plan.blocksPerSide = blocksPerSide;
    std::span<const Box3d> blocks;
    if (clip && !clip->blocks.empty()) {
      blocks = clip->blocks[gridIndex];
      if (blocks.size() != static_cast<std::size_t>(blocksPerSide) * blocksPerSide) {
        throw Error(ErrorCode::InvalidArgument,
                    "surface caster: the clip's block footprints do not match the grids");
      }
    }
    std::vector<char>& state = plan.state;
    state.assign(static_cast<std::size_t>(blocksPerSide) * blocksPerSide, clip ? 1 : 2);
    if (clip && !blocks.empty()) {
      const Box3d& c = clip->box;
      for (std::size_t i = 0; i < state.size(); ++i) {
        const Box3d& b = blocks[i];
        if (b.empty() || !wanted(b)) {
          state[i] = 0;
        } else if (c.contains(grownBox(b))) {
          state[i] = 2;
        }
      }
    }
    plan.bx0 = plan.by0 = blocksPerSide;
    for (int by = 0; by < blocksPerSide; ++by) {
      for (int bx = 0; bx < blocksPerSide; ++bx) {
        if (state[static_cast<std::size_t>(by) * blocksPerSide + bx] != 0) {
          plan.bx0 = std::min(plan.bx0, bx);
          plan.bx1 = std::max(plan.bx1, bx);
          plan.by0 = std::min(plan.by0, by);
          plan.by1 = std::max(plan.by1, by);
        }
      }
    }
    if (plan.bx1 >= 0) {
      const std::size_t w = static_cast<std::size_t>(plan.bx1 - plan.bx0 + 1) * kBlockCells;
      const std::size_t h = static_cast<std::size_t>(plan.by1 - plan.by0 + 1) * kBlockCells;
      cellBound += w * h;
      vertexBound += (w + 1) * (h + 1);
    }
  }
  m.cells.reserve(cellBound);
  m.vertices.reserve(vertexBound);

  m.gridCells.resize(grids.size());
  std::vector<std::uint32_t> index;  // per vertex of a grid's rectangle: its vertices index
  struct BorderVertex {
    std::uint32_t vertex, grid;
  };
  std::vector<BorderVertex> border;  // vertices on their grid's border
  for (std::size_t gridIndex = 0; gridIndex < grids.size(); ++gridIndex) {
    const auto& grid = grids[gridIndex];
    const GridPlan& plan = plans[gridIndex];
    if (!grid || plan.bx1 < 0) {
      continue;
    }
    const int s = grid->size();
    const int blocksPerSide = plan.blocksPerSide;
    const std::vector<char>& state = plan.state;
    const int bx0 = plan.bx0, bx1 = plan.bx1;
    auto at = [&](int x, int y) {
      const Vec3d g = grid->global(x, y);
      return transform ? transform->apply(g) : g;
    };
    // The vertices of the wanted blocks' rectangle [x0, x1] x [y0, y1] are indexed.
    const int x0 = plan.bx0 * kBlockCells;
    const int y0 = plan.by0 * kBlockCells;
    const int x1 = std::min((plan.bx1 + 1) * kBlockCells, s - 1);
    const int y1 = std::min((plan.by1 + 1) * kBlockCells, s - 1);
    index.assign(static_cast<std::size_t>(x1 - x0 + 1) * (y1 - y0 + 1), kNone);
    auto vertex = [&](int x, int y) {
      const std::size_t i = static_cast<std::size_t>(y - y0) * (x1 - x0 + 1) + (x - x0);
      if (index[i] == kNone) {
        index[i] = static_cast<std::uint32_t>(m.vertices.size());
        m.vertices.push_back(at(x, y));
        m.bounds.extend(m.vertices.back());  // every vertex is a built cell's corner
        if (x == 0 || y == 0 || x == s - 1 || y == s - 1) {
          border.push_back({index[i], static_cast<std::uint32_t>(gridIndex)});
        }
      }
      return index[i];
    };
    // Row by row (grid order, which the tie rule (smallest cell) wants), over the wanted blocks.
    const std::size_t firstCell = m.cells.size();
    for (int y = y0; y < y1; ++y) {
      const int by = y / kBlockCells;
      for (int bx = bx0; bx <= bx1; ++bx) {
        const char blockState = state[static_cast<std::size_t>(by) * blocksPerSide + bx];
        if (blockState == 0) {
          continue;
        }
        for (int x = bx * kBlockCells; x < std::min((bx + 1) * kBlockCells, s - 1); ++x) {
          int defined = 0;
          for (int k = 0; k < 4; ++k) {
            defined += grid->defined(x + kCornerX[k], y + kCornerY[k]) ? 1 : 0;
          }
          if (defined < 3) {
            continue;
          }
          if (blockState == 1) {
            Box3d box;
            for (int k = 0; k < 4; ++k) {
              if (grid->defined(x + kCornerX[k], y + kCornerY[k])) {
                box.extend(at(x + kCornerX[k], y + kCornerY[k]));
              }
            }
            if (!wanted(box)) {
              continue;
            }
          }
          Impl::Cell cell{{kNone, kNone, kNone, kNone},
                          static_cast<std::uint32_t>(gridIndex),
                          static_cast<std::uint32_t>(x),
                          static_cast<std::uint32_t>(y)};
          for (int k = 0; k < 4; ++k) {
            if (grid->defined(x + kCornerX[k], y + kCornerY[k])) {
              cell.corners[k] = vertex(x + kCornerX[k], y + kCornerY[k]);
            }
          }
          m.cells.push_back(cell);
        }
      }
    }
    if (m.cells.size() > firstCell) {
      Impl::GridCells& gc = m.gridCells[gridIndex];
      int x0 = s, y0 = s, x1 = -1, y1 = -1;
      for (std::size_t c = firstCell; c < m.cells.size(); ++c) {
        x0 = std::min(x0, static_cast<int>(m.cells[c].x));
        x1 = std::max(x1, static_cast<int>(m.cells[c].x));
        y0 = std::min(y0, static_cast<int>(m.cells[c].y));
        y1 = std::max(y1, static_cast<int>(m.cells[c].y));
      }
      gc.x0 = x0;
      gc.y0 = y0;
      gc.width = x1 - x0 + 1;
      gc.height = y1 - y0 + 1;
      gc.index.assign(static_cast<std::size_t>(gc.width) * gc.height, kNone);
      for (std::size_t c = firstCell; c < m.cells.size(); ++c) {
        gc.index[static_cast<std::size_t>(m.cells[c].y - y0) * gc.width + (m.cells[c].x - x0)] =
            static_cast<std::uint32_t>(c);
      }
    }
  }
  if (m.cells.empty()) {
    return;
  }

  // Seams: B's grids share their border lines, each rounded to float32 around its own origin, so
  // the "same" vertex differs by rounding from grid to grid. Border vertices of different grids
  // within kWeld of the cells' mean edge are one seam group (so a hit there is resolved among the
  // cells of both grids). Weld: a union-find over the vertices, the lowest index of a group.
  std::vector<std::uint32_t> weld(m.vertices.size());
  for (std::uint32_t v = 0; v < weld.size(); ++v) {
    weld[v] = v;
  }
  m.seamGroup.assign(m.vertices.size(), kNone);
  {
    double edgeSum = 0;
    std::size_t edges = 0;
    for (const Impl::Cell& c : m.cells) {
      if (c.corners[0] != kNone && c.corners[1] != kNone) {
        edgeSum += (m.vertices[c.corners[1]] - m.vertices[c.corners[0]]).norm();
        ++edges;
      }
    }
    constexpr double kWeld = 1e-4;
    const double eps = edges == 0 ? 0 : kWeld * edgeSum / static_cast<double>(edges);
    std::sort(border.begin(), border.end(), [&](const BorderVertex& a, const BorderVertex& b) {
      return m.vertices[a.vertex].x < m.vertices[b.vertex].x;
    });
    auto find = [&](std::uint32_t v) {
      while (weld[v] != v) {
        v = weld[v] = weld[weld[v]];
      }
      return v;
    };
    for (std::size_t i = 0; i < border.size(); ++i) {
      const Vec3d& p = m.vertices[border[i].vertex];
      for (std::size_t j = i + 1; j < border.size() && m.vertices[border[j].vertex].x - p.x <= eps;
           ++j) {
        const Vec3d& q = m.vertices[border[j].vertex];
        if (border[j].grid != border[i].grid && std::fabs(q.y - p.y) <= eps &&
            std::fabs(q.z - p.z) <= eps) {
          const std::uint32_t a = find(border[i].vertex), b = find(border[j].vertex);
          weld[std::max(a, b)] = std::min(a, b);
        }
      }
    }
    // Groups: every vertex whose root has another member.
    std::vector<std::uint32_t> members(m.vertices.size(), 0);
    for (const BorderVertex& b : border) {
      ++members[find(b.vertex)];
    }
    for (const BorderVertex& b : border) {
      const std::uint32_t root = find(b.vertex);
      weld[b.vertex] = root;
      if (members[root] > 1) {
        if (m.seamGroup[root] == kNone) {
          m.seamGroup[root] = static_cast<std::uint32_t>(m.seamCells.size());
          m.seamCells.emplace_back();
        }
        m.seamGroup[b.vertex] = m.seamGroup[root];
      }
    }
    for (std::size_t c = 0; c < m.cells.size(); ++c) {
      std::uint32_t last = kNone;
      for (const std::uint32_t v : m.cells[c].corners) {
        if (v != kNone && m.seamGroup[v] != kNone && m.seamGroup[v] != last) {
          last = m.seamGroup[v];
          std::vector<std::uint32_t>& list = m.seamCells[last];
          if (list.empty() || list.back() != c) {
            list.push_back(static_cast<std::uint32_t>(c));
          }
        }
      }
    }
  }

  for (const Impl::Cell& c : m.cells) {
    m.surfaceTriangles += c.full() ? 2 : 1;
  }

  // The bins' axis: the cells' dominant normal, the eigenvector of the largest eigenvalue of
  // sum(n n^T) over their area-weighted normals n (blind to their sign). Rays along it, as a
  // merge's along the target's normals over B mostly are, cast point-sized shadows.
  // Across it, e1 along the cells' rows (the sum of their (0,0)-(1,0) edges): a grid's cells
  // then project to boxes little wider than themselves (turned 45 degrees, theirs would be 1.4
  // times wider, and hold twice the bins' cells).
  Eigen::Matrix3d moments = Eigen::Matrix3d::Zero();
  Vec3d rows;
  // Every kAxisStride-th cell will do: any frame gives exact answers, this one only fewer cells
  // per ray.
  constexpr std::size_t kAxisStride = 7;
  for (std::size_t i = 0; i < m.cells.size(); i += kAxisStride) {
    const Impl::Cell& c = m.cells[i];
    const Vec3d n = m.normal(c);
    const Eigen::Vector3d e(n.x, n.y, n.z);
    moments += e * e.transpose();
    if (c.corners[0] != kNone && c.corners[1] != kNone) {
      rows = rows + (m.vertices[c.corners[1]] - m.vertices[c.corners[0]]);
    }
  }
  Vec3d axis{0, 0, 1};
  const Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> solver(moments);
  if (solver.info() == Eigen::Success && solver.eigenvectors().col(2).allFinite() &&
      solver.eigenvalues()(2) > 0) {
    const Eigen::Vector3d e = solver.eigenvectors().col(2);
    axis = {e.x(), e.y(), e.z()};
  }
  m.binFrame = UpFrame(m.bounds.center(), axis, rows);
  std::vector<Vec2d> projected;
  projected.reserve(m.vertices.size());
  for (const Vec3d& v : m.vertices) {
    projected.push_back(m.binFrame.project(v));
  }
  // Each cell's projected box, grown by its border reach: a ray that takes a point C of the cell
  // (within kBorderTolerance outside it, at a point X of the cell's surface extended) reports the
  // point of the ray nearest to C, no farther from C than X is, by at most the tolerance times
  // |e| + |f| + 3 |g| of a full cell (p(s, t) = p00 + s e + t f + s t g), the sum of the sides of
  // a 3-corner one; the projection along the axis moves nothing apart. Plus rounding, relative to
  // the coordinates.
  std::vector<Impl::Box2> cellBoxes;
  cellBoxes.reserve(m.cells.size());
  double sizeSum = 0;
  double largestMargin = 0;
  for (std::size_t c = 0; c < m.cells.size(); ++c) {
    const Impl::Cell& cell = m.cells[c];
    const auto& k = cell.corners;
    Impl::Box2 flat{
        std::numeric_limits<double>::infinity(), std::numeric_limits<double>::infinity(),
        -std::numeric_limits<double>::infinity(), -std::numeric_limits<double>::infinity()};
    for (const std::uint32_t v : k) {
      if (v != kNone) {
        flat.u0 = std::min(flat.u0, projected[v].u);
        flat.v0 = std::min(flat.v0, projected[v].v);
        flat.u1 = std::max(flat.u1, projected[v].u);
        flat.v1 = std::max(flat.v1, projected[v].v);
      }
    }
    double reach = 0;
    if (cell.full()) {
      const Vec3d& p00 = m.vertices[k[0]];
      const Vec3d& p10 = m.vertices[k[1]];
      const Vec3d& p11 = m.vertices[k[2]];
      const Vec3d& p01 = m.vertices[k[3]];
      reach = (p10 - p00).norm() + (p01 - p00).norm() + 3 * (p11 - p10 - p01 + p00).norm();
    } else {
      const std::array<int, 3> t = cell.triangle();
      for (int i = 0; i < 3; ++i) {
        reach += (m.vertices[k[t[(i + 1) % 3]]] - m.vertices[k[t[i]]]).norm();
      }
    }
    const double margin =
        kBorderTolerance * reach + roundingSlack({flat.u0, flat.v0, flat.u1, flat.v1, reach, 1});
    flat = {flat.u0 - margin, flat.v0 - margin, flat.u1 + margin, flat.v1 + margin};
    cellBoxes.push_back(flat);
    largestMargin = std::max(largestMargin, kBorderTolerance * reach);
    sizeSum += std::max(flat.u1 - flat.u0, flat.v1 - flat.v0);
  }
  // Every point a hit reports lies in the cells' bounds grown by the largest such margin.
  {
    const Box3d& b = m.bounds;
    const double grow =
        largestMargin + roundingSlack({b.min.x, b.min.y, b.min.z, b.max.x, b.max.y, b.max.z, 1});
    m.reachBox = {{b.min.x - grow, b.min.y - grow, b.min.z - grow},
                  {b.max.x + grow, b.max.y + grow, b.max.z + grow}};
  }
  // Square bins a little wider than the mean cell's box (so that most are in one bin, and a few
  // cells per bin), at most kBinsPerCell per cell however the boxes spread.
  double u0 = std::numeric_limits<double>::infinity(), v0 = u0, u1 = -u0, v1 = -u0;
  for (const Impl::Box2& b : cellBoxes) {
    u0 = std::min(u0, b.u0);
    v0 = std::min(v0, b.v0);
    u1 = std::max(u1, b.u1);
    v1 = std::max(v1, b.v1);
  }
  constexpr double kBinsPerCell = 4;
  const double maxBins = kBinsPerCell * static_cast<double>(m.cells.size()) + 64;
  constexpr double kSideOverMean = 1.25;
  double side = kSideOverMean * sizeSum / static_cast<double>(m.cells.size());
  side = std::max({side, std::sqrt((u1 - u0) * (v1 - v0) / maxBins), (u1 - u0) / maxBins,
                   (v1 - v0) / maxBins, std::numeric_limits<double>::min()});
  m.binU0 = u0;
  m.binV0 = v0;
  m.binSize = side;
  m.perBin = 1 / side;
  m.binsU = std::max(1, static_cast<int>(std::min(maxBins, std::ceil((u1 - u0) / side))));
  m.binsV = std::max(1, static_cast<int>(std::min(maxBins, std::ceil((v1 - v0) / side))));
  m.binStart.assign(static_cast<std::size_t>(m.binsU) * m.binsV + 1, 0);
  for (int pass = 0; pass < 2; ++pass) {
    if (pass == 1) {
      for (std::size_t b = 1; b < m.binStart.size(); ++b) {
        m.binStart[b] += m.binStart[b - 1];
      }
      m.binEntries.reset(new Impl::BinEntry[m.binStart.back()]);  // not zeroed: all are set
    }
    for (std::size_t c = 0; c < m.cells.size(); ++c) {
      const Impl::Box2 box{cellBoxes[c].u0 - m.binU0, cellBoxes[c].v0 - m.binV0,
                           cellBoxes[c].u1 - m.binU0, cellBoxes[c].v1 - m.binV0};
      Impl::BinRange r;
      if (std::max(box.u1 - box.u0, box.v1 - box.v0) <= side) {
        const double cu = 0.5 * (box.u0 + box.u1), cv = 0.5 * (box.v0 + box.v1);
        r = m.binRange({cu, cv, cu, cv});
      } else {
        r = m.binRange(box);
        m.anyWide = m.anyWide || r.u0 < r.u1 || r.v0 < r.v1;
      }
      const Impl::BinEntry entry{below(box.u0), below(box.v0), above(box.u1), above(box.v1),
                                 static_cast<std::uint32_t>(c)};
      for (int j = r.v0; j <= r.v1; ++j) {
        for (int i = r.u0; i <= r.u1; ++i) {
          const std::size_t b = static_cast<std::size_t>(j) * m.binsU + i;
          if (pass == 0) {
            ++m.binStart[b + 1];
          } else {
            m.binEntries[m.binStart[b]++] = entry;
          }
        }
      }
    }
  }
  // The fill moved each start to the next bin's: shift back.
  for (std::size_t b = m.binStart.size() - 1; b > 0; --b) {
    m.binStart[b] = m.binStart[b - 1];
  }
  m.binStart[0] = 0;
}

SurfaceCaster::~SurfaceCaster() = default;
SurfaceCaster::SurfaceCaster(SurfaceCaster&&) noexcept = default;
SurfaceCaster& SurfaceCaster::operator=(SurfaceCaster&&) noexcept = default;

std::size_t SurfaceCaster::cellCount() const {
  return impl_->cells.size();
}

std::size_t SurfaceCaster::triangleCount() const {
  return impl_->surfaceTriangles;
}

const Box3d& SurfaceCaster::bounds() const {
  return impl_->bounds;
}

std::size_t SurfaceCaster::bytes() const {
  const Impl& m = *impl_;
  std::size_t own = m.vertices.capacity() * sizeof(Vec3d) +
                    m.cells.capacity() * sizeof(Impl::Cell) +
                    m.seamGroup.capacity() * sizeof(std::uint32_t) +
                    m.binStart.capacity() * sizeof(std::uint32_t) +
                    (m.binStart.empty() ? 0 : m.binStart.back()) * sizeof(Impl::BinEntry);
  for (const Impl::GridCells& g : m.gridCells) {
    own += g.index.capacity() * sizeof(std::uint32_t);
  }
  for (const std::vector<std::uint32_t>& s : m.seamCells) {
    own += s.capacity() * sizeof(std::uint32_t);
  }
  return own;
}

std::optional<CastHit> SurfaceCaster::cast(const CastRay& ray) const {
  std::optional<CastHit> hit;
  cast(std::span<const CastRay>(&ray, 1), std::span<std::optional<CastHit>>(&hit, 1));
  return hit;
}

void SurfaceCaster::cast(std::span<const CastRay> rays,
                         std::span<std::optional<CastHit>> hits) const {
  if (hits.size() != rays.size()) {
    throw Error(ErrorCode::InvalidArgument, "surface caster: hits and rays differ in number");
  }
  const Impl& m = *impl_;
  std::fill(hits.begin(), hits.end(), std::nullopt);
  if (m.cells.empty()) {
    return;
  }
  // A cell the line meets (within B's border tolerance), at signed distance t.
  struct Found {
    double t;
    std::uint32_t cell;
    Impl::CellHit hit;
  };
  auto nearer = [](const Found& x, const Found& y) {
    // The nearest first, the positive side on a tie, then the cell in grid order.
    const double ax = std::fabs(x.t), ay = std::fabs(y.t);
    if (ax != ay) {
      return ax < ay;
    }
    return x.t != y.t ? x.t > y.t : x.cell < y.cell;
  };
  std::vector<std::uint32_t> tested, added;
  std::vector<Found> found;
  double lastDistance = 0;
  for (std::size_t r = 0; r < rays.size(); ++r) {
    const CastRay& ray = rays[r];
    // The direction scaled by its largest component first, so that its length neither
    // overflows nor underflows.
    const double largest = std::max(
        {std::fabs(ray.direction.x), std::fabs(ray.direction.y), std::fabs(ray.direction.z)});
    if (!ray.origin.finite() || !ray.direction.finite() || !(largest > 0) ||
        !std::isfinite(ray.tmin) || !std::isfinite(ray.tmax) || !(ray.tmin <= ray.tmax)) {
      continue;
    }
    const Vec3d scaled = ray.direction * (1.0 / largest);
    const Vec3d d = scaled * (1.0 / scaled.norm());
    // Only the part of [tmin, tmax] inside reachBox can hold a hit's point (widened by the
    // rounding of the slab test, relative to the coordinates).
    const auto inside = clipToBox(ray.origin, d, ray.tmin, ray.tmax, m.reachBox);
    if (!inside) {
      continue;
    }
    const Vec3d& low = m.reachBox.min;
    const Vec3d& high = m.reachBox.max;
    const double round = roundingSlack(
        {ray.origin.x, ray.origin.y, ray.origin.z, low.x, low.y, low.z, high.x, high.y, high.z});
    const double searchMin = std::max(ray.tmin, inside->first - round);
    const double searchMax = std::min(ray.tmax, inside->second + round);
    const Impl::Line line{ray.origin, d, UpFrame::aroundUnit(ray.origin, d)};
    // The line's shadow in the bins' plane, relative to the bins' corner: s0 + t * w.
    const Vec2d projected = m.binFrame.project(ray.origin);
    const Vec2d s0{projected.u - m.binU0, projected.v - m.binV0};
    const Vec2d w{dot(d, m.binFrame.e1), dot(d, m.binFrame.e2)};
    const double slack =
        roundingSlack({projected.u, projected.v, m.binU0, m.binV0, searchMin, searchMax, 1});
    // Whether the shadow of [lo, hi] meets a box (grown by slack) that meets the shadow's box
    // (so along a coordinate the line does not move in, it lies within the box's), in the plane.
    const double from[2] = {s0.u, s0.v}, along[2] = {w.u, w.v};
    const double inverse[2] = {w.u == 0 ? 0 : 1 / w.u, w.v == 0 ? 0 : 1 / w.v};
    auto meets = [&](const Impl::BinEntry& box, double lo, double hi) {
      const double bmin[2] = {box.u0 - slack, box.v0 - slack};
      const double bmax[2] = {box.u1 + slack, box.v1 + slack};
      for (int k = 0; k < 2; ++k) {
        if (along[k] != 0) {
          const double t0 = (bmin[k] - from[k]) * inverse[k];
          const double t1 = (bmax[k] - from[k]) * inverse[k];
          lo = std::max(lo, std::min(t0, t1));
          hi = std::min(hi, std::max(t0, t1));
        }
      }
      return lo <= hi;
    };
    // Rounds over a growing stretch [-reach, reach] of the ray (within [searchMin, searchMax]):
    // once every cell the stretch can meet is intersected, a hit within it is final (no farther
    // cell can be nearer), so a ray that meets B near its origin, as a merge's mostly do, looks
    // at a few cells only. The first stretch: twice the last hit's distance (rays in grid order
    // meet B at about the same), at least a quarter of a bin and at least as far as the search
    // range's nearer end; then 8 times longer each round. (Only the work depends on them, never
    // the answer.)
    tested.clear();
    found.clear();
    const double farthest = std::max(std::fabs(searchMin), std::fabs(searchMax));
    const double nearest = searchMin > 0 ? searchMin : (searchMax < 0 ? -searchMax : 0);
    for (double reach = std::max({m.binSize / 4, 2 * lastDistance, nearest});; reach *= 8) {
      const bool last = reach >= farthest;
      const double lo = last ? searchMin : std::max(searchMin, -reach);
      const double hi = last ? searchMax : std::min(searchMax, reach);
      added.clear();
      if (lo <= hi) {
        const Vec2d a{s0.u + w.u * lo, s0.v + w.v * lo}, b{s0.u + w.u * hi, s0.v + w.v * hi};
        // The shadow's box: a cell's box must meet it (cheap) before the exact slab test.
        const Impl::Box2 shadow{std::min(a.u, b.u) - slack, std::min(a.v, b.v) - slack,
                                std::max(a.u, b.u) + slack, std::max(a.v, b.v) + slack};
        const double half = 0.5 * m.binSize;
        const Impl::BinRange bins =
            m.binRange({shadow.u0 - half, shadow.v0 - half, shadow.u1 + half, shadow.v1 + half});
        for (int j = bins.v0; j <= bins.v1; ++j) {
          for (int i = bins.u0; i <= bins.u1; ++i) {
            const std::size_t bin = static_cast<std::size_t>(j) * m.binsU + i;
            for (std::uint32_t e = m.binStart[bin]; e < m.binStart[bin + 1]; ++e) {
              const Impl::BinEntry& box = m.binEntries[e];
              // One branch for the four comparisons (their outcome is hard to predict).
              if ((box.u0 <= shadow.u1) & (shadow.u0 <= box.u1) & (box.v0 <= shadow.v1) &
                      (shadow.v0 <= box.v1) &&
                  meets(box, lo, hi)) {
                added.push_back(box.cell);
              }
            }
          }
        }
        if (m.anyWide) {  // a wide cell comes once per bin it is in
          std::sort(added.begin(), added.end());
          added.erase(std::unique(added.begin(), added.end()), added.end());
        }
        for (const std::uint32_t c : added) {
          if (!tested.empty() && std::binary_search(tested.begin(), tested.end(), c)) {
            continue;
          }
          if (const std::optional<Impl::CellHit> h = m.intersect(m.cells[c], line)) {
            // Only hits within [tmin, tmax] compete (one outside must not win through a
            // neighbour, nor hide a farther one).
            const double t = m.distance(m.cells[c], *h, line);
            if (t >= ray.tmin && t <= ray.tmax) {
              found.push_back({t, c, *h});
            }
          }
        }
        std::sort(found.begin(), found.end(), nearer);
      }
      // The nearest hit, once it lies within the stretch (every hit as near is known then). Its
      // own point is within [tmin, tmax], so resolve() always answers.
      if (!found.empty() && (last || std::fabs(found.front().t) <= reach)) {
        const Found& f = found.front();
        hits[r] = m.resolve(f.cell, f.hit, line, ray.tmin, ray.tmax);
        if (hits[r]) {
          lastDistance = std::fabs(hits[r]->distance);
        }
      }
      if (hits[r] || last) {
        break;
      }
      // Another round: this one's cells are not intersected again.
      const std::size_t before = tested.size();
      std::sort(added.begin(), added.end());
      tested.insert(tested.end(), added.begin(), added.end());
      std::inplace_merge(tested.begin(), tested.begin() + static_cast<std::ptrdiff_t>(before),
                         tested.end());
      tested.erase(std::unique(tested.begin(), tested.end()), tested.end());
    }
  }
}

}  // namespace vsm::core
