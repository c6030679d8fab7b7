#pragma once

#include <atomic>
#include <string_view>

#include "core/common/error.hpp"

namespace vsm::core {

/// Receives progress of a long operation. Implementations must be cheap: report() is called often.
class Progress {
 public:
  virtual ~Progress() = default;
  /// `stage` names the current step ("reading", "writing", ...); `fraction` is in [0, 1] and
  /// never decreases within a stage.
  virtual void report(std::string_view stage, double fraction) = 0;
};

/// A cancellation flag shared between the one who asks and the operation that polls it.
class CancelToken {
 public:
  void cancel() noexcept { cancelled_.store(true, std::memory_order_relaxed); }
  bool cancelled() const noexcept { return cancelled_.load(std::memory_order_relaxed); }
  /// Throws Error(Cancelled) when cancel() was called.
  void throwIfCancelled() const {
    if (cancelled()) {
      throw Error(ErrorCode::Cancelled, "operation cancelled");
    }
  }

 private:
  std::atomic<bool> cancelled_{false};
};

}  // namespace vsm::core
