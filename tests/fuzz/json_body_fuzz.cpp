// Fuzz target: the JSON bodies of every POST route (POST /v1/models, POST /v1/jobs, POST
// /v1/models/{m}/ray), through http::jsonBody (the one parser, with its nesting bound) and the
// routes' body parsers.
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <string>

#include "server/api/requests.hpp"
#include "tests/fuzz/fuzz_support.hpp"

using namespace vsm;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  server::http::Request request;
  request.method = server::http::Method::Post;
  request.methodName = "POST";
  request.headers = {{"content-type", "application/json"}};
  request.body.assign(reinterpret_cast<const char*>(data), size);

  request.target = "/v1/models";
  fuzz::succeeds([&] {
    const server::api::ModelRequest model = server::api::parseModelRequest(request);
    fuzz::check(model.path.has_value() != model.import.has_value(),
                "a model request has exactly one of path and import");
    fuzz::check(model.patchSize == -1 || (model.patchSize >= 0 && model.patchSize <= 1'000'000),
                "a patch size is -1 or in range");
    fuzz::check(!model.path || model.patchSize == 257, "patch_size goes with import only");
  });
  request.target = "/v1/jobs";
  fuzz::succeeds([&] { server::api::parseMergeRequest(request); });
  request.target = "/v1/models/m/ray";
  fuzz::succeeds([&] {
    const auto rays = server::api::parseRayQuery(request, 8);
    fuzz::check(!rays.empty() && rays.size() <= 8, "a ray query has 1 to maxRays rays");
    for (const core::Ray& ray : rays) {
      const double length = ray.direction.norm();
      fuzz::check(ray.origin.finite() && length > 0 && std::isfinite(length),
                  "a ray has a finite origin and a finite, non-zero direction");
      fuzz::check(ray.maxDistance >= 0, "a ray's max distance is >= 0");
    }
  });
  return 0;
}
