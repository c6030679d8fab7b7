#pragma once

#include <atomic>
#include <cstdint>
#include <deque>
#include <filesystem>
#include <functional>
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

/// The file under Patches/ that keeps the hierarchy of revision `number` once a later one is
/// published: "vsm-revision-<number>.xml".
std::string revisionFileName(std::uint64_t number);

/// One kept revision of a model, as LiveModel::revisions() lists it.
struct RevisionSummary {
  std::uint64_t number = 0;
  RevisionRecord record;
  bool latest = false;
};

/// What publish() records and keeps.
struct PublishOptions {
  /// The job that made the revision (empty: none, e.g. the CLI).
  std::string job;
  /// Revisions kept after the publish, the new one included: at least 2 (the previous revision
  /// stays while replicas in other processes follow the new one).
  unsigned keepRevisions = kDefaultKeepRevisions;
  /// The revision whose content this one restores (0: none).
  std::uint64_t restoredFrom = 0;
  /// Writes the changed patches' files from kPublishWriters tasks on this executor at once
  /// (encoding and writing overlap); null: on the calling thread.
  Executor* executor = nullptr;
};

/// Write-backs a publish runs at once when it has an executor.
inline constexpr int kPublishWriters = 4;

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
  /// point (OpcWriter::finishHierarchy) and removes what interrupted edits of vsm left behind:
  /// folders named like vsm's ("d_x_y", "d_x_y-vN") that the hierarchy does not name, their
  /// texture tiles, and temporary files of interrupted writes (a removal that fails is logged and
  /// retried at the next open). Throws as readOpcModel, and Error(Io).
  ///
  /// `texturePixels` bounds the texture files it decodes (readTextureTile's `maxPixels`).
  static std::unique_ptr<LiveModel> open(const std::filesystem::path& dir, std::string name,
                                         PatchCache& cache, Access access = Access::Write,
                                         std::uint64_t texturePixels = kDefaultTexturePixels);

  /// A new opening of the same directory, read again from disk, with this one's writer lock
  /// passed on (both share it): after a failed write nothing this opening holds in memory is
  /// trusted. It does not remove leftovers (readers of this opening may still read the old
  /// version's folders); the next open() does. Throws as open().
  std::unique_ptr<LiveModel> reopen() const;
  /// Precondition: no edit open.
  ~LiveModel();
  LiveModel(const LiveModel&) = delete;
  LiveModel& operator=(const LiveModel&) = delete;

  const std::string& name() const { return name_; }
  /// False when opened for reading only; readOnlyReason() then says why (empty for Access::Read).
  bool writable() const { return lock_ != nullptr; }
  const std::string& readOnlyReason() const { return readOnlyReason_; }
  /// True when the directory's hierarchy file is no longer the one this opening read: another
  /// writer published a new version (or removed the model). For an opening for reading only,
  /// which follows such publishes by reopen(); an opening that writes publishes itself.
  bool changedOnDisk() const;
  const std::filesystem::path& dir() const { return dir_; }
  /// The bound on the pixels of a texture file this model decodes, as open() was given it.
  std::uint64_t texturePixels() const;

  /// The current published version.
  std::shared_ptr<const ModelSnapshot> snapshot() const;

  /// A kept revision (its number is the version it published): the current one, or one whose
  /// hierarchy is kept as Patches/vsm-revision-<n>.xml. Its patches are read through the cache as
  /// the current version's; its folders stay while the snapshot is held, even when a publish
  /// drops the revision meanwhile. Throws Error(NotFound) for a revision not kept (or newer than
  /// this opening's current one), Error(Corrupt / Io) from its files.
  std::shared_ptr<const ModelSnapshot> snapshotAt(std::uint64_t revision);
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

  /// Starts the one edit of this model. Throws Error(Conflict) while another edit is open or when
  /// the model was opened for reading only; Error(Io) when the file system cannot be opened for
  /// syncing.
  std::unique_ptr<ModelEdit> beginEdit();

  /// Patch versions a publish replaced (or removed): (key, old version).
  using ReplacedVersions = std::vector<std::pair<PatchKey, std::uint64_t>>;
  /// Sets the one function called after every publish with the versions it replaced, on the
  /// publishing thread with no lock held: for caches of data derived from patches (encoded
  /// responses) to drop what readers of the new version never ask for. Thread-safe.
  void onPublish(std::function<void(const ReplacedVersions&)> observer);

  /// Sets the one function called after every publish, after the onPublish observer, with the
  /// version published and every key it changed (added or replaced): for telling clients (the
  /// daemon's event stream). Same thread and lock rules as onPublish; independent of it, so that
  /// caches and notifications do not replace each other. Thread-safe.
  using NewVersionObserver =
      std::function<void(std::uint64_t version, const std::set<PatchKey>& changed)>;
  void onNewVersion(NewVersionObserver observer);

  class Store;  // the PatchStore over the directory; defined in the .cpp

 private:
  friend class ModelEdit;
  LiveModel(std::filesystem::path dir, std::string name, std::shared_ptr<Store> store,
            std::shared_ptr<ModelSnapshot> snapshot,
            std::shared_ptr<const durable::WriterLock> lock);
  /// Step 5 of ModelEdit::publish: drops the oldest kept revisions until `keep` remain with the
  /// current one (`current`, whose model is `latest`). Failures are logged, not thrown.
  void dropRevisions(std::uint64_t current, const Model& latest, unsigned keep);
  static std::unique_ptr<LiveModel> load(const std::filesystem::path& dir, std::string name,
                                         PatchCache& cache,
                                         std::shared_ptr<const durable::WriterLock> lock,
                                         bool sweep, std::uint64_t texturePixels);

  std::filesystem::path dir_;
  std::string name_;
  std::shared_ptr<Store> store_;
  mutable std::mutex mutex_;  // guards snapshot_ (the pointer, not the snapshot)
  std::shared_ptr<ModelSnapshot> snapshot_;
  std::atomic<bool> editing_{false};
  /// Null when opened for reading.
  std::shared_ptr<const durable::WriterLock> lock_;
  std::string readOnlyReason_;
  /// Every snapshot of a revision this opening made that may still be held (guarded by mutex_):
  /// a publish that drops a revision hands its folder removal to it.
  std::map<std::uint64_t, std::weak_ptr<ModelSnapshot>> revisionSnapshots_;
  /// The last old revisions read by snapshotAt, held so that the next request for them does not
  /// read their metadata again (guarded by mutex_; dropped with their revision).
  std::deque<std::shared_ptr<ModelSnapshot>> recentRevisions_;
  /// The hierarchy file as it was just before this opening read it.
  std::optional<HierarchyStamp> readStamp_;
  std::function<void(const ReplacedVersions&)> onPublish_;  // guarded by mutex_
  NewVersionObserver onNewVersion_;                         // guarded by mutex_
};

