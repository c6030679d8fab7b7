#include <gtest/gtest.h>
#include <meshoptimizer.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <map>
#include <memory>
#include <nlohmann/json.hpp>
#include <numbers>
#include <set>
#include <string>
#include <vector>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/pyramid/model.hpp"
#include "core/tiles/glb.hpp"
#include "core/tiles/lod_cut.hpp"
#include "core/tiles/lod_render.hpp"
#include "core/tiles/tile_tree.hpp"
#include "server/api/tiles_routes.hpp"
#include "tests/unit/test_support.hpp"

namespace vsm::core {
namespace {

using nlohmann::json;

// ---- an independent GLB reader (glTF 2.0, "GLB File Format Specification") ---------------------

std::uint32_t u32(const std::vector<std::byte>& b, std::size_t at) {
  std::uint32_t v = 0;
  for (int i = 3; i >= 0; --i) {
    v = v << 8 | std::to_integer<std::uint32_t>(b.at(at + i));
  }
  return v;
}

struct DecodedGlb {
  json gltf;
  std::vector<std::byte> bin;
  std::uint32_t jsonChunkLength = 0;

  /// The accessor's elements as doubles (components interleaved); checks that it lies in its view.
  std::vector<double> read(int accessorIndex) const {
    const json& a = gltf["accessors"][accessorIndex];
    const json& view = gltf["bufferViews"][a["bufferView"].get<int>()];
    const int type = a["componentType"];
    const std::string kind = a["type"];
    const std::size_t components = kind == "SCALAR" ? 1 : kind == "VEC2" ? 2 : 3;
    const std::size_t size = type == 5126 || type == 5125 ? 4 : type == 5123 ? 2 : 0;
    EXPECT_NE(size, 0u);
    const std::size_t count = a["count"];
    const std::size_t offset = view.value("byteOffset", 0) + a.value("byteOffset", 0);
    EXPECT_EQ(offset % size, 0u) << "accessor " << accessorIndex << " misaligned";
    EXPECT_LE(count * components * size, view["byteLength"].get<std::size_t>());
    EXPECT_LE(offset + count * components * size, bin.size());
    std::vector<double> out(count * components);
    for (std::size_t i = 0; i < out.size(); ++i) {
      const std::byte* p = bin.data() + offset + i * size;
      if (type == 5126) {
        float f;
        std::memcpy(&f, p, 4);
        out[i] = f;
      } else if (type == 5125) {
        std::uint32_t v;
        std::memcpy(&v, p, 4);
        out[i] = v;
      } else {
        std::uint16_t v;
        std::memcpy(&v, p, 2);
        out[i] = v;
      }
    }
    return out;
  }
};

DecodedGlb decodeGlb(const std::vector<std::byte>& glb) {
  DecodedGlb out;
  EXPECT_GE(glb.size(), 20u);
  EXPECT_EQ(u32(glb, 0), 0x46546C67u) << "magic glTF";
  EXPECT_EQ(u32(glb, 4), 2u) << "version";
  EXPECT_EQ(u32(glb, 8), glb.size()) << "length";
  EXPECT_EQ(glb.size() % 4, 0u);
  out.jsonChunkLength = u32(glb, 12);
  EXPECT_EQ(u32(glb, 16), 0x4E4F534Au) << "first chunk JSON";
  EXPECT_EQ(out.jsonChunkLength % 4, 0u);
  const auto* text = reinterpret_cast<const char*>(glb.data() + 20);
  out.gltf = json::parse(std::string(text, out.jsonChunkLength));
  const std::size_t next = 20 + out.jsonChunkLength;
  if (next < glb.size()) {
    const std::uint32_t length = u32(glb, next);
    EXPECT_EQ(u32(glb, next + 4), 0x004E4942u) << "second chunk BIN";
    EXPECT_EQ(length % 4, 0u);
    EXPECT_EQ(next + 8 + length, glb.size());
    out.bin.assign(glb.begin() + static_cast<std::ptrdiff_t>(next + 8), glb.end());
    EXPECT_EQ(out.gltf["buffers"][0]["byteLength"].get<std::size_t>(), out.bin.size());
  }
  return out;
}

// ---- synthetic data ----------------------------------------------------------------------------

// Terrain in ECEF near lon -84.25, lat 36.3 (Jacksboro): a local east/north/up frame, 10 m grid.
constexpr double kLat = 36.3 * std::numbers::pi / 180, kLon = -84.25 * std::numbers::pi / 180;
const Vec3d kEast{-std::sin(kLon), std::cos(kLon), 0};
const Vec3d kNorth{-std::sin(kLat) * std::cos(kLon), -std::sin(kLat) * std::sin(kLon),
                   std::cos(kLat)};
const Vec3d kUp{std::cos(kLat) * std::cos(kLon), std::cos(kLat) * std::sin(kLon), std::sin(kLat)};
const Vec3d kOrigin = kUp * 6371000.0;

Vec3d terrain(double east, double north) {
  const double h = 300 + 40 * std::sin(east * 0.01) + 25 * std::cos(north * 0.013);
  return kOrigin + kEast * east + kNorth * north + kUp * h;
}

/// A size x size grid with 10 m spacing, rows running north to south; `undefined(x, y)` marks
/// holes.
template <typename Hole>
PatchGrid terrainGrid(int size, Hole undefined) {
  Box3d box;
  for (int y = 0; y < size; y += size - 1) {
    for (int x = 0; x < size; x += size - 1) {
      box.extend(terrain(10.0 * x, -10.0 * y));
    }
  }
  PatchGrid grid(size, originFor(box));
  for (int y = 0; y < size; ++y) {
    for (int x = 0; x < size; ++x) {
      if (!undefined(x, y)) {
        grid.setGlobal(x, y, terrain(10.0 * x, -10.0 * y));
      }
    }
  }
  return grid;
}

Vec3d dot3(const Vec3d& a, const Vec3d& b) {
  return {a.x * b.x, a.y * b.y, a.z * b.z};
}
double dot(const Vec3d& a, const Vec3d& b) {
  const Vec3d p = dot3(a, b);
  return p.x + p.y + p.z;
}

/// Checks everything the tileset and the validator need of one GLB of `grid`, decoded
/// independently; returns the decoded asset.
DecodedGlb checkGlb(const PatchGrid& grid, const Vec3d& centre) {
  const std::vector<std::byte> bytes = encodeGlb(grid, centre);
  DecodedGlb glb = decodeGlb(bytes);
  const json& gltf = glb.gltf;
  EXPECT_EQ(gltf["asset"]["version"], "2.0");
  const int n = grid.size();
  std::size_t quads = 0;
  for (int y = 0; y + 1 < n; ++y) {
    for (int x = 0; x + 1 < n; ++x) {
      quads += grid.defined(x, y) && grid.defined(x + 1, y) && grid.defined(x, y + 1) &&
               grid.defined(x + 1, y + 1);
    }
  }
  if (quads == 0) {
    EXPECT_FALSE(gltf.contains("meshes"));
    return glb;
  }
  const json& primitive = gltf["meshes"][0]["primitives"][0];
  EXPECT_EQ(primitive.value("mode", 4), 4);
  const int positionAccessor = primitive["attributes"]["POSITION"];
  const int normalAccessor = primitive["attributes"]["NORMAL"];
  const int uvAccessor = primitive["attributes"]["TEXCOORD_0"];
  const int indexAccessor = primitive["indices"];
  const std::vector<double> positions = glb.read(positionAccessor);
  const std::vector<double> normals = glb.read(normalAccessor);
  const std::vector<double> uvs = glb.read(uvAccessor);
  const std::vector<double> indices = glb.read(indexAccessor);
  const std::size_t count = positions.size() / 3;

  // Every accessor's min/max are exactly the extremes of its data.
  for (const int accessor : {positionAccessor, normalAccessor, uvAccessor, indexAccessor}) {
    const json& a = gltf["accessors"][accessor];
    const std::vector<double> data = glb.read(accessor);
    const std::size_t components = a["min"].size();
    EXPECT_GT(components, 0u);
    for (std::size_t c = 0; c < components; ++c) {
      double lo = std::numeric_limits<double>::infinity(), hi = -lo;
      for (std::size_t i = c; i < data.size(); i += components) {
        lo = std::min(lo, data[i]);
        hi = std::max(hi, data[i]);
      }
      EXPECT_EQ(a["min"][c].get<double>(), lo) << "accessor " << accessor;
      EXPECT_EQ(a["max"][c].get<double>(), hi) << "accessor " << accessor;
    }
  }
  for (const int view : {0, 1, 2, 3}) {
    EXPECT_EQ(gltf["bufferViews"][view]["byteOffset"].get<std::size_t>() % 4, 0u);
  }

  // Two triangles per complete quad; no index past the vertices, no unused vertex.
  EXPECT_EQ(indices.size(), quads * 6);
  std::set<std::size_t> usedVertices;
  for (const double i : indices) {
    EXPECT_LT(i, static_cast<double>(count));
    usedVertices.insert(static_cast<std::size_t>(i));
  }
  EXPECT_EQ(usedVertices.size(), count);
  const int expectedIndexType = count <= 65535 ? 5123 : 5125;
  EXPECT_EQ(gltf["accessors"][indexAccessor]["componentType"], expectedIndexType);

  // Each vertex: its grid position from TEXCOORD_0, that grid vertex defined, the position equal
  // to it (y-up axes, relative to the centre) up to float32 rounding, the normal a unit vector.
  std::vector<std::pair<int, int>> gridOf(count);
  for (std::size_t v = 0; v < count; ++v) {
    const double gx = uvs[v * 2] * (n - 1), gy = uvs[v * 2 + 1] * (n - 1);
    const int x = static_cast<int>(std::lround(gx)), y = static_cast<int>(std::lround(gy));
    EXPECT_NEAR(gx, x, 1e-4);
    EXPECT_NEAR(gy, y, 1e-4);
    if (x < 0 || x >= n || y < 0 || y >= n) {
      ADD_FAILURE() << "vertex " << v << " outside the grid";
      continue;
    }
    EXPECT_TRUE(grid.defined(x, y))
        << "vertex " << v << " is undefined grid vertex " << x << "," << y;
    gridOf[v] = {x, y};
    const Vec3d expected = grid.global(x, y) - centre;
    const Vec3d zUp{positions[v * 3], -positions[v * 3 + 2], positions[v * 3 + 1]};
    const double tolerance = 1e-6 * (expected.norm() + 1);
    EXPECT_NEAR(zUp.x, expected.x, tolerance);
    EXPECT_NEAR(zUp.y, expected.y, tolerance);
    EXPECT_NEAR(zUp.z, expected.z, tolerance);
    const double length =
        std::sqrt(normals[v * 3] * normals[v * 3] + normals[v * 3 + 1] * normals[v * 3 + 1] +
                  normals[v * 3 + 2] * normals[v * 3 + 2]);
    EXPECT_NEAR(length, 1.0, 1e-6);
  }
  // Triangles connect grid neighbours within one quad.
  for (std::size_t t = 0; t < indices.size(); t += 3) {
    int minX = n, maxX = -1, minY = n, maxY = -1;
    for (int k = 0; k < 3; ++k) {
      const auto [x, y] = gridOf[static_cast<std::size_t>(indices[t + k])];
      minX = std::min(minX, x);
      maxX = std::max(maxX, x);
      minY = std::min(minY, y);
      maxY = std::max(maxY, y);
    }
    EXPECT_EQ(maxX - minX, 1);
    EXPECT_EQ(maxY - minY, 1);
  }
  return glb;
}

TEST(Glb, EncodesEveryCompleteQuadAndNothingUndefined) {
  const PatchGrid grid = terrainGrid(17, [](int x, int y) {
    return (x == 3 && y == 4) || (y == 10 && x > 8) || x == 16;  // a hole, a ragged edge, a column
  });
  const DecodedGlb glb = checkGlb(grid, grid.globalBox().center());
  EXPECT_EQ(glb.gltf["meshes"][0]["primitives"][0]["material"], 0);
  EXPECT_TRUE(glb.gltf["materials"][0]["doubleSided"].get<bool>());
}

TEST(Glb, NormalsPointUpAndTrianglesWindCounterClockwiseFromAbove) {
  const PatchGrid grid = terrainGrid(9, [](int, int) { return false; });
  const Vec3d centre = grid.globalBox().center();
  const DecodedGlb glb = checkGlb(grid, centre);
  const std::vector<double> p = glb.read(0), normals = glb.read(1), indices = glb.read(3);
  const auto zUp = [](const std::vector<double>& v, std::size_t i) {
    return Vec3d{v[i * 3], -v[i * 3 + 2], v[i * 3 + 1]};
  };
  for (std::size_t v = 0; v < normals.size() / 3; ++v) {
    EXPECT_GT(dot(zUp(normals, v), kUp), 0.9);
  }
  for (std::size_t t = 0; t < indices.size(); t += 3) {
    const Vec3d a = zUp(p, static_cast<std::size_t>(indices[t]));
    const Vec3d b = zUp(p, static_cast<std::size_t>(indices[t + 1]));
    const Vec3d c = zUp(p, static_cast<std::size_t>(indices[t + 2]));
    const Vec3d u = b - a, w = c - a;
    const Vec3d face{u.y * w.z - u.z * w.y, u.z * w.x - u.x * w.z, u.x * w.y - u.y * w.x};
    EXPECT_GT(dot(face, kUp), 0);
  }
}

TEST(Glb, LargeGridsUseUnsignedIntIndices) {
  const PatchGrid grid = terrainGrid(257, [](int x, int y) { return x + y < 20; });
  checkGlb(grid, grid.globalBox().center());
}

TEST(Glb, GridWithoutCompleteQuadIsAValidEmptyAsset) {
  const PatchGrid grid = terrainGrid(9, [](int x, int y) { return (x + y) % 2 == 1; });
  const DecodedGlb glb = checkGlb(grid, grid.globalBox().center());
  EXPECT_TRUE(glb.bin.empty());
  EXPECT_EQ(glb.gltf["scenes"].size(), 1u);
}

TEST(Glb, NonFiniteVerticesCountAsUndefined) {
  PatchGrid grid = terrainGrid(5, [](int, int) { return false; });
  const Vec3d centre = grid.globalBox().center();
  grid.setLocal(2, 2, {std::numeric_limits<float>::infinity(), 0, 0});
  const DecodedGlb glb = decodeGlb(encodeGlb(grid, centre));
  EXPECT_EQ(glb.read(3).size(), (16u - 4u) * 6);
  for (const int accessor : {0, 1, 2}) {
    for (const double v : glb.read(accessor)) {
      EXPECT_TRUE(std::isfinite(v));
    }
  }
}

TEST(Glb, TextureHookEmbedsTheImageAndCoordinates) {
  const PatchGrid grid = terrainGrid(5, [](int, int) { return false; });
  const std::vector<std::byte> image(37, std::byte{0xab});
  std::vector<float> texcoords(grid.vertexCount() * 2);
  for (std::size_t i = 0; i < texcoords.size(); ++i) {
    texcoords[i] = static_cast<float>(i % 7) / 8;
  }
  GlbOptions options;
  options.texture = {image, "image/png"};
  options.texcoords = texcoords;
  const DecodedGlb glb = decodeGlb(encodeGlb(grid, grid.globalBox().center(), options));
  const json& gltf = glb.gltf;
  ASSERT_EQ(gltf["images"].size(), 1u);
  EXPECT_EQ(gltf["images"][0]["mimeType"], "image/png");
  const json& view = gltf["bufferViews"][gltf["images"][0]["bufferView"].get<int>()];
  EXPECT_EQ(view["byteLength"], 37);
  EXPECT_EQ(view["byteOffset"].get<std::size_t>() % 4, 0u);
  EXPECT_EQ(glb.bin.at(view["byteOffset"].get<std::size_t>()), std::byte{0xab});
  EXPECT_EQ(gltf["materials"][0]["pbrMetallicRoughness"]["baseColorTexture"]["index"], 0);
  const std::vector<double> uvs = glb.read(2);
  EXPECT_EQ(uvs[2], texcoords[2]);  // vertex 1 = grid vertex 1: all are used
  EXPECT_THROW(
      encodeGlb(grid, {0, 0, 0}, {.texture = {}, .texcoords = std::span(texcoords).first(3)}),
      Error);
}

// ---- the compressed encoding: decoded with meshoptimizer's own decoder ------------------------

/// The attribute or index data of a GLB whose views may be EXT_meshopt_compression views, decoded
/// to doubles as glTF says a loader reads them (normalized integers to [-1, 1] or [0, 1]).
struct MeshoptGlb {
  DecodedGlb glb;
  std::map<int, std::vector<std::byte>> decodedViews;

