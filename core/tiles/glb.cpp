#include "core/tiles/glb.hpp"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"

namespace vsm::core {

namespace {

using nlohmann::json;

static_assert(std::endian::native == std::endian::little, "GLB is little-endian");

// glTF 2.0 constants.
constexpr std::uint32_t kGlbMagic = 0x46546C67;   // "glTF"
constexpr std::uint32_t kChunkJson = 0x4E4F534A;  // "JSON"
constexpr std::uint32_t kChunkBin = 0x004E4942;   // "BIN\0"
constexpr int kFloat = 5126;                      // FLOAT
constexpr int kUnsignedShort = 5123;              // UNSIGNED_SHORT
constexpr int kUnsignedInt = 5125;                // UNSIGNED_INT
constexpr int kArrayBuffer = 34962;               // vertex attributes
constexpr int kElementArrayBuffer = 34963;        // indices
constexpr int kTriangles = 4;

std::size_t padded4(std::size_t n) {
  return (n + 3) & ~std::size_t{3};
}

/// The model's z-up axes to glTF's y-up ones: the inverse of 3D Tiles' y-up -> z-up rotation
/// (x, y, z) -> (x, -z, y).
Vec3d toYUp(const Vec3d& v) {
  return {v.x, v.z, -v.y};
}

Vec3d cross(const Vec3d& a, const Vec3d& b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}

/// Component-wise min and max of float vectors, written as the doubles the floats are exactly
/// (nlohmann prints a double's shortest round-trip form), so a reader comparing with the float32
/// data finds them equal.
template <std::size_t N>
struct MinMax {
  std::array<float, N> min;
  std::array<float, N> max;
  MinMax() {
    min.fill(std::numeric_limits<float>::infinity());
    max.fill(-std::numeric_limits<float>::infinity());
  }
  void add(const float* v) {
    for (std::size_t i = 0; i < N; ++i) {
      min[i] = std::min(min[i], v[i]);
      max[i] = std::max(max[i], v[i]);
    }
  }
  json minJson() const { return toJson(min); }
  json maxJson() const { return toJson(max); }
  static json toJson(const std::array<float, N>& a) {
    json out = json::array();
    for (const float f : a) {
      out.push_back(static_cast<double>(f));
    }
    return out;
  }
};

void putU32(std::vector<std::byte>& out, std::uint32_t v) {
  const auto* p = reinterpret_cast<const std::byte*>(&v);
  out.insert(out.end(), p, p + 4);
}

template <typename T>
void append(std::vector<std::byte>& bin, const std::vector<T>& values) {
  const auto* p = reinterpret_cast<const std::byte*>(values.data());
  bin.insert(bin.end(), p, p + values.size() * sizeof(T));
  bin.resize(padded4(bin.size()), std::byte{0});
}

}  // namespace

std::vector<std::byte> encodeGlb(const PatchGrid& grid, const Vec3d& centre,
                                 const GlbOptions& options) {
  if (!centre.finite()) {
    throw Error(ErrorCode::InvalidArgument, "GLB centre must be finite");
  }
  const int n = grid.size();
  if (!options.texcoords.empty() && options.texcoords.size() != grid.vertexCount() * 2) {
    throw Error(ErrorCode::InvalidArgument,
                "GLB texture coordinates: expected " + std::to_string(grid.vertexCount() * 2) +
                    " floats, got " + std::to_string(options.texcoords.size()));
  }
  const auto at = [n](int x, int y) { return static_cast<std::size_t>(y) * n + x; };

  // Positions relative to the centre, in double: the float32 rounding happens once, at the end.
  // An infinite coordinate (a foreign OPC) counts as undefined: glTF forbids non-finite floats.
  std::vector<Vec3d> relative(grid.vertexCount());
  std::vector<std::uint8_t> defined(grid.vertexCount());
  for (int y = 0; y < n; ++y) {
    for (int x = 0; x < n; ++x) {
      if (grid.defined(x, y)) {
        const Vec3d r = grid.global(x, y) - centre;
        if (r.finite() && std::abs(r.x) < 3e38 && std::abs(r.y) < 3e38 && std::abs(r.z) < 3e38) {
          relative[at(x, y)] = r;
          defined[at(x, y)] = 1;
        }
      }
    }
  }

  // Triangles over grid indices; complete quads only.
  std::vector<std::uint32_t> triangles;
  std::vector<std::uint32_t> remap(grid.vertexCount(), std::numeric_limits<std::uint32_t>::max());
  for (int y = 0; y + 1 < n; ++y) {
    for (int x = 0; x + 1 < n; ++x) {
      const auto a = static_cast<std::uint32_t>(at(x, y));
      const auto b = static_cast<std::uint32_t>(at(x + 1, y));
      const auto c = static_cast<std::uint32_t>(at(x, y + 1));
      const auto d = static_cast<std::uint32_t>(at(x + 1, y + 1));
      if (!defined[a] || !defined[b] || !defined[c] || !defined[d]) {
        continue;
      }
      // The shorter diagonal gives the better-shaped pair (viewers do not rely on either).
      if ((relative[d] - relative[a]).norm() <= (relative[c] - relative[b]).norm()) {
        triangles.insert(triangles.end(), {a, c, d, a, d, b});
      } else {
        triangles.insert(triangles.end(), {a, c, b, b, c, d});
      }
      for (const std::uint32_t v : {a, b, c, d}) {
        remap[v] = 0;  // used; numbered below in grid order
      }
    }
  }

  // Used vertices in grid order.
  std::vector<std::uint32_t> used;
  for (std::uint32_t v = 0; v < remap.size(); ++v) {
    if (remap[v] == 0) {
      remap[v] = static_cast<std::uint32_t>(used.size());
      used.push_back(v);
    }
  }

  json gltf = {{"asset", {{"version", "2.0"}, {"generator", "vsm"}}}, {"scene", 0}};
  std::vector<std::byte> bin;
  if (used.empty()) {
    // Nothing to draw: a valid asset with an empty scene (3D Tiles content may be empty).
    gltf["scenes"] = json::array({json::object()});
  } else {
    // Area-weighted normals: the cross product's length is twice the triangle's area.
    std::vector<Vec3d> normalSum(grid.vertexCount());
    for (std::size_t t = 0; t < triangles.size(); t += 3) {
      const std::uint32_t i0 = triangles[t], i1 = triangles[t + 1], i2 = triangles[t + 2];
      const Vec3d face = cross(relative[i1] - relative[i0], relative[i2] - relative[i0]);
      for (const std::uint32_t i : {i0, i1, i2}) {
        normalSum[i] = normalSum[i] + face;
      }
    }
    // A vertex whose triangles are all degenerate gets the local vertical: away from the earth's
    // centre for ECEF models, +z otherwise.
    const Vec3d fallbackUp = centre.norm() > 1e6 ? centre * (1.0 / centre.norm()) : Vec3d{0, 0, 1};

    const std::size_t count = used.size();
    std::vector<float> positions(count * 3), normals(count * 3), uvs(count * 2);
    MinMax<3> positionRange, normalRange;
    MinMax<2> uvRange;
    const double step = 1.0 / (n - 1);
    for (std::size_t i = 0; i < count; ++i) {
      const std::uint32_t v = used[i];
      const Vec3d p = toYUp(relative[v]);
      positions[i * 3] = static_cast<float>(p.x);
      positions[i * 3 + 1] = static_cast<float>(p.y);
      positions[i * 3 + 2] = static_cast<float>(p.z);
      positionRange.add(&positions[i * 3]);

      const double length = normalSum[v].norm();
      const Vec3d unit =
          toYUp(length > 0 && std::isfinite(length) ? normalSum[v] * (1.0 / length) : fallbackUp);
      normals[i * 3] = static_cast<float>(unit.x);
      normals[i * 3 + 1] = static_cast<float>(unit.y);
      normals[i * 3 + 2] = static_cast<float>(unit.z);
      normalRange.add(&normals[i * 3]);

      if (options.texcoords.empty()) {
        uvs[i * 2] = static_cast<float>((v % n) * step);
        uvs[i * 2 + 1] = static_cast<float>((v / n) * step);
      } else {
        uvs[i * 2] = options.texcoords[v * 2];
        uvs[i * 2 + 1] = options.texcoords[v * 2 + 1];
      }
      uvRange.add(&uvs[i * 2]);
    }

    // 65535 is the primitive restart value of UNSIGNED_SHORT and must not occur as an index.
    const bool shortIndices = count <= 65535;
    std::uint32_t indexMin = std::numeric_limits<std::uint32_t>::max(), indexMax = 0;
    for (std::uint32_t& index : triangles) {
      index = remap[index];
      indexMin = std::min(indexMin, index);
      indexMax = std::max(indexMax, index);
    }

    json bufferViews = json::array();
    // A view of `length` bytes at `offset`; the bytes are in `bin` already, padded to 4.
    const auto addView = [&](std::size_t offset, std::size_t length, int target) {
      json view = {{"buffer", 0}, {"byteOffset", offset}, {"byteLength", length}};
      if (target != 0) {
        view["target"] = target;
      }
      bufferViews.push_back(std::move(view));
      return bufferViews.size() - 1;
    };
    const auto addArray = [&](const auto& values, int target) {
      const std::size_t offset = bin.size();
      append(bin, values);
      return addView(offset, values.size() * sizeof(values[0]), target);
    };
    const std::size_t positionView = addArray(positions, kArrayBuffer);
    const std::size_t normalView = addArray(normals, kArrayBuffer);
    const std::size_t uvView = addArray(uvs, kArrayBuffer);
    std::size_t indexView = 0;
    if (shortIndices) {
      const std::vector<std::uint16_t> shorts(triangles.begin(), triangles.end());
      indexView = addArray(shorts, kElementArrayBuffer);
    } else {
      indexView = addArray(triangles, kElementArrayBuffer);
    }

    json accessors = json::array();
    accessors.push_back({{"bufferView", positionView},
                         {"componentType", kFloat},
                         {"count", count},
                         {"type", "VEC3"},
                         {"min", positionRange.minJson()},
                         {"max", positionRange.maxJson()}});
    accessors.push_back({{"bufferView", normalView},
                         {"componentType", kFloat},
                         {"count", count},
                         {"type", "VEC3"},
                         {"min", normalRange.minJson()},
                         {"max", normalRange.maxJson()}});
    accessors.push_back({{"bufferView", uvView},
                         {"componentType", kFloat},
                         {"count", count},
                         {"type", "VEC2"},
                         {"min", uvRange.minJson()},
                         {"max", uvRange.maxJson()}});
    accessors.push_back({{"bufferView", indexView},
                         {"componentType", shortIndices ? kUnsignedShort : kUnsignedInt},
                         {"count", triangles.size()},
                         {"type", "SCALAR"},
                         {"min", json::array({indexMin})},
                         {"max", json::array({indexMax})}});

    json pbr = {
        {"baseColorFactor", options.baseColor}, {"metallicFactor", 0.0}, {"roughnessFactor", 1.0}};
    if (!options.texture.image.empty()) {
      // The texture hook: the image goes into the BIN chunk like any other view.
      const std::size_t offset = bin.size();
      bin.insert(bin.end(), options.texture.image.begin(), options.texture.image.end());
      bin.resize(padded4(bin.size()), std::byte{0});
      const std::size_t imageView = addView(offset, options.texture.image.size(), 0);
      gltf["images"] =
          json::array({{{"bufferView", imageView}, {"mimeType", options.texture.mimeType}}});
      // Linear filtering, clamped: neighbouring tiles each carry their own image.
      gltf["samplers"] = json::array(
          {{{"magFilter", 9729}, {"minFilter", 9987}, {"wrapS", 33071}, {"wrapT", 33071}}});
      gltf["textures"] = json::array({{{"sampler", 0}, {"source", 0}}});
      pbr["baseColorTexture"] = {{"index", 0}};
    }

    gltf["scenes"] = json::array({{{"nodes", json::array({0})}}});
    gltf["nodes"] = json::array({{{"mesh", 0}}});
    gltf["meshes"] = json::array(
        {{{"primitives",
           json::array({{{"attributes", {{"POSITION", 0}, {"NORMAL", 1}, {"TEXCOORD_0", 2}}},
                         {"indices", 3},
                         {"material", 0},
                         {"mode", kTriangles}}})}}});
    gltf["materials"] =
        json::array({{{"pbrMetallicRoughness", std::move(pbr)}, {"doubleSided", true}}});
    gltf["accessors"] = std::move(accessors);
    gltf["bufferViews"] = std::move(bufferViews);
    gltf["buffers"] = json::array({{{"byteLength", bin.size()}}});
  }

  std::string text = gltf.dump();
  text.resize(padded4(text.size()), ' ');
  const std::size_t total = 12 + 8 + text.size() + (bin.empty() ? 0 : 8 + bin.size());
  if (total > std::numeric_limits<std::uint32_t>::max()) {
    throw Error(ErrorCode::InvalidArgument, "GLB would exceed 4 GiB");
  }
  std::vector<std::byte> out;
  out.reserve(total);
  putU32(out, kGlbMagic);
  putU32(out, 2);
  putU32(out, static_cast<std::uint32_t>(total));
  putU32(out, static_cast<std::uint32_t>(text.size()));
  putU32(out, kChunkJson);
  const auto* jsonBytes = reinterpret_cast<const std::byte*>(text.data());
  out.insert(out.end(), jsonBytes, jsonBytes + text.size());
  if (!bin.empty()) {
    putU32(out, static_cast<std::uint32_t>(bin.size()));
    putU32(out, kChunkBin);
    out.insert(out.end(), bin.begin(), bin.end());
  }
  return out;
}

}  // namespace vsm::core
