#pragma once

#include "server/api/route_helpers.hpp"
#include "server/http/router.hpp"

namespace vsm::server::api {

/// GET/POST /v1/jobs, GET/DELETE /v1/jobs/{j} (see proto/openapi.yaml). In a cluster a merge is
/// redirected to its model's writer and a job of another node to that node (307).
void addJobRoutes(http::Router& router, ModelContext context);

}  // namespace vsm::server::api
