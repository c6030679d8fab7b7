#pragma once

#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <memory>
#include <mutex>
#include <string>
#include <string_view>

#include "server/config/config.hpp"

namespace vsm::core {
class PatchCache;
}

namespace vsm::server {

namespace exec {
class WorkPool;
}
namespace http {
class Router;
class Pipeline;
class Server;
}  // namespace http
namespace metrics {
class Registry;
}
namespace models {
class ModelRegistry;
class PatchData;
}  // namespace models
namespace jobs {
class JobRegistry;
}
namespace cluster {
class Coordinator;
}
namespace events {
class EventHub;
}

/// How the descriptors of the process are shared out.
struct DescriptorPlan {
  std::size_t connections = 0;
  /// Open files the caches may hold (in flight included).
  std::size_t cachedFiles = 0;
};

/// Keeps 64 descriptors (and two per thread) for the process itself — the listener, the event
/// loop, logs, the files merges, imports and cache misses open for a moment — one per model (the
/// writer lock a writable model holds for its whole life; `models` is limits.models), one per
/// job thread (the directory descriptor an edit holds to make its drafts durable, a
/// durable::FileSystemSync) and one per connection (plus the 64 being answered 503 at once);
/// cached files get the rest, at most 65536. When that leaves fewer than 64, connections are cut
/// to fit. `limit` is RLIMIT_NOFILE.
DescriptorPlan planDescriptors(std::size_t limit, std::size_t connections, std::size_t threads,
                               std::size_t models, std::size_t jobThreads);

/// The daemon's version ("0.1.0").
std::string_view version();

/// The composition root of vsmd: builds every component in order (metrics, patch cache, CPU and
/// job pools, model registry with every model under the data root opened, job registry, routes,
/// HTTP server) and tears them down in reverse. main() only parses arguments
/// and runs one; tests may run one in-process on 127.0.0.1:0.
///
/// Thread-safety: the constructor, start(), run() and the destructor from one thread; stop(),
/// port(), address() and ready() from any thread.
class Application {
 public:
  /// Validates the configuration, applies the log level, logs the effective configuration (token
  /// redacted) and builds the components; serves nothing yet. Throws core::Error(InvalidArgument)
  /// for an invalid configuration, core::Error(NotFound) when the data root is not a directory.
  explicit Application(Config config);
  /// Stops (with the configured grace) if still running, then destroys the components in reverse.
  ~Application();
  Application(const Application&) = delete;
  Application& operator=(const Application&) = delete;

  /// Binds and starts serving; in a cluster, joins it (Coordinator::start); logs "listening on
  /// HOST:PORT" and writes the port file. Returns once connections are accepted. Throws
  /// core::Error(Unavailable) when the address cannot be bound, core::Error(Io) when the port
  /// file cannot be written.
  void start();

  /// start() unless started, then blocks until stop() is called, then shuts down gracefully:
  /// readiness off, no new connections, in-flight requests finished (for up to
  /// limits.shutdown_grace), jobs cancelled (their edits discarded), pools drained; the models
  /// are closed (dirty data written back) when the Application is destroyed. Returns normally
  /// after a clean stop.
  void run();

  /// Makes run() return. The first call starts a graceful shutdown, a second one ends its grace
  /// period at once. Safe from any thread (not from a signal handler).
  void stop();

  /// The bound port; valid after start().
  std::uint16_t port() const;
  /// "127.0.0.1:43123"; valid after start().
  std::string address() const;
  /// True while serving (GET /readyz answers 200).
  bool ready() const;

 private:
  void shutdown();

  // Components in construction order; destroyed in reverse.
  Config config_;
  std::unique_ptr<metrics::Registry> metrics_;
  std::unique_ptr<core::PatchCache> cache_;
  std::unique_ptr<exec::WorkPool> cpuPool_;
  std::unique_ptr<exec::WorkPool> jobPool_;
  std::unique_ptr<exec::WorkPool> helperPool_;
  /// Before the registries it hears from: it outlives their models and jobs.
  std::unique_ptr<events::EventHub> events_;
  std::unique_ptr<models::ModelRegistry> models_;
  std::unique_ptr<jobs::JobRegistry> jobs_;
  /// Null unless cluster.coordinator is set.
  std::unique_ptr<cluster::Coordinator> coordinator_;
  /// The patch-data service the routes share (its housekeeping runs on the main thread).
  std::shared_ptr<models::PatchData> data_;
  std::unique_ptr<http::Router> router_;
  std::unique_ptr<http::Pipeline> pipeline_;
  std::unique_ptr<http::Server> server_;

  mutable std::mutex mutex_;  // guards the state below
  std::condition_variable stopRequested_;
  bool started_ = false;
  bool ready_ = false;
  int stopCalls_ = 0;
  bool shutDown_ = false;
};

}  // namespace vsm::server
