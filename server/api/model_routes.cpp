#include "server/api/model_routes.hpp"

#include <algorithm>
#include <bit>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <optional>
#include <set>
#include <span>

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/uio.h>
#include <unistd.h>

#include <nlohmann/json.hpp>

#include "core/cache/patch_cache.hpp"
#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/opc/texture_file.hpp"
#include "core/pyramid/model.hpp"
#include "core/store/live_model.hpp"
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

/// The .aara bytes of one version of a patch's positions in an anonymous in-memory file (memfd),
/// sealed against writes and mapped read-only: the server sends it with sendfile(2) like a static
/// file, and every response is answered from it without the grid it was made from. Cached in the
/// model's EncodedCache (MemoryCategory::PositionFiles), so it counts against the memory budget.
class AaraFile {
 public:
  /// The file of `grid`; nullptr when the system has no memfd or it cannot be written or mapped
  /// (the caller then answers from the grid).
  static std::shared_ptr<const AaraFile> make(const core::PatchGrid& grid) {
    auto file = std::make_shared<AaraFile>();
    file->fd_ = ::memfd_create("vsm-positions", MFD_CLOEXEC | MFD_ALLOW_SEALING);
    if (file->fd_ < 0) {
      return nullptr;
    }
    const std::string header = aaraHeader(grid.size());
    const std::span<const float> floats = grid.positions();
    const std::size_t size = header.size() + floats.size_bytes();
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
      const ssize_t n = ::writev(file->fd_, rest, count);
      if (n < 0 && errno == EINTR) {
        continue;
      }
      if (n <= 0) {
        return nullptr;
      }
      written += static_cast<std::size_t>(n);
    }
    // Sealed: nobody can change the bytes a response is being sent from.
    ::fcntl(file->fd_, F_ADD_SEALS, F_SEAL_SHRINK | F_SEAL_GROW | F_SEAL_WRITE | F_SEAL_SEAL);
    void* map = ::mmap(nullptr, size, PROT_READ, MAP_SHARED, file->fd_, 0);
    if (map == MAP_FAILED) {
      return nullptr;
    }
    file->map_ = map;
    file->size_ = size;
    file->gridSize_ = std::to_string(grid.size());
    file->local2global_ = matrixText(grid.local2global());
    return file;
  }

  AaraFile() = default;
  AaraFile(const AaraFile&) = delete;
  AaraFile& operator=(const AaraFile&) = delete;
  ~AaraFile() {
    if (map_ != nullptr) {
      ::munmap(map_, size_);
    }
    if (fd_ >= 0) {
      ::close(fd_);
    }
  }

  int fd() const { return fd_; }
  /// The whole .aara file: header and floats (the mapping shares the file's pages).
  std::string_view bytes() const { return {static_cast<const char*>(map_), size_}; }
  /// Values of the X-VSM-Grid-Size and X-VSM-Local2Global headers.
  const std::string& gridSize() const { return gridSize_; }
  const std::string& local2global() const { return local2global_; }

 private:
  int fd_ = -1;
  void* map_ = nullptr;
  std::size_t size_ = 0;
  std::string gridSize_;
  std::string local2global_;
};

/// The size of aaraHeader(): what precedes the floats.
constexpr std::size_t kAaraHeaderBytes = 13;

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

/// GET /v1/models/{m}/patches/{p}/positions. On a network thread (`onNetworkThread`) it answers
/// only what needs no blocking — a 304, or the patch's .aara file when cached — and nullopt
/// otherwise; on the CPU pool it reads the grid through the patch cache (a miss reads the disk)
/// and caches its file.
std::optional<http::Response> positions(const ModelContext& c, const http::Request& request,
                                        bool onNetworkThread) {
  const std::string& id = request.param("m");
  const models::ModelRegistry::Served served = c.models.getServed(id);
  const core::PatchKey key = parseKey(request.param("p"));
  const auto snapshot = served.live->snapshot();
  const core::PatchInfo& info = findPatch(id, *snapshot, key);
  std::string etag = patchEtag(info);
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  const core::ObjectId fileId{key, info.version, core::MemoryCategory::PositionFiles};
  // The handler pool runs this after the network thread's look missed: count that miss once.
  std::shared_ptr<const AaraFile> file = served.encoded->find<AaraFile>(fileId, onNetworkThread);
  http::Response response;
  if (file == nullptr) {
    if (onNetworkThread) {
      return std::nullopt;
    }
    // The pin is released before the snapshot and the model.
    const core::PatchCache::Pin pin = served.live->positions(*snapshot, key);
    const auto grid = pin.get<core::PatchGrid>();
    file = AaraFile::make(*grid);
    if (file != nullptr) {
      try {
        served.encoded->put(fileId, file, file->bytes().size());
      } catch (const Error& e) {
        if (e.code() != ErrorCode::ResourceExhausted) {
          throw;
        }
        file = nullptr;  // no room beside what is pinned: answer from the grid, uncached
      }
    }
    if (file == nullptr) {
      // The .aara payload is the grid's own float array, written to the socket from the cache
      // without a copy. The published grid is immutable; the response holds it until written.
      // Should the cache evict it meanwhile, its bytes outlive their charge for that long.
      response.body = aaraHeader(grid->size());
      const std::span<const float> floats = grid->positions();
      response.sharedBody =
          std::string_view(reinterpret_cast<const char*>(floats.data()), floats.size_bytes());
      response.bodyOwner = grid;
      response.set("X-VSM-Local2Global", matrixText(grid->local2global()));
      response.set("X-VSM-Grid-Size", std::to_string(grid->size()));
    }
  }
  if (file != nullptr) {
    // Sent with sendfile(2) from the file; the response holds it until written (should the cache
    // evict it meanwhile, its bytes outlive their charge for that long). As a body in memory: the
    // 13-byte .aara header, then the floats from the file's mapping.
    const std::string_view bytes = file->bytes();
    response.body = bytes.substr(0, kAaraHeaderBytes);
    response.sharedBody = bytes.substr(kAaraHeaderBytes);
    response.bodyFd = file->fd();
    response.set("X-VSM-Local2Global", file->local2global());
    response.set("X-VSM-Grid-Size", file->gridSize());
    response.bodyOwner = std::move(file);
  }
  response.contentType = "application/octet-stream";
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  response.set("X-VSM-Patch-Version", std::to_string(info.version));
  response.set("Cache-Control", std::string(kPatchCacheControl));
  response.set("ETag", std::move(etag));
  return response;
}

