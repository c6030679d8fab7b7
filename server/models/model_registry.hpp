#pragma once

#include <atomic>
#include <chrono>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <functional>
#include <limits>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <string_view>
#include <vector>

#include "core/opc/opc_reader.hpp"
#include "core/opc/texture_file.hpp"
#include "core/pyramid/patch_key.hpp"
#include "server/models/model_following.hpp"

namespace vsm::core {
class LiveModel;
class PatchCache;
struct PublishOptions;
}  // namespace vsm::core

namespace vsm::server::models {

class EncodedCache;

/// True for a valid model id: 1 to 64 of [A-Za-z0-9_-]. Ids name directories under the data root
/// and appear in URLs, so nothing else (no '.', no '/', no '%') is allowed.
bool isValidModelId(std::string_view id);

/// Throws core::Error(InvalidArgument) naming `what` unless isValidModelId(id).
void checkModelId(std::string_view id, std::string_view what = "model id");

/// Resolves a path a client named, relative to `root` (canonical, see ModelRegistry::dataRoot()),
/// to a path inside it. Rejects with core::Error(InvalidArgument) an empty path, an absolute one,
/// one with a NUL byte, a ".." component, and one that leaves `root` through a symbolic link
/// (the result is made weakly canonical, i.e. existing links are resolved, and must lie strictly
/// below `root`). Touches nothing on disk but reading links.
std::filesystem::path resolveInside(const std::filesystem::path& root, std::string_view relative);

/// The open models of the daemon, by id, over the one shared PatchCache.
///
/// Models are shared: a request or job holds a std::shared_ptr<LiveModel> for its duration, so a
/// model closed meanwhile stays usable until the last holder lets go (then its cache entries are
/// written back and dropped). Holders must release their cache pins before the LiveModel.
///
/// A *lease* marks a model (or a reserved id) as used by a job: close() answers Conflict while one
/// exists, so a merge target or an import cannot be closed under a job.
///
/// Thread-safe. One mutex guards the tables; it is never held while a model is opened or
/// destroyed (both read the disk).
class ModelRegistry {
 public:
  /// `dataRoot` must be an existing directory; `cache` must outlive the registry. Models decode
  /// texture files of at most `texturePixels` pixels (limits.texture_pixels).
  /// Jobs publishing into its models keep `keepRevisions` revisions (keep_revisions), and each
  /// whose successor is younger than `keepSeconds` (keep_revisions_seconds).
  ModelRegistry(const std::filesystem::path& dataRoot, core::PatchCache& cache,
                std::uint64_t texturePixels = core::kDefaultTexturePixels,
                unsigned keepRevisions = core::kDefaultKeepRevisions,
                std::chrono::seconds keepSeconds = std::chrono::seconds(0));
  /// Closes every model (their dirty data is written back by the cache).
  ~ModelRegistry();
  ModelRegistry(const ModelRegistry&) = delete;
  ModelRegistry& operator=(const ModelRegistry&) = delete;

  /// The canonical data root.
  const std::filesystem::path& dataRoot() const { return root_; }
  /// Revisions a publish keeps (core::PublishOptions::keepRevisions).
  unsigned keepRevisions() const { return keepRevisions_; }
  /// The one patch cache of every model.
  core::PatchCache& cache() const { return cache_; }

  /// Opens every directory directly under the data root whose name is a valid id, that holds an
  /// OPC (metadata only) and that is not open yet. A directory that fails to open is logged and
  /// skipped; called again (a cluster node discovers models other nodes imported), it tries such a
  /// directory again, silently, only once its hierarchy file changed, except after an I/O error
  /// (Io, Unavailable: a disk's transient read error), which it tries at every call until the
  /// model opens. Returns the number opened.
  /// For one caller at a time.
  std::size_t openAll();
  /// At most `max` models open, being opened or reserved at once (limits.models): each writable
  /// one holds its writer lock's descriptor for its whole life, so the bound is part of the
  /// descriptor plan. One more is refused (Conflict) and openAll() skips it with a warning.
  /// Call before openAll(); without it there is no bound.
  void limitModels(std::size_t max);

