#pragma once

// Internal to core/diff (included by revision_diff.cpp only): the other revision's surface around
// a leaf, indexed for casting lines along normals and counting points in cylinders
// (SurfaceIndex), and the grid helpers it and the diff's sampler share.

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <memory>
#include <optional>
#include <vector>

#include "core/common/error.hpp"
#include "core/grid/vec_ops.hpp"
#include "core/merge/merge.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core::diff_detail {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

using vec::cross;
using vec::dot;
using vec::vertexNormal;

/// A grid's global positions, computed once (NaN where undefined): what the diff reads of a grid
/// many times, with PatchGrid's interface (size, defined, global).
struct Points {
  const Vec3d* at = nullptr;
  int s = 0;
  int size() const { return s; }
  bool defined(int x, int y) const {
    return std::isfinite(at[static_cast<std::size_t>(y) * s + x].x);
  }
  const Vec3d& global(int x, int y) const { return at[static_cast<std::size_t>(y) * s + x]; }
};

/// `grid`'s global positions, NaN where undefined.
inline std::vector<Vec3d> globalPositions(const PatchGrid& grid) {
  const int s = grid.size();
  std::vector<Vec3d> out(grid.vertexCount(), Vec3d{kNaN, kNaN, kNaN});
  for (int y = 0; y < s; ++y) {
    for (int x = 0; x < s; ++x) {
      if (grid.defined(x, y)) {
        out[static_cast<std::size_t>(y) * s + x] = grid.global(x, y);
      }
    }
  }
  return out;
}

/// The corners of cell (x, y) of `grid` that are defined, in winding order ((x, y), (x+1, y),
/// (x+1, y+1), (x, y+1)); a cell is a surface with 3 or 4 of them.
template <class Grid>
inline int cellCorners(const Grid& grid, int x, int y, std::array<std::pair<int, int>, 4>& out) {
  int n = 0;
  for (const auto& [u, v] : {std::pair{x, y}, {x + 1, y}, {x + 1, y + 1}, {x, y + 1}}) {
    if (grid.defined(u, v)) {
      out[n++] = {u, v};
    }
  }
  return n;
}

/// Each vertex's share of the surface as an area vector (winding side): a quarter of every full
/// cell around it (half the cross product of its diagonals), a third of every 3-corner cell.
/// |a . n| is the vertex's area on a surface of normal n.
inline std::vector<Vec3d> vertexAreas(const PatchGrid& grid) {
  const int s = grid.size();
  std::vector<Vec3d> areas(grid.vertexCount());
  std::array<std::pair<int, int>, 4> at{};
  for (int y = 0; y + 1 < s; ++y) {
    for (int x = 0; x + 1 < s; ++x) {
      const int n = cellCorners(grid, x, y, at);
      Vec3d area;
      if (n == 4) {
        area =
            cross(grid.global(at[2].first, at[2].second) - grid.global(at[0].first, at[0].second),
                  grid.global(at[3].first, at[3].second) - grid.global(at[1].first, at[1].second));
      } else if (n == 3) {
        const Vec3d c0 = grid.global(at[0].first, at[0].second);
        area = cross(grid.global(at[1].first, at[1].second) - c0,
                     grid.global(at[2].first, at[2].second) - c0);
      } else {
        continue;
      }
      for (int k = 0; k < n; ++k) {
        Vec3d& a = areas[static_cast<std::size_t>(at[k].second) * s + at[k].first];
        a = a + area * (0.5 / n);
      }
    }
  }
  return areas;
}

/// Where the line p + t dir meets triangle (a, b, c) (Moeller-Trumbore): t and the barycentric
/// weights of b and c; none when it misses or runs parallel.
inline std::optional<std::array<double, 3>> lineTriangle(const Vec3d& p, const Vec3d& dir,
                                                         const Vec3d& a, const Vec3d& b,
                                                         const Vec3d& c) {
  constexpr double kTolerance = 1e-9;
  const Vec3d e1 = b - a, e2 = c - a;
  const Vec3d pv = cross(dir, e2);
  const double det = dot(e1, pv);
  if (!(std::abs(det) > 1e-300)) {
    return std::nullopt;
  }
  const double inv = 1 / det;
  const Vec3d tv = p - a;
  const double u = dot(tv, pv) * inv;
  if (u < -kTolerance || u > 1 + kTolerance) {
    return std::nullopt;
  }
  const Vec3d qv = cross(tv, e1);
  const double v = dot(dir, qv) * inv;
  if (v < -kTolerance || u + v > 1 + kTolerance) {
    return std::nullopt;
  }
  return std::array<double, 3>{dot(e2, qv) * inv, u, v};
}

