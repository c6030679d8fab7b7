#include <gtest/gtest.h>

#include <unistd.h>
#include <cmath>
#include <cstring>
#include <fstream>
#include <functional>
#include <map>
#include <memory>
#include <numbers>
#include <random>
#include <set>
#include <sstream>
#include <thread>

#include "core/cache/patch_cache.hpp"
#include "core/common/error.hpp"
#include "core/merge/merge.hpp"
#include "core/merge/register.hpp"
#include "core/merge/subdivider.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/validate.hpp"
#include "core/pyramid/model.hpp"
#include "core/pyramid/reduce.hpp"
#include "core/store/live_model.hpp"
#include "core/store/model_edit.hpp"
#include "tests/unit/surface_sampler_reference.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::core {
namespace {

using test::codeOf;
using test::filesUnder;
using test::messageOf;
using test::SurfaceSampler;

// ---- synthetic data ----------------------------------------------------------------------------

/// The analytic test surface: z = f(x, y), smooth, with tens of metres of relief.
double surfaceHeight(double x, double y) {
  return 20 * std::sin(x / 40) + 15 * std::cos(y / 55) + 5 * std::sin((x + y) / 25);
}

/// A bound on f's Hessian spectral norm: the sum of the terms' norms (the last term's Hessian is
/// -5/625 sin(.) [[1, 1], [1, 1]], of norm 2 * 5 / 625).
constexpr double kHessianBound = 20.0 / (40 * 40) + 15.0 / (55 * 55) + 2 * 5.0 / (25 * 25);

/// The interpolation error bound of B's surface, its bilinear cells (derived at SurfaceSampler in
/// tests/unit/surface_sampler_reference.hpp): (1/4) M s^2 for cells of side s, plus float32
/// rounding of stored coordinates (locals of at most ~100 m here).
double samplerBound(double spacing) {
  return 0.25 * kHessianBound * spacing * spacing + 1e-4;
}

/// A regular lattice in the plane: origin + i * spacing * (cos a, sin a) + j * spacing * (-sin a,
/// cos a), lifted onto the analytic surface.
struct Lattice {
  double x0 = 0, y0 = 0, spacing = 1, angle = 0;
  double (*height)(double, double) = surfaceHeight;

  Vec3d at(double i, double j) const {
    const double c = std::cos(angle), s = std::sin(angle);
    const double x = x0 + spacing * (i * c - j * s);
    const double y = y0 + spacing * (i * s + j * c);
    return {x, y, height(x, y)};
  }
  /// Lattice coordinates (i, j) of a plane point.
  std::pair<double, double> coordinates(double x, double y) const {
    const double c = std::cos(angle), s = std::sin(angle);
    const double dx = x - x0, dy = y - y0;
    return {(dx * c + dy * s) / spacing, (-dx * s + dy * c) / spacing};
  }
};

/// The grid of lattice samples [x0, x0 + size) x [y0, y0 + size), origin at its centre.
std::shared_ptr<PatchGrid> latticeGrid(const Lattice& lattice, int size, int x0, int y0) {
  const Vec3d centre = lattice.at(x0 + (size - 1) / 2.0, y0 + (size - 1) / 2.0);
  auto grid = std::make_shared<PatchGrid>(size, Mat4d::translation(centre));
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      grid->setGlobal(x, y, lattice.at(x0 + x, y0 + y));
    }
  }
  return grid;
}

/// A full pyramid of `depth` levels over the lattice: 2^depth x 2^depth leaves, overviews by
/// reduction.
std::unique_ptr<Model> latticeModel(const Lattice& lattice, int size, int depth) {
  auto model = std::make_unique<Model>(size);
  for (int d = 0; d <= depth; ++d) {
    for (std::uint32_t y = 0; y < (1u << d); ++y) {
      for (std::uint32_t x = 0; x < (1u << d); ++x) {
        PatchInfo info;
        info.key = {d, x, y};
        model->insert(info);
      }
    }
  }
  for (std::uint32_t y = 0; y < (1u << depth); ++y) {
    for (std::uint32_t x = 0; x < (1u << depth); ++x) {
      model->setGrid({depth, x, y}, latticeGrid(lattice, size, static_cast<int>(x) * (size - 1),
                                                static_cast<int>(y) * (size - 1)));
    }
  }
  model->refreshStale([](const PatchInfo&) { return std::shared_ptr<const PatchGrid>(); });
  return model;
}

/// MergeTarget / PatchSource over an in-memory Model with all grids attached.
class ModelAccess final : public MergeTarget {
 public:
  explicit ModelAccess(Model& model) : model_(model) {}
  const Model& model() const override { return model_; }
  std::shared_ptr<const PatchGrid> positions(const PatchKey& key) override {
    return model_.grid(key);
  }
  std::shared_ptr<const TextureTile> texture(const PatchKey&) override { return nullptr; }
  void setPositions(const PatchKey& key, std::shared_ptr<const PatchGrid> grid,
                    std::shared_ptr<const TextureTile>) override {
    if (model_.find(key) == nullptr) {
      PatchInfo info;
      info.key = key;
      model_.insert(info);
    }
    model_.setGrid(key, std::move(grid));
  }
  void refreshStale(const CancelToken*) override {
    model_.refreshStale([](const PatchInfo&) { return std::shared_ptr<const PatchGrid>(); });
  }

 private:
  Model& model_;
};

bool sameBits(const Vec3d& a, const Vec3d& b) {
  return std::memcmp(&a, &b, sizeof(Vec3d)) == 0;
}

// ---- SurfaceSampler, the caster tests' reference -----------------------------------------------
//
// surface_caster_test holds SurfaceCaster to SurfaceSampler along up (the point, the grid and
// vertex coordinates it names, B's border); these hold SurfaceSampler to analytic surfaces on the
// kind of B those tests use: a smooth surface within the interpolation bound (which the merge
// tests below rely on too), points in their grids' vertex space, B's border within the tolerance
// (outer border, seams between grids, holes), cells with one corner undefined.

TEST(MergeBatch, HoldsAtMostItsBytesOfFinishedPatchesAndAtLeastTwo) {
  using vsm::core::mergeBatch;
  // A 257 x 257 grid and its tile at 1, 4, 8 and 16 texels per quad.
  const std::size_t grid = std::size_t{257} * 257 * 12;
  const auto patch = [grid](std::size_t side) { return grid + side * side * 4; };
  EXPECT_EQ(mergeBatch(patch(256)), vsm::core::kMergeBatch);
  EXPECT_EQ(mergeBatch(patch(1024)), vsm::core::kMergeBatch);
  EXPECT_EQ(mergeBatch(patch(2048)), 4u);  // 80 MiB / 17.6 MB
  EXPECT_LE(mergeBatch(patch(2048)) * patch(2048), vsm::core::kMergeBatchBytes);
  EXPECT_EQ(mergeBatch(patch(4096)), 2u);
  EXPECT_EQ(mergeBatch(0), vsm::core::kMergeBatch);
}

