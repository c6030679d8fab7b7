#include "core/common/error.hpp"

#include <cerrno>
#include <cstring>

namespace vsm::core {

std::string_view toString(ErrorCode code) {
  switch (code) {
    case ErrorCode::InvalidArgument:
      return "invalid_argument";
    case ErrorCode::NotFound:
      return "not_found";
    case ErrorCode::Conflict:
      return "conflict";
    case ErrorCode::Unavailable:
      return "unavailable";
    case ErrorCode::ResourceExhausted:
      return "resource_exhausted";
    case ErrorCode::Corrupt:
      return "corrupt";
    case ErrorCode::Cancelled:
      return "cancelled";
    case ErrorCode::Io:
      return "io";
    case ErrorCode::Internal:
      return "internal";
  }
  return "internal";
}

void throwIoError(std::string_view what, std::string_view path, int errnum) {
  // Out of descriptors (the process's or the system's): transient, not a broken store, so callers
  // answer "retry shortly" (503) rather than a server error.
  const ErrorCode code =
      errnum == EMFILE || errnum == ENFILE ? ErrorCode::Unavailable : ErrorCode::Io;
  throw Error(code, std::string(what) + " '" + std::string(path) + "': " + std::strerror(errnum));
}

}  // namespace vsm::core
