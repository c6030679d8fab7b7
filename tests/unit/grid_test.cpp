#include <gtest/gtest.h>

#include <cmath>
#include <cstring>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/grid/shaded_relief.hpp"
#include "core/grid/texture_tile.hpp"

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

TEST(PatchGrid, BoxesAndResolutionOfRowsWiderThanTheVectorLanes) {
  // summarize and localBox take rows in lanes of eight and a tail: extremes in the middle of a
  // lane, in the tail, and a vertex with one coordinate NaN (undefined: left out of the box).
  PatchGrid grid(37, Mat4d::translation({500, 500, 0}));
  for (int y = 0; y < 37; ++y) {
    for (int x = 0; x < 37; ++x) {
      grid.setLocal(x, y, {float(2 * x), float(2 * y), 0});
    }
  }
  grid.setUndefined(0, 0);
  grid.setUndefined(1, 0);
  EXPECT_DOUBLE_EQ(grid.resolution(), 2.0);  // every pair 2 apart, those with a hole left out
  grid.setLocal(13, 5, {26, 10, 7});
  grid.setLocal(35, 20, {70, 40, -4});
  grid.positions()[(30 * 37 + 9) * 3] = 1000;  // x of vertex (9, 30)
  grid.positions()[(30 * 37 + 9) * 3 + 1] = NAN;
  const PatchGrid::Summary summary = grid.summarize();
  EXPECT_EQ(summary.localBox.min, (Vec3d{0, 0, -4}));
  EXPECT_EQ(summary.localBox.max, (Vec3d{72, 72, 7}));
  EXPECT_EQ(grid.localBox().min, summary.localBox.min);
  EXPECT_EQ(grid.localBox().max, summary.localBox.max);
  EXPECT_EQ(summary.definedRect, (GridRect{0, 0, 37, 37}));
  // Defined only in columns 3..29 of rows 4..35.
  PatchGrid holed(37, Mat4d::identity());
  for (int y = 4; y < 36; ++y) {
    for (int x = 3; x < 30; ++x) {
      holed.setLocal(x, y, {float(x), float(y), float(x % 8 == 5 ? -1 : 1)});
    }
  }
  EXPECT_EQ(holed.definedRect(), (GridRect{3, 4, 30, 36}));
  EXPECT_EQ(holed.summarize().localBox.min, (Vec3d{3, 4, -1}));
  EXPECT_EQ(holed.summarize().localBox.max, (Vec3d{29, 35, 1}));
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

// ---- texture tiles --------------------------------------------------------------------------

namespace {

/// A tile whose texel (i, j) has a distinct, position-derived colour.
vsm::core::TextureTile patternTile(int size, int seed) {
  vsm::core::TextureTile tile(size);
  for (int j = 0; j < size; ++j) {
    for (int i = 0; i < size; ++i) {
      std::uint8_t* t = tile.at(i, j);
      t[0] = static_cast<std::uint8_t>((i * 7 + j * 3 + seed) % 256);
      t[1] = static_cast<std::uint8_t>((i * 11 + j * 5 + 2 * seed) % 256);
      t[2] = static_cast<std::uint8_t>((i + j * 13 + 3 * seed) % 256);
      t[3] = static_cast<std::uint8_t>(200 + (i + j) % 50);
    }
  }
  return tile;
}

}  // namespace

TEST(TextureTile, TileSizeIsAPowerOfTwoTexelsPerGridQuad) {
  EXPECT_EQ(vsm::core::textureTileSize(257), 256);
  EXPECT_EQ(vsm::core::textureTileSize(65), 64);
  EXPECT_EQ(vsm::core::textureTileSize(3), 2);
  EXPECT_EQ(vsm::core::textureTileSize(257, 4), 1024);
  EXPECT_EQ(vsm::core::texelsPerQuadOf(256, 257), 1);
  EXPECT_EQ(vsm::core::texelsPerQuadOf(1024, 257), 4);
  EXPECT_EQ(vsm::core::texelsPerQuadOf(4096, 257), 16);
  // The cap: tiles of at most 4096 texels, or one texel per quad where even that is more.
  EXPECT_EQ(vsm::core::maxTexelsPerQuad(257), 16);
  EXPECT_EQ(vsm::core::maxTexelsPerQuad(65), 64);
  EXPECT_EQ(vsm::core::maxTexelsPerQuad(4097), 1);
  EXPECT_EQ(vsm::core::maxTexelsPerQuad(8193), 1);
  // Foreign layouts: not a multiple, not a power of two, smaller than the grid.
  EXPECT_EQ(vsm::core::texelsPerQuadOf(1000, 257), 0);
  EXPECT_EQ(vsm::core::texelsPerQuadOf(768, 257), 0);
  EXPECT_EQ(vsm::core::texelsPerQuadOf(128, 257), 0);
}

TEST(TextureTile, ResizingDownAveragesBlocksAndUpInterpolates) {
  using vsm::core::TextureTile;
  // 8 x 8 texels in 4 x 4 blocks of one colour each, two of their texels different.
  TextureTile tile(8);
  for (int j = 0; j < 8; ++j) {
    for (int i = 0; i < 8; ++i) {
      std::uint8_t* t = tile.at(i, j);
      t[0] = static_cast<std::uint8_t>(40 * (i / 4) + 10);
      t[1] = static_cast<std::uint8_t>(80 * (j / 4) + 20);
      t[2] = 7;
      t[3] = 255;
    }
  }
  tile.at(0, 0)[2] = 7 + 16 * 3;  // block (0, 0): blue sums to 16 * 7 + 48
  const TextureTile two = vsm::core::resizeTile(tile, 2);
  EXPECT_EQ(two.at(1, 0)[0], 50);
  EXPECT_EQ(two.at(0, 1)[1], 100);
  EXPECT_EQ(two.at(0, 0)[2], 10);  // 7 + 48 / 16
  EXPECT_EQ(two.at(1, 1)[2], 7);
  EXPECT_EQ(two.at(1, 1)[3], 255);

  // Up by 4: texel (i, j) is centred at ((i + 0.5) / 4 - 0.5, ...) in the small tile's texel
  // centres; texel 3 at 0.375 between the columns 10 and 50, so 25; the border clamps.
  const TextureTile up = vsm::core::resizeTile(two, 8);
  EXPECT_EQ(up.at(3, 0)[0], 25);
  EXPECT_EQ(up.at(0, 0)[0], 10);
  EXPECT_EQ(up.at(7, 7)[0], 50);
  EXPECT_EQ(up.at(7, 7)[3], 255);
  // Transparent texels stay out: an all-transparent tile stays transparent, and a texel next to
  // a transparent one takes the opaque colour alone.
  TextureTile half(2);
  std::uint8_t* opaque = half.at(0, 0);
  opaque[0] = 90;
  opaque[3] = 255;
  const TextureTile halfUp = vsm::core::resizeTile(half, 4);
  EXPECT_EQ(halfUp.at(1, 1)[0], 90);
  EXPECT_EQ(halfUp.at(1, 1)[3], 255);
  EXPECT_TRUE(vsm::core::resizeTile(TextureTile(2), 8).transparent());
  // Only powers of two.
  EXPECT_THROW(vsm::core::resizeTile(tile, 6), vsm::core::Error);
  EXPECT_THROW(vsm::core::resizeTile(two, 6), vsm::core::Error);
}

TEST(TextureTile, RejectsOddOrTinySizes) {
  EXPECT_THROW(vsm::core::TextureTile(3), vsm::core::Error);
  EXPECT_THROW(vsm::core::TextureTile(0), vsm::core::Error);
}

TEST(TextureTile, NewTileIsTransparent) {
  vsm::core::TextureTile tile(4);
  EXPECT_TRUE(tile.transparent());
  tile.at(3, 3)[3] = 1;
  EXPECT_FALSE(tile.transparent());
}

TEST(TextureTile, CoordinatesRunFromZeroAtTheFirstVertexToOneAtTheLast) {
  EXPECT_EQ(vsm::core::textureCoordinate(0, 65), 0.0f);
  EXPECT_EQ(vsm::core::textureCoordinate(64, 65), 1.0f);
  EXPECT_FLOAT_EQ(vsm::core::textureCoordinate(16, 65), 0.25f);
}

TEST(TextureTile, CoordinatesOfACroppedRectangleAreThoseOfItsVertices) {
  // Vertices (2..4) x (1..2) of a 5 x 5 grid: u = x / 4, v = y / 4 (v = 0 the top row).
  const std::vector<float> uv = vsm::core::textureCoordinates(5, 2, 1, 3, 2);
  ASSERT_EQ(uv.size(), 3u * 2u * 2u);
  EXPECT_FLOAT_EQ(uv[0], 0.5f);
  EXPECT_FLOAT_EQ(uv[1], 0.25f);
  EXPECT_FLOAT_EQ(uv[4], 1.0f);  // vertex (4, 1)
  EXPECT_FLOAT_EQ(uv[5], 0.25f);
  EXPECT_FLOAT_EQ(uv[6], 0.5f);  // vertex (2, 2): second row
  EXPECT_FLOAT_EQ(uv[7], 0.5f);
}

TEST(TextureTile, ParentTexelIsTheMeanOfItsTwoByTwoChildTexels) {
  const int size = 8;
  const std::array<vsm::core::TextureTile, 4> children{patternTile(size, 0), patternTile(size, 1),
                                                       patternTile(size, 2), patternTile(size, 3)};
  const vsm::core::TextureTile parent = vsm::core::downsampleQuadrants(
      {&children[0], &children[1], &children[2], &children[3]}, size);
  const int half = size / 2;
  for (int q = 0; q < 4; ++q) {
    const int ox = (q & 1) * half;  // nw, ne, sw, se
    const int oy = (q >> 1) * half;
    for (int j = 0; j < half; ++j) {
      for (int i = 0; i < half; ++i) {
        for (int c = 0; c < 4; ++c) {
          const int sum = children[q].at(2 * i, 2 * j)[c] + children[q].at(2 * i + 1, 2 * j)[c] +
                          children[q].at(2 * i, 2 * j + 1)[c] +
                          children[q].at(2 * i + 1, 2 * j + 1)[c];
          EXPECT_NEAR(parent.at(ox + i, oy + j)[c], sum / 4.0, 0.5)
              << "quadrant " << q << " texel " << i << "," << j << " channel " << c;
        }
      }
    }
  }
}

TEST(TextureTile, AParentTwiceTheChildsSizeHoldsItsTexelsAsTheyAre) {
  const vsm::core::TextureTile child = patternTile(4, 7);
  vsm::core::TextureTile parent(8);
  vsm::core::downsampleQuadrant(child, 2, parent);  // sw
  for (int j = 0; j < 8; ++j) {
    for (int i = 0; i < 8; ++i) {
      for (int c = 0; c < 4; ++c) {
        const int expected = i < 4 && j >= 4 ? child.at(i, j - 4)[c] : 0;
        EXPECT_EQ(parent.at(i, j)[c], expected) << i << "," << j << " channel " << c;
      }
    }
  }
  vsm::core::TextureTile other(16);
  EXPECT_THROW(vsm::core::downsampleQuadrant(child, 0, other), vsm::core::Error);
}

TEST(TextureTile, MissingChildLeavesItsQuadrantTransparent) {
  const vsm::core::TextureTile nw = patternTile(4, 5);
  const vsm::core::TextureTile parent =
      vsm::core::downsampleQuadrants({&nw, nullptr, nullptr, nullptr}, 4);
  EXPECT_NE(parent.at(0, 0)[3], 0);
  for (int j = 0; j < 4; ++j) {
    for (int i = 0; i < 4; ++i) {
      if (i >= 2 || j >= 2) {
        EXPECT_EQ(parent.at(i, j)[3], 0);
      }
    }
  }
}

TEST(TextureTile, UniformChildrenGiveTheSameUniformParent) {
  vsm::core::TextureTile child(4);
  for (std::size_t k = 0; k < child.texels().size(); ++k) {
    child.texels()[k] = static_cast<std::uint8_t>(k % 4 == 3 ? 255 : 77 + k % 4);
  }
  const vsm::core::TextureTile parent =
      vsm::core::downsampleQuadrants({&child, &child, &child, &child}, 4);
  for (std::size_t k = 0; k < parent.texels().size(); ++k) {
    EXPECT_EQ(parent.texels()[k], child.texels()[k]);
  }
}

TEST(TextureTile, SampleBilinearIsExactAtCentresAndSkipsTransparentTexels) {
  vsm::core::TextureTile tile(4);
  for (int j = 0; j < 4; ++j) {
    for (int i = 0; i < 4; ++i) {
      std::uint8_t* t = tile.at(i, j);
      t[0] = static_cast<std::uint8_t>(10 * i), t[1] = static_cast<std::uint8_t>(20 * j), t[2] = 7;
      t[3] = 255;
    }
  }
  tile.at(3, 3)[3] = 0;  // one transparent texel
  using Rgba = std::array<std::uint8_t, 4>;
  EXPECT_EQ(vsm::core::sampleBilinear(tile, 1, 2), (Rgba{10, 40, 7, 255}));
  // Halfway between texel centres: the mean (exact for this linear ramp).
  EXPECT_EQ(vsm::core::sampleBilinear(tile, 1.5, 0.5), (Rgba{15, 10, 7, 255}));
  // Outside the tile: the border texels.
  EXPECT_EQ(vsm::core::sampleBilinear(tile, -3, -1), (Rgba{0, 0, 7, 255}));
  // Next to the transparent texel its weight goes to the opaque ones.
  EXPECT_EQ(vsm::core::sampleBilinear(tile, 2.5, 2.5), (Rgba{23, 47, 7, 255}));
  EXPECT_EQ(vsm::core::sampleBilinear(tile, 3, 3), (Rgba{0, 0, 0, 0}));
}

namespace vsm::core {
namespace {

/// A 5 x 5 grid of the plane z = a x + b y (1 m lattice, +z up, +x east, +y north) placed by
/// `local2global` (a rotation of the whole plane and translation moves the frame with it).
PatchGrid plane(double a, double b, const Mat4d& local2global = Mat4d::identity()) {
  PatchGrid grid(5, local2global);
  for (int y = 0; y < 5; ++y) {
    for (int x = 0; x < 5; ++x) {
      grid.setLocal(x, y, {float(x), float(y), float(a * x + b * y)});
    }
  }
  return grid;
}

/// Lambert's law for the plane z = a x + b y under the sun at azimuth 315, altitude 45 degrees
/// (east-north-up): the sun vector is (-1/2, 1/2, sqrt(1/2)).
double lambert(double a, double b) {
  const double n = std::sqrt(a * a + b * b + 1);
  return 255 * std::max(0.0, (a * 0.5 - b * 0.5 + std::sqrt(0.5)) / n);
}

TEST(ShadedRelief, AFlatSurfaceIsLitAtTheSunsAltitude) {
  const TextureTile tile = shadedRelief(plane(0, 0));
  ASSERT_EQ(tile.size(), 4);
  for (int j = 0; j < 4; ++j) {
    for (int i = 0; i < 4; ++i) {
      EXPECT_EQ(tile.at(i, j)[0], 180);  // 255 sin 45 degrees
      EXPECT_EQ(tile.at(i, j)[1], 180);
      EXPECT_EQ(tile.at(i, j)[2], 180);
      EXPECT_EQ(tile.at(i, j)[3], 255);
    }
  }
}

TEST(ShadedRelief, SlopesFollowLambertWithTheSunInTheNorthWest) {
  // Rising to the east faces west, towards the sun: brighter; rising to the north darker; a
  // steep face away from the sun is black.
  for (const auto& [a, b] :
       {std::pair{0.5, 0.0}, {-0.5, 0.0}, {0.0, 0.5}, {0.3, -0.7}, {-3.0, 3.0}}) {
    const TextureTile tile = shadedRelief(plane(a, b));
    EXPECT_NEAR(tile.at(1, 2)[0], lambert(a, b), 0.5) << a << " " << b;
  }
  EXPECT_GT(shadedRelief(plane(0.5, 0)).at(0, 0)[0], 180);
  EXPECT_LT(shadedRelief(plane(0, 0.5)).at(0, 0)[0], 180);
  EXPECT_EQ(shadedRelief(plane(-3, 3)).at(0, 0)[0], 0);
}

TEST(ShadedRelief, RowOrderDoesNotTurnTheSurfaceUpsideDown) {
  // Rows running south (as rasters do) give the same shading for the same surface.
  PatchGrid grid(5, Mat4d::identity());
  for (int y = 0; y < 5; ++y) {
    for (int x = 0; x < 5; ++x) {
      grid.setLocal(x, y, {float(x), float(-y), float(0.5 * x)});
    }
  }
  EXPECT_NEAR(shadedRelief(grid).at(2, 2)[0], lambert(0.5, 0), 0.5);
}

TEST(ShadedRelief, UsesTheLocalVerticalOfEarthCentredCoordinates) {
  // A plane tangent to the sphere at lon 90 degrees, lat 0 (ECEF: up +y, east -x, north +z),
  // rising to the east with slope 0.5: Lambert's value of the same slope in a local frame.
  Mat4d m;  // local x -> east (-x), local y -> north (+z), local z -> up (+y)
  m.m = {-1, 0, 0, 0, 0, 0, 1, 6378137, 0, 1, 0, 0, 0, 0, 0, 1};
  EXPECT_NEAR(shadedRelief(plane(0.5, 0, m)).at(2, 2)[0], lambert(0.5, 0), 0.5);
  EXPECT_NEAR(shadedRelief(plane(0, 0.5, m)).at(2, 2)[0], lambert(0, 0.5), 0.5);
}

TEST(ShadedRelief, UsesTheLocalVerticalOfAGridStoredAsATranslation) {
  // The plane of the test above as vsm's importers store ECEF grids: axes as ECEF, local2global
  // a translation (the whole-row path of shadedRelief).
  for (const auto& [a, b] : {std::pair{0.5, 0.0}, {0.0, 0.5}, {-0.3, 0.7}}) {
    PatchGrid grid(5, Mat4d::translation({0, 6378137, 0}));
    for (int y = 0; y < 5; ++y) {
      for (int x = 0; x < 5; ++x) {
        grid.setLocal(x, y, {float(-x), float(a * x + b * y), float(y)});
      }
    }
    EXPECT_NEAR(shadedRelief(grid).at(2, 2)[0], lambert(a, b), 0.5) << a << " " << b;
  }
}

TEST(ShadedRelief, AQuadsGreyDependsOnItsOwnCornersOnly) {
  // Rows with a hole take another path through shadedRelief than whole rows: the quads away from
  // the hole must come out byte for byte the same, in a local and in an ECEF frame.
  for (const Mat4d& frame : {Mat4d::identity(), Mat4d::translation({4.1e6, 7.3e5, 4.8e6})}) {
    PatchGrid whole(9, frame);
    for (int y = 0; y < 9; ++y) {
      for (int x = 0; x < 9; ++x) {
        // A bumpy surface, so that every quad has a grey of its own.
        whole.setLocal(x, y,
                       {float(3 * x + 0.2 * y), float(3 * y - 0.1 * x),
                        float(std::sin(x * 1.3) * 2 + std::cos(y * 0.7) * 3)});
      }
    }
    PatchGrid holed = whole;
    holed.setUndefined(0, 4);  // quads (0, 3) and (0, 4) become triangles
    const TextureTile a = shadedRelief(whole);
    const TextureTile b = shadedRelief(holed);
    for (int j = 0; j < 8; ++j) {
      for (int i = j == 3 || j == 4 ? 1 : 0; i < 8; ++i) {
        EXPECT_EQ(std::memcmp(a.at(i, j), b.at(i, j), 4), 0) << i << " " << j;
      }
    }
    EXPECT_EQ(b.at(0, 3)[3], 255);  // the triangles are shaded too
  }
}

TEST(ShadedRelief, QuadsWithFewerThanThreeCornersAreTransparent) {
  PatchGrid grid = plane(0.5, 0);
  grid.setUndefined(1, 1);  // quads (0,0), (1,0), (0,1), (1,1) lose a corner: triangles
  grid.setUndefined(4, 4);
  grid.setUndefined(3, 4);  // quad (3, 3) keeps two corners
  const TextureTile tile = shadedRelief(grid);
  EXPECT_EQ(tile.at(0, 0)[3], 255);
  EXPECT_NEAR(tile.at(0, 0)[0], lambert(0.5, 0), 0.5);  // the triangle lies in the same plane
  EXPECT_EQ(tile.at(3, 3)[3], 0);
  EXPECT_EQ(tile.at(3, 3)[0], 0);
  EXPECT_EQ(tile.at(2, 2)[3], 255);
}

}  // namespace
}  // namespace vsm::core
