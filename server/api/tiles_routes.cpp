#include "server/api/tiles_routes.hpp"

#include <cstddef>
#include <memory>
#include <optional>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "core/tiles/glb.hpp"
#include "core/tiles/tile_tree.hpp"
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

/// As patch data (model_routes.cpp): revalidated after a minute. A GLB URL with `?v=` is answered
/// only with that version's bytes (versionedPatch), but a model directory replaced by another
/// model of the same name starts its versions again, so not even those are immutable.
constexpr std::string_view kTileCacheControl = http::cache_control::kMinute;

constexpr std::string_view kGlbType = "model/gltf-binary";

/// A column-major 4x4 translation, as 3D Tiles' tile.transform.
json translationJson(const core::Vec3d& t) {
  return json::array(
      {1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, t.x, t.y, t.z, 1.0});
}

/// "{key}.glb", with "?v={patch version}" when `model` is given (the version that wrote the
/// patch: the GLB route answers it with the patch as in that version, or 404), "&rev={revision}"
/// for a revision other than 0, and "compress=none" (after '?' or '&') for uncompressed content.
std::string contentUri(const core::TileNode& node, const core::Model* model, std::uint64_t revision,
                       bool compressedContent) {
  std::string uri = node.key.toString() + ".glb";
  if (model != nullptr) {
    uri += "?v=" + std::to_string(node.version);
    if (revision != 0) {
      uri += "&rev=" + std::to_string(revision);
    }
  }
  if (!compressedContent) {
    uri += model != nullptr ? "&compress=none" : "?compress=none";
  }
  return uri;
}

/// What a tileset's URIs name besides the tile: see tilesetJson().
struct UriParts {
  const core::Model* model = nullptr;
  std::uint64_t revision = 0;
  bool compressedContent = true;
  std::uint64_t modelVersion = 0;
  int levels = 0;
};

/// "tileset.json?root={key}" for an external tile, with the model version ("&v="), revision,
/// levels and "compress=none" the document's own URI had, so its subtree comes from the same
/// version and looks the same.
std::string externalUri(const core::PatchKey& key, const UriParts& parts) {
  std::string uri = "tileset.json?root=" + key.toString();
  if (parts.modelVersion != 0) {
    uri += "&v=" + std::to_string(parts.modelVersion);
  }
  if (parts.revision != 0) {
    uri += "&rev=" + std::to_string(parts.revision);
  }
  if (parts.levels != 0) {
    uri += "&levels=" + std::to_string(parts.levels);
  }
  if (!parts.compressedContent) {
    uri += "&compress=none";
  }
  return uri;
}

json tileJson(const core::TileNode& node, const core::Vec3d& parentCentre, const UriParts& parts) {
  const core::Vec3d c = node.box.center() - node.centre;
  const core::Vec3d half = node.box.size() * 0.5;
  json tile = {{"transform", translationJson(node.centre - parentCentre)},
               {"boundingVolume",
                {{"box", json::array({c.x, c.y, c.z, half.x, 0.0, 0.0, 0.0, half.y, 0.0, 0.0, 0.0,
                                      half.z})}}},
               {"geometricError", node.geometricError},
               {"refine", "REPLACE"}};
  tile["content"] = {{"uri", node.external ? externalUri(node.key, parts)
                                           : contentUri(node, parts.model, parts.revision,
                                                        parts.compressedContent)}};
  if (!node.children.empty()) {
    json children = json::array();
    for (const core::TileNode& child : node.children) {
      children.push_back(tileJson(child, node.centre, parts));
    }
    tile["children"] = std::move(children);
  }
  return tile;
}

http::Response withTileCache(http::Response response, std::string_view etag) {
  response.set("Cache-Control", std::string(kTileCacheControl));
  response.set("ETag", std::string(etag));
  return response;
}

