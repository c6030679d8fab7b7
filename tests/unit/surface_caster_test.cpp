#include <gtest/gtest.h>

#include <cmath>
#include <filesystem>
#include <functional>
#include <memory>
#include <numbers>
#include <optional>
#include <random>
#include <thread>
#include <vector>

#include "core/common/error.hpp"
#include "core/grid/vec_ops.hpp"
#include "core/merge/surface_caster.hpp"
#include "tests/unit/surface_sampler_reference.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::core {
namespace {

using test::codeOf;
using test::SurfaceSampler;
using Grids = std::vector<std::shared_ptr<const PatchGrid>>;

using vec::cross;
using vec::dot;
using vec::unit;

/// Distance of `p` from the line through `o` along `d`.
double offLine(const Vec3d& p, const Vec3d& o, const Vec3d& d) {
  return cross(p - o, unit(d)).norm();
}

/// A size x size grid around `origin` with vertex (x, y) at at(x, y) (nullopt: undefined). The
/// tests pick coordinates that float32 stores exactly (small dyadic numbers around a dyadic
/// origin), so that B's double vertices are the analytic surface's own points.
std::shared_ptr<PatchGrid> makeGrid(int size, const Vec3d& origin,
                                    const std::function<std::optional<Vec3d>(int, int)>& at) {
  auto grid = std::make_shared<PatchGrid>(size, Mat4d::translation(origin));
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      if (const std::optional<Vec3d> p = at(x, y)) {
        grid->setGlobal(x, y, *p);
      }
    }
  }
  return grid;
}

/// The plane z = 3 + x / 2 + y / 4 sampled at x = 1000 + i / 2, y = 2000 + j / 2 (exact floats
/// around the origin (1008, 2008, 0)).
double planeZ(double x, double y) {
  return 3 + (x - 1000) / 2 + (y - 2000) / 4;
}
std::shared_ptr<PatchGrid> planeGrid(int size = 33) {
  return makeGrid(size, {1008, 2008, 0}, [](int i, int j) -> std::optional<Vec3d> {
    const double x = 1000 + i / 2.0, y = 2000 + j / 2.0;
    return Vec3d{x, y, planeZ(x, y)};
  });
}
const Vec3d kPlaneNormal = unit({-0.5, -0.25, 1});

TEST(SurfaceCaster, HitsAPlaneExactlyAlongItsNormalAndObliquely) {
  const SurfaceCaster caster({planeGrid()});
  EXPECT_EQ(caster.cellCount(), 32u * 32);
  EXPECT_EQ(caster.triangleCount(), 2u * 32 * 32);
  std::mt19937 rng(3);
  std::uniform_real_distribution<double> along(3, 13), offset(-1, 1), tilt(-0.5, 0.5);
  for (int n = 0; n < 5000; ++n) {
    const double x = 1000 + along(rng), y = 2000 + along(rng);
    const Vec3d onPlane{x, y, planeZ(x, y)};
    const double h = offset(rng);
    // Along the normal (either way round) and tilted off it.
    Vec3d d = n % 2 ? kPlaneNormal : kPlaneNormal * -1.0;
    if (n % 3 == 0) {
      d = unit(d + Vec3d{tilt(rng), tilt(rng), 0});
    }
    const Vec3d origin = onPlane + kPlaneNormal * h;
    const auto hit = caster.cast({origin, d * 3.0, -3, 3});  // the direction is normalised
    ASSERT_TRUE(hit.has_value()) << n;
    // The analytic intersection of the line with the plane.
    const double t = -h / dot(d, kPlaneNormal);
    const Vec3d expected = origin + d * t;
    EXPECT_LE((hit->position - expected).norm(), 1e-9) << n;
    EXPECT_NEAR(hit->distance, t, 1e-9) << n;
    EXPECT_EQ(hit->grid, 0u);
    EXPECT_NEAR(hit->x, (expected.x - 1000) * 2, 1e-9);
    EXPECT_NEAR(hit->y, (expected.y - 2000) * 2, 1e-9);
  }
}

TEST(SurfaceCaster, HitsABilinearSurfaceExactlyFromAnyDirection) {
  // z = x y / 4 is bilinear, so B's bilinear cells reproduce it exactly (the triangles of the
  // hierarchy do not: the answer is the cell's bilinear surface).
  const auto grid = makeGrid(17, {0, 0, 0}, [](int i, int j) -> std::optional<Vec3d> {
    const double x = i - 8, y = j - 8;
    return Vec3d{x, y, x * y / 4};
  });
  const SurfaceCaster caster({grid});
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> along(-7.5, 7.5), tilt(-0.6, 0.6), offset(-0.5, 0.5);
  double worst = 0;
  for (int n = 0; n < 5000; ++n) {
    const double x = along(rng), y = along(rng);
    const Vec3d onSurface{x, y, x * y / 4};
    const Vec3d normal = unit({-y / 4, -x / 4, 1});
    const Vec3d d = unit(normal + Vec3d{tilt(rng), tilt(rng), tilt(rng)});
    const Vec3d origin = onSurface + normal * offset(rng);
    const auto hit = caster.cast({origin, d, -1, 1});
    ASSERT_TRUE(hit.has_value()) << n;
    const Vec3d p = hit->position;
    worst = std::max(worst, std::fabs(p.z - p.x * p.y / 4));
    EXPECT_LE(offLine(p, origin, d), 1e-9) << n;
    EXPECT_NEAR(hit->x, p.x + 8, 1e-9);
    EXPECT_NEAR(hit->y, p.y + 8, 1e-9);
  }
  EXPECT_LE(worst, 1e-9);
}

