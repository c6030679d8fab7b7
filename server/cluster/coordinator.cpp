#include "server/cluster/coordinator.hpp"

#include <algorithm>
#include <charconv>
#include <utility>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "server/cluster/etcd_client.hpp"

namespace vsm::server::cluster {

using core::Error;
using core::ErrorCode;
namespace log = core::log;
using namespace std::chrono_literals;
using Clock = std::chrono::steady_clock;

namespace {

std::string nodeKey(std::string_view node) {
  return std::string(kNodesPrefix) + std::string(node);
}

std::string writerKey(std::string_view model) {
  return std::string(kWritersPrefix) + std::string(model);
}

std::string readingKey(std::string_view model, std::string_view node) {
  return std::string(kReadingPrefix) + std::string(model) + "/" + std::string(node);
}

/// One etcd call may take this long: a quarter of the TTL, at most 2 s, so that a renewal that
/// hangs still leaves time to give the models up before the lease expires.
std::chrono::milliseconds callTimeout(std::chrono::milliseconds ttl) {
  return std::min<std::chrono::milliseconds>(2s, ttl / 4);
}

}  // namespace

Coordinator::Coordinator(Options options, Node node)
    : options_(std::move(options)),
      node_(std::move(node)),
      tickEvery_(std::min<std::chrono::milliseconds>(1s, options_.leaseTtl / 4)) {}

Coordinator::~Coordinator() {
  stop();
}

void Coordinator::start(const std::string& advertise) {
  if (options_.advertise.empty()) {
    options_.advertise = advertise;
  }
  EtcdClient etcd(options_.coordinator, callTimeout(options_.leaseTtl));
  try {
    tick(etcd);
  } catch (const std::exception& e) {
    // Reads are served meanwhile; the thread tries again every second.
    log::warn(std::string("cluster: cannot join yet, this node writes no model until it does: ") +
              e.what());
  }
  thread_ = std::thread([this] { loop(); });
}

void Coordinator::stop() {
  {
    const std::lock_guard lock(mutex_);
    stopping_ = true;
  }
  wake_.notify_all();
  if (thread_.joinable()) {
    thread_.join();
  }
  std::int64_t lease = 0;
  {
    const std::lock_guard lock(mutex_);
    lease = std::exchange(lease_, 0);
    writers_.clear();
    takeovers_.clear();
  }
  if (lease == 0) {
    return;
  }
  try {
    EtcdClient(options_.coordinator, callTimeout(options_.leaseTtl)).revoke(lease);
    log::info("cluster: lease revoked; the other nodes take this node's models over");
  } catch (const std::exception& e) {
    log::warn(std::string("cluster: cannot revoke the lease (the other nodes take over when it "
                          "expires): ") +
              e.what());
  }
}

void Coordinator::loop() {
  EtcdClient etcd(options_.coordinator, callTimeout(options_.leaseTtl));
  bool failing = false;
  std::unique_lock lock(mutex_);
  while (!wake_.wait_for(lock, tickEvery_, [this] { return stopping_; })) {
    lock.unlock();
    try {
      tick(etcd);
      if (failing) {
        log::info("cluster: etcd answers again");
      }
      failing = false;
    } catch (const std::exception& e) {
      if (!failing) {
        log::warn(std::string("cluster: ") + e.what());
      }
      failing = true;
      bool expiring = false;
      {
        const std::lock_guard relock(mutex_);
        // Give the models up while the lease surely still holds: one more failed round could
        // otherwise outlast it, and another node write meanwhile.
        expiring = lease_ != 0 && Clock::now() - renewed_ >= options_.leaseTtl - tickEvery_ -
                                                                 callTimeout(options_.leaseTtl);
      }
      if (expiring) {
        loseLease("it could not be renewed in time");
      }
    }
    lock.lock();
  }
}

void Coordinator::tick(EtcdClient& etcd) {
  std::int64_t lease = 0;
  {
    const std::lock_guard lock(mutex_);
    lease = lease_;
  }
  const auto now = Clock::now();
  if (lease == 0) {
    const auto ttl = std::chrono::ceil<std::chrono::seconds>(options_.leaseTtl);
    lease = etcd.grant(ttl);
    etcd.put(nodeKey(options_.node), options_.advertise, lease);
    {
      const std::lock_guard lock(mutex_);
      lease_ = lease;
      renewed_ = now;
    }
    log::info("cluster: node " + options_.node + " (" + options_.advertise + ") joined through " +
              options_.coordinator + " with a lease of " + std::to_string(ttl.count()) + " s");
  } else if (!renewIfDue(etcd, lease)) {
    return;
  }

  std::map<std::string, std::string, std::less<>> nodes;
  std::map<std::string, std::string, std::less<>> writers;
  std::map<std::string, std::int64_t, std::less<>> takeovers;
  std::map<std::string, std::set<std::uint64_t>, std::less<>> readElsewhere;
  for (KeyValue& kv : etcd.range("/vsm/")) {
    if (kv.key.starts_with(kReadingPrefix)) {
      const std::string rest = kv.key.substr(kReadingPrefix.size());
      const auto slash = rest.find('/');
      std::uint64_t version = 0;
      const auto [end, error] =
          std::from_chars(kv.value.data(), kv.value.data() + kv.value.size(), version);
      if (slash != std::string::npos && rest.substr(slash + 1) != options_.node &&
          error == std::errc() && version != 0) {
        readElsewhere[rest.substr(0, slash)].insert(version);
      }
    } else if (kv.key.starts_with(kNodesPrefix)) {
      nodes[kv.key.substr(kNodesPrefix.size())] = std::move(kv.value);
    } else if (kv.key.starts_with(kWritersPrefix)) {
      // A key of this node under an older lease is not a role: that lease is lost, and the key
      // vanishes with it.
      if (kv.value != options_.node || kv.lease == lease) {
        std::string model = kv.key.substr(kWritersPrefix.size());
        if (kv.value == options_.node) {
          takeovers[model] = kv.createRevision;
        }
        writers[std::move(model)] = std::move(kv.value);
      }
    }
  }
  if (!nodes.contains(options_.node)) {
    etcd.put(nodeKey(options_.node), options_.advertise, lease);
    nodes[options_.node] = options_.advertise;
  }
  const std::vector<std::string> models = node_.models();
  for (const std::string& id : models) {
    if (writers.contains(id)) {
      continue;
    }
    // A claim is made under a lease surely held (renewed when due): the etcd calls before it can
    // each take up to callTimeout.
    if (!renewIfDue(etcd, lease)) {
      return;
    }
    if (const std::int64_t revision = etcd.putIfAbsent(writerKey(id), options_.node, lease)) {
      writers[id] = options_.node;
      takeovers[id] = revision;
      log::info("cluster: model=" + id + " is written by this node (takeover " +
                std::to_string(revision) + ")");
    }
  }
  {
    const std::lock_guard lock(mutex_);
    if (lease_ != lease) {
      return;  // lost meanwhile
    }
    nodes_ = nodes;
    writers_ = writers;
    takeovers_ = takeovers;
    readElsewhere_ = readElsewhere;
  }
  sayWhatIsRead(etcd, lease, models, writers);
  for (const std::string& id : models) {
    // Opening a large model for writing can take seconds: renewed between models, so that many
    // models taken over at once cannot outlast the lease; and checked after each opening, which
    // may alone have outlasted it.
    if (!renewIfDue(etcd, lease)) {
      return;
    }
    const auto it = writers.find(id);
    const bool writer = it != writers.end() && it->second == options_.node;
    if (node_.setWriter(id, writer) && writer && !stillHeldAfter(etcd, lease, id)) {
      return;
    }
  }
}

void Coordinator::sayWhatIsRead(EtcdClient& etcd, std::int64_t lease,
                                const std::vector<std::string>& models,
                                const std::map<std::string, std::string, std::less<>>& writers) {
  if (!node_.servedVersion) {
    return;
  }
  for (const std::string& id : models) {
    const auto it = writers.find(id);
    if (it != writers.end() && it->second == options_.node) {
      continue;  // its own publishes keep what this process reads
    }
    const std::uint64_t version = node_.servedVersion(id);
    if (version == 0 || saidReading_[id] == version) {
      continue;
    }
    etcd.put(readingKey(id, options_.node), std::to_string(version), lease);
    saidReading_[id] = version;
  }
}

bool Coordinator::stillHeldAfter(EtcdClient& etcd, std::int64_t lease, const std::string& id) {
  {
    const std::lock_guard lock(mutex_);
    if (lease_ != lease) {
      return false;  // lost meanwhile: given up already
    }
    if (!pastFence(Clock::now())) {
      return true;
    }
  }
  // Until renewed, no job is accepted and no commit is allowed (pastFence). A lease etcd renews
  // now never ended, so no other node can have claimed the model meanwhile; one that expired
  // gives every model up. An etcd error is thrown: loop() gives the models up when the lease is
  // that close to its end.
  log::warn("cluster: model=" + id +
            " was opened for writing near the end of the lease: renewing it before writing");
  if (!renewIfDue(etcd, lease, /*force=*/true)) {
    log::warn("cluster: model=" + id + " given up: the lease ended while it was being opened");
    return false;
  }
  return true;
}

bool Coordinator::renewIfDue(EtcdClient& etcd, std::int64_t lease, bool force) {
  const auto now = Clock::now();
  {
    const std::lock_guard lock(mutex_);
    if (!force && now - renewed_ < options_.leaseTtl / 3) {
      return true;
    }
  }
  if (etcd.keepAlive(lease) <= 0) {
    loseLease("etcd says it expired");
    return false;
  }
  const std::lock_guard lock(mutex_);
  renewed_ = now;
  return true;
}

void Coordinator::loseLease(std::string_view why) {
  log::warn("cluster: node " + options_.node + " lost its lease (" + std::string(why) +
            "): it writes no model until it joins again");
  node_.lostLease();
  {
    const std::lock_guard lock(mutex_);
    lease_ = 0;
    writers_.clear();
    takeovers_.clear();
    readElsewhere_.clear();
  }
  saidReading_.clear();  // said again under the next lease
  for (const std::string& id : node_.models()) {
    node_.setWriter(id, false);
  }
}

std::optional<std::string> Coordinator::writerElsewhere(const std::string& id) {
  std::int64_t lease = 0;
  const auto urlOf = [this](const std::string& writer) -> std::optional<std::string> {
    if (writer == options_.node) {
      return std::nullopt;
    }
    const auto url = nodes_.find(writer);
    if (url == nodes_.end()) {
      throw Error(ErrorCode::Unavailable, "model is written by node " + writer +
                                              ", whose URL is not known yet; retry in a second");
    }
    return url->second;
  };
  {
    const std::lock_guard lock(mutex_);
    if (const auto it = writers_.find(id); it != writers_.end()) {
      if (it->second == options_.node && pastFence(Clock::now())) {
        // The lease may run out before a job could commit: no job is accepted on it.
        throw Error(ErrorCode::Unavailable,
                    "node " + options_.node + " is renewing its lease; retry in a second");
      }
      return urlOf(it->second);
    }
    lease = lease_;
  }
  if (lease == 0) {
    throw Error(ErrorCode::Unavailable, "node " + options_.node +
                                            " holds no lease of the cluster (etcd at " +
                                            options_.coordinator + " unreachable?); retry later");
  }
  EtcdClient etcd(options_.coordinator, callTimeout(options_.leaseTtl));
  if (const std::int64_t revision = etcd.putIfAbsent(writerKey(id), options_.node, lease)) {
    {
      const std::lock_guard lock(mutex_);
      if (lease_ != lease) {
        // Lost while the claim was on its way: the key goes with the old lease.
        throw Error(ErrorCode::Unavailable, "node " + options_.node +
                                                " lost its lease while claiming model '" + id +
                                                "'; retry in a second");
      }
      writers_[id] = options_.node;
      takeovers_[id] = revision;
    }
    log::info("cluster: model=" + id + " is written by this node (takeover " +
              std::to_string(revision) + ")");
    node_.setWriter(id, true);
    {
      // Opening it may have outlasted the lease: the coordinator's next round renews or gives
      // the model up; meanwhile no job is accepted on it.
      const std::lock_guard lock(mutex_);
      if (lease_ != lease || pastFence(Clock::now())) {
        throw Error(ErrorCode::Unavailable, "node " + options_.node +
                                                " is renewing its lease after opening model '" +
                                                id + "'; retry in a second");
      }
    }
    return std::nullopt;
  }
  std::string writer;
  for (const KeyValue& kv : etcd.range(writerKey(id))) {
    // This node's name under an older lease is a role it lost: nobody writes the model until
    // that lease expires and the key goes.
    if (kv.key == writerKey(id) && (kv.value != options_.node || kv.lease == lease)) {
      writer = kv.value;
    }
  }
  if (writer.empty()) {
    throw Error(ErrorCode::Unavailable, "model '" + id + "' changes its writer; retry in a second");
  }
  for (const KeyValue& kv : etcd.range(nodeKey(writer))) {
    if (kv.key == nodeKey(writer)) {
      const std::lock_guard lock(mutex_);
      nodes_[writer] = kv.value;
    }
  }
  const std::lock_guard lock(mutex_);
  writers_[id] = writer;
  if (writer != options_.node) {
    takeovers_.erase(id);
  }
  return urlOf(writer);
}

bool Coordinator::pastFence(Clock::time_point now) const {
  return now - renewed_ >= options_.leaseTtl - fenceMargin();
}

std::chrono::milliseconds Coordinator::fenceMargin() const {
  return std::max(std::chrono::milliseconds(1000), options_.leaseTtl / 5);
}

void Coordinator::checkWriter(std::string_view id, std::int64_t takeover) const {
  const auto now = Clock::now();
  const std::lock_guard lock(mutex_);
  const auto it = writers_.find(id);
  if (lease_ == 0 || it == writers_.end() || it->second != options_.node) {
    throw Error(ErrorCode::Conflict, "node " + options_.node +
                                         " is no longer the writer of model '" + std::string(id) +
                                         "'; the write is not committed");
  }
  if (const auto claim = takeovers_.find(id);
      takeover != 0 && (claim == takeovers_.end() || claim->second != takeover)) {
    throw Error(ErrorCode::Conflict,
                "node " + options_.node + " claimed model '" + std::string(id) +
                    "' again since the write began (takeover " + std::to_string(takeover) +
                    "): the write is not committed");
  }
  if (pastFence(now)) {
    const auto held = std::chrono::duration_cast<std::chrono::milliseconds>(now - renewed_);
    throw Error(ErrorCode::Conflict, "node " + options_.node +
                                         " cannot be sure it still holds its lease (last renewed " +
                                         std::to_string(held.count()) + " ms ago, TTL " +
                                         std::to_string(options_.leaseTtl.count()) +
                                         " ms): model '" + std::string(id) + "' is not committed");
  }
}

std::set<std::uint64_t> Coordinator::readElsewhere(std::string_view id) const {
  const std::lock_guard lock(mutex_);
  const auto it = readElsewhere_.find(id);
  return it == readElsewhere_.end() ? std::set<std::uint64_t>() : it->second;
}

std::optional<Coordinator::Takeover> Coordinator::takeover(std::string_view id) const {
  const std::lock_guard lock(mutex_);
  const auto it = takeovers_.find(id);
  if (lease_ == 0 || it == takeovers_.end()) {
    return std::nullopt;
  }
  return Takeover{it->second, lease_};
}

bool Coordinator::writes(std::string_view id) const {
  const std::lock_guard lock(mutex_);
  const auto it = writers_.find(id);
  return it != writers_.end() && it->second == options_.node;
}

std::optional<std::string> Coordinator::nodeUrl(std::string_view name) const {
  const std::lock_guard lock(mutex_);
  if (name == options_.node) {
    return std::nullopt;
  }
  const auto it = nodes_.find(name);
  return it == nodes_.end() ? std::nullopt : std::optional<std::string>(it->second);
}

std::map<std::string, std::string> Coordinator::writers() const {
  const std::lock_guard lock(mutex_);
  return {writers_.begin(), writers_.end()};
}

}  // namespace vsm::server::cluster
