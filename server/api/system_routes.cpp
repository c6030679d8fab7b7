#include "server/api/system_routes.hpp"

#include <array>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "server/models/encoded_cache.hpp"

namespace vsm::server::api {

using nlohmann::json;

namespace {

http::Response noStore(http::Response response) {
  response.set("Cache-Control", std::string(http::cache_control::kNoStore));
  return response;
}

/// Every category, in the order of the enum.
constexpr auto kCategories = [] {
  std::array<core::MemoryCategory, core::kMemoryCategoryCount> all{};
  for (std::size_t i = 0; i < all.size(); ++i) {
    all[i] = static_cast<core::MemoryCategory>(i);
  }
  return all;
}();

/// Resident bytes of cached responses, by encoding (every encoding, 0 where none is cached).
std::vector<std::pair<models::Encoding, std::size_t>> encodedBytes(const core::CacheStats& stats) {
  std::vector<std::pair<models::Encoding, std::size_t>> out;
  for (const models::Encoding encoding : models::kEncodings) {
    const auto it = stats.encodedByFormat.find(static_cast<std::uint8_t>(encoding));
    out.emplace_back(encoding, it == stats.encodedByFormat.end() ? 0 : it->second);
  }
  return out;
}

}  // namespace

json statsJson(const core::CacheStats& stats, core::EvictionPolicy policy) {
  json byCategory = json::object();
  for (const auto category : kCategories) {
    byCategory[std::string(core::toString(category))] =
        stats.residentByCategory[static_cast<std::size_t>(category)];
  }
  json byEncoding = json::object();
  for (const auto& [encoding, bytes] : encodedBytes(stats)) {
    byEncoding[std::string(models::toString(encoding))] = bytes;
  }
  json byModel = json::object();
  for (const auto& [model, bytes] : stats.residentByModel) {
    byModel[model] = bytes;
  }
  return {
      {"memory",
       {{"budget_bytes", stats.budgetBytes},
        {"resident_bytes", stats.residentBytes},
        {"pinned_bytes", stats.pinnedBytes},
        {"resident_bytes_by_category", std::move(byCategory)},
        {"encoded_bytes_by_encoding", std::move(byEncoding)},
        {"resident_bytes_by_model", std::move(byModel)},
        {"open_files", stats.handles},
        {"open_files_limit", stats.handleBudget}}},
      {"cache",
       {{"policy", core::toString(policy)},
        {"hits", stats.hits},
        {"misses", stats.misses},
        {"evictions", stats.evictions},
        {"write_backs", stats.writeBacks},
        {"exhausted", stats.exhausted}}},
  };
}

std::vector<metrics::Snapshot> cacheMetrics(const core::CacheStats& stats) {
  using metrics::Snapshot;
  using metrics::Type;
  const auto single = [](std::string name, std::string help, Type type, double value) {
    Snapshot s{std::move(name), std::move(help), type, {}, {}};
    s.samples.push_back({{}, value});
    return s;
  };
  std::vector<Snapshot> out;
  out.push_back(single("vsm_memory_budget_bytes", "The memory budget of all models' patch data",
                       Type::Gauge, static_cast<double>(stats.budgetBytes)));
  out.push_back(single("vsm_memory_pinned_bytes", "Resident bytes pinned by requests and jobs",
                       Type::Gauge, static_cast<double>(stats.pinnedBytes)));
  Snapshot byCategory{"vsm_memory_resident_bytes",
                      "Resident bytes by category: patch data and responses encoded from it",
                      Type::Gauge,
                      {"category"},
                      {}};
  for (const auto category : kCategories) {
    byCategory.samples.push_back(
        {{std::string(core::toString(category))},
         static_cast<double>(stats.residentByCategory[static_cast<std::size_t>(category)])});
  }
  out.push_back(std::move(byCategory));
  Snapshot byEncoding{"vsm_memory_encoded_bytes",
                      "Resident bytes of cached responses by encoding (part of category encoded)",
                      Type::Gauge,
                      {"encoding"},
                      {}};
  for (const auto& [encoding, bytes] : encodedBytes(stats)) {
    byEncoding.samples.push_back(
        {{std::string(models::toString(encoding))}, static_cast<double>(bytes)});
  }
  out.push_back(std::move(byEncoding));
  Snapshot byModel{"vsm_memory_model_resident_bytes",
                   "Resident patch data by model",
                   Type::Gauge,
                   {"model"},
                   {}};
  for (const auto& [model, bytes] : stats.residentByModel) {
    byModel.samples.push_back({{model}, static_cast<double>(bytes)});
  }
  out.push_back(std::move(byModel));
  out.push_back(single("vsm_cache_open_files",
                       "Stored patch files held open by the cache (sent with sendfile)",
                       Type::Gauge, static_cast<double>(stats.handles)));
  out.push_back(single("vsm_cache_open_files_limit",
                       "The most stored files the cache may hold open (from RLIMIT_NOFILE)",
                       Type::Gauge, static_cast<double>(stats.handleBudget)));
  out.push_back(single("vsm_cache_hits_total", "Cache lookups served from memory", Type::Counter,
                       static_cast<double>(stats.hits)));
  out.push_back(single("vsm_cache_misses_total",
                       "Cache lookups that found nothing resident (the data is then loaded from "
                       "disk, or the response encoded)",
                       Type::Counter, static_cast<double>(stats.misses)));
  out.push_back(single("vsm_cache_evictions_total", "Entries evicted to stay within the budget",
                       Type::Counter, static_cast<double>(stats.evictions)));
  out.push_back(single("vsm_cache_write_backs_total", "Dirty entries written back to disk",
                       Type::Counter, static_cast<double>(stats.writeBacks)));
  out.push_back(single("vsm_cache_exhausted_total",
                       "Loads refused because everything resident was pinned", Type::Counter,
                       static_cast<double>(stats.exhausted)));
  return out;
}

void addSystemRoutes(http::Router& router, SystemContext context) {
  // Liveness: answering at all is the signal (the handler ran on the CPU pool, so that is alive).
  router.add(http::Method::Get, "/healthz", [](const http::Request&) {
    return noStore(http::jsonResponse(200, {{"status", "ok"}}));
  });
  router.add(http::Method::Get, "/readyz", [ready = context.ready](const http::Request&) {
    if (!ready()) {
      throw core::Error(core::ErrorCode::Unavailable, "not ready: starting or stopping");
    }
    return noStore(http::jsonResponse(200, {{"status", "ready"}}));
  });
  router.add(http::Method::Get, "/metrics", [&metrics = context.metrics](const http::Request&) {
    http::Response response;
    response.contentType = std::string(metrics::kContentType);
    response.body = metrics.render();
    return noStore(std::move(response));
  });
  router.add(http::Method::Get, "/v1/stats",
             [&cache = context.cache, reads = context.reads](const http::Request&) {
               json body = statsJson(cache.stats(), cache.policy());
               if (reads) {
                 body["reads"] = reads();
               }
               return noStore(http::jsonResponse(200, body));
             });
}

}  // namespace vsm::server::api