TEST(SurfaceSampler, ReproducesAnalyticSurfaceOnRotatedGridWithinBound) {
  // B: 3 x 3 patches of 17 x 17 on a lattice rotated by 30 degrees, spacing 4 m / 5.3.
  const Lattice b{1000, 2000, 4.0 / 5.3, std::numbers::pi / 6};
  std::vector<std::shared_ptr<const PatchGrid>> grids;
  for (int y = 0; y < 3; ++y) {
    for (int x = 0; x < 3; ++x) {
      grids.push_back(latticeGrid(b, 17, x * 16, y * 16));
    }
  }
  const SurfaceSampler sampler(grids, {0, 0, 1});
  EXPECT_EQ(sampler.cellCount(), 9u * 16 * 16);

  const double bound = samplerBound(b.spacing);
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> along(0.01, 47.99);
  double maxError = 0;
  for (int n = 0; n < 20000; ++n) {
    const Vec3d onLattice = b.at(along(rng), along(rng));
    // Start far above and below the surface: only the plane position may matter.
    const Vec3d query{onLattice.x, onLattice.y, (n % 2 ? 500.0 : -500.0)};
    const auto s = sampler.sample(query);
    ASSERT_TRUE(s.has_value()) << "no surface at lattice point " << n;
    EXPECT_NEAR(s->x, query.x, 1e-9);
    EXPECT_NEAR(s->y, query.y, 1e-9);
    maxError = std::max(maxError, std::fabs(s->z - surfaceHeight(s->x, s->y)));
  }
  EXPECT_LE(maxError, bound);
  // The bound is not vacuous: linear interpolation of this surface does err visibly.
  EXPECT_GT(maxError, bound / 20);
}

TEST(SurfaceSampler, LocatesPointsInTheirGridsVertexSpace) {
  // 2 x 2 grids of 17 x 17 on a rotated lattice; grid g = 2 y + x starts at lattice (16 x, 16 y).
  // A point at lattice (i, j) lies at vertex (i - 16 x, j - 16 y) of the grid holding it (on a
  // shared border either neighbour is right).
  const Lattice b{0, 0, 0.7, std::numbers::pi / 6};
  std::vector<std::shared_ptr<const PatchGrid>> grids;
  for (int y = 0; y < 2; ++y) {
    for (int x = 0; x < 2; ++x) {
      grids.push_back(latticeGrid(b, 17, x * 16, y * 16));
    }
  }
  const SurfaceSampler sampler(grids, {0, 0, 1});
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> along(0.01, 31.99);
  for (int n = 0; n < 2000; ++n) {
    const double i = along(rng), j = along(rng);
    const Vec3d p = b.at(i, j);
    const auto hit = sampler.locate({p.x, p.y, 100});
    ASSERT_TRUE(hit.has_value()) << i << " " << j;
    ASSERT_LT(hit->grid, 4u);
    const double x0 = 16.0 * (hit->grid % 2), y0 = 16.0 * (hit->grid / 2);
    EXPECT_NEAR(hit->x + x0, i, 1e-6) << i << " " << j;
    EXPECT_NEAR(hit->y + y0, j, 1e-6) << i << " " << j;
    const auto sampled = sampler.sample({p.x, p.y, 100});
    ASSERT_TRUE(sampled.has_value());
    EXPECT_EQ((hit->position - *sampled).norm(), 0.0);
  }
}

TEST(SurfaceSampler, OutsideTheDetailSurfaceThereIsNothing) {
  const Lattice b{0, 0, 1, std::numbers::pi / 6};
  const SurfaceSampler sampler({latticeGrid(b, 17, 0, 0)}, {0, 0, 1});
  EXPECT_TRUE(sampler.sample(b.at(8, 8)).has_value());
  EXPECT_FALSE(sampler.sample(b.at(-0.5, 8)).has_value());
  EXPECT_FALSE(sampler.sample(b.at(8, 16.5)).has_value());
  EXPECT_FALSE(sampler.sample(b.at(100, 100)).has_value());
  const double nan = std::numeric_limits<double>::quiet_NaN();
  EXPECT_FALSE(sampler.sample({nan, nan, nan}).has_value());
}

TEST(SurfaceSampler, PointsWithinTheToleranceOfABorderTakeItsHeight) {
  // B: 2 x 2 grids of 17 x 17 on a rotated lattice (seams at lattice 16), a hole at (8, 24).
  const Lattice b{500, -300, 0.9, 0.3};
  std::vector<std::shared_ptr<const PatchGrid>> grids;
  for (int y = 0; y < 2; ++y) {
    for (int x = 0; x < 2; ++x) {
      auto grid = latticeGrid(b, 17, x * 16, y * 16);
      if (x == 0 && y == 1) {
        grid->setUndefined(8, 8);
      }
      grids.push_back(grid);
    }
  }
  const SurfaceSampler sampler(grids, {0, 0, 1});
  const double tolerance = SurfaceSampler::kBorderTolerance;
  // A border sample (i, j) of B approached from outside along (di, dj) by `offset` lattice units:
  // the height is the sample's own (the lattice generator's), at the query's plane position.
  auto check = [&](int i, int j, int di, int dj, double offset) {
    const Vec3d sample = b.at(i, j);
    const Vec3d query = b.at(i + di * offset, j + dj * offset);
    const auto s = sampler.sample({query.x, query.y, sample.z + (i % 2 ? 80.0 : -80.0)});
    if (offset > tolerance * 1.01) {
      EXPECT_FALSE(s.has_value()) << i << " " << j << " offset " << offset;
      return;
    }
    ASSERT_TRUE(s.has_value()) << i << " " << j << " offset " << offset;
    EXPECT_NEAR(s->x, query.x, 1e-9);
    EXPECT_NEAR(s->y, query.y, 1e-9);
    // float32 rounding of B's locals, and within the tolerance the surface's slope (below 1.2)
    // over the distance to the border point that the query takes.
    EXPECT_NEAR(s->z, sample.z, 1e-4 + 1.2 * std::fabs(offset) * b.spacing)
        << i << " " << j << " offset " << offset;
  };
  for (const double offset : {0.0, 1e-9, -1e-9, 1e-6, 0.02, 0.5}) {
    for (int k = 0; k <= 32; ++k) {
      check(k, 0, 0, -1, offset);  // south border
      check(k, 32, 0, 1, offset);  // north border
      check(0, k, -1, 0, offset);  // west border
      check(32, k, 1, 0, offset);  // east border
      if (offset <= tolerance) {
        check(16, k, 1, 0, offset);  // the seam between the grids, from either side
        check(16, k, -1, 0, offset);
        check(k, 16, 0, 1, offset);
      }
    }
    // The hole's neighbours, approached from the hole.
    check(7, 24, 1, 0, offset);
    check(9, 24, -1, 0, offset);
    check(8, 23, 0, 1, offset);
    check(8, 25, 0, -1, offset);
  }
  // On the seam half a cell to either side is inside B, not on its border.
  EXPECT_TRUE(sampler.sample(b.at(16.5, 7)).has_value());
  EXPECT_TRUE(sampler.sample(b.at(15.5, 7)).has_value());
  // In the hole, half a cell from its neighbours (the centre of the missing diamond's edge
  // region) there is nothing.
  EXPECT_FALSE(sampler.sample(b.at(8, 24)).has_value());
  EXPECT_FALSE(sampler.sample(b.at(8.4, 24)).has_value());
}

