#include "core/pyramid/reduce.hpp"

#include "core/common/error.hpp"
#include "core/pyramid/patch_key.hpp"

namespace vsm::core {
namespace {

/// parent[k] = child[2k] for k < n where child vertex 2k is defined, as setGlobal(global(...))
/// computes it when the child's local2global is a translation by `shift` and the parent's
/// global2local one by `back`: float((child + shift) + back).
void takeEverySecond(const float* __restrict child, int n, Vec3d shift, Vec3d back,
                     float* __restrict parent) {
  for (int k = 0; k < n; ++k) {
    const float x = child[6 * k], y = child[6 * k + 1], z = child[6 * k + 2];
    const bool defined = (x == x) & (y == y) & (z == z);
    const auto local = [](float v, double shift, double back) {
      return static_cast<float>((static_cast<double>(v) + shift) + back);
    };
    parent[3 * k] = defined ? local(x, shift.x, back.x) : parent[3 * k];
    parent[3 * k + 1] = defined ? local(y, shift.y, back.y) : parent[3 * k + 1];
    parent[3 * k + 2] = defined ? local(z, shift.z, back.z) : parent[3 * k + 2];
  }
}

}  // namespace

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
  if (translations) {
    // Every grid vsm builds: each parent row from its children's rows, the quadrants in reverse
    // order so that the first defined candidate (below) is the one that stays.
    const Vec3d back = parent.local2global().inverse().translationPart();
    const std::size_t stride = static_cast<std::size_t>(size) * 3;
    for (int j = 0; j < size; ++j) {
      for (int q = 3; q >= 0; --q) {
        const int qx = q & 1;
        const int qy = q >> 1;
        const PatchGrid* child = children[q];
        const int cy = 2 * j - qy * half;
        if (child == nullptr || cy < 0 || cy > half) {
          continue;
        }
        // Parent columns i with 0 <= 2i - qx * half <= half.
        const int first = (qx * half + 1) / 2;
        const int last = (half + qx * half) / 2;
        takeEverySecond(child->positions().data() + static_cast<std::size_t>(cy) * stride +
                            static_cast<std::size_t>(2 * first - qx * half) * 3,
                        last - first + 1, child->local2global().translationPart(), back,
                        parent.positions().data() + static_cast<std::size_t>(j) * stride +
                            static_cast<std::size_t>(first) * 3);
      }
    }
    return parent;
  }
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
