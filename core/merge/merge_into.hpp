#pragma once

#include <cstdint>
#include <optional>

#include "core/common/progress.hpp"
#include "core/merge/merge.hpp"
#include "core/merge/register.hpp"
#include "core/store/model_edit.hpp"

namespace vsm::core {

class LiveModel;

/// What mergeInto() does besides the merge itself.
struct MergeIntoOptions {
  /// Aligns the detail model first (registerModels), and merges it with the transform found.
  bool registerFirst = false;
  RegistrationOptions registration;
  /// Its transform is replaced by the registration's when registerFirst.
  MergeOptions merge;
  PublishOptions publish;
  /// Stages "registering" (when registerFirst), the merge's ("matching", "placing",
  /// "reducing"), then "publishing"; polled for cancellation up to the commit point. Passed on to
  /// registration and merge where their own options leave them unset.
  Progress* progress = nullptr;
  const CancelToken* cancel = nullptr;
};

struct MergeIntoResult {
  /// The version the edit started from, and the one it published.
  std::uint64_t baseVersion = 0;
  std::uint64_t version = 0;
  std::optional<RegistrationResult> registration;
  MergeResult merge;
};

/// Merges the model `detail` into the model `target` and publishes the result as target's next
/// version (DESIGN.md section 3): target.beginEdit(), registerModels() when asked, mergeModels(),
/// ModelEdit::publish(). The one sequence both vsmd's merge job and `vsm merge` run. Readers see
/// the old version until the commit point and the new one after; on an error or cancellation
/// before it the edit is discarded. Throws as its steps (Error(Conflict) from beginEdit or the
/// fenced commit; Error(Io) from a write: the caller then reads the model again).
MergeIntoResult mergeInto(LiveModel& target, LiveModel& detail, MergeIntoOptions options);

}  // namespace vsm::core
