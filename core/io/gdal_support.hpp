#pragma once

// Internal to core/io: what the GDAL readers (rasters, texture images) share.

#include <string>

namespace vsm::core::detail {

/// GDAL's raster block cache, unless the user set GDAL_CACHEMAX: GDAL's default (5 % of RAM) would
/// let an import's memory grow with its raster. Readers go around the cache where they can
/// (`DirectIo`); what is left (compressed strips and tiles, texture images) stays inside this.
constexpr long long kGdalBlockCacheBytes = 128ll << 20;

/// Registers GDAL's drivers and bounds its block cache (kGdalBlockCacheBytes), once per process.
void registerGdal();

/// While alive, datasets opened on this thread read uncompressed GeoTIFF windows straight from the
/// file (GTIFF_DIRECT_IO, read at open), bypassing GDAL's block cache: a window of a striped
/// raster then reads its own bytes of each row, not the whole rows into the cache.
class DirectIo {
 public:
  DirectIo();
  ~DirectIo();
  DirectIo(const DirectIo&) = delete;
  DirectIo& operator=(const DirectIo&) = delete;

 private:
  std::string previous_;
  bool hadPrevious_ = false;
};

/// While alive, GDAL's messages on this thread go to our debug log instead of stderr (which would
/// add lines to the one-line errors the CLI promises); failures become Error with
/// lastGdalMessage().
class GdalMessagesToLog {
 public:
  GdalMessagesToLog();
  ~GdalMessagesToLog();
  GdalMessagesToLog(const GdalMessagesToLog&) = delete;
  GdalMessagesToLog& operator=(const GdalMessagesToLog&) = delete;
};

/// GDAL's last error message on this thread, or "unknown GDAL error".
std::string lastGdalMessage();

}  // namespace vsm::core::detail
