// Fuzz target: the LOD query (GET /v1/models/{m}/lod?box=...&resolution=... or
// ?eye=...&dir=...&up=...&fov=...&height=...&sse=...): the query string as sent, its parameters
// percent-decoded, parsed by parseLodQuery or parseCameraQuery, and the cut of a model of
// variable depth for the parsed view (core::lodCut, core::lodCutForCamera).
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <string>
#include <vector>

#include "core/pyramid/model.hpp"
#include "core/tiles/lod_cut.hpp"
#include "server/api/requests.hpp"
#include "tests/fuzz/fuzz_support.hpp"

using namespace vsm;

namespace {

/// 1024 m square, 128 m resolution at the root, full to depth 3, deeper (to 8) in its north-west
/// corner at every level.
core::Model makeModel() {
  core::Model model(9);
  std::vector<core::PatchKey> queue{core::PatchKey::root()};
  for (std::size_t i = 0; i < queue.size(); ++i) {
    const core::PatchKey key = queue[i];
    const double side = 1024.0 / (1u << key.depth);
    core::PatchInfo info;
    info.key = key;
    info.globalBox.min = {key.x * side, key.y * side, 0.0};
    info.globalBox.max = {(key.x + 1) * side, (key.y + 1) * side, 100.0};
    info.localBox = info.globalBox;
    info.resolution = 128.0 / (1u << key.depth);
    info.stored = core::GridRect{0, 0, 9, 9};
    model.insert(info);
    if (key.depth < 3 || (key.depth < 8 && key.x == 0 && key.y == 0)) {
      for (const core::Quadrant q : core::kQuadrants) {
        queue.push_back(key.child(q));
      }
    }
  }
  return model;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  static const core::Model model = makeModel();
  server::http::Request request;
  request.target = "/v1/models/m/lod?" + std::string(reinterpret_cast<const char*>(data), size);
  fuzz::succeeds([&] {
    if (request.queryParam("eye")) {
      const server::api::CameraQuery query = server::api::parseCameraQuery(request);
      const auto cut = core::lodCutForCamera(model, query.camera, query.maxScreenError);
      fuzz::check(cut.size() <= model.patchCount(), "a camera cut names each patch at most once");
      for (const core::CameraCutEntry& entry : cut) {
        fuzz::check(model.find(entry.key) != nullptr, "a camera cut names patches of the model");
        fuzz::check(entry.screenError <= query.maxScreenError || model.at(entry.key).isLeaf(),
                    "a drawn tile is fine enough or a leaf");
      }
      return;
    }
    const auto box = request.queryParam("box");
    const auto resolution = request.queryParam("resolution");
    if (!box || !resolution) {
      return;
    }
    const server::api::LodQuery query = server::api::parseLodQuery(*box, *resolution);
    fuzz::check(std::isfinite(query.resolution) && query.resolution > 0, "resolution > 0");
    fuzz::check(query.box.min.x <= query.box.max.x && query.box.min.y <= query.box.max.y &&
                    query.box.min.z <= query.box.max.z,
                "min <= max on every axis");
    const std::vector<core::PatchKey> cut = core::lodCut(model, query.box, query.resolution);
    fuzz::check(cut.size() <= model.patchCount(), "a cut names each patch at most once");
    for (const core::PatchKey& key : cut) {
      fuzz::check(model.find(key) != nullptr, "a cut names patches of the model");
    }
  });
  return 0;
}
