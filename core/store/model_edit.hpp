#pragma once

#include <chrono>
#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <set>
#include <string>

#include "core/cache/patch_cache.hpp"
#include "core/common/executor.hpp"
#include "core/common/progress.hpp"
#include "core/durable/durable_io.hpp"
#include "core/store/live_model.hpp"

namespace vsm::core {

/// What publish() records and keeps.
struct PublishOptions {
  /// The job that made the revision (empty: none, e.g. the CLI).
  std::string job;
  /// Revisions kept after the publish, the new one included: at least 2 (the previous revision
  /// stays while replicas in other processes follow the new one).
  unsigned keepRevisions = kDefaultKeepRevisions;
  /// A time floor beside the count: a revision is kept while the one that replaced it is younger
  /// than this (by its record's time), however many there are: readers in other processes (a
  /// replica re-reading it) get that long. 0: the count alone.
  std::chrono::seconds keepSeconds{0};
  /// The revision whose content this one restores (0: none).
  std::uint64_t restoredFrom = 0;
  /// Writes the changed patches' files from kPublishWriters tasks on this executor at once
  /// (encoding and writing overlap), and the new hierarchy beside them; null: one after the other
  /// on the calling thread.
  Executor* executor = nullptr;
  /// Called just before the commit point, after every other check: throws to refuse the commit
  /// (a cluster node that no longer holds the model's lease: Error(Conflict)). Null: no fence.
  std::function<void()> fence;
  /// The writer's fencing token (a cluster node's claim on the model), recorded in the new
  /// revision (<Vsm><Revision><Fence>). With it the commit is refused (Error(Conflict)) when the
  /// hierarchy on disk carries a newer token: a writer that took the model over later published.
  /// Nullopt: no token recorded, none checked.
  std::optional<FencingToken> token;
  /// The revisions other processes read now (a cluster's replicas, as they say in etcd), asked
  /// when old revisions are dropped: each is kept, with every later one, besides the count and
  /// the time floor. Null: none.
  std::function<std::set<std::uint64_t>()> readElsewhere;
  /// False: the folders of the revisions the publish drops are removed before it returns. True:
  /// they wait for LiveModel::removeRetiredFolders(), which the caller runs off the writer's path
  /// (vsmd's housekeeping, after the job has answered: ~150 ms for a small merge's 57 folders).
  bool deferFolderRemoval = false;
};

/// Write-backs a publish runs at once when it has an executor.
inline constexpr int kPublishWriters = 4;

/// The next version of a LiveModel, invisible to readers until publish(). A changed patch gets
/// version (published version + 1) and a new folder (named with the edit's nonce); its data lives
/// in the cache as dirty and is written there when evicted or at publish. Destroying an unpublished
/// edit discards it: its cache entries are dropped and its folders removed.
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
  /// Error(InvalidArgument) for a wrong grid size, a tile not in vsm's layout (texelsPerQuadOf) or
  /// a missing parent,
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
  /// time; its texture tile is downsampled from the children's (downsampleQuadrants) with as many
  /// texels per quad as the finest child's (coarser ones upsampled: resizeTile; at most
  /// kMaxTextureTileSize texels a side, a finer foreign tile downsampled), a child without
  /// a tile in vsm's layout (none, or a foreign one: texelsPerQuadOf) counting with its shaded
  /// relief (shadedRelief), so every overview an edit writes has a tile.
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
  ///    when the edit began, so no write-back error since is missed); beside the patches' writes
  ///    (another task on options.executor), writes the new hierarchy, recording the revision
  ///    (`options`), under a temporary name and fsyncs it;
  /// 2. keeps the base revision's hierarchy as Patches/vsm-revision-<base>.xml (when not kept
  ///    yet);
  /// 3. **the commit point**, fenced: refuses (Error(Conflict)) unless the opening is still its
  ///    writer's current one, the hierarchy on disk is still the one it last read or published and
  ///    carries no fencing token newer than options.token, then calls options.fence; then renames
  ///    the new hierarchy over Patches/patchhierarchy.xml (a rename error is resolved by looking:
  ///    durable::PendingFile). snapshot() is the new version from here on;
  /// 4. syncs Patches/ and removes a stale hierarchy.cache (OpcWriter::finishHierarchy):
  ///    durable before announced;
  /// 5. tells the onPublish and onNewVersion observers (what they throw is logged, not thrown);
  /// 6. drops the oldest revisions beyond options.keepRevisions: first its hierarchy file, then
  ///    the folders (and tiles) no later revision names, once no snapshot of it is held through
  ///    any opening of the model in this process (and, with options.deferFolderRemoval, when
  ///    the caller runs LiveModel::removeRetiredFolders()). The folders are those the next
  ///    revision's index records as retired from it, or, without such a record, those neither
  ///    the next revision nor the latest names (both trees read).
  ///
  /// A failure before 3 throws and leaves the old version: the edit is then only fit to be
  /// discarded (its drafts are removed; a failed sync is never retried on the same pages).
  /// Cancellation is honoured up to 3. A failure in 4 throws Error(Io) saying the version is
  /// published: it is not undone, not announced, and the next open() retries step 4. A removal in
  /// 6 that fails is logged and left to the next open. Throws Error(InvalidArgument) first when
  /// keepRevisions < 2 or the edit changes nothing.
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
  /// Throws Error(Conflict) once published: the model is then the published version's.
  void requireOpen() const;
  /// Keeps the base's hierarchy (and its index) as Patches/`baseName`, durable: a hard link where
  /// the file system allows, else a copy. Throws Error(Io).
  void keepBaseHierarchy(const std::filesystem::path& patches, const std::string& baseName);
  /// Whether a patch this edit adds at `key` is a hidden level's (its parent exists).
  bool hiddenForNew(const PatchKey& key);
  /// The texels per quad of the base's visible leaves (the patches whose children are hidden),
  /// read off one of their tiles once; 0 without hidden levels.
  int visibleTexelsPerQuad();

  LiveModel& live_;
  /// Opened when the edit begins: syncfs on it reports every write-back error since.
  durable::FileSystemSync sync_;
  std::shared_ptr<const ModelSnapshot> base_;
  /// Shared with the published snapshot from the commit point on (and then never changed).
  std::shared_ptr<Model> model_;
  std::set<PatchKey> changed_;
  std::set<PatchKey> removed_;
  /// The parents of every patch given new data (Model::markChanged marked them and their
  /// ancestors stale): where refreshStale looks, instead of at every patch of the model.
  std::set<PatchKey> staleParents_;
  bool published_ = false;
  std::optional<int> visibleTexelsPerQuad_;
  /// This edit's own: in its draft folders' names and its revision record.
  std::string nonce_;
};

}  // namespace vsm::core