/// The layer a patch's texture entry names ("Diffuse" of "Diffuse\\3_0_1.tif"); empty when the
/// entry has no folder.
std::string_view textureLayer(std::string_view entry) {
  const std::size_t slash = entry.find_first_of("\\/");
  return slash == std::string_view::npos ? std::string_view() : entry.substr(0, slash);
}

/// The patch of a texture or coordinates request, 404 unless it has a texture (of the requested
/// layer, when the route names one).
const core::PatchInfo& texturedPatch(std::string_view id, const core::ModelSnapshot& snapshot,
                                     const http::Request& request) {
  const core::PatchInfo& info = findPatch(id, snapshot, parseKey(request.param("p")));
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

/// GET /v1/models/{m}/patches/{p}/coordinates: the texture coordinates file (.aara) as stored.
http::Response getCoordinates(const ModelContext& c, const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = c.models.get(id);
  const auto snapshot = live->snapshot();
  const core::PatchInfo& info = texturedPatch(id, *snapshot, request);
  const std::string etag = http::strongEtag(std::string(http::opaqueOf(patchEtag(info))) + "-uv");
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  const std::vector<std::byte> bytes = core::readPatchCoordinates(live->dir(), info);
  http::Response response;
  response.body.assign(reinterpret_cast<const char*>(bytes.data()), bytes.size());
  response.contentType = "application/octet-stream";
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  response.set("X-VSM-Patch-Version", std::to_string(info.version));
  return withCache(std::move(response), kPatchCacheControl, etag);
}

/// GET /v1/models/{m}/patches/{p}/texture[/{layer}]: the texture tile as PNG.
http::Response getTexture(const ModelContext& c, const http::Request& request) {
  const std::string& id = request.param("m");
  const auto live = c.models.get(id);
  const auto snapshot = live->snapshot();
  const core::PatchInfo& info = texturedPatch(id, *snapshot, request);
  const std::string etag = http::strongEtag(std::string(http::opaqueOf(patchEtag(info))) + "-png");
  if (http::ifNoneMatch(request, etag)) {
    return http::notModified(etag, kPatchCacheControl);
  }
  const std::vector<std::byte> png = core::readPatchTexturePng(live->dir(), info);
  http::Response response;
  response.body.assign(reinterpret_cast<const char*>(png.data()), png.size());
  response.contentType = "image/png";
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  response.set("X-VSM-Patch-Version", std::to_string(info.version));
  response.set("X-VSM-Texture-Layer", std::string(textureLayer(info.textureFile)));
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

std::string aaraHeader(std::size_t gridSize) {
  static_assert(std::endian::native == std::endian::little, ".aara is little-endian");
  const auto size = static_cast<std::int32_t>(gridSize);
  std::string out(kAaraHeaderBytes, '\0');
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
  router.add(
      http::Method::Get, "/v1/models/{m}/patches/{p}/positions",
      [context](const http::Request& request) { return *positions(context, request, false); },
      [context](const http::Request& request) { return positions(context, request, true); });
  router.add(http::Method::Get, "/v1/models/{m}/patches/{p}/coordinates", bind(getCoordinates));
  router.add(http::Method::Get, "/v1/models/{m}/patches/{p}/texture", bind(getTexture));
  router.add(http::Method::Get, "/v1/models/{m}/patches/{p}/texture/{layer}", bind(getTexture));
  router.add(http::Method::Get, "/v1/models/{m}/lod", bind(getLod));
}

}  // namespace vsm::server::api
