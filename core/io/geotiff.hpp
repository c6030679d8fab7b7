#pragma once

#include <array>
#include <filesystem>
#include <span>

namespace vsm::core {

/// A one-band float32 raster to write as a GeoTIFF.
struct FloatRaster {
  int width = 0;
  int height = 0;
  /// Row-major, top row first, width * height values; NaN is no-data.
  std::span<const float> values;
  /// GDAL's geotransform: x = t[0] + col * t[1] + row * t[2], y = t[3] + col * t[4] + row * t[5]
  /// for the pixel's upper-left corner.
  std::array<double, 6> geoTransform{0, 1, 0, 0, 0, -1};
  /// True: the coordinates are WGS 84 longitude/latitude (EPSG:4326, written so); false: none is
  /// named (a model's own Cartesian x/y).
  bool wgs84 = false;
};

/// Writes `raster` as a deflate-compressed GeoTIFF at `file` (NaN declared as no-data), through
/// GDAL, under a temporary name in the same directory that is fsynced and renamed over `file`.
/// Throws Error(InvalidArgument) for a size that does not match the values, Error(Io) when GDAL
/// cannot write it.
void writeFloatGeoTiff(const std::filesystem::path& file, const FloatRaster& raster);

}  // namespace vsm::core
