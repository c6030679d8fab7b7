#include "core/tiles/glb.hpp"

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>

#include <meshoptimizer.h>
#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/grid/patch_grid.hpp"
#include "core/grid/vec_ops.hpp"

namespace vsm::core {

namespace {

using nlohmann::json;

static_assert(std::endian::native == std::endian::little, "GLB is little-endian");

// glTF 2.0 constants.
constexpr std::uint32_t kGlbMagic = 0x46546C67;   // "glTF"
constexpr std::uint32_t kChunkJson = 0x4E4F534A;  // "JSON"
constexpr std::uint32_t kChunkBin = 0x004E4942;   // "BIN\0"
constexpr int kFloat = 5126;                      // FLOAT
constexpr int kByte = 5120;                       // BYTE
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

using vec::cross;

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

/// The mesh encodeGlb() stores: y-up positions relative to the centre, unit normals, texture
/// coordinates (interleaved), triangles over the vertices.
struct Mesh {
  const std::vector<Vec3d>& positions;
  const std::vector<Vec3d>& normals;
  const std::vector<float>& uvs;
  const std::vector<std::uint32_t>& triangles;
};

/// Adds `view` to gltf["bufferViews"] and returns its index.
std::size_t addView(json& gltf, json view) {
  json& views = gltf["bufferViews"];
  views.push_back(std::move(view));
  return views.size() - 1;
}

/// The mesh primitive's accessors (POSITION, NORMAL, TEXCOORD_0, indices: 0..3) and one node.
void addMesh(json& gltf, json node) {
  node["mesh"] = 0;
  gltf["nodes"] = json::array({std::move(node)});
  gltf["meshes"] = json::array(
      {{{"primitives",
         json::array({{{"attributes", {{"POSITION", 0}, {"NORMAL", 1}, {"TEXCOORD_0", 2}}},
                       {"indices", 3},
                       {"material", 0},
                       {"mode", kTriangles}}})}}});
}

/// Core glTF: float32 attributes and plain indices in buffer 0 (the BIN chunk).
void writeFloat(const Mesh& mesh, json& gltf, std::vector<std::byte>& bin) {
  const std::size_t count = mesh.positions.size();
  std::vector<float> positions(count * 3), normals(count * 3);
  MinMax<3> positionRange, normalRange;
  MinMax<2> uvRange;
  for (std::size_t i = 0; i < count; ++i) {
    const Vec3d& p = mesh.positions[i];
    const Vec3d& u = mesh.normals[i];
    positions[i * 3] = static_cast<float>(p.x);
    positions[i * 3 + 1] = static_cast<float>(p.y);
    positions[i * 3 + 2] = static_cast<float>(p.z);
    positionRange.add(&positions[i * 3]);
    normals[i * 3] = static_cast<float>(u.x);
    normals[i * 3 + 1] = static_cast<float>(u.y);
    normals[i * 3 + 2] = static_cast<float>(u.z);
    normalRange.add(&normals[i * 3]);
    uvRange.add(&mesh.uvs[i * 2]);
  }
  // 65535 is the primitive restart value of UNSIGNED_SHORT and must not occur as an index.
  const bool shortIndices = count <= 65535;
  std::uint32_t indexMin = std::numeric_limits<std::uint32_t>::max(), indexMax = 0;
  for (const std::uint32_t index : mesh.triangles) {
    indexMin = std::min(indexMin, index);
    indexMax = std::max(indexMax, index);
  }
  const auto addArray = [&](const auto& values, int target) {
    const std::size_t offset = bin.size();
    append(bin, values);
    return addView(gltf, {{"buffer", 0},
                          {"byteOffset", offset},
                          {"byteLength", values.size() * sizeof(values[0])},
                          {"target", target}});
  };
  const std::size_t positionView = addArray(positions, kArrayBuffer);
  const std::size_t normalView = addArray(normals, kArrayBuffer);
  const std::size_t uvView = addArray(mesh.uvs, kArrayBuffer);
  std::size_t indexView = 0;
  if (shortIndices) {
    const std::vector<std::uint16_t> shorts(mesh.triangles.begin(), mesh.triangles.end());
    indexView = addArray(shorts, kElementArrayBuffer);
  } else {
    indexView = addArray(mesh.triangles, kElementArrayBuffer);
  }
  json& accessors = gltf["accessors"];
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
                       {"count", mesh.triangles.size()},
                       {"type", "SCALAR"},
                       {"min", json::array({indexMin})},
                       {"max", json::array({indexMax})}});
  gltf["buffers"] = json::array({json::object()});  // byteLength once the BIN chunk is complete
  addMesh(gltf, json::object());
}