  /// In a cluster: from now on a model is opened for writing only when `writes(id)` says this node
  /// is its elected writer, and for reading otherwise; setWriter() changes it. Call before
  /// openAll(). Without it, every model is opened for writing when its writer lock is free.
  void electWriters(std::function<bool(std::string_view id)> writes);
  /// Makes the open model `id` one this process writes (opened again for writing: its writer lock
  /// taken, leftovers of interrupted writes removed) or only reads (opened again for reading, the
  /// lock let go once the jobs holding the old opening end). Requests and jobs holding the old
  /// opening finish on it. True when `id` is open in that role now; false when it is not open or
  /// the opening failed (logged once per model until it succeeds).
  bool setWriter(std::string_view id, bool writer);
  /// In a cluster, how the commits of this process's jobs are fenced. Call before the first job.
  struct WriterFence {
    /// This node's claim on model `id` as a fencing token, asked when a write begins: recorded
    /// in the revision it publishes (core::PublishOptions::token). Nullopt: none.
    std::function<std::optional<core::FencingToken>(std::string_view id)> token;
    /// Called just before the commit of a write into `id` that began under `token`
    /// (core::PublishOptions::fence): throws to refuse it (the node no longer holds the model's
    /// lease, or claimed it again since).
    std::function<void(std::string_view id, const std::optional<core::FencingToken>& token)> check;
    /// The revisions of `id` other processes read now, asked when a publish drops revisions
    /// (core::PublishOptions::readElsewhere).
    std::function<std::set<std::uint64_t>(std::string_view id)> readElsewhere;
  };
  void fenceWrites(WriterFence fence);
  /// How a job `job` that begins now publishes into `id`: the revisions and time floor kept, the
  /// dropped revisions' folders left to the housekeeping (housekeeping()), and fenced:
  /// token, fence and readElsewhere from what fenceWrites() set (unset without it).
  core::PublishOptions publishOptions(const std::string& id, std::string job) const;
  /// The ids of the open models, in order.
  std::vector<std::string> ids() const;

  /// A new version of an open model: published by this process, or read again after another
  /// writer published it (follow(), setWriter(), reopen()).
  struct Publication {
    std::string model;
    std::uint64_t version = 0;
    /// The keys of the patches added or replaced, in key order: as the publish made them, or,
    /// for a version read again, the patches stored differently in the two openings (modelChange).
    std::vector<core::PatchKey> changed;
    /// The keys of the patches the version no longer has (a restore of a revision without them),
    /// in key order.
    std::vector<core::PatchKey> removed;
    /// True when the version was read again (another writer published it).
    bool followed = false;
  };
  /// Sets the one function told of every new version, on the publishing (or following) thread
  /// with no lock held; it must not throw or block. Call before openAll() and open(): openings
  /// made earlier are not watched.
  void onPublished(std::function<void(const Publication&)> listener);

  /// Opens the OPC directory `dir` (inside the data root) as `id`, for writing (holding its
  /// writer lock), or for reading only when another writer holds the lock or the directory is not
  /// writable (a read-only mount): LiveModel::Access::WriteIfPossible. Throws core::Error(Conflict)
  /// when the id is open or reserved, or the directory is open under another id; InvalidArgument
  /// for a bad id; the errors of LiveModel::open (NotFound when `dir` holds no OPC, Corrupt, Io).
  std::shared_ptr<core::LiveModel> open(const std::string& id, const std::filesystem::path& dir);

  /// Replaces the open model `id` by a new opening of its directory, read again from disk
  /// (LiveModel::reopen), with a new cache of encoded responses: after a failed write nothing the
  /// old opening holds in memory is trusted. Requests and jobs holding the old opening finish on
  /// it. Failures are logged (the old opening stays); NotFound when `id` is not open.
  void reopen(std::string_view id);

  /// Follows other writers: every model open for reading only whose directory holds a version
  /// another process published since it was read (LiveModel::changedOnDisk) is read again, as by
  /// reopen(); requests holding the old opening finish on it, new ones see the new version whole.
  /// A reading that fails is logged and tried again after kFollowRetry. Returns how many models
  /// were read again. For one caller at a time (the daemon calls it twice a second).
  ///
  /// Fenced: a version whose revision carries a fencing token older than the newest this
  /// process has seen for the model (in any opening of it, its own publishes included) was
  /// committed by a writer that had lost the model; it is not followed (logged, counted in
  /// followsRefused(), not read again until the hierarchy file changes) and the model stays at
  /// the version it serves. Versions without a token are followed.
  std::size_t follow();
  /// The daemon's housekeeping, on its main thread, for every open model: removes the folders of
  /// dropped revisions whose last reader let go since (core::LiveModel::removeRetiredFolders), so
  /// that a request letting go of a revision never removes files itself; once per opening for
  /// writing, what interrupted edits left (core::LiveModel::removeLeftovers: after the daemon is
  /// ready, not before it listens; failures logged); and charges each model's metadata to the
  /// budget afresh (core::LiveModel::chargeMetadata). Returns the number of retired folders
  /// removed.
  std::size_t housekeeping();
  /// Versions follow() refused for a stale fencing token, since the registry was made.
  std::uint64_t followsRefused() const { return followsRefused_; }
  static constexpr std::chrono::seconds kFollowRetry{5};

  /// The open model `id`, or nullptr.
  std::shared_ptr<core::LiveModel> find(std::string_view id) const;
  /// The open model `id`. Throws core::Error(NotFound).
  std::shared_ptr<core::LiveModel> get(std::string_view id) const;

