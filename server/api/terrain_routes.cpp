#include "server/api/terrain_routes.hpp"

#include <charconv>
#include <chrono>
#include <exception>
#include <future>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "core/tiles/quantized_mesh.hpp"
#include "server/api/etags.hpp"
#include "server/api/model_routes.hpp"
#include "server/http/gzip.hpp"
#include "server/models/encoded_cache.hpp"
#include "server/models/model_registry.hpp"

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

/// The terrain layers of the published versions being served, built once per version: the first
/// request that needs a version's layer builds it, requests that need it meanwhile wait for that
/// build (on the CPU pool; network threads only look), and a failed build is forgotten so that the
/// next request tries again.
class TerrainLayers {
 public:
  using Layer = std::shared_ptr<const core::TerrainLayer>;

  /// The layer of `snapshot` when built already, else null. Never blocks (network threads).
  Layer find(const std::shared_ptr<const core::ModelSnapshot>& snapshot) const {
    std::shared_future<Layer> building;
    {
      const std::lock_guard lock(mutex_);
      const auto it = layers_.find(snapshot.get());
      if (it == layers_.end() || it->second.snapshot.lock() != snapshot) {
        return nullptr;
      }
      building = it->second.layer;
    }
    if (building.wait_for(std::chrono::seconds(0)) != std::future_status::ready) {
      return nullptr;
    }
    try {
      return building.get();
    } catch (...) {
      return nullptr;  // the request that built it reports the error
    }
  }

  /// The layer of `snapshot`, built (reading every patch of it through the cache) when missing,
  /// or waited for while another request builds it. Throws what the build throws.
  Layer get(core::LiveModel& live, const std::shared_ptr<const core::ModelSnapshot>& snapshot) {
    std::promise<Layer> promise;
    std::shared_future<Layer> building;
    {
      const std::lock_guard lock(mutex_);
      // Forget the layers of versions no longer served (their snapshots are gone).
      std::erase_if(layers_, [](const auto& entry) { return entry.second.snapshot.expired(); });
      auto& entry = layers_[snapshot.get()];
      if (entry.snapshot.lock() == snapshot) {
        building = entry.layer;
      } else {
        entry = {snapshot, promise.get_future().share()};
      }
    }
    if (building.valid()) {
      return building.get();  // no lock held while waiting
    }
    try {
      const auto start = std::chrono::steady_clock::now();
      auto layer = std::make_shared<const core::TerrainLayer>(
          core::buildTerrainLayer(*snapshot->model, [&](const core::PatchInfo& info) {
            return live.positions(*snapshot, info.key).get<core::PatchGrid>();
          }));
      core::log::info(
          "model=" + live.name() + " terrain layer of version " +
          std::to_string(snapshot->version) + ": " +
          (layer->heightField ? "levels 0.." + std::to_string(layer->maxZoom) : "no height field") +
          ", " +
          std::to_string(std::chrono::duration_cast<std::chrono::milliseconds>(
                             std::chrono::steady_clock::now() - start)
                             .count()) +
          " ms");
      promise.set_value(layer);
      return layer;
    } catch (...) {
      promise.set_exception(std::current_exception());
      const std::lock_guard lock(mutex_);
      if (const auto it = layers_.find(snapshot.get());
          it != layers_.end() && it->second.snapshot.lock() == snapshot) {
        layers_.erase(it);
      }
      throw;
    }
  }

 private:
  struct Entry {
    std::weak_ptr<const core::ModelSnapshot> snapshot;  // the key's owner, to detect reuse
    std::shared_future<Layer> layer;                    // ready once built
  };
  mutable std::mutex mutex_;  // guards layers_ (the map; layers are immutable once built)
  std::map<const core::ModelSnapshot*, Entry> layers_;
};

std::uint32_t parseTileNumber(std::string_view text, std::string_view what) {
  std::uint32_t value = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  if (text.empty() || text.size() > 10 || ec != std::errc() || end != text.data() + text.size()) {
    throw Error(ErrorCode::InvalidArgument, "terrain tile " + std::string(what) +
                                                " must be a non-negative integer, not '" +
                                                std::string(text.substr(0, 32)) + "'");
  }
  return value;
}

core::TerrainTileKey parseTile(const http::Request& request) {
  core::TerrainTileKey key;
  const std::uint32_t z = parseTileNumber(request.param("z"), "level z");
  key.x = parseTileNumber(request.param("x"), "column x");
  key.y = parseTileNumber(request.param("y"), "row y");
  if (z > static_cast<std::uint32_t>(core::TerrainTileKey::kMaxLevel)) {
    throw Error(ErrorCode::InvalidArgument,
                "terrain tile level " + std::to_string(z) + " is outside the tiling scheme (0.." +
                    std::to_string(core::TerrainTileKey::kMaxLevel) + ")");
  }
  key.z = static_cast<int>(z);
  if (!key.valid()) {
    throw Error(ErrorCode::InvalidArgument,
                "terrain tile " + key.toString() +
                    " is outside the geographic tiling scheme (EPSG:4326, TMS): level " +
                    std::to_string(z) + " has x 0.." + std::to_string((std::uint64_t{2} << z) - 1) +
                    " and y 0.." + std::to_string((std::uint64_t{1} << z) - 1));
  }
  return key;
}

