#include "core/tiles/lod_render.hpp"

#include <algorithm>
#include <cmath>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core {

Rgb8 depthColour(int depth) {
  return kDepthPalette[std::clamp<std::size_t>(static_cast<std::size_t>(std::max(depth, 0)), 0,
                                               kDepthPalette.size() - 1)];
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

  TopDownGrid view;
  view.geographic = image.geographic;
  double minX = Box3d::kInf, minY = Box3d::kInf, maxX = -Box3d::kInf, maxY = -Box3d::kInf;
  for (const PatchKey& key : leaves) {
    reportLeaf("bounds");
    const auto grid = load(model.at(key));
    for (int y = 0; y < grid->size(); ++y) {
      for (int x = 0; x < grid->size(); ++x) {
        if (grid->defined(x, y)) {
          const Point2d p = view.plane(grid->global(x, y));
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
  view = TopDownGrid::fit(image.geographic, minX, maxX, minY, maxY, options.size);
  image.width = view.width;
  image.height = view.height;
  image.x0 = view.x0;
  image.y0 = view.y0;
  image.dx = view.dx;
  image.dy = view.dy;
  image.depth.assign(view.pixels(), -1);

  done = 0;
  for (const PatchKey& key : leaves) {
    reportLeaf("drawing");
    const auto grid = load(model.at(key));
    const int n = grid->size();
    std::vector<Point2d> pixel(grid->vertexCount());
    for (int y = 0; y < n; ++y) {
      for (int x = 0; x < n; ++x) {
        if (grid->defined(x, y)) {
          pixel[static_cast<std::size_t>(y) * n + x] = view.pixel(view.plane(grid->global(x, y)));
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
        const Point2d& a = pixel[static_cast<std::size_t>(y) * n + x];
        const Point2d& b = pixel[static_cast<std::size_t>(y) * n + x + 1];
        const Point2d& c = pixel[static_cast<std::size_t>(y + 1) * n + x];
        const Point2d& d = pixel[static_cast<std::size_t>(y + 1) * n + x + 1];
        const auto fill = [&](int col, int row, double, double, double) {
          image.depth[static_cast<std::size_t>(row) * image.width + col] = value;
        };
        forEachPixelInTriangle(a, c, d, image.width, image.height, fill);
        forEachPixelInTriangle(a, d, b, image.width, image.height, fill);
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
