// Shaded relief from a patch's own vertices: the texture of a model that has no image.
#include "core/grid/shaded_relief.hpp"

#include "core/common/vectorised.hpp"
#include "core/grid/vec_ops.hpp"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <numbers>
#include <vector>

namespace vsm::core {
namespace {

using vec::cross;
using vec::dot;

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

  /// The sun's east, north and up components.
  Vec3d direction() const { return {east_, north_, up_}; }

 private:
  static std::uint8_t toGrey(double shade) {
    return static_cast<std::uint8_t>(255.0 * std::min(std::max(shade, 0.0), 1.0) + 0.5);
  }

  double east_, north_, up_;
  std::uint8_t flat_;
};

/// Six arrays of n doubles in one block. The loops below take each as a pointer of its own:
/// stores into one block at offsets the compiler does not know would have to be checked against
/// each other before a loop vectorises.
struct Arrays6 {
  explicit Arrays6(int n) : n(static_cast<std::size_t>(n)), values(6 * this->n) {}
  double* operator[](int a) { return values.data() + static_cast<std::size_t>(a) * n; }
  double& at(int a, int i) { return (*this)[a][i]; }
  std::size_t n;
  std::vector<double> values;
};

/// One quad row's normals (not normalised) and global centres, arrays nx, ny, nz, cx, cy, cz of
/// `quads`, and what the loops below compute of them.
struct QuadRow {
  explicit QuadRow(int n) : quads(n), grey(quads.n), plain(quads.n), defined(quads.n) {}
  void set(int i, const Vec3d& normal, const Vec3d& centre) {
    quads.at(0, i) = normal.x, quads.at(1, i) = normal.y, quads.at(2, i) = normal.z;
    quads.at(3, i) = centre.x, quads.at(4, i) = centre.y, quads.at(5, i) = centre.z;
  }
  Vec3d normal(int i) { return {quads.at(0, i), quads.at(1, i), quads.at(2, i)}; }
  Vec3d centre(int i) { return {quads.at(3, i), quads.at(4, i), quads.at(5, i)}; }

