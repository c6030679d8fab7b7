#include "server/metrics/metrics.hpp"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <limits>

#include "core/common/error.hpp"

namespace vsm::server::metrics {

using core::Error;
using core::ErrorCode;

namespace {

std::vector<std::string> toKey(std::initializer_list<std::string_view> values, std::size_t count) {
  if (values.size() != count) {
    throw Error(ErrorCode::Internal, "metric needs " + std::to_string(count) +
                                         " label values, got " + std::to_string(values.size()));
  }
  return {values.begin(), values.end()};
}

bool validName(std::string_view name, bool allowColon) {
  if (name.empty() || (name[0] >= '0' && name[0] <= '9')) {
    return false;
  }
  return std::all_of(name.begin(), name.end(), [&](char c) {
    return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') || c == '_' ||
           (allowColon && c == ':');
  });
}

std::string number(double value) {
  if (std::isinf(value)) {
    return value > 0 ? "+Inf" : "-Inf";
  }
  if (std::isnan(value)) {
    return "NaN";
  }
  if (value == std::trunc(value) && std::fabs(value) < 9.0e15) {
    return std::to_string(static_cast<long long>(value));  // counts and bytes: exact integers
  }
  // Shortest round-trip form, never locale-dependent ("0.0005", not "5e-04").
  char text[64];
  const auto result = std::to_chars(text, text + sizeof text, value, std::chars_format::general);
  return std::string(text, result.ptr);
}

std::string_view typeName(Type type) {
  switch (type) {
    case Type::Counter:
      return "counter";
    case Type::Gauge:
      return "gauge";
    case Type::Histogram:
      return "histogram";
  }
  return "untyped";
}

void appendEscaped(std::string& out, std::string_view text, bool quotes) {
  for (const char c : text) {
    if (c == '\\') {
      out += "\\\\";
    } else if (c == '\n') {
      out += "\\n";
    } else if (quotes && c == '"') {
      out += "\\\"";
    } else {
      out += c;
    }
  }
}

void appendHeader(std::string& out, std::string_view name, std::string_view help, Type type) {
  out += "# HELP ";
  out += name;
  out += ' ';
  appendEscaped(out, help, false);
  out += "\n# TYPE ";
  out += name;
  out += ' ';
  out += typeName(type);
  out += '\n';
}

/// name{a="x",b="y",extra="z"} value
void appendSample(std::string& out, std::string_view name, const std::vector<std::string>& labels,
                  const std::vector<std::string>& values, std::string_view extraLabel,
                  std::string_view extraValue, double value) {
  out += name;
  if (!labels.empty() || !extraLabel.empty()) {
    out += '{';
    bool first = true;
    for (std::size_t i = 0; i < labels.size() && i < values.size(); ++i) {
      out += first ? "" : ",";
      first = false;
      out += labels[i];
      out += "=\"";
      appendEscaped(out, values[i], true);
      out += '"';
    }
    if (!extraLabel.empty()) {
      out += first ? "" : ",";
      out += extraLabel;
      out += "=\"";
      out += extraValue;
      out += '"';
    }
    out += '}';
  }
  out += ' ';
  out += number(value);
  out += '\n';
}

}  // namespace

std::vector<double> latencyBuckets() {
  return {0.0005, 0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10};
}

Counter::Series& Counter::series(std::initializer_list<std::string_view> labelValues) {
  auto key = toKey(labelValues, labelCount_);
  const std::lock_guard lock(mutex_);
  return values_.try_emplace(std::move(key)).first->second;
}

double Counter::value(std::initializer_list<std::string_view> labelValues) const {
  const auto key = toKey(labelValues, labelCount_);
  const std::lock_guard lock(mutex_);
  const auto it = values_.find(key);
  return it == values_.end() ? 0.0 : it->second.value();
}

void Histogram::Series::observe(double value) {
  const std::size_t bucket = static_cast<std::size_t>(
      std::lower_bound(bounds_.begin(), bounds_.end(), value) - bounds_.begin());
  buckets_[bucket].fetch_add(1, std::memory_order_relaxed);
  sum_.fetch_add(value, std::memory_order_relaxed);
}

Histogram::Series& Histogram::series(std::initializer_list<std::string_view> labelValues) {
  auto key = toKey(labelValues, labelCount_);
  const std::lock_guard lock(mutex_);
  return series_.try_emplace(std::move(key), bounds_).first->second;
}

void Registry::checkNew(const std::string& name, const std::vector<std::string>& labelNames) const {
  if (!validName(name, true)) {
    throw Error(ErrorCode::InvalidArgument, "bad metric name '" + name + "'");
  }
  for (const std::string& label : labelNames) {
    if (!validName(label, false) || label == "le") {
      throw Error(ErrorCode::InvalidArgument, "bad label name '" + label + "' of " + name);
    }
  }
  for (const auto& family : families_) {
    if (family->name == name) {
      throw Error(ErrorCode::InvalidArgument, "metric '" + name + "' registered twice");
    }
  }
}

Counter& Registry::counter(std::string name, std::string help,
                           std::vector<std::string> labelNames) {
  const std::lock_guard lock(mutex_);
  checkNew(name, labelNames);
  auto family = std::make_unique<Family>(Family{std::move(name), std::move(help), Type::Counter,
                                                std::move(labelNames), nullptr, nullptr});
  family->counter = std::make_unique<Counter>(family->labelNames.size());
  Counter& out = *family->counter;
  families_.push_back(std::move(family));
  return out;
}

Histogram& Registry::histogram(std::string name, std::string help,
                               std::vector<std::string> labelNames, std::vector<double> bounds) {
  if (!std::is_sorted(bounds.begin(), bounds.end()) ||
      std::adjacent_find(bounds.begin(), bounds.end()) != bounds.end()) {
    throw Error(ErrorCode::InvalidArgument, "histogram '" + name + "' needs ascending bounds");
  }
  const std::lock_guard lock(mutex_);
  checkNew(name, labelNames);
  auto family = std::make_unique<Family>(Family{std::move(name), std::move(help), Type::Histogram,
                                                std::move(labelNames), nullptr, nullptr});
  family->histogram = std::make_unique<Histogram>(family->labelNames.size(), std::move(bounds));
  Histogram& out = *family->histogram;
  families_.push_back(std::move(family));
  return out;
}

void Registry::collector(std::function<std::vector<Snapshot>()> collect) {
  const std::lock_guard lock(mutex_);
  collectors_.push_back(
      std::make_shared<const std::function<std::vector<Snapshot>()>>(std::move(collect)));
}

std::string Registry::render() const {
  std::vector<const Family*> families;
  std::vector<std::shared_ptr<const std::function<std::vector<Snapshot>()>>> collectors;
  {
    const std::lock_guard lock(mutex_);
    for (const auto& family : families_) {
      families.push_back(family.get());  // families are never removed: the pointers stay valid
    }
    collectors = collectors_;
  }

  std::string out;
  out.reserve(4096);
  for (const Family* family : families) {
    appendHeader(out, family->name, family->help, family->type);
    if (family->counter) {
      const std::lock_guard lock(family->counter->mutex_);
      if (family->labelNames.empty() && family->counter->values_.empty()) {
        appendSample(out, family->name, {}, {}, {}, {}, 0.0);  // a counter never hit is 0
      }
      for (const auto& [labels, series] : family->counter->values_) {
        appendSample(out, family->name, family->labelNames, labels, {}, {}, series.value());
      }
    } else if (family->histogram) {
      const Histogram& h = *family->histogram;
      const std::lock_guard lock(h.mutex_);
      for (const auto& [labels, series] : h.series_) {
        std::uint64_t cumulative = 0;
        for (std::size_t i = 0; i <= h.bounds_.size(); ++i) {
          cumulative += series.buckets_[i].load(std::memory_order_relaxed);
          const double bound =
              i < h.bounds_.size() ? h.bounds_[i] : std::numeric_limits<double>::infinity();
          appendSample(out, family->name + "_bucket", family->labelNames, labels, "le",
                       number(bound), static_cast<double>(cumulative));
        }
        appendSample(out, family->name + "_sum", family->labelNames, labels, {}, {},
                     series.sum_.load(std::memory_order_relaxed));
        appendSample(out, family->name + "_count", family->labelNames, labels, {}, {},
                     static_cast<double>(cumulative));
      }
    }
  }
  // No lock held here: collectors take their components' locks.
  for (const auto& collect : collectors) {
    for (const Snapshot& snapshot : (*collect)()) {
      appendHeader(out, snapshot.name, snapshot.help, snapshot.type);
      for (const Sample& sample : snapshot.samples) {
        appendSample(out, snapshot.name, snapshot.labelNames, sample.labelValues, {}, {},
                     sample.value);
      }
    }
  }
  return out;
}

}  // namespace vsm::server::metrics
