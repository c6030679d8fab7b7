#pragma once

// The products of Vec3d, once for the files that use them: `using vec::dot;` in a file's own
// namespace keeps its calls as they are. core/merge and core/diff still define their own copies.

#include "core/grid/geometry.hpp"

namespace vsm::core::vec {

inline double dot(const Vec3d& a, const Vec3d& b) {
  return a.x * b.x + a.y * b.y + a.z * b.z;
}

inline Vec3d cross(const Vec3d& a, const Vec3d& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

/// `v` scaled to length 1 (not finite for a zero vector).
inline Vec3d unit(const Vec3d& v) {
  return v * (1.0 / v.norm());
}

}  // namespace vsm::core::vec
