#pragma once

#include <cstddef>
#include <cstdint>
#include <optional>
#include <vector>

#include "core/grid/patch_grid.hpp"

namespace vsm::core {

class SurfaceSampler;
struct SurfacePoint;
struct Rect2d;
struct UpFrame;

/// Refines one bottom patch `a` (size s = 2^n+1) by k levels: level j (0 <= j <= k) below `a` is
/// 2^j x 2^j patches whose union is 2^j (s-1) + 1 vertices per side, neighbours sharing their
/// border lines. Every new vertex is interpolated bilinearly, in global double coordinates, from
/// the cell of `a` it falls in; when some of the cell's corners are undefined the weights are
/// re-normalised over the defined ones, and the vertex is undefined when the defined corners have
/// no weight at it (all undefined, or it lies on an edge/corner whose defining vertices are
/// undefined). A vertex at a position of `a`'s own lattice therefore reproduces `a` exactly, so the
/// reduction of the new levels gives back `a` wherever nothing replaced it.
///
/// With a detail surface, each defined new vertex is then replaced by detail.sample(vertex) where
/// that exists (the thesis' "placing" step, done per vertex).
///
/// Union vertex (u, v) at level k is a pure function of (u, v): the border line two neighbouring
/// new patches share is computed once per vertex position and is bit-identical in double before
/// each patch rounds it to float32 around its own origin (originFor(its box)).
///
/// Thread-safe for concurrent const calls.
class Subdivider {
 public:
  /// Copies `a`'s global positions. Throws Error(InvalidArgument) unless 0 <= k <= 16 and
  /// a.size() is 2^n+1. With k = 0, level 0 is `a` itself (to place it on a detail surface in
  /// place).
  Subdivider(const PatchGrid& a, int k);

  int k() const { return k_; }
  int size() const { return size_; }

  /// A's interpolation at union vertex (u, v) of level k (0 <= u, v <= 2^k (s-1)); NaN
  /// components when undefined.
  Vec3d interpolate(std::int64_t u, std::int64_t v) const;

  /// Global positions (row-major, size x size, NaN = undefined) of patch (i, j) of level `level`
  /// (0..k; 0 <= i, j < 2^level), placed on `detail` where it has surface (detail may be null).
  /// `fromDetail`, when given, receives how many vertices were taken from `detail`; `onDetail`,
  /// when given, where on `detail` each vertex was placed (row-major as the positions; nullopt
  /// for a vertex not taken from it).
  std::vector<Vec3d> positions(int level, std::uint32_t i, std::uint32_t j,
                               const SurfaceSampler* detail, std::size_t* fromDetail = nullptr,
                               std::vector<std::optional<SurfacePoint>>* onDetail = nullptr) const;

  /// The projection (in `frame`) of the bounding rectangle of a's defined vertices around the
  /// cells patch (i, j) of `level` covers: every position interpolated there lies inside it.
  Rect2d footprint(int level, std::uint32_t i, std::uint32_t j, const UpFrame& frame) const;

 private:
  int k_;
  int size_;
  std::vector<Vec3d> global_;  // a's vertices in global double; NaN when undefined
};

/// Turns global positions (size x size, NaN = undefined) into a PatchGrid with originFor(box).
PatchGrid gridFromGlobal(int size, const std::vector<Vec3d>& global);

}  // namespace vsm::core
