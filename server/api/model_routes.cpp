#include "server/api/model_routes.hpp"

#include <algorithm>
#include <bit>
#include <cerrno>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <numbers>
#include <optional>
#include <set>
#include <span>

#include <nlohmann/json.hpp>

#include "core/cache/patch_cache.hpp"
#include "core/common/error.hpp"
#include "core/common/progress.hpp"
#include "core/diff/revision_diff.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/opc/aara.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/stored_file.hpp"
#include "core/opc/texture_file.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "core/tiles/lod_cut.hpp"
#include "server/api/diff_gate.hpp"
#include "server/cluster/coordinator.hpp"
#include "server/http/gzip.hpp"
#include "server/jobs/job_registry.hpp"
#include "server/jobs/model_jobs.hpp"
#include "server/models/encoded_cache.hpp"
#include "server/models/model_registry.hpp"

namespace vsm::server::api {

namespace fs = std::filesystem;
using core::Error;
using core::ErrorCode;
using nlohmann::json;

namespace {

/// Patch metadata and data: revalidated after a minute. The URL names no version, so a merge
/// changes what it returns; a minute of staleness in client caches is the trade for fewer
/// round trips (the ETag makes the revalidation cheap).
constexpr std::string_view kPatchCacheControl = http::cache_control::kMinute;

/// The largest diff.png asked for (pixels along the longer side): 4096 x 4096 RGBA is 64 MiB
/// before encoding, the map's floats another 64 MiB.
constexpr int kMaxDiffPngSize = 4096;

json vecJson(const core::Vec3d& v) {
  return json::array({v.x, v.y, v.z});
}

json rectJson(const core::GridRect& r) {
  return {{"x0", r.x0}, {"y0", r.y0}, {"x1", r.x1}, {"y1", r.y1}};
}

/// A JSON number, or null when not finite (JSON has no NaN).
json number(double v) {
  return std::isfinite(v) ? json(v) : json(nullptr);
}

core::PatchKey parseKey(std::string_view text) {
  const auto key = core::PatchKey::parse(text);
  if (!key) {
    throw Error(ErrorCode::InvalidArgument, "patch key must be depth_x_y (e.g. 2_1_3), not '" +
                                                std::string(text.substr(0, 64)) + "'");
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
                         std::string_view etag = {}) {
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

json nodeJson(const core::Model& model, const core::PatchInfo& info, int levels) {
  json node = {{"key", info.key.toString()},
               {"box", boxJson(info.globalBox)},
               {"resolution", number(info.resolution)},
               {"version", info.version},
               {"leaf", info.isLeaf()},
               {"child_count", std::popcount(static_cast<unsigned>(info.childMask))}};
  if (levels != 0 && !info.isLeaf()) {
    json children = json::array();
    for (const core::Quadrant q : core::kQuadrants) {
      if (info.hasChild(q)) {
        children.push_back(nodeJson(model, model.at(info.key.child(q)), levels - 1));
      }
    }
    node["children"] = std::move(children);
  }
  return node;
}

// ---- handlers --------------------------------------------------------------------------------

http::Response listModels(const ModelContext& c, const http::Request&) {
  json models = json::array();
  for (const auto& live : c.models.list()) {
    models.push_back(modelJson(live->name(), *live->snapshot(), false));
  }
  return withCache(http::jsonResponse(200, {{"models", std::move(models)}}),
                   http::cache_control::kRevalidate);
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

json revisionJson(const core::RevisionSummary& revision) {
  const core::RevisionRecord& r = revision.record;
  const auto orNull = [](auto value) { return value ? json(value) : json(nullptr); };
  return {{"revision", revision.number},
          {"parent", orNull(r.parent)},
          {"time", r.time},
          {"job", r.job.empty() ? json(nullptr) : json(r.job)},
          {"changed_patches", r.changed},
          {"removed_patches", r.removed},
          {"restored_from", orNull(r.restoredFrom)},
          {"latest", revision.latest}};
}

/// GET /v1/models/{m}/revisions: the kept revisions, oldest first.
http::Response getRevisions(const ModelContext& c, const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = c.models.get(id);
  json list = json::array();
  for (const core::RevisionSummary& revision : live->revisions()) {
    list.push_back(revisionJson(revision));
  }
  return withCache(
      http::jsonResponse(200,
                         {{"model", id}, {"keep", c.models.keepRevisions()}, {"revisions", list}}),
      http::cache_control::kRevalidate);
}

/// Stops a diff at its next leaf once its slot's deadline has passed (the diff reports progress
/// after every leaf and checks the token before the next).
class DiffDeadline final : public core::Progress {
 public:
  DiffDeadline(std::chrono::steady_clock::time_point deadline, core::CancelToken& cancel)
      : deadline_(deadline), cancel_(cancel) {}
  void report(std::string_view, double) override {
    if (std::chrono::steady_clock::now() >= deadline_) {
      cancel_.cancel();
    }
  }

 private:
  std::chrono::steady_clock::time_point deadline_;
  core::CancelToken& cancel_;
};

/// The most a diff's spatial index of one leaf's neighbourhood may take (core::DiffOptions::
/// indexBytes): a neighbourhood of 257 x 257 leaves fits.
constexpr std::size_t kDiffIndexBytes = std::size_t{16} << 20;

/// The working memory of a diff with a map of `mapSize` pixels along its longer side, allocated
/// outside the cache: the spatial index (kDiffIndexBytes at most), and the map's floats, the RGBA
/// picture and, at most as large again, the PNG.
std::size_t diffWorkBytes(int mapSize) {
  const auto pixels = static_cast<std::size_t>(mapSize) * static_cast<std::size_t>(mapSize);
  return kDiffIndexBytes + pixels * (sizeof(float) + 4 + 4);
}

/// The diff a request asks for: between the kept revisions ?from=A and ?to=B of model {m}, with a
/// map of `mapSize` pixels along its longer side when > 0. Runs inside the gate (a slot held
/// throughout, 503 when none is free), with its work memory (diffWorkBytes) charged to the budget
/// (Encoding::DiffWork) while it is drawn and encoded, and stops at the slot's deadline (503).
/// `finish` turns the diff into the response while the slot and the charge are held. Throws
/// Error(InvalidArgument) for a missing or malformed revision, NotFound for one not kept,
/// Unavailable when every slot is taken or the deadline passed, ResourceExhausted when the map
/// does not fit in the budget.
http::Response runDiff(const ModelContext& c, const http::Request& request, int mapSize,
                       const std::function<http::Response(const core::RevisionDiff&)>& finish) {
  const std::string& id = request.param("m");
  const models::ModelRegistry::Served served = c.models.getServed(id);
  const auto fromText = request.queryParam("from");
  const auto toText = request.queryParam("to");
  if (!fromText || !toText) {
    throw Error(ErrorCode::InvalidArgument,
                "diff needs ?from=A&to=B (revision numbers, GET /v1/models/{m}/revisions)");
  }
  const std::uint64_t from = parseRevision("query parameter 'from'", *fromText);
  const std::uint64_t to = parseRevision("query parameter 'to'", *toText);
  const std::unique_ptr<DiffGate::Slot> slot = c.diffs->enter();
  const std::shared_ptr<const void> charged =
      served.encoded->reserve(models::Encoding::DiffWork, diffWorkBytes(mapSize));
  core::CancelToken cancel;
  DiffDeadline deadline(slot->deadline(), cancel);
  core::DiffOptions options;
  options.mapSize = mapSize;
  options.indexBytes = kDiffIndexBytes;
  if (const auto error = request.queryParam("registration_error")) {
    char* end = nullptr;
    const std::string text(*error);
    options.registrationError = std::strtod(text.c_str(), &end);
    if (text.empty() || end != text.c_str() + text.size() ||
        !(options.registrationError >= 0 && options.registrationError < 1e7)) {
      throw Error(ErrorCode::InvalidArgument,
                  "query parameter 'registration_error' must be a length in metres >= 0");
    }
  }
  options.cancel = &cancel;
  options.progress = &deadline;
  try {
    return finish(core::diffRevisions(*served.live, served.live->snapshotAt(from),
                                      served.live->snapshotAt(to), options));
  } catch (const Error& e) {
    if (e.code() != ErrorCode::Cancelled || !cancel.cancelled()) {
      throw;
    }
    c.diffs->countTimeout();
    throw Error(ErrorCode::Unavailable,
                "the diff of revisions " + std::to_string(from) + " and " + std::to_string(to) +
                    " of model '" + id + "' ran longer than limits.diff_timeout and was stopped");
  }
}

/// GET /v1/models/{m}/diff?from=A&to=B: the displacement per changed patch and in total.
http::Response getDiff(const ModelContext& c, const http::Request& request) {
  return runDiff(c, request, 0, [&](const core::RevisionDiff& diff) {
    http::Response response;
    response.status = 200;
    response.contentType = "application/json";
    response.body = core::diffJson(diff, request.param("m"));
    return withCache(std::move(response), http::cache_control::kRevalidate);
  });
}

/// GET /v1/models/{m}/diff.png?from=A&to=B&size=N: the displacement seen from above, blue - white
/// - red over [-R, R], R the largest |d|, named by the PNG's text and X-VSM-Diff-Range.
http::Response getDiffPng(const ModelContext& c, const http::Request& request) {
  const int size = intQuery(request, "size", 1024, 1, kMaxDiffPngSize);
  return runDiff(c, request, size, [&](const core::RevisionDiff& diff) {
    const std::vector<std::byte> png = core::diffPng(diff, size);
    http::Response response;
    response.status = 200;
    response.contentType = "image/png";
    response.body.assign(reinterpret_cast<const char*>(png.data()), png.size());
    char range[64];
    std::snprintf(range, sizeof range, "%.9g", diff.totals.maxAbs());
    response.set("X-VSM-Diff-Range", range);
    response.set("X-VSM-Diff-Legend", core::diffLegend(diff));
    return withCache(std::move(response), http::cache_control::kRevalidate);
  });
}

/// POST /v1/models/{m}/revisions/{n}/restore: a job publishing revision n's content anew.
http::Response postRestore(const ModelContext& c, const http::Request& request) {
  const std::string& id = request.param("m");
  const std::uint64_t revision = parseRevision("the revision", request.param("n"));
  if (auto redirect = redirectToWriter(c, id, request)) {
    return std::move(*redirect);
  }
  const jobs::JobStatus job = jobs::submitRestore(c.jobs, c.models, id, revision);
  http::Response response = http::jsonResponse(202, jobs::toJson(job));
  response.set("Location", "/v1/jobs/" + job.id);
  return withCache(std::move(response), http::cache_control::kNoStore);
}

http::Response postModel(const ModelContext& c, const http::Request& request) {
  const ModelRequest body = parseModelRequest(request);
  const std::string& id = body.id;
  models::checkModelId(id);
  if (auto redirect = redirectToWriter(c, id, request)) {
    return std::move(*redirect);
  }
  if (body.path) {
    const fs::path dir = models::resolveInside(c.models.dataRoot(), *body.path);
    std::error_code ec;
    if (!fs::is_directory(dir, ec)) {
      throw Error(ErrorCode::NotFound, "source path is not a directory in the data root");
    }
    const auto live = c.models.open(id, dir);
    http::Response response = http::jsonResponse(201, modelJson(id, *live->snapshot(), true));
    response.set("Location", "/v1/models/" + id);
    return withCache(std::move(response), http::cache_control::kNoStore);
  }
  const fs::path input = models::resolveInside(c.models.dataRoot(), *body.import);
  const jobs::JobStatus job =
      jobs::submitImport(c.jobs, c.models, id, input, body.patchSize,
                         body.untextured ? core::ImportOptions::Drape::None
                                         : core::ImportOptions::Drape::ShadedRelief);
  http::Response response = http::jsonResponse(202, jobs::toJson(job));
  response.set("Location", "/v1/jobs/" + job.id);
  return response;
}

http::Response getModel(const ModelContext& c, const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = c.models.get(id);
  const auto snapshot = versionedSnapshot(*live, request);
  const std::string etag = modelEtag(*snapshot);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, http::cache_control::kRevalidate);
  }
  return withCache(http::jsonResponse(200, modelJson(id, *snapshot, true)),
                   http::cache_control::kRevalidate, etag);
}

http::Response deleteModel(const ModelContext& c, const http::Request& request) {
  if (c.cluster != nullptr) {
    throw Error(ErrorCode::Conflict,
                "in a cluster every node serves every model of the data root: to retire a model, "
                "move its directory out of the data root");
  }
  c.models.close(request.param("m"));
  http::Response response;
  response.status = 204;
  return response;
}

http::Response getHierarchy(const ModelContext& c, const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = c.models.get(id);
  const auto snapshot = versionedSnapshot(*live, request);
  const auto rootText = request.queryParam("root");
  const core::PatchKey root = rootText ? parseKey(*rootText) : core::PatchKey::root();
  const int levels = intQuery(request, "depth", -1, 0, core::PatchKey::kMaxDepth);
  findPatch(id, *snapshot, root);
  const std::string etag = viewEtag(*snapshot, "h", request.query());
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, http::cache_control::kRevalidate);
  }
  json body = {{"model", id},
               {"version", snapshot->version},
               {"grid_size", snapshot->model->gridSize()},
               {"root", hierarchyJson(*snapshot->model, root, levels)}};
  return withCache(http::jsonResponse(200, body), http::cache_control::kRevalidate, etag);
}

http::Response getPatch(const ModelContext& c, const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = c.models.get(id);
  const core::PatchKey key = parseKey(request.param("p"));
  const VersionedPatch read = *versionedPatch(*live, request, key);
  const core::ModelSnapshot& snapshot = *read.snapshot;
  const core::PatchInfo& info = *read.info;
  const std::string etag = patchEtag(info);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  return withCache(http::jsonResponse(200, patchJson(id, snapshot, info)), kPatchCacheControl,
                   etag);
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

/// The full-grid .aara of a patch whose stored file is laid out otherwise, cached with its
/// Local2Global as the encoding's note: a cropped V3f file's rows are copied into place (no
/// decoding); a V3d file is decoded and re-based.
std::shared_ptr<const models::EncodedCache::Body> encodePositions(
    models::EncodedCache& encoded, const core::LiveModel& live, const core::ModelSnapshot& snapshot,
    const core::PatchInfo& info) {
  if (std::optional<std::vector<std::byte>> bytes =
          core::readFullGridPositions(live.dir(), snapshot.model->gridSize(), info)) {
    return encoded.put(info.key, info.version, models::Encoding::PositionsAara, std::move(*bytes),
                       matrixText(info.local2global));
  }
  const core::PatchGrid grid = core::readPatchGrid(live.dir(), *snapshot.model, info);
  const std::span<const float> floats = grid.positions();
  const std::int32_t n = grid.size();
  const std::array<std::int32_t, 2> sizes{n, n};
  std::vector<std::byte> bytes = core::encodeAaraHeader(core::AaraType::V3f, sizes);
  const std::size_t header = bytes.size();
  bytes.resize(header + floats.size_bytes());
  std::memcpy(bytes.data() + header, floats.data(), floats.size_bytes());
  return encoded.put(info.key, info.version, models::Encoding::PositionsAara, std::move(bytes),
                     matrixText(grid.local2global()));
}

/// GET /v1/models/{m}/patches/{p}/positions. A patch whose stored file holds exactly the bytes
/// served (the full grid as V3f) is sent from that file with sendfile(2) like a static file: no
/// decoding, no copy, the page cache holds the bytes, the budget only the open file's entry.
/// Other patches (cropped borders, V3d) are decoded and encoded once, and that encoding is cached
/// in the budget. On a network thread (`onNetworkThread`) it answers only what needs no blocking
/// — a 304, a held open file, a cached encoding — and nullopt otherwise; on the CPU pool it opens
/// or encodes.
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
  const core::ModelSnapshot* snapshot = read->snapshot.get();
  const core::PatchInfo& info = *read->info;
  std::string etag = patchEtag(info);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  const int n = snapshot->model->gridSize();
  const bool asStored = info.stored == core::GridRect{0, 0, n, n};
  http::Response response = positionsResponse(*snapshot, info, std::move(etag));
  // A patch stored whole is cached as its open file, or as a body when the file cannot be sent as
  // it is (V3d): one look for either, one miss counted when neither is there. The handler pool
  // runs this after the network thread's look missed, and counts nothing again.
  std::shared_ptr<const models::EncodedCache::File> file;
  if (asStored) {
    file = served.encoded->findFile(key, info.version, models::StoredKind::Positions, false);
  }
  std::shared_ptr<const models::EncodedCache::Body> body;
  if (file == nullptr) {
    body = served.encoded->find(key, info.version, models::Encoding::PositionsAara, false);
  }
  if (file == nullptr && body == nullptr) {
    if (onNetworkThread) {
      served.encoded->countMiss();
      return std::nullopt;
    }
    if (asStored) {
      if (std::unique_ptr<core::StoredFile> stored =
              core::openFullGridPositions(served.live->dir(), n, info)) {
        try {
          file = served.encoded->putFile(key, info.version, models::StoredKind::Positions,
                                         std::move(stored));
        } catch (const Error& e) {
          if (e.code() != ErrorCode::ResourceExhausted) {
            throw;
          }
          // Every descriptor the cache may hold is being sent: encode this one in the budget.
        }
      }
    }
    if (file == nullptr) {
      body = encodePositions(*served.encoded, *served.live, *snapshot, info);
    }
  }
  if (file != nullptr) {
    response.set("X-VSM-Local2Global", matrixText(info.local2global));
    sendFile(response, std::move(file));
  } else {
    response.set("X-VSM-Local2Global", std::string(body->note()));
    sendBody(response, std::move(body));
  }
  return response;
}

/// The layer a patch's texture entry names ("Diffuse" of "Diffuse\\3_0_1.tif"); empty when the
/// entry has no folder.
std::string_view textureLayer(std::string_view entry) {
  const std::size_t slash = entry.find_first_of("\\/");
  return slash == std::string_view::npos ? std::string_view() : entry.substr(0, slash);
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
  const core::ModelSnapshot* snapshot = read->snapshot.get();
  const core::PatchInfo& info = texturedPatch(id, *read->info, request);
  const std::string etag = patchDataEtag(info, "uv");
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  auto file = served.encoded->findFile(info.key, info.version, models::StoredKind::Coordinates,
                                       onNetworkThread);
  if (file == nullptr) {
    if (onNetworkThread) {
      return std::nullopt;
    }
    // Throws ResourceExhausted (503, retry) while every file the cache may hold is being sent.
    file = served.encoded->putFile(info.key, info.version, models::StoredKind::Coordinates,
                                   core::openCoordinatesFile(served.live->dir(), info));
  }
  http::Response response = textureResponse(*snapshot, info, "application/octet-stream", etag);
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
  const core::ModelSnapshot* snapshot = read->snapshot.get();
  const core::PatchInfo& info = texturedPatch(id, *read->info, request);
  const std::string etag = patchDataEtag(info, "png");
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  auto body =
      served.encoded->find(info.key, info.version, models::Encoding::TexturePng, onNetworkThread);
  if (body == nullptr) {
    if (onNetworkThread) {
      return std::nullopt;
    }
    body = served.encoded->put(
        info.key, info.version, models::Encoding::TexturePng,
        core::readPatchTexturePng(served.live->dir(), info, served.live->texturePixels()));
  }
  http::Response response = textureResponse(*snapshot, info, "image/png", etag);
  response.set("X-VSM-Texture-Layer", std::string(textureLayer(info.textureFile)));
  sendBody(response, std::move(body));
  return response;
}

json cutPatchJson(const core::PatchInfo& info) {
  return {{"key", info.key.toString()},
          {"box", boxJson(info.globalBox)},
          {"resolution", number(info.resolution)},
          {"version", info.version},
          {"leaf", info.isLeaf()}};
}

/// GET /v1/models/{m}/lod: the cut for a box and a resolution, or for a camera (eye=...).
http::Response getLod(const ModelContext& c, const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = c.models.get(id);
  const bool byCamera = request.queryParam("eye").has_value();
  const auto boxText = request.queryParam("box");
  const auto resolutionText = request.queryParam("resolution");
  if (byCamera == (boxText || resolutionText)) {
    throw Error(ErrorCode::InvalidArgument,
                "lod needs either ?box=x0,y0,z0,x1,y1,z1&resolution=r (metres) or a camera: "
                "?eye=x,y,z&dir=x,y,z&up=x,y,z&fov=deg&height=px&sse=px");
  }
  if (!byCamera && (!boxText || !resolutionText)) {
    throw Error(ErrorCode::InvalidArgument,
                "lod needs ?box=x0,y0,z0,x1,y1,z1&resolution=r (metres)");
  }
  // Parsed before the model is read: a bad query is a 400 whatever the model holds.
  const std::optional<LodQuery> boxQuery =
      byCamera ? std::nullopt : std::optional(parseLodQuery(*boxText, *resolutionText));
  const std::optional<CameraQuery> cameraQuery =
      byCamera ? std::optional(parseCameraQuery(request)) : std::nullopt;
  const auto snapshot = versionedSnapshot(*live, request);
  const std::string etag = viewEtag(*snapshot, "l", request.query());
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, http::cache_control::kRevalidate);
  }
  json patches = json::array();
  json body = {{"model", id}, {"version", snapshot->version}};
  if (boxQuery) {
    if (!snapshot->model->empty()) {
      for (const core::PatchKey& key :
           core::lodCut(*snapshot->model, boxQuery->box, boxQuery->resolution)) {
        patches.push_back(cutPatchJson(snapshot->model->at(key)));
      }
    }
    body["box"] = boxJson(boxQuery->box);
    body["resolution"] = boxQuery->resolution;
  } else {
    const core::Camera& camera = cameraQuery->camera;
    for (const core::CameraCutEntry& entry :
         core::lodCutForCamera(*snapshot->model, camera, cameraQuery->maxScreenError)) {
      json patch = cutPatchJson(snapshot->model->at(entry.key));
      patch["screen_error"] = number(entry.screenError);
      patches.push_back(std::move(patch));
    }
    body["camera"] = {{"eye", vecJson(camera.eye)},
                      {"dir", vecJson(camera.dir)},
                      {"up", vecJson(camera.up)},
                      {"fov", camera.fovY * 180 / std::numbers::pi},
                      {"width", camera.width},
                      {"height", camera.height},
                      {"sse", cameraQuery->maxScreenError}};
  }
  body["patches"] = std::move(patches);
  return withCache(http::jsonResponse(200, body), http::cache_control::kRevalidate, etag);
}

}  // namespace

