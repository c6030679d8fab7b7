#pragma once

// The products of Vec3d, and a grid vertex's normal, once for the files that use them: `using
// vec::dot;` in a file's own namespace keeps its calls as they are.

#include <limits>

#include "core/grid/geometry.hpp"

namespace vsm::core::vec {

inline double dot(const Vec3d& a, const Vec3d& b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}

inline Vec3d cross(const Vec3d& a, const Vec3d& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

/// `v` scaled to length 1 (not finite for a zero vector).
inline Vec3d unit(const Vec3d& v) {
  return v * (1.0 / v.norm());
}

/// The unit normal of a grid at vertex (x, y) at the scale of its spacing: the cross product of
/// the central differences along x and y (one-sided at a border or beside an undefined vertex),
/// on the side of the grid's winding times `sign`; NaN when either direction has no neighbour.
/// `Grid` has size(), defined(x, y) and global(x, y) (PatchGrid, or a view of one).
template <class Grid>
Vec3d vertexNormal(const Grid& grid, int x, int y, double sign = 1) {
  constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
  const int s = grid.size();
  const auto along = [&](int dx, int dy) -> Vec3d {
    const int x0 = x - dx, y0 = y - dy, x1 = x + dx, y1 = y + dy;
    const bool lo = x0 >= 0 && y0 >= 0 && grid.defined(x0, y0);
    const bool hi = x1 < s && y1 < s && grid.defined(x1, y1);
    if (lo && hi) {
      return grid.global(x1, y1) - grid.global(x0, y0);
    }
    if (hi) {
      return grid.global(x1, y1) - grid.global(x, y);
    }
    if (lo) {
      return grid.global(x, y) - grid.global(x0, y0);
    }
    return {kNaN, kNaN, kNaN};
  };
  const Vec3d n = cross(along(1, 0), along(0, 1));
  const double length = n.norm();
  if (!(length > 0)) {
    return {kNaN, kNaN, kNaN};
  }
  return n * (sign / length);
}

}  // namespace vsm::core::vec