TEST(SurfaceSampler, CellWithOneUndefinedCornerKeepsItsOtherTriangle) {
  const Lattice b{0, 0, 1, 0};
  auto grid = latticeGrid(b, 5, 0, 0);
  grid->setUndefined(1, 1);  // the corner (1,1) of cell (0,0) and of three more cells
  const SurfaceSampler sampler({grid}, {0, 0, 1});
  // Cell (0,0) keeps the triangle (0,0), (1,0), (0,1): points near (0,0) are defined...
  EXPECT_TRUE(sampler.sample(b.at(0.2, 0.2)).has_value());
  // ... points near the missing corner are not.
  EXPECT_FALSE(sampler.sample(b.at(0.9, 0.9)).has_value());
  // A cell with two undefined corners contributes nothing.
  grid->setUndefined(3, 3);
  grid->setUndefined(4, 3);
  const SurfaceSampler sparse({grid}, {0, 0, 1});
  EXPECT_FALSE(sparse.sample(b.at(3.5, 3.2)).has_value());
  EXPECT_TRUE(sparse.sample(b.at(2.5, 2.5)).has_value());
}

// ---- Subdivider --------------------------------------------------------------------------------

TEST(Subdivider, NewPatchesShareBitIdenticalBorders) {
  const Lattice a{1000, 2000, 4, 0.1};
  auto grid = latticeGrid(a, 17, 0, 0);
  grid->setUndefined(3, 4);  // re-weighting paths
  grid->setUndefined(16, 16);
  grid->setUndefined(8, 0);
  const int k = 2;
  const Subdivider sub(*grid, k);
  // The positions, and the normals along which the merge casts them onto B.
  std::map<std::pair<int, int>, std::vector<Vec3d>> patches, normals;
  for (std::uint32_t j = 0; j < 4; ++j) {
    for (std::uint32_t i = 0; i < 4; ++i) {
      patches[{i, j}] = sub.positions(k, i, j);
      normals[{i, j}] = sub.normals(k, i, j, patches[{i, j}]);
      // The same, bit for bit, as normal() at each union vertex.
      for (int y = 0; y < 17; ++y) {
        for (int x = 0; x < 17; ++x) {
          ASSERT_TRUE(sameBits(normals[{i, j}][y * 17 + x], sub.normal(16 * i + x, 16 * j + y)))
              << i << "," << j << " " << x << "," << y;
        }
      }
    }
  }
  const int s = 17;
  int compared = 0;
  for (int j = 0; j < 4; ++j) {
    for (int i = 0; i < 4; ++i) {
      const auto& p = patches[{i, j}];
      if (i + 1 < 4) {
        const auto& right = patches[{i + 1, j}];
        const PatchGrid g0 = gridFromGlobal(s, p), g1 = gridFromGlobal(s, right);
        for (int y = 0; y < s; ++y) {
          EXPECT_TRUE(sameBits(p[y * s + s - 1], right[y * s])) << i << "," << j << " y " << y;
          EXPECT_TRUE(sameBits(normals[{i, j}][y * s + s - 1], normals[{i + 1, j}][y * s]));
          ASSERT_EQ(g0.defined(s - 1, y), g1.defined(0, y));
          if (g0.defined(s - 1, y)) {
            EXPECT_LE((g0.global(s - 1, y) - g1.global(0, y)).norm(), 1e-4);
          }
          ++compared;
        }
      }
      if (j + 1 < 4) {
        const auto& below = patches[{i, j + 1}];
        for (int x = 0; x < s; ++x) {
          EXPECT_TRUE(sameBits(p[(s - 1) * s + x], below[x])) << i << "," << j << " x " << x;
          EXPECT_TRUE(sameBits(normals[{i, j}][(s - 1) * s + x], normals[{i, j + 1}][x]));
          ++compared;
        }
      }
    }
  }
  EXPECT_EQ(compared, 2 * 12 * 17);
}

