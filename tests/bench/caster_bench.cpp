// Benchmark (not a test): SurfaceCaster (core/merge/surface_caster.hpp) on one core.
// B is a wavy, tilted surface in grids x grids patches of 257 x 257 sharing their borders
// (4 x 2 patches: 1,048,576 triangles). Measures the construction (vertex copy, seam groups, the
// bins) and the rays per second of rays cast along the surface's normal from points up to one
// spacing off it (search distance two spacings, both directions), one per vertex of a lattice
// twice as fine as B's, in grid order (row by row, as a merge places a new patch) and in random
// order. Each figure is the median of --repeat runs.
//
//   caster_bench [--grids-x N] [--grids-y N] [--repeat N]
#include <unistd.h>
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <ctime>
#include <fstream>
#include <memory>
#include <numeric>
#include <optional>
#include <random>
#include <string>
#include <vector>

#include "core/grid/patch_grid.hpp"
#include "core/merge/surface_caster.hpp"

using namespace vsm::core;

namespace {

constexpr int kSize = 257;
constexpr double kSpacing = 0.5;

// The surface: a plane tilted by 60 degrees about x with waves on it, parameter (u, v) in metres.
Vec3d surface(double u, double v) {
  const double w = 3 * std::sin(u / 17) * std::cos(v / 23) + 0.5 * std::sin((u + 2 * v) / 5);
  const double c = std::cos(1.047), s = std::sin(1.047);
  return {1000 + u, 2000 + v * c - w * s, 300 + v * s + w * c};
}

Vec3d normalAt(double u, double v) {
  const double h = 1e-4;
  const Vec3d du = surface(u + h, v) - surface(u - h, v);
  const Vec3d dv = surface(u, v + h) - surface(u, v - h);
  const Vec3d n{du.y * dv.z - du.z * dv.y, du.z * dv.x - du.x * dv.z, du.x * dv.y - du.y * dv.x};
  return n * (1.0 / n.norm());
}

double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  return v[v.size() / 2];
}

// CPU time of this thread: the machine is shared, so wall time measures the other load too.
double cpuSeconds() {
  timespec t{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);
  return static_cast<double>(t.tv_sec) + static_cast<double>(t.tv_nsec) * 1e-9;
}

double seconds(std::chrono::steady_clock::time_point since) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - since).count();
}

std::size_t residentBytes() {
  std::ifstream statm("/proc/self/statm");
  std::size_t size = 0, resident = 0;
  statm >> size >> resident;
  return resident * static_cast<std::size_t>(sysconf(_SC_PAGESIZE));
}

}  // namespace

int main(int argc, char** argv) {
  int gridsX = 4, gridsY = 2, repeat = 3;
  for (int i = 1; i + 1 < argc; i += 2) {
    if (std::strcmp(argv[i], "--grids-x") == 0) {
      gridsX = std::stoi(argv[i + 1]);
    } else if (std::strcmp(argv[i], "--grids-y") == 0) {
      gridsY = std::stoi(argv[i + 1]);
    } else if (std::strcmp(argv[i], "--repeat") == 0) {
      repeat = std::stoi(argv[i + 1]);
    } else {
      std::fprintf(stderr, "usage: caster_bench [--grids-x N] [--grids-y N] [--repeat N]\n");
      return 2;
    }
  }
  std::vector<std::shared_ptr<const PatchGrid>> grids;
  for (int gy = 0; gy < gridsY; ++gy) {
    for (int gx = 0; gx < gridsX; ++gx) {
      const double u0 = gx * (kSize - 1) * kSpacing, v0 = gy * (kSize - 1) * kSpacing;
      auto grid = std::make_shared<PatchGrid>(
          kSize, Mat4d::translation(surface(u0 + 64 * kSpacing * 2, v0 + 64 * kSpacing * 2)));
      for (int y = 0; y < kSize; ++y) {
        for (int x = 0; x < kSize; ++x) {
          grid->setGlobal(x, y, surface(u0 + x * kSpacing, v0 + y * kSpacing));
        }
      }
      grids.push_back(std::move(grid));
    }
  }

  std::vector<double> build, buildCpu;
  std::size_t triangles = 0, bytesEstimate = 0, rssGrowth = 0;
  std::optional<SurfaceCaster> caster;
  for (int r = 0; r < repeat; ++r) {
    caster.reset();
    const std::size_t before = residentBytes();
    const auto start = std::chrono::steady_clock::now();
    const double cpu = cpuSeconds();
    caster.emplace(grids);
    buildCpu.push_back(cpuSeconds() - cpu);
    build.push_back(seconds(start));
    rssGrowth = residentBytes() - before;
    triangles = caster->triangleCount();
    bytesEstimate = caster->bytes();
  }

  // Rays: one per vertex of a lattice of half B's spacing, in grid order (row by row over B).
  const int perSideU = gridsX * (kSize - 1) * 2, perSideV = gridsY * (kSize - 1) * 2;
  std::vector<CastRay> rays;
  rays.reserve(static_cast<std::size_t>(perSideU) * perSideV);
  std::mt19937 rng(1);
  std::uniform_real_distribution<double> offset(-kSpacing, kSpacing);
  for (int j = 0; j < perSideV; ++j) {
    for (int i = 0; i < perSideU; ++i) {
      const double u = (i + 0.5) * kSpacing / 2, v = (j + 0.5) * kSpacing / 2;
      const Vec3d n = normalAt(u, v);
      rays.push_back({surface(u, v) + n * offset(rng), n, -2 * kSpacing, 2 * kSpacing});
    }
  }
  std::vector<CastRay> shuffled = rays;
  std::shuffle(shuffled.begin(), shuffled.end(), rng);
  std::vector<std::optional<CastHit>> hits(rays.size());

  std::printf("triangles %zu, cells %zu, grids %zu of %d x %d, spacing %.2f m\n", triangles,
              caster->cellCount(), grids.size(), kSize, kSize, kSpacing);
  std::printf(
      "build: median %.3f s CPU (%.3f s wall) of %d; resident growth %.1f MB "
      "(%.0f bytes/triangle), bytes() %.1f MB\n",
      median(buildCpu), median(build), repeat, static_cast<double>(rssGrowth) / 1e6,
      static_cast<double>(rssGrowth) / static_cast<double>(triangles),
      static_cast<double>(bytesEstimate) / 1e6);
  for (const bool random : {false, true}) {
    const std::vector<CastRay>& set = random ? shuffled : rays;
    std::vector<double> rates, cpuRates;
    std::size_t hitCount = 0;
    for (int r = 0; r < repeat; ++r) {
      const auto start = std::chrono::steady_clock::now();
      const double cpu = cpuSeconds();
      caster->cast(set, hits);
      cpuRates.push_back(static_cast<double>(set.size()) / (cpuSeconds() - cpu));
      rates.push_back(static_cast<double>(set.size()) / seconds(start));
      hitCount = static_cast<std::size_t>(
          std::count_if(hits.begin(), hits.end(), [](const auto& h) { return h.has_value(); }));
    }
    std::printf("%-6s order: median %.2f M rays/s CPU (%.2f M/s wall) of %d (%zu rays, %zu hit)\n",
                random ? "random" : "grid", median(cpuRates) / 1e6, median(rates) / 1e6, repeat,
                set.size(), hitCount);
  }
  return 0;
}
