#include "server/api/terrain_routes.hpp"

#include <charconv>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/common/numbers.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "core/tiles/heights.hpp"
#include "core/tiles/quantized_mesh.hpp"
#include "core/tiles/terrain_rgb.hpp"
#include "server/api/etags.hpp"
#include "server/api/route_helpers.hpp"
#include "server/http/gzip.hpp"
#include "server/models/encoded_cache.hpp"
#include "server/models/model_registry.hpp"
#include "server/models/patch_data.hpp"

namespace vsm::server::api {

using core::Error;
using core::ErrorCode;
using nlohmann::json;

namespace {

/// As the 3D Tiles: revalidated (by ETag) after a minute. layer.json's tile URLs name the model
/// version ("?v=N") and a tile is answered only from that version (or 404), but a model directory
/// replaced by another of the same name starts its versions again, so not even those are
/// immutable.
constexpr std::string_view kTerrainCacheControl = http::cache_control::kMinute;
constexpr std::string_view kTerrainType = "application/vnd.quantized-mesh";

std::uint32_t parseTileNumber(std::string_view text, std::string_view what) {
  std::uint32_t value = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  if (text.empty() || text.size() > 10 || ec != std::errc() || end != text.data() + text.size()) {
    throw Error(ErrorCode::InvalidArgument, "tile " + std::string(what) +
                                                " must be a non-negative integer, not '" +
                                                std::string(text.substr(0, 32)) + "'");
  }
  return value;
}

/// The {z}/{x}/{y} of a tile route as a `Key` (core::TerrainTileKey or core::MercatorTileKey) of
/// the tiling scheme `scheme`, whose level z has 2^(z + columnShift) columns and 2^z rows. Throws
/// Error(InvalidArgument) for a part that is not a number, a level beyond Key::kMaxLevel, or a
/// tile outside the scheme.
template <typename Key>
Key parseTile(const http::Request& request, std::string_view scheme, int columnShift) {
  Key key;
  const std::uint32_t z = parseTileNumber(request.param("z"), "level z");
  key.x = parseTileNumber(request.param("x"), "column x");
  key.y = parseTileNumber(request.param("y"), "row y");
  if (z > static_cast<std::uint32_t>(Key::kMaxLevel)) {
    throw Error(ErrorCode::InvalidArgument,
                "tile level " + std::to_string(z) + " is beyond the deepest level of the " +
                    std::string(scheme) + " (" + std::to_string(Key::kMaxLevel) + ")");
  }
  key.z = static_cast<int>(z);
  if (!key.valid()) {
    throw Error(ErrorCode::InvalidArgument,
                "tile " + key.toString() + " is outside the " + std::string(scheme) + ": level " +
                    std::to_string(z) + " has x 0.." +
                    std::to_string((std::uint64_t{1} << (z + columnShift)) - 1) + " and y 0.." +
                    std::to_string((std::uint64_t{1} << z) - 1));
  }
  return key;
}

constexpr std::string_view kGeographicScheme = "geographic tiling scheme (EPSG:4326, TMS)";
constexpr std::string_view kMercatorScheme = "Web Mercator tiling scheme (EPSG:3857, XYZ)";

void requireHeightField(const std::string& id, const core::TerrainLayer& layer) {
  if (!layer.heightField) {
    throw Error(ErrorCode::NotFound, "model '" + id + "' has no terrain: " + layer.reason);
  }
}

http::Response getLayer(models::ModelRegistry& models, models::PatchData& data,
                        const http::Request& request) {
  const std::string& id = request.param("m");
  const auto [served, snapshot] = *tiledRead(models, request);
  const auto rev = request.queryParam("rev");
  const bool gzipped = http::acceptsGzip(request);
  const std::string etag =
      viewEtag(*snapshot, "terrain-" + std::string(kTerrainFormat) + (gzipped ? "-gz" : ""),
               rev ? "rev=" + std::to_string(snapshot->version) : "");
  if (http::ifNoneMatch(request, etag)) {
    http::Response response = http::notModified(etag, http::cache_control::kRevalidate);
    http::varyOnEncoding(response);
    return response;
  }
  const auto layer = data.terrainLayer(served, snapshot, models::Asker::Pool);
  requireHeightField(id, *layer);
  const auto build = [&] {
    return terrainLayerJson(id, *layer, snapshot->version, rev ? snapshot->version : 0);
  };
  http::Response response = gzipped ? gzippedJson(data, served,
                                                  rev ? GzippedDocument::TerrainLayerRevision
                                                      : GzippedDocument::TerrainLayer,
                                                  snapshot->version, build)
                                    : http::jsonResponse(200, build());
  http::varyOnEncoding(response);
  response.set("Cache-Control", std::string(http::cache_control::kRevalidate));
  response.set("ETag", etag);
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  return response;
}

/// GET .../terrain/{z}/{x}/{y}.terrain[?v=N][&rev=R]: with layer.json's `?v=`, the tile of that
/// version or 404 (versionedSnapshot): a tile is sampled from several patches and the layer's
/// availability, so only that very version answers it. On a network thread it answers only a 304
/// or a cached tile (nullopt otherwise); on the CPU pool it builds the layer if needed, samples
/// and encodes.
std::optional<http::Response> getTile(models::ModelRegistry& models, models::PatchData& data,
                                      const http::Request& request, bool onNetworkThread) {
  const models::Asker asker =
      onNetworkThread ? models::Asker::NetworkThread : models::Asker::PoolAfterNetwork;
  const std::string& id = request.param("m");
  const auto key = parseTile<core::TerrainTileKey>(request, kGeographicScheme, 1);
  const std::optional<TiledRead> read = tiledRead(models, request, onNetworkThread);
  if (!read) {
    return std::nullopt;
  }
  const auto& [served, snapshot] = *read;
  const auto layer = data.terrainLayer(served, snapshot, asker);
  if (layer == nullptr) {
    return std::nullopt;
  }
  requireHeightField(id, *layer);

  const std::vector<core::PatchKey> sources = core::terrainSources(*snapshot->model, *layer, key);
  const std::string* accept = request.header("accept");
  const TerrainExtensions extensions = parseTerrainAccept(accept ? *accept : "");
  const bool gzipped = http::acceptsGzip(request);
  // The metadata extension lists the children layer.json makes available: part of the content,
  // so part of the version (a few ranges at most; cheap enough for a network thread).
  const std::string metadata = extensions.metadata ? core::terrainMetadataJson(*layer, key) : "";
  const std::string variant = std::string(extensions.normals ? "n" : "") +
                              (extensions.metadata ? "m" + metadata : "") + (gzipped ? "-gz" : "");
  const std::string tile = key.toString();
  const std::uint64_t version = api::terrainVersion(tile, *snapshot->model, sources, variant);
  const std::string etag = terrainEtag(tile, version);
  if (http::ifNoneMatch(request, etag)) {
    http::Response response = http::notModified(etag, kTerrainCacheControl);
    response.set("Vary", "Accept-Encoding, Accept");
    return response;
  }

  models::PatchData::TerrainTile wanted;
  wanted.key = &key;
  wanted.sources = &sources;
  wanted.version = version;
  wanted.normals = extensions.normals;
  wanted.metadata = metadata;
  wanted.gzipped = gzipped;
  auto body = data.terrainTile(served, *snapshot, wanted, asker);
  if (body == nullptr) {
    return std::nullopt;
  }
  http::Response response;
  sendBody(response, std::move(body));
  response.contentType = std::string(kTerrainType);
  if (gzipped) {
    http::setGzipEncoded(response);
  }
  // Both the content coding and the extensions (from Accept) select the representation.
  response.set("Vary", "Accept-Encoding, Accept");
  response.set("Cache-Control", std::string(kTerrainCacheControl));
  response.set("ETag", etag);
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  return response;
}

// ---- terrain-RGB (MapLibre's raster-dem)
// ---------------------------------------------------------

constexpr std::string_view kDemCacheControl = kTerrainCacheControl;

/// What a terrain-RGB request asks for besides the tile: `?encoding=` (terrarium, the default, or
/// mapbox) and `?nodata=` (the height of pixels without data, 0 m by default).
struct DemQuery {
  core::DemEncoding encoding = core::DemEncoding::Terrarium;
  double nodataHeight = 0;

