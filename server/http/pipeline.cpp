#include "server/http/pipeline.hpp"

#include <algorithm>
#include <exception>

#include "core/common/log.hpp"

namespace vsm::server::http {

using core::ErrorCode;

namespace {

constexpr std::string_view kUnmatched = "unmatched";
constexpr std::string_view kUnauthorized = "unauthorized";
constexpr std::string_view kOptions = "options";

std::string joinMethods(const std::vector<Method>& methods) {
  std::string out;
  for (const Method m : methods) {
    out += out.empty() ? "" : ", ";
    out += toString(m);
  }
  return out;
}

Response internalError(std::string_view requestId, std::string_view what) {
  core::log::error("req=" + std::string(requestId) + " internal error: " + std::string(what));
  return errorResponse(
      500, core::toString(ErrorCode::Internal),
      "internal error; the server log has the details under request id " + std::string(requestId));
}

}  // namespace

ErrorStatus statusFor(ErrorCode code) {
  switch (code) {
    case ErrorCode::InvalidArgument:
      return {400, false, false};
    case ErrorCode::NotFound:
      return {404, false, false};
    case ErrorCode::Conflict:
    case ErrorCode::Cancelled:
      return {409, false, false};
    case ErrorCode::Unavailable:
    case ErrorCode::ResourceExhausted:
      return {503, true, false};
    case ErrorCode::Corrupt:
    case ErrorCode::Io:
    case ErrorCode::Internal:
      return {500, false, true};
  }
  return {500, false, true};
}

Response errorFor(const core::Error& error, std::string_view requestId) {
  const ErrorStatus mapped = statusFor(error.code());
  const std::string_view code = core::toString(error.code());
  if (mapped.internal) {
    core::log::error("req=" + std::string(requestId) + " " + std::string(code) + ": " +
                     error.what());
    return errorResponse(mapped.status, code,
                         std::string(code) +
                             " error; the server log has the details under "
                             "request id " +
                             std::string(requestId));
  }
  Response response = errorResponse(mapped.status, code, error.what());
  if (mapped.retryAfter) {
    response.set("Retry-After", "1");
  }
  return response;
}

Pipeline::Pipeline(const Router& router, std::string token)
    : router_(router), token_(std::move(token)) {
  paddedToken_ = token_;
  paddedToken_.resize(std::max(kSecretBytes, token_.size()), '\0');
}

/// Compares `presented` with the token in time that depends on neither the token (its bytes or
/// its length) nor where the two differ: every byte of the padded token is looked at, whatever
/// was presented. Only the presented length, which the client knows, may show.
bool Pipeline::sameSecret(std::string_view presented) const {
  const std::size_t n = paddedToken_.size();
  if (presented.size() > n) {
    return false;  // longer than any token can be: says nothing about the token
  }
  // The lengths are compared as data, not by a branch.
  std::size_t diff = presented.size() ^ token_.size();
  for (std::size_t i = 0; i < n; ++i) {
    const auto p = static_cast<unsigned char>(i < presented.size() ? presented[i] : '\0');
    diff |= static_cast<unsigned char>(p ^ static_cast<unsigned char>(paddedToken_[i]));
  }
  // An opaque read, so that the compiler cannot turn the loop into one that stops early.
  volatile std::size_t result = diff;
  return result == 0 && !token_.empty();
}

bool Pipeline::authorized(const Request& request, bool* wrongToken) const {
  *wrongToken = false;
  if (token_.empty()) {
    return true;
  }
  const std::string* header = request.header("authorization");
  if (header == nullptr) {
    return false;
  }
  std::string_view value = *header;
  const std::size_t space = value.find(' ');
  std::string_view scheme = value.substr(0, space);
  std::string_view credentials =
      space == std::string_view::npos ? std::string_view{} : value.substr(space + 1);
  while (credentials.starts_with(' ')) {
    credentials.remove_prefix(1);
  }
  const bool bearer =
      scheme.size() == 6 && (scheme[0] == 'B' || scheme[0] == 'b') && scheme.substr(1) == "earer";
  *wrongToken = true;
  return sameSecret(credentials) && bearer;
}

Handled Pipeline::handle(Request& request) const noexcept {
  return *dispatch(request, false);
}

std::optional<Handled> Pipeline::handleInline(Request& request) const noexcept {
  return dispatch(request, true);
}

std::optional<Handled> Pipeline::authorize(const Request& request) const noexcept {
  if (!isWrite(request.method)) {
    return std::nullopt;
  }
  try {
    bool wrongToken = false;
    if (authorized(request, &wrongToken)) {
      return std::nullopt;
    }
    Handled out{{}, kUnauthorized};
    out.response = errorResponse(401, "unauthorized",
                                 wrongToken ? "the bearer token is not valid"
                                            : "writes need 'Authorization: Bearer <token>'");
    out.response.set("WWW-Authenticate", wrongToken ? R"(Bearer realm="vsm", error="invalid_token")"
                                                    : R"(Bearer realm="vsm")");
    finish(out.response, request.id);
    return out;
  } catch (...) {
    // Only allocation can throw here; refuse rather than let an unchecked write through.
    Handled out{{}, kUnauthorized};
    out.response.status = 503;
    return out;
  }
}

std::optional<Handled> Pipeline::dispatch(Request& request, bool onNetworkThread) const noexcept {
  // The server asked authorize() at header time already; asking again keeps handle() safe for
  // every caller (a few hundred nanoseconds).
  if (std::optional<Handled> refused = authorize(request)) {
    return refused;
  }
  Handled out{{}, kUnmatched};
  try {
    const std::string_view path = request.path();
    RouteMatch match = router_.match(request.method, path);
    if (match.kind != RouteMatch::Kind::NotFound && match.route != nullptr) {
      out.route = match.route->pattern;
    }
    if (match.kind == RouteMatch::Kind::NotFound) {
      out.response = errorResponse(404, core::toString(ErrorCode::NotFound),
                                   "no resource at " + std::string(path));
    } else if (request.method == Method::Options) {
      out.route = kOptions;
      // Plain OPTIONS and CORS preflight alike: what the path supports, and what browsers may send.
      const std::string allowed = joinMethods(match.allowed);
      out.response.status = 204;
      out.response.set("Allow", allowed);
      out.response.set("Access-Control-Allow-Methods", allowed);
      out.response.set("Access-Control-Allow-Headers",
                       "Authorization, Content-Type, If-None-Match, X-Request-Id");
      out.response.set("Access-Control-Max-Age", "600");
      out.response.set("Cache-Control", "no-store");
    } else if (match.kind == RouteMatch::Kind::MethodNotAllowed) {
      out.response = errorResponse(405, "method_not_allowed",
                                   request.methodName + " is not allowed on " + std::string(path) +
                                       " (allowed: " + joinMethods(match.allowed) + ")");
      out.response.set("Allow", joinMethods(match.allowed));
    } else {
      if (onNetworkThread && !match.route->inlineHandler) {
        return std::nullopt;
      }
      request.params = std::move(match.params);
      if (onNetworkThread) {
        std::optional<Response> response = match.route->inlineHandler(request);
        if (!response) {
          return std::nullopt;
        }
        out.response = std::move(*response);
      } else {
        out.response = match.route->handler(request);
      }
    }
  } catch (const core::Error& e) {
    out.response = errorFor(e, request.id);
  } catch (const std::exception& e) {
    out.response = internalError(request.id, e.what());
  } catch (...) {
    out.response = internalError(request.id, "a non-exception was thrown");
  }
  finish(out.response, request.id);
  return out;
}

void Pipeline::finish(Response& response, std::string_view requestId) {
  response.set("Access-Control-Allow-Origin", "*");
  response.set("Access-Control-Expose-Headers",
               "ETag, Location, Retry-After, X-Request-Id, X-VSM-Local2Global, X-VSM-Grid-Size, "
               "X-VSM-Model-Version, X-VSM-Patch-Version, X-VSM-Node");
  response.set("X-Request-Id", std::string(requestId));
  if (response.header("Cache-Control") == nullptr) {
    response.set("Cache-Control", std::string(cache_control::kNoStore));
  }
}

}  // namespace vsm::server::http
