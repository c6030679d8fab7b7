#pragma once

#include <array>
#include <cstddef>
#include <filesystem>
#include <functional>
#include <span>
#include <vector>

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

/// A one-band float32 raster made in strips of rows, so that writing it never holds more than one
/// strip (a height export of any size in bounded memory).
struct StripRaster {
  /// Rows per strip: the GeoTIFF's tile height, so each strip fills one row of tiles.
  static constexpr int kRows = 256;
  int width = 0;
  int height = 0;
  /// As FloatRaster's.
  std::array<double, 6> geoTransform{0, 1, 0, 0, 0, -1};
  bool wgs84 = false;
  /// Fills `values` (rows x width, top row first; NaN is no-data) with rows [row, row + rows) of
  /// the raster; rows <= kRows. Called once per strip, top to bottom; what it throws is thrown
  /// by the writer.
  std::function<void(int row, int rows, std::span<float> values)> fill;
};

/// Writes `raster` as a cloud-optimised GeoTIFF (GDAL's COG driver: 256 x 256 tiles, DEFLATE with
/// the floating-point predictor, the header and tile index before the tiles, no overviews) with
/// NaN as no-data, under a temporary name in the same directory that is fsynced and renamed over
/// `file`. Memory: about one strip (width x kRows floats) and GDAL's block cache. Throws
/// Error(InvalidArgument) for an empty raster, Error(Io) when GDAL cannot write it, and what
/// `fill` throws.
void writeCogGeoTiff(const std::filesystem::path& file, const StripRaster& raster);
/// The same file's bytes, made in memory (GDAL's /vsimem/).
std::vector<std::byte> encodeCogGeoTiff(const StripRaster& raster);

}  // namespace vsm::core