TEST(Subdivider, LatticePositionsReproduceTheCoarsePatchAndReduceBackToIt) {
  const Lattice a{1000, 2000, 4, 0.3};
  auto grid = latticeGrid(a, 17, 0, 0);
  grid->setUndefined(5, 5);
  const Subdivider sub(*grid, 2);
  for (int y = 0; y < 17; ++y) {
    for (int x = 0; x < 17; ++x) {
      const Vec3d p = sub.interpolate(4 * x, 4 * y);
      if (grid->defined(x, y)) {
        EXPECT_TRUE(sameBits(p, grid->global(x, y)));
      } else {
        EXPECT_FALSE(p.finite());
      }
    }
  }
  // Between lattice points: the bilinear mean, re-weighted next to the undefined vertex.
  const Vec3d mid = sub.interpolate(2, 2);
  const Vec3d expect =
      (grid->global(0, 0) + grid->global(1, 0) + grid->global(0, 1) + grid->global(1, 1)) * 0.25;
  EXPECT_LE((mid - expect).norm(), 1e-9);
  const Vec3d nearHole = sub.interpolate(4 * 5 + 2, 4 * 5);  // on the edge (5,5)-(6,5)
  EXPECT_TRUE(sameBits(nearHole, grid->global(6, 5)));

  // Two levels of reduction of the 16 new patches give the coarse patch back (float rounding).
  std::array<std::shared_ptr<PatchGrid>, 4> level1;
  for (const Quadrant q1 : kQuadrants) {
    std::array<std::unique_ptr<PatchGrid>, 4> kids;
    std::array<const PatchGrid*, 4> children{};
    const int q1i = static_cast<int>(q1);
    for (const Quadrant q2 : kQuadrants) {
      const int q2i = static_cast<int>(q2);
      const std::uint32_t i = 2 * (q1i & 1) + (q2i & 1), j = 2 * (q1i >> 1) + (q2i >> 1);
      kids[q2i] = std::make_unique<PatchGrid>(gridFromGlobal(17, sub.positions(2, i, j)));
      children[q2i] = kids[q2i].get();
    }
    level1[q1i] = std::make_shared<PatchGrid>(reduce(children));
  }
  const PatchGrid back =
      reduce({level1[0].get(), level1[1].get(), level1[2].get(), level1[3].get()});
  for (int y = 0; y < 17; ++y) {
    for (int x = 0; x < 17; ++x) {
      ASSERT_EQ(back.defined(x, y), grid->defined(x, y));
      if (grid->defined(x, y)) {
        EXPECT_LE((back.global(x, y) - grid->global(x, y)).norm(), 1e-4);
      }
    }
  }
}

TEST(Subdivider, RejectsBadArguments) {
  PatchGrid grid(17, Mat4d::identity());
  EXPECT_THROW(Subdivider(grid, -1), Error);
  EXPECT_THROW(Subdivider(grid, 17), Error);
  EXPECT_THROW(Subdivider(PatchGrid(6, Mat4d::identity()), 1), Error);
  const Subdivider sub(grid, 1);
  EXPECT_THROW(sub.positions(1, 2, 0), Error);
  EXPECT_THROW(sub.positions(2, 0, 0), Error);
  EXPECT_THROW(Subdivider(grid, 1, Ring{std::vector<Vec3d>(16), {}, {}, {}}), Error);
}

TEST(Subdivider, NeighboursWithRingsCastTheirSharedBorderAlongOneNormal) {
  // Two side by side patches of a curved surface z = f(x, y) (17 x 17, 4 m spacing), each with
  // the other's column next to the shared border as its ring: a vertex on the border has the
  // same normal from both (up to the rounding of the two patches' float32 storage). At a's own
  // vertices (away from the ends of the border, where the ring has no corner) central
  // differences of the interpolation are exact for a quadratic f: the normal is f's, up to that
  // rounding; a one-sided normal (no ring) is off by f's curvature times half a cell.
  auto f = [](double x, double y) { return 0.002 * x * x + 0.001 * x * y - 0.003 * y * y; };
  auto patch = [&](double x0) {
    auto grid = std::make_shared<PatchGrid>(17, Mat4d::translation({x0, 0, 0}));
    for (int y = 0; y < 17; ++y) {
      for (int x = 0; x < 17; ++x) {
        grid->setGlobal(x, y, {x0 + 4.0 * x, 4.0 * y, f(x0 + 4.0 * x, 4.0 * y)});
      }
    }
    return grid;
  };
  const auto left = patch(0), right = patch(64);
  Ring leftRing, rightRing;
  for (int y = 0; y < 17; ++y) {
    leftRing.east.push_back(right->global(1, y));
    rightRing.west.push_back(left->global(15, y));
  }
  const int k = 2;
  const Subdivider l(*left, k, leftRing), r(*right, k, rightRing), lonely(*left, k);
  const std::int64_t last = 16 << k;
  for (std::int64_t v = 1 << k; v < last; v += 1 << k) {
    const Vec3d nl = l.normal(last, v), nr = r.normal(0, v);
    EXPECT_LE((nl - nr).norm(), 1e-5) << v;
    // The analytic normal (-fx, -fy, 1), normalised, at the vertex.
    const Vec3d p = l.interpolate(last, v);
    Vec3d exact{-(0.004 * p.x + 0.001 * p.y), -(0.001 * p.x - 0.006 * p.y), 1};
    exact = exact * (1 / exact.norm());
    EXPECT_LE((nl - exact).norm(), 1e-5) << v;
    EXPECT_GT((lonely.normal(last, v) - exact).norm(), 1e-3) << v;
  }
}

// ---- mergeModels on in-memory models -----------------------------------------------------------

struct SyntheticMerge {
  // A: 4 x 4 leaves of 17 x 17 at 4 m (256 m square); B: 4 x 4 leaves of 17 x 17 on a lattice
  // rotated by 30 degrees with spacing 4 / 5.3 m (about 48 m square), well inside A.
  Lattice aLattice{1000, 2000, 4, 0};
  Lattice bLattice{1100, 2070, 4.0 / 5.3, std::numbers::pi / 6};
  std::unique_ptr<Model> a = latticeModel(aLattice, 17, 2);
  std::unique_ptr<Model> b = latticeModel(bLattice, 17, 2);

  /// True when the plane point lies inside B's lattice with `margin` cells to spare.
  bool insideB(const Vec3d& p, double margin) const {
    const auto [i, j] = bLattice.coordinates(p.x, p.y);
    return i >= margin && j >= margin && i <= 64 - margin && j <= 64 - margin;
  }
};

