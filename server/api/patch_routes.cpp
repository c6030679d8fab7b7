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

/// A read of one patch's data: the model as served and the patch as the request names it.
struct PatchRead {
  models::ModelRegistry::Served served;
  VersionedPatch read;
};
/// The model and patch of a patch-data request ({m}, {p}, ?v=, ?rev=); nullopt on a network
/// thread when the snapshot would have to be read from disk. Throws as versionedPatch().
std::optional<PatchRead> readPatch(const ModelContext& c, const http::Request& request,
                                   bool onNetworkThread) {
  models::ModelRegistry::Served served = c.models.getServed(request.param("m"));
  const core::PatchKey key = parseKey(request.param("p"));
  std::optional<VersionedPatch> read = versionedPatch(*served.live, request, key, onNetworkThread);
  if (!read) {
    return std::nullopt;
  }
  return PatchRead{std::move(served), std::move(*read)};
}

/// The headers every patch-data answer carries, X-VSM-Grid-Size first with `gridSize`.
http::Response patchDataResponse(const core::ModelSnapshot& snapshot, const core::PatchInfo& info,
                                 std::string_view contentType, const std::string& etag,
                                 bool gridSize) {
  http::Response response;
  response.contentType = std::string(contentType);
  if (gridSize) {
    response.set("X-VSM-Grid-Size", std::to_string(snapshot.model->gridSize()));
  }
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
  const std::optional<PatchRead> patch = readPatch(c, request, onNetworkThread);
  if (!patch) {
    return std::nullopt;
  }
  const models::ModelRegistry::Served& served = patch->served;
  const core::ModelSnapshot& snapshot = *patch->read.snapshot;
  const core::PatchInfo& info = *patch->read.info;
  const std::string etag = patchEtag(info);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  http::Response response =
      patchDataResponse(snapshot, info, "application/octet-stream", etag, /*gridSize=*/true);
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
  if (info.textureFile().empty()) {
    throw Error(ErrorCode::NotFound, "patch " + info.key.toString() + " of model '" +
                                         std::string(id) + "' has no texture");
  }
  if (const auto it = request.params.find("layer"); it != request.params.end()) {
    const std::string_view own = textureLayer(info.textureFile());
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

/// GET /v1/models/{m}/patches/{p}/coordinates (`png` false): the texture coordinates file
/// (.aara) as stored, sent with sendfile(2) from the file held open (as positions); and
/// GET /v1/models/{m}/patches/{p}/texture[/{layer}] (`png` true): the texture tile as PNG, encoded
/// once and cached in the budget. On a network thread only a 304 or what the budget holds is
/// answered.
std::optional<http::Response> textureData(const ModelContext& c, const http::Request& request,
                                          bool onNetworkThread, bool png) {
  const std::optional<PatchRead> patch = readPatch(c, request, onNetworkThread);
  if (!patch) {
    return std::nullopt;
  }
  const core::PatchInfo& info = texturedPatch(request.param("m"), *patch->read.info, request);
  const std::string etag = patchDataEtag(info, png ? "png" : "uv");
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  const models::Asker asker = askerOf(onNetworkThread);
  std::shared_ptr<const models::EncodedCache::File> file;
  std::shared_ptr<const models::EncodedCache::Body> body;
  if (png) {
    body = c.data->texturePng(patch->served, info, asker);
  } else {
    file = c.data->coordinates(patch->served, info, asker);
  }
  if (file == nullptr && body == nullptr) {
    return std::nullopt;
  }
  http::Response response = patchDataResponse(
      *patch->read.snapshot, info, png ? "image/png" : "application/octet-stream", etag, false);
  if (png) {
    response.set("X-VSM-Texture-Layer", std::string(textureLayer(info.textureFile())));
    sendBody(response, std::move(body));
  } else {
    sendFile(response, std::move(file));
  }
  return response;
}

std::optional<http::Response> coordinates(const ModelContext& c, const http::Request& request,
                                          bool onNetworkThread) {
  return textureData(c, request, onNetworkThread, false);
}

std::optional<http::Response> texture(const ModelContext& c, const http::Request& request,
                                      bool onNetworkThread) {
  return textureData(c, request, onNetworkThread, true);
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
