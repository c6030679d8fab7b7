// Benchmark (not a test): the 3D Tiles content of real models as vsmd encodes it, uncompressed
// (float32, `?compress=none`) against compressed (KHR_mesh_quantization + EXT_meshopt_compression,
// the default): bytes per tile, total and geometry only (the GLB without its embedded image
// texture), and the time encodeGlb takes per tile.
//
//   glb_bench <opc-dir>... [--repeat N]
//
// Every patch of every model is read once (positions through the cache, texture tile and
// coordinates as tiles_routes.cpp reads them), then encoded N times each way; the time per tile is
// the median of its N encodings, so disk reads and image conversion are not counted.
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstring>
#include <memory>
#include <optional>
#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/opc/texture_file.hpp"
#include "core/store/live_model.hpp"
#include "core/tiles/glb.hpp"
#include "core/tiles/tile_tree.hpp"

using namespace vsm::core;

namespace {

struct Totals {
  std::size_t tiles = 0;
  std::size_t bytes = 0;
  std::size_t geometryBytes = 0;
  std::vector<double> milliseconds;
  std::vector<double> geometryRatios;  // per tile, compressed / uncompressed geometry
};

double median(std::vector<double> v) {
  if (v.empty()) {
    return 0;
  }
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

double mean(const std::vector<double>& v) {
  double sum = 0;
  for (const double x : v) {
    sum += x;
  }
  return v.empty() ? 0 : sum / static_cast<double>(v.size());
}

/// The median time of `repeat` encodings and the bytes of the last.
std::pair<double, std::vector<std::byte>> timeEncode(const PatchGrid& grid, const Vec3d& centre,
                                                     const GlbOptions& options, int repeat) {
  std::vector<double> times;
  std::vector<std::byte> out;
  for (int i = 0; i < repeat; ++i) {
    const auto start = std::chrono::steady_clock::now();
    out = encodeGlb(grid, centre, options);
    times.push_back(
        std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - start)
            .count());
  }
  return {median(times), std::move(out)};
}

void print(const char* name, const Totals& t) {
  std::printf(
      "  %-12s %6zu tiles  %12zu B total (%8.0f B/tile)  %11zu B geometry (%7.0f B/tile)"
      "  encode median %.3f ms, mean %.3f ms, max %.3f ms per tile\n",
      name, t.tiles, t.bytes, static_cast<double>(t.bytes) / t.tiles, t.geometryBytes,
      static_cast<double>(t.geometryBytes) / t.tiles, median(t.milliseconds), mean(t.milliseconds),
      t.milliseconds.empty() ? 0 : *std::max_element(t.milliseconds.begin(), t.milliseconds.end()));
}

}  // namespace

int main(int argc, char** argv) {
  std::vector<std::string> dirs;
  int repeat = 5;
  for (int i = 1; i < argc; ++i) {
    if (std::strcmp(argv[i], "--repeat") == 0 && i + 1 < argc) {
      repeat = std::max(1, std::atoi(argv[++i]));
    } else {
      dirs.emplace_back(argv[i]);
    }
  }
  if (dirs.empty()) {
    std::fprintf(stderr, "usage: glb_bench <opc-dir>... [--repeat N]\n");
    return 2;
  }
  try {
    for (const std::string& dir : dirs) {
      PatchCache cache(std::size_t{4} << 30);
      const auto live = LiveModel::open(dir, "bench", cache, LiveModel::Access::Read);
      const auto snapshot = live->snapshot();
      Totals plain, packed;
      std::size_t textureBytes = 0, vertices = 0;
      for (const auto& [key, info] : snapshot->model->patches()) {
        const PatchCache::Pin pin = live->positions(*snapshot, key);
        const PatchGrid& grid = *pin.get<PatchGrid>();
        const std::optional<PatchTexture> texture =
            readPatchTexture(live->dir(), *snapshot->model, info, live->texturePixels());
        GlbOptions options;
        std::size_t image = 0;
        if (texture) {
          options.texture = {texture->image, texture->mimeType};
          options.texcoords = texture->texcoords;
          options.baseColor = {1.0, 1.0, 1.0, 1.0};
          image = (texture->image.size() + 3) & ~std::size_t{3};  // padded in the BIN chunk
        }
        textureBytes += image;
        vertices += grid.vertexCount();
        const Vec3d centre = tileCentre(info);
        options.compression = GlbCompression::None;
        const auto [plainMs, plainGlb] = timeEncode(grid, centre, options, repeat);
        options.compression = GlbCompression::Meshopt;
        const auto [packedMs, packedGlb] = timeEncode(grid, centre, options, repeat);
        for (auto [t, ms, size] : {std::tuple{&plain, plainMs, plainGlb.size()},
                                   std::tuple{&packed, packedMs, packedGlb.size()}}) {
          ++t->tiles;
          t->bytes += size;
          t->geometryBytes += size - image;
          t->milliseconds.push_back(ms);
        }
        if (plainGlb.size() > image) {
          packed.geometryRatios.push_back(static_cast<double>(packedGlb.size() - image) /
                                          static_cast<double>(plainGlb.size() - image));
        }
      }
      std::printf(
          "%s: %zu patches, %zu grid vertices, %zu B of embedded textures (JPEG, or PNG with "
          "alpha)\n",
          dir.c_str(), snapshot->model->patches().size(), vertices, textureBytes);
      print("uncompressed", plain);
      print("compressed", packed);
      std::printf(
          "  compressed / uncompressed: geometry %.3f (per tile: median %.3f, max %.3f),"
          " total %.3f; encode time median x%.2f\n",
          static_cast<double>(packed.geometryBytes) / plain.geometryBytes,
          median(packed.geometryRatios),
          packed.geometryRatios.empty()
              ? 0
              : *std::max_element(packed.geometryRatios.begin(), packed.geometryRatios.end()),
          static_cast<double>(packed.bytes) / plain.bytes,
          median(packed.milliseconds) / median(plain.milliseconds));
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "glb_bench: %s\n", e.what());
    return 1;
  }
  return 0;
}
