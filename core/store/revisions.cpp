#include <unistd.h>

#include <algorithm>
#include <cerrno>
#include <chrono>
#include <cstring>
#include <ctime>
#include <functional>
#include <future>
#include <optional>
#include <set>
#include <string_view>
#include <utility>
#include <vector>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
#include "core/opc/opc_index.hpp"
#include "core/opc/opc_reader.hpp"
#include "core/store/live_model.hpp"
#include "core/store/model_store.hpp"
#include "core/store/store_files.hpp"

// The kept revisions of a model: reading them, listing them, and dropping the oldest after a
// publish without taking a folder from under a reader of any opening of the process.

namespace fs = std::filesystem;

namespace vsm::core {

using namespace store;

namespace {

/// Runs a function when the last owner lets go; a failure is logged.
class RunOnRelease {
 public:
  explicit RunOnRelease(std::function<void()> run) : run_(std::move(run)) {}
  ~RunOnRelease() {
    try {
      run_();
    } catch (const std::exception& e) {
      log::warn(std::string("releasing a model version: ") + e.what());
    }
  }
  RunOnRelease(const RunOnRelease&) = delete;
  RunOnRelease& operator=(const RunOnRelease&) = delete;

 private:
  std::function<void()> run_;
};

}  // namespace

std::string revisionFileName(std::uint64_t number) {
  return "vsm-revision-" + std::to_string(number) + ".xml";
}

std::shared_ptr<const ModelSnapshot> LiveModel::heldSnapshot(std::uint64_t revision) const {
  std::lock_guard lock(mutex_);
  if (snapshot_->version == revision) {
    return snapshot_;
  }
  if (const auto it = revisionSnapshots_.find(revision); it != revisionSnapshots_.end()) {
    return it->second.lock();
  }
  return nullptr;
}

namespace {

/// Makes `snapshot` the most recently asked for of `recent` (adding it when missing), dropping the
/// least recently asked for beyond `bound` into `released` (to be let go after the lock: the last
/// holder of a dropped revision runs its folder removal).
void remember(std::deque<std::shared_ptr<ModelSnapshot>>& recent,
              const std::shared_ptr<ModelSnapshot>& snapshot, std::size_t bound,
              std::vector<std::shared_ptr<ModelSnapshot>>& released) {
  if (const auto it = std::find(recent.begin(), recent.end(), snapshot); it != recent.end()) {
    recent.erase(it);
  }
  recent.push_back(snapshot);
  while (recent.size() > bound) {
    released.push_back(std::move(recent.front()));
    recent.pop_front();
  }
}

}  // namespace

std::shared_ptr<const ModelSnapshot> LiveModel::snapshotAt(std::uint64_t revision) {
  // Let go after the lock (declared before it): a dropped snapshot may run a removal.
  std::vector<std::shared_ptr<ModelSnapshot>> released;
  std::promise<std::shared_ptr<ModelSnapshot>> promise;
  std::shared_future<std::shared_ptr<ModelSnapshot>> reading;
  {
    std::lock_guard lock(mutex_);
    if (snapshot_->version == revision) {
      return snapshot_;
    }
    if (const auto it = revisionSnapshots_.find(revision); it != revisionSnapshots_.end()) {
      if (std::shared_ptr<ModelSnapshot> held = it->second.lock()) {
        remember(recentRevisions_, held, kCachedRevisions, released);
        return held;
      }
    }
    if (const auto it = revisionReads_.find(revision); it != revisionReads_.end()) {
      reading = it->second;
      ++readStats_.sharedReads;
      ++readStats_.waiting;
    } else {
      revisionReads_.emplace(revision, promise.get_future().share());
      ++readStats_.reads;
      ++readStats_.reading;
    }
  }
  if (reading.valid()) {
    // Another caller reads it: wait for that read (no lock held), sharing its result or error.
    const auto done = [this] {
      std::lock_guard lock(mutex_);
      --readStats_.waiting;
    };
    try {
      std::shared_ptr<ModelSnapshot> read = reading.get();
      done();
      return read;
    } catch (...) {
      done();
      throw;
    }
  }
  std::shared_ptr<ModelSnapshot> read;
  try {
    read = readRevision(revision);
  } catch (...) {
    // Not kept: the next caller reads again.
    promise.set_exception(std::current_exception());
    std::lock_guard lock(mutex_);
    revisionReads_.erase(revision);
    --readStats_.reading;
    throw;
  }
  promise.set_value(read);
  std::lock_guard lock(mutex_);
  revisionReads_.erase(revision);
  --readStats_.reading;
  return read;
}

std::shared_ptr<ModelSnapshot> LiveModel::readRevision(std::uint64_t revision) {
  const auto start = std::chrono::steady_clock::now();
  std::shared_ptr<const ModelSnapshot> current = snapshot();
  const fs::path file = patchesDirOf(dir_) / revisionFileName(revision);
  if (revision > current->version || !fs::is_regular_file(file)) {
    throw Error(ErrorCode::NotFound, "model '" + name_ + "' keeps no revision " +
                                         std::to_string(revision) + " (GET its revisions)");
  }
  std::shared_ptr<ModelSnapshot> read =
      snapshotOf(readOpcRevision(dir_, file.filename().string(), revisionBases_.get()), file);
  if (read->version != revision || read->model->gridSize() != current->model->gridSize()) {
    throw Error(ErrorCode::Corrupt, file.string() + " does not hold revision " +
                                        std::to_string(revision) + " of this model");
  }
  store_->addRevision(*read->model);
  std::vector<std::shared_ptr<ModelSnapshot>> released;  // let go after the lock
  {
    std::lock_guard lock(mutex_);
    revisionSnapshots_[revision] = read;
    remember(recentRevisions_, read, kCachedRevisions, released);
  }
  // A publish that dropped the revision meanwhile removed its file before looking for snapshots
  // of it to hand its folders to: either it found this one, or the file is gone now.
  if (!fs::exists(file)) {
    std::lock_guard lock(mutex_);
    std::erase(recentRevisions_, read);
    throw Error(ErrorCode::NotFound,
                "model '" + name_ + "' no longer keeps revision " + std::to_string(revision));
  }
  log::info("model=" + name_ + " read revision " + std::to_string(revision) + " (" +
            std::to_string(read->model->patchCount()) + " patches, " +
            std::to_string(std::chrono::duration_cast<std::chrono::milliseconds>(
                               std::chrono::steady_clock::now() - start)
                               .count()) +
            " ms)");
  return read;
}

LiveModel::RevisionReadStats LiveModel::revisionReadStats() const {
  std::lock_guard lock(mutex_);
  RevisionReadStats stats = readStats_;
  stats.cached = recentRevisions_.size();
  return stats;
}

std::vector<RevisionSummary> LiveModel::revisions() const {
  const std::shared_ptr<const ModelSnapshot> current = snapshot();
  std::vector<RevisionSummary> list;
  for (const auto& [number, file] : revisionFiles(patchesDirOf(dir_))) {
    if (number >= current->version) {
      continue;
    }
    {
      std::lock_guard lock(mutex_);
      if (const auto it = revisionSnapshots_.find(number); it != revisionSnapshots_.end()) {
        if (const auto held = it->second.lock()) {
          list.push_back({number, held->revision, false});
          continue;
        }
      }
    }
    // The record alone: the hierarchy file without the patches' metadata.
    RevisionRecord record = readRevisionRecord(file).value_or(RevisionRecord{});
    if (record.time.empty()) {
      record.time = fileTime(file);
    }
    list.push_back({number, std::move(record), false});
  }
  list.push_back({current->version, current->revision, true});
  return list;
}

namespace {

/// The folders of `retired` (those a revision no longer names that its parent did) that `latest`
/// does not name either: the parent's own folders. (No later revision names them, as a restore
/// copies; checked against the latest all the same, by key, at no cost.)
FolderSet foldersRetiredBy(const std::vector<RetiredFolder>& retired, const Model& latest) {
  FolderSet only;
  for (const RetiredFolder& entry : retired) {
    const PatchInfo* now = latest.find(entry.key);
    if (now == nullptr || now->folder() != entry.folder) {
      only.insert(entry.folder);
    }
  }
  return only;
}

/// The folders the hierarchy file `oldest` names that neither `next` (a later kept revision's
/// hierarchy file; empty: none) nor `latest` names, read from the files (their indexes when
/// current): what foldersRetiredBy gives without a record of the change, at the cost of reading
/// both revisions' trees.
FolderSet foldersOnlyIn(const fs::path& oldest, const fs::path& next, const Model& latest) {
  // Folders are never shared across a gap (a restore copies): what the oldest and the current
  // model both name, every revision between names, and what the next kept revision does not
  // name, no later one does. So the oldest's own folders are those neither names.
  FolderSet only;
  {
    const NamedFolders latestFolders(latest);
    forEachNamedFolder(oldest, [&](std::string_view folder) {
      if (!latestFolders.contains(folder)) {
        only.emplace(folder);
      }
    });
  }
  if (!next.empty() && !only.empty()) {
    forEachNamedFolder(next, [&](std::string_view folder) {
      if (const auto it = only.find(folder); it != only.end()) {
        only.erase(it);
      }
    });
  }
  return only;
}

/// True when the current index of `patches` or one of the kept revisions' (`kept`) builds on
/// `base`.
bool baseNamedBy(const fs::path& patches, const IndexBase& base,
                 const std::map<std::uint64_t, fs::path>& kept) {
  std::vector<fs::path> indexes{patches / indexFileName("patchhierarchy.xml")};
  for (const auto& [number, file] : kept) {
    indexes.push_back(patches / indexFileName(file.filename().string()));
  }
  return std::any_of(indexes.begin(), indexes.end(), [&](const fs::path& index) {
    const std::optional<IndexBase> named = readIndexBase(index);
    return named && named->name == base.name;
  });
}

}  // namespace

void LiveModel::dropRevisions(const ModelSnapshot& current, unsigned keep,
                              std::chrono::seconds keepSeconds,
                              const std::set<std::uint64_t>& readElsewhere,
                              std::set<std::string> hiddenFiles) {
  const Model& latest = *current.model;
  const std::time_t now = std::time(nullptr);
  const fs::path patches = patchesDirOf(dir_);
  // The kept revision files as the last publish left them, with the base revision this one kept;
  // listed from Patches/ the first time (and after a failure).
  std::optional<std::map<std::uint64_t, fs::path>> listed;
  {
    std::lock_guard lock(writer_->mutex);
    listed.swap(writer_->revisionFiles);
  }
  try {
    std::map<std::uint64_t, fs::path> files;
    if (listed) {
      files = std::move(*listed);
      const std::uint64_t base = current.revision.parent;
      if (base != 0 && fs::is_regular_file(patches / revisionFileName(base))) {
        files.emplace(base, patches / revisionFileName(base));
      }
    } else {
      files = revisionFiles(patches);
    }
    std::erase_if(files, [&](const auto& entry) { return entry.first >= current.version; });
    while (files.size() + 1 > keep) {
      const auto oldest = files.begin();
      const std::uint64_t number = oldest->first;
      const auto nextFile = std::next(oldest);
      if (readElsewhere.contains(number)) {
        log::info("model=" + name_ + " keeps revision " + std::to_string(number) +
                  " beyond the count: another process reads it");
        break;
      }
      // The next revision's record and the folders it retired from its parent, from its index's
      // head (a few kB): when its parent is the oldest, those are the oldest's own folders.
      const std::optional<IndexedRevision> next =
          nextFile != files.end() ? readIndexedRevision(nextFile->second) : std::nullopt;
      // The time floor: readers elsewhere may still read this revision for that long after the
      // next one replaced it.
      if (keepSeconds.count() > 0) {
        std::string replaced = current.revision.time;
        if (nextFile != files.end()) {
          replaced = next && next->record
                         ? next->record->time
                         : readRevisionRecord(nextFile->second).value_or(RevisionRecord{}).time;
        }
        const std::optional<std::time_t> when = parseUtcTime(replaced);
        if (!when || now - *when < keepSeconds.count()) {
          break;  // (an unreadable time keeps it: dropping is the irreversible side)
        }
      }
      const FolderSet only =
          next && next->record && next->record->parent == number && next->retired
              ? foldersRetiredBy(*next->retired, latest)
              : foldersOnlyIn(oldest->second,
                              nextFile != files.end() ? nextFile->second : fs::path(), latest);
      // Its second hierarchy file goes with it, below, unless another hierarchy names it.
      if (std::optional<std::string> hidden = hiddenHierarchyNamedBy(oldest->second)) {
        hiddenFiles.insert(std::move(*hidden));
      }
      // The file first: a crash after it leaves folders no kept revision names, which the next
      // open removes; never a listed revision without its folders.
      if (::unlink(oldest->second.c_str()) != 0 && errno != ENOENT) {
        throw Error(ErrorCode::Io,
                    "cannot remove " + oldest->second.string() + ": " + std::strerror(errno));
      }
      // Its index after it: one left by a crash between the two is an orphan the next open
      // removes (never an index taken for a hierarchy it does not describe: it has a stamp).
      const fs::path index = patches / indexFileName(oldest->second.filename().string());
      const std::optional<IndexBase> base = readIndexBase(index);
      ::unlink(index.c_str());
      files.erase(oldest);
      // Then the base it built on, when no index left names it (the current one and the kept
      // revisions': a few heads read). A crash before leaves it to the next open.
      if (base && !baseNamedBy(patches, *base, files)) {
        ::unlink((patches / base->name).c_str());
      }
      durable::syncDirectory(patches);
      log::info("model=" + name_ + " dropped revision " + std::to_string(number) + " (" +
                std::to_string(only.size()) + " folders only it used)");
      // Letting go queues the folders; removeRetiredFolders() removes them (after the publish,
      // or the caller's housekeeping later).
      auto removal = std::make_shared<const RunOnRelease>(
          [writer = std::weak_ptr<Writer>(writer_), store = std::weak_ptr<Store>(store_), only] {
            if (const std::shared_ptr<Writer> alive = writer.lock()) {
              const std::lock_guard retiredLock(alive->retiredMutex);
              alive->retired.emplace_back(store, only);
            }
          });
      // Every opening sharing the writer hands it to the snapshots of the revision its readers
      // hold; `removal` runs when the last of them lets go, or here, as its last owner goes.
      std::lock_guard writerLock(writer_->mutex);
      for (LiveModel* opening : writer_->openings) {
        opening->holdRemoval(number, removal);
      }
    }
    if (!hiddenFiles.empty()) {
      std::vector<fs::path> kept{patches / "patchhierarchy.xml"};
      for (const auto& [number, file] : files) {
        kept.push_back(file);
      }
      removeUnnamedHiddenFiles(patches, hiddenFiles, kept);
    }
    std::lock_guard lock(writer_->mutex);
    writer_->revisionFiles = std::move(files);
  } catch (const std::exception& e) {
    // The list is listed again next time (it stays forgotten).
    log::warn("model=" + name_ + " dropping old revisions: " + e.what() +
              " (retried at the next publish)");
  }
}

std::size_t LiveModel::removeRetiredFolders() {
  if (!writer_) {
    return 0;
  }
  std::vector<std::pair<std::weak_ptr<Store>, FolderSet>> retired;
  {
    const std::lock_guard lock(writer_->retiredMutex);
    retired.swap(writer_->retired);
  }
  std::size_t removed = 0;
  for (const auto& [weakStore, folders] : retired) {
    if (const std::shared_ptr<Store> store = weakStore.lock()) {
      store->forgetFolders(folders);
    }
    removeFolders(dir_, folders);
    removed += folders.size();
  }
  return removed;
}

void LiveModel::holdRemoval(std::uint64_t revision, const std::shared_ptr<const void>& removal) {
  // Released after the lock: a snapshot let go here may run an earlier removal.
  std::vector<std::shared_ptr<ModelSnapshot>> released;
  std::lock_guard lock(mutex_);
  for (auto it = recentRevisions_.begin(); it != recentRevisions_.end();) {
    if ((*it)->version == revision) {
      released.push_back(std::move(*it));
      it = recentRevisions_.erase(it);
    } else {
      ++it;
    }
  }
  if (const auto it = revisionSnapshots_.find(revision); it != revisionSnapshots_.end()) {
    if (std::shared_ptr<ModelSnapshot> held = it->second.lock()) {
      held->heldRemovals.push_back(removal);
      released.push_back(std::move(held));
    }
    revisionSnapshots_.erase(it);
  }
  std::erase_if(revisionSnapshots_, [](const auto& entry) { return entry.second.expired(); });
}

}  // namespace vsm::core
