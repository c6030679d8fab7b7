// core/tiles/quantized_mesh and the terrain routes' wire mapping. A test executable of its own
// beside tiles_test (the 3D Tiles half of core/tiles), so that the two halves change apart.
#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <numbers>
#include <vector>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/pyramid/model.hpp"
#include "core/tiles/heights.hpp"
#include "core/tiles/quantized_mesh.hpp"
#include "core/tiles/terrain_footprints.hpp"
#include "core/tiles/terrain_rgb.hpp"
#include "core/tiles/top_down.hpp"
#include "server/api/terrain_routes.hpp"

namespace vsm::core {
namespace {

using nlohmann::json;

// ---- a reader of quantized-mesh-1.0, from the spec (github.com/CesiumGS/quantized-mesh) --------

struct Reader {
  const std::vector<std::byte>& b;
  std::size_t at = 0;
  template <typename T>
  T get() {
    T v;
    EXPECT_LE(at + sizeof v, b.size());
    std::memcpy(&v, b.data() + at, sizeof v);
    at += sizeof v;
    return v;
  }
};

struct Decoded {
  double centre[3], sphere[4], horizon[3];
  float minH = 0, maxH = 0;
  std::vector<int> u, v, h;
  std::vector<int> indices;
  std::vector<int> edges[4];  // west, south, east, north
  std::vector<std::uint8_t> normals;
  std::string metadata;
};

int zigZagDecode(int value) {
  return (value >> 1) ^ (-(value & 1));
}

Decoded decode(const std::vector<std::byte>& bytes) {
  Decoded d;
  Reader r{bytes};
  for (double& c : d.centre)
    c = r.get<double>();
  d.minH = r.get<float>();
  d.maxH = r.get<float>();
  for (double& s : d.sphere)
    s = r.get<double>();
  for (double& p : d.horizon)
    p = r.get<double>();
  const auto n = r.get<std::uint32_t>();
  for (auto* array : {&d.u, &d.v, &d.h}) {
    int value = 0;
    for (std::uint32_t i = 0; i < n; ++i) {
      value += zigZagDecode(r.get<std::uint16_t>());
      array->push_back(value);
    }
  }
  if (r.at % 2 != 0)
    ++r.at;
  const auto triangles = r.get<std::uint32_t>();
  int highest = 0;
  for (std::uint32_t i = 0; i < triangles * 3; ++i) {
    const int code = r.get<std::uint16_t>();
    d.indices.push_back(highest - code);
    if (code == 0)
      ++highest;
  }
  for (auto& edge : d.edges) {
    const auto count = r.get<std::uint32_t>();
    for (std::uint32_t i = 0; i < count; ++i)
      edge.push_back(r.get<std::uint16_t>());
  }
  while (r.at < bytes.size()) {
    const auto id = r.get<std::uint8_t>();
    const auto length = r.get<std::uint32_t>();
    if (id == 1) {
      for (std::uint32_t i = 0; i < length; ++i)
        d.normals.push_back(r.get<std::uint8_t>());
    } else if (id == 4) {
      const auto jsonLength = r.get<std::uint32_t>();
      EXPECT_EQ(jsonLength + 4, length);
      d.metadata.assign(reinterpret_cast<const char*>(bytes.data()) + r.at, jsonLength);
      r.at += jsonLength;
    } else {
      r.at += length;
    }
  }
  EXPECT_EQ(r.at, bytes.size());
  return d;
}

// ---- a synthetic height field: h linear in lon/lat, so interpolation is exact -----------------

constexpr double kWest = -100.0, kSouth = 40.0, kSpan = 0.5;

double heightAt(double lon, double lat) {
  return 100.0 + 200.0 * (lon - kWest) + 300.0 * (lat - kSouth);
}

/// A size x size grid of the synthetic surface over the square of `side` degrees whose north-west
/// corner is (west, north), row 0 north: in ECEF, or else in a local frame (lon and lat in km).
std::shared_ptr<PatchGrid> gridOver(int size, double west, double north, double side, bool ecef) {
  Box3d box;
  std::vector<Vec3d> points;
  for (int j = 0; j < size; ++j) {
    for (int i = 0; i < size; ++i) {
      const double lon = west + side * i / (size - 1);
      const double lat = north - side * j / (size - 1);
      points.push_back(ecef ? geodeticToEcef(lon, lat, heightAt(lon, lat))
                            : Vec3d{lon * 1000, lat * 1000, heightAt(lon, lat)});
      box.extend(points.back());
    }
  }
  auto grid = std::make_shared<PatchGrid>(size, originFor(box));
  for (int j = 0; j < size; ++j) {
    for (int i = 0; i < size; ++i) {
      grid->setGlobal(i, j, points[static_cast<std::size_t>(j) * size + i]);
    }
  }
  return grid;
}

struct GeoModel {
  static constexpr int kSize = 33;
  Model model{kSize};
  std::shared_ptr<const PatchGrid> root;

