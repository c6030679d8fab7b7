#pragma once

#include <stdexcept>
#include <string>
#include <string_view>

namespace vsm::core {

/// What went wrong, independent of transport. The server maps each code to one HTTP status.
enum class ErrorCode {
  InvalidArgument,    ///< the caller's input is wrong (bad option, bad name, unsupported CRS)
  NotFound,           ///< a named file, model or patch does not exist
  Conflict,           ///< the operation clashes with the current state (target exists, ...)
  Unavailable,        ///< temporarily impossible; retry later
  ResourceExhausted,  ///< a budget or limit would be exceeded
  Corrupt,            ///< stored data violates the format or the model's invariants
  Cancelled,          ///< the operation was cancelled by its caller
  Io,                 ///< the operating system failed a read or write
  Internal,           ///< a bug
};

std::string_view toString(ErrorCode code);

/// The one exception type core throws. The message is a single line meant for users.
class Error : public std::runtime_error {
 public:
  Error(ErrorCode code, const std::string& message) : std::runtime_error(message), code_(code) {}
  ErrorCode code() const noexcept { return code_; }

 private:
  ErrorCode code_;
};

/// Throws Error(Io) with `what`, the path and strerror(errno); Error(Unavailable) for EMFILE and
/// ENFILE (out of descriptors: transient).
[[noreturn]] void throwIoError(std::string_view what, std::string_view path, int errnum);

}  // namespace vsm::core
