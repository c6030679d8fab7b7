#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <optional>
#include <string>
#include <string_view>
#include <utility>
#include <vector>

#include <nlohmann/json_fwd.hpp>

#include "core/cache/patch_cache.hpp"
#include "core/common/log.hpp"
#include "server/events/event_hub.hpp"
#include "server/http/server.hpp"

namespace vsm::server {

/// A host and a port to listen on: "127.0.0.1:8080", "[::1]:8080", "0.0.0.0:0" (0 = any free
/// port). A small value type whose toString() and parse() round-trip.
struct ListenAddress {
  std::string host = "127.0.0.1";
  std::uint16_t port = 8080;

  std::string toString() const;
  /// Throws core::Error(InvalidArgument) unless `text` is HOST:PORT with a non-empty host (IPv6 in
  /// brackets) and a port in 0..65535.
  static ListenAddress parse(std::string_view text);
  friend bool operator==(const ListenAddress&, const ListenAddress&) = default;
};

/// Bounds on what one client can make the server hold or wait for. The defaults of those the HTTP
/// server and the event hub enforce are theirs (http::ServerOptions, events::HubOptions), stated
/// there once.
struct Limits {
  /// Largest request body; larger ones are answered 413 and the connection is closed.
  std::size_t bodyBytes = http::ServerOptions{}.bodyLimit;
  /// Largest request line plus header fields; larger ones are answered 431.
  std::size_t headerBytes = http::ServerOptions{}.headerLimit;
  /// Time from a request's first byte to the end of its header (for a new connection: from
  /// accepting it). Shorter than readTimeout: a header is small, and slow headers hold a
  /// connection without the server being able to tell who is asking for what.
  std::chrono::milliseconds headerTimeout = http::ServerOptions{}.headerTimeout;
  /// Time from the end of a request's header to the end of its body.
  std::chrono::milliseconds readTimeout = http::ServerOptions{}.readTimeout;
  /// Time a connection may wait for its next request (keep-alive) or its first one.
  std::chrono::milliseconds idleTimeout = http::ServerOptions{}.idleTimeout;
  /// Time to write one response.
  std::chrono::milliseconds writeTimeout = http::ServerOptions{}.writeTimeout;
  /// Open connections; one more is answered 503 with Retry-After and closed.
  std::size_t connections = http::ServerOptions{}.maxConnections;
  /// Open connections from one source address (loopback included); one more is answered 503
  /// with Retry-After and closed while other addresses are still served.
  std::size_t connectionsPerClient = http::ServerOptions{}.maxPerClient;
  /// Pipelined requests of one connection being handled or waiting to be written; the server
  /// stops reading the connection while it has this many.
  std::size_t pipelinedResponses = http::ServerOptions{}.maxPipelined;
  /// Pixels of a texture file the server decodes (width x height from the file's header, checked
  /// before anything is allocated); larger ones are refused. 16384 x 16384 by default.
  std::size_t texturePixels = std::size_t{16384} * 16384;
  /// Subscribers of the event stream (GET /v1/events) at once; one more is answered 503 with
  /// Retry-After. Each is also a connection (limits.connections).
  std::size_t eventSubscribers = events::HubOptions{}.maxSubscribers;
  /// Subscribers of the event stream from one source address at once; one more from it is
  /// answered 503 with Retry-After while other addresses still get a stream.
  std::size_t eventSubscribersPerClient = events::HubOptions{}.maxSubscribersPerClient;
  /// Models open at once (served, being opened or being imported); an import beyond it is refused
  /// (409) and a model directory beyond it is skipped with a warning at start. Each writable
  /// model holds its writer lock's descriptor, counted in the descriptor plan.
  std::size_t models = 256;
  /// Diffs (GET .../diff, .../diff.png) running at once; one more is answered 503 with
  /// Retry-After (0 refuses them all).
  std::size_t diffs = 2;
  /// How long one diff may run before it is stopped (503); 0 = no deadline.
  std::chrono::milliseconds diffTimeout{60'000};
  /// On SIGTERM/SIGINT, how long in-flight requests may take before connections are closed.
  std::chrono::milliseconds shutdownGrace{10'000};
};

/// Sizes of the thread pools.
struct ThreadCounts {
  /// Network threads (accept, read, write; they never block).
  std::size_t io = 2;
  /// Request handlers (disk reads, decoding, encoding); 0 = one per hardware thread.
  std::size_t cpu = 0;
  /// Long jobs (merges, imports), separate so they cannot starve request handling.
  std::size_t jobs = 2;
};

/// Membership of a cluster of nodes serving one shared data root (see server/cluster/). Without a
/// coordinator the daemon works alone.
struct ClusterConfig {
  /// etcd's client URL, "http://HOST:PORT" (its v3 JSON API); empty = no cluster.
  std::string coordinator;
  /// This node's name, unique in the cluster: 1 to 32 of [A-Za-z0-9_-]. Defaults to the host name.
  std::string node;
  /// The URL other nodes and the front reach this node by ("http://HOST:PORT", no path); redirects
  /// to the writer of a model name it. Defaults to http://<listen address>.
  std::string advertise;
  /// The etcd lease of the node's writer roles: when the node stops renewing it, another node
  /// takes its models over after this long.
  std::chrono::milliseconds leaseTtl{10'000};
};

/// The daemon's configuration: defaults here, then a JSON file (--config), then command-line
/// flags, each overriding the one before. Keys are dotted paths ("limits.body_bytes"); in a file
/// they may be written nested ({"limits": {"body_bytes": "1MiB"}}) or dotted.
///
/// Value syntax: sizes are bytes as a number or a string with a suffix B, KiB, MiB, GiB, TiB
/// (powers of 1024) or KB, MB, GB, TB (powers of 1000), e.g. "512MiB", "1.5GB"; durations are
/// seconds as a number or a string with a suffix ms, s, m, h, e.g. "250ms", "30s".
struct Config {
  ListenAddress listen;
  /// Where model directories live.
  std::filesystem::path dataRoot = "/var/lib/vsm";
  /// One budget (bytes) for the patch data of all open models.
  std::size_t memoryBudget = std::size_t{1} << 30;
  core::EvictionPolicy cachePolicy = core::EvictionPolicy::CostAwareClock;
  /// Revisions every model keeps (the latest included) when a job publishes a new one: older
  /// ones can be read (?rev=N) and restored. At least 2.
  std::size_t keepRevisions = 8;
  /// The time floor beside the count: a revision is kept while the one that replaced it is
  /// younger than this, so that a replica re-reading it (a large model on a slow disk) is not
  /// left without its folders by a writer publishing fast. 0: the count alone.
  std::chrono::milliseconds keepRevisionsSeconds{60'000};
  /// Bearer token required for writes (POST, PUT, PATCH, DELETE); empty = writes are open.
  std::string token;
  /// A file holding the token (its first line), so that it stays out of `ps`; read by
  /// parseCommandLine() (see loadTokenFile). Not both this and `token`.
  std::filesystem::path tokenFile;
  /// When set, the bound port is written there (atomically) once listening; for tests and
  /// supervisors that start the daemon on port 0.
  std::filesystem::path portFile;
  /// When set, the files of the browser viewer (client-examples/web, built) are served from this
  /// directory at /viewer/; empty = no /viewer/ route.
  std::filesystem::path viewerDir;
  core::log::Level logLevel = core::log::Level::Info;
  Limits limits;
  ThreadCounts threads;
  ClusterConfig cluster;

  /// Sets one key from a JSON value (a string is accepted wherever a number is, "--set" style).
  /// Throws core::Error(InvalidArgument) naming the key on an unknown key or a bad value.
  void set(std::string_view key, const nlohmann::json& value);

  /// Throws core::Error(InvalidArgument) naming the first key whose value is out of range.
  void validate() const;

  /// The effective configuration as "key=value" pairs in a fixed order, in the syntax set()
  /// accepts; the token is shown as "(redacted)" or "(none)".
  std::vector<std::pair<std::string, std::string>> describe() const;
};

/// Applies every key of `json` (nested objects are flattened to dotted keys) to `config`;
/// keys not present keep their value. Throws core::Error(InvalidArgument).
void from_json(const nlohmann::json& json, Config& config);

/// Parses "1048576", "64MiB", "1.5GB" (see Config). Throws core::Error(InvalidArgument).
std::size_t parseSize(std::string_view text);
/// The shortest exact form parseSize() accepts: "64MiB", "1000KB", "1234".
std::string formatSize(std::size_t bytes);
/// Parses "30", "30s", "250ms", "2m", "1h", "0.5s" (see Config). Throws
/// core::Error(InvalidArgument).
std::chrono::milliseconds parseDuration(std::string_view text);
/// "30s" for whole seconds, "250ms" otherwise.
std::string formatDuration(std::chrono::milliseconds duration);

/// What the command line asked for.
struct CommandLine {
  Config config;
  bool help = false;
  bool version = false;
};

/// True for a valid cluster node name: 1 to 32 of [A-Za-z0-9_-].
bool isNodeName(std::string_view name);

/// Usage text for --help.
std::string_view commandLineUsage();

/// Parses the arguments after the program name: reads --config FILE first (wherever it appears),
/// then applies the other flags in order, then validates. Throws core::Error(InvalidArgument) for
/// an unknown flag, a missing value or an invalid configuration; core::Error(NotFound / Io /
/// InvalidArgument) when the file cannot be read or is not a JSON object.
CommandLine parseCommandLine(const std::vector<std::string>& args);

/// Sets config.token from config.tokenFile when that is set: the file's first line, trailing
/// whitespace removed. Throws core::Error(InvalidArgument) when both token and token_file are set
/// or the file is empty, core::Error(NotFound / Io) when it cannot be read. Logs a warning when
/// the file can be read by every user. No-op without a token file.
void loadTokenFile(Config& config);

/// Reads a JSON configuration file onto `config`. Throws as parseCommandLine.
void loadConfigFile(const std::filesystem::path& file, Config& config);

}  // namespace vsm::server
