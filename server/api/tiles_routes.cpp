#include "server/api/tiles_routes.hpp"

#include <optional>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/opc/texture_file.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "core/tiles/glb.hpp"
#include "core/tiles/tile_tree.hpp"
#include "server/api/model_routes.hpp"
#include "server/models/model_registry.hpp"

namespace vsm::server::api {

using core::Error;
using core::ErrorCode;
using nlohmann::json;

namespace {

/// Bumped whenever encodeGlb() or tilesetJson() change what they produce for the same model, so
/// clients holding the old bytes under an ETag revalidate to the new ones.
constexpr std::string_view kTilesFormat = "t2";  // t2: textures embedded

/// As patch data (model_routes.cpp): the URL names no version, so revalidate after a minute.
constexpr std::string_view kTileCacheControl = "public, max-age=60";

constexpr std::string_view kGlbType = "model/gltf-binary";

/// The opaque part of a strong entity tag ("abc" -> abc).
std::string_view opaque(std::string_view etag) {
  if (etag.size() >= 2 && etag.front() == '"' && etag.back() == '"') {
    etag.remove_prefix(1);
    etag.remove_suffix(1);
  }
  return etag;
}

/// A column-major 4x4 translation, as 3D Tiles' tile.transform.
json translationJson(const core::Vec3d& t) {
  return json::array(
      {1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, t.x, t.y, t.z, 1.0});
}

json tileJson(const core::TileNode& node, const core::Vec3d& parentCentre) {
  const core::Vec3d c = node.box.center() - node.centre;
  const core::Vec3d half = node.box.size() * 0.5;
  json tile = {{"transform", translationJson(node.centre - parentCentre)},
               {"boundingVolume",
                {{"box", json::array({c.x, c.y, c.z, half.x, 0.0, 0.0, 0.0, half.y, 0.0, 0.0, 0.0,
                                      half.z})}}},
               {"geometricError", node.geometricError},
               {"refine", "REPLACE"},
               {"content", {{"uri", node.key.toString() + ".glb"}}}};
  if (!node.children.empty()) {
    json children = json::array();
    for (const core::TileNode& child : node.children) {
      children.push_back(tileJson(child, node.centre));
    }
    tile["children"] = std::move(children);
  }
  return tile;
}

core::PatchKey parseGlbKey(std::string_view text) {
  const auto key = core::PatchKey::parse(text);
  if (!key) {
    throw Error(ErrorCode::InvalidArgument, "tile must be {depth_x_y}.glb (e.g. 2_1_3.glb), not '" +
                                                std::string(text.substr(0, 64)) + ".glb'");
  }
  return *key;
}

http::Response withCache(http::Response response, std::string_view etag) {
  response.set("Cache-Control", std::string(kTileCacheControl));
  response.set("ETag", std::string(etag));
  return response;
}

http::Response getTileset(models::ModelRegistry& models, const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = models.get(id);
  const auto snapshot = live->snapshot();
  if (snapshot->model->empty()) {
    throw Error(ErrorCode::NotFound, "model '" + id + "' has no patches");
  }
  const std::string etag = tilesetEtag(*snapshot);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kTileCacheControl);
  }
  const core::TileNode root = core::buildTileTree(*snapshot->model);
  http::Response response =
      http::jsonResponse(200, tilesetJson(root, opaque(modelEtag(*snapshot))));
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  return withCache(std::move(response), etag);
}

http::Response getGlb(models::ModelRegistry& models, const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = models.get(id);
  const core::PatchKey key = parseGlbKey(request.param("p"));
  const auto snapshot = live->snapshot();
  const core::PatchInfo* info = snapshot->model->find(key);
  if (info == nullptr) {
    throw Error(ErrorCode::NotFound, "model '" + id + "' has no patch " + key.toString() +
                                         " (version " + std::to_string(snapshot->version) + ")");
  }
  const std::string etag = glbEtag(*info);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kTileCacheControl);
  }
  http::Response response;
  {
    // On the CPU pool, like every handler: a cache miss reads the disk here, and the encoding is
    // CPU work. The pin is released before the snapshot.
    const core::PatchCache::Pin pin = live->positions(*snapshot, key);
    // The patch's texture tile (converted to PNG) and coordinates, read from disk per request.
    const std::optional<core::PatchTexture> texture =
        core::readPatchTexture(live->dir(), *snapshot->model, *info);
    core::GlbOptions options;
    if (texture) {
      options.texture = {texture->png, "image/png"};
      options.texcoords = texture->texcoords;
      options.baseColor = {1.0, 1.0, 1.0, 1.0};  // the texture's own colours
    }
    const std::vector<std::byte> glb =
        core::encodeGlb(*pin.get<core::PatchGrid>(), core::tileCentre(*info), options);
    response.body.assign(reinterpret_cast<const char*>(glb.data()), glb.size());
  }
  response.contentType = std::string(kGlbType);
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  response.set("X-VSM-Patch-Version", std::to_string(info->version));
  return withCache(std::move(response), etag);
}

}  // namespace

json tilesetJson(const core::TileNode& root, std::string_view tilesetVersion) {
  return {
      {"asset", {{"version", "1.1"}, {"tilesetVersion", tilesetVersion}, {"generator", "vsmd"}}},
      {"geometricError", core::tilesetGeometricError(root)},
      {"root", tileJson(root, core::Vec3d{0, 0, 0})}};
}

std::string tilesetEtag(const core::ModelSnapshot& snapshot) {
  return http::strongEtag("tileset-" + std::string(opaque(modelEtag(snapshot))) + "-" +
                          std::string(kTilesFormat));
}

std::string glbEtag(const core::PatchInfo& info) {
  return http::strongEtag(std::string(opaque(patchEtag(info))) + "-glb-" +
                          std::string(kTilesFormat));
}

void addTilesRoutes(http::Router& router, models::ModelRegistry& models) {
  router.add(http::Method::Get, "/v1/models/{m}/3dtiles/tileset.json",
             [&models](const http::Request& request) { return getTileset(models, request); });
  router.add(http::Method::Get, "/v1/models/{m}/3dtiles/{p}.glb",
             [&models](const http::Request& request) { return getGlb(models, request); });
}

}  // namespace vsm::server::api
