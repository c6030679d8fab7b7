#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "core/grid/geometry.hpp"
#include "core/pyramid/patch_key.hpp"

namespace vsm::core {

struct ModelChange;

class Model;
class PatchGrid;
struct PatchInfo;
class SavedFootprints;

// ---- the tiling scheme ------------------------------------------------------------------------

/// A tile of the geographic tiling scheme CesiumJS uses for quantized-mesh terrain (EPSG:4326,
/// TMS): level z has 2^(z+1) x 2^z tiles of 180 / 2^z degrees, x counted east from -180 deg, y
/// north from -90 deg.
struct TerrainTileKey {
  /// Deepest level served (tiles of 180/2^24 deg, ~1.2 m at the equator; vertices ~2 cm apart).
  static constexpr int kMaxLevel = 24;

  int z = 0;
  std::uint32_t x = 0;
  std::uint32_t y = 0;

  /// True when z is 0..kMaxLevel, x < 2^(z+1) and y < 2^z.
  bool valid() const;
  /// "z/x/y".
  std::string toString() const;
  friend bool operator==(const TerrainTileKey&, const TerrainTileKey&) = default;
};

/// A longitude/latitude rectangle in degrees (WGS 84); empty when west > east or south > north.
struct GeoRect {
  double west = 1, south = 1, east = -1, north = -1;

  bool empty() const { return west > east || south > north; }
  bool intersects(const GeoRect& o) const {
    return !empty() && !o.empty() && west <= o.east && o.west <= east && south <= o.north &&
           o.south <= north;
  }
  void extend(double lon, double lat);
  void extend(const GeoRect& o);
  friend bool operator==(const GeoRect&, const GeoRect&) = default;
};

/// Vertices per tile side (a tile is a regular 65 x 65 grid, 64 x 64 cells).
inline constexpr int kTerrainGridSize = 65;

/// The tile's rectangle; exact in the sense that neighbours compute their shared edge's
/// coordinate with the same expression. Precondition: key.valid().
GeoRect terrainTileRect(const TerrainTileKey& key);
/// Longitude of vertex column `i` (0..64, and -1 / 65 for the ring beyond) of tiles at level z in
/// tile column x: -180 + (64 x + i) * 180 / (64 * 2^z), the same value in both neighbours.
double terrainVertexLon(int z, std::uint32_t x, int i);
/// Latitude of vertex row `j` (0 south .. 64 north; -1 / 65 beyond), clamped to [-90, 90].
double terrainVertexLat(int z, std::uint32_t y, int j);
/// The distance between a tile's neighbouring vertices along a meridian, in metres, at level z:
/// pi * 6378137 / 2^z / 64 (the "vertex spacing" the level's resolution rules use).
double terrainVertexSpacing(int z);

/// Geodetic (lon, lat degrees; h metres above the WGS 84 ellipsoid) to ECEF metres.
Vec3d geodeticToEcef(double lonDeg, double latDeg, double h);

// ---- the layer: what a model offers as terrain --------------------------------------------------

/// An inclusive range of tiles of one level, as layer.json's `available` lists them.
struct TileRange {
  std::uint32_t startX = 0, startY = 0, endX = 0, endY = 0;
  friend bool operator==(const TileRange&, const TileRange&) = default;
};

/// Per patch with a defined vertex in its subtree: the lon/lat rectangle of the defined vertices
/// of the patch and its descendants. The layers of successive versions share one base map and
/// each holds only the entries changed since it, so a new version's copy costs its change; the
/// changes are folded into a new base once they pass 1/32 of it (compact()).
class Footprints {
 public:
  /// The patch's rectangle; null when it has none.
  const GeoRect* find(const PatchKey& key) const;
  void set(const PatchKey& key, const GeoRect& rect);
  void erase(const PatchKey& key);
  std::size_t size() const { return size_; }
  /// A new base of the base and the changes when the changes have grown past 1/32 of the base.
  void compact();

 private:
  std::shared_ptr<const std::map<PatchKey, GeoRect>> base_ =
      std::make_shared<const std::map<PatchKey, GeoRect>>();
  /// Since the base: a new rectangle, or nullopt where the base's entry is gone.
  std::map<PatchKey, std::optional<GeoRect>> changes_;
  std::size_t size_ = 0;
};

/// Whether a model can be served as terrain, and where at which levels. Built once per published
/// version of a model (buildTerrainLayer); immutable after.
struct TerrainLayer {
  /// False when the model is not a height field over the WGS 84 ellipsoid; `reason` says why.
  bool heightField = false;
  std::string reason;
  /// Exact, from the patches' data.
  Footprints footprint;
  /// The union of the footprints.
  GeoRect bounds;
  /// Per level 0..maxZoom: the available tiles (level 0: both root tiles always).
  std::vector<std::vector<TileRange>> available;
  int maxZoom = 0;
  /// True when a level would have listed over 2^20 tiles, so the list ends before it.
  bool capped = false;