TEST(SurfaceCaster, AlongUpItGivesWhatTheSamplerGives) {
  // A smooth surface on a rotated, unevenly scaled lattice in 2 x 2 grids (float32-rounded).
  auto height = [](double x, double y) {
    return 20 * std::sin(x / 40) + 15 * std::cos(y / 55) + 5 * std::sin((x + y) / 25);
  };
  const double c = std::cos(0.5), s = std::sin(0.5);
  auto at = [&](double i, double j) {
    const double x = 300 + 0.8 * (i * c - j * s), y = -200 + 0.8 * (i * s + j * c);
    return Vec3d{x, y, height(x, y)};
  };
  Grids grids;
  for (int gy = 0; gy < 2; ++gy) {
    for (int gx = 0; gx < 2; ++gx) {
      grids.push_back(makeGrid(
          33, at(16 + 32 * gx, 16 + 32 * gy),
          [&](int x, int y) -> std::optional<Vec3d> { return at(32 * gx + x, 32 * gy + y); }));
    }
  }
  const SurfaceSampler sampler(grids, {0, 0, 1});
  const SurfaceCaster caster(grids);
  std::mt19937 rng(9);
  std::uniform_real_distribution<double> along(0.01, 63.99);
  for (int n = 0; n < 5000; ++n) {
    const Vec3d q = at(along(rng), along(rng));
    const Vec3d origin{q.x, q.y, q.z + 7};
    const auto expected = sampler.locate(origin);
    ASSERT_TRUE(expected.has_value()) << n;
    const auto hit = caster.cast({origin, {0, 0, -1}, -50, 50});
    ASSERT_TRUE(hit.has_value()) << n;
    EXPECT_LE((hit->position - expected->position).norm(), 1e-9) << n;
    EXPECT_NEAR(hit->distance, origin.z - expected->position.z, 1e-9);
    // On a seam of B's grids either neighbour is right: compare in the lattice.
    const double i = hit->x + 32.0 * (hit->grid % 2), j = hit->y + 32.0 * (hit->grid / 2);
    EXPECT_NEAR(i, expected->x + 32.0 * (expected->grid % 2), 1e-6) << n;
    EXPECT_NEAR(j, expected->y + 32.0 * (expected->grid / 2), 1e-6) << n;
  }
}

TEST(SurfaceCaster, HitsAVerticalWallTheSamplerCannotSee) {
  // The wall y = 5: vertex (i, j) at (i / 2, 5, j / 4), spacing 0.5 along rows, 0.25 along columns.
  const auto wall = makeGrid(17, {4, 5, 2}, [](int i, int j) -> std::optional<Vec3d> {
    return Vec3d{i / 2.0, 5, j / 4.0};
  });
  const SurfaceSampler sampler({wall}, {0, 0, 1});
  EXPECT_EQ(sampler.cellCount(), 0u);  // every cell projects onto a segment
  const SurfaceCaster caster({wall});
  for (const double side : {-1.0, 1.0}) {
    for (double x = 0.1; x < 8; x += 0.37) {
      for (double z = 0.05; z < 4; z += 0.29) {
        const Vec3d origin{x, 5 + 2 * side, z};
        const auto hit = caster.cast({origin, {0, -side, 0}, -3, 3});
        ASSERT_TRUE(hit.has_value()) << x << " " << z;
        EXPECT_LE((hit->position - Vec3d{x, 5, z}).norm(), 1e-12);
        EXPECT_NEAR(hit->distance, 2, 1e-12);
        EXPECT_NEAR(hit->x, x * 2, 1e-9);
        EXPECT_NEAR(hit->y, z * 4, 1e-9);
      }
    }
  }
  const GridSpacing spacing = gridSpacing(*wall);
  EXPECT_DOUBLE_EQ(spacing.rows, 0.5);
  EXPECT_DOUBLE_EQ(spacing.columns, 0.25);
  EXPECT_DOUBLE_EQ(spacing.mean, 0.375);
  // Through a transform (a scale by 2 and a turn about z): lengths in the transformed space.
  Mat4d turn;
  turn.m = {0, -2, 0, 0, 2, 0, 0, 0, 0, 0, 2, 0, 0, 0, 0, 1};
  const GridSpacing turned = gridSpacing(*wall, turn);
  EXPECT_DOUBLE_EQ(turned.rows, 1.0);
  EXPECT_DOUBLE_EQ(turned.columns, 0.5);
}

