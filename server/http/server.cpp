// The network half of the HTTP server, after Boost.Beast's example/advanced/server: one strand per
// connection (every member of a Connection is touched only on its strand), error codes instead of
// exceptions, and tcp_stream timeouts for every read and write.
//
// Lock order: Server::Impl::mutex is the only lock here; it is never held while calling into a
// connection, the pipeline or the pools (connections are copied out first).
#include "server/http/server.hpp"

#include <pthread.h>
#include <sys/sendfile.h>
#include <sys/socket.h>
#include <sys/uio.h>

#include <csignal>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <condition_variable>
#include <deque>
#include <limits>
#include <mutex>
#include <optional>
#include <thread>
#include <unordered_map>
#include <vector>

#include <boost/asio/buffer.hpp>
#include <boost/asio/dispatch.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/post.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/asio/strand.hpp>
#include <boost/asio/write.hpp>
#include <boost/beast/core/flat_buffer.hpp>
#include <boost/beast/core/string.hpp>
#include <boost/beast/core/tcp_stream.hpp>
#include <boost/beast/http/message.hpp>
#include <boost/beast/http/parser.hpp>
#include <boost/beast/http/read.hpp>
#include <boost/beast/http/serializer.hpp>
#include <boost/beast/http/string_body.hpp>
#include <boost/beast/http/write.hpp>
#include <boost/optional/optional.hpp>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "server/exec/work_pool.hpp"
#include "server/http/pipeline.hpp"
#include "server/metrics/metrics.hpp"

namespace vsm::server::http {

namespace beast = boost::beast;
namespace bhttp = boost::beast::http;
namespace net = boost::asio;
using tcp = net::ip::tcp;
using beast::error_code;
using Clock = std::chrono::steady_clock;

namespace {

/// A response body of two parts written with one gather write: an owned string (JSON, a small
/// header) and bytes owned elsewhere, kept alive by a shared_ptr, written without a copy (a
/// patch's floats straight from the patch cache; see Response::sharedBody).
struct GatherBody {
  struct value_type {
    std::string owned;
    std::string_view shared;
    std::shared_ptr<const void> owner;
  };

  static std::uint64_t size(const value_type& body) {
    return body.owned.size() + body.shared.size();
  }

  class writer {
   public:
    using const_buffers_type = std::array<net::const_buffer, 2>;

    template <bool isRequest, class Fields>
    writer(const bhttp::header<isRequest, Fields>&, const value_type& body) : body_(body) {}

    void init(error_code& ec) { ec = {}; }

    boost::optional<std::pair<const_buffers_type, bool>> get(error_code& ec) {
      ec = {};
      if (done_) {
        return boost::none;
      }
      done_ = true;
      return {{const_buffers_type{net::const_buffer(body_.owned.data(), body_.owned.size()),
                                  net::const_buffer(body_.shared.data(), body_.shared.size())},
               false}};
    }

