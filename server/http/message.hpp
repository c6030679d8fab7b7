#pragma once

#include <cstdint>
#include <functional>
#include <map>
#include <memory>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include <nlohmann/json_fwd.hpp>

#include "core/common/text.hpp"

namespace vsm::server::http {

/// Request methods the server knows; anything else is Other (answered 405 or 501 by routing).
enum class Method { Get, Head, Post, Put, Patch, Delete, Options, Other };

std::string_view toString(Method method);
/// "GET" -> Get; unknown names -> Other. Case-sensitive, as HTTP methods are.
Method parseMethod(std::string_view name);
/// ASCII case-insensitive equality (header field names, tokens such as content codings).
bool equalsIgnoreCase(std::string_view a, std::string_view b);

/// `s` without leading and trailing white space (HTTP's optional whitespace): core's one trim.
using core::trim;

/// POST, PUT, PATCH, DELETE and unknown methods: the ones that need the bearer token.
bool isWrite(Method method);

/// One HTTP request as handlers see it: no Beast types, so handlers and their tests stay light.
struct Request {
  Method method = Method::Get;
  /// The method as sent (for logs, and for Other).
  std::string methodName = "GET";
  /// The request-target as sent: path and query, percent-encoded.
  std::string target = "/";
  /// Header fields, names in lower case, in arrival order.
  std::vector<std::pair<std::string, std::string>> headers;
  std::string body;
  /// Set by the server: "X-Request-Id" when the client sent a sane one, a fresh id otherwise.
  std::string id;
  /// Set by the server: the source address the connection is counted under
  /// (limits.connections_per_client; an IPv4-mapped IPv6 address as the IPv4 one). Empty when
  /// made elsewhere (tests).
  std::string client;
  /// Set by the server: true once the client has closed the connection (or reset it, or the
  /// server closed it), probed without reading anything, from any thread. A handler of long work
  /// asks it between steps and stops when nobody waits for the answer. Empty when made elsewhere
  /// (tests): call clientGone() below.
  std::function<bool()> goneProbe;
  /// Path parameters, percent-decoded; filled in by the Router ("{m}" -> params["m"]).
  std::map<std::string, std::string, std::less<>> params;

  /// The target up to '?', still percent-encoded.
  std::string_view path() const;
  /// The target after '?' (empty when none).
  std::string_view query() const;
  /// The first value of a header field; `name` in any case. nullptr when absent.
  const std::string* header(std::string_view name) const;
  /// goneProbe's answer; false without one.
  bool clientGone() const { return goneProbe && goneProbe(); }
  /// A path parameter. Throws core::Error(Internal) when the route has no such parameter.
  const std::string& param(std::string_view name) const;
  /// The first query parameter `name`, percent- and '+'-decoded; nullopt when absent. Throws
  /// core::Error(InvalidArgument) when its value has a malformed %-escape.
  std::optional<std::string> queryParam(std::string_view name) const;
};

/// A response body written as it is produced, for as long as the connection lasts (a
/// Server-Sent Events stream), instead of one complete body. The server writes the header without
/// Content-Length and with "Connection: close" (the body ends when the connection does), then
/// pulls bytes from the stream on the connection's strand whenever the previous ones are written
/// and the stream woke it. Nothing else is read from or written to such a connection.
///
/// Bounds are the stream's business: what pull() hands over is what the connection holds beyond
/// the socket's buffer, so a stream must keep what it queues bounded (and end itself when a slow
/// reader makes it overflow).
class BodyStream {
 public:
  virtual ~BodyStream() = default;

  /// Called once, on the connection's strand, once the header is written. `wake` asks the
  /// connection to call pull() soon: thread-safe, cheap, never blocks, and does nothing once the
  /// connection is gone. A stream calls it when bytes become ready or it ends.
  virtual void start(std::function<void()> wake) = 0;

  /// Moves the bytes ready now into `out` (empty on entry). Returns false when the stream has
  /// ended: `out` holds its last bytes, after which the connection closes.
  virtual bool pull(std::string& out) = 0;

  /// True once the stream has ended (pull() would return false). Thread-safe. A connection whose
  /// write is stuck behind a reader that does not read checks it to close soon after the end
  /// rather than wait for the write timeout.
  virtual bool ended() const = 0;

