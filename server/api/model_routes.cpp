#include "server/api/model_routes.hpp"

#include <algorithm>
#include <bit>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <list>
#include <mutex>
#include <set>
#include <unordered_map>

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/uio.h>
#include <unistd.h>

#include <nlohmann/json.hpp>

#include "core/cache/patch_cache.hpp"
#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
#include "server/jobs/job_registry.hpp"
#include "server/jobs/model_jobs.hpp"
#include "server/models/model_registry.hpp"

namespace vsm::server::api {

namespace fs = std::filesystem;
using core::Error;
using core::ErrorCode;
using nlohmann::json;

namespace {

/// The .aara bytes of a patch's positions in an anonymous in-memory file (memfd), sealed against
/// writes, so that the server can send them with sendfile(2) like a static file.
struct PositionFile {
  int fd = -1;
  std::size_t size = 0;
  PositionFile() = default;
  PositionFile(const PositionFile&) = delete;
  PositionFile& operator=(const PositionFile&) = delete;
  ~PositionFile() {
    if (fd >= 0) {
      ::close(fd);
    }
  }
};

/// What a positions response holds until written: the grid (the bytes in memory) and its file.
struct PositionBody {
  std::shared_ptr<const core::PatchGrid> grid;
  std::shared_ptr<const PositionFile> file;
};

/// The position files of recently served grids, least recently used dropped first, bounded in
/// bytes (memory outside the patch cache's budget: a quarter of it, at most 256 MiB). Keyed by
/// the cached grid object, which is immutable and unique to one version of one patch of one
/// open model; an entry whose grid has gone (evicted, a newer version published, the model
/// closed) is never served and is replaced on the next use of its address.
///
/// Thread-safe: one mutex guards the table, the LRU list and the byte count; it is not held while
/// a file is made (a copy of the grid: two threads may make one each, the first in wins).
class PositionFiles {
 public:
  explicit PositionFiles(std::size_t limit) : limit_(limit) {}

  /// The file of `grid`, made on first use; nullptr when it would not fit or the system has no
  /// memfd (the caller then writes from memory).
  std::shared_ptr<const PositionFile> get(const std::shared_ptr<const core::PatchGrid>& grid) {
    {
      const std::lock_guard lock(mutex_);
      const auto it = entries_.find(grid.get());
      if (it != entries_.end() && it->second.grid.lock() == grid) {
        lru_.splice(lru_.end(), lru_, it->second.lru);
        return it->second.file;
      }
    }
    const std::size_t size = 13 + grid->positions().size_bytes();
    if (size > limit_) {
      return nullptr;
    }
    auto file = make(*grid, size);
    if (!file) {
      return nullptr;
    }
    const std::lock_guard lock(mutex_);
    auto it = entries_.find(grid.get());
    if (it != entries_.end()) {
      if (it->second.grid.lock() == grid) {
        return it->second.file;  // another thread was first
      }
      erase(it);  // a dead grid's entry at a reused address
    }
    while (bytes_ + size > limit_ && !lru_.empty()) {
      erase(entries_.find(lru_.front()));
    }
    lru_.push_back(grid.get());
    entries_.emplace(grid.get(), Entry{grid, file, std::prev(lru_.end())});
    bytes_ += size;
    return file;
  }

 private:
  struct Entry {
    std::weak_ptr<const core::PatchGrid> grid;
    std::shared_ptr<const PositionFile> file;
    std::list<const void*>::iterator lru;
  };

