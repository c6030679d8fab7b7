#pragma once

// Internal to core/diff: the rasteriser diffRevisions draws its DisplacementMap with
// (diff_picture.cpp, beside the map's colours and legend).

#include <vector>

namespace vsm::core {

class PatchGrid;
struct DisplacementMap;

namespace diff_detail {

/// Fills the cells of `grid` whose corners all have a displacement into `map`, interpolated
/// linearly over each cell's two triangles (a 3-corner cell: its triangle).
void drawLeaf(const PatchGrid& grid, const std::vector<double>& d, DisplacementMap& map);

}  // namespace diff_detail

}  // namespace vsm::core
