#include "core/merge/subdivider.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <optional>
#include <string>

#include "core/common/error.hpp"
#include "core/grid/vec_ops.hpp"

namespace vsm::core {

bool Ball::meets(const Ball& other, double gap) const {
  if (empty() || other.empty()) {
    return false;
  }
  return (centre - other.centre).norm() <= radius + gap + other.radius;
}

namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

/// The Ball of the finite points each(f) visits (calling f(p) for each, in the same order on both
/// of its two calls: the mean, then the radius).
template <typename Each>
Ball ballOfEach(const Each& each) {
  Vec3d sum;
  std::size_t count = 0;
  each([&](const Vec3d& p) {
    if (p.finite()) {
      sum = sum + p;
      ++count;
    }
  });
  Ball ball;
  if (count == 0) {
    return ball;
  }
  ball.centre = sum * (1.0 / static_cast<double>(count));
  ball.radius = 0;
  each([&](const Vec3d& p) {
    if (p.finite()) {
      ball.radius = std::max(ball.radius, (p - ball.centre).norm());
    }
  });
  return ball;
}

}  // namespace

Ball ballOf(const std::vector<Vec3d>& points) {
  return ballOfEach([&](const auto& f) {
    for (const Vec3d& p : points) {
      f(p);
    }
  });
}

Ball ballOf(const PatchGrid& grid, const std::optional<Mat4d>& transform) {
  // Over the defined vertices in row order, without copying them.
  return ballOfEach([&](const auto& f) {
    for (int y = 0; y < grid.size(); ++y) {
      for (int x = 0; x < grid.size(); ++x) {
        if (grid.defined(x, y)) {
          f(transform ? transform->apply(grid.global(x, y)) : grid.global(x, y));
        }
      }
    }
  });
}

Subdivider::Subdivider(const PatchGrid& a, int k, const Ring& ring)
    : k_(k), size_(a.size()), ring_(ring) {
  const int cells = size_ - 1;
  if ((cells & (cells - 1)) != 0) {
    throw Error(ErrorCode::InvalidArgument, "subdivide: grid size is not 2^n+1");
  }
  if (k < 0 || k > 16) {
    throw Error(ErrorCode::InvalidArgument,
                "subdivide: " + std::to_string(k) + " new levels is outside 0..16");
  }
  global_.resize(static_cast<std::size_t>(size_) * size_);
  for (int y = 0; y < size_; ++y) {
    for (int x = 0; x < size_; ++x) {
      global_[static_cast<std::size_t>(y) * size_ + x] =
          a.defined(x, y) ? a.global(x, y) : Vec3d{kNaN, kNaN, kNaN};
    }
  }
  for (const std::vector<Vec3d>* side : {&ring_.west, &ring_.east, &ring_.south, &ring_.north}) {
    if (!side->empty() && side->size() != static_cast<std::size_t>(size_)) {
      throw Error(ErrorCode::InvalidArgument, "subdivide: a ring side is not one row long");
    }
  }
}

Vec3d Subdivider::interpolate(std::int64_t u, std::int64_t v) const {
  const std::int64_t last = size_ - 2;  // the last cell
  const std::int64_t cx = std::min(u >> k_, last);
  const std::int64_t cy = std::min(v >> k_, last);
  // Dyadic fractions: exact in double, so the weights (and a lattice position's result) are too.
  const double t = std::ldexp(static_cast<double>(u - (cx << k_)), -k_);
  const double r = std::ldexp(static_cast<double>(v - (cy << k_)), -k_);
  const std::size_t i00 = static_cast<std::size_t>(cy) * size_ + static_cast<std::size_t>(cx);
  const std::size_t corner[4] = {i00, i00 + 1, i00 + size_, i00 + size_ + 1};
  const double weight[4] = {(1 - t) * (1 - r), t * (1 - r), (1 - t) * r, t * r};
  Vec3d sum;
  double weights = 0;
  for (int c = 0; c < 4; ++c) {
    const Vec3d& p = global_[corner[c]];
    if (weight[c] == 0 || !p.finite()) {
      continue;
    }
    sum = sum + p * weight[c];
    weights += weight[c];
  }
  if (weights == 0) {
    return {kNaN, kNaN, kNaN};
  }
  return weights == 1 ? sum : sum * (1.0 / weights);
}

