#include "core/merge/surface_sampler.hpp"

#include <algorithm>
#include <array>
#include <cmath>
#include <limits>

#include "core/common/error.hpp"
#include "core/merge/cell_geometry.hpp"

namespace vsm::core {

namespace {

using namespace cell_geometry;

double dot(const Vec3d& a, const Vec3d& b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}

Vec3d cross(const Vec3d& a, const Vec3d& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

constexpr std::uint32_t kNoVertex = std::numeric_limits<std::uint32_t>::max();

}  // namespace

bool Rect2d::intersects(const Rect2d& r) const {
  if (empty() || r.empty()) {
    return false;
  }
  return min.u <= r.max.u && r.min.u <= max.u && min.v <= r.max.v && r.min.v <= max.v;
}

bool Rect2d::contains(const Rect2d& r, double tolerance) const {
  if (r.empty()) {
    return true;
  }
  return r.min.u >= min.u - tolerance && r.min.v >= min.v - tolerance &&
         r.max.u <= max.u + tolerance && r.max.v <= max.v + tolerance;
}

UpFrame::UpFrame(const Vec3d& originIn, const Vec3d& upIn) : origin(originIn) {
  const double n = upIn.norm();
  if (!upIn.finite() || n == 0) {
    throw Error(ErrorCode::InvalidArgument, "up direction must be finite and non-zero");
  }
  up = upIn * (1.0 / n);
  // e1: the coordinate axis least aligned with up, made perpendicular to it.
  const Vec3d axis = std::fabs(up.x) <= std::fabs(up.y) && std::fabs(up.x) <= std::fabs(up.z)
                         ? Vec3d{1, 0, 0}
                         : (std::fabs(up.y) <= std::fabs(up.z) ? Vec3d{0, 1, 0} : Vec3d{0, 0, 1});
  const Vec3d t = axis - up * dot(axis, up);
  e1 = t * (1.0 / t.norm());
  e2 = cross(up, e1);
}

Vec2d UpFrame::project(const Vec3d& p) const {
  const Vec3d d = p - origin;
  return {dot(d, e1), dot(d, e2)};
}

double UpFrame::height(const Vec3d& p) const {
  return dot(p - origin, up);
}

Rect2d UpFrame::footprint(const Box3d& box) const {
  Rect2d r;
  if (box.empty()) {
    return r;
  }
  for (int c = 0; c < 8; ++c) {
    r.extend(project({(c & 1) ? box.max.x : box.min.x, (c & 2) ? box.max.y : box.min.y,
                      (c & 4) ? box.max.z : box.min.z}));
  }
  return r;
}

SurfaceSampler::SurfaceSampler(const std::vector<std::shared_ptr<const PatchGrid>>& grids,
                               const Vec3d& up, const std::optional<Mat4d>& transform,
                               const std::optional<Clip>& clip)
    : frame_({}, up) {
  // The frame's origin is the centre of B, so projected coordinates stay small (ECEF!).
  Box3d box;
  for (const auto& grid : grids) {
    if (grid) {
      Box3d b = grid->globalBox();
      if (transform && !b.empty()) {
        Box3d t;
        for (int c = 0; c < 8; ++c) {
          t.extend(transform->apply({(c & 1) ? b.max.x : b.min.x, (c & 2) ? b.max.y : b.min.y,
                                     (c & 4) ? b.max.z : b.min.z}));
        }
        b = t;
      }
      box.extend(b);
    }
  }
  frame_ = UpFrame(box.empty() ? Vec3d{} : box.center(), up);

  // The clip in this frame: the same axes, so only the origin moves.
  Rect2d clipRect;
  Vec2d offset;
  if (clip) {
    const UpFrame& f = clip->frame;
    if (f.up.x != frame_.up.x || f.up.y != frame_.up.y || f.up.z != frame_.up.z) {
      throw Error(ErrorCode::InvalidArgument, "surface sampler: the clip's frame has another up");
    }
    offset = f.project(frame_.origin);
    clipRect = {{clip->rect.min.u - offset.u, clip->rect.min.v - offset.v},
                {clip->rect.max.u - offset.u, clip->rect.max.v - offset.v}};
  }

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
    auto global = [&](int x, int y) {
      const Vec3d g = grid->global(x, y);
      return transform ? transform->apply(g) : g;
    };
    projected.resize(static_cast<std::size_t>(s) * s);
    index.resize(projected.size());
    auto projectRange = [&](int x0, int y0, int x1, int y1) {  // vertices [x0, x1] x [y0, y1]
      for (int y = y0; y <= y1; ++y) {
        for (int x = x0; x <= x1; ++x) {
          const std::size_t i = static_cast<std::size_t>(y) * s + x;
          projected[i] = grid->defined(x, y) ? frame_.project(global(x, y))
                                             : Vec2d{std::numeric_limits<double>::quiet_NaN(), 0};
          index[i] = kNone;
        }
      }
    };
    projectRange(0, 0, s - 1, s - 1);
    auto vertex = [&](std::size_t i) {
      if (index[i] == kNone) {
        const int x = static_cast<int>(i % s), y = static_cast<int>(i / s);
        index[i] = static_cast<std::uint32_t>(vertices_.size());
        vertices_.push_back(global(x, y));
        projected_.push_back(projected[i]);
        origins_.push_back({static_cast<std::uint32_t>(gridIndex), static_cast<std::uint16_t>(x),
                            static_cast<std::uint16_t>(y)});
      }
      return index[i];
    };
    auto area2 = [&](std::size_t a, std::size_t b, std::size_t c) {
      return cross2(sub2(projected[b], projected[a]), sub2(projected[c], projected[a]));
    };
    // Whether a cell with these corners may hold a query projecting into the clip: its projected
    // rectangle, grown by kBorderTolerance grid units (generously: twice its width and height
    // for one unit), meets the clip.
    auto wanted = [&](std::initializer_list<std::size_t> corners) {
      if (!clip) {
        return true;
      }
      Rect2d r;
      for (const std::size_t c : corners) {
        r.extend(projected[c]);
      }
      const double margin = 2 * kBorderTolerance * (r.max.u - r.min.u + r.max.v - r.min.v);
      return r.min.u - margin <= clipRect.max.u && clipRect.min.u <= r.max.u + margin &&
             r.min.v - margin <= clipRect.max.v && clipRect.min.v <= r.max.v + margin;
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
          if ((area2(rest[0], rest[1], rest[2]) != 0 || area2(rest[0], rest[2], rest[3]) != 0) &&
              wanted({rest[0], rest[1], rest[2], rest[3]})) {
            cells_.insert(cells_.end(),
                          {vertex(rest[0]), vertex(rest[1]), vertex(rest[2]), vertex(rest[3])});
          }
        } else if (n == 3) {
          if (area2(rest[0], rest[1], rest[2]) != 0 && wanted({rest[0], rest[1], rest[2]})) {
            cells_.insert(cells_.end(), {vertex(rest[0]), vertex(rest[1]), vertex(rest[2]), kNone});
          }
        }
      }
    }
  }

  // Bucket size: the mean projected extent of a cell, so a query scans a handful of them.
  const std::size_t count = cellCount();
  cellRects_.assign(count, Rect2d{});
  std::vector<Rect2d>& rects = cellRects_;
  double extentSum = 0;
  double maxEdge2 = 0;
  for (std::size_t t = 0; t < count; ++t) {
    const std::uint32_t* cell = &cells_[4 * t];
    const int corners = cell[3] == kNoVertex ? 3 : 4;
    Rect2d& r = rects[t];
    for (int c = 0; c < corners; ++c) {
      const Vec2d a = projected_[cell[c]];
      r.extend(a);
      for (int e = c + 1; e < corners; ++e) {
        const Vec2d b = projected_[cell[e]];
        maxEdge2 = std::max(maxEdge2, (a.u - b.u) * (a.u - b.u) + (a.v - b.v) * (a.v - b.v));
      }
    }
    extentSum += std::max(r.max.u - r.min.u, r.max.v - r.min.v);
    bounds_.extend(r.min);
    bounds_.extend(r.max);
  }
  maxEdge_ = std::sqrt(maxEdge2);
  if (count == 0) {
    bucketStart_.assign(1, 0);
    return;
  }
  const double width = bounds_.max.u - bounds_.min.u;
  const double height = bounds_.max.v - bounds_.min.v;
  bucketSize_ = std::max(extentSum / static_cast<double>(count), 1e-12);
  // Never more buckets than 4 per cell (a sparse B spread over a large area).
  const double maxBuckets = 4.0 * static_cast<double>(count) + 16;
  while ((std::floor(width / bucketSize_) + 1) * (std::floor(height / bucketSize_) + 1) >
         maxBuckets) {
    bucketSize_ *= 1.5;
  }
  bucketsU_ = static_cast<int>(std::floor(width / bucketSize_)) + 1;
  bucketsV_ = static_cast<int>(std::floor(height / bucketSize_)) + 1;
  margin_ = kBorderTolerance * maxEdge_ + bucketSize_ * 1e-9;
  // A cell goes into every bucket its rectangle grown by margin_ meets, so that the one bucket
  // holding a query's projection lists every cell that may hold the query (see locate).
  auto bucketRange = [&](std::size_t t, int& u0, int& v0, int& u1, int& v1) {
    const Rect2d r{{rects[t].min.u - margin_, rects[t].min.v - margin_},
                   {rects[t].max.u + margin_, rects[t].max.v + margin_}};
    u0 = std::clamp(static_cast<int>(std::floor((r.min.u - bounds_.min.u) / bucketSize_)), 0,
                    bucketsU_ - 1);
    u1 = std::clamp(static_cast<int>(std::floor((r.max.u - bounds_.min.u) / bucketSize_)), 0,
                    bucketsU_ - 1);
    v0 = std::clamp(static_cast<int>(std::floor((r.min.v - bounds_.min.v) / bucketSize_)), 0,
                    bucketsV_ - 1);
    v1 = std::clamp(static_cast<int>(std::floor((r.max.v - bounds_.min.v) / bucketSize_)), 0,
                    bucketsV_ - 1);
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
  const double ph = frame_.height(p);
  for (std::uint32_t i = bucketStart_[b]; i < bucketStart_[b + 1]; ++i) {
    const std::size_t cell = bucketItems_[i];
    const Rect2d& rect = cellRects_[cell];
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
    hit.position = p + frame_.up * (frame_.height(hit.position) - ph);
    const double distance = std::fabs(frame_.height(hit.position) - ph);
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

bool SurfaceSampler::covers(const Rect2d& query) const {
  if (bucketsU_ == 0 || query.empty()) {
    return false;
  }
  const double margin = kBorderTolerance * maxEdge_;
  const Rect2d rect{{query.min.u - margin, query.min.v - margin},
                    {query.max.u + margin, query.max.v + margin}};
  if (!rect.intersects(bounds_)) {
    return false;
  }
  auto bucket = [&](double value, double origin, int count) {
    return std::clamp(static_cast<int>(std::floor((value - origin) / bucketSize_)), 0, count - 1);
  };
  const int u0 = bucket(rect.min.u, bounds_.min.u, bucketsU_);
  const int u1 = bucket(rect.max.u, bounds_.min.u, bucketsU_);
  const int v0 = bucket(rect.min.v, bounds_.min.v, bucketsV_);
  const int v1 = bucket(rect.max.v, bounds_.min.v, bucketsV_);
  for (int v = v0; v <= v1; ++v) {
    for (int u = u0; u <= u1; ++u) {
      const std::size_t b = static_cast<std::size_t>(v) * bucketsU_ + u;
      for (std::uint32_t i = bucketStart_[b]; i < bucketStart_[b + 1]; ++i) {
        if (cellRects_[bucketItems_[i]].intersects(rect)) {
          return true;
        }
      }
    }
  }
  return false;
}

std::size_t SurfaceSampler::bytes() const {
  return vertices_.capacity() * sizeof(Vec3d) + projected_.capacity() * sizeof(Vec2d) +
         origins_.capacity() * sizeof(VertexOrigin) +
         (cells_.capacity() + bucketStart_.capacity() + bucketItems_.capacity()) *
             sizeof(std::uint32_t) +
         cellRects_.capacity() * sizeof(Rect2d);
}

}  // namespace vsm::core
