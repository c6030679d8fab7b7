#pragma once

// Internal to core/merge: the plane geometry of one grid cell with which SurfaceCaster intersects a
// ray and a cell of B in the plane across the ray, and B's border tolerance. (The unit tests'
// reference, tests/unit/surface_sampler_reference.hpp, sees the same cells along one up with the
// same functions, so both find the very same point of a cell.)

#include <algorithm>
#include <array>
#include <cmath>
#include <optional>

#include "core/common/error.hpp"
#include "core/grid/geometry.hpp"
#include "core/grid/vec_ops.hpp"

namespace vsm::core {

/// A 2D point/extent in the plane perpendicular to a frame's up direction.
struct Vec2d {
  double u = 0, v = 0;
};

/// An orthonormal frame (e1, e2, up) around an origin: projects points onto the plane
/// perpendicular to `up`. SurfaceCaster takes a ray's direction as `up` and its origin as the
/// origin: the ray projects to (0, 0), and whether it meets a cell is decided in that plane.
struct UpFrame {
  Vec3d origin;
  Vec3d e1{1, 0, 0};
  Vec3d e2{0, 1, 0};
  Vec3d up{0, 0, 1};

  /// Throws Error(InvalidArgument) when `up` is zero or not finite (it is normalised here).
  UpFrame(const Vec3d& originIn, const Vec3d& upIn) : origin(originIn) {
    const double n = upIn.norm();
    if (!upIn.finite() || n == 0) {
      throw Error(ErrorCode::InvalidArgument, "up direction must be finite and non-zero");
    }
    setUp(upIn * (1.0 / n));
  }

  /// The frame whose e1 is `along` made perpendicular to `up` (where that leaves a direction;
  /// otherwise the frame above's).
  UpFrame(const Vec3d& originIn, const Vec3d& upIn, const Vec3d& along) : UpFrame(originIn, upIn) {
    const Vec3d t = along - up * vec::dot(along, up);
    const double n = t.norm();
    if (std::isfinite(n) && n > 1e-9 * along.norm()) {
      e1 = t * (1.0 / n);
      e2 = vec::cross(up, e1);
    }
  }

  /// The frame around a unit `unitUp` (finite, length 1 within rounding), taken as it is: no
  /// check, no normalising (SurfaceCaster makes one per ray).
  static UpFrame aroundUnit(const Vec3d& originIn, const Vec3d& unitUp) {
    UpFrame frame;
    frame.origin = originIn;
    frame.setUp(unitUp);
    return frame;
  }

  Vec2d project(const Vec3d& p) const {
    const Vec3d d = p - origin;
    return {vec::dot(d, e1), vec::dot(d, e2)};
  }

 private:
  UpFrame() = default;
  /// e1 and e2 across a unit `unit`, without a branch on its direction or a square root (Duff et
  /// al., "Building an Orthonormal Basis, Revisited", JCGT 2017), e2 = up x e1 as before.
  void setUp(const Vec3d& unit) {
    up = unit;
    const double sign = std::copysign(1.0, up.z);
    const double a = -1.0 / (sign + up.z);
    const double b = up.x * up.y * a;
    e1 = {1 + sign * up.x * up.x * a, sign * b, -sign * up.x};
    e2 = vec::cross(up, e1);
  }
};

}  // namespace vsm::core

