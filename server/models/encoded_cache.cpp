#include "server/models/encoded_cache.hpp"

#include <exception>
#include <optional>
#include <type_traits>
#include <utility>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/store/live_model.hpp"

namespace vsm::server::models {

using core::Error;
using core::ErrorCode;

namespace {

/// Bookkeeping bytes charged for an open file: the entry and the file object (its pages live in
/// the kernel's page cache, outside the budget).
constexpr std::size_t kOpenFileBytes = 256;

}  // namespace

std::string_view toString(Encoding encoding) {
  switch (encoding) {
    case Encoding::PositionsAara:
      return "aara";
    case Encoding::Glb:
      return "glb";
    case Encoding::TexturePng:
      return "png";
    case Encoding::Terrain:
      return "terrain";
    case Encoding::GlbMeshopt:
      return "glb_meshopt";
    case Encoding::JsonGzip:
      return "json_gzip";
    case Encoding::DiffWork:
      return "diff";
    case Encoding::HeightWork:
      return "heights";
    case Encoding::TerrainRgb:
      return "terrain_rgb";
    case Encoding::RayWork:
      return "rays";
  }
  return "unknown";
}

namespace {

core::ObjectId bodyId(const core::PatchKey& key, std::uint64_t version, Encoding encoding) {
  return {key, version, core::MemoryCategory::Encoded, static_cast<std::uint8_t>(encoding)};
}

/// The key of a model-wide body: depth -1 is no patch's.
core::PatchKey modelBodyKey(std::uint8_t variant) {
  return {-1, variant, 0};
}

core::ObjectId fileId(const core::PatchKey& key, std::uint64_t version, StoredKind kind) {
  return {key, version, core::MemoryCategory::OpenFiles, static_cast<std::uint8_t>(kind)};
}

}  // namespace

/// Encoded responses and open files are put() into the cache, never loaded by it; they are clean,
/// so they are never written back either.
class EncodedCache::Store final : public core::PatchStore {
 public:
  std::size_t expectedBytes(const core::ObjectId&) const override { return 0; }
  core::CacheValue load(const core::ObjectId& id) override {
    throw Error(ErrorCode::Internal,
                "encoded response " + id.key.toString() + " is made by the server, not loaded");
  }
  void writeBack(const core::ObjectId& id, const core::CacheValue&) override {
    throw Error(ErrorCode::Internal,
                "encoded response " + id.key.toString() + " is never dirty, not written back");
  }
};

std::shared_ptr<EncodedCache> EncodedCache::create(core::PatchCache& cache, core::LiveModel& live) {
  std::shared_ptr<EncodedCache> encoded(new EncodedCache(cache));
  encoded->model_ = cache.addModel(live.name(), *encoded->store_);
  live.onPublish([weak = std::weak_ptr<EncodedCache>(encoded)](
                     const core::LiveModel::ReplacedVersions& replaced) {
    if (const auto self = weak.lock()) {
      for (const auto& [key, version] : replaced) {
        self->dropVersion(key, version);
      }
    }
  });
  return encoded;
}

EncodedCache::EncodedCache(core::PatchCache& cache)
    : cache_(cache), store_(std::make_unique<Store>()) {}

EncodedCache::~EncodedCache() {
  try {
    cache_.removeModel(model_);  // clean entries only: nothing to write back
  } catch (const std::exception& e) {
    core::log::error(std::string("encoded responses: cannot drop them: ") + e.what());
  }
}

template <typename Held>
std::shared_ptr<const Held> EncodedCache::hold(core::PatchCache::Pin pin) const {
  if (!pin) {
    return nullptr;
  }
  auto held = std::make_shared<Held>();
  held->owner_ = shared_from_this();
  if constexpr (std::is_same_v<Held, Body>) {
    held->encoded_ = pin.get<EncodedBytes>().get();
  } else {
    held->file_ = pin.get<core::StoredFile>().get();
  }
  held->pin_ = std::move(pin);
  return held;
}

std::shared_ptr<const EncodedCache::Body> EncodedCache::find(const core::PatchKey& key,
                                                             std::uint64_t version,
                                                             Encoding encoding,
                                                             bool countMiss) const {
  return hold<Body>(cache_.find(model_, bodyId(key, version, encoding), countMiss));
}

std::shared_ptr<const EncodedCache::Body> EncodedCache::put(const core::PatchKey& key,
                                                            std::uint64_t version,
                                                            Encoding encoding,
                                                            std::vector<std::byte> bytes,
                                                            std::string note) {
  const std::size_t size = bytes.size() + note.size();
  auto object =
      std::make_shared<const EncodedBytes>(EncodedBytes{std::move(bytes), std::move(note)});
  return hold<Body>(cache_.put(model_, bodyId(key, version, encoding),
                               core::CacheValue{std::move(object), size, 0}, /*dirty=*/false));
}

std::shared_ptr<const EncodedCache::Body> EncodedCache::findModelBody(Encoding encoding,
                                                                      std::uint8_t variant,
                                                                      std::uint64_t version,
                                                                      bool countMiss) const {
  return find(modelBodyKey(variant), version, encoding, countMiss);
}

std::shared_ptr<const EncodedCache::Body> EncodedCache::putModelBody(Encoding encoding,
                                                                     std::uint8_t variant,
                                                                     std::uint64_t version,
                                                                     std::vector<std::byte> bytes) {
  auto body = put(modelBodyKey(variant), version, encoding, std::move(bytes));
  std::optional<std::uint64_t> replaced;
  {
    const std::lock_guard lock(modelBodiesMutex_);
    auto [it, inserted] = modelBodies_.try_emplace({encoding, variant}, version);
    if (!inserted && it->second != version) {
      replaced = it->second;
      it->second = version;
    }
  }
  if (replaced) {
    cache_.invalidate(model_, bodyId(modelBodyKey(variant), *replaced, encoding));
  }
  return body;
}

std::shared_ptr<const void> EncodedCache::reserve(Encoding encoding, std::size_t bytes) {
  std::uint32_t number = 0;
  {
    const std::lock_guard lock(modelBodiesMutex_);
    number = ++reservations_;
  }
  // Under a key no patch (depth >= 0) and no model body (depth -1) has; taken out of the table
  // at once (invalidate of a pinned entry), so it stays charged exactly as long as it is held.
  const core::ObjectId id = bodyId({-2, number, 0}, 1, encoding);
  auto body = hold<Body>(
      cache_.put(model_, id, core::CacheValue{std::make_shared<const EncodedBytes>(), bytes, 0},
                 /*dirty=*/false));
  cache_.invalidate(model_, id);
  return body;
}

void EncodedCache::countMiss() const {
  cache_.countMiss();
}

std::shared_ptr<const EncodedCache::File> EncodedCache::findFile(const core::PatchKey& key,
                                                                 std::uint64_t version,
                                                                 StoredKind kind,
                                                                 bool countMiss) const {
  return hold<File>(cache_.find(model_, fileId(key, version, kind), countMiss));
}

std::shared_ptr<const EncodedCache::File> EncodedCache::putFile(
    const core::PatchKey& key, std::uint64_t version, StoredKind kind,
    std::unique_ptr<core::StoredFile> file) {
  std::shared_ptr<const core::StoredFile> object = std::move(file);
  return hold<File>(cache_.put(model_, fileId(key, version, kind),
                               core::CacheValue{std::move(object), kOpenFileBytes, 1},
                               /*dirty=*/false));
}

void EncodedCache::dropVersion(const core::PatchKey& key, std::uint64_t version) {
  for (const Encoding encoding :
       {Encoding::PositionsAara, Encoding::Glb, Encoding::TexturePng, Encoding::GlbMeshopt}) {
    cache_.invalidate(model_, bodyId(key, version, encoding));
  }
  for (const StoredKind kind : {StoredKind::Positions, StoredKind::Coordinates}) {
    cache_.invalidate(model_, fileId(key, version, kind));
  }
}

}  // namespace vsm::server::models
