#pragma once

#include <functional>
#include <vector>

namespace vsm::core {

/// Runs batches of independent tasks, possibly in parallel, on threads its owner manages: core
/// creates no threads of its own, callers that have some (the CLI, the daemon) lend them.
class Executor {
 public:
  virtual ~Executor() = default;
  /// Runs every task and returns when all have finished. When tasks throw, the first exception
  /// is rethrown (after all have finished).
  virtual void runAll(std::vector<std::function<void()>> tasks) = 0;
};

}  // namespace vsm::core
