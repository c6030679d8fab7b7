#include "server/app/application.hpp"

#include <fcntl.h>
#include <sys/resource.h>
#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <filesystem>
#include <thread>

#include <nlohmann/json.hpp>

#include "core/cache/patch_cache.hpp"
#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/durable/durable_io.hpp"
#include "core/io/grid_source.hpp"
#include "core/opc/texture_file.hpp"
#include "core/store/live_model.hpp"
#include "server/api/diff_gate.hpp"
#include "server/api/event_routes.hpp"
#include "server/api/gis_routes.hpp"
#include "server/api/job_routes.hpp"
#include "server/api/model_routes.hpp"
#include "server/api/ray_routes.hpp"
#include "server/api/static_routes.hpp"
#include "server/api/system_routes.hpp"
#include "server/api/terrain_routes.hpp"
#include "server/api/tiles_routes.hpp"
#include "server/cluster/coordinator.hpp"
#include "server/events/event_hub.hpp"
#include "server/exec/work_pool.hpp"
#include "server/http/pipeline.hpp"
#include "server/http/router.hpp"
#include "server/http/server.hpp"
#include "server/jobs/job_registry.hpp"
#include "server/metrics/metrics.hpp"
#include "server/models/model_registry.hpp"
#include "server/models/patch_data.hpp"

#ifndef VSM_VERSION
#define VSM_VERSION "unknown"
#endif

