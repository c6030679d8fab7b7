#include "core/io/gdal_support.hpp"

#include <cpl_conv.h>
#include <cpl_error.h>
#include <gdal_priv.h>

#include <mutex>

#include "core/common/log.hpp"

namespace vsm::core::detail {
namespace {

void CPL_STDCALL logGdalMessage(CPLErr level, CPLErrorNum /*number*/, const char* message) {
  if (level != CE_Debug) {
    log::debug(std::string("gdal: ") + (message != nullptr ? message : ""));
  }
}

}  // namespace

void registerGdal() {
  static std::once_flag once;
  std::call_once(once, [] {
    GDALAllRegister();
    if (CPLGetConfigOption("GDAL_CACHEMAX", nullptr) == nullptr) {
      GDALSetCacheMax64(kGdalBlockCacheBytes);
    }
  });
}

namespace {
constexpr const char* kDirectIo = "GTIFF_DIRECT_IO";
}

DirectIo::DirectIo() {
  if (const char* value = CPLGetThreadLocalConfigOption(kDirectIo, nullptr)) {
    previous_ = value;
    hadPrevious_ = true;
  }
  CPLSetThreadLocalConfigOption(kDirectIo, "YES");
}

DirectIo::~DirectIo() {
  CPLSetThreadLocalConfigOption(kDirectIo, hadPrevious_ ? previous_.c_str() : nullptr);
}

GdalMessagesToLog::GdalMessagesToLog() {
  CPLPushErrorHandler(logGdalMessage);
}

GdalMessagesToLog::~GdalMessagesToLog() {
  CPLPopErrorHandler();
}

std::string lastGdalMessage() {
  const char* message = CPLGetLastErrorMsg();
  return message != nullptr && *message != '\0' ? message : "unknown GDAL error";
}

}  // namespace vsm::core::detail
