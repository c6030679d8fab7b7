#include "core/grid/patch_grid.hpp"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstring>
#include <limits>
#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/vectorised.hpp"

namespace vsm::core {

namespace {

/// out[x] = |b_x - a_x| in float32 for the vertices a_x, b_x (x < n) of two vertex arrays: the
/// distances between horizontal (b = a + 1 vertex) or vertical neighbours of a grid stored as a
/// translation. NaN where either end is undefined. A loop that vectorises.
VSM_VECTORISED void distances(const float* __restrict a, const float* __restrict b, int n,
                              float* __restrict out) {
  for (int x = 0; x < n; ++x) {
    const float dx = b[3 * x] - a[3 * x];
    const float dy = b[3 * x + 1] - a[3 * x + 1];
    const float dz = b[3 * x + 2] - a[3 * x + 2];
    out[x] = std::sqrt(dx * dx + dy * dy + dz * dz);
  }
}

/// Widens lo and hi (x, y, z) by the defined vertices (all three coordinates numbers) of a row of
/// n.
VSM_VECTORISED void extendBox(const float* __restrict row, int n, float* __restrict lo,
                              float* __restrict hi) {
  widenBoxInLanes<float>(
      static_cast<std::size_t>(n),
      [row](std::size_t i) {
        return std::array<float, 3>{row[3 * i], row[3 * i + 1], row[3 * i + 2]};
      },
      [](const std::array<float, 3>& p) {
        const float x = p[0], y = p[1], z = p[2];
        return (x == x) & (y == y) & (z == z);
      },
      lo, hi);
}

}  // namespace

PatchGrid::PatchGrid(int size, const Mat4d& local2global)
    : size_(size), local2global_(local2global) {
  if (size < 2 || size > 65537) {
    throw Error(ErrorCode::InvalidArgument,
                "patch grid size " + std::to_string(size) + " is outside 2..65537");
  }
  if (!local2global.isAffineInvertible()) {
    throw Error(ErrorCode::InvalidArgument, "Local2Global is not an invertible affine matrix");
  }
  global2local_ = local2global.inverse();
  positions_.assign(vertexCount() * 3, std::numeric_limits<float>::quiet_NaN());
}

void PatchGrid::setGlobal(int x, int y, const Vec3d& g) {
  if (!g.finite()) {
    setUndefined(x, y);
    return;
  }
  const Vec3d l = global2local_.apply(g);
  setLocal(x, y, {static_cast<float>(l.x), static_cast<float>(l.y), static_cast<float>(l.z)});
}

void PatchGrid::setUndefined(int x, int y) {
  float* p = at(x, y);
  p[0] = p[1] = p[2] = std::numeric_limits<float>::quiet_NaN();
}

bool PatchGrid::anyDefined() const {
  for (int y = 0; y < size_; ++y) {
    for (int x = 0; x < size_; ++x) {
      if (defined(x, y)) {
        return true;
      }
    }
  }
  return false;
}

std::size_t PatchGrid::definedCount() const {
  std::size_t n = 0;
  for (int y = 0; y < size_; ++y) {
    for (int x = 0; x < size_; ++x) {
      n += defined(x, y) ? 1 : 0;
    }
  }
  return n;
}

Box3d PatchGrid::localBox() const {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  float lo[3] = {kInf, kInf, kInf};
  float hi[3] = {-kInf, -kInf, -kInf};
  for (int y = 0; y < size_; ++y) {
    extendBox(positions_.data() + static_cast<std::size_t>(y) * size_ * 3, size_, lo, hi);
  }
  if (lo[0] > hi[0]) {
    return {};
  }
  return {{lo[0], lo[1], lo[2]}, {hi[0], hi[1], hi[2]}};
}

Box3d PatchGrid::globalBox() const {
  if (local2global_.isTranslation()) {
    // global = local + t, rounded once: monotonic, so the box of the globals is the local box
    // moved (bit for bit what transforming every vertex gives).
    const Box3d local = localBox();
    if (local.empty()) {
      return local;
    }
    const Vec3d t = local2global_.translationPart();
    return {local.min + t, local.max + t};
  }
  Box3d box;
  for (int y = 0; y < size_; ++y) {
    for (int x = 0; x < size_; ++x) {
      if (defined(x, y)) {
        box.extend(global(x, y));
      }
    }
  }
  return box;
}

PatchGrid::Summary PatchGrid::summarize() const {
  constexpr float kInf = std::numeric_limits<float>::infinity();
  float lo[3] = {kInf, kInf, kInf};
  float hi[3] = {-kInf, -kInf, -kInf};
  GridRect rect{size_, size_, 0, 0};
  // Distances from local differences: the translation cancels, the linear part (identity for
  // grids vsm writes) applies to the difference. Neighbours' coordinates are close, so their
  // float32 difference is exact (Sterbenz) or nearly so. An undefined end makes the distance NaN,
  // which is how pairs with one are left out (no test per vertex).
  const bool identity = local2global_.isTranslation();
  const auto& m = local2global_.m;
  std::vector<float> across(static_cast<std::size_t>(size_));
  std::vector<float> down(across.size());
  const auto distancesOf = [&](const float* a, const float* b, int n, float* out) {
    if (identity) {
      distances(a, b, n, out);
      return;
    }
    for (int x = 0; x < n; ++x, a += 3, b += 3) {
      const float dx = b[0] - a[0];
      const float dy = b[1] - a[1];
      const float dz = b[2] - a[2];
      const double gx = m[0] * dx + m[1] * dy + m[2] * dz;
      const double gy = m[4] * dx + m[5] * dy + m[6] * dz;
      const double gz = m[8] * dx + m[9] * dy + m[10] * dz;
      out[x] = static_cast<float>(std::sqrt(gx * gx + gy * gy + gz * gz));
    }
  };
  double sum = 0;
  std::size_t count = 0;
  const std::size_t stride = static_cast<std::size_t>(size_) * 3;
  for (int y = 0; y < size_; ++y) {
    const float* row = positions_.data() + static_cast<std::size_t>(y) * stride;
    int first = 0, last = size_ - 1;
    while (first < size_ && !defined(first, y)) {
      ++first;
    }
    if (first == size_) {
      continue;  // no defined vertex: no distance from this row either
    }
    while (!defined(last, y)) {
      --last;
    }
    extendBox(row + 3 * first, last + 1 - first, lo, hi);
    rect.x0 = std::min(rect.x0, first);
    rect.x1 = std::max(rect.x1, last + 1);
    rect.y0 = std::min(rect.y0, y);
    rect.y1 = y + 1;
    // Horizontal and vertical distances in sums of their own: two independent chains of
    // additions, and no branch (an undefined end adds 0 and counts nothing).
    double acrossSum = 0, downSum = 0;
    int rowCount = 0;
    const auto add = [&rowCount](double& to, float d) {
      const bool defined = d == d;
      to += defined ? d : 0.0f;
      rowCount += defined;
    };
    const float* begin = row + 3 * first;
    distancesOf(begin, begin + 3, last - first, across.data());
    for (int x = 0; x < last - first; ++x) {
      add(acrossSum, across[x]);
    }
    if (y + 1 < size_) {
      distancesOf(begin, begin + stride, last + 1 - first, down.data());
      for (int x = 0; x <= last - first; ++x) {
        add(downSum, down[x]);
      }
    }
    sum += acrossSum + downSum;
    count += static_cast<std::size_t>(rowCount);
  }
  Summary summary;
  if (lo[0] <= hi[0]) {
    summary.localBox = {{lo[0], lo[1], lo[2]}, {hi[0], hi[1], hi[2]}};
    summary.definedRect = rect;
  }
  summary.resolution = count == 0 ? 0.0 : sum / static_cast<double>(count);
  return summary;
}

double PatchGrid::maxAbsLocal() const {
  double m = 0;
  for (int y = 0; y < size_; ++y) {
    for (int x = 0; x < size_; ++x) {
      if (defined(x, y)) {
        const Vec3f l = local(x, y);
        m = std::max({m, std::fabs(double{l.x}), std::fabs(double{l.y}), std::fabs(double{l.z})});
      }
    }
  }
  return m;
}

bool operator==(const PatchGrid& a, const PatchGrid& b) {
  // Bitwise, so that NaN == NaN: two grids are equal when they would be stored identically.
  return a.size_ == b.size_ && a.local2global_ == b.local2global_ &&
         std::memcmp(a.positions_.data(), b.positions_.data(),
                     a.positions_.size() * sizeof(float)) == 0;
}

Mat4d originFor(const Box3d& box) {
  return box.empty() ? Mat4d::identity() : Mat4d::translation(box.center());
}

}  // namespace vsm::core
