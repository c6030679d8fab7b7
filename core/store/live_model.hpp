#pragma once

#include <atomic>
#include <chrono>
#include <cstdint>
#include <deque>
#include <filesystem>
#include <functional>
#include <future>
#include <map>
#include <memory>
#include <mutex>
#include <optional>
#include <set>
#include <string>
#include <utility>
#include <vector>

#include "core/cache/patch_cache.hpp"
#include "core/common/executor.hpp"
#include "core/common/progress.hpp"
#include "core/durable/durable_io.hpp"
#include "core/durable/writer_lock.hpp"
#include "core/grid/texture_tile.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/opc/texture_file.hpp"
#include "core/pyramid/model.hpp"

namespace vsm::core {

/// One published version of a model: immutable metadata (no vertex data attached). Readers hold a
/// snapshot for the length of a request and read every patch of it, so they see one consistent
/// version however long they take.
struct ModelSnapshot {
  std::shared_ptr<const Model> model;
  /// Increases with every publish: the newest version of any of its patches (at least 1), so it is
  /// the same in every process that reads the directory and after a restart.
  std::uint64_t version = 1;
  /// modelDigest(*model): computed once when the version is read, then kept by the change at
  /// each publish (what the server's entity tags of the whole model are made from).
  std::uint64_t digest = 0;
  /// For a version this process published: the metadata of the version it was published over
  /// (held weakly: no chain of versions is kept alive) and the change from it, which is exactly
  /// modelChange(parent, *model). Empty for a version read from disk.
  struct Published {
    std::weak_ptr<const Model> parent;
    ModelChange change;
  };
  std::optional<Published> published;
  /// What the hierarchy records about this revision (for one without a record, such as an
  /// import's or a foreign OPC's: no parent, the hierarchy file's time, every patch of this
  /// version counted as changed).
  RevisionRecord revision;
  /// Removals of folders only dropped revisions used, held back while this version is read (each
  /// runs when the last snapshot holding it is released; see ModelEdit::publish).
  std::vector<std::shared_ptr<const void>> heldRemovals;

  ModelSnapshot() = default;
  ModelSnapshot(const ModelSnapshot&) = delete;
  ModelSnapshot& operator=(const ModelSnapshot&) = delete;
  ~ModelSnapshot();
};

class ModelEdit;

/// The change from `before` to `after`'s metadata: the publish's record when `after` was
/// published over `before` in this process (no walk), else modelChange(*before, *after.model).
ModelChange changeSince(const std::shared_ptr<const Model>& before, const ModelSnapshot& after);

/// The file under Patches/ that keeps the hierarchy of revision `number` once a later one is
/// published: "vsm-revision-<number>.xml".
std::string revisionFileName(std::uint64_t number);

/// One kept revision of a model, as LiveModel::revisions() lists it.
struct RevisionSummary {
  std::uint64_t number = 0;
  RevisionRecord record;
  bool latest = false;
};

/// An open model: its OPC directory, the published metadata, and its patch data in the shared
/// cache. Readers work on snapshots; one edit at a time prepares the next version copy-on-write
/// (changed patches go to new folders) and publishes it by replacing the hierarchy atomically, so
/// a crash at any moment leaves the directory opening as exactly the old or the new version.
///
/// Opened for writing, a LiveModel holds the directory's durable::WriterLock for its whole life:
/// one writer per model across processes. Opened for reading, it takes no lock and cannot be
/// edited.
///
/// Thread-safe: any number of readers, one edit.
class LiveModel {
 public:
  /// Write: fail when the writer lock cannot be taken. WriteIfPossible: then open for reading
  /// only, keeping why (another writer holds the lock, or the directory is not writable: a
  /// read-only mount), as a server serving every model of a data root wants.
  enum class Access { Read, Write, WriteIfPossible };