  static std::shared_ptr<const PositionFile> make(const core::PatchGrid& grid, std::size_t size) {
    auto file = std::make_shared<PositionFile>();
    file->fd = ::memfd_create("vsm-positions", MFD_CLOEXEC | MFD_ALLOW_SEALING);
    if (file->fd < 0) {
      return nullptr;
    }
    const std::string header = aaraHeader(grid.size());
    const std::span<const float> floats = grid.positions();
    const iovec parts[2] = {{const_cast<char*>(header.data()), header.size()},
                            {const_cast<float*>(floats.data()), floats.size_bytes()}};
    std::size_t written = 0;
    while (written < size) {
      // One writev for the common case; a short write continues from where it stopped.
      iovec rest[2];
      int count = 0;
      std::size_t skip = written;
      for (const iovec& part : parts) {
        if (skip >= part.iov_len) {
          skip -= part.iov_len;
          continue;
        }
        rest[count++] = {static_cast<char*>(part.iov_base) + skip, part.iov_len - skip};
        skip = 0;
      }
      const ssize_t n = ::writev(file->fd, rest, count);
      if (n < 0 && errno == EINTR) {
        continue;
      }
      if (n <= 0) {
        return nullptr;
      }
      written += static_cast<std::size_t>(n);
    }
    // Sealed: nobody can change the bytes a response is being sent from.
    ::fcntl(file->fd, F_ADD_SEALS, F_SEAL_SHRINK | F_SEAL_GROW | F_SEAL_WRITE | F_SEAL_SEAL);
    file->size = size;
    return file;
  }

  void erase(std::unordered_map<const void*, Entry>::iterator it) {
    bytes_ -= it->second.file->size;
    lru_.erase(it->second.lru);
    entries_.erase(it);
  }

  const std::size_t limit_;
  std::mutex mutex_;  // guards entries_, lru_ and bytes_
  std::unordered_map<const void*, Entry> entries_;
  std::list<const void*> lru_;  // least recently used first
  std::size_t bytes_ = 0;
};

/// Patch metadata and data: revalidated after a minute. The URL names no version, so a merge
/// changes what it returns; a minute of staleness in client caches is the trade for fewer
/// round trips (the ETag makes the revalidation cheap).
constexpr std::string_view kPatchCacheControl = "public, max-age=60";

/// FNV-1a, 64 bits: a digest for entity tags (not a security boundary: the server makes them).
class Digest {
 public:
  void add(const void* data, std::size_t size) {
    const auto* bytes = static_cast<const unsigned char*>(data);
    for (std::size_t i = 0; i < size; ++i) {
      hash_ = (hash_ ^ bytes[i]) * 1099511628211ull;
    }
  }
  template <typename T>
  void add(const T& value) {
    static_assert(std::is_trivially_copyable_v<T>);
    add(&value, sizeof value);
  }
  void add(std::string_view text) {
    add(text.size());
    add(text.data(), text.size());
  }
  void add(const core::Box3d& box) {
    for (const double v : {box.min.x, box.min.y, box.min.z, box.max.x, box.max.y, box.max.z}) {
      add(v);
    }
  }
  std::string hex() const {
    char text[17];
    std::snprintf(text, sizeof text, "%016llx", static_cast<unsigned long long>(hash_));
    return text;
  }