/// A vertex stream or the indices, compressed with meshoptimizer into buffer 0 (the BIN chunk),
/// decoding into `fallbackBytes` of buffer 1 (EXT_meshopt_compression's fallback buffer, which
/// holds no data).
class MeshoptViews {
 public:
  MeshoptViews(json& gltf, std::vector<std::byte>& bin) : gltf_(gltf), bin_(bin) {}

  /// `count` vertices of `stride` bytes (a multiple of 4, as the codec needs).
  std::size_t addAttributes(const std::vector<std::byte>& raw, std::size_t count,
                            std::size_t stride) {
    std::vector<unsigned char> encoded(meshopt_encodeVertexBufferBound(count, stride));
    encoded.resize(
        meshopt_encodeVertexBuffer(encoded.data(), encoded.size(), raw.data(), count, stride));
    json view = add(encoded, count, stride, "ATTRIBUTES");
    view["byteStride"] = stride;
    view["target"] = kArrayBuffer;
    return addView(gltf_, std::move(view));
  }

  /// Triangles over `vertexCount` vertices, decoding into 2- or 4-byte indices.
  std::size_t addTriangles(const std::vector<std::uint32_t>& triangles, std::size_t vertexCount,
                           std::size_t indexSize) {
    std::vector<unsigned char> encoded(
        meshopt_encodeIndexBufferBound(triangles.size(), vertexCount));
    encoded.resize(meshopt_encodeIndexBuffer(encoded.data(), encoded.size(), triangles.data(),
                                             triangles.size()));
    json view = add(encoded, triangles.size(), indexSize, "TRIANGLES");
    view["target"] = kElementArrayBuffer;  // index views have no byteStride
    return addView(gltf_, std::move(view));
  }

  std::size_t fallbackBytes() const { return fallbackBytes_; }

 private:
  json add(const std::vector<unsigned char>& encoded, std::size_t count, std::size_t stride,
           std::string_view mode) {
    if (encoded.empty()) {
      throw Error(ErrorCode::Internal, "meshoptimizer could not encode a GLB buffer view");
    }
    const std::size_t offset = bin_.size();
    const auto* p = reinterpret_cast<const std::byte*>(encoded.data());
    bin_.insert(bin_.end(), p, p + encoded.size());
    bin_.resize(padded4(bin_.size()), std::byte{0});
    const std::size_t length = count * stride;
    json view = {{"buffer", 1},
                 {"byteOffset", fallbackBytes_},
                 {"byteLength", length},
                 {"extensions",
                  {{"EXT_meshopt_compression",
                    {{"buffer", 0},
                     {"byteOffset", offset},
                     {"byteLength", encoded.size()},
                     {"byteStride", stride},
                     {"count", count},
                     {"mode", mode}}}}}};
    fallbackBytes_ += padded4(length);
    return view;
  }

  json& gltf_;
  std::vector<std::byte>& bin_;
  std::size_t fallbackBytes_ = 0;
};

template <typename T>
void put(std::vector<std::byte>& out, std::size_t at, T value) {
  std::memcpy(out.data() + at, &value, sizeof(T));
}

