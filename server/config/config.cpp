#include "server/config/config.hpp"

#include <algorithm>
#include <cctype>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstring>
#include <fstream>
#include <limits>
#include <sstream>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/common/numbers.hpp"
#include "core/common/text.hpp"

namespace vsm::server {

using core::Error;
using core::ErrorCode;
using core::trim;
using nlohmann::json;

namespace {

constexpr std::size_t kKiB = 1024;
constexpr std::size_t kMiB = kKiB * 1024;
constexpr std::size_t kGiB = kMiB * 1024;
/// Longest token (the server compares tokens up to this length in constant time).
constexpr std::size_t kMaxTokenBytes = 1024;

std::string lower(std::string_view s) {
  std::string out(s);
  for (char& c : out) {
    if (c >= 'A' && c <= 'Z') {
      c = static_cast<char>(c - 'A' + 'a');
    }
  }
  return out;
}

/// Splits "1.5GiB" into the number "1.5" and the suffix "GiB".
std::pair<std::string_view, std::string_view> splitNumber(std::string_view text) {
  std::size_t i = 0;
  while (i < text.size() && ((text[i] >= '0' && text[i] <= '9') || text[i] == '.')) {
    ++i;
  }
  return {text.substr(0, i), trim(text.substr(i))};
}

/// number * multiplier as a whole count (fractions rounded down); nullopt on overflow or junk.
std::optional<std::uint64_t> scaled(std::string_view number, std::uint64_t multiplier) {
  if (number.empty()) {
    return std::nullopt;
  }
  if (number.find('.') == std::string_view::npos) {
    std::uint64_t value = 0;
    const auto [ptr, ec] = std::from_chars(number.data(), number.data() + number.size(), value);
    if (ec != std::errc() || ptr != number.data() + number.size() ||
        (multiplier != 0 && value > std::numeric_limits<std::uint64_t>::max() / multiplier)) {
      return std::nullopt;
    }
    return value * multiplier;
  }
  const std::optional<double> value = core::parseDouble(number);
  if (!value || !std::isfinite(*value) || *value < 0) {
    return std::nullopt;
  }
  const double product = std::floor(*value * static_cast<double>(multiplier));
  if (product >= 9.2e18) {
    return std::nullopt;
  }
  return static_cast<std::uint64_t>(product);
}

[[noreturn]] void badValue(std::string_view key, std::string_view expected, const json& value) {
  throw Error(ErrorCode::InvalidArgument, "config key '" + std::string(key) + "': expected " +
                                              std::string(expected) + ", got " + value.dump());
}

std::string textOf(std::string_view key, const json& value, std::string_view expected) {
  if (!value.is_string()) {
    badValue(key, expected, value);
  }
  return value.get<std::string>();
}

std::size_t sizeOf(std::string_view key, const json& value) {
  constexpr std::string_view kExpected = "a size such as 1048576 or \"1MiB\"";
  if (value.is_number_unsigned()) {
    return value.get<std::size_t>();
  }
  if (value.is_string()) {
    try {
      return parseSize(value.get<std::string>());
    } catch (const Error&) {
      badValue(key, kExpected, value);
    }
  }
  badValue(key, kExpected, value);
}

std::chrono::milliseconds durationOf(std::string_view key, const json& value) {
  constexpr std::string_view kExpected = "a duration such as 30 (seconds), \"30s\" or \"250ms\"";
  if (value.is_number() && value.get<double>() >= 0) {
    return std::chrono::milliseconds(std::llround(value.get<double>() * 1000.0));
  }
  if (value.is_string()) {
    try {
      return parseDuration(value.get<std::string>());
    } catch (const Error&) {
      badValue(key, kExpected, value);
    }
  }
  badValue(key, kExpected, value);
}

std::size_t countOf(std::string_view key, const json& value) {
  constexpr std::string_view kExpected = "a whole number >= 0";
  if (value.is_number_unsigned()) {
    return value.get<std::size_t>();
  }
  if (value.is_string()) {
    const std::string text = value.get<std::string>();
    if (const auto n = scaled(trim(text), 1)) {
      if (trim(text).find('.') == std::string_view::npos) {
        return static_cast<std::size_t>(*n);
      }
    }
  }
  badValue(key, kExpected, value);
}

std::string_view levelName(core::log::Level level) {
  switch (level) {
    case core::log::Level::Debug:
      return "debug";
    case core::log::Level::Info:
      return "info";
    case core::log::Level::Warn:
      return "warn";
    case core::log::Level::Error:
      return "error";
    case core::log::Level::Off:
      return "off";
  }
  return "info";
}

/// One configuration key: how to set it from JSON and how to show its value.
struct Key {
  std::string_view name;
  void (*set)(Config&, std::string_view key, const json&);
  std::string (*show)(const Config&);
};

// The one table of keys: set(), from_json (files), flags and describe() all go through it.
const Key kKeys[] = {
    {"listen",
     [](Config& c, std::string_view k, const json& v) {
       c.listen = ListenAddress::parse(textOf(k, v, "\"HOST:PORT\""));
     },
     [](const Config& c) { return c.listen.toString(); }},
    {"data_root",
     [](Config& c, std::string_view k, const json& v) { c.dataRoot = textOf(k, v, "a path"); },
     [](const Config& c) { return c.dataRoot.string(); }},
    {"memory_budget",
     [](Config& c, std::string_view k, const json& v) { c.memoryBudget = sizeOf(k, v); },
     [](const Config& c) { return formatSize(c.memoryBudget); }},
    {"keep_revisions",
     [](Config& c, std::string_view k, const json& v) { c.keepRevisions = countOf(k, v); },
     [](const Config& c) { return std::to_string(c.keepRevisions); }},
    {"keep_revisions_seconds",
     [](Config& c, std::string_view k, const json& v) {
       c.keepRevisionsSeconds = durationOf(k, v);
     },
     [](const Config& c) { return formatDuration(c.keepRevisionsSeconds); }},
    {"cache_policy",
     [](Config& c, std::string_view k, const json& v) {
       const std::string text =
           lower(textOf(k, v, "\"cost-aware-clock\" or \"fifo-second-chance\""));
       if (text == core::toString(core::EvictionPolicy::CostAwareClock)) {
         c.cachePolicy = core::EvictionPolicy::CostAwareClock;
       } else if (text == core::toString(core::EvictionPolicy::FifoSecondChance)) {
         c.cachePolicy = core::EvictionPolicy::FifoSecondChance;
       } else {
         badValue(k, "\"cost-aware-clock\" or \"fifo-second-chance\"", v);
       }
     },
     [](const Config& c) { return std::string(core::toString(c.cachePolicy)); }},
    {"token",
     [](Config& c, std::string_view k, const json& v) { c.token = textOf(k, v, "a string"); },
     [](const Config& c) {
       return std::string(c.token.empty()       ? "(none)"
                          : c.tokenFile.empty() ? "(redacted)"
                                                : "(from token_file)");
     }},
    {"token_file",
     [](Config& c, std::string_view k, const json& v) { c.tokenFile = textOf(k, v, "a path"); },
     [](const Config& c) {
       return c.tokenFile.empty() ? std::string("(none)") : c.tokenFile.string();
     }},
    {"port_file",
     [](Config& c, std::string_view k, const json& v) { c.portFile = textOf(k, v, "a path"); },
     [](const Config& c) {
       return c.portFile.empty() ? std::string("(none)") : c.portFile.string();
     }},
    {"viewer_dir",
     [](Config& c, std::string_view k, const json& v) { c.viewerDir = textOf(k, v, "a path"); },
     [](const Config& c) {
       return c.viewerDir.empty() ? std::string("(none)") : c.viewerDir.string();
     }},
    {"log_level",
     [](Config& c, std::string_view k, const json& v) {
       constexpr std::string_view kExpected = "one of debug, info, warn, error, off";
       const std::string text = lower(textOf(k, v, kExpected));
       for (const auto level :
            {core::log::Level::Debug, core::log::Level::Info, core::log::Level::Warn,
             core::log::Level::Error, core::log::Level::Off}) {
         if (text == levelName(level)) {
           c.logLevel = level;
           return;
         }
       }
       badValue(k, kExpected, v);
     },
     [](const Config& c) { return std::string(levelName(c.logLevel)); }},
    {"limits.body_bytes",
     [](Config& c, std::string_view k, const json& v) { c.limits.bodyBytes = sizeOf(k, v); },
     [](const Config& c) { return formatSize(c.limits.bodyBytes); }},
    {"limits.header_bytes",
     [](Config& c, std::string_view k, const json& v) { c.limits.headerBytes = sizeOf(k, v); },
     [](const Config& c) { return formatSize(c.limits.headerBytes); }},
    {"limits.header_timeout",
     [](Config& c, std::string_view k, const json& v) {
       c.limits.headerTimeout = durationOf(k, v);
     },
     [](const Config& c) { return formatDuration(c.limits.headerTimeout); }},
    {"limits.read_timeout",
     [](Config& c, std::string_view k, const json& v) { c.limits.readTimeout = durationOf(k, v); },
     [](const Config& c) { return formatDuration(c.limits.readTimeout); }},
    {"limits.idle_timeout",
     [](Config& c, std::string_view k, const json& v) { c.limits.idleTimeout = durationOf(k, v); },
     [](const Config& c) { return formatDuration(c.limits.idleTimeout); }},
    {"limits.write_timeout",
     [](Config& c, std::string_view k, const json& v) { c.limits.writeTimeout = durationOf(k, v); },
     [](const Config& c) { return formatDuration(c.limits.writeTimeout); }},
    {"limits.connections",
     [](Config& c, std::string_view k, const json& v) { c.limits.connections = countOf(k, v); },
     [](const Config& c) { return std::to_string(c.limits.connections); }},
    {"limits.connections_per_client",
     [](Config& c, std::string_view k, const json& v) {
       c.limits.connectionsPerClient = countOf(k, v);
     },
     [](const Config& c) { return std::to_string(c.limits.connectionsPerClient); }},
    {"limits.pipelined_responses",
     [](Config& c, std::string_view k, const json& v) {
       c.limits.pipelinedResponses = countOf(k, v);
     },
     [](const Config& c) { return std::to_string(c.limits.pipelinedResponses); }},
    {"limits.texture_pixels",
     [](Config& c, std::string_view k, const json& v) { c.limits.texturePixels = countOf(k, v); },
     [](const Config& c) { return std::to_string(c.limits.texturePixels); }},
    {"limits.event_subscribers",
     [](Config& c, std::string_view k, const json& v) {
       c.limits.eventSubscribers = countOf(k, v);
     },
     [](const Config& c) { return std::to_string(c.limits.eventSubscribers); }},
    {"limits.event_subscribers_per_client",
     [](Config& c, std::string_view k, const json& v) {
       c.limits.eventSubscribersPerClient = countOf(k, v);
     },
     [](const Config& c) { return std::to_string(c.limits.eventSubscribersPerClient); }},
    {"limits.models",
     [](Config& c, std::string_view k, const json& v) { c.limits.models = countOf(k, v); },
     [](const Config& c) { return std::to_string(c.limits.models); }},
    {"limits.diffs",
     [](Config& c, std::string_view k, const json& v) { c.limits.diffs = countOf(k, v); },
     [](const Config& c) { return std::to_string(c.limits.diffs); }},
    {"limits.diff_timeout",
     [](Config& c, std::string_view k, const json& v) { c.limits.diffTimeout = durationOf(k, v); },
     [](const Config& c) { return formatDuration(c.limits.diffTimeout); }},
    {"limits.shutdown_grace",
     [](Config& c, std::string_view k, const json& v) {
       c.limits.shutdownGrace = durationOf(k, v);
     },
     [](const Config& c) { return formatDuration(c.limits.shutdownGrace); }},
    {"threads.io",
     [](Config& c, std::string_view k, const json& v) { c.threads.io = countOf(k, v); },
     [](const Config& c) { return std::to_string(c.threads.io); }},
    {"threads.cpu",
     [](Config& c, std::string_view k, const json& v) { c.threads.cpu = countOf(k, v); },
     [](const Config& c) { return std::to_string(c.threads.cpu); }},
    {"threads.jobs",
     [](Config& c, std::string_view k, const json& v) { c.threads.jobs = countOf(k, v); },
     [](const Config& c) { return std::to_string(c.threads.jobs); }},
    {"cluster.coordinator",
     [](Config& c, std::string_view k, const json& v) {
       c.cluster.coordinator = textOf(k, v, "\"http://HOST:PORT\"");
     },
     [](const Config& c) {
       return c.cluster.coordinator.empty() ? std::string("(none)") : c.cluster.coordinator;
     }},
    {"cluster.node",
     [](Config& c, std::string_view k, const json& v) { c.cluster.node = textOf(k, v, "a name"); },
     [](const Config& c) {
       return c.cluster.node.empty() ? std::string("(host name)") : c.cluster.node;
     }},
    {"cluster.advertise",
     [](Config& c, std::string_view k, const json& v) {
       c.cluster.advertise = textOf(k, v, "\"http://HOST:PORT\"");
     },
     [](const Config& c) {
       return c.cluster.advertise.empty() ? std::string("(listen address)") : c.cluster.advertise;
     }},
    {"cluster.lease_ttl",
     [](Config& c, std::string_view k, const json& v) { c.cluster.leaseTtl = durationOf(k, v); },
     [](const Config& c) { return formatDuration(c.cluster.leaseTtl); }},
};

void flatten(const json& object, const std::string& prefix, Config& config) {
  for (const auto& [name, value] : object.items()) {
    const std::string key = prefix + name;
    if (value.is_object()) {
      flatten(value, key + ".", config);
    } else {
      config.set(key, value);
    }
  }
}

[[noreturn]] void outOfRange(std::string_view key, std::string_view range, std::string_view got) {
  throw Error(ErrorCode::InvalidArgument, "config key '" + std::string(key) + "' must be " +
                                              std::string(range) + " (got " + std::string(got) +
                                              ")");
}

void checkSize(std::string_view key, std::size_t value, std::size_t min, std::size_t max) {
  if (value < min || value > max) {
    outOfRange(key, "between " + formatSize(min) + " and " + formatSize(max), formatSize(value));
  }
}

void checkCount(std::string_view key, std::size_t value, std::size_t min, std::size_t max) {
  if (value < min || value > max) {
    outOfRange(key, "between " + std::to_string(min) + " and " + std::to_string(max),
               std::to_string(value));
  }
}

void checkDuration(std::string_view key, std::chrono::milliseconds value,
                   std::chrono::milliseconds min, std::chrono::milliseconds max) {
  if (value < min || value > max) {
    outOfRange(key, "between " + formatDuration(min) + " and " + formatDuration(max),
               formatDuration(value));
  }
}

/// RFC 6750 b64token: what may follow "Bearer " in an Authorization header.
bool isTokenChar(char c) {
  return (c >= 'A' && c <= 'Z') || (c >= 'a' && c <= 'z') || (c >= '0' && c <= '9') || c == '-' ||
         c == '.' || c == '_' || c == '~' || c == '+' || c == '/' || c == '=';
}

/// "http://HOST:PORT" with a non-empty host, a port, and nothing after it.
bool isHttpUrl(std::string_view url) {
  constexpr std::string_view kScheme = "http://";
  if (!url.starts_with(kScheme)) {
    return false;
  }
  const std::string_view rest = url.substr(kScheme.size());
  const std::size_t colon = rest.rfind(':');
  if (colon == std::string_view::npos || colon == 0 || colon + 1 == rest.size() ||
      rest.size() - colon > 6) {
    return false;
  }
  const auto isHostChar = [](char c) {
    return std::isalnum(static_cast<unsigned char>(c)) != 0 || c == '.' || c == '-' || c == '[' ||
           c == ']' || c == ':';
  };
  return std::all_of(rest.begin(), rest.begin() + static_cast<std::ptrdiff_t>(colon), isHostChar) &&
         std::all_of(rest.begin() + static_cast<std::ptrdiff_t>(colon) + 1, rest.end(),
                     [](char c) { return c >= '0' && c <= '9'; });
}

}  // namespace

bool isNodeName(std::string_view name) {
  return !name.empty() && name.size() <= 32 && std::all_of(name.begin(), name.end(), [](char c) {
    return std::isalnum(static_cast<unsigned char>(c)) != 0 || c == '_' || c == '-';
  });
}

std::string ListenAddress::toString() const {
  const bool v6 = host.find(':') != std::string::npos;
  return (v6 ? "[" + host + "]" : host) + ":" + std::to_string(port);
}

ListenAddress ListenAddress::parse(std::string_view text) {
  const auto fail = [&]() -> ListenAddress {
    throw Error(ErrorCode::InvalidArgument, "listen address '" + std::string(text) +
                                                "' is not HOST:PORT (e.g. 127.0.0.1:8080 or "
                                                "[::1]:8080)");
  };
  const std::size_t colon = text.rfind(':');
  if (colon == std::string_view::npos) {
    return fail();
  }
  std::string_view host = text.substr(0, colon);
  const std::string_view port = text.substr(colon + 1);
  if (host.size() >= 2 && host.front() == '[' && host.back() == ']') {
    host = host.substr(1, host.size() - 2);
  } else if (host.find(':') != std::string_view::npos) {
    return fail();  // a bare IPv6 address is ambiguous: "::1:80"
  }
  unsigned value = 0;
  const auto [ptr, ec] = std::from_chars(port.data(), port.data() + port.size(), value);
  if (host.empty() || port.empty() || ec != std::errc() || ptr != port.data() + port.size() ||
      value > 65535) {
    return fail();
  }
  return ListenAddress{std::string(host), static_cast<std::uint16_t>(value)};
}

std::size_t parseSize(std::string_view text) {
  const std::string_view trimmed = trim(text);
  const auto [number, suffix] = splitNumber(trimmed);
  static const std::pair<std::string_view, std::uint64_t> kUnits[] = {
      {"", 1},
      {"b", 1},
      {"kib", kKiB},
      {"mib", kMiB},
      {"gib", kGiB},
      {"tib", kGiB * kKiB},
      {"kb", 1000},
      {"mb", 1000 * 1000},
      {"gb", 1000 * 1000 * 1000},
      {"tb", std::uint64_t{1000} * 1000 * 1000 * 1000},
  };
  const std::string unit = lower(suffix);
  for (const auto& [name, multiplier] : kUnits) {
    if (unit == name) {
      if (const auto value = scaled(number, multiplier);
          value && *value <= std::numeric_limits<std::size_t>::max()) {
        return static_cast<std::size_t>(*value);
      }
      break;
    }
  }
  throw Error(
      ErrorCode::InvalidArgument,
      "'" + std::string(text) +
          "' is not a size (bytes, or a number with B, KiB, MiB, GiB, TiB, KB, MB, GB, TB)");
}

std::string formatSize(std::size_t bytes) {
  static const std::pair<std::string_view, std::size_t> kUnits[] = {
      {"TiB", kGiB * kKiB}, {"GiB", kGiB}, {"MiB", kMiB}, {"KiB", kKiB}};
  for (const auto& [name, unit] : kUnits) {
    if (bytes >= unit && bytes % unit == 0) {
      return std::to_string(bytes / unit) + std::string(name);
    }
  }
  return std::to_string(bytes);
}

std::chrono::milliseconds parseDuration(std::string_view text) {
  const auto [number, suffix] = splitNumber(trim(text));
  static const std::pair<std::string_view, std::uint64_t> kUnits[] = {
      {"", 1000}, {"s", 1000}, {"ms", 1}, {"m", 60'000}, {"h", 3'600'000}};
  const std::string unit = lower(suffix);
  for (const auto& [name, millis] : kUnits) {
    if (unit == name) {
      if (const auto value = scaled(number, millis);
          value && *value <= static_cast<std::uint64_t>(std::numeric_limits<std::int64_t>::max())) {
        return std::chrono::milliseconds(static_cast<std::int64_t>(*value));
      }
      break;
    }
  }
  throw Error(ErrorCode::InvalidArgument, "'" + std::string(text) +
                                              "' is not a duration (seconds, or a number with ms, "
                                              "s, m, h)");
}

std::string formatDuration(std::chrono::milliseconds duration) {
  const auto ms = duration.count();
  return ms % 1000 == 0 ? std::to_string(ms / 1000) + "s" : std::to_string(ms) + "ms";
}

void Config::set(std::string_view key, const json& value) {
  for (const Key& k : kKeys) {
    if (k.name == key) {
      k.set(*this, key, value);
      return;
    }
  }
  throw Error(ErrorCode::InvalidArgument, "unknown config key '" + std::string(key) + "'");
}

void Config::validate() const {
  using std::chrono::milliseconds;
  using namespace std::chrono_literals;
  if (listen.host.empty()) {
    outOfRange("listen", "HOST:PORT", listen.toString());
  }
  if (dataRoot.empty()) {
    outOfRange("data_root", "a directory", "an empty path");
  }
  checkSize("memory_budget", memoryBudget, kMiB, std::numeric_limits<std::size_t>::max());
  checkCount("keep_revisions", keepRevisions, 2, 10000);
  if (!token.empty()) {
    for (const char c : token) {
      if (!isTokenChar(c)) {
        // The token itself is never echoed: it may be one typo away from the real one.
        outOfRange("token", "letters, digits and -._~+/= only", "another character");
      }
    }
    checkCount("token (its length)", token.size(), 1, kMaxTokenBytes);
  }
  checkSize("limits.body_bytes", limits.bodyBytes, 1, kGiB);
  checkSize("limits.header_bytes", limits.headerBytes, kKiB, kMiB);
  checkDuration("limits.header_timeout", limits.headerTimeout, 10ms, 1h);
  checkDuration("limits.read_timeout", limits.readTimeout, 10ms, 1h);
  checkDuration("limits.idle_timeout", limits.idleTimeout, 10ms, 1h);
  checkDuration("limits.write_timeout", limits.writeTimeout, 10ms, 1h);
  checkDuration("limits.shutdown_grace", limits.shutdownGrace, 0ms, 1h);
  checkCount("limits.connections", limits.connections, 1, 100'000);
  checkCount("limits.connections_per_client", limits.connectionsPerClient, 1, 100'000);
  checkCount("limits.pipelined_responses", limits.pipelinedResponses, 1, 256);
  checkCount("limits.texture_pixels", limits.texturePixels, 1, std::size_t{1} << 32);
  checkCount("limits.event_subscribers", limits.eventSubscribers, 0, 100'000);
  checkCount("limits.event_subscribers_per_client", limits.eventSubscribersPerClient, 0, 100'000);
  checkCount("limits.models", limits.models, 1, 100'000);
  checkCount("limits.diffs", limits.diffs, 0, 1024);
  checkDuration("limits.diff_timeout", limits.diffTimeout, 0ms, 24h);
  checkCount("threads.io", threads.io, 1, 256);
  checkCount("threads.cpu", threads.cpu, 0, 1024);
  checkCount("threads.jobs", threads.jobs, 1, 256);
  if (!cluster.coordinator.empty() && !isHttpUrl(cluster.coordinator)) {
    outOfRange("cluster.coordinator", "http://HOST:PORT", cluster.coordinator);
  }
  if (!cluster.advertise.empty() && !isHttpUrl(cluster.advertise)) {
    outOfRange("cluster.advertise", "http://HOST:PORT", cluster.advertise);
  }
  if (!cluster.node.empty() && !isNodeName(cluster.node)) {
    outOfRange("cluster.node", "1 to 32 of A-Z a-z 0-9 _ -", cluster.node);
  }
  checkDuration("cluster.lease_ttl", cluster.leaseTtl, 2s, 5min);
}

std::vector<std::pair<std::string, std::string>> Config::describe() const {
  std::vector<std::pair<std::string, std::string>> out;
  for (const Key& k : kKeys) {
    out.emplace_back(std::string(k.name), k.show(*this));
  }
  return out;
}

void from_json(const json& json, Config& config) {
  if (!json.is_object()) {
    throw Error(ErrorCode::InvalidArgument, "configuration must be a JSON object");
  }
  flatten(json, "", config);
}

void loadTokenFile(Config& config) {
  if (config.tokenFile.empty()) {
    return;
  }
  const std::string name = "token file '" + config.tokenFile.string() + "'";
  if (!config.token.empty()) {
    throw Error(ErrorCode::InvalidArgument,
                "set token or token_file (--token or --token-file), not both");
  }
  std::ifstream in(config.tokenFile, std::ios::binary);
  if (!in) {
    if (errno == ENOENT) {
      throw Error(ErrorCode::NotFound, name + " not found");
    }
    core::throwIoError("cannot read token file", config.tokenFile.string(), errno);
  }
  std::string line;
  std::getline(in, line);
  while (!line.empty() && (line.back() == '\r' || line.back() == ' ' || line.back() == '\t')) {
    line.pop_back();
  }
  if (line.empty()) {
    throw Error(ErrorCode::InvalidArgument, name + " is empty (its first line is the token)");
  }
  std::error_code ec;
  const auto perms = std::filesystem::status(config.tokenFile, ec).permissions();
  if (!ec && (perms & std::filesystem::perms::others_read) != std::filesystem::perms::none) {
    core::log::warn(name + " can be read by every user (chmod o-r it)");
  }
  config.token = std::move(line);
}

void loadConfigFile(const std::filesystem::path& file, Config& config) {
  std::ifstream in(file, std::ios::binary);
  if (!in) {
    if (errno == ENOENT) {
      throw Error(ErrorCode::NotFound, "config file '" + file.string() + "' not found");
    }
    core::throwIoError("cannot read config file", file.string(), errno);
  }
  // A configuration is a few hundred bytes, two levels deep ("limits": {"body_bytes": ...}); a
  // file far beyond is a mistake (or hostile), refused before it is parsed or recursed into.
  constexpr std::streamsize kMaxBytes = 1 << 20;
  constexpr int kMaxDepth = 8;
  std::string text(static_cast<std::size_t>(kMaxBytes) + 1, '\0');
  in.read(text.data(), kMaxBytes + 1);
  text.resize(static_cast<std::size_t>(in.gcount()));
  if (text.size() > static_cast<std::size_t>(kMaxBytes)) {
    throw Error(ErrorCode::InvalidArgument,
                "config file '" + file.string() + "' is larger than 1 MiB: not a configuration");
  }
  const auto boundDepth = [&](int depth, json::parse_event_t event, json&) {
    if (depth >= kMaxDepth &&
        (event == json::parse_event_t::object_start || event == json::parse_event_t::array_start)) {
      throw Error(ErrorCode::InvalidArgument, "config file '" + file.string() +
                                                  "' nests deeper than " +
                                                  std::to_string(kMaxDepth) + " levels");
    }
    return true;
  };
  json parsed;
  try {
    parsed = json::parse(text, boundDepth, true, /*ignore_comments=*/true);
  } catch (const json::exception& e) {  // parse_error, or out_of_range for "1E400"
    throw Error(ErrorCode::InvalidArgument,
                "config file '" + file.string() + "' is not valid JSON: " + e.what());
  }
  try {
    from_json(parsed, config);
  } catch (const Error& e) {
    throw Error(e.code(), "config file '" + file.string() + "': " + e.what());
  }
}

std::string_view commandLineUsage() {
  return "usage: vsmd [options]\n"
         "\n"
         "The VSM daemon: serves surface models over HTTP/JSON (see proto/openapi.yaml).\n"
         "\n"
         "options (flags override the config file, whatever their order):\n"
         "  --config FILE          JSON configuration file\n"
         "  --listen HOST:PORT     address to listen on (default 127.0.0.1:8080; port 0 = any)\n"
         "  --data-root DIR        where model directories live (default /var/lib/vsm)\n"
         "  --memory-budget SIZE   patch data budget of all models, e.g. 4GiB (default 1GiB)\n"
         "  --token TOKEN          bearer token required for POST/PUT/PATCH/DELETE (visible in\n"
         "                         ps: prefer --token-file)\n"
         "  --token-file PATH      read the token from the first line of PATH\n"
         "  --port-file PATH       write the bound port there once listening\n"
         "  --log-level LEVEL      debug, info, warn, error or off (default info)\n"
         "  --viewer-dir DIR       serve the browser viewer's files from DIR at /viewer/\n"
         "  --keep-revisions N     revisions kept per model, the latest included (default 8,\n"
         "                         at least 2): older ones are read with ?rev=N and restored\n"
         "  --coordinator URL      join a cluster: etcd's client URL (http://HOST:PORT); every\n"
         "                         node serves every model, one elected node writes each\n"
         "  --node NAME            this node's name in the cluster (default: the host name)\n"
         "  --advertise URL        how other nodes reach this one (default http://LISTEN)\n"
         "  --set KEY=VALUE        any configuration key, e.g. --set limits.body_bytes=4MiB\n"
         "  --help, --version\n"
         "\n"
         "configuration keys (file or --set):\n"
         "  listen, data_root, memory_budget, cache_policy (cost-aware-clock |\n"
         "  fifo-second-chance), keep_revisions, keep_revisions_seconds, token, token_file,\n"
         "  port_file, viewer_dir,\n"
         "  log_level,\n"
         "  limits.body_bytes, limits.header_bytes, limits.header_timeout, limits.read_timeout,\n"
         "  limits.idle_timeout, limits.write_timeout, limits.connections,\n"
         "  limits.connections_per_client, limits.pipelined_responses, limits.texture_pixels,\n"
         "  limits.event_subscribers, limits.event_subscribers_per_client, limits.models,\n"
         "  limits.diffs, limits.diff_timeout,\n"
         "  limits.shutdown_grace, threads.io,\n"
         "  threads.cpu (0 = one per core), threads.jobs,\n"
         "  cluster.coordinator, cluster.node, cluster.advertise, cluster.lease_ttl (10s)\n"
         "sizes: bytes or 512KiB, 64MiB, 4GiB, 1GB ...; durations: seconds or 250ms, 30s, 5m\n";
}

CommandLine parseCommandLine(const std::vector<std::string>& args) {
  static const std::pair<std::string_view, std::string_view> kFlags[] = {
      {"--listen", "listen"},
      {"--data-root", "data_root"},
      {"--memory-budget", "memory_budget"},
      {"--token", "token"},
      {"--token-file", "token_file"},
      {"--port-file", "port_file"},
      {"--log-level", "log_level"},
      {"--viewer-dir", "viewer_dir"},
      {"--keep-revisions", "keep_revisions"},
      {"--coordinator", "cluster.coordinator"},
      {"--node", "cluster.node"},
      {"--advertise", "cluster.advertise"},
      {"--config", ""},
      {"--set", ""},
  };
  CommandLine out;
  std::optional<std::filesystem::path> configFile;
  std::vector<std::pair<std::string, std::string>> settings;  // key, value, in command-line order

  for (std::size_t i = 0; i < args.size(); ++i) {
    std::string_view arg = args[i];
    if (arg == "--help" || arg == "-h") {
      out.help = true;
      continue;
    }
    if (arg == "--version") {
      out.version = true;
      continue;
    }
    std::optional<std::string> value;
    if (const std::size_t eq = arg.find('='); arg.starts_with("--") && eq != std::string::npos) {
      value = std::string(arg.substr(eq + 1));
      arg = arg.substr(0, eq);
    }
    const auto flag = std::find_if(std::begin(kFlags), std::end(kFlags),
                                   [&](const auto& f) { return f.first == arg; });
    if (flag == std::end(kFlags)) {
      throw Error(ErrorCode::InvalidArgument,
                  "unknown option '" + std::string(arg) + "' (see vsmd --help)");
    }
    if (!value) {
      if (i + 1 >= args.size()) {
        throw Error(ErrorCode::InvalidArgument, "option " + std::string(arg) + " needs a value");
      }
      value = args[++i];
    }
    if (arg == "--config") {
      configFile = *value;
    } else if (arg == "--set") {
      const std::size_t eq = value->find('=');
      if (eq == std::string::npos || eq == 0) {
        throw Error(ErrorCode::InvalidArgument, "--set needs KEY=VALUE, got '" + *value + "'");
      }
      settings.emplace_back(value->substr(0, eq), value->substr(eq + 1));
    } else {
      settings.emplace_back(std::string(flag->second), *value);
    }
  }
  if (out.help || out.version) {
    return out;
  }
  if (configFile) {
    loadConfigFile(*configFile, out.config);
  }
  for (const auto& [key, value] : settings) {
    out.config.set(key, json(value));
  }
  loadTokenFile(out.config);
  out.config.validate();
  return out;
}

}  // namespace vsm::server
