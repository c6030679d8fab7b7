#pragma once

#include <array>
#include <vector>

#include "core/grid/geometry.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core {

/// The cut of the tree for a view: from the root, descends through patches whose global box meets
/// `box`; stops at a patch whose resolution is at or below `resolution` (finer or equal) or at a
/// leaf. Parents before children, in key order; empty for an empty model.
std::vector<PatchKey> lodCut(const Model& model, const Box3d& box, double resolution);

/// A perspective camera in global coordinates (ECEF metres for georeferenced models), as a 3D
/// Tiles renderer holds it.
struct Camera {
  Vec3d eye;
  /// Viewing direction and the screen's up; any length, up not parallel to dir (it is made
  /// orthogonal to dir).
  Vec3d dir;
  Vec3d up;
  /// Vertical field of view, radians, in (0, pi).
  double fovY = 1.0;
  /// Viewport size, pixels.
  double width = 1;
  double height = 1;
};

/// Checks a camera; throws Error(InvalidArgument) naming what is wrong (a non-finite number, a
/// zero dir or up, up parallel to dir, fovY outside (0, pi), a viewport under one pixel).
void checkCamera(const Camera& camera);

/// The four side planes and the near plane (through the eye) of `camera`'s frustum, each as an
/// inward unit normal n and offset d: a point p is inside when n·p + d >= 0 for all five. The
/// frustum has no far plane.
struct Plane {
  Vec3d n;
  double d = 0;
};
std::array<Plane, 5> frustumPlanes(const Camera& camera);

/// False only when `box` lies wholly outside one of the planes (the test 3D Tiles renderers use:
/// conservative, a box beyond a frustum's corner counts as visible).
bool boxInFrustum(const Box3d& box, const std::array<Plane, 5>& planes);

/// The screen-space error, in pixels, of drawing a tile whose geometric error is `geometricError`
/// metres and whose bounding box is `box`: geometricError * height / (2 * distance * tan(fovY/2)),
/// distance the eye's to the box (3D Tiles' formula, as CesiumJS and 3d-tiles-renderer compute
/// it). Infinite when the eye is inside the box and the error is not 0.
double screenSpaceError(const Camera& camera, const Box3d& box, double geometricError);

/// One patch of a camera's cut: its key and its screen-space error (pixels).
struct CameraCutEntry {
  PatchKey key;
  double screenError = 0;
};

/// The cut a 3D Tiles renderer with `camera` and threshold `maxScreenError` (pixels) would draw
/// from the model's tileset (buildTileTree: its padded tile boxes and geometric errors, REPLACE
/// refinement): from the root, tiles whose box is outside the frustum are culled; a visible tile
/// is refined into its children when its screen-space error exceeds `maxScreenError` and it has
/// children, else drawn. Parents before children, in key order; empty for an empty model or when
/// the root is culled. Preconditions: checkCamera(camera) holds, maxScreenError > 0.
std::vector<CameraCutEntry> lodCutForCamera(const Model& model, const Camera& camera,
                                            double maxScreenError);

}  // namespace vsm::core
