#include <unistd.h>

#include <cerrno>
#include <cstring>
#include <ctime>
#include <functional>
#include <optional>
#include <utility>

#include "core/common/error.hpp"
#include "core/common/log.hpp"
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

std::shared_ptr<const ModelSnapshot> LiveModel::snapshotAt(std::uint64_t revision) {
  if (auto held = heldSnapshot(revision)) {
    return held;
  }
  std::shared_ptr<const ModelSnapshot> current = snapshot();
  const fs::path file = patchesDirOf(dir_) / revisionFileName(revision);
  if (revision > current->version || !fs::is_regular_file(file)) {
    throw Error(ErrorCode::NotFound, "model '" + name_ + "' keeps no revision " +
                                         std::to_string(revision) + " (GET its revisions)");
  }
  std::shared_ptr<ModelSnapshot> read =
      snapshotOf(readOpcRevision(dir_, file.filename().string()), file);
  if (read->version != revision || read->model->gridSize() != current->model->gridSize()) {
    throw Error(ErrorCode::Corrupt, file.string() + " does not hold revision " +
                                        std::to_string(revision) + " of this model");
  }
  for (const auto& [key, info] : read->model->patches()) {
    store_->add(info);
  }
  {
    std::lock_guard lock(mutex_);
    revisionSnapshots_[revision] = read;
    recentRevisions_.push_back(read);
    if (recentRevisions_.size() > 2) {
      recentRevisions_.pop_front();
    }
  }
  // A publish that dropped the revision meanwhile removed its file before looking for snapshots
  // of it to hand its folders to: either it found this one, or the file is gone now.
  if (!fs::exists(file)) {
    std::lock_guard lock(mutex_);
    std::erase(recentRevisions_, read);
    throw Error(ErrorCode::NotFound,
                "model '" + name_ + "' no longer keeps revision " + std::to_string(revision));
  }
  return read;
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

void LiveModel::dropRevisions(const ModelSnapshot& current, unsigned keep,
                              std::chrono::seconds keepSeconds) {
  const Model& latest = *current.model;
  const std::time_t now = std::time(nullptr);
  try {
    const fs::path patches = patchesDirOf(dir_);
    std::map<std::uint64_t, fs::path> files = revisionFiles(patches);
    std::erase_if(files, [&](const auto& entry) { return entry.first >= current.version; });
    while (files.size() + 1 > keep) {
      const auto oldest = files.begin();
      const std::uint64_t number = oldest->first;
      std::set<std::string> only = namedFolders(oldest->second);
      // Folders are never shared across a gap (a restore copies), so what the next kept revision
      // does not name, no later one does.
      const auto nextFile = std::next(oldest);
      // The time floor: readers elsewhere may still read this revision for that long after the
      // next one replaced it.
      if (keepSeconds.count() > 0) {
        const std::string replaced =
            nextFile != files.end()
                ? readRevisionRecord(nextFile->second).value_or(RevisionRecord{}).time
                : current.revision.time;
        const std::optional<std::time_t> when = parseUtcTime(replaced);
        if (!when || now - *when < keepSeconds.count()) {
          break;  // (an unreadable time keeps it: dropping is the irreversible side)
        }
      }
      if (nextFile != files.end()) {
        for (const std::string& folder : namedFolders(nextFile->second)) {
          only.erase(folder);
        }
      } else {
        for (const auto& [key, info] : latest.patches()) {
          only.erase(info.folder);
        }
      }
      // The file first: a crash after it leaves folders no kept revision names, which the next
      // open removes; never a listed revision without its folders.
      if (::unlink(oldest->second.c_str()) != 0 && errno != ENOENT) {
        throw Error(ErrorCode::Io,
                    "cannot remove " + oldest->second.string() + ": " + std::strerror(errno));
      }
      durable::syncDirectory(patches);
      files.erase(oldest);
      log::info("model=" + name_ + " dropped revision " + std::to_string(number) + " (" +
                std::to_string(only.size()) + " folders only it used)");
      std::shared_ptr<Store> keepStore = store_;
      const fs::path dir = dir_;
      auto removal = std::make_shared<const RunOnRelease>([keepStore, dir, only] {
        keepStore->forgetFolders(only);
        removeFolders(dir, only);
      });
      // Every opening sharing the writer hands it to the snapshots of the revision its readers
      // hold; `removal` runs when the last of them lets go, or here, as its last owner goes.
      std::lock_guard writerLock(writer_->mutex);
      for (LiveModel* opening : writer_->openings) {
        opening->holdRemoval(number, removal);
      }
    }
  } catch (const std::exception& e) {
    log::warn("model=" + name_ + " dropping old revisions: " + e.what() +
              " (retried at the next publish)");
  }
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
