#pragma once

#include <cstddef>
#include <cstdint>
#include <limits>
#include <span>
#include <vector>

#include "core/grid/geometry.hpp"
#include "core/pyramid/patch_key.hpp"
#include "core/tiles/quantized_mesh.hpp"
#include "core/tiles/top_down.hpp"

namespace vsm::core {

class Model;

/// Lon/lat (degrees) and height (metres above the WGS 84 ellipsoid) of an ECEF point by Bowring's
/// formula: one step, well below a millimetre for points within tens of kilometres of the
/// ellipsoid, and about 3x faster than ecefToGeodetic's iteration (the sampler converts every
/// vertex it paints with).
Vec3d geodeticOf(const Vec3d& ecef);

// ---- the one height sampler ---------------------------------------------------------------------

/// The height sampler that every height product shares (quantized-mesh tiles, point and profile
/// queries, GeoTIFF coverages): paints the patches `sources` (coarse first; read through `load`)
/// onto the geographic picture `view` (lon/lat degrees, row 0 north). Each patch's vertices are
/// turned to lon/lat/height (geodeticOf) and each complete quad's two triangles rasterised
/// (forEachPixelInTriangle, pixel centres, edges included) with the height interpolated by the
/// barycentric weights (exact at a vertex, and for a surface linear in lon/lat); later sources
/// paint over earlier ones. Blocks of 16 x 16 cells whose corners (padded by half the block) lie
/// outside `area` are skipped before any conversion, so `area` must hold the view. `heights` and
/// `painted` have view.pixels() entries; painted pixels get their height and painted = 1, the
/// others are left as they were. `edgeTolerance` is forEachPixelInTriangle's: how far outside a
/// triangle, relative to its size, a pixel centre still counts. Throws what `load` throws.
void paintHeights(const Model& model, const std::vector<PatchKey>& sources, const TopDownGrid& view,
                  const GeoRect& area, const TerrainGridLoader& load, std::span<double> heights,
                  std::span<std::uint8_t> painted, double edgeTolerance = 1e-9);

/// The edge tolerance of the GIS queries: a point within 1e-4 of a cell outside the surface's
/// border still gets the border's height. A point on an outer vertex (a raster's edge pixel)
/// lands that far off after the round trip through the patch's float32 positions and the
/// geodetic conversion (measured: up to a few 1e-6 of a cell); the terrain tiles keep 1e-9.
inline constexpr double kQueryEdgeTolerance = 1e-4;

// ---- what GIS clients ask for -------------------------------------------------------------------

/// A point on the WGS 84 ellipsoid, degrees.
struct GeoPoint {
  double lon = 0;
  double lat = 0;
};

/// The height at a point and what answered it.
struct HeightSample {
  /// Metres above the WGS 84 ellipsoid; NaN where no leaf covers the point.
  double height = std::numeric_limits<double>::quiet_NaN();
  /// Depth and resolution (m) of the leaf that answered, -1 and 0 where none did.
  int depth = -1;
  double resolution = 0;
};

/// The heights at `points` from the model's finest leaves (heightSources with no resolution
/// bound), each point sampled by paintHeights on a one-pixel picture centred on it: the same
/// interpolation as the terrain tiles. Where leaves overlap, the deepest wins.
std::vector<HeightSample> sampleHeights(const Model& model, const TerrainLayer& layer,
                                        std::span<const GeoPoint> points,
                                        const TerrainGridLoader& load);

/// The heights at the pixel centres of the geographic picture `view` from the finest leaves, as
/// float32, row 0 north; NaN where no leaf covers a pixel. `out` has view.pixels() entries.
/// Memory: one double and one byte per pixel besides `out`, and the leaves `load` keeps.
void sampleHeightGrid(const Model& model, const TerrainLayer& layer, const TopDownGrid& view,
                      const TerrainGridLoader& load, std::span<float> out);

/// The geographic picture of an area: pixel edges at `bounds` (degrees; west and north exact,
/// east and south rounded to whole pixels of `resolution` degrees, at least one pixel each way).
/// Throws Error(InvalidArgument) for an empty or inverted box, a resolution that is not positive,
/// or more than `maxPixels` pixels (naming both).
TopDownGrid heightPicture(const GeoRect& bounds, double resolution, std::size_t maxPixels);
/// Rows [row, row + rows) of `view` as a picture of their own (a strip of an export).
TopDownGrid pictureRows(const TopDownGrid& view, int row, int rows);

/// The vertex spacing in degrees of the finest leaf meeting `area` (the larger of its longitude
/// and latitude steps between neighbouring defined vertices): an export at it puts a pixel on
/// every vertex of a raster imported in lon/lat. 0 when no leaf meets the area.
double finestSpacingDegrees(const Model& model, const TerrainLayer& layer, const GeoRect& area,
                            const TerrainGridLoader& load);

/// The finest resolution (m) of the leaves whose footprint meets `area`; 0 when none does.
double finestResolution(const Model& model, const TerrainLayer& layer, const GeoRect& area);

/// Great-circle distance in metres (haversine on the mean earth radius, 6371008.8 m): what Open
/// Topo Data's and most web maps' profiles report; within 0.5 % of the ellipsoidal distance.
double greatCircleDistance(const GeoPoint& a, const GeoPoint& b);

/// A point along a path and its distance from the path's start, in metres.
struct PathSample {
  GeoPoint point;
  double distance = 0;
};

/// `samples` points evenly spaced by distance along the path through `vertices` (linear in
/// lon/lat within each segment, as Open Topo Data's `samples`): the first and last are the path's
/// ends. Precondition: at least one vertex; samples >= 2 (one vertex gives that vertex once).
std::vector<PathSample> samplePath(std::span<const GeoPoint> vertices, std::size_t samples);

}  // namespace vsm::core