  std::string_view encodingName() const {
    return encoding == core::DemEncoding::Terrarium ? "terrarium" : "mapbox";
  }
  /// The query as the tiles' URLs carry it (empty for the defaults).
  std::string urlQuery() const {
    std::string q;
    if (encoding != core::DemEncoding::Terrarium) {
      q += "&encoding=" + std::string(encodingName());
    }
    if (nodataHeight != 0) {
      q += "&nodata=" + core::formatDouble(nodataHeight);
    }
    return q;
  }
};

DemQuery parseDemQuery(const http::Request& request) {
  DemQuery q;
  if (const auto encoding = request.queryParam("encoding")) {
    if (*encoding == "mapbox") {
      q.encoding = core::DemEncoding::Mapbox;
    } else if (*encoding != "terrarium") {
      throw Error(ErrorCode::InvalidArgument, "encoding must be 'terrarium' or 'mapbox', not '" +
                                                  encoding->substr(0, 40) + "'");
    }
  }
  if (const auto nodata = request.queryParam("nodata")) {
    const auto value = core::parseDouble(*nodata);
    const double lo = core::demEncodingMin(q.encoding), hi = core::demEncodingMax(q.encoding);
    if (!value || !(*value >= lo && *value <= hi)) {
      throw Error(ErrorCode::InvalidArgument,
                  "nodata must be a height from " + core::formatDouble(lo) + " to " +
                      core::formatDouble(hi) + " m (the " + std::string(q.encodingName()) +
                      " encoding's range), not '" + nodata->substr(0, 40) + "'");
    }
    q.nodataHeight = *value;
  }
  return q;
}

/// The Web Mercator projection's latitude limit (degrees).
constexpr double kMercatorMaxLatitude = 85.0511287798066;

/// GET .../terrain-rgb/tiles.json: the TileJSON a MapLibre `raster-dem` source takes as its `url`.
/// The tile URLs name the model version (`?v=N`, answered only from that version, as layer.json's)
/// and are path-absolute: a page of another origin gives the source its `tiles` itself.
http::Response getDemTileJson(models::ModelRegistry& models, models::PatchData& data,
                              const http::Request& request) {
  const std::string& id = request.param("m");
  const DemQuery query = parseDemQuery(request);
  const auto [served, snapshot] = *tiledRead(models, request);
  const auto rev = request.queryParam("rev");
  const std::string revQuery = rev ? "&rev=" + std::to_string(snapshot->version) : "";
  const std::string etag = viewEtag(*snapshot, "terrain-rgb-json", query.urlQuery() + revQuery);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, http::cache_control::kRevalidate);
  }
  const auto layer = data.terrainLayer(served, snapshot, models::Asker::Pool);
  requireHeightField(id, *layer);
  const core::GeoRect& b = layer->bounds;
  const double south = std::max(b.south, -kMercatorMaxLatitude);
  const double north = std::min(b.north, kMercatorMaxLatitude);
  // The deepest level is the one whose pixels are as fine as the finest data where the ground
  // pixels are largest, the latitude nearest the equator.
  const double nearestEquator = south > 0 ? south : (north < 0 ? north : 0.0);
  const int maxZoom =
      core::mercatorLevelFor(core::finestResolution(*snapshot->model, *layer, b), nearestEquator);
  const json body = {{"tilejson", "3.0.0"},
                     {"name", id},
                     {"description", "terrain-RGB heights of the vsm model '" + id +
                                         "' (metres above the WGS 84 ellipsoid)"},
                     {"version", "1.0.0"},
                     {"scheme", "xyz"},
                     {"tiles",
                      {"/v1/models/" + id + "/terrain-rgb/{z}/{x}/{y}.png?v=" +
                       std::to_string(snapshot->version) + query.urlQuery() + revQuery}},
                     {"minzoom", 0},
                     {"maxzoom", maxZoom},
                     {"bounds", {b.west, south, b.east, north}},
                     {"tileSize", core::kDemTileSize},
                     {"encoding", query.encodingName()},
                     {"nodata_height", query.nodataHeight},
                     {"height_reference", "ellipsoid (WGS 84)"},
                     {"model_version", snapshot->version}};
  http::Response response = http::jsonResponse(200, body);
  response.set("Cache-Control", std::string(http::cache_control::kRevalidate));
  response.set("ETag", etag);
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  return response;
}

