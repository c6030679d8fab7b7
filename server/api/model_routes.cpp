#include "server/api/model_routes.hpp"

#include <algorithm>
#include <bit>
#include <charconv>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <numbers>
#include <optional>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/common/progress.hpp"
#include "core/diff/diff_json.hpp"
#include "core/diff/diff_picture.hpp"
#include "core/diff/revision_diff.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "core/tiles/lod_cut.hpp"
#include "server/api/diff_gate.hpp"
#include "server/api/patch_routes.hpp"
#include "server/jobs/job_registry.hpp"
#include "server/jobs/model_jobs.hpp"
#include "server/models/encoded_cache.hpp"
#include "server/models/model_registry.hpp"
#include "server/models/patch_data.hpp"

namespace vsm::server::api {

namespace fs = std::filesystem;
using core::Error;
using core::ErrorCode;
using nlohmann::json;

namespace {

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

json nodeJson(const core::Model& model, const core::PatchInfo& info, int levels) {
  json node = {{"key", info.key.toString()},
               {"box", boxJson(info.globalBox)},
               {"resolution", number(info.resolution)},
               {"version", info.version},
               {"leaf", info.isLeaf()},
               {"child_count", std::popcount(static_cast<unsigned>(info.childMask))}};
  if (info.hidden) {
    node["hidden"] = true;
  }
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

/// Stops a diff at its next leaf once its slot's deadline has passed or its client has gone (the
/// diff reports progress after every leaf and checks the token before the next).
class DiffStop final : public core::Progress {
 public:
  DiffStop(std::chrono::steady_clock::time_point deadline, const http::Request& request,
           core::CancelToken& cancel)
      : deadline_(deadline), request_(request), cancel_(cancel) {}
  void report(std::string_view, double) override {
    if (std::chrono::steady_clock::now() >= deadline_) {
      cancel_.cancel();
    } else if (request_.clientGone()) {
      abandoned_ = true;
      cancel_.cancel();
    }
  }
  bool abandoned() const { return abandoned_; }

 private:
  std::chrono::steady_clock::time_point deadline_;
  const http::Request& request_;
  core::CancelToken& cancel_;
  bool abandoned_ = false;
};

/// The working memory of a diff with a map of `mapSize` pixels along its longer side, allocated
/// outside the cache: the spatial index (core::kDiffIndexBytes at most, the CLI's bound too), and
/// the map's floats, the RGBA picture and, at most as large again, the PNG.
std::size_t diffWorkBytes(int mapSize) {
  const auto pixels = static_cast<std::size_t>(mapSize) * static_cast<std::size_t>(mapSize);
  return core::kDiffIndexBytes + pixels * (sizeof(float) + 4 + 4);
}

/// The diff a request asks for: between the kept revisions ?from=A and ?to=B of model {m}, with a
/// map of `mapSize` pixels along its longer side when > 0. Runs inside the gate (a slot held
/// throughout, 503 when none is free), with its work memory (diffWorkBytes) charged to the budget
/// (Encoding::DiffWork) while it runs, is drawn and encoded, and stops at the slot's deadline (503)
/// or when its client closes the connection (Cancelled, answered to nobody).
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
  DiffStop stop(slot->deadline(), request, cancel);
  core::DiffOptions options;
  options.mapSize = mapSize;
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
  options.progress = &stop;
  try {
    return finish(core::diffRevisions(*served.live, served.live->snapshotAt(from),
                                      served.live->snapshotAt(to), options));
  } catch (const Error& e) {
    if (e.code() != ErrorCode::Cancelled || !cancel.cancelled()) {
      throw;
    }
    if (stop.abandoned()) {
      c.diffs->countAbandoned();
      throw Error(ErrorCode::Cancelled, "the client of the diff went away; it was stopped");
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
  const jobs::JobStatus job = jobs::submitImport(
      c.jobs, c.models, id, input, body.patchSize,
      body.untextured ? core::ImportOptions::Drape::None : core::ImportOptions::Drape::ShadedRelief,
      body.visibleTexelsPerQuad);
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
  // From the levels' sums, which a model keeps per shared chunk: no walk of every patch (a model
  // of 10^6 patches is polled for its version).
  const std::vector<core::LevelSummary> summary = model.levels();
  std::size_t leaves = 0;
  double finest = 0;
  for (const core::LevelSummary& level : summary) {
    leaves += level.leaves;
    if (level.finestLeaf > 0 && (finest == 0 || level.finestLeaf < finest)) {
      finest = level.finestLeaf;
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
    for (const core::LevelSummary& level : summary) {
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
  return {{"model", id},
          {"model_version", snapshot.version},
          {"key", info.key.toString()},
          {"depth", info.key.depth},
          {"x", info.key.x},
          {"y", info.key.y},
          {"folder", info.folder()},
          {"version", info.version},
          {"grid_size", snapshot.model->gridSize()},
          {"box", boxJson(info.globalBox)},
          {"local_box", boxJson(info.localBox)},
          {"local2global", json(info.local2global().m)},
          {"resolution", number(info.resolution)},
          {"stored", rectJson(info.stored)},
          {"parent", parent ? json(parent->toString()) : json(nullptr)},
          {"children", std::move(children)},
          {"leaf", info.isLeaf()},
          {"texture", info.textureFile().empty()
                          ? json(nullptr)
                          : json{{"layer", textureLayer(info.textureFile())},
                                 {"coordinates", !info.coordinatesFile().empty()}}}};
}

json hierarchyJson(const core::Model& model, const core::PatchKey& root, int levels) {
  return nodeJson(model, model.at(root), levels);
}

void addModelRoutes(http::Router& router, ModelContext context) {
  if (context.diffs == nullptr) {
    context.diffs = DiffGate::create({});
  }
  if (context.data == nullptr) {
    context.data = std::make_shared<models::PatchData>();
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
  router.add(http::Method::Get, "/v1/models/{m}/lod", bind(getLod));
  addPatchDataRoutes(router, context);
}

}  // namespace vsm::server::api