/// The GLB encoding a request's `compress` asks for: absent or "meshopt" the compressed one (the
/// default), "none" float32. Throws Error(InvalidArgument) for anything else.
core::GlbCompression requestedCompression(const http::Request& request) {
  const std::optional<std::string> value = request.queryParam("compress");
  if (!value || *value == "meshopt") {
    return core::GlbCompression::Meshopt;
  }
  if (*value == "none") {
    return core::GlbCompression::None;
  }
  throw Error(
      ErrorCode::InvalidArgument,
      "compress must be 'meshopt' (the default) or 'none', not '" + value->substr(0, 32) + "'");
}

/// Levels of tiles in one tileset document by default: the tiles of five depths (up to 341), and
/// up to 1024 external tiles naming the documents of the depth below. A client that walks the
/// tree gets 1,365 tiles in the first document, as from a whole model of 1,365 patches, whatever
/// the model's size.
constexpr int kTilesetLevels = 5;
constexpr int kMaxTilesetLevels = 16;

/// GET /v1/models/{m}/3dtiles/tileset.json[?root=d_x_y][&levels=L][&compress=none][&rev=N][&v=V]:
/// the tiles of `levels` depths from patch `root` (the model's root by default), the patches
/// below them as external tilesets (core::buildTileTree). A client that accepts gzip gets the
/// model root's document in the default levels gzipped from the model's EncodedCache (made once
/// per snapshot version and variant: content compression, revision URIs), within the budget;
/// a subtree's, or other levels', is small and gzipped per request. Every answer carries
/// "Vary: Accept-Encoding" and its own ETag.
http::Response getTileset(models::ModelRegistry& models, const models::PatchData& data,
                          const http::Request& request) {
  const auto [served, snapshot] = *tiledRead(models, request);
  const bool compressedContent = requestedCompression(request) == core::GlbCompression::Meshopt;
  const bool revisionUris = request.queryParam("rev").has_value();
  const bool gzipped = http::acceptsGzip(request);
  const std::optional<std::string> rootText = request.queryParam("root");
  const core::PatchKey root =
      rootText ? parseKey(*rootText, "root must be a patch key depth_x_y (e.g. 2_1_3)")
               : core::PatchKey::root();
  const int levels = intQuery(request, "levels", kTilesetLevels, 1, kMaxTilesetLevels);
  const bool wholeDefault = !rootText && levels == kTilesetLevels;
  // The representation: content URIs (compressed or "raw", with "&rev=" or not), the part of the
  // tree and the encoding.
  std::string variant = compressedContent ? "" : "raw";
  for (const auto& [on, part] :
       {std::pair{revisionUris, std::string("rev")},
        std::pair{rootText.has_value(), "root" + root.toString()},
        std::pair{levels != kTilesetLevels, "levels" + std::to_string(levels)},
        std::pair{gzipped, std::string("gz")}}) {
    if (on) {
      variant += (variant.empty() ? "" : "-") + part;
    }
  }
  const std::string etag = tilesetEtag(*snapshot, variant);
  if (http::ifNoneMatch(request, etag)) {
    http::Response response = http::notModified(etag, kTileCacheControl);
    http::varyOnEncoding(response);
    return response;
  }
  const auto build = [&] {
    // The model root's default document by the change since the last version's (every viewer
    // asks for it after each publish); a subtree's walks that subtree alone.
    const std::shared_ptr<const core::TileNode> tree =
        wholeDefault ? data.rootTileTree(served, *snapshot, levels)
                     : std::make_shared<const core::TileNode>(
                           core::buildTileTree(*snapshot->model, root, levels));
    return tilesetJson(*tree, http::opaqueOf(modelEtag(*snapshot)), snapshot->model.get(),
                       revisionUris ? snapshot->version : 0, compressedContent, snapshot->version,
                       levels == kTilesetLevels ? 0 : levels);
  };
  const GzippedDocument document =
      compressedContent
          ? (revisionUris ? GzippedDocument::TilesetRevision : GzippedDocument::Tileset)
          : (revisionUris ? GzippedDocument::TilesetUncompressedRevision
                          : GzippedDocument::TilesetUncompressed);
  http::Response response;
  if (gzipped && wholeDefault) {
    response = gzippedJson(data, served, document, snapshot->version, build);
  } else {
    response = http::jsonResponse(200, build());
    if (gzipped) {
      response.body = http::gzip(response.body);
      http::setGzipEncoded(response);
    }
  }
  http::varyOnEncoding(response);
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  return withTileCache(std::move(response), etag);
}

