#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <mutex>

namespace vsm::server::api {

/// The bound on the diffs (GET /v1/models/{m}/diff and diff.png) that run at once, and how long
/// each may run. A diff samples every changed leaf of two revisions and, for the PNG, draws a map
/// of up to 4096^2 pixels: whole-model work that any client may ask for (reads are public), so the
/// daemon runs at most `slots` of them at a time and answers more with 503 and Retry-After
/// (Error(Unavailable)), and stops one at its next leaf once `timeout` has passed or its client
/// has closed the connection.
///
/// Thread-safe.
class DiffGate {
 public:
  struct Options {
    /// Diffs at once; 0 refuses every diff.
    std::size_t slots = 2;
    /// How long one diff may run (from entering the gate); zero or less: no deadline.
    std::chrono::milliseconds timeout{60'000};
  };

  /// A diff's place in the gate: held for the length of the diff, freed when destroyed.
  class Slot {
   public:
    ~Slot();
    Slot(const Slot&) = delete;
    Slot& operator=(const Slot&) = delete;
    /// When the diff must stop (time_point::max() without a deadline).
    std::chrono::steady_clock::time_point deadline() const { return deadline_; }

   private:
    friend class DiffGate;
    Slot(std::shared_ptr<DiffGate> gate, std::chrono::steady_clock::time_point deadline)
        : gate_(std::move(gate)), deadline_(deadline) {}
    std::shared_ptr<DiffGate> gate_;
    std::chrono::steady_clock::time_point deadline_;
  };

  struct Stats {
    std::size_t running = 0;
    std::size_t slots = 0;
    /// Diffs refused because every slot was taken, and diffs stopped at their deadline.
    std::uint64_t refused = 0;
    std::uint64_t timedOut = 0;
    /// Diffs stopped because their client closed the connection.
    std::uint64_t abandoned = 0;
  };

  static std::shared_ptr<DiffGate> create(Options options);

  /// A slot for one diff; throws core::Error(Unavailable) (503, Retry-After) when every slot is
  /// taken. Never blocks.
  std::unique_ptr<Slot> enter();
  /// Counts a diff stopped at its deadline.
  void countTimeout();
  /// Counts a diff stopped because its client went away.
  void countAbandoned();
  Stats stats() const;
  const Options& options() const { return options_; }

 private:
  explicit DiffGate(Options options) : options_(options) {}
  void leave();

  std::weak_ptr<DiffGate> self_;
  const Options options_;
  mutable std::mutex mutex_;  // guards stats_
  Stats stats_;
};

}  // namespace vsm::server::api
