#pragma once

// The stages of mergeModels (merge.hpp), each in its own file and named as the job's progress
// names them: matching (merge_matching.cpp), placing (merge_placing.cpp), reducing (merge.cpp).
// Internal to core/merge.

#include <cstddef>
#include <string_view>
#include <utility>
#include <vector>

#include "core/grid/geometry.hpp"
#include "core/merge/merge.hpp"
#include "core/merge/surface_sampler.hpp"

namespace vsm::core::merge_stages {

/// A bottom patch of the target that B's surface meets.
struct Match {
  PatchKey target;
  /// Indices of the B leaves (in bLeaves) whose footprint meets the target leaf's.
  std::vector<std::size_t> detail;
  int levels = 1;
};

/// What matching finds and placing works through.
struct MergePlan {
  explicit MergePlan(const UpFrame& frame) : frame(frame) {}

  /// The direction along which B is placed (MergeOptions::up, or B's default), and the plane
  /// perpendicular to it in which footprints and resolutions are measured.
  Vec3d up;
  UpFrame frame;
  /// B's leaves with their footprints, grown by SurfaceSampler::kBorderTolerance of a cell.
  std::vector<std::pair<PatchKey, Rect2d>> bLeaves;
  /// Per B leaf a target leaf meets: its block footprints (SurfaceSampler::blockFootprints).
  std::vector<std::vector<Rect2d>> bBlocks;
  /// The target's matched leaves, in key order, with their new levels.
  std::vector<Match> matches;
  /// Bottom patches of B that meet at least one matched target patch (MergeResult::detailLeaves).
  std::size_t detailLeaves = 0;
};

/// Stage "matching": A's bottom patches under B's footprint and B's leaves over each, and the
/// levels each needs. Throws as mergeModels() for a B outside or partly outside A, or too fine.
MergePlan matchLeaves(MergeTarget& target, PatchSource& detail, const MergeOptions& options);

/// Stage "placing": the new levels under each matched leaf, placed on B's surface, with their
/// textures, inserted into `target`; counts them in `result`.
void placeDetail(MergeTarget& target, PatchSource& detail, const MergePlan& plan,
                 const MergeOptions& options, MergeResult& result);

/// Stage "reducing": every stale overview recomputed, from the new levels up to the root.
void reduceStale(MergeTarget& target, const MergeOptions& options);

/// Reports `fraction` of `stage` to options.progress, if any.
void report(const MergeOptions& options, std::string_view stage, double fraction);
/// Throws Error(Cancelled) once options.cancel is cancelled.
void checkCancelled(const MergeOptions& options);

}  // namespace vsm::core::merge_stages
