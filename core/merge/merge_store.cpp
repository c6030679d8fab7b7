// The store adapters of the merge, in their own file so that the algorithm (merge.cpp) links
// without the store.
#include <utility>

#include "core/merge/merge.hpp"
#include "core/store/live_model.hpp"
#include "core/store/model_edit.hpp"

namespace vsm::core {

namespace {

/// The pin rides along with the grid pointer, so the data stays pinned exactly as long as it is
/// used.
template <typename T>
std::shared_ptr<const T> pinned(PatchCache::Pin pin) {
  if (!pin) {
    return nullptr;
  }
  auto holder = std::make_shared<PatchCache::Pin>(std::move(pin));
  const T* object = holder->get<T>().get();
  return std::shared_ptr<const T>(std::move(holder), object);
}

class EditTarget final : public MergeTarget {
 public:
  explicit EditTarget(ModelEdit& edit) : edit_(edit) {}
  const Model& model() const override { return edit_.model(); }
  std::shared_ptr<const PatchGrid> positions(const PatchKey& key) override {
    return pinned<PatchGrid>(edit_.positions(key));
  }
  std::shared_ptr<const TextureTile> texture(const PatchKey& key) override {
    return pinned<TextureTile>(edit_.texture(key));
  }
  void setPositions(const PatchKey& key, std::shared_ptr<const PatchGrid> grid,
                    std::shared_ptr<const TextureTile> texture) override {
    edit_.setPositions(key, std::move(grid), std::move(texture));
  }
  void refreshStale(const CancelToken* cancel) override { edit_.refreshStale(cancel); }
  void writeEarly(const PatchKey& key) override { edit_.writeEarly(key); }

 private:
  ModelEdit& edit_;
};

class LiveSource final : public PatchSource {
 public:
  LiveSource(LiveModel& live, std::shared_ptr<const ModelSnapshot> snapshot)
      : live_(live), snapshot_(std::move(snapshot)) {}
  const Model& model() const override { return *snapshot_->model; }
  std::shared_ptr<const PatchGrid> positions(const PatchKey& key) override {
    return pinned<PatchGrid>(live_.positions(*snapshot_, key));
  }
  std::shared_ptr<const TextureTile> texture(const PatchKey& key) override {
    return pinned<TextureTile>(live_.texture(*snapshot_, key));
  }

 private:
  LiveModel& live_;
  std::shared_ptr<const ModelSnapshot> snapshot_;  // one version for the whole merge
};

}  // namespace

std::unique_ptr<MergeTarget> editTarget(ModelEdit& edit) {
  return std::make_unique<EditTarget>(edit);
}

std::unique_ptr<PatchSource> liveSource(LiveModel& model) {
  return std::make_unique<LiveSource>(model, model.snapshot());
}

std::unique_ptr<PatchSource> liveSource(LiveModel& model,
                                        std::shared_ptr<const ModelSnapshot> snapshot) {
  return std::make_unique<LiveSource>(model, std::move(snapshot));
}

MergeResult mergeModels(ModelEdit& target, LiveModel& detail, const MergeOptions& options) {
  EditTarget t(target);
  LiveSource d(detail, detail.snapshot());
  return mergeModels(t, d, options);
}

}  // namespace vsm::core
