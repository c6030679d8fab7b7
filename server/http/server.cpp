// The acceptor and the admission limits of the HTTP server, and its network threads: binding,
// accepting (with a back-off when descriptors run out), the caps on connections in all and per
// source address (503 with Retry-After beyond them), graceful shutdown. A connection, once
// admitted, is connection.hpp's business. After Boost.Beast's example/advanced/server: one strand
// per connection, error codes instead of exceptions on the network path.
//
// Lock order: Server::Impl::mutex is the only lock here; it is never held while calling into a
// connection, the pipeline or the pools (connections are copied out first).
#include "server/http/server.hpp"

#include <pthread.h>

#include <csignal>

#include <algorithm>

#include <boost/asio/dispatch.hpp>
#include <boost/asio/post.hpp>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "server/http/connection.hpp"
#include "server/http/server_impl.hpp"

namespace vsm::server::http {

namespace {

/// Pause before accepting again after the process ran out of descriptors.
constexpr std::chrono::milliseconds kAcceptBackoff{100};
/// Rejected connections being answered 503 at once, at most (see ServerOptions::maxConnections).
constexpr std::size_t kMaxRejecting = 64;

/// The source address a connection is counted under (limits.connections_per_client): an
/// IPv4-mapped IPv6 address counts as the IPv4 one.
std::string clientOf(const tcp::socket& socket) {
  error_code ec;
  auto address = socket.remote_endpoint(ec).address();
  if (ec) {
    return "-";
  }
  if (address.is_v6() && address.to_v6().is_v4_mapped()) {
    address = net::ip::make_address_v4(net::ip::v4_mapped, address.to_v6());
  }
  return address.to_string();
}

}  // namespace

void Server::Impl::start() {
  error_code ec;
  tcp::resolver resolver(ioc);
  const auto results =
      resolver.resolve(options.host, std::to_string(options.port),
                       tcp::resolver::passive | tcp::resolver::numeric_service, ec);
  if (ec || results.empty()) {
    throw core::Error(core::ErrorCode::InvalidArgument,
                      "cannot resolve listen host '" + options.host + "': " + ec.message());
  }
  const tcp::endpoint endpoint = results.begin()->endpoint();
  const auto fail = [&](std::string_view what) {
    throw core::Error(
        core::ErrorCode::Unavailable,
        "cannot " + std::string(what) + " " + endpointText(endpoint) + ": " + ec.message());
  };
  if (acceptor.open(endpoint.protocol(), ec); ec) {
    fail("open a socket for");
  }
  if (acceptor.set_option(net::socket_base::reuse_address(true), ec); ec) {
    fail("set SO_REUSEADDR on");
  }
  if (acceptor.bind(endpoint, ec); ec) {
    fail("bind");
  }
  if (acceptor.listen(net::socket_base::max_listen_connections, ec); ec) {
    fail("listen on");
  }
  const tcp::endpoint bound = acceptor.local_endpoint(ec);
  boundPort = bound.port();
  boundAddress = endpointText(bound);
  started = true;

  work.emplace(net::make_work_guard(ioc));
  net::dispatch(acceptor.get_executor(), [this] { accept(); });
  for (std::size_t i = 0; i < std::max<std::size_t>(options.ioThreads, 1); ++i) {
    threads.emplace_back([this] {
      // sendfile(2) has no MSG_NOSIGNAL: with SIGPIPE blocked in this thread, a write to a
      // connection the peer closed fails with EPIPE instead of killing the process.
      sigset_t pipe;
      sigemptyset(&pipe);
      sigaddset(&pipe, SIGPIPE);
      pthread_sigmask(SIG_BLOCK, &pipe, nullptr);
      for (;;) {
        try {
          ioc.run();
          return;
        } catch (const std::exception& e) {
          // Handlers report errors by error_code; this is a bug (or out of memory). The connection
          // whose handler threw is gone with its shared_ptr; keep serving the others.
          core::log::error(std::string("network thread: unexpected exception: ") + e.what());
        }
      }
    });
  }
}

void Server::Impl::accept() {
  acceptor.async_accept(net::make_strand(ioc), [this](error_code ec, tcp::socket socket) {
    onAccept(ec, std::move(socket));
  });
}

void Server::Impl::onAccept(error_code ec, tcp::socket socket) {
  if (ec == net::error::operation_aborted || !acceptor.is_open()) {
    return;
  }
  if (ec) {
    core::log::warn("accept: " + ec.message());
    if (ec == net::error::no_descriptors || ec == net::error::no_buffer_space ||
        ec == net::error::no_memory) {
      // Retrying at once would spin: give connections a moment to close.
      acceptRetry.expires_after(kAcceptBackoff);
      acceptRetry.async_wait([this](error_code wait) {
        if (!wait && acceptor.is_open()) {
          accept();
        }
      });
      return;
    }
    accept();
    return;
  }
  error_code ignored;
  socket.set_option(tcp::no_delay(true), ignored);
  std::string client = clientOf(socket);
  bool admit = false;
  bool clientFull = false;
  {
    // Only this strand adds connections, so the counts can only fall before the insert below.
    const std::lock_guard lock(mutex);
    admit = !stopping && connections.size() < options.maxConnections;
    if (admit) {
      const auto it = perClient.find(client);
      clientFull = it != perClient.end() && it->second >= options.maxPerClient;
      admit = !clientFull;
    }
  }
  if (admit) {
    auto connection = std::make_shared<Connection>(*this, std::move(socket), client, true);
    {
      const std::lock_guard lock(mutex);
      admit = !stopping;
      if (admit) {
        connections.emplace(connection.get(), connection);
        ++perClient[client];
        openCount->store(connections.size());
      }
    }
    if (admit) {
      accepted.inc({});
      connection->start();
    }
  } else {
    rejected.inc({});
    std::string message;
    if (clientFull) {
      warnClientFull(client);
      message = "this client address has " + std::to_string(options.maxPerClient) +
                " connections open, its limit; retry shortly";
    } else {
      warnFull();
      message = "the server has " + std::to_string(options.maxConnections) +
                " connections open, its limit; retry shortly";
    }
    // Answering is bounded too (each holds a descriptor): beyond kMaxRejecting in flight, close.
    if (rejecting.fetch_add(1) < std::min(options.maxConnections, kMaxRejecting)) {
      std::make_shared<Connection>(*this, std::move(socket), std::string(), false)
          ->reject(std::move(message));
    } else {
      rejecting.fetch_sub(1);
    }
  }
  accept();
}

void Server::Impl::warnFull() {
  const auto now = Clock::now().time_since_epoch().count();
  auto last = lastFullWarning.load();
  const auto interval = std::chrono::duration_cast<Clock::duration>(std::chrono::seconds(10));
  if (now - last >= interval.count() && lastFullWarning.compare_exchange_strong(last, now)) {
    core::log::warn("connection limit " + std::to_string(options.maxConnections) +
                    " reached: new connections are answered 503 (limits.connections)");
  }
}

void Server::Impl::warnClientFull(const std::string& client) {
  const auto now = Clock::now().time_since_epoch().count();
  auto last = lastClientWarning.load();
  const auto interval = std::chrono::duration_cast<Clock::duration>(std::chrono::seconds(10));
  if (now - last >= interval.count() && lastClientWarning.compare_exchange_strong(last, now)) {
    core::log::warn("client " + client + " reached the limit of " +
                    std::to_string(options.maxPerClient) +
                    " connections per address: its new connections are answered 503 "
                    "(limits.connections_per_client)");
  }
}

std::vector<std::shared_ptr<Connection>> Server::Impl::liveConnections() const {
  std::vector<std::shared_ptr<Connection>> out;
  const std::lock_guard lock(mutex);
  for (const auto& [key, weak] : connections) {
    if (auto connection = weak.lock()) {
      out.push_back(std::move(connection));
    }
  }
  return out;
}

void Server::Impl::forget(const Connection* connection, const std::string& client) {
  const std::lock_guard lock(mutex);
  if (connections.erase(connection) != 0) {
    if (const auto it = perClient.find(client); it != perClient.end() && --it->second == 0) {
      perClient.erase(it);
    }
  }
  openCount->store(connections.size());
  if (connections.empty()) {
    drained.notify_all();
  }
}

void Server::Impl::stop(std::chrono::milliseconds grace) {
  {
    const std::lock_guard lock(mutex);
    if (!started || stopping) {
      return;
    }
    stopping = true;
    deadline = Clock::now() + grace;
  }
  net::post(acceptor.get_executor(), [this] {
    error_code ignored;
    acceptor.close(ignored);
    acceptRetry.cancel();
  });
  for (const auto& connection : liveConnections()) {
    connection->beginShutdown();
  }
  bool late = false;
  {
    std::unique_lock lock(mutex);
    while (!connections.empty() && !cutShort && Clock::now() < deadline) {
      drained.wait_until(lock, deadline);
    }
    late = !connections.empty();
  }
  if (late) {
    core::log::warn("shutdown: closing " + std::to_string(openConnections()) +
                    " connections still busy after the grace period");
    for (const auto& connection : liveConnections()) {
      connection->forceClose();
    }
    std::unique_lock lock(mutex);
    drained.wait_for(lock, std::chrono::seconds(1), [this] { return connections.empty(); });
  }
  work.reset();
  ioc.stop();
  for (std::thread& thread : threads) {
    thread.join();
  }
  threads.clear();
  stopped = true;
}

Server::Server(ServerOptions options, const Pipeline& pipeline, exec::WorkPool& handlers,
               metrics::Registry& metrics)
    : impl_(std::make_unique<Impl>(std::move(options), pipeline, handlers, metrics)) {}

Server::~Server() {
  impl_->stop(std::chrono::milliseconds(0));
}

void Server::start() {
  impl_->start();
}

std::uint16_t Server::port() const {
  return impl_->boundPort;
}

std::string Server::address() const {
  return impl_->boundAddress;
}

std::size_t Server::connections() const {
  return impl_->openConnections();
}

void Server::stop(std::chrono::milliseconds grace) {
  impl_->stop(grace);
}

void Server::cutShort() {
  {
    const std::lock_guard lock(impl_->mutex);
    impl_->cutShort = true;
  }
  impl_->drained.notify_all();
}

}  // namespace vsm::server::http
