#pragma once

#include <cstdint>
#include <memory>
#include <string_view>

#include <nlohmann/json_fwd.hpp>

#include "server/http/router.hpp"

namespace vsm::core {
struct TerrainLayer;
}

namespace vsm::server::models {
class ModelRegistry;
class PatchData;
}  // namespace vsm::server::models

namespace vsm::server::api {

/// GET /v1/models/{m}/terrain/layer.json and GET /v1/models/{m}/terrain/{z}/{x}/{y}.terrain: the
/// quantized-mesh-1.0 terrain of every open model that is a height field over the WGS 84
/// ellipsoid, for CesiumJS's CesiumTerrainProvider (see proto/openapi.yaml, core/tiles/README.md).
/// The patch-data service `data` keeps each published version's layer (availability, footprints;
/// core::buildTerrainLayer, which reads every patch once), built on the CPU pool at its first use
/// and kept while the version is served, and samples and encodes a tile on the CPU pool, kept as
/// sent (gzipped or not) in the model's EncodedCache within the one budget; cached tiles and 304s
/// are answered on the network thread. `models` must outlive the router; a null `data` makes one
/// of their own.
void addTerrainRoutes(http::Router& router, models::ModelRegistry& models,
                      std::shared_ptr<models::PatchData> data = nullptr);

// ---- wire mapping, public for tests -----------------------------------------------------------

/// The extensions an Accept header asks for: "application/vnd.quantized-mesh;
/// extensions=octvertexnormals-metadata" (any order, any other extension ignored; the
/// deprecated name "vertexnormals" counts as octvertexnormals).
struct TerrainExtensions {
  bool normals = false;
  bool metadata = false;
};
TerrainExtensions parseTerrainAccept(std::string_view accept);

/// layer.json of a terrain layer of model version `modelVersion`: tilejson 2.1.0, format
/// quantized-mesh-1.0, version 1.0.0, scheme tms, projection EPSG:4326, bounds, tiles
/// ["{z}/{x}/{y}.terrain?v={modelVersion}"] (with "&rev=N" for a revision other than 0),
/// model_version, available, minzoom/maxzoom, extensions.
nlohmann::json terrainLayerJson(std::string_view id, const core::TerrainLayer& layer,
                                std::uint64_t modelVersion, std::uint64_t revision = 0);

}  // namespace vsm::server::api