  Arrays6 quads;
  /// 255 max(0, min(shade, 1)) + 0.5: the grey before truncation, where plain is 1.
  std::vector<double> grey;
  /// 1 where grey holds the texel's grey, 0 where Sun::grey must decide it: a degenerate quad, a
  /// quad on the z axis, or one in the other kind of frame than the row's first.
  std::vector<double> plain;
  std::vector<std::uint8_t> defined;  // 3 or 4 defined corners
};

/// Per vertex column k of a quad row's top and bottom vertex rows (n + 1 columns): sum = top +
/// bottom, down = bottom - top.
VSM_VECTORISED void columnSums(const float* __restrict top, const float* __restrict bottom, int n,
                               double* __restrict sx, double* __restrict sy, double* __restrict sz,
                               double* __restrict dx, double* __restrict dy,
                               double* __restrict dz) {
  for (int k = 0; k <= n; ++k) {
    const double tx = top[3 * k], ty = top[3 * k + 1], tz = top[3 * k + 2];
    const double bx = bottom[3 * k], by = bottom[3 * k + 1], bz = bottom[3 * k + 2];
    sx[k] = tx + bx, sy[k] = ty + by, sz[k] = tz + bz;
    dx[k] = bx - tx, dy[k] = by - ty, dz[k] = bz - tz;
  }
}

/// The normals and centres of a row of n quads whose corners are all defined, from their
/// columnSums, in a grid whose local2global is a translation by `offset`: quad i has the edges
/// u = sum[i+1] - sum[i] and v = down[i] + down[i+1] and its centre at (sum[i] + sum[i+1]) / 4.
/// shadedRelief's loop below without its branches, with the same operations.
VSM_VECTORISED void fullQuadRow(const double* __restrict sx, const double* __restrict sy,
                                const double* __restrict sz, const double* __restrict dx,
                                const double* __restrict dy, const double* __restrict dz, int n,
                                Vec3d offset, double* __restrict nx, double* __restrict ny,
                                double* __restrict nz, double* __restrict cx, double* __restrict cy,
                                double* __restrict cz) {
  for (int i = 0; i < n; ++i) {
    const double ux = sx[i + 1] - sx[i], uy = sy[i + 1] - sy[i], uz = sz[i + 1] - sz[i];
    const double vx = dx[i] + dx[i + 1], vy = dy[i] + dy[i + 1], vz = dz[i] + dz[i + 1];
    nx[i] = uy * vz - uz * vy;
    ny[i] = uz * vx - ux * vz;
    nz[i] = ux * vy - uy * vx;
    cx[i] = (sx[i] + sx[i + 1]) * 0.25 + offset.x;
    cy[i] = (sy[i] + sy[i + 1]) * 0.25 + offset.y;
    cz[i] = (sz[i] + sz[i + 1]) * 0.25 + offset.z;
  }
}

/// Sun::grey for a whole row (QuadRow::quads' block), in its body-centred or its local Cartesian
/// (up = +z) case, without branches so that it vectorises (four texels an instruction with AVX2):
/// the same operations in the same order, so the same bytes.
template <bool kBodyCentred>
VSM_VECTORISED void shadeRow(const Vec3d& sun, int n, const double* __restrict quads,
                             double* __restrict grey, double* __restrict plain) {
  constexpr double kRadius2 = kBodyCentredRadius * kBodyCentredRadius;
  const std::size_t m = static_cast<std::size_t>(n);
  for (std::size_t i = 0; i < m; ++i) {
    const double nx = quads[i], ny = quads[m + i], nz = quads[2 * m + i];
    const double cx = quads[3 * m + i], cy = quads[4 * m + i], cz = quads[5 * m + i];
    const double length2 = nx * nx + ny * ny + nz * nz;
    double shade;  // lit, n turned to point up
    bool plainCase;
    if constexpr (kBodyCentred) {
      const double rho2 = cx * cx + cy * cy;
      const double r2 = rho2 + cz * cz;
      const double horizontal = nx * cx + ny * cy;
      const double up = horizontal + nz * cz;
      const double east = ny * cx - nx * cy;
      const double north = rho2 * nz - cz * horizontal;
      const double r = std::sqrt(r2), rho = std::sqrt(rho2);
      const double lit =
          (sun.x * east * r + sun.y * north + sun.z * up * rho) / (r * rho * std::sqrt(length2));
      shade = up < 0 ? -lit : lit;
      plainCase = (length2 > 0) & (r2 > kRadius2) & (rho2 > 1e-24 * r2);
    } else {
      const double r2 = (cx * cx + cy * cy) + cz * cz;
      const double lit = (sun.x * nx + sun.y * ny + sun.z * nz) / std::sqrt(length2);
      shade = nz < 0 ? -lit : lit;
      plainCase = (length2 > 0) & !(r2 > kRadius2);
    }
    grey[i] = 255.0 * std::min(std::max(shade, 0.0), 1.0) + 0.5;
    plain[i] = plainCase ? 1.0 : 0.0;
  }
}

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
  // True when the whole row is defined.
  const auto testRow = [&](int y, std::vector<std::uint8_t>& out) {
    const float* p = grid.positions().data() + stride * static_cast<std::size_t>(y);
    std::uint8_t all = 1;
    for (std::size_t x = 0; x < out.size(); ++x, p += 3) {
      out[x] = p[0] == p[0] && p[1] == p[1] && p[2] == p[2];
      all &= out[x];
    }
    return all != 0;
  };
  QuadRow row(size);
  // Row j's texels from its quads, in the frame of its first shaded quad (quads in the other kind
  // of frame fall to Sun::grey).
  const auto shade = [&](int j, int first) {
    const Vec3d c = row.centre(first);
    (dot(c, c) > kBodyCentredRadius * kBodyCentredRadius
         ? shadeRow<true>
         : shadeRow<false>)(sun.direction(), size, row.quads.values.data(), row.grey.data(),
                            row.plain.data());
    std::uint8_t* texel = tile.at(0, j);
    for (int i = 0; i < size; ++i, texel += TextureTile::kChannels) {
      if (row.defined[i] == 0) {
        continue;
      }
      const std::uint32_t grey = row.plain[i] != 0 ? static_cast<std::uint8_t>(row.grey[i])
                                                   : sun.grey(row.normal(i), row.centre(i));
      // Grey, grey, grey, opaque: one store.
      const std::uint32_t rgba = grey * 0x010101u | 0xff000000u;
      std::memcpy(texel, &rgba, sizeof rgba);
    }
  };
  Arrays6 columns(size + 1);  // per vertex column: top + bottom, then bottom - top
  bool bottomFull = testRow(0, bottomDefined);
  for (int j = 0; j < size; ++j) {
    topDefined.swap(bottomDefined);
    const bool topFull = bottomFull;
    bottomFull = testRow(j + 1, bottomDefined);
    const float* top = grid.positions().data() + stride * static_cast<std::size_t>(j);
    const float* bottom = top + stride;
    if (topFull && bottomFull && translation) {
      columnSums(top, bottom, size, columns[0], columns[1], columns[2], columns[3], columns[4],
                 columns[5]);
      Arrays6& q = row.quads;
      fullQuadRow(columns[0], columns[1], columns[2], columns[3], columns[4], columns[5], size,
                  offset, q[0], q[1], q[2], q[3], q[4], q[5]);
      std::fill(row.defined.begin(), row.defined.end(), 1);
      shade(j, 0);
      continue;
    }
    // Per vertex column k of the quad row: sum[k] = top + bottom, down[k] = bottom - top. A quad
    // with four corners has u = sum[i+1] - sum[i] and v = down[i] + down[i+1], the sums of its
    // two opposite edges, and its centre at (sum[i] + sum[i+1]) / 4; so each column is read once.
    Vec3d sum = vec(top) + vec(bottom), down = vec(bottom) - vec(top);
    int first = -1;  // the row's first shaded quad
    for (int i = 0; i < size; ++i) {
      const float* q[4] = {top + 3 * i, top + 3 * i + 3, bottom + 3 * i, bottom + 3 * i + 3};
      const Vec3d nextSum = vec(q[1]) + vec(q[3]), nextDown = vec(q[3]) - vec(q[1]);
      const Vec3d quadSum = sum + nextSum, quadDown = down + nextDown;
      const Vec3d across = nextSum - sum;
      sum = nextSum;
      down = nextDown;
      const bool d[4] = {topDefined[i] != 0, topDefined[i + 1] != 0, bottomDefined[i] != 0,
                         bottomDefined[i + 1] != 0};
      const int count = d[0] + d[1] + d[2] + d[3];
      row.defined[i] = count >= 3;
      if (count < 3) {
        row.set(i, {}, {});  // transparent; zeros keep the row's loops free of NaN
        continue;
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
      row.set(i, cross(u, v), translation ? centre + offset : l2g.apply(centre));
      if (first < 0) {
        first = i;
      }
    }
    if (first >= 0) {
      shade(j, first);
    }
  }
  return tile;
}

}  // namespace vsm::core