   private:
    const value_type& body_;
    bool done_ = false;
  };
};

using BeastRequest = bhttp::request<bhttp::string_body>;
using BeastResponse = bhttp::response<GatherBody>;

/// How long a closing connection keeps reading (and discarding) after its last response, so that
/// request bytes still in flight do not make the kernel reset the connection before the client has
/// read that response (413 after an unread body, 503 to a connection over the cap).
constexpr std::chrono::milliseconds kLinger{1000};
/// Bytes asked for per raw read (waiting for a request's first bytes, lingering).
constexpr std::size_t kReadChunk = 16 * 1024;
/// What a connection's read buffer may hold beyond a header of the largest size: Beast reads in
/// pieces of up to 64 KiB. Bounds what a client can make the server buffer (pipelined requests
/// read ahead, a chunk header or chunk extension without an end: 400 when it overflows).
constexpr std::size_t kReadAhead = 64 * 1024;
/// The interim response to "Expect: 100-continue", sent once the header has been accepted.
constexpr std::string_view kContinue = "HTTP/1.1 100 Continue\r\n\r\n";
/// Pause before accepting again after the process ran out of descriptors.
constexpr std::chrono::milliseconds kAcceptBackoff{100};
/// Rejected connections being answered 503 at once, at most (see ServerOptions::maxConnections).
constexpr std::size_t kMaxRejecting = 64;
/// Longest request target written to the access log.
constexpr std::size_t kLoggedTargetMax = 256;
/// How long a streamed body that ended (dropped, or the daemon stopping) may take to write its
/// last bytes when a write is stuck behind a client that does not read; then the connection closes.
constexpr std::chrono::milliseconds kStreamEndGrace{1000};

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

std::string endpointText(const tcp::endpoint& endpoint) {
  const auto address = endpoint.address();
  const std::string host = address.to_string();
  return (address.is_v6() ? "[" + host + "]" : host) + ":" + std::to_string(endpoint.port());
}

/// Quotes `target` for the access log: '"', '\\' and control bytes escaped, long ones cut.
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

/// True when a header value or name could split the header (CR, LF, NUL).
bool unsafeHeaderText(std::string_view text) {
  // One pass (find_first_of searches the set once per character: a memchr each).
  return std::any_of(text.begin(), text.end(),
                     [](char c) { return c == '\r' || c == '\n' || c == '\0'; });
}

bool isHttpError(const error_code& ec) {
  return ec.category() == bhttp::make_error_code(bhttp::error::bad_target).category();
}

}  // namespace

class Connection;

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

/// One client connection. Every member is touched only on the connection's strand; handlers run
/// on the CPU pool and post their result back to the strand (inline handlers run on the strand).
class Connection : public std::enable_shared_from_this<Connection> {
 public:
  /// `client`: the source address it is counted under (when `counted`).
  Connection(Server::Impl& server, tcp::socket&& socket, std::string client, bool counted)
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
  ~Connection() {
    if (bodyStream_) {
      bodyStream_->stop();
    }
    if (counted_) {
      server_.forget(this, client_);
    } else {
      server_.rejecting.fetch_sub(1);
    }
  }
  Connection(const Connection&) = delete;
  Connection& operator=(const Connection&) = delete;

  void start() {
    net::dispatch(stream_.get_executor(), [self = shared_from_this()] { self->readNext(); });
  }

  /// Answers 503 with `message` without reading a request, then closes.
  void reject(std::string message) {
    net::dispatch(stream_.get_executor(),
                  [self = shared_from_this(), message = std::move(message)]() mutable {
                    Response response = errorResponse(
                        503, core::toString(core::ErrorCode::Unavailable), std::move(message));
                    response.set("Retry-After", "1");
                    self->closing_ = true;
                    self->pushError(std::move(response), /*quiet=*/true);
                  });
  }