  explicit MeshoptGlb(const std::vector<std::byte>& bytes) : glb(decodeGlb(bytes)) {}

  const std::vector<std::byte>& view(int index) {
    auto found = decodedViews.find(index);
    if (found != decodedViews.end()) {
      return found->second;
    }
    const json& view = glb.gltf["bufferViews"][index];
    std::vector<std::byte> out(view["byteLength"].get<std::size_t>());
    if (view.contains("extensions") && view["extensions"].contains("EXT_meshopt_compression")) {
      const json& ext = view["extensions"]["EXT_meshopt_compression"];
      EXPECT_EQ(ext["buffer"], 0);
      EXPECT_EQ(view["buffer"], 1) << "decodes into the fallback buffer";
      const std::size_t offset = ext["byteOffset"], length = ext["byteLength"];
      const std::size_t count = ext["count"], stride = ext["byteStride"];
      EXPECT_EQ(count * stride, out.size());
      EXPECT_LE(offset + length, glb.bin.size());
      const auto* source = reinterpret_cast<const unsigned char*>(glb.bin.data() + offset);
      const std::string mode = ext["mode"];
      EXPECT_EQ(ext.value("filter", "NONE"), "NONE");
      int rc = -1;
      if (mode == "ATTRIBUTES") {
        EXPECT_EQ(view["byteStride"], stride);
        rc = meshopt_decodeVertexBuffer(out.data(), count, stride, source, length);
      } else {
        EXPECT_EQ(mode, "TRIANGLES");
        EXPECT_FALSE(view.contains("byteStride"));
        rc = meshopt_decodeIndexBuffer(out.data(), count, stride, source, length);
      }
      EXPECT_EQ(rc, 0) << "meshopt decode of view " << index;
    } else {
      EXPECT_EQ(view["buffer"], 0);
      const std::size_t offset = view.value("byteOffset", 0);
      std::memcpy(out.data(), glb.bin.data() + offset, out.size());
    }
    return decodedViews.emplace(index, std::move(out)).first->second;
  }

