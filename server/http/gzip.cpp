#include "server/http/gzip.hpp"

#include <zlib.h>

#include <charconv>
#include <limits>

#include "core/common/error.hpp"

namespace vsm::server::http {

namespace {

/// The q-value of one Accept-Encoding element's parameters ("q=0.5"); 1 when none, 0 when
/// malformed (a client that sends nonsense gets the identity encoding).
double qValue(std::string_view params) {
  while (!params.empty()) {
    const std::size_t semi = params.find(';');
    const std::string_view param = trim(params.substr(0, semi));
    params = semi == std::string_view::npos ? std::string_view{} : params.substr(semi + 1);
    if (param.size() >= 2 && (param[0] == 'q' || param[0] == 'Q') && param[1] == '=') {
      const std::string_view number = param.substr(2);
      double q = 0;
      const auto [end, error] = std::from_chars(number.data(), number.data() + number.size(), q);
      if (error != std::errc{} || end != number.data() + number.size() || q < 0 || q > 1) {
        return 0;
      }
      return q;
    }
  }
  return 1;
}

}  // namespace

bool acceptsGzip(const Request& request) {
  const std::string* header = request.header("accept-encoding");
  if (header == nullptr) {
    return false;
  }
  std::string_view rest = *header;
  double gzipQ = -1;  // not named
  double anyQ = -1;
  while (!rest.empty()) {
    const std::size_t comma = rest.find(',');
    const std::string_view element = rest.substr(0, comma);
    rest = comma == std::string_view::npos ? std::string_view{} : rest.substr(comma + 1);
    const std::size_t semi = element.find(';');
    const std::string_view coding = trim(element.substr(0, semi));
    const double q = semi == std::string_view::npos ? 1.0 : qValue(element.substr(semi + 1));
    if (equalsIgnoreCase(coding, "gzip") || equalsIgnoreCase(coding, "x-gzip")) {
      gzipQ = q;
    } else if (coding == "*") {
      anyQ = q;
    }
  }
  return gzipQ >= 0 ? gzipQ > 0 : anyQ > 0;
}

std::string gzip(std::string_view data, int level) {
  // zlib counts in 32 bits; nothing vsmd compresses comes near that.
  if (data.size() > std::numeric_limits<uInt>::max() / 2) {
    throw core::Error(core::ErrorCode::InvalidArgument, "gzip: input over 2 GiB");
  }
  z_stream stream{};
  // 15 window bits + 16: a gzip header and trailer instead of zlib's.
  if (deflateInit2(&stream, level, Z_DEFLATED, 15 + 16, 8, Z_DEFAULT_STRATEGY) != Z_OK) {
    throw core::Error(core::ErrorCode::Internal, "gzip: deflateInit2 failed");
  }
  // deflateBound covers zlib's own header; gzip's is 12 bytes longer.
  std::string out(deflateBound(&stream, static_cast<uLong>(data.size())) + 32, '\0');
  stream.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(data.data()));
  stream.avail_in = static_cast<uInt>(data.size());
  stream.next_out = reinterpret_cast<Bytef*>(out.data());
  stream.avail_out = static_cast<uInt>(out.size());
  const int result = deflate(&stream, Z_FINISH);
  const std::size_t written = stream.total_out;
  deflateEnd(&stream);
  if (result != Z_STREAM_END) {
    throw core::Error(core::ErrorCode::Internal, "gzip: deflate failed");
  }
  out.resize(written);
  return out;
}

void setGzipEncoded(Response& response) {
  response.set("Content-Encoding", "gzip");
  varyOnEncoding(response);
}

void varyOnEncoding(Response& response) {
  response.set("Vary", "Accept-Encoding");
}

}  // namespace vsm::server::http
