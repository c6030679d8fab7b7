#include "core/merge/subdivider.hpp"

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>

#include "core/common/error.hpp"
#include "core/merge/surface_sampler.hpp"

namespace vsm::core {

namespace {
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
}

Subdivider::Subdivider(const PatchGrid& a, int k) : k_(k), size_(a.size()) {
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

std::vector<Vec3d> Subdivider::positions(int level, std::uint32_t i, std::uint32_t j,
                                         const SurfaceSampler* detail, std::size_t* fromDetail,
                                         std::vector<std::optional<SurfacePoint>>* onDetail) const {
  if (level < 0 || level > k_ || (i >> level) != 0 || (j >> level) != 0) {
    throw Error(ErrorCode::InvalidArgument, "subdivide: patch outside the new levels");
  }
  const std::int64_t stride = std::int64_t{1} << (k_ - level);
  const std::int64_t cells = size_ - 1;
  std::vector<Vec3d> out(static_cast<std::size_t>(size_) * size_);
  if (onDetail != nullptr) {
    onDetail->assign(out.size(), std::nullopt);
  }
  std::size_t taken = 0;
  for (int y = 0; y < size_; ++y) {
    const std::int64_t v = (static_cast<std::int64_t>(j) * cells + y) * stride;
    for (int x = 0; x < size_; ++x) {
      const std::int64_t u = (static_cast<std::int64_t>(i) * cells + x) * stride;
      const std::size_t index = static_cast<std::size_t>(y) * size_ + x;
      Vec3d p = interpolate(u, v);
      if (detail != nullptr && p.finite()) {
        if (std::optional<SurfacePoint> hit = detail->locate(p)) {
          p = hit->position;
          ++taken;
          if (onDetail != nullptr) {
            (*onDetail)[index] = std::move(hit);
          }
        }
      }
      out[index] = p;
    }
  }
  if (fromDetail != nullptr) {
    *fromDetail = taken;
  }
  return out;
}

Rect2d Subdivider::footprint(int level, std::uint32_t i, std::uint32_t j,
                             const UpFrame& frame) const {
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
  std::int64_t x0, x1, y0, y1;
  range(i, x0, x1);
  range(j, y0, y1);
  Rect2d rect;
  for (std::int64_t y = y0; y <= y1; ++y) {
    for (std::int64_t x = x0; x <= x1; ++x) {
      const Vec3d& p = global_[static_cast<std::size_t>(y) * size_ + static_cast<std::size_t>(x)];
      if (p.finite()) {
        rect.extend(frame.project(p));
      }
    }
  }
  return rect;
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