// ---- wire mapping ----------------------------------------------------------------------------

json boxJson(const core::Box3d& box) {
  if (box.empty()) {
    return nullptr;
  }
  return {{"min", vecJson(box.min)}, {"max", vecJson(box.max)}};
}

json modelJson(std::string_view id, const core::ModelSnapshot& snapshot, bool details) {
  const core::Model& model = *snapshot.model;
  const core::PatchInfo* root = model.find(core::PatchKey::root());
  std::size_t leaves = 0;
  double finest = 0;
  for (const auto& [key, info] : model.patches()) {
    if (info.isLeaf()) {
      ++leaves;
      if (info.resolution > 0 && (finest == 0 || info.resolution < finest)) {
        finest = info.resolution;
      }
    }
  }
  json out = {{"id", id},
              {"version", snapshot.version},
              {"grid_size", model.gridSize()},
              {"depth", model.maxDepth()},
              {"patches", model.patchCount()},
              {"leaves", leaves},
              {"bounds", root != nullptr ? boxJson(root->globalBox) : json(nullptr)},
              {"resolution",
               {{"coarsest", root != nullptr ? number(root->resolution) : json(nullptr)},
                {"finest", finest > 0 ? json(finest) : json(nullptr)}}}};
  if (details) {
    json levels = json::array();
    for (const core::LevelSummary& level : model.levels()) {
      levels.push_back({{"depth", level.depth},
                        {"patches", level.patches},
                        {"leaves", level.leaves},
                        {"bounds", boxJson(level.bounds)},
                        {"resolution", number(level.resolution)}});
    }
    out["levels"] = std::move(levels);
  }
  return out;
}

