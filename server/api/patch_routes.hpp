#pragma once

#include "server/api/route_helpers.hpp"
#include "server/http/router.hpp"

namespace vsm::server::api {

/// GET /v1/models/{m}/patches/{p}/positions, .../coordinates, .../texture[/{layer}]: a patch's
/// data, found or made by the patch-data service (context.data, which must be set), answered on
/// a network thread when held in the budget, else on the CPU pool (see proto/openapi.yaml). Every
/// read honours `?v=` and `?rev=` (versionedPatch).
void addPatchDataRoutes(http::Router& router, const ModelContext& context);

}  // namespace vsm::server::api
