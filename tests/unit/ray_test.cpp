#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <map>
#include <memory>
#include <numbers>
#include <optional>
#include <random>
#include <set>
#include <string>
#include <tuple>
#include <vector>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/grid/vec_ops.hpp"
#include "core/pyramid/model.hpp"
#include "core/pyramid/reduce.hpp"
#include "core/ray/ray_query.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::core {
namespace {

using test::errorOf;
using vec::cross;
using vec::dot;
using vec::unit;

constexpr double kPi = std::numbers::pi;

/// A model whose leaves are `leaves` (their ancestors are overviews reduced from them), every
/// leaf a size x size grid sampling `surface` (u, v): leaf (depth, kx, ky) spans u in [kx, kx + 1]
/// and v in [ky, ky + 1] times side / 2^depth, vertex (i, j) at the lattice point i, j. Counts
/// what its loader reads.
struct Scene {
  explicit Scene(int size) : model(size) {}

  Model model;
  std::map<PatchKey, std::shared_ptr<const PatchGrid>> grids;
  std::vector<PatchKey> reads;

  Model::GridLoader loader() {
    return [this](const PatchInfo& info) {
      reads.push_back(info.key);
      return grids.at(info.key);
    };
  }
  std::vector<std::optional<RayHit>> cast(const std::vector<Ray>& rays,
                                          const RayLimits& limits = {},
                                          const RayWorkCharge& charge = {}) {
    return castRays(model, rays, loader(), limits, charge);
  }
  std::optional<RayHit> hit(const Ray& ray) { return cast(std::vector<Ray>{ray}).front(); }
};

std::unique_ptr<Scene> makeScene(int size, double side,
                                 const std::function<Vec3d(double, double)>& surface,
                                 const std::vector<PatchKey>& leaves) {
  auto scene = std::make_unique<Scene>(size);
  std::set<PatchKey> keys;
  for (const PatchKey& leaf : leaves) {
    for (std::optional<PatchKey> k = leaf; k; k = k->parent()) {
      keys.insert(*k);
    }
  }
  for (const PatchKey& key : keys) {  // parents first
    PatchInfo info;
    info.key = key;
    scene->model.insert(info);
  }
  for (auto it = keys.rbegin(); it != keys.rend(); ++it) {  // children first
    const PatchKey& key = *it;
    if (std::find(leaves.begin(), leaves.end(), key) != leaves.end()) {
      const double span = side / (1u << key.depth), step = span / (size - 1);
      Box3d box;
      std::vector<Vec3d> points;
      for (int j = 0; j < size; ++j) {
        for (int i = 0; i < size; ++i) {
          points.push_back(surface(key.x * span + i * step, key.y * span + j * step));
          box.extend(points.back());
        }
      }
      auto grid = std::make_shared<PatchGrid>(size, Mat4d::translation(box.min));
      for (int j = 0; j < size; ++j) {
        for (int i = 0; i < size; ++i) {
          grid->setGlobal(i, j, points[static_cast<std::size_t>(j) * size + i]);
        }
      }
      scene->grids[key] = grid;
    } else {
      std::array<const PatchGrid*, 4> children{};
      for (const Quadrant q : kQuadrants) {
        const auto child = scene->grids.find(key.child(q));
        children[static_cast<int>(q)] = child == scene->grids.end() ? nullptr : child->second.get();
      }
      scene->grids[key] = std::make_shared<PatchGrid>(reduce(children));
    }
    scene->model.describe(key, *scene->grids[key]);
  }
  return scene;
}

std::vector<PatchKey> childrenOf(const PatchKey& key) {
  std::vector<PatchKey> out;
  for (const Quadrant q : kQuadrants) {
    out.push_back(key.child(q));
  }
  return out;
}

// ---- a vertical wall
// ------------------------------------------------------------------------------

/// A vertical wall, 8 x 8 m: the plane y = 5 + x / 4 (turned about z), x in [0, 8], z in [0, 8]
/// (grid rows run down from z = 8). Dyadic lattice points, so float32 keeps them exact.
Vec3d wallPoint(double u, double v) {
  return {u, 5 + u / 4, 8 - v};
}
const Vec3d kWallNormal = unit({-0.25, 1, 0});  // facing +y (away from the rays' side)

/// The wall at depth 1 (4 m leaves of 9 x 9, 0.5 m spacing), its north-west quarter at depth 2
/// (2 m leaves, 0.25 m spacing: a finer scan merged there).
std::unique_ptr<Scene> wallScene() {
  std::vector<PatchKey> leaves = childrenOf(PatchKey{1, 0, 0});
  for (const PatchKey& k : {PatchKey{1, 1, 0}, PatchKey{1, 0, 1}, PatchKey{1, 1, 1}}) {
    leaves.push_back(k);
  }
  return makeScene(9, 8, wallPoint, leaves);
}

TEST(RayQuery, HorizontalRaysHitTheWallWhereThePlaneIs) {
  const auto scene = wallScene();
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> along(0.01, 7.99);
  std::vector<Ray> rays;
  for (int n = 0; n < 300; ++n) {
    rays.push_back({{along(rng), -3, along(rng)}, {0, 2, 0}});  // any length of direction
  }
  // On a seam between leaves, and on the seam between depths (x = 4 or z = 4).
  rays.push_back({{4, -3, 6}, {0, 1, 0}});
  rays.push_back({{2, -3, 4}, {0, 1, 0}});
  rays.push_back({{4, -3, 4}, {0, 1, 0}});
  const auto hits = scene->cast(rays);
  ASSERT_EQ(hits.size(), rays.size());
  for (std::size_t n = 0; n < rays.size(); ++n) {
    const Ray& ray = rays[n];
    ASSERT_TRUE(hits[n].has_value()) << n;
    const RayHit& hit = *hits[n];
    const double x = ray.origin.x, z = ray.origin.z;
    const Vec3d expected{x, 5 + x / 4, z};
    EXPECT_LE((hit.point - expected).norm(), 1e-6) << n;
    EXPECT_NEAR(hit.distance, expected.y - ray.origin.y, 1e-6) << n;
    // Facing the ray (which comes from -y).
    EXPECT_LE((hit.normal - kWallNormal * -1.0).norm(), 1e-9) << n;
    // The leaf holding (x, z): depth 2 in the north-west quarter (x < 4, z > 4), else depth 1.
    const bool fine = x < 4 && z > 4;
    const double span = fine ? 2 : 4;
    if (std::fabs(x / span - std::round(x / span)) > 1e-9 &&
        std::fabs((8 - z) / span - std::round((8 - z) / span)) > 1e-9) {
      EXPECT_EQ(hit.leaf, (PatchKey{fine ? 2 : 1, static_cast<std::uint32_t>(x / span),
                                    static_cast<std::uint32_t>((8 - z) / span)}))
          << n;
    }
    EXPECT_EQ(hit.resolution, scene->model.at(hit.leaf).resolution);
    EXPECT_TRUE(scene->model.at(hit.leaf).isLeaf());
  }
}

TEST(RayQuery, ObliqueRaysHitTheWallOnTheirLine) {
  const auto scene = wallScene();
  std::mt19937 rng(11);
  std::uniform_real_distribution<double> along(1, 7), tilt(-0.6, 0.6);
  for (int n = 0; n < 200; ++n) {
    const Vec3d target = wallPoint(along(rng), along(rng));
    const Vec3d d = unit({tilt(rng), 1, tilt(rng)});
    const Vec3d origin = target - d * 2.5;
    const auto hit = scene->hit({origin, d});
    ASSERT_TRUE(hit.has_value()) << n;
    // The analytic line-plane intersection: target itself.
    EXPECT_LE((hit->point - target).norm(), 1e-6) << n;
    EXPECT_NEAR(hit->distance, 2.5, 1e-6) << n;
    EXPECT_LT(dot(hit->normal, d), 0) << n;
  }
}

TEST(RayQuery, FromBehindTheWallTheNormalTurnsAndGoingAwayMisses) {
  const auto scene = wallScene();
  // Behind (y greater than the plane), towards it: the hit, the normal facing the ray.
  const auto back = scene->hit({{6, 12, 2}, {0, -1, 0}});
  ASSERT_TRUE(back.has_value());
  EXPECT_NEAR(back->point.y, 6.5, 1e-9);
  EXPECT_NEAR(back->distance, 5.5, 1e-9);
  EXPECT_LE((back->normal - kWallNormal).norm(), 1e-9);
  // Behind and going away; in front and going away; just off the surface going away.
  EXPECT_FALSE(scene->hit({{6, 12, 2}, {0, 1, 0}}).has_value());
  EXPECT_FALSE(scene->hit({{6, -3, 2}, {0, -1, 0}}).has_value());
  EXPECT_FALSE(scene->hit({{6, 6.5 + 1e-3, 2}, {0, 1, 0}}).has_value());
  EXPECT_FALSE(scene->hit({{6, 6.5 - 1e-3, 2}, {0, -1, 0}}).has_value());
  // Beside the wall, above it, and parallel to it.
  EXPECT_FALSE(scene->hit({{9, -3, 2}, {0, 1, 0}}).has_value());
  EXPECT_FALSE(scene->hit({{2, -3, 8.5}, {0, 1, 0}}).has_value());
  EXPECT_FALSE(scene->hit({{0, 4, 2}, {1, 0.25, 0}}).has_value());
}

TEST(RayQuery, MaxDistanceCutsAHitOff) {
  const auto scene = wallScene();
  // The wall is 6.5 m along +y from (6, 0, 2).
  const Vec3d origin{6, 0, 2};
  EXPECT_FALSE(scene->hit({origin, {0, 1, 0}, 6.4}).has_value());
  const auto at = scene->hit({origin, {0, 1, 0}, 6.5 + 1e-9});
  ASSERT_TRUE(at.has_value());
  EXPECT_NEAR(at->distance, 6.5, 1e-9);
  EXPECT_TRUE(scene->hit({origin, {0, 1, 0}, 6.6}).has_value());
  // From behind the wall too (5.5 m away).
  EXPECT_FALSE(scene->hit({{6, 12, 2}, {0, -1, 0}, 5.4}).has_value());
}

TEST(RayQuery, ReadsOnlyTheLeavesTheSegmentMeets) {
  const auto scene = wallScene();
  // In the middle of leaf 1_1_1 (x in [4, 8], z in [0, 4]), across the wall only.
  ASSERT_TRUE(scene->hit({{6, -3, 2}, {0, 1, 0}}).has_value());
  EXPECT_EQ(scene->reads, (std::vector<PatchKey>{{1, 1, 1}}));
  // Nothing read for a ray that misses the model's box, nor for one stopped short of it.
  scene->reads.clear();
  EXPECT_FALSE(scene->hit({{6, -3, 20}, {0, 1, 0}}).has_value());
  EXPECT_FALSE(scene->hit({{6, -3, 2}, {0, 1, 0}, 2}).has_value());
  EXPECT_TRUE(scene->reads.empty());
  // A batch along one leaf reads it once.
  std::vector<Ray> rays;
  for (int k = 0; k < 10; ++k) {
    rays.push_back({{5 + 0.25 * k, -3, 1}, {0, 1, 0}});
  }
  const auto hits = scene->cast(rays);
  EXPECT_EQ(scene->reads, (std::vector<PatchKey>{{1, 1, 1}}));
  EXPECT_EQ(std::count_if(hits.begin(), hits.end(), [](const auto& h) { return h.has_value(); }),
            10);
}

TEST(RayQuery, BuildsOnlyTheBlocksTheSegmentCrosses) {
  // The wall as one 65 x 65 leaf (4 x 4 blocks of 16 x 16 cells, each 2 m square).
  const auto scene = makeScene(65, 8, wallPoint, {PatchKey::root()});
  RayLimits oneBlock;
  oneBlock.cellsPerRay = 256;
  // Across the wall in the middle of a block: that block alone.
  const auto hit = scene->cast(std::vector<Ray>{{{3, -3, 5}, {0, 1, 0}}}, oneBlock).front();
  ASSERT_TRUE(hit.has_value());
  EXPECT_LE((hit->point - Vec3d{3, 5.75, 5}).norm(), 1e-9);
  // Along the wall, through a row of blocks: refused at one block, answered with the default.
  const Ray along{{-1, 5.5, 5}, {1, 0, -0.01}};
  EXPECT_EQ(errorOf([&] { scene->cast(std::vector<Ray>{along}, oneBlock); }).first,
            ErrorCode::InvalidArgument);
  ASSERT_TRUE(scene->hit(along).has_value());
}

TEST(RayQuery, BoundsAreClearErrors) {
  const auto scene = wallScene();
  RayLimits limits;
  limits.rays = 2;
  const std::vector<Ray> three(3, Ray{{6, -3, 2}, {0, 1, 0}});
  auto [code, message] = errorOf([&] { scene->cast(three, limits); });
  EXPECT_EQ(code, ErrorCode::InvalidArgument);
  EXPECT_NE(message.find("more than the 2"), std::string::npos) << message;

  const auto refused = [&](const Ray& ray, const RayLimits& l = {}) {
    return errorOf([&] { scene->cast(std::vector<Ray>{{{6, -3, 2}, {0, 1, 0}}, ray}, l); });
  };
  const double nan = std::nan("");
  for (const Ray& bad : {Ray{{nan, 0, 0}, {0, 1, 0}}, Ray{{0, 0, 0}, {0, 0, 0}},
                         Ray{{0, 0, 0}, {0, nan, 0}}, Ray{{0, 0, 0}, {1e308, 1e308, 0}},
                         Ray{{0, 0, 0}, {0, 1, 0}, -1}, Ray{{0, 0, 0}, {0, 1, 0}, nan}}) {
    std::tie(code, message) = refused(bad);
    EXPECT_EQ(code, ErrorCode::InvalidArgument);
    EXPECT_EQ(message.rfind("ray 2: ", 0), 0u) << message;
  }

  // Along the wall's face, 0.1 m in front of it, it meets every leaf's box: too long for 2.
  limits = {};
  limits.leavesPerRay = 2;
  const Ray grazing{{-1, 4.65, 6}, {1, 0.25, 0}};
  std::tie(code, message) = refused(grazing, limits);
  EXPECT_EQ(code, ErrorCode::InvalidArgument);
  EXPECT_NE(message.find("ray 2 is too long"), std::string::npos) << message;
  EXPECT_NE(message.find("max distance"), std::string::npos) << message;
  // Shortened, it passes.
  Ray shorter = grazing;
  shorter.maxDistance = 2;
  EXPECT_FALSE(scene->cast(std::vector<Ray>{shorter}, limits).front().has_value());
  limits = {};
  limits.cellsPerRay = 256;
  std::tie(code, message) = refused(grazing, limits);
  EXPECT_EQ(code, ErrorCode::InvalidArgument);
  EXPECT_NE(message.find("ray 2 is too long"), std::string::npos) << message;
}

TEST(RayQuery, ChargesEachRaysWorkAndStopsWhenItDoesNotFit) {
  const auto scene = wallScene();
  std::vector<std::size_t> charged;
  const auto hits = scene->cast(std::vector<Ray>{{{6, -3, 2}, {0, 1, 0}}, {{1, -3, 7}, {0, 1, 0}}},
                                {}, [&](std::size_t bytes) {
                                  charged.push_back(bytes);
                                  return std::make_shared<int>(0);
                                });
  EXPECT_TRUE(hits[0] && hits[1]);
  ASSERT_EQ(charged.size(), 2u);
  EXPECT_GT(charged[0], 0u);
  const auto [code, message] = errorOf([&] {
    scene->cast(std::vector<Ray>{{{6, -3, 2}, {0, 1, 0}}}, {},
                [](std::size_t) -> std::shared_ptr<const void> {
                  throw Error(ErrorCode::ResourceExhausted, "the budget is full");
                });
  });
  EXPECT_EQ(code, ErrorCode::ResourceExhausted);
}

// ---- a tunnel
// -------------------------------------------------------------------------------------

/// A closed tunnel: a cylinder of radius 3 m about the line y = 0, z = 4, 16 m along x. Leaf
/// (1, kx, ky) spans x in [8 kx, 8 kx + 8] and the angle phi (from the top, towards +y) in
/// [pi ky, pi ky + pi]: 17 x 17 grids, 16 steps of 11.25 degrees. Each cell is a planar rectangle
/// between two lines of the cylinder, so the surface is exactly the prism over the 32-gon.
constexpr double kRadius = 3;
constexpr double kAxisZ = 4;
Vec3d tunnelPoint(double u, double v) {
  const double phi = v * kPi / 16;  // the model's side is 32: v in [0, 32]
  return {u / 2, kRadius * std::sin(phi), kAxisZ + kRadius * std::cos(phi)};
}
std::unique_ptr<Scene> tunnelScene() {
  return makeScene(17, 32, tunnelPoint, childrenOf(PatchKey::root()));
}

/// Where a ray across the axis (direction with no x) first meets the 32-gon in its plane, in
/// closed form: the nearest positive crossing of the polygon's edges.
std::optional<double> polygonHit(const Vec3d& origin, const Vec3d& d) {
  std::optional<double> best;
  for (int k = 0; k < 32; ++k) {
    const double a = k * kPi / 16, b = (k + 1) * kPi / 16;
    const double py = kRadius * std::sin(a), pz = kAxisZ + kRadius * std::cos(a);
    const double ey = kRadius * std::sin(b) - py, ez = kAxisZ + kRadius * std::cos(b) - pz;
    // origin + t d = p + s e  (in y, z)
    const double det = d.y * -ez - d.z * -ey;
    if (std::fabs(det) < 1e-15) {
      continue;
    }
    const double ry = py - origin.y, rz = pz - origin.z;
    const double t = (ry * -ez - rz * -ey) / det;
    const double s = (d.y * rz - d.z * ry) / det;
    if (s >= 0 && s <= 1 && t >= 0 && (!best || t < *best)) {
      best = t;
    }
  }
  return best;
}

TEST(RayQuery, FromInsideTheTunnelRaysHitTheNearWall) {
  const auto scene = tunnelScene();
  std::mt19937 rng(13);
  std::uniform_real_distribution<double> along(0.5, 15.5), angle(0, 2 * kPi), off(-1.5, 1.5);
  for (int n = 0; n < 300; ++n) {
    const Vec3d origin{along(rng), off(rng), kAxisZ + off(rng)};
    const double a = angle(rng);
    const Vec3d d{0, std::sin(a), std::cos(a)};
    const auto hit = scene->hit({origin, d});
    const auto t = polygonHit(origin, d);
    ASSERT_TRUE(t.has_value());
    ASSERT_TRUE(hit.has_value()) << n;
    // Float32 positions of cos and sin: well under 1e-5 m.
    EXPECT_NEAR(hit->distance, *t, 1e-5) << n;
    EXPECT_LE((hit->point - (origin + d * *t)).norm(), 1e-5) << n;
    // The wall's normal points back to the axis, within the polygon's facets (11.25 degrees).
    const Vec3d radial = unit({0, hit->point.y, hit->point.z - kAxisZ});
    EXPECT_LT(dot(hit->normal, radial), -std::cos(kPi / 32) + 1e-6) << n;
    EXPECT_NEAR(hit->normal.x, 0, 1e-6);
    EXPECT_EQ(hit->leaf.depth, 1);
  }
}

TEST(RayQuery, FromOutsideTheTunnelTheNearerOfItsTwoWallsAnswers) {
  const auto scene = tunnelScene();
  // Across the tunnel along +y: the outside of the wall at y = -3, not the far one at +3.
  const auto hit = scene->hit({{5, -10, kAxisZ}, {0, 1, 0}});
  ASSERT_TRUE(hit.has_value());
  EXPECT_NEAR(hit->point.y, -3, 1e-5);
  EXPECT_NEAR(hit->distance, 7, 1e-5);
  // On the edge between two facets (phi = 270 degrees): either facet's normal, facing -y.
  const double facet = std::cos(kPi / 32) - 1e-6;  // float32 vertices
  EXPECT_GE(dot(hit->normal, {0, -1, 0}), facet);
  // From inside along +y: the far wall, whose inside faces the ray.
  const auto inside = scene->hit({{5, 0, kAxisZ}, {0, 1, 0}});
  ASSERT_TRUE(inside.has_value());
  EXPECT_NEAR(inside->point.y, 3, 1e-5);
  EXPECT_GE(dot(inside->normal, {0, -1, 0}), facet);
  // From below, up through the floor and the ceiling: the floor (at the seam between the halves,
  // phi = 180 degrees).
  const auto up = scene->hit({{12, 0, -2}, {0, 0, 1}});
  ASSERT_TRUE(up.has_value());
  EXPECT_NEAR(up->point.z, kAxisZ - kRadius, 1e-5);
  EXPECT_NEAR(up->distance, 3, 1e-5);
}

TEST(RayQuery, TunnelMissesAlongTheAxisAwayAndShortOfTheWall) {
  const auto scene = tunnelScene();
  // Along the axis, inside: parallel to every wall, out of the far end.
  EXPECT_FALSE(scene->hit({{1, 0, kAxisZ}, {1, 0, 0}}).has_value());
  // Outside and going away from the tunnel.
  EXPECT_FALSE(scene->hit({{5, -10, kAxisZ}, {0, -1, 0}}).has_value());
  EXPECT_FALSE(scene->hit({{5, 3.5, kAxisZ}, {0, 1, 0}}).has_value());
  // Short of the wall (3 m from the axis at phi = 90 degrees), then reaching it.
  EXPECT_FALSE(scene->hit({{5, 0, kAxisZ}, {0, 1, 0}, 2.9}).has_value());
  const auto reached = scene->hit({{5, 0, kAxisZ}, {0, 1, 0}, 3.1});
  ASSERT_TRUE(reached.has_value());
  EXPECT_NEAR(reached->distance, 3, 1e-5);
  // Past the tunnel's end.
  EXPECT_FALSE(scene->hit({{17, -10, kAxisZ}, {0, 1, 0}}).has_value());
}

}  // namespace
}  // namespace vsm::core