/// The next version of a LiveModel, invisible to readers until publish(). A changed patch gets
/// version (published version + 1) and a new folder; its data lives in the cache as dirty and is
/// written there when evicted or at publish. Destroying an unpublished edit discards it: its
/// cache entries are dropped and its folders removed.
///
/// Not thread-safe: one thread drives an edit. Pins it returns must be released before publish()
/// or destruction.
class ModelEdit {
 public:
  ~ModelEdit();
  ModelEdit(const ModelEdit&) = delete;
  ModelEdit& operator=(const ModelEdit&) = delete;

  /// The working metadata (structure, boxes, states) of the next version.
  const Model& model() const { return *model_; }
  /// The version this edit was started from.
  const ModelSnapshot& base() const { return *base_; }

  /// Current data of a patch in this edit: its new data if changed, else the published data.
  /// Throws Error(NotFound) for a key not in the model.
  PatchCache::Pin positions(const PatchKey& key);
  /// Current texture tile of a patch (as positions()); an empty Pin when it has none.
  PatchCache::Pin texture(const PatchKey& key);

  /// Adds a patch (its parent must exist already) or replaces a patch's data, with its texture
  /// tile or without one (null). Marks the patch changed and every ancestor stale. Throws
  /// Error(InvalidArgument) for a wrong grid or tile size or a missing parent,
  /// Error(ResourceExhausted) when the budget is full of pinned data.
  void setPositions(const PatchKey& key, std::shared_ptr<const PatchGrid> grid,
                    std::shared_ptr<const TextureTile> texture = nullptr);

