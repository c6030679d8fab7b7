#pragma once

#include <array>
#include <cstddef>
#include <span>
#include <string>
#include <vector>

#include "core/grid/geometry.hpp"

namespace vsm::core {

class PatchGrid;

/// An encoded image to embed as the mesh's base colour texture (the texture hook of issue 6: the
/// importer's texture tiles go here once patches carry them).
struct GlbTexture {
  /// The encoded file (PNG or JPEG bytes, as glTF 2.0 allows), copied into the GLB's buffer.
  std::span<const std::byte> image;
  /// "image/png" or "image/jpeg".
  std::string mimeType;
};

/// How encodeGlb() stores the mesh.
enum class GlbCompression : unsigned char {
  /// float32 POSITION, NORMAL and TEXCOORD_0, plain indices: core glTF 2.0, no extension.
  None,
  /// KHR_mesh_quantization (POSITION UNSIGNED_SHORT with a node transform, NORMAL BYTE normalized,
  /// TEXCOORD_0 UNSIGNED_SHORT normalized) and every vertex and index view compressed with
  /// EXT_meshopt_compression; both extensions required.
  Meshopt,
};

/// Options of encodeGlb(). The defaults make an untextured, double-sided grey mesh, uncompressed.
struct GlbOptions {
  /// Embedded as material 0's baseColorTexture when set (image.empty() means no texture).
  GlbTexture texture;
  /// Per-vertex texture coordinates (u, v interleaved, size x size pairs, row-major, v = 0 the top
  /// image row, as OPC's Coordinates.aara): used for TEXCOORD_0 instead of the default (u, v) =
  /// (x / (size - 1), y / (size - 1)). Empty: the default. Precondition: empty or 2 x vertexCount.
  std::span<const float> texcoords;
  /// Linear RGBA base colour factor (multiplies the texture when there is one).
  std::array<double, 4> baseColor{0.8, 0.8, 0.8, 1.0};
  /// The mesh's storage.
  GlbCompression compression = GlbCompression::None;
};

/// Encodes a patch grid as a binary glTF 2.0 (GLB) holding one triangle mesh:
///
/// - every grid quad whose four corners are defined becomes two triangles (along the shorter
///   diagonal); quads touching an undefined (or non-finite) vertex are skipped, and only vertices
///   used by a triangle are stored (a grid without a complete quad gives a valid GLB without a
///   mesh);
/// - POSITION is float32, relative to `centre` (global coordinates, e.g. ECEF metres) and turned
///   from the model's z-up axes into glTF's y-up ones, (x, y, z) -> (x, z, -y), so a 3D Tiles
///   runtime (which rotates glTF content y-up -> z-up) places it at centre + (x, y, z) under a tile
///   transform translating by `centre`;
/// - NORMAL: unit per-vertex normals (area-weighted face normals, same axes); TEXCOORD_0: see
///   GlbOptions::texcoords; indices UNSIGNED_SHORT when the vertices fit, UNSIGNED_INT otherwise.
///   Triangles wind counter-clockwise seen from +z for a grid whose rows run north to south and
///   columns west to east (rasters as vsm imports them); the material is double-sided anyway;
/// - every accessor carries its exact min/max; buffer views are 4-byte aligned, the JSON chunk is
///   padded with spaces and the BIN chunk with zeros.
///
/// With GlbCompression::Meshopt the same vertices and triangles, in the same order (the index
/// codec may rotate a triangle's indices, keeping its winding), are stored quantized and
/// compressed:
///
/// - POSITION: UNSIGNED_SHORT (unnormalized) per axis, q = round((p - min) / s), with one scale s
///   for all three axes (the largest extent / 65535, so normals need no correction) and the
///   mesh's node carrying `translation` = the per-axis minimum and `scale` = (s, s, s); q is
///   clamped to floor((max - min) / s) on each axis, so every decoded position lies inside the
///   float path's range (and so inside the tile's box) and within s of its float value;
/// - NORMAL: BYTE normalized, round(127 n) (within 0.5 / 127 per component, before renormalising);
/// - TEXCOORD_0: UNSIGNED_SHORT normalized, round(65535 t), when every coordinate is in [0, 1];
///   float32 otherwise;
/// - each vertex stream and the indices are EXT_meshopt_compression buffer views (mode ATTRIBUTES
///   and TRIANGLES, filter NONE) in the BIN chunk; the views they decode into lie in a second
///   buffer without data, marked `"fallback": true` (the extension's layout for a required
///   compression); the texture stays a plain view of the BIN chunk.
///
/// Thread-safe (reads `grid` only). Throws Error(InvalidArgument) when `centre` is not finite,
/// when texcoords has the wrong size, or when the GLB would exceed 4 GiB.
std::vector<std::byte> encodeGlb(const PatchGrid& grid, const Vec3d& centre,
                                 const GlbOptions& options = {});

}  // namespace vsm::core
