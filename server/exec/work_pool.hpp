#pragma once

#include <atomic>
#include <cstddef>
#include <functional>
#include <memory>
#include <string>

namespace vsm::server::exec {

/// A fixed set of threads running posted tasks in FIFO order (over asio::thread_pool, kept out of
/// this header). The daemon has two: "cpu" for request handlers and "jobs" for merges and imports,
/// so long jobs cannot starve request handling.
///
/// The queue itself is unbounded; what feeds it is bounded instead (the HTTP server holds at most
/// connections x pipelined responses handlers; the job queue has its own cap).
///
/// Thread-safe.
class WorkPool {
 public:
  /// Starts `threads` threads (at least 1). `name` appears in logs and metrics.
  WorkPool(std::string name, std::size_t threads);
  /// join()
  ~WorkPool();
  WorkPool(const WorkPool&) = delete;
  WorkPool& operator=(const WorkPool&) = delete;

  /// Queues `task`. A task should not throw; one that does is logged (as a bug) and the pool goes
  /// on. Tasks posted after join() has begun may never run.
  void post(std::function<void()> task);

  /// Runs every task queued so far to completion, then ends the threads. Idempotent; must not be
  /// called from one of the pool's own threads.
  void join();

  const std::string& name() const { return name_; }
  std::size_t threads() const { return threads_; }
  /// Tasks waiting for a thread.
  std::size_t queued() const { return queued_.load(std::memory_order_relaxed); }
  /// Tasks running now.
  std::size_t active() const { return active_.load(std::memory_order_relaxed); }

 private:
  struct Impl;
  std::string name_;
  std::size_t threads_;
  std::atomic<std::size_t> queued_{0};
  std::atomic<std::size_t> active_{0};
  std::unique_ptr<Impl> impl_;
};

}  // namespace vsm::server::exec
