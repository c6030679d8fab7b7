#pragma once

#include "core/grid/patch_grid.hpp"
#include "core/grid/texture_tile.hpp"

namespace vsm::core {

/// The sun of vsm's shaded relief (GDAL's hillshade defaults): azimuth in degrees clockwise from
/// north, altitude in degrees above the horizon, both in the local east-north-up frame.
inline constexpr double kReliefAzimuthDeg = 315.0;
inline constexpr double kReliefAltitudeDeg = 45.0;

/// The shaded relief of a patch as its texture tile (textureTileSize(grid.size()) texels a side):
/// texel (i, j) shades grid quad (i, j), the texel the image texture would give that quad.
///
/// Lambertian, from the quad's own surface normal, no vertical exaggeration (heights as they are):
/// grey = round(255 max(0, n . s)), opaque, where n is the unit normal of the quad (the cross
/// product of its two mid-lines; of the triangle of its defined corners when one is undefined)
/// turned to point up, and s the unit vector towards the sun at kReliefAzimuthDeg /
/// kReliefAltitudeDeg in the east-north-up frame at the quad's centre: up = upAt(centre), east
/// = +z x up normalised (+x where up is +z, a local Cartesian model), north = up x east. So it
/// needs no CRS and works for point clouds. Quads with fewer than 3 defined corners are
/// transparent. A flat quad has grey round(255 sin(altitude)) = 180.
TextureTile shadedRelief(const PatchGrid& grid);

}  // namespace vsm::core
