#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <string>

namespace vsm::server::exec {
class WorkPool;
}
namespace vsm::server::metrics {
class Registry;
}

namespace vsm::server::http {

class Pipeline;

/// Limits and threads of the HTTP server (see Limits in server/config for their meaning). The
/// defaults of the limits are the daemon's: server/config's Limits takes them from here.
struct ServerOptions {
  std::string host = "127.0.0.1";
  std::uint16_t port = 0;
  std::size_t ioThreads = 1;
  std::size_t bodyLimit = 1024 * 1024;
  std::size_t headerLimit = 16 * 1024;
  std::chrono::milliseconds headerTimeout{10'000};
  std::chrono::milliseconds readTimeout{30'000};
  std::chrono::milliseconds idleTimeout{60'000};
  std::chrono::milliseconds writeTimeout{60'000};
  /// Connections served at once; beyond it up to 64 more are answered 503 and closed. The process
  /// holds a descriptor for each.
  std::size_t maxConnections = 512;
  /// Connections of one source address served at once; beyond it answered 503 and closed like
  /// those over maxConnections.
  std::size_t maxPerClient = 256;
  std::size_t maxPipelined = 8;
  /// In a cluster, this node's name: every response then carries "X-VSM-Node: <node>".
  std::string node;
};

/// The HTTP/1.1 server (Boost.Beast, kept out of this header): an acceptor, one strand per
/// connection, keep-alive and pipelining with at most maxPipelined requests per connection being
/// handled or waiting to be written (reading pauses at the cap), explicit limits (body, header,
/// read/idle/write timeouts, connections) and error codes rather than exceptions on the network
/// path. A request is first offered to Pipeline::handleInline() on the network thread (answers
/// that need no blocking: the pipeline's own errors, a route's InlineHandler such as a cached
/// response body); everything else is handed to `handlers` (the CPU pool), so network threads never
/// run a Handler.
///
/// A request's header is read first (by headerTimeout, counted from the accept for a
/// connection's first request) and decided on alone: a write without a valid token gets
/// Pipeline::authorize()'s 401 before any of its body is read (the connection then closes when a
/// body was announced), "Expect: 100-continue" is answered only after that; then the body is
/// read under readTimeout.
///
/// Protocol errors are answered by the server itself and close the connection: malformed request
/// 400, body over the limit 413, header over the limit 431, an HTTP major version other than 1
/// 505, connection over the cap (or over maxPerClient for its source address) 503 with
/// Retry-After. Every request gets one access-log line and is counted in `metrics`
/// (vsm_http_requests_total, vsm_http_request_duration_seconds, ...).
///
/// Thread-safety: start() and stop() from one controlling thread (not a network or handler
/// thread); port(), address(), connections() and cutShort() from any thread.
class Server {
 public:
  /// `pipeline`, `handlers` and `metrics` must outlive the server; `handlers` must also stay
  /// running until stop() returned. Registers the server's metric families in `metrics`.
  Server(ServerOptions options, const Pipeline& pipeline, exec::WorkPool& handlers,
         metrics::Registry& metrics);
  /// stop() with no grace when still running.
  ~Server();
  Server(const Server&) = delete;
  Server& operator=(const Server&) = delete;

  /// Binds, listens and starts the network threads. Throws core::Error(InvalidArgument) when the
  /// host does not resolve, core::Error(Unavailable) when the address cannot be bound.
  void start();

  /// The bound port (the real one when options.port was 0). Valid after start().
  std::uint16_t port() const;
  /// "127.0.0.1:43123", "[::1]:8080": the bound address. Valid after start().
  std::string address() const;
  /// Connections open now (rejected ones not counted).
  std::size_t connections() const;

  /// Graceful shutdown: stops accepting, closes idle connections, lets requests that are being
  /// read, handled or written finish (the last response of a connection says Connection: close),
  /// and after `grace` closes whatever is left. Returns when the network threads have ended.
  /// Handlers still running on the CPU pool then (a hung one) are not waited for: the caller
  /// joins that pool before destroying the server. Idempotent.
  void stop(std::chrono::milliseconds grace);

  /// Ends the grace period of a running stop() now (a second SIGTERM). Thread-safe.
  void cutShort();

  struct Impl;  // public so the connection class in the .cpp can name it

 private:
  std::unique_ptr<Impl> impl_;
};

}  // namespace vsm::server::http
