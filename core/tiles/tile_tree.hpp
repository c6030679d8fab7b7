#pragma once

#include <cstdint>
#include <limits>
#include <vector>

#include "core/grid/geometry.hpp"
#include "core/pyramid/patch_key.hpp"

namespace vsm::core {

class Model;
struct ModelChange;
struct PatchInfo;

/// One tile of the 3D Tiles view of a model: a patch, its children, and what a tileset needs to
/// know about it. Built from metadata only (no vertex data).
struct TileNode {
  PatchKey key;
  /// The patch's version (PatchInfo::version): what a content URI names.
  std::uint64_t version = 0;
  /// Global point the tile's content is relative to (tileCentre() of the patch).
  Vec3d centre;
  /// Global axis-aligned box holding the patch's defined vertices and every descendant's box,
  /// padded (tilePadding()) so float32 rounding of the content never leaves it. Never empty.
  Box3d box;
  /// Metres: 0 for a leaf; otherwise at least the patch's resolution and at least twice the
  /// largest child's, so it falls strictly from parent to child.
  double geometricError = 0;
  /// In quadrant order (NW, NE, SW, SE), missing children left out.
  std::vector<TileNode> children;
  /// The tile stands for a subtree whose tiles are left out here (`children` is empty, though the
  /// patch has children): its box and error are the whole subtree's, and its tiles are in a tree
  /// of their own (buildTileTree from this key).
  bool external = false;
};

/// The point a patch's tile content (encodeGlb) is relative to: the centre of its global box, or
/// the translation of its Local2Global when the box is empty.
Vec3d tileCentre(const PatchInfo& info);

/// The padding added on every side of a tile box of the given (unpadded) box: 1 mm plus 1e-6 of
/// its largest half extent (float32 positions relative to the centre round by at most ~1e-7 of it).
/// Grows with the box, so a padded child stays inside its padded parent.
double tilePadding(const Box3d& box);

/// The tile tree of a model from patch `root` (by default the model's root), `levels` deep: the
/// tiles of depths root.depth .. root.depth + levels - 1, and at depth root.depth + levels a tile
/// per patch there, `external` when that patch has children. Boxes and errors are those of the
/// whole tree, whatever `levels` leaves out, so the trees from every external tile's key put
/// together give the whole tree. Reads metadata only; an external tile costs a walk of its subtree
/// (boxes and errors), not a node per patch. Throws Error(NotFound) for a root not in the model,
/// Error(InvalidArgument) for `levels` < 1.
///
/// With `previous` (a tree built before from the same root and levels, and the change from its
/// model to `model`), an external tile whose subtree holds no changed or removed key takes its box
/// and error from `previous.tree` without the walk: a new version's tree after a small merge walks
/// only the subtrees the merge changed.
struct TileTreeBase {
  const TileNode& tree;
  const ModelChange& change;
};
TileNode buildTileTree(const Model& model, const PatchKey& root = PatchKey::root(),
                       int levels = std::numeric_limits<int>::max(),
                       const TileTreeBase* previous = nullptr);

/// The error of the whole tileset (what not rendering the root costs): twice the root's, or the
/// root's box diagonal for a single-tile model.
double tilesetGeometricError(const TileNode& root);

}  // namespace vsm::core
