#pragma once

#include <cstddef>
#include <optional>

#include "core/common/progress.hpp"
#include "core/grid/geometry.hpp"

namespace vsm::core {

class LiveModel;
class PatchSource;

struct RegistrationOptions {
  /// Receives the stage "registering".
  Progress* progress = nullptr;
  /// Polled between ICP stages.
  const CancelToken* cancel = nullptr;
  /// ICP iterations per stage.
  int maxIterations = 50;
  /// At most this many target vertices per stage, and 4 times as many detail points (evenly
  /// thinned beyond).
  std::size_t maxPoints = 10000;
  /// Largest misalignment searched for, metres; default: 4 cells of the target's coarse level.
  std::optional<double> searchRadius;
  /// As MergeOptions::up.
  std::optional<Vec3d> up;
};

struct RegistrationResult {
  /// Rigid transform to apply to every vertex of the detail model (MergeOptions::transform).
  Mat4d transform;
  /// PCL's fitness score of the last stage: mean squared distance (m^2) from the target's points
  /// to their nearest detail points after alignment.
  double fitness = 0;
  /// Root mean square distance, along the target's normals, between its vertices used in the last
  /// stage and the detail surface after alignment (metres): the interpolation error of the finer
  /// model plus what registration could not remove.
  double rms = 0;
  /// Whether the last ICP stage converged.
  bool converged = false;
  /// Depths of the levels used in the first (coarse) stage, and the number of stages run.
  int targetDepth = 0;
  int detailDepth = 0;
  int stages = 0;
  double seconds = 0;
};

/// Registers the detail model B to the target model A by ICP (thesis 3.3.4, Algorithm 2), done
/// with PCL (point-to-plane, normals from the grids' neighbours):
///
/// 1. coarse stage: A's coarsest overview level with enough vertices over B's footprint against
///    B's level whose resolution is closest to it;
/// 2. refinement stages with a shrinking correspondence distance: A's bottom vertices over B
///    against a B level about twice as fine as them (B's planes then follow the surface
///    closely), down to a distance of a few B cells.
///
/// A's vertices are the moving cloud (they are exact surface samples; B is the denser one, so its
/// local planes are the better model of the surface) and only those lying over B's surface with a
/// margin of the current correspondence distance (at most a quarter of B's width) take part, so
/// B's border attracts nothing; the result is inverted into one transform for B. Coordinates are
/// centred on B before they become PCL's float32 points.
///
/// Throws Error(InvalidArgument) when the models are empty or do not overlap enough to register
/// (fewer than 12 target vertices over B), Error(Cancelled), and the stores' errors.
RegistrationResult registerModels(PatchSource& target, PatchSource& detail,
                                  const RegistrationOptions& options = {});

/// The same over open models (their current snapshots).
RegistrationResult registerModels(LiveModel& target, LiveModel& detail,
                                  const RegistrationOptions& options = {});

}  // namespace vsm::core