json patchJson(std::string_view id, const core::ModelSnapshot& snapshot,
               const core::PatchInfo& info) {
  json children = json::array();
  for (const core::Quadrant q : core::kQuadrants) {
    if (info.hasChild(q)) {
      children.push_back(info.key.child(q).toString());
    }
  }
  const auto parent = info.key.parent();
  return {
      {"model", id},
      {"model_version", snapshot.version},
      {"key", info.key.toString()},
      {"depth", info.key.depth},
      {"x", info.key.x},
      {"y", info.key.y},
      {"folder", info.folder},
      {"version", info.version},
      {"grid_size", snapshot.model->gridSize()},
      {"box", boxJson(info.globalBox)},
      {"local_box", boxJson(info.localBox)},
      {"local2global", json(info.local2global.m)},
      {"resolution", number(info.resolution)},
      {"stored", rectJson(info.stored)},
      {"parent", parent ? json(parent->toString()) : json(nullptr)},
      {"children", std::move(children)},
      {"leaf", info.isLeaf()},
      {"texture", info.textureFile.empty() ? json(nullptr)
                                           : json{{"layer", textureLayer(info.textureFile)},
                                                  {"coordinates", !info.coordinatesFile.empty()}}}};
}

json hierarchyJson(const core::Model& model, const core::PatchKey& root, int levels) {
  return nodeJson(model, model.at(root), levels);
}

