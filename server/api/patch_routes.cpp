#include "server/api/patch_routes.hpp"

#include <algorithm>
#include <cctype>
#include <memory>
#include <optional>
#include <string>
#include <utility>

#include "core/common/error.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "server/api/etags.hpp"
#include "server/models/model_registry.hpp"
#include "server/models/patch_data.hpp"

namespace vsm::server::api {

using core::Error;
using core::ErrorCode;

namespace {

/// Where a patch-data route runs: its inline handler on a network thread, its handler on the CPU
/// pool after that look missed.
models::Asker askerOf(bool onNetworkThread) {
  return onNetworkThread ? models::Asker::NetworkThread : models::Asker::PoolAfterNetwork;
}

/// The positions response of a patch: the .aara bytes and what describes them.
http::Response positionsResponse(const core::ModelSnapshot& snapshot, const core::PatchInfo& info,
                                 std::string etag) {
  http::Response response;
  response.contentType = "application/octet-stream";
  response.set("X-VSM-Grid-Size", std::to_string(snapshot.model->gridSize()));
  response.set("X-VSM-Model-Version", std::to_string(snapshot.version));
  response.set("X-VSM-Patch-Version", std::to_string(info.version));
  return withCache(std::move(response), kPatchCacheControl, etag);
}

/// GET /v1/models/{m}/patches/{p}/positions. A patch whose stored file holds exactly the bytes
/// served (the full grid as V3f) is sent from that file with sendfile(2) like a static file: no
/// decoding, no copy, the page cache holds the bytes, the budget only the open file's entry.
/// Other patches (cropped borders, V3d) are decoded and encoded once, and that encoding is cached
/// in the budget (PatchData::positions). On a network thread (`onNetworkThread`) it answers only
/// what needs no blocking — a 304, a held open file, a cached encoding — and nullopt otherwise;
/// on the CPU pool the service opens or encodes.
std::optional<http::Response> positions(const ModelContext& c, const http::Request& request,
                                        bool onNetworkThread) {
  const std::string& id = request.param("m");
  const models::ModelRegistry::Served served = c.models.getServed(id);
  const core::PatchKey key = parseKey(request.param("p"));
  const std::optional<VersionedPatch> read =
      versionedPatch(*served.live, request, key, onNetworkThread);
  if (!read) {
    return std::nullopt;
  }
  const core::ModelSnapshot& snapshot = *read->snapshot;
  const core::PatchInfo& info = *read->info;
  std::string etag = patchEtag(info);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  http::Response response = positionsResponse(snapshot, info, std::move(etag));
  std::optional<models::PatchData::Positions> data =
      c.data->positions(served, snapshot, info, askerOf(onNetworkThread));
  if (!data) {
    return std::nullopt;
  }
  response.set("X-VSM-Local2Global", std::move(data->local2global));
  if (data->file != nullptr) {
    sendFile(response, std::move(data->file));
  } else {
    sendBody(response, std::move(data->body));
  }
  return response;
}

/// `info`, the patch of a texture or coordinates request, 404 unless it has a texture (of the
/// requested layer, when the route names one).
const core::PatchInfo& texturedPatch(std::string_view id, const core::PatchInfo& info,
                                     const http::Request& request) {
  if (info.textureFile.empty()) {
    throw Error(ErrorCode::NotFound, "patch " + info.key.toString() + " of model '" +
                                         std::string(id) + "' has no texture");
  }
  if (const auto it = request.params.find("layer"); it != request.params.end()) {
    const std::string_view own = textureLayer(info.textureFile);
    const std::string* layer = &it->second;
    const bool same = own.size() == layer->size() &&
                      std::equal(own.begin(), own.end(), layer->begin(), [](char a, char b) {
                        return std::tolower(static_cast<unsigned char>(a)) ==
                               std::tolower(static_cast<unsigned char>(b));
                      });
    if (!same) {
      throw Error(ErrorCode::NotFound, "patch " + info.key.toString() + " has no texture layer '" +
                                           std::string(layer->substr(0, 64)) + "' (it has '" +
                                           std::string(own) + "')");
    }
  }
  return info;
}

/// The response headers every texture-data answer carries.
http::Response textureResponse(const core::ModelSnapshot& snapshot, const core::PatchInfo& info,
                               std::string_view contentType, const std::string& etag) {
  http::Response response;
  response.contentType = std::string(contentType);
  response.set("X-VSM-Model-Version", std::to_string(snapshot.version));
  response.set("X-VSM-Patch-Version", std::to_string(info.version));
  return withCache(std::move(response), kPatchCacheControl, etag);
}

/// GET /v1/models/{m}/patches/{p}/coordinates: the texture coordinates file (.aara) as stored,
/// sent with sendfile(2) from the file held open (as positions). On a network thread only a 304
/// or a held file is answered.
std::optional<http::Response> coordinates(const ModelContext& c, const http::Request& request,
                                          bool onNetworkThread) {
  const std::string& id = request.param("m");
  const models::ModelRegistry::Served served = c.models.getServed(id);
  const core::PatchKey key = parseKey(request.param("p"));
  const std::optional<VersionedPatch> read =
      versionedPatch(*served.live, request, key, onNetworkThread);
  if (!read) {
    return std::nullopt;
  }
  const core::PatchInfo& info = texturedPatch(id, *read->info, request);
  const std::string etag = patchDataEtag(info, "uv");
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  auto file = c.data->coordinates(served, info, askerOf(onNetworkThread));
  if (file == nullptr) {
    return std::nullopt;
  }
  http::Response response =
      textureResponse(*read->snapshot, info, "application/octet-stream", etag);
  sendFile(response, std::move(file));
  return response;
}

/// GET /v1/models/{m}/patches/{p}/texture[/{layer}]: the texture tile as PNG, encoded once and
/// cached in the budget. On a network thread only a 304 or a cached PNG is answered.
std::optional<http::Response> texture(const ModelContext& c, const http::Request& request,
                                      bool onNetworkThread) {
  const std::string& id = request.param("m");
  const models::ModelRegistry::Served served = c.models.getServed(id);
  const core::PatchKey key = parseKey(request.param("p"));
  const std::optional<VersionedPatch> read =
      versionedPatch(*served.live, request, key, onNetworkThread);
  if (!read) {
    return std::nullopt;
  }
  const core::PatchInfo& info = texturedPatch(id, *read->info, request);
  const std::string etag = patchDataEtag(info, "png");
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  auto body = c.data->texturePng(served, info, askerOf(onNetworkThread));
  if (body == nullptr) {
    return std::nullopt;
  }
  http::Response response = textureResponse(*read->snapshot, info, "image/png", etag);
  response.set("X-VSM-Texture-Layer", std::string(textureLayer(info.textureFile)));
  sendBody(response, std::move(body));
  return response;
}

}  // namespace

void addPatchDataRoutes(http::Router& router, const ModelContext& context) {
  // Answered on the network thread when cached (the inline handler), else on the CPU pool.
  using Handler =
      std::optional<http::Response> (*)(const ModelContext&, const http::Request&, bool);
  const auto add = [&](const char* pattern, Handler handler) {
    router.add(
        http::Method::Get, pattern,
        [context, handler](const http::Request& request) {
          return *handler(context, request, false);
        },
        [context, handler](const http::Request& request) {
          return handler(context, request, true);
        });
  };
  add("/v1/models/{m}/patches/{p}/coordinates", coordinates);
  add("/v1/models/{m}/patches/{p}/texture", texture);
  add("/v1/models/{m}/patches/{p}/texture/{layer}", texture);
  add("/v1/models/{m}/patches/{p}/positions", positions);
}

}  // namespace vsm::server::api