/// KHR_mesh_quantization + EXT_meshopt_compression (see GlbCompression::Meshopt).
void writeMeshopt(const Mesh& mesh, json& gltf, std::vector<std::byte>& bin) {
  const std::size_t count = mesh.positions.size();

  // Positions: one scale for all axes (a uniform node scale leaves normals alone).
  Vec3d low = mesh.positions[0], high = mesh.positions[0];
  for (const Vec3d& p : mesh.positions) {
    low = {std::min(low.x, p.x), std::min(low.y, p.y), std::min(low.z, p.z)};
    high = {std::max(high.x, p.x), std::max(high.y, p.y), std::max(high.z, p.z)};
  }
  const Vec3d extent = high - low;
  const double largest = std::max({extent.x, extent.y, extent.z});
  const double scale = largest > 0 ? largest / 65535.0 : 1.0;
  // The largest q per axis whose position stays inside [low, high].
  const std::array<double, 3> top{std::min(65535.0, std::floor(extent.x / scale)),
                                  std::min(65535.0, std::floor(extent.y / scale)),
                                  std::min(65535.0, std::floor(extent.z / scale))};
  const std::array<double, 3> base{low.x, low.y, low.z};
  constexpr std::size_t kPositionStride = 8;  // 3 x uint16 and 2 bytes of padding
  std::vector<std::byte> positions(count * kPositionStride, std::byte{0});
  std::array<std::uint16_t, 3> qMin{65535, 65535, 65535}, qMax{0, 0, 0};
  for (std::size_t i = 0; i < count; ++i) {
    const Vec3d& p = mesh.positions[i];
    const std::array<double, 3> c{p.x, p.y, p.z};
    for (std::size_t k = 0; k < 3; ++k) {
      const auto q =
          static_cast<std::uint16_t>(std::clamp(std::round((c[k] - base[k]) / scale), 0.0, top[k]));
      put(positions, i * kPositionStride + k * 2, q);
      qMin[k] = std::min(qMin[k], q);
      qMax[k] = std::max(qMax[k], q);
    }
  }

  // Normals: signed bytes, 127 = 1 (glTF's normalized BYTE), one byte of padding.
  std::vector<std::byte> normals(count * 4, std::byte{0});
  for (std::size_t i = 0; i < count; ++i) {
    const Vec3d& u = mesh.normals[i];
    const std::array<double, 3> c{u.x, u.y, u.z};
    for (std::size_t k = 0; k < 3; ++k) {
      put(normals, i * 4 + k,
          static_cast<std::int8_t>(std::clamp(std::round(c[k] * 127.0), -127.0, 127.0)));
    }
  }

  // Texture coordinates: normalized uint16 when they are all in [0, 1] (OPC's are).
  const bool quantizedUvs =
      std::all_of(mesh.uvs.begin(), mesh.uvs.end(), [](float t) { return t >= 0.0f && t <= 1.0f; });
  const std::size_t uvStride = quantizedUvs ? 4 : 8;
  std::vector<std::byte> uvs(count * uvStride);
  if (quantizedUvs) {
    for (std::size_t i = 0; i < count * 2; ++i) {
      put(uvs, i * 2, static_cast<std::uint16_t>(std::lround(mesh.uvs[i] * 65535.0)));
    }
  } else {
    std::memcpy(uvs.data(), mesh.uvs.data(), uvs.size());
  }

  // Vertices and triangles stay in the grid's row order: neighbouring vertices follow each other
  // (small deltas for the vertex codec) and consecutive triangles share edges (the index codec's
  // best case). meshopt_optimizeVertexCache, with or without optimizeVertexFetch, made the real
  // models' GLBs 10-15 % larger and their encoding 2-8 times slower (tests/bench/glb_bench.sh), for
  // a post-transform cache gain that tiles of a few thousand triangles do not need.
  const std::vector<std::uint32_t>& triangles = mesh.triangles;
  // 65535 is the primitive restart value of UNSIGNED_SHORT and must not occur as an index.
  const bool shortIndices = count <= 65535;

  MeshoptViews views(gltf, bin);
  const std::size_t positionView = views.addAttributes(positions, count, kPositionStride);
  const std::size_t normalView = views.addAttributes(normals, count, 4);
  const std::size_t uvView = views.addAttributes(uvs, count, uvStride);
  const std::size_t indexView = views.addTriangles(triangles, count, shortIndices ? 2 : 4);

  const auto toJson = [](const std::array<std::uint16_t, 3>& a) {
    return json::array({a[0], a[1], a[2]});
  };
  json& accessors = gltf["accessors"];
  accessors.push_back({{"bufferView", positionView},
                       {"componentType", kUnsignedShort},
                       {"count", count},
                       {"type", "VEC3"},
                       {"min", toJson(qMin)},
                       {"max", toJson(qMax)}});
  accessors.push_back({{"bufferView", normalView},
                       {"componentType", kByte},
                       {"normalized", true},
                       {"count", count},
                       {"type", "VEC3"}});
  json uvAccessor = {{"bufferView", uvView}, {"count", count}, {"type", "VEC2"}};
  if (quantizedUvs) {
    uvAccessor["componentType"] = kUnsignedShort;
    uvAccessor["normalized"] = true;
  } else {
    uvAccessor["componentType"] = kFloat;
  }
  accessors.push_back(std::move(uvAccessor));
  accessors.push_back({{"bufferView", indexView},
                       {"componentType", shortIndices ? kUnsignedShort : kUnsignedInt},
                       {"count", triangles.size()},
                       {"type", "SCALAR"}});
  gltf["buffers"] =
      json::array({json::object(),  // byteLength once the BIN chunk is complete
                   {{"byteLength", views.fallbackBytes()},
                    {"extensions", {{"EXT_meshopt_compression", {{"fallback", true}}}}}}});
  gltf["extensionsUsed"] = json::array({"EXT_meshopt_compression", "KHR_mesh_quantization"});
  gltf["extensionsRequired"] = gltf["extensionsUsed"];
  addMesh(gltf, {{"translation", json::array({low.x, low.y, low.z})},
                 {"scale", json::array({scale, scale, scale})}});
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
    std::vector<Vec3d> positions(count), normals(count);
    std::vector<float> uvs(count * 2);
    const double step = 1.0 / (n - 1);
    for (std::size_t i = 0; i < count; ++i) {
      const std::uint32_t v = used[i];
      positions[i] = toYUp(relative[v]);
      const double length = normalSum[v].norm();
      normals[i] =
          toYUp(length > 0 && std::isfinite(length) ? normalSum[v] * (1.0 / length) : fallbackUp);
      if (options.texcoords.empty()) {
        uvs[i * 2] = static_cast<float>((v % n) * step);
        uvs[i * 2 + 1] = static_cast<float>((v / n) * step);
      } else {
        uvs[i * 2] = options.texcoords[v * 2];
        uvs[i * 2 + 1] = options.texcoords[v * 2 + 1];
      }
    }
    for (std::uint32_t& index : triangles) {
      index = remap[index];
    }
    const Mesh mesh{positions, normals, uvs, triangles};
    if (options.compression == GlbCompression::Meshopt) {
      writeMeshopt(mesh, gltf, bin);
    } else {
      writeFloat(mesh, gltf, bin);
    }
    json& bufferViews = gltf["bufferViews"];

    json pbr = {
        {"baseColorFactor", options.baseColor}, {"metallicFactor", 0.0}, {"roughnessFactor", 1.0}};
    if (!options.texture.image.empty()) {
      // The texture hook: the image goes into the BIN chunk like any other view.
      const std::size_t offset = bin.size();
      bin.insert(bin.end(), options.texture.image.begin(), options.texture.image.end());
      bin.resize(padded4(bin.size()), std::byte{0});
      bufferViews.push_back(
          {{"buffer", 0}, {"byteOffset", offset}, {"byteLength", options.texture.image.size()}});
      const std::size_t imageView = bufferViews.size() - 1;
      gltf["images"] =
          json::array({{{"bufferView", imageView}, {"mimeType", options.texture.mimeType}}});
      // Linear filtering, clamped: neighbouring tiles each carry their own image.
      gltf["samplers"] = json::array(
          {{{"magFilter", 9729}, {"minFilter", 9987}, {"wrapS", 33071}, {"wrapT", 33071}}});
      gltf["textures"] = json::array({{{"sampler", 0}, {"source", 0}}});
      pbr["baseColorTexture"] = {{"index", 0}};
    }

    gltf["scenes"] = json::array({{{"nodes", json::array({0})}}});
    gltf["materials"] =
        json::array({{{"pbrMetallicRoughness", std::move(pbr)}, {"doubleSided", true}}});
    gltf["buffers"][0] = {{"byteLength", bin.size()}};
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
