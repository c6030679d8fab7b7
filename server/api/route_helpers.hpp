#pragma once

// The helpers the route files share: the context of the model and job routes, the snapshot and
// patch a read answers from (?rev=, ?v=), redirects to the writer, and the answers built from
// what the patch-data service (server/models/patch_data.hpp) returns.

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>

#include <nlohmann/json_fwd.hpp>

#include "core/pyramid/patch_key.hpp"
#include "server/http/router.hpp"
#include "server/models/encoded_cache.hpp"
#include "server/models/model_registry.hpp"

namespace vsm::core {
class LiveModel;
struct ModelSnapshot;
struct PatchInfo;
}  // namespace vsm::core

namespace vsm::server::models {
class PatchData;
}  // namespace vsm::server::models
namespace vsm::server::jobs {
class JobRegistry;
}
namespace vsm::server::cluster {
class Coordinator;
}

namespace vsm::server::api {

class DiffGate;

/// Patch metadata and data: revalidated after a minute. The URL names no version, so a merge
/// changes what it returns; a minute of staleness in client caches is the trade for fewer
/// round trips (the ETag makes the revalidation cheap).
inline constexpr std::string_view kPatchCacheControl = http::cache_control::kMinute;

/// What the model and job routes use. Every reference must outlive the router.
struct ModelContext {
  models::ModelRegistry& models;
  jobs::JobRegistry& jobs;
  /// In a cluster: who writes which model. Null for a daemon alone.
  cluster::Coordinator* cluster = nullptr;
  /// The bound on diffs at once and their deadline; null: DiffGate's defaults.
  std::shared_ptr<DiffGate> diffs = nullptr;
  /// The patch-data service the routes ask for encoded bodies; null: one of their own.
  std::shared_ptr<models::PatchData> data = nullptr;
};

/// In a cluster, a write to model `id` that another node must do: 307 to the same target on that
/// node (the client repeats the request there, body and all), naming it. nullopt when this node
/// writes `id` or works alone. Throws core::Error(Unavailable) when no writer can be named.
std::optional<http::Response> redirectToWriter(const ModelContext& context, const std::string& id,
                                               const http::Request& request);

/// The snapshot a read asks for: the kept revision `?rev=N` (LiveModel::snapshotAt) or, without
/// the parameter, the current one. With `onNetworkThread` a revision that would have to be read
/// from disk gives null (the caller answers on the CPU pool instead). Throws
/// core::Error(InvalidArgument) for a malformed `rev`, NotFound for a revision not kept.
std::shared_ptr<const core::ModelSnapshot> requestedSnapshot(core::LiveModel& live,
                                                             const http::Request& request,
                                                             bool onNetworkThread = false);

/// The model version a read's `?v=N` names, or nullopt without the parameter. A read that names
/// one answers exactly what version N of the model holds, or 404: in a cluster a node that has
/// not followed the publish of N yet must not answer N's URL with its older data (a cache in
/// front would keep that under N's URL). Throws core::Error(InvalidArgument) unless N is an
/// integer >= 1.
std::optional<std::uint64_t> requestedVersion(const http::Request& request);

/// The snapshot a read of the whole model (summary, hierarchy, LOD cut, tileset, terrain layer
/// and tiles) answers from: requestedSnapshot()'s; with `?v=N` it must be version N: the current
/// one, or (without `?rev=`) kept revision N when N is older. Null on a network thread when that
/// needs the disk (as requestedSnapshot()). Throws core::Error(NotFound), naming both versions,
/// when this node cannot answer version N: N is newer than its current version (it has not
/// followed that publish yet, or there is no such version), no longer kept, or not the revision
/// `?rev=` names. The pipeline answers NotFound with 404 and Cache-Control: no-store, so no cache
/// keeps it. Also throws as requestedSnapshot().
std::shared_ptr<const core::ModelSnapshot> versionedSnapshot(core::LiveModel& live,
                                                             const http::Request& request,
                                                             bool onNetworkThread = false);

/// The served model and snapshot a read of a whole model's tiles answers from.
struct TiledRead {
  models::ModelRegistry::Served served;
  std::shared_ptr<const core::ModelSnapshot> snapshot;  ///< holds at least one patch
};
/// The tileset's and the terrain's read: model `{m}` as getServed() serves it and its
/// versionedSnapshot(). nullopt on a network thread when that needs the disk. Throws as those,
/// and core::Error(NotFound) for a model without patches (it has no tiles).
std::optional<TiledRead> tiledRead(models::ModelRegistry& models, const http::Request& request,
                                   bool onNetworkThread = false);

/// One patch of one snapshot, as a read of the patch answers it.
struct VersionedPatch {
  std::shared_ptr<const core::ModelSnapshot> snapshot;
  const core::PatchInfo* info = nullptr;  ///< in *snapshot
};
/// The snapshot and patch `key` a read of that patch (metadata, positions, texture, coordinates,
/// GLB tile) answers from: requestedSnapshot()'s. With `?v=N`, the patch as it is in version N:
/// a patch is rewritten with the version of the publish that rewrote it, so a snapshot of
/// version M holding the patch at version k (k <= M) holds what every version from k to M holds,
/// and answers any N in [k, M] (the tileset's links name k, so they stay the same, and cached,
/// across publishes that leave the patch alone). An N older than k is answered from kept revision
/// N (without `?rev=`). nullopt on a network thread when that needs the disk. Throws
/// core::Error(NotFound) for a patch not in that snapshot, and as versionedSnapshot() (404,
/// no-store) when the node cannot answer version N: N newer than its current version, older than
/// k and no longer kept, or outside [k, R] for `?rev=R`.
std::optional<VersionedPatch> versionedPatch(core::LiveModel& live, const http::Request& request,
                                             const core::PatchKey& key,
                                             bool onNetworkThread = false);

/// A model-wide JSON document answered gzipped (the client accepts gzip): the bytes made once per
/// (`document`, snapshot `version`) from build().dump() by the patch-data service and kept in the
/// model's EncodedCache as Encoding::JsonGzip, within the memory budget, never gzipped per
/// request. `document` names the document and
/// what it depends on besides the version. Sets the body, Content-Type and Content-Encoding; the
/// caller adds Vary (on every answer of the route), ETag and caching. Throws
/// core::Error(ResourceExhausted) when the budget is full of pinned data.
/// Which document a gzipped body is (gzippedJson's `variant`), allocated here for every route.
enum class GzippedDocument : std::uint8_t {
  /// tileset.json: content compressed or not (?compress=none), URIs with or without "&rev=".
  Tileset = 1,
  TilesetUncompressed = 2,
  TilesetRevision = 3,
  TilesetUncompressedRevision = 4,
  /// The terrain's layer.json, tile URIs without or with "&rev=".
  TerrainLayer = 5,
  TerrainLayerRevision = 6,
};
http::Response gzippedJson(const models::PatchData& data,
                           const models::ModelRegistry::Served& served, GzippedDocument document,
                           std::uint64_t version, const std::function<nlohmann::json()>& build);

/// 307 to `location`, with an error body (code "temporary_redirect") saying `why`.
http::Response temporaryRedirect(const std::string& location, std::string_view why);

/// The patch key of a route's {p}. Throws core::Error(InvalidArgument) unless it is depth_x_y,
/// with the message "<form>, not '<text><suffix>'": a route whose {p} stands in a longer name
/// (e.g. "{p}.glb") passes its own `form` and the `suffix` the router took off.
core::PatchKey parseKey(std::string_view text,
                        std::string_view form = "patch key must be depth_x_y (e.g. 2_1_3)",
                        std::string_view suffix = {});
/// Patch `key` of `snapshot` of model `id`. Throws core::Error(NotFound).
const core::PatchInfo& findPatch(std::string_view id, const core::ModelSnapshot& snapshot,
                                 const core::PatchKey& key);
/// A revision number in the path or the query (`name` says which): a decimal integer >= 1.
/// Throws core::Error(InvalidArgument).
std::uint64_t parseRevision(std::string_view name, std::string_view text);
/// An integer query parameter in [lo, hi], `fallback` without it. Throws
/// core::Error(InvalidArgument).
int intQuery(const http::Request& request, std::string_view name, int fallback, int lo, int hi);
/// `response` with Cache-Control and, when given, ETag.
http::Response withCache(http::Response response, std::string_view cacheControl,
                         std::string_view etag = {});

/// The layer a patch's texture entry names ("Diffuse" of "Diffuse\\3_0_1.tif"); empty when the
/// entry has no folder.
std::string_view textureLayer(std::string_view entry);

/// A body sent with sendfile(2) from a held open file, which the response keeps open (and its
/// cache entry pinned) until written.
void sendFile(http::Response& response, std::shared_ptr<const models::EncodedCache::File> file);
/// A body written from held encoded bytes, without a copy; the response keeps them (and their
/// cache entry pinned, so in-flight bytes stay counted) until written.
void sendBody(http::Response& response, std::shared_ptr<const models::EncodedCache::Body> body);

}  // namespace vsm::server::api
