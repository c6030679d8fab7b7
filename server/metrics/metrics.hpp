#pragma once

#include <atomic>
#include <cstdint>
#include <functional>
#include <initializer_list>
#include <map>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>
#include <vector>

namespace vsm::server::metrics {

enum class Type { Counter, Gauge, Histogram };

/// A counter family: one monotonically increasing value per combination of label values.
/// Thread-safe.
class Counter {
 public:
  /// One series of the family, incremented without the family's lock or a lookup of its labels:
  /// hot paths may keep a reference (valid as long as the family, i.e. the registry).
  class Series {
   public:
    /// Adds `by` (>= 0). Lock-free.
    void inc(double by = 1.0) { value_.fetch_add(by, std::memory_order_relaxed); }
    double value() const { return value_.load(std::memory_order_relaxed); }

   private:
    std::atomic<double> value_{0.0};
  };

  /// Made by Registry::counter().
  explicit Counter(std::size_t labelCount) : labelCount_(labelCount) {}
  /// The series with these label values (one per label name, in order), made on first use.
  /// Throws core::Error(Internal) on a wrong number of label values.
  Series& series(std::initializer_list<std::string_view> labelValues);
  /// Adds `by` (>= 0) to the series with these label values. Throws as series().
  void inc(std::initializer_list<std::string_view> labelValues, double by = 1.0) {
    series(labelValues).inc(by);
  }
  /// The current value of a series; 0 when it was never incremented.
  double value(std::initializer_list<std::string_view> labelValues) const;

 private:
  friend class Registry;
  std::size_t labelCount_;
  mutable std::mutex mutex_;  // guards values_ (the map, not the values: they are atomic)
  std::map<std::vector<std::string>, Series> values_;  // nodes never move: Series& stay valid
};

/// A histogram family: per combination of label values, counts of observations per bucket
/// (cumulative when rendered), their sum and count. Thread-safe.
class Histogram {
 public:
  /// One series of the family, observed without the family's lock or a lookup of its labels:
  /// hot paths may keep a reference (valid as long as the family, i.e. the registry).
  class Series {
   public:
    explicit Series(const std::vector<double>& bounds)
        : bounds_(bounds),
          buckets_(std::make_unique<std::atomic<std::uint64_t>[]>(bounds.size() + 1)) {}
    /// Records one observation. Lock-free.
    void observe(double value);

   private:
    friend class Registry;
    const std::vector<double>& bounds_;  // the family's
    // Non-cumulative; one per upper bound, then +Inf. The count is their total (so a scrape
    // never sees a count that disagrees with the +Inf bucket).
    std::unique_ptr<std::atomic<std::uint64_t>[]> buckets_;
    std::atomic<double> sum_{0.0};
  };

  /// Made by Registry::histogram().
  Histogram(std::size_t labelCount, std::vector<double> bounds)
      : labelCount_(labelCount), bounds_(std::move(bounds)) {}
  /// The series with these label values, made on first use. Throws core::Error(Internal) on a
  /// wrong number of label values.
  Series& series(std::initializer_list<std::string_view> labelValues);
  /// Records one observation. Throws as series().
  void observe(std::initializer_list<std::string_view> labelValues, double value) {
    series(labelValues).observe(value);
  }

 private:
  friend class Registry;
  std::size_t labelCount_;
  std::vector<double> bounds_;  // ascending upper bounds, without +Inf
  mutable std::mutex mutex_;    // guards series_ (the map, not the series: they are atomic)
  std::map<std::vector<std::string>, Series> series_;  // nodes never move: Series& stay valid
};

/// One value of a family computed at scrape time.
struct Sample {
  std::vector<std::string> labelValues;
  double value = 0;
};

/// A counter or gauge family computed at scrape time (open connections, cache statistics).
struct Snapshot {
  std::string name;
  std::string help;
  Type type = Type::Gauge;
  std::vector<std::string> labelNames;
  std::vector<Sample> samples;
};

/// Upper bounds (seconds) for request latencies: 0.5 ms to 10 s.
std::vector<double> latencyBuckets();

/// A small registry of metric families rendered in the Prometheus text exposition format 0.0.4.
/// Families are registered once (at start-up) and live as long as the registry.
///
/// Thread-safe. Lock order: the registry's mutex before a family's; collectors are called with no
/// lock held, so they may take their own locks (the patch cache's).
class Registry {
 public:
  Registry() = default;
  Registry(const Registry&) = delete;
  Registry& operator=(const Registry&) = delete;

  /// Registers a counter family. Names follow Prometheus rules ([a-zA-Z_:][a-zA-Z0-9_:]*, label
  /// names [a-zA-Z_][a-zA-Z0-9_]*); counters should end in "_total". Throws core::Error(
  /// InvalidArgument) on a bad or duplicate name.
  Counter& counter(std::string name, std::string help, std::vector<std::string> labelNames = {});
  /// Registers a histogram family with ascending upper bounds (+Inf is implied).
  Histogram& histogram(std::string name, std::string help, std::vector<std::string> labelNames,
                       std::vector<double> bounds);
  /// Registers a function producing families at scrape time. It must be cheap and must not
  /// call back into the registry.
  void collector(std::function<std::vector<Snapshot>()> collect);

  /// Every family, registered ones first in registration order, then the collectors'.
  std::string render() const;

 private:
  struct Family {
    std::string name;
    std::string help;
    Type type;
    std::vector<std::string> labelNames;
    std::unique_ptr<Counter> counter;
    std::unique_ptr<Histogram> histogram;
  };
  void checkNew(const std::string& name, const std::vector<std::string>& labelNames) const;

  mutable std::mutex mutex_;  // guards families_ and collectors_ (the vectors, not the families)
  std::vector<std::unique_ptr<Family>> families_;
  std::vector<std::shared_ptr<const std::function<std::vector<Snapshot>()>>> collectors_;
};

/// The Content-Type of render()'s output.
inline constexpr std::string_view kContentType = "text/plain; version=0.0.4; charset=utf-8";

}  // namespace vsm::server::metrics
