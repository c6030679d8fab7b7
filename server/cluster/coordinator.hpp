#pragma once

#include <chrono>
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <map>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <thread>
#include <vector>

namespace vsm::server::cluster {

class EtcdClient;

/// Where a node is and what it writes, as etcd holds it:
///   /vsm/nodes/<node>    = the node's advertised URL
///   /vsm/writers/<model> = the name of the node that writes the model
/// Both attached to the node's one lease, so when a node stops renewing it (it died, or lost etcd)
/// its keys vanish after the lease's TTL and the other nodes take its models over.
inline constexpr std::string_view kNodesPrefix = "/vsm/nodes/";
inline constexpr std::string_view kWritersPrefix = "/vsm/writers/";
/// /vsm/reading/<model>/<node> = the version of the model the node serves while it only reads it
/// (attached to its lease too): the writer keeps that revision (issue 32, finding 3).
inline constexpr std::string_view kReadingPrefix = "/vsm/reading/";

/// A node's part in a cluster of vsmd nodes sharing one data root: every node serves every model;
/// for each model one node, elected through etcd, writes it (runs its jobs, holds its writer
/// lock), and the others follow its publishes from the disk.
///
/// A thread of its own renews the node's lease (every TTL/3), reads who writes what (every
/// second), claims every model that has no writer, and tells the node which models it writes
/// (Node::setWriter, called again every second for each model until it succeeds). When the lease
/// cannot be renewed for nearly its TTL, or etcd says it expired, the node gives every model up
/// (Node::lostLease first, so that jobs stop) before another node can claim them; it then joins
/// again with a new lease. stop() revokes the lease, so the others take over at once.
///
/// Thread-safe: the queries from any thread.
class Coordinator {
 public:
  struct Options {
    std::string coordinator;  // etcd's client URL
    std::string node;
    std::string advertise;
    std::chrono::milliseconds leaseTtl{10'000};
  };
  /// How the coordinator acts on the node. Called from the coordinator's thread, or from the thread
  /// of a query that claims a model (writerElsewhere).
  struct Node {
    /// The ids of the models the node serves.
    std::function<std::vector<std::string>()> models;
    /// Makes the node write `id` (true) or only read it (false); false when that failed (it is
    /// asked again a second later).
    std::function<bool(const std::string& id, bool writer)> setWriter;
    /// The lease is lost: stop writing (cancel jobs) before the models are given up.
    std::function<void()> lostLease;
    /// The version of `id` the node serves (0: not open); said in etcd for the models it only
    /// reads. Null: nothing said.
    std::function<std::uint64_t(const std::string& id)> servedVersion;
  };

  Coordinator(Options options, Node node);
  /// stop().
  ~Coordinator();
  Coordinator(const Coordinator&) = delete;
  Coordinator& operator=(const Coordinator&) = delete;

  /// Starts the thread, after joining the cluster once (lease, node key, claims) so that the node
  /// is known when it starts answering. `advertise` is the node's URL when Options::advertise is
  /// empty. When etcd cannot be reached, logs it and goes on: the node serves reads, writes no
  /// model, and the thread tries again every second.
  void start(const std::string& advertise);
  /// Revokes the lease (the node's models go to others at once) and ends the thread. Idempotent.
  void stop();

  const std::string& node() const { return options_.node; }