  /// Opens `dir` (metadata only) and registers it with `cache` under `name`.
  ///
  /// Access::Write takes the writer lock first (Error(Conflict) naming the holder when another
  /// writer has it), then, under it, completes what an interrupted publish left after its commit
  /// point (OpcWriter::finishHierarchy); what interrupted edits left behind is removed later, by
  /// removeLeftovers(). Throws as readOpcModel, and Error(Io).
  ///
  /// `texturePixels` bounds the texture files it decodes (readTextureTile's `maxPixels`).
  static std::unique_ptr<LiveModel> open(const std::filesystem::path& dir, std::string name,
                                         PatchCache& cache, Access access = Access::Write,
                                         std::uint64_t texturePixels = kDefaultTexturePixels);

  /// A new opening of the same directory, read again from disk, sharing this one's writer state:
  /// the lock, the one edit of the model and the revisions readers hold. After a failed write
  /// nothing this opening holds in memory is trusted. From then on only the new opening can begin
  /// an edit (this one answers Conflict); readers of this one finish on it, and the revisions they
  /// hold are kept as snapshots are. Leftovers are removed once per open(), before its first
  /// edit, so never again after a reopen (readers of this opening may still read the old version's
  /// folders); the next open() removes them. Throws as open().
  std::unique_ptr<LiveModel> reopen() const;
  /// Precondition: no edit open.
  ~LiveModel();
  LiveModel(const LiveModel&) = delete;
  LiveModel& operator=(const LiveModel&) = delete;

  const std::string& name() const { return name_; }
  /// False when opened for reading only; readOnlyReason() then says why (empty for Access::Read).
  bool writable() const { return writer_ != nullptr; }
  const std::string& readOnlyReason() const { return readOnlyReason_; }
  /// True when the directory's hierarchy file is no longer the one this opening read: another
  /// writer published a new version (or removed the model). For an opening for reading only,
  /// which follows such publishes by reopen(); an opening that writes publishes itself.
  bool changedOnDisk() const;
  const std::filesystem::path& dir() const { return dir_; }
  /// The bound on the pixels of a texture file this model decodes, as open() was given it.
  std::uint64_t texturePixels() const;

  /// A cache file of vsm's beside the model's hierarchy in Patches/ (a name "vsm-<what>.bin", such
  /// as core::kSavedFootprintsFile; other OPC tools ignore it): its bytes, or nullopt when there is
  /// none or it holds more than `maxBytes` (a cache's size is the caller's bound). Throws
  /// Error(InvalidArgument) for another name, Error(Io) when it cannot be read.
  std::optional<std::vector<std::byte>> readCacheFile(std::string_view name,
                                                      std::size_t maxBytes) const;
  /// Replaces that file atomically and durably (durable::writeFileAtomically: a crash leaves the
  /// old bytes or the new), after removeLeftovers(). Throws Error(Conflict) for an opening for
  /// reading only, and as readCacheFile, removeLeftovers and the write.
  void writeCacheFile(std::string_view name, std::span<const std::byte> bytes);

  /// The current published version.
  std::shared_ptr<const ModelSnapshot> snapshot() const;

  /// A kept revision (its number is the version it published): the current one, or one whose
  /// hierarchy is kept as Patches/vsm-revision-<n>.xml. Its patches are read through the cache as
  /// the current version's; its folders stay while the snapshot is held, even when a publish
  /// drops the revision meanwhile. Throws Error(NotFound) for a revision not kept (or newer than
  /// this opening's current one), Error(Corrupt / Io) from its files.
  ///
  /// Each revision is read from disk once while it stays cached: the kCachedRevisions revisions
  /// last asked for are kept (least recently asked for dropped first), and a caller asking for a
  /// revision another caller is reading waits for that read (on this call's thread; no thread is
  /// created) and gets its snapshot or its error. A failed read is not kept: the next call reads
  /// again. Thread-safe.
  std::shared_ptr<const ModelSnapshot> snapshotAt(std::uint64_t revision);
  /// How many old revisions snapshotAt keeps read (per opening; their metadata is charged to the
  /// memory budget with the rest by chargeMetadata(); those whose indexes build on one base share
  /// it, and cost one model and their deltas).
  static constexpr std::size_t kCachedRevisions = 8;

