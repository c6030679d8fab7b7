// The connection of the HTTP server (private to server/http: it includes Beast, so no header
// outside this folder includes it). One class whose members are defined by job, each job in a file
// of its own:
//
//   connection.cpp       life and death: start, reject, shutdown, close, linger, the access log
//   request_reader.cpp   reading requests (header, authorization, 100-continue, body), pipelining,
//                        handing them to the pipeline (inline or on the CPU pool)
//   response_writer.cpp  writing responses in request order: Beast's serializer for a body held in
//                        memory, then on to the next request
//   file_writer.cpp      a body that is a range of a file: the header by sendmsg(2), the body by
//                        sendfile(2)
//   stream_writer.cpp    a streamed body (Server-Sent Events): pulled from a BodyStream until it
//                        or the client ends
//
// Every member is touched only on the connection's strand.
#pragma once

#include <array>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <deque>
#include <memory>
#include <mutex>
#include <optional>
#include <string>
#include <string_view>
#include <utility>

#include <boost/asio/buffer.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/asio/steady_timer.hpp>
#include <boost/beast/core/flat_buffer.hpp>
#include <boost/beast/core/tcp_stream.hpp>
#include <boost/beast/http/message.hpp>
#include <boost/beast/http/parser.hpp>
#include <boost/beast/http/serializer.hpp>
#include <boost/beast/http/string_body.hpp>
#include <boost/optional/optional.hpp>

#include "server/http/message.hpp"
#include "server/http/pipeline.hpp"
#include "server/http/server.hpp"
#include "server/metrics/metrics.hpp"

namespace vsm::server::http {

namespace beast = boost::beast;
namespace bhttp = boost::beast::http;
namespace net = boost::asio;
using tcp = net::ip::tcp;
using beast::error_code;
using Clock = std::chrono::steady_clock;

/// How long a closing connection keeps reading (and discarding) after its last response, so that
/// request bytes still in flight do not make the kernel reset the connection before the client has
/// read that response (413 after an unread body, 503 to a connection over the cap).
inline constexpr std::chrono::milliseconds kLinger{1000};
/// Bytes asked for per raw read (waiting for a request's first bytes, lingering).
inline constexpr std::size_t kReadChunk = 16 * 1024;
/// What a connection's read buffer may hold beyond a header of the largest size: Beast reads in
/// pieces of up to 64 KiB. Bounds what a client can make the server buffer (pipelined requests
/// read ahead, a chunk header or chunk extension without an end: 400 when it overflows).
inline constexpr std::size_t kReadAhead = 64 * 1024;

/// "127.0.0.1:43123", "[::1]:8080".
std::string endpointText(const tcp::endpoint& endpoint);
/// Quotes `target` for the access log: '"', '\\' and control bytes escaped, long ones cut.
std::string quoted(std::string_view target);

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

/// One client connection. Every member is touched only on the connection's strand; handlers run
/// on the CPU pool and post their result back to the strand (inline handlers run on the strand).
class Connection : public std::enable_shared_from_this<Connection> {
 public:
  /// `client`: the source address it is counted under (when `counted`).
  Connection(Server::Impl& server, tcp::socket&& socket, std::string client, bool counted);
  ~Connection();
  Connection(const Connection&) = delete;
  Connection& operator=(const Connection&) = delete;

  /// Starts reading requests.
  void start();
  /// Answers 503 with `message` without reading a request, then closes.
  void reject(std::string message);
  /// Graceful shutdown: no new requests; idle connections close now, busy ones after their last
  /// response.
  void beginShutdown();
  /// The grace period is over.
  void forceClose();
  /// True once the peer closed or reset the connection, or it was closed here: a peek at the
  /// socket (MSG_PEEK, non-blocking) that reads nothing. Any thread (Request::goneProbe).
  bool peerGone() const;

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

  /// Where a read failed: waiting for a request, in its header, in its body.
  enum class Phase { Idle, Header, Body };

  // ---- connection.cpp: closing, the access log ----------------------------------------------
  /// Metrics and the access-log line of a written (or failed) response.
  void record(const Slot& slot, error_code ec);
  /// Half-closes, then discards whatever the client still sends for a moment (see kLinger).
  void lingerClose();
  /// Reads and discards until the client closes or kLinger passes, then closes.
  void drain();
  /// Closes the socket now (a running stream is finished first). Idempotent.
  void closeNow();

