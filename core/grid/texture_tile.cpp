#include "core/grid/texture_tile.hpp"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <string>

#include "core/common/error.hpp"

namespace vsm::core {

TextureTile::TextureTile(int size) : size_(size) {
  if (size < 2 || size > 32768 || size % 2 != 0) {
    throw Error(ErrorCode::InvalidArgument,
                "texture tile size must be even and in 2..32768, not " + std::to_string(size));
  }
  texels_.assign(static_cast<std::size_t>(size) * size * kChannels, 0);
}

bool TextureTile::transparent() const {
  for (std::size_t i = 3; i < texels_.size(); i += kChannels) {
    if (texels_[i] != 0) {
      return false;
    }
  }
  return true;
}

int TextureTile::storedChannels() const {
  bool grey = true;
  for (std::size_t i = 0; i < texels_.size(); i += kChannels) {
    if (texels_[i + 3] != 255) {
      return kChannels;
    }
    grey = grey && texels_[i] == texels_[i + 1] && texels_[i] == texels_[i + 2];
  }
  return grey ? 1 : 3;
}

std::vector<float> textureCoordinates(int gridSize, int x0, int y0, int width, int height) {
  std::vector<float> out(static_cast<std::size_t>(width) * height * 2);
  float* p = out.data();
  for (int y = y0; y < y0 + height; ++y) {
    const float v = textureCoordinate(y, gridSize);
    for (int x = x0; x < x0 + width; ++x) {
      *p++ = textureCoordinate(x, gridSize);
      *p++ = v;
    }
  }
  return out;
}

int maxTexelsPerQuad(int gridSize) {
  int f = 1;
  while (textureTileSize(gridSize, 2 * f) <= kMaxTextureTileSize) {
    f *= 2;
  }
  return f;
}

int texelsPerQuadOf(int tileSize, int gridSize) {
  const int quads = gridSize - 1;
  if (quads < 1 || tileSize < quads || tileSize % quads != 0) {
    return 0;
  }
  const int f = tileSize / quads;
  return (f & (f - 1)) == 0 ? f : 0;
}

TextureTile resizeTile(const TextureTile& tile, int size) {
  const int from = tile.size();
  const int big = std::max(from, size);
  const int small = std::min(from, size);
  const int ratio = big / small;
  if (big % small != 0 || (ratio & (ratio - 1)) != 0) {
    throw Error(ErrorCode::InvalidArgument, "cannot resize a texture tile of " +
                                                std::to_string(from) + " texels to " +
                                                std::to_string(size));
  }
  TextureTile out(size);
  if (size > from) {
    // New texel (i, j) is centred at ((i + 0.5) / ratio - 0.5, ...) in the old texel centres.
    for (int j = 0; j < size; ++j) {
      const double y = (j + 0.5) / ratio - 0.5;
      for (int i = 0; i < size; ++i) {
        const std::array<std::uint8_t, 4> colour = sampleBilinear(tile, (i + 0.5) / ratio - 0.5, y);
        std::copy(colour.begin(), colour.end(), out.at(i, j));
      }
    }
    return out;
  }
  const int area = ratio * ratio;
  for (int j = 0; j < size; ++j) {
    for (int i = 0; i < size; ++i) {
      int sum[TextureTile::kChannels] = {0, 0, 0, 0};
      for (int y = j * ratio; y < (j + 1) * ratio; ++y) {
        const std::uint8_t* row = tile.at(i * ratio, y);
        for (int x = 0; x < ratio * TextureTile::kChannels; ++x) {
          sum[x % TextureTile::kChannels] += row[x];
        }
      }
      for (int c = 0; c < TextureTile::kChannels; ++c) {
        out.at(i, j)[c] = static_cast<std::uint8_t>((sum[c] + area / 2) / area);
      }
    }
  }
  return out;
}

TextureTile downsampleQuadrants(const std::array<const TextureTile*, 4>& children, int size) {
  TextureTile parent(size);
  for (int q = 0; q < 4; ++q) {
    if (children[q] != nullptr) {
      downsampleQuadrant(*children[q], q, parent);
    }
  }
  return parent;
}

void downsampleQuadrant(const TextureTile& child, int quadrant, TextureTile& parent) {
  const int size = parent.size();
  if (child.size() != size && 2 * child.size() != size) {
    throw Error(ErrorCode::InvalidArgument,
                "child texture tile of size " + std::to_string(child.size()) + ", expected " +
                    std::to_string(size) + " or " + std::to_string(size / 2));
  }
  const int half = size / 2;
  // Quadrant order nw, ne, sw, se: bit 0 is east, bit 1 south.
  const int offsetX = (quadrant & 1) * half;
  const int offsetY = (quadrant >> 1) * half;
  if (child.size() == half) {
    // Twice the child's texels per quad: the child as it is.
    const std::size_t rowBytes = static_cast<std::size_t>(half) * TextureTile::kChannels;
    for (int j = 0; j < half; ++j) {
      std::memcpy(parent.at(offsetX, offsetY + j), child.at(0, j), rowBytes);
    }
    return;
  }
  for (int j = 0; j < half; ++j) {
    const std::uint8_t* top = child.at(0, 2 * j);
    const std::uint8_t* bottom = child.at(0, 2 * j + 1);
    std::uint8_t* out = parent.at(offsetX, offsetY + j);
    for (int i = 0; i < half; ++i) {
      for (int c = 0; c < TextureTile::kChannels; ++c) {
        const int k = 2 * i * TextureTile::kChannels + c;
        const int sum = top[k] + top[k + TextureTile::kChannels] + bottom[k] +
                        bottom[k + TextureTile::kChannels];
        out[i * TextureTile::kChannels + c] = static_cast<std::uint8_t>((sum + 2) / 4);
      }
    }
  }
}

std::array<std::uint8_t, 4> sampleBilinear(const TextureTile& tile, double x, double y) {
  const int last = tile.size() - 1;
  x = std::clamp(x, 0.0, static_cast<double>(last));
  y = std::clamp(y, 0.0, static_cast<double>(last));
  const int x0 = std::min(static_cast<int>(x), last - 1);
  const int y0 = std::min(static_cast<int>(y), last - 1);
  const double fx = x - x0;
  const double fy = y - y0;
  const double weights[4] = {(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy};
  const std::uint8_t* texels[4] = {tile.at(x0, y0), tile.at(x0 + 1, y0), tile.at(x0, y0 + 1),
                                   tile.at(x0 + 1, y0 + 1)};
  double sum[3] = {0, 0, 0};
  double total = 0;
  for (int k = 0; k < 4; ++k) {
    if (texels[k][3] != 0 && weights[k] > 0) {
      for (int c = 0; c < 3; ++c) {
        sum[c] += weights[k] * texels[k][c];
      }
      total += weights[k];
    }
  }
  if (total == 0) {
    return {0, 0, 0, 0};
  }
  std::array<std::uint8_t, 4> out{0, 0, 0, 255};
  for (int c = 0; c < 3; ++c) {
    out[c] = static_cast<std::uint8_t>(std::clamp(std::lround(sum[c] / total), 0L, 255L));
  }
  return out;
}

}  // namespace vsm::core
