#include "core/merge/surface_caster.hpp"

#include <embree3/rtcore.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>
#include <string>

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
// Rays go through Embree in chunks of this many (each as a forward and a backward ray).
constexpr std::size_t kChunk = 128;

double dot(const Vec3d& a, const Vec3d& b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}

// Grid offsets of a cell's corners, in the order (0,0), (1,0), (1,1), (0,1).
constexpr int kCornerX[4] = {0, 1, 1, 0};
constexpr int kCornerY[4] = {0, 0, 1, 1};

/// The one Embree device: created on first use, with threads=1 (builds and casts run on the
/// calling thread; core creates no threads). Never released.
RTCDevice device() {
  static const RTCDevice d = [] {
    RTCDevice created = rtcNewDevice("threads=1,set_affinity=0");
    if (created == nullptr) {
      throw Error(ErrorCode::Internal,
                  "embree: cannot create a device: " + std::to_string(rtcGetDeviceError(nullptr)));
    }
    return created;
  }();
  return d;
}

void checkEmbree(const char* what) {
  const RTCError error = rtcGetDeviceError(device());
  if (error != RTC_ERROR_NONE) {
    throw Error(ErrorCode::Internal,
                std::string("embree: ") + what + " failed (error " + std::to_string(error) + ")");
  }
}

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

  Vec3d origin;  // the float geometry's origin
  // Far beyond float32 rounding of a distance along a ray in the float geometry: 2^-16 of its
  // largest coordinate (rounding is 2^-24 of it per coordinate and operation).
  float tSlack = 0;
  std::vector<Vec3d> vertices;  // global (transformed) double positions of the cells' corners
  std::vector<Cell> cells;      // in grid order
  std::vector<std::uint32_t> quadCell;  // per Embree quad (primID), its cell
  std::size_t surfaceTriangles = 0;     // the cells' (a full cell's two, a 3-corner cell's one)
  std::size_t triangles = 0;            // the cells' and the skirts'
  // Seams between B's grids: per vertex on a grid's border that coincides (within rounding) with
  // a vertex of another grid, its group (index into seamCells, else kNone), and per group the
  // cells with a corner in it.
  std::vector<std::uint32_t> seamGroup;
  std::vector<std::vector<std::uint32_t>> seamCells;
  std::vector<GridCells> gridCells;
  Box3d bounds;
  RTCScene scene = nullptr;

  ~Impl() {
    if (scene != nullptr) {
      rtcReleaseScene(scene);
    }
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

  std::optional<CellHit> intersect(const Cell& cell, const Line& line) const {
    const Vec2d q{0, 0};  // the ray, projected across itself
    if (cell.corners[3] == kNone || cell.corners[0] == kNone || cell.corners[1] == kNone ||
        cell.corners[2] == kNone) {
      std::array<int, 3> which{};
      std::array<Vec2d, 3> p{};
      int n = 0;
      for (int k = 0; k < 4; ++k) {
        if (cell.corners[k] != kNone) {
          which[n] = k;
          p[n] = line.frame.project(vertices[cell.corners[k]]);
          ++n;
        }
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

  /// The answer for a hit Embree reported in `cellIndex`: the best of that cell and (near its
  /// border) its neighbours, by (outside, |t|, cell); nullopt when none is within tolerance or
  /// the best lies outside [tmin, tmax].
  std::optional<CastHit> resolve(std::uint32_t cellIndex, const Line& line, double tmin,
                                 double tmax) const {
    std::optional<CastHit> best;
    double bestOutside = std::numeric_limits<double>::infinity();
    double bestAbs = std::numeric_limits<double>::infinity();
    std::uint32_t bestCell = kNone;
    auto consider = [&](std::uint32_t index) -> bool {  // returns nearBorder
      const Cell& cell = cells[index];
      const std::optional<CellHit> h = intersect(cell, line);
      if (!h) {
        return false;
      }
      Vec3d p{0, 0, 0};
      double x = 0, y = 0;
      for (int k = 0; k < 4; ++k) {
        if (h->weights[k] != 0) {
          p = p + vertices[cell.corners[k]] * h->weights[k];
          x += (cell.x + kCornerX[k]) * h->weights[k];
          y += (cell.y + kCornerY[k]) * h->weights[k];
        }
      }
      const double t = dot(p - line.origin, line.direction);
      const double a = std::fabs(t);
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
    if (consider(cellIndex)) {
      const Cell& cell = cells[cellIndex];
      const GridCells& grid = gridCells[cell.grid];
      for (int dy = -1; dy <= 1; ++dy) {
        for (int dx = -1; dx <= 1; ++dx) {
          const std::uint32_t n =
              grid.at(static_cast<int>(cell.x) + dx, static_cast<int>(cell.y) + dy);
          if ((dx != 0 || dy != 0) && n != kNone) {
            consider(n);
          }
        }
      }
      // Across a seam: the other grids' cells sharing a corner with this one.
      for (const std::uint32_t corner : cell.corners) {
        if (corner != kNone && seamGroup[corner] != kNone) {
          for (const std::uint32_t n : seamCells[seamGroup[corner]]) {
            if (cells[n].grid != cell.grid) {
              consider(n);
            }
          }
        }
      }
    }
    if (best && !(best->distance >= tmin && best->distance <= tmax)) {
      return std::nullopt;
    }
    return best;
  }
};

Box3d SurfaceCaster::grownBox(const Box3d& b) {
  const Vec3d size = b.size();
  const double margin = 2 * kBorderTolerance * (size.x + size.y + size.z) +
                        1e-9 * (std::fabs(b.min.x) + std::fabs(b.min.y) + std::fabs(b.min.z) + 1);
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

  m.gridCells.resize(grids.size());
  std::vector<std::uint32_t> index;  // per grid vertex: its vertices index, kNone before use
  struct BorderVertex {
    std::uint32_t vertex, grid;
  };
  std::vector<BorderVertex> border;  // vertices on their grid's border
  std::vector<Vec3d> global;
  for (std::size_t gridIndex = 0; gridIndex < grids.size(); ++gridIndex) {
    const auto& grid = grids[gridIndex];
    if (!grid) {
      continue;
    }
    const int s = grid->size();
    const int blocksPerSide = (s - 1 + kBlockCells - 1) / kBlockCells;
    std::span<const Box3d> blocks;
    if (clip && !clip->blocks.empty()) {
      blocks = clip->blocks[gridIndex];
      if (blocks.size() != static_cast<std::size_t>(blocksPerSide) * blocksPerSide) {
        throw Error(ErrorCode::InvalidArgument,
                    "surface caster: the clip's block footprints do not match the grids");
      }
    }
    index.assign(static_cast<std::size_t>(s) * s, kNone);
    global.assign(index.size(), Vec3d{});
    std::vector<char> computed(index.size(), 0);
    auto at = [&](int x, int y) -> const Vec3d& {
      const std::size_t i = static_cast<std::size_t>(y) * s + x;
      if (!computed[i]) {
        const Vec3d g = grid->global(x, y);
        global[i] = transform ? transform->apply(g) : g;
        computed[i] = 1;
      }
      return global[i];
    };
    auto vertex = [&](int x, int y) {
      const std::size_t i = static_cast<std::size_t>(y) * s + x;
      if (index[i] == kNone) {
        index[i] = static_cast<std::uint32_t>(m.vertices.size());
        m.vertices.push_back(at(x, y));
        if (x == 0 || y == 0 || x == s - 1 || y == s - 1) {
          border.push_back({index[i], static_cast<std::uint32_t>(gridIndex)});
        }
      }
      return index[i];
    };
    const std::size_t firstCell = m.cells.size();
    for (int by = 0; by < blocksPerSide; ++by) {
      for (int bx = 0; bx < blocksPerSide; ++bx) {
        if (!blocks.empty()) {
          const Box3d& b = blocks[static_cast<std::size_t>(by) * blocksPerSide + bx];
          if (b.empty() || !wanted(b)) {
            continue;
          }
        }
        for (int y = by * kBlockCells; y < std::min((by + 1) * kBlockCells, s - 1); ++y) {
          for (int x = bx * kBlockCells; x < std::min((bx + 1) * kBlockCells, s - 1); ++x) {
            int defined = 0;
            Box3d box;
            for (int k = 0; k < 4; ++k) {
              if (grid->defined(x + kCornerX[k], y + kCornerY[k])) {
                ++defined;
                box.extend(at(x + kCornerX[k], y + kCornerY[k]));
              }
            }
            if (defined < 3 || !wanted(box)) {
              continue;
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
            m.bounds.extend(box);
          }
        }
      }
    }
    // Blocks were visited block by block: put the grid's cells in grid order (row by row), which
    // the tie rule (smallest cell) and coherent traversal want.
    std::sort(m.cells.begin() + static_cast<std::ptrdiff_t>(firstCell), m.cells.end(),
              [](const Impl::Cell& a, const Impl::Cell& b) {
                return a.y != b.y ? a.y < b.y : a.x < b.x;
              });
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
  // within kWeld of the cells' mean edge are one vertex of the hierarchy (so the float traversal is
  // watertight across seams too) and one seam group (so a hit there is resolved among the cells of
  // both grids). Weld: the lowest index of a group.
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

  // The float geometry's origin: the clip's centre (a patch-local origin), else B's.
  m.origin = clip && !clip->box.empty() ? clip->box.center() : m.bounds.center();
  // One Embree quad per cell: half the primitives of two triangles, so the hierarchy builds in
  // about 0.6 of the time (tests/bench/caster_bench.sh). Embree splits a quad (v0, v1, v2, v3)
  // into the triangles (v0, v1, v3) and (v2, v3, v1), along v1-v3: a full cell is given so that
  // this is its shorter diagonal in 3D; a 3-corner cell is its triangle with the last corner
  // repeated (Embree's encoding of a triangle: the second one is a line, never hit).
  std::vector<std::array<std::uint32_t, 4>> quads;
  quads.reserve(m.cells.size());
  m.quadCell.reserve(m.cells.size());
  for (std::size_t c = 0; c < m.cells.size(); ++c) {
    const auto& k = m.cells[c].corners;
    if (k[0] != kNone && k[1] != kNone && k[2] != kNone && k[3] != kNone) {
      const double d02 = (m.vertices[k[2]] - m.vertices[k[0]]).norm();
      const double d13 = (m.vertices[k[3]] - m.vertices[k[1]]).norm();
      if (d02 <= d13) {
        quads.push_back({k[1], k[2], k[3], k[0]});
      } else {
        quads.push_back({k[0], k[1], k[2], k[3]});
      }
      m.surfaceTriangles += 2;
    } else {
      std::array<std::uint32_t, 4> t{};
      int n = 0;
      for (const std::uint32_t v : k) {
        if (v != kNone) {
          t[n++] = v;
        }
      }
      t[3] = t[2];
      quads.push_back(t);
      m.surfaceTriangles += 1;
    }
    m.quadCell.push_back(static_cast<std::uint32_t>(c));
  }
  m.triangles = m.surfaceTriangles;
  // Skirts: every edge of a cell on B's border (no cell across it in its grid, and not a welded
  // seam) gets a strip of two triangles outside it, owned by the cell, so that a ray within
  // kBorderTolerance of the cell (cell_geometry's measure: the parameter clamped onto a full
  // cell, a triangle's barycentric coordinates clamped and re-normalised) meets the hierarchy
  // and resolves to the cell's nearest point. The strip is wider than that (a full cell's sides
  // extended by 1.5 times the tolerance, a triangle scaled about the corner off the edge by 2
  // times it, which covers the re-normalised measure): resolve() refuses the rest and the ray
  // goes on past it. Float vertices only.
  const auto vertexCount = static_cast<std::uint32_t>(m.vertices.size());
  std::vector<Vec3d> skirt;
  {
    constexpr double kQuadSkirt = 1.5 * kBorderTolerance;
    constexpr double kTriangleSkirt = 2 * kBorderTolerance;
    constexpr int kAcrossX[4] = {0, 1, 0, -1};  // the neighbour across edge e = (e, e + 1)
    constexpr int kAcrossY[4] = {-1, 0, 1, 0};
    auto addStrip = [&](std::uint32_t a, std::uint32_t b, const Vec3d& awayA, const Vec3d& awayB,
                        double width, std::uint32_t cellIndex) {
      const Vec3d& pa = m.vertices[a];
      const Vec3d& pb = m.vertices[b];
      const auto ea = vertexCount + static_cast<std::uint32_t>(skirt.size());
      skirt.push_back(pa + awayA * width);
      skirt.push_back(pb + awayB * width);
      quads.push_back({b, a, ea, ea + 1});  // the triangles (b, a, ea + 1) and (ea, ea + 1, a)
      m.quadCell.push_back(cellIndex);
      m.triangles += 2;
    };
    for (std::size_t c = 0; c < m.cells.size(); ++c) {
      const Impl::Cell& cell = m.cells[c];
      const auto& k = cell.corners;
      const auto cellIndex = static_cast<std::uint32_t>(c);
      const bool full = k[0] != kNone && k[1] != kNone && k[2] != kNone && k[3] != kNone;
      std::uint32_t opposite = kNone;  // a triangle's: the corner off a given edge
      for (int e = 0; e < 4; ++e) {
        const std::uint32_t a = k[e], b = k[(e + 1) % 4];
        if (a == kNone || b == kNone) {
          continue;
        }
        const bool across =
            m.gridCells[cell.grid].at(static_cast<int>(cell.x) + kAcrossX[e],
                                      static_cast<int>(cell.y) + kAcrossY[e]) != kNone;
        const bool seam = m.seamGroup[a] != kNone && m.seamGroup[b] != kNone;
        if (across || seam) {
          continue;
        }
        if (full) {
          const Vec3d& innerA = m.vertices[k[(e + 3) % 4]];
          const Vec3d& innerB = m.vertices[k[(e + 2) % 4]];
          addStrip(a, b, m.vertices[a] - innerA, m.vertices[b] - innerB, kQuadSkirt, cellIndex);
        } else {
          for (const std::uint32_t v : k) {
            if (v != kNone && v != a && v != b) {
              opposite = v;
            }
          }
          const Vec3d& o = m.vertices[opposite];
          addStrip(a, b, m.vertices[a] - o, m.vertices[b] - o, kTriangleSkirt, cellIndex);
        }
      }
      if (!full) {  // the diagonal of a 3-corner cell is always B's border
        // The corners off the diagonal: the missing corner's neighbours in the cycle.
        int missing = 0;
        while (k[missing] != kNone) {
          ++missing;
        }
        const std::uint32_t a = k[(missing + 1) % 4], b = k[(missing + 3) % 4];
        const Vec3d& o = m.vertices[k[(missing + 2) % 4]];
        addStrip(a, b, m.vertices[a] - o, m.vertices[b] - o, kTriangleSkirt, cellIndex);
      }
    }
  }

  const RTCDevice dev = device();
  RTCGeometry geometry = rtcNewGeometry(dev, RTC_GEOMETRY_TYPE_QUAD);
  auto* vertexBuffer = static_cast<float*>(
      rtcSetNewGeometryBuffer(geometry, RTC_BUFFER_TYPE_VERTEX, 0, RTC_FORMAT_FLOAT3,
                              3 * sizeof(float), m.vertices.size() + skirt.size()));
  auto* indexBuffer = static_cast<unsigned*>(rtcSetNewGeometryBuffer(
      geometry, RTC_BUFFER_TYPE_INDEX, 0, RTC_FORMAT_UINT4, 4 * sizeof(unsigned), quads.size()));
  if (vertexBuffer == nullptr || indexBuffer == nullptr) {
    rtcReleaseGeometry(geometry);
    checkEmbree("allocating the geometry");
    throw Error(ErrorCode::Internal, "embree: allocating the geometry failed");
  }
  double largest = 0;
  for (std::size_t v = 0; v < m.vertices.size(); ++v) {
    const Vec3d p = m.vertices[v] - m.origin;
    largest = std::max({largest, std::fabs(p.x), std::fabs(p.y), std::fabs(p.z)});
    vertexBuffer[3 * v] = static_cast<float>(p.x);
    vertexBuffer[3 * v + 1] = static_cast<float>(p.y);
    vertexBuffer[3 * v + 2] = static_cast<float>(p.z);
  }
  for (std::size_t v = 0; v < skirt.size(); ++v) {
    const Vec3d p = skirt[v] - m.origin;
    float* f = vertexBuffer + 3 * (vertexCount + v);
    f[0] = static_cast<float>(p.x);
    f[1] = static_cast<float>(p.y);
    f[2] = static_cast<float>(p.z);
  }
  for (std::size_t q = 0; q < quads.size(); ++q) {
    for (int k = 0; k < 4; ++k) {
      const std::uint32_t v = quads[q][k];
      indexBuffer[4 * q + k] = v < vertexCount ? weld[v] : v;
    }
  }
  m.tSlack = static_cast<float>(largest * 0x1p-16);
  rtcCommitGeometry(geometry);
  m.scene = rtcNewScene(dev);
  rtcSetSceneFlags(m.scene, RTC_SCENE_FLAG_ROBUST);
  rtcSetSceneBuildQuality(m.scene, RTC_BUILD_QUALITY_MEDIUM);
  rtcAttachGeometry(m.scene, geometry);
  rtcReleaseGeometry(geometry);
  rtcCommitScene(m.scene);
  checkEmbree("building the hierarchy");
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
                    m.quadCell.capacity() * sizeof(std::uint32_t);
  for (const Impl::GridCells& g : m.gridCells) {
    own += g.index.capacity() * sizeof(std::uint32_t);
  }
  // Embree's float vertices and indices, and its hierarchy (measured by caster_bench: about
  // 100 bytes per triangle with the vertex and index buffers).
  return own + m.triangles * 100;
}

std::optional<CastHit> SurfaceCaster::cast(const CastRay& ray) const {
  std::optional<CastHit> hit;
  cast(std::span<const CastRay>(&ray, 1), std::span<std::optional<CastHit>>(&hit, 1),
       Batch::Single);
  return hit;
}

void SurfaceCaster::cast(std::span<const CastRay> rays, std::span<std::optional<CastHit>> hits,
                         Batch batch) const {
  if (hits.size() != rays.size()) {
    throw Error(ErrorCode::InvalidArgument, "surface caster: hits and rays differ in number");
  }
  const Impl& m = *impl_;
  std::fill(hits.begin(), hits.end(), std::nullopt);
  if (m.scene == nullptr) {
    return;
  }
  RTCIntersectContext context;
  rtcInitIntersectContext(&context);
  context.flags = RTC_INTERSECT_CONTEXT_FLAG_COHERENT;
  // Per ray of a chunk, a forward ray (along the direction, t in [max(tmin, 0), tmax]) and a
  // backward one (against it, for t in [tmin, min(tmax, 0)]), next to each other. An unused one
  // has tnear > tfar (inactive). The far end is widened a little for float rounding: the answer is
  // checked against [tmin, tmax] in double.
  std::array<RTCRayHit, 2 * kChunk> stream;
  std::array<float, 2 * kChunk> far;  // each ray's end of the search (Embree moves tfar to a hit)
  for (std::size_t first = 0; first < rays.size(); first += kChunk) {
    const std::size_t n = std::min(kChunk, rays.size() - first);
    for (std::size_t i = 0; i < n; ++i) {
      const CastRay& ray = rays[first + i];
      const double length = ray.direction.norm();
      const bool valid = ray.origin.finite() && ray.direction.finite() && length > 0 &&
                         std::isfinite(ray.tmin) && std::isfinite(ray.tmax) && ray.tmin <= ray.tmax;
      const Vec3d d = valid ? ray.direction * (1.0 / length) : Vec3d{0, 0, 1};
      const Vec3d o = valid ? ray.origin - m.origin : Vec3d{};
      for (int side = 0; side < 2; ++side) {
        RTCRayHit& rh = stream[2 * i + side];
        const double sign = side == 0 ? 1.0 : -1.0;
        rh.ray.org_x = static_cast<float>(o.x);
        rh.ray.org_y = static_cast<float>(o.y);
        rh.ray.org_z = static_cast<float>(o.z);
        rh.ray.dir_x = static_cast<float>(sign * d.x);
        rh.ray.dir_y = static_cast<float>(sign * d.y);
        rh.ray.dir_z = static_cast<float>(sign * d.z);
        const double lo = side == 0 ? std::max(ray.tmin, 0.0) : std::max(-ray.tmax, 0.0);
        const double hi = side == 0 ? ray.tmax : -ray.tmin;
        if (valid && hi >= lo) {
          rh.ray.tnear = static_cast<float>(lo);
          rh.ray.tfar = static_cast<float>(hi + 1e-5 * std::fabs(hi) + m.tSlack);
        } else {
          rh.ray.tnear = 1;
          rh.ray.tfar = 0;
        }
        far[2 * i + side] = rh.ray.tfar;
        rh.ray.time = 0;
        rh.ray.mask = 0xFFFFFFFFu;
        rh.ray.id = 0;
        rh.ray.flags = 0;
        rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
        rh.hit.primID = RTC_INVALID_GEOMETRY_ID;
        rh.hit.instID[0] = RTC_INVALID_GEOMETRY_ID;
      }
    }
    // Resolves side `side` of ray i (already intersected): a hit the double resolution rejects
    // (beyond the tolerance, out of [tmin, tmax], or a triangle the bilinear cell does not meet)
    // does not hide a farther one: the ray goes on past it, a few times at most.
    auto settle = [&](std::size_t i, int side, const Impl::Line& line) -> std::optional<CastHit> {
      RTCRayHit& rh = stream[2 * i + side];
      const CastRay& ray = rays[first + i];
      for (int attempt = 0; attempt < 4 && rh.hit.geomID != RTC_INVALID_GEOMETRY_ID; ++attempt) {
        if (std::optional<CastHit> hit =
                m.resolve(m.quadCell[rh.hit.primID], line, ray.tmin, ray.tmax)) {
          return hit;
        }
        rh.ray.tnear = rh.ray.tfar + m.tSlack;  // past the rejected hit
        rh.ray.tfar = far[2 * i + side];
        rh.hit.geomID = RTC_INVALID_GEOMETRY_ID;
        if (rh.ray.tnear <= rh.ray.tfar) {
          rtcIntersect1(m.scene, &context, &rh);
        }
      }
      return std::nullopt;
    };
    if (batch == Batch::Stream) {
      rtcIntersect1M(m.scene, &context, stream.data(), static_cast<unsigned>(2 * n),
                     sizeof(RTCRayHit));
    }
    for (std::size_t i = 0; i < n; ++i) {
      RTCRayHit& forward = stream[2 * i];
      RTCRayHit& backward = stream[2 * i + 1];
      if (forward.ray.tnear > forward.ray.tfar && backward.ray.tnear > backward.ray.tfar) {
        continue;  // invalid, or nothing to search
      }
      const CastRay& ray = rays[first + i];
      const Vec3d d = ray.direction * (1.0 / ray.direction.norm());
      const Impl::Line line{ray.origin, d, UpFrame(ray.origin, d)};
      if (batch == Batch::Single && forward.ray.tnear <= forward.ray.tfar) {
        rtcIntersect1(m.scene, &context, &forward);
      }
      const std::optional<CastHit> a = settle(i, 0, line);
      if (batch == Batch::Single) {
        // Only a backward hit about as near as the forward one can win.
        if (a) {
          far[2 * i + 1] = std::min(
              far[2 * i + 1], static_cast<float>(std::fabs(a->distance)) * (1 + 1e-5f) + m.tSlack);
          backward.ray.tfar = far[2 * i + 1];
        }
        if (backward.ray.tnear <= backward.ray.tfar) {
          rtcIntersect1(m.scene, &context, &backward);
        }
      }
      const std::optional<CastHit> b = settle(i, 1, line);
      // The nearest wins, the positive side on a tie.
      if (a && b) {
        const double da = std::fabs(a->distance), db = std::fabs(b->distance);
        hits[first + i] = db < da || (db == da && b->distance > a->distance) ? b : a;
      } else {
        hits[first + i] = a ? a : b;
      }
    }
  }
}

}  // namespace vsm::core