TEST(Merge, PlacesDetailWithinTheBoundAndKeepsTheModelConsistent) {
  SyntheticMerge data;
  std::map<PatchKey, std::shared_ptr<const PatchGrid>> before;
  for (const auto& [key, info] : data.a->patches()) {
    before[key] = data.a->grid(key);
  }
  ModelAccess target(*data.a), detail(*data.b);
  const MergeResult result = mergeModels(target, detail);

  // Ratio 5.3 -> 3 new levels under every matched leaf.
  EXPECT_GT(result.matchedLeaves, 0u);
  EXPECT_EQ(result.maxLevels, 3);
  for (const auto& [key, k] : result.levels) {
    EXPECT_EQ(k, 3) << key.toString();
    EXPECT_EQ(key.depth, 2);
  }
  EXPECT_GT(result.verticesFromDetail, 1000u);
  EXPECT_EQ(data.a->maxDepth(), 5);

  // Merged bottom vertices inside B lie on the analytic surface within the sampler's bound.
  const double bound = samplerBound(data.bLattice.spacing);
  std::size_t checked = 0;
  for (const auto& [key, info] : data.a->patches()) {
    if (key.depth != 5) {
      continue;
    }
    const PatchGrid& g = *data.a->grid(key);
    for (int y = 0; y < g.size(); ++y) {
      for (int x = 0; x < g.size(); ++x) {
        if (!g.defined(x, y)) {
          continue;
        }
        const Vec3d p = g.global(x, y);
        if (data.insideB(p, 0.01)) {
          EXPECT_NEAR(p.z, surfaceHeight(p.x, p.y), bound) << key.toString();
          ++checked;
        }
      }
    }
  }
  EXPECT_GT(checked, 5000u);

  // Every overview is the exact reduction of its children; no stale patch is left.
  for (const auto& [key, info] : data.a->patches()) {
    EXPECT_FALSE(info.stale) << key.toString();
    if (info.isLeaf()) {
      continue;
    }
    std::array<const PatchGrid*, 4> children{};
    for (const Quadrant q : kQuadrants) {
      if (const PatchInfo* c = data.a->find(key.child(q))) {
        children[static_cast<int>(q)] = data.a->grid(c->key).get();
      }
    }
    EXPECT_TRUE(reduce(children) == *data.a->grid(key)) << key.toString();
  }

  // Neighbouring new bottom patches are watertight (up to float32 rounding of their origins).
  for (const auto& [key, info] : data.a->patches()) {
    if (key.depth != 5) {
      continue;
    }
    const PatchInfo* right = data.a->find({5, key.x + 1, key.y});
    if (right == nullptr) {
      continue;
    }
    for (int y = 0; y < 17; ++y) {
      ASSERT_EQ(data.a->grid(key)->defined(16, y), data.a->grid(right->key)->defined(0, y));
      if (data.a->grid(key)->defined(16, y)) {
        EXPECT_LE(
            (data.a->grid(key)->global(16, y) - data.a->grid(right->key)->global(0, y)).norm(),
            1e-4);
      }
    }
  }

  // Away from B the matched leaves keep their surface: the new levels interpolate it and reduce
  // back to it. Refinement is adaptive: some new patches stay leaves above the bottom level.
  std::size_t kept = 0;
  for (const auto& [leaf, k] : result.levels) {
    const PatchGrid& now = *data.a->grid(leaf);
    const PatchGrid& old = *before.at(leaf);
    for (int y = 0; y < 17; ++y) {
      for (int x = 0; x < 17; ++x) {
        ASSERT_EQ(now.defined(x, y), old.defined(x, y));
        if (old.defined(x, y) && !data.insideB(old.global(x, y), -2)) {
          EXPECT_LE((now.global(x, y) - old.global(x, y)).norm(), 1e-4) << leaf.toString();
          ++kept;
        }
      }
    }
  }
  EXPECT_GT(kept, 100u);
  std::size_t shallowNewLeaves = 0;
  for (const auto& [key, info] : data.a->patches()) {
    shallowNewLeaves += (key.depth == 3 || key.depth == 4) && info.isLeaf() ? 1 : 0;
  }
  EXPECT_GT(shallowNewLeaves, 0u);

  // Patches outside the matched subtrees and their ancestors are untouched.
  std::size_t untouched = 0;
  for (const auto& [key, grid] : before) {
    bool affected = false;
    for (const auto& [leaf, k] : result.levels) {
      affected = affected || key.isAncestorOrSelfOf(leaf);
    }
    if (!affected) {
      EXPECT_EQ(data.a->grid(key), grid) << key.toString();
      ++untouched;
    } else {
      EXPECT_NE(data.a->grid(key), grid) << key.toString();
    }
  }
  EXPECT_GT(untouched, 0u);
}

TEST(Merge, NewPatchesComputedInParallelGiveTheModelOneThreadGives) {
  SyntheticMerge serial, parallel;
  ModelAccess serialTarget(*serial.a), serialDetail(*serial.b);
  const MergeResult one = mergeModels(serialTarget, serialDetail);
  test::ThreadPerTask executor;
  MergeOptions options;
  options.executor = &executor;
  ModelAccess parallelTarget(*parallel.a), parallelDetail(*parallel.b);
  const MergeResult many = mergeModels(parallelTarget, parallelDetail, options);
  EXPECT_GT(executor.batches, 0);
  EXPECT_EQ(many.newPatches, one.newPatches);
  EXPECT_EQ(many.verticesFromDetail, one.verticesFromDetail);
  ASSERT_EQ(parallel.a->patchCount(), serial.a->patchCount());
  for (const auto& [key, info] : serial.a->patches()) {
    const PatchInfo* other = parallel.a->find(key);
    ASSERT_NE(other, nullptr) << key.toString();
    EXPECT_TRUE(*parallel.a->grid(other->key) == *serial.a->grid(key)) << key.toString();
  }
}

// A scan merged again lands where the first merge already reached its resolution: its leaves are
// placed on it in place, the tree does not deepen, and the surface stays where the first merge
// put it (before, each merge added a level under every such leaf: 486, 806, then 1886 patches for
// the same Jacksboro scan merged into PRISM three times).
TEST(Merge, MergingTheSameDetailAgainResamplesInPlace) {
  SyntheticMerge data;
  ModelAccess target(*data.a), detail(*data.b);
  const MergeResult first = mergeModels(target, detail);
  ASSERT_EQ(first.maxLevels, 3);
  ASSERT_EQ(first.resampledLeaves, 0u);
  std::map<PatchKey, std::shared_ptr<const PatchGrid>> once;
  for (const auto& [key, info] : data.a->patches()) {
    once[key] = data.a->grid(key);
  }

  const MergeResult second = mergeModels(target, detail);
  EXPECT_EQ(second.maxLevels, 0);
  EXPECT_EQ(second.newPatches, 0u);
  EXPECT_GT(second.resampledLeaves, 0u);
  EXPECT_EQ(second.resampledLeaves, second.matchedLeaves);
  for (const auto& [key, k] : second.levels) {
    EXPECT_EQ(k, 0) << key.toString();
    EXPECT_EQ(key.depth, 5) << key.toString();
  }
  EXPECT_EQ(data.a->maxDepth(), 5);
  ASSERT_EQ(data.a->patches().size(), once.size());

  const double bound = samplerBound(data.bLattice.spacing);
  std::size_t onB = 0;
  for (const auto& [key, info] : data.a->patches()) {
    ASSERT_TRUE(once.count(key)) << key.toString();
    EXPECT_FALSE(info.stale) << key.toString();
    const PatchGrid& now = *data.a->grid(key);
    const PatchGrid& then = *once.at(key);
    for (int y = 0; y < now.size(); ++y) {
      for (int x = 0; x < now.size(); ++x) {
        ASSERT_EQ(now.defined(x, y), then.defined(x, y)) << key.toString();
        if (!now.defined(x, y)) {
          continue;
        }
        // The second placement moves a vertex only along the first merge's normal there, by at
        // most its distance from B: B's interpolation error (the first merge's vertices near B's
        // border that were not on B) plus float32 rounding.
        const Vec3d p = now.global(x, y), q = then.global(x, y);
        EXPECT_LE((p - q).norm(), 2 * bound + 1e-4) << key.toString();
        if (key.depth == 5 && data.insideB(p, 0.01)) {
          EXPECT_NEAR(p.z, surfaceHeight(p.x, p.y), bound) << key.toString();
          ++onB;
        }
      }
    }
  }
  EXPECT_GT(onB, 5000u);
}

