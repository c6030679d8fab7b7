#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

namespace vsm::core {

/// The texture image of one patch: size x size RGBA 8-bit texels, row-major, row 0 the top
/// (north) row. Texel (i, j) covers the grid quad between vertices (i, j) and (i + 1, j + 1) of a
/// patch of size + 1 vertices per side, so vertex (x, y) sits at texture coordinate
/// (x / size, y / size) (textureCoordinate) and a parent's texel covers exactly 2 x 2 texels of one
/// child. Alpha 0 marks texels the image does not cover.
///
/// Not thread-safe for writing; tiles are passed by value or unique_ptr between build steps.
class TextureTile {
 public:
  static constexpr int kChannels = 4;

  /// A tile of size x size transparent black texels. Throws Error(InvalidArgument) unless size
  /// is even and in 2..32768.
  explicit TextureTile(int size);

  int size() const { return size_; }
  /// Bytes of texel data, for memory accounting.
  std::size_t bytes() const { return texels_.size(); }

  std::span<std::uint8_t> texels() { return texels_; }
  std::span<const std::uint8_t> texels() const { return texels_; }
  std::uint8_t* at(int i, int j) {
    return texels_.data() + (static_cast<std::size_t>(j) * size_ + i) * kChannels;
  }
  const std::uint8_t* at(int i, int j) const {
    return texels_.data() + (static_cast<std::size_t>(j) * size_ + i) * kChannels;
  }

  /// True when no texel is opaque at all (nothing of the image falls on the tile).
  bool transparent() const;

 private:
  int size_;
  std::vector<std::uint8_t> texels_;
};

/// The texture tile size of patches of `gridSize` vertices per side: one texel per grid quad
/// (256 x 256 for 257 x 257 grids).
inline int textureTileSize(int gridSize) {
  return gridSize - 1;
}

/// The texture coordinate of vertex index `x` (or `y`) of a grid of `gridSize` vertices: its
/// position across the tile, 0 at the first vertex and 1 at the last (v = 0 is the top row).
inline float textureCoordinate(int x, int gridSize) {
  return static_cast<float>(static_cast<double>(x) / (gridSize - 1));
}

/// Texture coordinates of the stored rectangle [x0, x0 + width) x [y0, y0 + height) of a grid of
/// `gridSize` vertices: (u, v) interleaved, row-major, as Coordinates.aara holds them.
std::vector<float> textureCoordinates(int gridSize, int x0, int y0, int width, int height);

/// A parent's tile from its children's (indexed by Quadrant: nw, ne, sw, se; null where a child is
/// missing, which leaves that quadrant transparent): each child is placed in its quadrant at half
/// resolution, a parent texel being the rounded mean of the 2 x 2 child texels it covers (every
/// channel, alpha included). Precondition: the present children have size `size`.
TextureTile downsampleQuadrants(const std::array<const TextureTile*, 4>& children, int size);

/// The colour of `tile` at (x, y) in texel-centre coordinates (texel (i, j) is centred at (i, j);
/// in a patch's grid, vertex coordinates minus 0.5), bilinearly filtered over the up to four
/// nearest texels that are not transparent, their weights re-normalised; positions outside the
/// tile take the border texels. Returns RGBA with alpha 255, or alpha 0 (all channels 0) when none
/// of those texels is opaque.
std::array<std::uint8_t, 4> sampleBilinear(const TextureTile& tile, double x, double y);

}  // namespace vsm::core