/// A side's roughness in a cylinder of axis n: the variance of the points' offsets `r` along n
/// about their least-squares plane (z = a + b s + c w, s and w across n), with m - 3 degrees of
/// freedom; 0 for fewer than 4 points. A plane's slope across the cylinder is no roughness (a
/// grid samples a steep but smooth wall exactly), its curvature and steps are.
inline double roughness(const std::vector<Vec3d>& r, const Vec3d& n) {
  const std::size_t m = r.size();
  if (m < 4) {
    return 0;
  }
  // Two unit vectors across n.
  const Vec3d helper = std::abs(n.x) < 0.9 ? Vec3d{1, 0, 0} : Vec3d{0, 1, 0};
  Vec3d e1 = cross(n, helper);
  e1 = e1 * (1 / e1.norm());
  const Vec3d e2 = cross(n, e1);
  // Each point once in (s, w, z), then the plane through the centroid: with s and w centred the
  // normal equations of [1 s w] [a b c]^T = z split into a = mean z and a 2 x 2 system for b, c.
  // A degenerate set (points on a line) keeps its spread about the mean.
  thread_local std::vector<std::array<double, 3>> swz;
  if (swz.size() < m) {
    swz.resize(m);
  }
  const auto end = swz.begin() + static_cast<std::ptrdiff_t>(m);
  double ms = 0, mw = 0, mz = 0;
  for (std::size_t k = 0; k < m; ++k) {
    swz[k] = {dot(r[k], e1), dot(r[k], e2), dot(r[k], n)};
    ms += swz[k][0];
    mw += swz[k][1];
    mz += swz[k][2];
  }
  const double inv = 1 / static_cast<double>(m);
  ms *= inv;
  mw *= inv;
  mz *= inv;
  double ss = 0, sw = 0, ww = 0, sz = 0, wz = 0;
  for (auto it = swz.begin(); it != end; ++it) {
    std::array<double, 3>& q = *it;
    q[0] -= ms;
    q[1] -= mw;
    q[2] -= mz;
    ss += q[0] * q[0];
    sw += q[0] * q[1];
    ww += q[1] * q[1];
    sz += q[0] * q[2];
    wz += q[1] * q[2];
  }
  const double det = ss * ww - sw * sw;
  const bool solved = det > 1e-12 * (ss + ww) * (ss + ww) && det > 0;
  const double b = solved ? (sz * ww - wz * sw) / det : 0;
  const double c = solved ? (wz * ss - sz * sw) / det : 0;
  double sum = 0;
  for (auto it = swz.begin(); it != end; ++it) {
    const std::array<double, 3>& q = *it;
    const double e = q[2] - b * q[0] - c * q[1];
    sum += e * e;
  }
  return sum / static_cast<double>(solved ? m - 3 : m - 1);
}

/// The other revision's surface around one leaf, for casting lines along normals and counting
/// points in cylinders: its leaves within reach, pinned, with their cells in a uniform 3D grid of
/// buckets (twice their largest spacing), kept as sorted (bucket, cell) pairs, 8 bytes each
/// (buckets numbered densely over the leaves' box). The last set is kept for the next leaf when it
/// needs the same leaves.
class SurfaceIndex {
 public:
  SurfaceIndex(PatchSource& source, double sign, std::size_t maxBytes)
      : source_(source), sign_(sign), maxBytes_(maxBytes) {}

  struct Hit {
    double t = 0;
    /// Unit normal there (the hit cell's vertex normals, interpolated).
    Vec3d normal;
    /// The hit cell: its grid (of this index) and corner.
    std::size_t grid = 0;
    int x = 0, y = 0;
  };