Vec3d Subdivider::extended(std::int64_t u, std::int64_t v) const {
  const std::int64_t unit = std::int64_t{1} << k_;
  const std::int64_t last = (size_ - 1) * unit;
  if (u >= 0 && u <= last && v >= 0 && v <= last) {
    return interpolate(u, v);
  }
  // One coordinate beyond the border (normals step along one axis at a time): the cell between
  // the ring and a's border line, interpolated along the other coordinate as interpolate() does.
  const bool alongU = u < 0 || u > last;
  const std::int64_t out = alongU ? u : v;
  const std::int64_t along = alongU ? v : u;
  if (along < 0 || along > last || out < -unit || out > last + unit) {
    return {kNaN, kNaN, kNaN};
  }
  const std::vector<Vec3d>& side =
      alongU ? (u < 0 ? ring_.west : ring_.east) : (v < 0 ? ring_.south : ring_.north);
  if (side.empty()) {
    return {kNaN, kNaN, kNaN};
  }
  const std::int64_t c = std::min(along >> k_, static_cast<std::int64_t>(size_) - 2);
  const double r = std::ldexp(static_cast<double>(along - (c << k_)), -k_);
  // Weight of the ring's side: how far beyond the border line, in cells.
  const double t = std::ldexp(static_cast<double>(out < 0 ? -out : out - last), -k_);
  const auto border = [&](std::int64_t index) -> const Vec3d& {
    const std::int64_t x = alongU ? (u < 0 ? 0 : size_ - 1) : index;
    const std::int64_t y = alongU ? index : (v < 0 ? 0 : size_ - 1);
    return global_[static_cast<std::size_t>(y) * size_ + static_cast<std::size_t>(x)];
  };
  const Vec3d* corner[4] = {&border(c), &border(c + 1), &side[static_cast<std::size_t>(c)],
                            &side[static_cast<std::size_t>(c + 1)]};
  const double weight[4] = {(1 - r) * (1 - t), r * (1 - t), (1 - r) * t, r * t};
  Vec3d sum;
  double weights = 0;
  for (int i = 0; i < 4; ++i) {
    if (weight[i] == 0 || !corner[i]->finite()) {
      continue;
    }
    sum = sum + *corner[i] * weight[i];
    weights += weight[i];
  }
  if (weights == 0) {
    return {kNaN, kNaN, kNaN};
  }
  return weights == 1 ? sum : sum * (1.0 / weights);
}

Vec3d Subdivider::normalFrom(const Vec3d& p, const Vec3d& west, const Vec3d& east,
                             const Vec3d& south, const Vec3d& north) {
  const Vec3d nan{kNaN, kNaN, kNaN};
  if (!p.finite()) {
    return nan;
  }
  // The difference across (u, v) along one axis: central where both sides are defined, else
  // one-sided.
  auto across = [&](const Vec3d& before, const Vec3d& after) -> std::optional<Vec3d> {
    if (before.finite() && after.finite()) {
      return after - before;
    }
    if (after.finite()) {
      return after - p;
    }
    if (before.finite()) {
      return p - before;
    }
    return std::nullopt;
  };
  const std::optional<Vec3d> du = across(west, east);
  const std::optional<Vec3d> dv = across(south, north);
  if (!du || !dv) {
    return nan;
  }
  const Vec3d n{du->y * dv->z - du->z * dv->y, du->z * dv->x - du->x * dv->z,
                du->x * dv->y - du->y * dv->x};
  const double length = n.norm();
  if (!(length > 0) || !std::isfinite(length)) {
    return nan;
  }
  return n * (1.0 / length);
}

Vec3d Subdivider::normal(std::int64_t u, std::int64_t v) const {
  const Vec3d p = interpolate(u, v);
  if (!p.finite()) {
    return p;
  }
  return normalFrom(p, extended(u - 1, v), extended(u + 1, v), extended(u, v - 1),
                    extended(u, v + 1));
}

std::vector<Vec3d> Subdivider::positions(int level, std::uint32_t i, std::uint32_t j) const {
  return lattice(level, i, j, [this](std::int64_t u, std::int64_t v) { return interpolate(u, v); });
}