  /// What snapshotAt did, since this opening was made.
  struct RevisionReadStats {
    /// Revisions read from disk, and calls that waited for another caller's read instead.
    std::uint64_t reads = 0;
    std::uint64_t sharedReads = 0;
    /// Reads in progress, and callers waiting for one, now.
    std::uint64_t reading = 0;
    std::uint64_t waiting = 0;
    /// Old revisions kept read now (at most kCachedRevisions).
    std::uint64_t cached = 0;
  };
  RevisionReadStats revisionReadStats() const;
  /// snapshotAt() when that needs no disk access (the current revision, or one held in memory);
  /// null otherwise. Never blocks on I/O.
  std::shared_ptr<const ModelSnapshot> heldSnapshot(std::uint64_t revision) const;

  /// The kept revisions, oldest first, the current one last. Throws Error(Corrupt / Io) from a
  /// revision file.
  std::vector<RevisionSummary> revisions() const;

  /// Vertex data of `key` as published in `snapshot`, through the cache (pinned while the Pin
  /// lives). Throws Error(NotFound) when the snapshot has no such patch, Error(ResourceExhausted)
  /// when the budget is full of pinned data, Error(Corrupt / Io) from the files.
  PatchCache::Pin positions(const ModelSnapshot& snapshot, const PatchKey& key);

  /// The texture tile (TextureTile) of `key` as published in `snapshot`, through the cache; an
  /// empty Pin when the patch has none. Throws as positions(), and Error(Corrupt) for a tile that
  /// does not decode.
  PatchCache::Pin texture(const ModelSnapshot& snapshot, const PatchKey& key);

  /// Starts the one edit of this model, whatever the opening (model_edit.hpp). Throws
  /// Error(Conflict) when the model was opened for reading only, while another edit of it is open
  /// (through any opening sharing the writer state), when a later reopen() replaced this opening,
  /// or when the hierarchy on disk is not the one this opening last read or published (another
  /// writer changed it: optimistic concurrency on the hierarchy's stamp); Error(Io) when the file
  /// system cannot be opened for syncing.
  std::unique_ptr<ModelEdit> beginEdit();

  /// Patch versions a publish replaced (or removed): (key, old version).
  using ReplacedVersions = std::vector<std::pair<PatchKey, std::uint64_t>>;
  /// Sets the one function called after every publish with the versions it replaced, on the
  /// publishing thread with no lock held: for caches of data derived from patches (encoded
  /// responses) to drop what readers of the new version never ask for. Thread-safe.
  void onPublish(std::function<void(const ReplacedVersions&)> observer);

  /// Sets the one function called after every publish, after the onPublish observer, with the
  /// version published, every key it changed (added or replaced) and every key it removed (a
  /// restore): for telling clients (the daemon's event stream). Same thread and lock rules as
  /// onPublish; independent of it, so that caches and notifications do not replace each other.
  /// Thread-safe.
  using NewVersionObserver = std::function<void(
      std::uint64_t version, const std::set<PatchKey>& changed, const std::set<PatchKey>& removed)>;
  void onNewVersion(NewVersionObserver observer);

  /// For an opening that writes: removes what interrupted edits of vsm left behind: folders named
  /// like vsm's ("d_x_y", "d_x_y-vN") that no kept revision names, their texture tiles, indexes of
  /// no kept hierarchy, and temporary files of interrupted writes (a removal that fails is logged
  /// and retried at the next open). Once per open() for writing, before its first edit: beginEdit
  /// calls it, and a caller that opens many models calls it when it has time (the daemon, once it
  /// serves: at 10^6 patches this lists a million folders). Later calls, and calls on an opening
  /// for reading, do nothing. Throws Error(Io) when Patches/ cannot be listed (the next call tries
  /// again).
  void removeLeftovers();