  /// True when tile `key` lies in `available`.
  bool isAvailable(const TerrainTileKey& key) const;
};

/// Patch loader (as Model::GridLoader).
using TerrainGridLoader = std::function<std::shared_ptr<const PatchGrid>(const PatchInfo&)>;

/// Checks that the model is a height field over the ellipsoid (its root's defined vertices lie
/// 6200..6500 km from the origin, i.e. ECEF as vsm import makes from georeferenced rasters, and
/// its quads keep one orientation seen from above in lon/lat, i.e. the surface does not fold over
/// itself as a tunnel or an overhang would), then reads every patch once through `load` for its
/// footprint and derives availability:
///
///   tile (z, x, y), z >= 1, is available when it meets the footprint of a patch whose resolution
///   is at most 2 x terrainVertexSpacing(z)
///
/// (so the finest level a model offers is the last one whose vertices are at most twice as dense
/// as its finest data; levels are closed under parents because a patch that qualifies at z
/// qualifies at every coarser level). Level 0's two tiles are always available. A patch's
/// resolution, here and in terrainSources, is PatchInfo::resolution but at least half its
/// footprint's larger side over its cells (a guard for sparse patches), and a level that would
/// list over 2^20 tiles ends the list. A model that is not a height field gives heightField false
/// and nothing else. Throws what `load` throws, and
/// Error(InvalidArgument) for an empty model.
///
/// With `previous` (a layer built before and the model it was built from, such as the last
/// version's), only the patches that differ from `previous.model` (modelChange) and their
/// ancestors are read; every other footprint is the previous layer's. A level's availability then
/// changes only in the tiles a changed footprint meets: those are asked again (a descent through
/// the footprints meeting the tile), and the level's ranges are remade only when one of them
/// flips. A new version after a small merge so costs about its change (and a copy of the
/// footprints), not a read or a pass per level of every patch.
struct TerrainLayerBase {
  const Model& model;
  const TerrainLayer& layer;
  /// modelChange(model, the new model) when the caller knows it (a publish's record); null: it is
  /// computed.
  const ModelChange* change = nullptr;
};
///
/// Without `previous`, footprints `saved` by an earlier build (of this or an earlier version, read
/// from the model's directory) stand for every patch whose data they were saved for and whose
/// children's footprints were not read afresh: only the others are read (availability is then
/// derived in full, from metadata only).
TerrainLayer buildTerrainLayer(const Model& model, const TerrainGridLoader& load,
                               const TerrainLayerBase* previous = nullptr,
                               const SavedFootprints* saved = nullptr);

/// The patches tile `key` is sampled from, coarse to fine (the order they are painted in): from
/// the root down through patches whose footprint meets the tile (with its one-vertex ring), taking
/// a patch when its resolution is at most the level's vertex spacing or it has no children (the
/// finest the model holds), else descending to its children. Every point of the tile so gets the
/// coarsest surface at least as fine as the level warrants, never finer than the model holds.
/// Metadata only (no data is read): cheap enough for a network thread.
std::vector<PatchKey> terrainSources(const Model& model, const TerrainLayer& layer,
                                     const TerrainTileKey& key);

/// The patches a picture over `area` is sampled from, coarse to fine (sorted by key): from the root
/// down through patches whose footprint meets `area`, taking a patch when it has no children or
/// its resolution is at most `spacing` (metres), else descending. A negative spacing takes the
/// finest leaves only. Metadata only. terrainSources is this for a tile and its level.
std::vector<PatchKey> heightSources(const Model& model, const TerrainLayer& layer,
                                    const GeoRect& area, double spacing);

/// Heights of one tile on its 65 x 65 vertex grid plus a ring of one vertex beyond each edge
/// (67 x 67, so normals at the edges see the neighbours' surface and agree with them).
struct TerrainHeights {
  static constexpr int kSize = kTerrainGridSize + 2;
  TerrainTileKey key;
  /// Row-major, row 0 the ring south of the tile, column 0 the ring west of it: vertex (i, j) of
  /// the tile (i east, j north, 0..64) is at [(j + 1) * kSize + i + 1]. Metres above the
  /// ellipsoid; 0 where no source patch has a complete quad.
  std::vector<double> h;
  /// Tile vertices (not the ring) that got a height from the model.
  std::size_t covered = 0;

  double at(int i, int j) const {
    return h[static_cast<std::size_t>(j + 1) * kSize + static_cast<std::size_t>(i + 1)];
  }
};

/// Samples the tile from `sources` (terrainSources(); read through `load`): each patch's vertices
/// turned to lon/lat/height, each complete quad's two triangles rasterised into the 67 x 67 grid
/// (top_down.hpp) with barycentric interpolation of the height, coarser patches first and finer
/// ones over them. Vertices of quads that cannot reach the tile are not converted (blocks of the
/// patch grid are culled by the lon/lat of their corners). Throws what `load` throws.
TerrainHeights sampleTerrain(const Model& model, const std::vector<PatchKey>& sources,
                             const TerrainTileKey& key, const TerrainGridLoader& load);

/// What to put into an encoded tile besides the mesh.
struct QuantizedMeshOptions {
  /// Extension 1, "octvertexnormals".
  bool normals = false;
  /// Extension 4, "metadata": this JSON text when not empty.
  std::string metadata;
};

/// The tile as quantized-mesh-1.0 (little-endian; see README.md): header (centre and bounding
/// sphere of the ECEF vertices, min/max height, horizon occlusion point in ellipsoid-scaled
/// space), 65 x 65 vertices (u, v, height quantised to 0..32767, zig-zag delta encoded, in order
/// of first use by the triangles), two triangles per cell (counter-clockwise seen from above,
/// 16-bit high-water-mark encoded indices), the edge index lists (west and east south to north,
/// south and north west to east), then the extensions asked for.
std::vector<std::byte> encodeQuantizedMesh(const TerrainHeights& heights,
                                           const QuantizedMeshOptions& options = {});

/// The metadata extension's JSON for tile `key`: {"available": [[ranges of its children at level
/// z + 1 that are available]]} (empty list when none), consistent with layer.json.
std::string terrainMetadataJson(const TerrainLayer& layer, const TerrainTileKey& key);

/// Oct-encoding of a unit vector to two bytes, as CesiumJS's AttributeCompression.octEncode with
/// range 255; octDecode is its inverse (up to the quantisation).
std::array<std::uint8_t, 2> octEncode(const Vec3d& unit);
Vec3d octDecode(std::uint8_t x, std::uint8_t y);

}  // namespace vsm::core