TEST(Merge, DetailOutsideTheTargetIsAnErrorAndChangesNothing) {
  SyntheticMerge data;
  data.b = latticeModel({5000, 9000, 1, 0.2}, 17, 1);
  std::map<PatchKey, std::pair<std::shared_ptr<const PatchGrid>, bool>> before;
  for (const auto& [key, info] : data.a->patches()) {
    before[key] = {data.a->grid(key), info.stale};
  }
  ModelAccess target(*data.a), detail(*data.b);
  try {
    mergeModels(target, detail);
    FAIL() << "merge of a model outside the target succeeded";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::InvalidArgument);
    EXPECT_NE(std::string(e.what()).find("outside the target"), std::string::npos);
  }
  ASSERT_EQ(data.a->patchCount(), before.size());
  for (const auto& [key, info] : data.a->patches()) {
    EXPECT_EQ(data.a->grid(key), before[key].first) << key.toString();
    EXPECT_EQ(info.stale, before[key].second) << key.toString();
  }
}

TEST(Merge, DetailOnlyPartlyInsideTheTargetIsAnError) {
  SyntheticMerge data;
  data.b = latticeModel({1230, 2100, 1, 0}, 17, 1);  // 32 m square across A's east border
  ModelAccess target(*data.a), detail(*data.b);
  EXPECT_THROW(mergeModels(target, detail), Error);
}

TEST(Merge, HonoursCancellationAndReportsStages) {
  SyntheticMerge data;
  struct Recorder : Progress {
    std::vector<std::string> stages;
    void report(std::string_view stage, double) override {
      if (stages.empty() || stages.back() != stage) {
        stages.emplace_back(stage);
      }
    }
  } progress;
  ModelAccess target(*data.a), detail(*data.b);
  CancelToken cancel;
  cancel.cancel();
  MergeOptions options;
  options.cancel = &cancel;
  try {
    mergeModels(target, detail, options);
    FAIL() << "cancelled merge succeeded";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::Cancelled);
  }
  SyntheticMerge fresh;
  ModelAccess target2(*fresh.a), detail2(*fresh.b);
  options.cancel = nullptr;
  options.progress = &progress;
  mergeModels(target2, detail2, options);
  EXPECT_EQ(progress.stages, (std::vector<std::string>{"matching", "placing", "reducing"}));
}

TEST(Merge, AppliesTheTransformToEveryDetailVertex) {
  // B displaced by 7 m in x and 3 m up; the inverse transform puts it back on the surface.
  SyntheticMerge data;
  auto displaced = std::make_unique<Model>(17);
  {
    auto source = latticeModel(data.bLattice, 17, 2);
    for (const auto& [key, info] : source->patches()) {
      PatchInfo copy;
      copy.key = key;
      displaced->insert(copy);
    }
    for (const auto& [key, info] : source->patches()) {
      if (!info.isLeaf()) {
        continue;
      }
      auto g = std::make_shared<PatchGrid>(17, source->grid(key)->local2global());
      for (int y = 0; y < 17; ++y) {
        for (int x = 0; x < 17; ++x) {
          g->setGlobal(x, y, source->grid(key)->global(x, y) + Vec3d{7, 0, 3});
        }
      }
      displaced->setGrid(key, g);
    }
    displaced->refreshStale([](const PatchInfo&) { return std::shared_ptr<const PatchGrid>(); });
  }
  ModelAccess target(*data.a), detail(*displaced);
  MergeOptions options;
  options.transform = Mat4d::translation({-7, 0, -3});
  mergeModels(target, detail, options);
  const double bound = samplerBound(data.bLattice.spacing);
  std::size_t checked = 0;
  for (const auto& [key, info] : data.a->patches()) {
    if (key.depth != 5) {
      continue;
    }
    for (int y = 0; y < 17; ++y) {
      for (int x = 0; x < 17; ++x) {
        const Vec3d p = data.a->grid(key)->global(x, y);
        if (data.a->grid(key)->defined(x, y) && data.insideB(p, 0.01)) {
          EXPECT_NEAR(p.z, surfaceHeight(p.x, p.y), bound);
          ++checked;
        }
      }
    }
  }
  EXPECT_GT(checked, 5000u);
}

// ---- registration ------------------------------------------------------------------------------

/// Relief with features at 30-60 m, so a ~100 m detail model cannot slide along it.
double ridgedHeight(double x, double y) {
  return 6 * std::sin(x / 9) + 5 * std::cos(y / 7) + 3 * std::sin((x - 0.6 * y) / 5);
}

/// Rotation by `degrees` about `axis` through `centre`, then a translation by `offset`.
Mat4d rigid(double degrees, Vec3d axis, const Vec3d& centre, const Vec3d& offset) {
  axis = axis * (1.0 / axis.norm());
  const double a = degrees * std::numbers::pi / 180, c = std::cos(a), s = std::sin(a), t = 1 - c;
  const double x = axis.x, y = axis.y, z = axis.z;
  const double r[9] = {t * x * x + c,     t * x * y - s * z, t * x * z + s * y,
                       t * x * y + s * z, t * y * y + c,     t * y * z - s * x,
                       t * x * z - s * y, t * y * z + s * x, t * z * z + c};
  Mat4d m;
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) {
      m.m[i * 4 + j] = r[i * 3 + j];
    }
    const double rc = r[i * 3] * centre.x + r[i * 3 + 1] * centre.y + r[i * 3 + 2] * centre.z;
    m.m[i * 4 + 3] = (i == 0   ? centre.x
                      : i == 1 ? centre.y
                               : centre.z) -
                     rc +
                     (i == 0   ? offset.x
                      : i == 1 ? offset.y
                               : offset.z);
  }
  return m;
}