std::vector<Vec3d> Subdivider::normals(int level, std::uint32_t i, std::uint32_t j,
                                       const std::vector<Vec3d>& positions) const {
  const auto n = static_cast<std::size_t>(size_);
  if (positions.size() != n * n) {
    throw Error(ErrorCode::InvalidArgument, "subdivide: positions of another patch size");
  }
  if (level != k_) {  // the lattice's neighbours are not level-k steps apart
    return lattice(level, i, j, [this](std::int64_t u, std::int64_t v) { return normal(u, v); });
  }
  const std::int64_t cells = size_ - 1;
  const std::int64_t u0 = static_cast<std::int64_t>(i) * cells;
  const std::int64_t v0 = static_cast<std::int64_t>(j) * cells;
  std::vector<Vec3d> out(n * n);
  for (int y = 0; y < size_; ++y) {
    for (int x = 0; x < size_; ++x) {
      const std::size_t at = static_cast<std::size_t>(y) * n + static_cast<std::size_t>(x);
      const std::int64_t u = u0 + x, v = v0 + y;
      const Vec3d& p = positions[at];
      out[at] = normalFrom(p, x > 0 ? positions[at - 1] : extended(u - 1, v),
                           x < size_ - 1 ? positions[at + 1] : extended(u + 1, v),
                           y > 0 ? positions[at - n] : extended(u, v - 1),
                           y < size_ - 1 ? positions[at + n] : extended(u, v + 1));
    }
  }
  return out;
}

template <typename At>
std::vector<Vec3d> Subdivider::lattice(int level, std::uint32_t i, std::uint32_t j, At at) const {
  if (level < 0 || level > k_ || (i >> level) != 0 || (j >> level) != 0) {
    throw Error(ErrorCode::InvalidArgument, "subdivide: patch outside the new levels");
  }
  const std::int64_t stride = std::int64_t{1} << (k_ - level);
  const std::int64_t cells = size_ - 1;
  std::vector<Vec3d> out(static_cast<std::size_t>(size_) * size_);
  for (int y = 0; y < size_; ++y) {
    const std::int64_t v = (static_cast<std::int64_t>(j) * cells + y) * stride;
    for (int x = 0; x < size_; ++x) {
      const std::int64_t u = (static_cast<std::int64_t>(i) * cells + x) * stride;
      out[static_cast<std::size_t>(y) * size_ + x] = at(u, v);
    }
  }
  return out;
}

Subdivider::Vertices Subdivider::vertexRange(int level, std::uint32_t i, std::uint32_t j) const {
  if (level < 0 || level > k_ || (i >> level) != 0 || (j >> level) != 0) {
    throw Error(ErrorCode::InvalidArgument, "subdivide: patch outside the new levels");
  }
  // The patch spans union vertices [i (s-1), (i+1) (s-1)] * 2^(k-level) at level k; a's cells
  // there are those from floor(u0 / 2^k) to ceil(u1 / 2^k).
  const std::int64_t cells = size_ - 1;
  const std::int64_t scale = std::int64_t{1} << (k_ - level);
  const std::int64_t unit = std::int64_t{1} << k_;
  auto range = [&](std::uint32_t index, std::int64_t& lo, std::int64_t& hi) {
    const std::int64_t u0 = static_cast<std::int64_t>(index) * cells * scale;
    const std::int64_t u1 = u0 + cells * scale;
    lo = u0 / unit;
    hi = std::min<std::int64_t>((u1 + unit - 1) / unit, cells);
  };
  Vertices r;
  range(i, r.x0, r.x1);
  range(j, r.y0, r.y1);
  return r;
}

Ball Subdivider::ballOver(std::int64_t x0, std::int64_t x1, std::int64_t y0,
                          std::int64_t y1) const {
  return ballOfEach([&](const auto& f) {
    for (std::int64_t y = y0; y <= y1; ++y) {
      for (std::int64_t x = x0; x <= x1; ++x) {
        f(global_[static_cast<std::size_t>(y) * size_ + static_cast<std::size_t>(x)]);
      }
    }
  });
}

Ball Subdivider::ball(int level, std::uint32_t i, std::uint32_t j) const {
  const auto [x0, x1, y0, y1] = vertexRange(level, i, j);
  return ballOver(x0, x1, y0, y1);
}

