#include "server/api/ray_routes.hpp"

#include <cstddef>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/pyramid/model.hpp"
#include "core/ray/ray_query.hpp"
#include "core/store/live_model.hpp"
#include "server/api/requests.hpp"
#include "server/api/route_helpers.hpp"
#include "server/models/encoded_cache.hpp"
#include "server/models/model_registry.hpp"
#include "server/models/patch_data.hpp"

namespace vsm::server::api {

using core::Error;
using core::ErrorCode;
using nlohmann::json;

namespace {

/// Rays per request: at about a millisecond a ray (a few blocks of one or two leaves read from
/// the cache and built), one core answers them in about a second.
constexpr std::size_t kMaxRays = 1000;

json vecJson(const core::Vec3d& v) {
  return json::array({v.x, v.y, v.z});
}

json hitJson(const std::optional<core::RayHit>& hit) {
  if (!hit) {
    return {{"hit", nullptr}};
  }
  return {{"hit",
           {{"point", vecJson(hit->point)},
            {"distance", hit->distance},
            {"normal", vecJson(hit->normal)},
            {"patch", hit->leaf.toString()},
            {"depth", hit->leaf.depth},
            {"resolution", hit->resolution}}}};
}

/// GET or POST /v1/models/{m}/ray.
http::Response rayAnswer(models::ModelRegistry& models, models::PatchData& data,
                         const http::Request& request) {
  const std::vector<core::Ray> rays = parseRayQuery(request, kMaxRays);
  const std::string id = request.param("m");
  const models::ModelRegistry::Served served = models.getServed(id);
  const std::shared_ptr<const core::ModelSnapshot> snapshot =
      versionedSnapshot(*served.live, request);
  if (snapshot->model->empty()) {
    throw Error(ErrorCode::NotFound, "model '" + id + "' has no patches");
  }
  core::RayLimits limits;
  limits.rays = kMaxRays;
  const auto hits = core::castRays(
      *snapshot->model, rays, data.gridLoader(served, *snapshot), limits,
      [&](std::size_t bytes) { return served.encoded->reserve(models::Encoding::RayWork, bytes); });
  json results = json::array();
  for (const std::optional<core::RayHit>& hit : hits) {
    results.push_back(hitJson(hit));
  }
  http::Response response = http::jsonResponse(200, {{"status", "OK"},
                                                     {"results", std::move(results)},
                                                     {"model", id},
                                                     {"model_version", snapshot->version}});
  response.set("X-VSM-Model-Version", std::to_string(snapshot->version));
  return withCache(std::move(response), http::cache_control::kRevalidate);
}

}  // namespace

void addRayRoutes(http::Router& router, models::ModelRegistry& models,
                  std::shared_ptr<models::PatchData> data) {
  if (data == nullptr) {
    data = std::make_shared<models::PatchData>();
  }
  for (const http::Method method : {http::Method::Get, http::Method::Post}) {
    router.add(method, "/v1/models/{m}/ray", [&models, data](const http::Request& request) {
      return rayAnswer(models, *data, request);
    });
  }
}

}  // namespace vsm::server::api