 private:
  std::uint64_t hash_ = 14695981039346656037ull;
};

void addPatch(Digest& digest, const core::PatchInfo& info) {
  digest.add(info.key.depth);
  digest.add(info.key.x);
  digest.add(info.key.y);
  digest.add(info.version);
  digest.add(std::string_view(info.folder));
  digest.add(info.childMask);
  digest.add(info.globalBox);
  digest.add(info.local2global.m);
}

Digest modelDigest(const core::ModelSnapshot& snapshot) {
  Digest digest;
  digest.add(snapshot.model->gridSize());
  for (const auto& [key, info] : snapshot.model->patches()) {
    addPatch(digest, info);
  }
  return digest;
}

/// The entity tag of a view of the model chosen by the query (hierarchy, LOD cut).
std::string viewEtag(const core::ModelSnapshot& snapshot, std::string_view view,
                     std::string_view query) {
  Digest digest = modelDigest(snapshot);
  digest.add(view);
  digest.add(query);
  return http::strongEtag(std::string(view) + digest.hex());
}

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

/// The JSON object body of a write; rejects members other than `allowed` (typos fail loudly).
json objectBody(const http::Request& request, std::initializer_list<std::string_view> allowed) {
  json body = http::jsonBody(request);
  if (!body.is_object()) {
    throw Error(ErrorCode::InvalidArgument, "request body must be a JSON object");
  }
  for (const auto& [key, value] : body.items()) {
    if (std::find(allowed.begin(), allowed.end(), key) == allowed.end()) {
      throw Error(ErrorCode::InvalidArgument, "unknown member '" + key.substr(0, 64) + "'");
    }
  }
  return body;
}

const std::string& stringMember(const json& object, const char* name) {
  const auto it = object.find(name);
  if (it == object.end() || !it->is_string()) {
    throw Error(ErrorCode::InvalidArgument, std::string("'") + name + "' must be a string");
  }
  return it->get_ref<const std::string&>();
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

double parseNumber(std::string_view text, std::string_view what) {
  double value = 0;
  const auto [end, ec] = std::from_chars(text.data(), text.data() + text.size(), value);
  if (text.empty() || ec != std::errc() || end != text.data() + text.size() ||
      !std::isfinite(value)) {
    throw Error(ErrorCode::InvalidArgument, std::string(what) + " must be a finite number, not '" +
                                                std::string(text.substr(0, 32)) + "'");
  }
  return value;
}

void descend(const core::Model& model, const core::PatchKey& key, const core::Box3d& box,
             double resolution, std::vector<core::PatchKey>& out) {
  const core::PatchInfo& info = model.at(key);
  if (!info.globalBox.intersects(box)) {
    return;
  }
  if (info.isLeaf() || info.resolution <= resolution) {
    out.push_back(key);
    return;
  }
  for (const core::Quadrant q : core::kQuadrants) {
    if (info.hasChild(q)) {
      descend(model, key.child(q), box, resolution, out);
    }
  }
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

http::Response postModel(const ModelContext& c, const http::Request& request) {
  const json body = objectBody(request, {"id", "source"});
  const std::string& id = stringMember(body, "id");
  models::checkModelId(id);
  const auto source = body.find("source");
  if (source == body.end() || !source->is_object()) {
    throw Error(ErrorCode::InvalidArgument,
                R"('source' must be an object: {"path": ...} or {"import": ..., "patch_size": N})");
  }
  for (const auto& [key, value] : source->items()) {
    if (key != "path" && key != "import" && key != "patch_size") {
      throw Error(ErrorCode::InvalidArgument, "unknown member 'source." + key.substr(0, 64) + "'");
    }
  }
  const bool byPath = source->contains("path");
  if (byPath == source->contains("import")) {
    throw Error(ErrorCode::InvalidArgument, "'source' needs exactly one of 'path' and 'import'");
  }
  if (byPath) {
    if (source->contains("patch_size")) {
      throw Error(ErrorCode::InvalidArgument, "'patch_size' goes with 'import' only");
    }
    const fs::path dir = models::resolveInside(c.models.dataRoot(), stringMember(*source, "path"));
    std::error_code ec;
    if (!fs::is_directory(dir, ec)) {
      throw Error(ErrorCode::NotFound, "source path is not a directory in the data root");
    }
    const auto live = c.models.open(id, dir);
    http::Response response = http::jsonResponse(201, modelJson(id, *live->snapshot(), true));
    response.set("Location", "/v1/models/" + id);
    return withCache(std::move(response), http::cache_control::kNoStore);
  }
  int patchSize = 257;
  if (const auto size = source->find("patch_size"); size != source->end()) {
    if (!size->is_number_integer()) {
      throw Error(ErrorCode::InvalidArgument, "'patch_size' must be an integer (2^n + 1)");
    }
    const auto value = size->get<std::int64_t>();
    patchSize = value < 0 || value > 1'000'000 ? -1 : static_cast<int>(value);
  }
  const fs::path input =
      models::resolveInside(c.models.dataRoot(), stringMember(*source, "import"));
  const jobs::JobStatus job = jobs::submitImport(c.jobs, c.models, id, input, patchSize);
  http::Response response = http::jsonResponse(202, jobs::toJson(job));
  response.set("Location", "/v1/jobs/" + job.id);
  return response;
}

http::Response getModel(const ModelContext& c, const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = c.models.get(id);
  const auto snapshot = live->snapshot();
  const std::string etag = modelEtag(*snapshot);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, http::cache_control::kRevalidate);
  }
  return withCache(http::jsonResponse(200, modelJson(id, *snapshot, true)),
                   http::cache_control::kRevalidate, etag);
}

http::Response deleteModel(const ModelContext& c, const http::Request& request) {
  c.models.close(request.param("m"));
  http::Response response;
  response.status = 204;
  return response;
}

http::Response getHierarchy(const ModelContext& c, const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = c.models.get(id);
  const auto snapshot = live->snapshot();
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
  const auto snapshot = live->snapshot();
  const core::PatchInfo& info = findPatch(id, *snapshot, key);
  const std::string etag = patchEtag(info);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  return withCache(http::jsonResponse(200, patchJson(id, *snapshot, info)), kPatchCacheControl,
                   etag);
}

http::Response getPositions(const ModelContext& c, PositionFiles& files,
                            const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = c.models.get(id);
  const core::PatchKey key = parseKey(request.param("p"));
  const auto snapshot = live->snapshot();
  const core::PatchInfo& info = findPatch(id, *snapshot, key);
  const std::string etag = patchEtag(info);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  http::Response response;
  {
    // This runs on the CPU pool (every handler does): a miss reads the disk here. The pin is
    // released before the snapshot and the model.
    const core::PatchCache::Pin pin = live->positions(*snapshot, key);
    const auto grid = pin.get<core::PatchGrid>();
    // The .aara payload is the grid's own float array: it is written to the socket from the
    // cache, not copied (a 257 x 257 patch is 774 KiB; copying it per request halved the rate).
    // The published grid is immutable; the response holds it until written. Should the cache
    // evict it meanwhile, its bytes outlive their charge for that long, as a copy would.
    response.body = aaraHeader(grid->size());
    const std::span<const float> floats = grid->positions();
    response.sharedBody =
        std::string_view(reinterpret_cast<const char*>(floats.data()), floats.size_bytes());
    // The same bytes as a file for sendfile(2), when one can be had within its bound.
    auto file = files.get(grid);
    response.bodyFd = file ? file->fd : -1;
    response.bodyOwner = std::make_shared<const PositionBody>(PositionBody{grid, std::move(file)});
    response.set("X-VSM-Local2Global", matrixText(grid->local2global()));
    response.set("X-VSM-Grid-Size", std::to_string(grid->size()));
  }
  response.contentType = "application/octet-stream";
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  response.set("X-VSM-Patch-Version", std::to_string(info.version));
  return withCache(std::move(response), kPatchCacheControl, etag);
}

http::Response getLod(const ModelContext& c, const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = c.models.get(id);
  const auto boxText = request.queryParam("box");
  const auto resolutionText = request.queryParam("resolution");
  if (!boxText || !resolutionText) {
    throw Error(ErrorCode::InvalidArgument,
                "lod needs ?box=x0,y0,z0,x1,y1,z1&resolution=r (metres)");
  }
  const LodQuery query = parseLodQuery(*boxText, *resolutionText);
  const auto snapshot = live->snapshot();
  const std::string etag = viewEtag(*snapshot, "l", request.query());
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, http::cache_control::kRevalidate);
  }
  json patches = json::array();
  if (!snapshot->model->empty()) {
    for (const core::PatchKey& key : lodCut(*snapshot->model, query.box, query.resolution)) {
      const core::PatchInfo& info = snapshot->model->at(key);
      patches.push_back({{"key", key.toString()},
                         {"box", boxJson(info.globalBox)},
                         {"resolution", number(info.resolution)},
                         {"version", info.version},
                         {"leaf", info.isLeaf()}});
    }
  }
  json body = {{"model", id},
               {"version", snapshot->version},
               {"box", boxJson(query.box)},
               {"resolution", query.resolution},
               {"patches", std::move(patches)}};
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
  return {{"model", id},
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
          {"leaf", info.isLeaf()}};
}

