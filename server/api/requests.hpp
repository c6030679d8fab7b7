#pragma once

// What the routes read from a request before they touch a model: the LOD queries and the JSON
// bodies of the POST routes, parsed and checked. Kept apart from the handlers (and their
// registries) so the parsing can be tested and fuzzed alone (tests/fuzz/).

#include <cstddef>
#include <optional>
#include <string>
#include <string_view>
#include <vector>

#include "core/grid/geometry.hpp"
#include "core/ray/ray_query.hpp"
#include "core/tiles/lod_cut.hpp"
#include "server/http/message.hpp"

namespace vsm::server::api {

/// Parses the LOD query: `box` is "x0,y0,z0,x1,y1,z1" (six finite numbers, min <= max per axis),
/// `resolution` a finite number > 0. Throws core::Error(InvalidArgument).
struct LodQuery {
  core::Box3d box;
  double resolution = 0;
};
LodQuery parseLodQuery(std::string_view box, std::string_view resolution);

/// The camera form of the LOD query: `eye`, `dir`, `up` ("x,y,z", global coordinates), `fov`
/// (vertical, degrees), `height` and optional `width` (pixels; width defaults to height), `sse`
/// (the screen-space error threshold, pixels, > 0). Throws core::Error(InvalidArgument) naming
/// the missing or wrong parameter.
struct CameraQuery {
  core::Camera camera;
  double maxScreenError = 0;
};
CameraQuery parseCameraQuery(const http::Request& request);

/// The body of POST /v1/models (proto/examples/model-open-request.json and
/// model-import-request.json): open the OPC at `path`, or import the raster at `import`.
struct ModelRequest {
  /// Not yet checked against the model id rules (models::checkModelId).
  std::string id;
  /// Exactly one of `path` and `import` is set; both relative to the data root, not resolved.
  std::optional<std::string> path;
  std::optional<std::string> import;
  /// With `import`: the patch size asked for (257 when absent), -1 when it is out of any range
  /// (the import rejects it with the rule 2^n + 1).
  int patchSize = 257;
  /// With `import`: "texture": "relief" (the default, the surface's shaded relief) or "none" (no
  /// texture; PRo3D will not open the model). True for "none".
  bool untextured = false;
  /// With `import`: "visible_texels_per_quad" (hidden levels below it; 0 when absent), checked by
  /// the import's submission (jobs::submitImport); -1 when it is out of any range.
  int visibleTexelsPerQuad = 0;
};
/// Throws core::Error(InvalidArgument) naming the first wrong member, as http::jsonBody does for
/// a body that is not JSON.
ModelRequest parseModelRequest(const http::Request& request);

/// The body of POST /v1/jobs (proto/examples/merge-request.json): merge model `source` into
/// model `target`.
struct MergeRequest {
  std::string target;
  std::string source;
  bool registerFirst = false;
};
/// Throws core::Error(InvalidArgument) naming the first wrong member.
MergeRequest parseMergeRequest(const http::Request& request);

/// The rays of a ray query (proto/openapi.yaml, /v1/models/{m}/ray), in the model's global frame:
/// a GET's one ray, `origin=x,y,z&direction=dx,dy,dz[&max_distance=D]`, or a POST's JSON body
/// {"rays": [{"origin": [x, y, z], "direction": [dx, dy, dz], "max_distance": D}, ...]} (1 to
/// `maxRays` rays, no other members). Origins are finite, directions finite and not zero (any
/// length), max distances finite and >= 0 (infinity when absent: as far as the model reaches).
/// Throws core::Error(InvalidArgument) naming the parameter, or the ray (counted from 1) and its
/// member.
std::vector<core::Ray> parseRayQuery(const http::Request& request, std::size_t maxRays);

}  // namespace vsm::server::api
