#include "server/api/diff_gate.hpp"

#include <string>

#include "core/common/error.hpp"

namespace vsm::server::api {

using core::Error;
using core::ErrorCode;

std::shared_ptr<DiffGate> DiffGate::create(Options options) {
  std::shared_ptr<DiffGate> gate(new DiffGate(options));
  gate->self_ = gate;
  gate->stats_.slots = options.slots;
  return gate;
}

DiffGate::Slot::~Slot() {
  gate_->leave();
}

std::unique_ptr<DiffGate::Slot> DiffGate::enter() {
  {
    const std::lock_guard lock(mutex_);
    if (stats_.running >= options_.slots) {
      ++stats_.refused;
      throw Error(ErrorCode::Unavailable,
                  "the daemon runs at most " + std::to_string(options_.slots) +
                      " diffs at once (limits.diffs) and all are running; ask again in a moment");
    }
    ++stats_.running;
  }
  const auto deadline = options_.timeout.count() > 0
                            ? std::chrono::steady_clock::now() + options_.timeout
                            : std::chrono::steady_clock::time_point::max();
  return std::unique_ptr<Slot>(new Slot(self_.lock(), deadline));
}

void DiffGate::leave() {
  const std::lock_guard lock(mutex_);
  --stats_.running;
}

void DiffGate::countTimeout() {
  const std::lock_guard lock(mutex_);
  ++stats_.timedOut;
}

void DiffGate::countAbandoned() {
  const std::lock_guard lock(mutex_);
  ++stats_.abandoned;
}

DiffGate::Stats DiffGate::stats() const {
  const std::lock_guard lock(mutex_);
  return stats_;
}

}  // namespace vsm::server::api