  /// An open model with the cache of response bodies encoded from its data.
  struct Served {
    std::shared_ptr<core::LiveModel> live;
    std::shared_ptr<EncodedCache> encoded;
  };
  /// The open model `id` and its EncodedCache, taken together (so both belong to the same opening
  /// of the model). Throws core::Error(NotFound). Never blocks on I/O.
  Served getServed(std::string_view id) const;
  /// Every open model, ordered by id.
  std::vector<std::shared_ptr<core::LiveModel>> list() const;
  std::size_t size() const;

  /// Removes `id` from the registry; its data stays on disk. Throws core::Error(NotFound) for an
  /// unknown id, Conflict while a job holds a lease on it.
  void close(std::string_view id);

  /// An RAII hold of a job on a model id (see the class comment). Movable.
  class Lease {
   public:
    Lease() = default;
    Lease(Lease&& other) noexcept;
    Lease& operator=(Lease&& other) noexcept;
    ~Lease();

   private:
    friend class ModelRegistry;
    Lease(ModelRegistry* registry, std::string id) : registry_(registry), id_(std::move(id)) {}
    void release();
    ModelRegistry* registry_ = nullptr;
    std::string id_;
  };

  /// A lease on the open model `id`. Throws core::Error(NotFound).
  Lease lease(std::string_view id);
  /// Reserves an id that is not open yet (an import in progress): open() under it is then allowed
  /// only to the holder (pass the lease), and a second reservation or open() by others is a
  /// Conflict. Throws core::Error(InvalidArgument) for a bad id, Conflict when open or reserved.
  Lease reserve(const std::string& id);
  /// open() for the holder of reserve(id)'s lease.
  std::shared_ptr<core::LiveModel> openReserved(const Lease& reservation,
                                                const std::filesystem::path& dir);

 private:
  /// Throws Conflict when limitModels()'s bound is reached; under mutex_.
  void checkRoomLocked(std::string_view id) const;
  bool atLimit() const;
  std::shared_ptr<core::LiveModel> openChecked(const std::string& id,
                                               const std::filesystem::path& dir, bool reserved);
  void unlease(const std::string& id);
  /// Passes `live`'s publishes to onPublished_.
  void watch(core::LiveModel& live) const;

  // Following (model_following.cpp).
  /// Tells onPublished_ of `fresh` when it is a newer version than `old` (another writer's).
  void announceFollowed(const core::LiveModel& old, const core::LiveModel& fresh) const;
  /// Puts `fresh`, a new opening of `id`, in place of the opening `old` and announces the
  /// versions between them (announceFollowed); false, dropping `fresh`, when `id` was closed or
  /// replaced meanwhile.
  bool swapOpening(std::string_view id, const std::shared_ptr<core::LiveModel>& old, Served fresh);
  /// Replaces the opening `old` of `id` by old->reopen() and returns the new opening's version;
  /// nullopt when reading failed (logged with `why`) or `id` was closed or replaced meanwhile.
  /// With `refused`, a new opening whose fencing token is older than one seen for `id` is
  /// refused (follow()): nullopt, and *refused set.
  std::optional<std::uint64_t> replace(const std::shared_ptr<core::LiveModel>& old,
                                       std::string_view id, std::string_view why,
                                       bool* refused = nullptr);

  std::filesystem::path root_;
  core::PatchCache& cache_;
  const std::uint64_t texturePixels_;
  const unsigned keepRevisions_;
  const std::chrono::seconds keepSeconds_;
  std::size_t maxModels_ = std::numeric_limits<std::size_t>::max();
  mutable std::mutex mutex_;  // guards models_, leases_, reserved_, opening_
  std::map<std::string, Served, std::less<>> models_;
  /// Id -> number of leases (on open models and reservations alike).
  std::map<std::string, int, std::less<>> leases_;
  /// Ids reserved for imports.
  std::set<std::string, std::less<>> reserved_;
  /// Ids being opened right now (open() reads the disk without the lock).
  std::set<std::string, std::less<>> opening_;
  std::function<bool(std::string_view)> writes_;         // set before any model is opened
  WriterFence fence_;                                    // set before the first job
  std::function<void(const Publication&)> onPublished_;  // set before any model is opened
  /// setWriter()'s own state: models whose last change of role failed (logged once).
  std::set<std::string, std::less<>> roleFailed_;
  /// openAll()'s own state: directories it skipped, with their hierarchy file as it was then, and
  /// those that failed with an I/O error, tried at every call (their warning said once).
  std::map<std::string, std::optional<core::HierarchyStamp>, std::less<>> skipped_;
  std::set<std::string, std::less<>> retrying_;
  /// The newest fencing token (takeover) seen per model id, guarded by mutex_.
  TakeoverBook takeovers_;
  std::atomic<std::uint64_t> followsRefused_{0};
  /// follow()'s own state: models whose reading failed, hierarchy files it refused.
  FollowSchedule followSchedule_;
};

}  // namespace vsm::server::models
