#include "server/cluster/etcd_client.hpp"

#include <boost/asio/connect.hpp>
#include <boost/asio/io_context.hpp>
#include <boost/asio/ip/tcp.hpp>
#include <boost/beast/core/flat_buffer.hpp>
#include <boost/beast/core/tcp_stream.hpp>
#include <boost/beast/http/read.hpp>
#include <boost/beast/http/string_body.hpp>
#include <boost/beast/http/write.hpp>
#include <charconv>
#include <nlohmann/json.hpp>

#include "core/common/error.hpp"

namespace vsm::server::cluster {

namespace net = boost::asio;
namespace beast = boost::beast;
namespace bhttp = beast::http;
using core::Error;
using core::ErrorCode;
using nlohmann::json;
using tcp = net::ip::tcp;

namespace {

constexpr std::string_view kAlphabet =
    "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";

/// etcd's gateway writes 64-bit integers as JSON strings; accepts numbers too.
std::int64_t integerOf(const json& value) {
  if (value.is_number_integer()) {
    return value.get<std::int64_t>();
  }
  std::int64_t out = 0;
  if (value.is_string()) {
    const std::string& text = value.get_ref<const std::string&>();
    std::from_chars(text.data(), text.data() + text.size(), out);
  }
  return out;
}

/// The smallest key above every key that starts with `prefix` (etcd's range_end for a prefix).
std::string prefixEnd(std::string_view prefix) {
  std::string end(prefix);
  while (!end.empty()) {
    if (static_cast<unsigned char>(end.back()) < 0xff) {
      end.back() = static_cast<char>(static_cast<unsigned char>(end.back()) + 1);
      return end;
    }
    end.pop_back();
  }
  return std::string(1, '\0');  // every key
}

}  // namespace

std::string base64Encode(std::string_view bytes) {
  std::string out;
  out.reserve((bytes.size() + 2) / 3 * 4);
  std::size_t i = 0;
  for (; i + 2 < bytes.size(); i += 3) {
    const auto n = (static_cast<std::uint32_t>(static_cast<unsigned char>(bytes[i])) << 16) |
                   (static_cast<std::uint32_t>(static_cast<unsigned char>(bytes[i + 1])) << 8) |
                   static_cast<unsigned char>(bytes[i + 2]);
    for (int shift = 18; shift >= 0; shift -= 6) {
      out += kAlphabet[(n >> shift) & 63];
    }
  }
  if (const std::size_t left = bytes.size() - i; left > 0) {
    std::uint32_t n = static_cast<std::uint32_t>(static_cast<unsigned char>(bytes[i])) << 16;
    if (left == 2) {
      n |= static_cast<std::uint32_t>(static_cast<unsigned char>(bytes[i + 1])) << 8;
    }
    out += kAlphabet[(n >> 18) & 63];
    out += kAlphabet[(n >> 12) & 63];
    out += left == 2 ? kAlphabet[(n >> 6) & 63] : '=';
    out += '=';
  }
  return out;
}

std::string base64Decode(std::string_view text) {
  if (text.size() % 4 != 0) {
    throw Error(ErrorCode::InvalidArgument, "base64 text of a length not a multiple of 4");
  }
  std::string out;
  out.reserve(text.size() / 4 * 3);
  for (std::size_t i = 0; i < text.size(); i += 4) {
    std::uint32_t n = 0;
    int padding = 0;
    for (std::size_t j = 0; j < 4; ++j) {
      const char c = text[i + j];
      std::size_t value = 0;
      if (c == '=' && i + 4 == text.size() && j >= 2) {
        ++padding;
      } else if (padding > 0 || (value = kAlphabet.find(c)) == std::string_view::npos) {
        throw Error(ErrorCode::InvalidArgument, "text that is not base64");
      }
      n = (n << 6) | static_cast<std::uint32_t>(value);
    }
    out += static_cast<char>((n >> 16) & 0xff);
    if (padding < 2) {
      out += static_cast<char>((n >> 8) & 0xff);
    }
    if (padding < 1) {
      out += static_cast<char>(n & 0xff);
    }
  }
  return out;
}

struct EtcdClient::Impl {
  std::string host;
  std::string port;
  std::chrono::milliseconds timeout;
  net::io_context io;
};

EtcdClient::EtcdClient(std::string_view url, std::chrono::milliseconds timeout)
    : impl_(std::make_unique<Impl>()) {
  std::string_view rest =
      url.substr(url.find("://") == std::string_view::npos ? 0 : url.find("://") + 3);
  rest = rest.substr(0, rest.find('/'));
  const std::size_t colon = rest.rfind(':');
  impl_->host = std::string(rest.substr(0, colon));
  impl_->port = colon == std::string_view::npos ? "2379" : std::string(rest.substr(colon + 1));
  if (impl_->host.size() > 2 && impl_->host.front() == '[') {
    impl_->host = impl_->host.substr(1, impl_->host.size() - 2);
  }
  impl_->timeout = timeout;
}

EtcdClient::~EtcdClient() = default;

json EtcdClient::call(std::string_view path, const json& body) {
  Impl& impl = *impl_;
  const std::string what = "etcd " + std::string(path) + " at " + impl.host + ":" + impl.port;
  impl.io.restart();
  beast::error_code failure;
  tcp::resolver resolver(impl.io);
  const auto endpoints = resolver.resolve(impl.host, impl.port, failure);
  if (failure) {
    throw Error(ErrorCode::Unavailable, what + ": " + failure.message());
  }
  beast::tcp_stream stream(impl.io);
  bhttp::request<bhttp::string_body> request{bhttp::verb::post, std::string(path), 11};
  request.set(bhttp::field::host, impl.host + ":" + impl.port);
  request.set(bhttp::field::content_type, "application/json");
  request.body() = body.dump();
  request.prepare_payload();
  beast::flat_buffer buffer;
  bhttp::response_parser<bhttp::string_body> parser;
  parser.body_limit(std::uint64_t{64} << 20);
  bool done = false;
  // One deadline for the whole call: connect, write and read.
  stream.expires_after(impl.timeout);
  stream.async_connect(endpoints, [&](beast::error_code ec, const tcp::endpoint&) {
    if (ec) {
      failure = ec;
      return;
    }
    bhttp::async_write(stream, request, [&](beast::error_code ec, std::size_t) {
      if (ec) {
        failure = ec;
        return;
      }
      bhttp::async_read(stream, buffer, parser, [&](beast::error_code ec, std::size_t) {
        failure = ec;
        done = !ec;
      });
    });
  });
  impl.io.run();
  if (!done) {
    throw Error(ErrorCode::Unavailable,
                what + ": " + (failure ? failure.message() : std::string("no answer")));
  }
  const auto& response = parser.get();
  json reply = json::parse(response.body(), nullptr, false);
  if (response.result_int() != 200 || reply.is_discarded() || !reply.is_object()) {
    throw Error(ErrorCode::Unavailable, what + ": HTTP " + std::to_string(response.result_int()) +
                                            " " + response.body().substr(0, 200));
  }
  return reply;
}

std::int64_t EtcdClient::grant(std::chrono::seconds ttl) {
  const json reply = call("/v3/lease/grant", {{"TTL", ttl.count()}});
  const std::int64_t id = integerOf(reply.value("ID", json()));
  if (id == 0) {
    throw Error(ErrorCode::Unavailable, "etcd granted no lease: " + reply.dump().substr(0, 200));
  }
  return id;
}

std::int64_t EtcdClient::keepAlive(std::int64_t lease) {
  // A stream in gRPC; through the gateway one request with a body gets one answer.
  const json reply = call("/v3/lease/keepalive", {{"ID", std::to_string(lease)}});
  const json result = reply.value("result", json::object());
  return integerOf(result.value("TTL", json()));
}

void EtcdClient::revoke(std::int64_t lease) {
  call("/v3/lease/revoke", {{"ID", std::to_string(lease)}});
}

void EtcdClient::put(std::string_view key, std::string_view value, std::int64_t lease) {
  call("/v3/kv/put", {{"key", base64Encode(key)},
                      {"value", base64Encode(value)},
                      {"lease", std::to_string(lease)}});
}

std::int64_t EtcdClient::putIfAbsent(std::string_view key, std::string_view value,
                                     std::int64_t lease) {
  const std::string encoded = base64Encode(key);
  const json reply =
      call("/v3/kv/txn", {{"compare", json::array({{{"key", encoded},
                                                    {"target", "CREATE"},
                                                    {"result", "EQUAL"},
                                                    {"create_revision", "0"}}})},
                          {"success", json::array({{{"request_put",
                                                     {{"key", encoded},
                                                      {"value", base64Encode(value)},
                                                      {"lease", std::to_string(lease)}}}}})}});
  if (!reply.value("succeeded", false)) {
    return 0;
  }
  const std::int64_t revision =
      integerOf(reply.value("header", json::object()).value("revision", json()));
  if (revision <= 0) {
    throw Error(ErrorCode::Unavailable,
                "etcd created a key without naming its revision: " + reply.dump().substr(0, 200));
  }
  return revision;
}

std::vector<KeyValue> EtcdClient::range(std::string_view prefix) {
  const json reply = call("/v3/kv/range", {{"key", base64Encode(prefix)},
                                           {"range_end", base64Encode(prefixEnd(prefix))}});
  std::vector<KeyValue> out;
  for (const json& kv : reply.value("kvs", json::array())) {
    KeyValue entry;
    entry.key = base64Decode(kv.value("key", ""));
    entry.value = base64Decode(kv.value("value", ""));
    entry.lease = integerOf(kv.value("lease", json()));
    entry.createRevision = integerOf(kv.value("create_revision", json()));
    out.push_back(std::move(entry));
  }
  return out;
}

}  // namespace vsm::server::cluster
