#pragma once

#include <string>
#include <string_view>

#include "server/http/message.hpp"

namespace vsm::server::http {

/// True when the request's Accept-Encoding allows gzip: it names "gzip" (or "x-gzip"), or "*",
/// with a q-value above 0 (RFC 9110 §12.5.3). No Accept-Encoding, or "gzip;q=0", is false: a
/// client that did not ask gets the identity encoding.
bool acceptsGzip(const Request& request);

/// `data` as one gzip member (RFC 1952: deflate at `level`, 1 fastest to 9 smallest, with CRC-32
/// and size trailer), through zlib. Throws core::Error(Internal) when zlib fails (out of memory).
std::string gzip(std::string_view data, int level = 6);

/// Marks `response`, whose body is gzip(...) output, as gzip-encoded ("Content-Encoding: gzip").
/// Every response of a route that may gzip carries "Vary: Accept-Encoding" (varyOnEncoding), the
/// gzipped and the plain one alike, so caches keep them apart.
void setGzipEncoded(Response& response);
void varyOnEncoding(Response& response);

}  // namespace vsm::server::http
