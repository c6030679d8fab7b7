#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>

#include "core/grid/geometry.hpp"

namespace vsm::core {

/// WGS 84 geodetic coordinates of an ECEF point: longitude and latitude in degrees, height in
/// metres above the ellipsoid (x = lon, y = lat, z = h).
Vec3d ecefToGeodetic(const Vec3d& ecef);

/// A point in a picture's plane or in pixel units.
struct Point2d {
  double x = 0, y = 0;
};

/// An axis-aligned rectangle in a picture's plane; empty when min > max (the default).
struct Rect2d {
  Point2d min{Box3d::kInf, Box3d::kInf};
  Point2d max{-Box3d::kInf, -Box3d::kInf};

  bool empty() const { return min.x > max.x || min.y > max.y; }
  void extend(const Point2d& p) {
    min = {std::min(min.x, p.x), std::min(min.y, p.y)};
    max = {std::max(max.x, p.x), std::max(max.y, p.y)};
  }
  /// False when either is empty.
  bool intersects(const Rect2d& r) const {
    return !empty() && !r.empty() && min.x <= r.max.x && r.min.x <= max.x && min.y <= r.max.y &&
           r.min.y <= max.y;
  }
};

/// A north-up pixel grid over a model seen from above, as `vsm render-lod` and `vsm diff` draw
/// it: ECEF models in longitude/latitude (degrees, WGS 84), other models in their global x/y.
/// Pixel (col, row) covers x in [x0 + col * dx, x0 + (col + 1) * dx] and y in
/// [y0 - (row + 1) * dy, y0 - row * dy].
struct TopDownGrid {
  bool geographic = false;
  /// With `geographic`: the plane is Web Mercator (EPSG:3857 metres: x = a lon, y = a ln tan(pi/4 +
  /// lat/2), a the WGS 84 semi-major axis) instead of lon/lat degrees, as web maps tile it.
  bool mercator = false;
  double x0 = 0, y0 = 0, dx = 1, dy = 1;
  int width = 0;
  int height = 0;

  /// The grid of about `size` pixels along the longer side covering [minX, maxX] x [minY, maxY]
  /// (in the picture's plane), pixels 1/cos(mid-latitude) wider in degrees than tall when
  /// geographic, so the picture keeps its proportions. Precondition: min <= max, size >= 1.
  static TopDownGrid fit(bool geographic, double minX, double maxX, double minY, double maxY,
                         int size);

  /// Where a global point lies in the picture's plane (lon/lat, Web Mercator or x/y).
  Point2d plane(const Vec3d& global) const;
  /// Where a geographic point (degrees) lies in the picture's plane: itself, or its Web Mercator
  /// metres when `mercator` (latitudes clamped to +-89.9999 degrees, where the projection ends).
  Point2d planeOfLonLat(double lon, double lat) const;
  /// Where a point of the plane lies in pixel units (x right, y down; pixel centres at + 0.5).
  Point2d pixel(const Point2d& p) const { return {(p.x - x0) / dx, (y0 - p.y) / dy}; }
  std::size_t pixels() const { return static_cast<std::size_t>(width) * height; }
};

namespace detail {
/// Twice the signed area of (a, b, p).
inline double edge(const Point2d& a, const Point2d& b, const Point2d& p) {
  return (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x);
}
}  // namespace detail

/// Calls visit(col, row, wa, wb, wc) for every pixel of a width x height picture whose centre lies
/// in the triangle (a, b, c) given in pixel coordinates, edges included (with a relative
/// tolerance, so triangles sharing an edge leave no gap: a centre up to about `tolerance` x the
/// triangle's size outside an edge counts), with the centre's barycentric weights.
template <typename Visit>
void forEachPixelInTriangle(Point2d a, Point2d b, Point2d c, int width, int height, Visit&& visit,
                            double tolerance = 1e-9) {
  double area = detail::edge(a, b, c);
  if (area == 0 || !std::isfinite(area)) {
    return;
  }
  bool swapped = false;
  if (area < 0) {
    std::swap(b, c);
    area = -area;
    swapped = true;
  }
  const double slack = -tolerance * area;
  const int x0 = std::max(0, static_cast<int>(std::floor(std::min({a.x, b.x, c.x}) - 0.5)));
  const int x1 = std::min(width - 1, static_cast<int>(std::ceil(std::max({a.x, b.x, c.x}) - 0.5)));
  const int y0 = std::max(0, static_cast<int>(std::floor(std::min({a.y, b.y, c.y}) - 0.5)));
  const int y1 = std::min(height - 1, static_cast<int>(std::ceil(std::max({a.y, b.y, c.y}) - 0.5)));
  for (int y = y0; y <= y1; ++y) {
    for (int x = x0; x <= x1; ++x) {
      const Point2d p{x + 0.5, y + 0.5};
      const double ea = detail::edge(b, c, p), eb = detail::edge(c, a, p),
                   ec = detail::edge(a, b, p);
      if (ea >= slack && eb >= slack && ec >= slack) {
        const double wa = ea / area, wb = eb / area, wc = ec / area;
        if (swapped) {
          visit(x, y, wa, wc, wb);
        } else {
          visit(x, y, wa, wb, wc);
        }
      }
    }
  }
}

}  // namespace vsm::core