  /// Prepares the leaves meeting `box`; false when there are none.
  bool around(const Box3d& box) {
    std::vector<PatchKey> keys =
        source_.model().leavesWhere([&](const Box3d& b) { return b.intersects(box); });
    if (keys.empty()) {
      return false;
    }
    if (keys == keys_) {
      return true;
    }
    double spacing = 0, noise = 0;
    Box3d all;
    // A leaf still in the neighbourhood keeps its positions (the next leaf's neighbourhood is
    // mostly this one's).
    std::vector<std::shared_ptr<const Grid>> grids;
    std::size_t pointBytes = 0;
    for (const PatchKey& key : keys) {
      const auto kept = std::lower_bound(keys_.begin(), keys_.end(), key);
      if (kept != keys_.end() && *kept == key) {
        grids.push_back(grids_[static_cast<std::size_t>(kept - keys_.begin())]);
      } else {
        auto grid = std::make_shared<Grid>();
        grid->grid = source_.positions(key);
        grid->positions = globalPositions(*grid->grid);
        grid->resolution = grid->grid->resolution();
        grids.push_back(std::move(grid));
      }
      pointBytes += grids.back()->positions.size() * sizeof(Vec3d);
      const PatchInfo& info = source_.model().at(key);
      all.extend(info.globalBox);
      noise = std::max(noise, storageNoise(info.localBox));
      spacing = std::max(spacing, grids.back()->resolution);
    }
    clear();
    grids_ = std::move(grids);
    pointBytes_ = pointBytes;
    noise_ = noise;
    if (pointBytes_ > maxBytes_) {
      const std::size_t bytes = pointBytes_;
      clear();
      throw Error(ErrorCode::ResourceExhausted,
                  "diff: the spatial index of one leaf's neighbourhood needs more than " +
                      std::to_string(maxBytes_) + " bytes (" + std::to_string(bytes) + " so far)");
    }
    resolution_ = spacing;
    origin_ = all.center();
    const Vec3d size = all.size();
    // Twice the spacing, but no more than 2^20 buckets along any axis of the leaves' box, and
    // fewer than 2^32 in it, numbered densely (8 bytes an entry). A larger bucket only costs
    // time: the answer is the nearest hit among the cells of every bucket the line crosses.
    bucket_ = std::max({2 * spacing, size.x * 1e-6, size.y * 1e-6, size.z * 1e-6, 1e-9});
    for (;;) {
      low_ = bucketOf(all.min);
      const auto high = bucketOf(all.max);
      for (int a = 0; a < 3; ++a) {
        dims_[a] = high[a] - low_[a] + 1;
      }
      if (static_cast<double>(dims_[0]) * static_cast<double>(dims_[1]) *
              static_cast<double>(dims_[2]) <
          4.0e9) {
        break;
      }
      bucket_ *= 2;
    }
    const int s = source_.model().gridSize();
    const std::size_t cellsPerGrid = static_cast<std::size_t>(s - 1) * (s - 1);
    if (grids_.size() * cellsPerGrid >= (std::size_t{1} << 32)) {
      throw Error(ErrorCode::ResourceExhausted, "diff: too many leaves around one leaf");
    }
    std::array<std::pair<int, int>, 4> at{};
    for (std::size_t g = 0; g < grids_.size(); ++g) {
      const Points grid = points(g);
      for (int y = 0; y + 1 < s; ++y) {
        for (int x = 0; x + 1 < s; ++x) {
          const int n = cellCorners(grid, x, y, at);
          if (n < 3) {
            continue;
          }
          Box3d cell;
          for (int k = 0; k < n; ++k) {
            cell.extend(grid.global(at[k].first, at[k].second));
          }
          const auto lo = bucketOf(cell.min), hi = bucketOf(cell.max);
          const auto id = static_cast<std::uint32_t>(g * cellsPerGrid +
                                                     static_cast<std::size_t>(y) * (s - 1) + x);
          for (std::int64_t i = lo[0]; i <= hi[0]; ++i) {
            for (std::int64_t j = lo[1]; j <= hi[1]; ++j) {
              for (std::int64_t k = lo[2]; k <= hi[2]; ++k) {
                entries_.emplace_back(key({i, j, k}), id);
              }
            }
          }
          if (pointBytes_ + entries_.size() * sizeof(entries_[0]) > maxBytes_) {
            const std::size_t bytes = pointBytes_ + entries_.size() * sizeof(entries_[0]);
            clear();
            throw Error(ErrorCode::ResourceExhausted,
                        "diff: the spatial index of one leaf's neighbourhood needs more than " +
                            std::to_string(maxBytes_) + " bytes (" + std::to_string(bytes) +
                            " so far)");
          }
        }
      }
    }
    std::sort(entries_.begin(), entries_.end());
    keys_ = std::move(keys);
    return true;
  }

