// Reading requests (see connection.hpp): the header first, decided on alone (505, 401 before any of
// the body, 413 for an announced length over the limit), "100 Continue", then the body under the
// read timeout; protocol errors answered by the server itself; pipelining up to maxPipelined
// requests in flight; each request handed to the pipeline, inline on the strand when that needs no
// blocking, else on the CPU pool with its result posted back to the strand.
#include <limits>
#include <string>

#include <boost/asio/post.hpp>
#include <boost/asio/write.hpp>
#include <boost/beast/core/string.hpp>
#include <boost/beast/http/read.hpp>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "server/exec/work_pool.hpp"
#include "server/http/connection.hpp"
#include "server/http/server_impl.hpp"

namespace vsm::server::http {

namespace {

/// The interim response to "Expect: 100-continue", sent once the header has been accepted.
constexpr std::string_view kContinue = "HTTP/1.1 100 Continue\r\n\r\n";

bool isHttpError(const error_code& ec) {
  return ec.category() == bhttp::make_error_code(bhttp::error::bad_target).category();
}

}  // namespace

bool Connection::requestBegun() {
  error_code ec;
  return buffer_.size() > 0 || stream_.socket().available(ec) > 0;
}

void Connection::readNext() {
  // Once the server stops, only a request whose bytes have begun to arrive is still read (a
  // pipelined one behind those in flight); no new one is waited for.
  if (reading_ || closing_ || (shutdown_ && !requestBegun()) || closed_ || lingering_ ||
      queue_.size() >= server_.options.maxPipelined) {
    return;
  }
  if (buffer_.size() == 0 && !queue_.empty()) {
    // Nothing pipelined arrived yet: wait for the queue to drain rather than wait on the socket
    // while busy (an idle timeout then could not tell a slow handler from an idle client).
    return;
  }
  parser_.emplace();
  // No body limit while the header is read: Beast would answer a Content-Length over it with
  // 413 before the request is authorized. onHeader() checks it and sets it for the body. (Not
  // boost::none: Beast 1.74 compares the length with the optional, and none is less than all.)
  parser_->body_limit(std::numeric_limits<std::uint64_t>::max());
  parser_->header_limit(static_cast<std::uint32_t>(server_.options.headerLimit));
  reading_ = true;
  const bool first = nextSeq_ == 0;  // a new connection's deadline runs from the accept
  if (buffer_.size() > 0) {
    if (!first) {
      headerDeadline_ = Clock::now() + server_.options.headerTimeout;
    }
    readHeader();
    return;
  }
  // Idle: wait for the first byte of the next request under the idle timeout (a connection's
  // first request under the header timeout).
  idleWait_ = true;
  if (first) {
    stream_.expires_at(headerDeadline_);
  } else {
    stream_.expires_after(server_.options.idleTimeout);
  }
  stream_.async_read_some(buffer_.prepare(kReadChunk), [self = shared_from_this(), first](
                                                           error_code ec, std::size_t bytes) {
    self->buffer_.commit(bytes);
    self->idleWait_ = false;
    if (ec) {
      self->reading_ = false;
      self->onReadError(ec, first ? Phase::Header : Phase::Idle);
      return;
    }
    if (!first) {
      self->headerDeadline_ = Clock::now() + self->server_.options.headerTimeout;
    }
    self->readHeader();
  });
}

void Connection::readHeader() {
  stream_.expires_at(headerDeadline_);
  bhttp::async_read_header(stream_, buffer_, *parser_,
                           [self = shared_from_this()](error_code ec, std::size_t) {
                             if (ec) {
                               self->reading_ = false;
                               self->onReadError(ec, Phase::Header);
                             } else {
                               self->onHeader();
                             }
                           });
}

void Connection::onHeader() {
  const auto& header = parser_->get();
  Request request;
  request.methodName = std::string(header.method_string());
  request.method = parseMethod(request.methodName);
  request.target = std::string(header.target());
  request.headers.reserve(16);
  for (const auto& field : header) {
    std::string name(field.name_string());
    for (char& c : name) {
      c = (c >= 'A' && c <= 'Z') ? static_cast<char>(c + 32) : c;
    }
    request.headers.emplace_back(std::move(name), std::string(field.value()));
  }
  request.id = requestIdFor(request);
  request.client = client_;
  const bool body = !parser_->is_done();
  if (std::optional<Handled> refused = server_.pipeline.authorize(request)) {
    // Its body is never read: a connection with one still to come is closed after the 401
    // (lingerClose() discards what is in flight, for kLinger at most).
    reading_ = false;
    Slot slot = slotFor(request, header.version());
    slot.close = body || !header.keep_alive();
    closing_ = closing_ || slot.close;
    pushReady(std::move(slot), std::move(*refused));
    return;
  }
  if (const auto length = parser_->content_length();
      length && *length > server_.options.bodyLimit) {
    reading_ = false;
    closing_ = true;
    pushError(bodyTooLarge(), false);
    return;
  }
  parser_->body_limit(server_.options.bodyLimit);  // a chunked body is counted as it comes
  request_ = std::move(request);
  const std::string* expect = request_->header("expect");
  if (body && expect != nullptr && header.version() >= 11 &&
      beast::iequals(*expect, "100-continue")) {
    continuePending_ = true;
    maybeContinue();
    return;
  }
  readBody();
}

void Connection::maybeContinue() {
  if (!continuePending_ || writing_ || closed_ || !queue_.empty()) {
    return;
  }
  continuePending_ = false;
  writing_ = true;
  stream_.expires_after(server_.options.writeTimeout);
  net::async_write(stream_, net::buffer(kContinue.data(), kContinue.size()),
                   [self = shared_from_this()](error_code ec, std::size_t) {
                     self->writing_ = false;
                     if (ec) {
                       if (ec == beast::error::timeout) {
                         self->server_.timeouts.inc({"write"});
                       }
                       self->closeNow();
                       return;
                     }
                     self->readBody();
                   });
}

void Connection::readBody() {
  if (parser_->is_done()) {
    reading_ = false;
    onRequest();
    return;
  }
  stream_.expires_after(server_.options.readTimeout);
  bhttp::async_read(stream_, buffer_, *parser_,
                    [self = shared_from_this()](error_code ec, std::size_t) {
                      self->reading_ = false;
                      if (ec) {
                        self->onReadError(ec, Phase::Body);
                      } else {
                        self->onRequest();
                      }
                    });
}

Response Connection::bodyTooLarge() const {
  return errorResponse(
      413, "payload_too_large",
      "request body larger than " + std::to_string(server_.options.bodyLimit) + " bytes");
}

Connection::Slot Connection::slotFor(const Request& request, unsigned version) {
  Slot slot;
  slot.seq = nextSeq_++;
  slot.start = Clock::now();
  slot.version = version;
  slot.head = request.method == Method::Head;
  slot.method = request.methodName;
  slot.target = request.target;
  slot.id = request.id;
  return slot;
}

void Connection::pushReady(Slot slot, Handled handled) {
  slot.handled = std::move(handled);
  slot.ready = true;
  queue_.push_back(std::move(slot));
  maybeWrite();
  readNext();
}

void Connection::onReadError(error_code ec, Phase phase) {
  if (ec == bhttp::error::end_of_stream || ec == net::error::eof) {
    // The client is done with this connection; answer what it already asked.
    closing_ = true;
    if (queue_.empty()) {
      closeNow();
    }
    return;
  }
  if (ec == beast::error::timeout) {
    const char* name = phase == Phase::Idle ? "idle" : phase == Phase::Header ? "header" : "read";
    server_.timeouts.inc({name});
    core::log::debug("peer=" + peer_ + " " + name + " timeout: closed");
    closeNow();  // the stream closed the socket already
    return;
  }
  if (ec == net::error::operation_aborted || closed_) {
    return;
  }
  if (!isHttpError(ec)) {
    core::log::debug("peer=" + peer_ + " read: " + ec.message());
    closeNow();
    return;
  }
  Response response;
  std::optional<std::string> version;
  if (ec == bhttp::error::body_limit) {
    response = bodyTooLarge();
  } else if (ec == bhttp::error::bad_version && (version = otherVersion()).has_value()) {
    response =
        errorResponse(505, "http_version_not_supported",
                      "HTTP/" + *version + " is not supported; vsmd speaks HTTP/1.1 (and 1.0)");
  } else if (ec == bhttp::error::header_limit) {
    response = errorResponse(431, "headers_too_large",
                             "request line and header larger than " +
                                 std::to_string(server_.options.headerLimit) + " bytes");
  } else {
    response = errorResponse(400, core::toString(core::ErrorCode::InvalidArgument),
                             "malformed HTTP request: " + ec.message());
  }
  // The stream position is unknown after a protocol error: answer, then close.
  closing_ = true;
  pushError(std::move(response), false);
}

std::optional<std::string> Connection::otherVersion() const {
  const auto data = buffer_.cdata();
  const std::string_view text(static_cast<const char*>(data.data()), data.size());
  const std::string_view line = text.substr(0, text.find("\r\n"));
  if (line.size() == text.size() || line.size() < 9) {
    return std::nullopt;
  }
  const std::string_view tail = line.substr(line.size() - 9);  // " HTTP/d.d"
  const auto digit = [](char c) { return c >= '0' && c <= '9'; };
  if (!tail.starts_with(" HTTP/") || !digit(tail[6]) || tail[7] != '.' || !digit(tail[8]) ||
      line.find(' ') == line.size() - 9) {  // method, target and version: two spaces at least
    return std::nullopt;
  }
  return std::string(tail.substr(6));
}

void Connection::pushError(Response response, bool quiet) {
  Slot slot;
  slot.seq = nextSeq_++;
  slot.start = Clock::now();
  if (parser_ && parser_->is_header_done()) {
    slot.method = std::string(parser_->get().method_string());
    slot.target = std::string(parser_->get().target());
  }
  slot.id = newRequestId();
  slot.close = true;
  slot.quiet = quiet;
  slot.ready = true;
  Pipeline::finish(response, slot.id);
  slot.handled = Handled{std::move(response), "unmatched"};
  queue_.push_back(std::move(slot));
  maybeWrite();
}

void Connection::onRequest() {
  BeastRequest message = parser_->release();
  Request request = std::move(*request_);
  request_.reset();
  request.body = std::move(message.body());

  Slot slot;
  slot.seq = nextSeq_++;
  slot.start = Clock::now();
  slot.version = message.version();
  slot.head = request.method == Method::Head;
  slot.close = !message.keep_alive();
  closing_ = closing_ || slot.close;
  const std::uint64_t seq = slot.seq;
  // What needs no blocking is answered here, without a hop to the CPU pool and back: a cached
  // response body, a 304, the pipeline's own errors.
  if (std::optional<Handled> handled = server_.pipeline.handleInline(request)) {
    slot.method = std::move(request.methodName);  // the request is done with
    slot.target = std::move(request.target);
    slot.id = std::move(request.id);
    pushReady(std::move(slot), std::move(*handled));
    return;
  }
  slot.method = request.methodName;
  slot.target = request.target;
  slot.id = request.id;
  queue_.push_back(std::move(slot));
  request.goneProbe = [connection = weak_from_this()] {
    const std::shared_ptr<Connection> alive = connection.lock();
    return !alive || alive->peerGone();
  };

  // The handler runs on the CPU pool; its result comes back to this connection's strand.
  server_.handlers.post([self = shared_from_this(), executor = stream_.get_executor(), seq,
                         request = std::move(request)]() mutable {
    Handled handled = self->server_.pipeline.handle(request);
    net::post(executor, [self, seq, handled = std::move(handled)]() mutable {
      self->onHandled(seq, std::move(handled));
    });
  });
  readNext();
}

void Connection::onHandled(std::uint64_t seq, Handled handled) {
  if (closed_ || queue_.empty() || seq < queue_.front().seq) {
    return;  // the connection went away meanwhile
  }
  Slot& slot = queue_[seq - queue_.front().seq];
  slot.handled = std::move(handled);
  slot.ready = true;
  maybeWrite();
}

}  // namespace vsm::server::http
