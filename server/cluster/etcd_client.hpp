#pragma once

#include <chrono>
#include <cstdint>
#include <memory>
#include <string>
#include <string_view>
#include <vector>

#include <nlohmann/json_fwd.hpp>

namespace vsm::server::cluster {

/// One key of etcd with its value, the lease it is attached to (0 = none) and the etcd revision
/// that created it (greater for every later creation of any key: a key deleted and created again
/// gets a greater one).
struct KeyValue {
  std::string key;
  std::string value;
  std::int64_t lease = 0;
  std::int64_t createRevision = 0;
};

/// The few calls of etcd's v3 API a node needs, through etcd's JSON gateway (POST /v3/...; keys
/// and values travel base64-encoded), over HTTP/1.1 with one deadline for each whole call. No
/// client library: the gateway is part of every etcd since 3.3.
///
/// Every call throws core::Error(Unavailable) when etcd cannot be reached, does not answer within
/// the deadline, or answers with an error; the message names the call.
///
/// Not thread-safe: one thread (the Coordinator's) uses it.
class EtcdClient {
 public:
  /// `url` is "http://HOST:PORT" (Config::validate checks it).
  EtcdClient(std::string_view url, std::chrono::milliseconds timeout);
  ~EtcdClient();
  EtcdClient(const EtcdClient&) = delete;
  EtcdClient& operator=(const EtcdClient&) = delete;

  /// A new lease that expires `ttl` after its last renewal; its id.
  std::int64_t grant(std::chrono::seconds ttl);
  /// Renews `lease`; the seconds it has left, 0 when it has expired (or never existed).
  std::int64_t keepAlive(std::int64_t lease);
  /// Ends `lease` now: every key attached to it is deleted.
  void revoke(std::int64_t lease);
  /// Sets `key` to `value`, attached to `lease`.
  void put(std::string_view key, std::string_view value, std::int64_t lease);
  /// Creates `key` = `value` attached to `lease` unless the key exists (one transaction): the etcd
  /// revision that created it (its KeyValue::createRevision), 0 when the key existed.
  std::int64_t putIfAbsent(std::string_view key, std::string_view value, std::int64_t lease);
  /// Every key that starts with `prefix`, in key order.
  std::vector<KeyValue> range(std::string_view prefix);

 private:
  nlohmann::json call(std::string_view path, const nlohmann::json& body);

  struct Impl;
  std::unique_ptr<Impl> impl_;
};

/// Standard base64 (RFC 4648, with padding), as etcd's gateway writes bytes.
std::string base64Encode(std::string_view bytes);
/// Throws core::Error(InvalidArgument) for text that is not base64.
std::string base64Decode(std::string_view text);

}  // namespace vsm::server::cluster
