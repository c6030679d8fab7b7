#include <gtest/gtest.h>

#include <cmath>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"

namespace vsm::core {
namespace {

TEST(Box3d, DefaultIsEmptyAndExtendsToPoints) {
  Box3d box;
  EXPECT_TRUE(box.empty());
  box.extend(Vec3d{1, 2, 3});
  box.extend(Vec3d{-1, 5, 0});
  EXPECT_FALSE(box.empty());
  EXPECT_EQ(box.min, (Vec3d{-1, 2, 0}));
  EXPECT_EQ(box.max, (Vec3d{1, 5, 3}));
  EXPECT_TRUE(box.contains(Box3d{{0, 3, 1}, {1, 4, 2}}));
  EXPECT_FALSE(box.contains(Box3d{{0, 3, 1}, {1, 6, 2}}));
}

TEST(Mat4d, InverseUndoesARotationAndTranslation) {
  Mat4d m;
  // 90 degrees about z, then a translation.
  m.m = {0, -1, 0, 10, 1, 0, 0, 20, 0, 0, 1, 30, 0, 0, 0, 1};
  ASSERT_TRUE(m.isAffineInvertible());
  EXPECT_FALSE(m.isTranslation());
  const Vec3d p{1, 2, 3};
  const Vec3d back = m.inverse().apply(m.apply(p));
  EXPECT_NEAR(back.x, 1, 1e-12);
  EXPECT_NEAR(back.y, 2, 1e-12);
  EXPECT_NEAR(back.z, 3, 1e-12);
}

TEST(PatchGrid, StartsUndefined) {
  PatchGrid grid(5, Mat4d::identity());
  EXPECT_FALSE(grid.anyDefined());
  EXPECT_TRUE(grid.definedRect().empty());
  EXPECT_TRUE(grid.globalBox().empty());
  EXPECT_EQ(grid.resolution(), 0);
}

TEST(PatchGrid, RejectsSingularLocal2Global) {
  Mat4d singular;
  singular.m[0] = 0;
  EXPECT_THROW(PatchGrid(5, singular), Error);
}

TEST(PatchGrid, StoresGlobalPositionsRelativeToItsOrigin) {
  const Vec3d origin{6378137.0, 1000.0, -2000.0};
  PatchGrid grid(3, Mat4d::translation(origin));
  grid.setGlobal(1, 1, Vec3d{6378138.5, 1001.0, -1999.25});
  EXPECT_TRUE(grid.defined(1, 1));
  EXPECT_FALSE(grid.defined(0, 0));
  EXPECT_FLOAT_EQ(grid.local(1, 1).x, 1.5f);
  EXPECT_EQ(grid.global(1, 1), (Vec3d{6378138.5, 1001.0, -1999.25}));
}

TEST(PatchGrid, NonFiniteGlobalBecomesUndefined) {
  PatchGrid grid(3, Mat4d::identity());
  grid.setGlobal(0, 0, Vec3d{1, NAN, 2});
  EXPECT_FALSE(grid.defined(0, 0));
}

TEST(PatchGrid, DefinedRectAndBoxesCoverOnlyDefinedVertices) {
  PatchGrid grid(5, Mat4d::translation({100, 0, 0}));
  grid.setGlobal(1, 2, {101, 2, 0});
  grid.setGlobal(3, 3, {103, 3, 5});
  EXPECT_EQ(grid.definedRect(), (GridRect{1, 2, 4, 4}));
  EXPECT_EQ(grid.globalBox().min, (Vec3d{101, 2, 0}));
  EXPECT_EQ(grid.globalBox().max, (Vec3d{103, 3, 5}));
  EXPECT_EQ(grid.localBox().min, (Vec3d{1, 2, 0}));
  EXPECT_EQ(grid.definedCount(), 2u);
}

TEST(PatchGrid, ResolutionIsTheMeanDistanceBetweenDefinedNeighbours) {
  PatchGrid grid(3, Mat4d::identity());
  // Row 0: spacing 2 in x; vertex (0,1) 3 below (0,0). Pairs: (0,0)-(1,0)=2, (1,0)-(2,0)=2,
  // (0,0)-(0,1)=3. Mean 7/3.
  grid.setGlobal(0, 0, {0, 0, 0});
  grid.setGlobal(1, 0, {2, 0, 0});
  grid.setGlobal(2, 0, {4, 0, 0});
  grid.setGlobal(0, 1, {0, 3, 0});
  EXPECT_DOUBLE_EQ(grid.resolution(), 7.0 / 3.0);
}

TEST(PatchGrid, EqualityIsBitwiseSoUndefinedVerticesCompareEqual) {
  PatchGrid a(3, Mat4d::identity());
  PatchGrid b(3, Mat4d::identity());
  EXPECT_TRUE(a == b);
  a.setGlobal(0, 0, {1, 2, 3});
  EXPECT_FALSE(a == b);
  b.setGlobal(0, 0, {1, 2, 3});
  EXPECT_TRUE(a == b);
}

TEST(OriginFor, IsTheCentreOfTheBox) {
  const Mat4d m = originFor(Box3d{{0, 0, 0}, {2, 4, 6}});
  EXPECT_EQ(m.translationPart(), (Vec3d{1, 2, 3}));
  EXPECT_TRUE(m.isTranslation());
}

}  // namespace
}  // namespace vsm::core