std::string matrixText(const core::Mat4d& m) {
  std::string out;
  char text[32];
  for (std::size_t i = 0; i < m.m.size(); ++i) {
    const auto [end, ec] = std::to_chars(text, text + sizeof text, m.m[i]);
    out.append(i == 0 ? "" : ",");
    out.append(text, ec == std::errc() ? end : text);
  }
  return out;
}

// ---- routes ----------------------------------------------------------------------------------

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
  const core::PatchInfo* info = &findPatch(live.name(), *snapshot, key);
  if (!asked || info->version <= *asked) {
    return VersionedPatch{std::move(snapshot), info};
  }
  // The patch was rewritten after version `asked`: what that version holds is older.
  const std::string rewritten = " (patch " + key.toString() + " of version " +
                                std::to_string(info->version) + ", rewritten after version " +
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

http::Response gzippedJson(models::EncodedCache& encoded, GzippedDocument document,
                           std::uint64_t version, const std::function<json()>& build) {
  const auto variant = static_cast<std::uint8_t>(document);
  auto body = encoded.findModelBody(models::Encoding::JsonGzip, variant, version, true);
  if (body == nullptr) {
    const std::string packed = http::gzip(build().dump());
    const auto* bytes = reinterpret_cast<const std::byte*>(packed.data());
    body = encoded.putModelBody(models::Encoding::JsonGzip, variant, version,
                                std::vector<std::byte>(bytes, bytes + packed.size()));
  }
  http::Response response;
  response.status = 200;
  response.contentType = "application/json";
  response.sharedBody = body->text();
  response.bodyOwner = std::move(body);
  http::setGzipEncoded(response);
  return response;
}

