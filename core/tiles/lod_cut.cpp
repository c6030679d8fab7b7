#include "core/tiles/lod_cut.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <string>

#include "core/common/error.hpp"
#include "core/grid/vec_ops.hpp"
#include "core/tiles/tile_tree.hpp"

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

using vec::cross;
using vec::dot;
using vec::unit;

/// The inward unit normal `n` through the eye, as a plane.
Plane planeThrough(const Vec3d& eye, const Vec3d& n) {
  const Vec3d u = unit(n);
  return {u, -dot(u, eye)};
}

void descendCamera(const TileNode& node, const Camera& camera, const std::array<Plane, 5>& planes,
                   double maxScreenError, std::vector<CameraCutEntry>& out) {
  if (!boxInFrustum(node.box, planes)) {
    return;
  }
  const double error = screenSpaceError(camera, node.box, node.geometricError);
  if (error <= maxScreenError || node.children.empty()) {
    out.push_back({node.key, error});
    return;
  }
  for (const TileNode& child : node.children) {
    descendCamera(child, camera, planes, maxScreenError, out);
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

void checkCamera(const Camera& camera) {
  const auto fail = [](const std::string& what) { throw Error(ErrorCode::InvalidArgument, what); };
  if (!camera.eye.finite() || !camera.dir.finite() || !camera.up.finite()) {
    fail("camera eye, dir and up must be finite");
  }
  if (camera.dir.norm() == 0 || camera.up.norm() == 0) {
    fail("camera dir and up must not be zero");
  }
  // Parallel when the sine of their angle is under 1e-6.
  if (cross(unit(camera.dir), unit(camera.up)).norm() < 1e-6) {
    fail("camera up must not be parallel to dir");
  }
  if (!(camera.fovY > 0 && camera.fovY < std::numbers::pi)) {
    fail("camera fov must be between 0 and 180 degrees");
  }
  if (!(camera.width >= 1 && camera.height >= 1 && std::isfinite(camera.width) &&
        std::isfinite(camera.height))) {
    fail("camera viewport must be at least one pixel wide and high");
  }
}

std::array<Plane, 5> frustumPlanes(const Camera& camera) {
  const Vec3d forward = unit(camera.dir);
  const Vec3d right = unit(cross(forward, camera.up));
  const Vec3d up = cross(right, forward);
  const double tanY = std::tan(camera.fovY / 2);
  const double tanX = tanY * camera.width / camera.height;
  // Each side plane holds the eye and one edge of the image rectangle at distance 1: its inward
  // normal is perpendicular to that edge's direction and to the edge's image axis.
  return {planeThrough(camera.eye, forward),
          planeThrough(camera.eye, cross(up, forward + right * tanX)),   // right side
          planeThrough(camera.eye, cross(forward - right * tanX, up)),   // left side
          planeThrough(camera.eye, cross(forward + up * tanY, right)),   // top
          planeThrough(camera.eye, cross(right, forward - up * tanY))};  // bottom
}

bool boxInFrustum(const Box3d& box, const std::array<Plane, 5>& planes) {
  for (const Plane& plane : planes) {
    // The box's corner farthest along the normal: when even it is outside, the box is.
    const Vec3d p{plane.n.x >= 0 ? box.max.x : box.min.x, plane.n.y >= 0 ? box.max.y : box.min.y,
                  plane.n.z >= 0 ? box.max.z : box.min.z};
    if (dot(plane.n, p) + plane.d < 0) {
      return false;
    }
  }
  return true;
}

double screenSpaceError(const Camera& camera, const Box3d& box, double geometricError) {
  if (geometricError == 0) {
    return 0;
  }
  const auto gap = [](double v, double lo, double hi) {
    return v < lo ? lo - v : (v > hi ? v - hi : 0.0);
  };
  const double distance =
      Vec3d{gap(camera.eye.x, box.min.x, box.max.x), gap(camera.eye.y, box.min.y, box.max.y),
            gap(camera.eye.z, box.min.z, box.max.z)}
          .norm();
  return geometricError * camera.height / (2 * distance * std::tan(camera.fovY / 2));
}

std::vector<CameraCutEntry> lodCutForCamera(const Model& model, const Camera& camera,
                                            double maxScreenError) {
  std::vector<CameraCutEntry> out;
  if (model.empty()) {
    return out;
  }
  descendCamera(buildTileTree(model), camera, frustumPlanes(camera), maxScreenError, out);
  std::sort(out.begin(), out.end(),
            [](const CameraCutEntry& a, const CameraCutEntry& b) { return a.key < b.key; });
  return out;
}

}  // namespace vsm::core