  /// Graceful shutdown: no new requests; idle connections close now, busy ones after their last
  /// response.
  void beginShutdown() {
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

  /// The grace period is over.
  void forceClose() {
    net::post(stream_.get_executor(), [self = shared_from_this()] { self->closeNow(); });
  }

 private:
  /// A request being handled or a response waiting to be written, in request order.
  struct Slot {
    std::uint64_t seq = 0;
    Clock::time_point start;
    std::string method = "-";
    std::string target = "-";
    std::string id;
    unsigned version = 11;
    bool head = false;
    bool close = false;  // close the connection after this response
    bool quiet = false;  // no access-log line (rejected connections)
    bool ready = false;
    Handled handled;
    std::unique_ptr<BeastResponse> message;  // the serialised form, while being written
    // A body sent from a file (Response::file): the header goes through this serializer, the
    // body by sendfile(2); `fileSent` bytes of it are out.
    std::unique_ptr<bhttp::serializer<false, GatherBody>> serializer;
    std::size_t fileSent = 0;
    /// Body bytes of the response (what Content-Length says; 0 for HEAD and bodiless statuses).
    std::size_t bodyBytes = 0;
  };

  /// Bytes of a next request have arrived: read into buffer_, or waiting in the socket.
  bool requestBegun() {
    error_code ec;
    return buffer_.size() > 0 || stream_.socket().available(ec) > 0;
  }

  void readNext() {
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

  /// The header of a request whose first bytes are here, by headerDeadline_.
  void readHeader() {
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

  /// Decides on the header alone, before any of the body is read: 505 for another HTTP major
  /// version, 401 for a write without the token, 413 for a Content-Length over the limit. Then
  /// answers "Expect: 100-continue" and reads the body.
  void onHeader() {
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

  /// Sends "100 Continue" for the request whose header was accepted, once the responses before
  /// it are written (they must not be interleaved), then reads its body.
  void maybeContinue() {
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

  /// The body of the request whose header was accepted (request_), under the read timeout.
  void readBody() {
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

  Response bodyTooLarge() const {
    return errorResponse(
        413, "payload_too_large",
        "request body larger than " + std::to_string(server_.options.bodyLimit) + " bytes");
  }

  /// A slot for `request` (whose header is read), in request order.
  Slot slotFor(const Request& request, unsigned version) {
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

  /// Queues `slot` answered by `handled` (made on this strand), writes it when its turn comes and
  /// reads on.
  void pushReady(Slot slot, Handled handled) {
    slot.handled = std::move(handled);
    slot.ready = true;
    queue_.push_back(std::move(slot));
    maybeWrite();
    readNext();
  }

  /// Where a read failed: waiting for a request, in its header, in its body.
  enum class Phase { Idle, Header, Body };

  void onReadError(error_code ec, Phase phase) {
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

  /// "9.9" when the request line in the buffer is well formed but for its HTTP version (Beast
  /// refuses all but 1.0 and 1.1 as bad_version, like garbage where the version should be).
  std::optional<std::string> otherVersion() const {
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

  /// Queues a response the server made itself, ready to be written; the connection closes after.
  void pushError(Response response, bool quiet) {
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

  void onRequest() {
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

  void onHandled(std::uint64_t seq, Handled handled) {
    if (closed_ || queue_.empty() || seq < queue_.front().seq) {
      return;  // the connection went away meanwhile
    }
    Slot& slot = queue_[seq - queue_.front().seq];
    slot.handled = std::move(handled);
    slot.ready = true;
    maybeWrite();
  }

  void maybeWrite() {
    if (writing_ || closed_ || queue_.empty() || !queue_.front().ready) {
      return;
    }
    Slot& slot = queue_.front();
    // The last response before closing says so: the client asked, a protocol error, the peer
    // half-closed, or shutdown (then only once nothing else is pending: no request in flight and
    // no bytes of one arrived).
    slot.close = slot.close ||
                 (queue_.size() == 1 && !reading_ && (closing_ || (shutdown_ && !requestBegun())));
    const bool stream = slot.handled.response.stream != nullptr;
    if (stream) {
      slot.close = true;  // a streamed body ends with the connection
      closing_ = true;
    }
    slot.message = toBeast(slot);
    writing_ = true;
    stream_.expires_after(server_.options.writeTimeout);
    if (stream && !slot.head) {
      // The header (the message has no body and no length); then the stream's bytes as they come.
      bhttp::async_write(
          stream_, *slot.message,
          [self = shared_from_this()](error_code ec, std::size_t) { self->onStreamHeader(ec); });
      return;
    }
    if (slot.handled.response.file.fd >= 0 && slot.bodyBytes > 0) {
      // The header by Beast's serializer, the body by sendfile(2): the kernel sends the file's
      // pages without copying them through user space (as nginx serves static files).
      slot.serializer = std::make_unique<bhttp::serializer<false, GatherBody>>(*slot.message);
      slot.serializer->split(true);
      // The timer's handler may already be queued when the write completes (cancel() cannot
      // recall it): it acts only for the write it was started for (see fileWrite_).
      const std::uint64_t write = ++fileWrite_;
      fileTimer_.expires_after(server_.options.writeTimeout);
      fileTimer_.async_wait([self = shared_from_this(), write](error_code wait) {
        if (!wait && self->fileWriting_ && self->fileWrite_ == write) {
          self->server_.timeouts.inc({"write"});
          self->closeNow();
        }
      });
      fileWriting_ = true;
      sendHeader();
      return;
    }
    bhttp::async_write(stream_, *slot.message,
                       [self = shared_from_this()](error_code ec, std::size_t bytes) {
                         self->onWrite(ec, bytes);
                       });
  }

  std::unique_ptr<BeastResponse> toBeast(Slot& slot) {
    Response& r = slot.handled.response;
    if (r.status < 100 || r.status > 599) {
      core::log::error("req=" + slot.id + " handler returned status " + std::to_string(r.status) +
                       " (a bug)");
      r = errorResponse(500, core::toString(core::ErrorCode::Internal), "internal error");
      Pipeline::finish(r, slot.id);
    }
    auto message = std::make_unique<BeastResponse>();
    message->version(slot.version == 10 ? 10 : 11);
    message->result(static_cast<unsigned>(r.status));
    message->set(bhttp::field::server, "vsmd");
    if (!server_.options.node.empty()) {
      message->set("X-VSM-Node", server_.options.node);
    }
    if (!r.contentType.empty()) {
      message->set(bhttp::field::content_type, r.contentType);
    }
    for (const auto& [name, value] : r.headers) {
      if (unsafeHeaderText(name) || unsafeHeaderText(value)) {
        core::log::error("req=" + slot.id + " dropped header '" + quoted(name) +
                         "': CR, LF or NUL (a bug)");
        continue;
      }
      message->set(name, value);
    }
    message->keep_alive(!slot.close);
    const bool bodiless = r.status == 204 || r.status == 304 || r.status < 200;
    if (bodiless) {
      // No body and no Content-Length (RFC 9110 8.6).
    } else if (r.stream) {
      // No length: the body ends when the connection closes (keep_alive(false) above).
    } else if (slot.head) {
      message->content_length(r.bodySize());  // what GET would send; the body itself is not
    } else if (r.file.fd >= 0) {
      // The body goes by sendfile() after the header (maybeWrite); the message carries its length.
      message->content_length(r.file.size);
      message->body().owner = r.bodyOwner;  // the file stays open while the message lives
      slot.bodyBytes = r.file.size;
    } else {
      message->body().owned = std::move(r.body);
      message->body().shared = r.sharedBody;
      message->body().owner = std::move(r.bodyOwner);
      message->prepare_payload();
      slot.bodyBytes = GatherBody::size(message->body());
    }
    return message;
  }

  /// Sends the rest of the front slot's header with MSG_MORE, so that the kernel holds it back
  /// and sends it in one segment with the start of the body (nginx's tcp_nopush, without the two
  /// setsockopt calls), then the body file; waits for the socket whenever it is full.
  void sendHeader() {
    if (closed_ || queue_.empty()) {
      return;
    }
    auto& serializer = *queue_.front().serializer;
    const int socket = stream_.socket().native_handle();
    error_code ec;
    while (!ec && !serializer.is_header_done()) {
      std::array<iovec, 64> parts{};
      std::size_t count = 0;
      serializer.next(ec, [&](error_code&, const auto& buffers) {
        for (auto it = net::buffer_sequence_begin(buffers);
             it != net::buffer_sequence_end(buffers) && count < parts.size(); ++it) {
          const net::const_buffer part = *it;
          parts[count++] = {const_cast<void*>(part.data()), part.size()};
        }
      });
      if (ec) {
        break;
      }
      msghdr message{};
      message.msg_iov = parts.data();
      message.msg_iovlen = count;
      const ssize_t sent = ::sendmsg(socket, &message, MSG_MORE | MSG_NOSIGNAL | MSG_DONTWAIT);
      if (sent >= 0) {
        serializer.consume(static_cast<std::size_t>(sent));
      } else if (errno == EAGAIN || errno == EWOULDBLOCK) {
        waitWritable(&Connection::sendHeader);
        return;
      } else if (errno != EINTR) {
        ec = error_code(errno, boost::system::system_category());
      }
    }
    if (ec) {
      endFileWrite();
      onWrite(ec, 0);
      return;
    }
    sendFile();
  }

  /// Sends the rest of the front slot's body file; waits for the socket whenever it is full.
  void sendFile() {
    if (closed_ || queue_.empty()) {
      return;
    }
    Slot& slot = queue_.front();
    const Response::FileRange& file = slot.handled.response.file;
    tcp::socket& socket = stream_.socket();
    error_code ec;
    if (!nonBlocking_) {
      // sendfile(2) has no MSG_DONTWAIT: the socket itself must not block (set once).
      socket.native_non_blocking(true, ec);
      nonBlocking_ = !ec;
    }
    while (!ec && slot.fileSent < file.size) {
      auto offset = static_cast<off_t>(file.offset + slot.fileSent);
      const ssize_t sent =
          ::sendfile(socket.native_handle(), file.fd, &offset, file.size - slot.fileSent);
      if (sent > 0) {
        slot.fileSent += static_cast<std::size_t>(sent);
      } else if (sent < 0 && errno == EINTR) {
        continue;
      } else if (sent < 0 && (errno == EAGAIN || errno == EWOULDBLOCK)) {
        waitWritable(&Connection::sendFile);
        return;
      } else {
        // 0: the file is shorter than it claimed (a bug in the handler); < 0: a socket error.
        ec = sent == 0 ? net::error::make_error_code(net::error::eof)
                       : error_code(errno, boost::system::system_category());
      }
    }
    endFileWrite();
    onWrite(ec, slot.fileSent);
  }

  /// The body file of the front slot is sent (or failed): its write timer is done with.
  void endFileWrite() {
    fileWriting_ = false;
    fileTimer_.cancel();
  }

  /// Calls `next` once the socket takes more bytes (under the write timeout of fileTimer_).
  void waitWritable(void (Connection::*next)()) {
    stream_.socket().async_wait(tcp::socket::wait_write,
                                [self = shared_from_this(), next](error_code wait) {
                                  if (wait) {
                                    self->endFileWrite();
                                    self->onWrite(wait, 0);
                                  } else {
                                    ((*self).*next)();
                                  }
                                });
  }

  void onWrite(error_code ec, std::size_t) {
    writing_ = false;
    if (queue_.empty()) {
      return;
    }
    Slot slot = std::move(queue_.front());
    queue_.pop_front();
    record(slot, ec);
    if (ec) {
      if (ec == beast::error::timeout) {
        server_.timeouts.inc({"write"});
      }
      closeNow();
      return;
    }
    if (slot.close) {
      lingerClose();
      return;
    }
    maybeWrite();
    readNext();
    maybeContinue();
    if (queue_.empty() && !reading_ && (closing_ || shutdown_)) {
      lingerClose();
    }
  }

  /// Metrics and the access-log line of a written (or failed) response.
  void record(const Slot& slot, error_code ec) {
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

  /// Half-closes, then discards whatever the client still sends for a moment (see kLinger).
  void lingerClose() {
    if (closed_ || lingering_) {
      return;
    }
    lingering_ = true;
    error_code ignored;
    stream_.socket().shutdown(tcp::socket::shutdown_send, ignored);
    stream_.expires_after(kLinger);
    drain();
  }

  void drain() {
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

  // ---- A streamed body (Response::stream) ---------------------------------------------------

  /// The header of a streamed response is written: the stream starts, and the socket is watched
  /// for the client going away (nothing else is read from this connection any more).
  void onStreamHeader(error_code ec) {
    writing_ = false;
    Slot& slot = queue_.front();
    bodyStream_ = slot.handled.response.stream;
    streaming_ = true;
    if (ec || closed_ || shutdown_) {
      finishStream(ec);
      return;
    }
    if (!reading_) {
      watchPeer();
    }
    // The stream may call wake from any thread, after this connection is gone too: it holds the
    // connection weakly and only posts to its strand.
    bodyStream_->start([weak = weak_from_this(), executor = stream_.get_executor()] {
      net::post(executor, [weak] {
        if (const auto self = weak.lock()) {
          self->pumpStream();
        }
      });
    });
    pumpStream();
  }

  /// Writes what the stream has ready, unless a write is in flight (its completion pulls again).
  void pumpStream() {
    if (!streaming_ || closed_) {
      return;
    }
    if (writing_) {
      if (!streamEnding_ && bodyStream_->ended()) {
        // Ended (e.g. dropped for not reading) while a write waits on a full socket: the last
        // bytes get a moment, not the whole write timeout.
        streamEnding_ = true;
        streamTimer_.expires_after(kStreamEndGrace);
        streamTimer_.async_wait([self = shared_from_this()](error_code wait) {
          if (!wait) {
            self->finishStream(beast::error::timeout);
          }
        });
      }
      return;
    }
    streamChunk_.clear();
    streamMore_ = bodyStream_->pull(streamChunk_);
    if (streamChunk_.empty()) {
      if (!streamMore_) {
        finishStream({});
      }
      return;
    }
    writing_ = true;
    stream_.expires_after(server_.options.writeTimeout);
    net::async_write(stream_, net::buffer(streamChunk_),
                     [self = shared_from_this()](error_code ec, std::size_t bytes) {
                       self->writing_ = false;
                       self->streamBytes_ += bytes;
                       if (ec) {
                         if (ec == beast::error::timeout) {
                           self->server_.timeouts.inc({"write"});
                         }
                         self->finishStream(ec);
                       } else if (!self->streamMore_) {
                         self->finishStream({});
                       } else {
                         self->pumpStream();
                       }
                     });
  }

  /// Reads (and discards) what the client sends while its stream runs, to notice at once when it
  /// goes away. On the socket itself, not the tcp_stream: no read timeout applies here.
  void watchPeer() {
    stream_.socket().async_read_some(
        net::buffer(watchBuffer_), [self = shared_from_this()](error_code ec, std::size_t) {
          if (!self->streaming_) {
            return;
          }
          if (ec) {
            self->finishStream(ec == net::error::eof ? error_code{} : ec);
          } else {
            self->watchPeer();
          }
        });
  }

  /// Ends the streamed response at the front of the queue: the stream is stopped, the access log
  /// gets its line (the bytes streamed, the whole duration) and the connection closes. Idempotent.
  void finishStream(error_code ec) {
    if (!streaming_) {
      return;
    }
    streaming_ = false;
    streamTimer_.cancel();
    bodyStream_->stop();
    if (!queue_.empty()) {
      Slot slot = std::move(queue_.front());
      queue_.pop_front();
      slot.bodyBytes = streamBytes_;
      record(slot, ec);
    }
    closeNow();
  }

  void closeNow() {
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
    stream_.close();
  }

  /// The metric series of the last response recorded (see record()).
  struct Series {
    std::string_view method;  // a literal of toString(Method)
    std::string route;
    int status = 0;
    metrics::Counter::Series* requests = nullptr;
    metrics::Histogram::Series* latency = nullptr;
    metrics::Counter::Series* bytes = nullptr;
  };

  Server::Impl& server_;
  std::optional<Series> series_;
  beast::tcp_stream stream_;
  net::steady_timer fileTimer_;    // the write timeout of a body sent by sendfile()
  net::steady_timer streamTimer_;  // the last write of a streamed body that ended (see pumpStream)
  /// The streamed body being written (Response::stream), from its header on; and its state.
  std::shared_ptr<BodyStream> bodyStream_;
  std::string streamChunk_;  // the bytes being written
  std::size_t streamBytes_ = 0;
  std::array<char, 512> watchBuffer_{};  // what the client sends meanwhile, discarded
  bool streaming_ = false;               // bodyStream_ runs (the front slot is its response)
  bool streamMore_ = true;               // the chunk being written is not the stream's last
  bool streamEnding_ = false;    // the stream ended while a write was stuck (streamTimer_ armed)
  std::uint64_t fileWrite_ = 0;  // counts file bodies started; a timer acts for its own only
  bool fileWriting_ = false;     // a file body is being sent (fileTimer_ is armed for it)
  beast::flat_buffer buffer_;
  std::optional<bhttp::request_parser<bhttp::string_body>> parser_;
  /// The request whose header was accepted and whose body is being read.
  std::optional<Request> request_;
  std::deque<Slot> queue_;
  std::uint64_t nextSeq_ = 0;
  std::string peer_;
  const std::string client_;
  const bool counted_;
  /// When the header being read (or the first one of the connection) must be complete.
  Clock::time_point headerDeadline_;
  bool continuePending_ = false;  // "100 Continue" is due once the queue is written
  bool nonBlocking_ = false;      // the socket is in non-blocking mode (for sendfile)
  bool reading_ = false;          // a read is outstanding
  bool idleWait_ = false;         // ... and it waits for the first byte of a request
  bool writing_ = false;
  bool closing_ = false;   // read no more requests; close once the queue is written
  bool shutdown_ = false;  // the server is stopping
  bool lingering_ = false;
  bool closed_ = false;
};

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
