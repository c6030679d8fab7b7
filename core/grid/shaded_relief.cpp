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

/// The sun in the east-north-up frame of each quad centre, for one patch.
class Sun {
 public:
  Sun() {
    constexpr double kDeg = std::numbers::pi / 180.0;
    east_ = std::cos(kReliefAltitudeDeg * kDeg) * std::sin(kReliefAzimuthDeg * kDeg);
    north_ = std::cos(kReliefAltitudeDeg * kDeg) * std::cos(kReliefAzimuthDeg * kDeg);
    up_ = std::sin(kReliefAltitudeDeg * kDeg);
    flat_ = toGrey(up_);
  }

  /// Grey for the (not normalised) normal `n` at global position `c`: upAt(c), with east = +z x
  /// up and north = up x east written out, the frame's square roots shared.
  std::uint8_t grey(const Vec3d& n, const Vec3d& c) const {
    const double length2 = dot(n, n);
    if (!(length2 > 0)) {
      return flat_;  // a degenerate (collinear) quad counts as flat
    }
    const double rho2 = c.x * c.x + c.y * c.y;
    const double r2 = rho2 + c.z * c.z;
    double nEast, nNorth, nUp;
    if (!(r2 > kBodyCentredRadius * kBodyCentredRadius)) {
      // up = +z, east = +x, north = +y.
      nEast = n.x;
      nNorth = n.y;
      nUp = n.z;
    } else {
      const double invR = 1.0 / std::sqrt(r2);
      nUp = (n.x * c.x + n.y * c.y + n.z * c.z) * invR;
      if (rho2 > 1e-24 * r2) {
        const double invRho = 1.0 / std::sqrt(rho2);
        nEast = (n.y * c.x - n.x * c.y) * invRho;
        nNorth = (rho2 * n.z - c.z * (n.x * c.x + n.y * c.y)) * invR * invRho;
      } else {
        // On the axis: east = +x, north = up x east.
        nEast = n.x;
        nNorth = (c.z * n.y - c.y * n.z) * invR;
      }
    }
    const double lit = east_ * nEast + north_ * nNorth + up_ * nUp;
    const double shade = (nUp < 0 ? -lit : lit) / std::sqrt(length2);  // n turned to point up
    return toGrey(shade);
  }

 private:
  static std::uint8_t toGrey(double shade) {
    return static_cast<std::uint8_t>(255.0 * std::clamp(shade, 0.0, 1.0) + 0.5);
  }

  double east_, north_, up_;
  std::uint8_t flat_;
};

}  // namespace

TextureTile shadedRelief(const PatchGrid& grid) {
  TextureTile tile(textureTileSize(grid.size()));
  const Mat4d& l2g = grid.local2global();
  const bool translation = l2g.isTranslation();
  const Vec3d offset = l2g.translationPart();
  const Sun sun;
  const int size = tile.size();
  const std::size_t stride = static_cast<std::size_t>(grid.size()) * 3;
  const auto defined = [](const float* p) { return p[0] == p[0] && p[1] == p[1] && p[2] == p[2]; };
  const auto vec = [](const float* p) { return Vec3d{p[0], p[1], p[2]}; };
  for (int j = 0; j < size; ++j) {
    const float* top = grid.positions().data() + stride * static_cast<std::size_t>(j);
    const float* bottom = top + stride;
    std::uint8_t* texel = tile.at(0, j);
    for (int i = 0; i < size; ++i, texel += TextureTile::kChannels) {
      const float* q[4] = {top + 3 * i, top + 3 * i + 3, bottom + 3 * i, bottom + 3 * i + 3};
      const int count = defined(q[0]) + defined(q[1]) + defined(q[2]) + defined(q[3]);
      if (count < 3) {
        continue;  // transparent
      }
      Vec3d u, v;  // two edge directions spanning the surface
      Vec3d centre;
      if (count == 4) {
        const Vec3d p00 = vec(q[0]), p10 = vec(q[1]), p01 = vec(q[2]), p11 = vec(q[3]);
        u = (p10 - p00) + (p11 - p01);
        v = (p01 - p00) + (p11 - p10);
        centre = (p00 + p10 + p01 + p11) * 0.25;
      } else {
        // The triangle of the three defined corners, in grid order.
        Vec3d corners[3];
        int n = 0;
        for (const float* p : q) {
          if (defined(p)) {
            corners[n++] = vec(p);
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
      const std::uint8_t grey = sun.grey(normal, translation ? centre + offset : l2g.apply(centre));
      texel[0] = texel[1] = texel[2] = grey;
      texel[3] = 255;
    }
  }
  return tile;
}

}  // namespace vsm::core
