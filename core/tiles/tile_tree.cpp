#include "core/tiles/tile_tree.hpp"

#include <algorithm>
#include <cmath>

#include "core/pyramid/model.hpp"

namespace vsm::core {

namespace {

/// The smallest positive error a non-leaf tile gets (metres), for overviews without a measurable
/// resolution.
constexpr double kMinError = 1e-3;

TileNode build(const Model& model, const PatchInfo& info) {
  TileNode node;
  node.key = info.key;
  node.centre = tileCentre(info);
  Box3d box = info.globalBox;
  double childError = 0;
  for (const Quadrant q : kQuadrants) {
    if (info.hasChild(q)) {
      node.children.push_back(build(model, model.at(info.key.child(q))));
      const TileNode& child = node.children.back();
      // Children's boxes are padded already: take them as they are, so they stay inside ours.
      box.extend(child.box);
      childError = std::max(childError, child.geometricError);
    }
  }
  if (box.empty()) {
    box.extend(node.centre);
  }
  const double pad = tilePadding(box);
  box.min = box.min - Vec3d{pad, pad, pad};
  box.max = box.max + Vec3d{pad, pad, pad};
  node.box = box;
  if (!node.children.empty()) {
    const double resolution =
        std::isfinite(info.resolution) && info.resolution > 0 ? info.resolution : kMinError;
    node.geometricError = std::max({resolution, 2 * childError, kMinError});
  }
  return node;
}

}  // namespace

Vec3d tileCentre(const PatchInfo& info) {
  if (!info.globalBox.empty() && info.globalBox.min.finite() && info.globalBox.max.finite()) {
    return info.globalBox.center();
  }
  return info.local2global.translationPart();
}

double tilePadding(const Box3d& box) {
  if (box.empty()) {
    return 1e-3;
  }
  const Vec3d size = box.size();
  return 1e-3 + 1e-6 * 0.5 * std::max({size.x, size.y, size.z});
}

TileNode buildTileTree(const Model& model) {
  return build(model, model.at(PatchKey::root()));
}

double tilesetGeometricError(const TileNode& root) {
  if (root.geometricError > 0) {
    return 2 * root.geometricError;
  }
  return std::max((root.box.max - root.box.min).norm(), kMinError);
}

}  // namespace vsm::core