  // ---- request_reader.cpp -------------------------------------------------------------------
  /// Bytes of a next request have arrived: read into buffer_, or waiting in the socket.
  bool requestBegun();
  /// Starts reading the next request unless one is being read, the connection is closing or
  /// maxPipelined requests are in flight (onWrite() calls it again as the queue drains).
  void readNext();
  /// The header of a request whose first bytes are here, by headerDeadline_.
  void readHeader();
  /// Decides on the header alone, before any of the body is read: 505 for another HTTP major
  /// version, 401 for a write without the token, 413 for a Content-Length over the limit. Then
  /// answers "Expect: 100-continue" and reads the body.
  void onHeader();
  /// Sends "100 Continue" for the request whose header was accepted, once the responses before
  /// it are written (they must not be interleaved), then reads its body.
  void maybeContinue();
  /// The body of the request whose header was accepted (request_), under the read timeout.
  void readBody();
  /// The 413 for a body over bodyLimit.
  Response bodyTooLarge() const;
  /// A slot for `request` (whose header is read), in request order.
  Slot slotFor(const Request& request, unsigned version);
  /// Queues `slot` answered by `handled` (made on this strand), writes it when its turn comes and
  /// reads on.
  void pushReady(Slot slot, Handled handled);
  /// A read failed: the client left, a timeout (counted by phase), or a protocol error answered
  /// 400, 413, 431 or 505 before the connection closes.
  void onReadError(error_code ec, Phase phase);
  /// "9.9" when the request line in the buffer is well formed but for its HTTP version (Beast
  /// refuses all but 1.0 and 1.1 as bad_version, like garbage where the version should be).
  std::optional<std::string> otherVersion() const;
  /// Queues a response the server made itself, ready to be written; the connection closes after.
  void pushError(Response response, bool quiet);
  /// A whole request is read: answered inline when the pipeline can, else handed to the CPU pool.
  void onRequest();
  /// The CPU pool's answer to request `seq`, back on the strand.
  void onHandled(std::uint64_t seq, Handled handled);

  // ---- response_writer.cpp ------------------------------------------------------------------
  /// Writes the front slot of the queue when its response is ready and nothing is being written:
  /// whole by Beast, by sendHeader() for a file body, by onStreamHeader() for a stream.
  void maybeWrite();
  /// The Beast message of the slot's response: status, the server's own headers, the body or its
  /// length (sets slot.bodyBytes). A status out of range becomes a 500.
  std::unique_ptr<BeastResponse> toBeast(Slot& slot);
  /// The front slot's response is written (or failed): recorded, then the next one, or close.
  void onWrite(error_code ec, std::size_t);

  // ---- file_writer.cpp: a body sent by sendfile(2) (Response::file) -------------------------
  /// Sends the rest of the front slot's header with MSG_MORE, so that the kernel holds it back
  /// and sends it in one segment with the start of the body (nginx's tcp_nopush, without the two
  /// setsockopt calls), then the body file; waits for the socket whenever it is full.
  void sendHeader();
  /// Sends the rest of the front slot's body file; waits for the socket whenever it is full.
  void sendFile();
  /// The body file of the front slot is sent (or failed): its write timer is done with.
  void endFileWrite();
  /// Calls `next` once the socket takes more bytes (under the write timeout of fileTimer_).
  void waitWritable(void (Connection::*next)());

  // ---- stream_writer.cpp: a streamed body (Response::stream) --------------------------------
  /// The header of a streamed response is written: the stream starts, and the socket is watched
  /// for the client going away (nothing else is read from this connection any more).
  void onStreamHeader(error_code ec);
  /// Writes what the stream has ready, unless a write is in flight (its completion pulls again).
  void pumpStream();
  /// Reads (and discards) what the client sends while its stream runs, to notice at once when it
  /// goes away. On the socket itself, not the tcp_stream: no read timeout applies here.
  void watchPeer();
  /// Ends the streamed response at the front of the queue: the stream is stopped, the access log
  /// gets its line (the bytes streamed, the whole duration) and the connection closes. Idempotent.
  void finishStream(error_code ec);

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
  /// The socket's descriptor for peerGone(), -1 once closed; guarded by probeMutex_ so that a
  /// probe never peeks at a descriptor number the process reused.
  mutable std::mutex probeMutex_;
  int probeFd_ = -1;
};

}  // namespace vsm::server::http