  /// The connection is done with the stream (peer gone, write failed, server stopping); `wake`
  /// may still be called, to no effect. Idempotent.
  virtual void stop() noexcept = 0;
};

/// One HTTP response. Every header but Content-Type is in `headers`; the server adds
/// Content-Length, Connection, CORS and X-Request-Id.
struct Response {
  int status = 200;
  std::string contentType;
  std::string body;
  /// More body bytes, sent after `body` straight from where they live (no copy): e.g. a patch's
  /// floats in the patch cache. `bodyOwner` keeps them alive until the response is written. Empty
  /// unless a handler serves shared, immutable data this way.
  std::string_view sharedBody;
  /// Keeps `sharedBody` or `file` valid until the response is written (or dropped).
  std::shared_ptr<const void> bodyOwner;
  /// A body that is a range of an open file (a patch file as stored): when `fd` >= 0, the body is
  /// `size` bytes of it from `offset` on, and `body` and `sharedBody` are empty. The file is kept
  /// open by `bodyOwner` and never written while open. The server sends it with sendfile(2),
  /// which hands the file's pages to the socket without a copy (as nginx serves static files).
  struct FileRange {
    int fd = -1;
    std::size_t offset = 0;
    std::size_t size = 0;
  };
  FileRange file;
  std::vector<std::pair<std::string, std::string>> headers;
  /// A body produced over time (see BodyStream): `body`, `sharedBody` and `file` are then unused
  /// and the connection closes when the stream ends. Null for a complete response.
  std::shared_ptr<BodyStream> stream;

  /// What Content-Length says: file.size for a file body, else body.size() + sharedBody.size().
  std::size_t bodySize() const {
    return file.fd >= 0 ? file.size : body.size() + sharedBody.size();
  }
  /// The whole body in one string (a copy, read from the file for a file body; for tests and
  /// small bodies). Throws core::Error(Io) when the file cannot be read.
  std::string bodyText() const;

  /// Replaces every field `name` (any case) by one with `value`.
  void set(std::string_view name, std::string value);
  /// The first value of a header field; nullptr when absent.
  const std::string* header(std::string_view name) const;
};

/// A response with `body` serialised as JSON (application/json).
Response jsonResponse(int status, const nlohmann::json& body);
/// The one error body: {"error": {"code": code, "message": message}}.
Response errorResponse(int status, std::string_view code, std::string_view message);

/// Deepest nesting of arrays and objects a JSON request body may have.
inline constexpr int kMaxJsonDepth = 64;

/// Parses a JSON request body: the one parser of every POST route. Throws
/// core::Error(InvalidArgument) when it is empty, not JSON, nested deeper than kMaxJsonDepth, or
/// declared with a Content-Type other than application/json (or a +json type).
nlohmann::json jsonBody(const Request& request);

/// Cache-Control values the routes use.
namespace cache_control {
/// Health, readiness, metrics, statistics: always fresh.
inline constexpr std::string_view kNoStore = "no-store";
/// Cacheable, but revalidated with the ETag on every use (model summaries, hierarchies).
inline constexpr std::string_view kRevalidate = "no-cache";
/// Content addressed by version (patch data under a versioned ETag).
inline constexpr std::string_view kImmutable = "public, max-age=31536000, immutable";
/// Patch data, 3D Tiles and terrain tiles at URLs that name no version: a merge changes what
/// they return, so they are revalidated (by ETag, cheaply) after a minute; a minute of staleness
/// in client caches is the trade for fewer round trips.
inline constexpr std::string_view kMinute = "public, max-age=60";
}  // namespace cache_control

/// A strong entity tag: `opaque` in double quotes (opaque must not contain '"').
std::string strongEtag(std::string_view opaque);
/// The opaque part of an entity tag, without W/ and quotes; "" for junk.
std::string_view opaqueOf(std::string_view tag);
/// True when the request's If-None-Match lists `etag` (weak comparison, RFC 9110 13.1.2) or is
/// "*": the client's copy is current and a GET may be answered 304.
bool ifNoneMatch(const Request& request, std::string_view etag);
/// 304 Not Modified for `etag`, without a body, keeping the validator and the cache policy.
Response notModified(std::string_view etag, std::string_view cacheControl);

/// A fresh request id (16 hex digits, unique within the process, unpredictable across restarts).
std::string newRequestId();
/// The client's X-Request-Id when it is 1..64 characters of [A-Za-z0-9._-]; a new id otherwise.
std::string requestIdFor(const Request& request);

/// Decodes %XX escapes (and '+' as space when `plusIsSpace`); nullopt on a malformed escape.
std::optional<std::string> percentDecode(std::string_view text, bool plusIsSpace);

}  // namespace vsm::server::http
