#include "core/tiles/lod_render.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core {

namespace {

constexpr double kWgs84A = 6378137.0;
constexpr double kWgs84F = 1.0 / 298.257223563;
constexpr double kWgs84E2 = kWgs84F * (2 - kWgs84F);
constexpr double kDegrees = 180.0 / std::numbers::pi;

struct Point2 {
  double x = 0, y = 0;
};

/// Where a vertex goes in the picture's plane.
Point2 project(const Vec3d& global, bool geographic) {
  if (geographic) {
    const Vec3d g = ecefToGeodetic(global);
    return {g.x, g.y};
  }
  return {global.x, global.y};
}

/// Twice the signed area of (a, b, p): positive when p is left of a -> b (y down: clockwise).
double edge(const Point2& a, const Point2& b, const Point2& p) {
  return (b.x - a.x) * (p.y - a.y) - (b.y - a.y) * (p.x - a.x);
}

/// Sets `value` at every pixel whose centre lies in the triangle (pixel coordinates), edges
/// included (with a relative tolerance), so triangles sharing an edge leave no gap.
void fillTriangle(Point2 a, Point2 b, Point2 c, int width, int height, std::int8_t value,
                  std::vector<std::int8_t>& out) {
  double area = edge(a, b, c);
  if (area == 0 || !std::isfinite(area)) {
    return;
  }
  if (area < 0) {
    std::swap(b, c);
    area = -area;
  }
  const double tolerance = -1e-9 * area;
  const int x0 = std::max(0, static_cast<int>(std::floor(std::min({a.x, b.x, c.x}) - 0.5)));
  const int x1 = std::min(width - 1, static_cast<int>(std::ceil(std::max({a.x, b.x, c.x}) - 0.5)));
  const int y0 = std::max(0, static_cast<int>(std::floor(std::min({a.y, b.y, c.y}) - 0.5)));
  const int y1 = std::min(height - 1, static_cast<int>(std::ceil(std::max({a.y, b.y, c.y}) - 0.5)));
  for (int y = y0; y <= y1; ++y) {
    for (int x = x0; x <= x1; ++x) {
      const Point2 p{x + 0.5, y + 0.5};
      if (edge(a, b, p) >= tolerance && edge(b, c, p) >= tolerance && edge(c, a, p) >= tolerance) {
        out[static_cast<std::size_t>(y) * width + x] = value;
      }
    }
  }
}

}  // namespace

Rgb8 depthColour(int depth) {
  return kDepthPalette[std::clamp<std::size_t>(static_cast<std::size_t>(std::max(depth, 0)), 0,
                                               kDepthPalette.size() - 1)];
}

Vec3d ecefToGeodetic(const Vec3d& ecef) {
  const double p = std::hypot(ecef.x, ecef.y);
  const double lon = std::atan2(ecef.y, ecef.x);
  // Fixed-point iteration on the latitude; converges to well below a millimetre in a few steps
  // for points near the surface.
  double lat = std::atan2(ecef.z, p * (1 - kWgs84E2));
  double h = 0;
  for (int i = 0; i < 6; ++i) {
    const double s = std::sin(lat);
    const double n = kWgs84A / std::sqrt(1 - kWgs84E2 * s * s);
    h = std::abs(std::cos(lat)) > 1e-12 ? p / std::cos(lat) - n
                                        : std::abs(ecef.z) - n * (1 - kWgs84E2);
    lat = std::atan2(ecef.z, p * (1 - kWgs84E2 * n / (n + h)));
  }
  return {lon * kDegrees, lat * kDegrees, h};
}

bool looksEcef(const PatchGrid& grid) {
  bool any = false;
  for (int y = 0; y < grid.size(); ++y) {
    for (int x = 0; x < grid.size(); ++x) {
      if (grid.defined(x, y)) {
        const double r = grid.global(x, y).norm();
        if (r < 6.2e6 || r > 6.5e6) {
          return false;
        }
        any = true;
      }
    }
  }
  return any;
}

