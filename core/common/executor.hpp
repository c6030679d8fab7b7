#pragma once

#include <functional>
#include <utility>
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

/// Runs `tasks` on `executor`, or one after the other on the calling thread when there is none
/// (or only one task). Rethrows as runAll does; serially the first exception stops the rest.
inline void runTasks(Executor* executor, std::vector<std::function<void()>> tasks) {
  if (executor != nullptr && tasks.size() > 1) {
    executor->runAll(std::move(tasks));
  } else {
    for (const auto& task : tasks) {
      task();
    }
  }
}

}  // namespace vsm::core
