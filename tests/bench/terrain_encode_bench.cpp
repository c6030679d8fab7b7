// Benchmark (not a test): the core of a quantized-mesh tile, without HTTP and without gzip, on
// one thread. Reads an OPC model (every patch once, into memory, before timing: the disk is not
// measured), builds its terrain layer, then samples and encodes every available tile of the levels
// asked for (with both extensions, as CesiumJS asks), and prints per level the tiles, the
// median/p90/max time per tile and tiles/s. Run by tests/bench/terrain_bench.py, or by hand:
//
//   build/tests/bench/terrain_encode_bench <opc> [min-level] [max-tiles-per-level]
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <map>
#include <memory>
#include <vector>

#include "core/grid/patch_grid.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/pyramid/model.hpp"
#include "core/tiles/quantized_mesh.hpp"

int main(int argc, char** argv) {
  using namespace vsm::core;
  using Clock = std::chrono::steady_clock;
  if (argc < 2) {
    std::fprintf(stderr, "usage: terrain_encode_bench <opc> [min-level] [max-tiles-per-level]\n");
    return 2;
  }
  const std::filesystem::path dir = argv[1];
  const int minLevel = argc > 2 ? std::atoi(argv[2]) : 0;
  const std::size_t maxTiles = argc > 3 ? std::strtoul(argv[3], nullptr, 10) : 200;
  const Model model = readOpcModel(dir);
  std::map<PatchKey, std::shared_ptr<const PatchGrid>> grids;
  for (const auto& [key, info] : model.patches()) {
    grids[key] = std::make_shared<const PatchGrid>(readPatchGrid(dir, model, info));
  }
  const TerrainGridLoader load = [&](const PatchInfo& info) { return grids.at(info.key); };

  auto start = Clock::now();
  const TerrainLayer layer = buildTerrainLayer(model, load);
  std::printf("layer (footprints of %zu patches, availability to level %d): %.1f ms\n",
              model.patchCount(), layer.maxZoom,
              std::chrono::duration<double, std::milli>(Clock::now() - start).count());
  std::vector<double> all;
  for (int z = minLevel; z <= layer.maxZoom; ++z) {
    std::vector<TerrainTileKey> keys;
    for (const TileRange& r : layer.available[static_cast<std::size_t>(z)]) {
      for (std::uint32_t y = r.startY; y <= r.endY; ++y) {
        for (std::uint32_t x = r.startX; x <= r.endX; ++x) {
          keys.push_back({z, x, y});
        }
      }
    }
    if (keys.size() > maxTiles) {  // spread evenly
      std::vector<TerrainTileKey> some;
      for (std::size_t i = 0; i < maxTiles; ++i) {
        some.push_back(keys[i * keys.size() / maxTiles]);
      }
      keys = some;
    }
    std::vector<double> ms;
    std::size_t bytes = 0;
    for (const TerrainTileKey& key : keys) {
      start = Clock::now();
      const auto sources = terrainSources(model, layer, key);
      QuantizedMeshOptions options{.normals = true, .metadata = terrainMetadataJson(layer, key)};
      bytes += encodeQuantizedMesh(sampleTerrain(model, sources, key, load), options).size();
      ms.push_back(std::chrono::duration<double, std::milli>(Clock::now() - start).count());
    }
    std::sort(ms.begin(), ms.end());
    double sum = 0;
    for (const double m : ms) {
      sum += m;
    }
    all.insert(all.end(), ms.begin(), ms.end());
    std::printf(
        "level %2d: %4zu tiles, per tile median %.2f ms, p90 %.2f ms, max %.2f ms; %.0f "
        "tiles/s; %.1f KiB each\n",
        z, ms.size(), ms[ms.size() / 2], ms[ms.size() * 9 / 10], ms.back(), 1000 * ms.size() / sum,
        bytes / 1024.0 / ms.size());
  }
  std::sort(all.begin(), all.end());
  double sum = 0;
  for (const double m : all) {
    sum += m;
  }
  std::printf("all: %zu tiles, per tile median %.2f ms, p90 %.2f ms, max %.2f ms; %.0f tiles/s\n",
              all.size(), all[all.size() / 2], all[all.size() * 9 / 10], all.back(),
              1000 * all.size() / sum);
}
