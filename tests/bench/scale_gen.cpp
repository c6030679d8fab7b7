// Benchmark tool (not a test): writes a SYNTHETIC OPC of a full quadtree of tiny patches quickly,
// for tests/bench/scale_bench.sh and the scale tests (issue 31).
//
//   scale_gen <out-dir> <depth> [patch-size=17] [west=-98.5] [north=33.5] [spacing"=3]
//
// The surface is a WGS 84 geographic grid of 2^depth x (patch-size - 1) + 1 vertices a side from
// (west, north) at `spacing` arc seconds, heights of one analytic function of longitude and
// latitude (so models of different extents and spacings from the same corner describe the same
// surface, and a fine one merges into a coarse one). Coordinates are ECEF, each patch translated
// to the centre of its box as vsm writes them; no textures. Leaves are computed, overviews reduced
// from their children (core/pyramid's rule), depth first, so memory stays a few patches per level
// whatever the depth. Files are written as an import writes its staging directory (OpcWriter,
// Deferred, one syncfs at the end), then the hierarchy and its index (Patches/
// patchhierarchy.vsmidx).
// <depth> 8 with patch size 17 is 87,381 patches (the 4097^2 model), 4 is 341.
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <exception>
#include <filesystem>
#include <memory>
#include <string>
#include <vector>

#include "core/durable/durable_io.hpp"
#include "core/opc/opc_index.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/pyramid/model.hpp"
#include "core/pyramid/reduce.hpp"

namespace {

using namespace vsm::core;

constexpr double kSemiMajor = 6378137.0;
constexpr double kEccentricity2 = 6.69437999014e-3;
constexpr double kDegree = 3.14159265358979323846 / 180.0;

struct Surface {
  int depth = 0;
  int patchSize = 17;
  double west = -98.5;
  double north = 33.5;
  double spacing = 3.0 / 3600.0;  // degrees

  static double height(double lon, double lat) {
    return 300.0 + 40.0 * std::sin(lon * 40.0) * std::cos(lat * 35.0) +
           6.0 * std::sin(lon * 900.0 + lat * 700.0);
  }
  Vec3d ecef(long long column, long long row) const {
    const double lon = west + static_cast<double>(column) * spacing;
    const double lat = north - static_cast<double>(row) * spacing;
    const double h = height(lon, lat);
    const double s = std::sin(lat * kDegree);
    const double c = std::cos(lat * kDegree);
    const double n = kSemiMajor / std::sqrt(1.0 - kEccentricity2 * s * s);
    return {(n + h) * c * std::cos(lon * kDegree), (n + h) * c * std::sin(lon * kDegree),
            (n * (1.0 - kEccentricity2) + h) * s};
  }
};

class Generator {
 public:
  Generator(const Surface& surface, OpcWriter& writer) : surface_(surface), writer_(writer) {}

  /// Writes the subtree of `key` (children first) and returns its grid.
  std::unique_ptr<PatchGrid> build(const PatchKey& key) {
    std::unique_ptr<PatchGrid> grid;
    Box3d childrenBox;
    if (key.depth == surface_.depth) {
      grid = leaf(key);
    } else {
      std::array<std::unique_ptr<PatchGrid>, 4> children;
      std::array<const PatchGrid*, 4> pointers{};
      for (const Quadrant q : kQuadrants) {
        children[static_cast<int>(q)] = build(key.child(q));
        pointers[static_cast<int>(q)] = children[static_cast<int>(q)].get();
        childrenBox.extend(boxes_.back());
        boxes_.pop_back();
      }
      grid = std::make_unique<PatchGrid>(reduce(pointers));
    }
    PatchInfo info;
    info.key = key;
    writer_.writePatch(info, *grid, childrenBox);
    boxes_.push_back(info.globalBox);
    infos_.push_back(std::move(info));
    return grid;
  }

  std::vector<PatchInfo>& infos() { return infos_; }

 private:
  std::unique_ptr<PatchGrid> leaf(const PatchKey& key) const {
    const int n = surface_.patchSize;
    std::vector<Vec3d> points(static_cast<std::size_t>(n) * n);
    Box3d box;
    for (int y = 0; y < n; ++y) {
      for (int x = 0; x < n; ++x) {
        const Vec3d p = surface_.ecef(static_cast<long long>(key.x) * (n - 1) + x,
                                      static_cast<long long>(key.y) * (n - 1) + y);
        points[static_cast<std::size_t>(y) * n + x] = p;
        box.extend(p);
      }
    }
    auto grid = std::make_unique<PatchGrid>(n, originFor(box));
    for (int y = 0; y < n; ++y) {
      for (int x = 0; x < n; ++x) {
        grid->setGlobal(x, y, points[static_cast<std::size_t>(y) * n + x]);
      }
    }
    return grid;
  }

  const Surface& surface_;
  OpcWriter& writer_;
  std::vector<Box3d> boxes_;  // global boxes of the patches just built, a stack
  std::vector<PatchInfo> infos_;
};

}  // namespace

int main(int argc, char** argv) {
  if (argc < 3) {
    std::fprintf(stderr,
                 "usage: scale_gen <out-dir> <depth> [patch-size] [west] [north] [spacing\"]\n");
    return 2;
  }
  try {
    Surface surface;
    const std::filesystem::path out = argv[1];
    surface.depth = std::atoi(argv[2]);
    if (argc > 3)
      surface.patchSize = std::atoi(argv[3]);
    if (argc > 4)
      surface.west = std::atof(argv[4]);
    if (argc > 5)
      surface.north = std::atof(argv[5]);
    if (argc > 6)
      surface.spacing = std::atof(argv[6]) / 3600.0;
    if (surface.depth < 0 || surface.depth > 12) {
      std::fprintf(stderr, "depth must be 0 to 12\n");
      return 2;
    }
    std::filesystem::create_directories(out);
    durable::FileSystemSync sync(out);
    OpcWriter writer(out, OpcWriter::Durability::Deferred);
    Generator generator(surface, writer);
    generator.build(PatchKey::root());
    std::vector<PatchInfo>& infos = generator.infos();
    std::sort(infos.begin(), infos.end(),
              [](const PatchInfo& a, const PatchInfo& b) { return a.key < b.key; });
    Model model(surface.patchSize);
    for (PatchInfo& info : infos) {
      model.insert(std::move(info));
    }
    writer.writeHierarchy(model);
    sync.sync();
    // Its index, as a publish writes one: from the model in memory, which is what the files say
    // (every number is written in its shortest exact form); scale_test compares it with the full
    // read. VSM_GEN_FULL_INDEX=1 writes it from a full read instead (`vsm index`).
    if (std::getenv("VSM_GEN_FULL_INDEX") != nullptr) {
      writeOpcIndex(out);
    } else {
      const std::filesystem::path patches = out / "Patches";
      durable::writeFileAtomically(
          patches / indexFileName("patchhierarchy.xml"),
          encodeOpcIndex(fileStamp(patches / "patchhierarchy.xml"), model, nullptr));
    }
    std::printf("%zu patches\n", model.patchCount());
    return 0;
  } catch (const std::exception& e) {
    std::fprintf(stderr, "scale_gen: %s\n", e.what());
    return 1;
  }
}
