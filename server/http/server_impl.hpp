// Server::Impl: the acceptor, the admission limits and the network threads (private to
// server/http; defined in server.cpp). Connections reach it for the options, the pipeline, the CPU
// pool and the metrics, and to be forgotten when they end. `mutex` is the only lock (its order:
// server.cpp).
#pragma once

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <thread>
#include <unordered_map>
#include <vector>

#include <boost/asio/executor_work_guard.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/strand.hpp>

#include "server/http/connection.hpp"
#include "server/http/server.hpp"
#include "server/metrics/metrics.hpp"

namespace vsm::server::exec {
class WorkPool;
}

namespace vsm::server::http {

struct Server::Impl {
  Impl(ServerOptions o, const Pipeline& p, exec::WorkPool& h, metrics::Registry& m)
      : options(std::move(o)),
        pipeline(p),
        handlers(h),
        requests(m.counter("vsm_http_requests_total", "HTTP requests answered",
                           {"method", "route", "status"})),
        latency(m.histogram("vsm_http_request_duration_seconds",
                            "Time from a request's last byte read to its response's last byte "
                            "written",
                            {"route", "status"}, metrics::latencyBuckets())),
        responseBytes(m.counter("vsm_http_response_body_bytes_total", "Response body bytes written",
                                {"route"})),
        accepted(m.counter("vsm_http_connections_total", "Connections accepted")),
        rejected(m.counter("vsm_http_connections_rejected_total",
                           "Connections answered 503 (or closed) because the cap was reached")),
        timeouts(
            m.counter("vsm_http_timeouts_total", "Connections closed by a timeout", {"phase"})),
        acceptor(net::make_strand(ioc)),
        acceptRetry(acceptor.get_executor()) {
    for (const std::string_view phase : {"idle", "header", "read", "write"}) {
      timeouts.inc({phase}, 0);  // every series present from the start
    }
    // The registry may outlive the server: the collector holds the counter, not the server.
    m.collector([count = openCount] {
      metrics::Snapshot open{
          "vsm_http_connections_open", "Connections open now", metrics::Type::Gauge, {}, {}};
      open.samples.push_back({{}, static_cast<double>(count->load())});
      return std::vector<metrics::Snapshot>{std::move(open)};
    });
  }

  void start();
  void accept();
  void onAccept(error_code ec, tcp::socket socket);
  void stop(std::chrono::milliseconds grace);
  void forget(const Connection* connection, const std::string& client);
  std::size_t openConnections() const {
    const std::lock_guard lock(mutex);
    return connections.size();
  }
  std::vector<std::shared_ptr<Connection>> liveConnections() const;
  void warnFull();
  void warnClientFull(const std::string& client);

  const ServerOptions options;
  const Pipeline& pipeline;
  exec::WorkPool& handlers;
  metrics::Counter& requests;
  metrics::Histogram& latency;
  metrics::Counter& responseBytes;
  metrics::Counter& accepted;
  metrics::Counter& rejected;
  metrics::Counter& timeouts;

  mutable std::mutex mutex;  // guards connections, perClient, stopping, deadline, cutShort
  std::condition_variable drained;
  std::unordered_map<const Connection*, std::weak_ptr<Connection>> connections;
  /// Open (counted) connections per source address; addresses with none are not kept.
  std::unordered_map<std::string, std::size_t> perClient;
  std::shared_ptr<std::atomic<std::size_t>> openCount =
      std::make_shared<std::atomic<std::size_t>>(0);  // connections.size(), for the collector
  bool stopping = false;
  bool cutShort = false;
  Clock::time_point deadline;

  std::atomic<std::size_t> rejecting{0};  // rejected connections still being answered
  std::atomic<Clock::rep> lastFullWarning{0};
  std::atomic<Clock::rep> lastClientWarning{0};
  std::string boundAddress;
  std::uint16_t boundPort = 0;
  bool started = false;
  bool stopped = false;

  // Declared after everything a Connection touches in its destructor: destroying the io_context
  // destroys the handlers still queued in it, and with them the last references to connections.
  net::io_context ioc;
  tcp::acceptor acceptor;  // used on its own strand only
  net::steady_timer acceptRetry;
  std::optional<net::executor_work_guard<net::io_context::executor_type>> work;
  std::vector<std::thread> threads;
};

}  // namespace vsm::server::http