  /// The nearest place (smallest |t|, |t| <= reach) where the line p + t dir (dir a unit vector)
  /// meets the surface: a walk through the buckets the line crosses, outward from p both ways.
  std::optional<Hit> cast(const Vec3d& p, const Vec3d& dir, double reach) const {
    double best = kInfinity;
    std::uint32_t bestCell = 0;
    std::array<double, 3> bestHit{};
    int bestTri = 0;
    std::array<std::pair<int, int>, 4> at{};
    // Both ways at once, the nearer bucket first: a walk stops at the first bucket it enters
    // beyond the best hit so far, so a hit behind p no longer costs the whole reach ahead of it.
    std::array<Walker, 2> walkers{Walker(*this, p, dir), Walker(*this, p, dir * -1.0)};
    walkers[1].advance();  // p's bucket is the first walker's
    for (;;) {
      Walker& w = walkers[0].t <= walkers[1].t ? walkers[0] : walkers[1];
      if (w.t > reach || w.t > best) {
        break;
      }
      const std::array<std::int64_t, 3> b = w.bucket;
      w.advance();
      {
        const auto [first, last] = range(b);
        for (auto it = first; it != last; ++it) {
          const auto [grid, x, y] = cellOf(it->second);
          const Points g = points(grid);
          const int n = cellCorners(g, x, y, at);
          for (int tri = 0; tri + 2 < n; ++tri) {
            const auto hit = lineTriangle(p, dir, g.global(at[0].first, at[0].second),
                                          g.global(at[tri + 1].first, at[tri + 1].second),
                                          g.global(at[tri + 2].first, at[tri + 2].second));
            if (hit && std::abs((*hit)[0]) <= reach && std::abs((*hit)[0]) < best) {
              best = std::abs((*hit)[0]);
              bestCell = it->second;
              bestHit = *hit;
              bestTri = tri;  // its corners: 0, tri + 1, tri + 2
            }
          }
        }
      }
    }
    if (!(best < kInfinity)) {
      return std::nullopt;
    }
    const auto [grid, x, y] = cellOf(bestCell);
    const Points g = points(grid);
    const int corners = cellCorners(g, x, y, at);
    const double u = bestHit[1], v = bestHit[2];
    double t = bestHit[0];
    Vec3d n;
    bool onPatch = false;
    if (corners == 4) {
      // A full cell is the bilinear patch B(a, b) through its corners, as the merge subdivides
      // and SurfaceCaster places on B (its triangles chord a twisted cell by up to a quarter of
      // the twist): Newton's method on B(a, b) = p + t dir from the triangle's hit.
      const Vec3d c00 = g.global(x, y), c10 = g.global(x + 1, y), c11 = g.global(x + 1, y + 1),
                  c01 = g.global(x, y + 1);
      double a = bestTri == 0 ? u + v : u, b = bestTri == 0 ? v : u + v;
      bool ok = true;
      for (int k = 0; k < 6 && ok; ++k) {
        const Vec3d bp =
            c00 * ((1 - a) * (1 - b)) + c10 * (a * (1 - b)) + c11 * (a * b) + c01 * ((1 - a) * b);
        const Vec3d ba = (c10 - c00) * (1 - b) + (c11 - c01) * b;
        const Vec3d bb = (c01 - c00) * (1 - a) + (c11 - c10) * a;
        const Vec3d f = bp - (p + dir * t);
        const Vec3d m = dir * -1.0;
        // Solve [ba bb m] [da db dt]^T = -f by Cramer's rule.
        const double det = dot(ba, cross(bb, m));
        if (!(std::abs(det) > 1e-300)) {
          ok = false;
          break;
        }
        const Vec3d r = f * -1.0;
        const double da = dot(r, cross(bb, m)) / det, db = dot(ba, cross(r, m)) / det,
                     dt = dot(ba, cross(bb, r)) / det;
        if (da == 0 && db == 0 && dt == 0) {
          break;  // converged: further steps change nothing
        }
        a += da;
        b += db;
        t += dt;
        ok = std::isfinite(a) && std::isfinite(b) && std::isfinite(t);
      }
      constexpr double kSlack = 1e-6;
      if (ok && a >= -kSlack && a <= 1 + kSlack && b >= -kSlack && b <= 1 + kSlack &&
          std::abs(t) <= reach) {
        n = vertexNormal(g, x, y, sign_) * ((1 - a) * (1 - b)) +
            vertexNormal(g, x + 1, y, sign_) * (a * (1 - b)) +
            vertexNormal(g, x + 1, y + 1, sign_) * (a * b) +
            vertexNormal(g, x, y + 1, sign_) * ((1 - a) * b);
        onPatch = true;
      } else {
        t = bestHit[0];
      }
    }
    if (!onPatch) {
      // The triangle's hit: its corners' normals, interpolated.
      n = vertexNormal(g, at[0].first, at[0].second, sign_) * (1 - u - v) +
          vertexNormal(g, at[bestTri + 1].first, at[bestTri + 1].second, sign_) * u +
          vertexNormal(g, at[bestTri + 2].first, at[bestTri + 2].second, sign_) * v;
    }
    const double length = n.norm();
    if (!(length > 0)) {
      return std::nullopt;
    }
    return Hit{t, n * (1 / length), grid, x, y};
  }