namespace vsm::server {

namespace fs = std::filesystem;
using core::Error;
using core::ErrorCode;
namespace log = core::log;

namespace {

/// Writes "<port>\n" to `path` atomically (readers wait for the file to appear whole).
void writePortFile(const fs::path& path, std::uint16_t port) {
  const std::string text = std::to_string(port) + "\n";
  core::durable::writeFileAtomically(path, std::as_bytes(std::span(text.data(), text.size())));
}

/// Raises the soft RLIMIT_NOFILE to the hard limit (a service gets 1024 by default, far below
/// what thousands of connections and open patch files need) and logs both. Returns the soft limit
/// in force.
std::size_t raiseDescriptorLimit() {
  rlimit limit{};
  if (::getrlimit(RLIMIT_NOFILE, &limit) != 0) {
    log::warn(std::string("descriptors: cannot read RLIMIT_NOFILE: ") + std::strerror(errno));
    return 1024;
  }
  const rlim_t before = limit.rlim_cur;
  if (limit.rlim_cur != limit.rlim_max) {
    limit.rlim_cur = limit.rlim_max;
    if (::setrlimit(RLIMIT_NOFILE, &limit) != 0) {
      log::warn(std::string("descriptors: cannot raise the soft limit: ") + std::strerror(errno));
      limit.rlim_cur = before;
    }
  }
  const auto text = [](rlim_t v) {
    return v == RLIM_INFINITY ? std::string("unlimited") : std::to_string(v);
  };
  log::info("descriptors: soft limit " + text(limit.rlim_cur) + " (was " + text(before) +
            "), hard limit " + text(limit.rlim_max));
  return limit.rlim_cur == RLIM_INFINITY ? std::size_t{1} << 20
                                         : static_cast<std::size_t>(limit.rlim_cur);
}

bool isLoopback(const std::string& host) {
  return host == "localhost" || host == "::1" || host.starts_with("127.");
}

std::string hostName() {
  char name[256] = {};
  if (::gethostname(name, sizeof name - 1) != 0 || name[0] == '\0') {
    return "localhost";
  }
  return name;
}

/// The name of this node in a cluster: cluster.node, or the host name made a valid node name.
std::string nodeName(const ClusterConfig& cluster) {
  if (!cluster.node.empty()) {
    return cluster.node;
  }
  std::string name = hostName().substr(0, 32);
  for (char& c : name) {
    if (!isNodeName(std::string_view(&c, 1))) {
      c = '-';
    }
  }
  return name;
}

}  // namespace

DescriptorPlan planDescriptors(std::size_t limit, std::size_t connections, std::size_t threads,
                               std::size_t models, std::size_t jobThreads) {
  constexpr std::size_t kReserved = 64;
  constexpr std::size_t kRejecting = 64;
  constexpr std::size_t kMinCachedFiles = 64;
  constexpr std::size_t kMaxCachedFiles = 65536;
  const std::size_t reserved = kReserved + 2 * threads + kRejecting + models + jobThreads;
  DescriptorPlan plan;
  plan.connections = connections;
  const std::size_t available = limit > reserved ? limit - reserved : 0;
  if (available < connections + kMinCachedFiles) {
    plan.connections = available > 2 * kMinCachedFiles ? available - kMinCachedFiles
                                                       : std::max<std::size_t>(available / 2, 8);
  }
  plan.cachedFiles = available > plan.connections ? available - plan.connections : 8;
  plan.cachedFiles = std::clamp<std::size_t>(plan.cachedFiles, 8, kMaxCachedFiles);
  return plan;
}

std::string_view version() {
  return VSM_VERSION;
}

Application::Application(Config config) : config_(std::move(config)) {
  config_.validate();
  log::setLevel(config_.logLevel);
  log::info("vsmd " + std::string(version()) + " starting");
  for (const auto& [key, value] : config_.describe()) {
    log::info("config " + key + "=" + value);
  }
  std::error_code ec;
  if (!fs::is_directory(config_.dataRoot, ec)) {
    throw Error(ErrorCode::NotFound, "data root '" + config_.dataRoot.string() +
                                         "' is not a directory (set data_root or --data-root)");
  }
  if (config_.token.empty() && !isLoopback(config_.listen.host)) {
    log::warn("no token configured: anyone who can reach " + config_.listen.toString() +
              " may write (set token_file or --token-file)");
  }

  metrics_ = std::make_unique<metrics::Registry>();
  cache_ = std::make_unique<core::PatchCache>(config_.memoryBudget, config_.cachePolicy);
  const std::size_t cpuThreads =
      config_.threads.cpu != 0 ? config_.threads.cpu
                               : std::max<std::size_t>(1, std::thread::hardware_concurrency());
  // A job's tasks run on its own thread and on these (JobContext::executor): one fewer than the
  // hardware threads (at least one), a pool apart from the job pool so that tasks held up (a
  // stalled disk) hold no thread another job needs.
  const std::size_t helperThreads =
      std::max<std::size_t>(2, std::thread::hardware_concurrency()) - 1;
  const DescriptorPlan descriptors =
      planDescriptors(raiseDescriptorLimit(), config_.limits.connections,
                      cpuThreads + config_.threads.jobs + helperThreads + config_.threads.io,
                      config_.limits.models, config_.threads.jobs);
  cache_->setHandleBudget(descriptors.cachedFiles);
  if (descriptors.connections < config_.limits.connections) {
    log::warn("descriptors: the limit leaves room for " + std::to_string(descriptors.connections) +
              " connections, not limits.connections=" + std::to_string(config_.limits.connections) +
              " (raise the hard RLIMIT_NOFILE)");
  }
  log::info("descriptors: up to " + std::to_string(descriptors.connections) +
            " connections, up to " + std::to_string(descriptors.cachedFiles) +
            " open patch files held by the cache");
  cpuPool_ = std::make_unique<exec::WorkPool>("cpu", cpuThreads);
  // Merges and imports run here, a pool of its own so that they can never take the threads
  // request handlers need.
  jobPool_ = std::make_unique<exec::WorkPool>("jobs", config_.threads.jobs);
  helperPool_ = std::make_unique<exec::WorkPool>("job-helpers", helperThreads);
  events::HubOptions hubOptions;
  hubOptions.maxSubscribers = config_.limits.eventSubscribers;
  hubOptions.maxSubscribersPerClient = config_.limits.eventSubscribersPerClient;
  events_ = std::make_unique<events::EventHub>(std::move(hubOptions));
  models_ = std::make_unique<models::ModelRegistry>(
      config_.dataRoot, *cache_, config_.limits.texturePixels,
      static_cast<unsigned>(config_.keepRevisions),
      std::chrono::duration_cast<std::chrono::seconds>(config_.keepRevisionsSeconds));
  models_->limitModels(config_.limits.models);
  // Jobs live in memory only: after a restart none is listed, and a merge that had not published
  // left its model at the last published version (drafts are removed when the model opens).
  jobs::JobLimits jobLimits;
  if (!config_.cluster.coordinator.empty()) {
    cluster::Coordinator::Options options;
    options.coordinator = config_.cluster.coordinator;
    options.node = nodeName(config_.cluster);
    options.advertise = config_.cluster.advertise;
    options.leaseTtl = config_.cluster.leaseTtl;
    jobLimits.node = options.node;
    cluster::Coordinator::Node node;
    node.models = [this] { return models_->ids(); };
    node.setWriter = [this](const std::string& id, bool writer) {
      return models_->setWriter(id, writer);
    };
    node.lostLease = [this] { jobs_->cancelAll(/*refuseNew=*/false); };
    node.servedVersion = [this](const std::string& id) -> std::uint64_t {
      const auto live = models_->find(id);
      return live != nullptr ? live->snapshot()->version : 0;
    };
    coordinator_ = std::make_unique<cluster::Coordinator>(std::move(options), std::move(node));
    // Every model is read only until this node is elected to write it (Coordinator::start).
    models_->electWriters([this](std::string_view id) { return coordinator_->writes(id); });
    // A write records this node's claim on the model (its fencing token) in the revision it
    // publishes, and checks just before its commit point that the node still holds the lease
    // and that claim.
    models::ModelRegistry::WriterFence fence;
    fence.token = [this](std::string_view id) -> std::optional<core::FencingToken> {
      const auto claim = coordinator_->takeover(id);
      if (!claim) {
        return std::nullopt;
      }
      return core::FencingToken{static_cast<std::uint64_t>(claim->revision), claim->lease};
    };
    fence.check = [this](std::string_view id, const std::optional<core::FencingToken>& token) {
      coordinator_->checkWriter(id, token ? static_cast<std::int64_t>(token->takeover) : 0);
    };
    // A publish keeps the revisions the other nodes serve (they say so in etcd).
    fence.readElsewhere = [this](std::string_view id) { return coordinator_->readElsewhere(id); };
    models_->fenceWrites(std::move(fence));
    log::info("cluster: node " + coordinator_->node() + ", coordinator " +
              config_.cluster.coordinator);
  }
  jobs_ = std::make_unique<jobs::JobRegistry>(*jobPool_, *helperPool_, jobLimits);
  // Before any model opens, so that every opening is watched.
  api::connectEvents(*events_, *jobs_, *models_);
  // Staging directories of imports a crash interrupted (kept from the previous life of this
  // process, whose pid a container reuses); an import another node runs holds its lock.
  core::removeAbandonedImports(models_->dataRoot());
  const std::size_t opened = models_->openAll();
  log::info("data root " + models_->dataRoot().string() + ": " + std::to_string(opened) +
            " model(s) open");

  router_ = std::make_unique<http::Router>();
  // Shared by the diff routes and the statistics (the router's handlers keep it alive).
  const auto diffs = api::DiffGate::create({config_.limits.diffs, config_.limits.diffTimeout});
  const auto reads = [this, diffs] {
    core::LiveModel::RevisionReadStats revisions;
    for (const auto& live : models_->list()) {
      const auto one = live->revisionReadStats();
      revisions.reads += one.reads;
      revisions.sharedReads += one.sharedReads;
      revisions.reading += one.reading;
      revisions.waiting += one.waiting;
      revisions.cached += one.cached;
    }
    const api::DiffGate::Stats d = diffs->stats();
    return nlohmann::json{{"revisions",
                           {{"reads", revisions.reads},
                            {"shared_reads", revisions.sharedReads},
                            {"reading", revisions.reading},
                            {"waiting", revisions.waiting},
                            {"cached", revisions.cached}}},
                          {"diffs",
                           {{"running", d.running},
                            {"limit", d.slots},
                            {"refused", d.refused},
                            {"timed_out", d.timedOut},
                            {"abandoned", d.abandoned}}}};
  };
  api::addSystemRoutes(*router_, {*cache_, *metrics_, [this] { return ready(); }, reads});
  // One patch-data service for every route that answers with encoded patch data.
  data_ = std::make_shared<models::PatchData>();
  const std::shared_ptr<models::PatchData>& data = data_;
  api::addModelRoutes(*router_, {*models_, *jobs_, coordinator_.get(), diffs, data});
  api::addJobRoutes(*router_, {*models_, *jobs_, coordinator_.get(), diffs, data});
  api::addTilesRoutes(*router_, *models_, data);
  api::addTerrainRoutes(*router_, *models_, data);
  api::addGisRoutes(*router_, *models_, data);
  api::addRayRoutes(*router_, *models_, data);
  api::addEventRoutes(*router_, *events_);
  if (!config_.viewerDir.empty()) {
    api::addStaticRoutes(*router_, "/viewer", config_.viewerDir);
    log::info("viewer: files of " + config_.viewerDir.string() + " at /viewer/");
  }
  pipeline_ = std::make_unique<http::Pipeline>(*router_, config_.token);

  http::ServerOptions options;
  options.host = config_.listen.host;
  options.port = config_.listen.port;
  options.ioThreads = config_.threads.io;
  options.bodyLimit = config_.limits.bodyBytes;
  options.headerLimit = config_.limits.headerBytes;
  options.headerTimeout = config_.limits.headerTimeout;
  options.readTimeout = config_.limits.readTimeout;
  options.idleTimeout = config_.limits.idleTimeout;
  options.writeTimeout = config_.limits.writeTimeout;
  options.maxConnections = descriptors.connections;
  options.maxPerClient = config_.limits.connectionsPerClient;
  options.maxPipelined = config_.limits.pipelinedResponses;
  options.node = coordinator_ != nullptr ? coordinator_->node() : std::string();
  server_ = std::make_unique<http::Server>(options, *pipeline_, *cpuPool_, *metrics_);

  // Collectors run only while the server answers /metrics, i.e. while every component they read
  // exists (the registry is built first and destroyed last).
  metrics_->collector([cache = cache_.get()] { return api::cacheMetrics(cache->stats()); });
  const double startTime =
      std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
  metrics_->collector([this, startTime] {
    using metrics::Snapshot;
    using metrics::Type;
    Snapshot threads{"vsm_pool_threads", "Threads per pool", Type::Gauge, {"pool"}, {}};
    Snapshot queued{
        "vsm_pool_queued_tasks", "Tasks waiting for a thread", Type::Gauge, {"pool"}, {}};
    Snapshot active{"vsm_pool_active_tasks", "Tasks running", Type::Gauge, {"pool"}, {}};
    for (const exec::WorkPool* pool : {cpuPool_.get(), jobPool_.get(), helperPool_.get()}) {
      threads.samples.push_back({{pool->name()}, static_cast<double>(pool->threads())});
      queued.samples.push_back({{pool->name()}, static_cast<double>(pool->queued())});
      active.samples.push_back({{pool->name()}, static_cast<double>(pool->active())});
    }
    Snapshot jobStates{"vsm_jobs", "Jobs remembered, by state", Type::Gauge, {"state"}, {}};
    for (const auto& [state, count] : jobs_->counts()) {
      jobStates.samples.push_back(
          {{std::string(jobs::toString(state))}, static_cast<double>(count)});
    }
    Snapshot openModels{"vsm_models_open",
                        "Open models",
                        Type::Gauge,
                        {},
                        {{{}, static_cast<double>(models_->size())}}};
    Snapshot refused{"vsm_follows_refused_total",
                     "Versions on disk not followed: their writer's fencing token was older than "
                     "one already seen",
                     Type::Counter,
                     {},
                     {{{}, static_cast<double>(models_->followsRefused())}}};
    Snapshot up{"vsm_ready",
                "1 while the daemon serves, 0 while starting or stopping",
                Type::Gauge,
                {},
                {{{}, ready() ? 1.0 : 0.0}}};
    Snapshot build{"vsm_build_info",
                   "The daemon's version",
                   Type::Gauge,
                   {"version"},
                   {{{std::string(version())}, 1.0}}};
    Snapshot start{"vsm_process_start_time_seconds",
                   "Start time, seconds since the epoch",
                   Type::Gauge,
                   {},
                   {{{}, startTime}}};
    return std::vector<Snapshot>{std::move(threads),   std::move(queued),     std::move(active),
                                 std::move(jobStates), std::move(openModels), std::move(refused),
                                 std::move(up),        std::move(build),      std::move(start)};
  });
}

Application::~Application() {
  try {
    shutdown();
  } catch (const std::exception& e) {
    log::error(std::string("shutdown: ") + e.what());
  }
}

void Application::start() {
  {
    const std::lock_guard lock(mutex_);
    if (started_) {
      return;
    }
  }
  events_->start();
  server_->start();
  log::info("listening on " + server_->address());
  // OpenImageIO's module (~0.45 s to load, core/opc/image_codec.hpp) on a handler thread now,
  // rather than in the first request or merge that reads or writes a texture tile. A failure is
  // left to that first use, which tries again and answers with the error.
  cpuPool_->post([] {
    try {
      core::loadImageCodec();
    } catch (const core::Error& e) {
      log::warn(std::string("texture images: ") + e.what());
    }
  });
  if (coordinator_ != nullptr) {
    std::string advertise = config_.cluster.advertise;
    if (advertise.empty()) {
      const bool any = config_.listen.host == "0.0.0.0" || config_.listen.host == "::";
      advertise = "http://" +
                  (any ? hostName() + ":" + std::to_string(server_->port()) : server_->address());
    }
    coordinator_->start(advertise);
  }
  if (!config_.portFile.empty()) {
    writePortFile(config_.portFile, server_->port());
  }
  {
    const std::lock_guard lock(mutex_);
    started_ = true;
    ready_ = stopCalls_ == 0;
  }
  log::info("ready: " + std::to_string(cpuPool_->threads()) + " handler threads, " +
            std::to_string(jobPool_->threads()) + " job threads (" +
            std::to_string(helperPool_->threads()) + " helpers), " +
            std::to_string(config_.threads.io) + " network threads");
}

void Application::run() {
  start();
  // The main thread follows other writers' publishes of models open for reading only (a vsm
  // merge, another vsmd holding the writer lock), removes the folders of dropped revisions whose
  // last reader let go, charges the models' metadata to the budget, and frees the derived
  // documents' replaced bases, until asked to stop.
  constexpr auto kFollowEvery = std::chrono::milliseconds(500);
  for (;;) {
    {
      std::unique_lock lock(mutex_);
      if (stopRequested_.wait_for(lock, kFollowEvery, [this] { return stopCalls_ > 0; })) {
        break;
      }
    }
    if (coordinator_ != nullptr) {
      models_->openAll();  // models other nodes imported
    }
    models_->follow();
    models_->housekeeping();
    data_->releaseRetired();
  }
  shutdown();
}

void Application::stop() {
  int calls = 0;
  {
    const std::lock_guard lock(mutex_);
    calls = ++stopCalls_;
    ready_ = false;
  }
  stopRequested_.notify_all();
  if (calls == 2) {
    log::warn("stopping now: closing connections without waiting for the grace period");
    server_->cutShort();
  }
}

void Application::shutdown() {
  bool wasStarted = false;
  {
    const std::lock_guard lock(mutex_);
    if (shutDown_) {
      return;
    }
    shutDown_ = true;
    ready_ = false;
    wasStarted = started_;
  }
  if (wasStarted) {
    log::info("stopping: no new connections; " + std::to_string(server_->connections()) +
              " open ones get up to " + formatDuration(config_.limits.shutdownGrace) +
              " to finish");
  }
  // Jobs stop first (at their next check), so a long merge does not hold the exit; their edits
  // are discarded and the models stay at their last published version.
  jobs_->cancelAll();
  // Event streams never end by themselves: they end now (their queued events still go), so
  // that they do not hold the grace period.
  events_->close();
  server_->stop(config_.limits.shutdownGrace);
  // Handlers still running (past the grace period) post their results into the stopped server;
  // it must outlive them, so the pools are drained before any component is destroyed.
  cpuPool_->join();
  jobPool_->join();
  helperPool_->join();  // after the jobs: none of them lends it any more
  if (coordinator_ != nullptr) {
    coordinator_->stop();  // the lease goes: the other nodes take this node's models over
  }
  if (wasStarted && !config_.portFile.empty()) {
    std::error_code ignored;
    fs::remove(config_.portFile, ignored);
  }
  if (wasStarted) {
    log::info("stopped");
  }
}

std::uint16_t Application::port() const {
  return server_->port();
}

std::string Application::address() const {
  return server_->address();
}

bool Application::ready() const {
  const std::lock_guard lock(mutex_);
  return ready_;
}

}  // namespace vsm::server
