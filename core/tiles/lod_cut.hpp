#pragma once

#include <vector>

#include "core/grid/geometry.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core {

/// The cut of the tree for a view: from the root, descends through patches whose global box meets
/// `box`; stops at a patch whose resolution is at or below `resolution` (finer or equal) or at a
/// leaf. Parents before children, in key order; empty for an empty model.
std::vector<PatchKey> lodCut(const Model& model, const Box3d& box, double resolution);

}  // namespace vsm::core
