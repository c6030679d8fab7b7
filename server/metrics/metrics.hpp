#pragma once

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
  /// Made by Registry::counter().
  explicit Counter(std::size_t labelCount) : labelCount_(labelCount) {}
  /// Adds `by` (>= 0) to the series with these label values (one per label name, in order).
  /// Throws core::Error(Internal) on a wrong number of label values.
  void inc(std::initializer_list<std::string_view> labelValues, double by = 1.0);
  /// The current value of a series; 0 when it was never incremented.
  double value(std::initializer_list<std::string_view> labelValues) const;

 private:
  friend class Registry;
  std::size_t labelCount_;
  mutable std::mutex mutex_;  // guards values_
  std::map<std::vector<std::string>, double> values_;
};

/// A histogram family: per combination of label values, counts of observations per bucket
/// (cumulative when rendered), their sum and count. Thread-safe.
class Histogram {
 public:
  /// Made by Registry::histogram().
  Histogram(std::size_t labelCount, std::vector<double> bounds)
      : labelCount_(labelCount), bounds_(std::move(bounds)) {}
  /// Records one observation. Throws core::Error(Internal) on a wrong number of label values.
  void observe(std::initializer_list<std::string_view> labelValues, double value);

 private:
  friend class Registry;
  struct Series {
    std::vector<std::uint64_t> buckets;  // non-cumulative; one per upper bound, then +Inf
    double sum = 0;
    std::uint64_t count = 0;
  };
  std::size_t labelCount_;
  std::vector<double> bounds_;  // ascending upper bounds, without +Inf
  mutable std::mutex mutex_;    // guards series_
  std::map<std::vector<std::string>, Series> series_;
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