  /// M3C2's spread of this surface in a cylinder: the roughness (about their local plane) and the
  /// count of its vertices within `radius` of the axis through p along n, among the vertices of
  /// the hit cell's grid within `window` of it (a cylinder across a patch border sees one side).
  std::pair<double, int> spread(const Vec3d& p, const Vec3d& n, const Hit& hit, double radius,
                                int window) const {
    const Points g = points(hit.grid);
    const int s = g.size();
    std::vector<Vec3d>& inside = inside_;
    inside.clear();
    const double radius2 = radius * radius;
    for (int v = std::max(0, hit.y - window); v <= std::min(s - 1, hit.y + 1 + window); ++v) {
      for (int u = std::max(0, hit.x - window); u <= std::min(s - 1, hit.x + 1 + window); ++u) {
        if (g.defined(u, v)) {
          const Vec3d r = g.global(u, v) - p;
          const double along = dot(r, n);
          if (dot(r, r) - along * along <= radius2) {
            inside.push_back(r);
          }
        }
      }
    }
    return {roughness(inside, n), static_cast<int>(inside.size())};
  }

  /// The largest grid spacing and storageNoise of the leaves of the last around().
  double resolution() const { return resolution_; }
  /// The grid spacing of the index's grid `g` (Hit::grid).
  double resolutionOf(std::size_t g) const { return grids_[g]->resolution; }
  double noise() const { return noise_; }
  /// Memory of the index itself: its buckets and its grids' global positions (the grids are the
  /// cache's).
  std::size_t bytes() const { return pointBytes_ + entries_.capacity() * sizeof(entries_[0]); }
  /// Releases the pins and the index.
  void clear() {
    grids_.clear();
    keys_.clear();
    entries_.clear();
    entries_.shrink_to_fit();
    noise_ = 0;
    resolution_ = 0;
    pointBytes_ = 0;
  }

 private:
  static constexpr double kInfinity = std::numeric_limits<double>::infinity();
  static constexpr std::int64_t kBucketLimit = std::int64_t{1} << 20;

