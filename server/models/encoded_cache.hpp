#pragma once

#include <cstddef>
#include <memory>
#include <string>

#include "core/cache/patch_cache.hpp"

namespace vsm::server::models {

/// Response bodies encoded from one open model's published patch data — positions as .aara files
/// in memory (sent with sendfile(2)), binary glTF tiles — kept in the shared PatchCache beside the
/// data they come from, under the model's name: charged to the one memory budget, counted in the
/// statistics by category (MemoryCategory::PositionFiles, MemoryCategory::Tiles) and evicted by
/// the same policy. Entries are clean: evicting one just drops its bytes (a response being written
/// holds its own reference until done). An entry is keyed by patch key, patch version and category
/// (the format); entries of superseded versions are never asked for again and age out.
///
/// Thread-safe (the cache is). The ModelRegistry makes one per opening of a model; its entries go
/// with it.
class EncodedCache {
 public:
  /// Registers with `cache` (which must outlive this) under `modelName`.
  EncodedCache(core::PatchCache& cache, const std::string& modelName);
  /// Drops every entry.
  ~EncodedCache();
  EncodedCache(const EncodedCache&) = delete;
  EncodedCache& operator=(const EncodedCache&) = delete;

  /// The object cached as `id` (of type T, as put), or nullptr. Never blocks (PatchCache::find):
  /// network threads may call it. `countMiss`: false for the handler pool's second look after a
  /// network thread's first one missed (one miss per request in the statistics).
  template <typename T>
  std::shared_ptr<const T> find(const core::ObjectId& id, bool countMiss) const {
    return std::static_pointer_cast<const T>(cache_.find(model_, id, countMiss));
  }

  /// Caches `object`, occupying `bytes`, as `id` (replacing what is there), evicting others to
  /// make room. Throws core::Error(ResourceExhausted) when the budget is full of pinned data.
  void put(const core::ObjectId& id, std::shared_ptr<const void> object, std::size_t bytes);

 private:
  class Store;  // the PatchStore the cache needs; it never loads and never writes
  core::PatchCache& cache_;
  std::unique_ptr<Store> store_;
  core::PatchCache::ModelId model_ = 0;
};

}  // namespace vsm::server::models
