#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json_fwd.hpp>

#include "core/grid/geometry.hpp"
#include "core/pyramid/patch_key.hpp"
#include "server/api/etags.hpp"
#include "server/api/requests.hpp"
#include "server/http/router.hpp"

namespace vsm::core {
class LiveModel;
class Model;
struct ModelSnapshot;
struct PatchInfo;
class PatchGrid;
}  // namespace vsm::core

namespace vsm::server::models {
class EncodedCache;
class ModelRegistry;
}  // namespace vsm::server::models
namespace vsm::server::jobs {
class JobRegistry;
}
namespace vsm::server::cluster {
class Coordinator;
}

namespace vsm::server::api {

class DiffGate;

/// What the model and job routes use. Every reference must outlive the router.
struct ModelContext {
  models::ModelRegistry& models;
  jobs::JobRegistry& jobs;
  /// In a cluster: who writes which model. Null for a daemon alone.
  cluster::Coordinator* cluster = nullptr;
  /// The bound on diffs at once and their deadline; null: DiffGate's defaults.
  std::shared_ptr<DiffGate> diffs = nullptr;
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
/// (`variant`, snapshot `version`) from build().dump() and kept in `encoded` as Encoding::JsonGzip,
/// within the memory budget, never gzipped per request. `document` names the document and
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
http::Response gzippedJson(models::EncodedCache& encoded, GzippedDocument document,
                           std::uint64_t version, const std::function<nlohmann::json()>& build);

/// 307 to `location`, with an error body (code "temporary_redirect") saying `why`.
http::Response temporaryRedirect(const std::string& location, std::string_view why);

/// GET/POST /v1/models, GET/DELETE /v1/models/{m}, GET /v1/models/{m}/hierarchy,
/// /v1/models/{m}/patches/{p}, /v1/models/{m}/patches/{p}/positions, .../coordinates,
/// .../texture[/{layer}], /v1/models/{m}/lod, /v1/models/{m}/diff[.png] (see proto/openapi.yaml).
/// Every read works on one snapshot of the model, so a response never mixes two versions; the
/// summary, hierarchy, LOD cut and every patch route honour `?v=` (versionedSnapshot,
/// versionedPatch).
void addModelRoutes(http::Router& router, ModelContext context);

/// GET/POST /v1/jobs, GET/DELETE /v1/jobs/{j}.
void addJobRoutes(http::Router& router, ModelContext context);

// ---- wire mapping, public for tests -----------------------------------------------------------

/// {"min": [x, y, z], "max": [x, y, z]}, or null for an empty box.
nlohmann::json boxJson(const core::Box3d& box);
/// An entry of GET /v1/models (proto/examples/models.json); with `details` the full summary of
/// GET /v1/models/{m} (per-level summaries; proto/examples/model.json).
nlohmann::json modelJson(std::string_view id, const core::ModelSnapshot& snapshot, bool details);
/// GET /v1/models/{m}/patches/{p} (proto/examples/patch.json).
nlohmann::json patchJson(std::string_view id, const core::ModelSnapshot& snapshot,
                         const core::PatchInfo& info);
/// The tree below `root`, `levels` levels deep (0: the root alone; negative: all).
nlohmann::json hierarchyJson(const core::Model& model, const core::PatchKey& root, int levels);

/// 16 numbers, row-major, comma-separated, shortest round-trip form ("1,0,0,12.5,...").
std::string matrixText(const core::Mat4d& m);

}  // namespace vsm::server::api