  /// Where a write to model `id` must go: nullopt when this node writes it; otherwise the writer's
  /// advertised URL. A model without a writer is claimed for this node on the spot. Throws
  /// core::Error(Unavailable) when no node can be named (etcd unreachable, the writer's URL
  /// unknown) or this node has no lease.
  std::optional<std::string> writerElsewhere(const std::string& id);
  /// True when this node is the elected writer of `id`.
  bool writes(std::string_view id) const;
  /// The fence of a commit into model `id` (core::PublishOptions::fence), called just before its
  /// commit point: throws core::Error(Conflict) unless this node is the writer of `id` under a
  /// lease that etcd cannot have expired yet with a margin (the last renewal etcd confirmed was
  /// sent less than TTL - kFenceMargin ago), so a node paused or cut off from etcd past its lease
  /// never commits over the node that took the model over.
  ///
  /// With `takeover` (not 0), the write began under that claim (takeover()): the commit is also
  /// refused when this node's claim on `id` is another one now (lost and claimed again meanwhile).
  void checkWriter(std::string_view id, std::int64_t takeover = 0) const;
  /// This node's claim on model `id`, its fencing token: the etcd revision that created the
  /// model's writer key (greater for every later claim, by any node) and the lease it is attached
  /// to. Nullopt when this node does not write `id`.
  struct Takeover {
    std::int64_t revision = 0;
    std::int64_t lease = 0;
  };
  std::optional<Takeover> takeover(std::string_view id) const;
  /// What checkWriter keeps in hand of the lease: a fifth of the TTL, at least a second.
  std::chrono::milliseconds fenceMargin() const;
  /// The advertised URL of node `name`: nullopt for this node and for a node not in the cluster.
  std::optional<std::string> nodeUrl(std::string_view name) const;
  /// The versions of model `id` the other nodes serve while they read it (as etcd said at the
  /// last round): the revisions a publish into it keeps (core::PublishOptions::readElsewhere).
  std::set<std::uint64_t> readElsewhere(std::string_view id) const;
  /// The writer of every model with one, by model id.
  std::map<std::string, std::string> writers() const;

 private:
  void loop();
  /// One round: renew or get the lease, read the keys, claim, tell the node. Throws on etcd errors.
  void tick(EtcdClient& etcd);
  void loseLease(std::string_view why);
  /// Renews `lease` when a third of its TTL has passed since the last renewal. False when etcd says
  /// it has expired: the models are given up (loseLease). Throws on etcd errors.
  /// `force`: renews whenever called.
  bool renewIfDue(EtcdClient& etcd, std::int64_t lease, bool force = false);
  /// After a slow step (opening `id` for writing): true when the lease is still surely held
  /// (renewed now if it was near its end); otherwise gives `id` up, or every model when etcd
  /// says the lease expired, and returns false. Throws on etcd errors, having given `id` up.
  bool stillHeldAfter(EtcdClient& etcd, std::int64_t lease, const std::string& id);
  /// Puts /vsm/reading/<model>/<node> for each of `models` this node only reads whose served
  /// version changed since it last said it (Node::servedVersion). The coordinator's thread.
  void sayWhatIsRead(EtcdClient& etcd, std::int64_t lease, const std::vector<std::string>& models,
                     const std::map<std::string, std::string, std::less<>>& writers);
  /// True when the lease may end before a write started now commits (checkWriter's fence):
  /// `now` is fenceMargin() or less from the end of the last confirmed renewal. With mutex_ held.
  bool pastFence(std::chrono::steady_clock::time_point now) const;

  Options options_;  // advertise is set by start()
  const Node node_;
  std::chrono::milliseconds tickEvery_;

  mutable std::mutex mutex_;  // guards the state below
  std::condition_variable wake_;
  bool stopping_ = false;
  std::int64_t lease_ = 0;
  /// When the last renewal that etcd confirmed was sent.
  std::chrono::steady_clock::time_point renewed_;
  std::map<std::string, std::string, std::less<>> nodes_;    // name -> URL
  std::map<std::string, std::string, std::less<>> writers_;  // model -> node
  /// model -> the etcd revision that created its writer key, for the models this node writes.
  std::map<std::string, std::int64_t, std::less<>> takeovers_;
  /// model -> the versions other nodes read (their /vsm/reading/ keys).
  std::map<std::string, std::set<std::uint64_t>, std::less<>> readElsewhere_;
  /// model -> the version this node last said it reads, under lease_ (the coordinator's thread).
  std::map<std::string, std::uint64_t, std::less<>> saidReading_;
  std::thread thread_;
};

}  // namespace vsm::server::cluster