/// GET /v1/models/{m}/3dtiles/{p}.glb[?v=N][&rev=R][&compress=none]: with the tileset's `?v=`, the
/// patch as in that version or 404 (versionedPatch), so that no node answers a version it has not
/// followed yet. On a network thread (`onNetworkThread`) it answers only a 304 or a cached GLB,
/// and nullopt otherwise; on the CPU pool the patch-data service encodes the GLB from the patch's
/// data (read through the patch cache) and caches it.
std::optional<http::Response> glb(models::ModelRegistry& models, const models::PatchData& data,
                                  const http::Request& request, bool onNetworkThread) {
  const std::string& id = request.param("m");
  const models::ModelRegistry::Served served = models.getServed(id);
  const core::PatchKey key =
      parseKey(request.param("p"), "tile must be {depth_x_y}.glb (e.g. 2_1_3.glb)", ".glb");
  const std::optional<VersionedPatch> read =
      versionedPatch(*served.live, request, key, onNetworkThread);
  if (!read) {
    return std::nullopt;
  }
  const core::ModelSnapshot* snapshot = read->snapshot.get();
  const core::PatchInfo* info = read->info;
  const core::GlbCompression compression = requestedCompression(request);
  const bool compressed = compression == core::GlbCompression::Meshopt;
  const std::string etag = glbEtag(*info, compressed ? "" : "raw");
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kTileCacheControl);
  }
  auto body =
      data.glb(served, *snapshot, *info, compression,
               onNetworkThread ? models::Asker::NetworkThread : models::Asker::PoolAfterNetwork);
  if (body == nullptr) {
    return std::nullopt;
  }
  http::Response response;
  // Written from the cached bytes without a copy; the response holds them (pinned, so they stay
  // counted in the budget) until written.
  sendBody(response, std::move(body));
  response.contentType = std::string(kGlbType);
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  response.set("X-VSM-Patch-Version", std::to_string(info->version));
  return withTileCache(std::move(response), etag);
}

}  // namespace

json tilesetJson(const core::TileNode& root, std::string_view tilesetVersion,
                 const core::Model* model, std::uint64_t revision, bool compressedContent,
                 std::uint64_t modelVersion, int levels) {
  json asset = {{"version", "1.1"}, {"tilesetVersion", tilesetVersion}, {"generator", "vsmd"}};
  if (modelVersion != 0) {
    asset["extras"] = {{"model_version", modelVersion}};
  }
  // An external tileset's root is placed by the tile that names it (3D Tiles: its transform
  // applies after that tile's), so only the model's root is placed from the origin.
  const core::Vec3d origin =
      root.key == core::PatchKey::root() ? core::Vec3d{0, 0, 0} : root.centre;
  return {{"asset", std::move(asset)},
          {"geometricError", core::tilesetGeometricError(root)},
          {"root", tileJson(root, origin,
                            UriParts{model, revision, compressedContent, modelVersion, levels})}};
}

void addTilesRoutes(http::Router& router, models::ModelRegistry& models,
                    std::shared_ptr<models::PatchData> data) {
  if (data == nullptr) {
    data = std::make_shared<models::PatchData>();
  }
  router.add(
      http::Method::Get, "/v1/models/{m}/3dtiles/tileset.json",
      [&models, data](const http::Request& request) { return getTileset(models, *data, request); });
  router.add(
      http::Method::Get, "/v1/models/{m}/3dtiles/{p}.glb",
      [&models, data](const http::Request& request) { return *glb(models, *data, request, false); },
      [&models, data](const http::Request& request) { return glb(models, *data, request, true); });
}

}  // namespace vsm::server::api
