#include "tests/unit/surface_sampler_reference.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include "core/grid/vec_ops.hpp"

namespace vsm::core::test {

namespace {

using namespace cell_geometry;

constexpr std::uint32_t kNoVertex = std::numeric_limits<std::uint32_t>::max();

}  // namespace

SurfaceSampler::SurfaceSampler(const std::vector<std::shared_ptr<const PatchGrid>>& grids,
                               const Vec3d& up)
    : frame_({}, up) {
  // The frame's origin is the centre of B, so projected coordinates stay small (ECEF!).
  Box3d box;
  for (const auto& grid : grids) {
    if (grid) {
      box.extend(grid->globalBox());
    }
  }
  frame_ = UpFrame(box.empty() ? Vec3d{} : box.center(), up);

  constexpr std::uint32_t kNone = kNoVertex;
  // Every vertex of every grid at most: reserved once.
  std::size_t vertexBound = 0;
  for (const auto& grid : grids) {
    if (grid) {
      vertexBound += static_cast<std::size_t>(grid->size()) * grid->size();
    }
  }
  vertices_.reserve(vertexBound);
  projected_.reserve(vertexBound);
  origins_.reserve(vertexBound);
  cells_.reserve(4 * vertexBound);
  // Per grid vertex: its projection (u NaN when undefined), and its vertices_ index once a cell
  // uses it.
  std::vector<Vec2d> projected;
  std::vector<std::uint32_t> index;
  for (std::size_t gridIndex = 0; gridIndex < grids.size(); ++gridIndex) {
    const auto& grid = grids[gridIndex];
    if (!grid) {
      continue;
    }
    const int s = grid->size();
    projected.resize(static_cast<std::size_t>(s) * s);
    index.assign(projected.size(), kNone);
    for (int y = 0; y < s; ++y) {
      for (int x = 0; x < s; ++x) {
        projected[static_cast<std::size_t>(y) * s + x] =
            grid->defined(x, y) ? frame_.project(grid->global(x, y))
                                : Vec2d{std::numeric_limits<double>::quiet_NaN(), 0};
      }
    }
    auto vertex = [&](std::size_t i) {
      if (index[i] == kNone) {
        const int x = static_cast<int>(i % s), y = static_cast<int>(i / s);
        index[i] = static_cast<std::uint32_t>(vertices_.size());
        vertices_.push_back(grid->global(x, y));
        projected_.push_back(projected[i]);
        origins_.push_back({static_cast<std::uint32_t>(gridIndex), static_cast<std::uint16_t>(x),
                            static_cast<std::uint16_t>(y)});
      }
      return index[i];
    };
    auto area2 = [&](std::size_t a, std::size_t b, std::size_t c) {
      return cross2(sub2(projected[b], projected[a]), sub2(projected[c], projected[a]));
    };
    for (int y = 0; y + 1 < s; ++y) {
      for (int x = 0; x + 1 < s; ++x) {
        const std::size_t i = static_cast<std::size_t>(y) * s + x;
        const std::size_t corners[4] = {i, i + 1, i + s + 1, i + s};  // (0,0) (1,0) (1,1) (0,1)
        std::size_t rest[4];
        int n = 0;
        for (const std::size_t c : corners) {
          if (!std::isnan(projected[c].u)) {
            rest[n++] = c;
          }
        }
        if (n == 4) {
          // A cell that projects to a segment (a vertical wall) has no height to give.
          if (area2(rest[0], rest[1], rest[2]) != 0 || area2(rest[0], rest[2], rest[3]) != 0) {
            cells_.insert(cells_.end(),
                          {vertex(rest[0]), vertex(rest[1]), vertex(rest[2]), vertex(rest[3])});
          }
        } else if (n == 3) {
          if (area2(rest[0], rest[1], rest[2]) != 0) {
            cells_.insert(cells_.end(), {vertex(rest[0]), vertex(rest[1]), vertex(rest[2]), kNone});
          }
        }
      }
    }
  }

  // Bucket size: the mean projected extent of a cell, so a query scans a handful of them.
  const auto extend = [](Extent& e, const Vec2d& p) {
    e.min = {std::min(e.min.u, p.u), std::min(e.min.v, p.v)};
    e.max = {std::max(e.max.u, p.u), std::max(e.max.v, p.v)};
  };
  const std::size_t count = cellCount();
  cellExtents_.assign(count, Extent{});
  double extentSum = 0;
  double maxEdge2 = 0;
  for (std::size_t t = 0; t < count; ++t) {
    const std::uint32_t* cell = &cells_[4 * t];
    const int corners = cell[3] == kNoVertex ? 3 : 4;
    Extent& r = cellExtents_[t];
    for (int c = 0; c < corners; ++c) {
      const Vec2d a = projected_[cell[c]];
      extend(r, a);
      for (int e = c + 1; e < corners; ++e) {
        const Vec2d b = projected_[cell[e]];
        maxEdge2 = std::max(maxEdge2, (a.u - b.u) * (a.u - b.u) + (a.v - b.v) * (a.v - b.v));
      }
    }
    extentSum += std::max(r.max.u - r.min.u, r.max.v - r.min.v);
    extend(bounds_, r.min);
    extend(bounds_, r.max);
  }
  if (count == 0) {
    bucketStart_.assign(1, 0);
    return;
  }
  const double spanU = bounds_.max.u - bounds_.min.u;
  const double spanV = bounds_.max.v - bounds_.min.v;
  bucketSize_ = std::max(extentSum / static_cast<double>(count), 1e-12);
  // Never more buckets than 4 per cell (a sparse B spread over a large area).
  const double maxBuckets = 4.0 * static_cast<double>(count) + 16;
  while ((std::floor(spanU / bucketSize_) + 1) * (std::floor(spanV / bucketSize_) + 1) >
         maxBuckets) {
    bucketSize_ *= 1.5;
  }
  bucketsU_ = static_cast<int>(std::floor(spanU / bucketSize_)) + 1;
  bucketsV_ = static_cast<int>(std::floor(spanV / bucketSize_)) + 1;
  margin_ = kBorderTolerance * std::sqrt(maxEdge2) + bucketSize_ * 1e-9;
  // A cell goes into every bucket its rectangle grown by margin_ meets, so that the one bucket
  // holding a query's projection lists every cell that may hold the query (see locate).
  auto bucketRange = [&](std::size_t t, int& u0, int& v0, int& u1, int& v1) {
    const Extent& r = cellExtents_[t];
    auto bucket = [&](double value, double origin, int buckets) {
      return std::clamp(static_cast<int>(std::floor((value - origin) / bucketSize_)), 0,
                        buckets - 1);
    };
    u0 = bucket(r.min.u - margin_, bounds_.min.u, bucketsU_);
    u1 = bucket(r.max.u + margin_, bounds_.min.u, bucketsU_);
    v0 = bucket(r.min.v - margin_, bounds_.min.v, bucketsV_);
    v1 = bucket(r.max.v + margin_, bounds_.min.v, bucketsV_);
  };
  const std::size_t buckets = static_cast<std::size_t>(bucketsU_) * bucketsV_;
  bucketStart_.assign(buckets + 1, 0);
  for (std::size_t t = 0; t < count; ++t) {
    int u0, v0, u1, v1;
    bucketRange(t, u0, v0, u1, v1);
    for (int v = v0; v <= v1; ++v) {
      for (int u = u0; u <= u1; ++u) {
        ++bucketStart_[static_cast<std::size_t>(v) * bucketsU_ + u + 1];
      }
    }
  }
  for (std::size_t b = 0; b < buckets; ++b) {
    bucketStart_[b + 1] += bucketStart_[b];
  }
  bucketItems_.resize(bucketStart_[buckets]);
  std::vector<std::uint32_t> fill(bucketStart_.begin(), bucketStart_.end() - 1);
  for (std::size_t t = 0; t < count; ++t) {
    int u0, v0, u1, v1;
    bucketRange(t, u0, v0, u1, v1);
    for (int v = v0; v <= v1; ++v) {
      for (int u = u0; u <= u1; ++u) {
        bucketItems_[fill[static_cast<std::size_t>(v) * bucketsU_ + u]++] =
            static_cast<std::uint32_t>(t);
      }
    }
  }
}

double SurfaceSampler::height(const Vec3d& p) const {
  return vec::dot(p - frame_.origin, frame_.up);
}

std::optional<SurfaceSampler::CellHit> SurfaceSampler::onTriangle(const std::uint32_t* t,
                                                                  const Vec2d& q) const {
  return onTriangle(t, barycentric(projected_[t[0]], projected_[t[1]], projected_[t[2]], q));
}

std::optional<SurfaceSampler::CellHit> SurfaceSampler::onTriangle(
    const std::uint32_t* t, const std::array<double, 3>& l) const {
  std::array<double, 3> x{}, y{};
  for (int c = 0; c < 3; ++c) {
    x[c] = origins_[t[c]].x;
    y[c] = origins_[t[c]].y;
  }
  const std::optional<ClampedPoint> point = clampOntoTriangle(l, x, y);
  if (!point || !(point->outside <= kBorderTolerance)) {
    return std::nullopt;
  }
  return CellHit{{point->weights[0], point->weights[1], point->weights[2], 0}, point->outside};
}

std::optional<SurfaceSampler::CellHit> SurfaceSampler::onQuad(const std::uint32_t* c,
                                                              const Vec2d& q) const {
  // c = (0,0), (1,0), (1,1), (0,1): (s, t) is the point's parameter in the cell, i.e. its grid
  // coordinates relative to the (0,0) corner. The triangles' barycentric coordinates give the
  // exact (s, t) of a parallelogram and a close start for Newton otherwise, also just outside.
  const Vec2d p00 = projected_[c[0]], p10 = projected_[c[1]], p11 = projected_[c[2]],
              p01 = projected_[c[3]];
  const cell_geometry::BilinearPoint point = invertBilinear(p00, p10, p11, p01, q);
  const auto& l1 = point.first;
  const auto& l2 = point.second;
  const bool converged = point.converged;
  const double cs = point.cs, ct = point.ct, outside = point.outside;
  if (!converged || !(outside <= kBorderTolerance)) {
    // A strongly distorted (non-convex) cell, or a point outside it: fall back to its triangles,
    // the nearer one.
    const std::uint32_t first[3] = {c[0], c[1], c[2]};
    const std::uint32_t second[3] = {c[0], c[2], c[3]};
    std::optional<CellHit> a = onTriangle(first, l1);
    std::optional<CellHit> b = onTriangle(second, l2);
    if (a && (!b || a->outside <= b->outside)) {
      return CellHit{{a->weights[0], a->weights[1], a->weights[2], 0}, a->outside};
    }
    if (b) {
      return CellHit{{b->weights[0], 0, b->weights[1], b->weights[2]}, b->outside};
    }
    return std::nullopt;
  }
  return CellHit{{(1 - cs) * (1 - ct), cs * (1 - ct), cs * ct, (1 - cs) * ct},
                 outside <= kBarycentricSlack ? 0.0 : outside};
}

std::optional<SurfacePoint> SurfaceSampler::locate(const Vec3d& p) const {
  if (!p.finite() || bucketsU_ == 0) {
    return std::nullopt;
  }
  const Vec2d q = frame_.project(p);
  // Cells within kBorderTolerance of q (in grid units) lie within margin_ of it projected.
  const double margin = margin_;
  if (q.u < bounds_.min.u - margin || q.u > bounds_.max.u + margin ||
      q.v < bounds_.min.v - margin || q.v > bounds_.max.v + margin) {
    return std::nullopt;
  }
  // The bucket of q lists every such cell (each cell is in the buckets its rectangle grown by
  // margin_ meets; floor((x - origin) / size) grows with x, so the index of q lies in the range).
  auto bucket = [&](double value, double origin, int count) {
    return std::clamp(static_cast<int>(std::floor((value - origin) / bucketSize_)), 0, count - 1);
  };
  const std::size_t b =
      static_cast<std::size_t>(bucket(q.v, bounds_.min.v, bucketsV_)) * bucketsU_ +
      bucket(q.u, bounds_.min.u, bucketsU_);

  // The best hit: inside a cell before within tolerance of one (the nearer cell first), then,
  // among cells holding q alike (an overhang, or a seam of B's grids), the layer nearest to p,
  // then the first cell in grid order: the smallest (outside, distance, cell), whatever the order
  // the bucket lists them in.
  std::optional<SurfacePoint> best;
  std::size_t bestCell = 0;
  double bestOutside = std::numeric_limits<double>::infinity();
  double bestDistance = std::numeric_limits<double>::infinity();
  const double ph = height(p);
  for (std::uint32_t i = bucketStart_[b]; i < bucketStart_[b + 1]; ++i) {
    const std::size_t cell = bucketItems_[i];
    const Extent& rect = cellExtents_[cell];
    if (q.u < rect.min.u - margin || q.u > rect.max.u + margin || q.v < rect.min.v - margin ||
        q.v > rect.max.v + margin) {
      continue;
    }
    const std::uint32_t* c = &cells_[4 * cell];
    const std::optional<CellHit> h = c[3] == kNoVertex ? onTriangle(c, q) : onQuad(c, q);
    if (!h || h->outside > bestOutside) {
      continue;
    }
    SurfacePoint hit{{0, 0, 0}, origins_[c[0]].grid, 0, 0};
    for (int k = 0; k < 4; ++k) {
      if (h->weights[k] != 0) {
        hit.position = hit.position + vertices_[c[k]] * h->weights[k];
        hit.x += origins_[c[k]].x * h->weights[k];
        hit.y += origins_[c[k]].y * h->weights[k];
      }
    }
    // The height there, at p's own projection: only p's height changes, also where the
    // parameter was clamped onto the cell (a point on or just outside its border).
    hit.position = p + frame_.up * (height(hit.position) - ph);
    const double distance = std::fabs(height(hit.position) - ph);
    if (h->outside < bestOutside || distance < bestDistance ||
        (distance == bestDistance && cell < bestCell)) {
      bestOutside = h->outside;
      bestDistance = distance;
      bestCell = cell;
      best = hit;
    }
  }
  return best;
}

std::optional<Vec3d> SurfaceSampler::sample(const Vec3d& p) const {
  if (std::optional<SurfacePoint> hit = locate(p)) {
    return hit->position;
  }
  return std::nullopt;
}

}  // namespace vsm::core::test
