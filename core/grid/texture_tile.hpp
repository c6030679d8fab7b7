#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>
#include <vector>

namespace vsm::core {

/// The texture image of one patch: size x size RGBA 8-bit texels, row-major, row 0 the top
/// (north) row. A patch of g vertices per side has f x f texels per grid quad (f a power of two,
/// the tile size (g - 1) f, textureTileSize): texel (i, j) covers the part of the patch between
/// vertex coordinates (i / f, j / f) and ((i + 1) / f, (j + 1) / f), so vertex (x, y) sits at
/// texture coordinate (x / (g - 1), y / (g - 1)) (textureCoordinate) whatever f, and a parent's
/// texel covers exactly 2 x 2 texels of one child of the same f. Alpha 0 marks texels the image
/// does not cover.
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
  /// The channels a file needs to hold this tile exactly: 4 (RGBA) when a texel is not opaque,
  /// else 1 when every texel is grey (R = G = B: the shaded relief), else 3 (RGB).
  int storedChannels() const;

 private:
  int size_;
  std::vector<std::uint8_t> texels_;
};

/// The largest texture tile an import or a merge makes: 4096 x 4096 texels (64 MiB as RGBA, in
/// memory; the cache charges a tile's real size).
inline constexpr int kMaxTextureTileSize = 4096;

/// The texture tile size of patches of `gridSize` vertices per side with `texelsPerQuad` texels per
/// grid quad side (a power of two): 256 x 256 for 257 x 257 grids at one texel per quad, 1024 x
/// 1024 at four.
inline int textureTileSize(int gridSize, int texelsPerQuad = 1) {
  return (gridSize - 1) * texelsPerQuad;
}

/// The most texels per grid quad side vsm gives patches of `gridSize` vertices: the largest power
/// of two whose tiles stay within kMaxTextureTileSize, and 1 where even those do not.
int maxTexelsPerQuad(int gridSize);

/// The texels per grid quad side of a tile `tileSize` texels wide on patches of `gridSize`
/// vertices: the power of two f with tileSize == (gridSize - 1) * f; 0 when there is none (a
/// foreign tile in another layout, which vsm does not place).
int texelsPerQuadOf(int tileSize, int gridSize);

/// `tile` at `size` texels a side, size / tile.size() a power of two (or its inverse): smaller by
/// box filtering (the rounded mean of each block of texels, alpha included, as
/// downsampleQuadrants), larger by bilinear filtering (sampleBilinear at the new texels' centres,
/// so transparent texels stay out of the colours); the same size returns a copy. Throws
/// Error(InvalidArgument) for any other ratio.
TextureTile resizeTile(const TextureTile& tile, int size);

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

/// One child's part of downsampleQuadrants: `child` at half resolution into quadrant `quadrant`
/// (Quadrant's order: nw, ne, sw, se) of `parent`, the rest of `parent` left as it is; or, when
/// `parent` is twice the child's size (twice its texels per quad: the level above a hidden one,
/// thesis 5.2), the child's texels as they are. Throws Error(InvalidArgument) for other sizes.
void downsampleQuadrant(const TextureTile& child, int quadrant, TextureTile& parent);

/// The colour of `tile` at (x, y) in texel-centre coordinates (texel (i, j) is centred at (i, j);
/// in a patch's grid, vertex coordinates minus 0.5), bilinearly filtered over the up to four
/// nearest texels that are not transparent, their weights re-normalised; positions outside the
/// tile take the border texels. Returns RGBA with alpha 255, or alpha 0 (all channels 0) when none
/// of those texels is opaque.
std::array<std::uint8_t, 4> sampleBilinear(const TextureTile& tile, double x, double y);

}  // namespace vsm::core
