// Writing responses in request order (see connection.hpp): the front slot of the queue, once its
// response is ready, is turned into a Beast message and written whole by Beast's serializer (a
// body held in memory: an owned string and shared bytes in one gather write), or handed to
// file_writer.cpp (a file body) or stream_writer.cpp (a streamed body); then the next one, and
// reading goes on.
#include <algorithm>
#include <string>

#include <boost/beast/http/write.hpp>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "server/http/connection.hpp"
#include "server/http/server_impl.hpp"

namespace vsm::server::http {

namespace {

/// True when a header value or name could split the header (CR, LF, NUL).
bool unsafeHeaderText(std::string_view text) {
  // One pass (find_first_of searches the set once per character: a memchr each).
  return std::any_of(text.begin(), text.end(),
                     [](char c) { return c == '\r' || c == '\n' || c == '\0'; });
}

}  // namespace

void Connection::maybeWrite() {
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
  bhttp::async_write(
      stream_, *slot.message,
      [self = shared_from_this()](error_code ec, std::size_t bytes) { self->onWrite(ec, bytes); });
}

std::unique_ptr<BeastResponse> Connection::toBeast(Slot& slot) {
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

void Connection::onWrite(error_code ec, std::size_t) {
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

}  // namespace vsm::server::http
