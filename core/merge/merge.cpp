#include "core/merge/merge.hpp"

#include <algorithm>
#include <chrono>
#include <string>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/merge/merge_stages.hpp"

namespace vsm::core {

namespace merge_stages {

void report(const MergeOptions& options, std::string_view stage, double fraction) {
  if (options.progress != nullptr) {
    options.progress->report(stage, std::clamp(fraction, 0.0, 1.0));
  }
}

void checkCancelled(const MergeOptions& options) {
  if (options.cancel != nullptr) {
    options.cancel->throwIfCancelled();
  }
}

void reduceStale(MergeTarget& target, const MergeOptions& options) {
  checkCancelled(options);
  report(options, "reducing", 0);
  target.refreshStale(options.cancel);
  report(options, "reducing", 1);
}

}  // namespace merge_stages

// The stages are those MergeOptions::progress receives, each in its own file (merge_stages.hpp).
MergeResult mergeModels(MergeTarget& target, PatchSource& detail, const MergeOptions& options) {
  const auto start = std::chrono::steady_clock::now();
  MergeResult result;
  const Model& a = target.model();
  const Model& b = detail.model();
  if (a.empty() || b.empty()) {
    throw Error(ErrorCode::InvalidArgument, "merge: the target or the detail model is empty");
  }
  if (a.gridSize() != b.gridSize()) {
    // Not needed by the algorithm, but new patches take the target's size; say so plainly.
    log::info("merge: detail grid size " + std::to_string(b.gridSize()) + " differs from target " +
              std::to_string(a.gridSize()));
  }

  merge_stages::report(options, "matching", 0);
  merge_stages::MergePlan plan = merge_stages::matchLeaves(target, detail, options);
  result.detailLeaves = plan.detailLeaves;
  merge_stages::report(options, "matching", 1);

  merge_stages::report(options, "placing", 0);
  merge_stages::placeDetail(target, detail, plan, options, result);
  merge_stages::report(options, "placing", 1);

  merge_stages::reduceStale(target, options);

  result.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  log::info(
      "merge: " + std::to_string(result.matchedLeaves) + " target leaves, " +
      std::to_string(result.detailLeaves) + " detail leaves, " + std::to_string(result.newPatches) +
      " new patches, " + std::to_string(result.resampledLeaves) + " resampled in place, up to " +
      std::to_string(result.maxLevels) + " new levels, " + std::to_string(result.seconds) + " s");
  return result;
}

}  // namespace vsm::core
