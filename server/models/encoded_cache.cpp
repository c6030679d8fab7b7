#include "server/models/encoded_cache.hpp"

#include <exception>

#include "core/common/error.hpp"
#include "core/common/log.hpp"

namespace vsm::server::models {

using core::Error;
using core::ErrorCode;

/// Encoded responses are made by the routes and put() into the cache, never loaded by it; they
/// are clean, so they are never written back either.
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

EncodedCache::EncodedCache(core::PatchCache& cache, const std::string& modelName)
    : cache_(cache), store_(std::make_unique<Store>()) {
  model_ = cache_.addModel(modelName, *store_);
}

EncodedCache::~EncodedCache() {
  try {
    cache_.removeModel(model_);  // clean entries only: nothing to write back
  } catch (const std::exception& e) {
    core::log::error(std::string("encoded responses: cannot drop them: ") + e.what());
  }
}

void EncodedCache::put(const core::ObjectId& id, std::shared_ptr<const void> object,
                       std::size_t bytes) {
  // put() pins the entry for its caller; nobody needs it pinned, so the pin goes at once.
  cache_.put(model_, id, core::CacheValue{std::move(object), bytes}, /*dirty=*/false);
}

}  // namespace vsm::server::models
