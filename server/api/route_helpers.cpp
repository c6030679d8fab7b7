#include "server/api/route_helpers.hpp"

#include <charconv>
#include <utility>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "server/cluster/coordinator.hpp"
#include "server/http/gzip.hpp"
#include "server/models/patch_data.hpp"

namespace vsm::server::api {

using core::Error;
using core::ErrorCode;
using nlohmann::json;

core::PatchKey parseKey(std::string_view text, std::string_view form, std::string_view suffix) {
  const auto key = core::PatchKey::parse(text);
  if (!key) {
    throw Error(ErrorCode::InvalidArgument, std::string(form) + ", not '" +
                                                std::string(text.substr(0, 64)) +
                                                std::string(suffix) + "'");
  }
  return *key;
}

const core::PatchInfo& findPatch(std::string_view id, const core::ModelSnapshot& snapshot,
                                 const core::PatchKey& key) {
  const core::PatchInfo* info = snapshot.model->find(key);
  if (info == nullptr) {
    throw Error(ErrorCode::NotFound, "model '" + std::string(id) + "' has no patch " +
                                         key.toString() + " (version " +
                                         std::to_string(snapshot.version) + ")");
  }
  return *info;
}

http::Response withCache(http::Response response, std::string_view cacheControl,
                         std::string_view etag) {
  response.set("Cache-Control", std::string(cacheControl));
  if (!etag.empty()) {
    response.set("ETag", std::string(etag));
  }
  return response;
}

int intQuery(const http::Request& request, std::string_view name, int fallback, int lo, int hi) {
  const auto text = request.queryParam(name);
  if (!text) {
    return fallback;
  }
  int value = 0;
  const auto [end, ec] = std::from_chars(text->data(), text->data() + text->size(), value);
  if (ec != std::errc() || end != text->data() + text->size() || value < lo || value > hi) {
    throw Error(ErrorCode::InvalidArgument, "query parameter '" + std::string(name) +
                                                "' must be an integer from " + std::to_string(lo) +
                                                " to " + std::to_string(hi));
  }
  return value;
}

/// A revision number in the path or the query: a decimal integer >= 1.
std::uint64_t parseRevision(std::string_view name, std::string_view text) {
  std::uint64_t value = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  if (ec != std::errc() || end != text.data() + text.size() || value == 0) {
    throw Error(ErrorCode::InvalidArgument,
                std::string(name) + " must be a revision number (an integer >= 1), not '" +
                    std::string(text.substr(0, 32)) + "'");
  }
  return value;
}

/// A body sent with sendfile(2) from a held open file, which the response keeps open (and its
/// cache entry pinned) until written.
void sendFile(http::Response& response, std::shared_ptr<const models::EncodedCache::File> file) {
  response.file = {file->fd(), 0, file->size()};
  response.bodyOwner = std::move(file);
}

/// A body written from held encoded bytes, without a copy; the response keeps them (and their
/// cache entry pinned, so in-flight bytes stay counted) until written.
void sendBody(http::Response& response, std::shared_ptr<const models::EncodedCache::Body> body) {
  response.sharedBody = body->text();
  response.bodyOwner = std::move(body);
}

/// The layer a patch's texture entry names ("Diffuse" of "Diffuse\\3_0_1.tif"); empty when the
/// entry has no folder.
std::string_view textureLayer(std::string_view entry) {
  const std::size_t slash = entry.find_first_of("\\/");
  return slash == std::string_view::npos ? std::string_view() : entry.substr(0, slash);
}

std::shared_ptr<const core::ModelSnapshot> requestedSnapshot(core::LiveModel& live,
                                                             const http::Request& request,
                                                             bool onNetworkThread) {
  const auto text = request.queryParam("rev");
  if (!text) {
    return live.snapshot();
  }
  const std::uint64_t revision = parseRevision("query parameter 'rev'", *text);
  return onNetworkThread ? live.heldSnapshot(revision) : live.snapshotAt(revision);
}

std::optional<std::uint64_t> requestedVersion(const http::Request& request) {
  const auto text = request.queryParam("v");
  if (!text) {
    return std::nullopt;
  }
  std::uint64_t value = 0;
  const auto [end, ec] = std::from_chars(text->data(), text->data() + text->size(), value);
  if (ec != std::errc() || end != text->data() + text->size() || value == 0) {
    throw Error(ErrorCode::InvalidArgument,
                "query parameter 'v' must be a model version (an integer >= 1), not '" +
                    text->substr(0, 32) + "'");
  }
  return value;
}

namespace {

/// The 404 of a read whose `?v=N` this node cannot answer from `snapshot`: N is newer than the
/// version it serves, or (with `?rev=`) not the revision's.
Error versionNotServed(const core::LiveModel& live, std::uint64_t asked,
                       const core::ModelSnapshot& snapshot, bool revision) {
  const std::string model = "model '" + live.name() + "'";
  const std::string askedText = std::to_string(asked);
  const std::string served = std::to_string(snapshot.version);
  if (revision) {
    return Error(ErrorCode::NotFound, "?v=" + askedText + " asks for version " + askedText +
                                          " of " + model + ", but ?rev= names revision " + served +
                                          " (version " + served + ")");
  }
  return Error(ErrorCode::NotFound,
               "?v=" + askedText + " asks for version " + askedText + " of " + model +
                   ", but this node serves version " + served +
                   " (it has not followed that publish yet, or there is no such version); ask "
                   "again in a moment, or without ?v= for the current version");
}

/// Kept revision `asked` (older than `current`, the version the node serves), which answers a read
/// of `?v=asked` that the current version cannot. Null on a network thread when it has to be read
/// from disk. Throws Error(NotFound) naming both versions when it is no longer kept.
std::shared_ptr<const core::ModelSnapshot> olderVersion(core::LiveModel& live, std::uint64_t asked,
                                                        std::uint64_t current,
                                                        std::string_view what,
                                                        bool onNetworkThread) {
  if (onNetworkThread) {
    return live.heldSnapshot(asked);
  }
  try {
    return live.snapshotAt(asked);
  } catch (const Error& e) {
    if (e.code() != ErrorCode::NotFound) {
      throw;
    }
    throw Error(ErrorCode::NotFound,
                "?v=" + std::to_string(asked) + " asks for version " + std::to_string(asked) +
                    " of model '" + live.name() + "', but this node serves version " +
                    std::to_string(current) + std::string(what) + ", and version " +
                    std::to_string(asked) +
                    " is no longer kept (GET the model's revisions); ask without ?v= for the "
                    "current version");
  }
}

}  // namespace

std::shared_ptr<const core::ModelSnapshot> versionedSnapshot(core::LiveModel& live,
                                                             const http::Request& request,
                                                             bool onNetworkThread) {
  const std::optional<std::uint64_t> asked = requestedVersion(request);
  auto snapshot = requestedSnapshot(live, request, onNetworkThread);
  if (!asked || snapshot == nullptr || snapshot->version == *asked) {
    return snapshot;
  }
  const bool revision = request.queryParam("rev").has_value();
  if (revision || *asked > snapshot->version) {
    throw versionNotServed(live, *asked, *snapshot, revision);
  }
  return olderVersion(live, *asked, snapshot->version, "", onNetworkThread);
}

std::optional<TiledRead> tiledRead(models::ModelRegistry& models, const http::Request& request,
                                   bool onNetworkThread) {
  const std::string& id = request.param("m");
  TiledRead read{models.getServed(id), nullptr};
  read.snapshot = versionedSnapshot(*read.served.live, request, onNetworkThread);
  if (read.snapshot == nullptr) {
    return std::nullopt;
  }
  if (read.snapshot->model->empty()) {
    throw Error(ErrorCode::NotFound, "model '" + id + "' has no patches");
  }
  return read;
}

std::optional<VersionedPatch> versionedPatch(core::LiveModel& live, const http::Request& request,
                                             const core::PatchKey& key, bool onNetworkThread) {
  const std::optional<std::uint64_t> asked = requestedVersion(request);
  auto snapshot = requestedSnapshot(live, request, onNetworkThread);
  if (snapshot == nullptr) {
    return std::nullopt;
  }
  const bool revision = request.queryParam("rev").has_value();
  if (asked && *asked > snapshot->version) {
    throw versionNotServed(live, *asked, *snapshot, revision);
  }
  const core::PatchInfo* info = snapshot->model->find(key);
  if (info == nullptr && (!asked || revision || *asked == snapshot->version)) {
    findPatch(live.name(), *snapshot, key);  // throws NotFound naming the version
  }
  if (!asked || (info != nullptr && info->version <= *asked)) {
    return VersionedPatch{std::move(snapshot), info};
  }
  // The patch was rewritten, or removed (a restore), after version `asked`: what that version
  // holds is older.
  const std::string rewritten =
      info != nullptr
          ? " (patch " + key.toString() + " of version " + std::to_string(info->version) +
                ", rewritten after version " + std::to_string(*asked) + ")"
          : " (without patch " + key.toString() + ", removed after version " +
                std::to_string(*asked) + ")";
  if (revision) {
    throw Error(ErrorCode::NotFound, "?v=" + std::to_string(*asked) + " asks for version " +
                                         std::to_string(*asked) + " of model '" + live.name() +
                                         "', but ?rev= names revision " +
                                         std::to_string(snapshot->version) + rewritten);
  }
  snapshot = olderVersion(live, *asked, snapshot->version, rewritten, onNetworkThread);
  if (snapshot == nullptr) {
    return std::nullopt;
  }
  info = &findPatch(live.name(), *snapshot, key);
  return VersionedPatch{std::move(snapshot), info};
}

std::optional<http::Response> redirectToWriter(const ModelContext& context, const std::string& id,
                                               const http::Request& request) {
  if (context.cluster == nullptr) {
    return std::nullopt;
  }
  const std::optional<std::string> writer = context.cluster->writerElsewhere(id);
  if (!writer) {
    return std::nullopt;
  }
  return temporaryRedirect(*writer + request.target,
                           "model '" + id + "' is written by another node");
}

http::Response temporaryRedirect(const std::string& location, std::string_view why) {
  http::Response response = http::errorResponse(
      307, "temporary_redirect", std::string(why) + ": repeat the request at " + location);
  response.set("Location", location);
  response.set("Cache-Control", std::string(http::cache_control::kNoStore));
  return response;
}

http::Response gzippedJson(const models::PatchData& data,
                           const models::ModelRegistry::Served& served, GzippedDocument document,
                           std::uint64_t version, const std::function<json()>& build) {
  auto body = data.gzippedJson(served, static_cast<std::uint8_t>(document), version,
                               [&] { return build().dump(); });
  http::Response response;
  response.status = 200;
  response.contentType = "application/json";
  sendBody(response, std::move(body));
  http::setGzipEncoded(response);
  return response;
}

}  // namespace vsm::server::api