/// GET .../terrain-rgb/{z}/{x}/{y}.png[?v=N][&rev=R][&encoding=][&nodata=]: a 256 x 256 RGB PNG of
/// the heights at its pixel centres, 404 for a tile the model's footprint does not meet. Tagged,
/// as the quantized-mesh tiles, by the versions of the patches it is sampled from: a merge
/// changes the tags of the tiles over the patches it rewrote and no others. On a network thread
/// it answers only a 304 or a cached tile (nullopt otherwise).
std::optional<http::Response> getDemTile(models::ModelRegistry& models, models::PatchData& data,
                                         const http::Request& request, bool onNetworkThread) {
  const models::Asker asker =
      onNetworkThread ? models::Asker::NetworkThread : models::Asker::PoolAfterNetwork;
  const std::string& id = request.param("m");
  const auto key = parseTile<core::MercatorTileKey>(request, kMercatorScheme, 0);
  const DemQuery query = parseDemQuery(request);
  const std::optional<TiledRead> read = tiledRead(models, request, onNetworkThread);
  if (!read) {
    return std::nullopt;
  }
  const auto& [served, snapshot] = *read;
  const auto layer = data.terrainLayer(served, snapshot, asker);
  if (layer == nullptr) {
    return std::nullopt;
  }
  requireHeightField(id, *layer);
  if (!core::mercatorTileRect(key).intersects(layer->bounds)) {
    throw Error(ErrorCode::NotFound,
                "terrain-RGB tile " + key.toString() + " does not meet the model '" + id + "'");
  }
  const std::vector<core::PatchKey> sources = core::demTileSources(*snapshot->model, *layer, key);
  const std::string tile = "rgb/" + key.toString();
  const std::uint64_t version =
      api::terrainVersion(tile, *snapshot->model, sources, query.urlQuery());
  const std::string etag = terrainEtag(tile, version);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kDemCacheControl);
  }
  models::PatchData::DemTile wanted;
  wanted.key = &key;
  wanted.sources = &sources;
  wanted.version = version;
  wanted.encoding = query.encoding;
  wanted.nodataHeight = query.nodataHeight;
  auto body = data.demTile(served, *snapshot, wanted, asker);
  if (body == nullptr) {
    return std::nullopt;
  }
  http::Response response;
  sendBody(response, std::move(body));
  response.contentType = "image/png";
  response.set("Cache-Control", std::string(kDemCacheControl));
  response.set("ETag", etag);
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  return response;
}

}  // namespace