  std::array<std::int64_t, 3> bucketOf(const Vec3d& p) const {
    const auto axis = [&](double v) {
      return std::clamp(static_cast<std::int64_t>(std::floor(v / bucket_)), -kBucketLimit + 1,
                        kBucketLimit - 2);
    };
    return {axis(p.x - origin_.x), axis(p.y - origin_.y), axis(p.z - origin_.z)};
  }
  /// The dense number of bucket `b` of the leaves' box; kOutside beyond it (no cell there).
  static constexpr std::uint32_t kOutside = std::numeric_limits<std::uint32_t>::max();
  std::uint32_t key(const std::array<std::int64_t, 3>& b) const {
    std::array<std::int64_t, 3> r{};
    for (int a = 0; a < 3; ++a) {
      r[a] = b[a] - low_[a];
      if (r[a] < 0 || r[a] >= dims_[a]) {
        return kOutside;
      }
    }
    return static_cast<std::uint32_t>((r[0] * dims_[1] + r[1]) * dims_[2] + r[2]);
  }
  using Entries = std::vector<std::pair<std::uint32_t, std::uint32_t>>;
  std::pair<Entries::const_iterator, Entries::const_iterator> range(
      const std::array<std::int64_t, 3>& b) const {
    const std::uint32_t k = key(b);
    if (k == kOutside) {
      return {entries_.end(), entries_.end()};
    }
    const auto first = std::lower_bound(entries_.begin(), entries_.end(), std::pair{k, 0u});
    auto last = first;
    while (last != entries_.end() && last->first == k) {
      ++last;
    }
    return {first, last};
  }
  std::tuple<std::size_t, int, int> cellOf(std::uint32_t id) const {
    const int s = source_.model().gridSize() - 1;
    const std::size_t perGrid = static_cast<std::size_t>(s) * s;
    const std::size_t cell = id % perGrid;
    return {id / perGrid, static_cast<int>(cell % s), static_cast<int>(cell / s)};
  }

  /// The buckets the ray p + t dir (t >= 0) crosses, one at a time (3D DDA, Amanatides and
  /// Woo): `bucket`, entered at `t` (infinity once it leaves the index's range).
  struct Walker {
    Walker(const SurfaceIndex& index, const Vec3d& p, const Vec3d& dir)
        : bucket(index.bucketOf(p)) {
      const Vec3d q = (p - index.origin_) * (1 / index.bucket_);
      const std::array<double, 3> qa{q.x, q.y, q.z}, da{dir.x, dir.y, dir.z};
      const double size = index.bucket_;
      for (int a = 0; a < 3; ++a) {
        if (da[a] > 0) {
          step[a] = 1;
          next[a] = (static_cast<double>(bucket[a] + 1) - qa[a]) * size / da[a];
          delta[a] = size / da[a];
        } else if (da[a] < 0) {
          step[a] = -1;
          next[a] = (qa[a] - static_cast<double>(bucket[a])) * size / -da[a];
          delta[a] = size / -da[a];
        } else {
          next[a] = delta[a] = kInfinity;
        }
      }
    }
    /// Into the next bucket along the ray.
    void advance() {
      const int a =
          next[0] <= next[1] ? (next[0] <= next[2] ? 0 : 2) : (next[1] <= next[2] ? 1 : 2);
      t = next[a];
      bucket[a] += step[a];
      next[a] += delta[a];
      if (bucket[a] <= -kBucketLimit + 1 || bucket[a] >= kBucketLimit - 2) {
        t = kInfinity;
      }
    }

    std::array<std::int64_t, 3> bucket;
    double t = 0;
    std::array<int, 3> step{};
    std::array<double, 3> next{}, delta{};
  };

  PatchSource& source_;
  double sign_;
  std::size_t maxBytes_;
  std::vector<PatchKey> keys_;
  /// A leaf of the neighbourhood: its grid (pinned), global positions and spacing.
  struct Grid {
    std::shared_ptr<const PatchGrid> grid;
    std::vector<Vec3d> positions;
    double resolution = 0;
  };
  Points points(std::size_t g) const {
    return {grids_[g]->positions.data(), grids_[g]->grid->size()};
  }

  std::vector<std::shared_ptr<const Grid>> grids_;
  std::size_t pointBytes_ = 0;
  Entries entries_;
  Vec3d origin_;
  double bucket_ = 1;
  std::array<std::int64_t, 3> low_{};
  std::array<std::int64_t, 3> dims_{};
  double noise_ = 0;
  double resolution_ = 0;
  mutable std::vector<Vec3d> inside_;
};

}  // namespace vsm::core::diff_detail
