#pragma once

#include <cstdint>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json_fwd.hpp>

#include "core/grid/geometry.hpp"
#include "core/pyramid/patch_key.hpp"
#include "server/http/router.hpp"

namespace vsm::core {
class Model;
struct ModelSnapshot;
struct PatchInfo;
class PatchGrid;
}  // namespace vsm::core

namespace vsm::server::models {
class ModelRegistry;
}
namespace vsm::server::jobs {
class JobRegistry;
}

namespace vsm::server::api {

/// What the model and job routes use. Every reference must outlive the router.
struct ModelContext {
  models::ModelRegistry& models;
  jobs::JobRegistry& jobs;
};

/// GET/POST /v1/models, GET/DELETE /v1/models/{m}, GET /v1/models/{m}/hierarchy,
/// /v1/models/{m}/patches/{p}, /v1/models/{m}/patches/{p}/positions, /v1/models/{m}/lod
/// (see proto/openapi.yaml). Every read works on one snapshot of the model, so a response never
/// mixes two versions.
void addModelRoutes(http::Router& router, ModelContext context);

/// GET/POST /v1/jobs, GET/DELETE /v1/jobs/{j}.
void addJobRoutes(http::Router& router, ModelContext context);

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

/// A patch's full grid as `.aara` bytes: V3f, 2 dimensions (size x size), the 13-byte header of
/// ../shared/docs/OPC.md followed by the little-endian floats; NaN marks undefined vertices.
std::string positionsAara(const core::PatchGrid& grid);
/// The 13-byte .aara header of a V3f grid of gridSize x gridSize (what precedes the floats).
std::string aaraHeader(std::size_t gridSize);
/// 16 numbers, row-major, comma-separated, shortest round-trip form ("1,0,0,12.5,...").
std::string matrixText(const core::Mat4d& m);

/// The entity tag of a model's published metadata (summary, hierarchy, LOD cuts): a digest of
/// every patch's key, version, folder, children and box. Derived from content rather than from the
/// snapshot's version, which restarts at 1 whenever the model is opened.
std::string modelEtag(const core::ModelSnapshot& snapshot);
/// The entity tag of one patch (metadata and data): key, patch version (persisted in the OPC)
/// and a digest of its metadata.
std::string patchEtag(const core::PatchInfo& info);

/// Parses the LOD query: `box` is "x0,y0,z0,x1,y1,z1" (six finite numbers, min <= max per axis),
/// `resolution` a finite number > 0. Throws core::Error(InvalidArgument).
struct LodQuery {
  core::Box3d box;
  double resolution = 0;
};
LodQuery parseLodQuery(std::string_view box, std::string_view resolution);

/// The cut of the tree for a view: from the root, descends through patches whose global box meets
/// `box`; stops at a patch whose resolution is at or below `resolution` (finer or equal) or at a
/// leaf. Parents before children, in key order.
std::vector<core::PatchKey> lodCut(const core::Model& model, const core::Box3d& box,
                                   double resolution);

}  // namespace vsm::server::api