  /// Charges the metadata this opening holds in memory to the cache's budget
  /// (PatchCache::chargeMetadata): an estimate, made of Model::heapBytes of every version it
  /// holds (the current one, kept revisions read and still held, the index bases it keeps), each
  /// chunk once, the store's table of the versions the current one does not hold, and a writer's
  /// hierarchy text. The first call walks every patch (~0.3 s at 10^6: the daemon makes it in its
  /// housekeeping, after it serves), later ones the chunks of those versions that are new since
  /// (each chunk keeps what it found): the caller charges again often (the daemon: every half
  /// second). Thread-safe.
  void chargeMetadata();

  /// Removes the folders of dropped revisions whose last reader has let go. Letting go only
  /// queues them (it may happen on a network thread or under a lock, and a removal is slow
  /// I/O); the publish that dropped them and the daemon's housekeeping (ModelRegistry) call
  /// this. Returns the number of folders removed (failures are logged: the next open removes
  /// what is left). A model closed with folders queued leaves them to its next open, which
  /// removes every folder no kept revision names.
  std::size_t removeRetiredFolders();

  class Store;    // the PatchStore over the directory (model_store.hpp)
  struct Writer;  // what the openings of a model that may write share (below)

 private:
  friend class ModelEdit;
  LiveModel(std::filesystem::path dir, std::string name, std::shared_ptr<Store> store,
            std::shared_ptr<ModelSnapshot> snapshot, std::shared_ptr<Writer> writer);
  /// Throws Error(Conflict) unless this opening is its writer's current one and `onDisk`, the
  /// hierarchy's stamp taken just before (no lock is held over the stat), is the one it last read
  /// or published. Called with writer_->mutex held.
  void checkCurrent(const std::optional<HierarchyStamp>& onDisk) const;
  /// Hands `removal` to every snapshot of `revision` held through this opening (it runs when the
  /// last of them, and of the other openings', is released), and forgets the revision.
  void holdRemoval(std::uint64_t revision, const std::shared_ptr<const void>& removal);
  /// The last step of ModelEdit::publish: drops the oldest kept revisions until `keep` remain with
  /// the current one, `current`, keeping each whose successor is younger than `keepSeconds` and
  /// each in `readElsewhere` (with the ones after it: folders are dropped oldest first).
  /// Failures are logged, not thrown.
  /// `hiddenFiles`: second hierarchy files that may no longer be named (the replaced hierarchy's),
  /// removed with the dropped revisions' when no kept hierarchy names them.
  void dropRevisions(const ModelSnapshot& current, unsigned keep, std::chrono::seconds keepSeconds,
                     const std::set<std::uint64_t>& readElsewhere = {},
                     std::set<std::string> hiddenFiles = {});
  /// `indexBases`: the memo of a reading opening being read again (reopen()); null for a first
  /// opening (a reading one makes its own) and for a writer's, which keeps none.
  static std::unique_ptr<LiveModel> load(const std::filesystem::path& dir, std::string name,
                                         PatchCache& cache, std::shared_ptr<Writer> writer,
                                         std::uint64_t texturePixels,
                                         std::shared_ptr<IndexBaseMemo> indexBases = nullptr);

