// A streamed body (Response::stream, the Server-Sent Events of GET /v1/events; see
// connection.hpp): after the header, the stream's bytes are pulled and written whenever the
// previous ones are out and the stream woke the connection, until the stream ends, the client
// goes away (watched by a read on the socket) or a write fails; then the connection closes.
#include <boost/asio/post.hpp>
#include <boost/asio/write.hpp>

#include "server/http/connection.hpp"
#include "server/http/server_impl.hpp"

namespace vsm::server::http {

namespace {

/// How long a streamed body that ended (dropped, or the daemon stopping) may take to write its
/// last bytes when a write is stuck behind a client that does not read; then the connection closes.
constexpr std::chrono::milliseconds kStreamEndGrace{1000};

}  // namespace

void Connection::onStreamHeader(error_code ec) {
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

void Connection::pumpStream() {
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

void Connection::watchPeer() {
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

void Connection::finishStream(error_code ec) {
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

}  // namespace vsm::server::http
