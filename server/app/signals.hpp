#pragma once

#include <atomic>
#include <functional>
#include <thread>

namespace vsm::server {

/// Blocks SIGINT and SIGTERM in the calling thread, so every thread started after this call
/// inherits the mask and no thread is interrupted by them; SignalWaiter then receives them.
/// Call first in main(), before anything starts a thread. Throws core::Error(Internal) on failure.
void blockTerminationSignals();

/// Waits for SIGINT or SIGTERM on a thread of its own and calls `onSignal` with the signal number
/// for each one (a normal function call, not a signal handler: it may lock and log).
/// Requires blockTerminationSignals() first.
class SignalWaiter {
 public:
  explicit SignalWaiter(std::function<void(int)> onSignal);
  /// Stops waiting; `onSignal` is not called after this returns.
  ~SignalWaiter();
  SignalWaiter(const SignalWaiter&) = delete;
  SignalWaiter& operator=(const SignalWaiter&) = delete;

 private:
  std::function<void(int)> onSignal_;
  std::atomic<bool> stopping_{false};
  std::thread thread_;
};

}  // namespace vsm::server
