#include "server/app/signals.hpp"

#include <pthread.h>
#include <signal.h>

#include <cstring>
#include <string>

#include "core/common/error.hpp"

namespace vsm::server {

namespace {

sigset_t terminationSignals() {
  sigset_t set;
  sigemptyset(&set);
  sigaddset(&set, SIGINT);
  sigaddset(&set, SIGTERM);
  return set;
}

}  // namespace

void blockTerminationSignals() {
  const sigset_t set = terminationSignals();
  if (const int rc = pthread_sigmask(SIG_BLOCK, &set, nullptr); rc != 0) {
    throw core::Error(core::ErrorCode::Internal,
                      std::string("cannot block SIGINT/SIGTERM: ") + std::strerror(rc));
  }
}

SignalWaiter::SignalWaiter(std::function<void(int)> onSignal) : onSignal_(std::move(onSignal)) {
  thread_ = std::thread([this] {
    const sigset_t set = terminationSignals();
    for (;;) {
      int signal = 0;
      if (sigwait(&set, &signal) != 0) {
        continue;
      }
      if (stopping_.load()) {
        return;  // the destructor's wake-up call (or a signal during destruction: we exit anyway)
      }
      onSignal_(signal);
    }
  });
}

SignalWaiter::~SignalWaiter() {
  stopping_.store(true);
  // Directed at the waiting thread, which has SIGTERM blocked: sigwait() takes it.
  pthread_kill(thread_.native_handle(), SIGTERM);
  thread_.join();
}

}  // namespace vsm::server
