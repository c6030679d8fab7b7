#pragma once

#include <cstddef>
#include <span>
#include <vector>

#include "core/grid/geometry.hpp"

namespace vsm::core {

/// A rectangle of grid cells [x0, x1) x [y0, y1); empty when x0 >= x1 or y0 >= y1.
struct GridRect {
  int x0 = 0, y0 = 0, x1 = 0, y1 = 0;
  bool empty() const { return x0 >= x1 || y0 >= y1; }
  int width() const { return x1 - x0; }
  int height() const { return y1 - y0; }
  friend bool operator==(const GridRect&, const GridRect&) = default;
};

/// The vertex grid of one patch: size x size float32 positions, row-major (x fastest), local to
/// the patch; global = local2global x local, in double. A vertex is undefined when any component
/// is NaN; setUndefined() writes all three as NaN.
///
/// Not thread-safe for writing; published grids are shared as shared_ptr<const PatchGrid>.
class PatchGrid {
 public:
  /// A grid of size x size undefined vertices. Throws Error(InvalidArgument) when size < 2 or the
  /// matrix is not an invertible affine transform.
  PatchGrid(int size, const Mat4d& local2global);

  int size() const { return size_; }
  const Mat4d& local2global() const { return local2global_; }
  std::size_t vertexCount() const { return static_cast<std::size_t>(size_) * size_; }
  /// Bytes of vertex data, for memory accounting.
  std::size_t bytes() const { return positions_.size() * sizeof(float); }

  bool defined(int x, int y) const {
    const float* p = at(x, y);
    return p[0] == p[0] && p[1] == p[1] && p[2] == p[2];
  }
  Vec3f local(int x, int y) const {
    const float* p = at(x, y);
    return {p[0], p[1], p[2]};
  }
  Vec3d global(int x, int y) const {
    const Vec3f l = local(x, y);
    return local2global_.apply({l.x, l.y, l.z});
  }
  void setLocal(int x, int y, const Vec3f& v) {
    float* p = at(x, y);
    p[0] = v.x;
    p[1] = v.y;
    p[2] = v.z;
  }
  /// Stores `g` (global, double) as local float32; an undefined input stays undefined.
  void setGlobal(int x, int y, const Vec3d& g);
  void setUndefined(int x, int y);

  /// Interleaved x, y, z floats, vertexCount() * 3 of them.
  std::span<const float> positions() const { return positions_; }
  std::span<float> positions() { return positions_; }

  bool anyDefined() const;
  std::size_t definedCount() const;
  Box3d localBox() const;
  /// Box of the defined vertices in global coordinates (each vertex transformed in double).
  Box3d globalBox() const;

  /// What describing or writing a patch needs of its vertices, from one pass over them.
  struct Summary {
    /// localBox().
    Box3d localBox;
    /// The smallest rectangle holding every defined vertex (empty when none is defined).
    GridRect definedRect;
    /// Mean global distance between defined horizontal and vertical grid neighbours (each
    /// distance in float32 when local2global is a translation, relative error below 1e-6); 0
    /// when no two neighbours are defined.
    double resolution = 0;
  };
  Summary summarize() const;
  /// summarize().definedRect and summarize().resolution.
  GridRect definedRect() const { return summarize().definedRect; }
  double resolution() const { return summarize().resolution; }
  /// Largest absolute local coordinate of a defined vertex: float32 rounding of stored positions is
  /// at most this times 2^-24.
  double maxAbsLocal() const;

  friend bool operator==(const PatchGrid& a, const PatchGrid& b);

 private:
  const float* at(int x, int y) const {
    return &positions_[(static_cast<std::size_t>(y) * size_ + x) * 3];
  }
  float* at(int x, int y) { return &positions_[(static_cast<std::size_t>(y) * size_ + x) * 3]; }

  int size_;
  Mat4d local2global_;
  Mat4d global2local_;
  std::vector<float> positions_;
};

/// The Local2Global vsm writes: a translation to the centre of `box`, so float32 local coordinates
/// stay small (ECEF coordinates are ~6.4e6 m from the origin).
Mat4d originFor(const Box3d& box);

}  // namespace vsm::core