  explicit GeoModel(bool ecef = true) {
    const auto grid = gridOver(kSize, kWest, kSouth + kSpan, kSpan, ecef);
    PatchInfo info;
    info.key = PatchKey::root();
    model.insert(info);
    model.describe(info.key, *grid);
    root = grid;
  }
  TerrainGridLoader loader() const {
    return [this](const PatchInfo&) { return root; };
  }
};

// A level-10 tile well inside the synthetic patch, and its eastern neighbour.
constexpr TerrainTileKey kInside{10, 456, 740};
constexpr TerrainTileKey kEastOfInside{10, 457, 740};

TEST(TerrainTiling, LevelZeroIsTwoTilesOfHalfTheGlobe) {
  EXPECT_TRUE((TerrainTileKey{0, 0, 0}.valid()));
  EXPECT_TRUE((TerrainTileKey{0, 1, 0}.valid()));
  EXPECT_FALSE((TerrainTileKey{0, 2, 0}.valid()));
  EXPECT_FALSE((TerrainTileKey{0, 0, 1}.valid()));
  EXPECT_TRUE((TerrainTileKey{3, 15, 7}.valid()));
  EXPECT_FALSE((TerrainTileKey{3, 16, 7}.valid()));
  EXPECT_FALSE((TerrainTileKey{25, 0, 0}.valid()));
  const GeoRect west = terrainTileRect({0, 0, 0});
  EXPECT_EQ(west.west, -180);
  EXPECT_EQ(west.east, 0);
  EXPECT_EQ(west.south, -90);
  EXPECT_EQ(west.north, 90);
  const GeoRect ne = terrainTileRect({1, 3, 1});
  EXPECT_EQ(ne.west, 90);
  EXPECT_EQ(ne.east, 180);
  EXPECT_EQ(ne.south, 0);
  EXPECT_EQ(ne.north, 90);
}

TEST(TerrainTiling, NeighboursShareTheirEdgeCoordinatesExactly) {
  for (std::uint32_t x = 0; x + 1 < 2048; x += 37) {
    EXPECT_EQ(terrainTileRect({10, x, 5}).east, terrainTileRect({10, x + 1, 5}).west);
    EXPECT_EQ(terrainVertexLon(10, x, 64), terrainVertexLon(10, x + 1, 0));
    EXPECT_EQ(terrainVertexLon(10, x, 63), terrainVertexLon(10, x + 1, -1));
  }
  EXPECT_EQ(terrainVertexLat(10, 5, 64), terrainVertexLat(10, 6, 0));
  EXPECT_NEAR(terrainVertexSpacing(0), std::numbers::pi * 6378137.0 / 64, 1e-6);
  EXPECT_NEAR(terrainVertexSpacing(3) * 8, terrainVertexSpacing(0), 1e-6);
}

TEST(TerrainTiling, GeodeticRoundTrips) {
  for (const auto& [lon, lat, h] :
       {std::tuple{-84.2, 36.3, 512.0}, {10.0, -45.0, -30.0}, {179.9, 89.0, 4000.0}}) {
    const Vec3d g = ecefToGeodetic(geodeticToEcef(lon, lat, h));
    EXPECT_NEAR(g.x, lon, 1e-9);
    EXPECT_NEAR(g.y, lat, 1e-9);
    EXPECT_NEAR(g.z, h, 1e-4);
  }
}

TEST(OctEncoding, RoundTripsWithinOneDegree) {
  for (double a = 0; a < 6.28; a += 0.37) {
    for (double b = -1.5; b < 1.5; b += 0.29) {
      const Vec3d n{std::cos(b) * std::cos(a), std::cos(b) * std::sin(a), std::sin(b)};
      const auto e = octEncode(n);
      const Vec3d d = octDecode(e[0], e[1]);
      EXPECT_NEAR(d.norm(), 1, 1e-12);
      EXPECT_GT(d.x * n.x + d.y * n.y + d.z * n.z, std::cos(1.0 * std::numbers::pi / 180));
    }
  }
}

TEST(TerrainLayer, AvailabilityFollowsTheResolutionRule) {
  const GeoModel geo;
  const TerrainLayer layer = buildTerrainLayer(geo.model, geo.loader());
  ASSERT_TRUE(layer.heightField) << layer.reason;
  ASSERT_FALSE(layer.available.empty());
  EXPECT_EQ(layer.available[0], (std::vector<TileRange>{{0, 0, 1, 0}}));
  const double resolution = geo.model.at(PatchKey::root()).resolution;
  int expected = 0;
  while (expected < TerrainTileKey::kMaxLevel &&
         resolution <= 2 * terrainVertexSpacing(expected + 1)) {
    ++expected;
  }
  EXPECT_EQ(layer.maxZoom, expected);
  EXPECT_EQ(static_cast<int>(layer.available.size()), expected + 1);
  EXPECT_NEAR(layer.bounds.west, kWest, 1e-6);            // float32 positions: ~1 mm
  EXPECT_NEAR(layer.bounds.east, kWest + kSpan, 1e-6);    // float32 positions: ~1 mm
  EXPECT_NEAR(layer.bounds.south, kSouth, 1e-6);          // float32 positions: ~1 mm
  EXPECT_NEAR(layer.bounds.north, kSouth + kSpan, 1e-6);  // float32 positions: ~1 mm
  // Every available tile meets the data; its parent is available; tiles far away are not.
  for (int z = 1; z <= layer.maxZoom; ++z) {
    for (const TileRange& r : layer.available[static_cast<std::size_t>(z)]) {
      for (std::uint32_t y = r.startY; y <= r.endY; ++y) {
        for (std::uint32_t x = r.startX; x <= r.endX; ++x) {
          EXPECT_TRUE(terrainTileRect({z, x, y}).intersects(layer.bounds));
          EXPECT_TRUE(layer.isAvailable({z - 1, x / 2, y / 2}));
        }
      }
    }
  }
  EXPECT_FALSE(layer.isAvailable({3, 0, 0}));
  EXPECT_TRUE(layer.isAvailable({0, 0, 0}));
  EXPECT_TRUE(layer.isAvailable({0, 1, 0}));
  // The metadata extension names the available children only.
  const json meta = json::parse(terrainMetadataJson(layer, {layer.maxZoom - 1, 0, 0}));
  EXPECT_EQ(meta["available"], json::array());
}

TEST(TerrainLayer, ASparsePatchCountsNoFinerThanItsGridCanBe) {
  // Only every fourth vertex of every fourth row defined: no defined neighbours, resolution 0.
  GeoModel geo;
  auto sparse = std::make_shared<PatchGrid>(*geo.root);
  for (int j = 0; j < GeoModel::kSize; ++j) {
    for (int i = 0; i < GeoModel::kSize; ++i) {
      if (i % 4 != 0 || j % 4 != 0) {
        sparse->setUndefined(i, j);
      }
    }
  }
  Model model{GeoModel::kSize};
  PatchInfo info;
  info.key = PatchKey::root();
  model.insert(info);
  model.describe(info.key, *sparse);
  ASSERT_EQ(model.at(PatchKey::root()).resolution, 0);
  const TerrainLayer layer = buildTerrainLayer(
      model, [&](const PatchInfo&) -> std::shared_ptr<const PatchGrid> { return sparse; });
  ASSERT_TRUE(layer.heightField) << layer.reason;
  // Half of the 0.5 deg side over 32 cells: ~870 m, so about level 8, not level 24.
  EXPECT_GE(layer.maxZoom, 7);
  EXPECT_LE(layer.maxZoom, 9);
}

TEST(TerrainLayer, ASurfaceThatFoldsOverItselfIsNoHeightField) {
  // An overhang: the eastern half of the grid runs back west over the western half, 500 m higher.
  constexpr int kSize = GeoModel::kSize;
  Box3d box;
  std::vector<Vec3d> points;
  for (int j = 0; j < kSize; ++j) {
    for (int i = 0; i < kSize; ++i) {
      const int folded = i <= kSize / 2 ? i : kSize - 1 - i;
      const double lon = kWest + kSpan * folded / (kSize - 1);
      const double lat = kSouth + kSpan - kSpan * j / (kSize - 1);
      points.push_back(geodeticToEcef(lon, lat, i <= kSize / 2 ? 100.0 : 600.0));
      box.extend(points.back());
    }
  }
  auto grid = std::make_shared<PatchGrid>(kSize, originFor(box));
  for (int j = 0; j < kSize; ++j) {
    for (int i = 0; i < kSize; ++i) {
      grid->setGlobal(i, j, points[static_cast<std::size_t>(j) * kSize + i]);
    }
  }
  Model model{kSize};
  PatchInfo info;
  info.key = PatchKey::root();
  model.insert(info);
  model.describe(info.key, *grid);
  const TerrainLayer layer = buildTerrainLayer(
      model, [&](const PatchInfo&) -> std::shared_ptr<const PatchGrid> { return grid; });
  EXPECT_FALSE(layer.heightField);
  EXPECT_NE(layer.reason.find("folds over itself"), std::string::npos) << layer.reason;
}

TEST(TerrainLayer, AModelInALocalFrameIsNoHeightField) {
  const GeoModel local(false);
  const TerrainLayer layer = buildTerrainLayer(local.model, local.loader());
  EXPECT_FALSE(layer.heightField);
  EXPECT_NE(layer.reason.find("not earth-centred"), std::string::npos) << layer.reason;
  EXPECT_TRUE(terrainSources(local.model, layer, kInside).empty());
}

/// A full quadtree of depth 2 over the synthetic surface: each patch's grid covers its share of
/// the 0.5 degree square at its own spacing.
struct GeoPyramid {
  static constexpr int kSize = 17;
  using Grids = std::map<PatchKey, std::shared_ptr<const PatchGrid>>;
  Model model{kSize};
  Grids grids;