  std::filesystem::path dir_;
  std::string name_;
  std::shared_ptr<Store> store_;
  /// Lock order: writer_->mutex, then mutex_.
  /// Guards snapshot_ (the pointer, not the snapshot), readStamp_, and the revision cache below
  /// (revisionSnapshots_, recentRevisions_, revisionReads_, readStats_). snapshotAt never holds it
  /// while reading a revision's file or waiting for another caller's read.
  mutable std::mutex mutex_;
  std::shared_ptr<ModelSnapshot> snapshot_;
  /// Null when opened for reading.
  std::shared_ptr<Writer> writer_;
  /// A reading opening's last decoded index base, passed on by reopen(): following a publish
  /// decodes only its delta. Null for a writer's (the base it read is soon replaced by its own
  /// publishes, and would be kept for nothing).
  std::shared_ptr<IndexBaseMemo> indexBases_;
  /// The index base the revisions snapshotAt reads build on (indexBases_ for a reading opening,
  /// its own for a writer's): revisions over one base share its chunks and nodes, so the
  /// kCachedRevisions kept read cost one model and their deltas, not one model each.
  std::shared_ptr<IndexBaseMemo> revisionBases_;
  std::string readOnlyReason_;
  /// Every snapshot of a revision this opening made that may still be held (guarded by mutex_):
  /// a publish that drops a revision hands its folder removal to it.
  std::map<std::uint64_t, std::weak_ptr<ModelSnapshot>> revisionSnapshots_;
  /// The old revisions snapshotAt read or handed out last, least recently asked for first, at
  /// most kCachedRevisions, held so that the next request for them does not read their metadata
  /// again (guarded by mutex_; dropped with their revision).
  std::deque<std::shared_ptr<ModelSnapshot>> recentRevisions_;
  /// Reads of revisions in progress: the callers asking for one meanwhile wait for its future
  /// (guarded by mutex_; never waited on with it held).
  std::map<std::uint64_t, std::shared_future<std::shared_ptr<ModelSnapshot>>> revisionReads_;
  /// RevisionReadStats (guarded by mutex_).
  RevisionReadStats readStats_;
  /// Reads revision `revision` from its file (no lock held). Throws as snapshotAt.
  std::shared_ptr<ModelSnapshot> readRevision(std::uint64_t revision);
  /// The hierarchy file as it was just before this opening read it, or as its last publish made
  /// it.
  std::optional<HierarchyStamp> readStamp_;
  std::function<void(const ReplacedVersions&)> onPublish_;  // guarded by mutex_
  NewVersionObserver onNewVersion_;                         // guarded by mutex_
};

/// What every opening of one model in this process that may write shares (open() makes it,
/// reopen() passes it on): the writer lock, the flag of the one edit, the opening that may begin
/// it, and every opening, so that a publish through one keeps what readers of the others hold.
struct LiveModel::Writer {
  std::shared_ptr<const durable::WriterLock> lock;
  /// Folders of dropped revisions whose last reader let go, with the store that knew them,
  /// waiting for removeRetiredFolders(). Guarded by retiredMutex, a leaf lock: a reader may let
  /// go anywhere, on any thread, with any other lock held.
  std::mutex retiredMutex;
  std::vector<std::pair<std::weak_ptr<Store>, FolderSet>> retired;
  /// Set once removeLeftovers() has run (guarded by leftoversMutex, held over the removal, which
  /// takes writer->mutex and mutex_ of the current opening for moments).
  std::mutex leftoversMutex;
  bool leftoversRemoved = false;
  std::mutex mutex;  // guards everything below but hierarchyText (its own lock)
  bool editing = false;
  /// The newest opening: the only one that may begin an edit.
  const LiveModel* current = nullptr;
  /// Every live opening (each adds itself when made and removes itself when destroyed).
  std::vector<LiveModel*> openings;
  /// The kept revisions' hierarchy files (number -> path) as the last publish left them: listed
  /// from Patches/ once (it holds a folder per patch: 34 ms at 87k patches, ~0.6 s at 10^6), by
  /// the leftover sweep or else the first publish, then kept by each publish (dropRevisions).
  /// Nullopt: not listed yet, or forgotten after a failure or a reopen.
  std::optional<std::map<std::uint64_t, std::filesystem::path>> revisionFiles;
  /// The text of the last hierarchy a publish staged: the next one makes only the runs of
  /// patches its change touched (about the hierarchy's size: 60 MB at 10^6 patches).
  HierarchyMemo hierarchyText;
};

}  // namespace vsm::core