/// `model`'s tree with every leaf grid replaced by `leaf(grid)`, overviews reduced again.
std::unique_ptr<Model> withLeaves(
    const Model& model, const std::function<std::shared_ptr<PatchGrid>(const PatchGrid&)>& leaf) {
  auto out = std::make_unique<Model>(model.gridSize());
  for (const auto& [key, info] : model.patches()) {
    PatchInfo copy;
    copy.key = key;
    out->insert(copy);
  }
  for (const auto& [key, info] : model.patches()) {
    if (info.isLeaf()) {
      out->setGrid(key, leaf(*model.grid(key)));
    }
  }
  out->refreshStale([](const PatchInfo&) { return std::shared_ptr<const PatchGrid>(); });
  return out;
}

/// `model` with every leaf vertex moved by `transform`, overviews reduced again.
std::unique_ptr<Model> transformedModel(const Model& model, const Mat4d& transform) {
  return withLeaves(model, [&transform](const PatchGrid& g) {
    auto moved = std::make_shared<PatchGrid>(
        g.size(), Mat4d::translation(transform.apply(g.globalBox().center())));
    for (int y = 0; y < g.size(); ++y) {
      for (int x = 0; x < g.size(); ++x) {
        if (g.defined(x, y)) {
          moved->setGlobal(x, y, transform.apply(g.global(x, y)));
        }
      }
    }
    return moved;
  });
}

/// The worst distance over the vertices of `model`'s leaves between a vertex and where `recovered`
/// puts it back after `displacement` moved it.
double worstRecoveryError(const Model& model, const Mat4d& displacement, const Mat4d& recovered) {
  double worst = 0;
  for (const auto& [key, info] : model.patches()) {
    if (!info.isLeaf()) {
      continue;
    }
    const int size = model.grid(key)->size();
    for (int y = 0; y < size; ++y) {
      for (int x = 0; x < size; ++x) {
        const Vec3d truth = model.grid(key)->global(x, y);
        worst = std::max(worst, (recovered.apply(displacement.apply(truth)) - truth).norm());
      }
    }
  }
  return worst;
}

TEST(Registration, RecoversHalfADegreeAndSeveralCellsWithinAQuarterOfTheDetailSpacing) {
  const Lattice aLattice{1000, 2000, 4, 0, ridgedHeight};
  const Lattice bLattice{1150, 2150, 4.0 / 5.3, std::numbers::pi / 6, ridgedHeight};
  auto a = latticeModel(aLattice, 17, 3);  // 512 m at 4 m
  auto b = latticeModel(bLattice, 33, 2);  // ~97 m at 0.75 m, rotated by 30 degrees
  const Vec3d centre = b->at(PatchKey::root()).globalBox.center();
  // 0.5 degrees about a tilted axis, and 3 x -2 of A's cells plus 1.5 m up.
  const Mat4d displacement = rigid(0.5, {0.3, 0.2, 1}, centre, {12, -8, 1.5});
  auto displaced = transformedModel(*b, displacement);

  ModelAccess target(*a), detail(*displaced);
  const RegistrationResult r = registerModels(target, detail);
  EXPECT_TRUE(r.converged);
  EXPECT_GE(r.stages, 2);
  EXPECT_LT(r.rms, 0.1);  // vertical residual after alignment, metres
  EXPECT_LE(worstRecoveryError(*b, displacement, r.transform), bLattice.spacing / 4)
      << "fitness " << r.fitness;
  // Without registration the error is the displacement itself.
  EXPECT_GT((displacement.apply(centre) - centre).norm(), 10.0);

  // And the merge with that transform puts B's surface where it belongs.
  MergeOptions options;
  options.transform = r.transform;
  const MergeResult merged = mergeModels(target, detail, options);
  EXPECT_GT(merged.verticesFromDetail, 1000u);
}

/// `model` with holes in every leaf: a block of undefined vertices a sixth of its width inside, one
/// an eighth of its width at a border, and every 41st vertex (so normals meet one-sided differences
/// and missing neighbours); overviews reduced again.
std::unique_ptr<Model> withHoles(const Model& model) {
  return withLeaves(model, [](const PatchGrid& g) {
    auto grid = std::make_shared<PatchGrid>(g);
    const int s = grid->size();
    for (int y = 0; y < s; ++y) {
      for (int x = 0; x < s; ++x) {
        const bool inner = x >= s / 3 && x < s / 3 + s / 6 && y >= s / 2 && y < s / 2 + s / 6;
        const bool border = x >= s - s / 8 && y >= s / 4 && y < s / 4 + s / 8;
        if (inner || border || (y * s + x) % 41 == 0) {
          grid->setUndefined(x, y);
        }
      }
    }
    return grid;
  });
}

TEST(Registration, RecoversTheDisplacementAcrossHolesFromThinnedPoints) {
  const Lattice aLattice{1000, 2000, 4, 0, ridgedHeight};
  const Lattice bLattice{1150, 2150, 4.0 / 5.3, std::numbers::pi / 6, ridgedHeight};
  auto a = withHoles(*latticeModel(aLattice, 17, 3));
  auto b = latticeModel(bLattice, 33, 2);
  const Vec3d centre = b->at(PatchKey::root()).globalBox.center();
  const Mat4d displacement = rigid(0.5, {0.3, 0.2, 1}, centre, {12, -8, 1.5});
  auto displaced = withHoles(*transformedModel(*b, displacement));

  ModelAccess target(*a), detail(*displaced);
  RegistrationOptions options;
  // A has ~300 vertices over B (with the margin), B's fine level ~4000: both are thinned.
  options.maxPoints = 200;
  const RegistrationResult r = registerModels(target, detail, options);
  EXPECT_TRUE(r.converged);
  EXPECT_LT(r.rms, 0.1);
  EXPECT_LE(worstRecoveryError(*b, displacement, r.transform), bLattice.spacing / 4)
      << "fitness " << r.fitness;
}

TEST(Registration, FailsClearlyWithoutOverlap) {
  auto a = latticeModel({1000, 2000, 4, 0, ridgedHeight}, 17, 2);
  auto b = latticeModel({9000, 9000, 1, 0, ridgedHeight}, 17, 1);
  ModelAccess target(*a), detail(*b);
  EXPECT_THROW(registerModels(target, detail), Error);
}

// ---- end to end over OPC directories
// -------------------------------------------------------------

namespace fs = std::filesystem;

