#pragma once

#include <memory>
#include <string>
#include <string_view>

#include <nlohmann/json_fwd.hpp>

#include "server/api/etags.hpp"
#include "server/http/router.hpp"

namespace vsm::core {
class Model;
struct ModelSnapshot;
struct PatchInfo;
struct TileNode;
}  // namespace vsm::core

namespace vsm::server::models {
class ModelRegistry;
class PatchData;
}  // namespace vsm::server::models

namespace vsm::server::api {

/// GET /v1/models/{m}/3dtiles/tileset.json and GET /v1/models/{m}/3dtiles/{p}.glb: the OGC 3D
/// Tiles 1.1 view of every open model (see proto/openapi.yaml). The tileset is built from one
/// snapshot's metadata; a GLB is found or made by the patch-data service `data` (encoded from the
/// patch's data, read through the cache on the CPU pool, and kept in the model's EncodedCache, one
/// budget with the data), from which repeated requests are answered on the network thread.
/// `models` must outlive the router; a null `data` makes one of their own.
void addTilesRoutes(http::Router& router, models::ModelRegistry& models,
                    std::shared_ptr<models::PatchData> data = nullptr);

// ---- wire mapping, public for tests -----------------------------------------------------------

/// The tileset.json of a tile tree (core::buildTileTree): asset.version "1.1", per tile a
/// transform (column-major 4x4 translating by the tile's centre minus its parent's; the root's by
/// its centre, in ECEF for models imported from georeferenced rasters), boundingVolume.box
/// relative to the tile's centre, geometricError, refine "REPLACE", content.uri "{key}.glb"
/// (relative to the tileset's URL) and children. With `model` (the one the tree was built from),
/// each URI names the patch's version, "{key}.glb?v={version}": the version of the publish that
/// wrote the patch, in which it is exactly as in this one (model version `modelVersion`). The GLB
/// route answers that URI with the patch as in that version or with 404 (never with another
/// version's bytes), so neither a node that has not followed this version yet nor a browser or
/// CDN cache mixes a tile of one version of the model with a tileset of another; and a URI stays
/// the same (and cached) across publishes that leave its patch alone. A `revision` other than 0
/// (the tileset of ?rev=N) is added to each URI ("&rev=N"), so the tiles come from that revision.
/// `compressedContent` false (the tileset of ?compress=none) adds "compress=none" to each URI
/// (after '?' or '&'), which names the uncompressed GLBs; true names the default, compressed
/// ones. A `modelVersion` other than 0 is named as asset.extras.model_version.
///
/// An external tile (TileNode::external) has no children; its content.uri is
/// "tileset.json?root={key}" with "&v={modelVersion}", "&rev=", "&levels={levels}" (when
/// `levels` is not 0) and "&compress=none" as this document has them: its subtree's tileset, of
/// the same version. A tree whose root is not the model's (an external tileset) gives its root a
/// zero translation: 3D Tiles applies it after the transform of the tile that names the document,
/// which places it.
nlohmann::json tilesetJson(const core::TileNode& root, std::string_view tilesetVersion,
                           const core::Model* model = nullptr, std::uint64_t revision = 0,
                           bool compressedContent = true, std::uint64_t modelVersion = 0,
                           int levels = 0);

}  // namespace vsm::server::api
