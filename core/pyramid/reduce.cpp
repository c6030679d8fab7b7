#include "core/pyramid/reduce.hpp"

#include "core/common/error.hpp"
#include "core/pyramid/patch_key.hpp"

namespace vsm::core {

PatchGrid reduce(const std::array<const PatchGrid*, 4>& children) {
  int size = 0;
  // The parent's origin: the centre of its children's origins when those are translations (as in
  // every grid vsm builds: each the centre of its child's box), so its locals stay as small as
  // theirs without a pass over their vertices; otherwise the centre of their global boxes.
  Box3d origins;
  Box3d box;
  bool translations = true;
  for (const PatchGrid* child : children) {
    if (child == nullptr) {
      continue;
    }
    if (size != 0 && child->size() != size) {
      throw Error(ErrorCode::InvalidArgument, "reduce: children differ in grid size");
    }
    size = child->size();
    if (!child->anyDefined()) {
      continue;  // its origin (identity) says nothing about where it is
    }
    translations = translations && child->local2global().isTranslation();
    if (translations) {
      origins.extend(child->local2global().translationPart());
    } else {
      box.extend(child->globalBox());
    }
  }
  if (size == 0) {
    throw Error(ErrorCode::InvalidArgument, "reduce: no children");
  }
  const int half = size - 1;  // 2^n intervals per child
  if ((half & (half - 1)) != 0) {
    throw Error(ErrorCode::InvalidArgument, "reduce: grid size is not 2^n+1");
  }

  if (!translations) {
    for (const PatchGrid* child : children) {
      if (child != nullptr) {
        box.extend(child->globalBox());
      }
    }
  }
  PatchGrid parent(size, originFor(translations ? origins : box));
  for (int j = 0; j < size; ++j) {
    const int v = 2 * j;  // row in the children's union
    for (int i = 0; i < size; ++i) {
      const int u = 2 * i;
      // Candidates in quadrant order; a border vertex (u or v == half) lies in two or four
      // children, which agree wherever they all exist.
      for (const Quadrant q : kQuadrants) {
        const int qx = static_cast<int>(q) & 1;
        const int qy = static_cast<int>(q) >> 1;
        const int cx = u - qx * half;
        const int cy = v - qy * half;
        const PatchGrid* child = children[static_cast<int>(q)];
        if (child == nullptr || cx < 0 || cx > half || cy < 0 || cy > half ||
            !child->defined(cx, cy)) {
          continue;
        }
        parent.setGlobal(i, j, child->global(cx, cy));
        break;
      }
    }
  }
  return parent;
}

}  // namespace vsm::core
