#include "core/tiles/lod_cut.hpp"

#include <algorithm>

namespace vsm::core {

namespace {

void descend(const Model& model, const PatchKey& key, const Box3d& box, double resolution,
             std::vector<PatchKey>& out) {
  const PatchInfo& info = model.at(key);
  if (!info.globalBox.intersects(box)) {
    return;
  }
  if (info.isLeaf() || info.resolution <= resolution) {
    out.push_back(key);
    return;
  }
  for (const Quadrant q : kQuadrants) {
    if (info.hasChild(q)) {
      descend(model, key.child(q), box, resolution, out);
    }
  }
}

}  // namespace

std::vector<PatchKey> lodCut(const Model& model, const Box3d& box, double resolution) {
  std::vector<PatchKey> out;
  if (model.find(PatchKey::root()) != nullptr) {
    descend(model, PatchKey::root(), box, resolution, out);
  }
  std::sort(out.begin(), out.end());
  return out;
}

}  // namespace vsm::core
