#pragma once

#include <memory>

#include "server/http/router.hpp"

namespace vsm::server::models {
class ModelRegistry;
class PatchData;
}  // namespace vsm::server::models

namespace vsm::server::api {

/// Ray queries, for every open model whatever its shape (rock faces, tunnels and overhangs in a
/// point cloud's own frame as much as terrain in ECEF): the first hit of each ray on the model's
/// finest leaves (core/ray/ray_query.hpp), with its distance, the surface's normal there and the
/// leaf that answered.
///
/// - GET /v1/models/{m}/ray?origin=x,y,z&direction=dx,dy,dz[&max_distance=D]: one ray;
/// - POST /v1/models/{m}/ray with {"rays": [{"origin", "direction", "max_distance"?}, ...]}: up to
///   1000 rays (a write by method: it needs the token when one is set, as POST /elevation).
///
/// Both take `?rev=` and `?v=` (versionedSnapshot) and answer {"status": "OK", "results":
/// [{"hit": {...} or null}], "model", "model_version"}. Bounded: 1000 rays a request, 32 leaves
/// and 2^17 cells' blocks a ray (more: 400 "too long", shorten it with max_distance); each ray's
/// hierarchy is charged to the budget (Encoding::RayWork) while it is built and cast. Leaves are
/// read through PatchData::gridLoader. Pool only. See proto/openapi.yaml.
void addRayRoutes(http::Router& router, models::ModelRegistry& models,
                  std::shared_ptr<models::PatchData> data);

}  // namespace vsm::server::api
