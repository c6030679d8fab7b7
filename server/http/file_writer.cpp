// A body that is a range of an open file (Response::file; see connection.hpp): the header goes
// through Beast's serializer and out by sendmsg(2) with MSG_MORE, the body by sendfile(2), so the
// kernel sends the file's pages without copying them through user space (as nginx serves static
// files). The write timeout is fileTimer_'s, since these writes bypass the tcp_stream.
#include <sys/sendfile.h>
#include <sys/socket.h>
#include <sys/uio.h>

#include <array>
#include <cerrno>

#include "server/http/connection.hpp"
#include "server/http/server_impl.hpp"

namespace vsm::server::http {

void Connection::sendHeader() {
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

void Connection::sendFile() {
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

void Connection::endFileWrite() {
  fileWriting_ = false;
  fileTimer_.cancel();
}

void Connection::waitWritable(void (Connection::*next)()) {
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

}  // namespace vsm::server::http