  /// `scale` moves every vertex that much farther from the earth's centre: another model with the
  /// same keys, versions and folders, and other data and boxes.
  explicit GeoPyramid(double scale = 1.0) {
    for (int depth = 0; depth <= 2; ++depth) {
      for (std::uint32_t y = 0; y < (1u << depth); ++y) {
        for (std::uint32_t x = 0; x < (1u << depth); ++x) {
          const PatchKey key{depth, x, y};
          PatchInfo info;
          info.key = key;
          model.insert(info);
          auto grid = gridOf(key);
          for (int j = 0; scale != 1.0 && j < kSize; ++j) {
            for (int i = 0; i < kSize; ++i) {
              grid->setGlobal(i, j, grid->global(i, j) * scale);
            }
          }
          grids[key] = grid;
        }
      }
    }
    for (int depth = 2; depth >= 0; --depth) {  // children first: a box holds theirs
      for (const auto& [key, grid] : grids) {
        if (key.depth == depth) {
          model.describe(key, *grid);
        }
      }
    }
  }
  static std::shared_ptr<PatchGrid> gridOf(const PatchKey& key) {
    const double side = kSpan / (1 << key.depth);
    const double west = kWest + side * key.x;
    const double north = kSouth + kSpan - side * key.y;
    return gridOver(kSize, west, north, side, true);
  }
};

TEST(Footprints, CopiesShareTheBaseSeeOnlyTheirOwnChangesAndCompactToTheSameContent) {
  const auto rectOf = [](int i, int round) {
    return GeoRect{i * 0.1, round * 0.1, i * 0.1 + 1, round * 0.1 + 1};
  };
  // Keys 0..199 at depth 8; a reference map beside each Footprints.
  const auto keyOf = [](int i) { return PatchKey{8, static_cast<std::uint32_t>(i), 3}; };
  Footprints a;
  std::map<PatchKey, GeoRect> ra;
  for (int i = 0; i < 200; ++i) {
    a.set(keyOf(i), rectOf(i, 0));
    ra[keyOf(i)] = rectOf(i, 0);
  }
  a.compact();
  const auto expectHolds = [&](const Footprints& f, const std::map<PatchKey, GeoRect>& r,
                               const std::string& when) {
    EXPECT_EQ(f.size(), r.size()) << when;
    for (int i = -5; i < 260; ++i) {
      const GeoRect* got = f.find(keyOf(i));
      const auto want = r.find(keyOf(i));
      ASSERT_EQ(got != nullptr, want != r.end()) << when << " key " << i;
      if (got != nullptr) {
        EXPECT_EQ(*got, want->second) << when << " key " << i;
      }
    }
  };
  expectHolds(a, ra, "built");
  // Rounds of changes on a copy (the next version's layer): sets, new keys and erasures, some of
  // a key set in the same round; every few rounds the changes pass 1/32 and compact() folds them.
  Footprints b = a;
  std::map<PatchKey, GeoRect> rb = ra;
  for (int round = 1; round <= 12; ++round) {
    for (int j = 0; j < 3; ++j) {
      const int i = (round * 37 + j * 11) % 250;
      b.set(keyOf(i), rectOf(i, round));
      rb[keyOf(i)] = rectOf(i, round);
    }
    const int gone = (round * 53) % 250;
    b.erase(keyOf(gone));
    rb.erase(keyOf(gone));
    b.erase(keyOf(-1));  // never there
    b.compact();
    expectHolds(b, rb, "round " + std::to_string(round));
    expectHolds(a, ra, "the copy's source after round " + std::to_string(round));
  }
}

/// The same footprint for every patch of `model` (and no other), availability and levels.
void expectSameLayer(const TerrainLayer& a, const TerrainLayer& b, const Model& model) {
  ASSERT_EQ(a.footprint.size(), b.footprint.size());
  std::size_t found = 0;
  for (const auto& [key, info] : model.patches()) {
    const GeoRect* rect = a.footprint.find(key);
    const GeoRect* other = b.footprint.find(key);
    ASSERT_EQ(rect == nullptr, other == nullptr) << key.toString();
    if (rect != nullptr) {
      EXPECT_EQ(*rect, *other) << key.toString();
      ++found;
    }
  }
  EXPECT_EQ(found, a.footprint.size()) << "a footprint of a patch not in the model";
  EXPECT_EQ(a.available, b.available);
  EXPECT_EQ(a.maxZoom, b.maxZoom);
}

/// A loader of what `model` has attached, else of `grids`, that records the keys it loads into
/// `read`.
TerrainGridLoader countingLoader(const Model& model, const GeoPyramid::Grids& grids,
                                 std::vector<PatchKey>& read) {
  return [&model, &grids, &read](const PatchInfo& info) -> std::shared_ptr<const PatchGrid> {
    read.push_back(info.key);
    std::shared_ptr<const PatchGrid> attached = model.grid(info.key);
    return attached ? attached : grids.at(info.key);
  };
}

/// A merge's new version of `before`: `leaf` loses its western half (its footprint and its
/// ancestors' change), its ancestors are reduced again; every other patch is the same.
Model withWesternHalfCut(const GeoPyramid& before, const PatchKey& leaf) {
  Model after = before.model;
  auto cut = GeoPyramid::gridOf(leaf);
  for (int j = 0; j < GeoPyramid::kSize; ++j) {
    for (int i = 0; i < GeoPyramid::kSize / 2; ++i) {
      cut->setUndefined(i, j);
    }
  }
  after.setGrid(leaf, cut);
  after.refreshStale([&](const PatchInfo& info) { return before.grids.at(info.key); });
  return after;
}

TEST(TerrainLayer, ANewVersionReadsOnlyItsChangedPatchesAndGivesTheFullBuildsLayer) {
  const GeoPyramid before;
  std::vector<PatchKey> read;
  const auto loaderOf = [&](const Model& model, const GeoPyramid::Grids& grids) {
    return countingLoader(model, grids, read);
  };
  const TerrainLayer first = buildTerrainLayer(before.model, loaderOf(before.model, before.grids));
  ASSERT_TRUE(first.heightField) << first.reason;
  EXPECT_EQ(read.size(), 22u) << "every patch, and the root once more for the height field check";

  // A merge's new version: leaf 2_1_2 loses its western half (its footprint and its ancestors'
  // change), its ancestors are reduced again; every other patch is the same.
  const PatchKey leaf{2, 1, 2};
  const Model after = withWesternHalfCut(before, leaf);
  read.clear();
  const TerrainLayerBase base{before.model, first};
  const TerrainLayer incremental = buildTerrainLayer(after, loaderOf(after, before.grids), &base);
  std::sort(read.begin(), read.end());
  read.erase(std::unique(read.begin(), read.end()), read.end());
  EXPECT_EQ(read, (std::vector<PatchKey>{PatchKey::root(), {1, 0, 1}, leaf}))
      << "the changed leaf and its ancestors only";
  read.clear();
  const TerrainLayer full = buildTerrainLayer(after, loaderOf(after, before.grids));
  EXPECT_EQ(read.size(), 22u);
  expectSameLayer(incremental, full, after);
  EXPECT_GT(full.footprint.find(leaf)->west, first.footprint.find(leaf)->west + kSpan / 4 / 3)
      << "the cut shows in the layer";

  // A base of another model (same keys, versions and folders, other boxes) is not taken.
  const GeoPyramid other(1.0001);
  read.clear();
  const TerrainLayer unrelated =
      buildTerrainLayer(other.model, loaderOf(other.model, other.grids), &base);
  EXPECT_EQ(read.size(), 22u);
  read.clear();
  expectSameLayer(unrelated, buildTerrainLayer(other.model, loaderOf(other.model, other.grids)),
                  other.model);
}

// The first layer of a process at 10^6 patches read every patch (minutes): footprints saved by an
// earlier build stand for the patches they were saved for, and for those only.
TEST(TerrainLayer, SavedFootprintsStandForThePatchesTheyWereSavedForAndOnlyThose) {
  const GeoPyramid before;
  std::vector<PatchKey> read;
  const auto loaderOf = [&](const Model& model, const GeoPyramid::Grids& grids) {
    return countingLoader(model, grids, read);
  };
  const TerrainLayer first = buildTerrainLayer(before.model, loaderOf(before.model, before.grids));
  ASSERT_TRUE(first.heightField) << first.reason;
  const std::vector<std::byte> bytes = SavedFootprints::encode(before.model, first);
  ASSERT_EQ(bytes.size(), 24 + 21 * SavedFootprints::kRecordBytes + 8) << "21 footprints";
  const SavedFootprints saved(bytes, GeoPyramid::kSize);
  EXPECT_EQ(saved.size(), 21u);

  // The same version: no patch read but the root's height field check.
  read.clear();
  const TerrainLayer again =
      buildTerrainLayer(before.model, loaderOf(before.model, before.grids), nullptr, &saved);
  EXPECT_EQ(read, std::vector<PatchKey>{PatchKey::root()});
  expectSameLayer(again, first, before.model);

  // A later version (leaf 2_1_2 cut in half, its ancestors reduced again): that leaf and its
  // ancestors are read, and the layer is the full build's.
  const PatchKey leaf{2, 1, 2};
  const Model after = withWesternHalfCut(before, leaf);
  read.clear();
  const TerrainLayer later =
      buildTerrainLayer(after, loaderOf(after, before.grids), nullptr, &saved);
  std::sort(read.begin(), read.end());
  read.erase(std::unique(read.begin(), read.end()), read.end());
  EXPECT_EQ(read, (std::vector<PatchKey>{PatchKey::root(), {1, 0, 1}, leaf}));
  expectSameLayer(later, buildTerrainLayer(after, loaderOf(after, before.grids)), after);

  // Another model with the same keys, versions and folders but other data (its boxes differ):
  // every patch is read.
  const GeoPyramid other(1.0001);
  read.clear();
  const TerrainLayer unrelated =
      buildTerrainLayer(other.model, loaderOf(other.model, other.grids), nullptr, &saved);
  EXPECT_EQ(read.size(), 22u);
  expectSameLayer(unrelated, buildTerrainLayer(other.model, loaderOf(other.model, other.grids)),
                  other.model);

  // Damage is refused, saying what is wrong: each byte flipped in turn, a cut, another grid size.
  for (std::size_t i = 0; i < bytes.size(); i += 7) {
    std::vector<std::byte> damaged = bytes;
    damaged[i] ^= std::byte{0x20};
    EXPECT_THROW(SavedFootprints(std::move(damaged), GeoPyramid::kSize), Error) << "byte " << i;
  }
  EXPECT_THROW(
      SavedFootprints(std::vector<std::byte>(bytes.begin(), bytes.end() - 9), GeoPyramid::kSize),
      Error);
  EXPECT_THROW(
      SavedFootprints(std::vector<std::byte>(bytes.begin(), bytes.begin() + 20), GeoPyramid::kSize),
      Error);
  try {
    SavedFootprints(bytes, 33);
    ADD_FAILURE() << "another grid size taken";
  } catch (const Error& e) {
    EXPECT_EQ(e.code(), ErrorCode::Corrupt);
    EXPECT_NE(std::string(e.what()).find("33"), std::string::npos) << e.what();
  }
}

TEST(TerrainLayer, ByTheChangeItFollowsNewFinerLevelsAndTheirRemovalAsTheFullBuildDoes) {
  const GeoPyramid before;
  std::map<PatchKey, std::shared_ptr<const PatchGrid>> grids = before.grids;
  const auto load = [&](const PatchInfo& info) -> std::shared_ptr<const PatchGrid> {
    return grids.at(info.key);
  };
  const TerrainLayer first = buildTerrainLayer(before.model, load);
  ASSERT_TRUE(first.heightField) << first.reason;

  // Detail below leaf 2_3_0 (the north-east corner): two levels of finer patches, so the layer
  // gains levels there and only there.
  Model deeper = before.model;
  const PatchKey corner{2, 3, 0};
  std::vector<PatchKey> added;
  for (const Quadrant q : kQuadrants) {
    added.push_back(corner.child(q));
    if (q == Quadrant::SW) {
      for (const Quadrant r : kQuadrants) {
        added.push_back(corner.child(q).child(r));
      }
    }
  }
  std::sort(added.begin(), added.end());
  for (const PatchKey& key : added) {
    PatchInfo info;
    info.key = key;
    deeper.insert(info);
  }
  for (auto it = added.rbegin(); it != added.rend(); ++it) {
    grids[*it] = GeoPyramid::gridOf(*it);
    deeper.setGrid(*it, grids[*it]);
  }
  deeper.refreshStale(load);
  const TerrainLayerBase fromFirst{before.model, first};
  const TerrainLayer grown = buildTerrainLayer(deeper, load, &fromFirst);
  const TerrainLayer grownFull = buildTerrainLayer(deeper, load);
  expectSameLayer(grown, grownFull, deeper);
  EXPECT_EQ(grown.maxZoom, first.maxZoom + 2) << "two finer levels of patches";
  // The new levels hold the corner's tiles only, and each coarser level its old tiles too.
  const GeoRect detail = *grownFull.footprint.find(corner);
  for (int z = first.maxZoom + 1; z <= grown.maxZoom; ++z) {
    for (const TileRange& r : grown.available[static_cast<std::size_t>(z)]) {
      EXPECT_TRUE(terrainTileRect({z, r.startX, r.startY}).intersects(detail));
      EXPECT_TRUE(terrainTileRect({z, r.endX, r.endY}).intersects(detail));
    }
  }
  for (int z = 0; z <= first.maxZoom; ++z) {
    for (const TileRange& r : first.available[static_cast<std::size_t>(z)]) {
      EXPECT_TRUE(grown.isAvailable({z, r.startX, r.startY}));
      EXPECT_TRUE(grown.isAvailable({z, r.endX, r.endY}));
    }
  }

  // The detail removed again (leaves first): the layer is the first one's, level for level.
  Model removed = deeper;
  for (auto it = added.rbegin(); it != added.rend(); ++it) {
    removed.eraseLeaf(*it);
  }
  removed.setGrid(corner, before.grids.at(corner));
  removed.refreshStale(load);
  const TerrainLayerBase fromGrown{deeper, grown};
  const TerrainLayer shrunk = buildTerrainLayer(removed, load, &fromGrown);
  expectSameLayer(shrunk, buildTerrainLayer(removed, load), removed);
  EXPECT_EQ(shrunk.available, first.available);
}

TEST(TerrainSampling, HeightsInterpolateTheSurfaceAndAreZeroOutside) {
  const GeoModel geo;
  const TerrainLayer layer = buildTerrainLayer(geo.model, geo.loader());
  const auto sources = terrainSources(geo.model, layer, kInside);
  ASSERT_EQ(sources, std::vector<PatchKey>{PatchKey::root()});
  const TerrainHeights t = sampleTerrain(geo.model, sources, kInside, geo.loader());
  EXPECT_EQ(t.covered, 65u * 65u);
  for (int j = -1; j <= 65; ++j) {
    for (int i = -1; i <= 65; ++i) {
      const double lon = terrainVertexLon(10, kInside.x, i),
                   lat = terrainVertexLat(10, kInside.y, j);
      ASSERT_NEAR(t.at(i, j), heightAt(lon, lat), 2e-3) << i << "," << j;
    }
  }
  // A tile outside the model: no sources, flat at 0.
  const TerrainTileKey far{10, 100, 100};
  EXPECT_TRUE(terrainSources(geo.model, layer, far).empty());
  const TerrainHeights flat = sampleTerrain(geo.model, {}, far, geo.loader());
  EXPECT_EQ(flat.covered, 0u);
  const Decoded d = decode(encodeQuantizedMesh(flat));
  EXPECT_EQ(d.minH, 0);
  EXPECT_EQ(d.maxH, 0);
}

TEST(QuantizedMesh, EncodesTheSpecsLayoutAndInvariants) {
  const GeoModel geo;
  const TerrainLayer layer = buildTerrainLayer(geo.model, geo.loader());
  const TerrainHeights t =
      sampleTerrain(geo.model, terrainSources(geo.model, layer, kInside), kInside, geo.loader());
  const Decoded d = decode(encodeQuantizedMesh(t, {.normals = true, .metadata = "{\"a\":1}"}));
  ASSERT_EQ(d.u.size(), 65u * 65u);
  EXPECT_EQ(d.indices.size(), 64u * 64u * 6);
  EXPECT_EQ(d.normals.size(), 65u * 65u * 2);
  EXPECT_EQ(d.metadata, "{\"a\":1}");
  const GeoRect rect = terrainTileRect(kInside);
  std::vector<int> onEdge[4];
  double maxError = 0;
  for (std::size_t k = 0; k < d.u.size(); ++k) {
    ASSERT_GE(d.u[k], 0);
    ASSERT_LE(d.u[k], 32767);
    ASSERT_GE(d.v[k], 0);
    ASSERT_LE(d.v[k], 32767);
    ASSERT_GE(d.h[k], 0);
    ASSERT_LE(d.h[k], 32767);
    if (d.u[k] == 0)
      onEdge[0].push_back(static_cast<int>(k));
    if (d.v[k] == 0)
      onEdge[1].push_back(static_cast<int>(k));
    if (d.u[k] == 32767)
      onEdge[2].push_back(static_cast<int>(k));
    if (d.v[k] == 32767)
      onEdge[3].push_back(static_cast<int>(k));
    const double lon = rect.west + (rect.east - rect.west) * d.u[k] / 32767.0;
    const double lat = rect.south + (rect.north - rect.south) * d.v[k] / 32767.0;
    const double h = d.minH + (d.maxH - d.minH) * d.h[k] / 32767.0;
    maxError = std::max(maxError, std::abs(h - heightAt(lon, lat)));
    const Vec3d p = geodeticToEcef(lon, lat, h);
    const double dist = std::hypot(p.x - d.sphere[0], p.y - d.sphere[1], p.z - d.sphere[2]);
    EXPECT_LE(dist, d.sphere[3]);
    // Normals: unit, and within a degree of the plane's normal is too strict for a sloped
    // plane on the ellipsoid; within 10 degrees of the ellipsoid normal here (slopes are small).
    const Vec3d n = octDecode(d.normals[k * 2], d.normals[k * 2 + 1]);
    const Vec3d up = geodeticToEcef(lon, lat, 1000) - geodeticToEcef(lon, lat, 0);
    EXPECT_GT((n.x * up.x + n.y * up.y + n.z * up.z) / up.norm(),
              std::cos(10 * std::numbers::pi / 180));
  }
  EXPECT_LT(maxError, (d.maxH - d.minH) / 32767.0 + 2e-3);
  for (int e = 0; e < 4; ++e) {
    std::vector<int> listed = d.edges[e];
    std::sort(listed.begin(), listed.end());
    EXPECT_EQ(listed, onEdge[e]) << "edge " << e;
    EXPECT_EQ(listed.size(), 65u);
  }
  // Triangles: counter-clockwise in (u, v), indices in range.
  for (std::size_t k = 0; k < d.indices.size(); k += 3) {
    const int a = d.indices[k], b = d.indices[k + 1], c = d.indices[k + 2];
    ASSERT_LT(std::max({a, b, c}), 65 * 65);
    const double area =
        double(d.u[b] - d.u[a]) * (d.v[c] - d.v[a]) - double(d.v[b] - d.v[a]) * (d.u[c] - d.u[a]);
    EXPECT_GT(area, 0);
  }
}

TEST(QuantizedMesh, NeighboursAgreeOnTheirSharedEdge) {
  const GeoModel geo;
  const TerrainLayer layer = buildTerrainLayer(geo.model, geo.loader());
  const auto tileOf = [&](const TerrainTileKey& key) {
    return decode(encodeQuantizedMesh(
        sampleTerrain(geo.model, terrainSources(geo.model, layer, key), key, geo.loader()),
        {.normals = true, .metadata = {}}));
  };
  const Decoded w = tileOf(kInside), e = tileOf(kEastOfInside);
  const auto byV = [](const Decoded& d, int edge) {
    std::map<int, std::pair<double, Vec3d>> out;
    for (const int k : d.edges[edge]) {
      out[d.v[k]] = {d.minH + (d.maxH - d.minH) * d.h[k] / 32767.0,
                     octDecode(d.normals[k * 2], d.normals[k * 2 + 1])};
    }
    return out;
  };
  const auto east = byV(w, 2), west = byV(e, 0);
  ASSERT_EQ(east.size(), 65u);
  for (const auto& [v, value] : east) {
    ASSERT_TRUE(west.count(v));
    const double tolerance = (w.maxH - w.minH + e.maxH - e.minH) / 32767.0;
    EXPECT_NEAR(value.first, west.at(v).first, tolerance);
    const Vec3d a = value.second, b = west.at(v).second;
    EXPECT_GT(a.x * b.x + a.y * b.y + a.z * b.z, std::cos(1.5 * std::numbers::pi / 180));
  }
}

// ---- heights for GIS clients (core/tiles/heights.hpp) -------------------------------------------

TEST(Heights, PointsAtVerticesAndBetweenThemFollowTheSurfaceAndAreNaNOutside) {
  const GeoModel geo;
  const TerrainLayer layer = buildTerrainLayer(geo.model, geo.loader());
  std::vector<GeoPoint> points;
  for (int j = 0; j < GeoModel::kSize; j += 4) {
    for (int i = 0; i < GeoModel::kSize; i += 4) {  // vertices, the border included
      points.push_back(
          {kWest + kSpan * i / (GeoModel::kSize - 1), kSouth + kSpan * j / (GeoModel::kSize - 1)});
    }
  }
  points.push_back({kWest + 0.1234, kSouth + 0.321});  // inside a cell
  points.push_back({kWest - 0.01, kSouth + 0.1});      // outside, west
  const auto heights = sampleHeights(geo.model, layer, points, geo.loader());
  ASSERT_EQ(heights.size(), points.size());
  for (std::size_t k = 0; k + 1 < points.size(); ++k) {
    ASSERT_NEAR(heights[k].height, heightAt(points[k].lon, points[k].lat), 2e-3) << k;
    EXPECT_EQ(heights[k].depth, 0);
  }
  EXPECT_TRUE(std::isnan(heights.back().height));
  EXPECT_EQ(heights.back().depth, -1);
}

TEST(Heights, AGridAtTheVerticesIsTheSurfaceAndNaNBeyondIt) {
  const GeoModel geo;
  const TerrainLayer layer = buildTerrainLayer(geo.model, geo.loader());
  const double cell = kSpan / (GeoModel::kSize - 1);
  // Pixel centres on the vertices, and one column of pixels beyond the east edge.
  const TopDownGrid view = heightPicture(
      {kWest - cell / 2, kSouth - cell / 2, kWest + kSpan + 1.5 * cell, kSouth + kSpan + cell / 2},
      cell, 1 << 20);
  ASSERT_EQ(view.width, GeoModel::kSize + 1);
  ASSERT_EQ(view.height, GeoModel::kSize);
  std::vector<float> values(view.pixels());
  // In two strips, as an export samples them.
  sampleHeightGrid(geo.model, layer, pictureRows(view, 0, 10), geo.loader(),
                   std::span(values).first(10 * static_cast<std::size_t>(view.width)));
  sampleHeightGrid(geo.model, layer, pictureRows(view, 10, view.height - 10), geo.loader(),
                   std::span(values).subspan(10 * static_cast<std::size_t>(view.width)));
  for (int row = 0; row < view.height; ++row) {
    for (int col = 0; col < view.width; ++col) {
      const float v = values[static_cast<std::size_t>(row) * view.width + col];
      if (col == GeoModel::kSize) {
        EXPECT_TRUE(std::isnan(v)) << row;
        continue;
      }
      const double lon = kWest + col * cell, lat = kSouth + kSpan - row * cell;
      ASSERT_NEAR(v, heightAt(lon, lat), 2e-3) << row << "," << col;
    }
  }
  EXPECT_THROW(heightPicture({1, 0, 0, 1}, 0.1, 100), Error);    // inverted
  EXPECT_THROW(heightPicture({0, 0, 1, 1}, 0.001, 100), Error);  // too many pixels
  EXPECT_THROW(heightPicture({0, 0, 1, 1}, -1, 100), Error);     // resolution
  // Measured between neighbouring vertices, whose positions are float32 relative to the patch:
  // within about 1e-6 of the cell.
  EXPECT_NEAR(finestSpacingDegrees(geo.model, layer, layer.bounds, geo.loader()), cell,
              cell * 1e-6);
}

// ---- terrain-RGB: Web Mercator tiles of encoded heights -----------------------------------------

// The slippy-map formulas (OpenStreetMap wiki), written here apart from the code under test.
double tileLon(double x, int z) {
  return x / std::ldexp(1.0, z) * 360.0 - 180.0;
}
double tileLat(double y, int z) {
  return std::atan(std::sinh(std::numbers::pi * (1 - 2 * y / std::ldexp(1.0, z)))) * 180.0 /
         std::numbers::pi;
}

TEST(MercatorTiling, TilesFollowTheSlippyMapScheme) {
  EXPECT_TRUE((MercatorTileKey{0, 0, 0}.valid()));
  EXPECT_FALSE((MercatorTileKey{0, 1, 0}.valid()));
  EXPECT_FALSE((MercatorTileKey{1, 0, 2}.valid()));
  EXPECT_TRUE((MercatorTileKey{24, (1u << 24) - 1, 0}.valid()));
  EXPECT_FALSE((MercatorTileKey{25, 0, 0}.valid()));
  const GeoRect world = mercatorTileRect({0, 0, 0});
  EXPECT_NEAR(world.west, -180, 1e-12);
  EXPECT_NEAR(world.east, 180, 1e-12);
  EXPECT_NEAR(world.north, 85.0511287798066, 1e-9);
  EXPECT_NEAR(world.south, -85.0511287798066, 1e-9);
  for (const MercatorTileKey key :
       {MercatorTileKey{1, 0, 0}, MercatorTileKey{7, 34, 50}, MercatorTileKey{15, 7000, 12345}}) {
    const GeoRect r = mercatorTileRect(key);
    EXPECT_NEAR(r.west, tileLon(key.x, key.z), 1e-9) << key.toString();
    EXPECT_NEAR(r.east, tileLon(key.x + 1, key.z), 1e-9) << key.toString();
    EXPECT_NEAR(r.north, tileLat(key.y, key.z), 1e-9) << key.toString();
    EXPECT_NEAR(r.south, tileLat(key.y + 1, key.z), 1e-9) << key.toString();
  }
  // 156,543 m per pixel at level 0 on the equator: 4.6 km data gets level 6 (2,446 m pixels),
  // and at 60 degrees, where pixels are half as large on the ground, level 5.
  EXPECT_EQ(mercatorLevelFor(4600, 0), 6);
  EXPECT_EQ(mercatorLevelFor(4600, 60), 5);
  EXPECT_EQ(mercatorLevelFor(0, 0), 0);
  EXPECT_EQ(mercatorLevelFor(1e-6, 0), MercatorTileKey::kMaxLevel);
}

TEST(DemEncoding, PacksHeightsAsTheFormatsSpecify) {
  // Terrarium: h = R * 256 + G + B / 256 - 32768.  Mapbox: h = -10000 + (R 65536 + G 256 + B) / 10.
  EXPECT_EQ(encodeDemHeight(0, DemEncoding::Terrarium), (std::array<std::uint8_t, 3>{128, 0, 0}));
  EXPECT_EQ(encodeDemHeight(0, DemEncoding::Mapbox), (std::array<std::uint8_t, 3>{1, 134, 160}));
  EXPECT_EQ(encodeDemHeight(-32768, DemEncoding::Terrarium),
            (std::array<std::uint8_t, 3>{0, 0, 0}));
  EXPECT_EQ(encodeDemHeight(1e9, DemEncoding::Mapbox),
            (std::array<std::uint8_t, 3>{255, 255, 255}));
  EXPECT_EQ(encodeDemHeight(-1e9, DemEncoding::Mapbox), (std::array<std::uint8_t, 3>{0, 0, 0}));
  for (const double h : {-412.7, 0.001, 123.456, 4321.0, 8848.86}) {
    const auto t = encodeDemHeight(h, DemEncoding::Terrarium);
    EXPECT_NEAR(t[0] * 256.0 + t[1] + t[2] / 256.0 - 32768, h, 0.5 / 256 + 1e-9) << h;
    EXPECT_NEAR(decodeDemHeight(t[0], t[1], t[2], DemEncoding::Terrarium), h, 0.5 / 256 + 1e-9);
    const auto m = encodeDemHeight(h, DemEncoding::Mapbox);
    EXPECT_NEAR(-10000 + (m[0] * 65536.0 + m[1] * 256.0 + m[2]) / 10, h, 0.05 + 1e-9) << h;
    EXPECT_NEAR(decodeDemHeight(m[0], m[1], m[2], DemEncoding::Mapbox), h, 0.05 + 1e-9);
  }
  EXPECT_EQ(demEncodingMin(DemEncoding::Terrarium), -32768);
  EXPECT_EQ(demEncodingMin(DemEncoding::Mapbox), -10000);
}

TEST(DemTile, PixelCentresGetTheSurfaceAndNoDataOutsideIt) {
  const GeoModel geo;
  const TerrainLayer layer = buildTerrainLayer(geo.model, geo.loader());
  const int z = 12;
  const auto column = [&](double lon) {
    return static_cast<std::uint32_t>((lon + 180) / 360 * std::ldexp(1.0, z));
  };
  const auto row = [&](double lat) {
    const double phi = lat * std::numbers::pi / 180;
    return static_cast<std::uint32_t>((1 - std::asinh(std::tan(phi)) / std::numbers::pi) / 2 *
                                      std::ldexp(1.0, z));
  };
  // A tile inside the patch, and one over its western edge.
  const MercatorTileKey inside{z, column(kWest + 0.25), row(kSouth + 0.25)};
  const MercatorTileKey edge{z, column(kWest), row(kSouth + 0.25)};
  for (const DemEncoding encoding : {DemEncoding::Terrarium, DemEncoding::Mapbox}) {
    for (const MercatorTileKey key : {inside, edge}) {
      const std::vector<PatchKey> sources = demTileSources(geo.model, layer, key);
      ASSERT_EQ(sources, std::vector<PatchKey>{PatchKey::root()});
      const double nodata = -123.4;
      const DemTile tile = sampleDemTile(geo.model, sources, key, geo.loader(), encoding, nodata);
      ASSERT_EQ(tile.rgb.size(), std::size_t{3} * kDemTileSize * kDemTileSize);
      const double step = encoding == DemEncoding::Terrarium ? 1.0 / 256 : 0.1;
      std::size_t covered = 0;
      for (int j = 0; j < kDemTileSize; ++j) {
        for (int i = 0; i < kDemTileSize; ++i) {
          const double lon = tileLon(key.x + (i + 0.5) / kDemTileSize, z);
          const double lat = tileLat(key.y + (j + 0.5) / kDemTileSize, z);
          const std::uint8_t* p = &tile.rgb[(static_cast<std::size_t>(j) * kDemTileSize + i) * 3];
          const double h = decodeDemHeight(p[0], p[1], p[2], encoding);
          const bool in = lon > kWest + 1e-9 && lat > kSouth && lat < kSouth + kSpan;
          covered += in;
          // Linear in lon/lat, sampled barycentrically in the Mercator plane over cells of 0.016
          // degrees: a few tenths of a millimetre apart.
          ASSERT_NEAR(h, in ? heightAt(lon, lat) : nodata, step / 2 + 2e-3)
              << key.toString() << " " << i << "," << j;
        }
      }
      EXPECT_EQ(tile.covered, covered) << key.toString();
      EXPECT_GT(covered, 0u);
    }
  }
}

TEST(Heights, APathIsSampledEvenlyByDistanceFromEndToEnd) {
  const std::vector<GeoPoint> path{{0, 0}, {1, 0}, {1, 1}};
  const auto samples = samplePath(path, 5);
  ASSERT_EQ(samples.size(), 5u);
  const double leg = greatCircleDistance({0, 0}, {1, 0});
  EXPECT_NEAR(leg, 111195.08, 0.01);  // one degree on the mean radius
  EXPECT_EQ(samples.front().distance, 0);
  EXPECT_DOUBLE_EQ(samples.back().point.lon, 1);
  EXPECT_DOUBLE_EQ(samples.back().point.lat, 1);
  for (std::size_t k = 1; k < samples.size(); ++k) {
    EXPECT_GT(samples[k].distance, samples[k - 1].distance);
  }
  // The middle sample lies at the corner (the two legs are about equally long).
  EXPECT_NEAR(samples[2].point.lon, 1, 1e-3);
  EXPECT_NEAR(samples[2].point.lat, 0, 1e-3);
  EXPECT_EQ(samplePath(std::vector<GeoPoint>{{3, 4}}, 10).size(), 1u);
}

}  // namespace
}  // namespace vsm::core

