#pragma once

#include <cstddef>
#include <functional>
#include <limits>
#include <memory>
#include <optional>
#include <span>
#include <vector>

#include "core/grid/geometry.hpp"
#include "core/pyramid/model.hpp"
#include "core/pyramid/patch_key.hpp"

namespace vsm::core {

/// A ray of a query, in the model's global frame (the frame of PatchInfo::globalBox: a point
/// cloud's own frame, ECEF for georeferenced rasters): the points origin + t * direction for t in
/// [0, maxDistance], t a length (the direction is normalised).
struct Ray {
  Vec3d origin;
  /// Finite and not zero; any length.
  Vec3d direction;
  /// >= 0; infinity: as far as the model reaches.
  double maxDistance = std::numeric_limits<double>::infinity();
};

/// Where a ray first meets the surface, and what answered.
struct RayHit {
  /// On the ray: origin + distance * the normalised direction, on the surface of the leaf.
  Vec3d point;
  /// In [0, maxDistance].
  double distance = 0;
  /// The unit normal of the surface at the hit (the hit cell's bilinear surface, or its triangle
  /// for a cell with three defined corners), on the side the ray came from: dot(normal,
  /// direction) <= 0. A point cloud's grid has no outside of its own, so the side is the ray's.
  Vec3d normal;
  /// The leaf whose cell was hit (its depth is leaf.depth), and its resolution (m).
  PatchKey leaf;
  double resolution = 0;
};

/// The bounds of one castRays call.
struct RayLimits {
  /// Rays per call.
  std::size_t rays = 1000;
  /// Leaves a ray's segment may meet (each is read, as a whole grid, through the loader).
  std::size_t leavesPerRay = 32;
  /// Cells a ray may build into its hierarchy: the cells of the 16 x 16-cell blocks of those
  /// leaves whose box the segment meets (SurfaceCaster::blockBoxes), 256 per block.
  std::size_t cellsPerRay = std::size_t{1} << 17;
};

/// Charges `bytes` of working memory (a ray's hierarchy) while the returned hold lives; throws
/// when they do not fit (the server charges its memory budget). Empty: nothing is charged.
using RayWorkCharge = std::function<std::shared_ptr<const void>(std::size_t bytes)>;

/// The first hit of each ray on the model's surface: its finest leaves (the actual surface at
/// every place; overviews are never hit), cell by cell as SurfaceCaster sees them (a full cell is
/// the bilinear surface of its corners, a 3-corner cell its triangle, the border within the
/// caster's tolerance, 1/32 of a cell). Works for any surface: walls, overhangs, tunnels,
/// terrain.
///
/// Per ray: its segment, clipped to the root's box, selects the leaves whose global box it meets
/// (a descent from the root, boxes grown for rounding), and within them the 16 x 16-cell blocks
/// whose box it meets; only those cells go into a SurfaceCaster (clipped to the segment's box),
/// whose nearest hit with t in [0, maxDistance] is the answer (the caster looks both ways along
/// a line: here the backward side is empty, so a surface behind the origin is never reported).
/// Nothing is built over the whole model: the cost follows the ray's length through the surface.
/// nullopt where the ray meets no surface within maxDistance.
///
/// Leaves are read through `load` (each leaf once per call while a ray needs it; their block
/// boxes are kept for the call). `charge` is asked for each ray's estimated working memory before
/// its hierarchy is built.
///
/// Throws Error(InvalidArgument), naming the ray (counted from 1), for more than limits.rays rays,
/// a non-finite origin, a zero or non-finite direction, a negative or NaN maxDistance; and, as a
/// "too long" refusal, for a ray whose segment meets more than limits.leavesPerRay leaves or more
/// than limits.cellsPerRay cells' blocks (the message says to shorten it with a max distance).
/// Throws what `load` and `charge` throw. Creates no threads; not thread-safe on one Model.
std::vector<std::optional<RayHit>> castRays(const Model& model, std::span<const Ray> rays,
                                            const Model::GridLoader& load,
                                            const RayLimits& limits = {},
                                            const RayWorkCharge& charge = {});

}  // namespace vsm::core