TEST(SurfaceCaster, OnAnOverhangTheNearestLayerWins) {
  // Two layers of B, z = 0 and z = 1, in two grids over the same ground.
  auto layer = [](double z) {
    return makeGrid(9, {4, 4, z}, [z](int i, int j) -> std::optional<Vec3d> {
      return Vec3d{i * 1.0, j * 1.0, z};
    });
  };
  const SurfaceCaster caster({layer(0), layer(1)});
  const struct {
    double z;
    double hitZ;
    std::uint32_t grid;
  } cases[] = {{0.3, 0, 0}, {0.7, 1, 1}, {-0.4, 0, 0}, {1.2, 1, 1}, {0.5, 0, 0}};
  for (const auto& c : cases) {
    for (const double sign : {1.0, -1.0}) {  // the direction's sense does not matter...
      const auto hit = caster.cast({{2.3, 5.6, c.z}, {0, 0, sign}, -2, 2});
      ASSERT_TRUE(hit.has_value()) << c.z;
      if (c.z == 0.5) {  // ...except on a tie, which goes to the positive side
        EXPECT_EQ(hit->position.z, sign > 0 ? 1 : 0);
        continue;
      }
      ASSERT_TRUE(hit.has_value()) << c.z;
      EXPECT_EQ(hit->position.z, c.hitZ) << c.z << " " << sign;
      EXPECT_EQ(hit->grid, c.grid) << c.z << " " << sign;
      EXPECT_NEAR(hit->distance, sign * (c.hitZ - c.z), 1e-12);
    }
  }
  // Only what lies within [tmin, tmax] counts: the farther layer when the nearer is excluded.
  const auto up = caster.cast({{2.3, 5.6, 0.3}, {0, 0, 1}, 0, 2});
  ASSERT_TRUE(up.has_value());
  EXPECT_EQ(up->position.z, 1);
  EXPECT_FALSE(caster.cast({{2.3, 5.6, 0.3}, {0, 0, 1}, 0.8, 2}).has_value());

  // One grid folding back over itself (a face leaning past vertical, then back): rows
  // j = 0..16 follow the half-ellipse (4 sin a, 2 - 2 cos a), a = pi j / 16.
  auto folded = std::make_shared<PatchGrid>(17, Mat4d::translation({2, 8, 2}));
  for (int j = 0; j < 17; ++j) {
    const double a = std::numbers::pi * j / 16;
    for (int i = 0; i < 17; ++i) {
      folded->setGlobal(i, j, {4 * std::sin(a), i * 1.0, 2 - 2 * std::cos(a)});
    }
  }
  const SurfaceCaster foldCaster({folded});
  // At x = 2 the fold has z = 2 -+ sqrt(3) (0.27 and 3.73, up to the cells' chords).
  const auto low = foldCaster.cast({{2, 7.5, 1.5}, {0, 0, 1}, -3, 3});
  const auto high = foldCaster.cast({{2, 7.5, 3.0}, {0, 0, 1}, -3, 3});
  ASSERT_TRUE(low.has_value());
  ASSERT_TRUE(high.has_value());
  EXPECT_NEAR(low->position.z, 2 - std::sqrt(3.0), 0.05);
  EXPECT_NEAR(high->position.z, 2 + std::sqrt(3.0), 0.05);
  EXPECT_LT(low->distance, 0);
  EXPECT_GT(high->distance, 0);
  EXPECT_LT(low->y, 8);   // the lower limb: rows before the turn
  EXPECT_GT(high->y, 8);  // the upper limb
}

