#include "server/exec/pool_executor.hpp"

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <exception>
#include <memory>
#include <mutex>
#include <utility>

#include "server/exec/work_pool.hpp"

namespace vsm::server::exec {

namespace {

/// One runAll's tasks, shared with the helpers it posted: a helper that starts after the call
/// returned finds nothing left to take and touches nothing else.
struct Batch {
  explicit Batch(std::vector<std::function<void()>> t) : tasks(std::move(t)) {}

  /// Takes tasks until none is left; the thread that finishes the last one wakes the caller.
  void work() {
    for (std::size_t i; (i = next.fetch_add(1)) < tasks.size();) {
      try {
        tasks[i]();
      } catch (...) {
        const std::lock_guard lock(mutex);
        if (!first) {
          first = std::current_exception();
        }
      }
      const std::lock_guard lock(mutex);
      if (++finished == tasks.size()) {
        done.notify_all();
      }
    }
  }

  std::vector<std::function<void()>> tasks;
  std::atomic<std::size_t> next{0};
  std::mutex mutex;  // guards finished and first
  std::condition_variable done;
  std::size_t finished = 0;
  std::exception_ptr first;
};

}  // namespace

PoolExecutor::PoolExecutor(WorkPool& pool, std::size_t helpers, std::function<void()> onHelperStart)
    : pool_(pool), helpers_(helpers), onHelperStart_(std::move(onHelperStart)) {}

void PoolExecutor::runAll(std::vector<std::function<void()>> tasks) {
  if (tasks.empty()) {
    return;
  }
  auto batch = std::make_shared<Batch>(std::move(tasks));
  const std::size_t helpers = std::min(helpers_, batch->tasks.size() - 1);
  for (std::size_t h = 0; h < helpers; ++h) {
    pool_.post([batch, start = onHelperStart_] {
      if (batch->next.load() >= batch->tasks.size()) {
        return;  // all taken before this thread came free
      }
      if (start) {
        start();
      }
      batch->work();
    });
  }
  batch->work();
  std::unique_lock lock(batch->mutex);
  // Every task is taken by now, each by a thread running it: this waits for no queued helper.
  batch->done.wait(lock, [&] { return batch->finished == batch->tasks.size(); });
  if (batch->first) {
    std::rethrow_exception(batch->first);
  }
}

}  // namespace vsm::server::exec
