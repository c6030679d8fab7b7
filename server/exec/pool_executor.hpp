#pragma once

#include <cstddef>
#include <functional>
#include <vector>

#include "core/common/executor.hpp"

namespace vsm::server::exec {

class WorkPool;

/// A core::Executor over a WorkPool of helpers (the one vsmd lends its jobs' operations): runAll
/// runs the tasks on the calling thread and on up to `helpers` of the pool's threads that come
/// free meanwhile. It never waits for a task no thread has started, so callers cannot deadlock,
/// not even on the pool's own threads; with the pool busy the caller runs every task itself.
///
/// Thread-safe: runAll may be called from several threads at once.
class PoolExecutor final : public core::Executor {
 public:
  /// `pool` must outlive the executor's calls. `onHelperStart` runs on a pool thread before it
  /// takes tasks (the job pool lowers the thread's priority there).
  PoolExecutor(WorkPool& pool, std::size_t helpers, std::function<void()> onHelperStart = {});

  void runAll(std::vector<std::function<void()>> tasks) override;

 private:
  WorkPool& pool_;
  std::size_t helpers_;
  std::function<void()> onHelperStart_;
};

}  // namespace vsm::server::exec