void requireHeightField(const std::string& id, const core::TerrainLayer& layer) {
  if (!layer.heightField) {
    throw Error(ErrorCode::NotFound, "model '" + id + "' has no terrain: " + layer.reason);
  }
}

http::Response getLayer(models::ModelRegistry& models, TerrainLayers& layers,
                        const http::Request& request) {
  const std::string& id = request.param("m");
  const models::ModelRegistry::Served served = models.getServed(id);
  const auto snapshot = versionedSnapshot(*served.live, request);
  if (snapshot->model->empty()) {
    throw Error(ErrorCode::NotFound, "model '" + id + "' has no patches");
  }
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
  const auto layer = layers.get(*served.live, snapshot);
  requireHeightField(id, *layer);
  const auto build = [&] {
    return terrainLayerJson(id, *layer, snapshot->version, rev ? snapshot->version : 0);
  };
  http::Response response = gzipped ? gzippedJson(*served.encoded,
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
std::optional<http::Response> getTile(models::ModelRegistry& models, TerrainLayers& layers,
                                      const http::Request& request, bool onNetworkThread) {
  const std::string& id = request.param("m");
  const core::TerrainTileKey key = parseTile(request);
  const models::ModelRegistry::Served served = models.getServed(id);
  const auto snapshot = versionedSnapshot(*served.live, request, onNetworkThread);
  if (snapshot == nullptr) {
    return std::nullopt;
  }
  if (snapshot->model->empty()) {
    throw Error(ErrorCode::NotFound, "model '" + id + "' has no patches");
  }
  const auto layer = onNetworkThread ? layers.find(snapshot) : layers.get(*served.live, snapshot);
  if (layer == nullptr) {
    return std::nullopt;
  }
  requireHeightField(id, *layer);

  const std::vector<core::PatchKey> sources = core::terrainSources(*snapshot->model, *layer, key);
  std::vector<const core::PatchInfo*> infos;
  infos.reserve(sources.size());
  for (const core::PatchKey& source : sources) {
    infos.push_back(&snapshot->model->at(source));
  }
  const std::string* accept = request.header("accept");
  const TerrainExtensions extensions = parseTerrainAccept(accept ? *accept : "");
  const bool gzipped = http::acceptsGzip(request);
  // The metadata extension lists the children layer.json makes available: part of the content,
  // so part of the version (a few ranges at most; cheap enough for a network thread).
  const std::string metadata = extensions.metadata ? core::terrainMetadataJson(*layer, key) : "";
  const std::string variant = std::string(extensions.normals ? "n" : "") +
                              (extensions.metadata ? "m" + metadata : "") + (gzipped ? "-gz" : "");
  const std::string tile = key.toString();
  const std::uint64_t version = api::terrainVersion(tile, infos, variant);
  const std::string etag = terrainEtag(tile, version);
  if (http::ifNoneMatch(request, etag)) {
    http::Response response = http::notModified(etag, kTerrainCacheControl);
    response.set("Vary", "Accept-Encoding, Accept");
    return response;
  }

  // Cached under the tile as a key (z, x, y fit a PatchKey's fields) and its content version.
  const core::PatchKey cacheKey{key.z, key.x, key.y};
  auto body = served.encoded->find(cacheKey, version, models::Encoding::Terrain, onNetworkThread);
  if (body == nullptr) {
    if (onNetworkThread) {
      return std::nullopt;
    }
    const core::TerrainHeights heights =
        core::sampleTerrain(*snapshot->model, sources, key, [&](const core::PatchInfo& info) {
          return served.live->positions(*snapshot, info.key).get<core::PatchGrid>();
        });
    core::QuantizedMeshOptions options;
    options.normals = extensions.normals;
    options.metadata = metadata;
    std::vector<std::byte> bytes = core::encodeQuantizedMesh(heights, options);
    if (gzipped) {
      const std::string packed =
          http::gzip(std::string_view(reinterpret_cast<const char*>(bytes.data()), bytes.size()));
      bytes.assign(reinterpret_cast<const std::byte*>(packed.data()),
                   reinterpret_cast<const std::byte*>(packed.data()) + packed.size());
    }
    // Throws ResourceExhausted (503, retry) when the budget is full of pinned data.
    body = served.encoded->put(cacheKey, version, models::Encoding::Terrain, std::move(bytes));
  }
  http::Response response;
  response.sharedBody = body->text();
  response.bodyOwner = std::move(body);
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

void addTerrainRoutes(http::Router& router, models::ModelRegistry& models) {
  // Lives as long as the routes (the router owns the handlers that share it).
  auto layers = std::make_shared<TerrainLayers>();
  router.add(http::Method::Get, "/v1/models/{m}/terrain/layer.json",
             [&models, layers](const http::Request& request) {
               return getLayer(models, *layers, request);
             });
  router.add(
      http::Method::Get, "/v1/models/{m}/terrain/{z}/{x}/{y}.terrain",
      [&models, layers](const http::Request& request) {
        return *getTile(models, *layers, request, false);
      },
      [&models, layers](const http::Request& request) {
        return getTile(models, *layers, request, true);
      });
}

}  // namespace vsm::server::api