namespace vsm::core::cell_geometry {

/// B's border: how far outside a cell of B (in B's grid units, i.e. sample spacings) a point
/// still takes B's surface, measured in the cell's own parameter space (a full cell's bilinear
/// (s, t) clamped onto [0, 1]^2, a triangle's barycentric coordinates clamped and re-normalised):
/// far above float32 rounding (about 1e-5 of a cell for 257 x 257 grids) and the projection
/// offsets of ECEF merges (about 5e-3 of a cell for the real merge of issue 18), far below half a
/// cell, so a lattice half a sample off B's border is decided by its geometry.
inline constexpr double kBorderTolerance = 1.0 / 32;

// Barycentric coordinates may come out a few ulps negative for a point on a shared edge; both
// neighbours then accept it (and agree on the result), so no point falls between triangles.
inline constexpr double kBarycentricSlack = 1e-9;

inline double cross2(const Vec2d& a, const Vec2d& b) {
  return a.u * b.v - a.v * b.u;
}

inline Vec2d sub2(const Vec2d& a, const Vec2d& b) {
  return {a.u - b.u, a.v - b.v};
}

/// Barycentric coordinates of q in the projected triangle (a, b, c); NaN when it is degenerate.
inline std::array<double, 3> barycentric(const Vec2d& a, const Vec2d& b, const Vec2d& c,
                                         const Vec2d& q) {
  const Vec2d ab = sub2(b, a), ac = sub2(c, a), aq = sub2(q, a);
  const double d = cross2(ab, ac);
  const double l1 = cross2(aq, ac) / d;
  const double l2 = cross2(ab, aq) / d;
  return {1 - l1 - l2, l1, l2};
}

inline bool inside(const std::array<double, 3>& l) {
  return l[0] >= -kBarycentricSlack && l[1] >= -kBarycentricSlack && l[2] >= -kBarycentricSlack;
}

/// A point with barycentric coordinates `l` in a triangle whose corners lie at grid coordinates
/// (x[k], y[k]), moved onto the triangle: its coordinates clamped at 0 and re-normalised
/// (`weights`), and how far that moved it, in grid units (`outside`, 0 when it was inside; the
/// triangle's projection is affine, so this is exact). Nothing for non-finite coordinates (a
/// degenerate triangle).
struct ClampedPoint {
  std::array<double, 3> weights{};
  double outside = 0;
};

inline std::optional<ClampedPoint> clampOntoTriangle(const std::array<double, 3>& l,
                                                     const std::array<double, 3>& x,
                                                     const std::array<double, 3>& y) {
  if (!std::isfinite(l[0]) || !std::isfinite(l[1]) || !std::isfinite(l[2])) {
    return std::nullopt;
  }
  std::array<double, 3> clamped{};
  for (int k = 0; k < 3; ++k) {
    clamped[k] = std::max(l[k], 0.0);
  }
  const double sum = clamped[0] + clamped[1] + clamped[2];
  ClampedPoint point;
  for (int k = 0; k < 3; ++k) {
    point.weights[k] = clamped[k] / sum;
  }
  if (!inside(l)) {
    double du = 0, dv = 0;
    for (int k = 0; k < 3; ++k) {
      du += (l[k] - point.weights[k]) * x[k];
      dv += (l[k] - point.weights[k]) * y[k];
    }
    point.outside = std::hypot(du, dv);
  }
  return point;
}

/// Where q lies in the projected bilinear cell p00, p10, p11, p01 (corners (0,0), (1,0), (1,1),
/// (0,1)): its barycentric coordinates in the cell's triangles (p00, p10, p11) and (p00, p11,
/// p01), and the parameter (s, t) with q = p00 + s e + t f + s t g, by Newton's method from the
/// nearer triangle's coordinates (exact for a parallelogram, a close start otherwise, also just
/// outside). `converged` is false for a cell Newton cannot invert (strongly distorted, or seen
/// edge-on): callers then fall back to the triangles. (cs, ct) is (s, t) clamped onto the cell,
/// `outside` the distance between the two in grid units (0 inside).
struct BilinearPoint {
  std::array<double, 3> first{};
  std::array<double, 3> second{};
  double s = 0;
  double t = 0;
  bool converged = false;
  double cs = 0;
  double ct = 0;
  double outside = 0;
};

inline BilinearPoint invertBilinear(const Vec2d& p00, const Vec2d& p10, const Vec2d& p11,
                                    const Vec2d& p01, const Vec2d& q) {
  BilinearPoint point;
  point.first = barycentric(p00, p10, p11, q);
  point.second = barycentric(p00, p11, p01, q);
  const auto& l1 = point.first;
  const auto& l2 = point.second;
  double s = 0, t = 0;
  if (std::min({l1[0], l1[1], l1[2]}) >= std::min({l2[0], l2[1], l2[2]})) {
    s = l1[1] + l1[2];
    t = l1[2];
  } else {
    s = l2[1];
    t = l2[1] + l2[2];
  }
  const Vec2d e = sub2(p10, p00), f = sub2(p01, p00);
  const Vec2d g{p00.u - p10.u - p01.u + p11.u, p00.v - p10.v - p01.v + p11.v};
  bool converged = g.u == 0 && g.v == 0;  // a parallelogram: the start is exact
  for (int iteration = 0; iteration < 12 && !converged; ++iteration) {
    const Vec2d residual{p00.u + s * e.u + t * f.u + s * t * g.u - q.u,
                         p00.v + s * e.v + t * f.v + s * t * g.v - q.v};
    const Vec2d ds{e.u + t * g.u, e.v + t * g.v};  // d/ds
    const Vec2d dt{f.u + s * g.u, f.v + s * g.v};  // d/dt
    const double det = cross2(ds, dt);
    if (det == 0 || !std::isfinite(det)) {
      break;
    }
    const double stepS = cross2(residual, dt) / det;
    const double stepT = cross2(ds, residual) / det;
    s -= stepS;
    t -= stepT;
    converged = std::fabs(stepS) + std::fabs(stepT) < 1e-13;
  }
  point.s = s;
  point.t = t;
  point.converged = converged;
  point.cs = std::clamp(s, 0.0, 1.0);
  point.ct = std::clamp(t, 0.0, 1.0);
  point.outside = s == point.cs && t == point.ct ? 0.0 : std::hypot(s - point.cs, t - point.ct);
  return point;
}

}  // namespace vsm::core::cell_geometry
