#include <exception>
#include <set>
#include <utility>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/opc/opc_index.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/opc/opc_writer.hpp"
#include "core/store/model_edit.hpp"
#include "core/store/model_store.hpp"
#include "core/store/store_files.hpp"

// ModelEdit::publish: the protocol that makes an edit the model's next version, with one commit
// point (model_edit.hpp lists the steps).

namespace fs = std::filesystem;

namespace vsm::core {

using namespace store;

namespace {

/// Calls an observer of a publish, containing what it throws: the version is published and
/// durable whatever an observer does, so its failure is logged, never the job's.
template <typename Call>
void tellObserver(const std::string& model, const char* what, Call&& call) {
  try {
    call();
  } catch (const std::exception& e) {
    log::error("model=" + model + " " + what + " of a published version failed: " + e.what());
  } catch (...) {
    log::error("model=" + model + " " + what + " of a published version failed");
  }
}

/// Refuses a commit under `token` when the hierarchy on disk (`file`) was published under a newer
/// one: a writer that took the model over later has published, and this one lost it.
void checkToken(const fs::path& file, const FencingToken& token) {
  const std::optional<RevisionRecord> onDisk = readRevisionRecord(file);
  if (onDisk && onDisk->fence && onDisk->fence->takeover > token.takeover) {
    throw Error(ErrorCode::Conflict,
                "the model on disk was published by a later writer (fencing token " +
                    std::to_string(onDisk->fence->takeover) + ", this writer's " +
                    std::to_string(token.takeover) + "); the write is not committed");
  }
}

}  // namespace

void ModelEdit::keepBaseHierarchy(const fs::path& patches, const std::string& baseName) {
  // A hard link to the base's hierarchy file and its index where the file system allows: no copy,
  // and the index stays current for it (a link has the file's stamp). The link is checked to be
  // the base this edit began from (another writer may have replaced the file); else a copy.
  durable::DraftWriter links;
  const fs::path current = patches / "patchhierarchy.xml";
  const fs::path kept = patches / baseName;
  const std::optional<HierarchyStamp> baseStamp = [&] {
    std::lock_guard lock(live_.mutex_);
    return live_.readStamp_;
  }();
  if (baseStamp && links.link(current, kept)) {
    const std::optional<HierarchyStamp> linked = [&]() -> std::optional<HierarchyStamp> {
      try {
        return fileStamp(kept);
      } catch (const Error&) {
        return std::nullopt;
      }
    }();
    if (linked && linked->inode == baseStamp->inode && linked->size == baseStamp->size &&
        linked->modifiedNs == baseStamp->modifiedNs) {
      if (readOpcIndexSummary(live_.dir_)) {  // current (its head's stamp), not decoded
        links.link(patches / indexFileName("patchhierarchy.xml"),
                   patches / indexFileName(baseName));
      }
      durable::syncDirectory(patches);
      return;
    }
    std::error_code ec;
    fs::remove(kept, ec);  // another file: a copy replaces it below
  }
  const std::unique_ptr<durable::PendingFile> copy =
      stageHierarchy(live_.dir_, *base_->model, &base_->revision, baseName);
  stageOpcIndex(live_.dir_, baseName, copy->staged(), *base_->model, &base_->revision)->commit();
  copy->commit();
  durable::syncDirectory(patches);
}

void ModelEdit::publish(const CancelToken* cancel, const PublishOptions& options) {
  requireOpen();
  if (options.keepRevisions < 2) {
    throw Error(ErrorCode::InvalidArgument,
                "at least 2 revisions are kept (the previous one while replicas follow), not " +
                    std::to_string(options.keepRevisions));
  }
  if (changed_.empty() && removed_.empty()) {
    throw Error(ErrorCode::InvalidArgument, "the edit changes nothing: no new revision");
  }
  refreshStale(cancel);
  if (cancel != nullptr) {
    cancel->throwIfCancelled();
  }
  LiveModel::Store& store = *live_.store_;
  const std::uint64_t version = base_->version + 1;
  auto snapshot = std::make_shared<ModelSnapshot>();
  snapshot->revision = {base_->version,  utcNow(),        options.job,
                        changed_.size(), removed_.size(), options.restoredFrom,
                        nonce_,          options.token};
  // 1. Every changed patch into its new folder (evicted ones were written already), durable.
  // Flushers take distinct dirty entries, so several run side by side. Beside them, the new
  // hierarchy naming the new folders, fsynced under a temporary name that nothing names before
  // the commit point: at 10^6 patches its 43 MB took as long as the rest of the publish.
  std::unique_ptr<durable::PendingFile> hierarchy;
  std::vector<std::function<void()>> writes{[&] {
    hierarchy = stageHierarchy(live_.dir_, *model_, &snapshot->revision, "patchhierarchy.xml",
                               &live_.writer_->hierarchyText);
  }};
  writes.resize(1 + (options.executor != nullptr ? kPublishWriters : 1),
                [&] { store.cache().flush(store.id()); });
  runTasks(options.executor, std::move(writes));
  sync_.sync();
  if (cancel != nullptr) {
    cancel->throwIfCancelled();
  }
  // 2. The base revision's hierarchy kept under its own name (once), durable before the commit
  // point: from then on its folders are named by a kept revision. Then everything the switch to
  // the new version needs, prepared so that nothing after the commit point can fail but its
  // durability.
  const fs::path patches = patchesDirOf(live_.dir_);
  const std::string baseName = revisionFileName(base_->version);
  if (!fs::exists(patches / baseName)) {
    keepBaseHierarchy(patches, baseName);
  }
  // The base's second hierarchy file (hidden levels): named by the kept revision when that is a
  // link, else by nothing once the new hierarchy replaces the base's (removed in step 6).
  std::set<std::string> replacedHidden;
  if (std::optional<std::string> hidden = hiddenHierarchyNamedBy(patches / "patchhierarchy.xml")) {
    replacedHidden.insert(std::move(*hidden));
  }
  // Its index (opc_index.hpp), for the staged file's stamp, which the rename keeps: committed just
  // before the hierarchy, both made durable by the one sync of Patches/ in step 4. A crash between
  // the two renames leaves the old hierarchy with an index of another stamp: read in full once.
  // With the folders this version no longer names, which dropping the base revision removes.
  std::vector<RetiredFolder> retired;
  for (const PatchKey& key : changed_) {
    if (const PatchInfo* old = base_->model->find(key);
        old != nullptr && old->folder() != model_->at(key).folder()) {
      retired.push_back({key, old->folder()});
    }
  }
  for (const PatchKey& key : removed_) {
    retired.push_back({key, base_->model->at(key).folder()});
  }
  // A delta over the current index's base, or a new base when the change since it has grown.
  const std::optional<HierarchyStamp> replacedStamp = [&] {
    std::lock_guard lock(live_.mutex_);
    return live_.readStamp_;
  }();
  const StagedIndex index = stagePublishedIndex(
      live_.dir_, hierarchy->staged(), *model_, snapshot->revision, retired, changed_, removed_,
      replacedStamp, "vsm-index-base-" + std::to_string(version) + "-" + nonce_ + ".vsmidx");
  // Durable before any index names it (a lost rename would leave a delta without its base).
  index.commitBase();
  // The new version's metadata is the edit's own, shared, not copied (10^5 patches: tens of MB
  // and a tenth of a second): nothing changes it after the commit point (requireOpen).
  snapshot->model = model_;
  snapshot->version = version;
  // The digest by the change: the base's, less the patches replaced or removed, plus the new ones.
  snapshot->digest = base_->digest;
  for (const PatchKey& key : removed_) {
    snapshot->digest -= patchDigest(base_->model->at(key));
  }
  for (const PatchKey& key : changed_) {
    if (const PatchInfo* old = base_->model->find(key); old != nullptr) {
      snapshot->digest -= patchDigest(*old);
    }
    snapshot->digest += patchDigest(model_->at(key));
  }
  snapshot->published = ModelSnapshot::Published{
      base_->model, {{changed_.begin(), changed_.end()}, {removed_.begin(), removed_.end()}}};

  // 3. The commit point, fenced: this opening is still the model's and the hierarchy on disk is
  // still the base (no other writer published meanwhile), and the caller's fence (a cluster
  // node's lease) still holds. From the rename on, the new version is the model's.
  if (cancel != nullptr) {
    cancel->throwIfCancelled();
  }
  {
    const std::optional<HierarchyStamp> onDisk = hierarchyStamp(live_.dir_);
    std::lock_guard lock(live_.writer_->mutex);
    live_.checkCurrent(onDisk);
  }
  if (options.token) {
    checkToken(patches / "patchhierarchy.xml", *options.token);
  }
  if (options.fence) {
    options.fence();
  }
  index.index->commit();
  hierarchy->commit();
  published_ = true;
  store.publish(model_, snapshot->published->change);
  const std::optional<HierarchyStamp> stamp = hierarchyStamp(live_.dir_);
  {
    std::lock_guard lock(live_.mutex_);
    live_.snapshot_ = snapshot;
    live_.revisionSnapshots_[version] = snapshot;
    live_.readStamp_ = stamp;
  }

  // 4. Durable before announced: a failure is reported, never undone (the next open retries it),
  // and the version is not announced (the caller reads the model again).
  try {
    finishHierarchy(live_.dir_);
  } catch (const Error& e) {
    throw Error(ErrorCode::Io, "version " + std::to_string(version) + " of model '" + live_.name_ +
                                   "' is published, but " + e.what() +
                                   " (retried at the next open)");
  }

  // 5. Announced: what others derived from the replaced versions may go (LiveModel::onPublish),
  // and listeners hear of the new version. Observers cannot fail the publish.
  std::function<void(const LiveModel::ReplacedVersions&)> observer;
  LiveModel::NewVersionObserver announce;
  {
    std::lock_guard lock(live_.mutex_);
    observer = live_.onPublish_;
    announce = live_.onNewVersion_;
  }
  if (observer) {
    LiveModel::ReplacedVersions replaced;
    for (const PatchKey& key : changed_) {
      if (const PatchInfo* old = base_->model->find(key)) {
        replaced.emplace_back(key, old->version);
      }
    }
    for (const PatchKey& key : removed_) {
      replaced.emplace_back(key, base_->model->at(key).version);
    }
    tellObserver(live_.name_, "dropping derived data", [&] { observer(replaced); });
  }
  if (announce) {
    tellObserver(live_.name_, "the announcement", [&] { announce(version, changed_, removed_); });
  }
  // 6. Revisions beyond the count go, oldest first.
  std::set<std::uint64_t> readElsewhere;
  if (options.readElsewhere) {
    tellObserver(live_.name_, "asking which revisions others read",
                 [&] { readElsewhere = options.readElsewhere(); });
  }
  live_.dropRevisions(*snapshot, options.keepRevisions, options.keepSeconds, readElsewhere,
                      std::move(replacedHidden));
  if (!options.deferFolderRemoval) {
    live_.removeRetiredFolders();
  }
}

}  // namespace vsm::core
