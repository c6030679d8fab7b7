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
std::string contentUri(const core::PatchKey& key, const core::Model* model, std::uint64_t revision,
                       bool compressedContent) {
  std::string uri = key.toString() + ".glb";
  if (model != nullptr) {
    uri += "?v=" + std::to_string(model->at(key).version);
    if (revision != 0) {
      uri += "&rev=" + std::to_string(revision);
    }
  }
  if (!compressedContent) {
    uri += model != nullptr ? "&compress=none" : "?compress=none";
  }
  return uri;
}

json tileJson(const core::TileNode& node, const core::Vec3d& parentCentre, const core::Model* model,
              std::uint64_t revision, bool compressedContent) {
  const core::Vec3d c = node.box.center() - node.centre;
  const core::Vec3d half = node.box.size() * 0.5;
  json tile = {{"transform", translationJson(node.centre - parentCentre)},
               {"boundingVolume",
                {{"box", json::array({c.x, c.y, c.z, half.x, 0.0, 0.0, 0.0, half.y, 0.0, 0.0, 0.0,
                                      half.z})}}},
               {"geometricError", node.geometricError},
               {"refine", "REPLACE"},
               {"content", {{"uri", contentUri(node.key, model, revision, compressedContent)}}}};
  if (!node.children.empty()) {
    json children = json::array();
    for (const core::TileNode& child : node.children) {
      children.push_back(tileJson(child, node.centre, model, revision, compressedContent));
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

/// GET /v1/models/{m}/3dtiles/tileset.json[?compress=none][&rev=N]. A client that accepts gzip
/// gets the body gzipped; that body is made once per snapshot version and variant (content
/// compression, revision URIs) and kept in the model's EncodedCache, within the budget. The
/// identity body is built per request, as before (serialising the tree is cheaper than
/// compressing it). Both carry "Vary: Accept-Encoding" and their own ETag.
http::Response getTileset(models::ModelRegistry& models, const models::PatchData& data,
                          const http::Request& request) {
  const auto [served, snapshot] = *tiledRead(models, request);
  const bool compressedContent = requestedCompression(request) == core::GlbCompression::Meshopt;
  const bool revisionUris = request.queryParam("rev").has_value();
  const bool gzipped = http::acceptsGzip(request);
  // The representation: content URIs (compressed or "raw", with "&rev=" or not) and encoding.
  std::string variant = compressedContent ? "" : "raw";
  for (const auto& [on, part] : {std::pair{revisionUris, "rev"}, std::pair{gzipped, "gz"}}) {
    if (on) {
      variant += (variant.empty() ? "" : "-") + std::string(part);
    }
  }
  const std::string etag = tilesetEtag(*snapshot, variant);
  if (http::ifNoneMatch(request, etag)) {
    http::Response response = http::notModified(etag, kTileCacheControl);
    http::varyOnEncoding(response);
    return response;
  }
  const auto build = [&] {
    const core::TileNode root = core::buildTileTree(*snapshot->model);
    return tilesetJson(root, http::opaqueOf(modelEtag(*snapshot)), snapshot->model.get(),
                       revisionUris ? snapshot->version : 0, compressedContent, snapshot->version);
  };
  const GzippedDocument document =
      compressedContent
          ? (revisionUris ? GzippedDocument::TilesetRevision : GzippedDocument::Tileset)
          : (revisionUris ? GzippedDocument::TilesetUncompressedRevision
                          : GzippedDocument::TilesetUncompressed);
  http::Response response = gzipped ? gzippedJson(data, served, document, snapshot->version, build)
                                    : http::jsonResponse(200, build());
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
                 std::uint64_t modelVersion) {
  json asset = {{"version", "1.1"}, {"tilesetVersion", tilesetVersion}, {"generator", "vsmd"}};
  if (modelVersion != 0) {
    asset["extras"] = {{"model_version", modelVersion}};
  }
  return {{"asset", std::move(asset)},
          {"geometricError", core::tilesetGeometricError(root)},
          {"root", tileJson(root, core::Vec3d{0, 0, 0}, model, revision, compressedContent)}};
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
