#include "core/tiles/top_down.hpp"

#include <numbers>

namespace vsm::core {

namespace {

constexpr double kWgs84A = 6378137.0;
constexpr double kWgs84F = 1.0 / 298.257223563;
constexpr double kWgs84E2 = kWgs84F * (2 - kWgs84F);
constexpr double kDegrees = 180.0 / std::numbers::pi;

}  // namespace

Vec3d ecefToGeodetic(const Vec3d& ecef) {
  const double p = std::hypot(ecef.x, ecef.y);
  const double lon = std::atan2(ecef.y, ecef.x);
  // Fixed-point iteration on the latitude; converges to well below a millimetre in a few steps
  // for points near the surface.
  double lat = std::atan2(ecef.z, p * (1 - kWgs84E2));
  double h = 0;
  for (int i = 0; i < 6; ++i) {
    const double s = std::sin(lat);
    const double n = kWgs84A / std::sqrt(1 - kWgs84E2 * s * s);
    h = std::abs(std::cos(lat)) > 1e-12 ? p / std::cos(lat) - n
                                        : std::abs(ecef.z) - n * (1 - kWgs84E2);
    lat = std::atan2(ecef.z, p * (1 - kWgs84E2 * n / (n + h)));
  }
  return {lon * kDegrees, lat * kDegrees, h};
}

TopDownGrid TopDownGrid::fit(bool geographic, double minX, double maxX, double minY, double maxY,
                             int size) {
  TopDownGrid view;
  view.geographic = geographic;
  // Ground distance per unit of x relative to y: cos(latitude) for degrees, 1 otherwise.
  const double xScale = geographic ? std::max(std::cos((minY + maxY) * 0.5 / kDegrees), 1e-3) : 1.0;
  const double spanX = std::max(maxX - minX, 1e-9);
  const double spanY = std::max(maxY - minY, 1e-9);
  view.dy = std::max(spanX * xScale, spanY) / size;
  view.dx = view.dy / xScale;
  view.width = std::max(1, static_cast<int>(std::ceil(spanX / view.dx - 1e-9)));
  view.height = std::max(1, static_cast<int>(std::ceil(spanY / view.dy - 1e-9)));
  view.x0 = minX;
  view.y0 = maxY;
  return view;
}

Point2d TopDownGrid::plane(const Vec3d& global) const {
  if (geographic) {
    const Vec3d g = ecefToGeodetic(global);
    return planeOfLonLat(g.x, g.y);
  }
  return {global.x, global.y};
}

Point2d TopDownGrid::planeOfLonLat(double lon, double lat) const {
  if (!mercator) {
    return {lon, lat};
  }
  const double phi = std::clamp(lat, -89.9999, 89.9999) / kDegrees;
  return {kWgs84A * lon / kDegrees, kWgs84A * std::log(std::tan(std::numbers::pi / 4 + phi / 2))};
}

}  // namespace vsm::core