json hierarchyJson(const core::Model& model, const core::PatchKey& root, int levels) {
  return nodeJson(model, model.at(root), levels);
}

std::string aaraHeader(std::size_t gridSize) {
  static_assert(std::endian::native == std::endian::little, ".aara is little-endian");
  const auto size = static_cast<std::int32_t>(gridSize);
  std::string out(13, '\0');
  char* p = out.data();
  *p++ = 3;
  std::memcpy(p, "V3f", 3);
  p += 3;
  *p++ = 2;
  std::memcpy(p, &size, 4);
  std::memcpy(p + 4, &size, 4);
  return out;
}

std::string positionsAara(const core::PatchGrid& grid) {
  const std::span<const float> floats = grid.positions();
  std::string out = aaraHeader(grid.size());
  out.append(reinterpret_cast<const char*>(floats.data()), floats.size_bytes());
  return out;
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

std::string modelEtag(const core::ModelSnapshot& snapshot) {
  return http::strongEtag("m" + modelDigest(snapshot).hex());
}

std::string patchEtag(const core::PatchInfo& info) {
  Digest digest;
  addPatch(digest, info);
  return http::strongEtag(info.key.toString() + "-v" + std::to_string(info.version) + "-" +
                          digest.hex().substr(0, 8));
}

LodQuery parseLodQuery(std::string_view box, std::string_view resolution) {
  LodQuery out;
  double v[6];
  std::size_t count = 0;
  for (std::string_view rest = box;;) {
    const std::size_t comma = rest.find(',');
    if (count == 6) {
      count = 7;
      break;
    }
    v[count++] = parseNumber(rest.substr(0, comma), "each box coordinate");
    if (comma == std::string_view::npos) {
      break;
    }
    rest.remove_prefix(comma + 1);
  }
  if (count != 6) {
    throw Error(ErrorCode::InvalidArgument, "box must be six numbers x0,y0,z0,x1,y1,z1");
  }
  if (v[0] > v[3] || v[1] > v[4] || v[2] > v[5]) {
    throw Error(ErrorCode::InvalidArgument, "box must have x0 <= x1, y0 <= y1 and z0 <= z1");
  }
  out.box.min = {v[0], v[1], v[2]};
  out.box.max = {v[3], v[4], v[5]};
  out.resolution = parseNumber(resolution, "resolution");
  if (out.resolution <= 0) {
    throw Error(ErrorCode::InvalidArgument, "resolution must be greater than 0 (metres)");
  }
  return out;
}

std::vector<core::PatchKey> lodCut(const core::Model& model, const core::Box3d& box,
                                   double resolution) {
  std::vector<core::PatchKey> out;
  if (model.find(core::PatchKey::root()) != nullptr) {
    descend(model, core::PatchKey::root(), box, resolution, out);
  }
  std::sort(out.begin(), out.end());
  return out;
}

// ---- routes ----------------------------------------------------------------------------------

void addModelRoutes(http::Router& router, ModelContext context) {
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
  const auto files = std::make_shared<PositionFiles>(
      std::min<std::size_t>(context.models.cache().budgetBytes() / 4, std::size_t{256} << 20));
  router.add(http::Method::Get, "/v1/models/{m}/patches/{p}/positions",
             [context, files](const http::Request& request) {
               return getPositions(context, *files, request);
             });
  router.add(http::Method::Get, "/v1/models/{m}/lod", bind(getLod));
}

}  // namespace vsm::server::api