  std::vector<double> read(int accessorIndex) {
    const json& a = glb.gltf["accessors"][accessorIndex];
    const int viewIndex = a["bufferView"];
    const std::vector<std::byte>& data = view(viewIndex);
    const int type = a["componentType"];
    const bool normalized = a.value("normalized", false);
    const std::string kind = a["type"];
    const std::size_t components = kind == "SCALAR" ? 1 : kind == "VEC2" ? 2 : 3;
    const std::size_t size = type == 5126 || type == 5125 ? 4 : type == 5123 ? 2 : 1;
    const std::size_t stride =
        glb.gltf["bufferViews"][viewIndex].value("byteStride", components * size);
    const std::size_t count = a["count"];
    EXPECT_LE((count - 1) * stride + components * size, data.size());
    std::vector<double> out(count * components);
    for (std::size_t i = 0; i < count; ++i) {
      for (std::size_t c = 0; c < components; ++c) {
        const std::byte* p = data.data() + a.value("byteOffset", 0) + i * stride + c * size;
        double value = 0;
        if (type == 5126) {
          float f;
          std::memcpy(&f, p, 4);
          value = f;
        } else if (type == 5125) {
          std::uint32_t v;
          std::memcpy(&v, p, 4);
          value = v;
        } else if (type == 5123) {
          std::uint16_t v;
          std::memcpy(&v, p, 2);
          value = normalized ? v / 65535.0 : v;
        } else {
          EXPECT_EQ(type, 5120);
          std::int8_t v;
          std::memcpy(&v, p, 1);
          value = normalized ? std::max(v / 127.0, -1.0) : v;
        }
        out[i * components + c] = value;
      }
    }
    return out;
  }
};

/// A triangle as its indices, rotated to start at its smallest (winding kept).
std::array<std::uint32_t, 3> canonical(double a, double b, double c) {
  std::array<std::uint32_t, 3> t{static_cast<std::uint32_t>(a), static_cast<std::uint32_t>(b),
                                 static_cast<std::uint32_t>(c)};
  while (t[0] > t[1] || t[0] > t[2]) {
    t = {t[1], t[2], t[0]};
  }
  return t;
}

/// Encodes `grid` both ways and checks that the compressed GLB decodes (meshoptimizer's decoder,
/// the node's translation and scale) to the uncompressed one within the quantization steps.
/// Returns the two sizes.
std::pair<std::size_t, std::size_t> checkCompressed(const PatchGrid& grid, GlbOptions options) {
  const Vec3d centre = grid.globalBox().center();
  options.compression = GlbCompression::None;
  const std::vector<std::byte> plainBytes = encodeGlb(grid, centre, options);
  options.compression = GlbCompression::Meshopt;
  const std::vector<std::byte> packedBytes = encodeGlb(grid, centre, options);
  const DecodedGlb plain = decodeGlb(plainBytes);
  MeshoptGlb packed(packedBytes);
  const json& gltf = packed.glb.gltf;

  EXPECT_EQ(gltf["extensionsUsed"],
            json::array({"EXT_meshopt_compression", "KHR_mesh_quantization"}));
  EXPECT_EQ(gltf["extensionsRequired"], gltf["extensionsUsed"]);
  EXPECT_EQ(gltf["buffers"].size(), 2u);
  EXPECT_FALSE(gltf["buffers"][1].contains("uri"));
  EXPECT_TRUE(gltf["buffers"][1]["extensions"]["EXT_meshopt_compression"]["fallback"].get<bool>());
  for (const json& view : gltf["bufferViews"]) {
    EXPECT_EQ(view["byteOffset"].get<std::size_t>() % 4, 0u);
    if (view["buffer"] == 1) {
      EXPECT_LE(view["byteOffset"].get<std::size_t>() + view["byteLength"].get<std::size_t>(),
                gltf["buffers"][1]["byteLength"].get<std::size_t>());
      EXPECT_EQ(view["extensions"]["EXT_meshopt_compression"]["byteOffset"].get<std::size_t>() % 4,
                0u);
    }
  }
  const json& attributes = gltf["meshes"][0]["primitives"][0]["attributes"];
  const json& node = gltf["nodes"][0];
  EXPECT_EQ(gltf["accessors"][attributes["POSITION"].get<int>()]["componentType"], 5123);
  EXPECT_EQ(gltf["accessors"][attributes["NORMAL"].get<int>()]["componentType"], 5120);
  const std::vector<double> q = packed.read(attributes["POSITION"]);
  const std::vector<double> normals = packed.read(attributes["NORMAL"]);
  const std::vector<double> uvs = packed.read(attributes["TEXCOORD_0"]);
  const std::vector<double> indices = packed.read(gltf["meshes"][0]["primitives"][0]["indices"]);
  const std::vector<double> plainPositions = plain.read(0), plainNormals = plain.read(1),
                            plainUvs = plain.read(2), plainIndices = plain.read(3);

  // The same vertices in the same order.
  EXPECT_EQ(q.size(), plainPositions.size());
  EXPECT_EQ(uvs.size(), plainUvs.size());
  EXPECT_EQ(indices.size(), plainIndices.size());
  const double scale = node["scale"][0];
  EXPECT_EQ(node["scale"][1], scale);
  EXPECT_EQ(node["scale"][2], scale);
  const json& positionAccessor = gltf["accessors"][attributes["POSITION"].get<int>()];
  const json& plainAccessor = plain.gltf["accessors"][0];
  double largestError = 0;
  for (std::size_t i = 0; i < std::min(q.size(), plainPositions.size()); ++i) {
    const std::size_t c = i % 3;
    const double position = node["translation"][c].get<double>() + q[i] * scale;
    const double expected = plainPositions[i];
    // Within one step (rounding, or clamping at the top of the range) and float32's rounding of
    // the plain encoding.
    EXPECT_NEAR(position, expected, scale * 1.0001 + 1e-6 * std::abs(expected) + 1e-9) << i;
    largestError = std::max(largestError, std::abs(position - expected));
    // Inside the plain encoding's range, so inside the tile's box.
    const double slack = 1e-6 * (std::abs(expected) + 1);
    EXPECT_GE(position, plainAccessor["min"][c].get<double>() - slack);
    EXPECT_LE(position, plainAccessor["max"][c].get<double>() + slack);
    EXPECT_GE(q[i], positionAccessor["min"][c].get<double>());
    EXPECT_LE(q[i], positionAccessor["max"][c].get<double>());
  }
  EXPECT_GT(largestError, 0) << "the positions are quantized";
  for (std::size_t c = 0; c < 3; ++c) {  // min and max are the data's extremes
    double lo = 65535, hi = 0;
    for (std::size_t i = c; i < q.size(); i += 3) {
      lo = std::min(lo, q[i]);
      hi = std::max(hi, q[i]);
    }
    EXPECT_EQ(positionAccessor["min"][c].get<double>(), lo);
    EXPECT_EQ(positionAccessor["max"][c].get<double>(), hi);
  }
  for (std::size_t i = 0; i < std::min(normals.size(), plainNormals.size()); ++i) {
    EXPECT_NEAR(normals[i], plainNormals[i], 0.5 / 127 + 1e-6) << i;
  }
  const bool quantizedUvs =
      gltf["accessors"][attributes["TEXCOORD_0"].get<int>()]["componentType"] == 5123;
  for (std::size_t i = 0; i < std::min(uvs.size(), plainUvs.size()); ++i) {
    EXPECT_NEAR(uvs[i], plainUvs[i], quantizedUvs ? 0.5 / 65535 + 1e-7 : 0.0) << i;
  }
  // The same triangles, each with its winding (the codec may rotate and reorder them).
  std::multiset<std::array<std::uint32_t, 3>> triangles, plainTriangles;
  for (std::size_t t = 0; t + 2 < indices.size(); t += 3) {
    triangles.insert(canonical(indices[t], indices[t + 1], indices[t + 2]));
  }
  for (std::size_t t = 0; t + 2 < plainIndices.size(); t += 3) {
    plainTriangles.insert(canonical(plainIndices[t], plainIndices[t + 1], plainIndices[t + 2]));
  }
  EXPECT_TRUE(triangles == plainTriangles);
  EXPECT_EQ(
      gltf["accessors"][gltf["meshes"][0]["primitives"][0]["indices"].get<int>()]["componentType"],
      plain.gltf["accessors"][3]["componentType"]);
  // The texture, byte for byte.
  if (!options.texture.image.empty()) {
    const json& view = gltf["bufferViews"][gltf["images"][0]["bufferView"].get<int>()];
    EXPECT_EQ(view["buffer"], 0);
    const std::size_t offset = view["byteOffset"];
    EXPECT_EQ(view["byteLength"].get<std::size_t>(), options.texture.image.size());
    EXPECT_TRUE(offset + options.texture.image.size() <= packed.glb.bin.size() &&
                std::equal(options.texture.image.begin(), options.texture.image.end(),
                           packed.glb.bin.begin() + static_cast<std::ptrdiff_t>(offset)));
  }
  return {packedBytes.size(), plainBytes.size()};
}

TEST(Glb, CompressedDecodesToTheUncompressedMeshWithinTheQuantizationSteps) {
  const PatchGrid grid = terrainGrid(65, [](int x, int y) {
    return (x == 3 && y == 4) || (y == 40 && x > 50) || x == 64;  // a hole, a ragged edge, a column
  });
  std::vector<float> texcoords(grid.vertexCount() * 2);
  for (std::size_t i = 0; i < texcoords.size(); i += 2) {
    texcoords[i] = static_cast<float>((i / 2) % 65) / 64;
    texcoords[i + 1] = static_cast<float>((i / 2) / 65) / 64;
  }
  const std::vector<std::byte> image(41, std::byte{0x5c});
  GlbOptions options;
  options.texture = {image, "image/png"};
  options.texcoords = texcoords;
  const auto [packed, plain] = checkCompressed(grid, options);
  // Smooth terrain: well under a third of the float32 encoding.
  EXPECT_LT(packed * 3, plain) << packed << " bytes against " << plain;
}

TEST(Glb, CompressedLargeGridsKeepUnsignedIntIndices) {
  const PatchGrid grid = terrainGrid(257, [](int x, int y) { return x + y < 20; });
  checkCompressed(grid, {});
}

TEST(Glb, CompressedTexcoordsOutsideTheUnitSquareStayFloat) {
  const PatchGrid grid = terrainGrid(9, [](int, int) { return false; });
  std::vector<float> texcoords(grid.vertexCount() * 2, 0.25f);
  texcoords[7] = 1.5f;
  GlbOptions options;
  options.texcoords = texcoords;
  checkCompressed(grid, options);
  options.compression = GlbCompression::Meshopt;
  const DecodedGlb glb = decodeGlb(encodeGlb(grid, grid.globalBox().center(), options));
  EXPECT_EQ(glb.gltf["accessors"][2]["componentType"], 5126);
}

TEST(Glb, CompressedGridWithoutCompleteQuadIsAValidEmptyAsset) {
  const PatchGrid grid = terrainGrid(9, [](int x, int y) { return (x + y) % 2 == 1; });
  GlbOptions options;
  options.compression = GlbCompression::Meshopt;
  const DecodedGlb glb = decodeGlb(encodeGlb(grid, grid.globalBox().center(), options));
  EXPECT_TRUE(glb.bin.empty());
  EXPECT_FALSE(glb.gltf.contains("extensionsRequired"));
}

// ---- the tile tree and tileset.json -----------------------------------------------------------

/// A three-level model on a 10 m terrain lattice: the root, its four children, and four
/// grandchildren under the north-west child only (a deeper area, as after a merge).
struct Pyramid {
  static constexpr int kSize = 9;
  Model model{kSize};
  std::map<PatchKey, std::shared_ptr<const PatchGrid>> grids;

