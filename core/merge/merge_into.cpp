#include "core/merge/merge_into.hpp"

#include <memory>

#include "core/store/live_model.hpp"

namespace vsm::core {

MergeIntoResult mergeInto(LiveModel& target, LiveModel& detail, MergeIntoOptions options) {
  MergeIntoResult result;
  // The one edit of the target first: a model being written elsewhere fails before any work.
  std::unique_ptr<ModelEdit> edit = target.beginEdit();
  result.baseVersion = edit->base().version;
  auto inherit = [&](auto& stepOptions) {
    if (stepOptions.progress == nullptr) {
      stepOptions.progress = options.progress;
    }
    if (stepOptions.cancel == nullptr) {
      stepOptions.cancel = options.cancel;
    }
  };
  inherit(options.merge);
  if (options.registerFirst) {
    inherit(options.registration);
    result.registration = registerModels(target, detail, options.registration);
    options.merge.transform = result.registration->transform;
  }
  result.merge = mergeModels(*edit, detail, options.merge);
  if (options.progress != nullptr) {
    options.progress->report("publishing", 0);
  }
  // Cancellation is honoured up to the commit point; after it the new version is the model's.
  edit->publish(options.cancel, options.publish);
  result.version = target.snapshot()->version;
  edit.reset();
  if (options.progress != nullptr) {
    options.progress->report("publishing", 1);
  }
  return result;
}

}  // namespace vsm::core