void writeOpc(Model& model, const fs::path& dir) {
  OpcWriter writer(dir, OpcWriter::Durability::Deferred);
  for (const auto& [key, info] : model.patches()) {
    PatchInfo& mutableInfo = model.edit(key);
    writer.writePatch(mutableInfo, *model.grid(key), model.childrenBox(key));
  }
  writer.writeHierarchy(model);
}

class MergeStoreTest : public test::TempDirTest {
 protected:
  MergeStoreTest() : TempDirTest("merge") {}
  void SetUp() override {
    SyntheticMerge data;
    writeOpc(*data.a, dir_ / "a");
    writeOpc(*data.b, dir_ / "b");
    aLattice_ = data.aLattice;
    bLattice_ = data.bLattice;
  }
  Lattice aLattice_, bLattice_;
};

TEST_F(MergeStoreTest, MergedModelValidatesFollowsTheDetailAndLeavesOtherFilesAlone) {
  const auto before = filesUnder(dir_ / "a");
  const Model oldModel = readOpcModel(dir_ / "a");
  PatchCache cache(64 << 20);
  auto a = LiveModel::open(dir_ / "a", "a", cache);
  auto b = LiveModel::open(dir_ / "b", "b", cache);
  MergeResult result;
  {
    auto edit = a->beginEdit();
    result = mergeModels(*edit, *b);
    edit->publish();
  }
  EXPECT_EQ(result.maxLevels, 3);
  const auto findings = validateOpc(dir_ / "a");
  for (const Finding& f : findings) {
    ADD_FAILURE() << f.where << ": " << f.message;
  }

  // Reopened from disk: bottom vertices over B follow B's surface within the bound.
  const auto snapshot = a->snapshot();
  const Model& merged = *snapshot->model;
  EXPECT_EQ(merged.maxDepth(), 5);
  const double bound = samplerBound(bLattice_.spacing);
  std::size_t checked = 0;
  SyntheticMerge geometry;
  for (const auto& [key, info] : merged.patches()) {
    const auto grid = a->positions(*snapshot, key).get<PatchGrid>();
    if (key.depth == 5) {
      for (int y = 0; y < 17; ++y) {
        for (int x = 0; x < 17; ++x) {
          const Vec3d p = grid->global(x, y);
          if (grid->defined(x, y) && geometry.insideB(p, 0.01)) {
            EXPECT_NEAR(p.z, surfaceHeight(p.x, p.y), bound) << key.toString();
            ++checked;
          }
        }
      }
    }
    // Every overview is the reduction of its children as stored.
    if (!info.isLeaf()) {
      std::array<std::shared_ptr<const PatchGrid>, 4> held;
      std::array<const PatchGrid*, 4> children{};
      for (const Quadrant q : kQuadrants) {
        if (merged.find(key.child(q)) != nullptr) {
          held[static_cast<int>(q)] = a->positions(*snapshot, key.child(q)).get<PatchGrid>();
          children[static_cast<int>(q)] = held[static_cast<int>(q)].get();
        }
      }
      const PatchGrid reduced = reduce(children);
      for (int y = 0; y < 17; ++y) {
        for (int x = 0; x < 17; ++x) {
          ASSERT_EQ(reduced.defined(x, y), grid->defined(x, y)) << key.toString();
          if (grid->defined(x, y)) {
            EXPECT_LE((reduced.global(x, y) - grid->global(x, y)).norm(), 1e-6) << key.toString();
          }
        }
      }
    }
  }
  EXPECT_GT(checked, 5000u);

  // Patches outside the matched subtrees and their ancestors: same folder, byte-identical files.
  const auto after = filesUnder(dir_ / "a");
  std::size_t untouched = 0;
  for (const auto& [key, info] : oldModel.patches()) {
    bool affected = false;
    for (const auto& [leaf, k] : result.levels) {
      affected = affected || key.isAncestorOrSelfOf(leaf);
    }
    if (affected) {
      continue;
    }
    EXPECT_EQ(merged.at(key).folder(), info.folder());
    for (const auto& [path, bytes] : before) {
      if (path.rfind("Patches/" + info.folder() + "/", 0) == 0) {
        ASSERT_TRUE(after.count(path)) << path;
        EXPECT_EQ(after.at(path), bytes) << path;
        ++untouched;
      }
    }
  }
  EXPECT_GT(untouched, 0u);
}

TEST_F(MergeStoreTest, DetailOutsideTheTargetLeavesTheTargetUntouched) {
  fs::remove_all(dir_ / "b");
  auto far = latticeModel({5000, 9000, 1, 0.2}, 17, 1);
  writeOpc(*far, dir_ / "b");
  const auto before = filesUnder(dir_ / "a");
  PatchCache cache(64 << 20);
  auto a = LiveModel::open(dir_ / "a", "a", cache);
  auto b = LiveModel::open(dir_ / "b", "b", cache);
  const std::uint64_t version = a->snapshot()->version;
  {
    auto edit = a->beginEdit();
    try {
      mergeModels(*edit, *b);
      ADD_FAILURE() << "merge of a model outside the target succeeded";
    } catch (const Error& e) {
      EXPECT_EQ(e.code(), ErrorCode::InvalidArgument);
      EXPECT_NE(std::string(e.what()).find("outside the target"), std::string::npos);
    }
  }  // the edit is discarded
  EXPECT_EQ(a->snapshot()->version, version);
  EXPECT_EQ(filesUnder(dir_ / "a"), before);
}

TEST_F(MergeStoreTest, WorksUnderATightMemoryBudget) {
  // A detail model at twice A's resolution (one new level, few files to write), and room for 8
  // patches of 17 x 17: the merge must stream (dirty patches get written back early).
  fs::remove_all(dir_ / "b");
  auto coarser = latticeModel({1100, 2070, 4.0 / 1.8, std::numbers::pi / 6}, 17, 1);
  writeOpc(*coarser, dir_ / "b");
  PatchCache cache(8 * 17 * 17 * 12);
  auto a = LiveModel::open(dir_ / "a", "a", cache);
  auto b = LiveModel::open(dir_ / "b", "b", cache);
  {
    auto edit = a->beginEdit();
    const MergeResult result = mergeModels(*edit, *b);
    EXPECT_EQ(result.maxLevels, 1);
    EXPECT_GT(result.newPatches, 8u);
    EXPECT_GT(cache.stats().writeBacks, 0u);
    edit->publish();
  }
  for (const Finding& f : validateOpc(dir_ / "a")) {
    ADD_FAILURE() << f.where << ": " << f.message;
  }
  EXPECT_LE(cache.stats().residentBytes, cache.budgetBytes());
}

}  // namespace
}  // namespace vsm::core
