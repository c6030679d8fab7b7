#pragma once

#include <array>

#include "core/grid/patch_grid.hpp"

namespace vsm::core {

/// Reduces up to four children into their parent by the thesis rule: the children's union is
/// 2^(n+1)+1 vertices per side (neighbours share their border line) and the parent keeps every
/// second vertex of it (indices 0, 2, 4, ...), so every parent vertex *is* a child vertex.
///
/// `children` is indexed by Quadrant (NW, NE, SW, SE); null entries are missing children, whose
/// area becomes undefined. A vertex on a shared border is taken from the first present child (in
/// quadrant order) that defines it. The parent gets its own origin: the centre of its (defined)
/// children's origins when all are translations, else originFor the union of their global boxes;
/// its float32 locals are the children's global positions rounded once.
///
/// Preconditions: at least one child, all children of the same size 2^n+1.
/// Throws Error(InvalidArgument) when they are not met.
PatchGrid reduce(const std::array<const PatchGrid*, 4>& children);

}  // namespace vsm::core