  Pyramid() {
    // Depth 2 covers the lattice at spacing 1 (x 10 m), patches of 8 cells.
    const auto sampled = [](int step, int x0, int y0) {
      return std::make_shared<PatchGrid>(terrainGridAt(step, x0, y0));
    };
    PatchInfo root;
    root.key = PatchKey::root();
    model.insert(root);
    for (const Quadrant q : kQuadrants) {
      PatchInfo info;
      info.key = root.key.child(q);
      model.insert(info);
    }
    const PatchKey nw = root.key.child(Quadrant::NW);
    for (const Quadrant q : kQuadrants) {
      PatchInfo info;
      info.key = nw.child(q);
      model.insert(info);
      grids[info.key] =
          sampled(1, 8 * static_cast<int>(info.key.x), 8 * static_cast<int>(info.key.y));
    }
    for (const Quadrant q : kQuadrants) {
      const PatchKey key = root.key.child(q);
      grids[key] = sampled(2, 16 * static_cast<int>(key.x), 16 * static_cast<int>(key.y));
    }
    grids[root.key] = sampled(4, 0, 0);
    for (auto it = grids.rbegin(); it != grids.rend(); ++it) {
      model.describe(it->first, *it->second);
    }
  }

  /// Lattice samples x0 + step * i, y0 + step * j.
  static PatchGrid terrainGridAt(int step, int x0, int y0) {
    Box3d box;
    box.extend(terrain(10.0 * x0, -10.0 * y0));
    box.extend(terrain(10.0 * (x0 + step * (kSize - 1)), -10.0 * (y0 + step * (kSize - 1))));
    PatchGrid grid(kSize, originFor(box));
    for (int j = 0; j < kSize; ++j) {
      for (int i = 0; i < kSize; ++i) {
        grid.setGlobal(i, j, terrain(10.0 * (x0 + step * i), -10.0 * (y0 + step * j)));
      }
    }
    return grid;
  }
};

void checkTile(const TileNode& node, const Pyramid& p, int& visited) {
  ++visited;
  const PatchGrid& grid = *p.grids.at(node.key);
  EXPECT_EQ(node.centre, tileCentre(p.model.at(node.key)));
  EXPECT_TRUE(node.box.contains(grid.globalBox())) << node.key.toString();
  if (node.children.empty()) {
    EXPECT_EQ(node.geometricError, 0) << node.key.toString();
  } else {
    EXPECT_GE(node.geometricError, p.model.at(node.key).resolution);
  }
  for (const TileNode& child : node.children) {
    EXPECT_EQ(*child.key.parent(), node.key);
    EXPECT_LT(child.geometricError, node.geometricError);
    EXPECT_TRUE(node.box.contains(child.box)) << child.key.toString();
    checkTile(child, p, visited);
  }
}

TEST(TileTree, ErrorsFallAndBoxesNestFromRootToLeaves) {
  const Pyramid p;
  const TileNode root = buildTileTree(p.model);
  int visited = 0;
  checkTile(root, p, visited);
  EXPECT_EQ(visited, 9);
  EXPECT_EQ(root.children.size(), 4u);
  EXPECT_EQ(root.children[0].children.size(), 4u);
  EXPECT_GT(tilesetGeometricError(root), root.geometricError);
}

/// Whether two tiles agree in key, centre, box and error (not in their children).
void expectSameTile(const TileNode& a, const TileNode& b) {
  EXPECT_EQ(a.key, b.key);
  EXPECT_EQ(a.centre, b.centre) << a.key.toString();
  EXPECT_EQ(a.box.min, b.box.min) << a.key.toString();
  EXPECT_EQ(a.box.max, b.box.max) << a.key.toString();
  EXPECT_EQ(a.geometricError, b.geometricError) << a.key.toString();
}

TEST(TileTree, LevelsCutTheTreeIntoExternalTilesWithTheWholeSubtreesBoxAndError) {
  const Pyramid p;
  const TileNode whole = buildTileTree(p.model);
  EXPECT_FALSE(whole.external);

  // One level: the root and a tile per child, external where the child has children (only NW).
  const TileNode top = buildTileTree(p.model, PatchKey::root(), 1);
  expectSameTile(top, whole);
  ASSERT_EQ(top.children.size(), 4u);
  for (std::size_t i = 0; i < 4; ++i) {
    const TileNode& cut = top.children[i];
    expectSameTile(cut, whole.children[i]);
    EXPECT_TRUE(cut.children.empty());
    EXPECT_EQ(cut.external, !whole.children[i].children.empty()) << cut.key.toString();
  }

  // The external tile's own tree is the whole tree's subtree.
  const PatchKey nw = PatchKey::root().child(Quadrant::NW);
  const TileNode below = buildTileTree(p.model, nw, 1);
  expectSameTile(below, whole.children[0]);
  ASSERT_EQ(below.children.size(), 4u);
  for (std::size_t i = 0; i < 4; ++i) {
    expectSameTile(below.children[i], whole.children[0].children[i]);
    EXPECT_FALSE(below.children[i].external);  // leaves
  }

  // Enough levels leave nothing external.
  const TileNode deep = buildTileTree(p.model, PatchKey::root(), 2);
  ASSERT_EQ(deep.children[0].children.size(), 4u);
  EXPECT_FALSE(deep.children[0].external);

  EXPECT_THROW(buildTileTree(p.model, PatchKey::root(), 0), Error);
  EXPECT_THROW(buildTileTree(p.model, nw.child(Quadrant::SE).child(Quadrant::NW)), Error);
}

TEST(TileTree, ANewVersionTakesTheExtentsOfUnchangedExternalTilesFromThePreviousTree) {
  const Pyramid p;
  const PatchKey nw = PatchKey::root().child(Quadrant::NW);
  const TileNode first = buildTileTree(p.model, PatchKey::root(), 1);
  ASSERT_EQ(first.children.size(), 4u);
  ASSERT_TRUE(first.children[0].external);

  // A previous tree whose external tile carries a marker error: taken where nothing below it
  // changed (a copy of the model: no change at all), not where its subtree changed.
  TileNode marked = first;
  marked.children[0].geometricError = 12345;
  const Model same = p.model;
  const ModelChange none = modelChange(p.model, same);
  EXPECT_TRUE(none.empty());
  const TileTreeBase unchanged{marked, none};
  EXPECT_EQ(buildTileTree(same, PatchKey::root(), 1, &unchanged).children[0].geometricError, 12345)
      << "the previous tree's extent is taken, not walked again";

  // A leaf below NW raised by 500 m: NW's subtree changed, so its extent is walked again and is
  // the full build's; the other tiles (leaves, built directly) are the full build's too.
  Model after = p.model;
  const PatchKey leaf = nw.child(Quadrant::SE);
  auto raised = std::make_shared<PatchGrid>(*p.grids.at(leaf));
  for (int j = 0; j < raised->size(); ++j) {
    for (int i = 0; i < raised->size(); ++i) {
      raised->setGlobal(i, j, raised->global(i, j) + Vec3d{0, 0, 500});
    }
  }
  after.setGrid(leaf, raised);
  after.refreshStale([&](const PatchInfo& info) { return p.grids.at(info.key); });
  const ModelChange change = modelChange(p.model, after);
  EXPECT_EQ(change.changed, (std::vector<PatchKey>{PatchKey::root(), nw, leaf}));
  EXPECT_TRUE(change.removed.empty());
  const TileTreeBase base{marked, change};
  const TileNode byChange = buildTileTree(after, PatchKey::root(), 1, &base);
  const TileNode full = buildTileTree(after, PatchKey::root(), 1);
  expectSameTile(byChange, full);
  ASSERT_EQ(byChange.children.size(), full.children.size());
  for (std::size_t i = 0; i < full.children.size(); ++i) {
    expectSameTile(byChange.children[i], full.children[i]);
    EXPECT_EQ(byChange.children[i].external, full.children[i].external);
  }
  EXPECT_GT(full.children[0].box.max.z, first.children[0].box.max.z + 400) << "the raise shows";

  // A previous tree of another root is not taken.
  const TileTreeBase otherRoot{buildTileTree(p.model, nw, 1), none};
  expectSameTile(buildTileTree(same, PatchKey::root(), 1, &otherRoot).children[0],
                 first.children[0]);
}

TEST(Tileset, TransformsAreColumnMajorTranslationsBetweenCentres) {
  const Pyramid p;
  const TileNode tree = buildTileTree(p.model);
  const json tileset = server::api::tilesetJson(tree, "v7");
  EXPECT_EQ(tileset["asset"]["version"], "1.1");
  EXPECT_EQ(tileset["asset"]["tilesetVersion"], "v7");
  EXPECT_GT(tileset["geometricError"].get<double>(),
            tileset["root"]["geometricError"].get<double>());
  const json& root = tileset["root"];
  EXPECT_EQ(root["refine"], "REPLACE");
  EXPECT_EQ(root["content"]["uri"], "0_0_0.glb");
  const json& t = root["transform"];
  ASSERT_EQ(t.size(), 16u);
  EXPECT_EQ(t[12].get<double>(), tree.centre.x);
  EXPECT_EQ(t[13].get<double>(), tree.centre.y);
  EXPECT_EQ(t[14].get<double>(), tree.centre.z);
  EXPECT_EQ(t[15].get<double>(), 1.0);
  EXPECT_EQ(t[3].get<double>(), 0.0);
  // The box, moved by the root's transform, is the tree's box.
  const json& box = root["boundingVolume"]["box"];
  ASSERT_EQ(box.size(), 12u);
  EXPECT_NEAR(box[0].get<double>() + tree.centre.x - box[3].get<double>(), tree.box.min.x, 1e-6);
  EXPECT_NEAR(box[2].get<double>() + tree.centre.z + box[11].get<double>(), tree.box.max.z, 1e-6);
  // A child's transform is relative to its parent's.
  const json& child = root["children"][0];
  EXPECT_EQ(child["content"]["uri"], "1_0_0.glb");
  EXPECT_NEAR(child["transform"][12].get<double>() + tree.centre.x, tree.children[0].centre.x,
              1e-6);
  EXPECT_EQ(child["children"].size(), 4u);
  EXPECT_FALSE(root["children"][1].contains("children"));
  EXPECT_EQ(root["children"][1]["geometricError"], 0.0);
}

// ---- camera LOD --------------------------------------------------------------------------------

/// A camera at the origin looking along +x, up +z, 90 degrees vertical, 200 x 100 pixels.
Camera cameraAlongX() {
  Camera c;
  c.eye = {0, 0, 0};
  c.dir = {2, 0, 0};   // any length
  c.up = {0.5, 0, 3};  // not orthogonal to dir: made so
  c.fovY = std::numbers::pi / 2;
  c.width = 200;
  c.height = 100;
  return c;
}

Box3d pointBox(const Vec3d& p) {
  return {p, p};
}

TEST(CameraLod, FrustumHoldsWhatTheFieldOfViewSees) {
  const auto planes = frustumPlanes(cameraAlongX());
  // Vertical half-angle 45 degrees; horizontal: tan = 2 (aspect 2), about 63.4 degrees.
  EXPECT_TRUE(boxInFrustum(pointBox({10, 0, 0}), planes));
  EXPECT_TRUE(boxInFrustum(pointBox({10, 0, 9.9}), planes));
  EXPECT_FALSE(boxInFrustum(pointBox({10, 0, 10.1}), planes));
  EXPECT_FALSE(boxInFrustum(pointBox({10, 0, -10.1}), planes));
  EXPECT_TRUE(boxInFrustum(pointBox({10, 19.9, 0}), planes));
  EXPECT_TRUE(boxInFrustum(pointBox({10, -19.9, 0}), planes));
  EXPECT_FALSE(boxInFrustum(pointBox({10, 20.1, 0}), planes));
  EXPECT_FALSE(boxInFrustum(pointBox({10, -20.1, 0}), planes));
  EXPECT_FALSE(boxInFrustum(pointBox({-1, 0, 0}), planes));  // behind
  // A box reaching into the frustum from outside is in it; one wholly beside it is not.
  EXPECT_TRUE(boxInFrustum({{10, 19, -1}, {11, 40, 1}}, planes));
  EXPECT_FALSE(boxInFrustum({{10, 23, -1}, {11, 40, 1}}, planes));  // y <= 22 at x = 11
  EXPECT_TRUE(boxInFrustum({{-5, -5, -5}, {5, 5, 5}}, planes));     // around the eye
}

TEST(CameraLod, ScreenSpaceErrorIsThe3DTilesFormula) {
  Camera c = cameraAlongX();
  c.fovY = std::numbers::pi / 3;
  c.height = 1000;
  // 10 m of error 100 m away: 10 * 1000 / (2 * 100 * tan(30 deg)) = 86.60 px.
  EXPECT_NEAR(screenSpaceError(c, {{100, -5, -5}, {120, 5, 5}}, 10), 86.6025, 1e-3);
  // The distance is the box's nearest point's: 100 m along x, 100 m along y.
  EXPECT_NEAR(screenSpaceError(c, {{100, 100, -5}, {120, 120, 5}}, 10), 86.6025 / std::sqrt(2),
              1e-3);
  EXPECT_EQ(screenSpaceError(c, {{100, -5, -5}, {120, 5, 5}}, 0), 0);
  EXPECT_TRUE(std::isinf(screenSpaceError(c, {{-1, -1, -1}, {1, 1, 1}}, 1)));
}

TEST(CameraLod, CheckCameraRejectsWhatNoRendererHas) {
  Camera c = cameraAlongX();
  EXPECT_NO_THROW(checkCamera(c));
  const auto rejected = [](Camera bad) {
    return test::codeOf([&] { checkCamera(bad); }) == ErrorCode::InvalidArgument;
  };
  Camera bad = c;
  bad.up = {4, 0, 0};  // parallel to dir
  EXPECT_TRUE(rejected(bad));
  bad = c;
  bad.dir = {0, 0, 0};
  EXPECT_TRUE(rejected(bad));
  bad = c;
  bad.fovY = std::numbers::pi;
  EXPECT_TRUE(rejected(bad));
  bad = c;
  bad.height = 0.5;
  EXPECT_TRUE(rejected(bad));
  bad = c;
  bad.eye.x = std::numeric_limits<double>::quiet_NaN();
  EXPECT_TRUE(rejected(bad));
}

/// Whether `key` is in the cut, by the definition: it and every ancestor are visible, every
/// ancestor's error exceeds the threshold (so was refined), and its own does not or it is a leaf.
void bruteForceCut(const TileNode& node, const Camera& camera, double sse, bool ancestorsRefined,
                   std::set<std::string>& out) {
  const bool visible = boxInFrustum(node.box, frustumPlanes(camera));
  const double error = screenSpaceError(camera, node.box, node.geometricError);
  if (ancestorsRefined && visible && (error <= sse || node.children.empty())) {
    out.insert(node.key.toString());
  }
  for (const TileNode& child : node.children) {
    bruteForceCut(child, camera, sse, ancestorsRefined && visible && error > sse, out);
  }
}

TEST(CameraLod, CutIsTheBruteForceOneForEveryView) {
  const Pyramid p;
  const TileNode tree = buildTileTree(p.model);
  const Vec3d centre = tree.box.center();
  const double size = tree.box.size().norm();
  int nonTrivial = 0;
  // Cameras above the model at several heights and angles, some looking away.
  for (const double height : {0.05, 0.2, 1.0, 5.0}) {
    for (const double tilt : {0.0, 0.5, 1.2, 2.5}) {
      for (const double sse : {1.0, 16.0, 256.0}) {
        Camera c;
        c.eye = centre + Vec3d{0, 0, size * height} + Vec3d{size * 0.3 * tilt, 0, 0};
        c.dir = Vec3d{std::sin(tilt), 0, -std::cos(tilt)};
        c.up = {0, 1, 0};
        c.fovY = 1.0;
        c.width = 800;
        c.height = 600;
        std::set<std::string> expected;
        bruteForceCut(tree, c, sse, true, expected);
        std::set<std::string> got;
        const std::vector<CameraCutEntry> cut = lodCutForCamera(p.model, c, sse);
        for (std::size_t i = 0; i < cut.size(); ++i) {
          got.insert(cut[i].key.toString());
          // Drawn tiles are fine enough (a leaf's error is 0); keys ascend.
          EXPECT_LE(cut[i].screenError, sse);
          EXPECT_TRUE(i == 0 || cut[i - 1].key < cut[i].key);
        }
        EXPECT_EQ(got, expected) << "height " << height << " tilt " << tilt << " sse " << sse;
        nonTrivial += got.size() > 1 && got.size() < 9 ? 1 : 0;
      }
    }
  }
  // Some views cut between the root and the leaves (the test covers refinement, not only "all" or
  // "root").
  EXPECT_GT(nonTrivial, 3);
}

// ---- render-lod --------------------------------------------------------------------------------

TEST(Geodesy, EcefToGeodeticInvertsTheWgs84Formulas) {
  for (const auto& [lonDeg, latDeg, h] : {std::tuple{-84.25, 36.3, 500.0},
                                          {10.0, -60.0, -30.0},
                                          {179.0, 89.0, 4000.0},
                                          {-125.0, 24.0, 0.0}}) {
    const double a = 6378137.0, f = 1 / 298.257223563, e2 = f * (2 - f);
    const double lat = latDeg * std::numbers::pi / 180, lon = lonDeg * std::numbers::pi / 180;
    const double n = a / std::sqrt(1 - e2 * std::sin(lat) * std::sin(lat));
    const Vec3d ecef{(n + h) * std::cos(lat) * std::cos(lon),
                     (n + h) * std::cos(lat) * std::sin(lon), (n * (1 - e2) + h) * std::sin(lat)};
    const Vec3d g = ecefToGeodetic(ecef);
    EXPECT_NEAR(g.x, lonDeg, 1e-9);
    EXPECT_NEAR(g.y, latDeg, 1e-9);
    EXPECT_NEAR(g.z, h, 1e-4);
  }
}

TEST(RenderLod, DeeperColoursCoverExactlyTheDeeperArea) {
  const Pyramid p;
  const LodImage image = renderLod(
      p.model, [&](const PatchInfo& info) { return p.grids.at(info.key); }, {.size = 200});
  ASSERT_TRUE(image.geographic);
  EXPECT_EQ(std::max(image.width, image.height), 200);
  ASSERT_EQ(image.pixelsPerDepth.size(), 3u);
  EXPECT_EQ(image.pixelsPerDepth[0], 0u);
  EXPECT_GT(image.pixelsPerDepth[1], 0u);
  EXPECT_GT(image.pixelsPerDepth[2], 0u);
  // Depth 2 is the north-west quarter: roughly a quarter of the picture, all in its upper left.
  const double total = static_cast<double>(image.pixelsPerDepth[1] + image.pixelsPerDepth[2]);
  EXPECT_NEAR(image.pixelsPerDepth[2] / total, 0.25, 0.05);
  for (int y = 0; y < image.height; ++y) {
    for (int x = 0; x < image.width; ++x) {
      const std::size_t i = static_cast<std::size_t>(y) * image.width + x;
      if (image.depth[i] == 2) {
        EXPECT_LE(x, image.width / 2 + 2);
        EXPECT_LE(y, image.height / 2 + 2);
        const Rgb8 c = depthColour(2);
        EXPECT_EQ(image.rgba[i * 4], c.r);
        EXPECT_EQ(image.rgba[i * 4 + 3], 255);
      }
    }
  }
  EXPECT_EQ(depthColour(40), kDepthPalette.back());
}

}  // namespace
}  // namespace vsm::core
