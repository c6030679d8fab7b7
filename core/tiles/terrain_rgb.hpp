#pragma once
// Heights as web maps draw terrain: Web Mercator tiles of heights packed into the red, green and
// blue bytes of an image (MapLibre GL JS's `raster-dem` sources, in Terrarium's or Mapbox's
// terrain-RGB encoding), sampled by the one height sampler (heights.hpp) that the quantized-mesh
// tiles and the GIS queries share.

#include <array>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "core/pyramid/patch_key.hpp"
#include "core/tiles/quantized_mesh.hpp"
#include "core/tiles/top_down.hpp"

namespace vsm::core {

class Model;

/// A tile of the Web Mercator tiling scheme web maps use (EPSG:3857, "XYZ"): level z has 2^z x 2^z
/// square tiles, x counted east from -180 degrees, y south from the projection's north edge
/// (85.0511 degrees).
struct MercatorTileKey {
  /// Deepest level served: tiles of about 2.4 m at the equator, pixels of about 1 cm.
  static constexpr int kMaxLevel = 24;
  int z = 0;
  std::uint32_t x = 0;
  std::uint32_t y = 0;
  /// True when z is 0..kMaxLevel and x, y < 2^z.
  bool valid() const;
  /// "z/x/y".
  std::string toString() const;
};

/// Pixels per side of a terrain-RGB tile (MapLibre's `tileSize` of the source must say so: its
/// default is 512).
inline constexpr int kDemTileSize = 256;

/// The tile's lon/lat rectangle (degrees). Precondition: key.valid().
GeoRect mercatorTileRect(const MercatorTileKey& key);
/// The tile as a picture of kDemTileSize^2 pixels in the Web Mercator plane (row 0 north): the
/// pixel centres are where the tile's heights are sampled. Precondition: key.valid().
TopDownGrid mercatorTilePicture(const MercatorTileKey& key);
/// The ground size (m) of the tile's pixels at its middle latitude.
double mercatorPixelGround(const MercatorTileKey& key);
/// The first level whose pixels at `latitude` (degrees) are at most `resolution` metres on the
/// ground (every vertex of data that fine gets a pixel of its own), at most kMaxLevel; 0 for a
/// resolution that is not positive.
int mercatorLevelFor(double resolution, double latitude);

/// The patches tile `key` is sampled from, coarse to fine: heightSources over the tile's rectangle
/// (grown by a pixel) at the ground size of its pixels (mercatorPixelGround), so a tile reads
/// what the level warrants, never finer than the model holds. Metadata only.
std::vector<PatchKey> demTileSources(const Model& model, const TerrainLayer& layer,
                                     const MercatorTileKey& key);

/// How heights become pixels. Both pack a 24-bit integer n into red (n >> 16), green (n >> 8 &
/// 255) and blue (n & 255):
///   Terrarium (Mapzen's, MapLibre's "terrarium"): h = n / 256 - 32768, steps of 1/256 m;
///   Mapbox terrain-RGB (MapLibre's "mapbox"):     h = n / 10 - 10000, steps of 0.1 m.
enum class DemEncoding : std::uint8_t { Terrarium, Mapbox };

/// The lowest and highest heights (m) an encoding holds.
double demEncodingMin(DemEncoding encoding);
double demEncodingMax(DemEncoding encoding);
/// The pixel of height `h`, rounded to the encoding's nearest step; heights beyond its range
/// are clamped to it.
std::array<std::uint8_t, 3> encodeDemHeight(double h, DemEncoding encoding);
/// The height a pixel stands for.
double decodeDemHeight(std::uint8_t r, std::uint8_t g, std::uint8_t b, DemEncoding encoding);

/// A sampled and encoded tile: kDemTileSize^2 RGB pixels, row 0 north.
struct DemTile {
  std::vector<std::uint8_t> rgb;
  /// Pixels that got a height from the model; the others hold `nodataHeight`.
  std::size_t covered = 0;
};

/// Samples tile `key` from `sources` (demTileSources(); read through `load`) at its pixel centres
/// with paintHeights (heights above the WGS 84 ellipsoid, barycentric in the Mercator plane within
/// each triangle of the model's quads, coarse sources first) and encodes them; pixels no source
/// covers get `nodataHeight`. Throws what `load` throws.
DemTile sampleDemTile(const Model& model, const std::vector<PatchKey>& sources,
                      const MercatorTileKey& key, const TerrainGridLoader& load,
                      DemEncoding encoding, double nodataHeight);

}  // namespace vsm::core
