#pragma once

#include <string_view>

#include <nlohmann/json_fwd.hpp>

#include "core/grid/geometry.hpp"
#include "core/pyramid/patch_key.hpp"
#include "server/api/etags.hpp"
#include "server/api/requests.hpp"
#include "server/api/route_helpers.hpp"
#include "server/http/router.hpp"

namespace vsm::core {
class Model;
struct ModelSnapshot;
struct PatchInfo;
}  // namespace vsm::core

namespace vsm::server::api {

/// GET/POST /v1/models, GET/DELETE /v1/models/{m}, GET /v1/models/{m}/hierarchy,
/// /v1/models/{m}/patches/{p}, /v1/models/{m}/patches/{p}/positions, .../coordinates,
/// .../texture[/{layer}] (addPatchDataRoutes), /v1/models/{m}/lod, /v1/models/{m}/diff[.png] (see
/// proto/openapi.yaml).
/// Every read works on one snapshot of the model, so a response never mixes two versions; the
/// summary, hierarchy, LOD cut and every patch route honour `?v=` (versionedSnapshot,
/// versionedPatch).
void addModelRoutes(http::Router& router, ModelContext context);

// ---- wire mapping, public for tests -----------------------------------------------------------

/// {"min": [x, y, z], "max": [x, y, z]}, or null for an empty box.
nlohmann::json boxJson(const core::Box3d& box);
/// An entry of GET /v1/models (proto/examples/models.json); with `details` the full summary of
/// GET /v1/models/{m} (per-level summaries; proto/examples/model.json).
nlohmann::json modelJson(std::string_view id, const core::ModelSnapshot& snapshot, bool details);
/// GET /v1/models/{m}/patches/{p} (proto/examples/patch.json).
nlohmann::json patchJson(std::string_view id, const core::ModelSnapshot& snapshot,
                         const core::PatchInfo& info);
/// The tree below `root`, `levels` levels deep (0: the root alone; negative: all).
nlohmann::json hierarchyJson(const core::Model& model, const core::PatchKey& root, int levels);

}  // namespace vsm::server::api
