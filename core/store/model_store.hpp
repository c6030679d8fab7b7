#pragma once

// Internal to core/store: the cache's store adapter of one LiveModel. Not included outside
// core/store.

#include <cstdint>
#include <filesystem>
#include <map>
#include <mutex>
#include <set>
#include <string>
#include <utility>

#include "core/cache/patch_cache.hpp"
#include "core/store/live_model.hpp"

namespace vsm::core {

/// The PatchStore of one LiveModel: knows where every live version of every patch is stored
/// (published, kept revisions read, and an edit's drafts), and loads and writes them for the
/// cache. Registered with the cache for its life. Thread-safe.
///
/// The current version's patches are looked up in its model itself (shared, never copied: an
/// opening of 10^6 patches makes no second table of them); a table holds only the others: the
/// versions publishes replaced while kept revisions name them, those of revisions read, and
/// drafts. So opening costs nothing here and a publish what it changed.
class LiveModel::Store final : public PatchStore {
 public:
  /// `current`: the version opened, every patch of it loadable.
  Store(std::filesystem::path dir, PatchCache& cache, const std::string& name,
        std::shared_ptr<const Model> current, std::uint64_t texturePixels);
  ~Store() override;

  PatchCache& cache() { return cache_; }
  std::uint64_t texturePixels() const { return texturePixels_; }
  PatchCache::ModelId id() const { return id_; }
  const std::filesystem::path& dir() const { return dir_; }

  /// Makes a draft loadable: holds a copy of its metadata.
  void add(const PatchInfo& info);
  void forget(const PatchKey& key, std::uint64_t version);
  /// Makes the versions of a revision read loadable (those the current version does not hold).
  void addRevision(const Model& revision);
  /// `next`, published over the current version with `change` (keys it changed or removed),
  /// becomes the current one; the versions it replaced stay loadable (kept revisions name them)
  /// until forgetFolders. Costs the change.
  void publish(std::shared_ptr<const Model> next, const ModelChange& change);
  /// Forgets every version stored in one of `folders` and drops its cached data.
  void forgetFolders(const FolderSet& folders);
  /// Heap bytes of the table of the versions the current one does not hold (their nodes counted
  /// too, though a revision read may hold them as well: an upper estimate).
  std::size_t otherVersionsBytes() const;

  std::size_t expectedBytes(const ObjectId& id) const override;
  CacheValue load(const ObjectId& id) override;
  /// Only drafts are ever dirty: written without a sync of their own (the edit's FileSystemSync
  /// makes them durable before the hierarchy names them).
  void writeBack(const ObjectId& id, const CacheValue& value) override;

 private:
  std::shared_ptr<const PatchInfo> lookup(const ObjectId& id) const;
  /// add() without the lock.
  void addLocked(const PatchInfo& info);

  std::filesystem::path dir_;
  PatchCache& cache_;
  PatchCache::ModelId id_ = 0;
  /// An empty model of the right patch size: what readPatchGrid needs to know of the model.
  const Model shape_;
  mutable std::mutex mutex_;  // guards current_ (the pointer) and others_
  std::shared_ptr<const Model> current_;
  /// Every loadable version the current one does not hold.
  std::map<std::pair<PatchKey, std::uint64_t>, std::shared_ptr<const PatchInfo>> others_;
  const std::uint64_t texturePixels_;
};

}  // namespace vsm::core