TerrainExtensions parseTerrainAccept(std::string_view accept) {
  TerrainExtensions out;
  std::size_t start = 0;
  while (start <= accept.size()) {
    const std::size_t comma = std::min(accept.find(',', start), accept.size());
    const std::string_view range = http::trim(accept.substr(start, comma - start));
    start = comma + 1;
    const std::size_t semicolon = std::min(range.find(';'), range.size());
    if (!http::equalsIgnoreCase(http::trim(range.substr(0, semicolon)),
                                "application/vnd.quantized-mesh")) {
      continue;
    }
    std::string_view params = range.substr(semicolon);
    while (!params.empty()) {
      params.remove_prefix(1);  // ';'
      const std::size_t next = std::min(params.find(';'), params.size());
      const std::string_view param = http::trim(params.substr(0, next));
      params = params.substr(next);
      const std::size_t eq = param.find('=');
      if (eq == std::string_view::npos ||
          !http::equalsIgnoreCase(http::trim(param.substr(0, eq)), "extensions")) {
        continue;
      }
      std::string_view names = http::trim(param.substr(eq + 1));
      if (names.size() >= 2 && names.front() == '"' && names.back() == '"') {
        names = names.substr(1, names.size() - 2);
      }
      while (!names.empty()) {
        const std::size_t dash = std::min(names.find('-'), names.size());
        const std::string_view name = names.substr(0, dash);
        if (name == "octvertexnormals" || name == "vertexnormals") {
          out.normals = true;
        } else if (name == "metadata") {
          out.metadata = true;
        }
        names = names.substr(std::min(dash + 1, names.size()));
      }
    }
  }
  return out;
}

