#pragma once

#include <optional>
#include <string>
#include <string_view>

#include "core/common/error.hpp"
#include "server/http/message.hpp"
#include "server/http/router.hpp"

namespace vsm::server::http {

/// How a core::ErrorCode is answered: the one table (see errors in proto/openapi.yaml).
///
/// | code               | status | why                                                        |
/// |--------------------|--------|------------------------------------------------------------|
/// | invalid_argument   | 400    | the request is wrong                                       |
/// | not_found          | 404    |                                                            |
/// | conflict           | 409    | clashes with the current state (model exists, job running) |
/// | cancelled          | 409    | the operation was cancelled (by a DELETE of its job): the  |
/// |                    |        | state changed under the request; retrying as is won't help |
/// | unavailable        | 503    | transient; Retry-After: 1                                  |
/// | resource_exhausted | 503    | the memory budget is full of pinned data: transient too    |
/// |                    |        | (pins are released when requests end); Retry-After: 1     |
/// | corrupt            | 500    | stored data is broken: the server's fault, not the client's|
/// | io                 | 500    |                                                            |
/// | internal           | 500    | a bug                                                      |
///
/// 500s hide the message from the client (it may name server paths); it is logged with the
/// request id, which the client gets in the body and in X-Request-Id.
struct ErrorStatus {
  int status;
  /// Send "Retry-After: 1".
  bool retryAfter;
  /// Log the message and replace it by a pointer to the log.
  bool internal;
};
ErrorStatus statusFor(core::ErrorCode code);

/// The JSON error response for `error` per statusFor(); logs internal ones with `requestId`.
Response errorFor(const core::Error& error, std::string_view requestId);

/// What the pipeline made of a request.
struct Handled {
  Response response;
  /// The matched route's pattern, or "unmatched", "unauthorized", "options": few distinct values,
  /// so fit for a metrics label. Points into the Router or at a literal.
  std::string_view route;
};

/// Everything between a parsed request and its response that does not touch the network: bearer
/// token for writes, CORS preflight, routing (404, 405 with Allow), the handler, and the one catch
/// point turning exceptions into JSON errors. Stateless apart from its configuration: thread-safe.
class Pipeline {
 public:
  /// `router` must outlive the pipeline. `token`: the bearer token writes need; empty = none.
  Pipeline(const Router& router, std::string token);

  /// The decision a request's header alone allows, made before its body is read: a write
  /// without a valid bearer token gets its 401 (finished, route "unauthorized"); nullopt = go on
  /// (read the body, then handle()). `request` needs method, headers and id; its body is not
  /// looked at. The token comparison takes the same time whatever the token and the credentials
  /// presented (up to kSecretBytes; longer ones are refused at once). Never throws.
  std::optional<Handled> authorize(const Request& request) const noexcept;

  /// Tokens up to this length are compared in constant time (Config::validate caps tokens).
  static constexpr std::size_t kSecretBytes = 1024;

  /// Never throws (an exception escaping a handler becomes a 500 with the request id logged).
  /// Runs the handler on the calling thread. `request.id` must be set.
  Handled handle(Request& request) const noexcept;

  /// handle() for a network thread: what needs no blocking — the answers the pipeline makes
  /// itself (401, 404, 405, OPTIONS) and those of the route's inline handler. nullopt when the
  /// route has none or it declined: then handle() must run on the CPU pool. Never throws.
  std::optional<Handled> handleInline(Request& request) const noexcept;

  /// Adds what every response carries: CORS headers, X-Request-Id, and Cache-Control: no-store
  /// unless the handler chose a policy. The server calls it for the responses it makes itself
  /// (400, 413, 431, 503).
  static void finish(Response& response, std::string_view requestId);

 private:
  bool authorized(const Request& request, bool* wrongToken) const;
  bool sameSecret(std::string_view presented) const;
  std::optional<Handled> dispatch(Request& request, bool onNetworkThread) const noexcept;

  const Router& router_;
  std::string token_;
  /// token_ zero-padded to kSecretBytes (or to its own length when longer).
  std::string paddedToken_;
};

}  // namespace vsm::server::http
