#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/grid/geometry.hpp"
#include "core/pyramid/patch_key.hpp"
#include "server/models/encoded_cache.hpp"
#include "server/models/model_registry.hpp"

namespace vsm::core {
class PatchGrid;
struct ModelSnapshot;
struct PatchInfo;
struct PatchKey;
struct TerrainLayer;
struct TileNode;
struct TerrainTileKey;
struct MercatorTileKey;
enum class DemEncoding : std::uint8_t;
enum class GlbCompression : unsigned char;
}  // namespace vsm::core

namespace vsm::server::models {

class Retired;
class TerrainLayers;
class TileTrees;

/// Who asks the patch-data service, which decides whether it may block. The one rule of the
/// server's two kinds of threads (server/README.md): a network thread never reads the disk or
/// encodes; it answers from the budget or hands the request to the CPU pool, which makes.
enum class Asker : std::uint8_t {
  /// A network thread (a route's inline handler): look in the budget only. A miss is counted and
  /// answered with null (or nullopt), and the route returns nullopt so the pool runs it again.
  NetworkThread,
  /// The CPU pool after a network thread's look missed: look again (that miss was counted, so
  /// this look counts none), else make the body and put it in the budget.
  PoolAfterNetwork,
  /// The CPU pool with no look before (a route without an inline handler): look (a miss is
  /// counted), else make and put.
  Pool,
};

/// The patch-data service: every encoded body the routes answer with (positions, texture
/// coordinates, texture PNG, GLB, quantized-mesh terrain tiles, model-wide gzipped JSON) and the
/// terrain layers, each found in the model's EncodedCache (the one memory budget) or made from the
/// model's data and put there. It is the only part of the server that reads a model's files
/// (core/opc through the model's directory) or LiveModel's patch data for a response; the routes
/// (server/api) parse, ask it and answer.
///
/// Every call takes the model as served (ModelRegistry::getServed: the LiveModel and its
/// EncodedCache of the same opening) and the snapshot and patch the route resolved (?v=, ?rev=).
/// With Asker::NetworkThread a call never blocks and returns null (nullopt) when the body is not
/// in the budget; otherwise it makes what is missing. What it returns holds the body (pinned in
/// the budget) for the length of the response. Making throws core::Error(ResourceExhausted) when
/// the budget is full of pinned data, and the store's errors.
///
/// Thread-safe. One per daemon (Application), shared by the model, tiles and terrain routes.
class PatchData {
 public:
  PatchData();
  ~PatchData();
  PatchData(const PatchData&) = delete;
  PatchData& operator=(const PatchData&) = delete;

  /// A patch's positions: its stored file held open for sendfile(2) when the file is the full
  /// grid as V3f, else the full-grid .aara encoded once. `local2global` is the matrix the
  /// X-VSM-Local2Global header names (the stored file's, or the one the encoding re-based to).
  struct Positions {
    std::shared_ptr<const EncodedCache::File> file;  ///< or
    std::shared_ptr<const EncodedCache::Body> body;
    std::string local2global;
  };
  /// nullopt on a network thread when neither the open file nor an encoding is in the budget
  /// (one miss counted for both).
  std::optional<Positions> positions(const ModelRegistry::Served& served,
                                     const core::ModelSnapshot& snapshot,
                                     const core::PatchInfo& info, Asker asker) const;

  /// The texture coordinates file (.aara) as stored, held open for sendfile(2). Null on a network
  /// thread when not held. Throws Error(ResourceExhausted) while every file the cache may hold is
  /// being sent.
  std::shared_ptr<const EncodedCache::File> coordinates(const ModelRegistry::Served& served,
                                                        const core::PatchInfo& info,
                                                        Asker asker) const;

  /// The texture tile as PNG. Null on a network thread when not cached.
  std::shared_ptr<const EncodedCache::Body> texturePng(const ModelRegistry::Served& served,
                                                       const core::PatchInfo& info,
                                                       Asker asker) const;

  /// The 3D Tiles GLB of a patch (`compression` picks the encoding: Encoding::GlbMeshopt or
  /// Encoding::Glb), with its texture when it has one. Null on a network thread when not cached.
  std::shared_ptr<const EncodedCache::Body> glb(const ModelRegistry::Served& served,
                                                const core::ModelSnapshot& snapshot,
                                                const core::PatchInfo& info,
                                                core::GlbCompression compression,
                                                Asker asker) const;