json terrainLayerJson(std::string_view id, const core::TerrainLayer& layer,
                      std::uint64_t modelVersion, std::uint64_t revision) {
  json available = json::array();
  for (const auto& level : layer.available) {
    json ranges = json::array();
    for (const core::TileRange& r : level) {
      ranges.push_back(
          {{"startX", r.startX}, {"startY", r.startY}, {"endX", r.endX}, {"endY", r.endY}});
    }
    available.push_back(std::move(ranges));
  }
  // The model version itself, not CesiumJS's "{version}" template (which it fills with the
  // "version" field below, the same for every model version): the tile route answers "?v=N" only
  // from version N, so a node that has not followed N yet answers 404 rather than older tiles.
  std::string tiles = "{z}/{x}/{y}.terrain?v=" + std::to_string(modelVersion);
  if (revision != 0) {
    tiles += "&rev=" + std::to_string(revision);
  }
  const core::GeoRect& b = layer.bounds;
  return {{"tilejson", "2.1.0"},
          {"name", id},
          {"description", "quantized-mesh terrain of the vsm model '" + std::string(id) + "'"},
          {"version", "1.0.0"},
          {"format", "quantized-mesh-1.0"},
          {"attribution", ""},
          {"scheme", "tms"},
          {"projection", "EPSG:4326"},
          {"bounds", b.empty() ? json::array({-180.0, -90.0, 180.0, 90.0})
                               : json::array({b.west, b.south, b.east, b.north})},
          {"tiles", json::array({tiles})},
          {"model_version", modelVersion},
          {"minzoom", 0},
          {"maxzoom", layer.maxZoom},
          {"available", std::move(available)},
          {"extensions", json::array({"octvertexnormals", "metadata"})},
          // CesiumJS reads availability from the tiles' metadata extension when this is set (each
          // tile names its available children), and must: with `available` alone it fails on
          // every tile that carries the extension (CesiumTerrainProvider has no
          // availabilityTilesLoaded then). `available` stays, whole, for other clients.
          {"metadataAvailability", 1}};
}

void addTerrainRoutes(http::Router& router, models::ModelRegistry& models,
                      std::shared_ptr<models::PatchData> data) {
  if (data == nullptr) {
    data = std::make_shared<models::PatchData>();
  }
  router.add(
      http::Method::Get, "/v1/models/{m}/terrain/layer.json",
      [&models, data](const http::Request& request) { return getLayer(models, *data, request); });
  router.add(
      http::Method::Get, "/v1/models/{m}/terrain/{z}/{x}/{y}.terrain",
      [&models, data](const http::Request& request) {
        return *getTile(models, *data, request, false);
      },
      [&models, data](const http::Request& request) {
        return getTile(models, *data, request, true);
      });
  router.add(http::Method::Get, "/v1/models/{m}/terrain-rgb/tiles.json",
             [&models, data](const http::Request& request) {
               return getDemTileJson(models, *data, request);
             });
  router.add(
      http::Method::Get, "/v1/models/{m}/terrain-rgb/{z}/{x}/{y}.png",
      [&models, data](const http::Request& request) {
        return *getDemTile(models, *data, request, false);
      },
      [&models, data](const http::Request& request) {
        return getDemTile(models, *data, request, true);
      });
}

}  // namespace vsm::server::api