TEST(SurfaceCaster, HitsASphereCapAlongItsNormalsWithinTheInterpolationBound) {
  // The cap of the sphere |p| = 10 over [-6, 6]^2, sampled every 0.5 (float32-rounded heights).
  constexpr double kRadius = 10;
  const auto cap = makeGrid(25, {0, 0, 9}, [](int i, int j) -> std::optional<Vec3d> {
    const double x = -6 + i / 2.0, y = -6 + j / 2.0;
    return Vec3d{x, y, std::sqrt(kRadius * kRadius - x * x - y * y)};
  });
  const SurfaceCaster caster({cap});
  const SurfaceSampler sampler({cap}, {0, 0, 1});
  std::mt19937 rng(13);
  std::uniform_real_distribution<double> along(-5.5, 5.5), offset(-0.5, 0.5);
  // Bound: a cell's bilinear surface lies in the convex hull of its corners, which lie on the
  // sphere within a chord c of the point of the sphere over their mean: at most c^2 / (2 radius)
  // inside it. Plus float32 rounding of the heights.
  double bound = 0;
  for (int j = 0; j < 24; ++j) {
    for (int i = 0; i < 24; ++i) {
      const Vec3d corners[4] = {cap->global(i, j), cap->global(i + 1, j), cap->global(i + 1, j + 1),
                                cap->global(i, j + 1)};
      const Vec3d mean = (corners[0] + corners[1] + corners[2] + corners[3]) * 0.25;
      for (const Vec3d& c : corners) {
        const double chord = (c - unit(mean) * kRadius).norm();
        bound = std::max(bound, chord * chord / (2 * kRadius));
      }
    }
  }
  bound += 1e-5;
  double worst = 0;
  for (int n = 0; n < 3000; ++n) {
    const double x = along(rng), y = along(rng);
    const Vec3d normal = unit({x, y, std::sqrt(kRadius * kRadius - x * x - y * y)});
    const Vec3d origin = normal * (kRadius + offset(rng));
    const auto hit = caster.cast({origin, normal * -1.0, -1, 1});  // inward, from either side
    ASSERT_TRUE(hit.has_value()) << n;
    EXPECT_LE(offLine(hit->position, origin, normal), 1e-9);
    worst = std::max(worst, std::fabs(hit->position.norm() - kRadius));
    // On B's bilinear surface: where the sampler puts the same plane point.
    const auto s = sampler.sample({hit->position.x, hit->position.y, 100});
    ASSERT_TRUE(s.has_value());
    EXPECT_NEAR(s->z, hit->position.z, 1e-9) << n;
  }
  EXPECT_LE(worst, bound);
  EXPECT_GT(worst, bound / 50);  // the bound is not vacuous
}

TEST(SurfaceCaster, InsideATunnelTheNearerWallWins) {
  // A horseshoe around the y axis: radius 3, from -135 to 135 degrees (0 at the crown), every
  // 270 / 64 degrees, y every 0.5 m.
  constexpr double kRadius = 3;
  const auto tunnel = makeGrid(65, {0, 8, 0}, [](int i, int j) -> std::optional<Vec3d> {
    const double a = (-135 + 270.0 * i / 64) * std::numbers::pi / 180;
    return Vec3d{kRadius * std::sin(a), j * 0.25, kRadius * std::cos(a)};
  });
  const SurfaceCaster caster({tunnel});
  // The chord sagitta of a cell: how far inside the circle its surface may lie.
  const double step = 270.0 / 64 * std::numbers::pi / 180;
  const double sagitta = kRadius * (1 - std::cos(step / 2)) + 1e-5;
  std::mt19937 rng(17);
  std::uniform_real_distribution<double> angle(-2.2, 2.2), radius(0, 2.5), y(1, 15);
  for (int n = 0; n < 2000; ++n) {
    // From a point inside, off the axis along a direction across the tunnel, cast both ways.
    const double a = angle(rng), r = radius(rng);
    const Vec3d d{std::sin(a), 0, std::cos(a)};
    const Vec3d origin = Vec3d{0, y(rng), 0} + d * r;
    const auto hit = caster.cast({origin, d, -6, 6});
    ASSERT_TRUE(hit.has_value()) << n;
    const double hitRadius = std::hypot(hit->position.x, hit->position.z);
    EXPECT_LE(hitRadius, kRadius + 1e-6);  // float32 rounding of the stored vertices
    EXPECT_GE(hitRadius, kRadius - sagitta);
    EXPECT_LE(offLine(hit->position, origin, d), 1e-9);
    const Vec3d back = hit->position - Vec3d{0, hit->position.y, 0};
    // The wall ahead (3 - r away), not the one behind (3 + r, where the horseshoe has one).
    EXPECT_GT(dot(back, d), 0) << n;
    EXPECT_NEAR(hit->distance, kRadius - r, sagitta + 1e-9) << n;
  }
  // Through the opening (the floor between -135 and 135 degrees): nothing below, the crown above.
  EXPECT_FALSE(caster.cast({{0, 5, 0}, {0, 0, -1}, 0, 6}).has_value());
  const auto crown = caster.cast({{0, 5, 0}, {0, 0, -1}, -6, 6});
  ASSERT_TRUE(crown.has_value());
  EXPECT_NEAR(crown->position.z, kRadius, 1e-12);
  EXPECT_NEAR(crown->x, 32, 1e-9);
  EXPECT_NEAR(crown->y, 20, 1e-9);
}

