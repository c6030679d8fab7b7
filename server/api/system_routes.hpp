#pragma once

#include <functional>

#include <nlohmann/json_fwd.hpp>

#include "core/cache/patch_cache.hpp"
#include "server/http/router.hpp"
#include "server/metrics/metrics.hpp"

namespace vsm::server::api {

/// What the system routes read. Every reference must outlive the router.
struct SystemContext {
  const core::PatchCache& cache;
  const metrics::Registry& metrics;
  /// True once the daemon serves and until it begins to stop.
  std::function<bool()> ready;
  /// The "reads" object of /v1/stats: what costly reads did (revisions read, diffs); null: none.
  std::function<nlohmann::json()> reads = nullptr;
};

/// GET /healthz, /readyz, /metrics, /v1/stats (see proto/openapi.yaml; the model and job routes
/// are in model_routes.hpp and job_routes.hpp).
void addSystemRoutes(http::Router& router, SystemContext context);

/// The body of GET /v1/stats (proto/examples/stats.json).
nlohmann::json statsJson(const core::CacheStats& stats, core::EvictionPolicy policy);

/// Cache statistics as Prometheus families (vsm_cache_*), for a metrics::Registry collector.
std::vector<metrics::Snapshot> cacheMetrics(const core::CacheStats& stats);

}  // namespace vsm::server::api