  /// Writes a changed patch's data (positions and texture tile) into its draft folder now rather
  /// than at publish, for a patch this edit will not change again: the write overlaps the edit's
  /// further work, and the data becomes evictable without a write-back. Nothing for a patch
  /// whose data is not changed or already written. Thread-safe for distinct keys, beside
  /// setPositions of other keys. Throws Error(Io) as publish would; the edit is then only fit to
  /// be discarded.
  void writeEarly(const PatchKey& key);

  /// Recomputes every stale overview bottom-up by reduction, holding one parent's children at a
  /// time; its texture tile is downsampled from the children's (downsampleQuadrants), a child
  /// without a tile of its own size (none, or a foreign one of another size) counting with its
  /// shaded relief (shadedRelief), so every overview an edit writes has a tile.
  void refreshStale(const CancelToken* cancel = nullptr);

  /// Makes this edit's content that of `from`, a kept revision of the same model
  /// (LiveModel::snapshotAt): each patch it holds in another version than the edit gets its data
  /// and texture tile again in a new folder (copy-on-write, so the model version still rises),
  /// and each patch it does not hold is removed. Published, the surface is `from`'s, patch for
  /// patch. Call it on a fresh edit. Throws as setPositions, and Error(InvalidArgument) for a
  /// snapshot of another patch size.
  void restore(const ModelSnapshot& from, const CancelToken* cancel = nullptr);

  /// Publishes the edit as the model's next version:
  ///
  /// 1. refreshes stale overviews, writes every changed patch that is still in the cache, and
  ///    makes all draft files durable with the edit's FileSystemSync (its descriptor was opened
  ///    when the edit began, so no write-back error since is missed);
  /// 2. keeps the base revision's hierarchy as Patches/vsm-revision-<base>.xml (when not kept
  ///    yet), and writes the new hierarchy, recording the revision (`options`), under a temporary
  ///    name and fsyncs it;
  /// 3. **the commit point**: renames it over Patches/patchhierarchy.xml. snapshot() is the new
  ///    version from here on;
  /// 4. syncs Patches/ and removes a stale hierarchy.cache (OpcWriter::finishHierarchy);
  /// 5. drops the oldest revisions beyond options.keepRevisions: first its hierarchy file, then
  ///    the folders (and tiles) no later revision names, once no snapshot of it is held here.
  ///
  /// A failure before 3 throws and leaves the old version: the edit is then only fit to be
  /// discarded (its drafts are removed; a failed sync is never retried on the same pages).
  /// Cancellation is honoured up to 3. A failure in 4 throws Error(Io) saying the version is
  /// published: it is not undone, and the next open() retries step 4. A removal in 5 that fails is
  /// logged and left to the next open. Throws Error(InvalidArgument) first when keepRevisions < 2
  /// or the edit changes nothing.
  void publish(const CancelToken* cancel = nullptr, const PublishOptions& options = {});

  /// True from the commit point of publish() on.
  bool published() const { return published_; }

  /// Keys changed (added or replaced) in this edit.
  const std::set<PatchKey>& changed() const { return changed_; }
  /// Keys of the base this edit removed.
  const std::set<PatchKey>& removed() const { return removed_; }

 private:
  friend class LiveModel;
  ModelEdit(LiveModel& live, std::shared_ptr<const ModelSnapshot> base);
  ObjectId draftId(const PatchKey& key) const;

  LiveModel& live_;
  /// Opened when the edit begins: syncfs on it reports every write-back error since.
  durable::FileSystemSync sync_;
  std::shared_ptr<const ModelSnapshot> base_;
  std::unique_ptr<Model> model_;
  std::set<PatchKey> changed_;
  std::set<PatchKey> removed_;
  bool published_ = false;
};

}  // namespace vsm::core