LodImage renderLod(const Model& model,
                   const std::function<std::shared_ptr<const PatchGrid>(const PatchInfo&)>& load,
                   const LodRenderOptions& options) {
  if (model.empty()) {
    throw Error(ErrorCode::InvalidArgument, "render-lod: the model is empty");
  }
  if (options.size < 1 || options.size > 16384) {
    throw Error(ErrorCode::InvalidArgument, "render-lod: size must be 1..16384 pixels");
  }
  LodImage image;
  image.geographic = looksEcef(*load(model.at(PatchKey::root())));

  // Leaves shallow to deep: deeper ones are drawn last and win where they meet.
  std::vector<PatchKey> leaves = model.leaves();
  std::stable_sort(leaves.begin(), leaves.end(),
                   [](const PatchKey& a, const PatchKey& b) { return a.depth < b.depth; });

  // One pass over the leaves per stage, each reported per leaf.
  std::size_t done = 0;
  const auto reportLeaf = [&](std::string_view stage) {
    if (options.progress != nullptr) {
      options.progress->report(stage,
                               static_cast<double>(++done) / static_cast<double>(leaves.size()));
    }
  };

  double minX = Box3d::kInf, minY = Box3d::kInf, maxX = -Box3d::kInf, maxY = -Box3d::kInf;
  for (const PatchKey& key : leaves) {
    reportLeaf("bounds");
    const auto grid = load(model.at(key));
    for (int y = 0; y < grid->size(); ++y) {
      for (int x = 0; x < grid->size(); ++x) {
        if (grid->defined(x, y)) {
          const Point2 p = project(grid->global(x, y), image.geographic);
          minX = std::min(minX, p.x);
          maxX = std::max(maxX, p.x);
          minY = std::min(minY, p.y);
          maxY = std::max(maxY, p.y);
        }
      }
    }
  }
  if (!(minX <= maxX && minY <= maxY)) {
    throw Error(ErrorCode::InvalidArgument, "render-lod: the model has no defined vertex");
  }
  // Ground distance per unit of x relative to y: cos(latitude) for degrees, 1 otherwise.
  const double xScale =
      image.geographic ? std::max(std::cos((minY + maxY) * 0.5 / kDegrees), 1e-3) : 1.0;
  const double spanX = std::max(maxX - minX, 1e-9);
  const double spanY = std::max(maxY - minY, 1e-9);
  image.dy = std::max(spanX * xScale, spanY) / options.size;
  image.dx = image.dy / xScale;
  image.width = std::max(1, static_cast<int>(std::ceil(spanX / image.dx - 1e-9)));
  image.height = std::max(1, static_cast<int>(std::ceil(spanY / image.dy - 1e-9)));
  image.x0 = minX;
  image.y0 = maxY;
  image.depth.assign(static_cast<std::size_t>(image.width) * image.height, -1);

  done = 0;
  for (const PatchKey& key : leaves) {
    reportLeaf("drawing");
    const auto grid = load(model.at(key));
    const int n = grid->size();
    std::vector<Point2> pixel(grid->vertexCount());
    for (int y = 0; y < n; ++y) {
      for (int x = 0; x < n; ++x) {
        if (grid->defined(x, y)) {
          const Point2 p = project(grid->global(x, y), image.geographic);
          pixel[static_cast<std::size_t>(y) * n + x] = {(p.x - image.x0) / image.dx,
                                                        (image.y0 - p.y) / image.dy};
        }
      }
    }
    const auto value = static_cast<std::int8_t>(key.depth);
    for (int y = 0; y + 1 < n; ++y) {
      for (int x = 0; x + 1 < n; ++x) {
        if (!grid->defined(x, y) || !grid->defined(x + 1, y) || !grid->defined(x, y + 1) ||
            !grid->defined(x + 1, y + 1)) {
          continue;
        }
        const Point2& a = pixel[static_cast<std::size_t>(y) * n + x];
        const Point2& b = pixel[static_cast<std::size_t>(y) * n + x + 1];
        const Point2& c = pixel[static_cast<std::size_t>(y + 1) * n + x];
        const Point2& d = pixel[static_cast<std::size_t>(y + 1) * n + x + 1];
        fillTriangle(a, c, d, image.width, image.height, value, image.depth);
        fillTriangle(a, d, b, image.width, image.height, value, image.depth);
      }
    }
  }

  image.pixelsPerDepth.assign(static_cast<std::size_t>(model.maxDepth()) + 1, 0);
  image.rgba.assign(image.depth.size() * 4, 0);
  for (std::size_t i = 0; i < image.depth.size(); ++i) {
    if (image.depth[i] >= 0) {
      const Rgb8 colour = depthColour(image.depth[i]);
      image.rgba[i * 4] = colour.r;
      image.rgba[i * 4 + 1] = colour.g;
      image.rgba[i * 4 + 2] = colour.b;
      image.rgba[i * 4 + 3] = 255;
      ++image.pixelsPerDepth[static_cast<std::size_t>(image.depth[i])];
    }
  }
  return image;
}

}  // namespace vsm::core
