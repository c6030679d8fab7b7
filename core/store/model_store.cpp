#include "core/store/model_store.hpp"

#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/texture_file.hpp"

namespace fs = std::filesystem;

namespace vsm::core {

LiveModel::Store::Store(fs::path dir, PatchCache& cache, const std::string& name, int gridSize,
                        std::uint64_t texturePixels)
    : dir_(std::move(dir)), cache_(cache), shape_(gridSize), texturePixels_(texturePixels) {
  id_ = cache_.addModel(name, *this);
}

LiveModel::Store::~Store() {
  try {
    cache_.removeModel(id_);
  } catch (const std::exception& e) {
    log::error(std::string("closing model: ") + e.what());
  }
}

void LiveModel::Store::add(std::shared_ptr<const PatchInfo> info) {
  if (info->grid != nullptr) {  // the cache holds vertex data, within its budget; never the store
    auto copy = std::make_shared<PatchInfo>(*info);
    copy->grid.reset();
    info = std::move(copy);
  }
  const std::pair<PatchKey, std::uint64_t> id{info->key, info->version};
  std::lock_guard lock(mutex_);
  versions_[id] = std::move(info);
}

void LiveModel::Store::forget(const PatchKey& key, std::uint64_t version) {
  std::lock_guard lock(mutex_);
  versions_.erase({key, version});
}

void LiveModel::Store::forgetFolders(const FolderSet& folders) {
  std::vector<std::pair<PatchKey, std::uint64_t>> gone;
  {
    std::lock_guard lock(mutex_);
    for (auto it = versions_.begin(); it != versions_.end();) {
      if (folders.contains(it->second->folder)) {
        gone.push_back(it->first);
        it = versions_.erase(it);
      } else {
        ++it;
      }
    }
  }
  for (const auto& [key, version] : gone) {
    cache_.invalidate(id_, {key, version, MemoryCategory::Positions});
    cache_.invalidate(id_, {key, version, MemoryCategory::Textures});
  }
}

std::size_t LiveModel::Store::expectedBytes(const ObjectId& id) const {
  const auto n = static_cast<std::size_t>(shape_.gridSize());
  return id.category == MemoryCategory::Textures ? (n - 1) * (n - 1) * TextureTile::kChannels
                                                 : n * n * 3 * sizeof(float);
}

CacheValue LiveModel::Store::load(const ObjectId& id) {
  const std::shared_ptr<const PatchInfo> held = lookup(id);
  const PatchInfo& info = *held;
  if (id.category == MemoryCategory::Textures) {
    auto tile =
        std::make_shared<const TextureTile>(readPatchTextureTile(dir_, info, texturePixels_));
    const std::size_t bytes = tile->bytes();
    return {std::move(tile), bytes};
  }
  auto grid = std::make_shared<const PatchGrid>(readPatchGrid(dir_, shape_, info));
  const std::size_t bytes = grid->bytes();
  return {std::move(grid), bytes};
}

void LiveModel::Store::writeBack(const ObjectId& id, const CacheValue& value) {
  PatchInfo info = *lookup(id);  // the writer fills in what it wrote
  // Only drafts are ever dirty: their folders are invisible until publish() makes them durable
  // (the edit's FileSystemSync) before the hierarchy names them, so no fsync or temp file per
  // file here.
  OpcWriter writer(dir_, OpcWriter::Durability::Deferred);
  if (id.category == MemoryCategory::Textures) {
    writer.writeTexture(info, *value.object.as<TextureTile>());
    return;
  }
  // The edit described the patch after its children: its box already holds theirs. A textured
  // draft names its tile, written by its own entry's write-back.
  writer.writePatch(info, *value.object.as<PatchGrid>(), info.globalBox);
}

std::shared_ptr<const PatchInfo> LiveModel::Store::lookup(const ObjectId& id) const {
  std::lock_guard lock(mutex_);
  const auto it = versions_.find({id.key, id.version});
  if (it == versions_.end()) {
    throw Error(ErrorCode::NotFound, "patch " + id.key.toString() + " version " +
                                         std::to_string(id.version) + " is not stored");
  }
  return it->second;
}

}  // namespace vsm::core
