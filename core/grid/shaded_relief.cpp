// Shaded relief from a patch's own vertices: the texture of a model that has no image.
#include "core/grid/shaded_relief.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numbers>

namespace vsm::core {
namespace {

Vec3d cross(const Vec3d& a, const Vec3d& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

double dot(const Vec3d& a, const Vec3d& b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}

/// The linear part of `m` applied to direction `v`.
Vec3d direction(const Mat4d& m, const Vec3d& v) {
  return m.apply(v) - m.translationPart();
}

}  // namespace

TextureTile shadedRelief(const PatchGrid& grid) {
  TextureTile tile(textureTileSize(grid.size()));
  const Mat4d& l2g = grid.local2global();
  const bool translation = l2g.isTranslation();
  constexpr double kDeg = std::numbers::pi / 180.0;
  // The sun in (east, north, up) components.
  const double sunEast = std::cos(kReliefAltitudeDeg * kDeg) * std::sin(kReliefAzimuthDeg * kDeg);
  const double sunNorth = std::cos(kReliefAltitudeDeg * kDeg) * std::cos(kReliefAzimuthDeg * kDeg);
  const double sunUp = std::sin(kReliefAltitudeDeg * kDeg);
  const auto local = [&grid](int x, int y) {
    const Vec3f v = grid.local(x, y);
    return Vec3d{v.x, v.y, v.z};
  };
  const int size = tile.size();
  for (int j = 0; j < size; ++j) {
    for (int i = 0; i < size; ++i) {
      const bool d00 = grid.defined(i, j);
      const bool d10 = grid.defined(i + 1, j);
      const bool d01 = grid.defined(i, j + 1);
      const bool d11 = grid.defined(i + 1, j + 1);
      const int defined = d00 + d10 + d01 + d11;
      if (defined < 3) {
        continue;  // transparent
      }
      Vec3d u, v;  // two edge directions spanning the surface
      Vec3d centre;
      if (defined == 4) {
        const Vec3d p00 = local(i, j), p10 = local(i + 1, j);
        const Vec3d p01 = local(i, j + 1), p11 = local(i + 1, j + 1);
        u = (p10 - p00) + (p11 - p01);
        v = (p01 - p00) + (p11 - p10);
        centre = (p00 + p10 + p01 + p11) * 0.25;
      } else {
        // The triangle of the three defined corners, in grid order.
        Vec3d corners[3];
        int n = 0;
        for (int c = 0; c < 4; ++c) {
          const int x = i + (c & 1), y = j + (c >> 1);
          if (grid.defined(x, y)) {
            corners[n++] = local(x, y);
          }
        }
        u = corners[1] - corners[0];
        v = corners[2] - corners[0];
        centre = (corners[0] + corners[1] + corners[2]) * (1.0 / 3.0);
      }
      if (!translation) {
        u = direction(l2g, u);
        v = direction(l2g, v);
      }
      const Vec3d normal = cross(u, v);
      const Vec3d up = upAt(l2g.apply(centre));
      Vec3d east = cross({0, 0, 1}, up);
      const double eastNorm = east.norm();
      east = eastNorm > 1e-12 ? east * (1.0 / eastNorm) : Vec3d{1, 0, 0};
      const Vec3d north = cross(up, east);
      const double length = normal.norm();
      double shade = sunUp;  // a degenerate (collinear) quad counts as flat
      if (length > 0) {
        const double sign = dot(normal, up) < 0 ? -1.0 : 1.0;
        shade = sign *
                (sunEast * dot(normal, east) + sunNorth * dot(normal, north) +
                 sunUp * dot(normal, up)) /
                length;
      }
      const auto grey = static_cast<std::uint8_t>(std::lround(255.0 * std::clamp(shade, 0.0, 1.0)));
      std::uint8_t* texel = tile.at(i, j);
      texel[0] = texel[1] = texel[2] = grey;
      texel[3] = 255;
    }
  }
  return tile;
}

}  // namespace vsm::core