namespace vsm::server::api {
namespace {

TEST(TerrainRoutes, AcceptHeaderSelectsTheExtensions) {
  const auto cesium = parseTerrainAccept(
      "application/vnd.quantized-mesh;extensions=octvertexnormals-metadata,"
      "application/octet-stream;q=0.9,*/*;q=0.01");
  EXPECT_TRUE(cesium.normals);
  EXPECT_TRUE(cesium.metadata);
  const auto plain = parseTerrainAccept("application/vnd.quantized-mesh,application/octet-stream");
  EXPECT_FALSE(plain.normals);
  EXPECT_FALSE(plain.metadata);
  const auto meta = parseTerrainAccept("application/vnd.quantized-mesh; extensions=metadata");
  EXPECT_FALSE(meta.normals);
  EXPECT_TRUE(meta.metadata);
  EXPECT_TRUE(
      parseTerrainAccept("application/vnd.quantized-mesh;extensions=vertexnormals").normals);
  EXPECT_FALSE(parseTerrainAccept("text/plain;extensions=octvertexnormals").normals);
  EXPECT_FALSE(parseTerrainAccept("").normals);
}

TEST(TerrainRoutes, LayerJsonNamesTheSchemeAndTemplate) {
  core::TerrainLayer layer;
  layer.heightField = true;
  layer.bounds = {-1, -2, 3, 4};
  layer.available = {{{0, 0, 1, 0}}, {{1, 1, 1, 1}}};
  layer.maxZoom = 1;
  const nlohmann::json j = terrainLayerJson("m", layer, 7, 7);
  EXPECT_EQ(j["format"], "quantized-mesh-1.0");
  EXPECT_EQ(j["scheme"], "tms");
  EXPECT_EQ(j["projection"], "EPSG:4326");
  EXPECT_EQ(j["tiles"][0], "{z}/{x}/{y}.terrain?v=7&rev=7");
  EXPECT_EQ(j["model_version"], 7);
  // The tiles' URL names the model version itself, not CesiumJS's "{version}" template.
  EXPECT_EQ(terrainLayerJson("m", layer, 12)["tiles"][0], "{z}/{x}/{y}.terrain?v=12");
  EXPECT_EQ(j["maxzoom"], 1);
  EXPECT_EQ(j["available"][1][0]["startX"], 1);
  EXPECT_EQ(j["bounds"], nlohmann::json::array({-1.0, -2.0, 3.0, 4.0}));
}

}  // namespace
}  // namespace vsm::server::api
