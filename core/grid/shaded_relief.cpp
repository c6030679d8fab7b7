// Shaded relief from a patch's own vertices: the texture of a model that has no image.
#include "core/grid/shaded_relief.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <numbers>
#include <vector>

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

  /// Grey for the (not normalised) normal `n` at global position `c`, in the frame of upAt(c):
  /// east = +z x up, north = up x east. Written out, the normal's east, north and up components
  /// share the denominator R rho |n| (R = |c|, rho = c's distance from the z axis), so a texel
  /// takes three square roots and one division.
  std::uint8_t grey(const Vec3d& n, const Vec3d& c) const {
    const double length2 = dot(n, n);
    if (!(length2 > 0)) {
      return flat_;  // a degenerate (collinear) quad counts as flat
    }
    const double rho2 = c.x * c.x + c.y * c.y;
    const double r2 = rho2 + c.z * c.z;
    double lit, up;  // lit and n . up, both times the same positive factor
    if (!(r2 > kBodyCentredRadius * kBodyCentredRadius)) {
      // up = +z, east = +x, north = +y.
      up = n.z;
      lit = (east_ * n.x + north_ * n.y + up_ * n.z) / std::sqrt(length2);
    } else if (rho2 > 1e-24 * r2) {
      const double horizontal = n.x * c.x + n.y * c.y;
      up = horizontal + n.z * c.z;                         // n . up  times R
      const double east = n.y * c.x - n.x * c.y;           // n . east  times rho
      const double north = rho2 * n.z - c.z * horizontal;  // n . north  times R rho
      const double r = std::sqrt(r2), rho = std::sqrt(rho2);
      lit = (east_ * east * r + north_ * north + up_ * up * rho) / (r * rho * std::sqrt(length2));
    } else {
      // On the axis: east = +x, north = up x east.
      up = n.z * c.z + n.y * c.y + n.x * c.x;
      const double r = std::sqrt(r2);
      lit = (east_ * n.x * r + north_ * (c.z * n.y - c.y * n.z) + up_ * up) /
            (r * std::sqrt(length2));
    }
    return toGrey(up < 0 ? -lit : lit);  // n turned to point up
  }

 private:
  static std::uint8_t toGrey(double shade) {
    return static_cast<std::uint8_t>(255.0 * std::min(std::max(shade, 0.0), 1.0) + 0.5);
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
  const auto vec = [](const float* p) { return Vec3d{p[0], p[1], p[2]}; };
  // Which vertices of the quads' top and bottom rows are defined, each row tested once.
  std::vector<std::uint8_t> topDefined(static_cast<std::size_t>(grid.size()));
  std::vector<std::uint8_t> bottomDefined(topDefined.size());
  const auto testRow = [&](int y, std::vector<std::uint8_t>& out) {
    const float* p = grid.positions().data() + stride * static_cast<std::size_t>(y);
    for (std::size_t x = 0; x < out.size(); ++x, p += 3) {
      out[x] = p[0] == p[0] && p[1] == p[1] && p[2] == p[2];
    }
  };
  testRow(0, bottomDefined);
  for (int j = 0; j < size; ++j) {
    topDefined.swap(bottomDefined);
    testRow(j + 1, bottomDefined);
    const float* top = grid.positions().data() + stride * static_cast<std::size_t>(j);
    const float* bottom = top + stride;
    std::uint8_t* texel = tile.at(0, j);
    // Per vertex column k of the quad row: sum[k] = top + bottom, down[k] = bottom - top. A quad
    // with four corners has u = sum[i+1] - sum[i] and v = down[i] + down[i+1], the sums of its
    // two opposite edges, and its centre at (sum[i] + sum[i+1]) / 4; so each column is read once.
    Vec3d sum = vec(top) + vec(bottom), down = vec(bottom) - vec(top);
    for (int i = 0; i < size; ++i, texel += TextureTile::kChannels) {
      const float* q[4] = {top + 3 * i, top + 3 * i + 3, bottom + 3 * i, bottom + 3 * i + 3};
      const Vec3d nextSum = vec(q[1]) + vec(q[3]), nextDown = vec(q[3]) - vec(q[1]);
      const Vec3d quadSum = sum + nextSum, quadDown = down + nextDown;
      const Vec3d across = nextSum - sum;
      sum = nextSum;
      down = nextDown;
      const bool d[4] = {topDefined[i] != 0, topDefined[i + 1] != 0, bottomDefined[i] != 0,
                         bottomDefined[i + 1] != 0};
      const int count = d[0] + d[1] + d[2] + d[3];
      if (count < 3) {
        continue;  // transparent
      }
      Vec3d u = across, v = quadDown;  // two edge directions spanning the surface
      Vec3d centre = quadSum * 0.25;
      if (count == 3) {
        // The triangle of the three defined corners, in grid order.
        Vec3d corners[3];
        int n = 0;
        for (int c = 0; c < 4; ++c) {
          if (d[c]) {
            corners[n++] = vec(q[c]);
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
      // Grey, grey, grey, opaque: one store.
      const std::uint32_t grey =
          sun.grey(normal, translation ? centre + offset : l2g.apply(centre));
      const std::uint32_t rgba = grey * 0x010101u | 0xff000000u;
      std::memcpy(texel, &rgba, sizeof rgba);
    }
  }
  return tile;
}

}  // namespace vsm::core