http::Response temporaryRedirect(const std::string& location, std::string_view why) {
  http::Response response = http::errorResponse(
      307, "temporary_redirect", std::string(why) + ": repeat the request at " + location);
  response.set("Location", location);
  response.set("Cache-Control", std::string(http::cache_control::kNoStore));
  return response;
}

void addModelRoutes(http::Router& router, ModelContext context) {
  if (context.diffs == nullptr) {
    context.diffs = DiffGate::create({});
  }
  const auto bind = [context](
                        http::Response (*handler)(const ModelContext&, const http::Request&)) {
    return [context, handler](const http::Request& request) { return handler(context, request); };
  };
  router.add(http::Method::Get, "/v1/models", bind(listModels));
  router.add(http::Method::Post, "/v1/models", bind(postModel));
  router.add(http::Method::Get, "/v1/models/{m}", bind(getModel));
  router.add(http::Method::Delete, "/v1/models/{m}", bind(deleteModel));
  router.add(http::Method::Get, "/v1/models/{m}/hierarchy", bind(getHierarchy));
  router.add(http::Method::Get, "/v1/models/{m}/patches/{p}", bind(getPatch));
  router.add(http::Method::Get, "/v1/models/{m}/revisions", bind(getRevisions));
  router.add(http::Method::Post, "/v1/models/{m}/revisions/{n}/restore", bind(postRestore));
  router.add(http::Method::Get, "/v1/models/{m}/diff", bind(getDiff));
  router.add(http::Method::Get, "/v1/models/{m}/diff.png", bind(getDiffPng));
  // Routes with an inline handler: answered on the network thread when cached.
  using Inline = std::optional<http::Response> (*)(const ModelContext&, const http::Request&, bool);
  const auto addCached = [&](const char* pattern, Inline handler) {
    router.add(
        http::Method::Get, pattern,
        [context, handler](const http::Request& request) {
          return *handler(context, request, false);
        },
        [context, handler](const http::Request& request) {
          return handler(context, request, true);
        });
  };
  addCached("/v1/models/{m}/patches/{p}/coordinates", coordinates);
  addCached("/v1/models/{m}/patches/{p}/texture", texture);
  addCached("/v1/models/{m}/patches/{p}/texture/{layer}", texture);
  router.add(http::Method::Get, "/v1/models/{m}/lod", bind(getLod));
  addCached("/v1/models/{m}/patches/{p}/positions", positions);
}

}  // namespace vsm::server::api