TEST(SurfaceCaster, TransformsBWithItsRays) {
  // The plane turned by a rigid transform: a ray turned with it meets the turned point.
  Mat4d turn;
  const double c = std::cos(0.7), s = std::sin(0.7);
  turn.m = {c, 0, s, 10, 0, 1, 0, -20, -s, 0, c, 5, 0, 0, 0, 1};
  const SurfaceCaster plain({planeGrid()});
  const SurfaceCaster turned({planeGrid()}, turn);
  auto rotate = [&](const Vec3d& v) {  // the linear part
    return turn.apply(v) - turn.apply({0, 0, 0});
  };
  for (double i = 1.3; i < 30; i += 2.9) {
    const double x = 1000 + i / 2, y = 2000 + (32 - i) / 2;
    const Vec3d origin = Vec3d{x, y, planeZ(x, y)} + Vec3d{0.1, -0.2, 0.6};
    const auto a = plain.cast({origin, {0.1, 0.2, -1}, -2, 2});
    const auto b = turned.cast({turn.apply(origin), rotate({0.1, 0.2, -1}), -2, 2});
    ASSERT_TRUE(a.has_value());
    ASSERT_TRUE(b.has_value());
    EXPECT_LE((turn.apply(a->position) - b->position).norm(), 1e-9);
    EXPECT_NEAR(a->distance, b->distance, 1e-9);
    EXPECT_NEAR(a->x, b->x, 1e-9);
    EXPECT_NEAR(a->y, b->y, 1e-9);
  }
}

TEST(SurfaceCaster, HolesHaveNoSurface) {
  // The plane with vertex (8, 8) undefined (its four cells become triangles of their other three
  // corners) and vertices (20, 20) and (21, 20) undefined (the two cells between them have two
  // corners left: nothing).
  const auto grid = makeGrid(33, {1008, 2008, 0}, [](int i, int j) -> std::optional<Vec3d> {
    if ((i == 8 && j == 8) || (j == 20 && (i == 20 || i == 21))) {
      return std::nullopt;
    }
    const double x = 1000 + i / 2.0, y = 2000 + j / 2.0;
    return Vec3d{x, y, planeZ(x, y)};
  });
  const SurfaceCaster caster({grid});
  EXPECT_EQ(caster.cellCount(), 32u * 32 - 2);
  EXPECT_EQ(caster.triangleCount(), 2u * (32 * 32 - 2) - 4 - 4);  // 4 triangles + 4 cells less
  auto castAt = [&](double i, double j) {
    const double x = 1000 + i / 2.0, y = 2000 + j / 2.0;
    return caster.cast({Vec3d{x, y, planeZ(x, y)} + kPlaneNormal * 0.5, kPlaneNormal, -1, 1});
  };
  EXPECT_FALSE(castAt(8, 8).has_value());
  EXPECT_FALSE(castAt(7.7, 7.7).has_value());   // beyond the diagonal of cell (7, 7)
  EXPECT_FALSE(castAt(8.3, 8.3).has_value());   // and of cell (8, 8)
  EXPECT_TRUE(castAt(7.25, 7.25).has_value());  // the triangle (7, 7), (8, 7), (7, 8)
  EXPECT_TRUE(castAt(8.6, 7.2).has_value());    // the triangle (8, 7), (9, 7), (9, 8)
  EXPECT_FALSE(castAt(8.2, 7.6).has_value());   // beyond its diagonal
  EXPECT_FALSE(castAt(20.5, 19.5).has_value());
  EXPECT_FALSE(castAt(20.5, 20.5).has_value());
  EXPECT_FALSE(castAt(21.3, 20.3).has_value());  // the triangle (22, 20), (22, 21), (21, 21)
  EXPECT_TRUE(castAt(21.7, 20.7).has_value());
  EXPECT_TRUE(castAt(22.5, 20.5).has_value());
  const auto hit = castAt(7.25, 7.25);
  ASSERT_TRUE(hit.has_value());
  EXPECT_NEAR(hit->x, 7.25, 1e-9);
  EXPECT_NEAR(hit->y, 7.25, 1e-9);
}

