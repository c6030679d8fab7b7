// A connection's life: start, the 503 of a rejected one, graceful shutdown, closing (with a
// linger), and the access-log line and metrics of every response (see connection.hpp).
#include <sys/socket.h>

#include <cerrno>
#include <cstdio>
#include <string>

#include <boost/asio/dispatch.hpp>
#include <boost/asio/post.hpp>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "server/http/connection.hpp"
#include "server/http/server_impl.hpp"

namespace vsm::server::http {

namespace {

/// Longest request target written to the access log.
constexpr std::size_t kLoggedTargetMax = 256;

}  // namespace

std::string endpointText(const tcp::endpoint& endpoint) {
  const auto address = endpoint.address();
  const std::string host = address.to_string();
  return (address.is_v6() ? "[" + host + "]" : host) + ":" + std::to_string(endpoint.port());
}

std::string quoted(std::string_view target) {
  std::string out = "\"";
  for (std::size_t i = 0; i < target.size() && i < kLoggedTargetMax; ++i) {
    const auto c = static_cast<unsigned char>(target[i]);
    if (c == '"' || c == '\\') {
      out += '\\';
      out += static_cast<char>(c);
    } else if (c < 0x20 || c == 0x7f) {
      char hex[8];
      std::snprintf(hex, sizeof hex, "\\x%02x", c);
      out += hex;
    } else {
      out += static_cast<char>(c);
    }
  }
  out += target.size() > kLoggedTargetMax ? "...\"" : "\"";
  return out;
}

Connection::Connection(Server::Impl& server, tcp::socket&& socket, std::string client, bool counted)
    : server_(server),
      stream_(std::move(socket)),
      fileTimer_(stream_.get_executor()),
      streamTimer_(stream_.get_executor()),
      buffer_(server.options.headerLimit + kReadAhead),
      client_(std::move(client)),
      counted_(counted),
      headerDeadline_(Clock::now() + server.options.headerTimeout) {
  error_code ec;
  const auto remote = stream_.socket().remote_endpoint(ec);
  peer_ = ec ? std::string("-") : endpointText(remote);
}

Connection::~Connection() {
  if (bodyStream_) {
    bodyStream_->stop();
  }
  if (counted_) {
    server_.forget(this, client_);
  } else {
    server_.rejecting.fetch_sub(1);
  }
}

void Connection::start() {
  {
    const std::lock_guard lock(probeMutex_);
    probeFd_ = stream_.socket().native_handle();
  }
  net::dispatch(stream_.get_executor(), [self = shared_from_this()] { self->readNext(); });
}

void Connection::reject(std::string message) {
  net::dispatch(
      stream_.get_executor(), [self = shared_from_this(), message = std::move(message)]() mutable {
        Response response =
            errorResponse(503, core::toString(core::ErrorCode::Unavailable), std::move(message));
        response.set("Retry-After", "1");
        self->closing_ = true;
        self->pushError(std::move(response), /*quiet=*/true);
      });
}

void Connection::beginShutdown() {
  net::post(stream_.get_executor(), [self = shared_from_this()] {
    self->shutdown_ = true;
    if (self->streaming_) {
      self->finishStream({});  // a stream never ends by itself: it must not hold the shutdown
      return;
    }
    if (self->idleWait_ ||
        (!self->reading_ && !self->writing_ && !self->lingering_ && self->queue_.empty())) {
      self->closeNow();
    }
  });
}

void Connection::forceClose() {
  net::post(stream_.get_executor(), [self = shared_from_this()] { self->closeNow(); });
}

void Connection::record(const Slot& slot, error_code ec) {
  const double seconds = std::chrono::duration<double>(Clock::now() - slot.start).count();
  const int status = slot.handled.response.status;
  const std::size_t bytes = slot.message ? slot.bodyBytes : 0;
  const std::string_view method = toString(parseMethod(slot.method));
  // A keep-alive connection mostly repeats one kind of request: its metric series are looked up
  // (under the families' locks) only when the kind changes, then updated lock-free.
  if (!series_ || series_->status != status || series_->method != method ||
      series_->route != slot.handled.route) {
    const std::string statusText = std::to_string(status);
    series_ = Series{method,
                     std::string(slot.handled.route),
                     status,
                     &server_.requests.series({method, slot.handled.route, statusText}),
                     &server_.latency.series({slot.handled.route, statusText}),
                     &server_.responseBytes.series({slot.handled.route})};
  }
  series_->requests->inc();
  series_->latency->observe(seconds);
  series_->bytes->inc(static_cast<double>(bytes));
  const core::log::Level level = core::log::level();
  if (slot.quiet && !ec) {
    if (level <= core::log::Level::Debug) {
      core::log::debug("req=" + slot.id + " peer=" + peer_ + " rejected: connection limit");
    }
    return;
  }
  if (level > core::log::Level::Info) {
    return;  // the line would be dropped: do not build it
  }
  char ms[32];
  std::snprintf(ms, sizeof ms, "%.3f", seconds * 1000.0);
  // The method is a token (the parser checked it), the target is quoted.
  std::string line = "access req=" + slot.id + " method=" + slot.method +
                     " target=" + quoted(slot.target) + " status=" + std::to_string(status) +
                     " bytes=" + std::to_string(bytes) + " ms=" + ms + " peer=" + peer_;
  if (ec) {
    line += " error=\"" + ec.message() + "\"";
  }
  core::log::info(line);
}

void Connection::lingerClose() {
  if (closed_ || lingering_) {
    return;
  }
  lingering_ = true;
  error_code ignored;
  stream_.socket().shutdown(tcp::socket::shutdown_send, ignored);
  stream_.expires_after(kLinger);
  drain();
}

void Connection::drain() {
  buffer_.consume(buffer_.size());
  stream_.async_read_some(buffer_.prepare(kReadChunk),
                          [self = shared_from_this()](error_code ec, std::size_t) {
                            if (ec) {
                              self->closeNow();
                            } else {
                              self->drain();
                            }
                          });
}

void Connection::closeNow() {
  if (streaming_) {
    finishStream(net::error::operation_aborted);
    return;
  }
  if (closed_) {
    return;
  }
  closed_ = true;
  endFileWrite();
  error_code ignored;
  stream_.socket().shutdown(tcp::socket::shutdown_both, ignored);
  const std::lock_guard lock(probeMutex_);
  probeFd_ = -1;
  stream_.close();
}

bool Connection::peerGone() const {
  const std::lock_guard lock(probeMutex_);
  if (probeFd_ < 0) {
    return true;
  }
  char byte = 0;
  const ssize_t n = ::recv(probeFd_, &byte, 1, MSG_PEEK | MSG_DONTWAIT);
  // 0: the peer's FIN (after any bytes it sent, which a peek returns first: a client that sent
  // more requests is still there); an error other than "nothing yet": reset.
  return n == 0 || (n < 0 && errno != EAGAIN && errno != EWOULDBLOCK && errno != EINTR);
}

}  // namespace vsm::server::http