  /// The terrain layer of `snapshot` (availability, footprints), built once per published
  /// version and kept while the version is served; requests that need it meanwhile wait for the
  /// build. Null on a network thread when not built yet.
  std::shared_ptr<const core::TerrainLayer> terrainLayer(
      const ModelRegistry::Served& served,
      const std::shared_ptr<const core::ModelSnapshot>& snapshot, Asker asker);

  /// The tile tree (core::buildTileTree) of `snapshot` from the model's root, `levels` deep:
  /// metadata only, so made on the caller's thread. The last one made for a model (by its
  /// directory) and its levels is kept as the base of the next version's, which then walks only
  /// the subtrees that changed (core::TileTreeBase).
  std::shared_ptr<const core::TileNode> rootTileTree(const ModelRegistry::Served& served,
                                                     const core::ModelSnapshot& snapshot,
                                                     int levels) const;

  /// Releases the layers and tile trees replaced by newer versions' since the last call, and the
  /// model metadata they held: the housekeeping's work (the main thread), so that no request pays
  /// for freeing a version's metadata.
  void releaseRetired();

  /// Patch grids of `snapshot` through the patch cache (LiveModel::positions): what the height
  /// sampler (core/tiles/heights.hpp: the terrain tiles, point and profile queries, coverages)
  /// reads. Blocks on the disk: the CPU pool only. The loader holds `served` and `snapshot` by
  /// reference: it must not outlive them.
  std::function<std::shared_ptr<const core::PatchGrid>(const core::PatchInfo&)> gridLoader(
      const ModelRegistry::Served& served, const core::ModelSnapshot& snapshot) const;

  /// What a quantized-mesh tile is made of, as the route resolved it.
  struct TerrainTile {
    const core::TerrainTileKey* key = nullptr;
    /// The patches it samples (core::terrainSources) and its content version over them
    /// (api::terrainVersion: sources, extensions, coding).
    const std::vector<core::PatchKey>* sources = nullptr;
    std::uint64_t version = 0;
    bool normals = false;
    /// The metadata extension's JSON, empty without it.
    std::string metadata;
    /// Kept as sent: gzipped or not.
    bool gzipped = false;
  };
  /// The tile, sampled from `tile.sources` of `snapshot` and encoded. Null on a network thread
  /// when not cached.
  std::shared_ptr<const EncodedCache::Body> terrainTile(const ModelRegistry::Served& served,
                                                        const core::ModelSnapshot& snapshot,
                                                        const TerrainTile& tile, Asker asker) const;

  /// What a terrain-RGB tile is made of, as the route resolved it.
  struct DemTile {
    const core::MercatorTileKey* key = nullptr;
    /// The patches it samples (core::demTileSources) and its content version over them
    /// (api::terrainVersion: sources, encoding, no-data height).
    const std::vector<core::PatchKey>* sources = nullptr;
    std::uint64_t version = 0;
    core::DemEncoding encoding{};
    double nodataHeight = 0;
  };
  /// The tile, sampled from `tile.sources` of `snapshot` and encoded as an RGB PNG. Null on a
  /// network thread when not cached.
  std::shared_ptr<const EncodedCache::Body> demTile(const ModelRegistry::Served& served,
                                                    const core::ModelSnapshot& snapshot,
                                                    const DemTile& tile, Asker asker) const;

  /// A model-wide JSON document gzipped (Encoding::JsonGzip): made once per (`variant`, snapshot
  /// `version`) from build().dump(), on the pool only (Asker::Pool).
  std::shared_ptr<const EncodedCache::Body> gzippedJson(
      const ModelRegistry::Served& served, std::uint8_t variant, std::uint64_t version,
      const std::function<std::string()>& build) const;

 private:
  std::unique_ptr<Retired> retired_;  // before the users that hold it
  std::unique_ptr<TerrainLayers> layers_;
  std::unique_ptr<TileTrees> trees_;
};

/// 16 numbers, row-major, comma-separated, shortest round-trip form ("1,0,0,12.5,..."): the
/// X-VSM-Local2Global header of positions (Positions::local2global).
std::string matrixText(const core::Mat4d& m);

}  // namespace vsm::server::models