TEST(SurfaceCaster, BsBorderReachesAsFarAsTheSamplersTolerance) {
  // The plane with a hole at vertex (8, 8): within kBorderTolerance grid units across B's outer
  // border and across the diagonals around the hole a ray takes B (its nearest point's distance,
  // on the ray), beyond it nothing; the sampler along up agrees (away from B's corners, where the
  // sampler's tolerance is a quarter disc the caster does not cover).
  const auto grid = makeGrid(33, {1008, 2008, 0}, [](int i, int j) -> std::optional<Vec3d> {
    if (i == 8 && j == 8) {
      return std::nullopt;
    }
    const double x = 1000 + i / 2.0, y = 2000 + j / 2.0;
    return Vec3d{x, y, planeZ(x, y)};
  });
  const SurfaceCaster caster({grid});
  const SurfaceSampler sampler({grid}, {0, 0, 1});
  constexpr double kTolerance = cell_geometry::kBorderTolerance;
  auto rayAt = [](double i, double j) {
    const double x = 1000 + i / 2.0, y = 2000 + j / 2.0;
    return CastRay{{x, y, planeZ(x, y) + 0.5}, {0, 0, -1}, -1, 1};
  };
  std::mt19937 rng(23);
  std::uniform_real_distribution<double> along(0.5, 31.5), outside(0, 2 * kTolerance);
  int taken = 0, refused = 0;
  for (int n = 0; n < 4000; ++n) {
    const double a = along(rng), o = outside(rng);
    double i = 0, j = 0;
    double measure = o;  // how far outside B the sampler sees the point, in grid units
    switch (n % 5) {
      case 0:
        i = -o, j = a;
        break;
      case 1:
        i = 32 + o, j = a;
        break;
      case 2:
        i = a, j = -o;
        break;
      case 3:
        i = a, j = 32 + o;
        break;
      default: {  // beyond the diagonal of cell (7, 7), a 3-corner cell: (7, 8) to (8, 7)
        const double t = 0.1 + 0.8 * (a - 0.5) / 31;
        const double s = t + o / std::sqrt(2.0), u = 1 - t + o / std::sqrt(2.0);
        i = 7 + s, j = 7 + u;
        // Barycentric coordinates clamped and re-normalised: the point moves towards (7, 7).
        measure = std::hypot(s, u) * (s + u - 1) / (s + u);
      }
    }
    if (std::fabs(measure - kTolerance) < 1e-3) {
      continue;
    }
    const CastRay ray = rayAt(i, j);
    const auto hit = caster.cast(ray);
    const auto expected = sampler.locate(ray.origin);
    ASSERT_EQ(hit.has_value(), measure < kTolerance) << n << " " << i << " " << j;
    ASSERT_EQ(expected.has_value(), measure < kTolerance) << n;
    if (hit) {
      ++taken;
      EXPECT_LE((hit->position - expected->position).norm(), 1e-9) << n;
      EXPECT_NEAR(hit->x, expected->x, 1e-9) << n;
      EXPECT_NEAR(hit->y, expected->y, 1e-9) << n;
    } else {
      ++refused;
    }
  }
  EXPECT_GT(taken, 1000);
  EXPECT_GT(refused, 1000);
}

TEST(SurfaceCaster, MissesBeyondTheSearchDistanceAndOutsideB) {
  const SurfaceCaster caster({planeGrid()});
  const Vec3d onPlane{1005, 2005, planeZ(1005, 2005)};
  EXPECT_FALSE(caster.cast({onPlane + kPlaneNormal * 2, kPlaneNormal, -1.99, 1.99}).has_value());
  EXPECT_TRUE(caster.cast({onPlane + kPlaneNormal * 2, kPlaneNormal, -2.01, 2.01}).has_value());
  EXPECT_FALSE(caster.cast({onPlane + kPlaneNormal * 2, kPlaneNormal, 0, 5}).has_value());
  EXPECT_TRUE(caster.cast({onPlane + kPlaneNormal * 2, kPlaneNormal, -5, 0}).has_value());
  // Outside B (it spans [1000, 1016] x [2000, 2016]) and parallel to it.
  EXPECT_FALSE(caster.cast({{1017, 2005, 20}, {0, 0, 1}, -100, 100}).has_value());
  EXPECT_FALSE(caster.cast({onPlane + kPlaneNormal, {1, 0, 0.5}, -100, 100}).has_value());
  // Undefined rays.
  const double nan = std::numeric_limits<double>::quiet_NaN();
  EXPECT_FALSE(caster.cast({{nan, 0, 0}, kPlaneNormal, -1, 1}).has_value());
  EXPECT_FALSE(caster.cast({onPlane, {0, 0, 0}, -1, 1}).has_value());
  EXPECT_FALSE(caster.cast({onPlane, kPlaneNormal, 1, -1}).has_value());
  // An empty B.
  const SurfaceCaster empty(Grids{nullptr});
  EXPECT_EQ(empty.cellCount(), 0u);
  EXPECT_FALSE(empty.cast({onPlane, kPlaneNormal, -1, 1}).has_value());
  std::vector<CastRay> rays(3);
  std::vector<std::optional<CastHit>> hits(2);
  EXPECT_EQ(codeOf([&] { caster.cast(rays, hits); }), ErrorCode::InvalidArgument);
}

/// A zig-zag along x, every row alike: vertex (i, j) at (i, j, heights[i]), 4 x 4.
std::shared_ptr<PatchGrid> zigZag(const std::array<double, 4>& heights) {
  return makeGrid(4, {2, 2, 0}, [&](int i, int j) -> std::optional<Vec3d> {
    return Vec3d{double(i), double(j), heights[i]};
  });
}

/// A large flat grid far away: it turns the bins' axis to z without meeting the rays.
std::shared_ptr<PatchGrid> farFloor() {
  return makeGrid(65, {132, 32, 0}, [](int i, int j) -> std::optional<Vec3d> {
    return Vec3d{100.0 + i, double(j), 0};
  });
}

