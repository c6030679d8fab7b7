#pragma once

#include <algorithm>

#include <array>
#include <cmath>
#include <limits>
#include <optional>
#include <utility>

namespace vsm::core {

struct Vec3f {
  float x = 0, y = 0, z = 0;
};

struct Vec3d {
  double x = 0, y = 0, z = 0;

  friend Vec3d operator+(Vec3d a, Vec3d b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
  friend Vec3d operator-(Vec3d a, Vec3d b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
  friend Vec3d operator*(Vec3d a, double s) { return {a.x * s, a.y * s, a.z * s}; }
  friend bool operator==(const Vec3d&, const Vec3d&) = default;
  double norm() const { return std::sqrt(x * x + y * y + z * z); }
  bool finite() const { return std::isfinite(x) && std::isfinite(y) && std::isfinite(z); }
};

/// Axis-aligned box; empty when min > max on any axis (the default).
struct Box3d {
  static constexpr double kInf = std::numeric_limits<double>::infinity();
  Vec3d min{kInf, kInf, kInf};
  Vec3d max{-kInf, -kInf, -kInf};

  bool empty() const { return min.x > max.x || min.y > max.y || min.z > max.z; }
  void extend(const Vec3d& p) {
    min = {std::min(min.x, p.x), std::min(min.y, p.y), std::min(min.z, p.z)};
    max = {std::max(max.x, p.x), std::max(max.y, p.y), std::max(max.z, p.z)};
  }
  void extend(const Box3d& b);
  Vec3d center() const { return (min + max) * 0.5; }
  Vec3d size() const { return max - min; }
  /// True when `b` lies inside this box, allowing `tolerance` on every side.
  bool contains(const Box3d& b, double tolerance = 0) const;
  bool intersects(const Box3d& b) const;
  friend bool operator==(const Box3d&, const Box3d&) = default;
};

/// The part of [t0, t1] where origin + t d lies in `box` (slab test); nullopt when there is none.
inline std::optional<std::pair<double, double>> clipToBox(const Vec3d& origin, const Vec3d& d,
                                                          double t0, double t1, const Box3d& box) {
  if (box.empty()) {
    return std::nullopt;
  }
  const std::array<double, 3> o{origin.x, origin.y, origin.z};
  const std::array<double, 3> dir{d.x, d.y, d.z};
  const std::array<double, 3> lo{box.min.x, box.min.y, box.min.z};
  const std::array<double, 3> hi{box.max.x, box.max.y, box.max.z};
  for (int a = 0; a < 3; ++a) {
    if (std::fabs(dir[a]) < 1e-300) {  // parallel to the slab (1 / d would overflow)
      if (o[a] < lo[a] || o[a] > hi[a]) {
        return std::nullopt;
      }
      continue;
    }
    double ta = (lo[a] - o[a]) / dir[a];
    double tb = (hi[a] - o[a]) / dir[a];
    if (ta > tb) {
      std::swap(ta, tb);
    }
    t0 = std::max(t0, ta);
    t1 = std::min(t1, tb);
    if (!(t0 <= t1)) {
      return std::nullopt;
    }
  }
  return std::pair{t0, t1};
}

/// A 4x4 affine matrix, row-major (m[row * 4 + col]); translation in the last column, as OPC's
/// Local2Global is written.
struct Mat4d {
  std::array<double, 16> m{1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1};

  static Mat4d identity() { return {}; }
  static Mat4d translation(const Vec3d& t);
  Vec3d apply(const Vec3d& p) const {
    return {m[0] * p.x + m[1] * p.y + m[2] * p.z + m[3],
            m[4] * p.x + m[5] * p.y + m[6] * p.z + m[7],
            m[8] * p.x + m[9] * p.y + m[10] * p.z + m[11]};
  }
  Vec3d translationPart() const { return {m[3], m[7], m[11]}; }
  /// True when the linear part is the identity (only a translation), as vsm writes it.
  bool isTranslation() const;
  /// True when the last row is (0, 0, 0, 1) and the linear part is invertible.
  bool isAffineInvertible() const;
  /// Inverse of an affine matrix; precondition: isAffineInvertible().
  Mat4d inverse() const;
  friend bool operator==(const Mat4d&, const Mat4d&) = default;
};

/// Points farther than this from the origin (metres) are in body-centred coordinates (upAt).
inline constexpr double kBodyCentredRadius = 1e5;

/// The up direction vsm uses at global point `p`: for body-centred coordinates (ECEF; `p` farther
/// than kBodyCentredRadius from the origin) the normalised position, i.e. the local vertical of a
/// sphere around the origin (any planet); otherwise +z (a local Cartesian frame).
Vec3d upAt(const Vec3d& p);

/// upAt() of the centre of `box` (+z for an empty box): the up direction of a whole model.
Vec3d defaultUp(const Box3d& box);

/// The axis-aligned box holding `box` transformed by `m` (its eight corners); empty stays empty.
Box3d transformBox(const Mat4d& m, const Box3d& box);

}  // namespace vsm::core
