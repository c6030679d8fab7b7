#pragma once

// Internal to core/io: what the GDAL readers (rasters, texture images) share.

#include <string>

namespace vsm::core::detail {

/// Registers GDAL's drivers, once per process.
void registerGdal();

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