TEST(SurfaceCaster, OnlyHitsWithinTheSearchRangeCompeteWhateverTheAxisAndClip) {
  // Found by review: a cell whose own hit lies outside [tmin, tmax] (the zig-zag's third cell,
  // 0.25 from the origin, within B's border tolerance) must not decide the answer through a
  // neighbour. The nearest hit within [1.5, 3] is the plate at x = 1.6 (t = 1.65), with the axis
  // along x (zig-zag and plate alone), along z (a far floor added) and in a clip around the ray.
  const auto zig = zigZag({0, 1.2, 0, 0.98});
  const auto plate = makeGrid(2, {1.6, 1, 1}, [](int i, int j) -> std::optional<Vec3d> {
    return Vec3d{1.6, 0.5 + i, 0.5 + j};
  });
  const CastRay ray{{3.25, 1, 1}, {-1, 0, 0}, 1.5, 3};
  SurfaceCaster::Clip clip{Box3d{{0.2, 0.9, 0.9}, {1.76, 1.1, 1.1}}};
  for (const SurfaceCaster& caster :
       {SurfaceCaster(Grids{zig, plate}), SurfaceCaster(Grids{zig, plate, farFloor()}),
        SurfaceCaster(Grids{zig, plate}, std::nullopt, clip)}) {
    const auto hit = caster.cast(ray);
    ASSERT_TRUE(hit.has_value());
    EXPECT_EQ(hit->grid, 1u);
    EXPECT_NEAR(hit->distance, 1.65, 1e-12);
  }
}

TEST(SurfaceCaster, NeighboursOutsideTheSearchRangeDoNotVetoAHit) {
  // Found by review: the ray along the zig-zag's row edge meets its second cell at t = 0.8 within
  // [0.5, 1]; the first cell's hit at t = -0.2 is nearer but outside the range, and a clip around
  // the ray does not build it. Whole and clipped, the answer is the hit at 0.8.
  const auto zig = zigZag({0, 1, 0, 1});
  const CastRay ray{{0.7, 1, 0.5}, {1, 0, 0}, 0.5, 1};
  SurfaceCaster::Clip clip{Box3d{{1.19, 0.9, 0.4}, {1.75, 1.1, 0.6}}};
  for (const SurfaceCaster& caster : {SurfaceCaster(Grids{zig, farFloor()}),
                                      SurfaceCaster(Grids{zig, farFloor()}, std::nullopt, clip)}) {
    const auto hit = caster.cast(ray);
    ASSERT_TRUE(hit.has_value());
    EXPECT_NEAR(hit->distance, 0.8, 1e-12);
    EXPECT_NEAR(hit->position.x, 1.5, 1e-12);
  }
}

TEST(SurfaceCaster, DirectionsOfAnyFiniteLengthCast) {
  // Found by review: a direction whose length overflows (or underflows) in double is still a
  // direction.
  const SurfaceCaster caster({planeGrid()});
  const Vec3d onPlane{1005, 2005, planeZ(1005, 2005)};
  const auto unitHit = caster.cast({onPlane + kPlaneNormal, kPlaneNormal, -2, 2});
  ASSERT_TRUE(unitHit.has_value());
  for (const double scale : {1e200, 1e-200}) {
    const auto hit = caster.cast({onPlane + kPlaneNormal, kPlaneNormal * scale, -2, 2});
    ASSERT_TRUE(hit.has_value()) << scale;
    EXPECT_NEAR(hit->distance, unitHit->distance, 1e-12) << scale;
    EXPECT_LE((hit->position - unitHit->position).norm(), 1e-9) << scale;
  }
}

