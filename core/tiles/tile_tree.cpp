#include "core/tiles/tile_tree.hpp"

#include <algorithm>
#include <cmath>
#include <map>
#include <set>
#include <string>

#include "core/common/error.hpp"

#include "core/pyramid/model.hpp"

namespace vsm::core {

namespace {

/// The smallest positive error a non-leaf tile gets (metres), for overviews without a measurable
/// resolution.
constexpr double kMinError = 1e-3;

/// A subtree's padded box and geometric error, from the patch's own box and its children's.
struct Extent {
  Box3d box;
  double geometricError = 0;
};

/// `box`: the patch's global box extended by its children's padded boxes (taken as they are, so
/// they stay inside ours); `childError` the largest of their errors.
Extent finish(const PatchInfo& info, const Vec3d& centre, Box3d box, double childError) {
  if (box.empty()) {
    box.extend(centre);
  }
  const double pad = tilePadding(box);
  box.min = box.min - Vec3d{pad, pad, pad};
  box.max = box.max + Vec3d{pad, pad, pad};
  Extent extent{box, 0};
  if (!info.isLeaf()) {
    const double resolution =
        std::isfinite(info.resolution) && info.resolution > 0 ? info.resolution : kMinError;
    extent.geometricError = std::max({resolution, 2 * childError, kMinError});
  }
  return extent;
}

/// A subtree's extent without building its nodes.
Extent extentOf(const Model& model, const PatchInfo& info) {
  Box3d box = info.globalBox;
  double childError = 0;
  for (const Quadrant q : kQuadrants) {
    if (info.hasChild(q)) {
      const Extent child = extentOf(model, model.at(info.key.child(q)));
      box.extend(child.box);
      childError = std::max(childError, child.geometricError);
    }
  }
  return finish(info, tileCentre(info), box, childError);
}

/// The external tiles of an earlier tree whose extents still hold (TileTreeBase).
struct Reusable {
  std::map<PatchKey, const TileNode*> external;
  /// The keys at the external tiles' depth with a changed or removed key in their subtrees.
  std::set<PatchKey> changed;

  const TileNode* find(const PatchKey& key) const {
    const auto it = external.find(key);
    return it == external.end() || changed.contains(key) ? nullptr : it->second;
  }
};

void collectExternal(const TileNode& node, std::map<PatchKey, const TileNode*>& out) {
  if (node.external) {
    out.emplace(node.key, &node);
  }
  for (const TileNode& child : node.children) {
    collectExternal(child, out);
  }
}

/// The tile of `info` and, while `levels` > 0, its children's.
TileNode build(const Model& model, const PatchInfo& info, int levels, const Reusable* reusable) {
  TileNode node;
  node.key = info.key;
  node.version = info.version;
  node.centre = tileCentre(info);
  if (levels == 0 && !info.isLeaf()) {
    const TileNode* before = reusable != nullptr ? reusable->find(info.key) : nullptr;
    const Extent extent =
        before != nullptr ? Extent{before->box, before->geometricError} : extentOf(model, info);
    node.box = extent.box;
    node.geometricError = extent.geometricError;
    node.external = true;
    return node;
  }
  Box3d box = info.globalBox;
  double childError = 0;
  for (const Quadrant q : kQuadrants) {
    if (info.hasChild(q)) {
      node.children.push_back(build(model, model.at(info.key.child(q)), levels - 1, reusable));
      box.extend(node.children.back().box);
      childError = std::max(childError, node.children.back().geometricError);
    }
  }
  const Extent extent = finish(info, node.centre, box, childError);
  node.box = extent.box;
  node.geometricError = extent.geometricError;
  return node;
}

}  // namespace

Vec3d tileCentre(const PatchInfo& info) {
  if (!info.globalBox.empty() && info.globalBox.min.finite() && info.globalBox.max.finite()) {
    return info.globalBox.center();
  }
  return info.local2global().translationPart();
}

double tilePadding(const Box3d& box) {
  if (box.empty()) {
    return 1e-3;
  }
  const Vec3d size = box.size();
  return 1e-3 + 1e-6 * 0.5 * std::max({size.x, size.y, size.z});
}

TileNode buildTileTree(const Model& model, const PatchKey& root, int levels,
                       const TileTreeBase* previous) {
  if (levels < 1) {
    throw Error(ErrorCode::InvalidArgument,
                "a tile tree is at least one level deep, not " + std::to_string(levels));
  }
  const PatchInfo& top = model.at(root);
  if (previous == nullptr || previous->tree.key != root || levels > PatchKey::kMaxDepth) {
    return build(model, top, levels, nullptr);
  }
  Reusable reusable;
  collectExternal(previous->tree, reusable.external);
  const int depth = root.depth + levels;  // the external tiles'
  for (const auto* keys : {&previous->change.changed, &previous->change.removed}) {
    for (const PatchKey& key : *keys) {
      if (key.depth >= depth) {
        const int up = key.depth - depth;
        reusable.changed.insert(PatchKey{depth, key.x >> up, key.y >> up});
      }
    }
  }
  return build(model, top, levels, &reusable);
}

double tilesetGeometricError(const TileNode& root) {
  if (root.geometricError > 0) {
    return 2 * root.geometricError;
  }
  return std::max((root.box.max - root.box.min).norm(), kMinError);
}

}  // namespace vsm::core