std::vector<Ball> Subdivider::balls(int level, std::uint32_t i, std::uint32_t j, int parts) const {
  if (parts < 1) {
    throw Error(ErrorCode::InvalidArgument, "subdivide: no parts");
  }
  const auto [x0, x1, y0, y1] = vertexRange(level, i, j);
  const std::int64_t nx = std::min<std::int64_t>(parts, std::max<std::int64_t>(x1 - x0, 1));
  const std::int64_t ny = std::min<std::int64_t>(parts, std::max<std::int64_t>(y1 - y0, 1));
  std::vector<Ball> result;
  for (std::int64_t gy = 0; gy < ny; ++gy) {
    for (std::int64_t gx = 0; gx < nx; ++gx) {
      const std::int64_t ya = y0 + (y1 - y0) * gy / ny, yb = y0 + (y1 - y0) * (gy + 1) / ny;
      const std::int64_t xa = x0 + (x1 - x0) * gx / nx, xb = x0 + (x1 - x0) * (gx + 1) / nx;
      if (const Ball b = ballOver(xa, xb, ya, yb); !b.empty()) {
        result.push_back(b);
      }
    }
  }
  return result;
}

std::optional<Subdivider::Cone> Subdivider::normalCone(int level, std::uint32_t i, std::uint32_t j,
                                                       double margin) const {
  // a's cells under the patch (those of vertexRange), and one more on every side.
  const Vertices r = vertexRange(level, i, j);
  const std::int64_t x0 = std::max<std::int64_t>(r.x0 - 1, 0);
  const std::int64_t x1 = std::min<std::int64_t>(r.x1 + 1, size_ - 1);
  const std::int64_t y0 = std::max<std::int64_t>(r.y0 - 1, 0);
  const std::int64_t y1 = std::min<std::int64_t>(r.y1 + 1, size_ - 1);
  auto at = [&](std::int64_t x, std::int64_t y) -> const Vec3d& {
    return global_[static_cast<std::size_t>(y) * size_ + static_cast<std::size_t>(x)];
  };
  // Calls f with each unit normal of those cells (four per cell: its edge vectors crossed);
  // false when a cell has an undefined corner or a degenerate normal. Run twice (the sum, then
  // the widest angle) rather than keeping the normals: at level 0 they are 4 x (s-1)^2.
  auto eachNormal = [&](auto&& f) {
    for (std::int64_t y = y0; y < y1; ++y) {
      for (std::int64_t x = x0; x < x1; ++x) {
        const Vec3d& p00 = at(x, y);
        const Vec3d& p10 = at(x + 1, y);
        const Vec3d& p01 = at(x, y + 1);
        const Vec3d& p11 = at(x + 1, y + 1);
        if (!p00.finite() || !p10.finite() || !p01.finite() || !p11.finite()) {
          return false;
        }
        const Vec3d u[2] = {p10 - p00, p11 - p01};
        const Vec3d v[2] = {p01 - p00, p11 - p10};
        for (const Vec3d& eu : u) {
          for (const Vec3d& ev : v) {
            const Vec3d n = vec::cross(eu, ev);
            const double length = n.norm();
            if (!(length > 0) || !std::isfinite(length)) {
              return false;
            }
            f(n * (1.0 / length));
          }
        }
      }
    }
    return true;
  };
  Vec3d sum;
  std::size_t count = 0;
  if (!eachNormal([&](const Vec3d& n) {
        sum = sum + n;
        ++count;
      })) {
    return std::nullopt;
  }
  const double length = sum.norm();
  if (count == 0 || !(length > 0)) {
    return std::nullopt;
  }
  const Vec3d axis = sum * (1.0 / length);
  double cosine = 1;
  eachNormal([&](const Vec3d& n) { cosine = std::min(cosine, vec::dot(n, axis)); });
  const double angle = std::acos(std::clamp(cosine, -1.0, 1.0)) + margin;
  if (!(angle < M_PI / 2)) {
    return std::nullopt;
  }
  return Cone{axis, std::sin(angle)};
}

Box3d Subdivider::box(int level, std::uint32_t i, std::uint32_t j) const {
  const auto [x0, x1, y0, y1] = vertexRange(level, i, j);
  Box3d box;
  for (std::int64_t y = y0; y <= y1; ++y) {
    for (std::int64_t x = x0; x <= x1; ++x) {
      if (const Vec3d& p =
              global_[static_cast<std::size_t>(y) * size_ + static_cast<std::size_t>(x)];
          p.finite()) {
        box.extend(p);
      }
    }
  }
  return box;
}

PatchGrid gridFromGlobal(int size, const std::vector<Vec3d>& global) {
  Box3d box;
  for (const Vec3d& p : global) {
    if (p.finite()) {
      box.extend(p);
    }
  }
  PatchGrid grid(size, originFor(box));
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      grid.setGlobal(x, y, global[static_cast<std::size_t>(y) * size + x]);
    }
  }
  return grid;
}

}  // namespace vsm::core