TEST(SurfaceCaster, RaysThroughEdgesAndVerticesHitAndClipsChangeNothing) {
  // B in 2 x 2 grids of a tilted, curved surface sharing their borders.
  auto at = [](int i, int j) {
    const double x = i * 0.5, y = j * 0.5;
    return Vec3d{x, y, 0.3 * x + 0.02 * x * x - 0.01 * y * y};
  };
  Grids grids;
  std::vector<std::vector<Box3d>> blocks;
  for (int gy = 0; gy < 2; ++gy) {
    for (int gx = 0; gx < 2; ++gx) {
      grids.push_back(makeGrid(
          33, at(16 + 32 * gx, 16 + 32 * gy),
          [&](int x, int y) -> std::optional<Vec3d> { return at(32 * gx + x, 32 * gy + y); }));
      blocks.push_back(SurfaceCaster::blockBoxes(*grids.back(), std::nullopt));
    }
  }
  const SurfaceCaster whole(grids);
  // Rays along the up direction and tilted, through every vertex and every edge's midpoint.
  std::vector<CastRay> rays;
  for (int j = 0; j <= 128; ++j) {
    for (int i = 0; i <= 128; ++i) {
      if ((i % 2 == 1 && j % 2 == 1) || i == 0 || j == 0 || i == 128 || j == 128) {
        continue;  // a cell's centre, or B's outer border
      }
      const Vec3d p = at(0, 0) + Vec3d{i * 0.25, j * 0.25, 0};
      const Vec3d q{p.x, p.y, 0.3 * p.x + 0.02 * p.x * p.x - 0.01 * p.y * p.y};
      rays.push_back({q + Vec3d{0, 0, 0.7}, {0, 0, 1}, -2, 2});
      rays.push_back({q + Vec3d{-0.3, 0.1, 1}, {-0.3, 0.1, 1}, -2, 2});
    }
  }
  // Cast as one batch and one by one.
  std::vector<std::optional<CastHit>> stream(rays.size()), single(rays.size());
  whole.cast(rays, stream);
  for (std::size_t r = 0; r < rays.size(); ++r) {
    single[r] = whole.cast(rays[r]);
  }
  // A clipped caster (the box around one quarter of B, rays inside it) answers bit-identically.
  SurfaceCaster::Clip clip{Box3d{{7, 9, -100}, {17, 22, 100}}, {}};
  for (const auto& b : blocks) {
    clip.blocks.emplace_back(b);
  }
  const SurfaceCaster clipped(grids, std::nullopt, clip);
  EXPECT_LT(clipped.cellCount(), whole.cellCount() / 3);
  std::size_t compared = 0;
  for (std::size_t r = 0; r < rays.size(); ++r) {
    ASSERT_TRUE(stream[r].has_value()) << r;
    ASSERT_TRUE(single[r].has_value()) << r;
    EXPECT_EQ(stream[r]->position, single[r]->position) << r;
    EXPECT_EQ(stream[r]->distance, single[r]->distance) << r;
    EXPECT_LE(std::fabs(stream[r]->distance), 1.2);
    const Vec3d o = rays[r].origin;
    if (o.x > 8 && o.x < 16 && o.y > 10 && o.y < 21) {
      const auto c = clipped.cast(rays[r]);
      ASSERT_TRUE(c.has_value()) << r;
      EXPECT_EQ(c->position, stream[r]->position) << r;
      EXPECT_EQ(c->grid, stream[r]->grid) << r;
      EXPECT_EQ(c->x, stream[r]->x) << r;
      EXPECT_EQ(c->y, stream[r]->y) << r;
      ++compared;
    }
  }
  EXPECT_GT(compared, 1000u);
}

TEST(SurfaceCaster, BuildsAndCastsOnSeveralThreadsAtOnce) {
  // A merge builds one caster per new patch, on every executor thread: concurrent construction
  // and casting (each on its own thread, and two threads on one caster) give the sequential
  // answers.
  std::vector<CastRay> rays;
  for (int n = 0; n < 4000; ++n) {
    const double x = 1000.3 + (n % 60) * 0.25, y = 2000.3 + (n / 60) * 0.2;
    rays.push_back({{x, y, planeZ(x, y) + 0.3}, {0.1, 0, 1}, -1, 1});
  }
  const SurfaceCaster reference({planeGrid()});
  std::vector<std::optional<CastHit>> expected(rays.size());
  reference.cast(rays, expected);
  std::vector<std::vector<std::optional<CastHit>>> got(
      4, std::vector<std::optional<CastHit>>(rays.size()));
  std::vector<std::thread> threads;
  for (int t = 0; t < 2; ++t) {
    threads.emplace_back([&, t] {
      const SurfaceCaster own({planeGrid()});
      own.cast(rays, got[t]);
    });
    threads.emplace_back([&, t] { reference.cast(rays, got[2 + t]); });
  }
  for (std::thread& thread : threads) {
    thread.join();
  }
  for (const auto& hits : got) {
    for (std::size_t r = 0; r < rays.size(); ++r) {
      ASSERT_TRUE(hits[r].has_value()) << r;
      EXPECT_EQ(hits[r]->position, expected[r]->position) << r;
    }
  }
}

TEST(SurfaceCaster, CreatesNoThreads) {
  auto threads = [] {
    std::size_t n = 0;
    for ([[maybe_unused]] const auto& entry :
         std::filesystem::directory_iterator("/proc/self/task")) {
      ++n;
    }
    return n;
  };
  const std::size_t before = threads();
  const SurfaceCaster caster({planeGrid(129)});
  std::vector<CastRay> rays;
  for (int n = 0; n < 10000; ++n) {
    const double x = 1000 + (n % 100) * 0.6, y = 2000 + (n / 100) * 0.6;
    rays.push_back({{x, y, planeZ(x, y) + 1}, {0, 0, 1}, -2, 2});
  }
  std::vector<std::optional<CastHit>> hits(rays.size());
  caster.cast(rays, hits);
  EXPECT_TRUE(hits[0].has_value());
  EXPECT_EQ(threads(), before);
}

}  // namespace
}  // namespace vsm::core
