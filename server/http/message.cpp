#include "server/http/message.hpp"

#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdio>

#include <nlohmann/json.hpp>

#include "core/common/error.hpp"
#include "core/common/random.hpp"

namespace vsm::server::http {

using core::Error;
using core::ErrorCode;

bool equalsIgnoreCase(std::string_view a, std::string_view b) {
  if (a.size() != b.size()) {
    return false;
  }
  for (std::size_t i = 0; i < a.size(); ++i) {
    const auto fold = [](char c) { return c >= 'A' && c <= 'Z' ? static_cast<char>(c + 32) : c; };
    if (fold(a[i]) != fold(b[i])) {
      return false;
    }
  }
  return true;
}

namespace {

int hexValue(char c) {
  if (c >= '0' && c <= '9') {
    return c - '0';
  }
  if (c >= 'a' && c <= 'f') {
    return c - 'a' + 10;
  }
  if (c >= 'A' && c <= 'F') {
    return c - 'A' + 10;
  }
  return -1;
}

}  // namespace

std::string_view toString(Method method) {
  switch (method) {
    case Method::Get:
      return "GET";
    case Method::Head:
      return "HEAD";
    case Method::Post:
      return "POST";
    case Method::Put:
      return "PUT";
    case Method::Patch:
      return "PATCH";
    case Method::Delete:
      return "DELETE";
    case Method::Options:
      return "OPTIONS";
    case Method::Other:
      return "OTHER";
  }
  return "OTHER";
}

Method parseMethod(std::string_view name) {
  for (const Method m : {Method::Get, Method::Head, Method::Post, Method::Put, Method::Patch,
                         Method::Delete, Method::Options}) {
    if (toString(m) == name) {
      return m;
    }
  }
  return Method::Other;
}

bool isWrite(Method method) {
  return method != Method::Get && method != Method::Head && method != Method::Options;
}

std::string_view Request::path() const {
  const std::string_view t = target;
  return t.substr(0, t.find('?'));
}

std::string_view Request::query() const {
  const std::string_view t = target;
  const std::size_t q = t.find('?');
  return q == std::string_view::npos ? std::string_view{} : t.substr(q + 1);
}

const std::string* Request::header(std::string_view name) const {
  for (const auto& [n, v] : headers) {
    if (equalsIgnoreCase(n, name)) {
      return &v;
    }
  }
  return nullptr;
}

const std::string& Request::param(std::string_view name) const {
  const auto it = params.find(name);
  if (it == params.end()) {
    throw Error(ErrorCode::Internal, "route has no parameter '" + std::string(name) + "'");
  }
  return it->second;
}

std::optional<std::string> Request::queryParam(std::string_view name) const {
  std::string_view rest = query();
  while (!rest.empty()) {
    const std::size_t amp = rest.find('&');
    const std::string_view pair = rest.substr(0, amp);
    rest = amp == std::string_view::npos ? std::string_view{} : rest.substr(amp + 1);
    const std::size_t eq = pair.find('=');
    const auto key = percentDecode(pair.substr(0, eq), true);
    if (key && *key == name) {
      if (eq == std::string_view::npos) {
        return std::string();
      }
      if (auto value = percentDecode(pair.substr(eq + 1), true)) {
        return value;
      }
      throw Error(ErrorCode::InvalidArgument,
                  "query parameter '" + std::string(name) + "' has a malformed %-escape");
    }
  }
  return std::nullopt;
}

std::string Response::bodyText() const {
  std::string out;
  if (file.fd >= 0) {
    out.resize(file.size);
    std::size_t done = 0;
    while (done < file.size) {
      const ssize_t n = ::pread(file.fd, out.data() + done, file.size - done,
                                static_cast<off_t>(file.offset + done));
      if (n < 0 && errno == EINTR) {
        continue;
      }
      if (n <= 0) {
        core::throwIoError("cannot read a response body", "fd " + std::to_string(file.fd),
                           n < 0 ? errno : EIO);
      }
      done += static_cast<std::size_t>(n);
    }
    return out;
  }
  out.reserve(bodySize());
  out.append(body);
  out.append(sharedBody);
  return out;
}

void Response::set(std::string_view name, std::string value) {
  std::erase_if(headers, [&](const auto& h) { return equalsIgnoreCase(h.first, name); });
  headers.emplace_back(std::string(name), std::move(value));
}

const std::string* Response::header(std::string_view name) const {
  for (const auto& [n, v] : headers) {
    if (equalsIgnoreCase(n, name)) {
      return &v;
    }
  }
  return nullptr;
}

Response jsonResponse(int status, const nlohmann::json& body) {
  Response response;
  response.status = status;
  response.contentType = "application/json";
  response.body = body.dump();
  return response;
}

Response errorResponse(int status, std::string_view code, std::string_view message) {
  // Messages come from core and may hold bytes that are not UTF-8 (file names): replace them
  // rather than fail to serialise the error.
  const nlohmann::json body = {{"error", {{"code", code}, {"message", message}}}};
  Response response;
  response.status = status;
  response.contentType = "application/json";
  response.body = body.dump(-1, ' ', false, nlohmann::json::error_handler_t::replace);
  return response;
}

nlohmann::json jsonBody(const Request& request) {
  if (const std::string* type = request.header("content-type")) {
    const std::string_view media = trim(std::string_view(*type).substr(0, type->find(';')));
    const bool json =
        equalsIgnoreCase(media, "application/json") ||
        (media.size() > 5 && equalsIgnoreCase(media.substr(media.size() - 5), "+json"));
    if (!json) {
      throw Error(ErrorCode::InvalidArgument,
                  "request body must be application/json, not '" + std::string(media) + "'");
    }
  }
  if (request.body.empty()) {
    throw Error(ErrorCode::InvalidArgument, "request body must be a JSON document");
  }
  // Nesting is bounded before anything deeper is built: every use of a document (dump, compare,
  // items) recurses once per level. `depth` counts the levels around the one starting (0 for the
  // outermost).
  const auto boundDepth = [](int depth, nlohmann::json::parse_event_t event, nlohmann::json&) {
    if (depth >= kMaxJsonDepth && (event == nlohmann::json::parse_event_t::object_start ||
                                   event == nlohmann::json::parse_event_t::array_start)) {
      throw Error(ErrorCode::InvalidArgument,
                  "request body nests deeper than " + std::to_string(kMaxJsonDepth) + " levels");
    }
    return true;
  };
  try {
    return nlohmann::json::parse(request.body, boundDepth);
  } catch (const nlohmann::json::exception& e) {
    // parse_error, and out_of_range for a number beyond double ("1E400"): the client's fault.
    throw Error(ErrorCode::InvalidArgument, std::string("request body is not JSON: ") + e.what());
  }
}

std::string_view opaqueOf(std::string_view tag) {
  tag = trim(tag);
  if (tag.starts_with("W/")) {
    tag.remove_prefix(2);
  }
  if (tag.size() < 2 || tag.front() != '"' || tag.back() != '"') {
    return {};
  }
  return tag.substr(1, tag.size() - 2);
}

std::string strongEtag(std::string_view opaque) {
  return "\"" + std::string(opaque) + "\"";
}

bool ifNoneMatch(const Request& request, std::string_view etag) {
  const std::string* header = request.header("if-none-match");
  const std::string_view wanted = opaqueOf(etag);
  if (header == nullptr) {
    return false;
  }
  std::string_view list = *header;
  if (trim(list) == "*") {
    return true;
  }
  // A list of entity tags: ',' may occur inside an opaque tag, so walk from quote to quote.
  while (!list.empty()) {
    list = trim(list);
    if (list.starts_with(",")) {
      list.remove_prefix(1);
      continue;
    }
    std::size_t start = list.starts_with("W/") ? 2 : 0;
    if (start >= list.size() || list[start] != '"') {
      return false;  // malformed: ignore the whole field (the response is then a full 200)
    }
    const std::size_t end = list.find('"', start + 1);
    if (end == std::string_view::npos) {
      return false;
    }
    if (list.substr(start + 1, end - start - 1) == wanted && !wanted.empty()) {
      return true;
    }
    list.remove_prefix(end + 1);
  }
  return false;
}

Response notModified(std::string_view etag, std::string_view cacheControl) {
  Response response;
  response.status = 304;
  response.set("ETag", std::string(etag));
  response.set("Cache-Control", std::string(cacheControl));
  return response;
}

std::string newRequestId() {
  static const std::uint32_t prefix = core::randomWord();
  static std::atomic<std::uint32_t> counter{0};
  char text[17];
  std::snprintf(text, sizeof text, "%08x%08x", prefix, counter.fetch_add(1) + 1);
  return text;
}

std::string requestIdFor(const Request& request) {
  if (const std::string* id = request.header("x-request-id")) {
    const bool sane =
        !id->empty() && id->size() <= 64 && std::all_of(id->begin(), id->end(), [](char c) {
          return (c >= 'a' && c <= 'z') || (c >= 'A' && c <= 'Z') || (c >= '0' && c <= '9') ||
                 c == '.' || c == '_' || c == '-';
        });
    if (sane) {
      return *id;
    }
  }
  return newRequestId();
}

std::optional<std::string> percentDecode(std::string_view text, bool plusIsSpace) {
  std::string out;
  out.reserve(text.size());
  for (std::size_t i = 0; i < text.size(); ++i) {
    const char c = text[i];
    if (c == '%') {
      if (i + 2 >= text.size()) {
        return std::nullopt;
      }
      const int hi = hexValue(text[i + 1]);
      const int lo = hexValue(text[i + 2]);
      if (hi < 0 || lo < 0) {
        return std::nullopt;
      }
      out += static_cast<char>(hi * 16 + lo);
      i += 2;
    } else if (c == '+' && plusIsSpace) {
      out += ' ';
    } else {
      out += c;
    }
  }
  return out;
}

}  // namespace vsm::server::http
