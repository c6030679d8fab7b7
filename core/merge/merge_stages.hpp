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
#include "core/merge/subdivider.hpp"

namespace vsm::core::merge_stages {

/// A bottom patch of B with what matching learnt of it.
struct DetailLeaf {
  PatchKey key;
  /// Its box in global coordinates (after MergeOptions::transform), from B's metadata.
  Box3d box;
  /// Read from its grid for the leaves near A only (`read`): its Ball, its spacing on the
  /// surface, its SurfaceCaster::blockBoxes, and the Balls of the same blocks (placing refines a
  /// new patch only where one of these is within reach of its rays).
  bool read = false;
  Ball ball;
  double spacing = 0;
  std::vector<Box3d> blocks;
  std::vector<Ball> blockBalls;
};

/// A bottom patch of the target that B's surface meets.
struct Match {
  PatchKey target;
  /// Indices of the B leaves (in MergePlan::bLeaves) whose ball meets the target leaf's, grown
  /// by `search` and the B leaf's spacing.
  std::vector<std::size_t> detail;
  int levels = 1;
  /// How far along its normal a new vertex looks for B's surface (either way): 4 of the target
  /// leaf's spacings on the surface (gridSpacing().mean), at least 16 of B's finest spacing
  /// (merge_matching.cpp says why).
  double search = 0;
  /// The target's vertices around the leaf, from its neighbours at the same depth.
  Ring ring;
};

/// What matching finds and placing works through.
struct MergePlan {
  std::vector<DetailLeaf> bLeaves;
  /// The target's matched leaves, in key order, with their new levels.
  std::vector<Match> matches;
  /// Bottom patches of B that meet at least one matched target patch (MergeResult::detailLeaves).
  std::size_t detailLeaves = 0;
};

/// Stage "matching": A's bottom patches near B's surface and B's leaves near each, and the levels
/// each needs. Throws as mergeModels() for a B outside or partly outside A, or too fine.
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
