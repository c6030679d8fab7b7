#include "core/store/model_store.hpp"

#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/texture_file.hpp"

namespace fs = std::filesystem;

namespace vsm::core {

LiveModel::Store::Store(fs::path dir, PatchCache& cache, const std::string& name,
                        std::shared_ptr<const Model> current, std::uint64_t texturePixels)
    : dir_(std::move(dir)),
      cache_(cache),
      shape_(current->gridSize()),
      current_(std::move(current)),
      texturePixels_(texturePixels) {
  id_ = cache_.addModel(name, *this);
}

LiveModel::Store::~Store() {
  try {
    cache_.removeModel(id_);
  } catch (const std::exception& e) {
    log::error(std::string("closing model: ") + e.what());
  }
}

void LiveModel::Store::add(const PatchInfo& info) {
  std::lock_guard lock(mutex_);
  addLocked(info);
}

void LiveModel::Store::addLocked(const PatchInfo& info) {
  // A copy: the model's patch lives in a chunk of hundreds.
  others_.insert_or_assign(std::pair{info.key, info.version}, std::make_shared<PatchInfo>(info));
}

void LiveModel::Store::forget(const PatchKey& key, std::uint64_t version) {
  std::lock_guard lock(mutex_);
  others_.erase({key, version});
}

void LiveModel::Store::addRevision(const Model& revision) {
  std::lock_guard lock(mutex_);
  for (const auto& [key, info] : revision.patches()) {
    const PatchInfo* current = current_->find(key);
    if (current == nullptr || current->version != info.version) {
      addLocked(info);
    }
  }
}

void LiveModel::Store::publish(std::shared_ptr<const Model> next, const ModelChange& change) {
  std::lock_guard lock(mutex_);
  const auto keepReplaced = [&](const PatchKey& key) {
    if (current_->find(key) != nullptr) {
      addLocked(current_->at(key));
    }
  };
  for (const PatchKey& key : change.changed) {
    keepReplaced(key);
    others_.erase({key, next->at(key).version});  // a draft until now
  }
  for (const PatchKey& key : change.removed) {
    keepReplaced(key);
  }
  current_ = std::move(next);
}

void LiveModel::Store::forgetFolders(const FolderSet& folders) {
  std::vector<std::pair<PatchKey, std::uint64_t>> gone;
  {
    std::lock_guard lock(mutex_);
    for (auto it = others_.begin(); it != others_.end();) {
      if (folders.contains(it->second->folder())) {
        gone.push_back(it->first);
        it = others_.erase(it);
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

std::size_t LiveModel::Store::otherVersionsBytes() const {
  std::lock_guard lock(mutex_);
  using Node = decltype(others_)::value_type;
  return others_.size() * (sizeof(Node) + 32 + 16 + sizeof(PatchInfo) + 32);
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
  if (const PatchInfo* current = current_->find(id.key);
      current != nullptr && current->version == id.version) {
    return current_->shared(id.key);
  }
  const auto it = others_.find({id.key, id.version});
  if (it == others_.end()) {
    throw Error(ErrorCode::NotFound, "patch " + id.key.toString() + " version " +
                                         std::to_string(id.version) + " is not stored");
  }
  return it->second;
}

}  // namespace vsm::core
