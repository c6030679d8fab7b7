#include "core/tiles/terrain_rgb.hpp"

#include <algorithm>
#include <cmath>
#include <numbers>

#include "core/tiles/heights.hpp"

namespace vsm::core {

namespace {

constexpr double kWgs84A = 6378137.0;
constexpr double kDegrees = 180.0 / std::numbers::pi;
/// Half the Web Mercator world's side, metres.
constexpr double kHalfWorld = std::numbers::pi * kWgs84A;
/// The largest 24-bit value.
constexpr double kMaxPacked = 16777215.0;

struct Packing {
  double offset;  // h = n / scale - offset
  double scale;
};

Packing packingOf(DemEncoding encoding) {
  return encoding == DemEncoding::Terrarium ? Packing{32768.0, 256.0} : Packing{10000.0, 10.0};
}

double latitudeOfMercatorY(double y) {
  return std::atan(std::sinh(y / kWgs84A)) * kDegrees;
}

double tileSide(int z) {
  return 2 * kHalfWorld / static_cast<double>(std::uint64_t{1} << z);
}

/// The tile's rectangle grown by a pixel: what its pixel centres' triangles can come from.
GeoRect paddedRect(const MercatorTileKey& key) {
  const GeoRect r = mercatorTileRect(key);
  const double padX = (r.east - r.west) / kDemTileSize, padY = (r.north - r.south) / kDemTileSize;
  return {r.west - padX, r.south - padY, r.east + padX, r.north + padY};
}

}  // namespace

bool MercatorTileKey::valid() const {
  return z >= 0 && z <= kMaxLevel && x < (std::uint64_t{1} << z) && y < (std::uint64_t{1} << z);
}

std::string MercatorTileKey::toString() const {
  return std::to_string(z) + "/" + std::to_string(x) + "/" + std::to_string(y);
}

GeoRect mercatorTileRect(const MercatorTileKey& key) {
  const double side = tileSide(key.z);
  const double west = -kHalfWorld + key.x * side;
  const double north = kHalfWorld - key.y * side;
  return {west / kWgs84A * kDegrees, latitudeOfMercatorY(north - side),
          (west + side) / kWgs84A * kDegrees, latitudeOfMercatorY(north)};
}

TopDownGrid mercatorTilePicture(const MercatorTileKey& key) {
  const double side = tileSide(key.z);
  TopDownGrid view;
  view.geographic = true;
  view.mercator = true;
  view.x0 = -kHalfWorld + key.x * side;
  view.y0 = kHalfWorld - key.y * side;
  view.dx = view.dy = side / kDemTileSize;
  view.width = view.height = kDemTileSize;
  return view;
}

double mercatorPixelGround(const MercatorTileKey& key) {
  const GeoRect r = mercatorTileRect(key);
  return tileSide(key.z) / kDemTileSize * std::cos((r.south + r.north) / 2 / kDegrees);
}

int mercatorLevelFor(double resolution, double latitude) {
  if (!(resolution > 0)) {
    return 0;
  }
  const double cosLat = std::cos(std::clamp(latitude, -85.0, 85.0) / kDegrees);
  int z = 0;
  while (z < MercatorTileKey::kMaxLevel && tileSide(z) / kDemTileSize * cosLat > resolution) {
    ++z;
  }
  return z;
}

std::vector<PatchKey> demTileSources(const Model& model, const TerrainLayer& layer,
                                     const MercatorTileKey& key) {
  return heightSources(model, layer, paddedRect(key), mercatorPixelGround(key));
}

double demEncodingMin(DemEncoding encoding) {
  return -packingOf(encoding).offset;
}

double demEncodingMax(DemEncoding encoding) {
  const Packing p = packingOf(encoding);
  return kMaxPacked / p.scale - p.offset;
}

std::array<std::uint8_t, 3> encodeDemHeight(double h, DemEncoding encoding) {
  const Packing p = packingOf(encoding);
  const double n = std::clamp(std::round((h + p.offset) * p.scale), 0.0, kMaxPacked);
  const auto packed = static_cast<std::uint32_t>(std::isnan(n) ? 0.0 : n);
  return {static_cast<std::uint8_t>(packed >> 16), static_cast<std::uint8_t>((packed >> 8) & 255),
          static_cast<std::uint8_t>(packed & 255)};
}

double decodeDemHeight(std::uint8_t r, std::uint8_t g, std::uint8_t b, DemEncoding encoding) {
  const Packing p = packingOf(encoding);
  const auto packed = (std::uint32_t{r} << 16) | (std::uint32_t{g} << 8) | b;
  return packed / p.scale - p.offset;
}

DemTile sampleDemTile(const Model& model, const std::vector<PatchKey>& sources,
                      const MercatorTileKey& key, const TerrainGridLoader& load,
                      DemEncoding encoding, double nodataHeight) {
  const TopDownGrid view = mercatorTilePicture(key);
  std::vector<double> heights(view.pixels(), nodataHeight);
  std::vector<std::uint8_t> painted(view.pixels(), 0);
  paintHeights(model, sources, view, paddedRect(key), load, heights, painted);
  DemTile tile;
  tile.rgb.resize(view.pixels() * 3);
  for (std::size_t i = 0; i < view.pixels(); ++i) {
    const auto rgb = encodeDemHeight(heights[i], encoding);
    std::copy(rgb.begin(), rgb.end(), tile.rgb.begin() + static_cast<std::ptrdiff_t>(i * 3));
    tile.covered += painted[i];
  }
  return tile;
}

}  // namespace vsm::core
